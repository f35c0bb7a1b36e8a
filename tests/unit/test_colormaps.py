"""Preview colour maps: scales, rank colouring, non-finite values."""

from __future__ import annotations

import matplotlib
import numpy as np
import pytest
import torch

from uncertsplat.report.colormaps import color_range, colorize, rank_colorize


def _lut(t, cmap="turbo"):
    return np.asarray(matplotlib.colormaps[cmap](t, bytes=True))[..., :3]


def test_fixed_scale_ends_and_clipping():
    x = np.array([[0.0, 1.0, 2.0, -1.0]])
    img = colorize(x, mode="fixed", vmin=0.0, vmax=1.0)
    assert img.dtype == np.uint8 and img.shape == (1, 4, 3)
    assert (img[0, 0] == _lut(0.0)).all() and (img[0, 1] == _lut(1.0)).all()
    assert (img[0, 2] == img[0, 1]).all() and (img[0, 3] == img[0, 0]).all()


def test_fixed_scale_that_does_not_start_at_zero():
    """[vmin, vmax] = [2, 4] maps 2, 3, 4 to the colour map's low end, middle and high end (the callers' vmin of 0
    could not tell (a - vmin) / (vmax - vmin) from (a - vmin) / vmax)."""
    img = colorize(np.array([[2.0, 3.0, 4.0]]), mode="fixed", vmin=2.0, vmax=4.0)
    assert (img[0] == _lut(np.array([0.0, 0.5, 1.0]))).all()


def test_percentile_scale_ignores_outliers():
    x = np.linspace(0, 1, 1000).reshape(20, 50)
    x[0, 0] = 1e6
    lo, hi = color_range(x, "percentile")
    assert hi < 2.0 and lo < 0.05
    img = colorize(torch.tensor(x), mode="percentile")
    # the bulk is spread over the colour map, not crushed to the low end by the outlier
    assert len({tuple(p) for p in img.reshape(-1, 3)}) > 100


def test_rank_colorize_is_invariant_to_monotone_maps():
    g = np.random.default_rng(0)
    x = g.random((16, 16))
    a = rank_colorize(x)
    b = rank_colorize(np.exp(5 * x) + 3)  # same order, different scale
    assert (a == b).all()
    assert (rank_colorize(-x) != a).any()


def test_rank_colorize_constant_and_ties():
    img = rank_colorize(np.zeros((4, 4)))
    assert (img == _lut(0.5)).all()
    x = np.array([[1.0, 1.0, 2.0, 3.0]])
    img = rank_colorize(x)
    assert (img[0, 0] == img[0, 1]).all()


def test_nonfinite_black_and_shapes():
    x = np.array([[np.nan, 0.5], [np.inf, 0.2]])
    for img in (colorize(x), rank_colorize(x), colorize(x[..., None], mode="fixed")):
        assert (img[0, 0] == 0).all() and (img[1, 0] == 0).all()
        assert img[0, 1].any()
    with pytest.raises(ValueError):
        colorize(np.zeros((2, 2, 3)))
    with pytest.raises(ValueError):
        colorize(np.zeros((2, 2)), mode="bogus")
