"""The low-resolution phase of training (``TrainConfig.low_res_fraction``): which steps render at which size, the
images it trains on, resume inside the phase, and the settings it refuses."""

from __future__ import annotations

import pydantic
import pytest
import torch

from tests.e2e.test_train_resume import assert_resume_is_exact, toy_config, toy_scene
from uncertsplat.config import TrainConfig
from uncertsplat.train.trainer import Trainer


def _recording(trainer: Trainer) -> list[tuple[int, int]]:
    """Wrap ``trainer.render``; returns the list the (width, height) of every training render goes to."""
    sizes: list[tuple[int, int]] = []
    render = trainer.render

    def wrapped(g, cams):
        sizes.append((cams.width, cams.height))
        return render(g, cams)

    trainer.render = wrapped
    return sizes


class TestLowResolutionPhase:
    def test_the_first_fraction_of_the_steps_renders_at_the_low_scale(self):
        scene, tr, te = toy_scene(width=48, height=36)
        # no densification, SH band test or posterior update in between: every render below is a training step's
        t = Trainer(scene, toy_config(iterations=10, low_res_fraction=0.4, densify={"start": 1000},
                                      sh_degree_interval=1000, method="deterministic"), tr, te)
        sizes = _recording(t)
        for _ in range(10):
            t.train_step()
        assert sizes == [(24, 18)] * 4 + [(48, 36)] * 6
        assert t.low_images.shape == (tr.shape[0], 18, 24, 3)

    def test_low_images_are_the_area_averages(self):
        scene, tr, te = toy_scene(width=48, height=36)
        t = Trainer(scene, toy_config(low_res_fraction=0.5), tr, te)
        block = tr.reshape(tr.shape[0], 18, 2, 24, 2, 3).mean((2, 4))
        torch.testing.assert_close(t.low_images, block)
        # the cameras scale with them: the same world point lands on half its pixel coordinates
        torch.testing.assert_close(t.low_cams.K[:, :2], t.train_cams.K[:, :2] * 0.5)

    def test_off_by_default_and_at_scale_one(self):
        scene, tr, te = toy_scene(width=48, height=36)
        assert TrainConfig().low_res_fraction == 0.0
        for cfg in (toy_config(iterations=4), toy_config(iterations=4, low_res_fraction=0.5, low_res_scale=1.0)):
            t = Trainer(scene, cfg, tr, te)
            sizes = _recording(t)
            for _ in range(4):
                t.train_step()
            assert t.low_images is None and set(sizes) == {(48, 36)}

    def test_resume_inside_the_phase_equals_uninterrupted(self):
        # 30 steps: low resolution up to step 15, densification in it
        assert_resume_is_exact(toy_config(low_res_fraction=0.5), until=7)

    @pytest.mark.parametrize("bad", [{"low_res_fraction": 1.0}, {"low_res_fraction": -0.1}, {"low_res_scale": 0.0},
                                     {"low_res_scale": 1.5}])
    def test_settings_out_of_range_are_refused(self, bad):
        with pytest.raises(pydantic.ValidationError):
            TrainConfig(**bad)
