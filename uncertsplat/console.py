"""The shared rich console and progress bars (library code prints through these, never print())."""

from __future__ import annotations

import contextlib
import os
import re
import sys
import time

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TaskID,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.table import Column

# The markup tags our own messages use ("[yellow]note:[/]", "[bold]", "[dim]", ...). Any other bracketed text is the
# user's (a folder named `scene[v2]`, a photo `IMG [2].jpg`): rich would read it as a tag and drop it, or fail on a
# closing `[/]` that has nothing to close, so it is escaped before rich parses the markup.
_STYLE_WORDS = frozenset({"bold", "dim", "italic", "underline", "yellow", "red", "green", "cyan", "blue", "magenta"})
_TAG = re.compile(r"(\\*)\[([a-z#/@][^\[]*?)\]")


def escape_foreign_markup(text: str) -> str:
    """``text`` with every ``[...]`` that is not one of our style tags escaped, so rich prints it as it is: a tag of
    ours is a style (``[yellow]``, ``[bold red]``) or the close of the style open last (``[/]``, ``[/bold]``); a
    user's ``[/]`` after our tags are closed, ``[v2]`` or ``[/bold]`` that closes nothing is text. A user's text
    inside one of our tags is escaped where it is put there (``qm``): a ``[/]`` in it would close ours."""
    out, at, stack = [], 0, []
    for m in _TAG.finditer(text):
        slashes, tag = m.group(1), m.group(2)
        if len(slashes) % 2:  # escaped already: rich prints it as text
            continue
        closing = tag.startswith("/")
        name = " ".join((tag[1:] if closing else tag).split())
        if not closing and name and all(w in _STYLE_WORDS for w in name.split()):
            stack.append(name)
            continue
        if closing and stack and name in ("", stack[-1]):
            stack.pop()
            continue
        bracket = m.start() + len(slashes)
        out.append(text[at:bracket] + "\\")
        at = bracket
    out.append(text[at:])
    return "".join(out)


def env_flag(name: str) -> bool:
    """Whether the environment variable ``name`` is set to something that means yes (not "", 0, false, no, off)."""
    return os.environ.get(name, "").strip().lower() not in ("", "0", "false", "no", "off")


def advice_within(name: str, fields, text: str, within: str, knobs: dict[str, str] | None = None,
                  others: dict[str, tuple[str, object]] | None = None) -> str:
    """``text`` (a command's message) with its advice in the words of a ``within`` ("pipeline", "sweep") that gives
    the command's settings under ``name``: ``--set key=value`` of one of ``fields`` as ``--set NAME.key=value``, and
    the command's options that are its keys (``--features dsp-sift``) named after it as ``--set NAME.features``;
    ``knobs`` {dotted key: knob}: a key the ``within`` sets by a knob of its own (a sweep's ``downscale``, which
    refuses ``--set train.scene.downscale``) is named as that knob; ``others`` {command: (its name within, its
    fields)}: advice about another command's settings (an evaluation's "`train --set random_background=true`", or
    "--iterations N" for the training that made the run) named as that command's (``--set train.random_background``).
    Text that speaks of pipelines (or of the ``within``) already is left as it is."""
    if "pipeline" in text or within in text:
        return text
    for command, (other, its_fields) in (others or {}).items():
        # (a whole command line, `uncertsplat train ...`, is one a user runs by hand: left as it is)
        text = re.sub(rf"(?<!uncertsplat )\b{re.escape(command)} --set (['\"]?)([a-z_][a-z0-9_]*)([.=])",
                      lambda m, o=other, f=its_fields: (f"--set {m.group(1)}{o}.{m.group(2)}{m.group(3)}"
                                                        if m.group(2) in f else m.group(0)), text)
    if knobs:
        text = re.sub(r"--set (['\"]?)([a-z_][a-z0-9_.]*)=([^\s'\",;)]*)\1",
                      lambda m: (f"{knobs[m.group(2)]} = {m.group(3)} (a knob of the {within}: its [default] or [axes])"
                                 if m.group(2) in knobs else m.group(0)), text)
    text = re.sub(r"--set (['\"]?)([a-z_][a-z0-9_]*)([.=])",
                  lambda m: f"--set {m.group(1)}{name}.{m.group(2)}{m.group(3)}" if m.group(2) in fields else m.group(0),
                  text)
    keys = [o.replace("-", "_") for o in re.findall(r"(?<![\w-])--([a-z][a-z0-9-]*)", text)]
    named = [f"--set {name}.{k}" for k in dict.fromkeys(k for k in keys if k in fields and k != "set")]
    for command, (other, its_fields) in (others or {}).items():  # (an option of the other command's alone, not one
        if f"uncertsplat {command} " in text:  # of a whole command line of it, e.g. a resume's `--method fisher`)
            continue
        named += [f"--set {other}.{k}" for k in dict.fromkeys(k for k in keys if k in its_fields and k not in fields)]
    return text + (f" (in this {within}: {', '.join(named)})" if named else "")


