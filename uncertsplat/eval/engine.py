"""The evaluation engine: K posterior samples of each view -> uncertainty maps -> every metric.

``evaluate_views(sampler, views, cfg, device)`` renders K Monte-Carlo samples of each view
(``uncertainty.mc.mc_render``), scores the mean and std against the views' images (and GT depth when
there is some) and returns an ``EvalReport``. ``fit_std_scale`` fits the one factor for the predicted
std on training views. Used by ``evaluate`` (which writes the maps and ``metrics.json``), ``prune``
(held-out metrics before and after) and ``sweep`` (one record per point).

Pure in the sense of the package's layering: it takes a ``Sampler`` (how to draw and render samples
of a run: ``baselines.LoadedRun.sampler`` builds it for every method), the views as tensors
(``types.ViewSet``: ``data.dataset.load_view_set`` loads them) and the settings (``EvalSettings``:
``config.EvalConfig`` has them), and it reads and writes no file; ``on_view`` hands each view's maps
to the caller. The prediction is the Monte-Carlo mean (as in the paper); the per-pixel uncertainty is
the unbiased std over the K samples.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import torch
from torch import Tensor

from uncertsplat.console import progress
from uncertsplat.errors import UserError
from uncertsplat.render.exposure import PhotoExposure
from uncertsplat.schemas.metrics import EvalReport
from uncertsplat.types import Cameras, GaussianSample, RenderOutput, ViewSet
from uncertsplat.uncertainty.consistency import STEP_VARIANCE, ViewConsistency
from uncertsplat.uncertainty.residual import C0, ResidualField

STD_TERMS = "std² = "
"""How the note that lists the predictive's terms begins: they are variances and add as such (the std is the root of
their sum), the first the K samples' own."""

KDE_MAX_SAMPLES = 64
"""The KDE NLL keeps every sample of a view in memory; above this K it is skipped (and noted)."""


class EvalSettings(Protocol):
    """What the engine reads of an evaluation config (``config.EvalConfig`` has all of it)."""

    split: str
    """The split the views come from (recorded; the std factor is fitted only when scoring "test")."""
    num_samples: int
    seed: int
    std_floor: float
    ause_steps: int
    paper_nll: bool
    depth_scale: str | float
    """"auto", or a factor from rendered depth to GT depth units."""
    depth_gt: Path | None
    """The GT depth folder given (None: the scene's own); named in errors about it."""
    depth_align: str
    max_views: int | None
    """Evaluate only the first n views of the split (None: all)."""
    calibration_views: int
    resolution_on_training_views: bool
    """Keep the resolution term in the predictive the std factor is fitted on when that is fitted on training views
    (``fit_std_scale``)."""
    degrees_of_freedom: str | float
    """"fit" (nu of the RGB predictive's Student-t fitted with the std factor, ``fit_std_scale``), "gaussian", or nu."""
    empty_rays: bool
    """Add the sampler's ``empty_std`` where rays meet no Gaussian (False: the samples' spread only)."""
    residual_views: int
    """Training views to fit the pixel noise of the model's Gaussians on (``fit_residual``; 0: none)."""
    resolution: float
    """The resolution term's shift, in fractions of each Gaussian's size (``uncertainty.mc.resolution_shift``)."""
    resolution_renders: int
    """Renders of the resolution term per posterior sample (``uncertainty.mc.mc_render``'s ``shift_renders``)."""
    residual_scale: str | float
    """"fit" (``fit_noise_scale``) or a factor for the pixel noise."""
    residual_leverage: str
    """``none``, ``relative`` (each Gaussian's noise by (1 - its leverage) / (1 - the median's) where above 1) or
    ``full`` (by 1 - its leverage) (``ResidualField.out_of_sample``)."""
    colour_posterior: bool
    """Add each Gaussian's colour posterior variance to its noise (``ResidualField.colour_variance``)."""
    colour_covariance: str
    """The colour posterior's form: "block" (the DC term and band 1 jointly) or "diagonal"."""
    consistency_views: int
    """Training views the view-consistency term compares each evaluated view with (``view_consistency``; 0: none)."""
    depth_spread: bool
    """Add the variance of the depths each ray blends (``uncertainty.mc.depth_spread``) to the depth variance."""
    hidden_depth: bool
    """Add the depth variance of the surface points no compared training view sees
    (``ViewConsistency.hidden_depth_variance``; part of the view-consistency term, so none when ``consistency_views``
    is 0)."""
    edge_noise: bool
    """Split the pixel noise into an edge term ``delta^2 |grad I|^2`` and the per-Gaussian rest
    (``uncertainty.residual.fit_edge_scale``; ``fit_residual_field`` fits it in its own pass)."""
    finer_detail: bool
    """Add the finer-detail term where a view resolves the surface finer than the training views that see it
    (``uncertainty.consistency``; part of the view-consistency term, so none when ``consistency_views`` is 0)."""


@dataclass(frozen=True)
class Sampler:
    """How to draw and render posterior samples of one run.

    Attributes:
        sample_fn: ``sample_fn(generator) -> GaussianSample``, one posterior sample per call (a baseline's
            own sampler for ensemble / Fisher runs).
        render_fn: ``render_fn(sample, cameras) -> RenderOutput`` with the run's background, tile size and
            near plane.
        det_sample: the one deterministic sample ``train`` reports (the expected render), scored as
            ``psnr_render``; None for methods without one.
        empty_std: (colour, depth) std of the unknown surface behind a ray that meets no Gaussian
            (``uncertainty.mc.mc_render``); None when the background is part of the data.
        residual: the pixel noise of the model's Gaussians (``fit_residual``), added to the RGB variance;
            None: the samples' spread only.
        coverage: the opacity the model reaches on its training views' surfaces (``uncertainty.mc.
            training_coverage``): rays covered less than this count as partly empty (``mc_render``).
        mean_sample: a deterministic model that stands for the run in the predictive's side terms (pixel noise,
            resolution term) when it has no ``det_sample`` (an ensemble's first member, a Fisher run's mean).
        consistency: the view-consistency term (``view_consistency``), added to the RGB variance; None: none.
        exposure: the training photos' learned exposures (``TrainConfig.exposure``): the training photos the pixel
            noise is fitted on are brought to the model's exposure, and the spread of the exposures is added to the
            RGB variance (a new photo's exposure is not known; the std factor is fitted on photos as they are, each
            at its own exposure like a new one); None: photos taken as they are.
    """

    sample_fn: Callable[[torch.Generator], GaussianSample]
    render_fn: Callable[[GaussianSample, Cameras], RenderOutput]
    det_sample: GaussianSample | None = None
    empty_std: tuple[float, float] | None = None
    residual: ResidualField | None = None
    coverage: float = 1.0
    mean_sample: GaussianSample | None = None
    consistency: ViewConsistency | None = None
    exposure: PhotoExposure | None = None


@dataclass(frozen=True)
class ViewMaps:
    """One evaluated view's maps, as ``on_view`` receives them (CPU tensors).

    Attributes:
        name: the image name.
        gt: [H,W,3] the image.
        rgb_mean: [H,W,3] the Monte-Carlo mean clamped to [0, 1] (the prediction that is scored).
        rgb_std: [H,W,3] the unbiased std over the K samples.
        depth_mean, depth_std: [H,W,1] in the run's world units.
        alpha_mean: [H,W,1] mean accumulated opacity (None when not given).
        dof: the degrees of freedom of the RGB predictive's Student-t (``evaluate_views``' ``dof``; None: the
            Gaussian).
        rgb_terms: {part: [H,W,1]} what each part of the predictive adds to the RGB variance (``UncertaintyMaps.
            rgb_terms``; None when not given).
    """

    name: str
    gt: Tensor
    rgb_mean: Tensor
    rgb_std: Tensor
    depth_mean: Tensor
    depth_std: Tensor
    alpha_mean: Tensor | None = None
    dof: float | None = None
    rgb_terms: dict[str, Tensor] | None = None


@dataclass
class _ViewResult:
    name: str
    metrics: dict
    curves: dict
    calibration: object
    # kept only when there is GT depth, until the split's depth factor is known (then scored and dropped): each
    # held-out pixel costs 9 bytes here, not the maps' 12 (alpha is needed only as the mask it gives)
    depth_mean: Tensor | None = None  # [H,W,1] on CPU
    depth_std: Tensor | None = None  # [H,W,1]
    depth_valid: Tensor | None = None  # [H,W,1] bool: alpha > 0.5, inside the view's mask


