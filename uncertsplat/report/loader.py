"""Read a run folder for the report, through the schema of each file (``uncertsplat.schemas``).

Every input of the report is optional: a run may have been trained but not evaluated, evaluated but not
pruned, or interrupted. ``load_run`` reads each file with its model's ``read_optional``:

- a file that is absent leaves its field None, and the report leaves the section out with a short note;
- a file that is present but invalid (not JSON, a missing or renamed key, a newer schema version) also
  leaves its field None, and its one-line ``UserError`` text (which names the file and the key or
  version) is kept in ``RunData.problems``, shown in the report where the section would have been.

Nothing is guessed: a file is read through its model or not at all. Only a path that is not a run
folder is an error.

=============================  ==========================================
file (relative to the run)     model
=============================  ==========================================
``config.json``                :class:`uncertsplat.config.TrainConfig`
``scene.json``                 :class:`RunScene` (``scene`` = scene folder)
``train_summary.json``         :class:`TrainSummary`
``manifest.json``              :class:`Manifest`
``eval/metrics.json``          :class:`EvalReport`
``prune.json``                 :class:`PruneReport`
``SCENE/reconstruct_report``   :class:`ReconstructReport`
``stats.jsonl``                free-form training log (one JSON object a line; a line cut by a crash
                               is skipped with a note); an ensemble's are its members' (``members/*/``)
=============================  ==========================================
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from uncertsplat.config import TrainConfig, build_config
from uncertsplat.console import q
from uncertsplat.conventions import ENSEMBLE_MEMBERS, ensemble_member_dir
from uncertsplat.errors import UserError
from uncertsplat.schemas import EvalReport, Manifest, PruneReport, ReconstructReport, RunScene, TrainSummary
from uncertsplat.schemas.base import run_file_hint
from uncertsplat.types import similarity_scale

# Files whose presence makes a folder a run folder (at least one is needed).
RUN_MARKERS = ("config.json", "stats.jsonl", "train_summary.json", "eval/metrics.json", "prune.json",
               "manifest.json")

CONFIG = "config.json"
SCENE = "scene.json"
STATS = "stats.jsonl"
SUMMARY = "train_summary.json"
MANIFEST = "manifest.json"
METRICS = "eval/metrics.json"
PRUNE = "prune.json"
RECONSTRUCT = "reconstruct_report.json"
MEMBERS = ENSEMBLE_MEMBERS
"""An ensemble run's folder of member runs (``members/member_0``, ...), each with its own ``stats.jsonl``."""

@dataclass
class RunData:
    """What the report knows about one run folder (each field None/empty when absent or invalid)."""

    path: Path
    name: str
    config: TrainConfig | None = None
    stats: list[dict] = field(default_factory=list)
    train_summary: TrainSummary | None = None
    metrics: EvalReport | None = None
    prune: PruneReport | None = None
    scene_info: RunScene | None = None
    manifest: Manifest | None = None
    reconstruct: ReconstructReport | None = None
    reconstruct_path: Path | None = None
    member_stats: list[tuple[str, list[dict]]] = field(default_factory=list)
    """An ensemble's training logs, (``members/NAME``, rows) per member with a ``stats.jsonl``: the run itself has
    none."""
    problems: dict[str, str] = field(default_factory=dict)
    """File (relative to the run, e.g. ``prune.json``) -> one line saying why it could not be read."""
    notes: list[str] = field(default_factory=list)
    """Every problem met while reading (those of ``problems`` and skipped log lines), shown in the summary."""

    @property
    def maps_dir(self) -> Path:
        return self.path / "eval" / "maps"

    @property
    def scene_path(self) -> Path | None:
        """The scene folder the run was trained on (``RunScene.scene_folder``), None without a valid scene.json."""
        return self.scene_info.scene_folder(self.path) if self.scene_info is not None else None

    @property
    def depth_to_source(self) -> float | None:
        """The factor that takes the run's normalised lengths (depth maps, depth RMSE/MAE) to the scene's own units:
        1 / s of scene.json's ``world_from_source`` (x_run = s x_source + t), as ``evaluate`` writes it into the maps'
        ``uncertsplat:depth_to_source``; None without a valid scene.json. The evaluation's own factor (the header of its
        first map) where it has maps: an evaluation made after the scene folder's frame changed (a model aligned to
        metres after training) is in the folder's units, which scene.json does not record."""
        written = self._maps_factor()
        if written is not None:
            return written
        if self.scene_info is None:
            return None
        m = np.asarray(self.scene_info.world_from_source, dtype=np.float64)
        s = similarity_scale(m) if m.shape == (4, 4) else 0.0
        return 1.0 / s if math.isfinite(s) and s > 0 else None

    def _maps_factor(self) -> float | None:
        """``uncertsplat:depth_to_source`` of the first EXR map of the evaluation (read once), None without one."""
        if not hasattr(self, "_maps_factor_value"):
            from uncertsplat.io.maps import written_depth_to_source

            try:
                self._maps_factor_value = written_depth_to_source(self.maps_dir)
            except Exception:  # an unreadable map: scene.json's factor (the maps' own problems are said elsewhere)
                self._maps_factor_value = None
        return self._maps_factor_value

    @property
    def is_pruned(self) -> bool:
        return self.prune is not None or PRUNE in self.problems

    def problem(self, file: str) -> str | None:
        """The one-line problem of ``file`` (a key of ``problems``), or None when it was read or is absent."""
        return self.problems.get(file)


