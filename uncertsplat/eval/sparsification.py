"""Sparsification curves and AUSE (Area Under the Sparsification Error), with deterministic ties.

Definitions (docs/method.md, "Evaluation protocol"). Given per-element errors e_i >= 0
and uncertainties u_i (RGB channels count as separate elements), for removal fractions
r_j = j / S, j = 0 .. S-1 (S = ``steps``, default 100, so r runs from 0 to 0.99):

- the number of kept elements is n_j = max(1, floor((S - j) * n / S)) (exact integer arithmetic, so
  no floating-point off-by-one at fractions like 0.29);
- oracle curve O(r_j): the error of the n_j smallest errors (remove the largest errors first);
- uncertainty curve U(r_j): the error of the n_j least uncertain elements (remove the most
  uncertain first);
- "error of a kept set" is the mean |e| (MAE), the mean e^2 (MSE) or sqrt(mean e^2) (RMSE);
- normalisation: both curves are divided by max(max O, max U). This is the "larger of their
  maxima" convention of the official code: it keeps both curves on one scale in [0, 1] (dividing each
  by its own maximum would hide an uncertainty curve that rises above the starting error). O is
  non-increasing, so max O = O(0) = U(0) = the error of all elements; the shared maximum differs
  from it only when U rises above its starting value. All errors zero -> both curves are 0 and AUSE 0;
- AUSE = trapezoid integral over r of (U - O); AURG = trapezoid integral of (R - U), where the random
  curve R is constant at the overall error (what a random uncertainty gives in expectation).

Ties (docs/method.md, the original code's defect 2): large areas have an uncertainty of exactly 0, and with a plain sort the
official code's result depends on the order in which tied elements happen to come. Here elements with
equal uncertainty form one group; when a cut falls inside a group, each of the group's kept elements
counts with the group's *mean* error (mean squared error for MSE/RMSE). This is the expectation of
the curve over all random orders within the tie, so the result does not depend on the input order
(it is invariant under any permutation of the elements). Ties in the error do not matter for the
oracle (equal values).

Cost: two sorts of n elements (O(n log n)) and prefix sums in float64; 10^6 elements take well
under a second on a CPU.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from uncertsplat.eval._common import broadcast_mask

Metric = Literal["mae", "mse", "rmse"]
METRICS: tuple[Metric, ...] = ("mae", "mse", "rmse")


@dataclass(frozen=True)
class SparsificationResult:
    """One sparsification analysis.

    Attributes:
        metric: "mae", "mse" or "rmse".
        fractions: [S] removal fractions r_j = j / S.
        oracle: [S] normalised oracle curve.
        uncertainty: [S] normalised uncertainty curve.
        ause: trapezoid integral of (uncertainty - oracle) over the fractions.
        aurg: trapezoid integral of (random - uncertainty); > 0 means better than random.
        scale: the normalising constant (the larger of the two raw curve maxima).
        num_elements: number of valid elements used.
    """

    metric: str
    fractions: Tensor
    oracle: Tensor
    uncertainty: Tensor
    ause: float
    aurg: float
    scale: float
    num_elements: int


def flatten_valid(error: Tensor, uncertainty: Tensor, mask: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Flatten |error| and uncertainty to [n] over valid, finite elements.

    ``uncertainty`` may have a trailing channel dim of 1 against an error with several channels
    (one std per pixel shared by the channels); ``mask`` may omit the channel dim. Elements whose
    error or uncertainty is not finite are dropped (they carry no usable ranking).
    """
    err = error.abs()
    unc = uncertainty.expand_as(err) if uncertainty.shape != err.shape else uncertainty
    valid = torch.isfinite(err) & torch.isfinite(unc)
    if mask is not None:
        valid = valid & broadcast_mask(mask, err.shape)
    return err[valid], unc[valid]


