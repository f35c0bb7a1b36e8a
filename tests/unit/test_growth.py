"""Growth that stops when the model's last doubling no longer pays (``strategy.growth``,
``DensifyConfig.growth_min_gain_db``)."""

from __future__ import annotations

import math

import pytest
import torch

from tests.e2e.test_train_resume import assert_same_parameters, toy_config, toy_scene
from tests.fixtures import tiny_scene_path  # noqa: F401
from tests.run_fixtures import resume_without_key, tiny_run_path  # noqa: F401
from uncertsplat.config import GROWTH_MIN_GAIN_DB, GROWTH_MIN_GAIN_REFIT_DB, DensifyConfig
from uncertsplat.io.checkpoints import decode, encode
from uncertsplat.schemas.runs import GrowthCheck
from uncertsplat.strategy.growth import (
    AT_BUDGET,
    at_budget,
    growth_check_due,
    growth_reason,
    halving_cost_db,
    skipped,
    skips_next,
    weakest_half,
)
from uncertsplat.train.trainer import GrowthCopy, Trainer
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
        cost = halving_cost_db(_sample(4), off, self.CAMS, images, _sum_render(0.1))  # 0.4 with all, 0.2 without
        assert cost == pytest.approx(10 * math.log10(0.3**2 / 0.1**2), rel=1e-5)

    def test_nothing_switched_off_costs_exactly_zero_and_a_perfect_fit_is_infinite(self):
        images = torch.full((2, 4, 5, 3), 0.4)
        none = torch.zeros(4, dtype=torch.bool)
        assert halving_cost_db(_sample(4), none, self.CAMS, images, _sum_render(0.1)) == 0.0
        assert halving_cost_db(_sample(4), ~none, self.CAMS, images, _sum_render(0.1)) == math.inf


class TestTraining:
    """The toy schedule densifies at steps 10 and 20 (``toy_config``); a test every 10 steps runs at 10 and 20."""

    @staticmethod
    def _cfg(gain: float, **densify):
        cfg = toy_config()
        return cfg.model_copy(update={"densify": cfg.densify.model_copy(update={
            "growth_min_gain_db": gain, "growth_check_interval": 10, "growth_patience": 1, "grad_threshold": 1e-5,
            "growth_refit_steps": 3, "growth_skip_factor": None, **densify})})

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
        assert max(sizes[9:]) <= check.gaussians, "after the stop it never grows past its size at the test"
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

    def test_patience_counts_only_the_tests_just_before(self, monkeypatch):
        """With patience 2 the test that stops is the second cheap one in a row, however many tests came before:
        the slice over the earlier tests (``check_growth``) must take exactly ``patience - 1`` of them (an
        off-by-one there passed the two-test case above). The costs are set: 100 dB, then 0 dB at every test."""
        from uncertsplat.train import trainer as trainer_module

        costs = iter([100.0] + [0.0] * 10)
        monkeypatch.setattr(trainer_module, "halving_cost_db", lambda *a, **k: next(costs))
        scene, tr, te = toy_scene()
        t = Trainer(scene, self._cfg(1.0, growth_check_interval=5, growth_patience=2, growth_refit_steps=0,
                                     start=1), tr, te)
        t.fit()
        assert [(g.cost_db, g.stopped) for g in t.growth] == [(100.0, False), (0.0, False), (0.0, True)]
        assert not t.densifier.grow

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
        assert resumed.densifier.grown_to == part.densifier.grown_to == part.growth[-1].gaussians
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

    def test_checkpoints_from_before_the_refill_only_prune_after_a_stop(self):
        scene, tr, te = toy_scene()
        part = Trainer(scene, self._cfg(50.0), tr, te)
        part.fit(until=15)
        assert not part.densifier.grow and part.densifier.grown_to == part.growth[0].gaussians
        state = part.state_dict()
        del state["grown_to"]
        resumed = Trainer(scene, self._cfg(50.0), tr, te, state=state)
        assert not resumed.densifier.grow and resumed.densifier.grown_to is None


