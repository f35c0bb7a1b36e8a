"""Stage manifests: what a stage ran with, so an unchanged stage can be skipped.

``<stage output>/manifest.json`` records the stage kind, the hash of its resolved config, the hashes of
its inputs (an upstream stage's manifest hash, or a fingerprint of a user folder), the package
versions and whether it finished. A stage is skipped when a finished manifest with the same config
and input hashes exists.
"""

from __future__ import annotations

import hashlib
import time
from collections.abc import Sequence
from pathlib import Path

from uncertsplat.errors import UserError
from uncertsplat.provenance import (  # (the last two re-exported: the stage's manifest API)
    file_sha256,
    hash_config,
    versions,
)
from uncertsplat.schemas.runs import Manifest

MANIFEST = "manifest.json"


_NOT_READ = ("*~", "*.swp", "*.swo", "*.bak", "*.orig", "*.tmp", "Thumbs.db", "desktop.ini")
"""Files no stage reads wherever they are: editors' and systems' leftovers (hidden files are skipped too)."""
_NOT_READ_AT_TOP = ("*.txt", "*.md", "*.pdf", "*.log")
"""Files no stage reads at the top of an input folder (a user's notes; COLMAP text models are under sparse/)."""


def _read_by_stages(rel: Path) -> bool:
    """Whether a file at ``rel`` in an input folder may be read by a stage: not hidden (nor in a hidden folder: the
    lock, ``reconstruct --extend``'s staging), not a leftover of ``_NOT_READ``, not a note at the top."""
    if any(part.startswith(".") for part in rel.parts):
        return False
    if any(rel.match(pattern) for pattern in _NOT_READ):
        return False
    return not (len(rel.parts) == 1 and any(rel.match(pattern) for pattern in _NOT_READ_AT_TOP))


def fingerprints(folder: Path, max_files: int = 100_000,
                 skip: Path | Sequence[Path] | None = None) -> tuple[str, str, str]:
    """(``fingerprint_folder``, the same over every file (what manifests held before 2026-11-29's thirty-eighth
    session), the names, sizes and mtimes of every file (before that day)) of ``folder`` in one pass: the pipeline takes an input
    as unchanged when a stage's manifest holds any of them. ``skip``: a folder inside ``folder`` left out (the
    command's own output folder, written there: it would change the input with every call; a pipeline's evaluation
    of a run outside it, written into the run), or several."""
    folder = Path(folder)
    if not folder.exists():
        return "missing", "missing", "missing"
    skips = [] if skip is None else [skip] if isinstance(skip, (str, Path)) else list(skip)
    top = folder.resolve()
    inside = [s for s in (Path(s).resolve() for s in skips) if top in s.parents]
    read, every, legacy = hashlib.sha256(), hashlib.sha256(), hashlib.sha256()
    for i, p in enumerate(sorted(folder.rglob("*"))):
        if i >= max_files:
            break
        if inside and any(p.resolve() == s or s in p.resolve().parents for s in inside):
            continue
        if p.is_file():
            rel = p.relative_to(folder)
            try:
                st = p.stat()
            except OSError:  # gone since the listing
                continue
            legacy.update(f"{rel}|{st.st_size}|{int(st.st_mtime)}\n".encode())
            try:
                digest = file_sha256(p)
            except OSError:  # unreadable (or gone since the listing): its size and time stand for it
                digest = f"{st.st_size}|{st.st_mtime_ns}" if p.exists() else "gone"
            line = f"{rel}|{digest}\n".encode()
            every.update(line)
            if _read_by_stages(rel):
                read.update(line)
    return read.hexdigest()[:16], every.hexdigest()[:16], legacy.hexdigest()[:16]


def fingerprint_folder(folder: Path, max_files: int = 100_000, skip: Path | Sequence[Path] | None = None) -> str:
    """Hash of the relative names and contents of the files under ``folder`` that a stage may read
    (``_read_by_stages``: not a note beside the photos, an editor's backup or a hidden file, each of which retrained
    a pipeline): a copy that did not keep the modification times (``cp -r``, a sync, a restore) is the same input
    (sha256 reads 0.9-2 GB/s: a second or two for a phone capture of 300 photos)."""
    return fingerprints(folder, max_files, skip)[0]


_NOT_OUTPUTS = ("ckpts/*", "predictive.pt", "residual.pt", MANIFEST)
"""A stage folder's files that ``stage_outputs`` leaves out: checkpoints (a later resume rotates them; the model is in
the PLY) and the evaluation's caches (rebuilt when gone), and the manifest itself."""


