"""Depth scale alignment and depth error metrics.

A reconstruction from photos lives in an arbitrary (normalised) scale, so rendered depth is multiplied
by a factor s before it is compared with GT depth. s is estimated over valid pixels (GT > 0, render >
0 i.e. something was hit, both finite, inside the mask) by

- ``"median"``: median(gt / pred), robust to outliers (the usual choice for monocular depth);
- ``"lsq"``: least squares through the origin, argmin_s sum (s pred - gt)^2 = sum(pred gt) / sum(pred^2);
- a given float (e.g. SceneData.depth_scale_to_gt when the scene knows it).

Maps may come stacked or one tensor a view; above ``EXACT_MAX_PIXELS`` valid pixels the factor is found slice by
slice in bounded memory (the median exactly: the same two middle ratios as a sort of all of them).

The factor and how it was obtained are always written into the results. The depth std scales with the
same factor (std of s * D is s * std of D); AUSE is scale-invariant in any case.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence
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


def valid_depth_mask(pred: Tensor, gt: Tensor, mask: Tensor | None = None) -> Tensor:
    """Pixels usable for depth evaluation: both finite, GT > 0, render > 0, inside ``mask``."""
    if pred.shape != gt.shape:
        raise ValueError(f"pred and gt depth must have the same shape, got {tuple(pred.shape)} vs {tuple(gt.shape)}")
    valid = torch.isfinite(pred) & torch.isfinite(gt) & (gt > 0) & (pred > 0)
    if mask is not None:
        valid = valid & broadcast_mask(mask, pred.shape)
    return valid


EXACT_MAX_PIXELS = 1 << 21
"""Up to this many valid pixels ``align_depth_scale`` gathers them all in float64 and sorts them (what it always did:
about 40 bytes a pixel). Above, it streams over slices of the maps (``SLICE_ELEMENTS``) in bounded memory: the
median by a radix selection on the ratios' float64 bits, the same two middle values (the same factor, to the bit),
and the least-squares sums slice by slice (the same to rounding). Every held-out pixel of a large evaluation at once
took ~140 bytes a pixel (63 views of 1600x1067: ~15 GB)."""
SLICE_ELEMENTS = 1 << 20
"""Elements of the maps per slice of the bounded path (its temporaries: a few tens of bytes each)."""
GATHER_MAX = 1 << 20
"""The radix selection narrows the bits until the bucket holding the rank has at most this many ratios, then sorts it."""
RADIX_BITS = 16
"""Bits of the ratios' float64 patterns one pass of the selection resolves (a histogram of 2**16 counts)."""

DepthMaps = Tensor | Sequence[Tensor]
"""Depth maps: one tensor (a view [H,W,1], or views stacked [C,H,W,1]) or one tensor per view (nothing is stacked)."""


