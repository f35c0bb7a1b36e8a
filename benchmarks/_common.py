"""What the benchmark scripts share: a run does not replace an existing results file unless asked.

``benchmarks/results/`` holds the measurements BENCHMARKS.md quotes, committed. Every script names its results
file(s) from ``--out`` / ``--label`` (or ``--tag``) and, before it measures anything, refuses to write over one
that exists unless ``--overwrite`` is given: a documented command run again with its own label stops at once with a
message instead of replacing the committed file.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"


def add_overwrite_option(ap: argparse.ArgumentParser) -> None:
    """``--overwrite``: replace existing results files (without it, ``refuse_overwrite`` stops the run)."""
    ap.add_argument("--overwrite", action="store_true",
                    help="replace existing results files (default: refuse, since benchmarks/results/ holds the "
                         "committed measurements; or give another --out / --label)")


def refuse_overwrite(*paths: Path | str, overwrite: bool) -> None:
    """Exit with a message when one of ``paths`` exists and ``overwrite`` is off; call it before measuring."""
    existing = [str(p) for p in paths if Path(p).exists()]
    if existing and not overwrite:
        script = Path(sys.argv[0]).name
        sys.exit(f"{script}: {', '.join(existing)} exists (a committed or earlier result): name another (--out, "
                 "--label or --tag, as the script has), or give --overwrite to replace it")