def _shift_fn(sampler: Sampler, cfg: EvalSettings, device: torch.device):
    """The resolution term's sampler (``uncertainty.mc.resolution_shift``) of the run's representative model, or
    None when ``cfg.resolution`` is 0."""
    from uncertsplat.uncertainty.mc import resolution_shift

    if cfg.resolution <= 0:
        return None
    return resolution_shift(_representative(sampler, device), cfg.resolution)


def predictive_terms(sampler: Sampler, cfg: EvalSettings, cams: Cameras, *, depth: bool = True) -> dict:
    """The terms ``mc_render`` adds to the samples' spread for ``cams``, as the settings allow (``depth=False``: none
    of the depth-only ones, for a caller that reads the RGB maps alone): ``mc_render(..., **predictive_terms(...))``
    is ``evaluate``'s predictive (``uncertsplat.predict`` for any camera). The side terms come as named maps
    (``mc.sum_terms`` adds them up; ``mc_render``'s ``terms`` keeps each)."""
    from uncertsplat.uncertainty.mc import depth_spread

    extra, hidden = _side_variance(sampler, cams, hidden_depth=depth and cfg.hidden_depth)
    depth_parts: dict[str, Tensor] = {}
    if cfg.depth_spread and depth:
        depth_parts["depth spread"] = depth_spread(_representative(sampler, cams.device), cams, sampler.render_fn)
    if hidden is not None:
        depth_parts["hidden surface"] = hidden
    return {"empty_std": sampler.empty_std if cfg.empty_rays else None, "coverage": sampler.coverage,
            "extra_var": extra or None, "extra_depth_var": depth_parts or None,
            "shift_fn": _shift_fn(sampler, cfg, cams.device), "shift_renders": cfg.resolution_renders}


def _side_variance(sampler: Sampler, cams: Cameras, *, hidden_depth: bool = False
                   ) -> tuple[dict[str, Tensor], Tensor | None]:
    """The RGB variance maps [C,H,W,1] of the sampler's side terms, by name in the order ``mc_render`` adds them
    (empty without any): the pixel noise's parts (``ResidualField.blended_parts``), "view consistency" and
    "exposure"; and with ``hidden_depth`` the depth variance of the view-consistency term's hidden points
    (``ViewConsistency.hidden_depth_variance``, from the same render and lookup; None without the term or
    ``hidden_depth``)."""
    extra = dict(sampler.residual.blended_parts(cams, sampler.render_fn)) if sampler.residual is not None else {}
    hidden = None
    if sampler.consistency is not None:
        parts = [sampler.consistency.variances(cams[[j]], sampler.render_fn, hidden_depth=hidden_depth)
                 for j in range(len(cams))]
        extra["view consistency"] = torch.cat([p[0] for p in parts])
        if hidden_depth:
            hidden = torch.cat([p[1] for p in parts])
    if sampler.exposure is not None:
        rep = _representative(sampler, cams.device)
        with torch.no_grad():
            extra["exposure"] = torch.cat([sampler.exposure.variance(sampler.render_fn(rep, cams[[j]]).rgb)
                                           for j in range(len(cams))])
    return extra, hidden


def evenly_spaced(items: Sequence[int], n: int) -> list[int]:
    """At most ``n`` of ``items``, evenly spaced with both ends included (all of them when n >= len(items))."""
    items = list(items)
    n = min(n, len(items))
    return [items[round(j * (len(items) - 1) / max(n - 1, 1))] for j in range(n)]


def view_consistency(sampler: Sampler, train_cameras: Cameras, cfg: EvalSettings,
                     device: torch.device, edge_scale: float = 0.0) -> ViewConsistency | None:
    """The view-consistency term (``uncertainty.consistency``) of the sampler's representative model against its
    training cameras, comparing at most ``cfg.consistency_views`` of them (evenly spaced); None when that is 0 or there
    is no training camera. Renders each compared training view once. With ``cfg.finer_detail``, the term also carries
    the finer-detail term, with the pixel noise's ``edge_scale`` (delta^2, 0 without an edge term)."""
    if cfg.consistency_views <= 0 or len(train_cameras) == 0:
        return None
    chosen = evenly_spaced(range(len(train_cameras)), cfg.consistency_views)
    finer = edge_scale + STEP_VARIANCE if cfg.finer_detail else 0.0
    return ViewConsistency.of(_representative(sampler, device), train_cameras[chosen].to(device), sampler.render_fn,
                              frustum_cameras=train_cameras.to(device), finer_detail=finer,
                              unseen_empty=sampler.empty_std is None and cfg.empty_rays)


def with_side_terms(sampler: Sampler, residual: ResidualField | None, train_cameras: Cameras, cfg: EvalSettings,
                    device: torch.device) -> Sampler:
    """``sampler`` with the pixel noise ``residual`` (``fit_residual``) and the view-consistency term of its
    ``train_cameras`` (``view_consistency``) attached: what every evaluation of a run scores."""
    edge = residual.edge_scale if residual is not None else 0.0
    return dataclasses.replace(sampler, residual=residual,
                               consistency=view_consistency(sampler, train_cameras, cfg, device, edge_scale=edge))


def scored_sampler(new_sampler: Callable[[], Sampler], residual: ResidualField | None, cameras: Cameras,
                   split: Mapping[str, Sequence[int]], cfg: EvalSettings, device: torch.device, *,
                   load_views: Callable[[list[int]], ViewSet] | None,
                   set_aside_maps: dict[int, tuple[Tensor, Tensor]] | None = None,
                   known_fit: StdFit | None = None) -> tuple[Sampler, StdFit]:
    """The sampler an evaluation of a run scores (``with_side_terms``: the pixel noise ``residual`` and the
    view-consistency term of the ``split``'s training ``cameras``), with the std factor and the tails
    ``fit_std_scale`` fits for it. ``new_sampler()`` gives a fresh sampler of the run; the fit is made with one and
    the returned sampler is another (a baseline's sampler may keep state between calls), both with the same side
    terms, built once. ``set_aside_maps``: ``fit_residual``'s, when it fitted the noise in this process
    (``fit_std_scale``). ``known_fit``: the fit an earlier evaluation of the same model and settings made
    (``stages.predictive_cache``), returned as it is: nothing is fitted and ``load_views`` is not called."""
    fitting = with_side_terms(new_sampler(), residual, cameras[list(split.get("train", ()))], cfg, device)
    fit = known_fit if known_fit is not None else fit_std_scale(fitting, split, cfg, device, load_views=load_views,
                                                                set_aside_maps=set_aside_maps)
    return dataclasses.replace(new_sampler(), residual=residual, consistency=fitting.consistency), fit


def residual_indices(train_indices: Sequence[int], cfg: EvalSettings) -> list[int]:
    """The at most ``cfg.residual_views`` evenly spaced training views the pixel noise is fitted on."""
    return evenly_spaced(train_indices, cfg.residual_views)


@torch.no_grad()
def _representative(sampler: Sampler, device: torch.device) -> GaussianSample:
    """The deterministic model the side terms use: the expected render, else ``mean_sample``, else one sample."""
    if sampler.det_sample is not None:
        return sampler.det_sample
    if sampler.mean_sample is not None:
        return sampler.mean_sample
    return sampler.sample_fn(torch.Generator(device=device).manual_seed(0))


