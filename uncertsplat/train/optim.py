"""Adam with one parameter group per attribute (per-parameter learning rates) and the position schedule.

Group names are the keys of ``GaussianModel.parameters()`` (PARAM_SPECS then TABLE_SPECS), in that fixed
order, so an optimiser state dict saved in a checkpoint loads back into a freshly built optimiser.
"""

from __future__ import annotations

import torch

from uncertsplat import native
from uncertsplat.gaussians.params import PARAM_SPECS, GaussianModel
from uncertsplat.gaussians.prior import TABLE_SPECS
from uncertsplat.strategy.schedule import position_lr
from uncertsplat.train.adam import Adam

ADAM_EPS = 1e-15


def base_rates(lr_cfg, step: int, total: int, extent: float, *, table_lr_factor: float, variant: str
               ) -> dict[str, float]:
    """Learning rate of every group at ``step``.

    Positions: ``means_init`` x extent decaying exponentially to ``means_final`` x extent. Tables:
    ``table_lr_factor`` x the rate of the attribute they modulate. The position table is in units of the
    extent in variant "ours", so its rate is the (decayed) position rate divided by the extent.
    """
    pos = position_lr(step, total, lr_cfg.means_init, lr_cfg.means_final, extent)
    rates = {"means": pos, "sh0": lr_cfg.sh0, "shN": lr_cfg.shN, "opacities": lr_cfg.opacities,
             "scales": lr_cfg.scales, "quats": lr_cfg.quats}
    out = {s.name: rates[s.lr] for s in PARAM_SPECS}
    for s in TABLE_SPECS:
        base = rates[s.lr]
        if s.lr == "means" and variant == "ours":
            base = pos / extent
        out[s.name] = table_lr_factor * base
    return out


def make_optimizer(model: GaussianModel, rates: dict[str, float], sparse: str = "dense") -> torch.optim.Optimizer:
    """Adam (eps 1e-15, as 3DGS) with one named group per tensor of ``model.parameters()``.

    ``sparse``: ``"dense"`` (every row every step), ``"visible"`` or ``"lazy"`` (only the rows the step's views
    touch; ``TrainConfig.sparse_updates``). Ours (``train.adam.Adam``) where the native kernels take the
    parameters (CPU float32: one call for every group, with the NaN/Inf check) or the update is sparse; torch's
    fused Adam otherwise (one kernel per tensor; several times faster than torch's default there). Both keep the
    same state layout, so checkpoints load either way.
    """
    groups = [{"params": [p], "lr": rates[name], "name": name} for name, p in model.parameters().items()]
    params = list(model.parameters().values())
    if sparse != "dense" or native.use_for(*params, dtypes=(torch.float32,), strict=False):
        return Adam(groups, eps=ADAM_EPS, lazy=sparse == "lazy")
    device = model.device.type
    fused = device in ("cpu", "cuda") and all(p.dtype.is_floating_point for p in params)
    return torch.optim.Adam(groups, lr=0.0, eps=ADAM_EPS, fused=fused or None)


def load_optimizer_state(optimizer: torch.optim.Optimizer, state_dict: dict) -> None:
    """``optimizer.load_state_dict`` of a checkpoint saved by either Adam (ours on CPU, torch's elsewhere): each
    group keeps this optimiser's own options (torch's Adam needs its keys, such as ``weight_decay``, and a CUDA run
    resumed from a CPU checkpoint should stay fused), the rates and moments come from the checkpoint."""
    saved = state_dict["param_groups"]
    if len(saved) == len(optimizer.param_groups):
        saved = [{**{k: v for k, v in mine.items() if k != "params"}, "params": old["params"], "lr": old["lr"]}
                 for mine, old in zip(optimizer.param_groups, saved, strict=True)]
    optimizer.load_state_dict({**state_dict, "param_groups": saved})


def set_rates(optimizer: torch.optim.Optimizer, rates: dict[str, float]) -> None:
    for g in optimizer.param_groups:
        g["lr"] = rates[g["name"]]
