"""Stage ``evaluate``: Monte-Carlo uncertainty maps of held-out views, scored against the images.

Config in, files out: reads the run (``baselines.load_run``) and its scene, calls the evaluation
engine (``eval.engine``: K samples per view, every metric) and writes into ``RUN/eval/``:

- ``maps/{image}.exr``: float channels ``rgb_mean.R/G/B``, ``rgb_std.R/G/B``, ``depth_mean.Z``,
  ``depth_std.Z`` (depth in the run's normalised world units; layout in ``io.maps``), and PNG previews
  ``{image}_{gt,mean,error,std,error_rank,std_rank,depth,depth_std}.png``. Colour scales: ``error`` and
  ``std`` use the turbo map over the 1st-99th percentile of that map (``--set preview=fixed`` maps [0, 1]);
  the ``*_rank`` previews colour each pixel by its rank, so error and std compare without any scale. A photo the
  scene turned to its common orientation (``SceneData.photo_fits``) has its maps turned back, as the photo lies.
- ``metrics.json``: the ``EvalReport`` (per view by image name, mean, curves, calibration).
- with ``--split train``, the same files go to ``RUN/eval-train/`` (``eval_dir``): the held-out evaluation in
  ``RUN/eval/`` stays as it was (only the pixel-noise cache ``residual.pt`` below is kept there, for every split).
- ``config.json``: the resolved ``EvalConfig``.
- ``residual.pt``: the pixel noise fitted on the training views, with a key of the model and the settings it
  depends on (``stages.residual_cache``): the next ``evaluate`` or ``prune`` of the same model reads it.

A ``prune`` output that removed nothing holds its source run's model file unchanged; its evaluation with the
settings, versions and device the source run was evaluated with is that one, so it is copied
(``same_model_evaluation``; ``--set reuse=false`` evaluates again).

The prediction is the Monte-Carlo mean (as in the paper); the per-pixel uncertainty is the unbiased
std over the K samples.
"""

from __future__ import annotations

import math
import os
import shutil
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import torch

from uncertsplat.config import EvalConfig
from uncertsplat.console import console, print_table
from uncertsplat.errors import UserError, run_folder_missing
from uncertsplat.eval.engine import (
    GIVEN_SCENE_GT,
    IMPLAUSIBLE_DEPTH_NOTE,
    MASKED_NOTE,
    NOT_A_NUMBER_NOTE,
    PHOTO_MASKS_NOTE,
    TRANSIENT_MASKS_NOTE,
    ZERO_STD_NOTE,
    ViewMaps,
)
from uncertsplat.eval.nll import NLL_WORSE_BY
from uncertsplat.eval.tails import MIN_DOF
from uncertsplat.eval.tails import half_width as _half_width
from uncertsplat.io.maps import (
    EXR_ALPHA_CHANNEL,
    EXR_CHANNELS,
    EXR_DEPTH_TO_SOURCE,
    EXR_RGB_DOF,
    EXR_RGB_PREDICTIVE,
    map_stem,
)
from uncertsplat.schemas.runs import RunExposure
from uncertsplat.schemas.scene import RunScene

if TYPE_CHECKING:
    from uncertsplat.schemas.metrics import EvalReport


def eval_dir(run_dir: Path, cfg: EvalConfig) -> Path:
    """Where an evaluation of ``run_dir`` goes: ``RUN/eval`` for the held-out views (what ``report`` and ``prune``
    read), ``RUN/eval-train`` for ``split = "train"``, so that scoring the training views never replaces the
    held-out evaluation."""
    return Path(run_dir) / ("eval" if cfg.split == "test" else "eval-train")


def write_view_maps(folder: Path, maps: ViewMaps, preview: str, turns: dict[str, int] | None = None,
                    depth_to_source: float | None = None, among: Sequence[str] = ()) -> None:
    """EXR float maps and PNG previews of one view (see the module docstring for the colour scales), named by
    ``map_stem(name, among)``: ``among`` the names of every view the evaluation writes.

    ``turns``: {image name: clockwise quarter turns} of the photos the scene turned to its common orientation
    (``SceneData.photo_fits``); their maps are turned back, so that each view's maps lie as its photo does.
    ``depth_to_source``: ``SceneData.depth_scale_to_gt``, written to the EXR header (``EXR_DEPTH_TO_SOURCE``)."""
    from uncertsplat.data.dataset import turned_back
    from uncertsplat.io.images import write_exr, write_png
    from uncertsplat.report.colormaps import colorize, rank_colorize

    folder = Path(folder)
    stem = map_stem(maps.name, among)
    back = (turns or {}).get(maps.name, 0)
    gt, pred, std, depth_mean, depth_std = (turned_back(t, back) for t in (maps.gt, maps.rgb_mean, maps.rgb_std,
                                                                         maps.depth_mean, maps.depth_std))
    arrays = [pred[..., c] for c in range(3)] + [std[..., c] for c in range(3)] + [depth_mean[..., 0], depth_std[..., 0]]
    # the maps say which predictive their std is the std of (a reader of the EXR alone can build intervals)
    predictive = {EXR_RGB_PREDICTIVE: "gaussian" if maps.dof is None else "student-t"}
    if maps.dof is not None:
        predictive[EXR_RGB_DOF] = float(maps.dof)
    if depth_to_source is not None:  # the depths are in the run's normalised units: the factor to the scene's own
        predictive[EXR_DEPTH_TO_SOURCE] = float(depth_to_source)
    channels = {n: a.numpy() for n, a in zip(EXR_CHANNELS, arrays, strict=True)}
    if maps.alpha_mean is not None:  # where rays meet little of the model (a reader masks floaters and empty sky)
        channels[EXR_ALPHA_CHANNEL] = turned_back(maps.alpha_mean, back)[..., 0].numpy()
    write_exr(folder / f"{stem}.exr", channels, predictive)
    err = (pred - gt).abs().mean(-1).numpy()
    s = std.mean(-1).numpy()
    write_png(folder / f"{stem}_gt.png", gt.numpy())
    write_png(folder / f"{stem}_mean.png", pred.numpy())
    write_png(folder / f"{stem}_error.png", colorize(err, mode=preview))
    write_png(folder / f"{stem}_std.png", colorize(s, mode=preview))
    write_png(folder / f"{stem}_error_rank.png", rank_colorize(err))
    write_png(folder / f"{stem}_std_rank.png", rank_colorize(s))
    write_png(folder / f"{stem}_depth.png", colorize(depth_mean[..., 0].numpy(), mode="percentile"))
    write_png(folder / f"{stem}_depth_std.png", colorize(depth_std[..., 0].numpy(), mode="percentile"))



