"""Interruption of real `uncertsplat train` subprocesses: SIGINT, SIGTERM and SIGKILL at several moments.

What must hold: a signal gives a final checkpoint and a clean exit (code 2, one paragraph, how to resume);
a SIGKILL leaves every checkpoint under its final name complete and loadable, and ``--resume`` continues
from the newest one; the log (stats.jsonl) ends up with every step exactly once: nothing lost, nothing
repeated.
"""

from __future__ import annotations

import random
import signal
from pathlib import Path

import pytest
import torch

from tests.fixtures import tiny_scene_path  # noqa: F401
from tests.reliability.helpers import (
    FAST,
    assert_clean_error,
    assert_clean_interrupt,
    finish,
    logged_steps,
    run_cli,
    start_cli,
    start_python,
    temp_leftovers,
    wait_until,
)
from uncertsplat.io.checkpoints import list_checkpoints, load_checkpoint


def _check_all_checkpoints_load(run: Path) -> list[int]:
    steps = []
    for step, path in list_checkpoints(run):
        state = load_checkpoint(path)  # raises CorruptCheckpoint if anything is incomplete
        assert int(state["step"]) == step
        assert all(torch.isfinite(t).all() for t in state["model"]["params"].values())
        steps.append(step)
    return steps


def _interrupt(proc, sig, run: Path, after_step: int) -> tuple[int, str]:
    wait_until(lambda: len(logged_steps(run)) and max(logged_steps(run)) >= after_step, proc,
               what=f"step {after_step}")
    proc.send_signal(sig)
    return finish(proc)


def _interrupted_step(out: str) -> int:
    import re

    m = re.search(r"training interrupted at step (\d+)", out)
    assert m, out
    return int(m.group(1))


def test_sigint_then_resume_then_sigterm_and_second_writer_refused(tiny_scene_path, tmp_path):
    run = tmp_path / "run"
    # no periodic checkpoint: on a fast machine thousands of steps pass before a signal lands, and this
    # test is about the checkpoints the signals write
    args = ["train", tiny_scene_path, "-o", run, *FAST, "--set", "iterations=1000000",
            "--set", "checkpoint_every=1000000000"]
    proc = start_cli(*args)
    wait_until(lambda: len(logged_steps(run)) > 0, proc, what="the first step")

    # a second command on the same run folder while the first one trains: refused, nothing touched
    before = {p: p.stat().st_mtime_ns for p in run.rglob("*") if p.is_file() and p.name != "stats.jsonl"}
    second = run_cli(*args, "--resume")
    assert_clean_error(second.returncode, second.stderr + second.stdout, "another uncertsplat process",
                       f"PID {proc.pid}")
    # the same command without --resume: a run with no checkpoint yet would be started again, but this one is
    # training: refused by its lock, naming the process (it said "already exists ... --resume", which the lock refuses)
    plain = run_cli(*args)
    assert_clean_error(plain.returncode, plain.stderr + plain.stdout, "another uncertsplat process", f"PID {proc.pid}")
    assert proc.poll() is None, proc.stdout.read()
    assert {p: p.stat().st_mtime_ns for p in before} == before

    # SIGINT (Ctrl-C): the step in progress completes, a checkpoint is written, clean exit
    rc, out = _interrupt(proc, signal.SIGINT, run, after_step=2)
    assert_clean_interrupt(rc, out, "training interrupted", "checkpoint saved", "--resume")
    n = _interrupted_step(out)
    assert n >= 2
    assert _check_all_checkpoints_load(run) == [n]
    assert max(logged_steps(run)) == n
    assert not (run / ".lock").exists()
    assert not temp_leftovers(run)

    # --resume continues from step n; then SIGTERM (what `kill` and job schedulers send)
    proc = start_cli(*args, "--resume")
    rc, out = _interrupt(proc, signal.SIGTERM, run, after_step=n + 2)
    assert_clean_interrupt(rc, out, "training interrupted", "checkpoint saved")
    assert f"step {n})" in " ".join(out.split()), out  # "resuming from ... (step n)"
    m = _interrupted_step(out)
    assert m >= n + 2
    assert _check_all_checkpoints_load(run) == [n, m]
    # every step logged exactly once across the two processes
    assert logged_steps(run) == list(range(1, m + 1))
    assert not (run / ".lock").exists()
    assert not temp_leftovers(run)


