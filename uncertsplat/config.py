"""Pydantic configuration schemas: one model per stage, plus the pipeline chain.

Every model forbids unknown keys, validates ranges and rejects NaN/Inf, so a typo in a TOML file or a
``--set`` override is an error that names the key instead of a silently ignored setting. The fully
resolved config of a stage is written as JSON beside its outputs (``RUN/config.json``).
"""

from __future__ import annotations

import difflib
import json
import math
import re
import tomllib
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from uncertsplat.errors import UserError


def _parts(annotation) -> tuple:
    """``annotation`` without Annotated's metadata, with its origin and arguments (``typing.get_origin`` / ``_args``)."""
    import typing

    while typing.get_origin(annotation) is Annotated:
        annotation = typing.get_args(annotation)[0]
    return annotation, typing.get_origin(annotation), typing.get_args(annotation)


def _members(args: tuple) -> list:
    """A union's members other than None."""
    return [a for a in args if a is not type(None)]


def _takes_bool(annotation) -> bool:
    """Whether a field of type ``annotation`` takes true/false (bool, Any, or a union or literal with a bool)."""
    import types
    import typing

    annotation, origin, args = _parts(annotation)
    if annotation is bool or annotation is Any:
        return True
    if origin in (typing.Union, types.UnionType):
        if any(_is_number(a) for a in _members(args)):  # "auto" | float: true is no number, and no word either
            return any(a is bool or a is Any for a in _members(args))
        return any(_takes_bool(a) for a in _members(args))
    if origin is Literal:  # only a literal of numbers refuses it (a validator may read a legacy bool into words)
        return not all(isinstance(a, (int, float)) and not isinstance(a, bool) for a in args)
    return not _is_number(annotation)  # only a number field refuses it (a model, a dict, a path: pydantic says)


def _is_number(annotation) -> bool:
    """Whether ``annotation`` is (a union or list of, an Annotated) int or float, as a field's value or items."""
    import types
    import typing

    annotation, origin, args = _parts(annotation)
    if annotation in (int, float):
        return True
    if origin in (typing.Union, types.UnionType):
        return any(_is_number(a) for a in _members(args))
    if origin in (list, tuple):
        return bool(args) and all(_is_number(a) for a in args if a is not Ellipsis)
    return False


def refuse_bool_numbers(model: type[BaseModel], field: str, value):
    """``value`` unchanged, or a ValueError when it is true/false (or a list holding one) for a number field:
    pydantic reads true as 1 (``num_samples = true`` evaluated with K = 1 without a word)."""
    annotation = model.model_fields[field].annotation
    items = value if isinstance(value, list) else [value]
    if any(isinstance(v, bool) for v in items) and not _takes_bool(annotation):
        raise ValueError("true/false given where a number is expected")
    return value


class _Base(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)

    @field_validator("*", mode="before")
    @classmethod
    def _no_bool_numbers(cls, value, info):
        return refuse_bool_numbers(cls, info.field_name, value)


# ----------------------------------------------------------------------------------------------- synth
class SynthConfig(_Base):
    """Synthetic scene generation (``uncertsplat synth``)."""

    preset: Literal["tiny", "demo"] = "demo"
    """tiny: ~24 views at 128x96 for tests; demo: ~40 views at 320x240."""
    seed: int = Field(0, ge=0, le=2**32 - 1)
    """Random seed: the same seed gives byte-identical outputs (below 2**32: the generators take seed x 104729 + 7,
    which must fit in 64 bits)."""
    num_views: int | None = Field(None, ge=3, le=2000)
    """Override the preset's number of views."""
    width: int | None = Field(None, ge=16, le=8192)
    """Override the preset's image width (height follows the 4:3 aspect)."""
    test_every: int = Field(8, ge=2)
    """Every n-th view (by sorted name, index 0, n, 2n, ...) is a test view."""
    layout: Literal["colmap", "blender"] = "colmap"
    """colmap: images/ + a COLMAP model (sparse/0) with GT poses and sparse points; blender: the NeRF-synthetic
    layout (transforms_train.json / transforms_test.json, RGBA PNGs in train/ and test/, no sparse points)."""
    rig: Literal["ring", "hemisphere"] = "ring"
    """ring: a jittered orbit at 22 +- 10 degrees elevation; hemisphere: cameras spread over the upper hemisphere
    (10 to 75 degrees elevation, radius 4) all looking at one point, as in the NeRF-synthetic scenes."""
    backdrop: Literal["room", "transparent"] = "room"
    """room: the objects inside a closed textured room (every pixel hits a surface); transparent: the objects
    alone, written as RGBA with alpha = pixel coverage (the training background then shows through)."""


# ------------------------------------------------------------------------------------------ reconstruct
class ReconstructConfig(_Base):
    """Structure-from-motion with COLMAP through pycolmap (``uncertsplat reconstruct``)."""

    matcher: Literal["auto", "exhaustive", "sequential"] = "auto"
    """auto: exhaustive for up to ``exhaustive_max_images`` images, sequential above."""
    exhaustive_max_images: int = Field(150, ge=2)
    camera_model: Literal["SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV"] = "SIMPLE_RADIAL"
    """Camera model estimated by SfM; images are undistorted to PINHOLE afterwards."""
    single_camera: bool = True
    """One camera shared by all images of the same size (one device); else one per image."""
    max_image_size: int = Field(1600, ge=64)
    """Longest side used for feature extraction and undistorted output."""
    features: Literal["sift", "dsp-sift"] = "sift"
    """sift: COLMAP's SIFT. dsp-sift: SIFT with affine-adapted regions and domain-size pooling (descriptors pooled
    over several region sizes), which match across wider changes of view; more observations per photo and better
    poses on captures whose photos are far apart, for more extraction time (BENCHMARKS.md, "Features for photos far
    apart")."""
    masks: Path | None = None
    """A folder of masks for the photos (the mask of ``IMG_1.jpg``: ``IMG_1.jpg.png`` as COLMAP names it,
    ``IMG_1.jpg`` or ``IMG_1.png``), white where the photo shows the scene and black where not (a person walking
    through, the rig, the sky): no feature is taken under black pixels, and the workspace gets ``masks/``, each mask
    undistorted as its image is, which ``train`` and ``evaluate`` read (docs/guide.md, "Masks"). A photo without a mask
    counts every pixel."""
    guided_matching: bool = False
    """After a pair's geometry is verified, match its features again constrained by that geometry (more inlier
    matches per pair; matching takes several times longer)."""
    min_registered: float = Field(0.8, gt=0.0, le=1.0)
    """Fail when fewer than this fraction of the images register."""
    mapping_attempts: int = Field(4, ge=1, le=20)
    """Incremental mapping runs at most: it is run with seeds ``seed``, ``seed + 1``, ... until two runs agree on the
    geometry (images, feature observations, focal lengths; ``sfm.reconstruct.attempts_agree``) and the run that
    explains the most feature observations is kept. One run can settle in a wrong focal length (bonsai: 3 of 8 seeds;
    BENCHMARKS.md "Mapping runs that disagree"). 1: one run, as COLMAP alone."""
    seed: int = Field(0, ge=0, le=2**31 - 21)
    """Seed for COLMAP's RANSAC and mapper (a 32-bit signed integer there, plus one per mapping run: at most
    2**31 - 21); results are bit-identical for a seed only with num_threads=1
    (with more threads the camera centres differ slightly between runs; BENCHMARKS.md, Reconstruct)."""
    num_threads: int = Field(-1, ge=-1)
    """Threads for COLMAP (-1: all cores)."""
    overwrite: bool = False
    """Replace an existing workspace in the output folder."""
    extend: bool = False
    """Add the photos that are new in the photo folder to the existing workspace: registered into its model with
    every camera already there fixed (pose and intrinsics), with the workspace's own options (the others
    given are not used), so that a run trained on it can go on with them (``train --resume --add-views``). Without
    it, a changed photo folder asks for --overwrite, a new reconstruction in a new frame."""

    @model_validator(mode="after")
    def _extend_or_overwrite(self):
        if self.extend and self.overwrite:
            raise ValueError("extend and overwrite exclude each other: --extend keeps the workspace, --overwrite "
                             "replaces it")
        return self


