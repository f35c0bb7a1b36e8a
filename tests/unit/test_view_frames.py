"""The viewer's frames (``view.frames``): the same pixels as ``render()``, std modes that refine, the prune
preview that matches ``prune``'s mask, and camera conversions that round-trip."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tests.fixtures import tiny_scene_path  # noqa: F401
from tests.run_fixtures import tiny_run_path  # noqa: F401
from uncertsplat.baselines import load_run
from uncertsplat.view.frames import (
    FrameRenderer,
    camera_pose,
    rotmat_to_wxyz,
    viewer_camera,
)


@pytest.fixture(scope="module")
def renderer(tiny_run_path, device):
    loaded = load_run(tiny_run_path, device)
    scene = loaded.load_scene()
    return FrameRenderer(loaded, scene.scene_scale, device, score_cameras=scene.cameras[scene.split["train"][:3]])


@pytest.fixture(scope="module")
def scene(renderer):
    return renderer.loaded.load_scene()


def _train_camera(scene, i=0, width=None, height=None, device="cpu"):
    c = scene.cameras[[i]]
    wxyz, pos, fov = camera_pose(c.cam_from_world[0], c.K[0], c.height)
    return viewer_camera(wxyz, pos, fov, width or c.width, height or c.height, device)


class TestCameras:
    def test_pose_round_trip(self, scene):
        c = scene.cameras[[3]]
        cam = _train_camera(scene, 3)
        torch.testing.assert_close(cam.cam_from_world, c.cam_from_world, atol=1e-5, rtol=0)
        torch.testing.assert_close(cam.K[0, 0, 0], c.K[0, 1, 1], atol=1e-3, rtol=1e-5)

    @pytest.mark.parametrize("angle", [0.0, 1e-7, math.pi / 2, math.pi - 1e-7, math.pi])
    @pytest.mark.parametrize("axis", [(1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 1)])
    def test_quaternion_of_every_rotation(self, angle, axis):
        # Shepperd's branches, including the 180-degree rotations where the trace is -1
        from uncertsplat.gaussians.ops import quat_to_rotmat

        a = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
        q = np.concatenate([[math.cos(angle / 2)], math.sin(angle / 2) * a])
        R = quat_to_rotmat(torch.tensor(q)[None])[0].numpy()
        back = quat_to_rotmat(torch.tensor(rotmat_to_wxyz(R))[None])[0].numpy()
        np.testing.assert_allclose(back, R, atol=1e-9)
        assert rotmat_to_wxyz(R)[0] >= 0


    def test_a_photo_the_run_did_not_train_on_is_no_training_camera(self):
        """A run on scene.train_names leaves the scene's other photos untrained: they are drawn grey and named "not
        trained on" (they were blue training cameras with their photos, hiding the gap a user looks for)."""
        from types import SimpleNamespace

        from uncertsplat.view.server import _ROLE_COLOURS, _ROLE_WORDS, Viewer

        fake = SimpleNamespace(scene=SimpleNamespace(split={"train": (1, 2), "test": (0,), "calibration": (3,)}))
        roles = [Viewer._role(fake, i) for i in range(5)]
        assert roles == ["test", "train", "train", "calibration", "unused"]
        assert _ROLE_WORDS["unused"] == "not trained on" and len(set(_ROLE_COLOURS.values())) == 4


