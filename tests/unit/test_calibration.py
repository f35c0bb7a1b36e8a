"""Calibration coverage and Spearman correlation."""

from __future__ import annotations

import math

import pytest
import torch

from uncertsplat.eval.calibration import (
    average_ranks,
    calibration,
    mean_calibration,
    nominal_coverage,
    spearman,
)


def test_nominal_values():
    assert nominal_coverage(1.0) == pytest.approx(0.682689, abs=1e-6)
    assert nominal_coverage(2.0) == pytest.approx(0.954500, abs=1e-6)


def test_gaussian_data_is_near_perfect(device):
    g = torch.Generator().manual_seed(0)
    n = 200_000
    std = (0.01 + 0.2 * torch.rand(n, generator=g)).to(device)
    err = (torch.randn(n, generator=g).to(device)) * std
    r = calibration(err, std)
    assert r.num_elements == n
    for o, m in zip(r.observed, r.nominal, strict=True):
        assert o == pytest.approx(m, abs=0.01)
    assert r.calibration_error < 0.01
    # over-confident (std halved): observed coverage falls below nominal, error grows
    bad = calibration(err, std / 2)
    assert all(o < m for o, m in zip(bad.observed, bad.nominal, strict=True))
    assert bad.calibration_error > 0.1


def test_zero_std_and_constant_error_no_nan(device):
    err = torch.full((100,), 0.1, device=device)
    r = calibration(err, torch.zeros(100, device=device))
    assert all(o == 0.0 for o in r.observed)
    assert math.isfinite(r.calibration_error)
    exact = calibration(torch.zeros(100, device=device), torch.zeros(100, device=device))
    assert all(o == 1.0 for o in exact.observed)
    s = spearman(torch.zeros(100, device=device), err)
    assert s.value is None and "constant" in s.reason
    s2 = spearman(torch.rand(100, device=device), err)
    assert s2.value is None and "error is constant" in s2.reason


def test_calibration_mask_and_mean(device):
    err = torch.tensor([[0.0, 5.0]], device=device)
    std = torch.tensor([[1.0, 1.0]], device=device)
    r = calibration(err, std, ks=(1.0,), mask=torch.tensor([[True, False]], device=device))
    assert r.observed == (1.0,) and r.num_elements == 1
    r2 = calibration(err, std, ks=(1.0,))
    m = mean_calibration([r, r2])
    assert m.observed[0] == pytest.approx(0.75)
    assert m.calibration_error == pytest.approx(abs(0.75 - nominal_coverage(1.0)))


def test_average_ranks_ties():
    r = average_ranks(torch.tensor([10.0, 20.0, 10.0, 30.0, 10.0]))
    assert r.tolist() == [2.0, 4.0, 2.0, 5.0, 2.0]


def test_spearman_against_scipy(device):
    from scipy.stats import spearmanr

    g = torch.Generator().manual_seed(1)
    x = torch.randint(0, 20, (500,), generator=g).float()  # many ties
    y = x + 5 * torch.rand(500, generator=g)
    y[:50] = 0.0
    ref = spearmanr(x.numpy(), y.numpy()).statistic
    got = spearman(x.to(device), y.to(device))
    assert got.value == pytest.approx(ref, abs=1e-10) and got.reason is None
    assert spearman(x, -x).value == pytest.approx(-1.0)


def test_spearman_broadcast_std(device):
    std = torch.arange(12, dtype=torch.float32, device=device).reshape(2, 6, 1)
    err = std.expand(2, 6, 3) * 2 + 1
    assert spearman(std, err).value == pytest.approx(1.0)


def test_std_factor_notes_name_too_few_views_and_a_factor_these_views_disagree_with():
    from uncertsplat.stages.evaluate import std_factor_notes

    assert std_factor_notes(12, -1.0, -0.9) == [] and std_factor_notes(3, -1.0, -0.9) == []
    (few,) = std_factor_notes(2, -1.0, -0.9)
    assert few == "the std factor rests on 2 views only, too few to trust"
    (both,) = std_factor_notes(1, -0.01, -0.12)
    assert both.startswith("the std factor rests on 1 view only") and "makes these views' NLL worse" in both
    (worse,) = std_factor_notes(8, -0.01, -0.12)
    assert worse.startswith("the fitted factor makes these views' NLL worse than the raw std does, by 0.110 nats")
    assert std_factor_notes(8, -1.6135, -1.6164) == []  # 0.003 nats worse: no disagreement worth a warning


