"""``EvalReport``: the schema of ``RUN/eval/metrics.json`` (written by ``evaluate``, read by ``report``).

Numbers that are not available (no GT depth, LPIPS without local weights, an undefined Spearman, a
view with no valid pixel) are ``null``. Non-finite floats are stored as ``null`` too (JSON has no NaN;
a PSNR of +inf, identical images, is therefore null): ``None`` always means "not a number we can
state".

Curves are stored as ``curves[key][modality][metric]`` with key = "mean" or an image name, modality
"rgb" or "depth", metric "mae" / "mse" / "rmse"; each curve has ``fractions``, ``oracle``,
``uncertainty`` (normalised, see ``eval/sparsification.py``) and its ``ause``.
"""

from __future__ import annotations

from typing import Any

from pydantic import Field, field_validator

from uncertsplat.schemas.base import SchemaFile
from uncertsplat.schemas.base import Strict as _Strict
from uncertsplat.schemas.base import finite_or_none as _finite_or_none

SCHEMA_VERSION = 5
"""``EvalReport``'s: 2 added ``calibration_held_out`` (2026-11-27), 4 the Student-t predictive
(``degrees_of_freedom``, the Gaussian readings and the calibration table's half-widths; 2026-11-28), 5
``variance_shares`` (2026-12-01)."""


class ViewMetrics(_Strict):
    """Metrics of one view (or their mean over views). All optional: None = not available."""

    psnr: float | None = None
    """PSNR of the prediction: the mean of the K sampled renders."""
    psnr_render: float | None = None
    """PSNR of one deterministic render: the expected render of a variational run
    (``variational.expected_render_sample``), the plain render of a deterministic one; None for the
    ensemble and Fisher baselines."""
    ssim: float | None = None
    lpips: float | None = None
    ause_mae: float | None = None
    ause_mse: float | None = None
    ause_rmse: float | None = None
    nll: float | None = None
    """NLL of the RGB predictive with the std floor (``EvalReport.std_floor``): a Student-t with the std and
    ``EvalReport.degrees_of_freedom``, or the Gaussian when that is None."""
    nll_kde: float | None = None
    """KDE NLL over the K samples, Silverman bandwidth from K."""
    nll_paper: float | None = None
    """The original code's KDE NLL formula; NOT comparable (depends on resolution)."""
    calibration_error: float | None = None
    """Mean |observed - nominal| coverage of the RGB predictive's central intervals (``eval.calibration``)."""
    nll_calibrated: float | None = None
    """The NLL with the std times ``EvalReport.std_scale`` (fitted on training views or views set aside)."""
    calibration_error_calibrated: float | None = None
    """Calibration error with the std times ``EvalReport.std_scale``."""
    nll_gaussian: float | None = None
    """The Gaussian NLL of the same (raw) std, when the predictive is a Student-t; None when it is the Gaussian."""
    calibration_error_gaussian: float | None = None
    """The calibration error of Gaussian intervals of the same (raw) std, when the predictive is a Student-t."""
    spearman: float | None = None
    """Spearman(std, |error|) over RGB elements; None when undefined (see ``spearman_note``)."""
    spearman_note: str | None = None
    depth_ause_mae: float | None = None
    depth_ause_rmse: float | None = None
    depth_abs_rel: float | None = None
    depth_rmse: float | None = None
    depth_mae: float | None = None
    depth_nll: float | None = None
    depth_spearman: float | None = None
    seconds: float | None = None
    """Wall time of the K Monte-Carlo renders of this view."""

    @field_validator("*", mode="before")
    @classmethod
    def _nonfinite_to_none(cls, v):
        return _finite_or_none(v)

    @classmethod
    def mean_of(cls, views: list[ViewMetrics]) -> ViewMetrics:
        """Field-wise mean over views, skipping None (a field None in every view stays None)."""
        out: dict[str, Any] = {}
        for name in cls.model_fields:
            if name == "spearman_note":  # the only non-numeric field
                continue
            vals = [getattr(v, name) for v in views if getattr(v, name) is not None]
            out[name] = sum(vals) / len(vals) if vals else None
        notes = {v.spearman_note for v in views if v.spearman_note}
        if notes and out.get("spearman") is None:
            out["spearman_note"] = "; ".join(sorted(notes))
        elif notes:
            out["spearman_note"] = f"averaged over the views where it is defined ({len(notes)} note(s))"
        return cls(**out)


