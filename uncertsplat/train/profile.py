"""Where a training step's time goes: wall seconds per phase (``TrainConfig.profile``).

The phases are those of ``Trainer.train_step`` (data, sample, render, loss, backward, densify statistics,
optimizer, densify, posterior update) and of ``Trainer.fit`` around it (held-out evaluation, checkpoints).
On CUDA every phase boundary synchronises the device (otherwise a phase would only measure the launch of its
kernels), which slows training a little; that is why profiling is off unless asked for.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager

import torch


class PhaseTimer:
    """Accumulates wall seconds per named phase; does nothing when disabled."""

    def __init__(self, device: torch.device, enabled: bool):
        self.enabled = enabled
        self._sync = enabled and device.type == "cuda"
        self._device = device
        self.seconds: dict[str, float] = {}
        self.steps = 0

    @contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        if not self.enabled:
            yield
            return
        if self._sync:
            torch.cuda.synchronize(self._device)
        t0 = time.perf_counter()
        try:
            yield
        finally:
            if self._sync:
                torch.cuda.synchronize(self._device)
            self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - t0

    def summary(self) -> dict | None:
        """``{"steps", "seconds": {phase: s}, "fraction": {phase: share of the total}}`` or None when disabled."""
        if not self.enabled:
            return None
        total = sum(self.seconds.values())
        return {"steps": self.steps, "seconds": dict(self.seconds),
                "fraction": {k: v / total for k, v in self.seconds.items()} if total > 0 else {}}


__all__ = ["PhaseTimer"]
