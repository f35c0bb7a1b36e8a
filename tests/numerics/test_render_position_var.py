"""``GaussianSample.position_var``: the render averaged over an isotropic position noise.

The renderer draws each Gaussian with covariance Sigma + var I and lowers its opacity per view by the 2D
peak ratio sqrt(det Sigma2d / det Sigma2d'), both with the 0.3 px dilation. Checked against the float64
oracle, for the property it exists for (a blurred footprint keeps its mass), and at extremes.
"""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from tests.reference.naive_render import look_at_cameras, naive_render, project_one, random_scene
from uncertsplat.render import render
from uncertsplat.types import Cameras, GaussianSample


def _scene(n: int, device, seed: int = 0) -> GaussianSample:
    return random_scene(n, torch.Generator().manual_seed(seed), sh_degree=1, extent=0.8,
                        opacity_range=(0.05, 0.6)).to(device=device)


def _var(n: int, device, seed: int = 1, std: float = 0.06) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (std * torch.rand(n, generator=g)).square().to(device)  # [N] up to std^2


def _oracle(sample: GaussianSample, cams: Cameras, eps2d: float = 0.3) -> dict:
    """float64 reference: blurred scales, opacity times the per-view 2D peak ratio, one camera at a time."""
    var = sample.position_var.double()
    blurred = replace(sample, scales=torch.sqrt(sample.scales.double() ** 2 + var[:, None]), position_var=None)
    outs = []
    for c in range(len(cams)):
        cam = cams[[c]]
        args = (cam.cam_from_world[0], cam.K[0], cams.width, cams.height, 0.01, 1e10, eps2d)
        keep, _, conic_sharp, *_ = project_one(replace(sample, position_var=None), *args)
        _, _, conic_blur, *_ = project_one(blurred, *args)
        peak = torch.ones(len(sample), dtype=torch.float64, device=var.device)
        peak[keep] = torch.sqrt(torch.linalg.det(conic_blur) / torch.linalg.det(conic_sharp))
        outs.append(naive_render(replace(blurred, opacities=sample.opacities.double() * peak), cam))
    return {k: torch.cat([o[k] for o in outs]) for k in ("rgb", "alpha")}


def test_zero_variance_is_a_plain_render(device):
    s = _scene(30, device)
    cams = look_at_cameras(2, 40, 32, 40.0, radius=3.0).to(device)
    a = render(s, cams)
    b = render(replace(s, position_var=torch.zeros(30, device=device)), cams)
    torch.testing.assert_close(b.rgb, a.rgb, rtol=0, atol=1e-6)
    torch.testing.assert_close(b.alpha, a.alpha, rtol=0, atol=1e-6)


def test_matches_the_float64_oracle(device):
    s = replace(_scene(25, device, seed=2), position_var=_var(25, device))
    cams = look_at_cameras(2, 40, 32, 40.0, radius=3.0).to(device)
    out = render(s, cams)
    ref = _oracle(s, cams)
    assert float((out.alpha.double() - render(replace(s, position_var=None), cams).alpha.double()).abs().max()) > 1e-3
    torch.testing.assert_close(out.rgb.double(), ref["rgb"].to(device), rtol=0, atol=2e-4)
    torch.testing.assert_close(out.alpha.double(), ref["alpha"].to(device), rtol=0, atol=2e-4)


