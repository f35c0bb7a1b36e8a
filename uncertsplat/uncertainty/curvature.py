"""The data's curvature: the diagonal Fisher information of a Gaussian pixel likelihood, by Rademacher probes.

Likelihood: every training pixel channel is Gaussian around the render, ``gt ~ N(rgb(theta), s^2)``. Its
Fisher information w.r.t. per-Gaussian parameters theta is ``F = J^T J / s^2`` (J: the Jacobian of the
rendered pixels); ``fisher_diagonal`` estimates its diagonal, summed over the training views. It says how
strongly the training views pin each parameter down: 0 for a Gaussian no training view sees. Used by the
Fisher baseline (``baselines.fisher``, a Laplace posterior around a trained deterministic model) and by the
variational model's data-informed posterior (``gaussians.variational.informed_tables``).

Takes the renderer as a function, so it imports neither ``render`` nor a model class.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from uncertsplat.types import Cameras, GaussianSample, RenderOutput


def activate(params: dict[str, Tensor], sh_degree: int, delta: dict[str, Tensor] | None = None) -> GaussianSample:
    """A render-ready sample from stored parameters (log-scales, logits) plus optional offsets ``delta``."""
    delta = delta or {}

    def get(name):
        v = params[name]
        return v + delta[name] if name in delta else v

    sh = torch.cat([get("sh0"), params["shN"]], dim=1)
    return GaussianSample(means=get("means"), quats=params["quats"], scales=torch.exp(get("scales")),
                          opacities=torch.sigmoid(get("opacities")), sh=sh, sh_degree=sh_degree)


def _masked_residual(rgb: Tensor, image: Tensor, mask: Tensor | None) -> tuple[Tensor, int]:
    """``rgb - image`` [H,W,3] with 0 outside ``mask`` [H,W,1] bool (None: every pixel counts), and how many
    pixel channels count."""
    r = rgb - image.to(rgb.device)
    if mask is None:
        return r, r.numel()
    m = mask.to(r)
    return r * m, int(m.sum()) * r.shape[-1]


def residual_noise_std(params: dict[str, Tensor], cameras: Cameras, images: Tensor, render_fn, *, sh_degree: int,
                       floor: float = 1.0 / 255.0, masks: Tensor | None = None) -> float:
    """RMS of ``render - image`` over every training pixel channel (at least ``floor``).

    Args:
        params: stored per-Gaussian parameters (``GaussianModel.params``).
        cameras: T training cameras; images: [T,H,W,3]; masks: [T,H,W,1] bool, the pixels that count (None: all).
    """
    total, count = 0.0, 0
    with torch.no_grad():
        g = activate(params, sh_degree)
        for i in range(len(cameras)):
            r, n = _masked_residual(render_fn(g, cameras[[i]]).rgb[0], images[i], None if masks is None else masks[i])
            total += float(r.square().sum())
            count += n
    return max(math.sqrt(total / max(count, 1)), floor)


def fisher_diagonal(params: dict[str, Tensor], cameras: Cameras, images: Tensor,
                    render_fn: Callable[[GaussianSample, Cameras], RenderOutput], *, names: tuple[str, ...],
                    noise_std: float, generator: torch.Generator, sh_degree: int, estimator: str = "ggn",
                    probes: int = 2, masks: Tensor | None = None) -> dict[str, Tensor]:
    """Diagonal Fisher information of the Gaussian pixel likelihood, summed over the training views.

    Args:
        params: stored per-Gaussian parameters (tensors [N,...]; not modified, no ``.grad`` written).
        cameras: T training cameras; images: [T,H,W,3] in [0, 1].
        render_fn: ``render_fn(sample, cameras) -> RenderOutput`` (differentiable).
        names: the parameters to estimate it for (keys of ``params``).
        noise_std: observation noise std s.
        generator: source of the Rademacher probes (``ggn``).
        sh_degree: SH degree to render with.
        estimator: ``"ggn"`` or ``"empirical"`` (``baselines.fisher``'s module docstring).
        probes: probe vectors per view (``ggn``).
        masks: [T,H,W,1] bool, the pixels that count (the photos' masks), or None for all.

    Returns:
        name -> [N,...] non-negative tensor shaped like ``params[name]``.
    """
    if estimator not in ("ggn", "empirical"):
        raise ValueError(f"unknown estimator {estimator!r}")
    if estimator == "ggn":
        return curvature(params, cameras, images, render_fn, names=names, generator=generator, sh_degree=sh_degree,
                         probes=probes, noise_std=noise_std, masks=masks).fisher
    leaves = {n: params[n].detach().clone().requires_grad_(True) for n in names}
    fixed = {k: v.detach() for k, v in params.items()}
    acc = {n: torch.zeros_like(v) for n, v in leaves.items()}
    inv_var = 1.0 / noise_std**2
    for i in range(len(cameras)):
        sample = activate({**fixed, **leaves}, sh_degree)
        rgb = render_fn(sample, cameras[[i]]).rgb[0]  # [H,W,3]
        r, _ = _masked_residual(rgb, images[i], None if masks is None else masks[i])
        grads = torch.autograd.grad(r.square().sum() * (0.5 * inv_var), list(leaves.values()), allow_unused=True)
        for n, gr in zip(leaves, grads, strict=True):
            if gr is not None:
                acc[n] += gr.square()
    return acc


@dataclass(frozen=True)
class Curvature:
    """What one pass over the training views says about the parameters (``curvature``)."""

    fisher: dict[str, Tensor]
    """name -> diagonal Fisher information [N,...] of the Gaussian pixel likelihood with noise ``noise_std``."""
    noise_std: float
    """The likelihood's noise: the given one, or the RMS training residual (at least ``floor``)."""
    disagreement: dict[str, Tensor] | None
    """name -> [N,...] how much the views disagree (see ``curvature``), or None when not asked for."""


def curvature(params: dict[str, Tensor], cameras: Cameras, images: Tensor,
              render_fn: Callable[[GaussianSample, Cameras], RenderOutput], *, names: tuple[str, ...],
              generator: torch.Generator, sh_degree: int, probes: int = 2, noise_std: float | None = None,
              disagreement: bool = False, floor: float = 1.0 / 255.0, masks: Tensor | None = None,
              on_view: Callable[[int, int], None] | None = None) -> Curvature:
    """The diagonal Fisher (``fisher_diagonal``'s ``ggn`` estimator, the same probes), the likelihood's noise and,
    optionally, how much the training views disagree, from one render per view.

    With ``noise_std`` None the noise is the RMS residual of these renders (``residual_noise_std``); every term
    is accumulated without it and scaled at the end (the Fisher by 1 / s^2), so the residual pass and the
    curvature pass are one. ``masks`` [T,H,W,1] bool: the pixels that count (the photos' masks; None: all), the
    others in neither the noise nor the curvature. ``on_view(done, views)``: called as each view is done (a progress
    line: the last update of a large capture takes minutes).

    The disagreement is the variance over the T views of each view's score (the gradient of its Gaussian
    log-likelihood), times T: ``D = T/(T-1) sum_v (g_v - mean g)^2``. For a correctly specified model (pixels
    independent, noise s) its expectation is the Fisher itself; where the views pull a parameter different ways
    (residuals correlated across a Gaussian's footprint, a view-dependent look the model cannot fit) it is
    larger. ``D / (F + prior precision)^2`` is the sandwich (infinitesimal jackknife) variance: how much the
    parameter would move if the set of views were drawn again.
    """
    leaves = {n: params[n].detach().clone().requires_grad_(True) for n in names}
    fixed = {k: v.detach() for k, v in params.items()}
    fisher = {n: torch.zeros_like(v) for n, v in leaves.items()}
    s1 = {n: torch.zeros_like(v, dtype=torch.float64) for n, v in leaves.items()} if disagreement else {}
    s2 = {n: torch.zeros_like(v, dtype=torch.float64) for n, v in leaves.items()} if disagreement else {}
    sq_sum, count = 0.0, 0
    t = len(cameras)
    for i in range(t):
        sample = activate({**fixed, **leaves}, sh_degree)
        rgb = render_fn(sample, cameras[[i]]).rgb[0]  # [H,W,3]
        m = masks[i] if masks is not None else None  # [H,W,1]
        r, n = _masked_residual(rgb.detach(), images[i], m)
        sq_sum += float(r.square().sum())
        count += n
        for p in range(probes):
            z = torch.randint(0, 2, rgb.shape, generator=generator, device=generator.device).to(rgb) * 2 - 1
            if m is not None:
                z = z * m.to(z)
            grads = torch.autograd.grad((rgb * z).sum(), list(leaves.values()), retain_graph=disagreement or p < probes - 1,
                                        allow_unused=True)
            for n, gr in zip(leaves, grads, strict=True):
                if gr is not None:
                    fisher[n] += gr.square() / probes
        if disagreement:  # the score without the 1 / s^2 (applied below)
            grads = torch.autograd.grad((rgb * r).sum(), list(leaves.values()), allow_unused=True)
            for n, gr in zip(leaves, grads, strict=True):
                if gr is not None:
                    g = gr.double()
                    s1[n] += g
                    s2[n] += g.square()
        if on_view is not None:
            on_view(i + 1, t)
    if noise_std is None:
        noise_std = max(math.sqrt(sq_sum / max(count, 1)), floor)
    inv_var = 1.0 / noise_std**2
    fisher = {n: v * inv_var for n, v in fisher.items()}
    dis = None
    if disagreement:
        scale = t / max(t - 1, 1) * inv_var**2
        dis = {n: ((s2[n] - s1[n].square() / t) * scale).clamp_min(0.0).to(fisher[n].dtype) for n in leaves}
    return Curvature(fisher, float(noise_std), dis)
