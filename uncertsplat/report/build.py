"""Assemble the HTML report from loaded runs: sections, figures, tables.

Every input is read through its schema (``report.loader``). A section whose input is absent is replaced
by a short note saying what is missing and which command produces it; a section whose input is present
but invalid shows the one-line reason (naming the file and the key or version). Metric values are shown
as stored in the run's files (each numeric cell also carries the raw value in ``data-value``), never
recomputed.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from uncertsplat.config import method_label
from uncertsplat.console import q
from uncertsplat.errors import UserError
from uncertsplat.eval.engine import (
    GIVEN_SCENE_GT,
    MASKED_NOTE,
    PHOTO_MASKS_NOTE,
    SAME_RENDER,
    STD_TERMS,
    TRANSIENT_MASKS_NOTE,
)
from uncertsplat.eval.nll import NLL_WORSE_BY
from uncertsplat.gaussians.variational import describe_posterior
from uncertsplat.report import figures as F
from uncertsplat.report.extract import (
    METRIC_SPECS,
    PRUNE_SPECS,
    SPEC_BY_KEY,
    SUMMARY_KEYS,
    Calibration,
    Curve,
    MetricValue,
    calibrations_of,
    curves_of,
    format_value,
    metric_row,
    prune_row,
)
from uncertsplat.report.html import Cell, details, esc, figure, kv, note, page, para, pre, table
from uncertsplat.report.loader import (
    CONFIG,
    MANIFEST,
    METRICS,
    PRUNE,
    RECONSTRUCT,
    SCENE,
    SUMMARY,
    RunData,
    one_line,
    other_splits,
    unfinished_members,
    without_model,
)
from uncertsplat.report.views import SURFACE_MIN_ALPHA, ViewMaps, load_view
from uncertsplat.schemas import EvalReport, PruneMetrics, PruneReport, PruneSweep
from uncertsplat.schemas.prune import METRIC_KEYS as PRUNE_EVAL_KEYS
from uncertsplat.schemas.prune import PRUNED_FROM_EVALUATE, UNPRUNED_FROM_EVALUATE
from uncertsplat.strategy.growth import growth_reason
from uncertsplat.strategy.sh_bands import band_reason
from uncertsplat.train.imported import frame_phrase
from uncertsplat.train.transients import STOPPED as TRANSIENTS_STOPPED
from uncertsplat.train.transients import transients_note


@dataclass
class ReportWriter:
    """Collects figures (written through ``write_bytes``) and the HTML sections."""

    out: Path
    write_bytes: Callable[[Path, bytes], Any]
    figures: list[str] = field(default_factory=list)
    sections: list[tuple[str, str, str]] = field(default_factory=list)  # (anchor, nav label, html)

    def add_figure(self, name: str, png: bytes | None, caption: str, alt: str) -> str:
        """Write ``figures/name`` and return its <figure> HTML ('' when there is nothing to draw)."""
        if png is None:
            return ""
        rel = f"figures/{name}"
        self.write_bytes(self.out / rel, png)
        self.figures.append(rel)
        return figure(rel, caption, alt)

    def section(self, anchor: str, label: str, body: str) -> None:
        self.sections.append((anchor, label, f'<section id="{esc(anchor)}"><h2>{esc(label)}</h2>{body}</section>'))


# --------------------------------------------------------------------------------------------- helpers
def _problem_note(run: RunData, file: str) -> str:
    """A note with the one-line reason ``file`` could not be read ('' when it was read or is absent)."""
    problem = run.problem(file)
    return "" if problem is None else note(f"{run.name}: left out: {problem}")


def _file_note(run: RunData, file: str, absent: str) -> str:
    """The note for a section whose input ``file`` is not available: why it could not be read, or ``absent``."""
    return _problem_note(run, file) or note(f"{run.name}: {absent}")


def holds_no_model(run: RunData) -> bool:
    """Whether ``run`` is a prune folder without a model (``prune --dry-run``, or ``--sweep`` alone with -o): it holds
    prune.json, scores.npz and the mask only, no config.json or PLY, so ``evaluate`` refuses it."""
    p = run.prune
    return p is not None and (p.dry_run or (p.written is not None and not p.written.model))


PRUNE_MODE_KEYS = ("keep_ratio", "threshold", "auto", "tolerance_db", "score", "dry_run", "sweep", "sweep_ratios")
"""``PruneConfig`` keys the command's flags give (or that a model-writing prune must not repeat): the others of a dry
run's ``prune_config.json`` are passed on as ``--set``."""


def prune_again_command(p: PruneReport, config: dict | None = None, run_dir: Path | None = None) -> str | None:
    """The ``prune`` command that writes the model a dry run chose, into NEW_RUN: its source, mode and score, and
    every other setting of its ``prune_config.json`` (``config``) that is not the default (without it: the seed and K
    ``prune.json`` records), numbers as they were (``repr``: a threshold of 0.123456789 is not rounded); None for a
    sweep only, which chose no mask. ``run_dir``: the dry run's folder, from which its source is found
    (``PruneReport.source_folder``: a project moved elsewhere names its own)."""
    from uncertsplat.config import PruneConfig

    mode = {"keep_ratio": f"--keep-ratio {p.keep_ratio!r}" if p.keep_ratio is not None else None,
            "threshold": f"--threshold {p.threshold!r}" if p.threshold is not None else None,
            "auto": f"--auto --tolerance-db {p.tolerance_db!r}"}.get(p.mode)
    if mode is None:
        return None
    default = PruneConfig().model_dump(mode="json")
    source = p.source_folder(run_dir) if run_dir is not None else Path(p.source_run)
    args = ["uncertsplat", "prune", q(source), "-o", "NEW_RUN", mode]
    if p.score_requested != default["score"]:
        args.append(f"--score {q(p.score_requested)}")
    given = config if config is not None else {"seed": p.seed, "num_samples": p.num_samples}
    for k, v in given.items():
        if k in PRUNE_MODE_KEYS or k not in default or v == default[k]:
            continue
        value = json.dumps(v) if not isinstance(v, float) else repr(v)
        args.append(f"--set {q(f'{k}={value}')}")
    return " ".join(args)


