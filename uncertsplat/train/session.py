"""Train one model into a run folder: scene folder -> checkpoints, stats, PLYs and a summary.

``train_model`` is what every single-model method runs (variational, paper, vi-single, deterministic,
and the models under the ensemble and Fisher baselines); ``stages.train.run`` is the command's entry
point, dispatching on the method (``baselines.train_run``).

Writes (README, "Outputs and their schemas"): ``RUN/config.json`` (resolved TrainConfig), ``RUN/scene.json``
(``schemas.RunScene``: scene path, extent, split), ``RUN/ckpts/step_{N:06d}.pt``, ``RUN/stats.jsonl``,
``RUN/point_cloud.ply``, ``RUN/variational.ply`` and ``RUN/train_summary.json``. An existing run folder is
refused unless ``resume`` is set; a resumed run uses the configuration stored in the run (and says so
when the one given differs) and continues exactly where the last good checkpoint left off.
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import replace
from pathlib import Path

import torch

from uncertsplat import native
from uncertsplat.config import TrainConfig, VariationalConfig, build_config
from uncertsplat.console import console, count, list_names, progress, q
from uncertsplat.conventions import ENSEMBLE_MEMBERS
from uncertsplat.errors import Interrupted, UserError
from uncertsplat.gaussians.variational import describe_posterior
from uncertsplat.io.atomic import (
    atomic_write_text,
    read_json,
    remove_stale_temp_files,
    run_lock,
)
from uncertsplat.schemas import PruneReport, RunExposure, RunScene, TrainSummary
from uncertsplat.schemas.base import run_file_hint
from uncertsplat.schemas.scene import ViewsAdded
from uncertsplat.strategy.exposure import EXPOSURE_SPREAD, exposure_reason, gain_spread
from uncertsplat.strategy.growth import growth_reason
from uncertsplat.strategy.sh_bands import band_reason
from uncertsplat.train.imported import frame_phrase
from uncertsplat.train.transients import transients_warning

# What a run trained with when its config.json predates a key (every dump has the key since), per config section;
# a callable gets the stored section: variational.posterior, before the informed posterior existed: SGD tables;
# variational.train_on, before it existed: an informed run fitted its Gaussians to posterior samples;
# variational.refresh_probes, before it existed: every update used `probes`; variational.spawn_keeps_render, before
# it existed: spawned carriers took the prior's gate and multiplier on top of their parameters; densify.growth_min_gain_db,
# before the growth test: densification grew the model up to its budget; densify.growth_refit_steps, before the test
# re-fitted the rest: the half was switched off in the model as it was; densify.growth_skip_factor, before tests were
# skipped: a test at every interval.
_KEYS_BEFORE = {"variational": {"posterior": "sgd", "train_on": "samples",
                                "refresh_probes": lambda section: section.get("probes", 2),
                                "spawn_keeps_render": False},
                "densify": {"growth_min_gain_db": 0.0, "growth_refit_steps": 0, "growth_skip_factor": None}}


def _transparent(data) -> bool:
    """Whether the first training image has real transparency (an alpha channel with some alpha < 1): the
    background is then data, and a ray that meets no Gaussian shows it (``LoadedRun.empty_std``)."""
    from uncertsplat.io.images import read_alpha

    train = data.split.get("train", ())
    if not train:
        return False
    a = read_alpha(data.image_paths[train[0]])
    return a is not None and bool((a < 1.0).any())


def _differences(a: dict, b: dict, prefix: str = "") -> list[str]:
    out = []
    for k in sorted(set(a) | set(b)):
        va, vb = a.get(k), b.get(k)
        if isinstance(va, dict) and isinstance(vb, dict):
            out += _differences(va, vb, f"{prefix}{k}.")
        elif va != vb:
            out.append(f"{prefix}{k}")
    return out


def _truncate_stats(path: Path, step: int) -> None:
    """Drop log lines written after the checkpoint we resume from (they will be written again)."""
    if not path.is_file():
        return
    keep = []
    for line in path.read_text(encoding="utf-8").splitlines():
        try:
            if int(json.loads(line).get("step", 0)) <= step:
                keep.append(line)
        except (ValueError, json.JSONDecodeError):
            continue  # a line cut short by a crash
    atomic_write_text(path, "".join(f"{line}\n" for line in keep))


def _settle_notes(cfg: TrainConfig, resume: bool = False) -> list[str]:
    """A note when the run is too short for its ``densify.until``: densification stops at the last
    ``schedule.SETTLE_FRACTION`` of its steps instead (a shortened preset densified at its last step). ``resume``:
    the run goes on with its stored configuration, so the note does not offer a setting it would ignore."""
    from uncertsplat.strategy.schedule import SETTLE_FRACTION, densify_end

    end = densify_end(cfg.densify, cfg.iterations)
    if end >= cfg.densify.until or cfg.densify.start >= end:
        return []
    return [f"densification stops before step {int(end)}, not at densify.until = {cfg.densify.until}: the last "
            f"{SETTLE_FRACTION:.0%} of a run's {cfg.iterations} steps train the Gaussians without growing new ones "
            "(grown at the end, they would be left untrained); "
            + ("a resumed run keeps its stored densify.until" if resume else
               "--set densify.until=N chooses an earlier end")]


def _posterior_notes(cfg: TrainConfig) -> list[str]:
    """Said before training when the settings give no Gaussian a posterior over the whole run (it was said only
    after it: a helper's densify.start beyond the run's steps trained all of it for a model without uncertainty)."""
    from uncertsplat.train.trainer import no_carriers_reason

    reason = no_carriers_reason(cfg, cfg.iterations, planned=True) if cfg.has_offset_tables else None
    return [f"no Gaussian will carry a posterior in this run: {reason}"] if reason else []


def _reset_notes(cfg: TrainConfig) -> list[str]:
    """A note when the run's opacity resets all fall in its last ``RESET_RECOVERY_STEPS`` steps, where none is made:
    a short run took ``densify.opacity_reset_interval`` without a word and reset nothing."""
    from uncertsplat.strategy.schedule import RESET_RECOVERY_STEPS, is_opacity_reset_step

    d = cfg.densify
    n = d.opacity_reset_interval
    asked = range(n, min(d.until, cfg.iterations + 1), n) if n > 0 else range(0)
    if not asked or any(is_opacity_reset_step(m, d, cfg.iterations) for m in asked):
        return []
    return [f"no opacity reset in this run: none is made in a run's last {RESET_RECOVERY_STEPS} steps (the model needs "
            f"them to recover from one), and every multiple of densify.opacity_reset_interval = {n} before "
            f"densify.until falls there in a run of {cfg.iterations} steps"]


def _unused_setting_notes(cfg: TrainConfig, member: bool = False) -> list[str]:
    """Settings given that the configured method does not use (they were taken silently); ``member``: the run is an
    ensemble's member (its config keeps the ensemble's keys)."""
    out = []
    entries = cfg.variational.num_entries
    if cfg.method == "variational" and cfg.posterior == "informed" and entries != VariationalConfig().num_entries:
        out.append(f"variational.num_entries = {entries} is not used by the informed posterior, which gives every "
                   "entry of a table the same values and so stores one; it sets the tables of --set "
                   "variational.posterior=sgd (and --variant paper)")
    default = TrainConfig()
    unused = []
    if cfg.method != "ensemble" and not member:  # (a member's config keeps its ensemble's size)
        unused += [k for k in ("ensemble_size", "ensemble_members") if getattr(cfg, k) != getattr(default, k)]
    # (fisher.* is not named: select-views' fisher score reads it for a run of any method)
    if not cfg.has_offset_tables and cfg.variational != default.variational:
        unused.append("variational.*")
    if cfg.exposure == "off" and cfg.exposure_lr != default.exposure_lr:
        unused.append("exposure_lr (exposure is off)")
    if cfg.low_res_fraction == 0 and cfg.low_res_scale != default.low_res_scale:
        unused.append("low_res_scale (low_res_fraction is 0)")
    if unused:
        out.append(f"settings this run does not use (method {cfg.method}): {', '.join(unused)}")
    return out


def _same_scene_path(run_dir: Path, scene: Path) -> bool:
    """Whether ``run_dir``'s scene.json records ``scene`` as its scene folder."""
    try:
        info = RunScene.read_optional(run_dir / RunScene.FILE_NAME)
    except UserError:
        return False
    # the recorded path, not ``scene_folder``: a run copied with its scene, resumed on that copy, records it
    return info is not None and Path(info.scene).resolve() == Path(scene).resolve()


