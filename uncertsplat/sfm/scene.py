"""Scene loading: COLMAP workspaces, Blender and nerfstudio folders and our synthetic scenes -> ``SceneData``.

Detection order for a folder ``P``:

1. ``P/scene.json`` written by ``uncertsplat synth``: a synthetic scene with GT depth/masks, in the COLMAP
   layout (``sparse/0``) or the Blender layout (``transforms_*.json``), as its ``layout`` says.
2. ``P/transforms_train.json`` (and/or ``transforms_val.json``, ``transforms_test.json``): a Blender
   (NeRF-synthetic) folder (``sfm.transforms``).
3. ``P/transforms.json``: a nerfstudio / instant-ngp folder (``sfm.transforms``).
4. ``P/images/`` + ``P/sparse/0`` (or a model directly in ``P/sparse``): a COLMAP workspace.

Images are sorted by name. Scenes without sparse points get random initial points around the scene centre
(``sfm.center``: where the optical axes of an inward-facing rig meet, else the camera centroid), carved to the
visual hull of the training views' alpha masks when those images are transparent. Cameras are
normalised: the centre moves to the origin and the scene is scaled so that the farthest camera is at distance
1 from the camera centroid; the similarity is recorded as ``world_from_source``, the centre and why it was
chosen as ``SceneData.center`` / ``center_method`` / ``center_reason``.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from uncertsplat.config import SceneConfig
from uncertsplat.console import list_names, q
from uncertsplat.errors import UserError
from uncertsplat.io.folders import stage_hint
from uncertsplat.io.images import IMAGE_EXTENSIONS, has_alpha, read_image_size
from uncertsplat.schemas.reconstruct import EXTEND_DIR, REPORT_NAME
from uncertsplat.schemas.scene import SynthScene
from uncertsplat.sfm.center import choose_center, random_points
from uncertsplat.sfm.colmap_io import MODEL_FILES, ColmapModel, has_model, read_colmap_model
from uncertsplat.sfm.transforms import TransformsScene, read_blender, read_nerfstudio
from uncertsplat.types import (
    Cameras,
    SceneData,
    focal_unusable,
    principal_point_near_edge,
    principal_point_place,
    similarity_scale,
)

_POINT_SEED = 0  # seeds random initial points (Blender, nerfstudio) and point subsampling: loading is deterministic
_RANDOM_POINTS = 100_000  # at most this many random initial points (what 3DGS uses for Blender scenes) ...
_PIXELS_PER_RANDOM_POINT = 100  # ... and one per this many training pixels (at the loaded resolution)
_PIXELS_PER_CARVED_POINT = 50  # ... or this many when the points are carved with alpha masks (see _finish)
_CARVE_SIZE = 400  # carve random initial points with alpha masks of at most this many pixels on a side
TWIN_DISTANCE = 0.002
"""Two cameras whose centres lie closer than this fraction of the rig's radius from its centroid (``pose_twins``) ..."""
TWIN_ANGLE_DEG = 0.5
"""... whose optical axes differ by less than this many degrees and whose focal lengths by less than 2 % may have taken
the same picture: a copy re-encoded or renamed, an exposure bracket, a burst from a tripod ..."""
TWIN_JUMP = 10.0
"""... when the next training view's pose differs this many times more (``pose_twins``)."""


# ----------------------------------------------------------------------------------------------- public
def load_scene(path: str | Path, cfg: SceneConfig | None = None, *, initial_points: bool = True) -> SceneData:
    """Load a scene folder (see the module docstring for what is recognised).

    Args:
        path: the scene folder.
        cfg: downscale, split and normalisation options (defaults when None).
        initial_points: make random initial points for a scene without sparse points (reading the alpha masks
            to carve them). Only a fresh training needs them; rendering a trained run passes False, which
            leaves ``points`` empty for such scenes and changes nothing else (centre, normalisation, split).

    Raises:
        UserError: naming the file or folder and the fix, for every input we cannot use.
    """
    cfg = cfg or SceneConfig()
    path = Path(path)
    if not path.exists():
        raise UserError("scene folder not found", path=path, hint="Check the path.")
    if not path.is_dir():
        raise UserError("expected a scene folder, got a file", path=path,
                        hint="Pass the folder that contains images/ and sparse/0.")
    if not any(path.iterdir()):
        raise UserError("the scene folder is empty", path=path,
                        hint="Run `uncertsplat reconstruct PHOTOS -o FOLDER` or `uncertsplat synth FOLDER` first.")
    aside = path / EXTEND_DIR / "old"  # `reconstruct --extend` killed while it swapped the workspace's parts
    if aside.is_dir() and not (aside / REPORT_NAME).exists():  # (once the report moved, it is complete)
        raise UserError("a `reconstruct --extend` was stopped while it replaced this workspace's parts", path=path,
                        hint=f"Run `uncertsplat reconstruct PHOTOS -o {q(path)}` (or with --extend) again: it first "
                             "undoes the half-made swap.")
    from uncertsplat.data.synthetic import read_scene_meta

    meta = read_scene_meta(path)
    if meta is not None:
        return _load_synthetic(path, cfg, meta, initial_points)
    if any((path / f"transforms_{split}.json").is_file() for split in ("train", "val", "test")):
        return _with_notes(_from_transforms(read_blender(path, cfg), cfg, initial_points),
                           _colmap_beside(path, "a Blender scene (transforms_*.json)"))
    if (path / "transforms.json").is_file():
        data = _from_transforms(read_nerfstudio(path, cfg), cfg, initial_points)
        masks, mask_notes = _nerfstudio_masks(path, data.cameras.image_names)
        if masks is not None:
            data = replace(data, mask_paths=masks, masks_train=True)
        return _with_notes(data, _colmap_beside(path, "a nerfstudio scene (transforms.json)") + mask_notes
                           + _unread_frame_notes(path / "transforms.json"))
    return _load_colmap(path, cfg)


def _colmap_beside(path: Path, read_as: str) -> list[str]:
    """A note when a folder read as ``read_as`` (a transforms file) also holds a COLMAP model, which is not used."""
    if not (path / "sparse").is_dir() or not any(has_model(d) for d in (path / "sparse", *_model_dirs(path))):
        return []
    return [f"read as {read_as}; the folder also holds a COLMAP model in sparse/, not used (move the transforms file "
            "away to train on it)"]


def _nerfstudio_masks(root: Path, names: Sequence[str]) -> tuple[tuple[Path | None, ...] | None, list[str]]:
    """The masks a nerfstudio ``transforms.json`` names (a frame's ``mask_path``, relative to ``root``), one per image
    name (None for a frame without one), or None when no frame names one; and the note on them.

    Raises:
        UserError: a frame names a mask file that does not exist.
    """
    import json

    from uncertsplat.sfm.transforms import image_name

    try:
        frames = json.loads((root / "transforms.json").read_text(encoding="utf-8")).get("frames", [])
    except (OSError, ValueError, AttributeError):
        return None, []  # read_nerfstudio has said what is wrong with it
    named = {image_name(root, f["file_path"]): str(f["mask_path"]).replace("\\", "/").removeprefix("./")
             for f in frames if isinstance(f, dict) and f.get("mask_path") and f.get("file_path")}
    if not named:
        return None, []
    found = []
    for n in names:
        rel = named.get(n)
        if rel is not None and not (root / rel).is_file():
            raise UserError(f"frame '{n}' of transforms.json names a mask_path that does not exist",
                            path=root / rel, hint="Put the mask there, or remove the frame's mask_path to train "
                                                  "on every pixel of its photo.")
        found.append(root / rel if rel is not None else None)
    if all(m is None for m in found):
        return None, []
    return tuple(found), [masks_note(names, found, "(transforms.json's mask_path)")]


def _unread_frame_notes(transforms: Path) -> list[str]:
    """A note when a nerfstudio transforms file names per-frame depth maps (``depth_file_path``), which are not
    read (it was silent)."""
    import json

    try:
        frames = json.loads(transforms.read_text(encoding="utf-8")).get("frames", [])
    except (OSError, ValueError, AttributeError):
        return []  # read_nerfstudio has said what is wrong with it
    count = lambda key: sum(1 for f in frames if isinstance(f, dict) and f.get(key))  # noqa: E731
    notes = []
    if n := count("depth_file_path"):
        notes.append(f"{n} frame(s) of {transforms.name} name a depth_file_path: depth maps are not read (training "
                     "fits the photos alone); to score the rendered depth against them, give `uncertsplat evaluate "
                     "--depth-gt FOLDER` the folder of those maps (16-bit PNGs are read as stored: millimetres for nerfstudio's)")
    return notes


def mask_file(folder: Path, name: str) -> Path | None:
    """The mask of image ``name`` (its path relative to the images folder) in ``folder``, or None: COLMAP's name
    (``IMG_1.jpg.png``), the image's own name (``IMG_1.jpg``), then its stem as a PNG (``IMG_1.png``), in sub-folders
    as the images are."""
    for candidate in (f"{name}.png", name, Path(name).with_suffix(".png").as_posix()):
        path = folder / candidate
        if path.is_file():
            return path
    return None


