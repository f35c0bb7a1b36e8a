"""Every output file's schema: round trip, clear errors for missing / renamed keys and versions."""

from __future__ import annotations

import json
import re

import pytest

from uncertsplat.errors import UserError
from uncertsplat.schemas import (
    EvalReport,
    Manifest,
    PruneReport,
    PruneSweep,
    ReconstructReport,
    RunScene,
    SchemaFile,
    SweepRecord,
    SweepSummary,
    SynthScene,
    TrainSummary,
    ViewMetrics,
)
from uncertsplat.schemas.prune import PruneCounts, PruneMetrics, PruneMetricSet, ScoreStats, SweepPoint
from uncertsplat.schemas.runs import MemoryPerGaussian, PosteriorSummary, Quantiles


def _metrics(n: int, psnr: float) -> PruneMetrics:
    return PruneMetrics(num_gaussians=n, num_carriers=n // 2, psnr=psnr, ssim=0.9, ause_mae=0.1, ause_rmse=0.2,
                        nll=-1.5, depth_ause_mae=None, coverage=0.99, variational_ply_bytes=1000 * n,
                        point_cloud_ply_bytes=600 * n, seconds=1.5)


def _sweep() -> PruneSweep:
    before = _metrics(100, 30.0)
    point = SweepPoint(keep_ratio=0.9, num_removed=10, keep_ratio_achieved=0.9, score=_metrics(90, 29.9),
                       random=_metrics(90, 29.5))
    return PruneSweep(ratios=[1.0, 0.9], score="gate", split="test", unpruned=before,
                      points=[SweepPoint(keep_ratio=1.0, num_removed=0, keep_ratio_achieved=1.0, score=before,
                                         random=before), point], tolerance_db=0.1)


def _quantiles() -> Quantiles:
    return Quantiles(q10=0.1, q50=0.5, q90=0.9)


def _examples() -> list[SchemaFile]:
    """One instance of every schema, with nested records filled in."""
    single = TrainSummary(method="variational", variant="ours", steps=100, seconds=12.5, sec_per_step=0.125,
                          num_gaussians=1000, num_carriers=400, peak_memory_mb=512.0, device="cpu", scene="/s",
                          test_psnr=25.0, carrier_fraction=0.4,
                          memory=MemoryPerGaussian(params=236, tables=100, index=4, optimizer=472, total=812,
                                                   table_bytes_per_carrier=250),
                          posterior=PosteriorSummary(carriers=400, moved_kl_nats=0.01, gate_off_prior=0.158,
                                                     moved_fraction=0.001, kl_nats=_quantiles(),
                                                     position_spread_ratio=_quantiles(),
                                                     scale_width_ratio=_quantiles(), gate_off=_quantiles()))
    return [
        EvalReport(image_names=["a.png"], per_view={"a.png": ViewMetrics(psnr=20.0)}, mean=ViewMetrics(psnr=20.0)),
        PruneReport(source_run="/r", source_model="variational.ply", source_model_sha256="ab", score="gate",
                    score_requested="gate", mode="keep_ratio", keep_ratio=0.9, tolerance_db=0.1, seed=0,
                    num_samples=4, metric_split="test", metric_views=["a.png"], score_views=["b.png"],
                    score_seconds=0.5, dry_run=False, device="cpu",
                    score_stats={"gate": ScoreStats(min=0.0, median=0.1, max=0.9)},
                    metrics=PruneMetricSet(before=_metrics(100, 30.0), after=_metrics(90, 29.9),
                                           random=_metrics(90, 29.5)),
                    counts=PruneCounts(before=100, after=90, removed=10, carriers_before=50, carriers_after=40),
                    sweep=_sweep(), undo="use the source run"),
        _sweep(),
        ReconstructReport(success=True, photos="/p", images_found=["a.jpg"], registered_fraction=1.0),
        SynthScene(kind="uncertsplat-synthetic", generator_version=1, preset="tiny", seed=0, width=128, height=96,
                   num_views=24, intrinsics={"fx": 100.0, "fy": 100.0, "cx": 64.0, "cy": 48.0},
                   image_names=["v0.png"], test_every=8, test_views=["v0.png"], num_points=10, depth="d", mask="m",
                   room={"half_width": 2.0, "floor": -1.0, "ceiling": 1.0},
                   objects=[{"kind": "box", "center": [0, 0, 0], "size": [1, 1, 1], "pattern": "checker"}],
                   config={"preset": "tiny"}),
        RunScene(scene="/s", extent=1.1, scene_scale=1.0, width=128, height=96, train=["a"], test=["b"],
                 cameras={"a": [0.0, 0.0, 2.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 100.0, 100.0, 64.0, 48.0]}),
        single,
        TrainSummary(method="ensemble", variant="ours", steps=100, seconds=25.0, sec_per_step=0.25,
                     num_gaussians=2000, num_carriers=0, peak_memory_mb=512.0, device="cpu", scene="/s",
                     ensemble_size=2, members=[single, single]),
        Manifest(stage="train", name="train", config_hash="h", input_hashes={"synth": "k"}, config={"a": 1},
                 status="done", started_at=1.0, finished_at=2.0, seconds=1.0),
        SweepSummary(name="t", spec={"name": "t"}, num_points=1, num_failed=0, default="p", pareto_x="time",
                     pareto={"ause_mae_vs_time": ["p"]},
                     records=[SweepRecord(id="p", hash="h", job="j", method="variational", knobs={"iterations": 5},
                                          is_default=True, status="ok", run_dir="/r", device="cpu", threads=1,
                                          psnr=20.0, ause_mae=0.1, time=3.0)]),
    ]