def _no_model_text(run: RunData) -> str:
    """What a prune folder without a model holds and what a user can do instead of evaluating it."""
    p = run.prune
    what = ("a dry-run prune (prune --dry-run)" if p.dry_run else
            "a prune that measured the sweep only (prune --sweep without --keep-ratio, --threshold or --auto)")
    held = "prune.json and scores.npz" if p.counts is None else \
        "prune.json, scores.npz and prune_mask.npy (the indices of the Gaussians it keeps)"
    try:  # the dry run's whole configuration: every setting that chose its mask
        config = json.loads((run.path / "prune_config.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        config = None
    cmd = prune_again_command(p, config if isinstance(config, dict) else None, run.path)
    todo = (f"to measure the pruned model, prune without --dry-run, which writes it: `{cmd}`, then "
            "`uncertsplat evaluate NEW_RUN`" if cmd else
            "to measure a pruned model, prune with --keep-ratio, --threshold or --auto (without --dry-run), which "
            f"writes one (`uncertsplat prune {q(p.source_folder(run.path))} -o NEW_RUN --auto`), then "
            "`uncertsplat evaluate NEW_RUN`")
    return (f"{run.name}: {what}: it holds {held}, no model, so there is nothing to evaluate (`uncertsplat evaluate` "
            f"needs a run's config.json and model); the Pruning section shows what prune measured; {todo}.")


def _missing_metrics_note(run: RunData, full: bool = True) -> str:
    """The note for a run without eval/metrics.json: why it could not be read, what a prune folder without a model
    is (``full``: with what to do, said once in the Summary), or the command that measures the run."""
    if holds_no_model(run) and run.problem(METRICS) is None:
        return note(_no_model_text(run) if full else
                    f"{run.name}: a prune folder without a model (nothing to evaluate; the Summary says what to do).")
    if without_model(run) and run.problem(METRICS) is None:  # (`evaluate` of it fails: "no trained model here")
        return note(f"{run.name}: no trained model (neither variational.ply nor a checkpoint in ckpts/: its training "
                    "stopped before its first checkpoint), so there is nothing to evaluate: `uncertsplat train SCENE "
                    f"-o {q(run.path)} --resume` trains it from step 0; metric sections are left out for this run.")
    members = unfinished_members(run)
    if members is not None and run.problem(METRICS) is None:  # `evaluate` refuses it until every member is trained
        return note(f"{run.name}: no eval/metrics.json, and {members[1] - members[0]} of the ensemble's {members[1]} "
                    "members are not trained yet: finish training (the note above), then `uncertsplat evaluate "
                    f"{q(run.path)}`; metric sections are left out for this run.")
    other = other_splits(run)
    also = (f" ({', '.join(f'{n}/metrics.json' for n in other)} is another split's evaluation, which the report does "
            "not show: it reads the held-out views)" if other else "")
    return _file_note(run, METRICS, f"no eval/metrics.json{also} — run `uncertsplat evaluate {q(run.path)}` to "
                                    "measure the uncertainty; metric sections are left out for this run.")


def _fmt_seconds(v: float | None) -> str:
    if v is None:
        return "n/a"
    if v >= 120:
        return f"{v / 60:.1f} min"
    return f"{v:.1f} s"


def _short(v: Any) -> str:
    if v is None:
        return "—"
    if isinstance(v, float):
        return format(v, ".6g")
    return str(v)


def _cell(mv: MetricValue, key: str | None = None) -> Cell:
    return Cell(mv.text, key=key or mv.spec.key, value=mv.value)


def _num_cell(value: Any, fmt: str, key: str) -> Cell:
    return Cell(format_value(value, fmt), key=key, value=value)


def _num_gaussians(run: RunData) -> int | None:
    """The run's model size: after pruning for a pruned run, else what ``train`` ended with."""
    if run.prune is not None and run.prune.counts is not None:
        return run.prune.counts.after
    return run.train_summary.num_gaussians if run.train_summary is not None else None


def _ensemble_size(run: RunData) -> int | None:
    """The number of members of an unpruned ensemble run (whose Gaussian count sums theirs), else None."""
    s = run.train_summary
    if s is None or run.is_pruned or not s.ensemble_size or s.ensemble_size < 2:
        return None
    return s.ensemble_size


# ----------------------------------------------------------------------------------------- sections
MASKED_KEYS = ("psnr", "psnr_render")
"""Columns ``evaluate`` takes inside a scene's validity masks (``eval.engine.MASKED_NOTE``) that a reader compares with
numbers over whole images (train's held-out PSNR): labelled so where they are."""
MASK_MARK = " †"


def is_masked(run: RunData) -> bool:
    """Whether the run's evaluation took its PSNR (and AUSE, NLL, ...) inside the scene's validity masks."""
    return run.metrics is not None and any(n.startswith(MASKED_NOTE) for n in run.metrics.notes)


def _trained_inside_masks(run: RunData) -> bool:
    """Whether the masks of the run's evaluation are those its training left out (``eval.engine.PHOTO_MASKS_NOTE`` or
    ``TRANSIENT_MASKS_NOTE``), so that train's held-out PSNR is taken inside them too."""
    return run.metrics is not None and any(n.startswith(MASKED_NOTE) and (PHOTO_MASKS_NOTE in n or
                                                                         TRANSIENT_MASKS_NOTE in n)
                                           for n in run.metrics.notes)


def _prune_masked(run: RunData, p: PruneReport, runs: list[RunData]) -> bool:
    """Whether the prune's held-out PSNRs are inside the scene's masks: as its own or its source run's evaluation
    says (prune scores the views evaluate scores, with the same masks)."""
    source = p.source_folder(run.path).resolve()
    return is_masked(run) or any(is_masked(r) for r in runs if r.path.resolve() == source)


def _inside_masks(label: str) -> str:
    """'PSNR, expected render (dB)' -> 'PSNR, expected render, inside the masks (dB)'."""
    head, sep, unit = label.rpartition(" (")
    return f"{head}, inside the masks ({unit}" if sep else f"{label}, inside the masks"


def summary_section(w: ReportWriter, runs: list[RunData]) -> None:
    rows_by_run = [metric_row(r.metrics.mean) if r.metrics is not None else {} for r in runs]
    keys = [k for k in SUMMARY_KEYS if any(k in row and row[k].value is not None for row in rows_by_run)]
    masked = [is_masked(r) for r in runs]
    evaluated = [m for r, m in zip(runs, masked, strict=True) if r.metrics is not None]
    all_masked, some_masked = bool(evaluated) and all(evaluated), any(evaluated)
    labels = {k: SPEC_BY_KEY[k].label for k in keys}
    for k in MASKED_KEYS:
        if k in labels and some_masked:  # all: the header says it; some: a mark on those runs' cells
            labels[k] = _inside_masks(labels[k]) if all_masked else f"{labels[k]}{MASK_MARK}: inside the masks"
    header = ["run", "scene", "trained at (px)"] + [labels[k] for k in keys] + [
        "Gaussians", "training time", "s / view (uncertainty)", "samples K"]
    rows = []
    for run, mrow, mask in zip(runs, rows_by_run, masked, strict=True):
        info = run.scene_info
        cells: list[Cell | str] = [Cell(Path(info.scene).name if info else "n/a", text_cell=True),
                                   Cell(f"{info.width}x{info.height}" if info else "n/a")]
        for k in keys:
            cell = _cell(mrow[k]) if k in mrow else Cell("n/a")
            if mask and not all_masked and k in MASKED_KEYS and k in mrow:
                cell.text += MASK_MARK
            cells.append(cell)
        ng = _num_gaussians(run)
        cell = _num_cell(ng, ",d", "num_gaussians") if ng is not None else Cell("n/a")
        members = _ensemble_size(run)
        if ng is not None and members:  # the members' sum: the size of no one model
            cell.text += f" over {members} members"
        if ng is not None and holds_no_model(run):  # a dry run's count is what it would keep: no model holds it
            cell.text += " (would keep; no model written)"
        cells.append(cell)
        ts = run.train_summary.seconds if run.train_summary is not None else None
        if ts is not None and run.train_summary.imported is not None:
            # a model trained elsewhere: no step trained here ("0.0 s" read as a training); its posterior's time
            built = sum(float(u.seconds or 0.0) for u in run.train_summary.posterior_updates)
            cells.append(Cell(f"imported (posterior {_fmt_seconds(built)})", key="train_seconds", value=ts))
        else:
            cells.append(Cell(_fmt_seconds(ts), key="train_seconds", value=ts) if ts is not None else Cell("n/a"))
        m = run.metrics
        cells.append(_num_cell(m.seconds_per_view, ".3f", "seconds_per_view")
                     if m is not None and m.seconds_per_view is not None else Cell("n/a"))
        cells.append(Cell(str(m.num_samples), key="num_samples", value=m.num_samples) if m is not None
                     else Cell("n/a"))
        rows.append((run.name, cells))
    body = [table(header, rows, table_id="summary-table")]  # (the section is "summary": an id is unique)
    for mismatch in (comparability_note(runs), views_note(runs), samples_note(runs)):
        if mismatch:
            body.append(note(mismatch))
    body.append(para("Metrics are the means over the evaluated views, exactly as in each run's eval/metrics.json. "
                     "Lower is better for AUSE, NLL and calibration error; higher for PSNR and SSIM. AUSE: the area "
                     "under the sparsification error, how far removing pixels by their predicted std falls short of "
                     "removing them by their true error (0: a perfect ranking). NLL: the negative log-likelihood of the "
                     "photo per pixel and channel, in nats. Carriers: the Gaussians that carry a posterior (the others "
                     "are plain 3DGS Gaussians).", "legend"))
    for run in runs:
        if run.metrics is None and run.problem(METRICS) is None:
            body.append(_missing_metrics_note(run))
        for n in run.notes:
            body.append(note(f"{run.name}: {n}"))
        verdict = calibration_verdict(run.metrics) if run.metrics is not None else None
        if verdict:
            body.append(note(f"{run.name}: {verdict}"))
        if run.metrics is not None:
            if run.metrics.mean.spearman_note:
                body.append(note(f"{run.name}: Spearman: {run.metrics.mean.spearman_note}"))
            for n in evaluate_notes(run.metrics.notes, run.metrics.mean):
                body.append(note(f"{run.name} (evaluate): {n}"))
            parts = run.metrics.variance_parts()
            if parts:
                body.append(note(f"{run.name} (evaluate): what the variance is made of on the scored pixels of its "
                                 f"{run.metrics.split} views (each part's share, before the std factor and the RGB "
                                 f"std's cap at 0.5): {parts}"))
        post = run.train_summary.posterior if run.train_summary is not None else None
        if post is not None and post.carriers and post.moved_fraction is not None \
                and post.position_spread_ratio is not None and post.gate_off is not None:
            updates = run.train_summary.posterior_updates
            last = updates[-1].model_dump() if updates else None
            body.append(note(f"{run.name} (train): {describe_posterior(post.model_dump(), last)}"))
    w.section("summary", "Summary", "".join(body))


def comparability_note(runs: list[RunData]) -> str | None:
    """One sentence when the runs were trained on different scenes or at different resolutions (from each scene.json):
    their metrics then measure different things and must not be ranked against each other. None when they agree, or
    fewer than two runs say."""
    known = [r for r in runs if r.scene_info is not None]
    if len(known) < 2:
        return None
    scenes = {str(r.scene_path.resolve()) for r in known}
    sizes = {(r.scene_info.width, r.scene_info.height) for r in known}
    what = []
    if len(scenes) > 1:
        what.append("on different scenes (" + ", ".join(f"{r.name}: {r.scene_path}" for r in known) + ")")
    if len(sizes) > 1:
        what.append("at different resolutions (" + ", ".join(f"{r.name}: {r.scene_info.width}x{r.scene_info.height}"
                                                          for r in known) + ")")
    if not what:
        return None
    return ("These runs were trained " + " and ".join(what) + ": their metrics are not comparable (PSNR, NLL and the rest are measured on different images).")


VIEWS_LISTED = 6
"""``views_note`` names a run's evaluated views up to this many, and counts them beyond."""


def _evaluated_views(m) -> list[str]:
    """The views an evaluation (``EvalReport``) scored: its ``image_names``, or its per-view keys in files without
    them."""
    return list(m.image_names) or list(m.per_view)


def views_note(runs: list[RunData]) -> str | None:
    """One sentence when the evaluated runs were scored on different views (``EvalReport.image_names`` and split, e.g.
    one evaluated with ``--set max_views=1``): their means are over different images, so the sentence names which run
    was scored on which views (how many, and their names up to ``VIEWS_LISTED``). None when they agree (in any order)
    or fewer than two runs were evaluated."""
    evaluated = [r for r in runs if r.metrics is not None]
    if len({(r.metrics.split, frozenset(_evaluated_views(r.metrics))) for r in evaluated}) < 2:
        return None
    parts = []
    for r in evaluated:
        names = _evaluated_views(r.metrics)
        listed = ", ".join(names[:VIEWS_LISTED]) + (", …" if len(names) > VIEWS_LISTED else "")
        parts.append(f"{r.name}: {len(names)} {r.metrics.split} view{'' if len(names) == 1 else 's'}"
                     + (f": {listed}" if names else ""))
    return ("These runs were scored on different views (" + "; ".join(parts) + "): their means are over different "
            "images and do not rank them (evaluate them on the same split and views, e.g. the same max_views, to "
            "compare).")


def samples_note(runs: list[RunData]) -> str | None:
    """One sentence when the evaluated runs drew different numbers of samples K (a helper's six-run report ranked a
    run of K = 1 beside runs of K = 10 without a word); None when they agree or fewer than two were evaluated."""
    evaluated = [r for r in runs if r.metrics is not None]
    if len({r.metrics.num_samples for r in evaluated}) < 2:
        return None
    parts = "; ".join(f"{r.name}: K = {r.metrics.num_samples}" for r in evaluated)
    return (f"These runs were evaluated with different numbers of samples ({parts}): the samples' spread, and its "
            "Monte Carlo noise, change with K, so their AUSE, NLL and calibration do not rank the models alone "
            "(evaluate them with the same --num-samples to compare).")


SPREAD_TERM = STD_TERMS + "the variance of the K samples"
OLD_SPREAD_TERM = "std = the spread of the K samples"
"""How older evaluations began the formula (it read as a sum of stds; the terms always added as variances)."""


FACTOR_WORSE = "the fitted factor makes these views' NLL worse"
"""How evaluate's note (``stages.evaluate.std_factor_notes``) that the std factor worsens the NLL begins."""


def evaluate_notes(notes: list[str], mean=None) -> list[str]:
    """evaluate's notes as shown: for a model whose samples are all one render, the 'std² =' formula's first term says
    it is 0 there (it read as if the spread counted, beside the note that says it is 0); the warning that the fitted std
    factor worsens the NLL is left out where ``mean`` (``ViewMetrics``) shows it worse by no more than
    ``NLL_WORSE_BY`` (evaluations written before that threshold warned of 0.003 nats)."""
    # written before as "std = the spread ... + ...": the same terms, which always added as variances
    out = [SPREAD_TERM + n[len(OLD_SPREAD_TERM):] if n.startswith(OLD_SPREAD_TERM) else n for n in notes]
    if any(SAME_RENDER in n for n in out):
        out = [n.replace(SPREAD_TERM, f"{SPREAD_TERM} (0 for this model: {SAME_RENDER})", 1)
               if n.startswith(SPREAD_TERM) and not n.startswith(SPREAD_TERM + " (0") else n for n in out]
    raw, fitted = (mean.nll, mean.nll_calibrated) if mean is not None else (None, None)
    if raw is not None and fitted is not None and fitted - raw <= NLL_WORSE_BY:
        kept = []
        for n in out:  # the note joins its reasons with "; ": keep the others
            parts = [p for p in n.split("; ") if not p.startswith(FACTOR_WORSE)]
            if parts:
                kept.append("; ".join(parts))
        out = kept
    return out


CALIBRATION_SLACK = 0.05
"""``calibration_verdict``: how far the observed share inside the central 68 % interval may lie from 68 % before the
std is called too small or too large."""


def calibration_verdict(m) -> str | None:
    """One plain sentence on the RGB std's level on the evaluated views: the share of the errors inside the
    predictive's central 68 % interval against 68 % (None when calibrated within ``CALIBRATION_SLACK`` or not
    measured)."""
    table = m.calibration.get("rgb") if m.calibration else None
    if table is None or not table.ks:
        return None
    i = min(range(len(table.ks)), key=lambda j: abs(table.ks[j] - 1.0))
    seen, nominal = table.observed[i], table.nominal[i]
    if seen is None or abs(seen - nominal) <= CALIBRATION_SLACK:
        return None
    if seen < nominal:
        what = (f"the RGB std is too small on these views (over-confident): {seen:.0%} of the errors lie inside its "
                f"central {nominal:.0%} interval")
        fix = ("; the std factor fitted on training views does not mend it (it was fitted where the model fits "
               "better): views set aside from training give one that holds for new views "
               "(train with --set scene.calibration_holdout=3; in a pipeline, --set train.scene.calibration_holdout=3)"
               if m.std_scale is not None and m.std_scale < 1.0 and not m.calibration_held_out else "")
        return what + fix
    what = (f"the RGB std is too large on these views (under-confident): {seen:.0%} of the errors lie inside its "
            f"central {nominal:.0%} interval")
    raw, fitted = m.mean.nll, m.mean.nll_calibrated
    if m.std_scale is None or raw is None or fitted is None:
        return what
    if m.std_scale > 1.0:  # it widens a std that is already too wide: nothing to correct with it
        return what + f"; the std factor fitted on other views (x{m.std_scale:.3g}) widens it further"
    if fitted - raw > NLL_WORSE_BY:  # (a factor fitted where the model fits better overshoots here: said below)
        return what + "; the std factor fitted on other views does not correct it here (its NLL is worse)"
    before, after = m.mean.calibration_error, m.mean.calibration_error_calibrated
    if before is not None and after is not None and after > 0.05 and before - after < 0.5 * before:
        # a factor near 1 moves little: "corrects" overstated it (x0.95 took 0.085 to 0.078)
        return what + (f"; the std factor (x{m.std_scale:.3g}, NLL std rescaled) narrows it a little: calibration "
                       f"error {before:.3f} -> {after:.3f}")
    return what + f"; the std factor (x{m.std_scale:.3g}, NLL std rescaled) corrects the level"


def metrics_section(w: ReportWriter, runs: list[RunData]) -> None:
    body = []
    for ri, run in enumerate(runs):
        title = f"<h3>{esc(run.name)}</h3>" if len(runs) > 1 else ""
        m = run.metrics
        if m is None:
            if run.problem(METRICS) is not None:
                body.append(title + _missing_metrics_note(run))
            continue
        factor = run.depth_to_source
        gt_units = m.depth_scale is not None and in_gt_maps_units(m.depth_scale)
        rows_in = [(name, depth_in_scene_units(metric_row(v), factor, gt_units)) for name, v in m.per_view.items()]
        rows_in.append(("mean", depth_in_scene_units(metric_row(m.mean), factor, gt_units)))
        keys = [s.key for s in METRIC_SPECS if any(r[s.key].value is not None for _, r in rows_in)]
        empty = [s.label for s in METRIC_SPECS if s.key not in keys]
        labels = {k: rows_in[-1][1][k].spec.label for k in keys}
        if is_masked(run):
            labels.update({k: _inside_masks(labels[k]) for k in MASKED_KEYS if k in labels})
        rows = [(name, [_cell(r[k]) for k in keys]) for name, r in rows_in]
        facts: list[tuple[str, Any]] = [("split", m.split), ("views", len(m.per_view)), ("samples K", m.num_samples)]
        if m.depth_scale is not None:
            facts += _depth_facts(m.depth_scale, factor)
        if m.std_floor is not None:
            facts.append(("std floor (NLL)", m.std_floor))
        if m.std_scale is not None:
            facts.append(("std scale (calibrated NLL)",
                          f"x{m.std_scale:.3g}, fitted on {len(m.calibration_views)} {m.calibration_source}"))
        if m.degrees_of_freedom is not None:
            facts.append(("RGB predictive", f"Student-t with the std and {m.degrees_of_freedom:.3g} degrees of freedom"
                                            + (f", fitted on the {m.calibration_source}" if m.calibration_views else "")))
        if m.lpips is not None and not m.lpips.available:
            facts.append(("LPIPS", m.lpips.reason or "unavailable"))
            empty = [e for e in empty if e != SPEC_BY_KEY["lpips"].label]  # said once, with its reason
        if empty:
            facts.append(("not available", ", ".join(empty)))
        header = ["view"] + [labels[k] for k in keys]
        body.append(f'{title}{kv(facts)}<div data-run="{ri}">{table(header, rows, table_id=f"metrics-{ri}")}</div>')
    if not body:
        body.append(note(NO_METRICS if not all(holds_no_model(r) for r in runs) else NO_MODEL))
    else:
        body.append(para(METRICS_LEGEND, "legend"))
    w.section("metrics", "Metrics per view", "".join(body))


NO_METRICS = "No run has eval/metrics.json: run `uncertsplat evaluate RUN` first."
NO_MODEL = ("No run holds a model to evaluate: prune folders without a model (a dry run or a sweep only); the Summary "
            "says how to write one.")
"""The Metrics section's note when no run has eval/metrics.json: every run a prune folder without a model, which
``evaluate`` refuses (``holds_no_model``), or not."""


DEPTH_LENGTH_KEYS = ("depth_rmse", "depth_mae")
"""Depth metrics that are lengths: ``evaluate`` writes them in the run's normalised units, the report shows them in the
scene's (``data-value`` keeps the file's number)."""

_DEPTH_METHODS = {"scene": "none: the scene's GT depth has a known scale", "median": "estimated: median ratio",
                  "lsq": "estimated: least squares", "given": "given with --depth-scale",
                  GIVEN_SCENE_GT: "given with --depth-scale, against the scene's own GT depth"}


def in_gt_maps_units(info) -> bool:
    """Whether the depth errors of an evaluation (``info``: its ``DepthScaleInfo``) are in the units of GT maps of
    their own (a --depth-gt folder, the factor fitted or given: the rendered depth was scaled to them), rather than
    in the run's normalised units (the scene's own GT, with or without a given factor)."""
    return info.method not in ("scene", GIVEN_SCENE_GT)


def depth_in_scene_units(row: dict[str, MetricValue], factor: float | None,
                         gt_units: bool = False) -> dict[str, MetricValue]:
    """``row`` with its depth lengths (``DEPTH_LENGTH_KEYS``) shown in the scene's units (times ``factor``) and labelled
    so; without a factor they stay in the run's normalised units, labelled so; with ``gt_units`` (the rendered depth
    was scaled to GT maps of their own units) they are in those units already, labelled so."""
    out = dict(row)
    for k in DEPTH_LENGTH_KEYS:
        spec = row[k].spec
        unit = "GT maps' units" if gt_units else "scene units" if factor is not None else "run's normalised units"
        scale = 1.0 if gt_units else (factor or 1.0)
        out[k] = MetricValue(replace(spec, label=f"{spec.label} ({unit})", scale=spec.scale * scale), row[k].value)
    return out


def _depth_facts(info, factor: float | None) -> list[tuple[str, str]]:
    """What the depth numbers are: the alignment applied to the rendered depth and the units shown."""
    method = _DEPTH_METHODS.get(info.method, info.method)
    facts = [("depth alignment", f"rendered depth x{info.scale:.6g} before it is compared with the GT ({method})")]
    if in_gt_maps_units(info):
        facts.append(("depth units", "the GT maps' own: depth RMSE, MAE and NLL compare the rendered depth, scaled "
                                     "by the alignment, with them"
                                     + (f"; the depth maps are in the scene's units (x{factor:.6g})" if factor else "")))
    elif factor is not None:
        facts.append(("depth units", f"the scene's own (its GT depth's or COLMAP model's): depth RMSE, MAE and the "
                                     f"maps are the run's normalised values x{factor:.6g} (1 / the scale of the scene's "
                                     f"world_from_source); depth NLL stays per normalised unit (add "
                                     f"ln {factor:.4g} = {math.log(factor):+.3f} for the scene's)"))
    else:
        facts.append(("depth units", "the run's normalised units (no scene.json gives the factor to the scene's)"))
    return facts


METRICS_LEGEND = (
    "NLL (nats): of the predictive evaluate writes (the std of every term, Student-t tails where fitted), per pixel "
    "and channel; the number to compare methods on. NLL, std rescaled: the same with the std times the fitted factor. "
    "NLL, read as a Gaussian: the same std without the tails. NLL (KDE): a kernel density (Silverman's bandwidth) "
    "over the K samples' renders alone, without the pixel noise and the other terms; where the samples agree closely "
    "and the photo differs it runs into the thousands, which says the samples' spread is narrow, not that the "
    "predictive is wrong. NLL (paper formula): the original code's kernel density with its own bandwidth, not "
    "comparable with the others.")


def views_section(w: ReportWriter, runs: list[RunData], max_views: int) -> dict[int, dict[str, ViewMaps]]:
    """Per-view figures; returns the loaded maps (run index -> name -> maps) for the comparison section."""
    loaded: dict[int, dict[str, ViewMaps]] = {}
    body = [para("Each row: the ground-truth test image and the prediction (the mean of the sampled renders); the "
                 "absolute error and the predicted RGB std on one shared colour scale (same colour = same value); "
                 "depth mean and std (in the scene's own units, or the run's normalised ones where the factor is "
                 "not known, as the panel says); and the rank-coloured std next to the rank-coloured error (each pixel "
                 "coloured by its rank quantile in its own map, so good uncertainty makes the two look alike "
                 "whatever the scales). The colour bars end at the 99th percentile (the depth mean's start at the "
                 "1st): an end labelled ≥ or ≤ has pixels beyond it, drawn in its colour. In the depth panels, "
                 "grey pixels hold no surface (depth 0, or the samples' mean opacity below "
                 f"{SURFACE_MIN_ALPHA:g} where the maps carry it: a transparent background, empty sky): 0 there is "
                 "not a distance, and they are left out of the depth colour bars.", "legend")]
    for ri, run in enumerate(runs):
        title = f"<h3>{esc(run.name)}</h3>" if len(runs) > 1 else ""
        if run.metrics is None:
            body.append(title + _file_note(run, METRICS, "no eval/metrics.json (it names the evaluated views); "
                                                         "per-view figures left out."))
            continue
        if not run.maps_dir.is_dir():
            body.append(title + note(f"{run.name}: no eval/maps/ folder (evaluate with save_maps on to get the "
                                     "uncertainty maps); per-view figures left out."))
            continue
        names = list(run.metrics.image_names)
        if not names:
            body.append(title + note(f"{run.name}: eval/metrics.json lists no evaluated view; per-view figures "
                                     "left out."))
            continue
        body.append(title)
        loaded[ri] = {}
        shown = names[:max_views]
        if len(names) > len(shown):
            body.append(para(f"Showing {len(shown)} of {len(names)} views (`report --set max_views=N` shows more; "
                             "the tables list every view).", "muted"))
        for vi, name in enumerate(shown):
            view = load_view(name, run.maps_dir, run.depth_to_source, among=names)
            loaded[ri][name] = view
            empty = view.no_surface  # [H,W] bool
            share = float(empty.mean()) if empty is not None and empty.size else 0.0
            part = f"{share:.0%}" if share >= 0.01 else "under 1 %"
            caption = f"{run.name} — {name}" + (f"; grey in the depth panels: no surface ({part} of the pixels)"
                                                 if share > 0 else "")
            html = w.add_figure(f"run{ri}_view{vi}.png", F.view_figure(view, title=name), caption,
                                f"uncertainty maps of {name}")
            body.append(f"<h4>{esc(name)}</h4>" + (html or note(f"{name}: no maps could be read ({view.note}).")))
            if view.note and html:
                body.append(note(f"{name}: {view.note}"))
    w.section("views", "Test views", "".join(body))
    return loaded


COMPARED_VIEWS = 3
"""The most side-by-side figures the report draws (fewer with ``max_views`` below it)."""


def compare_plan(views_of: dict[int, list[str]], limit: int) -> list[tuple[str, list[int]]]:
    """The views to draw side by side, each with the runs that evaluated it: ``views_of`` maps a run's index
    to its evaluated views (``EvalReport.image_names``); each (view, run indices) returned has two runs or
    more.

    Runs evaluated on different views (one with ``--split train``, another ``max_views``, a scene of another
    split) share some views and not others. Requiring every run to hold a view drew nothing when one run
    shared none; instead each figure holds the runs that have its view. The first view is the one the most
    runs hold; each next one the view that adds the most runs not drawn yet (then the most runs), so within
    ``limit`` figures every run that shares a view with another is drawn where it can be. Ties go to the view
    listed first (the runs' order, then each run's): runs that share every view keep their first views, as
    before.
    """
    order: list[str] = []
    holders: dict[str, list[int]] = {}
    for ri in sorted(views_of):
        for name in views_of[ri]:
            if name not in holders:
                order.append(name)
                holders[name] = []
            if ri not in holders[name]:
                holders[name].append(ri)
    candidates = [n for n in order if len(holders[n]) >= 2]
    plan: list[tuple[str, list[int]]] = []
    drawn: set[int] = set()
    while candidates and len(plan) < limit:
        # max() keeps the first of equals: the view listed first
        name = max(candidates, key=lambda n: (len(set(holders[n]) - drawn), len(holders[n])))
        candidates.remove(name)
        plan.append((name, holders[name]))
        drawn.update(holders[name])
    return plan


def _has_rgb(view: ViewMaps) -> bool:
    """Whether a view's maps give a row of the side-by-side figure (``side_by_side_figure``'s test)."""
    return view.rgb_mean is not None or view.rgb_std is not None


def compare_section(w: ReportWriter, runs: list[RunData], loaded: dict[int, dict[str, ViewMaps]],
                    max_views: int) -> None:
    """One evaluated view across runs, for the views two runs or more evaluated (``compare_plan``), each
    figure naming the runs left out of it and why. ``loaded`` holds the maps ``views_section`` read (run index
    -> view -> maps); the others are read here (a view shared past a run's first ``max_views``)."""
    if len(runs) < 2:
        return
    # the runs with maps are compared; those without any (no evaluation, or save_maps off) are named
    with_maps = [ri for ri in range(len(runs)) if loaded.get(ri)]
    views_of = {ri: list(runs[ri].metrics.image_names) for ri in with_maps}
    plan = compare_plan(views_of, min(COMPARED_VIEWS, max_views))
    body = []
    without = [runs[ri].name for ri in range(len(runs)) if ri not in with_maps]
    if len(with_maps) < 2:
        body.append(note("Fewer than two runs have uncertainty maps; side-by-side images left out"
                         + (f" (no maps: {', '.join(without)})." if without else ".")))
        w.section("compare", "Runs side by side", "".join(body))
        return

    def listed(names: list[str]) -> str:
        return ", ".join(names[:VIEWS_LISTED]) + (", …" if len(names) > VIEWS_LISTED else "")

    def evaluated(ri: int) -> str:
        names = views_of[ri]
        return f"{len(names)} {runs[ri].metrics.split} view{'' if len(names) == 1 else 's'}: {listed(names)}"

    if not plan:
        body.append(note("The runs with maps share no evaluated view ("
                         + "; ".join(f"{runs[ri].name}: {evaluated(ri)}" for ri in with_maps)
                         + "); side-by-side images left out."))
        w.section("compare", "Runs side by side", "".join(body))
        return
    if without:
        body.append(note(f"Left out, no maps: {', '.join(without)}."))
    drawn = {ri for _, held in plan for ri in held}
    why = []
    for ri in (ri for ri in with_maps if ri not in drawn):
        common = [n for n in views_of[ri] if any(n in views_of[rj] for rj in with_maps if rj != ri)]
        if common:  # only where the figures ran out: compare_plan draws every run it can
            more = (f"; `report --set max_views={COMPARED_VIEWS}` draws {COMPARED_VIEWS}"
                    if max_views < COMPARED_VIEWS else "")
            why.append(f"{runs[ri].name} (the views it shares with other runs, {listed(common)}, are past "
                       f"the {len(plan)} figure{'' if len(plan) == 1 else 's'} drawn{more})")
        else:
            why.append(f"{runs[ri].name} (its {evaluated(ri)}; no other run with maps evaluated any of them)")
    if why:
        body.append(note("Left out of the side-by-side figures: " + "; ".join(why) + "."))
    if any(len(held) < len(with_maps) for _, held in plan):
        body.append(para("The runs were evaluated on different views: each figure holds the runs that "
                         "evaluated its view, and its caption names the others.", "muted"))
    # a view of --split train is a training view: "test view" would say the run never saw it
    kind = "test view" if all(runs[ri].metrics.split == "test" for _, held in plan for ri in held) else "view"
    body.append(para(f"One {kind} across runs. Error and std share one colour scale across all rows.",
                     "legend"))
    for vi, (name, held) in enumerate(plan):
        views = []
        for ri in held:
            view = loaded[ri].get(name)
            if view is None:  # past the run's first max_views: views_section did not read it
                view = load_view(name, runs[ri].maps_dir, runs[ri].depth_to_source, among=views_of[ri])
            views.append((ri, view))
        rows = [(runs[ri].name, v) for ri, v in views if _has_rgb(v)]
        # side_by_side_figure drops a run without maps: the caption says so rather than lose it unsaid
        unread = [f"{runs[ri].name}: no maps could be read ({v.note})" for ri, v in views if not _has_rgb(v)]
        missing = [runs[ri].name for ri in with_maps if ri not in held]
        splits = sorted({runs[ri].metrics.split for ri in held})
        caption = f"{name} across runs"
        if len(splits) > 1:  # one run's test view is another's training view (--split train, another split)
            for s in splits:
                of = ", ".join(runs[ri].name for ri in held if runs[ri].metrics.split == s)
                caption += f"; a {s} view of {of}"
        if missing:
            caption += f"; not drawn: {', '.join(missing)} (not evaluated on this view)"
        if unread and len(rows) >= 2:
            caption += "; " + "; ".join(unread)
        html = w.add_figure(f"compare_view{vi}.png", F.side_by_side_figure(rows, name), caption,
                            f"{name} side by side")
        body.append(html or note(f"{name}: not enough maps to compare"
                                 + (f" ({'; '.join(unread)})." if unread else ".")))
    w.section("compare", "Runs side by side", "".join(body))


def sparsification_section(w: ReportWriter, runs: list[RunData]) -> list[tuple[str, list[Curve]]]:
    body = [para("Sparsification: remove the most uncertain pixels first and track the error of the rest "
                 "(red); the oracle removes the largest errors first (dashed). The shaded gap is the AUSE: "
                 "smaller is better, 0 is a perfect ranking.", "legend")]
    per_run = []
    for ri, run in enumerate(runs):
        if run.metrics is None:
            body.append(_missing_metrics_note(run, full=False))
            continue
        curves = curves_of(run.metrics)
        per_run.append((run.name, curves))
        if not curves:
            body.append(note(f"{run.name}: eval/metrics.json has no sparsification curves."))
            continue
        n_views = len({c.view for c in curves if c.view is not None})
        html = w.add_figure(f"sparsification_run{ri}.png",
                            F.sparsification_figure(curves, run.name if len(runs) > 1 else ""),
                            f"{run.name}: {n_views} per-view curves (thin) and their mean (thick)",
                            f"sparsification curves of {run.name}")
        body.append(html)
    if len(runs) > 1:
        body.append(w.add_figure("sparsification_compare.png", F.sparsification_compare_figure(per_run),
                                 "Mean RGB MAE sparsification curves of all runs", "sparsification comparison"))
    w.section("sparsification", "Sparsification curves", "".join(body))
    return per_run


def calibration_section(w: ReportWriter, runs: list[RunData]) -> None:
    body = []
    per_run: list[tuple[str, list[Calibration]]] = []
    for run in runs:
        if run.metrics is None:
            if run.problem(METRICS) is not None:  # evaluated, but its metrics.json could not be read: say why
                body.append(note(f"{run.name}: {run.problem(METRICS)}"))
            continue
        cals = calibrations_of(run.metrics)
        if not cals:
            body.append(note(f"{run.name}: eval/metrics.json has no calibration table."))
            continue
        per_run.append((run.name, cals))
    if not per_run and not body:
        body.append(note("No calibration table available " + (
            "(run `uncertsplat evaluate` first)." if not all(holds_no_model(r) for r in runs) else
            "(no run holds a model to evaluate: the Summary says how to write one).")))
    else:
        body.append(w.add_figure("calibration.png", F.calibration_figure(per_run),
                                 "Observed fraction of errors inside the predictive's central interval vs the "
                                 "interval's probability (a Gaussian's ±kσ; a Student-t predictive's interval of the "
                                 "same probability is ±wσ, w in the table). On the diagonal: calibrated; below: "
                                 "over-confident (σ too small); above: under-confident.", "reliability plot"))
        # One table per set of k values: rows = k, columns = nominal, then observed per run and modality.
        groups: dict[tuple, list[tuple[str, Calibration]]] = {}
        for label, cals in per_run:
            for c in cals:
                groups.setdefault(tuple(c.table.ks), []).append(
                    (f"{label + ' ' if len(runs) > 1 else ''}{'depth' if c.depth else 'RGB'} observed", c))
        for ks, cols in groups.items():
            first = cols[0][1].table
            # a Student-t's half-widths differ from the ks: one column per table that has its own
            widths = [(name.replace(" observed", " half-width w"), c) for name, c in cols
                      if c.table.half_widths is not None and c.table.half_widths != c.table.ks]
            rows = []
            for i, k in enumerate(ks):
                cells = [_num_cell(first.nominal[i], ".3f", "nominal")]
                cells += [_num_cell(c.table.half_widths[i], ".2f", "half-width") for _, c in widths]
                cells += [_num_cell(c.table.observed[i], ".3f", "observed") for _, c in cols]
                rows.append((f"{k:g}σ", cells))
            body.append(table(["k", "nominal"] + [name for name, _ in widths] + [name for name, _ in cols], rows))
    w.section("calibration", "Calibration", "".join(body))


def training_section(w: ReportWriter, runs: list[RunData]) -> None:
    body = []
    with_stats = []
    for r in runs:
        if r.stats:
            with_stats.append((r.name, r.stats))
        with_stats += [(f"{r.name} {member}", rows) for member, rows in r.member_stats]
    if with_stats:
        body.append(w.add_figure("timeline.png", F.timeline_figure(with_stats),
                                 "Training timeline from stats.jsonl (an ensemble's from each member's, "
                                 "members/*/stats.jsonl): loss terms (symlog scale), number of "
                                 "Gaussians (dashed: those carrying a posterior), held-out PSNR, seconds per step. "
                                 "A held-out PSNR that drops at a step and recovers within a few hundred is an "
                                 "opacity reset (densify.opacity_reset_interval, 3DGS's way to clear floaters: every "
                                 "opacity is lowered at once and relearned), not a failure.",
                                 "training timeline"))
    for run in runs:
        if not run.stats and not run.member_stats:
            body.append(note(f"{run.name}: no stats.jsonl (a pruned run has none; its source run has the timeline)."
                             if run.is_pruned else f"{run.name}: no stats.jsonl; training timeline left out."))
        s = run.train_summary
        if s is not None:
            data = s.model_dump(mode="json")
            # without a carrier the expected render is the model's plain render: naming the variational one misleads
            skip = {"test_render"} if not s.num_carriers else set()
            items = [(k, _short(v)) for k, v in data.items()
                     if v is not None and not isinstance(v, (dict, list)) and k not in skip]
            members = _ensemble_size(run)
            if members:
                items = [(k, f"{v} (the sum over {members} members)" if k == "num_gaussians" else v)
                         for k, v in items]
            body.append(f"<h4>{esc(run.name)}: train_summary.json</h4>" + kv(items))
            if is_masked(run) and not _trained_inside_masks(run) and s.test_psnr is not None:
                body.append(note(f"{run.name}: test_psnr is over whole images; evaluate's PSNR (Summary, Metrics) is "
                                 "inside the scene's validity masks, so the two differ for the same render."))
            if s.imported is not None:  # a model another tool trained (train --from-ply): not trained here
                im = s.imported
                body.append(note(f"{run.name}: the model of {im.path} ({im.gaussians:,} Gaussians, SH degree "
                                 f"{im.sh_degree}, read in {frame_phrase(im.model_dump())}), trained elsewhere and given the informed posterior here without a step of "
                                 "training (train --from-ply); its held-out metrics are honest only if its trainer "
                                 "held out the same views."))
            for warning in s.warnings:  # e.g. a model that cannot fit its own training views
                body.append(note(f"{run.name}: {warning}"))
            for band in s.sh_bands:  # which SH bands the scene kept, and why
                body.append(note(f"{run.name}: {band_reason(band)}"))
            stops = [g for g in s.growth if g.stopped]  # where densification stopped growing the model, and why
            if s.growth:
                skipping = sum(g.skip_next for g in s.growth)  # (densify.growth_skip_factor)
                body.append(note(f"{run.name}: {growth_reason(stops[0] if stops else s.growth[-1])} "
                                 f"({len(s.growth)} growth test(s) in all"
                                 + (f", {skipping} of them far above the threshold, each skipping the next one"
                                    if skipping else "") + ")"))
            stopped = any(w.startswith(TRANSIENTS_STOPPED) for w in s.warnings)
            if s.transients is not None and not stopped:  # which photos held transient objects, left out of training
                # (a test that switched itself off: its warning, above, says so)
                where = "the members' transients/ folders" if s.method == "ensemble" else "the run's transients/ folder"
                body.append(note(f"{run.name}: {transients_note(s.transients, where=where)}"))
            more = {k: v for k, v in data.items() if isinstance(v, (dict, list)) and v}
            for member in more.get("members", []):  # an ensemble's members: models without carriers, as above
                if not member.get("num_carriers"):
                    member.pop("test_render", None)
            nested = json.dumps(more, indent=2)
            if more:
                body.append(details("more", pre(nested)))
        else:
            body.append(_problem_note(run, SUMMARY))
        last = run.stats[-1] if run.stats else None
        if last and s is None:
            body.append(f"<h4>{esc(run.name)}: last logged step</h4>" + kv((k, _short(v)) for k, v in last.items()))
    w.section("training", "Training", "".join(body))


# -------------------------------------------------------------------------------------------- pruning
def _prune_facts(p: PruneReport, run_dir: Path | None = None) -> list[tuple[str, str]]:
    if p.score == p.score_requested:
        score = p.score
    elif p.score_requested == "auto":
        # prune measures the alternatives only with --auto or --keep-ratio (and says how it chose in a note)
        compared = any(n.startswith("score auto:") for n in p.notes)
        score = (f"{p.score} (chosen automatically by --score auto: the note below says how)" if compared
                 else f"{p.score} (the default --score auto takes for this run; no other score was measured)")
    else:
        score = f"{p.score} (requested: {p.score_requested})"
    if p.mode == "auto":  # no ratio was asked for: --auto chose it, 0.7 is not the user's
        ratio = ("keep ratio", (format_value(p.keep_ratio, ".3f") if p.keep_ratio is not None else "none") +
                 f", chosen automatically (prune --auto): the largest removal whose held-out PSNR of the expected "
                 f"render stays within {p.tolerance_db:g} dB of the unpruned model's")
    else:
        ratio = ("keep ratio requested", format_value(p.keep_ratio, ".3f") if p.keep_ratio is not None else "—")
    facts = [("score", score), ("mode", p.mode), ratio,
             ("keep ratio achieved", format_value(p.keep_ratio_achieved, ".3f")
              if p.keep_ratio_achieved is not None else "—"),
             ("threshold requested", _short(p.threshold)),
             ("threshold_effective (smallest removed score)", _short(p.threshold_effective))]
    if p.counts is not None:
        c = p.counts
        facts += [("Gaussians before → after", f"{c.before:,} → {c.after:,} ({c.removed:,} removed, "
                                               f"{100.0 * c.removed / max(c.before, 1):.1f} %)"),
                  ("posterior carriers before → after", f"{c.carriers_before:,} → {c.carriers_after:,}")]
    if p.delta_psnr_db is not None:
        facts.append(("held-out PSNR change (the mean of the K samples)",
                      f"{_psnr_change(p, 'after', p.delta_psnr_db.score)} by the score, "
                      f"{_psnr_change(p, 'random', p.delta_psnr_db.random)} by random removal"))
    facts += [("metric views", f"{len(p.metric_views)} {p.metric_split} views, K = {p.num_samples} samples"),
              ("seed", str(p.seed)),
              ("source run", str(p.source_folder(run_dir)) if run_dir is not None else p.source_run)]
    if p.dry_run:
        facts.append(("dry run", "yes: no model written"))
    return facts


def _psnr_change(p: PruneReport, row: str, delta: float) -> str:
    """A PSNR change as the table beside it shows it: the difference of the two PSNRs as rounded there (the stored
    -0.155 rounds to -0.16, beside 22.66 -> 22.51), with both; the stored change alone where a row has no PSNR."""
    before, after = p.metrics.before.psnr, getattr(p.metrics, row).psnr if getattr(p.metrics, row) else None
    if before is None or after is None:
        return f"{delta:+.3f} dB"
    b, a = float(format_value(before, ".2f")), float(format_value(after, ".2f"))
    return f"{a - b:+.2f} dB ({b:.2f} → {a:.2f})"


def _prune_table(p: PruneReport, ri: int, masked: bool = False) -> str:
    rows_in = [("before", p.metrics.before), ("after", p.metrics.after), ("random removal", p.metrics.random)]
    rows = [(label, [_cell(v) for v in prune_row(m).values()]) for label, m in rows_in if m is not None]
    labels = [_inside_masks(s.label) if masked and s.key in MASKED_KEYS else s.label for s in PRUNE_SPECS]
    return table(["model"] + labels, rows, table_id=f"prune-{ri}")


def _sweep_loss(sweep: PruneSweep, best) -> str:
    """The PSNR the sweep's chosen removal loses, as the sweep table beside it shows it: the difference of the two
    PSNRs as rounded there (the stored 0.0569 read "0.06 dB" beside 32.66 -> 32.61), with both; the stored loss where
    the table has no such row."""
    point = next((q for q in sweep.points if q.num_removed == best.num_removed and q.keep_ratio == best.keep_ratio),
                 None)
    before = getattr(sweep.unpruned, sweep.metric)
    after = getattr(point.score, sweep.metric) if point is not None else None
    if before is None or after is None or not (math.isfinite(before) and math.isfinite(after)):
        loss = best.psnr_loss_db
        return f"{loss:.2f} dB lost" if loss >= 0 else f"{-loss:.2f} dB gained"
    b, a = float(format_value(before, ".2f")), float(format_value(after, ".2f"))
    # (a removal that raised the PSNR read "-0.03 dB (20.54 → 20.57) lost")
    return f"{b - a:.2f} dB ({b:.2f} → {a:.2f}) lost" if b >= a else f"{a - b:.2f} dB ({b:.2f} → {a:.2f}) gained"


def _sweep_table(sweep: PruneSweep, ri: int, masked: bool = False) -> str:
    best = sweep.largest_removal_within_tolerance
    rows = []
    for pt in sweep.points:
        chosen = best is not None and pt.num_removed == best.num_removed and pt.keep_ratio == best.keep_ratio
        rows.append((format_value(pt.keep_ratio, ".3f"), [
            _num_cell(pt.keep_ratio_achieved, ".3f", "keep_ratio_achieved"),
            _num_cell(pt.num_removed, ",d", "num_removed"),
            _num_cell(getattr(pt.score, sweep.metric), ".2f", f"score.{sweep.metric}"),
            _num_cell(getattr(pt.random, sweep.metric), ".2f", f"random.{sweep.metric}"),
            Cell("largest within tolerance" if chosen else "", text_cell=True),
        ]))
    what = " of the expected render" if sweep.metric == "psnr_render" else ""
    what += ", inside the masks" if masked else ""
    header = ["keep ratio", "achieved", "removed", f"PSNR{what}, score '{sweep.score}' (dB)",
              f"PSNR{what}, random removal (dB)", ""]
    return table(header, rows, table_id=f"prune-sweep-{ri}")


def _evaluation_now(folder: Path, runs: list[RunData]) -> tuple[str, EvalReport | None, str | None]:
    """(name, evaluation, problem) of ``folder``'s eval/metrics.json as it is now: as loaded for the report when
    ``folder`` is one of ``runs`` (the Summary shows that one), else read here; evaluation None when the file is absent
    or invalid (problem: why, when invalid)."""
    target = folder.resolve()
    for r in runs:
        if r.path.resolve() == target:
            return r.name, r.metrics, r.problem(METRICS)
    try:
        return str(folder), EvalReport.read_optional(folder / METRICS), None
    except UserError as err:
        return str(folder), None, one_line(err)


def _views_text(n: int, split: str) -> str:
    return f"{n} {split} view{'' if n == 1 else 's'}"


def _prune_settings(p: PruneReport) -> str:
    """The settings prune measured its rows with, as ``_eval_settings`` says an evaluation's."""
    return f"K = {p.num_samples}, seed {p.seed}, {_views_text(len(p.metric_views), p.metric_split)} on {p.device}"


def _eval_settings(m: EvalReport) -> str:
    seed = "seed not recorded" if m.seed is None else f"seed {m.seed}"
    return (f"K = {m.num_samples}, {seed}, {_views_text(len(_evaluated_views(m)), m.split)}"
            + (f" on {m.device}" if m.device else ""))


def evaluation_differences(p: PruneReport, m: EvalReport, row: PruneMetrics | None = None) -> list[str]:
    """How the evaluation ``m`` differs from the settings prune measured with (``p``'s K, seed, split and views,
    device) and, with ``row`` (a row prune copied ``m``'s means into) and the settings alike, from that row's means:
    [] when it is the evaluation prune read (or one it would have read)."""
    out = []
    if m.num_samples != p.num_samples:
        out.append("K")
    if m.seed != p.seed:
        out.append("seed")
    if m.split != p.metric_split or set(_evaluated_views(m)) != set(p.metric_views):
        out.append("views")
    if m.device is not None and m.device != p.device:
        out.append("device")
    if row is not None and not out:
        # prune copied these means from the file exactly (stages.prune.Measure.unpruned): any change is another
        # evaluation (another model file, or another of evaluate's settings)
        out += [k for k in PRUNE_EVAL_KEYS if getattr(row, k) != getattr(m.mean, k)]
    return out


def prune_evaluation_note(text: str, run: RunData, p: PruneReport, runs: list[RunData]) -> str:
    """prune's note ``text`` as shown: its claim that a row's uncertainty metrics are an evaluate report's
    (``UNPRUNED_FROM_EVALUATE``: the source run's; ``PRUNED_FROM_EVALUATE``: the pruned run's own) is checked against
    that eval/metrics.json as it is now, and replaced by what holds when the file was written again since (another K,
    seed, views or numbers: the Summary then shows the new evaluation, the Pruning table the one prune read) or is
    gone. Other notes, and claims that still hold, are returned as they are."""
    if text.startswith(UNPRUNED_FROM_EVALUATE):
        row_name, folder, row = "before", p.source_folder(run.path), p.metrics.before
    elif text.startswith(PRUNED_FROM_EVALUATE):
        row_name, folder, row = "after", run.path, p.metrics.after
    else:
        return text
    name, m, problem = _evaluation_now(folder, runs)
    then = (f"the '{row_name}' row's uncertainty metrics were read from {folder / METRICS} when prune ran, an "
            f"evaluation with {_prune_settings(p)}")
    if m is None:
        return then + ("; that file is now unreadable (" + problem + ")" if problem else "; that file is gone") + \
            ": the row cannot be checked against it"
    diffs = evaluation_differences(p, m, row)
    if not diffs:  # (the file where it is now: a project moved or copied since names its own, not the old place)
        head = UNPRUNED_FROM_EVALUATE if row_name == "before" else PRUNED_FROM_EVALUATE
        old = f"{head} ("
        if text.startswith(old) and f"{METRICS}:" in text:
            return f"{old}{folder / METRICS}:" + text.split(f"{METRICS}:", 1)[1]
        return text
    shown = any(r.path.resolve() == folder.resolve() for r in runs)
    now = (f"; that file now holds another evaluation, with {_eval_settings(m)}" if any(
        d in ("K", "seed", "views", "device") for d in diffs) else
           f"; that file now holds another evaluation with the same settings and other means ({', '.join(diffs)}: "
           "another model file or other evaluate settings)")
    where = (f": the Summary and Metrics for {name} show the new one, this table's '{row_name}' row the one prune read"
             if shown else f": this table's '{row_name}' row is the one prune read")
    return then + now + where


def _source_settings_note(p: PruneReport, run: RunData, runs: list[RunData]) -> str | None:
    """When prune measured its 'before' row itself (no ``UNPRUNED_FROM_EVALUATE`` note) and the source run is in the
    report, evaluated with other settings: a sentence saying which settings the Summary's row and the table used."""
    if any(n.startswith(UNPRUNED_FROM_EVALUATE) for n in p.notes):
        return None
    source = p.source_folder(run.path).resolve()
    src = next((r for r in runs if r.path.resolve() == source and r.metrics is not None), None)
    if src is None or not evaluation_differences(p, src.metrics):
        return None
    return (f"the Summary's row for {src.name} (the source run) is evaluate's, with {_eval_settings(src.metrics)}; "
            f"this table's 'before' row was measured by prune, with {_prune_settings(p)}: they differ by their "
            "settings, not only by the model")


def prune_section(w: ReportWriter, runs: list[RunData]) -> None:
    pruned = [(ri, r) for ri, r in enumerate(runs) if r.is_pruned]
    if not pruned:
        return
    body = [para("Held-out metrics of the model before pruning, after removing the Gaussians the score ranks most "
                 "uncertain, and after removing as many random Gaussians (the baseline the score must beat).",
                 "legend")]
    for ri, run in pruned:
        body.append(f"<h3>{esc(run.name)}</h3>")
        p = run.prune
        if p is None:
            body.append(_problem_note(run, PRUNE))
            continue
        body.append(kv(_prune_facts(p, run.path)))
        masked = _prune_masked(run, p, runs)
        body.append(_prune_table(p, ri, masked))
        if p.metrics.random is not None and any(n.startswith(PRUNED_FROM_EVALUATE) for n in p.notes):
            body.append(para("The 'after' row's uncertainty metrics are evaluate's of the pruned run (its pixel noise, "
                             "tails and std factor fitted again); the 'random removal' row's keep the source run's "
                             "fits: their PSNRs compare as they are, their AUSE and NLL within those fits' "
                             "difference.", "muted"))
        if p.metrics.after is None:
            body.append(para("No mask was chosen (a sweep only): no 'after' or 'random removal' row.", "muted"))
        for n in p.notes:
            body.append(note(f"{run.name} (prune): {prune_evaluation_note(n, run, p, runs)}"))
        settings = _source_settings_note(p, run, runs)
        if settings:
            body.append(note(f"{run.name} (prune): {settings}"))
        if p.sweep is None:
            body.append(para("No keep-ratio sweep in prune.json (run `uncertsplat prune --sweep` to measure one).",
                             "muted"))
            continue
        sw = p.sweep
        best = sw.largest_removal_within_tolerance
        caption = (f"Held-out PSNR ({sw.split} views{', expected render' if sw.metric == 'psnr_render' else ''}"
                   f"{', inside the masks' if masked else ''}) "
                   f"against the fraction of Gaussians kept: the score "
                   f"'{sw.score}' (solid) against random removal of as many Gaussians (dashed); dotted: the unpruned "
                   f"model, shaded: within {sw.tolerance_db:g} dB of it.")
        if best is not None:
            caption += (f" Circled: the largest removal within tolerance (keep ratio {best.keep_ratio:g}, "
                        f"{best.num_removed:,} removed, {_sweep_loss(sw, best)}"
                        f"{' in the expected render' if sw.metric == 'psnr_render' else ''}).")
        html = w.add_figure(f"prune_sweep_run{ri}.png", F.prune_sweep_figure(sw, masked=masked), caption,
                            "pruning sweep")
        body.append(html or note(f"{run.name}: the sweep has no PSNR to plot."))
        body.append(_sweep_table(sw, ri, masked))
        measured = {q.keep_ratio for q in sw.points}
        missing = [r for r in sw.ratios if r not in measured]
        if missing:  # (a reader counted 3 rows against the 6 ratios of prune.json's sweep)
            body.append(para(f"Keep ratios {', '.join(f'{r:g}' for r in missing)} of the sweep were not measured: "
                             "`prune --auto` stops at the first ratio past the tolerance.", "muted"))
        if best is None:
            body.append(para(f"No removal stays within {sw.tolerance_db:g} dB of the unpruned PSNR.", "muted"))
    w.section("prune", "Pruning", "".join(body))


# ------------------------------------------------------------------------------------------ provenance
def _hashes(run: RunData) -> list[tuple[str, Any]]:
    out: list[tuple[str, Any]] = []
    if run.manifest is not None:
        out += [(f"input hash ({k})", v) for k, v in run.manifest.input_hashes.items()]
        out.append(("config hash (manifest)", run.manifest.config_hash))
    if run.metrics is not None and run.metrics.config_hash:
        out.append(("config hash (evaluate)", run.metrics.config_hash))
    if run.reconstruct is not None and run.reconstruct.inputs_fingerprint:
        out.append(("photos fingerprint", run.reconstruct.inputs_fingerprint))
    return out


def _reconstruct_html(run: RunData) -> str:
    r = run.reconstruct
    if r is None:
        if run.problem(RECONSTRUCT) is not None:
            return _problem_note(run, RECONSTRUCT)
        if run.scene_path is None:
            return _file_note(run, SCENE, "no scene.json (written by `uncertsplat train`): the scene folder and its "
                                          "reconstruction health report are not shown.")
        if not run.scene_path.is_dir():
            return note(f"{run.name}: the scene folder {run.scene_path} no longer exists.")
        return para(f"No {RECONSTRUCT} in {run.scene_path} (a synthetic scene with its own cameras, or a workspace "
                    "made by another tool).", "muted")
    n_found, n_reg = len(r.images_found), len(r.images_registered)
    items = [("success", r.success), ("registered", f"{n_reg}/{n_found} ({100 * r.registered_fraction:.0f} %)"),
             ("models found", r.models_found), ("3D points", r.num_points3d),
             ("mean reprojection error (px)", _short(r.mean_reprojection_error)),
             ("matcher", r.matcher or "—"), ("COLMAP", r.colmap_version or r.pycolmap_version or "—"),
             ("time", _fmt_seconds(r.total_seconds))]
    if r.mapping_attempts:
        verdict = {True: "two agreed", False: "they disagreed", None: "one run"}[r.mapping_agreed]
        kept = next((a for a in r.mapping_attempts if a.kept), None)
        focal = "" if kept is None or not kept.focal_lengths else \
            " at " + " / ".join(f"{f:.0f}" for f in kept.focal_lengths.values()) + " px"
        items.append(("mapping runs", f"{len(r.mapping_attempts)} ({verdict})" + (
            "" if kept is None else f"; kept seed {kept.seed}: {kept.num_observations:,} feature observations{focal}")))
    if r.images_unregistered:
        unreg = r.images_unregistered
        items.append(("unregistered images", ", ".join(unreg[:30]) + (" …" if len(unreg) > 30 else "")))
    gt = r.ground_truth or {}
    if {"centre_error_mean_pct", "rotation_error_mean_deg"} <= gt.keys():  # photos of a synthetic scene: its cameras
        items.append(("cameras against the scene's GT", (
            f"centres {gt['centre_error_mean_pct']:.3g} % of the rig's radius (mean), rotations "
            f"{gt['rotation_error_mean_deg']:.3g}° (mean)"
            + (f", focal lengths {gt['focal_error_mean_pct']:.3g} %" if "focal_error_mean_pct" in gt else ""))))
    own = run.scene_path is not None and run.reconstruct_path is not None and \
        run.reconstruct_path.parent.resolve() != run.scene_path.resolve()
    html = f"<h4>reconstruction health ({esc(run.reconstruct_path)})</h4>" + kv(items)
    if own:  # (the run trained with the scene's own cameras; this is the SfM check of its photos beside it)
        html += para(f"A reconstruction of this scene's photos beside the run ({esc(run.reconstruct_path.parent)}); "
                     "the run trained with the scene's own cameras.", "muted")
    if not r.success:
        html += note(f"The reconstruction reported a failure: {r.message}")
    for text in r.notes:  # e.g. mapping runs that disagreed, a capture split into several models
        html += note(text)
    return html + details(RECONSTRUCT, pre(r.to_json()))


def provenance_section(w: ReportWriter, runs: list[RunData]) -> None:
    body = []
    for run in runs:
        body.append(f"<h3>{esc(run.name)}</h3>")
        facts: list[tuple[str, Any]] = [("run folder", str(run.path.resolve()))]
        if run.scene_path is not None:
            facts.append(("scene", str(run.scene_path)))
        cfg = run.config
        if cfg is not None:
            facts += [("train method", method_label(cfg)), ("train variant", cfg.variant),
                      ("train iterations", cfg.iterations), ("train seed", cfg.seed)]
        m = run.metrics
        if m is not None:
            facts += [("evaluate split", m.split), ("evaluate samples K", m.num_samples)]
            facts += [(f"evaluate {k}", v) for k, v in (("seed", m.seed), ("device", m.device)) if v is not None]
        versions: dict[str, str] = {}
        for src in (run.manifest, run.metrics):
            if src is not None:
                versions.update(src.versions)
        if versions:
            facts.append(("versions", ", ".join(f"{k} {v}" for k, v in sorted(versions.items()))))
        facts += _hashes(run)
        body.append(kv((k, _short(v)) for k, v in facts))
        if cfg is not None:
            body.append(details("config.json (resolved training config)", pre(cfg.model_dump_json(indent=2))))
        else:
            body.append(_file_note(run, CONFIG, "no config.json."))
        body.append(_reconstruct_html(run))
        if run.manifest is not None:
            body.append(details("manifest.json", pre(run.manifest.to_json())))
        else:
            body.append(_problem_note(run, MANIFEST))
    w.section("provenance", "Provenance", "".join(body))


# ------------------------------------------------------------------------------------------------ page
def build_report(runs: list[RunData], out: Path, title: str, max_views: int,
                 write_bytes: Callable[[Path, bytes], Any]) -> tuple[str, list[str]]:
    """Render every section; returns (index.html text, relative figure paths written)."""
    w = ReportWriter(out=out, write_bytes=write_bytes)
    summary_section(w, runs)
    metrics_section(w, runs)
    loaded = views_section(w, runs, max_views)
    compare_section(w, runs, loaded, max_views)
    sparsification_section(w, runs)
    calibration_section(w, runs)
    training_section(w, runs)
    prune_section(w, runs)
    provenance_section(w, runs)
    subtitle = (f"{len(runs)} run(s): " + ", ".join(r.name for r in runs)
                + f" — generated {time.strftime('%Y-%m-%d %H:%M:%S')}")
    text = page(title, subtitle, [(a, lab) for a, lab, _ in w.sections], "".join(h for _, _, h in w.sections))
    return text, w.figures
