"""Matplotlib figures of the report (Agg backend, PNG bytes; no display needed).

Each function takes plain arrays / the extracted quantities and returns PNG bytes, or None when it has
nothing to draw. Colours: error and std of a view share one colour scale (both are RGB differences, so
the same colour means the same value); the rank-coloured pair compares orderings, free of scale.
"""

from __future__ import annotations

import functools
import io
import warnings
from collections.abc import Sequence

import matplotlib

matplotlib.use("Agg", force=False)  # no display; must run before pyplot is imported
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from uncertsplat.io.images import to_uint8  # noqa: E402
from uncertsplat.report.colormaps import colorize, rank_colorize  # noqa: E402
from uncertsplat.report.extract import Calibration, Curve  # noqa: E402
from uncertsplat.report.grid import Panel, grid_png, rank_bar, value_bar  # noqa: E402
from uncertsplat.report.loader import stats_series  # noqa: E402
from uncertsplat.report.views import ViewMaps  # noqa: E402
from uncertsplat.schemas.prune import PruneSweep  # noqa: E402

DPI = 100
PNG_COMPRESS = 2
"""zlib level of the figures' PNGs: on the demo report's per-view figures, level 2 encodes in 0.3 s less than the
default 6 per figure for files 19 % larger (measured 2026-11-27)."""
_STYLE = {
    "text.parse_math": False,  # run names and titles are the user's text: "$5 vs $10" is no formula (it raised)
    "font.size": 9,
    "axes.titlesize": 9,
    "axes.labelsize": 9,
    "legend.fontsize": 8,
    "axes.spines.top": False,
    "axes.spines.right": False,
    "axes.grid": True,
    "grid.alpha": 0.3,
    "figure.facecolor": "white",
}
RANK_CMAP = "turbo"  # the colour map of colormaps.rank_colorize (its default)
# 20 distinct colours, the strong ones first: an ensemble's 10 members beside other runs repeated the first 8 (a
# helper's audit: member_8 in member_0's colour); beyond 20 they repeat
RUN_COLORS = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b", "#e377c2", "#17becf",
              "#393b79", "#637939", "#8c6d31", "#843c39", "#7b4173", "#bcbd22", "#7f7f7f", "#aec7e8",
              "#ff9896", "#98df8a", "#c5b0d5", "#ffbb78")


def _no_missing_glyph_warnings(draw):
    """``draw`` without matplotlib's "Glyph ... missing from font(s)" warnings: a run named in a script its font lacks
    (名前) is drawn with boxes in the figure, which cannot be helped without a font; the page shows the name correctly,
    and the warning, with its source path, only alarmed the console."""
    @functools.wraps(draw)
    def quiet(*args, **kwargs):
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=r"Glyph \d+ .*missing from", category=UserWarning)
            return draw(*args, **kwargs)
    return quiet


LINEAR_LOSS_RANGE = 20.0
"""The training figure's loss panel is linear when its largest loss value is below this many times its smallest
positive one (else symlog)."""


def run_color(i: int) -> str:
    return RUN_COLORS[i % len(RUN_COLORS)]


