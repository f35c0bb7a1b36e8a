"""Stage ``sweep``: the speed-accuracy trade, measured (``uncertsplat sweep SPEC.toml -o OUT``).

Writes into ``OUT/``:
- ``scene/``: the synthetic scene, when the spec names none;
- ``runs/{job}/``: one run folder per training config (reused when unchanged: a sweep resumes);
- ``points/{point}.json``: the full ``EvalReport`` of each point;
- ``sweep.jsonl``: one JSON record per point (appended as jobs finish; see ``sweep.jobs.run_job``);
- ``sweep.json``: the summary: spec, records (latest per point), default, Pareto fronts;
- ``pareto.png``: accuracy vs time with the fronts and the default marked;
- ``index.html``: the figure and a table of every point (front members and the default marked).

Jobs (points sharing a training config) run over the local cores in a process pool of ``jobs``
workers, each a fresh process per job (so peak-memory figures are per job) with one torch thread
when several run at once. ``jobs = 1`` runs them one by one in this process.
"""

from __future__ import annotations

import json
import os
from concurrent.futures import ProcessPoolExecutor, as_completed
from multiprocessing import get_context
from pathlib import Path

from uncertsplat.console import console
from uncertsplat.errors import UserError
from uncertsplat.io.atomic import atomic_write_json, atomic_write_text, run_lock


def _read_records(path: Path) -> list[dict]:
    out = []
    if path.is_file():
        for line in path.read_text(encoding="utf-8").splitlines():
            try:
                out.append(json.loads(line))
            except json.JSONDecodeError:
                continue  # a line cut short by a crash
    return out


def summarize(spec, records: list[dict]) -> dict:
    """The ``sweep.json`` summary: the latest record per point, the default and the Pareto fronts."""
    from uncertsplat.sweep.pareto import pareto_front

    latest: dict[str, dict] = {}
    for r in records:
        latest[r["id"]] = r
    recs = list(latest.values())
    ok = [r for r in recs if r.get("status") == "ok"]
    fronts = {}
    for y in spec.pareto_y:
        fronts[f"{y}_vs_{spec.pareto_x}"] = [r["id"] for r in pareto_front(ok, x=spec.pareto_x, y=y,
                                                                             minimize_both=(y != "psnr"))]
    default = next((r for r in recs if r.get("is_default")), None)
    return {"name": spec.name, "spec": json.loads(spec.model_dump_json()), "num_points": len(recs),
            "num_failed": len(recs) - len(ok), "default": default["id"] if default else None,
            "pareto_x": spec.pareto_x, "pareto": fronts, "records": recs}


