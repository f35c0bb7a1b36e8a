"""The pixel noise of a model's Gaussians (``uncertainty.residual``) against closed forms, with the real renderer."""

from __future__ import annotations

import functools
from dataclasses import replace

import pytest
import torch

from uncertsplat.render import render
from uncertsplat.types import Cameras, GaussianSample
from uncertsplat.uncertainty.residual import ResidualField, fit_residual_field

W, H = 40, 30


def _cams(num: int) -> Cameras:
    """``num`` cameras at the origin looking down +z, shifted along x by 0.05 each."""
    cw = torch.eye(4).repeat(num, 1, 1)
    cw[:, 0, 3] = -0.05 * torch.arange(num, dtype=torch.float32)
    K = torch.tensor([[40.0, 0, W / 2], [0, 40.0, H / 2], [0, 0, 1.0]]).repeat(num, 1, 1)
    return Cameras(cw, K, W, H, tuple(f"v{i}.png" for i in range(num)))


def _sample(n=30, seed=0) -> GaussianSample:
    g = torch.Generator().manual_seed(seed)
    means = torch.cat([(torch.rand(n, 2, generator=g) - 0.5) * 1.2, 2.0 + torch.rand(n, 1, generator=g)], 1)
    means[-1] = torch.tensor([0.0, 0.0, -5.0])  # behind every camera: no training pixel sees it
    return GaussianSample(means=means, quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
                          scales=torch.full((n, 3), 0.08), opacities=torch.full((n,), 0.7),
                          sh=torch.randn(n, 1, 3, generator=g) * 0.3, sh_degree=0)


RENDER = functools.partial(render, background=torch.tensor([0.2, 0.4, 0.6]))


def test_a_constant_residual_is_every_seen_gaussians_noise():
    """Images = render + d everywhere: every Gaussian a pixel sees gets d^2, the unseen one the mean (d^2), and the
    rendered noise of a view is alpha x d^2 (the Gaussians' share of the pixel)."""
    sample, cams, d = _sample(), _cams(3), 0.05
    with torch.no_grad():
        out = RENDER(sample, cams)
    field = fit_residual_field(sample, cams, out.rgb + d, RENDER)
    assert not bool(field.seen[-1]) and bool(field.seen[:-1].any())
    torch.testing.assert_close(field.variance, torch.full_like(field.variance, d * d), rtol=1e-4, atol=1e-7)
    assert abs(field.mean_variance - d * d) < 1e-7
    blended = field.blended(cams, RENDER)
    torch.testing.assert_close(blended, out.alpha * d * d, rtol=1e-3, atol=1e-7)


