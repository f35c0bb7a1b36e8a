"""The pixel noise a model leaves on its training views, fitted once per model and settings (``RUN/eval/residual.pt``).

``evaluate`` and ``prune`` both need the pixel noise of the model's Gaussians (``eval.engine.fit_residual``: a
render of up to 64 training views, with the resolution term's renders and the edge term's fit; about half of
``evaluate``'s time on the demo run). It depends only on the model file, the run's ``config.json`` and
``scene.json``, the settings ``eval.engine.RESIDUAL_SETTINGS`` names, the device type and the versions, so
``evaluate`` keeps it beside its maps with a key of all of those, and the next ``evaluate`` or ``prune`` of the same
model with the same settings reads it instead of fitting it again. A file whose key differs, or that cannot be read,
is ignored (the noise is fitted afresh). ``prune`` only reads it: the input run is never modified.
"""

from __future__ import annotations

import hashlib
import json
import time
from collections.abc import Callable
from pathlib import Path

import torch

from uncertsplat.types import ViewSet

FILE_NAME = "residual.pt"



def run_digests(loaded) -> dict | None:
    """{"model", "config", "scene"}: the SHA-256 of ``loaded``'s (a ``baselines.LoadedRun``) model file and of its
    run's ``config.json`` and ``scene.json`` (None for a run without one), and "masks" where the photos have their
    own (``sfm.scene.run_mask_digest``), what a kept fit of the run is keyed by (here and ``predictive_cache``); None
    when the model is not one file (an ensemble) or a file cannot be read."""
    from uncertsplat.provenance import file_sha256
    from uncertsplat.sfm.scene import run_mask_digest

    source, run_dir = Path(loaded.source), Path(loaded.run_dir)
    try:
        if not source.is_file():
            return None
        out = {
            "model": file_sha256(source),
            "config": hashlib.sha256((run_dir / "config.json").read_bytes()).hexdigest(),
            "scene": hashlib.sha256((run_dir / "scene.json").read_bytes()).hexdigest()
            if (run_dir / "scene.json").is_file() else None,
        }
    except OSError:
        return None
    masks = run_mask_digest(run_dir)  # the noise is fitted inside the training photos' masks: other masks, another fit
    return out if masks is None else {**out, "masks": masks}


def residual_key(loaded, cfg, device: torch.device, set_aside: bool = False) -> str | None:
    """The key of the pixel noise ``fit_residual`` would fit for ``loaded`` (a ``baselines.LoadedRun``) with
    ``cfg``: a SHA-256 over the model file, the run's config and scene files (``run_digests``), the settings it
    reads, the device type and the versions (and, with ``set_aside``: views set aside from training, where the
    noise's level is fitted given the rest of the predictive, the settings that shape it). None when the model is not
    one file (an ensemble) or a file cannot be read."""
    from uncertsplat.eval.engine import RESIDUAL_FIT
    from uncertsplat.provenance import versions

    digests = run_digests(loaded)
    if digests is None:
        return None
    parts = {**digests, "settings": _settings(cfg, set_aside), "fit": RESIDUAL_FIT, "device": device.type,
             "versions": versions()}
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()


def _settings(cfg, set_aside: bool) -> dict:
    """The evaluation settings the pixel noise's fit reads (with ``set_aside``: and those that shape it there)."""
    from uncertsplat.eval.engine import RESIDUAL_SET_ASIDE_SETTINGS, RESIDUAL_SETTINGS

    return {k: getattr(cfg, k) for k in RESIDUAL_SETTINGS + (RESIDUAL_SET_ASIDE_SETTINGS if set_aside else ())}


def same_residual_settings(a, b, set_aside: bool = False) -> bool:
    """Whether the evaluation settings ``a`` and ``b`` fit the same pixel noise (the settings ``residual_key`` reads,
    with ``set_aside`` as there)."""
    return _settings(a, set_aside) == _settings(b, set_aside)