class TestSkip:
    """A test whose half costs far above the threshold skips the next test due (``densify.growth_skip_factor``)."""

    CFG = DensifyConfig(start=100, until=4000, opacity_reset_interval=3000, growth_check_interval=250,
                        growth_skip_factor=3.0)

    @staticmethod
    def _check(step: int, skip: bool) -> GrowthCheck:
        return GrowthCheck(step=step, gaussians=10, seen=10, cost_db=1.0, min_gain_db=0.15, stopped=False, views=8,
                           skip_next=skip)

    def test_the_factor_against_the_threshold(self):
        assert self.CFG.growth_threshold_db == 0.15
        assert skips_next(0.45, self.CFG) and skips_next(math.inf, self.CFG)
        assert not skips_next(0.4499, self.CFG)
        assert not skips_next(0.45, self.CFG.model_copy(update={"growth_skip_factor": None}))
        assert skips_next(0.15, self.CFG.model_copy(update={"growth_skip_factor": 1.0}))
        assert not skips_next(5.0, self.CFG.model_copy(update={"growth_min_gain_db": 0.0})), (
            "a zero threshold (no test) skips nothing")
        assert not skips_next(5.0, self.CFG.model_copy(update={"growth_refit_steps": 0})), (
            "a test without copies costs a few renders: nothing to save")

    def test_only_the_next_test_due_is_skipped(self):
        last = self._check(500, True)
        assert skipped(last, 750, self.CFG) and not skipped(last, 1000, self.CFG)
        assert not skipped(self._check(500, False), 750, self.CFG)
        assert not skipped(None, 750, self.CFG) and not skipped(last, 500, self.CFG)

    def test_the_next_due_after_a_pause_is_the_one_skipped(self):
        """The tests pause after an opacity reset (at 3000, then none due until 4250): the first due after the
        pause is the next test, and the one after it runs."""
        cfg = self.CFG.model_copy(update={"until": 6000})
        last = self._check(2750, True)
        assert growth_check_due(3000, cfg) and skipped(last, 3000, cfg)
        last = self._check(3000, True)
        assert [m for m in range(3250, 4750, 250) if growth_check_due(m, cfg)] == [4250, 4500]
        assert skipped(last, 4250, cfg) and not skipped(last, 4500, cfg)
        # an interval not a multiple of the last test's step (a config changed on resume) still finds the next one
        other = self.CFG.model_copy(update={"growth_check_interval": 400})
        assert skipped(self._check(500, True), 800, other) and not skipped(self._check(500, True), 1200, other)

    def test_training_skips_and_records_and_resumes_the_same(self):
        """Tests every 5 steps on the toy schedule (due at 10, 15 and 20): a threshold far below every cost runs
        every other test; the skipped ones change nothing else (no test stops growth here), and a run resumed
        between a test and the one it skips skips it too."""
        scene, tr, te = toy_scene()
        every = Trainer(scene, TestTraining._cfg(1e-9, growth_check_interval=5, growth_patience=3), tr, te)
        every.fit()
        assert [g.step for g in every.growth] == [10, 15, 20]
        cfg = TestTraining._cfg(1e-9, growth_check_interval=5, growth_patience=3, growth_skip_factor=3.0)
        skip = Trainer(scene, cfg, tr, te)
        skip.fit()
        assert [(g.step, g.skip_next) for g in skip.growth] == [(10, True), (20, True)]
        assert [g.cost_db for g in skip.growth] == [every.growth[0].cost_db, every.growth[2].cost_db]
        assert_same_parameters(every.model, skip.model)
        assert [GrowthCheck.model_validate(g) for g in skip.summary()["growth"]] == skip.growth
        part = Trainer(scene, cfg, tr, te)
        part.fit(until=12)
        resumed = Trainer(scene, cfg, tr, te, state=decode(encode(part.state_dict())))
        resumed.fit()
        assert resumed.growth == skip.growth
        assert "the next test skipped" in growth_reason(skip.growth[0])


