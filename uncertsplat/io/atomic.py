"""Atomic file writes and run-folder locks.

A write goes to a temporary file in the same folder, is flushed and fsync'ed, then renamed over the
target, so a crash or a full disk never leaves a half-written file under the final name.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import re
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO

from uncertsplat.errors import UserError, WriteFailed


def _fsync_dir(folder: Path) -> None:
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


_UMASK = os.umask(0)
os.umask(_UMASK)


def current_umask() -> int:
    """The process's file-creation mask (read once at import): what a folder made by ``mkdtemp`` (0700) is
    chmod-ed by to get the permissions any other output has."""
    return _UMASK


def temp_folder(prefix: str, parent: Path) -> Path:
    """A new folder in ``parent`` (``tempfile.mkdtemp``) with the permissions the process's other outputs get: one
    that is renamed into place as an output would otherwise stay 0700, unreadable to other users of a shared
    disk."""
    tmp = Path(tempfile.mkdtemp(prefix=prefix, dir=parent))
    os.chmod(tmp, 0o777 & ~current_umask())
    return tmp


TEMP_STEM = 100
"""The most characters of a file's or folder's name its temporary sibling's name keeps (``temp_stem``)."""


def temp_stem(name: str) -> str:
    """``name`` as a temporary sibling's name holds it: whole up to ``TEMP_STEM`` characters, else its start and a
    hash of the whole (a legal name of 220-255 characters made ``.NAME.XXXXXXXX.tmp`` longer than a file system's 255,
    and the write ended in a traceback after the work was done)."""
    if len(name) <= TEMP_STEM:
        return name
    import hashlib

    return name[:TEMP_STEM - 9] + "~" + hashlib.sha256(name.encode()).hexdigest()[:8]


_SPACE_ERRNOS = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)
"""The write failures that freeing space (or raising a quota, or a file-size limit) cures."""


def atomic_write_via(path: str | Path, write_tmp: Callable[[str], None], *, what: str = "file") -> Path:
    """Write a file atomically through a writer that takes a file *name* (e.g. OpenImageIO).

    ``write_tmp(tmp_name)`` creates the file under a temporary name in the same folder, with the same
    extension (so format-sniffing writers pick the right format); it is fsync'ed and renamed over
    ``path``. On any failure the temp file is removed.

    Raises:
        UserError: when the folder is not writable or the disk is full.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{temp_stem(path.stem)}.", suffix=f".tmp{path.suffix[:16]}",
                                   dir=path.parent)
        os.close(fd)
    except OSError as err:
        space = err.errno in _SPACE_ERRNOS
        raise WriteFailed(f"cannot write here ({err.strerror})", path=path.parent, space=space,
                          hint="Free some space, then run again." if space else
                          "Choose an output folder you can write to.") from None
    try:
        write_tmp(tmp)
        os.chmod(tmp, 0o666 & ~_UMASK)  # mkstemp creates 0600; give the file the usual permissions
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as err:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        os_err = _os_error(err)
        if os_err is not None:
            why = "the disk is full" if os_err.errno == errno.ENOSPC else (os_err.strerror or str(os_err))
            raise WriteFailed(f"could not write the {what}: {why}; nothing was left half-written", path=path,
                              hint="Free some space or choose another output folder, then run again.",
                              space=os_err.errno in _SPACE_ERRNOS) from None
        raise
    _fsync_dir(path.parent)
    return path


def _os_error(err: BaseException) -> OSError | None:
    """``err`` when it is an OSError; for a RuntimeError, the OSError it was raised from or during (torch.save
    reports a full disk as a RuntimeError whose context is the file's OSError); else None (a Ctrl-C stays one)."""
    if isinstance(err, OSError):
        return err
    if isinstance(err, RuntimeError):
        inner = err.__cause__ or err.__context__
        return inner if isinstance(inner, OSError) else None
    return None


def atomic_write(path: str | Path, writer: Callable[[IO[bytes]], None]) -> Path:
    """Write a file atomically: ``writer`` receives a binary file object open on a temp file.

    Raises:
        UserError: when the folder is not writable or the disk is full (the temp file is removed).
    """

    def write_tmp(tmp: str) -> None:
        with open(tmp, "wb") as f:
            writer(f)

    return atomic_write_via(path, write_tmp)


def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    return atomic_write(path, lambda f: f.write(data))


def atomic_write_text(path: str | Path, text: str) -> Path:
    return atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: str | Path, obj) -> Path:
    return atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=False, default=str) + "\n")


def read_json(path: str | Path, hint: str | None = None):
    """Parse a JSON file we wrote; a missing, truncated or corrupted file is a ``UserError`` naming it (``hint``: what
    to do, where re-running the stage that wrote it would not write it again)."""
    path = Path(path)
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        why = err.strerror if isinstance(err, OSError) else f"not valid JSON: {err}"
        raise UserError(f"cannot read the file ({why}); it may be truncated or corrupted", path=path,
                        hint=hint or "Restore it from a copy, or re-run the stage that wrote it.") from None


# the temp names of atomic_write (".NAME.XXXXXXXX.tmp") and of io.images (".STEM.XXXXXXXX.tmp.EXT")
_TEMP_NAME = re.compile(r"^\..+\.[A-Za-z0-9_]{8}\.tmp(\.[A-Za-z0-9]+)?$")


