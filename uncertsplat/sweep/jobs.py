"""One sweep job: train one config (or reuse its finished run), evaluate it at each of its points.

``run_job(job)`` is a function of a plain, JSON-serialisable dict (``spec.make_jobs``) and of the files it
names, so a process pool here, or a cluster engine later, can run the jobs anywhere and in any order.
It never raises for a failure inside the job: the records then have ``status = "failed"`` and the error.
"""

from __future__ import annotations

import functools
import json
import shutil
import sys
import time
import traceback
from pathlib import Path

import torch

from uncertsplat.config import EvalConfig, TrainConfig
from uncertsplat.console import advice_within, console
from uncertsplat.errors import Interrupted, UserError
from uncertsplat.schemas import TrainSummary
from uncertsplat.strategy.budget import MEMORY_HOLD

RECORD_KEYS = ("psnr", "psnr_render", "ssim", "ause_mae", "ause_rmse", "nll", "nll_kde", "calibration_error",
               "nll_calibrated", "calibration_error_calibrated", "spearman", "depth_ause_mae", "depth_ause_rmse",
               "depth_abs_rel")


def _peak_mb(device: torch.device) -> float:
    from uncertsplat.train.trainer import peak_memory_mb

    return float(peak_memory_mb(device))


def held_notes(warnings: list[str]) -> list[str]:
    """The notes a point's record gets from its training's ``warnings``: where memory held its growth it has fewer
    Gaussians than its settings give (an ensemble's warnings name their member first: "member 2: memory held ...")."""
    return [f"training: {w}" for w in warnings if MEMORY_HOLD in w]


def _same_config(run_dir: Path, cfg) -> bool:
    """Whether ``run_dir/config.json`` holds ``cfg`` (False when absent or unreadable)."""
    try:
        return json.loads((run_dir / "config.json").read_text(encoding="utf-8")) == json.loads(cfg.model_dump_json())
    except (OSError, ValueError):
        return False


def retrain_folders(run_dir: Path) -> tuple[Path, Path]:
    """(``RUN.retrain``, ``RUN.retrained``): where ``sweep --force`` trains a finished run again, and the finished run
    while the new one takes its place (``_train``)."""
    return run_dir.with_name(f"{run_dir.name}.retrain"), run_dir.with_name(f"{run_dir.name}.retrained")


def finish_swap(run_dir: Path) -> None:
    """A forced retraining stopped between the two renames that put it in place (``_swap_in``): its points' records
    were not written (the swap comes after their evaluation, and the driver records what ``run_job`` returns), so the
    finished run goes back and the retraining waits in ``RUN.retrain`` for the next --force (a review: taking it then
    left the old records beside the new run). A leftover ``RUN.retrained`` beside the run is removed. The sweep calls
    it for every point before it decides which are done: a point with a record is not trained again, and its run
    folder was missing."""
    fresh, old = retrain_folders(run_dir)
    if not run_dir.exists():
        if old.is_dir():
            old.rename(run_dir)
        elif (fresh / "train_summary.json").is_file():  # (no run to go back to)
            fresh.rename(run_dir)
    if old.exists() and run_dir.exists():
        shutil.rmtree(old)


