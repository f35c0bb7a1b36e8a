"""Output files of an earlier uncertsplat still read, and a schema's keys never change without a version bump.

Readers refuse a file with a missing key (``schemas.base.key_problems``: writers dump every field, so a missing key
means a damaged or foreign file). A field added to a schema without raising its ``SCHEMA_VERSION`` and converting
the older version (``_upgrade``) therefore breaks every folder written before: on 2026-11-27 four files of the
previous day's runs (``reconstruct_report.json``, ``train_summary.json``, ``prune.json``, ``sweep.json``, kept in
``tests/data/outputs_v0.1_2026-11-27``) could no longer be read. ``tests/data/schema_keys.json`` holds each schema's
version and dotted keys; a change to one without a new version fails here.
"""

from __future__ import annotations

import json
import typing
from pathlib import Path

import pytest

from uncertsplat import schemas
from uncertsplat.schemas.base import _models_in

DATA = Path(__file__).resolve().parents[1] / "data"
KEYS_FILE = DATA / "schema_keys.json"
SCHEMAS = [schemas.EvalReport, schemas.Manifest, schemas.PruneReport, schemas.PruneSweep, schemas.ReconstructReport,
           schemas.RunExposure, schemas.RunScene, schemas.Selection, schemas.SweepSummary, schemas.SynthScene,
           schemas.TrainSummary]
PruneReport, PruneSweep, ReconstructReport, TrainSummary = (schemas.PruneReport, schemas.PruneSweep,
                                                            schemas.ReconstructReport, schemas.TrainSummary)


def schema_keys(model, prefix: str = "", seen: frozenset = frozenset()) -> list[str]:
    """Every dotted key of ``model`` and of the records nested in it (a record that nests itself, once)."""
    out = []
    for name, field in model.model_fields.items():
        out.append(prefix + name)
        for sub in _models_in(field.annotation)[:1]:
            if sub in seen or sub is model:
                continue
            inner = f"{prefix}{name}.*." if typing.get_origin(field.annotation) in (dict, list) else f"{prefix}{name}."
            out += schema_keys(sub, inner, seen | {model})
    return sorted(out)


def current() -> dict:
    return {cls.__name__: {"version": cls.SCHEMA_VERSION, "keys": schema_keys(cls)} for cls in SCHEMAS}


@pytest.mark.parametrize("cls", SCHEMAS, ids=lambda c: c.__name__)
def test_keys_change_only_with_a_new_schema_version(cls):
    """To change a schema: raise its SCHEMA_VERSION (and the ``schema_version`` field's default), convert the older
    version in ``_upgrade``, then write the new keys with
    ``python -c "from tests.unit.test_schema_versions import write_keys; write_keys()"``."""
    stored = json.loads(KEYS_FILE.read_text(encoding="utf-8"))[cls.__name__]
    now = current()[cls.__name__]
    assert cls.model_fields["schema_version"].default == cls.SCHEMA_VERSION, "the field's default is the version"
    if now["version"] == stored["version"]:
        added = sorted(set(now["keys"]) - set(stored["keys"]))
        removed = sorted(set(stored["keys"]) - set(now["keys"]))
        assert not added and not removed, (
            f"{cls.__name__}'s keys changed at schema version {now['version']} (added {added}, removed {removed}): "
            "files written before would no longer read. Raise SCHEMA_VERSION, convert the older version in "
            "_upgrade, then update tests/data/schema_keys.json (write_keys)")
    else:
        assert now["version"] > stored["version"], "a schema version never goes down"
        pytest.fail(f"{cls.__name__} is at version {now['version']}, tests/data/schema_keys.json at "
                    f"{stored['version']}: check that _upgrade converts version {stored['version']}, then update "
                    "the file (write_keys)")


