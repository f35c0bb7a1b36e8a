"""Sweep spec expansion, point configs, job grouping and the Pareto front on hand-made points."""

from __future__ import annotations

import contextlib
import json
import math
import types
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


def test_pareto_front_maximises_the_keys_whose_larger_values_are_better():
    """PSNR, SSIM and the std-error Spearman: larger is better on either axis (a sweep's pareto_x = "spearman" is
    maximised without being told)."""
    pts = [{"id": "a", "spearman": 0.8, "ause": 0.30}, {"id": "b", "spearman": 0.5, "ause": 0.20},
           {"id": "c", "spearman": 0.4, "ause": 0.25}]  # c: less correlated than b and a larger AUSE
    assert ids(pareto_front(pts, x="spearman", y="ause")) == ["a", "b"]
    assert ids(pareto_front(pts, x="ause", y="spearman", minimize_both=False)) == ["b", "a"]
    for key in ("psnr", "ssim", "spearman"):
        assert ids(pareto_front([{"id": "lo", key: 0.1, "t": 1.0}, {"id": "hi", key: 0.9, "t": 1.0}], x=key,
                                y="t")) == ["hi"], key


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


@pytest.mark.parametrize(("lo", "hi"), [(40.0, 90.0), (12.0, 45.0), (30.0, 300.0), (5.0, 5000.0), (0.7, 3.0), (0.7, 9.0)])
def test_plot_pareto_time_labels_are_plain_and_apart(tmp_path, monkeypatch, lo, hi):
    """Seconds read as 40, 100 (not 4 x 10^1), and the labels of a short log range do not run into each other."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figs = []
    monkeypatch.setattr(plt, "close", figs.append)  # keep the figure plot_pareto would close
    times = [lo * (hi / lo) ** (i / 5) for i in range(6)]
    recs = [{"id": f"p{i}", "method": "variational", "status": "ok", "time": t, "ause_mae": 0.2 - 0.01 * i,
             "nll": -3.0 - 0.05 * i, "is_default": i == 0} for i, t in enumerate(times)]
    plot_pareto(recs, tmp_path / "p.png")
    fig = figs[0]
    renderer = fig.canvas.get_renderer()
    for ax in fig.axes:
        labels = [t for t in ax.get_xticklabels(minor=False) + ax.get_xticklabels(minor=True)
                  if t.get_text() and t.get_visible() and lo * 0.9 <= t.get_position()[0] <= hi * 1.1]
        assert len(labels) >= 2, [t.get_text() for t in labels]  # a reader can place the points
        for t in labels:
            assert "times" not in t.get_text() and "^" not in t.get_text(), t.get_text()
            float(t.get_text().replace("\u2212", "-"))  # a plain number
        boxes = sorted((t.get_window_extent(renderer) for t in labels), key=lambda b: b.x0)
        for a, b in zip(boxes, boxes[1:], strict=False):
            assert a.x1 <= b.x0, "tick labels overlap"
    plt.close("all")


@pytest.mark.parametrize(("values", "expected"), [
    ([0.132, 0.139, 0.17, 0.29, 0.76], ("log", {})),  # AUSE with a K = 1 point: a factor 5.8
    ([0.132, 0.139, 0.17], ("linear", {})),  # close together
    ([0.1, 0.29], ("linear", {})),  # a factor 2.9: within 3
    ([0.1, 0.31], ("log", {})),
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
    # 110 of 300 steps: every step of the schedule x 11/30, rounded to the nearest step (36.7 -> 37, not 36)
    assert (base.sh_degree_interval, base.densify.start, base.densify.until, base.densify.spawn_interval) == (
        100, 50, 250, 100)
    short, _ = point_configs(s, s.default.model_copy(update={"iterations": 110}))
    assert (short.sh_degree_interval, short.densify.start, short.densify.until, short.densify.spawn_interval) == (
        37, 18, 92, 37)


def test_point_ids_name_the_knobs_that_matter():
    """The id is the run's folder and the key its records are found by: a whole float without its ".0", and the
    ensemble size only for an ensemble (two ensembles of 2 and 3 members are two runs; a model that is no ensemble
    is the same run whatever N says)."""
    s = spec()
    assert point_id(s.default.model_copy(update={"downscale": 2.0})).endswith("_ds2")
    assert point_id(s.default.model_copy(update={"downscale": 1.5})).endswith("_ds1.5")
    ens = [point_id(s.default.model_copy(update={"method": "ensemble", "ensemble_size": n})) for n in (2, 3)]
    assert ens[0] != ens[1] and ens[1].startswith("ensemble_") and "_n3" in ens[1]
    plain = [point_id(s.default.model_copy(update={"ensemble_size": n})) for n in (2, 3)]
    assert plain[0] == plain[1] and "_n" not in plain[0]
    assert point_id(s.default, "fern", 4) == "fern." + point_id(s.default) + "_seed4"


def test_num_entries_only_matters_to_sgd_tables(tmp_path):
    """The informed posterior stores one table entry whatever K_table is: its K_table points share one run (and are
    not labelled vi-single); SGD tables (the paper's variant) keep the knob."""
    from uncertsplat.baselines import method_label

    s = spec(axes={"num_entries": [1, 5, 20]})
    informed = [point_configs(s, s.default.model_copy(update={"num_entries": k}))[0] for k in (1, 5, 20)]
    assert informed[0] == informed[1] == informed[2] and method_label(informed[0]) == "variational"
    sgd = [point_configs(s, s.default.model_copy(update={"method": "paper", "num_entries": k}))[0] for k in (1, 5)]
    assert [c.variational.num_entries for c in sgd] == [1, 5] and method_label(sgd[0]) == "vi-single-paper"


def test_an_ensemble_of_our_models_keeps_its_posterior_settings_and_k():
    """Members of our model have offset tables: the sweep keeps their settings and the point's K (a deterministic
    ensemble's K is N, its table settings irrelevant)."""
    s = spec(train={"ensemble_members": "variational", "variational": {"refresh_interval": 7}})
    t, e = point_configs(s, s.default.model_copy(update={"method": "ensemble", "ensemble_size": 2, "num_samples": 6}))
    assert t.variational.refresh_interval == 7 and t.ensemble_members == "variational" and e.num_samples == 6
    d, e = point_configs(spec(train={"variational": {"refresh_interval": 7}}),
                         s.default.model_copy(update={"method": "ensemble", "ensemble_size": 2, "num_samples": 6}))
    assert d.variational.refresh_interval != 7 and e.num_samples == 2


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
    s = spec(axes={"num_samples": [1, 5, 20], "iterations": [150]})
    jobs = make_jobs(s, tmp_path, tmp_path / "scene", "cpu")
    sizes = sorted(len(j["points"]) for j in jobs)
    assert sizes == [1, 4]  # K only changes evaluation: one training for the 4 K points
    allp = [p for j in jobs for p in j["points"]]
    assert sum(p["is_default"] for p in allp) == 1
    assert len({p["hash"] for p in allp}) == len(allp)
    assert len({j["run_dir"] for j in jobs}) == len(jobs)
    import json

    json.dumps(jobs)  # jobs are plain data: any engine can ship them


def test_points_that_resolve_to_the_same_configs_are_one_point(tmp_path):
    """N only matters to ensembles: a variational sweep over ensemble_size is the default alone (once), not three
    records of one run under one hash."""
    s = spec(axes={"ensemble_size": [2, 3, 5]})
    assert len(expand_points(s)) == 4  # the knob's values differ ...
    jobs = make_jobs(s, tmp_path, tmp_path / "scene", "cpu")
    assert len(jobs) == 1 and [p["is_default"] for p in jobs[0]["points"]] == [True]  # ... their configs do not


def test_a_config_s_hash_does_not_depend_on_its_keys_order():
    from uncertsplat.provenance import hash_config

    a = {"train": {"iterations": 300, "scene": {"downscale": 2.0, "background": [0, 0, 0]}}, "eval": {"seed": 1}}
    b = {"eval": {"seed": 1}, "train": {"scene": {"background": [0, 0, 0], "downscale": 2.0}, "iterations": 300}}
    assert hash_config(a) == hash_config(b) and len(hash_config(a)) == 16
    assert hash_config(a) != hash_config({**a, "eval": {"seed": 2}})


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


def test_a_bad_set_value_is_named_with_the_spec(tmp_path):
    """--set train.iterations=-3 is not blamed on the spec file alone."""
    f = tmp_path / "s.toml"
    f.write_text('name = "x"\n[axes]\nnum_entries = [1]\n')
    with pytest.raises(UserError, match=r"train\.iterations: Input should be .* \(the file's values with --set "
                                        r"train\.iterations=-3\)"):
        load_spec(f, ["train.iterations=-3"])
    assert load_spec(f, ["train.iterations=3"]).train["iterations"] == 3


@pytest.mark.parametrize(("toml", "match"), [
    ("[axes]\nnum_samples = [0, 2]\n", r"s\.toml: axes\.num_samples\.0 \(line 3\): Input should be greater than or equal to 1"),
    ('[axes]\nmethod = ["variational", "mcdropout"]\n', r"axes\.method\.1 \(line 3\): unknown method 'mcdropout' \(methods: "),
    ('[default]\nmethod = "mc"\n', r"default\.method \(line 3\): unknown method 'mc'"),
    ('train = { iterations = "x" }\n', r"s\.toml \(preset tiny\): train\.iterations \(line 2\): Input should be a valid integer"),
    ("train = { densify = { untill = 5 } }\n", r"train\.densify\.untill \(line 2\): unknown key \(did you mean train\.densify\.until\?\)"),
    ("evaluate = { num_sample = 3 }\n", r"evaluate\.num_sample \(line 2\): unknown key \(did you mean evaluate\.num_samples\?\)"),
    ('[scenes.a]\nsynth = {}\ntrain = { iteraton = 4 }\n', r"scenes\.a\.train\.iteraton \(line 4\): unknown key"),
    ('evaluate = { num_samples = 0 }\n[scenes.a]\nsynth = {}\n', r"s\.toml: evaluate\.num_samples \(line 2\): Input should be"),
    ('[scenes.a]\nsynth = {}\nevaluate = { num_samples = 0 }\n', r"s\.toml: scenes\.a\.evaluate\.num_samples \(line 4\): Input"),
    ('scenes = "x"\n', r"s\.toml: scenes \(line 2\): Input should be a valid dictionary"),
    ('train_preset = "tny"\n', r"s\.toml: train_preset \(line 1\): unknown preset 'tny' \(presets: "),
    ('scene = "x"\nsynth = { preset = "tiny" }\n', r"gives both `scene` and `synth` \(line 3\)"),
    ('[scenes.a]\nsynth = {}\n[synth]\npreset = "tiny"\n', r"gives both `scenes` and `synth` \(line 4\)"),
    ("[scenes]\n", r"the spec's \[scenes\] table names no scene"),
    ('[scenes.a]\nsynth = {}\ndefault = { iteratons = 100 }\n', r"unknown knob\(s\) in `default`: iteratons \(did you mean iterations\?"),
    ('[scenes.a]\nsynth = {}\ntrain_preset = "tinyy"\n', r"s\.toml: scenes\.a\.train_preset \(line 4\): unknown preset 'tinyy'"),
    ('[scenes.a]\nsynth = { preset = "tiny", sede = 3 }\n', r"s\.toml: scenes\.a\.synth\.sede \(line 3\): unknown key"),
    ('synth = { preset = "huge" }\n', r"s\.toml: synth\.preset \(line 2\): "),
    ('[scenes.a]\nphotos = "p"\nreconstruct = { matcher = "fast" }\n', r"s\.toml: scenes\.a\.reconstruct\.matcher \(line 4\): "),
    ('scenes = ["a"]\n', r"s\.toml: scenes \(line 2\): Input should be a valid dictionary"),
])
def test_bad_knob_values_and_base_keys_are_refused_when_the_spec_is_read(tmp_path, toml, match):
    """Axis values, methods and the spec's train / evaluate keys are checked on reading, each named where it is in
    the file, with its line (an axis value of 0 was a traceback when the points were expanded; a bad `train` key was named as
    a key of "train config (preset ...)")."""
    f = tmp_path / "s.toml"
    f.write_text(('' if toml.startswith("train_preset") else 'train_preset = "tiny"\n') + toml)
    with pytest.raises(UserError, match=match):
        load_spec(f)


def test_empty_axes_and_seeds_are_said_and_a_scene_set_on_the_command_line_replaces_synth(tmp_path, capsys):
    """`axes.iterations = []` and `seeds = []` were taken without a word (a list emptied by mistake runs one point);
    a scene given with --set replaces the file's synthetic scene, as --scene does."""
    f = tmp_path / "s.toml"
    f.write_text('train_preset = "tiny"\nseeds = []\nsynth = { preset = "tiny" }\n[axes]\niterations = []\n')
    capsys.readouterr()
    spec = load_spec(f)
    said = " ".join(capsys.readouterr().err.split())
    assert "axes.iterations, seeds = [] leave the knob at its default" in said, said
    assert spec.seeds == [] and spec.axes.iterations == []
    assert load_spec(f, [f"scene={tmp_path}"]).scene == tmp_path
    both = tmp_path / "both.toml"
    both.write_text(f'train_preset = "tiny"\nscene = "{tmp_path}"\nsynth = {{ preset = "tiny" }}\n')
    with pytest.raises(UserError, match="gives both `scene` and `synth`"):  # another --set does not let it through
        load_spec(both, ["default.iterations=60"])


# ------------------------------------------------------------------------------------------ scenes and seeds
MULTI = """
name = "multi"
seeds = [3, 1]
train_preset = "tiny"
evaluate = { split = "test" }
[scenes.synthetic]
synth = { preset = "tiny", seed = 0 }
[scenes.mine]
path = "captures/mine"
train_preset = "paper"
train = { scene = { downscale = 2.0 } }
evaluate = { num_samples = 4 }
[default]
method = "variational"
[axes]
method = ["fisher"]
num_samples = [2]
"""


def test_scenes_and_seeds_replicate_every_point(tmp_path):
    f = tmp_path / "spec.toml"
    f.write_text(MULTI)
    s = load_spec(f)
    assert s.scenes["mine"].path == tmp_path / "captures" / "mine"  # read from the spec's folder
    jobs = make_jobs(s, tmp_path / "out", {"synthetic": tmp_path / "a", "mine": tmp_path / "b"}, "cpu")
    pts = [(j, p) for j in jobs for p in j["points"]]
    # 3 points (default, fisher, K=2) x 2 scenes x 2 seeds, in 2 trainings per scene and seed
    assert len(pts) == 12 and len(jobs) == 8
    ids = {p["id"] for _, p in pts}
    assert "synthetic.variational_seed3" in ids and "mine.fisher_seed1" in ids and "mine.variational_k2_seed1" in ids
    assert len({p["hash"] for _, p in pts}) == 12
    for j, p in pts:
        assert j["seed"] == j["train_config"]["seed"] == p["eval_config"]["seed"]
        assert j["run_dir"] == str((tmp_path / "out" / "runs" / j["scene_name"] / j["job_id"].split(".", 1)[1]).resolve())
        if j["scene_name"] == "mine":  # the scene's own preset and keys over the spec's
            assert j["train_config"]["scene"]["downscale"] == 2.0 and j["scene"] == str((tmp_path / "b").resolve())
            assert p["eval_config"]["num_samples"] == (2 if "_k2" in p["id"] else 4)
        else:
            assert j["train_config"]["scene"]["downscale"] == 1.0
    paper = point_configs(s, s.default, "mine", 1)[0]
    tiny = point_configs(s, s.default, "synthetic", 1)[0]
    assert paper.iterations != tiny.iterations  # the presets differ
    assert sum(p["is_default"] for _, p in pts) == 4  # one default per scene and seed
    # the same configs on another scene are other points: the scene is part of the hash
    one = SweepSpec(scenes={"a": {"synth": {}}, "b": {"synth": {}}})
    hashes = [p["hash"] for j in make_jobs(one, tmp_path, {"a": tmp_path, "b": tmp_path}, "cpu") for p in j["points"]]
    assert len(set(hashes)) == 2


def test_single_scene_specs_keep_their_ids_and_hashes(tmp_path):
    from uncertsplat.provenance import hash_config

    s = spec()
    (job,) = make_jobs(s, tmp_path, tmp_path / "scene", "cpu")
    (p,) = job["points"]
    t, e = point_configs(s, s.default)
    assert p["hash"] == hash_config({"train": t.model_dump(mode="json"), "eval": e.model_dump(mode="json")})
    assert p["id"] == point_id(s.default) and "seed" not in p["id"] and job["scene_name"] is None
    assert job["run_dir"] == str((tmp_path / "runs" / job["job_id"]).resolve())


@pytest.mark.parametrize(("toml", "match"), [
    ('[scenes.a]\npath = "x"\nsynth = {}\n', "exactly one of path, photos or synth"),
    ("[scenes.a]\n", "exactly one of path, photos or synth"),
    ('[scenes."a b"]\nsynth = {}\n', "scene name"),
    ('[scenes.a]\nsynth = {}\nreconstruct = { matcher = "exhaustive" }\n', "only apply to a `photos` scene"),
    ('seeds = [1, 1]\n', "distinct"),
    ('scene = "x"\n[scenes.a]\nsynth = {}\n', "not both"),
])
def test_bad_scenes_and_seeds_are_refused(tmp_path, toml, match):
    f = tmp_path / "s.toml"
    f.write_text(toml)
    with pytest.raises(UserError, match=match):
        load_spec(f)


def _record(pid, status="ok", psnr=20.0, time=1.0, scene=None, seed=None, default=False):
    from uncertsplat.schemas import SweepRecord

    extra = dict(psnr=psnr, time=time, ause_mae=0.1 * time, nll=1.0) if status == "ok" else dict(error="x")
    return SweepRecord(id=pid, hash=pid, job="j", method=pid.split(".")[-1].split("_")[0], knobs={},
                       is_default=default, status=status, scene=scene, seed=seed, **extra)


def test_table_averages_seeds_and_fronts_are_per_scene():
    from uncertsplat.sweep.pareto import group_records, summarize

    recs = [_record("a.variational_seed0", psnr=20.0, time=2.0, scene="a", seed=0, default=True),
            _record("a.variational_seed1", psnr=22.0, time=4.0, scene="a", seed=1, default=True),
            _record("a.variational_seed2", status="failed", scene="a", seed=2, default=True),
            _record("a.fisher_seed0", psnr=18.0, time=1.0, scene="a", seed=0),
            _record("b.variational_seed0", psnr=30.0, time=9.0, scene="b", seed=0, default=True)]
    table = {g.id: g for g in group_records(recs)}
    assert list(table) == ["a.variational", "a.fisher", "b.variational"]
    v = table["a.variational"]
    assert v.seeds == [0, 1] and v.num_failed == 1
    assert v.mean["psnr"] == pytest.approx(21.0) and v.spread["psnr"] == pytest.approx(2 ** 0.5)
    assert v.mean["time"] == pytest.approx(3.0) and table["a.fisher"].spread["psnr"] is None  # one seed: no spread
    s = SweepSpec(scenes={"a": {"synth": {}}, "b": {"synth": {}}}, seeds=[0, 1, 2], pareto_y=["ause_mae"])
    summary = summarize(s, recs)
    # per scene: on a, fisher (faster, lower AUSE) dominates the variational mean; b has its one point
    assert summary.pareto == {"a: ause_mae_vs_time": ["a.fisher"], "b: ause_mae_vs_time": ["b.variational"]}
    assert summary.default == "a.variational" and summary.num_failed == 1


def test_points_at_another_resolution_get_fronts_of_their_own(tmp_path):
    """A downscaled point is scored against smaller photos (a sweep put one on the default's front with NLL -1.44
    against -1.30): each resolution gets its own front, the figure a row of panels, the page a note."""
    from uncertsplat.report.sweep_page import build_sweep_page
    from uncertsplat.sweep.pareto import plot_pareto, split_by_resolution, summarize, table_points

    def at(pid, downscale, **kw):
        return _record(pid, **kw).model_copy(update={"knobs": {"downscale": downscale}})

    recs = [at("variational_ds1", 1.0, time=4.0, psnr=21.0), at("variational_ds2", 2.0, time=1.0, psnr=22.3),
            at("fisher_ds1", 1.0, time=3.0, psnr=20.0)]
    s = SweepSpec(pareto_y=["ause_mae"])
    summary = summarize(s, recs)
    assert summary.pareto == {"ause_mae_vs_time @ downscale 1": ["fisher_ds1"],
                              "ause_mae_vs_time @ downscale 2": ["variational_ds2"]}
    assert split_by_resolution(summary)
    assert {p["id"]: p["panel"] for p in table_points(summary)} == {
        "variational_ds1": "downscale 1", "variational_ds2": "downscale 2", "fisher_ds1": "downscale 1"}
    assert "each resolution has a front of its own" in " ".join(build_sweep_page(summary, None).split())
    same = summarize(s, [r.model_copy(update={"knobs": {}}) for r in recs])  # one resolution: one front, no note
    assert list(same.pareto) == ["ause_mae_vs_time"] and not split_by_resolution(same)
    assert "a front of its own" not in build_sweep_page(same, None)
    path = plot_pareto(table_points(summary), tmp_path / "p.png", ys=["ause_mae"], group="panel")
    assert path.stat().st_size > 1000
    # a point that leaves the knob unset trains at the spec's downscale: it shares that resolution's front
    recs = [at("variational", None, time=4.0, psnr=21.0), at("variational_ds1", 1.0, time=3.0, psnr=20.0),
            at("variational_ds2", 2.0, time=1.0, psnr=22.3)]
    summary = summarize(s, recs)
    assert summary.pareto == {"ause_mae_vs_time @ downscale 1": ["variational_ds1"],
                              "ause_mae_vs_time @ downscale 2": ["variational_ds2"]}
    assert {p["id"]: p["panel"] for p in table_points(summary, s)} == {
        "variational": "downscale 1", "variational_ds1": "downscale 1", "variational_ds2": "downscale 2"}
    halved = SweepSpec(pareto_y=["ause_mae"], train={"scene": {"downscale": 2.0}})  # the spec's own is 2
    assert list(summarize(halved, recs).pareto) == ["ause_mae_vs_time @ downscale 2",
                                                    "ause_mae_vs_time @ downscale 1"]


def test_multi_scene_sweep_refuses_scene_flag_and_missing_folders(tmp_path):
    from uncertsplat.stages import sweep

    f = tmp_path / "s.toml"
    f.write_text('[scenes.mine]\npath = "nowhere"\n')
    with pytest.raises(UserError, match="names 1 scenes"):
        sweep.run(f, tmp_path / "out", device="cpu", scene=tmp_path)
    with pytest.raises(UserError, match="scene 'mine' does not exist") as err:
        sweep.run(f, tmp_path / "out", device="cpu")
    assert "scenes.mine.path" in err.value.hint
    f.write_text('[scenes.mine]\nphotos = "nowhere"\n')
    with pytest.raises(UserError, match="photos folder of sweep scene 'mine'"):
        sweep.run(f, tmp_path / "out", device="cpu")


def test_a_scene_can_move_the_default_the_axes_vary_around(tmp_path):
    s = SweepSpec(train_preset="tiny", default={"iterations": 20, "num_samples": 5},
                  axes={"num_samples": [2]},
                  scenes={"small": {"synth": {}}, "long": {"synth": {}, "default": {"iterations": 40}}})
    jobs = make_jobs(s, tmp_path, {"small": tmp_path, "long": tmp_path}, "cpu")
    its = {p["id"]: j["train_config"]["iterations"] for j in jobs for p in j["points"]}
    assert its == {"small.variational_it20_k5": 20, "small.variational_it20_k2": 20,
                   "long.variational_it40_k5": 40, "long.variational_it40_k2": 40}
    defaults = [p["id"] for j in jobs for p in j["points"] if p["is_default"]]
    assert sorted(defaults) == ["long.variational_it40_k5", "small.variational_it20_k5"]
    with pytest.raises(ValueError, match="unknown knob"):
        SweepSpec(scenes={"a": {"synth": {}, "default": {"iterationz": 3}}})
    with pytest.raises(ValueError, match="scenes.a.default"):
        SweepSpec(scenes={"a": {"synth": {}, "default": {"iterations": 0}}})


def test_only_scenes_restricts_a_multi_scene_spec(tmp_path):
    from uncertsplat.stages import sweep

    f = tmp_path / "s.toml"
    f.write_text('[scenes.mine]\npath = "nowhere"\n[scenes.other]\npath = "nowhere2"\n')
    with pytest.raises(UserError, match="--scenes names typo") as err:
        sweep.run(f, tmp_path / "out", device="cpu", only_scenes=["typo"])
    assert "mine, other" in err.value.hint
    with pytest.raises(UserError, match="scene 'other' does not exist"):  # mine is not even looked at
        sweep.run(f, tmp_path / "out", device="cpu", only_scenes=["other"])


def test_methods_spec_file_is_valid():
    s = load_spec(ROOT / "benchmarks" / "specs" / "methods.toml")
    assert set(s.scenes) == {"synthetic", "fern", "bonsai"} and s.seeds == [0, 1, 2]
    assert s.scenes["fern"].photos.resolve() == (ROOT.parent / "shared" / "datasets" / "fern" / "images").resolve()
    jobs = make_jobs(s, ROOT / "never-written", {n: ROOT for n in s.scenes}, "cpu")
    assert len(jobs) == 45  # 5 methods x 3 scenes x 3 seeds
    fern = next(j for j in jobs if j["scene_name"] == "fern")["train_config"]
    assert fern["iterations"] == 3000 and fern["densify"]["until"] < 3000  # the paper's schedule, scaled


def test_an_interrupted_point_stops_a_sequential_sweep_without_a_retry():
    """Ctrl-C during a point's training (an Interrupted error, its checkpoint written) stops the sweep: the points
    before it keep their records, it is not run again, the ones after are not started."""
    from uncertsplat.errors import Interrupted
    from uncertsplat.sweep.executors import run_local

    calls, got = [], []

    def run_job(job):
        calls.append(job["job_id"])
        if job["job_id"] == "b":
            raise Interrupted("training interrupted at step 7; checkpoint saved (x)")
        p = job["points"][0]
        return [{"id": p["id"], "hash": p["hash"], "job": job["job_id"], "status": "ok"}]

    jobs = [{"job_id": n, "points": [{"id": n, "hash": n}]} for n in ("a", "b", "c")]
    with pytest.raises(Interrupted, match="step 7"):
        run_local(jobs, jobs=1, retries=2, on_records=got.extend, run_job=run_job)
    assert calls == ["a", "b"] and [r["job"] for r in got] == ["a"]


def test_pareto_metrics_must_be_table_columns(tmp_path):
    f = tmp_path / "s.toml"
    f.write_text('name = "x"\npareto_x = "foo"\n')
    with pytest.raises(UserError, match="pareto_x \\(line 2\\): unknown metric 'foo'; the table's metrics are psnr"):
        load_spec(f)
    f.write_text('name = "x"\npareto_y = ["nll", "bar"]\n')
    with pytest.raises(UserError, match=r"pareto_y \(line 2\): unknown metric 'bar'"):
        load_spec(f)


def test_an_ensemble_point_is_labelled_with_the_k_it_is_measured_with(tmp_path):
    """A plain ensemble is evaluated with K = N whatever the point's K: its id and knobs say the K used (they said
    the spec's K, beside a record of another)."""
    s = spec(default={"method": "variational", "num_samples": 4},
             axes={"method": ["ensemble"], "ensemble_size": [2]}, design="grid")
    points = [p for j in make_jobs(s, tmp_path, tmp_path / "scene", "cpu") for p in j["points"]]
    (ens,) = [p for p in points if p["knobs"]["method"] == "ensemble"]
    assert ens["knobs"]["num_samples"] == ens["eval_config"]["num_samples"] == 2 and "_k2" in ens["id"]
    (default,) = [p for p in points if p["is_default"]]
    assert default["knobs"]["method"] == "variational" and default["knobs"]["num_samples"] == 4


def test_ctrl_c_outside_a_training_stops_the_sweep_with_its_advice(tmp_path, monkeypatch):
    """Ctrl-C while a point is evaluated (a KeyboardInterrupt, not a training's Interrupted) ends the sweep as an
    interruption that says how to go on (it printed only 'interrupted')."""
    from uncertsplat.errors import Interrupted
    from uncertsplat.stages import sweep
    from uncertsplat.sweep import executors

    def stopped(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(executors, "run_local", stopped)
    (tmp_path / "scene").mkdir()
    f = tmp_path / "s.toml"
    f.write_text('name = "x"\ntrain_preset = "tiny"\n[default]\niterations = 5\n')
    with pytest.raises(Interrupted, match="sweep stopped") as err:
        sweep.run(f, tmp_path / "out", device="cpu", scene=tmp_path / "scene", jobs=1)
    assert "Run the same sweep command again" in err.value.hint


def test_a_sweep_resumed_with_another_default_summarises_this_spec(tmp_path, monkeypatch, capsys):
    """Run again with the default moved (--set default.num_samples): the records of points both specs share take
    this spec's ids and default flag, the earlier default's record is left out of the summary, and the counts say
    what this spec has done (they counted every record of the log)."""
    from uncertsplat.stages import sweep
    from uncertsplat.sweep import jobs as sweep_jobs

    def fake(job):  # an ok record per point, no training
        return [{"id": p["id"], "hash": p["hash"], "job": job["job_id"], "method": job["method_label"],
                 "knobs": p["knobs"], "is_default": p["is_default"], "status": "ok", "run_dir": job["run_dir"],
                 "psnr": 20.0, "ause_mae": 0.1, "time": 1.0} for p in job["points"]]

    monkeypatch.setattr(sweep_jobs, "run_job", fake)
    (tmp_path / "scene").mkdir()
    f = tmp_path / "s.toml"
    f.write_text('name = "x"\ntrain_preset = "tiny"\n[default]\niterations = 5\nnum_samples = 4\n'
                 '[axes]\nnum_samples = [2, 4, 8]\n')
    out = tmp_path / "out"
    first = sweep.run(f, out, device="cpu", scene=tmp_path / "scene", jobs=1)
    assert first.default == "variational_it5_k4" and len(first.records) == 3
    capsys.readouterr()
    again = sweep.run(f, out, device="cpu", scene=tmp_path / "scene", jobs=1, overrides=["default.num_samples=2"])
    said = " ".join(capsys.readouterr().err.split())
    assert "0 points to run" in said and "(3 already done)" in said  # k2, k4, k8 are this spec's points too
    assert again.default == "variational_it5_k2"
    assert sorted(r.id for r in again.records) == ["variational_it5_k2", "variational_it5_k4", "variational_it5_k8"]
    assert [r.id for r in again.records if r.is_default] == ["variational_it5_k2"]
    f.write_text(f.read_text(encoding="utf-8").replace("[2, 4, 8]", "[2, 8]"))  # k4 is no point of the spec now
    third = sweep.run(f, out, device="cpu", scene=tmp_path / "scene", jobs=1, overrides=["default.num_samples=2"])
    said = " ".join(capsys.readouterr().err.split())
    assert "also holds 1 point of other settings" in said
    assert sorted(r.id for r in third.records) == ["variational_it5_k2", "variational_it5_k8"]


def _fake_jobs(monkeypatch, log=None):
    """Sweep jobs that train nothing: an ok record per point whose report names the point's hash."""
    from uncertsplat.sweep import jobs as sweep_jobs

    def fake(job):
        if log is not None:
            log.extend(p["id"] for p in job["points"])
        return [{"id": p["id"], "hash": p["hash"], "job": job["job_id"], "method": job["method_label"],
                 "knobs": p["knobs"], "is_default": p["is_default"], "status": "ok", "run_dir": job["run_dir"],
                 "psnr": 20.0, "ause_mae": 0.1, "time": 1.0, "point_report": f'{{"hash": "{p["hash"]}"}}'}
                for p in job["points"]]

    monkeypatch.setattr(sweep_jobs, "run_job", fake)


def _one_point_sweep(tmp_path, monkeypatch):
    """(spec, output folder, its record): a one-point sweep of fake jobs (``_fake_jobs``) on an empty scene folder,
    run once."""
    from uncertsplat.stages import sweep

    _fake_jobs(monkeypatch)
    (tmp_path / "scene").mkdir()
    f = tmp_path / "s.toml"
    f.write_text('name = "x"\ntrain_preset = "tiny"\n[default]\niterations = 5\n')
    out = tmp_path / "out"
    (rec,) = sweep.run(f, out, device="cpu", scene=tmp_path / "scene", jobs=1).records
    return f, out, rec


def test_a_point_whose_newest_record_failed_is_run_again(tmp_path, monkeypatch):
    """After `--force`, a point whose evaluation failed (its earlier record ok) was taken as done by every later sweep
    without --force ("0 points to run") while the summary showed it failed: only its newest record counts."""
    from uncertsplat.stages import sweep
    from uncertsplat.sweep import jobs as sweep_jobs

    f, out, rec = _one_point_sweep(tmp_path, monkeypatch)
    ok = sweep_jobs.run_job

    def failing(job):
        return [{**r, "status": "failed", "stage": "evaluate", "error": "boom"} for r in ok(job)]

    monkeypatch.setattr(sweep_jobs, "run_job", failing)
    with pytest.raises(UserError):  # (the sweep ends with exit 2 when a point failed)
        sweep.run(f, out, device="cpu", scene=tmp_path / "scene", jobs=1, force=True)
    log: list[str] = []
    _fake_jobs(monkeypatch, log)
    (again,) = sweep.run(f, out, device="cpu", scene=tmp_path / "scene", jobs=1).records
    assert log == [rec.id] and again.status == "ok"


def test_a_retrained_run_that_cannot_take_its_place_fails_its_points(tmp_path, monkeypatch):
    """run_job reports, it does not raise: a rename that fails when the retrained run takes the finished one's place
    marks the job's points failed, naming the folders (it escaped run_job, and the executors recorded a bare error)."""
    from types import SimpleNamespace

    from uncertsplat.sweep import jobs as sweep_jobs

    summary = SimpleNamespace(peak_memory_mb=1.0, seconds=2.0, num_gaussians=3, num_carriers=3,
                              memory_per_gaussian_bytes=4, warnings=[])
    pending = tmp_path / "r.retrain"
    monkeypatch.setattr(sweep_jobs, "_train", lambda job, device: (summary, True, pending))
    monkeypatch.setattr(sweep_jobs, "_evaluate", lambda job, p, device, run_dir=None: {
        "eval_peak_memory_mb": 1.0, "calibration_seconds": 0.5, "eval_seconds": 1.0, "notes": [],
        "evaluated": str(run_dir)})

    def refused(run_dir):
        raise PermissionError(13, "Permission denied", str(run_dir))

    monkeypatch.setattr(sweep_jobs, "_swap_in", refused)
    job = {"job_id": "j", "method_label": "m", "run_dir": str(tmp_path / "r"), "device": "cpu",
           "points": [{"id": "p", "hash": "h", "knobs": {}, "is_default": True}]}
    (record,) = sweep_jobs.run_job(job)
    assert record["status"] == "failed" and record["stage"] == "swap" and record["evaluated"] == str(pending)
    assert f"the retrained run in {pending} could not take the place of {tmp_path / 'r'}" in record["error"]


def test_a_point_of_other_settings_never_replaces_a_points_report(tmp_path, monkeypatch):
    """points/ID.json was named by id alone: a run with --set train.seed=1 (other hashes, the same ids) replaced the
    seed-0 reports, the only copies, while sweep.json went on showing seed 0's records; a deleted report was never
    written again. Every report is kept by hash and points/ID.json follows the spec's records."""
    from uncertsplat.stages import sweep

    f, out, rec = _one_point_sweep(tmp_path, monkeypatch)
    report = out / "points" / f"{rec.id}.json"
    assert rec.hash in report.read_text(encoding="utf-8")
    (other,) = sweep.run(f, out, device="cpu", scene=tmp_path / "scene", jobs=1,
                         overrides=["train.seed=1"]).records
    assert other.id == rec.id and other.hash != rec.hash and other.hash in report.read_text(encoding="utf-8")
    assert sweep.run(f, out, device="cpu", scene=tmp_path / "scene", jobs=1).records[0].hash == rec.hash
    assert rec.hash in report.read_text(encoding="utf-8")  # this spec's point's report again
    assert {p.stem for p in (out / "points" / "by_hash").iterdir()} == {rec.hash, other.hash}
    report.unlink()
    sweep.run(f, out, device="cpu", scene=tmp_path / "scene", jobs=1)
    assert rec.hash in report.read_text(encoding="utf-8")


def test_a_scene_folder_that_changed_is_refused_or_trained_again(tmp_path, monkeypatch, capsys):
    """A sweep on a scene of one's own reused every point after a photo of the scene changed (or after --scene named
    another folder): refused now, with --force training and measuring again (its runs removed: a finished run of
    the same config was reused as it was); notes beside the scene's files are no change."""
    from uncertsplat.stages import sweep

    measured: list[str] = []
    _fake_jobs(monkeypatch, measured)
    scene = tmp_path / "scene"
    (scene / "images").mkdir(parents=True)
    (scene / "images" / "a.png").write_bytes(b"a photo")
    f = tmp_path / "s.toml"
    f.write_text('name = "x"\ntrain_preset = "tiny"\n[default]\niterations = 5\n')
    out = tmp_path / "out"
    sweep.run(f, out, device="cpu", scene=scene, jobs=1)
    assert len(measured) == 1
    (scene / "notes.txt").write_text("taken at noon")
    sweep.run(f, out, device="cpu", scene=scene, jobs=1)
    assert len(measured) == 1
    (scene / "images" / "a.png").write_bytes(b"the photo edited")
    with pytest.raises(UserError, match=r"not the one its points were measured on .*'s files changed") as err:
        sweep.run(f, out, device="cpu", scene=scene, jobs=1)
    assert "--force" in err.value.hint
    other = tmp_path / "other"
    other.mkdir()
    with pytest.raises(UserError, match="moved from"):
        sweep.run(f, out, device="cpu", scene=other, jobs=1)
    (out / "runs" / "stale").mkdir(parents=True)
    capsys.readouterr()
    sweep.run(f, out, device="cpu", scene=scene, jobs=1, force=True)
    assert len(measured) == 2 and not (out / "runs").exists()
    assert "trained on the scene before it changed" in " ".join(capsys.readouterr().err.split())
    sweep.run(f, out, device="cpu", scene=scene, jobs=1)  # the edited scene is now the sweep's
    assert len(measured) == 2
    # the sweep's output inside its scene folder is not part of the scene (its runs and records changed it each time)
    inner = scene / "sweep"
    sweep.run(f, inner, device="cpu", scene=scene, jobs=1)
    sweep.run(f, inner, device="cpu", scene=scene, jobs=1)
    assert len(measured) == 3


def test_point_reports_follow_their_points_to_new_ids(tmp_path):
    """Two measured points that trade ids keep their own reports (every report is read before any is written)."""
    from types import SimpleNamespace

    from uncertsplat.stages.sweep import _move_point_reports

    pts = tmp_path / "points"
    pts.mkdir()
    (pts / "a.json").write_text("report of A")
    (pts / "b.json").write_text("report of B")
    records = [SimpleNamespace(hash="hA", id="a", status="ok"), SimpleNamespace(hash="hB", id="b", status="ok"),
               SimpleNamespace(hash="hC", id="c", status="failed")]
    _move_point_reports(tmp_path, records, {"hA": {"id": "b"}, "hB": {"id": "a"}, "hC": {"id": "d"}})
    assert (pts / "b.json").read_text(encoding="utf-8") == "report of A" and (pts / "a.json").read_text(encoding="utf-8") == "report of B"
    assert not (pts / "d.json").exists()


def test_a_spec_key_that_a_knob_replaces_is_named():
    """`--set evaluate.num_samples=3` beside `[default] num_samples = 2` had no effect and was recorded as used; a
    scene's `train.scene.downscale` beside a downscale knob likewise. Not named: a value equal to the knob's, a knob
    set only in [axes] (the default point uses the spec's value), a top-level key another scene uses, the informed
    posterior's num_entries (its one entry is the spec's), train.iterations (the schedule the knob scales)."""
    from uncertsplat.sweep.spec import shadowed_settings

    assert shadowed_settings(spec(evaluate={"num_samples": 3})) == ["evaluate.num_samples = 3 (the knob `num_samples`)"]
    assert shadowed_settings(spec(evaluate={"num_samples": 10}, train={"iterations": 20})) == []
    axes_only = spec(evaluate={"num_samples": 7}, axes={"num_samples": [2, 4]})
    axes_only = axes_only.model_copy(update={"default": axes_only.default.model_copy(update={"num_samples": None})})
    assert shadowed_settings(axes_only) == []
    multi = SweepSpec(train_preset="tiny", default={"method": "variational", "downscale": 4.0},
                      scenes={"a": {"synth": {"preset": "tiny"}, "train": {"scene": {"downscale": 8.0}}}})
    assert shadowed_settings(multi) == ["scenes.a.train.scene.downscale = 8.0 (the knob `downscale`)"]
    two = SweepSpec(train_preset="tiny", train={"scene": {"downscale": 2.0}}, default={"method": "variational"},
                    scenes={"a": {"synth": {"preset": "tiny"}, "default": {"downscale": 4.0}},
                            "b": {"synth": {"preset": "tiny"}}})
    assert shadowed_settings(two) == []  # scene b trains at the spec's 2.0
    only_a = two.model_copy(update={"scenes": {"a": two.scenes["a"]}})
    assert shadowed_settings(only_a) == ["train.scene.downscale = 2.0 (the knob `downscale`)"]
    informed = spec(train={"variational": {"num_entries": 5}})  # the default point sets num_entries = 10
    assert shadowed_settings(informed) == []


def test_the_sweep_refuses_a_key_a_knob_replaces_before_running(tmp_path):
    from uncertsplat.stages import sweep as stage

    spec_file = tmp_path / "s.toml"
    spec_file.write_text('train_preset = "tiny"\nevaluate = { num_samples = 3 }\n[synth]\npreset = "tiny"\n'
                         '[default]\nmethod = "variational"\nnum_samples = 2\n')
    with pytest.raises(UserError, match=r"evaluate.num_samples = 3 \(the knob `num_samples`\): the knob sets this in "
                                        r"every point of the sweep"):
        stage.run(spec_file, tmp_path / "out", jobs=1, device="cpu")
    assert not (tmp_path / "out").exists()


def test_a_changed_synthetic_scene_is_not_taken_for_the_old_one(tmp_path):
    """The sweep's synthetic scene generated with other settings than the spec's now (--set synth.seed=1 on a sweep
    made with seed 0) is refused: its points would be reused as the new scene's; --force generates it again."""
    from uncertsplat.data.synthetic import read_scene_meta
    from uncertsplat.stages.sweep import _synth

    folder = tmp_path / "scene"
    _synth({"preset": "tiny", "seed": 0, "num_views": 6}, folder)
    stamp = (folder / "scene.json").stat().st_mtime_ns
    assert _synth({"preset": "tiny", "seed": 0, "num_views": 6}, folder) == folder  # the same: kept as it is
    assert (folder / "scene.json").stat().st_mtime_ns == stamp
    with pytest.raises(UserError, match=r"generated with other settings than the spec's now \(seed 0 -> 1\).*--force"):
        _synth({"preset": "tiny", "seed": 1, "num_views": 6}, folder)
    with pytest.raises(UserError, match=r"num_views 6 -> 8"):
        _synth({"preset": "tiny", "seed": 0, "num_views": 8}, folder)
    _synth({"preset": "tiny", "seed": 1, "num_views": 6}, folder, force=True)
    assert read_scene_meta(folder).seed == 1 and read_scene_meta(folder).config["seed"] == 1
    with pytest.raises(UserError, match=r"seed 1 -> 0"):
        _synth({"preset": "tiny", "seed": 0, "num_views": 6}, folder)
    with pytest.raises(UserError, match=r"num_views 6 -> 12"):  # every setting, not the six it compared before
        _synth({"preset": "tiny", "seed": 1, "num_views": 12}, folder)
    assert read_scene_meta(folder).config["num_views"] == 6  # a refused spec leaves the scene as it was


def _sleepy_job(job: dict) -> list[dict]:
    """A sweep job for the pool tests (module level: spawn workers import it)."""
    import time

    time.sleep(float(job.get("sleep", 0.2)))
    return [{"job": job["job_id"], "status": "ok"}]


def _job_until_stopped(job: dict) -> str:
    """A sweep job that trains until the sweep stops it (``train.trainer.STOP_REQUESTED``), at most 60 s."""
    import time

    from uncertsplat.train.trainer import STOP_REQUESTED

    t0 = time.perf_counter()
    while time.perf_counter() - t0 < 60:
        if STOP_REQUESTED.is_set():
            return "stopped"
        time.sleep(0.05)
    return "ran to its end"


def test_the_pool_gets_a_job_only_when_a_worker_is_free_and_a_stop_reaches_every_worker():
    """A job is handed to the pool only when a worker is free (the pool's queue cannot be taken back: on Ctrl-C a
    queued job trained to its end in a worker started after the signal); the sweep's stop event stops a worker's
    training as Ctrl-C does, without a second signal (which acted mid-step, after the terminal's first)."""
    import time
    from concurrent.futures import ProcessPoolExecutor
    from multiprocessing import get_context

    from uncertsplat.sweep.executors import _worker_stops_quietly_on_ctrl_c, run_local

    running, most, got = [0], [0], []

    def started(job):
        running[0] += 1
        most[0] = max(most[0], running[0])

    def finished(recs):
        running[0] -= 1
        got.extend(recs)

    todo = [{"job_id": f"j{i}", "points": [], "sleep": 0.3} for i in range(5)]
    run_local(todo, jobs=2, retries=0, on_records=finished, on_start=started, run_job=_sleepy_job)
    assert most[0] == 2 and sorted(r["job"] for r in got) == [f"j{i}" for i in range(5)]
    ctx = get_context("spawn")
    stop = ctx.RawValue("b", 0)
    with ProcessPoolExecutor(max_workers=1, mp_context=ctx, initializer=_worker_stops_quietly_on_ctrl_c,
                             initargs=(stop,)) as pool:
        fut = pool.submit(_job_until_stopped, {"job_id": "long"})
        time.sleep(3.0)  # the worker is up and training
        t0 = time.perf_counter()
        stop.value = 1
        assert fut.result(timeout=30) == "stopped" and time.perf_counter() - t0 < 20


def test_pareto_axes_name_what_they_show():
    """Axis names with units and direction (PSNR was 'PSNR (dB)' with no direction, memory the raw key), titles from
    the axes asked (it said 'accuracy vs time' for any x), and SSIM's front maximised as PSNR's."""
    from uncertsplat.sweep.pareto import AXIS_LABELS, HIGHER_IS_BETTER, axis_name

    assert AXIS_LABELS["psnr"] == "PSNR (dB), higher is better" and axis_name("nll") == "NLL (nats)"
    assert axis_name("peak_memory_mb") == "peak memory (MB)" and axis_name("unknown_key") == "unknown_key"
    assert {"psnr", "ssim"} <= HIGHER_IS_BETTER
    pts = [{"time": 1.0, "ssim": 0.8}, {"time": 2.0, "ssim": 0.9}, {"time": 3.0, "ssim": 0.85}]
    assert [p["ssim"] for p in pareto_front(pts, x="time", y="ssim", minimize_both=False)] == [0.8, 0.9]


def test_a_record_written_before_the_fit_was_timed_reads_with_it():
    """Records of a sweep resumed across the change of `time` (train + eval, then train + fit + eval) sum alike."""
    from uncertsplat.schemas.runs import SweepRecord

    base = {"id": "a", "hash": "h", "status": "ok", "is_default": False, "job": "j", "method": "variational",
            "knobs": {}, "train_seconds": 10.0, "eval_seconds": 2.0, "calibration_seconds": 5.0}
    assert SweepRecord.model_validate({**base, "time": 12.0}).time == 17.0  # written before: the fit added
    assert SweepRecord.model_validate({**base, "time": 17.0}).time == 17.0
    assert SweepRecord.model_validate({**base, "time": 12.0, "calibration_seconds": None}).time == 12.0


def _job_checkpointing_on_ctrl_c(job: dict) -> list[dict]:
    """A sweep job for the Ctrl-C test: ``quick`` returns at once; ``training`` steps as ``Trainer.fit`` does (its
    handler: the first SIGINT or SIGTERM asks for a stop and puts the previous handlers back, so a second acts at
    once) until stopped, then takes a second to write its checkpoint, the file ``checkpoint``. (It leaves out
    ``train.trainer.STOP_REQUESTED``, set after the driver's Ctrl-C: torch's import would slow the test down.)"""
    import os
    import signal
    import time

    from uncertsplat.errors import Interrupted

    folder = Path(job["dir"])
    if job["job_id"] == "quick":
        (folder / "quick.pid").write_text(str(os.getpid()))
        return [{"job": "quick", "status": "ok"}]
    stopped = []
    old = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}

    def handler(signum, frame):
        stopped.append(signum)
        for s, h in old.items():
            signal.signal(s, h)

    for s in old:
        signal.signal(s, handler)
    (folder / "training.pid").write_text(str(os.getpid()))  # (stepping now)
    t0 = time.monotonic()
    while not stopped and time.monotonic() - t0 < 60:
        time.sleep(0.01)  # a step
    time.sleep(1.0)  # the checkpoint of a big model
    (folder / "checkpoint").write_text("written")
    raise Interrupted("training interrupted; checkpoint saved")


def _pool_driver(tmp_path: Path, job: str, **popen):
    """A sweep driver in a process of its own (its own session): ``run_local`` of the jobs ``quick`` and ``training``
    on two workers, with ``tests.unit.test_sweep.<job>`` as the job, each record a file ``JOB.done``; Ctrl-C exits
    130."""
    import os
    import subprocess
    import sys

    driver = (
        "import sys\n"
        "from pathlib import Path\n"
        f"from tests.unit.test_sweep import {job}\n"
        "from uncertsplat.sweep.executors import run_local\n"
        f"d = {str(tmp_path)!r}\n"
        "todo = [{'job_id': j, 'points': [], 'dir': d} for j in ('quick', 'training')]\n"
        "def record(recs):\n"
        "    Path(d, recs[0]['job'] + '.done').write_text('')\n"
        "try:\n"
        f"    run_local(todo, jobs=2, retries=0, on_records=record, run_job={job})\n"
        "except KeyboardInterrupt:\n"
        "    sys.exit(130)\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    return subprocess.Popen([sys.executable, "-c", driver], cwd=ROOT, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True, **popen)


def _pool_workers(driver: int, started_only: bool = False) -> set[int]:
    """The pool workers of the process ``driver`` (its resource tracker left out); ``started_only``: those whose
    initializer has run (it starts a thread, the sweep's stop watch)."""
    found = set()
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            ppid = int(stat.read_text(encoding="utf-8").rsplit(")", 1)[1].split()[1])
            cmdline = (stat.parent / "cmdline").read_bytes()
            threads = len(list((stat.parent / "task").iterdir()))
        except (OSError, IndexError, ValueError):
            continue  # gone meanwhile
        if ppid == driver and b"spawn_main" in cmdline and (not started_only or threads > 1):
            found.add(int(stat.parent.name))
    return found


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="finds the pool's workers in /proc (Linux)")
@pytest.mark.parametrize("moment", ["starting", "idle"])
def test_ctrl_c_lets_a_training_write_its_checkpoint_while_another_worker_is_between_jobs(tmp_path, moment):
    """Ctrl-C goes to the terminal's whole process group. A pool worker between jobs (here the fresh one that
    replaced the finished `quick` job's, still starting or idle) died of it, the pool took itself for broken and
    killed the other workers (SIGTERM), one writing its training's checkpoint after the same Ctrl-C included: the
    resume then went back to the last periodic checkpoint (about one Ctrl-C in four of a real sweep). A worker
    between jobs ignores Ctrl-C now, and starts with it blocked, so the checkpoint is written and the sweep exits
    130."""
    import os
    import signal
    import subprocess
    import sys
    import time

    from tests.fixtures import default_sigint

    proc = _pool_driver(tmp_path, "_job_checkpointing_on_ctrl_c", preexec_fn=default_sigint)

    def workers() -> set[int]:
        """The driver's pool workers; idle: those whose initializer has run."""
        return _pool_workers(proc.pid, started_only=moment == "idle")

    try:
        t0 = time.monotonic()
        # the quick job recorded, the training stepping, and the worker that replaced the quick one's started (or
        # idle: waiting for a job)
        while time.monotonic() - t0 < 60 and proc.poll() is None:
            # (a pid file is written by its job while this reads: an empty one is not there yet)
            pids = [p.read_text(encoding="utf-8").strip() if p.exists() else "" for p in
                    (tmp_path / f"{j}.pid" for j in ("quick", "training"))]
            if (tmp_path / "quick.done").exists() and all(pids) and workers() - {int(p) for p in pids}:
                break
            time.sleep(0.05)
        assert proc.poll() is None and (tmp_path / "quick.done").exists(), proc.communicate(timeout=30)[0][-3000:]
        os.killpg(proc.pid, signal.SIGINT)  # what the terminal's Ctrl-C does
        output = proc.communicate(timeout=60)[0]
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert (tmp_path / "checkpoint").exists(), f"the training was killed writing its checkpoint:\n{output[-3000:]}"
    assert proc.returncode == 130 and "BrokenProcessPool" not in output, output[-3000:]


def test_a_switch_between_the_sweeps_own_scene_and_one_of_yours_is_refused(tmp_path):
    """A sweep measured on its generated scene, then given --scene (or the reverse), reused every point as the other
    scene's: the generated scene was not recorded (a helper's audit)."""
    from uncertsplat.errors import UserError
    from uncertsplat.stages.sweep import _check_scene_inputs

    own, theirs = tmp_path / "out" / "scene", tmp_path / "mine"
    for folder in (own, theirs):
        folder.mkdir(parents=True)
        (folder / "scene.json").write_text("{}")
    _check_scene_inputs(tmp_path / "out", {None: own}, force=False, measured=False)
    _check_scene_inputs(tmp_path / "out", {None: own}, force=False, measured=True)  # the same: no word
    with pytest.raises(UserError, match=r"measured on \(moved from the scene the sweep made \(.*out/scene\) to"):
        _check_scene_inputs(tmp_path / "out", {None: theirs}, force=False, measured=True)
    _check_scene_inputs(tmp_path / "out", {None: theirs}, force=True, measured=True)  # --force: measured again
    with pytest.raises(UserError, match=r"moved from .*mine to the scene the sweep made \(.*out/scene\)"):
        _check_scene_inputs(tmp_path / "out", {None: own}, force=False, measured=True)
    # the sweep's folder moved elsewhere, its own scene with it: it goes on (a review: refused, and --force deleted
    # every run)
    _check_scene_inputs(tmp_path / "out", {None: own}, force=True, measured=True)
    (tmp_path / "out").rename(tmp_path / "moved")
    _check_scene_inputs(tmp_path / "moved", {None: tmp_path / "moved" / "scene"}, force=False, measured=True)


def test_runs_trained_inside_a_scene_folder_do_not_change_it(tmp_path):
    """A run trained into SCENE/run (or a pipeline's output there) changed the scene's fingerprint with every command,
    and the sweep refused every point on it; a file of the scene's own still counts, and the message says what does."""
    from uncertsplat.errors import UserError
    from uncertsplat.stages.sweep import _check_scene_inputs

    scene = tmp_path / "scene"
    (scene / "images").mkdir(parents=True)
    (scene / "images" / "a.png").write_bytes(b"photo")
    _check_scene_inputs(tmp_path / "out", {None: scene}, force=False, measured=False)
    run = scene / "run"
    run.mkdir()
    (run / "config.json").write_text("{}")
    (run / "train_summary.json").write_text("{}")
    (scene / "pipe" / "train").mkdir(parents=True)
    (scene / "pipe" / ".stages_started.json").write_text("{}")
    (scene / "pipe" / "train" / "weights.bin").write_bytes(b"x")
    _check_scene_inputs(tmp_path / "out", {None: scene}, force=False, measured=True)  # no word
    # nor a run's evaluation copied there (SCENE/ev) or a `select-views -o SCENE/next` (a known limit before)
    from uncertsplat.schemas.metrics import EvalReport
    from uncertsplat.schemas.select import Selection

    (scene / "ev" / "maps").mkdir(parents=True)
    EvalReport().write(scene / "ev" / "metrics.json")
    (scene / "ev" / "config.json").write_text("{}")
    (scene / "ev" / "maps" / "a_std.exr").write_bytes(b"map")
    Selection(run="r", score="s", candidates="c", num_candidates=0, chosen=[], seconds=0.0,
              seconds_per_candidate=0.0).write(scene / "next" / "selection.json")
    (scene / "next" / "selection.png").write_bytes(b"png")
    _check_scene_inputs(tmp_path / "out", {None: scene}, force=False, measured=True)  # no word
    # recorded by the version before, which left runs and stages out but counted these: the same scene
    from uncertsplat.stages.manifest import fingerprint_folder as fingerprint
    from uncertsplat.stages.sweep import SCENE_INPUTS as INPUTS
    from uncertsplat.stages.sweep import _outputs_inside

    kept = json.loads((tmp_path / "out" / INPUTS).read_text(encoding="utf-8"))
    kept[""]["fingerprint"] = fingerprint(scene, skip=[tmp_path / "out", *_outputs_inside(scene, evaluations=False)])
    (tmp_path / "out" / INPUTS).write_text(json.dumps(kept))
    _check_scene_inputs(tmp_path / "out", {None: scene}, force=False, measured=True)  # no word
    # another tool's metrics.json is a file of the scene's
    (scene / "theirs").mkdir()
    (scene / "theirs" / "config.json").write_text("{}")
    (scene / "theirs" / "metrics.json").write_text('{"accuracy": 0.9}')
    _check_scene_inputs(tmp_path / "out", {None: scene}, force=True, measured=True)
    (scene / "theirs" / "metrics.json").write_text('{"accuracy": 0.8}')
    with pytest.raises(UserError, match="files changed"):
        _check_scene_inputs(tmp_path / "out", {None: scene}, force=False, measured=True)
    _check_scene_inputs(tmp_path / "out", {None: scene}, force=True, measured=True)
    # recorded by the version before, which counted the run's files: taken as the same scene, recorded anew
    from uncertsplat.stages.manifest import fingerprint_folder
    from uncertsplat.stages.sweep import SCENE_INPUTS

    record = tmp_path / "out" / SCENE_INPUTS
    before = json.loads(record.read_text(encoding="utf-8"))
    before[""]["fingerprint"] = fingerprint_folder(scene, skip=tmp_path / "out")
    record.write_text(json.dumps(before))
    _check_scene_inputs(tmp_path / "out", {None: scene}, force=False, measured=True)
    assert json.loads(record.read_text(encoding="utf-8"))[""]["fingerprint"] != before[""]["fingerprint"]
    (scene / "images" / "a.png").write_bytes(b"another photo")
    with pytest.raises(UserError, match=r"files changed \(every file under it counts but hidden ones"):
        _check_scene_inputs(tmp_path / "out", {None: scene}, force=False, measured=True)
    # a manifest.json of a capture app's among the photos does not hide them (a review: images/ was left out whole)
    _check_scene_inputs(tmp_path / "out", {None: scene}, force=True, measured=True)
    (scene / "images" / "manifest.json").write_text('{"stage": "x", "config_hash": "y"}')
    (scene / "extra").mkdir()
    (scene / "extra" / "manifest.json").write_text('{"files": 3}')
    (scene / "extra" / "a.bin").write_bytes(b"data")
    _check_scene_inputs(tmp_path / "out", {None: scene}, force=True, measured=True)
    for changed in (scene / "images" / "a.png", scene / "extra" / "a.bin"):
        changed.write_bytes(b"changed again " + changed.name.encode())
        with pytest.raises(UserError, match="files changed"):
            _check_scene_inputs(tmp_path / "out", {None: scene}, force=False, measured=True)
        _check_scene_inputs(tmp_path / "out", {None: scene}, force=True, measured=True)


def test_a_higher_is_better_x_axis_is_maximised():
    """pareto_x = "psnr" (accepted, and drawn "higher is better") was minimised: every point came out on the front
    where the one with both the best PSNR and the best AUSE dominates the others (a helper's sweep)."""
    pts = [{"id": "default", "psnr": 19.36, "ause": 0.276}, {"id": "b", "psnr": 18.9, "ause": 0.30},
           {"id": "c", "psnr": 17.2, "ause": 0.29}]
    assert [p["id"] for p in pareto_front(pts, x="psnr", y="ause")] == ["default"]
    pts.append({"id": "d", "psnr": 16.0, "ause": 0.2})  # worse PSNR, better AUSE: on the front too
    assert [p["id"] for p in pareto_front(pts, x="psnr", y="ause")] == ["default", "d"]
    assert [p["id"] for p in pareto_front(pts, x="psnr", y="ause", maximize_x=False)] == ["d"]


def test_a_point_s_peak_memory_is_its_own():
    """Points trained one after another in one process (--jobs 1) each reported the process's peak so far (a
    1,000-Gaussian point 482 MB, 430 MB alone): the peak starts over at each point (Linux's VmHWM)."""
    import sys

    import numpy as np
    import torch

    from uncertsplat.train.trainer import peak_memory_mb, reset_peak_memory

    if not sys.platform.startswith("linux"):
        pytest.skip("the high-water mark is reset through Linux's /proc")
    cpu = torch.device("cpu")
    big = np.ones(40_000_000)  # 305 MiB touched
    big.sum()
    high = peak_memory_mb(cpu)
    del big
    reset_peak_memory(cpu)
    assert peak_memory_mb(cpu) < high - 200


def test_force_trains_a_finished_run_again_beside_it(tmp_path, monkeypatch, capsys):
    """`sweep --force` evaluated every point again but reused each finished run, so a point's training time was an
    earlier sweep's: a run finished before the forced sweep started is trained again from step 0, beside it, and put
    in its place when done; one it trained itself (a retry of a point whose evaluation failed) and an unfinished one
    (resumed) are not started over. A review of the first version: a forced sweep stopped midway had deleted the
    finished run (a later sweep without --force kept its records for models that were gone), and a run changed by
    hand was deleted instead of moved aside."""
    import time

    import uncertsplat.baselines as baselines
    from uncertsplat.config import train_config_from
    from uncertsplat.errors import Interrupted
    from uncertsplat.sweep import jobs

    calls = []

    def fake_train(scene, run_dir, cfg, device, resume):
        calls.append((Path(run_dir).name, resume))
        run_dir.mkdir(parents=True, exist_ok=True)
        (run_dir / "config.json").write_text(cfg.model_dump_json())
        if stop_training:
            raise Interrupted("training interrupted; checkpoint saved")
        (run_dir / "train_summary.json").write_text("{}")
        (run_dir / "weights.bin").write_text(f"training {len(calls)}")

    stop_training = False
    monkeypatch.setattr(baselines, "train_run", fake_train)
    monkeypatch.setattr(jobs.TrainSummary, "read", classmethod(lambda cls, path: "summary"))
    run = tmp_path / "runs" / "variational_x"
    tcfg = json.loads(train_config_from("tiny").model_dump_json())
    job = {"run_dir": str(run), "job_id": "variational_x", "scene": str(tmp_path), "train_config": tcfg}
    assert jobs._train(job, "cpu") == ("summary", True, None) and calls == [("variational_x", False)]
    assert jobs._train(job, "cpu") == ("summary", False, None)  # reused without --force
    assert jobs._train({**job, "retrain_before": None}, "cpu") == ("summary", False, None)
    forced = {**job, "retrain_before": time.time() + 1}  # the run finished before the forced sweep started
    stop_training = True  # Ctrl-C during the forced training: the finished run stands as it was
    with pytest.raises(Interrupted):
        jobs._train(forced, "cpu")
    assert (run / "weights.bin").read_text(encoding="utf-8") == "training 1" and (run / "train_summary.json").is_file()
    capsys.readouterr()
    assert jobs._train(job, "cpu") == ("summary", False, None)  # a sweep without --force reuses it, naming the leftover
    assert f"note: {run}.retrain holds a training that `sweep --force` began" in capsys.readouterr().err
    stop_training = False
    capsys.readouterr()
    fresh = run.parent / "variational_x.retrain"
    # --force again: the new training resumed, and left beside the finished run until its points are evaluated (a
    # review: put in place first, a stop during the evaluation left the old records beside the new run)
    assert jobs._train(forced, "cpu") == ("summary", True, fresh)
    assert calls[-1] == ("variational_x.retrain", True)
    assert (run / "weights.bin").read_text(encoding="utf-8") == "training 1"
    assert jobs._train(job, "cpu") == ("summary", False, None)  # (stopped there: the next sweep keeps the old run)
    assert f"{run}.retrain holds a training that `sweep --force` began and finished and was not yet evaluated" in \
        " ".join(capsys.readouterr().err.split())
    n = len(calls)  # --force again: the finished retraining is evaluated, not trained, nor called trained now
    assert jobs._train(forced, "cpu") == ("summary", False, fresh) and len(calls) == n
    jobs._swap_in(run)  # (run_job, once the points are evaluated)
    assert f"retrained: {run} (trained in variational_x.retrain" in capsys.readouterr().err
    assert (run / "weights.bin").read_text(encoding="utf-8") == f"training {len(calls)}"
    assert sorted(p.name for p in run.parent.iterdir()) == ["variational_x"]
    assert jobs._train({**job, "retrain_before": time.time() - 60}, "cpu") == ("summary", False, None)  # trained since
    (run / "train_summary.json").unlink()  # unfinished: resumed, forced or not
    assert jobs._train(forced, "cpu") == ("summary", True, None) and calls[-1] == ("variational_x", True)
    # changed by hand (train --resume --iterations N): moved aside with a note, forced or not
    (run / "config.json").write_text(json.dumps({**tcfg, "iterations": tcfg["iterations"] + 1}))
    assert jobs._train(forced, "cpu") == ("summary", True, None) and calls[-1] == ("variational_x", False)
    assert json.loads((run.parent / "variational_x.replaced" / "config.json").read_text(encoding="utf-8"))["iterations"] == \
        tcfg["iterations"] + 1
    # killed between the swap's two renames: the next sweep finishes the swap
    run.rename(run.parent / "variational_x.retrained")
    assert jobs._train(job, "cpu") == ("summary", False, None) and run.is_dir()
    assert not (run.parent / "variational_x.retrained").exists()


def _job_until_orphaned(job: dict) -> list[dict]:
    """A sweep job for the orphan test: ``quick`` returns at once; ``training`` steps until the sweep stops it
    (``train.trainer.STOP_REQUESTED``), then writes the file ``checkpoint``."""
    import os
    import time

    folder = Path(job["dir"])
    (folder / f"{job['job_id']}.pid").write_text(str(os.getpid()))
    if job["job_id"] == "quick":
        return [{"job": "quick", "status": "ok"}]
    from uncertsplat.train.trainer import STOP_REQUESTED

    t0 = time.monotonic()
    while not STOP_REQUESTED.is_set() and time.monotonic() - t0 < 120:
        time.sleep(0.02)  # a step
    (folder / "checkpoint").write_text("written" if STOP_REQUESTED.is_set() else "ran to its end")
    return [{"job": "training", "status": "ok"}]


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="finds the pool's workers in /proc (Linux)")
def test_the_workers_of_a_sweep_killed_with_sigkill_end(tmp_path):
    """A sweep killed without a word (kill -9, the OOM killer) left its pool's workers: an idle one waited for jobs
    forever, a training one trained on to its end. Each worker now sees its parent go: a training stops as on Ctrl-C
    (its checkpoint written) and every worker ends."""
    import os
    import signal
    import subprocess
    import sys
    import time

    proc = _pool_driver(tmp_path, "_job_until_orphaned")

    def workers() -> set[int]:
        return _pool_workers(proc.pid)

    def alive(pid: int) -> bool:
        try:
            state = Path(f"/proc/{pid}/stat").read_text(encoding="utf-8").rsplit(")", 1)[1].split()[0]
        except OSError:
            return False
        return state != "Z"  # (a zombie has ended; its new parent reaps it)

    try:
        t0 = time.monotonic()
        pool: set[int] = set()
        while time.monotonic() - t0 < 60 and proc.poll() is None:
            pool = workers()
            training = tmp_path / "training.pid"
            pid = training.read_text(encoding="utf-8").strip() if training.exists() else ""  # (empty while its job writes it)
            # the quick job recorded, the training stepping, and an idle worker beside it (the quick one's successor)
            if (tmp_path / "quick.done").exists() and pid and pool - {int(pid)}:
                break
            time.sleep(0.05)
        assert proc.poll() is None and (tmp_path / "quick.done").exists(), proc.communicate(timeout=30)[0][-3000:]
        assert len(pool) >= 2
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        t0 = time.monotonic()
        while time.monotonic() - t0 < 60 and any(alive(p) for p in pool):
            time.sleep(0.1)
        left = [p for p in pool if alive(p)]
    finally:
        for p in workers() | pool:
            with contextlib.suppress(OSError):
                os.kill(p, signal.SIGKILL)
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert not left, f"workers still running after the sweep was killed: {left}"
    assert (tmp_path / "checkpoint").read_text(encoding="utf-8") == "written"


