"""Reading and writing COLMAP models through pycolmap (the only place besides sfm/ that touches it).

Poses are exchanged as plain numpy ``cam_from_world`` [4,4] matrices (OpenCV axes, as COLMAP uses),
so the rest of the package never sees pycolmap objects.
"""

from __future__ import annotations

import functools
import os
import shutil
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from uncertsplat.errors import UserError
from uncertsplat.io.atomic import temp_folder, temp_stem

MODEL_FILES = ("cameras", "images", "points3D")


@dataclass(frozen=True)
class ColmapCamera:
    """One COLMAP camera: model name, size, pinhole part K [3,3] and its distortion parameters."""

    camera_id: int
    model: str
    width: int
    height: int
    K: np.ndarray  # [3,3]
    distortion: np.ndarray  # [D] the model's extra parameters (empty for PINHOLE / SIMPLE_PINHOLE)


@dataclass(frozen=True)
class ColmapImage:
    name: str
    camera_id: int
    cam_from_world: np.ndarray  # [4,4]


@dataclass(frozen=True)
class ColmapModel:
    """A COLMAP reconstruction as numpy arrays. Only registered images (with a pose) are listed."""

    cameras: dict[int, ColmapCamera]
    images: list[ColmapImage]
    points: np.ndarray  # [P,3] float64
    points_rgb: np.ndarray  # [P,3] uint8
    point_images: tuple[tuple[str, ...], ...] | None = None
    """Per point, the names of the registered images that observe it (its track), when read from a file."""


def has_model(folder: Path) -> bool:
    """True when ``folder`` holds cameras/images/points3D as .bin or .txt."""
    folder = Path(folder)
    return any(all((folder / f"{n}{ext}").is_file() for n in MODEL_FILES) for ext in (".bin", ".txt"))


@functools.lru_cache(maxsize=64)
def _camera_param_count(model_id: int) -> int | None:
    import pycolmap

    try:
        return len(pycolmap.Camera.create_from_model_id(1, pycolmap.CameraModelId(model_id), 1.0, 1, 1).params)
    except Exception:  # an unknown model id
        return None


def check_binary_model(folder: Path) -> None:
    """Walk the record structure of cameras/images/points3D.bin and check it fits the file sizes.

    pycolmap trusts the counts in these files: a truncated file or one flipped bit in a count can make it
    read past the end for a very long time (seen: ReadPoints3DBinary spinning on an exhausted stream) or
    load garbage. This check costs one pass over the counts (no float parsing) and raises ``UserError``
    naming the damaged file instead.
    """
    import struct

    def bad(path: Path, why: str) -> UserError:
        return UserError(f"the COLMAP model file is damaged ({why})", path=path,
                         hint="The file may be truncated or corrupted; re-run `uncertsplat reconstruct` "
                         "or restore the workspace from a copy.")

    def walk(path: Path, record) -> None:
        data = path.read_bytes()
        if len(data) < 8:
            raise bad(path, f"only {len(data)} bytes")
        (count,) = struct.unpack_from("<Q", data, 0)
        off = 8
        for i in range(count):
            try:
                off = record(data, off)
            except struct.error:
                off = len(data) + 1
            if off > len(data):
                raise bad(path, f"the file ends inside record {i + 1} of the {count} it announces")
        if off != len(data):
            raise bad(path, f"{len(data) - off} unexpected bytes after the {count} records")

    def camera(data: bytes, off: int) -> int:
        _cid, model_id, width, height = struct.unpack_from("<iiQQ", data, off)
        n = _camera_param_count(model_id)
        if n is None:
            raise bad(folder / "cameras.bin", f"unknown camera model id {model_id}")
        if not (0 < width < 2**20 and 0 < height < 2**20):
            raise bad(folder / "cameras.bin", f"implausible image size {width}x{height}")
        return off + 24 + 8 * n

    def image(data: bytes, off: int) -> int:
        end = data.find(b"\0", off + 64)  # after id, qvec, tvec, camera id: the name, NUL-terminated
        if end < 0:
            return len(data) + 1
        (n2d,) = struct.unpack_from("<Q", data, end + 1)
        return end + 1 + 8 + 24 * n2d

    def point(data: bytes, off: int) -> int:
        (track,) = struct.unpack_from("<Q", data, off + 43)  # id, xyz, rgb, error, then the track length
        return off + 51 + 8 * track

    for name, record in (("cameras", camera), ("images", image), ("points3D", point)):
        walk(folder / f"{name}.bin", record)


