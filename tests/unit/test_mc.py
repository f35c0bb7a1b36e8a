"""Monte-Carlo rendering: Welford mean/std against direct formulas; memory does not grow with K."""

from __future__ import annotations

import weakref
from dataclasses import replace

import pytest
import torch

from uncertsplat.types import Cameras, GaussianSample, RenderOutput
from uncertsplat.uncertainty.mc import RunningMoments, mc_render

H, W, C = 6, 5, 2


def _cameras(device):
    eye = torch.eye(4, device=device).expand(C, 4, 4).contiguous()
    K = torch.eye(3, device=device).expand(C, 3, 3).contiguous()
    return Cameras(eye, K, W, H, ("a.png", "b.png"))


class Dummy:
    """A 'posterior' with one scalar v ~ N(0.5, 0.1^2) per sample; rgb = v * pattern, depth = 2 + v."""

    def __init__(self, device, requires_grad=False, h=H, w=W):
        self.device = device
        self.h, self.w = h, w
        self.values: list[float] = []
        self.alive: list[weakref.ref] = []
        self.max_alive_at_render = 0
        self.pattern = torch.linspace(0, 1, C * h * w * 3, device=device).reshape(C, h, w, 3)
        self.pattern[0, 0, 0] = 0.0  # a pixel whose value never changes: std must be exactly 0
        self.requires_grad = requires_grad

    def sample_fn(self, generator):
        v = 0.5 + 0.1 * torch.randn((), generator=generator)
        self.values.append(float(v))
        means = torch.full((1, 3), float(v), device=self.device, requires_grad=self.requires_grad)
        return GaussianSample(
            means=means,
            quats=torch.tensor([[1.0, 0, 0, 0]], device=self.device),
            scales=torch.ones(1, 3, device=self.device),
            opacities=torch.ones(1, device=self.device),
            sh=torch.zeros(1, 1, 3, device=self.device),
        )

    def render_fn(self, sample, cameras):
        # how many earlier renders are still referenced somewhere when a new one is made
        self.max_alive_at_render = max(self.max_alive_at_render, sum(r() is not None for r in self.alive))
        v = sample.means[0, 0]
        rgb = v * self.pattern
        h, w = self.h, self.w
        out = RenderOutput(
            rgb=rgb,
            alpha=torch.full((C, h, w, 1), 0.75, device=self.device),
            depth=(2.0 + v) * torch.ones(C, h, w, 1, device=self.device),
            depth_expected=torch.zeros(C, h, w, 1, device=self.device),
            means2d=torch.zeros(C, 1, 2, device=self.device),
            radii=torch.zeros(C, 1, device=self.device),
        )
        # Track the storages (not the tensor objects): a detached view or a slice kept by mc_render
        # would keep the storage alive and be caught here.
        self.alive.append(weakref.ref(rgb.untyped_storage()))
        self.alive.append(weakref.ref(out.depth.untyped_storage()))
        return out


def test_mean_std_match_direct_formulas(device):
    d = Dummy(device)
    maps, samples = mc_render(d.sample_fn, d.render_fn, _cameras(device), 7, torch.Generator().manual_seed(0),
                              keep_samples=True)
    v = torch.tensor(d.values, dtype=torch.float64)
    assert len(d.values) == 7
    assert samples.rgb.shape == (7, C, H, W, 3) and samples.depth.shape == (7, C, H, W, 1)
    assert torch.allclose(maps.rgb_mean, samples.rgb.mean(0), atol=1e-6)
    assert torch.allclose(maps.rgb_std, samples.rgb.std(0, unbiased=True), atol=1e-6)
    assert torch.allclose(maps.rgb_std.double().cpu(), v.std() * d.pattern.double().cpu(), atol=1e-6)
    assert maps.rgb_std[0, 0, 0].eq(0).all()  # exactly zero, not 1e-9
    assert torch.allclose(maps.depth_mean.double().cpu(), (2 + v.mean()).expand(C, H, W, 1), atol=1e-6)
    assert torch.allclose(maps.depth_std.double().cpu(), v.std().expand(C, H, W, 1), atol=1e-6)
    assert torch.allclose(maps.alpha_mean, torch.full_like(maps.alpha_mean, 0.75))
    assert maps.n_samples == 7 and maps.image_names == ("a.png", "b.png")


