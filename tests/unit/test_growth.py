"""Growth that stops when the model's last doubling no longer pays (``strategy.growth``,
``DensifyConfig.growth_min_gain_db``)."""

from __future__ import annotations

import math

import pytest
import torch

from tests.e2e.test_train_resume import assert_same_parameters, toy_config, toy_scene
from tests.fixtures import tiny_scene_path  # noqa: F401
from tests.run_fixtures import resume_without_key, tiny_run_path  # noqa: F401
from uncertsplat.config import DensifyConfig
from uncertsplat.io.checkpoints import decode, encode
from uncertsplat.schemas.runs import GrowthCheck
from uncertsplat.strategy.growth import (
    AT_BUDGET,
    RESERVE_MIN_TRAINING,
    at_budget,
    growth_check_due,
    growth_reason,
    halving_cost_db,
    reserved_views,
    weakest_half,
)
from uncertsplat.train.trainer import Trainer
from uncertsplat.types import Cameras, GaussianSample


class TestSchedule:
    CFG = DensifyConfig(start=100, until=4000, opacity_reset_interval=3000, growth_check_interval=250)

    @pytest.mark.parametrize(("step", "due"), [
        (0, False), (100, False), (250, True), (300, False), (2750, True),
        (3000, True),  # tested before that step's opacity reset
        (3250, False), (3750, False),  # recovering from the reset
        (4000, False), (4250, False),  # densification is over
    ])
    def test_due_inside_the_window_and_not_after_a_reset(self, step, due):
        assert growth_check_due(step, self.CFG) is due

    def test_zero_threshold_tests_nothing(self):
        assert not growth_check_due(250, self.CFG.model_copy(update={"growth_min_gain_db": 0.0}))

    def test_only_resets_that_happen_pause_the_tests(self):
        """A reset interval under the recovery window, or a run too short for any reset (none in a run's last 1000
        steps), switched every growth test off: the test assumed a reset at every multiple of the interval."""
        often = DensifyConfig(start=0, until=4000, opacity_reset_interval=30, growth_check_interval=25)
        assert not growth_check_due(75, often, iterations=5000)  # the resets at 30 and 60 happened
        assert growth_check_due(75, often, iterations=150)  # a run of 150 steps has no reset at all
        assert growth_check_due(25, often, iterations=5000)  # before the first
        late = self.CFG.model_copy(update={"opacity_reset_interval": 1500})  # no reset in a run's last 1000 steps:
        assert growth_check_due(1750, late, iterations=2400)  # none at 1500 in a run of 2400 steps
        assert not growth_check_due(1750, late, iterations=5000)  # in one of 5000, 250 steps after it

    def test_without_resets_every_interval_is_due(self):
        cfg = self.CFG.model_copy(update={"opacity_reset_interval": 0})
        assert growth_check_due(3250, cfg) and growth_check_due(3750, cfg)


class TestAtBudget:
    @pytest.mark.parametrize(("n", "budget", "at"), [
        (40_000, 40_000, True), (39_991, 40_000, True), (39_600, 40_000, True), (39_599, 40_000, False),
        (0, 1, False), (1, 1, True), (41_000, 40_000, True)])
    def test_within_one_percent_is_at_the_budget(self, n, budget, at):
        assert AT_BUDGET == 0.99 and at_budget(n, budget) is at


class TestWeakestHalf:
    def test_smallest_seen_weights_with_ties_by_row(self):
        w = torch.tensor([0.0, 3.0, 1.0, 2.0, 1.0, 0.0])
        assert weakest_half(w).tolist() == [False, False, True, False, True, False]

    def test_rounds_down_and_never_picks_the_unseen(self):
        w = torch.tensor([5.0, 0.0, 4.0, 3.0, 0.0, 2.0, 1.0])  # 5 seen -> 2 off
        assert weakest_half(w).tolist() == [False, False, False, False, False, True, True]
        assert not weakest_half(torch.zeros(4)).any()
        assert not weakest_half(torch.tensor([1.0])).any()


def _sum_render(scale: float):
    """A renderer whose image is a constant: ``scale`` x the sum of the sample's opacities."""

    def render_fn(sample: GaussianSample, cam: Cameras) -> torch.Tensor:
        return torch.full((1, 4, 5, 3), scale * float(sample.opacities.sum()))

    return render_fn


