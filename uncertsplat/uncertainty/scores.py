"""Per-Gaussian uncertainty scores from the learned posterior (what ``uncertsplat prune`` ranks by).

Only posterior carriers (Gaussians with an offset table) have a learned posterior. Every score is >= 0
for carriers and exactly 0 for non-carriers, and ``carriers`` marks which is which: non-carriers have no
posterior to judge, so they count as the least uncertain and pruning by a score never removes them.

Scores (``SCORE_NAMES``; higher = more uncertain). All table columns are first averaged over the K
entries, as ``variational.posterior_mean`` does.

``position``
    Position spread relative to the Gaussian's own size: RMS posterior position std over the 3 axes
    (world units) divided by the largest axis of its posterior-mean scale. A spread of 1 means a sample
    moves the Gaussian by about its own footprint. Dimensionless, so large and small Gaussians compare.
``scale``
    Width w of the scale-multiplier interval [l, l + w] averaged over the 3 axes: how much the size of
    the Gaussian varies between samples, as a fraction of its size (dimensionless).
``gate``
    Gate-off probability P(g < 0.5) = P(nu + tau eta < 0) = Phi(-nu / tau) for the gate logit
    N(nu, tau^2): the chance that a sample switches the Gaussian (mostly) off. In [0, 1].
``free-space``
    For floaters: how far the Gaussian lies in front of the model's own surface. In every training view
    whose image contains its centre (posterior mean), the model's rendered depth at that pixel (where the
    render covers it, alpha >= 0.5; elsewhere the ray shows no surface) minus the centre's depth; the
    smallest over those views, in units of the Gaussian's largest axis, is d. A Gaussian in front of the
    surface by more than ``free_space_margin`` (1) of its own sizes in *every* view that contains it sits in
    free space, where the views see through it to the surface behind: it scores 1 + d; every other carrier
    scores its ``gate`` probability (in [0, 1]), so the floaters rank first and the rest in ``gate``'s order.
    One render per view (at most ``free_space_views`` training views, evenly spaced), no sampling.
``predictive``
    How much the Gaussian's sampled variation changes the rendered training views, weighted by how much
    it contributes to them. With W_s = its blending weight accumulated over the chosen training views in
    posterior sample s (sum over pixels of T_i alpha_i, divided by the pixels of one view, so 1 = one
    full view's worth of coverage), the score is

        predictive = sqrt( Var_s[W_s] + (mean_s[W_s] * min(1, position))^2 )

    The first term is the change of its coverage (gate switching it off, the scale multiplier, moving
    behind or out of occluders); the second approximates the change of the image when a footprint of
    weight W moves by ``position`` times its size (a move of its full size or more changes all of it).
    A cheap Monte-Carlo estimate: S posterior samples (default 4) of V training views (default: at most
    8, evenly spaced). W is read from one backward pass per render: the rendered colour is linear in
    each Gaussian's colour with coefficient T_i alpha_i summed over pixels, so rendering every Gaussian
    with SH DC 0 (colour 0.5, above the clamp at 0) and differentiating the red channel's sum w.r.t. its
    DC coefficient gives C0 x W_i. Gaussians that no chosen view sees score 0.

Which score is the default (``DEFAULT_SCORE``) is decided by the pruning benchmark
(``benchmarks/bench_prune.py``, BENCHMARKS.md "Pruning"): held-out PSNR vs keep ratio, and the floaters that
training leaves (GT-depth labels); ``--score auto`` measures ``AUTO_ALTERNATIVES`` beside it on the held-out views
and prunes by the better one (``stages.prune``).
``predictive`` ranks Gaussians that matter most to the image first (its weight is their contribution), so
it must not be used to shrink a model: removing even its top few percent costs much of the image quality.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import replace

import torch
import torch.nn.functional as F
from torch import Tensor

from uncertsplat.gaussians.params import GaussianModel
from uncertsplat.gaussians.prior import MAX_WIDTH, MIN_WIDTH, Variant
from uncertsplat.gaussians.variational import gate_off_probability, posterior_mean, sample
from uncertsplat.render.sh import C0
from uncertsplat.types import Cameras, GaussianSample

SCORE_NAMES: tuple[str, ...] = ("position", "scale", "gate", "predictive", "free-space")
POSTERIOR_SCORES: tuple[str, ...] = ("position", "scale", "gate")
"""Scores that need no rendering (read from the offset tables only)."""
DEFAULT_SCORE = "free-space"
"""The score ``--score auto`` uses, chosen from the pruning benchmark's floater table (BENCHMARKS.md, "Pruning"):
on the demo scene it ranks the floaters that training leaves (labelled with GT depth) at ROC AUC 0.89 against
0.68 for ``gate``, and past the floaters it removes Gaussians in ``gate``'s order, so shrinking a model costs
about what ``gate`` costs. ``gate`` (no rendering at all) remains the choice for shrinking a model without
looking for floaters. ``predictive`` removes important Gaussians too: use it only with a small removal
(``--keep-ratio 0.98``) and look at the before/after renders."""


AUTO_ALTERNATIVES: tuple[str, ...] = ("gate",)
"""What ``--score auto`` also measures with ``--auto`` or ``--keep-ratio`` on held-out views, using whichever of it and
``DEFAULT_SCORE`` prunes better there (``prune.policy.choose_score_by_removal`` / ``choose_score_at_ratio``): on fern at
1/8 (7000 steps) ``free-space`` cost 0.46 dB for its first 5 % (random removal 0.67 dB), ``gate`` 0.00 dB for 30 %
(BENCHMARKS.md, "Pruning"). No render: it is read from the offset tables."""


def resolve_score_name(name: str) -> str:
    """``auto`` -> ``DEFAULT_SCORE``; other names are checked against ``SCORE_NAMES`` (ValueError)."""
    if name == "auto":
        return DEFAULT_SCORE
    if name not in SCORE_NAMES:
        raise ValueError(f"unknown score '{name}' (choose one of: auto, {', '.join(SCORE_NAMES)})")
    return name


def carrier_mask(model: GaussianModel) -> Tensor:
    """[N] bool: the Gaussians that carry a posterior."""
    return model.posterior_row >= 0


@torch.no_grad()
def posterior_scores(model: GaussianModel, *, variant: Variant = "ours", extent: float = 1.0,
                     temperature: float = 0.2) -> dict[str, Tensor]:
    """The ``position``, ``scale`` and ``gate`` scores [N] (0 for non-carriers; see the module docstring)."""
    n = len(model)
    dev = model.device
    out = {k: torch.zeros(n, device=dev) for k in POSTERIOR_SCORES}
    idx = model.carrier_index()  # [P] in table-row order
    if idx.numel() == 0:
        return out
    t = {k: v.detach().mean(1) for k, v in model.tables.items()}  # [P,D]
    unit = float(extent) if variant == "ours" else 1.0
    sigma = F.softplus(t["pos_spread_raw"]) * unit  # [P,3] world units
    rms = sigma.square().mean(1).sqrt()
    size = posterior_mean(model, variant=variant, extent=extent, temperature=temperature).scales[idx].amax(1)
    # a degenerate (zero-size) Gaussian: any spread is "large"; keep the ratio finite
    out["position"][idx] = rms / size.clamp_min(1e-12)
    out["scale"][idx] = F.softplus(t["scale_width_raw"]).clamp(MIN_WIDTH, MAX_WIDTH).mean(1)
    out["gate"][idx] = gate_off_probability(t["gate_loc"][:, 0], F.softplus(t["gate_spread_raw"])[:, 0])
    return out


def blending_weights(sample_: GaussianSample, cameras: Cameras, *, render_fn, masks: Tensor | None = None) -> Tensor:
    """[N] blending weight of each Gaussian accumulated over ``cameras``, in units of one view's pixels.

    Computed through one backward pass (see the module docstring): every Gaussian gets SH DC 0 and no
    higher bands, so the red channel is 0.5 x sum_i T_i alpha_i, and its gradient w.r.t. the DC is C0 x
    that sum per Gaussian. ``render_fn(sample, cameras)`` must not add a background that depends on it.
    ``masks``: [C,H,W,1] bool, the pixels that count in each view (None: all); a Gaussian seen only where they are
    False (a masked-out sky, a passer-by's region) weighs 0 there.
    """
    n = len(sample_)
    dc = torch.zeros(n, 1, 3, device=sample_.means.device, dtype=sample_.means.dtype, requires_grad=True)
    plain = replace(sample_.detach(), sh=dc, sh_degree=0)  # keeps position_var when the sample has one
    total = torch.zeros(n, device=sample_.means.device)
    for c in range(len(cameras)):  # one view at a time keeps memory at one render
        if dc.grad is not None:
            dc.grad = None
        out = render_fn(plain, cameras[[c]])
        red = out.rgb[..., 0]  # [1,H,W]
        (red if masks is None else red * masks[c, ..., 0]).sum().backward()
        total += dc.grad[:, 0, 0].detach() / C0
    return total / float(cameras.width * cameras.height)


def predictive_score(model: GaussianModel, cameras: Cameras, generator: torch.Generator, *, render_fn,
                     num_samples: int = 4, subset_size: int = 2, variant: Variant = "ours", extent: float = 1.0,
                     temperature: float = 0.2, position: Tensor | None = None) -> dict[str, Tensor]:
    """The ``predictive`` score [N] and the mean contribution ``contribution`` [N] (see the module docstring).

    Args:
        model: the Gaussians and their offset tables.
        cameras: training views to measure on (their count sets the cost: num_samples x views renders).
        generator: source of the posterior samples.
        render_fn: ``render_fn(sample, cameras) -> RenderOutput`` (background and tile size bound).
        num_samples: S posterior samples (>= 2 for a variance).
        position: the ``position`` score [N] (computed when None).
    """
    if num_samples < 2:
        raise ValueError("predictive_score needs num_samples >= 2 (a variance over samples)")
    carriers = carrier_mask(model)
    if position is None:
        position = posterior_scores(model, variant=variant, extent=extent, temperature=temperature)["position"]
    weights = []
    for _ in range(num_samples):
        with torch.no_grad():
            s = sample(model, generator, subset_size=subset_size, variant=variant, extent=extent,
                       temperature=temperature, sh_degree=0)
        weights.append(blending_weights(s, cameras, render_fn=render_fn))
    w = torch.stack(weights)  # [S,N]
    mean = w.mean(0)
    var = w.var(0, unbiased=True)
    pred = torch.sqrt(var + (mean * position.clamp_max(1.0)).square())
    pred = torch.where(carriers, pred, torch.zeros_like(pred))
    return {"predictive": pred, "contribution": mean}


@torch.no_grad()
def centre_gap(means: Tensor, cameras: Cameras, depth_of: Callable[[int], Tensor], *,
               near: float = 1e-3) -> tuple[Tensor, Tensor]:
    """How far each centre lies in front of the surface, over the views whose image contains it.

    Args:
        means: [N,3] centres in world units.
        cameras: C views; ``depth_of(c)`` gives view c's [H,W] surface depth (camera z; 0, negative or
            non-finite: no surface, i.e. free space along the whole ray).
        near: centres closer to a camera than this are not inside its image.

    Returns:
        ([N] the smallest (surface depth - centre depth) over the views containing the centre, +inf when no
        view contains it or every such ray is free; [N] int, the number of views containing it).
    """
    n = means.shape[0]
    dev = means.device
    gap = torch.full((n,), float("inf"), device=dev, dtype=means.dtype)
    views = torch.zeros(n, dtype=torch.long, device=dev)
    H, W = cameras.height, cameras.width
    for c in range(len(cameras)):
        rt = cameras.cam_from_world[c].to(dev, means.dtype)
        p = means @ rt[:3, :3].T + rt[:3, 3]  # [N,3] camera coordinates
        z = p[:, 2]
        k = cameras.K[c].to(dev, means.dtype)
        zs = z.clamp_min(near)
        u = k[0, 0] * p[:, 0] / zs + k[0, 2]
        v = k[1, 1] * p[:, 1] / zs + k[1, 2]
        inside = (z > near) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
        d = depth_of(c).to(dev, means.dtype)[v.clamp(0, H - 1).long(), u.clamp(0, W - 1).long()]  # [N]
        d = torch.where(torch.isfinite(d) & (d > 0), d, torch.full_like(d, float("inf")))
        gap = torch.minimum(gap, torch.where(inside, d - z, torch.full_like(z, float("inf"))))
        views += inside.long()
    return gap, views


FREE_SPACE_ALPHA = 0.5
"""A pixel whose render covers less than this shows no surface to the ``free-space`` score."""


@torch.no_grad()
def free_space_depth(sample_: GaussianSample, cameras: Cameras, *, render_fn) -> tuple[Tensor, Tensor]:
    """([N] d: the smallest depth by which each centre lies in front of the model's rendered surface over the
    ``cameras`` containing it, in units of its largest axis (+inf: no surface behind it in any of them); [N]
    the number of those views). One render per camera (see ``free-space`` in the module docstring)."""
    means = sample_.means.detach()

    def depth_of(c: int) -> Tensor:
        out = render_fn(sample_, cameras[[c]])
        d = out.depth[0, ..., 0]
        return torch.where(out.alpha[0, ..., 0] >= FREE_SPACE_ALPHA, d, torch.zeros_like(d))

    gap, views = centre_gap(means, cameras, depth_of)
    return gap / sample_.scales.detach().amax(1).clamp_min(1e-12), views


def free_space_score(model: GaussianModel, cameras: Cameras, *, render_fn, gate: Tensor, margin: float = 1.0,
                     variant: Variant = "ours", extent: float = 1.0, temperature: float = 0.2) -> Tensor:
    """The ``free-space`` score [N] (0 for non-carriers; see the module docstring).

    Args:
        model: the Gaussians (their posterior mean is rendered and tested).
        cameras: training views (one render each).
        render_fn: ``render_fn(sample, cameras) -> RenderOutput``.
        gate: the ``gate`` score [N], the order of the Gaussians that are not in free space.
        margin: how many of its own sizes in front of the surface a Gaussian must be in every view.
    """
    pm = posterior_mean(model, variant=variant, extent=extent, temperature=temperature, sh_degree=0)
    d, views = free_space_depth(pm, cameras, render_fn=render_fn)
    free = (views > 0) & (d > margin)
    score = torch.where(free, 1.0 + d.clamp_max(1e6).to(gate.dtype), gate)
    return torch.where(carrier_mask(model), score, torch.zeros_like(score))


def spread_views(indices: Sequence[int], max_views: int) -> list[int]:
    """At most ``max_views`` of ``indices``, evenly spaced (all of them when there are fewer)."""
    indices = list(indices)
    if len(indices) <= max_views:
        return indices
    step = len(indices) / max_views
    return [indices[int(i * step)] for i in range(max_views)]


def compute_scores(model: GaussianModel, cameras: Cameras | None, generator: torch.Generator | None, *,
                   render_fn=None, names: Sequence[str] = SCORE_NAMES, num_samples: int = 4, subset_size: int = 2,
                   variant: Variant = "ours", extent: float = 1.0, temperature: float = 0.2,
                   free_space_cameras: Cameras | None = None, free_space_margin: float = 1.0) -> dict[str, Tensor]:
    """Every score in ``names`` as [N] tensors, plus ``contribution`` when ``predictive`` is asked for.

    ``cameras``, ``generator`` and ``render_fn`` are needed only for ``predictive``; ``free-space`` renders
    ``free_space_cameras`` (default: ``cameras``) with ``render_fn``.
    """
    for name in names:
        resolve_score_name(name)
    out = posterior_scores(model, variant=variant, extent=extent, temperature=temperature)
    if "free-space" in names:
        fs_cams = free_space_cameras if free_space_cameras is not None else cameras
        if fs_cams is None or render_fn is None:
            raise ValueError("the free-space score needs training cameras and render_fn")
        out["free-space"] = free_space_score(model, fs_cams, render_fn=render_fn, gate=out["gate"],
                                             margin=free_space_margin, variant=variant, extent=extent,
                                             temperature=temperature)
    if "predictive" in names:
        if cameras is None or generator is None or render_fn is None:
            raise ValueError("the predictive score needs cameras, a generator and render_fn")
        out.update(predictive_score(model, cameras, generator, render_fn=render_fn, num_samples=num_samples,
                                    subset_size=subset_size, variant=variant, extent=extent,
                                    temperature=temperature, position=out["position"]))
    return {k: v for k, v in out.items() if k in names or k == "contribution"}