def test_rgb_std_never_exceeds_that_of_a_colour_in_the_unit_range(device):
    """Side terms that add up past 0.25 in variance (a render far finer than the photos) give 0.5, the largest std
    a value in [0, 1] has; the depth std is not bounded."""
    from uncertsplat.uncertainty.mc import RGB_STD_MAX

    d = Dummy(device)
    huge = torch.full((C, H, W, 1), 0.5, device=device)  # variance 0.5: std 0.71 before the bound
    maps, _ = mc_render(d.sample_fn, d.render_fn, _cameras(device), 3, torch.Generator().manual_seed(0),
                        extra_var=huge, extra_depth_var=huge)
    assert RGB_STD_MAX == 0.5 and float(maps.rgb_std.max()) == 0.5
    assert torch.allclose(maps.depth_std.min(), torch.tensor(0.5 ** 0.5, device=device), atol=0.05)
    small, _ = mc_render(d.sample_fn, d.render_fn, _cameras(device), 3, torch.Generator().manual_seed(0),
                         extra_var=huge * 0.01)
    assert float(small.rgb_std.max()) < 0.5  # below the bound, untouched


def test_the_terms_are_each_part_of_the_variance_and_add_up_to_it(device):
    """``terms=True``: the samples' spread, the resolution renders, the empty rays and the named side terms, in the
    order they are added, sum to the variance (RGB: the mean over the channels of std^2, below the cap); a mapping of
    side terms gives the std of their sum to the bit; a bare tensor is named "extra"; without ``terms`` none."""
    from uncertsplat.uncertainty.mc import sum_terms

    d = Dummy(device)
    a = torch.full((C, H, W, 1), 0.01, device=device)
    b = torch.linspace(0.0, 0.02, C * H * W, device=device).reshape(C, H, W, 1)
    dep = torch.full((C, H, W, 1), 0.3, device=device)

    def shift(generator):  # a second 'posterior' for the resolution term
        return d.sample_fn(generator)

    def render(mapping):
        return mc_render(d.sample_fn, d.render_fn, _cameras(device), 5, torch.Generator().manual_seed(4),
                         empty_std=(0.2, 0.5), coverage=1.0, extra_var=mapping,
                         extra_depth_var={"depth spread": dep}, shift_fn=shift, terms=True)[0]

    maps = render({"pixel noise": a, "view consistency": b})
    assert list(maps.rgb_terms) == ["samples", "resolution", "empty rays", "pixel noise", "view consistency"]
    assert list(maps.depth_terms) == ["samples", "resolution", "empty rays", "depth spread"]
    assert all(t.shape == (C, H, W, 1) and float(t.min()) >= 0.0 for t in maps.rgb_terms.values())
    torch.testing.assert_close(sum_terms(maps.rgb_terms), maps.rgb_std.square().mean(-1, keepdim=True),
                               rtol=1e-5, atol=1e-8)
    torch.testing.assert_close(sum_terms(maps.depth_terms), maps.depth_std.square(), rtol=1e-5, atol=1e-8)
    torch.testing.assert_close(maps.rgb_terms["view consistency"], b)
    assert float(maps.rgb_terms["samples"].max()) > 0.0 and float(maps.rgb_terms["resolution"].max()) > 0.0
    summed = render(a + b)  # the sum given as one tensor: the same std to the bit, named "extra"
    assert torch.equal(summed.rgb_std, maps.rgb_std) and list(summed.rgb_terms)[-1] == "extra"
    plain = mc_render(d.sample_fn, d.render_fn, _cameras(device), 5, torch.Generator().manual_seed(4))[0]
    assert plain.rgb_terms is None and plain.depth_terms is None
    with pytest.raises(ValueError, match="empty mapping"):
        sum_terms({})


def test_single_sample_std_zero(device):
    d = Dummy(device)
    maps, samples = mc_render(d.sample_fn, d.render_fn, _cameras(device), 1, torch.Generator().manual_seed(0))
    assert samples is None
    assert maps.rgb_std.eq(0).all() and maps.depth_std.eq(0).all()
    assert torch.allclose(maps.rgb_mean, d.values[0] * d.pattern)


def test_same_seed_same_maps(device):
    a = mc_render(Dummy(device).sample_fn, Dummy(device).render_fn, _cameras(device), 5,
                  torch.Generator().manual_seed(3))[0]
    b = mc_render(Dummy(device).sample_fn, Dummy(device).render_fn, _cameras(device), 5,
                  torch.Generator().manual_seed(3))[0]
    assert torch.equal(a.rgb_std, b.rgb_std) and torch.equal(a.rgb_mean, b.rgb_mean)


