"""Methods side by side, and the speed-accuracy trade, on the synthetic demo scene (issue 9).

Runs one sweep (``uncertsplat.stages.sweep``) whose default is our variational model and whose axes
are the methods (paper variant, single-entry VI, Fisher/Laplace, an N-member ensemble),
the offset-table size K_table, the evaluation samples K, the training steps, the resolution and
(optionally) the spawn rule.
Writes ``benchmarks/results/methods.json`` (the method table + every sweep record) and
``benchmarks/results/methods_pareto.png``, and prints the table as markdown for BENCHMARKS.md.

Usage (CPU, shared 2 cores: about 15 minutes with the defaults)::

    .venv/bin/python benchmarks/bench_methods.py --out /tmp/bench_methods [--jobs 2] [--iterations 300]

Any other scene, methods only (fern at 1/8 from a ``reconstruct`` workspace of the LLFF 1/4 images)::

    .venv/bin/python benchmarks/bench_methods.py --scene WS --label fern-1-8 --methods-only --train-preset paper \
        --downscale 1.5873 --iterations 3000 --max-gaussians 60000 --out /tmp/bench_methods_fern

``--spawn-fractions F ...`` adds the spawn rule as an axis (how many Gaussians carry a posterior).
"""

from __future__ import annotations

import argparse
import json
import platform
import shutil
import time
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"


def spec_toml(args) -> str:
    its = args.iterations
    scene = f'scene = "{args.scene}"' if args.scene else 'synth = { preset = "demo", seed = 0 }'
    spawn = f"\nspawn_fraction = {sorted(args.spawn_fractions)}" if args.spawn_fractions else ""
    # --densify-until: the base config then has the run's length, so the scaled schedule keeps this window
    base_its = f" iterations = {its}," if args.densify_until else ""
    until = f", until = {args.densify_until}" if args.densify_until else ""
    if args.methods_only:
        axes = 'method = ["variational", "paper", "vi-single", "fisher", "ensemble"]' + spawn
    else:
        axes = f"""method = ["variational", "paper", "vi-single", "fisher", "ensemble"]
num_entries = [1, 10, 20]
num_samples = [1, 5, 10, 20]
iterations = {sorted({max(its // 2, 1), its})}
downscale = {sorted({args.downscale, args.downscale * 2})}{spawn}"""
    return f"""
name = "methods"
{scene}
train_preset = "{args.train_preset}"
train = {{ eval_every = 100000, checkpoint_every = 100000, log_every = 50,{base_its} densify = {{ max_gaussians = {args.max_gaussians}{until} }} }}
evaluate = {{ split = "test" }}
design = "axes"
schedule = "scaled"
pareto_x = "time"
pareto_y = ["ause_mae", "nll"]
[default]
method = "variational"
iterations = {its}
num_entries = 10
num_samples = 10
downscale = {args.downscale}
ensemble_size = {args.ensemble}
[axes]
{axes}
"""


