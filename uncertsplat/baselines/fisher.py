"""Post-hoc Laplace/Fisher baseline (in the spirit of FisherRF) on a trained deterministic 3DGS model.

Likelihood: every training pixel channel is Gaussian around the render, ``gt ~ N(rgb(theta), s^2)``.
Its Fisher information w.r.t. the per-Gaussian parameters theta (means, log-scales, opacity logits and
SH DC colour by default) is ``F = J^T J / s^2`` with J the Jacobian of the rendered pixels. We keep its
diagonal, estimated per training view in one of two ways (``FisherConfig.estimator``):

* ``"ggn"`` (default): ``diag(J^T J) = E_z[(J^T z)^2]`` over Rademacher vectors z (+-1 per pixel
  channel): one backward pass per probe gives an unbiased estimate of the exact diagonal;
* ``"empirical"``: the squared gradient of the view's loss ``sum (rgb - gt)^2 / (2 s^2)``, i.e.
  ``(J^T r)^2 / s^4``. It is what "squared gradients of the photometric loss" usually means, but it
  vanishes where the fit is perfect (r = 0), so well-fit parameters get the prior's variance; kept to
  measure that difference.

The Laplace posterior is ``N(theta_hat, diag(1 / (F + 1 / prior_std^2)))`` per parameter element; the
observation noise ``s`` is the RMS training residual unless given. ``evaluate`` draws its K samples as
``theta_hat + sqrt(var) * eps`` (``perturbed_sample``), rendering RGB and depth uncertainty.

Run folder: a normal deterministic run (``method = "fisher"`` in ``config.json``) plus ``fisher.pt``
(``{"variance": {name: [N,...]}, "fisher": {...}, "noise_std", "estimator", ...}``).
"""

from __future__ import annotations

import io
import time
from dataclasses import dataclass, field, fields
from pathlib import Path

import torch
from torch import Tensor

from uncertsplat.baselines.runs import LoadedRun, load_single_model
from uncertsplat.console import console, q
from uncertsplat.errors import UserError
from uncertsplat.eval.engine import Sampler
from uncertsplat.schemas import TrainSummary
from uncertsplat.types import GaussianSample
from uncertsplat.uncertainty.curvature import activate as _activate
from uncertsplat.uncertainty.curvature import curvature, fisher_diagonal, residual_noise_std

__all__ = ["FISHER_FILE", "FisherRun", "compute_fisher", "fisher_diagonal", "load_fisher", "perturbed_sample",
           "posterior_variance", "residual_noise_std", "train_fisher"]

FISHER_FILE = "fisher.pt"
PARAM_ORDER = ("means", "scales", "opacities", "sh0")
"""Perturbed parameters, in the order their noise is drawn."""


def posterior_variance(fisher: dict[str, Tensor], prior_std: dict[str, float]) -> dict[str, Tensor]:
    """Laplace posterior variance per element: ``1 / (fisher + 1 / prior_std^2)``."""
    return {n: 1.0 / (f + 1.0 / prior_std[n] ** 2) for n, f in fisher.items()}


def perturbed_sample(params: dict[str, Tensor], variance: dict[str, Tensor], generator: torch.Generator, *,
                     sh_degree: int) -> GaussianSample:
    """One Laplace-posterior sample ``theta + sqrt(var) * eps`` (noise drawn in ``PARAM_ORDER``)."""
    delta = {}
    for name in PARAM_ORDER:
        if name in variance:
            v = variance[name]
            eps = torch.randn(v.shape, generator=generator, device=generator.device).to(v.device, v.dtype)
            delta[name] = v.sqrt() * eps
    return _activate(params, sh_degree, delta)


def prior_stds(fcfg, extent: float) -> dict[str, float]:
    """Prior std per parameter from a ``FisherConfig`` (means relative to the scene extent)."""
    return {"means": fcfg.prior_std_means * extent, "scales": fcfg.prior_std_scales,
            "opacities": fcfg.prior_std_opacities, "sh0": fcfg.prior_std_sh0}


