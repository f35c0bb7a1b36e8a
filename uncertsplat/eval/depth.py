"""Depth scale alignment and depth error metrics.

A reconstruction from photos lives in an arbitrary (normalised) scale, so rendered depth is multiplied
by a factor s before it is compared with GT depth. s is estimated over valid pixels (GT > 0, render >
0 i.e. something was hit, both finite, inside the mask) by

- ``"median"``: median(gt / pred), robust to outliers (the usual choice for monocular depth);
- ``"lsq"``: least squares through the origin, argmin_s sum (s pred - gt)^2 = sum(pred gt) / sum(pred^2);
- a given float (e.g. SceneData.depth_scale_to_gt when the scene knows it).

The factor and how it was obtained are always written into the results. The depth std scales with the
same factor (std of s * D is s * std of D); AUSE is scale-invariant in any case.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from uncertsplat.eval._common import broadcast_mask


@dataclass(frozen=True)
class DepthScale:
    """A depth scale factor: GT depth ~= scale * rendered depth."""

    scale: float
    method: str  # "median", "lsq" or "given"
    num_pixels: int


@dataclass(frozen=True)
class DepthMetrics:
    """Errors of the aligned depth against GT over valid pixels (GT units)."""

    abs_rel: float  # mean |d - gt| / gt
    rmse: float
    mae: float
    num_pixels: int

    def to_dict(self) -> dict:
        return {"abs_rel": self.abs_rel, "rmse": self.rmse, "mae": self.mae, "num_pixels": self.num_pixels}


def valid_depth_mask(pred: Tensor, gt: Tensor, mask: Tensor | None = None) -> Tensor:
    """Pixels usable for depth evaluation: both finite, GT > 0, render > 0, inside ``mask``."""
    if pred.shape != gt.shape:
        raise ValueError(f"pred and gt depth must have the same shape, got {tuple(pred.shape)} vs {tuple(gt.shape)}")
    valid = torch.isfinite(pred) & torch.isfinite(gt) & (gt > 0) & (pred > 0)
    if mask is not None:
        valid = valid & broadcast_mask(mask, pred.shape)
    return valid


def align_depth_scale(
    pred: Tensor,
    gt: Tensor,
    *,
    mask: Tensor | None = None,
    method: Literal["median", "lsq"] | float = "median",
) -> DepthScale:
    """Estimate (or pass through) the factor s with gt ~= s * pred; see the module docstring.

    ``pred``/``gt`` are any same-shaped depth maps (one view [H,W,1], or all views stacked so one
    factor serves the whole scene). Raises ValueError when no pixel is valid.
    """
    valid = valid_depth_mask(pred, gt, mask)
    n = int(valid.sum())
    if not isinstance(method, str):
        scale = float(method)
        if not (scale > 0 and torch.isfinite(torch.tensor(scale))):
            raise ValueError(f"a given depth scale must be a positive finite number, got {method}")
        return DepthScale(scale, "given", n)
    if n == 0:
        raise ValueError("no valid pixel to align depth (need GT > 0 and rendered depth > 0)")
    p = pred[valid].to(torch.float64)
    g = gt[valid].to(torch.float64)
    if method == "median":
        ratios = g / p
        # The lower median of torch is biased for even n; take the midpoint of the two middle values.
        srt, _ = torch.sort(ratios)
        scale = float((srt[(n - 1) // 2] + srt[n // 2]) / 2)
    elif method == "lsq":
        scale = float((p * g).sum() / p.square().sum())
    else:
        raise ValueError(f"unknown depth alignment {method!r}; use 'median', 'lsq' or a number")
    return DepthScale(scale, method, n)


def depth_metrics(pred: Tensor, gt: Tensor, *, scale: float = 1.0, mask: Tensor | None = None) -> DepthMetrics:
    """abs rel, RMSE and MAE of ``scale * pred`` against ``gt`` over valid pixels (NaN if none)."""
    valid = valid_depth_mask(pred, gt, mask)
    n = int(valid.sum())
    if n == 0:
        nan = float("nan")
        return DepthMetrics(nan, nan, nan, 0)
    d = pred[valid].to(torch.float64) * scale
    g = gt[valid].to(torch.float64)
    diff = d - g
    return DepthMetrics(
        abs_rel=float((diff.abs() / g).mean()),
        rmse=float(diff.square().mean().sqrt()),
        mae=float(diff.abs().mean()),
        num_pixels=n,
    )