def test_the_std_factor_from_kept_maps_caps_the_std_as_the_rendered_predictive_does(monkeypatch):
    """``fit_std_scale`` given the maps ``fit_residual`` kept for the views set aside adds the side terms to them instead
    of rendering the samples again: the std it scores must be the one ``mc_render`` gives, capped at ``RGB_STD_MAX``.
    A pixel at error 0.5 whose kept std is 0.3 and whose side terms add 0.55 to the variance has the std
    min(sqrt(0.09 + 0.55), 0.5) = 0.5, so its z-score is 1 and so is the factor (0.8 uncapped: a factor of 0.625)."""
    from uncertsplat.config import EvalConfig
    from uncertsplat.eval import engine
    from uncertsplat.types import Cameras, ViewSet

    h, w = 2, 3
    cams = Cameras(torch.eye(4).repeat(3, 1, 1), torch.eye(3).repeat(3, 1, 1), w, h, ("a.png", "b.png", "c.png"))
    views = ViewSet(indices=(2,), cameras=cams[[2]], images=torch.zeros(1, h, w, 3))
    monkeypatch.setattr(engine, "_side_variance", lambda sampler, cam: ({"pixel noise": torch.full((1, h, w, 1), 0.55)},
                                                                        None))
    sampler = engine.Sampler(sample_fn=lambda g: None, render_fn=lambda s, c: None)
    kept = {2: (torch.full((1, h, w, 3), 0.5), torch.full((1, h, w, 3), 0.3))}
    fit = engine.fit_std_scale(sampler, {"train": [0, 1], "calibration": [2]},
                               EvalConfig(degrees_of_freedom="gaussian"), torch.device("cpu"),
                               load_views=lambda indices: views, set_aside_maps=kept)
    assert fit.names == ["c.png"] and fit.dof is None
    assert fit.scale == pytest.approx(1.0, rel=1e-6)


class TestCalibrationArithmetic:
    """The calibration error's absolute differences, the averaging over views with elements, Spearman's
    reasons."""

    def test_calibration_error_adds_the_absolute_differences(self, device):
        # |e| / std = 0.5, 0.5, 0.5, 5: inside k = 1 and k = 2 three times of four: 0.75 lies above the
        # nominal 0.683 at k = 1 and below the nominal 0.954 at k = 2; the two misses must not cancel
        err = torch.tensor([0.5, -0.5, 0.5, 5.0], dtype=torch.float64, device=device)
        r = calibration(err, torch.ones_like(err), ks=(1.0, 2.0))
        assert r.observed == (0.75, 0.75)
        n1, n2 = nominal_coverage(1.0), nominal_coverage(2.0)
        assert r.calibration_error == pytest.approx(((0.75 - n1) + (n2 - 0.75)) / 2, rel=1e-12)
        assert r.calibration_error == pytest.approx(0.135905, abs=1e-6)

    def test_mean_calibration_skips_views_without_elements(self, device):
        err = torch.tensor([0.0, 5.0], device=device)
        std = torch.ones_like(err)
        r = calibration(err, std, ks=(1.0,))
        empty = calibration(err, std, ks=(1.0,), mask=torch.zeros(2, dtype=torch.bool, device=device))
        assert empty.num_elements == 0
        m = mean_calibration([r, empty])
        assert m.observed == (0.5,) and m.num_elements == 2
        assert m.calibration_error == pytest.approx(abs(0.5 - nominal_coverage(1.0)))
        with pytest.raises(ValueError, match="no view has valid elements"):
            mean_calibration([empty])

    def test_spearman_of_fewer_than_two_elements_says_how_many(self, device):
        one = spearman(torch.tensor([0.3], device=device), torch.tensor([0.1], device=device))
        assert one.value is None and one.reason == "undefined: 1 valid element(s)" and one.num_elements == 1
        none = spearman(torch.tensor([float("nan")], device=device), torch.tensor([0.1], device=device))
        assert none.value is None and none.reason == "undefined: 0 valid element(s)"
        assert none.num_elements == 0
