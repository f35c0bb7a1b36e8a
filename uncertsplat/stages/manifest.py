"""Stage manifests: what a stage ran with, so an unchanged stage can be skipped.

``<stage output>/manifest.json`` records the stage kind, the hash of its resolved config, the hashes of
its inputs (an upstream stage's manifest hash, or a fingerprint of a user folder), the package
versions and whether it finished. A stage is skipped when a finished manifest with the same config
and input hashes exists.
"""

from __future__ import annotations

import hashlib
import json
import platform
import time
from pathlib import Path

from pydantic import BaseModel, ConfigDict

from uncertsplat import __version__
from uncertsplat.io.atomic import atomic_write_text

MANIFEST = "manifest.json"


class Manifest(BaseModel):
    """What one stage ran with and whether it finished."""

    model_config = ConfigDict(extra="forbid")

    stage: str
    name: str
    config_hash: str
    input_hashes: dict[str, str]
    config: dict
    status: str  # "running" | "done" | "failed"
    started_at: float
    finished_at: float | None = None
    seconds: float | None = None
    error: str | None = None
    versions: dict[str, str] = {}

    @property
    def key(self) -> str:
        """Hash of config and inputs: downstream stages use it as their input hash."""
        text = json.dumps({"config": self.config_hash, "inputs": self.input_hashes}, sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:16]


def hash_config(config: dict) -> str:
    return hashlib.sha256(json.dumps(config, sort_keys=True, default=str).encode()).hexdigest()[:16]


def fingerprint_folder(folder: Path, max_files: int = 100_000) -> str:
    """Hash of the relative names, sizes and mtimes of the files under ``folder`` (fast, no content read)."""
    h = hashlib.sha256()
    folder = Path(folder)
    if not folder.exists():
        return "missing"
    for i, p in enumerate(sorted(folder.rglob("*"))):
        if i >= max_files:
            break
        if p.is_file():
            st = p.stat()
            h.update(f"{p.relative_to(folder)}|{st.st_size}|{int(st.st_mtime)}\n".encode())
    return h.hexdigest()[:16]


def versions() -> dict[str, str]:
    out = {"uncertsplat": __version__, "python": platform.python_version()}
    try:
        import torch

        out["torch"] = torch.__version__
    except ImportError:  # pragma: no cover
        pass
    return out


def read_manifest(folder: Path) -> Manifest | None:
    """The manifest in ``folder``, or None when absent or unreadable (then the stage simply re-runs)."""
    path = Path(folder) / MANIFEST
    try:
        return Manifest.model_validate_json(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


def write_manifest(folder: Path, manifest: Manifest) -> None:
    atomic_write_text(Path(folder) / MANIFEST, manifest.model_dump_json(indent=2) + "\n")


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
