"""Stage ``train``: a scene folder -> a run folder of the chosen method (``uncertsplat train``).

The one entry point of training for the command line and pipelines. ``run`` dispatches on
``cfg.method`` (``baselines.train_run``): one model (``train.session.train_model``, which lists what a
run folder holds), an ensemble of them (``baselines.ensemble``) or one model plus its Fisher posterior
(``baselines.fisher``). ``resolve_config`` turns the command's options into the ``TrainConfig``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from uncertsplat.config import TrainConfig
from uncertsplat.console import q


def resolve_config(preset: str | None, data: dict[str, Any], method: str | None, explicit: dict[str, Any],
                   overrides: list[str] | None, source: str | None = None) -> TrainConfig:
    """The ``TrainConfig`` of: preset < ``data`` (a config file, ``source``) < ``method``'s keys < explicit options <
    ``--set``. An error in the config file names it.

    Raises:
        UserError: an unknown method, preset or key, or a value out of range.
    """
    from uncertsplat.baselines import method_overrides
    from uncertsplat.config import KeyLines, deep_update, train_config_from
    from uncertsplat.errors import UserError

    merged = deep_update(data, method_overrides(method)) if method is not None else data
    try:
        cfg = train_config_from(preset, deep_update(merged, {k: v for k, v in explicit.items() if v is not None}),
                                overrides)
    except UserError:
        if data and source is not None:
            # the file alone: an error of its own names the file and the line
            train_config_from(preset, data, source=source, where=KeyLines(source))
        raise
    over = method_overrides(method) if method is not None else {}

    def taken_back(want: dict, have: dict, prefix: str = "") -> list[str]:
        """The keys --method set (nested) whose value in the config is another."""
        out = []
        for k, v in want.items():
            if isinstance(v, dict):
                out += taken_back(v, have.get(k, {}), f"{prefix}{k}.")
            elif have.get(k, v) != v:
                out.append(f"{prefix}{k} = {have.get(k)!r}")
        return out

    back = taken_back(over, cfg.model_dump(mode="json"))
    if back:
        # --method sets keys (paper: variant = "paper"; vi-single: the SGD posterior of one entry) that a later option
        # or --set took back (only method and variant were looked at: vi-single with another num_entries said nothing)
        from uncertsplat.console import console

        console.print(f"[yellow]note:[/] --method {method} was overridden by other options ({', '.join(back)}): this "
                      f"run trains method {cfg.method}, variant {cfg.variant}, posterior {cfg.posterior}")
    if cfg.variant == "paper" and not cfg.has_offset_tables:
        from uncertsplat.console import console

        console.print(f"[yellow]note:[/] the paper variant shapes the offset tables of the variational model; the "
                      f"{cfg.method} baseline has none, so it changes nothing here")
    return cfg


def given_keys(preset: str | None, data: dict[str, Any], method: str | None, explicit: dict[str, Any],
               overrides: list[str] | None) -> set[str]:
    """The dotted config keys a ``train`` command set itself (preset, config file, method, options, ``--set``): on
    ``--resume`` only those are worth naming where they differ from the run's stored configuration."""
    from uncertsplat.baselines import method_overrides
    from uncertsplat.config import TRAIN_PRESETS, parse_override

    def dotted(d: dict, prefix: str = "") -> set[str]:
        out: set[str] = set()
        for k, v in d.items():
            out |= dotted(v, f"{prefix}{k}.") if isinstance(v, dict) and v else {f"{prefix}{k}"}
        return out

    keys = dotted(TRAIN_PRESETS.get(preset, {})) if preset else set()
    keys |= dotted(data) | (dotted(method_overrides(method)) if method else set())
    keys |= {k for k, v in explicit.items() if v is not None}
    for o in overrides or []:
        keys |= dotted(parse_override(o))
    return keys


def run(scene: Path, run_dir: Path, cfg: TrainConfig, device: torch.device, resume: bool = False,
        extend_to: int | None = None, view=None, add_views: list[str] | None = None,
        given: set[str] | None = None) -> Path:
    """Train ``cfg.method`` on ``scene`` into ``run_dir``; returns ``run_dir``.

    ``extend_to`` (with ``resume``): train a single-model run on to this many steps instead of the stored
    ``iterations``. ``given``: the keys the command set (``given_keys``; None: all), named on ``resume`` where they
    differ from the stored configuration. ``view``: a ``ViewConfig`` to watch the training in the browser (``view.live``; the
    viewer closes when training ends). ``add_views`` (with ``resume``): image names to add to the training views
    (``train --add-views``).

    Raises:
        UserError: unreadable scene, an existing run folder without ``resume``, nothing to resume, an
            interruption (a checkpoint was written and ``--resume`` continues), or ``extend_to`` for a
            baseline that does not support it.
    """
    from uncertsplat.baselines import train_run

    if view is None:
        return train_run(Path(scene), Path(run_dir), cfg, device=torch.device(device), resume=resume,
                         extend_to=extend_to, add_views=add_views, given=given)
    from uncertsplat.view.live import LiveView
    from uncertsplat.view.server import require_viser

    require_viser()  # before training starts, not after the scene is loaded
    live = LiveView(view)
    try:
        return train_run(Path(scene), Path(run_dir), cfg, device=torch.device(device), resume=resume,
                         extend_to=extend_to, on_trainer=live.attach, add_views=add_views, given=given)
    finally:
        if live.viewer is not None:
            from uncertsplat.console import console

            console.print(f"the viewer drew {live.frames} frames ({live.share:.1%} of the training time); it closes "
                          f"now: `uncertsplat view {q(run_dir)}` shows the trained model")
        live.close()
