"""Uncertainty-based pruning: per-Gaussian score -> keep mask -> ``gaussians.ops.remove`` on a copy.

The scores live in ``uncertainty.scores``; the stage (``stages/prune.py``) does all disk I/O.
"""

from uncertsplat.prune.mask import (
    apply_keep,
    copy_model,
    keep_ratio_mask,
    keep_top,
    kept_indices,
    mask_from_indices,
    num_to_remove,
    random_mask,
    threshold_mask,
)

__all__ = ["apply_keep", "copy_model", "keep_ratio_mask", "keep_top", "kept_indices", "mask_from_indices",
           "num_to_remove", "random_mask", "threshold_mask"]
