"""Small helpers shared by the metric modules."""

from __future__ import annotations

import torch
from torch import Tensor


def broadcast_mask(mask: Tensor, shape: torch.Size) -> Tensor:
    """A validity mask given per pixel ([...,H,W] or [...,H,W,1]) or per element -> bool of ``shape``."""
    m = mask.to(torch.bool)
    if m.shape != shape and m.ndim == len(shape) - 1:
        m = m[..., None]
    return m.expand(shape)
