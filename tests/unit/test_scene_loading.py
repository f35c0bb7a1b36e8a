"""load_scene on our synthetic scene, COLMAP workspaces (binary/text) and NeRF-synthetic folders,
and every bad input it must refuse with a UserError naming the file."""

from __future__ import annotations

import json
import math
import re
import shutil
from pathlib import Path

import numpy as np
import pycolmap  # tests may build odd COLMAP models directly; the package goes through sfm/colmap_io
import pytest
import torch

from tests.fixtures import tiny_scene_path  # noqa: F401
from uncertsplat.config import SceneConfig
from uncertsplat.data.dataset import load_depths, load_images, load_masks
from uncertsplat.errors import UserError
from uncertsplat.io.images import read_exr, read_image, write_png
from uncertsplat.sfm.scene import camera_changes, camera_records, load_scene
from uncertsplat.types import Cameras


@pytest.fixture
def workspace(tiny_scene_path, tmp_path):  # noqa: F811
    """A plain COLMAP workspace (images/ + sparse/0) copied from the tiny scene, safe to modify."""
    ws = tmp_path / "ws"
    shutil.copytree(tiny_scene_path / "images", ws / "images")
    shutil.copytree(tiny_scene_path / "sparse", ws / "sparse")
    return ws


def _raises(path, cfg=None, match=None, name=None):
    with pytest.raises(UserError) as info:
        load_scene(path, cfg or SceneConfig())
    text = str(info.value)
    if match:
        assert match in text, text
    if name:
        assert name in text, text
    return text


# ----------------------------------------------------------------------------------------------- loading
def test_workspace_matches_synthetic_scene(tiny_scene_path, workspace):  # noqa: F811
    a = load_scene(tiny_scene_path)
    b = load_scene(workspace)
    assert a.source["kind"] == "synthetic" and b.source["kind"] == "colmap"
    torch.testing.assert_close(a.cameras.cam_from_world, b.cameras.cam_from_world)
    assert b.depth_paths is None and a.depth_paths is not None


