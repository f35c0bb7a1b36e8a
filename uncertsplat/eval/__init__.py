"""Metrics: image quality, sparsification/AUSE, NLL, calibration, depth, and the EvalReport schema;
the evaluation engine that renders K samples per view and computes them all is ``eval.engine``.

Pure functions of tensors: nothing here reads or writes files, imports config/io/stages, or
downloads anything.
"""

from uncertsplat.eval.calibration import (
    CalibrationResult,
    SpearmanResult,
    calibration,
    mean_calibration,
    nominal_coverage,
    spearman,
)
from uncertsplat.eval.depth import DepthMetrics, DepthScale, align_depth_scale, depth_metrics
from uncertsplat.eval.image import lpips, lpips_available, psnr, ssim
from uncertsplat.eval.nll import gaussian_nll, kde_bandwidth, kde_nll, paper_nll, predictive_nll
from uncertsplat.eval.sparsification import (
    SparsificationResult,
    ause,
    mean_curves,
    sparsification,
    sparsification_all,
)
from uncertsplat.schemas.metrics import EvalReport, ViewMetrics

__all__ = [
    "CalibrationResult",
    "DepthMetrics",
    "DepthScale",
    "EvalReport",
    "SparsificationResult",
    "SpearmanResult",
    "ViewMetrics",
    "align_depth_scale",
    "ause",
    "calibration",
    "depth_metrics",
    "gaussian_nll",
    "predictive_nll",
    "kde_bandwidth",
    "kde_nll",
    "lpips",
    "lpips_available",
    "mean_calibration",
    "mean_curves",
    "nominal_coverage",
    "paper_nll",
    "psnr",
    "sparsification",
    "sparsification_all",
    "spearman",
    "ssim",
]
