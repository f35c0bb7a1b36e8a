"""The runs or scenes inside (or around) a folder a user gave where a run or a scene was expected, so that the error
can name the folder to give instead of only saying what the given one is not: a pipeline's output (``uncertsplat
run -o OUT``: OUT/reconstruct, OUT/train, OUT/prune, OUT/report), a sweep's (OUT/runs/POINT), a folder inside a run
(RUN/eval, an ensemble's members/) or a folder of runs trained by hand."""

from __future__ import annotations

import os
from pathlib import Path

RUN_FILES = ("stats.jsonl", "train_summary.json", "ckpts", "prune.json")
"""Beside ``config.json``, the files that make a folder a training run (or a pruned one)."""

PIPELINE_STARTED = ".stages_started.json"
"""The file ``uncertsplat run`` keeps in its output folder (``stages.pipeline.STARTED``): what marks one."""


def is_run(folder: Path) -> bool:
    """Whether ``folder`` is a training or pruned run (``config.json`` and one of ``RUN_FILES``); False where it
    cannot be read."""
    try:
        return (folder / "config.json").is_file() and any((folder / n).exists() for n in RUN_FILES)
    except OSError:
        return False


def holds_files(folder: Path) -> bool:
    """Whether ``folder`` is a folder that holds anything but a command's lock (``.lock``, which ``run_lock`` makes
    before the command writes)."""
    return folder.is_dir() and any(p.name != ".lock" for p in folder.iterdir())


def is_scene(folder: Path) -> bool:
    """Whether ``folder`` looks like a scene ``train`` reads: a COLMAP workspace (``sparse/``) with its images, or a
    Blender layout (``transforms*.json``); False where it cannot be read."""
    try:
        return ((folder / "sparse").is_dir() and (folder / "images").is_dir()) or any(
            (folder / n).is_file() for n in ("transforms.json", "transforms_train.json"))
    except OSError:
        return False


def _run_scene(run: Path) -> Path | None:
    """The scene folder ``run``'s ``scene.json`` names where it still is a scene, else None."""
    import json

    try:
        scene = json.loads((run / "scene.json").read_text(encoding="utf-8")).get("scene")
        return Path(scene) if isinstance(scene, str) and is_scene(Path(scene)) else None
    except (OSError, ValueError, AttributeError):
        return None


def _subfolders(folder: Path) -> list[Path]:
    try:
        return sorted(p for p in folder.iterdir() if not p.name.startswith(".") and p.is_dir())
    except OSError:  # (a folder that cannot be listed holds nothing to name)
        return []


def _shown(path: Path) -> str:
    """``path`` relative to the working folder where that is shorter (``../train`` from inside ``OUT/report``)."""
    try:
        rel = os.path.relpath(path)
    except ValueError:  # (another drive)
        return str(path)
    return rel if len(rel) < len(str(path)) else str(path)


def _listed(found: list[Path]) -> str:
    return ", ".join(_shown(p) for p in found[:4]) + (", ..." if len(found) > 4 else "")


def stage_hint(folder: Path, want: str) -> str:
    """A sentence naming what to give instead of ``folder`` when a run (``want`` "run") or a scene (``want``
    "scene") was expected: the run it lies inside (``RUN/eval``, an ensemble's ``members/``), the runs or scenes
    it holds (a pipeline's output, a folder of runs, a sweep's ``runs/``), or, for a stage folder of a pipeline's
    output (its ``report/``), those of the pipeline; "" when there are none."""
    test = is_run if want == "run" else is_scene
    what = "runs" if want == "run" else "scenes"
    folder = Path(folder)
    absolute = Path(os.path.abspath(folder))
    if want == "run":
        for up in list(absolute.parents)[:2]:  # (RUN/eval; ENSEMBLE/members/member_0's folder members/)
            if is_run(up):
                return f"it lies inside the run {_shown(up)}: give that"
    else:
        if is_run(absolute):  # (a run given for its scene: "not a COLMAP workspace. Run `uncertsplat reconstruct`")
            scene = _run_scene(absolute)
            return ("it is a training run, the output of `uncertsplat train`" +
                    (f"; the scene it was trained on is {_shown(scene)}: give that" if scene else ""))
        for up in list(absolute.parents)[:2]:  # (WS/images, WS/sparse/0, a Blender scene's train/)
            if is_scene(up):
                return f"it lies inside the scene {_shown(up)}: give that"
    found = [p for p in _subfolders(absolute) if test(p)]
    if want == "run" and not found:  # (a sweep's points are its runs/)
        found = [p for p in _subfolders(absolute / "runs") if test(p)]
    if found:
        whose = " (a pipeline's output)" if (absolute / PIPELINE_STARTED).is_file() else ""
        return f"it holds {what}{whose}: give one of them: {_listed(found)}"
    if (absolute.parent / PIPELINE_STARTED).is_file():  # a stage folder of a pipeline's output
        found = [p for p in _subfolders(absolute.parent) if p != absolute and test(p)]
        if found:
            return f"it is a stage folder of a pipeline's output, whose {what} are: {_listed(found)}"
    return ""


__all__ = ["PIPELINE_STARTED", "RUN_FILES", "holds_files", "is_run", "is_scene", "stage_hint"]