def fit_residual(sampler: Sampler, train_indices: Sequence[int], cfg: EvalSettings, device: torch.device, *,
                 load_views: Callable[[list[int]], ViewSet],
                 calibration_indices: Sequence[int] = (),
                 set_aside_maps: dict[int, tuple[Tensor, Tensor]] | None = None) -> ResidualField | None:
    """The pixel noise of the sampler's Gaussians (``uncertainty.residual.fit_residual_field``), fitted on
    ``residual_indices`` of the training views against the run's deterministic render (a sample when the
    method has none); None when ``cfg.residual_views`` is 0 or there is no training view. Give it a sampler of
    its own (a baseline's sampler may keep state) and attach the field to the evaluation's sampler with
    ``dataclasses.replace(sampler, residual=field)``.

    With ``cfg.residual_scale`` "fit" or "auto" and ``calibration_indices`` (views set aside from training,
    ``SceneConfig.calibration_holdout``), the noise's level is fitted on those views, after the leverage: views the
    model never trained on show the noise a new view sees, so nothing is corrected for what training absorbed.
    ``set_aside_maps``: a dict that receives those views' predictive without the noise (``_rest_of_predictive``),
    for ``fit_std_scale`` to add the noise to instead of rendering the K samples again."""
    from uncertsplat.uncertainty.residual import fit_residual_field

    chosen = residual_indices(train_indices, cfg)
    if not chosen:
        return None
    views = load_views(chosen)
    if sampler.exposure is not None:
        views = sampler.exposure.unexposed(views)
    masks = views.masks.to(device) if views.masks is not None else None
    explained = None
    shift = _shift_fn(sampler, cfg, device)
    if shift is not None:
        cache: dict[tuple[bytes, bytes], Tensor] = {}

        def explained(cam: Cameras) -> Tensor:
            # the resolution term's variance on the training view; rendered once per view (the noise scale reuses it)
            from uncertsplat.uncertainty.mc import RunningMoments

            key = (cam.cam_from_world.cpu().numpy().tobytes(), cam.K.cpu().numpy().tobytes())
            if key not in cache:
                gen = torch.Generator(device=device).manual_seed(cfg.seed)
                moments = RunningMoments()
                for _ in range(RESIDUAL_SHIFTS):
                    moments.update(sampler.render_fn(shift(gen), cam).rgb)
                cache[key] = moments.var.mean(-1, keepdim=True)
            return cache[key]

    rep = _representative(sampler, device)
    cams, images = views.cameras.to(device), views.images.to(device)
    with torch.enable_grad():
        field = fit_residual_field(rep, cams, images, sampler.render_fn, masks=masks, explained=explained,
                                   colour_posterior=cfg.colour_posterior, view_factor=len(train_indices) / len(chosen),
                                   edge_scale="fit" if cfg.edge_noise else 0.0,
                                   colour_covariance=cfg.colour_covariance)
    mode = noise_scale_mode(cfg, calibration_indices)
    on_set_aside = mode == "fit" and len(calibration_indices) > 0
    if mode != "fit":
        field = field.scaled(float(mode))
    elif not on_set_aside:
        field = field.scaled(fit_noise_scale(field, rep, cams, images, sampler.render_fn, masks=masks,
                                             explained=explained, std_floor=cfg.std_floor))
    if cfg.residual_leverage != "none":
        # a scale fitted to training residuals (or set) is the noise of the training pixels; the leverage gives the
        # noise behind them
        k = 11 + 3 * (rep.sh_degree + 1) ** 2
        field = field.out_of_sample(k, view_factor=len(train_indices) / len(chosen),
                                    relative=cfg.residual_leverage == "relative")
    if on_set_aside:
        cal = load_views(list(calibration_indices))
        cal_masks = cal.masks.to(device) if cal.masks is not None else None
        field = field.scaled(fit_noise_scale(field, rep, cal.cameras.to(device), cal.images.to(device),
                                             sampler.render_fn, masks=cal_masks,
                                             explained=_rest_of_predictive(sampler, cfg, cal.cameras.to(device),
                                                                           cal.indices, device, set_aside_maps),
                                             std_floor=cfg.std_floor))
    return field


def _rest_of_predictive(sampler: Sampler, cfg: EvalSettings, cameras: Cameras, indices: Sequence[int],
                        device: torch.device,
                        keep: dict[int, tuple[Tensor, Tensor]] | None = None) -> Callable[[Cameras], Tensor]:
    """``explained(camera) -> [1,H,W,1]`` for ``fit_noise_scale`` on views set aside from training: the RGB
    variance of the predictive ``evaluate`` scores there without the pixel noise (the K samples' spread, the
    resolution term, the empty-ray term; the view-consistency term is 0 this close to the training views) of
    ``cameras`` (scene ``indices``), each with its evaluation seed, so the noise's level is the one at which
    the whole predictive's z-scores have unit variance there (``fit_noise_scale``), given everything else that
    will be added to it. With the resolution term alone in its place the demo's std came out 20-25 % too wide
    (BENCHMARKS.md, "Why the demo's raw calibration error stays above 0.05"). ``keep``: receives each view's
    (rgb_mean, rgb_std) [1,H,W,3] (on the CPU) by scene index."""
    from uncertsplat.uncertainty.mc import mc_render

    def explained(cam: Cameras) -> Tensor:
        match = (cameras.cam_from_world == cam.cam_from_world[0]).flatten(1).all(1).nonzero()[:, 0].tolist()
        j = match[0] if match else 0
        gen = torch.Generator(device=device).manual_seed(view_seed(cfg.seed, indices[j]))
        bare = dataclasses.replace(sampler, residual=None, consistency=None)
        maps, _ = mc_render(sampler.sample_fn, sampler.render_fn, cam, cfg.num_samples, gen,
                            **predictive_terms(bare, cfg, cam, depth=False))
        if keep is not None:
            keep[indices[j]] = (maps.rgb_mean.cpu(), maps.rgb_std.cpu())
        return maps.rgb_std.square().mean(-1, keepdim=True)

    return explained


def noise_scale_mode(cfg: EvalSettings, calibration_indices: Sequence[int] = ()) -> str | float:
    """``cfg.residual_scale`` resolved: "fit" or a factor ("auto": "fit" when views were set aside, else 1)."""
    if cfg.residual_scale == "auto":
        return "fit" if len(calibration_indices) > 0 else 1.0
    return cfg.residual_scale


RESIDUAL_SETTINGS = ("residual_views", "resolution", "residual_scale", "residual_leverage", "colour_posterior",
                     "colour_covariance", "edge_noise", "seed", "std_floor")
"""The settings ``fit_residual`` reads: a fitted field can stand for another evaluation of the same model whose
settings agree on these (``stages.residual_cache``)..."""
RESIDUAL_SET_ASIDE_SETTINGS = ("num_samples", "empty_rays", "resolution_renders")
"""... and on these too when it fits the noise's level on views set aside from training (``_rest_of_predictive``)."""
RESIDUAL_FIT = 2
"""How ``fit_residual`` fits (part of a cached field's key): 2 since the noise's level on views set aside is fitted
given the whole rest of the predictive (1: given the resolution term alone)."""


def residual_from_state(sampler: Sampler, state: dict, device: torch.device) -> ResidualField:
    """The field ``ResidualField.state()`` of an earlier ``fit_residual`` of the same model gave, attached to this
    sampler's representative model (the Gaussians ``fit_residual`` fits on).

    Raises:
        ValueError: the state does not fit the model.
    """
    return ResidualField.from_state(_representative(sampler, device), state)


MIN_NOISE_ALPHA = 0.5
"""Pixels whose accumulated opacity is below this do not enter the noise scale's fit (``fit_noise_scale``)."""
NOISE_SCALE_VIEWS = 16
"""Training views (of the residual views, evenly spaced) the pixel noise's scale is fitted on (``fit_noise_scale``)."""


