"""The pixel noise a model leaves on its training views, attached to its Gaussians and rendered anywhere.

The posterior says how unsure the model is about its Gaussians (epistemic); where the training views show
that the model does not reproduce them, e.g. texture finer than its Gaussians or view-dependent effects, a
pixel is uncertain however certain the parameters are (the noise of the pixel likelihood). This module
estimates that noise per Gaussian, heteroscedastically, and renders it:

* ``fit_residual_field``: each Gaussian's noise variance is the mean squared training residual of the
  pixels it is blended into, weighted by its blending weight w_i(p):
  ``v_i = sum_p w_i(p) r(p)^2 / sum_p w_i(p)`` over every training pixel p (r: the residual, averaged over
  the 3 channels). Both sums come out of one backward pass per view: the render is linear in each
  Gaussian's colour with coefficient w_i(p), so the gradient of ``sum_p c_0(p) r(p)^2 + c_1(p)`` w.r.t. a
  constant colour is the pair of sums. A Gaussian no training pixel sees gets the mean over all pixels.
* ``ResidualField.out_of_sample``: a training residual is smaller than the noise by the share of the data the
  Gaussian's own parameters absorbed (its leverage h, the parameters over the pixel channels it is blended into;
  in least squares the training residual's variance is s^2 (1 - h)), so each Gaussian's noise is divided by
  (1 - h): little for a Gaussian that hundreds of pixels pin down, much for one that a few pixels of a sparse
  capture fitted. Not (1 + h) / (1 - h), a new observation's whole error: its h s^2 is the parameters'
  uncertainty, which the posterior's spread and the resolution term already give the predictive. Relative to the
  typical Gaussian (``relative=True``, the evaluation's default): ``(1 - h_m) / (1 - h)`` where above 1, h_m the
  median leverage of the seen Gaussians. The level of the typical Gaussian's noise stays the one its residuals
  give, which the held-out views of dense captures confirm (the mean predicted variance about the mean squared
  error); only the Gaussians observed by fewer pixels than it, which the training residuals flatter most (the
  initial points of a surface few views saw), get more. Where the median Gaussian's leverage is already at the
  cap (a sparse capture: every Gaussian fitted by a few pixels) nothing changes.
* The colour posterior (``fit_residual_field(colour_posterior=True)``, ``ResidualField.colour_variance``): the
  variational posterior covers where a Gaussian is, not what colour it has. A Gaussian's colour is linear in
  its SH coefficients, so its Laplace posterior is Gaussian for the pixel likelihood, with the B x B precision
  ``sum_views Y(d_v) Y(d_v)^T sum_p w_i(p) / v_i + diag(1 / prior)`` (d_v: the direction from view v's centre
  to the Gaussian; ``sum_p w_i(p)`` stands in for the exact ``sum_p w_i(p)^2``, an upper bound since w <= 1).
  ``colour_covariance = "block"`` keeps the full precision of the first four coefficients (the DC term and band 1,
  ``colour_cross``): exact at degrees 0 and 1, and it tells a direction from its opposite, where band 1 changes
  sign; the higher bands, and every coefficient with ``"diagonal"``, keep only its diagonal (a mean-field
  approximation: precision_b = ``sum_views Y_b(d_v)^2 sum_p w_i(p) /
  v_i + 1 / prior_b``, the coefficients independent), so the covariance between the coefficients is dropped:
  the exact posterior pins down only the combinations the views' directions measured, while the diagonal one
  pins every coefficient a view's basis touches. Exact for the DC term alone (degree 0). The prior is
  empirical: the DC colour's is the variance of the training pixels ("a surface no view saw looks like some
  pixel of the capture"), each higher band's the mean square of that band over the seen Gaussians. Seen from a
  direction d, the colour's variance is ``Y(d)^T precision^-1 Y(d)`` (``sum_b Y_b(d)^2 / precision_b`` for the
  diagonal part): negligible for a Gaussian that views pinned down, the prior's for one no view saw (a surface a
  held-out view uncovers), and larger from a direction whose basis weighs coefficients the views did not
  constrain. The diagonal part depends on d only through Y_b(d)^2, so on its own it cannot tell a direction from
  its opposite as the exact posterior does (the direction opposite a single view, where the odd bands flip sign,
  gets the variance of the view's own direction; exact: about the prior's), and at a view's own direction it is
  up to the number of coefficients times the exact one.
* The edge term (``fit_edge_scale``, ``ResidualField.edge_scale``): most of a model's error sits on the edges
  and texture lines of its render, where a fraction of a pixel's misplacement changes a pixel by a lot, and a
  per-Gaussian noise spreads that error over all the Gaussian's pixels (too wide where the image is flat, too
  narrow on the edge itself). A misplacement of delta pixels changes a pixel by about ``delta |grad I(p)|``,
  so the predictive gets ``delta^2 g(p)`` with ``g`` the squared gradient of the view's own render
  (``image_gradient_sq``), ``delta^2`` fitted to the training residuals by least squares, and the per-Gaussian
  noise is fitted to what the edge term leaves (a Gaussian no training pixel sees keeps the mean of the whole
  residual, edges included: nothing tells where its edges are).
* ``ResidualField.blended``: the blended variance ``sum_i w_i(p) (v_i + c_i)`` of a view (c_i: the colour
  posterior's variance, when fitted; blended in a second channel of the same renders), which ``uncertainty.mc.mc_render`` adds to the samples'
  variance: the predictive of a pixel is the model's spread plus the noise and the unknown colour of its
  Gaussians.

Takes the sample and the renderer as a function (``render_fn(sample, cameras) -> RenderOutput``), so it
imports neither ``render`` nor a model class.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from uncertsplat.render.sh import sh_basis, view_directions
from uncertsplat.types import Cameras, GaussianSample, RenderOutput

MAX_LEVERAGE = 0.9
"""The largest leverage ``ResidualField.out_of_sample`` gives a Gaussian (a factor of 10 on its noise)."""
C0 = 0.28209479177387814  # the DC spherical harmonic: colour = C0 * sh0 + 0.5 (``render.sh``)
MIN_PRIOR = 1e-12
"""Floor of a colour prior variance (an SH band no seen Gaussian uses has no spread to give)."""
MIN_NOISE = 1e-10
"""Floor of the noise variance the colour posterior divides by (a Gaussian its training pixels fit exactly)."""


def with_colour(sample: GaussianSample, colour: Tensor) -> GaussianSample:
    """``sample`` with every Gaussian's colour the constant ``colour`` [N,3] (SH degree 0): renders it as a map of
    per-Gaussian values."""
    sh = ((colour - 0.5) / C0)[:, None, :]
    return replace(sample, sh=sh, sh_degree=0)


@dataclass(frozen=True)
class ResidualField:
    """Per-Gaussian noise variance of one sample's Gaussians.

    Attributes:
        sample: the Gaussians whose geometry blends the noise (the sample the residuals were taken on).
        variance: [N] noise variance per Gaussian (per colour channel).
        seen: [N] bool, the Gaussians some training pixel saw (the others got the mean).
        mean_variance: the mean squared residual over all training pixels and channels (before ``scale``).
        scale: the factor ``variance`` carries (``scaled``; ``eval.engine.fit_noise_scale`` fits one).
        observations: [N] the training pixels each Gaussian is blended into, ``sum_p w_i(p)`` over the views
            the field was fitted on (``out_of_sample``).
    """

    sample: GaussianSample
    variance: Tensor
    seen: Tensor
    mean_variance: float
    scale: float = 1.0
    """The factor ``variance`` was multiplied by (``scaled``): 1 as fitted."""
    observations: Tensor | None = None
    leverage_inflation: float | None = None
    """The mean factor ``out_of_sample`` multiplied the noise by (None: not applied)."""
    colour_evidence: Tensor | None = None
    """[N,B] ``sum_views Y_b(d_v)^2 sum_p w_i(p)`` per SH coefficient b, over all training views (the colour
    posterior, module docstring); None: no colour term."""
    colour_prior: Tensor | None = None
    """[B] the prior variance of each SH coefficient (SH units) of the colour posterior."""
    colour_cross: Tensor | None = None
    """[N,L,L] ``sum_views Y(d_v) Y(d_v)^T sum_p w_i(p)`` over the first L = min(B, 4) coefficients (the DC term and
    band 1), whose posterior is then taken jointly (``colour_covariance = "block"``: module docstring); None: every
    coefficient on its own (the diagonal ``colour_evidence``), and always at SH degree 0 (where the two are one)."""
    edge_scale: float = 0.0
    """``delta^2`` (pixels^2) of the edge term ``delta^2 g(p)`` (module docstring; ``fit_edge_scale``); 0: none."""
    pixel_variance: Tensor | None = None
    """[N] each Gaussian's whole noise, the edge term's share of its pixels included: the pixel likelihood's variance
    the colour posterior divides by (None: ``variance``, i.e. no edge term)."""

    @property
    def likelihood_variance(self) -> Tensor:
        """[N] the variance of a Gaussian's pixels in the likelihood: ``pixel_variance`` when the field has an edge
        term (the per-Gaussian noise alone would make the colours of edge Gaussians look exactly known), else
        ``variance``."""
        return self.variance if self.pixel_variance is None else self.pixel_variance

    @functools.cached_property
    def _colour_block_factor(self) -> tuple[Tensor, Tensor]:
        """The Cholesky factor L [N,L,L] of each Gaussian's block precision P = E / v + diag(1 / prior) (``colour_cross``)
        and its ``info`` [N] (> 0 where P is not positive definite), once per field: it does not depend on the camera.
        float64: the evidence can exceed the prior's inverse by 1e8, past float32's Cholesky. Y^T P^-1 Y = |L^-1 Y|^2."""
        low = self.colour_cross.shape[-1]
        noise = self.likelihood_variance.double().clamp_min(MIN_NOISE)[:, None, None]  # [N,1,1]
        prior = self.colour_prior.double().clamp_min(MIN_PRIOR)[:low]
        prec = self.colour_cross.double() / noise + torch.diag_embed(1.0 / prior).expand_as(self.colour_cross)
        return torch.linalg.cholesky_ex(prec)

    def colour_variance(self, centers: Tensor) -> Tensor:
        """[C,N] the posterior variance of each Gaussian's colour (per channel, RGB units) seen from each
        camera centre ``centers`` [C,3] under the Laplace posterior of its SH coefficients: jointly for the DC term
        and band 1 when the field has ``colour_cross`` (the block form), each coefficient on its own otherwise and
        for the higher bands (the module docstring says what each drops); zeros when the field has no colour
        term."""
        s = self.sample
        if self.colour_evidence is None:
            return torch.zeros(centers.shape[0], s.means.shape[0], device=s.means.device)
        # float32 is enough (evidence / noise stays far below its range) and keeps [C,N,B] small for large models
        noise = self.likelihood_variance.float().clamp_min(MIN_NOISE)[:, None]  # [N,1]
        prior = self.colour_prior.float().clamp_min(MIN_PRIOR)  # [B]
        coef_var = 1.0 / (self.colour_evidence.float() / noise + 1.0 / prior)  # [N,B]
        d = view_directions(s.means.float(), centers.float().to(s.means.device))  # [C,N,3]
        basis = sh_basis(_degree(coef_var.shape[1]), d)  # [C,N,B]
        alone = basis.square() * coef_var  # [C,N,B]: each coefficient's part on its own (the diagonal form)
        if self.colour_cross is None:
            return alone.sum(-1).to(self.variance.dtype)
        low = self.colour_cross.shape[-1]
        chol, info = self._colour_block_factor
        y = basis[..., :low].double().unsqueeze(-1)  # [C,N,L,1]
        z = torch.linalg.solve_triangular(chol.expand(y.shape[0], *chol.shape), y, upper=False)
        joint = z.square().sum((-2, -1))  # [C,N]
        # (a precision that lost definiteness to rounding, or holds no finite number: its coefficients on their own)
        failed = (info != 0) | ~torch.isfinite(joint).all(0)
        if bool(failed.any()):
            joint = torch.where(failed, alone[..., :low].sum(-1).double(), joint)
        return (joint + alone[..., low:].sum(-1).double()).to(self.variance.dtype)

    def out_of_sample(self, params_per_gaussian: int, view_factor: float = 1.0,
                      max_leverage: float = MAX_LEVERAGE, relative: bool = False) -> ResidualField:
        """The noise level behind the training residuals: each Gaussian's variance divided by (1 - h), with leverage
        ``h = min(params_per_gaussian / (3 x observations x view_factor), max_leverage)`` (module docstring).

        Args:
            params_per_gaussian: free parameters of a Gaussian (position 3, scale 3, rotation 4, opacity 1, colour
                3 per SH coefficient).
            view_factor: training views / views the field was fitted on (the observations of all views).
            max_leverage: the cap on h (a Gaussian no pixel saw gets it): 0.9 multiplies by 10.
            relative: divide by ``(1 - h) / (1 - h_m)`` where that is above 1 and leave the rest, h_m the median
                leverage of the seen Gaussians: the correction of a Gaussian observed by fewer pixels than the
                typical one, with the typical one's level kept as the residuals give it (module docstring).
        """
        if self.observations is None:
            raise ValueError("this field has no observation counts (fit it with fit_residual_field)")
        channels = 3.0 * self.observations.double() * view_factor
        h = (params_per_gaussian / channels.clamp_min(1e-30)).clamp(max=max_leverage)
        inflation = 1 / (1 - h)
        if relative:
            typical = h[self.seen].median() if bool(self.seen.any()) else h.new_tensor(0.0)
            inflation = (inflation * (1 - typical)).clamp_min(1.0)
        inflation = inflation.to(self.variance.dtype)
        mean = float(inflation.mean()) if inflation.numel() else 1.0
        pv = None if self.pixel_variance is None else self.pixel_variance * inflation
        return replace(self, variance=self.variance * inflation, pixel_variance=pv, leverage_inflation=mean)

    def scaled(self, factor: float) -> ResidualField:
        """The field with every Gaussian's noise variance times ``factor`` (e.g. a fitted noise level)."""
        if factor == 1.0:
            return self
        pv = None if self.pixel_variance is None else self.pixel_variance * factor
        return replace(self, variance=self.variance * factor, scale=self.scale * factor,
                       edge_scale=self.edge_scale * factor, pixel_variance=pv)

    def colour_unknown_fraction(self) -> float | None:
        """The share of the Gaussians whose DC colour the prior sets more than the data (posterior variance above half
        the prior's: ``evidence / noise < 1 / prior``); None without a colour term."""
        if self.colour_evidence is None or not self.colour_evidence.shape[0]:
            return None
        data = self.colour_evidence[:, 0].double() / self.likelihood_variance.double().clamp_min(MIN_NOISE)
        return float((data < 1.0 / float(self.colour_prior[0].clamp_min(MIN_PRIOR))).double().mean())

    @torch.no_grad()
    def colour_blended(self, cameras: Cameras, render_fn: Callable[[GaussianSample, Cameras], RenderOutput]) -> Tensor:
        """[C,H,W,1] ``sum_i w_i(p) c_i``: the colour posterior's variance alone, blended for the cameras (zeros
        without a colour term). What no training view showed, without the noise of what they did show."""
        return torch.cat([blend_values(self.sample, self.colour_variance(cameras[[j]].centers)[0], cameras[[j]],
                                       render_fn)[0] for j in range(len(cameras))])

    @torch.no_grad()
    def edge(self, cameras: Cameras, render_fn: Callable[[GaussianSample, Cameras], RenderOutput]) -> Tensor:
        """[C,H,W,1] the edge term ``edge_scale x g(p)`` of the field's sample rendered for the cameras (one render;
        zeros without an edge term, and no render)."""
        if self.edge_scale <= 0.0:
            return torch.zeros(len(cameras), cameras.height, cameras.width, 1, device=self.sample.means.device)
        return self.edge_scale * image_gradient_sq(render_fn(self.sample, cameras).rgb)

    @torch.no_grad()
    def blended_parts(self, cameras: Cameras,
                      render_fn: Callable[[GaussianSample, Cameras], RenderOutput]) -> dict[str, Tensor]:
        """``blended``'s parts, [C,H,W,1] each: "pixel noise" ``sum_i w_i(p) v_i``, "colour posterior" ``sum_i w_i(p)
        c_i`` (with a colour term) and "edge" (with an edge term). The first two are one blend (their values in two
        channels of the same renders)."""
        if self.colour_evidence is not None and len(cameras) > 1:  # the colour term depends on the camera
            per = [self.blended_parts(cameras[[j]], render_fn) for j in range(len(cameras))]
            return {k: torch.cat([p[k] for p in per]) for k in per[0]}
        if self.colour_evidence is not None:
            colour = self.colour_variance(cameras.centers)[0]
            both = blend_colours(self.sample, torch.stack([self.variance, colour, torch.zeros_like(colour)], -1),
                                 cameras, render_fn)[0]  # two renders: see blend_colours
            parts = {"pixel noise": both[..., :1], "colour posterior": both[..., 1:2]}
        else:
            parts = {"pixel noise": blend_values(self.sample, self.variance, cameras, render_fn)[0]}
        if self.edge_scale > 0.0:
            parts["edge"] = self.edge(cameras, render_fn)
        return parts

    @torch.no_grad()
    def blended(self, cameras: Cameras, render_fn: Callable[[GaussianSample, Cameras], RenderOutput]) -> Tensor:
        """[C,H,W,1] ``sum_i w_i(p) (v_i + c_i)`` for the cameras (c_i: the colour posterior's variance seen from
        the camera, 0 without a colour term), plus the edge term when the field has one: the sum of
        ``blended_parts``."""
        from uncertsplat.uncertainty.mc import sum_terms

        return sum_terms(self.blended_parts(cameras, render_fn))

    STATE_TENSORS = ("variance", "seen", "observations", "colour_evidence", "colour_prior", "pixel_variance",
                     "colour_cross")
    STATE_NUMBERS = ("mean_variance", "scale", "leverage_inflation", "edge_scale")

    def state(self) -> dict:
        """Everything but the sample, as CPU tensors and numbers (``from_state`` rebuilds the field): what a cache of
        the fitted noise stores."""
        out: dict = {k: getattr(self, k) for k in self.STATE_NUMBERS}
        for k in self.STATE_TENSORS:
            t = getattr(self, k)
            out[k] = None if t is None else t.detach().cpu()
        return out

    @classmethod
    def from_state(cls, sample: GaussianSample, state: dict) -> ResidualField:
        """The field ``state()`` gave, on ``sample`` (the Gaussians it was fitted on, on their device).

        Raises:
            ValueError: the state does not fit the sample (another number of Gaussians or SH coefficients) or
                misses a key.
        """
        n = sample.means.shape[0]
        dev = sample.means.device
        kw: dict = {}
        for k in cls.STATE_NUMBERS:
            if k not in state:
                raise ValueError(f"the residual state has no {k!r}")
            kw[k] = state[k]
        for k in cls.STATE_TENSORS:
            t = state.get(k)
            if t is None:
                kw[k] = None
                continue
            if k != "colour_prior" and t.shape[0] != n:
                raise ValueError(f"the residual state's {k} has {t.shape[0]} rows for {n} Gaussians")
            kw[k] = t.to(dev)
        if kw["variance"] is None or kw["seen"] is None:
            raise ValueError("the residual state has no variance")
        bases = (sample.sh_degree + 1) ** 2
        if kw["colour_evidence"] is not None and kw["colour_evidence"].shape[1] != bases:
            raise ValueError("the residual state's colour evidence is for another SH degree")
        if kw["colour_cross"] is not None and (kw["colour_evidence"] is None
                                               or tuple(kw["colour_cross"].shape[1:]) != (min(bases, 4),) * 2):
            raise ValueError("the residual state's joint colour evidence is for another SH degree")
        return cls(sample=sample, **kw)

    def subset(self, keep: Tensor) -> ResidualField:
        """The field of the Gaussians ``keep`` ([N] bool or indices) kept, e.g. by pruning: each keeps its own
        noise (a property of the Gaussian and the pixels it was blended into)."""
        s = self.sample
        pv = None if s.position_var is None else s.position_var[keep]
        sample = replace(s, means=s.means[keep], quats=s.quats[keep], scales=s.scales[keep],
                         opacities=s.opacities[keep], sh=s.sh[keep], position_var=pv)
        obs = None if self.observations is None else self.observations[keep]
        evidence = None if self.colour_evidence is None else self.colour_evidence[keep]
        cross = None if self.colour_cross is None else self.colour_cross[keep]
        pv = None if self.pixel_variance is None else self.pixel_variance[keep]
        return replace(self, sample=sample, variance=self.variance[keep], seen=self.seen[keep], observations=obs,
                       pixel_variance=pv, colour_evidence=evidence, colour_cross=cross)


