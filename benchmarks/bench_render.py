"""Rasterizer benchmark: forward and forward+backward time and peak memory on random scenes.

Scene: N Gaussians (seeded) uniformly inside the view frustum of a pinhole camera at depths 2..8,
log-uniform scales 0.005..0.05, opacities 0.1..0.9, random rotations, SH degree 3. Loss: L1 to a random
target image, gradients to all parameters. Medians over ``--repeats`` runs after one warm-up.
Every case is timed with both compositors in the same run: ``native`` (the CPU kernels of
``uncertsplat.native``, the default on CPU) and ``torch`` (the PyTorch blocks, the reference), and the
ratio is reported. The dense float64 oracle (tests/reference/naive_render.py) is timed at the smallest size.

    .venv/bin/python benchmarks/bench_render.py --label NAME   # full table: results/render_cpu_2thread-NAME.json
    .venv/bin/python benchmarks/bench_render.py --quick        # one size, for profiling: results/render_quick.json

Writes ``OUT/render_{device}_{threads}thread[-LABEL].json`` (``render_quick[-LABEL].json`` with ``--quick``;
``--out``: the folder, default ``benchmarks/results``) and prints the Markdown rows for BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from dataclasses import replace
from datetime import date
from pathlib import Path

import torch
from _common import add_overwrite_option, refuse_overwrite

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from uncertsplat.render import render  # noqa: E402
from uncertsplat.types import Cameras, GaussianSample  # noqa: E402

PARAMS = ("means", "quats", "scales", "opacities", "sh")
ORACLE_CASE = (2_000, 128, 128)  # N, width, height


def make_scene(n: int, width: int, height: int, seed: int = 0, device="cpu"):
    g = torch.Generator().manual_seed(seed)
    f = 0.9 * width
    z = torch.rand(n, generator=g) * 6 + 2
    x = (torch.rand(n, generator=g) - 0.5) * width / f * z
    y = (torch.rand(n, generator=g) - 0.5) * height / f * z
    means = torch.stack([x, y, z], -1)
    quats = torch.randn(n, 4, generator=g)
    scales = torch.exp(torch.rand(n, 3, generator=g) * math.log(10) + math.log(0.005))
    opac = torch.rand(n, generator=g) * 0.8 + 0.1
    sh = torch.randn(n, 16, 3, generator=g) * 0.2
    s = GaussianSample(means, quats, scales, opac, sh, 3).to(device=device)
    K = torch.tensor([[[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]]])
    cams = Cameras(torch.eye(4)[None], K, width, height).to(device=device)
    return s, cams


def _sync(device):
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()


def time_fn(fn, repeats: int, device, warmup: bool = True) -> tuple[list[float], list[float]]:
    """(wall times, process CPU times) in seconds. On a shared machine the CPU time of a 1-thread run is
    the stable number (wall time also counts the time the process waited for a core)."""
    if warmup:
        fn()
    wall, cpu = [], []
    for _ in range(repeats):
        _sync(device)
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        _sync(device)
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return wall, cpu


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def bench_case(n, width, height, repeats, device, compile=False, renderer=None, warmup=True, **kw):
    s, cams = make_scene(n, width, height, device=device)
    base_mem = peak_rss_mb()
    target = torch.rand(1, height, width, 3, generator=torch.Generator().manual_seed(1)).to(device)
    leaves = {k: getattr(s, k).detach().clone().requires_grad_() for k in PARAMS}
    sg = replace(s, **leaves)
    rfn = renderer or (lambda s_, c_: render(s_, c_, compile=compile, **kw))

    def fwd():
        with torch.no_grad():
            rfn(s, cams)

    def fwd_bwd():
        for v in leaves.values():
            v.grad = None
        out = rfn(sg, cams)
        rgb = out["rgb"] if isinstance(out, dict) else out.rgb
        (rgb - target).abs().mean().backward()

    if torch.device(device).type == "cuda":
        torch.cuda.reset_peak_memory_stats()
    t_f, c_f = time_fn(fwd, repeats, device, warmup)
    t_fb, c_fb = time_fn(fwd_bwd, repeats, device, warmup)
    mem = torch.cuda.max_memory_allocated() / 2**20 if torch.device(device).type == "cuda" else peak_rss_mb()
    with torch.no_grad():
        o = render(s, cams)
        pairs_visible = int((o.radii > 0).sum())
        coverage = float(o.alpha.mean())
    return {
        "n": n,
        "width": width,
        "height": height,
        "fwd_ms": 1e3 * statistics.median(t_f),
        "fwd_bwd_ms": 1e3 * statistics.median(t_fb),
        "fwd_cpu_ms": 1e3 * statistics.median(c_f),
        "fwd_bwd_cpu_ms": 1e3 * statistics.median(c_fb),
        "fwd_runs_ms": [round(1e3 * t, 2) for t in t_f],
        "fwd_bwd_runs_ms": [round(1e3 * t, 2) for t in t_fb],
        "peak_mem_mb": mem,
        "baseline_mem_mb": base_mem if torch.device(device).type == "cpu" else 0.0,
        "visible_gaussians": pairs_visible,
        "mean_alpha": coverage,
    }


def run_case_subprocess(args, n, w, h, mode) -> dict:
    """One case per process, so that the peak memory is that case's own."""
    cmd = [
        sys.executable,
        __file__,
        "--case",
        str(n),
        str(w),
        str(h),
        mode,
        "--threads",
        str(args.threads),
        "--repeats",
        str(args.repeats),
        "--device",
        args.device,
    ]
    res = subprocess.run(cmd, check=True, capture_output=True, text=True)
    return json.loads(res.stdout.strip().splitlines()[-1])


