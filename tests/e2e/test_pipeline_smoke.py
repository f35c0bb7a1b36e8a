"""`uncertsplat run pipelines/smoke.toml` end to end on the CPU, then a re-run that skips every stage."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
from typer.testing import CliRunner

from tests.fixtures import tiny_scene_path  # noqa: F401
from tests.run_fixtures import tiny_run_path  # noqa: F401
from uncertsplat.cli import app

ROOT = Path(__file__).resolve().parents[2]
runner = CliRunner()


@pytest.fixture(scope="module")
def smoke_out(tmp_path_factory):
    out = tmp_path_factory.mktemp("smoke") / "out"
    result = runner.invoke(app, ["run", str(ROOT / "pipelines" / "smoke.toml"), "-o", str(out), "--device", "cpu"])
    assert result.exit_code == 0, result.output
    return out, result.output


def test_every_stage_wrote_its_outputs(smoke_out):
    out, _ = smoke_out
    for name in ("synth", "train", "prune", "report"):
        manifest = json.loads((out / name / "manifest.json").read_text(encoding="utf-8"))
        assert manifest["status"] == "done", name
    assert (out / "train" / "eval" / "metrics.json").is_file()
    assert (out / "train" / "point_cloud.ply").is_file() and (out / "train" / "variational.ply").is_file()
    assert (out / "prune" / "prune.json").is_file()


def test_the_pruned_runs_evaluation_is_prunes_own(smoke_out):
    """prune evaluated the run it wrote with the pipeline's settings; the evaluate stage after it keeps that."""
    out, output = smoke_out
    text = " ".join(output.split())
    assert "evaluate " + str(out / "prune") + ": already evaluated with these settings" in text
    assert not (out / ".previous" / "evaluate_pruned-eval").exists()
    manifest = json.loads((out / "prune" / "eval" / "manifest.json").read_text(encoding="utf-8"))
    assert manifest["status"] == "done"
    report = json.loads((out / "prune" / "eval" / "metrics.json").read_text(encoding="utf-8"))
    pruned = json.loads((out / "prune" / "prune.json").read_text(encoding="utf-8"))
    assert pruned["metrics"]["after"]["nll"] == report["mean"]["nll"]


def test_report_references_every_figure_and_matches_metrics(smoke_out):
    out, _ = smoke_out
    html = (out / "report" / "index.html").read_text(encoding="utf-8")
    srcs = re.findall(r'<img[^>]+src="([^"]+)"', html)
    assert srcs, "the report has figures"
    for src in srcs:
        assert (out / "report" / src).is_file(), src
    figures = {p.name for p in (out / "report" / "figures").iterdir()}
    assert figures == {Path(s).name for s in srcs if s.startswith("figures/")}
    metrics = json.loads((out / "train" / "eval" / "metrics.json").read_text(encoding="utf-8"))
    psnr = metrics["mean"]["psnr"]
    values = [float(v) for v in re.findall(r'data-key="psnr"[^>]*data-value="([^"]+)"', html)]
    assert any(v == pytest.approx(psnr, rel=1e-9) for v in values), "the report shows metrics.json's PSNR"


