"""Which SH bands a scene needs: each band is kept only while the training views show that it pays.

The colour of a Gaussian is a spherical-harmonics expansion; band d (2d + 1 coefficients per channel) adds
view dependence of angular frequency d. Degree 3 (15 of the 16 coefficients per channel beyond the DC term:
45 of a Gaussian's 59 numbers) is 3DGS's fixed choice, whatever the scene. A matte scene needs none of it,
and then the bands cost a larger model, a larger PLY and slower steps for nothing.

The check (``TrainConfig.sh_min_gain_db``): the degree rises by one every ``sh_degree_interval`` steps; when
band d has trained for one interval (the step the next band would start), a few training views are rendered
with and without it. If band d improves their PSNR by less than ``sh_min_gain_db``, it and every band above
it are dropped (``gaussians.ops.truncate_sh``: coefficients and Adam moments removed) and the degree stays
at d - 1. Only training views are used: the held-out views stay unseen by every training decision.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import torch
from torch import Tensor

from uncertsplat.schemas.runs import ShBandCheck
from uncertsplat.strategy.view_checks import psnr_gain_db
from uncertsplat.types import Cameras, GaussianSample

# One band's test (degree, step, gain_db, kept, min_gain_db, views): the record ``train_summary.json`` keeps.
BandCheck = ShBandCheck


def band_reason(check: BandCheck) -> str:
    """One line for the log and the report: the band, its measured gain and what was decided."""
    verdict = "kept" if check.kept else f"dropped: the model keeps degree {check.degree - 1}"
    cmp = ">=" if check.kept else "<"
    return (f"SH band {check.degree} on for one sh_degree_interval, tested at step {check.step}: {check.gain_db:+.4f} dB on "
            f"{check.views} training views ({cmp} {check.min_gain_db:g} dB), {verdict}")


def check_due(step: int, interval: int, max_degree: int, min_gain_db: float, checked: set[int]) -> int | None:
    """The band to test before ``step`` runs, or None.

    Band d starts at step d x interval (``schedule.sh_degree_at``) and is tested at step (d + 1) x interval, after
    ``interval`` steps with it. Nothing is tested when ``min_gain_db`` is 0 (every band up to ``max_degree``
    stays), for degree 0, or twice.
    """
    if min_gain_db <= 0 or step <= 0 or step % interval:
        return None
    d = step // interval - 1
    if d < 1 or d > max_degree or d in checked:
        return None
    return d


@torch.no_grad()
def band_gain_db(sample: GaussianSample, degree: int, cameras: Cameras, images: Tensor,
                 render_fn: Callable[[GaussianSample, Cameras], Tensor], masks: Tensor | None = None) -> float:
    """Training-view PSNR gain (dB) of SH band ``degree``: ``10 log10(mse without / mse with)``.

    Args:
        sample: the Gaussians to render (their ``sh`` has at least ``(degree + 1)^2`` bases).
        degree: the band tested (>= 1); "with" renders degrees 0..degree, "without" 0..degree - 1.
        cameras: [V] training cameras. images: [V,H,W,3] their photos.
        render_fn: (sample, camera) -> [1,H,W,3] image in [0, 1].
        masks: [V,H,W,1] bool, the pixels that count, or None for all.

    As ``view_checks.psnr_gain_db``: two identical renders (no band content) give exactly 0.
    """
    if degree < 1:
        raise ValueError(f"band degree must be >= 1, got {degree}")
    return psnr_gain_db(replace(sample, sh_degree=degree), replace(sample, sh_degree=degree - 1), cameras, images,
                        render_fn, masks)
