"""Per-photo exposure (``TrainConfig.exposure``, ``render.exposure``): the affine map and its inverse, the spread's
variance against a direct computation, what training learns from photos of known exposure, exact resume, views added
on resume, and what evaluation reads back."""

from __future__ import annotations

import pydantic
import pytest
import torch

from tests.e2e.test_train_resume import assert_resume_is_exact, assert_same_parameters, toy_config, toy_scene
from tests.fixtures import tiny_scene_path  # noqa: F401
from tests.run_fixtures import tiny_run_path  # noqa: F401
from uncertsplat.baselines.runs import mean_exposure
from uncertsplat.config import TrainConfig
from uncertsplat.io.checkpoints import decode, encode
from uncertsplat.render.exposure import PhotoExposure, centred, expose, fitted_gain, spread_variance, unexpose
from uncertsplat.schemas import RunExposure
from uncertsplat.strategy.exposure import EXPOSURE_SPREAD, gain_spread
from uncertsplat.train.trainer import Trainer
from uncertsplat.types import Cameras, ViewSet


class TestAffineMap:
    def test_centred_has_unit_geometric_mean_gain_and_zero_mean_offset(self):
        params = torch.randn(7, 2, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
        gain, offset = centred(params)
        torch.testing.assert_close(gain.log().mean(0), torch.zeros(3, dtype=torch.float64))
        torch.testing.assert_close(offset.mean(0), torch.zeros(3, dtype=torch.float64))
        # a shift of every photo's parameters is the same exposure
        shifted = centred(params + torch.tensor([0.3, -0.2], dtype=torch.float64)[None, :, None])
        torch.testing.assert_close(shifted[0], gain)
        torch.testing.assert_close(shifted[1], offset)

    def test_unexpose_inverts_expose(self):
        g = torch.Generator().manual_seed(1)
        rgb = torch.rand(3, 5, 4, 3, generator=g, dtype=torch.float64)
        gain = 0.5 + torch.rand(3, 3, generator=g, dtype=torch.float64)
        offset = 0.1 * torch.randn(3, 3, generator=g, dtype=torch.float64)
        shown = expose(rgb, gain, offset)
        torch.testing.assert_close(shown[1, 2, 3], rgb[1, 2, 3] * gain[1] + offset[1])
        torch.testing.assert_close(unexpose(shown, gain, offset), rgb)

    def test_fitted_gain_finds_a_photos_brightness(self):
        g = torch.Generator().manual_seed(3)
        render = torch.rand(6, 8, 3, generator=g, dtype=torch.float64)
        assert fitted_gain(render, render) == pytest.approx(1.0)
        assert fitted_gain(render, 1.3 * render + 0.05) == pytest.approx(1.3)  # an offset does not change the gain
        gains = torch.tensor([0.5, 1.0, 2.0], dtype=torch.float64)
        assert fitted_gain(render, render * gains) == pytest.approx(float(gains.mean()))  # mean over the channels
        assert fitted_gain(torch.full((6, 8, 3), 0.4), render) == 1.0  # a flat render says nothing

    def test_spread_variance_is_the_variance_over_the_photos(self):
        g = torch.Generator().manual_seed(2)
        gain = 0.6 + 0.8 * torch.rand(9, 3, generator=g, dtype=torch.float64)
        offset = 0.05 * torch.randn(9, 3, generator=g, dtype=torch.float64)
        rgb = torch.rand(4, 6, 3, generator=g, dtype=torch.float64)
        shown = gain[:, None, None, :] * rgb[None] + offset[:, None, None, :]  # [T,4,6,3]
        direct = shown.var(0, unbiased=False).mean(-1, keepdim=True)
        torch.testing.assert_close(spread_variance(rgb, gain, offset), direct)

    def test_spread_variance_at_the_extremes(self):
        rgb = torch.rand(2, 3, 3)
        one = spread_variance(rgb, torch.ones(1, 3), torch.zeros(1, 3))
        assert one.shape == (2, 3, 1) and bool((one == 0).all())  # one photo: no spread
        same = spread_variance(rgb, torch.full((5, 3), 1.3), torch.full((5, 3), 0.02))
        torch.testing.assert_close(same, torch.zeros(2, 3, 1))  # identical exposures: none either
        offsets_only = spread_variance(rgb, torch.ones(2, 3), torch.tensor([[0.1] * 3, [-0.1] * 3]))
        torch.testing.assert_close(offsets_only, torch.full((2, 3, 1), 0.01))  # independent of the colour


class TestPhotoExposure:
    def test_only_the_training_photos_are_brought_to_the_models_exposure(self):
        images = torch.full((3, 2, 2, 3), 0.6)
        cams = Cameras(torch.eye(4).expand(3, 4, 4).clone(), torch.eye(3).expand(3, 3, 3).clone(), 2, 2,
                       ("a.png", "b.png", "c.png"))
        views = ViewSet(indices=(4, 7, 9), cameras=cams, images=images)
        ex = PhotoExposure((9, 4), torch.tensor([[2.0] * 3, [0.5] * 3]), torch.tensor([[0.1] * 3, [0.0] * 3]))
        out = ex.unexposed(views)
        torch.testing.assert_close(out.images[0], torch.full((2, 2, 3), 1.2))  # view 4: gain 0.5
        torch.testing.assert_close(out.images[1], images[1])  # view 7: not a training photo, as it is
        torch.testing.assert_close(out.images[2], torch.full((2, 2, 3), 0.25))  # view 9: (0.6 - 0.1) / 2
        assert torch.equal(views.images, images)  # the input is not changed
        none = PhotoExposure((1,), torch.ones(1, 3), torch.zeros(1, 3))
        assert none.unexposed(views) is views

    def test_run_exposure_is_checked(self):
        ok = RunExposure(images=["a", "b"], gain=[[1.0] * 3, [1.0] * 3], offset=[[0.0] * 3, [0.0] * 3], step=3)
        assert "2 training photos" in ok.describe()
        with pytest.raises(pydantic.ValidationError, match="2 images but 1 gains"):
            RunExposure(images=["a", "b"], gain=[[1.0] * 3], offset=[[0.0] * 3, [0.0] * 3], step=0)
        with pytest.raises(pydantic.ValidationError, match="positive"):
            RunExposure(images=["a"], gain=[[1.0, 0.0, 1.0]], offset=[[0.0] * 3], step=0)
        with pytest.raises(pydantic.ValidationError, match="3 channels"):
            RunExposure(images=["a"], gain=[[1.0, 1.0]], offset=[[0.0] * 3], step=0)

    def test_an_ensembles_exposure_is_the_members_mean(self):
        a = RunExposure(images=["x", "y"], gain=[[2.0] * 3, [0.5] * 3], offset=[[0.1] * 3, [-0.1] * 3], step=5)
        b = RunExposure(images=["x", "y"], gain=[[0.5] * 3, [2.0] * 3], offset=[[0.3] * 3, [0.1] * 3], step=4)
        m = mean_exposure([a, b])
        assert m is not None and m.step == 4
        torch.testing.assert_close(torch.tensor(m.gain, dtype=torch.float64), torch.ones(2, 3, dtype=torch.float64))  # geometric mean
        torch.testing.assert_close(torch.tensor(m.offset, dtype=torch.float64), torch.tensor([[0.2] * 3, [0.0] * 3], dtype=torch.float64))
        assert mean_exposure([a, None]) is None
        assert mean_exposure([a, b.model_copy(update={"images": ["x", "z"]})]) is None


def _exposed_toy(gains: torch.Tensor):
    """The toy scene with training photo i shown at gain ``gains[i]`` (all channels)."""
    scene, tr, te = toy_scene()
    return scene, (tr * gains[:, None, None, None]).clamp(0, 1), te


class TestTraining:
    def test_off_by_default_learns_nothing(self):
        assert TrainConfig().exposure == "off"
        scene, tr, te = toy_scene()
        t = Trainer(scene, toy_config(iterations=3, exposure="off"), tr, te)
        t.fit()
        assert t.exposure is None and t.exposures() is None and t.exposure_record(["x"] * 8) is None
        assert torch.equal(t.photos([0, 2]), tr[[0, 2]]) and t.photos() is tr
        assert t.state_dict()["exposure"] is None and t.exposure_checks == []

    def test_auto_trains_photos_of_one_exposure_exactly_as_off(self):
        scene, tr, te = toy_scene()
        off = Trainer(scene, toy_config(exposure="off"), tr, te)
        off.fit()
        auto = Trainer(scene, toy_config(exposure="auto", exposure_check_interval=5), tr, te)
        auto.fit()
        assert auto.exposure is None
        # tests after steps 10 and 15 (from a fifth to half of the 30 steps), none switching the exposures on
        assert [c.step for c in auto.exposure_checks] == [10, 15]
        assert not any(c.enabled for c in auto.exposure_checks)
        assert all(c.spread < EXPOSURE_SPREAD for c in auto.exposure_checks)
        assert_same_parameters(off.model, auto.model, atol=0.0)

    def test_auto_switches_the_exposures_on_for_photos_of_different_brightness(self):
        true = torch.tensor([0.6, 1.0, 1.4, 0.8, 1.2, 1.0])
        scene, tr, te = _exposed_toy(true)
        cfg = toy_config(iterations=200, exposure="auto", exposure_check_interval=20, exposure_lr=0.01,
                         eval_every=1000)
        t = Trainer(scene, cfg, tr, te)
        t.fit()
        first = t.exposure_checks[0]
        assert first.step == 40 and first.enabled and first.spread >= EXPOSURE_SPREAD  # the first at a fifth
        assert len(t.exposure_checks) == 1  # no test once the exposures are learned
        learned = t.exposures()[0].mean(1).log()
        expected = true.log() - true.log().mean()
        assert torch.corrcoef(torch.stack([learned, expected]))[0, 1] > 0.95, (learned, expected)
        assert t.summary()["exposure_checks"][0]["enabled"] is True

    def test_resume_is_exact_when_auto_switches_on_mid_run(self):
        true = torch.tensor([0.6, 1.0, 1.4, 0.8, 1.2, 1.0])
        scene, tr, te = _exposed_toy(true)
        cfg = toy_config(exposure="auto", exposure_check_interval=5, exposure_lr=0.01)
        full = Trainer(scene, cfg, tr, te)
        full.fit()
        part = Trainer(scene, cfg, tr, te)
        part.fit(until=12)  # after the test at step 10 switched them on
        assert part.exposure is not None
        resumed = Trainer(scene, cfg, tr, te, state=decode(encode(part.state_dict())))
        resumed.fit()
        assert_same_parameters(full.model, resumed.model)
        torch.testing.assert_close(resumed.exposure, full.exposure, rtol=0, atol=1e-6)
        assert resumed.exposure_checks == full.exposure_checks

    def test_learns_the_photos_gains(self):
        true = torch.tensor([0.7, 1.0, 1.3, 0.85, 1.15, 1.0])  # the 6 training photos of the toy scene
        scene, tr, te = _exposed_toy(true)
        cfg = toy_config(iterations=200, exposure="affine", exposure_lr=0.01, eval_every=1000)
        t = Trainer(scene, cfg, tr, te)
        t.fit()
        gain, offset = t.exposures()
        learned = gain.mean(1).log()
        expected = true.log() - true.log().mean()
        assert torch.corrcoef(torch.stack([learned, expected]))[0, 1] > 0.95, (learned, expected)
        # on the Gaussians (not the black background), the photos at the model's exposure are nearer the photos
        # at one exposure than the photos as they are
        clean = toy_scene()[1]
        lit = clean > 0.2
        assert (t.photos(list(range(6))) - clean)[lit].abs().mean() < 0.5 * (tr - clean)[lit].abs().mean()
        record = t.exposure_record([f"v{i}.png" for i in range(8)])
        assert record.images == [f"v{i}.png" for i in scene.split["train"]] and record.step == 200

    def test_resume_is_exact_with_the_exposures(self):
        full = assert_resume_is_exact(toy_config(exposure="affine", exposure_lr=0.01), until=13)
        assert full.exposure is not None and float(full.exposure.detach().abs().max()) > 0

    def test_views_added_on_resume_start_at_the_others_centre(self):
        scene, tr, te = toy_scene()
        cfg = toy_config(iterations=20, exposure="affine", exposure_lr=0.05)
        t = Trainer(scene, cfg, tr, te)
        t.fit()
        state = t.state_dict()
        # the checkpoint knew training views 1, 2, 3, 5, 6, 7; view 2 is dropped and view 0 added
        train = [0, 1, 3, 5, 6, 7]
        more = type(scene)(**{**scene.__dict__, "split": {**scene.split, "train": train}})
        images = toy_scene()[1]  # any images of the right shape
        resumed = Trainer(more, cfg, torch.cat([images[:1], images[:1], images[2:]]), te, state=state)
        saved = state["exposure"]
        rows = {v: r for r, v in enumerate(state["exposure_views"].tolist())}
        for r, v in enumerate(train):
            want = saved[rows[v]] if v in rows else saved.mean(0)
            torch.testing.assert_close(resumed.exposure.detach()[r], want)


def test_the_brightness_warning_leads_with_the_caveat_on_a_short_run():
    from uncertsplat.train.session import SHORT_RUN_STEPS, exposure_warnings

    gains = [0.55, 0.7, 0.9, 1.0]
    (short,) = exposure_warnings(gains, learned=False, steps=300)
    assert short.startswith("after only 300 steps the training photos differ in brightness against the model")
    assert "if a full run says so too" in short and "exposure=affine" in short
    (full,) = exposure_warnings(gains, learned=False, steps=SHORT_RUN_STEPS)
    assert full.startswith("the training photos differ in brightness (relative gains 0.55-1.00 on 4 of them)")
    assert exposure_warnings(gains, learned=True, steps=300) == []


def test_photo_gains_leave_out_the_views_added_late():
    """A view added in a gap with --add-views is fitted poorly whatever its exposure: the exposure check reads the
    views the run started with (one added view raised the brightness warning on photos of one exposure)."""
    from types import SimpleNamespace

    import torch

    from uncertsplat.train.trainer import Trainer

    seen = []
    rgb = torch.linspace(0.1, 0.6, 48).reshape(4, 4, 3)  # (a flat render has no gain to fit)

    def render(g, cam):
        seen.append(cam)
        return SimpleNamespace(rgb=rgb[None])

    fake = SimpleNamespace(mean_sample=lambda: None, render=render, train_cams=list(range(5)),
                           photos=lambda idx: [rgb * (1.5 if idx[0] == 3 else 1.0)], train_idx=list(range(5)),
                           train_masks=None, _train_masks=lambda views: None)
    gains = Trainer.photo_gains(fake, skip=[3])
    assert seen == [0, 1, 2, 4] and all(abs(g - 1.0) < 1e-6 for g in gains)
    seen.clear()
    assert max(Trainer.photo_gains(fake)) > 1.4 and 3 in seen  # the same photo counted when not skipped


def test_a_checkpoint_newer_than_the_model_file_comes_with_its_own_exposures(tiny_run_path, tmp_path):  # noqa: F811
    """A run trained on (`train --resume --iterations N`) and stopped before it wrote its model is loaded from its
    newest checkpoint; its exposures were read from exposure.json, the earlier training's (written with the PLY),
    so evaluate fitted the newer model's noise on photos brought to the older exposures."""
    import shutil

    from uncertsplat.baselines import load_run
    from uncertsplat.io.checkpoints import load_latest, save_checkpoint
    from uncertsplat.io.ply import read_variational_ply
    from uncertsplat.schemas.scene import RunScene

    run = tmp_path / "run"
    shutil.copytree(tiny_run_path, run)
    names = RunScene.read(run / RunScene.FILE_NAME).train
    _, meta = read_variational_ply(run / "variational.ply")
    done = int(meta["step"])
    RunExposure(images=names, gain=[[1.0] * 3] * len(names), offset=[[0.0] * 3] * len(names),
                step=done).write(run / RunExposure.FILE_NAME)
    _, state = load_latest(run)
    later = torch.zeros(len(names), 2, 3)
    later[0, 0] = 0.2  # the first photo brighter than the others
    save_checkpoint(run, done + 10, {**state, "step": done + 10, "exposure": later})
    loaded = load_run(run)
    assert loaded.step == done + 10 and loaded.exposure.step == done + 10
    assert loaded.exposure.gain[0][0] > 1.1 > loaded.exposure.gain[1][0]


def test_a_pruned_checkpoint_model_takes_the_checkpoints_exposures_and_transients(tiny_run_path, tmp_path):  # noqa: F811
    """prune copied the source folder's exposure.json and transients/ beside the pruned model; of a model read from a
    checkpoint newer than the PLY they are the earlier training's (written with the PLY), not the ones the model was
    loaded and pruned with, and the pruned run's evaluation paired the two."""
    import shutil

    import numpy

    from uncertsplat.baselines import load_run
    from uncertsplat.config import PruneConfig
    from uncertsplat.data.dataset import TRANSIENTS_FOLDER
    from uncertsplat.io.checkpoints import load_latest, save_checkpoint
    from uncertsplat.io.images import read_mask, write_png
    from uncertsplat.io.ply import read_variational_ply
    from uncertsplat.schemas.scene import RunScene
    from uncertsplat.stages import prune
    from uncertsplat.train.transients import pack_mask

    run = tmp_path / "run"
    shutil.copytree(tiny_run_path, run, ignore=shutil.ignore_patterns("eval"))
    info = RunScene.read(run / RunScene.FILE_NAME)
    names = info.train
    _, meta = read_variational_ply(run / "variational.ply")
    done = int(meta["step"])
    RunExposure(images=names, gain=[[1.0] * 3] * len(names), offset=[[0.0] * 3] * len(names),
                step=done).write(run / RunExposure.FILE_NAME)
    write_png(run / TRANSIENTS_FOLDER / f"{names[1]}.png", numpy.zeros((info.height, info.width), bool))  # the earlier
    _, state = load_latest(run)
    later = torch.zeros(len(names), 2, 3)
    later[0, 0] = 0.2
    keep = torch.ones(info.height, info.width, 1, dtype=torch.bool)
    keep[: info.height // 2] = False
    save_checkpoint(run, done + 10, {**state, "step": done + 10, "exposure": later, "train_names": list(names),
                                     "transient_views": torch.tensor([0]), "transient_keep": pack_mask(keep)[None]})
    loaded = load_run(run)
    assert loaded.step == done + 10 and loaded.exposure.gain[0][0] > 1.1
    out = tmp_path / "pruned"
    prune.run(run, out, PruneConfig(keep_ratio=0.9, num_samples=2, score_views=2, score_samples=2, render_views=0),
              torch.device("cpu"))
    assert RunExposure.read(out / RunExposure.FILE_NAME).gain == loaded.exposure.gain
    masks = {p.name.removesuffix(".png"): read_mask(p) for p in (out / TRANSIENTS_FOLDER).rglob("*.png")}
    assert masks.keys() == {names[0]} and (masks[names[0]] == keep[..., 0].numpy()).all()
    again = load_run(out)
    assert again.exposure.gain == loaded.exposure.gain


def test_gain_spread_of_no_one_or_several_gains():
    """The largest over the smallest gain; 1 (no spread, nothing learned) for fewer than two gains, none at all
    included, or a gain that is not positive."""
    assert gain_spread([]) == gain_spread([1.3]) == 1.0
    assert gain_spread([0.8, 1.0, 1.2]) == pytest.approx(1.5)
    assert gain_spread([0.0, 1.2]) == gain_spread([-0.5, 1.2]) == 1.0
