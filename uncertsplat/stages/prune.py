"""Stage ``prune``: remove the most uncertain Gaussians (floaters) into a new run, and measure it.

``uncertsplat prune RUN -o OUT (--keep-ratio R | --threshold T | --auto) [--score NAME] [--dry-run] [--sweep]``

The input run is never modified. The output is built in a temporary sibling folder and renamed into
place at the end, so an interrupted prune leaves no half-written run, and an existing output is refused
(nothing is overwritten). ``OUT`` holds:

- ``config.json``, ``scene.json``: copied from the input run (so ``evaluate``, ``report`` and ``prune``
  accept ``OUT`` as a run); ``variational.ply`` (the pruned model, what ``baselines.load_run`` reads) and
  ``point_cloud.ply`` (viewer PLY; the per-Gaussian scores are extra properties ``score_<name>`` (``-`` as ``_``), and
  ``contribution`` when the predictive score was computed). No checkpoints and no ``stats.jsonl``.
- ``prune_mask.npy``: int64 indices (ascending) of the kept Gaussians in the input run's model. With the
  input run's path and the SHA-256 of its model file (both in ``prune.json``) this makes the pruning
  reversible and reproducible: ``rebuild_from_mask(RUN, OUT/prune_mask.npy)`` rebuilds the pruned model,
  and undoing the prune is using (or re-pruning) ``RUN`` itself, which is unchanged.
- ``scores.npz``: the ``position``, ``scale`` and ``gate`` scores of every Gaussian of the input run, the score used
  when it is ``free-space`` or ``predictive``, and the ``carriers`` flag.
- ``renders/{view}_{before,after,random}.png``: deterministic renders (``expected_render_sample``) of a few
  held-out views before pruning, after pruning, and after removing as many random Gaussians.
- ``prune.json``: counts before/after, score, threshold, keep ratio, held-out metrics (PSNR, SSIM, AUSE,
  NLL, coverage = mean rendered alpha) before, after, and for the random-removal baseline at the same
  count, seed, and with ``--sweep``/``--auto`` the curve (also in ``sweep.json``).
- ``eval/``: when the written model removed something, the pruned run evaluated as ``evaluate`` does (its maps,
  ``metrics.json``, the pixel noise fitted for the pruned model), with this K and seed; the "after" row is its held-out
  means, and ``evaluate`` of ``OUT`` with the same settings keeps it instead of computing it again.

``--dry-run`` writes no model (no config.json, scene.json or PLYs; ``OUT`` then holds only the report
files, and with no ``-o`` nothing is written at all). ``--sweep`` alone (no keep ratio, threshold or
auto) measures the curve and writes no model either.

Which Gaussians a score may remove: only posterior carriers (see ``uncertainty.scores``), so a keep ratio
below the fraction of non-carriers is reached only as far as the carriers allow (``keep_ratio_achieved``
says how far). ``--auto`` walks the sweep ratios from the largest down and stops at the first whose
held-out PSNR of the expected render (``psnr_render``, one render per view) falls more than ``tolerance_db`` below
the unpruned model's (the last one before it wins); without ``--sweep`` it measures no ratio past that one and the
ratios it walks by their render only (the K samples' uncertainty metrics are measured for the chosen mask).
"""

from __future__ import annotations

import hashlib
import os
import shutil
import tempfile
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path

import numpy as np
import torch

from uncertsplat.config import EvalConfig, PruneConfig
from uncertsplat.console import console, print_table, q
from uncertsplat.errors import NoPosterior, UserError, run_folder_missing
from uncertsplat.io.atomic import temp_folder, temp_stem
from uncertsplat.provenance import file_sha256
from uncertsplat.schemas.base import path_from
from uncertsplat.schemas.prune import (
    METRIC_KEYS,
    PRUNED_FROM_EVALUATE,
    UNPRUNED_FROM_EVALUATE,
    PruneCounts,
    PruneMetrics,
    PruneMetricSet,
    PruneReport,
    PsnrChange,
    ScoreStats,
    Written,
)
from uncertsplat.schemas.runs import RunExposure
from uncertsplat.schemas.scene import RunScene


# ------------------------------------------------------------------------------------------ checks
def _check_paths(run_dir: Path, output: Path | None, cfg: PruneConfig) -> None:
    if not run_dir.is_dir():
        raise run_folder_missing(run_dir)
    writes_model = not cfg.dry_run and _has_mode(cfg)
    if writes_model and cfg.score == "predictive":
        # it ranks the Gaussians the image needs most first (uncertainty.scores): a helper's fern run lost 19 dB at
        # keep 0.8 (27.1 -> 8.2 dB; random removal 25.6), the note that said so came after the model was written
        raise UserError("the predictive score ranks first the Gaussians the rendered images depend on most: a model "
                        "pruned by it loses most of its image quality (fern, keep 0.8: 27.1 -> 8.2 dB)", path=run_dir,
                        hint="Prune by free-space, gate, position or scale (or --score auto); study the predictive "
                             "score with --dry-run or --sweep, which write no model.")
    if output is None:
        if writes_model:
            raise UserError("no output folder given", path=run_dir,
                            hint="Add -o NEW_RUN (the input run is never modified), or --dry-run to only report.")
        return
    src, dst = run_dir.resolve(), output.resolve()
    if dst == src:
        raise UserError("the output folder is the input run", path=output,
                        hint="Choose a new folder: prune writes a new run and never modifies the input.")
    if src in dst.parents:
        raise UserError("the output folder is inside the input run", path=output,
                        hint="Choose a folder outside the input run (e.g. next to it).")
    if dst in src.parents:
        raise UserError("the output folder contains the input run", path=output, hint="Choose a new, empty folder.")
    if output.exists() and (not output.is_dir() or any(output.iterdir())):
        raise UserError("the output folder already exists", path=output,
                        hint="Choose a new folder (prune never overwrites), or delete this one first.")