@pytest.mark.parametrize("k", [2, 16])
def test_memory_does_not_grow_with_k(device, k):
    d = Dummy(device)
    mc_render(d.sample_fn, d.render_fn, _cameras(device), k, torch.Generator().manual_seed(1))
    # No earlier render is alive when the next one is made, and none survives the call.
    assert d.max_alive_at_render == 0
    assert all(r() is None for r in d.alive)
    # keep_samples=True does retain them (so the check above can fail)
    d2 = Dummy(device)
    _, kept = mc_render(d2.sample_fn, d2.render_fn, _cameras(device), k, torch.Generator().manual_seed(1),
                        keep_samples=True)
    assert d2.max_alive_at_render == 2 * (k - 1)  # rgb and depth of every earlier sample


def test_runs_without_grad(device):
    d = Dummy(device, requires_grad=True)
    maps, _ = mc_render(d.sample_fn, d.render_fn, _cameras(device), 3, torch.Generator().manual_seed(2))
    assert maps.rgb_mean.grad_fn is None and not maps.rgb_std.requires_grad


def test_cuda_peak_memory_flat_in_k(device):
    if device.type != "cuda":
        pytest.skip("peak allocation is measured on CUDA")
    peaks = {}
    side = 256
    cams = Cameras(torch.eye(4, device=device).expand(C, 4, 4), torch.eye(3, device=device).expand(C, 3, 3),
                   side, side)
    for k in (2, 32):
        d = Dummy(device, h=side, w=side)
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats(device)
        base = torch.cuda.memory_allocated(device)
        maps, _ = mc_render(d.sample_fn, d.render_fn, cams, k, torch.Generator().manual_seed(0))
        torch.cuda.synchronize()
        peaks[k] = torch.cuda.max_memory_allocated(device) - base
        del maps, d
    assert peaks[32] <= peaks[2] * 1.1 + 1024


def test_running_moments_matches_torch():
    g = torch.Generator().manual_seed(5)
    xs = 1000.0 + torch.randn(50, 4, generator=g, dtype=torch.float64)  # large offset: Welford is stable
    m = RunningMoments()
    for x in xs:
        m.update(x)
    assert torch.allclose(m.mean, xs.mean(0), atol=1e-10)
    assert torch.allclose(m.std, xs.std(0), atol=1e-10)


