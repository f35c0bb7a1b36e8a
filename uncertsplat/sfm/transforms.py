"""Scenes described by NeRF-style ``transforms*.json`` files: Blender (NeRF-synthetic) and nerfstudio folders.

Both formats list frames with a ``file_path`` (relative to the folder) and a camera-to-world
``transform_matrix`` [4,4] in OpenGL camera axes (x right, y up, z backward: the camera looks down -z);
we convert to OpenCV axes (``uncertsplat.conventions``) by negating the y and z columns.

Blender layout (``transforms_train.json``, ``transforms_val.json``, ``transforms_test.json``)
    ``camera_angle_x`` (horizontal field of view) gives the focal length; file paths usually lack the
    extension (``./train/r_0`` is ``train/r_0.png``). The dataset's test file is the held-out split.
    A ``points3d.ply`` beside them gives the initial points, as in 3DGS (which writes its random ones there).

nerfstudio / instant-ngp layout (one ``transforms.json``)
    Intrinsics ``fl_x fl_y cx cy w h`` (or ``camera_angle_x``) at the top level and/or per frame (a frame's
    own values win), ``camera_model`` (OPENCV or PINHOLE; fisheye and equirectangular are refused), the
    distortion ``k1 k2 k3 k4 p1 p2`` (non-zero values are refused: splatting renders pinhole images),
    ``applied_transform`` [3,4] (what ``ns-process-data`` applied to the COLMAP world; we undo it, so the
    source coordinates are COLMAP's again), ``ply_file_path`` (initial points, in the same frame as the
    poses) and ``train_filenames`` / ``val_filenames`` / ``test_filenames`` (the held-out split). With an
    integer ``scene.downscale`` = f, images are read from nerfstudio's ``images_f/`` folder when it holds
    every image at the downscaled size (instead of resizing the full-size images).

Every image must have the same size (``Cameras`` holds one size); mixed sizes are refused.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from uncertsplat.config import SceneConfig
from uncertsplat.errors import UserError
from uncertsplat.io.images import IMAGE_EXTENSIONS, read_image_size
from uncertsplat.types import Cameras

BLENDER_SPLITS = ("train", "val", "test")
DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
PINHOLE_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "PERSPECTIVE")
_UNDISTORT_HINT = ("Undistort the images first: run `uncertsplat reconstruct` on the original photos (it undistorts "
                   "to PINHOLE), or undistort the COLMAP model that `ns-process-data` made (`colmap "
                   "image_undistorter --image_path images --input_path colmap/sparse/0 --output_path ws`) and train "
                   "on that workspace.")


@dataclass(frozen=True)
class TransformsScene:
    """What a transforms file describes, in source coordinates.

    Attributes:
        cameras: sorted by image name (OpenCV axes, full image size).
        paths: one image file per camera (possibly from a downscaled folder).
        points: [P,3] initial points (P = 0 when the folder has none), points_rgb [P,3] in [0, 1].
        split: the dataset's own train/test indices, or None.
        source: what was read (for ``SceneData.source``).
        file: the transforms file the cameras come from (the folder when they come from several), for errors.
    """

    cameras: Cameras
    paths: tuple[Path, ...]
    points: Tensor  # [P,3]
    points_rgb: Tensor  # [P,3]
    split: dict[str, tuple[int, ...]] | None
    source: dict
    file: Path | None = None


@dataclass(frozen=True)
class _Frame:
    name: str  # image path relative to the folder: the image name
    split: str | None
    c2w_gl: np.ndarray  # [4,4] camera-to-world, OpenGL camera axes
    entry: dict  # the frame's own keys
    meta: dict  # the file's top-level keys
    file: Path  # the transforms file it comes from


# ---------------------------------------------------------------------------------------------- parsing
def _read_json(path: Path, expect: str) -> dict:
    try:
        meta = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as err:
        raise UserError(f"cannot read the transforms file ({err})", path=path,
                        hint=f"Expected the {expect} layout: {{..., \"frames\": [{{\"file_path\", "
                        "\"transform_matrix\"}, ...]}.") from None
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list):
        raise UserError("not a valid transforms file (no list of 'frames')", path=path,
                        hint=f"Expected the {expect} layout: {{..., \"frames\": [{{\"file_path\", "
                        "\"transform_matrix\"}, ...]}.")
    return meta


_GUESSED_EXTENSIONS = (".png", ".jpg", ".jpeg", ".exr")
"""Tried, in this order and in any case, for a ``file_path`` without an image extension (``./train/r_0``)."""


def image_name(root: Path, file_path: str) -> str:
    """The image's path relative to ``root``: ``file_path``, or with its extension found on disk (``./train/r_0`` ->
    ``train/r_0.png``, ``images/IMG_1`` -> ``images/IMG_1.JPG``); unchanged (no extension) when no such file exists
    (``_missing_image`` says what was looked for)."""
    rel = str(file_path).replace("\\", "/").removeprefix("./")
    if Path(rel).suffix.lower() in IMAGE_EXTENSIONS:
        return rel
    for ext in _GUESSED_EXTENSIONS:  # the common spellings first: no folder listing for most datasets
        for e in (ext, ext.upper()):
            if (root / (rel + e)).is_file():
                return rel + e
    # any other case (.Jpg): compared with the folder's own names, as a case-sensitive file system stores them
    folder, base = (root / rel).parent, Path(rel).name
    if folder.is_dir():
        found = {p.name[len(base):].lower(): p.name[len(base):] for p in folder.iterdir()
                 if p.name.startswith(base + ".") and p.is_file()}  # extension (as on disk) by its lower case
        for ext in _GUESSED_EXTENSIONS:
            if ext in found:
                return rel + found[ext]
    return rel


def _missing_image(name: str, root: Path, file: Path) -> UserError:
    """The error for a frame whose image file does not exist (naming what was looked for)."""
    if Path(name).suffix.lower() in IMAGE_EXTENSIONS:
        return UserError(f"image '{name}' named in {file.name} is missing", path=root / name,
                         hint="Check that the dataset was extracted completely.")
    tried = ", ".join(_GUESSED_EXTENSIONS)
    folder, base = (root / name).parent, Path(name).name
    others = sorted(p.name for p in folder.iterdir() if p.name.startswith(base + ".")) if folder.is_dir() else []
    return UserError(f"no image for '{name}' named in {file.name}: its file_path has no image extension and no file "
                     f"'{name}' with {tried} (in any case) exists"
                     + (f" (there is {', '.join(others[:3])})" if others else ""), path=root / name,
                     hint="Check that the dataset was extracted completely, or write file_path with the image's "
                          "extension.")


def _frames(root: Path, meta: dict, path: Path, split: str | None) -> list[_Frame]:
    out = []
    layout = ('{"file_path": "./train/r_0", "transform_matrix": [[...], [...], [...], [0, 0, 0, 1]]}: its image and '
              "its camera-to-world pose")
    for i, fr in enumerate(meta["frames"]):
        # (a key left out was a raw "KeyError('transform_matrix')": the frame, the key and what a frame holds instead)
        if not isinstance(fr, dict):
            raise UserError(f"frames[{i}] is not an object of a frame's keys", path=path,
                            hint=f"Each frame is {layout}.")
        which = f"frames[{i}]" + (f" ('{fr['file_path']}')" if isinstance(fr.get("file_path"), str) else "")
        missing = [k for k in ("file_path", "transform_matrix") if k not in fr]
        if missing:
            raise UserError(f"{which} has no '{missing[0]}'"
                            + (f" (nor '{missing[1]}')" if len(missing) > 1 else ""), path=path,
                            hint=f"Each frame holds {layout}; add it, or remove the frame.")
        try:
            c2w = np.asarray(fr["transform_matrix"], dtype=np.float64)
            name = image_name(root, fr["file_path"])
        except (TypeError, ValueError) as err:
            raise UserError(f"{which}: 'file_path' must be a text and 'transform_matrix' a matrix of "
                            f"numbers ({err})", path=path, hint=f"Each frame holds {layout}.") from None
        if c2w.shape == (3, 4):
            c2w = np.concatenate([c2w, [[0.0, 0.0, 0.0, 1.0]]], 0)
        if c2w.shape != (4, 4) or not np.all(np.isfinite(c2w)):
            raise UserError(f"frame {i} ('{name}'): transform_matrix must be a finite 4x4 (or 3x4) matrix, "
                            f"got shape {c2w.shape}", path=path)
        R = c2w[:3, :3]
        if np.abs(R.T @ R - np.eye(3)).max() > 1e-3 or np.linalg.det(R) <= 0:
            raise UserError(f"frame {i} ('{name}'): transform_matrix is not a rigid camera-to-world pose "
                            "(its 3x3 part is not a rotation)", path=path,
                            hint="Write the pose without scale (a rotation and a translation).")
        out.append(_Frame(name, split, c2w, fr, meta, path))
    return out


def _value(fr: _Frame, key: str):
    """A frame's own value of ``key``, else the file's top-level value, else None."""
    v = fr.entry.get(key)
    return fr.meta.get(key) if v is None else v


def _number(fr: _Frame, key: str) -> float | None:
    """A frame's (else the file's) value of ``key`` as a float, None when absent; UserError naming the key when it is
    not a number (``"k1": "abc"`` was a ValueError traceback)."""
    v = _value(fr, key)
    if v is None:
        return None
    try:
        if isinstance(v, bool):  # float(True) is 1.0: a JSON true is no number
            raise TypeError
        return float(v)
    except (TypeError, ValueError):
        where = "frame's" if fr.entry.get(key) is not None else "file's"
        raise UserError(f"'{key}' must be a number, got {json.dumps(v)} (the {where} value, frame '{fr.name}')",
                        path=fr.file, hint=f"Write {key} as a number, or remove it.") from None


def _check_model(fr: _Frame) -> None:
    model = _value(fr, "camera_model")
    if model is not None and str(model).upper() not in PINHOLE_MODELS:
        raise UserError(f"frame '{fr.name}' uses the camera model {model}, which is not a pinhole camera",
                        path=fr.file, hint=_UNDISTORT_HINT)
    dist = {k: _number(fr, k) for k in DISTORTION_KEYS}
    bad = {k: v for k, v in dist.items() if v is not None and v != 0.0}
    if bad:
        raise UserError(
            f"frame '{fr.name}' has lens distortion ({', '.join(f'{k}={v:g}' for k, v in bad.items())}), which "
            "splatting cannot render", path=fr.file, hint=_UNDISTORT_HINT)


def _intrinsics(fr: _Frame, w: int, h: int) -> np.ndarray:
    """K [3,3] of a frame: fl_x / fl_y (or camera_angle_x / _y), cx / cy (default: the image centre)."""
    fx, fy = _number(fr, "fl_x"), _number(fr, "fl_y")
    focal = {}
    for key, given, side in (("camera_angle_x", fx, w), ("camera_angle_y", fy, h)):
        angle = _number(fr, key) if given is None else None  # (an angle beside fl_x / fl_y is not read)
        if angle is not None and not 0.0 < angle < math.pi:  # (degrees read as radians: 40 trained at 132 degrees)
            hint = (f"Write it in radians: {angle:g} degrees is {math.radians(angle):.4g}." if math.pi <= angle < 180.0
                    else "Write the field of view in radians, between 0 and pi (a pinhole camera sees less than "
                         "180 degrees).")
            raise UserError(f"frame '{fr.name}': {key} = {angle:g} is no field of view in radians (0 to pi)",
                            path=fr.file, hint=hint)
        focal[key] = given if angle is None else 0.5 * side / math.tan(0.5 * angle)
    fx, fy = focal["camera_angle_x"], focal["camera_angle_y"]
    if fx is None:
        raise UserError(f"no focal length for frame '{fr.name}' (fl_x or camera_angle_x)", path=fr.file,
                        hint="Add camera_angle_x (radians) or fl_x (pixels) to the file or the frame.")
    fy = fx if fy is None else fy
    cx, cy = _number(fr, "cx"), _number(fr, "cy")
    cx = w / 2.0 if cx is None else cx
    cy = h / 2.0 if cy is None else cy
    if not all(math.isfinite(v) for v in (fx, fy, cx, cy)) or fx <= 0 or fy <= 0:
        raise UserError(f"frame '{fr.name}': invalid intrinsics fx={fx:g} fy={fy:g} cx={cx:g} cy={cy:g}",
                        path=fr.file)
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def _size(fr: _Frame, root: Path) -> tuple[int, int]:
    """(w, h) of a frame: its ``w`` / ``h`` keys, else the image's own size."""
    w, h = _number(fr, "w"), _number(fr, "h")
    if w is not None and h is not None:
        for key, v in (("w", w), ("h", h)):
            if not (math.isfinite(v) and v >= 1 and v.is_integer()):
                raise UserError(f"'{key}' must be a whole number of pixels, got {v:g} (frame '{fr.name}')",
                                path=fr.file, hint=f"Write the image {'width' if key == 'w' else 'height'} as an "
                                "integer, or remove w and h (the images' own size is read).")
        return int(w), int(h)
    p = root / fr.name
    if not p.is_file():
        raise _missing_image(fr.name, root, fr.file)
    return read_image_size(p)