def _has_mode(cfg: PruneConfig) -> bool:
    return cfg.keep_ratio is not None or cfg.threshold is not None or cfg.auto


# ------------------------------------------------------------------------------------- measurement
class _Measure:
    """Held-out metrics of a model (MC uncertainty via ``evaluate_views``), coverage and file sizes."""

    def __init__(self, loaded, scene, indices: list[int], cfg: PruneConfig, device: torch.device):
        self.loaded, self.scene, self.indices, self.device = loaded, scene, indices, device
        self.ecfg = EvalConfig(num_samples=cfg.num_samples, seed=cfg.seed, save_maps=False)
        self.render_fn = loaded.render_fn(scene.scene_scale, device)
        self.cams = scene.cameras[indices].to(device)
        # the held-out images and GT depth are read once; every model of a sweep is measured on them
        # (8-bit photos kept as uint8, read as float32; masked as evaluate scores the run)
        self.views = loaded.scored_views(scene, indices, "test", keep_8bit=True)
        # the pixel noise of the source model's Gaussians, fitted once: a pruned model keeps its Gaussians' noise
        # (read from the source run's evaluation when it fitted the same one; the source run is never written)
        from uncertsplat.stages.residual_cache import fitted_residual

        self.residual = fitted_residual(loaded, scene.scene_scale, scene.split.get("train", ()), self.ecfg, device,
                                        load_views=loaded.training_views(scene), write=False,
                                        calibration_indices=scene.split.get("calibration", ()))
        self._dof: tuple[float | None] | None = None  # the source's predictive tails, once known (``dof``)
        # every pruned model's rays are counted empty against the source's coverage (``PruneReport.source_coverage``)
        self.source_coverage = (loaded.coverage(scene.scene_scale, device) if loaded.empty_std() is not None
                                else None)
        self.meta = {"variant": loaded.config.variant, "extent": loaded.extent, "step": loaded.step,
                     "sh_degree_active": loaded.sh_degree,
                     "temperature": loaded.config.variational.gate_temperature}
        self._cache: dict[str, PruneMetrics] = {}

    @torch.no_grad()
    def mean_renders(self, model) -> tuple[torch.Tensor, torch.Tensor]:
        """Deterministic rgb [C,H,W,3] and alpha [C,H,W,1] of the held-out views (CPU), by the expected render
        (``variational.expected_render_sample``)."""
        from uncertsplat.gaussians.variational import expected_render_sample

        s = expected_render_sample(model, **self.loaded.sample_kwargs)
        rgb, alpha = [], []
        for c in range(len(self.cams)):
            out = self.render_fn(s, self.cams[[c]])
            rgb.append(out.rgb[0].clamp(0, 1).cpu())
            alpha.append(out.alpha[0].cpu())
        return torch.stack(rgb), torch.stack(alpha)

    def unpruned(self, run_dir: Path) -> tuple[PruneMetrics, Path | None]:
        """The source model's metrics, and the ``evaluate`` report they were read from (None: measured here): its
        held-out means when ``evaluate`` scored this model file on these views with these settings
        (``stages.evaluate.matching_evaluation``: what ``self(model)`` would measure again); the expected render's
        PSNR, the coverage and the file sizes are measured either way."""
        from uncertsplat.schemas.metrics import EvalReport
        from uncertsplat.stages.evaluate import matching_evaluation

        names = [self.scene.cameras.image_names[i] for i in self.indices]
        report = matching_evaluation(run_dir, Path(self.loaded.source), self.ecfg, names, self.device)
        if report is None:
            return self(self.loaded.model), None
        self._dof = (report.degrees_of_freedom,)
        t0 = time.perf_counter()
        cheap = self(self.loaded.model, full=False)
        return cheap.model_copy(update={**{k: getattr(report.mean, k) for k in METRIC_KEYS},
                                        "seconds": time.perf_counter() - t0}), run_dir / EvalReport.FILE_NAME

    def dof(self) -> float | None:
        """The source model's RGB predictive tails (``eval.engine.fit_std_scale``), which every model of the sweep
        is scored with, so that their NLLs compare: read from the source's evaluation when ``unpruned`` found one,
        else fitted once here."""
        if self._dof is None:  # as `evaluate` fits it
            from uncertsplat.eval.engine import scored_sampler

            _, fit = scored_sampler(partial(self.loaded.sampler, self.scene.scene_scale, self.device), self.residual,
                                    self.scene.cameras, self.scene.split, self.ecfg, self.device,
                                    load_views=self.loaded.training_views(self.scene))
            self._dof = (fit.dof,)
        return self._dof[0]

    def file_sizes(self, model) -> dict[str, int]:
        from uncertsplat.io.ply import write_point_cloud_ply, write_variational_ply

        with tempfile.TemporaryDirectory(prefix="uncertsplat-prune-") as tmp:
            v = write_variational_ply(Path(tmp) / "variational.ply", model, meta=self.meta)
            p = write_point_cloud_ply(Path(tmp) / "point_cloud.ply", model, variant=self.meta["variant"],
                                      extent=self.loaded.extent, temperature=self.meta["temperature"],
                                      sh_degree=self.meta["sh_degree_active"])
            return {"variational_ply_bytes": v.stat().st_size, "point_cloud_ply_bytes": p.stat().st_size}

    def __call__(self, model, keep: torch.Tensor | None = None, full: bool = True) -> PruneMetrics:
        """Metrics of ``model``; with ``keep`` (the mask that made it) the result is cached per mask. ``full=False``:
        only what one expected render per view gives (``psnr_render``, coverage) and the file sizes."""
        from uncertsplat.eval.engine import evaluate_views, with_side_terms
        from uncertsplat.eval.image import psnr

        key = None
        if keep is not None:
            key = hashlib.sha256(keep.cpu().numpy().tobytes()).hexdigest()
            cached = self._cache.get((key, True)) or (None if full else self._cache.get((key, False)))
            if cached is not None:
                return cached
        t0 = time.perf_counter()
        uncertainty = {}
        if full:
            dof = self.dof()
            loaded = self.loaded.with_model(model, coverage=self.source_coverage)
            residual = self.residual
            if residual is not None and keep is not None:
                residual = residual.subset(keep.to(residual.variance.device))
            elif residual is not None and len(model) != len(self.loaded.model):
                residual = None  # a model that is not a subset of the source: no noise to carry over
            sampler = with_side_terms(loaded.sampler(self.scene.scene_scale, self.device), residual,
                                      self.scene.cameras[list(self.scene.split.get("train", ()))], self.ecfg,
                                      self.device)
            report = evaluate_views(sampler, self.views, self.ecfg, self.device, show_progress=False,
                                    dof=dof)
            uncertainty = {k: getattr(report.mean, k) for k in METRIC_KEYS}
        rgb, alpha = self.mean_renders(model)
        masks = self.views.masks
        render_psnr = [float(psnr(rgb[j], self.views.images[j], masks[j] if masks is not None else None))
                       for j in range(len(rgb))]
        out = PruneMetrics(num_gaussians=len(model), num_carriers=model.num_carriers, **uncertainty,
                           psnr_render=sum(render_psnr) / len(render_psnr) if render_psnr else None,
                           # (inside the photos' own masks: a masked-out sky is no surface to cover)
                           coverage=float(alpha[masks.to(alpha.device)].mean() if masks is not None
                                          and self.views.masks_trained else alpha.mean()),
                           **self.file_sizes(model), seconds=time.perf_counter() - t0)
        if key is not None:
            self._cache[(key, full)] = out
        return out


