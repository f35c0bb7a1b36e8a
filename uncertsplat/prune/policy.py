"""The prune policy: which keep mask to apply, the keep-ratio sweep and ``--auto``'s choice.

Measuring a model (rendering held-out views, scoring its uncertainty) is the caller's: the policy takes
a ``measure(model, keep) -> PruneMetrics`` function, so the decisions here are plain logic over
numbers and masks and can be tested without rendering.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from uncertsplat.errors import UserError
from uncertsplat.gaussians.params import GaussianModel
from uncertsplat.prune.mask import apply_keep, keep_ratio_mask, num_to_remove, random_mask, threshold_mask
from uncertsplat.schemas.prune import PruneMetrics, PruneSweep, SweepPoint, ToleranceChoice

Measure = Callable[[GaussianModel, Tensor | None, bool], PruneMetrics]
"""``measure(model, keep, full)``: held-out metrics of ``model``; ``keep`` (the mask that made it) lets the
measurement cache results per mask; ``full=False`` asks only for what one render per view gives (``psnr_render``,
coverage, sizes), not the K samples' uncertainty metrics."""

DECISION_METRIC = "psnr_render"
"""The PSNR the tolerance is checked on: the expected render's (what ``train`` reports), one render per view, so a
sweep can decide without the K samples of every point."""


def random_keep(n: int, n_remove: int, seed: int) -> Tensor:
    """Random-removal baseline: keep mask [n] removing ``n_remove`` of all Gaussians.

    The generator is re-seeded for every call, so the random masks of a sweep are nested (each removes
    a prefix of the same permutation) and the baseline at a ratio does not depend on the other ratios.
    """
    return random_mask(n, n_remove, torch.Generator().manual_seed(seed))


def _fails(metrics: PruneMetrics, unpruned_psnr: float | None, tolerance_db: float,
           metric: str = DECISION_METRIC) -> bool:
    """Whether a removal's held-out PSNR (``metric``) is unknown or more than ``tolerance_db`` below the unpruned
    one's."""
    value = getattr(metrics, metric)
    return unpruned_psnr is None or value is None or value < unpruned_psnr - tolerance_db


def largest_removal_within(points: Sequence[SweepPoint], unpruned_psnr: float | None, tolerance_db: float,
                           metric: str = DECISION_METRIC) -> ToleranceChoice | None:
    """The strongest removal, walking ``points`` by descending keep ratio, before the first whose
    held-out PSNR (``metric``) falls more than ``tolerance_db`` below ``unpruned_psnr``; None when the first fails."""
    if unpruned_psnr is None:
        return None
    within = None
    for p in points:
        if p.num_removed == 0:
            continue
        if not _fails(p.score, unpruned_psnr, tolerance_db, metric):
            within = p
        else:
            break  # stop at the first failure: a larger removal that passes again is noise, not a plateau
    if within is None:
        return None
    return ToleranceChoice(keep_ratio=within.keep_ratio, num_removed=within.num_removed,
                           psnr_loss_db=unpruned_psnr - getattr(within.score, metric), tolerance_db=tolerance_db)


def keep_ratio_sweep(model: GaussianModel, score: Tensor, carriers: Tensor, ratios: Sequence[float],
                     measure: Measure, *, unpruned: PruneMetrics, seed: int, tolerance_db: float, score_name: str,
                     split: str, on_point: Callable[[SweepPoint], None] | None = None,
                     stop_at_first_failure: bool = False, full: bool = True) -> PruneSweep:
    """Measure the score's removal and random removal of as many Gaussians at each keep ratio; the tolerance is
    checked on ``DECISION_METRIC``.

    Args:
        score: [N] per-Gaussian score (higher = removed first); carriers: [N] bool, the removable ones.
        ratios: keep ratios to try; 1.0 is always added; they are walked in descending order.
        unpruned: the metrics of ``model`` itself (measured once by the caller).
        stop_at_first_failure: stop after the first ratio whose held-out PSNR falls more than ``tolerance_db``
            below the unpruned model's: ``largest_removal_within`` never looks past it, so ``--auto`` alone
            needs no more (``--sweep`` measures the whole curve).
        full: measure every point's uncertainty metrics too (``measure(..., full=True)``); else its render only.
    """
    n = len(model)
    ordered = sorted(set(float(r) for r in ratios) | {1.0}, reverse=True)
    points = []
    for r in ordered:
        keep_s = keep_ratio_mask(score, carriers, r)
        removed = int((~keep_s).sum())
        if removed == 0:
            by_score = by_random = unpruned
        else:
            keep_r = random_keep(n, removed, seed)
            by_score = measure(apply_keep(model, keep_s), keep_s, full)
            by_random = measure(apply_keep(model, keep_r), keep_r, full)
        point = SweepPoint(keep_ratio=r, num_removed=removed, keep_ratio_achieved=(n - removed) / n,
                           score=by_score, random=by_random)
        points.append(point)
        if on_point is not None:
            on_point(point)
        if stop_at_first_failure and removed and _fails(by_score, getattr(unpruned, DECISION_METRIC), tolerance_db):
            break
    return PruneSweep(ratios=ordered, score=score_name, split=split, unpruned=unpruned, points=points,
                      tolerance_db=tolerance_db, metric=DECISION_METRIC, uncertainty_measured=full,
                      largest_removal_within_tolerance=largest_removal_within(points, getattr(unpruned, DECISION_METRIC),
                                                                              tolerance_db))


