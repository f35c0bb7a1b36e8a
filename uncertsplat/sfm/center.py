"""The scene centre: the point an inward-facing camera rig looks at, or the camera centroid.

3DGS centres a scene on the centroid of its camera centres. That is harmless when sparse points place the
initial Gaussians (the centre only fixes a translation, and training does not depend on it), and it is the
only sensible point for a forward-facing capture, whose optical axes are nearly parallel. It is wrong for
the random initial points of a scene without sparse points (Blender / nerfstudio folders): on a hemisphere
rig of radius 4 the centroid lies about 2 units above the object, and a box of random points around it
misses the object. For such inward-facing rigs the centre is the least-squares point nearest to all
optical axes, ``sum_i (I - d_i d_i^T) x = sum_i (I - d_i d_i^T) c_i`` (axis directions ``d_i``, centres
``c_i``), accepted only when the rig really looks inward (see :func:`fit_optical_axes`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from uncertsplat.errors import UserError
from uncertsplat.types import Cameras

# Acceptance of the optical-axes point (see fit_optical_axes).
MIN_AXIS_SPREAD = 0.01
"""Smallest eigenvalue of mean_i (I - d_i d_i^T): the mean squared sine of the axes' angle to the worst
direction. 0 for parallel axes; ~0.01 for axes spread over +-10 degrees in one plane, 0.5-0.85 for rings and
hemispheres. Below it the point is ill-determined (forward-facing captures)."""
MIN_IN_VIEW = 0.8
"""The point must be in front of, and project inside the image of, at least this fraction of the cameras."""
MAX_LOOK_DISTANCE = 4.0
MIN_LOOK_DISTANCE = 0.05
"""The median camera depth of the point, relative to the rig radius (median camera distance from the
centroid), must lie in [MIN_LOOK_DISTANCE, MAX_LOOK_DISTANCE]: about 1 for a ring or hemisphere; large when
near-parallel axes of a forward-facing capture meet far away."""
CARVE_ROUNDS = 8
MAX_CANDIDATES = 4_000_000
"""Carving the random points (see random_points): rounds of drawing candidates, and candidates per round."""


@dataclass(frozen=True)
class OpticalAxesFit:
    """The least-squares point nearest to all optical axes, and whether the rig looks inward at it.

    Attributes:
        point: [3] float64 source coordinates; None when the axes are all parallel (singular system).
        spread: smallest eigenvalue of mean_i (I - d_i d_i^T), in [0, 2/3].
        depths: [C] float64 camera z of ``point`` (empty when ``point`` is None).
        in_view: fraction of the cameras that have ``point`` in front of them and inside their image.
        rig_radius: median distance of the camera centres from their centroid.
        inward: the rig passes every test (an inward-facing rig: the point is its centre).
        why: one sentence saying why the rig was (not) taken for inward-facing.
    """

    point: Tensor | None
    spread: float
    depths: Tensor
    in_view: float
    rig_radius: float
    inward: bool
    why: str

    @property
    def look_distance(self) -> float:
        """Median camera depth of the point (nan without a point)."""
        return float(self.depths.median()) if self.depths.numel() else math.nan


@dataclass(frozen=True)
class CenterChoice:
    """The scene centre and how it was found.

    Attributes:
        center: [3] float64 source coordinates.
        method: "optical_axes" or "camera_centroid".
        reason: one sentence (recorded in RUN/scene.json).
        fit: the optical-axes fit (also computed when the centroid is used, for the record).
    """

    center: Tensor
    method: str
    reason: str
    fit: OpticalAxesFit


def _fmt(x: Tensor) -> str:
    return "(" + ", ".join(f"{float(v):.3g}" for v in x) + ")"


def fit_optical_axes(cameras: Cameras) -> OpticalAxesFit:
    """Solve for the point nearest to all optical axes and test whether the rig faces inward at it.

    The rig is taken for inward-facing when the system is well conditioned (``spread >= MIN_AXIS_SPREAD``),
    the point is in view of at least ``MIN_IN_VIEW`` of the cameras, and its median depth is a sensible
    multiple of the rig radius (``MIN_LOOK_DISTANCE`` .. ``MAX_LOOK_DISTANCE``).
    """
    c2w = cameras.cam_from_world.double().cpu()  # [C,4,4]
    R, t = c2w[:, :3, :3], c2w[:, :3, 3]
    d = R[:, 2, :]  # [C,3] optical axes (camera +z) in world coordinates: the third row of R
    c = -(R.transpose(1, 2) @ t[..., None])[..., 0]  # [C,3] camera centres
    n = c.shape[0]
    rig_radius = float((c - c.mean(0)).norm(dim=-1).median()) if n else 0.0
    eye = torch.eye(3, dtype=torch.float64)
    P = eye - d[:, :, None] * d[:, None, :]  # [C,3,3] projectors onto the plane normal to each axis
    A = P.mean(0)  # [3,3]
    b = (P @ c[..., None]).mean(0)[:, 0]  # [3]
    spread = float(torch.linalg.eigvalsh(A)[0]) if n else 0.0
    empty = torch.zeros(0, dtype=torch.float64)
    if n < 3 or spread < 1e-9:
        why = "fewer than 3 cameras" if n < 3 else "the optical axes are parallel"
        return OpticalAxesFit(None, spread, empty, 0.0, rig_radius, False, why)
    x = torch.linalg.solve(A, b)
    pc = (R @ x[:, None])[..., 0] + t  # [C,3] the point in each camera
    z = pc[:, 2]
    K = cameras.K.double().cpu()
    u = K[:, 0, 0] * pc[:, 0] / z.clamp_min(1e-12) + K[:, 0, 2]
    v = K[:, 1, 1] * pc[:, 1] / z.clamp_min(1e-12) + K[:, 1, 2]
    seen = (z > 0) & (u >= 0) & (u <= cameras.width) & (v >= 0) & (v <= cameras.height)
    in_view = float(seen.double().mean())
    look = float(z.median())
    ratio = look / rig_radius if rig_radius > 1e-12 else math.inf
    if spread < MIN_AXIS_SPREAD:
        inward, why = False, (f"near-parallel optical axes (spread {spread:.2g} < {MIN_AXIS_SPREAD}): a "
                              "forward-facing capture")
    elif in_view < MIN_IN_VIEW:
        inward, why = False, (f"the point nearest to the optical axes is in view of only {in_view:.0%} of the "
                              f"cameras (< {MIN_IN_VIEW:.0%})")
    elif not (MIN_LOOK_DISTANCE <= ratio <= MAX_LOOK_DISTANCE):
        inward, why = False, (f"the optical axes meet at {ratio:.3g} x the rig radius from the cameras (outside "
                              f"{MIN_LOOK_DISTANCE}..{MAX_LOOK_DISTANCE})")
    else:
        inward, why = True, (f"inward-facing rig: the optical axes meet at {_fmt(x)}, {look:.3g} in front of the "
                             f"cameras ({ratio:.2f} x the rig radius), in view of {in_view:.0%} of them")
    return OpticalAxesFit(x, spread, z, in_view, rig_radius, inward, why)


def choose_center(cameras: Cameras, has_points: bool, mode: str = "auto", where=None) -> CenterChoice:
    """The scene centre for ``SceneConfig.center`` = ``mode``.

    auto: the optical-axes point for an inward-facing rig without sparse points, else the camera centroid
    (which keeps COLMAP scenes and forward-facing captures exactly as before). optical_axes: that point
    whenever the axes are not all parallel. camera_centroid: always the centroid.

    Raises:
        UserError: ``mode = "optical_axes"`` for cameras whose axes are parallel (naming ``where``).
    """
    fit = fit_optical_axes(cameras)
    centroid = cameras.centers.double().cpu().mean(0)
    if mode == "camera_centroid":
        return CenterChoice(centroid, "camera_centroid", "requested (scene.center = camera_centroid)", fit)
    if mode == "optical_axes":
        if fit.point is None:
            raise UserError(f"scene.center = optical_axes needs cameras whose optical axes meet ({fit.why})",
                            path=where, hint="Use scene.center = auto or camera_centroid.")
        return CenterChoice(fit.point, "optical_axes", f"requested (scene.center = optical_axes); {fit.why}", fit)
    if mode != "auto":
        raise ValueError(f"unknown centre mode {mode!r}")
    if has_points:
        note = "the rig faces inward" if fit.inward else "the rig is not inward-facing"
        return CenterChoice(centroid, "camera_centroid",
                            f"the scene has sparse points, which place the initial Gaussians ({note})", fit)
    if fit.inward:
        return CenterChoice(fit.point, "optical_axes", fit.why, fit)
    return CenterChoice(centroid, "camera_centroid", f"not an inward-facing rig: {fit.why}", fit)


def random_points(cameras: Cameras, choice: CenterChoice, n: int, generator: torch.Generator,
                  carve: tuple[Cameras, Sequence[Tensor | None]] | None = None) -> tuple[Tensor, Tensor, str]:
    """``n`` random initial points [n,3] (float64, source coordinates) with colours [n,3], and a description.

    Around an optical-axes centre the points fill a cube that every camera sees: its half side is the
    half-extent of the median view at the centre's depth along its narrower side (median depth x tan of
    the narrower half field of view; 1.44 for the NeRF-synthetic rig, where 3DGS uses 1.3). On the tiny
    synthetic hemisphere scene this beat the wider side's cube (which holds every object) by 2 dB after
    300 steps: the points are denser where every view constrains them. Otherwise (no inward-facing rig:
    no better guess) a box around the camera centroid spanning a third of the rig, as before.

    ``carve`` = (views, foreground masks, one per view): keep only the points that every view which sees them
    projects onto its foreground (:func:`carve_points`, the visual hull), drawing more candidates in the box
    until ``n`` survive (at most ``CARVE_ROUNDS`` rounds of ``MAX_CANDIDATES``; fewer points when the hull is
    tiny). When no candidate survives the points are not carved (the description says so).
    """
    if choice.method == "optical_axes":
        K = cameras.K.double().cpu()
        tan_half = torch.minimum(cameras.width / (2 * K[:, 0, 0]), cameras.height / (2 * K[:, 1, 1]))  # [C]
        half = torch.full((3,), abs(choice.fit.look_distance) * float(tan_half.median()), dtype=torch.float64)
        mid = choice.center
        what = f"a cube of half side {float(half[0]):.3g} around the optical-axes centre"
    else:
        centers = cameras.centers.double().cpu()
        mid = centers.mean(0)
        half = (centers.max(0).values - centers.min(0).values) / 6.0
        what = "a box spanning a third of the camera rig around the camera centroid"

    def draw(m: int) -> Tensor:
        return mid + (torch.rand(m, 3, generator=generator, dtype=torch.float64) * 2 - 1) * half

    if carve is None:
        points = draw(n)
        rgb = torch.rand(n, 3, generator=generator)
        return points, rgb, f"{n} random points in {what}"
    views, masks = carve
    judged = sum(m is not None for m in masks)
    kept: list[Tensor] = []
    have = tried = 0
    for _ in range(CARVE_ROUNDS):
        rate = have / tried if tried else 1.0
        m = min(MAX_CANDIDATES, max(n - have, math.ceil((n - have) / max(rate, 1e-4) * 1.2)))
        cand = draw(m)
        cand = cand[carve_points(cand, views, masks)]
        tried += m
        have += cand.shape[0]
        kept.append(cand)
        if have >= n:
            break
    points = torch.cat(kept)[:n]
    if points.shape[0] == 0:
        points = draw(n)
        rgb = torch.rand(n, 3, generator=generator)
        return points, rgb, (f"{n} random points in {what} (not carved: no candidate fell inside the alpha "
                             f"masks of all {judged} views that see it)")
    rgb = torch.rand(points.shape[0], 3, generator=generator)
    return points, rgb, (f"{points.shape[0]} random points in {what}, carved with the alpha masks of {judged} "
                         f"views ({have} of {tried} candidates fell inside them)")


def carve_points(points: Tensor, cameras: Cameras, masks: Sequence[Tensor | None]) -> Tensor:
    """Space carving: which points [N,3] lie inside the foreground of every view that sees them.

    ``masks[i]`` is view ``i``'s foreground [h,w] bool at any resolution (its intrinsics are scaled by
    h / height and w / width; pixel ``(r, c)`` covers ``[c, c+1) x [r, r+1)``), or None (the view judges
    nothing). A point behind a camera or projecting outside its image is not judged by it; a point that no
    view with a mask sees goes too (no image supports it).

    Returns:
        [N] bool, True for the points that survive.
    """
    idx = torch.arange(points.shape[0])
    seen_by = torch.zeros(points.shape[0], dtype=torch.bool)  # indexed like idx
    pts = points.double().cpu()  # source coordinates, which may be far from the origin
    for i, mask in enumerate(masks):
        if mask is None or idx.numel() == 0:
            continue
        h, w = mask.shape
        M = cameras.cam_from_world[i].double().cpu()
        K = cameras.K[i].double().cpu()
        p = pts[idx] @ M[:3, :3].T + M[:3, 3]
        z = p[:, 2]
        zs = z.clamp_min(1e-12)
        u = (K[0, 0] * p[:, 0] / zs + K[0, 2]) * (w / cameras.width)
        v = (K[1, 1] * p[:, 1] / zs + K[1, 2]) * (h / cameras.height)
        seen = (z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        fg = mask[torch.where(seen, v, 0).long(), torch.where(seen, u, 0).long()]
        stay = ~(seen & ~fg)
        idx, seen_by = idx[stay], (seen_by | seen)[stay]
    keep = torch.zeros(points.shape[0], dtype=torch.bool)
    keep[idx[seen_by]] = True
    return keep