def _put_in_place(out: Path, maps: Path | None, report, cfg: EvalConfig) -> None:
    """The finished evaluation into ``out``: ``maps`` (its staging folder; None: no maps, and an earlier evaluation's
    are removed, which would sit beside metrics they do not belong to) as ``out/maps``, then ``metrics.json`` and
    ``config.json``. The earlier metrics.json goes first, so that a stop between the steps (milliseconds) leaves an
    evaluation without metrics (evaluated again), never new maps beside old metrics."""
    from uncertsplat.io.atomic import atomic_write_text

    (out / "metrics.json").unlink(missing_ok=True)
    old = out / f".maps-old-{os.getpid()}"
    if (out / "maps").is_dir():
        (out / "maps").rename(old)
    if maps is not None:
        if not maps.is_dir():  # no view written (none had maps to write): an empty folder, as before
            maps.mkdir(parents=True)
        maps.rename(out / "maps")
    atomic_write_text(out / "metrics.json", report.to_json() + "\n")
    atomic_write_text(out / "config.json", cfg.model_dump_json(indent=2) + "\n")
    shutil.rmtree(old, ignore_errors=True)


def same_model_evaluation(run_dir: Path, cfg: EvalConfig, device: torch.device) -> Path | None:
    """The ``eval`` folder of ``run_dir``'s source run when evaluating ``run_dir`` would repeat it exactly, else None.

    That is when ``run_dir`` is a ``prune`` output (``prune.json``) whose ``variational.ply`` is byte for byte the
    source run's (the SHA-256 ``prune.json`` recorded, of both files as they are now), whose ``config.json`` and
    ``scene.json`` equal the source's (but for the scene's path relative to each), and the source's ``eval/metrics.json`` was written with this config (its
    hash), by the same versions (uncertsplat, Python, torch) on the same device, with its maps and config beside it.
    Any file missing or unreadable: None (evaluate as usual).
    """
    from uncertsplat.provenance import file_sha256, hash_config, versions
    from uncertsplat.schemas.metrics import EvalReport
    from uncertsplat.schemas.prune import PruneReport

    if not cfg.reuse or cfg.split != "test":
        return None
    try:
        pruned = PruneReport.read_optional(run_dir / PruneReport.FILE_NAME)
        if pruned is None or pruned.source_model != "variational.ply":
            return None
        source = pruned.source_folder(run_dir)
        if source.resolve() == run_dir.resolve():
            return None
        if (run_dir / "config.json").read_bytes() != (source / "config.json").read_bytes():
            return None
        # scene.json alike but for where the scene lies from each (prune writes its own relative path)
        scenes = [RunScene.read(d / RunScene.FILE_NAME) for d in (run_dir, source)]
        if ({**scenes[0].model_dump(), "scene": None, "scene_from_run": None}
                != {**scenes[1].model_dump(), "scene": None, "scene_from_run": None}
                or scenes[0].scene_folder(run_dir).resolve() != scenes[1].scene_folder(source).resolve()):
            return None
        here, there = (d / RunExposure.FILE_NAME for d in (run_dir, source))
        if (here.read_bytes() if here.is_file() else None) != (there.read_bytes() if there.is_file() else None):
            return None
        previous = EvalReport.read_optional(source / EvalReport.FILE_NAME)
        if previous is not None and previous.run_sha256 is not None \
                and previous.run_sha256 != run_sha256(source, source / "variational.ply"):
            return None  # the source's evaluation is of its files (or the photos' masks) as they were: not now
        if (previous is None or previous.device != str(device) or previous.versions != versions()
                or not (source / "eval" / "config.json").is_file() or not (source / "eval" / "maps").is_dir()):
            return None
        # the settings it was measured with and wrote its files with, but for whether it may be reused (one made with
        # --set reuse=false was never copied, though `evaluate` and `prune` of the source reuse it)
        used = EvalConfig.model_validate_json((source / "eval" / "config.json").read_text(encoding="utf-8"))
        if (previous.config_hash != hash_config(used.model_dump(mode="json"))
                or used.model_dump(mode="json", exclude={"reuse"}) != cfg.model_dump(mode="json", exclude={"reuse"})):
            return None
        digest = pruned.source_model_sha256
        if file_sha256(run_dir / "variational.ply") != digest or file_sha256(source / "variational.ply") != digest:
            return None
    except (OSError, UserError, ValueError):  # (ValueError: an eval/config.json that is no EvalConfig)
        return None
    return source / "eval"


OUTPUT_SETTINGS = ("save_maps", "preview", "reuse")
"""``EvalConfig`` fields that change what ``evaluate`` writes or whether it runs, not the numbers it measures."""


def run_sha256(run_dir: Path, model_file: Path) -> str:
    """SHA-256 over what an evaluation of ``run_dir`` scores: ``model_file`` and the run's ``config.json`` and
    ``scene.json`` (either may be missing), its ``exposure.json`` when it has one, and the photos' own masks as they
    are now when the scene has them (``sfm.scene.run_mask_digest``: other masks score other pixels).

    Raises:
        OSError: the model file cannot be read.
    """
    import hashlib

    from uncertsplat.provenance import file_sha256

    parts = [file_sha256(model_file)]
    for name in ("config.json", "scene.json"):
        path = Path(run_dir) / name
        parts.append(file_sha256(path) if path.is_file() else "-")
    exposure = Path(run_dir) / RunExposure.FILE_NAME
    if exposure.is_file():  # only when present: the runs without one keep the hash they were evaluated under
        parts.append(file_sha256(exposure))
    from uncertsplat.sfm.scene import run_mask_digest

    masks = run_mask_digest(run_dir)
    if masks is not None:  # likewise: a scene without masks keeps its runs' hashes
        parts.append(f"masks:{masks}")
    return hashlib.sha256(" ".join(parts).encode()).hexdigest()


