"""A run folder of any method, loaded for rendering: ``load_run`` is the one place a run is read.

``load_run(run_dir, device)`` reads ``RUN/config.json`` (the ``TrainConfig``) and ``RUN/scene.json``
(``schemas.RunScene``), then the model: ``variational.ply`` when present, else the newest good
checkpoint (``load_single_model``). An ensemble run loads each member folder the same way
(``baselines.ensemble``); a Fisher run adds its posterior variances (``baselines.fisher``). Every
consumer (``evaluate``, ``prune``, ``sweep``, the examples and benchmarks) goes through it.

The ``LoadedRun`` it returns knows how to be sampled (``sampler``: what the evaluation engine draws its
K samples from), which notes an evaluation of it needs (``eval_notes``) and the scene it was trained on
(``load_scene``). It lives in ``baselines`` because loading dispatches on the method.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from uncertsplat.config import TrainConfig, build_config
from uncertsplat.console import esc, q
from uncertsplat.errors import UserError
from uncertsplat.eval.engine import SAME_RENDER, Sampler
from uncertsplat.gaussians.params import GaussianModel
from uncertsplat.gaussians.prior import Prior
from uncertsplat.io.folders import is_scene, stage_hint
from uncertsplat.render.exposure import PhotoExposure
from uncertsplat.schemas import RunExposure, RunScene
from uncertsplat.schemas.base import run_file_hint
from uncertsplat.types import GaussianSample, SceneData, ViewSet


@dataclass
class LoadedRun:
    """A trained run, ready to render.

    Attributes:
        model: the Gaussians and their offset tables.
        config: the resolved ``TrainConfig`` (``RUN/config.json``).
        scene_path: the scene folder the run was trained on (None when ``scene.json`` is missing).
        extent: scene extent used in training (position unit of the "ours" variant).
        step: training step of the model.
        sh_degree: SH degree active at the end of training.
        source: the file the model came from (the run folder for an ensemble).
        run_dir: the run folder.
    """

    model: GaussianModel
    config: TrainConfig
    scene_path: Path | None
    extent: float
    step: int
    sh_degree: int
    source: Path
    run_dir: Path
    transparent: bool = False
    """The training images had real transparency (``RUN/scene.json``): the background is data."""
    exposure: RunExposure | None = None
    """The training photos' learned exposures (``RUN/exposure.json``; ``TrainConfig.exposure``), None without."""
    near: float | None = None
    """The near plane the run was trained with (``RUN/scene.json``); None: ``render.near_plane`` of the scale."""
    transients: dict[str, Tensor] | None = None
    """The transient regions of the checkpoint the model was read from ({training photo: [H,W] bool, its pixels that
    count}, ``checkpoint_transients``), which stand for ``RUN/transients/`` (an earlier training's beside a newer
    checkpoint); None: the folder's."""
    _coverage: float | None = field(default=None, init=False, repr=False)  # ``coverage``, once computed
    _photo_exposure: PhotoExposure | None = field(default=None, init=False, repr=False)  # ``photo_exposure``, once
    _scene: SceneData | None = field(default=None, init=False, repr=False)  # ``load_scene``, once
    frame_note: str | None = field(default=None, init=False, repr=False)
    """Set by ``load_scene``: how the scene folder's source frame differs from the one scene.json records
    (``sfm.scene.frame_change``), or None."""

    def with_model(self, model: GaussianModel, coverage: float | None = None) -> LoadedRun:
        """This run with another ``model`` (e.g. a pruned subset): what depends on the model is computed again
        (``coverage``, unless given: a pruned subset is measured against its source's, as ``source_coverage``), what
        depends on the scene alone is kept (``photo_exposure``, which reads the scene)."""
        out = dataclasses.replace(self, model=model)
        out._photo_exposure = self._photo_exposure
        out._scene, out.frame_note = self._scene, self.frame_note
        if coverage is not None:
            out._coverage = coverage
        return out

    def with_scene(self, scene: SceneData) -> LoadedRun:
        """This run with ``scene`` standing in for its scene folder (``load_scene`` returns it): the scene as an
        earlier evaluation loaded it (``stages.predictive_cache``), where the folder itself is not."""
        out = dataclasses.replace(self)
        out._scene, out.frame_note = scene, self.frame_note
        return out

    @property
    def prior(self) -> Prior:
        """The ``gaussians.prior.Prior`` (variant, temperature, ...) to sample this model with."""
        from uncertsplat.train.trainer import prior_from_config

        return prior_from_config(self.config)

    @property
    def sample_kwargs(self) -> dict:
        """The keywords that render this model's posterior (``variational.sample``, ``posterior_mean``,
        ``expected_render_sample``): its prior's variant and temperature, extent and active SH degree."""
        prior = self.prior
        return {"variant": prior.variant, "extent": self.extent, "temperature": prior.temperature,
                "sh_degree": self.sh_degree}

    def empty_std(self) -> tuple[float, float] | None:
        """(colour, depth) std of the unknown surface behind a ray that meets no Gaussian: a colour uniform in
        [0, 1] (std 1 / sqrt(12)) and a depth anywhere within the scene extent; None when the training images
        were transparent (a ray that meets nothing then shows the known background)."""
        return None if self.transparent else (1.0 / math.sqrt(12.0), float(self.extent))

    def coverage(self, scene_scale: float, device: torch.device, sample: GaussianSample | None = None) -> float:
        """The opacity the model reaches on the surfaces its training views saw (``uncertainty.mc.
        training_coverage`` over the scene's training cameras; ``Sampler.coverage``), computed once per loaded
        run. ``sample``: the Gaussians to render (default: the model's expected render). 1 when the empty-ray
        term does not apply (transparent training images) or the run records no scene. A pruned run (``prune.json``
        beside its model) takes its source model's (``PruneReport.source_coverage``): pruning changed the model,
        not what the photos showed, and a model pruned to a few Gaussians would otherwise call nothing empty.
        """
        cached = getattr(self, "_coverage", None)
        if cached is not None:
            return cached
        value = 1.0
        source = self.source_coverage()
        if self.empty_std() is not None and source is not None:
            value = source
        elif self.empty_std() is not None and self.scene_path is not None:
            from uncertsplat.gaussians import variational
            from uncertsplat.uncertainty.mc import training_coverage

            scene = self.load_scene()
            train = list(scene.split.get("train", ()))
            if sample is None:
                with torch.no_grad():
                    sample = variational.expected_render_sample(self.model, **self.sample_kwargs)

            def masks_of(pick):  # a masked-out sky or passer-by is no surface to cover
                return self.training_masks(scene, [train[j] for j in pick])
            value = training_coverage(sample, scene.cameras[train].to(device), self.render_fn(scene_scale, device),
                                      masks_of=masks_of)
        self._coverage = value
        return value

    def source_coverage(self) -> float | None:
        """The unpruned source model's coverage a pruned run records (``PruneReport.source_coverage``; None: not a
        pruned run, one pruned before it was recorded, or its prune.json unreadable)."""
        from uncertsplat.schemas.prune import PruneReport

        path = self.run_dir / PruneReport.FILE_NAME
        if not path.is_file():
            return None
        try:
            return PruneReport.read(path).source_coverage
        except Exception:  # a damaged or foreign prune.json: the run's own coverage, as before it was recorded
            return None

    def render_fn(self, scene_scale: float, device: torch.device) -> Callable:
        """``render_fn(sample, cameras)`` with the run's background, tile size and near plane (as in training)."""
        from uncertsplat.render import near_plane, render

        bg = torch.tensor(self.config.scene.background, dtype=torch.float32, device=device)
        return functools.partial(render, background=bg, tile_size=self.config.tile_size,
                                 near=self.near if self.near is not None else near_plane(scene_scale))

    def training_masks(self, scene: SceneData, indices: Sequence[int], device=None) -> Tensor | None:
        """[C,H,W,1] bool: the pixels of the training views ``indices`` of ``scene`` that this run's training fitted,
        for what is computed from that fit (the training coverage, the Fisher curvature, ``select-views``' Fisher
        score): inside the photos' own masks when it trained with them (``sfm.scene.trained_with_masks``; masks
        added to the scene since are not, as its loss did not leave those pixels out), without the transient regions
        it found (``transient_runs``). None: every pixel was fitted."""
        from uncertsplat.data.dataset import load_masks, without_transients
        from uncertsplat.sfm.scene import trained_with_masks

        indices = [int(i) for i in indices]
        users = scene.masks_train and trained_with_masks(self.run_dir)
        masks = without_transients(load_masks(scene, indices) if users else None, scene, indices,
                                   self.transient_runs())
        return None if masks is None else masks.to(device)

    def position_prior_std(self, scene: SceneData) -> Tensor | None:
        """[P] the position prior std of each carrier (table units) that the run's informed posterior was fitted
        against (``variational.informed_position_prior`` at the training cameras of ``scene``: the reference of
        training's posterior summary); None where the config's single ``prior.position_std`` is the prior (the
        learned posterior, or a run without carriers)."""
        cfg = self.config
        if cfg.method != "variational" or cfg.posterior != "informed" or not self.model.num_carriers:
            return None
        from uncertsplat.gaussians.variational import informed_position_prior

        vcfg = cfg.variational
        centres = scene.cameras[list(scene.split["train"])].centers.to(self.model.device)
        return informed_position_prior(self.model, self.prior, extent=self.extent,
                                       position_prior_scale=vcfg.position_prior_scale, camera_centers=centres,
                                       position_depth_fraction=vcfg.position_depth_fraction)

    def training_views(self, scene: SceneData) -> Callable:
        """``load(indices) -> ViewSet``: the training views of ``scene`` as the fits on them read them (8-bit photos
        kept as uint8, no depth), inside the photos' masks and without the transient regions this run's training
        found in them (``data.dataset.TRANSIENTS_FOLDER``)."""
        from uncertsplat.data.dataset import load_view_set

        return functools.partial(load_view_set, scene, depth=False, keep_8bit=True, transients=self.transient_runs())

    def scored_views(self, scene: SceneData, indices, split: str, **load) -> ViewSet:
        """The views ``indices`` of ``scene`` as evaluate, sweep and prune score them (``data.dataset.load_view_set``,
        with ``load`` passed on): training views (``split`` "train") without the transient regions this run's
        training found in them, as its loss left them out; ``masks_trained`` saying whether the masks are those
        training used: the photos' own when it trained with them (masks added to the scene since are scored inside
        but not so called), or, for photos without masks of their own, the transient regions."""
        from uncertsplat.data.dataset import load_view_set, without_transients
        from uncertsplat.sfm.scene import trained_with_masks

        views = load_view_set(scene, indices, **load)
        transients = False
        if split == "train":
            masks = without_transients(views.masks, scene, views.indices, self.transient_runs())
            transients = views.masks is None and masks is not None  # (a scene's or photos' masks: not training's)
            views = dataclasses.replace(views, masks=masks, transients_out=masks is not views.masks,
                                        own_masks_too=masks is not views.masks and views.masks is not None)
        return dataclasses.replace(views, masks_trained=(views.masks_trained and trained_with_masks(self.run_dir))
                                   or transients)

    def transient_runs(self) -> list[Path | dict[str, Tensor]]:
        """The run folders whose ``transients/`` (``data.dataset.TRANSIENTS_FOLDER``) hold what training left out of
        this model's photos: the run's own (an ensemble: its members'), or the regions of the checkpoint the model
        was read from (``transients``: the folder is written with the PLY, an earlier training's beside a newer
        checkpoint)."""
        return [self.transients if self.transients is not None else self.run_dir]

    def sampler(self, scene_scale: float, device: torch.device) -> Sampler:
        """What the evaluation engine draws samples from: the model's posterior (its mean for a deterministic
        model or one without posterior carriers), and the expected render that ``train`` reports.

        Build one per evaluation: a baseline's sampler may keep state between calls.
        """
        from uncertsplat.gaussians import variational

        render_fn = self.render_fn(scene_scale, device)
        with torch.no_grad():
            det_sample = variational.expected_render_sample(self.model, **self.sample_kwargs)
        return Sampler(self.sample_fn(), render_fn, det_sample, empty_std=self.empty_std(),
                       coverage=self.coverage(scene_scale, device, det_sample), exposure=self.photo_exposure())

    def sample_fn(self):
        """``sample_fn(generator) -> GaussianSample``: one posterior sample per call (the posterior mean for a
        deterministic model or one without posterior carriers)."""
        from uncertsplat.gaussians import variational

        model, kw = self.model, self.sample_kwargs
        if self.config.method == "deterministic" or model.num_carriers == 0:
            mean_sample = variational.posterior_mean(model, **kw)
            return lambda g: mean_sample
        subset_size = self.config.variational.subset_size
        return lambda g: variational.sample(model, g, subset_size=subset_size, **kw)

    def photo_exposure(self) -> PhotoExposure | None:
        """``exposure`` with the photos as view indices of the run's scene (``Sampler.exposure``), computed once;
        None without exposures.

        Raises:
            UserError: ``exposure.json`` names a photo the scene does not have.
        """
        if self.exposure is None:
            return None
        if self._photo_exposure is not None:
            return self._photo_exposure
        names = self.load_scene().cameras.image_names
        index = {n: i for i, n in enumerate(names)}
        missing = [n for n in self.exposure.images if n not in index]
        if missing:
            raise UserError(f"{RunExposure.FILE_NAME} names {len(missing)} photo(s) the scene does not have "
                            f"(e.g. {missing[0]})", path=self.run_dir / RunExposure.FILE_NAME,
                            hint="Train the run again on this scene, or restore the scene it was trained on.")
        self._photo_exposure = PhotoExposure(tuple(index[n] for n in self.exposure.images),
                                             torch.tensor(self.exposure.gain, dtype=torch.float32),
                                             torch.tensor(self.exposure.offset, dtype=torch.float32))
        return self._photo_exposure

    def eval_notes(self, num_samples: int, scored: bool = False) -> list[str]:
        """Notes an evaluation with ``num_samples`` samples adds to its report for this kind of run (``scored``: of
        the training views, which it scores without their transient regions)."""
        from uncertsplat.data.dataset import TRANSIENTS_FOLDER, transient_mask_files

        runs = self.transient_runs()
        found = {name for r in runs for name in (r if isinstance(r, dict) else transient_mask_files(r))}
        where = (f"the checkpoint {self.source.name}" if isinstance(runs[0], dict) else runs[0] / TRANSIENTS_FOLDER
                 ) if len(runs) == 1 else f"the members' {TRANSIENTS_FOLDER}/ folders"
        notes = [f"the transient objects training found in {len(found)} training photo(s) ({where}) are left out "
                 "of the fits on the training views (the pixel noise, the std factor)"
                 + (" and of these training views' scores" if scored else "") + ", as training left them out"
                 ] if found else []
        return notes + self._method_notes(num_samples)

    def _method_notes(self, num_samples: int) -> list[str]:
        """``eval_notes``' part on the kind of model (a baseline's own)."""
        if self.config.method == "deterministic":
            return [f"deterministic model: {SAME_RENDER}, so the samples' spread is 0 everywhere; "
                    "the std holds the predictive's other terms (the 'std² =' note lists them)"]
        if self.config.method == "variational" and self.model.num_carriers == 0 and len(self.model):
            from uncertsplat.schemas.prune import PruneReport
            from uncertsplat.train.trainer import no_carriers_reason

            pruned = (self.run_dir / PruneReport.FILE_NAME).is_file()
            why = ("pruning removed every Gaussian that carried one (prune removes only those; a smaller share "
                   "removed keeps some)" if pruned else no_carriers_reason(self.config, self.step) or (
                "its Gaussians are all narrower than the spawn rule asks (densify.spawn_scale_fraction; train "
                "warned with the fraction that gives them one)"))
            return [f"no Gaussian carries a posterior: {SAME_RENDER}, so the std holds only the predictive's other "
                    f"terms (the 'std² =' note lists them); {why}"]
        return []

    def size_text(self) -> str:
        """The model's size as the commands print it: "N Gaussians (M with a posterior)"."""
        return f"{len(self.model)} Gaussians ({self.model.num_carriers} with a posterior)"

    def unfinished_notes(self) -> list[str]:
        """A note when the model is a training checkpoint before the run's last step (training was stopped and not
        resumed): what is measured is that checkpoint. None for finished runs (their model is ``variational.ply``)."""
        if self.source.suffix != ".pt" or self.step >= self.config.iterations:
            return []
        from uncertsplat.io.checkpoints import unfinished_training

        return [unfinished_training(self.step, self.config.iterations, self.scene_path, self.run_dir)
                + "; what is measured is that checkpoint"]

    def warn_if_unfinished(self) -> list[str]:
        """``unfinished_notes``, each also printed as a warning; returns them."""
        notes = self.unfinished_notes()
        if notes:
            from rich.text import Text

            from uncertsplat.console import console

            for note in notes:
                console.print(Text.assemble(("warning:", "yellow"), " ", note), soft_wrap=True)
        return notes

    def exposure_notes(self) -> list[str]:
        """What an evaluation notes about the run's learned exposures (``exposure``): none without them."""
        if self.exposure is None:
            return []
        return [f"{self.exposure.describe()} ({RunExposure.FILE_NAME}): the pixel noise is fitted on the training "
                "photos at the model's exposure, and the spread of the photos' exposures is part of the RGB std (a new "
                "photo's exposure is not known)"]

    def load_scene(self) -> SceneData:
        """The scene the run was trained on, with the run's scene config (same split and downscale); read once per
        loaded run (and its ``with_model`` copies): a COLMAP model of a million points takes seconds to read, and
        ``evaluate`` and ``prune`` ask for it several times.

        Raises:
            UserError: the run records no scene, or the scene folder is gone.
        """
        if self._scene is None:
            self._scene = self._read_scene()
        return self._scene

    def _read_scene(self) -> SceneData:
        from uncertsplat.sfm.scene import (
            frame_change,
            load_for_run,
            require_same_cameras,
            with_training_views,
        )

        if self.scene_path is None:
            raise UserError("the run does not record its scene (scene.json is missing)", path=self.run_dir,
                            hint="Evaluate a run written by `uncertsplat train`.")
        if not Path(self.scene_path).exists():
            if (self.run_dir / "prune.json").is_file():  # (no checkpoint: `train --resume` refuses a pruned model)
                from uncertsplat.schemas.base import resolve_from

                try:
                    info = RunScene.read_optional(self.run_dir / RunScene.FILE_NAME)
                except UserError:
                    info = None
                beside = (resolve_from(self.run_dir, info.scene_from_run)
                          if info is not None and info.scene_from_run else None)
                hint = ("Restore the scene folder at that path" + (
                    f" or at {beside}, its place relative to the run (where a run moved with its scene finds it)"
                    if beside is not None and beside != Path(self.scene_path) else "")
                    + ", then run this command again (a pruned model has no checkpoint, so `uncertsplat train "
                      "--resume` cannot point it at another folder).")
            else:
                hint = ("Restore the scene folder at that path; or, if you moved it, point the run at its new place "
                        f"with `uncertsplat train NEW_SCENE_FOLDER -o {q(self.run_dir)} --resume` (it checks that the "
                        "folder holds the run's images and trains no further when the run is finished). Then run this "
                        "command again.")
            raise UserError(f"the scene this run was trained on is gone: {self.scene_path}", path=self.run_dir,
                            hint=hint)
        # rendering a trained run needs no initial points (for a scene without sparse points, making them reads
        # every training view's alpha mask)
        info = RunScene.read_optional(self.run_dir / RunScene.FILE_NAME)
        # photos that joined the scene since (reconstruct --extend) move the normalisation and the split: the run's own
        data, own = load_for_run(Path(self.scene_path), self.config.scene, info, initial_points=False)
        if info is None:
            return data
        from uncertsplat.console import console, list_names

        if Path(self.scene_path) != Path(info.scene):  # (the cameras and the views' names are compared below)
            pruned = (self.run_dir / "prune.json").is_file()  # (`train --resume` refuses a pruned model)
            console.print(f"[yellow]note:[/] the scene this run was trained on, {info.scene}, is gone; reading the "
                          f"folder at the same place relative to the run, {self.scene_path} (the run was moved with "
                          "it)" + ("" if pruned else f"; `uncertsplat train {q(self.scene_path)} -o {q(self.run_dir)} "
                                                     "--resume` records it"))

        if own is not None:
            known = {*info.train, *info.test, *info.calibration}
            new = [n for n in data.cameras.image_names if n not in known]
            if new:  # what the user can do about it: train on them
                console.print(f"[yellow]note:[/] {own}; {len(new)} view(s) it has not trained on "
                              f"({list_names(new)}): `uncertsplat train {q(self.scene_path)} -o {q(self.run_dir)} --resume "
                              "--add-views NAMES` trains on them")
            else:  # the run already trains on the grown scene: a reminder, not news
                console.print(f"[dim]note: {esc(own)}[/]")
        # its renders would not line up with the photos: every score would measure the misalignment
        require_same_cameras(info.cameras, data, Path(self.scene_path),
                             "its renders and scores against these would be wrong")
        change = frame_change(info.world_from_source, data.world_from_source)
        if change is not None:
            self.frame_note = (f"the scene folder's frame is not the one the run was trained in ({change}; its cameras "
                               "agree): depths and poses in the scene's units follow the folder as it is now, not "
                               "scene.json's world_from_source")
            console.print(f"[yellow]note:[/] {self.frame_note}")
        # measured against the views it trained on (a later version's split rules may differ: pose twins)
        return with_training_views(data, info.train)


