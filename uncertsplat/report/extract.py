"""What the report shows of an ``EvalReport`` / ``PruneReport``: metric columns, curves, calibration tables.

The columns are fixed tables of presentation (label, number format, direction) keyed by the *field
names* of the schema records (``ViewMetrics``, ``PruneMetrics``); a test checks that every name is a real
field. Values are never transformed except for a unit where the label says so (bytes shown in MB):
what the report shows is what the file says.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from uncertsplat.report.loader import as_float
from uncertsplat.schemas.metrics import CalibrationTable, EvalReport, SparsificationCurve, ViewMetrics
from uncertsplat.schemas.prune import PruneMetrics


@dataclass(frozen=True)
class MetricSpec:
    """A metric column: the schema field it shows, its label, number format, direction and display unit."""

    key: str
    label: str
    fmt: str
    higher_is_better: bool | None
    scale: float = 1.0
    """The shown number is ``value * scale`` (e.g. 1e-6 for bytes shown in MB); ``data-value`` keeps the raw value."""


# Order = column order in the tables; every numeric ViewMetrics field has a column (tests check both ways).
METRIC_SPECS: tuple[MetricSpec, ...] = (
    MetricSpec("psnr", "PSNR (dB)", ".2f", True),
    MetricSpec("psnr_render", "PSNR, expected render (dB)", ".2f", True),
    MetricSpec("ssim", "SSIM", ".4f", True),
    MetricSpec("lpips", "LPIPS", ".4f", False),
    MetricSpec("ause_mae", "AUSE MAE", ".4f", False),
    MetricSpec("ause_rmse", "AUSE RMSE", ".4f", False),
    MetricSpec("ause_mse", "AUSE MSE", ".4f", False),
    MetricSpec("nll", "NLL (nats)", ".3f", False),
    MetricSpec("nll_kde", "NLL (KDE, nats)", ".3f", False),
    MetricSpec("nll_paper", "NLL (paper formula, nats)", ".3f", False),
    MetricSpec("calibration_error", "Calib. error", ".4f", False),
    MetricSpec("nll_calibrated", "NLL, std rescaled (nats)", ".3f", False),
    MetricSpec("calibration_error_calibrated", "Calib. error, std rescaled", ".4f", False),
    MetricSpec("nll_gaussian", "NLL, read as a Gaussian (nats)", ".3f", False),
    MetricSpec("calibration_error_gaussian", "Calib. error, read as a Gaussian", ".4f", False),
    MetricSpec("spearman", "Spearman", ".3f", True),
    MetricSpec("depth_ause_mae", "Depth AUSE MAE", ".4f", False),
    MetricSpec("depth_ause_rmse", "Depth AUSE RMSE", ".4f", False),
    MetricSpec("depth_abs_rel", "Depth AbsRel", ".4f", False),
    MetricSpec("depth_rmse", "Depth RMSE", ".4g", False),  # lengths in the scene's units: any magnitude
    MetricSpec("depth_mae", "Depth MAE", ".4g", False),
    MetricSpec("depth_nll", "Depth NLL (nats)", ".3f", False),
    MetricSpec("depth_spearman", "Depth Spearman", ".3f", True),
    MetricSpec("seconds", "MC time (s)", ".3f", False),
)
SPEC_BY_KEY = {s.key: s for s in METRIC_SPECS}

# The summary table shows these metric columns (when at least one run has them) plus run facts.
SUMMARY_KEYS = ("psnr", "psnr_render", "ssim", "ause_mae", "ause_rmse", "nll", "calibration_error", "nll_calibrated",
                "depth_ause_mae")

# The pruning table: PruneMetrics fields of the models before / after pruning and after random removal.
PRUNE_SPECS: tuple[MetricSpec, ...] = (
    MetricSpec("psnr", "PSNR (dB)", ".2f", True),
    MetricSpec("psnr_render", "PSNR, expected render (dB)", ".2f", True),
    MetricSpec("ssim", "SSIM", ".4f", True),
    MetricSpec("ause_mae", "AUSE MAE", ".4f", False),
    MetricSpec("nll", "NLL (nats)", ".3f", False),
    MetricSpec("num_gaussians", "Gaussians", ",d", None),
    MetricSpec("variational_ply_bytes", "variational.ply (MB)", ".2f", False, scale=1e-6),
    # (as train writes it: the pruned run's own file is larger by the score_* columns prune adds)
    MetricSpec("point_cloud_ply_bytes", "point_cloud.ply without scores (MB)", ".2f", False, scale=1e-6),
)


@dataclass(frozen=True)
class MetricValue:
    """One shown number: its column and the raw value exactly as in the file."""

    spec: MetricSpec
    value: Any  # as in the file (None = not available)

    @property
    def text(self) -> str:
        return format_value(self.value, self.spec)


def metric_row(m: ViewMetrics) -> dict[str, MetricValue]:
    """The metrics of one row (a view's or the mean), by field name, in METRIC_SPECS order."""
    return {s.key: MetricValue(s, getattr(m, s.key)) for s in METRIC_SPECS}


def prune_row(m: PruneMetrics) -> dict[str, MetricValue]:
    """The pruning-table columns of one model, by field name, in PRUNE_SPECS order."""
    return {s.key: MetricValue(s, getattr(m, s.key)) for s in PRUNE_SPECS}


def format_value(value: Any, spec: MetricSpec | str) -> str:
    """The text shown for a value; 'n/a' for missing or non-finite numbers.

    ``spec`` is a column (its format and scale) or a bare format string.
    """
    fmt, scale = (spec, 1.0) if isinstance(spec, str) else (spec.fmt, spec.scale)
    f = as_float(value)
    if f is None:
        return "n/a"
    if fmt.endswith("d"):
        return format(int(value), fmt)
    return format(f * scale, fmt)


# ---------------------------------------------------------------------------------------------- curves
@dataclass(frozen=True)
class Curve:
    """One sparsification curve of ``EvalReport.curves[key][modality][metric]``."""

    view: str | None
    """The image name; None for the mean over views (``key == "mean"``)."""
    modality: str
    """"rgb" or "depth"."""
    metric: str
    """"mae", "mse" or "rmse"."""
    curve: SparsificationCurve

    @property
    def depth(self) -> bool:
        return self.modality == "depth"

    @property
    def fractions(self) -> np.ndarray:
        return np.asarray(self.curve.fractions, dtype=np.float64)

    @property
    def oracle(self) -> np.ndarray:
        return np.asarray(self.curve.oracle, dtype=np.float64)

    @property
    def uncertainty(self) -> np.ndarray:
        return np.asarray(self.curve.uncertainty, dtype=np.float64)

    @property
    def ause(self) -> float | None:
        return self.curve.ause


MEAN_KEY = "mean"
"""The key of ``EvalReport.curves`` holding the mean over views (the others are image names)."""


def curves_of(report: EvalReport) -> list[Curve]:
    """Every curve of ``report.curves``, tagged with its view (None = the mean), modality and metric."""
    out = []
    for key, cs in report.curves.items():
        view = None if key == MEAN_KEY else key
        for modality, by_metric in (("rgb", cs.rgb), ("depth", cs.depth)):
            for metric, c in by_metric.items():
                out.append(Curve(view, modality, metric, c))
    return out


# ---------------------------------------------------------------------------------------- calibration
@dataclass(frozen=True)
class Calibration:
    """``EvalReport.calibration[modality]``: observed vs nominal coverage of the predictive's central intervals (a
    Gaussian's k-sigma ones, or a Student-t's of the same probabilities)."""

    modality: str
    table: CalibrationTable

    @property
    def depth(self) -> bool:
        return self.modality == "depth"

    @property
    def k(self) -> np.ndarray:
        return np.asarray(self.table.ks, dtype=np.float64)

    @property
    def nominal(self) -> np.ndarray:
        return np.asarray(self.table.nominal, dtype=np.float64)

    @property
    def observed(self) -> np.ndarray:
        """[len(ks)] with NaN where the file has null (no element to measure)."""
        return np.asarray([np.nan if o is None else o for o in self.table.observed], dtype=np.float64)


def calibrations_of(report: EvalReport) -> list[Calibration]:
    """The calibration tables of the mean over views, RGB first then depth."""
    return sorted((Calibration(m, t) for m, t in report.calibration.items()), key=lambda c: (c.depth, c.modality))