def mask_hashes(scene: SceneData, names: Sequence[str] | None = None) -> dict[str, str]:
    """{view name: SHA-256 of its mask file} of the photos' own masks (``SceneData.masks_train``) of the views
    ``names`` (all when None) that have one; empty for a scene without them (``RunScene.masks`` records them)."""
    from uncertsplat.provenance import file_sha256

    if not scene.masks_train or scene.mask_paths is None:
        return {}
    wanted = None if names is None else set(names)
    return {n: file_sha256(p) for n, p in zip(scene.cameras.image_names, scene.mask_paths, strict=True)
            if p is not None and (wanted is None or n in wanted)}


def user_mask_files(path: Path, names: Sequence[str]) -> dict[str, Path]:
    """{image name: mask file} of the photos' own masks (``SceneData.masks_train``) of the views ``names`` in the scene
    folder ``path``, found as ``load_scene`` finds them but without loading the scene (a COLMAP workspace's
    ``masks/``, nerfstudio's ``mask_path``); empty for a synthetic or Blender scene, or without masks.

    Raises:
        UserError, OSError: a folder or transforms file that cannot be read (a nerfstudio frame naming a mask that
            is gone, a folder without permission).
    """
    from uncertsplat.data.synthetic import read_scene_meta

    path = Path(path)
    if read_scene_meta(path) is not None or any((path / f"transforms_{s}.json").is_file()
                                                for s in ("train", "val", "test")):
        return {}
    if (path / "transforms.json").is_file():
        found, _ = _nerfstudio_masks(path, names)
    else:
        found, _ = _workspace_masks(path, names)
    return {} if found is None else {n: p for n, p in zip(names, found, strict=True) if p is not None}


def photo_folder_holding(out: Path, scene: Path | None, image_paths: Sequence[str | Path] = ()) -> Path | None:
    """The folder of the scene's photos that ``out`` is or lies inside, or None: the scene's ``images/`` (its photos
    may lie in subfolders), the folder ``reconstruct`` made the workspace from (``reconstruct_report.json``'s
    ``photos``) and the folders of ``image_paths``. Files a stage writes there are taken for photos by the next
    ``reconstruct`` of them."""
    from uncertsplat.schemas import ReconstructReport

    folders = {Path(p).parent.resolve() for p in image_paths}
    if scene is not None:
        if (Path(scene) / "images").is_dir():
            folders.add((Path(scene) / "images").resolve())
        try:
            report = ReconstructReport.read_optional(Path(scene) / REPORT_NAME)
        except UserError:
            report = None
        if report is not None and report.photos:
            folders.add(Path(report.photos).resolve())
    target = Path(out).resolve()
    return next((f for f in sorted(folders) if target == f or f in target.parents), None)


def trained_with_masks(run_dir: Path) -> bool:
    """Whether the run in ``run_dir`` was trained with the photos' own masks (``RunScene.masks``): its metrics are
    taken inside them as its training's were; masks added to the scene since are scored inside but not so called."""
    from uncertsplat.schemas.scene import RunScene

    try:
        info = RunScene.read_optional(Path(run_dir) / RunScene.FILE_NAME)
    except (UserError, OSError, ValueError):
        return False
    return info is not None and bool(info.masks)


def _digest_of(hashes: dict[str, str]) -> str:
    """``run_mask_digest``'s one SHA-256 of {view name: SHA-256 of its mask}."""
    import hashlib

    return hashlib.sha256("\n".join(f"{n}:{hashes[n]}" for n in sorted(hashes)).encode()).hexdigest()


def run_mask_digest(run_dir: Path) -> str | None:
    """One SHA-256 of the photos' own masks, as they are now, of the views the run in ``run_dir`` trains, holds out
    and sets aside (``RUN/scene.json``), and of the transient regions its training found (``RUN/transients/``,
    ``data.dataset.TRANSIENTS_FOLDER``): what an evaluation scored with besides the run's model and settings
    (``stages.evaluate.run_sha256``, the kept noise fit's key). None without either; where the scene folder is gone
    (a run used away from its photos), the photos' part is the digest of the masks the run was trained with
    (``RunScene.masks``), as the scene gave it while they were unchanged; "unreadable" where a mask cannot be read
    (never the digest of no masks)."""
    from uncertsplat.conventions import ENSEMBLE_MEMBERS
    from uncertsplat.data.dataset import TRANSIENTS_FOLDER, transient_mask_files
    from uncertsplat.provenance import file_sha256

    photos = _photo_mask_digest(run_dir)
    run_dir = Path(run_dir)
    # the run's own, and an ensemble's members' (each member's training left its own regions out)
    runs = [run_dir, *(f.parent for f in sorted((run_dir / ENSEMBLE_MEMBERS).glob(f"*/{TRANSIENTS_FOLDER}")))]
    try:
        found = {p.relative_to(run_dir).as_posix(): file_sha256(p)
                 for r in runs for p in transient_mask_files(r).values()}
    except OSError:
        return "unreadable"
    # (the runs without transients keep the digest they were evaluated under)
    return _digest_of({"photos": photos or "-", "transients": _digest_of(found)}) if found else photos


def _photo_mask_digest(run_dir: Path) -> str | None:
    """``run_mask_digest``'s part of the photos' own masks."""
    from uncertsplat.provenance import file_sha256
    from uncertsplat.schemas.scene import RunScene

    try:
        info = RunScene.read_optional(Path(run_dir) / RunScene.FILE_NAME)
    except (UserError, OSError, ValueError):
        return None
    if info is None or not info.scene:
        return None
    names = list(dict.fromkeys([*info.train, *info.test, *info.calibration]))
    try:
        folder = info.scene_folder(run_dir)
        if not folder.is_dir():
            return _digest_of(info.masks) if info.masks else None
        files = user_mask_files(folder, names)
        hashes = {n: file_sha256(p) for n, p in files.items()}
    except (UserError, OSError, ValueError, TypeError, AttributeError):
        return "unreadable"
    return _digest_of(hashes) if hashes else None


def mask_changes(recorded: dict[str, str], now: dict[str, str], names: Sequence[str]) -> str | None:
    """What differs between the masks a run ``recorded`` and the scene's masks ``now`` (``mask_hashes``) for the
    views ``names``, in words; None when nothing does."""
    changed = [n for n in names if recorded.get(n) != now.get(n)]
    if not changed:
        return None
    added = [n for n in changed if n not in recorded]
    gone = [n for n in changed if n not in now]
    edited = [n for n in changed if n in recorded and n in now]
    parts = [f"{what} for {list_names(group, 4)}" for what, group in
             (("a mask added", added), ("its mask removed", gone), ("its mask changed", edited)) if group]
    return "; ".join(parts)


def masks_note(names: Sequence[str], found: Sequence[object | None], where: str) -> str:
    """The note on the masks ``found`` (None for a photo without one) of the photos ``names``, from ``where``."""
    missing = [n for n, m in zip(names, found, strict=True) if m is None]
    return (f"masks: {len(names) - len(missing)} of {len(names)} photos have one {where}; their black pixels are "
            "neither trained on nor scored" + (f" (every pixel of the other {len(missing)} is: "
                                               f"{list_names(missing, 4)})" if missing else ""))


def mask_names(photo: str) -> str:
    """The names ``mask_file`` looks up for ``photo``, for a message: "photo IMG_1.jpg's would be IMG_1.jpg.png,
    IMG_1.jpg or IMG_1.png"."""
    names = list(dict.fromkeys((f"{photo}.png", photo, Path(photo).with_suffix(".png").as_posix())))
    return f"photo {photo}'s would be " + (", ".join(names[:-1]) + " or " + names[-1])


def _workspace_masks(path: Path, names: Sequence[str]) -> tuple[tuple[Path | None, ...] | None, list[str]]:
    """The masks of a COLMAP workspace's images in ``path/masks`` (``mask_file``), one per name (None for a photo
    without one), or None when the folder holds none of them; and the notes on what was found."""
    folder = path / "masks"
    if not folder.is_dir():
        return None, []
    found = tuple(mask_file(folder, n) for n in names)
    have = sum(m is not None for m in found)
    if not have:
        n = sum(1 for p in folder.rglob("*") if p.is_file())
        if not n:
            return None, []
        return None, [f"{folder} ({n} file(s)) holds no mask named for any photo ({mask_names(names[0] if names else 'IMG_1.jpg')}"
                      "): not read, every pixel is trained on and scored"]
    note = masks_note(names, found, f"in {folder}")
    if (path / REPORT_NAME).is_file() and not _reconstructed_with_masks(path):
        # reconstruct's images/ are the photos undistorted, and these masks/ are not its own (--masks)
        note += ("; `reconstruct` undistorted the photos into images/, so masks drawn on the photos as taken are off "
                 "by the lens's distortion there: draw them on the workspace's images, or reconstruct with --masks")
    return found, [note]


