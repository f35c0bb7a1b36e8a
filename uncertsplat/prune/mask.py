"""Score -> keep mask -> pruned copy of a model (pure tensor functions; no disk I/O).

Masks are [N] bool tensors, True = keep. Only posterior carriers are ever removed by a score (the
others have no posterior to judge; see ``uncertainty.scores``), so the strongest pruning a score can do
keeps every non-carrier. Ties in a score are broken by Gaussian index (stable sort), so the same
scores always give the same mask.
"""

from __future__ import annotations

import torch
from torch import Tensor

from uncertsplat.gaussians import ops
from uncertsplat.gaussians.params import GaussianModel


def num_to_remove(n: int, keep_ratio: float) -> int:
    """Gaussians to remove so that ``round(keep_ratio * n)`` remain (at least one kept when n > 0)."""
    if not (0.0 < keep_ratio <= 1.0):
        raise ValueError(f"keep_ratio must be in (0, 1], got {keep_ratio}")
    keep = max(1, round(keep_ratio * n)) if n > 0 else 0
    return n - keep


def keep_top(score: Tensor, candidates: Tensor, n_remove: int) -> Tensor:
    """[N] keep mask removing the ``n_remove`` highest-scoring ``candidates`` (at most all of them).

    Args:
        score: [N] higher = more uncertain (NaN counts as most uncertain).
        candidates: [N] bool, the Gaussians that may be removed.
        n_remove: how many to remove (clamped to the number of candidates).
    """
    n = score.shape[0]
    keep = torch.ones(n, dtype=torch.bool, device=score.device)
    cand = candidates.nonzero().flatten()
    k = min(max(int(n_remove), 0), cand.numel())
    if k == 0:
        return keep
    s = torch.nan_to_num(score[cand].double(), nan=float("inf"))
    # stable descending sort: among equal scores the lower index is removed first
    order = torch.sort(-s, stable=True).indices
    keep[cand[order[:k]]] = False
    return keep


def keep_ratio_mask(score: Tensor, candidates: Tensor, keep_ratio: float) -> Tensor:
    """[N] keep mask for a target fraction of all Gaussians kept (removing only candidates)."""
    return keep_top(score, candidates, num_to_remove(score.shape[0], keep_ratio))


def threshold_mask(score: Tensor, candidates: Tensor, threshold: float) -> Tensor:
    """[N] keep mask removing the candidates whose score exceeds ``threshold`` (NaN counts as above)."""
    above = (score > threshold) | torch.isnan(score)
    return ~(above & candidates)


def random_mask(n: int, n_remove: int, generator: torch.Generator, candidates: Tensor | None = None) -> Tensor:
    """[N] keep mask removing ``n_remove`` uniformly random Gaussians (among ``candidates`` when given).

    The random numbers come from ``generator`` only (on its device); the mask is on the candidates' device
    (the generator's when no candidates are given).
    """
    dev = candidates.device if candidates is not None else generator.device
    pool = torch.arange(n, device=dev) if candidates is None else candidates.nonzero().flatten()
    k = min(max(int(n_remove), 0), pool.numel())
    perm = torch.randperm(pool.numel(), generator=generator, device=generator.device).to(dev)
    keep = torch.ones(n, dtype=torch.bool, device=dev)
    keep[pool[perm[:k]]] = False
    return keep


def copy_model(model: GaussianModel) -> GaussianModel:
    """A deep copy (detached tensors), so that pruning never touches the original."""
    return GaussianModel.from_state_dict(model.state_dict())


def apply_keep(model: GaussianModel, keep: Tensor) -> GaussianModel:
    """A new model holding the rows where ``keep`` [N] is True (tables and ``posterior_row`` aligned)."""
    keep = keep.to(model.device, torch.bool)
    if keep.shape != (len(model),):
        raise ValueError(f"keep mask must be [{len(model)}], got {tuple(keep.shape)}")
    out = copy_model(model)
    ops.remove(out, None, ~keep)
    return out


def kept_indices(keep: Tensor) -> Tensor:
    """[M] int64 indices (into the original model) of the kept Gaussians, ascending."""
    return keep.nonzero().flatten().to(torch.long)


def mask_from_indices(indices: Tensor, n: int) -> Tensor:
    """Inverse of ``kept_indices``: [N] bool keep mask (ValueError on indices out of range or repeated)."""
    indices = indices.to(torch.long)
    if indices.numel() and (int(indices.min()) < 0 or int(indices.max()) >= n):
        raise ValueError(f"kept indices out of range for a model of {n} Gaussians")
    if torch.unique(indices).numel() != indices.numel():
        raise ValueError("kept indices repeat")
    keep = torch.zeros(n, dtype=torch.bool, device=indices.device)
    keep[indices] = True
    return keep
