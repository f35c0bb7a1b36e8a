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


def add_prediction_options(ap: argparse.ArgumentParser, label: str) -> None:
    """The options of the scripts that time ``Predictor.predict`` on one held-out camera of a run scaled to several
    widths (``bench_consistency.py``, ``bench_hidden_depth.py``): the run, ``--widths``, ``--samples`` (K),
    ``--repeats``, ``--label`` (default ``label``), ``--machine`` and ``--overwrite``."""
    import platform

    ap.add_argument("run", type=Path)
    ap.add_argument("--widths", type=int, nargs="+", default=[320, 1280])
    ap.add_argument("--samples", type=int, default=10)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--label", default=label)
    ap.add_argument("--machine", default=platform.processor() or platform.machine())
    add_overwrite_option(ap)


def held_out_camera(pred):
    """[1] the first held-out camera of a ``Predictor``'s scene (its last camera when every view trained)."""
    cams = pred.scene.cameras
    train = set(pred.scene.split.get("train", ()))
    test = [i for i in range(len(cams)) if i not in train] or [len(cams) - 1]
    return cams[[test[0]]]


def scaled_camera(cam, width: int):
    """``cam`` [1] at ``width`` pixels wide, its focal length and principal point scaled alike."""
    import dataclasses

    s = width / cam.width
    K = cam.K.clone()
    K[:, :2] *= s
    return dataclasses.replace(cam, K=K, width=width, height=round(cam.height * s))