def imported_not_trained_on(init_ply, what: str) -> str:
    """The refusal of training on (or adding views to) a run whose model was trained elsewhere (``init_ply``)."""
    return (f"this run is the posterior of a model trained elsewhere ({init_ply}), which uncertsplat does not train: "
            f"{what}")


def imported_retrain_hint(scene, init_ply) -> str:
    """What to do instead: train the model on in the tool that trained it, then import its new file."""
    from uncertsplat.console import q

    return (f"Train the model on (with the new photos, if any) in the tool that trained it, then give its new file: "
            f"uncertsplat train {q(scene)} -o NEW_RUN --from-ply NEW_MODEL.ply (this run stays as it is; it was "
            f"built from {Path(init_ply).name}).")


def _imported_from(run_dir: Path) -> str | None:
    """The model file a run was imported from (its config.json's ``init_ply``), or None (not one, or unreadable)."""
    try:
        value = json.loads((run_dir / "config.json").read_text(encoding="utf-8")).get("init_ply")
    except (OSError, ValueError, AttributeError):
        return None
    return str(value) if value else None


def _summary_steps(run_dir: Path) -> int | None:
    """The steps ``train_summary.json`` says the run's finished model was trained for (None: none readable)."""
    try:
        summary = TrainSummary.read_optional(run_dir / TrainSummary.FILE_NAME)
    except UserError:
        return None
    return summary.steps if summary is not None else None


PHOTO_MEMORY_SHARE = 0.5
"""``train`` warns before loading when the photos alone would take more than this share of the free memory."""


def _photo_memory_notes(data, device) -> list[str]:
    """A warning when the photos ``train`` is about to load (of ``data``, a ``SceneData``) would take more than
    ``PHOTO_MEMORY_SHARE`` of the free memory (``io.memory.available_memory``; on the CPU): training needs more
    beside them (renders, the SSIM statistics), and a capture too large ran out of memory minutes later with an
    allocator's traceback. Sizes from the headers: 3 bytes a pixel for 8-bit photos without alpha, 12 for others."""
    from uncertsplat.io.images import is_opaque_8bit
    from uncertsplat.io.memory import available_memory

    if torch.device(device).type != "cpu":
        return []
    views = [i for k in ("train", "test") for i in data.split.get(k, ())]
    if not views:
        return []
    pixels = data.cameras.width * data.cameras.height
    need = sum(pixels * (3 if is_opaque_8bit(data.image_paths[i]) else 12) for i in views)
    free = available_memory()
    if free is None or need <= PHOTO_MEMORY_SHARE * free:
        return []
    return [f"the {len(views)} photos at {data.cameras.width}x{data.cameras.height} take {need / 2**30:.1f} GB, "
            f"against {free / 2**30:.1f} GB of free memory, and training needs more beside them: it may run out; "
            "--set scene.downscale=2 holds a quarter of it (or train on fewer photos)"]


def _last_logged_step(run_dir: Path) -> int:
    """The last step ``stats.jsonl`` logged (0: none, or no readable line)."""
    last = 0
    try:
        lines = (run_dir / "stats.jsonl").read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError:
        return 0
    for line in lines:
        try:
            step = json.loads(line).get("step")
        except (ValueError, AttributeError):
            continue
        last = max(last, step) if isinstance(step, int) else last
    return last


def _close_names(unknown: list[str], scene: Path, cfg: TrainConfig) -> str:
    """" (did you mean X?)" for names given to --add-views that are near a photo of the scene (another case, a path
    before it, a letter or digit off: view_15.png for view_015.png), "" when none is."""
    import difflib

    from uncertsplat.sfm.scene import load_scene

    try:
        names = load_scene(scene, cfg.scene.model_copy(update={"train_names": None, "train_indices": None}),
                           initial_points=False).cameras.image_names
    except UserError:
        return ""
    by_key = {n.casefold(): n for n in names}
    found = []
    for name in unknown:
        key = Path(name).name.casefold()
        match = key if key in by_key else next(iter(difflib.get_close_matches(key, list(by_key), n=1, cutoff=0.8)),
                                               None)
        if match is not None:
            found.append(by_key[match])
    return f" (did you mean {', '.join(found)}?)" if found else ""


def _record_moved_scene(run_dir: Path, scene: Path, cfg: TrainConfig) -> None:
    """``scene.json`` of the finished run ``run_dir`` pointed at ``scene``, the folder its scene moved to, after the
    checks a resume makes (``_check_same_scene``: its images; ``camera_changes``: its cameras)."""
    from uncertsplat.sfm.scene import load_for_run, require_same_cameras

    before = RunScene.read(run_dir / RunScene.FILE_NAME)
    data, _ = load_for_run(scene, cfg.scene, before, initial_points=False)
    _check_same_scene(before, scene, data.cameras.image_names, run_dir)
    require_same_cameras(before.cameras, data, scene, "its renders against these would be wrong")
    before.scene = str(scene.resolve())
    before.scene_from_run = RunScene.relative_path(scene, run_dir)
    before.write(run_dir / RunScene.FILE_NAME)


FAILED_STATS = "stats.failed.jsonl"
"""Where a start that failed before its first checkpoint leaves its ``stats.jsonl`` when the run starts again."""

_STARTED_FILES = ("config.json", "scene.json", "stats.jsonl", ".lock", FAILED_STATS)
"""What a run folder holds when ``train`` failed before its first checkpoint (a photo it could not read, a bad
setting found while loading, memory that ran out at step 5): nothing to resume from, so the same command (with
other settings, e.g. a larger ``scene.downscale``) may start it again (``_never_trained``)."""


def _never_trained(run_dir: Path) -> bool:
    """Whether ``run_dir`` is a run that failed before its first checkpoint: only ``_STARTED_FILES`` and an empty
    ``ckpts/`` (its ``stats.jsonl`` may have logged steps: ``--resume`` would start from step 0 all the same, with
    the stored settings the user had to change; the folder was refused and a run out of memory could not be started
    again with a larger downscale)."""
    for p in run_dir.iterdir():
        if p.name == "ckpts" and p.is_dir() and not any(p.iterdir()):
            continue
        if p.name not in _STARTED_FILES or not p.is_file():
            return False
    return True


def _check_same_scene(before: RunScene, scene: Path, names: tuple[str, ...], run_dir: Path) -> None:
    """Refuse to resume ``run_dir`` on another scene than the one it was trained on (``scene.json``): its model
    would go on training on other photos and its held-out scores would mix two scenes. A scene folder that was
    moved (the recorded path is gone) is accepted when it holds every image the run trained on and held out."""
    recorded = Path(before.scene)
    if recorded.resolve() == scene.resolve():
        return
    missing = sorted((set(before.train) | set(before.test) | set(before.calibration)) - set(names))
    if recorded.exists() or missing:
        why = (f"{len(missing)} of its images are not in {scene} (e.g. {missing[0]})" if missing
               else f"that scene is still at {recorded}")
        raise UserError(f"the run was trained on {recorded}, not on {scene}: {why}", path=run_dir,
                        hint=f"Resume it on its own scene: uncertsplat train {q(recorded)} -o {q(run_dir)} --resume "
                             "(or train the other scene into a new run folder).")
    console.print(f"[yellow]note:[/] the run's scene was at {recorded} (gone); resuming on {scene}, which holds "
                  "all of its images")