def test_normalisation(tiny_scene_path):  # noqa: F811
    raw = load_scene(tiny_scene_path, SceneConfig(normalize=False))
    norm = load_scene(tiny_scene_path, SceneConfig())
    c = norm.cameras.centers.double()
    assert c.mean(0).abs().max() < 1e-5
    assert abs(c.norm(dim=-1).max().item() - 1.0) < 1e-5
    assert norm.scene_scale == pytest.approx(1.0, abs=1e-5)
    T = norm.world_from_source.double()
    src = torch.cat([raw.cameras.centers.double(), torch.ones(len(c), 1, dtype=torch.float64)], 1)
    torch.testing.assert_close((src @ T.T)[:, :3], c, atol=1e-5, rtol=0)
    pts = torch.cat([raw.points.double(), torch.ones(len(raw.points), 1, dtype=torch.float64)], 1)
    torch.testing.assert_close((pts @ T.T)[:, :3], norm.points.double(), atol=1e-5, rtol=0)
    # rotations unchanged, cameras stay rigid
    torch.testing.assert_close(norm.cameras.cam_from_world[:, :3, :3], raw.cameras.cam_from_world[:, :3, :3])
    # GT depth converted into normalised units
    s = T[0, 0].item()
    assert norm.depth_scale_to_gt == pytest.approx(1 / s)
    torch.testing.assert_close(load_depths(norm, [2]), load_depths(raw, [2]) * s, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize(("scale", "offset"), [(1.0, 1e7), (1000.0, 5.4e9)])
def test_the_frame_map_holds_far_from_the_origin(workspace, scale, offset):
    """A map in UTM-like coordinates (1e7, or millimetres 5e9 from the origin): world_from_source maps each camera's
    centre, as COLMAP has it in float64, onto the normalised camera to well under a pixel's worth (it was stored in
    float32: 0.1 run units off at 1e7, so Predictor.cameras_from_source, select-views' pose files and a PLY moved
    back into the map were 0.3 source units off)."""
    rec = pycolmap.Reconstruction(str(workspace / "sparse" / "0"))
    rec.transform(pycolmap.Sim3d(np.hstack([scale * np.eye(3), [[offset], [0.0], [0.0]]])))
    rec.write(str(workspace / "sparse" / "0"))
    norm = load_scene(workspace, SceneConfig())
    T = norm.world_from_source
    assert T.dtype == torch.float64
    by_name = {img.name: img.projection_center() for img in rec.images.values()}
    src = torch.tensor(np.stack([by_name[n] for n in norm.cameras.image_names]), dtype=torch.float64)  # [C,3]
    mapped = src @ T[:3, :3].T + T[:3, 3]
    torch.testing.assert_close(mapped, norm.cameras.centers.double(), atol=1e-5, rtol=0)


def test_downscale(tiny_scene_path):  # noqa: F811
    full = load_scene(tiny_scene_path)
    half = load_scene(tiny_scene_path, SceneConfig(downscale=2))
    assert (half.cameras.width, half.cameras.height) == (64, 48)
    torch.testing.assert_close(half.cameras.K[:, :2], full.cameras.K[:, :2] / 2)
    img = load_images(half, [0, 3])
    assert img.shape == (2, 48, 64, 3) and img.dtype == torch.float32
    full_img = load_images(full, [0])
    # the area average, rounded back to 8 bits (an 8-bit photo is kept as 8 bits: data.dataset.resized_8bit)
    torch.testing.assert_close(img[0], full_img[0].reshape(48, 2, 64, 2, 3).mean((1, 3)), atol=0.5 / 255 + 1e-6, rtol=0)
    assert load_depths(half, [0]).shape == (1, 48, 64, 1)
    m = load_masks(half, [0])
    assert m.dtype == torch.bool and m.shape == (1, 48, 64, 1) and m.all()


def test_downscale_to_a_rounded_size_keeps_each_pixel_on_its_ray(tiny_scene_path):  # noqa: F811
    """128 x 96 / 3 is 42.67 x 32, rounded to 43 x 32: the photo is stretched by 43/42.67 across, so the intrinsics
    must scale x by 43/128 (not 1/3), and the resize must average each target pixel's exact share of the photo."""
    from uncertsplat.io.images import resize_image
    from uncertsplat.render.project import project_points

    full = load_scene(tiny_scene_path)
    small = load_scene(tiny_scene_path, SceneConfig(downscale=3))
    W, H, w, h = full.cameras.width, full.cameras.height, small.cameras.width, small.cameras.height
    assert (w, h) == (43, 32)
    # an image holding each full-size pixel centre's own coordinates, resized as photos are
    ys, xs = np.meshgrid(np.arange(H) + 0.5, np.arange(W) + 0.5, indexing="ij")
    ramp = resize_image(np.stack([xs, ys], -1).astype(np.float32), w, h)  # [h,w,2]
    for cam in (0, 7):
        uv_full, _ = project_points(full.points.double(), full.cameras.cam_from_world[cam].double(),
                                    full.cameras.K[cam].double())
        uv, _ = project_points(full.points.double(), small.cameras.cam_from_world[cam].double(),
                               small.cameras.K[cam].double())
        inside = ((uv > 1.0) & (uv < torch.tensor([w - 1.0, h - 1.0], dtype=uv.dtype))).all(-1)
        assert inside.sum() > 20
        x, y = (uv[inside] - 0.5).unbind(-1)  # the resized image bilinearly at the point (exact on a ramp)
        x0, y0 = x.floor().long(), y.floor().long()
        fx, fy = (x - x0)[:, None], (y - y0)[:, None]
        r = torch.from_numpy(ramp).double()
        seen = ((1 - fy) * ((1 - fx) * r[y0, x0] + fx * r[y0, x0 + 1])
                + fy * ((1 - fx) * r[y0 + 1, x0] + fx * r[y0 + 1, x0 + 1]))
        # the resized photo shows there what the full photo shows where the full camera sees the point (to the
        # ramp's steps within a source pixel): with intrinsics scaled by 1/3 the right edge drifted a full source
        # pixel; with torch's adaptive area bins the content moved up to half a source pixel in a saw-tooth
        torch.testing.assert_close(seen, uv_full[inside], atol=0.01, rtol=0)


def test_splits(tiny_scene_path):  # noqa: F811
    names = [f"view_{i:03d}.png" for i in range(24)]
    s = load_scene(tiny_scene_path, SceneConfig(test_every=5))
    assert s.split["test"] == (0, 5, 10, 15, 20)
    assert set(s.split["train"]) | set(s.split["test"]) == set(range(24))
    s = load_scene(tiny_scene_path, SceneConfig(test_names=[names[7], names[2]]))
    assert s.split["test"] == (2, 7) and 2 not in s.split["train"]
    s = load_scene(tiny_scene_path, SceneConfig(test_indices=[23]))
    assert s.split["test"] == (23,) and len(s.split["train"]) == 23
    _raises(tiny_scene_path, SceneConfig(test_indices=list(range(24))), match="no training view")
    _raises(tiny_scene_path, SceneConfig(test_names=["nope.png"]), match="nope.png")


def test_explicit_training_views(tiny_scene_path):  # noqa: F811
    names = [f"view_{i:03d}.png" for i in range(24)]
    # training views only: the default held-out views stay held out, except those now trained on; the rest unused
    s = load_scene(tiny_scene_path, SceneConfig(train_indices=[0, 1, 2, 3]))
    assert s.split["train"] == (0, 1, 2, 3) and s.split["test"] == (8, 16)
    # ... and the scene says so (train prints its notes): a held-out view that became a training view
    (note,) = [n for n in s.notes if "default held-out views" in n]
    assert "include 1 of the default held-out views (view_000.png)" in note and "2 held out now" in note
    s = load_scene(tiny_scene_path, SceneConfig(train_names=names[:6], test_indices=[12, 13]))
    assert s.split == {"train": (0, 1, 2, 3, 4, 5), "test": (12, 13)}
    assert not [n for n in s.notes if "default held-out views" in n]  # the held-out views were given
    assert not [n for n in load_scene(tiny_scene_path, SceneConfig(train_indices=[1, 2])).notes
                if "default held-out views" in n]  # none taken
    _raises(tiny_scene_path, SceneConfig(train_indices=[1, 2], test_indices=[2, 3]), match="both trained on and held")
    _raises(tiny_scene_path, SceneConfig(train_indices=[24]), match="training indices out of range")
    _raises(tiny_scene_path, SceneConfig(train_names=["x.png"]), match="training image")


def test_views_set_aside_for_calibration(tiny_scene_path):  # noqa: F811
    """``calibration_holdout`` = n moves the middle view of each of n equal runs of the training views to
    "calibration": disjoint from both other sets, nothing lost, the held-out views as they were; with points from
    the training views only, the set-aside views give no point; n = every training view is refused."""
    base = load_scene(tiny_scene_path, SceneConfig())
    s = load_scene(tiny_scene_path, SceneConfig(calibration_holdout=3))
    train, cal = list(base.split["train"]), s.split["calibration"]
    assert cal == (train[3], train[10], train[17]) and len(train) == 21
    assert s.split["test"] == base.split["test"]
    assert set(s.split["train"]) == set(train) - set(cal)
    assert not set(cal) & set(s.split["test"])
    one = load_scene(tiny_scene_path, SceneConfig(train_indices=[4, 5, 6], calibration_holdout=1))
    assert one.split["train"] == (4, 6) and one.split["calibration"] == (5,)
    assert "calibration" not in base.split
    _raises(tiny_scene_path, SceneConfig(train_indices=[4, 5], calibration_holdout=2), match="calibration_holdout")
    from uncertsplat.sfm.colmap_io import read_colmap_model

    model = read_colmap_model(tiny_scene_path / "sparse" / "0", tracks=True)
    some = load_scene(tiny_scene_path, SceneConfig(train_indices=list(range(7)), calibration_holdout=1,
                                                   points_from="train"))
    assert some.split["calibration"] == (3,)
    kept = {f"view_{i:03d}.png" for i in (0, 1, 2, 4, 5, 6)}
    assert some.points.shape[0] == sum(len(kept.intersection(t)) >= 2 for t in model.point_images)


def test_points_from_training_views(tiny_scene_path):  # noqa: F811
    from uncertsplat.sfm.colmap_io import read_colmap_model

    model = read_colmap_model(tiny_scene_path / "sparse" / "0", tracks=True)
    train = {f"view_{i:03d}.png" for i in range(6)}
    expected = sum(len(train.intersection(t)) >= 2 for t in model.point_images)
    full = load_scene(tiny_scene_path, SceneConfig(train_indices=list(range(6))))
    some = load_scene(tiny_scene_path, SceneConfig(train_indices=list(range(6)), points_from="train"))
    assert 0 < expected < len(model.point_images)
    assert some.points.shape[0] == expected and full.points.shape[0] == len(model.point_images)
    # every kept point is one of the full set (same normalisation: the same cameras define it)
    d = torch.cdist(some.points, full.points, compute_mode="donot_use_mm_for_euclid_dist").amin(1)
    assert float(d.max()) < 1e-5


def test_text_model_and_sparse_without_0(workspace):
    binary = load_scene(workspace)
    rec = pycolmap.Reconstruction(str(workspace / "sparse" / "0"))
    shutil.rmtree(workspace / "sparse")
    (workspace / "sparse").mkdir()
    rec.write_text(str(workspace / "sparse"))  # the model directly in sparse/, as text
    text = load_scene(workspace)
    torch.testing.assert_close(text.cameras.cam_from_world, binary.cameras.cam_from_world, atol=1e-5, rtol=0)
    torch.testing.assert_close(text.cameras.K, binary.cameras.K)
    assert text.points.shape == binary.points.shape


def test_undistorted_camera_with_zero_distortion_is_accepted(workspace):
    sparse = workspace / "sparse" / "0"
    rec = pycolmap.Reconstruction(str(sparse))
    cam = rec.cameras[1]
    fx, fy, cx, cy = cam.params
    cam.model = pycolmap.CameraModelId.OPENCV
    cam.params = [fx, fy, cx, cy, 0.0, 0.0, 0.0, 0.0]
    rec.write_binary(str(sparse))
    scene = load_scene(workspace)
    assert scene.cameras.K[0, 0, 0].item() == pytest.approx(fx)


@pytest.mark.parametrize("model", ["OPENCV_FISHEYE", "SIMPLE_RADIAL_FISHEYE"])
def test_a_fisheye_camera_is_refused_even_with_zero_coefficients(workspace, model):
    """A fisheye of zero coefficients is an equidistant projection, not a pinhole one: it trained as a pinhole."""
    sparse = workspace / "sparse" / "0"
    rec = pycolmap.Reconstruction(str(sparse))
    cam = rec.cameras[1]
    fx, fy, cx, cy = cam.params
    cam.model = getattr(pycolmap.CameraModelId, model)
    cam.params = [fx, fy, cx, cy, 0.0, 0.0, 0.0, 0.0] if model == "OPENCV_FISHEYE" else [fx, cx, cy, 0.0]
    rec.write_binary(str(sparse))
    text = _raises(workspace, match=f"uses the {model} model, a projection that splatting cannot render")
    assert "image_undistorter" in text


def test_nerf_synthetic(tiny_scene_path, tmp_path):  # noqa: F811
    """Write the tiny scene in the Blender layout (OpenGL axes, RGBA) and load it back."""
    ref = load_scene(tiny_scene_path, SceneConfig(normalize=False))
    root = tmp_path / "nerf"
    K = ref.cameras.K[0].double()
    angle_x = 2 * math.atan(0.5 * ref.cameras.width / K[0, 0].item())
    angle_y = 2 * math.atan(0.5 * ref.cameras.height / K[1, 1].item())  # (of the height: the test split has it)
    for split, idx in (("train", ref.split["train"]), ("test", ref.split["test"])):
        frames = []
        for i in idx:
            name = ref.cameras.image_names[i]
            rgb = read_image(ref.image_paths[i])
            rgba = np.concatenate([rgb, np.ones_like(rgb[..., :1])], -1)
            rgba[:4, :4, 3] = 0.0  # a transparent corner shows the background
            write_png(root / split / name, rgba)
            c2w = np.linalg.inv(ref.cameras.cam_from_world[i].double().numpy())
            c2w[:3, 1:3] *= -1  # OpenCV -> OpenGL
            frames.append({"file_path": f"./{split}/{name[:-4]}", "transform_matrix": c2w.tolist()})
        angles = {"camera_angle_x": angle_x, **({"camera_angle_y": angle_y} if split == "test" else {})}
        (root / f"transforms_{split}.json").write_text(json.dumps({**angles, "frames": frames}))
    scene = load_scene(root, SceneConfig(normalize=False, background=(1.0, 1.0, 1.0)))
    assert scene.source["kind"] == "nerf_synthetic"
    assert len(scene.cameras) == 24
    assert len(scene.split["test"]) == 3  # the dataset's own split
    order = {n: i for i, n in enumerate(scene.cameras.image_names)}
    for i in ref.split["test"]:
        j = order[f"test/{ref.cameras.image_names[i]}"]
        assert j in scene.split["test"]
        torch.testing.assert_close(scene.cameras.cam_from_world[j], ref.cameras.cam_from_world[i], atol=1e-5, rtol=0)
        torch.testing.assert_close(scene.cameras.K[j], ref.cameras.K[i], atol=1e-4, rtol=0)
    img = load_images(scene, [0])
    assert torch.allclose(img[0, :4, :4], torch.ones(4, 4, 3))  # composited on the white background
    pts = scene.points
    assert len(pts) > 1000 and pts.std(0).min() > 0.1
    assert torch.equal(pts, load_scene(root, SceneConfig(normalize=False)).points)  # seeded


# ------------------------------------------------------------------------------------------- bad inputs
def test_missing_and_empty_folder(tmp_path):
    _raises(tmp_path / "nothing", match="not found", name="nothing")
    (tmp_path / "empty").mkdir()
    _raises(tmp_path / "empty", match="empty", name="empty")


def test_missing_sparse(workspace):
    shutil.rmtree(workspace / "sparse")
    _raises(workspace, match="sparse/0", name=str(workspace))
    (workspace / "sparse" / "0").mkdir(parents=True)
    _raises(workspace, match="no COLMAP model", name="sparse")


def test_distorted_camera_is_refused(workspace):
    sparse = workspace / "sparse" / "0"
    rec = pycolmap.Reconstruction(str(sparse))
    cam = rec.cameras[1]
    fx, _, cx, cy = cam.params
    cam.model = pycolmap.CameraModelId.SIMPLE_RADIAL
    cam.params = [fx, cx, cy, 0.05]
    rec.write_binary(str(sparse))
    text = _raises(workspace, match="SIMPLE_RADIAL", name=str(sparse))
    assert "reconstruct" in text and "undistort" in text


def test_images_of_different_sizes_are_refused(workspace):
    p = workspace / "images" / "view_005.png"
    write_png(p, np.zeros((50, 60, 3), np.float32))
    _raises(workspace, match="60x50", name="view_005.png")


def test_missing_image_is_refused(workspace):
    (workspace / "images" / "view_010.png").unlink()
    text = _raises(workspace, match="image 'view_010.png' named in the COLMAP model is missing", name="view_010.png")
    assert "reconstruct again without it" in text


def test_images_whose_names_differ_in_extension_case_are_named(workspace):
    """Files renamed to .PNG (a copy from another system): the near match is named, not just 'missing'."""
    for p in sorted((workspace / "images").iterdir()):
        p.rename(p.with_suffix(".PNG"))
    text = _raises(workspace, match="24 of the 24 images the COLMAP model names are missing (e.g. 'view_000.png'); "
                                    "view_000.PNG is there")
    assert "Rename the files to the model's names" in text


def test_truncated_image_is_refused(workspace):
    p = workspace / "images" / "view_002.png"
    p.write_bytes(p.read_bytes()[:200])
    with pytest.raises(UserError) as info:
        scene = load_scene(workspace)  # the header may still be readable ...
        load_images(scene, [2])  # ... the pixels are not
    assert "view_002.png" in str(info.value)


def test_failed_reconstruction_is_refused(workspace):
    from uncertsplat.schemas import ReconstructReport
    from uncertsplat.sfm.report import write_report

    write_report(workspace, ReconstructReport(success=False, photos="/p", message="2 of 24 registered"))
    _raises(workspace, match="failed reconstruction", name="reconstruct_report.json")
    write_report(workspace, ReconstructReport(success=True, photos="/p"))
    assert len(load_scene(workspace).cameras) == 24
    # a report that is not ours is refused with the key, not read by guessing
    (workspace / "reconstruct_report.json").write_text(json.dumps({"schema_version": 1, "ok": True}))
    _raises(workspace, match="key 'ok' is not part of the schema", name="reconstruct_report.json")


def test_missing_images_folder(workspace):
    shutil.move(workspace / "images", workspace / "images_4")  # LLFF's downscaled copies only
    text = _raises(workspace, match="missing images/ folder beside sparse/ (there is images_4)", name="images")
    assert "--set scene.downscale=N" in text
    shutil.rmtree(workspace / "images_4")
    assert "there is" not in _raises(workspace, match="missing images/ folder", name="images")


# ------------------------------------------------------------------------------------ photos of several sizes
def _with_camera(model, name, camera, cam_from_world):
    """``model`` with image ``name`` on ``camera`` (added to the cameras) at pose ``cam_from_world`` [4,4]."""
    from dataclasses import replace

    cameras = {**model.cameras, camera.camera_id: camera}
    images = [replace(im, camera_id=camera.camera_id, cam_from_world=cam_from_world) if im.name == name else im
              for im in model.images]
    return replace(model, cameras=cameras, images=images)


def _load_with_model(monkeypatch, workspace, model, cfg=None):
    monkeypatch.setattr("uncertsplat.sfm.scene.read_colmap_model", lambda _path, **_: model)
    return load_scene(workspace, cfg or SceneConfig())


@pytest.mark.parametrize("stored", [1, -1], ids=["anticlockwise", "clockwise"])
def test_portrait_photo_is_turned_with_its_camera(workspace, monkeypatch, tmp_path, stored):
    """A photo taken in the other orientation (stored turned a quarter turn either way, with the camera of that
    photo) loads as the original view: turned back the way that puts the scene's up where the other photos have
    it, the same camera and the same pixels; its maps are written as the photo lies."""
    from dataclasses import replace

    from uncertsplat.data.dataset import photo_turns
    from uncertsplat.eval.engine import ViewMaps
    from uncertsplat.sfm.colmap_io import read_colmap_model
    from uncertsplat.stages.evaluate import write_view_maps

    before = load_scene(workspace)
    name, i = "view_005.png", before.cameras.image_names.index("view_005.png")
    model = read_colmap_model(workspace / "sparse" / "0")
    im = next(m for m in model.images if m.name == name)
    cam = model.cameras[im.camera_id]
    W, H = cam.width, cam.height
    fx, fy, cx, cy = cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2]
    clockwise = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # camera axes (x, y, z) -> (-y, x, z)
    pose = im.cam_from_world.copy()
    if stored == 1:  # pixel (u, v) of the landscape photo is (v, W - u) of the portrait one
        K = np.array([[fy, 0.0, cy], [0.0, fx, W - cx], [0.0, 0.0, 1.0]])
        pose[:3, :] = clockwise.T @ pose[:3, :]
    else:  # (u, v) -> (H - v, u)
        K = np.array([[fy, 0.0, H - cy], [0.0, fx, cx], [0.0, 0.0, 1.0]])
        pose[:3, :] = clockwise @ pose[:3, :]
    portrait = replace(cam, camera_id=2, width=H, height=W, K=K)
    path = workspace / "images" / name
    original = read_image(path)
    write_png(path, np.rot90(original, k=stored).copy())
    scene = _load_with_model(monkeypatch, workspace, _with_camera(model, name, portrait, pose))
    assert (scene.cameras.width, scene.cameras.height) == (W, H)
    torch.testing.assert_close(scene.cameras.K, before.cameras.K, atol=1e-4, rtol=0)
    torch.testing.assert_close(scene.cameras.cam_from_world, before.cameras.cam_from_world, atol=1e-5, rtol=0)
    gt = load_images(scene, [i])[0]
    torch.testing.assert_close(gt, torch.from_numpy(original), atol=0, rtol=0)
    turns = 1 if stored == 1 else 3
    assert scene.photo_fits[i].turns == turns and all(f.turns == 0 for j, f in enumerate(scene.photo_fits) if j != i)
    assert photo_turns(scene) == {name: turns}
    assert any(name in note and "turned" in note for note in scene.notes)
    assert scene.source["photo_fits"][name][0] == turns
    # the view's maps lie as its photo does: the GT preview is the photo itself, every map turned alike
    depth = torch.arange(H * W, dtype=torch.float32).reshape(H, W, 1)
    write_view_maps(tmp_path, ViewMaps(name, gt, gt, 0.5 * gt, depth, 2.0 * depth), "percentile", photo_turns(scene))
    np.testing.assert_array_equal(read_image(tmp_path / "view_005_gt.png"), read_image(path))
    channels = read_exr(tmp_path / "view_005.exr")
    np.testing.assert_array_equal(channels["depth_mean.Z"], np.rot90(depth[..., 0].numpy(), k=stored))
    np.testing.assert_array_equal(channels["rgb_std.G"], np.rot90(0.5 * gt[..., 1].numpy(), k=stored))
    # a GT depth map of the upright photo (--depth-gt), at its size and at half of it, is turned with it
    from uncertsplat.data.dataset import load_depth_folder
    from uncertsplat.io.images import resize_image

    depth = (1.0 + np.arange(H * W, dtype=np.float32).reshape(H, W) / (H * W))  # the landscape view's
    for scale, folder in ((1, workspace / "gt_full"), (2, workspace / "gt_half")):
        folder.mkdir()
        small = depth[::scale, ::scale]
        np.save(folder / "view_005.npy", np.rot90(small, k=stored).copy())
        for other in scene.cameras.image_names:
            if other != name:
                np.save(folder / (other.rsplit(".", 1)[0] + ".npy"), np.ones((H, W), np.float32))
        got = load_depth_folder(folder, scene, [i])[0, ..., 0].numpy()
        np.testing.assert_allclose(got, resize_image(small, W, H), rtol=0, atol=1e-6)