def _sample(n: int) -> GaussianSample:
    return GaussianSample(torch.zeros(n, 3), torch.tensor([[1.0, 0, 0, 0]]).expand(n, 4), torch.ones(n, 3),
                          torch.ones(n), torch.zeros(n, 1, 3))


class TestCost:
    CAMS = Cameras(torch.eye(4).expand(2, 4, 4).clone(), torch.eye(3).expand(2, 3, 3).clone(), 5, 4, ("a", "b"))

    def test_closed_form(self):
        images = torch.full((2, 4, 5, 3), 0.5)
        off = torch.tensor([True, False, True, False])
        cost, quality = halving_cost_db(_sample(4), off, self.CAMS, images, _sum_render(0.1))  # 0.4 all, 0.2 without
        assert cost == pytest.approx(10 * math.log10(0.3**2 / 0.1**2), rel=1e-5)
        assert quality == pytest.approx(10 * math.log10(1 / 0.1**2), rel=1e-5)

    def test_nothing_switched_off_costs_exactly_zero_and_a_perfect_fit_is_infinite(self):
        images = torch.full((2, 4, 5, 3), 0.4)
        none = torch.zeros(4, dtype=torch.bool)
        assert halving_cost_db(_sample(4), none, self.CAMS, images, _sum_render(0.1))[0] == 0.0
        assert halving_cost_db(_sample(4), ~none, self.CAMS, images, _sum_render(0.1)) == (math.inf, math.inf)


class TestTraining:
    """The toy schedule densifies at steps 10 and 20 (``toy_config``); a test every 10 steps runs at 10 and 20."""

    @staticmethod
    def _cfg(gain: float, **densify):
        cfg = toy_config()
        return cfg.model_copy(update={"densify": cfg.densify.model_copy(update={
            "growth_min_gain_db": gain, "growth_check_interval": 10, "growth_patience": 1, "grad_threshold": 1e-5,
            **densify})})

    def test_a_cheap_half_stops_growth_and_is_recorded(self):
        scene, tr, te = toy_scene()
        grown = Trainer(scene, self._cfg(0.0), tr, te)
        grown.fit()
        stopped = Trainer(scene, self._cfg(50.0), tr, te)
        sizes = []
        stopped.on_step = lambda t: sizes.append(len(t.model))
        stopped.fit()
        (check,) = stopped.growth  # no test after the stop
        assert (check.step, check.stopped, check.views) == (10, True, 6)
        assert 0 < check.seen <= check.gaussians and check.cost_db < 50.0
        assert all(b <= a for a, b in zip(sizes[9:-1], sizes[10:], strict=True)), "after the stop it only shrinks"
        assert sizes[9] < len(grown.model) - 10, "the same schedule without the test grows"
        assert grown.growth == []
        recorded = [GrowthCheck.model_validate(g) for g in stopped.summary()["growth"]]
        assert recorded == [check] and "stops growing" in growth_reason(check)

    def test_patience_waits_for_that_many_cheap_tests_in_a_row(self):
        scene, tr, te = toy_scene()
        t = Trainer(scene, self._cfg(50.0, growth_patience=2), tr, te)
        t.fit()
        assert [(g.step, g.stopped) for g in t.growth] == [(10, False), (20, True)]
        t3 = Trainer(scene, self._cfg(50.0, growth_patience=3), tr, te)
        t3.fit()
        assert not any(g.stopped for g in t3.growth) and t3.densifier.grow, "two tests cannot make three in a row"

    def test_a_half_that_pays_lets_growth_go_on(self):
        scene, tr, te = toy_scene()
        t = Trainer(scene, self._cfg(1e-9), tr, te)
        t.fit()
        assert [g.step for g in t.growth] == [10, 20]
        assert all(not g.stopped and g.cost_db >= 1e-9 for g in t.growth)

    def test_no_test_while_the_model_is_at_its_budget(self):
        scene, tr, te = toy_scene()
        free = Trainer(scene, self._cfg(1e-9), tr, te)
        sizes = {}
        free.on_step = lambda t: sizes.setdefault(t.step, len(t.model))
        free.fit()
        # a budget the model has reached at step 10 (the first test): from there on no test runs
        cap = sizes[9]
        capped = Trainer(scene, self._cfg(1e-9, max_gaussians=cap), tr, te)
        capped.fit()
        assert at_budget(cap, capped.budget.max_gaussians)
        assert capped.growth == [] and capped.densifier.grow
        # a budget with room at every test: every test runs
        roomy = Trainer(scene, self._cfg(1e-9, max_gaussians=10 * max(sizes.values())), tr, te)
        roomy.fit()
        assert [g.step for g in roomy.growth] == [10, 20]

    def test_resume_after_a_stop_equals_uninterrupted(self):
        scene, tr, te = toy_scene()
        cfg = self._cfg(50.0)
        full = Trainer(scene, cfg, tr, te)
        full.fit()
        part = Trainer(scene, cfg, tr, te)
        part.fit(until=15)
        resumed = Trainer(scene, cfg, tr, te, state=decode(encode(part.state_dict())))
        assert resumed.growth == part.growth and not resumed.densifier.grow
        resumed.fit()
        assert_same_parameters(full.model, resumed.model)
        assert resumed.summary()["growth"] == full.summary()["growth"]

    def test_checkpoints_from_before_the_test_resume_growing(self):
        scene, tr, te = toy_scene()
        part = Trainer(scene, self._cfg(50.0), tr, te)
        part.fit(until=8)
        state = part.state_dict()
        del state["growth"]
        resumed = Trainer(scene, self._cfg(50.0), tr, te, state=state)
        assert resumed.growth == [] and resumed.densifier.grow


