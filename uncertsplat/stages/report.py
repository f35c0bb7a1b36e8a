"""Stage ``report``: one or more run folders -> ``OUT/index.html`` with PNG figures in ``OUT/figures/``.

The page is self-contained (inline CSS, no scripts, fonts or network access); figures are PNG files
beside it. Every input is read through its schema and is optional (see ``uncertsplat.report.loader``): a
run that was not evaluated gets a note instead of metric sections, and a file that is present but invalid
is named in a note with the key or version that is wrong. All files are written atomically; ``index.html`` is written
last, so a report folder never references a figure that is not there.
"""

from __future__ import annotations

import contextlib
from pathlib import Path

from uncertsplat.config import ReportConfig
from uncertsplat.console import console
from uncertsplat.errors import UserError
from uncertsplat.io.atomic import atomic_write_bytes, atomic_write_text
from uncertsplat.report.html import is_report_page
from uncertsplat.stages.evaluate import evaluation_is_current

INDEX = "index.html"
FIGURES = "figures"


def _display_names(paths: list[Path]) -> list[str]:
    """Folder names, made unique with their parents when two runs share a name."""
    names = [p.resolve().name or str(p) for p in paths]
    if len(set(names)) == len(names):
        return names
    out = []
    for p, n in zip(paths, names, strict=True):
        out.append(f"{p.resolve().parent.name}/{n}" if names.count(n) > 1 else n)
    # still ambiguous (same parent name too): number them
    return [f"{n} [{i + 1}]" if out.count(n) > 1 else n for i, n in enumerate(out)]


def _check_output(out: Path, runs: list[Path]) -> None:
    if out.exists() and not out.is_dir():
        raise UserError("the report output exists and is not a folder", path=out, hint="Choose a folder with -o.")
    for r in runs:
        if out.resolve() == r.resolve():
            raise UserError("the report folder cannot be the run folder itself", path=out,
                            hint=f"Use e.g. -o {r / 'report'}.")
    if out.is_dir() and any(out.iterdir()) and not is_report_page(out / INDEX) and not _unfinished_report(out):
        what = ("its index.html is not a page `report` wrote" if (out / INDEX).is_file()
                else "it holds no earlier report")
        raise UserError(f"the output folder is not empty and {what}; refusing to write into it (its index.html and "
                        "figures/ would be replaced)", path=out,
                        hint="Choose a new or empty folder (a folder of an earlier report is replaced).")


def _unfinished_report(out: Path) -> bool:
    """Whether ``out`` holds only what a report stopped before its page leaves (``figures/`` with PNGs and temp
    files): the same command may write there again (it refused, having no index.html to recognise)."""
    entries = list(out.iterdir())
    fig_dir = out / FIGURES
    return (all(p == fig_dir for p in entries) and fig_dir.is_dir()
            and all(f.is_file() and (f.suffix == ".png" or f.name.startswith(".")) for f in fig_dir.iterdir()))


def _remove_stale_figures(out: Path, keep: list[str]) -> None:
    """Delete PNGs of an earlier report in OUT/figures that the new page does not reference."""
    fig_dir = out / FIGURES
    if not fig_dir.is_dir():
        return
    keep_set = {Path(k).name for k in keep}
    for p in fig_dir.glob("*.png"):
        if p.name not in keep_set:
            with contextlib.suppress(OSError):
                p.unlink()


def run(runs: Path | str | list[Path], out: Path, cfg: ReportConfig | None = None) -> Path:
    """Write the HTML report of ``runs`` (one run folder or a list) into ``out``; returns ``out/index.html``.

    Raises:
        UserError: naming the run path when a run folder is missing or is not a run folder, or the
            output folder when it cannot be used.
    """
    from uncertsplat.report.build import build_report
    from uncertsplat.report.loader import load_run

    cfg = cfg or ReportConfig()
    paths = [Path(runs)] if isinstance(runs, (str, Path)) else [Path(r) for r in runs]
    if not paths:
        raise UserError("no run folder given", hint="Example: uncertsplat report runs/demo -o report/")
    seen: set[Path] = set()
    for p in paths:
        if p.resolve() in seen:
            raise UserError("this run folder is given twice", path=p, hint="Give each run once.")
        seen.add(p.resolve())
    out = Path(out)
    names = _display_names([p for p in paths if p.exists()]) if all(p.exists() for p in paths) else []
    loaded = [load_run(p, name=names[i] if names else None) for i, p in enumerate(paths)]
    _check_output(out, paths)
    for r in loaded:
        if r.metrics is not None and r.metrics.split == "test" and evaluation_is_current(r.path, r.metrics) is False:
            r.notes.append(f"its eval/metrics.json scored an earlier state of the run (the model, config or scene "
                           f"changed since, e.g. by `train --resume`), so the metrics shown are that model's: run "
                           f"`uncertsplat evaluate {r.path}` again, then this report")
    had_report = out.is_dir() and any(out.iterdir())  # (_check_output let it through: a report, or an unfinished one's figures)

    text, figures = build_report(loaded, out, cfg.title, cfg.max_views, atomic_write_bytes)
    if had_report:
        _remove_stale_figures(out, figures)
    index = atomic_write_text(out / INDEX, text)
    for r in loaded:
        for n in r.notes:
            console.print(f"[yellow]note[/] {r.name}: {n}")
    console.print(f"report: {index} ({len(figures)} figure{'' if len(figures) == 1 else 's'})")
    return index