def _refuse_twins_of_held_out(data, add: list[str], run_dir: Path) -> None:
    """Refuse added views that took the same picture as a held-out or set-aside view (``sfm.scene.held_out_twins``: a
    photo saved again under another name registers at its pose): trained on, the held-out score measures what the
    model memorised (a helper's re-saved copy of a held-out fern photo: that view 25.92 -> 28.27 dB)."""
    from uncertsplat.sfm.scene import held_out_twins

    names = data.cameras.image_names
    adding = set(add)
    twins = held_out_twins(data.cameras, data.split, [i for i, n in enumerate(names) if n in adding])
    if twins:
        h, (t, *_) = next(iter(twins.items()))
        raise UserError(f"--add-views {names[t]} took the same picture as the held-out view {names[h]} (the same pose: "
                        "a copy, or a photo saved again): trained on, that view's score would measure what the model "
                        "memorised", path=run_dir,
                        hint="Add another photo; the held-out views stay held out so that the scores compare.")


def _split_names(add: list[str], scene: Path | None) -> list[str]:
    """``--add-views`` values as image names: each split at commas ("a.png,b.png", as the Next lines print them), but
    a value that is itself the name of a photo of ``scene`` (in its ``images/`` or at its top) kept whole ("IMG 4045,
    final.jpg" could not be added)."""
    out: list[str] = []
    for item in add:
        whole = item.strip()
        if "," in whole and scene is not None and any((Path(scene) / sub / whole).is_file() for sub in ("images", ".")):
            out.append(whole)
        else:
            out.extend(n.strip() for n in item.split(",") if n.strip())
    return out


def _add_training_views(cfg: TrainConfig, run_dir: Path, add: list[str],
                        scene: Path | None = None) -> tuple[TrainConfig, list[str]]:
    """``cfg`` with the views ``add`` appended to its explicit training names, and those names.

    Raises:
        UserError: the run records no training views, sets views aside for calibration, or a view is held out or
            already trained on.
    """
    if cfg.scene.calibration_holdout:
        # the views set aside are chosen over the training views: more training views would set others aside, and a
        # view the model trained on could then calibrate it
        raise UserError("this run sets views aside for calibration (scene.calibration_holdout), and adding views "
                        "would change which ones", path=run_dir,
                        hint="Train a new run on the views you want (scene.train_names), with views set aside or not.")
    info = RunScene.read_optional(run_dir / RunScene.FILE_NAME)
    if cfg.scene.train_names is None and info is None:
        raise UserError("this run records no training views (scene.json is missing), so views cannot be added to "
                        "them", path=run_dir, hint="Add views to a run written by `uncertsplat train`.")
    held = set(info.test) if info is not None else set()
    # a run started on scene.train_indices continues on the names of those views (scene.json), so that the added
    # ones join them whatever their place in the sorted image list
    current = list(cfg.scene.train_names) if cfg.scene.train_names is not None else list(info.train)
    added: list[str] = []
    for name in _split_names(add, scene):  # "a.png,b.png" or repeated
        if name in held:
            raise UserError(f"'{name}' is a held-out view of this run", path=run_dir,
                            hint="Add an unused view (held-out views stay held out so the scores stay comparable).")
        if name in added:  # given twice on the command line: once is enough
            continue
        if name in current:
            recent = bool(info is not None and info.views_added and name in info.views_added[-1].names)
            every = cfg.scene.train_names is None and cfg.scene.train_indices is None
            raise UserError(f"'{name}' is already a training view of this run"
                            + (f" (added at step {info.views_added[-1].step})" if recent else
                               " (it trains on every photo of its scene that is not held out)" if every else ""),
                            path=run_dir,
                            hint="A training stopped after adding it (before its next checkpoint) goes on with "
                                 "`--resume` alone, which trains it." if recent else
                                 "New photos join a workspace of `uncertsplat reconstruct` with `uncertsplat "
                                 "reconstruct PHOTOS -o WORKSPACE --extend` (every camera there kept); then add them "
                                 "here." if every else
                                 "Add views it has not trained on: its scene.json lists the ones it trains on under "
                                 f"`train`, and `uncertsplat select-views {q(run_dir)}` ranks the others.")
        added.append(name)
    scene = cfg.scene.model_copy(update={"train_names": current + added, "train_indices": None})
    return cfg.model_copy(update={"scene": scene}), added


