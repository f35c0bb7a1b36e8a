"""Training at a lower resolution first (``TrainConfig.low_res_fraction``): how much time it saves and what it costs.

One scene, one preset, the same seed; for each fraction a run is trained (in the order given, repeated
``--repeats`` times with the order alternating, so that a drift of the machine's speed falls on every setting) and
evaluated with ``evaluate``'s defaults (``--eval-samples`` posterior samples). Reports per fraction: training seconds
and their ratio to the first fraction's in the same repeat, held-out PSNR of the expected render, AUSE-MAE, NLL,
calibration error and the Gaussians.

    .venv/bin/python benchmarks/bench_low_res.py --scene demo_out/synth --preset demo --label demo
    .venv/bin/python benchmarks/bench_low_res.py --scene /tmp/fern_ws --preset paper --label fern \\
        --set '{"scene": {"downscale": 1.5873}, "iterations": 3000}'

Writes ``benchmarks/results/low_res_<label>.json`` and prints the rows for BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import json
import platform
import shutil
import statistics
import time
from datetime import date
from pathlib import Path

import torch
from _common import add_overwrite_option, refuse_overwrite

from uncertsplat.baselines import train_run
from uncertsplat.config import EvalConfig, deep_update, train_config_from
from uncertsplat.device import resolve_device
from uncertsplat.stages import evaluate as evaluate_stage

ROOT = Path(__file__).resolve().parents[1]


def one_run(scene: Path, preset: str, over: dict, fraction: float, scale: float, out: Path, device,
            eval_samples: int) -> dict:
    run = out / f"fraction_{fraction:g}"
    shutil.rmtree(run, ignore_errors=True)
    cfg = train_config_from(preset, deep_update(over, {"low_res_fraction": fraction, "low_res_scale": scale}))
    t = time.perf_counter()
    train_run(scene, run, cfg, device)
    seconds = time.perf_counter() - t
    summary = json.loads((run / "train_summary.json").read_text(encoding="utf-8"))
    rep = evaluate_stage.run(run, EvalConfig(num_samples=eval_samples, save_maps=False), device)
    m = rep.mean
    return {"fraction": fraction, "scale": scale, "train_seconds": seconds, "train_psnr": summary["test_psnr"],
            "gaussians": summary["num_gaussians"], "psnr": m.psnr_render or m.psnr, "ause_mae": m.ause_mae,
            "nll": m.nll, "calibration_error": m.calibration_error, "std_factor": rep.std_scale}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", type=Path, required=True)
    ap.add_argument("--preset", default="demo")
    ap.add_argument("--label", required=True)
    ap.add_argument("--set", default="{}", help="JSON of train-config overrides (every run)")
    ap.add_argument("--fractions", type=float, nargs="+", default=[0.0, 0.5])
    ap.add_argument("--scale", type=float, default=0.5, help="low_res_scale")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--eval-samples", type=int, default=10)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--machine", default=None)
    ap.add_argument("--tmp", type=Path, default=Path("/tmp/bench_low_res"))
    add_overwrite_option(ap)
    args = ap.parse_args()
    path = ROOT / "benchmarks" / "results" / f"low_res_{args.label}.json"
    refuse_overwrite(path, overwrite=args.overwrite)
    device = resolve_device(args.device)
    over = json.loads(args.set)
    out = args.tmp / args.label
    out.mkdir(parents=True, exist_ok=True)
    results: list[dict] = []
    for rep in range(args.repeats):
        order = args.fractions if rep % 2 == 0 else list(reversed(args.fractions))
        rows = {}
        for f in order:
            r = one_run(args.scene, args.preset, over, f, args.scale, out, device, args.eval_samples)
            r["repeat"] = rep
            rows[f] = r
            print(f"RESULT fraction {f:g} repeat {rep}: train {r['train_seconds']:.1f} s, PSNR {r['psnr']:.2f}, "
                  f"AUSE {r['ause_mae']:.3f}, NLL {r['nll']:.3f}, cal. err {r['calibration_error']:.3f}, "
                  f"{r['gaussians']} Gaussians", flush=True)
        ref = rows[args.fractions[0]]["train_seconds"]
        for f in args.fractions:
            rows[f]["time_ratio"] = rows[f]["train_seconds"] / ref
            results.append(rows[f])
        path.write_text(json.dumps({"label": args.label, "scene": str(args.scene), "date": date.today().isoformat(),
                                    "machine": args.machine or platform.processor() or platform.machine(),
                                    "threads": torch.get_num_threads(), "device": str(device),
                                    "args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
                                    "results": results}, indent=1) + "\n")
    print(f"wrote {path}")
    for f in args.fractions:
        rs = [r for r in results if r["fraction"] == f]

        def mean(k, rs=rs):
            return statistics.fmean(r[k] for r in rs)
        print(f"| {f:g} | {mean('train_seconds'):.0f} | x{mean('time_ratio'):.2f} | {mean('psnr'):.2f} | "
              f"{mean('ause_mae'):.3f} | {mean('nll'):.2f} | {mean('calibration_error'):.3f} | "
              f"{mean('gaussians'):.0f} |")


if __name__ == "__main__":
    main()