def test_sigkill_at_a_random_step_then_resume(tiny_scene_path, tmp_path):
    """SIGKILL between or during steps / checkpoint writes: what is on disk is complete; resume continues."""
    rng = random.Random()
    kill_after = rng.randint(3, 9)
    run = tmp_path / "run"
    args = ["train", tiny_scene_path, "-o", run, *FAST, "--set", "iterations=1000000", "--set", "checkpoint_every=2"]
    proc = start_cli(*args)
    wait_until(lambda: len(logged_steps(run)) and max(logged_steps(run)) >= kill_after, proc,
               what=f"step {kill_after}")
    proc.send_signal(signal.SIGKILL)
    rc, _ = finish(proc)
    assert rc == -signal.SIGKILL
    steps = _check_all_checkpoints_load(run)
    assert steps, "at least one checkpoint (every 2 steps) must exist"
    last = steps[-1]
    assert last <= max(logged_steps(run))
    assert (run / ".lock").exists()  # left by the killed process: the next command takes it over

    inode = (run / "config.json").stat().st_ino
    proc = start_cli(*args, "--resume")
    # the resumed process truncates stats.jsonl to the checkpoint, then rewrites config.json
    wait_until(lambda: (run / "config.json").stat().st_ino != inode, proc, what="the resumed run to start")
    rc, out = _interrupt(proc, signal.SIGINT, run, after_step=last + 1)
    assert f"step {last})" in " ".join(out.split()), out
    assert_clean_interrupt(rc, out, "training interrupted")
    n = _interrupted_step(out)
    assert logged_steps(run) == list(range(1, n + 1)), f"killed after {kill_after}, resumed from {last}"
    assert _check_all_checkpoints_load(run)[-1] == n


_KILL_AT = """
import os, signal, sys
real = os.replace
def replace(src, dst, *a, **k):
    if os.path.basename(str(dst)) == {target!r}:
        os.kill(os.getpid(), signal.SIGKILL)  # die with the complete temp file written, before the rename
    return real(src, dst, *a, **k)
os.replace = replace
from uncertsplat.cli import app
sys.argv = ["uncertsplat", *{args!r}]
app()
"""


@pytest.mark.parametrize("target, iterations, good", [
    ("step_000006.pt", 8, [2, 4]),        # killed while renaming a checkpoint into place
    pytest.param("variational.ply", 4, [2, 4], marks=pytest.mark.slow),  # killed writing the final model
])
def test_sigkill_inside_an_atomic_write_then_resume_matches_uninterrupted(tiny_scene_path, tmp_path, target,
                                                                          iterations, good):
    run = tmp_path / "run"
    args = ["train", str(tiny_scene_path), "-o", str(run), *FAST, "--set", f"iterations={iterations}",
            "--set", "checkpoint_every=2", "--set", "keep_checkpoints=5"]
    rc, out = finish(start_python(_KILL_AT.format(target=target, args=args)))
    assert rc == -signal.SIGKILL, out
    assert not (run / target).exists() and not (run / "ckpts" / target).exists()
    assert _check_all_checkpoints_load(run) == good
    assert temp_leftovers(run), "the kill happened with a temp file written (the case under test)"

    done = run_cli(*args, "--resume")
    assert done.returncode == 0, done.stderr
    assert f"(step {good[-1]})" in " ".join(done.stderr.split())
    assert logged_steps(run) == list(range(1, iterations + 1))
    assert not temp_leftovers(run), "stale temp files of the killed process are cleaned up on resume"

    # nothing lost: the resumed run ends bit-identical to one never interrupted (CPU)
    ref = tmp_path / "ref"
    assert run_cli(*[str(a) if a != str(run) else str(ref) for a in args]).returncode == 0
    from uncertsplat.io.ply import read_variational_ply

    a, _ = read_variational_ply(run / "variational.ply")
    b, _ = read_variational_ply(ref / "variational.ply")
    for name, p in a.parameters().items():
        assert torch.equal(p, b.parameters()[name]), name
