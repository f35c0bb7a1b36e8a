"""What ``Predictor`` needs to render a run's predictive where its scene folder is not (``RUN/eval/predictive.pt``).

The predictive ``evaluate`` scores is the model's posterior plus side terms fitted on the scene's photos: the pixel
noise (``residual_cache``) and the std factor and tails (``eval.engine.fit_std_scale``), and it is rendered in the
scene's normalised frame, with the view-consistency term of its training cameras. A robot or a planner that queries
the run's uncertainty at its own poses has the run folder, not the photos (often gigabytes). So ``evaluate`` (and a
``Predictor.load`` that fits them) keeps these here: the fitted noise's state, the std factor and tails, and the scene's
cameras, split and normalisation as loaded; ``Predictor.load`` reads them when the scene cannot be loaded.

The file is keyed by the model file, the run's ``config.json`` and ``scene.json`` (but where the scene lies,
``SCENE_LOCATION``) and every evaluation setting (the whole ``EvalConfig``): a file for another model or other settings
is not used. Unlike ``residual.pt`` the key leaves
out the device type and the versions, which are recorded instead: a run evaluated on a desktop's CPU is queried on a
robot's GPU (the maps then differ from the EXR maps by the devices' rounding, and ``Predictor.load`` says so).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import torch

FILE_NAME = "predictive.pt"
FORMAT = 2
"""The layout of the file's dictionary; a file of another layout is not used (1: without ``parts``, unchecked)."""
UNUSED_SETTINGS = ("save_maps", "preview", "reuse", "max_views", "depth_gt", "depth_scale", "depth_align",
                   "paper_nll", "ause_steps", "hidden_depth")
"""Evaluation settings the file's content does not depend on: what is written or scored, not what is predicted, and
``hidden_depth``, a depth term computed at each prediction from the view-consistency term's renders (the file's
noise and std factor are fitted on the RGB); left out of the key, so that ``Predictor.load(run,
cfg=EvalConfig(save_maps=False))`` reads the evaluation's file, and files written before ``hidden_depth`` existed
still read."""


SCENE_LOCATION = {"scene": None, "scene_from_run": None, "source": ("path", "model")}
"""The fields of ``scene.json`` that say where the scene folder lies, not what the run was trained on: left out of the
key (``_digests``), so that a run pointed at its moved scene (``train NEW_SCENE_FOLDER -o RUN --resume``, which checks
that the folder holds the run's images and trains nothing) keeps its file; they made it "another model or run"."""


def _scene_digest(run_dir: Path) -> str | None:
    """The SHA-256 of ``run_dir/scene.json`` without ``SCENE_LOCATION`` (its bytes' where it is not a JSON object)."""
    path = Path(run_dir) / "scene.json"
    try:
        raw = path.read_bytes()
    except OSError:
        return None
    try:
        data = json.loads(raw)
    except ValueError:
        data = None
    if not isinstance(data, dict):
        return hashlib.sha256(raw).hexdigest()
    for name, inner in SCENE_LOCATION.items():
        if inner is None:
            data.pop(name, None)
        elif isinstance(data.get(name), dict):
            data[name] = {k: v for k, v in data[name].items() if k not in inner}
    return hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()


def _digests(loaded) -> tuple[dict, dict] | None:
    """(``residual_cache.run_digests`` with the scene's digest without where the scene lies, ``_scene_digest``; the
    same with ``scene.json``'s whole bytes, as files written before 2026-12-02 were keyed), or None."""
    from uncertsplat.stages.residual_cache import run_digests

    digests = run_digests(loaded)
    if digests is None or digests["scene"] is None:
        return None
    return {**digests, "scene": _scene_digest(Path(loaded.run_dir))}, digests


def _part_forms(loaded, cfg) -> tuple[dict, dict] | None:
    """What the key hashes, in today's form and in that of files written before 2026-12-02: the model file's, the
    run's ``config.json`` and ``scene.json``'s SHA-256 (the latter without where the scene lies, ``_digests``; before,
    of its bytes), the settings the predictive depends on and the noise fit's version; None for a model that is not
    one file (an ensemble), a run without ``scene.json`` or a file that cannot be read."""
    from uncertsplat.eval.engine import RESIDUAL_FIT

    both = _digests(loaded)
    if both is None:
        return None
    extra = {"settings": key_settings(cfg), "fit": RESIDUAL_FIT}
    if cfg.residual_scale == "fit" and cfg.residual_views > 0:
        extra["std_fit"] = STD_FIT_WITH_FITTED_NOISE
    today, before = ({**digests, **extra} for digests in both)
    return today, before


