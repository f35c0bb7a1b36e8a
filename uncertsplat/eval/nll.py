"""Negative log-likelihood of held-out pixels under the predicted distribution.

Four estimators, all per element (RGB channels are separate elements) and averaged (natural log):

- :func:`gaussian_nll`: N(target; mean, max(std, std_floor)^2). The floor (default 1e-3, i.e. a
  quarter of one 8-bit level) exists because large areas have a Monte-Carlo std of exactly 0; without
  it one such pixel with any error makes the mean NLL infinite. Its value is part of the metric and is
  written into the results.
- :func:`predictive_nll`: the same with a Student-t of that std and ``dof`` degrees of freedom (``eval.tails``;
  None: ``gaussian_nll``).
- :func:`kde_nll`: a Gaussian kernel density estimate over the K Monte-Carlo samples of each element,
  bandwidth by Silverman's rule from the *sample count*: h = 1.06 * std_hat * K^(-1/5), std_hat the
  unbiased sample std, floored at ``bandwidth_floor`` (same reason as above). Computed with
  logsumexp, so far-away targets give a large finite NLL rather than log(0).
- :func:`paper_nll`: the official code's estimator (docs/method.md, the original code's defect 1; bandwidth
  exponent +1/5 instead of -1/5, with the pixel count instead of the sample count). NOT COMPARABLE
  with a correct NLL: it depends on image resolution. Provided only to compare with published tables.
"""

from __future__ import annotations

import math
from typing import Literal

import torch
from torch import Tensor

from uncertsplat.eval import tails
from uncertsplat.eval._common import broadcast_mask

Reduction = Literal["mean", "none"]
_LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)

SILVERMAN_FACTOR = 1.06
"""Silverman's normal-reference rule: h = 1.06 * std * n^(-1/5) for n samples from a Gaussian."""


NLL_WORSE_BY = 0.01
"""Nats per pixel and channel the fitted std factor must cost the evaluated views' NLL before ``evaluate`` says to read
the raw numbers (``stages.evaluate.std_factor_notes``, and the report for older files): a few thousandths (0.003 on the
tiny scene) is no disagreement worth a warning."""


def _reduce(values: Tensor, mask: Tensor | None, reduction: Reduction) -> Tensor:
    """Mean over finite, masked elements ("mean"), or the per-element map ("none")."""
    if reduction == "none":
        return values
    valid = torch.isfinite(values)
    if mask is not None:
        valid = valid & broadcast_mask(mask, values.shape)
    if not valid.any():
        return torch.full((), float("nan"), dtype=values.dtype, device=values.device)
    return values[valid].mean()


def gaussian_nll(
    target: Tensor,
    mean: Tensor,
    std: Tensor,
    *,
    std_floor: float = 1e-3,
    mask: Tensor | None = None,
    reduction: Reduction = "mean",
) -> Tensor:
    """Gaussian NLL: 0.5 log(2 pi s^2) + (target - mean)^2 / (2 s^2), s = max(std, std_floor).

    Args:
        target, mean: [...] (e.g. [H,W,3]).
        std: [...] or broadcastable (a [H,W,1] std applies to every channel).
        std_floor: lower bound on the std (> 0), documented in the results.
        mask: optional validity mask ([...] or without the channel dim).
        reduction: "mean" (scalar over valid elements) or "none" (per element).
    """
    if std_floor <= 0:
        raise ValueError(f"std_floor must be > 0, got {std_floor}")
    s = std.clamp_min(std_floor)
    z = (target - mean) / s
    nll = 0.5 * z.square() + torch.log(s) + _LOG_SQRT_2PI
    return _reduce(nll, mask, reduction)


def predictive_nll(
    target: Tensor,
    mean: Tensor,
    std: Tensor,
    dof: float | None,
    *,
    std_floor: float = 1e-3,
    mask: Tensor | None = None,
    reduction: Reduction = "mean",
) -> Tensor:
    """NLL under the Student-t with std max(std, std_floor) and ``dof`` degrees of freedom (``eval.tails``); the
    arguments as :func:`gaussian_nll`, which it is for ``dof`` None."""
    return _reduce(tails.nll(target, mean, std, dof, std_floor=std_floor), mask, reduction)


def kde_bandwidth(sample_std: Tensor, num_samples: int, *, floor: float = 1e-3) -> Tensor:
    """Silverman's rule per element: max(1.06 * sample_std * K^(-1/5), floor).

    ``sample_std`` is the unbiased std over the K samples (0 for K = 1, so the floor applies).
    """
    if num_samples < 1:
        raise ValueError(f"num_samples must be >= 1, got {num_samples}")
    if floor <= 0:
        raise ValueError(f"floor must be > 0, got {floor}")
    return (SILVERMAN_FACTOR * sample_std * num_samples ** (-0.2)).clamp_min(floor)