def blend_colours(sample: GaussianSample, colour: Tensor, cameras: Cameras,
                  render_fn: Callable[[GaussianSample, Cameras], RenderOutput]) -> tuple[Tensor, Tensor]:
    """``sum_i w_i(p) colour_i`` ([N,3] non-negative per-Gaussian values, three at a time) for the cameras,
    [C,H,W,3], and the renders' alpha [C,H,W,1].

    Two renders: the render is linear in the colours, so the difference between colour ``colour`` and colour 0
    removes whatever background ``render_fn`` composites behind the Gaussians (clamped at 0 against rounding).
    """
    with_c = render_fn(with_colour(sample, colour), cameras)
    without = render_fn(with_colour(sample, torch.zeros_like(colour)), cameras).rgb
    return (with_c.rgb - without).clamp_min(0.0), with_c.alpha


def blend_values(sample: GaussianSample, values: Tensor, cameras: Cameras,
                 render_fn: Callable[[GaussianSample, Cameras], RenderOutput]) -> tuple[Tensor, Tensor]:
    """``sum_i w_i(p) values_i`` ([N] per-Gaussian values) for the cameras, [C,H,W,1], and the renders' alpha
    [C,H,W,1] (``blend_colours`` of the values in the first channel)."""
    zeros = torch.zeros_like(values)
    blended, alpha = blend_colours(sample, torch.stack([values, zeros, zeros], -1), cameras, render_fn)
    return blended[..., :1], alpha