class _Console(Console):
    """rich's console, with ``rewrite`` (None: off) applied to each text printed: a pipeline stage's advice names its
    command's options (``--set exposure=affine``), which in a pipeline are that stage's keys (``stages.pipeline``;
    in a sweep, its ``train`` or ``evaluate`` table's: ``sweep.jobs``; ``advice_within``).
    Text of the user's (paths, names) is never read as markup (``escape_foreign_markup``), and a reader that went
    away (``uncertsplat train ... | head``) stops the output, not the work: a training goes on to its end."""

    rewrite = None

    def print(self, *objects, **kwargs) -> None:  # noqa: D102
        if self.rewrite is not None:
            objects = tuple(self.rewrite(o) if isinstance(o, str) else o for o in objects)
        super().print(*objects, **kwargs)

    def log(self, *objects, **kwargs) -> None:  # noqa: D102
        if self.is_terminal:
            super().log(*objects, **kwargs)
        else:  # (rich's log pads each line to the width with the time in a column: one plain line instead)
            self.print(time.strftime("[%H:%M:%S]"), *objects, **kwargs)

    def render_str(self, text: str, **kwargs):  # noqa: D102
        markup = kwargs.get("markup")
        if markup or (markup is None and self._markup):
            text = escape_foreign_markup(text)
        return super().render_str(text, **kwargs)

    def on_broken_pipe(self) -> None:
        """The reader of our output closed it (``uncertsplat train ... 2>&1 | head``): later output goes nowhere,
        and the command goes on (rich's own handler exits with 1, which stopped a training without its
        checkpoint)."""
        self.quiet = True
        devnull = os.open(os.devnull, os.O_WRONLY)
        with contextlib.suppress(OSError, ValueError, AttributeError):  # (our stream only: stdout may be fine)
            os.dup2(devnull, self.file.fileno())


# Outside a terminal (CI logs, pipes, a cluster's log file) a line is written whole, never broken at a width (a path
# or a suggested command stays one line to copy); tables get 140 columns there. rich's emoji codes are off: a name
# such as `:cd:` is the user's, not an emoji.
_TTY = sys.stderr.isatty()
console = _Console(stderr=True, highlight=False, emoji=False, log_path=False, soft_wrap=not _TTY,
                   width=None if _TTY else 140)


class _Progress(Progress):
    """rich's progress bars; where the console cannot redraw a bar (a log file, a pipe, TERM=dumb) rich shows it only
    when it ends, so there a plain line is written at every tenth of a task and at least once a minute: `tail -f` on a
    cluster's log shows the work moving."""

    LINE_EVERY_S = 60.0
    QUIET_FIRST_S = 10.0

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self._lines: dict[TaskID, tuple[int, float]] = {}  # task -> (tenths written, time of the last line)

    def update(self, task_id: TaskID, **kwargs) -> None:  # noqa: D102
        super().update(task_id, **kwargs)
        self._line(task_id)

    def advance(self, task_id: TaskID, advance: float = 1) -> None:  # noqa: D102
        super().advance(task_id, advance)
        self._line(task_id)

    def _line(self, task_id: TaskID) -> None:
        if self.disable or self.console.is_interactive:
            return
        task = next((t for t in self.tasks if t.id == task_id), None)
        if task is None or not task.total:
            return
        now = time.monotonic()
        tenths, last = self._lines.get(task_id, (int(10 * task.completed / task.total), now))
        reached = int(10 * task.completed / task.total)
        # (a task done within seconds needs no lines: its bar is printed when it ends)
        if (reached > tenths and (task.elapsed or 0) >= self.QUIET_FIRST_S) or now - last >= self.LINE_EVERY_S:
            if task.completed < task.total:  # (the finished bar itself is printed when the bars stop)
                info = task.fields.get("info") or ""
                elapsed = int(task.elapsed or 0)
                self.console.print(f"{task.description}: {int(task.completed)}/{int(task.total)} "
                                   f"({elapsed // 60}:{elapsed % 60:02d}){'  ' + info if info else ''}",
                                   markup=False)
            tenths, last = reached, now
        self._lines[task_id] = (tenths, last)


