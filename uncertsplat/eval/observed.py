"""Which pixels of a view show surface that some training view saw: labels for epistemic uncertainty.

A model can only know what its training views observed. To measure whether a predicted uncertainty finds
the parts of a scene no training view saw, every pixel of a held-out view is labelled from ground-truth
depth: its surface point (the pixel-centre ray at the GT depth) is *observed* when it projects inside at
least one training view, in front of that camera, and is not hidden there by nearer surface (the training
view's GT depth at that pixel agrees with the point's depth within a relative tolerance).

Pure tensors: cameras are ``cam_from_world`` [4,4] and ``K`` [3,3] (OpenCV axes, pixel centres at
integer + 0.5, see ``uncertsplat.conventions``); depth is camera z, 0 where there is no surface.
"""

from __future__ import annotations

import torch
from torch import Tensor

from uncertsplat.render.project import project_points, unproject


def observed_mask(depth: Tensor, cam_from_world: Tensor, K: Tensor, train_depths: Tensor,
                  train_cam_from_world: Tensor, train_K: Tensor, *, rel_tol: float = 0.02) -> tuple[Tensor, Tensor]:
    """Label the pixels of one view as observed by the training views (see the module docstring).

    Args:
        depth: [H,W] GT depth of the view (camera z; 0 or non-finite = no surface).
        cam_from_world, K: [4,4], [3,3] of the view.
        train_depths: [T,H',W'] GT depth of the training views (same convention).
        train_cam_from_world, train_K: [T,4,4], [T,3,3] (or [3,3] shared).
        rel_tol: a surface point counts as visible in a training view when its depth there is within
            ``rel_tol`` x its depth of the training view's GT depth at the pixel it lands in (nearest pixel).

    Returns:
        (observed [H,W] bool, valid [H,W] bool): ``valid`` marks pixels with surface (finite depth > 0);
        ``observed`` is False wherever ``valid`` is False.

    Raises:
        ValueError: on shapes that do not fit or a negative tolerance.
    """
    if depth.ndim != 2 or train_depths.ndim != 3:
        raise ValueError(f"depth must be [H,W] and train_depths [T,H,W], got {tuple(depth.shape)} and "
                         f"{tuple(train_depths.shape)}")
    t = train_depths.shape[0]
    if train_cam_from_world.shape != (t, 4, 4):
        raise ValueError(f"train_cam_from_world must be [{t},4,4], got {tuple(train_cam_from_world.shape)}")
    if rel_tol < 0:
        raise ValueError(f"rel_tol must be >= 0, got {rel_tol}")
    train_K = train_K.expand(t, 3, 3) if train_K.ndim == 2 else train_K
    dt = torch.float64  # projections of far points at large resolutions need more than float32
    depth = depth.to(dt)
    valid = torch.isfinite(depth) & (depth > 0)
    points = unproject(torch.where(valid, depth, torch.zeros_like(depth)), cam_from_world, K)[valid]  # [V,3]
    seen = torch.zeros(points.shape[0], dtype=torch.bool, device=depth.device)
    th, tw = train_depths.shape[1:]
    for i in range(t):
        uv, z = project_points(points, train_cam_from_world[i], train_K[i])  # [V,2], [V] in training camera i
        front = z > 1e-9
        col, row = torch.floor(uv[:, 0]).long(), torch.floor(uv[:, 1]).long()
        inside = front & (col >= 0) & (col < tw) & (row >= 0) & (row < th)
        d = torch.zeros_like(z)
        d[inside] = train_depths[i].to(dt)[row[inside], col[inside]]
        ok = torch.isfinite(d) & (d > 0)
        seen |= inside & ok & ((z - d).abs() <= rel_tol * z)
    observed = torch.zeros_like(valid)
    observed[valid] = seen
    return observed, valid


__all__ = ["observed_mask"]
