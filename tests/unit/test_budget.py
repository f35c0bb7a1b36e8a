"""The model-size budget (``strategy.budget``): the user's limit, or one from the scene's training pixels."""

from __future__ import annotations

import pytest
import torch

from tests.e2e.test_train_resume import toy_config, toy_scene
from uncertsplat.config import PIXELS_PER_GAUSSIAN, DensifyConfig
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
