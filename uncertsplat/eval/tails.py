"""The predictive's tails: a Student-t with the predicted std, its degrees of freedom fitted on views not scored.

A pixel's error given its predicted std is not Gaussian: the std is a local estimate of the error's scale and the
error's true scale varies around it, so over many pixels the z-scores error / std are a scale mixture of Gaussians,
with a kurtosis of 9-14 on the demo, fern and bonsai (3 for a Gaussian; BENCHMARKS.md, "The predictive's tails").
A Gaussian of the right variance then covers too much at one std and too little at three, and its NLL pays for
every tail pixel. A Student-t with nu degrees of freedom is the scale mixture whose mixing law is an inverse gamma;
we parameterise it by its std (so the std maps keep their meaning and the variance terms still add):

    T = std * sqrt((nu - 2) / nu) * t_nu,   nu > 2,

i.e. the *unit-variance* t, with density c (1 + z^2 / (nu - 2))^(-(nu + 1) / 2), c = Gamma((nu + 1) / 2) /
(Gamma(nu / 2) sqrt(pi (nu - 2))). nu -> infinity is the Gaussian (``dof = None`` everywhere here).

Pure functions of tensors and floats; the coverage is integrated numerically in float64 (no scipy in the
package; the tests compare with scipy's t).
"""

from __future__ import annotations

import functools
import math

import torch
from torch import Tensor

MIN_DOF = 2.1
"""Smallest nu fitted or accepted: at 2 the variance is infinite, so a std cannot describe the distribution."""
MAX_DOF = 1000.0
"""Largest nu fitted; a fit at this end is reported as the Gaussian (the two differ by less than 1e-3 in coverage).
``config.MAX_DEGREES_OF_FREEDOM``, the largest nu accepted, is this (tested)."""
FIT_ELEMENTS = 1_000_000
"""At most this many z-scores (evenly strided) enter ``fit_dof``: more change nu in the third digit."""
MIN_FIT_ELEMENTS = 1000
"""``fit_dof`` needs at least this many finite z-scores (a few hundred tail pixels decide nu); fewer: the Gaussian."""


def _check(dof: float | None) -> None:
    if dof is not None and not (math.isfinite(dof) and dof >= MIN_DOF):
        raise ValueError(f"degrees of freedom must be >= {MIN_DOF} (or None for the Gaussian), got {dof}")


def _log_norm(dof: float) -> float:
    """log c of the unit-variance t."""
    return math.lgamma((dof + 1) / 2) - math.lgamma(dof / 2) - 0.5 * math.log(math.pi * (dof - 2))


def log_density(z: Tensor, dof: float | None) -> Tensor:
    """log p(z) [...] of the unit-variance t with ``dof`` degrees of freedom (None: the standard Gaussian)."""
    _check(dof)
    if dof is None:
        return -0.5 * z.square() - 0.5 * math.log(2 * math.pi)
    return _log_norm(dof) - 0.5 * (dof + 1) * torch.log1p(z.square() / (dof - 2))


def _simpson(f, a: float, b: float, n: int) -> float:
    """Simpson's rule of ``f`` (a float64 tensor function) over [a, b] with n (even) intervals."""
    x = torch.linspace(a, b, n + 1, dtype=torch.float64)
    w = torch.ones(n + 1, dtype=torch.float64)
    w[1:-1:2], w[2:-1:2] = 4.0, 2.0
    return float((f(x) * w).sum()) * (b - a) / (3 * n)


_BODY = 20.0
"""``coverage`` integrates [0, min(x, 20)] on a uniform grid and what lies beyond in log u (a power law there)."""


def coverage(x: float, dof: float | None) -> float:
    """P(|Z| <= x) for the unit-variance t (None: the Gaussian, erf(x / sqrt 2)); x in std units, >= 0."""
    _check(dof)
    if x <= 0.0:
        return 0.0
    if dof is None:
        return math.erf(x / math.sqrt(2.0))
    if math.isinf(x):
        return 1.0

    def pdf(u: Tensor) -> Tensor:
        return torch.exp(log_density(u, dof))

    # the density's width is its scale sqrt((nu - 2) / nu) >= 0.22: a step of 0.0025 resolves it to ~1e-10
    body = _simpson(pdf, 0.0, min(x, _BODY), 8000)
    tail = 0.0
    if x > _BODY:
        tail = _simpson(lambda w: pdf(torch.exp(w)) * torch.exp(w), math.log(_BODY), math.log(x), 4000)
    return min(1.0, 2.0 * (body + tail))


