"""SH bands kept only while they pay (``strategy.sh_bands``, ``TrainConfig.sh_min_gain_db``)."""

from __future__ import annotations

import math

import pytest
import torch

from tests.e2e.test_train_resume import assert_same_parameters, toy_config, toy_scene
from uncertsplat.gaussians.ops import truncate_sh
from uncertsplat.gaussians.params import GaussianModel
from uncertsplat.io.checkpoints import decode, encode
from uncertsplat.io.ply import read_variational_ply, write_variational_ply
from uncertsplat.schemas.runs import ShBandCheck
from uncertsplat.strategy.sh_bands import BandCheck, band_gain_db, band_reason, check_due
from uncertsplat.strategy.view_checks import check_views
from uncertsplat.train.optim import make_optimizer
from uncertsplat.train.trainer import Trainer
from uncertsplat.types import Cameras, GaussianSample


def _model(n: int = 5, degree: int = 3) -> GaussianModel:
    from uncertsplat.gaussians.params import init_from_points

    g = torch.Generator().manual_seed(0)
    m = init_from_points(torch.randn(n, 3, generator=g), torch.rand(n, 3, generator=g), sh_degree=degree,
                         num_entries=2, init_opacity=0.1, extent=1.0)
    with torch.no_grad():
        m.params["shN"].copy_(torch.randn(m.params["shN"].shape, generator=g))
    return m


class TestTruncate:
    @pytest.mark.parametrize(("degree", "keep"), [(3, 15), (2, 8), (1, 3), (0, 0)])
    def test_keeps_the_low_bands_and_their_moments(self, degree, keep):
        m = _model()
        opt = make_optimizer(m, {name: 1e-2 for name in m.parameters()})
        for p in m.parameters().values():
            p.grad = torch.ones_like(p)
        opt.step()
        before = m.params["shN"].detach().clone()
        moments = {k: v.clone() for k, v in opt.state[m.params["shN"]].items() if k != "step"}
        truncate_sh(m, opt, degree)
        m.check()
        assert m.sh_degree == degree and m.params["shN"].shape == (5, keep, 3)
        assert torch.equal(m.params["shN"].detach(), before[:, :keep])
        state = opt.state[m.params["shN"]]
        for k, v in moments.items():
            assert torch.equal(state[k], v[:, :keep]), k
        group = next(g for g in opt.param_groups if g["name"] == "shN")
        assert group["params"][0] is m.params["shN"]
        opt.step()  # the optimiser still steps with the narrower tensor

    def test_a_degree_at_or_above_the_model_changes_nothing(self):
        m = _model(degree=1)
        p = m.params["shN"]
        truncate_sh(m, None, 1)
        truncate_sh(m, None, 3)
        assert m.params["shN"] is p and m.sh_degree == 1

    def test_negative_degree_is_refused(self):
        with pytest.raises(ValueError, match=">= 0"):
            truncate_sh(_model(), None, -1)

    def test_truncated_model_round_trips_through_the_ply(self, tmp_path):
        m = _model()
        truncate_sh(m, None, 1)
        write_variational_ply(tmp_path / "v.ply", m, meta={"variant": "ours", "extent": 1.0, "step": 1})
        back, _ = read_variational_ply(tmp_path / "v.ply")
        assert back.sh_degree == 1
        torch.testing.assert_close(back.params["shN"], m.params["shN"].detach())


class TestSchedule:
    @pytest.mark.parametrize(("step", "expected"), [
        (0, None), (1000, None),  # degree 0 is never tested
        (2000, 1), (3000, 2), (4000, 3), (5000, None),  # band d at (d + 1) x interval, up to the max degree
        (2500, None),  # only at multiples of the interval
    ])
    def test_band_due(self, step, expected):
        assert check_due(step, 1000, 3, 0.05, set()) == expected

    def test_zero_threshold_tests_nothing_and_no_band_twice(self):
        assert check_due(2000, 1000, 3, 0.0, set()) is None
        assert check_due(2000, 1000, 3, 0.05, {1}) is None
        assert check_due(3000, 1000, 1, 0.05, set()) is None  # band 2 is beyond the model

    def test_views_spread_evenly_and_never_repeat(self):
        assert check_views(35, 8) == [0, 5, 10, 15, 19, 24, 29, 34]
        assert check_views(3, 8) == [0, 1, 2]
        assert check_views(1, 8) == [0]
        assert check_views(0, 8) == []


def _const_render(values: dict[int, float]):
    """A renderer whose image is a constant that depends only on the sample's SH degree."""

    def render_fn(sample: GaussianSample, cam: Cameras) -> torch.Tensor:
        return torch.full((1, 4, 5, 3), values[sample.sh_degree])

    return render_fn


