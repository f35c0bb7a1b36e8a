"""`uncertsplat synth` in the Blender layout, the hemisphere rig and the transparent backdrop: the same scene
loads to the same GT cameras, images and depth from either layout."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from uncertsplat.cli import app
from uncertsplat.config import SceneConfig, SynthConfig
from uncertsplat.data.dataset import load_depths, load_images, load_masks
from uncertsplat.data.synthetic import LOOK_AT, generate_scene, hemisphere_cameras, is_synthetic_scene
from uncertsplat.errors import UserError
from uncertsplat.io.images import read_image
from uncertsplat.schemas import SynthScene
from uncertsplat.sfm.scene import load_scene

SMALL = dict(preset="tiny", num_views=9, width=48, rig="hemisphere")  # test views 0 and 8


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    """The same transparent hemisphere scene in the COLMAP and the Blender layout."""
    root = tmp_path_factory.mktemp("layouts")
    colmap = generate_scene(root / "colmap", SynthConfig(**SMALL, backdrop="transparent"))
    blender = generate_scene(root / "blender", SynthConfig(**SMALL, backdrop="transparent", layout="blender"))
    return colmap, blender


def _by_stem(scene):
    return {name.rsplit("/", 1)[-1]: i for i, name in enumerate(scene.cameras.image_names)}


def test_blender_files(pair):
    _, blender = pair
    meta = SynthScene.read(blender / "scene.json")
    assert (meta.layout, meta.rig, meta.backdrop, meta.room) == ("blender", "hemisphere", "transparent", None)
    assert meta.look_at == list(LOOK_AT) and meta.num_points == 0
    assert meta.test_views == ["view_000.png", "view_008.png"]
    train = json.loads((blender / "transforms_train.json").read_text(encoding="utf-8"))
    test = json.loads((blender / "transforms_test.json").read_text(encoding="utf-8"))
    assert set(train) == {"camera_angle_x", "frames"} and len(train["frames"]) == 7 and len(test["frames"]) == 2
    assert test["frames"][1]["file_path"] == "./test/view_008"
    c2w = np.array(train["frames"][0]["transform_matrix"])
    # OpenGL camera axes: the camera looks down its -z axis, at the scene centre
    to_target = np.array(LOOK_AT) - c2w[:3, 3]
    assert np.allclose(-c2w[:3, 2], to_target / np.linalg.norm(to_target), atol=1e-12)
    assert np.linalg.norm(to_target) == pytest.approx(4.0)
    rgba = read_image(blender / "train" / "view_001.png", background=(1.0, 0.0, 1.0))
    assert rgba.shape == (36, 48, 3)
    assert not (blender / "sparse").exists() and not (blender / "images").exists()
    assert is_synthetic_scene(blender)


def test_both_layouts_load_the_gt_cameras_images_and_depth(pair):
    colmap, blender = pair
    cfg = SceneConfig(normalize=False, background=(1.0, 1.0, 1.0))
    a, b = load_scene(colmap, cfg), load_scene(blender, cfg)
    assert a.source["kind"] == b.source["kind"] == "synthetic" and b.source["layout"] == "blender"
    c2w, K = hemisphere_cameras(9, 48, 36, seed=0)
    ia, ib = _by_stem(a), _by_stem(b)
    assert sorted(ia) == sorted(ib) == [f"view_{i:03d}.png" for i in range(9)]
    for i in range(9):
        name = f"view_{i:03d}.png"
        for scene, j in ((a, ia[name]), (b, ib[name])):
            torch.testing.assert_close(scene.cameras.cam_from_world[j].double(), c2w[i], atol=1e-6, rtol=0)
            torch.testing.assert_close(scene.cameras.K[j].double(), K, atol=1e-6, rtol=0)
    order = [ib[f"view_{i:03d}.png"] for i in range(9)]
    torch.testing.assert_close(load_images(b, order), load_images(a), atol=0, rtol=0)
    torch.testing.assert_close(load_depths(b, order), load_depths(a), atol=0, rtol=0)
    assert torch.equal(load_masks(b, order), load_masks(a))
    # the held-out views are the same ones (the Blender layout's own split, the default test_every = 8)
    assert sorted(a.cameras.image_names[i] for i in a.split["test"]) == [
        b.cameras.image_names[i].removeprefix("test/") for i in b.split["test"]]


def test_transparent_backdrop(pair):
    colmap, _ = pair
    scene = load_scene(colmap, SceneConfig(normalize=False))
    rgba = read_image(colmap / "images" / "view_003.png", background=(0.0, 0.0, 0.0))
    white = read_image(colmap / "images" / "view_003.png", background=(1.0, 1.0, 1.0))
    alpha = 1.0 - (white - rgba)[..., 0]  # composite over black and white: the difference is 1 - alpha
    mask = load_masks(scene, [3])[0, ..., 0].numpy()
    depth = load_depths(scene, [3])[0, ..., 0].numpy()
    assert 0.05 < mask.mean() < 0.95  # objects and empty background
    assert np.all(depth[~mask] == 0) and np.all(depth[mask] > 0)
    assert np.all(alpha[~mask] < 1.0) and np.all(alpha[mask] > 0.0)  # the centre ray hits -> some coverage
    assert (alpha == 0).mean() > 0.05 and (alpha == 1).mean() > 0.05


def test_room_backdrop_blender_images_are_opaque(tmp_path):
    cfg = dict(preset="tiny", num_views=3, width=24)
    a = generate_scene(tmp_path / "c", SynthConfig(**cfg))
    b = generate_scene(tmp_path / "b", SynthConfig(**cfg, layout="blender"))
    for bg in ((0.0, 0.0, 0.0), (1.0, 1.0, 1.0)):  # alpha is 1 everywhere: the background never shows
        sa = load_scene(a, SceneConfig(background=bg))
        sb = load_scene(b, SceneConfig(background=bg))
        order = [_by_stem(sb)[n] for n in sa.cameras.image_names]
        torch.testing.assert_close(load_images(sb, order), load_images(sa), atol=0, rtol=0)


def test_overwrite_switches_layout_and_old_scenes_still_load(tmp_path):
    out = tmp_path / "s"
    cfg = dict(preset="tiny", num_views=3, width=16)
    generate_scene(out, SynthConfig(**cfg))
    generate_scene(out, SynthConfig(**cfg, layout="blender"), overwrite=True)
    assert not (out / "images").exists() and not (out / "sparse").exists()  # one scene per folder
    assert load_scene(out).source["layout"] == "blender"
    generate_scene(out, SynthConfig(**cfg), overwrite=True)
    assert not (out / "train").exists() and not (out / "transforms_train.json").exists()
    # a scene.json written before the schema (no schema_version, layout, rig, ...) is a COLMAP ring scene
    meta = json.loads((out / "scene.json").read_text(encoding="utf-8"))
    for key in ("schema_version", "layout", "rig", "backdrop", "look_at"):
        del meta[key]
    (out / "scene.json").write_text(json.dumps(meta))
    scene = load_scene(out)
    assert scene.source["kind"] == "synthetic" and scene.source["meta"]["layout"] == "colmap"
    # ours but damaged: a clear error naming the key, not a silent fallback to a plain COLMAP workspace
    del meta["num_views"]
    (out / "scene.json").write_text(json.dumps({**meta, "schema_version": 1, "layout": "colmap"}))
    with pytest.raises(UserError, match="num_views"):
        load_scene(out)
    assert not is_synthetic_scene(out)


def test_missing_gt_depth_in_the_blender_layout(tmp_path):
    out = generate_scene(tmp_path / "b", SynthConfig(preset="tiny", num_views=3, width=16, layout="blender"))
    shutil.rmtree(out / "depth")
    with pytest.raises(UserError, match="GT depth"):
        load_scene(out)


runner = CliRunner()


def test_cli_synth_layout_options(tmp_path):
    out = tmp_path / "obj"
    args = ["synth", str(out), "--preset", "tiny", "--layout", "blender", "--rig", "hemisphere", "--backdrop",
            "transparent", "--set", "num_views=3", "--set", "width=16"]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    assert (out / "transforms_train.json").is_file() and (out / "test" / "view_000.png").is_file()
    assert "nothing to do" in runner.invoke(app, args).output
    bad = runner.invoke(app, ["synth", str(tmp_path / "x"), "--layout", "llff"])
    assert bad.exit_code == 2 and "layout" in bad.output and "Traceback" not in bad.output
    text = runner.invoke(app, ["synth", "--help"]).output
    assert "--layout" in text and "--rig" in text and "--backdrop" in text


def _plain_copy(blender, out):
    """The synthetic Blender scene as a user's own RGBA capture: its transforms and images, no masks/ or scene.json."""
    out.mkdir()
    for name in ("train", "test", "transforms_train.json", "transforms_test.json"):
        src = blender / name
        (shutil.copytree if src.is_dir() else shutil.copy)(src, out / name)
    return out


