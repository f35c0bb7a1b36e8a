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


def versions() -> dict[str, str]:
    """Versions of uncertsplat, Python and torch (when importable)."""
    out = {"uncertsplat": __version__, "python": platform.python_version()}
    try:
        import torch

        out["torch"] = torch.__version__
    except ImportError:  # pragma: no cover
        pass
    return out


__all__ = ["hash_config", "versions"]
