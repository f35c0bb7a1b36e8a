"""Time one optimiser step: dense fused Adam against the sparse updates, by the fraction of rows a view touches.

The per-Gaussian tensors of a model of N Gaussians at SH degree 3 (means 3, scales 3, quats 4, opacity 1, SH DC 3,
SH rest 45: 59 numbers per Gaussian), random gradients; the touched rows a random subset (sorted, as
``Trainer.touched_rows`` gives them) of each fraction. Every case times ``torch.optim.Adam(fused=True)`` (what
``sparse_updates = "dense"`` runs) and ``train.adam.Adam`` (visible and lazy) in the same process, median of
``--repeats`` timings of ``--steps`` steps, and reports sparse / dense.

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/bench_sparse_adam.py --gaussians 60000 400000

Writes ``benchmarks/results/sparse_adam.json`` and prints the Markdown rows for BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from datetime import date
from pathlib import Path

import torch
from torch import nn

from uncertsplat import native
from uncertsplat.train.adam import Adam

RESULTS = Path(__file__).resolve().parents[1] / "benchmarks" / "results"
WIDTHS = {"means": (3,), "scales": (3,), "quats": (4,), "opacities": (), "sh0": (1, 3), "shN": (15, 3)}


def time_steps(opt, rows, steps: int, repeats: int) -> float:
    """Median milliseconds per step."""
    for _ in range(2):
        opt.step() if rows is None else opt.step(rows=rows)
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(steps):
            opt.step() if rows is None else opt.step(rows=rows)
        out.append((time.perf_counter() - t0) / steps * 1e3)
    return statistics.median(out)


def case(n: int, fraction: float, steps: int, repeats: int, seed: int = 0) -> dict:
    g = torch.Generator().manual_seed(seed)
    touched = torch.randperm(n, generator=g)[: max(1, int(round(fraction * n)))].sort().values

    def params():
        ps = {k: nn.Parameter(torch.randn((n, *w), generator=torch.Generator().manual_seed(1))) for k, w in WIDTHS.items()}
        for p in ps.values():
            p.grad = torch.randn(p.shape, generator=torch.Generator().manual_seed(2))
        return ps, [{"params": [p], "lr": 1e-3, "name": k} for k, p in ps.items()]

    _, groups = params()
    result = {"gaussians": n, "fraction": fraction,
              "dense_ms": time_steps(torch.optim.Adam(groups, eps=1e-15, fused=True), None, steps, repeats)}
    rows = dict.fromkeys(WIDTHS, touched)
    for mode in ("visible", "lazy"):
        _, groups = params()
        result[f"{mode}_ms"] = time_steps(Adam(groups, eps=1e-15, lazy=mode == "lazy"), rows, steps, repeats)
        result[f"{mode}_ratio"] = result[f"{mode}_ms"] / result["dense_ms"]
    return result


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gaussians", type=int, nargs="+", default=[60000])
    ap.add_argument("--fractions", type=float, nargs="+", default=[1.0, 0.8, 0.5, 0.2, 0.05])
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--machine", default=None)
    args = ap.parse_args()
    rows = [case(n, f, args.steps, args.repeats) for n in args.gaussians for f in args.fractions]
    result = {"cases": rows, "kernels": native.describe("cpu"), "threads": torch.get_num_threads(),
              "machine": args.machine or platform.processor() or platform.machine(), "torch": torch.__version__,
              "date": date.today().isoformat()}
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "sparse_adam.json").write_text(json.dumps(result, indent=2) + "\n")
    print("| Gaussians | rows touched | dense fused Adam ms | visible ms (ratio) | lazy ms (ratio) |")
    for r in rows:
        print(f"| {r['gaussians']:,} | {r['fraction']:.0%} | {r['dense_ms']:.2f} | {r['visible_ms']:.2f} "
              f"(x{r['visible_ratio']:.2f}) | {r['lazy_ms']:.2f} (x{r['lazy_ratio']:.2f}) |")


if __name__ == "__main__":
    main()