def test_a_swap_killed_between_its_renames_is_finished_before_any_point_is_skipped(tmp_path, monkeypatch):
    """A forced training killed between its two renames left RUN missing beside RUN.retrain / RUN.retrained; the
    recovery ran only inside a point's training, which a sweep skips for a point with a record: the next sweep said
    "already done" with the run folder its record names gone (a review). The sweep finishes the swap for every point
    first. Since the swap comes after the retrained point's evaluation, a swap stopped half way had no records
    written: the finished run goes back beside its records and the retraining waits for the next --force (a review:
    taking it put the new run beside the old records)."""
    from uncertsplat.stages import sweep

    f, out, rec = _one_point_sweep(tmp_path, monkeypatch)
    run = Path(rec.run_dir)
    (run.parent / f"{run.name}.retrain").mkdir(parents=True)  # the new training, finished, not yet in place
    (run.parent / f"{run.name}.retrain" / "train_summary.json").write_text('{"new": 1}')
    (run.parent / f"{run.name}.retrained").mkdir()  # the old one, moved aside
    (run.parent / f"{run.name}.retrained" / "train_summary.json").write_text('{"old": 1}')
    sweep.run(f, out, device="cpu", scene=tmp_path / "scene", jobs=1)
    assert (run / "train_summary.json").is_file() and "new" not in (run / "train_summary.json").read_text()
    assert sorted(p.name for p in run.parent.iterdir()) == [run.name, f"{run.name}.retrain"]