def _slices(pred: DepthMaps, gt: DepthMaps, mask: DepthMaps | None) -> Iterator[tuple[Tensor, Tensor, Tensor | None]]:
    """(pred, gt, mask) slices along each map's first dim of at most about ``SLICE_ELEMENTS`` elements, in the
    row-major order of the maps stacked (so a gather of the slices' valid pixels equals ``pred[valid]``)."""
    if isinstance(pred, Tensor):
        preds, gts, masks = [pred], [gt], [mask]
    else:
        preds, gts = list(pred), list(gt)
        masks = list(mask) if mask is not None else [None] * len(preds)
        if not (len(preds) == len(gts) == len(masks)):
            raise ValueError(f"pred, gt and mask must list as many maps, got {len(preds)}, {len(gts)}, {len(masks)}")
    for p, g, m in zip(preds, gts, masks, strict=True):
        if p.shape != g.shape:
            raise ValueError(f"pred and gt depth must have the same shape, got {tuple(p.shape)} vs {tuple(g.shape)}")
        m = broadcast_mask(m, p.shape) if m is not None else None
        if p.ndim == 0 or p.numel() <= SLICE_ELEMENTS:
            yield p, g, m
            continue
        rows = max(1, SLICE_ELEMENTS // max(1, p.numel() // p.shape[0]))
        for s in range(0, p.shape[0], rows):
            yield p[s:s + rows], g[s:s + rows], (m[s:s + rows] if m is not None else None)


def _valid_slices(pred: DepthMaps, gt: DepthMaps, mask: DepthMaps | None,
                  pred_scale: float) -> Iterator[tuple[Tensor, Tensor, Tensor]]:
    """(pred times ``pred_scale`` in its own dtype, gt, ``valid_depth_mask``) of each slice of ``_slices``."""
    for p, g, m in _slices(pred, gt, mask):
        if pred_scale != 1.0:
            p = p * pred_scale
        yield p, g, valid_depth_mask(p, g, m)


def _valid_pairs(pred: DepthMaps, gt: DepthMaps, mask: DepthMaps | None,
                 pred_scale: float) -> Iterator[tuple[Tensor, Tensor]]:
    """[n_i] float64 (pred, gt) of each slice's valid pixels, pred times ``pred_scale`` in its own dtype first."""
    for p, g, valid in _valid_slices(pred, gt, mask, pred_scale):
        yield p[valid].to(torch.float64), g[valid].to(torch.float64)


def _select(ratios: Callable[[], Iterator[Tensor]], k: int) -> tuple[Tensor, int]:
    """The sorted ratios of a bucket holding the k-th smallest (0-based) of all ``ratios()`` gives, and its index
    there: ``sorted[i]`` is the k-th smallest. Positive finite float64 ratios order as their bit patterns do (as
    int64), so each pass counts the patterns in 2**RADIX_BITS buckets of the range still holding rank k, then keeps
    the bucket that does, until it holds at most ``GATHER_MAX`` ratios (or a single pattern)."""
    lo, width = 0, 63  # rank k lies among the patterns [lo, lo + 2**width)
    while True:
        shift = max(width - RADIX_BITS, 0)
        hi = lo + (1 << width)
        counts = torch.zeros(1 << (width - shift), dtype=torch.int64)
        for r in ratios():
            bits = r.view(torch.int64)
            if width < 63:  # (the first pass's range is every positive pattern)
                bits = bits[(bits >= lo) & (bits < hi)] if hi < 1 << 63 else bits[bits >= lo]
            counts += torch.bincount(((bits - lo) >> shift).cpu(), minlength=counts.numel())
        cum = counts.cumsum(0)
        bucket = int(torch.searchsorted(cum, torch.tensor(k), right=True))  # the first with more than k below its end
        k -= int(cum[bucket - 1]) if bucket > 0 else 0
        lo, width = lo + (bucket << shift), shift
        if width == 0:  # one bit pattern: every ratio left is this value (however many there are)
            return torch.tensor([lo], dtype=torch.int64).view(torch.float64), 0
        if int(counts[bucket]) <= GATHER_MAX:
            hi = lo + (1 << width)
            kept = []
            for r in ratios():
                bits = r.view(torch.int64)
                kept.append(r[(bits >= lo) & (bits < hi)].cpu())
            return torch.sort(torch.cat(kept)).values, k


def _streamed_median(pred: DepthMaps, gt: DepthMaps, mask: DepthMaps | None, pred_scale: float, n: int) -> float:
    """The median of gt / pred over ``n`` valid pixels as the exact path gives it (the midpoint of the two middle
    float64 ratios), in memory bounded by the slices and ``GATHER_MAX``, not by ``n``."""
    def ratios() -> Iterator[Tensor]:
        return (g / p for p, g in _valid_pairs(pred, gt, mask, pred_scale))

    srt, i = _select(ratios, (n - 1) // 2)
    lower = srt[i]
    if n // 2 == (n - 1) // 2:
        upper = lower
    elif i + 1 < srt.numel():  # the next ratio overall is the next one in the same bucket
        upper = srt[i + 1]
    else:
        srt, i = _select(ratios, n // 2)
        upper = srt[i]
    return float((lower + upper) / 2)


def align_depth_scale(
    pred: DepthMaps,
    gt: DepthMaps,
    *,
    mask: DepthMaps | None = None,
    method: Literal["median", "lsq"] | float = "median",
    pred_scale: float = 1.0,
) -> DepthScale:
    """Estimate (or pass through) the factor s with gt ~= s * pred; see the module docstring.

    ``pred``/``gt`` are any same-shaped depth maps (one view [H,W,1], or all views stacked so one
    factor serves the whole scene), or lists of them (one factor for all of them; ``mask`` then a list too), so a
    caller need not stack every view. ``pred_scale`` multiplies ``pred`` first, slice by slice (a check of a given
    factor without a scaled copy of every map). Memory stays bounded above ``EXACT_MAX_PIXELS`` valid pixels.
    Raises ValueError when no pixel is valid.
    """
    if not isinstance(method, str):
        n = _count_valid(pred, gt, mask, pred_scale)
        scale = float(method)
        if not (scale > 0 and math.isfinite(scale)):
            raise ValueError(f"a given depth scale must be a positive finite number, got {method}")
        return DepthScale(scale, "given", n)
    if method not in ("median", "lsq"):
        raise ValueError(f"unknown depth alignment {method!r}; use 'median', 'lsq' or a number")
    n = _count_valid(pred, gt, mask, pred_scale)
    if n == 0:
        raise ValueError("no valid pixel to align depth (need GT > 0 and rendered depth > 0)")
    if n <= EXACT_MAX_PIXELS:
        # every valid pixel at once, as it always was (the committed results' factors, to the bit)
        pairs = list(_valid_pairs(pred, gt, mask, pred_scale))
        p = torch.cat([pg[0] for pg in pairs])  # [n] float64
        g = torch.cat([pg[1] for pg in pairs])
        del pairs
        if method == "median":
            ratios = g / p
            # The lower median of torch is biased for even n; take the midpoint of the two middle values.
            srt, _ = torch.sort(ratios)
            scale = float((srt[(n - 1) // 2] + srt[n // 2]) / 2)
        else:
            scale = float((p * g).sum() / p.square().sum())
    elif method == "median":
        scale = _streamed_median(pred, gt, mask, pred_scale, n)
    else:  # the sums slice by slice: the same to float64 rounding
        pg, pp = 0.0, 0.0
        for p, g in _valid_pairs(pred, gt, mask, pred_scale):
            pg += float((p * g).sum())
            pp += float(p.square().sum())
        scale = pg / pp
    return DepthScale(scale, method, n)


def _count_valid(pred: DepthMaps, gt: DepthMaps, mask: DepthMaps | None, pred_scale: float) -> int:
    """The number of valid pixels (``valid_depth_mask``) of ``pred * pred_scale`` against ``gt``, slice by slice."""
    return sum(int(valid.sum()) for _, _, valid in _valid_slices(pred, gt, mask, pred_scale))


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