def train_model(scene: Path, run_dir: Path, cfg: TrainConfig, device: torch.device, resume: bool = False,
                extend_to: int | None = None, on_trainer=None, add_views: list[str] | None = None,
                given: set[str] | None = None, done_label: str = "done", resume_dir: Path | None = None) -> Path:
    """Train one model on ``scene`` into ``run_dir``; returns ``run_dir``.

    ``extend_to`` (with ``resume``): train on to this many steps instead of the stored ``iterations``.
    ``on_trainer(trainer)``: called with the ``Trainer`` before it trains (``train --view`` attaches here).
    ``add_views`` (with ``resume``): image names added to the training set from the checkpoint's step on (the run
    must have started on explicit ``scene.train_names``); recorded in ``scene.json`` (``views_added``).
    ``given`` (with ``resume``): the dotted keys the command set; the note on values the stored configuration
    overrides names only those (None: every difference, the command's defaults too).
    ``done_label``: how the closing line starts (an ensemble's member says which member it is: the run is not done).
    ``resume_dir``: the folder an interruption's "Continue with" names (an ensemble member's: the ensemble's).

    Raises:
        UserError: unreadable scene, an existing run folder without ``resume``, nothing to resume, or an
            interruption (Ctrl-C / SIGTERM; a checkpoint was written and ``--resume`` continues).
    """
    from uncertsplat.data.dataset import load_masks, load_photos
    from uncertsplat.io.checkpoints import list_checkpoints, load_latest
    from uncertsplat.io.folders import stage_hint
    from uncertsplat.io.ply import write_point_cloud_ply, write_variational_ply
    from uncertsplat.render import near_plane
    from uncertsplat.sfm.scene import (
        camera_records,
        load_for_run,
        mask_changes,
        mask_hashes,
        require_same_cameras,
        with_training_views,
    )
    from uncertsplat.strategy.schedule import densify_steps_after
    from uncertsplat.train.trainer import (
        Trainer,
        TrainingInterrupted,
        few_carriers_warning,
        log_line,
        training_near_plane,
    )

    scene, run_dir = Path(scene), Path(run_dir)
    device = torch.device(device)
    # a bad UNCERTSPLAT_RASTERIZER, or =native without the kernels, is refused before the run folder is made
    native.require_requested(device)
    if run_dir.exists() and not run_dir.is_dir():
        raise UserError("the output path is a file, not a folder", path=run_dir,
                        hint="Give -o the folder for the run (a new one, or a run to --resume).")
    if not resume:  # (a run made there before this check resumes where it is)
        from uncertsplat.sfm.scene import photo_folder_holding

        photos = photo_folder_holding(run_dir, scene)
        if photos is not None:  # its renders, maps and figures would be photos to the next `reconstruct`
            raise UserError(f"the output folder is inside the folder of the scene's photos ({photos}): the run's "
                            "images would be taken for photos there", path=run_dir,
                            hint="Choose an output folder outside the photos (e.g. beside the scene).")
    exists = run_dir.exists() and any(p.name != ".lock" for p in run_dir.iterdir())
    if exists and not resume and (run_dir / "config.json").is_file() and _never_trained(run_dir):
        # a start that failed before its first step (e.g. a photo it could not read): nothing to keep. Under the
        # folder's lock: a training that is starting there looks the same until its first step, and is refused
        with run_lock(run_dir, "train"):
            if _never_trained(run_dir):  # (again under the lock: a training may have finished there since)
                logged = _last_logged_step(run_dir)
                console.print(f"[yellow]note:[/] {run_dir} holds a run that failed before "
                              + (f"its first checkpoint (step {logged} logged), so there is nothing to resume from"
                                 if logged else "training anything") + "; starting it again"
                              + (f" (its log kept as {FAILED_STATS})" if logged else ""))
                if logged:  # the failed start's log, which a user may want to read (one, the latest, is kept)
                    os.replace(run_dir / "stats.jsonl", run_dir / FAILED_STATS)
                for name in _STARTED_FILES[:3]:
                    (run_dir / name).unlink(missing_ok=True)
                exists = False
    if exists and not resume:
        if not (run_dir / "config.json").is_file():  # files of something else: nothing --resume could continue
            raise UserError("the output folder exists and holds files that are not a training run", path=run_dir,
                            hint="Choose another output folder (-o), or empty this one.")
        steps = _summary_steps(run_dir)
        imported = _imported_from(run_dir)
        try:
            before = RunScene.read_optional(run_dir / RunScene.FILE_NAME)
        except UserError:
            before = None
        if before is not None and Path(before.scene).exists() and not _same_scene_path(run_dir, scene):
            # --resume would be refused on this scene: say whose run it is instead of advising it
            raise UserError(f"the run folder already exists and holds a run of another scene ({before.scene})",
                            path=run_dir, hint="Choose another output folder (-o) for this scene, or resume that run "
                                               f"on its own: uncertsplat train {q(before.scene)} -o {q(run_dir)} --resume")
        if imported is not None and steps is not None:  # finished: nothing to continue (--resume says so)
            raise UserError(f"the run folder already exists and holds the posterior of {imported}", path=run_dir,
                            hint="Choose another output folder (-o) for this model, or move that run aside (or "
                                 "delete it) to import the model again.")
        raise UserError("the run folder already exists" + (f" and holds a run trained for {steps} steps" if steps
                                                           else ""), path=run_dir,
                        hint=("Add --resume --iterations N (N > its steps) to train it on" if steps else
                              "Add --resume to continue it") + ", or choose another output folder (-o).")
    if add_views and not resume:
        raise UserError("views can only be added to a run that exists (--add-views needs --resume)", path=run_dir,
                        hint="Train the first views, then resume with --add-views.")
    if resume and not (run_dir / "config.json").is_file():
        # a folder of other files (a scene, a prune's sweep): "start a new run without --resume" there was refused
        # next ("the output folder exists and holds files that are not a training run")
        near = stage_hint(run_dir, "run") if exists else ""
        raise UserError("nothing to resume: no config.json in the run folder"
                        + ("; the folder holds files that are not a training run" if exists else "")
                        + (f" ({near})" if near else ""), path=run_dir,
                        hint="Give --resume the folder `uncertsplat train -o` wrote, or start a new run without --resume "
                             "in a new or empty output folder (-o)." if exists else "Start a new run without --resume.")
    if resume and (run_dir / "prune.json").is_file():
        # a prune output holds a model and config.json but no checkpoint: a --resume started from step 0 in it and
        # wrote a new model over the pruned one, beside a prune.json and evaluation of neither (a helper followed
        # select-views' advice there)
        source = PruneReport.training_run(run_dir)
        raise UserError("this folder is a pruned model (prune.json), not a training run: it has no checkpoint to go on "
                        "from, and a training here would replace the pruned model", path=run_dir,
                        hint=f"Resume its source run{f' ({source})' if source else ''} with the same arguments, then "
                             "prune it again.")

    with run_lock(run_dir, "train"):
        state = None
        later: list[str] = []  # what the resume says once the scene and the added views are checked
        if resume:
            remove_stale_temp_files(run_dir, run_dir / "ckpts")  # left by a killed process; we hold the lock
            stored = read_json(run_dir / "config.json", hint=run_file_hint("config.json"))
            for section, before in _KEYS_BEFORE.items():
                if isinstance(stored.get(section), dict):
                    for key, value in before.items():
                        if key not in stored[section]:
                            stored[section][key] = value(stored[section]) if callable(value) else value
            diff = [d for d in _differences(stored, json.loads(cfg.model_dump_json()))
                    if not (d == "iterations" and extend_to is not None)
                    and (given is None or any(d == g or d.startswith(g + ".") for g in given))]
            if diff:
                console.print(f"[yellow]note:[/] resuming with the run's stored configuration; ignoring the "
                              f"given values of: {', '.join(diff)}")
            cfg = build_config(TrainConfig, stored, source=str(run_dir / "config.json"))
            if cfg.init_ply is not None and (add_views or extend_to not in (None, cfg.iterations)):
                # the config refuses steps with init_ply; --iterations N here trained N steps (a model_copy skips the
                # validation) and left a config.json that every later command refused
                raise UserError(imported_not_trained_on(cfg.init_ply, "views cannot be added to it" if add_views
                                                        else f"it cannot be trained on to {extend_to} steps"),
                                path=run_dir, hint=imported_retrain_hint(scene, cfg.init_ply))
            if add_views:
                cfg, add_views = _add_training_views(cfg, run_dir, list(add_views), scene)
            found = load_latest(run_dir, map_location=device)
            if extend_to is not None and extend_to != cfg.iterations:
                done = int(found[1]["step"]) if found is not None else 0
                if extend_to < done:
                    raise UserError(f"cannot shorten the run to {extend_to} steps: its checkpoint is at step {done}",
                                    path=run_dir, hint="Give --iterations at or above that step.")
                # (said once the scene and the added views are checked: before, a refused name followed it)
                later.append(f"[yellow]note:[/] continuing to {extend_to} steps instead of {cfg.iterations}; the "
                             "position learning-rate schedule is stretched to the new length from here on")
                cfg = cfg.model_copy(update={"iterations": extend_to})
            if add_views and found is not None and int(found[1]["step"]) >= cfg.iterations:
                raise UserError(f"the run has finished its {cfg.iterations} steps: the added view(s) would never be "
                                "trained on", path=run_dir,
                                hint=f"Give the steps to train them with: --iterations N (N > {cfg.iterations}).")
            if add_views and found is not None and not densify_steps_after(int(found[1]["step"]), cfg.densify,
                                                                           last_step=cfg.iterations):
                # the new views' surfaces get no Gaussians of their own: existing ones move and change colour only
                # (said once the views are known to be the scene's: an unknown name is refused below)
                later.append(f"[yellow]note:[/] no densification step is left after the checkpoint's step "
                              f"{int(found[1]['step'])} (every {cfg.densify.interval} steps before densify.until = "
                              f"{cfg.densify.until}, and the run ends at {cfg.iterations}): the added view(s) are "
                              "fitted with the Gaussians the model has, none are grown for them, so what only they "
                              "show stays poorly fitted; to grow for them, add views from an earlier checkpoint (a run "
                              "of more steps, or one started with a later densify.until)")
            finished = _summary_steps(run_dir) if (run_dir / "variational.ply").is_file() else None
            # checkpoints that are there but none loads (each named in a warning above) are not "gone": a copy of the
            # run restores them
            damaged = len(list_checkpoints(run_dir)) if found is None else 0
            broken = (f"{damaged} checkpoint{'s' if damaged > 1 else ''} in ckpts/ {'are all' if damaged > 1 else 'is'} "
                      "damaged (the warnings above name them)")
            if found is None and finished:  # a finished model whose checkpoints were deleted (to save disk) or damaged
                if extend_to is None or extend_to <= finished:
                    if not _same_scene_path(run_dir, scene):  # resumed to point it at its scene's new folder
                        _record_moved_scene(run_dir, scene, cfg)
                    console.print(f"{run_dir}: already trained for its {finished} steps, nothing to do ("
                                  + ("its checkpoints are damaged" if damaged else "its checkpoints are gone")
                                  + ", so it cannot be trained on)")
                    return run_dir
                why = f"the run's {broken}" if damaged else "the run's checkpoints are gone (ckpts/ holds none)"
                raise UserError(f"{why}: it cannot go on from its {finished} steps, and starting from step 0 would "
                                "replace its finished model", path=run_dir,
                                hint=("Copy the checkpoints back into ckpts/ from a copy of the run and run this "
                                      "again, or train" if damaged else "Train")
                                + f" a new run with the steps you want (-o NEW_RUN --iterations {extend_to}); this "
                                  "one stays as it is (its finished model is intact: evaluate, prune and view read it).")
            if found is None:
                console.print("[yellow]note:[/] no usable checkpoint in the run folder"
                              + (f": its {broken}" if damaged else "") + "; starting from step 0")
                for name in ("stats.jsonl",):
                    (run_dir / name).unlink(missing_ok=True)
            elif (int(found[1]["step"]) >= cfg.iterations and not add_views and (run_dir / "variational.ply").is_file()
                  and _summary_steps(run_dir) == int(found[1]["step"]) and _same_scene_path(run_dir, scene)):
                # (a run resumed on its scene's new folder goes on below: it checks the scene and records the folder)
                console.print(f"{run_dir}: its posterior is built from {cfg.init_ply}, nothing to do (a model "
                              "trained elsewhere is not trained on here)" if cfg.init_ply is not None else
                              f"{run_dir}: already trained for its {cfg.iterations} steps, nothing to do "
                              f"(--iterations N with N > {cfg.iterations} trains it on)")
                return run_dir
            else:
                path, state = found
                later.insert(0, f"resuming from {path} (step {state['step']})")
                _truncate_stats(run_dir / "stats.jsonl", int(state["step"]))

        before = RunScene.read_optional(run_dir / RunScene.FILE_NAME) if resume else None
        own = None
        try:
            # photos joined the scene since the run began (reconstruct --extend): it goes on in its own frame and
            # scale, with its held-out views (`--add-views` trains on the new ones)
            data, own = load_for_run(scene, cfg.scene, before)
        except UserError as err:
            unknown = [n for n in add_views or () if "not in the scene: " in err.message and n in err.message]
            if not unknown:
                raise
            on_disk = [n for n in unknown if (Path(scene) / "images" / n).is_file()]
            if on_disk:  # a photo the scene leaves out (another size, or one its COLMAP model does not hold)
                raise UserError(f"--add-views {', '.join(on_disk)}: the photo is in {Path(scene) / 'images'} but not "
                                "among the scene's views: left out for its size (the scene's photos are fitted to one "
                                "size; another shape is left out, as `train` noted) or not in its COLMAP model",
                                path=scene, hint="Bring the photo to the scene's size; a photo added to the photo "
                                                 "folder joins a workspace of `uncertsplat reconstruct` with "
                                                 f"`uncertsplat reconstruct PHOTOS -o {q(scene)} --extend` (its cameras "
                                                 "kept); or choose another view.") from None
            from uncertsplat.sfm.report import load_report

            try:
                report = load_report(scene)
            except UserError:
                report = None
            unregistered = set(report.images_unregistered) if report is not None else set()
            failed = [n for n in unknown if n in unregistered]
            if failed:  # in the photo folder, reconstructed (--extend), and not registered: not a missing photo
                raise UserError(f"--add-views {', '.join(failed)}: the reconstruction did not register it (listed under "
                                f"images_unregistered in {Path(scene) / 'reconstruct_report.json'}): it has no camera "
                                "in the scene", path=scene,
                                hint="A photo registers when it shares enough features with photos near it: take "
                                     "another closer to the capture's viewpoints (overlap, no blur), put it into the "
                                     "photo folder under a new name and run `reconstruct --extend`; or add another "
                                     "photo.") from None
            join = (f"put it into the photo folder, `uncertsplat reconstruct PHOTOS -o {q(scene)} --extend` registers it "
                    "into this workspace with every camera there kept, and the run then adds it here. "
                    if report is not None else  # (--extend grows workspaces of reconstruct only)
                    "add it to the scene with its camera, as the scene's own tool writes them (this scene is not a "
                    "workspace of `uncertsplat reconstruct`, whose --extend registers new photos), and the run then "
                    "adds it here. ")
            raise UserError(f"--add-views {', '.join(unknown)}: no photo of that name in the scene"
                            + _close_names(unknown, scene, cfg), path=scene,
                            hint="--add-views takes the names of photos the scene holds but the run did not train on; "
                                 "a pose that select-views proposed needs a photo taken there first: " + join
                                 + (err.hint or "")) from None
        if not data.split.get("train"):
            raise UserError("the scene has no training views", path=scene, hint="Check test_every / test_names.")
        if own is not None:
            console.print(f"[yellow]note:[/] {own}")
        names = data.cameras.image_names
        if before is not None:
            _check_same_scene(before, scene, names, run_dir)
            require_same_cameras(before.cameras, data, scene, "training on would spoil it")
            if not add_views:
                # the scene's split rules may have changed since the run began (a held-out view's twin now leaves
                # training): the run goes on with the views it trained on, which its checkpoint's view order indexes
                data = with_training_views(data, before.train)
                now = [names[i] for i in data.split["train"]]
                if before.train and now != before.train:  # recorded views held out or set aside now, or gone
                    moved = sorted(set(before.train) - set(now)) or sorted(set(now) - set(before.train))
                    raise UserError(f"the run trained on other views than this scene's split gives it now "
                                    f"({list_names(moved)}): its checkpoint's order of views would not match",
                                    path=run_dir, hint="Resume it on a scene folder holding the photos it started "
                                                       "with (photos added to the folder move the held-out views, "
                                                       "every scene.test_every-th by name), or train a new run.")
            held = [names[i] for i in data.split.get("test", ())]
            if add_views and before.test and held != before.test:  # (the plain resume's check is the one above)
                moved = sorted(set(before.test) ^ set(held))
                raise UserError(f"the scene holds out other views than the run did ({list_names(moved)}): a view the "
                                "run held out could be trained on, and its scores would no longer compare",
                                path=run_dir, hint="Add views on the scene folder the run started with (photos added "
                                                   "to the folder move the held-out views, every scene.test_every-th "
                                                   "by name), or train a new run.")
            if add_views:
                _refuse_twins_of_held_out(data, add_views, run_dir)
        for line in later:
            console.print(line)
        views_added = list(before.views_added) if before is not None else []
        if state is not None and not add_views and any(v.step > int(state["step"]) for v in views_added):
            # resumed from a checkpoint before views were added (later ones gone): they train from here on
            step = int(state["step"])
            late = [n for v in views_added if v.step > step for n in v.names]
            views_added = [ViewsAdded(step=min(v.step, step), names=v.names) for v in views_added]
            console.print(f"[yellow]note:[/] resuming from step {step}, before {list_names(late)} were added: they "
                          f"train from step {step} on (views_added in scene.json says so)")
        if add_views:
            views_added.append(ViewsAdded(step=int(state["step"]) if state is not None else 0, names=list(add_views)))
        # the images' transparency decides the empty-ray term (evaluate) and whether random_background applies
        data = replace(data, source=dict(data.source, transparent=_transparent(data)))
        if cfg.random_background and data.source["transparent"]:
            console.print("[yellow]note:[/] random_background is not used: the training images are transparent "
                          "(their background is data)")
        near = training_near_plane(data)
        if state is not None and before is not None:  # a resumed model keeps its plane (one recorded none: 1 %)
            near = before.near if before.near is not None else near_plane(data.scene_scale)
        recorded_views = [names[i] for k in ("train", "test", "calibration") for i in data.split.get(k, ())] \
            if names else []  # (the views whose cameras and masks scene.json records)
        run_scene = RunScene(
            scene=str(scene.resolve()), scene_from_run=RunScene.relative_path(scene, run_dir), source=data.source,
            extent=data.extent,
            scene_scale=data.scene_scale,
            width=data.cameras.width, height=data.cameras.height,
            train=[names[i] for i in data.split["train"]] if names else [],
            test=[names[i] for i in data.split.get("test", ())] if names else [],
            calibration=[names[i] for i in data.split.get("calibration", ())] if names else [],
            center=list(data.center) if data.center is not None else None, center_method=data.center_method,
            center_reason=data.center_reason, world_from_source=data.world_from_source.double().tolist(),
            views_added=views_added, near=near,
            cameras=camera_records(data.cameras, recorded_views), masks=mask_hashes(data, recorded_views),
        )
        if state is not None and before is not None:  # a resume goes on with the masks the scene has now: say so
            changed = mask_changes(before.masks, run_scene.masks,
                                   run_scene.train + run_scene.test + run_scene.calibration)
            if changed and int(state["step"]) >= cfg.iterations and not add_views:
                # nothing left to train: the model is the one the recorded masks trained (evaluate compares them)
                run_scene = run_scene.model_copy(update={"masks": before.masks})
            elif changed:
                console.print(f"[yellow]note:[/] the photos' masks changed since this run was trained ({changed}): "
                              "training goes on with them as they are now")
        for note in _photo_memory_notes(data, device):
            console.print(f"[yellow]warning:[/] {note}")
        # 8-bit photos stay uint8 (a quarter of float32's memory), converted one at a time where a step uses them
        # (a bar: 60 photos of 2000x1500 took 54 s with nothing said)
        with progress(transient=True) as bar:
            task = bar.add_task("loading photos", total=len(data.split["train"]) + len(data.split.get("test", ())),
                                info="")

            def step() -> None:
                bar.advance(task)

            train_images = load_photos(data, data.split["train"], device, on_photo=step)
            test_images = (load_photos(data, data.split["test"], device, on_photo=step) if data.split.get("test")
                           else None)
        masks = {k: load_masks(data, data.split[k], device) if data.masks_train and data.split.get(k) else None
                 for k in ("train", "test")}  # [T,H,W,1], [V,H,W,1]: a user's masks (SceneData.masks_train)
        trainer = Trainer(data, cfg, train_images, test_images, run_dir=run_dir, state=state, near=near,
                          train_masks=masks["train"], test_masks=masks["test"])
        # recorded once the photos read and the model is built: an added photo that cannot be read left both files
        # naming it, and every later command failed on it (a run only mended by editing them)
        atomic_write_text(run_dir / "config.json", cfg.model_dump_json(indent=2) + "\n")
        run_scene.write(run_dir / "scene.json")
        if add_views:
            console.print(f"added {len(add_views)} training view(s) at step {trainer.step}: {', '.join(add_views)} "
                          f"({len(data.split['train'])} in all)")
        kernels = native.describe(device)
        if trainer.imported:
            im = trainer.imported
            console.print(f"the model of {q(im['path'])} ({count(im['gaussians'], 'Gaussian')}, SH degree "
                          f"{im['sh_degree']}, read in {frame_phrase(im)}): its posterior from {count(len(data.split['train']), 'training view')} "
                          f"({data.cameras.width}x{data.cameras.height}), {len(data.split.get('test', ()))} held out, "
                          f"device {device} ({kernels}), no step trained")
        else:
            console.print(f"training {count(len(trainer.model), 'Gaussian')} on {count(len(data.split['train']), 'view')} "
                          f"({data.cameras.width}x{data.cameras.height}), {len(data.split.get('test', ()))} held "
                          "out, " + (f"{len(data.split['calibration'])} set aside for calibration, "
                                     if data.split.get("calibration") else "") +
                          f"device {device} ({kernels}), {cfg.iterations} steps, at most "
                          f"{count(trainer.budget.max_gaussians, 'Gaussian')} ({trainer.budget.reason})")
        if cfg.scene.test_indices is not None or cfg.scene.train_indices is not None:
            # indices count the scene's views, after any photo left out: the names say which views they are
            held = [data.cameras.image_names[i] for i in data.split.get("test", ())]
            console.print(f"held out (scene.test_indices / train_indices count the scene's {len(names)} views, in name "
                          f"order): {list_names(held, 10) if held else 'none'}")
        views = len(data.split["train"])
        run_notes = ([f"batch_size = {cfg.batch_size} is more than the {views} training views: each step renders all "
                      f"{views}"] if cfg.batch_size > views else [])
        if trainer.low_res_until > 0 and trainer.low_cams is not None and min(trainer.low_cams.width,
                                                                               trainer.low_cams.height) < 16:
            # (a scale of 1e-12 trained on 1x1 images without a word: 1.3 dB and 40 % of the Gaussians lost)
            run_notes.append(f"the low-resolution phase (its first {trainer.low_res_until} steps) trains on "
                             f"{trainer.low_cams.width}x{trainer.low_cams.height} images (low_res_scale = "
                             f"{cfg.low_res_scale:g}), too few pixels to place Gaussians by")
        member = run_dir.parent.name == ENSEMBLE_MEMBERS
        for note in [*data.notes, *small_images_notes(data.cameras.width, data.cameras.height, cfg.scene.downscale),
                     *run_notes, *trainer.init_notes, *_unused_setting_notes(cfg, member), *_settle_notes(cfg, resume),
                     *_reset_notes(cfg), *_posterior_notes(cfg)]:
            console.print(f"[yellow]note:[/] {note}")
        for text in workspace_notes(scene):
            console.print(f"[yellow]note:[/] {text}")
        trainer.on_log = lambda rec: console.log(log_line(rec)) if "eval_psnr" in rec else None
        trainer.on_band = lambda check: console.log(band_reason(check))
        trainer.on_growth = lambda check: console.log(growth_reason(check))
        # only the test that switches the exposures on is news (the others are in train_summary.json)
        trainer.on_exposure = lambda check: console.log(exposure_reason(check)) if check.enabled else None
        if on_trainer is not None:
            on_trainer(trainer)
        first_step, started = trainer.step, time.perf_counter()
        try:
            trainer.fit()
        except TrainingInterrupted as err:
            raise Interrupted(f"training interrupted at step {err.step}; checkpoint saved ({err.path})",
                              hint=f"Continue with: uncertsplat train {q(scene)} -o {q(resume_dir or run_dir)} --resume") from None

        meta = {"variant": cfg.variant, "extent": trainer.extent, "step": trainer.step,
                "sh_degree_active": trainer.sh_degree, "temperature": cfg.variational.gate_temperature}
        write_point_cloud_ply(run_dir / "point_cloud.ply", trainer.model, variant=cfg.variant, extent=trainer.extent,
                              temperature=cfg.variational.gate_temperature, sh_degree=trainer.sh_degree)
        write_variational_ply(run_dir / "variational.ply", trainer.model, meta=meta)
        exposure = trainer.exposure_record(names)
        if exposure is not None:
            exposure.write(run_dir / RunExposure.FILE_NAME)
            console.print(exposure.describe())
        elif (run_dir / RunExposure.FILE_NAME).exists():  # an earlier training of this folder learned exposures
            (run_dir / RunExposure.FILE_NAME).unlink()
        transients = _write_transients(run_dir, trainer, names)
        held = trainer.evaluate()
        fit_psnr = trainer.training_psnr()
        warnings = poor_fit_warnings(fit_psnr, scene, cfg) if not trainer.imported else imported_fit_warnings(
            fit_psnr, trainer.imported)
        if warnings and trainer.step < SHORT_RUN_STEPS and not trainer.imported:  # it judges a fitted model
            warnings = [f"{w} (after only {trainer.step} steps the model may not fit its photos yet: judge this on "
                        "a full run)" for w in warnings]
        warnings += few_carriers_warning(trainer.model, cfg, trainer.extent, trainer.prior, trainer.step)
        if trainer.imported and cfg.scene.calibration_holdout:
            # another tool held out at most this scene's test views (INRIA's --eval: every 8th), so it likely trained
            # on the views set aside here, whose residuals then read like training views' to `evaluate`'s calibration
            warnings.append(f"{cfg.scene.calibration_holdout} view(s) are set aside for calibration "
                            "(scene.calibration_holdout), but the model's own trainer likely trained on them (INRIA's "
                            "--eval holds out only every 8th view, this scene's test views): `evaluate` would fit "
                            "the std factor and the pixel noise on views the model has seen, as on training views, "
                            "and the std would read too small on new ones; import without calibration_holdout unless "
                            "that trainer held those views out too")
        # the views added during the run are left out: one added in a gap is fitted poorly whatever its exposure (a
        # view added there raised the warning on photos of one exposure)
        late = {n for added in views_added for n in added.names}
        skip = [k for k, i in enumerate(data.split["train"]) if names and names[i] in late]
        warnings += exposure_warnings(trainer.photo_gains(skip=skip), trainer.exposure is not None, trainer.step,
                                      imported=bool(trainer.imported))
        warnings += [w for w in [transients_warning(transients, len(data.split["train"]), trainer.transients_stopped)]
                     if w]
        # what loading changed of the photos (turned, cropped, left out) goes into the summary, so the report shows it
        # (memory holding growth was said when it happened)
        recorded = warnings + [w for w in [trainer.memory_hold_warning()] if w] + [f"scene: {note}" for note in data.notes]
        summary = TrainSummary(**trainer.summary(), test_psnr=held.get("psnr"), test_ssim=held.get("ssim"),
                               test_render="expected render (variational.expected_render_sample)",
                               num_test_views=len(data.split.get("test", ())), device=str(device), kernels=kernels,
                               scene=str(scene.resolve()), train_psnr=fit_psnr, warnings=recorded,
                               transients=transients)
        summary.write(run_dir / "train_summary.json")
        psnr_txt = f", held-out PSNR {held['psnr']:.2f} dB" if held else ""
        fit_txt = f", training views {_psnr_shown(fit_psnr):.2f} dB" if fit_psnr is not None else ""
        # the steps' time leaves the test renders and checkpoints out (4.5 % of a 40k-step tiny run): the loop's wall
        # time beside it, when this command ran the whole training, so the line agrees with the clock
        wall = time.perf_counter() - started
        wall_txt = (f" ({wall:.1f} s with its test renders and checkpoints)"
                    if first_step == 0 and wall > 1.02 * trainer.elapsed and f"{wall:.1f}" != f"{trainer.elapsed:.1f}"
                    else "")
        if trainer.imported:
            console.print(f"{done_label}: the posterior of {len(trainer.model)} Gaussians "
                          f"({trainer.model.num_carriers} with a posterior) in {wall:.1f} s{psnr_txt}{fit_txt} -> {run_dir}")
        else:
            console.print(f"{done_label}: {trainer.step} steps in {trainer.elapsed:.1f} s{wall_txt}, {len(trainer.model)} "
                          f"Gaussians ({trainer.model.num_carriers} with a posterior){psnr_txt}{fit_txt} -> {run_dir}")
        for warning in warnings:
            console.print(f"[yellow]warning:[/] {warning}")
        if summary.posterior is not None and summary.posterior.carriers:
            last = summary.posterior_updates[-1].model_dump() if summary.posterior_updates else None
            console.print(describe_posterior(summary.posterior.model_dump(), last))
    return run_dir