def fmt(x, p=3):
    return "-" if x is None else f"{x:.{p}f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("/tmp/bench_methods"))
    ap.add_argument("--iterations", type=int, default=150)
    ap.add_argument("--downscale", type=float, default=4.0)
    ap.add_argument("--ensemble", type=int, default=3, help="ensemble size N (the paper's upper bound uses 10)")
    ap.add_argument("--max-gaussians", type=int, default=10000, help="densification cap (keeps CPU runs short)")
    ap.add_argument("--jobs", type=int, default=None)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--scene", type=Path, default=None,
                    help="a scene/workspace folder (default: the synthetic demo scene, generated)")
    ap.add_argument("--label", default="synthetic-demo", help="results go to methods_<label>.json")
    ap.add_argument("--train-preset", default="demo", help="train preset of every point (fern: paper)")
    ap.add_argument("--densify-until", type=int, default=None,
                    help="densify until this step at --iterations (default: the preset's window, scaled)")
    ap.add_argument("--spawn-fractions", type=float, nargs="*", default=[],
                    help="also vary the spawn rule (||scale|| > f x extent carries a posterior)")
    ap.add_argument("--methods-only", action="store_true",
                    help="only the methods at the default knobs (no K_table/K/steps/resolution axes)")
    args = ap.parse_args()

    from uncertsplat.stages import sweep

    args.out.mkdir(parents=True, exist_ok=True)
    spec = args.out / "methods.toml"
    spec.write_text(spec_toml(args))
    t0 = time.perf_counter()
    summary = sweep.run(spec, args.out, jobs=args.jobs, device=args.device).model_dump()  # plain rows below
    wall = time.perf_counter() - t0
    recs = summary["records"]
    # the method table: every method at the default knobs (ensemble: K = N)
    d = next(r for r in recs if r["is_default"])["knobs"]
    rows = [r for r in recs if all(r["knobs"][k] == d[k] for k in ("iterations", "num_entries", "downscale"))
            and (r["knobs"]["num_samples"] == d["num_samples"])]
    rows.sort(key=lambda r: r["ause_mae"] if r.get("ause_mae") is not None else 9.0)
    header = ("| method | PSNR | AUSE-MAE | AUSE-RMSE | NLL | cal. err | std scale | NLL, std rescaled | cal. err, rescaled "
              "| depth AUSE | train s | eval s/view | peak MB |\n"
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    lines = [header]
    for r in rows:
        lines.append(f"| {r['method']} | {fmt(r['psnr'], 2)} | {fmt(r['ause_mae'])} | {fmt(r['ause_rmse'])} | "
                     f"{fmt(r['nll'])} | {fmt(r['calibration_error'])} | {fmt(r.get('std_scale'), 2)} | "
                     f"{fmt(r.get('nll_calibrated'))} | {fmt(r.get('calibration_error_calibrated'))} | "
                     f"{fmt(r['depth_ause_mae'])} | "
                     f"{fmt(r['train_seconds'], 1)} | {fmt(r['eval_seconds_per_view'], 2)} | "
                     f"{fmt(r.get('peak_memory_mb'), 0)} |")
    table = "\n".join(lines)
    knob_rows = ["| point | PSNR | AUSE-MAE | NLL | depth AUSE | train s | eval s/view | Gaussians | carriers | B/Gaussian |",
                 "|---|---|---|---|---|---|---|---|---|---|"]
    for r in sorted(recs, key=lambda r: r["id"]):
        if r.get("status") == "ok":
            knob_rows.append(f"| {r['id']} | {fmt(r['psnr'], 2)} | {fmt(r['ause_mae'])} | {fmt(r['nll'])} | "
                             f"{fmt(r['depth_ause_mae'])} | {fmt(r['train_seconds'], 1)} | "
                             f"{fmt(r['eval_seconds_per_view'], 2)} | {r.get('num_gaussians')} | {r.get('num_carriers')} | "
                             f"{fmt(r.get('memory_per_gaussian_bytes'), 0)} |")
    RESULTS.mkdir(parents=True, exist_ok=True)
    out = {
        "benchmark": "methods", "label": args.label,
        "scene": str(args.scene) if args.scene else "synthetic demo (320x240, 40 views, 5 test views)",
        "downscale": args.downscale, "iterations": args.iterations, "ensemble_size": args.ensemble,
        "max_gaussians": args.max_gaussians, "train_preset": args.train_preset,
        "device": args.device, "jobs": args.jobs, "wall_seconds": wall,
        "machine": {"platform": platform.platform(), "python": platform.python_version()},
        "note": "CPU shared with other processes: timings are indicative only",
        "table": rows, "pareto": summary["pareto"], "default": summary["default"], "records": recs,
    }
    name = "methods" if args.label == "synthetic-demo" else f"methods_{args.label}"
    (RESULTS / f"{name}.json").write_text(json.dumps(out, indent=2) + "\n")
    if (args.out / "pareto.png").is_file():
        shutil.copyfile(args.out / "pareto.png", RESULTS / f"{name}_pareto.png")
    print(table)
    print()
    print("\n".join(knob_rows))
    print(f"\nPareto (AUSE-MAE vs time): {summary['pareto'].get('ause_mae_vs_time')}")
    print(f"wall {wall:.0f} s; wrote {RESULTS / (name + '.json')}")


if __name__ == "__main__":
    main()