def progress(transient: bool = False) -> Progress:
    """A progress bar with counts and elapsed/remaining time; disabled when not a terminal in CI (or with
    UNCERTSPLAT_NO_PROGRESS=1). The counts and times never give way to the info text in a narrow terminal."""
    disable = env_flag("UNCERTSPLAT_NO_PROGRESS") or (not sys.stderr.isatty() and env_flag("CI"))
    # rich shrinks every column alike when a row is too wide (an 80-column terminal showed "tr… 300/… 0:00…"): the
    # info text alone gets what the bar, counts and times leave
    bar = 40 if console.width >= 160 else 20 if console.width >= 100 else 10
    info_width = max(8, console.width - bar - 52)  # (a description of up to 24, counts 9, times 2 x 7, the gaps)
    # (where the bars are not redrawn, a log or TERM=dumb, the finished bars are printed once: "matching (new against
    # a…" cut a log's line; 48 keeps every description whole and the counts beside it in a log's 140 columns)
    described = 24 if console.is_interactive else 48
    return _Progress(
        TextColumn("[bold]{task.description}",
                   table_column=Column(no_wrap=True, max_width=described, overflow="ellipsis")),
        BarColumn(bar_width=bar),
        MofNCompleteColumn(table_column=Column(no_wrap=True)),
        TimeElapsedColumn(table_column=Column(no_wrap=True)),
        TimeRemainingColumn(table_column=Column(no_wrap=True)),
        TextColumn("{task.fields[info]}", markup=False,
                   table_column=Column(no_wrap=True, overflow="ellipsis", max_width=info_width)),
        console=console,
        transient=transient,
        disable=disable,
    )


def print_table(table) -> None:
    """Print a rich ``Table``; where the console is narrower than the table's natural width (rich would cut its
    numbers and paths to "-1.5…" and "/home/…"), each row as one line of header=value pairs instead, whole."""
    from rich.measure import Measurement

    natural = Measurement.get(console, console.options.update_width(100_000), table).maximum
    if natural <= console.width:
        console.print(table)
        return
    if table.title:
        console.print(table.title)
    columns = table.columns
    for row in zip(*(list(c.cells) for c in columns), strict=True):
        cells = [str(c) for c in row]
        if table.show_header:
            rest = [f"{columns[i].header}={c}" if str(columns[i].header) else c
                    for i, c in enumerate(cells) if i > 0 and c != ""]
            console.print("  " + cells[0] + ": " + "; ".join(rest))
        else:
            console.print("  " + ": ".join(c for c in cells if c != ""))


def q(path) -> str:
    """``path`` as a shell takes it in a command we suggest (quoted where it holds a space, a quote or another
    character a shell reads): the command can be copied as printed."""
    import shlex

    return shlex.quote(str(path))


def esc(text) -> str:
    """A user's ``text`` (a path, photo names) to put inside one of our markup tags (``[dim]note: {esc(x)}[/]``):
    its brackets escaped, so ``S[/]`` neither closes the tag nor vanishes."""
    from rich.markup import escape

    return escape(str(text))


def qm(path) -> str:
    """``q(path)`` for a command inside one of our markup tags (``[bold]uncertsplat train {qm(scene)} ...[/]``)."""
    return esc(q(path))


def count(n: int, one: str, many: str | None = None) -> str:
    """"1 Gaussian", "3 Gaussians" (``many``: the plural when it is not ``one`` + "s"); thousands separated."""
    return f"{n:,} {one if n == 1 else (many or one + 's')}"


def list_names(names: list[str], limit: int = 15) -> str:
    """``names`` joined by commas for a message, the first ``limit`` of them and how many more."""
    shown = ", ".join(names[:limit])
    return shown + (f" and {len(names) - limit} more" if len(names) > limit else "")


def add_views_args(names: list[str]) -> str:
    """``--add-views`` for ``names`` as a shell takes them: one comma-joined value, or one quoted flag per name where a
    name holds a comma, a space or another character a shell reads (``IMG 4045, final.jpg``)."""
    if all(q(n) == n and "," not in n for n in names):
        return "--add-views " + ",".join(names)
    return " ".join(f"--add-views {q(n)}" for n in names)