def test_the_common_size_and_how_a_photo_joins_it():
    from uncertsplat.sfm.scene import PHOTO_SHAPE_TOLERANCE, common_size, size_fit

    # the most common size; among equals the larger (in pixels), then the wider
    assert common_size({(640, 480): 3, (800, 600): 2}) == (640, 480)
    assert common_size({(100, 200): 2, (150, 100): 2}) == (100, 200)
    assert common_size({(200, 100): 1, (100, 200): 1}) == (200, 100)
    # within 5 % of each side: cropped; the same shape within 1 % of the aspect ratio (3:2 here, 0.015): resized
    assert size_fit(3024, 2016, 3000, 2000) == "crop"
    assert PHOTO_SHAPE_TOLERANCE == 0.01
    assert size_fit(6000, 4000, 3000, 2000) == "resize"
    assert size_fit(6000, 4040, 3000, 2000) == "resize"  # aspect 1.4851: 0.0149 off, within 1 % of 1.5 (0.015)
    assert size_fit(6000, 4045, 3000, 2000) is None  # aspect 1.4833: 0.0167 off
    assert size_fit(3000, 2101, 3000, 2000) is None  # 5.05 % taller, and not the shape


def test_photos_a_few_pixels_larger_are_cropped_to_the_common_size(workspace, monkeypatch):
    from dataclasses import replace

    from uncertsplat.sfm.colmap_io import read_colmap_model

    before = load_scene(workspace)
    name, i = "view_007.png", before.cameras.image_names.index("view_007.png")
    model = read_colmap_model(workspace / "sparse" / "0")
    im = next(m for m in model.images if m.name == name)
    cam = model.cameras[im.camera_id]
    K = cam.K.copy()
    K[0, 2] += 2.0  # 2 more columns on the left, 1 more row on top (and as many on the other sides)
    K[1, 2] += 1.0
    wider = replace(cam, camera_id=2, width=cam.width + 4, height=cam.height + 2, K=K)
    path = workspace / "images" / name
    original = read_image(path)
    write_png(path, np.pad(original, ((1, 1), (2, 2), (0, 0)), mode="edge"))
    scene = _load_with_model(monkeypatch, workspace, _with_camera(model, name, wider, im.cam_from_world))
    assert (scene.cameras.width, scene.cameras.height) == (cam.width, cam.height)
    torch.testing.assert_close(scene.cameras.K, before.cameras.K, atol=1e-4, rtol=0)
    torch.testing.assert_close(load_images(scene, [i])[0], torch.from_numpy(original), atol=0, rtol=0)
    assert any(note.startswith("1 photo(s) cropped") and note.endswith(": view_007.png") for note in scene.notes)


