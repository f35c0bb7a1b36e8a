"""`evaluate` end to end on a trained tiny run: maps, metrics.json, determinism, bad input."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import shutil
from functools import partial
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from tests.fixtures import tiny_scene_path  # noqa: F401
from tests.run_fixtures import tiny_run_path  # noqa: F401
from uncertsplat.baselines import load_run
from uncertsplat.cli import app
from uncertsplat.config import EvalConfig, build_config
from uncertsplat.data.dataset import load_view_set
from uncertsplat.errors import UserError
from uncertsplat.eval.engine import StdFit, evaluate_views, fit_residual, fit_std_scale, with_side_terms
from uncertsplat.io.checkpoints import decode, encode
from uncertsplat.io.images import read_exr, read_exr_attribute
from uncertsplat.io.maps import (
    EXR_ALPHA_CHANNEL,
    EXR_CHANNELS,
    EXR_DEPTH_TO_SOURCE,
    EXR_RGB_DOF,
    EXR_RGB_PREDICTIVE,
    map_stem,
)
from uncertsplat.schemas.metrics import EvalReport
from uncertsplat.schemas.prune import PruneReport
from uncertsplat.stages import evaluate

runner = CliRunner()


@pytest.fixture(scope="module")
def evaluated(tiny_run_path, tmp_path_factory):
    run = tmp_path_factory.mktemp("ev") / "run"
    shutil.copytree(tiny_run_path, run)
    report = evaluate.run(run, EvalConfig(num_samples=5, seed=3), device=torch.device("cpu"))
    return run, report


def test_the_notes_say_what_a_point_no_training_camera_looked_at_gets(evaluated):
    """The predictive's description names the consistency term's level for such points: the palette's variance."""
    _, report = evaluated
    assert any("outside every training image gets the variance of the scene's colours" in n for n in report.notes)


def test_maps_that_would_fill_the_disk_are_warned_of_after_the_first_view(tiny_run_path, tmp_path, capsys,
                                                                          monkeypatch):  # noqa: F811
    """30 views of 1600x1200 wrote 2.2 GB without a word: after the first view's maps, the rest's size is weighed
    against the disk's free space."""
    import collections

    run = tmp_path / "run"
    shutil.copytree(tiny_run_path, run)
    evaluate.run(run, EvalConfig(num_samples=2, seed=3, max_views=2), device=torch.device("cpu"))
    assert "may fill before the last view" not in " ".join(capsys.readouterr().err.split())
    usage = collections.namedtuple("usage", "total used free")
    monkeypatch.setattr(evaluate.shutil, "disk_usage", lambda path: usage(10**9, 10**9 - 1000, 1000))
    evaluate.run(run, EvalConfig(num_samples=2, seed=4, max_views=2), device=torch.device("cpu"))
    said = " ".join(capsys.readouterr().err.split())
    assert "warning: the maps of the 2 views take about" in said and "--set save_maps=false" in said


def test_save_maps_false_writes_no_maps_and_clears_earlier_ones(tiny_run_path, tmp_path, capsys):  # noqa: F811
    run = tmp_path / "run"
    shutil.copytree(tiny_run_path, run)
    evaluate.run(run, EvalConfig(num_samples=2, seed=3), device=torch.device("cpu"))
    assert any((run / "eval" / "maps").iterdir())
    capsys.readouterr()
    evaluate.run(run, EvalConfig(num_samples=2, seed=4, save_maps=False), device=torch.device("cpu"))
    assert not (run / "eval" / "maps").exists()  # the earlier maps belonged to the earlier metrics
    said = " ".join(capsys.readouterr().err.split())
    assert "(no maps: save_maps = false)" in said
    # the whole evaluation's time beside the table's, which is each view's renders alone (read as the whole)
    assert re.search(r"\(\d+\.\d s in all; 'render s' is each view's samples' renders alone\)", said) and "render s" in said
    assert EvalReport.from_json((run / "eval" / "metrics.json").read_text(encoding="utf-8")).seed == 4


def test_writes_maps_and_metrics(evaluated):
    from uncertsplat.eval.depth import valid_depth_mask
    from uncertsplat.eval.sparsification import sparsification_all

    run, report = evaluated
    data = EvalReport.from_json((run / "eval" / "metrics.json").read_text(encoding="utf-8"))
    assert data.image_names == report.image_names and len(data.image_names) == 3  # every 8th of 24 views
    scene_data = load_run(run, "cpu").load_scene()
    for name in data.image_names:
        stem = map_stem(name)
        ch = read_exr(run / "eval" / "maps" / f"{stem}.exr")
        assert set(EXR_CHANNELS) <= set(ch)
        assert ch["rgb_std.R"].shape == (96, 128)
        assert np.all((ch[EXR_ALPHA_CHANNEL] >= 0) & (ch[EXR_ALPHA_CHANNEL] <= 1 + 1e-6))
        assert ch[EXR_ALPHA_CHANNEL].mean() > 0.5  # a trained model covers most of its held-out views
        assert np.all(ch["rgb_std.R"] >= 0) and np.all(np.isfinite(ch["depth_mean.Z"]))
        # the header says which predictive the std is the std of
        exr = run / "eval" / "maps" / f"{stem}.exr"
        assert read_exr_attribute(exr, EXR_RGB_PREDICTIVE) == "student-t"
        assert read_exr_attribute(exr, EXR_RGB_DOF) == pytest.approx(report.degrees_of_freedom, rel=1e-6)
        # the factor to the scene's own units (1 / s of world_from_source): depth_mean x it is the GT depth's scale
        scale = read_exr_attribute(exr, EXR_DEPTH_TO_SOURCE)
        world_from_source = json.loads((run / "scene.json").read_text(encoding="utf-8"))["world_from_source"]
        assert scale == pytest.approx(1.0 / world_from_source[0][0], rel=1e-6)
        scene = Path(json.loads((run / "scene.json").read_text(encoding="utf-8"))["scene"])
        gt_depth = np.load(scene / "depth" / f"{Path(name).stem}.npy").reshape(ch["depth_mean.Z"].shape)
        hit = np.isfinite(gt_depth) & (gt_depth > 0) & (ch["depth_mean.Z"] > 0)
        # (the scale is what is checked: s is ~0.25 here; a short run's depths are a few per cent off)
        assert np.median(ch["depth_mean.Z"][hit] * scale / gt_depth[hit]) == pytest.approx(1.0, abs=0.15)
        for suffix in ("gt", "mean", "error", "std", "error_rank", "std_rank", "depth", "depth_std"):
            assert (run / "eval" / "maps" / f"{stem}_{suffix}.png").is_file()
        # the view's AUSEs are those of the stored maps against its GT (float32 maps: the same numbers; a synthetic
        # scene's views are upright, nothing turned)
        view = load_view_set(scene_data, [scene_data.cameras.image_names.index(name)])
        mask = view.masks[0] if view.masks is not None else None
        mean = torch.from_numpy(np.stack([ch[f"rgb_mean.{c}"] for c in "RGB"], -1))
        std = torch.from_numpy(np.stack([ch[f"rgb_std.{c}"] for c in "RGB"], -1))
        err = mean.clamp(0, 1) - view.images[0]
        sp = sparsification_all(err, std, mask=mask, steps=data.ause_steps)
        v = data.per_view[name]
        assert v.ause_mae == pytest.approx(sp["mae"].ause, rel=1e-4, abs=1e-7)
        assert v.ause_mse == pytest.approx(sp["mse"].ause, rel=1e-4, abs=1e-7)
        assert v.ause_rmse == pytest.approx(sp["rmse"].ause, rel=1e-4, abs=1e-7)
        # the std ranks the errors better than a random score (AURG > 0), its reverse worse (the AUSEs of the two do
        # not tell them apart here: each is normalised by its own curves' maximum, which the reverse's rise lifts)
        reverse = sparsification_all(err, -std, mask=mask, steps=data.ause_steps)["mae"]
        assert sp["mae"].aurg > 0 > reverse.aurg
        assert data.curves[name].rgb["mae"].aurg == pytest.approx(sp["mae"].aurg, rel=1e-4, abs=1e-7)
        # depth: the scene's GT in the run's units (scale 1), scored where the model covers the pixel (alpha > 0.5)
        d_mean, d_std, alpha = (torch.from_numpy(ch[k])[..., None] for k in ("depth_mean.Z", "depth_std.Z",
                                                                               EXR_ALPHA_CHANNEL))
        covered = alpha > 0.5 if mask is None else (alpha > 0.5) & mask
        valid = valid_depth_mask(d_mean, view.depths[0], covered)
        dsp = sparsification_all(d_mean - view.depths[0], d_std, mask=valid, steps=data.ause_steps)
        assert v.depth_ause_mae == pytest.approx(dsp["mae"].ause, rel=1e-4, abs=1e-7)
        assert v.depth_ause_rmse == pytest.approx(dsp["rmse"].ause, rel=1e-4, abs=1e-7)
    m = data.mean
    assert 10 < m.psnr < 60 and 0 < m.ssim <= 1
    assert m.ause_mae is not None and m.nll is not None and m.nll_kde is not None
    # the one deterministic render `train` reports (the expected render) scores near the mean of K samples
    assert m.psnr_render is not None and abs(m.psnr_render - m.psnr) < 1.5
    summary = json.loads((run / "train_summary.json").read_text(encoding="utf-8"))
    assert m.psnr_render == pytest.approx(summary["test_psnr"], abs=1e-3)  # the same render, the same views
    # the synthetic scene has GT depth in the run's own units: the scale is known, not estimated
    assert data.depth_scale.method == "scene" and data.depth_scale.scale == 1.0
    assert m.depth_ause_mae is not None and m.depth_abs_rel is not None
    assert "depth" in data.curves["mean"].model_dump() and data.curves["mean"].depth["mae"].oracle
    assert data.num_samples == 5 and data.seconds_per_view > 0


def test_posterior_gives_nonzero_std(evaluated):
    run, report = evaluated
    name = report.image_names[0]
    ch = read_exr(run / "eval" / "maps" / f"{map_stem(name)}.exr")
    assert ch["rgb_std.R"].max() > 0, "a run with posterior carriers must have some spread"


def test_the_variance_shares_say_what_the_predictive_is_made_of(evaluated):
    """metrics.json records each part's share of the predictive's variance on the scored pixels (RGB and depth), in
    the order the parts are added, summing to 1; the console's and report's sentence ranks them. A file of schema
    version 4 (before the shares) reads with none."""
    run, report = evaluated
    path = run / "eval" / "metrics.json"
    data = EvalReport.from_json(path.read_text(encoding="utf-8"))
    assert data.variance_shares == report.variance_shares
    rgb, depth = data.variance_shares["rgb"], data.variance_shares["depth"]
    assert list(rgb)[:3] == ["samples", "resolution", "empty rays"]
    assert {"pixel noise", "colour posterior", "edge", "view consistency"} <= set(rgb)
    assert list(depth)[:3] == ["samples", "resolution", "empty rays"] and "depth spread" in depth
    for shares in (rgb, depth):
        assert sum(shares.values()) == pytest.approx(1.0, abs=1e-9) and min(shares.values()) >= 0.0
    assert rgb["samples"] > 0.0  # a posterior's spread
    text = data.variance_parts()
    top = max(rgb, key=rgb.get)
    assert text.startswith(f"RGB: {top if top != 'samples' else 'the samples' + chr(39) + ' spread'} ")
    assert "; depth: " in text
    old = json.loads(path.read_text(encoding="utf-8"))
    old["schema_version"] = 4
    del old["variance_shares"]
    back = EvalReport.from_dict(old)
    assert back.variance_shares == {} and back.variance_parts() is None


def test_same_seed_same_metrics(evaluated, tiny_run_path, monkeypatch):
    from uncertsplat.eval.nll import kde_nll
    from uncertsplat.uncertainty import mc

    run, report = evaluated
    cpu = torch.device("cpu")
    loaded = load_run(run, cpu)
    scene = loaded.load_scene()
    cfg = EvalConfig(num_samples=5, seed=3)
    field = fit_residual(loaded.sampler(scene.scene_scale, cpu), scene.split["train"], cfg, cpu,
                         load_views=partial(load_view_set, scene, depth=False))
    sampler = with_side_terms(loaded.sampler(scene.scene_scale, cpu), field, scene.cameras[scene.split["train"]], cfg,
                              cpu)
    kept = []  # the samples each view's renders keep (the KDE NLL's; evaluate writes none of them)
    real = mc.mc_render
    monkeypatch.setattr(mc, "mc_render", lambda *a, **k: kept.append(out := real(*a, **k)) or out)
    views = load_view_set(scene, scene.split["test"])
    again = evaluate_views(sampler, views, cfg, cpu, show_progress=False)
    assert again.mean.ause_mae == pytest.approx(report.mean.ause_mae, rel=1e-6)
    assert again.mean.psnr == pytest.approx(report.mean.psnr, rel=1e-6)
    # the KDE NLL is that of the view's GT image (not of the samples' own mean) under its K samples
    assert len(kept) == len(views.indices) == len(report.image_names)
    for j, (name, (_, samples)) in enumerate(zip(report.image_names, kept, strict=True)):
        assert samples is not None and samples.rgb.shape[0] == cfg.num_samples
        mask = views.masks[j] if views.masks is not None else None
        expected = float(kde_nll(samples.rgb[:, 0].cpu(), views.images[j], mask=mask))
        assert report.per_view[name].nll_kde == pytest.approx(expected, rel=1e-5, abs=1e-6)


