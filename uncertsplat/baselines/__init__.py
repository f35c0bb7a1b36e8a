"""Baselines in the same harness: every method trains into a run folder that ``evaluate`` and ``report`` read.

Methods (``METHODS``; ``uncertsplat train --method NAME``):

* ``variational`` (ours, default) and ``paper`` (``variational`` with ``variant = "paper"``);
* ``vi-single``: the variational model with one offset-table entry (K_table = 1), the paper's "naive VI";
* ``deterministic``: plain 3DGS, no uncertainty (every sample is the same render, std 0);
* ``ensemble``: N independently seeded deterministic models (``baselines.ensemble``), spread over members;
* ``fisher``: a post-hoc Laplace/Fisher posterior on a deterministic model (``baselines.fisher``).

``train_run`` trains any of them; ``load_run`` loads any run folder; ``make_sample_fn`` gives the
Monte-Carlo sampler ``evaluate`` draws its K samples from (None means "the model's own posterior").
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

METHODS: dict[str, dict[str, Any]] = {
    "variational": {"method": "variational", "variant": "ours"},
    "paper": {"method": "variational", "variant": "paper"},
    "vi-single": {"method": "variational", "variational": {"num_entries": 1}},
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


def method_label(cfg) -> str:
    """A short name for a resolved TrainConfig (``vi-single``, ``ensemble-10``, ``paper``, ...)."""
    if cfg.method == "ensemble":
        return f"ensemble-{cfg.ensemble_size}"
    if cfg.method in ("fisher", "deterministic"):
        return cfg.method
    if cfg.variational.num_entries == 1:
        return "vi-single" if cfg.variant == "ours" else "vi-single-paper"
    return "variational" if cfg.variant == "ours" else "paper"


def train_run(scene: Path, run_dir: Path, cfg, device: torch.device, resume: bool = False,
              extend_to: int | None = None) -> Path:
    """Train ``cfg.method`` on ``scene`` into ``run_dir`` (the entry point for every method).

    ``extend_to`` (with ``resume``): continue a single-model run to that many steps.
    """
    from uncertsplat.errors import UserError

    if extend_to is not None and cfg.method in ("ensemble", "fisher"):
        raise UserError(f"--iterations with --resume is not supported for the {cfg.method} baseline",
                        hint="Start a new run with the number of iterations you want.")
    if cfg.method == "ensemble":
        from uncertsplat.baselines.ensemble import train_ensemble

        return train_ensemble(scene, run_dir, cfg, device, resume=resume)
    if cfg.method == "fisher":
        from uncertsplat.baselines.fisher import train_fisher

        return train_fisher(scene, run_dir, cfg, device, resume=resume)
    from uncertsplat.stages import train

    return train.run(scene, run_dir, cfg, device=device, resume=resume, extend_to=extend_to)


def load_run(run_dir: Path, device: torch.device | str = "cpu"):
    """Load any run folder for rendering: an ``EnsembleRun``, a ``FisherRun`` or a plain ``LoadedRun``."""
    import json

    from uncertsplat.io.checkpoints import load_model

    run_dir = Path(run_dir)
    method = None
    cfg_path = run_dir / "config.json"
    if cfg_path.is_file():
        try:
            method = json.loads(cfg_path.read_text(encoding="utf-8")).get("method")
        except json.JSONDecodeError:
            method = None  # load_model reports the bad file
    if method == "ensemble":
        from uncertsplat.baselines.ensemble import load_ensemble

        return load_ensemble(run_dir, device)
    if method == "fisher":
        from uncertsplat.baselines.fisher import load_fisher

        return load_fisher(run_dir, device)
    return load_model(run_dir, device)


def make_sample_fn(loaded, device: torch.device):
    """The ``sample_fn(generator) -> GaussianSample`` of a baseline run, or None for the model's own posterior."""
    from uncertsplat.baselines.ensemble import EnsembleRun, ensemble_sample_fn
    from uncertsplat.baselines.fisher import FisherRun, fisher_sample_fn

    if isinstance(loaded, EnsembleRun):
        return ensemble_sample_fn(loaded.member_samples())
    if isinstance(loaded, FisherRun):
        return fisher_sample_fn(loaded)
    return None


def eval_notes(loaded, num_samples: int) -> list[str]:
    """Notes ``evaluate`` adds to the report for this kind of run (e.g. an ensemble of one member)."""
    from uncertsplat.baselines.ensemble import EnsembleRun

    notes: list[str] = []
    cfg = loaded.config
    if isinstance(loaded, EnsembleRun):
        n = len(loaded.members)
        if n == 1:
            notes.append("ensemble of 1 member: every sample is the same render, the spread (std) is 0 everywhere; "
                         "AUSE and NLL measure no uncertainty")
        elif num_samples % n:
            notes.append(f"K={num_samples} is not a multiple of the {n} ensemble members: members are weighted "
                         f"unequally (K = {n} uses each member once)")
    elif getattr(loaded, "variance", None) is not None:  # a FisherRun
        notes.append(f"fisher: Laplace posterior ({cfg.fisher.estimator} diagonal Fisher, observation noise std "
                     f"{loaded.noise_std:.4g}) sampled by perturbing {', '.join(sorted(loaded.variance))}")
    elif cfg.method == "deterministic":
        notes.append("deterministic model: every sample is the same render, the std is 0 everywhere")
    return notes


__all__ = ["METHODS", "method_overrides", "method_label", "train_run", "load_run", "make_sample_fn", "eval_notes"]