def _train(job: dict, device: torch.device) -> tuple[TrainSummary, bool, Path | None]:
    """Train the job's run unless it is finished; returns (train_summary, trained_now, the retrained run waiting to
    take the run's place, or None).

    ``job["retrain_before"]`` (sweep --force: its start): a run finished before it is trained again, so the point's
    training time is measured now, not carried over from an earlier sweep. The new training goes into
    ``RUN.retrain`` beside the finished run, which stays until the new one's points are evaluated (``run_job`` puts it
    in place then, ``_swap_in``): a forced sweep stopped midway leaves the run its records measured (deleted first,
    the records of a later sweep without --force described models that were gone; put in place before the
    evaluation, a stop there left the old records beside the new run), and the next --force resumes the new training.
    A run this sweep trained is kept for a retry of its evaluation; an unfinished run resumes either way."""
    from uncertsplat.baselines import train_run
    from uncertsplat.config import TrainConfig, build_config
    from uncertsplat.io.atomic import lock_holder
    from uncertsplat.train.trainer import reset_peak_memory

    run_dir = Path(job["run_dir"])
    summary_path = run_dir / "train_summary.json"
    cfg = build_config(TrainConfig, job["train_config"], source=f"sweep job {job['job_id']}")
    fresh, old = retrain_folders(run_dir)
    finish_swap(run_dir)
    before = job.get("retrain_before")
    finished = summary_path.is_file() and _same_config(run_dir, cfg)
    retrain = finished and before is not None and summary_path.stat().st_mtime < before
    if finished and not retrain:
        summary = TrainSummary.read(summary_path)
        if cfg.method != "fisher" or summary.fisher_seconds is not None:
            if fresh.is_dir():  # a forced retraining stopped midway, which this sweep (no --force) leaves alone
                what = ("finished and was not yet evaluated: the next --force evaluates it" if
                        (fresh / "train_summary.json").is_file() else "did not finish: the next --force resumes it")
                print(f"note: {fresh} holds a training that `sweep --force` began and {what}; without --force it is "
                      "not used (delete it to drop it)", file=sys.stderr, flush=True)
            return summary, False, None
    # past the reuse of a finished run (an evaluate of it holds its lock too, and reading it is safe): what follows
    # removes, moves or trains the run, under a `train --resume` of it by hand it would mix or destroy both
    for folder in (run_dir, fresh):
        holder = lock_holder(folder) if folder.is_dir() else None
        if holder is not None:
            raise UserError(f"another uncertsplat process ({holder}) holds this point's run now", path=folder,
                            hint="Wait for it to finish, then run the sweep again.")
    if retrain:
        resume = _same_config(fresh, cfg)
        if fresh.exists() and not resume:
            shutil.rmtree(fresh)
        if resume and (fresh / "train_summary.json").is_file():
            # an earlier --force's retraining, finished and stopped before its evaluation: evaluated now, its training
            # time its own (not "trained now": a record said so with 0.09 s of wall time)
            return TrainSummary.read(fresh / "train_summary.json"), False, fresh
        reset_peak_memory(device)  # the point's own peak, not that of the points trained before it in this process
        train_run(Path(job["scene"]), fresh, cfg, device, resume=resume)
        return TrainSummary.read(fresh / "train_summary.json"), True, fresh
    resume = (run_dir / "config.json").is_file()
    if run_dir.exists() and not resume:
        shutil.rmtree(run_dir)  # a job that died before writing anything useful
    if resume and not _same_config(run_dir, cfg):
        # another config under the same id (a run extended by hand): never mixed, never lost without a word
        aside = run_dir.with_name(f"{run_dir.name}.replaced")
        n = 1
        while aside.exists():  # an earlier replaced run stays too
            n += 1
            aside = run_dir.with_name(f"{run_dir.name}.replaced{n}")
        run_dir.rename(aside)
        print(f"note: {run_dir} held a run of other settings than the sweep's (changed by hand?): moved to {aside}",
              file=sys.stderr, flush=True)
        resume = False
    reset_peak_memory(device)  # the point's own peak, not that of the points trained before it in this process
    train_run(Path(job["scene"]), run_dir, cfg, device, resume=resume)
    return TrainSummary.read(summary_path), True, None


def _swap_in(run_dir: Path) -> None:
    """The retrained run (``RUN.retrain``) in place of the finished one, once its points are evaluated (a kill between
    the two renames is finished by ``finish_swap``)."""
    fresh, old = retrain_folders(run_dir)
    run_dir.rename(old)
    fresh.rename(run_dir)  # (beside each other: the run's paths relative to itself hold)
    shutil.rmtree(old)
    # (train's own last line named the folder it trained in, RUN.retrain, which is gone now)
    print(f"retrained: {run_dir} (trained in {fresh.name}, now in place of the finished run)", file=sys.stderr,
          flush=True)