def _parts(loaded, cfg) -> dict | None:
    """``_part_forms``' today's form, or None."""
    forms = _part_forms(loaded, cfg)
    return None if forms is None else forms[0]


STD_FIT_WITH_FITTED_NOISE = 2
"""How the std factor is fitted where ``residual_scale = "fit"`` with a pixel noise (part of the key with those
settings only): 2 since the factor on training views keeps the resolution term the noise's level was fitted with
(files from before hold a factor fitted without it, x1.7 on the demo, and are not used). Conservative: a run with
views set aside, whose factor did not change, is keyed apart too (its file is fitted again where the scene is)."""


LEFT_OUT_WHEN = {"resolution_on_training_views": True, "colour_covariance": "diagonal"}
"""Settings the key leaves out at these values: the files written before the setting existed were fitted as that
value fits, so they still read with it (``key_settings``). ``colour_covariance``: every file before it held the
diagonal colour posterior, its default."""


def key_settings(cfg) -> dict:
    """The evaluation settings ``cfg`` as the key holds them: all but ``UNUSED_SETTINGS``, and those of
    ``LEFT_OUT_WHEN`` only at other values."""
    settings = cfg.model_dump(mode="json", exclude=set(UNUSED_SETTINGS))
    for name, value in LEFT_OUT_WHEN.items():
        if name in settings and settings[name] == value:
            del settings[name]
    return settings


def _accepted_keys(parts: dict) -> set[str]:
    """The keys a file may hold for ``parts``: its own, and where ``LEFT_OUT_WHEN`` settings are left out, those
    with any of them written in (files of the commits that added ``resolution_on_training_views`` and
    ``colour_covariance`` keyed them so)."""
    from itertools import combinations

    left_out = [(name, value) for name, value in LEFT_OUT_WHEN.items() if name not in parts["settings"]]
    return {_key({**parts, "settings": {**parts["settings"], **dict(written)}})
            for r in range(len(left_out) + 1) for written in combinations(left_out, r)}


def _key(parts: dict) -> str:
    """The key of a predictive: a SHA-256 over ``_parts`` (the model file, the run's ``config.json`` and
    ``scene.json``, the evaluation settings but ``UNUSED_SETTINGS``, the noise fit's version)."""
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()


def keep_predictive(loaded, scene, cfg, residual, fit, device: torch.device) -> Path | None:
    """Write ``RUN/eval/predictive.pt`` for ``loaded``'s model under ``cfg``: the pixel noise ``residual`` (a
    ``ResidualField`` or None), the ``StdFit`` ``fit`` and ``scene``'s cameras, split and normalisation. Returns the
    path, or None when the model has no key (``_parts``: an ensemble, or a file that cannot be read). Call it under
    the run's lock."""
    from uncertsplat.io.atomic import atomic_write_bytes
    from uncertsplat.io.checkpoints import encode

    parts = _parts(loaded, cfg)
    if parts is None:
        return None
    cams = scene.cameras
    data = {
        "format": FORMAT,
        "key": _key(parts),
        "parts": json.dumps(parts, sort_keys=True, default=str),
        "device": device.type,
        "versions": plain_versions(),  # plain strings (torch's version is a class weights_only refuses)
        "residual": residual.state() if residual is not None else None,
        "std": {"scale": fit.scale, "dof": fit.dof, "names": list(fit.names)},
        "scene": {
            "cam_from_world": cams.cam_from_world.detach().cpu().clone(),  # [N,4,4]
            "K": cams.K.detach().cpu().clone(),  # [N,3,3]
            "width": int(cams.width), "height": int(cams.height), "names": list(cams.image_names),
            "split": {k: [int(i) for i in v] for k, v in scene.split.items()},
            "scene_scale": float(scene.scene_scale),
            "world_from_source": scene.world_from_source.detach().cpu().clone(),  # [4,4]
            "depth_scale_to_gt": scene.depth_scale_to_gt,
        },
    }
    path = Path(loaded.run_dir) / "eval" / FILE_NAME
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, encode(data))  # checksummed as a checkpoint: a flipped bit is found, not rendered
    return path


