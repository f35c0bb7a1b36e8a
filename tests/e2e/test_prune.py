"""`prune` end to end on a trained tiny run: a valid new run, reversible mask, dry run, sweep, bad input."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from plyfile import PlyData
from typer.testing import CliRunner

from tests.fixtures import tiny_scene_path  # noqa: F401
from tests.run_fixtures import tiny_run_path  # noqa: F401
from uncertsplat.baselines import load_run
from uncertsplat.cli import app
from uncertsplat.config import PruneConfig, TrainConfig
from uncertsplat.console import q
from uncertsplat.errors import UserError
from uncertsplat.gaussians.variational import random_model
from uncertsplat.io.ply import write_variational_ply
from uncertsplat.schemas import PruneReport, PruneSweep
from uncertsplat.stages import prune
from uncertsplat.uncertainty.scores import DEFAULT_SCORE

runner = CliRunner()
CPU = torch.device("cpu")
FAST = dict(num_samples=2, score_views=2, score_samples=2, render_views=1)


def _digest(folder):
    return {p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def pruned(tiny_run_path, tmp_path_factory):  # noqa: F811
    before = _digest(tiny_run_path)
    out = tmp_path_factory.mktemp("pr") / "pruned"
    cfg = PruneConfig(keep_ratio=0.8, sweep=True, sweep_ratios=[1.0, 0.8], **FAST)
    result = prune.run(tiny_run_path, out, cfg, device=CPU)
    return out, result, before


def test_writes_a_valid_pruned_run(pruned, tiny_run_path):  # noqa: F811
    out, result, before = pruned
    assert _digest(tiny_run_path) == before  # the input run is never modified
    src = load_run(tiny_run_path, CPU).model
    loaded = load_run(out, CPU)
    loaded.model.check()
    n = len(src)
    assert result.counts.before == n and len(loaded.model) == result.counts.after
    assert n - round(0.2 * n) <= result.counts.after < n  # (some removed, never more than asked)
    assert (out / "config.json").read_bytes() == (tiny_run_path / "config.json").read_bytes()
    assert json.loads((out / "prune_config.json").read_text(encoding="utf-8"))["keep_ratio"] == result.keep_ratio  # its settings
    assert (out / "scene.json").is_file() and (out / "point_cloud.ply").is_file()
    # the source's scene record, with the scene's path relative to the pruned run (not the source's: from another
    # folder it named whatever lay there)
    source, written = (json.loads((d / "scene.json").read_text(encoding="utf-8")) for d in (tiny_run_path, out))
    assert {**written, "scene_from_run": None} == {**source, "scene_from_run": None}
    assert (out / written["scene_from_run"]).resolve() == Path(source["scene"]).resolve()
    umask = os.umask(0)
    os.umask(umask)
    assert out.stat().st_mode & 0o777 == 0o777 & ~umask  # as any output folder (the temp folder's 0700 before)
    # the mask reproduces the pruned model from the untouched source run
    kept = np.load(out / "prune_mask.npy")
    assert kept.dtype == np.int64 and len(kept) == len(loaded.model) and np.all(np.diff(kept) > 0)
    for name, t in src.params.items():
        torch.testing.assert_close(loaded.model.params[name].detach(), t.detach()[torch.from_numpy(kept)])
    rebuilt = prune.rebuild_from_mask(tiny_run_path, out / "prune_mask.npy")
    for name, t in rebuilt.tables.items():
        torch.testing.assert_close(loaded.model.tables[name].detach(), t.detach())
    # scores are extra PLY properties; the removed Gaussians are the highest-scoring carriers
    ply = PlyData.read(str(out / "point_cloud.ply"))
    props = {p.name for p in ply["vertex"].properties}
    assert {"score_position", "score_scale", "score_gate", f"score_{DEFAULT_SCORE}".replace("-", "_"), "x",
            "opacity"} <= props
    assert all(p.isidentifier() for p in props)  # score_free_space, not score_free-space
    degree = loaded.sh_degree  # the pruned point cloud keeps the bands the source renders with, as train's
    assert sum(p.startswith("f_rest_") for p in props) == 3 * ((degree + 1) ** 2 - 1)
    scores = np.load(out / "scores.npz")
    s = scores[result.score]
    removed = np.setdiff1d(np.arange(n), kept)
    assert scores["carriers"][removed].all()
    assert s[removed].min() >= s[kept][scores["carriers"][kept]].max()
    # prune.json: metrics before/after/random, seed, the curve, renders
    data = PruneReport.read(out / "prune.json")
    assert data == result  # what run() returns is what it wrote
    for m in (data.metrics.before, data.metrics.after, data.metrics.random):
        assert np.isfinite(m.psnr) and m.num_gaussians > 0
    assert data.metrics.random.num_gaussians == data.metrics.after.num_gaussians
    assert data.metrics.after.variational_ply_bytes < data.metrics.before.variational_ply_bytes
    assert data.seed == 0 and data.score == DEFAULT_SCORE and data.source_run == str(tiny_run_path.resolve())
    sweep = PruneSweep.read(out / "sweep.json")
    assert sweep == data.sweep
    assert [p.keep_ratio for p in sweep.points] == [1.0, 0.8]
    assert sweep.points[1].score.psnr == data.metrics.after.psnr  # same mask, same metrics
    assert sweep.points[0].score.psnr == data.metrics.before.psnr
    assert len(list((out / "renders").glob("*_before.png"))) == 1
    assert len(list((out / "renders").glob("*_after.png"))) == 1


def test_the_pruned_run_is_evaluated_as_evaluate_does_and_evaluate_keeps_it(pruned, capsys):
    from uncertsplat.config import EvalConfig
    from uncertsplat.schemas import EvalReport
    from uncertsplat.stages import evaluate

    out, result, _ = pruned
    report = EvalReport.read(out / "eval" / "metrics.json")
    after = result.metrics.after
    assert (after.psnr, after.ause_mae, after.nll) == (report.mean.psnr, report.mean.ause_mae, report.mean.nll)
    assert any("the pruned model's uncertainty metrics are evaluate's" in n for n in result.notes)
    capsys.readouterr()
    again = evaluate.run(out, EvalConfig(num_samples=FAST["num_samples"]), device=CPU)
    assert again == report and "already evaluated" in " ".join(capsys.readouterr().err.split())


def test_the_pruned_run_counts_empty_rays_against_its_source_s_coverage(pruned, tiny_run_path, tmp_path):  # noqa: F811
    """Pruning changes the model, not what the photos showed: the pruned run's evaluation takes the source model's
    coverage (recorded in prune.json), where its own would sink with the Gaussians removed (to 0.001 for a prune to
    0.1 %, and then no ray counts as empty)."""
    from uncertsplat.baselines.runs import load_run as load

    out, result, _ = pruned
    src = load(tiny_run_path, CPU)
    scene = src.load_scene()
    own = src.coverage(scene.scene_scale, CPU)
    assert result.source_coverage == pytest.approx(own) and PruneReport.read(out / "prune.json").source_coverage == own
    pruned_run = load(out, CPU)
    assert pruned_run.coverage(scene.scene_scale, CPU) == own
    # the pruned model's own coverage is lower: what the evaluation used before it was recorded
    from uncertsplat.gaussians import variational
    from uncertsplat.uncertainty.mc import training_coverage

    sample = variational.expected_render_sample(pruned_run.model, **pruned_run.sample_kwargs)
    train = list(scene.split["train"])
    assert training_coverage(sample, scene.cameras[train], pruned_run.render_fn(scene.scene_scale, CPU)) < own
    # a prune.json that does not read: the run's own coverage, as before
    copy = tmp_path / "copy"
    import shutil
    shutil.copytree(out, copy)
    (copy / "prune.json").write_text("{")
    assert load(copy, CPU).coverage(scene.scene_scale, CPU) < own


def test_a_dry_run_reports_the_after_row_the_written_prune_does(pruned, tiny_run_path):  # noqa: F811
    """--dry-run previews the prune: its 'after' row is the pruned model evaluated as `evaluate` does, as the written
    prune's (it kept the source's fitted noise and tails: AUSE 0.189 against 0.184 on the demo run)."""
    from uncertsplat.schemas.prune import METRIC_KEYS

    _, result, _ = pruned
    cfg = PruneConfig(keep_ratio=0.8, sweep=True, sweep_ratios=[1.0, 0.8], dry_run=True, **FAST)
    dry = prune.run(tiny_run_path, None, cfg, device=CPU)
    assert dry.counts == result.counts
    for k in METRIC_KEYS:
        assert getattr(dry.metrics.after, k) == getattr(result.metrics.after, k), k
    assert any("evaluated as `evaluate` does" in n and "not kept" in n for n in dry.notes)
    assert not any(n.startswith("the pruned model's uncertainty metrics are evaluate's") for n in dry.notes)


def test_dry_run_on_a_pruned_run_writes_no_model(pruned, tmp_path):
    out, _, _ = pruned
    before = _digest(out)
    dry = tmp_path / "dry"
    result = prune.run(out, dry, PruneConfig(keep_ratio=0.9, dry_run=True, **FAST), device=CPU)
    assert _digest(out) == before  # a pruned run is a valid input, and stays unchanged
    names = {p.name for p in dry.iterdir()}
    assert "prune.json" in names and "prune_mask.npy" in names
    assert not names & {"variational.ply", "point_cloud.ply", "config.json", "ckpts"}
    assert result.counts.after < result.counts.before == len(load_run(out, CPU).model)
    assert PruneReport.read(dry / "prune.json").written.model is False
    # loaded as a run (evaluate, view, select-views, the Python API): named as a prune without a model, with its source
    with pytest.raises(UserError, match=r"a dry-run prune \(prune --dry-run\): it wrote no model") as err:
        load_run(dry, CPU)
    assert str(out) in err.value.hint


def test_bad_inputs(tiny_run_path, tmp_path):  # noqa: F811
    cfg = PruneConfig(keep_ratio=0.9, **FAST)
    with pytest.raises(UserError, match="run folder not found"):
        prune.run(tmp_path / "nope", tmp_path / "o", cfg, device=CPU)
    with pytest.raises(UserError, match="is the input run"):
        prune.run(tiny_run_path, tiny_run_path, cfg, device=CPU)
    with pytest.raises(UserError, match="inside the input run"):
        prune.run(tiny_run_path, tiny_run_path / "sub", cfg, device=CPU)
    existing = tmp_path / "existing"
    existing.mkdir()
    (existing / "keep.txt").write_text("mine")
    with pytest.raises(UserError, match="already exists"):
        prune.run(tiny_run_path, existing, cfg, device=CPU)
    assert (existing / "keep.txt").read_text(encoding="utf-8") == "mine" and len(list(existing.iterdir())) == 1
    with pytest.raises(UserError, match="no output folder"):
        prune.run(tiny_run_path, None, cfg, device=CPU)
    with pytest.raises(UserError, match="no pruning mode"):
        prune.run(tiny_run_path, tmp_path / "o2", PruneConfig(**FAST), device=CPU)
    with pytest.raises(UserError, match="unknown score"):
        prune.run(tiny_run_path, tmp_path / "o3", PruneConfig(keep_ratio=0.9, score="entropy"), device=CPU)
    assert not (tmp_path / "o2").exists() and not (tmp_path / "o3").exists()


def test_run_without_posterior_is_refused(tiny_run_path, tmp_path):  # noqa: F811
    run = tmp_path / "det"
    run.mkdir()
    for name in ("config.json", "scene.json"):
        (run / name).write_bytes((tiny_run_path / name).read_bytes())
    model = random_model(20, torch.Generator().manual_seed(0), carrier_fraction=0.0)
    write_variational_ply(run / "variational.ply", model, meta={"extent": 1.0})
    with pytest.raises(UserError, match="no Gaussians with a posterior"):
        prune.run(run, tmp_path / "out", PruneConfig(keep_ratio=0.5, **FAST), device=CPU)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("ratio", ["0", "1.5", "-0.2"])
def test_cli_rejects_ratio_outside_unit_interval(tiny_run_path, tmp_path, ratio):  # noqa: F811
    res = runner.invoke(app, ["prune", str(tiny_run_path), "-o", str(tmp_path / "o"), "--keep-ratio", ratio,
                              "--device", "cpu"])
    assert res.exit_code != 0
    assert "--keep-ratio" in res.output  # the option the user typed, not the config key
    assert not (tmp_path / "o").exists()


class TestAuto:
    """``--auto``: the strongest pruning of the sweep whose held-out PSNR stays within the tolerance."""

    def test_a_loose_tolerance_takes_the_strongest_ratio(self, tiny_run_path):  # noqa: F811
        cfg = PruneConfig(auto=True, tolerance_db=100.0, sweep_ratios=[1.0, 0.9, 0.6], dry_run=True, **FAST)
        result = prune.run(tiny_run_path, None, cfg, device=CPU)
        n = result.counts.before
        assert result.mode == "auto" and result.keep_ratio == 0.6
        assert result.counts.removed == round(0.4 * n)
        best = result.sweep.largest_removal_within_tolerance
        assert best.keep_ratio == 0.6 and best.psnr_loss_db <= 100.0
        # the choice was made on the held-out views it reports on: said
        assert any(n.startswith("the keep ratio and the score were chosen on these held-out views") for n in result.notes)

    def test_nothing_within_tolerance_removes_nothing_and_says_why(self, tiny_run_path):  # noqa: F811
        # removing 70 % of a trained model always costs PSNR, so a zero tolerance admits no ratio
        cfg = PruneConfig(auto=True, tolerance_db=0.0, sweep_ratios=[1.0, 0.3], dry_run=True, **FAST)
        result = prune.run(tiny_run_path, None, cfg, device=CPU)
        assert result.keep_ratio == 1.0 and result.counts.removed == 0
        assert result.sweep.largest_removal_within_tolerance is None
        (note,) = [x for x in result.notes if x.startswith("--auto")]
        assert "nothing was removed" in note and "70 %" in note and "--tolerance-db" in note
        # nothing removed: the 'after' row is the 'before' row, which no choice on these views flatters
        assert not any("chosen on these held-out views" in x for x in result.notes)

    def test_a_score_chosen_alone_is_said_in_the_singular(self, tiny_run_path):  # noqa: F811
        cfg = PruneConfig(keep_ratio=0.8, dry_run=True, **FAST)
        result = prune.run(tiny_run_path, None, cfg, device=CPU)
        assert any(x.startswith("the score was chosen on these held-out views") for x in result.notes)

    def test_auto_alone_measures_no_ratio_past_the_first_failure(self, tiny_run_path):  # noqa: F811
        """The decision never looks past the first ratio that fails, so ``--auto`` stops measuring there, and it
        measures the ratios it walks by their expected render only (the decision's PSNR); with ``--sweep`` the whole
        curve is measured, uncertainty included, and the choice is the same."""
        common = dict(auto=True, tolerance_db=0.0, sweep_ratios=[1.0, 0.5, 0.3, 0.2], dry_run=True, **FAST)
        alone = prune.run(tiny_run_path, None, PruneConfig(**common), device=CPU)
        # (--sweep measures one score: the one --auto kept, the nearest miss where no score removes anything)
        full = prune.run(tiny_run_path, None, PruneConfig(**common, sweep=True, score=alone.score), device=CPU)
        assert [p.keep_ratio for p in full.sweep.points] == [1.0, 0.5, 0.3, 0.2]
        assert [p.keep_ratio for p in alone.sweep.points] == [1.0, 0.5]  # removing half fails a zero tolerance
        assert alone.keep_ratio == full.keep_ratio == 1.0
        assert alone.sweep.metric == full.sweep.metric == "psnr_render"
        assert alone.sweep.points[1].score.psnr_render == full.sweep.points[1].score.psnr_render
        assert alone.sweep.points[1].random.psnr_render == full.sweep.points[1].random.psnr_render
        # the uncertainty of the ratios walked: measured with --sweep, not by --auto alone
        assert not alone.sweep.uncertainty_measured and full.sweep.uncertainty_measured
        assert alone.sweep.points[1].score.psnr is None and alone.sweep.points[1].score.ause_mae is None
        assert full.sweep.points[1].score.psnr is not None and full.sweep.points[1].score.ause_mae is not None
        # the unpruned model is measured in full either way, its render PSNR the same
        assert alone.sweep.unpruned == alone.metrics.before and alone.metrics.before.ause_mae is not None
        assert alone.metrics.before.psnr_render == pytest.approx(full.metrics.before.psnr_render, abs=0)

    def test_auto_names_the_psnr_its_tolerance_bounds(self, tiny_run_path):  # noqa: F811
        """The tolerance is checked on the expected render's PSNR; the table's PSNR and ``delta_psnr_db`` are the
        mean of K samples' renders, which may fall further: a note gives both changes, and the first is within the
        tolerance."""
        cfg = PruneConfig(auto=True, tolerance_db=5.0, sweep_ratios=[1.0, 0.7], dry_run=True, **FAST)
        result = prune.run(tiny_run_path, None, cfg, device=CPU)
        assert result.counts.removed > 0
        (note,) = [x for x in result.notes if x.startswith("the tolerance bounds the expected render's PSNR")]
        m = result.metrics
        assert f"{m.before.psnr_render:.3f} -> {m.after.psnr_render:.3f} dB" in note
        assert m.before.psnr_render - m.after.psnr_render <= 5.0
        assert f"({result.delta_psnr_db.score:+.3f} dB)" in note

    def test_cli_tolerance_option(self, tiny_run_path, tmp_path):  # noqa: F811
        res = runner.invoke(app, ["prune", str(tiny_run_path), "--auto", "--tolerance-db", "0", "--dry-run",
                                  "--set", "sweep_ratios=[1.0, 0.3]", "--set", "num_samples=2",
                                  "--set", "score_views=2", "--set", "render_views=0", "--device", "cpu"])
        assert res.exit_code == 0, res.output
        assert "nothing was removed" in " ".join(res.output.split())  # rich may wrap the line anywhere


def test_viewer_opens_the_pruned_run(pruned):  # noqa: F811
    from uncertsplat.baselines import load_run
    from uncertsplat.view.frames import FrameRenderer

    out, result, _ = pruned
    loaded = load_run(out, CPU)
    scene = loaded.load_scene()
    r = FrameRenderer(loaded, scene.scene_scale, CPU)
    assert "prune" in r.modes()  # a pruned run keeps its carriers: it can be pruned (and previewed) again
    frame = r.frame(scene.cameras[[0]], "rgb")
    assert frame.image.shape == (scene.cameras.height, scene.cameras.width, 3) and frame.image.std() > 5


def test_a_killed_prune_s_staging_folder_is_removed_by_the_next(tiny_run_path, tmp_path):  # noqa: F811
    """A prune killed while writing left `.OUT.tmp-PID-*` holding a whole model; the next prune into that output
    removes it when its process is gone, and leaves a live process's."""
    import subprocess
    import sys

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    host = prune._host_tag()
    stale = tmp_path / f".out.tmp-{host}-{dead.pid}-abc"
    live = tmp_path / f".out.tmp-{host}-{os.getpid()}-def"
    elsewhere = tmp_path / f".out.tmp-otherhost-{dead.pid}-ghi"  # another machine's: its PID means nothing here
    for p in (stale, live, elsewhere):
        p.mkdir()
        (p / "variational.ply").write_bytes(b"x" * 100)
    cfg = PruneConfig(keep_ratio=0.9, **FAST)
    prune.run(tiny_run_path, tmp_path / "out", cfg, device=CPU)
    assert not stale.exists() and live.is_dir() and elsewhere.is_dir() and (tmp_path / "out" / "prune.json").is_file()


def test_a_loaded_run_reads_its_scene_once(tiny_run_path, monkeypatch):
    """``LoadedRun.load_scene`` reads the scene folder once, its ``with_model`` copies (prune's pruned models) share
    it: a million-point COLMAP model takes seconds to read, and prune --auto read it six times, evaluate twice."""
    from uncertsplat.sfm import scene as scene_mod

    reads = []
    real = scene_mod.load_scene
    monkeypatch.setattr(scene_mod, "load_scene", lambda *a, **k: reads.append(a[0]) or real(*a, **k))
    loaded = load_run(tiny_run_path, CPU)
    first = loaded.load_scene()
    assert loaded.load_scene() is first
    pruned = loaded.with_model(loaded.model)
    assert pruned.load_scene() is first
    assert len(reads) == 1
    assert load_run(tiny_run_path, CPU).load_scene() is not first and len(reads) == 2  # another load reads again


def test_a_pruned_run_is_not_trained_on_and_select_views_names_its_source(pruned, tiny_scene_path, tmp_path,
                                                                           capsys):  # noqa: F811
    """A pruned run holds a model and config.json but no checkpoint: `train --resume` there started from step 0 and
    wrote a new model over the pruned one (select-views had suggested it); now it is refused, naming the source run,
    and select-views suggests adding the views to the source run."""
    import shutil

    from uncertsplat.baselines import train_run
    from uncertsplat.config import SelectConfig
    from uncertsplat.stages import select

    out, result, _ = pruned
    run = tmp_path / "pruned"
    shutil.copytree(out, run)
    model = (run / "variational.ply").read_bytes()
    cfg = TrainConfig.model_validate_json((run / "config.json").read_text(encoding="utf-8"))
    with pytest.raises(UserError, match="this folder is a pruned model") as err:
        train_run(tiny_scene_path, run, cfg.model_copy(update={"iterations": cfg.iterations + 10}), CPU, resume=True)
    assert result.source_run in err.value.hint and (run / "variational.ply").read_bytes() == model
    select.run(run, SelectConfig(score="coverage", candidates="around:3"), CPU, output=tmp_path / "sel")
    said = " ".join(capsys.readouterr().err.split())
    assert f"is a pruned model (prune.json): the views are added to the run it was pruned from, {result.source_run}" \
        in said
    assert f"-o {run} --resume" not in said
    # a prune of a prune: the training run at the chain's start, not the first prune (refused too)
    again = tmp_path / "again"
    shutil.copytree(run, again)
    rep = PruneReport.read(again / "prune.json")
    rep.source_run, rep.source_from_run = str(run), None
    rep.write(again / "prune.json")
    assert PruneReport.training_run(again) == Path(result.source_run) == PruneReport.training_run(run)
    with pytest.raises(UserError) as err:
        train_run(tiny_scene_path, again, cfg, CPU, resume=True)
    assert result.source_run in err.value.hint and str(run) + " " not in err.value.hint
    rep.source_run = str(again)  # a loop: no training run to name
    rep.write(again / "prune.json")
    assert PruneReport.training_run(again) is None and PruneReport.training_run(tiny_scene_path) is None


def test_a_model_is_not_pruned_by_the_predictive_score(tiny_run_path, tmp_path):  # noqa: F811
    """It ranks the Gaussians the images need most first (fern at keep 0.8: 27.1 -> 8.2 dB, and the note that said so
    came after the model was written): refused before any work, no folder made; --dry-run still measures it."""
    out = tmp_path / "out"
    for cfg in (PruneConfig(keep_ratio=0.8, score="predictive"), PruneConfig(auto=True, score="predictive")):
        with pytest.raises(UserError, match="the predictive score ranks first the Gaussians") as err:
            prune.run(tiny_run_path, out, cfg, device=CPU)
        assert "--dry-run or --sweep" in err.value.hint and not out.exists()


def test_an_evaluation_that_fails_leaves_no_output_and_its_advice_works(tiny_run_path, tmp_path, monkeypatch):  # noqa: F811
    """A full disk while prune evaluated the pruned run: the run was already under its final name, so the evaluation's
    advice ("free some space, then run again") led to a prune refused because its output existed. The evaluation runs
    in the staging folder now: nothing is left, the file is named as it lies in the output, and running again works."""
    from uncertsplat.stages import evaluate

    real = evaluate.run

    def full(run_dir, *args, **kwargs):
        raise UserError("could not write the file: the disk is full; nothing was left half-written",
                        path=Path(run_dir) / "eval" / "maps" / "view_000_rgb.png",
                        hint="Free some space or choose another output folder, then run again.")

    out = tmp_path / "out"
    monkeypatch.setattr(evaluate, "run", full)
    with pytest.raises(UserError) as err:
        prune.run(tiny_run_path, out, PruneConfig(keep_ratio=0.8, **FAST), device=CPU)
    said = err.value.render()
    assert "prune's evaluation of the pruned run failed" in said and "nothing was written" in said, said
    assert err.value.path == out / "eval" / "maps" / "view_000_rgb.png" and "Free some space" in said, said
    assert not out.exists() and list(tmp_path.iterdir()) == [], list(tmp_path.iterdir())
    monkeypatch.setattr(evaluate, "run", real)
    from uncertsplat.io import ply

    real_model = ply.write_variational_ply

    def model_full(path, *args, **kwargs):  # the same for the model itself: named where it was to be, not in staging
        if not Path(path).parent.name.startswith(".out.tmp-"):  # (the file sizes prune measures, elsewhere)
            return real_model(path, *args, **kwargs)
        raise UserError("could not write the file: the disk is full; nothing was left half-written", path=path)

    monkeypatch.setattr(ply, "write_variational_ply", model_full)
    with pytest.raises(UserError) as err:
        prune.run(tiny_run_path, out, PruneConfig(keep_ratio=0.8, **FAST), device=CPU)
    assert err.value.path == out / "variational.ply" and str(out / "variational.ply") in str(err.value)
    assert list(tmp_path.iterdir()) == []
    monkeypatch.undo()  # space freed: the same command
    result = prune.run(tiny_run_path, out, PruneConfig(keep_ratio=0.8, **FAST), device=CPU)
    assert result.metrics.after.ause_mae is not None and (out / "eval" / "metrics.json").is_file()


def test_ctrl_c_during_the_evaluation_writes_nothing(tiny_run_path, tmp_path, monkeypatch):  # noqa: F811
    """Ctrl-C while prune evaluated the pruned run: the CLI says "nothing was written (the output folder appears only
    when prune has finished)", which now holds; the run had been renamed into place before its evaluation."""
    from uncertsplat.stages import evaluate

    def stop(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(evaluate, "run", stop)
    with pytest.raises(KeyboardInterrupt):
        prune.run(tiny_run_path, tmp_path / "out", PruneConfig(keep_ratio=0.8, **FAST), device=CPU)
    assert list(tmp_path.iterdir()) == []


_KILLED_IN_EVALUATION = """
import os, signal, sys
from uncertsplat.stages import evaluate
def killed(*args, **kwargs):  # the evaluation's maps are written (in its staging folder): killed before they are put
    os.kill(os.getpid(), signal.SIGKILL)
evaluate._put_in_place = killed
from uncertsplat.cli import app
sys.argv = ["uncertsplat", *{args!r}]
app()
"""


def test_a_prune_killed_during_its_evaluation_leaves_no_output_and_the_same_command_works(tiny_run_path,  # noqa: F811
                                                                                             tmp_path):
    """kill -9 while prune evaluated the pruned run left OUT with a prune.json without its "after" row, the
    evaluation's staging maps and a dead lock, and the same command refused it ("the output folder already exists").
    Now OUT does not exist; the killed process's staging folder is removed by the next prune, which finishes."""
    import signal

    from tests.reliability.helpers import finish, run_cli, start_python

    out = tmp_path / "out"
    args = ["prune", str(tiny_run_path), "-o", str(out), "--keep-ratio", "0.8", "--device", "cpu",
            *[a for k, v in FAST.items() for a in ("--set", f"{k}={v}")]]
    rc, said = finish(start_python(_KILLED_IN_EVALUATION.format(args=args)))
    assert rc == -signal.SIGKILL, said
    assert "evaluating the pruned run" in said, said
    assert not out.exists(), sorted(p.relative_to(out).as_posix() for p in out.rglob("*"))
    left = [p.name for p in tmp_path.iterdir()]
    assert len(left) == 1 and left[0].startswith(".out.tmp-"), left  # the killed process's, with its model
    done = run_cli(*args)
    assert done.returncode == 0, done.stderr
    assert [p.name for p in tmp_path.iterdir()] == ["out"]
    assert PruneReport.read(out / "prune.json").metrics.after.ause_mae is not None
    assert not (out / ".lock").exists() and not list((out / "eval").glob(".maps-*"))


def test_a_moved_project_s_prune_reads_its_own_source_run(pruned, tiny_run_path, tmp_path):  # noqa: F811
    """prune.json named its source run by an absolute path: a project moved (or copied) elsewhere, with another project
    at the old place, compared its report with that other run and advised commands on it. The source's path relative
    to the prune is recorded too; the one of the two that holds the model prune read (by its SHA-256) is read."""
    out, result, _ = pruned
    written = PruneReport.read(out / "prune.json")
    assert (out / written.source_from_run).resolve() == tiny_run_path.resolve()
    project = tmp_path / "moved"
    shutil.copytree(tiny_run_path, project / "src", ignore=shutil.ignore_patterns(".lock"))
    shutil.copytree(out, project / "pr")
    rep = PruneReport.read(project / "pr" / "prune.json")
    rep.source_from_run = "../src"
    rep.write(project / "pr" / "prune.json")
    assert rep.source_folder(project / "pr") == project.resolve() / "src"  # its own copy, the original there too
    assert PruneReport.training_run(project / "pr") == project.resolve() / "src"
    from uncertsplat.report.build import _prune_facts

    assert ("source run", str(project.resolve() / "src")) in _prune_facts(rep, project / "pr")  # the page's row
    with open(project / "src" / "variational.ply", "ab") as f:  # not the model prune read: the recorded run
        f.write(b"\0")
    assert rep.source_folder(project / "pr") == Path(rep.source_run)
    old = json.loads((project / "pr" / "prune.json").read_text(encoding="utf-8"))
    old.pop("source_from_run")
    (project / "pr" / "prune.json").write_text(json.dumps({**old, "schema_version": 3}))
    assert PruneReport.read(project / "pr" / "prune.json").source_folder(project / "pr") == Path(rep.source_run)