def one_line(err: UserError) -> str:
    """The UserError text on one line (it names the file and what is wrong)."""
    return " ".join(str(err).split())


# ----------------------------------------------------------------------------------------------- read
def _read(run: RunData, key: str, reader) -> Any:
    """``reader()``; on a UserError record its one-line text under ``key`` and return None."""
    try:
        return reader()
    except UserError as err:
        run.problems[key] = one_line(err)
        run.notes.append(run.problems[key])
        return None


def read_train_config(path: Path) -> TrainConfig | None:
    """``RUN/config.json`` (the resolved ``TrainConfig`` written by ``train``), None when absent.

    Raises:
        UserError: naming the file when it is not JSON or not a valid TrainConfig.
    """
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise UserError(f"not valid JSON ({err})", path=path, hint=run_file_hint("config.json")) from None
    if not isinstance(data, dict):
        raise UserError(f"expected a JSON object, found {type(data).__name__}", path=path)
    return build_config(TrainConfig, data, source=str(path))


def read_jsonl(path: Path, notes: list[str]) -> list[dict]:
    """The JSON objects of a JSON-lines log; unreadable lines (e.g. cut by a crash) are skipped with a note."""
    if not path.is_file():
        return []
    rows: list[dict] = []
    bad = 0
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as err:
        notes.append(f"{path}: could not be read ({err.strerror}); left out")
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


def load_run(path: str | Path, name: str | None = None) -> RunData:
    """Read everything the report can use from a run folder (see the module docstring).

    Raises:
        UserError: naming ``path`` when it does not exist, is not a folder, or holds none of the files
            a run folder has (``RUN_MARKERS``).
    """
    path = Path(path)
    if not path.exists():
        raise UserError("run folder not found", path=path,
                        hint="Give the folder written by `uncertsplat train` (or `prune`).")
    if not path.is_dir():
        raise UserError("not a folder; expected a run folder", path=path,
                        hint="Give the folder written by `uncertsplat train` (or `prune`), not a file in it.")
    if not any((path / m).is_file() for m in RUN_MARKERS):
        # a scene folder (synth's or a COLMAP workspace) holds images and a scene.json or sparse/, but no run files
        scene = (path / "images").is_dir() or (path / "sparse").is_dir()
        # a pipeline's output (one folder per stage) or a sweep's: the runs are inside, and so is a report
        inside = sorted(p.name for p in path.iterdir() if p.is_dir() and ((p / CONFIG).is_file()
                                                                         or (p / PRUNE).is_file()))
        sweep = (path / "sweep.json").is_file()
        made = [p for p in (path / "report" / "index.html", path / "index.html") if p.is_file()]
        hint = "Give the folder written by `uncertsplat train` (or `prune`)."
        if inside or sweep:
            hint = ((f"Give the runs in it: uncertsplat report {' '.join(q(path / n) for n in inside)}" if inside
                     else "A sweep's points are its runs/ (uncertsplat report RUN ...)")
                    + (f"; its report is {made[0]}" if made else "") + ".")
        raise UserError(
            "not a run folder (none of config.json, stats.jsonl, eval/metrics.json, prune.json found)"
            + ("; this is a scene, the input of `uncertsplat train`" if scene else
               "; it holds runs (a pipeline's output)" if inside else
               "; this is a sweep's output" if sweep else ""),
            path=path, hint=hint)
    run = RunData(path=path, name=name or path.resolve().name)
    run.config = _read(run, CONFIG, lambda: read_train_config(path / CONFIG))
    run.stats = read_jsonl(path / STATS, run.notes)
    if not run.stats and (path / MEMBERS).is_dir():  # an ensemble: each member trained alone and logged its steps
        for member in sorted((p for p in (path / MEMBERS).iterdir() if (p / STATS).is_file()),
                             key=lambda p: (len(p.name), p.name)):
            rows = read_jsonl(member / STATS, run.notes)
            if rows:
                run.member_stats.append((f"{MEMBERS}/{member.name}", rows))
    run.train_summary = _read(run, SUMMARY, lambda: TrainSummary.read_optional(path / SUMMARY))
    run.manifest = _read(run, MANIFEST, lambda: Manifest.read_optional(path / MANIFEST))
    run.scene_info = _read(run, SCENE, lambda: RunScene.read_optional(path / SCENE))
    run.prune = _read(run, PRUNE, lambda: PruneReport.read_optional(path / PRUNE))
    run.metrics = _read(run, METRICS, lambda: EvalReport.read_optional(path / METRICS))
    run.notes.extend(_training_notes(run))
    scene = run.scene_path
    if scene is not None:
        rp = scene / RECONSTRUCT
        if not rp.is_file():  # a synthetic scene with its own cameras: a pipeline's SfM check of its photos, if any
            rp = _reconstruction_of(scene, path) or rp
        run.reconstruct = _read(run, RECONSTRUCT, lambda: ReconstructReport.read_optional(rp))
        run.reconstruct_path = rp if run.reconstruct is not None else None
    return run