def _advice(table: str, fields) -> functools.partial:
    """``text -> text``: a message of the command whose settings are the spec's ``table`` ("train", "evaluate",
    with ``fields``) in the sweep's words (``console.advice_within``); a key a knob sets is named as that knob (the
    sweep refuses the key where a knob replaces it)."""
    from uncertsplat.sweep.spec import KNOB_KEYS

    knobs = {dotted: knob for knob, (where, dotted) in KNOB_KEYS.items() if where == table}
    return functools.partial(advice_within, table, fields, within="sweep", knobs=knobs)


def run_job(job: dict) -> list[dict]:
    """Run one job and return one record per point (see the module docstring).

    Record keys: ``id``, ``hash``, ``job``, ``method``, ``scene`` and ``seed`` (None unless the spec sets them),
    ``knobs``, ``is_default``, ``status`` (ok/failed),
    ``error``, ``train_seconds``, ``eval_seconds_per_view``, ``eval_seconds``, ``time`` (train + the predictive's fit
    + eval),
    ``num_views``, ``num_samples``, ``peak_memory_mb`` (train / eval / max), ``num_gaussians``,
    ``num_carriers``, the metrics of ``RECORD_KEYS`` (means over the views), ``std_scale`` and
    ``calibration_seconds`` (the std factor fitted on training views, ``eval.engine.fit_std_scale``, and its cost,
    outside the timed evaluation), ``notes``, ``run_dir``; an ok record also carries ``point_report``, the point's
    full ``EvalReport`` as JSON text, which the driver writes to ``OUT/points/{id}.json`` and drops from the record.
    """
    from uncertsplat.device import resolve_device

    threads = job.get("threads")
    if threads:
        torch.set_num_threads(int(threads))  # one thread per job when jobs share the cores
    base = {"job": job["job_id"], "method": job["method_label"], "run_dir": job["run_dir"],
            "device": job["device"], "threads": torch.get_num_threads(), "scene": job.get("scene_name"),
            "seed": job.get("seed")}
    records = []
    previous = console.rewrite
    train_advice, eval_advice = _advice("train", TrainConfig.model_fields), _advice("evaluate", EvalConfig.model_fields)
    try:
        device = resolve_device(job["device"])
        t0 = time.perf_counter()
        # training's advice in the sweep's words (`--set train.exposure=affine`: the sweep refused `--set exposure`)
        console.rewrite = train_advice
        summary, trained, pending = _train(job, device)
        train_peak = summary.peak_memory_mb
        train_info = {"train_seconds": summary.seconds, "trained_now": trained,
                      "train_wall_seconds": time.perf_counter() - t0 if trained else None,
                      "num_gaussians": summary.num_gaussians, "num_carriers": summary.num_carriers,
                      "memory_per_gaussian_bytes": summary.memory_per_gaussian_bytes,
                      "train_peak_memory_mb": train_peak}
        train_notes = held_notes(summary.warnings)
    except Interrupted:  # Ctrl-C / SIGTERM: the sweep stops (the checkpoint resumes the point), it does not retry
        raise
    except Exception as err:  # report, do not kill the sweep
        msg = train_advice(f"{type(err).__name__}: {err}")
        tb = traceback.format_exc(limit=6)
        return [{**base, "id": p["id"], "hash": p["hash"], "knobs": p["knobs"], "is_default": p["is_default"],
                 "status": "failed", "stage": "train", "error": msg, "traceback": tb} for p in job["points"]]
    finally:
        console.rewrite = previous

    for p in job["points"]:
        rec = {**base, **train_info, "id": p["id"], "hash": p["hash"], "knobs": p["knobs"],
               "is_default": p["is_default"]}
        try:
            console.rewrite = eval_advice
            rec.update(_evaluate(job, p, device, run_dir=pending))
            rec["notes"] = train_notes + list(rec.get("notes") or [])
            rec["peak_memory_mb"] = max(train_peak, rec["eval_peak_memory_mb"])
            # what a user waits for: training, the predictive's fit (pixel noise, std factor: as long as a tiny
            # scene's training at K = 2, growing with K) and the evaluation
            rec["time"] = rec["train_seconds"] + rec["calibration_seconds"] + rec["eval_seconds"]
            rec["ause"] = rec.get("ause_mae")
            rec["status"] = "ok"
        except Exception as err:
            rec.update(status="failed", stage="evaluate", error=eval_advice(f"{type(err).__name__}: {err}"),
                       traceback=traceback.format_exc(limit=6))
        finally:
            console.rewrite = previous
        records.append(rec)
    if pending is not None:  # (a stop before this point leaves the finished run and its records as they were)
        try:
            _swap_in(Path(job["run_dir"]))
        except OSError as err:  # (run_job reports, it does not raise: the records say what is where)
            msg = (f"the retrained run in {pending} could not take the place of {job['run_dir']} ({err}); the next "
                   "sweep puts the finished run back, and --force evaluates the retraining again")
            records = [{**r, "status": "failed", "stage": "swap", "error": msg} for r in records]
    return records


