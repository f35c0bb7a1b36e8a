"""Baselines in the same harness: every method trains into a run folder that ``evaluate`` and ``report`` read.

Methods (``METHODS``; ``uncertsplat train --method NAME``):

* ``variational`` (ours, default) and ``paper`` (``variational`` with ``variant = "paper"``);
* ``vi-single``: the variational model with one offset-table entry (K_table = 1) learned by SGD, the paper's
  "naive VI" (the informed posterior holds one value per carrier whatever K, so K matters only to SGD tables);
* ``deterministic``: plain 3DGS, no uncertainty (every sample is the same render, std 0);
* ``ensemble``: N independently seeded deterministic models (``baselines.ensemble``), spread over members;
* ``fisher``: a post-hoc Laplace/Fisher posterior on a deterministic model (``baselines.fisher``).

``train_run`` trains any of them (``stages.train.run`` is the command's entry point to it);
``load_run`` (``baselines.runs``) loads any run folder, the only place a run is read, into a
``LoadedRun`` whose ``sampler`` gives the Monte-Carlo sampler the evaluation engine draws its K samples
from (a baseline's own for ensemble and Fisher runs).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from uncertsplat.baselines.runs import LoadedRun, load_run, load_single_model, read_run_config
from uncertsplat.config import method_label

METHODS: dict[str, dict[str, Any]] = {
    "variational": {"method": "variational", "variant": "ours"},
    "paper": {"method": "variational", "variant": "paper"},
    "vi-single": {"method": "variational", "variational": {"num_entries": 1, "posterior": "sgd"}},
    "deterministic": {"method": "deterministic"},
    "ensemble": {"method": "ensemble"},
    "fisher": {"method": "fisher"},
}
"""Method name -> the TrainConfig keys it sets (applied over a preset, under explicit ``--set`` overrides)."""


def method_overrides(name: str) -> dict[str, Any]:
    """The TrainConfig keys of method ``name`` (a copy); raises ``UserError`` for an unknown name."""
    import copy

    from uncertsplat.errors import UserError

    if name not in METHODS:
        raise UserError(f"unknown method '{name}'", hint=f"Choose one of: {', '.join(METHODS)}.")
    return copy.deepcopy(METHODS[name])


def train_run(scene: Path, run_dir: Path, cfg, device: torch.device, resume: bool = False,
              extend_to: int | None = None, on_trainer=None, add_views: list[str] | None = None,
              given: set[str] | None = None) -> Path:
    """Train ``cfg.method`` on ``scene`` into ``run_dir``: the dispatch on the method, for the ``train`` stage
    and the sweep.

    ``extend_to`` (with ``resume``): continue a single-model run to that many steps. ``on_trainer(trainer)``:
    called with each ``Trainer`` before it trains (an ensemble has one per member), e.g. to watch it.
    ``add_views`` (with ``resume``): training views to add to a single-model run (``train --add-views``).
    ``given``: the keys the command set (``stages.train.given_keys``), for ``train_model``'s note on resume.
    """
    from uncertsplat.errors import UserError

    stored = _stored_method(run_dir) if resume else None
    if stored in ("ensemble", "fisher") and stored != cfg.method:
        # an ensemble or Fisher run resumed without its --method: the run folder decides, as it does the method of
        # a single-model run (training one model into the ensemble's folder lost the ensemble)
        from uncertsplat.console import console

        console.print(f"[yellow]note:[/] the run folder holds a{'n' if stored == 'ensemble' else ''} {stored} run: "
                      f"resuming it as one (its stored configuration)")
        cfg = read_run_config(run_dir)
    if add_views and cfg.method in ("ensemble", "fisher"):
        raise UserError(f"--add-views is not supported for the {cfg.method} baseline",
                        hint="Grow a variational or deterministic run, or start a new run with the views you want.")
    if extend_to is not None and resume and (run_dir / "config.json").is_file() \
            and extend_to == read_run_config(run_dir).iterations:
        extend_to = None  # the run's own length (e.g. `--set iterations=N` repeating the first command): nothing to extend
    if extend_to is not None and cfg.method in ("ensemble", "fisher"):
        raise UserError(f"--iterations with --resume is not supported for the {cfg.method} baseline",
                        hint="Start a new run with the number of iterations you want.")
    if cfg.method == "ensemble":
        from uncertsplat.baselines.ensemble import train_ensemble

        return train_ensemble(scene, run_dir, cfg, device, resume=resume, on_trainer=on_trainer)
    if cfg.method == "fisher":
        from uncertsplat.baselines.fisher import train_fisher

        return train_fisher(scene, run_dir, cfg, device, resume=resume, on_trainer=on_trainer)
    from uncertsplat.train.session import train_model

    return train_model(scene, run_dir, cfg, device=device, resume=resume, extend_to=extend_to, on_trainer=on_trainer,
                       add_views=add_views, given=given)


def _stored_method(run_dir: Path) -> str | None:
    """The method in ``RUN/config.json``, or None when there is none to read (a new run; errors come later)."""
    import json

    try:
        method = json.loads((Path(run_dir) / "config.json").read_text(encoding="utf-8")).get("method")
    except (OSError, ValueError, AttributeError):
        return None
    return method if isinstance(method, str) else None


__all__ = ["METHODS", "LoadedRun", "load_run", "load_single_model", "method_label", "method_overrides", "train_run"]