def imported_fit_warnings(fit_psnr: float | None, imported: dict) -> list[str]:
    """The warning for a model trained elsewhere (``init_ply``) that renders its training views poorly here: a model
    its trainer fitted renders them far above ``POOR_FIT_PSNR`` unless it is not in the scene cameras' frame or that
    trainer renders otherwise."""
    if fit_psnr is None or fit_psnr >= POOR_FIT_PSNR:
        return []
    frame = imported["frame"]
    if frame == "aligned":  # a frame the points placed and the photos fitted: no frame to try, the model is the doubt
        fitted = (imported.get("alignment") or {}).get("refined_psnr")
        fit = f", fitted to the photos from {fitted[0]:.1f} to {fitted[1]:.1f} dB" if fitted else ""
        return [f"the model of {imported['path']} renders its training views at {_psnr_shown(fit_psnr):.2f} dB here "
                f"(read in {frame_phrase(imported)}{fit}; {imported['in_view_share']:.0%} of its Gaussians inside "
                "some training view): its trainer fitted them far better, and no frame the points and photos "
                "allow renders them better, so the model is likely of another scene (or of another capture of the "
                "place: a scene whose walls or ground alone match the points still gets a frame), or it renders "
                "otherwise than 3DGS does (an antialiased or filtered renderer, another background); where the trainer's frame is known, give it (--from-ply-transform FILE): its "
                "uncertainty here describes this render"]
    try_other = ("check init_ply_transform" if frame == "transform" else
                 "read in another: --set init_ply_frame=run, or =align to find its frame on the scene's sparse points"
                 if frame == "source" else
                 "read in another: --set init_ply_frame=source")
    read_in = frame_phrase(imported)
    return [f"the model of {imported['path']} renders its training views at {_psnr_shown(fit_psnr):.2f} dB here "
            f"(read in {read_in}; {imported['in_view_share']:.0%} of its Gaussians inside some training view): its "
            f"trainer fitted them far better, so the model and the scene's cameras are likely not in one frame "
            f"({try_other}; a trainer that normalises its world, as nerfstudio's splatfacto and gsplat's "
            "simple_trainer do by default, writes the model in that frame: give the transform it used, "
            "--from-ply-transform dataparser_transforms.json for nerfstudio; another mapping of the photos has "
            "another frame), or it renders otherwise than 3DGS does (an antialiased or filtered renderer, another "
            "background): its uncertainty here describes this render"]


