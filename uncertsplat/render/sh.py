"""Real spherical harmonics up to degree 3, in the basis and sign convention of 3DGS.

The colour of a Gaussian seen along the unit direction d (from the camera centre to the mean) is
``max(sum_b sh[b] * Y_b(d) + 0.5, 0)``; ``rgb_to_sh`` gives the constant (DC) term of a colour.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def num_sh_bases(degree: int) -> int:
    """Number of SH coefficients per channel for ``degree`` (0..3)."""
    return (degree + 1) ** 2


def rgb_to_sh(rgb: Tensor) -> Tensor:
    """DC coefficient whose evaluated colour is ``rgb`` (the colour of a DC coefficient is ``dc * C0 + 0.5``)."""
    return (rgb - 0.5) / C0


def sh_basis(degree: int, dirs: Tensor) -> Tensor:
    """Evaluate the SH basis functions.

    Args:
        degree: 0..3.
        dirs: [...,3] unit directions.

    Returns:
        [..., (degree+1)**2] basis values.
    """
    if not 0 <= degree <= 3:
        raise ValueError(f"SH degree must be in 0..3, got {degree}")
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, C0)]
    if degree >= 1:
        out += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        xy, yz, xz = x * y, y * z, x * z
        out += [
            C2[0] * xy,
            C2[1] * yz,
            C2[2] * (2.0 * zz - xx - yy),
            C2[3] * xz,
            C2[4] * (xx - yy),
        ]
    if degree >= 3:
        out += [
            C3[0] * y * (3.0 * xx - yy),
            C3[1] * xy * z,
            C3[2] * y * (4.0 * zz - xx - yy),
            C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
            C3[4] * x * (4.0 * zz - xx - yy),
            C3[5] * z * (xx - yy),
            C3[6] * x * (xx - 3.0 * yy),
        ]
    return torch.stack(out, dim=-1)


def _fibonacci_sphere(n: int) -> Tensor:
    """[n,3] float64 unit directions spread evenly over the sphere (a Fibonacci lattice: deterministic)."""
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * i / n
    r = (1.0 - z * z).sqrt()
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    return torch.stack([r * phi.cos(), r * phi.sin(), z], dim=-1)


def rotate_sh(sh_rest: Tensor, rotation: Tensor) -> Tensor:
    """The SH coefficients of the bands above 0 after the world is turned by ``rotation`` [3,3] (a proper rotation,
    d_new = R d_old): ``sh_rest`` [N,B-1,3] -> [N,B-1,3] such that every colour is the same in the turned direction,
    ``eval_sh(c', R d) = eval_sh(c, d)``. The DC term does not depend on the direction and is left as it is.

    Each band turns by itself (a (2l+1)x(2l+1) matrix, the real Wigner D of R in this basis), solved here by least
    squares from the basis at 64 directions and at their turned ones, exact to float64 rounding (the basis of a
    band is closed under rotation; 64 directions determine its 7 functions at most)."""
    b = sh_rest.shape[1] + 1
    degree = round(math.sqrt(b)) - 1
    if (degree + 1) ** 2 != b or not 0 <= degree <= 3:
        raise ValueError(f"sh_rest must hold (degree+1)^2 - 1 bases for a degree 0..3, got {b - 1}")
    if degree == 0:
        return sh_rest.clone()
    dirs = _fibonacci_sphere(64)  # [64,3]
    R = rotation.to(torch.float64).cpu()
    before, after = sh_basis(degree, dirs), sh_basis(degree, dirs @ R.T)  # [64,B]: Y(d), Y(R d)
    out = torch.empty_like(sh_rest)
    for band in range(1, degree + 1):
        lo, hi = band * band, (band + 1) ** 2
        # M with Y_l(R d) M = Y_l(d) for every d: c' = M c keeps Y_l(R d) . c' = Y_l(d) . c
        m = torch.linalg.lstsq(after[:, lo:hi], before[:, lo:hi]).solution  # [2l+1,2l+1]
        out[:, lo - 1:hi - 1] = torch.einsum("ij,njc->nic", m.to(sh_rest), sh_rest[:, lo - 1:hi - 1])
    return out


def eval_sh(degree: int, sh: Tensor, dirs: Tensor) -> Tensor:
    """Raw SH value (no +0.5, no clamp).

    Args:
        degree: degree to evaluate; ``sh`` may hold more bases than it uses.
        sh: [N,B,3] coefficients.
        dirs: [C,N,3] unit view directions.

    Returns:
        [C,N,3].
    """
    nb = num_sh_bases(degree)
    if sh.shape[-2] < nb:
        raise ValueError(f"sh has {sh.shape[-2]} bases, degree {degree} needs {nb}")
    basis = sh_basis(degree, dirs)  # [C,N,nb]
    # einsum (batched matmul) rather than a broadcast product and sum: half the time forward + backward
    return torch.einsum("cnb,nbk->cnk", basis, sh[:, :nb, :])


def sh_colors(degree: int, sh: Tensor, means: Tensor, centers: Tensor, backend: str | None = None) -> Tensor:
    """3DGS colour of each Gaussian seen from each camera centre.

    Args:
        degree: SH degree to evaluate.
        sh: [N,B,3] coefficients.
        means: [N,3] Gaussian centres.
        centers: [C,3] camera centres (world).

    Returns:
        [C,N,3] colours ``max(SH(d) + 0.5, 0)`` with d = normalise(mean - centre).

    On CPU (float32) the native kernel computes it and its gradient (``uncertsplat.native``; ``backend``
    as in ``native.use_for``); the code below is the reference and the path on other devices.
    """
    from uncertsplat import native

    if native.use_for(sh, means, centers, backend=backend, dtypes=(torch.float32,), strict=False,
                      supported=0 <= degree <= 3):
        return _NativeSH.apply(sh, None, means, centers, degree)
    if degree == 0:
        # The DC term does not depend on the direction: skip the normalisation (and its gradient).
        rgb = (sh[:, 0, :] * C0 + 0.5).unsqueeze(0).expand(centers.shape[0], -1, -1)
        return rgb.clamp_min(0.0)
    return (eval_sh(degree, sh, view_directions(means, centers)) + 0.5).clamp_min(0.0)


def sh_colors_split(degree: int, sh0: Tensor, sh_rest: Tensor, means: Tensor, centers: Tensor,
                    backend: str | None = None) -> Tensor:
    """``sh_colors`` of the coefficients ``cat([sh0, sh_rest], 1)`` (``sh0`` [N,1,3], ``sh_rest`` [N,B-1,3]: the
    parameter table's own tensors) without concatenating them: the native kernel reads both and writes their
    gradients into two tensors of their own layouts. A training step otherwise copied the coefficients into one
    array and its gradient back out of it (fern at 1/8, 60k Gaussians at degree 3: about 7 ms of a 125 ms step)."""
    from uncertsplat import native

    if native.use_for(sh0, sh_rest, means, centers, backend=backend, dtypes=(torch.float32,), strict=False,
                      supported=0 <= degree <= 3):
        return _NativeSH.apply(sh0, sh_rest, means, centers, degree)
    return sh_colors(degree, torch.cat([sh0, sh_rest], dim=1), means, centers, backend=backend)


def view_directions(means: Tensor, centers: Tensor) -> Tensor:
    """[C,N,3] the unit directions ``normalise(mean - centre)`` from each camera centre ``centers`` [C,3] to each
    Gaussian centre ``means`` [N,3], the directions the SH colour is evaluated at."""
    d = means.unsqueeze(0) - centers[:, None, :]  # [C,N,3]
    # Gaussians exactly at a camera centre have no direction: clamp the norm so values stay finite (zero vector).
    return d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)


class _NativeSH(torch.autograd.Function):
    """``sh_colors`` / ``sh_colors_split`` by the native kernel: the coefficients as one [N,B,3] array (``sh_rest``
    None) or as the DC [N,1,3] and the higher bands [N,B-1,3] apart, read in place; backward writes d loss / d
    coefficients in the same layout and d loss / d means (view direction)."""

    @staticmethod
    def forward(ctx, sh: Tensor, sh_rest: Tensor | None, means: Tensor, centers: Tensor, degree: int) -> Tensor:
        from uncertsplat import native

        parts = tuple(t.detach().contiguous() for t in ((sh,) if sh_rest is None else (sh, sh_rest)))
        means, centers = means.detach().contiguous(), centers.detach().contiguous()
        C, N, B = centers.shape[0], means.shape[0], sum(t.shape[1] for t in parts)
        if B < num_sh_bases(degree):
            raise ValueError(f"sh has {B} bases, degree {degree} needs {num_sh_bases(degree)}")
        out = parts[0].new_empty(C, N, 3)
        lib = native.library()
        fn = lib.us_sh_forward_f32 if len(parts) == 1 else lib.us_sh2_forward_f32
        fn(C, N, B, degree, *(t.data_ptr() for t in parts), means.data_ptr(), centers.data_ptr(), out.data_ptr(),
           native.kernel_threads())
        ctx.save_for_backward(means, centers, *parts)
        ctx.degree = degree
        return out

    @staticmethod
    def backward(ctx, grad: Tensor):
        from uncertsplat import native

        means, centers, *parts = ctx.saved_tensors
        C, N, B = centers.shape[0], means.shape[0], sum(t.shape[1] for t in parts)
        # at degree 0 the higher bands (apart) get no gradient, not one of zeros: nothing of them reached the render,
        # and a training step then neither writes nor reads them (``Adam.step_if_finite``'s ``idle``)
        g_parts = [torch.empty_like(t) if i == 0 or ctx.degree > 0 else None for i, t in enumerate(parts)]
        g_means = torch.empty_like(means)
        grad = grad.contiguous()  # kept in a variable: the kernel reads it after data_ptr() returns
        lib = native.library()
        fn = lib.us_sh_backward_f32 if len(parts) == 1 else lib.us_sh2_backward_f32
        fn(C, N, B, ctx.degree, *(t.data_ptr() for t in parts), means.data_ptr(), centers.data_ptr(), grad.data_ptr(),
           *(None if t is None else t.data_ptr() for t in g_parts), g_means.data_ptr(), native.kernel_threads())
        return g_parts[0], g_parts[1] if len(parts) == 2 else None, g_means, None, None