class SparsificationCurve(_Strict):
    """A normalised sparsification curve pair and its AUSE (see ``eval/sparsification.py``)."""

    metric: str
    fractions: list[float]
    oracle: list[float]
    uncertainty: list[float]
    ause: float | None
    aurg: float | None = None
    num_elements: int = 0

    @field_validator("ause", "aurg", mode="before")
    @classmethod
    def _nonfinite_to_none(cls, v):
        return _finite_or_none(v)

    @classmethod
    def from_result(cls, result) -> SparsificationCurve | None:
        """From an ``eval.sparsification.SparsificationResult``; None when it had no valid element."""
        if result.num_elements == 0:
            return None
        return cls(
            metric=result.metric,
            fractions=[float(x) for x in result.fractions.tolist()],
            oracle=[float(x) for x in result.oracle.tolist()],
            uncertainty=[float(x) for x in result.uncertainty.tolist()],
            ause=result.ause,
            aurg=result.aurg,
            num_elements=result.num_elements,
        )


class CurveSet(_Strict):
    """Curves of one view (or the mean) by modality and metric: {"mae": curve, "rmse": curve, ...}."""

    rgb: dict[str, SparsificationCurve] = Field(default_factory=dict)
    depth: dict[str, SparsificationCurve] = Field(default_factory=dict)


class CalibrationTable(_Strict):
    """Observed vs nominal coverage of the predictive's central intervals (see ``eval/calibration.py``)."""

    ks: list[float]
    """The levels, as a Gaussian's half-widths in stds (nominal = erf(k / sqrt 2))."""
    observed: list[float | None]
    nominal: list[float]
    calibration_error: float | None
    num_elements: int = 0
    half_widths: list[float] | None = None
    """The intervals' half-widths in stds (the ks for the Gaussian; a Student-t's are narrower at small k and wider
    at large k); None in reports from before schema version 4 (Gaussian)."""

    @field_validator("calibration_error", mode="before")
    @classmethod
    def _nonfinite_to_none(cls, v):
        return _finite_or_none(v)

    @field_validator("observed", mode="before")
    @classmethod
    def _nonfinite_list(cls, v):
        return [_finite_or_none(x) for x in v] if isinstance(v, (list, tuple)) else v

    @classmethod
    def from_result(cls, result) -> CalibrationTable:
        """From an ``eval.calibration.CalibrationResult``."""
        return cls(
            ks=list(result.ks),
            observed=list(result.observed),
            nominal=list(result.nominal),
            calibration_error=result.calibration_error,
            num_elements=result.num_elements,
            half_widths=list(result.half_widths) if result.half_widths else None,
        )


class DepthScaleInfo(_Strict):
    """The factor applied to rendered depth before comparing with GT depth, and where it came from."""

    scale: float
    method: str
    """"median" or "lsq" (estimated over all evaluated views' valid pixels), "given" (--depth-scale against a
    --depth-gt folder), "given-scene" (--depth-scale against the scene's own GT depth),
    or "scene" (the scene's known factor)."""
    num_pixels: int = 0


class LpipsStatus(_Strict):
    available: bool
    reason: str


def _percent(share: float) -> str:
    """A share as a whole percentage; below 0.5 % as "<1 %" (0 stays "0 %")."""
    return "0 %" if share <= 0.0 else "<1 %" if share < 0.005 else f"{100 * share:.0f} %"


