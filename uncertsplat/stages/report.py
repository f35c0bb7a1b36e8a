"""Stage ``report``: one or more run folders -> ``OUT/index.html`` with PNG figures in ``OUT/figures/``.

The page is self-contained (inline CSS, no scripts, fonts or network access); figures are PNG files
beside it. Every input is read through its schema and is optional (see ``uncertsplat.report.loader``): a
run that was not evaluated gets a note instead of metric sections, and a file that is present but invalid
is named in a note with the key or version that is wrong. All files are written atomically; the figures and the page
into a staging folder first, then put in place (``_swap_in``: the earlier page aside first, the new one last), so a
report folder never shows a page beside figures it did not draw, and a report that fails midway leaves the earlier
page with its own figures.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
from pathlib import Path

from uncertsplat.config import ReportConfig
from uncertsplat.console import console, q
from uncertsplat.errors import UserError
from uncertsplat.io.atomic import atomic_write_bytes, atomic_write_json, atomic_write_text, staging_folder
from uncertsplat.report.html import is_report_page
from uncertsplat.stages.evaluate import evaluation_is_current

INDEX = "index.html"
FIGURES = "figures"
CONFIG = "report_config.json"
"""``OUT/CONFIG``: the ``ReportConfig`` the page was written with (title, max_views)."""
MARKER = ".uncertsplat-report.json"
"""``OUT/MARKER``: the figures (``figures/NAME``) this command wrote into the folder, kept up to date before each one is
written. It is how a folder a report stopped in before its page (no index.html yet) is told from someone's folder, and
which PNGs of an earlier report may be deleted: only those listed here or referenced by its own page, never others."""


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
                            hint=f"Use e.g. -o {q(r / 'report')}.")
    # hidden files (a file manager's .DS_Store, Thumbs.db is not hidden but is the same kind) do not make a folder
    # anyone's: a folder holding only them was refused as "not empty"
    own = [p for p in out.iterdir() if not p.name.startswith(".") and p.name != "Thumbs.db"] if out.is_dir() else []
    if own and not is_report_page(out / INDEX) and not _unfinished_report(out) and not _swap_cut_short(out):
        from uncertsplat.io.folders import is_run

        what = ("it is a training run" if is_run(out) else "its index.html is not a page `report` wrote"
                if (out / INDEX).is_file() else "it holds no earlier report")
        raise UserError(f"the output folder is not empty and {what}; refusing to write into it (its index.html and "
                        "figures/ would be replaced)", path=out,
                        hint="Choose a new or empty folder, or one of an earlier report (its page and the figures it "
                             "wrote are replaced, other files kept).")


def _unfinished_report(out: Path) -> bool:
    """Whether ``out`` holds only what a report stopped before its page leaves: its ``MARKER`` and ``figures/`` (a
    folder of PNGs alone may be anyone's: without the marker it is not taken for a report)."""
    fig_dir = out / FIGURES
    # besides those two, only the temp files of an atomic write cut short (".NAME.xxxx.tmp.EXT")
    return ((out / MARKER).is_file() and (not fig_dir.exists() or fig_dir.is_dir())
            and all(p in (fig_dir, out / MARKER, out / CONFIG) or (p.name.startswith(".") and ".tmp" in p.name)
                    for p in out.iterdir()))


def _figures_written_before(out: Path) -> set[str]:
    """Names of the PNGs in ``OUT/figures`` an earlier report wrote: those its ``MARKER`` lists and those its page
    references (pages written before the marker existed); empty for a folder that holds no report."""
    names: set[str] = set()
    try:
        listed = json.loads((out / MARKER).read_text(encoding="utf-8")).get("figures", [])
        names.update(Path(n).name for n in listed if isinstance(n, str))
    except (OSError, ValueError, AttributeError):
        pass
    index = out / INDEX
    if is_report_page(index):
        with contextlib.suppress(OSError):
            text = index.read_text(encoding="utf-8", errors="replace")
            names.update(re.findall(rf'src="{FIGURES}/([^"/]+\.png)"', text))
    return names


def _remove_stale_figures(out: Path, earlier: set[str], keep: list[str]) -> None:
    """Delete the PNGs of an earlier report (``earlier``) in OUT/figures that the new page does not reference; a file
    the report did not write (a plot of yours put there) is never touched."""
    fig_dir = out / FIGURES
    keep_set = {Path(k).name for k in keep}
    for name in earlier - keep_set:
        p = fig_dir / name
        if p.is_file():
            with contextlib.suppress(OSError):
                p.unlink()


OLD = ".old"
"""``STAGING/OLD``: the earlier page and the figures the new ones replace, while ``_swap_in`` puts the new ones in."""


def _swap_in(out: Path, staging: Path, staged: dict[Path, Path], page: Path) -> None:
    """Put the staged figures (``staged``: final path -> staged file) and ``page`` in place in ``out``.

    The earlier page goes aside first and the new one comes last, so that no moment shows a page beside figures it
    did not draw (the figures were replaced in place under the earlier page: a kill before the new page left that
    page showing the new figures). The files replaced are moved aside into ``staging``, and a failure (an error,
    Ctrl-C) puts everything back as it was; a kill in between (milliseconds) leaves no page, which the next report
    finishes (``_swap_cut_short``)."""
    aside = staging / OLD
    moved: list[tuple[Path, Path | None]] = []  # (final path, the earlier file moved aside from it, or None)
    old_page: Path | None = None
    try:
        if (out / INDEX).exists():
            aside.mkdir(parents=True, exist_ok=True)
            old_page = aside / INDEX
            os.replace(out / INDEX, old_page)
        for final, written in staged.items():
            final.parent.mkdir(parents=True, exist_ok=True)
            before = None
            if final.is_file():
                before = aside / final.relative_to(out)
                before.parent.mkdir(parents=True, exist_ok=True)
                os.replace(final, before)
            moved.append((final, before))
            os.replace(written, final)
        os.replace(page, out / INDEX)
    except BaseException:
        for final, before in reversed(moved):
            with contextlib.suppress(OSError):
                if before is None:
                    final.unlink(missing_ok=True)
                else:
                    os.replace(before, final)
        if old_page is not None:
            with contextlib.suppress(OSError):
                os.replace(old_page, out / INDEX)
        raise


def _swap_cut_short(out: Path) -> bool:
    """Whether ``out`` is a report folder whose ``_swap_in`` was killed: its ``MARKER``, no page, and the earlier
    page aside in a staging folder (the next report's ``staging_folder`` removes it)."""
    return ((out / MARKER).is_file() and not (out / INDEX).exists()
            and any(is_report_page(p / OLD / INDEX) for p in out.glob(f".{FIGURES}.tmp-*")))


def run(runs: Path | str | list[Path], out: Path, cfg: ReportConfig | None = None,
        notes: dict[Path, list[str]] | None = None) -> Path:
    """Write the HTML report of ``runs`` (one run folder or a list) into ``out``; returns ``out/index.html``.
    ``notes``: more notes to show with a run, by its folder (a pipeline's: a prune stage it skipped).

    Raises:
        UserError: naming the run path when a run folder is missing or is not a run folder, or the
            output folder when it cannot be used.
    """
    from uncertsplat.report.build import build_report, holds_no_model
    from uncertsplat.report.loader import METRICS, load_run, other_splits, unfinished_members, without_model

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
    extra = {Path(p).resolve(): list(n) for p, n in (notes or {}).items()}
    for r in loaded:
        r.notes.extend(extra.get(r.path.resolve(), []))
    for r in loaded:
        if r.metrics is not None and r.metrics.split == "test" and evaluation_is_current(r.path, r.metrics) is False:
            r.notes.append(f"its eval/metrics.json scored an earlier state of the run (the model, config or scene, or "
                           f"the photos' masks, changed since, e.g. by `train --resume`), so the metrics shown are "
                           f"that model's: run "
                           f"`uncertsplat evaluate {q(r.path)}` again, then this report")
    earlier = _figures_written_before(out)  # (_check_output let it through: empty, a report, or a stopped one's)
    listed = set(earlier)
    # the figures are written apart and put in place with the page: a report that fails midway (a full disk, a kill)
    # leaves the earlier page with its own figures, where writing them in place showed old numbers beside new maps
    staged: dict[Path, Path] = {}
    with staging_folder(out, f".{FIGURES}.tmp-") as staging:

        def write_figure(path: Path, data: bytes) -> Path:
            # listed in the marker before it is written, so a report stopped at any point can tell its files from
            # others'
            if path.name not in listed:
                listed.add(path.name)
                atomic_write_json(out / MARKER, {"figures": sorted(listed)})
            staged[path] = atomic_write_bytes(staging / path.relative_to(out), data)
            return path

        text, figures = build_report(loaded, out, cfg.title, cfg.max_views, write_figure)
        if not (out / MARKER).is_file():
            # (a page written before the marker existed referenced every figure drawn: none was written above, and a
            # kill in ``_swap_in`` left a folder without page or marker, refused by every later report)
            atomic_write_json(out / MARKER, {"figures": sorted(listed)})
        # the page staged too (a full disk fails it before anything in OUT changed)
        _swap_in(out, staging, staged, atomic_write_text(staging / INDEX, text))
        index = out / INDEX
    _remove_stale_figures(out, earlier | listed, figures)
    atomic_write_json(out / MARKER, {"figures": sorted(Path(f).name for f in figures)})
    atomic_write_json(out / CONFIG, cfg.model_dump(mode="json"))  # as every stage writes its config beside its outputs
    for r in loaded:
        for n in r.notes:
            console.print(f"[yellow]note[/] {r.name}: {n}")
        if r.metrics is None and r.problem(METRICS) is None and without_model(r):
            console.print(f"[yellow]note[/] {r.name}: no trained model (its training stopped before its first "
                          f"checkpoint), so the report shows its settings only: `uncertsplat train SCENE -o "
                          f"{q(r.path)} --resume` trains it from step 0")
        elif (r.metrics is None and r.problem(METRICS) is None and not holds_no_model(r)
                and unfinished_members(r) is None):
            # (said on the page; a report of a run never evaluated looked finished from the console)
            other = other_splits(r)
            console.print(f"[yellow]note[/] {r.name}: "
                          + (f"its only evaluation is another split's ({', '.join(other)}), which the report does not "
                             "show" if other else "not evaluated (no eval/metrics.json)")
                          + f", so the report shows its training only: `uncertsplat evaluate {q(r.path)}` adds the "
                            "held-out views' uncertainty maps and metrics")
    console.print(f"report: {index} ({len(figures)} figure{'' if len(figures) == 1 else 's'})")
    return index
