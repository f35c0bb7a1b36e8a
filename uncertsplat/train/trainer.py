"""The training loop: variational multi-scale 3DGS with full-state checkpoints.

One step: pick the next training view (a shuffled queue, refilled when empty), form the Gaussians to render (the
informed posterior: the posterior mean or expected render, or a sample, by ``variational.train_on``; the SGD
posterior: one posterior sample with its KL, ``variational.sample_with_kl``; the plain parameters for
``method="deterministic"``), render, loss = L1/SSIM (+ kl_weight x KL for the SGD posterior), backward, Adam
update, accumulate screen-space gradients, then the topology changes due at this step (densify / prune / opacity
reset / spawn), deciding on the posterior mean, and the informed posterior's update when due.

Everything that influences the future is in ``state_dict()``: parameters, offset tables, posterior rows,
Adam moments, densification statistics, the generators' states (views, noise, drop, background), the view queue,
the step and the elapsed time. A ``Trainer`` built with that ``state`` continues exactly as if never
interrupted (bit-identical on CPU).
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import operator
import resource
import signal
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import torch
from torch import Tensor

from uncertsplat import native
from uncertsplat.config import TrainConfig
from uncertsplat.console import progress
from uncertsplat.eval.image import masked_ssim, psnr, ssim
from uncertsplat.gaussians.ops import remove as remove_rows
from uncertsplat.gaussians.ops import spawn, truncate_sh
from uncertsplat.gaussians.params import (
    GaussianModel,
    far_points,
    init_from_points,
    memory_per_gaussian,
    memory_per_new_gaussian,
)
from uncertsplat.gaussians.prior import Prior
from uncertsplat.gaussians.variational import (
    ExpectedConstants,
    absorbed_opacity_logit,
    expected_constants,
    expected_gate,
    expected_render_sample,
    informed_position_prior,
    informed_tables,
    mean_params,
    normal_quantile,
    posterior_mean,
    posterior_summary,
    sample,
    sample_with_kl,
)
from uncertsplat.io.images import area_resize
from uncertsplat.render import near_plane, render
from uncertsplat.render.exposure import centred, expose, exposure_record, fitted_gain, unexpose
from uncertsplat.render.project import point_depths, points_in_view
from uncertsplat.schemas.base import finite_or_none
from uncertsplat.schemas.runs import RunExposure
from uncertsplat.strategy.budget import (
    GROWN_GAUSSIAN_FACTOR,
    gaussian_budget,
    memory_growth_limit,
    memory_hold_warning,
)
from uncertsplat.strategy.densify import Densifier, DensifyStats, spawn_decisions
from uncertsplat.strategy.exposure import EXPOSURE_SPREAD, ExposureCheck, exposure_check_due, gain_spread
from uncertsplat.strategy.growth import (
    UNTOLD_DB,
    GrowthCheck,
    at_budget,
    growth_check_due,
    halving_cost_db,
    skipped,
    skips_next,
    weakest_half,
)
from uncertsplat.strategy.schedule import (
    SETTLE_FRACTION,
    densify_end,
    is_densify_step,
    is_opacity_reset_step,
    sh_degree_at,
)
from uncertsplat.strategy.sh_bands import BandCheck, band_gain_db, check_due
from uncertsplat.strategy.view_checks import check_views, gain_db, sum_squared_error
from uncertsplat.train.adam import Adam, all_finite
from uncertsplat.train.losses import SsimTargetCache, total_loss
from uncertsplat.train.optim import base_rates, load_optimizer_state, make_optimizer, set_rates
from uncertsplat.train.profile import PhaseTimer
from uncertsplat.train.transients import EVERYWHERE_SHARE, MIN_PHOTOS, pack_mask, transient_masks, unpack_mask
from uncertsplat.types import Cameras, GaussianSample, Photos, SceneData
from uncertsplat.uncertainty.curvature import curvature
from uncertsplat.uncertainty.scores import blending_weights

STATE_VERSION = 1
MAX_BAD_STEPS = 5
"""Consecutive steps with a NaN/Inf loss or gradient (each skipped) after which training stops."""


def prior_from_config(cfg: TrainConfig) -> Prior:
    v = cfg.variational
    return Prior(position_std=v.position_prior_std, scale_width=v.scale_prior_width, gate_mean=v.gate_prior_mean,
                 gate_std=v.gate_prior_std, temperature=v.gate_temperature, variant=cfg.variant)


def peak_memory_mb(device: torch.device) -> float:
    """Peak accelerator memory (CUDA) or peak resident memory of the process (CPU), in MiB, since the process began
    or the last ``reset_peak_memory``."""
    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) / 2**20
    from uncertsplat.io.memory import process_status

    hwm = process_status().get("VmHWM")  # Linux's high-water mark, which reset_peak_memory can lower
    if hwm is not None:
        return hwm / 2**20
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # (never goes down) Linux reports KiB


def reset_peak_memory(device: torch.device) -> None:
    """Start ``peak_memory_mb`` over from the memory in use now: a sweep's points trained one after another in one
    process each reported the peak of every point before it (a 1,000-Gaussian point 482 MB, 430 MB alone)."""
    device = torch.device(device)  # (a sweep job's may be its name)
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
        return
    try:  # (Linux: resets the process's VmHWM to its current RSS)
        with open("/proc/self/clear_refs", "w", encoding="ascii") as f:
            f.write("5")
    except OSError:
        pass


def _same_sample(a: GaussianSample, b: GaussianSample) -> bool:
    """Whether two samples are the same Gaussians to the bit (every tensor field equal, the same SH degree)."""
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, Tensor) or isinstance(y, Tensor):
            if not (isinstance(x, Tensor) and isinstance(y, Tensor) and x.shape == y.shape and x.dtype == y.dtype
                    and x.device == y.device and torch.equal(x, y)):
                return False
        elif x != y:
            return False
    return True


class TrainingInterrupted(Exception):
    """Raised after a checkpoint was written because of Ctrl-C / SIGTERM."""

    def __init__(self, step: int, path: Path | None):
        self.step, self.path = step, path
        super().__init__(f"training interrupted at step {step}" + (f"; checkpoint {path}" if path else ""))


def training_near_plane(scene: SceneData) -> float:
    """The near plane a run on ``scene`` renders with (``render.near_plane``, from the sparse points' depths in the
    training views; 1 % of the rig radius without points); ``RUN/scene.json`` records it for the other stages."""
    train = list(scene.split.get("train", ()))
    depths = point_depths(scene.points, scene.cameras[train]) if scene.points.shape[0] and train else None
    return near_plane(scene.scene_scale, depths)


STOP_REQUESTED = threading.Event()
"""Set by another thread of this process to stop a training as Ctrl-C does (the step finishes, a checkpoint is
written, then ``TrainingInterrupted``): a sweep's worker sets it when the sweep stops (a second SIGINT would have
acted at once, mid-step, after the terminal's first)."""

FEW_CARRIERS = 0.1
"""Below this share of a variational model's Gaussians carrying a posterior, ``few_carriers_warning`` says why (the
demo and tiny scenes: 98-100 %)."""


