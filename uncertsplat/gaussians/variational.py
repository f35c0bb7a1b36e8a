"""The variational part: offset tables of posterior carriers, posterior samples, KL terms.

Every posterior carrier owns K table entries (``TABLE_SPECS``) for three attributes:

* position: spread raw a [P,K,3] and location b [P,K,3];
  sigma = softplus(a), mu = b, x~ = x + unit (mu + sigma eps), eps ~ N(0, I).
* scale multiplier: width raw c [P,K,3] and left edge d [P,K,3];
  w = clamp(softplus(c), 0.01, 100), l = d, o = l + w u, u ~ U(0, 1).
* opacity gate: spread raw e [P,K,1] and location f [P,K,1];
  tau = softplus(e), nu = f, g = sigmoid((nu + tau eta) / T), eta ~ N(0, 1); alpha~ = sigmoid(a) g.

A sample draws one subset S of M entries (shared by all Gaussians of the sample, as in the paper),
averages the raw columns over S, then draws the noises above. Non-carriers get no offset, multiplier 1
and gate 1. Rotation and colour are deterministic.

Two variants (docs/method.md, "The two variants and the original code's defects"):

* ``"ours"``: the position table is in units of the scene extent (``unit = extent``), so the prior
  N(0, sigma_p^2) is relative to the scene and training is equivariant to a global scale; the scale
  multiplier acts on the linear scale, ``scale = exp(s) * o``.
* ``"paper"``: the position table is in world units (``unit = 1``, an absolute prior); the multiplier
  acts on the log-scale, ``scale = exp(s * o)`` (which makes small Gaussians, s < 0, grow).

KL terms (``kl_terms``) are computed for every table entry (not only the sampled subset), so all
entries are regularised every step, and averaged over elements:

* position and gate: the closed-form KL between Gaussians.
* scale multiplier: the true KL(U[l, l+w] || U[1-w_p, 1]) is log(w_p / w) when the posterior interval
  lies inside the prior's and +infinity otherwise, useless as a loss. ``"paper"`` uses the original
  code's L1 distance between interval end points, |l - (1 - w_p)| + |(l + w) - 1|. ``"ours"`` uses the
  KL between the moment-matched Gaussians of the two uniforms (same mean and variance: mean l + w/2,
  std w / sqrt(12)): finite everywhere, zero exactly at the prior, smooth, on the same nat scale as the
  other two terms, and growing both when the interval shrinks and when it leaves the prior's support.

All spreads go through a numerically safe log-softplus, so the KL and the samplers stay finite for
spreads from 1e-8 to 1e3, saturated gates, and an empty set of carriers (P = 0).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from uncertsplat.gaussians.params import GaussianModel
from uncertsplat.gaussians.prior import (  # noqa: F401 (the layout's names, also importable from here)
    MAX_WIDTH,
    MIN_WIDTH,
    TABLE_NAMES,
    TABLE_SPECS,
    Prior,
    TableSpec,
    Variant,
    empty_tables,
    inverse_softplus,
    mean_multiplier,
    prior_rows,
)
from uncertsplat.types import GaussianSample


def log_softplus(x: Tensor) -> Tensor:
    """log(softplus(x)) without underflow: softplus(x) ~ exp(x) for x << 0, so the log is x there."""
    low = x < -15.0
    # the branch not taken gets a safe input so it cannot produce inf (and NaN gradients); through ``where``, not a
    # clamp: a clamp's gradient at its bound is 1 up to torch 2.13 and 0 from 2.14, which left x = -15 without one
    safe = torch.where(low, torch.full_like(x, -15.0), x)
    return torch.where(low, x, torch.log(F.softplus(safe)))


def clamp_width(width: Tensor) -> Tensor:
    """``width`` clamped to [MIN_WIDTH, MAX_WIDTH], with the gradient 1 on the bounds themselves whatever torch's
    version (a clamp's is 0 there from torch 2.14: a width that starts at a bound never left it)."""
    inside = (width >= MIN_WIDTH) & (width <= MAX_WIDTH)
    return torch.where(inside, width, width.clamp(MIN_WIDTH, MAX_WIDTH))


def _unit(variant: Variant, extent: float) -> float:
    return float(extent) if variant == "ours" else 1.0


def _assemble(model: GaussianModel, idx: Tensor, offset: Tensor, mult: Tensor, gate: Tensor, *, variant: Variant,
              sh_degree: int | None) -> GaussianSample:
    """Full [N,...] activated tensors from per-carrier offset [P,3], multiplier [P,3] and gate [P]."""
    p = model.params
    means = p["means"]
    if idx.numel():
        means = means + torch.zeros_like(means).index_copy(0, idx, offset.to(means.dtype))
        full_mult = torch.ones_like(p["scales"]).index_copy(0, idx, mult.to(means.dtype))
        full_gate = torch.ones_like(p["opacities"]).index_copy(0, idx, gate.to(means.dtype))
        if variant == "ours":
            scales = torch.exp(p["scales"]) * full_mult
        else:
            scales = torch.exp(p["scales"] * full_mult)
        opacities = torch.sigmoid(p["opacities"]) * full_gate
    else:
        scales = torch.exp(p["scales"])
        opacities = torch.sigmoid(p["opacities"])
    sh = torch.cat([p["sh0"], p["shN"]], dim=1)
    degree = model.sh_degree if sh_degree is None else min(sh_degree, model.sh_degree)
    return GaussianSample(means=means, quats=p["quats"], scales=scales, opacities=opacities, sh=sh, sh_degree=degree)


def draw_subset(num_entries: int, subset_size: int, generator: torch.Generator) -> Tensor:
    """[M] distinct entry indices, M = min(subset_size, K), drawn with ``generator`` (on its device)."""
    m = min(max(int(subset_size), 1), num_entries)
    return torch.randperm(num_entries, generator=generator, device=generator.device)[:m]


def _subset_mean(table: Tensor, subset: Tensor) -> Tensor:
    """[P,K,D] -> [P,D]: the mean of the table entries ``subset`` [M].

    On the CPU as a sum of M column slices: ``index_select`` + ``mean(dim=1)`` (a copy and a reduction over the
    middle dimension) took 60 % of an informed training sample's time (BENCHMARKS.md, "Where a training step's
    time goes"). Elsewhere the indices stay on the device (reading them would synchronise it)."""
    if subset.device.type != "cpu":
        return table.index_select(1, subset).mean(dim=1)
    idx = subset.tolist()
    acc = table[:, idx[0]]
    for k in idx[1:]:
        acc = acc + table[:, k]
    return acc / len(idx) if len(idx) > 1 else acc


def _tables(model: GaussianModel, grad: bool) -> dict[str, Tensor]:
    """The offset tables as a sample reads them: the parameters, or detached (``tables_grad=False``: no gradient
    reaches them)."""
    return model.tables if grad else {k: v.detach() for k, v in model.tables.items()}


def sample(model: GaussianModel, generator: torch.Generator, *, subset_size: int = 2, variant: Variant = "ours",
           extent: float = 1.0, temperature: float = 0.2, sh_degree: int | None = None,
           tables_grad: bool = True) -> GaussianSample:
    """One posterior sample of every Gaussian, differentiable w.r.t. parameters and tables.

    Random numbers are drawn in a fixed order (subset, eps [P,3], u [P,3], eta [P,1]) from
    ``generator`` on its own device, so the same generator state gives the same sample.

    Args:
        model: the Gaussians and their offset tables.
        generator: the only source of randomness.
        subset_size: M, entries averaged per sample (clamped to K).
        variant: "ours" or "paper" (see the module docstring).
        extent: scene extent (position unit for "ours").
        temperature: gate temperature T.
        sh_degree: SH degree to evaluate (default: the model's maximum).
        tables_grad: False: the sample is differentiable w.r.t. the Gaussians' parameters only (the
            informed posterior sets its tables in closed form, ``informed_tables``).
    """
    draws = _draw(model, generator, subset_size)
    if draws.idx.numel() == 0:
        return _assemble(model, draws.idx, draws.eps, draws.u, draws.eta[:, 0], variant=variant, sh_degree=sh_degree)
    tables = _tables(model, tables_grad)
    avgs = {name: _subset_mean(tables[name], draws.subset) for name in TABLE_NAMES}  # [P,D]
    return _sample_from(model, draws, avgs, variant=variant, extent=extent, temperature=temperature,
                        sh_degree=sh_degree)


def sample_with_kl(model: GaussianModel, generator: torch.Generator, prior: Prior, *, subset_size: int = 2,
                   extent: float = 1.0, sh_degree: int | None = None) -> tuple[GaussianSample, dict[str, Tensor]]:
    """``sample(...)`` and ``kl_terms(model, prior)`` together (the training step needs both).

    The same random draws and values as the two calls. On the native path (CPU, float32) the tables
    enter the graph through one node, whose backward writes each table's gradient (KL plus the
    sampled entries) in a single pass instead of four.
    """
    from uncertsplat import native

    kw = {"variant": prior.variant, "extent": extent, "temperature": prior.temperature, "sh_degree": sh_degree}
    tables = [model.tables[name] for name in TABLE_NAMES]
    if model.num_carriers == 0 or not native.use_for(*tables, dtypes=(torch.float32,), strict=False):
        return sample(model, generator, subset_size=subset_size, **kw), kl_terms(model, prior)
    draws = _draw(model, generator, subset_size)
    want = torch.is_grad_enabled() and any(t.requires_grad for t in tables)
    *avg_list, kl_pos, kl_scale, kl_gate = _FusedTables.apply(draws.subset, prior, want, *tables)
    avgs = dict(zip(TABLE_NAMES, avg_list, strict=True))
    kl = {"position": kl_pos, "scale": kl_scale, "gate": kl_gate, "total": kl_pos + kl_scale + kl_gate}
    return _sample_from(model, draws, avgs, **kw), kl


@dataclass(frozen=True)
class _Draws:
    idx: Tensor  # [P] carriers in table-row order
    subset: Tensor  # [M] table entries averaged in this sample
    eps: Tensor  # [P,3] position noise
    u: Tensor  # [P,3] scale-multiplier noise
    eta: Tensor  # [P,1] gate noise


def _draw(model: GaussianModel, generator: torch.Generator, subset_size: int) -> _Draws:
    """The random numbers of one sample, in the documented order."""
    idx = model.carrier_index()
    P = idx.numel()
    gdev, dev = generator.device, model.device
    subset = draw_subset(model.num_entries, subset_size, generator).to(dev)
    eps = torch.randn((P, 3), generator=generator, device=gdev).to(dev)
    u = torch.rand((P, 3), generator=generator, device=gdev).to(dev)
    eta = torch.randn((P, 1), generator=generator, device=gdev).to(dev)
    return _Draws(idx, subset, eps, u, eta)


def _sample_from(model: GaussianModel, d: _Draws, avgs: dict[str, Tensor], *, variant: Variant, extent: float,
                 temperature: float, sh_degree: int | None) -> GaussianSample:
    """A sample from the subset-averaged raw columns ``avgs`` [P,D] and the draws."""
    sigma = F.softplus(avgs["pos_spread_raw"])
    offset = (avgs["pos_loc"] + sigma * d.eps) * _unit(variant, extent)
    width = clamp_width(F.softplus(avgs["scale_width_raw"]))
    mult = avgs["scale_left"] + width * d.u
    tau = F.softplus(avgs["gate_spread_raw"])
    gate = torch.sigmoid((avgs["gate_loc"] + tau * d.eta) / temperature)[:, 0]
    return _assemble(model, d.idx, offset, mult, gate, variant=variant, sh_degree=sh_degree)


class _FusedTables(torch.autograd.Function):
    """Tables -> (subset averages [P,D] in TABLE_NAMES order, KL position, scale, gate), by the native KL.

    Forward computes each KL term and its per-element gradient in one pass (kept only when needed);
    backward scales that gradient in place and adds the averages' gradient to the sampled entries.
    Backward can run once (the kept gradients are reused in place).
    """

    @staticmethod
    def forward(ctx, subset: Tensor, prior: Prior, want_grad: bool, *tables: Tensor):
        t = dict(zip(TABLE_NAMES, (x.detach() for x in tables), strict=True))
        entries = subset.tolist()
        avgs = []
        for name in TABLE_NAMES:  # the mean of M strided [P,D] views: cheaper than index_select + mean
            acc = t[name][:, entries[0]].clone()
            for k in entries[1:]:
                acc += t[name][:, k]
            avgs.append(acc / len(entries))
        unit: dict[str, Tensor] = {}
        terms = (("position", "pos_loc", "pos_spread_raw", "gaussian", 0.0, prior.position_std),
                 ("scale", "scale_left", "scale_width_raw", "scale", prior.scale_width,
                  0 if prior.variant == "ours" else 1),
                 ("gate", "gate_loc", "gate_spread_raw", "gaussian", prior.gate_mean, prior.gate_std))
        kls = []
        for term, loc, raw, kind, a, b in terms:
            value, g_loc, g_raw = _native_kl(kind, t[loc], t[raw], a, b, want_grad)
            kls.append(value)
            if want_grad:
                unit[loc], unit[raw] = (g_loc, term), (g_raw, term)
        ctx.unit, ctx.entries = unit, entries
        ctx.n = {term: t[loc].numel() for term, loc, *_ in terms}
        return (*avgs, *kls)

    @staticmethod
    def backward(ctx, *grads: Tensor):
        g_avgs = dict(zip(TABLE_NAMES, grads[:6], strict=True))
        g_kl = dict(zip(("position", "scale", "gate"), grads[6:], strict=True))
        out = []
        for name in TABLE_NAMES:
            g, term = ctx.unit[name]
            g.mul_(g_kl[term] / ctx.n[term])
            share = g_avgs[name] / len(ctx.entries)
            for k in ctx.entries:
                g[:, k] += share
            out.append(g)
        ctx.unit = None
        return (None, None, None, *out)


def expected_gate(loc: Tensor, spread: Tensor, temperature: float) -> Tensor:
    """E[sigmoid((nu + tau eta) / T)], eta ~ N(0,1), by the probit approximation (error < 0.02)."""
    z = loc / temperature
    s = spread / temperature
    return torch.sigmoid(z / torch.sqrt(1.0 + (math.pi / 8.0) * s * s))


def absorbed_opacity_logit(opacity: Tensor, gate: Tensor | float) -> Tensor:
    """The base opacity logit whose opacity times ``gate`` (the expected gate) is ``opacity``: a posterior's gate
    absorbed so that the posterior mean renders the Gaussian as before (capped below 1 where the gate cannot carry
    it)."""
    base = (opacity / gate).clamp(1e-6, 1.0 - 1e-4)
    return torch.log(base / (1.0 - base))


def posterior_mean(model: GaussianModel, *, variant: Variant = "ours", extent: float = 1.0,
                   temperature: float = 0.2, sh_degree: int | None = None,
                   tables_grad: bool = True, constants: ExpectedConstants | None = None) -> GaussianSample:
    """The deterministic render of the posterior: no random numbers.

    All K entries are averaged (the expectation over the random subset of the averaged columns), the
    position offset is its mean mu, the multiplier its mean l + w/2, and the gate its expectation
    (probit approximation), so that the mean render has the opacity the samples have on average.
    Densification, pruning and spawning decide on these values, never on a fresh sample. ``tables_grad``:
    as for ``sample``. ``constants``: as for ``expected_render_sample`` (the same table terms serve both), for a
    training step's render.
    """
    if (constants is not None and constants.mean_factor is not None and variant == "ours" and not tables_grad
            and model.num_carriers > 0 and constants.fits(model)):
        p = model.params
        degree = model.sh_degree if sh_degree is None else min(sh_degree, model.sh_degree)
        # the SH as the table's two tensors (GaussianSample.sh_rest), as expected_render_sample's fast path
        means, scales, opacities = _with_constants(p, constants.offset, constants.mean_factor, constants.gate)
        return GaussianSample(means=means, quats=p["quats"], scales=scales, opacities=opacities,
                              sh=p["sh0"], sh_rest=p["shN"], sh_degree=degree)
    t = _tables(model, tables_grad)
    idx = model.carrier_index()
    if idx.numel() == 0:
        z = torch.zeros(0, 3, device=model.device)
        return _assemble(model, idx, z, z, z[:, 0], variant=variant, sh_degree=sh_degree)
    offset, left, width, gate = _entry_means(t, variant, extent, temperature)
    return _assemble(model, idx, offset, left + 0.5 * width, gate, variant=variant, sh_degree=sh_degree)


def _with_constants(p: dict[str, Tensor], offset: Tensor, factor: Tensor, gate: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """(means + offset [N,3], exp(log scales) x factor [N,3], sigmoid(opacity logits) x gate [N]): a training step's
    Gaussians from the parameters and the table terms kept between steps (``ExpectedConstants``). On a CPU with the
    native kernels one pass forward and one backward (``native/csrc/sample.cpp``) instead of five tensor ops and
    their autograd nodes; the tensor ops elsewhere."""
    from uncertsplat import native

    tensors = (p["means"], offset, p["scales"], factor, p["opacities"], gate)
    n = tensors[0].shape[0]
    shapes_match = all(t.shape == (n, 3) for t in tensors[:4]) and all(t.shape == (n,) for t in tensors[4:])
    if (shapes_match and native.use_for(*tensors, dtypes=(torch.float32,), strict=False)
            and not any(t.requires_grad for t in (offset, factor, gate))):
        return _MeanGaussians.apply(*tensors)
    return p["means"] + offset, torch.exp(p["scales"]) * factor, torch.sigmoid(p["opacities"]) * gate


class _MeanGaussians(torch.autograd.Function):
    """``_with_constants`` by the native kernel: gradients to the means, log scales and opacity logits (the table
    terms are constants)."""

    @staticmethod
    def forward(ctx, means, offset, scales, factor, opacities, gate):
        from uncertsplat import native

        ins = [t.detach().contiguous() for t in (means, offset, scales, factor, opacities, gate)]
        out_means, out_scales, out_opacities = (torch.empty_like(ins[i]) for i in (0, 2, 4))
        native.library().us_mean_sample_forward_f32(means.shape[0], *(t.data_ptr() for t in ins),
                                                    out_means.data_ptr(), out_scales.data_ptr(),
                                                    out_opacities.data_ptr())
        ctx.save_for_backward(out_scales, ins[4], ins[5])
        ctx.set_materialize_grads(False)
        return out_means, out_scales, out_opacities

    @staticmethod
    def backward(ctx, g_means, g_scales, g_opacities):
        from uncertsplat import native

        out_scales, opacities, gate = ctx.saved_tensors
        grads = [None if g is None else g.contiguous() for g in (g_scales, g_opacities)]
        d_scales, d_opacities = torch.empty_like(out_scales), torch.empty_like(opacities)
        native.library().us_mean_sample_backward_f32(
            opacities.shape[0], out_scales.data_ptr(), opacities.data_ptr(), gate.data_ptr(),
            *(None if g is None else g.data_ptr() for g in grads), d_scales.data_ptr(), d_opacities.data_ptr())
        return g_means, None, d_scales, None, d_opacities, None


def _entry_means(t: dict[str, Tensor], variant: Variant, extent: float,
                 temperature: float) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Per carrier, from all K entries averaged: the mean position offset [P,3], the multiplier's interval
    [l, l + w] as (left, width) [P,3], and E[gate] [P]."""
    offset = t["pos_loc"].mean(1) * _unit(variant, extent)
    width = _multiplier_width(t)
    gate = expected_gate(t["gate_loc"].mean(1), F.softplus(t["gate_spread_raw"].mean(1)), temperature)[:, 0]
    return offset, t["scale_left"].mean(1), width, gate


def _multiplier_width(t: dict[str, Tensor]) -> Tensor:
    """[P,3] the width w of the multiplier's interval [l, l + w] (all K entries averaged, clamped)."""
    return clamp_width(F.softplus(t["scale_width_raw"].mean(1)))


def _position_variance(t: dict[str, Tensor], variant: Variant, extent: float) -> Tensor:
    """[P] the mean of a carrier's per-axis position variances (all K entries averaged)."""
    return (F.softplus(t["pos_spread_raw"].mean(1)) * _unit(variant, extent)).square().mean(1)


def _multiplier_second_moment(left: Tensor, width: Tensor) -> Tensor:
    """E[o^2] for o ~ U[l, l + w]."""
    return left * left + left * width + width * width / 3.0


def _scale_second_moment(log_scale: Tensor, left: Tensor, width: Tensor, variant: Variant) -> Tensor:
    """E[scale^2] [P,3] under the multiplier o ~ U[l, l + w]: exp(2s) E[o^2] (ours) or E[exp(2 s o)] (paper)."""
    if variant == "ours":
        return torch.exp(2.0 * log_scale) * _multiplier_second_moment(left, width)
    # E[exp(2 s o)] = exp(2 s l) (exp(2 s w) - 1) / (2 s w); the ratio tends to 1 as s w -> 0
    x = 2.0 * log_scale * width
    small = x.abs() < 1e-6
    ratio = torch.where(small, 1.0 + 0.5 * x, torch.expm1(x) / torch.where(small, torch.ones_like(x), x))
    return torch.exp(2.0 * log_scale * left) * ratio


@dataclass
class ExpectedConstants:
    """What ``expected_render_sample`` reads from the offset tables, spread to all N Gaussians (variant "ours").

    With the tables held fixed (``tables_grad=False``: the informed posterior sets them in closed form every
    ``refresh_interval`` steps) these are constants, and a training step needs only three element-wise ops on
    the parameters instead of the tables' reductions and scatters (about 6 of a demo step's 88 ms, forward and
    backward, BENCHMARKS.md). The caller owns their lifetime: ``fits`` catches a change of topology, not a change
    of the tables' values (``informed_tables`` writes them through ``.data``), so drop them when the tables change.
    """

    offset: Tensor  # [N,3] mean position offset (0 off the carriers)
    scale_factor: Tensor  # [N,3] sqrt(E[multiplier^2]) (1 off the carriers)
    gate: Tensor  # [N] E[gate] (1 off the carriers)
    position_var: Tensor  # [N] mean per-axis position variance (0 off the carriers)
    rows: Tensor  # the model's posterior_row when computed (identity and version checked by ``fits``)
    rows_version: int
    mean_factor: Tensor | None = None  # [N,3] E[multiplier] = l + w/2 (1 off the carriers): ``posterior_mean``'s

    def fits(self, model: GaussianModel) -> bool:
        return (model.posterior_row is self.rows and model.posterior_row._version == self.rows_version
                and self.offset.shape[0] == len(model))


@torch.no_grad()
def expected_constants(model: GaussianModel, *, extent: float = 1.0, temperature: float = 0.2) -> ExpectedConstants:
    """The table terms of ``expected_render_sample`` (variant "ours", tables without gradient), computed once."""
    t = _tables(model, False)
    idx = model.carrier_index()
    p = model.params
    offset = torch.zeros_like(p["means"])
    factor = torch.ones_like(p["scales"])
    mean_factor = torch.ones_like(p["scales"])
    gate = torch.ones_like(p["opacities"])
    var = torch.zeros_like(p["opacities"])
    if idx.numel():
        mean_offset, left, width, mean_gate = _entry_means(t, "ours", extent, temperature)
        offset.index_copy_(0, idx, mean_offset.to(offset.dtype))
        factor.index_copy_(0, idx, _multiplier_second_moment(left, width).sqrt().to(factor.dtype))
        mean_factor.index_copy_(0, idx, (left + 0.5 * width).to(factor.dtype))
        gate.index_copy_(0, idx, mean_gate.to(gate.dtype))
        var.index_copy_(0, idx, _position_variance(t, "ours", extent).to(var.dtype))
    row = model.posterior_row
    return ExpectedConstants(offset, factor, gate, var, row, row._version, mean_factor)


def expected_render_sample(model: GaussianModel, *, variant: Variant = "ours", extent: float = 1.0,
                           temperature: float = 0.2, sh_degree: int | None = None,
                           tables_grad: bool = True, constants: ExpectedConstants | None = None) -> GaussianSample:
    """Deterministic Gaussians whose render approximates the *mean of the posterior's renders*.

    ``posterior_mean`` renders each Gaussian at its mean parameters, which is sharper than the average
    of posterior samples the model was trained to fit: every sample jitters a carrier by its position
    spread. This sample matches the first two moments of each carrier's footprint instead (all K entries
    averaged, no random numbers): the scale at its second moment under the multiplier, sqrt(E[scale^2]),
    the opacity times E[gate], and ``position_var`` = sigma^2 (the mean of the per-axis position
    variances; exact for the isotropic prior), which ``render`` folds in per view: covariance
    Sigma + sigma^2 I, opacity lowered by the 2D peak ratio (``GaussianSample.position_var``).

    On the demo scene its held-out PSNR is above both ``posterior_mean`` and the mean of 10 sampled renders;
    on fern, where the position spreads are small next to the Gaussians, the three agree closely
    (BENCHMARKS.md, "The expected render"). It costs one render (its per-view peak factor needs
    no second projection: ``render._blur_log_peak``). Training
    decisions (densify, prune, spawn) keep using ``posterior_mean``: they concern the parameters, not a
    render. ``tables_grad``: as for ``sample``. ``constants``: ``expected_constants`` of the current tables
    (variant "ours" with ``tables_grad=False`` only; ignored otherwise or when they no longer ``fit``); the sample
    then holds the SH as the table's two tensors (``GaussianSample.sh_rest``), for a training step's render.
    """
    if (constants is not None and variant == "ours" and not tables_grad and model.num_carriers > 0
            and constants.fits(model)):
        p = model.params
        degree = model.sh_degree if sh_degree is None else min(sh_degree, model.sh_degree)
        # the SH as the table's two tensors (GaussianSample.sh_rest): a training step renders them uncopied
        means, scales, opacities = _with_constants(p, constants.offset, constants.scale_factor, constants.gate)
        return GaussianSample(means=means, quats=p["quats"], scales=scales, opacities=opacities,
                              sh=p["sh0"], sh_rest=p["shN"], sh_degree=degree,
                              position_var=constants.position_var)
    pm = posterior_mean(model, variant=variant, extent=extent, temperature=temperature, sh_degree=sh_degree,
                        tables_grad=tables_grad)
    if model.num_carriers == 0:
        return pm
    t = _tables(model, tables_grad)
    idx = model.carrier_index()
    sigma2 = _position_variance(t, variant, extent)  # [P]
    width = _multiplier_width(t)  # [P,3]
    second = _scale_second_moment(model.params["scales"][idx], t["scale_left"].mean(1), width, variant)  # [P,3]
    scales = pm.scales.index_copy(0, idx, second.sqrt().to(pm.scales.dtype))
    var = torch.zeros_like(pm.opacities).index_copy(0, idx, sigma2.to(pm.opacities.dtype))  # [N]
    return GaussianSample(means=pm.means, quats=pm.quats, scales=scales, opacities=pm.opacities, sh=pm.sh,
                          sh_degree=pm.sh_degree, position_var=var)


def mean_params(model: GaussianModel, *, variant: Variant = "ours", extent: float = 1.0,
                temperature: float = 0.2) -> dict[str, Tensor]:
    """The posterior mean as stored-style parameters [N,...] (means, log-scales, opacity logits, SH, quats),
    detached: what ``uncertainty.curvature.fisher_diagonal`` differentiates the render against."""
    with torch.no_grad():
        pm = posterior_mean(model, variant=variant, extent=extent, temperature=temperature)
        o = pm.opacities.clamp(1e-6, 1.0 - 1e-6)
        p = model.params
        return {"means": pm.means.detach(), "scales": torch.log(pm.scales).detach(),
                "opacities": torch.log(o / (1.0 - o)).detach(), "quats": p["quats"].detach(),
                "sh0": p["sh0"].detach(), "shN": p["shN"].detach()}


def normal_quantile(p: Tensor) -> Tensor:
    """Phi^-1(p), accurate in the tails (p down to 1e-38 in float32)."""
    return torch.special.ndtri(p)


def _posterior_variance(fisher: Tensor, prior_var: Tensor, disagreement: Tensor | None) -> Tensor:
    """Laplace variance ``1 / prec`` (prec = F + 1 / prior_var); with the views' disagreement D, the sandwich
    variance ``1 / prec + (D - F)_+ / prec^2``, at most the prior's (``informed_tables``)."""
    prec = fisher + 1.0 / prior_var
    if disagreement is None:
        return 1.0 / prec
    return torch.minimum(1.0 / prec + (disagreement - fisher).clamp_min(0.0) / prec.square(), prior_var)


@torch.no_grad()
def informed_tables(model: GaussianModel, fisher: dict[str, Tensor], prior: Prior, *, extent: float = 1.0,
                    position_prior_scale: float = 1.0, disagreement: dict[str, Tensor] | None = None,
                    camera_centers: Tensor | None = None, position_depth_fraction: float = 0.1) -> dict:
    """Set every carrier's table to the posterior that the training views' curvature implies (in place).

    ``fisher``: the diagonal Fisher information of the training views w.r.t. the posterior mean's
    ``means`` [N,3], ``scales`` (log) [N,3] and ``opacities`` (logit) [N] (``mean_params`` +
    ``uncertainty.curvature.fisher_diagonal``). For a Gaussian posterior and a likelihood expanded to second
    order around the mean, the evidence lower bound is maximised by the Laplace precision, prior precision plus
    Fisher: ``1 / var = 1 / prior_var + F``. So a parameter no view constrains keeps the prior's spread and a
    well-observed one gets the data's. Per carrier (all K entries get the same values):

    * position: the prior std is the larger of ``prior.position_std`` x extent and ``position_prior_scale``
      x the carrier's own size (geometric mean of its axes): before any data, a Gaussian is located to
      within its footprint. Posterior std per axis ``(F + 1 / prior_std^2)^-1/2``; location 0 (the mean is
      the base position; a location the tables held is folded into it). With ``camera_centers`` [T,3] (the
      training cameras) the prior std is at most ``position_depth_fraction`` x the carrier's distance to the
      nearest of them: the Fisher is the curvature at the mean, and for a Gaussian as large as its distance to
      the cameras (a background blob of a real capture) it is nearly 0, so its own size alone would let a sample
      move it by its depth, in front of a camera, where it covers the whole view; moved by 10 % of its depth, its
      footprint changes by about 10 %.
    * scale multiplier U[l, l + w]: the log-scale prior variance is the prior interval's,
      ``(w_p / m)^2 / 12`` with m = 1 - w_p / 2 its mean; the posterior width matches the Laplace variance,
      ``w = m sqrt(12 var)``, centred on m.
    * gate: switching a Gaussian off changes the render by ``-dr/da / (1 - o)`` (a pixel is linear in one
      Gaussian's opacity o; a is its logit), which lowers the log-likelihood by ``dL = F_a / (2 (1 - o)^2)``.
      The posterior odds of "off" are the prior's times ``exp(-dL)``; the gate keeps the prior's spread tau
      and gets the location ``nu = -tau Phi^-1(P_off)``, so that P(gate < 1/2) = P_off. Unseen Gaussians keep
      the prior's switch-off probability; those the data need are (almost) never switched off.

    ``disagreement`` (``uncertainty.curvature.curvature``; optional): how much the training views
    disagree about ``means`` and ``scales``. With it the position and log-scale variances are the sandwich's,
    ``1 / prec + (D - F)_+ / prec^2`` (prec = F + prior precision), at most the prior's: equal to the Laplace
    variance when the views disagree only as the pixel noise predicts, wider where the model cannot fit them all.

    The posterior-mean render is preserved: base opacity and scale absorb the change of the expected gate
    and of the mean multiplier, and the base position the old location.

    Returns:
        plain numbers for ``train_summary.json``: carriers, the fraction whose position variance is below half
        the prior's (``data_dominated``), and the median switch-off probability.
    """
    idx = model.carrier_index()
    P = idx.numel()
    if P == 0:
        return {"carriers": 0, "data_dominated": None, "gate_off_median": None}
    if prior.variant != "ours":
        raise ValueError("informed tables are defined for variant 'ours' (linear scale multiplier)")
    t = model.tables
    p = model.params
    unit = _unit(prior.variant, extent)
    before = posterior_mean(model, variant=prior.variant, extent=extent, temperature=prior.temperature)
    old_opacity = before.opacities[idx]  # [P] effective opacity (base x expected gate)
    old_mult = t["scale_left"].mean(1) + 0.5 * _multiplier_width(t)

    # position
    prior_std = _position_prior_std(before.means[idx], before.scales[idx], prior, unit=unit,
                                    position_prior_scale=position_prior_scale, camera_centers=camera_centers,
                                    position_depth_fraction=position_depth_fraction)  # [P] world units
    dis = disagreement or {}
    var = _posterior_variance(fisher["means"][idx], prior_std[:, None].square(),
                              dis["means"][idx] if "means" in dis else None)  # [P,3]
    p["means"].data.index_add_(0, idx, t["pos_loc"].mean(1) * unit)
    t["pos_loc"].data.zero_()
    sigma = (var.sqrt() / unit).clamp_min(1e-12)
    t["pos_spread_raw"].data.copy_(inverse_softplus(sigma)[:, None, :].expand_as(t["pos_spread_raw"]))

    # scale multiplier
    m = prior.scale_mean
    prior_var = (prior.scale_width / m) ** 2 / 12.0
    var_s = _posterior_variance(fisher["scales"][idx], torch.tensor(prior_var, device=idx.device),
                                dis["scales"][idx] if "scales" in dis else None)  # [P,3]
    width = (m * (12.0 * var_s).sqrt()).clamp(MIN_WIDTH, MAX_WIDTH)
    t["scale_width_raw"].data.copy_(inverse_softplus(width)[:, None, :].expand_as(t["scale_width_raw"]))
    t["scale_left"].data.copy_((m - 0.5 * width)[:, None, :].expand_as(t["scale_left"]))
    new_mult = m  # the multiplier's mean, l + w/2
    p["scales"].data.index_add_(0, idx, torch.log(old_mult / new_mult))

    # gate
    tau = torch.tensor(prior.gate_std, device=idx.device)
    p0 = gate_off_probability(torch.tensor(prior.gate_mean, device=idx.device), tau).clamp(1e-6, 1 - 1e-6)
    drop = fisher["opacities"][idx] / (2.0 * (1.0 - old_opacity).clamp_min(1e-3).square())  # [P] nats
    logit_off = (torch.log(p0) - torch.log1p(-p0) - drop).clamp_min(-80.0)
    p_off = torch.sigmoid(logit_off)
    nu = -prior.gate_std * normal_quantile(p_off)
    t["gate_spread_raw"].data.fill_(inverse_softplus(prior.gate_std))
    t["gate_loc"].data.copy_(nu[:, None, None].expand_as(t["gate_loc"]))
    gate = expected_gate(nu, tau.expand_as(nu), prior.temperature)  # [P]
    p["opacities"].data.index_copy_(0, idx, absorbed_opacity_logit(old_opacity, gate).to(p["opacities"].dtype))
    data_dominated = (var.mean(1) < 0.5 * prior_std.square()).float().mean()
    return {"carriers": P, "data_dominated": float(data_dominated), "gate_off_median": float(p_off.median())}


def gaussian_kl(loc: Tensor, spread_raw: Tensor, prior_loc: float, prior_std: float | Tensor) -> Tensor:
    """Elementwise KL(N(loc, softplus(spread_raw)^2) || N(prior_loc, prior_std^2)), finite at extremes
    (``prior_std`` a number or a tensor that broadcasts against ``loc``)."""
    std = F.softplus(spread_raw)
    log_std = log_softplus(spread_raw)
    log_prior = torch.log(prior_std) if isinstance(prior_std, Tensor) else math.log(prior_std)
    return log_prior - log_std + (std.square() + (loc - prior_loc).square()) / (2.0 * prior_std**2) - 0.5


def scale_kl(left: Tensor, width_raw: Tensor, prior_width: float, variant: Variant) -> Tensor:
    """Elementwise scale-multiplier divergence (see the module docstring for why not the true KL)."""
    width = clamp_width(F.softplus(width_raw))
    if variant == "paper":
        return (left - (1.0 - prior_width)).abs() + (left + width - 1.0).abs()
    # moment-matched Gaussians: N(l + w/2, w^2/12) against N(1 - w_p/2, w_p^2/12)
    dm = (left + 0.5 * width) - mean_multiplier(prior_width)
    return math.log(prior_width) - torch.log(width) + (width.square() + 12.0 * dm.square()) / (2.0 * prior_width**2) - 0.5


def kl_terms(model: GaussianModel, prior: Prior) -> dict[str, Tensor]:
    """KL terms averaged over table elements: ``position``, ``scale``, ``gate`` and their sum ``total``.

    All are 0-dim tensors; with no carriers they are exact zeros (no NaN from an empty mean). On CPU
    (float32) the fused native kernel computes each term and its gradient in one pass over the table
    (``uncertsplat.native``); ``gaussian_kl`` and ``scale_kl`` are the reference and the path elsewhere.
    """
    from uncertsplat import native

    t = model.tables
    if model.num_carriers == 0:
        z = t["pos_loc"].sum() * 0.0  # keeps the graph (and the device) without a NaN
        return {"position": z, "scale": z, "gate": z, "total": z}
    if native.use_for(*t.values(), dtypes=(torch.float32,), strict=False):
        kl_pos = _fused_kl("gaussian", t["pos_loc"], t["pos_spread_raw"], 0.0, prior.position_std)
        kl_scale = _fused_kl("scale", t["scale_left"], t["scale_width_raw"], prior.scale_width,
                             0 if prior.variant == "ours" else 1)
        kl_gate = _fused_kl("gaussian", t["gate_loc"], t["gate_spread_raw"], prior.gate_mean, prior.gate_std)
    else:
        kl_pos = gaussian_kl(t["pos_loc"], t["pos_spread_raw"], 0.0, prior.position_std).mean()
        kl_scale = scale_kl(t["scale_left"], t["scale_width_raw"], prior.scale_width, prior.variant).mean()
        kl_gate = gaussian_kl(t["gate_loc"], t["gate_spread_raw"], prior.gate_mean, prior.gate_std).mean()
    return {"position": kl_pos, "scale": kl_scale, "gate": kl_gate, "total": kl_pos + kl_scale + kl_gate}


def _fused_kl(kind: str, loc: Tensor, raw: Tensor, a: float, b: float) -> Tensor:
    """Mean of one KL term by the native kernel (see ``_native_kl``); the gradient is computed in the
    same pass, only when it is needed."""
    want = torch.is_grad_enabled() and (loc.requires_grad or raw.requires_grad)
    return _FusedKL.apply(loc, raw, kind, a, b, want)


def _native_kl(kind: str, loc: Tensor, raw: Tensor, a: float, b: float, want_grad: bool
               ) -> tuple[Tensor, Tensor | None, Tensor | None]:
    """(mean, d mean-sum / d loc, d sum / d raw) of one KL term by the native kernel: ``gaussian`` (prior
    mean a, std b) or ``scale`` (w_p = a, variant b: 0 ours, 1 paper). The gradients are of the *sum*
    over elements (callers divide by ``loc.numel()``), None unless ``want_grad``."""
    from uncertsplat import native

    lib = native.library()
    loc, raw = loc.detach().contiguous(), raw.detach().contiguous()
    g_loc = torch.empty_like(loc) if want_grad else None
    g_raw = torch.empty_like(raw) if want_grad else None
    ptrs = (g_loc.data_ptr(), g_raw.data_ptr()) if want_grad else (None, None)
    threads = native.kernel_threads()
    if kind == "gaussian":
        total = lib.us_gaussian_kl_f32(loc.numel(), loc.data_ptr(), raw.data_ptr(), a, b, *ptrs, threads)
    else:
        total = lib.us_scale_kl_f32(loc.numel(), loc.data_ptr(), raw.data_ptr(), a, int(b), MIN_WIDTH, MAX_WIDTH,
                                    *ptrs, threads)
    return loc.new_tensor(total / loc.numel()), g_loc, g_raw


class _FusedKL(torch.autograd.Function):
    @staticmethod
    def forward(ctx, loc: Tensor, raw: Tensor, kind: str, a: float, b: float, want_grad: bool) -> Tensor:
        value, g_loc, g_raw = _native_kl(kind, loc, raw, a, b, want_grad)
        if want_grad:
            ctx.save_for_backward(g_loc, g_raw)
        ctx.n = loc.numel()
        return value

    @staticmethod
    def backward(ctx, grad: Tensor):
        g_loc, g_raw = ctx.saved_tensors
        scale = grad / ctx.n
        return g_loc * scale, g_raw * scale, None, None, None, None


def carrier_uncertainty(model: GaussianModel, *, variant: Variant = "ours", extent: float = 1.0) -> dict[str, Tensor]:
    """Per-Gaussian [N] posterior spreads (0 for non-carriers), all K entries averaged.

    ``position``: RMS position std over the 3 axes in world units; ``scale``: mean multiplier width;
    ``gate``: gate-logit std; ``switch_off``: the chance that a posterior sample switches the Gaussian (mostly) off
    (``gate_off_probability`` of the entries' mean, ``prune``'s ``gate`` score).
    """
    n = len(model)
    dev = model.device
    out = {k: torch.zeros(n, device=dev) for k in ("position", "scale", "gate", "switch_off")}
    idx = model.carrier_index()
    if idx.numel() == 0:
        return out
    t = _tables(model, grad=False)
    sig = F.softplus(t["pos_spread_raw"].mean(1)) * _unit(variant, extent)
    out["position"][idx] = sig.square().mean(1).sqrt()
    out["scale"][idx] = _multiplier_width(t).mean(1)
    out["gate"][idx] = F.softplus(t["gate_spread_raw"].mean(1))[:, 0]
    out["switch_off"][idx] = gate_off_probability(t["gate_loc"].mean(1)[:, 0], out["gate"][idx])
    return out


def _position_prior_std(means: Tensor, scales: Tensor, prior: Prior, *, unit: float, position_prior_scale: float,
                        camera_centers: Tensor | None, position_depth_fraction: float) -> Tensor:
    """The informed posterior's position prior std per carrier, world units [P] (``informed_tables``: the larger
    of the config's and the carrier's own size, at most a fraction of its distance to the nearest camera).
    ``means`` [P,3], ``scales`` [P,3]: the carriers' posterior-mean positions and sizes."""
    own = scales.log().mean(1).exp()  # [P] geometric-mean size, world units
    prior_std = torch.clamp(position_prior_scale * own, min=prior.position_std * unit)  # [P]
    if camera_centers is not None and camera_centers.shape[0]:
        depth = torch.cdist(means.double(), camera_centers.to(means.device).double()).amin(1)  # [P]
        prior_std = torch.minimum(prior_std, (position_depth_fraction * depth).to(prior_std.dtype))
    return prior_std


@torch.no_grad()
def informed_position_prior(model: GaussianModel, prior: Prior, *, extent: float = 1.0,
                            position_prior_scale: float = 1.0, camera_centers: Tensor | None = None,
                            position_depth_fraction: float = 0.1) -> Tensor:
    """The position prior std the informed posterior gives each carrier, in table units [P] (the unit
    ``posterior_summary`` measures the tables in): the same arguments as ``informed_tables``, evaluated at the
    model's current posterior mean (which an informed update leaves unchanged, so right after the update it is the
    prior the update used)."""
    idx = model.carrier_index()
    unit = _unit(prior.variant, extent)
    mean = posterior_mean(model, variant=prior.variant, extent=extent, temperature=prior.temperature)
    return _position_prior_std(mean.means[idx], mean.scales[idx], prior, unit=unit,
                               position_prior_scale=position_prior_scale, camera_centers=camera_centers,
                               position_depth_fraction=position_depth_fraction) / unit


def gate_off_probability(loc: Tensor, spread: Tensor) -> Tensor:
    """P(gate < 1/2) = P(nu + tau eta < 0) = Phi(-nu / tau) for a gate logit N(nu, tau^2) (``spread`` = tau > 0).

    The chance that a posterior sample switches the Gaussian (mostly) off; in [0, 1], elementwise.
    """
    return 0.5 * torch.erfc((loc / spread.clamp_min(1e-12)) / math.sqrt(2.0))


MOVED_KL_NATS = 0.01
"""A carrier's posterior counts as moved from the prior when its KL exceeds this (nats, per table entry):
about what a 10 % change of one spread costs (KL(N(0, 0.9^2) || N(0, 1)) = 0.0104)."""


@torch.no_grad()
def posterior_summary(model: GaussianModel, prior: Prior, *, position_prior_std: Tensor | None = None) -> dict:
    """How far the learned posteriors are from the prior: a diagnostic of what the data taught the tables.

    A carrier whose posterior still equals the prior carries no information from the data, so its
    per-Gaussian scores (``uncertainty.scores``) say nothing about it; the rendered uncertainty then comes
    from the prior's noise propagated through the rendering. Per carrier (all K entries, as
    ``posterior_mean`` averages them for the ratios):

    * ``kl_nats``: KL of the carrier's table from the prior, summed over its 14 columns and averaged over
      its K entries (the same terms as the training loss: closed-form Gaussian KL for position and gate,
      the variant's scale term); ``moved_fraction``: carriers with ``kl_nats > MOVED_KL_NATS``.
    * ``position_spread_ratio``: posterior position std / prior std (geometric mean over the 3 axes).
    * ``scale_width_ratio``: multiplier interval width / w_p (mean over the axes).
    * ``gate_off``: P(gate < 1/2) = Phi(-nu / tau), and ``gate_off_prior``, the prior's value.

    ``position_prior_std`` [P] (table units; ``informed_position_prior``): the informed posterior's prior, which
    is per carrier (a Gaussian is located to within its own size before any data); the position KL and spread
    ratio are then measured against it (``position_prior`` "per_carrier"), not against the config's single std
    ("config"), which a carrier larger than it would exceed (ratios above 1 that read as a posterior wider than
    its prior).

    Distributions are given as quantiles ``q10``, ``q50``, ``q90``. Returns plain Python numbers (JSON);
    with no carriers every distribution is None.
    """
    t = {k: v.detach().float() for k, v in model.tables.items()}
    p = model.num_carriers
    gate_off_prior = float(gate_off_probability(torch.tensor(prior.gate_mean), torch.tensor(prior.gate_std)))
    out: dict = {"carriers": p, "moved_kl_nats": MOVED_KL_NATS, "gate_off_prior": gate_off_prior,
                 "position_prior": "config" if position_prior_std is None else "per_carrier"}
    keys = ("kl_nats", "position_spread_ratio", "scale_width_ratio", "gate_off")
    if p == 0:
        return {**out, "moved_fraction": None, **{k: None for k in keys}}
    if position_prior_std is None:
        pos_std: float | Tensor = prior.position_std
    else:
        if position_prior_std.shape != (p,):
            raise ValueError(f"position_prior_std has shape {tuple(position_prior_std.shape)}, expected ({p},), one "
                             "std per carrier")
        pos_std = position_prior_std.detach().float().to(t["pos_loc"].device)
    pos_std_t = pos_std[:, None, None] if isinstance(pos_std, Tensor) else pos_std  # broadcasts over [P,K,3]
    kl = (gaussian_kl(t["pos_loc"], t["pos_spread_raw"], 0.0, pos_std_t).sum(2)
          + scale_kl(t["scale_left"], t["scale_width_raw"], prior.scale_width, prior.variant).sum(2)
          + gaussian_kl(t["gate_loc"], t["gate_spread_raw"], prior.gate_mean, prior.gate_std).sum(2)).mean(1)  # [P]
    m = {k: v.mean(1) for k, v in t.items()}  # [P,D]
    spread = log_softplus(m["pos_spread_raw"]).mean(1).exp() / pos_std
    width = F.softplus(m["scale_width_raw"]).clamp(MIN_WIDTH, MAX_WIDTH).mean(1) / prior.scale_width
    gate_off = gate_off_probability(m["gate_loc"][:, 0], F.softplus(m["gate_spread_raw"])[:, 0])
    q = torch.tensor([0.1, 0.5, 0.9], device=kl.device)

    def quantiles(x: Tensor) -> dict[str, float]:
        # torch.quantile refuses more than 2^24 elements; a seeded subsample is exact enough for a summary
        if x.numel() > 1_000_000:
            x = x[torch.randperm(x.numel(), generator=torch.Generator().manual_seed(0))[:1_000_000].to(x.device)]
        v = torch.quantile(x.float(), q).tolist()
        return {"q10": v[0], "q50": v[1], "q90": v[2]}

    return {**out, "moved_fraction": float((kl > MOVED_KL_NATS).float().mean()),
            "kl_nats": quantiles(kl), "position_spread_ratio": quantiles(spread),
            "scale_width_ratio": quantiles(width), "gate_off": quantiles(gate_off)}


def describe_posterior(post: dict, update: dict | None = None) -> str:
    """One line on how far the learned posteriors are from the prior, from a ``posterior_summary`` dict and,
    for the informed posterior, its last update record (``informed_tables`` plus step and noise; printed by
    ``train``, shown in the report)."""
    pos, gate = post["position_spread_ratio"], post["gate_off"]
    if update is not None and update.get("data_dominated") is not None:
        return (f"posterior (informed, step {update['step']}): {100 * update['data_dominated']:.1f} % of "
                f"{update['carriers']} carriers are set by the data (position variance below half the prior's), the "
                f"rest by the prior; median switch-off probability {100 * update['gate_off_median']:.2f} % (prior "
                f"{100 * post['gate_off_prior']:.1f} %, kept where no view needs the Gaussian); likelihood noise "
                f"{update['noise_std']:.4f} (RMS training residual)")
    line = (f"posterior: {100 * post['moved_fraction']:.1f} % of {post['carriers']} carriers moved from the prior "
            f"(KL > {post['moved_kl_nats']} nats); position spread x{pos['q10']:.3f}-{pos['q90']:.3f} of the prior, "
            f"gate-off {100 * gate['q10']:.1f}-{100 * gate['q90']:.1f} % (prior {100 * post['gate_off_prior']:.1f} %), "
            "10th-90th percentile")
    if post["moved_fraction"] < 0.05:
        line += ("; the posteriors are still close to the prior, so per-Gaussian scores carry little from the data "
                 "(docs/guide.md: 'What the uncertainty is')")
    return line


def random_model(n: int, generator: torch.Generator, *, sh_degree: int = 1, num_entries: int = 10,
                 carrier_fraction: float = 0.5, extent: float = 1.0, prior: Prior | None = None,
                 perturb_tables: float = 0.0, device=None) -> GaussianModel:
    """A random model (for tests and examples): Gaussians in a cube of side ``extent``, a random subset
    of carriers with tables at the prior plus ``perturb_tables`` x N(0,1) noise (in raw units)."""
    prior = prior or Prior()
    device = device if device is not None else generator.device

    def randn(*shape):
        return torch.randn(shape, generator=generator, device=generator.device).to(device)

    def rand(*shape):
        return torch.rand(shape, generator=generator, device=generator.device).to(device)

    b = (sh_degree + 1) ** 2
    params = {
        "means": (rand(n, 3) - 0.5) * extent,
        "scales": torch.log(extent * (0.005 + 0.05 * rand(n, 3))),
        "quats": randn(n, 4),
        "opacities": randn(n),
        "sh0": randn(n, 1, 3) * 0.5,
        "shN": randn(n, b - 1, 3) * 0.1,
    }
    carriers = rand(n) < carrier_fraction
    c = int(carriers.sum())
    tables = prior_rows(c, num_entries, prior, device=device)
    if perturb_tables > 0:
        tables = {k: v + perturb_tables * randn(*v.shape) for k, v in tables.items()}
    row = torch.full((n,), -1, dtype=torch.long, device=device)
    # table rows in a shuffled order, so tests do not rely on rows following Gaussian order
    perm = torch.randperm(c, generator=generator, device=generator.device).to(device)
    row[carriers] = perm
    return GaussianModel(params, tables, row, sh_degree, num_entries)
