"""PSNR / SSIM against closed forms and an independent float64 reference; LPIPS never downloads."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import ndimage

from uncertsplat.eval.image import lpips_available, psnr, ssim, ssim_map


def _rand(shape, seed=0, device="cpu", dtype=torch.float32):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(shape, generator=g, dtype=dtype).to(device)


def test_psnr_closed_form(device):
    a = torch.zeros(8, 9, 3, device=device)
    b = torch.full((8, 9, 3), 0.1, device=device)
    # mse = 0.01 -> 20 dB
    assert psnr(a, b).item() == pytest.approx(20.0, abs=1e-4)


def test_psnr_identical_is_inf_not_nan(device):
    a = _rand((2, 6, 7, 3), device=device)
    v = psnr(a, a, reduction="none")
    assert v.shape == (2,)
    assert torch.isinf(v).all() and (v > 0).all()
    assert math.isinf(psnr(a, a).item())


def test_psnr_batch_and_mask(device):
    a = _rand((2, 5, 5, 3), seed=1, device=device)
    b = a.clone()
    b[0] += 0.1  # image 0: mse 0.01 -> 20 dB
    b[1, :2] += 0.2  # image 1: only rows 0..1 differ
    v = psnr(a, b, reduction="none")
    assert v[0].item() == pytest.approx(20.0, abs=1e-3)
    mask = torch.zeros(2, 5, 5, dtype=torch.bool, device=device)
    mask[:, :2] = True
    vm = psnr(a, b, mask, reduction="none")
    assert vm[1].item() == pytest.approx(-10 * math.log10(0.04), abs=1e-3)
    assert psnr(a, b).item() == pytest.approx(v.mean().item(), rel=1e-6)


def test_ssim_identical_is_one(device):
    a = _rand((3, 20, 24, 3), device=device)
    assert ssim(a, a).item() == pytest.approx(1.0, abs=1e-6)
    assert ssim(a[0], a[0]).item() == pytest.approx(1.0, abs=1e-6)


def test_ssim_constant_images_closed_form(device):
    # Constant images: sigma terms vanish, SSIM = (2ab + C1) / (a^2 + b^2 + C1) (valid windows only).
    a, b = 0.3, 0.7
    x = torch.full((16, 16, 3), a, device=device, dtype=torch.float64)
    y = torch.full((16, 16, 3), b, device=device, dtype=torch.float64)
    c1 = 0.01**2
    expected = (2 * a * b + c1) / (a * a + b * b + c1)
    assert ssim(x, y, padding="valid").item() == pytest.approx(expected, rel=1e-10)


def _ssim_reference(x: np.ndarray, y: np.ndarray) -> float:
    """Independent float64 SSIM: 2-D Gaussian window, zero padding, per channel."""
    r = np.arange(11) - 5.0
    g = np.exp(-(r**2) / (2 * 1.5**2))
    w2 = np.outer(g, g)
    w2 /= w2.sum()
    c1, c2 = 0.01**2, 0.03**2
    vals = []
    for c in range(x.shape[-1]):
        xc, yc = x[..., c], y[..., c]

        def f(im):
            return ndimage.correlate(im, w2, mode="constant", cval=0.0)

        mx, my = f(xc), f(yc)
        sxx, syy, sxy = f(xc * xc) - mx * mx, f(yc * yc) - my * my, f(xc * yc) - mx * my
        m = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx**2 + my**2 + c1) * (sxx + syy + c2))
        vals.append(m)
    return float(np.mean(vals))


def test_ssim_matches_reference(device):
    x = _rand((23, 19, 3), seed=2, dtype=torch.float64)
    y = (x + 0.2 * _rand((23, 19, 3), seed=3, dtype=torch.float64)).clamp(0, 1)
    ref = _ssim_reference(x.numpy(), y.numpy())
    got = ssim(x.to(device), y.to(device)).item()
    assert got == pytest.approx(ref, abs=1e-10)
    assert 0.0 < got < 1.0
    m = ssim_map(x, y, padding="valid")
    assert m.shape == (13, 9, 3)


def test_ssim_gradient_finite(device):
    x = _rand((2, 16, 16, 3), seed=4, device=device).requires_grad_(True)
    y = _rand((2, 16, 16, 3), seed=5, device=device)
    loss = 1 - ssim(x, y)
    loss.backward()
    assert x.grad is not None and torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0
    # Also at the optimum (identical images), where the gradient must be ~0 and finite.
    z = y.clone().requires_grad_(True)
    (1 - ssim(z, y)).backward()
    assert torch.isfinite(z.grad).all() and z.grad.abs().max() < 1e-5


def test_ssim_gradcheck_float64():
    x = _rand((8, 9, 1), seed=6, dtype=torch.float64).requires_grad_(True)
    y = _rand((8, 9, 1), seed=7, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda a: ssim(a, y), (x,))


def test_shape_mismatch_raises():
    with pytest.raises(ValueError):
        psnr(torch.zeros(4, 4, 3), torch.zeros(4, 5, 3))


def test_lpips_available_never_downloads(monkeypatch):
    def boom(*a, **k):
        raise AssertionError("attempted download")

    monkeypatch.setattr(torch.hub, "load_state_dict_from_url", boom)
    monkeypatch.setattr(torch.hub, "download_url_to_file", boom)
    ok, reason = lpips_available()
    assert isinstance(ok, bool) and isinstance(reason, str) and reason
    assert reason.startswith("available" if ok else "unavailable")