def _reconstructed_with_masks(path: Path) -> bool:
    """Whether ``reconstruct --masks`` made the workspace ``path`` (its masks/ undistorted as its images)."""
    import json

    try:
        return bool(json.loads((path / REPORT_NAME).read_text(encoding="utf-8")).get("options", {}).get("masks"))
    except (OSError, ValueError, AttributeError):
        return False


def _model_dirs(path: Path) -> list[Path]:
    """The numbered model folders of ``path/sparse`` (sparse/0, sparse/1, ...), in order."""
    sparse = path / "sparse"
    if not sparse.is_dir():
        return []
    return sorted((d for d in sparse.iterdir() if d.is_dir() and re.fullmatch(r"[0-9]+", d.name)),
                  key=lambda d: int(d.name))


def _with_notes(data: SceneData, notes: list[str]) -> SceneData:
    return replace(data, notes=(*data.notes, *notes)) if notes else data


def find_sparse_model(path: Path) -> Path:
    """``path/sparse/0`` when it holds a model, else ``path/sparse`` itself; UserError when neither does."""
    for cand in (path / "sparse" / "0", path / "sparse"):
        if has_model(cand):
            return cand
    if (path / "sparse").is_dir():
        raise UserError("no COLMAP model in sparse/0 (expected cameras, images, points3D as .bin or .txt)",
                        path=path / "sparse" / "0",
                        hint="Point to the workspace written by `uncertsplat reconstruct`, or re-run it.")
    near = stage_hint(path, "scene")  # (a pipeline's output folder: its workspace is OUT/reconstruct)
    raise UserError("missing sparse/0: this folder is not a COLMAP workspace" + (f"; {near}" if near else ""),
                    path=path / "sparse" / "0",
                    hint=None if near else  # (the message says which to give: "... give that")
                    "Run `uncertsplat reconstruct PHOTOS -o WORKSPACE` to create one.")


# ---------------------------------------------------------------------------------------------- loaders
def _check_reconstruct_report(path: Path) -> None:
    """Refuse a workspace whose ``reconstruct_report.json`` says the reconstruction failed."""
    from uncertsplat.sfm.report import require_successful

    require_successful(path)


def _colmap_cameras(model: ColmapModel, image_dir: Path, sparse: Path, cfg: SceneConfig
                    ) -> tuple[Cameras, list[Path], tuple | None, list[str]]:
    """Sorted, validated cameras and image paths of a COLMAP model, the ``PhotoFit`` of each when the images
    come in more than one size (``SceneConfig.photo_sizes``; None otherwise) and the notes on that."""
    if not model.images:
        raise UserError("the COLMAP model has no registered images", path=sparse,
                        hint="Re-run `uncertsplat reconstruct` with more overlapping photos.")
    used = {im.camera_id for im in model.images}
    for cam in model.cameras.values():
        if cam.camera_id not in used:  # a camera no image uses (an edited model's leftover) renders nothing
            continue
        if "FISHEYE" in cam.model or cam.model == "EQUIRECTANGULAR":
            # not a pinhole projection whatever its coefficients (a fisheye of zero coefficients is equidistant): it
            # trained as one without a word, 26 dB where the same photos undistorted gave 32
            raise UserError(
                f"COLMAP camera {cam.camera_id} uses the {cam.model} model, a projection that splatting cannot render "
                "(not a pinhole camera, whatever its coefficients)", path=sparse,
                hint="Undistort the images to a pinhole camera (`colmap image_undistorter`, or `uncertsplat "
                     "reconstruct` on the photos) and load the undistorted workspace.")
        if cam.model not in ("PINHOLE", "SIMPLE_PINHOLE") and np.any(np.abs(cam.distortion) > 0):
            raise UserError(
                f"COLMAP camera {cam.camera_id} uses the {cam.model} model with lens distortion "
                f"({', '.join(f'{d:g}' for d in cam.distortion)}), which splatting cannot render",
                path=sparse,
                hint="Run `uncertsplat reconstruct` (it undistorts), or undistort with "
                "`colmap image_undistorter` and load the undistorted workspace.",
            )
    images = sorted(model.images, key=lambda im: im.name)
    sizes = {(model.cameras[im.camera_id].width, model.cameras[im.camera_id].height) for im in images}
    if len(sizes) > 1 and cfg.photo_sizes == "strict":
        raise UserError(f"the images have different sizes ({_sizes_by_name(model, images)}) and scene.photo_sizes "
                        "is 'strict'", path=sparse,
                        hint="Use scene.photo_sizes = 'fit' (turns portrait photos and crops to a common size), or "
                             "bring all photos to one size and reconstruct again.")
    fits, notes = (None, []) if len(sizes) == 1 else _fit_sizes(model, images, sparse)
    if fits is not None:
        images = [im for im in images if im.name in fits]
    paths = []
    for im in images:
        p = image_dir / im.name
        if not p.is_file():
            missing = [m.name for m in images if not (image_dir / m.name).is_file()]
            stem = Path(im.name).with_suffix("").name.lower()
            near = sorted(q.name for q in p.parent.glob("*") if q.is_file() and q.stem.lower() == stem) \
                if p.parent.is_dir() else []
            what = (f"image '{im.name}' named in the COLMAP model is missing" if len(missing) == 1 else
                    f"{len(missing)} of the {len(images)} images the COLMAP model names are missing (e.g. '{im.name}')")
            raise UserError(what + (f"; {list_names(near)} is there: the model's names must match the files' "
                                    "exactly (extension and its case too)" if near else ""), path=p,
                            hint=("Rename the files to the model's names, or reconstruct again from them." if near
                                  else f"Put the image into {image_dir} or reconstruct again without it."
                                  if len(missing) == 1 else f"Put the images into {image_dir}, or reconstruct again "
                                  "from the photos you have."))
        cam = model.cameras[im.camera_id]
        w, h = read_image_size(p)
        if (w, h) != (cam.width, cam.height):
            raise UserError(
                f"image is {w}x{h} but its COLMAP camera is {cam.width}x{cam.height}",
                path=p,
                hint="Use the undistorted images the model was made for, or reconstruct again.",
            )
        paths.append(p)
    c2w = torch.tensor(np.stack([im.cam_from_world for im in images]), dtype=torch.float64)
    K = torch.tensor(np.stack([model.cameras[im.camera_id].K for im in images]), dtype=torch.float64)
    if fits is None:
        width, height = sizes.pop()
    else:
        ordered = [fits[im.name] for im in images]
        c2w, K = _fitted_cameras(c2w, K, ordered)
        width, height = ordered[0].width, ordered[0].height
    # float64 until the scene is normalised (``_finish``): a capture in map coordinates (UTM: millions of metres)
    # keeps its centimetres only there, and float32 poses lost 2 dB at 5e6
    cameras = Cameras(c2w, K, width, height, tuple(im.name for im in images))
    return cameras, paths, (tuple(fits[im.name] for im in images) if fits is not None else None), notes


PHOTO_SHAPE_TOLERANCE = 0.01
"""``SceneConfig.photo_sizes`` = "fit": a photo (turned to the scene's orientation) beyond ``PHOTO_SIZE_TOLERANCE``
of the most common size joins the scene resized to its width when its aspect ratio is within this fraction of the
scene's (another camera's resolution of the same shape, e.g. 4032x3024 among 3264x2448); the camera is scaled with
it. Other shapes are left out."""
PHOTO_SIZE_TOLERANCE = 0.05
"""``SceneConfig.photo_sizes`` = "fit": a photo (turned to the scene's orientation) joins the scene when its width
and height are within this fraction of the most common size; it is cropped to the size all joined photos share.
Small, so that one photo a little smaller cannot crop much off every other (undistortion's differences are a few
pixels; two phones of one make differ by about 1 %)."""


def _sizes_by_name(model: ColmapModel, images: list) -> str:
    """'800x600: 22 images; 600x800: 1 image (IMG_7.jpg)': the sizes of ``images``, the rarer ones with names."""
    groups: dict[tuple[int, int], list[str]] = {}
    for im in images:
        cam = model.cameras[im.camera_id]
        groups.setdefault((cam.width, cam.height), []).append(im.name)
    parts = []
    for (w, h), names in sorted(groups.items(), key=lambda kv: -len(kv[1])):
        shown = "" if len(names) == max(len(v) for v in groups.values()) else f" ({list_names(names, 5)})"
        parts.append(f"{w}x{h}: {len(names)} image{'s' if len(names) != 1 else ''}{shown}")
    return "; ".join(parts)


def size_fit(w: int, h: int, ref_w: int, ref_h: int) -> str | None:
    """How a photo of ``w`` x ``h`` (turned to the scene's orientation) joins a scene of ``ref_w`` x ``ref_h`` under
    ``SceneConfig.photo_sizes`` = "fit": "crop" (within ``PHOTO_SIZE_TOLERANCE``), "resize" (the same shape within
    ``PHOTO_SHAPE_TOLERANCE``), or None: left out."""
    if abs(w - ref_w) <= PHOTO_SIZE_TOLERANCE * ref_w and abs(h - ref_h) <= PHOTO_SIZE_TOLERANCE * ref_h:
        return "crop"
    if abs(w / h - ref_w / ref_h) <= PHOTO_SHAPE_TOLERANCE * ref_w / ref_h:
        return "resize"
    return None