def _keep_counts(n: int, steps: int, device) -> Tensor:
    j = torch.arange(steps, device=device, dtype=torch.long)
    return ((steps - j) * n // steps).clamp_min(1)  # [S]


def _tie_averaged(values_sorted: Tensor, keys_sorted: Tensor) -> Tensor:
    """Replace each value by the mean value of its group of equal (sorted) keys."""
    _, inverse, counts = torch.unique_consecutive(keys_sorted, return_inverse=True, return_counts=True)
    sums = torch.zeros(counts.shape[0], dtype=values_sorted.dtype, device=values_sorted.device)
    sums.index_add_(0, inverse, values_sorted)
    return (sums / counts.to(values_sorted.dtype))[inverse]


def _curve_from_prefix(prefix: Tensor, keep: Tensor, sqrt: bool) -> Tensor:
    """Mean of the first keep[j] elements from a prefix-sum array (prefix[0] = 0)."""
    mean = prefix[keep] / keep.to(prefix.dtype)
    return mean.clamp_min(0).sqrt() if sqrt else mean


def sparsification_all(
    error: Tensor,
    uncertainty: Tensor,
    *,
    mask: Tensor | None = None,
    steps: int = 100,
    metrics: tuple[Metric, ...] = METRICS,
) -> dict[str, SparsificationResult]:
    """Sparsification curves and AUSE for several error metrics, sharing the two sorts.

    Args:
        error: [...] signed or absolute errors (prediction - target); only |error| is used.
        uncertainty: [...] predicted std (or any score: only its order matters), same shape as
            ``error`` or with a trailing dim of 1.
        mask: optional validity mask ([...] or without the channel dim).
        steps: number of removal fractions S (r = 0, 1/S, ..., (S-1)/S).
        metrics: subset of ("mae", "mse", "rmse").

    Returns:
        {metric: SparsificationResult}. With no valid element every curve is NaN and AUSE is NaN.
    """
    if steps < 2:
        raise ValueError(f"steps must be >= 2, got {steps}")
    for m in metrics:
        if m not in METRICS:
            raise ValueError(f"unknown metric {m!r}; choose from {METRICS}")
    e, u = flatten_valid(error, uncertainty, mask)
    n = e.numel()
    device = e.device
    fractions = torch.arange(steps, dtype=torch.float64, device=device) / steps
    if n == 0:
        nan = torch.full((steps,), float("nan"), dtype=torch.float64, device=device)
        return {
            m: SparsificationResult(m, fractions, nan, nan, float("nan"), float("nan"), float("nan"), 0)
            for m in metrics
        }
    e = e.to(torch.float64)
    keep = _keep_counts(n, steps, device)
    zero = torch.zeros(1, dtype=torch.float64, device=device)

    # Oracle: ascending errors; keeping the n_j smallest = removing the largest first.
    e_sorted, _ = torch.sort(e)
    # Uncertainty: ascending uncertainty; keeping the n_j least uncertain.
    u_sorted, order = torch.sort(u)
    e_by_u = e[order]

    results = {}
    for m in metrics:
        power = 1 if m == "mae" else 2
        oracle_vals = e_sorted if power == 1 else e_sorted.square()
        unc_vals = _tie_averaged(e_by_u if power == 1 else e_by_u.square(), u_sorted)
        sqrt = m == "rmse"
        oracle = _curve_from_prefix(torch.cat([zero, oracle_vals.cumsum(0)]), keep, sqrt)
        unc = _curve_from_prefix(torch.cat([zero, unc_vals.cumsum(0)]), keep, sqrt)
        scale = float(torch.maximum(oracle.max(), unc.max()))
        if scale > 0:
            oracle_n, unc_n = oracle / scale, unc / scale
            random_n = torch.full_like(oracle, float(unc[0]) / scale)
        else:  # all errors zero: nothing to rank, perfect by definition
            oracle_n, unc_n, random_n = torch.zeros_like(oracle), torch.zeros_like(unc), torch.zeros_like(unc)
        ause = float(torch.trapezoid(unc_n - oracle_n, fractions))
        aurg = float(torch.trapezoid(random_n - unc_n, fractions))
        results[m] = SparsificationResult(m, fractions, oracle_n, unc_n, ause, aurg, scale, n)
    return results


def sparsification(
    error: Tensor,
    uncertainty: Tensor,
    *,
    metric: Metric = "mae",
    mask: Tensor | None = None,
    steps: int = 100,
) -> SparsificationResult:
    """Sparsification curves and AUSE for one metric; see :func:`sparsification_all`."""
    return sparsification_all(error, uncertainty, mask=mask, steps=steps, metrics=(metric,))[metric]


def ause(
    error: Tensor,
    uncertainty: Tensor,
    *,
    metric: Metric = "mae",
    mask: Tensor | None = None,
    steps: int = 100,
) -> float:
    """AUSE only (see :func:`sparsification_all`)."""
    return sparsification(error, uncertainty, metric=metric, mask=mask, steps=steps).ause


def mean_curves(results: list[SparsificationResult]) -> SparsificationResult:
    """Average per-view results (curves, AUSE, AURG) into one, as tables average AUSE over views.

    The mean AUSE equals the AUSE of the mean curves (the integral is linear), so the saved mean
    curves are consistent with the reported mean AUSE. Views with no valid element are skipped.
    """
    ok = [r for r in results if r.num_elements > 0]
    if not ok:
        raise ValueError("no view has valid elements")
    metric = ok[0].metric
    if any(r.metric != metric or r.fractions.shape != ok[0].fractions.shape for r in ok):
        raise ValueError("cannot average curves of different metrics or step counts")
    oracle = torch.stack([r.oracle for r in ok]).mean(0)
    unc = torch.stack([r.uncertainty for r in ok]).mean(0)
    return SparsificationResult(
        metric=metric,
        fractions=ok[0].fractions,
        oracle=oracle,
        uncertainty=unc,
        ause=sum(r.ause for r in ok) / len(ok),
        aurg=sum(r.aurg for r in ok) / len(ok),
        scale=float("nan"),  # per-view scales differ; the mean curves are averages of normalised ones
        num_elements=sum(r.num_elements for r in ok),
    )
