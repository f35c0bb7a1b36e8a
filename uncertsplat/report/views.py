"""Per-view images for the report, read exactly as ``evaluate`` writes them (``stages/evaluate.py`` through ``io.maps``).

For an image ``name`` of ``EvalReport.image_names``, ``RUN/eval/maps/{map_stem(name)}.exr`` holds the
float channels ``EXR_CHANNELS`` (``rgb_mean.R/G/B``, ``rgb_std.R/G/B``, ``depth_mean.Z``, ``depth_std.Z``)
and ``{stem}_gt.png`` the ground-truth image at the same size; maps written since 2026-11-29 also hold ``alpha.A`` (the
samples' mean opacity), which tells the pixels without a surface (``ViewMaps.no_surface``). The absolute error is
recomputed from the two, as ``evaluate`` does for its ``_error.png`` preview. The depths are in the run's normalised units; the header's
``uncertsplat:depth_to_source`` (or, in maps without it, the run's scene.json) gives the factor to the scene's own
units, kept in ``ViewMaps.depth_to_source`` for the figures to label their lengths truthfully. A missing or unreadable file, or an EXR without
one of the channels, leaves the view's panels out with a note naming the file.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from uncertsplat.errors import UserError
from uncertsplat.io.maps import EXR_ALPHA_CHANNEL, EXR_CHANNELS, EXR_DEPTH_TO_SOURCE, map_stem

GT_SUFFIX = "_gt.png"
SURFACE_MIN_ALPHA = 0.5
"""A pixel whose samples' mean opacity (``EXR_ALPHA_CHANNEL``) is below this holds no surface: its depth is mostly the
empty ray's 0 (README, "mask by alpha"); the threshold ``uncertainty.consistency.MIN_ALPHA`` and evaluate's empty-view
note use (not imported: that module pulls in torch)."""


@dataclass
class ViewMaps:
    """Float maps of one view (None when not available)."""

    name: str
    gt: np.ndarray | None = None  # [H,W,3] in [0,1]
    rgb_mean: np.ndarray | None = None  # [H,W,3]
    rgb_std: np.ndarray | None = None  # [H,W,3]
    depth_mean: np.ndarray | None = None  # [H,W]
    depth_std: np.ndarray | None = None  # [H,W]
    alpha: np.ndarray | None = None  # [H,W] the samples' mean opacity (None: maps written before it)
    error: np.ndarray | None = None  # [H,W] mean absolute RGB error
    note: str = ""
    depth_to_source: float | None = None
    """Factor from the maps' normalised depth units to the scene's own (None: unknown, shown in the run's units)."""

    @property
    def rgb_std_gray(self) -> np.ndarray | None:
        """[H,W] std averaged over the colour channels (what the error is compared with)."""
        return None if self.rgb_std is None else self.rgb_std.mean(axis=-1)

    @property
    def no_surface(self) -> np.ndarray | None:
        """[H,W] bool: pixels where the model holds no surface, whose depth 0 is not a distance: depth not above 0, or
        a mean opacity below ``SURFACE_MIN_ALPHA`` where the maps carry it (a transparent scene's background, empty
        sky); None without a depth map."""
        if self.depth_mean is None:
            return None
        empty = ~(self.depth_mean > 0)  # NaN too: no distance to draw
        if self.alpha is not None and self.alpha.shape == empty.shape:
            empty |= self.alpha < SURFACE_MIN_ALPHA
        return empty


def exr_path(maps_dir: Path, name: str, among: Sequence[str] = ()) -> Path:
    """The EXR of view ``name`` among the evaluated views ``among`` (``map_stem``)."""
    return Path(maps_dir) / f"{map_stem(name, among)}.exr"


def gt_path(maps_dir: Path, name: str, among: Sequence[str] = ()) -> Path:
    """The GT preview of view ``name`` among the evaluated views ``among`` (``map_stem``)."""
    return Path(maps_dir) / f"{map_stem(name, among)}{GT_SUFFIX}"


def load_view(name: str, maps_dir: Path, depth_to_source: float | None = None, among: Sequence[str] = ()
              ) -> ViewMaps:
    """Read the maps and GT of one view; missing parts stay None and ``note`` says which file and why.

    ``depth_to_source``: the run's factor to the scene's units (``RunData.depth_to_source``), used when the EXR's
    header does not carry its own. ``among``: every view the evaluation wrote (``EvalReport.image_names``), which
    names the files (``map_stem``).
    """
    from uncertsplat.io.images import read_exr, read_exr_attribute, read_image

    view = ViewMaps(name=name, depth_to_source=depth_to_source)
    problems = []
    exr = exr_path(maps_dir, name, among)
    if not exr.is_file():
        problems.append(f"{exr.name} not found")
    else:
        try:
            ch = read_exr(exr)
        except UserError as err:
            problems.append(" ".join(str(err).split()))
        else:
            missing = [c for c in EXR_CHANNELS if c not in ch]
            if missing:
                problems.append(f"{exr}: channel(s) {', '.join(missing)} missing (re-run `uncertsplat evaluate`)")
            else:
                view.rgb_mean = np.stack([ch[f"rgb_mean.{c}"] for c in "RGB"], axis=-1)
                view.rgb_std = np.stack([ch[f"rgb_std.{c}"] for c in "RGB"], axis=-1)
                view.depth_mean = ch["depth_mean.Z"]
                view.depth_std = ch["depth_std.Z"]
                view.alpha = ch.get(EXR_ALPHA_CHANNEL)
                factor = read_exr_attribute(exr, EXR_DEPTH_TO_SOURCE)
                if isinstance(factor, (int, float)) and factor > 0:
                    view.depth_to_source = float(factor)
    gt = gt_path(maps_dir, name, among)
    if not gt.is_file():
        problems.append(f"{gt.name} not found")
    else:
        try:
            view.gt = read_image(gt)
        except UserError as err:
            problems.append(" ".join(str(err).split()))
    if view.gt is not None and view.rgb_mean is not None:
        if view.gt.shape == view.rgb_mean.shape:
            view.error = np.abs(np.clip(view.rgb_mean, 0.0, 1.0) - view.gt).mean(axis=-1)  # [H,W]
        else:
            problems.append(f"{gt.name} is {view.gt.shape[1]}x{view.gt.shape[0]}, the maps "
                            f"{view.rgb_mean.shape[1]}x{view.rgb_mean.shape[0]}; error map left out")
    view.note = "; ".join(problems)
    return view