def other_orientation(w: int, h: int, ref_w: int, ref_h: int) -> bool:
    """Whether a ``w`` x ``h`` photo is of the other orientation than a scene of ``ref_w`` x ``ref_h`` (portrait in a
    landscape scene or the reverse; a square one is of both): ``SceneConfig.photo_sizes`` = "fit" turns it."""
    return (w >= h) != (ref_w >= ref_h) and w != h


def common_size(counts: dict[tuple[int, int], int]) -> tuple[int, int]:
    """The scene's size of photos of several sizes ({(width, height): count}): the most common; among equals the
    larger, then the wider (deterministic)."""
    return max(counts, key=lambda s: (counts[s], s[0] * s[1], s[0]))


def _fit_sizes(model: ColmapModel, images: list, sparse: Path) -> tuple[dict, list[str]]:
    """``SceneConfig.photo_sizes`` = "fit" for ``images`` of more than one size: {name: PhotoFit} of the photos
    that join the scene, and the notes that say what was turned, cropped and left out.

    Raises:
        UserError: fewer than two photos join (nothing to train and hold out).
    """
    from uncertsplat.types import PhotoFit

    counts: dict[tuple[int, int], int] = {}
    for im in images:
        cam = model.cameras[im.camera_id]
        counts[(cam.width, cam.height)] = counts.get((cam.width, cam.height), 0) + 1
    ref_w, ref_h = common_size(counts)
    cams = {im.name: model.cameras[im.camera_id] for im in images}
    # photos of the other orientation (a square one is of both)
    other = {n for n, c in cams.items() if other_orientation(c.width, c.height, ref_w, ref_h)}
    up = _scene_up([im for im in images if im.name not in other])
    # name -> (turns, width, height after turning, width, height after resizing)
    turned: dict[str, tuple[int, int, int, int, int]] = {}
    left_out: list[str] = []
    for im in images:
        cam = cams[im.name]
        turns = _quarter_turns(im.cam_from_world, up) if im.name in other else 0
        w, h = (cam.height, cam.width) if turns else (cam.width, cam.height)
        fit = size_fit(w, h, ref_w, ref_h)
        if fit == "crop":
            turned[im.name] = (turns, w, h, w, h)
        elif fit == "resize":  # another camera's resolution of the same shape: resized to the common width
            turned[im.name] = (turns, w, h, ref_w, max(1, round(h * ref_w / w)))
        else:
            left_out.append(f"{im.name} ({cam.width}x{cam.height})")
    if len(turned) < 2:
        raise UserError(f"the images have different sizes ({_sizes_by_name(model, images)}) and fewer than two "
                        "share one", path=sparse, hint="Reconstruct photos of one camera at one size.")
    width = min(sw for *_, sw, _ in turned.values())
    height = min(sh for *_, sh in turned.values())
    fits = {name: PhotoFit(turns, (sw - width) // 2, (sh - height) // 2, width, height, w, h,
                           sw if (sw, sh) != (w, h) else 0, sh if (sw, sh) != (w, h) else 0)
            for name, (turns, w, h, sw, sh) in turned.items()}
    notes = []
    rotated = sorted(n for n, f in fits.items() if f.turns)
    if rotated:
        notes.append(f"{len(rotated)} photo(s) of the other orientation turned a quarter turn, their cameras with "
                     f"them, so that the scene's up points where it does in the other photos (their maps are "
                     f"written turned back): {list_names(rotated, 8)}")
    scaled = sorted(n for n, f in fits.items() if f.scaled_width)
    if scaled:
        notes.append(f"{len(scaled)} photo(s) of another resolution of the same shape resized to the scene's (their "
                     f"cameras with them): {list_names(scaled, 8)}")
    cropped = sorted(n for n, f in fits.items() if f.scaled != (width, height))
    if cropped:
        notes.append(f"{len(cropped)} photo(s) cropped to the {width}x{height} pixels every photo of the scene has "
                     f"(at most a few percent of each side): {list_names(cropped, 8)}")
    if left_out:
        notes.append(f"{len(left_out)} photo(s) of another size left out (the scene's is {ref_w}x{ref_h}; "
                     f"scene.photo_sizes): {list_names(left_out, 8)}")
    return fits, notes


def _scene_up(images: list) -> np.ndarray:
    """[3] the mean of ``images``' up directions in world axes (OpenCV cameras: the image's up is -y), unit length;
    (0, 0, 0) when they cancel out."""
    up = -np.sum([im.cam_from_world[1, :3] for im in images], axis=0)
    norm = float(np.linalg.norm(up))
    return up / norm if norm > 1e-9 else np.zeros(3)


def _quarter_turns(cam_from_world: np.ndarray, up: np.ndarray) -> int:
    """1 (clockwise) or 3 (anticlockwise): the quarter turn after which the photo's up (its camera's -y) points
    closer to ``up``, the scene's up in the photos of the common orientation. A clockwise turn makes the camera's
    x axis its new y axis (``_fitted_cameras``), so its new up is -x; an anticlockwise one +x. Whichever way EXIF
    or the photographer turned the camera, the turned photo then lies as the others do (clockwise on a tie)."""
    x_axis = np.asarray(cam_from_world)[0, :3]
    return 3 if float(x_axis @ up) > 1e-9 else 1


def _fitted_cameras(c2w: torch.Tensor, K: torch.Tensor, fits: list) -> tuple[torch.Tensor, torch.Tensor]:
    """cam_from_world [C,4,4] and K [C,3,3] (float64) of the photos as ``fits`` turn, resize and crop them.

    A clockwise quarter turn takes pixel (u, v) of a photo of height H to (H - v, u): in camera axes
    (x, y, z) -> (-y, x, z), so fx' = fy, fy' = fx, cx' = H - cy, cy' = cx. An anticlockwise one takes (u, v) of a
    photo of width W to (v, W - u): (x, y, z) -> (y, -x, z), fx' = fy, fy' = fx, cx' = cy, cy' = W - cx. A resize
    by (sx, sy) scales fx, cx by sx and fy, cy by sy; a crop from (x0, y0) moves the principal point by (-x0, -y0)."""
    c2w, K = c2w.clone(), K.clone()
    clockwise = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=c2w.dtype)
    for i, fit in enumerate(fits):
        turns = fit.turns % 4
        if turns in (1, 3):
            c2w[i, :3, :] = (clockwise if turns == 1 else clockwise.T) @ c2w[i, :3, :]
            fx, fy, cx, cy = (float(K[i, 0, 0]), float(K[i, 1, 1]), float(K[i, 0, 2]), float(K[i, 1, 2]))
            # the photo's height before the turn is its width after it, and its width the height after it
            K[i, 0, 0], K[i, 1, 1] = fy, fx
            K[i, 0, 2], K[i, 1, 2] = (fit.turned_width - cy, cx) if turns == 1 else (cy, fit.turned_height - cx)
        sw, sh = fit.scaled  # a resize scales pixel coordinates (centres at +0.5) by the size ratio per axis
        K[i, 0] *= sw / fit.turned_width
        K[i, 1] *= sh / fit.turned_height
        K[i, 0, 2] -= fit.x0
        K[i, 1, 2] -= fit.y0
    return c2w, K


def _load_colmap(path: Path, cfg: SceneConfig, source: str = "colmap") -> SceneData:
    _check_reconstruct_report(path)
    sparse = find_sparse_model(path)
    image_dir = path / "images"
    if not image_dir.is_dir():
        others = sorted((d.name for d in path.glob("images_*") if d.is_dir() and re.fullmatch(r"images_[0-9]+", d.name)),
                        key=lambda n: int(n.split("_")[1]))  # LLFF's images_4, images_8 ...
        raise UserError("missing images/ folder beside sparse/" + (f" (there is {', '.join(others)})" if others
                                                                     else ""), path=image_dir,
                        hint="A COLMAP workspace needs the (undistorted) images its model was made for in "
                             "WORKSPACE/images" + (f"; {others[0]} holds downscaled copies: keep the full-size images "
                                                   "in images/ and use --set scene.downscale=N to train smaller"
                                                   if others else "") + ".")
    model = read_colmap_model(sparse, tracks=cfg.points_from == "train")
    cameras, paths, fits, notes = _colmap_cameras(model, image_dir, sparse, cfg)
    others = [d for d in _model_dirs(path) if d.resolve() != sparse.resolve() and has_model(d)]
    if others:  # COLMAP's mapper splits a capture it cannot join into several models: sparse/0 is not always all
        notes = [*notes, f"the workspace holds {len(others) + 1} COLMAP models; {sparse.relative_to(path)} is used "
                         f"({len(model.images)} images); the others ({', '.join(str(d.relative_to(path)) for d in others)}) "
                         "are not: reconstruct again (e.g. more overlap, --matcher exhaustive) to join them"]
    # (reconstruct's own workspaces hold none: COLMAP's undistorter writes the colour channels)
    notes = [*notes, *_alpha_note(paths, image_dir, cfg)]
    unused = _photos_not_in_model(image_dir, model)
    if unused:  # photos a user put there for the scene, which it does not hold
        notes = [*notes, f"{len(unused)} photo(s) in {image_dir} are not in the COLMAP model and are not used: "
                         f"{list_names(unused, 8)} (reconstruct again with them to use them)"]
    masks = None
    if source == "colmap":  # (a synthetic scene's masks/ are its own: _load_synthetic)
        masks, mask_notes = _workspace_masks(path, cameras.image_names)
        notes = [*notes, *mask_notes]
    if all((sparse / f"{n}.bin").is_file() for n in MODEL_FILES) and any((sparse / f"{n}.txt").is_file()
                                                                          for n in MODEL_FILES):
        notes = [*notes, f"{sparse} holds the model both as .bin and as .txt files: the .bin ones are read (as COLMAP "
                         "does); remove the stale ones"]
    points = torch.tensor(model.points, dtype=torch.float64).reshape(-1, 3)  # source units: float64 (see above)
    rgb = torch.tensor(model.points_rgb, dtype=torch.float32).reshape(-1, 3) / 255.0
    if cfg.points_from == "train":
        keep = _seen_by_training_views(model, cameras, cfg, sparse)
        points, rgb = points[keep], rgb[keep]
    data = _finish(cameras, paths, points, rgb, cfg, source={"kind": source, "path": str(path),
                                                            "model": str(sparse)}, photo_fits=fits, notes=notes)
    return data if masks is None else replace(data, mask_paths=masks, masks_train=True)