KDE_CHUNK = 1 << 22
"""``_kde_log_density`` works on at most this many sample values at a time (16 MB of float32 a temporary): over the
whole [K,...] stack its temporaries took three times the samples' memory (K = 64 at 1600x1200 ran out of memory)."""


def _kde_log_density(samples: Tensor, target: Tensor, h: Tensor) -> Tensor:
    """log (1/K sum_k N(target; samples_k, h^2)) per element; samples [K,...], target/h [...]. Computed over chunks
    of the elements (``KDE_CHUNK``): the values of the whole stack's (to the bit in one chunk, as every image of up
    to ``KDE_CHUNK`` / K values is; past it a chunk's tail may take torch's scalar exp, an ulp apart)."""
    k = samples.shape[0]
    flat_s, flat_t, flat_h = samples.reshape(k, -1), target.reshape(-1), h.expand_as(target).reshape(-1)
    out = torch.empty_like(flat_t)
    step = max(1, KDE_CHUNK // max(k, 1))
    for a in range(0, flat_t.numel(), step):
        t, hh = flat_t[a:a + step], flat_h[a:a + step]
        z = (t.unsqueeze(0) - flat_s[:, a:a + step].contiguous()) / hh.unsqueeze(0)  # [K,chunk]
        out[a:a + step] = torch.logsumexp(-0.5 * z.square(), dim=0) - math.log(k) - torch.log(hh) - _LOG_SQRT_2PI
    return out.reshape(target.shape)


def kde_nll(
    samples: Tensor,
    target: Tensor,
    *,
    bandwidth: Tensor | float | None = None,
    bandwidth_floor: float = 1e-3,
    mask: Tensor | None = None,
    reduction: Reduction = "mean",
) -> Tensor:
    """KDE NLL of ``target`` [...] under the K samples [K,...] of each element.

    ``bandwidth``: None for Silverman's rule from K (see :func:`kde_bandwidth`), or a fixed value /
    per-element tensor (still floored). Memory: the samples, and temporaries of at most ``KDE_CHUNK`` values.
    """
    if samples.ndim < 1 or samples.shape[1:] != target.shape:
        raise ValueError(f"samples must be [K,*target.shape], got {tuple(samples.shape)} vs {tuple(target.shape)}")
    k = samples.shape[0]
    if bandwidth is None:
        std = samples.std(dim=0, unbiased=True) if k > 1 else torch.zeros_like(target)
        h = kde_bandwidth(std, k, floor=bandwidth_floor)
    else:
        h = torch.as_tensor(bandwidth, dtype=target.dtype, device=target.device).expand_as(target)
        h = h.clamp_min(bandwidth_floor)
    return _reduce(-_kde_log_density(samples, target, h), mask, reduction)


def paper_bandwidth(sample_std: Tensor, num_pixels: int, *, eps: float = 1e-5) -> Tensor:
    """The flawed bandwidth of the original code (docs/method.md, defect 1): 1.06 * std * num_pixels^(+1/5) + eps.

    Two defects against Silverman's rule: the exponent has the wrong sign (+1/5) and the count is the
    number of pixels of the view instead of the number of samples K, so the bandwidth (and the NLL)
    grows with resolution. ``eps`` keeps a zero std finite.
    """
    return SILVERMAN_FACTOR * sample_std * float(num_pixels) ** 0.2 + eps


def paper_nll(
    samples: Tensor,
    target: Tensor,
    *,
    num_pixels: int | None = None,
    eps: float = 1e-5,
    mask: Tensor | None = None,
    reduction: Reduction = "mean",
) -> Tensor:
    """The original code's KDE NLL (NOT COMPARABLE with :func:`kde_nll` or :func:`gaussian_nll`).

    A per-channel Gaussian KDE over the K samples [K,H,W,3] with :func:`paper_bandwidth`;
    ``num_pixels`` defaults to H*W of the samples. Reconstructed from a written description of the
    official code (docs/method.md, defect 1: the two defects above), not from its source; the constant ``eps`` is our assumption, so numbers agree
    with published tables only up to that choice. Use it only to set our runs beside those tables.
    """
    if samples.ndim < 3 or samples.shape[1:] != target.shape:
        raise ValueError(f"samples must be [K,...,H,W,Ch] matching target, got {tuple(samples.shape)}")
    if num_pixels is None:
        num_pixels = samples.shape[-3] * samples.shape[-2]
    k = samples.shape[0]
    std = samples.std(dim=0, unbiased=True) if k > 1 else torch.zeros_like(target)
    h = paper_bandwidth(std, num_pixels, eps=eps)
    return _reduce(-_kde_log_density(samples, target, h), mask, reduction)
