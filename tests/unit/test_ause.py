"""AUSE / sparsification: hand-computed cases, ties, permutation invariance, masks, scale."""

from __future__ import annotations

import pytest
import torch

from uncertsplat.eval.sparsification import mean_curves, sparsification, sparsification_all


def _t(x, device):
    return torch.tensor(x, dtype=torch.float64, device=device)


def test_perfect_uncertainty_gives_zero(device):
    g = torch.Generator().manual_seed(0)
    err = torch.rand(1000, generator=g, dtype=torch.float64).to(device)
    for metric in ("mae", "mse", "rmse"):
        r = sparsification(err, err * 3 + 1, metric=metric)  # monotone in the error
        assert r.ause == pytest.approx(0.0, abs=1e-12)
        assert torch.allclose(r.oracle, r.uncertainty)
        assert r.aurg > 0.05  # a perfect ranking beats a random one


def test_hand_computed_reversed_mae(device):
    # errors 1..4, S = 4 -> keep 4, 3, 2, 1 elements.
    err = _t([1.0, 2.0, 3.0, 4.0], device)
    r = sparsification(err, -err, metric="mae", steps=4)
    # oracle means: 2.5, 2, 1.5, 1; reversed: 2.5, 3, 3.5, 4; scale = 4
    assert r.fractions.tolist() == [0.0, 0.25, 0.5, 0.75]
    assert r.oracle.tolist() == pytest.approx([0.625, 0.5, 0.375, 0.25])
    assert r.uncertainty.tolist() == pytest.approx([0.625, 0.75, 0.875, 1.0])
    assert r.scale == pytest.approx(4.0)
    # trapezoid of [0, .25, .5, .75] with spacing .25 = .25 * (0.125 + 0.375 + 0.625)
    assert r.ause == pytest.approx(0.28125)
    # AURG: random curve flat at U(0) = 0.625, R - U = [0, -.125, -.25, -.375]:
    # .25 * (-0.0625 - 0.1875 - 0.3125) = -0.140625 (worse than random)
    assert r.aurg == pytest.approx(-0.140625)
    # the perfect ranking: U = O = [2.5, 2, 1.5, 1] / 2.5 (its own maximum now), R - U = [0, .2, .4, .6]:
    # .25 * (.1 + .3 + .5) = 0.225 (better than random)
    perfect = sparsification(err, err, metric="mae", steps=4)
    assert perfect.ause == pytest.approx(0.0, abs=1e-12)
    assert perfect.aurg == pytest.approx(0.225)


def test_kept_counts_round_down_when_steps_do_not_divide_n(device):
    """n_j = max(1, floor((S - j) n / S)): with n = 3, S = 4 the kept counts are 3, 2, 1, 1 (9/4 -> 2, 6/4 -> 1,
    3/4 -> 0 -> 1), not the 3, 3, 2, 1 that rounding up would give."""
    err = _t([1.0, 2.0, 3.0], device)
    r = sparsification(err, -err, metric="mae", steps=4)
    # oracle (smallest kept): means of [1,2,3], [1,2], [1], [1] = 2, 1.5, 1, 1
    # reversed (largest kept): means of [1,2,3], [2,3], [3], [3] = 2, 2.5, 3, 3; scale 3
    assert r.oracle.tolist() == pytest.approx([2 / 3, 0.5, 1 / 3, 1 / 3])
    assert r.uncertainty.tolist() == pytest.approx([2 / 3, 5 / 6, 1.0, 1.0])
    assert r.scale == pytest.approx(3.0)
    # U - O = [0, 1/3, 2/3, 2/3]: .25 * (1/6 + 1/2 + 2/3) = 1/3
    assert r.ause == pytest.approx(1 / 3)


def test_hand_computed_rmse(device):
    err = _t([1.0, 2.0, 3.0, 4.0], device)
    r = sparsification(err, -err, metric="rmse", steps=2)
    # keep 4 then 2. oracle: sqrt(30/4), sqrt(5/2); reversed: sqrt(30/4), sqrt(25/2); scale sqrt(12.5)
    s = 12.5**0.5
    assert r.oracle.tolist() == pytest.approx([(7.5**0.5) / s, (2.5**0.5) / s])
    assert r.uncertainty.tolist() == pytest.approx([(7.5**0.5) / s, 1.0])
    assert r.ause == pytest.approx(0.5 * 0.5 * (1.0 - (2.5**0.5) / s))
    rm = sparsification(err, -err, metric="mse", steps=2)
    assert rm.uncertainty.tolist() == pytest.approx([7.5 / 12.5, 1.0])


