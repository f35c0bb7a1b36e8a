"""When to stop growing the model: densification stops once its last doubling no longer pays.

3DGS clones and splits every Gaussian whose screen-space gradient stays above a threshold, which on real
photos means growing long after the images have stopped improving (bonsai through ``pipelines/photos.toml``:
380k Gaussians in 1500 steps, where 50k and 150k give held-out PSNRs 0.14 dB apart). A budget from the
training pixels (``strategy.budget``) cannot tell such a scene from one that uses every Gaussian it gets, so
the model's own images decide (``DensifyConfig.growth_min_gain_db``):

every ``growth_check_interval`` steps while densifying, the weakest half of the Gaussians that a few training
views see (weakest: the smallest blending weight summed over the views, ``uncertainty.scores.blending_weights``)
is taken out of a copy of the training, and that copy and a copy of the whole training each train
``growth_refit_steps`` more steps, on the same views in the same order, with no topology change or posterior
update (``Trainer._refit_cost``; the copies change nothing of the training itself). The PSNR the whole copy then
has over the other on the views is what the last doubling of the model buys. Once that is below the threshold
(``DensifyConfig.growth_threshold_db``) in ``growth_patience`` tests in a row, densification adds no Gaussians past
the model's size at that test for the rest of the run: it goes on cloning and splitting only into the room pruning
makes, as a budget of that size would. The patience is for the first tests, which see a model that has barely
started to fit.

Why the re-fit: switched off in the model as it stands (``growth_refit_steps = 0``, the test before), the half
costs what the rest was never trained to cover: 0.7-1.4 dB on fern at 1/8's training views at every size, so fern
grew to 337k Gaussians where held-out PSNR gains 0.07 dB per doubling beyond 120k, while the same half re-fitted
for 100 steps costs 0.10 dB from 62k Gaussians on (the synthetic scenes, which use every Gaussian they get: at
least 0.39 dB; bonsai 0.01-0.02 dB from the first tests). BENCHMARKS.md, "The growth test with the rest re-fitted".
Gaussians the check views do not see are never taken out (they would cost nothing there and make the model look
over-grown). Only training views are used: the held-out views stay unseen by every training decision.

No test runs while the model is within ``AT_BUDGET`` of its budget (``DensifyConfig.max_gaussians``): the budget
already stops its growth there, and what the test could still stop is the refilling of what pruning removes
(the demo scene: 6 of its 8 tests, at 39,991-40,000 of 40,000; 0.47-0.56 s each on the 2-core CPU without
the re-fit, seconds with it). Once pruning leaves room
(e.g. after an opacity reset), the tests resume.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import torch
from torch import Tensor

from uncertsplat.schemas.runs import GrowthCheck
from uncertsplat.strategy.schedule import RESET_RECOVERY_STEPS
from uncertsplat.strategy.view_checks import psnr_gain_db
from uncertsplat.types import Cameras, GaussianSample


def growth_check_due(step: int, cfg, iterations: int | None = None) -> bool:
    """Whether the growth test runs before the densification of ``step`` (a ``DensifyConfig``).

    Every ``growth_check_interval`` steps strictly inside the densification window (``start < step <
    schedule.densify_end``: ``until``, or the last ``SETTLE_FRACTION`` of a run of ``iterations`` steps), never when
    the threshold (``growth_min_gain_db``) is 0, and never in the ``RESET_RECOVERY_STEPS`` after an opacity reset (the model's images
    are then still recovering, and would call any half of it cheap).
    """
    from uncertsplat.strategy.schedule import densify_end

    if cfg.growth_threshold_db <= 0 or step <= 0 or step % cfg.growth_check_interval:
        return False
    if not cfg.start < step < densify_end(cfg, iterations):
        return False
    return not reset_within(step, cfg, iterations)


def reset_within(step: int, cfg, iterations: int | None = None) -> bool:
    """Whether an opacity reset took place in the ``RESET_RECOVERY_STEPS`` before ``step`` (the resets
    ``schedule.is_opacity_reset_step`` makes: none in a run's last steps, none after ``until``). The growth test assumed
    one at every multiple of the interval, so an interval under the recovery (or a run too short for resets) switched
    every test off."""
    from uncertsplat.strategy.schedule import is_opacity_reset_step

    n = cfg.opacity_reset_interval
    if n <= 0:
        return False
    first = max(n, -(-(step - RESET_RECOVERY_STEPS) // n) * n)  # the first multiple of n in the window, past step 0
    return any(is_opacity_reset_step(m, cfg, iterations) for m in range(first, step, n))


def skips_next(cost_db: float, cfg) -> bool:
    """Whether a test that found the half worth ``cost_db`` skips the next test due: ``cost_db`` at least
    ``cfg.growth_skip_factor`` (a ``DensifyConfig``; None: never) times its threshold (``growth_threshold_db``), for
    the test with copies only (``growth_refit_steps`` > 0: without them a test costs a few renders, and its costs,
    0.7-4.5 dB on every scene measured, would skip every other test)."""
    factor, threshold = cfg.growth_skip_factor, cfg.growth_threshold_db
    return factor is not None and cfg.growth_refit_steps > 0 and threshold > 0 and cost_db >= factor * threshold


def skipped(last: GrowthCheck | None, step: int, cfg, iterations: int | None = None) -> bool:
    """Whether the test due at ``step`` is skipped: the last test ran (``last``) asked for it (``skip_next``) and no
    step between the two had a test due (``growth_check_due``; one at the budget counts as due, so that a skip never
    waits past the model's next chance to grow). A pure function of the recorded tests, so a resumed run skips the
    same tests."""
    if last is None or not last.skip_next or step <= last.step:
        return False
    n = cfg.growth_check_interval
    first = (last.step // n + 1) * n  # the first multiple of the interval after the last test
    return not any(growth_check_due(m, cfg, iterations) for m in range(first, step, n))


UNTOLD_DB = 1e3
"""A test's cost is recorded up to this (``GrowthCheck.cost_db``): a copy that could not train, memory too short for
a copy, or a whole copy that renders its views exactly (+inf) all read as this."""


# A model with at least this fraction of its budget is at the budget: the growth test is skipped (module docstring).
AT_BUDGET = 0.99


def at_budget(gaussians: int, max_gaussians: int) -> bool:
    """Whether a model of ``gaussians`` is at its budget ``max_gaussians`` (at least ``AT_BUDGET`` of it), where
    the growth test has nothing left to decide."""
    return gaussians >= AT_BUDGET * max_gaussians


def weakest_half(weights: Tensor) -> Tensor:
    """[N] bool: the half (rounded down) of the Gaussians with ``weights > 0`` that has the smallest weights.

    Ties are broken by row (the earlier row counts as weaker), so the choice is deterministic. Gaussians with
    weight 0 (not seen) are never chosen.
    """
    seen = (weights > 0).nonzero().flatten()  # [S]
    order = seen[torch.argsort(weights[seen], stable=True)]
    out = torch.zeros_like(weights, dtype=torch.bool)
    out[order[: seen.numel() // 2]] = True
    return out


def halving_cost_db(sample: GaussianSample, off: Tensor, cameras: Cameras, images: Tensor,
                    render_fn: Callable[[GaussianSample, Cameras], Tensor], masks: Tensor | None = None) -> float:
    """Training-view PSNR lost (dB) when the Gaussians in ``off`` [N] are switched off (opacity 0):
    ``view_checks.psnr_gain_db`` of the whole model over the rest (0 when nothing changes).

    Args:
        sample: the Gaussians to render. off: [N] bool, those to switch off.
        cameras: [V] training cameras. images: [V,H,W,3] their photos.
        render_fn: (sample, camera) -> [1,H,W,3] image in [0, 1].
        masks: [V,H,W,1] bool, the pixels that count, or None for all.
    """
    without = replace(sample, opacities=torch.where(off, torch.zeros_like(sample.opacities), sample.opacities))
    return psnr_gain_db(sample, without, cameras, images, render_fn, masks)


def growth_reason(check: GrowthCheck) -> str:
    """One line for the log and the report: the test's numbers and what was decided."""
    cheap = check.cost_db < check.min_gain_db
    verdict = (f"densification stops growing the model past {check.gaussians:,} Gaussians" if check.stopped
               else "growth goes on until the half is this cheap at consecutive tests" if cheap else "growth goes on")
    if check.skip_next:
        verdict += (" (the next test skipped)" if check.cost_db >= UNTOLD_DB else
                    " (the next test skipped: the cost is far above the threshold)")
    cmp = "<" if cheap else ">="
    how = (f"taking out the weakest half of the {check.seen:,} Gaussians {check.views} training views see (of "
           f"{check.gaussians:,}) and training the rest {check.refit_steps} steps costs"
           if check.refit_steps else
           f"switching off the weakest half of the {check.seen:,} Gaussians {check.views} training views see (of "
           f"{check.gaussians:,}) costs")
    if check.cost_db >= UNTOLD_DB:
        return (f"growth test at step {check.step}: {how} more than {UNTOLD_DB:g} dB or could not be measured (a copy "
                f"that could not train or memory too short for one), {verdict}")
    return f"growth test at step {check.step}: {how} {check.cost_db:.3f} dB ({cmp} {check.min_gain_db:g} dB), {verdict}"


__all__ = ["AT_BUDGET", "UNTOLD_DB", "GrowthCheck", "at_budget", "growth_check_due", "growth_reason", "halving_cost_db",
           "skipped", "skips_next", "weakest_half"]