# ------------------------------------------------------------------------------------------ helpers
def _num(x: float | None, digits: int = 2) -> str:
    return "n/a" if x is None else f"{x:.{digits}f}"


def _print_table(title: str, rows: list[tuple[str, PruneMetrics]]) -> None:
    from rich.table import Table

    table = Table(title=title)
    for col in ("model", "Gaussians", "PSNR dB", "PSNR dB, expected render", "SSIM", "AUSE-MAE", "NLL nats", "coverage",
                "variational.ply MB", "point_cloud.ply MB, no scores"):
        table.add_column(col, justify="right")

    def f(x, p=3):
        return "-" if x is None else f"{x:.{p}f}"

    for name, m in rows:
        table.add_row(name, str(m.num_gaussians), f(m.psnr, 2), f(m.psnr_render, 2), f(m.ssim), f(m.ause_mae),
                      f(m.nll), f(m.coverage), f(m.variational_ply_bytes / 1e6, 2),
                      f(m.point_cloud_ply_bytes / 1e6, 2))
    print_table(table)


def rebuild_from_mask(run_dir: str | Path, mask_file: str | Path, device: torch.device | str = "cpu"):
    """The pruned model rebuilt from the original run and a ``prune_mask.npy`` (kept indices).

    Raises:
        UserError: when the mask does not fit the run's model (e.g. the run was retrained since).
    """
    from uncertsplat.baselines import load_run
    from uncertsplat.prune import apply_keep, mask_from_indices

    loaded = load_run(run_dir, device)
    idx = torch.from_numpy(np.load(mask_file)).to(loaded.model.device)
    try:
        keep = mask_from_indices(idx, len(loaded.model))
    except ValueError as err:
        raise UserError(f"the mask does not fit this run ({err})", path=mask_file,
                        hint="Use the run recorded as 'source_run' in prune.json.") from None
    return apply_keep(loaded.model, keep)


# ---------------------------------------------------------------------------------------------- run
def run(run_dir: Path, output: Path | None, cfg: PruneConfig, device: torch.device) -> PruneReport:
    """Prune ``run_dir`` into ``output`` (see the module docstring); returns what ``prune.json`` holds.

    Raises:
        UserError: a missing run folder, a run without posterior carriers, no mode given, an unknown
            score, an output folder equal to / inside / containing the input or already existing.
    """
    from uncertsplat import native
    from uncertsplat.io.atomic import lock_holder

    if not Path(run_dir).is_dir():
        raise run_folder_missing(Path(run_dir))
    holder = lock_holder(run_dir)
    if holder is not None:  # a training going on there changes the model under the scores (a prune during `train
        # --resume` pruned the earlier model and named the run as its source); prune only reads the run, so it takes
        # no lock itself (other prunes of it, and a read-only run, are fine)
        raise UserError(f"another uncertsplat process ({holder}) is working on this run: its model or evaluation may "
                        "be changing", path=run_dir, hint="Wait for it to finish, then prune.")
    with native.single_threaded_torch(device):
        return _run(run_dir, output, cfg, device)


