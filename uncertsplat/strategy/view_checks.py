"""What the training decisions that look at images share (``strategy.sh_bands``, ``strategy.growth``): which
training views to render, and how much one model beats another on them. Only training views: the held-out views
stay unseen by every training decision."""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

from uncertsplat.types import Cameras, GaussianSample


def check_views(num_views: int, max_views: int) -> list[int]:
    """Up to ``max_views`` training view indices spread evenly over ``range(num_views)`` (deterministic)."""
    n = min(num_views, max_views)
    if n <= 0:
        return []
    return sorted({int(round(i * (num_views - 1) / max(n - 1, 1))) for i in range(n)})


@torch.no_grad()
def psnr_gain_db(sample: GaussianSample, other: GaussianSample, cameras: Cameras, images: Tensor,
                 render_fn: Callable[[GaussianSample, Cameras], Tensor], masks: Tensor | None = None) -> float:
    """How much better ``sample`` renders the views than ``other`` (dB): ``10 log10(mse other / mse sample)``.

    Args:
        sample, other: the two sets of Gaussians.
        cameras: [V] training cameras. images: [V,H,W,3] their photos.
        render_fn: (sample, camera) -> [1,H,W,3] image in [0, 1].
        masks: [V,H,W,1] bool, the pixels that count (the photos' masks), or None for all.

    The squared errors are summed over all the views' pixels before the ratio, so a view with large errors weighs
    more. Two identical renders give exactly 0; a perfect ``sample`` (and an imperfect ``other``) +inf.
    """
    return gain_db(*(sum_squared_error(g, cameras, images, render_fn, masks) for g in (sample, other)))


@torch.no_grad()
def sum_squared_error(sample: GaussianSample, cameras: Cameras, images: Tensor,
                      render_fn: Callable[[GaussianSample, Cameras], Tensor], masks: Tensor | None = None) -> float:
    """The squared error of ``sample``'s renders of ``cameras`` [V] (clamped to [0, 1]) against ``images``
    [V,H,W,3], summed in float64 over the views' pixels (those of ``masks`` [V,H,W,1], or all) and channels."""
    total = 0.0
    for i in range(len(cameras)):
        sq = (render_fn(sample, cameras[i])[0].clamp(0, 1) - images[i]).square()  # [H,W,3]
        total += float((sq if masks is None else sq * masks[i]).sum(dtype=torch.float64))
    return total


def gain_db(mine: float, theirs: float) -> float:
    """``10 log10(theirs / mine)``: how much better (dB) a model with summed squared error ``mine`` renders the
    same pixels than one with ``theirs``; exactly 0 for equal errors, +inf for ``mine`` = 0 < ``theirs``."""
    if mine == theirs:
        return 0.0
    if mine <= 0.0:
        return math.inf
    return 10.0 * math.log10(max(theirs, 1e-300) / mine)


__all__ = ["check_views", "gain_db", "psnr_gain_db", "sum_squared_error"]
