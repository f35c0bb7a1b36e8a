"""The expected render's per-view peak factor: one projection instead of two.

A sample with ``position_var`` (the expected render that training fits and ``train`` reports) is drawn with
covariance Sigma + v I and its opacity lowered per view by sqrt(det Sigma2d / det Sigma2d'). The sharp Sigma2d
used to come from a second projection of every Gaussian; ``render._blur_log_peak`` now gets it from the blurred
one as Sigma2d' - v J J^T. This times ``render`` forward + backward (L1 loss, gradients to every parameter) of
``bench_render.make_scene``'s random scene with a position variance, with the current factor and with the
two-projection reference below, alternating in one process, and checks that both give the same images.

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/bench_expected_render.py [--n 40000 --width 320 --height 240]

Writes ``benchmarks/results/expected_render.json``.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import time
from dataclasses import replace
from datetime import date
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_render import make_scene  # noqa: E402

from uncertsplat.render import render  # noqa: E402
from uncertsplat.render.project import project_gaussians  # noqa: E402

RENDER_MODULE = sys.modules["uncertsplat.render.render"]


def two_projection_log_peak(sample, blurred_conics, cam_from_world, K, W, H, near, far, eps2d):
    """The reference: project the sharp Gaussians a second time and take the conics' determinant ratio."""
    sharp = project_gaussians(sample.means, sample.quats, sample.scales, sample.opacities, cam_from_world, K, W, H,
                              near, far, eps2d)
    tiny = torch.finfo(blurred_conics.dtype).tiny

    def log_det(conics):
        a, b, c = conics.unbind(-1)
        return torch.log((a * c - b * b).clamp_min(tiny))

    return (0.5 * (log_det(blurred_conics) - log_det(sharp.conics))).clamp_max(0.0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=40_000)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--machine", default=platform.processor() or platform.machine())
    args = ap.parse_args()
    sample, cams = make_scene(args.n, args.width, args.height)
    g = torch.Generator().manual_seed(1)
    # position spreads of 0-60 % of a Gaussian's size, as the informed posterior gives
    var = (torch.rand(args.n, generator=g) * 0.6 * sample.scales.mean(-1)).square()
    sample = replace(sample, sh=sample.sh[:, :1], sh_degree=0, position_var=var)
    target = torch.rand(1, args.height, args.width, 3, generator=g)
    current = RENDER_MODULE._blur_log_peak
    variants = {"one projection (current)": current, "two projections (reference)": two_projection_log_peak}

    def run(fn):
        RENDER_MODULE._blur_log_peak = fn
        leaves = {k: getattr(sample, k).detach().clone().requires_grad_() for k in ("means", "quats", "scales",
                                                                                    "opacities", "sh")}
        out = render(replace(sample, **leaves), cams)
        (out.rgb - target).abs().mean().backward()
        return out.rgb.detach(), leaves["means"].grad

    try:
        images = {name: run(fn) for name, fn in variants.items()}
        times: dict[str, list[float]] = {name: [] for name in variants}
        for _ in range(args.repeats):
            for name, fn in variants.items():
                t0 = time.perf_counter()
                run(fn)
                times[name].append(time.perf_counter() - t0)
    finally:
        RENDER_MODULE._blur_log_peak = current
    (a, ga), (b, gb) = images.values()
    med = {name: statistics.median(v) for name, v in times.items()}
    ref = med["two projections (reference)"]
    result = {"n": args.n, "width": args.width, "height": args.height, "repeats": args.repeats,
              "median_ms": {k: v * 1e3 for k, v in med.items()}, "min_ms": {k: min(v) * 1e3 for k, v in times.items()},
              "ratio": med["one projection (current)"] / ref,
              "max_abs_rgb_difference": float((a - b).abs().max()),
              "means_grad_relative_difference": float((ga - gb).norm() / gb.norm()),
              "machine": args.machine, "threads": torch.get_num_threads(), "torch": torch.__version__,
              "date": date.today().isoformat()}
    path = ROOT / "benchmarks" / "results" / "expected_render.json"
    path.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))
    print(f"| {args.n:,} Gaussians, {args.width}x{args.height} | {med['two projections (reference)'] * 1e3:.1f} ms | "
          f"{med['one projection (current)'] * 1e3:.1f} ms | x{result['ratio']:.2f} | "
          f"{result['max_abs_rgb_difference']:.1e} | {args.machine} | {result['date']} |")


if __name__ == "__main__":
    main()
