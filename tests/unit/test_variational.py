"""Offset tables: KL terms, priors, sampling statistics, determinism, scene-scale equivariance."""

import itertools
import json
import math

import pytest
import torch
import torch.nn.functional as F
from torch.distributions import Normal, Uniform, kl_divergence

from uncertsplat.gaussians.variational import (
    MIN_WIDTH,
    Prior,
    expected_constants,
    expected_gate,
    expected_render_sample,
    gaussian_kl,
    inverse_softplus,
    kl_terms,
    log_softplus,
    posterior_mean,
    posterior_summary,
    prior_rows,
    random_model,
    sample,
    scale_kl,
)


def gen(seed=0, device="cpu"):
    return torch.Generator(device=device).manual_seed(seed)


@pytest.mark.parametrize("variant", ["ours", "paper"])
def test_kl_zero_at_prior(variant):
    prior = Prior(variant=variant)
    m = random_model(40, gen(), prior=prior, carrier_fraction=0.6)
    assert m.num_carriers > 0
    kl = kl_terms(m, prior)
    for k, v in kl.items():
        assert abs(v.item()) < 1e-5, (k, v.item())


def test_kl_zero_at_prior_any_k_ours():
    # ours starts the width at w_p, so the KL is 0 for any K (the paper's 1/K only for K = 10)
    for k in (1, 3, 10, 32):
        prior = Prior()
        m = random_model(10, gen(1), prior=prior, num_entries=k, carrier_fraction=1.0)
        assert abs(kl_terms(m, prior)["total"].item()) < 1e-5


def test_gaussian_kl_matches_torch():
    g = gen(3)
    loc = torch.randn(200, generator=g) * 3
    raw = torch.randn(200, generator=g) * 4
    for p_loc, p_std in [(0.0, 0.00248), (2.0, 1.996), (-1.0, 10.0)]:
        ours = gaussian_kl(loc, raw, p_loc, p_std)
        ref = kl_divergence(Normal(loc.double(), F.softplus(raw).double()), Normal(p_loc, p_std))
        torch.testing.assert_close(ours.double(), ref, rtol=1e-4, atol=1e-4)


def test_scale_kl_ours_is_moment_matched_gaussian_kl():
    g = gen(4)
    left = 0.8 + 0.2 * torch.rand(100, generator=g)
    raw = torch.randn(100, generator=g) - 2
    wp = 0.1
    w = F.softplus(raw).clamp(0.01, 100)
    ours = scale_kl(left, raw, wp, "ours")
    ref = kl_divergence(Normal((left + w / 2).double(), (w / math.sqrt(12)).double()),
                        Normal(1 - wp / 2, wp / math.sqrt(12)))
    torch.testing.assert_close(ours.double(), ref, rtol=1e-4, atol=1e-4)
    # inside the prior support the true KL is log(wp / w); ours agrees to first order there
    inside = torch.tensor([0.92]), inverse_softplus(torch.tensor([0.05]))
    true = kl_divergence(Uniform(0.92, 0.97), Uniform(1 - wp, 1.0))
    assert math.isclose(float(true), math.log(2.0), rel_tol=1e-5)
    assert float(scale_kl(*inside, wp, "ours")) > 0


def test_scale_kl_paper_is_l1_of_endpoints():
    left = torch.tensor([0.9, 0.8, 1.0])
    raw = inverse_softplus(torch.tensor([0.1, 0.1, 0.3]))
    out = scale_kl(left, raw, 0.1, "paper")
    torch.testing.assert_close(out, torch.tensor([0.0, 0.2, 0.4]), atol=1e-5, rtol=0)


