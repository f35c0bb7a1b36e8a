"""`uncertsplat sweep` end to end on the tiny scene: one record per point, summary, figure, resume."""

from __future__ import annotations

import json
import math

import pytest
from typer.testing import CliRunner

from tests.fixtures import tiny_scene, tiny_sweep_spec
from uncertsplat.cli import app
from uncertsplat.schemas import SweepSummary
from uncertsplat.stages import sweep
from uncertsplat.stages.sweep import read_records

SPEC = tiny_sweep_spec("tiny-sweep", """num_samples = [1, 3]
method = ["variational", "fisher"]""")


@pytest.fixture(scope="session")
def scene_path(tmp_path_factory):
    return tiny_scene(tmp_path_factory.getbasetemp() / "shared_scenes")


def read_jsonl(path):
    return [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines()]


def test_sweep_writes_one_record_per_point_and_resumes(scene_path, tmp_path):
    spec = tmp_path / "spec.toml"
    spec.write_text(SPEC)
    out = tmp_path / "out"
    res = CliRunner().invoke(app, ["sweep", str(spec), "-o", str(out), "--scene", str(scene_path), "--jobs", "1",
                                   "--device", "cpu"])
    assert res.exit_code == 0, res.output
    recs = read_jsonl(out / "sweep.jsonl")
    # default (K=3), K=1, fisher: three points, two trainings (the K points share one run)
    assert sorted(r["id"] for r in recs) == sorted(["variational_it16_kt4_k3_ds4", "variational_it16_kt4_k1_ds4",
                                                     "fisher_it16_kt4_k3_ds4"])
    assert all(r["status"] == "ok" for r in recs)
    assert len({r["run_dir"] for r in recs}) == 2
    for r in recs:
        for key in ("train_seconds", "eval_seconds_per_view", "peak_memory_mb", "psnr", "ause_mae",
                    "calibration_error", "time"):
            assert isinstance(r[key], float) and r[key] >= 0, (r["id"], key)
        assert isinstance(r["nll"], float) and math.isfinite(r["nll"])  # a density: may be negative
        assert r["time"] == pytest.approx(r["train_seconds"] + r["calibration_seconds"] + r["eval_seconds"])
    by_id = {r["id"]: r for r in recs}
    assert by_id["variational_it16_kt4_k3_ds4"]["is_default"]
    assert by_id["variational_it16_kt4_k1_ds4"]["num_samples"] == 1
    assert any("K=1" in n for n in by_id["variational_it16_kt4_k1_ds4"]["notes"])
    summary = SweepSummary.read(out / "sweep.json")
    assert [r.model_dump() for r in summary.records] == [r.model_dump() for r in read_records(out / "sweep.jsonl")]
    assert summary.num_points == 3 and summary.default == "variational_it16_kt4_k3_ds4"
    assert set(summary.pareto) == {"ause_mae_vs_time", "nll_vs_time"}
    assert all(summary.pareto["ause_mae_vs_time"])
    assert (out / "pareto.png").read_bytes()[:4] == b"\x89PNG"
    assert (out / "points" / "fisher_it16_kt4_k3_ds4.json").is_file()
    # the page shows the figure and one row per point, with the numbers of sweep.json
    page = (out / "index.html").read_text(encoding="utf-8")
    assert 'src="pareto.png"' in page
    for r in summary.records:
        assert f'data-point="{r.id}"' in page
        assert f'data-key="ause_mae" data-value="{r.ause_mae!r}"' in page

    # a second run finds every point done: nothing is trained or evaluated again
    summary2 = sweep.run(spec, out, jobs=1, device="cpu", scene=scene_path)
    assert len(read_jsonl(out / "sweep.jsonl")) == 3 and summary2.num_points == 3
    # points measured under other conditions (another thread count: an earlier --jobs 2) are reused with a note
    lines = (out / "sweep.jsonl").read_text(encoding="utf-8").splitlines()
    first = json.loads(lines[0])
    (out / "sweep.jsonl").write_text("\n".join([json.dumps({**first, "threads": 7}), *lines[1:]]) + "\n",
                                     encoding="utf-8")
    from uncertsplat.console import console

    with console.capture() as captured:
        sweep.run(spec, out, jobs=1, device="cpu", scene=scene_path)
    said = " ".join(captured.get().split())
    assert "the points were measured under 2 conditions (cpu," in said and "7 threads" in said, said


@pytest.mark.slow
def test_sweep_process_pool_runs_jobs_in_fresh_processes(scene_path, tmp_path):
    spec = tmp_path / "spec.toml"
    spec.write_text(SPEC.replace("num_samples = [1, 3]", "num_samples = [3]"))
    summary = sweep.run(spec, tmp_path / "out", jobs=2, device="cpu", scene=scene_path)
    recs = summary.records
    assert summary.num_points == 2 and all(r.status == "ok" for r in recs)
    assert all(r.threads == 1 for r in recs)  # jobs sharing the cores use one torch thread each
    assert len(read_jsonl(tmp_path / "out" / "sweep.jsonl")) == 2
