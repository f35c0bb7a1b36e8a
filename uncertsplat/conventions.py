"""Conventions used everywhere in uncertsplat.

Cameras
    OpenCV camera frame: x right, y down, z forward. Rigid transforms are named ``a_from_b`` and map
    points from frame ``b`` to frame ``a`` (``cam_from_world`` [4,4] maps world points to camera
    points), as in pycolmap. Intrinsics ``K`` [3,3] map camera points to pixels; pixel centres are at
    integer + 0.5 (the top-left pixel's centre is (0.5, 0.5)).

Gaussians
    Quaternions are wxyz. On disk and in the optimiser, scales are stored as log-scales and opacities as
    logits (the 3DGS PLY layout). A ``GaussianSample`` holds *activated* values ready to render: linear
    scales, opacities in [0, 1], normalised-or-not quaternions (the renderer normalises).

Images and depth
    Images are float32 HWC in [0, 1], linear in the file's encoding (no colour management). Depth is the
    camera-space z of the surface. A rendered depth is alpha-normalised (sum w_i z_i / sum w_i) where
    alpha > 0, and 0 where nothing was hit; the "expected" depth is sum w_i z_i (not normalised).

Shapes
    Shapes in comments use capital single letters: C cameras, N Gaussians, H height, W width,
    B SH bases ((degree + 1) ** 2), K offset-table entries, P posterior carriers, S samples.

Randomness
    Randomness only through an explicit ``torch.Generator`` argument; no property draws random numbers.

Devices
    No device literals in the library. The device comes from the input tensors; the CLI chooses it once
    (``--device auto|cpu|cuda``).
"""

from pathlib import Path

NO_SURFACE_DEPTH = 1e9
"""GT depths at or beyond this are "no surface" (Blender writes 1e10 where a ray meets nothing) and count as invalid:
left in, one such pixel made a view's depth RMSE 4e8."""


ENSEMBLE_MEMBERS = "members"
"""The folder of an ensemble run that holds its members (``ensemble_member_dir``)."""


def ensemble_member_dir(run_dir: str | Path, i: int) -> Path:
    """Where an ensemble run keeps its member ``i``: ``RUN/members/member_i``, a run of its own (``train`` writes it,
    ``report`` reads its log and summary)."""
    return Path(run_dir) / ENSEMBLE_MEMBERS / f"member_{i}"