def _mask_note(run_dir: Path, scene, indices) -> str | None:
    """A note when the photos' masks of the evaluated and training views differ from those the run was trained with,
    else None."""
    from uncertsplat.schemas.scene import RunScene
    from uncertsplat.sfm.scene import mask_changes, mask_hashes

    info = RunScene.read_optional(Path(run_dir) / RunScene.FILE_NAME)
    recorded = info.masks if info is not None else {}
    names = scene.cameras.image_names
    compared = list(dict.fromkeys([names[i] for i in indices] + [names[i] for k in ("train", "calibration")
                                                                for i in scene.split.get(k, ())]))
    changed = mask_changes(recorded, mask_hashes(scene, compared), compared)
    if changed is None:
        return None
    what = ("the photos' masks were added after this run was trained (it was trained on every pixel)" if not recorded
            else f"the photos' masks changed since this run was trained ({changed})")
    return f"{what}: the metrics are taken inside the masks as they are now"


def matching_evaluation(run_dir: Path, model_file: Path, cfg: EvalConfig, image_names: list[str],
                        device: torch.device) -> EvalReport | None:
    """``run_dir``'s ``eval/metrics.json`` when it holds what evaluating ``model_file`` on ``image_names`` with
    ``cfg`` would measure: the model file and the run's config and scene files as they are now
    (``EvalReport.run_sha256``), the same views, device and versions (uncertsplat, Python, torch), and settings equal
    to ``cfg`` but for ``OUTPUT_SETTINGS`` (``eval/config.json``, tied to the report by its hash). Else None, as for
    any file missing, unreadable or of an older version that did not record the run."""
    found = _matching(run_dir, model_file, cfg, image_names, device)
    return found[0] if found is not None else None


FEW_SAMPLES_GAP_DB = 0.5
"""``few_samples_notes``: the PSNR by which the mean of the K samples may fall below the one render before it is
noted."""


def few_samples_notes(psnr: float | None, psnr_render: float | None, num_samples: int) -> list[str]:
    """A note when the mean of the K samples' renders scores ``FEW_SAMPLES_GAP_DB`` below the one deterministic
    render: with few samples their mean keeps 1/K of their spread as noise, which costs PSNR and, since that noise is
    largest where the std is, flatters the AUSE (a sweep's fast few-sample points look better on it than they are)."""
    if psnr is None or psnr_render is None or psnr_render - psnr <= FEW_SAMPLES_GAP_DB or num_samples >= 8:
        return []  # (with many samples a gap is the posterior's own, e.g. samples that blur, not their noise)
    return [f"the mean of the {num_samples} samples scores {psnr_render - psnr:.2f} dB below the one render "
            f"({psnr:.2f} against {psnr_render:.2f} dB): with few samples their mean keeps 1/K of their spread as "
            "noise, which also flatters the AUSE (the noise is largest where the std is); more samples (--num-samples) "
            "bring the two together"]


def evaluation_is_current(run_dir: Path, report: EvalReport) -> bool | None:
    """Whether ``report`` (``run_dir``'s eval/metrics.json) scored the run as it is now: its ``run_sha256`` against the
    hash of the model file evaluate would load now (``variational.ply``, else the newest checkpoint) and the run's
    config and scene. None when that cannot be told (no hash recorded: an ensemble, or files of older versions; no
    model file)."""
    from uncertsplat.io.checkpoints import list_checkpoints

    if report.run_sha256 is None:
        return None
    model = Path(run_dir) / "variational.ply"
    if not model.is_file():
        # the newest checkpoint (evaluate loads the newest good one: read as stale only after a damaged last one)
        found = list_checkpoints(run_dir)
        if not found:
            return None
        model = found[-1][1]
    try:
        return run_sha256(Path(run_dir), model) == report.run_sha256
    except OSError:
        return None


def _matching(run_dir: Path, model_file: Path, cfg: EvalConfig, image_names: list[str],
              device: torch.device) -> tuple[EvalReport, EvalConfig] | None:
    """``matching_evaluation``'s report and the settings it was measured with (``eval/config.json``)."""
    from uncertsplat.provenance import hash_config, versions
    from uncertsplat.schemas.metrics import EvalReport

    try:
        report = EvalReport.read_optional(run_dir / EvalReport.FILE_NAME)
        if (report is None or report.run_sha256 is None or report.image_names != list(image_names)
                or report.device != str(device) or report.versions != versions()):
            return None
        used = EvalConfig.model_validate_json((run_dir / "eval" / "config.json").read_text(encoding="utf-8"))
        if report.config_hash != hash_config(used.model_dump(mode="json")):
            return None
        if used.model_dump(mode="json", exclude=set(OUTPUT_SETTINGS)) != cfg.model_dump(
                mode="json", exclude=set(OUTPUT_SETTINGS)):
            return None
        if run_sha256(run_dir, model_file) != report.run_sha256:
            return None
    except (OSError, UserError, ValueError):
        return None
    return report, used


