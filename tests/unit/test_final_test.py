"""The held-out test ``fit`` renders at the step it trains to is reused by the ``evaluate`` that follows (train's
summary) when the model is the same to the bit: the same numbers, without rendering every held-out view twice."""

from __future__ import annotations

import torch

from tests.e2e.test_train_resume import toy_config, toy_scene
from uncertsplat.train.trainer import Trainer


def _counting(t: Trainer) -> list[int]:
    """Count the renders ``t`` makes from here on (one entry per render)."""
    seen: list[int] = []
    render = t.render

    def wrapped(g, cams, background=None):
        seen.append(1)
        return render(g, cams, background=background)

    t.render = wrapped
    return seen


def _fitted() -> tuple[Trainer, dict]:
    scene, tr, te = toy_scene()
    t = Trainer(scene, toy_config(iterations=25, eval_every=100), tr, te)
    last = t.fit()
    return t, last


class TestFinalTest:
    def test_evaluate_after_fit_reuses_the_last_steps_test(self):
        t, last = _fitted()
        renders = _counting(t)
        held = t.evaluate()
        assert renders == []  # every held-out view was rendered twice
        assert held == {"psnr": last["eval_psnr"], "ssim": last["eval_ssim"]}
        t._final_test = None  # the numbers a fresh test gives
        assert t.evaluate() == held
        assert len(renders) == len(t.test_idx)

    def test_a_changed_model_is_tested_again(self):
        t, _ = _fitted()
        renders = _counting(t)
        with torch.no_grad():
            t.model.params["opacities"].sub_(1.0)
        held = t.evaluate()
        assert len(renders) == len(t.test_idx)
        t._final_test = None
        assert t.evaluate() == held

    def test_a_later_step_is_tested_again(self):
        t, _ = _fitted()
        renders = _counting(t)
        t.step += 1
        t.evaluate()
        assert len(renders) == len(t.test_idx)

    def test_a_test_of_some_views_is_rendered(self):
        t, _ = _fitted()
        renders = _counting(t)
        t.evaluate(max_views=1)
        assert len(renders) == 1
