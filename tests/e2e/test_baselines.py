"""Baselines end to end on the tiny synthetic scene: train, evaluate, maps of the right shape, spread.

Runs are kept very short (quarter resolution, 20 steps): these tests check the harness, not accuracy.
"""

from __future__ import annotations

import json
import shutil
from functools import partial

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from tests.fixtures import tiny_scene
from uncertsplat.baselines import load_run, train_run
from uncertsplat.baselines.ensemble import EnsembleRun
from uncertsplat.baselines.fisher import FISHER_FILE, FisherRun
from uncertsplat.cli import app
from uncertsplat.config import EvalConfig, deep_update, train_config_from
from uncertsplat.console import q
from uncertsplat.conventions import ensemble_member_dir
from uncertsplat.data.dataset import load_view_set
from uncertsplat.eval.engine import evaluate_views, fit_residual, with_side_terms
from uncertsplat.io.images import read_exr
from uncertsplat.io.maps import map_stem
from uncertsplat.schemas.metrics import EvalReport
from uncertsplat.stages import evaluate

CPU = torch.device("cpu")
H, W = 24, 32  # the tiny scene (128x96) at downscale 4
QUICK = {
    "iterations": 20, "scene": {"downscale": 4.0}, "eval_every": 1000, "checkpoint_every": 1000, "log_every": 10,
    "densify": {"start": 5, "until": 15, "interval": 5, "spawn_interval": 10},
}


@pytest.fixture(scope="session")
def scene_path(tmp_path_factory):
    """The shared tiny synthetic scene (the same folder as ``tests.fixtures.tiny_scene_path``)."""
    return tiny_scene(tmp_path_factory.getbasetemp() / "shared_scenes")


def quick_cfg(**over):
    return train_config_from("tiny", deep_update(QUICK, over))


def exr_maps(run, report):
    return [read_exr(run / "eval" / "maps" / f"{map_stem(n)}.exr") for n in report.image_names]


@pytest.fixture(scope="module")
def ensemble_run(scene_path, tmp_path_factory):
    run = tmp_path_factory.mktemp("ens") / "run"
    train_run(scene_path, run, quick_cfg(method="ensemble", ensemble_size=2), CPU)
    return run


@pytest.fixture(scope="module")
def fisher_run(scene_path, tmp_path_factory):
    run = tmp_path_factory.mktemp("fisher") / "run"
    train_run(scene_path, run, quick_cfg(method="fisher"), CPU)
    return run


def test_ensemble_layout_and_spread(ensemble_run):
    run = ensemble_run
    assert json.loads((run / "config.json").read_text(encoding="utf-8"))["method"] == "ensemble"
    assert (run / "scene.json").is_file()
    members = [json.loads((ensemble_member_dir(run, i) / "config.json").read_text(encoding="utf-8")) for i in range(2)]
    assert [m["method"] for m in members] == ["deterministic", "deterministic"]
    assert [m["seed"] for m in members] == [0, 1]
    summary = json.loads((run / "train_summary.json").read_text(encoding="utf-8"))
    assert summary["ensemble_size"] == 2 and len(summary["members"]) == 2
    assert summary["seconds"] == pytest.approx(sum(m["seconds"] for m in summary["members"]))
    # what training warned about in a member is in the ensemble's own summary, where the report looks
    assert summary["warnings"] == list(dict.fromkeys(f"member {i + 1}: {w}" for i, m in enumerate(summary["members"])
                                                     for w in m["warnings"]))
    assert summary["warnings"], "20-step members fit their photos badly and say so"
    loaded = load_run(run, CPU)
    assert isinstance(loaded, EnsembleRun) and len(loaded.members) == 2
    assert all(m.model.num_carriers == 0 for m in loaded.members)  # plain 3DGS members
    report = evaluate.run(run, EvalConfig(num_samples=2, max_views=2), device=CPU)
    assert len(report.image_names) == 2
    for ch in exr_maps(run, report):
        assert ch["rgb_std.R"].shape == (H, W) and ch["depth_std.Z"].shape == (H, W)
        assert ch["rgb_std.R"].max() > 0, "two differently seeded members must disagree somewhere"
    assert not any("1 member" in n for n in report.notes)
    assert report.mean.ause_mae is not None and report.mean.nll is not None


