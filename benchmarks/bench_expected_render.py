"""The expected render's per-view peak factor: one projection instead of two.

A sample with ``position_var`` (the expected render that training fits and ``train`` reports) is drawn with
covariance Sigma + v I and its opacity lowered per view by sqrt(det Sigma2d / det Sigma2d'). The sharp Sigma2d
used to come from a second projection of every Gaussian; ``render._blur_log_peak`` now gets it from the blurred
one as Sigma2d' - v J J^T. This times ``render`` forward + backward (L1 loss, gradients to every parameter) of
``bench_render.make_scene``'s random scene with a position variance, alternating in one process, with three
peak factors in place of ``render.blur_log_peak`` (the dispatcher ``render`` calls): the current one (on CPU
float32 the native kernel ``_NativeBlurPeak``, else ``_blur_log_peak``), ``_blur_log_peak`` (the one-projection
PyTorch code), and the two-projection reference below; and checks that they give the same images. Each path counts
its calls: the table names the path the current variant took, and a variant that ran the same code as the current
one (no native kernels: both are ``_blur_log_peak``) is reported as "same path", without a ratio between them.

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/bench_expected_render.py [--n 40000 --width 320 --height 240]

Writes ``--out`` (default ``benchmarks/results/expected_render.json``; an existing file only with ``--overwrite``).
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import time
from collections import Counter
from dataclasses import replace
from datetime import date
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from _common import add_overwrite_option, refuse_overwrite  # noqa: E402
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
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "expected_render.json",
                    help="the results file")
    add_overwrite_option(ap)
    args = ap.parse_args()
    refuse_overwrite(args.out, overwrite=args.overwrite)
    sample, cams = make_scene(args.n, args.width, args.height)
    g = torch.Generator().manual_seed(1)
    # position spreads of 0-60 % of a Gaussian's size, as the informed posterior gives
    var = (torch.rand(args.n, generator=g) * 0.6 * sample.scales.mean(-1)).square()
    sample = replace(sample, sh=sample.sh[:, :1], sh_degree=0, position_var=var)
    target = torch.rand(1, args.height, args.width, 3, generator=g)

    # ``render`` calls the module's ``blur_log_peak``, which sends CPU float32 to the native kernel
    # (``_NativeBlurPeak``) and the rest to ``_blur_log_peak``. Each variant replaces that dispatcher, and every
    # path counts its calls, so the table says which code each variant really ran.
    dispatch, torch_peak, native_peak = (RENDER_MODULE.blur_log_peak, RENDER_MODULE._blur_log_peak,
                                         RENDER_MODULE._NativeBlurPeak)
    calls: Counter[str] = Counter()

    def counted_torch_peak(*a, **kw):
        calls["torch one projection (_blur_log_peak)"] += 1
        return torch_peak(*a, **kw)

    class CountedNativePeak:
        @staticmethod
        def apply(*a):
            calls["native one projection (_NativeBlurPeak)"] += 1
            return native_peak.apply(*a)

    def two_projections(sample, blurred_conics, cam_from_world, K, W, H, near, far, eps2d, backend=None):
        calls["two projections (reference)"] += 1
        return two_projection_log_peak(sample, blurred_conics, cam_from_world, K, W, H, near, far, eps2d)

    def torch_one_projection(sample, blurred_conics, cam_from_world, K, W, H, near, far, eps2d, backend=None):
        return RENDER_MODULE._blur_log_peak(sample, blurred_conics, cam_from_world, K, W, H, near, far, eps2d)

    variants = {"one projection (current)": dispatch, "one projection, PyTorch": torch_one_projection,
                "two projections (reference)": two_projections}

    def run(fn):
        RENDER_MODULE.blur_log_peak = fn
        leaves = {k: getattr(sample, k).detach().clone().requires_grad_() for k in ("means", "quats", "scales",
                                                                                    "opacities", "sh")}
        out = render(replace(sample, **leaves), cams)
        (out.rgb - target).abs().mean().backward()
        return out.rgb.detach(), leaves["means"].grad

    paths: dict[str, str] = {}
    RENDER_MODULE._blur_log_peak, RENDER_MODULE._NativeBlurPeak = counted_torch_peak, CountedNativePeak
    try:
        images = {}
        for name, fn in variants.items():
            calls.clear()
            images[name] = run(fn)
            if len(calls) != 1:  # the replaced function was not called, or more than one path ran
                raise SystemExit(f"bench_expected_render: the variant {name!r} ran {dict(calls) or 'no peak factor'}"
                                 f"; the dispatcher's replacement did not take effect")
            paths[name] = next(iter(calls))
        times: dict[str, list[float]] = {name: [] for name in variants}
        for _ in range(args.repeats):
            for name, fn in variants.items():
                t0 = time.perf_counter()
                run(fn)
                times[name].append(time.perf_counter() - t0)
    finally:
        RENDER_MODULE.blur_log_peak, RENDER_MODULE._blur_log_peak, RENDER_MODULE._NativeBlurPeak = (
            dispatch, torch_peak, native_peak)
    current, reference = "one projection (current)", "two projections (reference)"
    assert paths[reference] != paths[current], paths
    same = sorted(name for name in variants if name != current and paths[name] == paths[current])
    med = {name: statistics.median(v) for name, v in times.items()}
    b, gb = images[reference]
    result = {"n": args.n, "width": args.width, "height": args.height, "repeats": args.repeats,
              "paths": paths, "same_path_as_current": same,
              "median_ms": {k: v * 1e3 for k, v in med.items()}, "min_ms": {k: min(v) * 1e3 for k, v in times.items()},
              "ratio_to_reference": {k: med[k] / med[reference] for k in variants if k != reference},
              # the current path against the PyTorch one projection: None where they are the same code
              "current_over_pytorch": None if same else med[current] / med["one projection, PyTorch"],
              "max_abs_rgb_difference": {k: float((a - b).abs().max()) for k, (a, _) in images.items()
                                         if k != reference},
              "means_grad_relative_difference": {k: float((ga - gb).norm() / gb.norm())
                                                 for k, (_, ga) in images.items() if k != reference},
              "machine": args.machine, "threads": torch.get_num_threads(), "torch": torch.__version__,
              "date": date.today().isoformat()}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))
    if same:
        print(f"\n*** SAME PATH: {', '.join(same)} ran the same code as the current variant ({paths[current]}); "
              f"no ratio between them. ***\n", file=sys.stderr)
    print(f"current variant's path: {paths[current]}")
    print("| case | two projections (reference) | one projection, PyTorch | one projection (current) | current / "
          "reference | max image difference | machine | date |")
    print("|---|---|---|---|---|---|---|---|")
    ratio = result["ratio_to_reference"][current]
    print(f"| {args.n:,} Gaussians, {args.width}x{args.height} | {med[reference] * 1e3:.1f} ms | "
          f"{med['one projection, PyTorch'] * 1e3:.1f} ms{' (same path)' if same else ''} | "
          f"{med[current] * 1e3:.1f} ms ({paths[current].split()[0]}) | x{ratio:.2f} | "
          f"{result['max_abs_rgb_difference'][current]:.1e} | {args.machine} | {result['date']} |")


if __name__ == "__main__":
    main()