EXAMPLES = _examples()


@pytest.mark.parametrize("doc", EXAMPLES, ids=lambda d: type(d).__name__)
class TestEverySchema:
    def test_round_trip(self, doc, tmp_path):
        path = doc.write(tmp_path / "f.json")
        again = type(doc).read(path)
        assert again == doc
        assert json.loads(path.read_text(encoding="utf-8"))["schema_version"] == type(doc).SCHEMA_VERSION

    def test_missing_key_names_the_file_and_the_key(self, doc, tmp_path):
        data = json.loads(doc.to_json())
        required = next(k for k in type(doc).model_fields if k != "schema_version")
        del data[required]
        path = tmp_path / "f.json"
        path.write_text(json.dumps(data))
        with pytest.raises(UserError) as err:
            type(doc).read(path)
        msg = str(err.value)
        assert str(path) in msg and f"key '{required}' is missing" in msg

    def test_renamed_key_names_both_keys(self, doc, tmp_path):
        data = json.loads(doc.to_json())
        required = next(k for k in type(doc).model_fields if k != "schema_version")
        data[required + "_old"] = data.pop(required)
        path = tmp_path / "f.json"
        path.write_text(json.dumps(data))
        with pytest.raises(UserError) as err:
            type(doc).read(path)
        msg = str(err.value)
        assert f"key '{required}' is missing" in msg and f"key '{required}_old' is not part of the schema" in msg

    def test_newer_version_is_refused_with_the_versions(self, doc, tmp_path):
        data = json.loads(doc.to_json())
        data["schema_version"] = type(doc).SCHEMA_VERSION + 1
        path = tmp_path / "f.json"
        path.write_text(json.dumps(data))
        with pytest.raises(UserError, match=f"schema version {type(doc).SCHEMA_VERSION + 1} is newer"):
            type(doc).read(path)


def test_nested_error_names_the_dotted_key(tmp_path):
    data = json.loads(EXAMPLES[1].to_json())
    data["metrics"]["after"]["psnrr"] = data["metrics"]["after"].pop("psnr")
    path = tmp_path / "prune.json"
    path.write_text(json.dumps(data))
    with pytest.raises(UserError, match=r"key 'metrics.after.psnrr' is not part of the schema"):
        PruneReport.read(path)