def test_reversed_is_the_maximum(device):
    g = torch.Generator().manual_seed(1)
    err = torch.rand(500, generator=g, dtype=torch.float64).to(device)
    worst = sparsification(err, -err).ause
    assert worst > 0.2
    for seed in range(5):
        gg = torch.Generator().manual_seed(100 + seed)
        u = torch.rand(500, generator=gg, dtype=torch.float64).to(device)
        assert sparsification(err, u).ause <= worst + 1e-12


def test_ties_use_group_mean(device):
    err = _t([1.0, 2.0, 3.0, 4.0], device)
    unc = _t([0.0, 0.0, 1.0, 1.0], device)
    r = sparsification(err, unc, metric="mae", steps=4)
    # groups {1,2} (mean 1.5), {3,4} (mean 3.5): keep 4 -> 2.5, 3 -> (1.5+1.5+3.5)/3, 2 -> 1.5, 1 -> 1.5
    raw = [2.5, 6.5 / 3, 1.5, 1.5]
    assert (r.uncertainty * r.scale).tolist() == pytest.approx(raw)


def test_ties_deterministic_under_permutation(device):
    g = torch.Generator().manual_seed(2)
    n = 2000
    err = torch.rand(n, generator=g).to(device)
    # 60% exactly zero std (a big tied area) and a few small tie groups
    unc = torch.randint(0, 5, (n,), generator=g).float().to(device)
    unc[: int(0.6 * n)] = 0.0
    ref = sparsification_all(err, unc)
    for seed in range(4):
        perm = torch.randperm(n, generator=torch.Generator().manual_seed(seed)).to(device)
        got = sparsification_all(err[perm], unc[perm])
        for m in ("mae", "mse", "rmse"):
            assert torch.allclose(got[m].uncertainty, ref[m].uncertainty, atol=1e-12, rtol=0)
            assert got[m].ause == pytest.approx(ref[m].ause, abs=1e-12)


def test_all_zero_std_and_constant_error_no_nan(device):
    err = torch.rand(300, generator=torch.Generator().manual_seed(3)).to(device)
    r = sparsification(err, torch.zeros_like(err))
    # one tie group: the uncertainty curve is flat at the mean, like a random uncertainty
    assert torch.isfinite(r.uncertainty).all() and r.ause > 0
    assert r.aurg == pytest.approx(0.0, abs=1e-12)
    const = sparsification(torch.full((300,), 0.2, device=device), err)
    assert const.ause == pytest.approx(0.0, abs=1e-12)
    zero = sparsification(torch.zeros(300, device=device), torch.zeros(300, device=device))
    assert zero.ause == 0.0 and torch.isfinite(zero.oracle).all()


def test_channels_mask_and_nonfinite(device):
    g = torch.Generator().manual_seed(4)
    err = torch.rand(6, 7, 3, generator=g).to(device)
    std = torch.rand(6, 7, 1, generator=g).to(device)  # one std per pixel, shared by channels
    mask = torch.zeros(6, 7, dtype=torch.bool, device=device)
    mask[:3] = True
    r = sparsification(err, std, mask=mask, steps=10)
    assert r.num_elements == 3 * 7 * 3
    ref = sparsification(err[:3], std[:3].expand(3, 7, 3).contiguous(), steps=10)
    assert r.ause == pytest.approx(ref.ause, abs=1e-12)
    err2 = err.clone()
    err2[0, 0, 0] = float("nan")
    assert sparsification(err2, std, steps=10).num_elements == 6 * 7 * 3 - 1
    empty = sparsification(err, std, mask=torch.zeros_like(mask), steps=10)
    assert empty.num_elements == 0 and empty.ause != empty.ause  # NaN


def test_fewer_elements_than_steps(device):
    r = sparsification(_t([0.5, 0.1], device), _t([1.0, 0.0], device), steps=100)
    assert torch.isfinite(r.uncertainty).all()
    assert r.ause == pytest.approx(0.0, abs=1e-12)


