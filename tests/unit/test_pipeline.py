"""Pipeline mechanics with stand-in stages: skipping unchanged stages, failures, overrides."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from uncertsplat.errors import NoPosterior, StageError, UserError
from uncertsplat.stages import pipeline as pl

PIPE = """
name = "t"
device = "cpu"
[[stages]]
stage = "synth"
config = { preset = "tiny" }
[[stages]]
stage = "train"
preset = "tiny"
[[stages]]
stage = "evaluate"
[[stages]]
stage = "report"
"""


@pytest.fixture
def calls(monkeypatch):
    log: list[tuple[str, Path]] = []

    def fake(kind, cfg, up_path, out_dir, device, kwargs):
        log.append((kind, out_dir))
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "out.txt").write_text(json.dumps(cfg.model_dump(mode="json")))
        if kind == "train" and getattr(cfg, "seed", 0) == 99:
            raise UserError("boom: the scene is broken", path=up_path)

    monkeypatch.setattr(pl, "_run_stage", fake)
    return log


def _write(tmp_path: Path) -> Path:
    p = tmp_path / "p.toml"
    p.write_text(PIPE)
    return p


def test_runs_all_then_skips_unchanged(tmp_path, calls):
    p = _write(tmp_path)
    outs = pl.run(p, tmp_path / "out")
    assert [k for k, _ in calls] == ["synth", "train", "evaluate", "report"]
    assert outs["evaluate"] == tmp_path / "out" / "train" / "eval"
    for name in ["synth", "train", "report"]:
        m = json.loads((tmp_path / "out" / name / "manifest.json").read_text(encoding="utf-8"))
        assert m["status"] == "done"
    calls.clear()
    pl.run(p, tmp_path / "out")
    assert calls == []  # everything unchanged


def test_changed_config_reruns_stage_and_downstream_and_keeps_previous(tmp_path, calls):
    p = _write(tmp_path)
    pl.run(p, tmp_path / "out")
    calls.clear()
    pl.run(p, tmp_path / "out", overrides=["train.iterations=7"])
    assert [k for k, _ in calls] == ["train", "evaluate", "report"]
    assert (tmp_path / "out" / ".previous" / "train" / "out.txt").exists()


def test_failure_names_stage_and_keeps_earlier_outputs(tmp_path, calls):
    p = _write(tmp_path)
    with pytest.raises(StageError, match=r"stage 'train' \(train\) failed: .*boom"):
        pl.run(p, tmp_path / "out", overrides=["train.seed=99"])
    assert (tmp_path / "out" / "synth" / "out.txt").exists()
    m = json.loads((tmp_path / "out" / "train" / "manifest.json").read_text(encoding="utf-8"))
    assert m["status"] == "failed" and "boom" in m["error"]
    # the failed stage re-runs next time, the finished one is skipped
    calls.clear()
    pl.run(p, tmp_path / "out")
    assert [k for k, _ in calls] == ["train", "evaluate", "report"]


def test_bad_override_names_stage(tmp_path, calls):
    p = _write(tmp_path)
    with pytest.raises(UserError, match="no stage named 'trian'"):
        pl.run(p, tmp_path / "out", overrides=["trian.iterations=3"])


def test_unknown_stage_key_rejected(tmp_path, calls):
    p = _write(tmp_path)
    with pytest.raises(UserError, match="iteratons"):
        pl.run(p, tmp_path / "out", overrides=["train.iteratons=3"])


def test_a_synth_stage_preset_is_set_in_its_config(tmp_path, calls):
    """``--set synth.preset=X`` changes the synth stage's own config key (``preset`` sits beside the config only in
    train stages)."""
    p = _write(tmp_path)
    cfg = pl.load_pipeline(p, overrides=["synth.preset=demo", "train.preset=paper"])
    synth, train = cfg.stages[0], cfg.stages[1]
    assert synth.config["preset"] == "demo" and train.preset == "paper"


def test_a_bad_set_value_is_named_with_the_file(tmp_path, calls):
    """A bad value given with --set is not blamed on the pipeline file alone: the error names the --set values that
    went in (and no line of the file); a file's own mistake is reported without them, with its line."""
    p = _write(tmp_path)
    with pytest.raises(UserError, match=r"iterations: Input should be .* \(the file's values with --set "
                                        r"train.iterations=-3 evaluate.seed=1\)"):
        pl.run(p, tmp_path / "out", overrides=["train.iterations=-3", "evaluate.seed=1"])
    p.write_text(PIPE.replace('stage = "train"\npreset = "tiny"', 'stage = "train"\npreset = "tiny"\n'
                                                                 'config = { iterations = -3 }'))
    with pytest.raises(UserError) as err:
        pl.run(p, tmp_path / "out")
    assert "iterations (line 10): Input should be" in err.value.message and "--set" not in err.value.message
    with pytest.raises(UserError) as err:  # the file's value replaced by --set: the line would name the wrong value
        pl.run(p, tmp_path / "out", overrides=["train.iterations=-4"])
    assert "iterations: Input should be" in err.value.message and "(line" not in err.value.message
    # synth's preset is a key of its config (a train stage's sits beside it): the line named the file's good value
    with pytest.raises(UserError) as err:
        pl.run(p, tmp_path / "out", overrides=["synth.preset=bogus"])
    assert "preset: Input should be" in err.value.message and "(line" not in err.value.message


@pytest.mark.parametrize("name", ["demo.toml", "smoke.toml", "photos.toml"])
def test_shipped_pipelines_validate(name):
    root = Path(__file__).resolve().parents[2] / "pipelines"
    cfg = pl.load_pipeline(root / name)
    assert cfg.stages[-1].stage == "report"
    for stage in cfg.stages:
        pl._stage_config(stage)
    assert len(pl.check_stages(cfg, root / name)) == len(cfg.stages)  # every stage reads what it can


@pytest.mark.parametrize("name", ["demo.toml", "smoke.toml", "photos.toml"])
def test_the_settings_a_shipped_pipeline_suggests_in_comments_validate(name, tmp_path):
    """Each commented ``# config = {...}`` line is a setting the file suggests for the next stage below it: uncommented
    in that stage's place, the pipeline still validates (a renamed key would otherwise live on in the comment)."""
    text = (Path(__file__).resolve().parents[2] / "pipelines" / name).read_text(encoding="utf-8")
    lines = text.splitlines()
    suggested = [i for i, line in enumerate(lines) if line.startswith("# config = {")]
    for i in suggested:
        stage_line = next(j for j in range(i, len(lines)) if lines[j].startswith("stage = "))
        config_line = next(j for j in range(stage_line, len(lines)) if lines[j].startswith("config = "))
        edited = lines.copy()
        edited[config_line] = lines[i][2:]
        (tmp_path / name).write_text("\n".join(edited) + "\n", encoding="utf-8")
        cfg = pl.load_pipeline(tmp_path / name)
        assert lines[i][2:] in (tmp_path / name).read_text(encoding="utf-8")
        for stage in cfg.stages:
            pl._stage_config(stage)
    assert len(suggested) >= (4 if name == "photos.toml" else 0)


@pytest.mark.parametrize(("edit", "match"), [
    # a report moved before evaluate: evaluate read the report (after synth and train had run)
    (lambda t: t.replace('[[stages]]\nstage = "evaluate"\n', "").replace('stage = "report"\n',
                                                                           'stage = "report"\n[[stages]]\n'
                                                                           'stage = "evaluate"\n'),
     r"stage 'evaluate' \(evaluate\) reads 'report' \(the stage before it: no `input` given\), a report stage; an "
     r"evaluate stage reads the output of a train or prune stage\. Set input = \"train\""),
    (lambda t: t.replace('stage = "evaluate"\n', 'stage = "evaluate"\ninput = "synth"\n'),
     r"reads 'synth', a synth stage"),
    # two evaluations of one run into one folder: each run of the pipeline replaced the other's
    (lambda t: t.replace('stage = "evaluate"\n', 'stage = "evaluate"\nname = "k2"\ninput = "train"\n'
                                                   '[[stages]]\nstage = "evaluate"\nname = "k8"\ninput = "train"\n'),
     r"stages 'k2' and 'k8' both evaluate 'train' \(test views\), into the same folder"),
])
def test_stages_that_cannot_read_their_input_are_refused_before_any_runs(tmp_path, calls, edit, match):
    p = tmp_path / "p.toml"
    p.write_text(edit(PIPE))
    with pytest.raises(UserError, match=match):
        pl.run(p, tmp_path / "out")
    assert calls == [] and not (tmp_path / "out").exists()


