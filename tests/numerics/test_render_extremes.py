"""Extreme inputs give finite images and finite gradients (one test per case)."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from tests.reference.naive_render import look_at_cameras, naive_render, random_scene
from uncertsplat.render import render
from uncertsplat.types import Cameras, GaussianSample

W, H = 24, 20
PARAMS = ("means", "quats", "scales", "opacities", "sh")


def _cam(device):
    """Camera at the origin looking down +z (world = camera frame)."""
    K = torch.tensor([[[20.0, 0, W / 2], [0, 20.0, H / 2], [0, 0, 1]]])
    return Cameras(torch.eye(4)[None], K, W, H).to(device=device)


def _base(n, device, seed=0, z=3.0):
    s = random_scene(n, torch.Generator().manual_seed(seed), sh_degree=3, extent=0.5)
    means = s.means.clone()
    means[:, 2] += z
    return replace(s, means=means).to(device=device)


def _run(sample: GaussianSample, device, cams=None, bg=True):
    """Render, backprop an L1 loss to a random target, assert everything is finite; return output, grads."""
    cams = _cam(device) if cams is None else cams
    leaves = {k: getattr(sample, k).detach().clone().requires_grad_() for k in PARAMS}
    s = replace(sample, **leaves)
    background = torch.tensor([0.3, 0.6, 0.9], device=device) if bg else None
    out = render(s, cams, background=background)
    for k in ("rgb", "alpha", "depth", "depth_expected", "means2d", "radii", "depths"):
        v = getattr(out, k)
        assert torch.isfinite(v).all(), f"non-finite {k}"
    target = torch.rand(out.rgb.shape, generator=torch.Generator().manual_seed(1)).to(device)
    loss = (out.rgb - target).abs().mean() + out.depth.mean() + out.alpha.mean()
    if loss.requires_grad:
        loss.backward()
    grads = {k: v.grad for k, v in leaves.items()}
    for k, g in grads.items():
        if g is not None:
            assert torch.isfinite(g).all(), f"non-finite gradient for {k}"
    assert out.alpha.min() >= 0 and out.alpha.max() <= 1 + 1e-6
    return out, grads


def _with(sample, **kw):
    return replace(sample, **{k: v.to(sample.means) for k, v in kw.items()})


def test_tiny_scales(device):
    s = _base(20, device)
    out, g = _run(_with(s, scales=torch.full((20, 3), 1e-7)), device)
    # Sub-pixel Gaussians are still drawn through the 0.3 px dilation.
    assert out.alpha.max() > 0 and g["means"].abs().sum() > 0


def test_huge_scales(device):
    s = _base(20, device)
    out, g = _run(_with(s, scales=torch.full((20, 3), 1e3)), device)
    assert out.alpha.min() > 0.5  # every pixel is covered


def test_opacity_almost_zero(device):
    s = _base(20, device)
    out, _ = _run(_with(s, opacities=torch.full((20,), 1e-6)), device)
    assert out.alpha.max() == 0 and (out.radii == 0).all()  # below 1/255 everywhere: culled


def test_opacity_almost_one(device):
    s = _base(20, device)
    out, g = _run(_with(s, opacities=torch.full((20,), 1 - 1e-6)), device)
    assert out.alpha.max() > 0.9 and g["opacities"] is not None


def test_behind_the_camera(device):
    s = _base(20, device, z=-3.0)
    out, _ = _run(s, device)
    assert out.alpha.max() == 0 and (out.radii == 0).all()
    assert torch.allclose(out.rgb, torch.tensor([0.3, 0.6, 0.9], device=device).expand_as(out.rgb))


def test_exactly_on_the_near_plane(device):
    s = _base(5, device)
    means = s.means.clone()
    means[:, 2] = 0.01  # == near: culled (strictly in front is required)
    out, _ = _run(_with(s, means=means), device)
    assert (out.radii == 0).all() and out.alpha.max() == 0


def test_just_past_the_near_plane(device):
    s = _base(5, device)
    means = s.means.clone()
    means[:, :2] *= 0.001
    means[:, 2] = 0.0100001
    out, _ = _run(_with(s, means=means), device)
    assert (out.radii > 0).any() and out.alpha.max() > 0


def test_far_away_subpixel(device):
    s = _base(20, device, z=1e6)
    out, g = _run(s, device)
    assert torch.isfinite(g["means"]).all()
    assert (out.radii[out.radii > 0] < 3).all()  # the footprint is the dilation only


def test_flat_covariance(device):
    s = _base(20, device)
    sc = torch.full((20, 3), 0.2)
    sc[:, 2] = 1e-7
    out, g = _run(_with(s, scales=sc), device)
    # seen at an angle, the discs still cover pixels (not culled as degenerate)
    assert (out.radii > 0).sum() > 10 and out.alpha.max() > 0.1 and g["scales"].abs().sum() > 0


def test_needle_covariance(device):
    s = _base(20, device)
    sc = torch.full((20, 3), 1e-7)
    sc[:, 0] = 10.0
    out, g = _run(_with(s, scales=sc), device)
    assert (out.radii > 0).sum() > 10 and out.alpha.max() > 0.1 and g["means"].abs().sum() > 0


def test_unnormalised_quaternions(device):
    s = _base(20, device)
    out_a, _ = _run(s, device)
    out_b, _ = _run(_with(s, quats=s.quats * 1e3), device)
    assert (out_a.rgb - out_b.rgb).abs().max() < 1e-5  # only the direction of q matters


def test_near_zero_quaternions(device):
    s = _base(20, device)
    q = torch.zeros(20, 4)
    q[:10] = 1e-30
    out, g = _run(_with(s, quats=q), device)
    # a zero quaternion has no direction: such a Gaussian is drawn (as some rotation), never NaN or dropped
    assert (out.radii[0, :10] > 0).any() and out.alpha.max() > 0


def test_entirely_off_screen(device):
    s = _base(20, device)
    means = s.means.clone()
    means[:, 0] += 50.0
    out, _ = _run(_with(s, means=means), device)
    assert out.alpha.max() == 0 and (out.radii == 0).all()


def test_empty_scene(device):
    s = GaussianSample(
        torch.zeros(0, 3), torch.zeros(0, 4), torch.zeros(0, 3), torch.zeros(0), torch.zeros(0, 16, 3), 3
    ).to(device=device)
    out, _ = _run(s, device)
    assert out.rgb.shape == (1, H, W, 3) and out.means2d.shape == (1, 0, 2) and out.radii.shape == (1, 0)
    assert torch.allclose(out.rgb, torch.tensor([0.3, 0.6, 0.9], device=device).expand_as(out.rgb))


def test_single_gaussian_covering_the_image(device):
    s = GaussianSample(
        torch.tensor([[0.0, 0.0, 2.0]]),
        torch.tensor([[1.0, 0.0, 0.0, 0.0]]),
        torch.tensor([[50.0, 50.0, 1.0]]),
        torch.tensor([0.7]),
        torch.zeros(1, 1, 3),
        0,
    ).to(device=device)
    out, g = _run(s, device)
    assert torch.allclose(out.alpha, torch.full_like(out.alpha, 0.7), atol=1e-3)
    assert torch.allclose(out.rgb, 0.7 * 0.5 + 0.3 * torch.tensor([0.3, 0.6, 0.9], device=device), atol=1e-3)
    ref = naive_render(s, _cam(device), background=torch.tensor([0.3, 0.6, 0.9], device=device))
    assert (out.rgb.double() - ref["rgb"]).abs().max() < 1e-5
    assert g["opacities"].abs().sum() > 0


def test_many_cameras_batch_equals_single_renders(device):
    s = random_scene(100, torch.Generator().manual_seed(2), sh_degree=3).to(device=device)
    cams = look_at_cameras(3, 20, 16, focal=18.0).to(device=device)
    out = render(s, cams)
    for c in range(3):
        one = render(s, cams[c])
        # float32 roundoff only: batched and single matmuls may take different SIMD paths on different
        # CPUs (1.6e-6 seen on one machine, 0 on another); a real batching bug is off by far more.
        assert (one.rgb[0] - out.rgb[c]).abs().max() < 1e-5


def test_gaussian_behind_stopped_rays_gets_exactly_zero_gradient(device):
    """Three near-opaque wide Gaussians stop every ray (T < 1e-4); a fourth behind them has no influence,
    so its gradients must be exactly 0 (not rounding residue of the suffix sums)."""
    n = 4
    means = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 2.5], [0.0, 0.0, 3.0], [0.1, -0.1, 5.0]])
    quats = torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1)
    scales = torch.tensor([[100.0, 100.0, 0.01]] * 3 + [[0.5, 0.5, 0.5]])
    opac = torch.tensor([1 - 1e-6] * 3 + [0.8])
    sh = torch.randn(n, 16, 3, generator=torch.Generator().manual_seed(0)) * 0.3
    s = GaussianSample(means, quats, scales, opac, sh, 3).to(device=device)
    out, g = _run(s, device)
    assert out.alpha.min() >= 0.99 - 1e-6  # every ray ends at the second (T = 1e-4) or third Gaussian
    for k in PARAMS:
        assert g[k] is not None and torch.equal(g[k][3], torch.zeros_like(g[k][3])), k
    # The front Gaussian does receive colour gradients (the check above is not vacuous); its alpha is
    # at the 0.99 cap everywhere, so its geometry gradients are 0 by the cap's semantics.
    assert g["sh"][0].abs().sum() > 0


def _stack(device, dtype, log_opacity, n, centre=2.0):
    """``n`` wide Gaussians stacked front to back over one 4 x 4 tile, all at pixel ``centre``, each of log opacity
    ``log_opacity``: composite's inputs (gparams [n,6], one feature of 1s: the output is the ray's alpha) and bins."""
    from uncertsplat.render.rasterize import bin_gaussians

    means2d = torch.full((1, n, 2), centre, dtype=dtype, device=device)
    conics = torch.tensor([[[0.01, 0.0, 0.01]] * n], dtype=dtype, device=device)
    opac = torch.full((n,), math.exp(log_opacity), dtype=dtype, device=device)
    bins = bin_gaussians(means2d, torch.full_like(means2d, 10.0), torch.ones(1, n, dtype=torch.bool, device=device),
                         torch.arange(1.0, n + 1, dtype=dtype, device=device)[None], 4, 4, 4, conics, opac)
    gparams = torch.cat([means2d[0], conics[0], torch.full((n, 1), log_opacity, dtype=dtype, device=device)], -1)
    return gparams, torch.ones(n, 1, dtype=dtype, device=device), bins


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_a_ray_whose_transmittance_reaches_t_min_exactly_keeps_that_gaussian(device, dtype, monkeypatch):
    """The ray stops before a Gaussian that would take T *under* T_MIN (3DGS's ``test_T < 0.0001f``, the oracle's
    ``t_incl >= 1e-4``): one that leaves T equal to it is added. With the cap at 0.5 and T_MIN 0.25 (exact in
    binary) three opaque Gaussians leave T = 0.5, 0.25 (kept), 0.125 (the ray stops before it): alpha 0.75 on every
    pixel, from both compositors (the PyTorch one zeroed T <= T_MIN and stopped at 0.5; a native ``<=`` too)."""
    from uncertsplat.render import rasterize

    monkeypatch.setattr(rasterize, "ALPHA_MAX", 0.5)
    monkeypatch.setattr(rasterize, "T_MIN", 0.25)
    gparams, feat, bins = _stack(device, dtype, 0.0, 3)
    out = rasterize.composite(gparams, feat, bins)
    assert torch.equal(out, torch.full_like(out, 0.75))


def test_an_alpha_of_exactly_alpha_min_is_drawn(device, monkeypatch):
    """Only alpha < ALPHA_MIN is skipped (3DGS's ``alpha < 1/255``, the oracle's ``alpha >= 1/255``): with ALPHA_MIN
    0.5 a Gaussian of opacity 0.5 is drawn exactly at its mean's pixel (alpha 0.5 there, in float64 where
    exp(log 0.5) is 0.5 on both paths) and nowhere else (the PyTorch compositor zeroed alpha <= ALPHA_MIN)."""
    from uncertsplat.render import rasterize

    monkeypatch.setattr(rasterize, "ALPHA_MIN", 0.5)
    gparams, feat, bins = _stack(device, torch.float64, math.log(0.5), 1, centre=1.5)
    out = rasterize.composite(gparams, feat, bins)[0, :, 0]
    expected = torch.zeros_like(out)
    expected[5] = 0.5  # pixel (1, 1) of the tile: centre (1.5, 1.5)
    assert torch.equal(out, expected)