def write_keys() -> None:
    """Record the schemas' current versions and keys (after a version bump with its conversion). Refuses a schema
    whose keys changed at the version recorded: rewriting the file for another schema's bump recorded
    ``posterior.position_prior`` of train_summary.json at version 4, and every summary written before it was refused
    (a helper regenerating the demo's report, 2026-11-29)."""
    stored = json.loads(KEYS_FILE.read_text(encoding="utf-8"))
    now = current()
    changed = [name for name, entry in now.items()
               if name in stored and entry["version"] == stored[name]["version"] and entry["keys"] != stored[name]["keys"]]
    if changed:
        raise SystemExit(f"the keys of {', '.join(changed)} changed without a new schema version: raise SCHEMA_VERSION "
                         "and convert the older version in _upgrade first")
    KEYS_FILE.write_text(json.dumps(now, indent=1) + "\n")


OLD = DATA / "outputs_v0.1_2026-11-27"


@pytest.mark.parametrize(("cls", "name"), [(ReconstructReport, "reconstruct_report.json"),
                                           (TrainSummary, "train_summary.json"), (PruneReport, "prune.json"),
                                           (PruneSweep, "sweep.json")])
def test_files_of_the_previous_version_read(cls, name):
    """Real files of ``make demo`` from 2026-11-27 (before the mapping runs, the training views' PSNR and the
    expected-render prune decision) read, with the new keys at their "not recorded" values."""
    got = cls.read(OLD / name)
    assert got.schema_version == cls.SCHEMA_VERSION
    old = json.loads((OLD / name).read_text(encoding="utf-8"))
    assert old["schema_version"] < cls.SCHEMA_VERSION  # the file really is of an older version
    if cls is ReconstructReport:
        assert got.mapping_attempts == [] and got.mapping_agreed is None and got.num_observations is None
        assert got.num_points3d == old["num_points3d"] and got.images_registered == old["images_registered"]
    elif cls is TrainSummary:
        assert got.train_psnr is None and got.warnings == [] and got.test_psnr == pytest.approx(old["test_psnr"])
    elif cls is PruneReport:
        assert got.sweep.metric == "psnr" and got.sweep.uncertainty_measured  # it decided on the samples' mean
        assert got.metrics.before.psnr_render is None and got.metrics.before.psnr == pytest.approx(
            old["metrics"]["before"]["psnr"])
    else:
        assert got.metric == "psnr" and got.unpruned.psnr_render is None and len(got.points) == len(old["points"])


def test_a_version_4_train_summary_reads_its_posterior_as_measured_against_the_config():
    """``make demo``'s train_summary.json of 2026-11-29 (version 4, before ``posterior.position_prior``): it read as
    "key 'posterior.position_prior' is missing", and the report showed no Gaussians, no training time and no posterior
    note. Now upgraded, its posterior measured against the config's std ("config"), every other value kept."""
    path = DATA / "outputs_2026-11-29" / "train_summary.json"
    old = json.loads(path.read_text(encoding="utf-8"))
    assert old["schema_version"] == 4 and "position_prior" not in old["posterior"]
    got = TrainSummary.read(path)
    assert got.schema_version == TrainSummary.SCHEMA_VERSION and got.posterior.position_prior == "config"
    assert got.posterior.carriers == old["posterior"]["carriers"] and got.steps == old["steps"]
    member = {**old, "members": [], "posterior": dict(old["posterior"])}
    both = TrainSummary.from_dict({**old, "method": "ensemble", "members": [member]})  # in members too
    assert both.members[0].posterior.position_prior == "config"


def test_write_keys_refuses_keys_changed_at_the_same_version(monkeypatch, tmp_path):
    keys = tmp_path / "schema_keys.json"
    stored = current()
    stored["TrainSummary"]["keys"] = [k for k in stored["TrainSummary"]["keys"] if k != "posterior.position_prior"]
    keys.write_text(json.dumps(stored))
    import tests.unit.test_schema_versions as this

    monkeypatch.setattr(this, "KEYS_FILE", keys)
    with pytest.raises(SystemExit, match="the keys of TrainSummary changed without a new schema version"):
        this.write_keys()
    assert json.loads(keys.read_text(encoding="utf-8")) == stored  # untouched