def auto_keep_ratio(sweep: PruneSweep) -> tuple[float, str | None]:
    """``--auto``: the keep ratio of the sweep's largest removal within tolerance, and a note when that
    is no removal at all (saying what the smallest removal would have cost)."""
    best = sweep.largest_removal_within_tolerance
    if best is not None:
        return best.keep_ratio, None
    first = next((p for p in sweep.points if p.num_removed > 0), None)
    if first is None:  # every ratio rounds to no removal: a model of a handful of Gaussians
        return 1.0, ("--auto: none of the evaluated keep ratios removes a Gaussian (the model has too few for them "
                     "to round to one), so nothing was removed; choose --keep-ratio, or prune a larger model")
    cost = ""
    ref = getattr(sweep.unpruned, sweep.metric)
    if first is not None and ref is not None and getattr(first.score, sweep.metric) is not None:
        rand = "" if getattr(first.random, sweep.metric) is None else \
            f"; random removal of as many {ref - getattr(first.random, sweep.metric):.2f} dB"
        cost = (f" (the smallest removal tried, {100 * (1 - first.keep_ratio_achieved):.0f} %, cost "
                f"{ref - getattr(first.score, sweep.metric):.2f} dB{rand})")
    return 1.0, (f"--auto: no evaluated keep ratio stays within {sweep.tolerance_db} dB of the unpruned held-out "
                 f"PSNR, so nothing was removed{cost}; allow more with --tolerance-db, or choose --keep-ratio")


def _removal(sweep: PruneSweep) -> int:
    best = sweep.largest_removal_within_tolerance
    return 0 if best is None else best.num_removed


def _first_cost(sweep: PruneSweep) -> float:
    """What the sweep's smallest removal cost (dB of its decision metric); inf when not measured."""
    first = next((p for p in sweep.points if p.num_removed > 0), None)
    ref = getattr(sweep.unpruned, sweep.metric)
    got = getattr(first.score, sweep.metric) if first is not None else None
    return ref - got if ref is not None and got is not None else float("inf")


def choose_score_by_removal(sweeps: dict[str, PruneSweep]) -> tuple[str, str]:
    """``--auto --score auto``: the score whose sweep removes the most within its tolerance; among equals the one whose
    removal cost least (that removal's; where none removes anything, its smallest removal's, which the note of
    ``auto_keep_ratio`` then quotes as the nearest miss: it quoted the default score's 0.40 dB where gate's cost
    0.06; a helper's tie at 4,714 Gaussians kept the one 0.08 dB worse), then the first of ``sweeps`` (the default
    score); and a note saying what each removes."""
    names = list(sweeps)

    def cost(n: str) -> float:
        best = sweeps[n].largest_removal_within_tolerance
        return best.psnr_loss_db if best is not None and best.num_removed > 0 else _first_cost(sweeps[n])

    chosen = max(names, key=lambda n: (_removal(sweeps[n]), -cost(n), -names.index(n)))

    def said(n: str) -> str:  # (the cost too: where both remove as many, it is what decided)
        c = cost(n)
        removed = _removal(sweeps[n])
        if c == float("inf"):
            return f"'{n}' {removed} Gaussians"
        return (f"'{n}' {removed} Gaussians for {c:.2f} dB" if removed else
                f"'{n}' 0 Gaussians, its smallest removal {c:.2f} dB")
    what = "; ".join(said(n) for n in names)
    return chosen, (f"score auto: the score that removes the most within {sweeps[chosen].tolerance_db} dB of the "
                    f"held-out PSNR is used, '{chosen}' ({what})")