def remove_stale_temp_files(*folders: str | Path) -> list[Path]:
    """Delete the temp files that a killed writer left in ``folders`` (not recursive); returns them.

    Only call this while holding the folder's ``run_lock``: then no live process is writing there.
    """
    removed = []
    for folder in folders:
        folder = Path(folder)
        if not folder.is_dir():
            continue
        for p in folder.iterdir():
            if _TEMP_NAME.match(p.name) and p.is_file():
                with contextlib.suppress(OSError):
                    p.unlink()
                    removed.append(p)
    return removed


_HELD: dict[str, int] = {}  # locks this process holds (re-entering one is allowed), by resolved path


@contextlib.contextmanager
def staging_folder(out: str | Path, prefix: str) -> Iterator[Path]:
    """``out / f"{prefix}{pid}"``, a folder to write a stage's outputs into before they are put in place, removed at
    the end with whatever is left in it (put in place, they are gone from it). Folders of ``prefix`` found first are a
    killed run's and removed: call it under the output's lock (``run_lock``)."""
    import shutil

    out = Path(out)
    for stale in out.glob(f"{prefix}*"):
        shutil.rmtree(stale, ignore_errors=True)
    staging = out / f"{prefix}{os.getpid()}"
    try:
        yield staging
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def _holder(lock: Path) -> str:
    """How a lock's holder is named in every message: "PID 123, train" (what its file says; "unknown" unreadable)."""
    try:
        pid, _, cmd = " ".join(lock.read_text(encoding="utf-8").split()[:2]).partition(" ")
    except OSError:
        pid, cmd = "", ""
    return f"PID {pid or 'unknown'}{', ' + cmd if cmd else ''}"


def lock_holder(folder: str | Path) -> str | None:
    """"PID n, command" of the live process that holds ``folder``'s ``run_lock``, or None when none does: for a reader
    of the folder (``prune`` reads its source run) that must not start while a writer changes it, and need not lock
    it itself (two readers do not exclude each other, and a read-only folder can be read). Creates nothing."""
    import fcntl

    lock = Path(folder) / ".lock"
    if str(lock.resolve()) in _HELD:  # (this process)
        return None
    try:
        fd = os.open(lock, os.O_RDONLY)
    except OSError:  # no lock file (or none we may open): nobody holds it
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except OSError as err:
        return _holder(lock) if err.errno in (errno.EWOULDBLOCK, errno.EACCES) else None
    finally:
        os.close(fd)
    return None


def check_output_folder(folder: str | Path) -> None:
    """Refuse an output folder that is a file, or lies under one (a command says so before its work, and
    ``run_lock`` before it makes the folder).

    Raises:
        UserError: naming the file.
    """
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise UserError("the output path is a file, not a folder", path=folder, hint="Choose another output folder (-o).")
    file = next((p for p in folder.parents if p.exists() and not p.is_dir()), None)
    if file is not None:
        raise UserError(f"cannot create the folder: {file} is a file, not a folder", path=folder,
                        hint="Choose another output folder (-o).")


@contextlib.contextmanager
def run_lock(folder: str | Path, command: str = "uncertsplat") -> Iterator[Path]:
    """Hold ``folder/.lock`` (holding our PID) for the duration; refuse when a live process holds it.

    The lock is an ``flock`` on that file, which the kernel releases when its process dies: a lock left by
    a dead (even SIGKILLed) process is simply taken over, and two processes racing for a stale lock cannot
    both win (the PID-file-only scheme had that race, and an empty file mid-creation looked stale).
    """
    import fcntl

    folder = Path(folder)
    created = not folder.exists()
    check_output_folder(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise UserError(f"cannot create the folder ({err.strerror})", path=folder,
                        hint="Choose an output folder you can write to.") from None
    lock = folder / ".lock"
    key = str(lock.resolve())
    if key in _HELD:  # this process already holds it (a stage run inside another on the same folder)
        _HELD[key] += 1
        try:
            yield lock
        finally:
            _HELD[key] -= 1
        return
    while True:
        try:
            fd = os.open(lock, os.O_CREAT | os.O_RDWR, 0o644)
        except OSError as err:
            if created:  # (as when the command fails later: no empty folder left behind)
                with contextlib.suppress(OSError):
                    folder.rmdir()
            # (a read-only or immutable folder, e.g. EPERM under `chattr +i`: the other write errors say what to do)
            raise UserError(f"cannot write here ({err.strerror})", path=folder,
                            hint="Make the folder writable, or write elsewhere: an output folder you can write to "
                                 "(-o), or a copy of the run for a command that writes into it (evaluate, "
                                 "select-views, train --resume); then run again.") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as err:
            os.close(fd)
            if err.errno not in (errno.EWOULDBLOCK, errno.EACCES):
                raise UserError(f"cannot lock the folder ({err.strerror})", path=folder) from None
            raise UserError(
                f"another uncertsplat process ({_holder(lock)}) is writing to this folder",
                path=folder,
                hint="Wait for it to finish (or stop it), then run this again; a command that writes its own output "
                     "can be given another output folder instead.",
            ) from None
        try:  # a holder may have released (unlinked) the file between our open and flock: lock the current one
            same = os.fstat(fd).st_ino == os.stat(lock).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    os.ftruncate(fd, 0)
    os.write(fd, f"{os.getpid()} {command}\n".encode())
    _HELD[key] = 1
    try:
        yield lock
    finally:
        del _HELD[key]
        with contextlib.suppress(FileNotFoundError):
            lock.unlink()
        os.close(fd)
        if created:  # a command that failed before writing anything leaves no empty folder behind
            with contextlib.suppress(OSError):
                folder.rmdir()