def _png(fig) -> bytes:
    """PNG bytes of ``fig`` (closed afterwards)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI, metadata={"Software": None},
                pil_kwargs={"compress_level": PNG_COMPRESS})
    plt.close(fig)
    return buf.getvalue()


def _png_with_legend_below(fig, axes=(), ncol: int = 4, handles=None) -> bytes:
    """PNG bytes of ``fig`` with one legend below the axes, where it covers no data: of ``handles`` (artists with
    labels) or else of ``axes``' labelled lines (each label once)."""
    handles = list(handles or [])
    labels = [h.get_label() for h in handles]
    for ax in axes:
        for h, lab in zip(*ax.get_legend_handles_labels(), strict=True):
            if lab not in labels:
                handles.append(h)
                labels.append(lab)
    fig.tight_layout()
    if handles:
        # as many columns as fit the figure's width: four long run names side by side ran off both edges of a
        # 5.5-inch figure (a helper's two-run report could not tell whose AUSE was whose); one column that is still
        # too wide widens the figure
        ncol = min(ncol, len(labels))
        while True:
            legend = fig.legend(handles, labels, loc="lower center", ncol=ncol, frameon=False)
            # the legend's own layout gives its width; drawing the whole figure for it took most of a report's time
            width = legend.get_window_extent(fig.canvas.get_renderer()).width / fig.dpi + 0.2  # inches, with a margin
            if width <= fig.get_figwidth() or ncol == 1:
                break
            legend.remove()
            ncol -= 1
        if width > fig.get_figwidth():
            fig.set_figwidth(width)
        rows = -(-len(labels) // ncol)
        height = fig.get_figheight()
        bottom = min(0.6, (0.3 + 0.2 * rows) / height)  # inches of legend rows, as a fraction of the figure
        if rows * 0.2 + 0.3 > 0.6 * height:  # more rows than the figure's lower part holds: a taller figure
            fig.set_figheight((rows * 0.2 + 0.3) / 0.6)
            bottom = 0.6
        fig.tight_layout(rect=(0, bottom, 1, 1))
    return _png(fig)


# ---------------------------------------------------------------------------------------------- colour
def rank_image(x: np.ndarray) -> np.ndarray:
    """Rank-coloured [H,W,3] uint8 (``report.colormaps.rank_colorize``, colour map ``RANK_CMAP``)."""
    return np.asarray(rank_colorize(x, cmap=RANK_CMAP))


def _robust_max(*arrays: np.ndarray | None, q: float = 99.0) -> float:
    vals = [np.nan_to_num(a, nan=0.0).reshape(-1) for a in arrays if a is not None]
    if not vals:
        return 1.0
    v = float(np.percentile(np.concatenate(vals), q))
    return v if v > 0 else max(float(max(a.max() for a in vals)), 1e-6)


def _beyond(top: float, *arrays: np.ndarray | None) -> bool:
    """Whether any finite value of ``arrays`` lies above ``top`` (the colour bar then says its top is clipped)."""
    return any(a is not None and bool(np.any(a[np.isfinite(a)] > top)) for a in arrays)


RGB_UNIT = "colour, 0-1"
"""What the error and RGB std maps are measured in: differences of colour channels on the image's 0-1 scale."""


# -------------------------------------------------------------------------------------------- per view
def _mapped(x: np.ndarray, cmap: str, vmin: float, vmax: float) -> np.ndarray:
    return colorize(x, mode="fixed", vmin=vmin, vmax=vmax, cmap=cmap)


NO_SURFACE_RGB = (170, 170, 170)
"""The neutral grey of the depth panels' pixels without a surface (``ViewMaps.no_surface``): in neither colour map."""


def _no_surface(image: np.ndarray, empty: np.ndarray | None) -> np.ndarray:
    """``image`` [H,W,3] uint8 with the pixels of ``empty`` [H,W] (no surface) drawn ``NO_SURFACE_RGB``."""
    if empty is not None and empty.shape == image.shape[:2]:
        image[empty] = NO_SURFACE_RGB
    return image


def depth_unit(view: ViewMaps) -> str:
    """What the view's depth maps are drawn in: the scene's units when the factor is known, else the run's."""
    return "scene units" if view.depth_to_source is not None else "run's normalised units"


def view_panels(view: ViewMaps) -> list[Panel]:
    """The panels of ``view_figure``: GT, mean, error, RGB std (shared scale), depth mean, depth std, rank(std) vs
    rank(error), with colour bars; depths in the scene's units when ``view.depth_to_source`` is known."""
    std = view.rgb_std_gray
    panels: list[Panel] = []
    if view.gt is not None:
        panels.append(Panel("ground truth", to_uint8(view.gt)))
    if view.rgb_mean is not None:
        panels.append(Panel("mean render", to_uint8(view.rgb_mean)))
    vmax = _robust_max(view.error, std)
    bar = value_bar("inferno", 0.0, vmax, above=_beyond(vmax, view.error, std))
    if view.error is not None:
        panels.append(Panel(f"|error| ({RGB_UNIT})", _mapped(view.error, "inferno", 0.0, vmax), bar))
    if std is not None:
        panels.append(Panel(f"RGB std ({RGB_UNIT})", _mapped(std, "inferno", 0.0, vmax), bar))
    # a length is worth reading only in the scene's units: the maps hold the run's normalised ones
    factor = view.depth_to_source or 1.0
    unit = depth_unit(view)
    # depth 0 where no surface is met is not a distance: those pixels are drawn NO_SURFACE_RGB and kept out of the
    # colour scales (they pinned the depth mean's bar to 0 and drew a transparent scene's background as the nearest)
    empty = view.no_surface  # [H,W] bool
    if view.depth_mean is not None:
        d = view.depth_mean * factor
        finite = d[np.isfinite(d) & ~empty]  # [P] the surface's depths
        lo, hi = (float(np.percentile(finite, 1)), float(np.percentile(finite, 99))) if finite.size else (0.0, 1.0)
        hi = max(hi, lo + 1e-9)
        below = bool(finite.size) and float(finite.min()) < lo
        panels.append(Panel(f"depth mean ({unit})", _no_surface(_mapped(d, "viridis", lo, hi), empty),
                            value_bar("viridis", lo, hi, below=below, above=_beyond(hi, finite))))
    if view.depth_std is not None:
        d_std = view.depth_std * factor
        surface = d_std if empty is None or empty.shape != d_std.shape else d_std[~empty]  # [P]
        top = _robust_max(surface) if surface.size else 1.0
        panels.append(Panel(f"depth std ({unit})", _no_surface(_mapped(d_std, "magma", 0.0, top), empty),
                            value_bar("magma", 0.0, top, above=_beyond(top, surface))))
    if std is not None and view.error is not None:
        panels.append(Panel("rank of RGB std", rank_image(std), rank_bar(RANK_CMAP)))
        panels.append(Panel("rank of |error|", rank_image(view.error), rank_bar(RANK_CMAP)))
    return panels


def view_figure(view: ViewMaps, title: str = "") -> bytes | None:
    """The panels of ``view_panels`` as one grid (``report.grid``), four a row; None when there is none."""
    panels = view_panels(view)
    if not panels:
        return None
    cols = 4 if len(panels) > 4 else len(panels)
    return grid_png([panels[i:i + cols] for i in range(0, len(panels), cols)], title=title,
                    compress_level=PNG_COMPRESS)


def side_by_side_figure(views: Sequence[tuple[str, ViewMaps]], view_name: str) -> bytes | None:
    """One view across runs: rows = runs; mean, error, RGB std on one shared scale, rank(std), rank(error)."""
    rows = [(label, v) for label, v in views if v.rgb_mean is not None or v.rgb_std is not None]
    if len(rows) < 2:
        return None
    maps = [v.error for _, v in rows] + [v.rgb_std_gray for _, v in rows]
    vmax = _robust_max(*maps)
    bar = value_bar("inferno", 0.0, vmax, above=_beyond(vmax, *maps))
    titles = ["mean render", f"|error| ({RGB_UNIT})", f"RGB std ({RGB_UNIT})", "rank of RGB std", "rank of |error|"]
    grid = []
    for r, (_, v) in enumerate(rows):
        std = v.rgb_std_gray
        both = std is not None and v.error is not None
        t = titles if r == 0 else [""] * len(titles)  # the columns are named once, above the first row
        grid.append([
            Panel(t[0], None if v.rgb_mean is None else to_uint8(v.rgb_mean)),
            Panel(t[1], None if v.error is None else _mapped(v.error, "inferno", 0.0, vmax)),
            Panel(t[2], None if std is None else _mapped(std, "inferno", 0.0, vmax), None if std is None else bar),
            Panel(t[3], rank_image(std) if both else None),
            Panel(t[4], rank_image(v.error) if both else None, rank_bar(RANK_CMAP) if both else None),
        ])
    return grid_png(grid, title=view_name, row_labels=[label for label, _ in rows], compress_level=PNG_COMPRESS)


# ---------------------------------------------------------------------------------------------- curves
@_no_missing_glyph_warnings
def sparsification_figure(curves: list[Curve], run_label: str = "") -> bytes | None:
    """One panel per (modality, metric): per-view uncertainty curves (thin), mean curve and oracle."""
    if not curves:
        return None
    groups: dict[tuple[bool, str], list[Curve]] = {}
    for c in curves:
        groups.setdefault((c.depth, c.metric), []).append(c)
    order = sorted(groups, key=lambda k: (k[0], {"mae": 0, "rmse": 1, "mse": 2}.get(k[1], 3)))
    order = [k for k in order if k[1] != "mse"] or order  # MSE repeats RMSE's ordering: leave it out
    n = len(order)
    with plt.rc_context(_STYLE):
        fig, axes = plt.subplots(1, n, figsize=(4.2 * n, 3.4), squeeze=False)
        for ax, key in zip(axes[0], order, strict=False):
            cs = groups[key]
            views = [c for c in cs if c.view is not None]
            means = [c for c in cs if c.view is None]
            for i, c in enumerate(views):
                ax.plot(c.fractions, c.uncertainty, color="#1f77b4", alpha=0.25, lw=0.8,
                        label="per view (uncertainty)" if i == 0 else None)
                ax.plot(c.fractions, c.oracle, color="0.4", alpha=0.25, lw=0.8, ls="--",
                        label="per view (oracle)" if i == 0 else None)
            ause = ""
            for c in means[:1]:
                ause = f" (AUSE {c.ause:.4f})" if c.ause is not None else ""
                ax.plot(c.fractions, c.uncertainty, color="#d62728", lw=2.0, label="uncertainty, mean")
                ax.plot(c.fractions, c.oracle, color="black", lw=1.6, ls="--", label="oracle, mean")
                ax.fill_between(c.fractions, c.oracle, c.uncertainty, color="#d62728", alpha=0.12)
            ax.set_xlabel("fraction of pixels removed (most uncertain first)")
            ax.set_ylabel(f"normalised {key[1].upper()}")
            ax.set_title(f"{'depth' if key[0] else 'RGB'} {key[1].upper()}{ause}")
            ax.set_xlim(0, 1)
            ax.set_ylim(bottom=0)
        if run_label:
            fig.suptitle(run_label, fontsize=10)
        # one legend below the panels (inside, it sat on the mean curve); the AUSE moved to each panel's title
        return _png_with_legend_below(fig, axes[0])


@_no_missing_glyph_warnings
def sparsification_compare_figure(per_run: list[tuple[str, list[Curve]]]) -> bytes | None:
    """Mean RGB sparsification curves (MAE) of several runs on one plot, each with its oracle."""
    items = []
    for label, curves in per_run:
        mean = [c for c in curves if c.view is None and not c.depth and c.metric == "mae"]
        if mean:
            items.append((label, mean[0]))
    if len(items) < 2:
        return None
    with plt.rc_context(_STYLE):
        fig, ax = plt.subplots(figsize=(5.5, 3.6))
        for i, (label, c) in enumerate(items):
            col = run_color(i)
            ause = f" (AUSE {c.ause:.4f})" if c.ause is not None else ""
            ax.plot(c.fractions, c.uncertainty, color=col, lw=1.8, label=f"{label}{ause}")
            ax.plot(c.fractions, c.oracle, color=col, lw=1.0, ls="--")
        ax.set_xlabel("fraction of pixels removed (most uncertain first)")
        ax.set_ylabel("normalised MAE")
        ax.set_title("mean sparsification curves (dashed: each run's oracle)")
        ax.set_xlim(0, 1)
        ax.set_ylim(bottom=0)
        return _png_with_legend_below(fig, [ax])


@_no_missing_glyph_warnings
def calibration_figure(per_run: list[tuple[str, list[Calibration]]]) -> bytes | None:
    """Reliability plot: observed vs nominal coverage of the predictive's central intervals (a Gaussian's k-sigma ones,
    a Student-t's of the same probabilities), one line per run."""
    items = [(label, c) for label, cals in per_run for c in cals]
    if not items:
        return None
    with plt.rc_context(_STYLE):
        fig, ax = plt.subplots(figsize=(4.4, 4.2) if len(items) <= 2 else (4.4, 4.2 + 0.2 * len(items)))
        ax.plot([0, 1], [0, 1], color="0.5", ls="--", lw=1, label="perfectly calibrated")
        for i, (label, c) in enumerate(items):
            run_i = [lab for lab, _ in per_run].index(label)
            col = run_color(run_i)
            name = f"{label} ({'depth' if c.depth else 'RGB'})" if len(items) > 1 else ("depth" if c.depth else "RGB")
            ax.plot(c.nominal, c.observed, marker="o" if not c.depth else "s", color=col,
                    ls="-" if not c.depth else ":", label=name)
            if c.k is not None and i == 0:
                for k, x, y in _spaced(c.k, c.nominal, c.observed):
                    ax.annotate(f"{k:g}σ", (x, y), textcoords="offset points", xytext=(4, -10), fontsize=7,
                                color="0.3")
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1)
        ax.set_aspect("equal")
        ax.set_xlabel("nominal coverage (a Gaussian's ±kσ)")
        ax.set_ylabel("observed fraction inside the interval")
        ax.set_title("reliability (below the diagonal: over-confident)")
        if len(items) <= 2:  # two lines leave the upper left free; more crowd it, so they go below the axes
            ax.legend(loc="upper left", frameon=False)
            fig.tight_layout()
            return _png(fig)
        return _png_with_legend_below(fig, [ax], ncol=2)


