"""`uncertsplat sweep` with scenes and seeds as axes, end to end on tiny scenes (issue 22)."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from tests.fixtures import tiny_scene
from uncertsplat.cli import app
from uncertsplat.schemas import SweepSummary
from uncertsplat.stages import sweep


@pytest.fixture(scope="session")
def scene_path(tmp_path_factory):
    return tiny_scene(tmp_path_factory.getbasetemp() / "shared_scenes")


def spec_text(scene_path) -> str:
    return f"""
name = "scenes-and-seeds"
seeds = [0, 1]
train_preset = "tiny"
train = {{ eval_every = 1000, checkpoint_every = 1000, log_every = 10 }}
evaluate = {{ max_views = 1 }}
[scenes.given]
path = "{scene_path}"
[scenes.generated]
synth = {{ preset = "tiny", seed = 1, num_views = 12 }}
train = {{ scene = {{ max_points = 500 }} }}  # a scene's own train key (the downscale knob would replace downscale)
[default]
method = "variational"
iterations = 12
num_entries = 4
num_samples = 3
downscale = 4.0
[axes]
num_samples = [1]
"""


def test_one_spec_runs_every_point_on_every_scene_and_seed(scene_path, tmp_path):
    spec = tmp_path / "spec.toml"
    spec.write_text(spec_text(scene_path))
    out = tmp_path / "out"
    res = CliRunner().invoke(app, ["sweep", str(spec), "-o", str(out), "--jobs", "1", "--device", "cpu"])
    assert res.exit_code == 0, res.output
    recs = [json.loads(line) for line in (out / "sweep.jsonl").read_text(encoding="utf-8").splitlines()]
    assert len(recs) == 8 and all(r["status"] == "ok" for r in recs)  # 2 points x 2 scenes x 2 seeds
    assert {(r["scene"], r["seed"]) for r in recs} == {(s, k) for s in ("given", "generated") for k in (0, 1)}
    assert len({r["run_dir"] for r in recs}) == 4  # K shares a training run; scenes and seeds do not
    assert all(f"/runs/{r['scene']}/" in r["run_dir"] for r in recs)
    assert (out / "scenes" / "generated" / "images").is_dir()  # the synth scene is generated under OUT
    assert not (out / "scenes" / "given").exists()  # a path scene is used where it is
    by_id = {r["id"]: r for r in recs}
    # seeds differ: the two trainings of a point are not the same run
    assert by_id["given.variational_it12_kt4_k3_ds4_seed0"]["psnr"] != by_id["given.variational_it12_kt4_k3_ds4_seed1"]["psnr"]
    for r in recs:
        assert (out / "points" / f"{r['id']}.json").is_file()
    summary = SweepSummary.read(out / "sweep.json")
    table = {g.id: g for g in summary.table}
    assert set(table) == {"given.variational_it12_kt4_k3_ds4", "given.variational_it12_kt4_k1_ds4",
                          "generated.variational_it12_kt4_k3_ds4", "generated.variational_it12_kt4_k1_ds4"}
    g = table["given.variational_it12_kt4_k3_ds4"]
    pair = [by_id[f"{g.id}_seed{k}"]["psnr"] for k in (0, 1)]
    assert g.seeds == [0, 1] and g.mean["psnr"] == pytest.approx(sum(pair) / 2)
    assert g.spread["psnr"] == pytest.approx(abs(pair[0] - pair[1]) / 2 ** 0.5)
    assert set(summary.pareto) == {f"{s}: {y}_vs_time" for s in ("given", "generated") for y in ("ause_mae", "nll")}
    for key, ids in summary.pareto.items():
        assert ids and all(i.startswith(key.split(":")[0] + ".") for i in ids)  # a front never mixes scenes
    page = (out / "index.html").read_text(encoding="utf-8")
    assert 'id="sweep-table"' in page and f'data-group="{g.id}"' in page
    assert (out / "pareto.png").read_bytes()[:4] == b"\x89PNG"

    again = sweep.run(spec, out, jobs=1, device="cpu")  # everything done: nothing runs again
    assert len((out / "sweep.jsonl").read_text(encoding="utf-8").splitlines()) == 8 and again.num_points == 8
    # one scene again (--scenes): the summary still covers both (it held only the scene run before)
    one = sweep.run(spec, out, jobs=1, device="cpu", only_scenes=["given"])
    assert one.num_points == 8 and {g.id for g in one.table} == set(table)
    assert SweepSummary.read(out / "sweep.json").num_points == 8


def test_a_photos_scene_is_reconstructed_once_before_the_jobs(tmp_path, monkeypatch):
    from uncertsplat.stages import reconstruct
    from uncertsplat.sweep.spec import SweepScene

    calls = []
    monkeypatch.setattr(reconstruct, "run", lambda photos, ws, cfg: calls.append((photos, ws, cfg)))
    (tmp_path / "photos").mkdir()
    entry = SweepScene(photos=tmp_path / "photos", reconstruct={"matcher": "exhaustive"})
    folder = sweep.prepare_scene("mine", entry, tmp_path / "out")
    assert folder == tmp_path / "out" / "scenes" / "mine"
    ((photos, ws, cfg),) = calls
    assert photos == tmp_path / "photos" and ws == folder and cfg.matcher == "exhaustive"


def test_a_job_writes_only_into_its_run_folder_and_returns_its_report(scene_path, tmp_path):
    """Workers that share no disk with the driver: the point's report comes back in the record."""
    from uncertsplat.schemas import EvalReport
    from uncertsplat.sweep.jobs import run_job
    from uncertsplat.sweep.spec import SweepSpec, make_jobs

    spec = SweepSpec(train_preset="tiny", train={"eval_every": 1000, "checkpoint_every": 1000},
                     evaluate={"max_views": 1}, default={"iterations": 8, "downscale": 4.0, "num_samples": 2})
    (job,) = make_jobs(spec, tmp_path / "out", scene_path, "cpu")
    (rec,) = run_job(job)
    assert rec["status"] == "ok", rec.get("error")
    report = EvalReport.model_validate_json(rec["point_report"])
    assert report.mean.psnr == rec["psnr"]
    written = {p.relative_to(tmp_path / "out").parts[:2] for p in (tmp_path / "out").rglob("*") if p.is_file()}
    assert written == {("runs", job["job_id"])}  # nothing outside the job's run folder
