"""``select-views`` and growing a run's views, end to end on the tiny scene: every policy, the active-learning
loop (two rounds), the files it writes and the errors a user can hit."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

from tests.fixtures import tiny_scene_path  # noqa: F401
from tests.run_fixtures import TINY_RUN_OVERRIDES
from uncertsplat.baselines import train_run
from uncertsplat.cli import app
from uncertsplat.config import SelectConfig, deep_update, train_config_from
from uncertsplat.console import q
from uncertsplat.errors import UserError
from uncertsplat.schemas import RunScene, Selection
from uncertsplat.stages import select as stage

CPU = torch.device("cpu")
START = ["view_001.png", "view_004.png", "view_012.png", "view_019.png"]


def _cfg(**over):
    return train_config_from("tiny", deep_update(TINY_RUN_OVERRIDES, {"iterations": 80, **over}))


def _with_views_set_aside(subset_run, tmp_path):
    """A copy of ``subset_run`` whose config sets one view aside for calibration."""
    run = tmp_path / "run"
    shutil.copytree(subset_run, run)
    config = json.loads((run / "config.json").read_text(encoding="utf-8"))
    config["scene"]["calibration_holdout"] = 1
    (run / "config.json").write_text(json.dumps(config))
    return run


@pytest.fixture(scope="module")
def subset_run(tiny_scene_path, tmp_path_factory):
    run = tmp_path_factory.mktemp("select") / "run"
    train_run(tiny_scene_path, run, _cfg(scene={"train_names": START}), CPU)
    return run


def test_the_console_gives_both_scores_of_a_later_choice(subset_run, tmp_path, capsys):
    """The second greedy choice is printed with its score when chosen and, where it differs, its score alone (the
    one selection.json's ranking holds)."""
    sel = stage.run(subset_run, SelectConfig(score="fisher", num_views=2), CPU, output=tmp_path / "sel")
    err = " ".join(capsys.readouterr().err.split())
    second = sel.chosen[1]
    assert f"{second.score:.6g}" != f"{second.score_when_chosen:.6g}"  # the first choice's information counts
    assert f"2. {second.name} score {second.score_when_chosen:.6g} (alone {second.score:.6g})" in err
    assert "each after the views chosen before it; only candidates in the capture's gaps compete (at least 0.5 x" in err
    # a choice that joined the gaps only after the earlier ones has no score alone, and says why
    sel = stage.run(subset_run, SelectConfig(score="fisher", num_views=12), CPU, output=tmp_path / "sel12")
    err = " ".join(capsys.readouterr().err.split())
    late = [c for c in sel.chosen if c.score is None]
    assert late, [(c.name, c.score) for c in sel.chosen]
    assert f"{late[0].rank}. {late[0].name} score {late[0].score_when_chosen:.6g} (outside the gaps before" in err


@pytest.mark.parametrize("score", ["variance", "unseen", "fisher", "coverage", "random"])
def test_every_policy_chooses_distinct_unused_views(subset_run, tmp_path, score):
    sel = stage.run(subset_run, SelectConfig(score=score, num_views=3), CPU, output=tmp_path / "sel")
    names = [c.name for c in sel.chosen]
    held = set(RunScene.read(subset_run / "scene.json").test)
    assert len(names) == len(set(names)) == 3
    assert not set(names) & (set(START) | held)
    assert [c.rank for c in sel.chosen] == [1, 2, 3]
    assert sel.num_candidates == len(sel.ranking) == 24 - len(START) - len(held)
    scores = [c.score for c in sel.ranking]
    scored = [x for x in scores if x is not None]  # fisher scores only the candidates in the gaps (the default)
    assert scores[:len(scored)] == sorted(scored, reverse=True) and len(scored) >= 3
    assert Selection.read(tmp_path / "sel" / "selection.json").chosen[0].name == names[0]
    assert (tmp_path / "sel" / "selection.png").stat().st_size > 1000
    if score in ("variance", "unseen", "random"):  # not greedy: the top ones of the first ranking
        assert names == [c.name for c in sel.ranking[:3]]


@pytest.mark.parametrize("score", ["variance", "fisher"])
def test_same_seed_same_choice(subset_run, tmp_path, score):
    a = stage.run(subset_run, SelectConfig(score=score, num_views=2), CPU, output=tmp_path / "a")
    b = stage.run(subset_run, SelectConfig(score=score, num_views=2), CPU, output=tmp_path / "b")
    assert [c.name for c in a.chosen] == [c.name for c in b.chosen]
    assert [c.score for c in a.ranking] == [c.score for c in b.ranking]


def test_fisher_log_det_is_the_saturating_information(subset_run, tmp_path):
    """log-det scores each candidate by sum log(1 + F / prec) / 2 with the same probes as the trace: never above
    half the trace (log1p(x) <= x), positive, and it chooses distinct unused views; the setting is recorded."""
    trace = stage.run(subset_run, SelectConfig(score="fisher", num_views=2, gaps=0.0), CPU, output=tmp_path / "t")
    logdet = stage.run(subset_run, SelectConfig(score="fisher", num_views=2, information="log-det", gaps=0.0), CPU,
                       output=tmp_path / "l")
    t = {c.name: c.score for c in trace.ranking}
    ld = {c.name: c.score for c in logdet.ranking}
    assert t.keys() == ld.keys()
    assert all(0 < ld[k] <= 0.5 * t[k] * (1 + 1e-9) for k in t)
    assert any(ld[k] < 0.45 * t[k] for k in t), "some candidate's information saturates"
    names = [c.name for c in logdet.chosen]
    assert len(set(names)) == 2 and not set(names) & set(START)
    assert logdet.settings["information"] == "log-det" and trace.settings["information"] == "trace"
    with pytest.raises(ValueError):
        SelectConfig(information="entropy")


def test_fisher_chooses_inside_the_gaps_by_default(subset_run, tmp_path):
    """The default (gaps = 0.5): only candidates at least half the farthest one's distance from the cameras used
    are scored, each choice is one of them (given the ones chosen before), and the setting is recorded."""
    from uncertsplat.baselines import load_run
    from uncertsplat.select.scores import gap_eligible

    sel = stage.run(subset_run, SelectConfig(score="fisher", num_views=2), CPU, output=tmp_path / "g")
    assert sel.settings["gaps"] == 0.5
    scene = load_run(subset_run, CPU).load_scene()  # the frame the stage measures distances in
    used = scene.cameras[list(scene.split["train"])].centers
    cands = sel.ranking
    centres = torch.tensor([c.position for c in cands], dtype=torch.float64)
    eligible = gap_eligible(centres, used, 0.5)
    names = [c.name for c in cands]
    chosen = []
    for c in sel.chosen:
        assert bool(eligible(chosen)[names.index(c.name)]), c.name
        chosen.append(names.index(c.name))
    first = eligible([])
    assert {c.name for c in cands if c.score is not None} == {n for i, n in enumerate(names) if bool(first[i])}
    assert 0 < int(first.sum()) < len(cands)
    plain = stage.run(subset_run, SelectConfig(score="fisher", num_views=1, gaps=0.0), CPU, output=tmp_path / "p")
    assert all(c.score is not None for c in plain.ranking) and plain.settings["gaps"] == 0.0


def test_fisher_predictive_runs_end_to_end(subset_run, tmp_path):
    """information=predictive through the stage: positive scores, two distinct unused views, the setting recorded
    (its arithmetic: tests/unit/test_select.py, TestFisherInformation)."""
    sel = stage.run(subset_run, SelectConfig(score="fisher", num_views=2, information="predictive", gaps=0.0), CPU,
                    output=tmp_path / "p")
    assert all(c.score > 0 for c in sel.ranking)
    names = [c.name for c in sel.chosen]
    assert len(set(names)) == 2 and not set(names) & set(START)
    assert sel.settings["information"] == "predictive"


def test_unseen_score_is_the_blended_relative_variance(subset_run):
    from uncertsplat.baselines import load_run
    from uncertsplat.select.scores import relative_position_variance, unseen_scores

    loaded = load_run(subset_run, CPU)
    scene = loaded.load_scene()
    sampler = loaded.sampler(scene.scene_scale, CPU)
    u = relative_position_variance(loaded.model, loaded.prior)
    assert u.shape == (len(loaded.model),) and 0 <= float(u.min()) and float(u.max()) <= 1
    assert float(u[loaded.model.posterior_row < 0].abs().sum()) == 0  # no posterior, nothing unknown
    cams = scene.cameras[[0, 5]]
    alpha = torch.stack([sampler.render_fn(sampler.det_sample, cams[[c]]).alpha.mean() for c in range(2)])
    # u = 0 everywhere: only the empty part of the view is unknown; u = 1: all of it
    zero = unseen_scores(sampler.det_sample, torch.zeros_like(u), sampler.render_fn, cams)
    one = unseen_scores(sampler.det_sample, torch.ones_like(u), sampler.render_fn, cams)
    torch.testing.assert_close(zero, (1 - alpha).double(), atol=1e-5, rtol=0)
    torch.testing.assert_close(one, torch.ones(2, dtype=torch.float64), atol=2e-3, rtol=0)
    mid = unseen_scores(sampler.det_sample, u, sampler.render_fn, cams)
    assert bool(((zero <= mid + 1e-6) & (mid <= one + 1e-6)).all())


def test_unseen_score_measures_against_the_prior_the_posterior_was_fitted_with(subset_run):
    """The informed posterior gives each carrier its own position prior (its size, capped by its depth); the unseen
    score divided by the config's single std read nearly every Gaussian as constrained by no view (1.1 % below half
    the prior's variance, scores of 0.94-0.96 for every candidate, where training's summary said 42 % were set by the
    data: a helper's review). It now takes the prior training's summary measures against."""
    from uncertsplat.baselines import load_run
    from uncertsplat.gaussians.variational import posterior_summary
    from uncertsplat.schemas.runs import TrainSummary
    from uncertsplat.select.scores import relative_position_variance

    loaded = load_run(subset_run, CPU)
    assert loaded.config.posterior == "informed" and loaded.model.num_carriers > 0
    scene = loaded.load_scene()
    std = loaded.position_prior_std(scene)
    assert std is not None and std.shape == (loaded.model.num_carriers,)
    recorded = TrainSummary.read(subset_run / "train_summary.json").posterior
    assert recorded.position_prior == "per_carrier"
    again = posterior_summary(loaded.model, loaded.prior, position_prior_std=std)["position_spread_ratio"]
    for key in ("q10", "q50", "q90"):  # the reference training's summary used
        assert again[key] == pytest.approx(getattr(recorded.position_spread_ratio, key), rel=1e-5)
    idx = loaded.model.carrier_index()
    u = relative_position_variance(loaded.model, loaded.prior, std)[idx]
    single = relative_position_variance(loaded.model, loaded.prior)[idx]
    assert float(u.median()) == pytest.approx(min(again["q50"] ** 2, 1.0), rel=1e-4)
    assert float((u < 0.5).float().mean()) > float((single < 0.5).float().mean())


def test_unseen_needs_a_posterior(tiny_scene_path, tmp_path, capsys):
    run = tmp_path / "det"
    train_run(tiny_scene_path, run, _cfg(iterations=10, method="deterministic", scene={"train_names": START}), CPU)
    with pytest.raises(UserError, match="unseen score reads"):
        stage.run(run, SelectConfig(score="unseen"), CPU)
    # the variance score runs on it, and says what it is then (it ranked silently by the empty-ray term alone)
    capsys.readouterr()
    stage.run(run, SelectConfig(score="variance", num_views=1, num_samples=2), CPU, output=tmp_path / "v")
    assert "variance score holds only the empty-ray term" in " ".join(capsys.readouterr().err.split())


def test_variance_prefers_views_of_what_the_start_views_miss(subset_run, tmp_path):
    # the uncertainty policy is not coverage in disguise, but it must rank the far side above the start views'
    # neighbours more often than not: its top third is farther from the used cameras than its bottom third
    sel = stage.run(subset_run, SelectConfig(score="variance", num_views=1), CPU, output=tmp_path / "v")
    cov = stage.run(subset_run, SelectConfig(score="coverage", num_views=1), CPU, output=tmp_path / "c")
    distance = {c.name: c.score for c in cov.ranking}
    ranked = [distance[c.name] for c in sel.ranking]
    third = len(ranked) // 3
    assert sum(ranked[:third]) / third > sum(ranked[-third:]) / third


def test_two_rounds_of_the_loop(tiny_scene_path, subset_run, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(subset_run, run)
    cfg = _cfg(scene={"train_names": START})
    step = 80
    added = []
    for r in range(2):
        sel = stage.run(run, SelectConfig(score="variance", seed=r), CPU)
        name = sel.chosen[0].name
        assert name not in added and name not in START
        step += 20
        train_run(tiny_scene_path, run, cfg, CPU, resume=True, extend_to=step, add_views=[name])
        added.append(name)
    info = RunScene.read(run / "scene.json")
    assert [(v.step, v.names) for v in info.views_added] == [(80, [added[0]]), (100, [added[1]])]
    assert sorted(info.train) == sorted(START + added)
    assert json.loads((run / "config.json").read_text(encoding="utf-8"))["scene"]["train_names"] == START + added
    summary = json.loads((run / "train_summary.json").read_text(encoding="utf-8"))
    assert summary["steps"] == 120
    # the next selection no longer offers them
    sel = stage.run(run, SelectConfig(score="coverage", num_views=1), CPU)
    assert not {c.name for c in sel.ranking} & set(added)


class TestAddViewsErrors:
    def test_needs_resume(self, tiny_scene_path, tmp_path):
        with pytest.raises(UserError, match="needs --resume"):
            train_run(tiny_scene_path, tmp_path / "new", _cfg(scene={"train_names": START}), CPU,
                      add_views=["view_002.png"])

    def test_a_view_added_again_is_named_with_its_step(self, tiny_scene_path, subset_run, tmp_path):
        """A training stopped right after adding a view left it recorded as trained; the same --add-views again was
        refused without a word on what to do."""
        run = tmp_path / "run"
        shutil.copytree(subset_run, run)
        train_run(tiny_scene_path, run, _cfg(), CPU, resume=True, extend_to=90, add_views=["view_002.png"])
        with pytest.raises(UserError, match=r"'view_002.png' is already a training view of this run \(added at "
                                            r"step 80\)") as err:
            train_run(tiny_scene_path, run, _cfg(), CPU, resume=True, extend_to=100, add_views=["view_002.png"])
        assert "`--resume` alone" in str(err.value)

    def test_a_resume_from_before_views_were_added_records_when_they_train(self, tiny_scene_path, tmp_path, capsys):
        """Resumed from a checkpoint before views were added (the later ones gone), the run trained them from that
        step while views_added still said the later one, without a word."""
        run = tmp_path / "run"
        cfg = _cfg(iterations=40, checkpoint_every=20, scene={"train_names": START})
        train_run(tiny_scene_path, run, cfg, CPU)
        train_run(tiny_scene_path, run, cfg, CPU, resume=True, extend_to=60, add_views=["view_002.png"])
        assert [v.step for v in RunScene.read(run / "scene.json").views_added] == [40]
        for step in (40, 60):
            (run / "ckpts" / f"step_{step:06d}.pt").unlink(missing_ok=True)
        capsys.readouterr()
        train_run(tiny_scene_path, run, cfg, CPU, resume=True, extend_to=60)
        assert [v.step for v in RunScene.read(run / "scene.json").views_added] == [20]
        assert "resuming from step 20, before view_002.png were added" in " ".join(capsys.readouterr().err.split())

    def test_held_out_or_trained_views_are_refused(self, tiny_scene_path, subset_run, tmp_path, capsys):
        run = tmp_path / "run"
        shutil.copytree(subset_run, run)
        held = RunScene.read(run / "scene.json").test[0]
        with pytest.raises(UserError, match="held-out view"):
            train_run(tiny_scene_path, run, _cfg(), CPU, resume=True, extend_to=90, add_views=[held])
        with pytest.raises(UserError, match="already a training view") as err:
            train_run(tiny_scene_path, run, _cfg(), CPU, resume=True, extend_to=90, add_views=[START[0]])
        # (a run on some of the scene's views: the error said no more, with nothing on what to do)
        assert "scene.json lists the ones it trains on" in str(err.value) and "select-views" in str(err.value)
        capsys.readouterr()
        with pytest.raises(UserError, match="--add-views nope.png: no photo of that name in the scene") as err:
            train_run(tiny_scene_path, run, _cfg(), CPU, resume=True, extend_to=90, add_views=["nope.png"])
        assert "a pose that select-views proposed needs a photo taken there first" in str(err.value)
        # a synthetic scene is no reconstruct workspace: --extend, which refuses it, is not suggested (a helper's audit)
        assert "--extend registers new photos" in str(err.value) and "reconstruct PHOTOS" not in str(err.value)
        said = capsys.readouterr().err  # nothing said of a resume that is refused (it warned, then refused)
        assert "resuming from" not in said and "none are grown" not in said and "continuing to" not in said, said
        assert "did you mean" not in str(err.value)
        # a near miss names the photo (another case, a path before it)
        for near in ("VIEW_002.PNG", "scene/images/view_002.png"):
            with pytest.raises(UserError, match=r"no photo of that name in the scene \(did you mean view_002\.png\?\)"):
                train_run(tiny_scene_path, run, _cfg(), CPU, resume=True, extend_to=90, add_views=[near])

    def test_a_photo_the_scene_leaves_out_is_named_as_such(self, tiny_scene_path, tmp_path):
        """A photo in the workspace's images/ that the scene does not hold (left out for its size, or not in the
        COLMAP model) was 'no photo of that name in the scene'."""
        scene = tmp_path / "scene"
        shutil.copytree(tiny_scene_path, scene)
        run = tmp_path / "run"
        train_run(scene, run, _cfg(iterations=10, scene={"train_names": START}), CPU)
        shutil.copy(scene / "images" / "view_002.png", scene / "images" / "extra.png")
        with pytest.raises(UserError, match=r"--add-views extra.png: the photo is in .*images but not among the "
                                            r"scene's views: left out for its size") as err:
            train_run(scene, run, _cfg(), CPU, resume=True, extend_to=20, add_views=["extra.png"])
        assert "--extend" in str(err.value)  # how a photo added to the folder joins a workspace

    def test_added_views_on_a_scene_whose_split_moved_keep_the_run_s_held_out_views(self, tiny_scene_path, tmp_path):
        """A photo put back into the workspace moves the every-8th split by name: --add-views went on with a view the
        run held out left unused (or trainable) and another set scored, without a word (then it was refused). The run
        now keeps its own held-out views (``sfm.scene.load_for_run``), so its scores compare."""
        pycolmap = pytest.importorskip("pycolmap")
        ws = tmp_path / "ws"
        shutil.copytree(tiny_scene_path / "images", ws / "images")
        shutil.copytree(tiny_scene_path / "sparse", ws / "sparse")
        full = tmp_path / "full"
        shutil.copytree(ws / "sparse" / "0", full)
        rec = pycolmap.Reconstruction(str(ws / "sparse" / "0"))
        rec.deregister_frame(next(im for im in rec.images.values() if im.name == "view_010.png").frame_id)
        rec.write_binary(str(ws / "sparse" / "0"))
        (ws / "images" / "view_010.png").rename(tmp_path / "view_010.png")
        run = tmp_path / "run"
        keep = {"train_names": START, "normalize": False}  # (the normalisation would move every camera too)
        train_run(ws, run, _cfg(iterations=10, scene=keep), CPU)
        before = (run / "scene.json").read_text(encoding="utf-8")
        shutil.rmtree(ws / "sparse" / "0")
        shutil.copytree(full, ws / "sparse" / "0")
        (tmp_path / "view_010.png").rename(ws / "images" / "view_010.png")
        held = json.loads(before)["test"]
        assert "view_017.png" in held  # (the 23 photos' every 8th; with view_010 back it would be view_016)
        train_run(ws, run, _cfg(iterations=10, scene=keep), CPU, resume=True, extend_to=20, add_views=["view_010.png"])
        after = json.loads((run / "scene.json").read_text(encoding="utf-8"))
        assert after["test"] == held and "view_010.png" in after["train"] and "view_016.png" not in after["test"]
        from uncertsplat.baselines import load_run

        scene = load_run(run).load_scene()  # evaluate scores the views the run held out, not the scene's split now
        assert [scene.cameras.image_names[i] for i in scene.split["test"]] == held

    def test_a_run_with_views_set_aside_takes_none(self, tiny_scene_path, subset_run, tmp_path):
        """More training views would set other views aside for calibration: refused, the run left as it was."""
        run = _with_views_set_aside(subset_run, tmp_path)
        before = (run / "scene.json").read_text(encoding="utf-8")
        with pytest.raises(UserError, match="sets views aside for calibration"):
            train_run(tiny_scene_path, run, _cfg(), CPU, resume=True, extend_to=90, add_views=["view_002.png"])
        assert (run / "scene.json").read_text(encoding="utf-8") == before

    def test_select_views_says_up_front_that_such_a_run_takes_none(self, subset_run, tmp_path, capsys):
        """The refusal came only at `train --add-views`, after choosing: select-views says so when it starts."""
        run = _with_views_set_aside(subset_run, tmp_path)
        stage.run(run, SelectConfig(score="fisher", num_views=1), CPU, output=tmp_path / "sel")
        said = " ".join(capsys.readouterr().err.split())
        assert "sets 1 view(s) aside for calibration, so `train --resume --add-views` refuses" in said
        # and its Next line does not give that command (a helper ran it as told, and it was refused)
        (nxt,) = [line for line in said.split("Next: ")[1:]]
        assert "--resume" not in nxt.replace("`--resume --add-views` refuses this run", "")
        assert "it sets views aside for calibration) train a new run" in nxt and "-o NEW_RUN" in nxt
        assert "scene.train_names=" in nxt and str(run / "scene.json") in nxt
        capsys.readouterr()
        stage.run(subset_run, SelectConfig(score="fisher", num_views=1), CPU, output=tmp_path / "plain")
        plain = " ".join(capsys.readouterr().err.split())
        assert "aside for calibration" not in plain and f"-o {q(subset_run)} --resume --iterations N --add-views" in plain

    def test_a_finished_run_needs_steps_for_the_added_views(self, tiny_scene_path, subset_run, tmp_path):
        """Without --iterations beyond its end the added view would be recorded as trained on with 0 steps."""
        run = tmp_path / "run"
        shutil.copytree(subset_run, run)
        before = {n: (run / n).read_text(encoding="utf-8") for n in ("config.json", "scene.json")}
        with pytest.raises(UserError, match="would never be trained on"):
            train_run(tiny_scene_path, run, _cfg(), CPU, resume=True, add_views=["view_002.png"])
        assert {n: (run / n).read_text(encoding="utf-8") for n in before} == before

    def test_an_added_photo_that_cannot_be_read_leaves_the_run_as_it_was(self, tiny_scene_path, tmp_path):
        """config.json and scene.json named the added view before its photo was read: a truncated photo then failed
        every later command on the run (a plain --resume too, and --add-views of another photo), mended only by
        editing both files. They are written once the photos read."""
        scene = tmp_path / "scene"
        shutil.copytree(tiny_scene_path, scene)
        run = tmp_path / "run"
        train_run(scene, run, _cfg(iterations=10, scene={"train_names": START}), CPU)
        before = {n: (run / n).read_text(encoding="utf-8") for n in ("config.json", "scene.json")}
        photo = scene / "images" / "view_002.png"
        photo.write_bytes(photo.read_bytes()[: photo.stat().st_size // 2])
        with pytest.raises(UserError, match="view_002.png"):
            train_run(scene, run, _cfg(), CPU, resume=True, extend_to=20, add_views=["view_002.png"])
        assert {n: (run / n).read_text(encoding="utf-8") for n in before} == before
        train_run(scene, run, _cfg(), CPU, resume=True, extend_to=20, add_views=["view_003.png"])  # another: trains
        info = RunScene.read(run / "scene.json")
        assert "view_003.png" in info.train and "view_002.png" not in info.train

    def test_a_run_started_on_indices_grows_by_name(self, tiny_scene_path, tmp_path):
        """scene.train_indices: the run continues on the names of those views, with the added one."""
        run = tmp_path / "idx"
        train_run(tiny_scene_path, run, _cfg(iterations=10, scene={"train_indices": [1, 4, 12, 19]}), CPU)
        first = RunScene.read(run / "scene.json")
        train_run(tiny_scene_path, run, _cfg(), CPU, resume=True, extend_to=20,
                  add_views=["view_002.png", "view_002.png"])  # (a name given twice is added once)
        info = RunScene.read(run / "scene.json")
        assert sorted(info.train) == sorted([*first.train, "view_002.png"]) and info.test == first.test
        scene = json.loads((run / "config.json").read_text(encoding="utf-8"))["scene"]
        assert scene["train_names"] == [*first.train, "view_002.png"] and scene["train_indices"] is None

    def test_views_added_after_densification_are_said_to_get_no_gaussians(self, tiny_scene_path, tmp_path, capsys):
        run = tmp_path / "late"
        train_run(tiny_scene_path, run, _cfg(iterations=20, densify={"until": 10},
                                             scene={"train_names": START}), CPU)
        capsys.readouterr()
        train_run(tiny_scene_path, run, _cfg(), CPU, resume=True, extend_to=25, add_views=["view_002.png"])
        err = " ".join(capsys.readouterr().err.split())
        assert "no densification step is left after the checkpoint's step 20" in err
        # the last densification step is the last multiple of the interval before until (80 here, until 100): a
        # checkpoint there gets the note too (it came only from until on)
        edge = tmp_path / "edge"
        train_run(tiny_scene_path, edge, _cfg(iterations=80, scene={"train_names": START}), CPU)
        capsys.readouterr()
        train_run(tiny_scene_path, edge, _cfg(), CPU, resume=True, extend_to=85, add_views=["view_002.png"])
        assert "no densification step is left after the checkpoint's step 80" in " ".join(capsys.readouterr().err.split())
        early = tmp_path / "early"
        train_run(tiny_scene_path, early, _cfg(iterations=10, scene={"train_names": START}), CPU)
        capsys.readouterr()
        train_run(tiny_scene_path, early, _cfg(), CPU, resume=True, extend_to=45, add_views=["view_002.png"])  # (densifies at 40)
        assert "no densification step is left" not in capsys.readouterr().err
        # a resumed run that ends before the next densification step grows nothing either (checkpoint 45, next 60)
        train_run(tiny_scene_path, early, _cfg(), CPU, resume=True, extend_to=50, add_views=["view_003.png"])
        assert "and the run ends at 50" in " ".join(capsys.readouterr().err.split())

    def test_a_run_on_every_view_has_none_to_add(self, tiny_scene_path, tmp_path):
        run = tmp_path / "all"
        train_run(tiny_scene_path, run, _cfg(iterations=10), CPU)
        with pytest.raises(UserError, match="already a training view of this run .it trains on every photo") as err:
            train_run(tiny_scene_path, run, _cfg(iterations=10), CPU, resume=True, extend_to=20,
                      add_views=["view_002.png"])
        assert "--extend" in err.value.hint  # how a new photo joins
        with pytest.raises(UserError, match="no unused view"):
            stage.run(run, SelectConfig(), CPU)


def test_cli_with_a_pose_file(subset_run, tmp_path):
    poses = tmp_path / "plan.txt"
    poses.write_text("front 1 0 0 0 0 0 4\nside 0.7071067811865476 0 0.7071067811865476 0 0 0 4\n")
    res = CliRunner().invoke(app, ["select-views", str(subset_run), "--candidates", str(poses), "-n", "1",
                                   "--score", "coverage", "-o", str(tmp_path / "out"), "--device", "cpu"])
    assert res.exit_code == 0, res.output
    sel = Selection.read(tmp_path / "out" / "selection.json")
    assert sel.num_candidates == 2 and sel.chosen[0].name in ("front", "side")
    said = " ".join(res.output.split())
    # how a photo joins the run: a synthetic scene is no workspace of `reconstruct`, which --extend grows
    assert "Next: take a photo at each chosen pose" in said and "add it to the scene" in said
    assert "--extend" not in said
    poses.write_text("front 1 0 0 0 0 0 4\nside 1 0 0\n")
    res = CliRunner().invoke(app, ["select-views", str(subset_run), "--candidates", str(poses), "--score",
                                   "coverage", "-o", str(tmp_path / "out2"), "--device", "cpu"])
    assert res.exit_code == 2 and "line 2" in res.output and "8 fields" in res.output


def test_a_config_files_pose_file_is_read_from_its_folder(subset_run, tmp_path, monkeypatch):
    """`candidates = "plan.txt"` in a --config file was read from the current folder (depth_gt from the file's),
    and the error did not say where it looked; the words unused and around[:N] stay words."""
    sub = tmp_path / "sub"
    sub.mkdir()
    (sub / "plan.txt").write_text("front 1 0 0 0 0 0 4\n")
    (sub / "select.toml").write_text('candidates = "plan.txt"\nscore = "coverage"\n')
    monkeypatch.chdir(tmp_path)
    res = CliRunner().invoke(app, ["select-views", str(subset_run), "--config", "sub/select.toml", "-o",
                                   str(tmp_path / "out"), "--device", "cpu"])
    assert res.exit_code == 0, res.output
    assert Selection.read(tmp_path / "out" / "selection.json").chosen[0].name == "front"
    # the pose file given on the command line, relative, recorded whole: selection.json given back as --config from
    # another folder reads the same file (it looked for /plan.txt)
    monkeypatch.chdir(sub)
    res = CliRunner().invoke(app, ["select-views", str(subset_run), "--candidates", "plan.txt", "--score", "coverage",
                                   "-o", str(tmp_path / "out_rel"), "--device", "cpu"])
    assert res.exit_code == 0, res.output
    assert Selection.read(tmp_path / "out_rel" / "selection.json").settings["candidates"] == str(sub / "plan.txt")
    monkeypatch.chdir("/")
    res = CliRunner().invoke(app, ["select-views", str(subset_run), "--config", str(tmp_path / "out_rel" /
                                   "selection.json"), "-o", str(tmp_path / "out_again"), "--device", "cpu"])
    assert res.exit_code == 0, res.output
    assert Selection.read(tmp_path / "out_again" / "selection.json").chosen[0].name == "front"
    monkeypatch.chdir(tmp_path)
    (sub / "select.toml").write_text('candidates = "missing.txt"\n')
    res = CliRunner().invoke(app, ["select-views", str(subset_run), "--config", "sub/select.toml", "-o",
                                   str(tmp_path / "out2"), "--device", "cpu"])
    said = " ".join(res.output.split())
    assert res.exit_code == 2 and f"looked for {tmp_path / 'missing.txt'}" in said, said
    (sub / "select.toml").write_text('candidates = "around:2"\nscore = "coverage"\n')
    res = CliRunner().invoke(app, ["select-views", str(subset_run), "--config", "sub/select.toml", "-o",
                                   str(tmp_path / "out3"), "--device", "cpu"])
    assert res.exit_code == 0, res.output


def test_cli_errors_print_the_message_as_given(subset_run, tmp_path):
    """An error that quotes what the user typed shows it verbatim: `around:x:` is not an emoji, `[red]` not markup."""
    res = CliRunner().invoke(app, ["select-views", str(subset_run), "--candidates", "around:x", "-o",
                                   str(tmp_path / "out"), "--device", "cpu"])
    assert res.exit_code == 2 and "around:x" in res.output and "\u274c" not in res.output, res.output
    res = CliRunner().invoke(app, ["evaluate", str(tmp_path / "[red]nope"), "--device", "cpu"])
    assert res.exit_code == 2 and "[red]nope" in res.output, res.output


def test_the_default_score_is_fisher(subset_run, tmp_path):
    """The uncertainty policy that did best in the active-learning loop (BENCHMARKS.md) is what a plain call uses."""
    res = CliRunner().invoke(app, ["select-views", str(subset_run), "-o", str(tmp_path / "out"), "--device", "cpu"])
    assert res.exit_code == 0, res.output
    sel = Selection.read(tmp_path / "out" / "selection.json")
    assert sel.score == "fisher" and len(sel.chosen) == 1 and sel.chosen[0].name not in sel.used


def test_candidates_that_see_none_of_the_model_are_named(subset_run, tmp_path, capsys):
    """Poses of the unused views as the file convention wants them: no note; the same poses inverted (camera-to-world,
    the most common mix-up) look away from the model and are named with how little of it they see."""
    from uncertsplat.baselines import load_run
    from uncertsplat.select.candidates import pose_line

    loaded = load_run(subset_run)
    scene = loaded.load_scene()
    wfs = torch.tensor(RunScene.read(subset_run / "scene.json").world_from_source, dtype=torch.float64)
    unused = [i for i in range(len(scene.cameras)) if i not in set(scene.split["train"]) | set(scene.split["test"])]
    right = [pose_line(f"v{i}", scene.cameras.cam_from_world[i], wfs) for i in unused[:3]]
    (tmp_path / "right.txt").write_text("\n".join(right) + "\n")
    stage.run(subset_run, SelectConfig(score="coverage", num_views=1, candidates=str(tmp_path / "right.txt")), CPU,
              output=tmp_path / "a")
    assert "see almost none of the model" not in capsys.readouterr().err
    inverted = [pose_line(f"v{i}", torch.linalg.inv(scene.cameras.cam_from_world[i].double()).float(), wfs)
                for i in unused[:3]]
    (tmp_path / "inverted.txt").write_text("\n".join(inverted) + "\n")
    stage.run(subset_run, SelectConfig(score="coverage", num_views=1, candidates=str(tmp_path / "inverted.txt")), CPU,
              output=tmp_path / "b")
    said = " ".join(capsys.readouterr().err.split())
    assert "3 of 3 candidate(s) see almost none of the model (v" in said and "world-to-camera" in said
    assert "where they face what no photo has seen" in said and "--score variance" in said


@pytest.mark.parametrize("score", ["coverage", "fisher"])
def test_a_planned_pose_far_outside_the_capture_is_ranked_last(subset_run, tmp_path, capsys, score):
    """A plan with two unused views' poses and the first moved 100 capture sizes away: coverage and fisher's gap rule
    both put the far one first (the gap rule measured every other pose against it, so they got no score). It is
    now ranked last with no score and named; ``plausible_only=false`` lets it compete again."""
    from uncertsplat.baselines import load_run
    from uncertsplat.select.candidates import pose_line

    loaded = load_run(subset_run)
    scene = loaded.load_scene()
    wfs = torch.tensor(RunScene.read(subset_run / "scene.json").world_from_source, dtype=torch.float64)
    unused = [i for i in range(len(scene.cameras)) if i not in set(scene.split["train"]) | set(scene.split["test"])]
    far = torch.linalg.inv(scene.cameras.cam_from_world[unused[0]].double())
    far[:3, 3] *= 100.0  # the same direction, 100 times as far from the scene's centre
    lines = [pose_line("far", torch.linalg.inv(far).float(), wfs)]
    lines += [pose_line(f"v{i}", scene.cameras.cam_from_world[i], wfs) for i in unused[1:3]]
    (tmp_path / "plan.txt").write_text("\n".join(lines) + "\n")
    cfg = SelectConfig(score=score, num_views=1, candidates=str(tmp_path / "plan.txt"))
    sel = stage.run(subset_run, cfg, CPU, output=tmp_path / "a")
    said = " ".join(capsys.readouterr().err.split())
    assert sel.chosen[0].name != "far" and sel.ranking[-1].name == "far" and sel.ranking[-1].score is None
    assert "1 candidate (far) lies over 2 capture sizes from every training camera" in said
    assert "plausible_only=false" in said
    sel = stage.run(subset_run, cfg.model_copy(update={"plausible_only": False}), CPU, output=tmp_path / "b")
    assert "capture sizes" not in capsys.readouterr().err
    # when it competes: coverage's farthest, and for fisher the only one in the gaps it set
    assert sel.chosen[0].name == "far"


def test_a_pose_ranked_last_does_not_join_the_predictive_information(subset_run, tmp_path, monkeypatch):
    """information=predictive scores what a candidate takes off the renders of the capture's views, the training
    views and every candidate: a pose left out of the competition (here one of three, set so by hand) is no view of
    the capture, so the other two score as in a plan without it."""
    from uncertsplat.baselines import load_run
    from uncertsplat.select.candidates import pose_line

    scene = load_run(subset_run).load_scene()
    wfs = torch.tensor(RunScene.read(subset_run / "scene.json").world_from_source, dtype=torch.float64)
    unused = [i for i in range(len(scene.cameras)) if i not in set(scene.split["train"]) | set(scene.split["test"])]
    lines = [pose_line(f"v{i}", scene.cameras.cam_from_world[i], wfs) for i in unused[:3]]
    (tmp_path / "three.txt").write_text("\n".join(lines) + "\n")
    (tmp_path / "two.txt").write_text("\n".join(lines[1:]) + "\n")
    scores = {}
    for name, left_out in (("three", torch.tensor([False, True, True])), ("two", None)):
        monkeypatch.setattr(stage, "_plausible", lambda *args, out=left_out: out)
        cfg = SelectConfig(num_views=1, information="predictive", gaps=0.0, candidates=str(tmp_path / f"{name}.txt"))
        scores[name] = {c.name: c.score for c in stage.run(subset_run, cfg, CPU, output=tmp_path / name).ranking}
    assert scores["three"][f"v{unused[0]}"] is None
    for k in scores["two"]:
        assert scores["three"][k] == pytest.approx(scores["two"][k], rel=1e-6)


def test_the_selection_plot_shows_the_held_out_views_and_keeps_its_legend_outside(tmp_path, monkeypatch):
    """The held-out views (a gap's middle, where the scores are measured) were left out of selection.png, and the
    legend sat over cameras."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from uncertsplat.stages.select import _plot

    figs = []
    monkeypatch.setattr(plt, "close", figs.append)
    ring = torch.stack([torch.tensor([torch.cos(t), torch.sin(t), 0.0]) for t in torch.linspace(0, 6.0, 12)])
    _plot(tmp_path / "s.png", ring[:6], ring[6:10], [0], torch.tensor([0.0, 0.0, 1.0]), "t", held=ring[10:])
    ax = figs[0].axes[0]
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert "held out (2)" in labels and "used (6)" in labels and "candidates (4)" in labels
    box = ax.get_legend().get_window_extent(figs[0].canvas.get_renderer())
    assert box.x0 >= ax.get_window_extent(figs[0].canvas.get_renderer()).x1  # beside the axes, not over them
    # candidates ruled out are left off the plot; the legend counts them (it said "candidates (3)" of 4)
    _plot(tmp_path / "s2.png", ring[:6], ring[6:9], [0], torch.tensor([0.0, 0.0, 1.0]), "t", not_drawn=1)
    labels = [t.get_text() for t in figs[-1].axes[0].get_legend().get_texts()]
    assert "candidates (3; 1 ruled out, not drawn)" in labels
    plt.close("all")


def test_a_forward_facing_grid_is_drawn_from_the_front(tmp_path, monkeypatch):
    """Cameras on an upright 3x3 grid (a forward-facing capture, y down as OpenCV's up is -y) were drawn from above,
    as a line with the chosen views on top of each other; a ring stays drawn from above."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from uncertsplat.stages.select import _plot

    figs = []
    monkeypatch.setattr(plt, "close", figs.append)
    grid = torch.tensor([[x, y, 0.0] for x in (-1.0, 0.0, 1.0) for y in (-1.0, 0.0, 1.0)])
    up = torch.tensor([0.0, -1.0, 0.0])
    _plot(tmp_path / "g.png", grid, grid + torch.tensor([0.5, 0.5, 0.0]), [0, 4], up, "grid")
    ax = figs[-1].axes[0]
    xs, ys = ax.collections[1].get_offsets().T  # the used cameras
    assert len(set(round(float(x), 6) for x in xs)) == 3 and len(set(round(float(y), 6) for y in ys)) == 3
    assert "seen from the front" in ax.get_title()
    ring = torch.stack([torch.tensor([torch.cos(t), 0.0, torch.sin(t)]) for t in torch.linspace(0, 6.0, 12)])
    _plot(tmp_path / "r.png", ring, ring * 1.1, [0], up, "ring")
    assert "seen from above" in figs[-1].axes[0].get_title()
    plt.close("all")


def test_a_run_that_cannot_grow_says_so_when_choosing(tiny_scene_path, tmp_path, capsys):
    """select-views chose views for an ensemble that `train --add-views` then refused, without a word."""
    run = tmp_path / "ens"
    train_run(tiny_scene_path, run, _cfg(iterations=10, method="ensemble", ensemble_size=2,
                                         scene={"train_names": START}), CPU)
    capsys.readouterr()
    stage.run(run, SelectConfig(score="coverage"), CPU, output=tmp_path / "sel")
    said = " ".join(capsys.readouterr().err.split())
    assert "`train --resume --add-views` does not grow an ensemble run" in said
    # the new run it says to train keeps the run's method and settings: without its config it was a variational run
    (nxt,) = said.split("Next: ")[1:]
    assert f"-o NEW_RUN --config {q(run / 'config.json')} --set 'scene.train_names=[...]'" in nxt, nxt


def test_a_planned_pose_named_as_a_photo_is_said(subset_run, tmp_path, capsys):
    """A plan line named like a training photo was chosen without comment; `--add-views` of that name then added (or
    refused) the photo, not the pose."""
    poses = tmp_path / "plan.txt"
    poses.write_text(f"{START[0]} 1 0 0 0 0 0 4\nfresh 0.7071067811865476 0 0.7071067811865476 0 0 0 4\n")
    capsys.readouterr()
    stage.run(subset_run, SelectConfig(score="coverage", candidates=str(poses)), CPU, output=tmp_path / "sel")
    said = " ".join(capsys.readouterr().err.split())
    assert f"1 planned pose(s) carry the name of a photo of the scene ({START[0]})" in said


def test_a_planned_pose_at_a_held_out_view_s_pose_does_not_compete(subset_run, tmp_path, capsys):
    """A plan holding a held-out view's exact pose ranked it first with no word, though `train --add-views` refuses
    the photo taken there (it is the held-out photo again): it gets no score and is named."""
    from uncertsplat.baselines import load_run
    from uncertsplat.select.candidates import pose_line

    loaded = load_run(subset_run)
    scene = loaded.load_scene()
    wfs = torch.tensor(RunScene.read(subset_run / "scene.json").world_from_source, dtype=torch.float64)
    unused = [i for i in range(len(scene.cameras)) if i not in set(scene.split["train"]) | set(scene.split["test"])]
    held = list(scene.split["test"])[0]
    lines = [pose_line("again", scene.cameras.cam_from_world[held], wfs)]
    lines += [pose_line(f"v{i}", scene.cameras.cam_from_world[i], wfs) for i in unused[:2]]
    (tmp_path / "plan.txt").write_text("\n".join(lines) + "\n")
    sel = stage.run(subset_run, SelectConfig(score="coverage", num_views=1, candidates=str(tmp_path / "plan.txt")),
                    CPU, output=tmp_path / "out")
    said = " ".join(capsys.readouterr().err.split())
    assert "1 candidate (again) lies at a held-out view's pose" in said, said
    assert sel.chosen[0].name != "again"


def test_the_variance_score_s_depth_std_is_in_the_scene_s_units(subset_run, tmp_path, monkeypatch):
    """selection.json's depth_std is documented in the scene's own units and was written in the run's normalised
    ones (a helper: 0.45 where Predictor gave 1.95, the scene's scale 0.247 apart)."""
    from uncertsplat.baselines import load_run
    from uncertsplat.select import scores

    def known(sample_fn, render_fn, cameras, num_samples, seed, **kwargs):
        return torch.linspace(1.0, 2.0, len(cameras), dtype=torch.float64), torch.full((len(cameras),), 0.5)

    monkeypatch.setattr(scores, "variance_scores", known)
    sel = stage.run(subset_run, SelectConfig(score="variance", num_views=1, candidates="around:4"), CPU,
                    output=tmp_path / "out")
    factor = load_run(subset_run).load_scene().depth_to_source
    assert factor != 1.0 and sel.chosen[0].depth_std == pytest.approx(0.5 * factor, rel=1e-6)


def test_the_last_round_s_selection_is_kept(subset_run, tmp_path, capsys):
    """Each round's select-views replaced RUN/select/selection.json without a word; the photos of the last round may
    not be taken yet: it is kept as selection.previous.json (one generation)."""
    cfg = SelectConfig(score="coverage", num_views=1, candidates="around:3")
    first = stage.run(subset_run, cfg, CPU, output=tmp_path / "sel")
    second = stage.run(subset_run, cfg.model_copy(update={"num_views": 2}), CPU, output=tmp_path / "sel")
    assert "is kept as selection.previous.json" in " ".join(capsys.readouterr().err.split())
    assert Selection.read(tmp_path / "sel" / "selection.previous.json") == first
    assert Selection.read(tmp_path / "sel" / "selection.json") == second


def test_candidates_all_at_held_out_poses_are_refused_not_chosen(subset_run, tmp_path, capsys):
    """With no candidate left but those at a held-out view's pose, they competed (the note blamed the poses'
    convention) and one was chosen, which `train --add-views` then refuses (a review): refused with the reason; beside
    a pose far out, that one competes and the twin does not."""
    from uncertsplat.baselines import load_run
    from uncertsplat.select.candidates import pose_line

    loaded = load_run(subset_run)
    scene = loaded.load_scene()
    wfs = torch.tensor(RunScene.read(subset_run / "scene.json").world_from_source, dtype=torch.float64)
    held = list(scene.split["test"])[0]
    twin = pose_line("again", scene.cameras.cam_from_world[held], wfs)
    (tmp_path / "one.txt").write_text(twin + "\n")
    with pytest.raises(UserError, match=r"every candidate lies at a held-out view's pose \(again\)"):
        stage.run(subset_run, SelectConfig(score="coverage", num_views=1, candidates=str(tmp_path / "one.txt")), CPU,
                  output=tmp_path / "a")
    far = scene.cameras.cam_from_world[held].clone()
    far[:3, 3] += 1000.0  # far outside the capture
    (tmp_path / "two.txt").write_text(twin + "\n" + pose_line("far", far, wfs) + "\n")
    sel = stage.run(subset_run, SelectConfig(score="coverage", num_views=1, candidates=str(tmp_path / "two.txt")),
                    CPU, output=tmp_path / "b")
    said = " ".join(capsys.readouterr().err.split())
    assert [c.name for c in sel.chosen] == ["far"] and "1 candidate at a held-out view's pose (again) does not compete" in said


def test_an_output_folder_among_the_scene_s_photos_is_refused(tiny_scene_path, subset_run):
    """`select-views RUN -o SCENE/images` wrote selection.png among the photos, where the next reconstruct of them (the
    one that adds the chosen photo) takes it for a photo: refused before the scoring, nothing written there."""
    images = Path(tiny_scene_path) / "images"
    before = sorted(p.name for p in images.iterdir())
    for out in (images, images / "next"):
        with pytest.raises(UserError, match="the output folder is inside the folder of the scene's photos"):
            stage.run(subset_run, SelectConfig(score="coverage"), CPU, output=out)
    assert sorted(p.name for p in images.iterdir()) == before


def test_a_run_without_its_scene_chooses_from_the_cameras_its_evaluation_kept(subset_run, tmp_path, monkeypatch,
                                                                                capsys):
    """A robot has the run folder, not the photos: the scores that read the model alone (variance, unseen, coverage)
    choose from the cameras, split and normalisation evaluate kept in eval/predictive.pt, the same choice as with the
    scene; fisher, which compares the model with the training photos, and a run without the file say what to do."""
    from uncertsplat.baselines import load_run
    from uncertsplat.baselines.runs import LoadedRun
    from uncertsplat.config import EvalConfig
    from uncertsplat.select.candidates import pose_line
    from uncertsplat.stages import evaluate

    run = tmp_path / "run"
    shutil.copytree(subset_run, run)
    evaluate.run(run, EvalConfig(num_samples=2, max_views=1), device=CPU)
    plan = tmp_path / "plan.txt"  # two of the scene's unused cameras, as planned poses
    cams = load_run(run, CPU).load_scene().cameras
    wfs = torch.tensor(RunScene.read(run / RunScene.FILE_NAME).world_from_source, dtype=torch.float64)
    plan.write_text("".join(pose_line(f"plan_{i}", cams.cam_from_world[i], wfs) + "\n" for i in (2, 6)),
                    encoding="utf-8")
    settings = [dict(score="variance"), dict(score="unseen", candidates=str(plan)),
                dict(score="coverage", candidates="around:6")]
    expected = [stage.run(run, SelectConfig(**s), CPU, output=tmp_path / f"with{i}") for i, s in enumerate(settings)]

    def gone(self):
        raise UserError(f"the scene this run was trained on is gone: {self.scene_path}", path=self.run_dir,
                        hint="Restore the scene folder.")

    monkeypatch.setattr(LoadedRun, "_read_scene", gone)
    capsys.readouterr()
    for i, s in enumerate(settings):
        got = stage.run(run, SelectConfig(**s), CPU, output=tmp_path / f"without{i}")
        assert [(c.name, c.score) for c in got.ranking] == [(c.name, c.score) for c in expected[i].ranking]
        assert [c.name for c in got.chosen] == [c.name for c in expected[i].chosen]
    printed = " ".join(capsys.readouterr().err.split())
    assert "the cameras, split and normalisation are those kept in" in printed
    with pytest.raises(UserError, match="is gone.*the fisher score .* compares the model with the training photos") as e:
        stage.run(run, SelectConfig(score="fisher"), CPU, output=tmp_path / "fisher")
    assert "--score variance, unseen or coverage" in e.value.hint
    (run / "eval" / "predictive.pt").unlink()
    with pytest.raises(UserError, match="is gone.*cannot stand in for it: .*predictive.pt is missing") as e:
        stage.run(run, SelectConfig(score="variance"), CPU, output=tmp_path / "none")
    assert "uncertsplat evaluate" in e.value.hint
    assert not (tmp_path / "fisher").exists() and not (tmp_path / "none").exists()
