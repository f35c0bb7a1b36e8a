"""Write failures: a full disk, a file-size limit, a read-only or forbidden folder.

We run as root in CI, so chmod cannot make a folder read-only; the failures are injected instead (the
OSError raised at the exact call: the data write, fsync, the rename, the temp-file creation), plus one real
OS-level failure: a subprocess with a file-size limit (RLIMIT_FSIZE) gets EFBIG from the kernel.
Every case must end in a clear error naming the file, the previous version of the file intact, and no
temp file left behind.
"""

from __future__ import annotations

import errno
import json
import os
import resource
import shutil
import signal
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.fixtures import tiny_scene_path  # noqa: F401
from tests.reliability.helpers import (
    FAST,
    WAIT_S,
    assert_clean_error,
    cli_args,
    env,
    logged_steps,
    temp_leftovers,
)
from uncertsplat.errors import UserError
from uncertsplat.io import atomic

ERRNOS = [errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS, errno.EACCES, errno.EIO]


def _raiser(code):
    def f(*a, **k):
        raise OSError(code, os.strerror(code))

    return f


class _FailingFile:
    """A file object whose write fails after ``ok`` bytes, like a disk filling up mid-file."""

    def __init__(self, f, code, ok=100):
        self.f, self.code, self.ok = f, code, ok

    def write(self, b):
        if self.ok <= 0:
            raise OSError(self.code, os.strerror(self.code))
        n = self.f.write(b[: self.ok])
        self.ok -= n
        if n < len(b):
            raise OSError(self.code, os.strerror(self.code))
        return n

    def __getattr__(self, k):
        return getattr(self.f, k)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.f.close()


@pytest.mark.parametrize("code", ERRNOS, ids=errno.errorcode.get)
@pytest.mark.parametrize("where", ["data", "fsync", "rename", "mkstemp"])
def test_atomic_write_failure_is_clear_and_leaves_the_old_file(tmp_path, monkeypatch, code, where):
    target = tmp_path / "sub" / "metrics.json"
    atomic.atomic_write_json(target, {"old": 1})
    if where == "fsync":
        monkeypatch.setattr(atomic.os, "fsync", _raiser(code))
    elif where == "rename":
        monkeypatch.setattr(atomic.os, "replace", _raiser(code))
    elif where == "mkstemp":
        monkeypatch.setattr(atomic.tempfile, "mkstemp", _raiser(code))
    with pytest.raises(UserError) as err:
        if where == "data":
            atomic.atomic_write(target, lambda f: _FailingFile(f, code).write(b"x" * 10_000))
        else:
            atomic.atomic_write_json(target, {"new": 2})
    monkeypatch.undo()
    text = str(err.value)
    assert str(target) in text or str(target.parent) in text
    if code == errno.ENOSPC and where != "mkstemp":
        assert "disk is full" in text
    assert json.loads(target.read_text(encoding="utf-8")) == {"old": 1}
    assert not temp_leftovers(tmp_path)


@pytest.mark.parametrize("where", ["rename", "fsync"])
def test_image_write_failure_is_clear(tmp_path, monkeypatch, where):
    from uncertsplat.io import atomic, images

    target = tmp_path / "maps" / "view.png"
    images.write_png(target, np.zeros((4, 4, 3)))
    before = target.read_bytes()
    # image writes go through io.atomic.atomic_write_via
    monkeypatch.setattr(atomic.os, "replace" if where == "rename" else "fsync", _raiser(errno.ENOSPC))
    with pytest.raises(UserError, match="disk is full") as err:
        images.write_png(target, np.ones((4, 4, 3)))
    monkeypatch.undo()
    assert str(target) in str(err.value)
    assert target.read_bytes() == before
    assert not temp_leftovers(tmp_path)


def test_real_file_size_limit_on_image_and_checkpoint_writes(tmp_path):
    """The kernel refuses writes past RLIMIT_FSIZE (EFBIG): a real write failure, not a mock."""
    from uncertsplat.io import images
    from uncertsplat.io.checkpoints import save_checkpoint

    old_limit = resource.getrlimit(resource.RLIMIT_FSIZE)
    old_handler = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    save_checkpoint(tmp_path, 1, {"x": torch.zeros(10)})
    try:
        resource.setrlimit(resource.RLIMIT_FSIZE, (20_000, old_limit[1]))
        with pytest.raises(UserError, match="cannot write the image|could not write the image") as err:
            images.write_exr(tmp_path / "big.exr", {"R": np.random.default_rng(0).random((200, 200))})
        assert "big.exr" in str(err.value)
        with pytest.raises(UserError, match="could not write the file") as err:
            save_checkpoint(tmp_path, 2, {"x": torch.randn(100_000)})
        assert "step_000002.pt" in str(err.value)
        # torch.save into a file (evaluate's residual.pt) reports the failed write as a RuntimeError
        from uncertsplat.io.atomic import atomic_write

        with pytest.raises(UserError, match="could not write the file: File too large") as err:
            atomic_write(tmp_path / "residual.pt", lambda f: torch.save({"x": torch.randn(100_000)}, f))
        assert "residual.pt" in str(err.value)
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, old_limit)
        signal.signal(signal.SIGXFSZ, old_handler)
    assert not (tmp_path / "big.exr").exists() and not (tmp_path / "ckpts" / "step_000002.pt").exists()
    assert not temp_leftovers(tmp_path)
    from uncertsplat.io.checkpoints import list_checkpoints, load_checkpoint

    assert [s for s, _ in list_checkpoints(tmp_path)] == [1]
    load_checkpoint(list_checkpoints(tmp_path)[0][1])