def _evaluate(job: dict, point: dict, device: torch.device, run_dir: Path | None = None) -> dict:
    """The point's evaluation of the job's run (``run_dir``: of that run retrained beside it, ``_train``)."""
    from functools import partial

    from uncertsplat.baselines import load_run
    from uncertsplat.config import EvalConfig, build_config
    from uncertsplat.eval.engine import evaluate_views, fit_residual, scored_sampler, split_indices
    from uncertsplat.provenance import hash_config
    from uncertsplat.train.trainer import reset_peak_memory

    ecfg = build_config(EvalConfig, point["eval_config"], source=f"sweep point {point['id']}")
    run_dir = Path(run_dir if run_dir is not None else job["run_dir"])
    loaded = load_run(run_dir, device)
    scene = loaded.load_scene()
    indices = split_indices(scene.split, ecfg)
    t_cal = time.perf_counter()
    # as `evaluate` does; not in the timed part
    train_views = loaded.training_views(scene)  # as evaluate loads them
    residual = fit_residual(loaded.sampler(scene.scene_scale, device), scene.split.get("train", ()), ecfg, device,
                            load_views=train_views, calibration_indices=scene.split.get("calibration", ()))
    sampler, fit = scored_sampler(partial(loaded.sampler, scene.scene_scale, device), residual, scene.cameras,
                                  scene.split, ecfg, device, load_views=train_views)
    calibration_seconds = time.perf_counter() - t_cal
    reset_peak_memory(device)  # the evaluation's own peak
    t0 = time.perf_counter()
    # the scene's own GT depth (a sweep point has no --depth-gt); masked as evaluate scores the run
    views = loaded.scored_views(scene, indices, ecfg.split)
    report = evaluate_views(sampler, views, ecfg, device, show_progress=False,
                            std_scale=fit.scale, calibration_views=fit.names, dof=fit.dof,
                            calibration_held_out=bool(scene.split.get("calibration")),
                            noise_scale=residual.scale if residual is not None else None,
                            notes=loaded.eval_notes(ecfg.num_samples, scored=ecfg.split == "train")
                            + loaded.exposure_notes(),
                            config_hash=hash_config(ecfg.model_dump(mode="json")))
    wall = time.perf_counter() - t0
    out = {k: getattr(report.mean, k) for k in RECORD_KEYS}
    out.update(std_scale=fit.scale, calibration_seconds=calibration_seconds)
    per_view = report.seconds_per_view or 0.0
    out.update(eval_seconds_per_view=per_view, eval_seconds=per_view * len(indices), eval_wall_seconds=wall,
               num_views=len(indices), num_samples=ecfg.num_samples, notes=list(report.notes),
               eval_peak_memory_mb=_peak_mb(device),
               peak_memory_scope="device" if device.type == "cuda" else "process (peak RSS of the phase: memory "
                                                                        "in use when it began counts)")
    # the driver writes OUT/points/{id}.json from this text: a worker writes nothing outside its run folder, so a
    # cluster whose nodes share no disk still gets every point's report on the driver's
    out["point_report"] = report.to_json()
    return out
