"""Per-view images for the report: the evaluate stage's float maps and the ground-truth image.

``RUN/eval/maps/{image}.exr`` holds named float channels (``rgb_mean.R/G/B``, ``rgb_std.R/G/B`` or a
single ``rgb_std``, ``depth_mean``, ``depth_std``; other spellings are tolerated). The GT image comes
from a ``{image}_gt.png`` preview when the evaluate stage wrote one, else from the scene's images folder.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

_SUFFIX_ORDER = {"r": 0, "x": 0, "g": 1, "y": 1, "b": 2, "z": 2, "0": 0, "1": 1, "2": 2}


@dataclass
class ViewMaps:
    """Float maps of one view ([H,W,3] or [H,W]; None when not available)."""

    name: str
    gt: np.ndarray | None = None  # [H,W,3] in [0,1]
    rgb_mean: np.ndarray | None = None  # [H,W,3]
    rgb_std: np.ndarray | None = None  # [H,W] (mean over channels) or [H,W,3]
    depth_mean: np.ndarray | None = None  # [H,W]
    depth_std: np.ndarray | None = None  # [H,W]
    error: np.ndarray | None = None  # [H,W] mean absolute RGB error
    note: str = ""

    @property
    def rgb_std_gray(self) -> np.ndarray | None:
        """[H,W] std averaged over the colour channels (what the error is compared with)."""
        if self.rgb_std is None:
            return None
        return self.rgb_std.mean(axis=-1) if self.rgb_std.ndim == 3 else self.rgb_std


def channel_group(channels: dict[str, np.ndarray], base: str) -> np.ndarray | None:
    """[H,W,C] (C = 3) or [H,W] for the channels called ``base``, ``base.R``.., ``base_r``.., ``base.Z``."""
    if base in channels:
        return channels[base]
    members = []
    for name, arr in channels.items():
        for sep in (".", "_"):
            if name.lower().startswith(base.lower() + sep):
                suffix = name[len(base) + 1:].lower()
                if suffix in _SUFFIX_ORDER:
                    members.append((_SUFFIX_ORDER[suffix], suffix, arr))
    if not members:
        return None
    members.sort(key=lambda t: t[0])
    if len(members) == 1:
        return members[0][2]
    if len(members) >= 3 and {m[0] for m in members} >= {0, 1, 2}:
        by = {m[0]: m[2] for m in members}
        return np.stack([by[0], by[1], by[2]], axis=-1)
    return np.mean(np.stack([m[2] for m in members], axis=-1), axis=-1)


def _first_group(channels: dict[str, np.ndarray], bases: tuple[str, ...]) -> np.ndarray | None:
    for b in bases:
        g = channel_group(channels, b)
        if g is not None:
            return g
    return None


def map_file(maps_dir: Path, name: str, suffix: str) -> Path | None:
    """``maps_dir/{name}{suffix}`` or ``maps_dir/{stem}{suffix}`` (image names may keep their extension)."""
    stem = Path(name).stem
    flat = str(Path(name).with_suffix("")).replace("/", "__")  # evaluate flattens sub-folders with "__"
    for base in (flat, stem, name):
        p = maps_dir / f"{base}{suffix}"
        if p.is_file():
            return p
    return None


def list_map_views(maps_dir: Path) -> list[str]:
    """Image names for which an EXR exists (used when metrics.json is absent)."""
    if not maps_dir.is_dir():
        return []
    return sorted(p.stem for p in maps_dir.glob("*.exr"))


def _find_gt(name: str, maps_dir: Path, scene: Path | None) -> Path | None:
    for suffix in ("_gt.png", "_target.png", "_image.png"):
        p = map_file(maps_dir, name, suffix)
        if p is not None:
            return p
    if scene is None:
        return None
    stem = Path(name).stem
    for folder in (scene / "images", scene, scene / "test", scene / "train", scene / "val"):
        if not folder.is_dir():
            continue
        direct = folder / name
        if direct.is_file():
            return direct
        for ext in (".png", ".jpg", ".jpeg", ".JPG", ".PNG", ".exr", ".tif", ".tiff"):
            p = folder / f"{stem}{ext}"
            if p.is_file():
                return p
    return None


def _fit(arr: np.ndarray | None, h: int, w: int) -> np.ndarray | None:
    """Resize ``arr`` to (h, w) when it differs (a GT photo at full size vs maps at the training size)."""
    if arr is None or arr.shape[:2] == (h, w):
        return arr
    from uncertsplat.io.images import resize_image

    return resize_image(arr, w, h)


def load_view(name: str, maps_dir: Path, scene: Path | None, background=(0.0, 0.0, 0.0)) -> ViewMaps:
    """Read the maps and GT of one view; missing parts stay None and ``note`` says what is missing."""
    from uncertsplat.errors import UserError
    from uncertsplat.io.images import read_exr, read_image

    view = ViewMaps(name=name)
    missing = []
    exr = map_file(maps_dir, name, ".exr")
    channels: dict[str, np.ndarray] = {}
    if exr is not None:
        try:
            channels = read_exr(exr)
        except UserError as err:
            missing.append(f"maps unreadable ({err.message})")
    else:
        # Fallback: one .npy per quantity, e.g. {image}_rgb_std.npy.
        for key in ("rgb_mean", "rgb_std", "depth_mean", "depth_std"):
            p = map_file(maps_dir, name, f"_{key}.npy")
            if p is not None:
                try:
                    a = np.load(p)
                    channels[key] = a[..., 0] if a.ndim == 3 and a.shape[-1] == 1 else a
                except (OSError, ValueError):
                    pass
        if not channels:
            missing.append("no float maps (eval/maps/*.exr)")
    view.rgb_mean = _first_group(channels, ("rgb_mean", "mean", "rgb", "color_mean"))
    if view.rgb_mean is not None and view.rgb_mean.ndim == 2:
        view.rgb_mean = np.repeat(view.rgb_mean[..., None], 3, axis=-1)
    view.rgb_std = _first_group(channels, ("rgb_std", "std", "color_std"))
    view.depth_mean = _first_group(channels, ("depth_mean", "depth"))
    view.depth_std = _first_group(channels, ("depth_std",))
    for a in ("depth_mean", "depth_std"):
        v = getattr(view, a)
        if v is not None and v.ndim == 3:
            setattr(view, a, v.mean(axis=-1))
    err_ch = _first_group(channels, ("error", "abs_error", "rgb_error"))

    ref = next((a for a in (view.rgb_mean, view.rgb_std, view.depth_std) if a is not None), None)
    gt_path = _find_gt(name, maps_dir, scene)
    if gt_path is not None:
        try:
            gt = read_image(gt_path, background=background)
            view.gt = _fit(gt, *ref.shape[:2]) if ref is not None else gt
        except UserError as err:
            missing.append(f"GT image unreadable ({err.message})")
    else:
        missing.append("GT image not found")
    if err_ch is not None:
        view.error = err_ch.mean(axis=-1) if err_ch.ndim == 3 else err_ch
    elif view.gt is not None and view.rgb_mean is not None and view.gt.shape == view.rgb_mean.shape:
        view.error = np.abs(np.clip(view.rgb_mean, 0.0, 1.0) - view.gt).mean(axis=-1)  # [H,W]
    view.note = "; ".join(missing)
    return view