def test_photos_pipeline_without_photos_says_how_to_give_them(tmp_path, calls):
    """photos.toml's `photos` is a placeholder: run without --set photos=... is refused before any output folder
    exists, with the option to use."""
    root = Path(__file__).resolve().parents[2] / "pipelines"
    with pytest.raises(UserError, match="--set photos=/path/to/photos"):
        pl.run(root / "photos.toml", tmp_path / "out")
    assert not (tmp_path / "out").exists() and calls == []


@pytest.mark.parametrize(("override", "match"), [
    ("evaluate.num_samples=0", r"p\.toml: invalid configuration in stage 'evaluate': num_samples: Input should be"),
    ("train.preset=tinyy", r"p\.toml: unknown preset 'tinyy'"),
    (None, r"p\.toml: stage 'evaluate': its input 'trian' is neither an earlier stage nor a folder"),
])
def test_every_stage_is_checked_before_the_first_runs(tmp_path, calls, override, match):
    """A mistake in a late stage's configuration or input is refused before any stage runs (synth and train ran
    first, and with photos a reconstruction of minutes), naming the pipeline file and the stage."""
    p = _write(tmp_path)
    if override is None:  # an input that names no stage
        p.write_text(PIPE.replace('stage = "evaluate"', 'stage = "evaluate"\ninput = "trian"'))
    with pytest.raises(UserError, match=match):
        pl.run(p, tmp_path / "out", overrides=[override] if override else None)
    assert calls == [] and not (tmp_path / "out").exists()


def test_photos_given_to_a_pipeline_without_reconstruct_are_noted(tmp_path, capsys):
    p = _write(tmp_path)
    pl.load_pipeline(p, overrides=["photos=/nowhere"])
    assert "--set photos is not used: no reconstruct stage of p.toml starts from photos" in " ".join(capsys.readouterr().err.split())


def test_a_stage_interrupted_with_its_work_kept_stops_the_pipeline_as_an_interruption(tmp_path, monkeypatch):
    """A stage that stops on Ctrl-C with an Interrupted (train's checkpoint, reconstruct's unfinished report) ends the
    pipeline as an interruption (exit code 130 in the CLI), not as a failed stage, and records it."""
    from uncertsplat.errors import Interrupted

    def fake(kind, cfg, up_path, out_dir, device, kwargs):
        out_dir.mkdir(parents=True, exist_ok=True)
        if kind == "train":
            raise Interrupted("training interrupted at step 5; checkpoint saved", path=out_dir)

    monkeypatch.setattr(pl, "_run_stage", fake)
    p = _write(tmp_path)
    with pytest.raises(Interrupted, match="stage 'train' \\(train\\) interrupted: training interrupted") as err:
        pl.run(p, tmp_path / "out")
    assert not isinstance(err.value, StageError) and "stages that finished are skipped" in str(err.value)
    manifest = json.loads((tmp_path / "out" / "train" / "manifest.json").read_text(encoding="utf-8"))
    assert manifest["status"] == "failed" and "interrupted" in json.dumps(manifest)


def _stopped_once(resumed: list[bool], write_config: bool = False, write_scene: bool = False):
    """A ``_run_stage`` whose train stage is stopped with a checkpoint the first time (each call's resume flag goes to
    ``resumed``; ``write_config``, ``write_scene``: it writes the run's config.json, scene.json as train does)."""
    from uncertsplat.errors import Interrupted
    from uncertsplat.schemas.scene import RunScene

    def fake(kind, cfg, up_path, out_dir, device, kwargs):
        out_dir.mkdir(parents=True, exist_ok=True)
        if kind == "train":
            resumed.append(kwargs.get("resume", False))
            if write_config:
                (out_dir / "config.json").write_text(cfg.model_dump_json(), encoding="utf-8")
            if write_scene and not kwargs.get("resume"):
                RunScene(scene=str(up_path.resolve()), source={"kind": "colmap"}, extent=1.0, scene_scale=1.0,
                         width=8, height=6, train=[], test=[]).write(out_dir / "scene.json")
            if len(resumed) == 1:
                (out_dir / "ckpts").mkdir()
                (out_dir / "ckpts" / "step_000005.pt").write_bytes(b"state")
                raise Interrupted("training interrupted at step 5; checkpoint saved", path=out_dir)
    return fake


def test_an_interrupted_train_stage_resumes_from_its_checkpoint(tmp_path, monkeypatch):
    """Run again after Ctrl-C, the train stage goes on from its checkpoint (same settings and inputs) instead of
    moving its folder to .previous and training from step 0; with other settings it starts over."""
    from uncertsplat.errors import Interrupted

    resumed: list[bool] = []
    monkeypatch.setattr(pl, "_run_stage", _stopped_once(resumed))
    p = _write(tmp_path)
    with pytest.raises(Interrupted) as err:
        pl.run(p, tmp_path / "out")
    assert "training resumes from its checkpoint" in str(err.value)
    pl.run(p, tmp_path / "out")
    assert resumed == [False, True]
    assert (tmp_path / "out" / "train" / "ckpts" / "step_000005.pt").is_file()
    assert not (tmp_path / "out" / ".previous" / "train").exists()
    # finished now: skipped; other settings: a new run, the old one kept under .previous
    pl.run(p, tmp_path / "out")
    assert resumed == [False, True]
    pl.run(p, tmp_path / "out", overrides=["train.seed=7"])
    assert resumed == [False, True, False] and (tmp_path / "out" / ".previous" / "train").is_dir()


def test_an_interrupted_train_stage_trained_on_by_hand_is_not_resumed(tmp_path, monkeypatch, capsys):
    """Stopped, then `train --resume --iterations 1700` by hand (its config.json says so), then the pipeline again with
    its own settings: it resumed that run and recorded a 1700-step model under a manifest of 1500 (a helper's
    review); it runs the stage again now, the hand-trained run kept under .previous."""
    from uncertsplat.errors import Interrupted

    resumed: list[bool] = []
    monkeypatch.setattr(pl, "_run_stage", _stopped_once(resumed, write_config=True))
    p = _write(tmp_path)
    with pytest.raises(Interrupted):
        pl.run(p, tmp_path / "out")
    run_config = tmp_path / "out" / "train" / "config.json"
    by_hand = json.loads(run_config.read_text(encoding="utf-8"))
    by_hand["iterations"] += 200  # `train OUT/synth -o OUT/train --resume --iterations N`
    run_config.write_text(json.dumps(by_hand), encoding="utf-8")
    capsys.readouterr()
    pl.run(p, tmp_path / "out")
    said = " ".join(capsys.readouterr().err.split())
    assert resumed == [False, False] and "it is not resumed; 'train' runs again" in said
    kept = next((tmp_path / "out" / ".previous").glob("train*"))
    assert json.loads((kept / "config.json").read_text(encoding="utf-8"))["iterations"] == by_hand["iterations"]


def test_a_file_where_a_stage_writes_its_folder_is_said(tmp_path, monkeypatch):
    monkeypatch.setattr(pl, "_run_stage", lambda *a: None)
    p = _write(tmp_path)
    (tmp_path / "out").mkdir()
    first = pl.load_pipeline(p).stages[0]
    (tmp_path / "out" / (first.name or first.stage)).write_text("mine")
    with pytest.raises(UserError, match="a file is where the stage '.*' writes its folder"):
        pl.run(p, tmp_path / "out")
    assert (tmp_path / "out" / (first.name or first.stage)).read_text(encoding="utf-8") == "mine"


def test_a_stage_s_advice_names_the_pipeline_s_keys(tmp_path, monkeypatch):
    """A failing stage's advice names its command's options (--iterations); the pipeline adds how to set them there
    (--set train.iterations), and only for options that are the stage's config keys (not --resume)."""
    def fake(kind, cfg, up_path, out_dir, device, kwargs):
        out_dir.mkdir(parents=True, exist_ok=True)
        if kind == "train":
            raise UserError("the run is too short", hint="Raise --iterations, or continue with --resume.")

    monkeypatch.setattr(pl, "_run_stage", fake)
    with pytest.raises(StageError) as err:
        pl.run(_write(tmp_path), tmp_path / "out")
    text = str(err.value)
    assert "(in this pipeline: --set train.iterations)" in text and "train.resume" not in text


PRUNED = PIPE.replace('[[stages]]\nstage = "report"', '[[stages]]\nstage = "prune"\ninput = "train"\n'
                                                        'config = { keep_ratio = 0.9 }\n[[stages]]\nstage = "report"')


def _no_posterior(seen: dict):
    def fake(kind, cfg, up_path, out_dir, device, kwargs):
        seen.setdefault("kinds", []).append(kind)
        if kind == "prune":  # as prune.run says it, before it writes anything
            raise NoPosterior("the run has no Gaussians with a posterior, so there is no uncertainty to prune by: "
                              "give it --iterations 222 or more for a posterior", path=up_path,
                              hint="Prune a run whose Gaussians carry a posterior.")
        out_dir.mkdir(parents=True, exist_ok=True)
        if kind == "report":
            seen["runs"], seen["notes"] = kwargs["runs"], kwargs["notes"]
    return fake