def test_a_photo_of_another_resolution_of_the_same_shape_is_resized_with_its_camera(workspace, monkeypatch):
    """Another camera's photo at twice the resolution (each pixel repeated 2 x 2, its intrinsics doubled) loads as
    the original view: the same camera, the same pixels (area averaging undoes the repetition)."""
    from dataclasses import replace

    from uncertsplat.sfm.colmap_io import read_colmap_model

    before = load_scene(workspace)
    name, i = "view_009.png", before.cameras.image_names.index("view_009.png")
    model = read_colmap_model(workspace / "sparse" / "0")
    im = next(m for m in model.images if m.name == name)
    cam = model.cameras[im.camera_id]
    big = replace(cam, camera_id=2, width=2 * cam.width, height=2 * cam.height, K=cam.K * [[2], [2], [1]])
    original = read_image(workspace / "images" / name)
    write_png(workspace / "images" / name, original.repeat(2, 0).repeat(2, 1))
    scene = _load_with_model(monkeypatch, workspace, _with_camera(model, name, big, im.cam_from_world))
    assert (scene.cameras.width, scene.cameras.height) == (cam.width, cam.height)
    torch.testing.assert_close(scene.cameras.K, before.cameras.K, atol=1e-4, rtol=0)
    torch.testing.assert_close(load_images(scene, [i])[0], torch.from_numpy(original), atol=1e-6, rtol=0)
    assert any(name in note and "resized" in note for note in scene.notes)


def test_photos_of_another_size_are_left_out_or_refused(workspace, monkeypatch):
    from dataclasses import replace

    from uncertsplat.sfm.colmap_io import read_colmap_model

    before = load_scene(workspace)
    name = "view_009.png"
    model = read_colmap_model(workspace / "sparse" / "0")
    im = next(m for m in model.images if m.name == name)
    cam = model.cameras[im.camera_id]
    wide = replace(cam, camera_id=2, width=2 * cam.width, K=cam.K * [[2], [1], [1]])  # another shape
    write_png(workspace / "images" / name, np.zeros((cam.height, 2 * cam.width, 3), np.float32))
    changed = _with_camera(model, name, wide, im.cam_from_world)
    scene = _load_with_model(monkeypatch, workspace, changed)
    assert name not in scene.cameras.image_names and len(scene.cameras) == len(before.cameras) - 1
    assert (scene.cameras.width, scene.cameras.height) == (cam.width, cam.height)
    assert any(name in note and "left out" in note for note in scene.notes)
    with pytest.raises(UserError) as info:
        _load_with_model(monkeypatch, workspace, changed, SceneConfig(photo_sizes="strict"))
    text = str(info.value)
    assert f"{2 * cam.width}x{cam.height}: 1 image ({name})" in text and "photo_sizes" in text


def _same_pose(workspace, name, as_name):
    """Move ``name``'s camera to ``as_name``'s pose in the workspace's COLMAP model (the same picture taken twice)."""
    sparse = workspace / "sparse" / "0"
    rec = pycolmap.Reconstruction(str(sparse))
    ims = {im.name: im for im in rec.images.values()}
    pose = ims[as_name].cam_from_world()
    rec.frames[ims[name].frame_id].set_cam_from_world(ims[name].camera_id, pose)
    rec.write_binary(str(sparse))


def test_a_held_out_views_twin_leaves_training(workspace):
    """A training view at a held-out view's pose (a copy under another name, an exposure bracket) would let the
    held-out score measure memory: it leaves training, and the scene says which and why."""
    _same_pose(workspace, "view_005.png", "view_008.png")
    s = load_scene(workspace, SceneConfig())
    assert s.split["test"] == (0, 8, 16) and s.split["train"] == tuple(i for i in range(24) if i not in (0, 5, 8, 16))
    (note,) = [n for n in s.notes if "took the same picture" in n]
    assert "view_005.png (= view_008.png)" in note and "left out of training" in note
    # ... nor is it offered as a view to add (select-views' unused views)
    from uncertsplat.select.candidates import unused_views
    from uncertsplat.sfm.scene import with_training_views

    assert unused_views(s) == []
    # a run trained before the rule (view_005 among its training views) goes on with, and is measured against, them
    names = s.cameras.image_names
    old = with_training_views(s, [names[i] for i in sorted([*s.split["train"], 5])])
    assert 5 in old.split["train"] and old.split["test"] == s.split["test"]
    (note,) = [n for n in old.notes if "took the same picture" in n]  # what that run's view_008 score measures
    assert "view_005.png (= view_008.png)" in note and "the run trained on them" in note
    assert "left out of training" not in note
    assert with_training_views(s, [names[i] for i in s.split["train"]]) is s
    assert with_training_views(s, ["not-there.png"]) is s
    # training views given by hand are trained on as given; the note still says what the held-out score measures
    s = load_scene(workspace, SceneConfig(train_indices=[1, 5, 9]))
    assert s.split["train"] == (1, 5, 9)
    (note,) = [n for n in s.notes if "took the same picture" in n]
    assert "trained on as given" in note
    # views merely near each other are no twins
    assert not [n for n in load_scene(workspace, SceneConfig(test_indices=[3])).notes if "same picture" in n]
    # a twin of a view set aside for calibration (the std factor is fitted there) leaves training too
    c = load_scene(workspace, SceneConfig(calibration_holdout=3)).split["calibration"][0]
    twin = next(i for i in (c - 1, c + 1) if i not in (0, 5, 8, 16))
    _same_pose(workspace, f"view_{twin:03d}.png", f"view_{c:03d}.png")
    aside = load_scene(workspace, SceneConfig(calibration_holdout=3))
    assert c in aside.split["calibration"] and twin not in aside.split["train"] and 5 not in aside.split["train"]
    (note,) = [n for n in aside.notes if "took the same picture" in n]
    assert f"view_{twin:03d}.png (= view_{c:03d}.png)" in note


def test_pose_twins_thresholds():
    from tests.reference.naive_render import look_at_cameras
    from uncertsplat.sfm.scene import TWIN_ANGLE_DEG, TWIN_DISTANCE, pose_twins
    from uncertsplat.types import Cameras

    base = look_at_cameras(4, 64, 48, 50.0, dtype=torch.float64)  # an arc of cameras 4 units from the origin

    def with_fifth(m, focal=50.0):
        K = torch.cat([base.K, base.K[:1]])
        K[4, 0, 0] = focal
        return Cameras(torch.cat([base.cam_from_world, m[None]]), K, 64, 48)

    radius = float((base.centers - base.centers.mean(0)).norm(dim=-1).max())
    assert pose_twins(with_fifth(base.cam_from_world[2]), [2], [0, 1, 3, 4]) == {2: [4]}
    assert pose_twins(with_fifth(base.cam_from_world[2]), [4], [0, 1, 2, 3]) == {4: [2]}
    assert pose_twins(with_fifth(base.cam_from_world[2], focal=60.0), [2], [4]) == {}  # zoomed: another picture
    moved = base.cam_from_world[2].clone()
    moved[0, 3] += 1.5 * TWIN_DISTANCE * radius  # a step to the side larger than the threshold
    assert pose_twins(with_fifth(moved), [2], [4]) == {}
    moved[0, 3] -= TWIN_DISTANCE * radius  # half the threshold
    assert pose_twins(with_fifth(moved), [2], [4]) == {2: [4]}
    turned = base.cam_from_world[2].clone()
    a = math.radians(1.5 * TWIN_ANGLE_DEG)  # turned about the camera's own centre past the angle
    Rz = torch.tensor([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]], dtype=torch.float64)
    c = base.centers[2]
    turned[:3, :3] = Rz @ turned[:3, :3]
    turned[:3, 3] = -turned[:3, :3] @ c
    assert pose_twins(with_fifth(turned), [2], [4]) == {}
    assert pose_twins(base, [0], [1, 2, 3]) == {} and pose_twins(base, [], [1]) == {}