# ------------------------------------------------------------------------------------------------ scene
class SceneConfig(_Base):
    """How a scene is loaded for training and evaluation."""

    downscale: float = Field(1.0, ge=1.0, le=64.0)
    """Divide image width and height by this factor (the paper uses 8 for LLFF)."""
    test_every: int = Field(8, ge=2)
    """Every n-th image by sorted name (index 0, n, 2n, ...) is held out, unless names/indices are given."""
    test_names: list[str] | None = None
    """Explicit held-out image names (overrides test_every)."""
    test_indices: list[int] | None = None
    """Explicit held-out indices into the sorted image list (overrides test_every)."""
    train_names: list[str] | None = None
    """Explicit training image names; images neither trained on nor held out are left unused (e.g. one side
    of a capture, to measure what the model says about the other side). Default: every image not held out."""
    train_indices: list[int] | None = None
    """Explicit training indices into the sorted image list (as train_names)."""
    calibration_holdout: int = Field(0, ge=0)
    """Training views set aside before training, evenly spaced over them, for ``evaluate`` to fit the std factor
    on: views the model never trained on, so the factor carries the gap between the training views and new ones
    (a factor fitted on training views errs low where the model fits them better than new views). 0: none, the
    factor is fitted on training views (``EvalConfig.calibration_views``)."""
    points_from: Literal["all", "train"] = "all"
    """Initial sparse points: all of them, or only those the SfM tracks show in at least 2 training views (no
    information from held-out or unused views reaches the model; COLMAP workspaces and synthetic scenes)."""
    normalize: bool = True
    """Move the scene centre (``center``) to the origin and scale the scene so that the camera rig has radius 1
    about its centroid (recorded as world_from_source)."""
    world_from_source: list[list[float]] | None = None
    """A fixed normalisation ([4,4]: x_world = s x_source + t, s > 0) instead of the one ``normalize`` computes
    from the cameras. A run's scene that photos joined after the run began (``reconstruct --extend``) is loaded with
    the run's own (``sfm.scene.load_for_run``): the cameras it trained with keep their place in its world, where the
    normalisation over the grown set of cameras would move them all."""
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Colour composited under images with an alpha channel, and rendered background."""
    max_points: int = Field(200_000, ge=1)
    """Cap on initial sparse points (random subset, seeded)."""
    center: Literal["auto", "optical_axes", "camera_centroid"] = "auto"
    """Scene centre used for normalisation and for random initial points. auto: where the optical axes meet
    for an inward-facing rig without sparse points (Blender / nerfstudio scenes), else the camera centroid
    (COLMAP scenes, forward-facing captures). The choice and its reason are recorded in RUN/scene.json."""
    principal_point_outside: bool = False
    """Accept cameras whose principal point lies outside their image or in its outer 5 % (crops of a larger photo,
    one side of a rectified pair). Off by default: that is what intrinsics measured on images of another size look
    like (a nerfstudio folder with full-size intrinsics and downscaled files trained off-centre, 13.6 dB for 19.4;
    halved files put the principal point on the corner: 14.8 dB for 19.5), and the scene is refused, naming the
    view."""
    photo_sizes: Literal["fit", "strict"] = "fit"
    """A COLMAP workspace whose images come in more than one size (portrait and landscape photos, two cameras).
    fit: the most common size is the scene's; a photo of the other orientation is turned a quarter turn (its
    camera with it, the way that puts the scene's up where the other photos have it; its maps are written turned
    back) and every photo within ``PHOTO_SIZE_TOLERANCE`` of that size is cropped to the size all of
    them share (a few pixels: undistortion crops each camera differently); a photo of another resolution of the
    same shape (``PHOTO_SHAPE_TOLERANCE``: a second camera) is resized to it, its camera scaled; photos of other
    shapes are left out, by name. strict: refuse such a workspace."""
    carve: bool = True
    """Random initial points (no sparse points) of a scene whose training images have real transparency: keep
    only those inside the alpha > 0.5 foreground of every training view that sees them (space carving)."""

    @field_validator("world_from_source")
    @classmethod
    def _check_frame(cls, v):
        if v is None:
            return v
        m = [list(map(float, row)) for row in v]
        if len(m) != 4 or any(len(row) != 4 for row in m) or not all(math.isfinite(x) for row in m for x in row):
            raise ValueError("world_from_source must be a 4x4 matrix of finite numbers")
        if m[3] != [0.0, 0.0, 0.0, 1.0]:
            raise ValueError(f"world_from_source's last row must be [0, 0, 0, 1], got {m[3]}")
        s = m[0][0]
        # a scale and a shift, as the normalisation makes them (the cameras are moved by those alone)
        if not (s > 0.0 and all(m[i][j] == (s if i == j else 0.0) for i in range(3) for j in range(3))):
            raise ValueError("world_from_source must scale by one positive number and shift (s on the diagonal of "
                             f"its 3x3 part, 0 elsewhere), got {[row[:3] for row in m[:3]]}")
        return m

    @field_validator("background", mode="before")
    @classmethod
    def _three_numbers(cls, v):  # (pydantic said "background.2: Field required" of two numbers)
        if isinstance(v, (list, tuple)) and len(v) != 3:
            raise ValueError(f"give 3 numbers (R, G, B) in [0, 1], e.g. [1, 1, 1] for white; got {len(v)}")
        return v

    @field_validator("background")
    @classmethod
    def _check_bg(cls, v):
        if any(not (0.0 <= c <= 1.0) for c in v):
            raise ValueError("background components must be in [0, 1]")
        return v


# ------------------------------------------------------------------------------------------------ train
class VariationalConfig(_Base):
    """The posterior of the variational multi-scale model (docs/method.md)."""

    num_entries: int = Field(10, ge=1, le=256)
    """K: offset-table entries per posterior carrier (1 = the paper's 'naive VI' ablation). Used by the SGD
    posterior; the informed posterior stores one entry per carrier (its entries would all be equal)."""
    subset_size: int = Field(2, ge=1, le=256)
    """M: entries averaged per sample (clamped to K)."""
    gate_temperature: float = Field(0.2, gt=0.0)
    """T in sigmoid((nu + tau * eta) / T)."""
    position_prior_std: float = Field(0.00248, gt=0.0)
    """Position prior std; in 'ours' as a fraction of the scene extent, in 'paper' in world units."""
    scale_prior_width: float = Field(0.1, gt=0.0, lt=1.0)
    """w_p: the scale-multiplier prior is U[1 - w_p, 1]."""
    gate_prior_mean: float = 2.0
    gate_prior_std: float = Field(1.996, gt=0.0)
    kl_weight: float = Field(1.0, ge=0.0)
    table_lr_factor: float = Field(0.1, gt=0.0)
    """Offset tables learn at this factor times their base attribute's rate (posterior = 'sgd')."""
    posterior: Literal["informed", "sgd"] | None = None
    """How the tables learn. informed: set in closed form from the training views' curvature (the Laplace
    optimum of the evidence lower bound; ``variational.informed_tables``) every ``refresh_interval`` steps
    and at the end, while SGD trains the Gaussians under samples of that posterior. sgd: the paper's
    stochastic-gradient tables with the KL in the loss. Default: informed for variant 'ours', sgd for
    'paper'."""
    refresh_interval: int = Field(500, ge=1)
    """Steps between two informed-posterior updates (each costs one render and ``probes`` backward
    passes per training view used). A step that resets the opacities (``densify.opacity_reset_interval``) has no
    update: its model is nearly transparent, and the tables fitted to it were the prior's until the next."""
    refresh_views: int = Field(64, ge=0)
    """Training views an update before the last step uses at most (drawn at random; the Fisher is scaled to all
    views); the last update uses every view. 0: every view every time."""
    probes: int = Field(2, ge=1, le=64)
    """Rademacher probes per training view for the curvature of the last update (informed): the posterior that
    ``evaluate`` samples."""
    refresh_probes: int = Field(1, ge=1, le=64)
    """Rademacher probes per training view for the updates before the last step, which only steer what the
    Gaussians are fitted to in between. Measured on the demo preset (BENCHMARKS.md, "Where a training step's time
    goes"): 1 instead of 2 takes the updates from 20.4 to 13.8 s of 274 s with the same PSNR, AUSE and NLL."""
    position_prior_scale: float = Field(1.0, ge=0.0)
    """Informed: a carrier's position prior std is the larger of position_prior_std x extent and this times its
    own size (geometric mean of its axes); 0 keeps only the fixed prior."""
    position_depth_fraction: float = Field(0.1, gt=0.0)
    """Informed: a carrier's position prior std is at most this fraction of its distance to the nearest training
    camera, so that no posterior sample moves a large, weakly constrained Gaussian (a background blob) in front
    of a camera (``gaussians.variational.informed_tables``; BENCHMARKS.md, "Training at half resolution first")."""
    train_on: Literal["samples", "expected", "mean"] = "mean"
    """Informed: what the Gaussians are fitted to between updates. mean: the posterior mean's render (the mode the
    posterior is spread around, as a Laplace posterior is; ``variational.posterior_mean``); expected: the expected
    render (``variational.expected_render_sample``: the samples' average render, each footprint widened by its
    position spread; the default until 2026-11-28); samples: renders of posterior samples (until 2026-11-25).
    Measured (BENCHMARKS.md, "Fitting the Gaussians to the posterior mean"), mean (with ``spawn_keeps_render``)
    against expected: the half ring's held-out views 19.20 -> 20.10 dB (plain 3DGS 20.24), unseen-surface AUC RGB
    0.955 -> 0.963; 5 sparse views at half the distance 25.34 -> 26.22 dB; the demo, fern and bonsai within 0.2 dB
    and 0.05 nats (bonsai's AUSE-MAE 0.015-0.027 worse). Fitted to the expected render, a Gaussian few views pin
    down is sharpened so that its widened footprint matches them, which new views then see."""
    spawn_keeps_render: bool = True
    """Informed: a Gaussian given a posterior (spawned) keeps its posterior-mean render, its base opacity and scale
    absorbing the prior's expected gate and mean multiplier, as every informed update does (``ops.spawn``); else the
    prior dims it by 17 % and shrinks it by 5 % at once, and training must win that back (half ring: 19.53 ->
    20.10 dB with it; BENCHMARKS.md, "Fitting the Gaussians to the posterior mean")."""
    split_keeps_render: bool = False
    """Informed: a split child of a Gaussian without a posterior (its new table rows at the prior) keeps the render
    3DGS's split gives it, its base opacity and scale absorbing the prior's expected gate and mean multiplier as
    ``spawn_keeps_render`` does (``ops.split``); off (the default), it renders 17 % dimmer and 5 % smaller than its
    sibling of a parent with a posterior. Measured (BENCHMARKS.md, "Split children keep their render, tried"):
    neutral on the synthetic protocols over 3 seeds, demo 32.69 -> 32.90 dB, but on fern it tipped the growth test
    (at the threshold there) into stopping at 64k Gaussians instead of 111k: 28.34 -> 28.15 dB held out."""
    sandwich: bool = False
    """Informed, last update only: widen the position and scale spreads by how much the training views disagree
    (the sandwich variance, ``uncertainty.curvature.curvature``), for a model the Gaussians cannot fit exactly.
    Measured (BENCHMARKS.md, "The sandwich variance"): better NLL and calibration, a better error ranking on a
    dense capture, 0.6 dB lower PSNR of the samples' mean and a weaker spread-only signal for unseen regions;
    off by default. Applied at every update it cost 2 dB (the Gaussians train under the wider samples)."""


MAX_ITERATIONS = 1_000_000
"""The most training steps a run (``TrainConfig.iterations``) or a growth test's copy (``growth_refit_steps``) takes:
33x the paper's 30k, hours at the fastest step measured, days on a photo scene; 1e20 was taken, with an ETA of
1e15 hours."""

PIXELS_PER_GAUSSIAN = 4.0
"""Default of ``DensifyConfig.pixels_per_gaussian`` (BENCHMARKS.md, "How many Gaussians a scene needs")."""


GROWTH_MIN_GAIN_DB = 0.25
"""The growth test's threshold without a re-fit (BENCHMARKS.md, "Growth that stops when it no longer pays")."""
GROWTH_MIN_GAIN_REFIT_DB = 0.15
"""The growth test's threshold with the rest re-fitted (BENCHMARKS.md, "The growth test with the rest re-fitted")."""


class DensifyConfig(_Base):
    """3DGS adaptive density control and the spawn rule."""

    start: int = Field(100, ge=0)
    until: int = Field(4000, ge=0)
    interval: int = Field(100, ge=1)
    grad_threshold: float = Field(2e-4, gt=0.0)
    """Screen-space mean-gradient threshold in NDC units as in 3DGS (pixel gradients x W/2, H/2), averaged
    over the views where the Gaussian is visible."""
    percent_dense: float = Field(0.01, gt=0.0)
    """Clone if max scale <= percent_dense * extent, else split."""
    split_factor: float = Field(1.6, gt=1.0)
    min_opacity: float = Field(0.005, ge=0.0, lt=1.0)
    opacity_reset_interval: int = Field(3000, ge=0)
    """0 disables opacity reset."""
    max_screen_size: float | None = Field(None, gt=0.0)
    """Prune Gaussians whose screen radius exceeds this many pixels (3DGS uses 20), after the first opacity reset."""
    max_gaussians: int | None = Field(None, ge=1)
    """The most Gaussians densification grows the model to. None (default): the scene's budget, one Gaussian per
    ``pixels_per_gaussian`` training pixels (``strategy.budget``; ``train_summary.json`` ``budget`` says which
    limit a run had and why)."""
    pixels_per_gaussian: float = Field(PIXELS_PER_GAUSSIAN, gt=0.0)
    """The automatic budget's training pixels per Gaussian (used when ``max_gaussians`` is None)."""
    growth_min_gain_db: float | None = Field(None, ge=0.0)
    """Stop adding Gaussians once the model's last doubling no longer pays: every ``growth_check_interval`` steps
    while densifying, the weakest half of the Gaussians ``growth_check_views`` training views see is taken out of a
    copy of the model, the rest re-fitted for ``growth_refit_steps`` steps beside a copy of the whole model trained
    as long; when the half is worth less than this many dB of the views' PSNR (``growth_patience`` tests in a row),
    densification never again takes the model past its size at that test, filling only the room pruning makes
    (only pruning with ``growth_refit_steps = 0``; ``strategy.growth``; each test is in ``train_summary.json``
    ``growth``). None (default): ``GROWTH_MIN_GAIN_REFIT_DB`` (0.15 dB) with the re-fit, ``GROWTH_MIN_GAIN_DB``
    (0.25 dB) without it (``growth_refit_steps = 0``: the half only switched off, which overstates what a model of
    half the size would lose). 0: grow up to ``max_gaussians`` as 3DGS does. Measured on four scenes in
    BENCHMARKS.md, "Growth that stops when it no longer pays" and "The growth test with the rest re-fitted". No
    test runs while the model is within 1 % of ``max_gaussians`` (``strategy.growth.at_budget``)."""
    growth_refit_steps: int = Field(100, ge=0, le=MAX_ITERATIONS)
    """Steps each copy of the growth test trains (the whole model's, and the one without the weakest half) before
    their PSNRs are compared; 0: no copies, the half switched off in the model as it is (the test before the
    re-fit: faster, but it kept growing a forward-facing capture such as fern at 1/8 to 3x its knee)."""
    growth_check_interval: int = Field(250, ge=1)
    """Steps between growth tests."""
    growth_skip_factor: float | None = Field(3.0, ge=1.0)
    """A test whose half costs at least this many times the threshold skips the next test due (growth goes on
    meanwhile): a cost that far above the threshold has not fallen below it one interval later on the scenes
    measured, and each test's copies train ``2 x growth_refit_steps`` steps, up to +60 % of the densification
    window's steps on a capture that grows through all of it (BENCHMARKS.md, "Growth tests skipped far above the
    threshold"). A test that could not tell (a copy that could not train or ran out of memory) skips the next too.
    Only with ``growth_refit_steps`` > 0. None: a test at every interval."""
    growth_patience: int = Field(2, ge=1)
    """Growth stops when this many tests in a row find the half cheaper than ``growth_min_gain_db`` (one test right
    after densification starts sees a model that has not fitted yet)."""
    growth_check_views: int = Field(8, ge=1)
    """Training views rendered for each growth test (one render and one backward pass each for the blending
    weights, then one render per model compared)."""

    @property
    def growth_threshold_db(self) -> float:
        """``growth_min_gain_db`` as the growth test applies it (its default filled in by ``growth_refit_steps``)."""
        if self.growth_min_gain_db is not None:
            return self.growth_min_gain_db
        return GROWTH_MIN_GAIN_REFIT_DB if self.growth_refit_steps > 0 else GROWTH_MIN_GAIN_DB
    spawn_interval: int = Field(1000, ge=1)
    spawn_scale_fraction: float = Field(0.01, gt=0.0)
    """Spawn: carry a posterior when ||scale|| > this * extent ..."""
    spawn_min_opacity: float = Field(0.0005, ge=0.0)
    """... and opacity >= this."""


class LearningRates(_Base):
    """Adam learning rates (3DGS defaults)."""

    means_init: float = Field(1.6e-4, gt=0.0)
    """Times the scene extent; decays exponentially to means_final."""
    means_final: float = Field(1.6e-6, gt=0.0)
    sh0: float = Field(2.5e-3, gt=0.0)
    shN: float = Field(2.5e-3 / 20, gt=0.0)
    opacities: float = Field(0.05, gt=0.0)
    scales: float = Field(5e-3, gt=0.0)
    quats: float = Field(1e-3, gt=0.0)


class FisherConfig(_Base):
    """Post-hoc Laplace/Fisher baseline (``method = "fisher"``; ``uncertsplat.baselines.fisher``)."""

    estimator: Literal["ggn", "empirical"] = "ggn"
    """ggn: diag(J^T J) / noise^2 by Rademacher probes (unbiased); empirical: squared per-view gradients."""
    probes: int = Field(2, ge=1, le=64)
    """Rademacher probe vectors per training view (ggn only)."""
    noise_std: Literal["auto"] | float = "auto"
    """Observation noise std of the Gaussian likelihood; auto: RMS training residual."""
    params: list[Literal["means", "scales", "opacities", "sh0"]] = Field(["means", "scales", "opacities", "sh0"],
                                                                         min_length=1)
    """Per-Gaussian parameters that get a posterior (scales are log-scales, opacities logits); at least one (an empty
    list trained the whole model, then failed at the Fisher pass, on every --resume too)."""
    prior_std_means: float = Field(0.01, gt=0.0)
    """Prior std of the means, as a fraction of the scene extent."""
    prior_std_scales: float = Field(0.1, gt=0.0)
    prior_std_opacities: float = Field(0.5, gt=0.0)
    prior_std_sh0: float = Field(0.1, gt=0.0)


class TransientsConfig(_Base):
    """Transient objects in the training photos (a person walking through, a car that left), found from the
    residual and left out of the loss (``train.transients``)."""

    detect: bool = False
    """Find them: from step ``start x iterations`` on, each step's regions whose residual stands far above the
    photo's typical residual are left out of its loss, as a mask a user brought would leave them (each photo's last
    regions also out of the posterior's noise and curvature and the training checks). After each pass over the
    photos, a test that has found regions in three quarters of them or more (of at least 4) switches itself off
    (parts of the scene the model cannot fit, not objects that came and went: bonsai's flowers at 20 dB) and
    ``train`` warns. Off by default: on scenes the model fits well a photo without transients loses nothing but the test's cost; measured in
    BENCHMARKS.md, "Transient objects found from the residual". Masks a user brings (docs/guide.md, "Masks") are exact where
    this is a guess."""
    start: float = Field(0.5, ge=0.0, le=1.0)
    """The share of the iterations before the first test: before it the model is far from every photo."""
    threshold: float = Field(5.0, gt=1.0)
    """A pixel is a candidate when its residual (mean absolute over the channels) is this many times the photo's
    median residual."""
    window: float = Field(0.06, gt=0.0, le=0.5)
    """The square window, as a share of the image's short side (at least 3 pixels): a region is transient where a
    share ``core`` of a window's pixels are candidates, and is widened by half a window. Bands of large residual
    narrower than that (the silhouettes and edges the model has not sharpened yet) stay in the loss; objects
    smaller than it are not found."""
    core: float = Field(0.7, gt=0.0, le=1.0)
    """The share of a window's pixels that must be candidates for its centre to be transient."""
    max_share: float = Field(0.5, gt=0.0, le=1.0)
    """A photo whose transient regions would cover more than this share of it keeps every pixel in that step (a
    model far from that photo, not an object in front of it)."""


TRAIN_SEED_MAX = 2**32 - 8
"""The largest training seed (``TrainConfig.seed``; an ensemble's, plus its ``ensemble_size - 1``, the seed of its
last member): the trainer's generators take seed + at most 5, and all stay below 2**32, which torch's CPU generator
keeps whole."""


class TrainConfig(_Base):
    """Training (``uncertsplat train``)."""

    method: Literal["variational", "deterministic", "ensemble", "fisher"] = "variational"
    """variational: ours; deterministic: plain 3DGS; ensemble / fisher: baselines (``uncertsplat.baselines``)."""
    ensemble_size: int = Field(10, ge=1, le=1000)
    """N: independently seeded members of ``method = "ensemble"`` (seeds seed .. seed + N - 1)."""
    ensemble_members: Literal["deterministic", "variational"] = "deterministic"
    """What each member of ``method = "ensemble"`` is: plain 3DGS (the deep-ensemble baseline: the uncertainty is the
    members' spread), or our variational model (each sample a posterior sample of one member: the members' spread
    and each one's posterior together)."""
    fisher: FisherConfig = FisherConfig()
    """Settings of ``method = "fisher"``."""
    variant: Literal["ours", "paper"] = "ours"
    """paper: the original code's choices (log-scale multiplier, absolute position prior)."""

    iterations: int = Field(7000, ge=0, le=MAX_ITERATIONS)
    """Training steps, at most ``MAX_ITERATIONS`` (1,000,000); 0 only with ``init_ply`` (no step trained)."""
    init_ply: Path | None = None
    """A 3DGS model trained elsewhere, as a PLY file in the standard layout (INRIA's 3DGS, gsplat, nerfstudio's
    export, SuperSplat's uncompressed PLY, Mip-Splatting's with its 3D filter folded in, or a run's
    ``point_cloud.ply``), to give the informed posterior (``train --from-ply``): the run starts from its Gaussians
    instead of the scene's points, the spawn rule gives the large ones a posterior (each rendering as in the file),
    and with ``iterations = 0`` no step is trained, so only the posterior update of the last step runs, over every
    training view of the scene. The scene must be the one the model was trained on (its cameras in the same frame:
    ``init_ply_frame``). Needs the variational method with the informed posterior."""
    init_ply_frame: Literal["auto", "source", "run", "align"] = "auto"
    """The frame of ``init_ply``'s Gaussians: ``source`` the scene's own coordinates (the COLMAP model's, as other
    tools train in them), moved into the run's normalised frame by the scene's ``world_from_source``; ``run`` the
    normalised frame already (a ``point_cloud.ply`` of uncertsplat); ``align`` a frame of the model's own, found by
    placing its Gaussians on the scene's sparse points (a similarity: scale, rotation, shift; ``sfm.align``), for a
    trainer that normalised its world and did not write how (gsplat's simple_trainer), then fitted to 8 training
    photos; ``auto`` ``run`` for files uncertsplat wrote, otherwise ``source``, or ``align`` when the Gaussians read in
    the source frame do not lie on the scene's sparse points and a frame found places them there and is pinned by
    them (points on about one plane or line pin none: ``sfm.align.MIN_FIRMNESS``)."""
    init_ply_transform: Path | None = None
    """A JSON file with the similarity that took the scene's source coordinates into ``init_ply``'s (x_file = s R
    x_source + t), for a trainer that normalises its world before training: nerfstudio's ``dataparser_transforms.json``
    (``transform`` and ``scale``), or ``{"file_from_source": [[4x4]]}``. The Gaussians' positions, sizes, rotations and
    SH colours are moved back through it (``train --from-ply-transform``)."""
    seed: int = Field(0, ge=0, le=TRAIN_SEED_MAX)
    """At most ``TRAIN_SEED_MAX`` (2**32 - 8; an ensemble: with its last member's seed, seed + ensemble_size - 1):
    the trainer's generators take seed + a few, and torch's CPU generator keeps a seed's low 32 bits (seeds s and
    s + 2**32 trained the same model; 2**64 was a traceback at the start)."""
    profile: bool = False
    """Time every phase of a training step (data, sample, render, loss, backward, optimizer, densify, posterior
    update, evaluation, checkpoints) into ``train_summary.json`` ``profile``; on CUDA this synchronises the
    device at every phase boundary."""
    sh_degree: int = Field(3, ge=0, le=3)
    sh_degree_interval: int = Field(1000, ge=1)
    sh_min_gain_db: float = Field(0.05, ge=0.0)
    """Keep an SH band only if it pays: when band d has trained for ``sh_degree_interval`` steps, training views
    are rendered with and without it, and a band that raises their PSNR by less than this many dB is dropped with
    every band above it (a smaller model, a smaller PLY and cheaper steps; ``strategy.sh_bands``). Each test and
    its outcome is in ``train_summary.json`` ``sh_bands``. 0 keeps every band up to ``sh_degree``."""
    sh_check_views: int = Field(8, ge=1)
    """Training views rendered (twice) for each band test."""
    sparse_updates: Literal["dense", "visible", "lazy"] = "dense"
    """Which rows Adam updates each step: ``dense`` every Gaussian (torch's Adam); ``visible`` only the Gaussians
    with a footprint in the step's views (and their offset-table rows), the others' parameters and moments left
    as they are; ``lazy`` as visible, with the skipped steps' decay applied to a row's moments when it comes back
    (``train.adam``). Measured in BENCHMARKS.md, "Sparse Adam updates"."""
    drop_rate: float = Field(0.0, ge=0.0, lt=1.0)
    """Leave each Gaussian out of a step's render with probability ``drop_rate x step / iterations`` (the
    others' opacity divided by 1 - rate): a regulariser against fitting the training views with Gaussians no
    other view checks, for sparse captures. 0: off."""
    random_background: bool = False
    """Render each training step over a random colour (uniform in [0, 1] per channel, its own random stream)
    instead of ``scene.background``: a ray the model leaves partly empty then shows a colour that changes from step
    to step, so the photos' surfaces, dark ones too, are fitted with Gaussians rather than with a black background
    showing through (which `evaluate`'s empty-ray term would count as a surface no view saw). Evaluation renders
    over ``scene.background`` as always. Not for training images with transparency (their background is data):
    ignored there, with a note."""
    low_res_fraction: float = Field(0.0, ge=0.0, lt=1.0)
    """The first ``low_res_fraction`` of the iterations train on the images (and cameras) scaled by
    ``low_res_scale``, area-averaged: the rasterizer's cost is per pixel, and the early steps, which place and
    grow the Gaussians, need the coarse picture more than the fine one. The steps after it, and every evaluation,
    growth and SH-band test, use the full images. The phase ends at step ``low_res_fraction x iterations`` of the
    run's current ``iterations`` (a resume that extends them extends it while the run is still in the phase; a run
    already past it stays at full resolution). 0: off. Measured in BENCHMARKS.md,
    "Training at half resolution first"."""
    low_res_scale: float = Field(0.5, gt=0.0, le=1.0)
    """The image scale of the low-resolution steps (``low_res_fraction``)."""
    transients: TransientsConfig = TransientsConfig()
    """Transient objects in the training photos found from the residual (``TransientsConfig``)."""
    exposure: Literal["off", "auto", "affine"] = "off"
    """``affine``: each training photo gets a gain and an offset per colour channel, learned with the model, so that
    photos of different exposure or white balance (automatic exposure, outdoor light) are not fitted with floaters
    (``render.exposure``); ``evaluate`` compares the training photos at the model's exposure and adds the spread of
    the learned exposures to a new view's variance. ``off``: every photo is taken as it is (``train`` warns at the end
    when they differ in brightness). ``auto``: as ``off`` until a test finds the photos' brightness different
    (``strategy.exposure``; each test in ``train_summary.json`` ``exposure_checks``), then as ``affine``. ``off`` is
    the default: ``affine`` costs 0.1-0.5 dB on photos of one exposure, and ``auto``'s test also fires on bonsai
    (BENCHMARKS.md, "Photos of different exposure")."""
    exposure_check_interval: int = Field(250, ge=1)
    """Steps between the exposure tests of ``exposure = "auto"`` (up to half of the iterations)."""
    exposure_lr: float = Field(2e-3, gt=0.0)
    """Adam learning rate of the exposure parameters (log gain and offset)."""
    ssim_lambda: float = Field(0.2, ge=0.0, le=1.0)
    ssim_cache_mb: float = Field(1024.0, ge=0.0)
    """Memory (MiB) for the training photos' own SSIM statistics, kept from each photo's first step (8 bytes per
    pixel and channel: 2.6 MB for a 401x266 photo): the fused CPU SSIM then blurs three of its five quantities a step, the
    same loss to the bit (BENCHMARKS.md, "The photos' SSIM statistics kept"). Photos beyond the budget are blurred
    every step as before. 0: off. Unused on CUDA."""
    tile_size: int = Field(8, ge=2, le=64)
    batch_size: int = Field(1, ge=1)
    init_opacity: float = Field(0.1, gt=0.0, lt=1.0)
    init_num_random: int = Field(0, ge=0, le=2_000_000)
    """Add this many random points in the scene box when the sparse cloud is poor (at most 2,000,000, the largest
    model budget: 10^12 tried to allocate 12 TB)."""
    init_outlier_factor: float = Field(10.0, ge=0.0)
    """Sparse points farther from the cloud's median point than this many times the larger of the cloud's
    90th-percentile distance and the cameras' radius start no Gaussian (``gaussians.params.far_points``): a lone
    point far out (a bad triangulation) becomes a Gaussian as wide as its distance to its nearest neighbour, and a
    trace of its weight on a ray pulls the depth maps by its distance (one point at 1e6 units: depth abs-rel 0.05 ->
    374). 0: every point starts a Gaussian."""
    log_every: int = Field(50, ge=1)
    eval_every: int = Field(500, ge=1)
    checkpoint_every: int = Field(1000, ge=1)
    keep_checkpoints: int = Field(3, ge=1)
    scene: SceneConfig = SceneConfig()
    variational: VariationalConfig = VariationalConfig()
    densify: DensifyConfig = DensifyConfig()
    lr: LearningRates = LearningRates()

    @field_validator("method", mode="before")
    @classmethod
    def _option_only(cls, value):
        # `--method paper` and `--method vi-single` are the option's shorthands for keys, not values of this key (a
        # `--set method=vi-single` or a pipeline's `method = "vi-single"` was refused naming the four values only)
        keys = {"paper": "variant = \"paper\"",
                "vi-single": "variational.num_entries = 1 and variational.posterior = \"sgd\""}
        if isinstance(value, str) and value in keys:
            raise ValueError(f"{value!r} is a shorthand of `uncertsplat train --method`, not a value of this key: it "
                             f"sets {keys[value]} (with method \"variational\"): set those keys instead (in a file, a "
                             "pipeline stage's config or with --set)")
        return value

    @model_validator(mode="after")
    def _members_seeds(self):
        if self.method == "ensemble" and self.seed + self.ensemble_size - 1 > TRAIN_SEED_MAX:
            raise ValueError(f"seed: an ensemble's members take seeds seed .. seed + ensemble_size - 1, and the last, "
                             f"{self.seed + self.ensemble_size - 1}, is over {TRAIN_SEED_MAX} (torch's CPU generator "
                             f"keeps 32 bits): give a seed of at most {TRAIN_SEED_MAX - self.ensemble_size + 1}")
        return self

    @model_validator(mode="after")
    def _imported_model(self):
        if self.init_ply is None:
            if self.init_ply_transform is not None:
                raise ValueError("init_ply_transform is the frame of a model given by init_ply (`train --from-ply "
                                 "MODEL.ply --from-ply-transform FILE`); give the model too, or drop the transform")
            if self.iterations == 0:
                raise ValueError("iterations: 0 trains nothing; it is for a model given by init_ply (`train "
                                 "--from-ply MODEL.ply`), to build its posterior only. Give at least 1 step")
            return self
        if self.method != "variational" or self.posterior != "informed":
            raise ValueError("init_ply: a model trained elsewhere gets the informed posterior (method \"variational\", "
                             "variational.posterior = \"informed\", variant \"ours\", the defaults); drop --method, "
                             f"--variant or the posterior setting (given: method {self.method!r}, variant "
                             f"{self.variant!r}, posterior {self.posterior!r})")
        if self.init_ply_transform is not None and self.init_ply_frame in ("run", "align"):
            raise ValueError(f"init_ply_transform with init_ply_frame = \"{self.init_ply_frame}\": the transform "
                             "takes the scene's source frame to the model's, so "
                             + ("the model is not in the run's frame" if self.init_ply_frame == "run" else
                                "there is no frame to find")
                             + "; drop one of the two")
        if self.exposure == "affine":
            # (accepted before: every gain 1, an exposure.json of nothing learned, and train's warning on photos of
            # different brightness silenced as if their exposures had been learned)
            raise ValueError("init_ply with exposure = \"affine\": the exposures are learned with the model's training, "
                             "which a model trained elsewhere does not have here (no step is trained); drop the "
                             "setting (train warns when the photos differ in brightness against the model)")
        if self.transients.detect:
            # (accepted before, and train said "found in none of the training photos" without a test made)
            raise ValueError("init_ply with transients.detect: transient objects are found from the residuals of "
                             "training steps, which a model trained elsewhere does not have here (no step is "
                             "trained); drop the setting, or give the photos' masks (a workspace's masks/)")
        if self.iterations != 0:
            raise ValueError(f"init_ply with iterations = {self.iterations}: a model trained elsewhere is given its "
                             "posterior as it is (iterations = 0, what --from-ply sets); training it on from its "
                             "Gaussians is not supported (the schedule would densify and reset it as a fresh run)")
        return self

    @model_validator(mode="after")
    def _posterior_for_variant(self):
        if self.variational.posterior == "informed" and self.variant == "paper":
            raise ValueError("variational.posterior = 'informed' needs variant 'ours' (the paper variant learns its "
                             "tables by SGD); drop one of the two settings")
        return self

    @property
    def has_offset_tables(self) -> bool:
        """Whether the run's models carry offset tables: our variational model, or an ensemble of it."""
        return self.method == "variational" or (self.method == "ensemble" and self.ensemble_members == "variational")

    @property
    def posterior(self) -> str:
        """The posterior that trains: ``variational.posterior``, or its default for the variant (informed for
        'ours', sgd for 'paper')."""
        return self.variational.posterior or ("sgd" if self.variant == "paper" else "informed")


TRAIN_PRESETS: dict[str, dict[str, Any]] = {
    # for tests: seconds on a CPU
    "tiny": {
        "iterations": 300,
        "sh_degree": 1,
        "sh_degree_interval": 100,
        "log_every": 25,
        "eval_every": 100,
        "checkpoint_every": 100,
        "densify": {"start": 50, "until": 250, "interval": 50, "spawn_interval": 100, "opacity_reset_interval": 0},
    },
    # the embedded synthetic demo scene (GT cameras), sized to train in a few minutes on a 2-core CPU. SH degree
    # 0 because the scene is Lambertian (colour does not depend on the view). 3500 steps is the shortest of the
    # schedules tried that reaches the demo's PSNR target with a margin inside its time budget; longer ones add
    # little. The cap of 40k Gaussians bounds the cost of a step. Times and PSNR for 2000-4000 steps:
    # BENCHMARKS.md, "The expected render, and the `demo` preset at 3500 steps".
    "demo": {
        "iterations": 3500,
        "sh_degree": 0,
        "log_every": 50,
        "eval_every": 500,
        "checkpoint_every": 500,
        "densify": {"start": 100, "until": 2250, "interval": 100, "spawn_interval": 250,
                    "opacity_reset_interval": 0, "max_gaussians": 40000},
    },
    # the paper's LLFF setting (1/8 resolution, 7000 steps, densify until 4000)
    "paper": {
        "iterations": 7000,
        "scene": {"downscale": 8.0},
        "densify": {"until": 4000},
    },
}


# --------------------------------------------------------------------------------------------- evaluate
EVAL_SEED_MAX = 2**32 - 1
"""The largest seed of the stages whose per-view seeds are ``seed x 1,000,003 + index`` (``eval.engine.view_seed``):
torch's CPU generator keeps a seed's low 32 bits, so seeds s and s + 2**32 gave the same maps (a helper's 2**32 and
2**40 repeated seed 0; the view seeds of two seeds below 2**32 differ in those bits, 1,000,003 being odd); every
view seed stays a 64-bit one (``predict.MAX_SEED`` is this)."""
MAX_DEGREES_OF_FREEDOM = 1000.0
"""The largest Student-t nu accepted (``eval.tails.MAX_DOF``, where a fit reads as the Gaussian): far beyond, the
t's log-density loses its digits (1e15 gave an NLL of 17.7 for -1.56, 1e300 a traceback)."""


class EvalConfig(_Base):
    """Uncertainty rendering and metrics (``uncertsplat evaluate``)."""

    split: Literal["test", "train"] = "test"
    num_samples: int = Field(10, ge=1, le=10_000)
    """K_eval: posterior samples per view (cost grows linearly)."""
    seed: int = Field(0, ge=0, le=EVAL_SEED_MAX)
    depth_gt: Path | None = None
    """Folder of GT depth maps ({image stem}.npy, .exr, 16-bit .png or float .tif); synthetic scenes provide their own."""
    depth_scale: Literal["auto", "scene"] | Annotated[float, Field(ge=1e-30, le=1e30)] = "auto"
    """Factor from rendered depth to GT depth units (1e-30 to 1e30: float32's range; 1e-300 made every rendered depth
    0). auto: the scene's own GT depth is in known units, a
    ``depth_gt`` folder's factor is fitted (``depth_align``); scene: the ``depth_gt`` maps are in the scene's own
    units (its COLMAP model's, e.g. a metric map's), the known factor of ``RUN/scene.json``."""
    depth_align: Literal["median", "lsq"] = "median"

    @field_validator("depth_gt", mode="after")
    @classmethod
    def _depth_gt_home(cls, v: Path | None) -> Path | None:
        return _home(v)

    std_floor: float = Field(1e-3, ge=1e-18, le=0.01)
    """The NLL uses max(std, std_floor) so a zero std does not give an infinite NLL (the depth NLL: std_floor in the
    run's normalised units, carried into the GT maps' units with the depths). At most 0.01 (1 % of the colour
    range): the std factor is fitted with the floor under the raw std and applied before the metrics' floor, which
    agree only while the floor is well below the std (a floor of 0.1 made the calibrated calibration error 0.14
    against a raw 0.03). At least 1e-18, whose square float32 still holds (1e-50 was 0 there: with every other
    term off a zero std divided the errors and the NLL was no number)."""
    paper_nll: bool = False
    """Also report the original code's KDE NLL formula (not comparable with a correct NLL)."""
    ause_steps: int = Field(100, ge=2, le=10_000)
    save_maps: bool = True
    preview: Literal["percentile", "fixed"] = "percentile"
    max_views: int | None = Field(None, ge=1)
    """Evaluate only the first n views of the split (for quick looks)."""
    reuse: bool = True
    """Keep an evaluation that measured what this one would: the run's own ``eval/`` when it scored the same model
    file, views and settings by the same versions on the same device (e.g. written by ``prune``, which evaluates
    the run it writes; ``stages.evaluate.matching_evaluation``), or, for a ``prune`` output that removed nothing
    (its model file byte for byte the source run's), the source run's evaluation, copied (``same_model_evaluation``;
    it says so in its notes). False: always evaluate."""
    calibration_views: int = Field(8, ge=0)
    """Fit one factor for the RGB std on this many evenly spaced training views (0: none); the metrics
    ``nll_calibrated`` and ``calibration_error_calibrated`` use std x factor, the maps keep the raw std.
    Costs K renders per view; only with ``split = "test"``."""
    resolution_on_training_views: bool = False
    """Keep the resolution term in the predictive the std factor is fitted on, when it is fitted on training views
    (no views set aside). The term stands for what the training images cannot show, Gaussians trading places unseen
    in them, and on those images it exceeded the residuals the model left, so the factor came out low and made new
    views' std too narrow: held-out NLL with the factor fitted without it, fern -2.347 -> -2.421, bonsai -0.815 ->
    -0.921, the demo -3.308 -> -3.267 (Gaussian; BENCHMARKS.md, "The std factor on training views without the
    resolution term"). True: the factor as before 2026-11-30. With ``residual_scale = "fit"`` (and a pixel noise,
    ``residual_views`` > 0) and no views set aside the term is kept regardless: the noise's level was fitted on those
    views given it."""
    degrees_of_freedom: Literal["fit", "gaussian"] | Annotated[float, Field(ge=2.1, le=MAX_DEGREES_OF_FREEDOM)] = "fit"
    """The RGB predictive's tails: a Student-t with the predicted std and nu degrees of freedom (``eval.tails``), or
    the Gaussian. A pixel's error given its std is heavy-tailed (the std estimates the error's scale, which varies
    around it): z-scores with a kurtosis of 9-14 on the demo, fern and bonsai, which a Gaussian of the right
    variance covers too often at one std and too rarely at three. ``fit`` (the default): nu by maximum likelihood on
    the views the std factor is fitted on (``calibration_views``; z-scores divided by their RMS, so nu sets the
    shape and not the level), the Gaussian where there are none; a number: that nu. The NLL, the calibration table
    and the calibration error use it (raw and calibrated); the maps keep the std; depth stays Gaussian. The
    Gaussian reading of the same std is reported beside (``nll_gaussian``, ``calibration_error_gaussian``).
    Measured in BENCHMARKS.md, "The predictive's tails"."""
    empty_rays: bool = True
    """Where a ray is covered less than the model covers the surfaces its training views saw (the alpha that 95 %
    of the training pixels reach, ``uncertainty.mc.training_coverage``), the model has no surface for that part of
    the pixel: add the std of an unknown colour (uniform in [0, 1]: 0.289) and an unknown depth (the scene
    extent), weighted by (1 - alpha / coverage)_+^2 (``uncertainty.mc.mc_render``). Not for scenes whose training
    images are transparent (the background is then data): there a ray that meets little of the model through space
    no photo saw empty gets (1 - alpha)^2 of the view-consistency term's palette variance instead, and (with
    ``hidden_depth``) below alpha 0.5 the depth variance of a surface anywhere between the model's nearest and
    farthest Gaussians, and a hidden point's depth stretch counts the space behind it too
    (``uncertainty.consistency.ViewConsistency.unseen_empty``). False: none of these."""
    resolution: float = Field(0.3, ge=0.0, le=10.0)
    """The resolution term: however many views constrain it, a Gaussian's position is known only to within this
    fraction of its own size (geometric mean of its axes), since neighbouring Gaussians can trade places that
    much with no visible change in the training views (a diagonal posterior cannot represent that). Each of the
    K samples is paired with ``resolution_renders`` renders of the model with every Gaussian moved by
    N(0, (resolution x size)^2); their variance is added to the RGB and depth variance (the prediction stays the
    samples' mean). 0: off. Also subtracted from the training residual the pixel noise is
    fitted on."""
    resolution_renders: int = Field(2, ge=1, le=100)
    """Renders of the resolution term per posterior sample. Its variance is estimated from K x this many renders,
    and at K = 10 its Monte Carlo noise is what costs the std's ranking most (BENCHMARKS.md, "The resolution term's
    renders": demo AUSE-MAE 0.131 at 1, 0.128 at 2, 0.127 at 3 or with K = 30; fern 0.193 -> 0.192 at 2). Each one
    more costs K renders per evaluated view."""
    residual_views: int = Field(64, ge=0)
    """Add the pixel noise the model leaves on its training views to the RGB std: each Gaussian's mean squared
    residual over the training pixels it is blended into (``uncertainty.residual``), rendered per pixel. Fitted
    on at most this many evenly spaced training views (one render and one backward pass each, before the timed
    evaluation); 0: off, the std is the samples' spread (and the empty-ray term) only. Fewer views cost ranking
    (BENCHMARKS.md, "How many training views the pixel noise is fitted on": bonsai's AUSE-MAE 0.336 with its 42 views,
    0.348 with 16, for 3.4 s of a 29 s evaluation)."""
    residual_scale: Literal["auto", "fit"] | Annotated[float, Field(gt=0.0, le=1e30)] = "auto"
    """The pixel noise's level: a factor for the fitted per-Gaussian noise (1: each Gaussian's mean squared training
    residual itself), or ``fit``: the unit z-variance factor given the rest of the predictive
    (``eval.engine.fit_noise_scale``) on the views set aside from training when the scene has some
    (``SceneConfig.calibration_holdout``), else on training views. ``auto`` (the default): ``fit`` on views set
    aside, 1 without them. Fitted on training views it calibrates views like the training ones (demo: std factor
    0.63 -> 0.88, both fitted with the resolution term as before 2026-11-30, calibration error 0.100 -> 0.055; fern
    0.85 -> 1.00, 0.052 -> 0.035) but makes the std too small where the model renders worse than on its training
    views (NLL: sparse views -2.61 -> -2.34, half-ring 0.26 -> 1.52, bonsai -1.00 -> -0.75; BENCHMARKS.md, "The
    pixel noise's level"), hence 1 there; fitted on views set aside it improves the raw NLL and calibration error on
    the demo, fern and bonsai (BENCHMARKS.md, "Views set aside for calibration"). A factor at most 1e30 (1e300
    overflowed float32: the std was no number in every pixel)."""
    colour_posterior: bool = True
    """Add the colour the model does not know to the RGB std: the Laplace posterior of each Gaussian's colour (its
    SH coefficients) given the training pixels it is blended into, seen from the evaluated view
    (``uncertainty.residual``, "The colour posterior"). Negligible where the training views pinned a Gaussian's
    colour down; the prior's (the training pixels' variance) for a Gaussian no view saw, e.g. a surface a new view
    uncovers; in between for a colour seen from few directions and looked at from a new one (SH degree > 0).
    Fitted in the same pass as the pixel noise (``residual_views`` > 0), no extra render."""
    colour_covariance: Literal["block", "diagonal"] = "block"
    """The colour posterior's form (``uncertainty.residual``): ``block`` (the default since 2026-12-01) takes the DC
    term and SH band 1 jointly (the exact Laplace posterior at SH degree <= 1: a colour seen from one side is unknown
    from the other), ``diagonal`` each SH coefficient on its own (the form before, which gives the direction opposite
    a view that view's certainty). The higher bands are diagonal in both; at SH degree 0 the two are one. Measured
    (BENCHMARKS.md, "The colour posterior's DC term and band 1 jointly"): the half ring at SH degree 1 NLL -1.178 ->
    -1.183, calibration error 0.057 -> 0.051, the same ROC AUC; fern -2.457 -> -2.455, AUSE-MAE 0.188 -> 0.189.
    Costs 128 bytes per Gaussian in the fitted noise (``RUN/eval/residual.pt``) when the model has SH band 1."""
    consistency_views: int = Field(64, ge=0)
    """The view-consistency term (``uncertainty.consistency``): each pixel's surface point, at the rendered depth, is
    compared with the same point in the training view that saw it from the nearest direction, and the squared
    difference of the model's two renders is added to the RGB variance, weighted by that angle: 0 up to twice the
    capture's own spacing, in full from four times it. What the rest of the predictive, fitted on the training views,
    cannot see: how a surface the views saw looks from directions none came from. Measured (BENCHMARKS.md, "Surfaces
    seen from a new direction"): trained on half the demo ring and tested on the other half, NLL -0.20 -> -1.16 and
    calibration error 0.137 -> 0.038 (AUSE-MAE 0.156 -> 0.166, and the unseen-surface ROC AUC 0.953 -> 0.901: the
    surfaces seen from the other side now count as uncertain too); fern with the last photos held out, the
    correlation over views of the mean std with the error -0.39 -> +0.31; dense captures and sparse views unchanged.
    Compares at most this many training views (evenly spaced), each rendered once per evaluation and kept (rgb as
    float16 and depth: 10 bytes per pixel); 0: off."""
    depth_spread: bool = True
    """Add to the depth variance the spread of the depths each ray blends, ``sum_i w_i z_i^2 / alpha - depth^2`` of the
    model's deterministic render (``uncertainty.mc.depth_spread``; two renders per evaluated view): a rendered depth
    is the weighted mean of the Gaussians' depths along the ray, and where a ray crosses an edge, a thin layer or a
    floater, that mean lies between surfaces. Measured on the demo (BENCHMARKS.md, "The depths a ray blends"):
    depth NLL 7.8 -> -2.6, depth calibration error 0.51 -> 0.08, depth AUSE-MAE 0.139 -> 0.129. False: the
    samples' spread, the resolution term and the empty rays only."""
    hidden_depth: bool = True
    """Where no compared training view sees a pixel's surface point (hidden behind what every photo holding it saw, or
    outside them all), add ``L^2 / 12`` to the depth variance (a point uniform on a stretch of length L), L the stretch
    of the view's ray in front of the point that no compared training view saw empty: a surface anywhere on it would
    have looked the same to every photo (``uncertainty.consistency``, "A surface no photo saw"; up to 20 points along
    each such ray tested against the compared views' renders). On scenes whose photos are transparent (with
    ``empty_rays``), L counts the stretch behind the point too, up to where a photo saw empty (20 more points), and
    the faint rays through unseen space get their depth variance (``empty_rays``). Nothing is fitted. Measured
    (BENCHMARKS.md, "A depth no photo pinned down", "The far side of an object"). Needs the view-consistency term
    (``consistency_views`` > 0), whose renders and lookup it uses. False: none."""
    edge_noise: bool = True
    """Split the pixel noise into an edge term and the per-Gaussian rest (``uncertainty.residual``, "The edge
    term"): a misplacement of delta pixels changes a pixel by about delta x the image gradient there, so each
    pixel gets ``delta^2 |grad I(p)|^2`` of the view's own render, with delta^2 fitted to the training residuals
    beyond the resolution term by least squares (one render per residual view and one per evaluated view), and
    each Gaussian's noise is fitted to what that leaves. Measured (BENCHMARKS.md, "The edge term"): demo AUSE-MAE
    0.143 -> 0.131, NLL -3.11 -> -3.24, calibration error 0.099 -> 0.083; fern 0.201 -> 0.190, -2.25 -> -2.29,
    0.055 -> 0.048; at the cost of a little of the unseen-surface ROC AUC (half the ring trained, see there).
    False: the per-Gaussian noise alone, as before 2026-11-26."""
    finer_detail: bool = True
    """Where a view resolves the surface finer than any training photo that sees it did (nearer, or zoomed in, by a
    factor r > 1 of the pixel footprints), add ``(r^2 - 1) (delta^2 + 1/12) |grad I(p)|^2`` to the RGB variance: the
    edge term's misplacement delta is in the photos' pixels (r delta in this view's), and an edge the photos
    recorded across one pixel may be a sharp step where the model renders a ramp (``uncertainty.consistency``,
    "Detail finer than any photo recorded"). Nothing is fitted. Measured on views moved to half their distance
    (BENCHMARKS.md, "Detail finer than any photo recorded"): 5 sparse views NLL -1.75 -> -2.11, AUSE-MAE 0.115 ->
    0.111; the dense demo NLL -3.07 -> -3.17, AUSE-MAE 0.120 -> 0.114; views at the capture's distance unchanged.
    Needs the view-consistency term (``consistency_views`` > 0), whose renders it uses."""
    residual_leverage: Literal["none", "relative", "full"] = "relative"
    """Carry the pixel noise from the training residuals to the noise itself. A training residual is smaller than
    the noise by what the Gaussian's own parameters absorbed, most where few pixels fit it: its leverage h, its
    parameters over the training pixel channels it is blended into (capped at 0.9;
    ``uncertainty.residual.ResidualField.out_of_sample``). ``full``: each Gaussian's noise divided by (1 - h).
    ``relative`` (default): by (1 - h) / (1 - h_m) where that is above 1, h_m the median Gaussian's leverage: only
    the Gaussians observed by fewer pixels than the typical one get more noise, e.g. the initial points of a
    surface few training views saw. ``none``: the residuals as they are (the default before 2026-11-27; ``true`` /
    ``false`` read as ``full`` / ``none``). Measured (BENCHMARKS.md, "The leverage relative to the typical
    Gaussian"): trained on half the ring, unseen-surface RGB AUC 0.944 -> 0.956 and NLL 0.22 -> -0.20 with
    ``relative``; fern's calibration error 0.047 -> 0.049 (``full``: 0.061); sparse views unchanged (``full``: NLL
    and calibration worse)."""

    @field_validator("residual_leverage", mode="before")
    @classmethod
    def _leverage_from_bool(cls, v):
        # configs and evaluations written before 2026-11-27 hold a bool
        if isinstance(v, bool):
            return "full" if v else "none"
        if isinstance(v, str) and v.strip().lower() in ("true", "false"):
            return "full" if v.strip().lower() == "true" else "none"
        return v


# ------------------------------------------------------------------------------------------------ prune
class PruneConfig(_Base):
    """Uncertainty-based pruning (``uncertsplat prune``)."""

    keep_ratio: float | None = Field(None, gt=0.0, le=1.0)
    threshold: float | None = None
    auto: bool = False
    score: str = "auto"
    """Per-Gaussian score name, or auto: ``free-space`` (``uncertainty.scores.DEFAULT_SCORE``), and with ``auto`` or
    ``keep_ratio`` on held-out views (not with ``sweep``) ``gate`` too, whichever prunes better there
    (``uncertainty.scores.AUTO_ALTERNATIVES``)."""
    tolerance_db: float = Field(0.1, ge=0.0)
    sweep: bool = False
    sweep_ratios: list[float] = [1.0, 0.95, 0.9, 0.8, 0.7, 0.6, 0.5]
    dry_run: bool = False
    seed: int = Field(0, ge=0, le=EVAL_SEED_MAX)
    num_samples: int = Field(10, ge=1, le=10_000)
    score_views: int = Field(8, ge=1)
    """Predictive score: at most this many training views (evenly spaced) are rendered."""
    score_samples: int = Field(4, ge=2)
    """Predictive score: posterior samples per view."""
    free_space_views: int = Field(64, ge=1)
    """Free-space score: at most this many training views (evenly spaced) are rendered for the model's depth."""
    free_space_margin: float = Field(1.0, ge=0.0)
    """Free-space score: how many of its own sizes (largest axis) a Gaussian must lie in front of the model's
    surface, in every training view containing it, to count as a floater."""
    render_views: int = Field(3, ge=0)
    """Before/after PNG renders of this many held-out views."""

    @model_validator(mode="after")
    def _one_mode(self):
        modes = [self.keep_ratio is not None, self.threshold is not None, self.auto]
        if sum(modes) > 1:
            raise ValueError("give only one of --keep-ratio, --threshold and --auto (keep_ratio, threshold and auto "
                             "in a config file)")
        if any(not (0.0 < r <= 1.0) for r in self.sweep_ratios):
            raise ValueError("sweep_ratios must be in (0, 1]")
        return self


# ----------------------------------------------------------------------------------------------- report
class ReportConfig(_Base):
    """HTML report (``uncertsplat report``)."""

    title: str = "uncertsplat report"
    max_views: int = Field(6, ge=1)
    """Per-view figures for at most this many test views."""


class SelectConfig(_Base):
    """Choosing the next photos by the model's uncertainty (``uncertsplat select-views``)."""

    candidates: str = "unused"
    """unused (the scene's images not trained on or held out), around[:N] (viewpoints near the training cameras)
    or a file of poses 'NAME QW QX QY QZ TX TY TZ' (``uncertsplat.select.candidates``)."""
    num_views: int = Field(1, ge=1)
    """How many views to choose (greedy for fisher and coverage; the top ones for variance and random)."""
    score: Literal["variance", "unseen", "fisher", "coverage", "random"] = "fisher"
    """How candidates are ranked (``uncertsplat.select.scores``). fisher, the default, with ``gaps`` = 0.5, is the
    policy that did best in the active-learning loop (BENCHMARKS.md, "Choosing the next view", "The Fisher inside the
    gaps": synthetic ring 21.16 dB against 20.70 for coverage and 20.87 for random choice; fern 27.64 against 27.49
    and 26.80; three seeds each; variance trailed random on both scenes)."""
    num_samples: int = Field(4, ge=2, le=256)
    """variance: posterior samples (K) per candidate."""
    max_side: int = Field(96, ge=16, le=4096)
    """variance and fisher: long side in pixels of the candidate (and training-view) renders."""
    probes: int = Field(1, ge=1, le=64)
    """fisher: Rademacher probes per view."""
    information: Literal["trace", "log-det", "predictive"] = "trace"
    """fisher: how a candidate's information is counted: trace (FisherRF's sum of F_cand / precision), log-det (the
    expected information gain of the diagonal posterior, sum of log(1 + F_cand / precision) / 2, which saturates per
    parameter) or predictive (the variance the candidate takes off the renders of the training views and all the
    candidates, sum of G F_cand / (precision (precision + F_cand)) with G their Fisher)."""
    gaps: float = Field(0.5, ge=0.0, le=1.0)
    """fisher: only the candidates whose distance to the nearest camera used (trained on or chosen) is at least
    this fraction of the largest such distance compete (``select.scores.gap_eligible``); the others get no score.
    0: every candidate (FisherRF's choice, which picked views next to ones just added), 1: coverage's farthest
    ones. 0.5, the one value tried, is the default since 2026-11-27."""
    around_radius: float = Field(1.0, gt=0.0, le=1000.0)
    """around: largest move of a candidate from its training camera, in median camera spacings (at most 1000: far
    beyond, the candidates' poses were not finite numbers)."""
    plausible_only: bool = True
    """Planned poses (a file's, ``around``) compete only where a camera can stand: a candidate whose centre lies
    behind the surface every training photo that looked toward it rendered (inside an object, behind a wall:
    ``ViewConsistency.seen_behind``), or farther from every training camera than ``FAR_CAPTURES`` x the capture's size
    (the larger of its cameras' spread and the median depth the photos see), gets no score and is ranked last, with a
    note. A helper's plan file had a pose 28 units into the fern and one 200 scene radii away ranked first by every
    score. false: every candidate competes. The scene's unused photos are not tested (a camera stood at each)."""
    seed: int = Field(0, ge=0, le=EVAL_SEED_MAX)


class ViewConfig(_Base):
    """The browser viewer (``uncertsplat view``); nothing here changes a result, only how it is shown."""

    host: str = "127.0.0.1"
    """Address to listen on: 127.0.0.1 (this machine only; use SSH port forwarding from elsewhere) or 0.0.0.0
    (every network interface: anyone who can reach the port sees the model)."""
    port: int = Field(8080, ge=0, le=65535)
    """Port to listen on; 0 picks a free one."""
    max_side: int = Field(800, ge=64, le=4096)
    """Long side in pixels of a frame when the camera stands still (at most the browser's canvas)."""
    still_samples: int = Field(16, ge=2, le=1024)
    """Posterior samples (K) of a still std frame, added ``moving_samples`` at a time."""
    moving_samples: int = Field(4, ge=1, le=64)
    """Posterior samples of a std frame while the camera moves."""
    moving_fps: float = Field(8.0, gt=0, le=120)
    """Target frame rate while moving: the preview's resolution is chosen from the measured cost per pixel."""
    jpeg_quality: int = Field(90, ge=10, le=100)
    """JPEG quality of the frames sent to the browser."""
    thumbnails: bool = True
    """Show each camera's photo on its frustum (read in the background after start)."""
    seed: int = 0
    """Seed of the std modes' posterior samples (the same camera gives the same frame)."""


# --------------------------------------------------------------------------------------------- pipeline
class PipelineStage(_Base):
    """One stage of a pipeline file: its kind and its config (as in the stage's own schema)."""

    stage: Literal["synth", "reconstruct", "train", "evaluate", "prune", "report"]
    name: str | None = None
    """Folder name under the pipeline output (default: the stage kind): letters, digits, '_' and '-' (a name is a
    folder inside OUT and the first part of ``--set NAME.key=value``)."""
    input: str | None = None
    """Name of the stage whose output this stage reads, or a path (default: the previous stage)."""
    preset: str | None = None
    """For train: a preset from TRAIN_PRESETS, applied under the config given here."""
    config: dict[str, Any] = {}

    @field_validator("name")
    @classmethod
    def _plain_name(cls, name: str | None) -> str | None:
        # "../x" or "/x" wrote outside OUT and moved a folder of the user's; "a.b" could not be addressed by --set;
        # a top-level key's name would be read as that key by --set
        if name is not None and (not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_-]*", name)
                                 or name in PipelineConfig.model_fields):
            raise ValueError(f"{name!r} is not a stage name: use letters, digits, '_' and '-' (it names a folder inside "
                             "the output and the first part of --set NAME.key=value), not a path and not one of "
                             f"{', '.join(PipelineConfig.model_fields)}")
        return name


