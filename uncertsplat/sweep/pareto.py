"""Pareto front of sweep points (accuracy vs time): a pure function, the sweep's summary, and its figure."""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from uncertsplat.schemas.runs import SweepGroup, SweepRecord, SweepSummary

TABLE_KEYS = ("psnr", "ssim", "ause_mae", "ause_rmse", "nll", "calibration_error", "nll_calibrated",
              "calibration_error_calibrated", "std_scale", "depth_ause_mae", "depth_ause_rmse", "depth_abs_rel",
              "spearman", "time", "train_seconds", "calibration_seconds", "eval_seconds_per_view", "peak_memory_mb",
              "num_gaussians", "num_carriers")
"""What the sweep's table averages over seeds (``SweepGroup.mean``)."""


def _value(point: Any, key: str) -> float | None:
    v = point.get(key) if isinstance(point, Mapping) else getattr(point, key, None)
    if v is None:
        return None
    try:
        v = float(v)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def pareto_front(points: Sequence[Any], x: str = "time", y: str = "ause", minimize_both: bool = True,
                 maximize_x: bool | None = None) -> list[Any]:
    """The points no other point dominates, sorted from the best ``x`` (then ``y``).

    ``x`` is minimised (a cost), or maximised where ``maximize_x`` (default: when ``x`` is one of
    ``HIGHER_IS_BETTER``: a sweep's ``pareto_x = "psnr"`` was minimised, and every point came out on the front);
    ``y`` is minimised when ``minimize_both`` (AUSE, NLL) and maximised otherwise (PSNR). A point dominates another
    when it is at least as good in both and strictly better in one, so exact duplicates all stay on the front.
    Points whose ``x`` or ``y`` is missing or not finite are ignored.

    Args:
        points: mappings (``point[x]``) or objects (``point.x``).
        x, y: the keys to compare.
        minimize_both: minimise ``y`` too (else maximise it).
        maximize_x: maximise ``x`` (None: by the key, ``HIGHER_IS_BETTER``).
    """
    sign = 1.0 if minimize_both else -1.0
    x_sign = -1.0 if (x in HIGHER_IS_BETTER if maximize_x is None else maximize_x) else 1.0
    valid = [(p, _value(p, x), _value(p, y)) for p in points]
    valid = [(p, x_sign * a, sign * b) for p, a, b in valid if a is not None and b is not None]
    # sweep by increasing cost; a point is on the front iff its y beats every cheaper-or-equal point's
    order = sorted(range(len(valid)), key=lambda i: (valid[i][1], valid[i][2]))
    front, best = [], math.inf
    i = 0
    while i < len(order):
        # points with the same x: only those with the smallest y in the group can be on the front
        j = i
        while j < len(order) and valid[order[j]][1] == valid[order[i]][1]:
            j += 1
        group = [order[k] for k in range(i, j)]
        gmin = min(valid[k][2] for k in group)
        if gmin < best:
            front += [valid[k][0] for k in group if valid[k][2] == gmin]
            best = gmin
        i = j
    return front


def _mean_std(values: list[float]) -> tuple[float | None, float | None]:
    if not values:
        return None, None
    m = sum(values) / len(values)
    if len(values) < 2:
        return m, None
    return m, math.sqrt(sum((v - m) ** 2 for v in values) / (len(values) - 1))


def group_records(records: Sequence[SweepRecord]) -> list[SweepGroup]:
    """One ``SweepGroup`` per point and scene: mean and sample std over the seeds whose record is ok.

    Rows keep the order in which their first record appears.
    """
    groups: dict[str, list[SweepRecord]] = {}
    for r in records:
        groups.setdefault(r.group, []).append(r)
    out = []
    for gid, recs in groups.items():
        ok = [r for r in recs if r.status == "ok"]
        mean, spread = {}, {}
        for key in TABLE_KEYS:
            vals = [v for v in (_value(r, key) for r in ok) if v is not None]
            mean[key], spread[key] = _mean_std(vals)
        first = recs[0]
        out.append(SweepGroup(id=gid, scene=first.scene, method=first.method, knobs=first.knobs,
                              is_default=first.is_default, seeds=[r.seed for r in ok],
                              num_failed=len(recs) - len(ok), mean=mean, spread=spread))
    return out


def resolution(knobs: Mapping[str, Any], spec=None, scene: str | None = None) -> str | None:
    """The resolution a point is trained and scored at, as a front's label: ``downscale D``, the downscale its
    training config resolves to on ``scene`` (``spec.point_configs``: the knob, else the spec's ``train`` or
    preset), or the knob alone without ``spec``; None when neither says. Its photos are scored at that size, so
    PSNR, AUSE and NLL compare only with points of the same resolution."""
    d = knobs.get("downscale")
    if spec is not None:
        from uncertsplat.sweep.spec import SweepPoint, point_configs

        try:
            d = point_configs(spec, SweepPoint(**knobs), scene)[0].scene.downscale
        except (ValueError, TypeError, KeyError):  # a record of another spec: its knob, as recorded
            pass
    return None if d is None else f"downscale {float(d):g}"


