"""Sweep spec expansion, point configs, job grouping and the Pareto front on hand-made points."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from uncertsplat.errors import UserError
from uncertsplat.sweep.pareto import pareto_front, plot_pareto, y_scale
from uncertsplat.sweep.spec import SweepSpec, expand_points, load_spec, make_jobs, point_configs, point_id

ROOT = Path(__file__).resolve().parents[2]


# ------------------------------------------------------------------------------------------ pareto
def ids(points):
    return [p["id"] for p in points]


def test_pareto_front_minimize_both():
    pts = [
        {"id": "a", "time": 1.0, "ause": 0.50},
        {"id": "b", "time": 2.0, "ause": 0.30},
        {"id": "c", "time": 3.0, "ause": 0.35},  # dominated by b
        {"id": "d", "time": 4.0, "ause": 0.10},
        {"id": "e", "time": 4.0, "ause": 0.20},  # same time as d, worse
        {"id": "f", "time": 0.5, "ause": 0.90},
        {"id": "g", "time": 5.0, "ause": 0.10},  # same ause as d, slower
    ]
    assert ids(pareto_front(pts)) == ["f", "a", "b", "d"]


def test_pareto_front_maximize_y_and_duplicates_and_missing():
    pts = [
        {"id": "a", "time": 1.0, "psnr": 20.0},
        {"id": "b", "time": 2.0, "psnr": 25.0},
        {"id": "b2", "time": 2.0, "psnr": 25.0},  # exact duplicate: neither dominates
        {"id": "c", "time": 3.0, "psnr": 24.0},
        {"id": "n", "time": None, "psnr": 40.0},
        {"id": "nan", "time": 1.0, "psnr": math.nan},
    ]
    assert ids(pareto_front(pts, x="time", y="psnr", minimize_both=False)) == ["a", "b", "b2"]
    assert ids(pareto_front(pts, x="time", y="psnr", minimize_both=True)) == ["a"]
    assert pareto_front([], x="time", y="ause") == []


def test_pareto_front_matches_brute_force():
    import random

    rnd = random.Random(0)
    pts = [{"id": str(i), "t": rnd.randint(0, 9), "y": rnd.randint(0, 9)} for i in range(60)]

    def dominated(p):
        return any(q["t"] <= p["t"] and q["y"] <= p["y"] and (q["t"] < p["t"] or q["y"] < p["y"]) for q in pts)

    assert sorted(ids(pareto_front(pts, x="t", y="y"))) == sorted(p["id"] for p in pts if not dominated(p))


def test_pareto_front_reads_attributes():
    class P:
        def __init__(self, time, ause):
            self.time, self.ause = time, ause

    a, b, c = P(1, 2), P(2, 1), P(3, 3)
    assert pareto_front([c, b, a]) == [a, b]


def test_plot_pareto_writes_a_png(tmp_path):
    recs = [{"id": f"p{i}", "method": m, "status": "ok", "time": t, "ause_mae": y, "nll": 1 + y,
             "is_default": i == 1} for i, (m, t, y) in enumerate([("variational", 1, 0.3), ("variational", 2, 0.2),
                                                                   ("fisher", 1.5, 0.5)])]
    recs.append({"id": "bad", "method": "x", "status": "failed"})
    out = plot_pareto(recs, tmp_path / "p.png")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize(("values", "expected"), [
    ([0.132, 0.139, 0.17, 0.29, 0.76], ("log", {})),  # AUSE with a K = 1 point: a factor 5.8
    ([0.132, 0.139, 0.17], ("linear", {})),  # close together
    ([-1.6, -1.3, -0.3, 11.8, 750.0], ("symlog", {"linthresh": 1.6})),  # NLL beside K = 1; t = median |value|
    ([-1.6, -1.3, -0.3, 2.2], ("linear", {})),  # NLL, no far point
    ([0.0, 0.0], ("linear", {})),
    ([], ("linear", {})),
])
def test_y_scale(values, expected):
    assert y_scale(values) == expected


# -------------------------------------------------------------------------------------------- spec
def spec(**kw) -> SweepSpec:
    base = {"train_preset": "tiny", "default": {"method": "variational", "iterations": 300, "num_entries": 10,
                                                  "num_samples": 10, "downscale": 1.0}}
    base.update(kw)
    return SweepSpec(**base)


def test_axes_design_varies_one_knob_at_a_time_without_duplicates():
    s = spec(axes={"num_entries": [1, 5, 10, 20], "num_samples": [1, 10], "method": ["variational", "fisher"]})
    pts = expand_points(s)
    assert pts[0] == s.default
    # default + 3 new K_table + 1 new K + 1 new method (the values equal to the default collapse)
    assert len(pts) == 6
    assert len({point_id(p) for p in pts}) == 6
    grid = expand_points(spec(design="grid", axes={"num_entries": [1, 5], "num_samples": [1, 10]}))
    assert len(grid) == 1 + 4


def test_point_configs_apply_knobs():
    s = spec()
    t, e = point_configs(s, s.default.model_copy(update={"method": "vi-single", "num_entries": 20}))
    assert t.variational.num_entries == 1  # the method wins over the knob
    t, e = point_configs(s, s.default.model_copy(update={"method": "ensemble", "ensemble_size": 3, "num_samples": 7}))
    assert t.method == "ensemble" and t.ensemble_size == 3 and e.num_samples == 3  # K = N for ensembles
    t, e = point_configs(s, s.default.model_copy(update={"iterations": 150, "downscale": 2.0, "num_samples": 5}))
    assert t.iterations == 150 and t.scene.downscale == 2.0 and e.num_samples == 5 and e.save_maps is False
    base, _ = point_configs(s, s.default)
    assert t.densify.until == round(base.densify.until / 2)  # scaled schedule ...
    assert t.densify.interval == base.densify.interval  # ... but not the densification interval
    fixed, _ = point_configs(spec(schedule="fixed"), s.default.model_copy(update={"iterations": 150}))
    assert fixed.densify.until == base.densify.until


def test_spawn_fraction_knob_sets_the_spawn_rule_and_only_matters_to_posteriors(tmp_path):
    s = spec(axes={"spawn_fraction": [0.01, 0.1], "method": ["variational", "fisher"]})
    t, _ = point_configs(s, s.default.model_copy(update={"spawn_fraction": 0.1}))
    assert t.densify.spawn_scale_fraction == 0.1 and point_id(s.default.model_copy(update={"spawn_fraction": 0.1})).endswith("sf0.1")
    d, _ = point_configs(s, s.default.model_copy(update={"method": "fisher", "spawn_fraction": 0.1}))
    f, _ = point_configs(s, s.default.model_copy(update={"method": "fisher"}))
    assert d == f  # plain 3DGS has no posteriors: the knob cannot change it
    jobs = make_jobs(spec(axes={"spawn_fraction": [0.05, 0.1]}), tmp_path, tmp_path / "scene", "cpu")
    assert len(jobs) == 3  # the default and two spawn fractions: three trainings


def test_jobs_group_points_that_share_training(tmp_path):
    s = spec(axes={"num_samples": [1, 5, 20], "num_entries": [5]})
    jobs = make_jobs(s, tmp_path, tmp_path / "scene", "cpu")
    sizes = sorted(len(j["points"]) for j in jobs)
    assert sizes == [1, 4]  # K only changes evaluation: one training for the 4 K points
    allp = [p for j in jobs for p in j["points"]]
    assert sum(p["is_default"] for p in allp) == 1
    assert len({p["hash"] for p in allp}) == len(allp)
    assert len({j["run_dir"] for j in jobs}) == len(jobs)
    import json

    json.dumps(jobs)  # jobs are plain data: any engine can ship them


def test_tradeoff_pipeline_file_is_valid():
    s = load_spec(ROOT / "pipelines" / "tradeoff.toml")
    pts = expand_points(s)
    assert any(p.method == "ensemble" for p in pts) and any(p.method == "fisher" for p in pts)
    assert {p.num_entries for p in pts} >= {1, 5, 10, 20} and {p.num_samples for p in pts} >= {1, 5, 10, 20}
    for p in pts:
        point_configs(s, p)


def test_bad_spec_names_the_key(tmp_path):
    f = tmp_path / "s.toml"
    f.write_text('name = "x"\n[axes]\nnum_entriez = [1]\n')
    with pytest.raises(UserError, match="num_entriez"):
        load_spec(f)