def run(spec_path: Path, out_dir: Path, *, jobs: int | None = None, device: str = "auto", scene: Path | None = None,
        overrides: list[str] | None = None, force: bool = False) -> dict:
    """Run (or resume) a sweep; returns the ``sweep.json`` summary.

    Args:
        spec_path: the sweep TOML (``pipelines/tradeoff.toml``).
        out_dir: output folder (see the module docstring).
        jobs: parallel jobs (None: the number of cores, 1 on CUDA).
        device: auto, cpu or cuda (every job uses it).
        scene: a scene folder overriding the spec's.
        overrides: ``key=value`` overrides of the spec (e.g. ``train.iterations=300``).
        force: recompute points that already have an ``ok`` record.

    Raises:
        UserError: a bad spec, or (after writing everything) when some points failed.
    """
    from uncertsplat.device import resolve_device
    from uncertsplat.report.sweep_page import build_sweep_page
    from uncertsplat.sweep.jobs import run_job
    from uncertsplat.sweep.pareto import plot_pareto
    from uncertsplat.sweep.spec import load_spec, make_jobs

    spec = load_spec(Path(spec_path), overrides)
    out_dir = Path(out_dir)
    dev = resolve_device(device)
    if jobs is None:
        jobs = 1 if dev.type == "cuda" else (os.cpu_count() or 1)
    if jobs < 1:
        raise UserError(f"--jobs must be at least 1, got {jobs}")
    out_dir.mkdir(parents=True, exist_ok=True)
    with run_lock(out_dir, "sweep"):
        scene_path = Path(scene) if scene is not None else spec.scene
        if scene_path is None:
            scene_path = out_dir / "scene"
            from uncertsplat.config import SynthConfig, build_config
            from uncertsplat.data.synthetic import generate_scene, is_synthetic_scene

            if not is_synthetic_scene(scene_path):
                console.print(f"generating the synthetic scene ({spec.synth}) into {scene_path}")
                generate_scene(scene_path, build_config(SynthConfig, spec.synth, source="sweep synth"), overwrite=True)
        if not Path(scene_path).exists():
            raise UserError("the sweep's scene folder does not exist", path=scene_path,
                            hint="Give --scene PATH or remove `scene` from the spec to use a synthetic scene.")
        all_jobs = make_jobs(spec, out_dir, Path(scene_path), str(dev), threads=None)
        hashes = {p["hash"] for j in all_jobs for p in j["points"]}  # this spec's points only
        log = out_dir / "sweep.jsonl"
        done = {r["hash"] for r in _read_records(log) if r.get("status") == "ok"} if not force else set()
        todo = []
        for job in all_jobs:
            job["points"] = [p for p in job["points"] if p["hash"] not in done]
            if job["points"]:
                todo.append(job)
        npts = sum(len(j["points"]) for j in todo)
        console.print(f"[bold]sweep[/] {spec.name}: {npts} points to run in {len(todo)} jobs "
                      f"({len(done)} already done), {min(jobs, max(len(todo), 1))} at a time, device {dev}")

        def record(recs: list[dict]) -> None:
            with open(log, "a", encoding="utf-8") as f:
                for r in recs:
                    f.write(json.dumps(r) + "\n")
            for r in recs:
                if r["status"] == "ok":
                    console.print(f"  {r['id']}: PSNR {r['psnr']:.2f}, AUSE {r['ause_mae']:.4f}, NLL {r['nll']:.3f}, "
                                  f"train {r['train_seconds']:.1f} s, eval {r['eval_seconds_per_view']:.2f} s/view")
                else:
                    console.print(f"  [red]{r['id']} failed[/] in {r.get('stage')}: {r.get('error')}")

        if jobs == 1 or len(todo) <= 1:
            for job in todo:
                record(run_job(job))
        else:
            for job in todo:
                job["threads"] = 1  # jobs share the cores: oversubscribing threads only slows them all
            ctx = get_context("spawn")  # no fork of a process holding torch threads
            with ProcessPoolExecutor(max_workers=min(jobs, len(todo)), mp_context=ctx, max_tasks_per_child=1) as pool:
                futures = {pool.submit(run_job, job): job for job in todo}
                for fut in as_completed(futures):
                    job = futures[fut]
                    try:
                        recs = fut.result()
                    except Exception as err:  # the worker died (e.g. out of memory)
                        recs = [{"id": p["id"], "hash": p["hash"], "job": job["job_id"], "knobs": p["knobs"],
                                 "method": job["method_label"], "is_default": p["is_default"], "status": "failed",
                                 "stage": "worker", "error": f"{type(err).__name__}: {err}"} for p in job["points"]]
                    record(recs)

        records = [r for r in _read_records(log) if r.get("hash") in hashes]
        summary = summarize(spec, records)
        atomic_write_json(out_dir / "sweep.json", summary)
        if any(r.get("status") == "ok" for r in summary["records"]):
            plot_pareto(summary["records"], out_dir / "pareto.png", x=spec.pareto_x, ys=spec.pareto_y,
                        title=f"{spec.name}: accuracy vs time (front in black, default starred)")
        fig = "pareto.png" if (out_dir / "pareto.png").is_file() else None
        atomic_write_text(out_dir / "index.html", build_sweep_page(summary, fig))
    console.print(f"wrote {log}, {out_dir / 'sweep.json'}, {out_dir / 'pareto.png'} and {out_dir / 'index.html'}")
    if summary["num_failed"]:
        failed = [r["id"] for r in summary["records"] if r.get("status") != "ok"]
        raise UserError(f"{len(failed)} sweep point(s) failed: {', '.join(failed)}", path=log,
                        hint="See their `error` in sweep.jsonl; run the sweep again to retry only those points.")
    return summary
