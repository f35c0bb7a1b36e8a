"""Evaluation cost and quality vs the number of posterior samples K (issue 6).

Usage:
    .venv/bin/python benchmarks/bench_evaluate.py RUN [--label NAME] [--ks 1 5 10 20] [--machine TEXT]

Evaluates the held-out views of a trained run at each K (same seed) without touching the run folder,
writes ``benchmarks/results/evaluate_{label}.json`` and prints a Markdown table (PSNR, SSIM, AUSE-MAE,
AUSE-RMSE, Gaussian and KDE NLL, Spearman, calibration error, depth AUSE, seconds per view).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
from pathlib import Path

import torch

from uncertsplat.config import EvalConfig
from uncertsplat.eval.engine import evaluate_views

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path)
    ap.add_argument("--label", default=None)
    ap.add_argument("--ks", type=int, nargs="+", default=[1, 5, 10, 20])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--depth-gt", type=Path, default=None, help="GT depth folder (reconstructed synthetic scenes)")
    ap.add_argument("--machine", default="2-core CPU, torch 2.13.0")
    args = ap.parse_args()

    from uncertsplat.baselines import load_run
    from uncertsplat.data.dataset import load_view_set

    device = torch.device("cpu")
    loaded = load_run(args.run, device)
    scene = loaded.load_scene()
    views = load_view_set(scene, scene.split["test"], depth_folder=args.depth_gt)
    rows = []
    for k in args.ks:
        cfg = EvalConfig(num_samples=k, seed=args.seed)
        rep = evaluate_views(loaded.sampler(scene.scene_scale, device), views, cfg, device, show_progress=False)
        m = rep.mean
        rows.append({
            "K": k, "psnr": m.psnr, "ssim": m.ssim, "ause_mae": m.ause_mae, "ause_rmse": m.ause_rmse,
            "nll": m.nll, "nll_kde": m.nll_kde, "spearman": m.spearman, "calibration_error": m.calibration_error,
            "depth_ause_mae": m.depth_ause_mae, "seconds_per_view": rep.seconds_per_view,
            "depth_scale": rep.depth_scale.model_dump() if rep.depth_scale else None,
        })
        print(f"K={k}: {rows[-1]}", flush=True)
    label = args.label or args.run.name
    out = ROOT / "benchmarks" / "results" / f"evaluate_{label}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({
        "run": str(args.run), "views": len(views), "gaussians": len(loaded.model) if hasattr(loaded, "model") else None,
        "machine": args.machine, "threads": torch.get_num_threads(), "omp": os.environ.get("OMP_NUM_THREADS"),
        "date": datetime.date.today().isoformat(), "rows": rows,
    }, indent=2) + "\n")

    def f(x, p=3):
        return "-" if x is None else f"{x:.{p}f}"

    print("| K | PSNR | SSIM | AUSE-MAE | AUSE-RMSE | NLL | NLL (KDE) | Spearman | cal. err | depth AUSE-MAE | s/view |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['K']} | {f(r['psnr'], 2)} | {f(r['ssim'])} | {f(r['ause_mae'])} | {f(r['ause_rmse'])} | "
              f"{f(r['nll'], 2)} | {f(r['nll_kde'], 2)} | {f(r['spearman'])} | {f(r['calibration_error'])} | "
              f"{f(r['depth_ause_mae'])} | {f(r['seconds_per_view'], 2)} |")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
