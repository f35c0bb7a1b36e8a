"""The training loss: (1 - lambda) L1 + lambda (1 - SSIM) + kl_weight x KL."""

from __future__ import annotations

import math
from collections.abc import Hashable, Sequence

from torch import Tensor

from uncertsplat.eval.image import ssim_and_l1, ssim_target_stats


def photometric_loss(pred: Tensor, target: Tensor, ssim_lambda: float,
                     target_stats: Tensor | None = None) -> dict[str, Tensor]:
    """L1 and D-SSIM terms for HWC images [...,H,W,3] in [0, 1]; ``target_stats``: ``target``'s own SSIM
    statistics (:class:`SsimTargetCache`), or None.

    Returns ``l1``, ``ssim`` (the similarity, not the loss) and ``photo`` = (1 - lambda) L1 + lambda (1 - SSIM).
    """
    if ssim_lambda > 0:
        s, l1 = ssim_and_l1(pred, target, target_stats)  # one pass of the fused kernel on a CPU
    else:
        l1 = (pred - target).abs().mean()
        s = l1.new_tensor(0.0)
    photo = (1.0 - ssim_lambda) * l1 + ssim_lambda * (1.0 - s)
    return {"l1": l1, "ssim": s, "photo": photo}


def total_loss(pred: Tensor, target: Tensor, kl: dict[str, Tensor] | None, *, ssim_lambda: float,
               kl_weight: float, target_stats: Tensor | None = None) -> dict[str, Tensor]:
    """All loss terms; ``loss`` is what is minimised. ``kl`` is ``variational.kl_terms`` (or None)."""
    out = photometric_loss(pred, target, ssim_lambda, target_stats)
    loss = out["photo"]
    if kl is not None:
        out.update({f"kl_{k}": v for k, v in kl.items()})
        loss = loss + kl_weight * kl["total"]
    out["loss"] = loss
    return out


class SsimTargetCache:
    """The training photos' own SSIM statistics (their blurred mean and mean square,
    :func:`~uncertsplat.eval.image.ssim_target_stats`), kept from a photo's first step on: the fused CPU SSIM then
    blurs three quantities a step instead of five, with the same result to the bit.

    Photos are kept in the order they come until ``budget_bytes`` is spent (8 bytes per pixel and channel); the
    others are blurred in the loss as before (no eviction: with photos in random order a cache that evicts would
    miss as often as one that stops). Where the fused kernel does not run (CUDA, float64, the native kernels off)
    :meth:`get` returns None and keeps nothing."""

    def __init__(self, budget_bytes: int):
        self.budget_bytes = int(budget_bytes)
        self.used_bytes = 0
        self._stats: dict[Hashable, Tensor] = {}
        self._full = False  # the budget is spent: no more stats are computed

    def __len__(self) -> int:
        return len(self._stats)

    def pending_bytes(self, shape: Sequence[int]) -> int:
        """Bytes the cache may still take for training photos of ``shape`` ([T,H,W,3]): what its budget leaves, at
        most the photos' own statistics not kept yet."""
        if self._full or self.budget_bytes <= 0:
            return 0
        return max(min(self.budget_bytes, 8 * math.prod(shape)) - self.used_bytes, 0)

    def get(self, key: Hashable, target: Tensor) -> Tensor | None:
        """The statistics of ``target`` (HWC images [...,H,W,3]) under ``key`` (which names those exact pixels, e.g.
        a training view's index and resolution), computed and kept on the first call while the budget lasts."""
        if key in self._stats:
            return self._stats[key]
        if self._full or self.budget_bytes <= 0:
            return None
        need = 8 * target.numel()  # the two float32 planes of every channel: ssim_target_stats' size
        if self.used_bytes + need > self.budget_bytes:
            self._full = True
            return None
        stats = ssim_target_stats(target)
        if stats is None:  # not the fused kernel's case: the loss blurs the target itself
            self._full = True
            return None
        self._stats[key] = stats
        self.used_bytes += need
        return stats