class TestFrames:
    def test_rgb_is_the_render_of_the_expected_sample(self, renderer, scene, device):
        from uncertsplat.render import near_plane, render

        cam = _train_camera(scene, 2, device=device)
        frame = renderer.frame(cam, "rgb")
        cfg = renderer.loaded.config
        ref = render(renderer.sampler.det_sample, cam, background=torch.tensor(cfg.scene.background, device=device),
                     tile_size=cfg.tile_size, near=near_plane(scene.scene_scale)).rgb[0]
        expected = (ref.clamp(0, 1) * 255 + 0.5).to(torch.uint8).cpu().numpy()
        assert frame.image.shape == (cam.height, cam.width, 3) and frame.image.dtype == np.uint8
        np.testing.assert_array_equal(frame.image, expected)

    def test_rgb_at_a_viewer_size(self, renderer, scene, device):
        # the browser's aspect is not the photo's: any size renders, with the same focal length per height
        cam = _train_camera(scene, 0, 200, 50, device)
        assert renderer.frame(cam, "rgb").image.shape == (50, 200, 3)

    def test_depth_is_black_where_there_is_no_surface(self, renderer, scene, device):
        cam = _train_camera(scene, 1, device=device)
        frame = renderer.frame(cam, "depth")
        lo, hi = frame.value_range
        assert 0 < lo < hi
        alpha = renderer.render_mean(cam).alpha[0, ..., 0].cpu().numpy()
        empty = alpha < 0.05
        assert np.isnan(frame.values[empty]).all() and np.isfinite(frame.values[~empty]).all()
        assert (frame.image[empty] == 0).all()

    def test_depth_modes_show_the_scenes_units_they_name(self, renderer, scene, device):
        """With the scene's factor the depth and depth-std values are the run's times it, and named scene units (they
        were the run's normalised units under that name: 4x too small on the tiny scene); without it they say they
        are the run's units. The depth buffer stays in the run's units (the 3D scene's)."""
        scaled = FrameRenderer(renderer.loaded, scene.scene_scale, device, depth_to_source=scene.depth_to_source)
        assert scene.depth_to_source == pytest.approx(1.0 / float(torch.linalg.det(scene.world_from_source[:3, :3]))
                                                      ** (1.0 / 3.0), rel=1e-6) and scene.depth_to_source != 1.0
        cam = _train_camera(scene, 1, device=device)
        run_units, own = renderer.frame(cam, "depth"), scaled.frame(cam, "depth")
        np.testing.assert_allclose(own.values, run_units.values * scene.depth_to_source, rtol=1e-6)
        np.testing.assert_array_equal(own.depth, run_units.depth)
        assert own.unit == "depth (scene units)" and run_units.unit == "depth (the run's normalised units)"
        std_run, std_own = renderer.frame(cam, "depth_std", num_samples=4), scaled.frame(cam, "depth_std", num_samples=4)
        np.testing.assert_allclose(std_own.values, std_run.values * scene.depth_to_source, rtol=1e-5, atol=1e-7)
        assert std_own.unit == "depth std (scene units)"

    @pytest.mark.parametrize("mode", ["rgb_std", "depth_std"])
    def test_std_refined_in_steps_equals_drawn_at_once(self, renderer, scene, mode, device):
        cam = _train_camera(scene, 4, device=device)
        once = renderer.frame(cam, mode, num_samples=8)
        acc = renderer.std_accumulator(cam)
        acc.add(4)
        first = acc.frame(mode)
        acc.add(4)
        steps = acc.frame(mode)
        assert once.samples == steps.samples == 8 and first.samples == 4
        np.testing.assert_allclose(steps.values, once.values, rtol=1e-5, atol=1e-7)
        assert not np.allclose(first.values, steps.values)  # more samples: a different estimate
        assert np.nanmax(steps.values) > 0

    def test_a_std_frame_says_what_its_samples_are(self, renderer, scene, device):
        """A deterministic run's std modes said "K = 16 posterior samples" of 16 equal renders, an ensemble's the
        same of draws among two members (a helper)."""
        from types import SimpleNamespace

        cam = _train_camera(scene, 0, device=device)
        assert renderer.frame(cam, "rgb_std", num_samples=4).note == "K = 4 posterior samples"
        real = renderer.loaded
        try:
            renderer.loaded = SimpleNamespace(config=real.config.model_copy(update={"method": "deterministic"}),
                                              model=real.model)
            assert renderer.samples_label(16).startswith("16 equal renders: the model has no posterior")
            renderer.loaded = SimpleNamespace(config=real.config.model_copy(update={"method": "ensemble",
                                                                                    "ensemble_size": 2}),
                                              model=real.model)
            assert renderer.samples_label(16) == "K = 16 draws among its 2 members"
        finally:
            renderer.loaded = real

    def test_std_mode_differs_from_rgb(self, renderer, scene, device):
        cam = _train_camera(scene, 0, device=device)
        assert np.abs(renderer.frame(cam, "rgb_std").image.astype(int) -
                      renderer.frame(cam, "rgb").image.astype(int)).mean() > 5

    def test_fixed_colour_range(self, renderer, scene, device):
        cam = _train_camera(scene, 0, device=device)
        from uncertsplat.report.colormaps import colorize

        f = renderer.frame(cam, "rgb_std", value_range=(0.0, 1e-9))
        assert f.value_range == (0.0, 1e-9)
        # coloured over that range: every std above 1e-9 takes the colour map's top colour
        np.testing.assert_array_equal(f.image, colorize(f.values, "fixed", 0.0, 1e-9))
        top = colorize(np.ones((1, 1)), "fixed", 0.0, 1.0)[0, 0]
        assert (f.image[f.values > 1e-9] == top).all() and (f.values > 1e-9).mean() > 0.5
        wide = renderer.frame(cam, "rgb_std", value_range=(0.0, 1.0))
        np.testing.assert_array_equal(wide.image, colorize(wide.values, "fixed", 0.0, 1.0))

    def test_unknown_mode(self, renderer, scene):
        with pytest.raises(ValueError, match="unknown view mode"):
            renderer.frame(_train_camera(scene), "normals")