class PipelineConfig(_Base):
    """A chain of stages (``uncertsplat run PIPELINE.toml -o OUT``)."""

    name: str = "pipeline"
    photos: Path | None = None
    """Input photo folder for pipelines that start with reconstruct."""
    device: Literal["auto", "cpu", "cuda"] = "auto"
    stages: list[PipelineStage] = Field(min_length=1)

    @field_validator("photos", mode="after")
    @classmethod
    def _photos_home(cls, v: Path | None) -> Path | None:
        return _home(v)


# ----------------------------------------------------------------------------------------------- helpers
def _home(path: Path | None) -> Path | None:
    """``path`` with a leading ``~`` taken as the home folder, as a shell would (a TOML file's or ``--set``'s path is
    not seen by one: ``~/photos`` was looked for in a folder named ``~``)."""
    return path.expanduser() if path is not None and str(path).startswith("~") else path


STAGE_CONFIGS: dict[str, type[_Base]] = {
    "synth": SynthConfig,
    "reconstruct": ReconstructConfig,
    "train": TrainConfig,
    "evaluate": EvalConfig,
    "prune": PruneConfig,
    "report": ReportConfig,
}


def config_owner(data: dict, other_than: type[_Base] | None = None) -> str | None:
    """The command (a ``STAGE_CONFIGS`` name) whose configuration has every key of ``data``, the first such but
    ``other_than``'s; None for none: what a --config file of another command (or a TOML given to ``run``) is."""
    return next((name for name, model in STAGE_CONFIGS.items()
                 if model is not other_than and all(k in model.model_fields for k in data)), None)