def test_a_points_advice_is_given_in_the_sweeps_words(monkeypatch, capsys):
    """Training inside a sweep advised `--set exposure=affine`, which `sweep` refuses (its settings are
    `--set train.exposure=affine`): what training and evaluation print and a failure's error name the sweep's
    keys; the console is left as it was."""
    from uncertsplat.config import EvalConfig, TrainConfig
    from uncertsplat.console import advice_within, console
    from uncertsplat.sweep import jobs as sweep_jobs

    assert advice_within("train", TrainConfig.model_fields, "--set exposure=affine learns", "sweep") == \
        "--set train.exposure=affine learns"
    assert advice_within("evaluate", EvalConfig.model_fields, "give --num-samples 8", "sweep") == \
        "give --num-samples 8 (in this sweep: --set evaluate.num_samples)"

    def train(job, device):
        console.print("[yellow]warning:[/] photos of other exposures: --set exposure=affine learns a gain")
        console.print("[yellow]note:[/] small photos: --set scene.downscale=1 trains at about 128 px")
        raise UserError("too short: --set iterations=5000")

    monkeypatch.setattr(sweep_jobs, "_train", train)
    job = {"job_id": "j", "method_label": "m", "run_dir": "r", "device": "cpu",
           "points": [{"id": "p", "hash": "h", "knobs": {}, "is_default": True}]}
    (record,) = sweep_jobs.run_job(job)
    captured = capsys.readouterr()
    out = " ".join((captured.out + captured.err).split())
    assert "--set train.exposure=affine learns a gain" in out
    # a key a knob sets (which the sweep refuses under train.) is named as the knob
    assert "downscale = 1 (a knob of the sweep: its [default] or [axes]) trains at about 128 px" in out
    assert record["status"] == "failed" and "--set train.iterations=5000" in record["error"]
    assert console.rewrite is None


