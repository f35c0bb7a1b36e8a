"""A user's masks (a COLMAP workspace's ``masks/``): found under COLMAP's names and the others tools use, read at
their photos' shape, and what they leave out is neither trained on nor scored: a transient object painted into the
masked pixels changes nothing of the model, its posterior or its metrics."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

from tests.e2e.test_train_resume import toy_config, toy_scene
from tests.fixtures import tiny_scene_path  # noqa: F401
from uncertsplat.data.dataset import load_masks
from uncertsplat.errors import UserError
from uncertsplat.io.images import read_image, write_png
from uncertsplat.sfm.scene import load_scene, mask_file
from uncertsplat.train.trainer import Trainer


def _block(h: int, w: int) -> np.ndarray:
    """[h,w] float32 mask: 1 everywhere but a block of the middle-left (a transient object's place)."""
    m = np.ones((h, w), dtype=np.float32)
    m[h // 4:3 * h // 4, w // 8:w // 2] = 0.0
    return m


@pytest.fixture
def masked_workspace(tiny_scene_path, tmp_path):  # noqa: F811
    """A COLMAP workspace of the tiny scene whose every photo has a mask with a black block (COLMAP's names)."""
    ws = tmp_path / "ws"
    shutil.copytree(tiny_scene_path / "images", ws / "images")
    shutil.copytree(tiny_scene_path / "sparse", ws / "sparse")
    (ws / "masks").mkdir()
    for photo in sorted((ws / "images").iterdir()):
        h, w = read_image(photo).shape[:2]
        write_png(ws / "masks" / f"{photo.name}.png", np.repeat(_block(h, w)[..., None], 3, axis=-1))
    return ws


def _paint(ws, colour=(1.0, 0.0, 1.0)) -> None:
    """Paint every photo of ``ws`` inside its mask's black block (a magenta person walking through)."""
    for photo in sorted((ws / "images").iterdir()):
        im = read_image(photo)
        im[_block(*im.shape[:2]) == 0.0] = colour
        write_png(photo, im)


class TestFindingMasks:
    def test_the_names_tools_use(self, tmp_path):
        (tmp_path / "a").mkdir()
        for name in ("IMG_1.jpg.png", "IMG_2.jpg", "a/IMG_3.png"):
            (tmp_path / name).write_bytes(b"x")
        assert mask_file(tmp_path, "IMG_1.jpg") == tmp_path / "IMG_1.jpg.png"  # COLMAP's
        assert mask_file(tmp_path, "IMG_2.jpg") == tmp_path / "IMG_2.jpg"  # the photo's own name
        assert mask_file(tmp_path, "a/IMG_3.jpg") == tmp_path / "a" / "IMG_3.png"  # its stem, in its sub-folder
        assert mask_file(tmp_path, "IMG_3.jpg") is None
        (tmp_path / "IMG_2.jpg.png").write_bytes(b"x")
        assert mask_file(tmp_path, "IMG_2.jpg") == tmp_path / "IMG_2.jpg.png"  # COLMAP's first

    def test_a_workspace_reads_its_masks_for_training_and_scoring(self, masked_workspace):
        for p in list((masked_workspace / "masks").iterdir())[:3]:  # three photos without a mask
            p.unlink()
        scene = load_scene(masked_workspace)
        assert scene.masks_train and scene.mask_paths is not None
        assert sum(m is None for m in scene.mask_paths) == 3
        (note,) = [n for n in scene.notes if n.startswith("masks:")]
        assert "21 of 24 photos have one" in note and "every pixel of the other 3 is" in note, note
        masks = load_masks(scene)  # [24,H,W,1]
        unmasked = [i for i, m in enumerate(scene.mask_paths) if m is None]
        assert bool(masks[unmasked].all())
        masked = [i for i, m in enumerate(scene.mask_paths) if m is not None]
        expect = torch.from_numpy(_block(scene.cameras.height, scene.cameras.width) > 0.5)
        assert all(torch.equal(masks[i, ..., 0], expect) for i in masked)

    def test_downscaled_a_pixel_counts_only_where_every_pixel_under_it_does(self, masked_workspace):
        from uncertsplat.config import SceneConfig

        full = load_masks(load_scene(masked_workspace))[0, ..., 0].float()  # [96,128]
        half = load_masks(load_scene(masked_workspace, SceneConfig(downscale=2)))[0, ..., 0]  # [48,64]
        expect = full.reshape(48, 2, 64, 2).amin(dim=(1, 3)) > 0.5
        assert torch.equal(half, expect)

    def test_a_folder_of_other_names_is_said_to_be_unread(self, masked_workspace):
        for p in (masked_workspace / "masks").iterdir():
            p.rename(p.with_name("mask_" + p.name))
        scene = load_scene(masked_workspace)
        assert scene.mask_paths is None and not scene.masks_train
        (note,) = [n for n in scene.notes if "masks" in n]
        assert "holds no mask named for any photo" in note and "view_000.png.png" in note, note

    def test_a_mask_of_another_shape_is_refused_by_name(self, masked_workspace):
        bad = masked_workspace / "masks" / "view_003.png.png"
        write_png(bad, np.ones((40, 128, 3), dtype=np.float32))
        scene = load_scene(masked_workspace)
        with pytest.raises(UserError) as info:
            load_masks(scene, [3])
        assert "the mask is 128x40, another shape than its view's 128x96" in str(info.value)
        assert "view_003.png.png" in str(info.value)


def _toy_trainer(images_painted: bool, masked: bool, **extra) -> Trainer:
    scene, tr, te = toy_scene()
    h, w = tr.shape[1:3]
    block = torch.from_numpy(_block(h, w) > 0.5)[None, ..., None]  # [1,H,W,1]
    if images_painted:
        tr = torch.where(block, tr, torch.tensor([1.0, 0.0, 1.0]))
        te = torch.where(block, te, torch.tensor([0.0, 1.0, 0.0]))
    masks = {"train_masks": block.expand(len(tr), -1, -1, -1).clone(),
             "test_masks": block.expand(len(te), -1, -1, -1).clone()} if masked else {}
    return Trainer(scene, toy_config(**extra), tr.clone(), te.clone(), **masks)


class TestTrainingLeavesMaskedPixelsOut:
    @pytest.mark.parametrize("extra", [{}, {"low_res_fraction": 0.4, "low_res_scale": 0.5},
                                       {"exposure": "affine"}])
    def test_what_the_masks_cover_changes_nothing(self, extra):
        """Two trainings whose photos differ only under the masks end with the same parameters to the bit, the
        same posterior updates, SH-band and growth tests and held-out scores; without masks they differ (the
        check can fail)."""
        runs = {}
        for painted in (False, True):
            t = _toy_trainer(painted, masked=True, **extra)
            t.fit()
            runs[painted] = t
        a, b = runs[False], runs[True]
        assert a.posterior_updates, "the toy run must update its posterior for the check to cover it"
        for name, p in a.model.parameters().items():
            assert torch.equal(p, b.model.parameters()[name]), name
        assert [u["noise_std"] for u in a.posterior_updates] == [u["noise_std"] for u in b.posterior_updates]
        assert a.sh_bands == b.sh_bands and a.growth == b.growth
        assert a.evaluate() == b.evaluate()
        assert a.training_psnr() == b.training_psnr() and a.photo_gains() == b.photo_gains()
        plain = _toy_trainer(True, masked=False, **extra)
        plain.fit()
        assert not torch.equal(plain.model.parameters()["sh0"], a.model.parameters()["sh0"])

    def test_masks_of_another_shape_are_refused(self):
        scene, tr, te = toy_scene()
        with pytest.raises(ValueError, match=r"masks must be \[C,H,W,1\]"):
            Trainer(scene, toy_config(), tr, te, train_masks=torch.ones(len(tr), 5, 5, 1, dtype=torch.bool))


def test_a_transient_under_the_masks_leaves_training_and_evaluation_as_they_were(masked_workspace, tmp_path):
    """End to end (train, then evaluate): the workspace's photos painted under their masks give the same model
    file and the same metrics, and evaluate says the masks were the photos' own."""
    from tests.run_fixtures import train_tiny_run
    from uncertsplat.config import EvalConfig
    from uncertsplat.eval.engine import PHOTO_MASKS_NOTE
    from uncertsplat.stages import evaluate

    painted = tmp_path / "painted"
    shutil.copytree(masked_workspace, painted)
    _paint(painted)
    metrics = []
    for ws in (masked_workspace, painted):
        run = train_tiny_run(ws, tmp_path / f"run_{ws.name}", iterations=60)
        evaluate.run(run, EvalConfig(num_samples=3, seed=1, save_maps=False), device=torch.device("cpu"), quiet=True)
        metrics.append(json.loads((run / "eval" / "metrics.json").read_text(encoding="utf-8")))
        assert (run / "variational.ply").is_file()
    a, b = ((tmp_path / f"run_{n}" / "variational.ply").read_bytes() for n in ("ws", "painted"))
    assert a == b
    assert any(PHOTO_MASKS_NOTE in n for n in metrics[0]["notes"]), metrics[0]["notes"]
    for key in ("psnr", "ssim", "ause_mae", "nll", "calibration_error"):
        assert metrics[0]["mean"][key] == metrics[1]["mean"][key], key


def test_the_curvature_and_noise_leave_masked_pixels_out():
    """``curvature`` (the informed posterior's, the Fisher baseline's, select-views' fisher score): the same Fisher
    and noise whatever the photos hold under their masks; without masks the painted pixels raise the noise."""
    from uncertsplat.uncertainty.curvature import curvature

    t = _toy_trainer(False, masked=False, iterations=10)
    params = {k: v.detach() for k, v in t.model.params.items()}
    images = t.train_images.clone()  # [T,H,W,3]
    block = torch.from_numpy(_block(*images.shape[1:3]) > 0.5)[None, ..., None].expand(len(images), -1, -1, -1)
    painted = torch.where(block, images, torch.tensor([1.0, 0.0, 1.0]))

    def run(imgs, masks):
        gen = torch.Generator().manual_seed(0)
        return curvature(params, t.train_cams, imgs, t.render, names=("means", "opacities"), generator=gen,
                         sh_degree=0, probes=2, masks=masks)

    a, b = run(images, block), run(painted, block)
    assert a.noise_std == b.noise_std and all(torch.equal(a.fisher[k], b.fisher[k]) for k in a.fisher)
    assert run(painted, None).noise_std > 2 * run(images, None).noise_std


class TestMaskValues:
    """``io.images.read_mask``: the ways tools save a mask."""

    def _write_rgba(self, path, rgb, alpha):
        import OpenImageIO as oiio

        arr = np.concatenate([rgb, alpha[..., None]], axis=-1).astype(np.uint8)
        spec = oiio.ImageSpec(arr.shape[1], arr.shape[0], 4, "uint8")
        spec.alpha_channel = 3
        out = oiio.ImageOutput.create(str(path))
        out.open(str(path), spec)
        out.write_image(np.ascontiguousarray(arr))
        out.close()

    def test_white_a_zero_one_mask_a_palette_colour_and_alpha(self, tmp_path):
        from uncertsplat.io.images import read_mask

        expect = np.zeros((6, 8), dtype=bool)
        expect[:, 3:] = True
        write_png(tmp_path / "white.png", np.repeat(expect[..., None].astype(np.float32), 3, axis=-1))
        write_png(tmp_path / "ones.png", np.repeat(expect[..., None].astype(np.float32), 3, axis=-1) / 255.0)
        green = np.zeros((6, 8, 3), dtype=np.float32)
        green[expect] = (0.0, 1.0, 0.0)  # a palette mask's index 1 as its colour
        write_png(tmp_path / "green.png", green)
        black_in_alpha = np.zeros((6, 8, 3))
        self._write_rgba(tmp_path / "alpha_black.png", black_in_alpha, expect * 255)
        self._write_rgba(tmp_path / "alpha_white.png", black_in_alpha + 255, expect * 255)
        both = np.zeros((6, 8, 3))
        both[:, 5:] = 255  # white only on part of where alpha holds: colour and alpha together
        self._write_rgba(tmp_path / "both.png", both, expect * 255)
        self._write_rgba(tmp_path / "ones_opaque.png", np.repeat(expect[..., None], 3, axis=-1),
                         np.full((6, 8), 255))  # a 0/1 mask converted to RGBA: its alpha opaque everywhere
        for name in ("white", "ones", "green", "alpha_black", "alpha_white", "ones_opaque"):
            assert np.array_equal(read_mask(tmp_path / f"{name}.png"), expect), name
        got = read_mask(tmp_path / "both.png")
        assert got[:, 5:].all() and not got[:, :5].any()

    def test_a_mask_that_leaves_no_pixel_is_refused_by_name(self, masked_workspace):
        write_png(masked_workspace / "masks" / "view_005.png.png", np.zeros((96, 128, 3), dtype=np.float32))
        scene = load_scene(masked_workspace)
        with pytest.raises(UserError, match=r"the mask leaves no pixel of its photo \(view_005.png\)") as info:
            load_masks(scene)
        assert "view_005.png.png" in str(info.value)


def test_the_training_coverage_is_taken_inside_the_masks():
    """The empty-ray term's level (``training_coverage``): a masked-out sky is no surface the model should cover."""
    from uncertsplat.uncertainty.mc import training_coverage

    t = _toy_trainer(False, masked=False, iterations=10)
    sample = t.mean_sample()
    alpha = t.render(sample, t.train_cams[[0]]).alpha[0]  # [H,W,1]
    lit = alpha > 0.5  # the pixels the model covers
    everywhere = training_coverage(sample, t.train_cams[[0]], t.render, quantile=0.05)
    inside = training_coverage(sample, t.train_cams[[0]], t.render, quantile=0.05, masks_of=lambda pick: lit[None])
    assert everywhere < 0.5 < inside


def test_ssim_inside_a_mask_is_not_inflated_by_what_it_leaves_out():
    from uncertsplat.eval.image import masked_ssim, ssim

    g = torch.Generator().manual_seed(0)
    target = torch.rand(48, 64, 3, generator=g)
    pred = (target + 0.2 * torch.randn(48, 64, 3, generator=g)).clamp(0, 1)
    mask = torch.zeros(48, 64, 1, dtype=torch.bool)
    mask[:, 32:] = True
    inside = masked_ssim(pred, target, mask)
    other = torch.where(mask, pred, torch.rand(48, 64, 3, generator=g))  # anything outside the mask
    assert masked_ssim(other, target, mask) == inside
    assert inside < float(ssim(pred * mask, target * mask)) - 0.05  # the zeros outside would count as matching


def test_masks_added_or_changed_after_training_are_said_and_scored_again(masked_workspace, tmp_path):
    """The run records the masks it was trained with (scene.json): masks added after training are scored inside but
    not called the ones training left out; a mask changed since makes evaluate score again instead of reusing."""
    from tests.run_fixtures import train_tiny_run
    from uncertsplat.config import EvalConfig
    from uncertsplat.eval.engine import PHOTO_MASKS_NOTE
    from uncertsplat.schemas.scene import RunScene
    from uncertsplat.stages import evaluate

    masks = masked_workspace / "masks"
    aside = tmp_path / "masks_aside"
    masks.rename(aside)
    run = train_tiny_run(masked_workspace, tmp_path / "run", iterations=40)
    assert RunScene.read(run / "scene.json").masks == {}
    aside.rename(masks)  # added after training
    cfg = EvalConfig(num_samples=2, seed=1, save_maps=False)
    evaluate.run(run, cfg, device=torch.device("cpu"), quiet=True)
    notes = json.loads((run / "eval" / "metrics.json").read_text(encoding="utf-8"))["notes"]
    assert not any(PHOTO_MASKS_NOTE in n for n in notes)
    assert any("or the photos' own added after training" in n for n in notes), notes
    # what is computed from the fit (the coverage, the Fisher curvature, select-views) takes the pixels training
    # fitted: every one, as its loss did not leave the added masks' out
    from uncertsplat.baselines import load_run
    from uncertsplat.data.dataset import load_masks

    loaded = load_run(run, torch.device("cpu"))
    scene = loaded.load_scene()
    train_idx = list(scene.split["train"])
    assert scene.masks_train and loaded.training_masks(scene, train_idx) is None

    trained = train_tiny_run(masked_workspace, tmp_path / "run2", iterations=40)
    recorded = RunScene.read(trained / "scene.json").masks
    assert len(recorded) == 24 and set(recorded.values()) != {""}
    fitted = load_run(trained, torch.device("cpu")).training_masks(scene, train_idx)
    assert fitted is not None and torch.equal(fitted, load_masks(scene, train_idx)) and not bool(fitted.all())
    evaluate.run(trained, cfg, device=torch.device("cpu"), quiet=True)
    first = (trained / "eval" / "metrics.json").stat().st_mtime_ns
    evaluate.run(trained, cfg, device=torch.device("cpu"), quiet=True)
    assert (trained / "eval" / "metrics.json").stat().st_mtime_ns == first  # the same masks: reused
    original = (masks / "view_000.png.png").read_bytes()
    write_png(masks / "view_000.png.png", np.ones((96, 128, 3), dtype=np.float32))  # a held-out view's mask
    evaluate.run(trained, cfg, device=torch.device("cpu"), quiet=True)
    second = (trained / "eval" / "metrics.json").stat().st_mtime_ns
    assert second != first  # scored again, inside the new mask
    evaluate.run(trained, cfg, device=torch.device("cpu"), quiet=True)
    assert (trained / "eval" / "metrics.json").stat().st_mtime_ns == second  # and kept while the masks stay
    (masks / "view_000.png.png").write_bytes(original)
    evaluate.run(trained, cfg, device=torch.device("cpu"), quiet=True)
    assert (trained / "eval" / "metrics.json").stat().st_mtime_ns != second  # the mask put back: scored again
    # a finished run resumed (on a moved scene, say) trains nothing: the masks it was trained with stay recorded;
    # the noise fit kept for the run is keyed by the masks as they are now
    from tests.run_fixtures import TINY_RUN_OVERRIDES
    from uncertsplat.config import deep_update, train_config_from
    from uncertsplat.stages import train
    from uncertsplat.stages.residual_cache import run_digests

    before = run_digests(load_run(trained, torch.device("cpu")))
    write_png(masks / "view_001.png.png", np.ones((96, 128, 3), dtype=np.float32))  # a training view's mask
    assert run_digests(load_run(trained, torch.device("cpu")))["masks"] != before["masks"]
    tcfg = train_config_from("tiny", deep_update(TINY_RUN_OVERRIDES, {"iterations": 40}))
    moved = tmp_path / "moved_ws"
    shutil.copytree(masked_workspace, moved)
    shutil.rmtree(masked_workspace)  # the scene moved (the run is pointed at its new place)
    digest_gone = run_digests(load_run(trained, torch.device("cpu")))  # away from its photos: the trained masks'
    assert digest_gone["masks"] == before["masks"]
    train.run(moved, trained, tcfg, device=torch.device("cpu"), resume=True)
    assert RunScene.read(trained / "scene.json").masks == recorded
    assert RunScene.read(trained / "scene.json").scene == str(moved.resolve())


@pytest.mark.parametrize("max_size", [0, 150])  # warped directly; warped at the photo's size, then filtered down
def test_an_undistorted_mask_keeps_no_pixel_the_undistorter_blends_with_a_masked_one(max_size):
    """``reconstruct --masks`` carries each mask to its undistorted image (``sfm.reconstruct.undistorted_mask``):
    COLMAP's own undistortion of the mask as an image is fully white on every pixel kept, and nearly every fully
    white pixel is kept."""
    import pycolmap

    from uncertsplat.sfm.reconstruct import undistorted_mask

    old = pycolmap.Camera.create_from_model_id(1, pycolmap.CameraModelId.SIMPLE_RADIAL, 300.0, 400, 300)
    old.params = np.array([300.0, 200.0, 150.0, -0.15])
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:300, 0:400]
    mask = np.ones((300, 400), dtype=bool)
    for _ in range(12):  # discs left out
        cx, cy, r = rng.uniform(0, 400), rng.uniform(0, 300), rng.uniform(10, 40)
        mask &= (xx - cx) ** 2 + (yy - cy) ** 2 > r * r
    options = pycolmap.UndistortCameraOptions()
    if max_size:
        options.max_image_size = max_size
    bitmap = pycolmap.Bitmap.from_array(np.repeat((mask * 255).astype(np.uint8)[..., None], 3, axis=-1))
    image, cam = pycolmap.undistort_image(options, bitmap, old)
    blended = image.to_array()[..., 0]  # [H,W] uint8
    kept = undistorted_mask(mask, cam, old)
    assert kept.shape == blended.shape
    assert int((blended[kept] < 255).sum()) == 0
    assert kept.sum() >= 0.9 * (blended == 255).sum()


@pytest.mark.parametrize(("model", "params"), [("PINHOLE", [50.0, 50.0, 20.0, 15.0]),
                                                ("SIMPLE_RADIAL", [50.0, 20.0, 15.0, 0.15])])
def test_an_undistorted_mask_is_what_colmap_fills_at_the_photo_s_edges(model, params):
    """A mask that keeps every pixel: the undistorted mask is exactly the pixels COLMAP's undistortion fills (its
    bilinear lookup needs the four neighbours inside the photo: a pinhole photo's own last row and column, at x =
    W - 1 exactly, come out blank)."""
    import pycolmap

    from uncertsplat.sfm.reconstruct import undistorted_mask

    old = pycolmap.Camera(model=model, width=40, height=30, params=params)
    mask = np.ones((30, 40), dtype=bool)
    bitmap = pycolmap.Bitmap.from_array(np.full((30, 40, 3), 255, dtype=np.uint8))
    image, cam = pycolmap.undistort_image(pycolmap.UndistortCameraOptions(), bitmap, old)
    filled = image.to_array()[..., 0] == 255
    np.testing.assert_array_equal(undistorted_mask(mask, cam, old), filled)
    if model == "PINHOLE":
        assert not filled[-1].any() and not filled[:, -1].any() and filled[:-1, :-1].all()