def deep_update(base: dict, update: dict) -> dict:
    """Recursively merge ``update`` into a copy of ``base``."""
    out = dict(base)
    for key, value in update.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = deep_update(out[key], value)
        else:
            out[key] = value
    return out


def _parse_value(raw: str) -> Any:
    """A ``--set`` value: TOML, else JSON, else a list of bare words (``[a.png, b.png]``, what a shell leaves of
    ``["a.png","b.png"]`` typed without quotes around it), else the bare string."""
    try:
        return tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        pass
    try:
        return json.loads(raw)
    except json.JSONDecodeError:
        pass
    text = raw.strip()
    if text.startswith("[") and text.endswith("]"):
        items = [item.strip().strip("'\"") for item in text[1:-1].split(",")]
        return [_parse_value(item) if item[:1].isdigit() or item in ("true", "false") else item
                for item in items if item]
    return raw


def parse_override(text: str) -> dict:
    """Turn ``a.b.c=value`` into ``{"a": {"b": {"c": value}}}``; value parsed as TOML/JSON when possible."""
    if "=" not in text:
        raise UserError(f"override '{text}' is not of the form key=value", hint="Example: --set iterations=500")
    key, raw = text.split("=", 1)
    key = key.strip()
    if not key:
        raise UserError(f"override '{text}' has an empty key")
    value = _parse_value(raw)
    out: dict = {}
    node = out
    parts = key.split(".")
    for p in parts[:-1]:
        node = node.setdefault(p, {})
    node[parts[-1]] = value
    return out


