"""3DGS adaptive density control and the spawn rule.

The decision functions are pure (tensors in, masks out) and table-tested. They are always fed the
posterior-mean parameters (``variational.posterior_mean``), never a fresh random sample, so a decision
does not depend on the noise of the step it happens at (docs/method.md, the original code's defect 4).
``Densifier`` ties the statistics, the schedule and ``gaussians.ops`` together for the trainer.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from uncertsplat import native
from uncertsplat.gaussians import ops
from uncertsplat.gaussians.params import GaussianModel
from uncertsplat.gaussians.prior import Prior
from uncertsplat.gaussians.variational import posterior_mean
from uncertsplat.strategy.budget import MAX_BUDGET
from uncertsplat.strategy.schedule import (  # noqa: F401 (RESET_RECOVERY_STEPS: also importable from here)
    RESET_RECOVERY_STEPS,
    is_densify_step,
    is_opacity_reset_step,
    is_spawn_step,
    is_stats_step,
)


# ------------------------------------------------------------------------------------------ decisions
def densify_decisions(grad: Tensor, max_scale: Tensor, *, grad_threshold: float, percent_dense: float,
                      extent: float) -> tuple[Tensor, Tensor]:
    """(clone [N], split [N]) masks: large mean screen gradient; small Gaussians clone, large ones split."""
    hot = grad >= grad_threshold
    small = max_scale <= percent_dense * extent
    return hot & small, hot & ~small


def limit_growth(clone: Tensor, split: Tensor, grad: Tensor, n: int, max_gaussians: int, split_children: int = 2
                 ) -> tuple[Tensor, Tensor]:
    """Keep only the highest-gradient candidates so that the model stays within ``max_gaussians``.

    A clone adds 1 Gaussian and a split adds ``split_children - 1``.
    """
    budget = max_gaussians - n
    growth = clone.sum() + (split_children - 1) * split.sum()
    if int(growth) <= budget:
        return clone, split
    cand = (clone | split).nonzero().flatten()
    order = cand[torch.argsort(grad[cand], descending=True, stable=True)]
    cost = torch.where(clone[order], 1, split_children - 1)
    ok = order[torch.cumsum(cost, 0) <= max(budget, 0)]
    keep = torch.zeros_like(clone)
    keep[ok] = True
    return clone & keep, split & keep


def prune_decisions(opacity: Tensor, *, min_opacity: float, max_scale: Tensor | None = None,
                    screen_radius: Tensor | None = None, max_screen_size: float | None = None,
                    extent: float = 1.0) -> Tensor:
    """[N] bool: transparent Gaussians, and (when ``max_screen_size`` is set) ones too big on screen
    (``screen_radius``, pixels, as in 3DGS) or in the world (> 0.1 x extent)."""
    out = opacity < min_opacity
    if max_screen_size is not None:
        if screen_radius is not None:
            out = out | (screen_radius > max_screen_size)
        if max_scale is not None:
            out = out | (max_scale > 0.1 * extent)
    return out


def spawn_decisions(scales: Tensor, opacity: Tensor, *, scale_fraction: float, min_opacity: float,
                    extent: float) -> Tensor:
    """[N] bool: Gaussians that should carry a posterior: ||scale|| > fraction x extent, not transparent."""
    return (scales.norm(dim=-1) > scale_fraction * extent) & (opacity >= min_opacity)


# ----------------------------------------------------------------------------------------- the driver
@dataclass
class DensifyStats:
    """Per-Gaussian screen statistics since the last densification (rows aligned with the model)."""

    grad_sum: Tensor  # [N] sum of NDC-space mean-gradient norms over the views where visible
    count: Tensor  # [N] number of such views
    max_radius: Tensor  # [N] largest screen radius in pixels

    @classmethod
    def zeros(cls, n: int, device) -> DensifyStats:
        z = torch.zeros(n, device=device)
        return cls(z, z.clone(), z.clone())

    def state_dict(self) -> dict:
        return {"grad_sum": self.grad_sum.clone(), "count": self.count.clone(), "max_radius": self.max_radius.clone()}

    @classmethod
    def from_state_dict(cls, s: dict, device=None) -> DensifyStats:
        return cls(s["grad_sum"].to(device), s["count"].to(device), s["max_radius"].to(device))


class Densifier:
    """Accumulates screen-space gradients and applies densify / prune / reset / spawn on schedule.

    Args:
        cfg: a ``DensifyConfig``.
        prior: the variational prior (new table rows start there; its variant and temperature form the posterior
            mean the decisions use, ``variational.posterior_mean``).
        extent: scene extent.
        n, device: the model's size and device (the rows of the screen statistics).
        posteriors: False for plain 3DGS (``method != "variational"``): no spawning, and split children
            carry a posterior only when their parent does (so a model without posteriors keeps none).
        iterations: the run's length (None: unknown): no opacity reset in its last ``RESET_RECOVERY_STEPS``.
        spawn_keeps_render: new carriers keep their posterior-mean render (``ops.spawn``'s ``keep_render``).
        split_keeps_render: so do split children given new rows (``ops.split``'s ``keep_render``).
    """

    def __init__(self, cfg, prior: Prior, extent: float, n: int, device, posteriors: bool = True,
                 iterations: int | None = None, spawn_keeps_render: bool = False, split_keeps_render: bool = False):
        self.cfg = cfg
        self.spawn_keeps_render = spawn_keeps_render  # ops.spawn's keep_render (the informed posterior's runs)
        self.split_keeps_render = split_keeps_render  # ops.split's keep_render (the same)
        self.posteriors = posteriors  # False: plain 3DGS, splits and spawns never create posteriors
        self.iterations = iterations  # the run's length: no opacity reset near its end (is_opacity_reset_step)
        self.prior = prior
        self.extent = float(extent)
        self.stats = DensifyStats.zeros(n, device)
        self.grow = True  # False once the growth test (strategy.growth) stopped growth
        # the model's size when the growth test stopped it: densification goes on cloning and splitting up to it,
        # replacing what pruning removes, as under a budget of that size (None with growth stopped: it only
        # prunes, as runs did before the refill; their checkpoints resume so)
        self.grown_to: int | None = None

    def accumulate(self, step: int, means2d_grad: Tensor, radii: Tensor, width: int, height: int) -> None:
        """Add one step's screen statistics. ``means2d_grad`` [C,N,2] is in pixels per unit loss; the
        threshold is defined in NDC, so x is scaled by W/2 and y by H/2 (times C: the loss is a mean)."""
        if not is_stats_step(step, self.cfg):
            return
        c = means2d_grad.shape[0]
        st = self.stats
        grad, radii = means2d_grad.detach(), radii.detach()
        n = grad.shape[1]
        shapes_fit = (grad.shape == (c, n, 2) and radii.shape == (c, n)
                      and all(t.shape == (n,) and t.is_contiguous() for t in (st.grad_sum, st.count, st.max_radius)))
        if shapes_fit and grad.is_contiguous() and radii.is_contiguous() and native.use_for(
                grad, radii, st.grad_sum, st.count, st.max_radius, dtypes=(torch.float32,), strict=False):
            # one pass instead of the ops below, the same bits (native/csrc/densify.cpp); a step's 0.3 ms at 30k
            native.library().us_densify_accumulate_f32(
                c, n, grad.data_ptr(), radii.data_ptr(), 0.5 * width * c, 0.5 * height * c,
                st.grad_sum.data_ptr(), st.count.data_ptr(), st.max_radius.data_ptr())
            return
        g = grad.clone()
        g[..., 0] *= 0.5 * width * c
        g[..., 1] *= 0.5 * height * c
        norm = g.norm(dim=-1)  # [C,N]
        vis = (radii > 0).to(norm.dtype)  # [C,N]
        self.stats.grad_sum += (norm * vis).sum(0)
        self.stats.count += vis.sum(0)
        radius = radii.detach().to(norm.dtype)
        self.stats.max_radius = torch.maximum(self.stats.max_radius, (radius * vis).amax(0))

    def step(self, step: int, model: GaussianModel, optimizer, generator: torch.Generator, *,
             limit: int | None = None) -> dict[str, int]:
        """Topology changes due at ``step`` (after its optimiser update). Returns counts of what happened; ``held``
        counts the clones and splits that ``limit`` (the model size memory allows, below the budget) left out."""
        cfg = self.cfg
        done = {"cloned": 0, "split": 0, "pruned": 0, "spawned": 0, "reset": 0, "held": 0}
        changed = False
        if is_densify_step(step, cfg, self.iterations):
            with torch.no_grad():
                pm = posterior_mean(model, variant=self.prior.variant, extent=self.extent,
                                    temperature=self.prior.temperature)
                grad = self.stats.grad_sum / self.stats.count.clamp_min(1)
                max_scale = pm.scales.amax(-1)
                clone_m, split_m = densify_decisions(grad, max_scale, grad_threshold=cfg.grad_threshold,
                                                     percent_dense=cfg.percent_dense, extent=self.extent)
                # the Trainer sets the scene's budget (strategy.budget); unset, the ceiling of any budget applies
                budget = cfg.max_gaussians if cfg.max_gaussians is not None else MAX_BUDGET
                if not self.grow:
                    budget = min(budget, self.grown_to) if self.grown_to is not None else 0
                clone_m, split_m = limit_growth(clone_m, split_m, grad, len(model), budget)
                if limit is not None and limit < budget and self.grow:
                    wanted = int(clone_m.sum()) + int(split_m.sum())
                    clone_m, split_m = limit_growth(clone_m, split_m, grad, len(model), limit)
                    done["held"] = wanted - int(clone_m.sum()) - int(split_m.sum())
                n0 = len(model)
                split_scales = pm.scales
            ops.clone(model, optimizer, clone_m)
            pad = len(model) - n0  # clones are appended at the end and are never split
            split_full = torch.cat([split_m, torch.zeros(pad, dtype=torch.bool, device=split_m.device)])
            scales_full = torch.cat([split_scales, split_scales[clone_m]])
            ops.split(model, optimizer, split_full, generator, scales=scales_full, prior=self.prior,
                      factor=cfg.split_factor, carry=self.posteriors, keep_render=self.split_keeps_render)
            with torch.no_grad():
                pm = posterior_mean(model, variant=self.prior.variant, extent=self.extent,
                                    temperature=self.prior.temperature)
                # split children are new: they have no screen statistics yet
                radius = torch.cat([self.stats.max_radius[~split_m],
                                    torch.zeros(len(model) - int((~split_m).sum()), device=model.device)])
                big = cfg.max_screen_size is not None and step > cfg.opacity_reset_interval
                prune_m = prune_decisions(pm.opacities, min_opacity=cfg.min_opacity, max_scale=pm.scales.amax(-1),
                                          screen_radius=radius, max_screen_size=cfg.max_screen_size if big else None,
                                          extent=self.extent)
            ops.remove(model, optimizer, prune_m)
            done.update(cloned=int(clone_m.sum()), split=int(split_m.sum()), pruned=int(prune_m.sum()))
            changed = True
        if is_opacity_reset_step(step, cfg, self.iterations):
            ops.reset_opacity(model, optimizer, 0.01)
            done["reset"] = 1
        if self.posteriors and is_spawn_step(step, cfg):
            with torch.no_grad():
                pm = posterior_mean(model, variant=self.prior.variant, extent=self.extent,
                                    temperature=self.prior.temperature)
                m = spawn_decisions(pm.scales, pm.opacities, scale_fraction=cfg.spawn_scale_fraction,
                                    min_opacity=cfg.spawn_min_opacity, extent=self.extent)
            done["spawned"] = ops.spawn(model, optimizer, m, self.prior, keep_render=self.spawn_keeps_render)
        if changed:
            self.stats = DensifyStats.zeros(len(model), model.device)
        return done