class TestResolutionTerm:
    """``mc_render(shift_fn=...)``: the variance of the shifted renders is added, the mean is the samples'."""

    def test_shift_variance_is_added_and_the_mean_kept(self, device):
        d, shifts = Dummy(device), Dummy(device)
        plain = mc_render(Dummy(device).sample_fn, Dummy(device).render_fn, _cameras(device), 6,
                          torch.Generator().manual_seed(1))[0]
        maps = mc_render(d.sample_fn, d.render_fn, _cameras(device), 6, torch.Generator().manual_seed(1),
                         shift_fn=shifts.sample_fn)[0]
        # the samples are the same as without the term (the shifts draw from a generator of their own)
        torch.testing.assert_close(maps.rgb_mean, plain.rgb_mean)
        assert len(d.values) == 6 == len(shifts.values)
        s = torch.tensor(shifts.values, dtype=torch.float64)
        want_rgb = (plain.rgb_std.double().square() + s.var() * d.pattern.double().square()).sqrt()
        torch.testing.assert_close(maps.rgb_std.double(), want_rgb, rtol=1e-5, atol=1e-6)
        want_depth = (plain.depth_std.double().square() + s.var()).sqrt()
        torch.testing.assert_close(maps.depth_std.double(), want_depth, rtol=1e-5, atol=1e-6)

    def test_several_shift_renders_per_sample_pool_into_one_variance(self, device):
        d, shifts = Dummy(device), Dummy(device)
        plain = mc_render(Dummy(device).sample_fn, Dummy(device).render_fn, _cameras(device), 4,
                          torch.Generator().manual_seed(2))[0]
        maps = mc_render(d.sample_fn, d.render_fn, _cameras(device), 4, torch.Generator().manual_seed(2),
                         shift_fn=shifts.sample_fn, shift_renders=3)[0]
        assert len(d.values) == 4 and len(shifts.values) == 12  # K samples, 3 shift renders each
        torch.testing.assert_close(maps.rgb_mean, plain.rgb_mean)
        s = torch.tensor(shifts.values, dtype=torch.float64)
        want_rgb = (plain.rgb_std.double().square() + s.var() * d.pattern.double().square()).sqrt()
        torch.testing.assert_close(maps.rgb_std.double(), want_rgb, rtol=1e-5, atol=1e-6)
        with pytest.raises(ValueError, match="shift_renders"):
            mc_render(d.sample_fn, d.render_fn, _cameras(device), 4, torch.Generator().manual_seed(2),
                      shift_fn=shifts.sample_fn, shift_renders=0)

    def test_shifts_are_seeded_by_the_samples_seed(self, device):
        runs = []
        for _ in range(2):
            shifts = Dummy(device)
            mc_render(Dummy(device).sample_fn, Dummy(device).render_fn, _cameras(device), 3,
                      torch.Generator().manual_seed(5), shift_fn=shifts.sample_fn)
            runs.append(shifts.values)
        assert runs[0] == runs[1]
        other = Dummy(device)
        mc_render(Dummy(device).sample_fn, Dummy(device).render_fn, _cameras(device), 3,
                  torch.Generator().manual_seed(6), shift_fn=other.sample_fn)
        assert other.values != runs[0]

    def test_resolution_shift_moves_by_a_fraction_of_the_size(self):
        from uncertsplat.uncertainty.mc import resolution_shift

        n = 4000
        scales = torch.tensor([[0.1, 0.4, 1.6]]).repeat(n, 1)  # geometric mean 0.4
        sample = GaussianSample(means=torch.zeros(n, 3), quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
                                scales=scales, opacities=torch.ones(n), sh=torch.zeros(n, 1, 3))
        shifted = resolution_shift(sample, 0.3)(torch.Generator().manual_seed(0))
        assert abs(float(shifted.means.std()) - 0.3 * 0.4) < 0.004
        assert torch.equal(shifted.scales, sample.scales) and torch.equal(sample.means, torch.zeros(n, 3))
        same = resolution_shift(sample, 0.0)(torch.Generator().manual_seed(0))
        assert torch.equal(same.means, sample.means)