LABEL_SPACING = 0.05
"""Least distance (in coverage, both axes) between two kσ labels of the reliability plot: near 1 the points crowd
(2.5σ at 0.988, 3σ at 0.997) and their labels overlapped."""


def _spaced(ks, xs, ys) -> list[tuple[float, float, float]]:
    """The (k, x, y) to label, from the largest k down, each at least ``LABEL_SPACING`` from the last one labelled."""
    out: list[tuple[float, float, float]] = []
    for k, x, y in sorted(zip(ks, xs, ys, strict=False), key=lambda t: -t[0]):
        if not (np.isfinite(x) and np.isfinite(y)):
            continue
        if not out or np.hypot(x - out[-1][1], y - out[-1][2]) >= LABEL_SPACING:
            out.append((k, x, y))
    return out


# -------------------------------------------------------------------------------------------- training
# The keys of stats.jsonl (``train/trainer.py``, ``train/losses.py``): the loss terms loss, l1, photo and
# kl_* (``kl_total`` among them); "ssim" there is the similarity, not a loss term; eval_psnr on held-out views.
_LOSS_KEYS = ("loss", "l1", "photo")
_PSNR_KEY = "eval_psnr"


@_no_missing_glyph_warnings
def timeline_figure(per_run: list[tuple[str, list[dict]]]) -> bytes | None:
    """Training timeline: loss terms, Gaussian (and carrier) count, held-out PSNR, seconds per step."""
    per_run = [(label, s) for label, s in per_run if s]
    if not per_run:
        return None
    multi = len(per_run) > 1
    keys = set().union(*[set().union(*[r.keys() for r in s]) for _, s in per_run])
    loss_keys = [k for k in _LOSS_KEYS if k in keys]
    loss_keys += sorted(k for k in keys if k.startswith("kl_") and k not in loss_keys)
    # symlog's linear zone sits below the smallest typical term, so small KL terms stay readable
    drawn = loss_keys if not multi else loss_keys[:1]  # (several runs: their totals only)
    positive = np.concatenate([stats_series(s, k)[1] for _, s in per_run for k in drawn] or [np.zeros(0)])
    positive = positive[positive > 0]
    linthresh = float(np.clip(np.percentile(positive, 5), 1e-8, 1e-2)) if positive.size else 1e-3
    # losses within a decade or so (a short run's 0.13-0.21) get a linear axis: symlog put its ticks at powers of ten
    # only, and such a panel had no number on its axis (a helper's audit)
    symlog = not (positive.size and float(positive.max()) < LINEAR_LOSS_RANGE * float(positive.min()))
    panels = []
    if loss_keys:
        panels.append("loss")
    if "num_gaussians" in keys:
        panels.append("gaussians")
    if _PSNR_KEY in keys:
        panels.append("psnr")
    if "sec_per_step" in keys:
        panels.append("speed")
    if not panels:
        return None
    with plt.rc_context(_STYLE):
        fig, axes = plt.subplots(1, len(panels), figsize=(3.6 * len(panels), 3.2), squeeze=False)
        for ax, panel in zip(axes[0], panels, strict=False):
            for ri, (label, stats) in enumerate(per_run):
                col = run_color(ri)
                pre = f"{label}: " if multi else ""
                if panel == "loss":
                    styles = ("-", "--", ":", "-.")
                    for j, k in enumerate(loss_keys if not multi else loss_keys[:1]):
                        x, y = stats_series(stats, k)
                        if x.size:
                            # the total wide and pale beneath the terms: where one term is all of it (the KL
                            # weighs nothing) the two lines coincide, and a thin one would hide the other
                            wide = k == "loss" and not multi
                            ax.plot(x, y, lw=3.0 if wide else 1.2, alpha=0.45 if wide else 1.0,
                                    ls=styles[j % 4] if multi else "-", color=col if multi else None,
                                    label=f"{pre}{k}")
                    ax.set_title("loss" if multi else "loss terms")
                    if symlog:
                        ax.set_yscale("symlog", linthresh=linthresh)
                elif panel == "gaussians":
                    x, y = stats_series(stats, "num_gaussians")
                    ax.plot(x, y, color=col, lw=1.4, label=f"{pre}Gaussians")
                    x, y = stats_series(stats, "num_carriers")
                    if x.size:
                        ax.plot(x, y, color=col, lw=1.2, ls="--", label=f"{pre}with posterior")
                    ax.set_title("number of Gaussians")
                elif panel == "psnr":
                    x, y = stats_series(stats, _PSNR_KEY)
                    if x.size:
                        ax.plot(x, y, color=col, marker="o", ms=3, lw=1.2, label=f"{pre}held-out PSNR")
                    ax.set_title("PSNR (dB)")
                elif panel == "speed":
                    x, y = stats_series(stats, "sec_per_step")
                    ax.plot(x, y, color=col, lw=1.0, label=f"{pre}s/step")
                    ax.set_title("seconds per step")
            if panel == "speed":
                # after every run is drawn: set inside the loop, it froze the top at the first run's range
                ax.set_ylim(bottom=0)
            ax.set_xlabel("step")
            if panel == "loss":
                ax.set_ylabel("loss (symlog scale)" if symlog else "loss")
            if not multi and ax.get_legend_handles_labels()[0]:
                ax.legend(frameon=False, loc="best")
        if not multi:
            fig.tight_layout()
            return _png(fig)
        # several runs: one legend below the panels (inside, the Gaussian counts' legend covered the lines); the
        # runs' colours, and the line styles named once
        from matplotlib.lines import Line2D

        handles = [Line2D([], [], color=run_color(ri), lw=1.6, label=label) for ri, (label, _) in enumerate(per_run)]
        if "gaussians" in panels and "num_carriers" in keys:
            handles.append(Line2D([], [], color="0.3", lw=1.2, ls="--", label="dashed: Gaussians with a posterior"))
        return _png_with_legend_below(fig, ncol=3, handles=handles)


