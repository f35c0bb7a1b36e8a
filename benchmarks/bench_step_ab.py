"""Training steps of one run with a change off and on, alternating in one process (the model trains on).

The machines drift by 10-40 % within the hour, so a change to the training step is measured here as a ratio:
blocks of ``--block`` steps alternate between the two modes (the order flips every round), and the min and the
median per mode are compared. ``--what``:

- ``fused-image``: render's compositing into images (``rasterize.composite_image``), SSIM reading HWC images
  in place and the L1 term from SSIM's pass (2026-11-27) against the paths before them in the same library:
  the packed compositor with ``tiles_to_image``, the channel slices and the background's blend, SSIM on
  permuted copies of the channels, L1 as tensor ops.
- ``train-on``: the informed posterior's Gaussians fitted to the posterior mean's render
  (``variational.train_on = "mean"``, now) against the expected render (``"expected"``, before).
- ``mean-sample``: a training step's Gaussians from the parameters and the kept table terms in one native pass and
  its backward (``variational._with_constants``, now) against the five tensor ops and their autograd nodes (before).
- ``tile-size``: the run's ``tile_size`` ("before") against ``--tile-size`` ("now"): the rasterizer's tiles, whose
  size trades the (tile, Gaussian) pairs binning lists against the pixels each pair's compositing visits.
- ``ssim-cache``: the training photos' SSIM statistics kept (``ssim_cache_mb``, the default 1024 MB, now) against
  blurring the photo in every step's SSIM (``ssim_cache_mb = 0``, before); the same loss to the bit.

Page faults per step are reported too (fresh pages the allocator got from the system). glibc's malloc thresholds
must not be set by ``mallopt`` in a "before" mode: setting them turns off its dynamic thresholds for the rest of
the process, so such a "default" is not the default (a first version of this script did that and measured a gain
that the real default does not leave).

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/bench_step_ab.py --run demo_out/train --scene demo_out/synth \
        --what fused-image --rounds 16 --label demo

Writes ``benchmarks/results/step_ab_{what}_{label}.json``.
"""

from __future__ import annotations

import argparse
import json
import platform
import resource
import statistics
import sys
import time
from datetime import date
from pathlib import Path

import torch
from _common import add_overwrite_option, refuse_overwrite

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_train import trainer_from_run  # noqa: E402

from uncertsplat import native  # noqa: E402
from uncertsplat.config import TrainConfig  # noqa: E402
from uncertsplat.eval import image as image_module  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results"


class _PlanarSSIM(torch.autograd.Function):
    """The fused SSIM as it was called before it read HWC images: on planes [B,H,W], no L1 term."""

    @staticmethod
    def forward(ctx, x, y, window):
        B, H, W = x.shape
        mean, partials = torch.empty(B, dtype=torch.float64), x.new_empty(3, B, H, W)
        native.library().us_ssim_forward_f32(B, H, W, window.numel(), 1, x.data_ptr(), y.data_ptr(), None,
                                             window.data_ptr(), image_module.SSIM_C1_DEFAULT,
                                             image_module.SSIM_C2_DEFAULT, mean.data_ptr(), partials.data_ptr(),
                                             None, native.kernel_threads())
        ctx.save_for_backward(x, y, window, partials)
        return mean.to(x.dtype)

    @staticmethod
    def backward(ctx, grad):
        x, y, window, partials = ctx.saved_tensors
        B, H, W = x.shape
        g_plane, g_x = grad.to(torch.float32).contiguous(), torch.empty_like(x)
        native.library().us_ssim_backward_f32(B, H, W, window.numel(), 1, x.data_ptr(), y.data_ptr(),
                                              window.data_ptr(), partials.data_ptr(), g_plane.data_ptr(), None,
                                              g_x.data_ptr(), native.kernel_threads())
        return g_x, None, None


def _ssim_and_l1_before(pred, target):
    lead, (h, w, ch) = pred.shape[:-3], pred.shape[-3:]
    planes = [t.reshape(-1, h, w, ch).permute(0, 3, 1, 2).reshape(-1, h, w).contiguous() for t in (pred, target)]
    window = image_module.gaussian_window(dtype=torch.float32)
    ssim = _PlanarSSIM.apply(planes[0], planes[1].detach(), window).view(-1, ch).mean(-1).reshape(lead).mean()
    return ssim, (pred - target).abs().mean()


def _fused_image_modes():
    """(set_before, set_now) for ``fused-image``."""
    import uncertsplat.render.render  # noqa: F401  (the module, not the function the package exports)
    import uncertsplat.train.losses as losses

    render_module = sys.modules["uncertsplat.render.render"]
    now = (losses.ssim_and_l1, render_module.composite_image_available)

    def before():
        losses.ssim_and_l1 = _ssim_and_l1_before
        render_module.composite_image_available = lambda *args, **kw: False

    def after():
        losses.ssim_and_l1, render_module.composite_image_available = now
    return before, after