def stage_outputs(folder: Path, max_files: int = 10_000) -> list[str]:
    """The files a finished stage left in ``folder`` (relative paths, sorted), but for its checkpoints, caches and
    hidden files (``_NOT_OUTPUTS``; the lock) and the folders of stages inside it (their own manifest): what must
    still be there for the stage to be skipped."""
    folder = Path(folder)
    found: list[str] = []
    nested = nested_stages(folder)
    for p in sorted(folder.rglob("*")) if folder.is_dir() else ():
        rel = p.relative_to(folder)
        if not p.is_file() or any(part.startswith(".") for part in rel.parts):
            continue
        if any(n in rel.parents for n in nested):
            continue
        if any(rel.match(pattern) for pattern in _NOT_OUTPUTS):  # (matched from the right: at any depth)
            continue
        found.append(rel.as_posix())
        if len(found) >= max_files:
            break
    return found


def missing_outputs(folder: Path, manifest: Manifest, owned: set[Path] | None = None) -> list[str]:
    """The files of ``manifest.outputs`` no longer in ``folder`` (none for a manifest that recorded none), but for
    those under a subfolder another stage now owns (its own manifest: prune's ``eval/``, evaluated again by an
    evaluate stage after it, which may write other files there). ``owned``: those subfolders, when the caller has
    looked them up (``nested_stages``; a walk of the whole folder)."""
    folder = Path(folder)
    owned = nested_stages(folder) if owned is None else owned
    return [name for name in manifest.outputs if not (folder / name).is_file()
            and not any(o in Path(name).parents for o in owned)]


def resized_outputs(folder: Path, manifest: Manifest, owned: set[Path] | None = None) -> list[str]:
    """The files of ``manifest.output_sizes`` still in ``folder`` whose size is not the one the stage left (a copy cut
    short, a file truncated by a full disk while written again in place), but for those a stage nested inside now
    owns (as ``missing_outputs``). Contents are not compared: reading every map and model at each `run` would cost
    seconds where sizes cost a stat each, and a model file carries its own checksum."""
    folder = Path(folder)
    if owned is None:
        owned = nested_stages(folder) if manifest.output_sizes else set()
    found = []
    for name, size in manifest.output_sizes.items():
        path = folder / name
        if any(o in Path(name).parents for o in owned):
            continue
        try:
            now = path.stat().st_size
        except OSError:  # gone: missing_outputs names it
            continue
        if now != size:
            found.append(name)
    return found


SIZED_OUTPUTS = (".ply", ".exr", ".png", ".jpg", ".jpeg", ".pt", ".npz", ".npy", ".bin")
"""The outputs whose size ``output_sizes`` records: the files that hold the data (models, maps, figures, COLMAP
models), the same bytes whenever the stage makes them again with the same settings. Not the JSON and HTML records: a
command run again by hand with the stage's settings rewrites them with other timings (each is checked where read)."""


def output_sizes(folder: Path, names: list[str]) -> dict[str, int]:
    """{name: bytes} of the files ``names`` in ``folder`` that end in ``SIZED_OUTPUTS`` (those that cannot be read
    left out)."""
    sizes = {}
    for name in names:
        if not name.lower().endswith(SIZED_OUTPUTS):
            continue
        try:
            sizes[name] = (Path(folder) / name).stat().st_size
        except OSError:
            continue
    return sizes


def nested_stages(folder: Path) -> set[Path]:
    """The subfolders of ``folder`` (relative) that hold a stage's output of their own, by their manifest: an evaluate
    stage's ``eval/`` inside its run, a prune's evaluation once an evaluate stage owns it."""
    if not folder.is_dir():
        return set()
    return {m.parent.relative_to(folder) for m in folder.rglob(MANIFEST) if m.parent != folder}


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


def start_manifest(stage: str, name: str, config: dict, inputs: dict[str, str], keyed: dict | None = None) -> Manifest:
    """A running stage's manifest: ``config`` as the stage runs with it; ``keyed``, where given, the config its key
    hashes instead (a pipeline keys a path inside its output folder by the stage that made it, not where it lies)."""
    return Manifest(
        stage=stage,
        name=name,
        config_hash=hash_config(config if keyed is None else keyed),
        input_hashes=inputs,
        config=config,
        status="running",
        started_at=time.time(),
        versions=versions(),
    )


__all__ = ["MANIFEST", "Manifest", "fingerprint_folder", "fingerprints", "hash_config", "missing_outputs", "nested_stages",
           "output_sizes", "read_manifest", "resized_outputs", "stage_outputs", "start_manifest", "versions",
           "write_manifest"]