def test_the_noise_follows_the_gaussian_that_makes_the_pixel():
    """A residual only on the left half of the images: Gaussians drawn there get more noise than those on the right."""
    sample, cams = _sample(seed=1), _cams(2)
    with torch.no_grad():
        out = RENDER(sample, cams)
    images = out.rgb.clone()
    images[:, :, : W // 2] += 0.1
    field = fit_residual_field(sample, cams, images, RENDER)
    x = sample.means[:, 0] / sample.means[:, 2]  # horizontal image coordinate (focal units) in camera 0
    left, right = field.seen & (x < -0.15), field.seen & (x > 0.15)
    assert bool(left.any()) and bool(right.any())
    assert float(field.variance[left].mean()) > 3 * float(field.variance[right].mean())


def test_masked_pixels_do_not_count_and_subset_keeps_each_gaussians_noise():
    sample, cams = _sample(seed=2), _cams(2)
    with torch.no_grad():
        out = RENDER(sample, cams)
    masks = torch.zeros(2, H, W, 1, dtype=torch.bool)
    masks[:, :, W // 2:] = True
    images = out.rgb.clone()
    images[:, :, : W // 2] += 0.5  # a large error only where the mask excludes it
    field = fit_residual_field(sample, cams, images, RENDER, masks=masks)
    assert float(field.variance.max()) < 1e-8
    keep = torch.arange(len(sample.means)) % 2 == 0
    sub = field.subset(keep)
    assert sub.sample.means.shape[0] == int(keep.sum())
    torch.testing.assert_close(sub.variance, field.variance[keep])
    # the sample's position variance (an expected render's) is kept with its Gaussians too
    spread = replace(field, sample=replace(sample, position_var=torch.linspace(0.0, 1.0, len(sample.means))))
    assert torch.equal(spread.subset(keep).sample.position_var, spread.sample.position_var[keep])


def test_a_faint_gaussian_is_seen_and_masked_pixels_leave_the_mean_too():
    """A Gaussian whose blending weight is a few percent of the others' is still seen (its own noise, not the mean);
    the mean over the training pixels (what the unseen Gaussian gets) is taken over the pixels inside the masks."""
    sample, cams, d = _sample(), _cams(3), 0.05
    faint = torch.full_like(sample.opacities, 0.7)
    faint[0] = 0.01
    sample = replace(sample, opacities=faint)
    with torch.no_grad():
        out = RENDER(sample, cams)
    field = fit_residual_field(sample, cams, out.rgb + d, RENDER)
    assert 0.0 < float(field.observations[0]) < 0.05 * float(field.observations.max())
    assert bool(field.seen[0]) and float(field.variance[0]) == pytest.approx(d * d, rel=1e-3)
    masks = torch.zeros(3, H, W, 1, dtype=torch.bool)
    masks[:, :, : W // 3] = True
    images = torch.where(masks, out.rgb + d, out.rgb + 5 * d)
    masked = fit_residual_field(sample, cams, images, RENDER, masks=masks)
    assert masked.mean_variance == pytest.approx(d * d, rel=1e-4)
    assert float(masked.variance[-1]) == pytest.approx(d * d, rel=1e-4)


def test_the_colour_prior_is_the_pixels_variance_and_each_bands_mean_square_over_the_seen_gaussians():
    """``fit_residual_field(colour_posterior=True)``'s prior: the DC coefficient's is the variance of the training
    pixels (inside the masks) over C0^2, each higher band's the mean square of that band's coefficients over the seen
    Gaussians (the unseen one's left out, however large)."""
    sample, cams = _sample(), _cams(3)
    g = torch.Generator().manual_seed(7)
    n = len(sample.means)
    band1, band2 = 0.2 * torch.randn(n, 3, 3, generator=g), 0.05 * torch.randn(n, 5, 3, generator=g)
    band1[-1], band2[-1] = 50.0, -50.0  # the unseen Gaussian's
    sample = replace(sample, sh=torch.cat([sample.sh, band1, band2], 1), sh_degree=2)
    images = torch.rand(3, H, W, 3, generator=g)
    masks = torch.ones(3, H, W, 1, dtype=torch.bool)
    masks[2, : H // 2] = False
    field = fit_residual_field(sample, cams, images, RENDER, masks=masks, colour_posterior=True)
    seen = field.seen
    assert not bool(seen[-1]) and bool(seen[:-1].all())
    pixels = images.double()[masks[..., 0]]  # [P,3]
    dc = float(pixels.var(0, unbiased=False).mean()) / 0.28209479177387814**2
    want = torch.tensor([dc] + [float(band1[seen].double().square().mean())] * 3
                        + [float(band2[seen].double().square().mean())] * 5, dtype=torch.float64)
    torch.testing.assert_close(field.colour_prior.double(), want, rtol=1e-5, atol=0)


def test_explained_variance_is_taken_off_the_residual():
    """With ``explained`` the noise is fitted to max(r^2 - explained, 0): a constant residual d and an explained
    variance e give every seen Gaussian d^2 - e, and an explained variance above d^2 gives 0."""
    sample, cams, d = _sample(), _cams(3), 0.05
    with torch.no_grad():
        out = RENDER(sample, cams)
    e = 0.3 * d * d
    field = fit_residual_field(sample, cams, out.rgb + d, RENDER,
                               explained=lambda cam: torch.full((1, H, W, 1), e))
    seen = field.seen
    torch.testing.assert_close(field.variance[seen], torch.full_like(field.variance[seen], d * d - e), rtol=1e-4,
                               atol=1e-7)
    none = fit_residual_field(sample, cams, out.rgb + d, RENDER, explained=lambda cam: torch.full((1, H, W, 1), 1.0))
    assert float(none.variance.abs().max()) == 0.0


def test_a_constant_colour_renders_as_that_colour():
    """``with_colour``: the sample's SH is degree 0 with ``C0 sh + 0.5`` (``render.sh``'s DC colour) equal to the
    given colour [N,3] of each Gaussian, the rest of the sample as it was (the value maps are rendered so)."""
    from uncertsplat.render.sh import eval_sh
    from uncertsplat.uncertainty.residual import with_colour

    sample = _sample(n=6)
    colour = torch.rand(6, 3, generator=torch.Generator().manual_seed(5)) * 2.0 - 0.5
    got = with_colour(sample, colour)
    assert got.sh_degree == 0 and got.sh.shape == (6, 1, 3) and torch.equal(got.means, sample.means)
    d = torch.nn.functional.normalize(torch.randn(1, 6, 3, generator=torch.Generator().manual_seed(6)), dim=-1)
    torch.testing.assert_close(eval_sh(0, got.sh, d)[0] + 0.5, colour, rtol=0, atol=1e-6)


class TestNoiseScale:
    """``eval.engine.fit_noise_scale``: the pixel noise's level at which the z-scores have unit variance."""

    @staticmethod
    def _setup(d: float = 0.05):
        from uncertsplat.uncertainty.residual import ResidualField

        sample, cams = _sample(seed=2), _cams(3)
        with torch.no_grad():
            out = RENDER(sample, cams)
        g = torch.Generator().manual_seed(0)
        images = (out.rgb + d * torch.randn(out.rgb.shape, generator=g)).clamp(0, 1)
        field = ResidualField(sample=sample, variance=torch.full((len(sample),), 1e-3), seen=torch.ones(len(sample),
                              dtype=torch.bool), mean_variance=1e-3)
        return sample, cams, images, field

    def test_the_scale_gives_unit_z_variance_on_the_views(self):
        from uncertsplat.eval.engine import fit_noise_scale

        sample, cams, images, field = self._setup()
        a = fit_noise_scale(field, sample, cams, images, RENDER)
        with torch.no_grad():
            r2 = (RENDER(sample, cams).rgb.clamp(0, 1) - images).square().mean(-1, keepdim=True)
            covered = RENDER(sample, cams).alpha >= 0.5  # the pixels the fit uses
        n = field.blended(cams, RENDER)
        assert 0.05 < float(covered.float().mean()) < 0.95, "the scene has covered and uncovered pixels"
        z2 = r2 / (a * n).clamp_min(1e-6)  # the default std floor, squared
        assert abs(float(z2[covered].double().mean()) - 1.0) < 1e-6
        scaled = field.scaled(a)
        assert scaled.scale == a and torch.allclose(scaled.variance, field.variance * a)
        assert field.scaled(1.0) is field

    def test_explained_variance_lowers_the_scale_and_extremes_hit_the_bounds(self):
        from uncertsplat.eval.engine import fit_noise_scale

        sample, cams, images, field = self._setup()
        a = fit_noise_scale(field, sample, cams, images, RENDER)
        some = fit_noise_scale(field, sample, cams, images, RENDER, explained=lambda cam: torch.full((1, H, W, 1),
                                                                                                    1e-3))
        assert 0 < some < a
        # what the rest explains already exceeds every residual: the noise all but vanishes
        assert fit_noise_scale(field, sample, cams, images, RENDER,
                               explained=lambda cam: torch.full((1, H, W, 1), 10.0)) == pytest.approx(1e-4)
        # a field that is (almost) nothing against the residual: the largest scale
        tiny = field.scaled(1e-12)
        assert fit_noise_scale(tiny, sample, cams, images, RENDER, std_floor=1e-9) == pytest.approx(1e4)
        # a perfect fit (no residual at all): the smallest
        with torch.no_grad():
            exact = RENDER(sample, cams).rgb.clamp(0, 1)
        assert fit_noise_scale(field, sample, cams, exact, RENDER) == pytest.approx(1e-4)

    def test_the_scale_solves_the_unit_variance_equation_which_is_ml_only_without_explained(self):
        """With ``explained`` e > 0 the fitted a is the root of mean r^2 / (e + a n) = 1 (its docstring), not
        the Gaussian likelihood's stationary point sum n (r^2 - v) / v^2 = 0 (v = e + a n), another number;
        with e = 0 the two are the same, a = mean(r^2 / n)."""
        from uncertsplat.eval.engine import fit_noise_scale

        sample, cams, images, field = self._setup()
        g = torch.Generator().manual_seed(1)
        e_maps = [torch.rand(1, H, W, 1, generator=g) ** 4 * 4e-3 for _ in range(len(cams))]

        def explained(cam):
            j = int(round(-float(cam.cam_from_world[0, 0, 3]) / 0.05))
            return e_maps[j]

        with torch.no_grad():
            out = RENDER(sample, cams)
            r2 = (out.rgb.clamp(0, 1) - images).square().mean(-1, keepdim=True).double()
        covered = out.alpha >= 0.5
        n = field.blended(cams, RENDER).double()[covered]
        e = torch.cat(e_maps).double()[covered]
        r2 = r2[covered]
        a = fit_noise_scale(field, sample, cams, images, RENDER, explained=explained, std_floor=1e-9)
        assert abs(float((r2 / (e + a * n)).mean()) - 1.0) < 1e-6

        def score(b: float) -> float:  # d log-likelihood / d a, up to a positive factor
            v = e + b * n
            return float((n * (r2 - v) / v.square()).sum())

        lo, hi = 1e-4, 1e4
        for _ in range(200):
            mid = (lo * hi) ** 0.5
            lo, hi = (mid, hi) if score(mid) > 0 else (lo, mid)
        assert abs(a / lo - 1.0) > 1e-3, "with e > 0 the unit-variance root is not the likelihood's"
        plain = fit_noise_scale(field, sample, cams, images, RENDER, std_floor=1e-9)
        assert plain == pytest.approx(float((r2 / n).mean()), rel=1e-9)


class TestOutOfSample:
    """``ResidualField.out_of_sample``: the leverage correction from training residuals to a new view's noise."""

    def test_observations_are_each_gaussians_share_of_the_pixels(self):
        """sum_i w_i(p) = alpha(p), so the Gaussians' observations add up to the views' summed alpha."""
        sample, cams = _sample(seed=3), _cams(3)
        with torch.no_grad():
            out = RENDER(sample, cams)
        field = fit_residual_field(sample, cams, out.rgb + 0.05, RENDER)
        assert float(field.observations[-1]) == 0.0
        torch.testing.assert_close(field.observations.double().sum(), out.alpha.double().sum(), rtol=1e-4, atol=1e-3)

    def test_the_factor_is_the_leverage_closed_form_and_capped(self):
        sample, cams = _sample(seed=4), _cams(2)
        with torch.no_grad():
            out = RENDER(sample, cams)
        field = fit_residual_field(sample, cams, out.rgb + 0.05, RENDER)
        k = 14
        oos = field.out_of_sample(k)
        h = (k / (3 * field.observations.double())).clamp(max=0.9)
        torch.testing.assert_close(oos.variance.double(), field.variance.double() / (1 - h), rtol=1e-5,
                                   atol=1e-9)
        # the Gaussian no pixel saw gets the cap: 1 / (1 - 0.9) = 10
        assert float(oos.variance[-1] / field.variance[-1]) == pytest.approx(10.0, rel=1e-5)
        assert oos.leverage_inflation == pytest.approx(float((1 / (1 - h)).mean()), rel=1e-5)
        # more views of the same pixels: smaller leverage, never below the in-sample noise
        more = field.out_of_sample(k, view_factor=100.0)
        seen = field.observations > 1.0
        assert bool((more.variance[seen] < oos.variance[seen]).all())
        assert bool((more.variance >= field.variance).all())
        # a pruned field keeps each Gaussian's observations
        keep = torch.arange(len(sample.means)) % 3 == 0
        torch.testing.assert_close(field.subset(keep).observations, field.observations[keep])

    def test_a_field_without_counts_is_refused(self):
        from dataclasses import replace

        sample, cams = _sample(seed=5), _cams(1)
        with torch.no_grad():
            out = RENDER(sample, cams)
        field = replace(fit_residual_field(sample, cams, out.rgb, RENDER), observations=None)
        with pytest.raises(ValueError, match="observation counts"):
            field.out_of_sample(14)


class TestColourPosterior:
    """The Laplace posterior of each Gaussian's colour (``fit_residual_field(colour_posterior=True)``) against closed forms."""

    @staticmethod
    def _fit(sample, cams, images, **kw):
        return fit_residual_field(sample, cams, images, RENDER, colour_posterior=True, **kw)

    def test_closed_form_at_degree_0(self):
        """Unseen Gaussian: the prior, the training pixels' variance. Seen: 1 / (n / v + 1 / prior) in RGB units,
        n the training pixels it is blended into (sum of weights), v its noise."""
        sample, cams, d = _sample(), _cams(3), 0.05
        with torch.no_grad():
            out = RENDER(sample, cams)
        images = (out.rgb + d).clamp(0, 1)
        field = self._fit(sample, cams, images)
        var = field.colour_variance(cams.centers)  # [3,N]
        pixel_var = float(images.double().reshape(-1, 3).var(0, unbiased=False).mean())
        assert var.shape == (3, len(sample))
        assert float(var[0, -1]) == pytest.approx(pixel_var, rel=1e-5)  # no training pixel saw the last one
        seen = field.seen
        expect = 1.0 / (field.observations.double() / field.variance.double() + 1.0 / pixel_var)
        torch.testing.assert_close(var[0, seen].double(), expect[seen], rtol=1e-4, atol=1e-12)
        # degree 0: no direction dependence
        torch.testing.assert_close(var[1], var[0])
        well_seen = seen & (field.observations > 5)  # blended into more than 5 training pixels
        assert bool(well_seen.any())
        assert float(var[0, well_seen].max()) < 0.2 * pixel_var, "a seen colour is known far better than the prior"

    def test_view_factor_scales_the_evidence(self):
        sample, cams = _sample(), _cams(2)
        with torch.no_grad():
            images = RENDER(sample, cams).rgb + 0.02
        one = self._fit(sample, cams, images)
        four = self._fit(sample, cams, images, view_factor=4.0)
        torch.testing.assert_close(four.colour_evidence, 4 * one.colour_evidence)
        assert bool((four.colour_variance(cams.centers) <= one.colour_variance(cams.centers) + 1e-12).all())

    def test_a_new_direction_is_less_known_than_the_seen_ones(self):
        """SH degree 1, every training view looking down +z: the band-1 coefficients along x and y get no evidence,
        so the colour seen from the side (+x) is less certain than from the training cameras, and equals the DC
        variance plus C1^2 x the band's prior for a coefficient no view constrains."""
        sample, cams = _sample(seed=3), _cams(3)
        g = torch.Generator().manual_seed(5)
        sample = replace(sample, sh=torch.cat([sample.sh, 0.2 * torch.randn(len(sample), 3, 3, generator=g)], 1),
                         sh_degree=1)
        with torch.no_grad():
            images = RENDER(sample, cams).rgb + 0.03
        field = self._fit(sample, cams, images)
        assert field.colour_evidence.shape == (len(sample), 4) and field.colour_prior.shape == (4,)
        i = int(torch.nonzero(field.seen & (field.observations > 5)).flatten()[0])
        centre = sample.means[i]
        front = (centre - torch.tensor([0.0, 0.0, 2.0]))[None]  # 2 units in front of it, on the training side
        side = (centre - torch.tensor([2.0, 0.0, 0.0]))[None]  # 2 units to its -x side, looking along +x
        v_front = float(field.colour_variance(front)[0, i])
        v_side = float(field.colour_variance(side)[0, i])
        assert v_side > 5 * v_front
        assert v_side <= float(field.colour_prior[0]) * 0.2821**2 + float(field.colour_prior[3]) * 0.4886**2 + 1e-9

    def test_the_variance_is_the_diagonal_laplace_posterior_not_the_full_one(self):
        """``colour_variance`` is sum_b Y_b(d)^2 / precision_b with the diagonal of the Laplace precision (its
        docstring: the coefficients' covariance is dropped), not Y(d)^T (sum_v s Y_v Y_v^T + diag(1/prior))^-1
        Y(d). Seen from one direction only, the exact posterior keeps about the prior's variance from the
        opposite side; the diagonal one gives it the seen side's (band 1 flips sign, its square does not)."""
        from uncertsplat.render.sh import sh_basis, view_directions

        s = GaussianSample(means=torch.zeros(1, 3), quats=torch.tensor([[1.0, 0, 0, 0]]),
                           scales=torch.ones(1, 3), opacities=torch.ones(1), sh=torch.zeros(1, 4, 3),
                           sh_degree=1)
        obs, noise = 200.0, 1e-3
        prior = torch.tensor([0.05 / 0.28209479177387814**2, 0.01, 0.01, 0.01], dtype=torch.float64)
        seen_centre = torch.tensor([[0.0, 0.0, 5.0]], dtype=torch.float64)
        y_seen = sh_basis(1, view_directions(s.means.double(), seen_centre))[0, 0]
        evidence = (obs * y_seen.square())[None]
        field = ResidualField(sample=s, variance=torch.tensor([noise]), seen=torch.tensor([True]),
                              mean_variance=noise, colour_evidence=evidence.float(),
                              colour_prior=prior.float())
        centers = torch.tensor([[0.0, 0.0, 5.0], [0.0, 0.0, -5.0]])
        got = field.colour_variance(centers)[:, 0].double()
        y = sh_basis(1, view_directions(s.means.double(), centers.double()))[:, 0]  # [2,4]
        diagonal = (y.square() / (evidence / noise + 1.0 / prior)).sum(-1)
        torch.testing.assert_close(got, diagonal, rtol=1e-5, atol=1e-12)
        full = torch.linalg.inv(obs / noise * torch.outer(y_seen, y_seen) + torch.diag(1.0 / prior))
        exact = torch.einsum("cb,bd,cd->c", y, full, y)
        # the opposite side is as known as the seen one; exactly, it keeps (about) the prior's variance
        assert float(got[1]) == pytest.approx(float(got[0]), rel=1e-5)
        assert float(exact[1]) > 100 * float(got[1])


    @pytest.mark.parametrize("degree", [1, 2])
    def test_the_block_form_is_the_exact_posterior_of_the_dc_term_and_band_1(self, degree):
        """``colour_covariance="block"`` (``colour_cross``): Y_low^T (E_low / v + diag(1/prior_low))^-1 Y_low for the
        DC term and band 1, plus the diagonal form for the higher bands; at degree 1 that is the exact Laplace
        posterior, so a Gaussian seen from one side only keeps (about) the prior's variance from the other, where the
        diagonal form gives it the seen side's. A precision whose evidence exceeds the prior's inverse by 1e9 stays
        finite (float64 Cholesky)."""
        from uncertsplat.render.sh import sh_basis, view_directions

        nb = (degree + 1) ** 2
        s = GaussianSample(means=torch.zeros(1, 3), quats=torch.tensor([[1.0, 0, 0, 0]]), scales=torch.ones(1, 3),
                           opacities=torch.ones(1), sh=torch.zeros(1, nb, 3), sh_degree=degree)
        obs, noise = 200.0, 1e-3
        prior = torch.cat([torch.tensor([0.05 / 0.28209479177387814**2]), torch.full((nb - 1,), 0.01)]).double()
        seen = torch.tensor([[0.0, 0.0, 5.0], [0.0, 3.0, 4.0]], dtype=torch.float64)  # two views, 37 degrees apart
        ys = sh_basis(degree, view_directions(s.means.double(), seen))[:, 0]  # [2,B]
        evidence = (obs * ys.square()).sum(0)[None]  # [1,B]
        cross = (obs * ys[:, :4, None] * ys[:, None, :4]).sum(0)[None]  # [1,4,4]
        base = dict(sample=s, variance=torch.tensor([noise]), seen=torch.tensor([True]), mean_variance=noise,
                    colour_evidence=evidence.float(), colour_prior=prior.float())
        block, diagonal = ResidualField(**base, colour_cross=cross), ResidualField(**base)
        # (the last from off both axes: there every coefficient of band 2 is non-zero, the first one too)
        centers = torch.tensor([[0.0, 0.0, 5.0], [0.0, 0.0, -5.0], [4.0, 0.0, 3.0], [2.0, 3.0, 4.0]])
        got = block.colour_variance(centers)[:, 0].double()
        y = sh_basis(degree, view_directions(s.means.double(), centers.double()))[:, 0]  # [3,B]
        p_low = obs / noise * (ys[:, :4, None] * ys[:, None, :4]).sum(0) + torch.diag(1.0 / prior[:4])
        want = torch.einsum("cb,bd,cd->c", y[:, :4], torch.linalg.inv(p_low), y[:, :4])
        want = want + (y[:, 4:].square() / (evidence[0, 4:] / noise + 1.0 / prior[4:])).sum(-1)
        torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-12)
        flat = diagonal.colour_variance(centers)[:, 0].double()
        assert float(got[1]) > 50 * float(flat[1])  # the far side: unknown with the block, "seen" without
        assert float(got[0]) < float(flat[0])  # a seen direction: the joint posterior pins it down more
        sure = ResidualField(**{**base, "colour_evidence": evidence.float() * 1e9}, colour_cross=cross * 1e9)
        assert bool(torch.isfinite(sure.colour_variance(centers)).all())
        # a block that is not positive definite (a damaged cache) or not a number: that Gaussian's diagonal form
        for bad in (-1e9 * torch.eye(4, dtype=torch.float64)[None], torch.full((1, 4, 4), float("nan"))):
            odd = ResidualField(**base, colour_cross=bad).colour_variance(centers)
            torch.testing.assert_close(odd, diagonal.colour_variance(centers))

    def test_the_block_form_is_fitted_kept_by_subset_and_state_and_refused_for_another_degree(self):
        sample, cams, d = _sample(), _cams(3), 0.05
        sample = replace(sample, sh=torch.cat([sample.sh, torch.zeros(len(sample.sh), 3, 3)], 1), sh_degree=1)
        with torch.no_grad():
            images = (RENDER(sample, cams).rgb + d).clamp(0, 1)
        diag = self._fit(sample, cams, images)
        block = self._fit(sample, cams, images, colour_covariance="block")
        assert diag.colour_cross is None and block.colour_cross.shape == (len(sample.means), 4, 4)
        # its diagonal is the diagonal form's evidence; the noise is the same
        torch.testing.assert_close(torch.diagonal(block.colour_cross, dim1=1, dim2=2).float(), block.colour_evidence)
        torch.testing.assert_close(block.colour_evidence, diag.colour_evidence)
        # sum_views Y(d_v) Y(d_v)^T sum_p w: symmetric, and its off-diagonal the products of different coefficients
        torch.testing.assert_close(block.colour_cross, block.colour_cross.transpose(1, 2), rtol=0, atol=0)
        assert float(block.colour_cross[:, 0, 1:].abs().max()) > 0.0
        # fitted on a share of the views: scaled to all of them as the diagonal evidence is
        four = self._fit(sample, cams, images, colour_covariance="block", view_factor=4.0)
        torch.testing.assert_close(four.colour_cross, 4 * block.colour_cross)
        # blended for several cameras: each with its own direction's colour variance (one moved 1 to the side; band 1
        # given a spread, so that its prior, and the variance's dependence on the direction, is not 0)
        band1 = 0.2 * torch.randn(len(sample.means), 3, 3, generator=torch.Generator().manual_seed(8))
        lit = replace(sample, sh=torch.cat([sample.sh[:, :1], band1], 1))
        with torch.no_grad():
            lit_images = RENDER(lit, cams).rgb + d
        lit_field = self._fit(lit, cams, lit_images, colour_covariance="block")
        side = cams.cam_from_world[:1].clone()
        side[0, 0, 3] = -1.0
        both = Cameras(torch.cat([cams.cam_from_world[:1], side]), cams.K[:2], W, H, ("v0.png", "side.png"))
        one_by_one = torch.cat([lit_field.blended_parts(both[[i]], RENDER)["colour posterior"] for i in range(2)])
        torch.testing.assert_close(lit_field.blended_parts(both, RENDER)["colour posterior"], one_by_one, rtol=1e-4,
                                   atol=0)
        keep = torch.arange(len(sample.means)) % 2 == 0
        torch.testing.assert_close(block.subset(keep).colour_cross, block.colour_cross[keep])
        back = ResidualField.from_state(sample, block.state())
        torch.testing.assert_close(back.colour_variance(cams.centers), block.colour_variance(cams.centers))
        with pytest.raises(ValueError, match="another SH degree"):
            ResidualField.from_state(replace(sample, sh=sample.sh[:, :1], sh_degree=0),
                                     {**block.state(), "colour_evidence": block.colour_evidence[:, :1]})
        with pytest.raises(ValueError, match="colour_covariance"):
            self._fit(sample, cams, images, colour_covariance="full")
        # at SH degree 0 the block is the DC term alone: no joint evidence, the diagonal form to the bit
        flat = replace(sample, sh=sample.sh[:, :1], sh_degree=0)
        assert self._fit(flat, cams, images, colour_covariance="block").colour_cross is None

    def test_blended_adds_the_unknown_colour_where_a_new_view_uncovers_an_unseen_gaussian(self):
        """The Gaussian behind every training camera is unseen; a camera turned around sees it, and its blended
        variance there is (almost) noise + prior; on the training views the colour term adds little."""
        sample, cams, d = _sample(), _cams(3), 0.05
        with torch.no_grad():
            out = RENDER(sample, cams)
        images = (out.rgb + d).clamp(0, 1)
        field = self._fit(sample, cams, images)
        plain = fit_residual_field(sample, cams, images, RENDER)
        on_train, plain_train = field.blended(cams, RENDER), plain.blended(cams, RENDER)
        assert float((on_train - plain_train).max()) < 0.15 * float(plain_train.max())
        back = torch.diag(torch.tensor([-1.0, 1.0, -1.0, 1.0]))[None]  # at the origin, looking down -z
        turned = Cameras(back, cams.K[:1], W, H, ("back.png",))
        with torch.no_grad():
            alpha = RENDER(sample, turned).alpha
        centre = alpha[0, H // 2, W // 2, 0]
        assert float(centre) > 0.3, "the turned camera sees the unseen Gaussian"
        got = field.blended(turned, RENDER)[0, H // 2, W // 2, 0]
        expect = centre * (field.variance[-1] + field.colour_variance(turned.centers)[0, -1])
        torch.testing.assert_close(got, expect, rtol=1e-3, atol=1e-7)
        assert float(got) > 0.5 * float(centre) * float(field.colour_prior[0]) * 0.2821**2

    def test_blended_parts_are_the_noise_the_colour_and_the_edge_and_add_up_to_blended(self):
        """``blended_parts``: "pixel noise" is the noise alone blended, "colour posterior" ``colour_blended``, "edge"
        the edge term, for each of several cameras (the colour term depends on the camera); ``blended`` is their sum.
        Without a colour or an edge term the part is absent."""
        sample, cams, d = _sample(), _cams(3), 0.05
        out, g, images = _edge_images(sample, cams, d, 0.5)
        field = self._fit(sample, cams, images, edge_scale=0.5)
        back = torch.diag(torch.tensor([-1.0, 1.0, -1.0, 1.0]))[None]  # the turned camera sees the unseen Gaussian
        both = Cameras(torch.cat([cams.cam_from_world[:1], back]), cams.K[:2], W, H, ("v0.png", "back.png"))
        parts = field.blended_parts(both, RENDER)
        assert list(parts) == ["pixel noise", "colour posterior", "edge"]
        noise_only = replace(field, colour_evidence=None, edge_scale=0.0)
        torch.testing.assert_close(parts["pixel noise"], noise_only.blended(both, RENDER), rtol=1e-5, atol=1e-7)
        torch.testing.assert_close(parts["colour posterior"], field.colour_blended(both, RENDER), rtol=1e-5, atol=1e-7)
        torch.testing.assert_close(parts["edge"], field.edge(both, RENDER))
        assert float(parts["colour posterior"][1].max()) > 3 * float(parts["colour posterior"][0].max())  # (x5.7)
        torch.testing.assert_close(field.blended(both, RENDER),
                                   parts["pixel noise"] + parts["colour posterior"] + parts["edge"], rtol=0, atol=0)
        assert list(noise_only.blended_parts(both, RENDER)) == ["pixel noise"]

    def test_the_block_form_on_the_device(self, device):
        """The block form fitted, kept (``state``/``from_state``) and rendered on the test session's device (``--device
        fake-cuda`` in ``make test-fake-cuda``: its float64 evidence and Cholesky on the Gaussians' device); at SH
        degree 0 it is the diagonal form (one coefficient: nothing to take jointly, no block built)."""
        render_on = functools.partial(render, background=torch.tensor([0.2, 0.4, 0.6], device=device))
        s = _sample()
        s = replace(s, means=s.means.to(device), quats=s.quats.to(device), scales=s.scales.to(device),
                    opacities=s.opacities.to(device), sh=torch.cat([s.sh, torch.zeros(len(s.sh), 3, 3)], 1).to(device),
                    sh_degree=1)
        cams = _cams(3).to(device)
        with torch.no_grad():
            images = (render_on(s, cams).rgb + 0.05).clamp(0, 1)
        block = fit_residual_field(s, cams, images, render_on, colour_posterior=True, colour_covariance="block")
        assert block.colour_cross.device.type == device.type and block.colour_cross.dtype == torch.float64
        var = block.colour_variance(cams.centers)
        assert var.device.type == device.type and bool(torch.isfinite(var).all())
        back = ResidualField.from_state(s, block.state())
        assert back.colour_cross.device.type == device.type
        torch.testing.assert_close(back.colour_variance(cams.centers), var)
        parts = block.blended_parts(cams, render_on)
        assert list(parts) == ["pixel noise", "colour posterior"]
        assert all(p.device.type == device.type for p in parts.values())
        s0 = replace(s, sh=s.sh[:, :1], sh_degree=0)
        kw = dict(colour_posterior=True)
        one = fit_residual_field(s0, cams, images, render_on, colour_covariance="block", **kw)
        flat = fit_residual_field(s0, cams, images, render_on, **kw)
        assert one.colour_cross is None  # (no block is built at degree 0: the diagonal form, to the bit)
        assert torch.equal(one.colour_variance(cams.centers), flat.colour_variance(cams.centers))

    def test_constant_images_and_subset(self):
        """Images without any variation: the prior is 0 (floored), every colour variance finite and ~0; ``subset``
        keeps each Gaussian's evidence."""
        sample, cams = _sample(), _cams(2)
        images = torch.full((2, H, W, 3), 0.4)
        field = self._fit(sample, cams, images)
        var = field.colour_variance(cams.centers)
        assert bool(torch.isfinite(var).all()) and float(var.max()) < 1e-9
        keep = torch.arange(len(sample)) % 3 != 0
        sub = field.subset(keep)
        torch.testing.assert_close(sub.colour_evidence, field.colour_evidence[keep])
        torch.testing.assert_close(sub.colour_variance(cams.centers), var[:, keep])

    def test_a_perfect_fit_leaves_only_the_unseen_colours_unknown(self):
        """Zero residual (images = the render): every seen Gaussian's noise is 0 and its colour variance (almost) 0,
        finite; the unseen one keeps the prior; nothing is NaN."""
        sample, cams = _sample(), _cams(3)
        with torch.no_grad():
            images = RENDER(sample, cams).rgb
        field = self._fit(sample, cams, images)
        var = field.colour_variance(cams.centers)
        assert bool(torch.isfinite(var).all())
        assert float(field.variance[field.seen].abs().max()) < 1e-10
        assert float(var[:, field.seen].max()) < 1e-6
        pixel_var = float(images.double().reshape(-1, 3).var(0, unbiased=False).mean())
        assert float(var[0, -1]) == pytest.approx(pixel_var, rel=1e-4)
        assert 0.0 < field.colour_unknown_fraction() < 0.5


def _edge_images(sample, cams, d, delta2):
    """(render, g, images): training images whose residual is sqrt(d^2 + delta2 g) in every channel, g the render's
    squared image gradient, i.e. noise d^2 plus an edge term of exactly delta2."""
    from uncertsplat.uncertainty.residual import image_gradient_sq

    with torch.no_grad():
        out = RENDER(sample, cams)
    g = image_gradient_sq(out.rgb)
    return out, g, out.rgb + (d * d + delta2 * g).sqrt()


class TestEdgeTerm:
    """The edge term ``delta^2 |grad I|^2`` (``image_gradient_sq``, ``fit_edge_scale``, ``ResidualField.edge``)."""

    def test_gradient_of_ramps_constants_and_single_pixels(self):
        from uncertsplat.uncertainty.residual import image_gradient_sq

        ys, xs = torch.meshgrid(torch.arange(5.0), torch.arange(7.0), indexing="ij")
        ramp = torch.stack([0.1 * xs, 0.1 * xs, 0.1 * xs], -1)  # slope 0.1 per pixel along x in every channel
        torch.testing.assert_close(image_gradient_sq(ramp), torch.full((5, 7, 1), 0.01))  # the borders too (linear)
        both = torch.stack([0.3 * ys, 0.0 * xs, 0.0 * xs], -1)[None]  # batched; one channel of three moves along y
        torch.testing.assert_close(image_gradient_sq(both), torch.full((1, 5, 7, 1), 0.09 / 3))
        assert float(image_gradient_sq(torch.full((4, 6, 3), 0.7)).abs().max()) == 0.0
        row = torch.stack([0.2 * torch.arange(9.0)] * 3, -1)[None]  # [1,9,3]: one row, no y difference to take
        torch.testing.assert_close(image_gradient_sq(row), torch.full((1, 9, 1), 0.04))
        pair = torch.stack([0.2 * torch.arange(2.0)] * 3, -1)[None]  # [1,2,3]: two pixels are enough for a difference
        torch.testing.assert_close(image_gradient_sq(pair), torch.full((1, 2, 1), 0.04))

    def test_the_slope_is_recovered_when_the_residual_follows_the_gradient(self):
        """Residuals with r^2 = s0 + delta^2 g (+ an explained e) exactly: least squares gives delta^2 back; pixels the
        model does not cover (alpha < 0.5) do not count, whatever their residual."""
        from uncertsplat.uncertainty.residual import fit_edge_scale, image_gradient_sq

        sample, cams = _sample(seed=3), _cams(3)
        with torch.no_grad():
            out = RENDER(sample, cams)
        g = image_gradient_sq(out.rgb)  # [3,H,W,1]
        s0, delta2, e = 1e-4, 0.8, 2e-5
        sign = torch.where(torch.rand(out.rgb.shape, generator=torch.Generator().manual_seed(0)) < 0.5, -1.0, 1.0)
        images = out.rgb + sign * (s0 + delta2 * g + e).sqrt()  # |r| the same in every channel
        uncovered = out.alpha < 0.5
        assert bool(uncovered.any()) and bool((~uncovered).any())
        images = torch.where(uncovered, images + 0.3, images)
        got = fit_edge_scale(sample, cams, images, RENDER, explained=lambda cam: torch.full((1, H, W, 1), e))
        assert got == pytest.approx(delta2, rel=1e-3)
        # without telling it about e, a constant e only moves the intercept
        assert fit_edge_scale(sample, cams, images, RENDER) == pytest.approx(delta2, rel=1e-3)
        # covered pixels outside the masks do not count either, whatever their residual
        masks = torch.ones(3, H, W, 1, dtype=torch.bool)
        masks[0, :, : W // 2] = False
        assert bool((~uncovered[0, :, : W // 2]).any())
        spoiled = torch.where(~masks, images + 0.3, images)
        assert fit_edge_scale(sample, cams, spoiled, RENDER, masks=masks) == pytest.approx(delta2, rel=1e-3)
        assert fit_edge_scale(sample, cams, spoiled, RENDER) != pytest.approx(delta2, rel=0.1)

    def test_no_gradient_relation_gives_zero_and_the_field_renders_nothing_then(self):
        from uncertsplat.uncertainty.residual import fit_edge_scale

        sample, cams, d = _sample(), _cams(2), 0.05
        with torch.no_grad():
            out = RENDER(sample, cams)
        # a residual that shrinks where the image changes: a negative slope is clamped to 0
        from uncertsplat.uncertainty.residual import image_gradient_sq

        g = image_gradient_sq(out.rgb)
        images = out.rgb + (d * d / (1.0 + 100 * g)).sqrt()
        assert fit_edge_scale(sample, cams, images, RENDER) == 0.0
        # nothing covered (every Gaussian behind the cameras): no pixel to fit on
        behind = replace(sample, means=sample.means * torch.tensor([1.0, 1.0, -1.0]))
        assert fit_edge_scale(behind, cams, images, RENDER) == 0.0
        field = fit_residual_field(sample, cams, out.rgb + d, RENDER)
        assert field.edge_scale == 0.0
        assert float(field.edge(cams, RENDER).abs().max()) == 0.0

    def test_the_noise_is_fitted_to_what_the_edge_term_leaves_and_blended_adds_it(self):
        sample, cams, d, delta2 = _sample(), _cams(3), 0.05, 0.5
        out, g, images = _edge_images(sample, cams, d, delta2)
        field = fit_residual_field(sample, cams, images, RENDER, edge_scale=delta2)
        seen = field.seen
        torch.testing.assert_close(field.variance[seen], torch.full_like(field.variance[seen], d * d), rtol=1e-3,
                                   atol=1e-7)
        # the Gaussian no pixel sees gets the whole residual's mean, the edge part included
        assert not bool(seen[-1])
        assert float(field.variance[-1]) == pytest.approx(float((d * d + delta2 * g).mean()), rel=1e-4)
        assert field.edge_scale == delta2
        torch.testing.assert_close(field.edge(cams, RENDER), delta2 * g)
        torch.testing.assert_close(field.blended(cams, RENDER), out.alpha * d * d + delta2 * g, rtol=1e-3, atol=1e-7)
        # an edge term larger than the residuals: each Gaussian's noise is clamped at 0, never negative
        over = fit_residual_field(sample, cams, images, RENDER, edge_scale=50 * delta2)
        assert float(over.variance.min()) == 0.0 and bool((over.variance >= 0).all())
        # a fitted noise level scales both parts; pruning keeps the edge term
        assert field.scaled(0.5).edge_scale == pytest.approx(0.25)
        assert field.subset(torch.arange(len(sample.means)) % 2 == 0).edge_scale == delta2


    def test_fitted_in_the_same_pass_as_the_noise_it_is_the_two_step_fit(self):
        """``edge_scale="fit"``: the slope and the noise from one pass over the views equal ``fit_edge_scale`` followed
        by the noise fitted with that slope, with an explained variance and a mask; a constant residual gives about 0;
        a word other than "fit" is refused."""
        from uncertsplat.uncertainty.residual import fit_edge_scale

        sample, cams, d, delta2 = _sample(), _cams(3), 0.05, 0.5
        _, _, images = _edge_images(sample, cams, d, delta2)
        masks = torch.ones(3, H, W, 1, dtype=torch.bool)
        masks[1, :, : W // 3] = False

        def explained(cam):
            return torch.full((1, H, W, 1), 3e-4)

        slope = fit_edge_scale(sample, cams, images, RENDER, masks=masks, explained=explained)
        assert slope == pytest.approx(delta2, rel=0.05)
        two = fit_residual_field(sample, cams, images, RENDER, masks=masks, explained=explained, colour_posterior=True,
                                 edge_scale=slope)
        one = fit_residual_field(sample, cams, images, RENDER, masks=masks, explained=explained, colour_posterior=True,
                                 edge_scale="fit")
        assert one.edge_scale == pytest.approx(slope, rel=1e-9)
        for k in ("variance", "pixel_variance", "observations", "colour_evidence"):
            torch.testing.assert_close(getattr(one, k), getattr(two, k), rtol=1e-5, atol=1e-9)
        assert torch.equal(one.seen, two.seen) and one.mean_variance == pytest.approx(two.mean_variance, rel=1e-12)
        with torch.no_grad():
            plain = RENDER(sample, cams).rgb
        flat = fit_residual_field(sample, cams, plain + d, RENDER, edge_scale="fit")
        assert flat.edge_scale < 1e-5  # (float32 rounding of r^2 only)
        with pytest.raises(ValueError, match="fit"):
            fit_residual_field(sample, cams, images, RENDER, edge_scale="auto")


def test_the_relative_leverage_raises_only_the_gaussians_observed_less_than_the_median():
    """``out_of_sample(relative=True)``: the factor (1 - h_m) / (1 - h) where above 1, h_m the median leverage of the
    seen Gaussians; 1 for the median and the better observed; the cap for one no pixel saw; nothing when the median
    is at the cap."""
    sample = _sample(n=5)
    obs = torch.tensor([100.0, 10.0, 5.0, 2.0, 0.0])  # h = 12 / (3 obs): 0.04, 0.4, 0.8, 0.9 (cap), 0.9 (cap)
    field = ResidualField(sample=sample, variance=torch.full((5,), 1e-3), seen=obs > 0, mean_variance=1e-3,
                          observations=obs)
    h = torch.tensor([0.04, 0.4, 0.8, 0.9, 0.9], dtype=torch.float64)
    hm = torch.tensor([0.04, 0.4, 0.8, 0.9]).double().median()  # of the seen: torch's lower median, 0.4
    want = ((1 - hm) / (1 - h)).clamp_min(1.0)
    got = field.out_of_sample(12, relative=True)
    torch.testing.assert_close(got.variance.double() / 1e-3, want, rtol=1e-5, atol=0)
    assert torch.equal(got.variance[:2], field.variance[:2])  # the median and the better observed: unchanged
    full = field.out_of_sample(12)
    assert bool((full.variance > got.variance).all())  # full divides every Gaussian by 1 - h
    # a capture where the median Gaussian is at the cap (every Gaussian fitted by a few pixels): nothing changes
    sparse = replace(field, observations=torch.tensor([1.0, 2.0, 3.0, 100.0, 0.0]), seen=torch.tensor([True] * 4 + [False]))
    back = sparse.out_of_sample(12, relative=True)
    assert torch.equal(back.variance, sparse.variance)


def test_the_colour_posterior_divides_by_the_whole_noise_with_an_edge_term():
    """With an edge term a Gaussian's own noise is what the edge term leaves; its pixels' variance in the likelihood
    (what the colour posterior divides by) stays the whole residual, so edge Gaussians do not get exactly known
    colours."""
    sample, cams, d, delta2 = _sample(), _cams(3), 0.05, 0.5
    _, _, images = _edge_images(sample, cams, d, delta2)
    plain = fit_residual_field(sample, cams, images, RENDER, colour_posterior=True)
    edge = fit_residual_field(sample, cams, images, RENDER, colour_posterior=True, edge_scale=delta2)
    assert plain.pixel_variance is None and edge.pixel_variance is not None
    torch.testing.assert_close(edge.likelihood_variance, plain.variance)
    assert bool((edge.variance[edge.seen] < plain.variance[edge.seen] - 1e-9).any())  # the edge share came off
    centers = cams.centers
    torch.testing.assert_close(edge.colour_variance(centers), plain.colour_variance(centers))
    assert edge.colour_unknown_fraction() == plain.colour_unknown_fraction()
    # scaled, subset and the leverage carry the whole noise along
    torch.testing.assert_close(edge.scaled(2.0).likelihood_variance, 2.0 * plain.variance)
    keep = torch.arange(len(sample.means)) % 3 == 0
    torch.testing.assert_close(edge.subset(keep).likelihood_variance, plain.variance[keep])
    torch.testing.assert_close(edge.out_of_sample(14).likelihood_variance, plain.out_of_sample(14).variance)


class TestState:
    """``ResidualField.state`` / ``from_state``: what the cache of the fitted noise stores, and what it refuses."""

    def test_the_field_comes_back_exactly(self, tmp_path):
        from uncertsplat.uncertainty.residual import ResidualField

        sample, cams, d, delta2 = _sample(), _cams(3), 0.05, 0.5
        _, _, images = _edge_images(sample, cams, d, delta2)
        field = fit_residual_field(sample, cams, images, RENDER, colour_posterior=True, edge_scale=delta2)
        field = field.scaled(0.7).out_of_sample(14)
        torch.save(field.state(), tmp_path / "f.pt")
        back = ResidualField.from_state(sample, torch.load(tmp_path / "f.pt", weights_only=True))
        for k in ResidualField.STATE_TENSORS:
            torch.testing.assert_close(getattr(back, k), getattr(field, k), rtol=0, atol=0)
        for k in ResidualField.STATE_NUMBERS:
            assert getattr(back, k) == getattr(field, k)
        torch.testing.assert_close(back.blended(cams, RENDER), field.blended(cams, RENDER), rtol=0, atol=0)
        plain = fit_residual_field(sample, cams, images, RENDER)  # no colour term, no edge term: the Nones too
        back = ResidualField.from_state(sample, plain.state())
        assert back.colour_evidence is None and back.pixel_variance is None and back.edge_scale == 0.0

    def test_a_state_for_other_gaussians_is_refused(self):
        from uncertsplat.uncertainty.residual import ResidualField

        sample, cams = _sample(), _cams(2)
        _, _, images = _edge_images(sample, cams, 0.05, 0.0)
        state = fit_residual_field(sample, cams, images, RENDER, colour_posterior=True).state()
        with pytest.raises(ValueError, match="rows"):
            ResidualField.from_state(_sample(n=20), state)
        deg1 = replace(sample, sh=torch.zeros(len(sample.means), 4, 3), sh_degree=1)
        with pytest.raises(ValueError, match="SH degree"):
            ResidualField.from_state(deg1, state)
        with pytest.raises(ValueError, match="edge_scale"):
            ResidualField.from_state(sample, {k: v for k, v in state.items() if k != "edge_scale"})