def plain_versions() -> dict[str, str]:
    """``provenance.versions()`` as plain strings, as the file records them and ``KeptPredictive.versions`` holds."""
    from uncertsplat.provenance import versions

    return {str(k): str(v) for k, v in versions().items()}


@dataclass(frozen=True)
class KeptPredictive:
    """``RUN/eval/predictive.pt`` as read (``read_predictive``).

    Attributes:
        scene: the scene as the evaluation loaded it (``SceneData``: cameras, split, normalisation; no points and
            no photos: its image paths name files that need not exist).
        residual_state: ``ResidualField.state()`` of the pixel noise (None: none was fitted).
        scale, dof: the std factor and the Student-t's degrees of freedom (None: not fitted / Gaussian).
        names: the images the two were fitted on.
        device: the device type the side terms were fitted on.
        versions: the versions that wrote the file.
    """

    scene: object
    residual_state: dict | None
    scale: float | None
    dof: float | None
    names: tuple[str, ...]
    device: str
    versions: dict


def evaluation_config(run_dir: Path):
    """The ``EvalConfig`` of the run's evaluation (``RUN/eval/config.json``: after ``evaluate --num-samples 4`` the
    defaults fitted another std factor than the evaluation's), ``evaluate``'s defaults when there is none or it
    cannot be read (a newer or damaged file)."""
    from pydantic import ValidationError

    from uncertsplat.config import EvalConfig

    path = run_dir / "eval" / "config.json"
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        if isinstance(data, dict):
            # an evaluation from before the setting existed (2026-12-01) used the diagonal colour posterior: its
            # predictive.pt holds that form, which the default (the block) would refuse
            data.setdefault("colour_covariance", "diagonal")
        return EvalConfig.model_validate(data)
    except (OSError, UnicodeDecodeError, ValueError, ValidationError):
        return EvalConfig()


def evaluation_predictive(loaded) -> tuple[KeptPredictive | None, str]:
    """``read_predictive`` of the run's own evaluation (its settings: ``evaluation_config``): the cameras, split and
    normalisation it kept, for a command that reads the run where the scene folder cannot be loaded."""
    return read_predictive(loaded, evaluation_config(Path(loaded.run_dir)), loaded.scene_path or loaded.run_dir)


def read_predictive(loaded, cfg, scene_folder: str | Path) -> tuple[KeptPredictive | None, str]:
    """(``RUN/eval/predictive.pt`` of ``loaded`` when it was written for this model, run and ``cfg``
    (``_key``), else None; "", else why not for an error: the file is missing, damaged, of another format,
    an ensemble's (no single model file), for another model or run, or for other settings, naming them).
    ``scene_folder``: where the run's scene was (the image paths are named under it)."""
    from uncertsplat.io.checkpoints import decode
    from uncertsplat.types import Cameras, SceneData

    path = Path(loaded.run_dir) / "eval" / FILE_NAME
    forms = _part_forms(loaded, cfg)
    if forms is None:
        return None, "an ensemble's predictive is not kept (it has no single model file)"
    parts = forms[0]
    if not path.is_file():
        return None, f"{path} is missing"
    raw = path.read_bytes()
    if raw[:4] == b"PK\x03\x04":  # a plain torch file: what versions before the checksum (2026-11-29) wrote
        return None, (f"{path} was written by an earlier version of uncertsplat (before the file carried a checksum); "
                      "`uncertsplat evaluate` where the scene is writes it again")
    try:
        data = decode(raw, path)
    except Exception as err:  # noqa: BLE001 - a damaged or foreign file is as good as none: the reason is said
        return None, f"{path} cannot be read ({getattr(err, 'message', err)})"
    try:
        if not isinstance(data, dict) or data.get("format") != FORMAT:
            return None, f"{path} is of another format (written by another version)"
        if data.get("key") not in _accepted_keys(parts) | _accepted_keys(forms[1]):
            return None, f"{path} holds the predictive of {_difference(json.loads(data['parts']), parts)}"
        s, std = data["scene"], data["std"]
        cams = Cameras(s["cam_from_world"].float(), s["K"].float(), int(s["width"]), int(s["height"]),
                       tuple(s["names"]))
        images = Path(scene_folder) / "images"
        scene = SceneData(cameras=cams, image_paths=tuple(images / n for n in cams.image_names),
                          split={k: tuple(v) for k, v in s["split"].items()},
                          points=torch.zeros(0, 3), points_rgb=torch.zeros(0, 3),
                          scene_scale=float(s["scene_scale"]), world_from_source=s["world_from_source"],
                          depth_scale_to_gt=s["depth_scale_to_gt"],
                          source={"kind": "kept", "path": str(path)})
        kept = KeptPredictive(scene=scene, residual_state=data["residual"], scale=std["scale"], dof=std["dof"],
                              names=tuple(std["names"]), device=str(data["device"]),
                              versions={str(k): str(v) for k, v in data["versions"].items()})
    except Exception as err:  # noqa: BLE001 - a well-formed file of an unexpected content: not used, said why
        return None, f"{path} cannot be read ({type(err).__name__}: {err})"
    return kept, ""


