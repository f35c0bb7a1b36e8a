"""EWA projection of 3D Gaussians to screen-space 2D Gaussians (differentiable through autograd).

Per camera c and Gaussian n: camera-space mean p = R x + t, pixel mean (fx p_x/p_z + cx, fy p_y/p_z + cy),
2D covariance ``J R Sigma R^T J^T + eps2d I`` with the perspective Jacobian J evaluated at the mean
(its x/z, y/z clamped to 1.3x the field of view, as 3DGS does, so off-screen Gaussians keep a sane
footprint), and Sigma = Rq S S Rq^T from the (normalised) quaternion and scales.

Numerics: the 2D covariance is written as ``A A^T + eps I`` with A = J R Rq S [2,3]; its determinant is
formed with the Lagrange identity ``|a1|^2 |a2|^2 - (a1.a2)^2 = |a1 x a2|^2`` (no cancellation for
needle-like Gaussians) after dividing A by its overall size (no overflow for huge Gaussians).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

ALPHA_MIN = 1.0 / 255.0  # contributions below this are skipped (3DGS)
ALPHA_MAX = 0.99  # per-Gaussian alpha cap (3DGS)
T_MIN = 1e-4  # a ray stops when its transmittance would fall below this (3DGS)


def unproject(depth: Tensor, cam_from_world: Tensor, K: Tensor) -> Tensor:
    """World points [H,W,3] of the pixel centres of one view at their depth (camera z) [H,W], in ``depth``'s dtype."""
    h, w = depth.shape
    dt = depth.dtype
    ys, xs = torch.meshgrid(torch.arange(h, dtype=dt, device=depth.device),
                            torch.arange(w, dtype=dt, device=depth.device), indexing="ij")
    pix = torch.stack([xs + 0.5, ys + 0.5, torch.ones_like(xs)], -1)  # [H,W,3]
    rays = pix @ torch.linalg.inv(K.to(dt)).T  # [H,W,3], z = 1
    cam = rays * depth[..., None]  # [H,W,3] camera coordinates
    world_from_cam = torch.linalg.inv(cam_from_world.to(dt))
    return cam @ world_from_cam[:3, :3].T + world_from_cam[:3, 3]


def project_points(points: Tensor, cam_from_world: Tensor, K: Tensor) -> tuple[Tensor, Tensor]:
    """Pixel coordinates [...,2] (centres at +0.5) and camera z [...] of world ``points`` [...,3] in one camera
    (``cam_from_world`` [4,4], ``K`` [3,3]), or [C,...,2] and [C,...] in each of C cameras ([C,4,4], [C,3,3]), in
    ``points``' dtype; points at z <= 1e-9 get finite, meaningless pixels (test z)."""
    dt = points.dtype
    shape = points.shape[:-1]
    flat = points.reshape(-1, 3)  # [P,3]
    R, t = cam_from_world[..., :3, :3].to(dt), cam_from_world[..., :3, 3].to(dt)  # [(C,)3,3], [(C,)3]
    p = flat @ R.transpose(-1, -2) + t[..., None, :]  # [(C,)P,3]
    z = p[..., 2]
    uv = (p[..., :2] / z.clamp_min(1e-9)[..., None]) @ K[..., :2, :2].to(dt).transpose(-1, -2) + \
        K[..., None, :2, 2].to(dt)
    lead = cam_from_world.shape[:-2]
    return uv.reshape(*lead, *shape, 2), z.reshape(*lead, *shape)


def _in_image(uv: Tensor, z: Tensor, cameras) -> Tensor:
    """[C,N] bool: projections (``uv`` [C,N,2], ``z`` [C,N]) in front of the ``cameras`` and inside their image."""
    return (z > 0) & (uv[..., 0] >= 0) & (uv[..., 0] < cameras.width) & (uv[..., 1] >= 0) & \
        (uv[..., 1] < cameras.height)


def points_in_view(points: Tensor, cameras) -> Tensor:
    """[C,N] bool: which of ``points`` [N,3] (world) each of the C ``cameras`` (``types.Cameras``) has in front of it
    and inside its image, in float64 on the CPU (``project_points``)."""
    uv, z = project_points(points.detach().double().cpu(), cameras.cam_from_world.cpu(), cameras.K.cpu())  # [C,N,2]
    return _in_image(uv, z, cameras)