def test_a_run_from_before_the_test_resumes_without_it(tiny_scene_path, tiny_run_path, tmp_path):  # noqa: F811
    """config.json files written before ``densify.growth_min_gain_db`` existed grew up to their budget; a resumed
    one keeps doing so."""
    cfg = resume_without_key(tiny_scene_path, tiny_run_path, tmp_path, "densify", "growth_min_gain_db", 10)
    assert cfg["densify"]["growth_min_gain_db"] == 0.0


def test_growth_reason_says_what_was_decided():
    g = GrowthCheck(step=500, gaussians=32156, seen=31273, cost_db=0.077, min_gain_db=0.25, stopped=True, views=8)
    assert growth_reason(g) == ("growth test at step 500: switching off the weakest half of the 31,273 Gaussians 8 "
                                "training views see (of 32,156) costs 0.077 dB (< 0.25 dB), densification stops "
                                "growing the model")
    waiting = growth_reason(g.model_copy(update={"stopped": False}))
    assert "(< 0.25 dB), growth goes on until" in waiting
    assert growth_reason(g.model_copy(update={"stopped": False, "cost_db": 2.0})).endswith(
        "costs 2.000 dB (>= 0.25 dB), growth goes on")
    assert "2 training views set aside see" in growth_reason(g.model_copy(update={"views": 2, "reserved": True}))


class TestReservedViews:
    @pytest.mark.parametrize(("n", "reserve", "views"), [
        (17, 2, [4, 12]), (10, 2, [2, 7]), (42, 3, [7, 21, 35]), (11, 1, [5]), (40, 40, []), (9, 2, []),
        (17, 0, []), (RESERVE_MIN_TRAINING, 1, []), (RESERVE_MIN_TRAINING + 1, 1, [4])])
    def test_spread_and_only_with_enough_views_left(self, n, reserve, views):
        assert reserved_views(n, reserve) == views

    @pytest.mark.parametrize("n", range(RESERVE_MIN_TRAINING + 1, 60))
    def test_every_count_asked_for_distinct_and_in_range(self, n):
        for reserve in range(1, n - RESERVE_MIN_TRAINING + 1):
            got = reserved_views(n, reserve)
            assert len(got) == reserve and got == sorted(set(got)) and 0 <= got[0] and got[-1] < n