def test_a_file_of_another_kind_is_named_as_what_it_is(tmp_path):
    """``Selection.read("RUN/eval/metrics.json")`` said "schema version 4 is newer than the 2 this version of uncertsplat
    reads. Upgrade uncertsplat to read it", and a synthetic scene's scene.json read as a run's named a missing key
    and "re-run `uncertsplat train`": a record of another kind is named as what it is."""
    from uncertsplat.schemas import Selection
    from uncertsplat.schemas.identify import own_words

    metrics = next(d for d in EXAMPLES if isinstance(d, EvalReport)).write(tmp_path / "metrics.json")
    with pytest.raises(UserError, match=r"this is `uncertsplat evaluate`'s metrics \(metrics.json\), not "
                                        r"`uncertsplat select-views`' record \(selection.json\)") as err:
        Selection.read(metrics)
    assert "Upgrade" not in err.value.render() and "selection.json that `uncertsplat select-views` writes" in err.value.hint
    synth = next(d for d in EXAMPLES if isinstance(d, SynthScene)).write(tmp_path / "scene.json")
    with pytest.raises(UserError, match=r"this is `uncertsplat synth`'s record of a synthetic scene \(scene.json\), "
                                        r"not `uncertsplat train`'s record of the run's scene"):
        RunScene.read(synth)
    # every example read as every other kind that can tell it: named, never read
    for doc in EXAMPLES:
        path = doc.write(tmp_path / "f.json")
        for other in {type(d) for d in EXAMPLES} - {type(doc)}:
            if own_words(type(doc)) is None or own_words(other) is None:
                continue
            with pytest.raises(UserError, match=f"this is .*, not {re.escape(own_words(other))}"):
                other.read(path)


def test_older_version_without_conversion_is_refused(tmp_path):
    data = json.loads(EXAMPLES[0].to_json())
    del data["schema_version"]  # an EvalReport always had a version: 0 cannot be converted
    path = tmp_path / "metrics.json"
    path.write_text(json.dumps(data))
    with pytest.raises(UserError, match=rf"the file has no 'schema_version' \(written before files were versioned, "
                       rf"or edited\): it is older than version {EvalReport.SCHEMA_VERSION} and cannot be converted"
                       ) as err:
        EvalReport.read(path)
    assert "uncertsplat evaluate" in str(err.value)  # says which command rewrites it
    assert err.value.render().count("metrics.json") == 1  # (the path once: its name was said twice)
    with pytest.raises(UserError, match=r"eval/metrics.json has no 'schema_version'"):  # (no file: its name)
        EvalReport.from_dict(data)


def test_unversioned_prune_json_is_converted(tmp_path):
    """prune.json files written before schema_version (same layout) still read."""
    data = json.loads(EXAMPLES[1].to_json())
    del data["schema_version"]
    del data["sweep"]["schema_version"]
    del data["sweep"]["tolerance_db"]
    path = tmp_path / "prune.json"
    path.write_text(json.dumps(data))
    got = PruneReport.read(path)
    assert got.sweep.tolerance_db == data["tolerance_db"] and got.metrics == EXAMPLES[1].metrics


def test_unversioned_manifest_is_converted(tmp_path):
    data = json.loads(EXAMPLES[8].to_json())
    del data["schema_version"]
    path = tmp_path / "manifest.json"
    path.write_text(json.dumps(data))
    assert Manifest.read(path) == EXAMPLES[8]


def test_not_json_and_not_an_object(tmp_path):
    path = tmp_path / "train_summary.json"
    path.write_text("{cut short")
    with pytest.raises(UserError, match="not valid JSON"):
        TrainSummary.read(path)
    path.write_text("[1, 2]")
    with pytest.raises(UserError, match="expected a JSON object, found list"):
        TrainSummary.read(path)
    with pytest.raises(UserError, match="train_summary.json not found"):
        TrainSummary.read(tmp_path / "nope.json")
    assert TrainSummary.read_optional(tmp_path / "nope.json") is None


def test_non_finite_numbers_are_written_as_null(tmp_path):
    m = _metrics(10, float("nan"))
    assert m.psnr is None
    s = TrainSummary.model_validate({**EXAMPLES[6].model_dump(), "test_psnr": float("inf")})
    assert s.test_psnr is None


def test_sweep_record_line_with_a_renamed_key_names_file_and_line(tmp_path):
    from uncertsplat.stages.sweep import read_records

    good = EXAMPLES[9].records[0]
    bad = json.loads(good.model_dump_json())
    bad["ause"] = bad.pop("ause_mae")
    log = tmp_path / "sweep.jsonl"
    log.write_text(good.model_dump_json() + "\n" + json.dumps(bad) + "\n" + '{"cut sh')
    with pytest.raises(UserError, match=r"line 2 does not match the sweep record schema") as err:
        read_records(log)
    assert str(log) in str(err.value) and "key 'ause_mae' is missing" in str(err.value)
    log.write_text(good.model_dump_json() + "\n" + '{"cut sh')  # a line cut by a crash is skipped
    assert read_records(log) == [good]