def _scene_settings(config) -> list[str]:
    """``scene.KEY=VALUE`` for each scene setting of a run's ``config`` (``TrainConfig``) apart from its default:
    a new run on the scene with them has the run's views, split and scale (its training views, not others, give an
    imported model its posterior, and its held-out views stay the ones the model never saw)."""
    import json

    from uncertsplat.config import SceneConfig

    default = SceneConfig().model_dump(mode="json")
    return [f"scene.{k}={json.dumps(v, separators=(',', ':'))}"
            for k, v in config.scene.model_dump(mode="json").items() if v != default.get(k)]


def _run(run_dir: Path, output: Path | None, cfg: PruneConfig, device: torch.device):
    from uncertsplat.baselines import load_run
    from uncertsplat.prune import apply_keep
    from uncertsplat.prune.policy import (
        auto_keep_ratio,
        choose_mask,
        choose_score_at_ratio,
        choose_score_by_removal,
        keep_ratio_sweep,
        random_keep,
    )
    from uncertsplat.uncertainty.scores import (
        AUTO_ALTERNATIVES,
        carrier_mask,
        compute_scores,
        resolve_score_name,
        spread_views,
    )

    run_dir = Path(run_dir)
    output = Path(output) if output is not None else None
    device = torch.device(device)
    _check_paths(run_dir, output, cfg)
    if not _has_mode(cfg) and not cfg.sweep:
        raise UserError("no pruning mode given", path=run_dir,
                        hint="Add one of --keep-ratio R (e.g. 0.9), --threshold T or --auto (or --sweep to only "
                             "measure the curve).")
    try:
        score_name = resolve_score_name(cfg.score)
    except ValueError as err:
        raise UserError(str(err)) from None

    loaded = load_run(run_dir, device)
    loaded.warn_if_unfinished()
    model = loaded.model
    if loaded.config.method == "ensemble" and model.num_carriers > 0:  # members of our model: each can be pruned
        raise UserError("an ensemble is pruned member by member: its members are runs of their own", path=run_dir,
                        hint=f"Prune a member, e.g. uncertsplat prune {q(run_dir / 'members' / 'member_0')} -o OUT.")
    if model.num_carriers == 0:
        method = loaded.config.method
        article = "an" if method[0] in "aeiou" else "a"
        why = (f"{article} {method} run has no per-Gaussian posterior" if method in ("deterministic", "ensemble", "fisher")
               else "the run has no Gaussians with a posterior (posterior carriers)")
        from uncertsplat.train.trainer import no_carriers_reason

        reason = no_carriers_reason(loaded.config, loaded.step) if method == "variational" else None
        # (NoPosterior: a run its settings left without one, a short test run, which a pipeline skips; a method
        # without a posterior, or a scene whose Gaussians the spawn rule passed over, is an error there too)
        error = NoPosterior if reason else UserError
        hint = ("Prune a run whose Gaussians carry a posterior (train's closing lines say how many do)."
                if method == "variational" else
                "Prune a run trained with the variational method (the default) past its first densification step")
        if method in ("deterministic", "fisher") and (run_dir / "point_cloud.ply").is_file():
            # a plain model gets the informed posterior without training again (seconds: train --from-ply)
            scene_dir = loaded.scene_path or "SCENE"
            hint += (f", or give this one the posterior first: uncertsplat train {q(scene_dir)} -o "
                     f"{q(run_dir.parent / (run_dir.name + '_posterior'))} --from-ply {q(run_dir / 'point_cloud.ply')}"
                     + "".join(f" --set {q(s)}" for s in _scene_settings(loaded.config))
                     + " (no training; then prune that run).")
        elif method != "variational":
            hint += "."
        raise error(f"{why}, so there is no uncertainty to prune by" + (f": {reason}" if reason else ""),
                    path=run_dir, hint=hint)
    scene = loaded.load_scene()
    notes: list[str] = []
    split = "test"
    indices = list(scene.split.get("test", ()))
    if not indices:
        split = "train"
        indices = list(scene.split["train"])
        notes.append("the scene has no held-out views: metrics are on the training views")
    if cfg.auto and split != "test":
        raise UserError("--auto needs held-out views to measure the PSNR loss, and this scene has none",
                        path=run_dir, hint="Use --keep-ratio or --threshold, or retrain with held-out views.")

    # ---- scores (every posterior score; the predictive one only when asked for: it renders)
    prior = loaded.prior
    render_fn = loaded.render_fn(scene.scene_scale, device)
    names = ("position", "scale", "gate") + ((score_name,) if score_name in ("predictive", "free-space") else ())
    score_cams = scene.cameras[spread_views(scene.split["train"], cfg.score_views)].to(device)
    free_cams = scene.cameras[spread_views(scene.split["train"], cfg.free_space_views)].to(device)
    t0 = time.perf_counter()
    scores = compute_scores(model, score_cams, torch.Generator(device=device).manual_seed(cfg.seed),
                            render_fn=render_fn, names=names, num_samples=cfg.score_samples,
                            subset_size=loaded.config.variational.subset_size, variant=prior.variant,
                            extent=loaded.extent, temperature=prior.temperature, free_space_cameras=free_cams,
                            free_space_margin=cfg.free_space_margin)
    score_seconds = time.perf_counter() - t0
    carriers = carrier_mask(model)
    n = len(model)

    # ---- which score: with score auto, --auto or --keep-ratio and held-out views, the default and its alternatives
    # are each measured and the one that prunes better is used (free-space misreads thin structure in front of a
    # surface as floaters on some captures; BENCHMARKS.md "Pruning")
    candidates = [score_name]
    if (cfg.score == "auto" and not cfg.sweep and split == "test" and cfg.threshold is None
            and (cfg.auto or cfg.keep_ratio is not None)):
        candidates += [n for n in AUTO_ALTERNATIVES if n != score_name]

    if split == "test" and (cfg.auto or len(candidates) > 1):
        # the choice is a fit to these views: a reader should not take the "after" row as an unbiased estimate
        chosen = [w for w, on in (("keep ratio", cfg.auto), ("score", len(candidates) > 1)) if on]
        notes.append("the " + " and the ".join(chosen) + (" were" if len(chosen) > 1 else " was")
                     + f" {CHOSEN_NOTE}, so the 'after' row flatters the pruned model a little for views it has not "
                       "seen (a choice among a few options)")
    which = f"'{score_name}'" if len(candidates) == 1 else f"auto ({', '.join(candidates)}: the better one)"
    console.print(f"[bold]prune[/] {run_dir}: {n} Gaussians ({model.num_carriers} with a posterior), score "
                  f"{which}, {len(indices)} {split} views, K={cfg.num_samples}, {device}")
    measure = _Measure(loaded, scene, indices, cfg, device)
    before, read_from = measure.unpruned(run_dir)
    if read_from is not None:
        notes.append(f"{UNPRUNED_FROM_EVALUATE} ({read_from}: the same model file, "
                     "views, settings and versions)")

    # ---- sweep (also what --auto decides on)
    def sweep_of(name: str, ratios, **kw):
        return keep_ratio_sweep(model, scores[name], carriers, ratios, measure, unpruned=before, seed=cfg.seed,
                                tolerance_db=cfg.tolerance_db, score_name=name, split=split, **kw)

    sweep = None
    if cfg.sweep or cfg.auto:
        def show(p, name=None):
            console.print(f"  {f'{name}: ' if name else ''}keep {p.keep_ratio:.2f}: removed {p.num_removed}, PSNR of "
                          f"the expected render {_num(p.score.psnr_render)} (random {_num(p.random.psnr_render)})")

        # --auto alone decides on the expected render's PSNR and measures the uncertainty of the chosen mask only
        sweeps = {name: sweep_of(name, cfg.sweep_ratios, stop_at_first_failure=not cfg.sweep, full=cfg.sweep,
                                 on_point=partial(show, name=name if len(candidates) > 1 else None))
                  for name in candidates}
        if len(sweeps) > 1:
            score_name, note = choose_score_by_removal(sweeps)
            notes.append(note)
        sweep = sweeps[score_name]
    elif len(candidates) > 1:  # --keep-ratio R: the expected render's PSNR at R by each score
        score_name, note = choose_score_at_ratio({name: sweep_of(name, [cfg.keep_ratio], full=False)
                                                  for name in candidates}, cfg.keep_ratio)
        notes.append(note)
    score = scores[score_name]

    # ---- the chosen mask
    threshold = cfg.threshold
    keep_ratio = cfg.keep_ratio
    if cfg.auto:
        keep_ratio, note = auto_keep_ratio(sweep)
        if note:
            notes.append(note)
    keep, mask_notes = choose_mask(score, carriers, threshold=threshold, keep_ratio=keep_ratio)
    notes.extend(mask_notes)

    result = PruneReport(
        source_run=str(run_dir.resolve()), source_model=str(loaded.source.name),
        source_model_sha256=file_sha256(loaded.source), score=score_name, score_requested=cfg.score,
        mode="auto" if cfg.auto else "threshold" if threshold is not None else
             "keep_ratio" if keep_ratio is not None else "sweep",
        threshold=threshold, keep_ratio=keep_ratio, tolerance_db=cfg.tolerance_db, seed=cfg.seed,
        num_samples=cfg.num_samples, metric_split=split, metric_views=[scene.cameras.image_names[i] for i in indices],
        score_views=list((free_cams if score_name == "free-space" else score_cams).image_names),
        score_seconds=score_seconds, dry_run=cfg.dry_run,
        device=str(device), notes=notes, source_coverage=measure.source_coverage,
        score_stats={k: ScoreStats(min=float(v[carriers].min()), median=float(v[carriers].median()),
                                   max=float(v[carriers].max())) for k, v in scores.items()},
        metrics=PruneMetricSet(before=before), sweep=sweep,
        undo=("The source run is unchanged: use it to undo. prune_mask.npy lists the kept indices into its model; "
              "uncertsplat.stages.prune.rebuild_from_mask(source_run, prune_mask.npy) rebuilds this model."
              if keep is not None else "Nothing was removed (a sweep only, no mask): the source run is unchanged."),
    )
    pruned = random_model = None
    # the pruned model is scored by ``evaluate`` itself (``_evaluate_written``): the "after" row is the pruned run's own
    # evaluation (its pixel noise, tails and std factor fitted on it, where the sweep's rows keep the source's so that
    # they compare), and an ``evaluate`` of the written run with the same settings has nothing to redo; a dry run
    # evaluates it in a temporary folder, so that its "after" row is the one the same prune with -o writes
    evaluate_written = output is not None and not cfg.dry_run
    if keep is not None:
        removed = int((~keep).sum())
        pruned = apply_keep(model, keep)
        rand_keep = random_keep(n, removed, cfg.seed)
        random_model = apply_keep(model, rand_keep)
        after = before if removed == 0 else measure(pruned, keep, full=not (evaluate_written or cfg.dry_run))
        rand = before if removed == 0 else measure(random_model, rand_keep)
        removed_scores = score[~keep]
        result.counts = PruneCounts(before=n, after=n - removed, removed=removed, carriers_before=model.num_carriers,
                                    carriers_after=pruned.num_carriers)
        result.keep_ratio_achieved = (n - removed) / n
        result.threshold_effective = float(removed_scores.min()) if removed else None
        result.metrics = PruneMetricSet(before=before, after=after, random=rand)
        if removed == 0:  # the 'after' row is the 'before' row: no choice of these views flatters it
            notes[:] = [n for n in notes if CHOSEN_NOTE not in n]
        _psnr_change(result)
        if cfg.dry_run and removed > 0:
            with tempfile.TemporaryDirectory(prefix="uncertsplat-prune-dry-") as tmp:
                _write_model(Path(tmp), run_dir, loaded, measure.meta, pruned, keep, carriers, scores)
                result.write(Path(tmp) / PruneReport.FILE_NAME)  # its source_coverage, as the written run's
                _evaluate_written(Path(tmp), result, measure, device, save_maps=False)
            notes.append("the 'after' row's uncertainty metrics are the pruned model evaluated as `evaluate` does "
                         f"(K = {cfg.num_samples}, seed {cfg.seed}; in a temporary folder, not kept)"
                         + ("" if cfg.score == "predictive" else  # (a model is not written by it)
                            ": the same prune with -o writes that evaluation as the pruned run's eval/"))
        _tolerance_note(result, notes, cfg)
        _random_note(result, notes, score_name, cfg)

    if output is None:
        _print_result(result, notes, score_name, cfg)
        console.print("dry run: nothing written" if cfg.dry_run else "sweep only: nothing written (no -o)")
        return result
    def evaluate_staged(staged: Path) -> None:  # (in the staging folder, before it is renamed to the output)
        _evaluate_written(staged, result, measure, device, shown=output)
        notes.append(f"{PRUNED_FROM_EVALUATE} ({output / 'eval' / 'metrics.json'}: "
                     "the pruned run evaluated as `evaluate` does, with this K and seed)")
        _tolerance_note(result, notes, cfg)
        _random_note(result, notes, score_name, cfg)

    # (nothing removed: the "after" row is the "before" row)
    evaluates = evaluate_written and keep is not None and result.counts.removed > 0
    _write_output(run_dir, output, cfg, measure, loaded, result, scores, carriers, keep, pruned, random_model, sweep,
                  evaluate_staged if evaluates else None)
    _print_result(result, notes, score_name, cfg)
    return result


