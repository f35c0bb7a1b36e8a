"""False-colour previews of scalar maps (error, std, depth) as uint8 RGB images.

Scales (also stated in the report next to each figure):

- ``colorize(x, mode="percentile")``: the colour range is [1st, 99th] percentile of the map's finite
  values, so a few extreme pixels do not wash out the rest; values outside are clipped to the ends.
  Each image gets its own range: compare colours only within one image.
- ``colorize(x, mode="fixed", vmin, vmax)``: a fixed range (default [0, 1], the range of colours and
  absolute colour errors), so several images can be compared with one colour bar.
- ``rank_colorize(x)``: colour = rank quantile of the value in its map ((rank - 0.5) / n, ties
  sharing their mean rank). Every map then uses the full colour range uniformly, so an error map and
  an uncertainty map can be compared pixel by pixel ("is the most uncertain 10% where the largest
  10% of errors are?") without any colour-scale argument. A constant map is uniformly mid-scale.

Non-finite values (NaN, inf) are drawn black. ``x`` may be a torch tensor or a numpy array [H,W]
(a trailing dim of 1 is accepted); colour maps are matplotlib's (default "turbo").
"""

from __future__ import annotations

from typing import Literal

import matplotlib
import numpy as np

PERCENTILES = (1.0, 99.0)
"""The percentile range used by ``mode="percentile"``."""


def _as_2d(x) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    a = np.asarray(x, dtype=np.float64)
    if a.ndim == 3 and a.shape[-1] == 1:
        a = a[..., 0]
    if a.ndim != 2:
        raise ValueError(f"expected a [H,W] map, got shape {a.shape}")
    return a


def _apply_cmap(t: np.ndarray, finite: np.ndarray, cmap: str) -> np.ndarray:
    """Map t in [0, 1] to uint8 [H,W,3]; non-finite pixels black."""
    lut = matplotlib.colormaps[cmap]
    rgba = lut(np.clip(np.where(finite, t, 0.0), 0.0, 1.0), bytes=True)  # [H,W,4] uint8
    out = np.ascontiguousarray(rgba[..., :3])
    out[~finite] = 0
    return out


def color_range(
    x, mode: Literal["percentile", "fixed"] = "percentile", vmin: float | None = None, vmax: float | None = None
) -> tuple[float, float]:
    """The (vmin, vmax) that :func:`colorize` uses for these arguments (for colour bars / legends)."""
    a = _as_2d(x)
    if mode == "fixed":
        lo = 0.0 if vmin is None else float(vmin)
        hi = 1.0 if vmax is None else float(vmax)
    elif mode == "percentile":
        vals = a[np.isfinite(a)]
        if vals.size == 0:
            lo, hi = 0.0, 1.0
        else:
            p_lo, p_hi = np.percentile(vals, PERCENTILES)
            lo = float(p_lo) if vmin is None else float(vmin)
            hi = float(p_hi) if vmax is None else float(vmax)
    else:
        raise ValueError(f"unknown colour scale mode {mode!r}; use 'percentile' or 'fixed'")
    return lo, hi


def colorize(
    x,
    mode: Literal["percentile", "fixed"] = "percentile",
    vmin: float | None = None,
    vmax: float | None = None,
    cmap: str = "turbo",
) -> np.ndarray:
    """Colour a scalar map [H,W] -> uint8 [H,W,3] with a linear scale (see the module docstring).

    Explicit ``vmin``/``vmax`` override the percentile ends in "percentile" mode. If vmax <= vmin,
    every finite pixel gets the low-end colour.
    """
    a = _as_2d(x)
    lo, hi = color_range(a, mode, vmin, vmax)
    finite = np.isfinite(a)
    t = (a - lo) / (hi - lo) if hi > lo else np.zeros_like(a)
    return _apply_cmap(t, finite, cmap)


def rank_colorize(x, cmap: str = "turbo") -> np.ndarray:
    """Colour a scalar map [H,W] by rank quantile -> uint8 [H,W,3] (see the module docstring)."""
    a = _as_2d(x)
    finite = np.isfinite(a)
    t = np.zeros_like(a)
    n = int(finite.sum())
    if n > 0:
        # torch's sort (eval.calibration.average_ranks, ties averaged) instead of scipy.stats.rankdata, whose import
        # alone took 1.2 s of every evaluate (2026-11-27)
        import torch

        from uncertsplat.eval.calibration import average_ranks

        t[finite] = (average_ranks(torch.from_numpy(np.ascontiguousarray(a[finite]))).numpy() - 0.5) / n
    return _apply_cmap(t, finite, cmap)
