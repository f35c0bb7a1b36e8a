"""Dense, obviously-correct float64 Gaussian renderer: the oracle for the tiled rasterizer.

Every Gaussian is evaluated at every pixel; nothing is tiled, bounded or culled except by the 3DGS
rules themselves. It implements, independently of ``uncertsplat.render``:

- projection: p = R x + t; pixel mean (fx x/z + cx, fy y/z + cy); Sigma = Rq diag(s^2) Rq^T;
  Sigma2d = J R Sigma R^T J^T + eps2d I with the Jacobian's x/z, y/z clamped to 1.3x the half FOV;
  Gaussians with z outside (near, far) are dropped.
- colour: 3DGS real SH of normalise(mean - camera centre), + 0.5, clamped at 0.
- compositing per pixel, front to back in depth order (stable): alpha = min(0.99, o exp(-d^T Sigma2d^-1 d / 2));
  alpha < 1/255 is skipped; the ray stops before a Gaussian that would make T < 1e-4.

The sequential compositing is written with a cumulative product: with alpha' = 0 for skipped
contributions, T_incl_i = prod_{j<=i} (1 - alpha'_j) is non-increasing, so "the ray has not stopped at
i" is exactly T_incl_i >= 1e-4, and w_i = alpha'_i T_excl_i on that prefix. ``composite_loop`` is the
literal per-pixel loop, used to test this equivalence.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = [
    1.0925484305920792,
    -1.0925484305920792,
    0.31539156525252005,
    -1.0925484305920792,
    0.5462742152960396,
]
SH_C3 = [
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
]


def sh_color(deg: int, sh: Tensor, d: Tensor) -> Tensor:
    """sh [N,B,3], unit d [N,3] -> [N,3] (no clamp, no +0.5)."""
    x, y, z = d[:, 0:1], d[:, 1:2], d[:, 2:3]
    res = SH_C0 * sh[:, 0]
    if deg > 0:
        res = res - SH_C1 * y * sh[:, 1] + SH_C1 * z * sh[:, 2] - SH_C1 * x * sh[:, 3]
    if deg > 1:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        res = (
            res
            + SH_C2[0] * xy * sh[:, 4]
            + SH_C2[1] * yz * sh[:, 5]
            + SH_C2[2] * (2 * zz - xx - yy) * sh[:, 6]
            + SH_C2[3] * xz * sh[:, 7]
            + SH_C2[4] * (xx - yy) * sh[:, 8]
        )
    if deg > 2:
        res = (
            res
            + SH_C3[0] * y * (3 * xx - yy) * sh[:, 9]
            + SH_C3[1] * xy * z * sh[:, 10]
            + SH_C3[2] * y * (4 * zz - xx - yy) * sh[:, 11]
            + SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy) * sh[:, 12]
            + SH_C3[4] * x * (4 * zz - xx - yy) * sh[:, 13]
            + SH_C3[5] * z * (xx - yy) * sh[:, 14]
            + SH_C3[6] * x * (xx - 3 * yy) * sh[:, 15]
        )
    return res


def quat_to_R(q: Tensor) -> Tensor:
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def project_one(sample, cam_from_world: Tensor, K: Tensor, W: int, H: int, near, far, eps2d):
    """float64 projection for one camera: (keep mask [N], means2d, conic [N,2,2], opacity, colour, z)."""
    means = sample.means.double()
    R, t = cam_from_world[:3, :3].double(), cam_from_world[:3, 3].double()
    K = K.double()
    p = means @ R.T + t
    z = p[:, 2]
    keep = (z > near) & (z < far)
    p, z = p[keep], z[keep]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    mean2d = torch.stack([fx * p[:, 0] / z + cx, fy * p[:, 1] / z + cy], -1)
    limx_hi, limx_lo = (W - cx) / fx + 0.15 * W / fx, -cx / fx - 0.15 * W / fx
    limy_hi, limy_lo = (H - cy) / fy + 0.15 * H / fy, -cy / fy - 0.15 * H / fy
    tx = (p[:, 0] / z).clamp(limx_lo, limx_hi)
    ty = (p[:, 1] / z).clamp(limy_lo, limy_hi)
    J = torch.zeros(z.shape[0], 2, 3, dtype=torch.float64, device=z.device)
    J[:, 0, 0] = fx / z
    J[:, 0, 2] = -fx * tx / z
    J[:, 1, 1] = fy / z
    J[:, 1, 2] = -fy * ty / z
    Rq = quat_to_R(sample.quats.double()[keep])
    S2 = torch.diag_embed(sample.scales.double()[keep] ** 2)
    cov3 = Rq @ S2 @ Rq.transpose(1, 2)
    cov2 = J @ R @ cov3 @ R.T @ J.transpose(1, 2) + eps2d * torch.eye(2, dtype=torch.float64, device=z.device)
    conic = torch.linalg.inv(cov2)
    centre = -R.T @ t
    d = means[keep] - centre
    d = d / d.norm(dim=-1, keepdim=True)
    rgb = (sh_color(sample.sh_degree, sample.sh.double()[keep], d) + 0.5).clamp_min(0.0)
    return keep, mean2d, conic, sample.opacities.double()[keep], rgb, z


def _composite_pixels(pix: Tensor, mean2d, conic, opac, feat) -> Tensor:
    """pix [P,2], Gaussians sorted front to back -> [P,F] composited features (cumprod form)."""
    d = pix[:, None, :] - mean2d[None]  # [P,N,2]
    power = -0.5 * torch.einsum("pni,nij,pnj->pn", d, conic, d)
    alpha = opac[None] * torch.exp(power)
    alpha = torch.where(alpha >= 1.0 / 255.0, alpha.clamp_max(0.99), torch.zeros_like(alpha))
    t_incl = torch.cumprod(1 - alpha, dim=1)
    t_excl = torch.cat([torch.ones_like(t_incl[:, :1]), t_incl[:, :-1]], dim=1)
    w = alpha * t_excl * (t_incl >= 1e-4)
    return w @ feat


def composite_loop(pix: Tensor, mean2d, conic, opac, feat) -> Tensor:
    """The literal 3DGS per-pixel loop (slow; for testing the cumprod form on a few pixels)."""
    out = torch.zeros(pix.shape[0], feat.shape[1], dtype=feat.dtype)
    for p in range(pix.shape[0]):
        T = 1.0
        for i in range(mean2d.shape[0]):
            d = pix[p] - mean2d[i]
            alpha = min(0.99, float(opac[i]) * math.exp(-0.5 * float(d @ conic[i] @ d)))
            if alpha < 1.0 / 255.0:
                continue
            test_T = T * (1 - alpha)
            if test_T < 1e-4:
                break
            out[p] += feat[i] * alpha * T
            T = test_T
    return out


def naive_render(
    sample,
    cameras,
    *,
    background: Tensor | None = None,
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = 0.3,
    pixel_chunk: int | None = None,
) -> dict:
    """Dense float64 render. Returns dict of rgb [C,H,W,3], alpha, depth, depth_expected [C,H,W,1].

    ``pixel_chunk`` renders that many pixels at a time under activation checkpointing, which bounds
    memory for large images (pixels are independent, so this changes nothing numerically).
    """
    W, H = cameras.width, cameras.height
    dev = sample.means.device
    ys, xs = torch.meshgrid(
        torch.arange(H, dtype=torch.float64, device=dev),
        torch.arange(W, dtype=torch.float64, device=dev),
        indexing="ij",
    )
    pix = torch.stack([xs.reshape(-1) + 0.5, ys.reshape(-1) + 0.5], -1)  # [HW,2]
    outs = []
    for c in range(len(cameras)):
        keep, m2, conic, opac, rgb, z = project_one(
            sample, cameras.cam_from_world[c], cameras.K[c], W, H, near, far, eps2d
        )
        order = torch.argsort(z, stable=True)
        feat = torch.cat([rgb, z[:, None], torch.ones_like(z)[:, None]], -1)[order]
        args = (m2[order], conic[order], opac[order], feat)
        if pixel_chunk is None:
            img = _composite_pixels(pix, *args)
        else:
            img = torch.cat(
                [
                    checkpoint(_composite_pixels, pix[s : s + pixel_chunk], *args, use_reentrant=False)
                    for s in range(0, pix.shape[0], pixel_chunk)
                ]
            )
        outs.append(img.view(H, W, 5))
    img = torch.stack(outs)
    alpha = img[..., 4:5]
    rgb = img[..., :3]
    if background is not None:
        rgb = rgb + (1 - alpha) * background.double()
    dexp = img[..., 3:4]
    depth = torch.where(alpha > 0, dexp / torch.where(alpha > 0, alpha, torch.ones_like(alpha)), 0.0)
    return {"rgb": rgb, "alpha": alpha, "depth": depth, "depth_expected": dexp}


def look_at_cameras(
    n_cams: int, width: int, height: int, focal: float, radius: float = 4.0, dtype=torch.float32
):
    """C cameras on a circle looking at the origin (OpenCV axes), principal point at the centre."""
    from uncertsplat.types import Cameras

    mats, Ks = [], []
    for i in range(n_cams):
        ang = 2 * math.pi * i / max(n_cams, 1) * 0.25
        eye = torch.tensor(
            [radius * math.sin(ang), 0.3 * radius * math.cos(ang * 3), -radius * math.cos(ang)],
            dtype=torch.float64,
        )
        fwd = -eye / eye.norm()
        up = torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64)
        right = torch.linalg.cross(fwd, up)
        right = right / right.norm()
        down = torch.linalg.cross(fwd, right)
        Rw = torch.stack([right, down, fwd])  # rows: camera axes in world
        m = torch.eye(4, dtype=torch.float64)
        m[:3, :3] = Rw
        m[:3, 3] = -Rw @ eye
        mats.append(m)
        Ks.append(
            torch.tensor([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1]], dtype=torch.float64)
        )
    return Cameras(torch.stack(mats).to(dtype), torch.stack(Ks).to(dtype), width, height)


def random_scene(
    n: int,
    generator: torch.Generator,
    *,
    sh_degree: int = 3,
    extent: float = 1.0,
    scale_range: tuple[float, float] = (0.02, 0.15),
    opacity_range: tuple[float, float] = (0.05, 0.95),
    dtype=torch.float32,
):
    """N random Gaussians in a cube of half-size ``extent`` around the origin (CPU tensors)."""
    from uncertsplat.types import GaussianSample

    g = generator
    means = (torch.rand(n, 3, generator=g, dtype=torch.float64) * 2 - 1) * extent
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    lo, hi = math.log(scale_range[0]), math.log(scale_range[1])
    scales = torch.exp(torch.rand(n, 3, generator=g, dtype=torch.float64) * (hi - lo) + lo)
    opac = (
        torch.rand(n, generator=g, dtype=torch.float64) * (opacity_range[1] - opacity_range[0])
        + opacity_range[0]
    )
    sh = torch.randn(n, (sh_degree + 1) ** 2, 3, generator=g, dtype=torch.float64) * 0.3
    sh[:, 0] = torch.randn(n, 3, generator=g, dtype=torch.float64)
    return GaussianSample(
        means.to(dtype), quats.to(dtype), scales.to(dtype), opac.to(dtype), sh.to(dtype), sh_degree
    )