def _cameras(root: Path, frames: list[_Frame], cfg: SceneConfig,
             downscaled: bool = False) -> tuple[Cameras, tuple[Path, ...], str]:
    """Cameras (OpenCV axes, transforms frame) and image paths of sorted frames, and the images folder used
    (``downscaled``: look for nerfstudio's ``images_f/`` folders)."""
    sizes: dict[tuple[int, int], str] = {}
    for fr in frames:
        _check_model(fr)
        sizes.setdefault(_size(fr, root), fr.name)
    if len(sizes) > 1:
        listed = ", ".join(f"{w}x{h} (e.g. '{n}')" for (w, h), n in sorted(sizes.items()))
        raise UserError(f"the frames have different image sizes: {listed}; one image size per scene is assumed",
                        path=frames[0].file,
                        hint="Resize all images (and their intrinsics) to one size, or split the frames by size "
                        "into separate scenes.")
    width, height = next(iter(sizes))
    # nerfstudio keeps downscaled copies in images_f/ (same file names): read those instead of resizing.
    paths, folder = None, "full size"
    f = cfg.downscale
    if downscaled and f > 1 and float(f).is_integer():
        small = [root / f"images_{int(f)}" / Path(fr.name).name for fr in frames]
        want = (max(1, round(width / f)), max(1, round(height / f)))
        if all(p.is_file() for p in small) and all(read_image_size(p) == want for p in small):
            paths, folder = tuple(small), f"images_{int(f)}"
    if paths is None:
        paths = tuple(root / fr.name for fr in frames)
        for fr, p in zip(frames, paths, strict=True):
            if not p.is_file():
                raise _missing_image(fr.name, root, fr.file)
            w, h = read_image_size(p)
            if (w, h) != (width, height):
                raise UserError(f"image is {w}x{h} but the transforms file says {width}x{height} "
                                "(one image size per scene is assumed)", path=p,
                                hint="Fix w / h in the transforms file, or resize the image.")
    w2c = []
    for fr in frames:
        c2w = fr.c2w_gl.copy()
        c2w[:3, 1:3] *= -1.0  # OpenGL camera axes (y up, z backward) -> OpenCV (y down, z forward)
        w2c.append(np.linalg.inv(c2w))
    K = np.stack([_intrinsics(fr, width, height) for fr in frames])
    cams = Cameras(torch.tensor(np.stack(w2c), dtype=torch.float64), torch.tensor(K, dtype=torch.float64),
                   width, height, tuple(fr.name for fr in frames))
    return cams, paths, folder


