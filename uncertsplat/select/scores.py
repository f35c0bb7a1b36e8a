"""Scores of candidate cameras for ``select-views`` (higher = take that photo first) and the ranking.

- ``variance``: the mean over the candidate's pixels of the posterior's RGB std (K Monte-Carlo samples at a
  low resolution, with the empty-ray term of ``evaluate``: a candidate that looks where the model has no
  Gaussian is uncertain there). The depth std is recorded beside it.
- ``fisher``: the expected information of the candidate about the Gaussians, as FisherRF scores views:
  ``sum_i F_cand,i / (F_train,i + 1 / prior_i^2)`` over the parameters of the Fisher baseline
  (``FisherConfig.params``), with ``F`` the diagonal Gauss-Newton Fisher of the rendered image
  (``uncertainty.curvature``, the same probes), the training views' noise and the baseline's prior. For
  several views it is greedy: the chosen view's Fisher joins the training views' before the next choice.
  ``information="log-det"`` scores the expected information gain of the same diagonal Gaussian posterior
  instead, ``sum_i log(1 + F_cand,i / (F_train,i + 1 / prior_i^2)) / 2`` nats: a parameter's gain saturates
  once the candidate pins it down, so a view that sees many unknown parameters a little beats one that sees a few
  very sharply (the trace grows without bound in the latter). ``information="predictive"`` scores what the
  candidate takes off the variance of the renders of every view of the capture (the training views and all the
  candidates, the views a user will look at): ``sum_i G_i F_cand,i / (P_i (P_i + F_cand,i))`` with ``P`` the
  precision above and ``G`` the Fisher summed over those views. A parameter counts by how much the capture's
  renders depend on it (G / P: its share of their variance) and saturates once the candidate pins it down, so a
  view that teaches what many other views show beats one that pins a corner no other view sees (the expected
  reduction of the integrated predictive variance of active learning).
- ``unseen``: the share of the candidate's view that shows what the data has not pinned down: each carrier's
  position variance relative to the prior's (1 = the prior: no view constrains it; near 0: the data sets it;
  ``gaussians.variational``'s tables), blended like a colour over the candidate's pixels, plus the
  transmittance left behind the last Gaussian (a ray that meets nothing shows the unknown; not where the training
  photos were transparent: such a ray shows the known background, and counted it ranked an object capture's
  candidates by how much background they showed, Spearman 0.81). Unlike the RGB std
  it does not grow with the texture or the edges in view, only with the posterior (one render per candidate).
  ``gaps`` (``SelectConfig.gaps``) lets only the candidates in the capture's gaps compete (``gap_eligible``): a
  candidate at least that fraction of the farthest candidate's distance from the cameras used, so the Fisher
  chooses among the views coverage would consider, not next to a view just added.
- ``coverage``: the distance from the candidate's centre to the nearest camera already used (trained on or
  chosen): farthest-point sampling, the strong baseline without any uncertainty. Greedy for several views.
- ``random``: uniform, from the seed.

Ties are broken by candidate order (the first candidate wins), NaN scores rank last, so the same inputs
always give the same choice.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from uncertsplat.types import Cameras

SCORES = ("variance", "unseen", "fisher", "coverage", "random")


def rank_order(scores: Tensor) -> list[int]:
    """Candidate positions by descending score; ties by position, NaN last."""
    s = torch.nan_to_num(scores.double().cpu(), nan=float("-inf"))
    return torch.sort(-s, stable=True).indices.tolist()


def low_resolution(cameras: Cameras, max_side: int) -> Cameras:
    """``cameras`` scaled so that the long side is at most ``max_side`` pixels (never up)."""
    factor = min(1.0, max_side / max(cameras.width, cameras.height))
    return cameras.scaled(factor) if factor < 1.0 else cameras


def best_unchosen(scores: Tensor, chosen: list[int]) -> int:
    """The position of the best score among the candidates not chosen yet (``rank_order``'s tie rule)."""
    masked = scores.clone()
    if chosen:
        masked[chosen] = float("nan")
    return rank_order(masked)[0]


def nearest_used_distance(candidates: Tensor, used: Tensor) -> Tensor:
    """[C] float64 distance from each candidate centre ([C,3]) to the nearest used camera centre ([U,3]); inf for
    every candidate when U = 0."""
    c = candidates.double()
    if used.shape[0]:
        return torch.cdist(c, used.double()).min(1).values
    return torch.full((c.shape[0],), float("inf"), dtype=torch.float64)


def only_allowed(scores: Tensor, allowed: Tensor | None) -> Tensor:
    """``scores`` [C] with no score (NaN: ranked last by ``rank_order``) for the candidates not ``allowed`` [C] bool
    (None: all allowed)."""
    if allowed is None:
        return scores
    return torch.where(allowed.to(torch.bool).to(scores.device), scores, torch.full_like(scores, float("nan")))


def coverage_choice(candidates: Tensor, used: Tensor, n: int,
                    allowed: Tensor | None = None) -> tuple[list[int], list[float], Tensor]:
    """Greedy farthest-point choice of ``n`` candidates.

    Args:
        candidates: [C,3] candidate camera centres.
        used: [U,3] centres of the cameras used already (U may be 0: then the first pick is candidate 0).
        n: how many to choose (at most the allowed ones).
        allowed: [C] bool, the candidates that compete (None: all); the others get no score (NaN).

    Returns:
        (chosen positions, their distance when chosen, [C] every candidate's distance before any choice).
    """
    c = candidates.double()
    dist = only_allowed(nearest_used_distance(c, used), allowed)
    first = dist.clone()
    chosen, at = [], []
    for _ in range(min(n, c.shape[0] if allowed is None else int(allowed.sum()))):
        j = best_unchosen(dist, chosen)
        chosen.append(j)
        at.append(float(dist[j]))
        dist = torch.minimum(dist, (c - c[j]).norm(dim=1))
    return chosen, at, first


@torch.no_grad()
def variance_scores(sample_fn: Callable, render_fn: Callable, cameras: Cameras, num_samples: int, seed: int, *,
                    empty_std: tuple[float, float] | None, coverage: float = 1.0) -> tuple[Tensor, Tensor]:
    """([C] mean RGB std, [C] mean depth std) of each candidate (one seeded generator per candidate); ``empty_std``
    and ``coverage`` as in ``uncertainty.mc.mc_render``.

    Every candidate is scored with the same draws (a generator seeded by ``seed`` alone; common random numbers):
    candidates are compared on the same K posterior samples, and a candidate's score depends neither on its place in
    the list (a plan file read in reverse moved a score by up to 3.5 % when the seed followed the place) nor on the
    last digits of its pose (seeded by the pose's values, a pose read back from its own ``pose_line`` moved too)."""
    from uncertsplat.uncertainty.mc import mc_render

    rgb, depth = [], []
    for c in range(len(cameras)):
        gen = torch.Generator(device=cameras.device).manual_seed(seed)
        maps, _ = mc_render(sample_fn, render_fn, cameras[[c]], num_samples, gen, empty_std=empty_std,
                            coverage=coverage)
        rgb.append(float(maps.rgb_std.mean()))
        depth.append(float(maps.depth_std.mean()))
    return torch.tensor(rgb, dtype=torch.float64), torch.tensor(depth, dtype=torch.float64)


def relative_position_variance(model, prior, position_prior_std: Tensor | None = None) -> Tensor:
    """[N] each Gaussian's posterior position variance over the prior's (geometric mean over the axes, at most
    1); 0 for Gaussians without a posterior (deterministic). ``position_prior_std`` [P] (table units): the prior of
    each carrier where it has its own (the informed posterior's, ``LoadedRun.position_prior_std``); None: the
    config's single ``prior.position_std``."""
    from uncertsplat.gaussians.variational import log_softplus

    u = torch.zeros(len(model), device=model.device)
    idx = model.carrier_index()
    if idx.numel():
        raw = model.tables["pos_spread_raw"].detach().float().mean(1)  # [P,3]
        ref = prior.position_std if position_prior_std is None else position_prior_std.float().to(raw.device)
        ratio = log_softplus(raw).mean(1).exp() / ref
        u[idx] = ratio.square().clamp(0.0, 1.0)
    return u


@torch.no_grad()
def unseen_scores(sample, uncertainty: Tensor, render_fn: Callable, cameras: Cameras, *,
                  empty_unknown: bool = True) -> Tensor:
    """[C] the mean over each candidate's pixels of ``sum_i w_i u_i + (1 - alpha)`` (see the module docstring);
    ``empty_unknown`` False (transparent training photos: the background is known): ``sum_i w_i u_i`` alone."""
    from uncertsplat.uncertainty.residual import blend_values

    out = []
    for c in range(len(cameras)):
        blended, alpha = blend_values(sample, uncertainty, cameras[[c]], render_fn)
        out.append(float((blended + (1.0 - alpha) if empty_unknown else blended).mean()))
    return torch.tensor(out, dtype=torch.float64)


INFORMATION = ("trace", "log-det", "predictive")
CACHE_ELEMENTS = 2**27
"""fisher_choice keeps every candidate's Fisher in memory up to this many values (512 MB in float32); beyond it,
each is computed again when needed (same seed, same values): about once per candidate and a few times per choice,
through the lazy greedy."""


def gap_eligible(candidates: Tensor, used: Tensor, fraction: float,
                 allowed: Tensor | None = None) -> Callable[[list[int]], Tensor]:
    """The candidates that lie in the capture's gaps: ``f(chosen)`` gives the [C] mask of the candidates whose
    distance to the nearest camera used (``used`` [U,3] and the ``chosen`` positions so far) is at least
    ``fraction`` x the largest such distance among the candidates not chosen yet (0: every candidate; 1:
    coverage's farthest ones). ``candidates``: [C,3] centres; ``allowed`` [C] bool: only those compete, and only
    they set the largest distance (a pose far outside the capture, not allowed, put every other out of the gaps)."""
    c = candidates.double()
    base = nearest_used_distance(c, used)

    def eligible(chosen: list[int]) -> Tensor:
        dist = base.clone()
        for j in chosen:
            dist = torch.minimum(dist, (c - c[j]).norm(dim=1))
        free = torch.ones_like(dist, dtype=torch.bool) if allowed is None else allowed.to(torch.bool).cpu().clone()
        free[chosen] = False
        if not bool(free.any()):
            return free
        top = dist[free].max()
        if not bool(torch.isfinite(top)):
            return free
        return free & (dist >= fraction * top)

    return eligible


def fisher_choice(params: dict[str, Tensor], train_cameras: Cameras, train_images: Tensor, cameras: Cameras,
                  render_fn: Callable, *, names: Sequence[str], prior_std: dict[str, float], sh_degree: int,
                  probes: int, seed: int, n: int, information: str = "trace",
                  eligible: Callable[[list[int]], Tensor] | None = None, competing: Tensor | None = None,
                  train_masks: Tensor | None = None) -> tuple[list[int], list[float], Tensor, float]:
    """Greedy FisherRF choice of ``n`` candidates (see the module docstring). ``eligible`` (``gap_eligible``)
    restricts each choice to the candidates its mask allows; the others are not scored (NaN). ``competing`` [C] bool:
    the candidates that compete at all (``SelectConfig.plausible_only``); only they join the ``predictive``
    information's reference (a pose inside an object is no view of the capture). ``train_masks`` [T,H,W,1] bool: the
    training photos' pixels that count (their masks, as training left the others out), or None.

    Returns:
        (chosen positions, their information when chosen, [C] every candidate's information before any choice,
        the training views' noise std used).
    """
    from uncertsplat.eval.engine import view_seed
    from uncertsplat.uncertainty.curvature import curvature

    if information not in INFORMATION:
        raise ValueError(f"unknown information {information!r} ({', '.join(INFORMATION)})")
    gen = torch.Generator(device=train_images.device).manual_seed(seed)
    names = tuple(names)
    base = curvature(params, train_cameras, train_images, render_fn, names=names, generator=gen,
                     sh_degree=sh_degree, probes=probes, masks=train_masks)
    noise = base.noise_std
    precision = {k: base.fisher[k] + 1.0 / prior_std[k] ** 2 for k in names}
    blank = torch.zeros(1, cameras.height, cameras.width, 3, device=train_images.device)
    num = len(cameras)
    keep = num * sum(base.fisher[k].numel() for k in names) <= CACHE_ELEMENTS
    cache: dict[int, dict[str, Tensor]] = {}

    def view_fisher(c: int) -> dict[str, Tensor]:
        if c in cache:
            return cache[c]
        # every candidate's probes from one seed (as variance_scores): not its place in the list, nor its pose's last
        # digits (seeded by the pose's values, a pose read back from its own pose_line scored up to 8.7 % apart
        # with one probe, and the order of the demo's top candidates changed); a stream apart from the training
        # views' probes
        g = torch.Generator(device=train_images.device).manual_seed(view_seed(seed, 1))
        f = curvature(params, cameras[[c]], blank, render_fn, names=names, generator=g, sh_degree=sh_degree,
                      probes=probes, noise_std=noise).fisher
        if keep:
            cache[c] = f
        return f

    reference = None
    if information == "predictive":  # the capture's views: the training views' Fisher plus every candidate's
        reference = {k: base.fisher[k].clone() for k in names}
        for c in range(num):
            if competing is not None and not bool(competing[c]):
                continue
            f = view_fisher(c)
            for k in names:
                reference[k] += f[k]

    def gain(f: dict[str, Tensor]) -> float:
        if information == "trace":
            return float(sum((f[k] / precision[k]).sum() for k in names))
        if information == "log-det":
            return float(sum(0.5 * torch.log1p(f[k] / precision[k]).sum() for k in names))
        return float(sum((reference[k] * f[k] / (precision[k] * (precision[k] + f[k]))).sum() for k in names))

    # Lazy greedy: a candidate's gain only falls as the chosen views' Fisher joins the precision (each of the three
    # informations decreases in it), so a gain computed before is an upper bound of today's. Each round recomputes
    # only the candidate on top until it stays there, which picks what recomputing every candidate would (ties to
    # the first) at about one curvature per candidate in all instead of one per candidate per round (past the cache,
    # 1,000 candidates took 242 s for 20 views).
    bound = torch.full((num,), float("inf"), dtype=torch.float64)  # inf: not computed yet
    fresh = torch.zeros(num, dtype=torch.bool)  # computed with the current precision
    first = None
    chosen, at = [], []
    for _ in range(min(n, num)):
        allowed = torch.tensor(eligible(chosen).tolist() if eligible is not None else [True] * num)
        if chosen:
            allowed[chosen] = False
        if not bool(allowed.any()):
            break
        while True:
            j = best_unchosen(torch.where(allowed, bound, float("nan")), [])
            if fresh[j]:
                break
            bound[j], fresh[j] = gain(view_fisher(j)), True
        if first is None:  # every candidate allowed now was computed before this first choice (they started at inf)
            first = torch.where(allowed, bound, float("nan"))
        chosen.append(j)
        at.append(float(bound[j]))
        if len(chosen) < n:  # the chosen view's information joins the training views' before the next choice
            f = view_fisher(j)
            precision = {k: precision[k] + f[k] for k in names}
            fresh[:] = False
    if first is None:
        first = torch.full((num,), float("nan"), dtype=torch.float64)
    return chosen, at, first, noise


__all__ = ["INFORMATION", "SCORES", "best_unchosen", "coverage_choice", "fisher_choice", "gap_eligible", "low_resolution", "only_allowed",
           "nearest_used_distance", "rank_order", "relative_position_variance", "unseen_scores", "variance_scores"]
