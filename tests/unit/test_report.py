"""The HTML report: figures referenced and present, numbers equal to metrics.json, tolerant of gaps."""

from __future__ import annotations

import json
import math
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest
import torch

from uncertsplat.config import ReportConfig, TrainConfig
from uncertsplat.errors import UserError
from uncertsplat.stages import report as stage

H, W = 12, 16


# ------------------------------------------------------------------------------------------ fake runs
def _curve(rng, metric: str, steps: int = 20) -> dict:
    fr = np.arange(steps) / steps
    oracle = np.sort(rng.random(steps))[::-1] * (1 - fr)
    unc = np.maximum(oracle, np.sort(rng.random(steps))[::-1])
    ause = float(np.trapezoid(unc - oracle, fr)) if hasattr(np, "trapezoid") else float(np.trapz(unc - oracle, fr))
    return {"metric": metric, "fractions": fr.tolist(), "oracle": oracle.tolist(), "uncertainty": unc.tolist(),
            "ause": ause, "aurg": 0.1, "num_elements": H * W * 3}


def make_scene(root: Path, names: list[str], seed: int = 0) -> Path:
    from uncertsplat.io.images import write_png
    from uncertsplat.sfm.report import ReconstructReport, write_report

    rng = np.random.default_rng(seed)
    scene = root / "scene"
    for n in names:
        write_png(scene / "images" / n, rng.random((H, W, 3)).astype(np.float32))
    rep = ReconstructReport(success=True, photos=str(root / "photos"), images_found=names,
                            images_registered=names, registered_fraction=1.0, models_found=1,
                            num_points3d=123, mean_reprojection_error=0.42, inputs_fingerprint="abc123def",
                            matcher="exhaustive", total_seconds=3.5)
    write_report(scene, rep)
    return scene


def make_metrics(names: list[str], seed: int = 0, depth: bool = True) -> dict:
    from uncertsplat.eval.report_schema import EvalReport, ViewMetrics

    rng = np.random.default_rng(seed)
    per_view = {}
    for n in names:
        v = dict(psnr=float(20 + 10 * rng.random()), ssim=float(rng.random()), ause_mae=float(rng.random()),
                 ause_mse=float(rng.random()), ause_rmse=float(rng.random()), nll=float(-rng.random()),
                 nll_kde=float(rng.random()), calibration_error=float(rng.random() / 3),
                 spearman=float(rng.random()), seconds=float(rng.random()))
        if depth:
            v.update(depth_ause_mae=float(rng.random()), depth_abs_rel=float(rng.random() / 10))
        per_view[n] = ViewMetrics(**v)
    mean = ViewMetrics.mean_of(list(per_view.values()))
    curves = {}
    for key in ["mean", *names]:
        cs = {"rgb": {m: _curve(rng, m) for m in ("mae", "mse", "rmse")}}
        if depth:
            cs["depth"] = {"mae": _curve(rng, "mae")}
        curves[key] = cs
    ks = [0.5, 1.0, 1.5, 2.0, 2.5, 3.0]
    nominal = [math.erf(k / math.sqrt(2)) for k in ks]
    cal = {"rgb": {"ks": ks, "observed": [x * 0.8 for x in nominal], "nominal": nominal,
                   "calibration_error": 0.1, "num_elements": 10}}
    if depth:
        cal["depth"] = {"ks": ks, "observed": [min(1.0, x * 1.1) for x in nominal], "nominal": nominal,
                        "calibration_error": 0.05, "num_elements": 10}
    rep = EvalReport(image_names=names, per_view=per_view, mean=mean, curves=curves, calibration=cal,
                     config_hash="cfg0001", versions={"uncertsplat": "0.1.0", "torch": "2.x"}, num_samples=4,
                     seed=0, seconds_per_view=0.123456, depth_scale={"scale": 1.5, "method": "median"})
    return json.loads(rep.to_json())