def image_gradient_sq(rgb: Tensor) -> Tensor:
    """[...,H,W,1] the squared gradient magnitude of images ``rgb`` [...,H,W,3] per pixel^2, mean over the channels:
    central differences inside, one-sided at the borders (``torch.gradient``; an image of 1 pixel along an axis has
    0 there)."""
    def diff(dim: int) -> Tensor:
        return torch.gradient(rgb, dim=dim)[0] if rgb.shape[dim] >= 2 else torch.zeros_like(rgb)

    return (diff(rgb.dim() - 2).square() + diff(rgb.dim() - 3).square()).mean(-1, keepdim=True)


EDGE_MIN_ALPHA = 0.5
"""Pixels whose accumulated opacity is below this do not enter the edge term's fit (``fit_edge_scale``): where the
model covers little, the residual is the missing surface's, not an edge's."""


def _edge_sums(pred: Tensor, alpha: Tensor, y: Tensor, mask: Tensor | None) -> Tensor:
    """[5] float64 (n, sum g, sum g^2, sum y, sum g y) over one view's pixels with alpha >= ``EDGE_MIN_ALPHA`` (and in
    ``mask``): the edge term's least-squares sums, g the render ``pred``'s ``image_gradient_sq``, y [H,W,1] what the
    term is fitted to."""
    g = image_gradient_sq(pred)
    valid = alpha >= EDGE_MIN_ALPHA
    if mask is not None:
        valid = valid & mask.to(valid.device).bool()
    g, y = g[valid].double().cpu(), y[valid].double().cpu()
    return torch.stack([torch.tensor(float(g.numel()), dtype=torch.float64), g.sum(), g.square().sum(), y.sum(),
                        (g * y).sum()])