CHOSEN_NOTE = "chosen on these held-out views"
"""Words of the note that the keep ratio or the score was chosen on the views the 'after' row is measured on."""
RANDOM_NOTE = "removing random Gaussians instead cost less"
RANDOM_MARGIN_DB = 0.1
"""``_random_note``: the held-out PSNR (expected render) by which random removal must beat the score to be noted."""


def _random_note(result: PruneReport, notes: list[str], score_name: str, cfg: PruneConfig) -> None:
    """A note when removing as many random Gaussians kept the held-out PSNR (the expected render's: one render a view,
    no sampling noise) better than the score's choice by more than ``RANDOM_MARGIN_DB``: the score did not find what
    the model can spare, on this run. Replaces an earlier such note in ``notes`` (and sets ``result.notes``)."""
    notes[:] = [n for n in notes if not n.startswith(RANDOM_NOTE)]
    m = result.metrics
    if (m.after is not None and m.random is not None and result.counts is not None and result.counts.removed > 0
            and None not in (m.after.psnr_render, m.random.psnr_render)
            and m.random.psnr_render - m.after.psnr_render > RANDOM_MARGIN_DB):
        notes.append(f"{RANDOM_NOTE}: {m.random.psnr_render:.2f} dB held out against {m.after.psnr_render:.2f} dB by "
                     f"'{score_name}' (expected render): this score did not find what this model can spare"
                     + ("; --score auto measures the scores on the run and keeps the better one"
                        if cfg.score != "auto" else "; a smaller removal (--auto) loses less"))
    result.notes = notes