def test_an_ensemble_of_variational_members_samples_their_posteriors(scene_path, tmp_path):
    """``ensemble_members = "variational"``: each member is our model with its posterior, and an ensemble of one
    such member still has a spread (its posterior's), unlike an ensemble of one plain 3DGS model."""
    run = tmp_path / "run"
    train_run(scene_path, run, quick_cfg(method="ensemble", ensemble_size=1, ensemble_members="variational"), CPU)
    assert json.loads((ensemble_member_dir(run, 0) / "config.json").read_text(encoding="utf-8"))["method"] == "variational"
    loaded = load_run(run, CPU)
    assert isinstance(loaded, EnsembleRun) and loaded.variational_members
    assert loaded.members[0].model.num_carriers > 0 and "each with its posterior" in loaded.size_text()
    report = evaluate.run(run, EvalConfig(num_samples=3, max_views=1, residual_views=0, consistency_views=0,
                                          resolution=0, empty_rays=False, depth_spread=False), device=CPU)
    assert not any("1 member" in n for n in report.notes)
    (maps,) = exr_maps(run, report)
    assert maps["rgb_std.R"].max() > 0, "the member's posterior samples differ"
    assert json.loads((run / "train_summary.json").read_text(encoding="utf-8"))["num_carriers"] == loaded.members[0].model.num_carriers
    from uncertsplat.config import PruneConfig
    from uncertsplat.errors import UserError
    from uncertsplat.stages import prune

    with pytest.raises(UserError, match="pruned member by member"):
        prune.run(run, tmp_path / "pruned", PruneConfig(keep_ratio=0.5), device=CPU)