def _photos_not_in_model(image_dir: Path, model: ColmapModel) -> list[str]:
    """The photos (image files, in sub-folders too) under ``image_dir`` that the model does not name, sorted."""
    named = {im.name for im in model.images}
    found = (p.relative_to(image_dir).as_posix() for p in image_dir.rglob("*")
             if p.suffix.lower() in IMAGE_EXTENSIONS and not p.name.startswith(".") and p.is_file())
    return sorted(n for n in found if n not in named)


def _seen_by_training_views(model: ColmapModel, cameras: Cameras, cfg: SceneConfig, where: Path) -> torch.Tensor:
    """[P] bool: points whose track has at least 2 training images (what SfM on those images alone could
    triangulate)."""
    if model.point_images is None:
        raise UserError("points_from = 'train' needs the points' tracks, which this model does not have", path=where,
                        hint="Use points_from = 'all', or a COLMAP model with tracks (points3D.bin / .txt).")
    names = cameras.image_names
    # the training views as _finish makes them (a held-out view's pose twin is none: its points would leak that view)
    train = {names[i] for i in _without_twins(cameras, make_split(names, cfg, where=where), cfg)[0]["train"]}
    return torch.tensor([len(train.intersection(t)) >= 2 for t in model.point_images], dtype=torch.bool)


def _load_synthetic(path: Path, cfg: SceneConfig, meta: SynthScene, initial_points: bool = True) -> SceneData:
    """A scene written by ``uncertsplat synth`` (``meta``: its ``SynthScene``): either layout, plus GT depth/masks."""
    if meta.layout == "blender":
        found = read_blender(path, cfg)
        scene = _from_transforms(replace(found, source=dict(found.source, kind="synthetic", layout="blender")), cfg,
                                 initial_points)
    else:  # held-out views: every scene.test_every-th, the same as synth's own split when both are the default 8
        scene = _load_colmap(path, cfg, source="synthetic")
    depth_paths, mask_paths = [], []
    for name in scene.cameras.image_names:
        stem = Path(name).stem  # train/view_001.png (Blender layout) and view_001.png share depth/view_001.npy
        d = path / "depth" / f"{stem}.npy"
        if not d.is_file():
            raise UserError("GT depth map missing from the synthetic scene", path=d,
                            hint="Regenerate it with `uncertsplat synth OUT --overwrite`.")
        depth_paths.append(d)
        m = path / "masks" / f"{stem}.png"
        mask_paths.append(m if m.is_file() else None)
    source = dict(scene.source, meta={"preset": meta.preset, "seed": meta.seed,
                                      "generator_version": meta.generator_version, "layout": meta.layout,
                                      "rig": meta.rig, "backdrop": meta.backdrop})
    return replace(
        scene,
        depth_paths=tuple(depth_paths),
        mask_paths=tuple(mask_paths) if all(m is not None for m in mask_paths) else None,
        source=source,
    )


def _from_transforms(found: TransformsScene, cfg: SceneConfig, initial_points: bool = True) -> SceneData:
    """SceneData of a Blender / nerfstudio folder (random initial points when it has no point cloud)."""
    data = _finish(found.cameras, list(found.paths), found.points, found.points_rgb, cfg, source=found.source,
                   default_split=found.split, random_init=initial_points, intrinsics_from=found.file)
    root = Path(found.file) if Path(found.file).is_dir() else Path(found.file).parent
    return _with_notes(data, _alpha_note(list(found.paths), root, cfg))


def _alpha_note(paths: list[Path], root: Path, cfg: SceneConfig) -> list[str]:
    """The note on photos with an alpha channel: the background training sees them over, and what evaluate
    scores (the NeRF-synthetic layout said nothing, and its white background is not our default)."""
    with_alpha = []
    for p in paths:
        if has_alpha(p):
            try:
                with_alpha.append(p.relative_to(root).as_posix())
            except ValueError:
                with_alpha.append(p.name)
    if not with_alpha:
        return []
    return [f"{len(with_alpha)} photo(s) have an alpha channel: where they are transparent, training sees them "
            f"composited over scene.background {list(cfg.background)} (NeRF-synthetic's is white: --set "
            "'scene.background=[1,1,1]'), and evaluate scores them only where alpha >= 0.5 (their objects) "
            f"({list_names(with_alpha, 8)})"]


# ------------------------------------------------------------------------------------- split, normalise
def _named(names: tuple[str, ...], wanted: list[str] | None, indices: list[int] | None, what: str,
           where: Path | None) -> list[int] | None:
    """Sorted indices of explicit image names or indices (None when neither is given)."""
    n = len(names)
    if wanted is not None:
        index = {name: i for i, name in enumerate(names)}
        missing = [t for t in wanted if t not in index]
        if missing:
            raise UserError(f"{what} image(s) not in the scene: {', '.join(missing)}", path=where,
                            hint=f"Valid names look like '{names[0]}'.")
        return sorted({index[t] for t in wanted})
    if indices is not None:
        bad = [i for i in indices if not (0 <= i < n)]
        if bad:
            raise UserError(f"{what} indices out of range 0..{n - 1}: {bad}", path=where)
        return sorted(set(indices))
    return None


def make_split(names: tuple[str, ...], cfg: SceneConfig, where: Path | None = None,
               default: dict[str, tuple[int, ...]] | None = None) -> dict[str, tuple[int, ...]]:
    """Train/test indices: explicit names, explicit indices, ``default`` (e.g. a dataset's own split),
    else every ``test_every``-th image by sorted name starting at index 0. Explicit training views
    (``train_names`` / ``train_indices``) restrict the training set; images in neither set are unused. With
    ``calibration_holdout`` = n, n of the training views move to a third set, ``"calibration"`` (``_set_aside``).

    Raises:
        UserError: a view in both sets, no training view left, or an index/name that does not exist.
    """
    split = _train_test(names, cfg, where, default)
    return _set_aside(split, cfg.calibration_holdout, where) if cfg.calibration_holdout else split


def _held_out_taken(names: tuple[str, ...], cfg: SceneConfig, default: dict[str, tuple[int, ...]] | None,
                    split: dict[str, tuple[int, ...]]) -> list[str]:
    """The names of the default held-out views that explicit training views took into training (``make_split``:
    they give way, silently otherwise), [] when the test views were given or none was taken."""
    explicit_train = cfg.train_names is not None or cfg.train_indices is not None
    explicit_test = cfg.test_names is not None or cfg.test_indices is not None
    if not explicit_train or explicit_test:
        return []
    test = default.get("test", ()) if default is not None else range(0, len(names), cfg.test_every)
    train = set(split["train"]) | set(split.get("calibration", ()))
    return [names[i] for i in test if i in train]


def _set_aside(split: dict[str, tuple[int, ...]], n: int, where: Path | None) -> dict[str, tuple[int, ...]]:
    """``split`` with ``n`` of its training views moved to ``"calibration"``: the middle view of each of n equal runs
    of the training views, so that they spread over the capture as the held-out views do."""
    train = list(split["train"])
    if len(train) - n < 1:
        raise UserError(f"calibration_holdout = {n} takes every one of the {len(train)} training views", path=where,
                        hint="Set aside fewer views for calibration (scene.calibration_holdout).")
    picked = {train[int((j + 0.5) * len(train) / n)] for j in range(n)}
    out = {k: tuple(v) for k, v in split.items() if k != "calibration"}
    out["train"] = tuple(i for i in train if i not in picked)
    out["calibration"] = tuple(sorted(picked))
    return out


