"""The stage folders inside (or beside) a folder a user gave where a run or a scene was expected: a pipeline's
output (``uncertsplat run -o OUT``: OUT/reconstruct, OUT/train, OUT/prune, OUT/report) or a sweep's, so that the
error can name the folder to give instead of only saying what the given one is not."""

from __future__ import annotations

from pathlib import Path

RUN_FILES = ("stats.jsonl", "train_summary.json", "ckpts", "prune.json")
"""Beside ``config.json``, the files that make a folder a training run (or a pruned one)."""


def is_run(folder: Path) -> bool:
    """Whether ``folder`` is a training or pruned run (``config.json`` and one of ``RUN_FILES``)."""
    return (folder / "config.json").is_file() and any((folder / n).exists() for n in RUN_FILES)


def is_scene(folder: Path) -> bool:
    """Whether ``folder`` looks like a scene ``train`` reads: a COLMAP workspace (``sparse/``) with its images, or a
    Blender layout (``transforms*.json``)."""
    return ((folder / "sparse").is_dir() and (folder / "images").is_dir()) or any(
        (folder / n).is_file() for n in ("transforms.json", "transforms_train.json"))


def _subfolders(folder: Path) -> list[Path]:
    try:
        return sorted(p for p in folder.iterdir() if p.is_dir() and not p.name.startswith("."))
    except OSError:
        return []


def stage_hint(folder: Path, want: str) -> str:
    """A sentence naming the runs (``want`` "run") or scenes (``want`` "scene") inside ``folder``, or beside it when
    ``folder`` is itself a stage folder of such an output (a pipeline's ``report/``); "" when there are none."""
    test = is_run if want == "run" else is_scene
    what = "runs" if want == "run" else "scenes"
    folder = Path(folder)
    places = [(folder, "it holds")] + ([(folder.parent, "beside it are")] if folder.is_dir() else [])
    for place, where in places:
        found = [p for p in _subfolders(place) if p != folder and test(p)]
        if found:
            listed = ", ".join(str(p) for p in found[:4]) + (", ..." if len(found) > 4 else "")
            return f"{where} {what} (a pipeline's output): give one of them: {listed}"
    return ""


__all__ = ["RUN_FILES", "is_run", "is_scene", "stage_hint"]
