"""The shared console as users meet it outside a terminal: paths with brackets, log files, pipes, narrow widths."""

from __future__ import annotations

import io
import os
import subprocess
import sys

import pytest
from rich.table import Table

import uncertsplat.console as ucon
from uncertsplat.console import _Console, escape_foreign_markup, q


def _capture(width: int = 140, terminal: bool = False) -> _Console:
    # (a height too: rich takes a dumb terminal's 80x25 over the width given without one; interactive as the
    # terminal, whatever TTY_INTERACTIVE says)
    return _Console(file=io.StringIO(), width=width, height=25, force_terminal=terminal,
                    force_interactive=terminal, highlight=False, emoji=False, log_path=False,
                    soft_wrap=not terminal, color_system=None)


class TestMarkupOfUserText:
    @pytest.mark.parametrize("text", ["run[/]", "scene[v2]", "IMG [2].jpg", "a[/bold]b", "x[bold]y", ":cd: photos"])
    def test_user_text_prints_as_it_is(self, text):
        c = _capture()
        # (x[bold]y: a user's name that looks like one of our tags stays a tag; it must at least not fail)
        c.print(f"[yellow]note:[/] wrote {text}")
        out = c.file.getvalue()
        assert out.startswith("note: wrote ")
        if "[bold]" not in text:
            assert out.rstrip("\n") == f"note: wrote {text}"

    @pytest.mark.parametrize("name", ["S[/]", "S2 [red]x", "S3[/bold]", "a\\[x]"])
    def test_user_text_inside_our_tags(self, name):
        # (a review: a user's [/] inside our [bold]...[/] closed ours, and the suggested command printed wrong)
        from uncertsplat.console import qm

        c = _capture()
        c.print(f"Next: [bold]uncertsplat train {qm(name)} -o RUN[/]")
        assert c.file.getvalue() == f"Next: uncertsplat train {q(name)} -o RUN\n"

    def test_a_close_that_matches_no_open_tag_is_text(self):
        c = _capture()
        c.print("[yellow]note:[/] [yellow]x /data/a[/bold]b[/]")
        assert c.file.getvalue() == "note: x /data/a[/bold]b\n"

    def test_our_tags_still_style(self):
        assert escape_foreign_markup("[bold red]x[/] [dim]y[/dim] z[/]") == "[bold red]x[/] [dim]y[/dim] z\\[/]"
        assert escape_foreign_markup("[v2]") == "\\[v2]"
        assert escape_foreign_markup("already \\[v2]") == "already \\[v2]"

    def test_markup_off_is_left_alone(self):
        c = _capture()
        c.print("a [v2] b", markup=False)
        assert c.file.getvalue() == "a [v2] b\n"

    def test_table_cells(self):
        c = _capture()
        t = Table(show_header=False)
        t.add_column()
        t.add_row("scene[v2]/run[/]")
        c.print(t)
        assert "scene[v2]/run[/]" in c.file.getvalue()


class TestLogFiles:
    def test_long_line_is_not_broken(self):
        c = _capture(width=40)
        path = "/a/very/long/folder/name/" * 8
        c.print(f"done: 300 steps -> {path}")
        assert c.file.getvalue() == f"done: 300 steps -> {path}\n"

    def test_log_is_one_plain_line(self):
        c = _capture()
        c.log("step 100, loss 0.1")
        line = c.file.getvalue()
        assert line.endswith("step 100, loss 0.1\n") and line.startswith("[") and "  \n" not in line

    def test_progress_lines_every_tenth_after_the_first_seconds(self, monkeypatch):
        c = _capture()
        monkeypatch.setattr(ucon, "console", c)
        monkeypatch.delenv("UNCERTSPLAT_NO_PROGRESS", raising=False)
        monkeypatch.delenv("CI", raising=False)
        monkeypatch.setattr(ucon.sys.stderr, "isatty", lambda: False, raising=False)
        bar = ucon.progress()
        bar.QUIET_FIRST_S = 0.0
        with bar:
            task = bar.add_task("work", total=100, info="")
            for _ in range(100):
                bar.advance(task)
        lines = [ln for ln in c.file.getvalue().splitlines() if ln.startswith("work: ")]
        assert [ln.split()[1] for ln in lines] == [f"{k}/100" for k in range(10, 100, 10)]

    def test_a_finished_bar_names_its_task_whole(self, monkeypatch):
        """A log's finished bar read "matching (new against a… ━━━ 12/12": the description was cut to 24 columns,
        which only a terminal's redrawn bar needs."""
        c = _capture()
        monkeypatch.setattr(ucon, "console", c)
        monkeypatch.delenv("UNCERTSPLAT_NO_PROGRESS", raising=False)
        monkeypatch.delenv("CI", raising=False)
        with ucon.progress() as bar:
            task = bar.add_task("matching (new against every photo)", total=3, info="")
            for _ in range(3):
                bar.advance(task)
        assert "matching (new against every photo) " in c.file.getvalue()

    def test_quick_task_writes_no_lines(self, monkeypatch):
        c = _capture()
        monkeypatch.setattr(ucon, "console", c)
        monkeypatch.delenv("UNCERTSPLAT_NO_PROGRESS", raising=False)
        with ucon.progress() as bar:
            task = bar.add_task("quick", total=10, info="")
            for _ in range(10):
                bar.advance(task)
        assert not [ln for ln in c.file.getvalue().splitlines() if ln.startswith("quick: ")]

    @pytest.mark.parametrize(("value", "on"), [("", False), ("0", False), ("false", False), ("off", False),
                                               ("1", True), ("yes", True)])
    def test_env_flags(self, monkeypatch, value, on):
        # CI services set CI=true and give no terminal, which disables the bars on its own: read the flag alone
        monkeypatch.delenv("CI", raising=False)
        monkeypatch.setenv("UNCERTSPLAT_NO_PROGRESS", value)
        assert ucon.env_flag("UNCERTSPLAT_NO_PROGRESS") is on
        assert ucon.progress().disable is on

    @pytest.mark.parametrize(("ci", "tty", "off"), [("true", False, True), ("true", True, False),
                                                    ("0", False, False)])
    def test_ci_without_a_terminal_disables_the_bars(self, monkeypatch, ci, tty, off):
        monkeypatch.delenv("UNCERTSPLAT_NO_PROGRESS", raising=False)
        monkeypatch.setenv("CI", ci)
        monkeypatch.setattr(ucon.sys.stderr, "isatty", lambda: tty, raising=False)
        assert ucon.progress().disable is off