def make_run(root: Path, name: str = "run", *, names=("view_000.png", "view_008.png"), seed: int = 0,
             metrics: bool = True, maps: bool = True, stats: bool = True, scene: Path | None = None,
             prune: bool = False, scene_json: bool = False) -> Path:
    """A small fake run folder following DESIGN.md section 2."""
    from uncertsplat.io.images import write_exr

    rng = np.random.default_rng(seed + 100)
    run = root / name
    run.mkdir(parents=True)
    (run / "config.json").write_text(TrainConfig(seed=seed, iterations=100).model_dump_json(indent=2))
    if scene is not None and scene_json:  # what `train` writes (io/checkpoints.load_model reads it)
        (run / "scene.json").write_text(json.dumps({"scene": str(scene), "extent": 4.4}))
    elif scene is not None:
        (run / "manifest.json").write_text(json.dumps({
            "stage": "train", "name": name, "config_hash": "c0ffee", "input_hashes": {str(scene): "f00d"},
            "config": {}, "status": "done", "started_at": 0.0, "finished_at": 12.0, "seconds": 12.0,
            "versions": {"uncertsplat": "0.1.0", "python": "3.x"}}))
    if stats:
        rows = [dict(step=s, loss=1.0 / (s + 1), l1=0.5 / (s + 1), ssim=0.2, kl_position=0.01, kl_scale=0.02,
                     num_gaussians=1000 + 10 * s, num_carriers=400 + 5 * s, sec_per_step=0.05,
                     peak_memory_mb=100.0, photo=0.3 / (s + 1), **({"eval_psnr": 20.0 + s / 10} if s % 50 == 0 else {}))
                for s in range(0, 200, 10)]
        (run / "stats.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
        (run / "train_summary.json").write_text(json.dumps({"seconds": 98.7, "num_gaussians": 1190,
                                                            "iterations": 200, "final_psnr_test": 21.5}))
    if metrics:
        (run / "eval").mkdir()
        (run / "eval" / "metrics.json").write_text(json.dumps(make_metrics(list(names), seed)))
    if maps:
        for n in names:
            mean = rng.random((H, W, 3)).astype(np.float32)
            std = (rng.random((H, W, 3)) * 0.2).astype(np.float32)
            ch = {f"rgb_mean.{c}": mean[..., i] for i, c in enumerate("RGB")}
            ch.update({f"rgb_std.{c}": std[..., i] for i, c in enumerate("RGB")})
            ch["depth_mean"] = (1 + rng.random((H, W))).astype(np.float32)
            ch["depth_std"] = (rng.random((H, W)) * 0.1).astype(np.float32)
            write_exr(run / "eval" / "maps" / f"{Path(n).stem}.exr", ch)
    if prune:
        sweep = [dict(keep_ratio=r, psnr=25 - (1 - r) * 2, random_psnr=25 - (1 - r) * 8, ssim=0.9, ause=0.3 + r / 10,
                      num_gaussians=int(1000 * r), file_size=int(250_000 * r)) for r in (1.0, 0.9, 0.7, 0.5)]
        (run / "prune.json").write_text(json.dumps({
            "counts": {"before": 1190, "after": 1071}, "score": "position_spread", "threshold": 0.42,
            "keep_ratio": 0.9, "metrics_before": {"psnr": 25.0, "ssim": 0.9, "ause_mae": 0.31},
            "metrics_after": {"psnr": 24.95, "ssim": 0.899, "ause_mae": 0.30}, "sweep": sweep}))
    return run


# ------------------------------------------------------------------------------------------ html parse
class _Page(HTMLParser):
    def __init__(self):
        super().__init__()
        self.imgs: list[str] = []
        self.cells: list[tuple[str, str, str]] = []  # (key, value, text)
        self.ids: list[str] = []
        self._cell: dict | None = None
        self.text: list[str] = []

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "img":
            self.imgs.append(a["src"])
        if "id" in a:
            self.ids.append(a["id"])
        if tag == "td" and "data-key" in a:
            self._cell = {"key": a["data-key"], "value": a["data-value"], "text": ""}

    def handle_data(self, data):
        self.text.append(data)
        if self._cell is not None:
            self._cell["text"] += data

    def handle_endtag(self, tag):
        if tag == "td" and self._cell is not None:
            self.cells.append((self._cell["key"], self._cell["value"], self._cell["text"]))
            self._cell = None


def parse(index: Path) -> _Page:
    p = _Page()
    p.feed(index.read_text(encoding="utf-8"))
    return p


def assert_figures_consistent(out: Path, page: _Page) -> None:
    for src in page.imgs:
        assert not src.startswith(("http:", "https:", "//", "/")), src
        assert (out / src).is_file(), f"missing figure {src}"
        assert (out / src).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    on_disk = {f"figures/{p.name}" for p in (out / "figures").glob("*")} if (out / "figures").is_dir() else set()
    assert on_disk == set(page.imgs), f"unreferenced or missing figures: {on_disk ^ set(page.imgs)}"


# ----------------------------------------------------------------------------------------------- tests
def test_single_run_report_has_every_section_and_exact_numbers(tmp_path):
    names = ["view_000.png", "view_008.png"]
    scene = make_scene(tmp_path, names)
    run = make_run(tmp_path, "run_a", names=tuple(names), scene=scene)
    out = tmp_path / "report"
    index = stage.run([run], out, ReportConfig())
    assert index == out / "index.html" and index.is_file()
    page = parse(index)
    assert_figures_consistent(out, page)
    for sec in ("summary", "metrics", "views", "sparsification", "calibration", "training", "provenance"):
        assert sec in page.ids, sec
    # a per-view figure per view, sparsification, calibration and timeline figures
    assert {"figures/run0_view0.png", "figures/run0_view1.png", "figures/sparsification_run0.png",
            "figures/calibration.png", "figures/timeline.png"} <= set(page.imgs)

    metrics = json.loads((run / "eval" / "metrics.json").read_text())
    mean = metrics["mean"]
    summary = [c for c in page.cells]
    # every metric of the mean and of each view appears with the exact value and its formatted text
    shown = {}
    for key, value, text in summary:
        shown.setdefault(key, []).append((value, text))
    for name, row in [("mean", mean), *metrics["per_view"].items()]:
        for key, v in row.items():
            if not isinstance(v, float):
                continue
            assert any(float(val) == v for val, _ in shown[key]), (name, key, v)
    # formatted PSNR of the mean is in the summary table
    assert any(val == repr(mean["psnr"]) and txt == f"{mean['psnr']:.2f}" for val, txt in shown["psnr"])
    assert any(float(val) == metrics["seconds_per_view"] for val, _ in shown["seconds_per_view"])
    text = " ".join(page.text)
    assert "abc123def" in text  # photos fingerprint from the reconstruct health report
    assert "0.42" in text  # reprojection error


def test_missing_inputs_give_notes_not_a_crash(tmp_path):
    run = make_run(tmp_path, "bare", metrics=False, maps=False, stats=False)
    out = tmp_path / "rep"
    index = stage.run([run], out, ReportConfig())
    page = parse(index)
    assert page.imgs == []
    assert_figures_consistent(out, page)
    html = index.read_text()
    assert "no eval/metrics.json" in html
    assert "no stats.jsonl" in html
    assert "uncertsplat evaluate" in html


def test_metrics_without_maps_and_corrupt_lines(tmp_path):
    run = make_run(tmp_path, "r", maps=False)
    with (run / "stats.jsonl").open("a") as f:
        f.write('{"step": 999, "loss": 0.1, "num_gau')  # a line cut by a crash
    index = stage.run([run], tmp_path / "out", ReportConfig())
    page = parse(index)
    assert_figures_consistent(tmp_path / "out", page)
    html = index.read_text()
    assert "no eval/maps/ folder" in html
    assert "1 unreadable line(s) skipped" in html
    assert "figures/sparsification_run0.png" in page.imgs


def test_corrupt_metrics_json_is_a_note(tmp_path):
    run = make_run(tmp_path, "r", maps=False)
    (run / "eval" / "metrics.json").write_text('{"per_view": {')
    index = stage.run([run], tmp_path / "out", ReportConfig())
    html = index.read_text()
    assert "metrics.json: could not be read" in html
    assert_figures_consistent(tmp_path / "out", parse(index))


def test_bad_run_path_names_it(tmp_path):
    good = make_run(tmp_path, "good")
    missing = tmp_path / "nope"
    with pytest.raises(UserError) as e:
        stage.run([good, missing], tmp_path / "out", ReportConfig())
    assert str(missing) in str(e.value)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(UserError) as e:
        stage.run([empty], tmp_path / "out", ReportConfig())
    assert str(empty) in str(e.value) and "not a run folder" in str(e.value)
    assert not (tmp_path / "out").exists()


def test_several_runs_side_by_side_and_pruning(tmp_path):
    names = ("view_000.png", "view_008.png")
    scene = make_scene(tmp_path, list(names))
    a = make_run(tmp_path / "x", "run", names=names, scene=scene, seed=1)
    b = make_run(tmp_path / "y", "run", names=names, scene=scene, seed=2, stats=False, prune=True, scene_json=True)
    out = tmp_path / "report"
    index = stage.run([a, b], out, ReportConfig(max_views=1))
    page = parse(index)
    assert_figures_consistent(out, page)
    assert {"compare", "prune"} <= set(page.ids)
    assert {"figures/compare_view0.png", "figures/prune_sweep_run1.png", "figures/sparsification_compare.png",
            "figures/run0_view0.png", "figures/run1_view0.png"} <= set(page.imgs)
    assert "figures/run0_view1.png" not in page.imgs  # max_views=1
    html = index.read_text()
    assert "x/run" in html and "y/run" in html  # same folder names are disambiguated
    # both runs' mean PSNRs are in the summary table, each exactly
    for r in (a, b):
        m = json.loads((r / "eval" / "metrics.json").read_text())["mean"]["psnr"]
        assert f'data-value="{m!r}"' in html
    assert 'data-key="psnr" data-value="24.95"' in html  # prune.json metrics after
    # both runs found the scene (one through the manifest, one through scene.json): GT panels, health report
    assert html.count("reconstruction health") == 2
    assert "GT image not found" not in html


def test_strings_are_escaped(tmp_path):
    run = make_run(tmp_path, 'a<b>&"c"', maps=False)
    m = json.loads((run / "eval" / "metrics.json").read_text())
    m["notes"] = ["<script>alert(1)</script>"]
    (run / "eval" / "metrics.json").write_text(json.dumps(m))
    index = stage.run([run], tmp_path / "out", ReportConfig(title="<i>t</i>"))
    html = index.read_text()
    assert "<script>" not in html and "<i>t</i>" not in html
    assert "&lt;script&gt;" in html and "a&lt;b&gt;&amp;&quot;c&quot;" in html


def test_output_folder_rules(tmp_path):
    run = make_run(tmp_path, "r", maps=False)
    busy = tmp_path / "busy"
    busy.mkdir()
    (busy / "keep.txt").write_text("mine")
    with pytest.raises(UserError, match="not empty"):
        stage.run([run], busy, ReportConfig())
    with pytest.raises(UserError, match="run folder itself"):
        stage.run([run], run, ReportConfig())
    out = tmp_path / "out"
    stage.run([run], out, ReportConfig())
    (out / "figures" / "stale.png").write_bytes(b"old")
    stage.run([run], out, ReportConfig())  # an earlier report is replaced, stale figures removed
    assert not (out / "figures" / "stale.png").exists()
    assert_figures_consistent(out, parse(out / "index.html"))


def test_cli_report(tmp_path):
    from typer.testing import CliRunner

    from uncertsplat.cli import app

    run = make_run(tmp_path, "r", maps=False, stats=False)
    res = CliRunner().invoke(app, ["report", str(run), "-o", str(tmp_path / "out")])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "out" / "index.html").is_file()
    res = CliRunner().invoke(app, ["report", str(tmp_path / "missing"), "-o", str(tmp_path / "o2")])
    assert res.exit_code == 2
    assert "missing" in res.output