def _valid_keys(model: type[BaseModel] | None, loc: tuple) -> list[str]:
    """The field names of the (nested) model at ``loc``'s parent, [] when it cannot be followed."""
    for part in loc[:-1]:
        field = model.model_fields.get(str(part)) if model is not None else None
        inner = getattr(field, "annotation", None) if field is not None else None
        model = inner if isinstance(inner, type) and issubclass(inner, BaseModel) else None
    return list(model.model_fields) if model is not None else []


def _other_stage(model: type[BaseModel] | None, loc: tuple) -> str | None:
    """The command whose configuration has ``loc`` (a key unknown to ``model``), e.g. "train" for
    ``ssim_cache_mb`` given to ``evaluate``: the same ``--set`` keys read differently per command. None when no
    other stage's model has it (or it is nested)."""
    stages = {"synth": SynthConfig, "reconstruct": ReconstructConfig, "train": TrainConfig, "evaluate": EvalConfig,
              "prune": PruneConfig, "select-views": SelectConfig, "view": ViewConfig}
    if len(loc) != 1:
        return None
    return next((name for name, other in stages.items() if other is not model and str(loc[0]) in other.model_fields),
                None)


# ------------------------------------------------------------------------------------ where a key is written
def _toml_key(text: str) -> tuple[list[str], str] | None:
    """The dotted key at the start of ``text`` (bare or quoted parts) and what follows it; None when ``text`` does
    not start with a key."""
    parts: list[str] = []
    i = 0
    while True:
        while i < len(text) and text[i] in " \t":
            i += 1
        if i < len(text) and text[i] in "\"'":
            quote, end = text[i], i + 1
            while end < len(text) and text[end] != quote:
                end += 2 if quote == '"' and text[end] == "\\" else 1  # a basic string's escapes
            if end >= len(text):
                return None
            part = text[i + 1:end]
            if quote == '"' and "\\" in part:
                try:
                    part = json.loads(f'"{part}"')  # TOML's basic-string escapes are JSON's (and \UXXXXXXXX)
                except json.JSONDecodeError:
                    pass
            parts.append(part)
            i = end + 1
        else:
            m = re.match(r"[A-Za-z0-9_-]+", text[i:])
            if m is None:
                return None
            parts.append(m.group())
            i += m.end()
        while i < len(text) and text[i] in " \t":
            i += 1
        if i < len(text) and text[i] == ".":
            i += 1
            continue
        return parts, text[i:]