def test_a_prune_of_a_run_without_a_posterior_is_skipped_and_the_report_says_why(tmp_path, monkeypatch, capsys):
    """A photos pipeline too short to give a posterior stopped at its prune stage without a report: the stage is
    skipped with a warning that names the train stage's key, and the report notes it with the run."""
    seen: dict = {}
    monkeypatch.setattr(pl, "_run_stage", _no_posterior(seen))
    p = tmp_path / "p.toml"
    p.write_text(PRUNED)
    outs = pl.run(p, tmp_path / "out")
    said = " ".join(capsys.readouterr().err.split())
    assert seen["kinds"] == ["synth", "train", "evaluate", "prune", "report"] and "prune" not in outs
    assert "stage 'prune' (prune) skipped:" in said and "(in this pipeline: --set train.iterations)" in said
    assert "('prune' skipped: see above)" in said
    assert seen["runs"] == [tmp_path / "out" / "train"]
    ((where, (note,)),) = seen["notes"].items()
    assert where == tmp_path / "out" / "train" and note.startswith("the pipeline's stage 'prune' did not run: ")
    assert "--set train.iterations" in note and "Prune a run whose" not in note
    assert not (tmp_path / "out" / "prune").exists()
    # the report says it, so it is made again when the prune stage comes or goes (it was "unchanged": a stale note)
    seen.clear()
    pl.run(p, tmp_path / "out")
    assert seen["kinds"] == ["prune"]
    p.write_text(PIPE)
    pl.run(p, tmp_path / "out")
    assert seen["kinds"] == ["prune", "report"] and seen["notes"] == {}
    p.write_text(PRUNED)
    pl.run(p, tmp_path / "out")
    assert seen["kinds"] == ["prune", "report", "prune", "report"] and seen["notes"]
    # a stage that reads the skipped one's output (the demo's evaluation of the pruned model) is skipped too, and the
    # pipeline still ends with its report (it stopped there, with a command-line option a pipeline does not have)
    p.write_text(PRUNED.replace('stage = "report"', 'stage = "evaluate"\nname = "again"\ninput = "prune"\n[[stages]]\nstage = "report"'))
    seen.clear()
    capsys.readouterr()
    pl.run(p, tmp_path / "out")
    said = " ".join(capsys.readouterr().err.split())
    assert seen["kinds"] == ["prune", "report"]
    assert "stage 'again' (evaluate) skipped: it reads the output of stage 'prune', which was skipped" in said
    assert "('prune', 'again' skipped: see above)" in said


def test_a_relative_photos_path_is_read_from_where_it_was_written(tmp_path, monkeypatch):
    """In the file: from the file's folder, even when the current folder has a folder of that name; on the command
    line: from the current folder."""
    (tmp_path / "pipes" / "photos").mkdir(parents=True)
    (tmp_path / "cwd" / "photos").mkdir(parents=True)
    p = tmp_path / "pipes" / "p.toml"
    p.write_text('\nphotos = "photos"' + PIPE)
    monkeypatch.chdir(tmp_path / "cwd")
    assert pl.load_pipeline(p).photos == (tmp_path / "pipes" / "photos").resolve()
    assert pl.load_pipeline(p, overrides=["photos=photos"]).photos == (tmp_path / "cwd" / "photos").resolve()
    (tmp_path / "pipes" / "photos").rmdir()  # only in the current folder: found there (what older versions read)
    assert pl.load_pipeline(p).photos == (tmp_path / "cwd" / "photos").resolve()


def test_a_failed_run_never_replaces_the_last_finished_output(tmp_path, calls):
    """After a finished train stage, a run with other settings that fails (or is stopped) and then another change:
    the finished output stays in .previous/train, the failed one goes to .previous/train-unfinished."""
    p = _write(tmp_path)
    pl.run(p, tmp_path / "out", overrides=["train.iterations=7"])
    good = (tmp_path / "out" / "train" / "out.txt").read_text(encoding="utf-8")
    with pytest.raises(StageError, match="boom"):
        pl.run(p, tmp_path / "out", overrides=["train.seed=99"])
    assert (tmp_path / "out" / ".previous" / "train" / "out.txt").read_text(encoding="utf-8") == good
    pl.run(p, tmp_path / "out", overrides=["train.iterations=8"])  # the failed output moves out of the way
    assert (tmp_path / "out" / ".previous" / "train" / "out.txt").read_text(encoding="utf-8") == good
    failed = json.loads((tmp_path / "out" / ".previous" / "train-unfinished" / "manifest.json").read_text(encoding="utf-8"))
    assert failed["status"] == "failed"
    pl.run(p, tmp_path / "out", overrides=["train.iterations=9"])  # finished replaces finished, as before
    assert json.loads((tmp_path / "out" / ".previous" / "train" / "out.txt").read_text(encoding="utf-8"))["iterations"] == 8


def _photos_pipeline(tmp_path: Path, calls) -> tuple[Path, Path]:
    """(photos, pipeline file): 3 photos, a reconstruct and a train stage on them, run once (``calls`` cleared)."""
    photos = tmp_path / "photos"
    photos.mkdir()
    for i in range(3):
        (photos / f"{i}.jpg").write_bytes(bytes([i]) * 100)
    p = tmp_path / "p.toml"
    p.write_text('name = "t"\ndevice = "cpu"\nphotos = "photos"\n[[stages]]\nstage = "reconstruct"\n'
                 '[[stages]]\nstage = "train"\npreset = "tiny"\n')
    pl.run(p, tmp_path / "out")
    calls.clear()
    return photos, p


def _as_recorded_before(out: Path, photos_hash: str) -> None:
    """The reconstruct stage's manifest holding ``photos_hash`` for its photos (as an earlier version wrote it), and
    the train stage's record of that manifest."""
    manifest = out / "reconstruct" / "manifest.json"
    data = json.loads(manifest.read_text(encoding="utf-8"))
    data["input_hashes"]["photos"] = photos_hash
    manifest.write_text(json.dumps(data))
    train = out / "train" / "manifest.json"
    record = json.loads(train.read_text(encoding="utf-8"))
    record["input_hashes"]["reconstruct"] = pl.read_manifest(manifest.parent).key
    train.write_text(json.dumps(record))


def test_photos_touched_or_copied_without_times_are_unchanged(tmp_path, calls):
    """The photo folder's fingerprint is its files' names and contents: new modification times (a `cp -r`, a sync)
    skip every stage; a changed photo runs them again; a manifest holding the earlier fingerprint (names, sizes,
    times) still counts as unchanged."""
    import os

    from uncertsplat.stages.manifest import fingerprints

    photos, p = _photos_pipeline(tmp_path, calls)
    for f in photos.iterdir():
        os.utime(f, (1e9, 1e9))
    pl.run(p, tmp_path / "out")
    assert calls == []
    _as_recorded_before(tmp_path / "out", fingerprints(photos)[2])  # names, sizes and times
    pl.run(p, tmp_path / "out")
    assert calls == []
    (photos / "1.jpg").write_bytes(b"another photo")
    pl.run(p, tmp_path / "out")
    assert [k for k, _ in calls] == ["reconstruct", "train"]


def test_the_photos_masks_are_an_input_of_reconstruct(tmp_path, calls, monkeypatch):
    """A reconstruct stage's ``masks`` (relative: from the pipeline file's folder) are an input as its photos are: a
    mask changed runs reconstruct and train again; the same masks skip both."""
    photos = tmp_path / "photos"
    photos.mkdir()
    (tmp_path / "masks").mkdir()
    for i in range(3):
        (photos / f"{i}.jpg").write_bytes(bytes([i]) * 100)
        (tmp_path / "masks" / f"{i}.jpg.png").write_bytes(bytes([i + 7]) * 50)
    p = tmp_path / "p.toml"
    p.write_text('name = "t"\ndevice = "cpu"\nphotos = "photos"\n[[stages]]\nstage = "reconstruct"\n'
                 'config = { masks = "masks" }\n[[stages]]\nstage = "train"\npreset = "tiny"\n')
    (tmp_path / "elsewhere").mkdir()
    monkeypatch.chdir(tmp_path / "elsewhere")
    pl.run(p, tmp_path / "out")
    assert [k for k, _ in calls] == ["reconstruct", "train"]
    given = json.loads((tmp_path / "out" / "reconstruct" / "out.txt").read_text(encoding="utf-8"))["masks"]
    assert Path(given) == tmp_path / "masks"
    calls.clear()
    pl.run(p, tmp_path / "out")
    assert calls == []
    (tmp_path / "masks" / "1.jpg.png").write_bytes(b"another mask")
    pl.run(p, tmp_path / "out")
    assert [k for k, _ in calls] == ["reconstruct", "train"]


