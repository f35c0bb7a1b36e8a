"""Image quality metrics: PSNR, SSIM (differentiable) and the LPIPS availability check.

Images are float HWC in [0, 1]: ``[H,W,3]`` for one view or ``[...,H,W,3]`` for a batch (usually
``[C,H,W,3]``). Everything runs on the inputs' device; nothing is downloaded.
"""

from __future__ import annotations

import functools
import importlib.util
import math
from pathlib import Path
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor

Reduction = Literal["mean", "none"]


def _check_pair(pred: Tensor, target: Tensor) -> None:
    if pred.shape != target.shape:
        raise ValueError(f"pred and target must have the same shape, got {tuple(pred.shape)} vs {tuple(target.shape)}")
    if pred.ndim < 3:
        raise ValueError(f"images must be [...,H,W,Ch], got {tuple(pred.shape)}")


def mse(pred: Tensor, target: Tensor, mask: Tensor | None = None) -> Tensor:
    """Per-image mean squared error, shape [...] (the leading dims of ``[...,H,W,Ch]``).

    ``mask`` ([...,H,W], [...,H,W,1] or [...,H,W,Ch], bool or float weights) restricts the mean to the
    selected pixels; an image whose mask is empty gives NaN (there is nothing to measure).
    """
    _check_pair(pred, target)
    sq = (pred - target).square()  # [...,H,W,Ch]
    if mask is None:
        return sq.mean(dim=(-3, -2, -1))
    w = mask.to(sq.dtype)
    if w.shape == sq.shape[:-1]:
        w = w[..., None]
    w = w.expand_as(sq)
    return (sq * w).sum(dim=(-3, -2, -1)) / w.sum(dim=(-3, -2, -1))


def psnr(pred: Tensor, target: Tensor, mask: Tensor | None = None, *, reduction: Reduction = "mean") -> Tensor:
    """Peak signal-to-noise ratio in dB for images in [0, 1] (peak 1).

    PSNR is computed per image (over H, W and channels, optionally masked), then averaged over the
    leading dims when ``reduction="mean"`` (the usual way tables average views); ``"none"`` returns
    the per-image values [...]. Identical images give ``+inf`` (not NaN); callers that average views
    should decide how to treat it. Not differentiable at mse == 0.
    """
    err = mse(pred, target, mask)
    # -10 log10(0) = +inf in IEEE arithmetic; written explicitly so the intent is clear.
    value = torch.where(err > 0, -10.0 * torch.log10(err.clamp_min(torch.finfo(err.dtype).tiny)),
                        torch.full_like(err, math.inf))
    value = torch.where(torch.isnan(err), err, value)
    return value.mean() if reduction == "mean" else value


def gaussian_window(size: int = 11, sigma: float = 1.5, *, dtype=torch.float32, device=None) -> Tensor:
    """Normalised 1-D Gaussian window [size] (the separable SSIM kernel)."""
    x = torch.arange(size, dtype=torch.float64, device=device) - (size - 1) / 2.0
    g = torch.exp(-(x**2) / (2.0 * sigma**2))
    return (g / g.sum()).to(dtype)


def _blur(x: Tensor, window: Tensor, padding: str) -> Tensor:
    """Separable Gaussian blur of [B,Ch,H,W] per channel (zero padding for "same")."""
    ch = x.shape[1]
    k = window.shape[0]
    pad = k // 2 if padding == "same" else 0
    wx = window.view(1, 1, 1, k).expand(ch, 1, 1, k)
    wy = window.view(1, 1, k, 1).expand(ch, 1, k, 1)
    x = F.conv2d(x, wx, padding=(0, pad), groups=ch)
    return F.conv2d(x, wy, padding=(pad, 0), groups=ch)


SSIM_C1_DEFAULT, SSIM_C2_DEFAULT = 0.01**2, 0.03**2


