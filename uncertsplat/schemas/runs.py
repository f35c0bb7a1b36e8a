"""Schemas of a run's bookkeeping files: ``train_summary.json``, a stage's ``manifest.json``, sweep records."""

from __future__ import annotations

import hashlib
import json
from typing import Any, Literal

from pydantic import Field, field_validator, model_validator

from uncertsplat.schemas.base import SchemaFile, Strict, finite_or_none


# ------------------------------------------------------------------------------------ train_summary.json
class Quantiles(Strict):
    """10th, 50th and 90th percentile of a per-carrier quantity."""

    q10: float
    q50: float
    q90: float


class PosteriorSummary(Strict):
    """How far the learned posteriors moved from the prior (``variational.posterior_summary``)."""

    carriers: int
    moved_kl_nats: float
    """A carrier "moved" when its KL from the prior exceeds this many nats."""
    gate_off_prior: float
    position_prior: Literal["config", "per_carrier"] = "config"
    """What the position KL and spread ratio are measured against: the config's single std, or the informed
    posterior's per-carrier prior (its own size, capped by its depth); "config" in summaries written before."""
    moved_fraction: float | None
    kl_nats: Quantiles | None
    position_spread_ratio: Quantiles | None
    scale_width_ratio: Quantiles | None
    gate_off: Quantiles | None


class PosteriorUpdate(Strict):
    """One informed-posterior update (``Trainer.update_posterior``)."""

    step: int
    views: int
    """Training views the update used."""
    probes: int | None = None
    """Rademacher probes per view (``variational.probes`` at the last step, ``refresh_probes`` before); None in
    summaries from before it was recorded."""
    noise_std: float
    """Observation noise of the Gaussian pixel likelihood: the RMS training residual."""
    carriers: int
    data_dominated: float | None
    """Carriers whose position variance is below half the prior's: the data, not the prior, set them."""
    gate_off_median: float | None
    """Median probability that a sample switches a carrier off (the prior's for a Gaussian no view needs)."""
    seconds: float


class StepProfile(Strict):
    """Where the training time went (``TrainConfig.profile``; ``train.profile.PhaseTimer``), this training call."""

    steps: int
    seconds: dict[str, float]
    """Wall seconds per phase: data, sample, render, loss, backward, optimizer, densify, posterior, eval,
    checkpoint."""
    fraction: dict[str, float]
    """Each phase's share of the sum."""


class ShBandCheck(Strict):
    """One SH band's test (``TrainConfig.sh_min_gain_db``; ``strategy.sh_bands``)."""

    degree: int
    """The band tested (1-3)."""
    step: int
    """The step it was tested at, after ``sh_degree_interval`` steps with it."""
    gain_db: float
    """Training-view PSNR with the band minus without it (bands above it off)."""
    kept: bool
    """``gain_db >= min_gain_db``; a dropped band takes the bands above it along."""
    min_gain_db: float
    views: int
    """Training views rendered."""


class GrowthCheck(Strict):
    """One test of whether densification should go on growing the model (``DensifyConfig.growth_min_gain_db``;
    ``strategy.growth``)."""

    step: int
    gaussians: int
    """The model's size at the test."""
    seen: int
    """Gaussians with a footprint in the test's views; the weakest half of them was switched off."""
    cost_db: float
    """Training-view PSNR of the whole model minus that without the weakest half (both trained ``refit_steps``
    more steps first)."""
    min_gain_db: float
    stopped: bool
    """``cost_db < min_gain_db`` here and in the ``growth_patience - 1`` tests before: the model grew no further
    than ``gaussians`` after this step (with ``refit_steps`` > 0 densification filled the room pruning made; without,
    no Gaussians were added)."""
    views: int
    """Training views rendered."""
    refit_steps: int = 0
    """Steps the two copies trained before they were compared (``DensifyConfig.growth_refit_steps``); 0: the half
    was switched off in the model as it was (every test before the re-fit existed)."""
    skip_next: bool = False
    """``cost_db`` was at least ``DensifyConfig.growth_skip_factor`` times ``min_gain_db``: the next test due was not
    run (``strategy.growth.skipped``)."""


class ExposureCheck(Strict):
    """One test of whether the training photos differ in exposure (``TrainConfig.exposure = "auto"``;
    ``strategy.exposure``)."""

    step: int
    views: int
    """Training photos tested."""
    gain_min: float
    gain_max: float
    """The smallest and largest fitted gain of a tested photo relative to the model's render."""
    spread: float
    """``gain_max / gain_min``."""
    threshold: float
    enabled: bool
    """``spread >= threshold``: the photos' exposures were learned from the next step on."""