def _edge_slope(sums: Tensor) -> float:
    """The least-squares slope (with an intercept) of y on g from ``_edge_sums`` summed over views, clamped at 0; 0
    when fewer than 2 pixels qualify or g does not vary."""
    n, sg, sgg, sy, sgy = sums.tolist()
    if n < 2:
        return 0.0
    var_g = sgg / n - (sg / n) ** 2
    if var_g <= 1e-20:
        return 0.0
    return max((sgy / n - (sg / n) * (sy / n)) / var_g, 0.0)


@torch.no_grad()
def fit_edge_scale(sample: GaussianSample, cameras: Cameras, images: Tensor,
                   render_fn: Callable[[GaussianSample, Cameras], RenderOutput], *, masks: Tensor | None = None,
                   explained: Callable[[Cameras], Tensor] | None = None) -> float:
    """``delta^2`` of the edge term (module docstring): the least-squares slope of ``r(p)^2 - e(p)`` on ``g(p)``
    (with an intercept) over the training pixels with alpha >= ``EDGE_MIN_ALPHA``, clamped at 0.

    r^2: the squared residual of ``sample``'s render (mean over the channels); e: what ``explained(camera)`` already
    gives each pixel (the resolution term; 0 without it); g: ``image_gradient_sq`` of the render. One render per
    camera. Returns 0 when no pixel qualifies or the gradient does not vary. (``fit_residual_field(edge_scale="fit")``
    fits the same slope in its own pass over the views.)
    """
    sums = torch.zeros(5, dtype=torch.float64)
    for j in range(len(cameras)):
        cam = cameras[[j]]
        out = render_fn(sample, cam)
        pred = out.rgb[0]
        y = (pred - images[j].to(pred)).square().mean(-1, keepdim=True)  # [H,W,1]
        if explained is not None:
            y = y - explained(cam)[0].to(y)
        sums += _edge_sums(pred, out.alpha[0], y, None if masks is None else masks[j])
    return _edge_slope(sums)