def test_transparent_photos_are_scored_on_their_objects(pair, tmp_path):
    # a user's RGBA capture has no masks/: the photos' alpha stands for them, else the background it is composited
    # over (trivially right) made its metrics look far better than its objects are
    _, blender = pair
    synth = load_scene(blender, SceneConfig(normalize=False))
    plain = load_scene(_plain_copy(blender, tmp_path / "plain"), SceneConfig(normalize=False))
    assert any("evaluate scores them only where alpha >= 0.5" in n for n in plain.notes)
    order = [_by_stem(plain)[n.rsplit("/", 1)[-1]] for n in synth.cameras.image_names]
    own = load_masks(synth, list(range(len(order))))[..., 0]
    from_alpha = load_masks(plain, order)[..., 0]
    assert 0.05 < float(from_alpha.float().mean()) < 0.95
    # alpha >= 0.5 against the synthetic masks' centre ray: the same pixels but for a few on the silhouettes
    assert float((own != from_alpha).float().mean()) < 0.02


def test_opaque_alpha_gives_no_masks(tmp_path):
    cfg = dict(preset="tiny", num_views=3, width=24, layout="blender")
    scene_dir = generate_scene(tmp_path / "room", SynthConfig(**cfg))  # RGBA files, alpha 1 everywhere
    plain = load_scene(_plain_copy(scene_dir, tmp_path / "plain"), SceneConfig(normalize=False))
    assert load_masks(plain) is None


