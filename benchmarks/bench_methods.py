"""The method table over scenes and seeds: one ``uncertsplat sweep`` of ``benchmarks/specs/methods.toml``.

The spec file is the benchmark (methods x scenes x seeds; see its comments); this script runs it (locally or on
Ray), then writes ``benchmarks/results/methods_<label>.json`` (the table of means and spreads over seeds, the Pareto
fronts and every record) and the sweep's figure, and prints the table per scene as markdown for BENCHMARKS.md.

Usage (CPU)::

    .venv/bin/python benchmarks/bench_methods.py --out /tmp/methods --jobs 1                 # everything
    .venv/bin/python benchmarks/bench_methods.py --out /tmp/methods --scenes fern --set 'seeds=[0]' --label fern
    .venv/bin/python benchmarks/bench_methods.py --out /shared/methods --executor ray --address auto --cpus-per-job 4

Any other spec (e.g. ``pipelines/tradeoff.toml``, the knob axes) works with ``--spec``. Re-running with the same
``--out`` resumes: finished points are kept.

The method tables in BENCHMARKS.md dated before 2026-11-25 came from this script's earlier form, which wrote a spec
from command-line flags (``--iterations``, ``--downscale``, ...; see its git history); the same points are
``--set`` overrides of a spec now.
"""

from __future__ import annotations

import argparse
import json
import platform
import shutil
import time
from pathlib import Path

from _common import add_overwrite_option, refuse_overwrite

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
COLUMNS = (("psnr", "PSNR", 2), ("ause_mae", "AUSE-MAE", 3), ("ause_rmse", "AUSE-RMSE", 3), ("nll", "NLL", 2),
           ("calibration_error", "cal. err", 3), ("std_scale", "std scale", 2), ("nll_calibrated", "NLL, rescaled", 2),
           ("depth_ause_mae", "depth AUSE", 3), ("train_seconds", "train s", 0), ("eval_seconds_per_view",
                                                                                  "eval s/view", 2))


def cell(group: dict, key: str, digits: int) -> str:
    m, s = group["mean"].get(key), group["spread"].get(key)
    if m is None:
        return "-"
    return f"{m:.{digits}f}" + (f" ± {s:.{digits}f}" if s is not None else "")


def markdown(table: list[dict]) -> str:
    """One markdown table per scene: every row of the sweep's table, sorted by AUSE-MAE."""
    out = []
    for scene in dict.fromkeys(g["scene"] for g in table):
        rows = sorted((g for g in table if g["scene"] == scene and g["seeds"]),
                      key=lambda g: g["mean"].get("ause_mae") if g["mean"].get("ause_mae") is not None else 9.0)
        out.append(f"**{scene or 'scene'}** (mean ± std over seeds)\n")
        out.append("| point | seeds | " + " | ".join(h for _, h, _ in COLUMNS) + " |")
        out.append("|---|---|" + "---|" * len(COLUMNS))
        for g in rows:
            seeds = ",".join("-" if s is None else str(s) for s in g["seeds"])
            out.append(f"| {g['id']} | {seeds} | " + " | ".join(cell(g, k, d) for k, _, d in COLUMNS) + " |")
        out.append("")
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spec", type=Path, default=HERE / "specs" / "methods.toml")
    ap.add_argument("--out", type=Path, default=Path("/tmp/bench_methods"))
    ap.add_argument("--label", default="scenes", help="results go to methods_<label>.json")
    ap.add_argument("--scenes", default=None, help="only these of the spec's scenes, comma-separated")
    ap.add_argument("--set", dest="overrides", action="append", default=[], help="spec override key=value")
    ap.add_argument("--jobs", type=int, default=None)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--executor", default="local", choices=["local", "ray"])
    ap.add_argument("--address", default=None)
    ap.add_argument("--cpus-per-job", type=float, default=1.0)
    ap.add_argument("--gpus-per-job", type=float, default=0.0)
    add_overwrite_option(ap)
    args = ap.parse_args()
    dest = RESULTS / f"methods_{args.label}.json"
    refuse_overwrite(dest, RESULTS / f"methods_{args.label}_pareto.png", overwrite=args.overwrite)

    from uncertsplat.stages import sweep

    only = [s.strip() for s in args.scenes.split(",")] if args.scenes else None
    t0 = time.perf_counter()
    summary = sweep.run(args.spec, args.out, jobs=args.jobs, device=args.device, overrides=args.overrides,
                        executor=args.executor, address=args.address, cpus_per_job=args.cpus_per_job,
                        gpus_per_job=args.gpus_per_job, only_scenes=only).model_dump(mode="json")
    wall = time.perf_counter() - t0
    RESULTS.mkdir(parents=True, exist_ok=True)
    out = {
        "benchmark": "methods", "label": args.label, "spec": str(args.spec), "overrides": args.overrides,
        "scenes": only, "device": args.device, "executor": args.executor, "jobs": args.jobs, "wall_seconds": wall,
        "machine": {"platform": platform.platform(), "python": platform.python_version()},
        "date": time.strftime("%Y-%m-%d"),
        "table": summary["table"], "pareto": summary["pareto"], "default": summary["default"],
        "records": summary["records"],
    }
    dest.write_text(json.dumps(out, indent=2) + "\n")
    if (args.out / "pareto.png").is_file():
        shutil.copyfile(args.out / "pareto.png", RESULTS / f"methods_{args.label}_pareto.png")
    print(markdown(summary["table"]))
    print(f"wall {wall:.0f} s; wrote {dest}")


if __name__ == "__main__":
    main()
