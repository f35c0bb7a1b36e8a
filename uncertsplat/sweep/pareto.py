"""Pareto front of sweep points (accuracy vs time): a pure function, the sweep's summary, and its figure."""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from uncertsplat.schemas.runs import SweepRecord, SweepSummary


def _value(point: Any, key: str) -> float | None:
    v = point.get(key) if isinstance(point, Mapping) else getattr(point, key, None)
    if v is None:
        return None
    try:
        v = float(v)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def pareto_front(points: Sequence[Any], x: str = "time", y: str = "ause", minimize_both: bool = True) -> list[Any]:
    """The points no other point dominates, sorted by ``x`` (then ``y``).

    ``x`` is always minimised (a cost); ``y`` is minimised when ``minimize_both`` (AUSE, NLL) and
    maximised otherwise (PSNR). A point dominates another when it is at least as good in both and
    strictly better in one, so exact duplicates all stay on the front. Points whose ``x`` or ``y`` is
    missing or not finite are ignored.

    Args:
        points: mappings (``point[x]``) or objects (``point.x``).
        x, y: the keys to compare.
        minimize_both: minimise ``y`` too (else maximise it).
    """
    sign = 1.0 if minimize_both else -1.0
    valid = [(p, _value(p, x), _value(p, y)) for p in points]
    valid = [(p, a, sign * b) for p, a, b in valid if a is not None and b is not None]
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


def summarize(spec, records: Sequence[SweepRecord]) -> SweepSummary:
    """The ``sweep.json`` summary of a ``spec.SweepSpec``'s records: the latest record per point, the default
    and the Pareto fronts (``spec.pareto_y`` against ``spec.pareto_x``; PSNR is maximised)."""
    latest: dict[str, SweepRecord] = {}
    for r in records:
        latest[r.id] = r
    recs = list(latest.values())
    ok = [r for r in recs if r.status == "ok"]
    fronts = {}
    for y in spec.pareto_y:
        fronts[f"{y}_vs_{spec.pareto_x}"] = [r.id for r in pareto_front(ok, x=spec.pareto_x, y=y,
                                                                          minimize_both=(y != "psnr"))]
    default = next((r for r in recs if r.is_default), None)
    return SweepSummary(name=spec.name, spec=json.loads(spec.model_dump_json()), num_points=len(recs),
                        num_failed=len(recs) - len(ok), default=default.id if default else None,
                        pareto_x=spec.pareto_x, pareto=fronts, records=recs)


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


def plot_pareto(records: Sequence[Any], path: Path, x: str = "time", ys: Sequence[str] = ("ause_mae", "nll"),
                title: str = "speed-accuracy trade") -> Path:
    """One panel per ``ys`` key: every point, its Pareto front (a step line) and the default (a star).

    Points are coloured by method; the points on the front and the default are labelled by their id (the
    sweep's ``index.html`` lists every point with its values). The y axis follows ``y_scale``. Written
    with matplotlib's Agg backend.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = [r for r in records if r.get("status") == "ok"]
    methods = sorted({r.get("method", "?") for r in ok})
    cmap = plt.get_cmap("tab10")
    colour = {m: cmap(i % 10) for i, m in enumerate(methods)}
    fig, axes = plt.subplots(1, len(ys), figsize=(6.0 * len(ys), 4.6), squeeze=False)
    labels = {"time": "training + evaluation time (s)", "train_seconds": "training time (s)",
              "eval_seconds_per_view": "evaluation time per view (s)", "ause_mae": "AUSE (MAE), lower is better",
              "ause_rmse": "AUSE (RMSE), lower is better", "nll": "NLL, lower is better", "psnr": "PSNR (dB)",
              "calibration_error": "calibration error", "depth_ause_mae": "depth AUSE (MAE)"}
    for ax, y in zip(axes[0], ys, strict=True):
        pts = [r for r in ok if _value(r, x) is not None and _value(r, y) is not None]
        for m in methods:
            sel = [r for r in pts if r.get("method") == m]
            if sel:
                ax.scatter([_value(r, x) for r in sel], [_value(r, y) for r in sel], color=colour[m], label=m,
                           s=28, zorder=3)
        front = pareto_front(pts, x=x, y=y, minimize_both=(y != "psnr"))
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
        if pts and min(_value(r, x) for r in pts) > 0:
            ax.set_xscale("log")
        scale, kw = y_scale([_value(r, y) for r in pts])  # e.g. the NLL of K = 1 (std 0) dwarfs the rest
        ax.set_yscale(scale, **kw)
        ax.set_xlabel(labels.get(x, x))
        ax.set_ylabel(labels.get(y, y))
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(title)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    tmp.replace(path)
    return path
