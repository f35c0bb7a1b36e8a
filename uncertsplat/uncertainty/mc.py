"""Monte-Carlo uncertainty rendering: K posterior samples -> per-pixel mean and std, streamed.

Each of the K samples is drawn (``sample_fn(generator)``), rendered (``render_fn(sample, cameras)``),
folded into running moments (Welford's algorithm) and released before the next one, so memory is that
of one render plus three accumulators, whatever K. The std is the unbiased sample std (divisor K - 1);
with K = 1 it is 0 everywhere. Welford's update leaves an exactly constant element with a variance of
exactly 0 (every delta is 0), which keeps "no uncertainty" areas exactly tied for AUSE.

This module takes the sampler and renderer as functions, so it imports neither ``gaussians`` nor
``render`` (and tests can pass tiny stand-ins).

Depth: the rendered depth is alpha-normalised and 0 where a sample hits nothing, so pixels at the
silhouette mix 0 and surface depths and get a large depth std. That is a real property of the
posterior (the surface may or may not be there); ``alpha_mean`` lets callers mask such pixels.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

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


class MonteCarloMoments:
    """Running moments of the renders of posterior samples: what ``mc_render`` accumulates, exposed so that a
    caller can add samples a few at a time and read the maps in between (the viewer refines a still frame
    this way).

    ``update(out)`` folds one ``RenderOutput`` in; ``maps(...)`` reads the mean and std maps with the same
    empty-ray and extra-variance terms as ``mc_render``.
    """

    def __init__(self) -> None:
        self.rgb, self.depth, self.alpha = RunningMoments(), RunningMoments(), RunningMoments()

    @property
    def count(self) -> int:
        return self.rgb.count

    def update(self, out: RenderOutput) -> None:
        self.rgb.update(out.rgb)
        self.depth.update(out.depth)
        self.alpha.update(out.alpha)

    def maps(self, image_names: tuple[str, ...] = (), *, empty_std: tuple[float, float] | None = None,
             extra_var: Tensor | None = None) -> UncertaintyMaps:
        """The mean and std maps of the samples so far (see ``mc_render`` for ``empty_std`` and ``extra_var``)."""
        rgb_std, depth_std = self.rgb.std, self.depth.std
        if empty_std is not None and (empty_std[0] > 0 or empty_std[1] > 0):
            gap = (1.0 - self.alpha.mean).square() + self.alpha.var  # E[(1 - alpha)^2], [C,H,W,1]
            rgb_std = (self.rgb.var + gap * empty_std[0] ** 2).sqrt()
            depth_std = (self.depth.var + gap * empty_std[1] ** 2).sqrt()
        if extra_var is not None:
            rgb_std = (rgb_std.square() + extra_var.to(rgb_std)).sqrt()
        return UncertaintyMaps(rgb_mean=self.rgb.mean, rgb_std=rgb_std, depth_mean=self.depth.mean,
                               depth_std=depth_std, alpha_mean=self.alpha.mean, n_samples=self.count,
                               image_names=image_names)


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
    extra_var: Tensor | None = None,
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
            a sample's accumulated opacity is alpha < 1, a fraction 1 - alpha of the pixel shows what the model
            has no Gaussian for: treated as an independent unknown value with this std, it adds
            ``E[(1 - alpha)^2] std^2`` to the variance (E over the samples), so a pixel the model knows
            nothing about is never certain. None: the samples' spread only (e.g. when the background is
            part of the data).
        extra_var: [C,H,W,1] a variance added to the RGB variance, e.g. the pixel noise of the model's
            Gaussians (``uncertainty.residual``): the predictive of a pixel is the samples' spread plus it.

    Returns:
        (UncertaintyMaps with rgb_mean/rgb_std [C,H,W,3], depth_mean/depth_std [C,H,W,1],
        alpha_mean [C,H,W,1]; MCSamples or None). Runs under ``torch.no_grad()``.
    """
    if num_samples < 1:
        raise ValueError(f"num_samples must be >= 1, got {num_samples}")
    moments = MonteCarloMoments()
    kept_rgb: list[Tensor] = []
    kept_depth: list[Tensor] = []
    with torch.no_grad():
        for _ in range(num_samples):
            sample = sample_fn(generator)
            out = render_fn(sample, cameras)
            moments.update(out)
            if keep_samples:
                kept_rgb.append(out.rgb.detach())
                kept_depth.append(out.depth.detach())
            # Drop the references now so the sample's and the render's memory can be reused by
            # the next iteration (otherwise two renders are alive at the peak).
            del sample, out
    maps = moments.maps(tuple(cameras.image_names), empty_std=empty_std, extra_var=extra_var)
    samples = MCSamples(torch.stack(kept_rgb), torch.stack(kept_depth)) if keep_samples else None
    return maps, samples