def test_unversioned_run_scene_is_converted(tmp_path):
    """Run folders trained before scene.json had a schema still load."""
    old = {"scene": "/s", "source": {"kind": "colmap"}, "extent": 1.1, "scene_scale": 1.0, "width": 8, "height": 6,
           "train": ["a"], "test": ["b"]}
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(old))
    got = RunScene.read(path)
    assert got.scene == "/s" and got.center_method == "camera_centroid" and got.center is None
    assert got.calibration == []


def _as_version_1(example, dropped: str, path):
    """``example`` written as its version 1 file, without the key ``dropped`` that version 2 added; read back."""
    data = json.loads(example.to_json())
    data["schema_version"] = 1
    del data[dropped]
    path.write_text(json.dumps(data))
    return type(example).read(path)


def test_version_1_run_scene_and_eval_report_are_converted(tmp_path):
    """scene.json and eval/metrics.json of runs before views could be set aside for calibration (version 1) read
    with none set aside and the std factor fitted on training views."""
    scene = next(e for e in EXAMPLES if isinstance(e, RunScene))
    scene = scene.model_copy(update={"cameras": {}})  # (version 3's key: not in a version 1 file either)
    got = _as_version_1(scene, "calibration", tmp_path / "scene.json")
    assert got.schema_version == RunScene.SCHEMA_VERSION and got.calibration == [] and got.train == scene.train
    report = next(e for e in EXAMPLES if isinstance(e, EvalReport))
    got = _as_version_1(report, "calibration_held_out", tmp_path / "metrics.json")
    assert got.schema_version == EvalReport.SCHEMA_VERSION and not got.calibration_held_out and got.mean == report.mean
    assert got.run_sha256 is None


def test_version_2_run_scene_reads_with_no_cameras_to_compare(tmp_path):
    """scene.json of runs before their cameras were recorded (version 2) reads with none: a later load compares
    nothing (``sfm.scene.camera_changes``) instead of refusing the run."""
    scene = next(e for e in EXAMPLES if isinstance(e, RunScene))
    data = json.loads(scene.to_json())
    data["schema_version"] = 2
    del data["cameras"], data["near"]
    (tmp_path / "scene.json").write_text(json.dumps(data))
    got = RunScene.read(tmp_path / "scene.json")
    assert got.schema_version == RunScene.SCHEMA_VERSION and got.cameras == {} and got.train == scene.train
    assert got.near is None  # the plane those runs rendered with: 1 % of the scene scale (LoadedRun.render_fn)
    data["schema_version"] = 3  # cameras recorded, no near plane
    data["cameras"] = json.loads(scene.to_json())["cameras"]
    (tmp_path / "scene.json").write_text(json.dumps(data))
    got = RunScene.read(tmp_path / "scene.json")
    assert got.near is None and got.cameras == scene.cameras


def test_train_summary_version_1_is_converted(tmp_path):
    """train_summary.json before the informed posterior (version 1) reads with no updates, members too."""
    summary = next(e for e in EXAMPLES if isinstance(e, TrainSummary))
    data = json.loads(summary.to_json())
    data["schema_version"] = 1
    del data["posterior_updates"]
    member = {**data, "members": []}
    data["members"] = [member]
    path = tmp_path / "train_summary.json"
    path.write_text(json.dumps(data))
    got = TrainSummary.read(path)
    assert got.schema_version == TrainSummary.SCHEMA_VERSION and got.posterior_updates == []
    assert got.members[0].posterior_updates == [] and got.members[0].train_psnr is None and got.warnings == []


def test_the_reconstruct_summary_names_the_models_only_when_there_are_several():
    """"12/12 images registered, 2 model(s)" read as a split capture where the second model was a subset of the
    first: with several models the line says the images are those of the largest, the one the workspace holds."""
    from uncertsplat.schemas.reconstruct import ReconstructReport

    report = ReconstructReport(success=True, photos="/p", images_found=[f"{i}.png" for i in range(12)],
                               images_registered=[f"{i}.png" for i in range(12)], models_found=1, num_points3d=10)
    assert report.summary().startswith("12/12 images registered, 10 points")
    report.models_found = 2
    assert report.summary().startswith("12/12 images registered in the largest of 2 models, 10 points")
