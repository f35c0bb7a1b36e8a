"""Parity of the tiled rasterizer (float32) with the dense float64 oracle, forward and backward.

Tolerances: forward max abs difference <= 1e-4 for rgb and alpha, <= 1e-4 x max depth for depths;
gradients: relative L2 error ||g - g_ref|| / ||g_ref|| <= 1e-4 per parameter and max abs error
<= 1e-3 x max |g_ref| (float32 accumulation over a few hundred Gaussians; measured ~1e-6 and ~1e-5).
"""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from tests.reference.naive_render import (
    composite_loop,
    look_at_cameras,
    naive_render,
    project_one,
    random_scene,
)
from uncertsplat.render import render

PARAMS = ("means", "quats", "scales", "opacities", "sh")


def _to(sample, cams, device):
    return sample.to(device=device), cams.to(device=device)


def _loss_weights(C, H, W, device, seed=5):
    g = torch.Generator().manual_seed(seed)
    return [torch.randn(C, H, W, k, generator=g, dtype=torch.float64).to(device) for k in (3, 1, 1, 1)]


def _grads(fn, sample, dtype, weights):
    leaves = {k: getattr(sample, k).detach().to(dtype).requires_grad_() for k in PARAMS}
    out = fn(replace(sample, **leaves))
    get = out.__getitem__ if isinstance(out, dict) else out.__getattribute__
    keys = ("rgb", "alpha", "depth", "depth_expected")
    loss = sum((get(k).double() * w).sum() for k, w in zip(keys, weights, strict=True))
    loss.backward()
    return out, {k: v.grad.double() for k, v in leaves.items()}


def _check_forward(out, ref):
    for k in ("rgb", "alpha"):
        err = (getattr(out, k).double() - ref[k]).abs().max().item()
        assert err <= 1e-4, f"{k}: max abs err {err}"
    dmax = ref["depth"].abs().max().item()
    for k in ("depth", "depth_expected"):
        err = (getattr(out, k).double() - ref[k]).abs().max().item()
        assert err <= 1e-4 * max(dmax, 1.0), f"{k}: max abs err {err}"


def _check_grads(ga, gb):
    for k in PARAMS:
        ref = gb[k]
        assert torch.isfinite(ga[k]).all(), k
        rel = ((ga[k] - ref).norm() / ref.norm().clamp_min(1e-30)).item()
        assert rel <= 1e-4, f"grad {k}: relative L2 error {rel}"
        mx = (ga[k] - ref).abs().max().item()
        assert mx <= 1e-3 * ref.abs().max().item(), f"grad {k}: max abs err {mx}"


@pytest.mark.parametrize(
    "seed,n,deg,tile,n_cams,w,h",
    [
        (0, 300, 3, 8, 2, 48, 40),
        (1, 150, 0, 16, 1, 37, 29),
        (2, 200, 1, 4, 1, 30, 34),
        (3, 250, 2, 5, 3, 26, 21),
    ],
)
def test_forward_and_gradients_match_oracle(device, seed, n, deg, tile, n_cams, w, h):
    sample = random_scene(n, torch.Generator().manual_seed(seed), sh_degree=deg)
    cams = look_at_cameras(n_cams, w, h, focal=0.9 * w)
    sample, cams = _to(sample, cams, device)
    bg = torch.tensor([0.2, 0.5, 0.9], device=device)
    weights = _loss_weights(n_cams, h, w, device, seed)
    out, ga = _grads(lambda s: render(s, cams, background=bg, tile_size=tile), sample, torch.float32, weights)
    ref, gb = _grads(lambda s: naive_render(s, cams, background=bg), sample, torch.float64, weights)
    assert out.rgb.shape == (n_cams, h, w, 3) and out.alpha.shape == (n_cams, h, w, 1)
    assert (ref["alpha"] > 0.5).float().mean().item() > 0.15, "scene should cover a good part of the image"
    _check_forward(out, ref)
    _check_grads(ga, gb)


def test_saturated_scene_with_early_stop_matches_oracle(device):
    """Many nearly opaque layers: most rays stop on the T < 1e-4 rule and the alpha cap is hit."""
    sample = random_scene(
        400, torch.Generator().manual_seed(7), sh_degree=1, scale_range=(0.15, 0.4), opacity_range=(0.9, 1.0)
    )
    cams = look_at_cameras(1, 32, 32, focal=60.0)
    sample, cams = _to(sample, cams, device)
    weights = _loss_weights(1, 32, 32, device)
    out, ga = _grads(lambda s: render(s, cams), sample, torch.float32, weights)
    ref, gb = _grads(lambda s: naive_render(s, cams), sample, torch.float64, weights)
    assert (1 - ref["alpha"] < 2e-4).float().mean().item() > 0.5, "most rays should have stopped"
    _check_forward(out, ref)
    _check_grads(ga, gb)


def test_small_blocks_and_tile_sizes_give_the_same_image(device):
    sample = random_scene(200, torch.Generator().manual_seed(3), sh_degree=2)
    cams = look_at_cameras(2, 33, 27, focal=30.0).to(device=device)
    sample = sample.to(device=device)
    base = render(sample, cams, tile_size=8)
    for kw in ({"tile_size": 16}, {"tile_size": 3}, {"tile_size": 8, "block_elements": 64}):
        other = render(sample, cams, **kw)
        for k in ("rgb", "alpha", "depth"):
            assert (getattr(other, k) - getattr(base, k)).abs().max() <= 2e-5, (kw, k)


def test_oracle_cumprod_form_matches_the_literal_loop():
    """The oracle's vectorised compositing equals the 3DGS per-pixel loop (including the stop rule)."""
    sample = random_scene(60, torch.Generator().manual_seed(11), sh_degree=0, opacity_range=(0.3, 1.0))
    cams = look_at_cameras(1, 16, 16, focal=14.0)
    keep, m2, conic, opac, rgb, z = project_one(
        sample, cams.cam_from_world[0], cams.K[0], 16, 16, 0.01, 1e10, 0.3
    )
    order = torch.argsort(z, stable=True)
    feat = torch.cat([rgb, z[:, None], torch.ones_like(z)[:, None]], -1)[order]
    from tests.reference.naive_render import _composite_pixels

    pix = torch.tensor(
        [[x + 0.5, y + 0.5] for x in range(0, 16, 3) for y in range(0, 16, 5)], dtype=torch.float64
    )
    a = _composite_pixels(pix, m2[order], conic[order], opac[order], feat)
    b = composite_loop(pix, m2[order], conic[order], opac[order], feat)
    assert (a - b).abs().max() < 1e-12
    assert (a[:, 4] > 0.9).any()
