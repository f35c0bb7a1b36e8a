"""The informed posterior (``variational.informed_tables``): closed forms, extremes, the render it preserves,
and the empty-ray term of the Monte-Carlo maps (``mc_render(empty_std=...)``)."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from uncertsplat.config import TrainConfig
from uncertsplat.gaussians.prior import Prior
from uncertsplat.gaussians.variational import (
    expected_gate,
    gate_off_probability,
    informed_position_prior,
    informed_tables,
    mean_params,
    posterior_mean,
    posterior_summary,
    random_model,
)
from uncertsplat.types import Cameras, RenderOutput
from uncertsplat.uncertainty.mc import mc_render

EXTENT = 2.0


def _model(n=64, k=10, seed=0):
    g = torch.Generator().manual_seed(seed)
    return random_model(n, g, num_entries=k, carrier_fraction=0.75, extent=EXTENT)


def _fisher(model, means=0.0, scales=0.0, opacities=0.0):
    n = len(model)
    return {"means": torch.full((n, 3), float(means)), "scales": torch.full((n, 3), float(scales)),
            "opacities": torch.full((n,), float(opacities))}


class TestClosedForm:
    def test_unseen_gaussians_keep_the_prior(self):
        """F = 0 (no view sees them): the prior's spread, width and switch-off probability."""
        prior = Prior()
        model = _model()
        info = informed_tables(model, _fisher(model), prior, extent=EXTENT, position_prior_scale=0.0)
        t = model.tables
        torch.testing.assert_close(F.softplus(t["pos_spread_raw"]), torch.full_like(t["pos_loc"], prior.position_std))
        torch.testing.assert_close(F.softplus(t["scale_width_raw"]), torch.full_like(t["pos_loc"], prior.scale_width),
                                   rtol=1e-5, atol=1e-6)
        off = gate_off_probability(t["gate_loc"], F.softplus(t["gate_spread_raw"]))
        p0 = float(gate_off_probability(torch.tensor(prior.gate_mean), torch.tensor(prior.gate_std)))
        torch.testing.assert_close(off, torch.full_like(off, p0), rtol=1e-4, atol=1e-6)
        assert info["data_dominated"] == 0.0

    def test_position_spread_is_the_laplace_one(self):
        prior = Prior()
        model = _model()
        fisher = _fisher(model)
        fisher["means"] = torch.rand(len(model), 3, generator=torch.Generator().manual_seed(1)) * 1e6
        idx = model.carrier_index()
        own = posterior_mean(model, extent=EXTENT).scales[idx].log().mean(1).exp()
        informed_tables(model, fisher, prior, extent=EXTENT, position_prior_scale=1.0)
        prior_std = own.clamp_min(prior.position_std * EXTENT)
        expected = (fisher["means"][idx] + prior_std[:, None] ** -2) ** -0.5 / EXTENT  # table unit: the extent
        got = F.softplus(model.tables["pos_spread_raw"])  # [P,K,3]
        torch.testing.assert_close(got, expected[:, None, :].expand_as(got), rtol=1e-4, atol=1e-9)
        assert float(model.tables["pos_loc"].detach().abs().max()) == 0.0

    def test_position_prior_is_capped_by_the_depth_to_the_nearest_camera(self):
        """F = 0: the prior's spread, unless a fraction of the distance to the nearest training camera is smaller
        (a large, unconstrained Gaussian must not be sampled in front of a camera)."""
        prior = Prior()
        model = _model()
        idx = model.carrier_index()
        with torch.no_grad():
            before = posterior_mean(model, extent=EXTENT)
        own = before.scales[idx].log().mean(1).exp()
        prior_std = own.clamp_min(prior.position_std * EXTENT)  # [P]
        # one camera at the first carrier's centre, one far away: that carrier gets spread 0, the others
        # fraction x their distance where that is below their own prior
        centers = torch.stack([before.means[idx[0]], torch.tensor([100.0, 0.0, 0.0])])
        depth = torch.cdist(before.means[idx], centers).amin(1)
        fraction = float((prior_std[1:] / depth[1:]).median())  # caps about half of the others
        informed_tables(model, _fisher(model), prior, extent=EXTENT, position_prior_scale=1.0,
                        camera_centers=centers, position_depth_fraction=fraction)
        expected = torch.minimum(prior_std, fraction * depth) / EXTENT
        got = F.softplus(model.tables["pos_spread_raw"]).detach()  # [P,K,3]
        torch.testing.assert_close(got, expected[:, None, None].expand_as(got), rtol=1e-4, atol=1e-9)
        assert float(got[0].max()) < 1e-9
        capped = (fraction * depth < prior_std)[1:]
        assert 0 < int(capped.sum()) < capped.numel(), "the test caps some carriers and leaves others"

    def test_disagreement_widens_the_spread_up_to_the_prior(self):
        """Sandwich: views that agree as the noise predicts (D = F) leave the Laplace spread; views that
        disagree widen it by (D - F) / (F + prior precision)^2, never beyond the prior; views that agree better than
        the noise predicts (D < F: a chance of few views) never narrow it below the Laplace spread."""
        prior = Prior()
        f = torch.rand(64, 3, generator=torch.Generator().manual_seed(1)) * 1e6 + 1e4
        spreads = []
        for d in (f, 2.0 * f, 1e6 * f, 0.5 * f):
            model = _model()
            fisher = _fisher(model)
            fisher["means"] = f.clone()
            dis = {"means": d, "scales": torch.zeros(64, 3)}
            idx = model.carrier_index()
            own = posterior_mean(model, extent=EXTENT).scales[idx].log().mean(1).exp()
            informed_tables(model, fisher, prior, extent=EXTENT, position_prior_scale=1.0, disagreement=dis)
            spreads.append(F.softplus(model.tables["pos_spread_raw"])[:, 0] * EXTENT)  # [P,3] world units
        prior_std = own.clamp_min(prior.position_std * EXTENT)[:, None]
        prec = f[idx] + prior_std**-2
        torch.testing.assert_close(spreads[0], prec**-0.5, rtol=1e-4, atol=1e-9)
        torch.testing.assert_close(spreads[1], (1 / prec + f[idx] / prec**2).sqrt(), rtol=1e-4, atol=1e-9)
        torch.testing.assert_close(spreads[2], prior_std.expand_as(spreads[2]), rtol=1e-4, atol=1e-9)
        torch.testing.assert_close(spreads[3], spreads[0], rtol=0, atol=0)

    def test_gate_follows_the_evidence(self):
        """dL = F_a / (2 (1 - o)^2) nats against 'off': none keeps the prior's odds, a lot switches it on."""
        prior = Prior()
        model = _model()
        idx = model.carrier_index()
        o = posterior_mean(model, extent=EXTENT).opacities[idx]
        drop = torch.linspace(0.0, 50.0, idx.numel())
        fisher = _fisher(model)
        fisher["opacities"][idx] = drop * 2.0 * (1.0 - o) ** 2
        informed_tables(model, fisher, prior, extent=EXTENT)
        t = model.tables
        off = gate_off_probability(t["gate_loc"][:, 0, 0], F.softplus(t["gate_spread_raw"][:, 0, 0]))
        p0 = float(gate_off_probability(torch.tensor(prior.gate_mean), torch.tensor(prior.gate_std)))
        expected = torch.sigmoid(math.log(p0 / (1 - p0)) - drop)
        torch.testing.assert_close(off, expected, rtol=2e-3, atol=1e-7)
        assert bool((off[1:] <= off[:-1]).all())  # more evidence, never more likely off

    def test_the_record_counts_the_data_dominated_and_gives_the_median_switch_off(self):
        """``informed_tables``' record: ``data_dominated`` the share of carriers whose position variance is below half
        the prior's (F = 3 / p^2: a quarter of it; F = 0.5 / p^2: two thirds, not counted), ``gate_off_median`` the
        median switch-off probability (most carriers unseen at the prior's, the rest switched on: the prior's)."""
        prior = Prior()
        model = _model()
        idx = model.carrier_index()
        p = idx.numel()
        pos_var = (prior.position_std * EXTENT) ** 2  # position_prior_scale 0: the config's std for every carrier
        fisher = _fisher(model)
        fisher["means"][idx[: p // 3]] = 3.0 / pos_var
        fisher["means"][idx[p // 3:]] = 0.5 / pos_var
        fisher["opacities"][idx[: p // 4]] = 1e6
        info = informed_tables(model, fisher, prior, extent=EXTENT, position_prior_scale=0.0)
        assert info["carriers"] == p and info["data_dominated"] == pytest.approx((p // 3) / p)
        p0 = float(gate_off_probability(torch.tensor(prior.gate_mean), torch.tensor(prior.gate_std)))
        assert info["gate_off_median"] == pytest.approx(p0, rel=1e-4)

    def test_the_mean_render_is_preserved(self):
        """Base opacity, scale and position absorb the change of expected gate, multiplier and location."""
        prior = Prior()
        model = _model()
        with torch.no_grad():  # tables away from the prior, as SGD might have left them
            for v in model.tables.values():
                v.add_(0.05 * torch.randn(v.shape, generator=torch.Generator().manual_seed(3)))
        before = posterior_mean(model, extent=EXTENT)
        fisher = _fisher(model, means=1e4, scales=1e3, opacities=30.0)
        informed_tables(model, fisher, prior, extent=EXTENT)
        after = posterior_mean(model, extent=EXTENT)
        torch.testing.assert_close(after.means, before.means, rtol=0, atol=1e-5)
        torch.testing.assert_close(after.scales, before.scales, rtol=1e-4, atol=1e-7)
        torch.testing.assert_close(after.opacities, before.opacities, rtol=1e-3, atol=1e-4)


class TestExtremes:
    @pytest.mark.parametrize("k", [1, 10])
    def test_one_entry_and_huge_or_zero_curvature(self, k):
        model = _model(k=k)
        for value in (0.0, 1e-30, 1e30):
            informed_tables(model, _fisher(model, value, value, value), Prior(), extent=EXTENT)
            for v in model.tables.values():
                assert bool(torch.isfinite(v).all())
            for v in model.params.values():
                assert bool(torch.isfinite(v).all())

    def test_summary_measures_against_the_per_carrier_prior(self):
        """train_summary's posterior block for the informed posterior: unseen carriers (F = 0) sit exactly at the
        per-carrier prior the update used (KL 0 for the position, spread ratio 1) and a carrier no larger than
        the config's std is measured the same either way, while against the config's single std a carrier larger
        than it reads as a posterior wider than its prior (ratio > 1)."""
        prior = Prior()
        model = _model()
        cams = torch.tensor([[0.0, 0.0, -6.0], [5.0, 0.0, 0.0]])
        kw = dict(extent=EXTENT, position_prior_scale=1.0, camera_centers=cams, position_depth_fraction=0.1)
        informed_tables(model, _fisher(model), prior, **kw)
        std = informed_position_prior(model, prior, **kw)  # [P] table units
        torch.testing.assert_close(F.softplus(model.tables["pos_spread_raw"][:, 0, 0]), std, rtol=1e-5, atol=1e-9)
        per = posterior_summary(model, prior, position_prior_std=std)
        assert per["position_prior"] == "per_carrier"
        assert per["position_spread_ratio"]["q10"] == pytest.approx(1.0, rel=1e-4)
        assert per["position_spread_ratio"]["q90"] == pytest.approx(1.0, rel=1e-4)
        fixed = posterior_summary(model, prior)
        assert fixed["position_prior"] == "config" and fixed["position_spread_ratio"]["q90"] > 1.5
        # the gate and the scale width keep the config's prior at F = 0: nothing moved at all
        assert per["moved_fraction"] == 0.0 and per["kl_nats"]["q90"] == pytest.approx(0.0, abs=1e-4)
        assert fixed["moved_fraction"] > 0.5
        # with data the per-carrier ratio is the Laplace shrinkage, never above 1
        fisher = _fisher(model)
        fisher["means"] = torch.rand(len(model), 3, generator=torch.Generator().manual_seed(1)) * 1e4
        informed_tables(model, fisher, prior, **kw)
        s = posterior_summary(model, prior, position_prior_std=informed_position_prior(model, prior, **kw))
        assert s["position_spread_ratio"]["q90"] <= 1.0 + 1e-5 and s["position_spread_ratio"]["q10"] < 0.5
        with pytest.raises(ValueError, match="one std per carrier"):
            posterior_summary(model, prior, position_prior_std=std[:-1])

    def test_no_carriers(self):
        g = torch.Generator().manual_seed(0)
        model = random_model(8, g, carrier_fraction=0.0)
        assert informed_tables(model, _fisher(model), Prior())["carriers"] == 0

    def test_paper_variant_is_refused(self):
        model = _model()
        with pytest.raises(ValueError, match="ours"):
            informed_tables(model, _fisher(model), Prior(variant="paper"))
        with pytest.raises(ValueError, match="informed"):
            TrainConfig(variant="paper", variational={"posterior": "informed"})
        assert TrainConfig().posterior == "informed" and TrainConfig(variant="paper").posterior == "sgd"
        # a config written for 'ours' and switched to 'paper' (e.g. by a sweep axis) keeps working
        data = TrainConfig().model_dump()
        assert TrainConfig.model_validate({**data, "variant": "paper"}).posterior == "sgd"

    def test_mean_params_render_like_the_posterior_mean(self):
        model = _model()
        p = mean_params(model, extent=EXTENT)
        pm = posterior_mean(model, extent=EXTENT)
        torch.testing.assert_close(torch.exp(p["scales"]), pm.scales)
        torch.testing.assert_close(torch.sigmoid(p["opacities"]), pm.opacities, rtol=1e-4, atol=1e-6)
        assert expected_gate(torch.tensor(30.0), torch.tensor(2.0), 0.2) > 0.999


class TestEmptyRays:
    @staticmethod
    def _render(alpha_value):
        def render_fn(sample, cams):
            h, w = cams.height, cams.width
            a = torch.full((1, h, w, 1), alpha_value)
            return RenderOutput(rgb=torch.full((1, h, w, 3), 0.3) * a, alpha=a, depth=torch.ones(1, h, w, 1),
                                depth_expected=a, means2d=torch.zeros(1, 0, 2), radii=torch.zeros(1, 0),
                                depths=torch.zeros(1, 0))
        return render_fn

    def _cams(self):
        return Cameras(torch.eye(4)[None], torch.eye(3)[None], 4, 3, ("a.png",))

    @pytest.mark.parametrize("alpha", [0.0, 0.25, 1.0])
    def test_std_of_the_missing_surface(self, alpha):
        """Identical samples: the only spread is (1 - alpha) x the unknown surface's std."""
        maps, _ = mc_render(lambda g: None, self._render(alpha), self._cams(), 4, torch.Generator(),
                            empty_std=(0.3, 2.0))
        torch.testing.assert_close(maps.rgb_std, torch.full_like(maps.rgb_std, (1 - alpha) * 0.3))
        torch.testing.assert_close(maps.depth_std, torch.full_like(maps.depth_std, (1 - alpha) * 2.0))
        plain, _ = mc_render(lambda g: None, self._render(alpha), self._cams(), 4, torch.Generator())
        assert float(plain.rgb_std.abs().max()) == 0.0

    @pytest.mark.parametrize(("alpha", "coverage"), [(0.0, 0.8), (0.4, 0.8), (0.8, 0.8), (0.95, 0.8), (0.5, 1e-3)])
    def test_coverage(self, alpha, coverage):
        """Only the part of the ray below the coverage the model reaches on its training views is unknown:
        (1 - alpha / coverage)_+ x the unknown surface's std."""
        maps, _ = mc_render(lambda g: None, self._render(alpha), self._cams(), 3, torch.Generator(),
                            empty_std=(0.3, 2.0), coverage=coverage)
        gap = max(0.0, 1.0 - alpha / coverage)
        torch.testing.assert_close(maps.rgb_std, torch.full_like(maps.rgb_std, gap * 0.3))
        torch.testing.assert_close(maps.depth_std, torch.full_like(maps.depth_std, gap * 2.0))

    def test_coverage_varies_over_samples(self):
        """E over the samples of the clipped gap squared: samples at alpha 0 and 1 with coverage 0.5 give gaps 1
        and 0, so the empty-ray variance is 0.5 x std^2 (plus the samples' own spread)."""
        alphas = iter([0.0, 1.0])
        render = self._render(0.0)

        def render_fn(sample, cams):
            a = next(alphas)
            out = render(sample, cams)
            return RenderOutput(rgb=torch.zeros_like(out.rgb), alpha=torch.full_like(out.alpha, a),
                                depth=torch.ones_like(out.depth), depth_expected=out.depth_expected,
                                means2d=out.means2d, radii=out.radii, depths=out.depths)

        maps, _ = mc_render(lambda g: None, render_fn, self._cams(), 2, torch.Generator(), empty_std=(0.3, 2.0),
                            coverage=0.5)
        torch.testing.assert_close(maps.rgb_std, torch.full_like(maps.rgb_std, (0.5 * 0.3**2) ** 0.5))

    @pytest.mark.parametrize("coverage", [0.0, -0.1, 1.5, float("nan")])
    def test_bad_coverage(self, coverage):
        with pytest.raises(ValueError, match="coverage"):
            mc_render(lambda g: None, self._render(0.5), self._cams(), 2, torch.Generator(), empty_std=(0.3, 2.0),
                      coverage=coverage)

    def test_training_coverage(self):
        """The quantile of the training cameras' alpha; at least 1e-3; 1 without cameras."""
        from uncertsplat.uncertainty.mc import training_coverage

        values = torch.linspace(0.0, 1.0, 12).reshape(1, 3, 4, 1)

        def render_fn(sample, cams):
            return RenderOutput(rgb=torch.zeros(1, 3, 4, 3), alpha=values, depth=torch.ones(1, 3, 4, 1),
                                depth_expected=values, means2d=torch.zeros(1, 0, 2), radii=torch.zeros(1, 0),
                                depths=torch.zeros(1, 0))

        cams = Cameras(torch.eye(4)[None].repeat(3, 1, 1), torch.eye(3)[None].repeat(3, 1, 1), 4, 3,
                       ("a.png", "b.png", "c.png"))
        assert training_coverage(None, cams, render_fn, quantile=0.5) == pytest.approx(0.5)
        assert training_coverage(None, cams, render_fn, quantile=0.0) == pytest.approx(1e-3)
        assert training_coverage(None, cams[[]], render_fn) == 1.0