def test_pose_twins_compare_the_optical_axes_in_any_world():
    """The angle of ``pose_twins`` is between the cameras' optical axes in the world (a row of the world-to-camera
    rotation; its column is the world's z axis seen from the camera). A camera at view 2's centre turned by
    3 x ``TWIN_ANGLE_DEG`` about the world's z axis keeps that column but points elsewhere: no twin. (The turn of
    test_pose_twins_thresholds moved row and column alike.) The answers stay when the whole rig is rotated."""
    from tests.reference.naive_render import look_at_cameras
    from uncertsplat.sfm.scene import TWIN_ANGLE_DEG, pose_twins
    from uncertsplat.types import Cameras

    base = look_at_cameras(4, 64, 48, 50.0, dtype=torch.float64)
    a = math.radians(3 * TWIN_ANGLE_DEG)
    Rz = torch.tensor([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]],
                      dtype=torch.float64)
    turned = base.cam_from_world[2].clone()
    turned[:3, :3] = turned[:3, :3] @ Rz  # turned about the world's z axis through its own centre
    turned[:3, 3] = -turned[:3, :3] @ base.centers[2]
    axis = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64) / math.sqrt(14.0)
    skew = torch.tensor([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]],
                        dtype=torch.float64)
    world = torch.eye(4, dtype=torch.float64)
    world[:3, :3] = torch.linalg.matrix_exp(math.radians(40.0) * skew)  # the whole rig rotated: x -> W x
    for fifth, twins in ((base.cam_from_world[2], {2: [4]}), (turned, {})):
        rig = Cameras(torch.cat([base.cam_from_world, fifth[None]]), torch.cat([base.K, base.K[:1]]), 64, 48)
        assert pose_twins(rig, [2], [0, 1, 3, 4]) == twins
        rotated = Cameras(rig.cam_from_world @ world.T, rig.K, 64, 48)
        torch.testing.assert_close(rotated.centers, rig.centers @ world[:3, :3].T)
        assert pose_twins(rotated, [2], [0, 1, 3, 4]) == twins


def test_map_coordinates_keep_their_precision(workspace, tmp_path):
    """A capture in map coordinates (UTM: millions of metres) loads to the same normalised scene as at the origin:
    the poses and points stay float64 until they are centred (float32 poses cost 2 dB at 5e6)."""
    far = tmp_path / "far"
    shutil.copytree(workspace, far)
    rec = pycolmap.Reconstruction(str(far / "sparse" / "0"))
    rec.transform(pycolmap.Sim3d(1.0, pycolmap.Rotation3d(), np.array([5e5, 4.5e6, 0.0])))
    rec.write_binary(str(far / "sparse" / "0"))
    near, moved = load_scene(workspace, SceneConfig()), load_scene(far, SceneConfig())
    scale = near.scene_scale
    torch.testing.assert_close(moved.cameras.cam_from_world, near.cameras.cam_from_world, rtol=0, atol=1e-5 * scale)
    torch.testing.assert_close(moved.points, near.points, rtol=0, atol=1e-5 * scale)
    assert moved.scene_scale == pytest.approx(scale, rel=1e-6)


@pytest.mark.parametrize("focal", [0.0, -128.0, float("nan")])
def test_a_focal_length_that_is_not_positive_is_refused(workspace, focal):
    sparse = workspace / "sparse" / "0"
    rec = pycolmap.Reconstruction(str(sparse))
    cam = rec.cameras[1]
    cam.params = np.array([focal, focal, *cam.params[2:]])
    rec.write_binary(str(sparse))
    text = _raises(workspace, match="camera intrinsics that are not usable", name="sparse")
    assert "focal lengths must be positive and finite" in text and "view_000.png" in text


def test_dense_video_frames_are_no_twins_but_brackets_and_paused_frames_are():
    """Frames evenly spaced along a path (5000 of a dolly shot, far closer than TWIN_DISTANCE of the rig) have no jump
    to the next frame: none is a twin. Three frames at each stop of the path (an exposure bracket, or the camera
    paused) are."""
    from uncertsplat.sfm.scene import pose_twins
    from uncertsplat.types import Cameras

    def along(x: torch.Tensor, yaw_deg: torch.Tensor | None = None) -> Cameras:
        """Cameras at (x, 0, 0) turned by yaw about y (0: looking down +z)."""
        a = torch.deg2rad(yaw_deg if yaw_deg is not None else torch.zeros_like(x))
        m = torch.eye(4, dtype=torch.float64).repeat(len(x), 1, 1)
        m[:, 0, 0], m[:, 0, 2], m[:, 2, 0], m[:, 2, 2] = a.cos(), -a.sin(), a.sin(), a.cos()
        m[:, :3, 3] = -(m[:, :3, :3] @ torch.stack([x, 0 * x, 0 * x], dim=-1)[..., None])[..., 0]
        K = torch.tensor([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]], dtype=torch.float64).repeat(len(x), 1, 1)
        return Cameras(m, K, 64, 48)

    n = 5000
    video = along(torch.linspace(0.0, 10.0, n, dtype=torch.float64))
    test = list(range(0, n, 8))
    assert pose_twins(video, test, [i for i in range(n) if i not in test]) == {}
    stops = torch.linspace(0.0, 10.0, 50, dtype=torch.float64).repeat_interleave(3)
    stops = stops + 1e-7 * torch.arange(150, dtype=torch.float64)  # SfM places them a hair apart
    bracket = along(stops)
    twins = pose_twins(bracket, [0, 3], [i for i in range(150) if i not in (0, 3)])
    assert twins == {0: [1, 2], 3: [4, 5]}
    # a panning shot: each frame turned 0.3 degrees and moved 0.1 % of the path from the last; no twins either
    pan = along(torch.linspace(0.0, 2.0, 2000, dtype=torch.float64), 0.3 * torch.arange(2000, dtype=torch.float64))
    test = list(range(0, 2000, 8))
    assert pose_twins(pan, test, [i for i in range(2000) if i not in test]) == {}
    # brackets from a turning tripod (3 exposures every 10 degrees, one spot) beside a line of other views: the
    # bracket frames are twins, the other directions at the same spot are not
    spot = torch.zeros(36 * 3, dtype=torch.float64) + 1e-6 * torch.arange(108, dtype=torch.float64)
    x = torch.cat([spot, torch.linspace(1.0, 10.0, 30, dtype=torch.float64)])
    yaw = torch.cat([10.0 * (torch.arange(108) // 3), torch.zeros(30)]).double()
    pano = along(x, yaw)
    held = [0, 9, 30]
    twins = pose_twins(pano, held, [i for i in range(138) if i not in held])
    assert twins == {0: [1, 2], 9: [10, 11], 30: [31, 32]}


def test_added_views_are_twins_only_as_the_split_finds_them():
    """``train --add-views`` refuses an added view that took a held-out view's picture, judged against every training
    view as the split judges: the next frame of a dense video (no jump from its neighbours) is added; a copy (a hair's
    breadth away) is refused. Judged against the added view alone, the video frame read as a twin."""
    from types import SimpleNamespace

    from uncertsplat.train.session import _refuse_twins_of_held_out
    from uncertsplat.types import Cameras

    n = 3000  # a step of 0.0033, a third of TWIN_DISTANCE x the radius of 5
    x = torch.linspace(0.0, 10.0, n, dtype=torch.float64)
    x = torch.cat([x, x[8:9] + 1e-7])  # the last: a copy of frame 8 saved again
    m = torch.eye(4, dtype=torch.float64).repeat(len(x), 1, 1)
    m[:, 0, 3] = -x
    K = torch.tensor([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]], dtype=torch.float64).repeat(len(x), 1, 1)
    cams = Cameras(m, K, 64, 48, tuple(f"f{i:04d}.png" for i in range(len(x))))
    test = tuple(range(0, n, 8))
    unused = {9, n}  # the frame after held-out frame 8, and the copy of frame 8
    train = tuple(i for i in range(n) if i not in test and i not in unused)
    data = SimpleNamespace(cameras=cams, split={"train": (*train, 9), "test": test})
    _refuse_twins_of_held_out(data, ["f0009.png"], Path("run"))  # the next frame: added
    data = SimpleNamespace(cameras=cams, split={"train": (*train, n), "test": test})
    with pytest.raises(UserError, match=f"f{n:04d}.png took the same picture as the held-out view f0008.png"):
        _refuse_twins_of_held_out(data, [f"f{n:04d}.png"], Path("run"))


def test_select_views_judges_twins_as_the_split_does():
    """select-views' candidates: the frame after a held-out one in a dense capture is a candidate (judged against
    the free views alone, it read as a twin and was left out with a note)."""
    from types import SimpleNamespace

    from uncertsplat.select.candidates import unused_views
    from uncertsplat.types import Cameras

    n = 3000
    x = torch.linspace(0.0, 10.0, n, dtype=torch.float64)
    m = torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)
    m[:, 0, 3] = -x
    K = torch.tensor([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]], dtype=torch.float64).repeat(n, 1, 1)
    test = tuple(range(0, n, 8))
    free = {9, 100, 1001}
    scene = SimpleNamespace(cameras=Cameras(m, K, 64, 48), split={
        "test": test, "train": tuple(i for i in range(n) if i not in test and i not in free)})
    assert unused_views(scene) == [9, 100, 1001]


def test_a_workspace_of_several_models_names_the_unused_ones(workspace):
    """COLMAP's mapper splits a capture it cannot join: sparse/0 is used and the others are named."""
    shutil.copytree(workspace / "sparse" / "0", workspace / "sparse" / "1")
    (note,) = [n for n in load_scene(workspace).notes if "COLMAP models" in n]
    assert "holds 2 COLMAP models; sparse/0 is used (24 images); the others (sparse/1) are not" in note
    rec = pycolmap.Reconstruction(str(workspace / "sparse" / "0"))
    rec.write_text(str(workspace / "sparse" / "0"))  # the same model as .txt beside the .bin
    assert any("both as .bin and as .txt files: the .bin ones are read" in n for n in load_scene(workspace).notes)


