"""``render``: Gaussians + cameras -> images, depth, screen-space means and radii."""

from __future__ import annotations

import torch
from torch import Tensor

from ..types import Cameras, GaussianSample, RenderOutput
from .project import ALPHA_MAX, clamped_view_angle, project_gaussians
from .rasterize import bin_gaussians, composite, composite_image, composite_image_available, tiles_to_image
from .sh import sh_colors, sh_colors_split

NEAR_FRACTION = 0.01
"""The near plane's default distance, as a fraction of the scene scale (the camera-rig radius)."""


def near_plane(scene_scale: float, depths: Tensor | None = None) -> float:
    """The near plane every stage renders with: 1% of the scene scale (the camera-rig radius), or nearer when the
    scene's surface is: a fifth of the 1st percentile of ``depths`` (the sparse points' camera z in the training
    views, ``project.point_depths``; 10 at least) when that is smaller.

    Relative to the scene so that training, evaluation and pruning agree and the whole pipeline is
    equivariant to a global rescaling of the scene. The radius is the farthest camera's: two stray cameras 100x
    out put 1 % of it beyond the surface the other cameras see (held out 24.1 -> 12.8 dB), and a close-range
    inspection (cameras 1 % of the rig's radius from a wall) has its surface there too; the points' depths keep
    such a surface in front of the plane, and leave every other scene's plane where it was.
    """
    base = NEAR_FRACTION * float(scene_scale)
    if depths is None or depths.numel() < 10:
        return base
    flat = depths.detach().flatten().double().cpu()
    k = max(1, int(0.01 * flat.numel()))
    # (floored: a cloud of stray points at a camera's lens must not put the plane at 0)
    return max(1e-3 * base, min(base, 0.2 * float(flat.kthvalue(k).values)))