def test_a_blurred_footprint_keeps_its_mass_and_lowers_its_peak(device):
    # one Gaussian facing the camera, far inside a 64x64 image: its summed alpha is its mass
    K = torch.tensor([[[64.0, 0, 32.5], [0, 64.0, 32.5], [0, 0, 1]]])  # the mean on a pixel centre
    cams = Cameras(torch.eye(4)[None], K, 64, 64).to(device=device)
    one = GaussianSample(means=torch.tensor([[0.0, 0.0, 3.0]]), quats=torch.tensor([[1.0, 0, 0, 0]]),
                         scales=torch.tensor([[0.1, 0.06, 0.01]]), opacities=torch.tensor([0.5]),
                         sh=torch.zeros(1, 1, 3), sh_degree=0).to(device=device)
    sharp = render(one, cams).alpha
    blur = render(replace(one, position_var=torch.tensor([0.08**2], device=device)), cams).alpha
    # 2D variances (px^2): sharp (64*0.1/3)^2 + 0.3, (64*0.06/3)^2 + 0.3; blurred adds (64*0.08/3)^2 to both
    f = (64 / 3) ** 2
    sx, sy, b = f * 0.1**2 + 0.3, f * 0.06**2 + 0.3, f * 0.08**2
    expected_peak = ((sx * sy) / ((sx + b) * (sy + b))) ** 0.5
    assert float(blur.max() / sharp.max()) == pytest.approx(expected_peak, rel=0.03)
    # the mass is kept up to what the 1/255 cut-off trims from the (lower, wider) tails
    assert float(blur.sum() / sharp.sum()) == pytest.approx(1.0, abs=0.03)


@pytest.mark.parametrize("var", [0.0, 1e-30, 1e-6, 1e6])
def test_extreme_variances_give_finite_images_and_gradients(device, var):
    s = _scene(20, device, seed=3)
    leaves = {k: getattr(s, k).detach().clone().requires_grad_() for k in ("means", "scales", "opacities")}
    pv = torch.full((20,), var, device=device, requires_grad=True)
    out = render(replace(s, **leaves, position_var=pv), look_at_cameras(2, 24, 20, 20.0, radius=3.0).to(device))
    assert torch.isfinite(out.rgb).all() and torch.isfinite(out.alpha).all()
    (out.rgb.sum() + out.alpha.sum()).backward()
    for name, t in {**leaves, "position_var": pv}.items():
        assert t.grad is None or torch.isfinite(t.grad).all(), name
    if var == 1e6:  # blurred over the whole scene: every peak falls below the 1/255 cut-off
        assert float(out.alpha.detach().max()) < 1e-6


def test_the_peak_factor_equals_a_second_projections_at_every_view_angle(device):
    """``_blur_log_peak`` gets the sharp covariance as Sigma2d' - v J J^T instead of projecting twice: the same
    factor as the two projections' determinants, for Gaussians inside, at the edge of and far outside the view
    (where the Jacobian's view angle is clamped), behind the camera, and for blurs from sub-pixel to huge."""
    from uncertsplat.render.project import project_gaussians
    from uncertsplat.render.render import blur_log_peak

    g = torch.Generator().manual_seed(7)
    n = 200
    s = _scene(n, device, seed=7)
    means = (torch.rand(n, 3, generator=g) - 0.5) * torch.tensor([8.0, 8.0, 4.0])  # many outside the frustum
    var = torch.exp(torch.empty(n).uniform_(-14.0, 2.0, generator=g))  # std from 1e-3 to 2.7 scene units
    s = replace(s, means=means.to(device), position_var=var.to(device))
    cams = look_at_cameras(3, 40, 32, 40.0, radius=3.0).to(device)
    cw, K = cams.cam_from_world, cams.K
    blurred = project_gaussians(s.means, s.quats, torch.sqrt(s.scales**2 + s.position_var[:, None]), s.opacities,
                                cw, K, 40, 32, 0.01, 1e10, 0.3)
    sharp = project_gaussians(s.means, s.quats, s.scales, s.opacities, cw, K, 40, 32, 0.01, 1e10, 0.3)

    def log_det(conics):
        a, b, c = conics.double().unbind(-1)
        return torch.log((a * c - b * b).clamp_min(1e-300))

    expected = (0.5 * (log_det(blurred.conics) - log_det(sharp.conics))).clamp_max(0.0)
    got = blur_log_peak(s, blurred.conics, cw, K, 40, 32, 0.01, 1e10, 0.3).double()
    front = blurred.depths > 0.01
    assert bool(front.any()) and bool((~front).any())
    # where the peak factor still shows (above 1e-4), the two agree to the float32 rounding of the conics (the
    # two-projection form has its own: a c - b^2 of an elongated conic cancels)
    shows = front & (expected > -9.0)
    assert int(shows.sum()) > 100
    torch.testing.assert_close(got[shows], expected[shows], rtol=1e-3, atol=2e-4)
    # far below that, both say "invisible"; behind the camera the factor is 0 (the Gaussian is culled)
    assert bool((got[front & ~shows] < -8.0).all())
    assert float(got[~front].abs().max()) == 0.0


