"""Stage ``sweep``: the speed-accuracy trade, measured (``uncertsplat sweep SPEC.toml -o OUT``).

Writes into ``OUT/``:
- ``scene/``: the synthetic scene, when the spec names none;
- ``scenes/{name}/``: a named scene's synthetic scene or ``reconstruct`` workspace (``[scenes.NAME]`` with
  ``synth`` or ``photos``), made once by this process before any job;
- ``runs/{job}/`` (named scenes: ``runs/{scene}/{job}/``): one run folder per training config (reused when
  unchanged: a sweep resumes);
- ``points/{point}.json``: the full ``EvalReport`` of each point of the spec as it is now (written by this process
  from what the job returns: workers write only into their run folders), and ``points/by_hash/{hash}.json``: every
  point's ever measured, by its settings' hash (a point of other settings under the same id, e.g. after
  ``--set train.seed=1``, never replaces another's; ``points/{point}.json`` is rebuilt from it when gone);
- ``scene_inputs.json``: the fingerprints of the scene folders of one's own the points were measured on (a
  changed or other folder is refused, or with ``--force`` trained on again);
- ``sweep.jsonl``: one JSON record per point (appended as jobs finish; see ``sweep.jobs.run_job``);
- ``sweep.json``: the summary: spec, records (latest per point), the table (mean and spread over seeds of each
  point on each scene), default, Pareto fronts (per scene);
- ``pareto.png``: accuracy vs time with the fronts and the default marked (one row of panels per scene);
- ``index.html``: the figure and a table of every point (front members and the default marked).

Jobs (points sharing a training config) run where ``executor`` says (``sweep.executors``): ``local``, over
this machine's cores in a process pool of ``jobs`` workers, each a fresh process per job (so peak-memory
figures are per job) with one torch thread when several run at once (``jobs = 1`` runs them one by one in
this process); or ``ray``, as Ray tasks with their CPU/GPU request, on a local Ray instance or a cluster.
Either way a failed job is retried ``retries`` times, only this process appends to ``sweep.jsonl`` (one
complete line per record), and a progress bar counts done / in progress (handed to a worker) / failed points.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

from pydantic import ValidationError

from uncertsplat.console import console, count, list_names, q
from uncertsplat.errors import Interrupted, UserError
from uncertsplat.io.atomic import atomic_write_text, run_lock
from uncertsplat.schemas.base import describe_validation_error, key_problems
from uncertsplat.schemas.runs import SweepRecord, SweepSummary


def _num(x: float | None, digits: int) -> str:
    return "n/a" if x is None else f"{x:.{digits}f}"


def read_records(path: Path) -> list[SweepRecord]:
    """The records of ``sweep.jsonl`` (a line cut short by a crash is skipped).

    Raises:
        UserError: naming the file, the line and the key when a complete line does not match the schema.
    """
    out = []
    if path.is_file():
        for i, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
            try:
                data = json.loads(line)
            except json.JSONDecodeError:
                continue  # a line cut short by a crash
            problems = key_problems(SweepRecord, data)
            try:
                if problems:
                    raise UserError("; ".join(problems[:4]))
                out.append(SweepRecord.model_validate(data))
            except (ValidationError, UserError) as err:
                why = describe_validation_error(err) if isinstance(err, ValidationError) else err.message
                raise UserError(f"line {i} does not match the sweep record schema (version "
                                f"{SweepRecord.model_fields['schema_version'].default}): {why}", path=path,
                                hint="Move the file away to start the sweep afresh.") from None
    return out


def _synth_changes(cfg, folder: Path) -> list[str]:
    """The settings of ``cfg`` (a ``SynthConfig``) that the scene in ``folder`` was not generated with ("seed 0 ->
    1"), from the ``SynthConfig`` its ``scene.json`` records; a setting the recorded one lacks (added since) is no
    change."""
    from uncertsplat.data.synthetic import read_scene_meta

    old = read_scene_meta(folder).config
    return [f"{k} {old[k]} -> {v}" for k, v in json.loads(cfg.model_dump_json()).items() if k in old and old[k] != v]


def _synth(keys: dict, folder: Path, force: bool = False, runs: Path | None = None) -> Path:
    """The synthetic scene of ``keys`` (SynthConfig) in ``folder``, generated unless it is already there with these
    settings; with other settings it is refused (the points measured on it would be reused as the new scene's),
    or generated again with ``force`` (which measures every point again: the run folders trained on it, ``runs``,
    are removed).

    Raises:
        UserError: the folder's scene was generated with other settings and ``force`` is not set.
    """
    from uncertsplat.config import SynthConfig, build_config
    from uncertsplat.data.synthetic import generate_scene, is_synthetic_scene

    cfg = build_config(SynthConfig, keys, source="sweep synth")
    if is_synthetic_scene(folder):
        changes = _synth_changes(cfg, folder)
        if not changes:
            return folder
        if not force:
            raise UserError(f"the sweep's synthetic scene was generated with other settings than the spec's now "
                            f"({', '.join(changes)}): its points would be reused as measurements of the new scene",
                            path=folder, hint="Run with --force to generate it again and measure every point on it, "
                                              "or give the sweep another output folder.")
        console.print(f"generating the synthetic scene again ({', '.join(changes)}) into {folder}")
        if runs is not None:  # trained on the scene before (a finished run of the same config was reused as it was)
            _drop_runs(runs)
    else:
        console.print(f"generating the synthetic scene ({keys}) into {folder}")
    generate_scene(folder, cfg, overwrite=True)
    return folder


SCENE_INPUTS = "scene_inputs.json"
"""``OUT/scene_inputs.json``: the scene folders of one's own a sweep measured on, with their fingerprints
(``_check_scene_inputs``)."""


SWEEP_FILES = ("sweep.jsonl", "sweep.json", SCENE_INPUTS, "points", "runs", "scene", "scenes")
"""What a sweep writes into its output folder (the module docstring): one of them makes a folder a sweep's."""


def _refuse_foreign_output(out_dir: Path, scenes: list[Path | None], spec_path: Path) -> None:
    """Refuse an output folder that is one of the sweep's scene folders (``scenes``: a scene's records would be among
    its files, which the next sweep takes for a changed scene), or that holds files and nothing a sweep writes
    (``SWEEP_FILES``): its index.html and pareto.png would replace a user's (a new user's web folder). The spec
    ``spec_path`` kept in the folder is the sweep's own.

    Raises:
        UserError: naming the folder and what to give instead.
    """
    out = out_dir.resolve()
    for folder in scenes:
        if folder is not None and Path(folder).resolve() == out:
            raise UserError("the sweep's output folder is its scene folder: the sweep's files would be counted as the "
                            "scene's, and the next sweep would take it for a changed scene", path=out_dir,
                            hint=f"Give the sweep a folder of its own, e.g. -o {q(out.parent / (out.name + '_sweep'))}.")
    # (hidden files, a file manager's .DS_Store, do not make a folder anyone's)
    held = [p.name for p in out_dir.iterdir() if not p.name.startswith(".") and p.resolve() != spec_path.resolve()] \
        if out_dir.is_dir() else []
    if held and not any(n in SWEEP_FILES for n in held):
        raise UserError(f"the output folder is not empty and holds no earlier sweep ({list_names(sorted(held))}): the "
                        "sweep would write its index.html, pareto.png and folders among them", path=out_dir,
                        hint="Choose a new output folder (-o), or an earlier sweep's folder to go on with it.")


def _runs_of(out_dir: Path, name: str | None) -> Path:
    """The folder of the runs trained on scene ``name`` (None: the single scene's)."""
    return out_dir / "runs" / name if name is not None else out_dir / "runs"


def _drop_runs(runs: Path) -> None:
    """Remove the run folders ``runs`` (``_runs_of``): their models are of a scene that changed, and a finished run of
    the same config is otherwise reused as it is."""
    import shutil

    if runs.is_dir():
        console.print(f"[yellow]note:[/] removing {runs}: trained on the scene before it changed")
        shutil.rmtree(runs)


def _outputs_inside(folder: Path, evaluations: bool = True) -> list[Path]:
    """uncertsplat's own outputs inside the scene folder ``folder`` (a run trained into SCENE/run, a pipeline's or a
    sweep's output, a stage folder with its manifest, a run's evaluation folder copied there, a ``select-views -o``
    folder): not the scene's files, and changed by every command run there (a review's run trained into the scene
    refused every point of the sweep on it). One walk of the folder, never into the folders a scene's loader reads
    (``_SCENE_DATA``).
    ``evaluations`` False: without evaluation and selection folders, as before 2026-12-01 (a fingerprint recorded
    then is taken by those rules)."""
    import os

    from uncertsplat.errors import UserError
    from uncertsplat.io.folders import PIPELINE_STARTED, is_run
    from uncertsplat.schemas.metrics import EvalReport
    from uncertsplat.schemas.select import Selection
    from uncertsplat.stages.manifest import MANIFEST, read_manifest

    def reads_as(schema, path: Path) -> bool:
        try:
            schema.read(path)
        except UserError:
            return False
        return True

    def ours(marker: str, place: Path) -> bool:
        if marker == "config.json":
            return is_run(place)
        if marker == MANIFEST:  # (a capture app's or a download's manifest.json is no stage's)
            return read_manifest(place) is not None
        if marker == SCENE_INPUTS:  # (a sweep's output: its runs/ or records beside it)
            return (place / "runs").is_dir() or (place / "sweep.jsonl").is_file()
        if marker == "metrics.json":  # (a copied RUN/eval; another tool's metrics.json is the scene's)
            return (place / "config.json").is_file() and reads_as(EvalReport, place / marker)
        if marker == "selection.json":
            return reads_as(Selection, place / marker)
        return True  # (.stages_started.json: uncertsplat run's own name)

    markers = ("config.json", MANIFEST, PIPELINE_STARTED, SCENE_INPUTS,
               *(("metrics.json", "selection.json") if evaluations else ()))
    found = set()
    for top, dirs, files in os.walk(folder):
        place = Path(top)
        if place == folder:
            dirs[:] = [d for d in dirs if d not in _SCENE_DATA]  # (never left out, whatever they hold)
            continue
        if any(m in files and ours(m, place) for m in markers):
            found.add(place)
            dirs[:] = []  # (all of it left out: nothing inside needs a look)
    return sorted(found)


_SCENE_DATA = frozenset({"images", "sparse", "masks", "depth", "distorted", "train", "test", "val"})
"""The folders of a scene the loaders read (COLMAP and Blender layouts): never left out of its fingerprint."""


def _check_scene_inputs(out_dir: Path, folders: dict[str | None, Path], force: bool, measured: bool) -> None:
    """Refuse a scene folder of one's own (``scene = PATH``, ``--scene``, ``[scenes.NAME] path``) whose files or
    place changed since the sweep measured points on it (``measured``), and a switch between such a folder and a
    scene the sweep makes in ``OUT``: a point's hash is its settings', so the points would be reused as measurements
    of the changed scene (and an unfinished run resumed on it). With ``force`` the runs on it are removed, to be
    trained again. Scenes the sweep makes have their own checks of their content (``_synth``, ``reconstruct``).
    Records the folders' fingerprints (the sweep's own scenes by place)."""
    from uncertsplat.stages.manifest import fingerprint_folder

    path = out_dir / SCENE_INPUTS
    try:
        recorded = json.loads(path.read_text(encoding="utf-8")) if path.is_file() else {}
    except (OSError, ValueError):
        recorded = {}  # (damaged: recorded again below)
    now, changed = dict(recorded), []
    for name, folder in folders.items():
        folder = Path(folder).resolve()
        key = name or ""
        if out_dir.resolve() in folder.parents:
            # made by the sweep (its own checks: ``_synth``, ``reconstruct``), recorded by its place in OUT only (a
            # sweep folder moved elsewhere goes on): a sweep that measured on it and is then given --scene (or the
            # reverse) reused every point as the other scene's
            entry = {"path": folder.relative_to(out_dir.resolve()).as_posix(), "made_by_the_sweep": True}
        else:
            entry = {"path": str(folder), "fingerprint": fingerprint_folder(folder, skip=[out_dir,
                                                                                      *_outputs_inside(folder)])}
        old = recorded.get(key)
        if (isinstance(old, dict) and old != entry and old.get("path") == entry["path"] and "fingerprint" in entry
                and old.get("fingerprint") in (fingerprint_folder(folder, skip=out_dir), fingerprint_folder(
                    folder, skip=[out_dir, *_outputs_inside(folder, evaluations=False)]))):
            old = entry  # (recorded by the rules before, 2026-12-01: every file, or runs and stages left out)
        if isinstance(old, dict) and old != entry:
            def where(e: dict) -> str:
                return (f"the scene the sweep made ({out_dir / e.get('path', '')})" if e.get("made_by_the_sweep")
                        else str(e.get("path")))

            what = (f"moved from {where(old)} to {where(entry)}" if old.get("path") != entry["path"]
                    else f"{folder}'s files changed (every file under it counts but hidden ones, notes at its top "
                         "and uncertsplat's own outputs inside it: runs, evaluations, selections, a pipeline's or a "
                         "sweep's folders)")
            changed.append((name, what))
        now[key] = entry
    if changed and measured and not force:
        names = "; ".join(f"scene {n!r}: {w}" if n else w for n, w in changed)
        raise UserError(f"the sweep's scene is not the one its points were measured on ({names}): they would be "
                        "reused as measurements of it", path=out_dir,
                        hint="Run with --force to train and measure every point again on it, or give the sweep "
                             "another output folder (-o).")
    for name, _ in changed:
        _drop_runs(_runs_of(out_dir, name))
    atomic_write_text(path, json.dumps(now, indent=2) + "\n")


def prepare_scene(name: str, entry, out_dir: Path, force: bool = False) -> Path:
    """The folder ``train`` reads for the spec's scene ``name`` (``sweep.spec.SweepScene``).

    ``path``: checked to exist; ``synth``: generated into ``OUT/scenes/NAME``; ``photos``: ``reconstruct`` runs
    into ``OUT/scenes/NAME`` (it reuses a workspace that already holds the same photos and options).

    Raises:
        UserError: naming the scene and the folder when a ``path`` or ``photos`` folder does not exist.
    """
    folder = Path(out_dir) / "scenes" / name
    if entry.synth is not None:
        return _synth(entry.synth, folder, force, runs=_runs_of(out_dir, name))
    if entry.path is not None:
        if not Path(entry.path).is_dir():
            what = "is a file, not a folder" if Path(entry.path).exists() else "does not exist"
            raise UserError(f"the folder of sweep scene {name!r} {what}", path=entry.path,
                            hint=f"Fix scenes.{name}.path in the spec (relative paths are read from the spec's "
                                 f"folder) or set it with --set scenes.{name}.path=FOLDER.")
        return Path(entry.path)
    from uncertsplat.config import ReconstructConfig, build_config
    from uncertsplat.stages import reconstruct

    if not Path(entry.photos).is_dir():
        what = "is a file, not a folder" if Path(entry.photos).exists() else "does not exist"
        raise UserError(f"the photos folder of sweep scene {name!r} {what}", path=entry.photos,
                        hint=f"Fix scenes.{name}.photos in the spec or set it with --set scenes.{name}.photos=FOLDER.")
    console.print(f"scene {name}: reconstructing {entry.photos} into {folder}")
    reconstruct.run(Path(entry.photos), folder,
                    build_config(ReconstructConfig, entry.reconstruct, source=f"sweep scene {name} reconstruct"))
    return folder


def _move_point_reports(out_dir: Path, records: list, current: dict[str, dict]) -> None:
    """Each measured point whose id this spec changes (``make_jobs``: e.g. the default moved) gets its report
    (``points/ID.json``) under the new id: every report is read before any is written (two points may trade ids),
    and before the points to run write theirs."""
    latest = {r.hash: r.id for r in records if r.status == "ok" and r.hash in current}  # the newest record per point
    moves = {old: current[h]["id"] for h, old in latest.items() if current[h]["id"] != old}
    texts = {new: (out_dir / "points" / f"{old}.json").read_text(encoding="utf-8") for old, new in moves.items()
             if (out_dir / "points" / f"{old}.json").is_file()}
    for new, text in texts.items():
        atomic_write_text(out_dir / "points" / f"{new}.json", text)


BY_HASH = "by_hash"
"""``points/by_hash/``: every point report by its settings' hash (module docstring)."""


def _sync_point_reports(out_dir: Path, records: list) -> None:
    """``points/{id}.json`` of every measured point of the summary ``records`` as its report by hash says (rewritten
    where another setting's report under the same id replaced it, or gone); a report gone from both is named (a
    sweep from before reports were kept by hash keeps its ``points/`` as it was)."""
    gone = []
    for r in records:
        if r.status != "ok":
            continue
        src, dst = out_dir / "points" / BY_HASH / f"{r.hash}.json", out_dir / "points" / f"{r.id}.json"
        if src.is_file():
            text = src.read_text(encoding="utf-8")
            if not dst.is_file() or dst.read_text(encoding="utf-8") != text:
                atomic_write_text(dst, text)
        elif not dst.is_file():
            gone.append(r.id)
    if gone:
        console.print(f"[yellow]note:[/] the report of {count(len(gone), 'point')} is gone ({', '.join(gone)}: "
                      f"points/ID.json): its record in sweep.jsonl stands; --force measures every point again")


def run(spec_path: Path, out_dir: Path, *, jobs: int | None = None, device: str = "auto", scene: Path | None = None,
        overrides: list[str] | None = None, force: bool = False, executor: str = "local", address: str | None = None,
        cpus_per_job: float = 1.0, gpus_per_job: float = 0.0, retries: int = 1,
        only_scenes: list[str] | None = None) -> SweepSummary:
    """Run (or resume) a sweep; returns the ``sweep.json`` summary.

    Args:
        spec_path: the sweep TOML (``pipelines/tradeoff.toml``).
        out_dir: output folder (see the module docstring).
        jobs: parallel jobs (None: the number of cores, 1 on CUDA).
        device: auto, cpu or cuda (every job uses it).
        scene: a scene folder overriding the spec's.
        overrides: ``key=value`` overrides of the spec (e.g. ``train.iterations=300``).
        force: measure every point again, those with an ``ok`` record too: their runs are trained again.
        executor: local or ray (``sweep.executors``).
        address: ray only: None starts a local Ray instance (``jobs`` CPUs when given), "auto" joins a cluster.
        cpus_per_job, gpus_per_job: ray only: the resources each job asks for (and its torch threads).
        retries: extra runs of a job whose worker died or whose points failed.
        only_scenes: run only these of the spec's ``[scenes.NAME]`` (None: all of them).

    Raises:
        UserError: a bad spec, or (after writing everything) when some points failed.
    """
    from uncertsplat.console import progress
    from uncertsplat.device import resolve_device
    from uncertsplat.report.sweep_page import build_sweep_page
    from uncertsplat.sweep.executors import EXECUTORS, connect_ray, require_ray, run_local, run_ray
    from uncertsplat.sweep.jobs import finish_swap
    from uncertsplat.sweep.pareto import axis_name, plot_pareto, split_by_resolution, summarize, table_points
    from uncertsplat.sweep.spec import expand_points, load_spec, make_jobs, shadowed_settings

    spec = load_spec(Path(spec_path), overrides)
    out_dir = Path(out_dir)
    dev = resolve_device(device)
    if jobs is None:
        jobs = 1 if dev.type == "cuda" else (os.cpu_count() or 1)
    if jobs < 1:
        raise UserError(f"--jobs must be at least 1, got {jobs}")
    if executor not in EXECUTORS:
        raise UserError(f"unknown executor {executor!r}", hint=f"Choose one of: {', '.join(EXECUTORS)}.")
    if retries < 0:
        raise UserError(f"--retries must be at least 0, got {retries}")
    if executor == "ray":
        require_ray()  # before any work, with the install command
        if address is not None:  # a cluster that cannot be reached: said before any scene is generated
            connect_ray(address)
    whole = spec  # the summary covers every scene of the spec, whichever of them this call runs
    if only_scenes:
        unknown = [n for n in only_scenes if n not in spec.scenes]
        if unknown:
            raise UserError(f"--scenes names {', '.join(unknown)}, which the spec does not have", path=spec_path,
                            hint=f"The spec's scenes: {', '.join(spec.scenes) or 'none (a single-scene spec)'}.")
        spec = spec.model_copy(update={"scenes": {n: e for n, e in spec.scenes.items() if n in only_scenes}})
    shadowed = shadowed_settings(spec)  # (on the scenes this call runs)
    if shadowed:  # the points set these: the spec's (or --set's) values would have no effect, recorded as used
        raise UserError(f"{'; '.join(shadowed)}: the knob sets this in every point of the sweep, so the value given "
                        "here would have no effect", path=Path(spec_path),
                        hint="Set it through the knob instead (e.g. `[default] num_samples = 3`, or --set "
                             "default.num_samples=3 / an axis), or remove the knob from [default].")
    if scene is not None and spec.scenes:
        raise UserError("--scene replaces the scene of a single-scene spec, and this spec names "
                        f"{len(spec.scenes)} scenes ({', '.join(spec.scenes)})", path=spec_path,
                        hint="Set one scene's folder with --set scenes.NAME.path=FOLDER instead.")
    _refuse_foreign_output(out_dir, [Path(scene) if scene is not None else spec.scene,
                                     *(e.path for e in (whole.scenes or {}).values())], spec_path)
    with run_lock(out_dir, "sweep"):  # (it makes the folder, or says why it cannot)
        if spec.scenes:
            folders = {name: prepare_scene(name, entry, out_dir, force) for name, entry in spec.scenes.items()}
        else:
            scene_path = Path(scene) if scene is not None else spec.scene
            if scene_path is None:
                scene_path = _synth(spec.synth, out_dir / "scene", force, runs=_runs_of(out_dir, None))
            if not Path(scene_path).is_dir():
                what = "is a file, not a folder" if Path(scene_path).exists() else "does not exist"
                raise UserError(f"the sweep's scene folder {what}", path=scene_path,
                                hint="Give --scene PATH or remove `scene` from the spec to use a synthetic scene.")
            folders = Path(scene_path)
        log = out_dir / "sweep.jsonl"
        before = read_records(log)  # what earlier runs of the sweep measured
        _check_scene_inputs(out_dir, folders if isinstance(folders, dict) else {None: folders}, force,
                            measured=any(r.status == "ok" for r in before))
        all_jobs = make_jobs(spec, out_dir, folders, str(dev), threads=None)
        for job in all_jobs:  # (a point whose record stands is not trained again: its run folder must be there)
            finish_swap(Path(job["run_dir"]))
        hashes = {p["hash"] for j in all_jobs for p in j["points"]}  # this spec's points only
        current = {p["hash"]: p for j in all_jobs for p in j["points"]}  # (before the done ones leave the jobs)
        asked = len(spec.seed_values()) * sum(len(expand_points(spec.on_scene(n))) for n in spec.scene_names())
        if asked > len(hashes):
            extra = asked - len(hashes)
            console.print(f"[yellow]note:[/] {count(extra, 'point')} of the spec {'has' if extra == 1 else 'have'} the same "
                          "training and evaluation configuration as another point and are measured once (e.g. a "
                          "knob at the value the preset already gives, num_entries with the informed posterior, "
                          "which stores one table entry, or ensemble_size and spawn_fraction without offset tables)")
        newest = {r.hash: r for r in before}  # (records in order: a point's last one says where it stands)
        # a point is done when its newest record is ok: one that failed after an ok record (its evaluation of a run
        # --force retrained) was never retried without --force, while the report showed it failed
        done = {h for h, r in newest.items() if r.status == "ok"} & hashes if not force else set()
        everywhere = current  # with --scenes, the other scenes' points too (their reports move with them)
        if whole is not spec:
            others = {n: out_dir / "scenes" / n for n in whole.scenes if n not in spec.scenes}
            everywhere = {p["hash"]: p for j in make_jobs(whole, out_dir, {**folders, **others}, str(dev), threads=None)
                          for p in j["points"]}
        _move_point_reports(out_dir, before, everywhere)
        todo = []
        started_at = time.time()
        for job in all_jobs:
            job["points"] = [p for p in job["points"] if p["hash"] not in done]
            job["retrain_before"] = started_at if force else None  # measured again: trained again (jobs._train)
            if job["points"]:
                todo.append(job)
        npts = sum(len(j["points"]) for j in todo)
        where = (f"{min(jobs, max(len(todo), 1))} at a time" if executor == "local" else
                 f"on Ray ({address or 'a local instance'}, {cpus_per_job:g} CPU / {gpus_per_job:g} GPU per job)")
        console.print(f"[bold]sweep[/] {spec.name}: {count(npts, 'point')} to run in {count(len(todo), 'job')} "
                      f"({len(done)} already done), {where}, device {dev}, {count(retries, 'retry', 'retries')}")

        counts = {"done": 0, "failed": 0}
        started_jobs: dict[str, int] = {}  # points of the jobs handed out and not recorded yet (a retry: once)
        bar = progress()
        task = bar.add_task("sweep", total=npts, info="")

        def show() -> None:
            bar.update(task, completed=counts["done"] + counts["failed"],
                       info=f"done {counts['done']}  in progress {sum(started_jobs.values())}  "
                            f"failed {counts['failed']}")

        def started(job: dict) -> None:
            started_jobs[job["job_id"]] = len(job["points"])
            show()

        def record(dicts: list[dict]) -> None:
            for r in dicts:
                r.setdefault("executor", executor)
                report = r.pop("point_report", None)
                if report is not None:
                    atomic_write_text(out_dir / "points" / BY_HASH / f"{r['hash']}.json", report + "\n")
                    atomic_write_text(out_dir / "points" / f"{r['id']}.json", report + "\n")
            recs = [SweepRecord.model_validate(r) for r in dicts]  # a writer bug fails here, not in a later read
            # one write of whole lines from this process only: a crash leaves no half record (read_records skips a
            # line cut short anyway)
            with open(log, "a", encoding="utf-8") as f:
                f.write("".join(r.model_dump_json() + "\n" for r in recs))
                f.flush()
                os.fsync(f.fileno())
            for r in recs:
                started_jobs.pop(r.job, None)
            counts["done"] += sum(r.status == "ok" for r in recs)
            counts["failed"] += sum(r.status != "ok" for r in recs)
            show()
            for r in recs:
                if r.status == "ok":
                    console.print(f"  {r.id}: PSNR {_num(r.psnr, 2)}, AUSE {_num(r.ause_mae, 4)}, NLL {_num(r.nll, 3)}, "
                                  f"train {_num(r.train_seconds, 1)} s, eval {_num(r.eval_seconds_per_view, 2)} s/view")
                else:
                    console.print(f"  [red]{r.id} failed[/] in {r.stage}: {r.error}")

        # what the same command does next: with --force every point is trained again, this sweep's too (a review:
        # the advice said the finished points were kept)
        again = ("Run the same sweep command again: the finished points are kept, the stopped one resumes from its "
                 "checkpoint, and a point whose training had not started runs (a trained model is evaluated, not "
                 "trained again)." if not force else
                 "Without --force, the same command keeps what is measured: the points this sweep measured with their "
                 "new records, the others with their earlier ones; a stopped point that had a record keeps it and its "
                 "run (its new training waits in the run folder's .retrain), one that had none resumes from its "
                 "checkpoint. With --force again, every point is trained again, a stopped training resumed from its "
                 "checkpoint, one finished in .retrain evaluated.")
        with bar:
            try:
                if executor == "ray":
                    run_ray(todo, address=address, cpus_per_job=cpus_per_job, gpus_per_job=gpus_per_job,
                            retries=retries, on_records=record, on_start=started,
                            num_cpus=jobs if address is None else None)
                else:
                    run_local(todo, jobs=jobs, retries=retries, on_records=record, on_start=started)
            except Interrupted as err:  # a point's training stopped on Ctrl-C: the sweep stops, it does not retry
                raise Interrupted(f"sweep stopped: {err.message}", hint=again) from None
            except KeyboardInterrupt:  # Ctrl-C elsewhere (a point's evaluation): the same advice
                raise Interrupted("sweep stopped", path=out_dir, hint=again) from None

        if whole is not spec:  # --scenes: the other scenes' points (a point's hash does not depend on its folder)
            current = everywhere
            hashes |= set(current)
        # a record measured under an earlier spec for a point of this one (the same configs) takes this spec's id,
        # knobs and default flag: a changed default made the old default's record claim to be it
        logged = read_records(log)  # with this run's records
        kept = [r for r in logged if r.hash in hashes]
        records = [r.model_copy(update={"id": current[r.hash]["id"], "knobs": current[r.hash]["knobs"],
                                        "is_default": current[r.hash]["is_default"]}) for r in kept]
        stale = len({r.hash for r in logged} - hashes)
        if stale:
            console.print(f"[yellow]note:[/] {log} also holds {count(stale, 'point')} of other settings (an earlier "
                          "spec or --set): kept there, left out of this sweep's summary and plot")
        conditions = sorted({(r.device or "?", r.threads or 0) for r in records if r.status == "ok"})
        if len(conditions) > 1:  # a point's hash holds its settings, not where it ran: its timings stay as measured
            console.print(f"[yellow]note:[/] the points were measured under {len(conditions)} conditions ("
                          + ", ".join(f"{d}, {t} thread{'s' if t != 1 else ''}" for d, t in conditions)
                          + "; sweep.jsonl's device and threads say which): their times and memory compare across "
                          "them only as far as those do; a sweep into a new folder measures every point under one")
        summary = summarize(whole, records)
        summary.write(out_dir / "sweep.json")
        _sync_point_reports(out_dir, summary.records)
        if any(r.status == "ok" for r in summary.records):
            means = " (means over seeds)" if spec.seeds else ""
            plot_pareto(table_points(summary, whole), out_dir / "pareto.png", x=spec.pareto_x, ys=spec.pareto_y,
                        title=f"{spec.name}: {', '.join(axis_name(y) for y in spec.pareto_y)} against "
                              f"{axis_name(spec.pareto_x)}{means} (front in black, default starred)",
                        group="panel" if spec.scenes or split_by_resolution(summary, whole) else None)
        else:  # no point to draw: an earlier sweep's figure there would be shown as this one's
            (out_dir / "pareto.png").unlink(missing_ok=True)
        fig = "pareto.png" if (out_dir / "pareto.png").is_file() else None
        atomic_write_text(out_dir / "index.html", build_sweep_page(summary, fig))
    written = [log, out_dir / "sweep.json", *([out_dir / "pareto.png"] if fig else [])]
    console.print(f"wrote {', '.join(str(p) for p in written)} and {out_dir / 'index.html'}"
                  + ("" if fig else " (no figure: no point was measured)"))
    if summary.num_failed:
        failed = [r.id for r in summary.records if r.status != "ok"]
        raise UserError(f"{len(failed)} sweep point(s) failed: {', '.join(failed)}", path=log,
                        hint="See their `error` in sweep.jsonl; run the sweep again to retry only those points.")
    return summary