def test_notes_and_leftovers_beside_the_photos_are_not_inputs(tmp_path, calls):
    """The fingerprint covered every file of an input folder: a notes.txt beside the photos, an editor's backup or a
    .DS_Store retrained the whole pipeline. A manifest holding the fingerprint of every file (written before) still
    counts as unchanged; a photo added counts."""
    from uncertsplat.stages.manifest import fingerprints

    photos, p = _photos_pipeline(tmp_path, calls)
    (photos / "sub").mkdir()
    (photos / "notes.txt").write_text("taken at noon")
    (photos / "README.md").write_text("my capture")
    (photos / ".DS_Store").write_bytes(b"x")
    (photos / "0.jpg~").write_bytes(b"backup")
    (photos / "sub" / ".0.jpg.swp").write_bytes(b"swap")
    pl.run(p, tmp_path / "out")
    assert calls == []
    _as_recorded_before(tmp_path / "out", fingerprints(photos)[1])  # as the version before wrote it: every file
    pl.run(p, tmp_path / "out")
    assert calls == []
    (photos / "sub" / "3.jpg").write_bytes(b"a photo in a subfolder")
    pl.run(p, tmp_path / "out")
    assert [k for k, _ in calls] == ["reconstruct", "train"]
    # an output inside the photo folder is refused before anything is written there (reconstruct refuses a
    # workspace among its photos, after the pipeline had left its own file in the photo folder)
    calls.clear()
    for inside in (photos / "out", photos, photos / "sub" / "out"):
        with pytest.raises(UserError, match="the output folder is inside the photo folder"):
            pl.run(p, inside)
    assert calls == [] and not (photos / "out").exists() and not (photos / "sub" / "out").exists()
    assert not (photos / pl.STARTED).exists()


def test_a_nested_stage_s_files_are_not_its_parent_s_outputs(tmp_path):
    """prune writes its evaluation into prune/eval; an evaluate stage after it then owns that folder (its manifest)
    and may write other files there: they are not prune's outputs gone (prune and the evaluation ran again on every
    call)."""
    from uncertsplat.stages.manifest import missing_outputs

    (tmp_path / "eval").mkdir()
    (tmp_path / "a.txt").write_text("")
    m = pl.Manifest(stage="prune", name="prune", config_hash="c", input_hashes={}, config={}, status="done",
                    started_at=0.0, outputs=["a.txt", "eval/maps/v.exr", "eval/metrics.json"])
    assert missing_outputs(tmp_path, m) == ["eval/maps/v.exr", "eval/metrics.json"]
    (tmp_path / "eval" / "manifest.json").write_text("{}")
    assert missing_outputs(tmp_path, m) == []
    (tmp_path / "a.txt").unlink()
    assert missing_outputs(tmp_path, m) == ["a.txt"]


def test_a_stage_whose_output_is_gone_runs_again(tmp_path, calls, capsys):
    """The skip read the manifest alone: with a trained model deleted, every stage was skipped (the report pointing
    at figures that were gone) and a later change failed in the next stage. A stage with a recorded output gone
    runs again, and says why; checkpoints and the evaluation's caches are not outputs (a resume rotates them)."""
    p = _write(tmp_path)
    pl.run(p, tmp_path / "out")
    recorded = json.loads((tmp_path / "out" / "train" / "manifest.json").read_text(encoding="utf-8"))["outputs"]
    assert recorded == ["out.txt"]
    (tmp_path / "out" / "train" / "ckpts").mkdir()
    (tmp_path / "out" / "train" / "ckpts" / "step_000001.pt").write_bytes(b"")
    assert pl.stage_outputs(tmp_path / "out" / "train") == ["out.txt"]  # (ckpts/ and the stage's eval/ manifest)
    calls.clear()
    (tmp_path / "out" / "train" / "out.txt").unlink()
    capsys.readouterr()
    pl.run(p, tmp_path / "out")
    said = " ".join(capsys.readouterr().err.split())
    assert "train's output out.txt is gone from" in said and "it runs again" in said, said
    # the train folder, its evaluation inside, went to .previous: that evaluation runs again too, and so does the
    # report of the two (a stage run again with the same key is another input: on CUDA another model, where the
    # report was skipped); synth is kept
    assert [k for k, _ in calls] == ["train", "evaluate", "report"]
    calls.clear()
    pl.run(p, tmp_path / "out")
    assert calls == []
    # manifests from before the stages were keyed with when their inputs finished (each input stage by its key
    # alone) are taken as they are
    from uncertsplat.schemas.runs import Manifest

    keys = {}
    for name, folder in (("synth", "synth"), ("train", "train"), ("evaluate", "train/eval"), ("report", "report")):
        m = tmp_path / "out" / folder / "manifest.json"
        data = json.loads(m.read_text(encoding="utf-8"))
        assert all("@" in v for v in data["input_hashes"].values())
        data["input_hashes"] = {k: keys[k] for k in data["input_hashes"]}
        keys[name] = Manifest.model_validate(data).key
        m.write_text(json.dumps(data))
    pl.run(p, tmp_path / "out")
    assert calls == []
    # ... but not where their input stage ran again (with the same key: its output deleted): they run again too
    (tmp_path / "out" / "synth" / "out.txt").unlink()
    pl.run(p, tmp_path / "out")
    assert [k for k, _ in calls] == ["synth", "train", "evaluate", "report"]


def test_a_stage_whose_data_file_changed_size_runs_again(tmp_path, monkeypatch, capsys):
    """An output damaged in place (a copy cut short, a file truncated by a full disk while written again) was taken as
    unchanged: the manifest held the names alone. The files that hold data (models, maps, figures) are recorded with
    their sizes; one of another size makes its stage run again. A JSON record rewritten at another size (a command
    run again by hand: other timings) does not."""
    ran: list[str] = []

    def fake(kind, cfg, up_path, out_dir, device, kwargs):
        ran.append(kind)
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "model.ply").write_bytes(b"x" * 1000)
        (out_dir / "record.json").write_text('{"seconds": 1.5}')

    monkeypatch.setattr(pl, "_run_stage", fake)
    p = _write(tmp_path)
    pl.run(p, tmp_path / "out")
    manifest = json.loads((tmp_path / "out" / "train" / "manifest.json").read_text(encoding="utf-8"))
    assert manifest["output_sizes"] == {"model.ply": 1000}
    ran.clear()
    (tmp_path / "out" / "train" / "record.json").write_text('{"seconds": 12.25}')
    pl.run(p, tmp_path / "out")
    assert ran == []
    with open(tmp_path / "out" / "train" / "model.ply", "r+b") as f:
        f.truncate(600)
    capsys.readouterr()
    pl.run(p, tmp_path / "out")
    said = " ".join(capsys.readouterr().err.split())
    assert "train's output model.ply in" in said and "is not the size the stage left" in said, said
    assert ran == ["train", "evaluate", "report"]  # (its evaluation inside went to .previous with it)
    assert (tmp_path / "out" / ".previous" / "train" / "model.ply").stat().st_size == 600  # kept, not deleted
    ran.clear()
    pl.run(p, tmp_path / "out")
    assert ran == []
    # a manifest of version 2 (no sizes) compares none
    m = tmp_path / "out" / "train" / "manifest.json"
    m.write_text(json.dumps({**{k: v for k, v in json.loads(m.read_text(encoding="utf-8")).items() if k != "output_sizes"},
                             "schema_version": 2}))
    with open(tmp_path / "out" / "train" / "model.ply", "r+b") as f:
        f.truncate(10)
    pl.run(p, tmp_path / "out")
    assert ran == []


def test_an_output_made_again_by_hand_with_other_settings_runs_again(tmp_path, calls, capsys):
    """`uncertsplat evaluate RUN --num-samples 4` on the pipeline's run replaced its evaluation, and the next `run`
    skipped the stage as unchanged (its manifest said K = 10, metrics.json K = 4): the evaluation's and the run's
    own record of their settings must be the stage's."""
    p = _write(tmp_path)
    pl.run(p, tmp_path / "out")
    used = tmp_path / "out" / "train" / "eval" / "config.json"
    ran = json.loads((tmp_path / "out" / "train" / "eval" / "manifest.json").read_text(encoding="utf-8"))["config"]
    used.write_text(json.dumps(ran))  # as the stage wrote it
    calls.clear()
    pl.run(p, tmp_path / "out")
    assert calls == []
    used.write_text(json.dumps({**ran, "preview": not ran["preview"]}))  # what it writes, not what it measures
    pl.run(p, tmp_path / "out")
    assert calls == []
    used.write_text(json.dumps({**ran, "num_samples": 4}))
    capsys.readouterr()
    pl.run(p, tmp_path / "out")
    said = " ".join(capsys.readouterr().err.split())
    assert [k for k, _ in calls] == ["evaluate", "report"] and "was made again since with other settings" in said, said
    trained = json.loads((tmp_path / "out" / "train" / "manifest.json").read_text(encoding="utf-8"))
    (tmp_path / "out" / "train" / "config.json").write_text(json.dumps(trained["config"]))
    calls.clear()
    pl.run(p, tmp_path / "out")
    assert calls == []
    (tmp_path / "out" / "train" / "config.json").write_text(json.dumps({**trained["config"], "iterations": 99}))
    pl.run(p, tmp_path / "out")
    assert [k for k, _ in calls] == ["train", "evaluate", "report"]