def test_a_sweep_whose_points_all_fail_names_no_figure(tmp_path, monkeypatch, capsys):
    """Every point failed: the console said it wrote pareto.png, which it had not (and an earlier sweep's figure
    there would have been shown as this one's)."""
    from uncertsplat.stages import sweep
    from uncertsplat.sweep import jobs as sweep_jobs

    def fail(job):
        return [{"id": p["id"], "hash": p["hash"], "job": job["job_id"], "method": job["method_label"],
                 "knobs": p["knobs"], "is_default": p["is_default"], "status": "failed", "stage": "train",
                 "error": "RuntimeError: diverged", "run_dir": job["run_dir"]} for p in job["points"]]

    monkeypatch.setattr(sweep_jobs, "run_job", fail)
    (tmp_path / "scene").mkdir()
    f = tmp_path / "s.toml"
    f.write_text('name = "x"\ntrain_preset = "tiny"\n[default]\niterations = 5\nnum_samples = 4\n')
    out = tmp_path / "out"
    out.mkdir()
    (out / "pareto.png").write_bytes(b"an earlier sweep's figure")
    (out / "sweep.jsonl").write_text("")  # (an earlier sweep's folder: a folder of other files is refused)
    with contextlib.suppress(UserError):  # (a sweep with failed points says so at its end)
        sweep.run(f, out, device="cpu", scene=tmp_path / "scene", jobs=1)
    said = " ".join(capsys.readouterr().err.split())
    assert "(no figure: no point was measured)" in said and "pareto.png" not in said
    assert not (out / "pareto.png").exists() and 'src="pareto.png"' not in (out / "index.html").read_text("utf-8")


