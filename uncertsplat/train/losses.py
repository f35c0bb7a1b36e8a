"""The training loss: (1 - lambda) L1 + lambda (1 - SSIM) + kl_weight x KL."""

from __future__ import annotations

from torch import Tensor

from uncertsplat.eval.image import ssim_and_l1


def photometric_loss(pred: Tensor, target: Tensor, ssim_lambda: float) -> dict[str, Tensor]:
    """L1 and D-SSIM terms for HWC images [...,H,W,3] in [0, 1].

    Returns ``l1``, ``ssim`` (the similarity, not the loss) and ``photo`` = (1 - lambda) L1 + lambda (1 - SSIM).
    """
    if ssim_lambda > 0:
        s, l1 = ssim_and_l1(pred, target)  # one pass of the fused kernel on a CPU
    else:
        l1 = (pred - target).abs().mean()
        s = l1.new_tensor(0.0)
    photo = (1.0 - ssim_lambda) * l1 + ssim_lambda * (1.0 - s)
    return {"l1": l1, "ssim": s, "photo": photo}


def total_loss(pred: Tensor, target: Tensor, kl: dict[str, Tensor] | None, *, ssim_lambda: float,
               kl_weight: float) -> dict[str, Tensor]:
    """All loss terms; ``loss`` is what is minimised. ``kl`` is ``variational.kl_terms`` (or None)."""
    out = photometric_loss(pred, target, ssim_lambda)
    loss = out["photo"]
    if kl is not None:
        out.update({f"kl_{k}": v for k, v in kl.items()})
        loss = loss + kl_weight * kl["total"]
    out["loss"] = loss
    return out
