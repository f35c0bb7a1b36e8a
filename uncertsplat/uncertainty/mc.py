"""Monte-Carlo uncertainty rendering: K posterior samples -> per-pixel mean and std, streamed.

Each of the K samples is drawn (``sample_fn(generator)``), rendered (``render_fn(sample, cameras)``),
folded into running moments (Welford's algorithm) and released before the next one, so memory is that
of one render plus the running moments (``MonteCarloMoments``: colour, depth, alpha, the empty part of each ray
and the shifted renders'), whatever K. The std is the unbiased sample std (divisor K - 1);
with K = 1 it is 0 everywhere. Welford's update leaves an exactly constant element with a variance of
exactly 0 (every delta is 0), which keeps "no uncertainty" areas exactly tied for AUSE.

This module takes the sampler and renderer as functions, so it imports neither ``gaussians`` nor
``render`` (and tests can pass tiny stand-ins).

Depth: the rendered depth is alpha-normalised and 0 where a sample hits nothing, so pixels at the
silhouette mix 0 and surface depths and get a large depth std. That is a real property of the
posterior (the surface may or may not be there); ``alpha_mean`` lets callers mask such pixels.

Empty rays: where a ray is covered less than the model covers the surfaces its training views saw
(``coverage``, from ``training_coverage``), the uncovered part shows something the model has no Gaussian
for; ``mc_render``'s ``empty_std`` adds that unknown value's variance (see there).

Resolution: ``mc_render``'s ``shift_fn`` pairs each sample with ``shift_renders`` renders of the model whose Gaussians
are moved by a fraction of their own size (``resolution_shift``); the variance of those renders is added too.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from uncertsplat.types import Cameras, GaussianSample, RenderOutput, UncertaintyMaps


class RunningMoments:
    """Welford running mean and unbiased variance of same-shaped tensors.

    ``update(x)`` folds one sample in; ``mean``, ``var`` and ``std`` read the state. Accumulates in the
    dtype of the first sample (float32 renders; Welford is stable there) on its device.
    """

    def __init__(self) -> None:
        self.count = 0
        self._mean: Tensor | None = None
        self._m2: Tensor | None = None

    def update(self, x: Tensor) -> None:
        x = x.detach()
        self.count += 1
        if self._mean is None:
            self._mean = x.clone()
            self._m2 = torch.zeros_like(x)
            return
        delta = x - self._mean
        self._mean.add_(delta / self.count)
        self._m2.add_(delta * (x - self._mean))

    @property
    def mean(self) -> Tensor:
        if self._mean is None:
            raise ValueError("RunningMoments has no samples yet")
        return self._mean

    @property
    def var(self) -> Tensor:
        """Unbiased variance (divisor count - 1); zeros for a single sample."""
        if self._m2 is None:
            raise ValueError("RunningMoments has no samples yet")
        if self.count < 2:
            return torch.zeros_like(self._m2)
        # Rounding can leave M2 a hair below 0 for near-constant elements.
        return self._m2.clamp_min(0) / (self.count - 1)

    @property
    def std(self) -> Tensor:
        return self.var.sqrt()


SHIFT_SEED = 0x5EED5  # mixes the shifts' seed with the samples' seed


class MonteCarloMoments:
    """Running moments of the renders of posterior samples: what ``mc_render`` accumulates, exposed so that a
    caller can add samples a few at a time and read the maps in between (the viewer refines a still frame
    this way).

    ``update(out)`` folds one ``RenderOutput`` in; ``maps(...)`` reads the mean and std maps with the same
    empty-ray and extra-variance terms as ``mc_render``. ``coverage`` (in (0, 1]) is the opacity below which a
    ray counts as partly empty (``mc_render``); it is needed while the samples are folded in.
    """

    def __init__(self, coverage: float = 1.0) -> None:
        if not (0.0 < coverage <= 1.0) or math.isnan(coverage):
            raise ValueError(f"coverage must be in (0, 1], got {coverage}")
        self.coverage = float(coverage)
        self.rgb, self.depth, self.alpha = RunningMoments(), RunningMoments(), RunningMoments()
        self.gap = RunningMoments()  # (1 - alpha / coverage)_+ of each sample
        self.shift_rgb, self.shift_depth = RunningMoments(), RunningMoments()  # ``update_shift``

    @property
    def count(self) -> int:
        return self.rgb.count

    def update(self, out: RenderOutput) -> None:
        self.rgb.update(out.rgb)
        self.depth.update(out.depth)
        self.alpha.update(out.alpha)
        self.gap.update((1.0 - out.alpha.detach() / self.coverage).clamp_min(0.0))

    def update_shift(self, out: RenderOutput) -> None:
        """Fold in one render of the model with its Gaussians shifted within their resolution (``mc_render``'s
        ``shift_fn``): their variance is added to the maps, their mean is not used."""
        self.shift_rgb.update(out.rgb)
        self.shift_depth.update(out.depth)

    def maps(self, image_names: tuple[str, ...] = (), *, empty_std: tuple[float, float] | None = None,
             extra_var: Terms | None = None, extra_depth_var: Terms | None = None,
             terms: bool = False) -> UncertaintyMaps:
        """The mean and std maps of the samples so far (see ``mc_render`` for ``empty_std``, ``extra_var``,
        ``extra_depth_var`` and ``terms``)."""
        rgb_var, depth_var = self.rgb.var, self.depth.var
        rgb_parts: dict[str, Tensor] = {"samples": rgb_var}
        depth_parts: dict[str, Tensor] = {"samples": depth_var}
        if self.shift_rgb.count:
            rgb_parts["resolution"], depth_parts["resolution"] = self.shift_rgb.var, self.shift_depth.var
            rgb_var = rgb_var + rgb_parts["resolution"]
            depth_var = depth_var + depth_parts["resolution"]
        if empty_std is not None and (empty_std[0] > 0 or empty_std[1] > 0):
            # the mean over the samples of (1 - alpha / coverage)_+^2, [C,H,W,1] (M2 / n is the biased variance)
            gap = self.gap.mean.square() + self.gap.var * ((self.count - 1) / self.count)
            rgb_parts["empty rays"], depth_parts["empty rays"] = gap * empty_std[0] ** 2, gap * empty_std[1] ** 2
            rgb_var = rgb_var + rgb_parts["empty rays"]
            depth_var = depth_var + depth_parts["empty rays"]
        if extra_var is not None:
            rgb_var = rgb_var + sum_terms(extra_var).to(rgb_var)
            rgb_parts.update(_named(extra_var, "extra"))
        if extra_depth_var is not None:
            depth_var = depth_var + sum_terms(extra_depth_var).to(depth_var)
            depth_parts.update(_named(extra_depth_var, "extra"))
        # a colour in [0, 1] spreads at most 0.5 (half its mass at each end): the side terms, each sized for a
        # render at the photos' resolution, add up past that on a render several times finer (0.69 at 8x)
        rgb_std, depth_std = rgb_var.sqrt().clamp_max(RGB_STD_MAX), depth_var.sqrt()
        rgb_terms = depth_terms = None
        if terms:  # per pixel, the RGB parts as the mean over the channels of those that have three
            rgb_terms = {k: (v.mean(-1, keepdim=True) if v.shape[-1] == 3 else v).to(rgb_var)
                         for k, v in rgb_parts.items()}
            depth_terms = {k: v.to(depth_var) for k, v in depth_parts.items()}
        return UncertaintyMaps(rgb_mean=self.rgb.mean, rgb_std=rgb_std, depth_mean=self.depth.mean,
                               depth_std=depth_std, alpha_mean=self.alpha.mean, n_samples=self.count,
                               image_names=image_names, rgb_terms=rgb_terms, depth_terms=depth_terms)


Terms = Tensor | Mapping[str, Tensor]
"""A variance map [C,H,W,1], or several named ones whose sum it is (``mc_render``'s ``extra_var``)."""


def sum_terms(extra: Terms) -> Tensor:
    """``extra`` itself, or the sum of its maps in their order (the first's device and dtype)."""
    if not isinstance(extra, Mapping):
        return extra
    if not extra:
        raise ValueError("an empty mapping of variance terms (give None for no term)")
    maps = list(extra.values())
    total = maps[0]
    for m in maps[1:]:
        total = total + m.to(total)
    return total


def _named(extra: Terms, name: str) -> dict[str, Tensor]:
    return dict(extra) if isinstance(extra, Mapping) else {name: extra}


RGB_STD_MAX = 0.5
"""The largest RGB std ``mc_render`` gives: that of a value in [0, 1] with half its mass at 0 and half at 1."""


@dataclass(frozen=True)
class MCSamples:
    """The individual renders, kept only on request (memory grows with K).

    Attributes:
        rgb: [K,C,H,W,3]
        depth: [K,C,H,W,1]
    """

    rgb: Tensor
    depth: Tensor


SampleFn = Callable[[torch.Generator], GaussianSample]
RenderFn = Callable[[GaussianSample, Cameras], RenderOutput]


def mc_render(
    sample_fn: SampleFn,
    render_fn: RenderFn,
    cameras: Cameras,
    num_samples: int,
    generator: torch.Generator,
    *,
    keep_samples: bool = False,
    empty_std: tuple[float, float] | None = None,
    coverage: float = 1.0,
    extra_var: Terms | None = None,
    extra_depth_var: Terms | None = None,
    shift_fn: SampleFn | None = None,
    shift_renders: int = 1,
    terms: bool = False,
) -> tuple[UncertaintyMaps, MCSamples | None]:
    """Render ``num_samples`` posterior samples of ``cameras`` and return their mean and std maps.

    Args:
        sample_fn: draws one posterior sample with the given generator.
        render_fn: renders a sample for the cameras (e.g. ``functools.partial(render, background=bg)``).
        cameras: C cameras sharing one image size.
        num_samples: K >= 1.
        generator: the only source of randomness; the same seed gives the same maps.
        keep_samples: also return every render (memory x K), e.g. for the KDE NLL of a view.
        empty_std: (colour std, depth std) of the unknown surface behind a ray that meets no Gaussian. Where
            a sample's accumulated opacity alpha is below ``coverage``, a fraction 1 - alpha / coverage of the
            pixel shows what the model has no Gaussian for: treated as an independent unknown value with this
            std, it adds ``E[(1 - alpha / coverage)_+^2] std^2`` to the variance (E over the samples), so a
            pixel the model knows nothing about is never certain. None: the samples' spread only (e.g. when
            the background is part of the data).
        coverage: the opacity the model reaches on the surfaces its training views saw
            (``training_coverage``): a trained model leaves some of each pixel uncovered even where the
            surface was seen (alpha 0.9-1, its colours fitted with that), and that part is not unknown. 1
            counts every alpha < 1 (the term before 2026-11-25; BENCHMARKS.md, "Coverage, resolution and floaters").
        extra_var: [C,H,W,1] a variance added to the RGB variance, e.g. the pixel noise of the model's
            Gaussians (``uncertainty.residual``): the predictive of a pixel is the samples' spread plus it. Or a
            mapping of named such maps, added as their sum in their order (``sum_terms``), each a part of ``terms``.
        extra_depth_var: [C,H,W,1] a variance added to the depth variance, e.g. the spread of the depths each ray
            blends (``depth_spread``); or a mapping of named ones, as ``extra_var``.
        shift_fn: the resolution term (``resolution_shift``): one render of it per sample, whose variance is added
            to the RGB and depth variance (their mean is not used). Draws from its own generator, seeded from
            ``generator``'s initial seed.
        shift_renders: renders of ``shift_fn`` per sample (``shift_renders`` x K in all): the resolution term's
            variance is estimated from that many renders, so its Monte Carlo noise falls with them (it is what
            the std's ranking loses most to at small K; BENCHMARKS.md, "The resolution term's renders").
        terms: also return what each part adds to the variance (``UncertaintyMaps.rgb_terms`` / ``depth_terms``):
            "samples" (the K renders' spread), "resolution", "empty rays", and ``extra_var``'s and
            ``extra_depth_var``'s named maps (a bare tensor is named "extra").

    Returns:
        (UncertaintyMaps with rgb_mean/rgb_std [C,H,W,3], depth_mean/depth_std [C,H,W,1],
        alpha_mean [C,H,W,1]; MCSamples or None). Runs under ``torch.no_grad()``.
    """
    if num_samples < 1:
        raise ValueError(f"num_samples must be >= 1, got {num_samples}")
    if shift_renders < 1:
        raise ValueError(f"shift_renders must be >= 1, got {shift_renders}")
    moments = MonteCarloMoments(coverage)
    # the shifts draw from a generator of their own (seeded from this one's seed, which they leave untouched):
    # a sampler may depend on its generator's state between its own calls (an ensemble's member order)
    shift_gen = None
    if shift_fn is not None:
        shift_gen = torch.Generator(device=generator.device).manual_seed(generator.initial_seed() ^ SHIFT_SEED)
    kept_rgb: list[Tensor] = []
    kept_depth: list[Tensor] = []
    with torch.no_grad():
        for _ in range(num_samples):
            sample = sample_fn(generator)
            out = render_fn(sample, cameras)
            moments.update(out)
            if shift_fn is not None:
                for _ in range(shift_renders):
                    moments.update_shift(render_fn(shift_fn(shift_gen), cameras))
            if keep_samples:
                kept_rgb.append(out.rgb.detach())
                kept_depth.append(out.depth.detach())
            # Drop the references now so the sample's and the render's memory can be reused by
            # the next iteration (otherwise two renders are alive at the peak).
            del sample, out
    maps = moments.maps(tuple(cameras.image_names), empty_std=empty_std, extra_var=extra_var,
                        extra_depth_var=extra_depth_var, terms=terms)
    samples = MCSamples(torch.stack(kept_rgb), torch.stack(kept_depth)) if keep_samples else None
    return maps, samples


COVERAGE_QUANTILE = 0.05
"""``training_coverage``: the fraction of training pixels allowed to lie below the coverage. Measured on the demo
scene at 160x120 with the coverage fixed at 0.5-0.95: about the same depth ranking on a dense capture from 0.8 down
(depth AUSE-MAE 0.155 at 0.8, 0.168 at 0.9, 0.280 at 1), but the lower the value, the worse the NLL where holes are
partly covered (half-ring protocol: 0.11 at 1, 0.24 at 0.9, 0.39 at 0.75); the 5 % quantile (0.87 there) lies
between."""


@torch.no_grad()
def training_coverage(sample: GaussianSample, cameras: Cameras, render_fn: RenderFn, *,
                      quantile: float = COVERAGE_QUANTILE, max_views: int = 8,
                      masks_of: Callable[[list[int]], Tensor | None] | None = None) -> float:
    """The opacity the model reaches on the surfaces its training views saw: the ``quantile`` of the rendered
    alpha over every pixel of at most ``max_views`` evenly spaced training cameras (``mc_render``'s
    ``coverage``). At least 1e-3, so a model that covers nothing still gives a valid value; 1 without cameras.

    Args:
        sample: the model's Gaussians (its expected render or posterior mean).
        cameras: the training cameras (images are not needed).
        render_fn: renders a sample for cameras.
        masks_of: the masks [k,H,W,1] bool of the training cameras at the given positions (the photos' own masks:
            the pixels training fitted; it may give None), or None: every pixel.
    """
    if not 0.0 <= quantile < 1.0:
        raise ValueError(f"quantile must be in [0, 1), got {quantile}")
    n = len(cameras)
    if n == 0:
        return 1.0
    k = min(max_views, n)
    pick = sorted({round(j * (n - 1) / max(k - 1, 1)) for j in range(k)})
    masks = masks_of(pick) if masks_of is not None else None  # [k,H,W,1], or None: every pixel
    masks = masks.cpu() if masks is not None else None
    alphas = [render_fn(sample, cameras[[i]]).alpha[0].float().cpu()[masks[j] if masks is not None else ...]
              .flatten() for j, i in enumerate(pick)]
    a = torch.cat(alphas)
    if a.numel() > 1 << 24:  # torch.quantile's input limit: every so many of them, by integer steps (a float32
        # linspace's last index rounded up to the count itself past 2^24 values: 8 views of 1920x1440 raised)
        a = a[spread_indices(a.numel(), 1 << 24)]
    return float(a.quantile(quantile).clamp(1e-3, 1.0))


def spread_indices(n: int, m: int) -> Tensor:
    """[m] int64 indices 0 .. n - 1 spread evenly over ``n`` (first and last included; ``m`` <= ``n``, ``m`` >= 2)."""
    return torch.arange(m, dtype=torch.int64) * (n - 1) // (m - 1)


@torch.no_grad()
def depth_spread(sample: GaussianSample, cameras: Cameras, render_fn: RenderFn) -> Tensor:
    """[C,H,W,1] the variance of the depths each ray blends: ``sum_i w_i z_i^2 / alpha - depth^2`` (w_i the blending
    weights, z_i each Gaussian's camera z, alpha = sum_i w_i, depth the alpha-normalised depth), clamped at 0; 0
    where nothing is blended.

    A rendered depth is the weighted mean of the depths of the Gaussians along the ray: where the ray crosses an
    edge, a semi-transparent layer or a floater in front of a surface, the pixel's depth is a mixture of distant
    values, and the mean says nothing of it. Two renders per camera (``uncertainty.residual.blend_colours`` of
    (z - z0, (z - z0)^2, 0), z0 the nearest Gaussian in front of the camera).
    """
    from uncertsplat.uncertainty.residual import blend_colours

    outs = []
    for j in range(len(cameras)):
        cam = cameras[[j]]
        cw = cam.cam_from_world[0].to(sample.means)  # [4,4]
        z = sample.means @ cw[2, :3] + cw[2, 3]  # [N] camera z of each mean, as the renderer's depth uses
        # shifted by the nearest Gaussian in front of the camera: the variance does not change, float32 keeps its
        # digits for a scene far from the camera, and the colours stay >= 0 (the renderer clamps colours at 0;
        # the Gaussians behind the camera, clamped, are culled anyway)
        front = z[z > 0]
        z = z - (front.min() if front.numel() else 0.0)
        moments, alpha = blend_colours(sample, torch.stack([z, z * z, torch.zeros_like(z)], -1), cam, render_fn)
        moments, alpha = moments[0], alpha[0]  # [H,W,3]: sum w z, sum w z^2, 0; [H,W,1]
        a = alpha.clamp_min(1e-6)
        mean = moments[..., :1] / a
        var = (moments[..., 1:2] / a - mean.square()).clamp_min(0.0)
        outs.append(torch.where(alpha > 1e-6, var, torch.zeros_like(var)))
    return torch.stack(outs)


def resolution_shift(sample: GaussianSample, resolution: float) -> SampleFn:
    """A sampler of ``sample`` with every Gaussian moved by N(0, (resolution x its size)^2) per axis (size: the
    geometric mean of its axes): ``mc_render``'s ``shift_fn`` (see ``config.EvalConfig.resolution``)."""
    size = sample.scales.detach().clamp_min(1e-30).log().mean(-1, keepdim=True).exp()  # [N,1]
    step = float(resolution) * size

    def shift(generator: torch.Generator) -> GaussianSample:
        eps = torch.randn(sample.means.shape, generator=generator, device=generator.device, dtype=sample.means.dtype)
        return replace(sample, means=sample.means + step * eps.to(sample.means.device))

    return shift
