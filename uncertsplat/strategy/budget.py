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


__all__ = ["MAX_BUDGET", "MIN_BUDGET", "GaussianBudget", "gaussian_budget"]