def test_version_1_files_that_already_have_the_new_keys_keep_them(tmp_path):
    """Files written on 2026-11-27 between the keys' arrival and the version bump carry them at version 1: the
    conversion keeps what they say (a sweep that decided on the expected render stays so)."""
    sweep = json.loads((OLD / "sweep.json").read_text(encoding="utf-8"))
    sweep.update(metric="psnr_render", uncertainty_measured=False)
    path = tmp_path / "sweep.json"
    path.write_text(json.dumps(sweep))
    got = PruneSweep.read(path)
    assert got.metric == "psnr_render" and not got.uncertainty_measured
    report = json.loads((OLD / "reconstruct_report.json").read_text(encoding="utf-8"))
    report.update(mapping_attempts=[], mapping_agreed=True, num_observations=1234)
    path = tmp_path / "reconstruct_report.json"
    path.write_text(json.dumps(report))
    got = ReconstructReport.read(path)
    assert got.mapping_agreed is True and got.num_observations == 1234


def test_schema_keys_walk_nested_records():
    keys = schema_keys(PruneReport)
    assert "metrics.before.psnr_render" in keys and "sweep.points.*.score.psnr_render" in keys
    assert "members" in schema_keys(TrainSummary)  # a record that nests itself is listed once
    assert issubclass(PruneReport, schemas.SchemaFile)


def test_evaluation_reports_of_versions_1_to_4_read(tmp_path):
    """``metrics.json`` gained ``run_sha256`` in version 3 (``prune`` reads an evaluation of the same model file
    back), the Student-t predictive in version 4 and ``variance_shares`` in version 5; older reports read with the
    model file at None, so ``prune`` measures again instead of trusting them, with the Gaussian predictive they were
    scored with, and without shares."""
    current = schemas.EvalReport(image_names=["a.png"], device="cpu", run_sha256="f" * 64).model_dump(mode="json")
    new_view_keys = ("nll_gaussian", "calibration_error_gaussian")
    v4 = {k: v for k, v in current.items() if k != "variance_shares"} | {"schema_version": 4,
                                                                          "degrees_of_freedom": 3.5}
    (tmp_path / "metrics.json").write_text(json.dumps(v4))
    got = schemas.EvalReport.read(tmp_path / "metrics.json")
    assert got.schema_version == 5 and got.variance_shares == {} and got.degrees_of_freedom == 3.5
    v3 = {k: v for k, v in v4.items() if k != "degrees_of_freedom"} | {
        "schema_version": 3, "mean": {k: v for k, v in current["mean"].items() if k not in new_view_keys}}
    v2 = {k: v for k, v in v3.items() if k != "run_sha256"} | {"schema_version": 2}
    v1 = {k: v for k, v in v2.items() if k != "calibration_held_out"} | {"schema_version": 1}
    for data in (v1, v2, v3):
        path = tmp_path / "metrics.json"
        path.write_text(json.dumps(data))
        got = schemas.EvalReport.read(path)
        assert got.schema_version == 5 and got.image_names == ["a.png"] and got.variance_shares == {}
        assert got.degrees_of_freedom is None and got.mean.nll_gaussian is None
        assert got.run_sha256 == ("f" * 64 if data is v3 else None)
        assert got.calibration_held_out is False
    kept = v2 | {"run_sha256": "e" * 64}  # written between the key's arrival and the bump: kept
    path.write_text(json.dumps(kept))
    assert schemas.EvalReport.read(path).run_sha256 == "e" * 64


def test_a_version_1_selection_reads_without_pose_lines():
    from uncertsplat.schemas.select import Selection

    pose = {"name": "v", "score": 1.0, "cam_from_world": [[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]],
            "position": [0.0, 0.0, 0.0]}
    old = {"schema_version": 1, "run": "r", "score": "fisher", "candidates": "unused", "num_candidates": 1,
           "chosen": [{**pose, "rank": 1, "score_when_chosen": 1.0}], "ranking": [pose], "seconds": 1.0,
           "seconds_per_candidate": 1.0}
    sel = Selection.from_dict(old)
    assert sel.schema_version == 2 and sel.chosen[0].pose_line is None and sel.ranking[0].pose_line is None