TOLERANCE_NOTE = "the tolerance bounds the expected render's PSNR"


def _tolerance_note(result: PruneReport, notes: list[str], cfg: PruneConfig) -> None:
    """With ``--auto``: which PSNR the tolerance bounds (the expected render's, ``psnr_render``) and by how much each
    changed, so that a table or ``delta_psnr_db`` (the mean of the K samples' renders) past the tolerance does not
    read as a broken promise. Replaces an earlier such note in ``notes`` (and sets ``result.notes``)."""
    m = result.metrics
    notes[:] = [n for n in notes if not n.startswith(TOLERANCE_NOTE)]
    removed = result.counts is not None and result.counts.removed > 0
    if cfg.auto and removed and m.after is not None and None not in (m.before.psnr_render, m.after.psnr_render):
        change = m.after.psnr_render - m.before.psnr_render
        line = (f"{TOLERANCE_NOTE} (psnr_render, one render a view; {cfg.tolerance_db:g} dB): "
                f"{m.before.psnr_render:.3f} -> {m.after.psnr_render:.3f} dB ({change:+.3f})")
        if result.delta_psnr_db is not None:
            line += (f"; the table's PSNR and delta_psnr_db are the mean of the K samples' renders "
                     f"({result.delta_psnr_db.score:+.3f} dB), which it does not bound")
        notes.append(line)
    result.notes = notes