def read_colmap_model(folder: str | Path, *, tracks: bool = False) -> ColmapModel:
    """Read a binary or text COLMAP model folder.

    ``tracks``: list each point's observing images (``point_images``; None without): only ``points_from =
    "train"`` needs them, and building them walks every observation in Python (about 10 s for a million points
    seen by 5 images each, most of a load).

    Raises:
        UserError: when the folder holds no model or pycolmap cannot parse it.
    """
    import pycolmap

    folder = Path(folder)
    if not has_model(folder):
        raise UserError("no COLMAP model here (expected cameras, images and points3D as .bin or .txt)",
                        path=folder, hint="Run `uncertsplat reconstruct` on your photos to create a workspace.")
    if all((folder / f"{n}.bin").is_file() for n in MODEL_FILES):
        check_binary_model(folder)
    try:
        rec = pycolmap.Reconstruction(str(folder))
    except Exception as err:  # pycolmap raises plain RuntimeErrors/ValueErrors for broken files
        raise UserError(f"cannot read the COLMAP model ({err})", path=folder,
                        hint="The model files may be truncated; re-run `uncertsplat reconstruct`.") from None
    cameras: dict[int, ColmapCamera] = {}
    for cid, cam in rec.cameras.items():
        extra = [int(i) for i in cam.extra_params_idxs()]
        params = np.asarray(cam.params, dtype=np.float64)
        cameras[int(cid)] = ColmapCamera(
            camera_id=int(cid),
            model=str(cam.model.name),
            width=int(cam.width),
            height=int(cam.height),
            K=np.asarray(cam.calibration_matrix(), dtype=np.float64),
            distortion=params[extra] if extra else np.zeros(0),
        )
    images = []
    for _, im in rec.images.items():
        if not im.has_pose:
            continue
        pose = im.cam_from_world()
        norm = float(np.linalg.norm(np.asarray(pose.rotation.quat, dtype=np.float64)))
        if not abs(norm - 1.0) <= 1e-3:  # (a doubled one made skewed camera axes, a zero one the identity: no word)
            raise UserError(f"image '{im.name}' of the COLMAP model has a rotation quaternion of norm {norm:.4g}, "
                            "not 1, so its pose is no rotation", path=folder,
                            hint="Write unit quaternions QW QX QY QZ in images.txt (divide by their norm), or "
                                 "re-run `uncertsplat reconstruct`.")
        M = np.eye(4)
        M[:3, :4] = np.asarray(pose.matrix(), dtype=np.float64)
        images.append(ColmapImage(name=str(im.name), camera_id=int(im.camera_id), cam_from_world=M))
    twice = sorted(n for n, k in Counter(im.name for im in images).items() if k > 1)
    if twice:  # (both trained on one photo at two poses, and scene.json's cameras kept one: the loaders of
        # transforms files refuse this as well)
        raise UserError(f"the COLMAP model lists image {twice[0]!r} twice" + (f" (and {len(twice) - 1} more name(s))"
                                                                             if len(twice) > 1 else ""),
                        path=folder, hint="Give each image of images.txt its own file name, or re-run "
                                          "`uncertsplat reconstruct`.")
    pts = list(rec.points3D.values())
    xyz = np.array([p.xyz for p in pts], dtype=np.float64).reshape(-1, 3)
    rgb = np.array([p.color for p in pts], dtype=np.uint8).reshape(-1, 3)
    point_images = None
    if tracks:
        names = {int(iid): str(im.name) for iid, im in rec.images.items()}
        point_images = tuple(tuple(sorted({names[int(e.image_id)] for e in p.track.elements
                                           if int(e.image_id) in names})) for p in pts)
    return ColmapModel(cameras, images, xyz, rgb, point_images)


def write_colmap_model(
    folder: str | Path,
    cam_from_world: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    names: Sequence[str],
    points: np.ndarray,
    points_rgb: np.ndarray,
    tracks: Sequence[Sequence[tuple[int, float, float]]] | None = None,
) -> Path:
    """Write a binary COLMAP model with one shared PINHOLE camera.

    Args:
        folder: the model folder (e.g. ``sparse/0``); replaced atomically (written beside, then renamed).
        cam_from_world: [C,4,4] poses (OpenCV axes).
        K: [3,3] shared intrinsics.
        names: C image names.
        points: [P,3] positions; points_rgb: [P,3] colours in [0, 1] (float) or uint8.
        tracks: per point, its observations (image index, u, v) in pixels (centres at +0.5, as COLMAP).
    """
    import pycolmap

    folder = Path(folder)
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera(model="PINHOLE", width=int(width), height=int(height),
                          params=[float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])], camera_id=1)
    rec.add_camera_with_trivial_rig(cam)
    C = len(names)
    # Keypoints per image, in the order the tracks reference them.
    keypoints: list[list[tuple[float, float]]] = [[] for _ in range(C)]
    elements: list[list[tuple[int, int]]] = []
    for obs in tracks or [[] for _ in range(len(points))]:
        el = []
        for j, u, v in obs:
            el.append((j, len(keypoints[j])))
            keypoints[j].append((u, v))
        elements.append(el)
    for j in range(C):
        kp = np.array(keypoints[j], dtype=np.float64).reshape(-1, 2)
        img = pycolmap.Image(name=str(names[j]), keypoints=kp, camera_id=1, image_id=j + 1)
        rec.add_image_with_trivial_frame(img, pycolmap.Rigid3d(np.asarray(cam_from_world[j][:3, :4], np.float64)))
    rgb = np.asarray(points_rgb)
    if rgb.dtype != np.uint8:
        rgb = np.round(np.clip(rgb, 0, 1) * 255).astype(np.uint8)
    for p in range(len(points)):
        track = pycolmap.Track([pycolmap.TrackElement(j + 1, k) for j, k in elements[p]])
        rec.add_point3D(np.asarray(points[p], np.float64), track, rgb[p])

    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_folder(f".{temp_stem(folder.name)}.", folder.parent)
    try:
        rec.write_binary(str(tmp))
        if folder.exists():
            shutil.rmtree(folder)
        os.replace(tmp, folder)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return folder
