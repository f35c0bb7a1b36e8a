"""How many Gaussians a scene gets: the model-size budget of densification (``DensifyConfig.max_gaussians``).

3DGS's densification grows the model while screen-space gradients stay above a threshold, which on a small
or smooth scene means long after the images have stopped improving (the 24-view 128x96 tiny scene reached 117k
Gaussians, more than one per 3 of its pixels). Unless the user fixes ``max_gaussians``, the budget is one
Gaussian per ``pixels_per_gaussian`` training pixels: the images' own resolution bounds the detail a model
can learn from them. The ratio's default is a measured point on the held-out PSNR / model-size curve
(BENCHMARKS.md, "How many Gaussians a scene needs").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

MIN_BUDGET = 1000
"""The automatic budget is never below this (a handful of low-resolution views still needs some Gaussians)."""
MAX_BUDGET = 2_000_000
"""Nor above this, the ceiling of the fixed budget it replaced."""


MEMORY_RESERVE = 256 * 2**20
"""Bytes growth leaves free beyond what training will take: the process's and the system's other allocations move
by more than the estimate of a grown Gaussian's cost is sure of."""
GROWN_GAUSSIAN_FACTOR = 8.0
"""Bytes a Gaussian grown by densification adds to a training step's peak, per byte of its stored state (its
parameters, offset-table rows and Adam moments: ``gaussians.params.memory_per_new_gaussian``): their gradients, the
render's per-Gaussian and per-pair buffers and the posterior updates' accumulators come on top. Measured (BENCHMARKS.md,
"Growth held before memory runs out"; against the state of a Gaussian without tables, 716 bytes): 3.9x at 320x240,
5.3x at 640x480 and 7.6x at 1280x960 for randomly placed Gaussians (whose footprints, and so pairs, grow with the
image), 4.3x for a model densified to 398k at 640x480. Set above them all: a factor too low lets growth run the process
out of memory, one too high only holds it sooner where memory is short."""


def memory_growth_limit(gaussians: int, room: int, per_gaussian: float) -> int:
    """The most Gaussians a model of ``gaussians`` may grow to when the process may take ``room`` more bytes beyond
    what its steps already take at their peaks, each added Gaussian costing ``per_gaussian`` bytes there, and
    ``MEMORY_RESERVE`` is kept free. Never below ``gaussians``: memory never removes Gaussians, it stops growth."""
    return gaussians + max(int((room - MEMORY_RESERVE) // max(per_gaussian, 1.0)), 0)


MEMORY_HOLD = "memory held the model's growth"
"""How ``memory_hold_warning`` begins: a sweep finds its held points by it."""


def memory_hold_warning(hold: dict) -> str:
    """The warning for a hold of densification's growth by memory (``Trainer.memory_hold``'s keys: the first hold's
    step, size, budget, room and price)."""
    room = hold["room_mb"] * 2**20
    more = memory_growth_limit(0, room, hold["per_gaussian_bytes"])  # (the Gaussians the room held beyond the model)
    return (f"{MEMORY_HOLD} from step {hold['step']} on, at {hold['gaussians']:,} Gaussians (its "
            f"budget: {hold['budget']:,}): {max(room, 0) / 2**30:.2f} GB were left beyond what training takes, growth "
            f"keeps {MEMORY_RESERVE / 2**30:.2f} GB free and takes about {hold['per_gaussian_bytes'] / 1024:.1f} KB a "
            f"Gaussian at a step's peak, room for {more:,} more where densification asked for more. Training goes on "
            "with the Gaussians memory holds rather than run out; for a larger model free memory or lower its use "
            f"(--set scene.downscale=2); --set densify.max_gaussians={hold['gaussians']} makes this size the budget")


@dataclass(frozen=True)
class GaussianBudget:
    """The model-size limit of a run and where it comes from (``train_summary.json`` ``budget``)."""

    max_gaussians: int
    source: str  # "config" (set by the user or a preset) or "auto" (from the training pixels)
    reason: str

    def as_dict(self) -> dict:
        return {"max_gaussians": self.max_gaussians, "source": self.source, "reason": self.reason}


def gaussian_budget(max_gaussians: int | None, pixels_per_gaussian: float, *, views: int, width: int,
                    height: int) -> GaussianBudget:
    """The budget for ``views`` training images of ``width`` x ``height``: ``max_gaussians`` when given, else one
    Gaussian per ``pixels_per_gaussian`` training pixels, within [MIN_BUDGET, MAX_BUDGET]."""
    if max_gaussians is not None:
        return GaussianBudget(int(max_gaussians), "config", "densify.max_gaussians")
    pixels = views * width * height
    n = min(max(math.ceil(pixels / pixels_per_gaussian), MIN_BUDGET), MAX_BUDGET)
    reason = (f"one Gaussian per {pixels_per_gaussian:g} training pixels: {views} views of {width}x{height} = "
              f"{pixels:,} pixels")
    if n in (MIN_BUDGET, MAX_BUDGET):
        reason += f", clamped to {n:,}"
    return GaussianBudget(n, "auto", reason)


__all__ = ["GROWN_GAUSSIAN_FACTOR", "MAX_BUDGET", "MEMORY_HOLD", "MEMORY_RESERVE", "MIN_BUDGET", "GaussianBudget",
           "gaussian_budget", "memory_growth_limit", "memory_hold_warning"]
