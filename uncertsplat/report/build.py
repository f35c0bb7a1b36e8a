"""Assemble the HTML report from loaded runs: sections, figures, tables.

Every section is optional: when its inputs are missing it is replaced by a short note saying what is
missing and which command produces it. Metric values are shown exactly as stored in the run's files
(each numeric cell also carries the raw value in ``data-value``), never recomputed.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from uncertsplat.gaussians.variational import describe_posterior
from uncertsplat.report import figures as F
from uncertsplat.report.extract import (
    METRIC_SPECS,
    SUMMARY_KEYS,
    Calibration,
    Curve,
    find_calibration,
    find_curves,
    format_value,
    mean_metrics,
    metric_row,
    per_view_metrics,
)
from uncertsplat.report.html import Cell, details, esc, figure, kv, note, page, para, pre, table
from uncertsplat.report.loader import RunData, as_float, first_key
from uncertsplat.report.views import ViewMaps, list_map_views, load_view

_SPEC_BY_KEY = {s.key: s for s in METRIC_SPECS}


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


# --------------------------------------------------------------------------------------------- facts
def _train_seconds(run: RunData) -> tuple[Any, str]:
    """(value, source) of the training wall time."""
    v = first_key(run.train_summary, ("train_seconds", "seconds", "total_seconds", "wall_seconds",
                                      "elapsed_seconds", "time_seconds", "elapsed"))
    if as_float(v) is not None:
        return v, "train_summary.json"
    if run.manifest and run.manifest.get("stage") == "train" and as_float(run.manifest.get("seconds")) is not None:
        return run.manifest["seconds"], "manifest.json"
    for row in reversed(run.stats):  # the trainer logs its cumulative training time as "elapsed"
        if as_float(row.get("elapsed")) is not None:
            return row["elapsed"], "stats.jsonl"
    return None, ""


def _prune_count(prune: dict | None, which: str) -> Any:
    """Gaussian count before/after in prune.json (flat keys or a nested counts object)."""
    if not isinstance(prune, dict):
        return None
    flat = first_key(prune, (f"num_{which}", f"count_{which}", f"gaussians_{which}", f"num_gaussians_{which}"))
    if flat is not None:
        return flat
    for key in ("counts", "num_gaussians", "gaussians"):
        sub = prune.get(key)
        if isinstance(sub, dict) and sub.get(which) is not None:
            return sub[which]
    sub = prune.get(which)
    if isinstance(sub, dict):
        return first_key(sub, ("num_gaussians", "count", "gaussians"))
    return None


def _num_gaussians(run: RunData) -> tuple[Any, str]:
    if run.prune is not None:
        v = _prune_count(run.prune, "after")
        if v is not None:
            return v, "prune.json"
    v = first_key(run.train_summary, ("num_gaussians", "final_num_gaussians", "gaussians"))
    if v is not None:
        return v, "train_summary.json"
    for row in reversed(run.stats):
        if row.get("num_gaussians") is not None:
            return row["num_gaussians"], "stats.jsonl"
    return None, ""


def _fmt_seconds(v: Any) -> str:
    f = as_float(v)
    if f is None:
        return "n/a"
    if f >= 120:
        return f"{f / 60:.1f} min"
    return f"{f:.1f} s"


def _metric_cell(mv, key: str | None = None) -> Cell:
    return Cell(format_value(mv.value, mv.spec.fmt), key=key or mv.source_key, value=mv.value)


def _columns(rows: list[dict]) -> tuple[list[str], list[str]]:
    """(metric keys with at least one number, keys that are null everywhere), in first-seen order."""
    keys: list[str] = []
    for r in rows:
        keys += [k for k in r if k not in keys]
    filled = [k for k in keys if any(k in r and as_float(r[k].value) is not None for r in rows)]
    return filled, [k for k in keys if k not in filled]


def _missing_metrics_note(run: RunData) -> str:
    return note(f"{run.name}: no eval/metrics.json — run `uncertsplat evaluate {run.path}` to measure the "
                "uncertainty; metric sections are left out for this run.")


# ----------------------------------------------------------------------------------------- sections
def summary_section(w: ReportWriter, runs: list[RunData]) -> None:
    rows_by_run = [metric_row(mean_metrics(r.metrics)) for r in runs]
    keys = [k for k in SUMMARY_KEYS if any(k in row for row in rows_by_run)]
    header = ["run"] + [_SPEC_BY_KEY[k].label for k in keys] + [
        "Gaussians", "training time", "s / view (uncertainty)", "samples K"]
    rows = []
    for run, mrow in zip(runs, rows_by_run, strict=True):
        cells: list[Cell | str] = []
        for k in keys:
            cells.append(_metric_cell(mrow[k]) if k in mrow else Cell("n/a"))
        ng, _ = _num_gaussians(run)
        cells.append(Cell(format_value(ng, ".4g"), key="num_gaussians", value=ng) if ng is not None else Cell("n/a"))
        ts, _ = _train_seconds(run)
        cells.append(Cell(_fmt_seconds(ts), key="train_seconds", value=ts) if ts is not None else Cell("n/a"))
        spv = first_key(run.metrics, ("seconds_per_view",))
        cells.append(Cell(format_value(spv, ".3f"), key="seconds_per_view", value=spv) if spv is not None
                     else Cell("n/a"))
        ns = first_key(run.metrics, ("num_samples",))
        cells.append(Cell(str(ns), key="num_samples", value=ns) if ns is not None else Cell("n/a"))
        rows.append((run.name, cells))
    body = [table(header, rows, table_id="summary")]
    body.append(para("Metrics are the means over the evaluated views, exactly as in each run's eval/metrics.json. "
                     "Lower is better for AUSE, NLL and calibration error; higher for PSNR and SSIM.", "legend"))
    for run in runs:
        if run.metrics is None:
            body.append(_missing_metrics_note(run))
        for n in run.notes:
            body.append(note(f"{run.name}: {n}"))
        sn = mean_metrics(run.metrics).get("spearman_note")
        if isinstance(sn, str) and sn:
            body.append(note(f"{run.name}: Spearman: {sn}"))
        for n in (run.metrics or {}).get("notes", []) or []:
            body.append(note(f"{run.name} (evaluate): {n}"))
        post = (run.train_summary or {}).get("posterior")
        if isinstance(post, dict) and post.get("carriers") and post.get("moved_fraction") is not None:
            try:
                body.append(note(f"{run.name} (train): {describe_posterior(post)}"))
            except (KeyError, TypeError):  # a summary written by another version: leave it to the provenance
                pass
    w.section("summary", "Summary", "".join(body))


def metrics_section(w: ReportWriter, runs: list[RunData]) -> None:
    body = []
    for ri, run in enumerate(runs):
        if run.metrics is None:
            continue
        pv = per_view_metrics(run.metrics)
        mean = metric_row(mean_metrics(run.metrics))
        rows_in = [(name, metric_row(d)) for name, d in pv.items()] + [("mean", mean)]
        keys, empty = _columns([r for _, r in rows_in])
        labels = {k: r[k].spec.label for _, r in rows_in for k in r}
        rows = [(name, [_metric_cell(r[k]) if k in r else Cell("n/a") for k in keys]) for name, r in rows_in]
        title = f"<h3>{esc(run.name)}</h3>" if len(runs) > 1 else ""
        facts = [("split", run.metrics.get("split", "n/a")), ("views", len(pv)),
                 ("samples K", run.metrics.get("num_samples", "n/a"))]
        ds = run.metrics.get("depth_scale")
        if isinstance(ds, dict) and ds.get("scale") is not None:
            facts.append(("depth scale", f"{ds.get('scale')} ({ds.get('method', '?')})"))
        if run.metrics.get("std_floor") is not None:
            facts.append(("std floor (NLL)", run.metrics["std_floor"]))
        if isinstance(run.metrics.get("std_scale"), (int, float)):
            n_cal = len(run.metrics.get("calibration_views") or [])
            facts.append(("std scale (calibrated NLL)",
                          f"x{run.metrics['std_scale']:.3g}, fitted on {n_cal} training views"))
        lp = run.metrics.get("lpips")
        if isinstance(lp, dict) and not lp.get("available", True):
            facts.append(("LPIPS", lp.get("reason") or "unavailable"))
        if empty:
            facts.append(("not available", ", ".join(labels[k] for k in empty)))
        body.append(f'{title}{kv(facts)}<div data-run="{ri}">'
                    f'{table(["view"] + [labels[k] for k in keys], rows, table_id=f"metrics-{ri}")}</div>')
    if not body:
        body.append(note("No run has eval/metrics.json: run `uncertsplat evaluate RUN` first."))
    w.section("metrics", "Metrics per view", "".join(body))


def _view_names(run: RunData) -> list[str]:
    names = list(per_view_metrics(run.metrics))
    if not names and isinstance((run.metrics or {}).get("image_names"), list):
        names = [str(n) for n in run.metrics["image_names"]]
    return names or list_map_views(run.maps_dir)


def _background(run: RunData):
    bg = ((run.config or {}).get("scene") or {}).get("background")
    if isinstance(bg, (list, tuple)) and len(bg) == 3 and all(as_float(c) is not None for c in bg):
        return tuple(float(c) for c in bg)
    return (0.0, 0.0, 0.0)


def views_section(w: ReportWriter, runs: list[RunData], max_views: int) -> dict[int, dict[str, ViewMaps]]:
    """Per-view figures; returns the loaded maps (run index -> name -> maps) for the comparison section."""
    loaded: dict[int, dict[str, ViewMaps]] = {}
    body = [para("Each row: the ground-truth test image and the prediction (the mean of the sampled renders); the "
                 "absolute error and the predicted RGB std on one shared colour scale (same colour = same value); "
                 "depth mean and std; and the rank-coloured std next to the rank-coloured error (each pixel "
                 "coloured by its rank quantile in its own map, so good uncertainty makes the two look alike "
                 "whatever the scales).", "legend")]
    for ri, run in enumerate(runs):
        names = _view_names(run)
        title = f"<h3>{esc(run.name)}</h3>" if len(runs) > 1 else ""
        if not run.maps_dir.is_dir():
            body.append(title + note(f"{run.name}: no eval/maps/ folder (evaluate with save_maps on to get the "
                                     "uncertainty maps); per-view figures left out."))
            continue
        if not names:
            body.append(title + note(f"{run.name}: eval/maps/ holds no maps; per-view figures left out."))
            continue
        body.append(title)
        loaded[ri] = {}
        shown = names[:max_views]
        if len(names) > len(shown):
            body.append(para(f"Showing {len(shown)} of {len(names)} views (ReportConfig.max_views).", "muted"))
        for vi, name in enumerate(shown):
            view = load_view(name, run.maps_dir, run.scene_path, _background(run))
            loaded[ri][name] = view
            png = F.view_figure(view, title=name)
            html = w.add_figure(f"run{ri}_view{vi}.png", png, f"{run.name} — {name}",
                                f"uncertainty maps of {name}")
            body.append(f"<h4>{esc(name)}</h4>" + (html or note(f"{name}: no maps could be read.")))
            if view.note and html:
                body.append(note(f"{name}: {view.note}"))
    w.section("views", "Test views", "".join(body))
    return loaded


def compare_section(w: ReportWriter, runs: list[RunData], loaded: dict[int, dict[str, ViewMaps]],
                    max_views: int) -> None:
    if len(runs) < 2:
        return
    common = None
    for ri in range(len(runs)):
        names = list(loaded.get(ri, {}))
        common = names if common is None else [n for n in common if n in names]
    body = []
    if not common:
        body.append(note("The runs share no evaluated view with maps; side-by-side images left out."))
    else:
        body.append(para("One test view across runs. Error and std share one colour scale across all rows.",
                         "legend"))
        for vi, name in enumerate(common[: min(3, max_views)]):
            views = [(runs[ri].name, loaded[ri][name]) for ri in sorted(loaded)]
            html = w.add_figure(f"compare_view{vi}.png", F.side_by_side_figure(views, name),
                                f"{name} across runs", f"{name} side by side")
            body.append(html or note(f"{name}: not enough maps to compare."))
    w.section("compare", "Runs side by side", "".join(body))


def sparsification_section(w: ReportWriter, runs: list[RunData]) -> list[tuple[str, list[Curve]]]:
    body = [para("Sparsification: remove the most uncertain pixels first and track the error of the rest "
                 "(red); the oracle removes the largest errors first (dashed). The shaded gap is the AUSE: "
                 "smaller is better, 0 is a perfect ranking.", "legend")]
    per_run = []
    for ri, run in enumerate(runs):
        if run.metrics is None:
            body.append(_missing_metrics_note(run))
            continue
        curves = find_curves(run.metrics, list(per_view_metrics(run.metrics)))
        per_run.append((run.name, curves))
        if not curves:
            body.append(note(f"{run.name}: metrics.json has no sparsification curves."))
            continue
        n_views = len({c.view for c in curves if c.view is not None})
        html = w.add_figure(f"sparsification_run{ri}.png", F.sparsification_figure(curves, run.name if len(runs) > 1 else ""),
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
            continue
        cals = find_calibration(run.metrics)
        if not cals:
            body.append(note(f"{run.name}: metrics.json has no calibration table."))
            continue
        per_run.append((run.name, cals))
    if not per_run:
        body.append(note("No calibration table available (run `uncertsplat evaluate` first)."))
    else:
        body.append(w.add_figure("calibration.png", F.calibration_figure(per_run),
                                 "Observed fraction of errors inside ±kσ vs the fraction a Gaussian with that σ "
                                 "would give. On the diagonal: calibrated; below: over-confident (σ too small); "
                                 "above: under-confident.", "reliability plot"))
        # One table per set of k values: rows = k, columns = nominal, then observed per run and modality.
        groups: dict[tuple, list[tuple[str, Calibration]]] = {}
        for label, cals in per_run:
            for c in cals:
                key = tuple(c.k.tolist()) if c.k is not None else tuple(c.nominal.tolist())
                groups.setdefault(key, []).append((f"{label + ' ' if len(runs) > 1 else ''}"
                                                   f"{'depth' if c.depth else 'RGB'} observed", c))
        for _, cols in groups.items():
            first = cols[0][1]
            rows = []
            for i, n in enumerate(first.nominal):
                k = first.k[i] if first.k is not None else None
                cells = [Cell(format_value(float(n), ".3f"), key="nominal", value=float(n))]
                cells += [Cell(format_value(float(c.observed[i]), ".3f"), key="observed", value=float(c.observed[i]))
                          for _, c in cols]
                rows.append((f"{k:g}σ" if k is not None else f"#{i + 1}", cells))
            body.append(table(["k", "nominal"] + [name for name, _ in cols], rows))
    w.section("calibration", "Calibration", "".join(body))


def training_section(w: ReportWriter, runs: list[RunData]) -> None:
    body = []
    with_stats = [(r.name, r.stats) for r in runs if r.stats]
    if with_stats:
        body.append(w.add_figure("timeline.png", F.timeline_figure(with_stats),
                                 "Training timeline from stats.jsonl: loss terms (symlog scale), number of "
                                 "Gaussians (dashed: those carrying a posterior), held-out PSNR, seconds per step.",
                                 "training timeline"))
    for run in runs:
        if not run.stats:
            body.append(note(f"{run.name}: no stats.jsonl (a pruned run has none; its source run has the timeline)."
                             if run.is_pruned else f"{run.name}: no stats.jsonl; training timeline left out."))
        if run.train_summary:
            items = [(k, _short(v)) for k, v in run.train_summary.items() if not isinstance(v, (dict, list))]
            title = f"<h4>{esc(run.name)}: train_summary.json</h4>"
            body.append(title + kv(items))
            nested = {k: v for k, v in run.train_summary.items() if isinstance(v, (dict, list))}
            if nested:
                body.append(details("more", pre(json.dumps(nested, indent=2, default=str))))
        last = run.stats[-1] if run.stats else None
        if last and not run.train_summary:
            body.append(f"<h4>{esc(run.name)}: last logged step</h4>" + kv((k, _short(v)) for k, v in last.items()))
    w.section("training", "Training", "".join(body))


def _short(v: Any) -> str:
    if isinstance(v, float):
        return format(v, ".6g")
    return str(v)


def prune_section(w: ReportWriter, runs: list[RunData]) -> None:
    pruned = [(ri, r) for ri, r in enumerate(runs) if r.prune is not None]
    if not pruned:
        return
    body = []
    for ri, run in pruned:
        p = run.prune or {}
        body.append(f"<h3>{esc(run.name)}</h3>")
        before, after = _prune_count(p, "before"), _prune_count(p, "after")
        facts = [("Gaussians before", before), ("Gaussians after", after)]
        if as_float(before) and as_float(after) is not None:
            facts.append(("removed", f"{100.0 * (1 - float(after) / float(before)):.1f} %"))
        for k in ("score", "threshold", "keep_ratio", "mode", "source", "source_run", "dry_run", "seed"):
            if k in p and not isinstance(p[k], (dict, list)):
                facts.append((k, _short(p[k])))
        body.append(kv((k, "n/a" if v is None else _short(v)) for k, v in facts))
        mb, ma = first_key(p, ("metrics_before", "before_metrics")), first_key(p, ("metrics_after", "after_metrics"))
        if mb is None and isinstance(p.get("before"), dict) and isinstance(p.get("before", {}).get("metrics"), dict):
            mb = p["before"]["metrics"]
        if ma is None and isinstance(p.get("after"), dict) and isinstance(p.get("after", {}).get("metrics"), dict):
            ma = p["after"]["metrics"]
        rows = []
        rnd = first_key(p, ("metrics_random", "random_metrics", "random"))
        for label, m in (("before", mb), ("after", ma), ("random removal", rnd)):
            if isinstance(m, dict):
                rows.append((label, metric_row(m)))
        if rows:
            keys = []
            for _, r in rows:
                keys += [k for k in r if k not in keys]
            labels = {k: r[k].spec.label for _, r in rows for k in r}
            body.append(table(["model"] + [labels[k] for k in keys],
                              [(lab, [_metric_cell(r[k]) if k in r else Cell("n/a") for k in keys]) for lab, r in rows],
                              table_id=f"prune-{ri}"))
        sweep = first_key(p, ("sweep", "sweep_results", "curve"))
        if isinstance(sweep, dict):
            sweep = first_key(sweep, ("rows", "points", "results"))
        if isinstance(sweep, list) and sweep and all(isinstance(s, dict) for s in sweep):
            body.append(w.add_figure(f"prune_sweep_run{ri}.png", F.prune_sweep_figure(sweep),
                                     "Pruning sweep on held-out views: the uncertainty score (solid) against random "
                                     "removal of the same number of Gaussians (dashed).", "pruning sweep"))
            cols = []
            for s in sweep:
                cols += [k for k, v in s.items() if k not in cols and not isinstance(v, (dict, list))]
            srows = [(_short(s.get(cols[0], i)), [Cell(_short(s[k])) if k in s else Cell("n/a") for k in cols[1:]])
                     for i, s in enumerate(sweep)]
            body.append(details("sweep table", table(cols, srows)))
        else:
            body.append(note(f"{run.name}: no sweep in prune.json (run `uncertsplat prune --sweep`)."))
    w.section("prune", "Pruning", "".join(body))


def _workspace_hash(run: RunData) -> list[tuple[str, Any]]:
    out = []
    if run.manifest:
        for k, v in (run.manifest.get("input_hashes") or {}).items():
            out.append((f"input hash ({k})", v))
        if run.manifest.get("config_hash"):
            out.append(("config hash (manifest)", run.manifest["config_hash"]))
    if run.metrics and run.metrics.get("config_hash"):
        out.append(("config hash (evaluate)", run.metrics["config_hash"]))
    if run.reconstruct and run.reconstruct.get("inputs_fingerprint"):
        out.append(("photos fingerprint", run.reconstruct["inputs_fingerprint"]))
    for src in (run.train_summary, run.config):
        for k in ("data_hash", "scene_hash", "dataset_hash"):
            if isinstance(src, dict) and src.get(k):
                out.append((k, src[k]))
    return out


def provenance_section(w: ReportWriter, runs: list[RunData]) -> None:
    body = []
    for run in runs:
        body.append(f"<h3>{esc(run.name)}</h3>")
        facts: list[tuple[str, Any]] = [("run folder", str(run.path.resolve()))]
        if run.scene_path is not None:
            facts.append(("scene", str(run.scene_path)))
        cfg = run.config or {}
        for k in ("method", "variant", "iterations", "seed"):
            if k in cfg:
                facts.append((f"train {k}", cfg[k]))
        if run.metrics:
            for k in ("seed", "num_samples", "split", "device"):
                if run.metrics.get(k) is not None:
                    facts.append((f"evaluate {k}", run.metrics[k]))
        versions: dict[str, Any] = {}
        for src in (run.manifest, run.train_summary, run.metrics):
            if isinstance(src, dict) and isinstance(src.get("versions"), dict):
                versions.update(src["versions"])
        if versions:
            facts.append(("versions", ", ".join(f"{k} {v}" for k, v in sorted(versions.items()))))
        facts += _workspace_hash(run)
        body.append(kv((k, _short(v)) for k, v in facts))
        if run.config is not None:
            body.append(details("config.json (resolved training config)", pre(json.dumps(run.config, indent=2))))
        else:
            body.append(note(f"{run.name}: no config.json."))
        if run.reconstruct is not None:
            r = run.reconstruct
            found, reg = r.get("images_found") or [], r.get("images_registered") or []
            rf = as_float(r.get("registered_fraction"))
            items = [("success", r.get("success")), ("registered", f"{len(reg)}/{len(found)}"
                     + (f" ({100 * rf:.0f} %)" if rf is not None else "")),
                     ("models found", r.get("models_found")), ("3D points", r.get("num_points3d")),
                     ("mean reprojection error (px)", _short(r.get("mean_reprojection_error"))),
                     ("matcher", r.get("matcher")), ("COLMAP", r.get("colmap_version") or r.get("pycolmap_version")),
                     ("time", _fmt_seconds(r.get("total_seconds")))]
            unreg = r.get("images_unregistered") or []
            if unreg:
                items.append(("unregistered images", ", ".join(map(str, unreg[:30])) + (" …" if len(unreg) > 30 else "")))
            body.append(f"<h4>reconstruction health ({esc(run.reconstruct_path)})</h4>"
                        + kv((k, "n/a" if v is None else v) for k, v in items))
            if r.get("success") is False:
                body.append(note(f"The reconstruction reported a failure: {r.get('message', '')}"))
            body.append(details("reconstruct_report.json", pre(json.dumps(r, indent=2))))
        elif run.scene_path is not None:
            body.append(para(f"No reconstruct_report.json in {run.scene_path} (a workspace made by another tool "
                             "or a synthetic scene with its own cameras).", "muted"))
        else:
            body.append(para("Scene folder not found from config.json / the manifest; GT images and the "
                             "reconstruction health report are not shown.", "muted"))
        if run.manifest is not None:
            body.append(details("manifest.json", pre(json.dumps(run.manifest, indent=2))))
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
