"""When things happen: pure predicates of the (1-based) step number and a ``DensifyConfig``.

Steps count completed optimiser updates, starting at 1, as in 3DGS (``iteration``). The predicates are
evaluated after the optimiser update of ``step``.
"""

from __future__ import annotations


def is_stats_step(step: int, cfg) -> bool:
    """Accumulate screen-space gradient statistics (while densification is still running)."""
    return step < cfg.until


def is_densify_step(step: int, cfg) -> bool:
    """Clone/split/prune: every ``interval`` steps strictly after ``start`` and strictly before ``until``."""
    return cfg.start < step < cfg.until and step % cfg.interval == 0


def densify_steps_after(step: int, cfg, last_step: int | None = None) -> bool:
    """Whether a densification step (``is_densify_step``) comes after ``step`` (and at or before ``last_step``, a
    run's end): none does once ``step`` is at or past the last multiple of ``interval`` before ``until`` (the tiny
    preset's until 250, interval 50: none after 200), nor when the run ends before the next one."""
    first = max(step, cfg.start) + 1
    nxt = -(-first // cfg.interval) * cfg.interval  # the first multiple of interval at or after ``first``
    return nxt < cfg.until and (last_step is None or nxt <= last_step)


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