def test_an_output_folder_of_other_files_or_the_scene_itself_is_refused(tmp_path, monkeypatch):
    """A folder of a user's files (a web folder with its index.html) had them replaced by the sweep's page and figure;
    the scene folder as -o took the sweep's own files for a change of the scene at the next identical run. Both are
    refused before anything is written; an earlier sweep's folder, hidden files alone, or a new folder are taken."""
    from uncertsplat.stages import sweep
    from uncertsplat.sweep import jobs as sweep_jobs

    monkeypatch.setattr(sweep_jobs, "run_job", lambda job: [])
    (tmp_path / "scene").mkdir()
    f = tmp_path / "s.toml"
    f.write_text('name = "x"\ntrain_preset = "tiny"\n[default]\niterations = 5\nnum_samples = 4\n')
    site = tmp_path / "site"
    site.mkdir()
    (site / "index.html").write_text("<h1>my page</h1>")
    with pytest.raises(UserError, match=r"not empty and holds no earlier sweep \(index.html\)"):
        sweep.run(f, site, device="cpu", scene=tmp_path / "scene", jobs=1)
    assert [p.name for p in site.iterdir()] == ["index.html"]
    assert (site / "index.html").read_text() == "<h1>my page</h1>"
    with pytest.raises(UserError, match="output folder is its scene folder") as err:
        sweep.run(f, tmp_path / "scene", device="cpu", scene=tmp_path / "scene", jobs=1)
    assert "scene_sweep" in err.value.hint and list((tmp_path / "scene").iterdir()) == []
    (tmp_path / "own").mkdir()
    own_spec = tmp_path / "own" / "spec.toml"  # (a spec kept in its sweep's folder: the sweep's own)
    own_spec.write_text(f.read_text())
    for ok in (tmp_path / "new", tmp_path / "hidden", tmp_path / "own"):
        if ok.name == "hidden":
            ok.mkdir()
            (ok / ".DS_Store").write_bytes(b"")
        if ok.name == "own":
            f = own_spec
        with contextlib.suppress(UserError):  # (no point measured: said at the end)
            sweep.run(f, ok, device="cpu", scene=tmp_path / "scene", jobs=1)
        assert (ok / "sweep.json").is_file()
        with contextlib.suppress(UserError):  # an earlier sweep's folder: taken again
            sweep.run(f, ok, device="cpu", scene=tmp_path / "scene", jobs=1)