def test_total_loss_is_the_photometric_mix_plus_the_weighted_kl():
    """The training loss (train/losses.py): (1 - lambda) L1 + lambda (1 - SSIM) + kl_weight x KL total, the KL
    added (minimising the loss pulls the posterior toward the prior), its terms logged as ``kl_*``."""
    from uncertsplat.eval.image import ssim
    from uncertsplat.train.losses import total_loss

    g = gen(21)
    target = torch.rand(2, 16, 16, 3, generator=g)
    pred = (target + 0.1 * torch.randn(2, 16, 16, 3, generator=g)).clamp(0, 1)
    l1 = float((pred - target).abs().mean())
    s = float(ssim(pred, target))
    assert 0.05 < l1 and s < 0.99  # a mix of two distinct terms
    kl = {"position": torch.tensor(0.5, requires_grad=True), "scale": torch.tensor(0.25), "gate": torch.tensor(0.125)}
    kl["total"] = kl["position"] + kl["scale"] + kl["gate"]
    out = total_loss(pred, target, kl, ssim_lambda=0.2, kl_weight=0.01)
    assert out["l1"].item() == pytest.approx(l1, rel=1e-5)
    assert out["ssim"].item() == pytest.approx(s, rel=1e-5)
    photo = 0.8 * l1 + 0.2 * (1.0 - s)
    assert out["photo"].item() == pytest.approx(photo, rel=1e-5)
    assert out["loss"].item() == pytest.approx(photo + 0.01 * 0.875, rel=1e-5)
    assert {k: out[f"kl_{k}"].item() for k in kl} == {"position": 0.5, "scale": 0.25, "gate": 0.125, "total": 0.875}
    out["loss"].backward()
    assert kl["position"].grad.item() == pytest.approx(0.01)  # +kl_weight: the KL enters with a plus sign
    # without a posterior the loss is the photometric term alone
    bare = total_loss(pred, target, None, ssim_lambda=0.2, kl_weight=0.01)
    assert bare["loss"].item() == pytest.approx(photo, rel=1e-5) and "kl_total" not in bare
    # lambda = 0: no SSIM computed (reported as 0), the loss the mean absolute error
    plain = total_loss(pred, target, None, ssim_lambda=0.0, kl_weight=0.01)
    assert plain["l1"].item() == pytest.approx(l1, rel=1e-5) and plain["ssim"].item() == 0.0
    assert plain["loss"].item() == plain["photo"].item() == pytest.approx(l1, rel=1e-5)

    # on a real model: a gradient step on the loss (the photometric term fixed) lowers the KL
    prior = Prior()
    m = random_model(20, gen(22), prior=prior, carrier_fraction=1.0, perturb_tables=0.3)
    before = kl_terms(m, prior)
    total_loss(pred, target, before, ssim_lambda=0.2, kl_weight=1.0)["loss"].backward()
    with torch.no_grad():
        for t in m.tables.values():
            t -= 1e-3 * t.grad
    assert kl_terms(m, prior)["total"].item() < before["total"].item()


def _subset_mixture(model, m_size, extent):
    """Exact mean and std of a sampled position / multiplier, enumerating every subset."""
    t = {k: v.detach().double() for k, v in model.tables.items()}
    subsets = list(itertools.combinations(range(model.num_entries), m_size))
    mus, vars_, lm, lv = [], [], [], []
    for s in subsets:
        s = list(s)
        mu = t["pos_loc"][:, s].mean(1) * extent
        sig = F.softplus(t["pos_spread_raw"][:, s].mean(1)) * extent
        w = F.softplus(t["scale_width_raw"][:, s].mean(1)).clamp(0.01, 100)
        left = t["scale_left"][:, s].mean(1)
        mus.append(mu)
        vars_.append(sig**2)
        lm.append(left + w / 2)
        lv.append(w**2 / 12)
    mus, vars_, lm, lv = map(torch.stack, (mus, vars_, lm, lv))
    pos_mean = mus.mean(0)
    pos_std = ((vars_ + mus**2).mean(0) - pos_mean**2).sqrt()
    mult_mean = lm.mean(0)
    mult_std = ((lv + lm**2).mean(0) - mult_mean**2).sqrt()
    return pos_mean, pos_std, mult_mean, mult_std