@functools.lru_cache(maxsize=256)
def half_width(p: float, dof: float | None) -> float:
    """The x with P(|Z| <= x) = p for the unit-variance t (None: the Gaussian): the central interval of probability
    p is mean +- x std. Bisection to 1e-10 relative."""
    _check(dof)
    if not 0.0 <= p < 1.0:
        percent = f" (a probability, not a percentage: {p / 100:g} for a {p:g} % interval)" if 1.0 < p < 100.0 else ""
        raise ValueError(f"a central interval's probability must be in [0, 1), got {p}{percent}")
    if p == 0.0:
        return 0.0
    lo, hi = 0.0, 1.0
    while coverage(hi, dof) < p:
        lo, hi = hi, hi * 4.0
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        if coverage(mid, dof) < p:
            lo = mid
        else:
            hi = mid
        if hi - lo <= 1e-10 * hi:
            break
    return 0.5 * (lo + hi)


def nll(target: Tensor, mean: Tensor, std: Tensor, dof: float | None, *, std_floor: float = 1e-3) -> Tensor:
    """Per-element NLL [...] of ``target`` under the predictive with this ``mean``, ``std`` (floored at
    ``std_floor``, as ``eval.nll.gaussian_nll``) and ``dof`` (None: the Gaussian, ``gaussian_nll`` exactly)."""
    if std_floor <= 0:
        raise ValueError(f"std_floor must be > 0, got {std_floor}")
    s = std.clamp_min(std_floor)
    return torch.log(s) - log_density((target - mean) / s, dof)


def fit_dof(z: Tensor) -> float | None:
    """The maximum-likelihood degrees of freedom of the unit-variance t for z-scores ``z`` [...] whose variance is 1
    (divide by their RMS first: the std's level is the std factor's business, the tails are this one's).

    A grid over log(nu - 2) from ``MIN_DOF`` to ``MAX_DOF`` with the Gaussian beside it, then golden-section search
    around the best point. Returns None (the Gaussian) when the Gaussian or the ``MAX_DOF`` end is best, or when
    there are fewer than ``MIN_FIT_ELEMENTS`` finite z-scores.
    """
    z = z.detach().reshape(-1).to(torch.float64)
    z = z[torch.isfinite(z)]
    if z.numel() < MIN_FIT_ELEMENTS:
        return None
    if z.numel() > FIT_ELEMENTS:
        z = z[:: -(-z.numel() // FIT_ELEMENTS)]
    z2 = z.square()

    def loglik(log_excess: float) -> float:
        dof = 2.0 + math.exp(log_excess)
        return _log_norm(dof) - 0.5 * (dof + 1) * float(torch.log1p(z2 / (dof - 2)).mean())

    grid = torch.linspace(math.log(MIN_DOF - 2), math.log(MAX_DOF - 2), 41).tolist()
    values = [loglik(g) for g in grid]
    best = max(range(len(grid)), key=values.__getitem__)
    gaussian = float(log_density(z, None).mean())
    if best == len(grid) - 1 or gaussian >= values[best]:
        return None
    lo, hi = grid[max(best - 1, 0)], grid[min(best + 1, len(grid) - 1)]
    ratio = (math.sqrt(5) - 1) / 2
    a, b = hi - ratio * (hi - lo), lo + ratio * (hi - lo)
    fa, fb = loglik(a), loglik(b)
    for _ in range(40):
        if fa >= fb:
            hi, b, fb = b, a, fa
            a = hi - ratio * (hi - lo)
            fa = loglik(a)
        else:
            lo, a, fa = a, b, fb
            b = lo + ratio * (hi - lo)
            fb = loglik(b)
    # exp(log(MIN_DOF - 2)) rounds to a hair below it: clamp, or the validation refuses the grid's own end
    return min(max(2.0 + math.exp(0.5 * (lo + hi)), MIN_DOF), MAX_DOF)


__all__ = ["FIT_ELEMENTS", "MAX_DOF", "MIN_DOF", "MIN_FIT_ELEMENTS", "coverage", "fit_dof", "half_width", "log_density", "nll"]
