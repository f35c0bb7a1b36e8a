"""nerfstudio ``transforms.json`` folders (sfm/transforms.py): the tiny synthetic scene converted the way
``ns-process-data`` writes it loads to the GT cameras; what we cannot render is refused naming the file."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest
import torch

from tests.fixtures import tiny_scene_path  # noqa: F401
from uncertsplat.config import SceneConfig
from uncertsplat.data.dataset import load_images
from uncertsplat.errors import UserError
from uncertsplat.io.images import read_image, resize_image, write_png
from uncertsplat.sfm.scene import load_scene

# what ns-process-data applies to the COLMAP world: (x, y, z) -> (x, z, -y)
NS_APPLIED = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0], [0, -1.0, 0, 0]])


def _write_ply(path, xyz, rgb):
    from plyfile import PlyData, PlyElement

    v = np.empty(len(xyz), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"),
                                  ("blue", "u1")])
    v["x"], v["y"], v["z"] = xyz.T
    v["red"], v["green"], v["blue"] = np.round(rgb * 255).astype(np.uint8).T
    PlyData([PlyElement.describe(v, "vertex")], text=True).write(str(path))


def convert(src, root, applied=NS_APPLIED, per_frame=False, extra=None):
    """The synthetic scene ``src`` as a nerfstudio folder (OpenGL poses in the transformed world)."""
    ref = load_scene(src, SceneConfig(normalize=False))
    shutil.copytree(src / "images", root / "images")
    A = np.concatenate([applied, [[0, 0, 0, 1.0]]], 0)
    R_A = A[:3, :3] / np.cbrt(np.linalg.det(A[:3, :3]))  # poses stay rigid in a scaled world
    K = ref.cameras.K.double().numpy()
    intr = lambda i: {"fl_x": K[i, 0, 0], "fl_y": K[i, 1, 1], "cx": K[i, 0, 2], "cy": K[i, 1, 2],  # noqa: E731
                      "w": ref.cameras.width, "h": ref.cameras.height}
    frames = []
    for i, name in enumerate(ref.cameras.image_names):
        c2w = np.linalg.inv(ref.cameras.cam_from_world[i].double().numpy())
        c2w[:3, 1:3] *= -1  # OpenCV -> OpenGL camera axes
        c2w[:3, :3], c2w[:3, 3] = R_A @ c2w[:3, :3], A[:3, :3] @ c2w[:3, 3] + A[:3, 3]
        frame = {"file_path": f"images/{name}", "transform_matrix": c2w.tolist(), "colmap_im_id": i + 1}
        frames.append({**frame, **intr(i)} if per_frame else frame)
    meta = {"camera_model": "OPENCV", "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, "frames": frames,
            "applied_transform": applied.tolist(), "ply_file_path": "sparse_pc.ply"}
    if not per_frame:
        meta.update(intr(0))
    meta.update(extra or {})
    xyz = ref.points.double().numpy() @ A[:3, :3].T + A[:3, 3]
    _write_ply(root / "sparse_pc.ply", xyz, ref.points_rgb.numpy())
    (root / "transforms.json").write_text(json.dumps(meta))
    return ref, meta


def _raises(root, match, cfg=None):
    with pytest.raises(UserError) as info:
        load_scene(root, cfg or SceneConfig())
    text = str(info.value)
    assert match in text and "transforms.json" in text, text
    return text


def test_loads_the_gt_cameras_and_points(tiny_scene_path, tmp_path):  # noqa: F811
    ref, _ = convert(tiny_scene_path, tmp_path / "ns")
    scene = load_scene(tmp_path / "ns", SceneConfig(normalize=False))
    assert scene.source["kind"] == "nerfstudio" and scene.source["frame"].startswith("COLMAP")
    assert scene.cameras.image_names == tuple(f"images/{n}" for n in ref.cameras.image_names)
    torch.testing.assert_close(scene.cameras.cam_from_world, ref.cameras.cam_from_world, atol=1e-5, rtol=0)
    torch.testing.assert_close(scene.cameras.K, ref.cameras.K, atol=1e-4, rtol=0)
    # the point cloud (written in the transformed world, as ns-process-data does) is back in COLMAP's frame
    torch.testing.assert_close(scene.points, ref.points, atol=1e-5, rtol=0)
    torch.testing.assert_close(scene.points_rgb, ref.points_rgb, atol=1 / 255, rtol=0)
    assert scene.split == ref.split
    # normalised like the COLMAP workspace: sparse points -> camera centroid, the same similarity
    norm, ref_norm = load_scene(tmp_path / "ns"), load_scene(tiny_scene_path)
    assert norm.center_method == "camera_centroid"
    torch.testing.assert_close(norm.cameras.cam_from_world, ref_norm.cameras.cam_from_world, atol=1e-5, rtol=0)
    torch.testing.assert_close(load_images(norm, [3]), load_images(ref_norm, [3]))


def test_per_frame_intrinsics_scaled_transform_and_split(tiny_scene_path, tmp_path):  # noqa: F811
    c, s_ = np.cos(0.4), np.sin(0.4)
    similarity = np.array([[2 * c, -2 * s_, 0, 1.0], [2 * s_, 2 * c, 0, -3.0], [0, 0, 2.0, 0.5]])
    ref, meta = convert(tiny_scene_path, tmp_path / "ns", applied=similarity, per_frame=True)
    for i, fr in enumerate(meta["frames"]):  # every frame its own focal lengths (fl_y apart from fl_x)
        fr["fl_x"] *= 1 + 0.01 * i
        fr["fl_y"] *= 1 - 0.005 * i
    meta["test_filenames"] = ["images/view_003.png", "./images/view_010.png"]
    del meta["ply_file_path"]
    (tmp_path / "ns" / "transforms.json").write_text(json.dumps(meta))
    scene = load_scene(tmp_path / "ns", SceneConfig(normalize=False))
    torch.testing.assert_close(scene.cameras.cam_from_world, ref.cameras.cam_from_world, atol=1e-5, rtol=0)
    fx = ref.cameras.K[:, 0, 0] * (1 + 0.01 * torch.arange(24))
    torch.testing.assert_close(scene.cameras.K[:, 0, 0], fx)
    torch.testing.assert_close(scene.cameras.K[:, 1, 1], ref.cameras.K[:, 1, 1] * (1 - 0.005 * torch.arange(24)))
    assert scene.split["test"] == (3, 10) and len(scene.split["train"]) == 22
    # no point cloud: random initial points around where the (inward-facing) ring looks
    assert scene.center_method == "optical_axes" and len(scene.points) > 1000


def test_downscaled_image_folder(tiny_scene_path, tmp_path):  # noqa: F811
    convert(tiny_scene_path, tmp_path / "ns")
    for p in sorted((tmp_path / "ns" / "images").iterdir()):
        write_png(tmp_path / "ns" / "images_2" / p.name, resize_image(read_image(p), 64, 48))
    scene = load_scene(tmp_path / "ns", SceneConfig(downscale=2))
    assert scene.source["images"] == "images_2" and scene.image_paths[0].parent.name == "images_2"
    assert (scene.cameras.width, scene.cameras.height) == (64, 48)
    full = load_scene(tmp_path / "ns", SceneConfig(downscale=4))  # no images_4/: the full-size images
    assert full.source["images"] == "full size" and full.cameras.width == 32
    torch.testing.assert_close(load_images(scene, [0]), load_images(load_scene(tiny_scene_path,
                                                                                SceneConfig(downscale=2)), [0]),
                               atol=1 / 255, rtol=0)


def test_distortion_and_fisheye_are_refused(tiny_scene_path, tmp_path):  # noqa: F811
    _, meta = convert(tiny_scene_path, tmp_path / "ns")
    path = tmp_path / "ns" / "transforms.json"
    path.write_text(json.dumps({**meta, "k1": 0.05, "p2": -1e-4}))
    text = _raises(tmp_path / "ns", "k1=0.05, p2=-0.0001")
    assert "distortion" in text and "uncertsplat reconstruct" in text and "undistort" in text
    meta["frames"][4]["k2"] = 0.01  # per-frame distortion names the frame
    path.write_text(json.dumps(meta))
    _raises(tmp_path / "ns", "frame 'images/view_004.png' has lens distortion (k2=0.01)")
    del meta["frames"][4]["k2"]
    path.write_text(json.dumps({**meta, "camera_model": "OPENCV_FISHEYE"}))
    _raises(tmp_path / "ns", "OPENCV_FISHEYE, which is not a pinhole camera")


def test_bad_files_are_refused(tiny_scene_path, tmp_path):  # noqa: F811
    _, meta = convert(tiny_scene_path, tmp_path / "ns")
    path = tmp_path / "ns" / "transforms.json"
    mixed = json.loads(json.dumps(meta))
    for fr in mixed["frames"][:3]:
        fr.update(w=256, h=192)
    path.write_text(json.dumps(mixed))
    _raises(tmp_path / "ns", "different image sizes: 128x96 (e.g. 'images/view_003.png'), 256x192")
    path.write_text(json.dumps({**meta, "w": 100}))
    with pytest.raises(UserError, match="image is 128x96 but the transforms file says 100x96"):
        load_scene(tmp_path / "ns")
    path.write_text(json.dumps({**meta, "applied_transform": [[1, 0, 0, 0], [0, 2, 0, 0], [0, 0, 1, 0]]}))
    _raises(tmp_path / "ns", "applied_transform is not a rotation with a uniform scale")
    # a mirror (determinant < 0) is orthogonal with a uniform scale too, but no rotation: the scene would be flipped
    path.write_text(json.dumps({**meta, "applied_transform": [[1, 0, 0, 0], [0, 0, 1, 0], [0, 1, 0, 0]]}))
    _raises(tmp_path / "ns", "applied_transform is not a rotation with a uniform scale")
    path.write_text(json.dumps({**meta, "ply_file_path": "nope.ply"}))
    with pytest.raises(UserError, match="nope.ply"):
        load_scene(tmp_path / "ns")
    path.write_text(json.dumps({"frames": "x"}))
    _raises(tmp_path / "ns", "no list of 'frames'")
    path.write_text("{")
    _raises(tmp_path / "ns", "cannot read the transforms file")


def test_a_frame_without_its_pose_names_the_frame_and_the_key(tiny_scene_path, tmp_path):  # noqa: F811
    """A frame missing `transform_matrix` (or `file_path`) said only "KeyError('transform_matrix')": the file, the
    frame and the key are named, with what a frame holds; a pose that is not numbers says so without the repr."""
    _, meta = convert(tiny_scene_path, tmp_path / "ns")
    path = tmp_path / "ns" / "transforms.json"
    for key, value, said in (("transform_matrix", None, "frames[2] ('images/view_002.png') has no 'transform_matrix'"),
                             ("file_path", None, "frames[2] has no 'file_path'"),
                             ("transform_matrix", "abc", "frames[2] ('images/view_002.png'): 'file_path' must be a "
                                                         "text and 'transform_matrix' a matrix of numbers")):
        bad = json.loads(json.dumps(meta))
        if value is None:
            del bad["frames"][2][key]
        else:
            bad["frames"][2][key] = value
        path.write_text(json.dumps(bad))
        text = _raises(tmp_path / "ns", said)
        assert "Each frame holds {\"file_path\"" in text and "Error(" not in text, text
    # the advice: without the frame the scene loads
    bad["frames"].pop(2)
    path.write_text(json.dumps(bad))
    assert load_scene(tmp_path / "ns") is not None


def test_masks_read_depth_unread_and_an_unused_colmap_model_are_named(tiny_scene_path, tmp_path):  # noqa: F811
    """A frame's mask_path is read (its black pixels neither trained on nor scored: test_masks.py), its
    depth_file_path is not (said so), and a COLMAP model beside transforms.json is not used: all were silent."""
    from uncertsplat.data.dataset import load_masks

    root = tmp_path / "ns"
    convert(tiny_scene_path, root)
    meta = json.loads((root / "transforms.json").read_text(encoding="utf-8"))
    meta["frames"][0]["mask_path"] = "./masks/view_000.png"
    for fr in meta["frames"][:2]:  # nerfstudio's depth (16-bit PNG, mm): not read either, and evaluate takes --depth-gt
        fr["depth_file_path"] = fr["file_path"].replace("images/", "depth/")
    (root / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(UserError, match="names a mask_path that does not exist") as info:
        load_scene(root)
    assert str(root / "masks" / "view_000.png") in str(info.value)
    (root / "masks").mkdir()
    mask = np.ones((96, 128, 3), dtype=np.float32)
    mask[:10] = 0.0
    write_png(root / "masks" / "view_000.png", mask)
    shutil.copytree(tiny_scene_path / "sparse", root / "sparse")
    scene = load_scene(root)
    notes = scene.notes
    assert any(n.startswith("masks: 1 of 24 photos have one (transforms.json's mask_path)") for n in notes), notes
    assert scene.masks_train and scene.mask_paths[0] == root / "masks" / "view_000.png"
    assert all(m is None for m in scene.mask_paths[1:])
    got = load_masks(scene, [0, 1])
    assert not bool(got[0, :10].any()) and bool(got[0, 10:].all()) and bool(got[1].all())
    (depth,) = [n for n in notes if "depth_file_path" in n]
    assert depth.startswith("2 frame(s) of transforms.json name a depth_file_path: depth maps are not read")
    assert "--depth-gt" in depth
    assert any("read as a nerfstudio scene (transforms.json); the folder also holds a COLMAP model" in n for n in notes)
    shutil.rmtree(root / "sparse")
    assert not [n for n in load_scene(root).notes if "COLMAP model" in n]


def test_intrinsics_of_larger_images_are_refused(tiny_scene_path, tmp_path):  # noqa: F811
    """Full-resolution intrinsics with downscaled files (no w / h to compare): the principal point (256, 192) lies
    outside the 128x96 images. It trained off-centre, several dB worse, with warnings that blamed the poses."""
    _, meta = convert(tiny_scene_path, tmp_path / "ns")
    for k in ("fl_x", "fl_y", "cx", "cy"):
        meta[k] *= 4
    del meta["w"], meta["h"]
    (tmp_path / "ns" / "transforms.json").write_text(json.dumps(meta))
    text = _raises(tmp_path / "ns", "view 'images/view_000.png' (and 23 more")
    assert "principal point at (256, 192), outside its 128x96 image" in text, text
    assert "seem to belong to images of about 512x384 pixels" in text, text
    # twice the size: the principal point lands on the corner, which counted as inside (a helper's audit: 14.8 dB
    # against 19.5 with the right intrinsics, and no word)
    for k in ("fl_x", "fl_y", "cx", "cy"):
        meta[k] /= 2
    (tmp_path / "ns" / "transforms.json").write_text(json.dumps(meta))
    text = _raises(tmp_path / "ns", "principal point at (128, 96), at the edge of its 128x96 image")
    assert "256x192" in text, text


def _truncated(path):
    """``path`` (a PLY) rewritten as binary and cut short, as an interrupted copy leaves it."""
    from plyfile import PlyData

    ply = PlyData.read(str(path))
    ply.text = False  # binary, as nerfstudio writes it
    ply.write(str(path))
    data = path.read_bytes()
    path.write_bytes(data[: len(data) - 100])


def test_unreadable_values_and_point_clouds_are_named(tiny_scene_path, tmp_path):  # noqa: F811
    """A truncated point cloud, ``"w": "abc"`` and ``"k1": "abc"`` were tracebacks (plyfile's PlyElementParseError,
    ValueError from int() / float()): now UserErrors naming the file and the key."""
    root = tmp_path / "ns"
    _, meta = convert(tiny_scene_path, root)
    path = root / "transforms.json"
    path.write_text(json.dumps({**meta, "w": "abc"}))
    text = _raises(root, "'w' must be a number, got \"abc\"")
    assert "the file's value" in text
    path.write_text(json.dumps({**meta, "w": 127.5}))
    _raises(root, "'w' must be a whole number of pixels, got 127.5")
    path.write_text(json.dumps({**meta, "k1": "abc"}))
    _raises(root, "'k1' must be a number, got \"abc\"")
    bad = json.loads(json.dumps(meta))
    bad["frames"][2]["fl_y"] = [1, 2]
    path.write_text(json.dumps(bad))
    _raises(root, "'fl_y' must be a number, got [1, 2] (the frame's value, frame 'images/view_002.png')")
    path.write_text(json.dumps(meta))
    _truncated(root / "sparse_pc.ply")
    with pytest.raises(UserError) as info:
        load_scene(root)
    text = str(info.value)
    assert "sparse_pc.ply: cannot read the point cloud named by ply_file_path in transforms.json" in text, text
    assert "early end-of-file" in text, text
    # a Blender folder's points3d.ply (3DGS's initial points) is read the same way
    blender = tmp_path / "blender"
    shutil.copytree(root / "images", blender / "images")
    (blender / "transforms_train.json").write_text(json.dumps({k: v for k, v in meta.items()
                                                               if k not in ("applied_transform", "ply_file_path")}))
    shutil.copy(root / "sparse_pc.ply", blender / "points3d.ply")
    with pytest.raises(UserError, match="points3d.ply: cannot read the point cloud beside the transforms files"):
        load_scene(blender)


def test_file_paths_without_extension_find_upper_case_files(tiny_scene_path, tmp_path):  # noqa: F811
    """``images/view_000`` finds ``images/view_000.JPG`` (cameras' own spelling): only lower-case .png / .jpg /
    .jpeg / .exr were tried, and the error named a ``.png`` that never existed."""
    root = tmp_path / "ns"
    ref, meta = convert(tiny_scene_path, root)
    for i, fr in enumerate(meta["frames"]):
        stem = fr["file_path"][: -len(".png")]
        ext = (".PNG", ".Png", ".png")[i % 3]  # any case: as the files are on disk
        (root / fr["file_path"]).rename(root / (stem + ext))
        fr["file_path"] = stem
    path = root / "transforms.json"
    path.write_text(json.dumps(meta))
    scene = load_scene(root, SceneConfig(normalize=False))
    assert scene.cameras.image_names[:3] == ("images/view_000.PNG", "images/view_001.Png", "images/view_002.png")
    assert all(p.is_file() for p in scene.image_paths)
    torch.testing.assert_close(scene.cameras.cam_from_world, ref.cameras.cam_from_world, atol=1e-5, rtol=0)
    (root / "images" / "view_001.Png").rename(root / "images" / "view_001.webp")
    text = _raises(root, "no image for 'images/view_001' named in transforms.json")
    assert ".png, .jpg, .jpeg, .exr (in any case)" in text and "there is view_001.webp" in text, text
    assert "view_001.png" not in text, text


def test_test_filenames_win_over_val_filenames(tiny_scene_path, tmp_path):  # noqa: F811
    """A file listing both splits holds its held-out views in test_filenames (nerfstudio's val views are for
    validation during training): they are the test split; val_filenames alone stand in for it."""
    _, meta = convert(tiny_scene_path, tmp_path / "ns")
    path = tmp_path / "ns" / "transforms.json"
    path.write_text(json.dumps({**meta, "val_filenames": ["images/view_005.png", "images/view_007.png"],
                                "test_filenames": ["images/view_003.png"]}))
    scene = load_scene(tmp_path / "ns", SceneConfig(normalize=False))
    assert scene.split["test"] == (3,) and len(scene.split["train"]) == 23
    assert scene.source["split_from"] == "test_filenames"
    path.write_text(json.dumps({**meta, "val_filenames": ["images/view_005.png", "images/view_007.png"]}))
    scene = load_scene(tmp_path / "ns", SceneConfig(normalize=False))
    assert scene.split["test"] == (5, 7) and scene.source["split_from"] == "val_filenames"


def test_8_bit_point_colours_are_read_over_255(tiny_scene_path, tmp_path):  # noqa: F811
    """The PLY's 8-bit colours (what nerfstudio and COLMAP write) are v / 255 exactly: 255 is white, not
    255/256."""
    convert(tiny_scene_path, tmp_path / "ns")
    levels = np.array([[0, 128, 255], [255, 1, 254]])
    _write_ply(tmp_path / "ns" / "sparse_pc.ply", np.array([[0.1, 0.2, 0.3], [-0.5, 0.0, 1.0]]), levels / 255)
    scene = load_scene(tmp_path / "ns", SceneConfig(normalize=False))
    torch.testing.assert_close(scene.points_rgb.double(), torch.tensor(levels / 255), atol=1e-7, rtol=0)
    assert scene.points_rgb[0, 2].item() == 1.0 and scene.points_rgb[0, 0].item() == 0.0


def test_a_mirrored_pose_is_refused(tiny_scene_path, tmp_path):  # noqa: F811
    """A transform_matrix whose 3x3 part is orthonormal but a reflection (determinant -1) is no camera
    pose."""
    _, meta = convert(tiny_scene_path, tmp_path / "ns")
    c2w = np.asarray(meta["frames"][2]["transform_matrix"])
    c2w[:3, 0] *= -1  # the x axis mirrored: still R^T R = I
    meta["frames"][2]["transform_matrix"] = c2w.tolist()
    (tmp_path / "ns" / "transforms.json").write_text(json.dumps(meta))
    _raises(tmp_path / "ns", "frame 2 ('images/view_002.png'): transform_matrix is not a rigid "
                             "camera-to-world pose")


def test_a_field_of_view_of_pi_is_refused(tiny_scene_path, tmp_path):  # noqa: F811
    """camera_angle_x = pi is a 180-degree view: no pinhole camera (its focal length would be 0)."""
    _, meta = convert(tiny_scene_path, tmp_path / "ns")
    for key in ("fl_x", "fl_y"):
        del meta[key]
    path = tmp_path / "ns" / "transforms.json"
    path.write_text(json.dumps({**meta, "camera_angle_x": math.pi}))
    _raises(tmp_path / "ns", f"camera_angle_x = {math.pi:g} is no field of view in radians (0 to pi)")
    path.write_text(json.dumps({**meta, "camera_angle_x": math.pi - 0.5}))  # 151 degrees: a wide pinhole
    scene = load_scene(tmp_path / "ns", SceneConfig(normalize=False))
    fx = 0.5 * 128 / math.tan(0.5 * (math.pi - 0.5))
    assert scene.cameras.K[0, 0, 0].item() == pytest.approx(fx, rel=1e-6)


def test_a_downscaled_folder_is_read_at_the_resized_size(tiny_scene_path, tmp_path):  # noqa: F811
    """downscale = 3 of 128 x 96 images resizes them to round(128 / 3) x 32 = 43 x 32 (``Cameras.scaled``):
    an images_3/ folder of that size is read; one of 42 x 32 (the width truncated) is not, the full-size
    images are."""
    convert(tiny_scene_path, tmp_path / "ns")
    small = tmp_path / "ns" / "images_3"
    for width, used in ((43, "images_3"), (42, "full size")):
        for p in sorted((tmp_path / "ns" / "images").iterdir()):
            write_png(small / p.name, resize_image(read_image(p), width, 32))
        scene = load_scene(tmp_path / "ns", SceneConfig(downscale=3))
        assert scene.source["images"] == used
        assert (scene.cameras.width, scene.cameras.height) == (43, 32)


def test_test_filenames_naming_every_frame_leave_the_default_split(tiny_scene_path, tmp_path):  # noqa: F811
    """No frame left to train on: the dataset's split is not used; the default (every 8th view held out)
    is."""
    _, meta = convert(tiny_scene_path, tmp_path / "ns")
    names = [fr["file_path"] for fr in meta["frames"]]
    (tmp_path / "ns" / "transforms.json").write_text(json.dumps({**meta, "test_filenames": names}))
    scene = load_scene(tmp_path / "ns", SceneConfig(normalize=False))
    assert scene.split["test"] == (0, 8, 16) and len(scene.split["train"]) == 21
