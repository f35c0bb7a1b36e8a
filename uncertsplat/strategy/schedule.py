"""When things happen: pure predicates of the (1-based) step number and a ``DensifyConfig``.

Steps count completed optimiser updates, starting at 1, as in 3DGS (``iteration``). The predicates are
evaluated after the optimiser update of ``step``.
"""

from __future__ import annotations


def is_stats_step(step: int, cfg) -> bool:
    """Accumulate screen-space gradient statistics (while densification is still running)."""
    return step < cfg.until


SETTLE_FRACTION = 0.1
"""The last fraction of a run's steps never densify (nor run the growth test): Gaussians grown there have no steps
left to train. A run shortened below its preset's ``densify.until`` densified at its very last step (fern, 1500 of the
paper preset's 7000 steps, until 4000: 14k new Gaussians at step 1500, held-out 25.15 against 26.65 dB without that
one step); no preset's schedule reaches into it."""


def densify_end(cfg, iterations: int | None = None) -> float:
    """The step densification stops before: ``until``, or the start of the run's last ``SETTLE_FRACTION`` when that is
    earlier (``iterations``: the run's length; None: unknown)."""
    return cfg.until if iterations is None else min(cfg.until, (1.0 - SETTLE_FRACTION) * iterations + 1)


def is_densify_step(step: int, cfg, iterations: int | None = None) -> bool:
    """Clone/split/prune: every ``interval`` steps strictly after ``start`` and strictly before ``densify_end`` (``until``,
    or the last ``SETTLE_FRACTION`` of a run of ``iterations`` steps)."""
    return cfg.start < step < densify_end(cfg, iterations) and step % cfg.interval == 0


def densify_steps_after(step: int, cfg, last_step: int | None = None) -> bool:
    """Whether a densification step (``is_densify_step``) comes after ``step`` (and at or before ``last_step``, a
    run's end, which also ends densification ``SETTLE_FRACTION`` of it before): none does once ``step`` is at or past
    the last multiple of ``interval`` before ``until`` (the tiny preset's until 250, interval 50: none after 200), nor
    when the run ends before the next one."""
    first = max(step, cfg.start) + 1
    nxt = -(-first // cfg.interval) * cfg.interval  # the first multiple of interval at or after ``first``
    return nxt < densify_end(cfg, last_step) and (last_step is None or nxt <= last_step)


RESET_RECOVERY_STEPS = 1000
"""No opacity reset in the last this many steps of a run (a short ``--iterations`` inside a preset's window): a
reset needs steps to recover (fern: 5.6 dB held-out PSNR right after one, 28.5 dB 1000 steps later)."""


def is_opacity_reset_step(step: int, cfg, iterations: int | None = None) -> bool:
    """Opacity reset every ``opacity_reset_interval`` steps while densifying (0 disables it), never in the last
    ``RESET_RECOVERY_STEPS`` of a run of ``iterations`` steps (None: no such limit)."""
    n = cfg.opacity_reset_interval
    late = iterations is not None and step > iterations - RESET_RECOVERY_STEPS
    return n > 0 and step < cfg.until and step % n == 0 and not late


def is_spawn_step(step: int, cfg) -> bool:
    """Give posteriors to large Gaussians every ``spawn_interval`` steps after ``start``, up to ``until``.

    ``until`` is included so the Gaussians of the final densification also get their posterior.
    """
    return cfg.start < step <= cfg.until and step % cfg.spawn_interval == 0


def sh_degree_at(step: int, max_degree: int, interval: int) -> int:
    """Active SH degree: +1 every ``interval`` steps, up to ``max_degree`` (step 0 -> degree 0)."""
    return min(max_degree, max(step, 0) // interval)


def position_lr(step: int, total: int, lr_init: float, lr_final: float, extent: float) -> float:
    """Exponential (log-linear) decay from ``lr_init`` to ``lr_final`` over ``total`` steps, times ``extent``."""
    t = min(max(step / max(total, 1), 0.0), 1.0)
    import math

    return extent * math.exp((1.0 - t) * math.log(lr_init) + t * math.log(lr_final))