def test_a_run_from_before_the_skip_resumes_testing_every_interval(tiny_scene_path, tiny_run_path,  # noqa: F811
                                                                    tmp_path):
    """config.json files written before ``densify.growth_skip_factor`` existed tested at every interval; a resumed
    one keeps doing so."""
    cfg = resume_without_key(tiny_scene_path, tiny_run_path, tmp_path, "densify", "growth_skip_factor", 10)
    assert cfg["densify"]["growth_skip_factor"] is None


def test_a_run_from_before_the_test_resumes_without_it(tiny_scene_path, tiny_run_path, tmp_path):  # noqa: F811
    """config.json files written before ``densify.growth_min_gain_db`` existed grew up to their budget; a resumed
    one keeps doing so."""
    cfg = resume_without_key(tiny_scene_path, tiny_run_path, tmp_path, "densify", "growth_min_gain_db", 10)
    assert cfg["densify"]["growth_min_gain_db"] == 0.0


class TestRefit:
    """The test with the rest re-fitted (``densify.growth_refit_steps``): two copies of the training at the test
    (``Trainer._fork``), with and without the weakest half, train a few steps before they are compared."""

    _cfg = staticmethod(TestTraining._cfg)

    @pytest.mark.parametrize("top", [{}, {"exposure": "affine"}, {"low_res_fraction": 0.8},
                                     {"random_background": True, "drop_rate": 0.5}])
    def test_the_copies_change_nothing_of_the_training(self, top):
        """Also where the copies train what the model does not hold: the photos' exposures and their optimiser (a
        review found the copies stepping the training's own exposure moments), the half-resolution phase's photos,
        a random background and left-out Gaussians (their generators)."""
        scene, tr, te = toy_scene()

        def cfg(gain, **densify):
            return self._cfg(gain, **densify).model_copy(update=top)

        plain = Trainer(scene, cfg(0.0), tr, te)  # no test at all
        plain.fit()
        # tests that cannot stop growth (two tests, three needed in a row): the run must be the one without them
        tested = Trainer(scene, cfg(1e-9, growth_patience=3), tr, te)
        tested.fit()
        assert [(g.step, g.refit_steps) for g in tested.growth] == [(10, 3), (20, 3)]
        assert_same_parameters(plain.model, tested.model, atol=0)
        for a, b in zip(plain.optimizer.state.values(), tested.optimizer.state.values(), strict=True):
            for key in ("exp_avg", "exp_avg_sq"):
                assert torch.equal(a[key], b[key])
        assert torch.equal(plain.gen_noise.get_state(), tested.gen_noise.get_state())
        assert torch.equal(plain.gen_views.get_state(), tested.gen_views.get_state())
        assert plain.view_queue == tested.view_queue
        if plain.exposure is not None:
            assert torch.equal(plain.exposure, tested.exposure)
            for a, b in zip(plain.exposure_optimizer.state.values(), tested.exposure_optimizer.state.values(),
                            strict=True):
                assert all(torch.equal(a[k], b[k]) for k in a)
        assert [{**u, "seconds": 0} for u in plain.posterior_updates] == [
            {**u, "seconds": 0} for u in tested.posterior_updates]

    def test_a_copy_leaves_the_memory_peaks_alone(self, monkeypatch):
        """The peak a training measures its memory room and summary by (``reset_peak_memory`` at a training's
        start) is not reset by a growth test's copy: a review saw VmHWM fall from 765 to 365 MiB at one copy."""
        from uncertsplat.train import trainer as trainer_module

        scene, tr, te = toy_scene()
        t = Trainer(scene, self._cfg(0.0), tr, te)
        t.fit(until=12)
        resets = []
        monkeypatch.setattr(trainer_module, "reset_peak_memory", lambda device: resets.append(device))
        t._fork(t.step)
        assert resets == []
        Trainer(scene, self._cfg(0.0), tr, te)
        assert len(resets) == 1

    def test_the_test_without_a_refit_only_prunes_after_a_stop(self):
        """``growth_refit_steps = 0`` is the test before, whole: after its stop densification adds nothing (the
        refill up to the size at the stop comes with the re-fitted test)."""
        scene, tr, te = toy_scene()
        t = Trainer(scene, self._cfg(50.0, growth_refit_steps=0), tr, te)
        t.fit(until=15)
        (check,) = t.growth
        assert check.stopped and check.refit_steps == 0 and check.min_gain_db == 50.0
        assert not t.densifier.grow and t.densifier.grown_to is None

    def test_a_copy_trains_as_its_parent_would(self):
        """Without topology changes in the window (the toy schedule's last densification is at step 20), a copy's
        steps are its parent's, bit for bit; one without some Gaussians trains the rest."""
        scene, tr, te = toy_scene()
        parent = Trainer(scene, self._cfg(0.0), tr, te)
        parent.fit(until=21)
        fork = parent._fork(parent.step)
        off = torch.zeros(len(parent.model), dtype=torch.bool)
        off[::3] = True
        smaller = parent._fork(parent.step, off)
        assert len(smaller.model) == len(parent.model) - int(off.sum())
        for _ in range(3):
            fork.train_step()
            smaller.train_step()
        parent.fit(until=24)
        assert fork.step == parent.step == 24
        assert_same_parameters(parent.model, fork.model, atol=0)
        moved = (smaller.model.params["means"] - parent._fork(21).model.params["means"][~off]).abs().amax()
        assert moved > 0, "the rest was trained"

    def test_nothing_taken_out_costs_exactly_zero(self):
        scene, tr, te = toy_scene()
        t = Trainer(scene, self._cfg(0.0), tr, te)
        t.fit(until=12)
        none = torch.zeros(len(t.model), dtype=torch.bool)
        assert t._refit_cost(t.step, none, [0, 2, 4], t.photos([0, 2, 4]), None) == 0.0
        half = torch.zeros(len(t.model), dtype=torch.bool)
        half[: len(t.model) // 2] = True
        assert math.isfinite(t._refit_cost(t.step, half, [0, 2, 4], t.photos([0, 2, 4]), None))

    @pytest.mark.parametrize("error", [
        "diverged", "cpu", "cuda", "memory-error", "other"])
    def test_a_copy_that_cannot_train_lets_the_model_grow(self, monkeypatch, error):
        """A copy that diverges or whose memory runs out decides nothing; any other error is raised. On the CPU
        torch's allocator raises a plain RuntimeError (seen under ``ulimit -v``), which the test let end the
        training."""
        from uncertsplat.errors import UserError

        raised = {"diverged": UserError("the loss is NaN"),
                  "cpu": RuntimeError("[enforce fail at alloc_cpu.cpp:127] err == 0. DefaultCPUAllocator: can't "
                                      "allocate memory: you tried to allocate 3221225472 bytes. Error code 12"),
                  "cuda": torch.OutOfMemoryError("CUDA out of memory. Tried to allocate 2.00 GiB"),
                  "memory-error": MemoryError(), "other": RuntimeError("shape mismatch")}[error]
        step = Trainer.train_step

        def failing(self):
            if isinstance(self, GrowthCopy):
                raise raised
            return step(self)

        monkeypatch.setattr(Trainer, "train_step", failing)
        scene, tr, te = toy_scene()
        t = Trainer(scene, self._cfg(50.0), tr, te)  # (any half would be cheap against 50 dB)
        if error == "other":
            with pytest.raises(RuntimeError, match="shape mismatch"):
                t.fit()
            return
        t.fit()
        assert [(g.cost_db, g.stopped) for g in t.growth] == [(1e3, False), (1e3, False)] and t.densifier.grow
        assert "could not be measured" in growth_reason(t.growth[0])
        skipping = Trainer(scene, self._cfg(50.0, growth_skip_factor=3.0), tr, te)
        skipping.fit()
        assert [(g.step, g.cost_db, g.skip_next) for g in skipping.growth] == [(10, 1e3, True)]
        assert growth_reason(skipping.growth[0]).endswith("growth goes on (the next test skipped)")

    def test_a_stop_during_the_copies_ends_them_without_a_test(self, monkeypatch):
        """Ctrl-C (or a sweep's stop) during a test's copies waited for all their steps (minutes for a large model):
        the copies end at the next of their steps, no test is recorded, and the step's stop follows; the resumed run
        tests at the next interval."""
        from uncertsplat.train.trainer import STOP_REQUESTED, TrainingInterrupted

        step = Trainer.train_step
        fork_steps, stops = [], [1]

        def stop_in_a_copy(self):
            if isinstance(self, GrowthCopy):
                fork_steps.append(self.step)
                if len(fork_steps) == 2 and stops:
                    stops.pop()
                    STOP_REQUESTED.set()  # (as a sweep's stop, or the Ctrl-C handler's flag)
            return step(self)

        monkeypatch.setattr(Trainer, "train_step", stop_in_a_copy)
        scene, tr, te = toy_scene()
        cfg = self._cfg(1e-9, growth_refit_steps=50)
        t = Trainer(scene, cfg, tr, te)
        try:
            with pytest.raises(TrainingInterrupted):
                t.fit()
        finally:
            STOP_REQUESTED.clear()
        assert t.step == 10 and t.growth == [] and len(fork_steps) == 2, "the copies stopped after the stop came"
        fork_steps.clear()
        resumed = Trainer(scene, cfg, tr, te, state=decode(encode(t.state_dict())))
        resumed.fit()
        assert [g.step for g in resumed.growth] == [20] and len(fork_steps) == 2 * 50

    def test_one_refit_step(self):
        scene, tr, te = toy_scene()
        t = Trainer(scene, self._cfg(1e-9, growth_refit_steps=1, growth_patience=3), tr, te)
        t.fit()
        assert [g.refit_steps for g in t.growth] == [1, 1] and all(math.isfinite(g.cost_db) for g in t.growth)

    def test_the_threshold_default_follows_the_test(self):
        assert DensifyConfig().growth_threshold_db == GROWTH_MIN_GAIN_REFIT_DB == 0.15
        assert DensifyConfig(growth_refit_steps=0).growth_threshold_db == GROWTH_MIN_GAIN_DB == 0.25
        assert DensifyConfig(growth_min_gain_db=0.4, growth_refit_steps=0).growth_threshold_db == 0.4
        off = DensifyConfig(growth_min_gain_db=0.0, growth_check_interval=250)
        assert off.growth_threshold_db == 0.0 and not growth_check_due(250, off)


def test_a_run_from_before_the_refit_resumes_without_it(tiny_scene_path, tiny_run_path, tmp_path):  # noqa: F811
    """config.json files written before ``densify.growth_refit_steps`` existed switched the half off in the model as
    it was; a resumed one keeps doing so."""
    cfg = resume_without_key(tiny_scene_path, tiny_run_path, tmp_path, "densify", "growth_refit_steps", 10)
    assert cfg["densify"]["growth_refit_steps"] == 0


def test_growth_reason_says_what_was_decided():
    g = GrowthCheck(step=500, gaussians=32156, seen=31273, cost_db=0.077, min_gain_db=0.25, stopped=True, views=8)
    assert growth_reason(g) == ("growth test at step 500: switching off the weakest half of the 31,273 Gaussians 8 "
                                "training views see (of 32,156) costs 0.077 dB (< 0.25 dB), densification stops "
                                "growing the model past 32,156 Gaussians")
    waiting = growth_reason(g.model_copy(update={"stopped": False}))
    assert "(< 0.25 dB), growth goes on until" in waiting
    assert growth_reason(g.model_copy(update={"stopped": False, "cost_db": 2.0})).endswith(
        "costs 2.000 dB (>= 0.25 dB), growth goes on")
    refit = g.model_copy(update={"refit_steps": 100, "min_gain_db": 0.15})
    assert growth_reason(refit) == ("growth test at step 500: taking out the weakest half of the 31,273 Gaussians 8 "
                                    "training views see (of 32,156) and training the rest 100 steps costs 0.077 dB "
                                    "(< 0.15 dB), densification stops growing the model past 32,156 Gaussians")