class TestReserveInTraining:
    """14 ring views of which every 4th is held out: 10 training views, 2 of them set aside."""

    @staticmethod
    def _run(gain: float, until: int | None = None, state=None, **densify):
        scene, tr, te = toy_scene(n_views=14)
        t = Trainer(scene, TestTraining._cfg(gain, growth_reserve_views=2, **densify), tr, te, state=state)
        drawn = []
        draw = t._next_view
        t._next_view = lambda: drawn.append((t.step + 1, draw())) or drawn[-1][1]
        t.fit(until=until)
        return t, drawn

    def test_set_aside_views_are_not_trained_until_growth_stops_and_the_test_renders_only_them(self):
        t, drawn = self._run(50.0)
        assert t.reserve == [2, 7]
        (check,) = t.growth
        assert (check.step, check.stopped, check.views, check.reserved) == (10, True, 2, True)
        assert t.reserve_closed == {"step": 10, "reason": "growth stopped"} and not t.reserve_open
        assert not {v for s, v in drawn if s <= 10} & {2, 7}, "set aside until the test decided"
        assert {v for s, v in drawn if s > 10} >= {2, 7}, "and trained after"
        assert t.summary()["growth_reserve"] == {"views": ["v3.png", "v10.png"], "joined_training": t.reserve_closed}

    def test_the_budget_or_the_end_of_densification_also_ends_the_reserve(self):
        capped, _ = self._run(1e-9)  # toy_config's budget of 400 is reached by step 20
        assert capped.reserve_closed["reason"].startswith("the model reached its budget")
        assert [g.reserved for g in capped.growth] == [True] * len(capped.growth)
        roomy, drawn = self._run(1e-9, max_gaussians=100_000)
        assert [(g.step, g.reserved) for g in roomy.growth] == [(10, True), (20, True)]
        # densification's last step is 20 (until 25, interval 10): the views join at step 24
        assert roomy.reserve_closed == {"step": 24, "reason": "densification ended"}
        assert not {v for s, v in drawn if s <= 24} & {2, 7}

    def test_no_reserve_without_the_test_or_with_too_few_views(self):
        scene, tr, te = toy_scene(n_views=14)
        off = Trainer(scene, TestTraining._cfg(0.0, growth_reserve_views=2), tr, te)
        assert off.reserve == [] and not off.reserve_open and "growth_reserve" not in off.summary()
        scene, tr, te = toy_scene()  # 6 training views
        few = Trainer(scene, TestTraining._cfg(1e-9, growth_reserve_views=2), tr, te)
        few.fit()
        plain = Trainer(scene, TestTraining._cfg(1e-9), tr, te)
        plain.fit()
        assert few.reserve == [] and few.growth == plain.growth
        assert_same_parameters(plain.model, few.model, atol=0)

    def test_resume_while_views_are_set_aside_equals_uninterrupted(self):
        full, _ = self._run(1e-9, max_gaussians=100_000)
        part, _ = self._run(1e-9, until=15, max_gaussians=100_000)
        assert part.reserve_open
        resumed, drawn = self._run(1e-9, state=decode(encode(part.state_dict())), max_gaussians=100_000)
        assert not {v for s, v in drawn if s <= 24} & {2, 7}
        assert_same_parameters(full.model, resumed.model)
        assert resumed.summary()["growth"] == full.summary()["growth"]
        assert resumed.reserve_closed == full.reserve_closed

    def test_a_checkpoint_from_before_the_option_trains_on_every_view(self):
        part, _ = self._run(1e-9, until=8, max_gaussians=100_000)
        state = part.state_dict()
        for key in ("reserve", "reserve_open", "reserve_closed"):
            del state[key]
        resumed, drawn = self._run(1e-9, state=state, max_gaussians=100_000)
        assert not resumed.reserve_open and resumed.reserve_closed is None
        assert [g.reserved for g in resumed.growth] == [False, False]
        assert {v for s, v in drawn if s <= 24} >= {2, 7}

    def test_the_posterior_and_the_exposure_test_leave_the_set_aside_views_out(self):
        t, _ = self._run(1e-9, until=5, max_gaussians=100_000)
        asked = []
        photos = t.photos
        t.photos = lambda views=None: asked.append(views) or photos(views)
        t.update_posterior()
        assert asked and all(v is not None and not set(v) & {2, 7} for v in asked)
        asked.clear()
        t.photo_gains(skip=t.reserve)
        assert asked and not {i for v in asked for i in v} & {2, 7}