class TestRayAddressProbe:
    """A wrong ``--address`` fails in seconds with one message: Ray's own attempt retried for minutes with a C++
    warning every few seconds (Ray 2.60: 2 minutes and 9 warnings for a port where nothing listens)."""

    @pytest.mark.parametrize("address,expected", [
        ("10.0.0.5:6379", ("10.0.0.5", 6379)), ("ray://head.lan:10001", ("head.lan", 10001)),
        ("[::1]:6379", ("::1", 6379)), ("auto", None), ("local", None), ("head.lan", None), ("head:port", None)])
    def test_host_and_port_of_an_address(self, address, expected):
        from uncertsplat.sweep.executors import _host_port

        assert _host_port(address) == expected

    def test_a_port_where_nothing_listens_is_refused_before_ray_is_called(self, monkeypatch):
        import socket

        from uncertsplat.sweep import executors

        with socket.socket() as s:  # a port just freed: nothing listens there
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        fake = types.SimpleNamespace(is_initialized=lambda: False, init=lambda **kw: pytest.fail("ray.init called"))
        monkeypatch.setattr(executors, "require_ray", lambda: fake)
        with pytest.raises(UserError, match=rf"cannot reach the Ray cluster at '127.0.0.1:{port}' \(connection "
                                            rf"refused at 127.0.0.1:{port}\)") as err:
            executors.connect_ray(f"127.0.0.1:{port}")
        assert "ray start --head" in err.value.hint

    def test_a_listening_port_and_auto_go_on_to_ray(self, monkeypatch):
        import socket

        from uncertsplat.sweep import executors

        calls = []
        fake = types.SimpleNamespace(is_initialized=lambda: False, init=lambda **kw: calls.append(kw["address"]))
        monkeypatch.setattr(executors, "require_ray", lambda: fake)
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            s.listen()
            port = s.getsockname()[1]
            assert executors.connect_ray(f"127.0.0.1:{port}") is True
        assert executors.connect_ray("auto") is True
        assert calls == [f"127.0.0.1:{port}", "auto"]

    def test_rays_value_error_is_one_message(self, monkeypatch):
        from uncertsplat.sweep import executors

        def client_missing(**kw):
            raise ValueError("Ray Client requires pip package `ray[client]`.")

        monkeypatch.setattr(executors, "require_ray", lambda: types.SimpleNamespace(is_initialized=lambda: False,
                                                                                   init=client_missing))
        monkeypatch.setattr(executors, "_probe", lambda address, timeout: None)
        with pytest.raises(UserError, match=r"Ray cannot connect to 'ray://head:10001': Ray Client requires"):
            executors.connect_ray("ray://head:10001")
        with pytest.raises(UserError, match=r"Ray cannot start on this machine: Ray Client requires"):
            executors.connect_ray(None)


def test_an_imported_model_has_no_steps_to_sweep():
    """A spec whose train settings give a model trained elsewhere (init_ply, 0 steps) and an iterations knob: said,
    not a ZeroDivisionError from the scaled schedule (the steps x knob / 0)."""
    s = spec(train={"init_ply": "m.ply", "iterations": 0})
    with pytest.raises(UserError, match="trains no step"):
        point_configs(s, s.default)
    t, _ = point_configs(s, s.default.model_copy(update={"iterations": None}))
    assert t.iterations == 0 and t.init_ply is not None