def _check_unique(frames: list[_Frame]) -> None:
    seen: dict[str, _Frame] = {}
    for fr in frames:
        if fr.name in seen:
            raise UserError(f"image '{fr.name}' is listed twice", path=fr.file,
                            hint="Each frame must name its own image file.")
        seen[fr.name] = fr


# ---------------------------------------------------------------------------------------------- Blender
def read_blender(root: Path, cfg: SceneConfig) -> TransformsScene:
    """A Blender / NeRF-synthetic folder: ``transforms_{train,val,test}.json`` (val frames train)."""
    frames: list[_Frame] = []
    for split in BLENDER_SPLITS:
        f = root / f"transforms_{split}.json"
        if f.is_file():
            frames += _frames(root, _read_json(f, "Blender (NeRF-synthetic)"), f, split)
    if not frames:
        raise UserError("the transforms files list no frames", path=root / "transforms_train.json")
    frames.sort(key=lambda fr: fr.name)
    _check_unique(frames)
    cameras, paths, folder = _cameras(root, frames, cfg)
    test = tuple(i for i, fr in enumerate(frames) if fr.split == "test")
    train = tuple(i for i, fr in enumerate(frames) if fr.split != "test")
    source = {"kind": "nerf_synthetic", "path": str(root), "images": folder}
    xyz, rgb = np.zeros((0, 3)), np.zeros((0, 3))
    if (root / "points3d.ply").is_file():  # 3DGS reads (and writes its random points to) this file
        xyz, rgb = _read_ply_points(root / "points3d.ply", "beside the transforms files (3DGS's initial points)")
        source["ply"] = "points3d.ply"
    files = {fr.file for fr in frames}
    return TransformsScene(cameras, paths, torch.tensor(xyz, dtype=torch.float64),
                           torch.tensor(rgb, dtype=torch.float32).clamp(0, 1),
                           {"train": train, "test": test} if train and test else None, source,
                           next(iter(files)) if len(files) == 1 else root)


