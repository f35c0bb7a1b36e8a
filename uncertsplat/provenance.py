"""What a result was computed with: the hash of a resolved config, of a file, and the package versions.

Recorded in ``manifest.json`` (pipeline stages), ``metrics.json`` (``evaluate``) and used as the
identity of sweep points. Foundation layer: imports nothing of uncertsplat but its version, so the
evaluation engine, the sweep and the stages can all use it.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import platform
from pathlib import Path

from uncertsplat import __version__


def file_sha256(path: str | Path) -> str:
    """The SHA-256 of a file's bytes (hex), read in 1 MiB blocks. Kept for the process by the file's identity (path,
    inode, size, modification time): a scan that fingerprints photos and then compares the same photos for copies
    reads each once."""
    st = os.stat(path)
    return _sha256_of(str(Path(path).resolve()), st.st_ino, st.st_size, st.st_mtime_ns)


@functools.lru_cache(maxsize=4096)
def _sha256_of(path: str, inode: int, size: int, mtime_ns: int) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def hash_config(config: dict) -> str:
    """A short, order-independent hash of a config dict (its JSON with sorted keys)."""
    return hashlib.sha256(json.dumps(config, sort_keys=True, default=str).encode()).hexdigest()[:16]


@functools.lru_cache(maxsize=1)
def source_fingerprint() -> str:
    """A short hash of this installation's own code (every ``.py``, ``.cpp`` and ``.h`` file of the package, with
    its path): two builds that share a version number but not their code (a checkout between releases, an edited
    install) are told apart. A helper's ``Predictor.load`` read a pixel noise and std factor that an older build had
    fitted (the same version string), and rendered maps 0.045 off the evaluation's; with the fingerprint among the
    ``versions`` it fits them again, as ``evaluate`` then does. About 5 ms, once a process."""
    return fingerprint_of(Path(__file__).resolve().parent)


def fingerprint_of(root: Path) -> str:
    """``source_fingerprint`` of the code under ``root``: 12 hex digits of the SHA-256 of every ``.py``, ``.cpp`` and
    ``.h`` file's path and bytes (``__pycache__`` left out; an unreadable file by its name alone)."""
    h = hashlib.sha256()
    for path in sorted(root.rglob("*")):
        if path.suffix in (".py", ".cpp", ".h") and "__pycache__" not in path.parts and path.is_file():
            try:
                data = path.read_bytes()
            except OSError:  # unreadable, or gone while walked: its name still counts
                data = b"?"
            h.update(path.relative_to(root).as_posix().encode() + b"\0" + data)
    return h.hexdigest()[:12]


def versions() -> dict[str, str]:
    """Versions of uncertsplat (and ``source_fingerprint``, its code's), Python and torch (when importable)."""
    out = {"uncertsplat": __version__, "source": source_fingerprint(), "python": platform.python_version()}
    try:
        import torch

        out["torch"] = torch.__version__
    except ImportError:  # pragma: no cover
        pass
    return out


__all__ = ["hash_config", "source_fingerprint", "versions"]