@torch.no_grad()
def fit_noise_scale(field: ResidualField, sample: GaussianSample, cameras: Cameras, images: Tensor,
                    render_fn: Callable[[GaussianSample, Cameras], RenderOutput], *, masks: Tensor | None = None,
                    explained: Callable[[Cameras], Tensor] | None = None, std_floor: float = 1e-3) -> float:
    """The scale ``a`` of the pixel noise at which the Gaussian predictive's z-scores have unit variance,
    given the rest of the predictive, on training views (or the views set aside: ``fit_residual``).

    Solves ``mean_p r(p)^2 / (e(p) + a n(p)) = 1`` over the valid pixels with alpha >= ``MIN_NOISE_ALPHA`` of
    at most ``NOISE_SCALE_VIEWS`` of ``cameras``, where r^2 is the squared residual of ``sample``'s render
    (mean over the channels), ``n`` the field's blended noise and ``e`` what ``explained`` gives (the
    resolution term; 0 without it): the scale at which the Gaussian predictive's z-scores have unit variance
    there. This is the maximum-likelihood scale only where ``e`` is 0 (then a = mean r^2 / n); with ``e`` > 0
    the likelihood's stationary point is the root of ``sum_p n(p) (r(p)^2 - v(p)) / v(p)^2 = 0``, v = e + a n,
    which weights the pixels the noise dominates more: a moment (unit z-variance) estimate, not the
    maximum-likelihood one (the two agree when the predictive's form is right; on heavy-tailed residuals they
    differ by a few per cent). The per-Gaussian noise is a local mean of r^2, and r^2 is heavy-tailed (most
    pixels fit closely, a few edges do not), so the unscaled noise makes most pixels' std too large (the demo
    scene: a factor of 0.63 fitted on the whole std). Monotone in ``a``: bisection in log space over [1e-4,
    1e4] (an end when the root lies beyond it).
    """
    r2s, es, ns = [], [], []
    for j in evenly_spaced(range(len(cameras)), NOISE_SCALE_VIEWS):
        cam = cameras[[j]]
        out = render_fn(sample, cam)
        pred = out.rgb[0].clamp(0, 1)
        r2 = (pred - images[j].to(pred)).square().mean(-1, keepdim=True)  # [H,W,1]
        n = field.blended(cam, render_fn)[0]
        e = explained(cam)[0].to(r2) if explained is not None else torch.zeros_like(r2)
        # only the pixels the Gaussians make (alpha >= 0.5): where they cover little, the noise cannot reach the
        # residual at any scale (the empty-ray term speaks there) and would drive the scale to its bound
        valid = out.alpha[0] >= MIN_NOISE_ALPHA
        if masks is not None:
            valid = valid & masks[j].bool()
        r2s.append(r2[valid].double().cpu())
        es.append(e.expand_as(r2)[valid].double().cpu())
        ns.append(n[valid].double().cpu())
    r2, e, n = torch.cat(r2s), torch.cat(es), torch.cat(ns)
    if r2.numel() == 0:
        return 1.0

    def excess(log_a: float) -> float:
        var = (e + math.exp(log_a) * n).clamp_min(std_floor**2)
        return float((r2 / var).mean()) - 1.0

    lo, hi = math.log(1e-4), math.log(1e4)
    if excess(lo) <= 0.0:
        return math.exp(lo)
    if excess(hi) >= 0.0:
        return math.exp(hi)
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if excess(mid) > 0.0:
            lo = mid
        else:
            hi = mid
    return math.exp(0.5 * (lo + hi))


RESIDUAL_SHIFTS = 4
"""Renders of the resolution term per training view when the pixel noise is fitted (``fit_residual``)."""


def view_seed(seed: int, index: int) -> int:
    """The generator seed of the view at ``index`` in the scene's camera list for an evaluation seeded ``seed``:
    per view, so that the same seed gives a view the same maps whatever else is evaluated (``uncertsplat.predict``
    seeds a scene's views the same way)."""
    return seed * 1_000_003 + index


FEW_DEPTH_PIXELS = 0.05
"""Below this fraction of the pixels with a GT depth, the evaluation notes that its depth metrics rest on few pixels
(a helper's model pruned to 5 Gaussians scored a depth NLL of 20,826 on 2 pixels a view, without a word)."""


def pose_index(cam_from_world: Tensor, K: Tensor) -> int:
    """A view index (0 to 2**40) from a camera's pose [4,4] and intrinsics [3,3], for ``view_seed``: a view that is
    not one of the scene's (``uncertsplat.predict``'s poses of one's own, ``select-views``' candidates) gets the same
    generator seed wherever it stands in a batch. From the float32 values, entries below 1e-7 taken as 0: the same
    pose written two ways (float64 or float32 world-to-camera, a float64 world_from_cam, an entry 0 or -0.0 or 1e-17)
    gets the same seed, where its float64 bytes gave two. Not every way: a float32 world_from_cam inverted lands a
    float32 rounding away from the matrix it was made from (6e-8), and gets another seed (other Monte Carlo noise,
    the same predictive: 0.2 % of the mean std at K = 10 on the tiny scene)."""
    import hashlib

    key = torch.cat([cam_from_world.flatten(), K.flatten()]).float().cpu()
    # an entry that is 0 one way is 1e-17 or -0.0 another (a rotation about one axis inverted, or negated): all one
    key = torch.where(key.abs() < 1e-7, torch.zeros_like(key), key).numpy()
    return int.from_bytes(hashlib.sha256(key.tobytes()).digest()[:5], "little")


def split_indices(split: Mapping[str, Sequence[int]], cfg: EvalSettings) -> list[int]:
    """The views to evaluate: those of ``split[cfg.split]`` (a scene's split), the first ``cfg.max_views`` of them.

    Raises:
        UserError: the split holds no view.
    """
    indices = list(split.get(cfg.split, ()))
    if cfg.max_views is not None:
        indices = indices[: cfg.max_views]
    if not indices:
        raise UserError("no view to evaluate in this split", hint="Use --split train, or a scene with held-out views.")
    return indices


def calibration_indices(split: Mapping[str, Sequence[int]], cfg: EvalSettings) -> list[int]:
    """The views the std factor is fitted on: at most ``cfg.calibration_views`` of the scene's ``"calibration"``
    views (set aside from training, ``SceneConfig.calibration_holdout``) when it has some, else of its training
    views, evenly spaced with both ends included; none when disabled or when scoring the training split (never fit
    on the views that are scored)."""
    if cfg.split != "test":
        return []
    return evenly_spaced(split.get("calibration") or split.get("train", ()), cfg.calibration_views)


@dataclass(frozen=True)
class StdFit:
    """What the views ``calibration_indices`` chooses say about the RGB predictive (``fit_std_scale``).

    Attributes:
        scale: one factor for the std (None: not fitted).
        dof: the Student-t's degrees of freedom (``eval.tails``; None: the Gaussian).
        names: the image names the two were fitted on.
    """

    scale: float | None = None
    dof: float | None = None
    names: list[str] = dataclasses.field(default_factory=list)


def _without_resolution(cfg: EvalSettings) -> EvalSettings:
    """``cfg`` with the resolution term off (a copy)."""
    if hasattr(cfg, "model_copy"):
        return cfg.model_copy(update={"resolution": 0.0})
    out = copy.copy(cfg)
    out.resolution = 0.0
    return out


def _fixed_dof(cfg: EvalSettings) -> float | None:
    """``cfg.degrees_of_freedom`` when it is a number; None for "gaussian" and "fit"."""
    return float(cfg.degrees_of_freedom) if not isinstance(cfg.degrees_of_freedom, str) else None