def test_sampling_statistics_match_posterior():
    extent = 2.0
    prior = Prior(position_std=0.05)
    model = random_model(30, gen(5), num_entries=4, carrier_fraction=1.0, prior=prior, perturb_tables=0.3,
                         extent=extent)
    idx = model.carrier_index()
    g = gen(6)
    S = 3000
    with torch.no_grad():
        draws = [sample(model, g, subset_size=2, extent=extent) for _ in range(S)]
    means = torch.stack([d.means[idx] for d in draws]).double()  # [S,P,3]
    mult = torch.stack([d.scales[idx] for d in draws]).double() / model.params["scales"].detach()[idx].exp()
    pos_mean, pos_std, mult_mean, mult_std = _subset_mixture(model, 2, extent)
    base = model.params["means"].detach()[idx].double()
    se = pos_std / math.sqrt(S)
    assert ((means.mean(0) - base - pos_mean).abs() < 5 * se + 1e-6).all()
    torch.testing.assert_close(means.std(0), pos_std, rtol=0.08, atol=1e-6)
    torch.testing.assert_close(mult.mean(0), mult_mean, rtol=0, atol=float(5 * mult_std.max() / math.sqrt(S)))
    torch.testing.assert_close(mult.std(0), mult_std, rtol=0.08, atol=1e-6)
    # gate: E[g] against a fine quadrature over eta, per carrier (subset M = K: no subset randomness)
    model1 = random_model(20, gen(7), num_entries=3, carrier_fraction=1.0, perturb_tables=0.5)
    idx1 = model1.carrier_index()
    with torch.no_grad():
        op = torch.stack([sample(model1, g, subset_size=3).opacities[idx1] for _ in range(S)]).double()
    base_op = torch.sigmoid(model1.params["opacities"].detach()[idx1]).double()
    t = model1.tables
    nu = t["gate_loc"].detach().mean(1)[:, 0].double()
    tau = F.softplus(t["gate_spread_raw"].detach().mean(1))[:, 0].double()
    eta = torch.linspace(-8, 8, 4001, dtype=torch.float64)
    w = torch.exp(-0.5 * eta**2)
    w = w / w.sum()
    eg = (torch.sigmoid((nu[:, None] + tau[:, None] * eta) / 0.2) * w).sum(1)
    assert ((op.mean(0) - base_op * eg).abs() < 0.03).all()
    # and the probit approximation used by posterior_mean is within 0.02 of the exact expectation
    assert ((expected_gate(nu, tau, 0.2) - eg).abs() < 0.02).all()


def test_sample_is_reproducible_and_noncarriers_untouched():
    model = random_model(50, gen(8), carrier_fraction=0.5, perturb_tables=0.2)
    a = sample(model, gen(9))
    b = sample(model, gen(9))
    torch.testing.assert_close(a.means, b.means, rtol=0, atol=0)
    c = sample(model, gen(10))
    assert not torch.equal(a.means, c.means)
    non = model.posterior_row < 0
    assert non.any()
    torch.testing.assert_close(a.means[non], model.params["means"].detach()[non], rtol=0, atol=0)
    torch.testing.assert_close(a.scales[non], model.params["scales"].detach()[non].exp())
    torch.testing.assert_close(a.opacities[non], torch.sigmoid(model.params["opacities"].detach()[non]))


def test_posterior_mean_is_deterministic_and_at_prior_center():
    extent = 3.0
    model = random_model(20, gen(11), carrier_fraction=1.0, extent=extent)
    pm1 = posterior_mean(model, extent=extent)
    pm2 = posterior_mean(model, extent=extent)
    torch.testing.assert_close(pm1.means, pm2.means, rtol=0, atol=0)
    # tables at the prior: no offset, multiplier 0.95 (mean of U[0.9, 1]), gate ~ P(logit > 0) ~ 0.84
    torch.testing.assert_close(pm1.means, model.params["means"].detach())
    torch.testing.assert_close(pm1.scales, 0.95 * model.params["scales"].detach().exp(), rtol=1e-5, atol=0)
    gate = pm1.opacities / torch.sigmoid(model.params["opacities"].detach())
    assert ((gate - 0.84).abs() < 0.03).all()


def test_paper_variant_multiplies_the_log_scale():
    prior = Prior(variant="paper")
    model = random_model(10, gen(12), carrier_fraction=1.0, prior=prior)
    pm = posterior_mean(model, variant="paper", temperature=prior.temperature)
    s = model.params["scales"].detach()
    torch.testing.assert_close(pm.scales, torch.exp(s * 0.95), rtol=1e-5, atol=0)
    assert (pm.scales > s.exp()).all()  # log-scales < 0: small Gaussians grow