def _toml_depth(text: str, depth: int, string: str | None) -> tuple[int, str | None]:
    """``depth`` (open brackets and braces) and ``string`` (the delimiter of an open multi-line string) after
    reading ``text``, one line of a value; comments and the contents of strings are skipped."""
    i = 0
    while i < len(text):
        if string is not None:
            end = text.find(string, i)
            if end < 0:
                return depth, string
            i = end + len(string)
            for _ in range(2):  # up to two quotes more belong to the string ('a = """x""""' ends in x")
                if i < len(text) and text[i] == string[0]:
                    i += 1
            string = None
            continue
        c = text[i]
        if c == "#":
            break
        if text.startswith(('"""', "'''"), i):
            string, i = text[i:i + 3], i + 3
        elif c in "\"'":
            end = i + 1
            while end < len(text) and text[end] != c:
                end += 2 if c == '"' and text[end] == "\\" else 1
            i = end + 1
        else:
            depth += (c in "[{") - (c in "]}")
            i += 1
    return depth, string


def toml_key_lines(text: str) -> dict[str, int]:
    """The line (from 1) on which each key of a TOML document is written, by its dotted path; an entry of an array
    of tables by its index (``stages.4.stage``). A key inside an inline table or a multi-line array is not listed:
    it sits on its parent's line (``KeyLines.line`` looks the parent up). Lines it cannot read are skipped: this
    only serves error messages, the file's values come from ``tomllib``."""
    out: dict[str, int] = {}
    table: list[str] = []
    arrays: dict[tuple[str, ...], int] = {}  # each array of tables' last index

    def indexed(path: list[str]) -> list[str]:  # a path through arrays of tables goes through their last entry
        full: list[str] = []
        for part in path:
            full.append(part)
            if tuple(full) in arrays:
                full.append(str(arrays[tuple(full)]))
        return full

    depth, string = 0, None
    for number, line in enumerate(text.splitlines(), start=1):
        if depth or string is not None:  # inside a multi-line value
            depth, string = _toml_depth(line, depth, string)
            continue
        stripped = line.strip()
        header = re.match(r"(\[\[?)(.*?)(\]\]?)\s*(#.*)?$", stripped) if stripped.startswith("[") else None
        if header is not None:
            key = _toml_key(header.group(2))
            if key is None or key[1].strip():
                continue
            if header.group(1) == "[[":
                path = tuple(indexed(key[0][:-1]) + [key[0][-1]])
                arrays[path] = arrays.get(path, -1) + 1
                out.setdefault(".".join(path), number)
                table = list(path) + [str(arrays[path])]
            else:
                table = indexed(key[0])
            out.setdefault(".".join(table), number)
            continue
        key = _toml_key(stripped) if stripped and not stripped.startswith("#") else None
        if key is None or not key[1].startswith("="):
            continue
        out[".".join(table + key[0])] = number
        depth, string = _toml_depth(key[1][1:], 0, None)
    return out


