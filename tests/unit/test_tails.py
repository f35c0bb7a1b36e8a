"""The Student-t predictive (``eval.tails``): its coverage, half-widths, NLL and the fit of its degrees of freedom,
against scipy's t and at the extremes; the calibration table and the NLL with it."""

from __future__ import annotations

import math

import pytest
import torch

from uncertsplat.eval import tails
from uncertsplat.eval.calibration import calibration, mean_calibration, nominal_coverage
from uncertsplat.eval.nll import gaussian_nll, predictive_nll

stats = pytest.importorskip("scipy.stats")


def unit_t(dof: float, n: int, seed: int) -> torch.Tensor:
    """n draws of the unit-variance t."""
    g = torch.Generator().manual_seed(seed)
    chi2 = 2.0 * torch._standard_gamma(torch.full((n,), dof / 2, dtype=torch.float64), generator=g)
    return torch.randn(n, dtype=torch.float64, generator=g) / torch.sqrt(chi2 / dof) * math.sqrt((dof - 2) / dof)


class TestAgainstScipy:
    @pytest.mark.parametrize("dof", [tails.MIN_DOF, 2.5, 3.5, 5.0, 30.0, tails.MAX_DOF])
    @pytest.mark.parametrize("x", [1e-3, 0.5, 1.0, 3.0, 25.0, 1e4])
    def test_coverage(self, dof, x):
        scale = math.sqrt((dof - 2) / dof)
        assert tails.coverage(x, dof) == pytest.approx(2 * stats.t.cdf(x / scale, dof) - 1, abs=1e-9)

    @pytest.mark.parametrize("dof", [tails.MIN_DOF, 3.0, 4.3, 100.0])
    @pytest.mark.parametrize("p", [0.0, 0.3829, 0.6827, 0.9973, 0.999999])
    def test_half_width(self, dof, p):
        want = stats.t.ppf(0.5 + p / 2, dof) * math.sqrt((dof - 2) / dof)
        assert tails.half_width(p, dof) == pytest.approx(want, rel=1e-7, abs=1e-12)

    @pytest.mark.parametrize("dof", [tails.MIN_DOF, 4.0, 50.0])
    def test_log_density(self, dof):
        z = torch.tensor([0.0, 0.3, -2.0, 40.0, 1e6], dtype=torch.float64)
        scale = math.sqrt((dof - 2) / dof)
        want = stats.t.logpdf(z.numpy(), dof, scale=scale)
        assert torch.allclose(tails.log_density(z, dof), torch.from_numpy(want), rtol=1e-10, atol=1e-10)

    def test_the_gaussian(self):
        assert tails.coverage(1.0, None) == pytest.approx(nominal_coverage(1.0), abs=1e-15)
        assert tails.half_width(nominal_coverage(2.0), None) == pytest.approx(2.0, rel=1e-8)
        # a large nu is the Gaussian within a thousandth of coverage
        for k in (0.5, 1.0, 3.0):
            assert tails.coverage(k, tails.MAX_DOF) == pytest.approx(nominal_coverage(k), abs=1e-3)


class TestNLL:
    def test_none_is_the_gaussian_nll(self, device):
        g = torch.Generator().manual_seed(1)
        target, mean = torch.rand(4, 5, 3, generator=g).to(device), torch.rand(4, 5, 3, generator=g).to(device)
        std = (0.1 * torch.rand(4, 5, 3, generator=g)).to(device)
        std[0] = 0.0  # floored
        assert torch.allclose(predictive_nll(target, mean, std, None), gaussian_nll(target, mean, std))

    def test_matches_scipy_with_the_floor(self):
        e = torch.tensor([0.0, 0.01, -0.3, 2.0], dtype=torch.float64)
        std = torch.tensor([0.02, 0.0, 0.1, 0.05], dtype=torch.float64)
        dof = 3.2
        s = std.clamp_min(1e-3)
        want = -stats.t.logpdf(e.numpy(), dof, scale=(s * math.sqrt((dof - 2) / dof)).numpy())
        got = predictive_nll(e, torch.zeros_like(e), std, dof, reduction="none")
        assert torch.allclose(got, torch.from_numpy(want), rtol=1e-10)

    def test_heavy_tailed_errors_prefer_the_t(self):
        e = unit_t(4.0, 200_000, 0) * 0.05
        std = torch.full_like(e, 0.05)
        assert float(predictive_nll(e, torch.zeros_like(e), std, 4.0)) < float(gaussian_nll(e, torch.zeros_like(e), std)) - 0.05

    def test_extremes_stay_finite(self):
        e = torch.tensor([1e6, -1e6, 0.0], dtype=torch.float64)
        std = torch.tensor([0.0, 1e-30, 1e6], dtype=torch.float64)
        for dof in (tails.MIN_DOF, tails.MAX_DOF):
            assert torch.isfinite(predictive_nll(e, torch.zeros_like(e), std, dof, reduction="none")).all()
        with pytest.raises(ValueError, match="degrees of freedom"):
            predictive_nll(e, e, std, 2.0)
        with pytest.raises(ValueError, match="degrees of freedom"):
            tails.coverage(1.0, float("nan"))
        with pytest.raises(ValueError, match="probability"):
            tails.half_width(1.0, 4.0)


