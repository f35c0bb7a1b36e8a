"""What ``uncertsplat view`` shows, as functions of a loaded run and a camera: no server, no threads.

A ``FrameRenderer`` wraps any run ``baselines.load_run`` reads (variational, deterministic, ensemble, Fisher,
pruned) and turns a camera into a ``Frame`` (a uint8 image, the values it colours and their range) in one
of the ``VIEW_MODES``:

- ``rgb``: the run's deterministic render (``Sampler.det_sample``, what ``train`` reports; an ensemble or a
  Fisher run has none, so its trained model's mean is shown: member 0 for an ensemble). The same pixels as
  ``render.render`` of that sample (tested).
- ``depth``: the alpha-normalised camera z of that render; pixels with accumulated opacity below
  ``EMPTY_ALPHA`` are drawn black (no surface).
- ``rgb_std`` / ``depth_std``: the Monte-Carlo std of K posterior samples (``uncertainty.mc``) with the
  empty-ray term of the evaluation (a ray that meets nothing is not certain); the RGB std is the mean over
  the three channels. ``StdAccumulator`` adds samples a few at a time, so the server can show K = 4 while
  the camera moves and refine the same frame while it stands still. The pixel-noise term of ``evaluate``
  (fitted on training views) is not added: the viewer shows what the posterior itself says.
- ``unseen``: what no training view showed, as an RGB std: each Gaussian's colour posterior (``evaluate``'s
  colour term, ``uncertainty.residual``, fitted once on the training views the first time the mode is shown)
  blended for the view, plus the empty-ray term of the mean render (a ray the model covers less than its
  training views is partly an unknown surface). Near 0 wherever the training views saw the surface; up to the
  capture's pixel std where a view looks at Gaussians no photo showed, the empty term's 0.29 where it looks at
  nothing. Only when the run's training photos are there (``unseen_field``).
- ``prune``: the run's expected render with every Gaussian that ``prune --keep-ratio R --score S`` would
  remove coloured by its score (turbo, from the threshold to the 99th percentile of the removed ones) and
  the kept ones in grey; or, with ``hide_removed``, the render of the kept Gaussians (what the pruned run
  will look like). Only for runs with posterior carriers (the scores read the offset tables).

Colour ranges are the 1st-99th percentile of the frame's finite values unless a fixed range is given (the
server's "lock colour range"), as in the report's previews (``report.colormaps``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from uncertsplat.baselines.runs import LoadedRun
from uncertsplat.gaussians.ops import quat_to_rotmat, rotmat_to_quat
from uncertsplat.report.colormaps import color_range, colorize
from uncertsplat.types import Cameras, GaussianSample, RenderOutput, _map_tensors
from uncertsplat.uncertainty.mc import MonteCarloMoments
from uncertsplat.uncertainty.residual import ResidualField, with_colour

VIEW_MODES: dict[str, str] = {
    "rgb": "RGB",
    "depth": "Depth",
    "rgb_std": "RGB std",
    "depth_std": "Depth std",
    "unseen": "Unseen by the photos",
    "prune": "Prune preview",
}
"""Mode key -> the label the panel shows."""

STD_MODES = ("rgb_std", "depth_std")
EMPTY_ALPHA = 0.05
"""A pixel whose accumulated opacity is below this shows no surface: black in the depth view."""
PRUNE_SCORES = ("free-space", "gate", "position", "scale", "predictive")  # the first available is the default


@dataclass(frozen=True)
class Frame:
    """One rendered view.

    Attributes:
        image: [H,W,3] uint8, what the browser shows.
        depth: [H,W] float32 camera z of the surface (inf where there is none), to composite the 3D overlays.
        value_range: (low, high) of the colour bar; None for the RGB modes without one.
        unit: what the colour bar measures (e.g. "RGB std").
        samples: posterior samples behind the frame (1 for the deterministic modes).
        note: one line for the panel (e.g. how many Gaussians prune would remove).
        values: [H,W] float32 map that was coloured (None for colour images).
    """

    image: np.ndarray
    depth: np.ndarray
    value_range: tuple[float, float] | None = None
    unit: str = ""
    samples: int = 1
    note: str = ""
    values: np.ndarray | None = None


def viewer_camera(wxyz, position, fov_y: float, width: int, height: int,
                  device: torch.device | str = "cpu") -> Cameras:
    """The pinhole ``Cameras`` (one) of a browser viewport.

    Args:
        wxyz: [4] rotation world_from_camera (OpenCV axes: +z forward, +y down), as viser reports it.
        position: [3] the camera centre in world coordinates.
        fov_y: vertical field of view in radians.
        width, height: the image size to render; pixels are square, the principal point is the centre.
    """
    q = torch.as_tensor(np.asarray(wxyz, dtype=np.float64), dtype=torch.float64)[None]
    world_from_cam = torch.eye(4, dtype=torch.float64)
    world_from_cam[:3, :3] = quat_to_rotmat(q)[0]
    world_from_cam[:3, 3] = torch.as_tensor(np.asarray(position, dtype=np.float64))
    cam_from_world = torch.linalg.inv(world_from_cam).float()
    f = 0.5 * height / math.tan(0.5 * float(fov_y))
    K = torch.tensor([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])
    return Cameras(cam_from_world[None].to(device), K[None].to(device), int(width), int(height), ("viewer",))


def camera_pose(cam_from_world: Tensor, K: Tensor, height: int) -> tuple[np.ndarray, np.ndarray, float]:
    """(wxyz world_from_camera, centre [3], vertical fov in radians) of one camera: the inverse of
    ``viewer_camera``, used to draw the training cameras and to move the view onto one."""
    world_from_cam = torch.linalg.inv(cam_from_world.double().cpu())
    R = world_from_cam[:3, :3].numpy()
    return rotmat_to_wxyz(R), world_from_cam[:3, 3].numpy().copy(), 2.0 * math.atan(0.5 * height / float(K[1, 1]))


def rotmat_to_wxyz(R: np.ndarray) -> np.ndarray:
    """[3,3] rotation -> unit quaternion wxyz with w >= 0, as numpy (``gaussians.ops.rotmat_to_quat``)."""
    return rotmat_to_quat(torch.from_numpy(np.asarray(R, dtype=np.float64))).numpy()


def _surface_depth(out: RenderOutput) -> np.ndarray:
    d = out.depth[0, ..., 0].float()
    return torch.where(out.alpha[0, ..., 0] >= 0.5, d, torch.full_like(d, float("inf"))).cpu().numpy()


def _to_uint8(rgb: Tensor) -> np.ndarray:
    """[H,W,3] float in [0, 1] -> uint8 (rounded)."""
    return (rgb.clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).cpu().numpy()


def colour_map(values: np.ndarray, value_range: tuple[float, float] | None) -> tuple[np.ndarray, tuple[float, float]]:
    """Colour a [H,W] map (NaN = black) with turbo over ``value_range`` (None: its 1st-99th percentile)."""
    lo, hi = value_range if value_range is not None else color_range(values, "percentile")
    return colorize(values, "fixed", lo, hi), (float(lo), float(hi))


class StdAccumulator:
    """Monte-Carlo moments of one camera's renders, refined a few samples at a time.

    The generator is seeded per camera, so the same camera and number of samples always give the same maps
    (whether they were drawn at once or in steps).
    """

    def __init__(self, renderer: FrameRenderer, cameras: Cameras, seed: int):
        self.renderer = renderer
        self.cameras = cameras
        self.moments = MonteCarloMoments(renderer.sampler.coverage)
        self.generator = torch.Generator(device=renderer.device).manual_seed(seed)

    @property
    def count(self) -> int:
        return self.moments.count

    @torch.no_grad()
    def add(self, n: int) -> None:
        """Draw and render ``n`` more posterior samples."""
        sampler = self.renderer.sampler
        for _ in range(n):
            self.moments.update(sampler.render_fn(sampler.sample_fn(self.generator), self.cameras))

    def frame(self, mode: str, value_range: tuple[float, float] | None = None) -> Frame:
        """The ``rgb_std`` or ``depth_std`` frame of the samples drawn so far."""
        if mode not in STD_MODES:
            raise ValueError(f"not a std mode: {mode!r} (choose one of {STD_MODES})")
        maps = self.moments.maps(empty_std=self.renderer.sampler.empty_std)
        if mode == "rgb_std":
            values, unit = maps.rgb_std[0].mean(-1), "RGB std (mean over channels)"
        else:
            values, unit = maps.depth_std[0, ..., 0] * self.renderer.depth_factor, \
                f"depth std ({self.renderer.depth_units})"
        values = values.float().cpu().numpy()
        image, rng = colour_map(values, value_range)
        d = maps.depth_mean[0, ..., 0]
        depth = torch.where(maps.alpha_mean[0, ..., 0] >= 0.5, d, torch.full_like(d, float("inf"))).cpu().numpy()
        return Frame(image, depth, rng, unit, self.count, self.renderer.samples_label(self.count), values)


class FrameRenderer:
    """Renders a loaded run for the viewer (see the module docstring).

    Args:
        loaded: the run (``baselines.load_run``).
        scene_scale: the scene's camera-rig radius (``SceneData.scene_scale``; sets the near plane).
        device: where to render (the run's device).
        score_cameras: training cameras for the ``predictive`` prune score (it renders them); None leaves
            that score out.
        free_space_cameras: training cameras for the ``free-space`` prune score (one render each); None
            leaves that score out.
        seed: seed of the std modes' samples (per camera) and of the predictive score.
        unseen_field: returns the run's ``ResidualField`` with its colour posterior (fitted on the training
            views; called once, when the ``unseen`` mode is first shown); None leaves that mode out.
        depth_to_source: the factor from the run's normalised depth to the scene's units (``SceneData.
            depth_to_source``), which the depth modes show; None: they show the run's own units, and say so.
    """

    def __init__(self, loaded: LoadedRun, scene_scale: float, device: torch.device | str, *,
                 score_cameras: Cameras | None = None, free_space_cameras: Cameras | None = None, seed: int = 0,
                 unseen_field: Callable[[], ResidualField | None] | None = None,
                 depth_to_source: float | None = None):
        from uncertsplat.gaussians import variational

        self.loaded = loaded
        # the depth modes' values and label (the frames' depth buffers stay in the run's units: the 3D scene's)
        self.depth_factor = float(depth_to_source) if depth_to_source is not None else 1.0
        self.depth_units = "scene units" if depth_to_source is not None else "the run's normalised units"
        self.device = torch.device(device)
        self.seed = int(seed)
        self.sampler = loaded.sampler(scene_scale, self.device)
        if self.sampler.det_sample is not None:
            self.mean_sample: GaussianSample = self.sampler.det_sample
            self.rgb_source = "the expected render (what train reports)"
        else:
            with torch.no_grad():
                self.mean_sample = variational.posterior_mean(loaded.model, **loaded.sample_kwargs)
            member = " of member 0" if loaded.config.method == "ensemble" else ""
            self.rgb_source = f"the trained model's mean{member} ({loaded.config.method} has no expected render)"
        self.score_cameras = score_cameras
        self.free_space_cameras = free_space_cameras
        self._scores: dict[str, Tensor] = {}
        self._unseen_fn = unseen_field
        self._unseen: ResidualField | None = None
        self._unseen_failed: str | None = None  # why the fit failed (it is not tried again)

    # ---- what the run offers
    @property
    def has_posterior(self) -> bool:
        """Posterior samples differ (not a deterministic model): the std modes show more than the empty term."""
        return not (self.loaded.config.method == "deterministic" or
                    (self.loaded.config.method in ("variational", "paper", "vi-single")
                     and self.loaded.model.num_carriers == 0))

    def samples_label(self, count: int) -> str:
        """What a std frame of ``count`` samples rests on: a deterministic model's "K = 16 posterior samples" were 16
        equal renders, and an ensemble's draw among a few members."""
        if not self.has_posterior:
            return f"{count} equal renders: the model has no posterior, the std is the empty-ray term alone"
        if self.loaded.config.method == "ensemble":
            return f"K = {count} draws among its {self.loaded.config.ensemble_size} members"
        return f"K = {count} posterior samples"

    @property
    def prune_available(self) -> bool:
        """The prune preview needs offset tables (posterior carriers) to score Gaussians by."""
        return self.loaded.config.method not in ("ensemble", "fisher", "deterministic") and \
            self.loaded.model.num_carriers > 0

    def modes(self) -> list[str]:
        """The ``VIEW_MODES`` keys this run supports."""
        return [m for m in VIEW_MODES if (m != "prune" or self.prune_available)
                and (m != "unseen" or self._unseen_fn is not None)]

    def score_names(self) -> list[str]:
        """The prune scores available (``predictive`` and ``free-space`` need training cameras)."""
        cams = {"predictive": self.score_cameras, "free-space": self.free_space_cameras}
        return [s for s in PRUNE_SCORES if s not in cams or cams[s] is not None]

    # ---- frames
    @torch.no_grad()
    def render_mean(self, cameras: Cameras) -> RenderOutput:
        """The render of ``mean_sample`` (what the RGB and depth modes show)."""
        return self.sampler.render_fn(self.mean_sample, cameras)

    def frame(self, cameras: Cameras, mode: str, *, num_samples: int = 4,
              value_range: tuple[float, float] | None = None, score: str = "gate", keep_ratio: float = 0.9,
              hide_removed: bool = False) -> Frame:
        """One frame of ``mode`` for one camera (``cameras`` holds one); std modes draw ``num_samples`` at once."""
        if len(cameras) != 1:
            raise ValueError(f"a frame is rendered for one camera, got {len(cameras)}")
        if mode in ("rgb", "depth"):
            out = self.render_mean(cameras)
            depth = _surface_depth(out)
            if mode == "rgb":
                return Frame(_to_uint8(out.rgb[0]), depth, note=f"RGB: {self.rgb_source}")
            d = out.depth[0, ..., 0].float()
            values = torch.where(out.alpha[0, ..., 0] >= EMPTY_ALPHA, d, torch.full_like(d, float("nan")))
            values = values.cpu().numpy() * self.depth_factor
            image, rng = colour_map(values, value_range)
            return Frame(image, depth, rng, f"depth ({self.depth_units})", 1, "black: no surface", values)
        if mode in STD_MODES:
            acc = self.std_accumulator(cameras)
            acc.add(num_samples)
            return acc.frame(mode, value_range)
        if mode == "unseen":
            return self.unseen_frame(cameras, value_range)
        if mode == "prune":
            return self.prune_frame(cameras, score=score, keep_ratio=keep_ratio, hide_removed=hide_removed)
        raise ValueError(f"unknown view mode {mode!r} (choose one of {', '.join(VIEW_MODES)})")

    @torch.no_grad()
    def unseen_frame(self, cameras: Cameras, value_range: tuple[float, float] | None = None) -> Frame:
        """The ``unseen`` frame (module docstring): ``sqrt(colour posterior blended + empty-ray variance)``."""
        if self._unseen_fn is None:
            raise ValueError("this viewer has no training photos to know what they showed (unseen mode)")
        if self._unseen_failed is not None:  # (a fit that failed is not done again at every move of the camera)
            raise ValueError(self._unseen_failed)
        if self._unseen is None:
            try:
                with torch.enable_grad():  # the fit's sums come from backward passes
                    fitted = self._unseen_fn()
            except Exception as err:
                self._unseen_failed = f"the run's colour posterior could not be fitted ({type(err).__name__}: {err})"
                raise
            if fitted is None or fitted.colour_evidence is None:
                self._unseen_failed = "the run's colour posterior could not be fitted (no training views)"
                raise ValueError(self._unseen_failed)
            self._unseen = fitted
        out = self.render_mean(cameras)
        # the mean render as a single sample: no spread, the empty-ray term as `evaluate` adds it, the colour term
        moments = MonteCarloMoments(self.sampler.coverage)
        moments.update(out)
        maps = moments.maps(empty_std=self.sampler.empty_std,
                            extra_var=self._unseen.colour_blended(cameras, self.sampler.render_fn))
        values = maps.rgb_std[0, ..., 0].float().cpu().numpy()  # the same in every channel
        image, rng = colour_map(values, value_range)
        share = self._unseen.colour_unknown_fraction() or 0.0
        note = f"colour posterior + empty rays; {100 * share:.1f} % of the Gaussians unseen by the training photos"
        return Frame(image, _surface_depth(out), rng, "RGB std of what no photo showed", 1, note, values)

    def std_accumulator(self, cameras: Cameras) -> StdAccumulator:
        """A fresh ``StdAccumulator`` for ``cameras`` (seeded with the renderer's seed)."""
        return StdAccumulator(self, cameras, self.seed)

    # ---- prune preview
    def scores(self, name: str) -> Tensor:
        """[N] the prune score ``name`` of every Gaussian (computed once, as ``prune`` does)."""
        from uncertsplat.uncertainty.scores import compute_scores

        if not self.prune_available:
            raise ValueError("this run has no posterior carriers to score")
        if name not in self.score_names():
            raise ValueError(f"unknown or unavailable score {name!r} (choose one of {', '.join(self.score_names())})")
        if name not in self._scores:
            prior = self.loaded.prior
            gen = torch.Generator(device=self.device).manual_seed(self.seed)
            names = ("position", "scale", "gate") + ((name,) if name in ("predictive", "free-space") else ())
            cams = self.score_cameras.to(self.device) if self.score_cameras is not None else None
            free = self.free_space_cameras.to(self.device) if self.free_space_cameras is not None else None
            with torch.enable_grad():  # the predictive score's blending weights come from one backward pass
                out = compute_scores(self.loaded.model, cams, gen, render_fn=self.sampler.render_fn, names=names,
                                     subset_size=self.loaded.config.variational.subset_size,
                                     variant=prior.variant, extent=self.loaded.extent, temperature=prior.temperature,
                                     free_space_cameras=free)
            self._scores.update({k: v for k, v in out.items() if k in PRUNE_SCORES})
        return self._scores[name]

    def keep_mask(self, score: str, keep_ratio: float) -> Tensor:
        """[N] bool, what ``prune --keep-ratio keep_ratio --score score`` keeps (same mask, same ties)."""
        from uncertsplat.prune.mask import keep_ratio_mask
        from uncertsplat.uncertainty.scores import carrier_mask

        return keep_ratio_mask(self.scores(score), carrier_mask(self.loaded.model), keep_ratio)

    @torch.no_grad()
    def prune_frame(self, cameras: Cameras, *, score: str = "gate", keep_ratio: float = 0.9,
                    hide_removed: bool = False) -> Frame:
        """The prune preview (see the module docstring)."""
        from uncertsplat.render.sh import C0

        s = self.scores(score)
        keep = self.keep_mask(score, keep_ratio)
        n, removed = len(keep), int((~keep).sum())
        note = f"prune --keep-ratio {keep_ratio:.3g} --score {score} removes {removed:,} of {n:,} Gaussians"
        if score == "predictive":  # (prune writes no model by it: it ranks first what the images need most)
            note = (f"prune --dry-run --keep-ratio {keep_ratio:.3g} --score predictive ranks these {removed:,} of "
                    f"{n:,} Gaussians first (a study: prune writes no model by this score)")
        sample = self.mean_sample
        if hide_removed:
            out = self.sampler.render_fn(_subset(sample, keep), cameras)
            return Frame(_to_uint8(out.rgb[0]), _surface_depth(out), None, f"{score} score", 1,
                         note + " (showing what is kept)")
        gone = s[~keep].float()
        if removed:
            lo = float(gone.min())
            hi = float(torch.quantile(gone, 0.99)) if removed > 1 else lo
        else:
            lo = hi = float(s.max()) if n else 0.0
        base = (sample.sh[:, 0, :] * C0 + 0.5).clamp(0, 1)  # [N,3] the DC colour
        grey = (0.25 + 0.5 * (base @ torch.tensor([0.299, 0.587, 0.114], device=base.device)))[:, None].expand(-1, 3)
        t = ((s.float() - lo) / (hi - lo)).clamp(0, 1) if hi > lo else torch.ones_like(s.float())
        lut = torch.from_numpy(colorize(np.linspace(0, 1, 256)[None], "fixed", 0.0, 1.0)[0]).to(base)  # [256,3]
        hot = lut[(t * 255).round().long()] / 255.0
        colour = torch.where(keep[:, None], grey, hot)
        out = self.sampler.render_fn(with_colour(sample, colour), cameras)
        return Frame(_to_uint8(out.rgb[0]), _surface_depth(out), (lo, hi), f"{score} score of the removed", 1,
                     note)


def _subset(sample: GaussianSample, keep: Tensor) -> GaussianSample:
    """The Gaussians ``keep`` ([N] bool) of a sample (every per-Gaussian tensor indexed alike)."""
    return _map_tensors(sample, lambda t: t[keep])


__all__ = ["EMPTY_ALPHA", "Frame", "FrameRenderer", "PRUNE_SCORES", "STD_MODES", "StdAccumulator", "VIEW_MODES",
           "camera_pose", "colour_map", "rotmat_to_wxyz", "viewer_camera"]