def test_a_damaged_manifest_is_named_before_its_stage_runs_again(tmp_path, calls, capsys):
    p = _write(tmp_path)
    pl.run(p, tmp_path / "out")
    (tmp_path / "out" / "train" / "manifest.json").write_text('{"stage": "tra')
    calls.clear()
    capsys.readouterr()
    pl.run(p, tmp_path / "out")
    assert [k for k, _ in calls][0] == "train"
    said = " ".join(capsys.readouterr().err.split())
    assert "manifest.json cannot be read (damaged or from another version), so 'train' runs again" in said
    assert (tmp_path / "out" / ".previous").is_dir()


@pytest.mark.parametrize("name", ["../escape", "/tmp/abs", "a/b", "my.synth", "device", ".hidden", ""])
def test_a_stage_name_that_is_no_plain_folder_name_is_refused(tmp_path, calls, name):
    """A stage's name is a folder inside OUT and the first part of --set NAME.key: "../x" or an absolute path wrote
    outside OUT (and moved a folder of the user's to .previous), "a.b" could not be addressed, "device" was read as
    the top-level key."""
    p = tmp_path / "p.toml"
    p.write_text(f'[[stages]]\nstage = "synth"\nname = "{name}"\nconfig = {{ preset = "tiny" }}\n')
    with pytest.raises(UserError, match="is not a stage name"):
        pl.run(p, tmp_path / "out")
    assert calls == [] and not (tmp_path / "out").exists()


def test_a_pipeline_that_would_do_nothing_says_so(tmp_path, calls, capsys):
    """No stage is an error (it finished in 0.0 s with exit code 0); photos given to a pipeline that never reads
    them are named."""
    p = tmp_path / "p.toml"
    p.write_text("stages = []\n")
    with pytest.raises(UserError, match=r"stages \(line 1\): List should have at least 1 item"):
        pl.run(p, tmp_path / "out")
    capsys.readouterr()
    pl.run(_write(tmp_path), tmp_path / "out", overrides=[f"photos={tmp_path}"])
    said = " ".join(capsys.readouterr().err.split())
    assert said.count("--set photos is not used: no reconstruct stage of p.toml starts from photos") == 1
    # a reconstruct after synth reads the synthetic images, not the photos (demo.toml): said too
    q = tmp_path / "q.toml"
    q.write_text('[[stages]]\nstage = "synth"\nconfig = { preset = "tiny" }\n[[stages]]\nstage = "reconstruct"\n')
    pl.load_pipeline(q, [f"photos={tmp_path}"])
    assert "--set photos is not used: no reconstruct stage of q.toml" in " ".join(capsys.readouterr().err.split())


def test_a_stage_s_relative_depth_folder_is_found_beside_the_pipeline_file(tmp_path, monkeypatch):
    """evaluate's depth_gt written relative in a pipeline: read from the current folder as before, and from the
    pipeline file's folder when the current folder has no such path (run from elsewhere, it was 'not found')."""
    (tmp_path / "cfg" / "depth").mkdir(parents=True)
    p = tmp_path / "cfg" / "p.toml"
    p.write_text(PIPE.replace('stage = "evaluate"\n', 'stage = "evaluate"\nconfig = { depth_gt = "depth" }\n'))
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    cfg = pl.load_pipeline(p)
    assert next(s for s in cfg.stages if s.stage == "evaluate").config["depth_gt"] == str(tmp_path / "cfg" / "depth")
    (elsewhere / "depth").mkdir()  # the current folder has it: read from there, as always
    cfg = pl.load_pipeline(p)
    assert next(s for s in cfg.stages if s.stage == "evaluate").config["depth_gt"] == "depth"


def test_a_rerun_that_holds_out_other_views_says_so(tmp_path, monkeypatch, capsys):
    """A photo removed from the folder moves the every-8th split: the train stage run again scores other held-out
    photos, and the two runs' metrics do not compare. The pipeline says which views moved and how to keep them."""
    from uncertsplat.schemas.scene import RunScene

    views = [f"v{i:02d}.png" for i in range(17)]

    def fake(kind, cfg, up_path, out_dir, device, kwargs):
        out_dir.mkdir(parents=True, exist_ok=True)
        if kind == "train":
            names = views if cfg.iterations != 7 else views[1:]  # the second run: the first photo is gone
            test = names[::8]
            RunScene(scene=str(up_path), extent=1.0, scene_scale=1.0, width=4, height=3, test=test,
                     train=[n for n in names if n not in test]).write(out_dir / "scene.json")

    monkeypatch.setattr(pl, "_run_stage", fake)
    p = _write(tmp_path)
    pl.run(p, tmp_path / "out")
    assert "holds out other views" not in capsys.readouterr().err  # no previous run
    pl.run(p, tmp_path / "out", overrides=["train.iterations=7"])
    text = " ".join(capsys.readouterr().err.split())
    assert "this run holds out other views than the previous one" in text
    assert "no longer held out: v00.png, v08.png, v16.png; newly held out: v01.png, v09.png" in text
    # the earlier held-out photos still in the scene, as the command line takes them
    assert """--set 'train.scene.test_names=["v08.png", "v16.png"]'""" in text
    assert pl.held_out_change(tmp_path / "out" / "train", tmp_path / "out" / "train") is None  # the same views
    assert pl.held_out_change(tmp_path / "nowhere", tmp_path / "out" / "train") is None


def test_extend_is_refused_as_a_pipeline_setting(tmp_path, calls):
    """A pipeline moves a stage's workspace aside before it runs the stage again, so --extend would find none: said
    before anything runs, with the command that grows the workspace."""
    p = tmp_path / "p.toml"
    p.write_text('name = "t"\ndevice = "cpu"\nphotos = "ph"\n[[stages]]\nstage = "reconstruct"\n'
                 'config = { extend = true }\n')
    (tmp_path / "ph").mkdir()
    with pytest.raises(UserError, match="extend is a step of its own") as err:
        pl.run(p, tmp_path / "out")
    assert "--extend" in err.value.hint and calls == []


def test_a_report_without_a_run_before_it_is_refused_before_any_stage_runs(tmp_path, calls):
    """Found only at the report's turn, after the stages before it had run (an external evaluate, then report)."""
    p = tmp_path / "p.toml"
    p.write_text('name = "t"\ndevice = "cpu"\n[[stages]]\nstage = "synth"\nconfig = { preset = "tiny" }\n'
                 '[[stages]]\nstage = "report"\n')
    with pytest.raises(UserError, match="stage 'report' needs a train or prune stage before it"):
        pl.run(p, tmp_path / "out")
    assert calls == []
    # a report given a run folder as its input (a robot's copied run): the input is not read, and the error says so
    (tmp_path / "RUN").mkdir()
    p.write_text('name = "t"\ndevice = "cpu"\n[[stages]]\nstage = "report"\ninput = "RUN"\n')
    with pytest.raises(UserError, match="needs a train or prune stage before it .*its input 'RUN' is not read") as err:
        pl.run(p, tmp_path / "out")
    assert "uncertsplat report RUN" in err.value.hint and calls == []
    (tmp_path / "copied run").mkdir()  # the hint names the folder given, quoted for the shell
    p.write_text('name = "t"\ndevice = "cpu"\n[[stages]]\nstage = "report"\ninput = "copied run"\n')
    with pytest.raises(UserError, match="its input 'copied run' is not read") as err:
        pl.run(p, tmp_path / "out")
    assert "uncertsplat report 'copied run'" in err.value.hint and calls == []


