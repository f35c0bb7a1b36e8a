"""Calibration of predicted std against observed errors, and Spearman rank correlation.

Calibration: for each k, the central interval of the predictive with the probability a Gaussian gives
mean +- k std, erf(k / sqrt 2) (0.383, 0.683, 0.866, 0.954, 0.988, 0.997 for k = 0.5 .. 3), is compared
with the observed fraction of elements inside it. For the Gaussian predictive the interval is |error| <= k std;
for a Student-t predictive with ``dof`` degrees of freedom and the same std (``eval.tails``) it is
|error| <= w std, w the t's half-width for that probability (narrower at small k, wider at k = 3).
Calibration error = mean |observed - nominal| over the k values (0 = the intervals hold as often as
claimed; over-confident stds give observed < nominal).

Spearman: Pearson correlation of average ranks (ties share the mean of their ranks, so large areas of
std exactly 0 are handled consistently). A constant input has no ranking: the value is then None with
a reason, never NaN.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from uncertsplat.eval._common import broadcast_mask
from uncertsplat.eval.tails import half_width

DEFAULT_KS: tuple[float, ...] = (0.5, 1.0, 1.5, 2.0, 2.5, 3.0)


@dataclass(frozen=True)
class CalibrationResult:
    """Observed vs nominal coverage of the predictive's central intervals.

    Attributes:
        ks: the levels, as the Gaussian's half-widths in units of std (k = 1: the probability 0.683).
        observed: fraction of elements inside the interval, per k.
        nominal: erf(k / sqrt 2), per k: the interval's probability.
        calibration_error: mean |observed - nominal| (NaN if there is no valid element).
        num_elements: number of valid elements.
        half_widths: the intervals' half-widths in units of std (the ks for the Gaussian).
        dof: the Student-t's degrees of freedom (None: the Gaussian).
    """

    ks: tuple[float, ...]
    observed: tuple[float, ...]
    nominal: tuple[float, ...]
    calibration_error: float
    num_elements: int
    half_widths: tuple[float, ...] = ()
    dof: float | None = None


def nominal_coverage(k: float) -> float:
    """P(|Z| <= k) for a standard normal Z: erf(k / sqrt 2)."""
    return math.erf(k / math.sqrt(2.0))


def _valid(error: Tensor, std: Tensor, mask: Tensor | None) -> tuple[Tensor, Tensor]:
    err = error.abs()
    s = std.expand_as(err) if std.shape != err.shape else std
    valid = torch.isfinite(err) & torch.isfinite(s)
    if mask is not None:
        valid = valid & broadcast_mask(mask, err.shape)
    return err[valid], s[valid]


def calibration(
    error: Tensor,
    std: Tensor,
    *,
    ks: tuple[float, ...] = DEFAULT_KS,
    mask: Tensor | None = None,
    dof: float | None = None,
) -> CalibrationResult:
    """Coverage of each k's central interval of the predictive (Gaussian: |error| <= k * std), against its
    probability erf(k / sqrt 2).

    Args:
        error: [...] prediction - target (sign ignored).
        std: [...] predicted std, or broadcastable (trailing dim 1). A zero std covers only exact
            hits (|error| == 0), which is the honest reading of a zero-width interval.
        ks: interval half-widths in std units.
        mask: optional validity mask.
        dof: the degrees of freedom of a Student-t predictive with this std (``eval.tails``); None: the Gaussian.
    """
    e, s = _valid(error, std, mask)
    n = e.numel()
    nominal = tuple(nominal_coverage(k) for k in ks)
    widths = tuple(float(k) if dof is None else half_width(p, dof) for k, p in zip(ks, nominal, strict=True))
    if n == 0:
        nan = tuple(float("nan") for _ in ks)
        return CalibrationResult(tuple(ks), nan, nominal, float("nan"), 0, widths, dof)
    observed = tuple(float((e <= w * s).to(torch.float64).mean()) for w in widths)
    cal_err = sum(abs(o - m) for o, m in zip(observed, nominal, strict=True)) / len(ks)
    return CalibrationResult(tuple(ks), observed, nominal, cal_err, n, widths, dof)


def mean_calibration(results: list[CalibrationResult]) -> CalibrationResult:
    """Average per-view calibration tables (each view weighs the same, like the other metrics)."""
    ok = [r for r in results if r.num_elements > 0]
    if not ok:
        raise ValueError("no view has valid elements")
    ks = ok[0].ks
    if any(r.ks != ks or r.half_widths != ok[0].half_widths for r in ok):
        raise ValueError("cannot average calibration tables with different k values or predictives")
    observed = tuple(sum(r.observed[i] for r in ok) / len(ok) for i in range(len(ks)))
    nominal = ok[0].nominal
    cal_err = sum(abs(o - m) for o, m in zip(observed, nominal, strict=True)) / len(ks)
    return CalibrationResult(ks, observed, nominal, cal_err, sum(r.num_elements for r in ok), ok[0].half_widths,
                             ok[0].dof)


def average_ranks(x: Tensor) -> Tensor:
    """Ranks 1..n of a 1-D tensor [n] in float64, ties getting the mean of their ranks."""
    n = x.numel()
    sorted_x, order = torch.sort(x)
    _, inverse, counts = torch.unique_consecutive(sorted_x, return_inverse=True, return_counts=True)
    ends = counts.cumsum(0).to(torch.float64)  # 1-based rank of each group's last element
    group_rank = ends - (counts.to(torch.float64) - 1) / 2  # mean of ranks start..end
    ranks = torch.empty(n, dtype=torch.float64, device=x.device)
    ranks[order] = group_rank[inverse]
    return ranks


@dataclass(frozen=True)
class SpearmanResult:
    """Spearman rank correlation; ``value`` is None (with a ``reason``) when it is undefined."""

    value: float | None
    reason: str | None
    num_elements: int


def spearman(x: Tensor, y: Tensor, *, mask: Tensor | None = None) -> SpearmanResult:
    """Spearman correlation of x and y over valid elements (e.g. x = std, y = |error|).

    ``x`` may broadcast against ``y`` (a [H,W,1] std against a [H,W,3] error). Non-finite elements
    are dropped. Undefined (None, with a reason) for fewer than 2 elements or a constant input.
    """
    y_ = y
    x_ = x.expand_as(y_) if x.shape != y_.shape else x
    valid = torch.isfinite(x_) & torch.isfinite(y_)
    if mask is not None:
        valid = valid & broadcast_mask(mask, y_.shape)
    a, b = x_[valid], y_[valid]
    n = a.numel()
    if n < 2:
        return SpearmanResult(None, f"undefined: {n} valid element(s)", n)
    if bool((a == a[0]).all()):
        return SpearmanResult(None, "undefined: the uncertainty is constant", n)
    if bool((b == b[0]).all()):
        return SpearmanResult(None, "undefined: the error is constant", n)
    ra, rb = average_ranks(a), average_ranks(b)
    ra = ra - ra.mean()
    rb = rb - rb.mean()
    value = float((ra * rb).sum() / torch.sqrt(ra.square().sum() * rb.square().sum()))
    return SpearmanResult(max(-1.0, min(1.0, value)), None, n)