class TestCameraChanges:
    """``camera_records`` / ``camera_changes``: a run's recorded cameras against the scene as it loads later."""

    @staticmethod
    def cameras(n: int = 4, turn_deg: float = 0.0, shift: float = 0.0, focal: float = 100.0) -> Cameras:
        a = math.radians(turn_deg)
        R = torch.tensor([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])
        cfw = torch.eye(4).repeat(n, 1, 1)
        cfw[:, :3, :3] = R
        cfw[:, :3, 3] = torch.tensor([[0.1 * i + shift, 0.0, 2.0] for i in range(n)])
        K = torch.tensor([[focal, 0.0, 32.0], [0.0, focal, 24.0], [0.0, 0.0, 1.0]]).repeat(n, 1, 1)
        return Cameras(cfw, K, 64, 48, tuple(f"v{i}.png" for i in range(n)))

    def test_the_same_cameras_and_float_rounding_are_no_change(self):
        rec = camera_records(self.cameras(), ["v0.png", "v2.png", "gone.png"])
        assert sorted(rec) == ["v0.png", "v2.png"] and len(rec["v0.png"]) == 13
        assert camera_changes(rec, self.cameras(), extent=1.0) is None
        assert camera_changes(rec, self.cameras(turn_deg=1e-5, shift=1e-7, focal=100.0001), extent=1.0) is None
        assert camera_changes({}, self.cameras(), extent=1.0) is None

    @pytest.mark.parametrize(("kw", "words"), [({"turn_deg": 0.01}, r"turned 0\.01 degrees"),
                                                ({"shift": 0.001}, r"moved 0\.1 % of the scene's extent"),
                                                ({"focal": 101.0}, r"intrinsics .*\[100\.0, 100\.0, 32\.0, 24\.0\] "
                                                                   r"-> \[101\.0, 101\.0")])
    def test_a_change_above_the_tolerance_is_named(self, kw, words):
        rec = camera_records(self.cameras(), ["v0.png", "v1.png", "v2.png", "v3.png"])
        said = camera_changes(rec, self.cameras(**kw), extent=1.0)
        assert said is not None and said.startswith("4 of its 4 views' cameras differ"), said
        assert re.search(words, said), said

    def test_a_record_is_the_centre_the_right_and_optical_axes_and_the_intrinsics(self):
        """What ``scene.json`` keeps of a view (runs written earlier are compared against it): [centre, right axis,
        optical axis, fx, fy, cx, cy]."""
        a = math.radians(30.0)
        rec = camera_records(self.cameras(turn_deg=30.0), ["v1.png"])["v1.png"]
        t = torch.tensor([0.1, 0.0, 2.0], dtype=torch.float64)
        R = torch.tensor([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]],
                         dtype=torch.float64)
        want = [*(-R.T @ t).tolist(), math.cos(a), -math.sin(a), 0.0, 0.0, 0.0, 1.0, 100.0, 100.0, 32.0, 24.0]
        assert rec == pytest.approx(want, abs=1e-6)

    def test_the_move_is_measured_against_the_extent_and_the_view_that_changed_most_is_named(self):
        rec = camera_records(self.cameras(), ["v0.png", "v1.png", "v2.png", "v3.png"])
        now = self.cameras()
        now.cam_from_world[1, 0, 3] += 0.004
        now.cam_from_world[2, 0, 3] += 0.02
        said = camera_changes(rec, now, extent=4.0)  # 0.1 % and 0.5 % of an extent of 4
        assert said is not None and said.startswith("2 of its 4 views' cameras differ"), said
        assert "(v2.png's camera moved 0.5 % of the scene's extent)" in said, said
        assert camera_changes(rec, now, extent=1000.0) is None  # 2e-5 of the extent: within the tolerance

    def test_only_views_the_scene_still_holds_are_compared(self):
        rec = camera_records(self.cameras(), ["v0.png", "v1.png"])
        assert camera_changes(rec, self.cameras(n=1), extent=1.0) is None  # (the caller checks missing names)
        assert camera_changes(rec, self.cameras(n=1, turn_deg=1.0), extent=1.0).startswith("1 of its 1 views'")


@pytest.mark.parametrize("tag", [3, 6])
def test_a_workspace_photos_exif_tag_is_ignored_as_colmap_ignores_it(workspace, tag):
    """COLMAP's cameras describe a photo's pixels as stored (its undistorter keeps a phone photo's tag): a workspace
    photo tagged 3 (upside down) was read turned against its camera without a word, one tagged 6 refused as the wrong
    size. Tagged, it loads and reads as the same pixels."""
    import OpenImageIO as oiio

    cfg = SceneConfig()
    before = load_scene(workspace, cfg)
    pixels = load_images(before, [0, 1])
    for i in (0, 1):
        path = before.image_paths[i]
        buf = oiio.ImageBuf(str(path))
        buf.specmod().attribute("Orientation", tag)
        assert buf.write(str(path))
        inp = oiio.ImageInput.open(str(path))
        assert inp.spec().get_int_attribute("Orientation", 1) == tag
        inp.close()
    after = load_scene(workspace, cfg)
    torch.testing.assert_close(after.cameras.cam_from_world, before.cameras.cam_from_world, rtol=0, atol=0)
    assert torch.equal(load_images(after, [0, 1]), pixels)


def test_a_distorted_camera_no_image_uses_is_ignored(workspace):
    """An edited model's leftover camera that no image uses blocked the whole workspace as distorted."""
    sparse = workspace / "sparse" / "0"
    rec = pycolmap.Reconstruction(str(sparse))
    cam = rec.cameras[1]
    rec.add_camera(pycolmap.Camera(model="OPENCV", width=cam.width, height=cam.height,
                                   params=[100.0, 100.0, 64.0, 48.0, 0.1, 0.0, 0.0, 0.0], camera_id=7))
    rec.write_binary(str(sparse))
    assert 7 in pycolmap.Reconstruction(str(sparse)).cameras
    assert len(load_scene(workspace).cameras) == 24


def test_depth_gt_maps_are_found_by_the_images_path_and_never_shared(tmp_path):
    """`--depth-gt` looked maps up by the bare stem: camA/frame.jpg and camB/frame.jpg both read frame.npy, and
    camB was scored against camA's depth without a word. A map is found as the images are laid out (camA/frame.npy),
    by its maps' stem (camA__frame.npy) or, for a name no other image shares, by its stem (x.npy); a shared stem
    alone is refused, naming the other image."""
    from types import SimpleNamespace

    from uncertsplat.data.dataset import depth_map_names, load_depth_folder

    names = ("camA/frame.jpg", "camB/frame.jpg", "camA/x.jpg", "IMG_1.jpg", "IMG_1.png")
    assert depth_map_names("camA/frame.jpg", names) == ["camA/frame", "camA__frame"]
    assert depth_map_names("camA/x.jpg", names) == ["camA/x", "camA__x", "x"]
    assert depth_map_names("IMG_1.jpg", names) == ["IMG_1_jpg"]  # (IMG_1 is both twins')
    cams = Cameras(torch.eye(4).repeat(5, 1, 1), torch.eye(3).repeat(5, 1, 1), 4, 3, names)
    scene = SimpleNamespace(cameras=cams, photo_fits=None)
    folder = tmp_path / "gt"
    (folder / "camA").mkdir(parents=True)
    np.save(folder / "camA" / "frame.npy", np.full((3, 4), 1.0, np.float32))
    np.save(folder / "camB__frame.npy", np.full((3, 4), 2.0, np.float32))
    np.save(folder / "x.npy", np.full((3, 4), 3.0, np.float32))
    np.save(folder / "frame.npy", np.full((3, 4), 9.0, np.float32))  # what both read before
    np.save(folder / "IMG_1_jpg.npy", np.full((3, 4), 4.0, np.float32))
    got = load_depth_folder(folder, scene, [0, 1, 2, 3])
    assert got[:, 0, 0, 0].tolist() == [1.0, 2.0, 3.0, 4.0]
    (folder / "camB__frame.npy").unlink()
    with pytest.raises(UserError, match="no GT depth map for image 'camB/frame.jpg'") as err:
        load_depth_folder(folder, scene, [1])
    assert "camB/frame.npy or camB__frame.npy" in str(err.value) and "camA/frame.jpg has the same name" in str(err.value)
    with pytest.raises(UserError, match="Expected IMG_1_png.npy"):
        load_depth_folder(folder, scene, [4])


@pytest.mark.parametrize("size", [(16, 12), (4, 3), (8, 6)])
def test_a_depth_map_s_holes_are_not_blended_into_its_depths_when_resized(tmp_path, size):
    """A depth camera's map at half the photos' size, with holes (0) at its border and beyond its range: the
    bilinear upscale averaged the 0 into the neighbouring depths (pixels at 402 mm where the surface lies at 9 m;
    abs_rel 0.28 where the same map at full size scored 0.02). A resized pixel keeps a depth only where every source
    pixel under it has one; a map of the photo's size is read as it is."""
    from uncertsplat.data.dataset import load_depth_map

    d = np.full((6, 8), 5.0, np.float32)
    d[0, :] = 0.0  # the border
    d[:, 5] = np.inf  # beyond the range (written as inf here)
    d[3, 2] = np.nan
    np.save(tmp_path / "d.npy", d)
    out = load_depth_map(tmp_path / "d.npy", *size)
    assert out.shape == (size[1], size[0])
    assert set(np.unique(out).tolist()) == {0.0, 5.0}  # no depth between a hole's 0 and the surface's 5
    assert (out > 0).mean() > 0.2
    if size == (8, 6):
        np.testing.assert_array_equal(out > 0, np.isfinite(d) & (d > 0))


