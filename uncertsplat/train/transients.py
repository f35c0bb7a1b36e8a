"""Transient objects in the training photos found from the residual (``TrainConfig.transients``).

A person walking through, a car parked for a few of the photos, a hand in front of the lens: the other photos
show the static scene there, so once the model has fitted the scene such a region of one photo stays far from
its render, while the scene's hard parts (edges, fine texture, view-dependent shine) leave thin lines and
scattered pixels of large residual. A pixel is a *candidate* when its residual is ``threshold`` times the
photo's typical residual (the median over the pixels not rendered exactly, on every other row and column); a region is *transient* where a
share ``core`` of a square window (``window`` of the short side) are candidates, widened by half a window so that the object's rim goes with it. Left in the loss
such a region is fitted by Gaussians that only that photo supports: the ghosts the held-out views show
(BENCHMARKS.md, "Transient objects in the photos").

The masks are a pure function of the render and the photo: the trainer computes them in each step, after
``start`` of the iterations (before it the whole model is far from the photos), and keeps each photo's last one
for the posterior's noise and curvature and the training checks.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

MEDIAN_FLOOR = 1.0 / 255.0
"""Residuals up to this (a quantisation step) count as rendered exactly: they are left out of a photo's typical
residual, which is never taken below it (a photo the model renders to within its quantisation would otherwise
mark its noise)."""

def window_pixels(height: int, width: int, window: float) -> int:
    """The odd side (pixels, at least 3) of the square window: ``window`` of the short side."""
    k = max(3, int(round(window * min(height, width))))
    return k if k % 2 == 1 else k + 1


def box_count(x: Tensor, k: int) -> Tensor:
    """[B,H,W] int32: how many of the k x k pixels (k odd) centred on each pixel of ``x`` [B,H,W] bool are True, those
    outside the image counted as False. Summed tables: a few operations per pixel whatever ``k`` (a pooling layer's
    k^2 made the detection cost more than the rest of fern's training step at k = 23)."""
    r = k // 2
    c = F.pad(x.to(torch.int32), (r + 1, r, r + 1, r)).cumsum(1, dtype=torch.int32).cumsum(2, dtype=torch.int32)
    # [B,H+k,W+k], a leading row and column of 0 (int32: exact up to 2**31 pixels)
    return c[:, k:, k:] - c[:, :-k, k:] - c[:, k:, :-k] + c[:, :-k, :-k]


def transient_masks(pred: Tensor, photo: Tensor, *, threshold: float, window: float, core: float, max_share: float,
                    valid: Tensor | None = None) -> Tensor:
    """The pixels that count: [B,H,W,1] bool, False on the transient regions of each photo.

    Args:
        pred: [B,H,W,3] the renders (at the photos' exposure), detached or not (nothing here is differentiated).
        photo: [B,H,W,3] the photos.
        threshold: a candidate's residual (mean absolute over the channels) over the photo's median residual.
        window: the window's side over the image's short side (:func:`window_pixels`).
        core: the share of a window's pixels that must be candidates for its centre to be transient.
        max_share: a photo whose transient regions would cover more than this share of its pixels (of its valid
            pixels) keeps every pixel: that is a model far from the photo, not an object in front of it.
        valid: [B,H,W,1] bool, the pixels a user's masks let count (None: all); the others are never transient
            and stay out of the median.
    """
    with torch.no_grad():
        b, h, w, _ = pred.shape
        e = (pred.detach() - photo).abs_().mean(dim=-1)  # [B,H,W]
        keep = torch.ones((b, h, w, 1), dtype=torch.bool, device=pred.device)
        if b == 0 or h == 0 or w == 0:
            return keep
        ok = valid[..., 0] if valid is not None else torch.ones_like(e, dtype=torch.bool)  # [B,H,W]
        # the typical residual of the pixels the model does not render exactly: a background rendered to the bit
        # (a studio's black, a masked-out sky) would otherwise set it near 0 and mark the whole object. Taken on
        # every other row and column (a quarter of the pixels, a quarter of the cost of a median)
        sub, fit = e[:, ::2, ::2], (ok & (e > MEDIAN_FLOOR))[:, ::2, ::2]  # [B,h,w]
        scale = torch.stack([sub[i][fit[i]].median() if fit[i].any() else e.new_tensor(0.0) for i in range(b)])  # [B]
        cand = (e > threshold * scale.clamp_min(MEDIAN_FLOOR)[:, None, None]) & ok  # [B,H,W]
        k = window_pixels(h, w, window)
        # (outside the image counts as no candidate: two lines crossing at a corner fill more of a window the border
        # cuts than of a whole one)
        centre = box_count(cand, k) >= core * k * k  # [B,H,W]
        region = (box_count(centre, k) > 0) & ok  # [B,H,W]: widened by k // 2
        covered = region.flatten(1).sum(1) / ok.flatten(1).sum(1).clamp_min(1)  # [B]
        region[covered > max_share] = False
        keep[..., 0] = ~region
        return keep


def pack_mask(keep: Tensor) -> Tensor:
    """[H,W,1] bool -> [ceil(H*W / 8)] uint8 on the CPU, a bit per pixel: what the trainer keeps of each photo's last
    regions and writes into its checkpoints (a byte per pixel was 330 MB for 300 photos of 1297x840)."""
    return torch.from_numpy(np.packbits(keep.reshape(-1).cpu().numpy()))


def unpack_mask(packed: Tensor, height: int, width: int, device=None) -> Tensor:
    """:func:`pack_mask`'s inverse: [H,W,1] bool on ``device``."""
    bits = np.unpackbits(packed.cpu().numpy(), count=height * width).astype(bool)
    return torch.from_numpy(bits).reshape(height, width, 1).to(device)


EVERYWHERE_SHARE = 0.75
"""``transients_warning``: regions in at least this share of the training photos (of at least ``MIN_PHOTOS``) look
like parts of the scene the model cannot fit rather than objects that came and went."""

STOPPED = "transients: the test switched itself off"
"""How ``transients_warning``'s warning for a test that switched itself off begins (the report finds it by it)."""

MIN_PHOTOS = 4
"""The fewest training photos a share of them says anything of (three of three may all hold a passer-by)."""


def transients_warning(shares: dict[str, float] | None, photos: int, stopped: dict | None = None) -> str | None:
    """A warning when training found transient regions in nearly every one of its ``photos`` training photos
    (``EVERYWHERE_SHARE``): passers-by are seldom in nearly every photo, while a part of the scene the model renders
    poorly in every view is (bonsai at 20 dB held out: its flowers and table cloth in 40 of 42 photos, 0.33 dB lost on
    clean photos; BENCHMARKS.md, "Transient objects found from the residual"). ``stopped``: the trainer's record of
    the test switching itself off for that reason after a pass over the photos (``Trainer.transients_stopped``).
    None otherwise."""
    if shares is None:  # (the detection off in this run)
        return None
    if stopped:
        return (f"{STOPPED} at step {stopped['step']}: after a pass over the photos it "
                f"had found regions in {stopped['photos']} of the {stopped['of']} training photos, and objects that "
                "come and go are seldom in nearly every photo; these were parts of the scene the model cannot fit yet "
                "(fine detail, reflections), trained on again from then on. Masks of the photos (docs/guide.md, \"Masks\") "
                "leave real transients out where this cannot")
    if not shares or photos < MIN_PHOTOS or len(shares) < EVERYWHERE_SHARE * photos:
        return None
    return (f"transients were found in {len(shares)} of the {photos} training photos: objects that come and go are "
            "seldom in nearly every photo, so these may be parts of the scene the model cannot fit yet (fine detail, "
            "reflections), left out of its training. Look at the run's transients/ folder (black: left out); if they "
            "cover the scene itself, train again without transients.detect, or with a higher transients.threshold")


def transients_note(shares: dict[str, float], photos: int | None = None,
                    where: str = "the run's transients/ folder", stopped: dict | None = None) -> str:
    """What training found, in words: ``shares`` {photo: share of its pixels left out} (``TrainSummary.transients``)
    of the photos with any, out of ``photos`` training photos (None: not said), their masks in ``where``;
    ``stopped``: the trainer's record of the test switching itself off (``transients_warning`` says why)."""
    from uncertsplat.console import count, list_names

    if stopped:
        return (f"{STOPPED} at step {stopped['step']} (regions in {stopped['photos']} "
                f"of the {stopped['of']} photos; the warning below says why); every pixel trained from then on, no "
                "masks written")
    if not shares:
        return (f"transients: found in none of the {count(photos, 'training photo')}" if photos is not None
                else "transients: found in no training photo") + "; every pixel trained"
    of = f" of {count(photos, 'training photo')}" if photos is not None else " training photo(s)"
    mean = sum(shares.values()) / len(shares)
    return (f"transients: found in {len(shares)}{of} ({list_names(list(shares), 4)}; {mean:.1%} of their pixels on "
            f"average), left out of the loss, the posterior and the fits on the training views; their masks are in "
            f"{where}")


__all__ = ["box_count", "pack_mask", "unpack_mask", "transient_masks", "transients_note", "transients_warning",
           "window_pixels", "EVERYWHERE_SHARE", "MEDIAN_FLOOR", "MIN_PHOTOS", "STOPPED"]
