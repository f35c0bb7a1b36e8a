"""Helpers of the reliability suite: CLI subprocesses that cannot hang, file snapshots, damage.

Training runs here use a deliberately small problem (the tiny synthetic scene at 1/4 resolution, 32x24,
with 150 starting Gaussians, no densification, no periodic evaluation) so one step takes well under a
second and a subprocess test takes seconds, not minutes.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PYTHON = sys.executable

# Small and fast: 32x24 images, 150 Gaussians, no densify/spawn, no periodic held-out evaluation.
FAST = [
    "--preset", "tiny", "--device", "cpu",
    "--set", "scene.downscale=4", "--set", "scene.max_points=150",
    "--set", "eval_every=100000", "--set", "log_every=1",
    "--set", "densify.start=100000",
]

# Generous: the CI machine is shared, a subprocess may run 3-5x slower than on an idle machine.
WAIT_S = 240.0


def env() -> dict[str, str]:
    e = dict(os.environ)
    e["UNCERTSPLAT_NO_PROGRESS"] = "1"
    e["OMP_WAIT_POLICY"] = "PASSIVE"
    e["COLUMNS"] = "200"  # keep rich from wrapping file names in messages
    e["PYTHONPATH"] = str(ROOT) + os.pathsep + e.get("PYTHONPATH", "")
    return e


def cli_args(*args: str) -> list[str]:
    return [PYTHON, "-m", "uncertsplat.cli", *[str(a) for a in args]]


def run_cli(*args: str, cwd: Path | None = None, timeout: float = WAIT_S) -> subprocess.CompletedProcess:
    """Run ``uncertsplat ARGS`` to completion (fails the test rather than hang)."""
    return subprocess.run(cli_args(*args), cwd=cwd, env=env(), capture_output=True, text=True, timeout=timeout)


def start_cli(*args: str, cwd: Path | None = None, extra_env: dict | None = None) -> subprocess.Popen:
    e = env()
    e.update(extra_env or {})
    return subprocess.Popen(cli_args(*args), cwd=cwd, env=e, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, start_new_session=True)


def start_python(code: str, cwd: Path | None = None) -> subprocess.Popen:
    """Run a Python snippet in a subprocess (used to kill a run at an exact moment from inside)."""
    return subprocess.Popen([PYTHON, "-c", code], cwd=cwd, env=env(), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True)


def finish(proc: subprocess.Popen, timeout: float = WAIT_S) -> tuple[int, str]:
    """Wait for ``proc``; kill it and fail when it takes longer than ``timeout``."""
    try:
        out, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, _ = proc.communicate()
        raise AssertionError(f"process did not finish in {timeout} s; output:\n{out}") from None
    return proc.returncode, out


def wait_until(cond: Callable[[], bool], proc: subprocess.Popen | None = None, timeout: float = WAIT_S,
               what: str = "condition") -> None:
    """Poll ``cond`` until true; fail (and kill ``proc``) on timeout or when ``proc`` exits first."""
    t0 = time.monotonic()
    while not cond():
        if proc is not None and proc.poll() is not None:
            out = proc.stdout.read() if proc.stdout else ""
            raise AssertionError(f"process exited ({proc.returncode}) before {what}; output:\n{out}")
        if time.monotonic() - t0 > timeout:
            if proc is not None:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.communicate()
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(0.05)


def logged_steps(run: Path) -> list[int]:
    """Training steps recorded in RUN/stats.jsonl (complete lines with a loss; the step-0 eval is left out)."""
    import json

    path = run / "stats.jsonl"
    if not path.is_file():
        return []
    steps = []
    for line in path.read_text(encoding="utf-8").splitlines():
        try:
            rec = json.loads(line)
        except ValueError:
            continue
        if "loss" in rec:
            steps.append(int(rec["step"]))
    return steps


def snapshot(root: Path) -> dict[str, tuple[int, int]]:
    """{relative path: (size, mtime_ns)} of every file under ``root``."""
    out = {}
    for p in Path(root).rglob("*"):
        if p.is_file():
            st = p.stat()
            out[str(p.relative_to(root))] = (st.st_size, st.st_mtime_ns)
    return out


def temp_leftovers(root: Path) -> list[Path]:
    """Temporary files of atomic writes (``.NAME.xxxx.tmp``) left anywhere under ``root``."""
    return [p for p in Path(root).rglob(".*") if p.is_file() and ".tmp" in p.name]


def truncate(path: Path, keep_fraction: float = 0.5) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep_fraction)])


def flip_bit(path: Path, offset: int, bit: int = 3) -> None:
    data = bytearray(path.read_bytes())
    data[offset % len(data)] ^= 1 << bit
    path.write_bytes(bytes(data))


def assert_clean_interrupt(rc: int, out: str, *must_contain: str) -> None:
    """Exit code 130 (as for Ctrl-C), an ``interrupted:`` paragraph naming what is asked, and no traceback."""
    _assert_clean(rc, out, 130, "interrupted:", must_contain)


def assert_clean_error(rc: int, out: str, *must_contain: str) -> None:
    """Exit code 2, an ``error:`` paragraph naming what is asked, and no traceback."""
    _assert_clean(rc, out, 2, "error:", must_contain)


def _assert_clean(rc: int, out: str, code: int, label: str, must_contain: tuple[str, ...]) -> None:
    assert rc == code, f"exit code {rc}, output:\n{out}"
    assert "Traceback" not in out, out
    assert label in out, out
    flat = " ".join(out.split())
    for s in must_contain:
        assert s in flat or s in out, f"{s!r} not in output:\n{out}"
