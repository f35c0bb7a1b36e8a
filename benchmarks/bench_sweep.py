"""Benchmark the sweep executors: the same 8-point sweep with ``--executor local`` and ``--executor ray``.

The sweep: the ``tiny`` synthetic scene (24 views, 128x96), the ``tiny`` preset for ``--iterations`` steps, 8 seeds
of the default variational point, so 8 independent jobs (8 trainings and 8 evaluations). Both executors get the
machine's 2 cores as 2 one-thread workers (local: a process pool of 2 fresh processes per job; Ray: a local
instance of 2 CPUs, 1 CPU per job). The rounds alternate (local, ray, local, ray, ...) so that the load of a
shared machine falls on both alike; every round writes into a fresh folder.

Per round: wall time of ``stages.sweep.run``; the work inside the jobs (sum over records of training wall time plus
evaluation and calibration wall time); the overhead per point = (wall x workers - work) / points, i.e. the
worker-seconds a point costs beyond its own training and evaluation (process start and imports, scheduling,
result transfer, the driver's writing; for Ray also starting and stopping the local instance, which is measured
on its own too).

Then, **on paper**: the wall time of the method spec (``benchmarks/specs/methods.toml``) on clusters of 1-16 nodes,
from the measured per-job seconds of the method tables in ``results/`` (a job's duration on a node of 2 cores as
measured here), the per-point overhead measured here, and a greedy longest-job-first schedule (Ray's scheduler is
not LPT: it is an estimate, labelled as such).

    .venv/bin/python benchmarks/bench_sweep.py [--rounds 2] [--iterations 150]

Writes ``--out`` (default ``benchmarks/results/sweep_executors.json``; after every round) and prints the rows for BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import heapq
import json
import os
import platform
import statistics
import sys
import time
from datetime import date
from pathlib import Path

from _common import add_overwrite_option, refuse_overwrite

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
RESULTS = ROOT / "benchmarks" / "results"

SPEC = """
name = "executor-overhead"
seeds = [0, 1, 2, 3, 4, 5, 6, 7]
train_preset = "tiny"
train = {{ eval_every = 100000, checkpoint_every = 100000, log_every = 1000 }}
evaluate = {{ num_samples = 4 }}
[default]
method = "variational"
iterations = {iterations}
"""


def work_seconds(rec: dict) -> float:
    """The seconds a record's job spent on its own work (training wall + calibration + evaluation wall)."""
    train = rec.get("train_wall_seconds") or rec.get("train_seconds") or 0.0
    return train + (rec.get("calibration_seconds") or 0.0) + (rec.get("eval_wall_seconds") or 0.0)


def ray_start_stop_seconds() -> float:
    import ray

    t0 = time.perf_counter()
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, configure_logging=False)
    ray.shutdown()
    return time.perf_counter() - t0


def lpt_makespan(durations: list[float], nodes: int) -> float:
    """Longest-job-first greedy schedule on ``nodes`` identical nodes (one job per node at a time)."""
    loads = [0.0] * nodes
    heapq.heapify(loads)
    for d in sorted(durations, reverse=True):
        heapq.heappush(loads, heapq.heappop(loads) + d)
    return max(loads)