class MemoryHold(Strict):
    """Densification's growth held below the budget because memory ran short (``Trainer._memory_limit``)."""

    step: int
    """The first densification step memory held."""
    last_step: int
    gaussians: int
    """The model's size at the first step held (growth may go on after it where the room allows)."""
    budget: int
    """The budget in force then (``--add-views`` may raise it later)."""
    room_mb: float
    """MiB training could still take at the first step held, beyond what its steps take again at their peaks."""
    per_gaussian_bytes: float
    """The estimate of what each added Gaussian takes at a step's peak (``strategy.budget.GROWN_GAUSSIAN_FACTOR`` x
    ``gaussians.params.memory_per_new_gaussian``)."""
    held: int
    """How many densification steps memory held."""


class Budget(Strict):
    """The model-size limit densification had (``strategy.budget.GaussianBudget``)."""

    max_gaussians: int
    source: str
    """``config`` (``densify.max_gaussians`` set by the user or a preset) or ``auto`` (from the training pixels)."""
    reason: str
    memory_hold: MemoryHold | None = None
    """Set when memory held growth below ``max_gaussians`` (the model stayed smaller, the run went on)."""


class ImportedAlignment(Strict):
    """The frame found for a model trained elsewhere by placing its Gaussians on the scene's sparse points
    (``TrainConfig.init_ply_frame`` "align", or "auto" when the source frame left them off; ``sfm.align``)."""

    file_from_source: list[list[float]]
    """[4,4] the similarity found, x_file = s R x_source + t."""
    residual: float
    """The nearest 70 % of the sparse points' mean distance to the model's solid Gaussians, over the points' radius,
    in the found frame (0.005-0.009 where a model lies on its points)."""
    source_residual: float
    """The same read in the scene's source frame."""
    points: int
    gaussians: int
    """Sparse points and solid Gaussians (opacity >= 0.5, all when too few) placed."""
    refined_psnr: list[float] | None = None
    """[before, after]: the mean PSNR of the compared training views before and after the frame was fitted to the
    photos (``train.imported.refine_frame``), or None where it was not."""


class ImportedModel(Strict):
    """The 3DGS model trained elsewhere that a run started from (``TrainConfig.init_ply``, ``train.imported``)."""

    path: str
    frame: str
    """``source`` (moved from the scene's source coordinates into the run's frame), ``transform`` (moved back through
    ``transform`` first), ``aligned`` (moved back through the frame ``alignment`` found) or ``run`` (taken as it
    was)."""
    transform: str | None = None
    """The file of ``TrainConfig.init_ply_transform``, or None."""
    gaussians: int
    """Gaussians read (rows with a value that is not finite left out)."""
    sh_degree: int
    in_view_share: float
    """The share of them inside some training view (low: the model and the scene may be in different frames)."""
    notes: list[str] = Field(default_factory=list)
    """What reading changed (rows left out, Mip-Splatting's 3D filter folded in)."""
    alignment: ImportedAlignment | None = None
    """The frame found on the scene's sparse points (``frame`` "aligned"), or None."""


class MemoryPerGaussian(Strict):
    """Bytes per Gaussian by kind (``gaussians.params.memory_per_gaussian``)."""

    params: float
    tables: float
    index: float
    optimizer: float
    total: float
    table_bytes_per_carrier: float