class TestDepthSpread:
    """``depth_spread``: the variance of the depths a ray blends, against the closed form with the real renderer."""

    W2, H2 = 24, 18

    def _cams(self, z0=0.0):
        cw = torch.eye(4)[None].clone()
        cw[0, 2, 3] = z0  # the camera looks down +z; z0 moves the scene away from it
        K = torch.tensor([[[20.0, 0, self.W2 / 2], [0, 20.0, self.H2 / 2], [0, 0, 1.0]]])
        return Cameras(cw, K, self.W2, self.H2, ("v.png",))

    @staticmethod
    def _two_layers(z1, z2, o1=0.5, o2=0.8):
        """Two equal, wide, flat Gaussians on the optical axis at depths z1 < z2 (the same footprint in the image
        when their sizes grow with depth)."""
        means = torch.tensor([[0.0, 0.0, z1], [0.0, 0.0, z2]])
        scales = torch.tensor([[0.6 * z1, 0.6 * z1, 1e-3], [0.6 * z2, 0.6 * z2, 1e-3]])
        return GaussianSample(means=means, quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(2, 1), scales=scales,
                              opacities=torch.tensor([o1, o2]), sh=torch.zeros(2, 1, 3), sh_degree=0)

    def _render(self):
        import functools

        from uncertsplat.render import render

        return functools.partial(render, background=torch.tensor([0.3, 0.6, 0.9]))

    def _closed_form(self, sample, cams, z_shift=0.0):
        """w1 = a1, w2 = (1 - a1) a2 from each Gaussian rendered alone; the variance of {z1 w.p. w1, z2 w.p. w2}."""
        render = self._render()
        a = [render(GaussianSample(means=sample.means[[i]], quats=sample.quats[[i]], scales=sample.scales[[i]],
                                   opacities=sample.opacities[[i]], sh=sample.sh[[i]], sh_degree=0), cams).alpha[0]
             for i in range(2)]
        w1, w2 = a[0], (1 - a[0]) * a[1]
        z1, z2 = (sample.means[:, 2] + z_shift).tolist()
        return w1 * w2 * (z1 - z2) ** 2 / (w1 + w2).square(), w1, w2

    def test_two_layers_give_the_mixture_variance_and_one_layer_none(self):
        from uncertsplat.uncertainty.mc import depth_spread

        sample, cams = self._two_layers(2.0, 3.0), self._cams()
        got = depth_spread(sample, cams, self._render())[0]
        want, w1, w2 = self._closed_form(sample, cams)
        both = (w1 > 0.05) & (w2 > 0.05)
        assert int(both.sum()) > 20
        torch.testing.assert_close(got[both], want[both], rtol=2e-3, atol=1e-5)
        one = GaussianSample(means=sample.means[:1], quats=sample.quats[:1], scales=sample.scales[:1],
                             opacities=sample.opacities[:1], sh=sample.sh[:1], sh_degree=0)
        assert float(depth_spread(one, cams, self._render()).abs().max()) < 1e-5  # one depth per ray: nothing
        empty = replace(sample, means=sample.means * torch.tensor([1.0, 1.0, -1.0]))  # behind the camera
        assert float(depth_spread(empty, cams, self._render()).abs().max()) == 0.0

    def test_a_scene_far_from_the_camera_keeps_its_digits(self):
        """The same two layers 1 apart, 2000 units from the camera: z^2 ~ 4e6 would leave float32 no digit for a
        variance of ~0.2 without the shift to the nearest Gaussian."""
        from uncertsplat.uncertainty.mc import depth_spread

        near_sample = self._two_layers(2.0, 3.0)
        far = 2000.0
        sample = replace(near_sample, means=near_sample.means + torch.tensor([0.0, 0.0, far]),
                         scales=near_sample.scales * (near_sample.means[:, 2:3] + far) / near_sample.means[:, 2:3])
        got = depth_spread(sample, self._cams(), self._render())[0]
        want, w1, w2 = self._closed_form(sample, self._cams())
        both = (w1 > 0.05) & (w2 > 0.05)
        assert int(both.sum()) > 20
        torch.testing.assert_close(got[both], want[both], rtol=1e-2, atol=1e-4)

    def test_mc_render_adds_it_to_the_depth_variance_only(self, device):
        d = Dummy(device)
        plain = mc_render(Dummy(device).sample_fn, Dummy(device).render_fn, _cameras(device), 4,
                          torch.Generator().manual_seed(2))[0]
        extra = torch.full((C, H, W, 1), 0.09, device=device)
        maps = mc_render(d.sample_fn, d.render_fn, _cameras(device), 4, torch.Generator().manual_seed(2),
                         extra_depth_var=extra)[0]
        torch.testing.assert_close(maps.rgb_std, plain.rgb_std)
        torch.testing.assert_close(maps.depth_std.square(), plain.depth_std.square() + 0.09, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("n", [2, 17, 1 << 24, 17_000_000, 22_118_400, 24_000_000, 96_000_000])
def test_spread_indices_stay_inside_and_reach_both_ends(n):
    """The coverage's subsample of more than 2^24 alphas indexed with a float32 linspace, whose last index rounded up
    to the count itself past 2^24 values: 8 training views of 1920x1440 (22,118,400 pixels) raised an IndexError in
    evaluate, prune, the viewer and select-views."""
    from uncertsplat.uncertainty.mc import spread_indices

    m = min(n, 1 << 24)
    idx = spread_indices(n, m)
    assert idx.dtype == torch.int64 and idx.shape == (m,)
    assert int(idx[0]) == 0 and int(idx[-1]) == n - 1 and bool((idx[1:] > idx[:-1]).all())
    assert torch.linspace(0, 24_000_000 - 1, 1 << 24).long()[-1] == 24_000_000  # (what it was: out of range)


def test_training_coverage_takes_more_than_two_to_the_24_pixels(monkeypatch):
    """Eight views whose alphas together exceed torch.quantile's 2^24 values: the coverage is their quantile."""
    from types import SimpleNamespace

    from uncertsplat.uncertainty import mc

    h, w = 1500, 2000  # 8 x 3 Mpx = 24,000,000 alphas
    gen = torch.Generator().manual_seed(0)
    alphas = torch.rand(8, h, w, 1, generator=gen)

    def render(sample, cams):
        i = int(cams.image_names[0].split("_")[1])
        return SimpleNamespace(alpha=alphas[i:i + 1])  # (all the coverage reads)

    cams = Cameras(torch.eye(4).repeat(8, 1, 1), torch.eye(3).repeat(8, 1, 1), w, h,
                   tuple(f"v_{i}" for i in range(8)))
    got = mc.training_coverage(None, cams, render, quantile=0.05)
    assert abs(got - 0.05) < 1e-3