def _resolutions(table: Sequence[SweepGroup], spec=None) -> dict[str, str | None]:
    """Each row's ``resolution`` label, None for every row of a scene whose rows share one (nothing to split)."""
    labels = {g.id: resolution(g.knobs, spec, g.scene) for g in table}
    sizes: dict = {}
    for g in table:
        sizes.setdefault(g.scene, set()).add(labels[g.id])
    return {g.id: labels[g.id] if len(sizes[g.scene]) > 1 else None for g in table}


def front_key(y: str, x: str, scene: str | None, resolution: str | None = None) -> str:
    """The ``SweepSummary.pareto`` key of the front of ``y`` against ``x`` (per scene when scenes are named, per
    resolution when the points are scored at several: ``resolution``)."""
    key = f"{y}_vs_{x}" if scene is None else f"{scene}: {y}_vs_{x}"
    return key if resolution is None else f"{key} @ {resolution}"


def summarize(spec, records: Sequence[SweepRecord]) -> SweepSummary:
    """The ``sweep.json`` summary of a ``spec.SweepSpec``'s records: the latest record per point, the table of
    means over seeds, the default and the Pareto fronts of the table's rows (``spec.pareto_y`` against
    ``spec.pareto_x``, per scene; PSNR is maximised)."""
    latest: dict[str, SweepRecord] = {}
    for r in records:
        latest[r.id] = r
    recs = list(latest.values())
    ok = [r for r in recs if r.status == "ok"]
    table = group_records(recs)
    fronts = {}
    sizes_of = _resolutions(table, spec)
    for scene in dict.fromkeys(g.scene for g in table) or [None]:
        groups = [g for g in table if g.scene == scene]
        # points scored at another resolution are scored against other photos: a front of their own each
        for size in dict.fromkeys(sizes_of[g.id] for g in groups):
            rows = [{"id": g.id, **g.mean} for g in groups if g.seeds and sizes_of[g.id] == size]
            for y in spec.pareto_y:
                fronts[front_key(y, spec.pareto_x, scene, size)] = [
                    p["id"] for p in pareto_front(rows, x=spec.pareto_x, y=y,
                                                  minimize_both=y not in HIGHER_IS_BETTER)]
    default = next((r for r in recs if r.is_default), None)
    return SweepSummary(name=spec.name, spec=json.loads(spec.model_dump_json()), num_points=len(recs),
                        num_failed=len(recs) - len(ok), default=default.group if default else None,
                        pareto_x=spec.pareto_x, pareto=fronts, records=recs, table=table)


