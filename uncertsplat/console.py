"""The shared rich console and progress bars (library code prints through these, never print())."""

from __future__ import annotations

import os
import sys

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)


class _Console(Console):
    """rich's console, with ``rewrite`` (None: off) applied to each text printed: a pipeline stage's advice names its
    command's options (``--set exposure=affine``), which in a pipeline are that stage's keys (``stages.pipeline``)."""

    rewrite = None

    def print(self, *objects, **kwargs) -> None:  # noqa: D102
        if self.rewrite is not None:
            objects = tuple(self.rewrite(o) if isinstance(o, str) else o for o in objects)
        super().print(*objects, **kwargs)


# Outside a terminal (CI logs, pipes) rich would wrap tables at 80 columns; give them room.
console = _Console(stderr=True, highlight=False, width=None if sys.stderr.isatty() else 140)


def progress(transient: bool = False) -> Progress:
    """A progress bar with counts and elapsed/remaining time; disabled when not a terminal in CI."""
    disable = bool(os.environ.get("UNCERTSPLAT_NO_PROGRESS")) or (not sys.stderr.isatty() and bool(os.environ.get("CI")))
    return Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        TextColumn("{task.fields[info]}"),
        console=console,
        transient=transient,
        disable=disable,
    )


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
    import shlex

    if all(shlex.quote(n) == n and "," not in n for n in names):
        return "--add-views " + ",".join(names)
    return " ".join(f"--add-views {shlex.quote(n)}" for n in names)
