"""A trained tiny run, shared by the end-to-end tests of later stages (evaluate, prune, report).

Use it with::

    from tests.fixtures import tiny_scene_path  # noqa: F401
    from tests.run_fixtures import tiny_run_path  # noqa: F401

The run is trained once per test session on the tiny synthetic scene with a short schedule that spawns
posteriors early, so it has posterior carriers. Treat it as read-only (copy it before changing it).
"""

from __future__ import annotations

from pathlib import Path

import pytest

TINY_RUN_OVERRIDES = {
    "iterations": 120,
    "eval_every": 1000,
    "checkpoint_every": 1000,
    "densify": {"start": 20, "until": 100, "interval": 20, "spawn_interval": 40},
}


def train_tiny_run(scene: Path, out: Path, **overrides) -> Path:
    """Train the tiny preset on ``scene`` into ``out`` on the CPU with the short schedule above."""
    import torch

    from uncertsplat.config import deep_update, train_config_from
    from uncertsplat.stages import train

    cfg = train_config_from("tiny", deep_update(TINY_RUN_OVERRIDES, overrides))
    train.run(scene, out, cfg, device=torch.device("cpu"))
    return out


@pytest.fixture(scope="session")
def tiny_run_path(tmp_path_factory, tiny_scene_path) -> Path:
    """Path of a run trained on the tiny synthetic scene (has posterior carriers)."""
    return train_tiny_run(tiny_scene_path, tmp_path_factory.mktemp("runs") / "tiny_run")


def resume_without_key(scene: Path, run: Path, tmp: Path, section: str, key: str, steps: int) -> dict:
    """Copy ``run`` to ``tmp / "old"``, delete ``section.key`` from its config.json (as a run written before the key
    existed), resume it for ``steps`` more steps with the tiny preset, and return the config.json it then has."""
    import json
    import shutil

    import torch

    from uncertsplat.config import train_config_from
    from uncertsplat.train.session import train_model

    old = tmp / "old"
    shutil.copytree(run, old, ignore=shutil.ignore_patterns("eval"))
    cfg_path = old / "config.json"
    data = json.loads(cfg_path.read_text(encoding="utf-8"))
    data[section].pop(key)
    cfg_path.write_text(json.dumps(data))
    step = json.loads((old / "train_summary.json").read_text(encoding="utf-8"))["steps"]
    train_model(scene, old, train_config_from("tiny", {}), torch.device("cpu"), resume=True, extend_to=step + steps)
    return json.loads(cfg_path.read_text(encoding="utf-8"))