def test_mean_curves_average(device):
    a = sparsification(_t([1.0, 2.0, 3.0, 4.0], device), _t([4.0, 3.0, 2.0, 1.0], device), steps=4)
    b = sparsification(_t([1.0, 2.0, 3.0, 4.0], device), _t([1.0, 2.0, 3.0, 4.0], device), steps=4)
    m = mean_curves([a, b])
    assert m.ause == pytest.approx((a.ause + b.ause) / 2)
    assert float(torch.trapezoid(m.uncertainty - m.oracle, m.fractions)) == pytest.approx(m.ause)


def test_million_elements(device):
    """A full-resolution image's worth of pixels (how fast it is: benchmarks/bench_evaluate.py)."""
    g = torch.Generator().manual_seed(5)
    err_cpu = torch.rand(10**6, generator=g)
    err = err_cpu.to(device)
    unc = (err_cpu + 0.3 * torch.rand(10**6, generator=g)).to(device)
    res = sparsification_all(err, unc)
    assert 0 < res["mae"].ause < sparsification(err, -err).ause


class TestInputsAndAverages:
    """What enters the curves (|error|, finite uncertainties, at least 2 steps) and how per-view results
    average."""

    def test_signed_errors_count_by_their_magnitude(self, device):
        # the reversed case of test_hand_computed_reversed_mae with alternating signs: the same numbers
        err = _t([1.0, -2.0, 3.0, -4.0], device)
        r = sparsification(err, -err.abs(), metric="mae", steps=4)
        assert r.oracle.tolist() == pytest.approx([0.625, 0.5, 0.375, 0.25])
        assert r.uncertainty.tolist() == pytest.approx([0.625, 0.75, 0.875, 1.0])
        assert r.scale == pytest.approx(4.0) and r.ause == pytest.approx(0.28125)
        # a ranking by the magnitude is perfect however the signs fall
        assert sparsification(err, err.abs(), metric="mae", steps=4).ause == pytest.approx(0.0, abs=1e-12)

    def test_non_finite_uncertainty_drops_the_element(self, device):
        err = _t([1.0, 2.0, 3.0, 4.0, 9.0], device)
        for bad in (float("nan"), float("inf")):
            unc = _t([4.0, 3.0, 2.0, 1.0, bad], device)
            r = sparsification(err, unc, metric="mae", steps=4)
            assert r.num_elements == 4
            # exactly the reversed case of test_hand_computed_reversed_mae (the 9 is gone)
            assert r.uncertainty.tolist() == pytest.approx([0.625, 0.75, 0.875, 1.0])
            assert r.ause == pytest.approx(0.28125)

    def test_fewer_than_two_steps_are_refused(self, device):
        err = _t([1.0, 2.0], device)
        with pytest.raises(ValueError, match="steps must be >= 2"):
            sparsification(err, err, steps=1)
        assert sparsification(err, err, steps=2).fractions.tolist() == [0.0, 0.5]

    def test_mean_curves_average_ause_aurg_and_sum_the_elements(self, device):
        err = _t([1.0, 2.0, 3.0, 4.0], device)
        reversed_ = sparsification(err, -err, steps=4)  # AUSE 0.28125, AURG -0.140625 (hand-computed above)
        perfect = sparsification(err, err, steps=4)  # AUSE 0, AURG 0.225
        m = mean_curves([reversed_, perfect])
        assert m.ause == pytest.approx((0.28125 + 0.0) / 2)
        assert m.aurg == pytest.approx((-0.140625 + 0.225) / 2)
        assert m.num_elements == 8
        # oracle: [0.625, 0.5, 0.375, 0.25] and [1, 0.8, 0.6, 0.4] (scale 2.5)
        assert m.oracle.tolist() == pytest.approx([0.8125, 0.65, 0.4875, 0.325])

    def test_mean_curves_skip_views_without_valid_elements(self, device):
        err = _t([1.0, 2.0, 3.0, 4.0], device)
        a = sparsification(err, -err, steps=4)
        empty = sparsification(err, err, mask=torch.zeros(4, dtype=torch.bool, device=device), steps=4)
        assert empty.num_elements == 0
        m = mean_curves([a, empty])
        assert m.ause == pytest.approx(a.ause) and m.aurg == pytest.approx(a.aurg) and m.num_elements == 4
        assert m.uncertainty.tolist() == pytest.approx(a.uncertainty.tolist())
        with pytest.raises(ValueError, match="no view has valid elements"):
            mean_curves([empty])