def _copy_evaluation(source_eval: Path, out: Path, run_dir: Path, device: torch.device) -> None:
    """Copy ``source_eval``'s maps, metrics and config to ``out`` (``run_dir``'s evaluation, evaluated on ``device``),
    with its pixel noise and predictive keyed for ``run_dir``, adding a note to the metrics and ``run_dir``'s own
    ``run_sha256`` (its scene.json may differ from the source's in the scene's relative path alone: the copy was
    taken for an earlier state of the run and evaluated again); the copy is built beside ``out`` and renamed into
    place, so a failure leaves ``out`` as it was."""
    import shutil

    from uncertsplat.io.atomic import temp_folder
    from uncertsplat.schemas.metrics import EvalReport
    from uncertsplat.stages.predictive_cache import FILE_NAME as PREDICTIVE
    from uncertsplat.stages.predictive_cache import rekeyed_predictive
    from uncertsplat.stages.residual_cache import FILE_NAME, rekeyed_residual

    tmp = temp_folder(".eval-copy-", out.parent)
    try:
        staged = tmp / "eval"
        # what evaluate writes, nothing else (a pipeline's manifest there belongs to the source's stage)
        shutil.copytree(source_eval / "maps", staged / "maps")
        shutil.copy2(source_eval / "config.json", staged / "config.json")
        shutil.copy2(source_eval / "metrics.json", staged / "metrics.json")
        # the same model's pixel noise and predictive (what Predictor.load reads, where the scene is gone), keyed
        # for this run: its scene.json differs from the source's in the scene's path, and so do the keys (copied as
        # they were, the noise was never read and Predictor.load found no predictive.pt)
        used = EvalConfig.model_validate_json((source_eval / "config.json").read_text(encoding="utf-8"))
        source, model = source_eval.parent, "variational.ply"  # (the only model file same_model_evaluation copies for)
        for name, rekey in ((FILE_NAME, lambda b: rekeyed_residual(b, source, run_dir, model, used, device)),
                            (PREDICTIVE, lambda b: rekeyed_predictive(b, source, run_dir, model))):
            data = rekey((source_eval / name).read_bytes()) if (source_eval / name).is_file() else None
            if data is not None:
                (staged / name).write_bytes(data)
        report = EvalReport.read(staged / "metrics.json")
        report.notes.append(f"copied from {source_eval}: this run's model file is that run's, unchanged (prune "
                            "removed nothing), and it was evaluated with the same settings, versions and device "
                            "(--set reuse=false evaluates again)")
        if report.run_sha256 is not None:
            report.run_sha256 = run_sha256(run_dir, run_dir / "variational.ply")
        (staged / "metrics.json").write_text(report.to_json() + "\n", encoding="utf-8")
        if out.exists():
            shutil.rmtree(out)
        staged.rename(out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


FEW_CALIBRATION_VIEWS = 3
"""A std factor fitted on fewer views than this is named as resting on too few (3 set aside is the recommended
``scene.calibration_holdout``; one or two views are what a capture of three or four photos leaves)."""


def std_factor_notes(views: int, nll_fitted: float | None, nll_raw: float | None) -> list[str]:
    """What to say of a std factor fitted on ``views`` views that gives the evaluated views ``nll_fitted`` against
    ``nll_raw`` with the raw std: that it rests on too few views, or that these views disagree with it (their NLL
    worse by more than ``NLL_WORSE_BY``)."""
    reasons = []
    if views < FEW_CALIBRATION_VIEWS:
        reasons.append(f"the std factor rests on {views} view{'' if views == 1 else 's'} only, too few to trust")
    if nll_fitted is not None and nll_raw is not None and nll_fitted - nll_raw > NLL_WORSE_BY:
        reasons.append(f"the fitted factor makes these views' NLL worse than the raw std does, by "
                       f"{nll_fitted - nll_raw:.3f} nats (they differ from the views it was fitted on): read the raw "
                       "numbers")
    return ["; ".join(reasons)] if reasons else []


def run(run_dir: Path, cfg: EvalConfig, device: torch.device, quiet: bool = False):
    """Evaluate ``run_dir`` and write ``run_dir/eval`` (maps + metrics.json); returns the EvalReport. An evaluation
    already there that measured what this one would (``matching_evaluation``, its maps too) is kept and returned
    (``cfg.reuse``). ``quiet``: print no table or notes (a caller that reports the numbers itself)."""
    from uncertsplat import native

    with native.single_threaded_torch(device):  # torch's own ops on one thread, the kernels on all
        return _run(run_dir, cfg, device, quiet)


def _finished(run_dir: Path, model_file: Path, cfg: EvalConfig, image_names: list[str], device: torch.device):
    """``run_dir``'s evaluation when it holds what this one would write: ``matching_evaluation``, with the maps of
    every view and the same preview scales when ``cfg.save_maps``; None otherwise or with ``cfg.reuse`` off."""
    from uncertsplat.io.maps import map_stem

    if not cfg.reuse:
        return None
    found = _matching(run_dir, model_file, cfg, image_names, device)
    if found is None:
        return None
    report, used = found
    if not cfg.save_maps:
        return report
    maps = run_dir / "eval" / "maps"
    if not used.save_maps or used.preview != cfg.preview or not all(
            (maps / f"{map_stem(n, image_names)}.exr").is_file() for n in image_names):
        return None
    return report


def kept_evaluation(run_dir: Path, cfg: EvalConfig, device: torch.device):
    """The evaluation ``run`` would keep in ``run_dir/eval`` (``_finished``: the same model file, views, settings,
    versions and device, its maps there), or None; for a caller that must not move it away first (``run``)."""
    from uncertsplat.baselines import load_run
    from uncertsplat.eval.engine import split_indices

    if not cfg.reuse or not (Path(run_dir) / "eval" / "metrics.json").is_file():
        return None
    try:
        loaded = load_run(run_dir, device)
        scene = loaded.load_scene()
    except UserError:
        return None
    if not _in_frame(loaded, scene, eval_dir(run_dir, cfg)):
        return None
    names = [scene.cameras.image_names[i] for i in split_indices(scene.split, cfg)]
    return _finished(Path(run_dir), Path(loaded.source), cfg, names, device)


def _in_frame(loaded, scene, out: Path) -> bool:
    """Whether an evaluation kept in ``out`` is in the scene folder's frame as it loads now (the folder's frame can
    change after training: a model aligned to metres): its maps' ``uncertsplat:depth_to_source`` is the folder's
    factor; without maps (or a factor in them), when the frame is the one the run was trained in
    (``LoadedRun.frame_note``)."""
    from uncertsplat.io.maps import written_depth_to_source

    try:
        factor = written_depth_to_source(out / "maps")
    except Exception:  # an unreadable map: evaluated again
        return False
    if factor is None:
        return loaded.frame_note is None
    return math.isclose(factor, float(scene.depth_scale_to_gt), rel_tol=1e-5)


def _run(run_dir: Path, cfg: EvalConfig, device: torch.device, quiet: bool = False):
    import time
    from functools import partial

    from uncertsplat.baselines import load_run
    from uncertsplat.data.dataset import photo_turns
    from uncertsplat.eval.engine import evaluate_views, scored_sampler, split_indices
    from uncertsplat.io.atomic import run_lock, staging_folder
    from uncertsplat.provenance import hash_config
    from uncertsplat.schemas.metrics import EvalReport
    from uncertsplat.stages.predictive_cache import keep_predictive
    from uncertsplat.stages.residual_cache import fitted_residual

    t_start = time.perf_counter()

    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise run_folder_missing(run_dir)
    out = eval_dir(run_dir, cfg)
    if out.exists() and not out.is_dir():  # (every write into it failed deep inside, the residual fit's first)
        raise UserError(f"the evaluation's folder {out.name} is a file, not a folder", path=out,
                        hint="Move or delete that file, then run this command again.")
    with run_lock(run_dir, "evaluate"):
        reusable = same_model_evaluation(run_dir, cfg, device)
        if reusable is not None:
            _copy_evaluation(reusable, out, run_dir, device)
    if reusable is not None:
        console.print(f"[bold]evaluate[/] {run_dir}: its model is {reusable.parent}'s, unchanged (prune removed "
                      f"nothing), evaluated there with the same settings: copied {reusable} "
                      "(--set reuse=false evaluates again)")
        return _print_report(run_dir, cfg, EvalReport.read(out / "metrics.json"), out)
    loaded = load_run(run_dir, device)  # any method: variational, deterministic, ensemble, fisher
    unfinished = loaded.warn_if_unfinished()
    scene = loaded.load_scene()
    indices = split_indices(scene.split, cfg)
    masks_note = _mask_note(run_dir, scene, indices)
    # (an evaluation made in another frame of the scene folder holds maps and depths in that frame's units: again;
    # one made with other masks of the photos scored other pixels: again, by its run_sha256)
    done = (_finished(run_dir, Path(loaded.source), cfg, [scene.cameras.image_names[i] for i in indices], device)
            if cfg.split == "test" and _in_frame(loaded, scene, out) else None)
    if done is not None:
        _keep_missing_predictive(run_dir, loaded, scene, cfg, done, device)
        console.print(f"[bold]evaluate[/] {run_dir}: already evaluated with these settings, versions and device "
                      f"({out / 'metrics.json'}; --set reuse=false evaluates again)")
        return done if quiet else _print_report(run_dir, cfg, done, out, written=False,
                                                depth_to_source=scene.depth_to_source)
    # 8-bit photos kept as uint8 (a quarter of the memory), each converted where the engine reads it; the training
    # views without the transient regions training left out of them, as its loss did
    views = loaded.scored_views(scene, indices, cfg.split, depth_folder=cfg.depth_gt,
                                folder_in_scene_units=cfg.depth_scale == "scene", keep_8bit=True)
    if masks_note is not None and not quiet:
        console.print(f"[yellow]note:[/] {masks_note}")
    with run_lock(run_dir, "evaluate"):
        if not quiet:
            console.print(f"[bold]evaluate[/] {run_dir}: {len(indices)} {cfg.split} views, K={cfg.num_samples}, "
                          f"{loaded.size_text()}, {device}")
            for note in loaded.eval_notes(cfg.num_samples):
                # a choice of the command's that changes what is measured, or a posterior that is not there
                if note.startswith(("K=", "no Gaussian carries a posterior")):
                    console.print(f"[yellow]note:[/] {note}")
            if cfg.residual_views == 0 and cfg.residual_scale != "auto":  # (it scales a noise not fitted)
                console.print(f"[yellow]note:[/] residual_scale = {cfg.residual_scale} has no effect with "
                              "residual_views = 0: there is no pixel noise to scale")
        train_views = loaded.training_views(scene)  # the residual fit's (64 by default)
        # the set-aside views' K samples, when the noise is fitted here: the std factor's fit reuses them
        set_aside_maps: dict = {}
        residual = fitted_residual(loaded, scene.scene_scale, scene.split.get("train", ()), cfg, device,
                                   load_views=train_views, write=True,
                                   calibration_indices=scene.split.get("calibration", ()),
                                   set_aside_maps=set_aside_maps)
        with console.status("fitting the std factor on " + ("the views set aside for calibration"
                                                             if scene.split.get("calibration") else "training views")):
            sampler, fit = scored_sampler(partial(loaded.sampler, scene.scene_scale, device), residual,
                                          scene.cameras, scene.split, cfg, device, load_views=train_views,
                                          set_aside_maps=set_aside_maps)
        if cfg.split == "test":  # what the predictive needs besides the model, for Predictor.load without photos
            keep_predictive(loaded, scene, cfg, residual, fit, device)
        # the maps are written into a folder of their own and put in place with metrics.json once every view is
        # scored: an evaluation that fails midway (a full disk, kill -9) leaves the earlier one whole, where deleting
        # its metrics.json first lost it (and one kept left it beside new maps); under the lock, a staging folder
        # found here is a killed evaluation's (staging_folder removes it)
        with staging_folder(out, ".maps-") as staging:
            report = evaluate_views(sampler, views, cfg, device,
                                    on_view=maps_writer(staging, len(views), preview=cfg.preview,
                                                        turns=photo_turns(scene),
                                                        depth_to_source=scene.depth_scale_to_gt, among=views.names)
                                    if cfg.save_maps else None,
                                    std_scale=fit.scale, calibration_views=fit.names, dof=fit.dof,
                                    calibration_held_out=bool(scene.split.get("calibration")),
                                    noise_scale=residual.scale if residual is not None else None,
                                    depth_to_source=scene.depth_to_source,
                                    notes=loaded.eval_notes(cfg.num_samples, scored=cfg.split == "train")
                                    + loaded.exposure_notes() + unfinished
                                    + ([loaded.frame_note] if loaded.frame_note else []),
                                    config_hash=hash_config(cfg.model_dump(mode="json")))
            reach = _reach_notes(sampler, views, device) + (_empty_view_notes(
                sampler, views, scene.cameras[list(scene.split.get("train", ()))], device)
                if cfg.split == "test" and cfg.empty_rays and sampler.empty_std is not None else [])
            # (on training views, or where an empty ray is the photo's background (a transparent scene: no empty-ray
            # term), a view's empty share says nothing of what no photo saw)
            low = low_coverage_notes(sampler.coverage if cfg.empty_rays and sampler.empty_std is not None else None,
                                     loaded.config.iterations,
                                     fitted=getattr(loaded.config, "init_ply", None) is not None)
            few = few_samples_notes(report.mean.psnr, report.mean.psnr_render, cfg.num_samples)
            if cfg.split == "test":  # held-out views one video frame from training ones flatter the model
                few += near_copy_notes(scene, views, report.mean.psnr)
            # the std factor's caveats go into the report too (the console said them, the page did not)
            factor = (std_factor_notes(len(report.calibration_views), report.mean.nll_calibrated, report.mean.nll)
                      if report.std_scale is not None and None not in (report.mean.nll_calibrated, report.mean.nll) else [])
            report.notes.extend([*reach, *low, *few, *factor])
            if Path(loaded.source).is_file():  # which model and run these numbers belong to (prune reads them back)
                report.run_sha256 = run_sha256(run_dir, Path(loaded.source))
            _put_in_place(out, staging if cfg.save_maps else None, report, cfg)
    if quiet:
        return report
    depth_units = [n for n in report.notes
                   if IMPLAUSIBLE_DEPTH_NOTE in n or n.startswith((ZERO_STD_NOTE, NOT_A_NUMBER_NOTE))]
    for note in depth_units:
        console.print(f"[yellow]warning:[/] {note}")
    for note in [*reach, *low, *few]:
        console.print(f"note: {note}")
    return _print_report(run_dir, cfg, report, out, depth_to_source=scene.depth_to_source,
                         seconds=time.perf_counter() - t_start)


def maps_writer(folder: Path, num_views: int, **write) -> Callable[[ViewMaps], None]:
    """``write_view_maps`` into ``folder`` for each of ``num_views`` views (``write``: its other arguments), saying
    after the first one when the rest would take more than 90 % of the disk's free space, with what writes less (30
    views of 1600x1200 wrote 2.2 GB without a word; a full disk ended the evaluation after its renders)."""
    first = [True]

    def on_view(maps: ViewMaps) -> None:
        write_view_maps(folder, maps, **write)
        if first[0] and num_views > 1:
            first[0] = False
            one = sum(f.stat().st_size for f in Path(folder).rglob("*") if f.is_file())
            free = shutil.disk_usage(folder).free
            if one * (num_views - 1) > 0.9 * free:
                console.print(f"[yellow]warning:[/] the maps of the {num_views} views take about "
                              f"{one * num_views / 2**30:.1f} GB ({one / 2**20:.0f} MB a view) and the disk holds "
                              f"{free / 2**30:.1f} GB free: it may fill before the last view; --set save_maps=false "
                              "writes none, --set max_views=N fewer views")

    return on_view


def _keep_missing_predictive(run_dir: Path, loaded, scene, cfg: EvalConfig, report, device: torch.device) -> None:
    """An evaluation kept as it is ("already evaluated") still leaves ``eval/predictive.pt`` (what ``Predictor``
    needs without the photos) when the file is missing or for other settings (a run evaluated before the file
    existed): the std factor, tails and the views they were fitted on from its metrics (the same numbers: JSON keeps a
    float to the bit), the pixel noise from ``residual.pt`` (else fitted, as the evaluation fitted it)."""

    from uncertsplat.eval.engine import StdFit
    from uncertsplat.io.atomic import run_lock
    from uncertsplat.stages.predictive_cache import keep_predictive, read_predictive
    from uncertsplat.stages.residual_cache import fitted_residual

    if cfg.split != "test" or read_predictive(loaded, cfg, scene.source.get("path", run_dir))[0] is not None:
        return
    with run_lock(run_dir, "evaluate"):
        residual = fitted_residual(loaded, scene.scene_scale, scene.split.get("train", ()), cfg, device,
                                   load_views=loaded.training_views(scene), write=True,
                                   calibration_indices=scene.split.get("calibration", ()))
        fit = StdFit(report.std_scale, report.degrees_of_freedom, list(report.calibration_views))
        keep_predictive(loaded, scene, cfg, residual, fit, device)


NEAR_COPY_DB = 4.0
"""``near_copy_notes`` speaks when the model scores less than this many dB above copying each held-out view's
nearest training photo,"""
NEAR_COPY_MIN_DB = 25.0
"""and that copy itself scores at least this: a photo is a near copy of another when it reproduces it (the video
frames of the note: 30.4 dB); a model that renders its held-out views at 15.7 dB was within 4 dB of neighbours at
12.8 dB, which are not copies (a helper's bonsai run of 22 photos)."""


def nearest_training_views(cameras, held: list[int], train: list[int]) -> list[int]:
    """For each of the views ``held``, the training view (of ``train``) nearest in pose: the centres' distance in
    units of the rig radius plus the angle between the optical axes in radians (1 radian weighs a radius)."""
    c = cameras.centers.double().cpu()
    z = cameras.cam_from_world[:, 2, :3].double().cpu()  # [C,3] optical axes in the world
    scale = max(float((c - c.mean(0)).norm(dim=-1).max()), 1e-12)
    tr = torch.tensor(train)
    out = []
    for i in held:
        dist = (c[tr] - c[i]).norm(dim=-1) / scale
        angle = (z[tr] @ z[i]).clamp(-1.0, 1.0).acos()
        out.append(train[int((dist + angle).argmin())])
    return out


def near_copy_notes(scene, views, psnr: float | None) -> list[str]:
    """A note when the held-out views are near copies of training photos: each held-out photo against the training
    photo nearest in pose scores within ``NEAR_COPY_DB`` of the model's PSNR. Every n-th frame of a video held out
    sits one frame from a training one (a robot's drive: the model 33.5 dB held out, above its own training views,
    and a copy of the neighbouring frame 30.4): the held-out metrics then say little about new viewpoints."""
    from uncertsplat.data.dataset import load_images
    from uncertsplat.eval.image import psnr as image_psnr

    train = list(scene.split.get("train", ()))
    held = list(views.indices)
    if psnr is None or not train or not held:
        return []
    # every k-th held-out view of a large set (the mean is what is compared), one training photo at a time (each
    # read once: held-out views often share their nearest), inside the views' masks as the model's PSNR is
    pick = list(range(0, len(held), max(1, -(-len(held) // 200))))
    nearest = nearest_training_views(scene.cameras, [held[k] for k in pick], train)
    scores, last = [], None
    for k, j in sorted(zip(pick, nearest, strict=True), key=lambda kj: kj[1]):
        if j != last:
            copy_image, last = load_images(scene, [j])[0], j  # [H,W,3] at the evaluation's resolution
        mask = views.masks[k] if views.masks is not None else None
        scores.append(float(image_psnr(copy_image.float(), views.images[k].float(), mask)))
    copy = sum(scores) / len(scores)
    if copy < psnr - NEAR_COPY_DB or copy < NEAR_COPY_MIN_DB:  # (a poor model near a poor copy: not a copy)
        return []
    return [f"the held-out views are near copies of training photos: the training photo nearest in pose scores "
            f"{copy:.2f} dB against each held-out photo, the model {psnr:.2f} dB, so these metrics say little about "
            "viewpoints the capture does not have (every n-th frame of a video; hold out a stretch of it instead when "
            "training: --set scene.test_indices=[...])"]


LOW_COVERAGE = 0.6
"""Below this training coverage (the alpha 95 % of the training pixels reach) `evaluate` says that the model leaves
its own training views partly empty: on bonsai 0.43 (dark furniture fitted by the black background showing through),
elsewhere 0.86-0.99 (BENCHMARKS.md, "Training over a random background colour")."""


def low_coverage_notes(coverage: float | None, steps: int, fitted: bool = False) -> list[str]:
    """The note for a model trained ``steps`` steps that covers its own training views poorly (``LOW_COVERAGE``);
    none for None, or for a run shorter than ``train``'s ``SHORT_RUN_STEPS`` (not yet fitted: its coverage says
    nothing about dark surfaces) unless ``fitted`` (a model trained elsewhere: ``init_ply``, 0 steps here)."""
    from uncertsplat.train.session import SHORT_RUN_STEPS  # here: evaluate's import needs no training module

    if coverage is None or coverage >= LOW_COVERAGE or (steps < SHORT_RUN_STEPS and not fitted):
        return []
    said = (f"the model covers its own training views only to alpha {coverage:.2f} (95 % of their pixels): it leaves "
            "surfaces partly empty, often dark ones fitted by the background showing through, and the empty-ray term "
            "counts them as surface no view saw")
    if fitted:  # (a model trained elsewhere: its trainer, not `train`, would train it over random backgrounds)
        return [said + "; a model trained over a random background colour (an option of some trainers) "
                "covers them"]
    return [said + "; `train --set random_background=true` covers them (bonsai: 0.43 -> "
            "0.99, held out +0.2-0.5 dB and AUSE-MAE 0.394 -> 0.370, but worse where new views extrapolate: "
            "BENCHMARKS.md, \"Training over a random background colour\")"]


UNLOOKED_NOTE = 0.05
"""``evaluate`` names the views with at least this fraction of their surface outside every training photo: a few
pixels at an image's edge are usual in any capture."""


FINER_NOTE = 1.5
"""``evaluate`` names the views that resolve the surface at least this many times finer than any training photo
that saw it (``ViewConsistency.reach``, the median over a view's surface): a held-out photo of a capture is about as
near as its neighbours (1.0-1.1 on the demo ring), one taken at half the distance is at 2."""


EMPTY_NOTE = 0.05
"""``evaluate`` names the views that the model leaves empty (alpha below 1/2) on at least this fraction of their pixels
more than it leaves any of the training views it renders for the reference: there the model holds no surface at all,
which the surface-based reach note cannot see (the tiny scene trained on a third of its ring: the view opposite 35 %
empty)."""
EMPTY_ALPHA = 0.5
EMPTY_TRAIN_VIEWS = 4
"""Training views rendered for the reference empty fraction (evenly spaced)."""


@torch.no_grad()
def _empty_view_notes(sampler, views, train_cameras, device: torch.device) -> list[str]:
    """The note naming the evaluated views whose pixels the model leaves empty (``EMPTY_NOTE``), with the fraction,
    beside the most its training views leave empty. One render of the representative model per view; none without
    training views. (The caller skips it on training views and on transparent scenes, whose empty rays are the
    photos' background.)"""
    from uncertsplat.eval.engine import _representative, evenly_spaced

    if len(train_cameras) == 0 or not views.names:
        return []
    rep = _representative(sampler, device)

    def empty(cams) -> float:
        return float((sampler.render_fn(rep, cams.to(device)).alpha < EMPTY_ALPHA).float().mean())

    # the most any of them leaves empty: the training views' own spread (their background) is not what no photo saw
    usual = max(empty(train_cameras[[i]]) for i in evenly_spaced(range(len(train_cameras)), EMPTY_TRAIN_VIEWS))
    found = {name: e for j, name in enumerate(views.names) if (e := empty(views.cameras[[j]])) >= usual + EMPTY_NOTE}
    if not found:
        return []
    listed = ", ".join(f"{name} {100 * e:.0f} %" for name, e in sorted(found.items(), key=lambda x: -x[1]))
    return [f"{len(found)} of {len(views.names)} views show parts the model holds no surface for (alpha below "
            f"{EMPTY_ALPHA:g}; its training views at most {100 * usual:.0f} %): {listed}; no photo saw what is there, "
            "and the std there is the empty-ray term's"]


def _reach_notes(sampler, views, device: torch.device) -> list[str]:
    """Notes naming the evaluated views that go beyond the capture (``ViewConsistency.reach``, one render each):
    those whose surface lies outside every training photo for at least ``UNLOOKED_NOTE`` of its pixels (the model
    extrapolates there, and the std there is the view-consistency term's palette variance), and those that resolve
    the surface at least ``FINER_NOTE`` times finer than any training photo (nearer or zoomed in: the model holds no
    detail finer than the photos; the finer-detail term widens the std at the render's edges there, and on a sparse
    capture it is still too low; BENCHMARKS.md, "Views closer than the training views" and "Detail finer than any
    photo recorded"). Empty without such a view or without the term (``consistency_views = 0``)."""
    if sampler.consistency is None:
        return []
    reach = {name: sampler.consistency.reach(views.cameras[[j]].to(device), sampler.render_fn)
             for j, name in enumerate(views.names)}
    notes = []
    beyond = {name: r[0] for name, r in reach.items() if r[0] >= UNLOOKED_NOTE}
    if beyond:
        listed = ", ".join(f"{name} {100 * f:.0f} %" for name, f in sorted(beyond.items(), key=lambda x: -x[1]))
        notes.append(f"{len(beyond)} of {len(reach)} views show surface that no training photo had in view (the model "
                     f"extrapolates there; its std is widened for it, and those views' calibration error says whether "
                     f"by enough): {listed}")
    finer = {name: r[1] for name, r in reach.items() if r[1] >= FINER_NOTE}
    if finer:
        listed = ", ".join(f"{name} x{f:.1f}" for name, f in sorted(finer.items(), key=lambda x: -x[1]))
        std = ("its std adds what a sharper surface could hold at the render's edges, and where few photos saw a "
               "surface it is still too low" if sampler.consistency.finer_detail > 0.0 else
               "and where few photos saw a surface its std there is too low (finer_detail is off)")
        notes.append(f"{len(finer)} of {len(reach)} views see the surface finer than any training photo did (nearer or "
                     f"zoomed in): the model holds no detail finer than the photos; {std}: {listed}")
    return notes


def _print_report(run_dir: Path, cfg: EvalConfig, report, out: Path, written: bool = True,
                  depth_to_source: float | None = None, seconds: float | None = None):
    """Print ``report``'s table and notes; returns it. ``written``: this call wrote it (else it was found).
    ``depth_to_source``: the scene's units per run unit, said beside depth metrics in the run's units. ``seconds``:
    the whole evaluation's time (the table's is each view's samples' renders alone: loading, the fits and writing
    the maps took as long again on large views)."""
    from rich.table import Table

    table = Table(title=f"{run_dir.name}: {cfg.split} views (K={cfg.num_samples})")
    for col in ("view", "PSNR", "SSIM", "AUSE-MAE", "AUSE-RMSE", "NLL", "cal.err", "Spearman", "depth AUSE",
                "render s"):
        table.add_column(col, justify="right")

    def f(x, p=3):
        return "-" if x is None else f"{x:.{p}f}"

    rows = list(report.per_view.items()) + [("mean", report.mean)]
    for name, v in rows:
        table.add_row(name, f(v.psnr, 2), f(v.ssim), f(v.ause_mae), f(v.ause_rmse), f(v.nll), f(v.calibration_error),
                      f(v.spearman), f(v.depth_ause_mae), f(v.seconds, 2))
    print_table(table)
    if report.noise_scale is not None:
        # a fitted level is worth a line (1, the default without views set aside, is not)
        if cfg.residual_scale == "fit" or (cfg.residual_scale == "auto" and report.calibration_held_out):
            console.print(f"pixel noise x {report.noise_scale:.3g} (unit z-variance on the "
                          f"{report.calibration_source})")
    if report.std_scale is not None:
        m = report.mean
        def g(x):  # (a metric with no valid pixel is None: the line is printed all the same)
            return "-" if x is None else f"{x:.3f}"

        console.print(f"std x {report.std_scale:.3g} (fitted on {len(report.calibration_views)} {report.calibration_source}): "
                      f"NLL {g(m.nll_calibrated)} (raw {g(m.nll)}), calibration error "
                      f"{g(m.calibration_error_calibrated)} (raw {g(m.calibration_error)}); AUSE is unchanged")
        for note in std_factor_notes(len(report.calibration_views), m.nll_calibrated, m.nll):
            console.print(f"[yellow]note:[/] {note}")
    parts = report.variance_parts()
    if parts:
        console.print(f"the predictive's variance on the scored pixels (share of each part, before the std factor and "
                      f"the RGB std's cap at 0.5): {parts}")
    if report.degrees_of_freedom is None and cfg.degrees_of_freedom == "fit" and report.mean.nll is not None:
        why = ("the Gaussian fitted the calibration views' errors best" if report.calibration_views else
               "no std factor or tails are fitted when the training views are the ones scored (a fit on the views "
               "it scores would flatter it); --set degrees_of_freedom=4 gives heavy tails" if cfg.split != "test" else
               "no views to fit the Student-t's tails on: calibration_views = 0 or none to use; --set "
               "degrees_of_freedom=4 gives heavy tails without them")
        console.print(f"RGB predictive: the Gaussian ({why})")
    if report.mean.nll_paper is not None:
        console.print(f"the paper's NLL (--paper-nll; its KDE formula depends on the resolution: not comparable "
                      f"with the NLL above): {report.mean.nll_paper:.3f}")
    if report.degrees_of_freedom is not None:
        m = report.mean
        where = (f"fitted on the {report.calibration_source}" if cfg.degrees_of_freedom == "fit" else "set")
        gaussian = ("" if m.nll_gaussian is None else
                    f"; read as a Gaussian, the same std gives NLL {m.nll_gaussian:.3f}, calibration error "
                    f"{m.calibration_error_gaussian:.3f}")
        console.print(f"RGB predictive: a Student-t with the std and {report.degrees_of_freedom:.3g} degrees of "
                      f"freedom ({where}; its 68 % interval is +-{_half_width(0.6827, report.degrees_of_freedom):.2f} "
                      f"std, its 99.73 % (3-sigma) one +-{_half_width(0.9973, report.degrees_of_freedom):.2f}){gaussian}")
        if cfg.degrees_of_freedom == "fit" and report.degrees_of_freedom <= MIN_DOF + 1e-6:
            console.print(f"[yellow]note:[/] the tails' fit hit its limit ({MIN_DOF:g} degrees of freedom): the std "
                          "does not describe these errors' scale (a model that has not fitted its photos yet, or "
                          "errors the model cannot see); read the NLL and calibration with care")
        if cfg.degrees_of_freedom == "fit" and not report.calibration_held_out and report.degrees_of_freedom < 10:
            # heavy tails fitted on training views may be heavier than new views' (light ones say nothing of that)
            console.print("[dim]the tails were fitted on training views, which a model usually fits better than new "
                          "ones, so new views may ask for lighter tails (bonsai: 2.75 degrees of freedom where its "
                          "held-out views ask for 3.4); views set aside from training give a fit that holds for new "
                          "views: train with --set scene.calibration_holdout=3 (in a pipeline, `uncertsplat run`: "
                          "--set train.scene.calibration_holdout=3)[/]")
    if report.mean.psnr_render is not None:
        masked = [n for n in report.notes if n.startswith(MASKED_NOTE)]
        where = "" if not masked else "; inside the photos' masks, as train's" if PHOTO_MASKS_NOTE in masked[0] \
            else "; without the transient regions training found, as train's" if TRANSIENT_MASKS_NOTE in masked[0] \
            else "; train's over whole images, these inside the scene's validity masks"
        samples = "the one sample" if cfg.num_samples == 1 else f"the mean of the {cfg.num_samples} samples"
        what = ("what train reports for the held-out views" if cfg.split == "test" else
                "as train renders them; its 'training views' figure is over at most 8 of them, evenly spaced")
        console.print(f"PSNR is that of {samples}; one deterministic render (the "
                      f"expected render, {what}{where}): {report.mean.psnr_render:.2f} dB")
    if report.depth_scale is not None:
        # the depth metrics' unit, which a robotics user read as metres on a metric scene (4.4 cm for 17.8)
        units = "the maps' own units" if report.depth_scale.method not in ("scene", GIVEN_SCENE_GT) or \
            not depth_to_source else (f"the run's normalised units: x {depth_to_source:.4g} for the scene's own "
                                      "(metres, if it is metric)")
        console.print(f"depth scale {report.depth_scale.scale:.4g} ({report.depth_scale.method}); the depth metrics "
                      f"are in {units}")
    maps = f" and maps in {out / 'maps'}" if (out / "maps").is_dir() else " (no maps: save_maps = false)"
    took = (f" ({seconds:.1f} s in all; 'render s' is each view's samples' renders alone)"
            if seconds is not None else "")
    console.print(f"{'wrote' if written else 'kept'} {out / 'metrics.json'}{maps}{took}")
    return report