def first_spawn_step(cfg: TrainConfig) -> int:
    """The first step at which Gaussians get a posterior (the first multiple of ``densify.spawn_interval`` after
    ``densify.start``: ``schedule.is_spawn_step``)."""
    d = cfg.densify
    return (d.start // d.spawn_interval + 1) * d.spawn_interval


def first_split_step(cfg: TrainConfig) -> int:
    """The first densification step of ``cfg``'s schedule (the first multiple of ``densify.interval`` after
    ``densify.start``: ``schedule.is_densify_step``), where the children of split Gaussians first carry a posterior,
    if it comes before densification ends."""
    d = cfg.densify
    return (d.start // d.interval + 1) * d.interval


def _earliest_posterior_step(cfg: TrainConfig, iterations: int) -> int | None:
    """The first step of a run of ``iterations`` steps at which some Gaussian may get a posterior: its first
    densification step (split children carry one; ``schedule.is_densify_step``) or its first spawn step
    (``schedule.is_spawn_step``), whichever comes first within the run; None when neither does."""
    d = cfg.densify
    split, spawn = first_split_step(cfg), first_spawn_step(cfg)
    steps = [s for s, ok in ((split, split < densify_end(d, iterations)), (spawn, spawn <= d.until))
             if ok and s <= iterations]
    return min(steps) if steps else None


def posterior_steps_needed(cfg: TrainConfig) -> int | None:
    """The fewest steps a run of ``cfg``'s settings needs for some Gaussian to get a posterior
    (``_earliest_posterior_step``; a run's last ``SETTLE_FRACTION`` never densifies, so a split step needs a run
    somewhat longer than it); None when no run length gives one (densification has no step before
    ``densify.until`` and no spawn step comes up to it)."""
    d = cfg.densify
    split, spawn = first_split_step(cfg), first_spawn_step(cfg)
    found = []
    if split < d.until:  # the fewest n with split < densify_end (the settle rule), checked against rounding
        n = max(split, math.floor((split - 1) / (1.0 - SETTLE_FRACTION)) + 1)
        while not split < densify_end(d, n):  # (monotone in n: ends; a first spawn step earlier never enters here)
            n += 1
        while n > split and split < densify_end(d, n - 1):
            n -= 1
        found.append(n)
    if spawn <= d.until:
        found.append(spawn)
    return min(found) if found else None


def no_carriers_reason(cfg: TrainConfig, step: int, planned: bool = False) -> str | None:
    """Why a model of ``cfg`` trained to ``step`` has no Gaussian with a posterior when that follows from its
    settings, with what to do; None when it may have some (a spawn step was reached: a scene whose Gaussians are
    narrower than the spawn rule asks, ``few_carriers_warning``). Gaussians get a posterior as the children of a
    split (from the first densification step) and at the spawn steps, which come only while densification runs
    (``densify.until``). ``planned``: said before training, of a run of ``step`` steps, where a split may yet come
    (None then once one can); else said of a model that has no carrier, whose splits therefore made none. None for
    a model given by ``init_ply``: the spawn rule gave its carriers at the start, whatever the run's steps (0), so
    only ``densify.spawn_scale_fraction`` decides (``few_carriers_warning``)."""
    if cfg.init_ply is not None:  # (its steps and schedule say nothing: --iterations N is refused with init_ply)
        return None
    d = cfg.densify
    needed = posterior_steps_needed(cfg)
    if needed is None and d.start >= cfg.iterations:  # (raising until would not help a run that ends first)
        return (f"densification starts at step {d.start} (densify.start), after the run's {cfg.iterations} steps, so "
                "no Gaussian gets a posterior: lower densify.start below the run's length"
                + (f", with densify.until past the first densification step after it (densify.until is {d.until})"
                   if d.until <= d.start else ""))
    if needed is None:
        fix = min(first_split_step(cfg) + 1, first_spawn_step(cfg))
        return (f"densification has no step before densify.until = {d.until} (the first would be step "
                f"{first_split_step(cfg)}) and no spawn step comes by then (the first would be step "
                f"{first_spawn_step(cfg)}), so no Gaussian gets a posterior whatever the run's length: set "
                f"densify.until to {fix} or more for one")
    earliest = _earliest_posterior_step(cfg, cfg.iterations)
    if earliest is None:
        return (f"the run's {cfg.iterations} steps end before Gaussians first get a posterior (split children from "
                f"the first densification step, spawned ones from the first spawn step; a run's last "
                f"{SETTLE_FRACTION:.0%} never densifies): give it --iterations {needed} or more for a posterior")
    if step < earliest:
        return (f"the run stopped at step {step}, before Gaussians first get a posterior (step {earliest}): train it "
                f"on to that step (`train --resume`, or `--iterations N` with N >= {max(needed, earliest)}) for a "
                "posterior")
    spawn = first_spawn_step(cfg)
    if not planned and spawn <= d.until and step < spawn:
        # said of a model without carriers: its densification steps split none (none grew, or the model was at its
        # budget from the start), and its first spawn step did not come
        end = "stopped at" if step < cfg.iterations else "ended at"
        return (f"no densification step split a Gaussian (split children carry a posterior: none grew, or the model "
                f"was at its budget, densify.max_gaussians), and the run {end} step {step}, before its first spawn "
                f"step ({spawn}): train it on past that step (`train --resume --iterations N`, N >= "
                f"{max(spawn, needed)}) for a posterior")
    return None


def few_carriers_warning(model: GaussianModel, cfg: TrainConfig, extent: float, prior: Prior,
                         step: int) -> list[str]:
    """The warning for a model with offset tables whose Gaussians mostly carry no posterior (their uncertainty is
    0): the spawn rule gives one to a Gaussian wider than ``densify.spawn_scale_fraction`` of the cameras' radius,
    which the Gaussians of a small scene seen from far (a long lens, a rig far larger than the scene) never are;
    names a fraction that gives one to about half of them. Where the settings decide it (densification off, or a
    run stopped before its first densification or spawn step: ``no_carriers_reason``), that reason, only when no
    Gaussian carries one."""
    n = len(model)
    d = cfg.densify
    if not cfg.has_offset_tables or n == 0 or model.num_carriers >= FEW_CARRIERS * n:
        return []
    reason = no_carriers_reason(cfg, step)
    if reason is not None:  # what the settings decide: said only where nothing carries one (a short test run)
        return [f"no Gaussian carries a posterior, so the uncertainty is only the predictive's other terms: {reason}"
                ] if model.num_carriers == 0 else []
    with torch.no_grad():
        pm = posterior_mean(model, variant=prior.variant, extent=extent, temperature=prior.temperature)
        width = pm.scales.norm(dim=-1)[pm.opacities >= d.spawn_min_opacity] / extent  # [M]
    if width.numel() == 0:
        return []
    median = float(width.median())
    digit = 10.0 ** math.floor(math.log10(0.9 * median))  # rounded down to one digit: below the median, never above
    suggested = math.floor(0.9 * median / digit) * digit
    few = f"only {model.num_carriers:,} of the {n:,} Gaussians carry a posterior (the others' uncertainty is 0)"
    if suggested >= d.spawn_scale_fraction:  # they grew past it after the last spawn step: a smaller one is no cure
        return [f"{few}, though most are wider than densify.spawn_scale_fraction = {d.spawn_scale_fraction:g} of the "
                f"cameras' radius (median {median:.2g}): they grew after the last spawn step (densify.until = "
                f"{d.until}); a later densify.until lets them carry one"]
    return [f"{few}: a Gaussian gets one when wider than densify.spawn_scale_fraction = {d.spawn_scale_fraction:g} "
            f"of the cameras' radius, and this scene's are smaller (median {median:.2g}: a small scene seen from far, "
            f"or a long lens); --set densify.spawn_scale_fraction={suggested:.1g} gives one to at least half of them"]


WIDE_VIEW_DEGREES = 150.0
"""Above this field of view (either image axis) ``wide_view_notes`` says the splatting is inexact at the edges."""


def wide_view_notes(cameras: Cameras) -> list[str]:
    """A note when a training camera sees more than ``WIDE_VIEW_DEGREES`` across: each Gaussian is projected by its
    local linearisation, which stretches it at the edges of so wide a view (the tiny scene at 169 degrees: 16.2 dB
    held out, at 137 degrees 22.9)."""
    K = cameras.K.double().cpu()
    fov_x = 2 * torch.atan(cameras.width / (2 * K[:, 0, 0])).rad2deg()
    fov_y = 2 * torch.atan(cameras.height / (2 * K[:, 1, 1])).rad2deg()
    widest = float(torch.maximum(fov_x, fov_y).max()) if len(cameras) else 0.0
    if widest <= WIDE_VIEW_DEGREES:
        return []
    return [f"a training camera sees {widest:.0f} degrees across: splatting projects each Gaussian by its local "
            "linearisation, which stretches it towards the edges of so wide a view (fisheye photos: undistort them "
            "to narrower pinhole views, e.g. reconstruct's undistortion)"]


FEW_POINTS = 100
"""Below this many initial points ``few_points_notes`` says the model starts from little (a sparse model that
registered but triangulated almost nothing, or points edited away)."""


def few_points_notes(points: Tensor, cameras: Cameras, init_num_random: int) -> list[str]:
    """A note when the model starts from fewer than ``FEW_POINTS`` points ([N,3], training frame) and how many of them
    any of the training ``cameras`` sees (in front of it and inside its image): growth from a handful is slow, and
    from points no view sees it cannot start."""
    n = points.shape[0]
    if n >= FEW_POINTS:
        return []
    seen = points_in_view(points, cameras).any(0)  # [N]
    more = "; --set init_num_random=10000 adds random points to grow from" if init_num_random == 0 else ""
    return [f"the model starts from only {n} point(s), {int(seen.sum())} of them in view of a training camera: it "
            f"grows slowly from so few{more}"]


class _Unexposed:
    """Training photos [T,H,W,3] at the model's exposure, each brought there as it is indexed (``unexpose`` of
    ``photos[index]``, the same numbers as unexposing all and indexing: the operation is per pixel); what
    ``Trainer.photos()`` gives for all photos with exposures on, to readers that index it one view at a time."""

    def __init__(self, photos: Tensor | Photos, gain: Tensor, offset: Tensor):
        self.photos, self.gain, self.offset = photos, gain, offset  # [T,H,W,3], [T,3], [T,3]

    def __len__(self) -> int:
        return len(self.photos)

    def __getitem__(self, index) -> Tensor:
        if isinstance(index, (slice, list, tuple, Tensor)):
            return unexpose(self.photos[index], self.gain[index], self.offset[index])
        i = operator.index(index) % len(self)  # one view [H,W,3] (negative counts from the end), as a batch of one
        return unexpose(self.photos[i:i + 1], self.gain[i:i + 1], self.offset[i:i + 1])[0]

    @property
    def shape(self) -> torch.Size:
        return self.photos.shape

    @property
    def device(self) -> torch.device:
        return self.photos.device


def _finite_or_null(value):
    """``value`` (a stats record: numbers, text, lists and dicts of them) with every non-finite float as None."""
    if isinstance(value, dict):
        return {k: _finite_or_null(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite_or_null(v) for v in value]
    return finite_or_none(value)


LONG_UPDATE_PIXELS = 8_000_000
"""The last posterior update is said before it runs where its training views hold more pixels than this together (it
runs inside the last step, for tens of seconds on large captures)."""


def _diverged_hint(changed: list[str], rates: str, saved: bool, run_dir: Path | None) -> str:
    """What to do after a training diverged: set back the settings of the fit the run changed from their defaults
    (``changed``; a helper's learning rates of 1e30 were told to lower lr.means_init), else lower the learning rates
    (``rates``); --resume where a checkpoint was ``saved`` (with the stored settings: those that diverged)."""
    first = (f"Train again into a new folder (-o NEW_RUN) with the settings this run changed from their defaults "
             f"({', '.join(changed)}) set back or nearer them" if changed else
             f"Train again into a new folder (-o NEW_RUN) with lower learning rates (--set {rates}), or check the "
             "input images")
    if saved:
        rest = "; --resume goes on from the last good checkpoint with this run's own settings" + (
            " (those that diverged)" if changed else "")
    else:  # (train starts a folder with no checkpoint again: session._never_trained)
        rest = (f"; with no checkpoint written, the same command with the new settings starts {run_dir} again (or "
                "delete it)" if run_dir is not None else "")
    return first + rest + "."


class Trainer:
    """Trains a ``GaussianModel`` on one scene.

    Args:
        scene: the scene (cameras, split, sparse points, extent).
        cfg: resolved training configuration.
        train_images: [T,H,W,3] images of ``scene.split["train"]``, in that order, on the training device: float32,
            or ``Photos`` (``data.dataset.load_photos``: 8-bit photos kept as uint8, each converted where it is used).
        test_images: [V,H,W,3] images of ``scene.split["test"]`` (held-out PSNR), or None; as ``train_images``.
        run_dir: where checkpoints and ``stats.jsonl`` go (None: nothing is written).
        state: a ``state_dict()`` to resume from (None: initialise from the scene's points).
        near: the near plane (None: ``training_near_plane`` of ``scene``; ``train`` passes what ``scene.json``
            records, so that a resumed model keeps the plane it was trained with).
        train_masks: [T,H,W,1] bool, the pixels of the training photos that count (``SceneData.masks_train``: the
            masks a user brought), or None for every pixel. The others are set to 0 in ``train_images`` (in place)
            and in each render before the loss, so that nothing of them reaches the loss, not even through SSIM's
            windows across a mask's edge; nor the posterior's noise and curvature, the exposure fit or the checks.
        test_masks: [V,H,W,1] bool, likewise for the held-out PSNR and SSIM (``test_images`` set to 0 outside), or
            None.
    """

    def __init__(self, scene: SceneData, cfg: TrainConfig, train_images: Tensor | Photos,
                 test_images: Tensor | Photos | None = None,
                 run_dir: Path | None = None, state: dict | None = None, near: float | None = None,
                 train_masks: Tensor | None = None, test_masks: Tensor | None = None, *,
                 _fork_of: Trainer | None = None):
        self.scene, self.cfg = scene, cfg
        # ``_fork_of``: the training a ``GrowthCopy`` copies, whose photos and their derived arrays it shares
        self.device = train_images.device
        self.train_idx = list(scene.split["train"])
        self.test_idx = list(scene.split.get("test", ()))
        self.train_cams = scene.cameras[self.train_idx].to(self.device)
        self.test_cams = scene.cameras[self.test_idx].to(self.device) if self.test_idx else None
        self.train_images, self.test_images = train_images, test_images
        if train_images.shape[0] != len(self.train_idx):
            raise ValueError("train_images must have one image per training view")
        self.train_masks, self.test_masks = train_masks, test_masks
        for images, masks in ((train_images, train_masks), (test_images, test_masks)):
            if masks is not None and _fork_of is None:  # (a fork's photos are its parent's, zeroed already)
                if images is None or masks.shape != (*images.shape[:3], 1):
                    raise ValueError("masks must be [C,H,W,1], one per image")
                (images.data if isinstance(images, Photos) else images).masked_fill_(~masks.expand(images.shape), 0)
        self.low_masks = None
        # the low-resolution phase's images and cameras (cfg.low_res_fraction), area-averaged once
        self.low_res_until = int(cfg.low_res_fraction * cfg.iterations)
        self.low_cams = self.low_images = None
        if _fork_of is not None:
            self.low_cams, self.low_images, self.low_masks = _fork_of.low_cams, _fork_of.low_images, _fork_of.low_masks
        elif self.low_res_until > 0 and cfg.low_res_scale < 1.0:
            self.low_cams = self.train_cams.scaled(cfg.low_res_scale)
            h, w = self.low_cams.height, self.low_cams.width
            self.low_images = torch.empty((len(self.train_idx), h, w, 3), dtype=torch.float32, device=self.device)
            for i in range(len(self.train_idx)):  # one photo at a time: uint8 photos are never all float at once
                self.low_images[i] = area_resize(train_images[i:i + 1].permute(0, 3, 1, 2), h, w)[0].permute(1, 2, 0)
            if train_masks is not None:  # a low pixel counts only where every pixel under it does
                self.low_masks = area_resize(train_masks.permute(0, 3, 1, 2).float(), h, w).permute(0, 2, 3, 1) \
                    >= 1.0 - 1e-6  # [T,h,w,1]
                self.low_images.masked_fill_(~self.low_masks.expand(self.low_images.shape), 0)
        self.run_dir = Path(run_dir) if run_dir is not None else None
        self.extent = float(scene.extent)
        self.prior = prior_from_config(cfg)
        self.background = torch.tensor(cfg.scene.background, dtype=torch.float32, device=self.device)
        # training renders over a random colour (cfg.random_background), unless the images' background is data
        self.random_background = cfg.random_background and not bool(scene.source.get("transparent", False))
        self.near = near if near is not None else training_near_plane(scene)
        self.variational = cfg.method == "variational"
        self.informed = self.variational and cfg.posterior == "informed"
        self.posterior_updates: list[dict] = []  # one record per informed-posterior update (kept in checkpoints)
        self.timer = PhaseTimer(self.device, cfg.profile)  # seconds per phase of this process's steps
        # the photos' own SSIM statistics, blurred once instead of every step (the same loss to the bit)
        self.ssim_cache = SsimTargetCache(int(cfg.ssim_cache_mb * 2**20)) if _fork_of is None else _fork_of.ssim_cache
        # the table terms of the expected render while the tables stay fixed (dropped whenever the tables or
        # the topology may have changed: posterior updates, densification, growth and SH-band checks)
        self._expected: ExpectedConstants | None = None
        self.init_notes: list[str] = []  # what train prints about the model it starts from (``_init_fresh``)
        # a stop skipped the test renders of the step it came in (``fit``): the resume renders and logs them first
        self.eval_pending = False
        # the held-out test of a step that resets the opacities, rendered before the reset (``train_step``): after
        # it every Gaussian is nearly transparent and the test read 5-8 dB, a collapse in the log and the report's
        # curve that training recovers from within a few hundred steps
        self._test_before_reset: dict[str, float] | None = None
        self._test_seconds = 0.0  # its renders' time, which ``fit`` keeps out of the training time as every test's
        # the test ``fit`` rendered at the step it trained to (step, the deterministic Gaussians it rendered, result):
        # ``evaluate`` of the same step and the same Gaussians returns it instead of rendering every held-out view
        # again (train's summary asked for it right after fit, doubling the final test's time)
        self._final_test: tuple[int, GaussianSample, dict[str, float]] | None = None
        self._fit_until: int | None = None  # the step ``fit`` trains to (it tests the model there); None outside fit
        self.skipped_steps = 0  # steps whose update was skipped because of a NaN/Inf loss or gradient
        self.bad_steps_in_a_row = 0
        # each training view's pixels that count after its last full-resolution step found transient objects in it
        # (cfg.transients; position in the training views -> its [H,W,1] bool mask packed a bit per pixel on the CPU
        # (transients.pack_mask), absent where the last test found none)
        self.transient_keep: dict[int, Tensor] = {}
        # the first step that tests for them: fixed by the run's first iterations once passed (``_load_state``)
        self.transients_from = int(cfg.transients.start * cfg.iterations)
        # {"step", "photos", "of"} when the test switched itself off (regions in nearly every photo after a pass over
        # them: parts of the scene the model cannot fit, not transients; ``_drop_transients``), else None
        self.transients_stopped: dict[str, int] | None = None
        # {"step", "last_step", "gaussians", "budget", "room_mb", "per_gaussian_bytes", "held"} once memory held
        # densification's growth below the budget (``_memory_limit``; the first hold's numbers), else None
        self.memory_hold: dict | None = None
        # the model trained elsewhere that the run started from (cfg.init_ply: ``train.imported``'s record), else None
        self.imported: dict | None = None
        if state is None:
            self._init_fresh()
        else:
            self._load_state(state)
        # growth is held by this training's own peaks (``_memory_room``), not those of what ran before it in this
        # process (an ensemble's earlier member, a sweep's earlier point, a pipeline's earlier stage: a later one
        # was held at its first size by them); the process's peak before is kept for the summary (``peak_mb``)
        self._peak_before_mb = peak_memory_mb(self.device)
        self._size_peak_before = None  # (the process's largest size before: ``room_beyond_peak``)
        if _fork_of is None:  # (a growth test's copy leaves its parent's peaks alone: its memory is the parent's)
            if self.device.type == "cpu":
                from uncertsplat.io.memory import process_size_peak, release_free_memory

                release_free_memory()
                self._size_peak_before = process_size_peak()
            reset_peak_memory(self.device)
        self._hold_said = False  # (the first hold of this process is said when it happens)
        self.on_log: Callable[[dict], None] | None = None
        # called after every step with the trainer (``train --view`` draws the model here, between steps, so it
        # never sees a half-updated model); its time is not in ``elapsed``
        self.on_step: Callable[[Trainer], None] | None = None
        self._bar = None  # (the progress bar and its task while ``fit`` runs: the last posterior update writes to it)
        self.on_band: Callable[[BandCheck], None] | None = None  # told of each SH band test (``train`` prints it)
        self.on_growth: Callable[[GrowthCheck], None] | None = None  # told of each growth test (likewise)
        self.on_exposure: Callable[[ExposureCheck], None] | None = None  # told of each exposure test (likewise)
        self._stop = False

    # ----------------------------------------------------------------------------------- state
    def _init_fresh(self) -> None:
        cfg = self.cfg
        self.gen_views = torch.Generator().manual_seed(cfg.seed)
        self.gen_noise = torch.Generator(device=self.device).manual_seed(cfg.seed + 1)
        self.gen_drop = torch.Generator(device=self.device).manual_seed(cfg.seed + 3)
        self.gen_background = torch.Generator(device=self.device).manual_seed(cfg.seed + 4)
        if cfg.init_ply is not None:
            self._init_imported()
        else:
            self._init_from_points()
        self.optimizer = make_optimizer(self.model, self._rates(0), sparse=cfg.sparse_updates)
        self.densifier = self._make_densifier()
        self.view_queue: list[int] = []
        self.sh_bands: list[BandCheck] = []
        self.growth: list[GrowthCheck] = []
        self.step = 0
        self.elapsed = 0.0
        self.exposure_checks: list[ExposureCheck] = []
        self._init_exposure(None)

    def _init_imported(self) -> None:
        """The model of ``cfg.init_ply`` (``train.imported``), its large Gaussians given a posterior by the spawn
        rule, each rendering as in the file (the posterior mean absorbs the prior's gate and multiplier)."""
        from uncertsplat.train.imported import model_from_ply, refine_frame

        cfg = self.cfg
        views = check_views(len(self.train_idx), 8)

        def refine(p: dict[str, Tensor], degree: int) -> tuple[Tensor, float, float]:
            # a frame found on the sparse points, fitted to 8 training photos (its first guess renders pixels off);
            # the photos as they are (an imported run learns no exposures: config refuses them)
            masks = self._train_masks(views)
            return refine_frame({k: t.to(self.device) for k, t in p.items()}, degree, self.train_cams[views],
                                lambda k: self.train_images[[views[k]]][0], lambda g, cam: self.render(g, cam).rgb,
                                extent=self.extent, mask=lambda k: None if masks is None else masks[k])

        model, notes, self.imported = model_from_ply(cfg.init_ply, self.scene, self.train_cams,
                                                     frame=cfg.init_ply_frame, transform=cfg.init_ply_transform,
                                                     device=self.device, refine=refine if views else None)
        with torch.no_grad():
            p = model.params
            opacity = torch.sigmoid(p["opacities"])  # [N] as the file renders them
            m = spawn_decisions(p["scales"].exp(), opacity, scale_fraction=cfg.densify.spawn_scale_fraction,
                                min_opacity=cfg.densify.spawn_min_opacity, extent=self.extent)
            spawn(model, None, m, self.prior, keep_render=True)
            # the prior's gate (expected 0.84) caps what a carrier's base opacity can carry: an opaque Gaussian of
            # the file would render at 0.84 and the update below would start from that. The gates start "on"
            # (switched off with probability 1e-12, as the update sets them where the views need a Gaussian) and
            # the base opacities carry the file's; the update then sets every gate from the views
            idx = model.carrier_index()
            loc = -self.prior.gate_std * float(normal_quantile(torch.tensor(1e-12, dtype=torch.float64)))
            model.tables["gate_loc"].data.fill_(loc)
            gate = expected_gate(torch.tensor(loc), torch.tensor(self.prior.gate_std), self.prior.temperature)
            p["opacities"].data[idx] = absorbed_opacity_logit(opacity[idx], gate).to(p["opacities"].dtype)
        self.model = model
        self.init_notes = notes

    def _init_from_points(self) -> None:
        cfg = self.cfg
        points = self.scene.points.to(self.device, torch.float32)
        colors = self.scene.points_rgb.to(self.device, torch.float32)
        far = far_points(points, factor=cfg.init_outlier_factor, extent=self.extent)  # [P]
        far_notes = []
        if far.any():  # before the random points' box, which such a point would stretch too
            # in the cameras' radius from their centre (the normalised frame's unit, but also without normalisation)
            centers = self.scene.cameras.centers.double()  # [C,3]
            mid = centers.mean(0)
            radius = float((centers - mid).norm(dim=-1).max()) or 1.0
            reach = float((points[far].double() - mid.to(points.device)).norm(dim=-1).max()) / radius
            far_notes.append(f"{int(far.sum()):,} of the scene's {points.shape[0]:,} sparse points lie far outside the "
                             f"rest (more than {cfg.init_outlier_factor:g}x its spread from its middle, up to "
                             f"{reach:.3g}x the cameras' radius from their centre): they "
                             "start no Gaussian, whose size and depth would come from that distance "
                             "(--set init_outlier_factor=0 keeps them)")
            points, colors = points[~far], colors[~far]
        if cfg.init_num_random > 0:
            if points.shape[0] > 0:
                lo, hi = points.amin(0), points.amax(0)
            else:
                c = self.train_cams.centers.mean(0)
                lo, hi = c - self.extent, c + self.extent
            r = torch.rand((cfg.init_num_random, 3), generator=self.gen_views).to(self.device)
            points = torch.cat([points, lo + (hi - lo) * r])
            colors = torch.cat([colors, torch.rand((cfg.init_num_random, 3), generator=self.gen_views).to(self.device)])
        if points.shape[0] == 0:
            from uncertsplat.errors import UserError

            if far_notes:  # the outlier filter took every one (a tiny init_outlier_factor): said, not "none"
                raise UserError(f"no sparse point is left to start from: {far_notes[0]}",
                                hint="Raise init_outlier_factor (or 0 to keep every point), or set init_num_random.")
            raise UserError("the scene has no sparse points to start from",
                            hint="Set init_num_random (e.g. --set init_num_random=10000).")
        self.init_notes = far_notes + few_points_notes(points, self.train_cams, cfg.init_num_random) + \
            wide_view_notes(self.train_cams)
        if self.near < near_plane(self.scene.scene_scale):
            share = 100 * self.near / self.scene.scene_scale
            self.init_notes.append(f"the near plane is at {share:.2g} % of the cameras' radius (1 % by default): the "
                                   "sparse points lie that close to the training cameras (a close-range capture, or "
                                   "a few cameras far from the rest setting the radius)")
        # the model-size limit holds from the start: a cloud above it is thinned at random (its own generator, so
        # that the runs below the limit draw what they drew before)
        cap = self._budget().max_gaussians
        if points.shape[0] > cap:
            keep = torch.randperm(points.shape[0], generator=torch.Generator().manual_seed(cfg.seed + 5))[:cap]
            keep = keep.sort().values.to(self.device)
            self.init_notes.append(f"the scene's {points.shape[0]:,} initial points are more than the model may hold "
                                   f"({cap:,} Gaussians): {cap:,} of them, chosen at random, start the model")
            points, colors = points[keep], colors[keep]
        # The informed posterior gives all entries of a carrier's table the same values (informed_tables), so it
        # stores one: a sample averages equal entries, so K copies would change nothing but the memory (K = 10:
        # 90 % of the tables). Runs trained before keep their K when resumed (the checkpoint's shapes).
        entries = 1 if self.informed else cfg.variational.num_entries
        self.model = init_from_points(points, colors, sh_degree=cfg.sh_degree,
                                      num_entries=entries, init_opacity=cfg.init_opacity,
                                      extent=self.extent)

    def _init_exposure(self, state: dict | None) -> None:
        """The per-photo exposure parameters [T,2,3] (``render.exposure``) and their optimiser, from ``state`` (a
        checkpoint's) or at the identity; None with ``exposure = "off"``. Views added since the checkpoint
        (``train --add-views``) start at the others' centre, the others keep their rows (matched by name, or by view
        index in checkpoints without names: ``_saved_views``) and, when none was added, their optimiser state."""
        self.exposure = self.exposure_optimizer = None
        saved = state.get("exposure") if state is not None else None
        if self.cfg.exposure == "off" or (self.cfg.exposure == "auto" and saved is None):
            return  # "auto": until a test switches them on (check_exposure)
        params = torch.zeros(len(self.train_idx), 2, 3, device=self.device)
        same = False
        if saved is not None:
            saved = saved.to(self.device, torch.float32)
            # by name where the checkpoint has them: photos that joined the scene since (reconstruct --extend) move
            # the others' indices
            rows = {v: r for r, v in enumerate(self._saved_views(state))}
            params[:] = saved.mean(0)  # a view the checkpoint has no row for: the others' centre
            now = self._view_keys(state)
            for r, v in enumerate(now):
                if v in rows:
                    params[r] = saved[rows[v]]
            same = list(rows) == now
        self._start_exposure(params)
        if same and state.get("exposure_optimizer") is not None:
            self.exposure_optimizer.load_state_dict(state["exposure_optimizer"])
            for group in self.exposure_optimizer.param_groups:  # the config's rate, as for the model's groups
                group["lr"] = self.cfg.exposure_lr

    def _train_names(self) -> list[str]:
        """The training views' names, in training order ([] for a scene without names)."""
        names = self.scene.cameras.image_names
        return [names[i] for i in self.train_idx] if names else []

    @staticmethod
    def _saved_views(state: dict) -> list:
        """The checkpoint's training views in its order: their names, or, in checkpoints from before they were
        kept (or without names), their indices in the scene."""
        if state.get("train_names"):
            return list(state["train_names"])
        saved = state.get("exposure_views")
        return [int(i) for i in saved.tolist()] if saved is not None else []

    def _view_keys(self, state: dict) -> list:
        """This trainer's training views, keyed as ``_saved_views(state)`` keys the checkpoint's."""
        return self._train_names() if state.get("train_names") else list(self.train_idx)

    def _start_exposure(self, params: Tensor) -> None:
        """Learn the photos' exposures from ``params`` [T,2,3] on, with a fresh optimiser."""
        self.exposure = params.requires_grad_(True)
        self.exposure_optimizer = torch.optim.Adam([self.exposure], lr=self.cfg.exposure_lr, eps=1e-15)

    def exposures(self) -> tuple[Tensor, Tensor] | None:
        """([T,3] gains, [T,3] offsets) of the training photos, centred (``render.exposure.centred``), detached;
        None with ``exposure = "off"``."""
        if self.exposure is None:
            return None
        with torch.no_grad():
            return centred(self.exposure.detach())

    def exposure_record(self, names) -> RunExposure | None:
        """The training photos' learned exposures as ``RUN/exposure.json`` holds them (``names``: the scene's image
        names, indexed by the scene's view indices); None with ``exposure = "off"``."""
        if self.exposure is None:
            return None
        return exposure_record(self.exposure, [names[i] for i in self.train_idx], self.step)

    def transient_regions(self, names) -> dict[str, Tensor]:
        """{training photo name: [H,W] bool, its pixels that count} of the photos whose last full-resolution step
        found transient objects in them (``cfg.transients``; ``names``: the scene's image names, indexed by its view
        indices), in the training views' order."""
        return {names[self.train_idx[v]]: self.transient_mask(v)[..., 0] for v in sorted(self.transient_keep)}

    def photos(self, views: list[int] | None = None) -> Tensor | Photos | _Unexposed:
        """[B,H,W,3] the training photos ``views`` (positions in the training list; None: all) at the model's
        exposure: as they are with ``exposure = "off"`` (``train_images`` itself for all), else with each photo's
        learned exposure taken out (``unexpose``). What the growth and SH-band tests, the training PSNR and the
        informed posterior compare the renders with."""
        ex = self.exposures()
        if ex is None:
            return self.train_images if views is None else self.train_images[views]
        # all: each photo unexposed as it is read (all of them at once were two float32 copies of every photo)
        unexposed = _Unexposed(self.train_images, *ex)
        return unexposed if views is None else unexposed[views]

    def state_dict(self) -> dict:
        """Everything needed to continue exactly (tensors, numbers and strings only)."""
        return {
            "version": STATE_VERSION,
            "step": self.step,
            "elapsed": self.elapsed,
            "extent": self.extent,
            "sh_degree_active": self.sh_degree,
            "config": self.cfg.model_dump_json(),
            "model": self.model.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "densify": self.densifier.stats.state_dict(),
            "gen_views": self.gen_views.get_state(),
            "gen_noise": self.gen_noise.get_state(),
            "gen_drop": self.gen_drop.get_state(),
            "gen_background": self.gen_background.get_state(),
            "view_queue": torch.tensor(self.view_queue, dtype=torch.long),
            "sh_bands": [b.model_dump() for b in self.sh_bands],
            "posterior_updates": [dict(u) for u in self.posterior_updates],
            "growth": [g.model_dump() for g in self.growth],
            "grown_to": -1 if self.densifier.grown_to is None else self.densifier.grown_to,
            "memory_hold": dict(self.memory_hold) if self.memory_hold else {},
            "imported": dict(self.imported) if self.imported else {},
            "exposure": self.exposure.detach().clone() if self.exposure is not None else None,
            "exposure_views": torch.tensor(self.train_idx, dtype=torch.long),
            "train_names": self._train_names(),
            "exposure_optimizer": self.exposure_optimizer.state_dict() if self.exposure_optimizer is not None else None,
            "exposure_checks": [c.model_dump() for c in self.exposure_checks],
            "eval_pending": self.eval_pending,
            "skipped_steps": self.skipped_steps,
            "bad_steps_in_a_row": self.bad_steps_in_a_row,
            "transients_from": self.transients_from,
            "transients_stopped": dict(self.transients_stopped) if self.transients_stopped else {},
            "transient_views": torch.tensor(sorted(self.transient_keep), dtype=torch.long),
            "transient_keep": (torch.stack([self.transient_keep[v] for v in sorted(self.transient_keep)])
                               if self.transient_keep else torch.zeros((0, 0), dtype=torch.uint8)),  # packed bits
        }

    def _restored_generator(self, state: dict, key: str, offset: int) -> torch.Generator:
        """The generator ``state[key]`` on the training device; seeded as a fresh run's (seed + ``offset``) for a
        checkpoint written before its option existed. A state another device type wrote (a CPU generator's 5056
        bytes for a CUDA one's 16: a run resumed with another --device) cannot be set: the generator is seeded
        from the state's bytes and the step instead, with a note (the run goes on, not bit for bit as it would
        have on its own device)."""
        gen = torch.Generator(device=self.device)
        if key not in state:
            gen.manual_seed(self.cfg.seed + offset)
            return gen
        saved = state[key].cpu()  # generator states are CPU byte tensors
        try:
            gen.set_state(saved)
        except RuntimeError:
            import hashlib

            digest = hashlib.sha256(saved.numpy().tobytes() + str(int(state["step"])).encode()).digest()
            gen.manual_seed(int.from_bytes(digest[:8], "little") >> 1)
            note = (f"the checkpoint's random generators were written on another device type than {self.device.type}: "
                    "they are seeded from their saved state here, so the run goes on, but not bit for bit as it "
                    "would have on the device it was trained on")
            if note not in self.init_notes:
                self.init_notes.append(note)
        return gen

    def _load_state(self, state: dict) -> None:
        if state.get("version") != STATE_VERSION:
            raise ValueError(f"unsupported trainer state version {state.get('version')}")
        self.model = GaussianModel.from_state_dict(state["model"], self.device)
        self.optimizer = make_optimizer(self.model, self._rates(int(state["step"])), sparse=self.cfg.sparse_updates)
        load_optimizer_state(self.optimizer, state["optimizer"])
        self.densifier = self._make_densifier()
        self.densifier.stats = DensifyStats.from_state_dict(state["densify"], self.device)
        self.gen_views = torch.Generator()
        self.gen_views.set_state(state["gen_views"].cpu())
        self.gen_noise = self._restored_generator(state, "gen_noise", 1)
        self.gen_drop = self._restored_generator(state, "gen_drop", 3)
        self.gen_background = self._restored_generator(state, "gen_background", 4)
        self.view_queue = [int(i) for i in state["view_queue"].tolist()]
        saved_views = self._saved_views(state)
        if saved_views and saved_views != self._view_keys(state):
            # the queue holds positions in the checkpoint's list of training views, which views joined since
            # (--add-views, or a plain --resume after one stopped before its first checkpoint): a new pass over all
            self.view_queue = []
        self.sh_bands = [BandCheck(**b) for b in state.get("sh_bands", [])]  # absent in checkpoints from before
        # the updates before the checkpoint (absent in checkpoints from before: the summary then lists this
        # process's updates only)
        self.posterior_updates = [dict(u) for u in state.get("posterior_updates", [])]
        self.growth = [GrowthCheck(**g) for g in state.get("growth", [])]  # likewise
        self.densifier.grow = not any(g.stopped for g in self.growth)
        # (absent in checkpoints from before the refill: a model stopped there only prunes)
        self.densifier.grown_to = None if int(state.get("grown_to", -1)) < 0 else int(state["grown_to"])
        self.memory_hold = dict(state.get("memory_hold") or {}) or None  # (absent in checkpoints from before)
        self.imported = dict(state.get("imported") or {}) or None  # likewise
        self.step = int(state["step"])
        self.elapsed = float(state["elapsed"])
        self.exposure_checks = [ExposureCheck(**c) for c in state.get("exposure_checks", [])]
        self.eval_pending = bool(state.get("eval_pending", False))
        self.skipped_steps = int(state.get("skipped_steps", 0))
        self.bad_steps_in_a_row = int(state.get("bad_steps_in_a_row", 0))
        self.transient_keep = {}
        if "transient_views" in state:
            # positions in the checkpoint's training views, kept by name where views joined since (--add-views)
            keys = self._view_keys(state)
            where = {key: k for k, key in enumerate(keys)}
            h, w = self.train_images.shape[1:3]
            for v, packed in zip(state["transient_views"].tolist(), state["transient_keep"], strict=True):
                key = saved_views[v] if saved_views and v < len(saved_views) else None
                if key in where and packed.numel() == (h * w + 7) // 8:
                    self.transient_keep[where[key]] = packed.cpu().clone()
        # a run extended past a low-resolution phase it finished trains on at full resolution (the phase stretches
        # with the run only while it is still in it)
        saved_cfg = json.loads(state["config"]) if isinstance(state.get("config"), str) else {}
        ended = int(float(saved_cfg.get("low_res_fraction", 0.0)) * int(saved_cfg.get("iterations", 0)))
        # (the step the checkpoint's run tests from; checkpoints without it: its config's start, of its iterations)
        began = int(state.get("transients_from", float(saved_cfg.get("transients", {}).get("start", 1.0))
                              * int(saved_cfg.get("iterations", 0))))
        self.transients_stopped = dict(state["transients_stopped"]) if state.get("transients_stopped") else None
        if self.step > began:  # a run extended after its test began keeps testing (the photos' known regions
            # would otherwise be trained on again until the start of the longer run)
            self.transients_from = min(self.transients_from, began)
        if self.step >= ended:
            self.low_res_until = min(self.low_res_until, ended)
            self.low_cams = self.low_images = self.low_masks = None  # never read again
        self._init_exposure(state)

    # -------------------------------------------------------------------------------- helpers
    def _budget(self):
        """The model-size limit: the user's, or the scene's from its training pixels (``strategy.budget``)."""
        d = self.cfg.densify
        return gaussian_budget(d.max_gaussians, d.pixels_per_gaussian, views=len(self.train_idx),
                               width=self.train_cams.width, height=self.train_cams.height)

    def peak_mb(self) -> float:
        """The process's peak memory (``peak_memory_mb``) over its training and what came before it."""
        return max(self._peak_before_mb, peak_memory_mb(self.device))

    def _memory_room(self) -> int | None:
        """Bytes training may still take on its device beyond what its steps take again at their peaks (a render's
        buffers, free between steps), and the SSIM statistics still to be kept; None where the device does not say.
        """
        if self.device.type == "cuda":
            try:
                free, _ = torch.cuda.mem_get_info(self.device)
            except RuntimeError:  # (a device or driver that does not say)
                return None
            allocated = torch.cuda.memory_allocated(self.device)
            cached = torch.cuda.memory_reserved(self.device) - allocated  # the allocator's, free to torch
            return free + cached - max(torch.cuda.max_memory_allocated(self.device) - allocated, 0)
        if self.device.type != "cpu":
            return None
        from uncertsplat.io.memory import room_beyond_peak

        room = room_beyond_peak(self._size_peak_before)
        # the SSIM statistics are kept only where a step renders one view with an SSIM term (``train_step``)
        keeps = self.cfg.batch_size == 1 and self.cfg.ssim_lambda > 0
        pending = self.ssim_cache.pending_bytes(self.train_images.shape) if keeps else 0
        return room - pending if room is not None else None

    def _memory_limit(self, step: int) -> tuple[int, int, float] | None:
        """(the most Gaussians densification may grow to at ``step`` before memory runs short, the room in bytes,
        the bytes an added Gaussian takes), or None where no growth is due or the device does not say. Growth that
        ran the process out of memory lost the run late (a capture's budget is up to ``MAX_BUDGET`` Gaussians, some
        GB): held here instead, with a warning (``_memory_held``)."""
        cfg = self.cfg.densify
        if not self.densifier.grow or not is_densify_step(step, cfg, self.cfg.iterations) \
                or len(self.model) >= self.budget.max_gaussians:
            return None
        room = self._memory_room()
        if room is None:
            return None
        # every Gaussian grown priced as a carrier where the model has posteriors (a split's children carry one)
        per = GROWN_GAUSSIAN_FACTOR * memory_per_new_gaussian(self.model, carrier=self.variational,
                                                              table_moments=not self.informed)
        return memory_growth_limit(len(self.model), room, per), room, per

    def _memory_held(self, step: int, room: int, per: float) -> None:
        """Record that memory held densification's growth at ``step`` (the first hold's numbers, the last step and
        how many were held), and say it the first time in this process (a resumed run's holds are said again)."""
        now = {"step": step, "last_step": step, "gaussians": len(self.model), "budget": self.budget.max_gaussians,
               "room_mb": round(room / 2**20, 1), "per_gaussian_bytes": round(per), "held": 1}
        if self.memory_hold is None:
            self.memory_hold = dict(now)
        else:
            self.memory_hold.update(last_step=step, held=self.memory_hold["held"] + 1)
        if not self._hold_said:
            from uncertsplat.console import console

            self._hold_said = True
            console.print(f"[yellow]warning:[/] {memory_hold_warning(now)}")

    def memory_hold_warning(self) -> str | None:
        """What ``train`` records in its warnings when memory held growth (the first hold); None when it never did."""
        return memory_hold_warning(self.memory_hold) if self.memory_hold else None

    def _make_densifier(self) -> Densifier:
        dcfg = self.cfg.densify
        self.budget = self._budget()
        dcfg = dcfg.model_copy(update={"max_gaussians": self.budget.max_gaussians})
        if not self.variational:  # plain 3DGS: densify, never spawn posteriors
            dcfg = dcfg.model_copy(update={"spawn_interval": 10**9})
        vcfg = self.cfg.variational
        return Densifier(dcfg, self.prior, self.extent, len(self.model), self.device, posteriors=self.variational,
                         iterations=self.cfg.iterations, spawn_keeps_render=self.informed and vcfg.spawn_keeps_render,
                         split_keeps_render=self.informed and vcfg.split_keeps_render)

    def _rates(self, step: int) -> dict[str, float]:
        return base_rates(self.cfg.lr, step, self.cfg.iterations, self.extent,
                          table_lr_factor=self.cfg.variational.table_lr_factor, variant=self.cfg.variant)

    @property
    def sh_degree(self) -> int:
        """Active SH degree: the schedule's, capped by the bands the model still has (``sh_min_gain_db``); a model
        trained elsewhere (``init_ply``) renders every band its file holds."""
        if self.cfg.init_ply is not None:
            return self.model.sh_degree
        return sh_degree_at(self.step, self.model.sh_degree, self.cfg.sh_degree_interval)

    @torch.no_grad()
    def check_sh_band(self, step: int) -> BandCheck | None:
        """Test the SH band due before ``step`` (``strategy.sh_bands``); drop it and those above when it does not
        pay. Returns the test, or None when none is due."""
        cfg = self.cfg
        d = check_due(step, cfg.sh_degree_interval, self.model.sh_degree, cfg.sh_min_gain_db,
                      {b.degree for b in self.sh_bands})
        if d is None:
            return None
        views = check_views(len(self.train_idx), cfg.sh_check_views)
        sample = expected_render_sample(self.model, variant=cfg.variant, extent=self.extent,
                                        temperature=self.prior.temperature, sh_degree=d)
        gain = band_gain_db(sample, d, self.train_cams[views], self.photos(views),
                            lambda g, cam: self.render(g, cam).rgb, masks=self._train_masks(views))
        # a perfect fit with the band gives +inf; JSON has no infinity
        check = BandCheck(degree=d, step=step, gain_db=round(min(gain, 1e3), 4), kept=gain >= cfg.sh_min_gain_db,
                          min_gain_db=cfg.sh_min_gain_db, views=len(views))
        if not check.kept:
            truncate_sh(self.model, self.optimizer, d - 1)
        self.sh_bands.append(check)
        if self.on_band is not None:
            self.on_band(check)
        return check

    @torch.no_grad()
    def check_growth(self, step: int) -> GrowthCheck | None:
        """Run the growth test due at ``step`` (``strategy.growth``); stop densification's growth when the weakest
        half of the model is worth less than ``densify.growth_threshold_db`` (``growth_min_gain_db``, or its default
        for ``growth_refit_steps``) at ``growth_patience`` tests in a row. Returns the test, or None (none due,
        growth already stopped, the model at its budget: ``strategy.growth.at_budget``, skipped:
        ``strategy.growth.skipped``, or a stop that came in during the copies: ``_refit_cost``)."""
        dcfg = self.cfg.densify
        if not self.densifier.grow or not growth_check_due(step, dcfg, self.cfg.iterations):
            return None
        if at_budget(len(self.model), self.budget.max_gaussians):
            return None
        if skipped(self.growth[-1] if self.growth else None, step, dcfg, self.cfg.iterations):
            return None
        views = check_views(len(self.train_idx), dcfg.growth_check_views)
        cams, images = self.train_cams[views], self.photos(views)
        g = self.mean_sample()
        masks = self._train_masks(views)  # (a Gaussian seen only where no pixel counts weighs nothing)
        with torch.enable_grad():  # the blending weights come from one backward pass per view
            weights = blending_weights(g, cams, render_fn=self.render, masks=masks)  # [N]
        off = weakest_half(weights)
        seen = int((weights > 0).sum())
        if dcfg.growth_refit_steps > 0:
            del g, weights  # (the copies below hold a model each)
            cost = self._refit_cost(step, off, views, images, masks)
            if cost is None:  # a stop asked for during the copies: no test (the step ends, its checkpoint follows)
                return None
        else:
            cost = halving_cost_db(g, off, cams, images, lambda s, cam: self.render(s, cam).rgb, masks=masks)
        threshold = dcfg.growth_threshold_db
        # the tests before this one that must also have found the half cheap (growth_patience - 1 of them)
        before = self.growth[len(self.growth) - dcfg.growth_patience + 1:] if dcfg.growth_patience > 1 else []
        cheap = cost < threshold and len(before) == dcfg.growth_patience - 1 and all(
            b.cost_db < b.min_gain_db for b in before)
        check = GrowthCheck(step=step, gaussians=len(self.model), seen=seen, cost_db=round(min(cost, UNTOLD_DB), 4),
                            min_gain_db=threshold, stopped=cheap, views=len(views),
                            refit_steps=dcfg.growth_refit_steps,
                            skip_next=skips_next(cost, dcfg))
        self.growth.append(check)
        self.densifier.grow = not check.stopped
        if check.stopped and check.refit_steps > 0:  # (the test before the re-fit only pruned after a stop)
            self.densifier.grown_to = check.gaussians
        if self.on_growth is not None:
            self.on_growth(check)
        return check

    def _refit_cost(self, step: int, off: Tensor, views: list[int], images, masks: Tensor | None) -> float | None:
        """The growth test's cost with the rest re-fitted (``densify.growth_refit_steps`` > 0): two copies of this
        training at ``step`` (``_fork``), the whole model and the model without the Gaussians in ``off`` [N], each
        train ``growth_refit_steps`` steps on the same views in the same order (the copies change nothing of this
        training); the cost is how much better the first renders the training ``views`` than the second, both
        against ``images`` [V,H,W,3] (their photos as this training sees them; ``masks`` [V,H,W,1] or None), in dB
        (``view_checks.gain_db``). +inf where a copy could not train (its loss not finite for ``MAX_BAD_STEPS``
        steps in a row) or memory was too short for one (the allocator's error): a test that cannot tell lets the
        model grow as far as the memory hold allows. (The hold reads the process's peak, which holds the last test's
        copies: growth leaves room for the next test's.) None where a stop (Ctrl-C, SIGTERM, ``STOP_REQUESTED``) came
        in during the copies' steps: they end there, and the test is not made (the copies of a large model train for
        minutes, which a stop waited for)."""
        from uncertsplat.errors import UserError, out_of_memory

        sse = []
        for remove in (None, off):
            fork = None  # (the first copy is freed before the second is made)
            try:
                fork = self._fork(step, remove)
                with torch.enable_grad():  # (the tests run under no_grad)
                    for _ in range(self.cfg.densify.growth_refit_steps):
                        if self._stop or STOP_REQUESTED.is_set():
                            return None
                        fork.train_step()
                sse.append(sum_squared_error(fork.mean_sample(), fork.train_cams[views], images,
                                             lambda s, cam, f=fork: f.render(s, cam).rgb, masks))
            except (UserError, MemoryError, RuntimeError) as err:
                # a copy that diverged, or memory too short for a copy (on the CPU torch's allocator raises a plain
                # RuntimeError, which ended the training): no decision, growth goes on inside what the hold allows
                if not isinstance(err, UserError) and out_of_memory(err, "train") is None:
                    raise
                return math.inf
        return gain_db(*sse)

    def _fork(self, step: int, remove: Tensor | None = None) -> GrowthCopy:
        """A copy of this training as it stands inside ``step`` (after the step's update, before its topology
        changes), without the Gaussians in ``remove`` [N] bool (None: all kept), for ``_refit_cost``: its
        parameters, moments and generators are copies, its photos its parent's (``GrowthCopy``: what its steps
        leave out)."""
        state = self.state_dict()
        # (the optimisers' states hold this training's own moment tensors, which loading them would share)
        state["optimizer"] = copy.deepcopy(state["optimizer"])
        state["exposure_optimizer"] = copy.deepcopy(state["exposure_optimizer"])
        state["step"], state["bad_steps_in_a_row"] = step, 0
        fork = GrowthCopy(self.scene, self.cfg, self.train_images, None, run_dir=None, state=state, near=self.near,
                          train_masks=self.train_masks, _fork_of=self)
        if remove is not None and bool(remove.any()):
            remove_rows(fork.model, fork.optimizer, remove)
            fork.densifier.stats = DensifyStats.zeros(len(fork.model), fork.model.device)
        return fork

    def touched_rows(self, radii: Tensor) -> dict[str, Tensor]:
        """Rows a step's render touched, per optimiser group: the Gaussians with a footprint in any of its views
        ([C,N] ``radii`` > 0) for the per-Gaussian tensors, and those Gaussians' offset-table rows for the tables."""
        gauss = (radii > 0).reshape(radii.shape[0], radii.shape[1], -1).any(-1).any(0).nonzero().squeeze(1)  # [R]
        table = self.model.posterior_row.index_select(0, gauss)
        table = table[table >= 0]
        return {**dict.fromkeys(self.model.params, gauss), **dict.fromkeys(self.model.tables, table)}

    def _next_view(self) -> int:
        if not self.view_queue:
            self.view_queue = torch.randperm(len(self.train_idx), generator=self.gen_views).tolist()
        return self.view_queue.pop()

    def mean_sample(self) -> GaussianSample:
        """The deterministic Gaussians at the current SH degree (what a plain render shows): the expected
        render of the posterior (``variational.expected_render_sample``)."""
        return expected_render_sample(self.model, variant=self.cfg.variant, extent=self.extent,
                              temperature=self.prior.temperature, sh_degree=self.sh_degree)

    def render(self, gaussians: GaussianSample, cams: Cameras, background: Tensor | None = None):
        """``render`` with the run's settings, over ``background`` [3] (default: ``scene.background``)."""
        return render(gaussians, cams, background=self.background if background is None else background,
                      tile_size=self.cfg.tile_size, near=self.near)

    @torch.no_grad()
    def evaluate(self, max_views: int | None = None, *, remember: bool = False) -> dict[str, float]:
        """Held-out PSNR / SSIM of the deterministic render, ``mean_sample`` (empty dict without test views).

        ``remember``: keep this test of every view (``fit``'s at the step it trains to); the next ``evaluate`` of
        every view returns it when the step and the deterministic Gaussians are the same to the bit."""
        if self.test_cams is None or self.test_images is None:
            return {}
        g = self.mean_sample()
        final, self._final_test = self._final_test, None
        if max_views is None and final is not None and final[0] == self.step and _same_sample(final[1], g):
            return dict(final[2])
        final = None  # (its copy of the Gaussians is not held while every view renders again)
        ps, ss = [], []
        n = len(self.test_idx) if max_views is None else min(max_views, len(self.test_idx))
        for i in range(n):
            out = self.render(g, self.test_cams[i])
            pred, photo = out.rgb[0].clamp(0, 1), self.test_images[i]
            m = self.test_masks[i] if self.test_masks is not None else None  # [H,W,1]
            ps.append(float(psnr(pred, photo, m)))
            ss.append(float(ssim(pred, photo)) if m is None else masked_ssim(pred, photo, m))
        result = {"psnr": sum(ps) / n, "ssim": sum(ss) / n}
        if remember and max_views is None:
            self._final_test = (self.step, g, dict(result))
        return result

    @torch.no_grad()
    def check_exposure(self, step: int) -> ExposureCheck | None:
        """Run the exposure test due after ``step`` (``exposure = "auto"``, ``strategy.exposure``); switch the
        photos' exposures on (at the identity) when their fitted gains spread by ``EXPOSURE_SPREAD`` or more.
        Returns the test, or None when none is due."""
        if not exposure_check_due(step, self.cfg, self.exposure is not None):
            return None
        gains = self.photo_gains()
        spread = gain_spread(gains)
        check = ExposureCheck(step=step, views=len(gains), gain_min=round(min(gains, default=1.0), 4),
                              gain_max=round(max(gains, default=1.0), 4), spread=round(spread, 4),
                              threshold=EXPOSURE_SPREAD, enabled=spread >= EXPOSURE_SPREAD)
        self.exposure_checks.append(check)
        if check.enabled:  # every photo at the identity
            self._start_exposure(torch.zeros(len(self.train_idx), 2, 3, device=self.device))
        if self.on_exposure is not None:
            self.on_exposure(check)
        return check

    @torch.no_grad()
    def photo_gains(self, max_views: int = 8, skip: Sequence[int] = ()) -> list[float]:
        """The gain of each of at most ``max_views`` evenly spaced training photos (at the model's exposure: after
        the learned exposures with ``exposure = "affine"``) relative to the deterministic render
        (``render.exposure.fitted_gain``): all near 1 when the photos share one exposure. ``skip``: positions in the
        training views left out (views added late, which the model has not fitted yet whatever their exposure)."""
        g = self.mean_sample()
        skip = set(skip)
        kept = [i for i in range(len(self.train_idx)) if i not in skip]
        gains = []
        for k in check_views(len(kept), max_views):
            render, photo = self.render(g, self.train_cams[kept[k]]).rgb[0], self.photos([kept[k]])[0]  # [H,W,3]
            masks = self._train_masks([kept[k]])
            if masks is not None:  # the pixels that count, [P,3]
                m = masks[0, ..., 0]
                render, photo = render[m], photo[m]
            gains.append(fitted_gain(render, photo))
        return gains

    @torch.no_grad()
    def training_psnr(self, max_views: int = 8) -> float | None:
        """Mean PSNR of the deterministic render (``mean_sample``) on at most ``max_views`` evenly spaced training
        views: how well the model fits its own photos (None without training views)."""
        chosen = check_views(len(self.train_idx), max_views)
        if not chosen:
            return None
        g = self.mean_sample()
        masks = self._train_masks(chosen)
        return sum(float(psnr(self.render(g, self.train_cams[i]).rgb[0].clamp(0, 1), self.photos([i])[0],
                              None if masks is None else masks[k]))
                   for k, i in enumerate(chosen)) / len(chosen)

    def _train_masks(self, views: Sequence[int]) -> Tensor | None:
        """[V,H,W,1] the pixels that count of training views ``views`` (positions in the training views): a user's
        masks without the transient regions last found in them (``cfg.transients``), or None for all."""
        views = list(views)
        hit = [k for k, v in enumerate(views) if v in self.transient_keep]
        if not hit and views == list(range(len(self.train_idx))):
            return self.train_masks  # (every view, nothing to take out: no copy of them all)
        masks = None if self.train_masks is None else self.train_masks[views]  # (a list index copies)
        if not hit:
            return masks
        if masks is None:
            masks = torch.ones((len(views), *self.train_images.shape[1:3], 1), dtype=torch.bool, device=self.device)
        for k in hit:
            masks[k] &= self.transient_mask(views[k])
        return masks

    def transient_mask(self, view: int) -> Tensor:
        """[H,W,1] bool, the pixels that count of training view ``view`` (a position in the training views) after
        the transient regions last found in it (every pixel where none was)."""
        h, w = self.train_images.shape[1:3]
        if view not in self.transient_keep:
            return torch.ones((h, w, 1), dtype=torch.bool, device=self.device)
        return unpack_mask(self.transient_keep[view], h, w, self.device)

    def _drop_transients(self, step: int, views: list[int], rgb: Tensor, gt: Tensor, low: bool,
                         pick) -> Tensor | None:
        """``cfg.transients``: [B,H,W,1] bool, this step's pixels that count without the transient regions its
        render shows in its photos (None: no test at this step, or none found). A full-resolution step keeps each
        view's result for the posterior and the checks (``_train_masks``)."""
        tcfg = self.cfg.transients
        if not tcfg.detect or step <= self.transients_from or self.transients_stopped is not None:
            return None
        valid = None if self.train_masks is None else (self.low_masks if low else self.train_masks)[pick]
        keep = transient_masks(rgb, gt, threshold=tcfg.threshold, window=tcfg.window, core=tcfg.core,
                               max_share=tcfg.max_share, valid=valid)  # [B,H,W,1]
        found = ~keep.flatten(1).all(1)  # [B]
        if not low:
            for k, v in enumerate(views):
                if found[k]:
                    self.transient_keep[v] = pack_mask(keep[k])
                else:
                    self.transient_keep.pop(v, None)
            t = len(self.train_idx)
            per_pass = -(-t // max(len(views), 1))  # steps for a pass over the training photos
            if (t >= MIN_PHOTOS and (step - self.transients_from) % per_pass == 0
                    and len(self.transient_keep) >= EVERYWHERE_SHARE * t):
                # passers-by are seldom in nearly every photo; what the model renders poorly in every view is (bonsai:
                # its flowers in 40 of 42 photos, -0.33 dB): stop, and train every pixel again from here on
                self.transients_stopped = {"step": step, "photos": len(self.transient_keep), "of": t}
                self.transient_keep.clear()
                return None
        return keep if bool(found.any()) else None

    # ----------------------------------------------------------------------------------- steps
    def train_step(self) -> dict[str, float]:
        """One optimisation step (plus the topology changes due); returns the loss terms. On the CPU with the
        native kernels, torch's own ops in it run on one thread (``native.single_threaded_torch``)."""
        with native.single_threaded_torch(self.device):
            return self._train_step()

    def _train_step(self) -> dict[str, float]:
        cfg = self.cfg
        step = self.step + 1
        set_rates(self.optimizer, self._rates(step))
        timer = self.timer
        if step % cfg.sh_degree_interval == 0:
            with timer("eval"):
                if self.check_sh_band(step) is not None:
                    self._expected = None
        degree = sh_degree_at(step, self.model.sh_degree, cfg.sh_degree_interval)
        with timer("data"):
            views = [self._next_view() for _ in range(min(cfg.batch_size, len(self.train_idx)))]
            # one view: a slice, which shares the image's memory (a list index copies it)
            pick = slice(views[0], views[0] + 1) if len(views) == 1 else views
            low = self.low_cams is not None and step <= self.low_res_until
            if low:
                cams, gt = self.low_cams[pick], self.low_images[pick]
            else:
                cams, gt = self.train_cams[pick], self.train_images[pick]
            gt_stats = self.ssim_cache.get((views[0], low), gt) if len(views) == 1 and cfg.ssim_lambda > 0 else None
        with timer("sample"):
            if self.informed and cfg.variational.train_on in ("expected", "mean"):
                if cfg.variant == "ours" and (self._expected is None or not self._expected.fits(self.model)):
                    self._expected = expected_constants(self.model, extent=self.extent,
                                                        temperature=self.prior.temperature)
                deterministic = expected_render_sample if cfg.variational.train_on == "expected" else posterior_mean
                g = deterministic(self.model, variant=cfg.variant, extent=self.extent,
                                  temperature=self.prior.temperature, sh_degree=degree, tables_grad=False,
                                  constants=self._expected)
                kl = None
            elif self.informed:  # the tables are set in closed form (update_posterior); the Gaussians learn here
                g = sample(self.model, self.gen_noise, subset_size=cfg.variational.subset_size, variant=cfg.variant,
                           extent=self.extent, temperature=self.prior.temperature, sh_degree=degree,
                           tables_grad=False)
                kl = None
            elif self.variational:
                g, kl = sample_with_kl(self.model, self.gen_noise, self.prior,
                                       subset_size=cfg.variational.subset_size, extent=self.extent, sh_degree=degree)
            else:
                g = posterior_mean(self.model, variant=cfg.variant, extent=self.extent,
                                   temperature=self.prior.temperature, sh_degree=degree)
                kl = None
            if cfg.drop_rate > 0.0:
                g = self._drop(g, step)
        with timer("render"):
            if self.random_background:
                out = self.render(g, cams, background=torch.rand(3, generator=self.gen_background,
                                                                  device=self.device))  # over a random colour [3]
            else:
                out = self.render(g, cams)
        with timer("loss"):
            rgb = out.rgb
            if self.exposure is not None:  # the render at each photo's exposure (render.exposure)
                gain, offset = centred(self.exposure)
                idx = torch.as_tensor(views, dtype=torch.long, device=self.device)
                rgb = expose(rgb, gain[idx], offset[idx])
            if self.train_masks is not None:  # 0 outside the mask, as the photo is there: no loss, no gradient
                rgb = rgb * (self.low_masks if low else self.train_masks)[pick]
            keep = self._drop_transients(step, views, rgb, gt, low, pick)
            if keep is not None:  # 0 on the transients in render and photo (the photo's SSIM statistics differ)
                rgb, gt, gt_stats = rgb * keep, gt * keep, None
            losses = total_loss(rgb, gt, kl, ssim_lambda=cfg.ssim_lambda, kl_weight=cfg.variational.kl_weight,
                                target_stats=gt_stats)
        with timer("backward"):
            losses["loss"].backward()
        # on a CPU one native call for every group on the kernels' threads (train.adam); never torch's second
        # thread, which spins after a parallel region (libgomp's wait policy) and takes a core from the next kernels
        # (BENCHMARKS.md, "Adam on torch's one thread", "One Adam call for every group")
        with timer("optimizer"):
            finite = self._update(losses["loss"], out.radii, self._idle_sh(degree))
            if finite:
                self.bad_steps_in_a_row = 0
                if self.exposure_optimizer is not None:
                    self.exposure_optimizer.step()
            else:
                self._skip_non_finite(step)
            self.optimizer.zero_grad(set_to_none=True)
            if self.exposure_optimizer is not None:
                self.exposure_optimizer.zero_grad(set_to_none=True)
        if finite and out.means2d.grad is not None:
            with timer("densify"):
                # screen radii in the full images' pixels (max_screen_size), whatever this step's resolution
                scale = self.train_cams.width / cams.width
                radii = out.radii if scale == 1.0 else out.radii * scale
                self.densifier.accumulate(step, out.means2d.grad, radii, cams.width, cams.height)
        with timer("eval"):
            if self.check_growth(step) is not None:
                self._expected = None
            self.check_exposure(step)
        if self._fit_until is not None and self._test_due(step) \
                and is_opacity_reset_step(step, cfg.densify, cfg.iterations):
            # rendered even when a stop came in during the step (the stop's checkpoint waits for one test's renders):
            # else the resume would test the reset model in its place
            t0, before = time.perf_counter(), self.step
            self.step = step  # the step's SH degree, as a test after the step renders it
            try:
                with timer("eval"):
                    self._test_before_reset = self.evaluate()
            finally:
                self.step = before
            self._test_seconds = time.perf_counter() - t0
        with timer("densify"):
            done = self._change_topology(step)
        if len(self.model) == 0:  # (trained on as an empty model, it ended in a traceback writing its PLY)
            from uncertsplat.errors import UserError

            raise UserError(f"every Gaussian was removed at step {step}: densification prunes those whose opacity "
                            f"is below densify.min_opacity = {cfg.densify.min_opacity:g} (or that grew too large), and "
                            "none was left to train", path=self.run_dir,
                            hint="Check the settings that lower or threshold opacities (densify.min_opacity, "
                                 "variational.gate_prior_mean, the learning rates) and train again into a new folder.")
        self.step = step
        timer.steps += 1
        # not at a step that reset the opacities: fitted to a model whose every Gaussian is nearly transparent, the
        # tables fell back to the prior for the next refresh_interval steps (bonsai's update at step 3000: 0.4 % of
        # the carriers' position spreads set by the data, against 75 % at step 2500; noise 0.34 against 0.08)
        if self.informed and (step % cfg.variational.refresh_interval == 0 or step == cfg.iterations) \
                and not done.get("reset"):
            with timer("posterior"):
                self.update_posterior()
        result = {k: float(v.detach()) for k, v in losses.items()}
        if not finite:
            result["skipped"] = 1.0
        result.update({k: float(v) for k, v in done.items() if v})
        return result

    def _change_topology(self, step: int) -> dict[str, int]:
        """Densification's changes due at ``step`` (clones, splits, prunes, opacity reset: their counts), inside what
        memory allows (``_memory_limit``)."""
        limit = self._memory_limit(step)
        done = self.densifier.step(step, self.model, self.optimizer, self.gen_noise,
                                   limit=limit[0] if limit is not None else None)
        if done.pop("held") and limit is not None:
            self._memory_held(step, *limit[1:])
        if any(done.values()):
            self._expected = None
        return done

    def _drop(self, g: GaussianSample, step: int) -> GaussianSample:
        """``drop_rate``: each Gaussian left out of this step's render with probability r = drop_rate x
        step / iterations, the others' opacity divided by 1 - r (capped below 1) so that a pixel keeps its
        expected coverage."""
        r = self.cfg.drop_rate * min(step / self.cfg.iterations, 1.0)
        keep = torch.rand(len(g), generator=self.gen_drop, device=g.opacities.device) >= r  # [N]
        opac = torch.where(keep, (g.opacities / (1.0 - r)).clamp(max=0.999), torch.zeros_like(g.opacities))
        return dataclasses.replace(g, opacities=opac)

    def update_posterior(self) -> dict:
        """Set the offset tables to the posterior the training views imply (``variational.informed_tables``):
        the diagonal Fisher of a Gaussian pixel likelihood at the posterior mean, with the observation noise
        the RMS training residual. Costs one render and ``probes`` backward passes per training view used; returns
        (and keeps) its record.

        Updates before the last step use at most ``refresh_views`` training views, drawn with the view generator,
        and scale the Fisher by (training views / views used), an unbiased estimate of the sum over all views;
        the update at the last step uses every training view and ``probes`` probes per view (the earlier ones
        ``refresh_probes``), and with ``variational.sandwich`` widens the spreads by the views' disagreement."""
        t0 = time.perf_counter()
        self._expected = None  # the tables change below (through .data, which no version counter sees)
        vcfg = self.cfg.variational
        params = mean_params(self.model, variant=self.cfg.variant, extent=self.extent,
                             temperature=self.prior.temperature)
        degree = self.sh_degree
        t = len(self.train_idx)
        cams, images = self.train_cams, self.photos()
        last = self.step >= self.cfg.iterations
        n = t if (vcfg.refresh_views == 0 or last) else min(vcfg.refresh_views, t)
        if n < t:
            pick = torch.randperm(t, generator=self.gen_views)[:n].sort().values.tolist()
            cams, images = cams[pick], images[pick]
        # one render per view: the noise (RMS residual), the curvature, and at the last update with
        # ``sandwich`` the views' disagreement (at every update it cost 2 dB: the config's docstring)
        probes = vcfg.probes if last else vcfg.refresh_probes
        if last and n * cams.width * cams.height > LONG_UPDATE_PIXELS:
            from uncertsplat.console import console

            # (it runs inside the last step: 52 views of 2000x1500 took 100 s with the bar standing still)
            console.print(f"posterior: the last update renders every training view ({n} at {cams.width}x"
                          f"{cams.height}, a render and {probes} backward pass{'es' if probes > 1 else ''} each)")
        masks = self._train_masks(pick if n < t else range(t))
        on_view = None
        if last and self._bar is not None:  # (the last update, of every view, runs for minutes on large captures)
            bar, task = self._bar

            # (the bar of an update alone counts its views)
            counts = any(t.id == task and t.description == "posterior" for t in bar.tasks)

            def on_view(done: int, views: int) -> None:
                bar.update(task, info=f"posterior update: view {done}/{views}", **({"completed": done} if counts else {}))

        curv = curvature(params, cams, images, self.render, names=("means", "scales", "opacities"),
                         generator=self.gen_noise, sh_degree=degree, probes=probes,
                         disagreement=vcfg.sandwich and last, masks=masks, on_view=on_view)
        noise, fisher, disagreement = curv.noise_std, curv.fisher, curv.disagreement
        if n < t:
            fisher = {k: v * (t / n) for k, v in fisher.items()}
            if disagreement is not None:
                disagreement = {k: v * (t / n) for k, v in disagreement.items()}
        record = informed_tables(self.model, fisher, self.prior, extent=self.extent,
                                 position_prior_scale=vcfg.position_prior_scale, disagreement=disagreement,
                                 camera_centers=self.train_cams.centers,
                                 position_depth_fraction=vcfg.position_depth_fraction)
        record = {"step": self.step, "views": n, "probes": probes, "noise_std": noise, **record,
                  "seconds": time.perf_counter() - t0}
        self.posterior_updates.append(record)
        return record

    def _idle_sh(self, degree: int) -> tuple[str, ...]:
        """Adam's ``idle`` groups at SH degree ``degree``: at degree 0 no coefficient of the higher bands (``shN``)
        reaches the render, nor has one before (the schedule only switches bands on), so their gradients and
        moments are zero and Adam, which would leave them as they are, need not read them (the native SH backward
        gives them no gradient there: ``render.sh``). Three quarters of a Gaussian's numbers at SH degree 3. Also
        when the model holds no higher band (``sh_degree = 0``, or band 1 dropped: ``shN`` [N,0,3]): its step count
        goes on as when each step handed Adam the empty gradient (before, and on torch's path)."""
        return ("shN",) if degree == 0 else ()

    def _update(self, loss: Tensor, radii: Tensor, idle: tuple[str, ...]) -> bool:
        """The optimisers' update from this step's gradients, unless the loss or a gradient is NaN/Inf (then
        nothing changes and False is returned). Our Adam checks the parameters' gradients in its own pass
        (``Adam.step_if_finite``); torch's (on other devices) after a check here. ``idle``: ``_idle_sh``."""
        rows = None if self.cfg.sparse_updates == "dense" else self.touched_rows(radii)
        exposure = self.exposure.grad if self.exposure is not None else None
        if isinstance(self.optimizer, Adam):
            return all_finite([loss, exposure]) and self.optimizer.step_if_finite(rows, idle=idle)
        params = self.model.parameters()
        for name in idle:  # torch's Adam skips a tensor without a gradient, its step count too
            if params[name].grad is None:
                params[name].grad = torch.zeros_like(params[name])
        if not all_finite([loss, exposure, *(p.grad for p in params.values())]):
            return False
        self.optimizer.step()
        return True

    def _warn_non_finite(self, step: int) -> None:
        from uncertsplat.console import console

        console.print(f"[yellow]warning:[/] step {step}: the loss or a gradient is NaN/Inf; update skipped "
                      "(parameters unchanged)")

    def _skip_non_finite(self, step: int) -> None:
        """A NaN/Inf loss or gradient: skip the update (Adam would spread it into every parameter)."""
        from uncertsplat.errors import UserError

        self.skipped_steps += 1
        self.bad_steps_in_a_row += 1
        self._warn_non_finite(step)
        if self.bad_steps_in_a_row >= MAX_BAD_STEPS:
            from uncertsplat.io.checkpoints import list_checkpoints
            from uncertsplat.train.session import _changed_fit_settings

            saved = self.run_dir is not None and bool(list_checkpoints(self.run_dir))
            rates = "lr.means_init=..., lr.scales=..." + (", exposure_lr=..." if self.cfg.exposure != "off" else "")
            changed = _changed_fit_settings(self.cfg)  # (a helper's lr of 1e30 was told to lower lr.means_init)
            # (--resume takes the run's stored settings, so lower rates need a new run; with no checkpoint the folder
            # holds nothing to go on from, and the same command with other settings starts it again)
            raise UserError(
                f"training diverged: the loss or gradients were NaN/Inf for {self.bad_steps_in_a_row} steps in a "
                f"row (steps {step - self.bad_steps_in_a_row + 1}-{step}); the model was not changed by them"
                + ("; the checkpoints on disk are the last good state" if saved else
                   "; no checkpoint was written before it"),
                path=self.run_dir,
                hint=_diverged_hint(changed, rates, saved, self.run_dir))

    # ------------------------------------------------------------------------------------- loop
    def _install_signal_handlers(self):
        if threading.current_thread() is not threading.main_thread():
            return None
        old = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}

        def handler(signum, frame):
            # finish the current step, checkpoint, stop; a second signal acts immediately
            self._stop = True
            for s, h in old.items():
                signal.signal(s, h)

        for s in old:
            signal.signal(s, handler)
        return old

    def save_checkpoint(self) -> Path | None:
        if self.run_dir is None:
            return None
        from uncertsplat.io.checkpoints import save_checkpoint

        if not all_finite(self.model.parameters().values()):  # never replace a good checkpoint by NaNs
            from uncertsplat.errors import UserError

            raise UserError(f"the model has NaN/Inf parameters at step {self.step}; no checkpoint written",
                            path=self.run_dir, hint="Resume from the last good checkpoint with lower learning rates.")
        return save_checkpoint(self.run_dir, self.step, self.state_dict(), keep=self.cfg.keep_checkpoints)

    def _log(self, record: dict) -> None:
        if self.run_dir is not None:
            try:
                with open(self.run_dir / "stats.jsonl", "a", encoding="utf-8") as f:
                    # (strict JSON: a NaN/inf loss of a skipped step is null, which jq and other readers take)
                    f.write(json.dumps(_finite_or_null(record), allow_nan=False) + "\n")
            except OSError as err:  # disk full: a clear message; a line cut short is dropped on resume
                from uncertsplat.errors import UserError

                if not self.run_dir.is_dir():  # moved or removed under the training, not a full disk
                    raise UserError("the run folder is gone while training wrote to it (moved or removed by another "
                                    "program?)", path=self.run_dir,
                                    hint="Find what moved or removed it; the training cannot go on here.") from None
                raise UserError(f"could not append to the training log ({err.strerror})",
                                path=self.run_dir / "stats.jsonl",
                                hint="Free some space, then continue with --resume.") from None
        if self.on_log is not None:
            self.on_log(record)

    def fit(self, until: int | None = None) -> dict:
        """Train up to step ``until`` (default: ``cfg.iterations``); returns the last log record.

        Writes a checkpoint every ``checkpoint_every`` steps and at the end. On Ctrl-C / SIGTERM the
        current step completes, a checkpoint is written and ``TrainingInterrupted`` is raised.
        """
        cfg = self.cfg
        until = cfg.iterations if until is None else min(until, cfg.iterations)
        self._fit_until, self._test_before_reset, self._test_seconds = until, None, 0.0
        old = self._install_signal_handlers()
        last: dict = {}
        window_t, window_n = 0.0, 0
        # the bar's s/step: the mean over this call's steps, so that one step with a posterior update (a second or
        # so; the last step of a run always has one) does not show as the rate
        start_step, start_elapsed = self.step, self.elapsed
        try:
            # step 0's test renders, or those a stop skipped (the run's record of that step has no test PSNR)
            last_eval = self.evaluate() if self.step == 0 or self.eval_pending else {}
            if last_eval:
                self._log({"step": self.step, "eval_psnr": last_eval["psnr"], "eval_ssim": last_eval["ssim"],
                           "num_gaussians": len(self.model), "num_carriers": self.model.num_carriers})
            self.eval_pending = False
            with progress() as bar:
                if self.step < until:  # (a call with no step to train draws no bar of 0 steps)
                    task = bar.add_task("train", total=until, completed=self.step, info="")
                    self._bar = (bar, task)
                while self.step < until:
                    t0 = time.perf_counter()
                    terms = self.train_step()
                    dt = time.perf_counter() - t0 - self._test_seconds  # (tests are not training time)
                    self._test_seconds = 0.0
                    self.elapsed += dt
                    window_t += dt
                    window_n += 1
                    step = self.step
                    # a stop asked for during the step skips its test renders (the checkpoint follows at once: a
                    # run's last step renders every test view, minutes for hundreds of large photos)
                    stopping = self._stop or STOP_REQUESTED.is_set()
                    due = self._test_due(step)
                    before_reset, self._test_before_reset = self._test_before_reset, None  # (rendered already)
                    evaluated = due and (not stopping or before_reset is not None)
                    self.eval_pending = due and not evaluated
                    if evaluated:
                        with self.timer("eval"):
                            last_eval = (before_reset if before_reset is not None
                                         else self.evaluate(remember=step == until))
                    if step % cfg.log_every == 0 or step == until or evaluated or "skipped" in terms:
                        last = {"step": step, **{k: round(v, 7) for k, v in terms.items()},
                                "num_gaussians": len(self.model), "num_carriers": self.model.num_carriers,
                                "sh_degree": self.sh_degree,
                                "lr_means": self.optimizer.param_groups[0]["lr"],
                                "sec_per_step": window_t / max(window_n, 1), "elapsed": self.elapsed,
                                "peak_memory_mb": self.peak_mb()}
                        if last_eval and evaluated:
                            last.update(eval_psnr=last_eval["psnr"], eval_ssim=last_eval["ssim"])
                        self._log(last)
                        window_t, window_n = 0.0, 0
                    info = f"loss {terms['loss']:.4f}  N {len(self.model)}  P {self.model.num_carriers}"
                    if last_eval:
                        info += f"  test PSNR {last_eval['psnr']:.2f}"
                    info += f"  {(self.elapsed - start_elapsed) / (step - start_step):.3f} s/step"
                    bar.update(task, completed=step, info=info)
                    if self.on_step is not None:
                        self.on_step(self)
                    if step % cfg.checkpoint_every == 0 and step != until:
                        with self.timer("checkpoint"):
                            self.save_checkpoint()
                    if self._stop or STOP_REQUESTED.is_set():
                        path = self.save_checkpoint()
                        raise TrainingInterrupted(step, path)
            if self.step == until:
                if until == cfg.iterations and self._final_update_missing():
                    # a resume told to stop at its checkpoint's step (--iterations N, N = that step) trains no step,
                    # and the update of a run's last step is made inside one: without this, the tables stayed as
                    # the last refresh left them (the prior, before the first)
                    with self.timer("posterior"):
                        if self._bar is None:  # no step trained in this call (a model given by init_ply): a bar of
                            # the update's views (the update counts them on it); else the training's bar shows it
                            with progress() as bar:
                                self._bar = (bar, bar.add_task("posterior", total=len(self.train_idx), info=""))
                                self.update_posterior()
                        else:
                            self.update_posterior()
                # written while a stop waits for it (a Ctrl-C during the write lost every step since the last
                # periodic checkpoint), then the stop is honoured
                path = self.save_checkpoint()
                if self._stop or STOP_REQUESTED.is_set():
                    raise TrainingInterrupted(self.step, path)
        finally:
            self._fit_until = None
            self._bar = None
            if old:
                for s, h in old.items():
                    signal.signal(s, h)
        return last

    def _test_due(self, step: int) -> bool:
        """Whether ``fit`` tests the model on the held-out views after ``step``: every ``eval_every`` steps and at the
        step it trains to."""
        return step % self.cfg.eval_every == 0 or step == self._fit_until

    def _final_update_missing(self) -> bool:
        """Whether an informed run at its last step lacks the update of that step (every training view, the
        final number of probes): the update ``train_step`` makes at the run's last step."""
        if not self.informed:
            return False
        u = self.posterior_updates[-1] if self.posterior_updates else None
        return (u is None or u.get("step") != self.step or u.get("views") != len(self.train_idx)
                or u.get("probes") != self.cfg.variational.probes)

    def posterior_summary(self) -> dict:
        """``variational.posterior_summary`` of the model; for the informed posterior measured against the
        per-carrier prior its updates use (the config's single position std is not that posterior's prior)."""
        if not self.informed:
            return posterior_summary(self.model, self.prior)
        vcfg = self.cfg.variational
        std = informed_position_prior(self.model, self.prior, extent=self.extent,
                                      position_prior_scale=vcfg.position_prior_scale,
                                      camera_centers=self.train_cams.centers,
                                      position_depth_fraction=vcfg.position_depth_fraction)
        return posterior_summary(self.model, self.prior, position_prior_std=std)

    def summary(self) -> dict:
        mem = memory_per_gaussian(self.model, table_moments=not self.informed)
        return {"steps": self.step, "seconds": self.elapsed,
                "sec_per_step": self.elapsed / max(self.step, 1),
                "num_gaussians": len(self.model), "num_carriers": self.model.num_carriers,
                "carrier_fraction": self.model.num_carriers / max(len(self.model), 1),
                "memory_per_gaussian_bytes": mem["total"], "memory": mem,
                "peak_memory_mb": self.peak_mb(), "extent": self.extent,
                "skipped_steps": self.skipped_steps,
                "sh_degree_active": self.sh_degree, "sh_bands": [b.model_dump() for b in self.sh_bands],
                "growth": [g.model_dump() for g in self.growth],
                "exposure_checks": [c.model_dump() for c in self.exposure_checks],
                "variant": self.cfg.variant, "method": self.cfg.method,
                "posterior": self.posterior_summary(),
                "posterior_updates": self.posterior_updates,
                "budget": {**self.budget.as_dict(), "memory_hold": self.memory_hold},
                **({"imported": self.imported} if self.imported else {}),
                **({"profile": self.timer.summary()} if self.timer.enabled else {})}


class GrowthCopy(Trainer):
    """A copy of a training that the growth test trains for a few steps (``Trainer._fork``, ``_refit_cost``): the
    same steps as its parent's, with everything that would change more than the copy itself left out. It shares its
    parent's photos and their derived arrays (low-resolution images, masks, SSIM statistics) and leaves its
    parent's memory peaks alone; its steps change no topology, update no posterior, make no test (SH band, growth,
    exposure) and warn of no skipped step (the parent never skipped it); it has no run folder, so it writes
    nothing."""

    def check_sh_band(self, step: int) -> None:
        return None

    def check_growth(self, step: int) -> None:
        return None

    def check_exposure(self, step: int) -> None:
        return None

    def update_posterior(self) -> dict:
        return {}

    def _change_topology(self, step: int) -> dict[str, int]:
        return {}

    def _warn_non_finite(self, step: int) -> None:
        return None


def log_line(record: dict) -> str:
    parts = [f"step {record.get('step')}"]
    for k in ("loss", "eval_psnr", "num_gaussians", "num_carriers", "sec_per_step"):
        if k in record:
            v = record[k]
            parts.append(f"{k} {v:.4g}" if isinstance(v, float) and not math.isnan(v) else f"{k} {v}")
    return ", ".join(parts)


__all__ = ["GrowthCopy", "Trainer", "TrainingInterrupted", "prior_from_config", "peak_memory_mb"]