def ssim_map(
    pred: Tensor,
    target: Tensor,
    *,
    window_size: int = 11,
    sigma: float = 1.5,
    c1: float = SSIM_C1_DEFAULT,
    c2: float = SSIM_C2_DEFAULT,
    padding: Literal["same", "valid"] = "same",
) -> Tensor:
    """Per-pixel SSIM map [...,H',W',Ch] of HWC images [...,H,W,Ch] in [0, 1] (data range 1).

    Local statistics use an 11x11 Gaussian window (sigma 1.5), constants C1 = 0.01^2, C2 = 0.03^2
    (Wang et al. 2004). ``padding="same"`` zero-pads like the 3DGS training/eval code (so published
    3DGS numbers are comparable; the border pixels are slightly pessimistic); ``"valid"`` keeps only
    windows fully inside the image (H' = H - 10), as scikit-image does.
    """
    _check_pair(pred, target)
    lead = pred.shape[:-3]
    h, w, ch = pred.shape[-3:]
    if padding == "valid" and (h < window_size or w < window_size):
        raise ValueError(f"valid SSIM needs images of at least {window_size}x{window_size}, got {h}x{w}")
    # [...,H,W,Ch] -> [B,Ch,H,W], made contiguous once: the elementwise ops below are several times
    # slower on the strided views
    x = pred.reshape(-1, h, w, ch).permute(0, 3, 1, 2).contiguous()
    y = target.reshape(-1, h, w, ch).permute(0, 3, 1, 2).contiguous()
    win = gaussian_window(window_size, sigma, dtype=pred.dtype, device=pred.device)
    # One blur call over the five stacked maps (fewer kernel launches than five calls).
    stats = _blur(torch.cat([x, y, x * x, y * y, x * y], dim=1), win, padding)
    mu_x, mu_y, exx, eyy, exy = stats.split(ch, dim=1)
    sxx = exx - mu_x * mu_x
    syy = eyy - mu_y * mu_y
    sxy = exy - mu_x * mu_y
    num = (2 * mu_x * mu_y + c1) * (2 * sxy + c2)
    den = (mu_x * mu_x + mu_y * mu_y + c1) * (sxx + syy + c2)
    out = (num / den).permute(0, 2, 3, 1)  # [B,H',W',Ch]
    return out.reshape(*lead, *out.shape[1:])


def masked_ssim(pred: Tensor, target: Tensor, mask: Tensor) -> float:
    """SSIM of HWC images [H,W,3] inside ``mask`` [H,W,1] bool: the mean of ``ssim_map`` over the pixels that count,
    with both images 0 outside them (what lies there, a passer-by a photo's mask left out, enters no window). The
    plain mean of the map would count the masked pixels as matching (two zeros: about 1)."""
    m = mask.to(pred.dtype)
    smap = ssim_map(pred * m, target * m)  # [H,W,3]
    inside = mask.expand_as(smap)
    return float(smap[inside].mean()) if bool(inside.any()) else float("nan")


def ssim(
    pred: Tensor,
    target: Tensor,
    *,
    reduction: Reduction = "mean",
    padding: Literal["same", "valid"] = "same",
) -> Tensor:
    """Structural similarity of HWC images in [0, 1]; differentiable (use ``1 - ssim`` as a loss).

    ``pred``/``target``: [H,W,3] or [C,H,W,3] (any [...,H,W,Ch]). Returns the mean of the SSIM map
    over pixels and channels: a scalar for ``reduction="mean"`` (also averaged over the leading dims),
    or one value per image [...] for ``"none"``. See :func:`ssim_map` for the window and padding.
    On CPU (float32, "same" padding, no gradient w.r.t. ``target``) the fused native kernel computes it
    (``uncertsplat.native``: same value and gradient as :func:`ssim_map`, in one pass over the images
    instead of a dozen tensor ops; BENCHMARKS.md, Rasterizer).
    """
    _check_pair(pred, target)
    if _fused_ssim(pred, target, padding):
        per_image = _fused_ssim_l1(pred, target)[0]
    else:
        per_image = ssim_map(pred, target, padding=padding).mean(dim=(-3, -2, -1))
    return per_image.mean() if reduction == "mean" else per_image