def _degree(num_bases: int) -> int:
    """The SH degree of ``num_bases`` coefficients per channel."""
    return round(num_bases ** 0.5) - 1


def _colour_prior(sample: GaussianSample, seen: Tensor, pixel_var: float, num_bases: int) -> Tensor:
    """[B] the colour posterior's prior variance per SH coefficient (SH units): the DC term's from the training
    pixels' variance, each higher band's the mean square of that band's coefficients over the seen Gaussians."""
    prior = torch.zeros(num_bases, dtype=torch.float64, device=sample.means.device)
    prior[0] = pixel_var / C0**2
    sh = sample.sh[seen][:, :num_bases].double()  # [S,B,3]
    for band in range(1, _degree(num_bases) + 1):
        lo, hi = band * band, (band + 1) ** 2
        if sh.shape[0]:
            prior[lo:hi] = sh[:, lo:hi].square().mean()
    return prior


def fit_residual_field(sample: GaussianSample, cameras: Cameras, images: Tensor,
                       render_fn: Callable[[GaussianSample, Cameras], RenderOutput],
                       masks: Tensor | None = None,
                       explained: Callable[[Cameras], Tensor] | None = None, colour_posterior: bool = False,
                       view_factor: float = 1.0, edge_scale: float | str = 0.0,
                       colour_covariance: str = "diagonal") -> ResidualField:
    """Each Gaussian's noise variance from the training views (see the module docstring).

    Args:
        sample: the Gaussians to attach the noise to (e.g. the expected render of a variational model).
        cameras: T training cameras; images: [T,H,W,3] in [0, 1]; masks: [T,H,W,1] bool valid pixels or None.
        render_fn: renders a sample for cameras (with the run's background).
        explained: ``explained(camera) -> [1,H,W,1]`` a variance the rest of the predictive already gives each
            pixel (the resolution term): the noise is fitted to what the residual leaves beyond it,
            ``max(r^2 - explained, 0)``, so that the two are not counted twice.
        colour_posterior: also fit the colour posterior (module docstring; ``ResidualField.colour_variance``).
        colour_covariance: ``"block"``: the DC term and band 1 of the colour posterior jointly (``colour_cross``);
            ``"diagonal"``: every coefficient on its own.
        view_factor: the training views over ``len(cameras)`` (when the field is fitted on a subset of them): the
            colour posterior's evidence is scaled to all training views by it.
        edge_scale: ``delta^2`` of the edge term (0: none; ``"fit"``: fitted as ``fit_edge_scale`` does, from the
            same renders): the noise is fitted to what the residual leaves beyond it as well, and the field renders
            it (``ResidualField.edge``).

    Returns:
        the ``ResidualField`` (on the sample's device).

    One pass over the views, two renders each (the sample's, and one with a constant colour whose gradient gives
    the blended sums): the noise is linear in ``delta^2``, ``sum_p w (r^2 - delta^2 g) = sum_p w r^2 - delta^2
    sum_p w g``, so the sums of r^2 and of g are kept apart and combined once ``delta^2`` is known.
    """
    if isinstance(edge_scale, str) and edge_scale != "fit":
        raise ValueError(f"edge_scale must be a number or 'fit', got {edge_scale!r}")
    if colour_covariance not in ("block", "diagonal"):
        raise ValueError(f"colour_covariance must be 'block' or 'diagonal', got {colour_covariance!r}")
    fit_edge = edge_scale == "fit"
    edge = fit_edge or float(edge_scale) > 0.0
    n = sample.means.shape[0]
    dev = sample.means.device
    colour = torch.full((n, 3), 0.5, device=dev, requires_grad=True)
    acc = torch.zeros(n, 3, device=dev, dtype=torch.float64)  # sum w r^2, sum w, sum w g (valid pixels)
    edge_sums = torch.zeros(5, dtype=torch.float64)  # the edge term's least squares (_edge_sums)
    num_bases = (sample.sh_degree + 1) ** 2
    evidence = torch.zeros(n, num_bases, device=dev, dtype=torch.float64) if colour_posterior else None
    low = min(num_bases, 4)
    # (at SH degree 0 the block is the DC term alone: the diagonal form, exactly)
    cross = torch.zeros(n, low, low, device=dev, dtype=torch.float64) \
        if colour_posterior and colour_covariance == "block" and low > 1 else None
    pix_sum = torch.zeros(3, dtype=torch.float64, device=dev)
    pix_sq = torch.zeros(3, dtype=torch.float64, device=dev)
    total_r2, count = 0.0, 0
    for j in range(len(cameras)):
        cam = cameras[[j]]
        mask = None if masks is None else masks[j]
        with torch.no_grad():
            rendered = render_fn(sample, cam)
            pred = rendered.rgb[0]
            r2 = (pred - images[j].to(pred)).square().mean(-1, keepdim=True)  # [H,W,1]
            if explained is not None:
                r2 = r2 - explained(cam)[0].to(r2)
            if fit_edge:  # fitted to r^2 - e unclamped, as fit_edge_scale
                edge_sums += _edge_sums(pred, rendered.alpha[0], r2, mask)
            r2 = r2.clamp_min(0.0) if explained is not None else r2
            valid = torch.ones_like(r2, dtype=torch.bool) if mask is None else mask.to(dev)
            r2 = torch.where(valid, r2, torch.zeros_like(r2))
            g = torch.where(valid, image_gradient_sq(pred), torch.zeros_like(r2)) if edge else torch.zeros_like(r2)
        total_r2 += float(r2.double().sum())
        count += int(valid.sum())
        out = render_fn(with_colour(sample, colour), cam)
        target = torch.cat([r2, valid.to(r2.dtype), g], -1)  # [H,W,3]: r^2, 1, g
        (grad,) = torch.autograd.grad((out.rgb[0] * target).sum(), colour)
        acc += grad.double()
        if evidence is not None:
            img = images[j].to(dev).double()[valid[..., 0]]  # [P,3]
            pix_sum += img.sum(0)
            pix_sq += img.square().sum(0)
            d = view_directions(sample.means.detach().double(), cam.centers.double())[0]  # [N,3]
            basis = sh_basis(sample.sh_degree, d)  # [N,B]
            evidence += basis.square() * grad[:, 1:2].double()
            if cross is not None:
                y = basis[:, :low]
                cross += y[:, :, None] * y[:, None, :] * grad[:, 1:2, None].double()
    delta2 = _edge_slope(edge_sums) if fit_edge else float(edge_scale)
    # the unseen Gaussians' noise: the whole residual's mean, edges included (nothing says where theirs lie)
    mean_var = total_r2 / max(count, 1)
    weight = acc[:, 1]
    seen = weight > 1e-6 * max(float(weight.max()), 1e-30) if n else torch.zeros(0, dtype=torch.bool, device=dev)
    # not clamped per pixel: an edge pixel the edge term over-explains lowers its Gaussians' noise, so that the two
    # terms together match the residual on average (each Gaussian's mean is clamped at 0)
    beyond = acc[:, 0] - delta2 * acc[:, 2]
    var = torch.where(seen, (beyond / weight.clamp_min(1e-30)).clamp_min(0.0), torch.full_like(weight, mean_var))
    whole_var = None
    if delta2 > 0.0:
        whole_var = torch.where(seen, acc[:, 0] / weight.clamp_min(1e-30), torch.full_like(weight, mean_var)).float()
    prior = None
    if evidence is not None:
        pixel_var = float((pix_sq / max(count, 1) - (pix_sum / max(count, 1)).square()).clamp_min(0).mean())
        prior = _colour_prior(sample, seen, pixel_var, num_bases).float()
        evidence = (evidence * view_factor).float()
        cross = None if cross is None else cross * view_factor  # (float64: its inverse is taken in float64)
    return ResidualField(sample=sample, variance=var.float(), seen=seen, mean_variance=mean_var,
                         observations=weight.float(), colour_evidence=evidence, colour_prior=prior,
                         edge_scale=delta2, pixel_variance=whole_var, colour_cross=cross)


__all__ = ["ResidualField", "blend_colours", "blend_values", "fit_edge_scale", "fit_residual_field", "image_gradient_sq",
           "with_colour"]
