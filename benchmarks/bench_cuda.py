"""The PyTorch rasterizer on a GPU: render fwd+bwd time against the compositor's block size and the tile size.

On a GPU the PyTorch compositor's cost is mostly kernel launches (a few dozen per block of tiles), so the
block size that suits a CPU's caches leaves the device idle. Per (tile size, block size) this prints and
writes the fwd+bwd time (min and median), the GPU's busy time and the number of kernel launches in one
step (torch.profiler), and the peak memory. ``block = default`` is ``default_block_elements(device)``.

    python benchmarks/bench_cuda.py --device cuda
    python benchmarks/bench_cuda.py --device cpu --cases 128x96/2000   # a dry run of the script itself
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from datetime import date
from pathlib import Path

import torch
from torch.profiler import ProfilerActivity, profile

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from _common import add_overwrite_option, refuse_overwrite  # noqa: E402
from bench_render import PARAMS, make_scene  # noqa: E402

from uncertsplat.render import render  # noqa: E402


def _case(spec: str) -> tuple[int, int, int]:
    size, n = spec.split("/")
    w, h = size.split("x")
    return int(n), int(w), int(h)


def time_case(n, w, h, tile, block, device, repeats):
    s, cams = make_scene(n, w, h, device=device)
    leaves = {k: getattr(s, k).detach().clone().requires_grad_() for k in PARAMS}
    sg = replace(s, **leaves)
    target = torch.rand(1, h, w, 3, generator=torch.Generator().manual_seed(1)).to(device)
    cuda = device.type == "cuda"

    def sync():
        if cuda:
            torch.cuda.synchronize(device)

    def step():
        for v in leaves.values():
            v.grad = None
        out = render(sg, cams, tile_size=tile, block_elements=block)
        (out.rgb - target).abs().mean().backward()

    step()
    step()
    sync()
    if cuda:
        torch.cuda.reset_peak_memory_stats(device)
    times = []
    for _ in range(repeats):
        sync()
        t0 = time.perf_counter()
        step()
        sync()
        times.append(time.perf_counter() - t0)
    times.sort()
    peak = torch.cuda.max_memory_allocated(device) / 2**20 if cuda else 0.0
    with profile(activities=[ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])) as prof:
        step()
        sync()
    events = prof.key_averages()
    return {
        "case": f"{w}x{h}/{n}",
        "tile": tile,
        "block": block or "default",
        "min_ms": round(1e3 * times[0], 1),
        "median_ms": round(1e3 * times[len(times) // 2], 1),
        "gpu_busy_ms": round(sum(e.self_device_time_total for e in events) / 1e3, 1),
        "launches": sum(e.count for e in events if "LaunchKernel" in e.key),
        "peak_mb": round(peak),
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--cases", nargs="+", default=["512x384/50000", "1920x1080/500000"], help="WxH/N")
    ap.add_argument("--tiles", nargs="+", type=int, default=[8, 16])
    ap.add_argument("--blocks", nargs="+", default=["131072", "1048576", "default", "16777216"])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "cuda_blocks.json")
    add_overwrite_option(ap)
    args = ap.parse_args()
    refuse_overwrite(args.out, overwrite=args.overwrite)
    device = torch.device(args.device)
    rows = []
    meta = {"date": str(date.today()), "torch": torch.__version__, "device": str(device),
            "gpu": torch.cuda.get_device_name(device) if device.type == "cuda" else None}
    for spec in args.cases:
        n, w, h = _case(spec)
        for tile in args.tiles:
            for b in args.blocks:
                block = None if b == "default" else int(b)
                try:
                    row = time_case(n, w, h, tile, block, device, args.repeats)
                except (RuntimeError, MemoryError) as err:  # e.g. out of GPU memory: record it, go on
                    row = {"case": spec, "tile": tile, "block": b, "error": repr(err)[:300]}
                print(row, flush=True)
                rows.append(row)
                args.out.parent.mkdir(parents=True, exist_ok=True)
                args.out.write_text(json.dumps({**meta, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