# -------------------------------------------------------------------------------------------- nerfstudio
def _similarity(A: np.ndarray, path: Path) -> tuple[np.ndarray, float]:
    """(rotation [3,3], scale) of the 3x3 part of ``applied_transform``; UserError when it is not a similarity."""
    M = A[:3, :3]
    det = float(np.linalg.det(M))
    s = abs(det) ** (1.0 / 3.0)
    R = M / s if s > 0 else M
    if det <= 0 or np.abs(R.T @ R - np.eye(3)).max() > 1e-4:
        raise UserError("applied_transform is not a rotation with a uniform scale (it cannot be undone rigidly)",
                        path=path, hint="Remove applied_transform, or write it as [s R | t].")
    return R, s


def _read_ply_points(path: Path, what: str) -> tuple[np.ndarray, np.ndarray]:
    """xyz [P,3] and rgb [P,3] in [0, 1] of a PLY point cloud (``what``: where it comes from, for errors)."""
    from plyfile import PlyData, PlyParseError

    if not path.is_file():
        raise UserError(f"the point cloud {what} is missing", path=path,
                        hint="Restore the file, or remove ply_file_path to start from random points.")
    try:
        v = PlyData.read(str(path))["vertex"].data
        xyz = np.stack([v["x"], v["y"], v["z"]], -1).astype(np.float64)
    except (OSError, ValueError, KeyError, IndexError, PlyParseError) as err:
        # PlyParseError: a truncated or malformed file (plyfile's own errors are no ValueError)
        raise UserError(f"cannot read the point cloud {what} ({err})", path=path,
                        hint="Expected a complete PLY file with a vertex element holding x, y, z (and red, green, "
                             "blue): write it again, or remove it to start from random points.") from None
    names = v.dtype.names or ()
    if all(c in names for c in ("red", "green", "blue")):
        rgb = np.stack([v["red"], v["green"], v["blue"]], -1)
        # 8-bit colours (what nerfstudio and COLMAP write) or floats in [0, 1]
        rgb = rgb.astype(np.float64) / 255.0 if np.issubdtype(rgb.dtype, np.integer) else rgb.astype(np.float64)
    else:
        rgb = np.full_like(xyz, 0.5)
    keep = np.all(np.isfinite(xyz), -1)
    return xyz[keep], rgb[keep]


