"""float64 torch.autograd.gradcheck of the rasterizer on tiny inputs."""

from __future__ import annotations

import pytest
import torch

from tests.reference.naive_render import look_at_cameras, random_scene
from uncertsplat.render import render
from uncertsplat.render.project import project_gaussians
from uncertsplat.render.rasterize import bin_gaussians, composite
from uncertsplat.types import GaussianSample


def _nondet_tol(device: torch.device) -> float:
    """On CUDA the per-Gaussian sums of the backward pass are atomic adds whose order varies between runs,
    so two backward passes differ in the last bits (seen on an H100, 2026-11-26); on the CPU they are exact."""
    return 1e-12 if device.type == "cuda" else 0.0


@pytest.mark.parametrize("n_cams,w,h,n,fast", [(2, 12, 10, 6, True), (1, 7, 6, 4, False)])
def test_gradcheck_render_all_parameters(device, n_cams, w, h, n, fast):
    """Fast mode (random projections of the Jacobian) on a larger case, the full Jacobian on a tiny one."""
    s = random_scene(
        n,
        torch.Generator().manual_seed(4),
        sh_degree=2,
        scale_range=(0.2, 0.5),
        opacity_range=(0.3, 0.8),
        dtype=torch.float64,
    )
    s = s.to(device=device)
    cams = look_at_cameras(n_cams, w, h, focal=0.75 * w, dtype=torch.float64).to(device=device)
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64, device=device)

    def fn(means, quats, scales, opacities, sh):
        out = render(GaussianSample(means, quats, scales, opacities, sh, 2), cams, background=bg, tile_size=4)
        return out.rgb, out.alpha, out.depth

    inputs = tuple(
        t.detach().clone().requires_grad_() for t in (s.means, s.quats, s.scales, s.opacities, s.sh)
    )
    out = fn(*inputs)
    assert (out[1] > 0.1).any(), "the scene must be visible for the check to mean anything"
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=fast,
                                     nondet_tol=_nondet_tol(device))


def test_gradcheck_compositor_alone(device):
    """The custom autograd function, with per-pair coefficients and features as direct inputs."""
    s = random_scene(
        8, torch.Generator().manual_seed(9), sh_degree=0, scale_range=(0.2, 0.5), dtype=torch.float64
    )
    s = s.to(device=device)
    cams = look_at_cameras(1, 9, 7, focal=8.0, dtype=torch.float64).to(device=device)
    p = project_gaussians(s.means, s.quats, s.scales, s.opacities, cams.cam_from_world, cams.K, 9, 7)
    bins = bin_gaussians(p.means2d, p.extents, p.valid, p.depths, 9, 7, 4, p.conics, s.opacities)
    gparams = torch.cat([p.means2d[0], p.conics[0], s.opacities.log()[:, None]], -1).detach().requires_grad_()
    feat = torch.rand(len(s), 5, dtype=torch.float64, device=device, generator=None).requires_grad_()
    assert bins.pair_gauss.numel() > len(s)
    assert torch.autograd.gradcheck(
        lambda c, f: composite(c, f, bins, block_elements=32), (gparams, feat), eps=1e-6, atol=1e-5,
        nondet_tol=_nondet_tol(device),
    )