def render(
    sample: GaussianSample,
    cameras: Cameras,
    *,
    background: Tensor | None = None,
    tile_size: int = 8,
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = 0.3,
    compile: bool = False,
    block_elements: int | None = None,
    backend: str | None = None,
) -> RenderOutput:
    """Render a batch of cameras with 3DGS semantics (exact, differentiable).

    EWA projection with a ``eps2d`` px screen-space dilation, SH colours (``sample.sh_degree``) seen
    from each camera centre, Gaussians with camera z outside (near, far) culled, front-to-back
    compositing with alpha capped at 0.99, contributions below 1/255 skipped, and a ray stopping
    before its transmittance falls under 1e-4.

    Args:
        sample: activated Gaussians (means [N,3], quats [N,4] wxyz, scales [N,3], opacities [N], sh [N,B,3]).
        cameras: C pinhole cameras of one image size.
        background: [3] colour behind the Gaussians (None = black).
        tile_size: tile edge in pixels (8 is fastest on CPU, 16 on GPU).
        near, far: camera-z culling planes.
        eps2d: screen-space dilation added to the 2D covariance (pixels^2).
        compile: run the per-pixel kernels through ``torch.compile`` (opt-in; first call compiles).
        block_elements: pair-pixel elements per dense block of the PyTorch compositor (memory/speed);
            None = ``default_block_elements(device)`` (larger on GPUs, where each block costs launches).
        backend: kernels for projection, SH colours, binning and compositing: ``"auto"`` (the native CPU
            kernels for CPU tensors when they build, else PyTorch), ``"native"`` or ``"torch"``; None reads
            ``UNCERTSPLAT_RASTERIZER`` (default auto). Projection and SH are native for float32 only.

    Returns:
        RenderOutput with rgb [C,H,W,3], alpha [C,H,W,1], depth [C,H,W,1] (alpha-normalised camera z,
        0 where alpha == 0), depth_expected [C,H,W,1], means2d [C,N,2] (pixels; it retains its gradient:
        read ``out.means2d.grad`` after backward), radii [C,N] (float pixels, 0 = culled), depths [C,N].
        Gradients flow to means, quats, scales, opacities and sh, and to the cameras' ``cam_from_world`` and ``K``
        when those require it (the native projection has no camera gradient: such a render takes the PyTorch
        projection and SH, the same images to rounding).
    """
    if backend not in (None, "auto", "native", "torch"):  # ("Torch" or "cuda" ran the native kernels without a word)
        raise ValueError(f"backend must be None, 'auto', 'native' or 'torch', got {backend!r}")
    front = backend  # projection and SH colours: the parts that see the cameras
    if backend != "torch" and (cameras.cam_from_world.requires_grad or cameras.K.requires_grad):
        # the native projection returns no gradient for the cameras (a pose refined through it got None); binning and
        # compositing take screen-space inputs, whose gradients reach the cameras through the PyTorch projection
        if backend == "native":
            raise ValueError("backend 'native' has no gradient for the cameras (cam_from_world or K requires grad): "
                             "use backend 'torch' or None")
        front = "torch"
    C, N = len(cameras), len(sample)
    W, H = cameras.width, cameras.height
    dtype = sample.means.dtype
    cam_from_world = cameras.cam_from_world.to(dtype)
    K = cameras.K.to(dtype)
    scales = sample.scales
    if sample.position_var is not None:  # the footprint averaged over the position noise: Sigma + var I
        scales = torch.sqrt(scales * scales + sample.position_var.clamp_min(0.0)[:, None])
    proj = project_gaussians(
        sample.means, sample.quats, scales, sample.opacities, cam_from_world, K, W, H, near, far, eps2d,
        backend=front,
    )
    means2d = proj.means2d
    if means2d.requires_grad:
        means2d.retain_grad()

    centers = -(cam_from_world[:, :3, :3].transpose(1, 2) @ cam_from_world[:, :3, 3:])[..., 0]  # [C,3]
    if sample.sh_rest is None:
        colors = sh_colors(sample.sh_degree, sample.sh, sample.means, centers, backend=front)  # [C,N,3]
    else:
        colors = sh_colors_split(sample.sh_degree, sample.sh, sample.sh_rest, sample.means, centers, backend=front)

    bins = bin_gaussians(
        means2d.detach(),
        proj.extents,
        proj.valid,
        proj.depths.detach(),
        W,
        H,
        tile_size,
        proj.conics.detach(),
        sample.opacities.detach(),
        backend=backend,
    )
    log_o = torch.log(sample.opacities.clamp_min(torch.finfo(dtype).tiny))  # [N]
    if sample.position_var is not None:
        log_o = log_o + blur_log_peak(sample, proj.conics, cam_from_world, K, W, H, near, far, eps2d,
                                      backend=front)  # [C,N]
    # [C,N]; one camera (a training step): a view whose backward is free, where expand's sums the camera axis
    log_o = log_o.unsqueeze(0) if (log_o.dim() == 1 and C == 1) else log_o.expand(C, N)
    if composite_image_available(means2d, colors, background=background, backend=backend, compile=compile):
        # the native kernel composites straight into the images, background included
        rgb, depth_expected, alpha = composite_image(means2d, proj.conics, log_o, colors, proj.depths, bins, H, W,
                                                     background)
    else:
        feat = torch.cat([colors, proj.depths[..., None], torch.ones_like(proj.depths)[..., None]], dim=-1)
        gparams = torch.cat([means2d, proj.conics, log_o[..., None]], dim=-1).reshape(C * N, 6)
        # Alpha can reach the 0.99 cap only for opacities near it (small margin for rounding).
        high = (sample.opacities.detach() > ALPHA_MAX - 1e-3).expand(C, N).reshape(-1)
        tiles = composite(gparams, feat.reshape(C * N, 5), bins, high, block_elements=block_elements,
                          compile=compile, backend=backend)
        img = tiles_to_image(tiles, C, bins, H, W)  # [C,H,W,5]
        rgb, depth_expected, alpha = img[..., 0:3], img[..., 3:4], img[..., 4:5]
        if background is not None:
            rgb = rgb + (1.0 - alpha) * background.to(rgb)
    radii = proj.extents.amax(dim=-1)  # [C,N]
    return RenderOutput(  # its depth (normalised by alpha) is computed when read
        rgb=rgb,
        alpha=alpha,
        depth_expected=depth_expected,
        means2d=means2d,
        radii=radii,
        depths=proj.depths,
    )


def blur_log_peak(sample: GaussianSample, blurred_conics: Tensor, cam_from_world: Tensor, K: Tensor, W: int, H: int,
                  near: float, far: float, eps2d: float, backend: str | None = None) -> Tensor:
    """[C,N] ``_blur_log_peak``, by the native CPU kernel for float32 CPU tensors (``native.use_for``; the same
    float64 arithmetic in one pass per Gaussian instead of some 20 tensor ops and their graph)."""
    from uncertsplat import native

    var = sample.position_var
    if native.use_for(sample.means, blurred_conics, var, cam_from_world, K, backend=backend, strict=False,
                      dtypes=(torch.float32,)):
        return _NativeBlurPeak.apply(sample.means, blurred_conics, var, cam_from_world, K, W, H, near, far, eps2d)
    return _blur_log_peak(sample, blurred_conics, cam_from_world, K, W, H, near, far, eps2d)