def test_the_native_peak_factor_matches_the_reference_and_its_gradients():
    """The native kernel of the peak factor against ``_blur_log_peak`` (float64 tensor ops): values and the gradients
    to the means, the blurred conics and the variances, with Gaussians behind the camera, at clamped view angles,
    without blur (v = 0), with a negative variance, a degenerate conic and blurs whose sharp determinant clamps."""
    from uncertsplat import native
    from uncertsplat.render.project import project_gaussians
    from uncertsplat.render.render import _blur_log_peak, _NativeBlurPeak

    if native.library() is None:
        pytest.skip(f"native kernels unavailable: {native.unavailable_reason()}")
    g = torch.Generator().manual_seed(11)
    n = 300
    s = _scene(n, "cpu", seed=11)
    means = (torch.rand(n, 3, generator=g) - 0.5) * torch.tensor([8.0, 8.0, 4.0])
    var = torch.exp(torch.empty(n).uniform_(-14.0, 2.0, generator=g))
    var[:20] = 0.0
    var[20:25] = -1e-3  # clamped to 0, as the reference does
    cams = look_at_cameras(3, 40, 32, 40.0, radius=3.0)
    cw, K = cams.cam_from_world, cams.K
    conics = project_gaussians(means, s.quats, torch.sqrt(s.scales**2 + var.clamp_min(0)[:, None]), s.opacities,
                               cw, K, 40, 32, 0.01, 1e10, 0.3).conics.detach().clone()
    conics[:, 25] = torch.tensor([1.0, 1.0, 1.0])  # a c - b^2 = 0: no factor
    conics[:, 26] = torch.tensor([1.0, 2.0, 1.0])  # a c - b^2 < 0 (not an ellipse): no factor either
    inputs = {"means": means, "conics": conics, "var": var}
    outs, grads = {}, {}
    weight = torch.rand(3, n, generator=g) - 0.5
    weight[:, ::3] = 0.0  # no gradient arrives there (the kernel skips them): as most unseen Gaussians in training
    for name in ("reference", "native"):
        leaves = {k: v.detach().clone().requires_grad_() for k, v in inputs.items()}
        if name == "native":
            out = _NativeBlurPeak.apply(leaves["means"], leaves["conics"], leaves["var"], cw, K, 40, 32, 0.01, 1e10,
                                        0.3)
        else:
            out = _blur_log_peak(replace(s, means=leaves["means"], position_var=leaves["var"]), leaves["conics"], cw, K,
                                 40, 32, 0.01, 1e10, 0.3)
        (out * weight).sum().backward()
        outs[name], grads[name] = out.detach(), {k: v.grad for k, v in leaves.items()}
    behind = project_gaussians(means, s.quats, s.scales, s.opacities, cw, K, 40, 32, 0.01, 1e10, 0.3).depths <= 0.01
    assert bool(behind.any()) and bool((outs["reference"] < -1.0).any()) and bool((outs["reference"] == 0).any())
    assert float(outs["native"][:, 25:27].abs().max()) == 0.0  # the degenerate conics
    torch.testing.assert_close(outs["native"], outs["reference"], rtol=1e-5, atol=1e-6)
    for k in inputs:
        ref, got = grads["reference"][k], grads["native"][k]
        if k == "var":  # at v = 0 the factor sits on its clamp at 0, where rounding decides which side passes
            assert float(ref[var < 0].abs().max()) == 0.0 == float(got[var < 0].abs().max())  # clamped: none
            ref, got = ref[var > 0], got[var > 0]
        assert float(ref.abs().max()) > 0, k  # the comparison is not vacuous
        torch.testing.assert_close(got, ref, rtol=1e-4, atol=1e-6 * float(ref.abs().max()), msg=k)
