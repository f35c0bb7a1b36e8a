"""A trained run's predictive at any camera, from Python: what ``evaluate`` writes, for poses of your own.

``evaluate`` scores held-out photos; a robot asks about poses no photo was taken from (a planned view, a pose between
two photos, one nearer the surface). ``Predictor`` builds the same predictive ``evaluate`` uses (the samples' spread
and every term it adds: the pixel noise, the edge, colour-posterior, view-consistency, finer-detail, resolution,
depth-spread and empty-ray terms, with the std factor and the Student-t tails fitted on the training or set-aside
views) and renders it for any camera, given in the scene's own coordinates and units (your COLMAP model's or map
frame) or in the run's normalised world::

    from uncertsplat.predict import Predictor

    pred = Predictor.load("RUN")  # fits what evaluate fits (or reads RUN/eval/residual.pt); ~1-30 s by the scene
    cams = pred.cameras_from_source(cam_from_source, K, width, height)  # [N,4,4] OpenCV world-to-camera, [N,3,3]
    out = pred.predict(cams, num_samples=10, seed=0)
    out.depth_mean, out.depth_std  # [N,H,W,1], in the scene's own units
    out.rgb_mean, out.rgb_std      # [N,H,W,3]; out.std_factor: the factor evaluate fitted (its "calibrated" rows)

The std maps are the raw ones, as in ``evaluate``'s EXR maps (the scene's views get them to the last bit for
evaluate's ``--seed``);
multiply the RGB std by ``std_factor`` for the calibrated one, and read it as a Student-t with ``dof`` degrees of
freedom (``examples/intervals.py``).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from pathlib import Path

import torch
from torch import Tensor

from uncertsplat.errors import UserError
from uncertsplat.types import Cameras


@dataclass(frozen=True)
class Prediction:
    """The predictive of N cameras (``Predictor.predict``).

    Attributes:
        rgb_mean: [N,H,W,3] the mean of the posterior samples' renders (not clamped).
        rgb_std: [N,H,W,3] the raw RGB std (``evaluate``'s EXR ``rgb_std``).
        depth_mean: [N,H,W,1] expected depth along the optical axis, in the scene's own units; 0 where the ray meets
            no Gaussian (no surface known there, not one at distance 0: mask by ``alpha``).
        depth_std: [N,H,W,1] its std, in the scene's own units.
        alpha: [N,H,W,1] the samples' mean accumulated opacity (low: the ray meets little of the model).
        std_factor: the factor ``evaluate`` fits for the RGB std (None: none fitted, e.g. no training view).
        dof: degrees of freedom of the Student-t the RGB std is read with (None: a Gaussian).
        depth_to_source: the factor from the run's normalised depth to the scene's units (already applied above).
        image_names: the cameras' names.
    """

    rgb_mean: Tensor
    rgb_std: Tensor
    depth_mean: Tensor
    depth_std: Tensor
    alpha: Tensor
    std_factor: float | None
    dof: float | None
    depth_to_source: float
    image_names: tuple[str, ...]


def _evaluation_config(run_dir: Path):
    """The ``EvalConfig`` of the run's evaluation (``RUN/eval/config.json``: after ``evaluate --num-samples 4`` the
    defaults fitted another std factor than the evaluation's), ``evaluate``'s defaults when there is none or it
    cannot be read (a newer or damaged file)."""
    from pydantic import ValidationError

    from uncertsplat.config import EvalConfig

    path = run_dir / "eval" / "config.json"
    try:
        return EvalConfig.model_validate_json(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValidationError):
        return EvalConfig()


class Predictor:
    """``evaluate``'s predictive of one trained run, for any camera (see the module's docstring).

    Attributes:
        run_dir: the run folder.
        scene: the run's scene as trained (``SceneData``: cameras in the normalised world, split, normalisation).
        device: where it renders.
        std_factor, dof: the fitted std factor and Student-t degrees of freedom (None when not fitted).
        config: the ``EvalConfig`` it was built with (``load``'s ``cfg``, or the run's evaluation's).
    """

    def __init__(self, run_dir: Path, loaded, scene, sampler, fit, cfg, device: torch.device):
        self.run_dir, self.loaded, self.scene, self.device = Path(run_dir), loaded, scene, device
        self._sampler, self._cfg = sampler, cfg
        self.config = cfg
        self.std_factor: float | None = fit.scale
        self.dof: float | None = fit.dof
        T = scene.world_from_source.double()
        self._world_from_source = T  # [4,4] x_world = s x_source + t
        # s of x_world = s x_source + t: what evaluate's EXR header gives as 1 / depth_to_source
        self.scale = (1.0 / scene.depth_scale_to_gt if scene.depth_scale_to_gt
                      else float(torch.linalg.det(T[:3, :3]).abs() ** (1.0 / 3.0)))

    @classmethod
    def load(cls, run_dir: str | Path, device: str | torch.device = "auto", *, cfg=None) -> Predictor:
        """The predictive of the run ``run_dir`` (any method: variational, deterministic, ensemble, fisher).

        Args:
            run_dir: a folder written by ``uncertsplat train``; its scene folder must be where ``scene.json`` says
                (the side terms are fitted on its training photos).
            device: ``auto``, ``cpu``, ``cuda[:n]`` or a torch.device.
            cfg: an ``EvalConfig`` (None: the settings of the run's evaluation, ``RUN/eval/config.json``, so that the
                predictive is the one ``evaluate`` scored; ``evaluate``'s defaults when the run has none;
                ``cfg.num_samples`` is ``predict``'s default K).

        Raises:
            UserError: not a run, its scene is gone or its cameras changed since training, no CUDA device.
        """
        from uncertsplat import native
        from uncertsplat.device import resolve_device

        device = resolve_device(device)
        evaluation = _evaluation_config(Path(run_dir))
        cfg = cfg if cfg is not None else evaluation
        with native.single_threaded_torch(device):  # as evaluate runs (its sums, so its maps, to the last bit)
            return cls._load(Path(run_dir), device, cfg, evaluation)

    @classmethod
    def _load(cls, run_dir: Path, device: torch.device, cfg, evaluation) -> Predictor:
        from uncertsplat.baselines import load_run
        from uncertsplat.data.dataset import load_view_set
        from uncertsplat.eval.engine import scored_sampler
        from uncertsplat.io.atomic import run_lock
        from uncertsplat.stages.residual_cache import fitted_residual, same_residual_settings

        loaded = load_run(run_dir, device)
        scene = loaded.load_scene()
        train_views = partial(load_view_set, scene, depth=False)
        set_aside: dict = {}
        # the pixel noise as evaluate fits it (read from RUN/eval/residual.pt when evaluate kept one for this model and
        # these settings; a fitted one is kept there too, as evaluate does, under the run's lock, when the settings
        # are the run's evaluation's: the file is the evaluation's, which evaluate and prune read, so a noise fitted
        # for other settings is kept in memory only; a read-only run, or one another process holds, is only read)
        calibration = scene.split.get("calibration", ())
        fit = partial(fitted_residual, loaded, scene.scene_scale, scene.split.get("train", ()), cfg, device,
                      load_views=train_views, calibration_indices=calibration, set_aside_maps=set_aside)
        fitted = False
        if same_residual_settings(cfg, evaluation, set_aside=len(calibration) > 0):
            try:
                with run_lock(run_dir, "predict"):
                    residual, fitted = fit(write=True), True
            except UserError:
                pass
        if not fitted:
            residual = fit(write=False)
        sampler, fit = scored_sampler(partial(loaded.sampler, scene.scene_scale, device), residual, scene.cameras,
                                      scene.split, cfg, device, load_views=train_views, set_aside_maps=set_aside)
        return cls(run_dir, loaded, scene, sampler, fit, cfg, device)

    def cameras_from_source(self, cam_from_source: Tensor, K: Tensor, width: int, height: int,
                            names: tuple[str, ...] = ()) -> Cameras:
        """Cameras given in the scene's own frame (the COLMAP model's, your map's), in the run's normalised world.

        Args:
            cam_from_source: [N,4,4] or [4,4] rigid world-to-camera transforms (OpenCV axes: x right, y down, z
                forward), translations in the scene's units (pycolmap's ``Image.cam_from_world().matrix()``).
            K: [N,3,3] or [3,3] pinhole intrinsics in pixels of a ``width`` x ``height`` image (any size: the render
                takes it; the run's own is ``scene.cameras.width`` x ``height``).
            names: N names (default ``pose_0``, ``pose_1``, ...).
        """
        from uncertsplat.sfm.scene import normalized_cam_from_world

        cfs = torch.as_tensor(cam_from_source, dtype=torch.float64)
        cfs = cfs[None] if cfs.ndim == 2 else cfs
        rigid = cfs.ndim == 3 and cfs.shape[-2:] == (4, 4)
        if rigid:
            R = cfs[:, :3, :3]
            rigid = (torch.allclose(R @ R.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand_as(R), atol=1e-5)
                     and bool((torch.linalg.det(R) > 0).all()))  # (a reflection is orthogonal too)
        if not rigid:
            raise UserError(f"cam_from_source must be [N,4,4] rigid transforms (a rotation and a translation), got "
                            f"shape {tuple(cfs.shape)}" + (" with a rotation part that is not one" if cfs.ndim == 3
                                                            and cfs.shape[-2:] == (4, 4) else ""),
                            hint="Pass world-to-camera matrices in the scene's units, as pycolmap's "
                                 "Image.cam_from_world().matrix() gives them (with the row [0, 0, 0, 1]).")
        Ks = torch.as_tensor(K, dtype=torch.float64)
        Ks = Ks[None] if Ks.ndim == 2 else Ks
        if Ks.ndim != 3 or Ks.shape[-2:] != (3, 3) or len(Ks) not in (1, len(cfs)):
            raise UserError(f"K must be [3,3] or [N,3,3] with N = {len(cfs)} poses, got shape {tuple(Ks.shape)}")
        if int(width) < 1 or int(height) < 1:
            raise UserError(f"the image size must be positive, got {width}x{height}")
        names = tuple(names) or tuple(f"pose_{i}" for i in range(len(cfs)))
        if len(names) != len(cfs):
            raise UserError(f"{len(names)} name(s) for {len(cfs)} pose(s): give one name per pose (or none)")
        cfw = normalized_cam_from_world(cfs, self._world_from_source)
        return Cameras(cfw.float(), Ks.expand(len(cfs), 3, 3).float().clone(), int(width), int(height), names)

    def predict(self, cameras: Cameras, num_samples: int | None = None, seed: int = 0) -> Prediction:
        """``evaluate``'s mean and std maps of ``cameras`` (normalised world: ``cameras_from_source`` or
        ``scene.cameras``), one view at a time. Each view's generator is seeded as ``evaluate`` seeds it
        (``eval.engine.view_seed``): a camera named as one of the scene's views by its index there, so that ``seed``
        = evaluate's ``--seed`` gives its EXR maps; any other camera by its pose and intrinsics, so that a pose gets
        the same maps wherever it stands in a batch.

        ``num_samples``: posterior samples (None: the config's K). The std factor and tails were fitted at the
        config's K: for another K load with ``cfg=EvalConfig(num_samples=k)``, which fits them at k."""
        from uncertsplat import native

        with native.single_threaded_torch(self.device):  # as evaluate runs (its sums, so its maps, to the last bit)
            return self._predict(cameras, num_samples, seed)

    def _predict(self, cameras: Cameras, num_samples: int | None, seed: int) -> Prediction:
        import hashlib

        from uncertsplat.eval.engine import predictive_terms, view_seed
        from uncertsplat.uncertainty.mc import mc_render

        k = int(num_samples if num_samples is not None else self._cfg.num_samples)
        if k < 1:
            raise UserError(f"num_samples must be 1 or more, got {k}")
        out = []
        gen = torch.Generator(device=self.device)
        with torch.no_grad():
            index = {n: i for i, n in enumerate(self.scene.cameras.image_names)}
            for j in range(len(cameras)):
                cam = cameras[[j]].to(self.device)
                name = cameras.image_names[j] if cameras.image_names else None
                if name in index:
                    at = index[name]
                else:  # a pose of one's own: an index from its bytes, past the scene's (which count from 0)
                    key = torch.cat([cameras.cam_from_world[j].flatten(), cameras.K[j].flatten()]).cpu().numpy()
                    at = len(index) + int.from_bytes(hashlib.sha256(key.tobytes()).digest()[:5], "little")
                gen.manual_seed(view_seed(seed, at))
                maps, _ = mc_render(self._sampler.sample_fn, self._sampler.render_fn, cam, k, gen,
                                    **predictive_terms(self._sampler, self._cfg, cam))
                out.append(maps)
        to_source = 1.0 / self.scale

        def cat(name: str) -> Tensor:
            return torch.cat([getattr(m, name) for m in out]).cpu()

        return Prediction(rgb_mean=cat("rgb_mean"), rgb_std=cat("rgb_std"), depth_mean=cat("depth_mean") * to_source,
                          depth_std=cat("depth_std") * to_source, alpha=cat("alpha_mean"), std_factor=self.std_factor,
                          dof=self.dof, depth_to_source=to_source, image_names=tuple(cameras.image_names))


__all__ = ["Prediction", "Predictor"]