def methods_job_seconds() -> dict[str, dict[str, float]]:
    """Measured seconds per job (training + evaluation of the held-out views) of the method tables in results/."""
    out = {}
    for label, name in (("synthetic", "methods_synthetic-demo-calibrated.json"), ("fern", "methods_fern-1-8.json")):
        path = RESULTS / name
        if not path.is_file():
            continue
        data = json.loads(path.read_text(encoding="utf-8"))
        per = {}
        for r in data.get("table", []):
            if r.get("train_seconds") is None:
                continue
            evals = (r.get("eval_seconds") or 0.0) + (r.get("calibration_seconds") or 0.0)
            per[r["method"]] = r["train_seconds"] + evals
        out[label] = per
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=2, help="rounds per executor (alternating)")
    ap.add_argument("--iterations", type=int, default=150)
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench_sweep"))
    ap.add_argument("--out", type=Path, default=RESULTS / "sweep_executors.json", help="the results file")
    add_overwrite_option(ap)
    args = ap.parse_args()
    refuse_overwrite(args.out, overwrite=args.overwrite)

    import shutil

    from uncertsplat.config import SynthConfig
    from uncertsplat.console import console
    from uncertsplat.data.synthetic import generate_scene, is_synthetic_scene
    from uncertsplat.stages import sweep

    os.environ.setdefault("OMP_NUM_THREADS", "1")
    args.work.mkdir(parents=True, exist_ok=True)
    scene = args.work / "scene"
    if not is_synthetic_scene(scene):
        generate_scene(scene, SynthConfig(preset="tiny", seed=0), overwrite=True)
    spec = args.work / "spec.toml"
    spec.write_text(SPEC.format(iterations=args.iterations))
    result = {"benchmark": "sweep_executors", "date": date.today().isoformat(),
              "machine": {"platform": platform.platform(), "python": platform.python_version(),
                          "cpus": os.cpu_count()},
              "sweep": {"scene": "tiny synthetic (24 views, 128x96)", "points": 8, "iterations": args.iterations,
                        "workers": 2, "threads_per_job": 1},
              "rounds": []}
    dest = args.out
    result["ray_start_stop_seconds"] = ray_start_stop_seconds()
    for rnd in range(args.rounds):
        for executor in ("local", "ray"):
            out = args.work / f"{executor}_{rnd}"
            shutil.rmtree(out, ignore_errors=True)
            t0 = time.perf_counter()
            with console.capture():  # the jobs' logs would swamp the terminal
                summary = sweep.run(spec, out, jobs=2, device="cpu", scene=scene, executor=executor,
                                    cpus_per_job=1.0, retries=0)
            wall = time.perf_counter() - t0
            recs = [r.model_dump() for r in summary.records]
            work = sum(work_seconds(r) for r in recs)
            row = {"executor": executor, "round": rnd, "wall_seconds": wall, "work_seconds": work,
                   "overhead_per_point_seconds": (wall * 2 - work) / len(recs),
                   "ok": sum(r["status"] == "ok" for r in recs),
                   "psnr": {r["id"]: r["psnr"] for r in recs}}
            result["rounds"].append(row)
            print(f"{executor} round {rnd}: wall {wall:.1f} s, work {work:.1f} s, "
                  f"overhead {row['overhead_per_point_seconds']:.2f} worker-s/point")
            dest.parent.mkdir(parents=True, exist_ok=True)
            dest.write_text(json.dumps(result, indent=2) + "\n")

    med = {e: {k: statistics.median(r[k] for r in result["rounds"] if r["executor"] == e)
               for k in ("wall_seconds", "work_seconds", "overhead_per_point_seconds")} for e in ("local", "ray")}
    result["median"] = med
    result["ray_over_local_wall"] = med["ray"]["wall_seconds"] / med["local"]["wall_seconds"]
    # the same seeds give the same model whatever ran them (records compared per point id)
    same = all(a["psnr"] == result["rounds"][0]["psnr"] for a in result["rounds"])
    result["same_psnr_every_round"] = same

    # ---- on paper: the methods spec on a cluster
    jobs = methods_job_seconds()
    overhead = med["ray"]["overhead_per_point_seconds"]
    paper = {"note": "ESTIMATE, not measured on a cluster: per-job seconds measured on this 2-core machine, one job "
                     "per 2-core node at a time, the per-point Ray overhead measured here added to each job, a "
                     "longest-job-first schedule; the spec's seeds repeat each scene's jobs",
             "job_seconds": jobs, "rows": []}
    durations = []
    for per in jobs.values():
        durations += [(s + overhead) for s in per.values()] * 3  # 3 seeds
    if durations:
        serial = sum(durations)
        for nodes in (1, 2, 4, 8, 16, 32):
            span = lpt_makespan(durations, nodes)
            paper["rows"].append({"nodes": nodes, "hours": span / 3600, "speedup": serial / span,
                                  "longest_job_hours": max(durations) / 3600})
    result["cluster_on_paper"] = paper
    dest.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps({"median": med, "ray_over_local_wall": result["ray_over_local_wall"],
                      "ray_start_stop_seconds": result["ray_start_stop_seconds"], "same_psnr": same}, indent=2))
    for row in paper["rows"]:
        print(f"| {row['nodes']} | {row['hours']:.2f} h | x{row['speedup']:.1f} |")


if __name__ == "__main__":
    main()
