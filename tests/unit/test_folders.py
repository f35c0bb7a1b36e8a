"""Errors for a pipeline's output folder given where a run or a scene was expected name the folder to give."""

from __future__ import annotations

import pytest

from uncertsplat.baselines.runs import read_run_config
from uncertsplat.errors import UserError
from uncertsplat.io.folders import is_run, is_scene, stage_hint
from uncertsplat.sfm.scene import find_sparse_model


@pytest.fixture
def pipeline_out(tmp_path):
    """The folders `uncertsplat run -o OUT` leaves (their content reduced to what tells them apart)."""
    out = tmp_path / "out"
    (out / "reconstruct" / "sparse" / "0").mkdir(parents=True)
    (out / "reconstruct" / "images").mkdir()
    for run in ("train", "prune"):
        (out / run).mkdir()
        (out / run / "config.json").write_text("{}")
    (out / "train" / "train_summary.json").write_text("{}")
    (out / "prune" / "prune.json").write_text("{}")
    (out / "report").mkdir()
    (out / "report" / "index.html").write_text("<html></html>")
    (out / "notes").mkdir()
    (out / "notes" / "config.json").write_text("{}")  # (a config alone is no run)
    return out


def test_runs_and_scenes_are_told_apart(pipeline_out):
    assert [is_run(pipeline_out / n) for n in ("train", "prune", "notes", "reconstruct")] == [True, True, False, False]
    assert [is_scene(pipeline_out / n) for n in ("reconstruct", "train", "report")] == [True, False, False]


def test_the_hint_names_the_stage_folders_inside_or_beside(pipeline_out, tmp_path):
    assert stage_hint(pipeline_out, "run") == (f"it holds runs (a pipeline's output): give one of them: "
                                               f"{pipeline_out / 'prune'}, {pipeline_out / 'train'}")
    assert stage_hint(pipeline_out / "report", "run").startswith("beside it are runs")
    assert stage_hint(pipeline_out, "scene").endswith(f"give one of them: {pipeline_out / 'reconstruct'}")
    (tmp_path / "empty").mkdir()
    assert stage_hint(tmp_path / "empty", "run") == "" and stage_hint(tmp_path / "missing", "scene") == ""


def test_commands_given_a_pipelines_output_name_what_to_give(pipeline_out):
    """`evaluate OUT`, `select-views OUT/report` and `train OUT` said only what OUT is not."""
    with pytest.raises(UserError, match=r"not a training run .*it holds runs .*give one of them: .*prune, .*train"):
        read_run_config(pipeline_out)
    with pytest.raises(UserError, match=r"beside it are runs"):
        read_run_config(pipeline_out / "report")
    with pytest.raises(UserError, match=r"not a COLMAP workspace; it holds scenes .*reconstruct"):
        find_sparse_model(pipeline_out)