@torch.no_grad()
def fit_std_scale(sampler: Sampler, split: Mapping[str, Sequence[int]], cfg: EvalSettings, device: torch.device, *,
                  load_views: Callable[[list[int]], ViewSet],
                  set_aside_maps: Mapping[int, tuple[Tensor, Tensor]] | None = None) -> StdFit:
    """One factor for the predicted std and the predictive's tails, fitted on the views ``calibration_indices``
    chooses from ``split``.

    The factor is the maximum-likelihood scale of a Gaussian predictive with std s x max(std, std_floor), s^2
    = mean((error / max(std, std_floor))^2) over every valid pixel and channel of those views (K samples each,
    as in evaluation): the one that makes the variance right. The calibrated metrics (``nll_calibrated``,
    ``calibration_error_calibrated``) score std x s floored after scaling, max(s x std, std_floor): the same
    predictive wherever std >= std_floor and s x std >= std_floor, not the one this s is the maximum of where
    many stds lie below the floor (a Monte-Carlo std of exactly 0 without the pixel-noise term: the floored
    pixels' errors then raise s, which widens every other pixel). With ``cfg.degrees_of_freedom`` "fit", the
    Student-t's nu is then fitted by maximum likelihood to the same z-scores divided by s
    (``eval.tails.fit_dof``): the shape, whatever the level. Training views fit better than held-out ones, so
    a factor fitted on them errs low; views set aside from training (``split["calibration"]``) do not have
    that bias. On training views the predictive is fitted without the resolution term unless
    ``cfg.resolution_on_training_views``: the term stands for what the training images cannot show (Gaussians
    trading places unseen in them), and on those images it exceeded the residuals the model left
    (BENCHMARKS.md, "The std factor on training views without the resolution term"); and unless the pixel
    noise's level was fitted on those views given the term (``cfg.residual_scale`` "fit", with a noise field).

    Args:
        sampler: the run's sampler (build a fresh one: a baseline's sampler may keep state between calls).
        split: the scene's split (``SceneData.split``).
        load_views: ``load_views(indices) -> ViewSet`` (images and masks; depth is not needed).
        set_aside_maps: (rgb_mean, rgb_std) [1,H,W,3] by scene index of the predictive without the pixel noise and
            the view-consistency term, the same K samples with the same seed (``fit_residual`` renders them to fit
            the noise's level on views set aside): for those views only the two terms are added (their variances
            add) instead of rendering the samples again.

    Returns:
        ``StdFit``: no factor (and nu only when ``cfg.degrees_of_freedom`` sets it) when disabled, when scoring the
        training split, when there is no view to fit on or no valid pixel.
    """
    from uncertsplat.eval.tails import FIT_ELEMENTS, fit_dof
    from uncertsplat.uncertainty.mc import RGB_STD_MAX, mc_render, sum_terms

    chosen = calibration_indices(split, cfg)
    if not chosen:
        return StdFit(dof=_fixed_dof(cfg))
    on_training = not split.get("calibration")  # (calibration_indices: the views set aside when there are some)
    # a noise level fitted on the training views (residual_scale "fit" without views set aside) was fitted with the
    # resolution term in the predictive: the factor is fitted on that same predictive (without it, the demo's came
    # out x1.7 and made the calibrated NLL 0.13 nats worse than the raw; BENCHMARKS.md, "The std factor where the
    # noise's level was fitted on training views")
    fitted_noise = noise_scale_mode(cfg) == "fit" and sampler.residual is not None
    with_resolution = cfg.resolution_on_training_views or fitted_noise
    fit_cfg = _without_resolution(cfg) if on_training and not with_resolution else cfg
    views = load_views(chosen)  # as they are: a photo at its own exposure, what the exposures' spread predicts
    gen = torch.Generator(device=device)
    # the factor from every z-score; nu from at most FIT_ELEMENTS of them, strided per view, so that large photos
    # do not keep every z-score of every view in memory
    total, count = 0.0, 0
    zs: list[Tensor] = []
    for j, i in enumerate(views.indices):
        cam = views.cameras[[j]].to(device)
        if set_aside_maps is not None and i in set_aside_maps:
            mean, bare_std = set_aside_maps[i]
            extra = _side_variance(dataclasses.replace(sampler, exposure=None), cam)[0]  # bare_std has the exposures' term
            # capped as mc_render caps the whole std (bare_std was capped alone: where it was, the sum is above the cap)
            std = (bare_std.square() + sum_terms(extra).cpu().to(bare_std)).sqrt().clamp_max(RGB_STD_MAX) \
                if extra else bare_std
        else:
            gen.manual_seed(view_seed(cfg.seed, i))
            maps, _ = mc_render(sampler.sample_fn, sampler.render_fn, cam, cfg.num_samples, gen,
                                **predictive_terms(sampler, fit_cfg, cam, depth=False))
            mean, std = maps.rgb_mean.cpu(), maps.rgb_std.cpu()
        err = mean[0].clamp(0, 1) - views.images[j]
        z = err / std[0].clamp_min(cfg.std_floor)  # [H,W,3]
        z = (z[views.masks[j][..., 0]] if views.masks is not None else z).reshape(-1)
        total += float(z.double().square().sum())
        count += z.numel()
        zs.append(z[:: -(-z.numel() * len(chosen) // FIT_ELEMENTS) or 1])
    if count == 0:
        return StdFit(dof=_fixed_dof(cfg))
    scale = (total / count) ** 0.5
    dof = fit_dof(torch.cat(zs) / scale) if cfg.degrees_of_freedom == "fit" and scale > 0.0 else _fixed_dof(cfg)
    return StdFit(scale, dof, views.names)


SAME_RENDER = "every sample is the same render"
"""How the notes on a model without a posterior (``LoadedRun.eval_notes``: deterministic, one ensemble member, no
carrier) say that the samples' spread is 0; ``evaluate_views``' 'std² =' note and the report read it."""

GIVEN_SCENE_GT = "given-scene"
"""``DepthScaleInfo.method`` of a factor given with ``--depth-scale`` against the scene's own GT depth (in the run's
normalised units, as with method "scene"); "given" is one against a ``--depth-gt`` folder (the folder's units)."""

ZERO_STD_NOTE = "every pixel's RGB std is 0"
"""How ``evaluate_views``' note begins when no pixel has a std (``stages.evaluate`` prints it)."""
NOT_A_NUMBER_NOTE = "the RGB std is not a number (NaN or inf)"
"""How ``evaluate_views``' note begins when some pixel's std is NaN or inf (``stages.evaluate`` prints it)."""
IMPLAUSIBLE_DEPTH_NOTE = "the GT maps are probably in other units"
"""What ``implausible_depth_scale_notes``' note says (``stages.evaluate`` prints the notes that say it: a warning
about every depth number, which only metrics.json and the report held)."""
IMPLAUSIBLE_DEPTH_RATIO = 2.0
"""A given depth factor (a number, or the scene's own units) that leaves the GT this many times the scaled render, or
less than 1/this, at the median, is noted as probably wrong (``implausible_depth_scale_notes``)."""


def implausible_depth_scale_notes(depth: Tensor | Sequence[Tensor], gt: Tensor | Sequence[Tensor],
                                  mask: Tensor | Sequence[Tensor], scale: float, given,
                                  to_source: float | None = None, scene_gt: bool = False) -> list[str]:
    """A note when the depth factor given (``given``: a number, or the scene's known units) leaves the GT depth
    ``IMPLAUSIBLE_DEPTH_RATIO`` times the scaled render (or less than its inverse) at the median: GT maps in other
    units than the factor assumes (``--depth-scale 1`` on maps in the scene's units gave abs-rel 0.76 without a
    word). The metrics stay those of the factor given. ``depth``, ``gt``, ``mask``: stacked [C,H,W,1] or one map a
    view (``align_depth_scale``, which scales the depth slice by slice: no scaled copy of every map). ``to_source``:
    the scene's units per run unit; when the right factor lies within 15 % of a power of ten of them (maps in
    millimetres of a metric scene: the scene's factor x 1000), the note gives it (a user tried 1000 and got another
    warning: the factor is from the run's units, not the scene's). ``scene_gt``: the GT is the scene's own (no
    ``--depth-gt``), already in the run's units: the factor it needs is 1, which the note says (it advised ``auto``,
    which does nothing there)."""
    from uncertsplat.eval.depth import align_depth_scale

    try:
        ratio = align_depth_scale(depth, gt, mask=mask, method="median", pred_scale=scale).scale
    except ValueError:  # no valid pixel: the depth metrics say so
        return []
    if 1 / IMPLAUSIBLE_DEPTH_RATIO <= ratio <= IMPLAUSIBLE_DEPTH_RATIO:
        return []
    what = f"the depth factor given ({given:g})" if isinstance(given, float) else "the scene's own depth units"
    hint = ("(the scene's own GT depth is in the run's units already: leave --depth-scale out, or give 1; a number is "
            "for maps of one's own, --depth-gt)" if scene_gt else
            "(--depth-scale auto fits the factor; scene takes maps in the scene's own units)")
    if to_source:
        # the factor from the run's depth to the maps' units this median asks for, as a power of ten of the scene's
        right = ratio * (given if isinstance(given, float) else to_source)
        power = math.log10(right / to_source)
        if abs(power - round(power)) < math.log10(1.15):
            tens = 10.0 ** round(power)
            hint = ("(maps in the scene's own units: --depth-scale scene" if round(power) == 0 else
                    f"(maps in the scene's units x {tens:g}, e.g. millimetres of a scene in metres for 1000: "
                    f"--depth-scale {to_source * tens:.6g}, the run's depth to the maps' units") +                 "; --depth-scale auto fits the factor instead)"
    return [f"with {what}, the GT depth is {ratio:.3g}x the render's at the median: {IMPLAUSIBLE_DEPTH_NOTE} "
            f"{hint}; the depth metrics are those of the factor given"]


MASKED_NOTE_BELOW = 0.995
"""``evaluate_views`` notes that its metrics are taken inside the scene's validity masks when these cover less of
the pixels than this (a mask of every pixel changes nothing)."""
MASKED_NOTE = "the scene has validity masks"
"""How that note begins (``stages.evaluate`` looks for it to say so beside the PSNR it prints)."""
PHOTO_MASKS_NOTE = "the masks are the photos' own"
"""What that note says when the masks are the photos' own (``ViewSet.masks_trained``: train's PSNR is inside them)."""
TRANSIENT_MASKS_NOTE = "the masks leave out the transient regions training found in these views"
"""What it says when they leave out the transient regions training found (``ViewSet.transients_out``)."""


def masks_note(views: ViewSet, inside: float) -> str | None:
    """``evaluate_views``' note on the masks its metrics are taken inside (``inside``: the share of the views' pixels
    they keep), None where they keep at least ``MASKED_NOTE_BELOW``: which masks they are, and whether train's
    held-out PSNR is taken inside them too."""
    if inside >= MASKED_NOTE_BELOW:  # train's held-out PSNR is over whole images: the two differ on such scenes
        return None
    if views.masks_trained:
        return (f"{MASKED_NOTE}: PSNR, AUSE, NLL, calibration and Spearman are taken inside them "
                f"({inside:.0%} of the pixels of these views; SSIM too, with both images black outside "
                "them), as train's held-out PSNR and SSIM; "
                + (f"{TRANSIENT_MASKS_NOTE}" + (" and the photos' own masks" if views.own_masks_too else "")
                   + ", which training left out too" if views.transients_out else
                   f"{PHOTO_MASKS_NOTE}, whose black pixels training left out too"))
    return (f"{MASKED_NOTE}: PSNR, AUSE, NLL, calibration and Spearman are taken inside them "
            f"({inside:.0%} of the pixels of these views; SSIM over whole images), train's held-out "
            "PSNR over whole images; the masks are a synthetic scene's, the objects of transparent "
            "photos (alpha >= 0.5: the background they are composited over left out), or the photos' "
            "own added after training"
            + ("; the transient regions training found in these views are left out too"
               if views.transients_out else ""))


def evaluate_views(sampler: Sampler, views: ViewSet, cfg: EvalSettings, device: torch.device, *,
                   on_view: Callable[[ViewMaps], None] | None = None, show_progress: bool = True,
                   std_scale: float | None = None, calibration_views: list[str] | None = None,
                   calibration_held_out: bool = False, dof: float | None = None,
                   noise_scale: float | None = None, depth_to_source: float | None = None,
                   notes: Sequence[str] = (), config_hash: str = "") -> EvalReport:
    """Render K posterior samples of each view and compute every metric.

    Args:
        sampler: how to draw and render samples of the run (``baselines.LoadedRun.sampler``).
        views: the views with their images, masks and GT depth (``data.dataset.load_view_set``). The GT
            depth is used as it is when ``views.depth_known_scale``, else one scale for the whole set is
            estimated (``cfg.depth_align``) unless ``cfg.depth_scale`` gives it.
        cfg: the evaluation settings (K, seed, std floor, AUSE steps, depth alignment, ...).
        device: where to render.
        on_view: called with each view's maps as soon as they are computed (e.g. to write them).
        show_progress: show a progress bar.
        std_scale: a factor for the RGB std (``fit_std_scale``): adds ``nll_calibrated`` and
            ``calibration_error_calibrated`` (the maps and the other metrics keep the raw std).
        calibration_views: the image names ``std_scale`` (and a fitted ``dof``) was fitted on (recorded in the report).
        dof: the degrees of freedom of the RGB predictive's Student-t (``StdFit.dof``; None: the Gaussian): the NLL
            and the calibration use it, raw and calibrated; ``nll_gaussian`` and ``calibration_error_gaussian`` give
            the Gaussian reading of the same std beside it.
        calibration_held_out: whether the scene set views aside from training, on which the std factor and a fitted
            noise level were then fitted (recorded).
        noise_scale: the factor the sampler's pixel noise carries (``ResidualField.scale``; recorded).
        depth_to_source: the scene's units per run unit (``SceneData.depth_scale_to_gt``), when known: a note on a
            given depth factor that looks wrong then names the factor of maps in a power of ten of those units.
        notes: notes about the run to record (``LoadedRun.eval_notes``); the engine adds its own.
        config_hash: the hash of the full evaluation config (recorded in the report).

    Returns:
        ``schemas.metrics.EvalReport`` (not written to disk).

    Raises:
        UserError: no view to evaluate, or GT depth that cannot be aligned with the rendered depth.
    """
    from uncertsplat.eval.calibration import calibration, mean_calibration, spearman
    from uncertsplat.eval.depth import align_depth_scale, depth_metrics, valid_depth_mask
    from uncertsplat.eval.image import lpips, lpips_available, masked_ssim, psnr, ssim
    from uncertsplat.eval.nll import gaussian_nll, kde_nll, paper_nll, predictive_nll
    from uncertsplat.eval.sparsification import mean_curves, sparsification_all
    from uncertsplat.provenance import versions
    from uncertsplat.schemas.metrics import (
        CalibrationTable,
        CurveSet,
        DepthScaleInfo,
        LpipsStatus,
        SparsificationCurve,
        ViewMetrics,
    )
    from uncertsplat.uncertainty.mc import mc_render

    if len(views) == 0:
        raise UserError("no view to evaluate in this split",
                        hint="Use --split train, or a scene with held-out views.")
    if views.masks is not None and not bool(views.masks.any()):  # (the curves' mean had no view: a traceback)
        raise UserError(f"the validity masks of the {len(views)} evaluated view(s) mark no pixel valid, so there is "
                        "nothing to score", hint="A mask marks the pixels to score white (non-zero): check the "
                                                 "scene's masks (all black, or inverted?).")
    sample_fn, render_fn, det_sample = sampler.sample_fn, sampler.render_fn, sampler.det_sample
    images, masks, gt_depth = views.images, views.masks, views.depths
    lp_ok, lp_reason = lpips_available()
    K = cfg.num_samples
    notes = list(notes)
    same = any(SAME_RENDER in n for n in notes)  # a model without a posterior (the run's note says so)
    # a KDE of one render (K = 1, or a model whose samples are all one) measures its bandwidth floor, not the model:
    # a helper's report showed NLL (KDE) 2,700-3,000 for such runs beside -2.5 for the others
    keep = K <= KDE_MAX_SAMPLES and K > 1 and not same
    std_max = 0.0  # the largest RGB std of any pixel (0: the NLL and calibration measure only the floor)
    not_numbers = 0  # RGB std values that are NaN or inf (a NaN read as 0 above: "every pixel's std is 0")
    if K > KDE_MAX_SAMPLES:
        notes.append(f"KDE NLL skipped: K={K} > {KDE_MAX_SAMPLES} would keep every sample in memory")
    elif K == 1 or same:
        notes.append("KDE NLL" + (" and the paper's NLL" if cfg.paper_nll else "") + " not computed: the samples are "
                     "one render (a kernel density of one value measures its bandwidth, not the model)")
    # the resolution term's renders (K x resolution_renders of them) still spread at K = 1 unless there is one
    one_shift = cfg.resolution > 0 and K * cfg.resolution_renders == 1
    if K == 1:
        notes.append("K=1: the samples' spread " + ("and the resolution term are 0 everywhere (one sample, one render "
                                                    "of the resolution term: no spread)" if one_shift else
                                                    "is 0 everywhere (one sample has no spread)")
                     + "; the std holds the predictive's other terms")
    masked = masks_note(views, float(masks.float().mean()) if masks is not None else 1.0)
    notes += [masked] if masked else []
    # a model without a posterior: its spread term is 0 too
    terms = ["the variance of the K samples" + (" (0: K = 1)" if K == 1 else
                                              f" (0 for this model: {SAME_RENDER})" if same else "")]
    if sampler.residual is not None:
        seen = float(sampler.residual.seen.float().mean()) if sampler.residual.seen.numel() else 0.0
        lev = sampler.residual.leverage_inflation
        lev = "" if lev is None else (
            f"; raised by the leverage ({cfg.residual_leverage}) by a factor {lev:.3g} on average"
            + (" (1 for every Gaussian observed at least as well as the median one)"
               if cfg.residual_leverage == "relative" else ""))
        terms.append(f"the pixel noise of the Gaussians on the training views (RMS residual "
                     f"{sampler.residual.mean_variance ** 0.5:.4f}; {100 * seen:.1f} % of the Gaussians seen{lev})")
        if sampler.residual.edge_scale > 0.0:
            terms.append(f"the edge term (a misplacement of {sampler.residual.edge_scale ** 0.5:.2f} px fitted on the "
                         "training views, times the image gradient of the view's render)")
        unknown = sampler.residual.colour_unknown_fraction()
        if unknown is not None:
            prior = float(sampler.residual.colour_prior[0]) ** 0.5 * C0
            terms.append(f"the colour the training views leave unknown (each Gaussian's colour posterior; prior std "
                         f"{prior:.3f}; {100 * unknown:.1f} % of the Gaussians' colour set mostly by the prior)")
    if cfg.resolution > 0:
        terms.append(f"the resolution term (every Gaussian moved by N(0, ({cfg.resolution:g} x its size)^2), "
                     f"{cfg.resolution_renders} render{'s' if cfg.resolution_renders > 1 else ''} per sample"
                     + ("; 0 with K = 1)" if one_shift else ")"))
    if sampler.consistency is not None:
        faint = ""  # the rays through space no photo saw empty, on transparent photos
        if sampler.consistency.unseen_empty:
            faint = "; transparent photos: a ray that meets little of the model through space no photo saw empty gets " \
                    "(1 - alpha)^2 of it"
            if cfg.hidden_depth:
                faint += (", and below alpha 0.5 the depth variance of a surface anywhere between the model's nearest "
                          "and farthest Gaussians, (1 - alpha)^2 (hi - lo)^2 / 12")
        terms.append(f"the squared difference between the model's renders of each surface point from the view and from "
                     f"the training view nearest in direction that saw it, where that is more than "
                     f"{sampler.consistency.gate:.1f} degrees away ({len(sampler.consistency.cameras)} training views "
                     f"compared; a point outside every training image gets the variance of the scene's colours in "
                     f"their renders, {sampler.consistency.palette_var:.4f}, and one they hold but none sees gets it "
                     f"weighted by its angle to the nearest of them{faint})")
        if sampler.consistency.finer_detail > 0.0:
            terms.append("where the view resolves a surface point finer than the training views that see it (r times: "
                         "nearer or zoomed in), (r^2 - 1) x the finer-detail coefficient x the squared gradient of the "
                         "view's render")
    if cfg.depth_spread:
        terms.append("for depth, the variance of the depths each ray blends (the model's deterministic render)")
    if cfg.hidden_depth and sampler.consistency is not None:
        terms.append("for depth, where no compared training view sees a surface point, L^2 / 12 with L the stretch "
                     "of the view's ray in front of it that no training view saw empty"
                     + (" and, the photos being transparent, the stretch behind it up to where a photo saw empty"
                        if sampler.consistency.unseen_empty else ""))
    if sampler.exposure is not None:
        terms.append(f"the spread of the {len(sampler.exposure.indices)} training photos' learned exposures at the "
                     "rendered colour (a new photo's exposure is not known)")
    if cfg.empty_rays and sampler.empty_std is not None:
        terms.append(f"an unknown surface where rays are covered less than the model covers its training views "
                     f"(alpha {sampler.coverage:.3f}; colour std {sampler.empty_std[0]:.3f}, depth "
                     f"std {sampler.empty_std[1]:.3g} in the run's normalised units)")
    notes.append(STD_TERMS + " + ".join(terms))

    results: list[_ViewResult] = []
    term_sums: dict[str, dict[str, float]] = {"rgb": {}, "depth": {}}  # per part, its mean over each view, summed
    kept: tuple[Tensor, Tensor, Tensor] | None = None  # the depth maps the depth metrics wait for (with GT depth)
    gen = torch.Generator(device=device)
    prog = progress() if show_progress else None
    task = prog.add_task("evaluate", total=len(views), info="") if prog else None
    if prog:
        prog.start()
    try:
        for j, i in enumerate(views.indices):
            name = views.cameras.image_names[j]
            cams = views.cameras[[j]].to(device)
            gen.manual_seed(view_seed(cfg.seed, i))
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            t0 = time.perf_counter()
            maps, samples = mc_render(sample_fn, render_fn, cams, K, gen, keep_samples=keep, terms=True,
                                      **predictive_terms(sampler, cfg, cams))
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            seconds = time.perf_counter() - t0
            pred = maps.rgb_mean[0].cpu().clamp(0, 1)
            std = maps.rgb_std[0].cpu()
            finite = torch.isfinite(std)
            not_numbers += int(std.numel() - finite.sum())
            std_max = max(std_max, float(std[finite].max())) if bool(finite.any()) else std_max
            gt = images[j]
            mask = masks[j] if masks is not None else None
            err = pred - gt
            sp = sparsification_all(err, std, mask=mask, steps=cfg.ause_steps)
            cal = calibration(err, std, mask=mask, dof=dof)
            sm = spearman(std, err.abs(), mask=mask)
            m = dict(
                # inside the photos' own masks (which training left out); a synthetic scene's masks leave SSIM
                # over whole images
                psnr=float(psnr(pred, gt, mask)),
                ssim=(masked_ssim(pred, gt, mask) if views.masks_trained and mask is not None
                      else float(ssim(pred, gt))),
                ause_mae=sp["mae"].ause, ause_mse=sp["mse"].ause, ause_rmse=sp["rmse"].ause,
                nll=float(predictive_nll(gt, pred, std, dof, std_floor=cfg.std_floor, mask=mask)),
                calibration_error=cal.calibration_error, spearman=sm.value, spearman_note=sm.reason,
                seconds=seconds,
            )
            if dof is not None:
                m.update(nll_gaussian=float(gaussian_nll(gt, pred, std, std_floor=cfg.std_floor, mask=mask)),
                         calibration_error_gaussian=calibration(err, std, mask=mask).calibration_error)
            if std_scale is not None:
                m.update(nll_calibrated=float(predictive_nll(gt, pred, std * std_scale, dof, std_floor=cfg.std_floor,
                                                             mask=mask)),
                         calibration_error_calibrated=calibration(err, std * std_scale, mask=mask,
                                                                  dof=dof).calibration_error)
            if lp_ok:
                m["lpips"] = float(lpips(pred, gt))
            if det_sample is not None:
                with torch.no_grad():
                    det = render_fn(det_sample, cams).rgb[0].cpu().clamp(0, 1)
                m["psnr_render"] = float(psnr(det, gt, mask))
            if samples is not None:
                s_rgb = samples.rgb[:, 0].cpu()
                m["nll_kde"] = float(kde_nll(s_rgb, gt, mask=mask))
                if cfg.paper_nll:
                    m["nll_paper"] = float(paper_nll(s_rgb, gt, mask=mask))
            curves = {k: SparsificationCurve.from_result(v) for k, v in sp.items()}
            r = _ViewResult(name, m, {"rgb": sp, "rgb_curves": curves}, cal)
            d_mean, d_std, a_mean = (t[0].cpu() for t in (maps.depth_mean, maps.depth_std, maps.alpha_mean))
            if gt_depth is not None:  # the depth metrics wait for the split's one factor (after the loop)
                if kept is None:
                    # one block per map for all views: kept one tensor a view amid the renders' transient buffers,
                    # they pinned the allocator's heap (RSS grew by several times their own size)
                    kept = (d_mean.new_empty((len(views), *d_mean.shape)), d_std.new_empty((len(views), *d_std.shape)),
                            torch.empty((len(views), *a_mean.shape), dtype=torch.bool))  # [C,H,W,1] each
                r.depth_mean, r.depth_std, r.depth_valid = kept[0][j], kept[1][j], kept[2][j]
                r.depth_mean.copy_(d_mean)
                r.depth_std.copy_(d_std)
                torch.gt(a_mean, 0.5, out=r.depth_valid)
                if masks is not None:
                    r.depth_valid &= masks[j]
            results.append(r)
            # each part's map of this view on the CPU once: for the shares and for on_view
            rgb_terms, depth_terms = ({k: t[0].cpu() for k, t in parts.items()} if parts is not None else None
                                      for parts in (maps.rgb_terms, maps.depth_terms))
            scored = mask if mask is not None else torch.ones_like(a_mean, dtype=torch.bool)
            _add_term_means(term_sums["rgb"], rgb_terms, scored)
            _add_term_means(term_sums["depth"], depth_terms, scored & (a_mean > 0.5))
            del maps, depth_terms
            if on_view is not None:
                on_view(ViewMaps(name, gt, pred, std, d_mean, d_std, a_mean, dof, rgb_terms))
            del rgb_terms
            if prog:
                prog.update(task, advance=1, info=f"{name}: PSNR {m['psnr']:.2f} AUSE {m['ause_mae']:.3f} "
                                                  f"{seconds:.2f}s")
    finally:
        if prog:
            prog.stop()

    # ---- depth: one scale for the whole split (estimated over all views' valid pixels, or known)
    depth_info = None
    depth_cal = []
    depth_sp_all = []
    if gt_depth is not None:
        # one map a view, never stacked (a stack copied every held-out pixel); align_depth_scale streams over them
        dm = [r.depth_mean for r in results]  # C x [H,W,1]
        gts = list(gt_depth.unbind(0))  # C x [H,W,1], views of the set's tensor
        base_mask = [r.depth_valid for r in results]  # C x [H,W,1] bool
        given = isinstance(cfg.depth_scale, float)
        from uncertsplat.conventions import NO_SURFACE_DEPTH

        def none() -> bool:  # (read only where it decides: a pass over every GT map)
            return not any(bool((g > 0).any()) for g in gts)

        no_depth = (f"the GT maps hold no usable depth at all: values of 0 or below, not finite, or of "
                    f"{NO_SURFACE_DEPTH:g} and above are read as no surface (Blender writes 1e10 there)")
        no_depth_hint = ("Depth maps stored in units that make every depth that large (nanometres) must be stored in "
                         "larger ones.")
        if cfg.depth_gt is not None and (given or views.depth_known_scale) and none():
            # (with a factor given, no metric came out and nothing said why: the aligned case refuses the same maps)
            raise UserError(f"no depth metric can be computed: {no_depth}", path=cfg.depth_gt, hint=no_depth_hint)
        if given or views.depth_known_scale:  # a factor the user gave, or the scene's own GT's (1)
            scale = align_depth_scale(dm, gts, mask=base_mask, method=cfg.depth_scale if given else 1.0)
            # against GT in the run's normalised units (the scene's own) or a --depth-gt folder's
            method = (GIVEN_SCENE_GT if views.depth_known_scale else "given") if given else "scene"
            scale = type(scale)(scale.scale, method, scale.num_pixels)
            # (the power of ten of the scene's units is a hint for maps of one's own: the scene's own GT needs 1)
            notes += implausible_depth_scale_notes(dm, gts, base_mask, scale.scale, cfg.depth_scale,
                                                   depth_to_source if cfg.depth_gt is not None else None,
                                                   scene_gt=views.depth_known_scale and cfg.depth_gt is None)
        else:
            try:
                scale = align_depth_scale(dm, gts, mask=base_mask, method=cfg.depth_align)
            except ValueError as err:
                empty = none()
                raise UserError(f"cannot align depth with the GT: {err}" + (f"; {no_depth}" if empty else ""),
                                path=cfg.depth_gt, hint=no_depth_hint if empty else None) from None
        depth_info = DepthScaleInfo(scale=scale.scale, method=scale.method, num_pixels=scale.num_pixels)
        del dm, base_mask, kept
        scored_px = with_gt_px = 0  # the depth metrics' pixels, against those with a GT depth
        for j, r in enumerate(results):
            valid = valid_depth_mask(r.depth_mean, gt_depth[j], r.depth_valid)
            d_err = r.depth_mean * scale.scale - gt_depth[j]
            d_std = r.depth_std * scale.scale
            dsp = sparsification_all(d_err, d_std, mask=valid, steps=cfg.ause_steps)
            dmet = depth_metrics(r.depth_mean, gt_depth[j], scale=scale.scale, mask=valid)
            scored_px += int(dmet.num_pixels)
            # (inside the view's validity mask, where the metrics are scored at all)
            has_gt = gt_depth[j] > 0
            with_gt_px += int((has_gt & masks[j] if masks is not None else has_gt).sum())
            dcal = calibration(d_err, d_std, mask=valid)
            r.metrics.update(
                depth_ause_mae=dsp["mae"].ause if dsp["mae"].num_elements else None,
                depth_ause_rmse=dsp["rmse"].ause if dsp["rmse"].num_elements else None,
                depth_abs_rel=dmet.abs_rel, depth_rmse=dmet.rmse, depth_mae=dmet.mae,
                # the floor in the run's normalised units, carried into the GT's like the depths: taken in the GT's own
                # units it depended on them (maps written in km or mm moved the NLL by 1.3 nats beyond ln f)
                depth_nll=float(gaussian_nll(gt_depth[j], r.depth_mean * scale.scale, d_std,
                                             std_floor=cfg.std_floor * scale.scale, mask=valid))
                if dmet.num_pixels else None,
                depth_spearman=spearman(d_std, d_err.abs(), mask=valid).value,
            )
            r.curves["depth"] = dsp
            r.depth_mean = r.depth_std = r.depth_valid = None  # scored: the report needs only the numbers
            depth_sp_all.append(dsp)
            if dcal.num_elements:
                depth_cal.append(dcal)
        if with_gt_px and scored_px == 0:
            notes.append(f"no depth metric could be computed: none of the {with_gt_px:,} pixels with a GT depth is "
                         "covered by the model (alpha >= 0.5) with a rendered depth")
        elif with_gt_px and scored_px < FEW_DEPTH_PIXELS * with_gt_px:
            notes.append(f"the depth metrics rest on {scored_px:,} pixel(s), {100.0 * scored_px / with_gt_px:.2g} % of "
                         f"the {with_gt_px:,} with a GT depth (scored where the model covers a pixel, alpha >= 0.5, "
                         "and renders a depth): they say little about the model's depth (a model pruned to a few "
                         "Gaussians, or one that did not fit)")

    if not_numbers:
        notes.append(f"{NOT_A_NUMBER_NOTE} in {not_numbers:,} values of the views' maps: a model or setting beyond "
                     "what float32 holds; the metrics of those pixels are not to be trusted")
    if std_max == 0.0 and not not_numbers:
        notes.append(f"{ZERO_STD_NOTE} (one sample and every side term off?): the NLL and calibration measure the "
                     f"std floor ({cfg.std_floor:g}), not the model, and a std factor changes nothing")
    per_view = {r.name: ViewMetrics(**r.metrics) for r in results}
    curves = {}
    for r in results:
        cs = CurveSet(rgb={k: v for k, v in r.curves["rgb_curves"].items() if v is not None})
        if "depth" in r.curves:
            cs.depth = {k: c for k, v in r.curves["depth"].items() if (c := SparsificationCurve.from_result(v))}
        curves[r.name] = cs
    mean_set = CurveSet()
    for metric in ("mae", "mse", "rmse"):
        mean_set.rgb[metric] = SparsificationCurve.from_result(mean_curves([r.curves["rgb"][metric] for r in results]))
        ok = [d[metric] for d in depth_sp_all if d[metric].num_elements > 0]
        if ok:
            mean_set.depth[metric] = SparsificationCurve.from_result(mean_curves(ok))
    curves["mean"] = mean_set
    cal_tables = {"rgb": CalibrationTable.from_result(mean_calibration([r.calibration for r in results]))}
    if depth_cal:
        cal_tables["depth"] = CalibrationTable.from_result(mean_calibration(depth_cal))
    seconds = [r.metrics["seconds"] for r in results]
    return EvalReport(
        split=cfg.split,
        image_names=[r.name for r in results],
        per_view=per_view,
        mean=ViewMetrics.mean_of(list(per_view.values())),
        curves=curves,
        calibration=cal_tables,
        config_hash=config_hash,
        versions=versions(),
        num_samples=K,
        seed=cfg.seed,
        seconds_per_view=sum(seconds) / len(seconds),
        ause_steps=cfg.ause_steps,
        std_floor=cfg.std_floor,
        depth_scale=depth_info,
        std_scale=std_scale,
        degrees_of_freedom=dof,
        calibration_views=calibration_views or [], calibration_held_out=calibration_held_out,
        noise_scale=noise_scale,
        edge_scale=sampler.residual.edge_scale if sampler.residual is not None else None,
        lpips=LpipsStatus(available=lp_ok, reason=lp_reason),
        device=str(device),
        variance_shares={k: shares for k, v in term_sums.items() if (shares := _shares(v))},
        notes=notes,
    )


def _add_term_means(sums: dict[str, float], terms: Mapping[str, Tensor] | None, scored: Tensor) -> None:
    """Adds each part's mean over one view's ``scored`` pixels ([H,W,1] bool) to ``sums`` (parts [H,W,1] on the CPU;
    a view without a scored pixel adds nothing)."""
    if terms is None or not bool(scored.any()):
        return
    for name, t in terms.items():
        value = float(t[scored].double().mean())
        sums[name] = sums.get(name, 0.0) + (value if math.isfinite(value) else 0.0)


def _shares(sums: Mapping[str, float]) -> dict[str, float]:
    """Each part's share of the summed variance (empty when there is none to share)."""
    total = sum(sums.values())
    return {k: v / total for k, v in sums.items()} if total > 0.0 else {}


__all__ = ["KDE_MAX_SAMPLES", "STD_TERMS", "EvalSettings", "Sampler", "StdFit", "ViewMaps", "calibration_indices",
           "evaluate_views", "fit_std_scale", "split_indices"]
