"""The HTML report: figures referenced and present, numbers equal to the files, tolerant of absent files,
explicit about invalid ones.

Every fake file is built from its schema model and written with ``.write()`` (the writers' own path), so
these tests cannot drift from what ``train``, ``evaluate`` and ``prune`` write.
"""

from __future__ import annotations

import json
import math
import re
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest
import torch

from uncertsplat.config import ReportConfig, TrainConfig
from uncertsplat.console import q
from uncertsplat.errors import UserError
from uncertsplat.io.maps import EXR_CHANNELS, map_stem
from uncertsplat.report import extract
from uncertsplat.schemas import (
    EvalReport,
    Manifest,
    PosteriorSummary,
    PruneMetrics,
    PruneReport,
    PruneSweep,
    RunScene,
    SweepPoint,
    SweepRecord,
    TrainSummary,
    ViewMetrics,
)
from uncertsplat.schemas.prune import (
    PruneCounts,
    PruneMetricSet,
    PsnrChange,
    ScoreStats,
    ToleranceChoice,
    Written,
)
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
    """A scene folder with images and a ``reconstruct_report.json`` (written as ``reconstruct`` writes it)."""
    from uncertsplat.io.images import write_png
    from uncertsplat.sfm.report import ReconstructReport, write_report

    rng = np.random.default_rng(seed)
    scene = root / "scene"
    for n in names:
        write_png(scene / "images" / n, rng.random((H, W, 3)).astype(np.float32))
    rep = ReconstructReport(success=True, photos=str(root / "photos"), images_found=names,
                            images_registered=names, registered_fraction=1.0, models_found=1,
                            num_points3d=123, mean_reprojection_error=0.42, inputs_fingerprint="abc123def",
                            matcher="exhaustive", total_seconds=3.5, mapping_agreed=False,
                            notes=["the 2 mapping runs disagree (seed 0: ...); kept seed 1"],
                            mapping_attempts=[
                                {"seed": 0, "relaxed": False, "num_images": 2, "num_points3d": 40,
                                 "num_observations": 90, "focal_lengths": {"1": 505.3}},
                                {"seed": 1, "relaxed": False, "num_images": 2, "num_points3d": 123,
                                 "num_observations": 301, "focal_lengths": {"1": 812.6}, "kept": True}])
    write_report(scene, rep)
    return scene


def make_metrics(names: list[str], seed: int = 0, depth: bool = True) -> EvalReport:
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
    return EvalReport(image_names=names, per_view=per_view, mean=mean, curves=curves, calibration=cal,
                      config_hash="cfg0001", versions={"uncertsplat": "0.1.0", "torch": "2.x"}, num_samples=4,
                      seed=0, seconds_per_view=0.123456, depth_scale={"scale": 1.5, "method": "median"})


