"""End-to-end ``reconstruct`` runs: a synthetic scene with known cameras, bad inputs, and LLFF fern."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pycolmap
import pytest

from uncertsplat.config import ReconstructConfig, SynthConfig
from uncertsplat.errors import UserError
from uncertsplat.sfm import reconstruct as sfm
from uncertsplat.sfm.report import (
    FAILED_REPORT_NAME,
    OVERWRITE_OLD,
    REPORT_NAME,
    ReconstructReport,
    load_report,
)
from uncertsplat.stages import reconstruct as stage

FERN = Path(__file__).parents[2] / "../shared/datasets/fern"

# Camera centres after a similarity alignment, as a fraction of the scene radius (the largest distance
# of a GT camera centre from their mean). COLMAP reaches a few tenths of a percent on real photos.
SYNTH_TOLERANCE = 0.02
FERN_TOLERANCE = 0.01

CFG = ReconstructConfig(num_threads=2)

# The "tiny" preset at 320x240: at its own 128x96, SIFT finds too few features per view for
# COLMAP's initial pair (100 inliers); at 320 px all 24 views register, 3/4-size copies included.
SFM_SCENE = SynthConfig(preset="tiny", width=320)


@pytest.fixture(scope="module")
def synth_scene(tmp_path_factory) -> Path:
    """The synthetic scene used for SfM tests (images/ + GT sparse/0)."""
    from uncertsplat.data.synthetic import generate_scene

    out = tmp_path_factory.mktemp("synth") / "scene"
    generate_scene(out, SFM_SCENE)
    return out


def centre_error(rec_dir: Path, gt: dict[str, np.ndarray]) -> tuple[np.ndarray, float]:
    """Per-camera centre errors after a similarity alignment, and the GT scene radius."""
    est = sfm.camera_centers(rec_dir)
    names = sorted(set(est) & set(gt))
    src = np.stack([est[n] for n in names])
    dst = np.stack([gt[n] for n in names])
    s, r, t = sfm.similarity_align(src, dst)
    err = np.linalg.norm(s * src @ r.T + t - dst, axis=1)
    radius = float(np.linalg.norm(dst - dst.mean(0), axis=1).max())
    return err, radius


def write_rgb(path: Path, arr: np.ndarray, orientation: int | None = None) -> None:
    spec = oiio.ImageSpec(arr.shape[1], arr.shape[0], 3, "uint8")
    if orientation is not None:
        spec.attribute("Orientation", orientation)
    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), spec)
    out.write_image(np.ascontiguousarray(arr))
    out.close()


def read_rgb(path: Path) -> np.ndarray:
    return oiio.ImageBuf(str(path)).get_pixels(oiio.UINT8)[..., :3]


def noise_image(seed: int, width: int = 160, height: int = 120) -> np.ndarray:
    """Blob-like random texture: many SIFT features, none shared with another seed."""
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 255, (height // 4, width // 4, 3)).astype(np.uint8)
    return np.repeat(np.repeat(small, 4, 0), 4, 1)


# ------------------------------------------------------------------------------------------ synthetic
def test_synthetic_scene_registers_and_matches_gt(synth_scene, tmp_path):
    ws = tmp_path / "ws"
    report = stage.run(synth_scene / "images", ws, CFG)
    names = sorted(p.name for p in (synth_scene / "images").iterdir())
    assert report.success
    assert report.images_registered == names and report.images_unregistered == []
    assert report.registered_fraction == 1.0
    assert not [n for n in report.notes if "camera it shares" in n]  # every photo fits the one camera
    assert report.num_points3d > 100
    assert 0 < report.mean_reprojection_error < 1.5
    assert set(report.stage_seconds) >= {"extract", "match", "map", "undistort"}
    # mapped again with the next seed until two runs agreed; the kept run is the workspace's model
    runs = report.mapping_attempts
    assert report.mapping_agreed is True and 2 <= len(runs) <= CFG.mapping_attempts
    assert [a.seed for a in runs] == list(range(CFG.seed, CFG.seed + len(runs))) and not any(a.relaxed for a in runs)
    (kept,) = [a for a in runs if a.kept]
    assert kept.num_observations == report.num_observations == max(a.num_observations for a in runs)
    assert kept.num_images == len(names) and kept.num_points3d == report.num_points3d
    assert all(a.seconds > 0 for a in runs) and sum(a.seconds for a in runs) <= report.stage_seconds["map"] + 1e-3
    assert report.num_observations == pytest.approx(report.mean_observations_per_image * len(names))

    # workspace layout: undistorted PINHOLE model in sparse/0 and one image per registered view
    assert sorted(p.name for p in (ws / "images").iterdir()) == names
    rec = pycolmap.Reconstruction(ws / "sparse" / "0")
    assert {c.model_name for c in rec.cameras.values()} <= {"PINHOLE", "SIMPLE_PINHOLE"}
    assert not (ws / "sparse" / "cameras.bin").exists()
    for i in rec.reg_image_ids():
        img = rec.image(i)
        h, w = read_rgb(ws / "images" / img.name).shape[:2]
        assert (w, h) == (img.camera.width, img.camera.height)
    on_disk = json.loads((ws / REPORT_NAME).read_text(encoding="utf-8"))
    assert on_disk["success"] is True and on_disk["pycolmap_version"] == pycolmap.__version__

    gt = sfm.camera_centers(synth_scene / "sparse" / "0")
    err, radius = centre_error(ws / "sparse" / "0", gt)
    assert err.max() < SYNTH_TOLERANCE * radius, (err.max() / radius)
    # the report compares with the GT cameras itself (the photos are a synthetic scene's images/)
    acc = report.ground_truth
    assert acc is not None and acc["num_images"] == len(names)
    assert acc["centre_error_max_pct"] == pytest.approx(100 * err.max() / radius, rel=1e-6)
    assert 0 < acc["rotation_error_mean_deg"] <= acc["rotation_error_max_deg"] < 1.0
    assert 0 <= acc["focal_error_mean_pct"] < 2.0
    same = sfm.pose_accuracy(synth_scene / "sparse" / "0", synth_scene / "sparse" / "0")
    assert same["centre_error_max_pct"] < 1e-6 and same["rotation_error_max_deg"] < 1e-3 and same["focal_error_mean_pct"] == 0

    # the same photos, options and output: reused, not recomputed
    mtime = (ws / REPORT_NAME).stat().st_mtime_ns
    again = stage.run(synth_scene / "images", ws, CFG)
    assert again == report and (ws / REPORT_NAME).stat().st_mtime_ns == mtime
    # other options: refused without --overwrite
    with pytest.raises(UserError, match="other options"):
        stage.run(synth_scene / "images", ws, CFG.model_copy(update={"seed": 1}))


def test_a_cropped_photo_saved_at_full_size_gets_a_camera_of_its_own(synth_scene, tmp_path, capsys):
    """One photo cropped to its middle 1/1.3 and saved at the full size (a digital zoom) shared the capture's camera
    and bent every photo's focal length towards its own (fern: 156 -> 200 px; bonsai: 395 -> 471): it is found by
    the focal length it fits alone and mapped again with a camera of its own, the others' focal length back at the
    scene's."""
    from uncertsplat.stages.reconstruct import OWN_CAMERA

    photos = tmp_path / "photos"
    shutil.copytree(synth_scene / "images", photos)
    later = sorted(p.name for p in photos.iterdir())[-1]  # added with --extend below
    (photos / later).unlink()
    names = sorted(p.name for p in photos.iterdir())
    zoomed = names[0]  # the first of its group by name
    buf = oiio.ImageBuf(str(photos / zoomed))
    w, h = buf.spec().width, buf.spec().height
    cut = oiio.ImageBufAlgo.cut(buf, oiio.ROI(round(w * 0.115), round(w * 0.885), round(h * 0.115), round(h * 0.885)))
    write_rgb(photos / zoomed, oiio.ImageBufAlgo.resize(cut, roi=oiio.ROI(0, w, 0, h)).get_pixels(oiio.UINT8)[..., :3])
    report = stage.run(photos, tmp_path / "ws", CFG)
    assert report.success and report.images_registered == names
    (note,) = [n for n in report.notes if n.startswith(OWN_CAMERA)]
    assert f": {zoomed} +" in note and "mapped again with a camera of its own" in note
    assert OWN_CAMERA in " ".join(capsys.readouterr().err.split())
    truth = next(iter(pycolmap.Reconstruction(synth_scene / "sparse" / "0").cameras.values())).mean_focal_length()
    rec = pycolmap.Reconstruction(tmp_path / "ws" / "distorted" / "sparse" / "0")
    focal = {rec.image(i).name: rec.image(i).camera.mean_focal_length() for i in rec.reg_image_ids()}
    assert len({rec.image(i).camera_id for i in rec.reg_image_ids()}) == 2
    assert max(abs(f / truth - 1) for n, f in focal.items() if n != zoomed) < 0.02
    assert focal[zoomed] / truth == pytest.approx(1 / 0.77, rel=0.05)
    # a photo added later joins the camera its group's photos share, not the odd first one's (a review: it took the
    # crop's focal length)
    shutil.copy2(synth_scene / "images" / later, photos / later)
    stage.run(photos, tmp_path / "ws", CFG.model_copy(update={"extend": True}))
    rec = pycolmap.Reconstruction(tmp_path / "ws" / "distorted" / "sparse" / "0")
    camera = {rec.image(i).name: rec.image(i).camera_id for i in rec.reg_image_ids()}
    assert camera[later] == camera[names[1]] != camera[zoomed]