def test_std_scale_is_fitted_on_training_views_and_applied_to_the_std(evaluated):
    from uncertsplat.data.dataset import load_images
    from uncertsplat.eval.calibration import calibration
    from uncertsplat.eval.nll import gaussian_nll, predictive_nll

    run, report = evaluated
    assert report.std_scale is not None and report.std_scale > 0
    scene = load_run(run, "cpu").load_scene()
    train_names = {scene.cameras.image_names[i] for i in scene.split["train"]}
    assert len(report.calibration_views) == 8 and set(report.calibration_views) <= train_names
    assert not set(report.calibration_views) & set(report.image_names)  # never the views it is scored on
    # the calibrated NLL is the NLL of the stored maps with the std times the fitted factor
    name = report.image_names[0]
    ch = read_exr(run / "eval" / "maps" / f"{map_stem(name)}.exr")
    mean = torch.from_numpy(np.stack([ch[f"rgb_mean.{c}"] for c in "RGB"], -1))
    std = torch.from_numpy(np.stack([ch[f"rgb_std.{c}"] for c in "RGB"], -1))
    gt = load_images(scene, [scene.cameras.image_names.index(name)])[0]
    v = report.per_view[name]
    # the predictive: a Student-t with the std and the degrees of freedom fitted on the same views
    dof = report.degrees_of_freedom
    assert dof is not None and dof >= 2.1
    assert float(predictive_nll(gt, mean, std, dof, std_floor=report.std_floor)) == pytest.approx(v.nll, abs=1e-4)
    assert float(gaussian_nll(gt, mean, std, std_floor=report.std_floor)) == pytest.approx(v.nll_gaussian, abs=1e-4)
    expected = float(predictive_nll(gt, mean, std * report.std_scale, dof, std_floor=report.std_floor))
    assert v.nll_calibrated == pytest.approx(expected, abs=1e-4)
    err = mean.clamp(0, 1) - gt
    assert calibration(err, std, dof=dof).calibration_error == pytest.approx(v.calibration_error, abs=1e-3)
    assert calibration(err, std).calibration_error == pytest.approx(v.calibration_error_gaussian, abs=1e-3)
    assert report.calibration["rgb"].half_widths == list(calibration(err, std, dof=dof).half_widths)
    assert report.mean.calibration_error_calibrated is not None
    # the calibrated calibration error is that of the std times the factor (the factor changes it: not the raw one)
    calibrated = calibration(err, std * report.std_scale, dof=dof).calibration_error
    assert v.calibration_error_calibrated == pytest.approx(calibrated, abs=1e-6)
    assert abs(calibrated - v.calibration_error) > 2e-3


def test_std_scale_is_fitted_on_the_views_set_aside_from_training(tiny_run_path, tmp_path, monkeypatch):
    """A run whose scene set views aside (``scene.calibration_holdout``) gets its std factor fitted on exactly those:
    none of them a training view, the report saying so, and the factor the maximum-likelihood one of their maps."""
    from uncertsplat.uncertainty import mc

    run = tmp_path / "run"
    shutil.copytree(tiny_run_path, run)
    cfg_path = run / "config.json"
    config = json.loads(cfg_path.read_text(encoding="utf-8"))
    config["scene"]["calibration_holdout"] = 2
    cfg_path.write_text(json.dumps(config))
    ecfg = EvalConfig(num_samples=2, max_views=1, residual_views=2)
    rep = evaluate.run(run, ecfg, device=torch.device("cpu"))
    loaded = load_run(run, "cpu")
    scene = loaded.load_scene()
    names = scene.cameras.image_names
    held = [names[i] for i in scene.split["calibration"]]
    assert len(held) == 2 and rep.calibration_views == held and rep.calibration_held_out
    assert rep.noise_scale is not None and rep.noise_scale != 1.0  # residual_scale "auto": fitted on the views aside
    assert not set(held) & {names[i] for i in scene.split["train"]}
    saved = EvalReport.from_json((run / "eval" / "metrics.json").read_text(encoding="utf-8"))
    assert saved.calibration_held_out and saved.calibration_views == held
    # the engine fits the same factor on the scene's split, and another one on its training views
    cpu = torch.device("cpu")
    field = fit_residual(loaded.sampler(scene.scene_scale, cpu), scene.split["train"], ecfg, cpu,
                         load_views=partial(load_view_set, scene, depth=False),
                         calibration_indices=scene.split["calibration"])
    assert field.scale == pytest.approx(rep.noise_scale, rel=1e-6)
    sampler = with_side_terms(loaded.sampler(scene.scene_scale, cpu), field, scene.cameras[scene.split["train"]], ecfg,
                              cpu)
    on_train = fit_std_scale(sampler, {"train": scene.split["train"]}, ecfg, cpu,
                             load_views=partial(load_view_set, scene, depth=False))
    assert not set(on_train.names) & set(held) and on_train.scale != pytest.approx(rep.std_scale, rel=1e-3)
    rendered = []  # the maps of the views the factor is fitted on
    real = mc.mc_render
    monkeypatch.setattr(mc, "mc_render", lambda *a, **k: rendered.append(out := real(*a, **k)) or out)
    again = fit_std_scale(sampler, scene.split, ecfg, cpu, load_views=partial(load_view_set, scene, depth=False))
    assert again.names == held and again.scale == pytest.approx(rep.std_scale, rel=1e-5)
    # the maximum-likelihood factor of a Gaussian on those maps: s^2 = mean((error / max(std, floor))^2) over every
    # pixel and channel of the views, so the z-scores divided by s have a unit second moment
    aside = load_view_set(scene, scene.split["calibration"], depth=False)
    assert len(rendered) == len(held)
    z = []
    for j, (maps, _) in enumerate(rendered):
        zj = (maps.rgb_mean[0].clamp(0, 1) - aside.images[j]) / maps.rgb_std[0].clamp_min(ecfg.std_floor)
        z.append((zj[aside.masks[j][..., 0]] if aside.masks is not None else zj).reshape(-1).double())
    assert again.scale == pytest.approx(float(torch.cat(z).square().mean()) ** 0.5, rel=1e-5)
    assert rep.degrees_of_freedom is not None and again.dof == pytest.approx(rep.degrees_of_freedom, rel=1e-5)



def test_on_training_views_the_factor_is_fitted_without_the_resolution_term(tiny_run_path, monkeypatch):
    """The resolution term stands for what the training images cannot show, so the factor fitted on training views
    leaves it out (``resolution_on_training_views`` keeps it); on views set aside it stays: they are new views."""
    from uncertsplat.eval import engine

    loaded = load_run(tiny_run_path, "cpu")
    scene = loaded.load_scene()
    cpu = torch.device("cpu")
    used = []
    terms = engine.predictive_terms

    def watched(sampler, cfg, cams, **kwargs):
        used.append(cfg.resolution)
        return terms(sampler, cfg, cams, **kwargs)

    monkeypatch.setattr(engine, "predictive_terms", watched)
    views = partial(load_view_set, scene, depth=False)
    ecfg = EvalConfig(num_samples=2, calibration_views=2, residual_views=0, consistency_views=0)
    assert ecfg.resolution > 0 and not ecfg.resolution_on_training_views
    sampler = loaded.sampler(scene.scene_scale, cpu)
    train = list(scene.split["train"])
    without = fit_std_scale(sampler, {"train": train}, ecfg, cpu, load_views=views)
    assert used == [0.0, 0.0]
    used.clear()
    kept = fit_std_scale(sampler, {"train": train}, ecfg.model_copy(update={"resolution_on_training_views": True}),
                         cpu, load_views=views)
    assert used == [ecfg.resolution] * 2
    assert without.scale > kept.scale  # (the term only adds variance: without it the std is narrower)
    used.clear()
    # a noise level fitted on the training views was fitted given the term: the factor keeps it; without a noise
    # (residual_views=0) nothing was fitted given it, and a noise of a set level was not fitted at all
    fit = ecfg.model_copy(update={"residual_scale": "fit"})
    assert fit_std_scale(sampler, {"train": train}, fit, cpu, load_views=views).scale == without.scale
    assert used == [0.0, 0.0]
    used.clear()
    for scale, kept_term in (("fit", True), (1.0, False), (0.5, False)):
        noisy = ecfg.model_copy(update={"residual_scale": scale, "residual_views": 2})
        field = fit_residual(loaded.sampler(scene.scene_scale, cpu), train, noisy, cpu, load_views=views)
        used.clear()
        fit_std_scale(dataclasses.replace(sampler, residual=field), {"train": train}, noisy, cpu, load_views=views)
        assert used == ([ecfg.resolution] if kept_term else [0.0]) * 2, scale
    used.clear()
    aside = fit_std_scale(sampler, {"train": train[2:], "calibration": train[:2]}, ecfg, cpu, load_views=views)
    assert used == [ecfg.resolution] * 2 and aside.names == [scene.cameras.image_names[i] for i in train[:2]]


def test_the_noise_level_is_fitted_on_the_views_set_aside_from_training(tiny_run_path):
    """``residual_scale = "fit"`` with views set aside fits the noise's level on them: noisier set-aside images give a
    larger level, and without them the level comes from the training views alone (the set-aside images unread);
    ``"auto"`` fits it the same way on views set aside and leaves it at 1 without them."""
    cpu = torch.device("cpu")
    loaded = load_run(tiny_run_path, cpu)
    scene = loaded.load_scene()
    train, aside = list(scene.split["train"])[:-2], list(scene.split["train"])[-2:]
    cfg = EvalConfig(residual_views=4, residual_scale="fit", resolution=0.0)
    plain = partial(load_view_set, scene, depth=False)
    g = torch.Generator().manual_seed(0)
    noise = {i: torch.randn(96, 128, 3, generator=g) * 0.1 for i in aside}
    read: list[int] = []

    def noisy(indices):
        views = plain(indices)
        read.extend(i for i in indices if i in noise)
        images = torch.stack([(im + noise[i]).clamp(0, 1) if i in noise else im
                              for i, im in zip(indices, views.images, strict=True)])
        return dataclasses.replace(views, images=images)

    def level(load, calibration):
        return fit_residual(loaded.sampler(scene.scene_scale, cpu), train, cfg, cpu, load_views=load,
                            calibration_indices=calibration).scale

    clean, dirty = level(plain, aside), level(noisy, aside)
    assert dirty > 2 * clean
    read.clear()
    assert level(noisy, ()) == pytest.approx(level(plain, ()), rel=1e-9) and not read
    cfg = EvalConfig(residual_views=4, resolution=0.0)  # "auto": fitted on the views set aside, else 1
    assert cfg.residual_scale == "auto"
    assert level(plain, aside) == pytest.approx(clean, rel=1e-9) and level(plain, ()) == 1.0


def test_the_level_on_views_set_aside_is_fitted_given_the_rest_of_the_predictive(tiny_run_path, monkeypatch):
    """On views set aside the noise's level is the maximum-likelihood one given the samples' spread and the other terms
    ``evaluate`` adds there: with that rest counted it is lower than with nothing else in the predictive."""
    from uncertsplat.eval import engine

    cpu = torch.device("cpu")
    loaded = load_run(tiny_run_path, cpu)
    scene = loaded.load_scene()
    train, aside = list(scene.split["train"])[:-2], list(scene.split["train"])[-2:]
    cfg = EvalConfig(residual_views=4, residual_scale="fit", resolution=0.0, num_samples=4)
    views = partial(load_view_set, scene, depth=False)

    def level():
        return fit_residual(loaded.sampler(scene.scene_scale, cpu), train, cfg, cpu, load_views=views,
                            calibration_indices=aside).scale

    given_rest = level()
    rest = engine._rest_of_predictive(loaded.sampler(scene.scene_scale, cpu), cfg,
                                      scene.cameras[aside], aside, cpu)(scene.cameras[[aside[1]]])
    assert rest.shape == (1, scene.cameras.height, scene.cameras.width, 1) and float(rest.mean()) > 0
    monkeypatch.setattr(engine, "_rest_of_predictive", lambda *a: lambda cam: torch.zeros(1, 1, 1, 1))
    assert given_rest < level()


def test_the_std_factor_reuses_the_samples_the_noise_level_was_fitted_with(tiny_run_path, monkeypatch):
    """With views set aside, ``fit_residual`` renders their K samples to fit the noise's level; ``fit_std_scale`` given
    those maps adds the pixel noise and the view-consistency term to them instead of rendering the samples again,
    and fits the same factor."""
    from uncertsplat.uncertainty import mc

    cpu = torch.device("cpu")
    loaded = load_run(tiny_run_path, cpu)
    scene = loaded.load_scene()
    train, aside = list(scene.split["train"])[:-2], list(scene.split["train"])[-2:]
    split = {"train": train, "calibration": aside}
    cfg = EvalConfig(residual_views=4, num_samples=3, consistency_views=4)
    views = partial(load_view_set, scene, depth=False)
    kept: dict = {}
    field = fit_residual(loaded.sampler(scene.scene_scale, cpu), train, cfg, cpu, load_views=views,
                         calibration_indices=aside, set_aside_maps=kept)
    assert sorted(kept) == sorted(aside)
    assert all(m.shape == s.shape == (1, scene.cameras.height, scene.cameras.width, 3) for m, s in kept.values())
    sampler = with_side_terms(loaded.sampler(scene.scene_scale, cpu), field, scene.cameras[train], cfg, cpu)
    assert sampler.consistency is not None and sampler.residual is not None
    rendered = fit_std_scale(sampler, split, cfg, cpu, load_views=views)
    calls = []
    real = mc.mc_render
    monkeypatch.setattr(mc, "mc_render", lambda *a, **k: calls.append(1) or real(*a, **k))
    reused = fit_std_scale(sampler, split, cfg, cpu, load_views=views, set_aside_maps=kept)
    assert calls == [] and reused.names == [scene.cameras.image_names[i] for i in aside]
    assert reused.scale == pytest.approx(rendered.scale, rel=1e-5)
    assert (reused.dof is None) == (rendered.dof is None)
    if reused.dof is not None:
        assert reused.dof == pytest.approx(rendered.dof, rel=1e-3)
    # a view the maps lack is rendered as before
    partial_maps = {aside[0]: kept[aside[0]]}
    assert fit_std_scale(sampler, split, cfg, cpu, load_views=views,
                         set_aside_maps=partial_maps).scale == pytest.approx(rendered.scale, rel=1e-5)
    assert calls == [1]