def ply_uncertainty(variance: dict[str, Tensor], n: int) -> dict[str, Tensor]:
    """``point_cloud.ply``'s uncertainty properties [N] from the Laplace posterior ``variance`` (name -> [N,...]), in
    the variational model's terms (``gaussians.variational.carrier_uncertainty``): ``position`` the RMS position std
    over the axes (run units), ``scale`` the RMS std of the log-scales (the width of a size multiplier, to first
    order), ``gate`` the std of the opacity logit (the gate logit's counterpart); ``switch_off`` 0 (no gate to switch
    off); ``has_posterior`` 1 for every Gaussian (each has a variance). A parameter without a variance gives 0."""
    def rms(name: str) -> Tensor:
        v = variance.get(name)
        return torch.zeros(n) if v is None else v.detach().cpu().double().reshape(n, -1).mean(1).sqrt().float()

    return {"uncertainty_position": rms("means"), "uncertainty_scale": rms("scales"),
            "uncertainty_gate": rms("opacities"), "uncertainty_switch_off": torch.zeros(n),
            "has_posterior": torch.ones(n)}


def compute_fisher(run_dir: Path, device: torch.device, seed: int = 0) -> dict:
    """Estimate the Laplace posterior of the trained deterministic model in ``run_dir`` and write ``fisher.pt``.

    Returns the stored dict (variances, Fisher diagonals, noise std, timings).
    """
    from uncertsplat.data.dataset import load_images
    from uncertsplat.io.atomic import atomic_write_bytes

    run_dir = Path(run_dir)
    loaded = load_single_model(run_dir, device)  # the trained model: its posterior does not exist yet
    fcfg = loaded.config.fisher
    data = loaded.load_scene()
    idx = list(data.split["train"])
    cams = data.cameras[idx].to(device)
    images = load_images(data, idx, device)
    masks = loaded.training_masks(data, idx, device)  # [T,H,W,1]: the pixels training fitted
    exposure = loaded.photo_exposure()
    if exposure is not None:  # the photos at the model's exposure, as training compared them
        images = exposure.unexposed_images(idx, images)
    render_fn = loaded.render_fn(data.scene_scale, device)  # as in training

    params = {k: v.detach() for k, v in loaded.model.params.items()}
    t0 = time.perf_counter()
    given = None if fcfg.noise_std == "auto" else float(fcfg.noise_std)
    gen = torch.Generator(device=device).manual_seed(seed)
    names = tuple(n for n in PARAM_ORDER if n in fcfg.params)
    if fcfg.estimator == "ggn":  # the noise (when "auto") and the curvature from one render per view
        curv = curvature(params, cams, images, render_fn, names=names, generator=gen, sh_degree=loaded.sh_degree,
                         probes=fcfg.probes, noise_std=given, masks=masks)
        noise, fisher = curv.noise_std, curv.fisher
    else:  # the empirical Fisher's pass needs the noise first
        noise = given if given is not None else residual_noise_std(params, cams, images, render_fn,
                                                                   sh_degree=loaded.sh_degree, masks=masks)
        fisher = fisher_diagonal(params, cams, images, render_fn, names=names, noise_std=noise, generator=gen,
                                 sh_degree=loaded.sh_degree, estimator="empirical", probes=fcfg.probes,
                                 masks=masks)
    var = posterior_variance(fisher, prior_stds(fcfg, loaded.extent))
    seconds = time.perf_counter() - t0
    state = {
        "variance": {k: v.cpu() for k, v in var.items()},
        "fisher": {k: v.cpu() for k, v in fisher.items()},
        "noise_std": noise, "estimator": fcfg.estimator, "probes": fcfg.probes, "num_views": len(idx),
        "num_gaussians": len(loaded.model), "seconds": seconds,
        "means_checksum": float(params["means"].double().sum()),
    }
    buf = io.BytesIO()
    torch.save(state, buf)
    atomic_write_bytes(run_dir / FISHER_FILE, buf.getvalue())
    return state