def test_mixed_sizes_and_exif_orientation(synth_scene, tmp_path, capsys):
    """Different image sizes get one camera each (none dropped); EXIF-rotated photos are used upright, and the console
    names them (the note was only in the report's JSON)."""
    photos = tmp_path / "photos"
    photos.mkdir()
    names = sorted(p.name for p in (synth_scene / "images").iterdir())
    resized, rotated = names[1::4], names[2::4]
    for name in names:
        arr = read_rgb(synth_scene / "images" / name)
        if name in resized:  # the same view at 3/4 size: another "device"
            buf = oiio.ImageBufAlgo.resize(oiio.ImageBuf(str(synth_scene / "images" / name)),
                                           roi=oiio.ROI(0, arr.shape[1] * 3 // 4, 0, arr.shape[0] * 3 // 4, 0, 1, 0, 3))
            buf.write(str(photos / name))
        elif name in rotated:  # stored sideways, tagged so that a viewer shows it upright
            write_rgb(photos / name, np.rot90(arr, k=1), orientation=6)
        else:
            shutil.copy(synth_scene / "images" / name, photos / name)
    report = stage.run(photos, tmp_path / "ws", CFG)
    assert report.success
    assert report.rotated == rotated
    printed = " ".join(capsys.readouterr().err.split())
    assert f"EXIF orientation applied to {len(rotated)} image(s): {rotated[0]}" in printed
    assert len(report.image_sizes) == 2 and len(report.cameras) == 2
    assert any("2 image sizes found" in n and "photo_sizes" in n for n in report.notes)
    # train loads every view at the common size: the 3/4-size ones (the same shape) resized, and names them
    from uncertsplat.sfm.scene import load_scene

    scene = load_scene(tmp_path / "ws")
    assert set(resized) <= set(scene.cameras.image_names)
    assert any("resized" in n and resized[0] in n for n in scene.notes)
    assert set(resized) <= set(report.images_registered)
    assert set(rotated) <= set(report.images_registered)
    assert report.registered_fraction >= 0.9
    gt = sfm.camera_centers(synth_scene / "sparse" / "0")
    err, radius = centre_error(tmp_path / "ws" / "sparse" / "0", gt)
    assert err.max() < 2 * SYNTH_TOLERANCE * radius, (err.max() / radius)


def test_photo_names_with_spaces_are_matched_and_kept(synth_scene, tmp_path):
    """COLMAP's imported pair lists split lines at spaces: such photos were never matched (0 verified pairs)."""
    photos = tmp_path / "photos"
    photos.mkdir()
    for p in sorted((synth_scene / "images").iterdir())[:12]:  # half the orbit keeps the test short
        shutil.copy(p, photos / f"my photo {p.stem}{p.suffix}")
    report = stage.run(photos, tmp_path / "ws", CFG)
    assert report.success and report.num_verified_pairs > 11
    assert sorted(report.images_registered) == sorted(p.name for p in photos.iterdir())
    assert sorted(p.name for p in (tmp_path / "ws" / "images").iterdir()) == sorted(report.images_registered)
    with pycolmap.Database.open(tmp_path / "ws" / "database.db") as db:  # the aliases were undone
        assert sorted(im.name for im in db.read_all_images()) == sorted(report.images_registered)


def test_too_few_registered_lists_the_images_and_writes_the_report(synth_scene, tmp_path, capsys):
    photos = tmp_path / "photos"
    photos.mkdir()
    for p in sorted((synth_scene / "images").iterdir())[:12]:  # half the orbit keeps the test short
        shutil.copy(p, photos / p.name)
    strays = ["stray_a.png", "stray_b.png"]
    for k, name in enumerate(strays):
        write_rgb(photos / name, noise_image(100 + k, 128, 96))
    write_rgb(photos / "black.png", np.zeros((96, 128, 3), np.uint8))
    ws = tmp_path / "ws"
    with pytest.raises(UserError) as err:
        stage.run(photos, ws, CFG.model_copy(update={"min_registered": 1.0}))
    msg = " ".join(str(err.value).split())
    assert "stray_a.png" in msg and "stray_b.png" in msg and "overlap" in msg
    # a black photo is named as such in the failure too, and leaving it out is the first thing to try
    assert "(black.png: no features found at all" in msg and "Try: leave out black.png" in msg
    report = load_report(ws)
    assert report is not None and not report.success
    assert set(strays) <= set(report.images_unregistered)
    assert report.retried_relaxed
    assert not (ws / "images").exists()  # nothing undistorted for a failed run
    # the failed workspace of the same photos is redone without --overwrite; the black photo is named as such where
    # the unregistered ones are (not only in the report's notes)
    capsys.readouterr()
    report = stage.run(photos, ws, CFG.model_copy(update={"min_registered": 0.5}))
    assert report.success and set([*strays, "black.png"]) <= set(report.images_unregistered)
    warning = next(line for line in capsys.readouterr().err.splitlines() if "not registered:" in line)
    assert "black.png: no features found at all" in warning and "stray_a.png" in warning
    # an --overwrite that fails puts the finished workspace back as it was (a new user's retry with stricter options
    # deleted it, and a run trained on it could no longer be evaluated); its own report is kept beside it
    before = _digest(ws)
    with pytest.raises(UserError, match=r"only \d+/15 images registered .*reconstruct_report\.failed\.json"):
        stage.run(photos, ws, CFG.model_copy(update={"min_registered": 1.0, "overwrite": True}))
    after = _digest(ws)
    assert after.pop(FAILED_REPORT_NAME) and after == before and load_report(ws).success
    failed = ReconstructReport.read(ws / FAILED_REPORT_NAME)
    assert not failed.success and "only" in failed.message
    assert not (ws / OVERWRITE_OLD).exists()
    assert "the workspace --overwrite was to replace is back" in capsys.readouterr().err


# ------------------------------------------------------------------------------------------ bad input
def test_no_overlap_fails_cleanly_with_a_report(tmp_path):
    photos = tmp_path / "photos"
    photos.mkdir()
    for k in range(4):
        write_rgb(photos / f"n{k}.png", noise_image(k))
    ws = tmp_path / "ws"
    with pytest.raises(UserError, match="overlap"):
        stage.run(photos, ws, CFG)
    report = load_report(ws)
    assert report is not None and not report.success
    assert report.images_registered == [] and len(report.images_unregistered) == 4
    assert report.models_found == 0
    assert not (ws / ".lock").exists()


def test_unreadable_file_is_named_before_any_work(tmp_path):
    photos = tmp_path / "photos"
    photos.mkdir()
    for k in range(3):
        write_rgb(photos / f"n{k}.png", noise_image(k))
    (photos / "truncated.JPG").write_bytes(b"\xff\xd8\xff\xe0 not really")
    with pytest.raises(UserError, match="truncated.JPG"):
        stage.run(photos, tmp_path / "ws", CFG)
    assert not (tmp_path / "ws").exists()


# ----------------------------------------------------------------------------------------------- fern
def llff_poses(folder: Path) -> dict[str, np.ndarray]:
    """Image name -> camera_from_world [4,4] (OpenCV axes) from LLFF's poses_bounds.npy."""
    pb = np.load(folder / "poses_bounds.npy")
    mats = pb[:, :15].reshape(-1, 3, 5)  # [N,3,5]: [R|t|hwf], R columns = camera (down, right, back)
    names = sorted(p.name for p in (folder / "images").iterdir())
    assert len(names) == len(mats)
    out = {}
    for name, m in zip(names, mats, strict=True):
        down, right, back = m[:, 0], m[:, 1], m[:, 2]
        world_from_cam = np.eye(4)
        world_from_cam[:3, :3] = np.stack([right, down, -back], axis=1)  # OpenCV: x right, y down, z forward
        world_from_cam[:3, 3] = m[:, 3]  # the camera centre, in the units of the original 4032x3024 model
        out[name] = np.linalg.inv(world_from_cam)
    return out


@pytest.mark.slow
@pytest.mark.dataset
def test_fern_registers_all_and_matches_llff_poses(tmp_path):
    if not (FERN / "poses_bounds.npy").is_file():
        pytest.skip(f"LLFF fern not found at {FERN.resolve()} (see shared/datasets/README.md)")
    ws = tmp_path / "fern"
    report = stage.run(FERN / "images", ws, CFG)
    assert report.success and len(report.images_registered) == 20 and report.registered_fraction == 1.0
    assert report.mean_reprojection_error < 1.0

    ref = llff_poses(FERN)
    gt_centres = {n: -m[:3, :3].T @ m[:3, 3] for n, m in ref.items()}
    err, radius = centre_error(ws / "sparse" / "0", gt_centres)
    assert err.max() < FERN_TOLERANCE * radius, (err.max() / radius)

    # orientations agree too once the alignment rotation is applied (a check of the axis conversion)
    rec = pycolmap.Reconstruction(ws / "sparse" / "0")
    est = {rec.image(i).name: rec.image(i).cam_from_world().matrix() for i in rec.reg_image_ids()}
    names = sorted(est)
    src = np.stack([-est[n][:, :3].T @ est[n][:, 3] for n in names])
    _, r_align, _ = sfm.similarity_align(src, np.stack([gt_centres[n] for n in names]))
    for n in names:
        r_est_world = est[n][:, :3] @ r_align.T  # cam_from_world expressed in the LLFF world
        r_gt = ref[n][:3, :3]
        cos = (np.trace(r_est_world @ r_gt.T) - 1) / 2
        assert np.degrees(np.arccos(np.clip(cos, -1, 1))) < 1.0


def test_cli_reports_bad_input_in_one_paragraph(tmp_path):
    from typer.testing import CliRunner

    from uncertsplat.cli import app

    photos = tmp_path / "photos"
    photos.mkdir()
    for k in range(2):
        write_rgb(photos / f"n{k}.png", noise_image(k))
    result = CliRunner().invoke(app, ["reconstruct", str(photos), "-o", str(tmp_path / "ws")])
    assert result.exit_code == 2
    assert "only 2 photo(s) found" in result.output and "Traceback" not in result.output


def test_same_seed_single_thread_is_bitwise_reproducible(synth_scene, tmp_path):
    """With one thread COLMAP is deterministic given the seed (with several, only up to round-off)."""
    photos = tmp_path / "photos"
    photos.mkdir()
    for p in sorted((synth_scene / "images").iterdir())[:10]:
        shutil.copy(p, photos / p.name)
    cfg = ReconstructConfig(num_threads=1, seed=7, min_registered=0.5, mapping_attempts=1)
    centres = []
    for ws in ("a", "b"):
        report = stage.run(photos, tmp_path / ws, cfg)
        assert [a.seed for a in report.mapping_attempts] == [7] and report.mapping_agreed is None
        c = sfm.camera_centers(tmp_path / ws / "sparse" / "0")
        centres.append(np.stack([c[n] for n in sorted(c)]))
    assert len(centres[0]) >= 5
    np.testing.assert_array_equal(centres[0], centres[1])


def _digest(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and p.name != ".lock"}


def test_photos_added_to_the_folder_join_the_workspace_and_the_run(synth_scene, tmp_path, capsys):
    """The active-learning loop with real photos: a workspace of 20 photos, a run trained on it; two new photos
    put into the folder join the workspace (`reconstruct --extend`) with every camera there kept, and the run goes
    on with them (`train --resume --add-views`) in its own frame and with its own held-out views; bad inputs leave the
    workspace as it was."""
    import torch

    from uncertsplat.baselines import load_run
    from uncertsplat.config import train_config_from
    from uncertsplat.schemas import RunScene
    from uncertsplat.stages import train as train_stage

    names = sorted(p.name for p in (synth_scene / "images").iterdir())
    new = ["view_003.png", "view_009.png"]
    photos = tmp_path / "photos"
    photos.mkdir()
    for n in names[:20]:
        if n not in new:
            shutil.copy(synth_scene / "images" / n, photos / n)
    ws = tmp_path / "ws"
    # one mapping thread: the same poses every run (with two, a poor map once registered the re-saved held-out photo
    # far enough from its original that the twin test below did not find it: a failing CI run, 2026-11-30)
    one = CFG.model_copy(update={"num_threads": 1})
    stage.run(photos, ws, one)
    before = pycolmap.Reconstruction(ws / "sparse" / "0")
    run = tmp_path / "run"
    cfg = train_config_from("tiny", None, ["iterations=6", "scene.downscale=4.0", "eval_every=1000",
                                           "checkpoint_every=6"])
    train_stage.run(ws, run, cfg, torch.device("cpu"))
    trained = RunScene.read(run / "scene.json")
    # runs whose split depends on the scene's list: views set aside for calibration, training views by index
    others = {}
    for tag, scene_cfg in (("calibration", "scene.calibration_holdout=2"), ("indices", "scene.train_indices=[1,4,10,12]")):
        others[tag] = tmp_path / f"run_{tag}"
        train_stage.run(ws, others[tag], train_config_from("tiny", None, ["iterations=3", "scene.downscale=4.0",
                                                                          "eval_every=1000", scene_cfg]),
                        torch.device("cpu"))
    recorded = {tag: RunScene.read(r / "scene.json") for tag, r in others.items()}

    with pytest.raises(UserError, match="no new photo") as err:
        stage.run(photos, ws, one.model_copy(update={"extend": True}))
    assert "not the ones the workspace was made from" not in str(err.value)
    # a hidden file, a note and a copy added: only the copy is named as left out, and a note above says which (a
    # review's .DS_Store was named among "copies of a photo", with "the notes above" when none was printed)
    (photos / ".DS_Store").write_bytes(b"x")
    (photos / "notes.txt").write_text("taken at noon")
    copy = photos / ("copy_" + sorted(photos.glob("*.png"))[0].name)
    copy.write_bytes(sorted(photos.glob("*.png"))[0].read_bytes())
    with pytest.raises(UserError, match="no new photo") as err:
        stage.run(photos, ws, one.model_copy(update={"extend": True}))
    message = " ".join(str(err.value).split())
    assert f"(left out: {copy.name}, copies of a photo or sharing its name: the notes above)" in message
    assert ".DS_Store" not in message and "notes.txt" not in message
    for extra in (photos / ".DS_Store", photos / "notes.txt", copy):
        extra.unlink()
    # a photo edited since, none added: said with the first refusal (only after a whole extension before)
    first = sorted(photos.iterdir())[0]
    kept = first.read_bytes()
    edited = read_rgb(first).copy()
    edited[0, 0] ^= 1
    write_rgb(first, edited)
    with pytest.raises(UserError, match=rf"not the ones the workspace was made from .{first.name} edited or replaced"):
        stage.run(photos, ws, one.model_copy(update={"extend": True}))
    # a workspace whose report predates the photos' hashes (version 2): the photo is not named, the change still said
    report = json.loads((ws / "reconstruct_report.json").read_text(encoding="utf-8"))
    aside = (ws / "reconstruct_report.json").read_bytes()
    del report["photo_sha256"]
    report["schema_version"] = 2
    (ws / "reconstruct_report.json").write_text(json.dumps(report), encoding="utf-8")
    with pytest.raises(UserError, match="not the ones the workspace was made from .a photo edited or replaced"):
        stage.run(photos, ws, one.model_copy(update={"extend": True}))
    (ws / "reconstruct_report.json").write_bytes(aside)
    first.write_bytes(kept)
    with pytest.raises(UserError, match="needs a finished workspace"):
        stage.run(photos, tmp_path / "nowhere", one.model_copy(update={"extend": True}))
    with pytest.raises(ValueError, match="exclude each other"):
        ReconstructConfig(extend=True, overwrite=True)
    # the plain command on the grown folder points to --extend
    for n in new[:-1]:
        shutil.copy(synth_scene / "images" / n, photos / n)
    # the last new photo stored sideways with its EXIF tag (a phone's portrait photo): turned, and said
    write_rgb(photos / new[-1], np.rot90(read_rgb(synth_scene / "images" / new[-1]), k=1), orientation=6)
    # (said as the folder's own photos with some added, which a review read as "made from other photos")
    with pytest.raises(UserError, match=rf"this folder's photos as they were then: {len(new)} photo\(s\) added "
                                        rf"since \({re.escape(new[0])}") as err:
        stage.run(photos, ws, one)
    assert "--extend" in err.value.hint
    # a photo of nothing the others show does not register: said, and nothing changes
    write_rgb(photos / "view_zzz.png", noise_image(7, 320, 240))
    untouched = _digest(ws)
    shutil.move(photos / new[0], tmp_path / new[0])
    shutil.move(photos / new[1], tmp_path / new[1])
    with pytest.raises(UserError, match="none of the 1 new photo"):
        stage.run(photos, ws, one.model_copy(update={"extend": True}))
    assert _digest(ws) == untouched and not (ws / ".extend_tmp").exists()
    (photos / "view_zzz.png").unlink()
    for n in new:
        shutil.move(tmp_path / n, photos / n)
    gone = photos / names[1]
    shutil.move(gone, tmp_path / "aside.png")
    with pytest.raises(UserError, match="lacks 1 of the photos the workspace registered"):
        stage.run(photos, ws, one.model_copy(update={"extend": True}))
    shutil.move(tmp_path / "aside.png", gone)

    first = load_report(ws)
    capsys.readouterr()
    report = stage.run(photos, ws, one.model_copy(update={"extend": True}))
    assert report.success and set(new) <= set(report.images_registered) and len(report.images_registered) == 20
    assert report.rotated == [new[-1]] and [n for n in report.notes if n.startswith("EXIF")] == [
        f"EXIF orientation applied to 1 image(s): {new[-1]} (turned upright before feature extraction; the "
        "workspace's images are upright)"]
    assert f"EXIF orientation applied to 1 new image(s): {new[-1]}" in " ".join(capsys.readouterr().err.split())
    # the extension's time is counted in the stages as in the total (it kept the first run's stages before)
    for k in ("extract", "match", "map", "undistort"):
        assert report.stage_seconds[k] > first.stage_seconds[k], k
    assert report.total_seconds > first.total_seconds
    assert any(n.startswith("extended with 2 photo(s)") for n in report.notes)
    after = pycolmap.Reconstruction(ws / "sparse" / "0")
    moved, params = sfm.pose_changes(before, after)
    assert moved < 1e-12 and params == 0.0
    assert all((ws / "images" / n).read_bytes() == untouched[f"images/{n}"] for n in names[:20] if n not in new)
    assert stage.run(photos, ws, one) == report  # the grown folder is now the workspace's input

    # the run, before it trains on them, still loads (evaluate, select-views) and resumes in its own frame, with its
    # held-out views: the normalisation over 20 cameras moved every one of its 18 (refused as cameras that changed)
    old_run = load_run(run)
    capsys.readouterr()
    seen = old_run.load_scene()
    said = " ".join(capsys.readouterr().err.split())
    assert "loaded in the run's own frame" in said and "2 view(s) it has not trained on" in said, said
    assert "--resume --add-views NAMES" in said
    assert [seen.cameras.image_names[i] for i in seen.split["test"]] == trained.test
    assert set(new) <= set(seen.cameras.image_names) and old_run.frame_note is None
    for tag, r in others.items():  # their views as recorded, whatever the grown list's order and count
        got = load_run(r).load_scene()
        for split in ("train", "test", "calibration"):
            assert [got.cameras.image_names[i] for i in got.split.get(split, ())] == getattr(recorded[tag], split)
    train_stage.run(ws, run, cfg.model_copy(update={"iterations": 7}), torch.device("cpu"), resume=True, extend_to=7)
    resumed = RunScene.read(run / "scene.json")
    assert resumed.train == trained.train and resumed.extent == trained.extent  # (not the grown cameras' extent)

    train_stage.run(ws, run, cfg.model_copy(update={"iterations": 9}), torch.device("cpu"), resume=True,
                    extend_to=9, add_views=new)
    grown = RunScene.read(run / "scene.json")
    assert grown.test == trained.test and grown.world_from_source == trained.world_from_source
    assert grown.extent == trained.extent
    assert sorted(grown.train) == sorted(trained.train + new) and grown.views_added[-1].names == new
    loaded = load_run(run)
    capsys.readouterr()
    scene = loaded.load_scene()
    assert loaded.frame_note is None and [scene.cameras.image_names[i] for i in scene.split["test"]] == trained.test
    said = " ".join(capsys.readouterr().err.split())  # trained on them: a reminder, with nothing left to add
    assert "loaded in the run's own frame" in said and "has not trained on" not in said, said

    # a held-out photo saved again (other bytes, the same picture), an exact copy of a workspace photo whose name sorts
    # first, a photo of nothing here: the copy is left out (the workspace's name kept, said), the other two join the
    # folder, only the re-saved one registers, and neither can be trained on
    held = trained.test[0]
    again = read_rgb(photos / held).copy()
    again[0, 0] ^= 1
    write_rgb(photos / "resaved.png", again)
    shutil.copy(photos / names[1], photos / "0000.png")
    write_rgb(photos / "zz_noise.png", noise_image(7, 320, 240))
    capsys.readouterr()
    report = stage.run(photos, ws, one.model_copy(update={"extend": True}))
    assert "0000.png" in report.ignored and names[1] in report.images_registered
    said = " ".join(capsys.readouterr().err.split())
    assert "exact copies of another and were left out: 0000.png" in said
    assert "resaved.png" in report.images_registered and "zz_noise.png" in report.images_unregistered
    with pytest.raises(UserError, match=f"took the same picture as the held-out view {held}"):
        train_stage.run(ws, run, cfg.model_copy(update={"iterations": 12}), torch.device("cpu"), resume=True,
                        extend_to=12, add_views=["resaved.png"])
    with pytest.raises(UserError, match="the reconstruction did not register it .listed under images_unregistered"):
        train_stage.run(ws, run, cfg.model_copy(update={"iterations": 12}), torch.device("cpu"), resume=True,
                        extend_to=12, add_views=["zz_noise.png"])


def test_an_extend_stopped_while_it_swapped_is_undone(tmp_path):
    """``reconstruct --extend`` swaps the grown parts in one by one, the originals aside: stopped (or killed) half
    way, the originals go back (the next command's first step too); once the report is in, the grown workspace
    stays."""
    ws = tmp_path / "ws"
    parts = [Path("distorted/sparse/0"), Path("sparse/0"), Path("images")]
    for part in parts:
        (ws / part).mkdir(parents=True)
        (ws / part / "f").write_text("grown")
    (ws / "database.db").write_text("grown")
    (ws / REPORT_NAME).write_text("old report")
    aside = ws / stage.EXTEND_DIR / "old"
    for part in parts[:2]:  # two of four parts swapped when it stopped
        (aside / part).mkdir(parents=True)
        (aside / part / "f").write_text("original")
    from uncertsplat.sfm.scene import load_scene

    with pytest.raises(UserError, match="stopped while it replaced this workspace's parts") as err:
        load_scene(ws)  # train, evaluate: said, with the command that mends it
    assert "reconstruct" in err.value.hint
    stage._recover_extend(ws)
    assert [(ws / p / "f").read_text(encoding="utf-8") for p in parts] == ["original", "original", "grown"]
    assert not (ws / stage.EXTEND_DIR).exists()
    (aside / "images").mkdir(parents=True)  # every part and the report swapped: complete, kept
    (aside / "images" / "f").write_text("original")
    (aside / REPORT_NAME).write_text("old report")
    stage._recover_extend(ws)
    assert (ws / "images" / "f").read_text(encoding="utf-8") == "grown" and not (ws / stage.EXTEND_DIR).exists()
    # killed between the report's two moves: no report in the workspace; the grown one is moved in
    (ws / REPORT_NAME).rename(tmp_path / "r")
    aside.mkdir(parents=True)
    (aside / REPORT_NAME).write_text("old report")
    (ws / stage.EXTEND_DIR / REPORT_NAME).write_text("grown report")
    stage._recover_extend(ws)
    assert (ws / REPORT_NAME).read_text(encoding="utf-8") == "grown report" and not (ws / stage.EXTEND_DIR).exists()
    # killed while the finished swap's staging folder was removed: it was renamed first, so what is left of it is
    # only leftovers (its report marker may be gone before the originals: no half-made state to misread)
    (ws / stage.EXTEND_DONE / "old" / "images").mkdir(parents=True)
    (ws / stage.EXTEND_DONE / "old" / "images" / "f").write_text("original")
    stage._recover_extend(ws)
    assert not (ws / stage.EXTEND_DONE).exists() and (ws / "images" / "f").read_text(encoding="utf-8") == "grown"


def test_extend_names_new_photos_of_another_shape():
    """A square crop added to a 4:3 workspace registers, but `train` leaves it out of the scene: --extend said to add
    it; it now names it, and the other orientation of the same shape still counts as fitting."""
    from types import SimpleNamespace

    report = SimpleNamespace(undistorted_size={"a.jpg": [800, 600], "b.jpg": [800, 600], "sq.jpg": [600, 600],
                                               "tall.jpg": [600, 800], "small.jpg": [400, 300],
                                               "cropped.jpg": [800, 572]})
    # a size within 5 % is cropped in, another of the same shape resized, either orientation: as train fits them
    odd, common = stage._other_shapes(report, ["sq.jpg", "tall.jpg", "small.jpg", "cropped.jpg"])
    assert odd == ["sq.jpg"] and common == (800, 600)


def test_masks_keep_features_off_and_come_undistorted_into_the_workspace(synth_scene, tmp_path):
    """``--masks``: no feature under a mask's black pixels; the workspace's masks/ are the masks undistorted as their
    images (a mask drawn on an EXIF-turned photo as stored turned alike), read by training; other masks are other
    inputs; bad masks are refused by name."""
    from uncertsplat.sfm.scene import load_scene

    photos, masks = tmp_path / "photos", tmp_path / "masks"
    photos.mkdir()
    masks.mkdir()
    names = sorted(p.name for p in (synth_scene / "images").iterdir())
    turned, upside_down, bare = names[3], names[7], names[10]
    for name in names:
        arr = read_rgb(synth_scene / "images" / name)
        h, w = arr.shape[:2]
        m = np.full((h, w, 3), 255, np.uint8)
        m[:, : w // 4] = 0  # the left quarter of the upright photo is not the scene
        if name in (turned, upside_down):  # stored turned with its EXIF tag, its mask drawn on it as stored
            k, tag = (1, 6) if name == turned else (2, 3)
            write_rgb(photos / name, np.rot90(arr, k=k), orientation=tag)
            m = np.rot90(m, k=k)
        else:
            shutil.copy(synth_scene / "images" / name, photos / name)
        if name != bare:  # (a photo without a mask counts every pixel)
            write_rgb(masks / f"{name}.png", np.ascontiguousarray(m))
    cfg = CFG.model_copy(update={"masks": masks})
    ws = tmp_path / "ws"
    report = stage.run(photos, ws, cfg)
    assert report.success and report.rotated == sorted([turned, upside_down]) and bare in report.images_registered
    assert any(n.startswith(f"masks: {len(names) - 1} of {len(names)} photos have one") and bare in n
               for n in report.notes)
    with pycolmap.Database.open(ws / "database.db") as db:
        for image in db.read_all_images():
            kp = db.read_keypoints(image.image_id)
            if image.name == bare:
                assert float(kp[:, 0].min()) < w / 4 - 1.0  # features found where the others' masks are black
            else:
                assert len(kp) > 0 and float(kp[:, 0].min()) >= w / 4 - 1.0, image.name
    rec = pycolmap.Reconstruction(ws / "sparse" / "0")
    assert not (ws / "masks" / f"{bare}.png").exists()
    for image in rec.images.values():
        if image.name == bare:
            continue
        m = read_rgb(ws / "masks" / f"{image.name}.png")[..., 0] > 127
        assert m.shape == (image.camera.height, image.camera.width)
        cut = image.camera.width // 4
        assert not m[:, : cut - 3].any() and m[2:-2, cut + 3:-2].all(), image.name  # (COLMAP blanks a border)
    scene = load_scene(ws)
    assert scene.masks_train and sum(p is None for p in scene.mask_paths) == 1
    (note,) = [n for n in scene.notes if n.startswith("masks:")]
    assert "`reconstruct` undistorted the photos" not in note  # (its own masks are undistorted already)
    # the same photos and masks: reused; a mask changed: other inputs
    assert stage.run(photos, ws, cfg) == report
    write_rgb(masks / f"{names[0]}.png", np.full((h, w, 3), 255, np.uint8))
    with pytest.raises(UserError, match="made from this folder's photos as they were then: a photo or mask edited"):
        stage.run(photos, ws, cfg)
    # the same photos without the masks: said as such (a review's read "a photo edited or replaced since"), and
    # --extend, which only adds photos, is not offered
    with pytest.raises(UserError, match=rf"as they were then: made with the masks in {re.escape(str(masks))}, now "
                                        "without") as err:
        stage.run(photos, ws, cfg.model_copy(update={"masks": None}))
    assert "--extend" not in err.value.hint and "edited" not in err.value.message
    # bad masks: named
    write_rgb(masks / f"{names[0]}.png", np.full((h // 2, w, 3), 255, np.uint8))
    with pytest.raises(UserError, match=f"the mask is {w}x{h // 2}, another shape than its photo") as info:
        stage.run(photos, tmp_path / "ws2", cfg)
    assert f"{names[0]}.png" in str(info.value)
    with pytest.raises(UserError, match="the masks folder does not exist"):
        stage.run(photos, tmp_path / "ws3", CFG.model_copy(update={"masks": tmp_path / "nothing"}))


def _masked_photos(synth_scene, tmp_path, names):
    """``names`` of the synthetic scene's photos copied to tmp_path/photos, each with a mask in tmp_path/masks whose
    left quarter is black."""
    photos, masks = tmp_path / "photos", tmp_path / "masks"
    photos.mkdir(parents=True, exist_ok=True)
    masks.mkdir(exist_ok=True)
    for name in names:
        shutil.copy(synth_scene / "images" / name, photos / name)
        h, w = read_rgb(photos / name).shape[:2]
        m = np.full((h, w, 3), 255, np.uint8)
        m[:, : w // 4] = 0
        write_rgb(masks / f"{name}.png", m)
    return photos, masks


def _assert_left_quarter_masked(ws: Path, names) -> None:
    """The workspace's masks of ``names`` are the left-quarter masks undistorted, and no feature lies under them."""
    rec = pycolmap.Reconstruction(ws / "sparse" / "0")
    cams = {im.name: im.camera for im in rec.images.values()}
    for name in names:
        m = read_rgb(ws / "masks" / f"{name}.png")[..., 0] > 127
        cut = cams[name].width // 4
        assert m.shape == (cams[name].height, cams[name].width)
        assert not m[:, : cut - 3].any() and m[2:-2, cut + 3:-2].all(), name
    with pycolmap.Database.open(ws / "database.db") as db:
        for image in db.read_all_images():
            if image.name in names:
                w = cams[image.name].width
                assert float(db.read_keypoints(image.image_id)[:, 0].min()) >= w / 4 - 1.0, image.name


def test_extend_reads_the_new_photos_masks_from_the_workspaces_folder(synth_scene, tmp_path):
    """A workspace made with --masks: photos added with --extend take their masks from the same folder, undistorted
    into masks/ beside the others' (kept to the byte); --masks naming another folder is refused while the
    workspace's is there; a mask of a photo already there edited since is refused as an edited photo is."""
    names = sorted(p.name for p in (synth_scene / "images").iterdir())
    later = [names[13]]  # (a photo between two others of the ring; the last two did not register with fixed poses)
    last = names[5]  # (added by a second extension)
    names = [n for n in names if n != last]
    photos, masks = _masked_photos(synth_scene, tmp_path, [n for n in names if n not in later])
    ws = tmp_path / "ws"
    assert stage.run(photos, ws, CFG.model_copy(update={"masks": masks})).success
    before = {p.name: p.read_bytes() for p in (ws / "masks").iterdir()}
    _masked_photos(synth_scene, tmp_path, later)  # (the new photos and their masks into the same folders)
    other = tmp_path / "other_masks"
    shutil.copytree(masks, other)
    with pytest.raises(UserError, match="the workspace was made with the masks in"):
        stage.run(photos, ws, CFG.model_copy(update={"masks": other, "extend": True}))
    report = stage.run(photos, ws, CFG.model_copy(update={"extend": True}))
    assert set(later) <= set(report.images_registered)
    assert any(n.startswith("new photos' masks: 1 of 1 photos have one") for n in report.notes), report.notes
    assert all((ws / "masks" / n).read_bytes() == b for n, b in before.items())
    _assert_left_quarter_masked(ws, later)
    assert load_report(ws).options["masks"] == str(masks.resolve())
    # a second photo with an old photo's mask edited since: refused, the workspace as it was
    _masked_photos(synth_scene, tmp_path, [last])
    h, w = read_rgb(photos / names[0]).shape[:2]
    write_rgb(masks / f"{names[0]}.png", np.full((h, w, 3), 255, np.uint8))
    grown = {p.name: p.read_bytes() for p in (ws / "masks").iterdir()}
    with pytest.raises(UserError, match=r"the masks of 1 photo\(s\) already in the workspace changed") as err:
        stage.run(photos, ws, CFG.model_copy(update={"extend": True}))
    assert names[0] in str(err.value)
    assert {p.name: p.read_bytes() for p in (ws / "masks").iterdir()} == grown


def test_extend_with_masks_gives_a_workspace_without_them_its_masks_folder(synth_scene, tmp_path, monkeypatch):
    """--extend --masks on a workspace made without masks: the new photos' masks come into a masks/ of their own
    (the others count every pixel), and the folder is recorded for later extensions; stopped after every part was
    swapped in but before the report, the workspace is the one it was, without masks/."""
    from uncertsplat.errors import Interrupted
    from uncertsplat.sfm.scene import load_scene

    names = sorted(p.name for p in (synth_scene / "images").iterdir())
    later = names[13]
    photos = tmp_path / "photos"
    photos.mkdir()
    for name in names:
        if name == later:
            continue
        shutil.copy(synth_scene / "images" / name, photos / name)
    ws = tmp_path / "ws"
    assert stage.run(photos, ws, CFG).success and not (ws / "masks").exists()
    # a folder with masks of the photos already there: their features were taken without them
    _, old = _masked_photos(synth_scene, tmp_path / "old", names[:2])
    shutil.copy(synth_scene / "images" / later, photos / later)
    with pytest.raises(UserError, match=r"holds masks of 2 photo\(s\) the workspace was made without masks"):
        stage.run(photos, ws, CFG.model_copy(update={"masks": old, "extend": True}))
    # masks drawn on the workspace's images by hand: not taken over
    (ws / "masks").mkdir()
    _, masks = _masked_photos(synth_scene, tmp_path, [later])
    with pytest.raises(UserError, match="a masks/ folder that reconstruct did not make"):
        stage.run(photos, ws, CFG.model_copy(update={"masks": masks, "extend": True}))
    (ws / "masks").rmdir()
    untouched = _digest(ws)
    real_rename = Path.rename

    def stop_at_the_report(self, target):  # Ctrl-C as the old report is moved aside: every part is in by then
        if self.name == REPORT_NAME and Path(target).parent.name == "old":
            assert (ws / "masks").is_dir()
            raise KeyboardInterrupt
        return real_rename(self, target)

    with monkeypatch.context() as m:
        m.setattr(Path, "rename", stop_at_the_report)
        with pytest.raises(Interrupted, match="the workspace is as it was"):
            stage.run(photos, ws, CFG.model_copy(update={"masks": masks, "extend": True}))
    assert _digest(ws) == untouched and not (ws / "masks").exists()
    report = stage.run(photos, ws, CFG.model_copy(update={"masks": masks, "extend": True}))
    assert later in report.images_registered
    assert sorted(p.name for p in (ws / "masks").iterdir()) == [f"{later}.png"]
    _assert_left_quarter_masked(ws, [later])
    scene = load_scene(ws)
    assert scene.masks_train and sum(p is not None for p in scene.mask_paths) == 1


def test_an_extend_that_brought_masks_and_stopped_takes_them_out_again(tmp_path):
    """Stopped while it swapped: a masks/ the extension brought into a workspace without one goes (the marker
    ``NO_MASKS``); a workspace's own masks/ moved aside comes back."""
    ws = tmp_path / "ws"
    (ws / "masks").mkdir(parents=True)
    (ws / "masks" / "a.png").write_text("grown")
    (ws / REPORT_NAME).write_text("old report")
    aside = ws / stage.EXTEND_DIR / "old"
    aside.mkdir(parents=True)
    (aside / stage.NO_MASKS).touch()
    stage._recover_extend(ws)
    assert not (ws / "masks").exists() and not (ws / stage.EXTEND_DIR).exists()
    (ws / "masks").mkdir()
    (ws / "masks" / "a.png").write_text("grown")
    (aside / "masks").mkdir(parents=True)
    (aside / "masks" / "a.png").write_text("original")
    stage._recover_extend(ws)
    assert (ws / "masks" / "a.png").read_text(encoding="utf-8") == "original"