def prune_metrics(n: int, psnr: float, ssim: float = 0.9, ause: float = 0.3, nll: float = -1.5,
                  ply: int = 1_234_567) -> PruneMetrics:
    return PruneMetrics(num_gaussians=n, num_carriers=n // 2, psnr=psnr, psnr_render=psnr + 0.03, ssim=ssim,
                        ause_mae=ause, ause_rmse=ause * 1.3, nll=nll, depth_ause_mae=None, coverage=0.98,
                        variational_ply_bytes=ply,
                        point_cloud_ply_bytes=ply // 2, seconds=1.5)


def make_prune_report(run: Path, *, n: int = 1190, sweep: bool = True) -> PruneReport:
    """What ``prune --keep-ratio 0.9 --sweep`` writes: before / after / random metrics and a 4-point sweep."""
    unpruned = prune_metrics(n, 25.0, 0.9, 0.31, -1.52, 1_234_567)
    points = []
    for r in (1.0, 0.9, 0.7, 0.5):
        removed = round(n * (1 - r)) if r > 0.5 else round(n * 0.45)  # carriers run out below 0.55
        achieved = (n - removed) / n
        points.append(SweepPoint(keep_ratio=r, num_removed=removed, keep_ratio_achieved=achieved,
                                 score=prune_metrics(n - removed, 25.0 - (1 - achieved) * 2.0),
                                 random=prune_metrics(n - removed, 25.0 - (1 - achieved) * 8.0)))
    sw = PruneSweep(ratios=[1.0, 0.9, 0.7, 0.5], score="position_spread", split="test", unpruned=unpruned,
                    points=points, tolerance_db=0.5,
                    largest_removal_within_tolerance=ToleranceChoice(
                        keep_ratio=0.9, num_removed=points[1].num_removed,
                        psnr_loss_db=25.0 - points[1].score.psnr, tolerance_db=0.5)) if sweep else None
    after = prune_metrics(1071, 24.95, 0.899, 0.30, -1.49, 1_111_000)
    rand = prune_metrics(1071, 24.21, 0.871, 0.35, -1.21, 1_111_000)
    return PruneReport(
        source_run=str(run.parent / "source"), source_model="variational.ply", source_model_sha256="ab" * 32,
        score="position_spread", score_requested="position_spread", mode="keep_ratio", threshold=None,
        keep_ratio=0.9, tolerance_db=0.5, seed=0, num_samples=4, metric_split="test",
        metric_views=["view_000.png", "view_008.png"], score_views=["view_001.png"], score_seconds=0.7,
        dry_run=False, device="cpu", notes=["only carriers can be removed: 45 % of the Gaussians at most"],
        score_stats={"position_spread": ScoreStats(min=0.01, median=0.2, max=0.97)},
        metrics=PruneMetricSet(before=unpruned, after=after, random=rand),
        counts=PruneCounts(before=n, after=1071, removed=n - 1071, carriers_before=600, carriers_after=481),
        keep_ratio_achieved=1071 / n, threshold_effective=0.4213, delta_psnr_db=PsnrChange(score=-0.05, random=-0.79),
        sweep=sw, undo="use the source run", written=Written(model=True, folder=str(run)))


def make_run(root: Path, name: str = "run", *, names=("view_000.png", "view_008.png"), seed: int = 0,
             metrics: bool = True, maps: bool = True, stats: bool = True, scene: Path | None = None,
             prune: bool = False, manifest: bool = False) -> Path:
    """A small fake run folder with the files ``train``, ``evaluate`` and ``prune`` write, built from their models."""
    from uncertsplat.io.images import write_exr, write_png

    rng = np.random.default_rng(seed + 100)
    run = root / name
    run.mkdir(parents=True)
    (run / "config.json").write_text(TrainConfig(seed=seed, iterations=100).model_dump_json(indent=2))
    if scene is not None:
        RunScene(scene=str(scene), source={"kind": "colmap", "path": str(scene)}, extent=4.4, scene_scale=1.0,
                 width=W, height=H, train=["view_001.png"], test=list(names)).write(run / "scene.json")
    if manifest:
        Manifest(stage="train", name=name, config_hash="c0ffee", input_hashes={"synth": "f00d"}, config={},
                 status="done", started_at=0.0, finished_at=12.0, seconds=12.0,
                 versions={"uncertsplat": "0.1.0", "python": "3.x"}).write(run / "manifest.json")
    if stats:
        rows = [dict(step=s, loss=1.0 / (s + 1), l1=0.5 / (s + 1), ssim=0.2, photo=0.3 / (s + 1), kl_position=0.01,
                     kl_scale=0.02, kl_total=0.03, num_gaussians=1000 + 10 * s, num_carriers=400 + 5 * s,
                     sec_per_step=0.05, elapsed=0.05 * s, peak_memory_mb=100.0,
                     **({"eval_psnr": 20.0 + s / 10, "eval_ssim": 0.8} if s % 50 == 0 else {}))
                for s in range(0, 200, 10)]
        (run / "stats.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
        TrainSummary(method="variational", variant="ours", steps=200, seconds=98.7, sec_per_step=0.49,
                     num_gaussians=1190, num_carriers=600, peak_memory_mb=100.0, device="cpu",
                     scene=str(scene), test_psnr=21.5, train_psnr=19.25,
                     warnings=["the model fits its own training views at only 19.2 dB"]).write(run / "train_summary.json")
    if metrics:
        make_metrics(list(names), seed).write(run / "eval" / "metrics.json")
    if maps:
        for n in names:
            mean = rng.random((H, W, 3)).astype(np.float32)
            std = (rng.random((H, W, 3)) * 0.2).astype(np.float32)
            arrays = [mean[..., c] for c in range(3)] + [std[..., c] for c in range(3)]
            arrays += [(1 + rng.random((H, W))).astype(np.float32), (rng.random((H, W)) * 0.1).astype(np.float32)]
            write_exr(run / "eval" / "maps" / f"{map_stem(n)}.exr", dict(zip(EXR_CHANNELS, arrays, strict=True)))
            write_png(run / "eval" / "maps" / f"{map_stem(n)}_gt.png", rng.random((H, W, 3)).astype(np.float32))
    if prune:
        make_prune_report(run).write(run / "prune.json")
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


def table_rows(html: str, table_id: str) -> dict[str, list[tuple[str, str, str]]]:
    """{row label: [(data-key, data-value, text) of each numeric cell]} of one table of the page."""
    m = re.search(rf'<table id="{re.escape(table_id)}">(.*?)</table>', html, re.S)
    assert m is not None, f"no table {table_id}"
    rows = {}
    for label, cells in re.findall(r'<tr[^>]*data-row="([^"]*)">(.*?)</tr>', m.group(1), re.S):
        rows[label] = re.findall(r'<td data-key="([^"]*)" data-value="([^"]*)">([^<]*)</td>', cells)
    return rows


# ----------------------------------------------------------------------------------------------- tests
def test_single_run_report_has_every_section_and_exact_numbers(tmp_path):
    names = ["view_000.png", "view_008.png"]
    scene = make_scene(tmp_path, names)
    run = make_run(tmp_path, "run_a", names=tuple(names), scene=scene)
    out = tmp_path / "report"
    index = stage.run(run, out)  # one folder, default config: what the end-to-end test calls
    assert index == out / "index.html" and index.is_file()
    page = parse(index)
    assert_figures_consistent(out, page)
    for sec in ("summary", "metrics", "views", "sparsification", "calibration", "training", "provenance"):
        assert sec in page.ids, sec
    assert "prune" not in page.ids  # no prune.json: no pruning section
    ids = re.findall(r'\bid="([^"]+)"', index.read_text(encoding="utf-8"))
    assert len(ids) == len(set(ids)), sorted(i for i in ids if ids.count(i) > 1)  # (the summary's table took "summary")
    # a per-view figure per view, sparsification, calibration and timeline figures
    assert {"figures/run0_view0.png", "figures/run0_view1.png", "figures/sparsification_run0.png",
            "figures/calibration.png", "figures/timeline.png"} <= set(page.imgs)

    metrics = EvalReport.read(run / "eval" / "metrics.json")
    shown: dict[str, list[tuple[str, str]]] = {}
    for key, value, text in page.cells:
        shown.setdefault(key, []).append((value, text))
    # every metric of the mean and of each view appears with the exact value and its formatted text
    for name, vm in [("mean", metrics.mean), *metrics.per_view.items()]:
        for key, v in vm.model_dump().items():
            if not isinstance(v, float):
                continue
            text = extract.format_value(v, extract.SPEC_BY_KEY[key])
            assert (repr(v), text) in shown[key], (name, key, v)
    assert any(float(val) == metrics.seconds_per_view for val, _ in shown["seconds_per_view"])
    text = " ".join(page.text)
    assert "abc123def" in text  # photos fingerprint from the reconstruct health report (via RunScene.scene)
    assert "0.42" in text  # reprojection error
    # the mapping runs, their disagreement, and train's warning about its own training views
    assert "2 (they disagreed); kept seed 1: 301 feature observations at 813 px" in text
    assert "the 2 mapping runs disagree (seed 0: ...); kept seed 1" in text
    assert "the model fits its own training views at only 19.2 dB" in text and "19.25" in text
    assert "GT image" not in text and "not found" not in text  # the GT previews were read from eval/maps


def test_missing_inputs_give_notes_not_a_crash(tmp_path, capsys):
    run = make_run(tmp_path, "bare", metrics=False, maps=False, stats=False)
    # a run stopped before its first checkpoint (no model at all): said as such, not "run evaluate" (which fails)
    index = stage.run([run], tmp_path / "rep0", ReportConfig())
    said = " ".join(capsys.readouterr().err.split())
    assert "bare: no trained model (its training stopped before its first checkpoint)" in said and "--resume" in said
    assert "no trained model (neither variational.ply nor a checkpoint in ckpts/" in " ".join(
        index.read_text(encoding="utf-8").split())
    (run / "variational.ply").write_bytes(b"")  # (its model, as far as the report looks)
    out = tmp_path / "rep"
    index = stage.run([run], out, ReportConfig())
    # the console says it too (a review's report of a run never evaluated printed only the page's path)
    said = " ".join(capsys.readouterr().err.split())
    assert "bare: not evaluated (no eval/metrics.json)" in said and f"uncertsplat evaluate {run}" in said
    page = parse(index)
    assert page.imgs == []
    assert_figures_consistent(out, page)
    html = index.read_text(encoding="utf-8")
    assert "no eval/metrics.json" in html
    assert "no stats.jsonl" in html
    assert "uncertsplat evaluate" in html
    assert "no scene.json" in html
    assert "prune" not in page.ids
    # evaluated with --split train only: said, not shown as if nothing were measured
    (run / "eval-train").mkdir()
    make_metrics(["view_001.png"]).write(run / "eval-train" / "metrics.json")
    capsys.readouterr()
    html = stage.run([run], tmp_path / "rep2", ReportConfig()).read_text(encoding="utf-8")
    assert "no eval/metrics.json (eval-train/metrics.json is another split" in " ".join(html.split())
    said = " ".join(capsys.readouterr().err.split())
    assert "bare: its only evaluation is another split's (eval-train), which the report does not show" in said
    # a pipeline's output given for a run: the runs in it are named
    import shutil

    project = tmp_path / "project"
    project.mkdir()
    shutil.copytree(run, project / "train")
    with pytest.raises(UserError, match="it holds runs") as err:
        stage.run([project], tmp_path / "rep3", ReportConfig())
    assert "train" in err.value.hint


def test_metrics_without_maps_and_corrupt_lines(tmp_path):
    run = make_run(tmp_path, "r", maps=False)
    with (run / "stats.jsonl").open("a") as f:
        f.write('{"step": 999, "loss": 0.1, "num_gau')  # a line cut by a crash
    index = stage.run([run], tmp_path / "out", ReportConfig())
    page = parse(index)
    assert_figures_consistent(tmp_path / "out", page)
    html = index.read_text(encoding="utf-8")
    assert "no eval/maps/ folder" in html
    assert "1 unreadable line(s) skipped" in html
    assert "figures/sparsification_run0.png" in page.imgs


def test_corrupt_metrics_json_is_a_note(tmp_path):
    run = make_run(tmp_path, "r", maps=False)
    (run / "eval" / "metrics.json").write_text('{"per_view": {')
    index = stage.run([run], tmp_path / "out", ReportConfig())
    html = index.read_text(encoding="utf-8")
    assert f"{run / 'eval' / 'metrics.json'}: not valid JSON" in html
    assert "figures/sparsification_run0.png" not in html
    # the calibration section says why there is no table, not that evaluate never ran
    section = html.split('id="calibration"')[1].split("<section")[0]
    assert "not valid JSON" in section and "run `uncertsplat evaluate` first" not in section
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
    # a scene folder (synth writes a scene.json too) is not a run: refused, not an empty report
    scene = tmp_path / "scene"
    (scene / "images").mkdir(parents=True)
    (scene / "scene.json").write_text('{"schema_version": 2}')
    with pytest.raises(UserError, match="this is a scene, the input of `uncertsplat train`"):
        stage.run([scene], tmp_path / "out", ReportConfig())
    assert not (tmp_path / "out").exists()


def test_several_runs_side_by_side_and_pruning(tmp_path):
    names = ("view_000.png", "view_008.png")
    scene = make_scene(tmp_path, list(names))
    a = make_run(tmp_path / "x", "run", names=names, scene=scene, seed=1, manifest=True)
    b = make_run(tmp_path / "y", "run", names=names, scene=scene, seed=2, stats=False, prune=True)
    out = tmp_path / "report"
    index = stage.run([a, b], out, ReportConfig(max_views=1))
    page = parse(index)
    assert_figures_consistent(out, page)
    assert {"compare", "prune"} <= set(page.ids)
    assert {"figures/compare_view0.png", "figures/prune_sweep_run1.png", "figures/sparsification_compare.png",
            "figures/run0_view0.png", "figures/run1_view0.png"} <= set(page.imgs)
    assert "figures/run0_view1.png" not in page.imgs  # max_views=1
    html = index.read_text(encoding="utf-8")
    assert "x/run" in html and "y/run" in html  # same folder names are disambiguated
    # both runs' mean PSNRs are in the summary table, each exactly
    for r in (a, b):
        m = EvalReport.read(r / "eval" / "metrics.json").mean.psnr
        assert f'data-value="{m!r}"' in html
    assert 'data-key="psnr" data-value="24.95"' in html  # prune.json metrics after
    assert html.count("reconstruction health") == 2  # both found the scene through RunScene.scene
    assert "input hash (synth)" in html  # the manifest's inputs in the provenance


def test_prune_section_shows_the_prune_report(tmp_path):
    """Every number of the before / after / random table and of the sweep table is the PruneReport's."""
    run = make_run(tmp_path, "pruned", stats=False, prune=True)
    rep = PruneReport.read(run / "prune.json")
    index = stage.run(run, tmp_path / "out")
    html = index.read_text(encoding="utf-8")
    page = parse(index)
    assert "prune" in page.ids and "figures/prune_sweep_run0.png" in page.imgs

    rows = table_rows(html, "prune-0")
    assert list(rows) == ["before", "after", "random removal"]
    for label, m in zip(rows, (rep.metrics.before, rep.metrics.after, rep.metrics.random), strict=True):
        expected = [(s.key, str(getattr(m, s.key)), extract.format_value(getattr(m, s.key), s))
                    for s in extract.PRUNE_SPECS]
        assert rows[label] == expected, label
    # spot-check the formats themselves, so a change of format is a deliberate one
    assert rows["after"][0][2] == "24.95" and rows["after"][1][2] == "24.98"
    assert rows["after"][5][2] == "1,071" and rows["after"][6][2] == "1.11"
    # which file each size is of: the model with its posterior, and the mean-parameter cloud viewers open
    assert rows["after"][6][0] == "variational_ply_bytes" and rows["after"][7][0] == "point_cloud_ply_bytes"
    assert {"PSNR (dB)", "SSIM", "AUSE MAE", "NLL (nats)", "Gaussians", "variational.ply (MB)",
            "point_cloud.ply without scores (MB)"} <= set(page.text)

    sweep_rows = table_rows(html, "prune-sweep-0")
    assert len(sweep_rows) == len(rep.sweep.points)
    for pt, (label, cells) in zip(rep.sweep.points, sweep_rows.items(), strict=True):
        assert label == f"{pt.keep_ratio:.3f}"
        got = {k: (v, t) for k, v, t in cells}
        assert got["keep_ratio_achieved"] == (repr(pt.keep_ratio_achieved), f"{pt.keep_ratio_achieved:.3f}")
        assert got["score.psnr"] == (repr(pt.score.psnr), f"{pt.score.psnr:.2f}")
        assert got["random.psnr"] == (repr(pt.random.psnr), f"{pt.random.psnr:.2f}")
    assert html.count("largest within tolerance") == 1

    text = " ".join(page.text)
    assert "keep_ratio" in text and "keep ratio requested" in text and "keep ratio achieved" in text
    assert f"{rep.keep_ratio_achieved:.3f}" in text
    assert "0.4213" in text  # threshold_effective
    assert "position_spread" in text
    assert rep.notes[0] in text
    assert "inside the masks" not in html
    # a masked scene (the run's evaluation says so): the prune's PSNRs are inside the masks too, and so labelled
    from uncertsplat.eval.engine import MASKED_NOTE

    m = EvalReport.read(run / "eval" / "metrics.json")
    m.notes = [f"{MASKED_NOTE}: PSNR, AUSE, NLL, calibration and Spearman are taken inside them (30% of the pixels)"]
    m.write(run / "eval" / "metrics.json")
    html = stage.run(run, tmp_path / "masked").read_text(encoding="utf-8")
    assert "<th>PSNR, inside the masks (dB)</th>" in html and "score 'position_spread', inside the masks" not in html
    assert "PSNR, inside the masks, score " in html and "(test views, inside the masks)" in html
    assert "row&#x27;s keep the source run" not in html
    # the 'after' row from evaluate of the pruned run
    from uncertsplat.schemas.prune import PRUNED_FROM_EVALUATE

    rep.notes.append(f"{PRUNED_FROM_EVALUATE} ({run / 'eval' / 'metrics.json'}: the pruned run evaluated)")
    rep.write(run / "prune.json")
    html = stage.run(run, tmp_path / "after_from_evaluate").read_text(encoding="utf-8")
    assert "row&#x27;s keep the source run" in " ".join(html.split())
    assert "threshold requested" in text and "None" not in text


def test_prune_facts_give_the_removed_share_of_the_model_before(tmp_path):
    """The facts' removed percentage is of the Gaussians before pruning: 25 of 100 is 25.0 % (of the 75 after, it
    would read 33.3 %). No other test reads the percentage."""
    from uncertsplat.report import build

    rep = make_prune_report(tmp_path / "run", sweep=False)
    rep.counts = PruneCounts(before=100, after=75, removed=25, carriers_before=60, carriers_after=35)
    facts = dict(build._prune_facts(rep))
    assert facts["Gaussians before → after"] == "100 → 75 (25 removed, 25.0 %)"
    assert facts["posterior carriers before → after"] == "60 → 35"


def test_prune_report_without_sweep_or_mask(tmp_path):
    run = make_run(tmp_path, "pruned", stats=False, metrics=False, maps=False)
    rep = make_prune_report(run, sweep=False)
    rep.metrics = PruneMetricSet(before=rep.metrics.before)
    rep.counts = rep.keep_ratio_achieved = rep.delta_psnr_db = None
    rep.write(run / "prune.json")
    index = stage.run(run, tmp_path / "out")
    html = index.read_text(encoding="utf-8")
    assert list(table_rows(html, "prune-0")) == ["before"]
    assert "No mask was chosen" in html and "No keep-ratio sweep in prune.json" in html
    assert "prune_sweep" not in html
    assert_figures_consistent(tmp_path / "out", parse(index))


def test_a_prune_folder_without_a_model_is_not_sent_to_evaluate(tmp_path):
    """prune --dry-run -o DRY writes prune.json, scores.npz and the mask but no model: `uncertsplat evaluate DRY` fails
    (no config.json), so the report does not suggest it; it says what the folder holds and gives the prune command
    that writes the model (the dry run's source, mode, score, seed and K), then evaluate of that."""
    run = make_run(tmp_path, "dry", metrics=False, maps=False, stats=False, prune=True)
    (run / "config.json").unlink()  # a dry run writes none
    rep = PruneReport.read(run / "prune.json")
    rep.dry_run, rep.written, rep.source_run, rep.seed = True, Written(model=False, folder=str(run)), \
        str(tmp_path / "run a"), 3
    rep.write(run / "prune.json")

    def text(out: str) -> str:
        return " ".join(parse(stage.run([run], tmp_path / out, ReportConfig())).text)

    shown = text("rep")
    assert f"uncertsplat evaluate {run}" not in shown and "uncertsplat evaluate RUN" not in shown
    assert f"{rep.counts.after:,} (would keep; no model written)" in shown  # (no model holds that count)
    assert ("dry: a dry-run prune (prune --dry-run): it holds prune.json, scores.npz and prune_mask.npy (the indices "
            "of the Gaussians it keeps), no model, so there is nothing to evaluate") in shown
    assert (f"prune without --dry-run, which writes it: `uncertsplat prune '{tmp_path / 'run a'}' -o NEW_RUN "
            "--keep-ratio 0.9 --score position_spread --set seed=3 --set num_samples=4`, then "
            "`uncertsplat evaluate NEW_RUN`") in shown
    # with the folder's prune_config.json, every setting that chose the mask, numbers as they were
    from uncertsplat.config import PruneConfig
    from uncertsplat.report.build import prune_again_command

    cfg = PruneConfig(threshold=0.123456789, dry_run=True, free_space_views=4, seed=3, score="free-space")
    (run / "prune_config.json").write_text(cfg.model_dump_json())
    rep.mode, rep.keep_ratio, rep.threshold = "threshold", None, 0.123456789
    rep.write(run / "prune.json")
    assert "-o NEW_RUN --threshold 0.123456789 --score position_spread --set seed=3 --set free_space_views=4`" in \
        text("cfg")
    assert prune_again_command(rep, cfg.model_dump(mode="json")).endswith("--set seed=3 --set free_space_views=4")
    (run / "prune_config.json").unlink()
    rep.mode, rep.keep_ratio, rep.threshold = "keep_ratio", 0.9, None
    rep.dry_run, rep.mode, rep.keep_ratio, rep.counts = False, "sweep", None, None  # --sweep -o OUT: no mask either
    rep.write(run / "prune.json")
    shown = text("sweep")
    assert f"uncertsplat evaluate {run}" not in shown
    assert ("a prune that measured the sweep only (prune --sweep without --keep-ratio, --threshold or --auto): it "
            "holds prune.json and scores.npz, no model") in shown
    assert "prune with --keep-ratio, --threshold or --auto (without --dry-run), which writes one" in shown


def test_invalid_prune_json_is_a_note_naming_the_file_and_key(tmp_path):
    run = make_run(tmp_path, "pruned", stats=False, maps=False)
    data = json.loads(make_prune_report(run).to_json())
    data["metrics_before_after"] = data.pop("metrics")  # a renamed key
    (run / "prune.json").write_text(json.dumps(data))
    index = stage.run(run, tmp_path / "out")
    html = index.read_text(encoding="utf-8")
    page = parse(index)
    assert "prune" in page.ids  # the section is there, with the reason instead of the numbers
    section = re.search(r'<section id="prune">(.*?)</section>', html, re.S).group(1)
    assert f"{run / 'prune.json'}" in section
    assert "key &#x27;metrics&#x27; is missing" in section
    assert "key &#x27;metrics_before_after&#x27; is not part of the schema" in section
    assert "prune-0" not in html and "prune_sweep" not in html
    assert_figures_consistent(tmp_path / "out", page)


def test_invalid_files_are_notes_not_guesses(tmp_path):
    """An invalid scene.json, train_summary.json or config.json: each named in a note, its section left out."""
    scene = make_scene(tmp_path, ["view_000.png", "view_008.png"])
    run = make_run(tmp_path, "r", maps=False, scene=scene)
    data = json.loads((run / "scene.json").read_text(encoding="utf-8"))
    data["scene_path"] = data.pop("scene")  # the report must not look under another name
    (run / "scene.json").write_text(json.dumps(data))
    (run / "train_summary.json").write_text(json.dumps({"schema_version": 99}))
    cfg = json.loads((run / "config.json").read_text(encoding="utf-8"))
    cfg["iteratoins"] = 5
    (run / "config.json").write_text(json.dumps(cfg))
    html = stage.run(run, tmp_path / "out").read_text(encoding="utf-8")
    assert "key &#x27;scene&#x27; is missing" in html and str(run / "scene.json") in html
    assert "reconstruction health" not in html  # no scene path: no guess at one
    assert "schema version 99 is newer" in html and str(run / "train_summary.json") in html
    assert f"invalid configuration in {run / 'config.json'}: iteratoins" in html


def test_exr_without_a_channel_is_a_note_naming_the_file(tmp_path):
    from uncertsplat.io.images import write_exr

    run = make_run(tmp_path, "r")
    exr = run / "eval" / "maps" / "view_000.exr"
    write_exr(exr, {"rgb_mean.R": np.zeros((H, W), np.float32)})
    html = stage.run(run, tmp_path / "out").read_text(encoding="utf-8")
    assert f"{exr}: channel(s) rgb_mean.G" in html


def test_metric_tables_name_real_schema_fields():
    from uncertsplat.report.sweep_page import COLUMNS

    fields = ViewMetrics.model_fields
    keys = [s.key for s in extract.METRIC_SPECS]
    assert len(keys) == len(set(keys))
    assert set(keys) <= set(fields), set(keys) - set(fields)
    numeric = {k for k, f in fields.items() if f.annotation != (str | None)}
    assert numeric <= set(keys), f"ViewMetrics fields without a report column: {numeric - set(keys)}"
    assert set(extract.SUMMARY_KEYS) <= set(keys)
    assert {s.key for s in extract.PRUNE_SPECS} <= set(PruneMetrics.model_fields)
    assert {k for k, _, _ in COLUMNS} <= set(SweepRecord.model_fields)


def test_strings_are_escaped(tmp_path):
    run = make_run(tmp_path, 'a<b>&"c"', maps=False)
    m = EvalReport.read(run / "eval" / "metrics.json")
    m.notes = ["<script>alert(1)</script>"]
    m.write(run / "eval" / "metrics.json")
    index = stage.run([run], tmp_path / "out", ReportConfig(title="<i>t</i>"))
    html = index.read_text(encoding="utf-8")
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
    shown = make_run(tmp_path, "shown")  # with maps: per-view figures the next report has no more
    stage.run([shown], out, ReportConfig())
    assert (out / "figures" / "run0_view0.png").is_file()
    (out / "figures" / "my_plot.png").write_bytes(b"mine")  # a file of yours beside the report's figures
    stage.run([run], out, ReportConfig())  # an earlier report is replaced, its stale figures removed
    assert not (out / "figures" / "run0_view0.png").exists()
    assert (out / "figures" / "my_plot.png").read_bytes() == b"mine"  # what report did not write is never deleted
    (out / "figures" / "my_plot.png").unlink()
    assert_figures_consistent(out, parse(out / "index.html"))
    # a report stopped before its page (Ctrl-C, a full disk) leaves its marker and figures: the same command writes
    # there again, and removes the half-written figure it listed
    from uncertsplat.report import build

    def stopped_build(runs, out_dir, title, max_views, write_bytes):
        write_bytes(out_dir / "figures" / "half.png", b"part")
        raise KeyboardInterrupt

    stopped = tmp_path / "stopped"
    original = build.build_report
    build.build_report = stopped_build
    try:
        with pytest.raises(KeyboardInterrupt):
            stage.run([run], stopped, ReportConfig())
    finally:
        build.build_report = original
    # its figures were staged apart and removed: what an earlier version left (the half-written figure it listed, in
    # place, and an atomic write's temp file) is made here
    assert not (stopped / "figures" / "half.png").exists() and not list(stopped.glob(".figures.tmp-*"))
    (stopped / "figures").mkdir()
    (stopped / "figures" / "half.png").write_bytes(b"part")
    (stopped / "figures" / ".x.tmp.png").write_bytes(b"")
    assert not (stopped / "index.html").exists()
    stage.run([run], stopped, ReportConfig())
    assert not (stopped / "figures" / "half.png").exists() and (stopped / "index.html").is_file()
    # figures alone, without the marker, are not taken for a stopped report: refused, nothing deleted
    mine = tmp_path / "mine"
    (mine / "figures").mkdir(parents=True)
    (mine / "figures" / "my_plot.png").write_bytes(b"keep")
    with pytest.raises(UserError, match="not empty"):
        stage.run([run], mine, ReportConfig())
    assert (mine / "figures" / "my_plot.png").read_bytes() == b"keep"
    (busy / "figures").mkdir()  # figures beside someone's file: still not ours
    with pytest.raises(UserError, match="not empty"):
        stage.run([run], busy, ReportConfig())
    # a folder holding only a file manager's hidden files is empty to a user (it was refused as "not empty")
    finder = tmp_path / "finder"
    finder.mkdir()
    (finder / ".DS_Store").write_bytes(b"\0")
    stage.run([run], finder, ReportConfig())
    assert (finder / "index.html").is_file() and (finder / ".DS_Store").read_bytes() == b"\0"


def test_a_run_whose_training_stopped_says_so_with_the_command_that_finishes_it(tmp_path):
    """A run stopped at step 75 of 100 showed n/a and sent the reader to `evaluate`; a finished one says nothing."""
    from uncertsplat.report.loader import load_run

    run = make_run(tmp_path, "r", maps=False, stats=False)
    (run / "ckpts").mkdir()
    (run / "ckpts" / "step_000100.pt").write_bytes(b"")
    assert not any("not finished" in n for n in load_run(run).notes)
    (run / "ckpts" / "step_000100.pt").unlink()
    (run / "ckpts" / "step_000075.pt").write_bytes(b"")
    (run / "train_summary.json").unlink(missing_ok=True)
    notes = " ".join(load_run(run).notes)
    assert "training is not finished: its newest checkpoint is step 75 of 100" in notes and "--resume" in notes


def test_notes_given_with_a_run_are_shown_with_it(tmp_path):
    """A pipeline's note on a run (a prune stage it skipped for want of a posterior) is shown with that run, given by
    its folder in any spelling, and with no other run."""
    from uncertsplat.stages import report

    a, b = make_run(tmp_path, "a", maps=False, stats=False), make_run(tmp_path, "b", maps=False, stats=False)
    index = report.run([a, b], tmp_path / "out", notes={tmp_path / "x" / ".." / "a": ["the stage 'prune' did not run"]})
    html = index.read_text(encoding="utf-8")
    assert html.count("the stage &#x27;prune&#x27; did not run") == 1
    assert "a: the stage &#x27;prune&#x27; did not run" in html


def test_cli_report(tmp_path):
    from typer.testing import CliRunner

    from uncertsplat.cli import app

    run = make_run(tmp_path, "r", maps=False, stats=False)
    res = CliRunner().invoke(app, ["report", str(run), "-o", str(tmp_path / "out"), "--set", "title=Mine"])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "out" / "index.html").is_file()
    # its config beside it, as every stage's (the README said so; nothing recorded it)
    assert json.loads((tmp_path / "out" / "report_config.json").read_text(encoding="utf-8")) == {"title": "Mine", "max_views": 6}
    res = CliRunner().invoke(app, ["report", str(run), "-o", str(tmp_path / "out")])  # a report's folder: replaced
    assert res.exit_code == 0, res.output
    res = CliRunner().invoke(app, ["report", str(tmp_path / "missing"), "-o", str(tmp_path / "o2")])
    assert res.exit_code == 2
    assert "missing" in res.output


def test_summary_says_how_far_the_posterior_moved(tmp_path):
    from uncertsplat.gaussians.variational import Prior, posterior_summary, random_model

    prior = Prior()
    post = posterior_summary(random_model(50, torch.Generator().manual_seed(0), prior=prior), prior)
    run = make_run(tmp_path, "r", maps=False)
    summary = TrainSummary.read(run / "train_summary.json")
    summary.posterior = PosteriorSummary(**post)
    summary.write(run / "train_summary.json")
    old = make_run(tmp_path, "old", maps=False)  # a summary whose posterior lacks keys: a note naming it
    s_old = json.loads((old / "train_summary.json").read_text(encoding="utf-8"))
    (old / "train_summary.json").write_text(json.dumps({**s_old, "posterior": {"carriers": 3, "moved_fraction": 0.5}}))
    html = stage.run([run, old], tmp_path / "out", ReportConfig()).read_text(encoding="utf-8")
    assert "r (train): posterior: 0.0 % of" in html and "moved from the prior" in html
    assert "old (train): posterior" not in html
    assert f"{old / 'train_summary.json'}" in html and "key &#x27;posterior.moved_kl_nats&#x27; is missing" in html


def test_metrics_section_states_the_fitted_std_scale(tmp_path):
    run = make_run(tmp_path, "r", maps=False)
    m = EvalReport.read(run / "eval" / "metrics.json")
    m.std_scale = 1.9034
    m.calibration_views = [f"view_{i:03d}.png" for i in range(1, 9)]
    m.mean.nll_calibrated = -2.74
    m.write(run / "eval" / "metrics.json")
    plain = make_run(tmp_path, "plain", maps=False)  # no std_scale: no fact, no crash
    html = stage.run([run, plain], tmp_path / "out", ReportConfig()).read_text(encoding="utf-8")
    assert "x1.9, fitted on 8 training views" in html
    assert html.count("std scale (calibrated NLL)") == 1
    assert "NLL, std rescaled" in html  # the summary column
    m.calibration_views, m.calibration_held_out = ["view_003.png", "view_010.png"], True
    m.write(run / "eval" / "metrics.json")
    html = stage.run([run], tmp_path / "out2", ReportConfig()).read_text(encoding="utf-8")
    assert "x1.9, fitted on 2 views set aside from training" in html


def test_summary_says_what_each_run_s_variance_is_made_of(tmp_path):
    """A run whose evaluation recorded ``variance_shares`` gets one sentence ranking the parts (RGB, then depth); a
    run without them (an older evaluation) none."""
    run = make_run(tmp_path, "r", maps=False)
    m = EvalReport.read(run / "eval" / "metrics.json")
    m.variance_shares = {"rgb": {"samples": 0.1, "resolution": 0.004, "pixel noise": 0.896},
                         "depth": {"samples": 0.0, "depth spread": 1.0}}
    m.write(run / "eval" / "metrics.json")
    plain = make_run(tmp_path, "plain", maps=False)
    html = stage.run([run, plain], tmp_path / "out", ReportConfig()).read_text(encoding="utf-8")
    assert ("r (evaluate): what the variance is made of on the scored pixels of its test views (each part&#x27;s "
            "share, before the std factor and the RGB std&#x27;s cap at 0.5): RGB: pixel noise 90 %, the samples&#x27; spread 10 %, resolution &lt;1 %; "
            "depth: depth spread 100 %, the samples&#x27; spread 0 %") in html
    assert "plain (evaluate): what the variance" not in html


def test_training_section_says_which_sh_bands_the_scene_kept(tmp_path):
    from uncertsplat.schemas.runs import ShBandCheck

    run = make_run(tmp_path, "r", maps=False)
    summary = TrainSummary.read(run / "train_summary.json")
    summary.sh_bands = [ShBandCheck(degree=1, step=2000, gain_db=0.31, kept=True, min_gain_db=0.05, views=8),
                        ShBandCheck(degree=2, step=3000, gain_db=0.012, kept=False, min_gain_db=0.05, views=8)]
    summary.write(run / "train_summary.json")
    html = stage.run([run], tmp_path / "out", ReportConfig()).read_text(encoding="utf-8")
    assert "SH band 1 on for one sh_degree_interval, tested at step 2000: +0.3100 dB on 8 training views (&gt;= 0.05 dB), kept" in html
    assert "SH band 2 on for one sh_degree_interval, tested at step 3000: +0.0120 dB" in html and "dropped: the model keeps degree 1" in html


def test_training_section_says_where_growth_stopped(tmp_path):
    from uncertsplat.schemas.runs import GrowthCheck

    run = make_run(tmp_path, "r", maps=False)
    summary = TrainSummary.read(run / "train_summary.json")
    summary.growth = [GrowthCheck(step=250, gaussians=16883, seen=16679, cost_db=0.018, min_gain_db=0.25,
                                  stopped=False, views=8),
                      GrowthCheck(step=500, gaussians=32156, seen=31273, cost_db=0.077, min_gain_db=0.25,
                                  stopped=True, views=8)]
    summary.write(run / "train_summary.json")
    html = stage.run([run], tmp_path / "out", ReportConfig()).read_text(encoding="utf-8")
    assert ("growth test at step 500: switching off the weakest half of the 31,273 Gaussians 8 training views see "
            "(of 32,156) costs 0.077 dB (&lt; 0.25 dB), densification stops growing the model past 32,156 Gaussians "
            "(2 growth test(s) "
            "in all)") in html
    # tests far above the threshold skipped the next one (densify.growth_skip_factor): counted
    summary.growth = [GrowthCheck(step=250, gaussians=11816, seen=11700, cost_db=0.70, min_gain_db=0.15,
                                  stopped=False, views=8, refit_steps=100, skip_next=True),
                      GrowthCheck(step=750, gaussians=55645, seen=55000, cost_db=0.76, min_gain_db=0.15,
                                  stopped=False, views=8, refit_steps=100, skip_next=True)]
    summary.write(run / "train_summary.json")
    html = stage.run([run], tmp_path / "out", ReportConfig()).read_text(encoding="utf-8")
    assert ("growth goes on (the next test skipped: the cost is far above the threshold) (2 growth test(s) in all, 2 "
            "of them far above the threshold, each skipping the next one)") in html


def test_own_page_is_replaced_anothers_is_not(tmp_path):
    """An index.html that report did not write (someone's page) is refused, with its figures/ kept."""
    run = make_run(tmp_path, "r", maps=False, stats=False)
    site = tmp_path / "site"
    (site / "figures").mkdir(parents=True)
    (site / "index.html").write_text("<html>my homepage</html>")
    (site / "figures" / "logo.png").write_bytes(b"mine")
    with pytest.raises(UserError, match="index.html is not a page `report` wrote"):
        stage.run([run], site, ReportConfig())
    assert (site / "index.html").read_text(encoding="utf-8") == "<html>my homepage</html>" and (site / "figures" / "logo.png").exists()
    out = tmp_path / "out"
    stage.run([run], out, ReportConfig(title="my title"))  # its own page, whatever the title, is replaced
    stage.run([run], out, ReportConfig())
    assert "<title>uncertsplat report</title>" in (out / "index.html").read_text(encoding="utf-8")
    # a page of the versions before the generator tag, with a title of its own, is still one of ours
    old = out / "index.html"
    old.write_text(old.read_text(encoding="utf-8").replace('<meta name="generator" content="uncertsplat report">', "")
                   .replace("<title>uncertsplat report</title>", "<title>bonsai sweep</title>"), encoding="utf-8")
    stage.run([run], out, ReportConfig())
    # a sweep's page is not a report: report -o SWEEP_OUT would replace it
    from uncertsplat.report.html import page

    sweep_out = tmp_path / "sweep"
    sweep_out.mkdir()
    (sweep_out / "index.html").write_text(page("x: sweep", "", [], "", generator="uncertsplat sweep"))
    with pytest.raises(UserError, match="index.html is not a page `report` wrote"):
        stage.run([run], sweep_out, ReportConfig())
    # ... nor one written before the tags (told by its title)
    (sweep_out / "index.html").write_text(page("uncertsplat sweep: bonsai", "", [], "").replace(
        '<meta name="generator" content="uncertsplat report">', ""))
    with pytest.raises(UserError, match="index.html is not a page `report` wrote"):
        stage.run([run], sweep_out, ReportConfig())
    # a report the user titled like a sweep is still a report
    stage.run([run], out, ReportConfig(title="uncertsplat sweep: mine"))
    stage.run([run], out, ReportConfig())


def test_an_evaluation_of_an_earlier_model_is_named(tmp_path, capsys):
    """A run trained further (train --resume) after evaluate: the report says its metrics are the earlier model's."""
    from uncertsplat.stages.evaluate import run_sha256

    run = make_run(tmp_path, "r", maps=False, stats=False)
    (run / "variational.ply").write_bytes(b"model at step 100")
    report = EvalReport.read(run / "eval" / "metrics.json")
    report.run_sha256 = run_sha256(run, run / "variational.ply")
    report.write(run / "eval" / "metrics.json")
    stage.run([run], tmp_path / "out", ReportConfig())
    assert "earlier state of the run" not in (tmp_path / "out" / "index.html").read_text(encoding="utf-8")
    (run / "variational.ply").write_bytes(b"model at step 200")
    capsys.readouterr()
    stage.run([run], tmp_path / "out", ReportConfig())
    assert "earlier state of the run" in (tmp_path / "out" / "index.html").read_text(encoding="utf-8")
    assert f"uncertsplat evaluate {q(run)}" in capsys.readouterr().err.replace("\n", "")


def test_runs_without_maps_are_left_out_of_the_side_by_side_not_the_others(tmp_path):
    """A run without eval maps (a prune --sweep output, save_maps off) among runs with them: the others are still
    compared, and the page names the one left out (it said the runs shared no view)."""
    names = ("view_000.png", "view_008.png")
    scene = make_scene(tmp_path, list(names))
    a = make_run(tmp_path / "a", "run", names=names, scene=scene, seed=1)
    b = make_run(tmp_path / "b", "run", names=names, scene=scene, seed=2)
    c = make_run(tmp_path / "c", "bare", names=names, scene=scene, seed=3, maps=False)
    out = tmp_path / "report"
    page = parse(stage.run([a, b, c], out, ReportConfig(max_views=1)))
    assert "figures/compare_view0.png" in page.imgs
    html = (out / "index.html").read_text(encoding="utf-8")
    assert "Left out, no maps: bare." in html and "share no evaluated view" not in html
    page = parse(stage.run([a, c], out, ReportConfig(max_views=1)))
    assert "figures/compare_view0.png" not in page.imgs
    assert "Fewer than two runs have uncertainty maps; side-by-side images left out (no maps: bare)." in \
        (out / "index.html").read_text(encoding="utf-8")


def _side_by_side_rows(monkeypatch) -> list[tuple[str, list[str]]]:
    """Record (view, row labels) of every side-by-side figure the report draws (still drawing it)."""
    from uncertsplat.report import figures

    drawn: list[tuple[str, list[str]]] = []
    real = figures.side_by_side_figure

    def recording(views, name):
        drawn.append((name, [label for label, _ in views]))
        return real(views, name)

    monkeypatch.setattr(figures, "side_by_side_figure", recording)
    return drawn


def _evaluated_on(run: Path, split: str) -> None:
    """Mark a fake run's evaluation as one of ``split``'s views (``evaluate --split train``)."""
    report = EvalReport.read(run / "eval" / "metrics.json")
    report.split = split
    report.write(run / "eval" / "metrics.json")


def test_a_run_evaluated_on_other_views_is_left_out_of_the_side_by_side_not_the_others(tmp_path, monkeypatch):
    """Two runs evaluated on the same test views beside one evaluated with --split train: the two are drawn
    side by side (the report said the runs shared no view and drew none), and the page names the third and
    why."""
    names = ("view_000.png", "view_008.png")
    scene = make_scene(tmp_path, [*names, "view_001.png"])
    a = make_run(tmp_path / "a", "run", names=names, scene=scene, seed=1)
    b = make_run(tmp_path / "b", "run", names=names, scene=scene, seed=2)
    c = make_run(tmp_path / "c", "run", names=("view_001.png",), scene=scene, seed=3)
    _evaluated_on(c, "train")
    drawn = _side_by_side_rows(monkeypatch)
    out = tmp_path / "report"
    page = parse(stage.run([a, b, c], out, ReportConfig()))
    assert_figures_consistent(out, page)
    assert drawn == [("view_000.png", ["a/run", "b/run"]), ("view_008.png", ["a/run", "b/run"])]
    assert {"figures/compare_view0.png", "figures/compare_view1.png"} <= set(page.imgs)
    html = (out / "index.html").read_text(encoding="utf-8")
    assert "share no evaluated view" not in html
    assert ("Left out of the side-by-side figures: c/run (its 1 train view: view_001.png; no other run with "
            "maps evaluated any of them).") in html
    assert "view_000.png across runs; not drawn: c/run (not evaluated on this view)" in html
    assert "One test view across runs." in html  # the train view is not drawn
    # runs that share no view at all are still told apart, each with the views it was evaluated on
    drawn.clear()
    page = parse(stage.run([a, c], out, ReportConfig()))
    assert drawn == [] and not any("compare_view" in src for src in page.imgs)
    assert ("The runs with maps share no evaluated view (a/run: 2 test views: view_000.png, view_008.png; "
            "c/run: 1 train view: view_001.png); side-by-side images left out.") in (
        out / "index.html").read_text(encoding="utf-8")


def test_each_side_by_side_view_holds_the_runs_that_evaluated_it(tmp_path, monkeypatch):
    """Runs sharing some views and not others: the view most runs hold comes first, then the one that draws
    runs not drawn yet, each figure with the runs that have its view (read past a run's first max_views) and
    a caption naming the others; a view another run scored as another split's says so, and unreadable maps
    are named."""
    scene = make_scene(tmp_path, ["view_000.png", "view_008.png", "view_016.png"])
    a = make_run(tmp_path / "a", "run", names=("view_000.png", "view_008.png"), scene=scene, seed=1)
    b = make_run(tmp_path / "b", "run", names=("view_000.png", "view_008.png"), scene=scene, seed=2)
    c = make_run(tmp_path / "c", "run", names=("view_008.png", "view_016.png"), scene=scene, seed=3)
    d = make_run(tmp_path / "d", "run", names=("view_016.png",), scene=scene, seed=4)
    _evaluated_on(d, "train")
    drawn = _side_by_side_rows(monkeypatch)
    out = tmp_path / "report"
    # max_views=1: the per-view section read a's and b's view_000 and c's view_008 alone; view_008 is drawn
    page = parse(stage.run([a, b, c, d], out, ReportConfig(max_views=1)))
    assert_figures_consistent(out, page)
    assert drawn == [("view_008.png", ["a/run", "b/run", "c/run"])]
    html = (out / "index.html").read_text(encoding="utf-8")
    assert "share no evaluated view" not in html
    assert ("Left out of the side-by-side figures: d/run (the views it shares with other runs, view_016.png, "
            "are past the 1 figure drawn; `report --set max_views=3` draws 3).") in html
    drawn.clear()
    page = parse(stage.run([a, b, c, d], out, ReportConfig()))
    assert_figures_consistent(out, page)
    assert drawn == [("view_008.png", ["a/run", "b/run", "c/run"]), ("view_016.png", ["c/run", "d/run"]),
                     ("view_000.png", ["a/run", "b/run"])]
    html = (out / "index.html").read_text(encoding="utf-8")
    assert "Left out of the side-by-side" not in html
    assert "view_008.png across runs; not drawn: d/run (not evaluated on this view)" in html
    assert ("view_016.png across runs; a test view of c/run; a train view of d/run; not drawn: a/run, b/run "
            "(not evaluated on this view)") in html
    assert "view_000.png across runs; not drawn: c/run, d/run (not evaluated on this view)" in html
    assert "One view across runs." in html and "each figure holds the runs that evaluated its view" in html
    # a run whose maps of a drawn view cannot be read is named in its caption, not dropped unsaid
    (b / "eval" / "maps" / f"{map_stem('view_008.png')}.exr").unlink()
    drawn.clear()
    stage.run([a, b, c, d], out, ReportConfig(max_views=1))
    assert drawn == [("view_008.png", ["a/run", "c/run"])]
    html = (out / "index.html").read_text(encoding="utf-8")
    assert re.search(r"view_008\.png across runs; not drawn: d/run \(not evaluated on this view\); b/run: "
                     r"no maps could be read \([^)]*view_008[^)]*not found\)", html)


def test_the_side_by_side_plan_covers_every_run_that_shares_a_view():
    """compare_plan: runs sharing every view keep their first views in order; disjoint pairs are both drawn;
    a view one run alone holds is never drawn; the next view is the one that draws the most runs not drawn yet,
    then the one holding the most runs, then the one listed first in the runs' order."""
    from uncertsplat.report.build import compare_plan

    assert compare_plan({0: ["v0", "v1", "v2", "v3"], 1: ["v0", "v1", "v2", "v3"]}, 3) == [
        ("v0", [0, 1]), ("v1", [0, 1]), ("v2", [0, 1])]
    assert compare_plan({0: ["v0", "v1"], 1: ["v1", "v0"], 2: ["v5"], 3: ["v5", "v9"]}, 2) == [
        ("v0", [0, 1]), ("v5", [2, 3])]
    assert compare_plan({0: ["v0"], 1: ["v1"], 2: ["v2", "v1"]}, 3) == [("v1", [1, 2])]
    assert compare_plan({0: ["v0"], 1: ["v1"]}, 3) == []
    assert compare_plan({0: ["v0", "v1"], 2: ["v1", "v0"], 5: ["v1"]}, 1) == [("v1", [0, 2, 5])]
    # runs not drawn yet come before runs in all: z draws 3 and 4, y only runs drawn already
    assert compare_plan({0: ["x", "y"], 1: ["x", "y"], 2: ["x", "y"], 3: ["z"], 4: ["z"]}, 2) == [
        ("x", [0, 1, 2]), ("z", [3, 4])]
    # as many runs not drawn yet (run 3): the view that holds more runs in all, though listed later
    assert compare_plan({0: ["p", "q", "r"], 1: ["p", "r"], 2: ["p"], 3: ["q", "r"]}, 2) == [
        ("p", [0, 1, 2]), ("r", [0, 1, 3])]
    # ties go by the runs' order, not the order of the mapping; a view listed twice by one run is one run's
    assert compare_plan({1: ["v1", "v0"], 0: ["v0", "v1"]}, 2) == [("v0", [0, 1]), ("v1", [0, 1])]
    assert compare_plan({0: ["v0", "v0"], 1: ["v1"]}, 3) == []


def _compare_html(monkeypatch, views: list[list[str]], max_views: int) -> str:
    """The "Runs side by side" section ``compare_section`` writes for runs evaluated on ``views`` (each run's test
    views, every map read), the figures not drawn: the plan's notes and captions alone."""
    from types import SimpleNamespace

    from uncertsplat.report import build

    monkeypatch.setattr(build.F, "side_by_side_figure", lambda rows, name: None)
    sections = {}
    writer = SimpleNamespace(add_figure=lambda file, fig, caption, alt: f"<figure>{caption}</figure>",
                             section=lambda key, title, html: sections.setdefault(key, html))
    runs = [SimpleNamespace(name=f"r{i}", metrics=SimpleNamespace(image_names=list(v), split="test"))
            for i, v in enumerate(views)]
    maps = SimpleNamespace(rgb_mean=np.zeros((2, 2, 3), np.float32), rgb_std=None, note="")
    build.compare_section(writer, runs, {i: {n: maps for n in v} for i, v in enumerate(views)}, max_views)
    return sections["compare"]


def test_the_side_by_side_notes_follow_the_plan(monkeypatch):
    """A run left out because the figures ran out is told to raise max_views only where max_views is below the
    figures the report draws at most (at that count, raising it draws no more); the sentence on runs evaluated
    on different views is there when one figure lacks a run, though another holds them all, and absent when
    every figure holds every run."""
    from uncertsplat.report.build import COMPARED_VIEWS

    # four pairs of runs, one view each (r0 in two): the fourth figure, r6's only shared view, is past the limit;
    # the note names the view r6 shares, not its own v9
    views = [["v0", "v3"], ["v0"], ["v1"], ["v1"], ["v2"], ["v2"], ["v9", "v3"]]
    html = _compare_html(monkeypatch, views, COMPARED_VIEWS)
    assert f"r6 (the views it shares with other runs, v3, are past the {COMPARED_VIEWS} figures drawn)" in html
    assert "max_views=" not in html
    html = _compare_html(monkeypatch, views, COMPARED_VIEWS - 1)
    assert f"figures drawn; `report --set max_views={COMPARED_VIEWS}` draws {COMPARED_VIEWS})" in html
    different = "each figure holds the runs that evaluated its view"
    assert different in _compare_html(monkeypatch, [["v0", "v1"], ["v0", "v1"], ["v0"]], COMPARED_VIEWS)
    assert different not in _compare_html(monkeypatch, [["v0", "v1"], ["v0", "v1"]], COMPARED_VIEWS)


def test_the_summary_says_plainly_when_the_std_is_too_small_or_too_large(tmp_path):
    """The calibration table's 68 % row, in one sentence (a reader had only the diagonal plot to go by)."""
    from uncertsplat.report.build import calibration_verdict

    m = make_metrics(["view_000.png"])  # observed = 0.8 x nominal: 55 % inside the 68 % interval
    text = calibration_verdict(m)
    assert text.startswith("the RGB std is too small on these views (over-confident): 55% of the errors lie inside "
                           "its central 68% interval")
    assert "calibration_holdout" not in text  # no fitted factor below 1 to warn of
    m.std_scale, m.calibration_held_out = 0.8, False
    assert ("(train with --set scene.calibration_holdout=3; in a pipeline, --set train.scene.calibration_holdout=3)"
            in calibration_verdict(m))
    m.calibration["rgb"].observed = [x * 1.0 for x in m.calibration["rgb"].nominal]
    assert calibration_verdict(m) is None
    m.calibration["rgb"].observed = [min(1.0, x * 1.2) for x in m.calibration["rgb"].nominal]
    assert "too large on these views (under-confident): 82%" in calibration_verdict(m)
    # the factor's correction claimed only where its NLL is not worse (a helper's stopped run: NLL -2.567 -> -2.526
    # beside "the std factor corrects the level")
    m.std_scale, m.mean.nll, m.mean.nll_calibrated = 0.626, -2.567, -2.526
    assert calibration_verdict(m).endswith("the std factor fitted on other views does not correct it here (its NLL is "
                                           "worse)")
    m.mean.nll_calibrated = -2.7
    m.mean.calibration_error, m.mean.calibration_error_calibrated = 0.12, 0.03
    assert calibration_verdict(m).endswith("the std factor (x0.626, NLL std rescaled) corrects the level")
    # one that moves little is not said to correct it (a helper: x0.95 took 0.085 to 0.078)
    m.mean.calibration_error, m.mean.calibration_error_calibrated = 0.085, 0.078
    assert calibration_verdict(m).endswith("the std factor (x0.626, NLL std rescaled) narrows it a little: "
                                           "calibration error 0.085 -> 0.078")
    # a factor above 1 widens a std already too wide, whatever its NLL (a helper's audit: "corrects the level")
    m.std_scale, m.mean.nll_calibrated = 1.2, -2.562
    assert calibration_verdict(m).endswith("the std factor fitted on other views (x1.2) widens it further")
    run = make_run(tmp_path, "r", maps=False, stats=False)
    stage.run([run], tmp_path / "out", ReportConfig())
    assert "over-confident" in (tmp_path / "out" / "index.html").read_text(encoding="utf-8")


def test_depth_lengths_are_shown_in_the_scenes_units(tmp_path):
    """evaluate writes depth maps and depth RMSE/MAE in the run's normalised units (x_run = s x_source + t): the
    report shows the lengths in the scene's own (x 1/s), says so, and keeps the file's number in data-value."""
    from uncertsplat.io.images import read_exr, write_exr
    from uncertsplat.io.maps import EXR_DEPTH_TO_SOURCE
    from uncertsplat.report import figures
    from uncertsplat.report.views import load_view

    names = ("view_000.png", "view_008.png")
    scene = make_scene(tmp_path, list(names))
    run = make_run(tmp_path, "r", names=names, scene=scene)
    info = RunScene.read(run / "scene.json")
    info.world_from_source = [[0.25, 0, 0, 0.1], [0, 0.25, 0, 0], [0, 0, 0.25, 0], [0, 0, 0, 1]]
    info.write(run / "scene.json")
    from uncertsplat.schemas.metrics import DepthScaleInfo

    m = EvalReport.read(run / "eval" / "metrics.json")
    for vm in [m.mean, *m.per_view.values()]:
        vm.depth_rmse, vm.depth_mae = 0.1447, 0.0786
    m.depth_scale = DepthScaleInfo(scale=1.0, method="scene", num_pixels=100)  # the scene's own GT depth
    m.write(run / "eval" / "metrics.json")
    html = stage.run([run], tmp_path / "out", ReportConfig()).read_text(encoding="utf-8")
    rmse = table_rows(html, "metrics-0")["mean"]
    cell = next(c for c in rmse if c[0] == "depth_rmse")
    assert cell == ("depth_rmse", repr(m.mean.depth_rmse), format(4 * m.mean.depth_rmse, ".4g"))  # 0.5788
    # a scene in km (a factor of 0.001): the digits are kept, where a fixed 4 decimals showed 0.0006 / 0.0003
    info.world_from_source = [[1000.0, 0, 0, 0.1], [0, 1000.0, 0, 0], [0, 0, 1000.0, 0], [0, 0, 0, 1]]
    info.write(run / "scene.json")
    km = table_rows(stage.run([run], tmp_path / "km", ReportConfig()).read_text(encoding="utf-8"), "metrics-0")["mean"]
    assert next(c for c in km if c[0] == "depth_rmse")[2] == "0.0001447"
    info.world_from_source = [[0.25, 0, 0, 0.1], [0, 0.25, 0, 0], [0, 0, 0.25, 0], [0, 0, 0, 1]]
    info.write(run / "scene.json")
    assert "Depth RMSE (scene units)" in html and "Depth MAE (scene units)" in html
    assert "normalised values x4 (1 / the scale of the scene&#x27;s world_from_source)" in html
    assert "depth scale" not in html  # the alignment is named for what it is
    # the maps: the EXR header's factor first, else the run's
    exr = run / "eval" / "maps" / f"{map_stem(names[0])}.exr"
    view = load_view(names[0], exr.parent, 4.0)
    assert view.depth_to_source == 4.0
    write_exr(exr, read_exr(exr), attributes={EXR_DEPTH_TO_SOURCE: 2.0})
    view = load_view(names[0], exr.parent, 4.0)
    assert view.depth_to_source == 2.0
    panels = {p.title: p for p in figures.view_panels(view)}
    bar = panels["depth std (scene units)"].bar
    assert bar.ticks[-1][1] == f"≥{float(np.percentile(view.depth_std * 2.0, 99)):.3g}"
    assert "depth mean (scene units)" in panels
    plain = make_run(tmp_path, "plain", names=names)  # no scene.json: the run's units, named
    m.write(plain / "eval" / "metrics.json")
    html = stage.run([plain], tmp_path / "out2", ReportConfig()).read_text(encoding="utf-8")
    assert "Depth RMSE (run&#x27;s normalised units)" in html
    # GT maps of their own units (--depth-gt, the factor fitted or given): the errors are in those units already,
    # not multiplied by the scene's factor
    m.depth_scale = DepthScaleInfo(scale=4.107, method="median", num_pixels=100)
    m.write(run / "eval" / "metrics.json")
    html = stage.run([run], tmp_path / "out3", ReportConfig()).read_text(encoding="utf-8")
    cell = next(c for c in table_rows(html, "metrics-0")["mean"] if c[0] == "depth_rmse")
    assert cell[2] == format(m.mean.depth_rmse, ".4f") and "Depth RMSE (GT maps&#x27; units)" in html
    assert "the GT maps&#x27; own: depth RMSE, MAE and NLL" in html
    m.depth_scale = DepthScaleInfo(scale=1.0, method="given-scene", num_pixels=100)  # a factor vs the scene's own GT
    m.write(run / "eval" / "metrics.json")
    html = stage.run([run], tmp_path / "out4", ReportConfig()).read_text(encoding="utf-8")
    cell = next(c for c in table_rows(html, "metrics-0")["mean"] if c[0] == "depth_rmse")
    # in the units the evaluation wrote its maps in (their header's factor, 2 above), where scene.json says 4: an
    # evaluation made after the scene folder's frame changed (aligned to metres after training) is in the folder's
    assert cell[2] == format(2 * m.mean.depth_rmse, ".4g") and "Depth RMSE (scene units)" in html


def test_timeline_speed_panel_holds_every_run(monkeypatch):
    """The seconds-per-step panel's limits are set after all runs are drawn (set in the loop, the first run's range
    froze the top and a slower run's line left the panel)."""
    from uncertsplat.report import figures

    monkeypatch.setattr(figures, "_png", lambda fig: fig)  # the figure itself, to read its axes
    fast = [dict(step=s, sec_per_step=0.05) for s in range(0, 100, 10)]
    slow = [dict(step=s, sec_per_step=5.0) for s in range(0, 100, 10)]
    fig = figures.timeline_figure([("fast", fast), ("slow", slow)])
    ax = next(a for a in fig.axes if a.get_title() == "seconds per step")
    bottom, top = ax.get_ylim()
    assert bottom == 0 and top >= 5.0


def test_summary_names_each_runs_scene_and_resolution_and_warns_when_they_differ(tmp_path):
    """A run trained at 16x12 (--preset paper) beside runs at 128x96, or on another scene: the summary shows each run's
    scene and training resolution and says the metrics are not comparable."""
    names = ("view_000.png", "view_008.png")
    scene = make_scene(tmp_path, list(names))
    a = make_run(tmp_path / "a", "run", names=names, scene=scene, maps=False, stats=False)
    b = make_run(tmp_path / "b", "run", names=names, scene=scene, maps=False, stats=False, seed=1)
    html = stage.run([a, b], tmp_path / "same", ReportConfig()).read_text(encoding="utf-8")
    rows = re.findall(r'<tr[^>]*data-row="([^"]*)"><td class="text">[^<]*</td><td class="text">([^<]*)</td>'
                      r'<td>([^<]*)</td>', html)
    assert rows[:2] == [("a/run", scene.name, f"{W}x{H}"), ("b/run", scene.name, f"{W}x{H}")]
    assert "These runs were trained" not in html
    info = RunScene.read(b / "scene.json")
    info.width, info.height = 2 * W, 2 * H
    info.write(b / "scene.json")
    html = stage.run([a, b], tmp_path / "res", ReportConfig()).read_text(encoding="utf-8")
    assert (f"These runs were trained at different resolutions (a/run: {W}x{H}, b/run: {2 * W}x{2 * H}): their "
            "metrics are not comparable") in html
    other = make_scene(tmp_path / "elsewhere", list(names))
    info.scene, info.width, info.height = str(other), W, H
    info.write(b / "scene.json")
    html = stage.run([a, b], tmp_path / "scn", ReportConfig()).read_text(encoding="utf-8")
    assert f"These runs were trained on different scenes (a/run: {scene}, b/run: {other}): their" in html


def test_summary_warns_when_the_runs_were_scored_on_different_views(tmp_path):
    """One run evaluated with --set max_views=1 beside one evaluated in full: their means are over different views,
    and the summary says which run was scored on which (and how many) views; runs scored on the same views (in any
    order) get no such note."""
    names = ("view_000.png", "view_008.png", "view_016.png")
    scene = make_scene(tmp_path, list(names))
    one = make_run(tmp_path / "e", "run", names=names[:1], scene=scene, maps=False, stats=False)
    full = make_run(tmp_path / "f", "run", names=names, scene=scene, maps=False, stats=False, seed=1)
    html = stage.run([one, full], tmp_path / "rep", ReportConfig()).read_text(encoding="utf-8")
    assert ("These runs were scored on different views (e/run: 1 test view: view_000.png; f/run: 3 test views: "
            "view_000.png, view_008.png, view_016.png)") in html
    assert "These runs were trained" not in html  # same scene, same resolution
    # the same views, listed in another order
    same = make_run(tmp_path / "g", "run", names=tuple(reversed(names)), scene=scene, maps=False, stats=False)
    html = stage.run([full, same], tmp_path / "same", ReportConfig()).read_text(encoding="utf-8")
    assert "scored on different views" not in html


def test_psnr_inside_the_masks_is_labelled_so(tmp_path):
    """On a masked scene evaluate's PSNR is inside the masks while train's test_psnr is over whole images: the columns
    say which (the header when every run is masked, a mark on the masked runs' cells otherwise)."""
    from uncertsplat.eval.engine import MASKED_NOTE

    masked = make_run(tmp_path, "masked", maps=False)
    m = EvalReport.read(masked / "eval" / "metrics.json")
    m.mean.psnr_render = 19.06
    m.notes = [f"{MASKED_NOTE}: PSNR, AUSE, NLL, calibration and Spearman are taken inside them (30% of the pixels)"]
    m.write(masked / "eval" / "metrics.json")
    html = stage.run([masked], tmp_path / "one", ReportConfig()).read_text(encoding="utf-8")
    assert "<th>PSNR, expected render, inside the masks (dB)</th>" in html
    assert "<th>PSNR, inside the masks (dB)</th>" in html
    assert "test_psnr is over whole images" in html
    plain = make_run(tmp_path, "plain", maps=False)
    html = stage.run([masked, plain], tmp_path / "two", ReportConfig()).read_text(encoding="utf-8")
    assert "<th>PSNR, expected render (dB) †: inside the masks</th>" in html
    row = table_rows(html, "summary-table")
    assert next(t for k, _, t in row["masked"] if k == "psnr_render") == "19.06 †"
    assert all(not t.endswith("†") for _, _, t in row["plain"])
    html = stage.run([plain], tmp_path / "none", ReportConfig()).read_text(encoding="utf-8")
    assert "inside the masks" not in html and "test_psnr is over whole images" not in html
    # masks the run trained with (the photos' own): train's test_psnr is inside them too, so no such note
    from uncertsplat.eval.engine import PHOTO_MASKS_NOTE

    m.notes = [f"{MASKED_NOTE}: PSNR, AUSE, NLL, calibration and Spearman are taken inside them (30% of the pixels), "
               f"as train's held-out PSNR and SSIM; {PHOTO_MASKS_NOTE}, whose black pixels training left out too"]
    m.write(masked / "eval" / "metrics.json")
    html = stage.run([masked], tmp_path / "own", ReportConfig()).read_text(encoding="utf-8")
    assert "<th>PSNR, inside the masks (dB)</th>" in html and "test_psnr is over whole images" not in html


def test_an_automatic_prune_says_its_ratio_and_score_were_chosen(tmp_path):
    """prune --auto writes keep_ratio (the one it chose) with mode "auto": not a ratio the user requested."""
    run = make_run(tmp_path, "auto", stats=False, maps=False, prune=True)
    rep = PruneReport.read(run / "prune.json")
    rep.mode, rep.keep_ratio, rep.score, rep.score_requested, rep.tolerance_db = "auto", 0.7, "gate", "auto", 0.1
    rep.notes = ["score auto: the score that removes the most within 0.1 dB of the held-out PSNR is used, 'gate'"]
    rep.write(run / "prune.json")
    text = " ".join(parse(stage.run(run, tmp_path / "out")).text)
    assert "keep ratio requested" not in text
    assert "0.700, chosen automatically (prune --auto): the largest removal whose held-out PSNR of the expected " \
           "render stays within 0.1 dB of the unpruned model's" in text
    assert "gate (chosen automatically by --score auto: the note below says how)" in text
    assert "requested: auto" not in text
    rep.mode, rep.notes = "keep_ratio", []  # --keep-ratio --sweep: score auto took its default, measured no other
    rep.write(run / "prune.json")
    text = " ".join(parse(stage.run(run, tmp_path / "out")).text)
    assert "keep ratio requested" in text and "prune --auto" not in text
    assert "gate (the default --score auto takes for this run; no other score was measured)" in text


def test_a_prune_note_that_its_before_row_is_evaluates_is_checked_against_the_evaluation_now(tmp_path):
    """prune read its 'before' row's uncertainty metrics from the source run's eval/metrics.json and says so; the source
    evaluated again since (evaluate SOURCE --num-samples 10 --seed 3): the Summary shows the new evaluation, the table
    the old one, and the report says which settings each used instead of the claim that no longer holds."""
    from uncertsplat.stages.prune import METRIC_KEYS, UNPRUNED_FROM_EVALUATE

    names = ("view_000.png", "view_008.png")
    source = make_run(tmp_path, "source", names=names, maps=False, stats=False)
    pruned = make_run(tmp_path, "pruned", names=names, maps=False, stats=False, prune=True)
    m = EvalReport.read(source / "eval" / "metrics.json")
    rep = PruneReport.read(pruned / "prune.json")
    claim = (f"{UNPRUNED_FROM_EVALUATE} ({source / 'eval' / 'metrics.json'}: the same model file, views, settings and "
             "versions)")
    rep.notes.append(claim)
    rep.metrics.before = rep.metrics.before.model_copy(update={k: getattr(m.mean, k) for k in METRIC_KEYS})
    rep.write(pruned / "prune.json")

    def text(out: str, runs=(source, pruned)) -> str:
        return " ".join(parse(stage.run(list(runs), tmp_path / out, ReportConfig())).text)

    assert claim in text("same") and "when prune ran" not in text("same2")  # the file prune read, unchanged
    # the project copied elsewhere: the note names the copy's file, not the old place's
    import shutil

    moved = tmp_path / "copied"
    moved.mkdir()
    for r in (source, pruned):
        shutil.copytree(r, moved / r.name)
    from uncertsplat.provenance import file_sha256

    (moved / "source" / "variational.ply").write_bytes(b"the model prune read")
    rep_moved = PruneReport.read(moved / "pruned" / "prune.json")
    rep_moved.source_from_run, rep_moved.source_model = "../source", "variational.ply"
    rep_moved.source_model_sha256 = file_sha256(moved / "source" / "variational.ply")
    rep_moved.write(moved / "pruned" / "prune.json")
    shown = text("report_of_the_copy", (moved / "source", moved / "pruned"))
    assert f"{UNPRUNED_FROM_EVALUATE} ({moved / 'source' / 'eval' / 'metrics.json'}: the same model file" in shown
    assert str(source / "eval" / "metrics.json") not in shown
    m.num_samples, m.seed = 10, 3
    m.mean.psnr += 0.5
    m.write(source / "eval" / "metrics.json")
    then = (f"the 'before' row's uncertainty metrics were read from {source / 'eval' / 'metrics.json'} when prune ran, "
            "an evaluation with K = 4, seed 0, 2 test views on cpu; that file now holds another evaluation")
    shown = text("again")
    assert claim not in shown
    assert (then + ", with K = 10, seed 3, 2 test views: the Summary and Metrics for source show the new one, this "
            "table's 'before' row the one prune read") in shown
    assert then + ", with K = 10, seed 3, 2 test views: this table's 'before' row is the one prune read" in text(
        "alone", [pruned])  # the source not in the report
    m.num_samples, m.seed = 4, 0  # prune's settings, other numbers (the source trained again, say)
    m.write(source / "eval" / "metrics.json")
    assert then + " with the same settings and other means (psnr: another model file" in text("retrained")
    m.num_samples = 10  # a 'before' row prune measured itself (no claim) beside a source evaluated at another K
    m.write(source / "eval" / "metrics.json")
    rep.notes.remove(claim)
    rep.write(pruned / "prune.json")
    assert ("the Summary's row for source (the source run) is evaluate's, with K = 10, seed 0, 2 test views; this "
            "table's 'before' row was measured by prune, with K = 4, seed 0, 2 test views on cpu") in text("measured")
    rep.notes.append(claim)
    rep.write(pruned / "prune.json")
    (source / "eval" / "metrics.json").unlink()
    assert "when prune ran, an evaluation with K = 4, seed 0, 2 test views on cpu; that file is gone" in text("gone")


def test_colour_bars_say_where_they_clip_and_what_they_measure():
    """The error / std / depth colour bars end at percentiles: an end with pixels beyond it reads ≥ (≤), as an extended
    colour bar would; one without reads the plain number. The panels name their units."""
    from uncertsplat.report import figures
    from uncertsplat.report.views import ViewMaps

    rng = np.random.default_rng(0)
    err = rng.random((H, W)) * 0.1
    err[0, 0] = 0.9  # one bright pixel past the 99th percentile
    view = ViewMaps("v", rgb_std=np.full((H, W, 3), 0.05), error=err, depth_mean=1 + rng.random((H, W)),
                    depth_std=np.full((H, W), 0.2))
    panels = {p.title: p for p in figures.view_panels(view)}
    assert panels["|error| (colour, 0-1)"].bar.ticks[-1][1].startswith("≥")
    assert panels["RGB std (colour, 0-1)"].bar is panels["|error| (colour, 0-1)"].bar  # one shared scale
    depth = panels["depth mean (run's normalised units)"].bar.ticks
    assert depth[0][1].startswith("≤") and depth[-1][1].startswith("≥")
    assert panels["depth std (run's normalised units)"].bar.ticks[-1][1] == "0.2"  # a constant map: nothing clipped


def test_the_error_and_std_panels_share_a_scale_that_holds_both():
    """The shared |error| / RGB std scale is taken over both maps: a std above every error (0.1 and 0.2 against
    0.05) tops the bar at 0.2, unclipped, and its two values keep two colours (a scale from the error alone
    drew the whole std panel in the top colour)."""
    from uncertsplat.report import figures
    from uncertsplat.report.views import ViewMaps

    std = np.full((H, W, 3), 0.2)
    std[: H // 2] = 0.1
    view = ViewMaps("v", rgb_std=std, error=np.full((H, W), 0.05))
    panels = {p.title: p for p in figures.view_panels(view)}
    error, spread = panels["|error| (colour, 0-1)"], panels["RGB std (colour, 0-1)"]
    assert spread.bar is error.bar and error.bar.ticks[-1][1] == "0.2"
    assert len({tuple(p) for p in spread.image.reshape(-1, 3)}) == 2
    assert len({tuple(p) for p in error.image.reshape(-1, 3)}) == 1


def test_depth_panels_draw_pixels_without_a_surface_grey_and_leave_them_out_of_the_colour_scale(tmp_path):
    """A transparent scene's background holds no surface: its depth 0 is not a distance. The depth mean and std panels
    draw such pixels (depth 0, or a mean opacity below 0.5 where the maps carry alpha.A) in a neutral grey, and their
    colour bars are the surface's percentiles (the depth mean's no longer starts at 0)."""
    from uncertsplat.io.images import write_exr
    from uncertsplat.report import figures
    from uncertsplat.report.views import load_view

    rng = np.random.default_rng(0)
    depth = (2 + rng.random((H, W))).astype(np.float32)  # [H,W] surfaces 2-3 units away
    std = np.full((H, W), 0.1, np.float32)
    alpha = np.ones((H, W), np.float32)
    depth[:, : W // 2], std[:, : W // 2], alpha[:, : W // 2] = 0.0, 0.0, 0.0  # the left half: the background
    alpha[0, -1], std[0, -1] = 0.2, 5.0  # a faint pixel: a depth, mostly the empty ray's, and a wide spread
    rgb = [np.full((H, W), 0.5, np.float32)] * 6
    channels = {**dict(zip(EXR_CHANNELS, [*rgb, depth, std], strict=True)), "alpha.A": alpha}
    write_exr(tmp_path / "maps" / f"{map_stem('v.png')}.exr", channels)
    view = load_view("v.png", tmp_path / "maps")
    assert view.alpha is not None and int(view.no_surface.sum()) == H * (W // 2) + 1
    panels = {p.title: p for p in figures.view_panels(view)}
    mean, spread = panels["depth mean (run's normalised units)"], panels["depth std (run's normalised units)"]
    surface = np.delete(depth[:, W // 2:].reshape(-1), W // 2 - 1)  # the surface pixels (not the faint one)
    assert mean.bar.ticks[0][1] == f"≤{float(np.percentile(surface, 1)):.3g}"  # not 0
    assert spread.bar.ticks[-1][1] == "0.1"  # the surface's spread: not the faint pixel's 5
    for panel in (mean, spread):
        grey = (panel.image == np.array(figures.NO_SURFACE_RGB, np.uint8)).all(axis=-1)  # [H,W]
        assert (grey == view.no_surface).all()
    # maps written before alpha.A: depth 0 alone says there is no surface
    view.alpha = None
    assert int(view.no_surface.sum()) == H * (W // 2)


def test_units_and_terms_are_said_once(tmp_path):
    """NLL headers say nats; AUSE and 'carriers' are explained once; an unavailable LPIPS is listed once (with its
    reason), not again among the metrics not available."""
    from uncertsplat.schemas.metrics import LpipsStatus

    run = make_run(tmp_path, "r", maps=False)
    m = EvalReport.read(run / "eval" / "metrics.json")
    m.lpips = LpipsStatus(available=False, reason="unavailable: no local weights")
    m.write(run / "eval" / "metrics.json")
    html = stage.run([run], tmp_path / "out", ReportConfig()).read_text(encoding="utf-8")
    assert "<th>NLL (nats)</th>" in html and "<th>NLL (KDE, nats)</th>" in html
    assert "<th>NLL</th>" not in html
    assert html.count("area under the sparsification error") == 1
    assert html.count("the Gaussians that carry a posterior") == 1
    facts = html[html.index('<section id="metrics">'):html.index('<section id="views">')]
    assert facts.count("LPIPS") == 1 and "unavailable: no local weights" in facts


def test_a_model_without_a_posterior_reads_consistently(tmp_path):
    """A deterministic run: evaluate's note says the samples' spread is 0, so the 'std =' formula says so at its
    spread term; train's 'test_render: expected render (variational...)' is not shown for a model without carriers."""
    run = make_run(tmp_path, "det", maps=False)
    m = EvalReport.read(run / "eval" / "metrics.json")
    m.notes = ["deterministic model: every sample is the same render, so the samples' spread is 0 everywhere; the std "
               "holds the predictive's other terms (the 'std =' note lists them)",
               "std = the spread of the K samples + the pixel noise of the Gaussians on the training views"]
    m.write(run / "eval" / "metrics.json")
    summary = TrainSummary.read(run / "train_summary.json")
    summary.method, summary.num_carriers = "deterministic", 0
    summary.test_render = "expected render (variational.expected_render_sample)"
    summary.write(run / "train_summary.json")
    html = stage.run([run], tmp_path / "out", ReportConfig()).read_text(encoding="utf-8")
    # an evaluation written before the formula said its terms are variances: shown in today's words
    assert ("std² = the variance of the K samples (0 for this model: every sample is the same render) + the pixel "
            "noise" in html) and "std = the spread" not in html
    assert "expected_render_sample" not in html
    summary.members = [summary.model_copy()]  # nor in an ensemble's members (the "more" dump)
    summary.write(run / "train_summary.json")
    assert "expected_render_sample" not in stage.run([run], tmp_path / "ens", ReportConfig()).read_text(encoding="utf-8")
    summary.members = []
    summary.method, summary.num_carriers = "variational", 600  # a model with a posterior keeps both as they are
    summary.write(run / "train_summary.json")
    m.notes = m.notes[1:]
    m.write(run / "eval" / "metrics.json")
    html = stage.run([run], tmp_path / "out2", ReportConfig()).read_text(encoding="utf-8")
    assert "std² = the variance of the K samples + the pixel noise" in html and "expected_render_sample" in html


def test_an_ensemble_says_its_count_is_the_members_sum_and_draws_their_timelines(tmp_path, monkeypatch):
    """An ensemble's num_gaussians sums its members': shown so; its timeline is in members/*/stats.jsonl, drawn from
    there (the report said 'no stats.jsonl')."""
    from uncertsplat.report import figures

    run = make_run(tmp_path, "ens", maps=False)
    summary = TrainSummary.read(run / "train_summary.json")
    summary.method, summary.ensemble_size, summary.num_gaussians = "ensemble", 2, 30526
    summary.write(run / "train_summary.json")
    log = (run / "stats.jsonl").read_text(encoding="utf-8")
    (run / "stats.jsonl").unlink()  # an ensemble run has none of its own
    for i in range(2):
        (run / "members" / f"member_{i}").mkdir(parents=True)
        (run / "members" / f"member_{i}" / "stats.jsonl").write_text(log)
    drawn = []
    real = figures.timeline_figure
    monkeypatch.setattr(figures, "timeline_figure", lambda per_run: drawn.append(per_run) or real(per_run))
    html = stage.run([run], tmp_path / "out", ReportConfig()).read_text(encoding="utf-8")
    cell = next(t for k, _, t in table_rows(html, "summary-table")["ens"] if k == "num_gaussians")
    assert cell == "30,526 over 2 members"
    assert "30526 (the sum over 2 members)" in html
    assert "no stats.jsonl" not in html
    assert [label for label, _ in drawn[0]] == ["ens members/member_0", "ens members/member_1"]
    assert "figures/timeline.png" in parse(tmp_path / "out" / "index.html").imgs


def test_runs_evaluated_with_different_k_are_said_to_be_so(tmp_path):
    """A run of K = 1 beside one of K = 4 was ranked without a word; now a note names each run's K."""
    a, b = make_run(tmp_path, "a", maps=False), make_run(tmp_path, "b", maps=False, seed=1)
    html = stage.run([a, b], tmp_path / "same", ReportConfig()).read_text(encoding="utf-8")
    assert "different numbers of samples" not in html
    m = EvalReport.read(b / "eval" / "metrics.json")
    m.num_samples = 1
    m.write(b / "eval" / "metrics.json")
    html = stage.run([a, b], tmp_path / "other", ReportConfig()).read_text(encoding="utf-8")
    assert "These runs were evaluated with different numbers of samples (a: K = 4; b: K = 1)" in html


def test_an_ensemble_stopped_before_its_last_member_says_so_and_not_evaluate(tmp_path):
    """Ctrl-C during member 2 of 3: no train_summary.json of the run, members 0 and 1 trained. The page told the reader
    to run `evaluate`, which refuses an ensemble with a member unfinished; now it says 2 of 3 members are trained and
    gives the command that trains the others."""
    run = make_run(tmp_path, "ens", maps=False, metrics=False)
    cfg = TrainConfig(seed=0, iterations=100, method="ensemble", ensemble_size=3)
    (run / "config.json").write_text(cfg.model_dump_json(indent=2))
    summary = (run / "train_summary.json").read_text(encoding="utf-8")
    (run / "train_summary.json").unlink()
    for i in range(3):
        (run / "members" / f"member_{i}").mkdir(parents=True)
        if i < 2:
            (run / "members" / f"member_{i}" / "train_summary.json").write_text(summary)
    html = stage.run([run], tmp_path / "out", ReportConfig()).read_text(encoding="utf-8")
    assert "training is not finished: 2 of the ensemble&#x27;s 3 members are trained" in html or \
        "training is not finished: 2 of the ensemble's 3 members are trained" in html
    from html import escape

    assert f"-o {escape(q(run))} --method ensemble --resume" in html
    assert "1 of the ensemble" in html and f"run `uncertsplat evaluate {escape(q(run))}` to measure" not in html
    (run / "members" / "member_2" / "train_summary.json").write_text(summary)  # the last member done, no run summary
    html = stage.run([run], tmp_path / "out2", ReportConfig()).read_text(encoding="utf-8")
    assert "members are trained" not in html


def test_shown_differences_agree_with_the_shown_numbers(tmp_path):
    """A PSNR change beside 22.66 -> 22.51 reads -0.15, not the stored -0.155 rounded to -0.16; evaluate's warning that
    the std factor worsens the NLL is not shown for 0.003 nats (older files wrote it for any difference)."""
    run = make_run(tmp_path, "pruned", stats=False, maps=False, prune=True)
    rep = PruneReport.read(run / "prune.json")
    rep.metrics.before.psnr, rep.metrics.after.psnr, rep.metrics.random.psnr = 22.662, 22.507, 21.0
    rep.delta_psnr_db = PsnrChange(score=-0.155, random=-1.662)
    rep.write(run / "prune.json")
    m = EvalReport.read(run / "eval" / "metrics.json")
    m.mean.nll, m.mean.nll_calibrated = -1.6164, -1.6135
    m.notes = ["the std factor rests on 2 views only, too few to trust; the fitted factor makes these views' NLL worse "
               "than the raw std does (they differ from the views it was fitted on): read the raw numbers"]
    m.write(run / "eval" / "metrics.json")
    html = stage.run(run, tmp_path / "out").read_text(encoding="utf-8")
    assert "-0.15 dB (22.66 → 22.51) by the score, -1.66 dB (22.66 → 21.00) by random removal" in html
    assert "NLL worse" not in html and "the std factor rests on 2 views only, too few to trust" in html
    m.mean.nll_calibrated = -1.50  # 0.116 nats worse: said
    m.write(run / "eval" / "metrics.json")
    assert "NLL worse" in stage.run(run, tmp_path / "out").read_text(encoding="utf-8")


def test_a_run_named_in_another_script_draws_without_glyph_warnings(tmp_path):
    """Matplotlib's font lacks CJK glyphs: the figures draw boxes for them, without its 'Glyph ... missing' warning."""
    import warnings

    from uncertsplat.report import figures
    from uncertsplat.report.extract import calibrations_of

    cals = calibrations_of(make_metrics(["view_000.png"]))
    stats = [dict(step=s, loss=1.0 / (s + 1), num_gaussians=100 + s, sec_per_step=0.1) for s in range(0, 50, 10)]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert figures.calibration_figure([("ünï 名前", cals), ("b", cals)])
        assert figures.timeline_figure([("ünï 名前", stats), ("b", stats)])


def test_legends_sit_outside_the_data_and_sigma_labels_do_not_overlap(monkeypatch):
    """Calibration with five runs, sparsification and a multi-run timeline: one legend below the axes (inside, each
    covered points or lines); the 2.5σ and 3σ labels (0.988 and 0.997) are not both drawn; the loss panel has a y
    label."""
    from uncertsplat.report import figures
    from uncertsplat.report.extract import calibrations_of, curves_of

    monkeypatch.setattr(figures, "_png", lambda fig: fig)
    m = make_metrics(["view_000.png"])
    fig = figures.calibration_figure([(f"run {i}", calibrations_of(m)) for i in range(5)])
    ax = fig.axes[0]
    assert ax.get_legend() is None and len(fig.legends) == 1
    labels = {t.get_text() for t in ax.texts}
    assert "3σ" in labels and "2.5σ" not in labels and {"0.5σ", "1σ", "2σ"} <= labels
    fig = figures.sparsification_figure(curves_of(m))
    assert all(a.get_legend() is None for a in fig.axes) and len(fig.legends) == 1
    assert "AUSE" in fig.axes[0].get_title()
    stats = [dict(step=s, loss=1.0 / (s + 1), num_gaussians=100 + s, num_carriers=50, sec_per_step=0.1)
             for s in range(0, 50, 10)]
    fig = figures.timeline_figure([("a", stats), ("b", stats)])
    assert all(a.get_legend() is None for a in fig.axes) and len(fig.legends) == 1
    assert [t.get_text() for t in fig.legends[0].get_texts()] == ["a", "b", "dashed: Gaussians with a posterior"]
    assert fig.axes[0].get_ylabel() == "loss (symlog scale)"  # (1 to 0.024: over a decade)
    # a short run's losses within a decade: a linear axis with numbers on it (symlog's powers of ten left none)
    short = [dict(step=s, loss=0.21 - 0.001 * s, kl_total=1e-4, num_gaussians=100) for s in range(0, 80, 10)]
    fig = figures.timeline_figure([("a", short), ("b", short)])
    assert fig.axes[0].get_ylabel() == "loss" and fig.axes[0].get_yscale() == "linear"
    # twenty runs, twenty colours (an ensemble's ten members and more repeated the first eight)
    assert len({figures.run_color(i) for i in range(20)}) == 20


def test_a_legend_of_long_run_names_fits_the_figure(monkeypatch):
    """Two runs named as a sweep names them (about 40 characters each, AUSE appended) in the 5.5-inch sparsification
    figure, and six in the calibration figure: the legend ran off both edges in four columns. Now it lies inside the
    figure, in fewer columns (or a wider figure)."""
    from uncertsplat.report import figures
    from uncertsplat.report.extract import calibrations_of, curves_of

    monkeypatch.setattr(figures, "_png", lambda fig: fig)
    m = make_metrics(["view_000.png"])
    names = ["bonsai_capture2_variational_seed0", "bonsai_capture2_deterministic_seed0"]
    for fig in (figures.sparsification_compare_figure([(n, curves_of(m)) for n in names]),
                figures.calibration_figure([(f"{names[i % 2]}_{i}", calibrations_of(m)) for i in range(6)])):
        fig.canvas.draw()
        box, width = fig.legends[0].get_window_extent(), fig.get_figwidth() * fig.dpi
        assert box.x0 >= 0 and box.x1 <= width and box.y0 >= 0
        for ax in fig.axes:  # the legend below the axes, not over them
            assert box.y1 <= ax.get_window_extent().y0 + 1


def test_two_views_of_one_name_stem_keep_maps_of_their_own(tmp_path):
    """IMG_1.jpg and IMG_1.png in one workspace wrote their maps to the same IMG_1.exr (the report showed one view's
    maps under both names): with the evaluated names, each gets its extension in its stem; a name with no twin keeps
    the plain stem, so every other run's files are named as before."""
    import torch

    from uncertsplat.eval.engine import ViewMaps
    from uncertsplat.report.views import load_view
    from uncertsplat.stages.evaluate import write_view_maps

    names = ["IMG_1.jpg", "IMG_1.png", "sub/b.png"]
    assert [map_stem(n, names) for n in names] == ["IMG_1_jpg", "IMG_1_png", "sub__b"]
    assert map_stem("IMG_1.jpg") == "IMG_1" and map_stem("IMG_1", ["IMG_1", "IMG_1.png"]) == "IMG_1_"
    for k, name in enumerate(names[:2]):
        gt = torch.full((4, 5, 3), 0.2 + 0.5 * k)
        depth = torch.full((4, 5, 1), 1.0 + k)
        write_view_maps(tmp_path, ViewMaps(name, gt, gt, 0.1 * gt, depth, 0.1 * depth), "percentile", among=names)
    assert (tmp_path / "IMG_1_jpg.exr").is_file() and (tmp_path / "IMG_1_png.exr").is_file()
    assert not (tmp_path / "IMG_1.exr").exists()
    a, b = (load_view(n, tmp_path, among=names) for n in names[:2])
    assert float(a.rgb_mean.mean()) == pytest.approx(0.2) and float(b.rgb_mean.mean()) == pytest.approx(0.7)


def test_the_sweep_caption_loses_what_the_table_beside_it_shows(tmp_path):
    """The caption's "dB lost" was the stored 0.0569 ("0.06") beside a table reading 32.66 -> 32.61 (a helper's
    audit): it is the difference of the rounded PSNRs, with both."""
    from uncertsplat.report.build import _sweep_loss

    sw = make_prune_report(tmp_path / "run").sweep
    best = sw.largest_removal_within_tolerance
    sw.unpruned.psnr, sw.points[1].score.psnr, best.psnr_loss_db = 32.6641, 32.6072, 0.0569
    assert _sweep_loss(sw, best) == "0.05 dB (32.66 → 32.61) lost"
    sw.points[1].score.psnr = 32.70  # a removal that raised the PSNR ("-0.04 dB ... lost" before)
    assert _sweep_loss(sw, best) == "0.04 dB (32.66 → 32.70) gained"
    sw.points[1].score.psnr = None  # no PSNR in the table's row: the stored loss
    assert _sweep_loss(sw, best) == "0.06 dB lost"
    best.psnr_loss_db = -0.03
    assert _sweep_loss(sw, best) == "0.03 dB gained"


def test_ratios_the_sweep_did_not_measure_are_named(tmp_path):
    """``prune --auto`` stops at the first ratio past the tolerance; the report listed 3 rows of a 6-ratio sweep
    without a word (a helper's audit)."""
    run = make_run(tmp_path, "run_a")
    report = make_prune_report(run)
    report.sweep.ratios = [1.0, 0.9, 0.7, 0.5, 0.3, 0.2]
    report.write(run / "prune.json")
    stage.run(run, tmp_path / "out")
    text = " ".join((tmp_path / "out" / "index.html").read_text(encoding="utf-8").split())
    assert "Keep ratios 0.3, 0.2 of the sweep were not measured" in text


def test_a_report_that_fails_midway_leaves_the_earlier_one_whole(tmp_path, monkeypatch):
    """Figures were written in place and the page last: a report that failed midway (a full disk) left the earlier
    page showing its numbers beside figures of the new one. They are now written apart and put in place with the
    page; a killed report's staging folder goes at the next."""
    run = make_run(tmp_path, "r")
    out = tmp_path / "out"
    stage.run([run], out, ReportConfig())
    before = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    real, calls = stage.atomic_write_bytes, []

    def full_after_two(path, data):
        calls.append(path)
        if len(calls) > 2:
            raise UserError("cannot write here (the disk is full)", path=path)
        return real(path, data)

    monkeypatch.setattr(stage, "atomic_write_bytes", full_after_two)
    with pytest.raises(UserError, match="the disk is full"):
        stage.run([run], out, ReportConfig(title="another"))
    after = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    assert {k: v for k, v in after.items() if k.name != stage.MARKER} == {
        k: v for k, v in before.items() if k.name != stage.MARKER}
    assert not list(out.glob(".figures.tmp-*"))
    monkeypatch.setattr(stage, "atomic_write_bytes", real)
    (out / ".figures.tmp-999999").mkdir()  # as a kill leaves it
    index = stage.run([run], out, ReportConfig(title="another"))
    assert "another" in index.read_text(encoding="utf-8") and not list(out.glob(".figures.tmp-*"))
    assert_figures_consistent(out, parse(index))


_KILLED_IN_SWAP = """
import os, sys
from pathlib import Path
from uncertsplat.config import ReportConfig
from uncertsplat.stages import report as stage
swap, real, n = stage._swap_in, os.replace, int(sys.argv[3])
def dying_swap(*args):
    moves = []
    def replace(src, dst):
        if len(moves) == n:
            os._exit(9)  # as a SIGKILL: nothing runs after it
        moves.append(dst)
        real(src, dst)
    os.replace = replace
    swap(*args)
stage._swap_in = dying_swap
stage.run([Path(sys.argv[1])], Path(sys.argv[2]), ReportConfig())
"""


def _figure_bytes(out: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in (out / "figures").glob("*.png")}


@pytest.mark.parametrize("moves", [0, 1, 3, -1])
def test_a_report_killed_while_its_files_go_in_never_shows_a_page_beside_figures_it_did_not_draw(tmp_path, moves):
    """The staged figures were put in place one by one under the earlier page, which was replaced last: a kill in
    between left that page showing the new report's figures (they have fixed names). The earlier page now goes aside
    first; a kill leaves either page with its own figures or none, and the next report finishes the folder."""
    import subprocess
    import sys

    out = tmp_path / "out"
    first, second = make_run(tmp_path / "a", "r", seed=0), make_run(tmp_path / "b", "r", seed=1)
    stage.run([first], out, ReportConfig())
    old, old_page = _figure_bytes(out), (out / "index.html").read_bytes()
    stage.run([second], tmp_path / "new", ReportConfig())  # the figures the second report draws
    new = _figure_bytes(tmp_path / "new")
    assert len(old) >= 3 and old.keys() == new.keys() and sum(old[n] != new[n] for n in old) >= 2
    (out / "mine.txt").write_text("a file of yours")  # kept, and no reason to refuse the folder
    n = 1 + 2 * len(new) if moves == -1 else moves  # -1: killed before the new page goes in (each figure
    # replaced is two moves: the earlier one aside, the new one in)
    done = subprocess.run([sys.executable, "-c", _KILLED_IN_SWAP, str(second), str(out), str(n)])
    assert done.returncode == 9
    on_disk = _figure_bytes(out)
    if (out / "index.html").exists():  # a page, and only the figures it drew
        assert (out / "index.html").read_bytes() == old_page
        assert on_disk == old
    else:  # no page: the kill came while the files went in
        assert moves != 0 or not on_disk
    index = stage.run([second], out, ReportConfig())
    assert _figure_bytes(out) == new and (out / "mine.txt").is_file() and not list(out.glob(".figures.tmp-*"))
    assert_figures_consistent(out, parse(index))


def test_a_report_of_an_older_version_killed_while_its_files_go_in_is_finished_by_the_next(tmp_path):
    """A page written before the marker existed references every figure the new report draws (fixed names), so no
    marker was written before the files went in: a kill there left figures/ without a page or a marker, and every
    later report refused the folder as 'not empty and it holds no earlier report'."""
    import subprocess
    import sys

    out = tmp_path / "out"
    first, second = make_run(tmp_path / "a", "r", seed=0), make_run(tmp_path / "b", "r", seed=1)
    stage.run([first], out, ReportConfig())
    (out / stage.MARKER).unlink()  # (as versions before the marker wrote the folder)
    (out / stage.CONFIG).unlink()
    done = subprocess.run([sys.executable, "-c", _KILLED_IN_SWAP, str(second), str(out), "1"])
    assert done.returncode == 9 and not (out / "index.html").exists()
    index = stage.run([second], out, ReportConfig())
    assert_figures_consistent(out, parse(index))


def test_a_report_that_fails_while_its_files_go_in_puts_the_earlier_one_back(tmp_path, monkeypatch):
    """An error (or Ctrl-C) while the staged files go in puts the earlier page and its figures back."""
    import os

    out = tmp_path / "out"
    first, second = make_run(tmp_path / "a", "r", seed=0), make_run(tmp_path / "b", "r", seed=1)
    stage.run([first], out, ReportConfig())
    before = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file() and p.name != stage.MARKER}
    real, moves = os.replace, []

    def failing(src, dst):
        moves.append(dst)
        if len(moves) == 3:
            raise KeyboardInterrupt
        real(src, dst)

    swap = stage._swap_in

    def failing_swap(*args):
        monkeypatch.setattr(os, "replace", failing)
        try:
            swap(*args)
        finally:
            monkeypatch.setattr(os, "replace", real)

    monkeypatch.setattr(stage, "_swap_in", failing_swap)
    with pytest.raises(KeyboardInterrupt):
        stage.run([second], out, ReportConfig())
    after = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file() and p.name != stage.MARKER}
    assert after == before and not list(out.glob(".figures.tmp-*"))


def test_run_names_with_dollar_signs_are_drawn_as_text():
    """Run names reach the figures' legends and titles: "dl$_$x" raised matplotlib's math parser (a traceback, no
    report) and "price $5 vs $10" was drawn as a formula ("price 5vs10")."""
    from uncertsplat.report import figures
    from uncertsplat.report.extract import calibrations_of, curves_of

    m = make_metrics(["view_000.png"])
    assert figures.sparsification_figure(curves_of(m), run_label="dl$_$x") is not None
    assert figures.calibration_figure([("dl$_$x", calibrations_of(m)), ("price $5 vs $10", calibrations_of(m))])
    stats = [dict(step=s, loss=1.0 / (s + 1), num_gaussians=100 + s, num_carriers=50, sec_per_step=0.1)
             for s in range(0, 50, 10)]
    real = figures._png
    drawn = []
    figures._png = lambda fig: drawn.append([t.get_text() for t in fig.legends[0].get_texts()]) or real(fig)
    try:
        figures.timeline_figure([("price $5 vs $10", stats), ("dl$_$x", stats)])
    finally:
        figures._png = real
    assert drawn[0][:2] == ["price $5 vs $10", "dl$_$x"]


def test_the_provenance_names_the_method_as_the_sweep_does(tmp_path):
    """A vi-single run read "train method: variational" like the default model: the method's label now."""
    run = make_run(tmp_path, "single", maps=False, stats=False)
    config = json.loads((run / "config.json").read_text(encoding="utf-8"))
    config["variational"].update(posterior="sgd", num_entries=1)
    (run / "config.json").write_text(json.dumps(config), encoding="utf-8")
    html = stage.run(run, tmp_path / "out").read_text(encoding="utf-8")
    assert "<dt>train method</dt><dd>vi-single</dd>" in html


def test_a_pipelines_sfm_check_of_a_synthetic_scene_is_shown_with_its_gt_errors(tmp_path):
    """`make demo` trains on the synthetic scene's own cameras and checks SfM on its photos in a stage beside it: the
    report said "No reconstruct_report.json in .../synth" and left the check (and its errors against the GT cameras)
    out. It shows that stage's report now, said to be beside the run; another scene's reconstruction is not taken."""
    from uncertsplat.sfm.report import ReconstructReport, write_report

    names = ["view_000.png", "view_008.png"]
    scene = make_scene(tmp_path, names)
    (scene / "reconstruct_report.json").unlink()  # a synthetic scene: its own cameras
    run = make_run(tmp_path, "train", names=tuple(names), scene=scene, maps=False, stats=False)
    html = stage.run(run, tmp_path / "before").read_text(encoding="utf-8")
    assert "reconstruction health" not in html and "No reconstruct_report.json in" in html
    check = tmp_path / "reconstruct"
    check.mkdir()
    gt = {"num_images": 2.0, "centre_error_mean_pct": 0.0988, "centre_error_max_pct": 0.23,
          "rotation_error_mean_deg": 0.0832, "rotation_error_max_deg": 0.15, "focal_error_mean_pct": 0.143}
    rep = ReconstructReport(success=True, photos=str(scene / "images"), images_found=names, images_registered=names,
                            registered_fraction=1.0, models_found=1, num_points3d=10, ground_truth=gt)
    write_report(check, rep)
    html = " ".join(stage.run(run, tmp_path / "after").read_text(encoding="utf-8").split())
    assert f"reconstruction health ({check / 'reconstruct_report.json'})" in html
    assert "centres 0.0988 % of the rig&#x27;s radius (mean), rotations 0.0832° (mean), focal lengths 0.143 %" in html
    assert "the run trained with the scene&#x27;s own cameras" in html
    rep.photos = str(tmp_path / "other" / "images")  # a reconstruction of other photos
    write_report(check, rep)
    html = stage.run(run, tmp_path / "other_photos").read_text(encoding="utf-8")
    assert "reconstruction health" not in html


def test_the_written_depth_factor_is_the_first_maps_positive_finite_one(tmp_path):
    """``written_depth_to_source`` reads the factor of the first EXR by name; a factor that is no length ratio
    (0, < 0, inf, NaN), none in the header, no map and no folder all give None."""
    from uncertsplat.io.images import write_exr
    from uncertsplat.io.maps import EXR_DEPTH_TO_SOURCE, written_depth_to_source

    plane = {"depth_mean.Z": np.zeros((2, 3), dtype=np.float32)}
    maps = tmp_path / "maps"
    assert written_depth_to_source(maps) is None  # no folder
    maps.mkdir()
    assert written_depth_to_source(maps) is None  # no map
    write_exr(maps / "b.exr", plane, attributes={EXR_DEPTH_TO_SOURCE: 3.0})
    write_exr(maps / "a.exr", plane, attributes={EXR_DEPTH_TO_SOURCE: 2.0})
    assert written_depth_to_source(maps) == 2.0
    for bad in (0.0, -2.0, float("inf"), float("nan")):
        write_exr(maps / "a.exr", plane, attributes={EXR_DEPTH_TO_SOURCE: bad})
        assert written_depth_to_source(maps) is None, bad
    write_exr(maps / "a.exr", plane)
    assert written_depth_to_source(maps) is None