def rekeyed_predictive(data: bytes, source: Path, run_dir: Path, model_file: str) -> bytes | None:
    """``RUN/eval/predictive.pt``'s bytes ``data`` of the run ``source``, keyed for ``run_dir``, whose ``model_file``
    and ``config.json`` are the source's byte for byte (a prune that removed nothing, whose evaluation is the
    source's, copied: without the file, ``Predictor.load`` of that run found none where the scene is gone); None when
    the file is not one written for the source's ``model_file`` and run (``_parts``) in this format."""
    from uncertsplat.io.checkpoints import decode, encode
    from uncertsplat.stages.residual_cache import _model_of

    try:
        stored = decode(data)
        parts = json.loads(stored["parts"])
        if stored.get("format") != FORMAT or stored.get("key") != _key(parts):
            return None
    except Exception:  # noqa: BLE001 - damaged or of another format: not copied (it would not be read either)
        return None
    was, now = _digests(_model_of(source, model_file)), _digests(_model_of(run_dir, model_file))
    if was is None or now is None or was[0].keys() != now[0].keys() \
            or not any(all(parts.get(k) == v for k, v in form.items()) for form in was):
        return None
    parts = {**parts, **now[0]}
    return encode({**stored, "key": _key(parts), "parts": json.dumps(parts, sort_keys=True, default=str)})


def _difference(kept: dict, now: dict) -> str:
    """What differs between a file's ``_parts`` and the ones asked for, in words."""
    if kept.get("model") != now["model"] or kept.get("config") != now["config"] or kept.get("scene") != now["scene"]:
        return "another model or run (trained on since, or another run's file)"
    if kept.get("masks") != now.get("masks"):
        return "other masks of the photos (added, removed or changed since it was fitted)"
    a, b = kept.get("settings", {}), now["settings"]
    b = {**{k: v for k, v in LEFT_OUT_WHEN.items() if k not in b}, **b}  # (left out of the key at that value)

    def there(k: str) -> str:
        if k in a:
            return f"{a[k]!r} there"
        was = f"; --set {k}={str(LEFT_OUT_WHEN[k]).lower()} reads it" if k in LEFT_OUT_WHEN else ""
        return f"not in the file (written before the setting existed{was})"

    def differs(k: str) -> bool:
        if k not in a and k in LEFT_OUT_WHEN:  # a file from before the setting: fitted as its left-out value fits
            return b.get(k) != LEFT_OUT_WHEN[k]
        return a.get(k) != b.get(k)

    keys = sorted(k for k in set(a) | set(b) if differs(k))
    if keys:
        return "other settings: " + ", ".join(f"{k} = {there(k)}, {b.get(k)!r} here" for k in keys[:4])
    return "another version of the noise fit or of the std factor's"


__all__ = ["FILE_NAME", "LEFT_OUT_WHEN", "KeptPredictive", "keep_predictive", "key_settings", "plain_versions",
           "read_predictive", "rekeyed_predictive"]