def test_no_std_scale_when_disabled_or_scoring_training_views(tiny_run_path, tmp_path, capsys):
    run = tmp_path / "run"
    shutil.copytree(tiny_run_path, run)
    off = evaluate.run(run, EvalConfig(num_samples=2, max_views=1, calibration_views=0), device=torch.device("cpu"))
    assert "calibration_views = 0 or none to use" in " ".join(capsys.readouterr().err.split())
    held_out = (run / "eval" / "metrics.json").read_bytes()
    on_train = evaluate.run(run, EvalConfig(num_samples=2, max_views=1, split="train"), device=torch.device("cpu"))
    said = " ".join(capsys.readouterr().err.split())
    assert "no std factor or tails are fitted when the training views are the ones scored" in said
    assert "calibration_views = 0" not in said
    for rep in (off, on_train):
        assert rep.std_scale is None and rep.calibration_views == [] and rep.mean.nll_calibrated is None
    # the training views' scores go beside the held-out evaluation, which stays as it was (report and prune read it)
    assert (run / "eval" / "metrics.json").read_bytes() == held_out
    assert EvalReport.read(run / "eval-train" / "metrics.json").split == "train"
    assert len(list((run / "eval-train" / "maps").glob("*.exr"))) == 1


def test_given_depth_gt_folder_estimates_scale(tiny_run_path, tiny_scene_path, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(tiny_run_path, run)
    rep = evaluate.run(run, EvalConfig(num_samples=2, depth_gt=tiny_scene_path / "depth", max_views=2),
                       device=torch.device("cpu"))
    # GT is in the generator's units; the run is normalised, so the estimated scale undoes that
    meta = json.loads((tiny_scene_path / "scene.json").read_text(encoding="utf-8"))
    assert rep.depth_scale.method == "median"
    assert rep.depth_scale.scale > 0 and np.isfinite(rep.depth_scale.scale)
    assert meta  # the scene records its generator settings
    # the factor takes the run's depth to the folder's (the scene's own) units: 1 / s of the run's world_from_source
    # (s is ~0.25 here; a short run's depths are a few per cent off, so the median ratio is too)
    world_from_source = json.loads((run / "scene.json").read_text(encoding="utf-8"))["world_from_source"]
    assert rep.depth_scale.scale == pytest.approx(1.0 / world_from_source[0][0], rel=0.15)


def test_the_depth_nll_of_gt_maps_in_other_units_moves_by_the_log_of_the_unit_alone(tiny_run_path, tiny_scene_path,
                                                                                     tmp_path):
    """The same GT maps written in km (x0.001): every depth length scales, so the depth NLL moves by ln 0.001 and
    nothing more (its std floor was taken in the maps' units: +1.34 nats beyond that at x0.001)."""
    run = tmp_path / "run"
    shutil.copytree(tiny_run_path, run)
    km = tmp_path / "depth_km"
    km.mkdir()
    for p in (tiny_scene_path / "depth").glob("*.npy"):
        np.save(km / p.name, np.load(p) * 1e-3)
    cfg = dict(num_samples=2, max_views=2, save_maps=False, reuse=False)
    base = evaluate.run(run, EvalConfig(**cfg, depth_gt=tiny_scene_path / "depth"), device=torch.device("cpu"))
    small = evaluate.run(run, EvalConfig(**cfg, depth_gt=km), device=torch.device("cpu"))
    assert small.depth_scale.scale == pytest.approx(base.depth_scale.scale * 1e-3, rel=1e-5)
    assert small.mean.depth_rmse == pytest.approx(base.mean.depth_rmse * 1e-3, rel=1e-4)
    assert small.mean.depth_nll == pytest.approx(base.mean.depth_nll + math.log(1e-3), abs=1e-3)


def test_depth_maps_with_no_usable_depth_and_depth_metrics_on_few_pixels_are_said(tiny_run_path, tiny_scene_path,
                                                                                   tmp_path):
    """Maps in nanometres (every depth >= 1e9, read as no surface) were 'no valid pixel to align depth', naming
    neither the rule nor the folder; a model pruned to a few Gaussians (a depth NLL of 20,826 on 2 pixels a view)
    gave depth metrics without a word."""
    from uncertsplat.config import PruneConfig
    from uncertsplat.stages import prune

    run = tmp_path / "run"
    shutil.copytree(tiny_run_path, run)
    nm = tmp_path / "depth_nm"
    nm.mkdir()
    for p in (tiny_scene_path / "depth").glob("*.npy"):
        np.save(nm / p.name, np.load(p) * 1e10)
    cfg = dict(num_samples=2, max_views=2, save_maps=False, reuse=False)
    with pytest.raises(UserError, match="the GT maps hold no usable depth at all: .* 1e[+]09 and above are read as "
                                        "no surface") as err:
        evaluate.run(run, EvalConfig(**cfg, depth_gt=nm), device=torch.device("cpu"))
    assert "depth_nm" in str(err.value) and "larger ones" in err.value.hint
    # the same maps with a factor given (or the scene's units): no metric came out and nothing said why
    for scale in ("scene", 2.0):
        with pytest.raises(UserError, match="no depth metric can be computed: the GT maps hold no usable depth"):
            evaluate.run(run, EvalConfig(**cfg, depth_gt=nm, depth_scale=scale), device=torch.device("cpu"))
    base = evaluate.run(run, EvalConfig(**cfg), device=torch.device("cpu"))
    assert not any(n.startswith("the depth metrics rest on ") for n in base.notes)
    prune.run(run, tmp_path / "few", PruneConfig(keep_ratio=0.002, score="gate"), torch.device("cpu"))
    rep = evaluate.run(tmp_path / "few", EvalConfig(**cfg), device=torch.device("cpu"))
    assert any(n.startswith("the depth metrics rest on ") and "with a GT depth" in n for n in rep.notes), rep.notes


def test_a_depth_gt_folder_in_the_scene_s_units_and_a_factor_that_cannot_be_right(tiny_run_path, tiny_scene_path,
                                                                                    tmp_path, capsys):
    """--depth-scale scene: a folder of maps in the scene's own units (a metric COLMAP model's) is scored with the
    scene's known factor, as the scene's own GT is (no fitted factor hiding a scale error); a factor given that
    leaves the GT 4x the render (--depth-scale 1 on such maps) is said, and the metrics are that factor's."""
    run = tmp_path / "run"
    shutil.copytree(tiny_run_path, run)
    own = evaluate.run(run, EvalConfig(num_samples=2, max_views=2, save_maps=False), device=torch.device("cpu"))
    folder = evaluate.run(run, EvalConfig(num_samples=2, max_views=2, save_maps=False, depth_scale="scene",
                                          depth_gt=tiny_scene_path / "depth"), device=torch.device("cpu"))
    assert own.depth_scale.method == folder.depth_scale.method == "scene" and folder.depth_scale.scale == 1.0
    assert folder.mean.depth_rmse == pytest.approx(own.mean.depth_rmse, rel=1e-5)
    assert not any("probably in other units" in n for n in folder.notes)
    capsys.readouterr()
    one = evaluate.run(run, EvalConfig(num_samples=2, max_views=2, save_maps=False, depth_scale=1.0,
                                       depth_gt=tiny_scene_path / "depth"), device=torch.device("cpu"))
    (note,) = [n for n in one.notes if "probably in other units" in n]
    assert note.startswith("with the depth factor given (1), the GT depth is 4.")  # 1 / the scene's 0.247
    assert "(maps in the scene's own units: --depth-scale scene;" in note  # the factor named, as a robotics user needed
    # on the console too (it was in metrics.json and the report only)
    assert "warning: with the depth factor given (1), the GT depth is 4." in " ".join(capsys.readouterr().err.split())
    assert one.depth_scale.method == "given" and one.mean.depth_abs_rel > 0.5
    own_given = evaluate.run(run, EvalConfig(num_samples=2, max_views=2, save_maps=False, depth_scale=1.0),
                             device=torch.device("cpu"))  # the scene's own GT (normalised units): said so
    assert own_given.depth_scale.method == "given-scene"
    assert own_given.mean.depth_rmse == pytest.approx(own.mean.depth_rmse, rel=1e-5)
    # a wrong factor on the scene's own GT (in the run's units: 1 is right) names no power of the scene's units
    off = evaluate.run(run, EvalConfig(num_samples=2, max_views=2, save_maps=False, depth_scale=40.0),
                       device=torch.device("cpu"))
    (note,) = [n for n in off.notes if "probably in other units" in n]
    assert "the scene's own GT depth is in the run's units already: leave --depth-scale out, or give 1" in note
    assert "--depth-scale auto fits" not in note and "the run's depth to the maps' units" not in note
    assert "the depth metrics are in the run's normalised units: x 4." in " ".join(capsys.readouterr().err.split())


def test_cli_missing_run_is_clear(tmp_path):
    result = runner.invoke(app, ["evaluate", str(tmp_path / "nope"), "--device", "cpu"])
    assert result.exit_code == 2
    assert "run folder not found" in result.output and "Traceback" not in result.output


def test_cli_not_a_run(tmp_path):
    result = runner.invoke(app, ["evaluate", str(tmp_path), "--device", "cpu"])
    assert result.exit_code == 2 and "config.json is missing" in result.output


def test_cli_an_evaluation_folder_names_its_run(evaluated):
    """RUN/eval holds a config.json too (evaluate's): one line that points to RUN, not 25 unknown keys."""
    run, _ = evaluated
    result = runner.invoke(app, ["evaluate", str(run / "eval"), "--device", "cpu"])
    assert result.exit_code == 2 and "another command's" in result.output, result.output
    assert str(run.resolve()) in result.output.replace("\n", "") and "unknown key" not in result.output


def test_the_pixel_noise_level_is_fitted_and_recorded(tiny_run_path, tmp_path):
    """``residual_scale``: "fit" records the maximum-likelihood factor and scales the noise by it (a given factor is
    used as given; without the pixel-noise term there is none)."""
    run = tmp_path / "run"
    shutil.copytree(tiny_run_path, run)
    base = {"num_samples": 2, "max_views": 1, "calibration_views": 0}
    cpu = torch.device("cpu")
    fit = evaluate.run(run, EvalConfig(**base, residual_scale="fit"), device=cpu)
    one = evaluate.run(run, EvalConfig(**base), device=cpu)
    half = evaluate.run(run, EvalConfig(**base, residual_scale=0.5), device=cpu)
    leverage = evaluate.run(run, EvalConfig(**base, residual_leverage=True), device=cpu)  # an old config's bool
    plain = evaluate.run(run, EvalConfig(**base, residual_leverage="none"), device=cpu)
    none = evaluate.run(run, EvalConfig(**base, residual_views=0), device=cpu)
    assert fit.noise_scale is not None and fit.noise_scale > 0 and fit.noise_scale != 1.0
    assert (one.noise_scale, half.noise_scale, none.noise_scale) == (1.0, 0.5, None)
    assert json.loads((run / "eval" / "metrics.json").read_text(encoding="utf-8"))["noise_scale"] is None  # the last run's
    name = next(iter(one.per_view))
    assert half.per_view[name].nll != one.per_view[name].nll
    # the leverage changes the std (each Gaussian's noise / (1 - h)), not the prediction; the default is relative to
    # the median Gaussian's (on this tiny run it may raise no Gaussian: the arithmetic is tested in test_residual.py)
    assert EvalConfig(residual_leverage=True).residual_leverage == "full"
    assert EvalConfig(residual_leverage=False).residual_leverage == "none" and EvalConfig().residual_leverage == "relative"
    assert leverage.per_view[name].psnr == one.per_view[name].psnr == plain.per_view[name].psnr
    assert leverage.per_view[name].nll != one.per_view[name].nll
    assert any("leverage (relative) by a factor" in n for n in one.notes)
    assert any("leverage (full) by a factor" in n for n in leverage.notes)
    assert not any("leverage" in n for n in plain.notes)


ONE_VIEW = {"num_samples": 2, "max_views": 1, "calibration_views": 0}


def _off_and_on(tiny_run_path, tmp_path, key):
    """(run, report with ``key`` off, report with it on): one view of a copy of the tiny run, evaluated both ways."""
    run = tmp_path / "run"
    shutil.copytree(tiny_run_path, run)
    cpu = torch.device("cpu")
    off = evaluate.run(run, EvalConfig(**ONE_VIEW, **{key: False}), device=cpu)
    on = evaluate.run(run, EvalConfig(**ONE_VIEW, **{key: True}), device=cpu)
    return run, off, on


def test_the_edge_term_is_fitted_recorded_and_changes_only_the_std(tiny_run_path, tmp_path):
    """``edge_noise``: delta^2 is fitted on the training views, recorded in metrics.json and named in the notes; the
    prediction is unchanged and the std is not; off, the report records 0."""
    run, off, on = _off_and_on(tiny_run_path, tmp_path, "edge_noise")
    assert off.edge_scale == 0.0 and on.edge_scale is not None and on.edge_scale > 0.0
    assert json.loads((run / "eval" / "metrics.json").read_text(encoding="utf-8"))["edge_scale"] == on.edge_scale
    assert any("edge term" in n for n in on.notes) and not any("edge term" in n for n in off.notes)
    name = next(iter(on.per_view))
    assert on.per_view[name].psnr == off.per_view[name].psnr
    assert on.per_view[name].ause_mae != off.per_view[name].ause_mae
    none = evaluate.run(run, EvalConfig(**ONE_VIEW, residual_views=0, edge_noise=True), device=torch.device("cpu"))
    assert none.edge_scale is None


def test_the_depth_spread_widens_the_depth_std_only(tiny_run_path, tmp_path):
    """``depth_spread``: the variance of the depths each ray blends joins the depth variance (named in the notes);
    the RGB metrics are those without it, and the depth NLL changes."""
    _, off, on = _off_and_on(tiny_run_path, tmp_path, "depth_spread")
    name = next(iter(on.per_view))
    a, b = off.per_view[name], on.per_view[name]
    assert (a.psnr, a.ause_mae, a.nll) == (b.psnr, b.ause_mae, b.nll)
    assert a.depth_nll is not None and b.depth_nll is not None and b.depth_nll != a.depth_nll
    assert any("depths each ray blends" in n for n in on.notes) and not any("depths each ray" in n for n in off.notes)


def test_more_resolution_renders_change_the_std_only(tiny_run_path, tmp_path):  # noqa: F811
    """``resolution_renders``: the resolution term's variance from more renders per sample (named in the notes); the
    prediction is the samples' mean either way."""
    run = tmp_path / "run"
    shutil.copytree(tiny_run_path, run)
    cpu = torch.device("cpu")
    one = evaluate.run(run, EvalConfig(**ONE_VIEW, resolution_renders=1), device=cpu)
    three = evaluate.run(run, EvalConfig(**ONE_VIEW, resolution_renders=3), device=cpu)
    name = next(iter(one.per_view))
    assert one.per_view[name].psnr == three.per_view[name].psnr
    assert one.per_view[name].ause_mae != three.per_view[name].ause_mae
    assert any("1 render per sample" in n for n in one.notes) and any("3 renders per sample" in n for n in three.notes)


SAME_CFG = EvalConfig(num_samples=2, max_views=1, calibration_views=0, residual_views=2)


@pytest.fixture(scope="module")
def same_model_runs(tiny_run_path, tmp_path_factory):  # noqa: F811
    from uncertsplat.config import PruneConfig
    from uncertsplat.stages import prune

    root = tmp_path_factory.mktemp("same")
    src = root / "src"
    shutil.copytree(tiny_run_path, src, ignore=shutil.ignore_patterns("eval"))
    kept = root / "kept"
    prune.run(src, kept, PruneConfig(keep_ratio=1.0, num_samples=2, score_views=2, score_samples=2,
                                     render_views=1), device=torch.device("cpu"))
    assert (kept / "variational.ply").read_bytes() == (src / "variational.ply").read_bytes()
    evaluate.run(src, SAME_CFG, device=torch.device("cpu"))
    return src, kept



def _copied_deeper(kept: Path, tmp_path: Path) -> Path:
    """A copy of the run ``kept`` (without its evaluation) two folders deeper, its scene.json's relative path to the
    scene rewritten for its new place: the same model and config, another scene.json."""
    deeper = tmp_path / "a" / "b" / "kept"
    deeper.parent.mkdir(parents=True)
    shutil.copytree(kept, deeper, ignore=shutil.ignore_patterns("eval"))
    info = json.loads((deeper / "scene.json").read_text(encoding="utf-8"))
    info["scene_from_run"] = os.path.relpath(info["scene"], deeper)
    (deeper / "scene.json").write_text(json.dumps(info))
    return deeper

class TestPrunedRunThatRemovedNothing:
    """A prune output whose model is its source's file, unchanged: evaluate copies the source's evaluation when it
    was made with the same settings, and evaluates anything else."""

    def test_copies_the_source_evaluation(self, same_model_runs):
        src, kept = same_model_runs
        report = evaluate.run(kept, SAME_CFG, device=torch.device("cpu"))
        source = EvalReport.read(src / "eval" / "metrics.json")
        copied = EvalReport.read(kept / "eval" / "metrics.json")
        assert copied == report
        assert copied.model_copy(update={"notes": source.notes}) == source  # every number the source's
        assert copied.notes[:-1] == source.notes and "copied from" in copied.notes[-1]
        for f in sorted((src / "eval" / "maps").iterdir()):
            assert (kept / "eval" / "maps" / f.name).read_bytes() == f.read_bytes()
        copied_files = sorted(p.name for p in (kept / "eval").iterdir())
        assert copied_files == ["config.json", "maps", "metrics.json", "predictive.pt", "residual.pt"]
        assert evaluate.same_model_evaluation(kept, SAME_CFG, torch.device("cpu")) == src / "eval"

    def test_a_copy_in_another_folder_is_this_run_s_current_evaluation(self, same_model_runs, tmp_path):
        """A prune written one folder deeper records the scene's path relative to itself, so its scene.json is not
        the source's byte for byte: the copied metrics carried the source's run_sha256, and the report called the
        evaluation one of an earlier state of the run (a review)."""
        from uncertsplat.stages.evaluate import evaluation_is_current

        src, kept = same_model_runs
        deeper = _copied_deeper(kept, tmp_path)
        assert (deeper / "scene.json").read_bytes() != (src / "scene.json").read_bytes()
        assert evaluate.same_model_evaluation(deeper, SAME_CFG, torch.device("cpu")) == src / "eval"
        report = evaluate.run(deeper, SAME_CFG, device=torch.device("cpu"))
        assert "copied from" in report.notes[-1]
        assert evaluation_is_current(deeper, EvalReport.read(deeper / "eval" / "metrics.json"))

    def test_a_copy_carries_the_noise_and_predictive_keyed_for_this_run(self, same_model_runs, tmp_path):
        """The copy left the source's predictive.pt out (Predictor.load of the pruned run, its scene gone: "predictive.pt
        is missing", though the hint said evaluate keeps it), and its residual.pt kept the source's key, which a run
        one folder deeper (another scene.json) never matches: the noise was fitted again."""
        from uncertsplat.baselines import load_run
        from uncertsplat.stages.predictive_cache import read_predictive
        from uncertsplat.stages.residual_cache import FILE_NAME, residual_key

        src, kept = same_model_runs
        cpu = torch.device("cpu")
        deeper = _copied_deeper(kept, tmp_path)
        assert "copied from" in evaluate.run(deeper, SAME_CFG, device=cpu).notes[-1]
        loaded = load_run(deeper, cpu)
        predictive, problem = read_predictive(loaded, SAME_CFG, src)
        source_predictive, _ = read_predictive(load_run(src, cpu), SAME_CFG, src)
        assert predictive is not None, problem
        assert (predictive.scale, predictive.dof, predictive.names) == (
            source_predictive.scale, source_predictive.dof, source_predictive.names)
        from uncertsplat.io.checkpoints import decode

        noise = decode((deeper / "eval" / FILE_NAME).read_bytes())
        assert noise["key"] == residual_key(loaded, SAME_CFG, cpu)
        assert noise["key"] != decode((src / "eval" / FILE_NAME).read_bytes())["key"]  # (a scene.json of its own)

    def test_anything_else_is_evaluated(self, same_model_runs, tmp_path):
        src, kept = same_model_runs
        cpu = torch.device("cpu")
        assert evaluate.same_model_evaluation(kept, SAME_CFG.model_copy(update={"num_samples": 3}), cpu) is None
        assert evaluate.same_model_evaluation(kept, SAME_CFG.model_copy(update={"reuse": False}), cpu) is None
        assert evaluate.same_model_evaluation(src, SAME_CFG, cpu) is None  # not a prune output
        # a pruned model that differs from its source's file (here: the source's file was changed since)
        other = tmp_path / "other"
        shutil.copytree(src, other)
        changed = tmp_path / "changed"
        shutil.copytree(kept, changed, ignore=shutil.ignore_patterns("eval"))
        data = PruneReport.read(changed / "prune.json")
        data.source_run = str(other)
        data.write(changed / "prune.json")
        assert evaluate.same_model_evaluation(changed, SAME_CFG, cpu) == other / "eval"
        with open(other / "variational.ply", "ab") as f:
            f.write(b"\0")
        assert evaluate.same_model_evaluation(changed, SAME_CFG, cpu) is None
        report = evaluate.run(changed, SAME_CFG, device=cpu)
        assert not any("copied from" in n for n in report.notes)


def test_a_source_evaluated_with_reuse_off_is_copied_too(same_model_runs, tmp_path):
    """The source's evaluation made with --set reuse=false was never copied into a pruned run that kept its model (its
    config hash holds `reuse`), though `evaluate` and `prune` of the source reuse it (a review)."""
    from uncertsplat.provenance import hash_config

    src, kept = same_model_runs
    other = tmp_path / "source"
    shutil.copytree(src, other)
    used = EvalConfig.model_validate_json((other / "eval" / "config.json").read_text(encoding="utf-8"))
    used = used.model_copy(update={"reuse": False})
    (other / "eval" / "config.json").write_text(used.model_dump_json(indent=2))
    report = EvalReport.read(other / "eval" / "metrics.json")
    report.config_hash = hash_config(used.model_dump(mode="json"))
    report.write(other / "eval" / "metrics.json")
    pruned = tmp_path / "kept"
    shutil.copytree(kept, pruned, ignore=shutil.ignore_patterns("eval"))
    data = PruneReport.read(pruned / "prune.json")
    data.source_run = str(other)
    data.write(pruned / "prune.json")
    assert evaluate.same_model_evaluation(pruned, SAME_CFG, torch.device("cpu")) == other / "eval"
    other_samples = SAME_CFG.model_copy(update={"num_samples": SAME_CFG.num_samples + 1})
    assert evaluate.same_model_evaluation(pruned, other_samples, torch.device("cpu")) is None


class TestPruneReadsTheEvaluation:
    """``prune``'s "before" row: ``evaluate``'s held-out means when it scored the same model file on the same views
    with the same settings and versions (``stages.evaluate.matching_evaluation``), the same numbers it would measure."""

    CFG = dict(keep_ratio=0.9, num_samples=2, score_views=2, score_samples=2, render_views=1)

    def test_the_same_numbers_as_measuring_again(self, tiny_run_path, tmp_path):  # noqa: F811
        from uncertsplat.config import PruneConfig
        from uncertsplat.provenance import file_sha256
        from uncertsplat.stages import prune
        from uncertsplat.stages.prune import METRIC_KEYS

        run = tmp_path / "run"
        shutil.copytree(tiny_run_path, run, ignore=shutil.ignore_patterns("eval"))
        cpu = torch.device("cpu")
        measured = prune.run(run, None, PruneConfig(**self.CFG, dry_run=True), device=cpu)
        assert not any("evaluate's" in n for n in measured.notes)
        report = evaluate.run(run, EvalConfig(num_samples=2), device=cpu)
        assert report.run_sha256 == evaluate.run_sha256(run, run / "variational.ply")
        assert report.run_sha256 != file_sha256(run / "variational.ply")  # the run's config and scene count too
        assert EvalReport.read(run / "eval" / "metrics.json").run_sha256 == report.run_sha256
        read = prune.run(run, None, PruneConfig(**self.CFG, dry_run=True), device=cpu)
        assert any("evaluate's" in n and "metrics.json" in n for n in read.notes)
        for k in METRIC_KEYS:  # what measuring gives, to the last digit
            assert getattr(read.metrics.before, k) == getattr(measured.metrics.before, k), k
        assert read.metrics.before.psnr_render == measured.metrics.before.psnr_render
        assert read.metrics.after == measured.metrics.after.model_copy(update={"seconds": read.metrics.after.seconds})

    def test_anything_else_is_measured(self, tiny_run_path, tmp_path):  # noqa: F811
        from uncertsplat.config import PruneConfig
        from uncertsplat.stages import prune
        from uncertsplat.stages.evaluate import matching_evaluation

        run = tmp_path / "run"
        shutil.copytree(tiny_run_path, run, ignore=shutil.ignore_patterns("eval"))
        cpu = torch.device("cpu")
        evaluate.run(run, EvalConfig(num_samples=3), device=cpu)  # another K than prune's
        read = prune.run(run, None, PruneConfig(**self.CFG, dry_run=True), device=cpu)
        assert not any("evaluate's" in n for n in read.notes)
        model = run / "variational.ply"
        names = EvalReport.read(run / "eval" / "metrics.json").image_names
        cfg = EvalConfig(num_samples=3)
        assert matching_evaluation(run, model, cfg, names, cpu) is not None
        assert matching_evaluation(run, model, cfg.model_copy(update={"save_maps": False, "reuse": False}), names,
                                   cpu) is not None  # what is written, not what is measured
        assert matching_evaluation(run, model, cfg.model_copy(update={"resolution": 0.2}), names, cpu) is None
        assert matching_evaluation(run, model, cfg, names[:1], cpu) is None
        assert matching_evaluation(run, model, cfg, names, torch.device("meta")) is None
        # a report of an older version (no model recorded), and one of another model file
        data = EvalReport.read(run / "eval" / "metrics.json")
        data.model_copy(update={"run_sha256": None}).write(run / "eval" / "metrics.json")
        assert matching_evaluation(run, model, cfg, names, cpu) is None
        data.model_copy(update={"run_sha256": "0" * 64}).write(run / "eval" / "metrics.json")
        assert matching_evaluation(run, model, cfg, names, cpu) is None
        data.write(run / "eval" / "metrics.json")
        assert matching_evaluation(run, model, cfg, names, cpu) is not None
        scene_json = (run / "scene.json").read_bytes()  # the run's files changed since it was evaluated
        (run / "scene.json").write_bytes(scene_json + b"\n")
        assert matching_evaluation(run, model, cfg, names, cpu) is None
        (run / "scene.json").write_bytes(scene_json)
        assert matching_evaluation(run, model, cfg, names, cpu) is not None
        # the settings file and the report disagree (written by different runs)
        (run / "eval" / "config.json").write_text(EvalConfig(num_samples=2).model_dump_json())
        assert matching_evaluation(run, model, EvalConfig(num_samples=2), names, cpu) is None
        (run / "eval" / "config.json").write_text("{not json")
        assert matching_evaluation(run, model, cfg, names, cpu) is None


class TestResidualCache:
    """``RUN/eval/residual.pt``: evaluate keeps the fitted pixel noise under a key of the model and the settings it
    depends on; the next evaluate or prune of the same model with those settings reads it and gets the same numbers."""

    def test_read_back_gives_the_same_evaluation(self, tiny_run_path, tmp_path, monkeypatch, capsys):  # noqa: F811
        from uncertsplat.eval import engine
        from uncertsplat.stages.residual_cache import FILE_NAME

        run = tmp_path / "run"
        shutil.copytree(tiny_run_path, run, ignore=shutil.ignore_patterns("eval"))
        cpu = torch.device("cpu")
        first = evaluate.run(run, EvalConfig(**ONE_VIEW), device=cpu)
        assert (run / "eval" / FILE_NAME).is_file()
        assert "pixel noise: fitted on" in capsys.readouterr().err
        fits = []
        real = engine.fit_residual
        monkeypatch.setattr(engine, "fit_residual", lambda *a, **k: fits.append(1) or real(*a, **k))
        again = evaluate.run(run, EvalConfig(**ONE_VIEW, reuse=False), device=cpu)  # read back: no fit
        assert fits == []
        assert "pixel noise: read from" in capsys.readouterr().err  # the user is told which
        name = next(iter(first.per_view))
        assert again.per_view[name].model_dump(exclude={"seconds"}) == first.per_view[name].model_dump(
            exclude={"seconds"})
        evaluate.run(run, EvalConfig(**{**ONE_VIEW, "num_samples": 3}), device=cpu)  # not a setting the noise reads
        assert fits == []
        evaluate.run(run, EvalConfig(**ONE_VIEW, resolution=0.2), device=cpu)  # one it reads: fitted again
        assert fits == [1]
        (run / "eval" / FILE_NAME).write_bytes(b"not a torch file")  # unreadable: fitted again, replaced
        evaluate.run(run, EvalConfig(**ONE_VIEW, reuse=False), device=cpu)
        assert fits == [1, 1]
        evaluate.run(run, EvalConfig(**ONE_VIEW, reuse=False), device=cpu)
        assert fits == [1, 1]

    def test_an_evaluation_already_there_is_kept(self, tiny_run_path, tmp_path, monkeypatch, capsys):  # noqa: F811
        from uncertsplat.eval import engine

        run = tmp_path / "run"
        shutil.copytree(tiny_run_path, run, ignore=shutil.ignore_patterns("eval"))
        cpu = torch.device("cpu")
        first = evaluate.run(run, EvalConfig(**ONE_VIEW), device=cpu)
        capsys.readouterr()
        calls = []
        real = engine.evaluate_views
        monkeypatch.setattr(engine, "evaluate_views", lambda *a, **k: calls.append(1) or real(*a, **k))
        again = evaluate.run(run, EvalConfig(**ONE_VIEW), device=cpu)  # the same settings: kept
        assert calls == [] and again == first
        assert "already evaluated with these settings" in " ".join(capsys.readouterr().err.split())
        evaluate.run(run, EvalConfig(**ONE_VIEW, preview="fixed"), device=cpu)  # other previews: evaluated again
        assert calls == [1]
        next(iter((run / "eval" / "maps").glob("*.exr"))).unlink()  # a map gone: evaluated again
        evaluate.run(run, EvalConfig(**ONE_VIEW, preview="fixed"), device=cpu)
        assert calls == [1, 1]
        evaluate.run(run, EvalConfig(**ONE_VIEW, preview="fixed", reuse=False), device=cpu)
        assert calls == [1, 1, 1]

    def test_prune_reads_it_and_leaves_the_source_alone(self, tiny_run_path, tmp_path, monkeypatch):  # noqa: F811
        from uncertsplat.config import PruneConfig
        from uncertsplat.eval import engine
        from uncertsplat.stages import prune
        from uncertsplat.stages.residual_cache import FILE_NAME, residual_key

        run = tmp_path / "run"
        shutil.copytree(tiny_run_path, run, ignore=shutil.ignore_patterns("eval"))
        cpu = torch.device("cpu")
        cfg = PruneConfig(keep_ratio=0.9, num_samples=2, score_views=2, score_samples=2, render_views=1)
        fits = []
        real = engine.fit_residual
        monkeypatch.setattr(engine, "fit_residual", lambda *a, **k: fits.append(1) or real(*a, **k))
        # nothing to read: fitted, and nothing written to the source; the pruned run it writes is evaluated there,
        # with a fit of its own model's noise
        prune.run(run, tmp_path / "p0", cfg, device=cpu)
        assert fits == [1, 1] and not (run / "eval" / FILE_NAME).exists()
        assert (tmp_path / "p0" / "eval" / FILE_NAME).is_file()
        evaluate.run(run, EvalConfig(**ONE_VIEW), device=cpu)
        assert fits == [1, 1, 1]
        cached = (run / "eval" / FILE_NAME).read_bytes()
        first = PruneReport.read(tmp_path / "p0" / "prune.json")
        second = prune.run(run, tmp_path / "p1", cfg, device=cpu)
        assert fits == [1, 1, 1, 1]  # the source's read, not fitted; the new pruned run's fitted
        assert (run / "eval" / FILE_NAME).read_bytes() == cached
        assert second.metrics.after.ause_mae == first.metrics.after.ause_mae
        assert second.metrics.before.nll == first.metrics.before.nll
        # the key: the model file, the settings the noise reads, the device type
        loaded = load_run(run, cpu)
        key = residual_key(loaded, EvalConfig(), cpu)
        assert key == residual_key(loaded, EvalConfig(num_samples=3, max_views=1), cpu)
        for change in ({"edge_noise": False}, {"residual_views": 3}, {"seed": 1}, {"colour_posterior": False}):
            assert residual_key(loaded, EvalConfig(**change), cpu) != key
        assert residual_key(loaded, EvalConfig(), torch.device("meta")) != key
        # with views set aside the noise's level is fitted given the K samples and the other terms: they count too
        aside = residual_key(loaded, EvalConfig(), cpu, set_aside=True)
        assert aside != key and aside == residual_key(loaded, EvalConfig(max_views=1), cpu, set_aside=True)
        for change in ({"num_samples": 3}, {"empty_rays": False}, {"resolution_renders": 1}):
            assert residual_key(loaded, EvalConfig(**change), cpu, set_aside=True) != aside
            assert residual_key(loaded, EvalConfig(**change), cpu) == key


def test_the_predictive_tails_follow_the_setting(tiny_run_path, monkeypatch):
    """``degrees_of_freedom``: "fit" fits nu on the views the std factor is fitted on, "gaussian" gives none, a number
    is kept, and without views to fit on "fit" falls back to the Gaussian while a number still holds."""
    cpu = torch.device("cpu")
    loaded = load_run(tiny_run_path, cpu)
    scene = loaded.load_scene()
    views = partial(load_view_set, scene, depth=False)
    cfg = EvalConfig(num_samples=2, residual_views=0, consistency_views=0, calibration_views=2)
    sampler = loaded.sampler(scene.scene_scale, cpu)
    fitted = fit_std_scale(sampler, scene.split, cfg, cpu, load_views=views)
    assert fitted.dof is not None and 2.1 <= fitted.dof and len(fitted.names) == 2
    # nu from a strided share of the z-scores when there are many; the factor still from all of them
    from uncertsplat.eval import tails

    seen = []
    fit_dof = tails.fit_dof
    monkeypatch.setattr(tails, "fit_dof", lambda z: seen.append(z.numel()) or fit_dof(z))
    fit_std_scale(sampler, scene.split, cfg, cpu, load_views=views)
    monkeypatch.setattr(tails, "FIT_ELEMENTS", 5000)
    strided = fit_std_scale(sampler, scene.split, cfg, cpu, load_views=views)
    assert strided.scale == pytest.approx(fitted.scale, rel=1e-9) and strided.dof is not None
    every, kept = seen
    assert every > 2 * 5000 and 0.9 * 5000 < kept <= 5000  # each view strided alike: at most FIT_ELEMENTS in all
    assert strided.dof == pytest.approx(fitted.dof, rel=0.5)
    monkeypatch.undo()
    assert fit_std_scale(sampler, scene.split, cfg.model_copy(update={"degrees_of_freedom": "gaussian"}), cpu,
                         load_views=views).dof is None
    fixed = cfg.model_copy(update={"degrees_of_freedom": 5.0})
    assert fit_std_scale(sampler, scene.split, fixed, cpu, load_views=views).dof == 5.0
    none = cfg.model_copy(update={"calibration_views": 0})
    assert fit_std_scale(sampler, scene.split, none, cpu, load_views=views) == StdFit()
    assert fit_std_scale(sampler, scene.split, fixed.model_copy(update={"calibration_views": 0}), cpu,
                         load_views=views).dof == 5.0
    with pytest.raises(ValueError):
        EvalConfig(degrees_of_freedom=2.0)


def test_the_intervals_example_reads_the_predictive_from_the_maps(evaluated, capsys, monkeypatch):
    """``examples/intervals.py`` builds each view's interval from its EXR alone (the std and the header's nu) and
    writes its bounds, the lower below the upper."""
    import runpy
    import sys
    from pathlib import Path

    run, report = evaluated
    monkeypatch.setattr(sys, "argv", ["intervals.py", str(run), "0.9"])
    runpy.run_path(str(Path(__file__).resolve().parents[2] / "examples" / "intervals.py"), run_name="__main__")
    printed = capsys.readouterr().out
    assert printed.count("Student-t") == len(report.image_names) and "nominal 90.0 %" in printed
    bounds = read_exr(run / "example_intervals" / f"{map_stem(report.image_names[0])}.exr")
    assert np.all(bounds["lower.R"] <= bounds["upper.R"])


@pytest.mark.parametrize("script, args, expect", [
    ("uncertainty_map.py", ["view_999.png"], "no held-out view 'view_999.png'"),
    ("uncertainty_map.py", ["10"], "no held-out view '10'"),
    ("intervals.py", [], "metrics.json"),
    ("evaluate_run.py", ["many"], "python examples/evaluate_run.py RUN [K]"),
    ("evaluate_run.py", ["0"], "K must be a whole number of samples, 1 or more"),
    ("uncertainty_map.py", ["0", "0"], "K must be a whole number of samples, 1 or more, not 0"),
    ("uncertainty_map.py", ["0", "2", "extra"], "Give RUN, and optionally VIEW and K (4 arguments given)"),
    ("evaluate_run.py", ["2", "extra"], "Give RUN, and optionally K (3 arguments given)"),
    ("intervals.py", ["1.5"], "P must be a probability between 0 and 1 (exclusive), not 1.5"),
    ("intervals.py", ["abc"], "P must be a probability between 0 and 1 (exclusive), not abc"),
])
def test_the_examples_end_with_a_message_not_a_traceback(tiny_run_path, tmp_path, monkeypatch, script, args, expect):
    """What a user types wrong (a view that is not held out, a run not evaluated yet, K not a number) ends the
    example with one message naming it."""
    import runpy
    import sys
    from pathlib import Path

    run = tmp_path / "run"
    shutil.copytree(tiny_run_path, run)
    shutil.rmtree(run / "eval", ignore_errors=True)
    monkeypatch.setattr(sys, "argv", [script, str(run), *args])
    with pytest.raises(SystemExit) as e:
        runpy.run_path(str(Path(__file__).resolve().parents[2] / "examples" / script), run_name="__main__")
    assert expect in str(e.value.code)


def test_the_map_example_takes_a_view_by_name(tiny_run_path, tmp_path, monkeypatch, capsys):
    import runpy
    import sys
    from pathlib import Path

    run = tmp_path / "run"
    shutil.copytree(tiny_run_path, run)
    name = load_run(run).load_scene().subset("test").image_names[1]
    monkeypatch.setattr(sys, "argv", ["uncertainty_map.py", str(run), name, "2"])
    runpy.run_path(str(Path(__file__).resolve().parents[2] / "examples" / "uncertainty_map.py"), run_name="__main__")
    out = capsys.readouterr().out
    assert out.startswith(f"view ({name}): mean RGB std") and "between (between): mean RGB std" in out
    assert all((run / "example_maps" / f"{tag}_{m}.png").is_file() for tag in ("view", "between")
               for m in ("mean", "rgb_std", "depth_std"))


def test_a_model_that_leaves_its_training_views_empty_gets_a_note(tiny_run_path, tmp_path, monkeypatch, capsys):
    """Coverage below LOW_COVERAGE (bonsai's 0.43: dark surfaces left to the background) is said, with the option
    that covers them; a well-covered model (the tiny run) gets no such note."""
    from uncertsplat.baselines.runs import LoadedRun
    from uncertsplat.stages.evaluate import LOW_COVERAGE, low_coverage_notes

    assert low_coverage_notes(None, 7000) == [] and low_coverage_notes(LOW_COVERAGE, 7000) == []
    assert low_coverage_notes(0.43, 120) == []  # a short run has not covered its surfaces yet: nothing to say
    run = tmp_path / "run"
    shutil.copytree(tiny_run_path, run)
    cfg = EvalConfig(num_samples=2, max_views=1, calibration_views=0, reuse=False, save_maps=False)
    plain = evaluate.run(run, cfg, device=torch.device("cpu"))  # 120 steps
    assert not any("covers its own training views" in n for n in plain.notes)
    config = json.loads((run / "config.json").read_text(encoding="utf-8"))
    (run / "config.json").write_text(json.dumps({**config, "iterations": 7000}))  # read as a full run
    monkeypatch.setattr(LoadedRun, "coverage", lambda self, *a, **k: 0.43)
    low = evaluate.run(run, cfg, device=torch.device("cpu"))
    (note,) = [n for n in low.notes if "covers its own training views" in n]
    assert "alpha 0.43" in note and "random_background=true" in note
    printed = capsys.readouterr()
    assert "random_background=true" in " ".join((printed.out + printed.err).split())


def test_a_sample_mean_well_below_the_render_is_noted():
    from uncertsplat.stages.evaluate import few_samples_notes

    (note,) = few_samples_notes(26.61, 29.19, 2)
    assert note.startswith("the mean of the 2 samples scores 2.58 dB below the one render (26.61 against 29.19 dB)")
    assert few_samples_notes(28.9, 29.19, 2) == [] and few_samples_notes(None, 29.0, 2) == []
    assert few_samples_notes(26.61, 29.19, 10) == []  # with many samples a gap is no sampling noise


class TestPredictor:
    """``uncertsplat.predict``: evaluate's predictive for cameras of one's own, from Python."""

    def test_gives_evaluates_maps_for_a_held_out_view(self, evaluated):
        """The same seed gives the EXR's maps (raw RGB std, depth in the scene's units), and the std factor and tails
        evaluate fitted; a pose given in the scene's own frame is the scene's camera."""
        pycolmap = pytest.importorskip("pycolmap")
        from uncertsplat.predict import Predictor

        run, report = evaluated
        cfg = EvalConfig(num_samples=5, seed=3)
        pred = Predictor.load(run, "cpu", cfg=cfg)
        assert pred.std_factor == pytest.approx(report.std_scale) and pred.dof == pytest.approx(
            report.degrees_of_freedom)
        # no cfg: the evaluation's own settings (eval/config.json, K = 5), not evaluate's defaults (K = 10)
        default = Predictor.load(run, "cpu")
        assert default.std_factor == pytest.approx(report.std_scale) and default.config.num_samples == 5
        name = report.image_names[1]
        i = pred.scene.cameras.image_names.index(name)
        out = pred.predict(pred.scene.cameras[[i]], seed=cfg.seed)  # evaluate's --seed: its per-view seeds
        exr = run / "eval" / "maps" / f"{map_stem(name)}.exr"
        ch = read_exr(exr)
        to_source = read_exr_attribute(exr, EXR_DEPTH_TO_SOURCE)
        assert out.depth_to_source == pytest.approx(to_source, rel=1e-6)
        std = np.stack([ch[f"rgb_std.{c}"] for c in "RGB"], -1)
        np.testing.assert_allclose(out.rgb_std[0].numpy(), std, rtol=1e-3, atol=1e-6)
        np.testing.assert_allclose(out.depth_std[0, ..., 0].numpy(), ch["depth_std.Z"] * to_source, rtol=1e-3,
                                   atol=1e-6)
        np.testing.assert_allclose(out.depth_mean[0, ..., 0].numpy(), ch["depth_mean.Z"] * to_source, rtol=1e-3,
                                   atol=1e-5)
        assert out.rgb_std.shape == (1, 96, 128, 3) and out.alpha.shape == (1, 96, 128, 1)
        # the view's pose in the scene's own frame (the synthetic scene's COLMAP model) is the run's camera
        model = pycolmap.Reconstruction(str(pred.scene.source["path"]) + "/sparse/0")
        image = next(im for im in model.images.values() if im.name == name)
        cfs = torch.eye(4, dtype=torch.float64)
        cfs[:3] = torch.as_tensor(image.cam_from_world().matrix())
        cams = pred.cameras_from_source(cfs, pred.scene.cameras.K[i], 128, 96)
        torch.testing.assert_close(cams.cam_from_world, pred.scene.cameras.cam_from_world[[i]], atol=1e-5, rtol=0)
        assert cams.image_names == ("pose_0",)

    def test_the_terms_are_the_parts_of_the_maps_variance(self, evaluated):
        """``predict(..., terms=True)``: each part's variance map, keyed as ``evaluate``'s shares; they add up to the
        RGB std's square (mean over the channels) and the depth std's (in the scene's units); the maps are the same
        as without; an empty batch gives empty mappings."""
        from uncertsplat.predict import Predictor
        from uncertsplat.uncertainty.mc import sum_terms

        run, report = evaluated
        pred = Predictor.load(run, "cpu")
        i = pred.scene.cameras.image_names.index(report.image_names[0])
        view = pred.scene.cameras[[i]]
        plain, parts = pred.predict(view, num_samples=3), pred.predict(view, num_samples=3, terms=True)
        assert plain.rgb_terms is None and torch.equal(parts.rgb_std, plain.rgb_std)
        assert list(parts.rgb_terms) == list(report.variance_shares["rgb"])
        assert list(parts.depth_terms) == list(report.variance_shares["depth"])
        below = parts.rgb_std.amax(-1, keepdim=True) < 0.5  # (the RGB std's cap)
        torch.testing.assert_close(sum_terms(parts.rgb_terms)[below],
                                   parts.rgb_std.square().mean(-1, keepdim=True)[below], rtol=1e-4, atol=1e-9)
        torch.testing.assert_close(sum_terms(parts.depth_terms), parts.depth_std.square(), rtol=1e-4, atol=1e-9)
        none = pred.predict(pred.scene.cameras[[]], terms=True)
        assert none.rgb_terms == {} and none.depth_terms == {}

    def test_refuses_what_is_not_a_pose_or_a_sample_count(self, evaluated):
        from uncertsplat.predict import Predictor

        run, _ = evaluated
        pred = Predictor.load(run, "cpu", cfg=EvalConfig(num_samples=2, seed=3))
        scaled = torch.eye(4, dtype=torch.float64)
        scaled[:3, :3] *= 2.0  # a similarity, not a camera pose
        with pytest.raises(UserError, match="rigid transforms"):
            pred.cameras_from_source(scaled, pred.scene.cameras.K[0], 128, 96)
        with pytest.raises(UserError, match="num_samples must be 1 or more"):
            pred.predict(pred.scene.cameras[[0]], num_samples=0)
        mirrored = torch.diag(torch.tensor([1.0, 1.0, -1.0, 1.0], dtype=torch.float64))  # orthogonal, det -1
        with pytest.raises(UserError, match="rotation part that is a reflection"):
            pred.cameras_from_source(mirrored, pred.scene.cameras.K[0], 128, 96)
        two = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
        with pytest.raises(UserError, match=r"K must be \[3,3\] or \[N,3,3\] with N = 2"):
            pred.cameras_from_source(two, pred.scene.cameras.K[:3], 128, 96)
        with pytest.raises(UserError, match="1 name\\(s\\) for 2 pose"):
            pred.cameras_from_source(two, pred.scene.cameras.K[0], 128, 96, names=("a",))
        with pytest.raises(UserError, match="width must be 1 or more, got 0"):
            pred.cameras_from_source(two, pred.scene.cameras.K[0], 0, 96)

    def test_the_default_seed_is_the_evaluations_and_no_camera_gives_empty_maps(self, evaluated):
        """``predict()`` after ``evaluate --seed 3`` gives evaluate's maps (it seeded with 0 before); an empty batch
        gives maps of no camera, not an error from inside."""
        from uncertsplat.predict import Predictor

        run, report = evaluated
        pred = Predictor.load(run, "cpu")  # the evaluation's settings: seed 3
        assert pred.config.seed == 3
        i = pred.scene.cameras.image_names.index(report.image_names[0])
        view = pred.scene.cameras[[i]]
        default = pred.predict(view, num_samples=2)
        torch.testing.assert_close(default.rgb_std, pred.predict(view, num_samples=2, seed=3).rgb_std, rtol=0, atol=0)
        assert not torch.equal(default.rgb_std, pred.predict(view, num_samples=2, seed=0).rgb_std)
        none = pred.predict(pred.scene.cameras[[]])
        assert none.rgb_std.shape == (0, 96, 128, 3) and none.depth_mean.shape == (0, 96, 128, 1)
        assert none.image_names == ()

    def test_a_pose_written_two_ways_gets_the_same_maps(self, evaluated):
        """A pose of one's own seeds its samples from its values (``eval.engine.pose_index``): the same camera given
        in float64 or in float32 gets the same maps (its bytes seeded each way differently, so the std maps of one
        pose differed by their Monte Carlo noise); another pose gets other noise."""
        from uncertsplat.predict import Predictor
        from uncertsplat.types import Cameras

        run, _ = evaluated
        pred = Predictor.load(run, "cpu", cfg=EvalConfig(num_samples=2, seed=3))
        cfw = pred.scene.cameras.cam_from_world[:1].double().clone()
        cfw[0, 0, 3] += 0.0123456789  # not a scene view: seeded by its pose
        K = pred.scene.cameras.K[:1].double()
        a = pred.predict(Cameras(cfw, K, 128, 96, ("mine",)))
        b = pred.predict(Cameras(cfw.float(), K.float(), 128, 96, ("mine",)))
        assert torch.equal(a.rgb_std, b.rgb_std) and torch.equal(a.depth_std, b.depth_std)
        cfw[0, 1, 3] += 1e-3
        c = pred.predict(Cameras(cfw, K, 128, 96, ("mine",)))
        assert not torch.equal(a.rgb_std, c.rgb_std)

    def test_a_load_with_other_settings_leaves_the_runs_noise_file_alone(self, evaluated, tmp_path, capsys):
        """RUN/eval/residual.pt is the evaluation's (evaluate and prune read it): a Predictor with other settings
        keeps the noise it fits in memory, so a later default load still reads the file."""
        from uncertsplat.predict import Predictor

        run = tmp_path / "run"
        shutil.copytree(evaluated[0], run)
        cache = run / "eval" / "residual.pt"
        kept = cache.read_bytes()
        other = Predictor.load(run, "cpu", cfg=EvalConfig(num_samples=2, seed=3, residual_views=4))
        assert other.config.residual_views == 4
        assert cache.read_bytes() == kept
        capsys.readouterr()
        Predictor.load(run, "cpu")
        printed = capsys.readouterr()
        assert "pixel noise and std factor read from" in " ".join((printed.out + printed.err).split())
        (run / "eval" / "predictive.pt").unlink()
        Predictor.load(run, "cpu")
        printed = capsys.readouterr()
        assert "pixel noise: read from" in " ".join((printed.out + printed.err).split())
        cache.unlink()  # the default load still keeps what it fits
        (run / "eval" / "predictive.pt").unlink()
        Predictor.load(run, "cpu")
        assert cache.is_file() and (run / "eval" / "predictive.pt").is_file()
        # a damaged file, with the scene there: fitted again and written again, and said (it was replaced silently)
        path = run / "eval" / "predictive.pt"
        good = path.read_bytes()
        data = bytearray(good)
        data[len(data) // 2] ^= 0x10
        path.write_bytes(bytes(data))
        capsys.readouterr()
        Predictor.load(run, "cpu")
        printed = " ".join("".join(capsys.readouterr()).split())
        assert "predictive.pt cannot be read (" in printed and "the predictive is fitted again on the training" in printed
        assert path.read_bytes() == good
        Predictor.load(run, "cpu")  # a missing or kept file: nothing said of it
        assert "fitted again" not in " ".join("".join(capsys.readouterr()).split())

    def test_a_run_without_its_scene_gives_the_maps_of_one_with_it(self, evaluated, tmp_path, monkeypatch, capsys):
        """A robot has the run folder, not the photos: evaluate keeps what the predictive fitted on them
        (eval/predictive.pt), and a load where the scene cannot be read renders the same maps to the bit; without the
        file, or for other settings, the error says what to run."""
        from uncertsplat.baselines.runs import LoadedRun
        from uncertsplat.predict import Predictor

        run = tmp_path / "run"
        shutil.copytree(evaluated[0], run)
        with_scene = Predictor.load(run, "cpu")
        expected = with_scene.predict(with_scene.scene.cameras[[0, 7]], num_samples=3)

        def gone(self):
            raise UserError(f"the scene this run was trained on is gone: {self.scene_path}", path=self.run_dir)

        monkeypatch.setattr(LoadedRun, "_read_scene", gone)
        (run / "eval" / "residual.pt").unlink()  # the kept predictive holds its own noise
        capsys.readouterr()
        offline = Predictor.load(run, "cpu")
        printed = capsys.readouterr()
        assert "is gone" in printed.out + printed.err
        assert "the predictive is the one kept in" in " ".join((printed.out + printed.err).split())
        assert offline.std_factor == with_scene.std_factor and offline.dof == with_scene.dof
        assert offline.scene.split == with_scene.scene.split and offline.scale == with_scene.scale
        assert torch.equal(offline.scene.cameras.cam_from_world, with_scene.scene.cameras.cam_from_world)
        got = offline.predict(offline.scene.cameras[[0, 7]], num_samples=3)
        for name in ("rgb_mean", "rgb_std", "depth_mean", "depth_std", "alpha"):
            torch.testing.assert_close(getattr(got, name), getattr(expected, name), rtol=0, atol=0)
        with pytest.raises(UserError, match="cannot stand in for it: .*predictive.pt holds the predictive of other "
                                            "settings: num_samples = 5 there, 2 here") as info:
            Predictor.load(run, "cpu", cfg=EvalConfig(num_samples=2, seed=3))
        assert "uncertsplat evaluate" in str(info.value)
        # settings that change no number (what is written, which views are scored) read the evaluation's file
        assert Predictor.load(run, "cpu", cfg=EvalConfig(num_samples=5, seed=3, save_maps=False, max_views=1,
                                                         reuse=False)).std_factor == with_scene.std_factor
        # nor does the hidden points' depth term, computed at each prediction (files written before it still read)
        no_hidden = Predictor.load(run, "cpu", cfg=EvalConfig(num_samples=5, seed=3, hidden_depth=False))
        assert no_hidden.std_factor == with_scene.std_factor
        flat = no_hidden.predict(offline.scene.cameras[[0, 7]], num_samples=3)
        torch.testing.assert_close(flat.rgb_std, expected.rgb_std, rtol=0, atol=0)
        assert bool((flat.depth_std <= expected.depth_std).all())
        assert not torch.equal(flat.depth_std, expected.depth_std)  # the tiny scene has hidden points
        path = run / "eval" / "predictive.pt"
        data = bytearray(path.read_bytes())
        data[len(data) // 2] ^= 0x10  # one flipped bit: the checksum finds it, nothing damaged is rendered
        path.write_bytes(bytes(data))
        with pytest.raises(UserError, match="is gone.*predictive.pt cannot be read .*checksum mismatch"):
            Predictor.load(run, "cpu")
        torch.save({"format": 1}, path)  # a plain torch file, as versions before the checksum wrote: said so
        with pytest.raises(UserError, match="is gone.*predictive.pt was written by an earlier version"):
            Predictor.load(run, "cpu")
        path.write_bytes(b".")  # (a file torch's unpickler fails on with an IndexError)
        with pytest.raises(UserError, match="is gone.*predictive.pt cannot be read"):
            Predictor.load(run, "cpu")
        path.unlink()
        with pytest.raises(UserError, match="is gone.*predictive.pt is missing"):
            Predictor.load(run, "cpu")

    def test_a_run_pointed_at_its_moved_scene_keeps_its_predictive(self, evaluated, tiny_scene_path, tmp_path,
                                                                    monkeypatch):
        """`train NEW_SCENE_FOLDER -o RUN --resume` (what the scene-gone error advises: it trains nothing) rewrote
        where scene.json says the scene lies, and eval/predictive.pt, keyed by the file's bytes, became "the predictive
        of another model or run": a robot given the run afterwards had no predictive. Where the scene lies is not part
        of the key; a file keyed by the whole scene.json, as before, still reads."""
        from uncertsplat.baselines.runs import LoadedRun
        from uncertsplat.predict import Predictor
        from uncertsplat.stages import predictive_cache as pc
        from uncertsplat.stages.predictive_cache import evaluation_config

        run = tmp_path / "run"
        shutil.copytree(evaluated[0], run)
        with_scene = Predictor.load(run, "cpu")
        moved = tmp_path / "moved"
        shutil.copytree(tiny_scene_path, moved)
        before = (run / "scene.json").read_bytes()
        info = json.loads(before)  # the scene moved away (the shared one stays; a resume on another is refused)
        (run / "scene.json").write_text(json.dumps({**info, "scene": str(tmp_path / "gone"), "scene_from_run": None}))
        result = CliRunner().invoke(app, ["train", str(moved), "-o", str(run), "--resume"])
        assert result.exit_code == 0, result.output
        assert (run / "scene.json").read_bytes() != before  # (the scene's new place recorded)

        def gone(self):
            raise UserError(f"the scene this run was trained on is gone: {self.scene_path}", path=self.run_dir)

        monkeypatch.setattr(LoadedRun, "_read_scene", gone)
        offline = Predictor.load(run, "cpu")
        assert offline.std_factor == with_scene.std_factor and offline.scene.split == with_scene.scene.split
        # a file written before (keyed by scene.json's bytes) reads as well
        path = run / "eval" / "predictive.pt"
        stored = decode(path.read_bytes())
        loaded = load_run(run, torch.device("cpu"))
        old = pc._part_forms(loaded, evaluation_config(run))[1]
        assert old["scene"] != pc._parts(loaded, evaluation_config(run))["scene"]
        path.write_bytes(encode({**stored, "key": pc._key(old), "parts": json.dumps(old, sort_keys=True, default=str)}))
        assert Predictor.load(run, "cpu").std_factor == with_scene.std_factor
        # copied to a run (a prune that removed nothing), such a file is rekeyed in today's form, without the location
        again = decode(pc.rekeyed_predictive(path.read_bytes(), run, run, Path(loaded.source).name))
        assert again["key"] == pc._key(pc._parts(loaded, evaluation_config(run))), json.loads(again["parts"])
        # a run without scene.json has no key (nor a rekeyed file)
        (run / "scene.json").rename(run / "scene.json.kept")
        assert pc._parts(loaded, evaluation_config(run)) is None
        assert pc.rekeyed_predictive(path.read_bytes(), run, run, Path(loaded.source).name) is None
        (run / "scene.json.kept").rename(run / "scene.json")
        # another scene.json content (another split) is another run's file, as before
        info = json.loads((run / "scene.json").read_text(encoding="utf-8"))
        (run / "scene.json").write_text(json.dumps({**info, "extent": info["extent"] * 2}))
        with pytest.raises(UserError, match="holds the predictive of another model or run"):
            Predictor.load(run, "cpu")

    def test_an_evaluation_kept_as_it_is_still_leaves_the_predictive(self, evaluated, tmp_path, capsys):
        """A run evaluated before eval/predictive.pt existed: `evaluate` again said "already evaluated" and wrote
        nothing, though the Predictor's error sent the user there. It now writes the file from its metrics and the
        noise, the same predictive a fresh fit gives."""
        from uncertsplat.predict import Predictor

        run = tmp_path / "run"
        shutil.copytree(evaluated[0], run)
        path = run / "eval" / "predictive.pt"
        fresh = decode(path.read_bytes())
        path.unlink()
        capsys.readouterr()
        evaluate.run(run, EvalConfig(num_samples=5, seed=3), device=torch.device("cpu"))
        assert "already evaluated" in " ".join(capsys.readouterr().err.split())
        kept = decode(path.read_bytes())
        assert kept["key"] == fresh["key"] and kept["std"] == fresh["std"]
        assert Predictor.load(run, "cpu").std_factor == evaluated[1].std_scale

    def test_the_kept_fit_is_read_on_its_device_and_fitted_again_on_another(self, evaluated, tmp_path, monkeypatch):
        """With the scene there, a predictive kept for this model and settings is read, not fitted again (the std
        factor's K renders of the calibration views); one fitted on another device type is fitted again, as
        evaluate on this device would, and leaves the file as it is. An evaluation of the training split leaves the
        file alone."""
        from uncertsplat.eval import engine
        from uncertsplat.predict import Predictor

        run = tmp_path / "run"
        shutil.copytree(evaluated[0], run)
        path = run / "eval" / "predictive.pt"
        kept = path.read_bytes()
        evaluate.run(run, EvalConfig(num_samples=2, seed=3, split="train", max_views=1, save_maps=False),
                     device=torch.device("cpu"))
        assert path.read_bytes() == kept
        real, calls = engine.fit_std_scale, []
        monkeypatch.setattr(engine, "fit_std_scale", lambda *a, **k: calls.append(1) or real(*a, **k))
        read = Predictor.load(run, "cpu")
        assert calls == [] and read.std_factor == pytest.approx(evaluated[1].std_scale)
        data = decode(path.read_bytes())
        path.write_bytes(encode({**data, "device": "cuda"}))
        fitted = Predictor.load(run, "cpu")
        assert calls == [1] and fitted.std_factor == read.std_factor
        # the file is the evaluation's (a robot on that device reads it): a load on another device leaves it
        assert decode(path.read_bytes())["device"] == "cuda"

    def test_says_which_poses_and_points_a_photo_showed_empty(self, evaluated):
        """``seen_free``: the scene's cameras and a point between a camera and the wall its middle pixel sees are in
        space a photo looked through; a camera beyond the room's wall (whose render looks like any other) is not;
        the scene's frame and the run's agree; bad points are refused."""
        from uncertsplat.predict import Predictor

        run, _ = evaluated
        pred = Predictor.load(run, "cpu", cfg=EvalConfig(num_samples=2, seed=3))
        cams = pred.scene.cameras
        test = list(pred.scene.split["test"])
        out = pred.predict(cams[test[:2]])
        assert out.seen_free.tolist() == [True, True]
        train = list(pred.scene.split["train"])
        cam = cams[[train[0]]]
        rendered = pred.predict(cam, num_samples=1)
        depth = rendered.depth_mean[0, ..., 0] / rendered.depth_to_source  # [H,W] the run's units
        row, col = divmod(int(depth.argmax()), cam.width)  # the farthest surface it sees: the room's wall
        ray = torch.tensor([col + 0.5, row + 0.5, 1.0]) @ torch.linalg.inv(cam.K[0]).T  # camera z = 1
        world = lambda z: cam.centers[0] + (ray * z) @ cam.cam_from_world[0, :3, :3]  # noqa: E731
        d = float(depth[row, col])
        assert pred.seen_free(torch.stack([world(0.5 * d), world(2.0 * d)]), frame="world").tolist() == [True, False]
        beyond = cam.cam_from_world.clone()
        beyond[0, :3, 3] = -(beyond[0, :3, :3] @ world(2.0 * d))  # the camera moved through the wall
        moved = pred.predict(dataclasses.replace(cam, cam_from_world=beyond, image_names=("beyond",)), num_samples=1)
        assert moved.seen_free.tolist() == [False]
        T = pred.scene.world_from_source.double()
        inside = torch.linalg.solve(T[:3, :3], world(0.5 * d).double() - T[:3, 3])  # the same point in the scene's frame
        assert pred.seen_free(inside).tolist() == [True]
        # without the view-consistency term the renders are made for it, once
        bare = Predictor.load(run, "cpu", cfg=EvalConfig(num_samples=2, seed=3, consistency_views=0))
        assert bare._sampler.consistency is None
        assert bare.seen_free(torch.stack([world(0.5 * d), world(2.0 * d)]), frame="world").tolist() == [True, False]
        assert bare._free is not None and len(bare._free.cameras) == len(train)
        with pytest.raises(UserError, match="point 1 is not finite"):
            pred.seen_free([[0.0, 0.0, 0.0], [float("nan"), 0.0, 0.0]])
        with pytest.raises(UserError, match=r"points must be \[P,3\] or \[3\], got \(4, 2\)"):
            pred.seen_free(torch.zeros(4, 2))
        with pytest.raises(UserError, match=r"got \(2,\)"):  # the shape given, not the one made of it
            pred.seen_free([1.0, 2.0])
        assert pred.seen_free([]).shape == (0,) and pred.seen_free(np.zeros((0, 3))).shape == (0,)  # no waypoints
        with pytest.raises(UserError, match="frame must be"):
            pred.seen_free(torch.zeros(1, 3), frame="camera")

    def test_a_pose_gets_the_same_maps_wherever_it_stands_in_a_batch(self, evaluated):
        """A pose of one's own is seeded by itself, not by its place: [A, B] and [B, A] give A the same maps."""
        from uncertsplat.predict import Predictor

        run, _ = evaluated
        pred = Predictor.load(run, "cpu", cfg=EvalConfig(num_samples=3, seed=3))
        cams = pred.scene.cameras
        a = dataclasses.replace(cams[[0]], image_names=("a",))
        b = dataclasses.replace(cams[[5]], image_names=("b",))
        both = dataclasses.replace(cams[[0, 5]], image_names=("a", "b"))
        flipped = dataclasses.replace(cams[[5, 0]], image_names=("b", "a"))
        first, second = pred.predict(both), pred.predict(flipped)
        torch.testing.assert_close(first.rgb_std[0], second.rgb_std[1], rtol=0, atol=0)
        torch.testing.assert_close(first.depth_std[1], second.depth_std[0], rtol=0, atol=0)
        torch.testing.assert_close(pred.predict(a).rgb_std[0], first.rgb_std[0], rtol=0, atol=0)
        renamed = dataclasses.replace(cams[[5]], image_names=("another name",))
        torch.testing.assert_close(pred.predict(renamed).rgb_std[0], pred.predict(b).rgb_std[0], rtol=0, atol=0)


def test_an_evaluation_stopped_midway_keeps_the_earlier_one_whole(tiny_run_path, tmp_path, monkeypatch):
    """Ctrl-C (or a full disk, kill -9) after the first view's maps of a new evaluation: the earlier evaluation, its
    metrics.json and its maps, is left as it was (deleting its metrics first lost it; keeping them beside new maps mixed
    two evaluations), and the next evaluate with the earlier settings keeps it; a killed one's staging folder goes."""
    run = tmp_path / "run"
    shutil.copytree(tiny_run_path, run)
    first = EvalConfig(num_samples=2, seed=0)
    evaluate.run(run, first, device=torch.device("cpu"))
    real = evaluate.write_view_maps

    def stop_after_one(*args, **kwargs):
        real(*args, **kwargs)
        raise KeyboardInterrupt

    before = {p.relative_to(run / "eval"): p.read_bytes() for p in (run / "eval").rglob("*")
              if p.is_file() and p.parent.name == "maps" or p.name in ("metrics.json", "config.json")}
    monkeypatch.setattr(evaluate, "write_view_maps", stop_after_one)
    with pytest.raises(KeyboardInterrupt):
        evaluate.run(run, EvalConfig(num_samples=3, seed=7), device=torch.device("cpu"))
    after = {p.relative_to(run / "eval"): p.read_bytes() for p in (run / "eval").rglob("*")
             if p.is_file() and p.parent.name == "maps" or p.name in ("metrics.json", "config.json")}
    assert after == before
    (run / "eval" / ".maps-999999").mkdir(exist_ok=True)  # as a kill -9 leaves it
    monkeypatch.setattr(evaluate, "write_view_maps", real)
    report = evaluate.run(run, EvalConfig(num_samples=3, seed=7), device=torch.device("cpu"))
    assert report.num_samples == 3 and not list((run / "eval").glob(".maps-*"))
    assert sorted(p.name for p in (run / "eval" / "maps").iterdir()) == sorted(
        p.name for p in before if p.parent.name == "maps")
    (run / "eval").rename(tmp_path / "moved-eval")
    (run / "eval").write_text("")
    with pytest.raises(UserError, match="the evaluation's folder eval is a file, not a folder"):
        evaluate.run(run, first, device=torch.device("cpu"))


def test_evaluate_stopped_says_what_is_on_disk(tiny_run_path, tmp_path, monkeypatch):  # noqa: F811
    """Ctrl-C during evaluate said "this evaluation has no metrics.json" beside an intact earlier metrics.json and maps:
    it says the earlier evaluation is kept whole, and without one that no metrics.json was written."""
    run = tmp_path / "run"
    shutil.copytree(tiny_run_path, run, ignore=shutil.ignore_patterns("eval", ".lock"))
    real = evaluate.write_view_maps

    def stop_after_one(*args, **kwargs):
        real(*args, **kwargs)
        raise KeyboardInterrupt

    args = ["evaluate", str(run), "--num-samples", "2", "--device", "cpu"]
    monkeypatch.setattr(evaluate, "write_view_maps", stop_after_one)
    result = runner.invoke(app, args)
    said = " ".join(result.output.split())
    assert result.exit_code == 130 and "no metrics.json was written" in said, said
    monkeypatch.setattr(evaluate, "write_view_maps", real)
    assert runner.invoke(app, args).exit_code == 0  # "the same command evaluates again"
    kept = {p.relative_to(run): p.read_bytes() for p in (run / "eval").rglob("*") if p.is_file()}
    monkeypatch.setattr(evaluate, "write_view_maps", stop_after_one)
    result = runner.invoke(app, [*args, "--seed", "5"])
    said = " ".join(result.output.split())
    assert result.exit_code == 130 and "the evaluation already here is kept whole" in said, said
    assert "has no metrics.json" not in said and f"{run / 'eval'}: " in said, said
    assert {p.relative_to(run): p.read_bytes() for p in (run / "eval").rglob("*") if p.is_file()
            and p.name not in ("residual.pt", "predictive.pt")} == {
        k: v for k, v in kept.items() if k.name not in ("residual.pt", "predictive.pt")}


def test_views_the_model_leaves_empty_are_named():
    """A held-out view whose pixels the model leaves empty (no Gaussian: alpha < 1/2) well beyond its training views'
    share is named with the fraction (the surface-based reach note cannot see empty rays: 40 % empty, 12 dB); the
    same share as the training views' (an object scene's background) is not."""
    from types import SimpleNamespace

    from uncertsplat.stages.evaluate import _empty_view_notes
    from uncertsplat.types import Cameras

    def cams(shifts, names):
        cfw = torch.eye(4).repeat(len(shifts), 1, 1)
        cfw[:, 0, 3] = torch.tensor(shifts, dtype=torch.float32)
        K = torch.tensor([[10.0, 0, 5], [0, 10.0, 5], [0, 0, 1]]).repeat(len(shifts), 1, 1)
        return Cameras(cfw, K, 10, 10, tuple(names))

    def render(rep, c):  # alpha 0 on a share of the rows set by the camera's x shift (0.1 empty per unit)
        share = float(c.cam_from_world[0, 0, 3]) / 10
        alpha = torch.ones(1, 10, 10, 1)
        alpha[:, : round(10 * share)] = 0.0
        return SimpleNamespace(alpha=alpha)

    sampler = SimpleNamespace(det_sample="rep", render_fn=render)
    train = cams([1.0, 1.0, 1.0, 2.0], [f"t{i}" for i in range(4)])  # 10-20 % empty: a background
    views = SimpleNamespace(names=["near", "mid", "far"], cameras=cams([1.0, 2.0, 5.0], ["near", "mid", "far"]))
    (note,) = _empty_view_notes(sampler, views, train, torch.device("cpu"))
    assert note.startswith("1 of 3 views show parts the model holds no surface for") and "far 50 %" in note
    # against the most a training view leaves empty (20 %): "mid" at 20 % is within the training views' own spread
    assert "training views at most 20 %" in note and "near" not in note.split(":", 1)[1] and "mid" not in note
    assert _empty_view_notes(sampler, SimpleNamespace(names=["near"], cameras=cams([1.0], ["near"])), train,
                             torch.device("cpu")) == []


def test_the_empty_view_note_is_asked_only_where_it_means_something(tiny_run_path, tmp_path, monkeypatch):
    """Held-out views with the empty-ray term on: asked; the training views, or the term off (a transparent scene
    has none: its empty rays are the photos' background): not asked."""
    run = tmp_path / "run"
    shutil.copytree(tiny_run_path, run)
    asked = []
    monkeypatch.setattr(evaluate, "_empty_view_notes", lambda *a: asked.append(1) or [])
    quick = dict(num_samples=2, max_views=1, save_maps=False, reuse=False, calibration_views=0)
    evaluate.run(run, EvalConfig(**quick), device=torch.device("cpu"))
    assert asked == [1]
    evaluate.run(run, EvalConfig(**quick, empty_rays=False), device=torch.device("cpu"))
    evaluate.run(run, EvalConfig(**quick, split="train"), device=torch.device("cpu"))
    assert asked == [1]


def test_held_out_views_that_are_near_copies_of_training_photos_are_named(tiny_scene_path, monkeypatch):  # noqa: F811
    """The nearest training view by pose (distance in rig radii + axis angle); a held-out set whose nearest
    training photos score within 4 dB of the model is named (every n-th frame of a video); the tiny ring's held-out
    views (the nearest photo about 15 dB) are not."""
    from uncertsplat.data.dataset import load_images
    from uncertsplat.eval.image import psnr
    from uncertsplat.sfm.scene import load_scene
    from uncertsplat.stages.evaluate import near_copy_notes, nearest_training_views

    scene = load_scene(tiny_scene_path)
    held, train = list(scene.split["test"]), list(scene.split["train"])
    near = nearest_training_views(scene.cameras, held, train)
    c = scene.cameras.centers
    for i, j in zip(held, near, strict=True):  # on the ring: a neighbour, one step away
        d = (c[train] - c[i]).norm(dim=-1)
        assert j in train and (c[j] - c[i]).norm() <= d.min() * 1.01
    views = load_view_set(scene, held, depth=False)
    copies = load_images(scene, near)
    copy = float(torch.stack([psnr(copies[k], views.images[k]) for k in range(len(held))]).mean())
    assert copy < 20.0
    assert near_copy_notes(scene, views, copy + 10.0) == []  # a model well above copying: a real test
    # neighbours at under 20 dB are no copies, whatever a poor model scores (a helper's bonsai run: 12.8 against 15.7)
    assert near_copy_notes(scene, views, copy + 2.0) == []
    from uncertsplat.stages import evaluate as ev

    monkeypatch.setattr(ev, "NEAR_COPY_MIN_DB", copy - 1.0)  # as if these neighbours reproduced their views
    (note,) = near_copy_notes(scene, views, copy + 2.0)
    assert note.startswith(f"the held-out views are near copies of training photos: the training photo nearest in "
                           f"pose scores {copy:.2f} dB")


def test_masks_that_leave_no_pixel_are_a_clear_error(tiny_run_path, tmp_path, monkeypatch):
    """Every evaluated view's mask empty (all black, or inverted) ended in a traceback from the curves' mean."""
    from uncertsplat.data import dataset

    run = tmp_path / "run"
    shutil.copytree(tiny_run_path, run)
    real = dataset.load_masks

    def empty(scene, indices=None, device=None):
        m = real(scene, indices, device)
        return None if m is None else torch.zeros_like(m)

    monkeypatch.setattr(dataset, "load_masks", empty)
    with pytest.raises(UserError, match=r"the validity masks of the \d+ evaluated view\(s\) mark no pixel valid"):
        evaluate.run(run, EvalConfig(num_samples=2, max_views=2, save_maps=False, reuse=False),
                     device=torch.device("cpu"))


def test_a_std_of_zero_everywhere_is_said(tiny_run_path, tmp_path):
    """One sample with every side term off: a std of 0 at every pixel, whose NLL and calibration measure the floor
    (a helper saw a std factor of x66.6 that changed nothing, and no word)."""
    run = tmp_path / "run"
    shutil.copytree(tiny_run_path, run)
    off = dict(residual_views=0, consistency_views=0, resolution=0.0, empty_rays=False, depth_spread=False,
               edge_noise=False, colour_posterior=False)
    report = evaluate.run(run, EvalConfig(num_samples=1, max_views=1, save_maps=False, reuse=False, **off),
                          device=torch.device("cpu"))
    assert any(n.startswith("every pixel's RGB std is 0") for n in report.notes)
    # nor a kernel density of that one render (it measured its bandwidth: 2,700 nats beside -2.5)
    assert report.mean.nll_kde is None and any(n.startswith("KDE NLL not computed") for n in report.notes)
    report = evaluate.run(run, EvalConfig(num_samples=2, max_views=1, save_maps=False, reuse=False),
                          device=torch.device("cpu"))
    assert not any(n.startswith("every pixel's RGB std is 0") for n in report.notes)
    assert report.mean.nll_kde is not None and not any(n.startswith("KDE NLL not") for n in report.notes)


def test_one_sample_still_has_the_resolution_term_s_spread(tiny_run_path, tmp_path):
    """K = 1 with the default two renders of the resolution term per sample: that term still spreads (its share is
    not 0), and the notes do not say it is 0 (a helper saw "the resolution term ... 0 with K = 1" beside its share,
    "resolution 2 %"); the shares' sentence says why the samples' spread is 0. With one render it is 0, and said."""
    run = tmp_path / "run"
    shutil.copytree(tiny_run_path, run)
    kw = dict(num_samples=1, max_views=1, save_maps=False, reuse=False)
    report = evaluate.run(run, EvalConfig(**kw), device=torch.device("cpu"))
    assert report.variance_shares["rgb"]["resolution"] > 0.0 and report.variance_shares["rgb"]["samples"] == 0.0
    assert not any("resolution term are 0" in n or "0 with K = 1" in n for n in report.notes)
    assert any(n.startswith("K=1: the samples' spread is 0 everywhere") for n in report.notes)
    assert "the samples' spread 0 % (K = 1: one sample has no spread)" in report.variance_parts()
    report = evaluate.run(run, EvalConfig(resolution_renders=1, **kw), device=torch.device("cpu"))
    assert report.variance_shares["rgb"]["resolution"] == 0.0
    assert any(n.startswith("K=1: the samples' spread and the resolution term are 0 everywhere") for n in report.notes)
    assert any("1 render per sample; 0 with K = 1)" in n for n in report.notes)


def test_files_kept_before_the_training_views_fit_changed_read_with_the_old_fit():
    """``predictive.pt`` files written before ``resolution_on_training_views`` existed hold a factor fitted with the
    resolution term: the default (false) fits another and does not read them; ``true`` keys as they were keyed."""
    from uncertsplat.stages.predictive_cache import UNUSED_SETTINGS, key_settings

    diagonal = {"colour_covariance": "diagonal"}  # (the colour posterior's form of those files, left out of keys)
    old = EvalConfig(**diagonal).model_dump(mode="json", exclude=set(UNUSED_SETTINGS))
    del old["resolution_on_training_views"]  # (what a file written before the setting holds)
    del old["colour_covariance"]  # (nor this one, added later: left out at "diagonal", the form before it)
    assert key_settings(EvalConfig(resolution_on_training_views=True, **diagonal)) == old
    assert key_settings(EvalConfig())["resolution_on_training_views"] is False
    assert "hidden_depth" not in key_settings(EvalConfig(hidden_depth=False))
    # a file keyed with true written in (the commit that added the setting) reads with true too
    from uncertsplat.stages.predictive_cache import _accepted_keys, _difference, _key

    parts = {"model": "m", "config": "c", "scene": "s",
             "settings": key_settings(EvalConfig(resolution_on_training_views=True, **diagonal)), "fit": 1}
    written_in = {**parts, "settings": {**parts["settings"], "resolution_on_training_views": True}}
    assert _key(written_in) in _accepted_keys(parts) and _key(parts) in _accepted_keys(parts)
    default = {**parts, "settings": key_settings(EvalConfig(**diagonal))}
    assert _key(default) in _accepted_keys(default)
    assert not {_key(parts), _key(written_in)} & _accepted_keys(default)
    # the difference says what the file lacks and how to read it, not "None there"
    said = _difference(parts, default)
    assert "resolution_on_training_views = not in the file (written before the setting existed; --set " \
           "resolution_on_training_views=true reads it), False here" in said and "None" not in said
    assert _difference(written_in, parts) == "another version of the noise fit or of the std factor's"  # (none differs)


def test_files_kept_before_colour_covariance_existed_read_with_the_diagonal_form():
    """``predictive.pt`` files written before ``colour_covariance`` existed hold the diagonal colour posterior
    (the default): they read with it, as do the files of the commit that added the setting (which wrote it in
    the key), with ``resolution_on_training_views`` left out or not; ``block`` reads neither and says why."""
    from uncertsplat.stages.predictive_cache import (
        UNUSED_SETTINGS,
        _accepted_keys,
        _difference,
        _key,
        key_settings,
    )

    def parts(settings: dict) -> dict:
        return {"model": "m", "config": "c", "scene": "s", "settings": settings, "fit": 2}

    for cfg in (EvalConfig(colour_covariance="diagonal"),
                EvalConfig(resolution_on_training_views=True, colour_covariance="diagonal")):
        before = cfg.model_dump(mode="json", exclude=set(UNUSED_SETTINGS))
        if cfg.resolution_on_training_views:
            del before["resolution_on_training_views"]  # (left out at true, as every file keys it)
        written_in = dict(before)  # the commit that added the setting keyed it so
        del before["colour_covariance"]  # (what a file written before the setting holds)
        now = parts(key_settings(cfg))
        assert _key(parts(before)) in _accepted_keys(now) and _key(parts(written_in)) in _accepted_keys(now)
    block = parts(key_settings(EvalConfig()))  # the default since 2026-12-01
    assert EvalConfig().colour_covariance == "block"
    old = parts({k: v for k, v in EvalConfig().model_dump(mode="json", exclude=set(UNUSED_SETTINGS)).items()
                 if k != "colour_covariance"})
    assert _key(old) not in _accepted_keys(block)
    assert "colour_covariance = not in the file (written before the setting existed; --set " \
           "colour_covariance=diagonal reads it), 'block' here" in _difference(old, block)


def test_files_with_a_fitted_noise_level_from_before_the_factor_kept_the_term_are_not_read(tiny_run_path):
    """With ``residual_scale = "fit"`` the std factor on training views is now fitted with the resolution term the
    noise's level was fitted with: files from before hold another factor (x1.7 against x0.84 on the demo) and are
    keyed apart; the other settings' keys are unchanged."""
    from uncertsplat.stages.predictive_cache import STD_FIT_WITH_FITTED_NOISE, _accepted_keys, _key, _parts

    loaded = load_run(tiny_run_path, "cpu")
    fitted = _parts(loaded, EvalConfig(residual_scale="fit"))
    assert fitted["std_fit"] == STD_FIT_WITH_FITTED_NOISE == 2
    before = {k: v for k, v in fitted.items() if k != "std_fit"}
    written_in = {**before, "settings": {**before["settings"], "resolution_on_training_views": True}}
    assert not {_key(before), _key(written_in)} & _accepted_keys(fitted)
    for cfg in (EvalConfig(), EvalConfig(residual_scale=1.0), EvalConfig(residual_scale="fit", residual_views=0)):
        assert "std_fit" not in _parts(loaded, cfg)


def test_the_std_formula_names_every_term_the_run_has(evaluated):
    """metrics.json's ``std² =`` note lists the terms of the predictive: with the defaults the view-consistency term
    with its finer-detail part and, for depth, the depths a ray blends and the hidden points' term (a helper found
    the finer-detail term missing from it)."""
    _, report = evaluated
    (std,) = [n for n in report.notes if n.startswith("std² = ")]
    for part in ("nearest in direction", "finer-detail coefficient", "depths each ray blends", "L^2 / 12"):
        assert part in std, part


def test_a_std_that_is_no_number_is_said_and_the_console_survives_it(tiny_run_path, tmp_path, monkeypatch):
    """A NaN std read as 0 ("every pixel's RGB std is 0 (one sample and every side term off?)") under K = 10 with
    every term on (a helper's residual_scale=1e300, now refused by the config, as is a std floor below what float32
    squares): the NaN is named, and the evaluation with its console lines finishes."""
    from uncertsplat.eval.engine import NOT_A_NUMBER_NOTE
    from uncertsplat.uncertainty import mc

    run = tmp_path / "run"
    shutil.copytree(tiny_run_path, run)
    real = mc.mc_render

    def nan_std(*args, **kwargs):
        maps, extra = real(*args, **kwargs)
        maps.rgb_std[0, :4, :4] = float("nan")
        return maps, extra

    monkeypatch.setattr(mc, "mc_render", nan_std)
    report = evaluate.run(run, EvalConfig(num_samples=2, max_views=1, save_maps=False, reuse=False),
                          device=torch.device("cpu"))
    assert any(n.startswith(NOT_A_NUMBER_NOTE) for n in report.notes), report.notes
    assert not any(n.startswith("every pixel's RGB std is 0") for n in report.notes)
    for bad in ({"residual_scale": 1e300}, {"std_floor": 1e-50}):
        with pytest.raises(UserError, match="invalid configuration"):
            build_config(EvalConfig, bad)
