"""Evaluation cost and quality vs the number of posterior samples K (issue 6).

Usage:
    .venv/bin/python benchmarks/bench_evaluate.py RUN [--label NAME] [--ks 1 5 10 20] [--machine TEXT]

Evaluates the held-out views of a trained run at each K (same seed) without touching the run folder,
writes ``benchmarks/results/evaluate_{label}.json`` and prints a Markdown table (PSNR, SSIM, AUSE-MAE,
AUSE-RMSE, Gaussian and KDE NLL, the NLL with the fitted std factor, Spearman, calibration error, depth AUSE,
seconds per view).

What is scored: ``uncertsplat evaluate``'s full predictive (``evaluate --set num_samples=K``): the samples' spread
plus the pixel noise fitted on training views, the view-consistency and the other terms of
``eval.engine.predictive_terms``, with the std factor and the Student-t's degrees of freedom fitted as evaluate fits
them (``fit_residual``, ``scored_sampler``; the noise is fitted in memory, not cached in the run folder). Fitting
them is timed apart (``calibration_seconds``); ``seconds_per_view`` is the scoring of the views.
``--spread-only`` scores the posterior samples' spread alone (no pixel noise, no side terms, no std factor): what
this script scored before 2026-11-29, and what the tables of BENCHMARKS.md measured on 2026-11-22 are. (The KDE
NLL is the engine's, of the samples alone, either way.)
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import time
from pathlib import Path

import torch
from _common import add_overwrite_option, refuse_overwrite

from uncertsplat.config import EvalConfig
from uncertsplat.eval.engine import evaluate_views, fit_residual, scored_sampler

ROOT = Path(__file__).resolve().parents[1]


def score_sampler(loaded, scene, cfg: EvalConfig, device: torch.device, *, spread_only: bool):
    """The sampler ``uncertsplat evaluate`` scores at these settings and ``evaluate_views``' keyword arguments for
    it (the fitted std factor and dof, the noise level), as the sweep's jobs build them (``sweep/jobs.py``), the
    pixel noise fitted in memory. ``spread_only``: the bare sampler (the samples' spread alone), no arguments."""
    from functools import partial

    from uncertsplat.data.dataset import load_view_set

    if spread_only:
        return loaded.sampler(scene.scene_scale, device), {}
    train_views = partial(load_view_set, scene, depth=False)
    residual = fit_residual(loaded.sampler(scene.scene_scale, device), scene.split.get("train", ()), cfg, device,
                            load_views=train_views, calibration_indices=scene.split.get("calibration", ()))
    sampler, fit = scored_sampler(partial(loaded.sampler, scene.scene_scale, device), residual, scene.cameras,
                                  scene.split, cfg, device, load_views=train_views)
    return sampler, {"std_scale": fit.scale, "calibration_views": fit.names, "dof": fit.dof,
                     "calibration_held_out": bool(scene.split.get("calibration")),
                     "noise_scale": residual.scale if residual is not None else None,
                     "notes": loaded.eval_notes(cfg.num_samples) + loaded.exposure_notes()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path)
    ap.add_argument("--label", default=None, help="results go to evaluate_<label>.json (default: the run's name)")
    ap.add_argument("--ks", type=int, nargs="+", default=[1, 5, 10, 20])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--depth-gt", type=Path, default=None, help="GT depth folder (reconstructed synthetic scenes)")
    ap.add_argument("--machine", default="2-core CPU, torch 2.13.0")
    ap.add_argument("--spread-only", action="store_true",
                    help="score the posterior samples' spread alone, not evaluate's full predictive (the script "
                         "before 2026-11-29)")
    add_overwrite_option(ap)
    args = ap.parse_args()
    label = args.label or args.run.name
    out = ROOT / "benchmarks" / "results" / f"evaluate_{label}.json"
    refuse_overwrite(out, overwrite=args.overwrite)

    from uncertsplat.baselines import load_run
    from uncertsplat.data.dataset import load_view_set

    device = torch.device("cpu")
    loaded = load_run(args.run, device)
    scene = loaded.load_scene()
    views = load_view_set(scene, scene.split["test"], depth_folder=args.depth_gt)
    predictive = ("the posterior samples' spread alone (--spread-only: no pixel noise, side terms or std factor)"
                  if args.spread_only else "evaluate's full predictive (samples' spread + pixel noise + "
                  "predictive_terms, std factor and dof fitted as evaluate fits them)")
    print(f"scoring {predictive}", flush=True)
    rows = []
    for k in args.ks:
        cfg = EvalConfig(num_samples=k, seed=args.seed)
        t0 = time.perf_counter()
        sampler, fitted = score_sampler(loaded, scene, cfg, device, spread_only=args.spread_only)
        calibration_seconds = time.perf_counter() - t0
        rep = evaluate_views(sampler, views, cfg, device, show_progress=False, **fitted)
        m = rep.mean
        rows.append({
            "K": k, "psnr": m.psnr, "ssim": m.ssim, "ause_mae": m.ause_mae, "ause_rmse": m.ause_rmse,
            "nll": m.nll, "nll_kde": m.nll_kde, "nll_calibrated": m.nll_calibrated, "spearman": m.spearman,
            "calibration_error": m.calibration_error, "calibration_error_calibrated": m.calibration_error_calibrated,
            "std_scale": rep.std_scale, "depth_ause_mae": m.depth_ause_mae,
            "seconds_per_view": rep.seconds_per_view, "calibration_seconds": calibration_seconds,
            "depth_scale": rep.depth_scale.model_dump() if rep.depth_scale else None,
        })
        print(f"K={k}: {rows[-1]}", flush=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({
        "run": str(args.run), "views": len(views), "gaussians": len(loaded.model) if hasattr(loaded, "model") else None,
        "machine": args.machine, "threads": torch.get_num_threads(), "omp": os.environ.get("OMP_NUM_THREADS"),
        "date": datetime.date.today().isoformat(), "predictive": predictive, "spread_only": args.spread_only,
        "rows": rows,
    }, indent=2) + "\n")

    def f(x, p=3):
        return "-" if x is None else f"{x:.{p}f}"

    print(f"\nScored: {predictive}.\n")
    print("| K | PSNR | SSIM | AUSE-MAE | AUSE-RMSE | NLL | NLL (KDE) | NLL rescaled | Spearman | cal. err | "
          "depth AUSE-MAE | s/view |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['K']} | {f(r['psnr'], 2)} | {f(r['ssim'])} | {f(r['ause_mae'])} | {f(r['ause_rmse'])} | "
              f"{f(r['nll'], 2)} | {f(r['nll_kde'], 2)} | {f(r['nll_calibrated'], 2)} | {f(r['spearman'])} | "
              f"{f(r['calibration_error'])} | {f(r['depth_ause_mae'])} | {f(r['seconds_per_view'], 2)} |")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