SHORT_RUN_STEPS = 1000
"""A run shorter than this has not fitted its photos yet (the tiny preset's 300-step smoke runs): `train`'s warnings
on the fit and on the photos' brightness say so."""
POOR_FIT_PSNR = 20.0
"""A model whose render of its own training views stays below this PSNR (dB) gets a warning: 3DGS fits the photos it
trains on far better than that when the cameras are right (the demo scene 33 dB and more, fern and bonsai 25-30 dB
at the paper's 7000 steps); bonsai trained on an SfM run caught in a wrong focal length fitted them at 18.9 dB."""


def _write_transients(run_dir: Path, trainer, names) -> dict[str, float] | None:
    """``RUN/transients/`` (``data.dataset.TRANSIENTS_FOLDER``): the transient regions training found, one mask per
    training photo with any (white where the pixels count, COLMAP's name: a workspace's ``masks/`` takes them as
    they are); an earlier training's folder is replaced. Returns {photo: share of its pixels left out}, or None with
    ``transients.detect`` off (and no folder)."""
    import shutil

    from uncertsplat.data.dataset import TRANSIENTS_FOLDER, write_transient_masks
    from uncertsplat.train.transients import transients_note

    folder = run_dir / TRANSIENTS_FOLDER
    partial, old = folder.with_name(f"{TRANSIENTS_FOLDER}.partial"), folder.with_name(f"{TRANSIENTS_FOLDER}.old")
    if old.exists():  # an earlier call stopped while it swapped the folders: the one it moved aside was whole
        if folder.exists():
            shutil.rmtree(old)
        else:
            old.rename(folder)
    if partial.exists():  # (one that stopped while it wrote: incomplete)
        shutil.rmtree(partial)
    if not trainer.cfg.transients.detect:
        if folder.exists():
            shutil.rmtree(folder)
        return None
    regions = trainer.transient_regions(names)
    write_transient_masks(partial, regions)  # the new masks beside the old ones, then swapped: never none of either
    shares = {name: round(1.0 - float(keep.float().mean()), 4) for name, keep in regions.items()}
    if folder.exists():
        folder.rename(old)
    if regions:
        partial.rename(folder)
    if old.exists():
        shutil.rmtree(old)
    console.print(transients_note(shares, len(trainer.train_idx), stopped=trainer.transients_stopped)
                  + (f" ({folder})" if regions else ""))
    return shares