class TrainSummary(SchemaFile):
    """``RUN/train_summary.json``: what ``train`` did (one model), and for an ensemble its members.

    The single-model fields are those of every method that trains one model (variational, vi-single,
    deterministic, fisher); an ensemble run sums its members' training and lists their summaries in
    ``members``, leaving the per-model diagnostics (``posterior``, ``memory``) to them.
    """

    FILE_NAME = "train_summary.json"
    SCHEMA_VERSION = 11
    WRITTEN_BY = "uncertsplat train SCENE -o RUN --resume"  # (a plain re-run refuses the existing run folder)

    schema_version: int = 11
    method: str
    variant: str
    steps: int
    seconds: float
    """Training time; for fisher the training loop plus the Fisher pass, for an ensemble the members' sum."""
    sec_per_step: float
    num_gaussians: int
    num_carriers: int
    peak_memory_mb: float
    device: str
    scene: str
    test_psnr: float | None = None
    """Held-out PSNR of the run's deterministic render (``test_render``); None without held-out views and
    for an ensemble (its mean render is scored by ``evaluate``)."""
    test_ssim: float | None = None
    test_render: str | None = None
    num_test_views: int | None = None
    train_psnr: float | None = None
    """PSNR of the same render on at most 8 evenly spaced training views: how well the model fits its own photos
    (None for an ensemble and runs from before it was recorded)."""
    warnings: list[str] = Field(default_factory=list)
    """What ``train`` warned about (e.g. a model that cannot fit its own photos), and, prefixed "scene: ", what
    loading changed of the photos (``SceneData.notes``: turned, cropped or left out)."""
    # ---- one model
    carrier_fraction: float | None = None
    memory_per_gaussian_bytes: float | None = None
    memory: MemoryPerGaussian | None = None
    extent: float | None = None
    skipped_steps: int | None = None
    sh_degree_active: int | None = None
    sh_bands: list[ShBandCheck] = Field(default_factory=list)
    """The SH bands tested and whether each stayed (empty: none was tested, e.g. ``sh_min_gain_db = 0``, degree 0,
    or runs from before the test)."""
    posterior: PosteriorSummary | None = None
    posterior_updates: list[PosteriorUpdate] = Field(default_factory=list)
    """The informed posterior's updates in the last training call (empty for other posteriors)."""
    kernels: str | None = None
    profile: StepProfile | None = None
    growth: list[GrowthCheck] = Field(default_factory=list)
    """The growth tests and whether densification stopped adding Gaussians (empty: none ran, e.g.
    ``growth_min_gain_db = 0``, a schedule too short for one, or runs from before the test)."""
    budget: Budget | None = None
    """None in runs from before the automatic budget (their limit was ``densify.max_gaussians``, 2,000,000 by
    default)."""
    exposure_checks: list[ExposureCheck] = Field(default_factory=list)
    """The exposure tests (``exposure = "auto"``) and whether they switched on the photos' exposures (empty: none ran,
    e.g. ``exposure`` "off" or "affine", or runs from before the test)."""
    transients: dict[str, float] | None = None
    """{training photo: share of its pixels left out as transient} of the photos in which training found transient
    objects (``TrainConfig.transients``; their masks in ``RUN/transients/``); None with the detection off."""
    imported: ImportedModel | None = None
    """The model trained elsewhere the run started from (``train --from-ply``); None for a run trained here."""
    # ---- fisher
    train_seconds: float | None = None
    fisher_seconds: float | None = None
    fisher_noise_std: float | None = None
    # ---- ensemble
    ensemble_size: int | None = None
    wall_seconds_this_call: float | None = None
    test_psnr_members_mean: float | None = None
    members: list[TrainSummary] = Field(default_factory=list)

    @field_validator("test_psnr", "test_ssim", "train_psnr", "test_psnr_members_mean", mode="before")
    @classmethod
    def _nonfinite_to_none(cls, v):
        return finite_or_none(v)

    @classmethod
    def _upgrade(cls, data: dict, version: int) -> dict | None:
        # version 1 had no informed posterior (no updates); versions 1 and 2 neither the fit on the training views
        # nor the warnings; versions 1-3 no exposure tests; versions 1-4 no posterior.position_prior (measured
        # against the config's std then); versions 1-5 no transients (none were found); versions 1-6 no hold of the
        # budget by memory (none held); versions 1-7 no growth test with a re-fit (each test's refit_steps: 0, its
        # default); versions 1-8 no skipped growth tests (each test's skip_next: False, its default); versions 1-9 no
        # model trained elsewhere (imported: None); versions 1-10 no frame found on the sparse points (imported's
        # alignment: None); in the run and its members
        if version not in (1, 2, 3, 4, 5, 6, 7, 8, 9, 10):
            return None

        def up(d: dict) -> dict:
            d = {"train_psnr": None, "warnings": [], "exposure_checks": [], "imported": None, **d,
                 "schema_version": cls.SCHEMA_VERSION}
            if isinstance(d.get("imported"), dict):
                d["imported"] = {"alignment": None, **d["imported"]}
            if isinstance(d.get("posterior"), dict):
                d["posterior"] = {"position_prior": "config", **d["posterior"]}
            if isinstance(d.get("budget"), dict):
                d["budget"] = {"memory_hold": None, **d["budget"]}
            return {**d, "posterior_updates": []} if version == 1 else d

        return {**up(data), "members": [up(m) for m in data.get("members", [])]}