def _train_test(names: tuple[str, ...], cfg: SceneConfig, where: Path | None,
                default: dict[str, tuple[int, ...]] | None) -> dict[str, tuple[int, ...]]:
    n = len(names)
    test = _named(names, cfg.test_names, cfg.test_indices, "test", where)
    train = _named(names, cfg.train_names, cfg.train_indices, "training", where)
    if test is None and train is None and default is not None:
        return {k: tuple(v) for k, v in default.items()}
    if test is None:
        if default is not None:
            test = list(default.get("test", ()))
        else:
            test = list(range(0, n, cfg.test_every))
        if train is not None:  # the default held-out views give way to explicit training views
            test = [i for i in test if i not in set(train)]
    if train is None:
        train = [i for i in range(n) if i not in set(test)]
    both = sorted(set(train) & set(test))
    if both:
        raise UserError(f"image(s) both trained on and held out: {', '.join(names[i] for i in both)}", path=where,
                        hint="An image is either a training or a held-out view; fix train_* or test_*.")
    if not train:
        if cfg.train_names == [] or cfg.train_indices == []:  # the user's own empty list, not the held-out views
            key = "train_names" if cfg.train_names == [] else "train_indices"
            raise UserError(f"scene.{key} is empty: no training view", path=where,
                            hint=f"Give the views to train on in scene.{key}, or leave it out to train on every "
                                 "view that is not held out.")
        raise UserError(f"the test split takes all {n} images and leaves no training view", path=where,
                        hint="Hold out fewer images (test_names / test_indices / a larger test_every).")
    return {"train": tuple(train), "test": tuple(test)}


def pose_twins(cameras: Cameras, held_out: Sequence[int], train: Sequence[int]) -> dict[int, list[int]]:
    """The training views that took the same picture as a held-out view, by held-out index ({} when none).

    A held-out view whose twin is trained on is scored on what the model memorised, not on what it learned: a photo
    and its copy under another name or format (which a byte comparison does not find), or the frames of an exposure
    bracket, register at the same pose. A training view's pose differs from held-out view h's by
    delta = max(centre distance / (``TWIN_DISTANCE`` x the rig's radius), angle between the optical axes /
    ``TWIN_ANGLE_DEG``) (a focal length more than 2 % off: another picture, never a twin). h's twins are its
    nearest views by delta up to a jump of ``TWIN_JUMP`` x, each with delta <= 1: a copy or a bracket frame sits a
    hair's breadth away and the next photo a step away. Frames of a dense video or a panning shot step evenly,
    with no such jump, however close; a tripod panorama's other directions are far in angle.
    """
    if not held_out or not train:
        return {}
    c = cameras.centers.double()  # [C,3]
    c = c - c.mean(0)  # centred: cdist in map coordinates (millions) would lose the centimetres
    radius = max(float(c.norm(dim=-1).max()), 1e-12)
    axis = cameras.cam_from_world[:, 2, :3].double()  # [C,3] each camera's optical axis in the world
    axis = axis / axis.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    focal = cameras.K[:, 0, 0].double()  # [C]
    t = torch.as_tensor(list(train))
    out: dict[int, list[int]] = {}
    held = list(held_out)
    rows = max(1, 2**22 // max(len(t), 1))  # held-out views per block: a few [rows,T] float64 arrays of 32 MB
    for start in range(0, len(held), rows):
        h = torch.as_tensor(held[start:start + rows])
        chord = torch.cdist(axis[h], axis[t]).clamp(max=2.0)  # [H,T]; the angle from the chord keeps digits near 0
        angle = torch.rad2deg(2.0 * torch.asin(chord / 2.0))
        delta = torch.maximum(torch.cdist(c[h], c[t]) / (TWIN_DISTANCE * radius), angle / TWIN_ANGLE_DEG)
        delta = delta.masked_fill((focal[h, None] - focal[None, t]).abs() > 0.02 * focal[h, None], math.inf)
        d, order = delta.sort(dim=1)  # [H,T] nearest first
        after = torch.cat([d[:, 1:], torch.full_like(d[:, :1], math.inf)], dim=1)  # the next view's delta
        ends = (d <= 1.0) & (after >= TWIN_JUMP * d.clamp_min(1e-6))  # a twin group can end here
        for i in ends.any(dim=1).nonzero()[:, 0].tolist():
            j = int(ends[i].nonzero()[0, 0])  # the first (tightest) group
            out[int(h[i])] = sorted(int(t[k]) for k in order[i, : j + 1])
    return out


def held_out_twins(cameras: Cameras, split: dict, among: Sequence[int]) -> dict[int, list[int]]:
    """Of the views ``among`` (added or candidate views), those that took the same picture as a held-out or set-aside
    view of ``split``, by that view's index ({} when none). Judged against every training view with them, as the
    split judges (``pose_twins``): the next frame of a dense capture steps as evenly from a held-out one as its
    other neighbours do (no twin), where against ``among`` alone it read as one; a copy sits a hair's breadth away."""
    among = set(among)
    held = [*split.get("test", ()), *split.get("calibration", ())]
    pool = sorted(set(split.get("train", ())) | among)
    found = {h: [t for t in ts if t in among] for h, ts in pose_twins(cameras, held, pool).items()}
    return {h: ts for h, ts in found.items() if ts}


TWIN_NOTE = "took the same picture as a held-out view"
"""Words of ``_without_twins``' note (``with_training_views`` drops the note with the split it described)."""


def with_training_views(data: SceneData, names: Sequence[str]) -> SceneData:
    """``data`` training on the views ``names`` (a run's recorded ones, ``RunScene.train``) when its split's differ
    and the scene holds them all; else ``data`` as it is.

    A run goes on with, and is measured against, the views it trained on, whatever the split rules of a later version
    say (a held-out view's pose twin now leaves training: ``_without_twins``); the twin note, which described the
    other split, goes with it."""
    index = {n: i for i, n in enumerate(data.cameras.image_names)}
    held = {i for k, v in data.split.items() if k != "train" for i in v}
    if [data.cameras.image_names[i] for i in data.split["train"]] == list(names) or not names or \
            not all(n in index for n in names) or any(index[n] in held for n in names):
        return data  # (recorded views now held out or set aside: another split altogether, not a rule's change)
    train = tuple(index[n] for n in names)
    notes = [n for n in data.notes if TWIN_NOTE not in n]
    twins = pose_twins(data.cameras, sorted(held), train)
    if twins:  # the recorded views hold a held-out view's twin: its score is one of memory, and the note says so
        notes.append(f"{sum(map(len, twins.values()))} training view(s) {TWIN_NOTE} (the same camera pose): "
                     f"{_twin_pairs(data.cameras.image_names, twins)}; the run trained on them (its scene.json), so "
                     "those held-out scores measure what the model memorised")
    return replace(data, split={**data.split, "train": train}, notes=tuple(notes))


def _twin_pairs(names: Sequence[str], twins: dict[int, list[int]]) -> str:
    """``pose_twins``' result for a note: "twin, twin (= held-out view); ..." (the first four)."""
    pairs = [f"{', '.join(names[j] for j in js)} (= {names[i]})" for i, js in sorted(twins.items())]
    return "; ".join(pairs[:4]) + ("; ..." if len(pairs) > 4 else "")


CAMERA_MOVE = 1e-4
"""A recorded view's camera counts as changed (``camera_changes``) when its centre moved more than this fraction of
the scene's extent, an axis turned more than this many radians, or a focal length or principal point moved more than
this fraction of the image width: far above float rounding (1e-7), far below what a model's render notices (a
tenth of a pixel at 1000 pixels across)."""


def camera_records(cameras: Cameras, names: Sequence[str]) -> dict[str, list[float]]:
    """{view name: [centre x, y, z, right axis x, y, z, optical axis x, y, z, fx, fy, cx, cy]} of the views ``names``
    in the scene's normalised world (the run's ``scene.json``: what ``camera_changes`` compares a later load with)."""
    index = {n: i for i, n in enumerate(cameras.image_names)}
    sel = [index[n] for n in names if n in index]
    if not sel:
        return {}
    views = cameras[sel].to(device="cpu", dtype=torch.float64)
    R, K = views.cam_from_world[:, :3, :3], views.K  # [V,3,3]
    rows = torch.cat([views.centers, R[:, 0], R[:, 2]], dim=1).numpy().round(7)  # [V,9]
    intr = torch.stack([K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2]], dim=1).numpy().round(4)  # [V,4]
    return {cameras.image_names[i]: [*map(float, r), *map(float, k)] for i, r, k in zip(sel, rows, intr, strict=True)}


def require_same_cameras(recorded: dict[str, list[float]], data: SceneData, scene: Path, why: str) -> None:
    """Refuse a run's scene whose cameras changed since training (``camera_changes`` of its recorded cameras against
    ``data`` as loaded from ``scene``); ``why``: what the change would spoil for the command at hand."""
    changed = camera_changes(recorded, data.cameras, data.extent)
    if changed:
        raise UserError(f"the scene's cameras have changed since this run was trained: {changed}; the model lines up "
                        f"with the cameras it was trained with, so {why}", path=scene,
                        hint="The scene folder was reconstructed again or its cameras edited after training (e.g. "
                             "`reconstruct --overwrite` into the same workspace): restore the workspace the run was "
                             f"trained on, or train a new run on this one (uncertsplat train {q(scene)} -o NEW_RUN).")


