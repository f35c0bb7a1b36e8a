"""Photos of different exposure, end to end: ``train`` warns about them with ``exposure`` off and learns them with
``exposure = "affine"`` (``RUN/exposure.json``), ``evaluate`` reads the exposures back, ``prune`` keeps them."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.fixtures import tiny_scene_path  # noqa: F401
from tests.run_fixtures import train_tiny_run
from uncertsplat.io.images import read_image, write_png
from uncertsplat.schemas import RunExposure, TrainSummary

GAINS = (0.6, 1.0, 1.4, 0.8, 1.2)
"""The brightness of the training photos, in turn (the held-out photos keep theirs)."""


@pytest.fixture(scope="module")
def exposed_scene(tiny_scene_path, tmp_path_factory) -> Path:  # noqa: F811
    """The tiny scene with each training photo's brightness scaled by one of ``GAINS``."""
    scene = tmp_path_factory.mktemp("exposure") / "scene"
    shutil.copytree(tiny_scene_path, scene)
    meta = json.loads((scene / "scene.json").read_text(encoding="utf-8"))
    held = set(meta["test_views"])
    for i, name in enumerate(n for n in meta["image_names"] if n not in held):
        path = scene / "images" / name
        pixels = np.clip(read_image(path)[..., :3] * GAINS[i % len(GAINS)], 0.0, 1.0)
        path.unlink()
        write_png(path, pixels.astype(np.float32))
    return scene


def test_train_warns_about_photos_of_different_brightness_with_exposure_off(exposed_scene, tmp_path):
    run = train_tiny_run(exposed_scene, tmp_path / "off")  # exposure "off", the default
    summary = TrainSummary.read(run / TrainSummary.FILE_NAME)
    assert any("differ in brightness" in w and "exposure=affine" in w for w in summary.warnings), summary.warnings
    assert not (run / RunExposure.FILE_NAME).exists() and summary.exposure_checks == []


def test_auto_learns_the_exposures_once_a_test_finds_them_different(exposed_scene, tmp_path, capsys):
    run = train_tiny_run(exposed_scene, tmp_path / "auto", exposure="auto", exposure_check_interval=40,
                         exposure_lr=0.01)
    summary = TrainSummary.read(run / TrainSummary.FILE_NAME)
    assert summary.exposure_checks and summary.exposure_checks[-1].enabled, summary.exposure_checks
    assert (run / RunExposure.FILE_NAME).is_file()
    assert not any("differ in brightness" in w for w in summary.warnings), summary.warnings
    err = " ".join(capsys.readouterr().err.split())
    assert "learning each photo's exposure from here on" in err


def test_affine_exposures_are_learned_evaluated_and_kept_by_prune(exposed_scene, tiny_scene_path, tmp_path):  # noqa: F811
    from uncertsplat.baselines import load_run
    from uncertsplat.config import EvalConfig, PruneConfig
    from uncertsplat.stages import evaluate, prune

    run = train_tiny_run(exposed_scene, tmp_path / "affine", exposure="affine", exposure_lr=0.01)
    summary = TrainSummary.read(run / TrainSummary.FILE_NAME)
    assert not any("differ in brightness" in w for w in summary.warnings), summary.warnings
    record = RunExposure.read(run / RunExposure.FILE_NAME)
    meta = json.loads((exposed_scene / "scene.json").read_text(encoding="utf-8"))
    train_names = [n for n in meta["image_names"] if n not in set(meta["test_views"])]
    assert record.images == train_names and record.step == summary.steps
    # the learned gains follow the photos' brightness
    learned = np.log([sum(g) / 3 for g in record.gain])
    true = np.log([GAINS[i % len(GAINS)] for i in range(len(train_names))])
    assert np.corrcoef(learned, true)[0, 1] > 0.8, (learned, true)

    loaded = load_run(run)
    scene = loaded.load_scene()
    exposure = loaded.photo_exposure()
    assert [scene.cameras.image_names[i] for i in exposure.indices] == train_names
    assert loaded.sampler(scene.scene_scale, torch.device("cpu")).exposure is not None
    # a pruned subset (prune's measurements) keeps the photos' exposures without reading the scene again, not the
    # model-dependent coverage
    subset = loaded.with_model(loaded.model)
    assert subset.photo_exposure() is exposure and subset._coverage is None and loaded._coverage is not None

    cfg = EvalConfig(num_samples=2)
    report = evaluate.run(run, cfg, torch.device("cpu"))
    assert np.isfinite(report.mean.nll) and report.mean.psnr > 10
    assert any(n.startswith("exposure of ") and "part of the RGB std" in n for n in report.notes), report.notes
    (std,) = [n for n in report.notes if n.startswith("std² = ")]  # the formula names the term too (a helper's audit)
    assert "training photos' learned exposures" in std

    out = tmp_path / "pruned"
    prune.run(run, out, PruneConfig(keep_ratio=0.9, num_samples=2), torch.device("cpu"))
    assert (out / RunExposure.FILE_NAME).read_bytes() == (run / RunExposure.FILE_NAME).read_bytes()
    assert load_run(out).exposure == record
