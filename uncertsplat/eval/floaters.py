"""Which Gaussians of a model are floaters, judged against ground-truth depth.

A floater is a Gaussian in free space: in every view whose image contains its centre, the centre is in
front of the true surface seen through that pixel by more than a margin. A Gaussian on a surface is at the
surface depth in the views that see it, and one inside an object or hidden behind another is behind the
surface in every view; neither counts. The margin (``margin_scale`` times the Gaussian's largest axis plus
``margin_extent`` times the scene extent) keeps the large, flat Gaussians that lie on a surface, whose
centre may sit a little off it, out of the floater set.

Only a scene with GT depth for its training views can be labelled this way (the synthetic scenes of
``uncertsplat synth``): the labels let the pruning benchmark ask whether a score finds the floaters that
training produced, instead of planted ones.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from uncertsplat.eval.calibration import average_ranks
from uncertsplat.types import Cameras
from uncertsplat.uncertainty.scores import centre_gap


@dataclass(frozen=True)
class FloaterLabels:
    """Per-Gaussian free-space labels.

    Attributes:
        is_floater: [N] bool, in front of the surface by more than the margin in every view that contains it.
        num_views: [N] int, views whose image contains the centre (in front of the camera's near plane).
        gap: [N] float, the smallest (GT depth - centre depth) over those views, in world units; +inf when
            no view contains the centre.
    """

    is_floater: Tensor
    num_views: Tensor
    gap: Tensor


@torch.no_grad()
def label_floaters(means: Tensor, scales: Tensor, cameras: Cameras, depths: Tensor, *, extent: float,
                   near: float = 1e-3, margin_scale: float = 3.0, margin_extent: float = 0.01) -> FloaterLabels:
    """Label the Gaussians in free space (see the module docstring).

    Args:
        means: [N,3] centres in world units.
        scales: [N,3] linear scales (the largest axis sets the Gaussian's own margin).
        cameras: the C views with ground truth.
        depths: [C,H,W] or [C,H,W,1] GT camera z per pixel, in the same world units (0, negative or
            non-finite: no surface there, i.e. free space along the whole ray).
        extent: the scene extent (for the absolute part of the margin).
        near: centres closer to a camera than this are not counted as inside its image.
    """
    if depths.ndim == 4:
        depths = depths[..., 0]
    margin = margin_scale * scales.amax(1) + margin_extent * float(extent)  # [N]
    gap, views = centre_gap(means, cameras, lambda c: depths[c], near=near)
    return FloaterLabels(is_floater=(views > 0) & (gap > margin), num_views=views, gap=gap)


def ranking_auc(score: Tensor, positive: Tensor, candidates: Tensor | None = None) -> float:
    """Probability that a random positive outranks a random negative (ties count half): the ROC AUC.

    ``candidates`` [N] bool restricts both sets (e.g. to the Gaussians a score can remove). Returns NaN when
    either set is empty.
    """
    if candidates is not None:
        score, positive = score[candidates], positive[candidates]
    npos, nneg = int(positive.sum()), int((~positive).sum())
    if npos == 0 or nneg == 0:
        return float("nan")
    # Mann-Whitney U from average ranks (ties share their mean rank)
    ranks = average_ranks(score.double())
    u = float(ranks[positive].sum()) - npos * (npos + 1) / 2.0
    return u / (npos * nneg)