class EvalReport(SchemaFile):
    """Everything ``evaluate`` measured for one run and split (``RUN/eval/metrics.json``)."""

    FILE_NAME = "eval/metrics.json"
    SCHEMA_VERSION = SCHEMA_VERSION
    WRITTEN_BY = "uncertsplat evaluate"

    @classmethod
    def _upgrade(cls, data: dict, version: int) -> dict | None:
        # version 1 had every key but calibration_held_out (its std factor was always fitted on training views) and
        # run_sha256; version 2 every key but run_sha256 (not recorded); version 3 every key but the Student-t's
        # (its predictive was the Gaussian: the defaults); version 4 every key but variance_shares (not recorded)
        if version not in (1, 2, 3, 4):
            return None
        out = dict(data)
        if version < 3:
            out = {"run_sha256": None, **out}
        if version == 1:
            out.setdefault("calibration_held_out", False)
        return out

    schema_version: int = SCHEMA_VERSION
    split: str = "test"
    image_names: list[str] = Field(default_factory=list)
    per_view: dict[str, ViewMetrics] = Field(default_factory=dict)
    mean: ViewMetrics = Field(default_factory=ViewMetrics)
    curves: dict[str, CurveSet] = Field(default_factory=dict)
    """Keyed by "mean" and by image name."""
    calibration: dict[str, CalibrationTable] = Field(default_factory=dict)
    """Mean over views, keyed "rgb" and (with GT depth) "depth"."""
    config_hash: str = ""
    versions: dict[str, str] = Field(default_factory=dict)
    num_samples: int = Field(1, ge=1)
    seed: int | None = None
    seconds_per_view: float | None = None
    ause_steps: int = 100
    std_floor: float | None = None
    kde_bandwidth: str = "silverman: max(1.06 * std_hat * K^(-1/5), floor)"
    depth_scale: DepthScaleInfo | None = None
    std_scale: float | None = None
    """Factor for the RGB std fitted on training views, or on views set aside from training
    (``eval.engine.fit_std_scale``); None = not fitted."""
    degrees_of_freedom: float | None = None
    """nu of the RGB predictive's Student-t (``EvalConfig.degrees_of_freedom``; ``eval.tails``), fitted on
    ``calibration_views`` or set; None: the Gaussian."""
    calibration_views: list[str] = Field(default_factory=list)
    """The images ``std_scale`` (and a fitted ``degrees_of_freedom``) was fitted on."""
    calibration_held_out: bool = False
    """True: the scene set views aside from training (``SceneConfig.calibration_holdout``), and the std factor
    (``calibration_views``) and a fitted pixel-noise level (``noise_scale``) were fitted on them; False: on training
    views."""
    @property
    def calibration_source(self) -> str:
        """The views the std factor and a fitted noise level come from, in words (``calibration_held_out``)."""
        return "views set aside from training" if self.calibration_held_out else "training views"

    def variance_parts(self) -> str | None:
        """``variance_shares`` in words, each modality's parts largest first ("RGB: resolution 40 %, view consistency
        39 %, ...; depth: ..."); None when not recorded. At K = 1 the samples' 0 % says why (one sample has no
        spread: not a posterior that knows everything)."""
        names = {"samples": "the samples' spread"}
        out = []
        for modality, label in (("rgb", "RGB"), ("depth", "depth")):
            shares = self.variance_shares.get(modality)
            if shares:
                ranked = sorted(shares.items(), key=lambda kv: -kv[1])
                out.append(f"{label}: " + ", ".join(f"{names.get(k, k)} {_percent(v)}" + (
                    " (K = 1: one sample has no spread)" if k == "samples" and self.num_samples == 1 else "")
                    for k, v in ranked))
        return "; ".join(out) or None

    noise_scale: float | None = None
    """The factor the pixel noise (``EvalConfig.residual_views``) carries: fitted so that the predictive's
    z-scores have unit variance (``eval.engine.fit_noise_scale``) on the views set aside from training
    (``calibration_held_out``) or on training views (``EvalConfig.residual_scale``), or set; None without the
    pixel-noise term, or in reports from before it was scaled (factor 1)."""
    edge_scale: float | None = None
    """delta^2 (pixels^2) of the pixel noise's edge term (``EvalConfig.edge_noise``): 0 without it, None without the
    pixel-noise term or in reports from before it."""
    lpips: LpipsStatus | None = None
    device: str | None = None
    variance_shares: dict[str, dict[str, float]] = Field(default_factory=dict)
    """What the predictive's variance is made of on the scored pixels: {"rgb": {part: share}, "depth": {...}}, each
    part's mean variance over the views' scored pixels (depth: those the samples cover, mean alpha above 0.5) as a
    share of their sum, before the std factor and the RGB std's cap. Parts in the order they are added: "samples" (the
    spread of the K renders: the posterior's, or an ensemble's members'), "resolution", "empty rays", "pixel noise",
    "colour posterior", "edge", "view consistency", "exposure"; for depth also "depth spread" and "hidden surface".
    Empty when not recorded (files of schema version 4 and older)."""
    run_sha256: str | None = None
    """What was scored: a SHA-256 over the model file (``variational.ply`` or the method's file) and the run's
    ``config.json`` and ``scene.json`` (``stages.evaluate.run_sha256``); None: not recorded (files of schema version
    2 and older) or a model of several files (an ensemble). ``prune`` reads this evaluation's held-out means as its
    "before" row when these, the settings and the versions are the same."""
    notes: list[str] = Field(default_factory=list)

    @field_validator("seconds_per_view", "std_floor", mode="before")
    @classmethod
    def _nonfinite_to_none(cls, v):
        return _finite_or_none(v)

    @classmethod
    def from_json(cls, text: str | bytes) -> EvalReport:
        """Parse and validate metrics.json text (raises pydantic.ValidationError on mismatch)."""
        return cls.model_validate_json(text)