class _NativeBlurPeak(torch.autograd.Function):
    """``_blur_log_peak`` by the native kernel (``native/csrc/project.cpp``); gradients to the means, the blurred
    conics and the position variances, none to the cameras (as the trainer uses it)."""

    @staticmethod
    def forward(ctx, means, conics, var, cam_from_world, K, W, H, near, far, eps2d):
        from uncertsplat import native

        means, conics, var, cams, Ks = (t.detach().contiguous() for t in (means, conics, var, cam_from_world, K))
        C, N = cams.shape[0], means.shape[0]
        out = means.new_empty(C, N)
        native.library().us_blur_peak_forward_f32(
            C, N, means.data_ptr(), conics.data_ptr(), var.data_ptr(), cams.data_ptr(), Ks.data_ptr(), W, H, near,
            far, eps2d, out.data_ptr(), native.kernel_threads())
        ctx.save_for_backward(means, conics, var, cams, Ks)
        ctx.args = (W, H, near, far, eps2d)
        return out

    @staticmethod
    def backward(ctx, g_out):
        from uncertsplat import native

        means, conics, var, cams, Ks = ctx.saved_tensors
        W, H, near, far, eps2d = ctx.args
        C, N = cams.shape[0], means.shape[0]
        g_out = g_out.contiguous()
        g_means, g_conics, g_var = torch.empty_like(means), torch.empty_like(conics), torch.empty_like(var)
        native.library().us_blur_peak_backward_f32(
            C, N, means.data_ptr(), conics.data_ptr(), var.data_ptr(), cams.data_ptr(), Ks.data_ptr(), W, H, near,
            far, eps2d, g_out.data_ptr(), g_means.data_ptr(), g_conics.data_ptr(), g_var.data_ptr(),
            native.kernel_threads())
        return g_means, g_conics, g_var, None, None, None, None, None, None, None


def _blur_log_peak(sample: GaussianSample, blurred_conics: Tensor, cam_from_world: Tensor, K: Tensor, W: int, H: int,
                   near: float, far: float, eps2d: float) -> Tensor:
    """[C,N] log of the peak-height factor sqrt(det Sigma2d / det Sigma2d') of ``sample.position_var``'s blur.

    Convolving a 2D Gaussian with another keeps its integral and lowers its peak by the square root of the
    determinant ratio. Both covariances include the screen-space dilation, so a blur far below a pixel
    changes nothing (a 3D estimate of the same ratio would dim sub-pixel axes for no visible blur). At most 0:
    blurring never brightens.

    The sharp covariance needs no second projection: the blur is isotropic in 3D and the camera's rotation keeps
    it so, hence Sigma2d' = J R (Sigma + v I) R^T J^T + eps I = Sigma2d + v J J^T, with J the projection's
    Jacobian at the mean (the same clamped view angle as ``project_gaussians``). Sigma2d' is the inverse of the
    blurred conic; the 2x2 algebra runs in float64, since Sigma2d' - v J J^T cancels when the blur dominates.
    """
    f64 = torch.float64
    R, t = cam_from_world[:, :3, :3].to(f64), cam_from_world[:, :3, 3].to(f64)
    p = torch.einsum("cij,nj->cni", R, sample.means.to(f64)) + t[:, None, :]  # [C,N,3]
    x, y, z = p.unbind(-1)
    inside = (z > near) & (z < far)
    zs = torch.where(inside, z, torch.ones_like(z))
    K64 = K.to(f64)
    fx, fy = K64[:, 0, 0, None], K64[:, 1, 1, None]  # [C,1]
    cx, cy = K64[:, 0, 2, None], K64[:, 1, 2, None]
    uc, vc = clamped_view_angle(x / zs, y / zs, fx, fy, cx, cy, W, H)
    iz2 = 1.0 / (zs * zs)
    jxx, jxy, jyy = fx * fx * iz2 * (1 + uc * uc), fx * fy * iz2 * uc * vc, fy * fy * iz2 * (1 + vc * vc)  # J J^T
    a, b, c = blurred_conics.to(f64).unbind(-1)
    det_conic = a * c - b * b  # 1 / det Sigma2d'
    ok = inside & (det_conic > torch.finfo(blurred_conics.dtype).tiny)
    dc = torch.where(ok, det_conic, torch.ones_like(det_conic))  # culled: harmless values, no inf in the graph
    var = sample.position_var.to(f64).clamp_min(0.0)[None, :]  # [1,N]
    sxx, sxy, syy = c / dc - var * jxx, -b / dc - var * jxy, a / dc - var * jyy  # Sigma2d (sharp)
    # Sigma2d >= eps I, so det >= eps^2: the clamp only catches the cancellation's rounding
    det_sharp = (sxx * syy - sxy * sxy).clamp_min(eps2d * eps2d)
    log_ratio = (0.5 * (torch.log(det_sharp) + torch.log(dc))).clamp_max(0.0)
    return torch.where(ok, log_ratio, torch.zeros_like(log_ratio)).to(blurred_conics.dtype)