def ssim_and_l1(pred: Tensor, target: Tensor, target_stats: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """(mean SSIM, mean |pred - target|) of HWC images [...,H,W,Ch] in [0, 1], both differentiable w.r.t. ``pred``:
    the training loss's two image terms. Where :func:`ssim` runs the fused native kernel, both come from its one
    pass over the images (the L1 term's subtraction, absolute value, mean and their backward are a few tensor ops
    per training step otherwise); elsewhere :func:`ssim` and the plain L1.

    ``target_stats``: :func:`ssim_target_stats` of ``target`` (or None), which the fused kernel then reads instead of
    blurring the target again (a caller whose targets repeat keeps them: the training photos); the same result to
    the bit. Ignored where the fused kernel does not run."""
    _check_pair(pred, target)
    if _fused_ssim(pred, target, "same"):
        per_image, l1 = _fused_ssim_l1(pred, target, target_stats)
        return per_image.mean(), l1
    return ssim(pred, target), (pred - target).abs().mean()


def ssim_target_stats(target: Tensor) -> Tensor | None:
    """The blurred mean and mean square of each channel of HWC images [...,H,W,Ch] ([2, n x Ch, H, W], the planes
    image-major), as the fused SSIM computes them of its target, or None where the fused kernel does not take these
    images (not a CPU float32 tensor, or the native kernels off). 8 bytes per pixel and channel."""
    if not _fused_ssim(target, target.detach(), "same"):
        return None
    from uncertsplat import native

    h, w, ch = target.shape[-3:]
    y = target.detach().reshape(-1, h, w, ch).contiguous()
    out = y.new_empty(2, y.shape[0] * ch, h, w)
    window = _fused_window()
    native.library().us_ssim_target_stats_f32(out.shape[1], h, w, window.numel(), ch, y.data_ptr(),
                                              window.data_ptr(), out.data_ptr(), native.kernel_threads())
    return out


def _fused_ssim(pred: Tensor, target: Tensor, padding: str) -> bool:
    """Whether the fused native SSIM takes these images (CPU float32, "same" padding, no gradient to the target)."""
    from uncertsplat import native

    fused = padding == "same" and not target.requires_grad
    return native.use_for(pred, target, supported=fused, dtypes=(torch.float32,), strict=False)


@functools.cache
def _fused_window() -> Tensor:
    """The fused kernel's window (CPU float32), built once: a training step calls the kernel every time."""
    return gaussian_window(dtype=torch.float32)


def _fused_ssim_l1(pred: Tensor, target: Tensor, target_stats: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """(per-image mean SSIM [...], mean |pred - target| over everything) by the fused kernel."""
    lead, (h, w, ch) = pred.shape[:-3], pred.shape[-3:]
    # the kernel reads the channels of HWC images as planes in place (no permuted copies)
    images = [t.reshape(-1, h, w, ch).contiguous() for t in (pred, target)]
    if target_stats is not None:
        planes = images[0].shape[0] * ch
        if target_stats.shape != (2, planes, h, w) or target_stats.dtype != torch.float32:
            raise ValueError(f"target_stats must be ssim_target_stats(target), [2, {planes}, {h}, {w}] float32; got "
                             f"{list(target_stats.shape)} {target_stats.dtype}")
        target_stats = target_stats.contiguous()
    window = _fused_window()
    plane_ssim, plane_l1 = _FusedSSIM.apply(images[0], images[1].detach(), window, target_stats)
    return plane_ssim.view(-1, ch).mean(-1).reshape(lead), plane_l1.mean()


class _FusedSSIM(torch.autograd.Function):
    """Mean SSIM and mean |x - y| of each channel of images [n,H,W,Ch] by the native kernel ([n*Ch] each,
    image-major), 11x11 window, zero padding; ``ystats`` [2, n*Ch, H, W] (or None): y's blurred mean and mean square.

    Forward keeps the per-pixel partial derivatives of the SSIM map w.r.t. (mu_x, E[x^2], E[xy]);
    backward blurs them (the zero-padded symmetric blur is its own adjoint) into d loss / d x.
    """

    @staticmethod
    def forward(ctx, x: Tensor, y: Tensor, window: Tensor, ystats: Tensor | None) -> Tensor:
        from uncertsplat import native

        lib = native.library()
        ctx.set_materialize_grads(False)
        n, H, W, ch = x.shape
        B = n * ch
        plane_mean, plane_l1 = torch.empty(B, dtype=torch.float64), torch.empty(B, dtype=torch.float64)
        partials = x.new_empty(3, B, H, W) if x.requires_grad else None
        lib.us_ssim_forward_f32(B, H, W, window.numel(), ch, x.data_ptr(), y.data_ptr(),
                                ystats.data_ptr() if ystats is not None else None, window.data_ptr(),
                                SSIM_C1_DEFAULT, SSIM_C2_DEFAULT, plane_mean.data_ptr(),
                                partials.data_ptr() if partials is not None else None, plane_l1.data_ptr(),
                                native.kernel_threads())
        ctx.save_for_backward(x, y, window, partials if partials is not None else x.new_empty(0))
        return plane_mean.to(x.dtype), plane_l1.to(x.dtype)

    @staticmethod
    def backward(ctx, grad: Tensor | None, grad_l1: Tensor | None):
        from uncertsplat import native

        x, y, window, partials = ctx.saved_tensors
        n, H, W, ch = x.shape
        if grad is None and grad_l1 is None:
            return None, None, None, None
        g_plane = grad.to(torch.float32).contiguous() if grad is not None else x.new_zeros(n * ch)
        g_l1 = grad_l1.to(torch.float32).contiguous() if grad_l1 is not None else None
        g_x = torch.empty_like(x)
        native.library().us_ssim_backward_f32(n * ch, H, W, window.numel(), ch, x.data_ptr(), y.data_ptr(),
                                              window.data_ptr(), partials.data_ptr(), g_plane.data_ptr(),
                                              g_l1.data_ptr() if g_l1 is not None else None, g_x.data_ptr(),
                                              native.kernel_threads())
        return g_x, None, None, None


# ------------------------------------------------------------------------------------------------ LPIPS
_TORCH_HUB_ALEXNET = "alexnet-owt-"  # torchvision's pretrained AlexNet file name prefix


def lpips_available() -> tuple[bool, str]:
    """Whether LPIPS can be computed from files already on this machine (never downloads).

    LPIPS needs the ``lpips`` package (which ships its linear-layer weights) *and* the pretrained
    AlexNet backbone in the torch hub cache; torchvision would otherwise download the backbone on
    first use, which we never allow. Returns ``(ok, reason)``; the reason is shown in reports.
    """
    spec = importlib.util.find_spec("lpips")
    if spec is None or spec.origin is None:
        return False, "unavailable: no local weights (the `lpips` package is not installed)"
    if importlib.util.find_spec("torchvision") is None:
        return False, "unavailable: no local weights (`torchvision` is not installed)"
    pkg_dir = Path(spec.origin).parent
    linear = pkg_dir / "weights" / "v0.1" / "alex.pth"
    if not linear.is_file():
        return False, f"unavailable: no local weights ({linear} is missing)"
    hub = Path(torch.hub.get_dir()) / "checkpoints"
    if not hub.is_dir() or not any(p.name.startswith(_TORCH_HUB_ALEXNET) for p in hub.iterdir()):
        return False, f"unavailable: no local weights (AlexNet backbone not in {hub})"
    return True, "available: lpips (alex) with local weights"


def lpips(pred: Tensor, target: Tensor) -> Tensor:
    """LPIPS (AlexNet) distance per image [...] for HWC images in [0, 1], only with local weights.

    Raises ``RuntimeError`` with the reason when :func:`lpips_available` says no.
    """
    ok, reason = lpips_available()
    if not ok:
        raise RuntimeError(f"LPIPS {reason}")
    import lpips as _lpips  # optional dependency, checked above

    net = _lpips_net(_lpips, pred.device)
    _check_pair(pred, target)
    lead = pred.shape[:-3]
    h, w, ch = pred.shape[-3:]
    x = pred.reshape(-1, h, w, ch).permute(0, 3, 1, 2) * 2 - 1  # LPIPS expects [-1, 1]
    y = target.reshape(-1, h, w, ch).permute(0, 3, 1, 2) * 2 - 1
    with torch.no_grad():
        d = net(x.float(), y.float()).reshape(-1)
    return d.reshape(lead)


_LPIPS_CACHE: dict = {}


def _lpips_net(module, device):
    key = str(device)
    if key not in _LPIPS_CACHE:
        _LPIPS_CACHE[key] = module.LPIPS(net="alex", verbose=False).to(device).eval()
    return _LPIPS_CACHE[key]