class KeyLines:
    """Where the keys of one validated table are written in a TOML file, for an error that gives the line.

    Args:
        path: the TOML file (read when an error asks for a line, not before).
        prefix: where the table sits in the file (``stages.2.config``); "" for the whole file.
        replaced: dotted keys (from the file's top) whose values came from elsewhere (``--set``, an option): an
            error about one of them, or about a key below one, gets no line of the file.
    """

    def __init__(self, path: str | Path, prefix: str = "", replaced: set[str] | None = None):
        self.path, self.prefix, self.replaced = Path(path), prefix, set(replaced or ())
        self._lines: dict[str, int] | None = None

    def line(self, key: str) -> int | None:
        """The line of ``key`` (a dotted path below ``prefix``), or of the nearest table or key above it that the
        file writes; None when the value came from elsewhere or the file cannot be read again."""
        full = (self.prefix.split(".") if self.prefix else []) + key.split(".")
        if any(".".join(full[:n]) in self.replaced for n in range(1, len(full) + 1)):
            return None
        if self._lines is None:
            try:
                self._lines = toml_key_lines(self.path.read_text(encoding="utf-8"))
            except (OSError, UnicodeDecodeError):
                self._lines = {}
        for n in range(len(full), 0, -1):
            if ".".join(full[:n]) in self._lines:
                return self._lines[".".join(full[:n])]
        return None


def dotted_keys(data: dict, prefix: str = "") -> set[str]:
    """The dotted path of every value in a nested dict (``{"a": {"b": 1}}`` -> ``{"a.b"}``)."""
    out: set[str] = set()
    for key, value in data.items():
        path = f"{prefix}.{key}" if prefix else str(key)
        out |= dotted_keys(value, path) if isinstance(value, dict) and value else {path}
    return out


