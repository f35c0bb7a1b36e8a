"""Time one optimiser step: dense fused Adam against the sparse updates, by the fraction of rows a view touches;
and the dense step as training runs it, torch's fused Adam against ours in one native call.

The per-Gaussian tensors of a model of N Gaussians at SH degree 3 (means 3, scales 3, quats 4, opacity 1, SH DC 3,
SH rest 45: 59 numbers per Gaussian), random gradients; the touched rows a random subset (sorted, as
``Trainer.touched_rows`` gives them) of each fraction. Every case times ``torch.optim.Adam(fused=True)`` (what
``sparse_updates = "dense"`` ran before the native dense step) and ``train.adam.Adam`` (visible and lazy) in the same
process, median of ``--repeats`` timings of ``--steps`` steps, and reports sparse / dense.

The dense cases (``dense``) time, with torch's ops on one thread as ``Trainer.train_step`` runs them, torch's fused
Adam after the NaN/Inf check the trainer made for it (a sum per gradient) against ``Adam.step_if_finite`` (one native
call for every group, the check inside: what the default training runs on a CPU), once with every number live and
once with the SH rest's gradients and moments all zero (SH bands not switched on yet, which the native step skips).

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/bench_sparse_adam.py --gaussians 60000 400000

Writes ``--out`` (default ``benchmarks/results/sparse_adam.json``) and prints the Markdown rows for BENCHMARKS.md.
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
from _common import add_overwrite_option, refuse_overwrite
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


def dense_case(n: int, steps: int, repeats: int) -> dict:
    """Torch's fused Adam (with the trainer's former check) against ours, every number live and the SH rest inert."""
    from uncertsplat.train.adam import all_finite

    out: dict = {"gaussians": n}
    for inert in (False, True):
        times: dict[str, list[float]] = {"torch": [], "native": []}
        opts = {}
        for name in times:
            ps = {k: nn.Parameter(torch.randn((n, *w), generator=torch.Generator().manual_seed(1)))
                  for k, w in WIDTHS.items()}
            for k, p in ps.items():
                zero = inert and k == "shN"
                p.grad = torch.zeros_like(p) if zero else torch.randn(p.shape, generator=torch.Generator().manual_seed(2))
            groups = [{"params": [p], "lr": 1e-3, "name": k} for k, p in ps.items()]
            if name == "torch":
                opt = torch.optim.Adam(groups, eps=1e-15, fused=True)

                def step(opt=opt, ps=ps):
                    if all_finite(p.grad for p in ps.values()):
                        opt.step()
            else:
                opt = Adam(groups, eps=1e-15)
                step = opt.step_if_finite
            opts[name] = step
        with native.single_threaded_torch("cpu"):
            for _ in range(2):
                for step in opts.values():
                    step()
            for _ in range(repeats):  # alternating, so that the machine's drift falls on both
                for name, step in opts.items():
                    t0 = time.perf_counter()
                    for _ in range(steps):
                        step()
                    times[name].append((time.perf_counter() - t0) / steps * 1e3)
        key = "sh_off_" if inert else ""
        for name, v in times.items():
            out[f"{key}{name}_ms"] = statistics.median(v)
        out[f"{key}ratio"] = out[f"{key}native_ms"] / out[f"{key}torch_ms"]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gaussians", type=int, nargs="+", default=[60000])
    ap.add_argument("--fractions", type=float, nargs="+", default=[1.0, 0.8, 0.5, 0.2, 0.05])
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--machine", default=None)
    ap.add_argument("--out", type=Path, default=RESULTS / "sparse_adam.json", help="the results file")
    add_overwrite_option(ap)
    args = ap.parse_args()
    refuse_overwrite(args.out, overwrite=args.overwrite)
    rows = [case(n, f, args.steps, args.repeats) for n in args.gaussians for f in args.fractions]
    dense = [dense_case(n, args.steps, args.repeats) for n in args.gaussians]
    result = {"cases": rows, "dense": dense, "kernels": native.describe("cpu"), "threads": torch.get_num_threads(),
              "machine": args.machine or platform.processor() or platform.machine(), "torch": torch.__version__,
              "date": date.today().isoformat()}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print("| Gaussians | rows touched | dense fused Adam ms | visible ms (ratio) | lazy ms (ratio) |")
    print("|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['gaussians']:,} | {r['fraction']:.0%} | {r['dense_ms']:.2f} | {r['visible_ms']:.2f} "
              f"(x{r['visible_ratio']:.2f}) | {r['lazy_ms']:.2f} (x{r['lazy_ratio']:.2f}) |")
    print("\n| Gaussians | torch fused Adam + check ms | one native call ms (ratio) | SH rest inert: torch ms | "
          "native ms (ratio) |")
    print("|---|---|---|---|---|")
    for r in dense:
        print(f"| {r['gaussians']:,} | {r['torch_ms']:.2f} | {r['native_ms']:.2f} (x{r['ratio']:.2f}) | "
              f"{r['sh_off_torch_ms']:.2f} | {r['sh_off_native_ms']:.2f} (x{r['sh_off_ratio']:.2f}) |")


if __name__ == "__main__":
    main()
