"""Schemas of what ``uncertsplat prune`` writes: ``prune.json`` and, with ``--sweep``/``--auto``, ``sweep.json``."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator

from uncertsplat.schemas.base import SchemaFile, Strict, finite_or_none, resolve_from

METRIC_KEYS = ("psnr", "ssim", "ause_mae", "ause_rmse", "nll", "depth_ause_mae")
"""The ``PruneMetrics`` keys that are ``evaluate``'s metrics (the means over the metric views)."""
UNPRUNED_FROM_EVALUATE = "the unpruned model's uncertainty metrics are evaluate's"
"""How prune's note begins that its 'before' row's ``METRIC_KEYS`` are the source run's ``eval/metrics.json`` means
(``report`` checks it against that file as it is when the report is made)."""
PRUNED_FROM_EVALUATE = "the pruned model's uncertainty metrics are evaluate's"
"""How prune's note begins that its 'after' row's ``METRIC_KEYS`` are the pruned run's ``eval/metrics.json`` means."""


class PruneMetrics(Strict):
    """Held-out metrics of one model (the unpruned, the pruned, or the random-removal baseline).

    ``psnr`` .. ``depth_ause_mae`` are the means over the metric views of ``evaluate``'s metrics (K
    posterior samples); None when not available (e.g. no GT depth).
    """

    num_gaussians: int
    num_carriers: int
    psnr: float | None = None
    ssim: float | None = None
    psnr_render: float | None = None
    """Held-out PSNR of the expected render (one deterministic render per view, what ``train`` reports): what
    ``--auto`` and the sweep's tolerance compare (``PruneSweep.metric``). None in files from before it."""
    ause_mae: float | None = None
    ause_rmse: float | None = None
    nll: float | None = None
    depth_ause_mae: float | None = None
    coverage: float
    """Mean accumulated opacity of the expected render over the metric views (1 = every pixel covered)."""
    variational_ply_bytes: int
    point_cloud_ply_bytes: int
    """The sizes of this model's two PLY files as ``train`` writes them (what the model costs on disk, alike for
    before, after and random): the pruned run's own ``point_cloud.ply`` is larger by the ``score_<name>`` columns
    ``prune`` adds to it for inspection, 4 bytes per Gaussian and score."""
    seconds: float
    """Time to measure this model."""

    @field_validator("psnr", "ssim", "psnr_render", "ause_mae", "ause_rmse", "nll", "depth_ause_mae", mode="before")
    @classmethod
    def _nonfinite_to_none(cls, v):
        return finite_or_none(v)


class SweepPoint(Strict):
    """One keep ratio of the sweep: the score's removal and random removal of as many Gaussians."""

    keep_ratio: float
    num_removed: int
    keep_ratio_achieved: float
    """Fraction of all Gaussians kept (only carriers can be removed, so it may stay above ``keep_ratio``)."""
    score: PruneMetrics
    random: PruneMetrics


class ToleranceChoice(Strict):
    """The strongest removal whose held-out PSNR stays within ``tolerance_db`` of the unpruned model's."""

    keep_ratio: float
    num_removed: int
    psnr_loss_db: float
    tolerance_db: float


class PruneSweep(SchemaFile):
    """The keep-ratio sweep (``OUT/sweep.json`` of ``prune --sweep``, and ``sweep`` in ``prune.json``)."""

    FILE_NAME = "sweep.json"
    SCHEMA_VERSION = 2
    WRITTEN_BY = "uncertsplat prune --sweep"

    schema_version: int = 2
    ratios: list[float]
    """Descending; always includes 1.0 (nothing removed)."""
    score: str
    split: str
    unpruned: PruneMetrics
    points: list[SweepPoint]
    tolerance_db: float
    largest_removal_within_tolerance: ToleranceChoice | None = None
    metric: Literal["psnr", "psnr_render"] = "psnr"
    """The PSNR of ``PruneMetrics`` the tolerance is checked on: ``psnr_render`` (the expected render's; sweeps written
    since 2026-11-27) or ``psnr`` (the mean of the K samples; sweeps written before)."""
    uncertainty_measured: bool = True
    """Whether the points carry the uncertainty metrics (``prune --sweep``); ``--auto`` alone measures the points by
    their render only (``psnr_render``, coverage, sizes) and the chosen mask in full."""

    @classmethod
    def _upgrade(cls, data: dict, version: int) -> dict | None:
        # version 1 checked the tolerance on the K samples' mean and measured every point in full; its metrics had
        # no expected-render PSNR (None). Files written between those keys' arrival and the version's bump have them:
        # kept
        if version != 1:
            return None
        return {"metric": "psnr", "uncertainty_measured": True, **data, "schema_version": cls.SCHEMA_VERSION}


class PruneCounts(Strict):
    before: int
    after: int
    removed: int
    carriers_before: int
    carriers_after: int


