"""The model-size budget (``strategy.budget``): the user's limit, or one from the scene's training pixels."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from tests.e2e.test_train_resume import toy_config, toy_scene
from uncertsplat.config import PIXELS_PER_GAUSSIAN, DensifyConfig
from uncertsplat.gaussians.params import memory_per_gaussian, memory_per_new_gaussian
from uncertsplat.schemas.runs import Budget
from uncertsplat.strategy import budget as budget_mod
from uncertsplat.strategy.budget import MAX_BUDGET, MIN_BUDGET, gaussian_budget
from uncertsplat.train.trainer import Trainer


class TestBudget:
    def test_a_limit_the_user_sets_wins(self):
        b = gaussian_budget(40000, 1.0, views=100, width=1000, height=1000)
        assert (b.max_gaussians, b.source) == (40000, "config")

    def test_auto_is_one_gaussian_per_pixels_per_gaussian(self):
        b = gaussian_budget(None, 50.0, views=35, width=320, height=240)
        assert b.max_gaussians == 53760 and b.source == "auto"  # 2,688,000 / 50
        assert gaussian_budget(None, 7.0, views=1, width=100, height=100).max_gaussians == 1429  # rounded up
        assert "35 views of 320x240" in b.reason and "clamped" not in b.reason

    @pytest.mark.parametrize(("views", "expected"), [(1, MIN_BUDGET), (10**6, MAX_BUDGET)])
    def test_extremes_are_clamped(self, views, expected):
        b = gaussian_budget(None, 32.0, views=views, width=64, height=48)
        assert b.max_gaussians == expected and "clamped" in b.reason

    def test_default_config_uses_the_automatic_budget(self):
        d = DensifyConfig()
        assert d.max_gaussians is None and d.pixels_per_gaussian == PIXELS_PER_GAUSSIAN


def test_training_respects_and_records_the_automatic_budget(monkeypatch):
    monkeypatch.setattr(budget_mod, "MIN_BUDGET", 10)
    scene, tr, te = toy_scene()
    pixels = tr.shape[0] * tr.shape[1] * tr.shape[2]
    cfg = toy_config(densify={"start": 5, "until": 25, "interval": 5, "spawn_interval": 10,
                              "opacity_reset_interval": 0, "grad_threshold": 1e-5, "max_gaussians": None,
                              "pixels_per_gaussian": pixels / 170})
    t = Trainer(scene, cfg, tr, te)
    t.fit()
    recorded = Budget.model_validate(t.summary()["budget"])
    assert recorded.source == "auto" and recorded.max_gaussians == 170
    assert 150 < len(t.model) <= 170, "it grows, up to the budget"
    unlimited = Trainer(scene, cfg.model_copy(update={"densify": cfg.densify.model_copy(
        update={"max_gaussians": 10**6})}), tr, te)
    unlimited.fit()
    assert len(unlimited.model) > 170, "without the budget the same schedule grows past it"
    assert unlimited.summary()["budget"]["source"] == "config"
    assert torch.isfinite(t.model.params["means"]).all()


class TestMemoryGrowthLimit:
    def test_room_past_the_reserve_is_shared_among_new_gaussians(self):
        assert budget_mod.memory_growth_limit(1000, budget_mod.MEMORY_RESERVE + 10_000, 100.0) == 1100

    @pytest.mark.parametrize("room", [0, budget_mod.MEMORY_RESERVE - 1, -(2**40)])
    def test_no_room_never_removes_gaussians(self, room):
        assert budget_mod.memory_growth_limit(1000, room, 100.0) == 1000

    def test_a_zero_cost_does_not_divide_by_zero(self):
        assert budget_mod.memory_growth_limit(0, budget_mod.MEMORY_RESERVE + 5, 0.0) == 5

    def test_the_warning_says_the_hold_s_numbers(self):
        """The record keeps the room in MiB (``Trainer``: room / 2**20): 1024 of them are 1 GiB, of which 0.25 are
        kept free and 0.75 GiB at 2 KiB a Gaussian hold 393,216 more."""
        hold = {"step": 300, "gaussians": 52_000, "budget": 80_000, "room_mb": 1024.0, "per_gaussian_bytes": 2048}
        said = " ".join(budget_mod.memory_hold_warning(hold).split())
        assert said.startswith("memory held the model's growth from step 300 on, at 52,000 Gaussians (its budget: "
                               "80,000): 1.00 GB were left beyond what training takes"), said
        assert "keeps 0.25 GB free and takes about 2.0 KB a Gaussian" in said
        assert "room for 393,216 more" in said and said.endswith("--set densify.max_gaussians=52000 makes this size "
                                                                 "the budget")

    def test_a_grown_gaussian_is_priced_above_every_measured_factor(self):
        # BENCHMARKS.md's measured peaks per byte of state: 3.9x, 5.3x, 7.6x (random Gaussians at 320x240 to
        # 1280x960), 4.3x (a densified model): a factor below any of them lets growth run the process out of memory
        assert budget_mod.GROWN_GAUSSIAN_FACTOR >= 7.6


def _grown(monkeypatch, room):
    scene, tr, te = toy_scene()
    cfg = toy_config(densify={"start": 5, "until": 25, "interval": 5, "spawn_interval": 10,
                              "opacity_reset_interval": 0, "grad_threshold": 1e-5, "max_gaussians": 10**6})
    t = Trainer(scene, cfg, tr, te)
    if room is not None:
        monkeypatch.setattr(Trainer, "_memory_room", lambda self: room(self))
    t.fit()
    return t


def test_memory_holds_growth_below_the_budget_and_records_it(monkeypatch, capsys):
    free = _grown(monkeypatch, None)
    start = len(Trainer(*toy_scene()[:1], toy_config(), *toy_scene()[1:]).model)

    def room(self):  # room for 30 more Gaussians than the model starts with, at the trainer's own cost per Gaussian
        per = budget_mod.GROWN_GAUSSIAN_FACTOR * memory_per_new_gaussian(self.model, carrier=True,
                                                                         table_moments=not self.informed)
        return budget_mod.MEMORY_RESERVE + int((start + 30 - len(self.model)) * per) + 1

    held = _grown(monkeypatch, room)
    assert len(free.model) > start + 60, "without the hold the schedule grows well past it"
    assert start < len(held.model) <= start + 30, "it grows into the room it has, no further"
    hold = Budget.model_validate(held.summary()["budget"]).memory_hold
    assert hold is not None and hold.gaussians <= start + 30 and hold.held >= 1 and hold.step <= hold.last_step
    assert hold.budget == 10**6 and free.summary()["budget"]["memory_hold"] is None
    warning = held.memory_hold_warning()
    assert "memory held the model's growth" in warning and f"densify.max_gaussians={hold.gaussians}" in warning
    said = capsys.readouterr().err
    assert said.count("memory held the model's growth") == 1, "said once, when it first holds"
    assert " ".join(said.split()).endswith(" ".join(warning.split())), "what it said is what it records"
    assert torch.isfinite(held.model.params["means"]).all()


def test_no_room_at_all_keeps_the_model_and_trains_on(monkeypatch):
    held = _grown(monkeypatch, lambda self: 0)
    start = len(Trainer(*toy_scene()[:1], toy_config(), *toy_scene()[1:]).model)
    assert len(held.model) <= start, "no Gaussian added (pruning may still remove some)"
    assert held.step == held.cfg.iterations


def test_a_device_that_does_not_say_leaves_the_budget_alone(monkeypatch):
    free = _grown(monkeypatch, None)
    unknown = _grown(monkeypatch, lambda self: None)
    assert len(unknown.model) == len(free.model) and unknown.memory_hold is None


def test_a_resume_keeps_the_record_of_memory_holding_growth(monkeypatch, capsys):
    from uncertsplat.io.checkpoints import decode, encode

    scene, tr, te = toy_scene()
    cfg = toy_config(densify={"start": 5, "until": 25, "interval": 5, "spawn_interval": 10,
                              "opacity_reset_interval": 0, "grad_threshold": 1e-5, "max_gaussians": 10**6})
    monkeypatch.setattr(Trainer, "_memory_room", lambda self: 0)
    part = Trainer(scene, cfg, tr, te)
    part.fit(until=12)
    assert part.memory_hold is not None and part.memory_hold["last_step"] <= 12
    capsys.readouterr()
    resumed = Trainer(scene, cfg, tr, te, state=decode(encode(part.state_dict())))
    resumed.fit()
    hold = resumed.summary()["budget"]["memory_hold"]
    assert hold == {**part.memory_hold, "last_step": hold["last_step"], "held": hold["held"]}, \
        "the first hold's numbers are the ones before the checkpoint"
    assert hold["last_step"] > 12 and hold["held"] > part.memory_hold["held"], "the holds after it are added"
    assert capsys.readouterr().err.count("memory held the model's growth") == 1, "the resumed process says it too"


def test_a_version_6_train_summary_reads_with_no_hold():
    """``make demo``'s train_summary.json of 2026-12-01 (version 6, before memory could hold growth): its budget
    reads with ``memory_hold`` None (nothing held), every other value kept."""
    from uncertsplat.schemas.runs import TrainSummary

    path = Path(__file__).resolve().parents[1] / "data" / "outputs_2026-11-29" / "train_summary.json"
    old = json.loads(path.read_text(encoding="utf-8"))
    v6 = {**old, "schema_version": 6, "posterior": {"position_prior": "config", **old["posterior"]},
          "budget": {"max_gaussians": 40000, "source": "config", "reason": "densify.max_gaussians"}}
    got = TrainSummary.from_dict(v6)
    assert got.schema_version == TrainSummary.SCHEMA_VERSION and got.budget.memory_hold is None
    assert got.budget.max_gaussians == 40000 and got.steps == old["steps"]


def test_a_new_gaussian_is_priced_as_a_carrier_before_any_carrier_exists():
    """Split children carry a posterior: priced by the model's average while none did, growth was priced 7x low."""
    from uncertsplat.gaussians.variational import random_model

    gen = torch.Generator().manual_seed(0)
    none = random_model(100, gen, carrier_fraction=0.0)
    some = random_model(100, gen, carrier_fraction=0.5)
    carrier = memory_per_new_gaussian(none, carrier=True)
    assert carrier == memory_per_new_gaussian(some, carrier=True), "whatever the share of carriers"
    assert carrier > memory_per_gaussian(none)["total"] + 2 * some.tables["pos_loc"][0].numel() * 4
    assert memory_per_new_gaussian(none, carrier=False) == pytest.approx(memory_per_gaussian(none)["total"])
    assert memory_per_new_gaussian(none, carrier=True, table_moments=False) < carrier


def test_each_training_is_held_by_its_own_peaks_not_the_process_s(monkeypatch):
    """An ensemble's later member, a sweep's later point, a pipeline's train stage: a Trainer starts its peak over."""
    from uncertsplat.train import trainer as trainer_mod

    resets = []
    monkeypatch.setattr(trainer_mod, "reset_peak_memory", lambda device: resets.append(str(device)))
    monkeypatch.setattr(trainer_mod, "peak_memory_mb", lambda device: 4321.0 if not resets else 1234.0)
    scene, tr, te = toy_scene()
    t = Trainer(scene, toy_config(), tr, te)
    assert resets == ["cpu"], "reset once it is built"
    assert t.summary()["peak_memory_mb"] == 4321.0, "the summary keeps the process's peak from before"
