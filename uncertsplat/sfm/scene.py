"""Scene loading: COLMAP workspaces, NeRF-synthetic folders and our synthetic scenes -> ``SceneData``.

Detection order for a folder ``P``:

1. ``P/scene.json`` written by ``uncertsplat synth`` (+ ``sparse/0``): a COLMAP model with GT depth/masks.
2. ``P/transforms_train.json`` (and/or ``transforms_test.json``): a NeRF-synthetic (Blender) folder.
3. ``P/images/`` + ``P/sparse/0`` (or a model directly in ``P/sparse``): a COLMAP workspace.

Images are sorted by name; cameras are normalised (centred on the camera centroid, scaled so the
farthest camera is at distance 1) and the applied similarity is recorded as ``world_from_source``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch

from uncertsplat.config import SceneConfig
from uncertsplat.errors import UserError
from uncertsplat.io.images import IMAGE_EXTENSIONS, read_image_size
from uncertsplat.sfm.colmap_io import ColmapModel, has_model, read_colmap_model
from uncertsplat.types import Cameras, SceneData

_NERF_SPLITS = ("train", "val", "test")
_POINT_SEED = 0  # seeds random initial points (NeRF-synthetic) and point subsampling: loading is deterministic


# ----------------------------------------------------------------------------------------------- public
def load_scene(path: str | Path, cfg: SceneConfig | None = None) -> SceneData:
    """Load a scene folder (see the module docstring for what is recognised).

    Args:
        path: the scene folder.
        cfg: downscale, split and normalisation options (defaults when None).

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
    if (path / "scene.json").is_file() and _is_synth_meta(path / "scene.json"):
        return _load_synthetic(path, cfg)
    if (path / "transforms_train.json").is_file() or (path / "transforms_test.json").is_file():
        return _load_nerf_synthetic(path, cfg)
    return _load_colmap(path, cfg)


def find_sparse_model(path: Path) -> Path:
    """``path/sparse/0`` when it holds a model, else ``path/sparse`` itself; UserError when neither does."""
    for cand in (path / "sparse" / "0", path / "sparse"):
        if has_model(cand):
            return cand
    if (path / "sparse").is_dir():
        raise UserError("no COLMAP model in sparse/0 (expected cameras, images, points3D as .bin or .txt)",
                        path=path / "sparse" / "0",
                        hint="Point to the workspace written by `uncertsplat reconstruct`, or re-run it.")
    raise UserError("missing sparse/0: this folder is not a COLMAP workspace", path=path / "sparse" / "0",
                    hint="Run `uncertsplat reconstruct PHOTOS -o WORKSPACE` to create one.")


# ---------------------------------------------------------------------------------------------- loaders
def _is_synth_meta(meta: Path) -> bool:
    from uncertsplat.data.synthetic import SCENE_KIND

    try:
        return json.loads(meta.read_text(encoding="utf-8")).get("kind") == SCENE_KIND
    except (OSError, ValueError, AttributeError):
        return False