def one_case(args):
    n, w, h = (int(v) for v in args.case[:3])
    mode = args.case[3]
    torch.set_num_threads(args.threads)
    if mode == "oracle":
        from tests.reference.naive_render import naive_render

        r = bench_case(
            n,
            w,
            h,
            1,
            args.device,
            warmup=False,
            renderer=lambda s_, c_: naive_render(s_, c_, pixel_chunk=1024),
        )
    elif mode == "compile":
        r = bench_case(n, w, h, args.repeats, args.device, compile=True, backend="torch")
    else:  # "native" or "torch"
        r = bench_case(n, w, h, args.repeats, args.device, backend=mode)
    r["mode"] = mode
    print(json.dumps(r))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--case", nargs=4, help=argparse.SUPPRESS)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--quick", action="store_true", help="only 512x384 / 50k")
    ap.add_argument("--compile", action="store_true", help="also time the torch.compile path")
    ap.add_argument("--no-oracle", action="store_true")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results"),
                    help="the folder of the results file (not the file: see --label)")
    ap.add_argument("--label", default=None, help="appended to the results file's name: render_cpu_2thread-LABEL.json")
    add_overwrite_option(ap)
    args = ap.parse_args()
    if args.case:
        return one_case(args)
    out = Path(args.out)
    if out.suffix == ".json":  # the file's name was given: its folder would be named *.json
        ap.error(f"--out is the folder of the results file, not the file ({args.out}); name the file with --label")
    name = "render_quick" if args.quick else f"render_{args.device}_{args.threads}thread"
    path = out / (f"{name}-{args.label}.json" if args.label else f"{name}.json")
    refuse_overwrite(path, overwrite=args.overwrite)
    load_start = os.getloadavg()
    print(f"load average at start: {load_start}", flush=True)

    sizes = [(256, 256), (512, 384)]
    ns = [5_000, 20_000, 50_000]
    cases = [(50_000, 512, 384)] if args.quick else [(n, w, h) for (w, h) in sizes for n in ns]
    modes = ["native", "torch"] if args.device == "cpu" else ["torch"]
    rows = []
    for n, w, h in cases:
        for mode in modes:
            r = run_case_subprocess(args, n, w, h, mode)
            rows.append(r)
            print(
                f"{mode:7s} {w}x{h} N={n:>6}: fwd {r['fwd_ms']:8.1f} ms  fwd+bwd {r['fwd_bwd_ms']:8.1f} ms  "
                f"(CPU time {r['fwd_cpu_ms']:.1f} / {r['fwd_bwd_cpu_ms']:.1f} ms)",
                flush=True,
            )
        if len(modes) == 2:
            nat, ref = rows[-2], rows[-1]
            nat["speedup_fwd_vs_torch"] = ref["fwd_ms"] / nat["fwd_ms"]
            nat["speedup_fwd_bwd_vs_torch"] = ref["fwd_bwd_ms"] / nat["fwd_bwd_ms"]
            print(f"        native vs torch: x{nat['speedup_fwd_vs_torch']:.2f} fwd, "
                  f"x{nat['speedup_fwd_bwd_vs_torch']:.2f} fwd+bwd", flush=True)
        if args.compile:
            rc = run_case_subprocess(args, n, w, h, "compile")
            rows.append(rc)
            print(
                f"compile {w}x{h} N={n:>6}: fwd {rc['fwd_ms']:8.1f} ms  fwd+bwd {rc['fwd_bwd_ms']:8.1f} ms",
                flush=True,
            )

    oracle = None
    if not args.no_oracle and not args.quick:
        # The dense oracle evaluates every Gaussian at every pixel in float64 (minutes at 256x256/5k on
        # 2 cores), so it is compared with ours on a smaller scene, both measured in this run.
        n, w, h = ORACLE_CASE
        ours = run_case_subprocess(args, n, w, h, modes[0])
        o = run_case_subprocess(args, n, w, h, "oracle")
        o["ours_fwd_ms"] = ours["fwd_ms"]
        o["ours_fwd_bwd_ms"] = ours["fwd_bwd_ms"]
        o["ratio_fwd"] = o["fwd_ms"] / ours["fwd_ms"]
        o["ratio_fwd_bwd"] = o["fwd_bwd_ms"] / ours["fwd_bwd_ms"]
        oracle = o
        rows.append(ours)
        print(
            f"oracle  {w}x{h} N={n:>6}: fwd {o['fwd_ms']:8.1f} ms  fwd+bwd {o['fwd_bwd_ms']:8.1f} ms "
            f"(x{o['ratio_fwd']:.0f} / x{o['ratio_fwd_bwd']:.0f} slower than ours)"
        )

    result = {
        "date": date.today().isoformat(),
        "torch": torch.__version__,
        "threads": args.threads,
        "device": args.device,
        "machine": platform.processor() or platform.machine(),
        "repeats": args.repeats,
        "rows": rows,
        "oracle": oracle,
        "note": "CPU: peak_mem_mb is the peak RSS of the process running that case alone (baseline_mem_mb: "
        "after importing torch and building the scene); CUDA: max_memory_allocated",
        "load_average_start": load_start,
        "load_average_end": os.getloadavg(),
    }
    out.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=2))
    print(f"wrote {path}")
    print("\n| mode | image | N | fwd ms | fwd+bwd ms | fwd CPU ms | fwd+bwd CPU ms | peak MB | fwd+bwd vs torch |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows + ([oracle] if oracle else []):
        ratio = f"x{r['speedup_fwd_bwd_vs_torch']:.2f}" if "speedup_fwd_bwd_vs_torch" in r else ""
        print(
            f"| {r['mode']} | {r['width']}x{r['height']} | {r['n']} | {r['fwd_ms']:.1f} | {r['fwd_bwd_ms']:.1f} "
            f"| {r['fwd_cpu_ms']:.1f} | {r['fwd_bwd_cpu_ms']:.1f} | {r['peak_mem_mb']:.0f} | {ratio} |"
        )


if __name__ == "__main__":
    main()