def test_unseen_score_leaves_a_known_background_out():
    from uncertsplat.select.scores import unseen_scores
    from uncertsplat.types import Cameras

    cams = Cameras(K=torch.eye(3).expand(2, 3, 3).clone(), cam_from_world=torch.eye(4).expand(2, 4, 4).clone(),
                   width=4, height=2)
    blended = {0: torch.full((2, 4), 0.25), 1: torch.full((2, 4), 0.25)}
    alpha = {0: torch.ones(2, 4), 1: torch.zeros(2, 4)}  # view 1: every ray meets nothing

    def fake_blend(sample, u, cam, render_fn):
        c = int(cam.cam_from_world[0, 0, 3])
        return blended[c], alpha[c]

    cams.cam_from_world[1, 0, 3] = 1.0
    import uncertsplat.uncertainty.residual as residual

    mp = pytest.MonkeyPatch()
    mp.setattr(residual, "blend_values", fake_blend)
    try:
        assert unseen_scores(None, None, None, cams).tolist() == [0.25, 1.25]
        assert unseen_scores(None, None, None, cams, empty_unknown=False).tolist() == [0.25, 0.25]
    finally:
        mp.undo()


@pytest.mark.parametrize(("views", "every"), [(24, 8), (40, 8), (100, 8), (60, 3)])
def test_hemisphere_held_out_views_on_every_side_and_apart(views, every):
    """The held-out views (every ``every``-th) lie around the object (one spiral through all views put every 8th 20
    degrees of azimuth after the one before: 40 views' held-out ones within 100 degrees), and each as far from a
    training view as the views' spacing (two spirals, one per set, put one 4 degrees from a training view)."""
    c2w, _ = hemisphere_cameras(views, 32, 24, seed=1, test_every=every)
    centres = -(c2w[:, :3, :3].transpose(1, 2) @ c2w[:, :3, 3:])[..., 0] - torch.tensor(LOOK_AT, dtype=torch.float64)
    d = centres / centres.norm(dim=1, keepdim=True)
    test = [i for i in range(views) if i % every == 0]
    train = [i for i in range(views) if i % every]
    az = torch.sort(torch.rad2deg(torch.atan2(d[test, 1], d[test, 0])) % 360).values
    gap = float(torch.diff(torch.cat([az, az[:1] + 360])).max())
    assert gap < 2 * 360 / len(test)  # (evenly spread: 360 / n; the one spiral: 280 for 40 views, 119 for 100)
    spacing = math.degrees(math.sqrt(2 * math.pi * 0.8 / views))  # the hemisphere band's area per view
    nearest = torch.rad2deg(torch.acos((d[test] @ d[train].T).clamp(-1, 1))).min()
    assert float(nearest) > 0.6 * spacing


def test_a_blender_folder_without_test_frames_has_no_split_of_its_own(pair, tmp_path):
    """Only transforms_train.json: the dataset names no held-out view, so the default split (every 8th view)
    is used rather than an empty test set."""
    from uncertsplat.sfm.transforms import read_blender

    _, blender = pair
    root = tmp_path / "blender"
    shutil.copytree(blender, root)
    test = json.loads((root / "transforms_test.json").read_text())
    train = json.loads((root / "transforms_train.json").read_text())
    every = {**train, "frames": train["frames"] + test["frames"]}
    (root / "transforms_train.json").write_text(json.dumps(every))
    (root / "transforms_test.json").unlink()
    assert read_blender(root, SceneConfig()).split is None
    scene = load_scene(root, SceneConfig(normalize=False))
    assert scene.split["test"] == (0, 8) and len(scene.split["train"]) == 7