def fitted_residual(loaded, scene_scale: float, train_indices, cfg, device: torch.device, *,
                    load_views: Callable[[list[int]], ViewSet], write: bool, calibration_indices=(),
                    set_aside_maps: dict | None = None):
    """The pixel noise of ``loaded``'s model (``eval.engine.fit_residual``), read from ``RUN/eval/residual.pt``
    when that file was written for the same key (``residual_key``), else fitted; with ``write``, a fitted field is
    kept there for the next evaluation. None when ``cfg.residual_views`` is 0 or there is no training view.
    ``calibration_indices``: views set aside from training and ``set_aside_maps`` (filled only when the noise is
    fitted here): as ``fit_residual``'s."""
    from uncertsplat.console import console, count
    from uncertsplat.eval.engine import fit_residual, residual_from_state, residual_indices
    from uncertsplat.io.atomic import atomic_write_bytes
    from uncertsplat.io.checkpoints import decode, encode

    sampler = loaded.sampler(scene_scale, device)
    key = residual_key(loaded, cfg, device, set_aside=len(calibration_indices) > 0)
    path = Path(loaded.run_dir) / "eval" / FILE_NAME
    if key is not None and path.is_file():
        try:
            data = decode(path.read_bytes(), path, map_location="cpu")
            if isinstance(data, dict) and data.get("key") == key:
                field = residual_from_state(sampler, data["state"], device)
                console.print(f"pixel noise: read from {path} (fitted earlier for this model and these settings)")
                return field
        except Exception:  # noqa: BLE001 - damaged (checksum), of the unchecked older format, or another model's: fit
            pass  # it again (and replace it below)
    views = len(residual_indices(train_indices, cfg))
    t0 = time.perf_counter()
    with console.status(f"fitting the pixel noise on {views} training views"):
        field = fit_residual(sampler, train_indices, cfg, device, load_views=load_views,
                             calibration_indices=calibration_indices, set_aside_maps=set_aside_maps)
    if field is not None:
        console.print(f"pixel noise: fitted on {count(views, 'training view')} in {time.perf_counter() - t0:.1f} s")
    if write and key is not None and field is not None:
        state = {"key": key, "state": field.state()}
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(path, encode(state))  # checksummed as a checkpoint: a flipped bit is found, not used
    return field


def _model_of(run_dir: Path, model_file: str):
    """What ``run_digests`` reads of a ``baselines.LoadedRun``: its model file and run folder."""
    from types import SimpleNamespace

    return SimpleNamespace(source=Path(run_dir) / model_file, run_dir=Path(run_dir))


def rekeyed_residual(data: bytes, source: Path, run_dir: Path, model_file: str, cfg, device: torch.device) -> bytes | None:
    """``RUN/eval/residual.pt``'s bytes ``data`` of the run ``source``, keyed for ``run_dir``, whose ``model_file`` and
    ``config.json`` are the source's byte for byte (a prune that removed nothing: its scene.json differs in the
    scene's path, its key with it, and the copy evaluate made was never read); None when the file is not the noise of
    the source's ``model_file`` under ``cfg`` (the settings of the evaluation it was copied with) on ``device``."""
    from uncertsplat.io.checkpoints import decode, encode

    try:
        stored = decode(data, map_location="cpu")
    except Exception:  # noqa: BLE001 - damaged or of another format: not copied (it would not be read either)
        return None
    if not isinstance(stored, dict) or "state" not in stored:
        return None
    for set_aside in (False, True):
        if stored.get("key") is not None and stored.get("key") == residual_key(_model_of(source, model_file), cfg,
                                                                                device, set_aside):
            key = residual_key(_model_of(run_dir, model_file), cfg, device, set_aside)
            return None if key is None else encode({**stored, "key": key})
    return None


__all__ = ["FILE_NAME", "fitted_residual", "rekeyed_residual", "residual_key", "run_digests",
           "same_residual_settings"]