def _reconstruction_of(scene: Path, run_dir: Path) -> Path | None:
    """The ``reconstruct_report.json`` of a stage beside the run (a pipeline's folders: ``make demo``'s reconstruct
    stage checks SfM on the synthetic scene's photos, whose GT cameras the run trained with) that reconstructed
    ``scene``'s own photos; None when there is none."""
    photos = (scene / "images").resolve()
    for folder in sorted(p for p in run_dir.resolve().parent.iterdir() if p.is_dir()):
        found = folder / RECONSTRUCT
        if found.is_file():
            try:
                if Path(ReconstructReport.read(found).photos).resolve() == photos:
                    return found
            except (UserError, OSError, ValueError):
                continue
    return None


def _training_notes(run: RunData) -> list[str]:
    """What the page says of a training that is not finished: a process training the run now, or a run stopped
    before its last step (no train_summary.json past its newest checkpoint), with the command that finishes it
    (the page showed n/a and sent the reader to `evaluate`)."""
    from uncertsplat.io.atomic import lock_holder
    from uncertsplat.io.checkpoints import list_checkpoints, unfinished_training

    notes = []
    holder = lock_holder(run.path)
    if holder is not None:
        notes.append(f"another process ({holder}) is writing this run now: the page shows it as it was when read")
    members = unfinished_members(run)
    if members is not None:  # (its checkpoints are the members': the run folder holds none)
        scene = run.scene_path if run.scene_path is not None else "SCENE"
        notes.append(f"training is not finished: {members[0]} of the ensemble's {members[1]} members are trained "
                     f"(`uncertsplat train {q(scene)} -o {q(run.path)} --method ensemble --resume` trains the others; "
                     "`evaluate` needs them all)")
        return notes
    found = list_checkpoints(run.path)
    if run.config is None or not found:
        return notes
    step, total = found[-1][0], run.config.iterations
    summary_steps = run.train_summary.steps if run.train_summary is not None else None
    if step < total and (summary_steps is None or summary_steps < step):
        notes.append(unfinished_training(step, total, run.scene_path, run.path)
                     + "; `evaluate` then scores the finished model")
    return notes


def other_splits(run: RunData) -> list[str]:
    """The folders of ``run``'s evaluations of other splits than the held-out views (``evaluate --split train``'s
    ``eval-train/``), which the report does not show."""
    return sorted(p.parent.name for p in run.path.glob("eval-*/metrics.json"))


def without_model(run: RunData) -> bool:
    """Whether a training run holds no model at all: no ``variational.ply``, no checkpoint and no ensemble members (a
    training stopped before its first checkpoint), so there is nothing to evaluate (a prune folder: ``prune.json``)."""
    p = run.path
    return (run.config is not None and not (p / "variational.ply").is_file() and not any((p / "ckpts").glob("*.pt"))
            and not (p / MEMBERS).is_dir() and not (p / PRUNE).is_file())


def unfinished_members(run: RunData) -> tuple[int, int] | None:
    """(members trained, members in all) of an ensemble run stopped before its last member finished (no
    train_summary.json of its own); None for every other run."""
    if run.config is None or run.config.method != "ensemble" or run.train_summary is not None:
        return None
    total = run.config.ensemble_size
    done = sum((ensemble_member_dir(run.path, i) / SUMMARY).is_file() for i in range(total))
    return (done, total) if done < total else None


# --------------------------------------------------------------------------------------------- helpers
def as_float(v: Any) -> float | None:
    """A finite float, or None for missing/non-numeric/NaN/inf values."""
    if isinstance(v, bool) or v is None:
        return None
    if isinstance(v, (int, float)):
        f = float(v)
        return f if math.isfinite(f) else None
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