def y_scale(values: Sequence[float]) -> tuple[str, dict]:
    """The y-axis scale that keeps a cluster of close values readable beside a few far ones.

    ``("log", {})`` for positive values spanning more than a factor 3 (AUSE with a K = 1 point),
    ``("symlog", {"linthresh": t})`` when values reach zero or below and the far ones are more than 20x the
    typical magnitude away (an NLL of -1.6 beside one of 750): linear within +-t, t the median magnitude
    (at least 1e-3), logarithmic beyond; else ``("linear", {})``.
    """
    v = sorted(float(a) for a in values)
    if not v:
        return "linear", {}
    if v[0] > 0:
        return ("log", {}) if v[-1] > 3.0 * v[0] else ("linear", {})
    mags = sorted(abs(a) for a in v)
    typical = max(mags[len(mags) // 2], 1e-3)
    if v[-1] - v[0] > 20.0 * typical:
        return "symlog", {"linthresh": typical}
    return "linear", {}


def table_points(summary: SweepSummary, spec=None) -> list[dict]:
    """The rows of ``summary.table`` that have a finished seed, as the plain points ``plot_pareto`` draws; ``panel``
    names the front a row is compared in (its scene and, where a scene's points are scored at several resolutions,
    its ``resolution`` with ``spec``), what ``plot_pareto(..., group="panel")`` draws a row of panels for."""
    sizes_of = _resolutions(summary.table, spec)
    points = []
    for g in summary.table:
        if not g.seeds:
            continue
        panel = ", ".join(p for p in (f"scene {g.scene}" if g.scene is not None else None, sizes_of[g.id]) if p)
        points.append({"id": g.id, "method": g.method, "status": "ok", "is_default": g.is_default, "scene": g.scene,
                       "panel": panel or None, **g.mean})
    return points


def split_by_resolution(summary: SweepSummary, spec=None) -> bool:
    """Whether some scene's points are scored at several resolutions (their fronts are drawn apart)."""
    return any(v is not None for v in _resolutions(summary.table, spec).values())


HIGHER_IS_BETTER = frozenset({"psnr", "ssim", "spearman"})
"""Record keys whose larger values are better (the Pareto front maximises them)."""

AXIS_LABELS = {
    "time": "training + fitting + evaluation time (s)", "train_seconds": "training time (s)",
    "eval_seconds_per_view": "evaluation time per view (s)", "peak_memory_mb": "peak memory (MB)",
    "num_gaussians": "Gaussians", "num_carriers": "Gaussians with a posterior",
    "ause_mae": "AUSE (MAE), lower is better", "ause_rmse": "AUSE (RMSE), lower is better",
    "nll": "NLL (nats), lower is better", "nll_calibrated": "NLL, std rescaled (nats), lower is better",
    "psnr": "PSNR (dB), higher is better", "ssim": "SSIM, higher is better",
    "calibration_error": "calibration error, lower is better", "depth_ause_mae": "depth AUSE (MAE), lower is better",
    "spearman": "Spearman (std vs error), higher is better"}
"""What ``plot_pareto`` calls a record key on its axes (the key itself when it has no entry)."""


def axis_name(key: str) -> str:
    """A short name of ``key`` for a title: its axis label without the direction ("NLL (nats)")."""
    return AXIS_LABELS.get(key, key).split(", ")[0]


def plot_pareto(records: Sequence[Any], path: Path, x: str = "time", ys: Sequence[str] = ("ause_mae", "nll"),
                title: str = "speed-accuracy trade", group: str | None = None) -> Path:
    """One panel per ``ys`` key: every point, its Pareto front (a step line) and the default (a star).

    Points are coloured by method; the points on the front and the default are labelled by their id (the
    sweep's ``index.html`` lists every point with its values). The y axis follows ``y_scale``. With ``group``
    (e.g. ``"scene"``, or ``"panel"``: ``table_points``' scene and resolution, headed by the value alone), one row
    of panels per distinct value of that key, each with its own fronts. Written
    with matplotlib's Agg backend.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = [r for r in records if r.get("status") == "ok"]
    methods = sorted({r.get("method", "?") for r in ok})
    cmap = plt.get_cmap("tab10")
    colour = {m: cmap(i % 10) for i, m in enumerate(methods)}
    groups = list(dict.fromkeys(r.get(group) for r in ok)) if group else [None]
    groups = groups or [None]
    with plt.rc_context({"text.parse_math": False}):  # (the spec's name and the points' ids are the user's text)
        fig, axes = plt.subplots(len(groups), len(ys), figsize=(6.0 * len(ys), 4.6 * len(groups)), squeeze=False)
        for row, g in enumerate(groups):
            rows = [r for r in ok if group is None or r.get(group) == g]
            _panels(axes[row], rows, x, ys, methods, colour,
                    None if group is None else (str(g) if group == "panel" else f"{group} {g}"))
        fig.suptitle(title)
        fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    tmp.replace(path)
    return path


def _panels(axes, ok: Sequence[Any], x: str, ys: Sequence[str], methods: list[str], colour: dict,
            heading: str | None) -> None:
    """One row of ``plot_pareto``'s panels (one per ``ys`` key) for the points ``ok``."""
    from matplotlib.ticker import FuncFormatter, LogLocator

    labels = AXIS_LABELS
    for ax, y in zip(axes, ys, strict=True):
        pts = [r for r in ok if _value(r, x) is not None and _value(r, y) is not None]
        for m in methods:
            sel = [r for r in pts if r.get("method") == m]
            if sel:
                ax.scatter([_value(r, x) for r in sel], [_value(r, y) for r in sel], color=colour[m], label=m,
                           s=28, zorder=3)
        front = pareto_front(pts, x=x, y=y, minimize_both=y not in HIGHER_IS_BETTER)
        on_front = {id(r) for r in front}
        for r in pts:
            if id(r) in on_front or r.get("is_default"):
                ax.annotate(r.get("id"), (_value(r, x), _value(r, y)), fontsize=6.5, alpha=0.85, xytext=(4, 4),
                            textcoords="offset points")
        if front:
            ax.step([_value(r, x) for r in front], [_value(r, y) for r in front], where="post", color="black",
                    lw=1.2, alpha=0.8, label="Pareto front", zorder=2)
        for r in pts:
            if r.get("is_default"):
                ax.scatter([_value(r, x)], [_value(r, y)], marker="*", s=260, facecolor="none", edgecolor="red",
                           linewidth=1.5, label="default", zorder=4)
        xs = [_value(r, x) for r in pts]
        if xs and min(xs) > 0 and max(xs) >= 10 * min(xs):  # a log axis where the values span a decade or more
            ax.set_xscale("log")
            # plain numbers at 1, 2, 5 x 10^k (40 s, not 4e+01; a range of 0.7-3 s read '7e-01 8e-01 9e-01 1' and
            # left the points past 1 without a label)
            plain = FuncFormatter(lambda v, _: f"{v:g}")
            ax.xaxis.set_major_formatter(plain)
            ax.xaxis.set_minor_locator(LogLocator(subs=(2.0, 5.0)))
            ax.xaxis.set_minor_formatter(plain)
        scale, kw = y_scale([_value(r, y) for r in pts])  # e.g. the NLL of K = 1 (std 0) dwarfs the rest
        ax.set_yscale(scale, **kw)
        ax.set_xlabel(labels.get(x, x))
        ax.set_ylabel(labels.get(y, y))
        if heading:
            ax.set_title(heading, fontsize=10)
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:  # a panel with no point to draw (no metric there) has nothing to name
            ax.legend(fontsize=7)