def test_depth_gt_as_16_bit_png_and_float_tiff_is_read_as_stored(tmp_path):
    """A depth camera's, nerfstudio's or TUM RGB-D's depth comes as one-channel 16-bit PNGs (millimetres, or another
    fixed step; 0 for none): `--depth-gt` refused them (only .npy and .exr) and told the user to convert. They are read
    now as their stored values (not scaled to [0, 1] as an image reader would; the unit is fitted by --depth-scale
    auto or given), as are float TIFFs; an 8-bit or colour picture of depth, or the scene's own photo, is refused;
    another type is named with how to convert it."""
    from types import SimpleNamespace

    import OpenImageIO as oiio
    import PIL.Image

    from uncertsplat.data.dataset import load_depth_folder

    names = ("images/view_000.png", "images/view_001.png", "images/view_002.png")
    cams = Cameras(torch.eye(4).repeat(3, 1, 1), torch.eye(3).repeat(3, 1, 1), 4, 3, names)
    folder = tmp_path / "depth"
    folder.mkdir()
    photo = tmp_path / "images" / "view_002.png"
    photo.parent.mkdir()
    scene = SimpleNamespace(cameras=cams, photo_fits=None, image_paths=[photo.parent / n.split("/")[1] for n in names])
    mm = np.array([[0, 1, 2500, 65535]] * 3, np.uint16)
    PIL.Image.fromarray(mm).save(folder / "view_000.png")
    got = load_depth_folder(folder, scene, [0])[0, ..., 0]
    assert got[0].tolist() == [0.0, 1.0, 2500.0, 65535.0]  # 0 stays "no depth" (load_depth_map)
    metres = np.full((3, 4, 1), 2.5, np.float32)
    out = oiio.ImageOutput.create(str(folder / "view_001.tif"))
    out.open(str(folder / "view_001.tif"), oiio.ImageSpec(4, 3, 1, "float"))
    out.write_image(metres)
    out.close()
    torch.testing.assert_close(load_depth_folder(folder, scene, [1]), torch.full((1, 3, 4, 1), 2.5))
    PIL.Image.fromarray(np.full((3, 4), 200, np.uint8)).save(folder / "view_000.png")
    with pytest.raises(UserError, match="8-bit values"):
        load_depth_folder(folder, scene, [0])
    PIL.Image.fromarray(np.zeros((3, 4, 3), np.uint8)).save(folder / "view_000.png")
    with pytest.raises(UserError, match="3 channels, not one: a colour image"):
        load_depth_folder(folder, scene, [0])
    PIL.Image.fromarray(np.zeros((3, 4, 3), np.uint8)).save(photo)
    with pytest.raises(UserError, match="view_002.png in the GT depth folder is the scene's own photo"):
        load_depth_folder(photo.parent, scene, [2])
    out = oiio.ImageOutput.create(str(photo.with_suffix(".tif")))  # a depth beside its photo: read, the photo not
    out.open(str(photo.with_suffix(".tif")), oiio.ImageSpec(4, 3, 1, "float"))
    out.write_image(metres)
    out.close()
    torch.testing.assert_close(load_depth_folder(photo.parent, scene, [2]), torch.full((1, 3, 4, 1), 2.5))
    (folder / "depth_000.png").write_bytes(b"")  # named otherwise: the error says what the folder holds
    (folder / "view_000.png").unlink()
    with pytest.raises(UserError, match="no GT depth map for image 'images/view_000.png'") as err:
        load_depth_folder(folder, scene, [0])
    assert "the folder holds depth_000.png, view_001.tif: a map is found by its photo's name" in str(err.value)
    (folder / "more").mkdir()  # five entries: four shown
    (folder / "zz.npy").write_bytes(b"")
    with pytest.raises(UserError) as err:
        load_depth_folder(folder, scene, [0])
    assert "the folder holds depth_000.png, more/, view_001.tif, zz.npy: a map" in str(err.value)
    (folder / "yy.npy").write_bytes(b"")
    with pytest.raises(UserError) as err:
        load_depth_folder(folder, scene, [0])
    assert "the folder holds depth_000.png, more/, view_001.tif, yy.npy, ...: a map" in str(err.value)
    nested = tmp_path / "nested"
    (nested / "x").mkdir(parents=True)  # the maps one level down
    with pytest.raises(UserError, match=r"the folder holds only folders \(x/\): give the one that holds the maps"):
        load_depth_folder(nested, scene, [0])
    (folder / "view_002.pfm").write_bytes(b"PF")
    with pytest.raises(UserError, match="no GT depth map for image 'images/view_002.png'") as err:
        load_depth_folder(folder, scene, [2])
    assert "view_002.pfm exists, but only .npy, .exr, .png, .tif, .tiff maps are read" in str(err.value)


def test_photos_the_model_does_not_name_are_noted(workspace):
    """Photos put into a workspace's images/ that its COLMAP model does not hold were ignored without a word."""
    assert not any("not in the COLMAP model" in n for n in load_scene(workspace).notes)
    shutil.copy(workspace / "images" / "view_002.png", workspace / "images" / "new shot.png")
    (workspace / "images" / "more").mkdir()
    shutil.copy(workspace / "images" / "view_003.png", workspace / "images" / "more" / "b.png")
    (workspace / "images" / "notes.txt").write_text("not a photo")
    scene = load_scene(workspace)
    (note,) = [n for n in scene.notes if "not in the COLMAP model" in n]
    assert note.startswith("2 photo(s) in") and "more/b.png" in note and "new shot.png" in note
    assert len(scene.cameras) == 24


def test_photos_with_alpha_in_a_workspace_are_noted(workspace):
    """A workspace photo with transparency is composited over the background colour: said, not silent."""
    assert not any("alpha channel" in n for n in load_scene(workspace).notes)
    path = workspace / "images" / "view_004.png"
    rgb = read_image(path)
    write_png(path, np.concatenate([rgb, np.ones_like(rgb[..., :1])], -1))
    (note,) = [n for n in load_scene(workspace, SceneConfig(background=(1.0, 1.0, 1.0))).notes if "alpha channel" in n]
    assert note.startswith("1 photo(s) have an alpha channel") and "[1.0, 1.0, 1.0]" in note and "view_004.png" in note


def test_the_depth_of_a_layered_exr_is_its_depth_channel(tmp_path):
    """A layered EXR (Blender's ViewLayer.Combined.R/G/B/A + ViewLayer.Depth.Z; evaluate's own maps) was read from its
    first channel, the red or the alpha, without a word."""
    from uncertsplat.data.dataset import read_depth_file
    from uncertsplat.io.images import write_exr

    depth = np.full((3, 4), 2.5, np.float32)
    other = np.full((3, 4), 0.25, np.float32)
    blender = {f"ViewLayer.Combined.{c}": other for c in "RGBA"} | {"ViewLayer.Depth.Z": depth}
    ours = {"alpha.A": other, "depth_mean.Z": depth, "depth_std.Z": other, "rgb_mean.R": other}
    for name, channels in (("blender", blender), ("ours", ours), ("one", {"R": depth}), ("z", {"Z": depth})):
        write_exr(tmp_path / f"{name}.exr", channels)
        np.testing.assert_array_equal(read_depth_file(tmp_path / f"{name}.exr"), depth, err_msg=name)
    write_exr(tmp_path / "rgb.exr", {"R": depth, "G": other, "B": other})  # a colour image: which one?
    with pytest.raises(UserError, match="cannot tell which channel of the EXR holds depth: .*R"):
        read_depth_file(tmp_path / "rgb.exr")
    write_exr(tmp_path / "grey.exr", {"R": depth, "G": depth, "B": depth})
    np.testing.assert_array_equal(read_depth_file(tmp_path / "grey.exr"), depth)


def test_a_depth_map_that_is_not_one_is_refused_with_what_to_write_instead(tmp_path):
    """A user's --depth-gt map of three channels said only its shape, and a truncated one told them to regenerate
    the scene (a helper's audit): both say what to write."""
    from uncertsplat.data.dataset import read_depth_file

    np.save(tmp_path / "rgb.npy", np.zeros((4, 5, 3), np.float32))
    with pytest.raises(UserError, match=r"must be 2-D \(one depth per pixel\), got shape \(4, 5, 3\)") as err:
        read_depth_file(tmp_path / "rgb.npy")
    assert "HxW" in err.value.hint
    (tmp_path / "cut.npy").write_bytes((tmp_path / "rgb.npy").read_bytes()[:100])
    with pytest.raises(UserError, match="cannot read the depth map") as err:
        read_depth_file(tmp_path / "cut.npy")
    assert "write it again" in err.value.hint and "uncertsplat synth" in err.value.hint


