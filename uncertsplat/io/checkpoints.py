"""Full-state training checkpoints: atomic, checksummed, with fallback to the previous good one.

File layout of ``RUN/ckpts/step_{N:06d}.pt``::

    b"USPLCKPT"  (8 bytes)  | format version (4 bytes, little endian) | SHA-256 of the payload (32 bytes)
    payload: torch.save() of a dict of tensors / numbers / strings (loaded with weights_only=True)

A truncated or corrupted file fails the checksum and is reported, and ``load_latest`` falls back to
the previous checkpoint. Loading a run for rendering (its PLY or newest checkpoint, config and scene)
is ``baselines.load_run``'s. Files are written through ``io.atomic`` (temp file, fsync, rename), so a crash
while saving never leaves a half-written file under the final name.
"""

from __future__ import annotations

import hashlib
import io
import re
import struct
from pathlib import Path

import torch

from uncertsplat.console import console, q
from uncertsplat.errors import UserError
from uncertsplat.io.atomic import atomic_write_bytes

MAGIC = b"USPLCKPT"
VERSION = 1
_HEADER = len(MAGIC) + 4 + 32
_NAME = re.compile(r"^step_(\d+)\.pt$")


class CorruptCheckpoint(UserError):
    """A checkpoint file that is truncated, corrupted or of an unknown format."""


def checkpoint_dir(run_dir: str | Path) -> Path:
    return Path(run_dir) / "ckpts"


def checkpoint_path(run_dir: str | Path, step: int) -> Path:
    return checkpoint_dir(run_dir) / f"step_{step:06d}.pt"


def unfinished_training(step: int, total: int, scene: str | Path | None, run_dir: str | Path) -> str:
    """How every command says a run's model is a training checkpoint before its last step: the one text of the
    report's note and of the warning of the commands that load the run (they said it in two texts)."""
    return (f"training is not finished: its newest checkpoint is step {step} of {total} (`uncertsplat train "
            f"{q(scene) if scene is not None else 'SCENE'} -o {q(run_dir)} --resume` finishes it)")


def list_checkpoints(run_dir: str | Path) -> list[tuple[int, Path]]:
    """(step, path) of every checkpoint file in ``RUN/ckpts``, oldest first."""
    folder = checkpoint_dir(run_dir)
    if not folder.is_dir():
        return []
    out = []
    for p in folder.iterdir():
        m = _NAME.match(p.name)
        if m and p.is_file():
            out.append((int(m.group(1)), p))
    return sorted(out)


def encode(state: dict) -> bytes:
    buf = io.BytesIO()
    torch.save(state, buf)
    payload = buf.getvalue()
    return MAGIC + struct.pack("<I", VERSION) + hashlib.sha256(payload).digest() + payload


def decode(data: bytes, path: Path | None = None, map_location=None) -> dict:
    """Inverse of ``encode``; raises ``CorruptCheckpoint`` when the bytes are not a valid checkpoint."""
    if len(data) < _HEADER or data[: len(MAGIC)] != MAGIC:
        raise CorruptCheckpoint("not an uncertsplat checkpoint (bad header or empty file)", path=path)
    (version,) = struct.unpack("<I", data[len(MAGIC): len(MAGIC) + 4])
    if version != VERSION:
        raise CorruptCheckpoint(f"checkpoint format {version} is not supported (expected {VERSION})", path=path)
    digest = data[len(MAGIC) + 4: _HEADER]
    payload = data[_HEADER:]
    if hashlib.sha256(payload).digest() != digest:
        raise CorruptCheckpoint("checksum mismatch: the file is truncated or corrupted", path=path)
    return torch.load(io.BytesIO(payload), map_location=map_location, weights_only=True)


def save_checkpoint(run_dir: str | Path, step: int, state: dict, keep: int = 3) -> Path:
    """Write ``state`` as ``RUN/ckpts/step_{step:06d}.pt`` atomically; keep only the newest ``keep`` files."""
    path = atomic_write_bytes(checkpoint_path(run_dir, step), encode(state))
    for _, old in list_checkpoints(run_dir)[:-keep] if keep > 0 else []:
        if old != path:
            old.unlink(missing_ok=True)
    return path


def load_checkpoint(path: str | Path, map_location=None) -> dict:
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as err:
        raise CorruptCheckpoint(f"cannot read the checkpoint ({err.strerror})", path=path) from None
    try:
        return decode(data, path, map_location)
    except CorruptCheckpoint:
        raise
    except Exception as err:  # an unpickling error despite a good checksum: a foreign or newer file
        raise CorruptCheckpoint(f"cannot load the checkpoint ({type(err).__name__}: {err})", path=path) from None


def load_latest(run_dir: str | Path, map_location=None) -> tuple[Path, dict] | None:
    """The newest checkpoint that loads, falling back (with a message) past corrupted ones; None if none."""
    for _step, path in reversed(list_checkpoints(run_dir)):
        try:
            return path, load_checkpoint(path, map_location)
        except CorruptCheckpoint as err:
            console.print(f"[yellow]warning:[/] {err}; trying the previous checkpoint")
    return None