def test_a_folder_the_pipeline_did_not_write_is_kept_apart_and_never_replaced(tmp_path, calls):
    """OUT/train trained by hand went into the one-generation rotation (.previous/train) and the next change deleted
    it (a helper's audit): a folder without a manifest is kept under a name no later generation takes."""
    p = _write(tmp_path)
    mine = tmp_path / "out" / "train"
    mine.mkdir(parents=True)
    (mine / "NOTES.txt").write_text("my own run")
    pl.run(p, tmp_path / "out")
    kept = tmp_path / "out" / ".previous" / "train-not-from-this-pipeline"
    assert (kept / "NOTES.txt").read_text(encoding="utf-8") == "my own run"
    pl.run(p, tmp_path / "out", overrides=["train.iterations=7"])  # a change: the pipeline's train rotates
    pl.run(p, tmp_path / "out", overrides=["train.iterations=8"])
    assert (kept / "NOTES.txt").read_text(encoding="utf-8") == "my own run"
    assert json.loads((tmp_path / "out" / ".previous" / "train" / "out.txt").read_text(encoding="utf-8"))["iterations"] == 7
    # a folder of its own without a manifest (a stage killed before writing it) takes the rotation, as an unfinished
    # output beside the finished one (a review: it was kept apart, one more copy at every such kill)
    (tmp_path / "out" / "train" / "manifest.json").unlink()
    pl.run(p, tmp_path / "out", overrides=["train.iterations=9"])
    assert json.loads((tmp_path / "out" / ".previous" / "train-unfinished" / "out.txt").read_text(encoding="utf-8"))["iterations"] == 8
    assert not (tmp_path / "out" / ".previous" / "train-not-from-this-pipeline-2").exists()
    # a second folder it never wrote takes a numbered name
    shutil.rmtree(tmp_path / "out" / "report")
    theirs = tmp_path / "out" / "report"
    theirs.mkdir()
    (theirs / "mine.txt").write_text("x")
    (tmp_path / "out" / ".stages_started.json").write_text(json.dumps(["synth", "train", "evaluate"]))
    (tmp_path / "out" / ".previous" / "report-not-from-this-pipeline").mkdir(parents=True)
    pl.run(p, tmp_path / "out", overrides=["train.iterations=10"])
    assert (tmp_path / "out" / ".previous" / "report-not-from-this-pipeline-2" / "mine.txt").is_file()


def _one_train_stage(root: Path) -> Path:
    """``root/p.toml``, a pipeline of one train stage on the folder ``root/scene`` (one image); returns its path."""
    (root / "scene" / "images").mkdir(parents=True)
    (root / "scene" / "images" / "a.png").write_text("x")
    p = root / "p.toml"
    p.write_text('name = "m"\n[[stages]]\nstage = "train"\ninput = "scene"\npreset = "tiny"\n')
    return p


def test_a_project_moved_with_its_pipeline_file_skips_its_stages(tmp_path, calls, capsys):
    """A stage reading a folder beside the pipeline file (``input = "scene"``) was keyed by the folder's resolved path:
    the project moved elsewhere trained again from scratch (and the next move lost the first run from .previous).
    Keyed as the file writes it, the moved project skips every stage; a manifest keyed the old way is taken too."""
    project = tmp_path / "a"
    p = _one_train_stage(project)
    pl.run(p, project / "out")
    assert [k for k, _ in calls] == ["train"]
    recorded = json.loads((project / "out" / "train" / "manifest.json").read_text(encoding="utf-8"))["input_hashes"]
    assert list(recorded) == ["scene"]
    calls.clear()
    project.rename(tmp_path / "b")
    pl.run(tmp_path / "b" / "p.toml", tmp_path / "b" / "out")
    assert calls == []
    # the layout of before: keyed by the resolved path of the folder
    m = tmp_path / "b" / "out" / "train" / "manifest.json"
    data = json.loads(m.read_text(encoding="utf-8"))
    data["input_hashes"] = {str((tmp_path / "b" / "scene").resolve()): recorded["scene"]}
    m.write_text(json.dumps(data))
    pl.run(tmp_path / "b" / "p.toml", tmp_path / "b" / "out")
    assert calls == []
    (tmp_path / "b" / "scene" / "images" / "a.png").write_text("y")  # its contents changed: it runs again
    pl.run(tmp_path / "b" / "p.toml", tmp_path / "b" / "out")
    assert [k for k, _ in calls] == ["train"]


def test_a_run_trained_into_the_scene_folder_by_hand_is_no_change_of_the_scene(tmp_path, calls):
    """A train stage's scene folder was fingerprinted with every file in it: a run trained into it by hand
    (`uncertsplat train scene -o scene/myrun`), which the scene's loader never reads, retrained the stage from step 0
    (as the sweep's scene fingerprint, uncertsplat's own outputs inside the scene are left out). A manifest holding
    the fingerprint with such a run counted still skips; a photo changed runs the stage again."""
    from uncertsplat.stages.manifest import fingerprints

    p = _one_train_stage(tmp_path)
    pl.run(p, tmp_path / "out")
    assert [k for k, _ in calls] == ["train"]
    calls.clear()
    run = tmp_path / "scene" / "myrun"
    (run / "ckpts").mkdir(parents=True)
    (run / "config.json").write_text("{}")
    (run / "stats.jsonl").write_text('{"step": 1}\n')
    (run / "ckpts" / "step_000001.pt").write_bytes(b"model")
    pl.run(p, tmp_path / "out")
    assert calls == []
    # a manifest recorded with the run in the fingerprint (as before) is the same scene too
    m = tmp_path / "out" / "train" / "manifest.json"
    data = json.loads(m.read_text(encoding="utf-8"))
    data["input_hashes"] = {"scene": fingerprints(tmp_path / "scene", skip=[tmp_path / "out"])[0]}
    m.write_text(json.dumps(data))
    pl.run(p, tmp_path / "out")
    assert calls == []
    (tmp_path / "scene" / "images" / "a.png").write_text("y")
    pl.run(p, tmp_path / "out")
    assert [k for k, _ in calls] == ["train"]


def test_a_prune_stage_of_a_run_outside_out_is_skipped_when_unchanged(tmp_path, calls):
    """A prune stage of a run outside OUT fingerprinted every file of the run, the evaluation an evaluate stage of the
    pipeline writes into it too: the prune stage pruned again at every call, nothing changed; so did a `select-views
    RUN` by hand (its output is RUN/select). Neither is the run's model; the model trained on is."""
    from uncertsplat.schemas.select import Selection

    run = tmp_path / "myrun"
    run.mkdir()
    (run / "config.json").write_text("{}")
    (run / "variational.ply").write_text("model")
    p = tmp_path / "p.toml"
    p.write_text('[[stages]]\nstage = "prune"\ninput = "myrun"\nconfig = { keep_ratio = 0.9 }\n[[stages]]\n'
                 'stage = "evaluate"\nname = "ev"\ninput = "myrun"\n')
    pl.run(p, tmp_path / "out")
    assert [k for k, _ in calls] == ["prune", "evaluate"]
    calls.clear()
    pl.run(p, tmp_path / "out")
    assert calls == []
    Selection(run=str(run), score="variance", candidates="around:6", num_candidates=6, chosen=[], seconds=0.1,
              seconds_per_candidate=0.01).write(run / "select" / "selection.json")
    (run / "select" / "selection.png").write_bytes(b"png")
    pl.run(p, tmp_path / "out")
    assert calls == []
    (run / "variational.ply").write_text("trained on")
    pl.run(p, tmp_path / "out")
    assert [k for k, _ in calls] == ["prune", "evaluate"]


def test_a_home_folder_in_a_path_setting_is_expanded(monkeypatch, tmp_path):
    """``photos = "~/..."`` in a pipeline file or ``--set depth_gt=~/...`` was looked for in a folder named ``~``
    (no shell expands them there)."""
    from uncertsplat.config import EvalConfig, PipelineConfig

    monkeypatch.setenv("HOME", str(tmp_path))
    assert PipelineConfig(photos="~/shots", stages=[{"stage": "synth"}]).photos == tmp_path / "shots"
    assert EvalConfig(depth_gt="~/depth").depth_gt == tmp_path / "depth"
    assert EvalConfig(depth_gt="depth").depth_gt == Path("depth")  # relative paths as they were