def _psnr_change(result: PruneReport) -> None:
    """``result.delta_psnr_db`` from its metrics, when all three rows have a PSNR."""
    m = result.metrics
    if m.after is not None and m.random is not None and None not in (m.before.psnr, m.after.psnr, m.random.psnr):
        result.delta_psnr_db = PsnrChange(score=m.after.psnr - m.before.psnr, random=m.random.psnr - m.before.psnr)


def _print_result(result: PruneReport, notes: list[str], score_name: str, cfg: PruneConfig) -> None:
    m = result.metrics
    if result.counts is not None and m.after is not None and m.random is not None:
        c = result.counts
        _print_table(f"prune: keep {c.after}/{c.before} by '{score_name}' ({result.metric_split} views, "
                     f"K={cfg.num_samples})", [("before", m.before), ("after", m.after), ("random", m.random)])
    for note in notes:
        console.print(f"[yellow]note:[/] {note}")


def _evaluate_written(output: Path, result: PruneReport, measure: _Measure, device: torch.device,
                      save_maps: bool = True, shown: Path | None = None) -> None:
    """Evaluate the pruned run just written to ``output`` as ``evaluate`` does (``output/eval``), and take its held-out
    means as the "after" row of ``result`` (a dry run's: a temporary folder, without the maps). ``shown``: the folder
    the console names (the output, where ``output`` is its staging folder)."""
    from uncertsplat.stages import evaluate

    console.print(f"evaluating the pruned run {shown or output} as `evaluate` does" if save_maps else
                  "evaluating the pruned model as `evaluate` would (in a temporary folder, removed after)")
    report = evaluate.run(output, measure.ecfg.model_copy(update={"save_maps": save_maps}), device, quiet=True)
    after = result.metrics.after
    result.metrics.after = after.model_copy(update={k: getattr(report.mean, k) for k in METRIC_KEYS})
    _psnr_change(result)


def _host_tag() -> str:
    """This machine's name for a staging folder's name (letters and digits only): a PID is only checked on its host."""
    import re
    import socket

    return re.sub(r"[^A-Za-z0-9]", "", socket.gethostname())[:32] or "host"


def _remove_dead_temp_folders(output: Path) -> None:
    """Remove the staging folders of earlier prunes into ``output`` whose process is gone (killed while writing: each
    held a whole model); a live one's is another prune at work and stays."""
    host = _host_tag()
    for p in output.parent.glob(f".{temp_stem(output.name)}.tmp-{host}-*-*"):
        pid = p.name[len(f".{temp_stem(output.name)}.tmp-{host}-"):].split("-", 1)[0]
        if not pid.isdigit() or not p.is_dir():  # (another host's, on a shared file system: not ours to judge)
            continue
        try:
            os.kill(int(pid), 0)
        except ProcessLookupError:
            shutil.rmtree(p, ignore_errors=True)
        except OSError:  # alive under another user: not ours to remove
            pass


def _in_output(path: Path | None, staging: Path, output: Path) -> Path | None:
    """``path`` as it would lie in ``output`` when it lies in ``staging`` (the staging folder, removed), else itself."""
    if path is None:
        return None
    try:
        return output / Path(path).relative_to(staging)
    except ValueError:
        return path


def _write_model(folder: Path, run_dir: Path, loaded, meta: dict, pruned, keep: torch.Tensor, carriers: torch.Tensor,
                 scores: dict) -> None:
    """The pruned run's own files in ``folder``: the source's config, scene and exposure, the pruned PLYs (the point
    cloud with each kept Gaussian's scores)."""
    import shutil

    from uncertsplat.data.dataset import TRANSIENTS_FOLDER, write_transient_masks
    from uncertsplat.io.atomic import atomic_write_bytes
    from uncertsplat.io.ply import set_vertex_properties, write_point_cloud_ply, write_variational_ply

    # a model read from a checkpoint newer than the PLY (a --resume stopped before its end) comes with that
    # checkpoint's exposures and transient regions (``baselines.runs._load_single``): the folder's exposure.json and
    # transients/ are an earlier training's, which the pruned run's evaluation would pair with this model
    from_checkpoint = Path(loaded.source).suffix == ".pt"
    for name in ("config.json", RunExposure.FILE_NAME):
        if name == RunExposure.FILE_NAME and from_checkpoint and loaded.exposure is not None:
            loaded.exposure.write(folder / name)
        elif (run_dir / name).is_file():
            atomic_write_bytes(folder / name, (run_dir / name).read_bytes())
    if loaded.transients is not None:  # (set only for a model read from a checkpoint)
        write_transient_masks(folder / TRANSIENTS_FOLDER, loaded.transients)
    elif (run_dir / TRANSIENTS_FOLDER).is_dir():  # what training left out of the photos, which pruning does not change
        shutil.copytree(run_dir / TRANSIENTS_FOLDER, folder / TRANSIENTS_FOLDER)
    info = RunScene.read_optional(run_dir / RunScene.FILE_NAME)
    if info is not None:  # its path relative to the run, from here (the staging folder is the output's sibling)
        scene = info.scene_folder(run_dir)
        info.scene, info.scene_from_run = str(scene.resolve()), RunScene.relative_path(scene, folder)
        info.write(folder / RunScene.FILE_NAME)
    write_variational_ply(folder / "variational.ply", pruned, meta=meta)
    write_point_cloud_ply(folder / "point_cloud.ply", pruned, variant=meta["variant"],
                          extent=loaded.extent, temperature=meta["temperature"], sh_degree=meta.get("sh_degree_active"))
    kept = keep.to(carriers.device)
    # names a program can take for identifiers: score_free_space, not score_free-space
    set_vertex_properties(folder / "point_cloud.ply",
                          {("contribution" if k == "contribution" else f"score_{k}".replace("-", "_")):
                           v[kept].cpu().numpy() for k, v in scores.items()})