class PruneMetricSet(Strict):
    """The metrics before pruning, after it, and after removing as many random Gaussians."""

    before: PruneMetrics
    after: PruneMetrics | None = None
    random: PruneMetrics | None = None


class PsnrChange(Strict):
    """Held-out PSNR change in dB (negative = worse) by the score's removal and by random removal."""

    score: float
    random: float


class ScoreStats(Strict):
    """Range of a score over the posterior carriers."""

    min: float
    median: float
    max: float


class Written(Strict):
    model: bool
    """Whether a model was written (False for --dry-run and for a sweep only)."""
    folder: str


class PruneReport(SchemaFile):
    """``OUT/prune.json``: what ``prune`` removed, by which score, and what it cost on held-out views."""

    FILE_NAME = "prune.json"
    SCHEMA_VERSION = 4
    WRITTEN_BY = "uncertsplat prune"

    schema_version: int = 4
    source_run: str
    source_model: str
    source_model_sha256: str
    source_from_run: str | None = None
    """``source_run`` relative to the prune's output folder (None: before version 4, or on another drive), so that a
    project moved or copied elsewhere finds its own source run (``source_folder``)."""
    score: str
    score_requested: str
    mode: str
    """"keep_ratio", "threshold", "auto" or "sweep" (measure the curve only)."""
    threshold: float | None = None
    keep_ratio: float | None = None
    tolerance_db: float
    seed: int
    num_samples: int
    metric_split: str
    metric_views: list[str]
    score_views: list[str]
    score_seconds: float
    dry_run: bool
    device: str
    source_coverage: float | None = Field(None, gt=0.0, le=1.0)
    """The opacity the source model reached on its training views' surfaces (``LoadedRun.coverage``): the pruned
    run's evaluation counts its rays as partly empty below this, not below its own (a model pruned to 0.1 % covers
    0.001 of its training pixels and would call nothing empty). None in files before version 3."""
    notes: list[str] = Field(default_factory=list)
    score_stats: dict[str, ScoreStats]
    metrics: PruneMetricSet
    counts: PruneCounts | None = None
    """None when no mask was chosen (a sweep only)."""
    keep_ratio_achieved: float | None = None
    threshold_effective: float | None = None
    """The smallest score among the removed Gaussians."""
    delta_psnr_db: PsnrChange | None = None
    sweep: PruneSweep | None = None
    undo: str
    written: Written | None = None

    def source_folder(self, run_dir: str | Path) -> Path:
        """The source run of the prune output in ``run_dir``: the folder at ``source_from_run`` from there, else
        ``source_run``, whichever holds the model prune read (``source_model`` with ``source_model_sha256``: a
        project moved or copied elsewhere reads its own source, not another project's run that took the old place);
        when neither does (the source trained on since, or gone), ``source_run`` as recorded."""
        from uncertsplat.provenance import file_sha256

        recorded = Path(self.source_run)
        candidates = [recorded]
        if self.source_from_run is not None:
            here = resolve_from(run_dir, self.source_from_run)
            if here.resolve() != recorded.resolve():
                candidates.insert(0, here)
        for folder in candidates:
            try:
                if file_sha256(folder / self.source_model) == self.source_model_sha256:
                    return folder
            except OSError:
                continue
        return recorded

    @classmethod
    def training_run(cls, run_dir: str | Path) -> Path | None:
        """The training run a prune output descends from, following ``source_run`` through prunes of prunes (a prune
        of a prune named the first prune, which has no checkpoint either); None when ``run_dir`` is no prune output or
        a prune.json on the way cannot be read (or loops)."""
        from uncertsplat.errors import UserError

        here, seen = Path(run_dir), set()
        while (here / cls.FILE_NAME).is_file():
            if here.resolve() in seen:
                return None
            seen.add(here.resolve())
            try:
                here = cls.read(here / cls.FILE_NAME).source_folder(here)
            except UserError:
                return None
        return here if seen else None

    @classmethod
    def _upgrade(cls, data: dict, version: int) -> dict | None:
        # version 0 (no schema_version key) had version 1's layout, its sweep without the version and tolerance;
        # version 1's metrics had no expected-render PSNR (None) and its sweep decided on the samples' mean; version 2
        # had no source_coverage (None: the pruned run's evaluation measures its own, as it did); versions 0-3 no
        # source_from_run (None: source_run alone, as they read it)
        if version in (2, 3):
            return data
        if version not in (0, 1):
            return None
        sweep = data.get("sweep")
        if isinstance(sweep, dict):
            if version == 0:
                sweep = {"schema_version": 1, "tolerance_db": data.get("tolerance_db"), **sweep}
            data["sweep"] = PruneSweep._upgrade(dict(sweep), sweep.get("schema_version", 1))
        return data