def _refuse_prune_without_model(folder: Path) -> None:
    """A prune output that wrote no model (``prune --dry-run``, or ``--sweep`` alone) is named as one, with the run it
    pruned: "not a training run (config.json is missing)" did not say what to do."""
    from uncertsplat.schemas.prune import PruneReport

    path = folder / PruneReport.FILE_NAME
    if not path.is_file():
        return
    try:
        report = PruneReport.read(path)
    except UserError:
        return  # (damaged: the plain message)
    what = "a dry-run prune (prune --dry-run)" if report.dry_run else "a prune that measured its sweep only"
    raise UserError(f"{what}: it wrote no model, so there is nothing to load here", path=folder,
                    hint=f"Use the run it pruned ({q(report.source_folder(folder))}), or prune that run again with "
                         "--keep-ratio, --threshold or --auto and -o NEW_RUN to write a pruned model; `uncertsplat "
                         f"report {q(folder)}` shows what this prune measured.")


def read_run_config(run_dir: Path) -> TrainConfig:
    """``RUN/config.json`` as a ``TrainConfig``.

    Raises:
        UserError: the file is missing (not a training run), not JSON, or not a valid config.
    """
    cfg_path = Path(run_dir) / "config.json"
    if not cfg_path.is_file():
        _refuse_prune_without_model(Path(run_dir))
        # (a scene, as `report` says it; a pipeline's output folder or its report/, RUN/eval, ...: what to give)
        near = "; ".join(n for n in ("this is a scene, the input of `uncertsplat train`" if is_scene(Path(run_dir))
                                     else "", stage_hint(Path(run_dir), "run")) if n)
        raise UserError("not a training run (config.json is missing)" + (f"; {near}" if near else ""), path=run_dir,
                        hint="Point to a folder written by `uncertsplat train` (or `prune`).")
    try:
        data = json.loads(cfg_path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as err:
        raise UserError(f"config.json is not valid JSON ({err})", path=cfg_path,
                        hint=run_file_hint("config.json")) from None
    if isinstance(data, dict) and 2 * len(data.keys() - TrainConfig.model_fields.keys()) > len(data):
        # another stage's output (RUN/eval, a prune or select folder's config): name the run it belongs to
        parent = Path(run_dir).resolve().parent
        owner = parent if (parent / "config.json").is_file() else None
        raise UserError("not a training run (its config.json is another command's)", path=run_dir,
                        hint=f"Give the run folder{f': {owner}' if owner else ' (written by `uncertsplat train`)'}.")
    return build_config(TrainConfig, data, source=str(cfg_path))


def load_single_model(run_dir: str | Path, device: torch.device | str = "cpu") -> LoadedRun:
    """The one trained model of a run folder, whatever its method: ``variational.ply`` when present, else the
    newest good checkpoint. ``load_run`` uses it for every single-model method (and for each ensemble
    member); a Fisher run's model is read here before its posterior exists.

    Raises:
        UserError: no config or no model in the folder, naming the file and the fix.
    """
    run_dir = Path(run_dir)
    return _load_single(run_dir, read_run_config(run_dir), device)


def refuse_non_finite(model: GaussianModel, path: Path) -> None:
    """Raise a ``UserError`` naming ``path`` when ``model`` holds a NaN anywhere or an infinite position: its renders
    and every uncertainty term built from them would be NaN (a helper's model with 5 NaN positions of 9,428 scored
    finite metrics from maps whose std was NaN in 98 % of the pixels, and `prune` failed with a traceback)."""
    bad = []
    for name, t in model.parameters().items():
        x = t.detach()
        if x.numel() == 0:
            continue
        # a position, or a table's position terms, at infinity samples an infinite position; elsewhere inf is a
        # limit a render takes (an opacity logit of +inf is opacity 1)
        wrong = ~torch.isfinite(x) if name == "means" or name.startswith("pos_") else torch.isnan(x)
        rows = int(wrong.reshape(x.shape[0], -1).any(1).sum())
        if rows:
            what = "Gaussian" if name in model.params else "posterior carrier"
            bad.append(f"{name} of {rows:,} {what}{'s' if rows > 1 else ''}")
    if bad:
        raise UserError(f"the model holds values that are not numbers ({', '.join(bad)}; NaN, or an infinite "
                        "position): its renders and uncertainty would be NaN", path=path,
                        hint="Train it again (training never writes such values: it skips the steps that would), "
                             "or restore the file from a copy; a model file changed outside uncertsplat must keep "
                             "every value a finite number.")


def _load_single(run_dir: Path, cfg: TrainConfig, device: torch.device | str) -> LoadedRun:
    from uncertsplat.io.checkpoints import CorruptCheckpoint, list_checkpoints, load_latest
    from uncertsplat.io.ply import read_variational_ply

    info = RunScene.read_optional(run_dir / RunScene.FILE_NAME)
    scene_path = info.scene_folder(run_dir) if info is not None and info.scene else None
    transparent = bool(info.source.get("transparent", False)) if info is not None else False
    near = info.near if info is not None else None
    exposure = RunExposure.read_optional(run_dir / RunExposure.FILE_NAME)
    device = torch.device(device)
    ply = run_dir / "variational.ply"
    from_ply = None
    if ply.is_file():
        model, meta = read_variational_ply(ply, device=device)
        newest = max((step for step, _ in list_checkpoints(run_dir)), default=-1)

        def from_ply(model: GaussianModel = model) -> LoadedRun:  # (bound now: ``model`` is the checkpoint's below)
            refuse_non_finite(model, ply)  # (a newer checkpoint stands in for the file: that one is checked)
            extent = float(meta.get("extent", info.extent if info is not None else 1.0))
            return LoadedRun(model, cfg, scene_path, extent, int(meta.get("step", 0)),
                             int(meta.get("sh_degree_active", model.sh_degree)), ply, run_dir, transparent, exposure,
                             near)

        # a --resume stopped (Ctrl-C, a crash) before it wrote its model leaves the PLY of the steps before it, and
        # checkpoints past them: the newer model is the checkpoint's (``unfinished_notes`` says so), not the PLY
        # every command otherwise scored without a word (views added since counted as trained, as scene.json says)
        if "step" not in meta or newest <= int(meta["step"]):
            return from_ply()
    found = load_latest(run_dir, map_location=device)
    if from_ply is not None and (found is None or int(found[1]["step"]) < int(meta["step"])):
        # every checkpoint past the PLY is damaged (each named in a warning): the PLY is the newest good model (a run
        # keeping one checkpoint was refused as holding 'neither variational.ply nor a checkpoint')
        return from_ply()
    if found is None:
        raise UserError("no trained model here (neither variational.ply nor a checkpoint in ckpts/)", path=run_dir,
                        hint="Run `uncertsplat train` (or `--resume`) to finish training first.")
    path, state = found
    try:
        try:
            model = GaussianModel.from_state_dict(state["model"], device)
        except (KeyError, ValueError) as err:  # a good checksum over an inconsistent model: written by other code
            raise CorruptCheckpoint(f"the model in the checkpoint is inconsistent ({err})", path=path) from None
        refuse_non_finite(model, path)
    except UserError as err:
        if from_ply is None:
            raise
        # a checkpoint past the PLY that loads but holds no usable model: the PLY is the newest good one, as where
        # every such checkpoint is damaged (above)
        from uncertsplat.console import console

        console.print(f"[yellow]warning:[/] {err.message} ({path}); using {ply}, the model of step {meta['step']}")
        return from_ply()
    if state.get("exposure") is not None and info is not None:
        # the checkpoint's own: an exposure.json beside it is an earlier training's (it is written with the PLY, which
        # is older than this checkpoint or absent; a --resume --iterations stopped midway paired its model with them)
        exposure = checkpoint_exposure(state, info.train) or exposure
    # the checkpoint's transient regions too: RUN/transients/ is written with the PLY (an earlier training's here)
    transients = checkpoint_transients(state, info.width, info.height) if info is not None else None
    return LoadedRun(model, cfg, scene_path, float(state["extent"]), int(state["step"]),
                     int(state.get("sh_degree_active", model.sh_degree)), path, run_dir, transparent, exposure, near,
                     transients)


def checkpoint_transients(state: dict, width: int, height: int) -> dict[str, Tensor] | None:
    """The transient regions a training checkpoint ``state`` holds (``Trainer.transient_keep``: each training photo's
    last regions, what ``train`` writes into ``RUN/transients/`` with the PLY), as {photo name: [H,W] bool, its
    pixels that count} of the photos with any (``width`` x ``height``: the training photos'); None where the
    checkpoint does not say by name (one from before it kept its photos' names or regions) or its masks are of
    another size."""
    from uncertsplat.train.transients import unpack_mask

    names, views = state.get("train_names"), state.get("transient_views")
    if not names or views is None or "transient_keep" not in state or (
            len(views) and len(views) != len(state["transient_keep"])):
        return None
    out = {}
    for v, packed in zip(views.tolist(), state["transient_keep"], strict=False):
        if not 0 <= v < len(names) or packed.numel() != (width * height + 7) // 8:
            return None
        out[str(names[v])] = unpack_mask(packed, height, width)[..., 0]
    return out


def checkpoint_exposure(state: dict, train_names: list[str]) -> RunExposure | None:
    """The exposures a training checkpoint ``state`` holds, as ``exposure.json`` would, for its training photos (the
    names it keeps; ``train_names``, the run's training photos in the order of its split, ``RunScene.train``, for a
    checkpoint from before it kept them: scene.json names views added after the checkpoint too); None when its rows
    do not match them."""
    from uncertsplat.render.exposure import exposure_record

    params = state["exposure"]
    names = list(state.get("train_names") or train_names)
    if params.shape[0] != len(names):
        return None
    return exposure_record(params, names, int(state.get("step", 0)))


def mean_exposure(records: list[RunExposure | None]) -> RunExposure | None:
    """The exposures of several models of one capture (an ensemble's members), averaged per photo (the log gains
    and the offsets); None when any has none or they name different photos."""
    if not records or any(r is None for r in records) or any(r.images != records[0].images for r in records):
        return None
    log_gain = torch.tensor([r.gain for r in records], dtype=torch.float64).log().mean(0)
    offset = torch.tensor([r.offset for r in records], dtype=torch.float64).mean(0)
    return RunExposure(images=records[0].images, gain=log_gain.exp().tolist(), offset=offset.tolist(),
                       step=min(r.step for r in records))


def load_run(run_dir: str | Path, device: torch.device | str = "cpu") -> LoadedRun:
    """Load any run folder for rendering: an ``EnsembleRun``, a ``FisherRun`` or a plain ``LoadedRun``.

    Raises:
        UserError: the folder is not a finished run of its method (the message names the file and the fix), or
            ``device`` names a CUDA device this machine does not have.
    """
    from uncertsplat.device import resolve_device

    device = resolve_device(device)  # "auto" too; "cuda" without CUDA: the CLI's error, not torch's assertion
    run_dir = Path(run_dir)
    cfg = read_run_config(run_dir)
    if cfg.method == "ensemble":
        from uncertsplat.baselines.ensemble import load_ensemble

        return load_ensemble(run_dir, cfg, device)
    base = _load_single(run_dir, cfg, device)
    if cfg.method == "fisher":
        from uncertsplat.baselines.fisher import load_fisher

        return load_fisher(base)
    return base


__all__ = ["LoadedRun", "checkpoint_exposure", "load_run", "load_single_model", "mean_exposure", "read_run_config",
           "refuse_non_finite"]