def test_disk_full_during_training_then_resume_loses_nothing(tiny_scene_path, tmp_path, monkeypatch):
    """ENOSPC while writing the step-4 checkpoint: clear error; after 'freeing space' --resume finishes, and
    nothing is lost: it ends bit-identical to an uninterrupted run (CPU), optimizer moments included."""
    from tests.reliability.test_corruption import small_config
    from uncertsplat.stages import train

    run = tmp_path / "run"
    real = os.replace

    def replace(src, dst, *a, **k):
        if Path(dst).name == "step_000004.pt":
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real(src, dst, *a, **k)

    monkeypatch.setattr(atomic.os, "replace", replace)
    with pytest.raises(UserError, match="disk is full") as err:
        train.run(tiny_scene_path, run, small_config(), device=torch.device("cpu"))
    monkeypatch.undo()
    assert "step_000004.pt" in str(err.value)
    assert not temp_leftovers(run) and not (run / ".lock").exists()
    assert sorted(p.name for p in (run / "ckpts").iterdir()) == ["step_000002.pt"]
    train.run(tiny_scene_path, run, small_config(), device=torch.device("cpu"), resume=True)
    assert logged_steps(run) == [1, 2, 3, 4, 5, 6]
    assert (run / "variational.ply").is_file() and (run / "train_summary.json").is_file()

    # the resume from step 2 must restore everything (parameters, Adam moments, generators): the final
    # parameters equal those of a run never interrupted
    from uncertsplat.io.ply import read_variational_ply

    ref = tmp_path / "ref"
    train.run(tiny_scene_path, ref, small_config(), device=torch.device("cpu"))
    a, _ = read_variational_ply(run / "variational.ply")
    b, _ = read_variational_ply(ref / "variational.ply")
    assert a.parameters().keys() == b.parameters().keys()
    for name, p in a.parameters().items():
        assert torch.equal(p, b.parameters()[name]), name


def test_disk_full_on_the_training_log(tiny_scene_path, tmp_path, monkeypatch):
    from tests.reliability.test_corruption import small_config
    from uncertsplat.stages import train
    from uncertsplat.train import trainer

    calls = {"n": 0}

    def failing_open(path, mode="r", *a, **k):
        f = open(path, mode, *a, **k)
        if Path(path).name == "stats.jsonl" and "a" in mode:
            calls["n"] += 1
            if calls["n"] == 3:
                return _FailingFile(f, errno.ENOSPC, ok=10)
        return f

    monkeypatch.setattr(trainer, "open", failing_open, raising=False)
    with pytest.raises(UserError, match="stats.jsonl") as err:
        train.run(tiny_scene_path, tmp_path / "run", small_config(), device=torch.device("cpu"))
    assert "--resume" in str(err.value)


def test_cli_with_a_file_size_limit_fails_cleanly_and_resumes(tiny_scene_path, tmp_path):
    """A real subprocess whose checkpoints do not fit under the file-size limit: exit 2, one paragraph."""
    run = tmp_path / "run"
    args = cli_args("train", tiny_scene_path, "-o", run, *FAST, "--set", "iterations=4",
                    "--set", "checkpoint_every=2")

    def limit():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (30_000, resource.RLIM_INFINITY))

    proc = subprocess.run(args, env=env(), capture_output=True, text=True, timeout=WAIT_S, preexec_fn=limit)
    # its advice is the command that works: run again without --resume, the folder (config.json) is refused
    assert_clean_error(proc.returncode, proc.stderr, "could not write the file", "step_000002.pt",
                       "then run the same command again with --resume")
    assert not temp_leftovers(run) and not (run / ".lock").exists()
    assert not (run / "ckpts").exists() or not any((run / "ckpts").iterdir())
    ok = subprocess.run(args + ["--resume"], env=env(), capture_output=True, text=True, timeout=WAIT_S)
    assert ok.returncode == 0, ok.stderr
    assert logged_steps(run) == [1, 2, 3, 4]
    shutil.rmtree(run)