def _check_reconstruct_report(path: Path) -> None:
    report = path / "reconstruct_report.json"
    if not report.is_file():
        return
    try:
        data = json.loads(report.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return  # the report is informative only; a damaged one does not block loading
    if isinstance(data, dict) and data.get("success") is False:
        why = data.get("reason") or data.get("message") or data.get("error")
        raise UserError(
            "this workspace comes from a failed reconstruction" + (f" ({why})" if why else ""),
            path=report,
            hint="Read the report, fix the photos (overlap, sharpness) and re-run `uncertsplat reconstruct`.",
        )


def _colmap_cameras(model: ColmapModel, image_dir: Path, sparse: Path) -> tuple[Cameras, list[Path]]:
    """Sorted, validated cameras and image paths of a COLMAP model."""
    if not model.images:
        raise UserError("the COLMAP model has no registered images", path=sparse,
                        hint="Re-run `uncertsplat reconstruct` with more overlapping photos.")
    for cam in model.cameras.values():
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
    if len(sizes) > 1:
        raise UserError(
            f"the images have different sizes ({', '.join(f'{w}x{h}' for w, h in sorted(sizes))}) but one "
            "image size is assumed",
            path=sparse,
            hint="Resize all photos to one size (or undistort to a common size) and reconstruct again.",
        )
    width, height = sizes.pop()
    paths = []
    for im in images:
        p = image_dir / im.name
        if not p.is_file():
            raise UserError(f"image '{im.name}' named in the COLMAP model is missing", path=p,
                            hint=f"Put the image into {image_dir} or reconstruct again without it.")
        w, h = read_image_size(p)
        if (w, h) != (width, height):
            raise UserError(
                f"image is {w}x{h} but its COLMAP camera is {width}x{height} (one camera size is assumed)",
                path=p,
                hint="Use the undistorted images the model was made for, or reconstruct again.",
            )
        paths.append(p)
    c2w = torch.tensor(np.stack([im.cam_from_world for im in images]), dtype=torch.float32)
    K = torch.tensor(np.stack([model.cameras[im.camera_id].K for im in images]), dtype=torch.float32)
    return Cameras(c2w, K, width, height, tuple(im.name for im in images)), paths


def _load_colmap(path: Path, cfg: SceneConfig, source: str = "colmap") -> SceneData:
    _check_reconstruct_report(path)
    sparse = find_sparse_model(path)
    image_dir = path / "images"
    if not image_dir.is_dir():
        raise UserError("missing images/ folder beside sparse/", path=image_dir,
                        hint="A COLMAP workspace needs the (undistorted) images in WORKSPACE/images.")
    model = read_colmap_model(sparse)
    cameras, paths = _colmap_cameras(model, image_dir, sparse)
    points = torch.tensor(model.points, dtype=torch.float32).reshape(-1, 3)
    rgb = torch.tensor(model.points_rgb, dtype=torch.float32).reshape(-1, 3) / 255.0
    return _finish(cameras, paths, points, rgb, cfg, source={"kind": source, "path": str(path),
                                                            "model": str(sparse)})


def _load_synthetic(path: Path, cfg: SceneConfig) -> SceneData:
    scene = _load_colmap(path, cfg, source="synthetic")
    depth_paths, mask_paths = [], []
    for name in scene.cameras.image_names:
        stem = Path(name).stem
        d = path / "depth" / f"{stem}.npy"
        if not d.is_file():
            raise UserError("GT depth map missing from the synthetic scene", path=d,
                            hint="Regenerate it with `uncertsplat synth OUT --overwrite`.")
        depth_paths.append(d)
        m = path / "masks" / f"{stem}.png"
        mask_paths.append(m if m.is_file() else None)
    meta = json.loads((path / "scene.json").read_text(encoding="utf-8"))
    source = dict(scene.source, meta={k: meta.get(k) for k in ("preset", "seed", "generator_version")})
    from dataclasses import replace

    return replace(
        scene,
        depth_paths=tuple(depth_paths),
        mask_paths=tuple(mask_paths) if all(m is not None for m in mask_paths) else None,
        source=source,
    )


def _nerf_frames(path: Path) -> list[tuple[str, str, np.ndarray, dict]]:
    """(name, split, c2w OpenGL [4,4], meta) for every frame of every transforms_*.json."""
    frames = []
    for split in _NERF_SPLITS:
        f = path / f"transforms_{split}.json"
        if not f.is_file():
            continue
        try:
            meta = json.loads(f.read_text(encoding="utf-8"))
            entries = meta["frames"]
        except (OSError, ValueError, KeyError, TypeError) as err:
            raise UserError(f"not a valid transforms file ({err})", path=f,
                            hint="Expected the NeRF-synthetic layout: {camera_angle_x, frames: [...]}") from None
        for fr in entries:
            rel = str(fr["file_path"]).removeprefix("./")
            if Path(rel).suffix.lower() not in IMAGE_EXTENSIONS:
                rel = rel + ".png"
            frames.append((rel, split, np.asarray(fr["transform_matrix"], dtype=np.float64), meta))
    return frames


def _load_nerf_synthetic(path: Path, cfg: SceneConfig) -> SceneData:
    frames = _nerf_frames(path)
    if not frames:
        raise UserError("the transforms files list no frames", path=path / "transforms_train.json")
    frames.sort(key=lambda fr: fr[0])
    width = height = None
    c2w_list, K_list, paths = [], [], []
    for name, _, c2w, meta in frames:
        p = path / name
        if not p.is_file():
            raise UserError(f"image '{name}' named in the transforms file is missing", path=p,
                            hint="Check that the dataset was extracted completely.")
        w, h = read_image_size(p)
        if width is None:
            width, height = w, h
        elif (w, h) != (width, height):
            raise UserError(f"image is {w}x{h}, others are {width}x{height} (one image size is assumed)",
                            path=p, hint="Resize all images to one size.")
        if "fl_x" in meta:
            fx = float(meta["fl_x"])
            fy = float(meta.get("fl_y", fx))
        elif "camera_angle_x" in meta:
            fx = 0.5 * w / math.tan(0.5 * float(meta["camera_angle_x"]))
            fy = 0.5 * h / math.tan(0.5 * float(meta["camera_angle_y"])) if "camera_angle_y" in meta else fx
        else:
            raise UserError("no focal length (camera_angle_x or fl_x) in the transforms file",
                            path=path / "transforms_train.json")
        cx = float(meta.get("cx", w / 2.0))
        cy = float(meta.get("cy", h / 2.0))
        # Blender/OpenGL camera axes (x right, y up, z backward) -> OpenCV (x right, y down, z forward).
        c2w = c2w.copy()
        c2w[:3, 1:3] *= -1.0
        c2w_list.append(np.linalg.inv(c2w))
        K_list.append(np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=np.float64))
        paths.append(p)
    cameras = Cameras(torch.tensor(np.stack(c2w_list), dtype=torch.float32),
                      torch.tensor(np.stack(K_list), dtype=torch.float32), width, height,
                      tuple(fr[0] for fr in frames))
    # No sparse points: random points in a box around the object, as 3DGS does for Blender scenes
    # (the box spans a third of the camera rig, [-1.3, 1.3]^3 for the usual radius-4 rig).
    g = torch.Generator().manual_seed(_POINT_SEED)
    centers = cameras.centers.double()
    mid = centers.mean(0)
    half = (centers.max(0).values - centers.min(0).values) / 6.0
    n = min(cfg.max_points, 100_000)
    points = (mid + (torch.rand(n, 3, generator=g, dtype=torch.float64) * 2 - 1) * half).float()
    rgb = torch.rand(n, 3, generator=g)
    file_split = {
        "train": tuple(i for i, fr in enumerate(frames) if fr[1] != "test"),
        "test": tuple(i for i, fr in enumerate(frames) if fr[1] == "test"),
    }
    return _finish(cameras, paths, points, rgb, cfg, source={"kind": "nerf_synthetic", "path": str(path)},
                   default_split=file_split if file_split["test"] and file_split["train"] else None)