def in_run_frame(cfg: SceneConfig, world_from_source, test: list[str], pool: list[str]) -> SceneConfig:
    """``cfg`` with a run's own frame (``world_from_source``, [4,4]), held-out views (``test``) and pool of training
    and set-aside views (``pool``, unless the config names its training views) fixed: how a scene that photos
    joined since the run began (``reconstruct --extend``) is loaded for it, where the normalisation over the grown
    set of cameras, the every-n-th split by name and the views set aside over the grown pool would move them."""
    update: dict = {"world_from_source": [list(map(float, r)) for r in world_from_source]}
    if test:
        update.update(test_names=list(test), test_indices=None)
    if cfg.train_names is None and pool:
        update.update(train_names=list(pool), train_indices=None)
    return SceneConfig.model_validate({**cfg.model_dump(), **update})


def load_for_run(scene: Path, cfg: SceneConfig, info, initial_points: bool = True) -> tuple[SceneData, str | None]:
    """The scene as the run of ``info`` (its ``RunScene``) sees it, and a note when that took its own frame: loaded
    as ``cfg`` says; where the run's recorded cameras no longer line up in the normalised world, or its held-out
    views moved, loaded again in the run's frame with its split and scale (``in_run_frame``), which is kept when the
    cameras line up there: photos joined the scene since the run began (``reconstruct --extend``), whose cameras
    moved the normalisation over all of them. Otherwise the first load is returned, for the caller's checks to
    refuse (a scene reconstructed again matches in neither frame)."""
    from dataclasses import replace

    try:
        data, failed = load_scene(scene, cfg, initial_points=initial_points), None
    except UserError as err:  # e.g. the every-n-th split over the grown list holding out a view given to train on
        if info is None or not info.cameras:
            raise
        data, failed = None, err
    if info is None or not info.cameras:
        return data, None
    if data is not None:
        names = data.cameras.image_names
        held = [names[i] for i in data.split.get("test", ())]
        moved = camera_changes(info.cameras, data.cameras, data.extent) is not None
        if not moved and (not info.test or held == list(info.test)):
            return data, None
    else:
        moved = True
    try:
        own = load_scene(scene, in_run_frame(cfg, info.world_from_source, info.test,
                                             [*info.train, *info.calibration]), initial_points=initial_points)
    except UserError:  # (a recorded view gone from the scene: the caller's checks say so)
        if failed is not None:
            raise failed from None
        return data, None
    own = replace(own, scene_scale=float(info.scene_scale))
    if camera_changes(info.cameras, own.cameras, own.extent) is not None:
        if failed is not None:
            raise failed
        return data, None
    why = ("the scene's cameras, normalised over all of them, no longer line up with this run's (photos joined the "
           "scene since it began: reconstruct --extend)" if moved else
           "the scene's split by name holds out other views than this run did (photos joined or came back since)")
    return own, why + ": loaded in the run's own frame and scale (scene.json), with its held-out views"


FRAME_CHANGE = 1e-6
"""``frame_change``: the relative change of a scene's normalisation beyond which its source frame counts as changed."""


def frame_change(recorded, now) -> str | None:
    """How the scene folder's source frame differs from the one a run recorded (``RunScene.world_from_source`` against
    ``SceneData.world_from_source`` as loaded now, both [4,4] world-from-source similarities), in words, or None when
    they agree within ``FRAME_CHANGE``. The run's cameras may agree in its normalised world while the folder's frame
    changed as a whole: a COLMAP model aligned to metres after training (``model_aligner``), or moved or turned.
    Depths and poses in the scene's units then follow the folder as it is now."""
    a = torch.as_tensor(recorded, dtype=torch.float64)
    b = torch.as_tensor(now, dtype=torch.float64)
    if a.shape != (4, 4) or b.shape != (4, 4):
        return None
    sa, sb = similarity_scale(a), similarity_scale(b)
    if not (sa > 0 and sb > 0):
        return None
    # the same world point from either frame: x_source_now = S x_source_then with S = b^-1 a
    S = torch.linalg.inv(b) @ a
    ratio = sa / sb  # the source units grew by this
    rest = S[:3, :3] / ratio - torch.eye(3, dtype=torch.float64)
    shift = float(S[:3, 3].norm()) * sb  # in the run's normalised units
    parts = []
    if abs(ratio - 1.0) > FRAME_CHANGE:
        parts.append(f"its units are {ratio:.6g}x the ones the run was trained in")
    if float(rest.abs().max()) > FRAME_CHANGE:
        parts.append("it is turned")
    if shift > FRAME_CHANGE:
        parts.append("its origin moved")
    return ", ".join(parts) if parts else None


def camera_changes(recorded: dict[str, list[float]], cameras: Cameras, extent: float) -> str | None:
    """What changed in the cameras of the views ``recorded`` (``camera_records`` of a run's scene) in the scene
    ``cameras`` as it loads now, in words (the view that moved most and how many did), or None when none moved by
    more than ``CAMERA_MOVE``. Views the scene no longer holds are not compared (the caller checks names)."""
    now = camera_records(cameras, list(recorded))
    if not now:
        return None
    names = list(now)
    a = torch.tensor([recorded[n] for n in names], dtype=torch.float64)  # [V,13]
    b = torch.tensor([now[n] for n in names], dtype=torch.float64)
    moved = (a[:, :3] - b[:, :3]).norm(dim=1) / max(extent, 1e-12)  # [V]

    def angle(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        return torch.atan2(torch.linalg.cross(u, v).norm(dim=1), (u * v).sum(dim=1))

    turned = torch.maximum(angle(a[:, 3:6], b[:, 3:6]), angle(a[:, 6:9], b[:, 6:9]))  # [V] radians
    intr = (a[:, 9:] - b[:, 9:]).abs().amax(dim=1) / max(cameras.width, 1)  # [V]
    changed = (moved > CAMERA_MOVE) | (turned > CAMERA_MOVE) | (intr > CAMERA_MOVE)
    if not bool(changed.any()):
        return None
    worst = int(torch.stack([moved, turned, intr]).amax(dim=0).argmax())
    what = [f"moved {100 * float(moved[worst]):.3g} % of the scene's extent" if moved[worst] > CAMERA_MOVE else "",
            f"turned {math.degrees(float(turned[worst])):.3g} degrees" if turned[worst] > CAMERA_MOVE else "",
            "changed its intrinsics (focal length or principal point: "
            f"{[round(x, 2) for x in a[worst, 9:].tolist()]} -> {[round(x, 2) for x in b[worst, 9:].tolist()]} px)"
            if intr[worst] > CAMERA_MOVE else ""]
    return (f"{int(changed.sum())} of its {len(names)} views' cameras differ from those it was trained with "
            f"({names[worst]}'s camera {', '.join(w for w in what if w)})")


def _without_twins(cameras: Cameras, split: dict[str, tuple[int, ...]], cfg: SceneConfig
                   ) -> tuple[dict[str, tuple[int, ...]], str | None]:
    """``split`` with the training twins of its held-out and calibration views left out of training (``pose_twins``)
    and a note naming them; with training views given by hand (scene.train_names / train_indices) they stay, and the
    note says so."""
    names = cameras.image_names
    held_out = [*split["test"], *split.get("calibration", ())]
    twins = pose_twins(cameras, held_out, split["train"])
    if not twins:
        return split, None
    what = (f"{sum(map(len, twins.values()))} training view(s) {TWIN_NOTE} (the same camera pose: a copy under "
            f"another name or format, or an exposure bracket): {_twin_pairs(names, twins)}")
    if cfg.train_names is not None or cfg.train_indices is not None:
        return split, what + "; they are trained on as given, so those held-out scores measure what the model " \
                             "memorised (leave them out of scene.train_names / train_indices)"
    drop = {j for js in twins.values() for j in js}
    kept = tuple(i for i in split["train"] if i not in drop)
    if not kept:
        return split, what + "; kept in training, the only views there are"
    return {**split, "train": kept}, what + "; left out of training, so the held-out scores measure what was learned"


def normalization(cameras: Cameras, center: torch.Tensor | None = None) -> tuple[torch.Tensor, float]:
    """The similarity ``world_from_source`` [4,4] (float64) that moves ``center`` [3] (default: the camera
    centroid) to the origin and scales by ``s`` so that the farthest camera is at distance 1 from the camera
    centroid, and ``s``.

    The scale is the same whatever the centre: a different centre only translates the scene, which
    training does not depend on (scene_scale, the extent and the learning rates stay as they were).
    """
    centers = cameras.centers.double()
    mid = centers.mean(0)
    radius = float((centers - mid).norm(dim=-1).max())
    s = 1.0 / radius if radius > 1e-12 else 1.0
    c = mid if center is None else center.to(torch.float64)
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] *= s
    T[:3, 3] = -s * c
    return T, s