def point_depths(points: Tensor, cameras, max_points: int = 20000, max_cameras: int = 100) -> Tensor:
    """[M] float64 camera z of ``points`` [N,3] (world) in each of the ``cameras`` (``types.Cameras``) that has the
    point in front of it and inside its image, on the CPU; every k-th point and camera above ``max_points`` and
    ``max_cameras`` (the distribution is what matters: at most 2M depths, 16 MB, however large the capture), a few
    cameras at a time."""
    pts = points.detach().double().cpu()
    pts = pts[:: max(1, -(-pts.shape[0] // max_points))]
    chosen = list(range(0, len(cameras), max(1, -(-len(cameras) // max_cameras))))
    out = []
    for lo in range(0, len(chosen), 16):
        cams = cameras[chosen[lo:lo + 16]]
        uv, z = project_points(pts, cams.cam_from_world.cpu(), cams.K.cpu())  # [c,P,2], [c,P]
        out.append(z[_in_image(uv, z, cams)])
    return torch.cat(out) if out else torch.zeros(0, dtype=torch.float64)


class Projection(NamedTuple):
    means2d: Tensor  # [C,N,2] pixels (centres at +0.5)
    conics: Tensor  # [C,N,3] inverse 2D covariance (a, b, c): power = -0.5 (a dx^2 + 2 b dx dy + c dy^2)
    depths: Tensor  # [C,N] camera z of the mean
    extents: Tensor  # [C,N,2] half-widths of the box where alpha >= 1/255 (no grad), 0 where culled
    valid: Tensor  # [C,N] bool: in front of the near plane, opacity above 1/255, box touches the image


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """[N,4] wxyz quaternions (any norm; ~0 gives the identity) -> [N,3,3] rotation matrices."""
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    # For an exactly-zero quaternion every product is 0 and the matrix below is the identity.
    R = torch.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    )
    return R.view(*quats.shape[:-1], 3, 3)


def clamped_view_angle(u: Tensor, v: Tensor, fx: Tensor, fy: Tensor, cx: Tensor, cy: Tensor, width: int,
                       height: int) -> tuple[Tensor, Tensor]:
    """The normalised image coordinates ``u = x / z``, ``v = y / z`` [C,N] clamped to 15 % of the image beyond its
    edges (3DGS's 1.3 x tan(fov / 2)): where the projection's Jacobian is evaluated (``fx`` etc.: [C,1])."""
    mx, my = 0.15 * width / fx, 0.15 * height / fy
    uc = torch.maximum(torch.minimum(u, (width - cx) / fx + mx), -cx / fx - mx)
    vc = torch.maximum(torch.minimum(v, (height - cy) / fy + my), -cy / fy - my)
    return uc, vc


def project_gaussians(
    means: Tensor,  # [N,3]
    quats: Tensor,  # [N,4]
    scales: Tensor,  # [N,3]
    opacities: Tensor,  # [N]
    cam_from_world: Tensor,  # [C,4,4]
    K: Tensor,  # [C,3,3]
    width: int,
    height: int,
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = 0.3,
    backend: str | None = None,
) -> Projection:
    """Project Gaussians into every camera (see the module docstring for the model).

    On CPU (float32) the native kernel computes it and its gradient (``uncertsplat.native``; ``backend``
    as in ``native.use_for``); the code below is the reference and the path on other devices.
    """
    from uncertsplat import native

    if native.use_for(means, quats, scales, opacities, cam_from_world, K, backend=backend, dtypes=(torch.float32,),
                      strict=False):
        return Projection(*_NativeProjection.apply(means, quats, scales, opacities, cam_from_world, K, width, height,
                                                   near, far, eps2d))
    R = cam_from_world[:, :3, :3]  # [C,3,3]
    t = cam_from_world[:, :3, 3]  # [C,3]
    p = torch.einsum("cij,nj->cni", R, means) + t[:, None, :]  # [C,N,3]
    x, y, z = p.unbind(-1)
    valid = (z > near) & (z < far)
    # Culled Gaussians get a harmless z so that no inf/NaN enters the graph (where() would
    # otherwise propagate 0 * inf = NaN gradients).
    zs = torch.where(valid, z, torch.ones_like(z))
    fx, fy = K[:, 0, 0, None], K[:, 1, 1, None]  # [C,1]
    cx, cy = K[:, 0, 2, None], K[:, 1, 2, None]
    u = x / zs
    v = y / zs
    means2d = torch.stack([fx * u + cx, fy * v + cy], dim=-1)  # [C,N,2]

    # Jacobian of the perspective map, evaluated with the view angle clamped (3DGS: 1.3 x tan(fov/2)).
    uc, vc = clamped_view_angle(u, v, fx, fy, cx, cy, width, height)
    zero = torch.zeros_like(u)
    J = torch.stack(
        [torch.stack([fx / zs, zero, -fx * uc / zs], -1), torch.stack([zero, fy / zs, -fy * vc / zs], -1)],
        dim=-2,
    )  # [C,N,2,3]
    M = quat_to_rotmat(quats) * scales[:, None, :]  # [N,3,3], Sigma = M M^T
    A = J @ torch.einsum("cij,njk->cnik", R, M)  # [C,N,2,3], Sigma2d = A A^T + eps I

    # Normalise A by its overall size s so that squares/products cannot overflow (scales up to 1e3
    # at the near plane) and the determinant has no cancellation (Lagrange identity).
    s = (A * A).sum(dim=(-1, -2)) + eps2d  # [C,N]  >= eps2d > 0
    An = A / s.sqrt()[..., None, None]
    e = eps2d / s  # [C,N]
    a1, a2 = An[..., 0, :], An[..., 1, :]
    a = (a1 * a1).sum(-1) + e  # normalised Sigma2d entries
    c = (a2 * a2).sum(-1) + e
    b = (a1 * a2).sum(-1)
    cross = torch.linalg.cross(a1, a2)
    det = (cross * cross).sum(-1) + e * (a + c - 2 * e) + e * e  # = a c - b^2, without cancellation
    denom = (det * s).clamp_min(torch.finfo(det.dtype).tiny)
    conics = torch.stack([c / denom, -b / denom, a / denom], dim=-1)  # [C,N,3]

    with torch.no_grad():
        # Opacity-aware footprint: o exp(-q/2) >= 1/255  <=>  q <= 2 ln(255 o); the box of that ellipse
        # has half-widths sqrt(thr * Sigma_xx), sqrt(thr * Sigma_yy).
        o = opacities.detach().unsqueeze(0).expand_as(z)
        thr = 2.0 * torch.log((o / ALPHA_MIN).clamp_min(1.0))
        sxx = a.detach() * s.detach()
        syy = c.detach() * s.detach()
        # A small relative/absolute margin makes the box conservative against rounding; the exact
        # per-pixel test happens in the compositor, so this does not change the image.
        ex = (thr * sxx).sqrt() * (1 + 1e-3) + 1e-3
        ey = (thr * syy).sqrt() * (1 + 1e-3) + 1e-3
        m2 = means2d.detach()
        valid = valid & (o >= ALPHA_MIN) & torch.isfinite(ex) & torch.isfinite(ey)
        # The box must contain at least one pixel centre of the image.
        valid = valid & (m2[..., 0] + ex > 0.5) & (m2[..., 0] - ex < width - 0.5)
        valid = valid & (m2[..., 1] + ey > 0.5) & (m2[..., 1] - ey < height - 0.5)
        extents = torch.where(valid[..., None], torch.stack([ex, ey], -1), torch.zeros_like(m2))
    return Projection(means2d, conics, z, extents, valid)


class _NativeProjection(torch.autograd.Function):
    """``project_gaussians`` by the native kernel. Gradients flow to means, quats and scales from means2d,
    conics and depths; extents and valid carry none (as in the reference)."""

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, cam_from_world, K, width, height, near, far, eps2d):
        from uncertsplat import native

        means, quats, scales, opacities, cams, Ks = (
            t.detach().contiguous() for t in (means, quats, scales, opacities, cam_from_world, K))
        C, N = cams.shape[0], means.shape[0]
        means2d, conics = means.new_empty(C, N, 2), means.new_empty(C, N, 3)
        depths, extents = means.new_empty(C, N), means.new_empty(C, N, 2)
        valid = torch.empty(C, N, dtype=torch.uint8)
        native.library().us_project_forward_f32(
            C, N, means.data_ptr(), quats.data_ptr(), scales.data_ptr(), opacities.data_ptr(), cams.data_ptr(),
            Ks.data_ptr(), width, height, near, far, eps2d, ALPHA_MIN, means2d.data_ptr(), conics.data_ptr(),
            depths.data_ptr(), extents.data_ptr(), valid.data_ptr(), native.kernel_threads())
        ctx.save_for_backward(means, quats, scales, cams, Ks)
        ctx.args = (width, height, near, far, eps2d)
        ctx.mark_non_differentiable(extents)
        valid = valid.bool()
        ctx.mark_non_differentiable(valid)
        return means2d, conics, depths, extents, valid

    @staticmethod
    def backward(ctx, g_means2d, g_conics, g_depths, _g_extents, _g_valid):
        from uncertsplat import native

        means, quats, scales, cams, Ks = ctx.saved_tensors
        width, height, near, far, eps2d = ctx.args
        C, N = cams.shape[0], means.shape[0]
        grads = [None if g is None else g.contiguous() for g in (g_means2d, g_conics, g_depths)]
        g_means, g_quats, g_scales = torch.empty_like(means), torch.empty_like(quats), torch.empty_like(scales)
        native.library().us_project_backward_f32(
            C, N, means.data_ptr(), quats.data_ptr(), scales.data_ptr(), cams.data_ptr(), Ks.data_ptr(), width,
            height, near, far, eps2d, *(None if g is None else g.data_ptr() for g in grads), g_means.data_ptr(),
            g_quats.data_ptr(), g_scales.data_ptr(), native.kernel_threads())
        return g_means, g_quats, g_scales, None, None, None, None, None, None, None, None