# ------------------------------------------------------------------------------------- split, normalise
def make_split(names: tuple[str, ...], cfg: SceneConfig, where: Path | None = None,
               default: dict[str, tuple[int, ...]] | None = None) -> dict[str, tuple[int, ...]]:
    """Train/test indices: explicit names, explicit indices, ``default`` (e.g. a dataset's own split),
    else every ``test_every``-th image by sorted name starting at index 0."""
    n = len(names)
    if cfg.test_names is not None:
        index = {name: i for i, name in enumerate(names)}
        missing = [t for t in cfg.test_names if t not in index]
        if missing:
            raise UserError(f"test image(s) not in the scene: {', '.join(missing)}", path=where,
                            hint=f"Valid names look like '{names[0]}'.")
        test = sorted({index[t] for t in cfg.test_names})
    elif cfg.test_indices is not None:
        bad = [i for i in cfg.test_indices if not (0 <= i < n)]
        if bad:
            raise UserError(f"test indices out of range 0..{n - 1}: {bad}", path=where)
        test = sorted(set(cfg.test_indices))
    elif default is not None:
        return {k: tuple(v) for k, v in default.items()}
    else:
        test = list(range(0, n, cfg.test_every))
    train = [i for i in range(n) if i not in set(test)]
    if not train:
        raise UserError(f"the test split takes all {n} images and leaves no training view", path=where,
                        hint="Hold out fewer images (test_names / test_indices / a larger test_every).")
    return {"train": tuple(train), "test": tuple(test)}


def normalization(cameras: Cameras) -> tuple[torch.Tensor, float]:
    """The similarity ``world_from_source`` [4,4] (float64) that centres the camera centroid at the
    origin and puts the farthest camera at distance 1, and its scale factor."""
    centers = cameras.centers.double()
    mid = centers.mean(0)
    radius = float((centers - mid).norm(dim=-1).max())
    s = 1.0 / radius if radius > 1e-12 else 1.0
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] *= s
    T[:3, 3] = -s * mid
    return T, s


def _finish(cameras: Cameras, paths: list[Path], points: torch.Tensor, rgb: torch.Tensor, cfg: SceneConfig,
            source: dict, default_split: dict | None = None) -> SceneData:
    split = make_split(cameras.image_names, cfg, where=Path(source["path"]), default=default_split)
    if points.shape[0] > cfg.max_points:
        g = torch.Generator().manual_seed(_POINT_SEED)
        keep = torch.randperm(points.shape[0], generator=g)[: cfg.max_points].sort().values
        points, rgb = points[keep], rgb[keep]
    if cfg.normalize:
        T, s = normalization(cameras)
    else:
        T, s = torch.eye(4, dtype=torch.float64), 1.0
    # cam_from_world' = S_s * cam_from_world * world_from_source^-1 (camera frame scaled by s too,
    # so the result stays rigid): R' = R, t' = s * (R c + t) with T = [sI, -s c].
    c2w = cameras.cam_from_world.double()
    R = c2w[:, :3, :3]
    t = c2w[:, :3, 3]
    mid = -T[:3, 3] / s
    new = c2w.clone()
    new[:, :3, 3] = s * ((R @ mid) + t)
    pts = (points.double() * s + T[:3, 3]).float()
    cams = Cameras(new.float(), cameras.K.clone(), cameras.width, cameras.height, cameras.image_names)
    scene_scale = float((cams.centers.double() - cams.centers.double().mean(0)).norm(dim=-1).max())
    if cfg.downscale != 1.0:
        cams = cams.scaled(1.0 / cfg.downscale)
    source = dict(source, background=list(cfg.background), downscale=cfg.downscale)
    return SceneData(
        cameras=cams,
        image_paths=tuple(paths),
        split=split,
        points=pts,
        points_rgb=rgb.float().clamp(0, 1),
        scene_scale=scene_scale,
        world_from_source=T.float(),
        depth_scale_to_gt=1.0 / s,
        source=source,
    )