def format_validation_error(err: ValidationError, source: str, model: type[BaseModel] | None = None,
                            key_prefix: str = "", names: dict[str, str] | None = None,
                            where: KeyLines | None = None) -> str:
    """One readable paragraph from a pydantic ValidationError; an unknown key gets the closest valid ones.
    ``key_prefix``: where the validated table sits in the file (e.g. "train" for a sweep spec's ``train`` keys).
    ``names``: what to call a key instead (e.g. the command-line option that gave its value). ``where``: the file's
    lines, so that each key the file wrote is named with its line."""
    import difflib
    import re

    lines: list[str] = []
    listed: set[tuple] = set()  # the parents whose valid keys a line has listed already
    for e in err.errors():
        # a union's members appear in the path as tags (literal['fit','gaussian'], constrained-float): left out, so
        # that the alternatives for one key read as one key's
        path = [p for p in e["loc"] if not (isinstance(p, str) and re.search(r"[\[\]'\-]", p))]
        loc = ".".join(str(p) for p in (key_prefix.split(".") if key_prefix else []) + path) or "(root)"
        number = where.line(loc) if where is not None and path and loc not in (names or {}) else None
        loc = (names or {}).get(loc, loc)
        label = f"{loc} (line {number})" if number is not None else loc
        msg = e["msg"].removeprefix("Value error, ")  # our validators' messages are sentences of their own
        msg = re.sub(r" or instance of \w+", "", msg)  # "a valid dictionary or instance of SweepScene"
        if e["type"] == "string_type" and not isinstance(e.get("input"), (dict, type(None))):
            # `--set title=2024` (or a date, true, [draft]) is read as that value's type: text is quoted
            msg += (f" (found {e.get('input')!r}: a text that reads as a number, date, true/false or list is given "
                    f"in quotes: --set '{e['loc'][-1]}=\"{e.get('input')}\"', or {e['loc'][-1]} = \"{e.get('input')}\" "
                    "in a file)")
        if e["type"] == "less_than_equal" and path and path[-1] in ("iterations", "growth_refit_steps"):
            # (the bound alone read as arbitrary: what it allows)
            msg += f" ({MAX_ITERATIONS:,} steps are already days of training; 3DGS trains 30,000)"
        if e["type"] == "extra_forbidden":
            valid = _valid_keys(model, tuple(e["loc"]))
            close = difflib.get_close_matches(str(e["loc"][-1]), valid, n=3, cutoff=0.6)
            prefix = ".".join(str(p) for p in (key_prefix.split(".") if key_prefix else []) + list(e["loc"][:-1]))
            named = [f"{prefix}.{k}" if prefix else k for k in close]
            # a key that another command has exactly is most likely meant for it (keep_ratio given to train read as
            # a misspelt iterations); a close key of this command's is named after it
            stage = _other_stage(model, tuple(e["loc"])) if not key_prefix else None
            if stage is not None:
                msg = (f"not a setting of this command: `{e['loc'][-1]}` is one of `uncertsplat {stage}`'s "
                       f"(uncertsplat {stage} ... --set {e['loc'][-1]}=...)"
                       + (f"; or did you mean {' or '.join(named)}?" if named else ""))
            else:
                msg = "unknown key" + (f" (did you mean {' or '.join(named)}?)" if named else " (check the spelling)")
            parent = tuple(e["loc"][:-1])
            if valid and not named and parent not in listed:
                msg += f"; valid keys here: {', '.join(valid)}"
                listed.add(parent)
        same = next((i for i, line in enumerate(lines) if line.startswith(f"{label}: ")), None)
        if same is not None:  # another alternative of a union: one line for the key
            lines[same] += f", or {msg[0].lower()}{msg[1:]}"
        elif loc == "(root)":  # a rule over several keys (a model validator): its message names them
            lines.append(msg)
        else:
            lines.append(f"{label}: {msg}")
    return f"invalid configuration in {source}: " + "; ".join(lines)


def build_config(model: type[_Base], data: dict, source: str = "config", key_prefix: str = "",
                 names: dict[str, str] | None = None, where: KeyLines | None = None):
    """Validate ``data`` against ``model``; errors become a ``UserError`` naming each bad key (after
    ``key_prefix``, where ``data`` sits in ``source``; ``names``, ``where``: see ``format_validation_error``)."""
    try:
        return model.model_validate(data)
    except ValidationError as err:
        raise UserError(format_validation_error(err, source, model, key_prefix, names, where)) from None


STAGE_PATH_KEYS = ("depth_gt", "candidates", "masks", "init_ply", "init_ply_transform")
"""The stage configs' path settings (``EvalConfig.depth_gt``, ``SelectConfig.candidates`` when it names a file,
``ReconstructConfig.masks``, ``TrainConfig.init_ply`` and ``init_ply_transform``): a relative one is read from the folder of the file that wrote it (a --config file's; a
pipeline file's where the current folder has no such path)."""

SHIPPED = Path(__file__).resolve().parent / "pipelines"
"""The pipelines and sweep specs installed with the package (the repository's ``pipelines/`` links here)."""


_KIND_COMMAND = {"pipeline": "run", "sweep": "sweep"}
_KIND_WORDS = {"pipeline": "a pipeline", "sweep": "a sweep spec"}
_KIND_PLURAL = {"pipeline": "pipelines", "sweep": "sweep specs", None: "pipelines and sweep specs"}


def method_label(cfg: TrainConfig) -> str:
    """A short name for a resolved TrainConfig (``vi-single``, ``ensemble-10``, ``ensemble-2-variational``, ``paper``,
    ...): what the sweep and the report call a run's method."""
    if cfg.method == "ensemble":
        return f"ensemble-{cfg.ensemble_size}" + ("-variational" if cfg.ensemble_members == "variational" else "")
    if cfg.method in ("fisher", "deterministic"):
        return cfg.method
    if cfg.variational.num_entries == 1 and cfg.posterior == "sgd":  # the informed posterior stores one anyway
        return "vi-single" if cfg.variant == "ours" else "vi-single-paper"
    return "variational" if cfg.variant == "ours" else "paper"


def shipped_file(path: str | Path, kind: str | None = None,
                 describe: Callable[[dict], str | None] | None = None) -> Path:
    """``path``, or the installed pipeline / sweep spec it names when there is no such file: a bare name
    (``photos``, ``photos.toml``) or the repository's path (``pipelines/photos.toml``, what the README types) run
    from outside the repository, e.g. after ``pip install``. ``kind`` (``"pipeline"`` for ``run``, ``"sweep"`` for
    ``sweep``): a file of the other kind is refused with the command that runs it (a sweep spec given to ``run``
    failed on every key), and a name not found is offered those of this kind only. ``describe``: what a file of
    neither kind is, from its keys (``schemas.identify.what_file_is``, a layer above this module), for the refusal.

    Raises:
        UserError: no such file and no installed one of that name (the installed names listed), or a file of the
            other kind.
    """
    path = Path(path)
    found = None
    if path.is_file():  # (a folder of that name, e.g. the photos of `run photos`, is not the pipeline)
        found = path
    elif path.parent in (Path("."), Path("pipelines")):
        for name in (path.name, f"{path.name}.toml"):
            if (SHIPPED / name).is_file():
                found = SHIPPED / name
                break
    if found is None:
        names = shipped_names(kind)
        close = difflib.get_close_matches(path.stem, names, n=1)
        example = ("uncertsplat sweep tradeoff -o OUT" if kind == "sweep" else
                   "uncertsplat run photos -o OUT --set photos=PHOTOS")
        what = _KIND_PLURAL[kind]
        raise UserError("file not found" + (f" (did you mean {close[0]}?)" if close else ""), path=path,
                        hint=f"The {what} installed with uncertsplat run by name: {', '.join(names)} (e.g. {example}).")
    actual = _toml_kind(found)
    if kind is not None and actual is None:
        _refuse_not_toml(found, kind, describe)
    if kind is not None and actual is not None and actual != kind:
        shown = found.stem if found.parent == SHIPPED else str(found)
        raise UserError(f"this is {_KIND_WORDS[actual]}, not {_KIND_WORDS[kind]}", path=found,
                        hint=f"Run it with `uncertsplat {_KIND_COMMAND[actual]} {shown} -o OUT`.")
    return found


def _refuse_not_toml(path: Path, kind: str, describe: Callable[[dict], str | None] | None) -> None:
    """A file ``run`` or ``sweep`` cannot read as TOML (a run's config.json, a stage's manifest.json), or one command's
    TOML configuration: what it is and what the command takes, in one sentence (the TOML parser's "Invalid statement
    (at line 1, column 1)" said neither; a configuration had a clause per key)."""
    what: str | None = None
    err: Exception | None = None
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
        what = describe(data) if describe is not None and len(data) >= 2 else None
        if what is None or not what.endswith("configuration"):
            return  # TOML of neither kind: the command's reader names the key
    except (OSError, UnicodeDecodeError):
        pass  # (not text: a PLY, an image)
    except tomllib.TOMLDecodeError as toml_err:
        err = toml_err
        try:
            what = describe(json.loads(path.read_text(encoding="utf-8"))) if describe is not None else None
        except (OSError, ValueError, UnicodeDecodeError):
            what = None
    expected = ("a pipeline (a TOML file that lists [[stages]])" if kind == "pipeline"
                else "a sweep spec (a TOML file of the points to train and evaluate)")
    example = ("uncertsplat run photos -o OUT --set photos=PHOTOS" if kind == "pipeline"
               else "uncertsplat sweep tradeoff -o OUT")
    names = ", ".join(shipped_names(kind))
    raise UserError((f"this is {what}, not {expected}" if what else
                     f"not {expected}" + (f": not a valid TOML file ({err})" if err else "")), path=path,
                    hint=(f"Give it to that command's --config; `uncertsplat {_KIND_COMMAND[kind]}` takes "
                          if what and what.endswith("configuration") else "Give ")
                    + f"{_KIND_WORDS[kind]} file, or the name of one installed with uncertsplat: {names} "
                      f"(e.g. {example}).")


SWEEP_KEYS = frozenset({"axes", "default", "design", "pareto_x", "pareto_y", "seeds", "scenes", "synth",
                         "train_preset"})
"""Keys only a sweep spec has (``sweep.spec.SweepSpec``); a pipeline has ``stages``."""


def _toml_kind(path: Path) -> str | None:
    """"pipeline" (a TOML with ``stages``), "sweep" (one with a sweep spec's keys) or None: not TOML, or neither
    (a mistyped file: the command's own reader names the key)."""
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, tomllib.TOMLDecodeError, UnicodeDecodeError):
        return None
    if "stages" in data:
        return "pipeline"
    return "sweep" if SWEEP_KEYS & set(data) else None


def shipped_names(kind: str | None = None) -> list[str]:
    """The installed pipelines' and sweep specs' names (``shipped_file``); ``kind``: those of one kind only."""
    return sorted(p.stem for p in SHIPPED.glob("*.toml") if kind is None or _toml_kind(p) == kind)


def load_toml(path: str | Path) -> dict:
    """Read a TOML file with errors that name the file."""
    path = Path(path)
    if path.is_dir():
        raise UserError("this is a folder, not a config file", path=path, hint="Give the path of a .toml file.")
    if not path.is_file():
        raise UserError("config file not found", path=path,
                        hint=f"Check the path (a relative one is read from {Path.cwd()}).")
    try:
        return tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as err:
        raise UserError(f"not a valid TOML file ({err})", path=path) from None


def train_config_from(preset: str | None, data: dict | None = None, overrides: list[str] | None = None,
                      source: str | None = None, where: KeyLines | None = None) -> TrainConfig:
    """Resolve a TrainConfig: preset, then ``data`` (e.g. from TOML), then ``key=value`` overrides. ``source``:
    what an error names (default "train config"), e.g. the TOML file ``data`` came from; ``where``: its lines."""
    merged: dict = {}
    if preset is not None:
        if preset not in TRAIN_PRESETS:
            raise UserError(f"unknown preset '{preset}'", hint=f"Choose one of: {', '.join(TRAIN_PRESETS)}.")
        merged = deep_update(merged, TRAIN_PRESETS[preset])
    if data:
        merged = deep_update(merged, data)
    given = set(data or {})
    for o in overrides or []:
        parsed = parse_override(o)
        given |= set(parsed)
        merged = deep_update(merged, parsed)
    if merged.get("init_ply") is not None and "iterations" not in given:
        # a model trained elsewhere is given its posterior without training (what --from-ply sets): the steps of a
        # preset or the default (7000) were refused, in a config file, a pipeline stage or --set init_ply=...
        merged["iterations"] = 0
    label = source or "train config"
    return build_config(TrainConfig, merged, source=f"{label} (preset {preset})" if preset else label, where=where)