def choose_score_at_ratio(sweeps: dict[str, PruneSweep], keep_ratio: float) -> tuple[str, str]:
    """``--keep-ratio R --score auto``: the score whose removal at ``keep_ratio`` keeps the higher held-out PSNR
    (``DECISION_METRIC``; the first of ``sweeps`` among equals or when one is unknown), and a note with both."""
    names = list(sweeps)

    def value(n: str) -> float:
        point = next((p for p in sweeps[n].points if p.keep_ratio == keep_ratio), None)
        v = None if point is None else getattr(point.score, DECISION_METRIC)
        return float("-inf") if v is None else float(v)

    chosen = max(names, key=lambda n: (value(n), -names.index(n)))
    what = "; ".join(f"'{n}' {value(n):.2f} dB" for n in names)
    return chosen, (f"score auto: at keep ratio {keep_ratio:g} the score whose removal keeps the higher held-out PSNR "
                    f"of the expected render is used, '{chosen}' ({what})")


def choose_mask(score: Tensor, carriers: Tensor, *, threshold: float | None,
                keep_ratio: float | None) -> tuple[Tensor | None, list[str]]:
    """The keep mask [N] for a threshold (wins) or a keep ratio, and notes; (None, []) for neither."""
    if threshold is not None:
        keep = threshold_mask(score, carriers, threshold)
        removed, total = int((~keep).sum()), int(carriers.sum())
        if keep.numel() and not bool(keep.any()):  # (an empty model failed deep in writing its PLY: a traceback)
            lo, hi = float(score[carriers].min()), float(score[carriers].max())
            raise UserError(f"--threshold {threshold:g} removes every one of the {removed:,} Gaussians (this score "
                            f"ranges from {lo:.3g} to {hi:.3g} on this run): a model of none is no model",
                            hint=f"Give a threshold above {lo:.3g} (it removes the Gaussians scoring above it), or "
                                 "--keep-ratio or --auto, which choose by the count.")
        if total and bool((~keep & carriers).sum() == total):  # (7 Gaussians left, 7 dB: written without a word)
            lo = float(score[carriers].min())
            raise UserError(f"--threshold {threshold:g} removes every one of the {total:,} Gaussians that carry a "
                            f"posterior (this score ranges from {lo:.3g} on them), leaving only the "
                            f"{int(keep.sum()):,} without one: no model of the scene",
                            hint=f"Give a threshold above {lo:.3g} (it removes the Gaussians scoring above it), or "
                                 "--keep-ratio or --auto, which choose by the count.")
        notes = []
        if total and removed >= 0.5 * total:  # a threshold below most scores: likely not what was meant
            lo, mid = float(score[carriers].min()), float(score[carriers].median())
            notes.append(f"--threshold {threshold:g} removes {removed} of the {total} Gaussians that carry a "
                         f"posterior ({removed / total:.0%}); this score ranges from {lo:.3g} (median {mid:.3g}) on "
                         "this run: --keep-ratio or --auto choose by the count instead")
        elif total and removed == 0:  # above every score: nothing to prune, likely not what was meant either
            hi, mid = float(score[carriers].max()), float(score[carriers].median())
            notes.append(f"--threshold {threshold:g} is above every score ({hi:.3g} at most, median {mid:.3g} on "
                         "this run), so nothing was removed: a lower threshold, or --keep-ratio or --auto, which "
                         "choose by the count")
        return keep, notes
    if keep_ratio is None:
        return None, []
    keep = keep_ratio_mask(score, carriers, keep_ratio)
    n = score.shape[0]
    wanted = num_to_remove(n, keep_ratio)
    notes = []
    if int((~keep).sum()) < wanted:
        notes.append(f"keep ratio {keep_ratio} needs {wanted} removals but only {int(carriers.sum())} "
                     "Gaussians carry a posterior; non-carriers are never removed by a score")
    return keep, notes


__all__ = ["Measure", "auto_keep_ratio", "choose_mask", "choose_score_at_ratio", "choose_score_by_removal",
           "keep_ratio_sweep", "largest_removal_within", "random_keep"]
