"""Per-photo exposure: an affine colour map per training photo, learned with the model (``TrainConfig.exposure``).

Photos taken with automatic exposure or white balance (phones, outdoor captures) show one surface brighter in some
than in others. A model without a way to explain that fits each photo's brightness with Gaussians, and Gaussians a
single photo needs sit in front of the surface where the other views do not check them: floaters. With
``exposure = "affine"``, each training photo ``v`` gets a gain and an offset per channel, and the loss compares
``gain_v * render + offset_v`` with the photo, so the Gaussians hold the scene at a common exposure.

The parameters are stored as ``[T,2,3]`` (log gain, offset) per training photo and used *centred*: the mean log gain
and the mean offset over the photos are subtracted, so the model's colours are those of the capture's typical
exposure (a shift of every photo's exposure is the same as a change of every Gaussian's colour, and the centring
takes that freedom away). A new photo's exposure is not known: the spread of the learned exposures over the
training photos is the uncertainty a new photo's colours carry (``spread_variance``).

Pure tensor functions; the trainer owns the parameters and their optimiser.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch
from torch import Tensor

from uncertsplat.schemas.runs import RunExposure
from uncertsplat.types import ViewSet


def centred(params: Tensor) -> tuple[Tensor, Tensor]:
    """([T,3] gains, [T,3] offsets) of ``params`` [T,2,3] (log gain, offset per photo and channel), centred over the
    photos: the gains' geometric mean and the offsets' mean are 1 and 0 per channel."""
    log_gain, offset = params[:, 0], params[:, 1]
    return torch.exp(log_gain - log_gain.mean(0, keepdim=True)), offset - offset.mean(0, keepdim=True)


def exposure_record(params: Tensor, images: list[str], step: int) -> RunExposure:
    """``RUN/exposure.json``'s record of ``params`` [T,2,3] (``centred``) for the training photos ``images``."""
    gain, offset = (t.detach().double().cpu().tolist() for t in centred(params.detach()))
    return RunExposure(images=list(images), gain=gain, offset=offset, step=int(step))


def expose(rgb: Tensor, gain: Tensor, offset: Tensor) -> Tensor:
    """``rgb`` [B,H,W,3] at the exposures ``gain``, ``offset`` [B,3] (one per image): what those photos show."""
    return rgb * gain[:, None, None, :] + offset[:, None, None, :]


def unexpose(photos: Tensor, gain: Tensor, offset: Tensor) -> Tensor:
    """``photos`` [B,H,W,3] brought to the model's exposure (the inverse of ``expose``)."""
    return (photos - offset[:, None, None, :]) / gain[:, None, None, :]


def spread_variance(rgb: Tensor, gain: Tensor, offset: Tensor) -> Tensor:
    """[...,1] the variance, over the photos' exposures ``gain``, ``offset`` [T,3], of the colour a photo at one of
    them shows where the model renders ``rgb`` [...,3], mean over the channels: Var(g c + o) = Var(g) c^2 +
    2 Cov(g, o) c + Var(o) per channel (population moments over the T photos; 0 for fewer than two)."""
    if gain.shape[0] < 2:
        return rgb.new_zeros(*rgb.shape[:-1], 1)
    g, o = gain.to(rgb.dtype), offset.to(rgb.dtype)
    dg, do = g - g.mean(0), o - o.mean(0)
    var_g, var_o, cov = dg.square().mean(0), do.square().mean(0), (dg * do).mean(0)  # [3] each
    var = var_g * rgb.square() + 2.0 * cov * rgb + var_o
    return var.clamp_min(0.0).mean(-1, keepdim=True)


def fitted_gain(render: Tensor, photo: Tensor) -> float:
    """The gain of the least-squares affine map (per channel, with an offset) from ``render`` [H,W,3] to ``photo``
    [H,W,3], mean over the channels: about 1 for a photo at the model's exposure, g for one g times brighter. A flat
    render (no variance) gives 1."""
    r, p = render.reshape(-1, 3).double(), photo.reshape(-1, 3).double()
    if r.shape[0] < 2:
        return 1.0
    rc, pc = r - r.mean(0), p - p.mean(0)
    var = rc.square().sum(0)
    gain = torch.where(var > 1e-12, (rc * pc).sum(0) / var.clamp_min(1e-12), torch.ones_like(var))
    return float(gain.mean())


@dataclass(frozen=True)
class PhotoExposure:
    """The learned exposures of a run's training photos (``RUN/exposure.json``), for evaluation.

    Attributes:
        indices: the training photos' view indices in their scene.
        gain: [T,3] per photo and channel, centred (``centred``).
        offset: [T,3] likewise.
    """

    indices: tuple[int, ...]
    gain: Tensor
    offset: Tensor

    def unexposed(self, views: ViewSet) -> ViewSet:
        """``views`` with the images of the training photos among them brought to the model's exposure
        (``unexpose``); other views (held out, set aside for calibration: their exposure is not known) unchanged."""
        images = self.unexposed_images(views.indices, views.images)
        return views if images is views.images else dataclasses.replace(views, images=images)

    def unexposed_images(self, indices, images):
        """``images`` [B,H,W,3] (a float32 tensor or ``types.Photos``) of the scene's views ``indices`` [B], those of
        training photos brought to the model's exposure (a new float32 tensor; ``images`` itself when none is a
        training photo)."""
        rows = {v: r for r, v in enumerate(self.indices)}
        which = [(j, rows[int(v)]) for j, v in enumerate(indices) if int(v) in rows]
        if not which:
            return images
        base = images.float()  # types.Photos of uint8: all converted (a new tensor); of float32, or a tensor: its own
        out = base.clone() if base is images or base is getattr(images, "data", None) else base
        pos = torch.tensor([j for j, _ in which], dtype=torch.long, device=base.device)
        row = torch.tensor([r for _, r in which], dtype=torch.long)
        out[pos] = unexpose(base[pos], self.gain[row].to(base), self.offset[row].to(base))
        return out

    def variance(self, rgb: Tensor) -> Tensor:
        """[...,1] the variance of a new photo's colours where the model renders ``rgb`` [...,3]
        (``spread_variance`` over the training photos' exposures)."""
        return spread_variance(rgb, self.gain.to(rgb.device), self.offset.to(rgb.device))


__all__ = ["PhotoExposure", "centred", "expose", "exposure_record", "fitted_gain", "spread_variance",
           "unexpose"]