def _write_output(run_dir: Path, output: Path, cfg: PruneConfig, measure: _Measure, loaded, result: PruneReport,
                  scores: dict, carriers: torch.Tensor, keep, pruned, random_model, sweep,
                  evaluate: Callable[[Path], None] | None = None) -> None:
    """Write the prune's files into a staging folder beside ``output`` and rename it into place. ``evaluate(staging)``
    (the pruned run evaluated as ``evaluate`` does, ``_evaluate_written``) runs before the rename: a prune stopped or
    killed during its evaluation (the longest step) left ``output`` with a prune.json without its "after" row and a
    dead process's lock and maps, which the same command then refused as an existing output."""
    from uncertsplat.data.dataset import photo_turns, turned_back
    from uncertsplat.io.atomic import atomic_write_bytes
    from uncertsplat.io.images import write_png
    from uncertsplat.io.maps import map_stem
    from uncertsplat.prune import kept_indices
    from uncertsplat.uncertainty.scores import spread_views

    output.parent.mkdir(parents=True, exist_ok=True)
    _remove_dead_temp_folders(output)
    tmp = temp_folder(f".{temp_stem(output.name)}.tmp-{_host_tag()}-{os.getpid()}-", output.parent)
    try:
        writes_model = keep is not None and not cfg.dry_run
        if writes_model:
            _write_model(tmp, run_dir, loaded, measure.meta, pruned, keep, carriers, scores)
        if keep is not None:
            np.save(tmp / "prune_mask.npy", kept_indices(keep).cpu().numpy().astype(np.int64))
        np.savez(tmp / "scores.npz", carriers=carriers.cpu().numpy(),
                 **{k: v.cpu().numpy() for k, v in scores.items()})
        if keep is not None and cfg.render_views > 0:
            sel = spread_views(range(len(measure.indices)), cfg.render_views)
            turns = photo_turns(measure.scene)  # each render lies as its photo does (as evaluate's maps)
            for tag, m in (("before", loaded.model), ("after", pruned), ("random", random_model)):
                rgb, _ = measure.mean_renders(m)
                among = [measure.scene.cameras.image_names[i] for i in measure.indices]
                for j in sel:
                    name = measure.scene.cameras.image_names[measure.indices[j]]
                    write_png(tmp / "renders" / f"{map_stem(name, among)}_{tag}.png",
                              turned_back(rgb[j].numpy(), turns.get(name, 0)))
        result.written = Written(model=writes_model, folder=str(output))
        if sweep is not None:
            sweep.write(tmp / "sweep.json")
        # the resolved settings of this prune (config.json beside it is the pruned run's training config)
        atomic_write_bytes(tmp / "prune_config.json", (cfg.model_dump_json(indent=2) + "\n").encode())
        result.source_from_run = path_from(output, run_dir)  # (tmp is the output's sibling: the same path from either)
        result.write(tmp / "prune.json")  # (the evaluation reads it: the source's coverage)
        if evaluate is not None:
            try:
                evaluate(tmp)
            except UserError as err:  # (a full disk while it wrote the maps): its own advice ("run again") works, as
                # nothing is kept; its file is named in the output below, which the rename would have made of the staging
                raise UserError(f"prune's evaluation of the pruned run failed: {err.message}; nothing was written "
                                "(the output folder appears only when prune has finished)",
                                path=err.path, hint=err.hint) from None
            result.write(tmp / "prune.json")  # with its "after" row
        try:
            if output.exists():
                output.rmdir()  # checked empty before any work; rmdir fails (safely) if something appeared since
            os.rename(tmp, output)
        except OSError:
            if output.exists() and any(output.iterdir()):  # another prune (or anything else) wrote it meanwhile
                raise UserError("the output folder was written by another process while this prune ran", path=output,
                                hint="Nothing of this prune was kept; choose another output folder (-o).") from None
            raise
    except BaseException as err:
        shutil.rmtree(tmp, ignore_errors=True)
        if isinstance(err, UserError) and err.path is not None:  # (a full disk): not the staging folder just removed
            err.path = _in_output(err.path, tmp, output)
            err.args = (err.render(),)
        raise
    what = "pruned run" if result.written.model else "report (no model: dry run)" \
        if cfg.dry_run else "report (no model: sweep only)"
    console.print(f"wrote {what} to {output}")