def test_an_ensembles_predictor_gives_threads_the_serial_maps(ensemble_run):
    """``Predictor.predict`` from two threads at once on an ensemble run: each call gets the maps a serial call gets
    (one sampler serves every call; its member cycle must not mix the threads' draws)."""
    import threading

    from uncertsplat.predict import Predictor
    from uncertsplat.types import Cameras

    light = EvalConfig(num_samples=2, residual_views=0, consistency_views=0, resolution=0)
    pred = Predictor.load(ensemble_run, "cpu", cfg=light)
    cams = pred.scene.cameras
    cams = Cameras(cams.cam_from_world, cams.K, cams.width, cams.height, tuple(f"c{i}" for i in range(len(cams))))
    views = range(min(6, len(cams)))
    serial = [pred.predict(cams[[i]], seed=1) for i in views]
    got: dict[int, list] = {}

    def work(t: int) -> None:
        got[t] = [pred.predict(cams[[i]], seed=1) for _ in range(3) for i in views]

    threads = [threading.Thread(target=work, args=(t,)) for t in range(2)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert sorted(got) == [0, 1]
    for out in got.values():
        for j, o in enumerate(out):
            ref = serial[j % len(serial)]
            assert torch.equal(o.rgb_std, ref.rgb_std) and torch.equal(o.rgb_mean, ref.rgb_mean)
            assert torch.equal(o.depth_std, ref.depth_std)


def test_ensemble_of_one_has_zero_spread(ensemble_run, tmp_path):
    # an ensemble folder with N = 1 (member 0 of the N = 2 run; same layout, no retraining)
    run = tmp_path / "ens1"
    shutil.copytree(ensemble_run, run, ignore=shutil.ignore_patterns("member_1", "eval"))
    cfg = json.loads((run / "config.json").read_text(encoding="utf-8"))
    cfg["ensemble_size"] = 1
    (run / "config.json").write_text(json.dumps(cfg))
    # the samples' spread alone (no empty-ray term, no pixel noise, no depth spread along the rays, no view consistency)
    # is exactly 0 ...
    spread_only = EvalConfig(num_samples=3, max_views=2, empty_rays=False, residual_views=0, resolution=0,
                             depth_spread=False, consistency_views=0)
    report = evaluate.run(run, spread_only, device=CPU)
    for ch in exr_maps(run, report):
        assert ch["rgb_std.R"].shape == (H, W)
        assert np.all(ch["rgb_std.R"] == 0) and np.all(ch["depth_std.Z"] == 0)
    assert any("ensemble of 1 member" in n and "spread" in n for n in report.notes)
    # ... and the default predictive adds the pixel noise of the member's Gaussians
    report = evaluate.run(run, EvalConfig(num_samples=3, max_views=2), device=CPU)
    assert all(ch["rgb_std.R"].max() > 0 for ch in exr_maps(run, report))
    stored = EvalReport.from_json((run / "eval" / "metrics.json").read_text(encoding="utf-8"))
    assert any("ensemble of 1 member" in n for n in stored.notes)
    # its K samples are one render: a kernel density of them measures its bandwidth (a report showed 2,700 nats beside
    # -2.5 for the other runs), so none is given, and the note says why
    assert stored.mean.nll_kde is None and all(m.nll_kde is None for m in stored.per_view.values())
    assert any(n.startswith("KDE NLL not computed: the samples are one render") for n in stored.notes)


def test_fisher_variances_and_spread(fisher_run):
    run = fisher_run
    assert (run / FISHER_FILE).is_file()
    loaded = load_run(run, CPU)
    assert isinstance(loaded, FisherRun)
    assert loaded.model.num_carriers == 0, "the Fisher baseline starts from a plain (deterministic) 3DGS model"
    assert set(loaded.variance) == {"means", "scales", "opacities", "sh0"}
    cfg = loaded.config.fisher
    for name, prior in (("means", cfg.prior_std_means * loaded.extent), ("scales", cfg.prior_std_scales)):
        v = loaded.variance[name]
        assert v.shape == loaded.model.params[name].shape
        assert torch.all(v > 0) and torch.all(v <= prior**2 * (1 + 1e-5))
        assert bool((v < 0.99 * prior**2).any()), "observed Gaussians must be tighter than the prior"
    summary = json.loads((run / "train_summary.json").read_text(encoding="utf-8"))
    assert summary["seconds"] == pytest.approx(summary["train_seconds"] + summary["fisher_seconds"])
    # the viewer PLY carries the posterior's spreads (they were 0, read as a certain model), the standard layout kept
    from plyfile import PlyData

    v = PlyData.read(str(run / "point_cloud.ply"))["vertex"].data
    names = v.dtype.names
    assert names.index("rot_3") < names.index("uncertainty_position") and len(v) == len(loaded.model)
    position = loaded.variance["means"].double().mean(1).sqrt().numpy()
    np.testing.assert_allclose(v["uncertainty_position"], position, rtol=1e-5)
    assert (v["uncertainty_scale"] > 0).all() and (v["uncertainty_gate"] > 0).all() and (v["has_posterior"] == 1).all()
    assert (v["uncertainty_switch_off"] == 0).all()
    report = evaluate.run(run, EvalConfig(num_samples=3, max_views=2, seed=1), device=CPU)
    for ch in exr_maps(run, report):
        assert ch["rgb_std.R"].shape == (H, W) and ch["rgb_std.R"].max() > 0
        assert ch["depth_std.Z"].max() > 0
    scene = loaded.load_scene()
    cfg = EvalConfig(num_samples=3, max_views=2, seed=1)
    field = fit_residual(loaded.sampler(scene.scene_scale, CPU), scene.split["train"], cfg, CPU,
                         load_views=partial(load_view_set, scene, depth=False))
    again = evaluate_views(with_side_terms(loaded.sampler(scene.scene_scale, CPU), field,
                                           scene.cameras[scene.split["train"]], cfg, CPU),
                           load_view_set(scene, report_indices(run, 2)), cfg, CPU, show_progress=False)
    assert again.mean.ause_mae == pytest.approx(report.mean.ause_mae, rel=1e-6)  # explicit generator: repeatable


def report_indices(run, n):
    scene = load_run(run, CPU).load_scene()
    return list(scene.split["test"])[:n]


def test_vi_single_through_the_cli(scene_path, tmp_path):
    run = tmp_path / "vi1"
    res = CliRunner().invoke(app, ["train", str(scene_path), "-o", str(run), "--preset", "tiny",
                                   "--method", "vi-single", "--device", "cpu",
                                   "--set", "iterations=20", "--set", "scene.downscale=4.0",
                                   "--set", "eval_every=1000", "--set", "checkpoint_every=1000",
                                   "--set", "densify={start=5, until=15, interval=5, spawn_interval=10}"])
    assert res.exit_code == 0, res.output
    cfg = json.loads((run / "config.json").read_text(encoding="utf-8"))
    assert cfg["method"] == "variational" and cfg["variational"]["num_entries"] == 1
    loaded = load_run(run, CPU)
    assert loaded.model.num_entries == 1 and loaded.model.num_carriers > 0
    report = evaluate.run(run, EvalConfig(num_samples=3, max_views=1), device=CPU)
    (ch,) = exr_maps(run, report)
    assert ch["rgb_std.R"].shape == (H, W) and ch["rgb_std.R"].max() > 0


def test_ensemble_members_do_not_say_done(scene_path, tmp_path):
    """Each member's closing line names the member; only the ensemble's own line says "done"."""
    run = tmp_path / "ens"
    res = CliRunner().invoke(app, ["train", str(scene_path), "-o", str(run), "--preset", "tiny",
                                   "--method", "ensemble", "--device", "cpu", "--set", "ensemble_size=2",
                                   "--set", "iterations=6", "--set", "scene.downscale=4.0",
                                   "--set", "eval_every=1000", "--set", "checkpoint_every=1000"])
    assert res.exit_code == 0, res.output
    text = " ".join(res.output.split())
    assert "member 1/2 trained: 6 steps" in text and "member 2/2 trained: 6 steps" in text
    assert [line.split(":")[0] for line in res.output.splitlines() if line.startswith("done")] == ["done"]
    assert "done: ensemble of 2 members" in text and "the members' held-out PSNR" in text
    res = CliRunner().invoke(app, ["evaluate", str(run), "--num-samples", "3", "--set", "max_views=1", "--device", "cpu"])
    assert res.exit_code == 0, res.output
    flat = " ".join(res.output.split())
    assert " Gaussians in 2 members (no posterior)" in flat and "note: K=3 is not a multiple of the 2 ensemble" in flat


def test_an_interrupted_ensemble_resumes_as_one(scene_path, tmp_path):
    """An ensemble stopped in its second member names the ensemble's folder to resume, and a plain --resume (without
    --method ensemble) finishes the ensemble instead of training one model into its folder."""
    from uncertsplat.errors import UserError
    from uncertsplat.schemas import TrainSummary

    run, members = tmp_path / "ens", []

    def stop_the_second(trainer):  # as if Ctrl-C arrived at step 10 of member 2
        members.append(trainer)
        if len(members) == 2:
            trainer.on_log = lambda rec: setattr(trainer, "_stop", rec["step"] >= 10)

    with pytest.raises(UserError) as info:
        train_run(scene_path, run, quick_cfg(method="ensemble", ensemble_size=3), CPU, on_trainer=stop_the_second)
    assert info.value.hint.endswith(f"-o {q(run)} --resume")
    # the run's own length given again (`--set iterations=20`, as the first command had it) is nothing to extend
    train_run(scene_path, run, quick_cfg(), CPU, resume=True, extend_to=20)  # the command's default method
    summary = TrainSummary.read(run / "train_summary.json")
    assert summary.method == "ensemble" and len(summary.members) == 3
    assert all(m.steps == 20 for m in summary.members)
    assert not (run / "ckpts").exists() and not (run / "point_cloud.ply").exists()


def test_an_unfinished_run_is_evaluated_with_a_note(scene_path, tmp_path):
    """A run stopped at step 10 of 20 and not resumed: evaluate measures its checkpoint and says so (with the
    command that finishes it); a finished run has no such note."""
    from uncertsplat.errors import Interrupted

    run = tmp_path / "half"

    def stop(trainer):
        trainer.on_log = lambda rec: setattr(trainer, "_stop", rec["step"] >= 10)

    with pytest.raises(Interrupted):
        train_run(scene_path, run, quick_cfg(), CPU, on_trainer=stop)
    report = evaluate.run(run, EvalConfig(num_samples=2, max_views=1), device=CPU)
    (note,) = [n for n in report.notes if "training is not finished: its newest checkpoint is step" in n]
    assert "step 10 of 20" in note and f"-o {q(run)} --resume" in note
    assert load_run(run, CPU).unfinished_notes() == [note]
    train_run(scene_path, run, quick_cfg(), CPU, resume=True)
    assert load_run(run, CPU).unfinished_notes() == []
    # a --resume that carries the finished run on and is stopped: its variational.ply is the step-20 model, and
    # every command scored that one without a word while the checkpoints went on (views added counted as trained)

    def stop_later(trainer):
        trainer.on_log = lambda rec: setattr(trainer, "_stop", rec["step"] >= 30)

    with pytest.raises(Interrupted):
        train_run(scene_path, run, quick_cfg(), CPU, resume=True, extend_to=40, on_trainer=stop_later)
    loaded = load_run(run, CPU)
    assert loaded.source.suffix == ".pt" and loaded.step == 30
    (note,) = loaded.unfinished_notes()
    assert "step 30 of 40" in note


@pytest.mark.parametrize("which", ["ensemble", "fisher"])
def test_prune_refuses_a_baseline_naming_its_method(which, ensemble_run, fisher_run, tmp_path):
    from uncertsplat.config import PruneConfig
    from uncertsplat.errors import UserError
    from uncertsplat.stages import prune

    run = ensemble_run if which == "ensemble" else fisher_run
    with pytest.raises(UserError, match=f"an? {which} run has no per-Gaussian posterior") as info:
        prune.run(run, tmp_path / "out", PruneConfig(keep_ratio=0.5), device=CPU)
    assert not (tmp_path / "out").exists()
    from uncertsplat.errors import NoPosterior

    # a method without one is a mistake a pipeline stops at (it skips a prune of a run too short for one)
    assert not isinstance(info.value, NoPosterior) and "variational method" in str(info.value)
    # a plain model (Fisher's) can be given the posterior without training again; an ensemble's members cannot
    assert ("--from-ply" in str(info.value)) == (which == "fisher"), str(info.value)


def test_unknown_method_is_a_user_error(scene_path, tmp_path):
    res = CliRunner().invoke(app, ["train", str(scene_path), "-o", str(tmp_path / "x"), "--method", "mc-dropout"])
    assert res.exit_code == 2 and "unknown method" in res.output and "ensemble" in res.output


@pytest.mark.parametrize("which", ["ensemble", "fisher"])
def test_viewer_renders_baseline_runs(which, ensemble_run, fisher_run):
    # `uncertsplat view` opens every method: the render modes and a posterior spread, no prune preview
    from uncertsplat.baselines import load_run
    from uncertsplat.view.frames import FrameRenderer

    run = ensemble_run if which == "ensemble" else fisher_run
    loaded = load_run(run, CPU)
    scene = loaded.load_scene()
    r = FrameRenderer(loaded, scene.scene_scale, CPU)
    assert r.modes() == ["rgb", "depth", "rgb_std", "depth_std"] and r.has_posterior
    cam = scene.cameras[[0]]
    assert r.frame(cam, "rgb").image.std() > 5
    std = r.frame(cam, "rgb_std", num_samples=4)
    assert std.samples == 4 and np.nanmax(std.values) > 0


def test_an_ensemble_whose_scene_is_refused_leaves_no_run_behind(scene_path, tmp_path):
    """The ensemble wrote config.json and members/ before its first member read the scene: a scene error left them,
    the same command was then refused as an existing run, and --resume went on with the failed settings. Nothing
    trained, nothing is left; a member that trained something keeps the run."""
    from uncertsplat.errors import UserError

    run = tmp_path / "run"
    bad = quick_cfg(method="ensemble", ensemble_size=2, scene={"test_names": ["no_such_view.png"]})
    for _ in range(2):  # the same command again: the same scene error, not "already exists"
        with pytest.raises(UserError, match="no_such_view.png"):
            train_run(scene_path, run, bad, CPU)
        assert not (run / "config.json").exists() and not (run / "members").exists()
    train_run(scene_path, run, quick_cfg(method="ensemble", ensemble_size=1), CPU)
    assert (run / "train_summary.json").is_file()


def test_an_ensemble_out_of_memory_before_any_checkpoint_can_be_started_again(scene_path, tmp_path, monkeypatch):
    """Memory that ran out in the first member left config.json and members/: the same command with a larger
    downscale (what the error advises) was refused as an existing run. A bug's RuntimeError still keeps the folder."""
    from uncertsplat.train.trainer import Trainer

    run = tmp_path / "run"
    real = Trainer.fit

    def out(self, *a, **k):
        raise RuntimeError("DefaultCPUAllocator: can't allocate memory: you tried to allocate 108000000 bytes")

    monkeypatch.setattr(Trainer, "fit", out)
    with pytest.raises(RuntimeError, match="can't allocate memory"):
        train_run(scene_path, run, quick_cfg(method="ensemble", ensemble_size=2), CPU)
    assert not (run / "config.json").exists() and not (run / "members").exists()

    def bug(self, *a, **k):
        raise RuntimeError("shape mismatch")

    monkeypatch.setattr(Trainer, "fit", bug)
    with pytest.raises(RuntimeError, match="shape mismatch"):
        train_run(scene_path, run, quick_cfg(method="ensemble", ensemble_size=2), CPU)
    assert (run / "config.json").exists()  # (kept as it was: a bug is reported, not tidied away)
    monkeypatch.setattr(Trainer, "fit", real)