def _train_on_modes(trainer):
    """(set_before, set_now) for ``train-on``: the trainer's ``variational.train_on``, "expected" then "mean"."""

    def setter(value):
        def set_mode():
            cfg = trainer.cfg
            trainer.cfg = cfg.model_copy(update={"variational": cfg.variational.model_copy(update={"train_on": value})})
            trainer._expected = None
        return set_mode
    return setter("expected"), setter("mean")


def _mean_sample_modes():
    """(set_before, set_now) for ``mean-sample``: the tensor ops, then the native pass."""
    import uncertsplat.gaussians.variational as variational

    now = variational._with_constants

    def before():
        variational._with_constants = lambda p, offset, factor, gate: (
            p["means"] + offset, torch.exp(p["scales"]) * factor, torch.sigmoid(p["opacities"]) * gate)

    def after():
        variational._with_constants = now
    return before, after


def _ssim_cache_modes(trainer):
    """(set_before, set_now) for ``ssim-cache``: no photo statistics kept, then the trainer's own cache."""
    from uncertsplat.train.losses import SsimTargetCache

    kept, none = trainer.ssim_cache, SsimTargetCache(0)
    # every photo's statistics first, as after a training run's first epoch (a photo's first step computes them once)
    for i in range(trainer.train_images.shape[0]):
        kept.get((i, False), trainer.train_images[i:i + 1])

    def before():
        trainer.ssim_cache = none

    def now():
        trainer.ssim_cache = kept
    return before, now


def _tile_size_modes(trainer, size: int):
    """(set_before, set_now) for ``tile-size``: the run's tile size, then ``size``."""

    def setter(value):
        def set_mode():
            trainer.cfg = trainer.cfg.model_copy(update={"tile_size": value})
        return set_mode
    return setter(trainer.cfg.tile_size), setter(size)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", type=Path, required=True, help="a run folder with checkpoints")
    ap.add_argument("--scene", type=Path, required=True, help="the scene of --run")
    ap.add_argument("--what", choices=["fused-image", "train-on", "ssim-cache", "mean-sample", "tile-size"],
                    default="fused-image")
    ap.add_argument("--tile-size", type=int, default=16, help="the tile size of --what tile-size's \"now\"")
    ap.add_argument("--rounds", type=int, default=16)
    ap.add_argument("--block", type=int, default=10)
    ap.add_argument("--label", default="run")
    ap.add_argument("--machine", default=platform.processor() or platform.machine())
    add_overwrite_option(ap)
    args = ap.parse_args()
    path = RESULTS / f"step_ab_{args.what}_{args.label}.json"
    refuse_overwrite(path, overwrite=args.overwrite)

    cfg = TrainConfig.model_validate(json.loads((args.run / "config.json").read_text(encoding="utf-8")))
    trainer = trainer_from_run(args.scene, args.run, cfg, torch.device("cpu"),
                               extra_steps=2 * args.block * args.rounds + 10)
    modes = {"fused-image": lambda: _fused_image_modes(), "train-on": lambda: _train_on_modes(trainer),
             "ssim-cache": lambda: _ssim_cache_modes(trainer), "mean-sample": _mean_sample_modes,
             "tile-size": lambda: _tile_size_modes(trainer, args.tile_size)}
    set_before, set_now = modes[args.what]()
    for _ in range(5):  # warm-up
        trainer.train_step()
    seconds: dict[str, list[float]] = {"before": [], "now": []}
    faults: dict[str, list[float]] = {"before": [], "now": []}
    try:
        for r in range(args.rounds):
            for mode in (("before", "now") if r % 2 == 0 else ("now", "before")):
                (set_before if mode == "before" else set_now)()
                f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
                t0 = time.perf_counter()
                for _ in range(args.block):
                    trainer.train_step()
                seconds[mode].append((time.perf_counter() - t0) / args.block)
                faults[mode].append((resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0) / args.block)
    finally:
        set_now()
    out = {
        "what": args.what, **({"tile_size": {"before": cfg.tile_size, "now": args.tile_size}}
                              if args.what == "tile-size" else {}), "run": str(args.run), "num_gaussians": len(trainer.model), "rounds": args.rounds,
        "block": args.block, "threads": torch.get_num_threads(), "machine": args.machine,
        "date": date.today().isoformat(), "torch": torch.__version__,
        "ms_per_step": {k: [1e3 * s for s in v] for k, v in seconds.items()},
        "page_faults_per_step": {k: statistics.median(v) for k, v in faults.items()},
        "ratio_min": min(seconds["now"]) / min(seconds["before"]),
        "ratio_median": statistics.median(seconds["now"]) / statistics.median(seconds["before"]),
    }
    RESULTS.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=1))
    for k in ("before", "now"):
        v = out["ms_per_step"][k]
        print(f"{k:7s} min {min(v):.1f} ms, median {statistics.median(v):.1f} ms, page faults per step "
              f"{out['page_faults_per_step'][k]:.0f}")
    print(f"now / before: x{out['ratio_min']:.3f} (min), x{out['ratio_median']:.3f} (median); "
          f"{out['num_gaussians']} Gaussians -> {path}")


if __name__ == "__main__":
    main()