@pytest.mark.parametrize("scale", [1e-3, 1.0, 1e3])
def test_ours_is_equivariant_to_scene_scale(scale):
    ref = random_model(30, gen(13), carrier_fraction=0.7, perturb_tables=0.3)
    scaled = random_model(30, gen(13), carrier_fraction=0.7, perturb_tables=0.3)
    with torch.no_grad():
        scaled.params["means"].mul_(scale)
        scaled.params["scales"].add_(math.log(scale))
    a = sample(ref, gen(14), extent=1.0)
    b = sample(scaled, gen(14), extent=scale)
    torch.testing.assert_close(b.means / scale, a.means, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(b.scales / scale, a.scales, rtol=1e-5, atol=1e-9)
    torch.testing.assert_close(b.opacities, a.opacities)
    ea, eb = expected_render_sample(ref, extent=1.0), expected_render_sample(scaled, extent=scale)
    torch.testing.assert_close(eb.scales / scale, ea.scales, rtol=1e-5, atol=1e-9)
    torch.testing.assert_close(eb.opacities, ea.opacities, rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(eb.position_var / scale**2, ea.position_var, rtol=1e-4, atol=1e-12)
    assert kl_terms(ref, Prior())["total"].item() == pytest.approx(kl_terms(scaled, Prior())["total"].item())


def test_prior_rows_shapes_and_values():
    rows = prior_rows(4, 10, Prior())
    assert rows["pos_spread_raw"].shape == (4, 10, 3) and rows["gate_loc"].shape == (4, 10, 1)
    assert torch.allclose(F.softplus(rows["pos_spread_raw"]), torch.tensor(0.00248))
    assert torch.allclose(F.softplus(rows["gate_spread_raw"]), torch.tensor(1.996))
    assert torch.allclose(rows["scale_left"], torch.tensor(0.9))


def test_a_subset_holds_between_one_and_all_distinct_entries():
    """``draw_subset``: M = min(subset_size, K) distinct entries, at least one (a subset size of 0 or below still
    averages one entry: a sample always has one)."""
    from uncertsplat.gaussians.variational import draw_subset

    for size, want in ((0, 1), (-3, 1), (1, 1), (4, 4), (10, 10), (25, 10)):
        got = draw_subset(10, size, gen(size + 5))
        assert got.shape == (want,) and got.unique().numel() == want and bool(((got >= 0) & (got < 10)).all())


def test_an_absorbed_gate_leaves_the_opacity_as_it_was():
    """``absorbed_opacity_logit``: sigmoid(logit) x gate is the given opacity, for any gate above it; where the gate
    cannot carry it (opacity above the gate) the base opacity is capped below 1."""
    from uncertsplat.gaussians.variational import absorbed_opacity_logit

    opacity = torch.tensor([0.01, 0.3, 0.5, 0.89])
    gate = torch.tensor([0.05, 0.4, 0.9, 0.9])
    torch.testing.assert_close(torch.sigmoid(absorbed_opacity_logit(opacity, gate)) * gate, opacity)
    torch.testing.assert_close(torch.sigmoid(absorbed_opacity_logit(opacity, 1.0)), opacity)
    capped = torch.sigmoid(absorbed_opacity_logit(torch.tensor([0.8]), torch.tensor([0.5])))
    assert float(capped) == pytest.approx(1.0 - 1e-4, abs=1e-6)


def test_the_paper_scales_second_moment_is_the_integral_near_and_far_from_its_limit():
    """E[exp(2 s o)] for o ~ U[l, l + w] (the paper variant's expected render): ``exp(2 s l) (exp(2 s w) - 1) / (2 s
    w)``, its limit ``exp(2 s l) (1 + s w)`` only where 2 s w is below 1e-6; against the mean over a fine grid of o."""
    from uncertsplat.gaussians.variational import _scale_second_moment

    s = torch.tensor([[-3.0, -0.5, 0.02, 1e-9, 2.0]], dtype=torch.float64)
    left, width = torch.full_like(s, 0.9), torch.tensor([[0.01, 0.05, 0.1, 0.1, 0.02]], dtype=torch.float64)
    o = left[..., None] + width[..., None] * (torch.arange(20000, dtype=torch.float64) + 0.5) / 20000
    want = torch.exp(2.0 * s[..., None] * o).mean(-1)
    torch.testing.assert_close(_scale_second_moment(s, left, width, "paper"), want, rtol=1e-7, atol=0)


def test_the_mean_params_of_a_saturated_opacity_are_finite():
    """``mean_params``: an opacity of 0 or 1 in float32 (logits of +-20 and beyond, gates of 1 off the carriers) gives
    a finite logit (clamped to 1e-6 from either end), so the curvature differentiates finite numbers."""
    from uncertsplat.gaussians.variational import mean_params

    model = random_model(6, gen(3), carrier_fraction=0.0)
    model.params["opacities"].data.copy_(torch.tensor([-200.0, -20.0, 0.0, 20.0, 40.0, 200.0]))
    logits = mean_params(model)["opacities"]
    assert bool(torch.isfinite(logits).all())
    assert float(logits.abs().max()) == pytest.approx(math.log((1 - 1e-6) / 1e-6), rel=1e-3)


def test_prior_rows_width_is_clamped_as_every_reader_clamps_it():
    """The paper's 1/K width below ``MIN_WIDTH`` (K = 200) starts at ``MIN_WIDTH``, the width the sampler and the KL
    read from the table anyway: the table holds what is used, not a width that only the clamp hides."""
    paper = prior_rows(2, 200, Prior(variant="paper"))
    torch.testing.assert_close(F.softplus(paper["scale_width_raw"]), torch.full((2, 200, 3), MIN_WIDTH))


@pytest.mark.parametrize("k", [1, 4, 10, 32])
def test_prior_rows_paper_interval_for_any_k(k):
    """The paper variant (METHOD.md: "table init width = 1/K, left = 0.9") starts every multiplier interval at
    [1 - w_p, 1 - w_p + 1/K]: the left edge is the prior's, whatever K; only the width follows K (ours: w_p).
    At K = 10 the two agree, so only another K tells a left edge of 1 - w_p from one of 1 - 1/K."""
    wp = 0.1
    paper = prior_rows(3, k, Prior(variant="paper", scale_width=wp))
    assert torch.allclose(paper["scale_left"], torch.tensor(1.0 - wp))
    torch.testing.assert_close(F.softplus(paper["scale_width_raw"]), torch.full((3, k, 3), 1.0 / k))
    ours = prior_rows(3, k, Prior(variant="ours", scale_width=wp))
    assert torch.allclose(ours["scale_left"], torch.tensor(1.0 - wp))
    torch.testing.assert_close(F.softplus(ours["scale_width_raw"]), torch.full((3, k, 3), wp))
    # so the paper's scale term at initialisation is |(1 - w_p + 1/K) - 1| = |1/K - w_p|: 0 only for K = 10
    kl = scale_kl(paper["scale_left"], paper["scale_width_raw"], wp, "paper")
    torch.testing.assert_close(kl, torch.full((3, k, 3), abs(1.0 / k - wp)), atol=1e-6, rtol=0)
    assert float(scale_kl(ours["scale_left"], ours["scale_width_raw"], wp, "ours").abs().max()) < 1e-5


def test_gradients_reach_tables_and_params():
    model = random_model(20, gen(15), carrier_fraction=1.0, perturb_tables=0.1)
    s = sample(model, gen(16))
    loss = s.means.sum() + s.scales.sum() + s.opacities.sum() + kl_terms(model, Prior())["total"]
    loss.backward()
    for name, p in model.parameters().items():
        if name in ("quats", "sh0", "shN"):
            continue
        assert p.grad is not None and p.grad.abs().sum() > 0, name


class TestPosteriorSummary:
    """``posterior_summary``: how far the learned posteriors are from the prior."""

    def _model(self, prior, n=400, carrier_fraction=0.5):
        return random_model(n, torch.Generator().manual_seed(3), carrier_fraction=carrier_fraction, prior=prior)

    @pytest.mark.parametrize("variant", ["ours", "paper"])
    def test_at_the_prior_nothing_moved(self, variant):
        prior = Prior(variant=variant)
        s = posterior_summary(self._model(prior), prior)
        assert s["carriers"] > 0 and s["moved_fraction"] == 0.0
        assert s["kl_nats"]["q90"] == pytest.approx(0.0, abs=1e-6)
        assert s["position_spread_ratio"]["q10"] == pytest.approx(1.0, rel=1e-5)
        assert s["position_spread_ratio"]["q90"] == pytest.approx(1.0, rel=1e-5)
        assert s["scale_width_ratio"]["q50"] == pytest.approx(1.0, rel=1e-5)
        assert s["gate_off"]["q50"] == pytest.approx(s["gate_off_prior"], rel=1e-5)
        # the documented value: N(2, 1.996^2) puts about 16 % of the gate logits below 0
        assert s["gate_off_prior"] == pytest.approx(Normal(2.0, 1.996).cdf(torch.tensor(0.0)).item(), rel=1e-5)

    def test_an_anisotropic_spread_is_summed_up_by_its_means(self):
        """Position spreads of 1, 2 and 4 x the prior's along the axes: ``posterior_summary``'s ratio is their
        geometric mean (2), ``carrier_uncertainty``'s position std their RMS (sqrt 7 x the prior's, world units)."""
        from uncertsplat.gaussians.variational import carrier_uncertainty

        prior = Prior()
        model = self._model(prior)
        std = prior.position_std * torch.tensor([1.0, 2.0, 4.0])
        model.tables["pos_spread_raw"].data.copy_(inverse_softplus(std).expand_as(model.tables["pos_spread_raw"]))
        s = posterior_summary(model, prior)
        assert s["position_spread_ratio"]["q10"] == s["position_spread_ratio"]["q90"] == pytest.approx(2.0, rel=1e-4)
        got = carrier_uncertainty(model, extent=3.0)["position"]
        idx = model.carrier_index()
        torch.testing.assert_close(got[idx], torch.full((idx.numel(),), 3.0 * math.sqrt(7.0) * prior.position_std),
                                   rtol=1e-4, atol=0)
        assert float(got[model.posterior_row < 0].abs().max()) == 0.0

    def test_counts_the_carriers_that_moved(self):
        prior = Prior()
        model = self._model(prior)
        p = model.num_carriers
        half = torch.arange(p) < p // 2
        # halve the position spread of half of the carriers (every entry, every axis): KL 3 x 0.318 nats
        raw = model.tables["pos_spread_raw"]
        model.tables["pos_spread_raw"] = torch.where(half[:, None, None],
                                                     inverse_softplus(torch.full_like(raw, prior.position_std / 2)), raw)
        s = posterior_summary(model, prior)
        assert s["moved_fraction"] == pytest.approx((p // 2) / p)
        expected = 3 * (math.log(2.0) + 0.125 - 0.5)
        assert s["kl_nats"]["q90"] == pytest.approx(expected, rel=1e-3)
        assert s["position_spread_ratio"]["q10"] == pytest.approx(0.5, rel=1e-3)
        assert s["position_spread_ratio"]["q90"] == pytest.approx(1.0, rel=1e-3)

    def test_gate_shift_shows_in_gate_off(self):
        prior = Prior()
        model = self._model(prior, carrier_fraction=1.0)
        model.tables["gate_loc"] = torch.zeros_like(model.tables["gate_loc"])  # nu = 0: half the samples off
        s = posterior_summary(model, prior)
        assert s["gate_off"]["q50"] == pytest.approx(0.5, abs=1e-6)
        assert s["moved_fraction"] == 1.0

    def test_no_carriers_gives_none_not_nan(self):
        prior = Prior()
        s = posterior_summary(self._model(prior, carrier_fraction=0.0), prior)
        assert s["carriers"] == 0 and s["moved_fraction"] is None and s["kl_nats"] is None
        json.dumps(s)  # JSON-serialisable as written into train_summary.json


def _average_render(model, cams, variant, n, seed):
    from uncertsplat.render import render

    g = gen(seed)
    acc = None
    with torch.no_grad():
        for _ in range(n):
            rgb = render(sample(model, g, subset_size=model.num_entries, variant=variant), cams).rgb
            acc = rgb if acc is None else acc + rgb
    return acc / n


@pytest.mark.parametrize("variant", ["ours", "paper"])
def test_expected_render_is_closer_to_the_average_of_samples_than_the_posterior_mean(variant):
    from tests.reference.naive_render import look_at_cameras
    from uncertsplat.render import render

    # a position spread comparable to the Gaussians' sizes (0.005-0.055), so the noise visibly blurs the
    # average render; subset M = K so the only randomness is the per-Gaussian noise the moments describe
    prior = Prior(position_std=0.02, variant=variant)
    model = random_model(120, gen(20), carrier_fraction=1.0, prior=prior, perturb_tables=0.1, num_entries=3)
    with torch.no_grad():
        model.params["opacities"].add_(2.0)  # mostly opaque: blending order matters, as in a scene
    cams = look_at_cameras(2, 48, 40, 60.0, radius=1.6)
    avg = _average_render(model, cams, variant, 400, seed=21)  # [C,H,W,3]
    with torch.no_grad():
        plain = render(posterior_mean(model, variant=variant, temperature=prior.temperature), cams).rgb
        matched = render(expected_render_sample(model, variant=variant, temperature=prior.temperature), cams).rgb
    err_plain = float((plain - avg).square().mean())
    err_matched = float((matched - avg).square().mean())
    assert err_plain > 1e-5  # the noise does change the average render here
    assert err_matched < 0.2 * err_plain, (err_matched, err_plain)


def test_expected_render_without_noise_is_the_posterior_mean():
    model = random_model(30, gen(22), carrier_fraction=0.6, perturb_tables=0.2)
    with torch.no_grad():  # no position spread, a point-mass multiplier at 1
        model.tables["pos_spread_raw"].fill_(-40.0)
        model.tables["scale_width_raw"].fill_(-40.0)  # width clamps to MIN_WIDTH = 0.01
        model.tables["scale_left"].fill_(1.0 - 0.005)
    pm = posterior_mean(model)
    er = expected_render_sample(model)
    torch.testing.assert_close(er.means, pm.means, rtol=0, atol=0)
    torch.testing.assert_close(er.scales, pm.scales, rtol=1e-4, atol=0)
    torch.testing.assert_close(er.opacities, pm.opacities, rtol=0, atol=0)
    assert float(er.position_var.detach().abs().max()) < 1e-30
    # without carriers it is the posterior mean exactly (a plain render)
    none = random_model(10, gen(23), carrier_fraction=0.0)
    er0 = expected_render_sample(none)
    torch.testing.assert_close(er0.scales, posterior_mean(none).scales, rtol=0, atol=0)
    assert er0.position_var is None


class TestExpectedConstants:
    """The table terms computed once give the expected render's values and gradients, and know when they are stale."""

    def _model(self, seed=25, fraction=0.6):
        model = random_model(50, gen(seed), carrier_fraction=fraction, perturb_tables=0.3, extent=1.5)
        for v in model.params.values():
            v.requires_grad_(True)
        return model

    def test_same_sample_and_gradients(self):
        model = self._model()
        kw = dict(extent=1.5, temperature=0.2, tables_grad=False)
        c = expected_constants(model, extent=1.5, temperature=0.2)
        slow, fast = expected_render_sample(model, **kw), expected_render_sample(model, constants=c, **kw)
        grads = []
        for s_ in (slow, fast):
            for v in model.params.values():
                v.grad = None
            w = torch.linspace(0.5, 1.5, s_.means.numel()).view_as(s_.means)
            (s_.means * w).sum().add(s_.scales.square().sum()).add(s_.opacities.sum()).add(
                s_.full_sh().sum()).backward()
            grads.append({k: v.grad.clone() for k, v in model.params.items() if v.grad is not None})
        for k in ("means", "scales", "opacities", "quats"):
            torch.testing.assert_close(getattr(fast, k), getattr(slow, k), rtol=1e-6, atol=0)
        assert fast.sh_rest is not None and slow.sh_rest is None  # the training sample keeps the table's SH tensors
        torch.testing.assert_close(fast.full_sh(), slow.full_sh(), rtol=0, atol=0)
        torch.testing.assert_close(fast.position_var, slow.position_var, rtol=0, atol=0)
        assert grads[0].keys() == grads[1].keys()
        for k in grads[0]:
            torch.testing.assert_close(grads[1][k], grads[0][k], rtol=1e-5, atol=1e-7)

    def test_ignored_when_the_topology_changed_or_not_applicable(self):
        model = self._model()
        c = expected_constants(model, extent=1.5)
        other = self._model(seed=26)  # a different model (another posterior_row): constants do not fit
        assert not c.fits(other)
        torch.testing.assert_close(expected_render_sample(other, extent=1.5, tables_grad=False, constants=c).scales,
                                   expected_render_sample(other, extent=1.5, tables_grad=False).scales)
        with torch.no_grad():  # an in-place write to the rows (put back: the table keeps its invariant)
            model.posterior_row[0] = model.posterior_row[0].clone()
        assert not c.fits(model)
        # with gradients to the tables, or the paper variant, the constants are not used
        fresh = expected_constants(model, extent=1.5)
        assert fresh.fits(model)
        with torch.no_grad():
            model.tables["pos_loc"].add_(0.5)  # the table terms change: a caller must drop the constants
        torch.testing.assert_close(expected_render_sample(model, extent=1.5, tables_grad=True, constants=fresh).means,
                                   expected_render_sample(model, extent=1.5, tables_grad=True).means)

    def test_no_carriers(self):
        model = self._model(fraction=0.0)
        c = expected_constants(model)
        er = expected_render_sample(model, tables_grad=False, constants=c)
        assert er.position_var is None  # as without constants: a plain render


def test_expected_render_at_the_prior():
    extent = 2.0
    model = random_model(40, gen(24), carrier_fraction=0.5, extent=extent)
    pm = posterior_mean(model, extent=extent)
    er = expected_render_sample(model, extent=extent)
    car = model.posterior_row >= 0
    s = model.params["scales"].detach().exp()
    second = s.square() * (0.9**2 + 0.9 * 0.1 + 0.1**2 / 3)  # E[o^2] for o ~ U[0.9, 1]
    torch.testing.assert_close(er.scales[car], second[car].sqrt(), rtol=1e-5, atol=0)
    torch.testing.assert_close(er.position_var[car], torch.full((int(car.sum()),), (0.00248 * extent) ** 2),
                               rtol=1e-4, atol=0)
    assert (er.position_var[~car] == 0).all()
    torch.testing.assert_close(er.opacities, pm.opacities, rtol=0, atol=0)  # E[gate]; the blur's dimming is per view
    torch.testing.assert_close(er.scales[~car], pm.scales[~car], rtol=0, atol=0)


class TestBoundsWhateverTorchsClamp:
    """A clamp's gradient at its bound is 1 up to torch 2.13 and 0 from torch 2.14: the functions the posterior's
    gradients pass through give the same value and gradient under both (x = -15 in the KL's log, a width at a
    bound)."""

    def test_log_softplus_has_its_true_gradient_at_the_branch_point(self):
        x = torch.tensor([-30.0, -15.0 - 1e-3, -15.0, -14.0, 0.0, 30.0], dtype=torch.float64, requires_grad=True)
        y = log_softplus(x)
        y.sum().backward()
        exact = torch.log(torch.nn.functional.softplus(x.detach()))
        truth = torch.sigmoid(x.detach()) / torch.nn.functional.softplus(x.detach())  # d/dx log softplus(x)
        torch.testing.assert_close(y.detach(), torch.where(x.detach() < -15, x.detach(), exact))
        torch.testing.assert_close(x.grad, truth, rtol=1e-6, atol=0)

    def test_a_width_on_a_bound_keeps_its_gradient(self):
        from uncertsplat.gaussians.prior import MAX_WIDTH, MIN_WIDTH
        from uncertsplat.gaussians.variational import clamp_width

        w = torch.tensor([MIN_WIDTH / 2, MIN_WIDTH, 1.0, MAX_WIDTH, MAX_WIDTH * 2], requires_grad=True)
        out = clamp_width(w)
        out.sum().backward()
        torch.testing.assert_close(out.detach(), w.detach().clamp(MIN_WIDTH, MAX_WIDTH))
        assert w.grad.tolist() == [0.0, 1.0, 1.0, 1.0, 0.0]