def test_a_training_killed_without_a_word_resumes_from_its_checkpoint(tmp_path, monkeypatch):
    """A train stage killed by ``kill -9`` (the OOM killer) or ended by a full disk left checkpoints and no manifest of
    its start (or a failed one): the next `run` moved the folder to .previous and trained from step 0. The pipeline
    records the key each stage was started with; started again with it, the training resumes."""
    seen: list[tuple[str, bool]] = []
    fail: dict[str, type[BaseException] | None] = {"train": None}

    class Killed(BaseException):  # nothing of the stage's own handling runs, as under SIGKILL
        pass

    def fake(kind, cfg, up_path, out_dir, device, kwargs):
        seen.append((kind, bool(kwargs.get("resume"))))
        out_dir.mkdir(parents=True, exist_ok=True)
        if kind == "train":
            (out_dir / "ckpts").mkdir(exist_ok=True)
            (out_dir / "ckpts" / "step_000002.pt").write_bytes(b"x")
            if fail["train"] is not None:
                raise fail["train"]()
        (out_dir / "out.txt").write_text("done")

    monkeypatch.setattr(pl, "_run_stage", fake)
    monkeypatch.setattr(pl, "_has_checkpoint", lambda d: (d / "ckpts").is_dir())
    p = _write(tmp_path)
    fail["train"] = Killed
    with pytest.raises(Killed):
        pl.run(p, tmp_path / "out")
    assert not (tmp_path / "out" / "train" / "manifest.json").exists()
    fail["train"] = None
    seen.clear()
    pl.run(p, tmp_path / "out")
    assert seen[:2] == [("train", True), ("evaluate", False)]
    assert not (tmp_path / "out" / ".previous" / "train").exists()  # nothing moved aside
    # another setting since: it trains anew (the killed one's checkpoints are not this run's)
    fail["train"] = Killed
    with pytest.raises(Killed):
        pl.run(p, tmp_path / "out", overrides=["train.iterations=7"])
    fail["train"] = None
    seen.clear()
    pl.run(p, tmp_path / "out")
    assert seen[0] == ("train", False)
    # a failure the stage reported (a full disk): resumed too
    fail["train"] = lambda: UserError("the disk is full")
    with pytest.raises(pl.StageError):
        pl.run(p, tmp_path / "out", overrides=["train.iterations=9"])
    fail["train"] = None
    seen.clear()
    pl.run(p, tmp_path / "out", overrides=["train.iterations=9"])
    assert seen[0] == ("train", True)


def test_add_views_names_holding_commas_and_spaces(tmp_path):
    """``--add-views`` split every value at commas, so a photo named ``IMG 4045, final.jpg`` could never be added,
    and the Next line printed such names unquoted. A value that is a photo's name is kept whole, and the Next line
    quotes one flag per name where a shell or the split would cut it."""
    import shlex

    from uncertsplat.console import add_views_args
    from uncertsplat.train.session import _split_names

    (tmp_path / "images").mkdir()
    (tmp_path / "images" / "IMG 4045, final é.jpg").write_bytes(b"")
    assert _split_names(["a.png,b.png", " c.png "], tmp_path) == ["a.png", "b.png", "c.png"]
    assert _split_names(["IMG 4045, final é.jpg"], tmp_path) == ["IMG 4045, final é.jpg"]
    assert _split_names(["IMG 4045, final é.jpg"], None) == ["IMG 4045", "final é.jpg"]
    assert add_views_args(["a.png", "b.png"]) == "--add-views a.png,b.png"
    args = shlex.split(add_views_args(["IMG 4045, final é.jpg", "b.png"]))
    assert args == ["--add-views", "IMG 4045, final é.jpg", "--add-views", "b.png"]


def test_a_stage_s_advice_is_given_in_the_pipeline_s_words(tmp_path, monkeypatch, capsys):
    """Notes printed during `uncertsplat run` gave the single command's form (`--set exposure=affine`, `--features
    dsp-sift`), which a pipeline refuses: they name the stage's keys (`--set train.exposure=affine`), as its errors
    already did; text that speaks of pipelines itself is left alone."""
    from uncertsplat.config import TrainConfig
    from uncertsplat.console import console

    fields = TrainConfig.model_fields
    assert pl.pipeline_advice("train", fields, "--set exposure=affine learns a gain") == \
        "--set train.exposure=affine learns a gain"
    assert pl.pipeline_advice("t2", fields, "give --set 'scene.downscale=1' or --iterations N") == \
        "give --set 't2.scene.downscale=1' or --iterations N (in this pipeline: --set t2.iterations)"
    assert pl.pipeline_advice("train", fields, "--set nothing_of_its=1 --resume") == "--set nothing_of_its=1 --resume"
    kept = "train with --set scene.calibration_holdout=3 (in a pipeline: --set train.scene.calibration_holdout=3)"
    assert pl.pipeline_advice("train", fields, kept) == kept
    others = {"train": ("fit", fields)}  # (another stage's advice about the training: whole command lines left alone)
    whole = "run `uncertsplat train S -o R --method fisher --resume`, or uncertsplat train --set seed=2"
    assert pl.pipeline_advice("evaluate", {}, whole, others=others) == whole

    def fake(kind, cfg, up_path, out_dir, device, kwargs):
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "out.txt").write_text("x")
        if kind == "train":
            console.print("[yellow]warning:[/] photos of other exposures: --set exposure=affine learns a gain")
        if kind == "evaluate":  # advice about the training that made the run (a review saw both in a pipeline)
            console.print("[yellow]note:[/] `train --set random_background=true` covers them; give it --iterations "
                          "222 or more for a posterior; --set num_samples=20")
            raise UserError("the run is too short: give it --iterations 300")  # (an error's advice alike)

    monkeypatch.setattr(pl, "_run_stage", fake)
    capsys.readouterr()
    with pytest.raises(UserError, match=r"give it --iterations 300 \(in this pipeline: --set train.iterations\)"):
        pl.run(_write(tmp_path), tmp_path / "out")
    said = " ".join(capsys.readouterr().err.split())
    assert "--set train.exposure=affine learns a gain" in said, said
    assert ("`--set train.random_background=true` covers them; give it --iterations 222 or more for a posterior; "
            "--set evaluate.num_samples=20 (in this pipeline: --set train.iterations)") in said, said
    assert console.rewrite is None  # off once the stage ends


def test_the_photos_pipeline_without_photos_is_named_as_typed(tmp_path):
    """`run photos -o OUT` without --set photos: the placeholder folder beside the installed pipeline was named,
    and the hint gave the package's path to the file instead of `run photos`."""
    from uncertsplat.config import shipped_file

    with pytest.raises(UserError) as err:
        pl.run(shipped_file("photos", "pipeline"), tmp_path / "out")
    text = err.value.render()
    assert "which names a folder beside the pipeline file until --set photos gives yours" in text
    assert f"uncertsplat run photos -o {tmp_path / 'out'} --set photos=" in " ".join(text.split())
    with pytest.raises(UserError) as err:
        pl.run(shipped_file("photos", "pipeline"), tmp_path / "out", overrides=[f"photos={tmp_path / 'none'}"])
    assert "photo folder not found (the pipeline's `photos`)" in err.value.render()
    assert not (tmp_path / "out").exists()


def test_an_evaluate_stage_with_the_synth_stages_depth_is_skipped_whichever_way_o_is_written(tmp_path, calls,
                                                                                             monkeypatch):
    """SfM on a synthetic scene's photos: the evaluate stage takes the synth stage's GT depth, whose path was keyed as
    -o was typed, so an absolute `-o` after a relative one evaluated again (a helper's review)."""
    p = tmp_path / "chain.toml"
    p.write_text('name = "chain"\n[[stages]]\nstage = "synth"\nconfig = { preset = "tiny" }\n'
                 '[[stages]]\nstage = "reconstruct"\n[[stages]]\nstage = "train"\npreset = "tiny"\n'
                 '[[stages]]\nstage = "evaluate"\n')
    monkeypatch.chdir(tmp_path)
    pl.run(p, Path("out"))
    ran = len(calls)
    assert [k for k, _ in calls] == ["synth", "reconstruct", "train", "evaluate"]
    pl.run(p, Path("./out"))
    pl.run(p, tmp_path / "out")
    assert len(calls) == ran  # every stage skipped
    # the project moved elsewhere: its GT depth is keyed by the synth stage it comes from, not where it lies (the
    # evaluate stage ran again); the stage still runs with the depth where it now is
    monkeypatch.chdir(tmp_path.parent)
    (tmp_path / "moved").mkdir()
    for f in ("chain.toml", "out"):
        (tmp_path / f).rename(tmp_path / "moved" / f)
    pl.run(tmp_path / "moved" / "chain.toml", tmp_path / "moved" / "out")
    assert len(calls) == ran
    m = json.loads((tmp_path / "moved" / "out" / "train" / "eval" / "manifest.json").read_text(encoding="utf-8"))
    assert m["config"]["depth_gt"] == str((tmp_path / "out" / "synth" / "depth").resolve())  # as it ran
    pl.run(tmp_path / "moved" / "chain.toml", tmp_path / "moved" / "out", overrides=["evaluate.num_samples=3"])
    (last, where) = calls[-1]
    assert last == "evaluate" and len(calls) == ran + 1
    m = json.loads((where / "manifest.json").read_text(encoding="utf-8"))
    assert m["config"]["depth_gt"] == str((tmp_path / "moved" / "out" / "synth" / "depth").resolve())
    # a manifest keyed as before (by the path as run) is taken where the project has not moved
    from uncertsplat.stages.manifest import hash_config

    m["config_hash"] = hash_config(m["config"])
    (where / "manifest.json").write_text(json.dumps(m))
    pl.run(tmp_path / "moved" / "chain.toml", tmp_path / "moved" / "out", overrides=["evaluate.num_samples=3"])
    assert len(calls) == ran + 1