def train_fisher(scene: Path, run_dir: Path, cfg, device: torch.device, resume: bool = False,
                 on_trainer=None) -> Path:
    """Train a deterministic model (``method = "fisher"`` trains like ``deterministic``), then ``compute_fisher``.

    ``train_summary.json`` gets ``train_seconds`` (the training loop), ``fisher_seconds`` and ``seconds``
    (their sum: the method's whole cost).
    """
    from uncertsplat.train.session import train_model

    run_dir = Path(run_dir)
    summary_path = run_dir / "train_summary.json"
    if not (resume and summary_path.is_file()):
        train_model(scene, run_dir, cfg, device=device, resume=resume, on_trainer=on_trainer)
    summary = TrainSummary.read(summary_path)
    if resume and (run_dir / FISHER_FILE).is_file() and summary.fisher_seconds is not None:
        return run_dir
    console.print(f"[bold]fisher[/]: estimating the Laplace posterior ({cfg.fisher.estimator}) over the training views")
    state = compute_fisher(run_dir, device, seed=cfg.seed)
    # the viewer PLY carries the posterior's spreads, as a variational run's does (they were 0: read as certain)
    from uncertsplat.io.ply import set_vertex_properties

    n = int(state["num_gaussians"])
    set_vertex_properties(run_dir / "point_cloud.ply",
                          {k: v.numpy() for k, v in ply_uncertainty(state["variance"], n).items()})
    if summary.train_seconds is None:  # a second Fisher pass (resume) must not add the first one's time
        summary.train_seconds = summary.seconds
    summary.fisher_seconds = float(state["seconds"])
    summary.seconds = summary.train_seconds + summary.fisher_seconds
    summary.fisher_noise_std = float(state["noise_std"])
    summary.write(summary_path)
    console.print(f"done: Fisher diagonal over {state['num_views']} views in {state['seconds']:.1f} s "
                  f"(noise std {state['noise_std']:.4f}) -> {run_dir / FISHER_FILE}")
    return run_dir


@dataclass
class FisherRun(LoadedRun):
    """A loaded deterministic model plus its Laplace posterior variances (name -> [N,...])."""

    variance: dict = field(default_factory=dict)
    noise_std: float = 0.0

    def sampler(self, scene_scale: float, device: torch.device) -> Sampler:
        """Laplace-posterior samples (``fisher_sample_fn``); no deterministic render of its own."""
        from uncertsplat.gaussians.variational import posterior_mean

        with torch.no_grad():
            mean = posterior_mean(self.model, **self.sample_kwargs)
        return Sampler(fisher_sample_fn(self), self.render_fn(scene_scale, device), empty_std=self.empty_std(),
                       coverage=self.coverage(scene_scale, device, mean), mean_sample=mean,
                       exposure=self.photo_exposure())

    def _method_notes(self, num_samples: int) -> list[str]:
        fcfg = self.config.fisher
        return [f"fisher: Laplace posterior ({fcfg.estimator} diagonal Fisher, observation noise std "
                f"{self.noise_std:.4g}) sampled by perturbing {', '.join(sorted(self.variance))}"]


def load_fisher(base: LoadedRun) -> FisherRun:
    """A fisher run: its trained model ``base`` plus ``fisher.pt``, checking that the variances belong to the
    model (``runs.load_run`` calls it)."""
    run_dir = base.run_dir
    device = base.model.device
    path = run_dir / FISHER_FILE
    if not path.is_file():
        raise UserError(f"{FISHER_FILE} is missing: the Fisher posterior was never computed", path=run_dir,
                        hint=f"Finish it with: uncertsplat train SCENE -o {q(run_dir)} --method fisher --resume")
    try:
        state = torch.load(path, map_location=torch.device(device), weights_only=True)
    except Exception as err:  # a truncated or foreign file
        raise UserError(f"cannot read {FISHER_FILE} ({type(err).__name__}: {err})", path=path,
                        hint="Delete it and run train --method fisher --resume to recompute it.") from None
    n = len(base.model)
    if int(state["num_gaussians"]) != n or any(v.shape[0] != n for v in state["variance"].values()):
        raise UserError(f"{FISHER_FILE} was computed for {state['num_gaussians']} Gaussians, the model has {n}",
                        path=path, hint="Delete it and run train --method fisher --resume to recompute it.")
    return FisherRun(**{f.name: getattr(base, f.name) for f in fields(LoadedRun) if f.init}, variance=state["variance"],
                     noise_std=float(state["noise_std"]))


def fisher_sample_fn(loaded: FisherRun):
    """``sample_fn(generator)`` drawing Laplace-posterior samples of a ``FisherRun``."""
    params = {k: v.detach() for k, v in loaded.model.params.items()}
    variance = {k: v.to(params["means"].device) for k, v in loaded.variance.items()}

    def sample_fn(generator: torch.Generator) -> GaussianSample:
        return perturbed_sample(params, variance, generator, sh_degree=loaded.sh_degree)

    return sample_fn