class TestGain:
    def _sample(self, degree=2):
        m = _model(degree=degree)
        from uncertsplat.gaussians.variational import posterior_mean

        return posterior_mean(m, sh_degree=degree)

    def test_closed_form(self):
        cams = Cameras(torch.eye(4).expand(2, 4, 4).clone(), torch.eye(3).expand(2, 3, 3).clone(), 5, 4, ("a", "b"))
        images = torch.full((2, 4, 5, 3), 0.5)
        gain = band_gain_db(self._sample(), 2, cams, images, _const_render({1: 0.3, 2: 0.45}))
        assert gain == pytest.approx(10 * math.log10(0.2**2 / 0.05**2), rel=1e-5)  # float32 images
        worse = band_gain_db(self._sample(), 2, cams, images, _const_render({1: 0.45, 2: 0.3}))
        assert worse == pytest.approx(-gain, rel=1e-9), "a band that hurts has a negative gain"

    def test_no_band_content_is_exactly_zero_and_a_perfect_fit_infinite(self):
        cams = Cameras(torch.eye(4)[None], torch.eye(3)[None], 5, 4, ("a",))
        images = torch.full((1, 4, 5, 3), 0.5)
        assert band_gain_db(self._sample(), 1, cams, images, _const_render({0: 0.2, 1: 0.2})) == 0.0
        assert band_gain_db(self._sample(), 1, cams, images, _const_render({0: 0.2, 1: 0.5})) == math.inf

    def test_renders_are_clamped_to_the_image_range_before_the_error(self):
        """A band that pushes the render past 1 (or under 0) is judged by what an image shows: renders above the white
        or below the black of the photos match them (0 error; the band is a perfect fit, not a worse one)."""
        from uncertsplat.strategy.view_checks import sum_squared_error

        cams = Cameras(torch.eye(4)[None], torch.eye(3)[None], 5, 4, ("a",))
        white, black = torch.ones(1, 4, 5, 3), torch.zeros(1, 4, 5, 3)
        assert sum_squared_error(self._sample(), cams, white, _const_render({2: 1.4})) == 0.0
        assert sum_squared_error(self._sample(), cams, black, _const_render({2: -0.3})) == 0.0
        assert band_gain_db(self._sample(), 2, cams, white, _const_render({1: 0.8, 2: 1.4})) == math.inf

    def test_degree_zero_is_refused(self):
        cams = Cameras(torch.eye(4)[None], torch.eye(3)[None], 5, 4, ("a",))
        with pytest.raises(ValueError, match=">= 1"):
            band_gain_db(self._sample(), 0, cams, torch.zeros(1, 4, 5, 3), _const_render({0: 0.0}))


class TestTraining:
    """The toy scene is matte (rendered at SH degree 0); the model may use degree 1 from step 10, tested at 20."""

    def test_a_band_below_the_threshold_is_dropped_and_recorded(self):
        scene, tr, te = toy_scene()
        t = Trainer(scene, toy_config(sh_min_gain_db=50.0), tr, te)
        t.fit()
        assert t.model.sh_degree == 0 and t.model.params["shN"].shape[1] == 0 and t.sh_degree == 0
        t.model.check()
        (check,) = t.sh_bands
        assert (check.degree, check.step, check.kept, check.views) == (1, 20, False, 6)
        assert check.gain_db < 50.0 and "dropped" in band_reason(check)
        recorded = [ShBandCheck.model_validate(b) for b in t.summary()["sh_bands"]]
        assert recorded[0].degree == 1 and not recorded[0].kept
        assert all(torch.isfinite(p).all() for p in t.model.parameters().values())

    def test_zero_threshold_keeps_every_band_without_testing(self):
        scene, tr, te = toy_scene()
        t = Trainer(scene, toy_config(sh_min_gain_db=0.0), tr, te)
        t.fit()
        assert t.model.sh_degree == 1 and t.sh_degree == 1 and t.sh_bands == []

    def test_a_band_switches_on_at_its_step(self):
        """Band 1 of a ``sh_degree_interval`` of 5 is rendered from step 5 (``schedule.sh_degree_at`` of the step
        being made, not of the step before: that switched each band on one step late)."""
        scene, tr, te = toy_scene()
        t = Trainer(scene, toy_config(sh_min_gain_db=0.0, sh_degree_interval=5), tr, te)
        degrees = {}
        render = t.render

        def recording(g, cams, background=None):
            degrees.setdefault(t.step + 1, g.sh_degree)  # the step's training render comes first
            return render(g, cams, background)

        t.render = recording
        for _ in range(6):
            t.train_step()
        assert degrees == {1: 0, 2: 0, 3: 0, 4: 0, 5: 1, 6: 1}

    def test_a_band_that_pays_is_kept(self):
        scene, tr, te = toy_scene()
        t = Trainer(scene, toy_config(sh_min_gain_db=1e-12), tr, te)
        checks = []
        t.on_band = checks.append
        t.fit()
        (check,) = checks
        # whatever band 1 learned in 10 steps, the decision follows the measured gain
        assert check.kept == (check.gain_db >= 1e-12)
        assert t.model.sh_degree == (1 if check.kept else 0)

    def test_resume_after_a_drop_equals_uninterrupted(self):
        scene, tr, te = toy_scene()
        cfg = toy_config(sh_min_gain_db=50.0)
        full = Trainer(scene, cfg, tr, te)
        full.fit()
        part = Trainer(scene, cfg, tr, te)
        part.fit(until=24)  # after the drop at step 20
        assert part.model.sh_degree == 0
        resumed = Trainer(scene, cfg, tr, te, state=decode(encode(part.state_dict())))
        assert resumed.sh_bands == part.sh_bands and resumed.model.sh_degree == 0
        resumed.fit()
        assert_same_parameters(full.model, resumed.model)
        assert resumed.summary()["sh_bands"] == full.summary()["sh_bands"]

    def test_checkpoints_from_before_the_test_resume(self):
        scene, tr, te = toy_scene()
        cfg = toy_config(sh_min_gain_db=50.0)
        part = Trainer(scene, cfg, tr, te)
        part.fit(until=12)
        state = part.state_dict()
        del state["sh_bands"]
        resumed = Trainer(scene, cfg, tr, te, state=state)
        assert resumed.sh_bands == []
        resumed.fit()
        assert [b.degree for b in resumed.sh_bands] == [1]


def test_band_reason_says_what_was_decided():
    b = BandCheck(degree=2, step=3000, gain_db=0.01, kept=False, min_gain_db=0.05, views=8)
    assert band_reason(b) == ("SH band 2 on for one sh_degree_interval, tested at step 3000: +0.0100 dB on 8 training views (< 0.05 dB), dropped: the "
                              "model keeps degree 1")
    assert band_reason(b.model_copy(update={"kept": True})).endswith("(>= 0.05 dB), kept")
