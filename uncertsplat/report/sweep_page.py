"""The sweep's HTML page (``OUT/index.html`` of ``uncertsplat sweep``): the Pareto figure and every point.

A pure function of the ``SweepSummary`` (what ``sweep.json`` holds): numbers are shown as stored (each
numeric cell carries the exact value in ``data-value``), points on a Pareto front are marked, the default
is starred. The columns name ``SweepRecord`` fields (a test checks that they are real fields).
"""

from __future__ import annotations

import math
import time

from uncertsplat.report.html import Cell, figure, kv, note, page, para, table
from uncertsplat.schemas.runs import SweepGroup, SweepRecord, SweepSummary
from uncertsplat.strategy.budget import MEMORY_HOLD

# (SweepRecord field, column header, format)
COLUMNS: tuple[tuple[str, str, str], ...] = (
    ("psnr", "PSNR (dB)", "{:.2f}"),
    ("ause_mae", "AUSE-MAE", "{:.4f}"),
    ("ause_rmse", "AUSE-RMSE", "{:.4f}"),
    ("nll", "NLL (nats)", "{:.3f}"),
    ("calibration_error", "cal. err", "{:.4f}"),
    ("depth_ause_mae", "depth AUSE", "{:.4f}"),
    ("time", "time s", "{:.1f}"),
    ("train_seconds", "train s", "{:.1f}"),
    ("calibration_seconds", "fit s", "{:.1f}"),
    ("eval_seconds_per_view", "eval s/view", "{:.2f}"),
    ("peak_memory_mb", "peak MB", "{:.0f}"),
)


def _cell(rec: SweepRecord, key: str, fmt: str) -> Cell | str:
    v = getattr(rec, key)
    if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(float(v)):
        return "-"
    return Cell(fmt.format(v), key=key, value=v)


def _group_cell(g: SweepGroup, key: str, fmt: str) -> Cell | str:
    """``mean ± spread`` over the seeds (the cell's value is the mean, as in ``sweep.json``)."""
    m, s = g.mean.get(key), g.spread.get(key)
    if m is None or not math.isfinite(m):
        return "-"
    text = fmt.format(m) + (f" ± {fmt.format(s)}" if s is not None and math.isfinite(s) else "")
    return Cell(text, key=key, value=m)


def _knobs(rec: SweepRecord) -> str:
    # (a knob the spec never set is None in the record: the configs' own value, nothing to show)
    return ", ".join(f"{a}={b}" for a, b in rec.knobs.items() if b is not None)


def build_sweep_page(summary: SweepSummary, figure_rel: str | None) -> str:
    """HTML text of the sweep page.

    Args:
        summary: the sweep's summary (``sweep.pareto.summarize``, written as ``sweep.json``).
        figure_rel: path of ``pareto.png`` relative to the page (None: no figure yet).
    """
    recs = list(summary.records)
    fronts = summary.pareto
    on_front = {pid for ids in fronts.values() for pid in ids}  # ids of table rows (a point without its seed)
    default = summary.default
    ok = [r for r in recs if r.status == "ok"]
    failed = [r for r in recs if r.status != "ok"]

    sections = []
    head = kv([("points", summary.num_points), ("failed", summary.num_failed),
               ("default (starred)", default or "-"), ("x axis", summary.pareto_x)]
              + [(f"front {name}", ", ".join(ids) or "-") for name, ids in fronts.items()])
    if any(" @ " in name for name in fronts):  # (sweep.pareto.front_key)
        head += note("Points trained at another downscale are scored against their photos at that size, so their "
                     "PSNR, AUSE and NLL do not compare with the others': each resolution has a front of its own "
                     "(\"@ downscale D\"), and the figure a row of panels.")
    held = [r.id for r in recs if any(MEMORY_HOLD in n for n in (r.notes or []))]
    if held:
        head += note(f"Memory held the model's growth in the training of {', '.join(held)}: they have fewer Gaussians "
                     "than their settings grow where memory allows, and their accuracy and time are of that smaller "
                     "model (train_summary.json's budget.memory_hold in each run).")
    sections.append(("summary", "Summary", head))
    if figure_rel:
        body = figure(figure_rel, "Accuracy vs time: every point coloured by method, the Pareto front as a black "
                      "step line, the default as a red star.", "Pareto fronts of the sweep")
    else:
        body = note("No figure: no point has finished yet. Run the sweep again to resume it.")
    sections.append(("pareto", "Pareto front", body))

    replicated = any(g.scene is not None or len(g.seeds) > 1 for g in summary.table)
    if replicated:  # scenes or seeds: the table the fronts compare (a single-scene, single-seed sweep has the points)
        grows = []
        for g in summary.table:
            mark = ("★ " if g.is_default else "") + ("front" if g.id in on_front else "")
            seeds = ", ".join("-" if s is None else str(s) for s in g.seeds) or "none finished"
            cells: list[Cell | str] = [Cell(g.scene or "-", text_cell=True), Cell(g.method, text_cell=True),
                                       Cell(seeds, text_cell=True), Cell(mark.strip(), text_cell=True)]
            cells += [_group_cell(g, key, fmt) for key, _, fmt in COLUMNS]
            grows.append((g.id, cells))
        body = table(["point", "scene", "method", "seeds", "default / front"] + [h for _, h, _ in COLUMNS], grows,
                     table_id="sweep-table", row_attr="data-group")
        body += para("Mean ± sample standard deviation over the seeds whose run finished; the Pareto fronts "
                     "compare these means, per scene.", "legend")
        sections.append(("table", "Per scene, over seeds", body))

    rows = []
    for r in sorted(ok, key=lambda r: (r.method, r.id)):
        mark = ("★ " if r.is_default else "") + ("front" if r.group in on_front else "")
        cells: list[Cell | str] = [Cell(r.method, text_cell=True),
                                   Cell(_knobs(r), text_cell=True), Cell(mark.strip(), text_cell=True)]
        cells += [_cell(r, key, fmt) for key, _, fmt in COLUMNS]
        rows.append((r.id, cells))
    header = ["point", "method", "knobs", "default / front"] + [h for _, h, _ in COLUMNS]
    body = (table(header, rows, table_id="sweep-points", row_attr="data-point") if rows
            else note("No point has finished."))
    body += para("Times are wall-clock seconds on the machine that ran the sweep; when several jobs share "
                 "the cores they are comparable with each other, not with a quiet machine. time = train + fit (the "
                 "predictive's pixel noise and std factor, fitted on the training views) + evaluation of every "
                 "view.", "legend")
    sections.append(("points", "Points", body))
    if failed:
        frows = [(r.id, [Cell(str(r.stage or "?"), text_cell=True), Cell(str(r.error or ""), text_cell=True)])
                 for r in failed]
        sections.append(("failed", "Failed points",
                         table(["point", "stage", "error"], frows, table_id="sweep-failed", row_attr="data-point")
                         + para("Run the sweep again to retry only these points.")))
    html_sections = "".join(f'<section id="{a}"><h2>{label}</h2>{b}</section>' for a, label, b in sections)
    title = f"uncertsplat sweep: {summary.name}"
    subtitle = f"{len(ok)} of {len(recs)} points finished — generated {time.strftime('%Y-%m-%d %H:%M:%S')}"
    return page(title, subtitle, [(a, label) for a, label, _ in sections], html_sections,
                generator="uncertsplat sweep")  # not a report: `report -o` must not replace it
