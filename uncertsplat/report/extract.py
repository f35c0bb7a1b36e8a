"""Find the report's quantities in a metrics.json / prune.json / stats.jsonl, whatever their exact layout.

The EvalReport schema may gain fields or nest curves differently between versions; the report finds
sparsification curves (objects with ``fractions``, ``oracle`` and ``uncertainty``) and calibration
tables (``nominal`` with ``observed``/``empirical``) wherever they are, and names scalar metrics
through one table of aliases. Values are never transformed: what the report shows is what the file says.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from uncertsplat.report.loader import as_float, first_key


@dataclass(frozen=True)
class MetricSpec:
    """A metric column: the keys it may be stored under, its label, number format and direction."""

    key: str
    aliases: tuple[str, ...]
    label: str
    fmt: str
    higher_is_better: bool | None


# Order = column order in the tables. Unknown scalar keys are shown after these, under their own names.
METRIC_SPECS: tuple[MetricSpec, ...] = (
    MetricSpec("psnr", ("psnr",), "PSNR (dB)", ".2f", True),
    MetricSpec("psnr_render", ("psnr_render",), "PSNR, one render (dB)", ".2f", True),
    MetricSpec("ssim", ("ssim",), "SSIM", ".4f", True),
    MetricSpec("lpips", ("lpips",), "LPIPS", ".4f", False),
    MetricSpec("ause_mae", ("ause_mae", "ause"), "AUSE MAE", ".4f", False),
    MetricSpec("ause_rmse", ("ause_rmse",), "AUSE RMSE", ".4f", False),
    MetricSpec("ause_mse", ("ause_mse",), "AUSE MSE", ".4f", False),
    MetricSpec("nll", ("nll", "nll_gaussian", "gaussian_nll"), "NLL", ".3f", False),
    MetricSpec("nll_kde", ("nll_kde", "kde_nll"), "NLL (KDE)", ".3f", False),
    MetricSpec("nll_paper", ("nll_paper", "paper_nll"), "NLL (paper formula)", ".3f", False),
    MetricSpec("calibration_error", ("calibration_error", "calib_error", "ece", "calibration_ece"),
               "Calib. error", ".4f", False),
    MetricSpec("nll_calibrated", ("nll_calibrated",), "NLL, std rescaled on train views", ".3f", False),
    MetricSpec("calibration_error_calibrated", ("calibration_error_calibrated",),
               "Calib. error, std rescaled", ".4f", False),
    MetricSpec("spearman", ("spearman", "spearman_rgb"), "Spearman", ".3f", True),
    MetricSpec("depth_ause_mae", ("depth_ause_mae", "depth_ause", "ause_depth_mae", "ause_depth"),
               "Depth AUSE MAE", ".4f", False),
    MetricSpec("depth_ause_rmse", ("depth_ause_rmse", "ause_depth_rmse"), "Depth AUSE RMSE", ".4f", False),
    MetricSpec("depth_abs_rel", ("depth_abs_rel", "depth_absrel", "abs_rel"), "Depth AbsRel", ".4f", False),
    MetricSpec("depth_rmse", ("depth_rmse",), "Depth RMSE", ".4f", False),
    MetricSpec("depth_mae", ("depth_mae",), "Depth MAE", ".4f", False),
    MetricSpec("depth_nll", ("depth_nll", "nll_depth"), "Depth NLL", ".3f", False),
    MetricSpec("depth_spearman", ("depth_spearman", "spearman_depth"), "Depth Spearman", ".3f", True),
    MetricSpec("seconds", ("seconds", "seconds_per_view"), "MC time (s)", ".3f", False),
)
_KNOWN_ALIASES = {a for s in METRIC_SPECS for a in s.aliases}

# The summary table shows these metric columns (when at least one run has them) plus run facts.
SUMMARY_KEYS = ("psnr", "psnr_render", "ssim", "ause_mae", "ause_rmse", "nll", "calibration_error", "nll_calibrated",
                "depth_ause_mae")


def _flatten_scalars(d: Any, prefix: str = "", depth: int = 0) -> dict[str, Any]:
    """{key: value} of the numeric scalars in ``d``; one level of nesting is joined with '_'."""
    out: dict[str, Any] = {}
    if not isinstance(d, dict):
        return out
    for k, v in d.items():
        name = f"{prefix}{k}"
        if isinstance(v, bool) or str(k).endswith("_note"):
            continue
        if isinstance(v, (int, float)) or v is None:
            out[name] = v
        elif isinstance(v, dict) and depth == 0:
            out.update(_flatten_scalars(v, f"{name}_", depth + 1))
    return out


@dataclass(frozen=True)
class MetricValue:
    """One shown number: the key it came from and the raw value exactly as in the file."""

    spec: MetricSpec
    source_key: str
    value: Any  # as in the file (may be None / NaN)


def metric_row(d: dict | None) -> dict[str, MetricValue]:
    """The metrics of one row (a view's or the mean), by spec key, in METRIC_SPECS order then unknowns."""
    flat = _flatten_scalars(d)
    row: dict[str, MetricValue] = {}
    for spec in METRIC_SPECS:
        for alias in spec.aliases:
            if alias in flat:
                row[spec.key] = MetricValue(spec, alias, flat[alias])
                break
    for k, v in flat.items():
        if k in _KNOWN_ALIASES or k in row:
            continue
        row[k] = MetricValue(MetricSpec(k, (k,), k, ".4g", None), k, v)
    return row


def format_value(value: Any, fmt: str) -> str:
    """The text shown for a value; 'n/a' for missing or non-finite numbers."""
    f = as_float(value)
    if f is None:
        return "n/a"
    if isinstance(value, int) and not isinstance(value, bool) and fmt in (".4g", ".4f", ".3f"):
        return f"{value:,}"
    return format(f, fmt)


# --------------------------------------------------------------------------------------------- metrics
def per_view_metrics(metrics: dict | None) -> dict[str, dict]:
    """{image name: metrics dict} from metrics.json (per_view as a dict by name, or a list with names)."""
    pv = first_key(metrics, ("per_view", "views", "per_image"))
    if isinstance(pv, dict):
        return {str(k): v for k, v in pv.items() if isinstance(v, dict)}
    if isinstance(pv, list):
        out = {}
        for i, v in enumerate(pv):
            if isinstance(v, dict):
                name = first_key(v, ("image", "name", "image_name")) or f"view {i}"
                out[str(name)] = v
        return out
    return {}


def mean_metrics(metrics: dict | None) -> dict:
    m = first_key(metrics, ("mean", "average", "summary"))
    return m if isinstance(m, dict) else {}


# ---------------------------------------------------------------------------------------------- curves
@dataclass(frozen=True)
class Curve:
    """One sparsification analysis found in metrics.json."""

    path: tuple[str, ...]
    metric: str  # mae / mse / rmse
    fractions: np.ndarray
    oracle: np.ndarray
    uncertainty: np.ndarray
    ause: float | None
    view: str | None  # None for the mean curve
    depth: bool


def _is_curve(d: Any) -> bool:
    return isinstance(d, dict) and all(k in d for k in ("fractions", "oracle", "uncertainty"))


def _walk(obj: Any, path: tuple[str, ...], found: list, pred, max_depth: int = 6) -> None:
    if pred(obj):
        found.append((path, obj))
        return
    if max_depth <= 0:
        return
    if isinstance(obj, dict):
        for k, v in obj.items():
            _walk(v, path + (str(k),), found, pred, max_depth - 1)
    elif isinstance(obj, list) and len(obj) < 10_000 and any(isinstance(v, dict) for v in obj[:5]):
        for i, v in enumerate(obj):
            _walk(v, path + (str(i),), found, pred, max_depth - 1)


def _array(v: Any) -> np.ndarray | None:
    try:
        a = np.asarray(v, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        return None
    return a if a.size >= 2 else None


def _schema_curves(curves: dict) -> list[Curve]:
    """The EvalReport layout: ``curves[key][modality][metric]``, key = "mean" or an image name."""
    out = []
    for key, sets in curves.items():
        if not isinstance(sets, dict):
            continue
        for modality, by_metric in sets.items():
            if not isinstance(by_metric, dict):
                continue
            for metric, d in by_metric.items():
                if not _is_curve(d):
                    continue
                fr, orc, unc = _array(d["fractions"]), _array(d["oracle"]), _array(d["uncertainty"])
                if fr is None or orc is None or unc is None or not (fr.size == orc.size == unc.size):
                    continue
                out.append(Curve(("curves", str(key), str(modality), str(metric)), str(d.get("metric") or metric).lower(),
                                 fr, orc, unc, as_float(d.get("ause")), None if key == "mean" else str(key),
                                 str(modality).lower() == "depth"))
    return out


def find_curves(metrics: dict | None, view_names: list[str]) -> list[Curve]:
    """Every sparsification curve in metrics.json, tagged with its view (None = mean) and modality."""
    if not isinstance(metrics, dict):
        return []
    if isinstance(metrics.get("curves"), dict):
        got = _schema_curves(metrics["curves"])
        if got:
            return got
    found: list = []
    _walk(metrics, (), found, _is_curve)
    names = set(view_names)
    curves = []
    for path, d in found:
        fr, orc, unc = _array(d["fractions"]), _array(d["oracle"]), _array(d["uncertainty"])
        if fr is None or orc is None or unc is None or not (fr.size == orc.size == unc.size):
            continue
        metric = str(d.get("metric") or next((p for p in reversed(path) if p.lower() in ("mae", "mse", "rmse")),
                                             "mae")).lower()
        view = next((p for p in path if p in names), None)
        is_mean = view is None and any("mean" in p.lower() for p in path)
        if view is None and not is_mean:
            # a per-view list with an "image" field, or a top-level curve: treat unnamed as the mean
            view = d.get("image") if isinstance(d.get("image"), str) else None
        depth = any("depth" in p.lower() for p in path) or str(d.get("modality", "")).lower() == "depth"
        curves.append(Curve(path, metric, fr, orc, unc, as_float(d.get("ause")), view, depth))
    return curves


# ---------------------------------------------------------------------------------------- calibration
@dataclass(frozen=True)
class Calibration:
    """Observed vs nominal coverage (fraction of errors within k std)."""

    nominal: np.ndarray
    observed: np.ndarray
    k: np.ndarray | None
    depth: bool
    path: tuple[str, ...]


_OBS_KEYS = ("observed", "empirical", "fraction", "coverage", "observed_fraction", "empirical_fraction")
_NOM_KEYS = ("nominal", "expected", "nominal_fraction", "expected_fraction")


def _calibration_from(obj: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray | None] | None:
    if isinstance(obj, dict):
        nom, obs = first_key(obj, _NOM_KEYS), first_key(obj, _OBS_KEYS)
        if isinstance(nom, list) and isinstance(obs, list):
            n, o = _array(nom), _array(obs)
            k = _array(first_key(obj, ("k", "ks", "k_values", "sigmas")) or [])
            if n is not None and o is not None and n.size == o.size:
                return n, o, (k if k is not None and k.size == n.size else None)
            return None
        # {"1.0": {"nominal":..., "observed":...}, ...}
        rows = [v for v in obj.values() if isinstance(v, dict)]
        if rows and len(rows) == len(obj):
            got = _calibration_from(rows)
            if got is not None:
                ks = []
                for key in obj:
                    f = _try_float(key)
                    ks.append(f)
                if all(k is not None for k in ks):
                    return got[0], got[1], np.asarray(ks, dtype=np.float64)
                return got
    if isinstance(obj, list) and obj and all(isinstance(v, dict) for v in obj):
        nom = [as_float(first_key(v, _NOM_KEYS)) for v in obj]
        obs = [as_float(first_key(v, _OBS_KEYS)) for v in obj]
        ks = [as_float(first_key(v, ("k", "sigma"))) for v in obj]
        if all(x is not None for x in nom) and all(x is not None for x in obs) and len(nom) >= 2:
            k = np.asarray(ks, dtype=np.float64) if all(x is not None for x in ks) else None
            return np.asarray(nom, dtype=np.float64), np.asarray(obs, dtype=np.float64), k
    return None


def _try_float(s: Any) -> float | None:
    try:
        return float(s)
    except (TypeError, ValueError):
        return None


def find_calibration(metrics: dict | None) -> list[Calibration]:
    """Calibration tables of the mean (not per view), RGB first then depth."""
    if not isinstance(metrics, dict):
        return []
    out: list[Calibration] = []
    for key, value in metrics.items():
        if key in ("per_view", "views", "per_image"):
            continue
        if "calib" not in key.lower() and "coverage" not in key.lower() and "reliab" not in key.lower():
            if not (isinstance(value, dict) and any("calib" in str(k).lower() for k in value)):
                continue
        candidates: list = []
        _walk(value, (key,), candidates, lambda o: _calibration_from(o) is not None, max_depth=4)
        for path, obj in candidates:
            got = _calibration_from(obj)
            assert got is not None
            nom, obs, k = got
            depth = any("depth" in p.lower() for p in path)
            out.append(Calibration(nom, obs, k, depth, path))
    out.sort(key=lambda c: c.depth)
    return out