# ------------------------------------------------------------------------------------------------ prune
@_no_missing_glyph_warnings
def prune_sweep_figure(sweep: PruneSweep, label: str = "", masked: bool = False) -> bytes | None:
    """Held-out PSNR vs keep ratio achieved: the score's removal and random removal of as many Gaussians.

    The unpruned model's PSNR is a horizontal reference line (with the tolerance band below it) and the
    sweep's ``largest_removal_within_tolerance`` is circled. None when no point has a PSNR.
    """
    pts = sorted(sweep.points, key=lambda p: -p.keep_ratio_achieved)
    metric = sweep.metric  # the PSNR the tolerance was checked on

    def value(m):
        return getattr(m, metric)

    score = [(p.keep_ratio_achieved, value(p.score)) for p in pts if value(p.score) is not None]
    rand = [(p.keep_ratio_achieved, value(p.random)) for p in pts if value(p.random) is not None]
    if not score and not rand:
        return None
    best = sweep.largest_removal_within_tolerance
    chosen = None
    if best is not None:
        chosen = next((p for p in pts if p.num_removed == best.num_removed and p.keep_ratio == best.keep_ratio), None)
    with plt.rc_context(_STYLE):
        fig, ax = plt.subplots(figsize=(6.4, 3.8))
        ref = value(sweep.unpruned)
        if ref is not None:
            ax.axhline(ref, color="0.35", lw=1.0, ls=":", label=f"unpruned ({ref:.2f} dB)")
            ax.axhspan(ref - sweep.tolerance_db, ref, color="0.5", alpha=0.08, lw=0,
                       label=f"within {sweep.tolerance_db:g} dB")
        if score:
            x, y = zip(*score, strict=True)
            ax.plot(x, y, color=run_color(0), marker="o", ms=4, lw=1.8, label=f"score '{sweep.score}'")
        if rand:
            x, y = zip(*rand, strict=True)
            ax.plot(x, y, color=run_color(1), marker="s", ms=4, lw=1.4, ls="--", label="random removal")
        if chosen is not None and value(chosen.score) is not None:
            ax.plot([chosen.keep_ratio_achieved], [value(chosen.score)], marker="o", ms=13, mfc="none", mec="black",
                    mew=1.5, ls="none", label=f"largest removal within tolerance (keep {chosen.keep_ratio_achieved:.3f})")
        ax.set_xlabel("keep ratio achieved (fraction of Gaussians kept)")
        what = "expected render" if metric == "psnr_render" else "mean of the samples"
        ax.set_ylabel(f"held-out PSNR (dB, {sweep.split} views, {what}{', inside the masks' if masked else ''})")
        ax.set_title("pruning sweep: PSNR vs keep ratio")
        ax.invert_xaxis()  # left to right: stronger pruning
        ax.legend(frameon=False, loc="lower left")
        if label:
            fig.suptitle(label, fontsize=10)
        fig.tight_layout()
        return _png(fig)