class TestNarrowTerminal:
    def _table(self):
        t = Table(title="run: test views")
        for col in ("view", "PSNR", "SSIM", "AUSE-MAE", "AUSE-RMSE", "NLL", "cal.err", "Spearman", "depth AUSE"):
            t.add_column(col, justify="right")
        t.add_row("view_000.png", "22.15", "0.703", "0.215", "0.246", "-1.518", "0.008", "0.541", "0.107")
        return t

    def test_rows_as_lines_when_too_wide(self, monkeypatch):
        c = _capture(width=60, terminal=True)
        monkeypatch.setattr(ucon, "console", c)
        ucon.print_table(self._table())
        out = c.file.getvalue()
        assert "NLL=-1.518" in out and "…" not in out and "view_000.png:" in out

    def test_rows_are_whole_lines_in_a_log_file(self, monkeypatch):
        c = _capture(width=60, terminal=False)
        monkeypatch.setattr(ucon, "console", c)
        t = self._table()
        t.add_row("view_008.png", "22.56", "0.727", "0.193", "0.228", "-1.668", "0.011", "0.588", "")
        ucon.print_table(t)
        lines = c.file.getvalue().splitlines()
        assert lines[0] == "run: test views" and len(lines) == 3
        assert lines[2].endswith("Spearman=0.588")  # (an empty cell left out)

    def test_table_when_it_fits(self, monkeypatch):
        c = _capture(width=140, terminal=True)
        monkeypatch.setattr(ucon, "console", c)
        ucon.print_table(self._table())
        assert "│" in c.file.getvalue() or "|" in c.file.getvalue()

    def test_counts_keep_their_width(self, monkeypatch):
        c = _capture(width=80, terminal=True)
        monkeypatch.setattr(ucon, "console", c)
        bar = ucon.progress()
        task = bar.add_task("train", total=7000, completed=300, info="loss 0.0793  N 15791  P 15784  test PSNR 22.66")
        c.print(bar.make_tasks_table([t for t in bar.tasks if t.id == task]))
        line = c.file.getvalue().splitlines()[0]
        assert " 300/7000 " in line and "train" in line


def test_suggested_paths_are_quoted():
    assert q("données ☃/run (1)") == "'données ☃/run (1)'"
    assert q("plain/run") == "plain/run"


def _run(code: str, env: dict) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, env={**os.environ, **env}, timeout=120)


def test_help_in_an_ascii_stream():
    # rich's help layout cuts option names with an ellipsis, which an ascii stream could not hold
    r = _run("import sys; from uncertsplat.cli import app; sys.argv=['uncertsplat','train','--help']; app()",
             {"PYTHONIOENCODING": "ascii", "COLUMNS": "60"})
    assert r.returncode == 0, r.stderr.decode(errors="replace")[-2000:]
    assert b"Usage" in r.stdout


def test_a_closed_stderr_leaves_stdout_alone(tmp_path):
    code = ("import os, sys\n"
            "r, w = os.pipe(); os.close(r); os.dup2(w, 2)\n"
            "from uncertsplat.console import console\n"
            "print('before', flush=True)\n"
            "for i in range(3): console.print('line', i)\n"
            "print('after', flush=True)\n")
    r = _run(code, {})
    assert r.returncode == 0 and r.stdout.split() == [b"before", b"after"]


def test_closed_pipe_does_not_stop_the_work(tmp_path):
    code = ("import os, sys\n"
            "r, w = os.pipe(); os.close(r); os.dup2(w, 2)\n"
            "from uncertsplat.console import console\n"
            "for i in range(3): console.print('line', i)\n"
            f"open({str(tmp_path / 'done')!r}, 'w').write('ok')\n")
    r = _run(code, {})
    assert r.returncode == 0
    assert (tmp_path / "done").read_text(encoding="utf-8") == "ok"
