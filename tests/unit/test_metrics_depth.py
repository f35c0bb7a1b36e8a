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


def _sorted_median(pred, gt, mask=None) -> tuple[float, int]:
    """The median of gt / pred over the valid pixels by one float64 sort of all of them (the exact path's way)."""
    from uncertsplat.eval.depth import valid_depth_mask

    valid = valid_depth_mask(pred, gt, mask)
    srt = torch.sort(gt[valid].double() / pred[valid].double()).values  # [n]
    n = srt.numel()
    return float((srt[(n - 1) // 2] + srt[n // 2]) / 2), n


@pytest.mark.parametrize("case", ["spread", "ties", "constant", "odd"])
def test_the_bounded_median_is_the_sorted_one(monkeypatch, case):
    # small limits force the streamed path, several selection passes and many slices on a small case; the factor
    # must be the sorted median's to the bit (the same two middle ratios), whether the maps come stacked or a list
    import uncertsplat.eval.depth as depth

    g = torch.Generator().manual_seed(3)
    pred = torch.rand(5, 30, 41, 1, generator=g) + 0.1  # [C,H,W,1]
    gt = pred * (2.0 + 0.3 * torch.randn(pred.shape, generator=g))
    if case == "ties":
        gt = torch.round(gt * 4) / 4
    if case == "constant":
        gt = 3.0 * torch.ones_like(pred)
        pred = 1.5 * torch.ones_like(pred)
    gt[0, :3] = 0.0
    pred[1, :2] = float("nan")
    mask = torch.rand(pred.shape[:-1], generator=g) > 0.2  # [C,H,W]
    if case == "odd":
        mask[0, 0, 0] = not mask[0, 0, 0]  # flips the count's parity
    want, n = _sorted_median(pred, gt, mask)
    monkeypatch.setattr(depth, "EXACT_MAX_PIXELS", 10)
    monkeypatch.setattr(depth, "GATHER_MAX", 40)
    monkeypatch.setattr(depth, "SLICE_ELEMENTS", 700)
    stacked = align_depth_scale(pred, gt, mask=mask)
    listed = align_depth_scale(list(pred), list(gt), mask=list(mask))
    assert stacked.scale == listed.scale == want
    assert stacked.num_pixels == listed.num_pixels == n


def test_a_large_case_takes_the_bounded_path_and_gives_the_exact_median(monkeypatch):
    # above EXACT_MAX_PIXELS (here at its default) the sort of every pixel is never made
    import uncertsplat.eval.depth as depth

    g = torch.Generator().manual_seed(0)
    n = depth.EXACT_MAX_PIXELS + 200_001
    pred = torch.rand(n, generator=g) + 0.05
    gt = pred * torch.exp(0.5 * torch.randn(n, generator=g))
    want, m = _sorted_median(pred, gt)
    calls = []
    streamed = depth._streamed_median
    monkeypatch.setattr(depth, "_streamed_median", lambda *a: calls.append(a[-1]) or streamed(*a))
    got = align_depth_scale(pred, gt)
    assert calls == [m] and got.num_pixels == m
    assert got.scale == pytest.approx(want, rel=1e-4) and got.scale == want  # (the brief's tolerance; it is exact)
    lsq = align_depth_scale(pred, gt, method="lsq").scale
    assert lsq == pytest.approx(float((pred.double() * gt.double()).sum() / pred.double().square().sum()), rel=1e-12)


def test_up_to_the_threshold_every_pixel_is_sorted_at_once(monkeypatch):
    # the exact path (the committed factors' way) up to EXACT_MAX_PIXELS valid pixels inclusive, the bounded one above
    import uncertsplat.eval.depth as depth

    g = torch.Generator().manual_seed(1)
    pred = torch.rand(64, generator=g) + 0.1
    gt = pred * (1.0 + torch.rand(64, generator=g))
    calls = []
    streamed = depth._streamed_median
    monkeypatch.setattr(depth, "_streamed_median", lambda *a: calls.append(a[-1]) or streamed(*a))
    monkeypatch.setattr(depth, "EXACT_MAX_PIXELS", 64)
    exact = align_depth_scale(pred, gt)
    assert calls == []
    monkeypatch.setattr(depth, "EXACT_MAX_PIXELS", 63)
    bounded = align_depth_scale(pred, gt)
    assert calls == [64] and bounded.scale == exact.scale == _sorted_median(pred, gt)[0]


def test_a_scaled_check_needs_no_scaled_copy():
    # pred_scale multiplies slice by slice: the same factor as scaling the maps first
    g = torch.Generator().manual_seed(2)
    pred = torch.rand(3, 8, 9, 1, generator=g) + 0.1
    gt = 2.0 * pred + 0.01 * torch.rand(pred.shape, generator=g)
    want = align_depth_scale(pred * 0.37, gt)
    got = align_depth_scale(list(pred), list(gt), pred_scale=0.37)
    assert got.scale == want.scale and got.num_pixels == want.num_pixels
    with pytest.raises(ValueError, match="as many maps"):
        align_depth_scale(list(pred), list(gt)[:2])


def test_the_implausible_factor_note_takes_one_map_a_view():
    # evaluate passes its views' maps as lists (no stack); the note is the one the stacked maps give
    from uncertsplat.eval.engine import implausible_depth_scale_notes

    g = torch.Generator().manual_seed(4)
    depth = torch.rand(3, 6, 7, 1, generator=g) + 0.5  # [C,H,W,1]
    gt = 3.1 * depth
    mask = torch.rand(depth.shape, generator=g) > 0.3
    stacked = implausible_depth_scale_notes(depth, gt, mask, 1.0, 1.0)
    listed = implausible_depth_scale_notes(list(depth), list(gt), list(mask), 1.0, 1.0)
    assert stacked == listed and len(listed) == 1 and "3.1x" in listed[0]
    assert implausible_depth_scale_notes(list(depth), list(gt), list(mask), 3.0, 3.0) == []
    # a factor given against the scene's own GT (in the run's units already): the note says it needs none (it
    # advised --depth-scale auto, which does nothing without --depth-gt; a review gave the run-to-scene factor)
    (own,) = implausible_depth_scale_notes(depth, depth, mask, 4.044, 4.044, scene_gt=True)
    assert "the scene's own GT depth is in the run's units already: leave --depth-scale out, or give 1" in own
    assert "auto fits" not in own


def test_the_implausible_factor_note_names_a_power_of_ten_of_the_scenes_units():
    """Millimetre maps of a metric scene: with the scene's units the GT is 1000x the render, with --depth-scale 1000 it
    is still 4x (the factor is from the run's units, not the scene's); the note names the factor (the scene's units
    per run unit x 1000), and the scene's own units when the maps are in them, but no factor off every power of ten."""
    from uncertsplat.eval.engine import implausible_depth_scale_notes

    depth = torch.full((1, 4, 5, 1), 2.0)  # the run's units
    mask = torch.ones_like(depth, dtype=torch.bool)
    to_source = 4.0  # the scene's metres per run unit
    gt_mm = depth * to_source * 1000.0
    (scene,) = implausible_depth_scale_notes(depth, gt_mm / to_source, mask, 1.0, "scene", to_source)
    assert "1e+03x the render's" in scene and "--depth-scale 4000, the run's depth to the maps' units" in scene
    (given,) = implausible_depth_scale_notes(depth, gt_mm, mask, 1000.0, 1000.0, to_source)
    assert "4x the render's" in given and "--depth-scale 4000," in given
    (metres,) = implausible_depth_scale_notes(depth, depth * to_source, mask, 1.0, 1.0, to_source)
    assert "(maps in the scene's own units: --depth-scale scene;" in metres
    (odd,) = implausible_depth_scale_notes(depth, depth * 22.0, mask, 1.0, 1.0, to_source)  # 5.5x the scene's
    assert "--depth-scale auto fits the factor" in odd and "the run's depth to the maps' units" not in odd


class TestExactValues:
    """The least-squares factor and the relative error by their formulas on numbers where the alternatives
    differ; a given factor must be positive."""

    def test_lsq_is_the_least_squares_factor_through_the_origin(self, device):
        pred = torch.tensor([1.0, 2.0, 4.0], device=device)
        gt = torch.tensor([2.0, 2.0, 2.0], device=device)
        # argmin_s sum (s p - g)^2 = sum(p g) / sum(p^2) = (2 + 4 + 8) / (1 + 4 + 16)
        got = align_depth_scale(pred, gt, method="lsq")
        assert got.scale == pytest.approx(14 / 21, rel=1e-12) and got.num_pixels == 3
        # the median of the ratios 2, 1, 0.5
        assert align_depth_scale(pred, gt, method="median").scale == 1.0

    def test_abs_rel_divides_by_the_ground_truth(self, device):
        pred = torch.tensor([1.0, 2.0, 4.0], device=device)
        gt = torch.tensor([2.0, 4.0, 1.0], device=device)
        m = depth_metrics(pred, gt)
        # over the GT, not the prediction ((1 + 1 + 0.75) / 3)
        assert m.abs_rel == pytest.approx((1 / 2 + 2 / 4 + 3 / 1) / 3, rel=1e-12)
        assert m.mae == pytest.approx(2.0) and m.rmse == pytest.approx((14 / 3) ** 0.5)
        assert depth_metrics(pred, gt, scale=2.0).abs_rel == pytest.approx((0 + 0 + 7 / 1) / 3, rel=1e-12)

    @pytest.mark.parametrize("bad", [0.0, -2.0, float("inf"), float("nan")])
    def test_a_given_factor_must_be_positive_and_finite(self, bad, device):
        pred = torch.ones(4, device=device)
        with pytest.raises(ValueError, match="positive finite"):
            align_depth_scale(pred, 2 * pred, method=bad)