def _workspace_report(scene: Path):
    """The ``reconstruct`` report of a workspace scene; None for other scenes or an unreadable report."""
    from uncertsplat.sfm.report import load_report

    if not scene.is_dir():
        return None
    try:
        return load_report(scene)
    except UserError:  # a damaged report must not stop a training (the scene loader decides what it needs)
        return None


def workspace_notes(scene: Path) -> list[str]:
    """What ``train`` says before it starts about the scene's SfM: its mapping runs disagreed (the cameras may be
    wrong, and a bad SfM costs a whole training to find out)."""
    report = _workspace_report(scene)
    if report is None or report.mapping_agreed is not False:
        return []
    kept = next((a for a in report.mapping_attempts if a.kept), None)
    which = f" (kept seed {kept.seed}, {kept.num_observations:,} feature observations)" if kept else ""
    return [f"the mapping runs of {scene / 'reconstruct_report.json'} disagreed{which}: if the model fits its own "
            f"training views poorly, `train` says so at the end; {_map_again_advice(scene)} (or more mapping "
            "attempts) maps again"]


SMALL_TRAINING_SIDE = 300
"""A training image whose long side is below this many pixels after ``scene.downscale`` has little detail to fit
(the paper's LLFF setting trains at 504 px, ``pipelines/photos.toml`` at about 400 px). The paper preset's downscale 8 is
for photos of about 4000 px: 400 px photos train at 50 px, and a phone's photos that ``reconstruct`` resized to its
``max_image_size`` of 1600 px at 200 px."""


