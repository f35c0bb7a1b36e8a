"""Depth scale alignment and depth error metrics."""

from __future__ import annotations

import pytest
import torch

from uncertsplat.eval.depth import align_depth_scale, depth_metrics


def test_scale_recovered(device):
    g = torch.Generator().manual_seed(0)
    pred = (0.5 + torch.rand(8, 9, 1, generator=g)).to(device)
    gt = 2.5 * pred
    gt[0, 0, 0] = 0.0  # invalid GT
    pred[1, 1, 0] = 0.0  # nothing rendered
    for method in ("median", "lsq"):
        s = align_depth_scale(pred, gt, method=method)
        assert s.scale == pytest.approx(2.5, rel=1e-6) and s.method == method
        assert s.num_pixels == 72 - 2
    given = align_depth_scale(pred, gt, method=3.0)
    assert given.scale == 3.0 and given.method == "given"
    m = depth_metrics(pred, gt, scale=2.5)
    assert m.abs_rel == pytest.approx(0.0, abs=1e-6) and m.rmse == pytest.approx(0.0, abs=1e-5)


def test_median_robust_lsq_not(device):
    pred = torch.ones(101, device=device)
    gt = torch.full((101,), 2.0, device=device)
    gt[:10] = 100.0  # outliers
    assert align_depth_scale(pred, gt, method="median").scale == pytest.approx(2.0)
    assert align_depth_scale(pred, gt, method="lsq").scale > 10.0


def test_depth_metrics_values(device):
    pred = torch.tensor([1.0, 2.0, 4.0], device=device)
    gt = torch.tensor([2.0, 2.0, 2.0], device=device)
    m = depth_metrics(pred, gt)
    assert m.mae == pytest.approx(1.0)
    assert m.rmse == pytest.approx(((1 + 0 + 4) / 3) ** 0.5)
    assert m.abs_rel == pytest.approx((0.5 + 0 + 1) / 3)
    mask = torch.tensor([True, True, False], device=device)
    assert depth_metrics(pred, gt, mask=mask).mae == pytest.approx(0.5)


def test_no_valid_pixels(device):
    z = torch.zeros(4, device=device)
    with pytest.raises(ValueError):
        align_depth_scale(z, z)
    m = depth_metrics(z, z)
    assert m.num_pixels == 0 and m.mae != m.mae
