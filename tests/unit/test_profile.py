"""``TrainConfig.profile``: seconds per phase of the training steps (``train.profile.PhaseTimer``)."""

from __future__ import annotations

import time

import torch

from tests.e2e.test_train_resume import toy_config, toy_scene
from uncertsplat.schemas.runs import StepProfile
from uncertsplat.train.profile import PhaseTimer
from uncertsplat.train.trainer import Trainer

CPU = torch.device("cpu")


def test_disabled_timer_records_nothing():
    timer = PhaseTimer(CPU, enabled=False)
    with timer("render"):
        time.sleep(0.01)
    assert timer.seconds == {} and timer.summary() is None


def test_phases_accumulate_even_when_the_phase_raises():
    timer = PhaseTimer(CPU, enabled=True)
    for _ in range(2):
        with timer("render"):
            time.sleep(0.01)
    try:
        with timer("loss"):
            raise RuntimeError
    except RuntimeError:
        pass
    s = timer.summary()
    assert s["seconds"]["render"] >= 0.02 and "loss" in s["seconds"]
    assert abs(sum(s["fraction"].values()) - 1.0) < 1e-9


def test_profiled_training_reports_every_phase():
    scene, tr, te = toy_scene()
    t = Trainer(scene, toy_config(iterations=20, profile=True,
                                  variational={"posterior": "informed", "refresh_interval": 10}), tr, te)
    t.fit()
    prof = StepProfile.model_validate(t.summary()["profile"])
    assert prof.steps == 20
    assert {"data", "sample", "render", "loss", "backward", "optimizer", "densify", "posterior", "eval"} <= set(
        prof.seconds)
    assert all(v >= 0 for v in prof.seconds.values())
    unprofiled = Trainer(scene, toy_config(iterations=2), tr, te)
    unprofiled.fit()
    assert "profile" not in unprofiled.summary()
