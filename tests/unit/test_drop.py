"""Leaving Gaussians out of training renders (``TrainConfig.drop_rate``): the rate's ramp, the opacity
compensation, what is left untouched when it is off, and exact resume."""

from __future__ import annotations

import pydantic
import pytest
import torch

from tests.e2e.test_train_resume import assert_resume_is_exact, toy_config, toy_scene
from tests.fixtures import tiny_scene_path
from uncertsplat.config import TrainConfig
from uncertsplat.train.trainer import Trainer
from uncertsplat.types import GaussianSample


def _sample(n: int, opacity: float) -> GaussianSample:
    return GaussianSample(means=torch.zeros(n, 3), quats=torch.tensor([[1.0, 0, 0, 0]]).expand(n, 4),
                          scales=torch.full((n, 3), 0.1), opacities=torch.full((n,), opacity),
                          sh=torch.zeros(n, 1, 3))


class TestDrop:
    def _trainer(self, **extra) -> Trainer:
        scene, tr, te = toy_scene()
        return Trainer(scene, toy_config(**extra), tr, te)

    def test_rate_ramps_with_the_step_and_keeps_the_expected_opacity(self):
        t = self._trainer(iterations=100, drop_rate=0.4)
        g = _sample(200_000, 0.3)
        at_start = t._drop(g, 0)
        torch.testing.assert_close(at_start.opacities, g.opacities)  # the rate is 0 at step 0
        for step, rate in ((50, 0.2), (100, 0.4)):
            d = t._drop(g, step).opacities
            dropped = (d == 0).double().mean().item()
            assert abs(dropped - rate) < 0.005
            kept = d[d > 0]
            torch.testing.assert_close(kept, torch.full_like(kept, 0.3 / (1 - rate)))
            # a pixel covered by one of these Gaussians keeps its expected alpha
            assert abs(d.double().mean().item() - 0.3) < 0.003
        # compensation never reaches alpha 1
        assert t._drop(_sample(1000, 0.9), 100).opacities.max() < 1.0
        # the other fields are the sample's own
        d = t._drop(g, 100)
        assert d.means is g.means and d.scales is g.scales and d.sh is g.sh

    def test_off_by_default_renders_what_the_sample_is(self):
        assert TrainConfig().drop_rate == 0.0
        t = self._trainer(iterations=6)
        seen: list[torch.Tensor] = []
        render = t.render

        def wrapped(g, cams):
            seen.append(g.opacities.detach().clone())
            return render(g, cams)

        t.render = wrapped
        t.train_step()
        assert seen and bool((seen[0] > 0).all())

    def test_drop_changes_training_and_resume_is_exact(self):
        full = assert_resume_is_exact(toy_config(drop_rate=0.3), until=13)
        scene, tr, te = toy_scene()
        plain = Trainer(scene, toy_config(), tr, te)
        plain.fit()
        assert not torch.equal(full.model.params["means"], plain.model.params["means"])

    @pytest.mark.parametrize("bad", [-0.1, 1.0])
    def test_rates_out_of_range_are_refused(self, bad):
        with pytest.raises(pydantic.ValidationError):
            TrainConfig(drop_rate=bad)