def small_images_notes(width: int, height: int, downscale: float) -> list[str]:
    """The note for training images that ``scene.downscale`` made very small, with a downscale that trains at about
    800 px on the long side (or at the photos' own size)."""
    side = max(width, height)
    if downscale <= 1.0 or side >= SMALL_TRAINING_SIDE:
        return []
    photo = side * downscale
    better = max(1.0, round(photo / 800.0, 2))
    return [f"training at {width}x{height}: scene.downscale={downscale:g} shrinks photos of about {photo:.0f} px to "
            f"{side} px, which leaves little to fit; --set scene.downscale={better:g} trains at about "
            f"{photo / better:.0f} px"]


def exposure_warnings(gains: list[float], learned: bool, steps: int | None = None,
                      imported: bool = False) -> list[str]:
    """The warning for training photos of different brightness (``strategy.exposure.EXPOSURE_SPREAD``) when their
    exposures were not ``learned``; after fewer than ``SHORT_RUN_STEPS`` ``steps`` it leads with the caveat (a model
    that has not fitted its photos yet shows such gains on photos of one exposure too). ``imported``: a model trained
    elsewhere (``init_ply``: fitted by its own trainer, whatever ``steps`` says), which ``exposure=affine`` cannot
    retrain."""
    spread = gain_spread(gains)
    if learned or spread < EXPOSURE_SPREAD:
        return []
    gains_text = f"relative gains {min(gains):.2f}-{max(gains):.2f} on {len(gains)} of them"
    if imported:
        return [f"the training photos differ in brightness against the model ({gains_text}): if they were taken "
                "with automatic exposure or white balance, the model's residuals, and the uncertainty built from "
                "them, hold the difference (a trainer that learns a per-photo exposure fits it instead); if the "
                "model renders poorly overall (the warning above), that is the likelier cause"]
    if steps is not None and steps < SHORT_RUN_STEPS:
        return [f"after only {steps} steps the training photos differ in brightness against the model ({gains_text}), "
                "as a model this short often shows on photos of one exposure: if a full run says so too, they were "
                "likely taken with automatic exposure or white balance, and --set exposure=affine learns a gain and "
                "offset per photo"]
    return [f"the training photos differ in brightness ({gains_text}): if they were taken with automatic exposure or "
            "white balance, train again with --set exposure=affine (a gain and offset per photo, learned with the "
            "model)"]


def _psnr_shown(psnr: float) -> float:
    """A training-view PSNR as printed: rounded down to 0.01 dB, so that a value just below ``POOR_FIT_PSNR`` reads as
    below it both in the closing line and in the warning (19.995 was "20.00 dB" there and "19.99" here)."""
    return math.floor(psnr * 100.0 + 1e-6) / 100.0


def _map_again_advice(scene: Path) -> str:
    """How to map a workspace's photos again: the reconstruct command, or, for the output of a pipeline's reconstruct
    stage (its manifest.json), that stage's key in the pipeline."""
    from uncertsplat.schemas import Manifest

    try:
        manifest = Manifest.read_optional(Path(scene) / Manifest.FILE_NAME)
    except UserError:  # damaged or of another version: the command's own advice
        manifest = None
    if manifest is not None and manifest.stage == "reconstruct":
        seed = int(manifest.config.get("seed", 0)) + 1
        return f"running the pipeline again with --set {manifest.name}.seed={seed}"
    return "`uncertsplat reconstruct` with --overwrite and another --seed"


def _changed_fit_settings(cfg: TrainConfig | None) -> list[str]:
    """The settings of how the model fits (learning rates, the gate's prior, the first opacity) that ``cfg`` sets
    apart from their defaults (no preset changes them)."""
    if cfg is None:
        return []
    default = TrainConfig()
    out = [f"lr.{k}" for k, v in cfg.lr.model_dump().items() if v != getattr(default.lr, k)]
    for key in ("gate_prior_mean", "gate_prior_std", "position_prior_std"):
        if getattr(cfg.variational, key) != getattr(default.variational, key):
            out.append(f"variational.{key}")
    return out + (["init_opacity"] if cfg.init_opacity != default.init_opacity else [])


def poor_fit_warnings(fit_psnr: float | None, scene: Path, cfg: TrainConfig | None = None) -> list[str]:
    """The warning for a model that cannot fit its own training views (``POOR_FIT_PSNR``), naming what to check:
    the settings of the fit the run changed from their defaults (``cfg``; a helper's lr.scales of 1e12 was blamed on
    the photos), the SfM health report when the scene is a ``reconstruct`` workspace."""
    if fit_psnr is None or fit_psnr >= POOR_FIT_PSNR:
        return []
    changed = _changed_fit_settings(cfg)
    where = "the camera poses"
    report = _workspace_report(scene)
    if report is not None:
        err = "n/a" if report.mean_reprojection_error is None else f"{report.mean_reprojection_error:.2f} px"
        where = (f"the camera poses ({scene / 'reconstruct_report.json'}: {report.num_points3d:,} points, "
                 f"reprojection error {err}"
                 + (", its mapping runs disagreed" if report.mapping_agreed is False else "") +
                 f"; {_map_again_advice(scene)} maps the photos again)")
    first = (f"the settings changed from their defaults ({', '.join(changed)}), " if changed else "")
    return [f"the model fits its own training views at only {_psnr_shown(fit_psnr):.2f} dB (below {POOR_FIT_PSNR:g} dB): "
            f"check {first}{where}, moving objects or exposure changes between the photos"]


__all__ = ["POOR_FIT_PSNR", "exposure_warnings", "poor_fit_warnings", "small_images_notes", "train_model",
           "workspace_notes"]