def test_summary_says_how_far_the_posterior_moved(tmp_path):
    from uncertsplat.gaussians.variational import Prior, posterior_summary, random_model

    prior = Prior()
    post = posterior_summary(random_model(50, torch.Generator().manual_seed(0), prior=prior), prior)
    run = make_run(tmp_path, "r", maps=False)
    summary = json.loads((run / "train_summary.json").read_text())
    (run / "train_summary.json").write_text(json.dumps({**summary, "posterior": post}))
    old = make_run(tmp_path, "old", maps=False)  # an older summary (no carriers / other keys): no note, no crash
    s_old = json.loads((old / "train_summary.json").read_text())
    (old / "train_summary.json").write_text(json.dumps({**s_old, "posterior": {"carriers": 3, "moved_fraction": 0.5}}))
    html = stage.run([run, old], tmp_path / "out", ReportConfig()).read_text()
    assert "r (train): posterior: 0.0 % of" in html and "moved from the prior" in html
    assert "old (train): posterior" not in html


def test_metrics_section_states_the_fitted_std_scale(tmp_path):
    run = make_run(tmp_path, "r", maps=False)
    m = json.loads((run / "eval" / "metrics.json").read_text())
    m.update(std_scale=1.9034, calibration_views=[f"view_{i:03d}.png" for i in range(1, 9)])
    m["mean"]["nll_calibrated"] = -2.74
    (run / "eval" / "metrics.json").write_text(json.dumps(m))
    plain = make_run(tmp_path, "plain", maps=False)  # no std_scale: no fact, no crash
    html = stage.run([run, plain], tmp_path / "out", ReportConfig()).read_text()
    assert "x1.9, fitted on 8 training views" in html
    assert html.count("std scale (calibrated NLL)") == 1
    assert "NLL, std rescaled on train views" in html  # the summary column
