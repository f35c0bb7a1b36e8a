"""Where an NLL gap between two methods comes from: each method's mean scored with each method's std.

Evaluates the runs ``bench_unseen.py`` trained under ``--out`` (``--methods``, the full predictive, K = 10) on their
held-out views and scores the Student-t NLL of every (mean of A, std of B) pair with one nu for all pairs
(``--dof``), on every pixel, on the pixels some training view saw and on the others (GT depth labels). A method's
own pair repeats its NLL (up to the shared nu); the rows with another method's mean show how much of a gap the mean
makes, the columns how much the std does. Also the best single factor for each method's own std (a factor fitted on
the test views themselves: an upper bound for any recalibration) and the RMSE of each mean::

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/bench_unseen.py --protocol sparse \
        --methods variational ensemble-3 vensemble-2x0.75 --predictives full --out /tmp/sparse
    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/bench_nll_swap.py --out /tmp/sparse \
        --methods variational ensemble-3 vensemble-2x0.75 --label sparse

Writes ``benchmarks/results/nll_swap_<label>.json`` and prints the Markdown table for BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import torch
from _common import add_overwrite_option, refuse_overwrite

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_unseen import evaluate_run, observed  # noqa: E402

FACTORS = (0.5, 0.6, 0.7, 0.8, 0.9, 1.0, 1.1, 1.25, 1.5, 2.0)


def main() -> None:
    from uncertsplat.config import EvalConfig
    from uncertsplat.eval.tails import nll

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True, help="bench_unseen.py's --out (its run folders)")
    ap.add_argument("--methods", nargs="+", required=True)
    ap.add_argument("--dof", type=float, default=3.5, help="nu of the Student-t for every pair")
    ap.add_argument("--samples", type=int, default=10)
    ap.add_argument("--label", default="sparse", help="results go to nll_swap_<label>.json")
    ap.add_argument("--machine", default=platform.processor() or platform.machine())
    add_overwrite_option(ap)
    args = ap.parse_args()
    path = Path(__file__).resolve().parent / "results" / f"nll_swap_{args.label}.json"
    refuse_overwrite(path, overwrite=args.overwrite)
    device = torch.device("cpu")
    runs = {m: evaluate_run(args.out / m, device, EvalConfig(num_samples=args.samples)) for m in args.methods}
    first = runs[args.methods[0]]
    gt = first["views"].images  # [V,H,W,3]
    if any(r["test"] != first["test"] for r in runs.values()):
        raise SystemExit("the runs were tested on different views: train them with one protocol and seed")

    def stacked(run: dict, key: str) -> torch.Tensor:  # [V,H,W,3]
        return torch.stack([getattr(m, key).cpu().reshape(gt.shape[1:]) for m in run["maps"]])

    mean = {m: stacked(r, "rgb_mean").clamp(0, 1) for m, r in runs.items()}
    std = {m: stacked(r, "rgb_std") for m, r in runs.items()}
    seen = torch.stack([observed(first, j)[0] for j in range(gt.shape[0])])[..., None].expand_as(gt)  # [V,H,W,3]
    pairs = []
    for a in args.methods:
        for b in args.methods:
            v = nll(gt, mean[a], std[b], args.dof)
            pairs.append({"mean": a, "std": b, "nll": float(v.mean()), "nll_seen": float(v[seen].mean()),
                          "nll_unseen": float(v[~seen].mean()) if (~seen).any() else None})
    own = {}
    for m in args.methods:
        best = min((float(nll(gt, mean[m], std[m] * f, args.dof).mean()), f) for f in FACTORS)
        own[m] = {"rmse": float((gt - mean[m]).square().mean().sqrt()), "report_nll": runs[m]["report"].mean.nll,
                  "best_factor_on_test": best[1], "nll_at_best_factor": best[0]}
    out = {"label": args.label, "machine": args.machine, "date": time.strftime("%Y-%m-%d"), "dof": args.dof,
           "samples": args.samples, "methods": args.methods, "pairs": pairs, "own": own}
    path.write_text(json.dumps(out, indent=1))
    print("| mean of | std of | NLL | seen / unseen pixels |\n|---|---|---|---|")
    for p in pairs:
        unseen = f"{p['nll_unseen']:.2f}" if p["nll_unseen"] is not None else "-"
        print(f"| {p['mean']} | {p['std']} | {p['nll']:.3f} | {p['nll_seen']:.3f} / {unseen} |")
    for m, o in own.items():
        print(f"{m}: RMSE {o['rmse']:.4f}, NLL in the report {o['report_nll']:.3f}, best factor on the test views "
              f"x{o['best_factor_on_test']} -> {o['nll_at_best_factor']:.3f}")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