# ------------------------------------------------------------------------------------------ exposure.json
class RunExposure(SchemaFile):
    """``RUN/exposure.json``: each training photo's learned exposure (``TrainConfig.exposure = "affine"``,
    ``render.exposure``): the gain and offset per colour channel that take the model's colours to what the photo
    shows, centred over the photos (geometric mean gain 1, mean offset 0 per channel). ``evaluate`` brings the
    training photos to the model's exposure with them and adds their spread to a new view's variance."""

    FILE_NAME = "exposure.json"
    SCHEMA_VERSION = 1
    WRITTEN_BY = "uncertsplat train"

    schema_version: int = 1
    images: list[str]
    """The training photos' names, in the order of ``gain`` and ``offset``."""
    gain: list[list[float]]
    """[T][3] per photo and channel (r, g, b)."""
    offset: list[list[float]]
    """[T][3] likewise, in colour units (0-1)."""
    step: int
    """The training step the exposures belong to."""

    @model_validator(mode="after")
    def _aligned(self) -> RunExposure:
        if len(self.gain) != len(self.images) or len(self.offset) != len(self.images):
            raise ValueError(f"{len(self.images)} images but {len(self.gain)} gains and {len(self.offset)} offsets")
        if any(len(row) != 3 for row in (*self.gain, *self.offset)):
            raise ValueError("every gain and offset has 3 channels (r, g, b)")
        if any(not (v > 0.0) for row in self.gain for v in row):
            raise ValueError("every gain must be positive")
        return self

    def describe(self) -> str:
        """One line: the range of the photos' gains and the spread of their offsets."""
        import statistics

        gains = [sum(row) / 3.0 for row in self.gain]
        offsets = [sum(row) / 3.0 for row in self.offset]
        spread = statistics.pstdev(offsets) if len(offsets) > 1 else 0.0
        return (f"exposure of {len(self.images)} training photos: gain {min(gains):.3f}-{max(gains):.3f} "
                f"(mean over channels), offset spread {spread:.4f}")


# ----------------------------------------------------------------------------------------- manifest.json
class Manifest(SchemaFile):
    """``STAGE/manifest.json``: what one pipeline stage ran with and whether it finished."""

    FILE_NAME = "manifest.json"
    SCHEMA_VERSION = 3
    WRITTEN_BY = "uncertsplat run"

    schema_version: int = 3
    stage: str
    name: str
    config_hash: str
    input_hashes: dict[str, str]
    """Input name -> hash: an upstream stage's ``key`` (by its folder name) or a user folder's fingerprint."""
    config: dict[str, Any]
    status: str
    """"running", "done", "failed" or "skipped" (a prune of a run too short for a posterior: ``errors.NoPosterior``;
    written only where the stage left its folder)."""
    started_at: float
    finished_at: float | None = None
    seconds: float | None = None
    error: str | None = None
    versions: dict[str, str] = Field(default_factory=dict)
    outputs: list[str] = Field(default_factory=list)
    """The files the finished stage left in its folder (relative paths; ``stages.manifest.stage_outputs``: not its
    checkpoints or caches): a stage with one of them gone runs again rather than being skipped."""
    output_sizes: dict[str, int] = Field(default_factory=dict)
    """The bytes of each of ``outputs`` that holds data (``stages.manifest.SIZED_OUTPUTS``: models, maps, figures) when
    the stage finished: a stage with one of another size since (a copy cut short, a disk that filled while a file was
    written again in place) runs again rather than being skipped."""

    @classmethod
    def _upgrade(cls, data: dict, version: int) -> dict | None:
        # version 0 (before schema_version existed) had version 1's keys; version 1 recorded no outputs (none are
        # checked), versions 0-2 no sizes (none are compared)
        return data if version in (0, 1, 2) else None

    @property
    def key(self) -> str:
        """Hash of config and inputs: downstream stages use it as their input hash."""
        text = json.dumps({"config": self.config_hash, "inputs": self.input_hashes}, sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:16]