def _alpha_masks(cameras: Cameras, paths: list[Path], train: tuple[int, ...]):
    """(training cameras, their foreground masks) for carving random initial points, or None when no training
    image has real transparency (an alpha channel with some alpha < 1).

    A mask is alpha > 0.5, reduced to at most ``_CARVE_SIZE`` pixels on the longer side (a reduced pixel is
    foreground when any pixel under it is) and dilated by one reduced pixel, so that rounding never carves the
    object's rim. Images without alpha, or of another size than their camera, judge nothing (None).
    """
    import torch.nn.functional as F

    from uncertsplat.io.images import read_alpha

    f = max(1, math.ceil(max(cameras.width, cameras.height) / _CARVE_SIZE))
    masks: list[torch.Tensor | None] = []
    transparent = False
    for i in train:
        a = read_alpha(paths[i])
        if a is None or a.shape != (cameras.height, cameras.width):
            masks.append(None)
            continue
        transparent = transparent or bool((a < 1.0).any())
        fg = torch.from_numpy(a > 0.5).float()[None, None]
        fg = F.max_pool2d(fg, f, ceil_mode=True)  # any foreground pixel under a reduced one
        fg = F.max_pool2d(fg, 3, stride=1, padding=1)  # dilate by one reduced pixel
        masks.append(fg[0, 0] > 0)
    return (cameras[list(train)], masks) if transparent else None


def normalized_cam_from_world(cam_from_world: torch.Tensor, world_from_source: torch.Tensor) -> torch.Tensor:
    """[C,4,4] float64: source-frame ``cam_from_world`` [C,4,4] in the normalised world of the similarity
    ``world_from_source`` [4,4] (``SceneData.world_from_source``: x' = s x + T[:3, 3]).

    cam_from_world' = S_s * cam_from_world * world_from_source^-1 (the camera frame scaled by s too, so the result
    stays rigid): R' = R, t' = s * (R c + t) with T = [sI, -s c]."""
    T = world_from_source.double()
    s = float(T[0, 0])
    c2w = cam_from_world.double()
    new = c2w.clone()
    new[:, :3, 3] = s * ((c2w[:, :3, :3] @ (-T[:3, 3] / s)) + c2w[:, :3, 3])
    return new


def _check_intrinsics(cameras: Cameras, where: Path, outside_ok: bool = False) -> None:
    """Refuse focal lengths that are not positive and finite (a model edited or written by other tools: a focal of
    0 trains a model that never changes, a negative one a mirrored scene, both without a word), and, unless
    ``outside_ok`` (``SceneConfig.principal_point_outside``), a principal point outside the image or in its outer
    ``types.EDGE_MARGIN`` (intrinsics of the full-size photos given with downscaled files: the model trains,
    off-centre, several dB worse, and the warnings blame the poses; halved files put it on the corner, which counted
    as inside)."""
    K = cameras.K.double()
    f = torch.stack([K[:, 0, 0], K[:, 1, 1]], dim=-1)  # [C,2]
    bad = focal_unusable(K) | ~torch.isfinite(K[:, :2, 2]).all(-1)
    if bool(bad.any()):
        i = int(bad.nonzero()[0, 0])
        names = [cameras.image_names[j] for j in bad.nonzero()[:, 0].tolist()]
        raise UserError(f"{len(names)} image(s) have camera intrinsics that are not usable ({list_names(names)}: "
                        f"focal lengths {float(f[i, 0]):g} / {float(f[i, 1]):g} px, principal point "
                        f"{float(K[i, 0, 2]):g}, {float(K[i, 1, 2]):g}); focal lengths must be positive and finite",
                        path=where, hint="Fix the camera in the model, or reconstruct the photos again.")
    W, H = cameras.width, cameras.height
    outside = principal_point_near_edge(K, W, H)  # [C] (outside the image too)
    if bool(outside.any()) and not outside_ok:
        i = int(outside.nonzero()[0, 0])
        names = [cameras.image_names[j] for j in outside.nonzero()[:, 0].tolist()]
        raise UserError(f"view '{names[0]}'" + (f" (and {len(names) - 1} more: {list_names(names[1:], 4)})"
                                                 if len(names) > 1 else "")
                        + f" has its principal point {principal_point_place(K[i], W, H, 'its')}",
                        path=where,
                        hint=f"Give the intrinsics of the {W}x{H} images that are read (scale the focal lengths and the "
                             "principal point by the ratio of the sizes), or the images the intrinsics were measured "
                             "on; views cropped from larger photos, whose optical centre lies outside them or near "
                             "their edge, take --set scene.principal_point_outside=true.")


def _finish(cameras: Cameras, paths: list[Path], points: torch.Tensor, rgb: torch.Tensor, cfg: SceneConfig,
            source: dict, default_split: dict | None = None, random_init: bool = False,
            photo_fits: tuple | None = None, notes: list[str] | tuple[str, ...] = (),
            intrinsics_from: Path | None = None) -> SceneData:
    """Split, choose the centre, add random initial points (``random_init`` and no points), normalise;
    ``photo_fits`` and ``notes`` are ``_colmap_cameras``'s (recorded in ``source`` too); ``intrinsics_from`` is the
    file that gave the intrinsics (for errors; default: the COLMAP model, else the scene folder)."""
    _check_intrinsics(cameras, intrinsics_from or Path(source.get("model", source["path"])),
                      outside_ok=cfg.principal_point_outside)
    split = make_split(cameras.image_names, cfg, where=Path(source["path"]), default=default_split)
    taken = _held_out_taken(cameras.image_names, cfg, default_split, split)
    if taken:
        notes = [*notes, f"the training views given (scene.train_names / train_indices) include {len(taken)} of the "
                         f"default held-out views ({', '.join(taken[:4])}{', ...' if len(taken) > 4 else ''}), which "
                         f"are trained on: {len(split['test'])} held out now (scene.test_names / test_indices "
                         "choose them)"]
    split, twin_note = _without_twins(cameras, split, cfg)
    if twin_note:
        notes = [*notes, twin_note]
    choice = choose_center(cameras, has_points=points.shape[0] > 0, mode=cfg.center, where=Path(source["path"]))
    if points.shape[0] == 0 and random_init:
        # 100k points (3DGS) for NeRF-synthetic at full size, fewer for small or downscaled scenes: there 100k
        # random Gaussians make an opaque fog that a short training cannot clear. Carved points (alpha masks)
        # all lie in the object's visual hull and make no fog, so twice as many do better. Measured in
        # BENCHMARKS.md, "Object scenes without sparse points".
        carve = _alpha_masks(cameras, paths, split["train"]) if cfg.carve else None
        pixels = len(split["train"]) * (cameras.width / cfg.downscale) * (cameras.height / cfg.downscale)
        per_point = _PIXELS_PER_RANDOM_POINT if carve is None else _PIXELS_PER_CARVED_POINT
        n = max(1, min(cfg.max_points, _RANDOM_POINTS, int(pixels // per_point)))
        g = torch.Generator().manual_seed(_POINT_SEED)
        points, rgb, what = random_points(cameras, choice, n, g, carve=carve)
        source = dict(source, initial_points=what)
    else:
        source = dict(source, initial_points=f"{points.shape[0]} sparse points")
    if points.shape[0] > cfg.max_points:
        g = torch.Generator().manual_seed(_POINT_SEED)
        keep = torch.randperm(points.shape[0], generator=g)[: cfg.max_points].sort().values
        points, rgb = points[keep], rgb[keep]
    if cfg.world_from_source is not None:  # a run's own frame, kept as photos join its scene
        T = torch.tensor(cfg.world_from_source, dtype=torch.float64)
        s = similarity_scale(T)
    elif cfg.normalize:
        T, s = normalization(cameras, choice.center)
    else:
        T, s = torch.eye(4, dtype=torch.float64), 1.0
    new = normalized_cam_from_world(cameras.cam_from_world, T)
    pts = (points.double() * s + T[:3, 3]).float()
    cams = Cameras(new.float(), cameras.K.float(), cameras.width, cameras.height, cameras.image_names)
    scene_scale = float((cams.centers.double() - cams.centers.double().mean(0)).norm(dim=-1).max())
    if cfg.downscale != 1.0:
        cams = cams.scaled(1.0 / cfg.downscale)
    source = dict(source, background=list(cfg.background), downscale=cfg.downscale)
    if photo_fits is not None:
        source = dict(source, photo_fits={name: [f.turns, f.x0, f.y0, f.width, f.height, f.turned_width,
                                                 f.turned_height, *f.scaled]
                                          for name, f in zip(cams.image_names, photo_fits, strict=True)})
    return SceneData(
        cameras=cams,
        image_paths=tuple(paths),
        split=split,
        points=pts,
        points_rgb=rgb.float().clamp(0, 1),
        scene_scale=scene_scale,
        world_from_source=T,  # float64: a map in UTM coordinates (1e6-1e7) loses metres in float32
        depth_scale_to_gt=1.0 / s,
        source=source,
        center=tuple(float(v) for v in choice.center),
        center_method=choice.method,
        center_reason=choice.reason,
        photo_fits=photo_fits,
        notes=tuple(notes),
    )