def test_a_copy_of_an_output_folder_with_an_unfinished_training_runs_it_again(tmp_path, monkeypatch, capsys):
    """`cp -a OUT OUT2` with a training stopped in OUT: the pipeline on OUT2 resumed the run, which train refused
    every time (trained on OUT's scene, which is still there), so OUT2 could never finish (a helper's review). The
    copy's stage runs again; OUT itself, and a moved OUT, resume."""
    import shutil

    from uncertsplat.errors import Interrupted

    resumed: list[bool] = []
    monkeypatch.setattr(pl, "_run_stage", _stopped_once(resumed, write_scene=True))
    p = _write(tmp_path)
    with pytest.raises(Interrupted):
        pl.run(p, tmp_path / "out")
    shutil.copytree(tmp_path / "out", tmp_path / "copy")
    capsys.readouterr()
    pl.run(p, tmp_path / "copy")
    said = " ".join(capsys.readouterr().err.split())
    assert resumed == [False, False] and "which is still there (a copy of another output folder?)" in said
    shutil.move(tmp_path / "out", tmp_path / "moved")  # the old scene gone with it: resumed beside the run
    pl.run(p, tmp_path / "moved")
    assert resumed == [False, False, True]


def test_an_evaluate_stage_of_a_run_outside_out_is_skipped_when_unchanged(tmp_path, calls, capsys):
    """Its evaluation is written into the run, which is the stage's input: the input changed with every call and the
    stage was never skipped. The run's own files still are its input (a model trained on: evaluated again)."""
    run = tmp_path / "myrun"
    run.mkdir()
    (run / "config.json").write_text("{}")
    (run / "variational.ply").write_text("model")
    p = tmp_path / "p.toml"
    p.write_text('[[stages]]\nstage = "evaluate"\ninput = "myrun"\n')
    pl.run(p, tmp_path / "out")
    assert calls == [("evaluate", run / "eval")] and (run / "eval" / "out.txt").is_file()
    capsys.readouterr()
    pl.run(p, tmp_path / "out")
    assert len(calls) == 1 and "skip evaluate: unchanged" in " ".join(capsys.readouterr().err.split())
    (run / "variational.ply").write_text("trained on")
    pl.run(p, tmp_path / "out")
    assert len(calls) == 2
    # a second stage of the training views' evaluation, or one made by hand: neither is an input of the other
    p.write_text('[[stages]]\nstage = "evaluate"\ninput = "myrun"\n[[stages]]\nstage = "evaluate"\nname = "evtrain"\n'
                 'input = "myrun"\nconfig = { split = "train" }\n')
    pl.run(p, tmp_path / "out")
    assert [k for k, _ in calls[2:]] == ["evaluate"] and calls[-1][1] == run / "eval-train"
    for _ in range(2):
        pl.run(p, tmp_path / "out")
    assert len(calls) == 3


def test_a_stage_out_of_memory_is_told_the_keys_that_lower_its_use(tmp_path, monkeypatch):
    """A stage whose memory ran out failed "with an internal error" and its allocator's message."""
    def fake(kind, cfg, up_path, out_dir, device, kwargs):
        out_dir.mkdir(parents=True, exist_ok=True)
        if kind == "train":
            raise RuntimeError("DefaultCPUAllocator: can't allocate memory: you tried to allocate 108000000 bytes")

    monkeypatch.setattr(pl, "_run_stage", fake)
    with pytest.raises(StageError) as info:
        pl.run(_write(tmp_path), tmp_path / "out")
    text = " ".join(str(info.value).split())
    assert text.startswith("stage 'train' (train) failed: train ran out of the machine's memory")
    assert "--set train.scene.downscale=2" in text and "internal error" not in text


def test_a_report_without_an_evaluate_stage_is_made_again_after_an_evaluation_by_hand(tmp_path, calls):
    # the report shows RUN/eval whoever wrote it: an `uncertsplat evaluate RUN` by hand, made, changed or deleted
    # after the pipeline ran, makes its report again; an evaluate stage's own output keys the report as before
    p = tmp_path / "p.toml"
    p.write_text(PIPE.replace('[[stages]]\nstage = "evaluate"\n', ""))
    out = tmp_path / "out"
    pl.run(p, out)
    calls.clear()
    pl.run(p, out)
    assert calls == []
    metrics = out / "train" / "eval" / "metrics.json"
    metrics.parent.mkdir()
    metrics.write_text('{"psnr": 20.0}')
    pl.run(p, out)
    assert [k for k, _ in calls] == ["report"]
    calls.clear()
    pl.run(p, out)
    assert calls == []
    metrics.write_text('{"psnr": 21.0}')  # evaluated again, other numbers
    (out / "train" / "eval-train").mkdir()
    (out / "train" / "eval-train" / "metrics.json").write_text('{"psnr": 25.0}')
    pl.run(p, out)
    assert [k for k, _ in calls] == ["report"]
    calls.clear()
    shutil.rmtree(metrics.parent)
    pl.run(p, out)
    assert [k for k, _ in calls] == ["report"]
    # with an evaluate stage, its evaluation is the stage's: written again by it, the report is not run twice
    calls.clear()
    p.write_text(PIPE)
    pl.run(p, out)
    assert [k for k, _ in calls] == ["evaluate", "report"]
    calls.clear()
    pl.run(p, out)
    assert calls == []


def test_a_stage_folder_gone_and_the_stages_after_it_say_why_they_run_again(tmp_path, calls, capsys):
    """A project copied without its scene folder (out/synth): synth was made again and train ran again, its
    finished model moved to .previous, with no word of why; each says it."""
    import shutil

    p = _write(tmp_path)
    pl.run(p, tmp_path / "out")
    shutil.rmtree(tmp_path / "out" / "synth")
    calls.clear()
    capsys.readouterr()
    pl.run(p, tmp_path / "out")
    said = " ".join(capsys.readouterr().err.split())
    assert [k for k, _ in calls] == ["synth", "train", "evaluate", "report"]
    assert f"{tmp_path / 'out' / 'synth'}, where 'synth' wrote its output before, is gone: it runs again" in said, said
    assert "'train' runs again: its input 'synth' ran again" in said, said
    assert "'report' runs again: its inputs 'evaluate', 'train' ran again" in said, said
    # a config changed is said as well, naming the stage
    capsys.readouterr()
    pl.run(p, tmp_path / "out", overrides=["train.iterations=7"])
    said = " ".join(capsys.readouterr().err.split())
    assert "'train' runs again: its settings changed since its last run" in said, said
    assert "'evaluate' runs again: its input 'train' ran again" in said, said


def test_why_again_names_each_reason_and_stays_quiet_otherwise(tmp_path):
    """``_why_again`` by itself: a stage never started here, an unfinished one and an unchanged one say nothing; an
    input gone from the stage's inputs is a change; inputs that ran again and inputs that changed are both named."""
    from uncertsplat.schemas.runs import Manifest

    def manifest(status="done", **hashes):
        return Manifest(stage="train", name="t", config_hash="c", input_hashes=hashes, config={}, status=status,
                        started_at=0.0)

    gone = tmp_path / "gone"
    new = manifest(a="1")
    # never started here: quiet, whether its input ran again or its folder is missing
    assert pl._why_again("t", gone, None, new, True, "up", {"up"}, set()) is None
    assert pl._why_again("t", gone, None, new, True, None, set(), set()) is None
    assert "'t' runs again: its input 'up' ran again" == pl._why_again("t", tmp_path, None, new, True, "up", {"up"},
                                                                       {"t"})
    # unfinished (failed or running): it resumes or starts over, unsaid
    for status in ("failed", "running"):
        assert pl._why_again("t", tmp_path, manifest(status, a="0"), new, True, None, set(), {"t"}) is None
    # finished, same settings and inputs: a skip
    assert pl._why_again("t", tmp_path, manifest(a="1"), new, True, None, set(), {"t"}) is None
    # an input no longer given is a change
    assert pl._why_again("t", tmp_path, manifest(a="1", b="2"), new, True, None, set(), {"t"}) == \
        "'t' runs again: its input 'b' changed"
    # one ran again, another changed: both said
    both = pl._why_again("t", tmp_path, manifest(a="0", b="0"), manifest(a="1", b="2"), True, None, {"a"}, {"t"})
    assert both == "'t' runs again: its input 'a' ran again; its input 'b' changed", both