# ------------------------------------------------------------------------------------------- sweep records
class SweepRecord(Strict):
    """One line of ``sweep.jsonl``: a sweep point's training and evaluation (failed points carry ``error``)."""

    schema_version: int = 1
    id: str
    hash: str
    job: str
    method: str
    knobs: dict[str, Any]
    is_default: bool
    status: str
    """"ok" or "failed"."""
    run_dir: str | None = None
    """None only for a point whose worker process died before it could say."""
    device: str | None = None
    threads: int | None = None
    stage: str | None = None
    """The stage that failed (train / evaluate)."""
    error: str | None = None
    traceback: str | None = None
    attempts: int | None = None
    """How many times the point's job ran (1 + retries after a failure or a dead worker); None before retries."""
    executor: str | None = None
    """local or ray (None in records written before the executors)."""
    scene: str | None = None
    """The spec's scene name (None for a single-scene spec)."""
    seed: int | None = None
    """The spec's seed for this point (None: the configs' own seed, no ``seeds`` list)."""

    @property
    def group(self) -> str:
        """The point's id on its scene without the seed: the row of the sweep's table it belongs to."""
        suffix = f"_seed{self.seed}"
        return self.id[: -len(suffix)] if self.seed is not None and self.id.endswith(suffix) else self.id
    train_seconds: float | None = None
    trained_now: bool | None = None
    train_wall_seconds: float | None = None
    num_gaussians: int | None = None
    num_carriers: int | None = None
    memory_per_gaussian_bytes: float | None = None
    train_peak_memory_mb: float | None = None
    # ---- evaluation (means over the views; see EvalReport.ViewMetrics)
    psnr: float | None = None
    psnr_render: float | None = None
    ssim: float | None = None
    ause_mae: float | None = None
    ause_rmse: float | None = None
    nll: float | None = None
    nll_kde: float | None = None
    calibration_error: float | None = None
    nll_calibrated: float | None = None
    calibration_error_calibrated: float | None = None
    spearman: float | None = None
    depth_ause_mae: float | None = None
    depth_ause_rmse: float | None = None
    depth_abs_rel: float | None = None
    ause: float | None = None
    """``ause_mae`` again, the name the Pareto axes use."""
    std_scale: float | None = None
    calibration_seconds: float | None = None
    eval_seconds_per_view: float | None = None
    eval_seconds: float | None = None
    eval_wall_seconds: float | None = None
    num_views: int | None = None
    num_samples: int | None = None
    notes: list[str] = Field(default_factory=list)
    eval_peak_memory_mb: float | None = None
    peak_memory_scope: str | None = None
    peak_memory_mb: float | None = None
    time: float | None = None
    """Training, the predictive's fit and evaluation seconds (the Pareto x axis); a record written before the fit
    was counted (train + eval) is read with it added (``_time_with_the_fit``), so that one table sums alike."""

    @field_validator("*", mode="before")
    @classmethod
    def _nonfinite_to_none(cls, v):
        return finite_or_none(v)

    @model_validator(mode="after")
    def _time_with_the_fit(self):
        parts = (self.train_seconds, self.eval_seconds, self.calibration_seconds)
        if self.time is not None and None not in parts and parts[2] > 0 and \
                abs(self.time - (parts[0] + parts[1])) <= 1e-9 * max(1.0, abs(self.time)):
            self.time = parts[0] + parts[2] + parts[1]  # written before the fit was counted
        return self

    def get(self, key: str, default: Any = None) -> Any:
        """Field by name (``pareto`` reads records and plain dicts alike)."""
        return getattr(self, key, default)


class SweepGroup(Strict):
    """A point on one scene over its seeds: a row of the sweep's table (what the Pareto fronts compare)."""

    id: str
    """The point's id without the seed (``SCENE.POINT`` for named scenes)."""
    scene: str | None = None
    method: str
    knobs: dict[str, Any]
    is_default: bool
    seeds: list[int | None]
    """The seeds whose record is ok (what ``mean`` averages)."""
    num_failed: int = 0
    mean: dict[str, float | None]
    """The mean over ``seeds`` of each metric and cost (None when no seed has it)."""
    spread: dict[str, float | None]
    """The sample standard deviation over ``seeds`` (None with fewer than 2)."""


class SweepSummary(SchemaFile):
    """``OUT/sweep.json`` of ``uncertsplat sweep``: the latest record per point and the Pareto fronts."""

    FILE_NAME = "sweep.json"
    SCHEMA_VERSION = 1
    WRITTEN_BY = "uncertsplat sweep"

    schema_version: int = 1
    name: str
    spec: dict[str, Any]
    num_points: int
    num_failed: int
    default: str | None
    pareto_x: str
    pareto: dict[str, list[str]]
    """"{y}_vs_{x}" (named scenes: "{scene}: {y}_vs_{x}") -> ids of the ``table`` rows on that front."""
    records: list[SweepRecord]
    table: list[SweepGroup] = Field(default_factory=list)
    """One row per point and scene: the mean and spread over its seeds (one seed: its record's values)."""
