"""The opt-in torch.compile path gives the same image and gradients as eager (slow: compiles)."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from tests.reference.naive_render import look_at_cameras, random_scene
from uncertsplat.render import render


@pytest.mark.slow
def test_compiled_kernels_match_eager(device):
    s = random_scene(200, torch.Generator().manual_seed(0), sh_degree=3).to(device=device)
    cams = look_at_cameras(1, 48, 40, 40.0).to(device=device)
    grads = []
    for compile in (False, True):
        leaves = {k: getattr(s, k).clone().requires_grad_() for k in ("means", "opacities", "sh")}
        out = render(replace(s, **leaves), cams, compile=compile)
        out.rgb.square().sum().backward()
        grads.append((out.rgb.detach(), {k: v.grad for k, v in leaves.items()}))
    (rgb_e, g_e), (rgb_c, g_c) = grads
    assert (rgb_e - rgb_c).abs().max() < 1e-5
    for k in g_e:
        rel = ((g_e[k] - g_c[k]).norm() / g_e[k].norm()).item()
        assert rel < 1e-4, (k, rel)
