"""The initial Gaussian scales of a large sparse cloud: the adaptive grid against the brute force it replaced.

``init_from_points`` gives each point the mean distance to its 3 nearest neighbours. Up to 16,384 points that is a
brute force (row blocks of ``cdist``); above, an adaptive grid (``uncertsplat.gaussians.neighbors``). This times
both on the same clouds in one run (the brute force only up to ``--brute-max`` points: it is quadratic) and checks
the grid against exact float64 distances for a sample of points.

The clouds imitate a large SfM reconstruction: a few surfaces at different distances (so densities differ by
about 30x), 2 % of the points in dense clumps (a textured patch seen by many photos), 0.1 % far points (sky,
mismatches) up to 1000x the scene's size.

    python benchmarks/bench_init.py --sizes 20000 50000 96000 200000 500000 1000000 --label cpu
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from datetime import date
from pathlib import Path

import torch

from benchmarks._common import RESULTS, add_overwrite_option, refuse_overwrite
from uncertsplat.gaussians import neighbors


def sfm_like_cloud(n: int, gen: torch.Generator) -> torch.Tensor:
    """[n,3] surfaces at distances 1, 3 and 10 (equal shares), 2 % in clumps, 0.1 % far points."""
    share = n // 3
    parts = []
    for i, dist in enumerate((1.0, 3.0, 10.0)):
        m = share if i < 2 else n - 2 * share
        uv = (torch.rand(m, 2, generator=gen) - 0.5) * dist
        z = dist + 0.1 * dist * torch.sin(3 * uv[:, 0] / dist) * torch.cos(2 * uv[:, 1] / dist)
        parts.append(torch.stack([uv[:, 0], uv[:, 1], z], 1))
    pts = torch.cat(parts)
    perm = torch.randperm(n, generator=gen)
    clump = perm[: n // 50]
    centres = pts[perm[:20]]
    pts[clump] = centres[torch.randint(0, 20, (clump.numel(),), generator=gen)] + \
        torch.randn(clump.numel(), 3, generator=gen) * 1e-3
    far = perm[n // 50: n // 50 + n // 1000]
    pts[far] = torch.randn(far.numel(), 3, generator=gen) * 1000
    return pts


def exact_sample(pts: torch.Tensor, idx: torch.Tensor, k: int = 3) -> torch.Tensor:
    """[S] exact float64 mean distance to the k nearest other points for the points ``idx``."""
    p = pts.double()
    out = []
    for s in range(0, idx.numel(), 256):
        d2 = torch.cdist(p[idx[s:s + 256]], p, compute_mode="donot_use_mm_for_euclid_dist").square()
        out.append(d2.topk(k + 1, largest=False).values[:, 1:].mean(1).sqrt())
    return torch.cat(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[20_000, 50_000, 96_000, 200_000, 500_000, 1_000_000])
    ap.add_argument("--brute-max", type=int, default=96_000, help="largest cloud also timed by brute force")
    ap.add_argument("--check", type=int, default=2000, help="points checked against exact float64 distances")
    ap.add_argument("--label", default="cpu")
    ap.add_argument("--out", type=Path, default=None)
    add_overwrite_option(ap)
    args = ap.parse_args()
    out_path = args.out or RESULTS / f"init_{args.label}.json"
    refuse_overwrite(out_path, overwrite=args.overwrite)

    rows = []
    for n in args.sizes:
        gen = torch.Generator().manual_seed(n)
        pts = sfm_like_cloud(n, gen)
        t = time.perf_counter()
        grid = neighbors._grid_mean_sq(pts, 3).clamp_min(0).sqrt()
        t_grid = time.perf_counter() - t
        check = torch.randperm(n, generator=gen)[: args.check]
        ref = exact_sample(pts, check)
        rel = float(((grid[check].double() - ref).abs() / ref.clamp_min(1e-300)).max())
        row = {"points": n, "grid_s": round(t_grid, 3), "grid_max_rel_error": rel}
        if n <= args.brute_max:
            every = torch.arange(n)
            t = time.perf_counter()
            brute = neighbors._brute_mean_sq(pts, every, 3).clamp_min(0).sqrt()
            row["brute_s"] = round(time.perf_counter() - t, 3)
            row["grid_over_brute"] = round(t_grid / row["brute_s"], 4)
            row["brute_max_rel_error"] = float(((brute[check].double() - ref).abs() / ref.clamp_min(1e-300)).max())
        rows.append(row)
        print(json.dumps(row), flush=True)

    result = {"machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
              "torch_threads": torch.get_num_threads(), "date": str(date.today()), "rows": rows}
    out_path.parent.mkdir(parents=True, exist_ok=True)
    out_path.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {out_path}")


if __name__ == "__main__":
    main()
