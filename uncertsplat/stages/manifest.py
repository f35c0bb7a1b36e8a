"""Stage manifests: what a stage ran with, so an unchanged stage can be skipped.

``<stage output>/manifest.json`` records the stage kind, the hash of its resolved config, the hashes of
its inputs (an upstream stage's manifest hash, or a fingerprint of a user folder), the package
versions and whether it finished. A stage is skipped when a finished manifest with the same config
and input hashes exists.
"""

from __future__ import annotations

import hashlib
import time
from pathlib import Path

from uncertsplat.errors import UserError
from uncertsplat.provenance import (  # (the last two re-exported: the stage's manifest API)
    file_sha256,
    hash_config,
    versions,
)
from uncertsplat.schemas.runs import Manifest

MANIFEST = "manifest.json"


def fingerprint_folder(folder: Path, max_files: int = 100_000, *, legacy: bool = False) -> str:
    """Hash of the relative names and contents of the files under ``folder``: a copy that did not keep the
    modification times (``cp -r``, a sync, a restore) is the same input (sha256 reads 0.9-2 GB/s: a second or two
    for a phone capture of 300 photos). ``legacy``: the hash of names, sizes and mtimes that manifests written before
    2026-11-29 hold, which the pipeline still accepts as unchanged."""
    h = hashlib.sha256()
    folder = Path(folder)
    if not folder.exists():
        return "missing"
    for i, p in enumerate(sorted(folder.rglob("*"))):
        if i >= max_files:
            break
        if p.is_file():
            if legacy:
                st = p.stat()
                h.update(f"{p.relative_to(folder)}|{st.st_size}|{int(st.st_mtime)}\n".encode())
            else:
                try:
                    digest = file_sha256(p)
                except OSError:  # unreadable (or gone since the listing): its size and time stand for it
                    st = p.stat() if p.exists() else None
                    digest = f"{st.st_size}|{st.st_mtime_ns}" if st is not None else "gone"
                h.update(f"{p.relative_to(folder)}|{digest}\n".encode())
    return h.hexdigest()[:16]


def read_manifest(folder: Path) -> Manifest | None:
    """The manifest in ``folder``, or None when absent or unreadable (then the stage simply re-runs)."""
    try:
        return Manifest.read_optional(Path(folder) / MANIFEST)
    except UserError:
        # a manifest is a cache key: one that cannot be read (damaged, an unknown version) only means the
        # stage is run again, which rewrites it
        return None


def write_manifest(folder: Path, manifest: Manifest) -> None:
    manifest.write(Path(folder) / MANIFEST)


def start_manifest(stage: str, name: str, config: dict, inputs: dict[str, str]) -> Manifest:
    return Manifest(
        stage=stage,
        name=name,
        config_hash=hash_config(config),
        input_hashes=inputs,
        config=config,
        status="running",
        started_at=time.time(),
        versions=versions(),
    )


__all__ = ["MANIFEST", "Manifest", "fingerprint_folder", "hash_config", "read_manifest", "start_manifest", "versions",
           "write_manifest"]
