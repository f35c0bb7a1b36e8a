"""Read a run folder for the report, tolerantly.

Every input of the report is optional: a run may have been trained but not evaluated, evaluated but not
pruned, made by an older version, or interrupted. ``load_run`` reads what is there into a ``RunData``
and records a short note for every file that exists but cannot be read, so the report can leave the
section out and say why instead of failing. Only a path that is not a run folder at all is an error.

The on-disk contract is DESIGN.md section 2.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from uncertsplat.errors import UserError

# Files whose presence makes a folder a run folder (at least one is needed).
RUN_MARKERS = ("config.json", "stats.jsonl", "train_summary.json", "eval/metrics.json", "prune.json",
               "manifest.json")


@dataclass
class RunData:
    """What the report knows about one run folder (each field None/empty when unavailable)."""

    path: Path
    name: str
    config: dict | None = None
    stats: list[dict] = field(default_factory=list)
    train_summary: dict | None = None
    metrics: dict | None = None
    """``eval/metrics.json`` as plain JSON (the values shown in the report come from here)."""
    metrics_schema_ok: bool | None = None
    """True when the EvalReport schema validated it, False when it did not, None when no schema."""
    prune: dict | None = None
    scene_info: dict | None = None
    """``RUN/scene.json`` written by ``train``: {"scene": path, "extent": ...}."""
    manifest: dict | None = None
    reconstruct: dict | None = None
    reconstruct_path: Path | None = None
    scene_path: Path | None = None
    notes: list[str] = field(default_factory=list)
    """Problems met while reading (a corrupt file, a skipped line), shown in the report."""

    @property
    def maps_dir(self) -> Path:
        return self.path / "eval" / "maps"

    @property
    def is_pruned(self) -> bool:
        return self.prune is not None


# ----------------------------------------------------------------------------------------------- json
def read_json(path: Path, notes: list[str]) -> dict | None:
    """A JSON object from ``path``, or None (with a note) when it is missing, corrupt or not an object."""
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        notes.append(f"{path.name}: could not be read ({type(err).__name__}: {err}); left out")
        return None
    if not isinstance(data, dict):
        notes.append(f"{path.name}: expected a JSON object, found {type(data).__name__}; left out")
        return None
    return data


def read_jsonl(path: Path, notes: list[str]) -> list[dict]:
    """The JSON objects of a JSON-lines file; unreadable lines (e.g. cut by a crash) are skipped."""
    if not path.is_file():
        return []
    rows: list[dict] = []
    bad = 0
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as err:
        notes.append(f"{path.name}: could not be read ({err.strerror}); left out")
        return []
    for line in text.splitlines():
        line = line.strip()
        if not line:
            continue
        try:
            obj = json.loads(line)
        except json.JSONDecodeError:
            bad += 1
            continue
        if isinstance(obj, dict):
            rows.append(obj)
        else:
            bad += 1
    if bad:
        notes.append(f"{path.name}: {bad} unreadable line(s) skipped")
    return rows


def _validate_metrics(data: dict) -> tuple[bool | None, str]:
    """Validate against the EvalReport schema when it can be imported."""
    try:
        from uncertsplat.eval.report_schema import EvalReport
    except Exception:  # the schema module is optional for the report: plain JSON is enough
        return None, ""
    try:
        EvalReport.model_validate(data)
    except Exception as err:  # pydantic.ValidationError, or a schema that rejects old files
        first = str(err).splitlines()[0] if str(err) else type(err).__name__
        return False, first
    return True, ""


# ------------------------------------------------------------------------------------------ scene path
_SCENE_KEYS = ("scene_path", "scene", "scene_dir", "source_path", "workspace", "data", "data_dir", "input")


def _scene_from(obj: Any) -> str | None:
    if not isinstance(obj, dict):
        return None
    for key in _SCENE_KEYS:
        v = obj.get(key)
        if isinstance(v, str) and v:
            return v
        if isinstance(v, dict):  # e.g. {"scene": {"path": ...}} or a source dict
            for k2 in ("path", "root", "scene_path"):
                if isinstance(v.get(k2), str) and v.get(k2):
                    return v[k2]
    return None


def find_scene_path(run: RunData) -> Path | None:
    """The scene (workspace) the run was trained on: from RUN/scene.json (what ``train`` writes), else
    config.json / train_summary.json, else the inputs named in the manifest."""
    candidates: list[str] = []
    for obj in (run.scene_info, run.config, run.train_summary, (run.config or {}).get("source"),
                (run.train_summary or {}).get("source")):
        s = _scene_from(obj)
        if s:
            candidates.append(s)
    if run.manifest:
        # A pipeline manifest names its inputs: a path, or the name of a sibling stage folder.
        for key in (run.manifest.get("input_hashes") or {}):
            key = str(key)
            candidates.append(key if Path(key).is_absolute() else str(run.path.parent / key))
    for c in candidates:
        p = Path(c)
        if not p.is_absolute():
            p = (run.path / p) if (run.path / p).exists() else p
        if p.is_dir() and p.resolve() != run.path.resolve() and (
            (p / "images").is_dir() or (p / "sparse").is_dir() or (p / "reconstruct_report.json").is_file()
            or any(p.glob("transforms_*.json"))
        ):
            return p
    return None


# ------------------------------------------------------------------------------------------------ load
def load_run(path: str | Path, name: str | None = None) -> RunData:
    """Read everything the report can use from a run folder.

    Raises:
        UserError: naming ``path`` when it does not exist, is not a folder, or holds none of the files
            a run folder has (config.json, stats.jsonl, eval/metrics.json, prune.json, manifest.json).
    """
    path = Path(path)
    if not path.exists():
        raise UserError("run folder not found", path=path,
                        hint="Give the folder written by `uncertsplat train` (or `prune`).")
    if not path.is_dir():
        raise UserError("not a folder; expected a run folder", path=path,
                        hint="Give the folder written by `uncertsplat train` (or `prune`), not a file in it.")
    if not any((path / m).is_file() for m in RUN_MARKERS):
        raise UserError(
            "not a run folder (none of config.json, stats.jsonl, eval/metrics.json, prune.json found)",
            path=path, hint="Give the folder written by `uncertsplat train` (or `prune`).")
    run = RunData(path=path, name=name or path.resolve().name)
    notes = run.notes
    run.config = read_json(path / "config.json", notes)
    run.stats = read_jsonl(path / "stats.jsonl", notes)
    run.train_summary = read_json(path / "train_summary.json", notes)
    run.manifest = read_json(path / "manifest.json", notes)
    run.scene_info = read_json(path / "scene.json", notes)
    run.prune = read_json(path / "prune.json", notes)
    run.metrics = read_json(path / "eval" / "metrics.json", notes)
    if run.metrics is not None:
        ok, why = _validate_metrics(run.metrics)
        run.metrics_schema_ok = ok
        if ok is False:
            notes.append(f"eval/metrics.json does not match the current EvalReport schema ({why}); "
                         "read as plain JSON")
    run.scene_path = find_scene_path(run)
    if run.scene_path is not None:
        rp = run.scene_path / "reconstruct_report.json"
        run.reconstruct = read_json(rp, notes)
        run.reconstruct_path = rp if run.reconstruct is not None else None
    return run


# --------------------------------------------------------------------------------------------- helpers
def as_float(v: Any) -> float | None:
    """A finite float, or None for missing/non-numeric/NaN/inf values."""
    if isinstance(v, bool) or v is None:
        return None
    if isinstance(v, (int, float)):
        f = float(v)
        return f if math.isfinite(f) else None
    return None


def first_key(d: dict | None, keys: tuple[str, ...]) -> Any:
    """The value of the first of ``keys`` present in ``d`` (None when none is)."""
    if not isinstance(d, dict):
        return None
    for k in keys:
        if k in d and d[k] is not None:
            return d[k]
    return None


def stats_series(stats: list[dict], key: str) -> tuple[np.ndarray, np.ndarray]:
    """(steps [S], values [S]) of one numeric key of stats.jsonl, skipping rows without it."""
    xs, ys = [], []
    for i, row in enumerate(stats):
        y = as_float(row.get(key))
        if y is None:
            continue
        x = as_float(row.get("step"))
        xs.append(x if x is not None else float(i))
        ys.append(y)
    return np.asarray(xs, dtype=np.float64), np.asarray(ys, dtype=np.float64)