class TestPrunePreview:
    def test_mask_is_prunes_mask(self, renderer):
        from uncertsplat.prune.policy import choose_mask
        from uncertsplat.uncertainty.scores import carrier_mask

        keep = renderer.keep_mask("gate", 0.8)
        ref, _ = choose_mask(renderer.scores("gate"), carrier_mask(renderer.loaded.model), threshold=None,
                             keep_ratio=0.8)
        assert torch.equal(keep, ref)
        assert int((~keep).sum()) > 0

    def test_removed_gaussians_are_coloured_and_hidden(self, renderer, scene, device):
        cam = _train_camera(scene, 0, device=device)
        keep_all = renderer.frame(cam, "prune", keep_ratio=1.0)
        painted = renderer.frame(cam, "prune", keep_ratio=0.5)
        assert "removes 0 of" in keep_all.note
        # kept Gaussians are grey: with nothing removed every pixel is (nearly) grey; removals add colour
        def saturation(img):
            return (img.max(-1).astype(int) - img.min(-1).astype(int)).mean()
        assert saturation(keep_all.image) < 3 < saturation(painted.image)
        lo, hi = painted.value_range
        assert lo <= hi
        hidden = renderer.frame(cam, "prune", keep_ratio=0.5, hide_removed=True)
        assert np.abs(hidden.image.astype(int) - renderer.frame(cam, "rgb").image.astype(int)).mean() > 0.1

    def test_predictive_score_preview(self, renderer, scene, device):
        # the predictive score renders the training cameras (with a backward pass) even from a no-grad frame
        f = renderer.frame(_train_camera(scene, 0, device=device), "prune", score="predictive", keep_ratio=0.9)
        assert "--score predictive" in f.note and renderer.scores("predictive").shape == (len(renderer.loaded.model),)

    def test_predictive_score_needs_cameras(self, tiny_run_path, device):
        loaded = load_run(tiny_run_path, device)
        r = FrameRenderer(loaded, loaded.load_scene().scene_scale, device)
        assert "predictive" not in r.score_names()
        with pytest.raises(ValueError, match="unavailable"):
            r.scores("predictive")

    def test_deterministic_run_has_no_prune_mode(self, tiny_run_path, device):
        # a deterministic run offers the render and std modes only; its std is the empty-ray term alone: the
        # part of the ray covered less than the model covers its training views
        loaded = load_run(tiny_run_path, device)
        loaded.config = loaded.config.model_copy(update={"method": "deterministic"})
        r = FrameRenderer(loaded, loaded.load_scene().scene_scale, device)
        assert "prune" not in r.modes() and not r.prune_available and not r.has_posterior
        scene = loaded.load_scene()
        cam = _train_camera(scene, 0, device=device)
        f = r.frame(cam, "rgb_std", num_samples=2)
        every_sample = r.sampler.sample_fn(torch.Generator(device=device))  # the model's mean, whatever the seed
        alpha = r.sampler.render_fn(every_sample, cam).alpha[0, ..., 0].detach().cpu().numpy()
        c = r.sampler.coverage
        assert 0.0 < c <= 1.0
        np.testing.assert_allclose(f.values, np.clip(1 - alpha / c, 0, None) / math.sqrt(12.0), atol=1e-6)


class TestUnseenMode:
    """``unseen``: the colour posterior blended for the view plus the empty-ray term, fitted once."""

    @staticmethod
    def _renderer(tiny_run_path, device, calls):
        from functools import partial

        from uncertsplat.config import EvalConfig
        from uncertsplat.data.dataset import load_view_set
        from uncertsplat.eval.engine import fit_residual

        loaded = load_run(tiny_run_path, device)
        scene = loaded.load_scene()

        def field():
            calls.append(1)
            return fit_residual(loaded.sampler(scene.scene_scale, device), scene.split["train"],
                                EvalConfig(resolution=0.0), device, load_views=partial(load_view_set, scene, depth=False))

        return FrameRenderer(loaded, scene.scene_scale, device, unseen_field=field), scene

    def test_values_are_the_blended_colour_posterior_and_the_empty_term(self, tiny_run_path, device):
        calls: list[int] = []
        r, scene = self._renderer(tiny_run_path, device, calls)
        assert "unseen" in r.modes() and not calls  # nothing is fitted before the mode is shown
        cam = _train_camera(scene, 1, device=device)
        f = r.frame(cam, "unseen")
        field = r._unseen
        with torch.no_grad():
            colour = field.colour_blended(cam, r.sampler.render_fn)[0, ..., 0]
            alpha = r.render_mean(cam).alpha[0, ..., 0]
        gap = (1 - alpha / r.sampler.coverage).clamp_min(0)
        expect = (colour + gap.square() * r.sampler.empty_std[0] ** 2).sqrt().cpu().numpy()
        np.testing.assert_allclose(f.values, expect, rtol=1e-5, atol=1e-7)
        assert np.isfinite(f.values).all() and f.values.min() >= 0
        r.frame(_train_camera(scene, 2, device=device), "unseen")
        assert len(calls) == 1, "the colour posterior is fitted once"

    def test_a_seen_view_is_known_far_better_than_the_prior(self, tiny_run_path, device):
        r, scene = self._renderer(tiny_run_path, device, [])
        f = r.frame(_train_camera(scene, 0, device=device), "unseen")
        prior_std = float(r._unseen.colour_prior[0]) ** 0.5 * 0.28209479177387814
        covered = r.render_mean(_train_camera(scene, 0, device=device)).alpha[0, ..., 0].cpu().numpy() >= \
            r.sampler.coverage
        assert covered.any()
        assert float(np.median(f.values[covered])) < 0.25 * prior_std

    def test_without_photos_there_is_no_unseen_mode(self, renderer, scene):
        assert "unseen" not in renderer.modes()
        with pytest.raises(ValueError, match="no training photos"):
            renderer.frame(_train_camera(scene), "unseen")
