"""Errors for a folder given where a run or a scene was expected name the folder to give (a pipeline's output, its
report/, a folder inside a run, a sweep's output)."""

from __future__ import annotations

from pathlib import Path

import pytest

from uncertsplat.baselines.runs import read_run_config
from uncertsplat.errors import UserError
from uncertsplat.io.folders import PIPELINE_STARTED, is_run, is_scene, stage_hint
from uncertsplat.sfm.scene import find_sparse_model
from uncertsplat.stages.pipeline import STARTED


def _run(folder: Path, marker: str = "train_summary.json") -> Path:
    folder.mkdir(parents=True)
    (folder / "config.json").write_text("{}")
    (folder / marker).write_text("{}")
    return folder


@pytest.fixture
def pipeline_out(tmp_path):
    """The folders `uncertsplat run -o OUT` leaves (their content reduced to what tells them apart)."""
    out = tmp_path / "out"
    (out / "reconstruct" / "sparse" / "0").mkdir(parents=True)
    (out / "reconstruct" / "images").mkdir()
    _run(out / "train")
    _run(out / "prune", "prune.json")
    (out / "report").mkdir()
    (out / "report" / "index.html").write_text("<html></html>")
    (out / "notes").mkdir()
    (out / "notes" / "config.json").write_text("{}")  # (a config alone is no run)
    (out / PIPELINE_STARTED).write_text("{}")
    return out


def test_runs_and_scenes_are_told_apart(pipeline_out):
    assert STARTED == PIPELINE_STARTED
    assert [is_run(pipeline_out / n) for n in ("train", "prune", "notes", "reconstruct")] == [True, True, False, False]
    assert [is_scene(pipeline_out / n) for n in ("reconstruct", "train", "report")] == [True, False, False]


def test_the_hint_names_what_to_give(pipeline_out, tmp_path, monkeypatch):
    assert stage_hint(pipeline_out, "run") == (f"it holds runs (a pipeline's output): give one of them: "
                                               f"{pipeline_out / 'prune'}, {pipeline_out / 'train'}")
    assert stage_hint(pipeline_out / "report", "run").startswith("it is a stage folder of a pipeline's output, whose "
                                                                 "runs are")
    assert stage_hint(pipeline_out, "scene").endswith(f"give one of them: {pipeline_out / 'reconstruct'}")
    # inside a run (RUN/eval, an ensemble's members/): the run
    (pipeline_out / "train" / "eval").mkdir()
    assert stage_hint(pipeline_out / "train" / "eval", "run") == f"it lies inside the run {pipeline_out / 'train'}: " \
                                                                 "give that"
    # runs trained by hand side by side: named, but not as a pipeline's, and a folder beside them is not one of them
    _run(tmp_path / "exp" / "a")
    (tmp_path / "exp" / "junk").mkdir()
    assert stage_hint(tmp_path / "exp", "run") == f"it holds runs: give one of them: {tmp_path / 'exp' / 'a'}"
    assert stage_hint(tmp_path / "exp" / "junk", "run") == ""
    # a sweep's output: its runs/
    _run(tmp_path / "sweep" / "runs" / "p0")
    assert stage_hint(tmp_path / "sweep", "run").endswith(str(tmp_path / "sweep" / "runs" / "p0"))
    (tmp_path / "empty").mkdir()
    assert stage_hint(tmp_path / "empty", "run") == "" and stage_hint(tmp_path / "missing", "scene") == ""
    # from inside the report folder, `.`: the pipeline's runs, as the working folder sees them
    monkeypatch.chdir(pipeline_out / "report")
    assert stage_hint(Path("."), "run").endswith("runs are: ../prune, ../train")


def test_a_folder_that_cannot_be_read_is_passed_over(pipeline_out, monkeypatch):
    """A `lost+found` (mode 0700) beside the folder raised PermissionError from the hint, which the command then
    reported as the error."""
    unreadable = pipeline_out / "lost+found"
    unreadable.mkdir()
    is_file = Path.is_file

    def refused(self):
        if unreadable in (self, *self.parents):
            raise PermissionError(13, "Permission denied", str(self))
        return is_file(self)

    monkeypatch.setattr(Path, "is_file", refused)
    assert stage_hint(pipeline_out, "run").endswith(f"{pipeline_out / 'prune'}, {pipeline_out / 'train'}")


def test_commands_given_a_pipelines_output_name_what_to_give(pipeline_out):
    """`evaluate OUT`, `select-views OUT/report` and `train OUT` said only what OUT is not (and train, to run
    reconstruct)."""
    with pytest.raises(UserError, match=r"not a training run .*it holds runs .*give one of them: .*prune, .*train"):
        read_run_config(pipeline_out)
    with pytest.raises(UserError, match=r"a stage folder of a pipeline's output, whose runs are"):
        read_run_config(pipeline_out / "report")
    with pytest.raises(UserError, match=r"not a training run .*; this is a scene, the input of `uncertsplat train`"):
        read_run_config(pipeline_out / "reconstruct")  # (evaluate SCENE, prune SCENE: as report says it)
    with pytest.raises(UserError, match=r"not a COLMAP workspace; it holds scenes .*reconstruct") as err:
        find_sparse_model(pipeline_out)
    # the message says which to give: no hint repeating it ("give one of them: ...", then "Give that scene instead.")
    assert err.value.hint is None and "uncertsplat reconstruct" not in err.value.render()


def test_a_folder_inside_a_scene_or_a_run_given_for_the_scene_names_the_scene(pipeline_out, tmp_path):
    """`train WS/images`, `train WS/sparse/0` or `train RUN` said "this folder is not a COLMAP workspace. Run
    `uncertsplat reconstruct PHOTOS -o WORKSPACE` to create one", advice that makes a second workspace of the one
    there: the scene the folder lies in, or the one the run was trained on, is named instead."""
    import json

    ws = pipeline_out / "reconstruct"
    (ws / "sparse" / "0" / "cameras.bin").write_bytes(b"")
    for inside in (ws / "images", ws / "sparse" / "0"):
        assert stage_hint(inside, "scene") == f"it lies inside the scene {ws}: give that"
        with pytest.raises(UserError) as err:
            find_sparse_model(inside)
        assert f"it lies inside the scene {ws}: give that" in err.value.render()
        assert "reconstruct PHOTOS" not in err.value.render()
    (pipeline_out / "train" / "scene.json").write_text(json.dumps({"scene": str(ws)}))
    assert stage_hint(pipeline_out / "train", "scene") == ("it is a training run, the output of `uncertsplat train`; "
                                                           f"the scene it was trained on is {ws}: give that")
    (pipeline_out / "train" / "scene.json").write_text(json.dumps({"scene": str(tmp_path / "gone")}))
    assert stage_hint(pipeline_out / "train", "scene") == "it is a training run, the output of `uncertsplat train`"
    (tmp_path / "photos").mkdir()  # a folder of photos in no scene: reconstruct is the advice still
    with pytest.raises(UserError, match="Run `uncertsplat reconstruct PHOTOS -o WORKSPACE`"):
        find_sparse_model(tmp_path / "photos")
