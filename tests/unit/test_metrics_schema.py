"""EvalReport: round trip through JSON, strictness, non-finite values, means, readers."""

from __future__ import annotations

import json
import math

import pydantic
import pytest
import torch

from uncertsplat.eval.calibration import calibration
from uncertsplat.eval.sparsification import sparsification_all
from uncertsplat.schemas.metrics import (
    CalibrationTable,
    CurveSet,
    DepthScaleInfo,
    EvalReport,
    LpipsStatus,
    SparsificationCurve,
    ViewMetrics,
)


def _report() -> EvalReport:
    g = torch.Generator().manual_seed(0)
    err = torch.rand(8, 8, 3, generator=g)
    std = err + 0.1 * torch.rand(8, 8, 3, generator=g)
    sp = sparsification_all(err, std, steps=10)
    curves = CurveSet(rgb={m: SparsificationCurve.from_result(r) for m, r in sp.items()},
                      depth={"mae": SparsificationCurve.from_result(sp["mae"])})
    v1 = ViewMetrics(psnr=float("inf"), ssim=0.9, ause_mae=sp["mae"].ause, spearman=None,
                     spearman_note="undefined: the uncertainty is constant", nll=float("nan"), seconds=1.5)
    v2 = ViewMetrics(psnr=20.0, ssim=0.8, ause_mae=0.1, spearman=0.5, seconds=2.5)
    return EvalReport(
        split="test",
        image_names=["a.png", "b.png"],
        per_view={"a.png": v1, "b.png": v2},
        mean=ViewMetrics.mean_of([v1, v2]),
        curves={"a.png": curves, "mean": curves},
        calibration={"rgb": CalibrationTable.from_result(calibration(err, std))},
        config_hash="abc",
        versions={"torch": torch.__version__},
        num_samples=10,
        seed=0,
        seconds_per_view=2.0,
        std_floor=1e-3,
        depth_scale=DepthScaleInfo(scale=2.0, method="median", num_pixels=64),
        lpips=LpipsStatus(available=False, reason="unavailable: no local weights"),
    )


def test_round_trip_and_nonfinite():
    rep = _report()
    text = rep.to_json()
    data = json.loads(text)  # strict JSON: no NaN / Infinity tokens
    assert "NaN" not in text and "Infinity" not in text
    assert data["per_view"]["a.png"]["psnr"] is None and data["per_view"]["a.png"]["nll"] is None
    back = EvalReport.from_json(text)
    assert back == EvalReport.model_validate(data)
    assert back.curves["mean"].rgb["mae"].ause == pytest.approx(rep.curves["mean"].rgb["mae"].ause)
    assert len(back.curves["mean"].rgb["rmse"].fractions) == 10


def test_mean_of_skips_none():
    rep = _report()
    assert rep.mean.psnr == 20.0  # the inf (None) view is skipped
    assert rep.mean.ssim == pytest.approx(0.85)
    assert rep.mean.seconds == pytest.approx(2.0)
    assert rep.mean.spearman == 0.5 and rep.mean.spearman_note
    assert rep.mean.lpips is None


def test_extra_fields_forbidden():
    data = json.loads(_report().to_json())
    data["per_view"]["a.png"]["bogus"] = 1.0
    with pytest.raises(pydantic.ValidationError):
        EvalReport.model_validate(data)
    data = json.loads(_report().to_json())
    data["surprise"] = 1
    with pytest.raises(pydantic.ValidationError):
        EvalReport.model_validate(data)


def test_empty_curve_is_none():
    sp = sparsification_all(torch.rand(4), torch.rand(4), mask=torch.zeros(4, dtype=torch.bool), steps=4)
    assert SparsificationCurve.from_result(sp["mae"]) is None
    assert math.isnan(sp["mae"].ause)


def test_report_reader_finds_curves_and_calibration():
    from uncertsplat.report.extract import calibrations_of, curves_of

    report = EvalReport.from_json(_report().to_json())  # what the report reads back from metrics.json
    kinds = {(c.view, c.depth, c.metric) for c in curves_of(report)}
    assert ("a.png", False, "rmse") in kinds and (None, True, "mae") in kinds
    cal = calibrations_of(report)
    assert cal and len(cal[0].table.nominal) == 6