def read_nerfstudio(root: Path, cfg: SceneConfig) -> TransformsScene:
    """A nerfstudio / instant-ngp folder with one ``transforms.json``."""
    path = root / "transforms.json"
    meta = _read_json(path, "nerfstudio")
    frames = _frames(root, meta, path, None)
    if not frames:
        raise UserError("the transforms file lists no frames", path=path)
    frames.sort(key=lambda fr: fr.name)
    _check_unique(frames)
    cameras, paths, folder = _cameras(root, frames, cfg, downscaled=True)
    source: dict = {"kind": "nerfstudio", "path": str(root), "images": folder}

    xyz = np.zeros((0, 3))
    rgb = np.zeros((0, 3))
    if meta.get("ply_file_path"):
        xyz, rgb = _read_ply_points(root / str(meta["ply_file_path"]), f"named by ply_file_path in {path.name}")
        source["ply"] = str(meta["ply_file_path"])

    w2c = cameras.cam_from_world.double().numpy()
    if meta.get("applied_transform") is not None:
        # ns-process-data rotated the COLMAP world (x, z, -y): X_file = A X_colmap. Undo it, so that poses
        # (and GT depth, points) are in COLMAP's frame and units again.
        try:
            A = np.asarray(meta["applied_transform"], dtype=np.float64)
        except (TypeError, ValueError):
            A = np.zeros(0)
        if A.shape not in ((3, 4), (4, 4)) or not np.all(np.isfinite(A)):
            raise UserError(f"applied_transform must be a 3x4 matrix, got shape {A.shape}", path=path)
        R_A, s = _similarity(A, path)
        t_A = A[:3, 3]
        # camera centre c_file = s R_A c + t_A and axes R_file^T = R_A R^T, so R = R_file R_A, c = R_A^T (c_file - t_A) / s
        R_file, t_file = w2c[:, :3, :3], w2c[:, :3, 3]
        c_file = -np.einsum("cji,cj->ci", R_file, t_file)
        R = R_file @ R_A
        c = (c_file - t_A) @ R_A / s
        w2c = w2c.copy()
        w2c[:, :3, :3] = R
        w2c[:, :3, 3] = -np.einsum("cij,cj->ci", R, c)
        xyz = (xyz - t_A) @ R_A / s
        source["applied_transform"] = A[:3].tolist()
        source["frame"] = "COLMAP (applied_transform undone)"
    cameras = Cameras(torch.tensor(w2c, dtype=torch.float64), cameras.K, cameras.width, cameras.height,
                      cameras.image_names)

    split = None
    key = next((k for k in ("test_filenames", "val_filenames") if meta.get(k)), None)
    if key is not None:
        index = {fr.name: i for i, fr in enumerate(frames)}
        wanted = [image_name(root, n) for n in meta[key]]
        missing = [n for n in wanted if n not in index]
        if missing:
            raise UserError(f"{key} names images that are not frames: {', '.join(missing[:5])}", path=path,
                            hint="List file paths exactly as the frames give them.")
        test = tuple(sorted({index[n] for n in wanted}))
        train = tuple(i for i in range(len(frames)) if i not in set(test))
        split = {"train": train, "test": test} if train else None
        source["split_from"] = key
    return TransformsScene(cameras, paths, torch.tensor(xyz, dtype=torch.float64),
                           torch.tensor(rgb, dtype=torch.float32).clamp(0, 1), split, source, path)