class TestFit:
    @pytest.mark.parametrize("dof", [2.5, 4.0, 10.0])
    def test_recovers_the_degrees_of_freedom(self, dof):
        z = unit_t(dof, 400_000, 2)
        z = z / z.square().mean().sqrt()
        assert tails.fit_dof(z) == pytest.approx(dof, rel=0.1)

    def test_gaussian_z_give_the_gaussian_or_a_large_dof(self):
        z = torch.randn(400_000, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
        dof = tails.fit_dof(z)
        assert dof is None or dof > 50

    def test_a_best_fit_past_the_largest_dof_is_the_gaussian(self):
        """z-scores shaped exactly as the unit-variance t with nu = 1500 (its quantiles): the likelihood peaks past
        MAX_DOF, so the grid's last point is best and beats the Gaussian; that end is reported as the Gaussian
        (None), not as a nu a hair under MAX_DOF from a search against the grid's end."""
        nu, n = 1500.0, 200_000
        q = (torch.arange(n, dtype=torch.float64) + 0.5) / n
        z = torch.from_numpy(stats.t.ppf(q.numpy(), df=nu)) * math.sqrt((nu - 2) / nu)
        z = z / z.square().mean().sqrt()
        assert tails.fit_dof(z) is None

    def test_nothing_to_fit(self):
        assert tails.fit_dof(torch.empty(0)) is None
        assert tails.fit_dof(torch.tensor([float("nan"), float("inf")])) is None
        # too few z-scores for the tails to say anything: the Gaussian, however heavy they look
        few = unit_t(2.5, tails.MIN_FIT_ELEMENTS - 1, 7)
        assert tails.fit_dof(few / few.square().mean().sqrt()) is None
        assert tails.fit_dof(torch.cat([few, torch.full((1,), float("nan"), dtype=few.dtype)])) is None

    @pytest.mark.parametrize("kind", ["zeros", "cauchy"])
    def test_the_heaviest_tails_give_a_valid_dof(self, kind):
        """z-scores whose best fit is the grid's lower end (all 0: the most peaked t; Cauchy's tails, heavier than
        any t with a variance) give MIN_DOF exactly, which every use of the dof accepts (a value a rounding below it
        stopped `evaluate`)."""
        if kind == "zeros":
            z = torch.zeros(tails.MIN_FIT_ELEMENTS, dtype=torch.float64)
        else:
            u = torch.rand(200_000, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
            z = torch.tan(math.pi * (u - 0.5))  # Cauchy
            z = z / z.square().mean().sqrt()
        dof = tails.fit_dof(z)
        assert dof == tails.MIN_DOF
        assert 0.0 < tails.coverage(1.0, dof) < 1.0
        assert math.isfinite(float(tails.nll(z, torch.zeros_like(z), torch.ones_like(z), dof).mean()))

    def test_many_elements_are_strided(self, monkeypatch):
        z = unit_t(4.0, 200_000, 4)
        z = z / z.square().mean().sqrt()
        every = tails.fit_dof(z)
        strided = tails.fit_dof(z[::200])  # the 1000 z-scores a stride of 200 keeps
        monkeypatch.setattr(tails, "FIT_ELEMENTS", 1000)
        assert tails.fit_dof(z) == strided != every  # the fit saw only the strided ones
        assert strided == pytest.approx(4.0, rel=0.5)  # and 1000 of them still say nu ~ 4


class TestCalibration:
    def test_t_errors_are_calibrated_only_with_the_t(self, device):
        g = torch.Generator().manual_seed(5)
        std = (0.01 + 0.2 * torch.rand(300_000, generator=g, dtype=torch.float64))
        err = (unit_t(3.5, 300_000, 6) * std).to(device)
        std = std.to(device)
        gaussian = calibration(err, std)
        t = calibration(err, std, dof=3.5)
        assert t.calibration_error < 0.005 < 0.03 < gaussian.calibration_error
        # the t's intervals: narrower than k std at small k, wider at k = 3
        assert t.half_widths[0] < 0.5 and t.half_widths[-1] > 3.0 and t.dof == 3.5
        assert gaussian.half_widths == gaussian.ks and gaussian.dof is None

    def test_tables_of_different_predictives_do_not_average(self):
        e, s = torch.randn(100), torch.ones(100)
        with pytest.raises(ValueError, match="predictives"):
            mean_calibration([calibration(e, s), calibration(e, s, dof=4.0)])
        both = mean_calibration([calibration(e, s, dof=4.0), calibration(e * 2, s, dof=4.0)])
        assert both.dof == 4.0 and both.half_widths == calibration(e, s, dof=4.0).half_widths


def test_the_configs_refuse_what_the_arithmetic_cannot_take():
    """nu far past MAX_DOF gave a wrong NLL (1e15: 17.7 for -1.56) or a traceback (1e300); seeds of 2**32 and more
    repeat smaller ones (torch's CPU generator keeps 32 bits); a std floor near the std undoes the std factor; a depth
    factor beyond float32 was a traceback."""
    from pydantic import ValidationError

    from uncertsplat.config import MAX_DEGREES_OF_FREEDOM, EvalConfig, PruneConfig, SelectConfig
    from uncertsplat.eval.tails import MAX_DOF
    from uncertsplat.predict import MAX_SEED

    assert MAX_DEGREES_OF_FREEDOM == MAX_DOF and MAX_SEED == 2**32 - 1
    assert EvalConfig(degrees_of_freedom=MAX_DOF, seed=2**32 - 1, std_floor=0.01, depth_scale=1e30).seed == 2**32 - 1
    for bad in ({"degrees_of_freedom": 1e15}, {"seed": 2**32}, {"std_floor": 0.1}, {"depth_scale": 1e39}):
        with pytest.raises(ValidationError):
            EvalConfig(**bad)
    for model, bad in ((PruneConfig, {"seed": 2**32}), (PruneConfig, {"num_samples": 10_001}),
                       (SelectConfig, {"seed": 2**32}), (SelectConfig, {"seed": -1}),
                       (SelectConfig, {"around_radius": 1e300})):
        with pytest.raises(ValidationError):
            model(**bad)