def test_report_prune_section_equals_prune_json(smoke_out):
    """The report built from the pipeline's real outputs shows prune.json's numbers and the keep-ratio figure."""
    from uncertsplat.report.extract import PRUNE_SPECS, format_value
    from uncertsplat.schemas import PruneReport

    out, _ = smoke_out
    rep = PruneReport.read(out / "prune" / "prune.json")
    assert rep.sweep is not None and len(rep.sweep.points) == 3
    html = (out / "report" / "index.html").read_text(encoding="utf-8")
    (table_id,) = re.findall(r'<table id="(prune-\d+)">', html)
    table = re.search(rf'<table id="{table_id}">(.*?)</table>', html, re.S).group(1)
    rows = dict(re.findall(r'<tr[^>]*data-row="([^"]*)">(.*?)</tr>', table, re.S))
    assert list(rows) == ["before", "after", "random removal"]
    for label, m in zip(rows, (rep.metrics.before, rep.metrics.after, rep.metrics.random), strict=True):
        cells = re.findall(r'<td data-key="([^"]*)" data-value="([^"]*)">([^<]*)</td>', rows[label])
        assert cells == [(s.key, str(getattr(m, s.key)), format_value(getattr(m, s.key), s)) for s in PRUNE_SPECS]
        assert all(text != "n/a" for key, _, text in cells if key != "depth_ause_mae"), (label, cells)
    sweep_table = re.search(rf'<table id="{table_id.replace("prune", "prune-sweep")}">(.*?)</table>', html, re.S)
    metric = rep.sweep.metric  # the PSNR the tolerance was checked on (the expected render's)
    assert metric == "psnr_render"
    for p in rep.sweep.points:
        for which in ("score", "random"):
            value = getattr(getattr(p, which), metric)
            assert value is not None
            assert f'data-key="{which}.{metric}" data-value="{value!r}"' in sweep_table.group(1)
    fig = re.search(r'<img src="(figures/prune_sweep_run\d+\.png)"', html)
    assert fig and (out / "report" / fig.group(1)).read_bytes()[:4] == b"\x89PNG"


def test_rerun_skips_unchanged_stages(smoke_out):
    import tomllib

    out, _ = smoke_out
    pipeline = ROOT / "pipelines" / "smoke.toml"
    stages = tomllib.loads(pipeline.read_text(encoding="utf-8"))["stages"]
    files = {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file() and "pipeline" not in p.name}
    result = runner.invoke(app, ["run", str(pipeline), "-o", str(out), "--device", "cpu"])
    assert result.exit_code == 0, result.output
    skipped = re.findall(r"^skip (\S+): unchanged since its last run", result.output, flags=re.M)
    assert len(skipped) == len(stages) == len(set(skipped)), result.output
    changed = [p for p, t in files.items() if not p.is_file() or p.stat().st_mtime_ns != t]
    assert not changed, changed


def test_stage_failure_is_reported_clearly(tmp_path):
    (tmp_path / "not_a_scene").mkdir()  # a folder, so the pipeline's check passes and the stage itself fails
    bad = tmp_path / "bad.toml"
    bad.write_text('name = "bad"\n[[stages]]\nstage = "train"\ninput = "not_a_scene"\npreset = "tiny"\n')
    result = runner.invoke(app, ["run", str(bad), "-o", str(tmp_path / "o"), "--device", "cpu"])
    assert result.exit_code == 2
    assert "stage 'train' (train) failed" in result.output and "Traceback" not in result.output


def test_an_output_folder_that_is_another_commands_output_is_refused(tiny_scene_path, tiny_run_path, tmp_path):
    """A pipeline writes one folder per stage into -o: into a training run or a scene they mixed with its files
    (and a scene's runs then saw their scene changed). Refused before anything is written; other folders are fine."""
    afile = tmp_path / "afile"
    afile.write_text("x")
    for out, what in ((tiny_run_path, "a training run"), (tiny_scene_path, "a scene"), (afile, "is a file")):
        before = sorted(p.name for p in out.iterdir()) if out.is_dir() else None
        result = runner.invoke(app, ["run", str(ROOT / "pipelines" / "smoke.toml"), "-o", str(out), "--device", "cpu"])
        assert result.exit_code == 2 and what in " ".join(result.output.split()), result.output
        assert (sorted(p.name for p in out.iterdir()) if out.is_dir() else None) == before
    # a folder of photos alone, or a pipeline's own output whose stage is named like a marker, is not refused
    from uncertsplat.stages import pipeline

    project = tmp_path / "project"
    (project / "images").mkdir(parents=True)
    pipeline._refuse_other_outputs(project)
    (project / "sparse").mkdir()
    (project / "sparse" / "manifest.json").write_text("{}")
    pipeline._refuse_other_outputs(project)
    (project / "sparse" / "manifest.json").unlink()  # (killed before its manifest: the pipeline's record says whose)
    (project / ".stages_started.json").write_text('{"sparse": null}')
    pipeline._refuse_other_outputs(project)
