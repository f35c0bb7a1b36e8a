"""Transient objects found from the residual (``train.transients``, ``TrainConfig.transients``): a region of one
photo far from its render is left out, the scene's thin edges and scattered noise are not, and the trainer keeps
each view's regions through a checkpoint."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from tests.e2e.test_train_resume import assert_same_parameters, toy_config, toy_scene
from tests.fixtures import tiny_scene_path  # noqa: F401
from uncertsplat.train.trainer import Trainer
from uncertsplat.train.transients import transient_masks, window_pixels

KW = {"threshold": 5.0, "window": 0.05, "core": 0.5, "max_share": 0.5}


def _scene(h: int = 96, w: int = 128, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """A textured photo [1,H,W,3] and its render: the photo plus small noise (a model that fits it)."""
    g = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    photo = torch.stack([0.5 + 0.3 * torch.sin(9 * xx), 0.4 + 0.2 * torch.cos(7 * yy), 0.3 + 0.2 * xx * yy], -1)
    render = photo + 0.02 * torch.randn(photo.shape, generator=g)
    return render[None], photo[None]


def _disc(h: int, w: int, cy: float, cx: float, r: float) -> torch.Tensor:
    yy, xx = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32), indexing="ij")
    return (yy - cy) ** 2 + (xx - cx) ** 2 <= r * r  # [H,W]


class TestTransientMasks:
    def test_a_disc_one_photo_shows_is_left_out_with_its_rim(self):
        render, photo = _scene()
        disc = _disc(96, 128, 40, 50, 14)
        photo[0][disc] = torch.tensor([1.0, 0.0, 1.0])
        keep = transient_masks(render, photo, **KW)[0, ..., 0]  # [H,W]
        assert not keep[disc].any(), "every pixel of the object is out"
        k = window_pixels(96, 128, KW["window"])
        wide = _disc(96, 128, 40, 50, 14 + k)
        assert keep[~wide].all(), "nothing farther than a window from it"
        assert (~keep).sum() > disc.sum(), "its rim goes with it"

    @pytest.mark.parametrize("width", [1, 2])
    def test_thin_lines_of_large_residual_stay(self, width):
        """Edges the model has not sharpened: lines of residual 0.5, every 10 rows and columns."""
        render, photo = _scene()
        for i in range(5, 96, 10):
            photo[0, i:i + width] += 0.5
        for j in range(5, 128, 10):
            photo[0, :, j:j + width] += 0.5
        assert transient_masks(render, photo, **KW).all()

    def test_scattered_pixels_of_large_residual_stay(self):
        render, photo = _scene()
        g = torch.Generator().manual_seed(3)
        hit = torch.rand(96, 128, generator=g) < 0.1
        photo[0][hit] = 1.0 - photo[0][hit]
        assert transient_masks(render, photo, **KW).all()

    def test_a_render_far_from_a_large_share_keeps_every_pixel(self):
        """A model far from much of the photo (early in training, another exposure): more than max_share."""
        render, photo = _scene()
        far = photo.clone()
        far[0, :, :56] = 1.0 - far[0, :, :56]  # 44 % of the pixels, 45 % with its rim
        assert transient_masks(render, far, **{**KW, "max_share": 0.4}).all()
        assert (~transient_masks(render, far, **{**KW, "max_share": 0.5})).float().mean() == pytest.approx(58 / 128)

    def test_the_share_is_of_the_valid_pixels_and_exactly_max_share_keeps_the_regions(self):
        """``max_share`` bounds the regions' share of the pixels that count: a region that covers exactly it is left out
        (only a larger one means a model far from the photo), and under a user's mask the share is of the pixels the
        mask lets count, not of the whole image."""
        render, photo = _scene(h=64)  # 8192 pixels: every share of them is exact in binary
        photo[0][_disc(64, 128, 30, 30, 12)] = torch.tensor([1.0, 0.0, 1.0])
        region = ~transient_masks(render, photo, **{**KW, "max_share": 1.0})
        share = float(region.sum()) / (64 * 128)
        assert 0.02 < share < 0.1
        assert torch.equal(~transient_masks(render, photo, **{**KW, "max_share": share}), region)
        assert transient_masks(render, photo, **{**KW, "max_share": share - 1e-6}).all()
        valid = torch.zeros(1, 64, 128, 1, dtype=torch.bool)
        valid[0, :, :64] = True  # the disc lies in the half that counts: twice the share of it
        assert torch.equal(~transient_masks(render, photo, **{**KW, "max_share": 2 * share}, valid=valid), region)
        assert transient_masks(render, photo, **{**KW, "max_share": 1.5 * share}, valid=valid).all()

    def test_a_window_exactly_core_full_of_candidates_is_transient(self):
        """The share of candidates is compared with ``core`` inclusively: with core 1 a block of candidates wider than
        the window is transient (every window inside it is full)."""
        render, photo = _scene()
        photo[0, 30:50, 40:70] = torch.tensor([1.0, 0.0, 1.0])
        keep = transient_masks(render, photo, **{**KW, "core": 1.0})[0, ..., 0]
        assert not keep[30:50, 40:70].any()

    def test_a_background_rendered_exactly_does_not_set_the_scale(self):
        """An object on a black background the model renders to the bit: the object's own residuals, not the
        background's zeros, are the typical residual, so only the object painted over counts."""
        render, photo = _scene()
        black = torch.zeros(96, 128, dtype=torch.bool)
        black[:, :40] = black[:, 90:] = True  # 60 % of the photo
        render[0][black] = photo[0][black] = 0.0
        assert transient_masks(render, photo, **KW).all()
        disc = _disc(96, 128, 40, 64, 12)
        photo[0][disc] = torch.tensor([1.0, 0.0, 1.0])
        keep = transient_masks(render, photo, **KW)[0, ..., 0]
        assert not keep[disc].any() and keep[:, 80:].all()

    def test_a_perfect_render_and_a_flat_photo_mark_nothing(self):
        photo = torch.full((2, 20, 30, 3), 0.5)
        photo[1, 5:15, 5:15] = 0.5 + 0.5 / 255  # below the floor's multiple: a quantisation step
        assert transient_masks(photo.clone(), photo.clone(), **KW).all()
        assert transient_masks(photo[:1].clone(), photo[1:].clone(), **KW).all()

    def test_pixels_a_users_mask_leaves_out_are_never_transient_nor_in_the_median(self):
        render, photo = _scene()
        disc = _disc(96, 128, 40, 64, 14)
        photo[0][disc] = torch.tensor([1.0, 0.0, 1.0])
        valid = torch.ones(1, 96, 128, 1, dtype=torch.bool)
        valid[0, :, :64] = False  # the disc's half under it
        keep = transient_masks(render, photo, **KW, valid=valid)[0, ..., 0]
        assert keep[:, :64].all() and not keep[:, 64:][disc[:, 64:]].any()
        # the median over the valid pixels only: a mask's zeros (render and photo 0 there) do not lower it
        zeroed_r, zeroed_p = render * valid, photo * valid
        zeroed_p[0][disc & (torch.arange(128) >= 64)] = torch.tensor([1.0, 0.0, 1.0])
        assert torch.equal(transient_masks(zeroed_r, zeroed_p, **KW, valid=valid)[0, ..., 0], keep)

    @pytest.mark.parametrize("shape", [(1, 1), (1, 7), (3, 3), (0, 5)])
    def test_tiny_and_empty_images(self, shape):
        h, w = shape
        photo = torch.rand(1, h, w, 3, generator=torch.Generator().manual_seed(0))
        keep = transient_masks(photo * 0, photo, **KW)
        assert keep.shape == (1, h, w, 1) and keep.dtype == torch.bool

    @pytest.mark.parametrize(("shape", "k"), [((2, 9, 13), 3), ((1, 40, 31), 7), ((1, 4, 5), 9), ((1, 1, 1), 3)])
    def test_box_count_is_a_zero_padded_window_sum(self, shape, k):
        """Against the pooling layers it replaces (count_include_pad: outside the image counts as False)."""
        import torch.nn.functional as F

        from uncertsplat.train.transients import box_count

        x = torch.rand(shape, generator=torch.Generator().manual_seed(k)) < 0.4
        want = F.avg_pool2d(x[:, None].double(), k, stride=1, padding=k // 2, count_include_pad=True)[:, 0] * k * k
        got = box_count(x, k)
        assert got.dtype == torch.int32 and torch.equal(got.double(), want.round())
        dilated = F.max_pool2d(x[:, None].float(), k, stride=1, padding=k // 2)[:, 0] > 0
        assert torch.equal(box_count(x, k) > 0, dilated)

    def test_window_sizes(self):
        assert window_pixels(96, 128, 0.03) == 3 and window_pixels(378, 504, 0.03) == 11
        assert window_pixels(1, 1, 0.5) == 3 and window_pixels(100, 100, 0.1) == 11  # an even 10 widened to 11


def _painted_trainer(state: dict | None = None) -> Trainer:
    """The toy scene with a magenta block in its first training photo, trained with transients.detect."""
    scene, tr, te = toy_scene()
    tr = tr.clone()
    tr[0, 8:20, 10:24] = torch.tensor([1.0, 0.0, 1.0])
    cfg = toy_config(iterations=60, transients={"detect": True, "start": 0.1, "window": 0.1, "core": 0.5})
    return Trainer(scene, cfg, tr, te, state=state)


class TestTrainerLeavesTransientsOut:
    def test_the_painted_view_keeps_its_region_and_the_posterior_leaves_it_out(self):
        t = _painted_trainer()
        t.fit()
        assert 0 in t.transient_keep, "the painted photo's region was found"
        keep = t.transient_mask(0)[..., 0]  # [36,48]
        assert (~keep[8:20, 10:24]).float().mean() > 0.6, "most of the block is out"
        rim = torch.ones_like(keep)
        rim[8 - 3:20 + 3, 10 - 3:24 + 3] = False  # (window 0.1 of 36 rows: 5 pixels, widened by 2)
        assert keep[rim].all(), "nothing farther than its rim"
        masks = t._train_masks(range(len(t.train_idx)))
        assert masks is not None and torch.equal(masks[0], t.transient_mask(0))
        assert all(masks[i].all() for i in range(1, len(masks)) if i not in t.transient_keep)

    def test_off_keeps_every_pixel(self):
        scene, tr, te = toy_scene()
        tr = tr.clone()
        tr[0, 8:20, 10:24] = torch.tensor([1.0, 0.0, 1.0])
        t = Trainer(scene, toy_config(iterations=60), tr, te)
        t.fit()
        assert t.transient_keep == {} and t._train_masks(range(len(t.train_idx))) is None

    def test_a_resume_restores_the_regions_exactly(self):
        from uncertsplat.io.checkpoints import decode, encode

        full = _painted_trainer()
        full.fit()
        part = _painted_trainer()
        part.fit(until=45)
        assert part.transient_keep, "the run must have found a region at the stop for the check to cover it"
        resumed = _painted_trainer(state=decode(encode(part.state_dict())))
        assert resumed.transient_keep.keys() == part.transient_keep.keys()
        assert all(torch.equal(resumed.transient_mask(v), part.transient_mask(v)) for v in part.transient_keep)
        resumed.fit()
        assert_same_parameters(full.model, resumed.model)
        assert resumed.transient_keep.keys() == full.transient_keep.keys()


    def test_an_extended_run_keeps_testing_from_where_it_began(self):
        """`train --resume` with more iterations: the test began at half of the first 60 steps and goes on at once
        (at half of the longer run's 200, the painted photo's known region was trained on again until step 100)."""
        from uncertsplat.io.checkpoints import decode, encode

        scene, tr, te = toy_scene()
        tr = tr.clone()
        tr[0, 8:20, 10:24] = torch.tensor([1.0, 0.0, 1.0])
        kw = {"transients": {"detect": True, "start": 0.5, "window": 0.1, "core": 0.5}}
        t = Trainer(scene, toy_config(iterations=60, **kw), tr, te)
        t.fit()
        assert 0 in t.transient_keep
        longer = Trainer(scene, toy_config(iterations=200, **kw), tr, te, state=decode(encode(t.state_dict())))
        assert longer.transients_from == 30
        fresh = Trainer(scene, toy_config(iterations=200, **kw), tr, te)
        assert fresh.transients_from == 100
        longer.fit(until=80)  # the longer run stopped again, then resumed with its own (200-step) settings
        again = Trainer(scene, toy_config(iterations=200, **kw), tr, te, state=decode(encode(longer.state_dict())))
        assert again.transients_from == 30
        early = _painted_trainer()  # (start 0.1: a run stopped before its test began stretches it with the run)
        early.fit(until=5)
        stretched = Trainer(early.scene, toy_config(iterations=600, transients=early.cfg.transients.model_dump()),
                            early.train_images, early.test_images, state=decode(encode(early.state_dict())))
        assert stretched.transients_from == 60

    def test_views_added_later_keep_the_regions_found_by_name(self):
        """`train --resume --add-views`: the checkpoint's regions follow their photos into the longer list."""
        import dataclasses

        from uncertsplat.io.checkpoints import decode, encode

        t = _painted_trainer()
        t.fit()
        names = t.scene.cameras.image_names
        before = {n: m for n, m in t.transient_regions(names).items()}
        assert before, "the run must find a region for the check to cover it"
        scene, te = t.scene, t.test_images
        more = dataclasses.replace(scene, split={"train": (*scene.split["train"], scene.split["test"][1]),
                                                 "test": scene.split["test"][:1]})
        images = torch.cat([t.train_images, te[1:2]])
        r = Trainer(more, t.cfg, images, te[:1], state=decode(encode(t.state_dict())))
        after = r.transient_regions(names)
        assert after.keys() == before.keys() and all(torch.equal(after[n], before[n]) for n in before)

    def test_the_masks_are_kept_a_bit_per_pixel(self):
        from uncertsplat.train.transients import pack_mask, unpack_mask

        keep = torch.rand(37, 29, 1, generator=torch.Generator().manual_seed(0)) < 0.5
        packed = pack_mask(keep)
        assert packed.dtype == torch.uint8 and packed.numel() == (37 * 29 + 7) // 8
        assert torch.equal(unpack_mask(packed, 37, 29), keep)


def test_a_run_writes_its_transients_and_the_fits_on_its_training_views_leave_them_out(tiny_scene_path, tmp_path,  # noqa: F811
                                                                                        monkeypatch):
    """End to end: train finds the blocks painted into three training photos, writes their masks under COLMAP's
    names (``RUN/transients/``) and their shares into train_summary.json; the training views evaluate fits on are
    read without them, and they are part of the run's mask digest (a kept noise fit of other regions is not reused).
    With the detection off no folder is written."""
    import shutil

    from tests.run_fixtures import train_tiny_run
    from uncertsplat.baselines import load_run
    from uncertsplat.data.dataset import TRANSIENTS_FOLDER
    from uncertsplat.io.images import read_image, read_mask, write_png
    from uncertsplat.schemas import TrainSummary
    from uncertsplat.sfm.scene import load_scene, run_mask_digest

    ws = tmp_path / "ws"
    shutil.copytree(tiny_scene_path / "images", ws / "images")
    shutil.copytree(tiny_scene_path / "sparse", ws / "sparse")
    scene = load_scene(ws)
    names = [scene.cameras.image_names[i] for i in scene.split["train"]]
    painted = names[:3]
    for n in painted:
        im = read_image(ws / "images" / n)
        h, w = im.shape[:2]
        im[h // 4:h // 2, w // 4:w // 2] = (1.0, 0.0, 1.0)
        write_png(ws / "images" / n, im)
    run = train_tiny_run(ws, tmp_path / "run", iterations=300,
                         transients={"detect": True, "start": 0.3, "window": 0.1, "core": 0.5})
    folder = run / TRANSIENTS_FOLDER
    found = sorted(p.name.removesuffix(".png") for p in folder.iterdir())
    summary = TrainSummary.read(run / "train_summary.json")
    assert set(painted) <= set(found) and sorted(summary.transients) == found
    assert all(summary.transients[n] > 0.05 for n in painted)
    mask = read_mask(folder / f"{painted[0]}.png")  # [H,W] bool, white where the pixels count
    h, w = mask.shape
    assert not mask[h // 4 + 2:h // 2 - 2, w // 4 + 2:w // 2 - 2].any() and mask.mean() > 0.5

    loaded = load_run(run)
    assert any(f"found in {len(found)} training photo(s)" in n for n in loaded.eval_notes(4))
    views = loaded.training_views(loaded.load_scene())(list(scene.split["train"][:4]))
    assert views.masks is not None
    assert [bool((~m).any()) for m in views.masks[:3]] == [True] * 3
    import uncertsplat.baselines.fisher as fisher
    from uncertsplat.stages import report

    seen = {}
    real = fisher.curvature

    def spy(*args, masks=None, **kw):
        seen["masks"] = masks
        return real(*args, masks=masks, **kw)

    monkeypatch.setattr(fisher, "curvature", spy)
    fisher.compute_fisher(run, torch.device("cpu"))
    # the Fisher baseline's curvature leaves them out as well (the training photos in their order)
    assert seen["masks"] is not None and [bool((~m).any()) for m in seen["masks"][:3]] == [True] * 3

    html = report.run(run, tmp_path / "report").read_text(encoding="utf-8")
    assert f"transients: found in {len(found)} training photo(s)" in html
    digest = run_mask_digest(run)
    assert digest is not None
    shutil.move(folder, tmp_path / "kept")
    assert run_mask_digest(run) is None, "a run without transients and masks keeps the digest it had"
    shutil.move(tmp_path / "kept", folder)
    assert run_mask_digest(run) == digest

    # a pruned run keeps what training left out of its photos (its evaluation fits as the source's)
    from uncertsplat.config import PruneConfig
    from uncertsplat.stages import prune

    prune.run(run, tmp_path / "pruned", PruneConfig(keep_ratio=0.9, num_samples=2), torch.device("cpu"))
    assert sorted(p.name.removesuffix(".png") for p in (tmp_path / "pruned" / TRANSIENTS_FOLDER).iterdir()) == found
    assert run_mask_digest(tmp_path / "pruned") is not None

    # a sweep's evaluation fits on the training views as evaluate does
    import uncertsplat.eval.engine as engine
    import uncertsplat.sweep.jobs as jobs

    calls = []
    real_fit = engine.fit_residual

    def fit_spy(*args, load_views, **kw):
        calls.append(load_views(list(scene.split["train"][:3])).masks)
        return real_fit(*args, load_views=load_views, **kw)

    monkeypatch.setattr(engine, "fit_residual", fit_spy)  # (jobs imports it when it runs)
    jobs._evaluate({"run_dir": str(run)}, {"id": 0, "eval_config": {"num_samples": 2, "save_maps": False}},
                   torch.device("cpu"))
    assert calls and calls[0] is not None and all(bool((~m).any()) for m in calls[0])

    # evaluate --split train scores the training views without them, as training's loss left them out; the
    # held-out views have none
    from uncertsplat.config import EvalConfig
    from uncertsplat.stages import evaluate

    scored = []
    real_views = engine.evaluate_views

    def views_spy(sampler, views, *args, notes=(), **kw):
        scored.append((views, list(notes)))
        return real_views(sampler, views, *args, notes=notes, **kw)

    monkeypatch.setattr(engine, "evaluate_views", views_spy)
    for split in ("train", "test"):
        evaluate.run(run, EvalConfig(split=split, num_samples=2, save_maps=False), torch.device("cpu"), quiet=True)
    (train_views, train_notes), (test_views, test_notes) = scored
    k = train_views.names.index(painted[0])
    assert not train_views.own_masks_too  # (the transient regions alone: the scene has no masks of its own)
    assert train_views.masks is not None and not train_views.masks[k].all() and train_views.masks_trained
    assert any("and of these training views' scores" in n for n in train_notes) and train_views.transients_out
    from uncertsplat.eval.engine import TRANSIENT_MASKS_NOTE
    from uncertsplat.schemas.metrics import EvalReport

    written = EvalReport.read(run / "eval-train" / "metrics.json").notes
    assert any(TRANSIENT_MASKS_NOTE in n for n in written), written
    assert test_views.masks is None and not test_views.transients_out and not any("these training views' scores" in n for n in test_notes)
    # a sweep point's evaluation of the training views scores them as evaluate does
    jobs._evaluate({"run_dir": str(run)}, {"id": 1, "eval_config": {"split": "train", "num_samples": 2,
                                                                    "save_maps": False}}, torch.device("cpu"))
    sweep_views, sweep_notes = scored[-1]
    assert torch.equal(sweep_views.masks, train_views.masks) and sweep_views.masks_trained
    assert any("and of these training views' scores" in n for n in sweep_notes)
    # masks of the photos added since training: the transient regions are left out of them too, but the masks are
    # not the ones training used (it trained on every pixel of the rest)
    (ws / "masks").mkdir()
    for n in names:
        h, w = read_image(ws / "images" / n).shape[:2]
        corner = np.ones((h, w, 3), np.float32)
        corner[: h // 8, : w // 8] = 0.0
        write_png(ws / "masks" / f"{n}.png", corner)
    evaluate.run(run, EvalConfig(split="train", num_samples=2, save_maps=False), torch.device("cpu"), quiet=True)
    masked_views, _ = scored[-1]
    k = masked_views.names.index(painted[0])
    assert not masked_views.masks_trained and not masked_views.masks[k, : h // 8, : w // 8].any()
    assert masked_views.own_masks_too
    written = EvalReport.read(run / "eval-train" / "metrics.json").notes
    assert not any(TRANSIENT_MASKS_NOTE in n for n in written)
    assert any("the transient regions training found in these views are left out too" in n for n in written)
    assert not masked_views.masks[k].all() and (~masked_views.masks[k]).sum() > (~train_views.masks[k]).sum()
    shutil.rmtree(ws / "masks")

    plain = train_tiny_run(ws, tmp_path / "plain", iterations=40)
    assert not (plain / TRANSIENTS_FOLDER).exists() and load_run(plain).eval_notes(4) == []
    assert TrainSummary.read(plain / "train_summary.json").transients is None


def test_a_model_read_from_a_newer_checkpoint_leaves_out_that_checkpoints_regions(tiny_scene_path, tmp_path,  # noqa: F811
                                                                                  monkeypatch):
    """A --resume stopped before it wrote its model is read from its newest checkpoint, but the fits on its training
    views left out RUN/transients/, written with the PLY by the earlier training: other regions than the ones that
    model was trained without (the checkpoint holds its own). The checkpoint's are used now."""
    import shutil

    from tests.run_fixtures import TINY_RUN_OVERRIDES, train_tiny_run
    from uncertsplat.baselines import load_run
    from uncertsplat.config import deep_update, train_config_from
    from uncertsplat.data.dataset import TRANSIENTS_FOLDER
    from uncertsplat.errors import UserError
    from uncertsplat.io.checkpoints import load_latest
    from uncertsplat.io.images import read_image, read_mask, write_png
    from uncertsplat.sfm.scene import load_scene
    from uncertsplat.stages import train
    from uncertsplat.train.transients import unpack_mask

    ws = tmp_path / "ws"
    shutil.copytree(tiny_scene_path / "images", ws / "images")
    shutil.copytree(tiny_scene_path / "sparse", ws / "sparse")
    scene = load_scene(ws)
    names = [scene.cameras.image_names[i] for i in scene.split["train"]]
    for n in names[:3]:
        im = read_image(ws / "images" / n)
        h, w = im.shape[:2]
        im[h // 4:h // 2, w // 4:w // 2] = (1.0, 0.0, 1.0)
        write_png(ws / "images" / n, im)
    found = {"detect": True, "start": 0.3, "window": 0.1, "core": 0.5}
    run = train_tiny_run(ws, tmp_path / "run", iterations=300, transients=found)
    real = Trainer.train_step

    def stopping(self, *args, **kw):
        out = real(self, *args, **kw)
        if self.step == 360:
            self._stop = True  # as a Ctrl-C: a checkpoint, no model files
        return out

    monkeypatch.setattr(Trainer, "train_step", stopping)
    cfg = train_config_from("tiny", deep_update(TINY_RUN_OVERRIDES, {"iterations": 300, "transients": found}))
    with pytest.raises(UserError, match="interrupted at step 360"):
        train.run(ws, run, cfg, device=torch.device("cpu"), resume=True, extend_to=500)
    _, state = load_latest(run)
    H, W = scene.cameras.height, scene.cameras.width
    ckpt = {state["train_names"][v]: unpack_mask(packed, H, W)[..., 0]
            for v, packed in zip(state["transient_views"].tolist(), state["transient_keep"], strict=True)}
    folder = {p.name.removesuffix(".png"): torch.from_numpy(read_mask(p))
              for p in (run / TRANSIENTS_FOLDER).iterdir()}
    assert ckpt and any(n not in folder or not torch.equal(m, folder[n]) for n, m in ckpt.items())
    loaded = load_run(run)
    assert loaded.step == 360
    views = loaded.training_views(loaded.load_scene())(list(scene.split["train"]))
    used = {n: views.masks[k, ..., 0] for k, n in enumerate(views.names) if not views.masks[k].all()}
    assert used.keys() == ckpt.keys() and all(torch.equal(used[n], m) for n, m in ckpt.items())
    assert any("(the checkpoint step_000360.pt)" in n for n in loaded.eval_notes(4))


def test_the_note_names_the_photos_and_their_share():
    from uncertsplat.train.transients import transients_note

    text = transients_note({"a.png": 0.1, "b.png": 0.3}, 20)
    assert "found in 2 of 20 training photos (a.png, b.png; 20.0% of their pixels on average)" in text
    assert text.endswith("the run's transients/ folder")
    assert transients_note({}, 5).startswith("transients: found in none of the 5 training photos;")
    assert transients_note({}) == "transients: found in no training photo; every pixel trained"
    assert transients_note({"a.png": 0.1}, where="the members' transients/ folders").endswith("folders")


def test_the_folder_is_replaced_whole_or_not_at_all(tmp_path, monkeypatch):
    """A stop while the new masks are written keeps the last whole folder, and the next write goes on from it."""
    from types import SimpleNamespace

    import uncertsplat.io.images as images
    from uncertsplat.train.session import _write_transients

    def trainer(regions, detect=True):
        return SimpleNamespace(cfg=SimpleNamespace(transients=SimpleNamespace(detect=detect)), train_idx=[0, 1, 2],
                               transient_regions=lambda names: regions, transients_stopped=None)

    keep = torch.ones(4, 6, dtype=torch.bool)
    keep[0, 0] = False
    assert _write_transients(tmp_path, trainer({"a.png": keep, "b.png": keep}), None) == {
        "a.png": round(1 / 24, 4), "b.png": round(1 / 24, 4)}
    assert sorted(p.name for p in (tmp_path / "transients").iterdir()) == ["a.png.png", "b.png.png"]
    from tests.fixtures import fail_png_write

    real = images.write_png
    fail_png_write(monkeypatch, 2)
    with pytest.raises(OSError):
        _write_transients(tmp_path, trainer({"c.png": keep, "d.png": keep}), None)
    assert sorted(p.name for p in (tmp_path / "transients").iterdir()) == ["a.png.png", "b.png.png"]
    monkeypatch.setattr(images, "write_png", real)
    _write_transients(tmp_path, trainer({"c.png": keep}), None)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["transients"]
    assert [p.name for p in (tmp_path / "transients").iterdir()] == ["c.png.png"]
    (tmp_path / "transients").rename(tmp_path / "transients.old")  # a stop between the swap's two renames
    assert _write_transients(tmp_path, trainer({}), None) == {}
    assert sorted(p.name for p in tmp_path.iterdir()) == [], "none found: no folder (the stale one gone)"
    _write_transients(tmp_path, trainer({"a.png": keep}), None)
    assert _write_transients(tmp_path, trainer({}, detect=False), None) is None and not any(tmp_path.iterdir())


def test_an_ensembles_members_leave_out_every_region_any_of_them_found(tmp_path):
    """Each member writes its own transients/: the fits on the training views leave out a region any member left
    out, the ensemble's summary takes each photo's largest share, and the members' folders are in the digest."""
    from uncertsplat.baselines.ensemble import _members_transients
    from uncertsplat.conventions import ENSEMBLE_MEMBERS
    from uncertsplat.data.dataset import TRANSIENTS_FOLDER, without_transients
    from uncertsplat.io.images import write_png
    from uncertsplat.sfm.scene import run_mask_digest

    scene = SimpleScene(("a.png", "b.png", "c.png"), 6, 4)
    members = [tmp_path / ENSEMBLE_MEMBERS / f"member_{i}" for i in range(2)]
    left = {0: ("a.png", (0, 0)), 1: ("a.png", (3, 5))}
    for i, (name, (y, x)) in left.items():
        m = torch.ones(4, 6, dtype=torch.bool)
        m[y, x] = False
        write_png(members[i] / TRANSIENTS_FOLDER / f"{name}.png", m.numpy())
    write_png(members[1] / TRANSIENTS_FOLDER / "c.png.png", torch.zeros(4, 6, dtype=torch.bool).numpy())
    masks = without_transients(None, scene, [0, 1, 2], members)
    assert masks.shape == (3, 4, 6, 1)
    assert not masks[0, 0, 0, 0] and not masks[0, 3, 5, 0] and int((~masks[0]).sum()) == 2
    assert masks[1].all() and not masks[2].any()
    assert without_transients(None, scene, [1], members) is None  # (none found for b.png)
    given = torch.ones(3, 4, 6, 1, dtype=torch.bool)
    assert torch.equal(without_transients(given, scene, [0, 1, 2], members), masks) and given.all()
    assert run_mask_digest(tmp_path) is not None
    from uncertsplat.schemas.runs import TrainSummary

    def summary(shares):
        return TrainSummary(method="variational", variant="ours", steps=1, seconds=1.0, sec_per_step=1.0,
                            num_gaussians=1, num_carriers=0, peak_memory_mb=0.0, device="cpu", scene="s",
                            transients=shares)

    assert _members_transients([summary(None), summary(None)], members) is None
    # a photo whose members' masks differ in shape (members at other resolutions): the largest member's share,
    # whatever the members' order
    other = tmp_path / "other"
    write_png(other / TRANSIENTS_FOLDER / "b.png.png", torch.zeros(2, 3, dtype=torch.bool).numpy())
    write_png(members[0] / TRANSIENTS_FOLDER / "b.png.png", torch.ones(4, 6, dtype=torch.bool).numpy())
    both = [summary({"b.png": 0.1}), summary({"b.png": 1.0})]
    assert _members_transients(both, [members[0], other])["b.png"] == 1.0
    assert _members_transients(both[::-1], [other, members[0]])["b.png"] == 1.0
    (members[0] / TRANSIENTS_FOLDER / "b.png.png").unlink()
    # the shares of what the fits leave out: a.png's two pixels (of 24), one from each member
    assert _members_transients([summary({"a.png": 0.0417}), summary({"a.png": 0.0417, "c.png": 1.0})], members) == {
        "a.png": round(2 / 24, 4), "c.png": 1.0}


class SimpleScene:
    """What ``without_transients`` reads of a scene: its cameras' names and size."""

    def __init__(self, names, width, height):
        from types import SimpleNamespace

        self.cameras = SimpleNamespace(image_names=names, width=width, height=height)


def test_regions_in_nearly_every_photo_are_warned_about():
    """Passers-by are seldom in nearly every photo; a part of the scene the model cannot fit is (bonsai: 40 of 42)."""
    from uncertsplat.train.transients import transients_warning

    shares = {f"{i}.png": 0.05 for i in range(40)}
    text = transients_warning(shares, 42)
    assert text is not None and text.startswith("transients were found in 40 of the 42 training photos")
    assert transients_warning(dict(list(shares.items())[:31]), 42) is None  # (below 3/4 of them)
    assert transients_warning(shares, 42 * 2) is None and transients_warning({}, 42) is None
    assert transients_warning(None, 42) is None and transients_warning({"a": 0.1, "b": 0.1}, 2) is None
    assert transients_warning({"a": 0.1, "b": 0.1, "c": 0.1}, 3) is None  # (fewer than 4 photos say nothing)
    assert transients_warning({"a": 0.1, "b": 0.1, "c": 0.1, "d": 0.1}, 4) is not None  # 4 of 4 do


def test_the_test_switches_itself_off_when_nearly_every_photo_has_regions():
    """Regions in three quarters of the photos or more after a pass over them are parts of the scene the model
    cannot fit (bonsai's flowers), not transients: the test stops, every pixel trains again, train warns; a resume
    keeps it stopped."""
    from uncertsplat.io.checkpoints import decode, encode
    from uncertsplat.train.transients import transients_warning

    scene, tr, te = toy_scene()
    tr = tr.clone()
    tr[:, 8:20, 10:24] = torch.tensor([1.0, 0.0, 1.0])  # (the block in every training photo)
    cfg = toy_config(iterations=60, transients={"detect": True, "start": 0.1, "window": 0.1, "core": 0.5})
    t = Trainer(scene, cfg, tr, te)
    t.fit(until=40)
    stopped = t.transients_stopped
    assert stopped is not None and stopped["of"] == len(t.train_idx) and stopped["photos"] >= 0.75 * stopped["of"]
    assert t.transient_keep == {} and t._train_masks(range(len(t.train_idx))) is None
    resumed = Trainer(scene, cfg, tr, te, state=decode(encode(t.state_dict())))
    assert resumed.transients_stopped == stopped
    resumed.fit()
    assert resumed.transient_keep == {}
    text = transients_warning({}, len(t.train_idx), stopped)
    assert text.startswith(f"transients: the test switched itself off at step {stopped['step']}")
    assert transients_warning(None, len(t.train_idx), stopped) is None  # (the detection off in that run)
    from uncertsplat.train.transients import transients_note

    note = transients_note({}, len(t.train_idx), stopped=stopped)
    assert note.startswith(f"transients: the test switched itself off at step {stopped['step']} (regions in")
    assert "found in none" not in note
    one = _painted_trainer()  # (one photo of six painted: it goes on)
    one.fit()
    assert one.transients_stopped is None and 0 in one.transient_keep


def test_the_masks_note_names_the_masks_the_metrics_are_taken_inside():
    """Training views scored without the transient regions training found: the note said "(and the photos' own
    masks, where it trained with them)" whichever the case; it names the photos' own masks only where they are in."""
    from uncertsplat.eval.engine import MASKED_NOTE_BELOW, PHOTO_MASKS_NOTE, TRANSIENT_MASKS_NOTE, masks_note
    from uncertsplat.types import Cameras, ViewSet

    cams = Cameras(torch.eye(4)[None], torch.eye(3)[None], 4, 4)
    views = ViewSet((0,), cams, torch.zeros(1, 4, 4, 3))
    assert masks_note(views, MASKED_NOTE_BELOW) is None
    alone = masks_note(dataclasses.replace(views, masks_trained=True, transients_out=True), 0.9)
    assert f"{TRANSIENT_MASKS_NOTE}, which training left out too" in alone and "own masks" not in alone
    both = masks_note(dataclasses.replace(views, masks_trained=True, transients_out=True, own_masks_too=True), 0.9)
    assert f"{TRANSIENT_MASKS_NOTE} and the photos' own masks, which training left out too" in both
    own = masks_note(dataclasses.replace(views, masks_trained=True), 0.9)
    assert PHOTO_MASKS_NOTE in own and "90%" in own and TRANSIENT_MASKS_NOTE not in own
    later = masks_note(dataclasses.replace(views, transients_out=True), 0.5)
    assert "train's held-out PSNR over whole images" in later and "transient regions training found" in later