def test_a_depth_map_of_another_shape_is_refused_and_no_surface_is_invalid(tmp_path):
    """A transposed map was stretched to its photo (AbsRel 0.55 against 0.07, no word); Blender's 1e10 where a ray
    meets nothing counted as a depth (RMSE 4e8)."""
    from uncertsplat.data.dataset import load_depth_map

    d = np.full((96, 128), 3.0, np.float32)
    d[0, 0] = 1e10
    np.save(tmp_path / "ok.npy", d)
    got = load_depth_map(tmp_path / "ok.npy", 64, 48)
    assert got.shape == (48, 64) and got.max() == pytest.approx(3.0)  # (the corner averaged with invalid 0)
    np.save(tmp_path / "half.npy", d[::2, ::2])  # another resolution of the same shape: resized
    assert load_depth_map(tmp_path / "half.npy", 128, 96).shape == (96, 128)
    np.save(tmp_path / "t.npy", d.T.copy())
    with pytest.raises(UserError, match="the depth map is 96x128, another shape than its view's 128x96"):
        load_depth_map(tmp_path / "t.npy", 128, 96)
    # a view downscaled 5x rounds each side (26x19): its photo's own map is its shape, within that rounding
    assert load_depth_map(tmp_path / "ok.npy", 26, 19).shape == (19, 26)


def test_masks_of_zero_and_one_mark_their_ones_valid(workspace):
    """A boolean mask saved as 0 and 1 (not 255) marked every pixel invalid; 0/255 masks are read as before."""
    from types import SimpleNamespace

    cams = Cameras(torch.eye(4).repeat(2, 1, 1), torch.eye(3).repeat(2, 1, 1), 4, 3, ("a.png", "b.png"))
    m = np.zeros((3, 4, 1), np.float32)
    m[1:, 2:] = 1.0
    write_png(workspace / "a.png", m / 255.0)  # values 0 and 1
    write_png(workspace / "b.png", m)  # values 0 and 255
    scene = SimpleNamespace(cameras=cams, mask_paths=(workspace / "a.png", workspace / "b.png"), photo_fits=None,
                            masks_train=True)
    masks = load_masks(scene)
    assert masks.shape == (2, 3, 4, 1) and torch.equal(masks[0], masks[1]) and int(masks[0].sum()) == 4


def test_a_principal_point_outside_the_image_is_refused(workspace):
    """A COLMAP camera whose principal point lies outside its images (intrinsics of another image size) is refused,
    naming the view and the size the intrinsics seem to belong to, as for every loader (``_check_intrinsics``)."""
    sparse = workspace / "sparse" / "0"
    rec = pycolmap.Reconstruction(str(sparse))
    cam = rec.cameras[1]
    cam.params = np.array([*cam.params[:2], 200.0, 48.0])  # cx beyond the 128-pixel width
    rec.write_binary(str(sparse))
    text = _raises(workspace, match="principal point at (200, 48), outside its 128x96 image", name="sparse")
    assert "view 'view_000.png'" in text and "about 400x96" in text, text
    # a crop of a larger photo has its optical centre outside it: accepted when said so
    scene = load_scene(workspace, SceneConfig(principal_point_outside=True))
    assert float(scene.cameras.K[0, 0, 2]) == pytest.approx(200.0)


def test_a_workspace_masks_are_trained_with_a_synthetic_scene_s_are_scored_only(tiny_scene_path, workspace):  # noqa: F811
    """A COLMAP workspace's masks/ are the user's (transients, the rig): training leaves their black pixels out too;
    a synthetic scene's masks/ mark where its GT is defined and only the scoring reads them (test_masks.py has the
    rest)."""
    assert not any("masks" in n for n in load_scene(workspace).notes)
    shutil.copytree(tiny_scene_path / "masks", workspace / "masks")
    scene = load_scene(workspace)
    (note,) = [n for n in scene.notes if "masks" in n]
    assert note.startswith("masks: 24 of 24 photos have one in") and scene.masks_train, note
    synthetic = load_scene(tiny_scene_path)
    assert synthetic.mask_paths is not None and not synthetic.masks_train
    assert not any(n.startswith("masks:") for n in synthetic.notes)


def test_depth_gt_given_the_images_folder_says_so(tiny_scene_path):  # noqa: F811
    """--depth-gt pointed at the scene's own images: the error told the user to convert their photo into depth."""
    from uncertsplat.data.dataset import load_depth_folder

    scene = load_scene(tiny_scene_path)
    with pytest.raises(UserError, match="view_000.png in the GT depth folder is the scene's own photo"):
        load_depth_folder(tiny_scene_path / "images", scene, [0])


def test_depth_gt_given_the_scene_folder_names_its_depth_sub_folder(tiny_scene_path):  # noqa: F811
    """--depth-gt SCENE (a synthetic scene's folder, its maps in SCENE/depth) said "rename the maps after the photos",
    which no renaming mends: the sub-folder that holds the map is named as the folder to give."""
    from uncertsplat.data.dataset import load_depth_folder

    scene = load_scene(tiny_scene_path)
    with pytest.raises(UserError, match="no GT depth map for image 'view_000.png'") as err:
        load_depth_folder(tiny_scene_path, scene, [0])
    said = " ".join(err.value.render().split())
    assert f"its sub-folder depth/ holds view_000.npy: give that folder, --depth-gt {tiny_scene_path / 'depth'}" in said
    assert "rename" not in said and "images/" not in said.split("sub-folder", 1)[1]
    load_depth_folder(tiny_scene_path / "depth", scene, [0])  # (the folder named reads)


def test_an_empty_list_of_training_views_is_named_as_such(workspace):
    """`--set 'scene.train_names=[]'` was 'the test split takes all 24 images and leaves no training view': the list
    the user emptied is named."""
    with pytest.raises(UserError, match=r"scene.train_names is empty: no training view"):
        load_scene(workspace, SceneConfig(train_names=[]))
    with pytest.raises(UserError, match=r"scene.train_indices is empty"):
        load_scene(workspace, SceneConfig(train_indices=[]))


@pytest.mark.parametrize(("angle", "said"), [(40.0, "40 degrees is 0.6981"), (200.0, "between 0 and pi"),
                                             (0.0, "between 0 and pi")])
def test_a_field_of_view_in_degrees_is_refused(tmp_path, angle, said):
    """camera_angle_x = 40 (degrees, read as radians) trained at a 132-degree view, 53.13 at 164, and 60 was a
    negative focal length with no word of units (a helper's audit)."""
    root = tmp_path / "deg"
    frames = []
    for i in range(3):
        write_png(root / "train" / f"v{i}.png", np.full((6, 8, 3), 0.5, np.float32))
        c2w = np.eye(4)
        c2w[0, 3] = 0.1 * i
        frames.append({"file_path": f"./train/v{i}", "transform_matrix": c2w.tolist()})
    (root / "transforms_train.json").write_text(json.dumps({"camera_angle_x": angle, "frames": frames}))
    with pytest.raises(UserError, match=rf"camera_angle_x = {angle:g} is no field of view in radians") as err:
        load_scene(root, SceneConfig(normalize=False))
    assert said in err.value.hint


def _old_text_model(workspace, tmp_path, edit):
    """The workspace's model as an old-style text model (cameras, images and points3D only), ``edit`` applied to
    the lines of images.txt that hold poses."""
    folder = tmp_path / "txt"
    folder.mkdir(parents=True)
    pycolmap.Reconstruction(str(workspace / "sparse" / "0")).write_text(str(folder))
    for extra in ("frames.txt", "rigs.txt"):
        (folder / extra).unlink(missing_ok=True)
    lines = (folder / "images.txt").read_text(encoding="utf-8").splitlines()
    poses = [i for i, line in enumerate(lines) if line and not line.startswith("#")][::2]
    edit(lines, poses)
    (folder / "images.txt").write_text("\n".join(lines) + "\n")
    return folder


def test_a_colmap_pose_that_is_no_rotation_or_a_name_listed_twice_is_refused(workspace, tmp_path):
    """A doubled quaternion gave skewed camera axes and a zero one the identity, and two images of one name both
    trained on one photo, without a word (a helper's audit; the transforms loaders refuse such files)."""
    from uncertsplat.sfm.colmap_io import read_colmap_model

    def doubled(lines, poses):
        f = lines[poses[1]].split()
        f[1:5] = [str(2 * float(v)) for v in f[1:5]]
        lines[poses[1]] = " ".join(f)

    def same_name(lines, poses):
        name = lines[poses[0]].split()[-1]
        f = lines[poses[1]].split()
        lines[poses[1]] = " ".join(f[:-1] + [name])

    assert len(read_colmap_model(_old_text_model(workspace, tmp_path / "a", lambda lines, poses: None)).images) > 2
    with pytest.raises(UserError, match="rotation quaternion of norm 2, not 1"):
        read_colmap_model(_old_text_model(workspace, tmp_path / "b", doubled))

    def off(lines, poses):  # 0.2 % long: past rounding (1e-3), a pose typed with too few digits
        f = lines[poses[1]].split()
        f[1:5] = [repr(1.002 * float(v)) for v in f[1:5]]
        lines[poses[1]] = " ".join(f)

    with pytest.raises(UserError, match="rotation quaternion of norm 1.002, not 1"):
        read_colmap_model(_old_text_model(workspace, tmp_path / "b2", off))
    with pytest.raises(UserError, match="lists image 'view_.*' twice"):
        read_colmap_model(_old_text_model(workspace, tmp_path / "c", same_name))
