"""A trained run's predictive at any camera, from Python: what ``evaluate`` writes, for poses of your own.

``evaluate`` scores held-out photos; a robot asks about poses no photo was taken from (a planned view, a pose between
two photos, one nearer the surface). ``Predictor`` builds the same predictive ``evaluate`` uses (the samples' spread
and every term it adds: the pixel noise, the edge, colour-posterior, view-consistency, finer-detail, resolution,
depth-spread, hidden-depth and empty-ray terms, with the std factor and the Student-t tails fitted on the training or
set-aside views) and renders it for any camera, given in the scene's own coordinates and units (your COLMAP model's
or map frame) or in the run's normalised world::

    from uncertsplat.predict import Predictor

    pred = Predictor.load("RUN")  # fits what evaluate fits (or reads RUN/eval/residual.pt); ~1-30 s by the scene
    cams = pred.cameras_from_source(cam_from_source, K, width, height)  # [N,4,4] or [N,3,4] OpenCV world-to-camera,
    # [N,3,3]; camera-to-world poses: transform="world_from_cam", OpenGL/Blender axes: axes="opengl"
    out = pred.predict(cams, num_samples=10)  # seed: the run's evaluation's (evaluate --seed), config.seed
    out.depth_mean, out.depth_std  # [N,H,W,1], in the scene's own units
    out.rgb_mean, out.rgb_std      # [N,H,W,3]; out.std_factor: the factor evaluate fitted (its "calibrated" rows)
    lower, upper = out.interval(0.95)  # each pixel's central 95 % interval of its colour

The std maps are the raw ones, as in ``evaluate``'s EXR maps (the scene's views get them to the last bit for
evaluate's ``--seed``, ``predict``'s default); multiply the RGB std by ``std_factor`` for the calibrated one. The
RGB predictive is a Student-t with ``dof`` degrees of freedom *whose standard deviation is* ``rgb_std``: the
unit-variance t scaled by the std, i.e. scipy's ``t(df=dof, loc=mean, scale=std * sqrt((dof - 2) / dof))``, not
``scale=std`` (``eval.tails``; ``Prediction.interval``, ``examples/intervals.py``). ``rgb_mean`` is the samples'
mean as rendered, not clamped; ``evaluate`` scores, and writes to its EXR maps, the mean clamped to [0, 1].

``predict`` may be called from several threads at once, each call getting the maps a serial call gets (not faster
than one after another where the kernels already use every core: x0.75-1.32 with a pool of 2 on 2 cores).
"""

from __future__ import annotations

import dataclasses
import math
import operator
import threading
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import torch
from torch import Tensor

from uncertsplat.config import EVAL_SEED_MAX
from uncertsplat.console import q
from uncertsplat.errors import UserError
from uncertsplat.types import Cameras, focal_unusable, principal_point_near_edge, principal_point_place


@dataclass(frozen=True)
class Prediction:
    """The predictive of N cameras (``Predictor.predict``).

    Attributes:
        rgb_mean: [N,H,W,3] the mean of the posterior samples' renders, not clamped (``evaluate`` scores it, and
            writes it to its EXR maps, clamped to [0, 1]: ``rgb_mean.clamp(0, 1)`` is that).
        rgb_std: [N,H,W,3] the raw RGB std (``evaluate``'s EXR ``rgb_std``): the standard deviation of the predictive,
            a Student-t with ``dof`` degrees of freedom; scipy's ``t`` takes it as ``scale = rgb_std * sqrt((dof - 2)
            / dof)`` (``interval`` does this).
        depth_mean: [N,H,W,1] expected depth along the optical axis, in the scene's own units; 0 where the ray meets
            no Gaussian (no surface known there, not one at distance 0: mask by ``alpha``).
        depth_std: [N,H,W,1] its std, in the scene's own units (read as a Gaussian's, as ``evaluate``'s depth NLL).
        alpha: [N,H,W,1] the samples' mean accumulated opacity (low: the ray meets little of the model).
        std_factor: the factor ``evaluate`` fits for the RGB std (None: none fitted, e.g. no training view).
        dof: degrees of freedom of the Student-t the RGB std is read with (None: a Gaussian).
        depth_to_source: the factor from the run's normalised depth to the scene's units (already applied above).
        image_names: the cameras' names (``pose_0``, ``pose_1``, ... for cameras given without names, as
            ``Predictor.cameras_from_source`` names them).
        seen_free: [N] bool, whether a training photo looked through each camera's position before meeting a surface
            (``Predictor.seen_free``). False for a camera inside an object or behind a wall, whose maps look confident
            (it sees the inside of a surface the photos saw from outside), and for one in space no photo showed
            empty: a planner should not take such a pose as reachable. None: not computed.
        rgb_terms, depth_terms: with ``predict(..., terms=True)``, what each part of the predictive adds to the RGB
            variance (the mean over the channels) and to the depth variance (in the scene's units squared), [N,H,W,1]
            each, keyed as ``evaluate``'s ``variance_shares`` ("samples", "resolution", "empty rays", "pixel noise",
            ...): their sum is ``rgb_std ** 2`` (its mean over the channels, below the std's cap at 0.5) and
            ``depth_std ** 2``. Which part makes a pixel uncertain. None without ``terms``; empty mappings for an
            empty batch (the parts are known only once a view is rendered).
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
    seen_free: Tensor | None = None
    rgb_terms: dict[str, Tensor] | None = None
    depth_terms: dict[str, Tensor] | None = None

    def interval(self, p: float = 0.95, *, calibrated: bool = False) -> tuple[Tensor, Tensor]:
        """([N,H,W,3] lower, upper): each pixel's central interval of probability ``p`` for its colour, around the
        mean ``evaluate`` scores (``rgb_mean`` clamped to [0, 1]): mean +- w std with w the half-width of the
        unit-variance Student-t with ``dof`` degrees of freedom (``eval.tails.half_width``; the Gaussian's when
        ``dof`` is None), the std ``rgb_std``, or ``rgb_std * std_factor`` with ``calibrated``.

        Raises:
            ValueError: ``p`` not in [0, 1).
            UserError: ``calibrated`` without a fitted std factor.
        """
        from uncertsplat.eval.tails import half_width

        std = self.rgb_std
        if calibrated:
            if self.std_factor is None:
                raise UserError("this prediction has no fitted std factor (the run has no view to fit it on)",
                                hint="Use the raw std (calibrated=False).")
            std = std * self.std_factor
        w = half_width(float(p), self.dof)
        mean = self.rgb_mean.clamp(0, 1)
        return mean - w * std, mean + w * std


def _eval_config(cfg, evaluation):
    """``Predictor.load``'s ``cfg`` as an ``EvalConfig``: one as it is; a dict of its keys over the run's evaluation's
    settings ``evaluation`` (``cfg={"num_samples": 4}`` is that evaluation with K = 4, as ``evaluate --set`` changes
    one setting; with the defaults under it the predictive was another than the one ``evaluate`` scored), validated
    (a bad key named, as ``--set`` names it; a dict was an AttributeError about ``model_dump`` from deep inside the
    load)."""
    from collections.abc import Mapping

    from uncertsplat.config import EvalConfig, build_config

    def merged(base: dict, given: Mapping) -> dict:
        out = dict(base)
        for k, v in given.items():
            out[k] = merged(out[k], v) if isinstance(v, Mapping) and isinstance(out.get(k), dict) else v
        return out

    if isinstance(cfg, EvalConfig):
        return cfg
    if isinstance(cfg, Mapping):
        return build_config(EvalConfig, merged(evaluation.model_dump(mode="json"), cfg),
                            source="Predictor.load's cfg")
    raise TypeError(f"cfg must be an uncertsplat.config.EvalConfig (or a dict of its keys, e.g. {{'num_samples': 4}}), "
                    f"got {type(cfg).__name__}")


TRANSFORMS = ("cam_from_world", "world_from_cam")
"""The poses ``Predictor.cameras_from_source`` takes: world-to-camera (COLMAP's) or camera-to-world."""
AXES = ("opencv", "opengl", "blender")
"""The camera axes it takes: OpenCV's (x right, y down, z forward), OpenGL's = Blender's (x right, y up, z backward)."""
BLIND_POINTS = 20000
"""How many of the model's Gaussian means (evenly strided) ``cameras_from_source`` projects to tell a pose that sees
almost none of the model."""
MAX_SEED = EVAL_SEED_MAX
"""The largest seed ``Predictor.predict`` takes (``view_seed`` of it and of any view index stays a 64-bit seed)."""
_RIGID_HINT = ("Pass world-to-camera matrices in the scene's units, as pycolmap's Image.cam_from_world().matrix() "
               "gives them ([N,3,4], or [N,4,4] with the row [0, 0, 0, 1]); camera-to-world ones with "
               "transform=\"world_from_cam\", OpenGL/Blender axes with axes=\"opengl\".")


_PREDICTED = ("rgb_mean", "rgb_std", "depth_mean", "depth_std", "alpha_mean")
"""The maps of ``mc_render`` a ``Prediction`` holds."""


def _whole(value, name: str, minimum: int) -> int:
    """``value`` as an int: an integer, or a float that is one (320.0); anything else is refused (320.7 was cut to
    320 without a word)."""
    if isinstance(value, bool):
        raise UserError(f"{name} must be a whole number, got {value!r}")
    try:
        out = operator.index(value)  # int, numpy and 0-d torch integers
    except TypeError:
        try:  # a float of any kind (numpy's float32 of a camera-info array, a 0-d torch tensor) that is whole
            x = None if isinstance(value, (str, bytes)) else float(value)
        except (TypeError, ValueError, RuntimeError):
            x = None
        if x is None or not x.is_integer():
            raise UserError(f"{name} must be a whole number, got {value!r}") from None
        out = int(x)
    if out < minimum:
        raise UserError(f"{name} must be {minimum} or more, got {out}")
    return out


def _contiguous(values):
    """``values`` as torch takes them: a tensor detached (a pose with ``requires_grad`` warned from deep inside) and on
    the CPU (the checks compare with CPU constants: a robot's poses on the GPU ended in torch's device error), a
    numpy array with negative strides (``np.flip``, ``a[::-1]``), of the other byte order (``astype(">f8")``) or
    read-only (``np.broadcast_to``, ``np.frombuffer``) copied, which ``torch.as_tensor`` refuses (or warns of)."""
    if isinstance(values, torch.Tensor):
        return values.detach().cpu()
    if isinstance(values, (list, tuple)) and values and all(isinstance(v, torch.Tensor) for v in values):
        try:  # a list of poses as tensors: one tensor (torch.as_tensor takes a list of one-element tensors only)
            return torch.stack([v.detach().cpu() for v in values])
        except RuntimeError:  # of different shapes: the caller's message says what it takes
            return values
    if (isinstance(values, (list, tuple)) and values
            and all(type(v).__module__ == "numpy" and hasattr(v, "shape") for v in values)):
        import numpy as np  # (torch.as_tensor of a list of arrays warns that it is very slow)

        try:
            return np.stack(values)
        except ValueError:
            return values
    if type(values).__module__ == "numpy" and hasattr(values, "strides") and (
            any(st < 0 for st in values.strides) or not values.flags.writeable or not values.dtype.isnative):
        import numpy as np

        return np.array(values, dtype=values.dtype.newbyteorder("="))
    return values


ROTATION_TOLERANCE = 1e-5
"""How far from the identity ``R R^T`` of a pose given to ``cameras_from_source`` may be."""
HAND_ROTATION_TOLERANCE = 1e-3
"""The same for a ``Cameras`` built by hand and given to ``predict``: the scene loaders' (a ``transforms.json`` pose
within 1e-3 of a rotation trains, and ``scene.cameras`` holds it as written), so that the run's own cameras pass.
Taken of the pose or of its inverse (the loader measures ``R^T R`` of the camera-to-world pose, whose inverse is
``scene.cameras``' pose: ``R R^T`` of that is ``(R^T R)^-1``, a little further off), with float32's rounding."""


def _not_rigid(m: Tensor, tolerance: float, inverse_too: bool = False) -> str | None:
    """Why the finite [4,4] float64 ``m`` is not a rigid transform (as a clause: "has ..."), None when it is one.
    ``inverse_too``: a rotation part within ``tolerance`` measured on the inverse (as a loader measured it) passes."""
    if not torch.allclose(m[3], torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=m.dtype), rtol=0, atol=1e-6):
        # the renderer reads the top three rows only, the side terms invert the whole 4x4: the mean would be the
        # pose's and the std another's (or the inverse fails: a 3x4 padded with zeros)
        return f"has the last row {[round(float(v), 6) for v in m[3]]}, not [0, 0, 0, 1]"
    R = m[:3, :3]
    off = float((R @ R.T - torch.eye(3, dtype=m.dtype)).abs().max())  # how far from orthonormal
    within = off <= tolerance
    if inverse_too and not within and float(torch.linalg.det(R)) > 0:
        inv = torch.linalg.inv(R)  # the camera-to-world rotation the scene loader measured (R^T R of it)
        within = float((inv.T @ inv - torch.eye(3, dtype=m.dtype)).abs().max()) <= tolerance + 1e-6  # (float32)
    if not within:
        most = f"{tolerance:.0e}".replace("e-0", "e-")  # 1e-5, not 1e-05
        return (f"has a rotation part that is not orthonormal: R R^T is {off:.1e} off the identity (at most {most} "
                "is taken; a pose with a scale, a sim(3), is not rigid: divide its rotation by the scale, or "
                "re-orthonormalise it, e.g. by its SVD)")
    if float(torch.linalg.det(R)) <= 0:  # (a reflection is orthogonal too)
        return "has a rotation part that is a reflection (determinant < 0)"
    return None


def _its_pose(clause: str | None) -> str | None:
    return f"its pose (cam_from_world) {clause}" if clause is not None else None


def _check_cameras(cameras: Cameras) -> Cameras:
    """Refuse a ``Cameras`` (built by hand, not by ``cameras_from_source``) the renderer cannot take: an image size
    that is not a positive whole number (torch failed deep inside on 0, -5 or 1.5), a pose or K that is not finite
    (a NaN pose gave NaN maps without a word), a pose that is not rigid (a last row other than [0, 0, 0, 1], a 3x4
    padded with zeros, ended in torch's "linalg.inv: ... singular" from the view-consistency term; a scaled or
    mirrored rotation rendered other maps without a word), a focal length that is not positive. Returns them with
    the size as ints (320.0 is taken as 320)."""
    width, height = _whole(cameras.width, "the cameras' width", 1), _whole(cameras.height, "the cameras' height", 1)
    for i in range(len(cameras)):
        what = ("its pose (cam_from_world) is not finite" if not bool(torch.isfinite(cameras.cam_from_world[i]).all())
                else _its_pose(_not_rigid(cameras.cam_from_world[i].detach().double().cpu(), HAND_ROTATION_TOLERANCE,
                                          inverse_too=True))
                or ("its K is not finite" if not bool(torch.isfinite(cameras.K[i]).all())
                    else "its focal lengths are not positive, or too large for float32"
                    if bool(focal_unusable(cameras.K[i])) else None))
        if what is not None:
            name = f" ({cameras.image_names[i]})" if i < len(cameras.image_names) else ""
            raise UserError(f"camera {i}{name}: {what}",
                            hint="Build cameras from poses with cameras_from_source(cam_from_source, K, width, height), "
                                 "which checks them.")
    if type(cameras.width) is int and type(cameras.height) is int:
        return cameras
    return dataclasses.replace(cameras, width=width, height=height)


def _names(names) -> tuple[str, ...]:
    """``cameras_from_source``'s ``names`` as a tuple of texts: one text is one name (not its letters), None none (it
    was "'NoneType' object is not iterable"), numpy's texts and whole numbers (a frame index) as plain texts; anything
    else, a None among them, refused by its place (they became the maps' names as given)."""
    import numbers

    if names is None:
        return ()
    if isinstance(names, str):
        return (str(names),)
    if isinstance(names, (bytes, bytearray)):  # (iterated, its bytes were whole numbers: b"ab" named "97", "98")
        raise UserError(f"names must be texts, one per pose, got {type(names).__name__} {names!r}",
                        hint="Decode it first (names.decode()), or give one name per pose.")
    try:
        given = tuple(names)
    except TypeError:
        raise UserError(f"names must be texts, one per pose, got {type(names).__name__}") from None
    out = []
    for i, n in enumerate(given):
        if isinstance(n, str) or (isinstance(n, numbers.Integral) and not isinstance(n, bool)):
            out.append(str(n))
        else:
            raise UserError(f"name {i} must be a text (or a whole number), got {n!r}",
                            hint="Give one name per pose, e.g. names=(\"pose_a\", \"pose_b\"), or none.")
    return tuple(out)


def _cam_from_world(poses, transform: str, axes: str) -> Tensor:
    """[N,4,4] float64 world-to-camera transforms with OpenCV axes from ``cameras_from_source``'s poses."""
    if transform not in TRANSFORMS:
        raise UserError(f"unknown transform {transform!r}", hint=f"Use one of {', '.join(TRANSFORMS)}.")
    if axes not in AXES:
        raise UserError(f"unknown axes {axes!r}", hint=f"Use one of {', '.join(AXES)}.")
    try:
        m = torch.as_tensor(_contiguous(poses), dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError) as e:
        raise UserError(f"cam_from_source must be a tensor or array of poses ([N,4,4] or [N,3,4]), got "
                        f"{type(poses).__name__}: {e}") from None
    m = m[None] if m.ndim == 2 else m
    if m.ndim != 3 or m.shape[-2:] not in ((4, 4), (3, 4)):
        raise UserError(f"cam_from_source must be [N,4,4] or [N,3,4] rigid transforms (a rotation and a translation), "
                        f"got shape {tuple(m.shape)}", hint=_RIGID_HINT)
    if m.shape[-2] == 3:  # pycolmap's Rigid3d.matrix(): the row [0, 0, 0, 1] is implied
        m = torch.cat([m, torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=m.dtype).expand(len(m), 1, 4)], dim=1)
    for i in range(len(m)):
        what = None
        if not bool(torch.isfinite(m[i]).all()):
            what = "has entries that are not finite (NaN or infinite)"
        else:
            what = _not_rigid(m[i], ROTATION_TOLERANCE)
            given = str(getattr(poses, "dtype", "")).rsplit(".", 1)[-1]  # torch.float16 or numpy's float16
            if what is not None and "not orthonormal" in what and given in ("float16", "bfloat16", "half"):
                what += (f"; the poses are {given}, whose 2-3 significant digits cannot hold a rotation that "
                         "closely: pass them as float32 or float64")
        if what is not None:
            raise UserError(f"cam_from_source must be rigid transforms (a rotation and a translation): pose {i} {what}",
                            hint=_RIGID_HINT)
    m = m.clone()
    m[:, 3] = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=m.dtype)
    if transform == "world_from_cam":
        # the matrix inverse, not [R^T, -R^T t]: a robot's rotation is orthonormal to its float precision only, and
        # a pose inverted elsewhere (np.linalg.inv) then came back 1e-8 off the world-to-camera matrix it was made
        # from, so it got another seed (``pose_index``) and other maps (a helper: 20 poses of 20)
        m = torch.linalg.inv(m)
        m[:, 3] = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=m.dtype)  # (as given, not as rounded by the inverse)
    if axes != "opencv":  # OpenGL's camera (y up, z backward) is OpenCV's turned half a turn about x
        m = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=m.dtype)) @ m
    return m


def _swapped_size(cx: float, cy: float, width: int, height: int) -> bool:
    """Whether the principal point (``cx``, ``cy``) lies at the centre of a ``height`` x ``width`` image (within 2 %)
    and well off the centre of the ``width`` x ``height`` one given (10 %): the size passed as (height, width), the
    order of an image array's shape, which rendered an off-centre view of the pose without a word."""
    if width == height:
        return False
    swapped = abs(cx - height / 2) <= 0.02 * height and abs(cy - width / 2) <= 0.02 * width
    return swapped and (abs(cx - width / 2) > 0.1 * width or abs(cy - height / 2) > 0.1 * height)


def _intrinsics(K, n: int, width: int, height: int, outside_ok: bool = False) -> Tensor:
    """[1 or n,3,3] float64 pinhole intrinsics of ``cameras_from_source``: refused when the renderer could not take
    them as given (it reads fx, fy, cx, cy alone: a skew or another last row would be dropped without a word), and,
    unless ``outside_ok``, with the principal point outside the ``width`` x ``height`` image or in its outer
    ``types.EDGE_MARGIN`` (a full-size photo's K given with a smaller size renders a zoomed, off-centre patch whose
    std looks more certain, not an error; halved, its principal point lands exactly on the corner)."""
    try:
        Ks = torch.as_tensor(_contiguous(K), dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError) as e:
        raise UserError(f"K must be a tensor or array ([3,3] or [N,3,3]), got {type(K).__name__}: {e}") from None
    Ks = Ks[None] if Ks.ndim == 2 else Ks
    if Ks.ndim != 3 or Ks.shape[-2:] != (3, 3) or len(Ks) not in (1, n):
        raise UserError(f"K must be [3,3] or [N,3,3] with N = {n} poses, got shape {tuple(Ks.shape)}")
    for i in range(len(Ks)):
        k = Ks[i]
        fx, fy, cx, cy = (float(v) for v in (k[0, 0], k[1, 1], k[0, 2], k[1, 2]))
        what = None
        if bool(focal_unusable(k)):
            what = f"has the focal lengths {fx:g} / {fy:g} px: they must be positive and finite in float32"
        elif not (math.isfinite(cx) and math.isfinite(cy)):
            what = f"has the principal point {cx:g}, {cy:g}: it must be finite"
        elif not torch.allclose(k[2], torch.tensor([0.0, 0.0, 1.0], dtype=k.dtype), rtol=0, atol=1e-6):
            what = f"has the last row {[round(float(v), 6) for v in k[2]]}, not [0, 0, 1]"
        elif abs(float(k[0, 1])) > 1e-6 * fx or not math.isfinite(float(k[0, 1])) or float(k[1, 0]) != 0.0:
            what = (f"has the skew K[0,1] = {float(k[0, 1]):g} (or K[1,0] = {float(k[1, 0]):g}): the renderer takes "
                    "pinhole cameras without skew")
        hint = "Pass [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] in pixels."
        # near the edge too: a K twice the size with halved width and height puts it exactly on the corner
        if what is None and not outside_ok and bool(principal_point_near_edge(k, width, height)):
            what = f"has its principal point {principal_point_place(k, width, height)}"
            hint = (f"Scale fx, fy, cx and cy by the ratio of the sizes for a {width}x{height} render (or pass the "
                    "size the intrinsics were measured at); a crop whose optical centre lies outside it or near its "
                    "edge takes principal_point_outside=True.")
        if what is None and not outside_ok and _swapped_size(cx, cy, width, height):
            what = (f"has its principal point at ({cx:g}, {cy:g}): the centre of a {height}x{width} image, far off the "
                    f"centre of the {width}x{height} one given (width and height swapped? an image array's shape is "
                    "(height, width))")
            hint = (f"Pass width={height}, height={width}; a crop whose optical centre lies there takes "
                    "principal_point_outside=True.")
        if what is not None:
            where = "K" if len(Ks) == 1 and n != 1 else f"K of pose {i}"
            raise UserError(f"{where} {what}", hint=hint)
    return Ks


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
        self._free, self._free_lock = None, threading.Lock()  # ``_free_space``, built on first use
        self._train_seen: float | None = None  # ``_blind_poses_note``'s reference, measured on first use
        self.config = cfg
        self.std_factor: float | None = fit.scale
        self.dof: float | None = fit.dof
        T = scene.world_from_source.double()
        self._world_from_source = T  # [4,4] x_world = s x_source + t
        # s of x_world = s x_source + t: what evaluate's EXR header gives as 1 / depth_to_source
        self.scale = 1.0 / scene.depth_to_source

    @classmethod
    def load(cls, run_dir: str | Path, device: str | torch.device = "auto", *, cfg=None) -> Predictor:
        """The predictive of the run ``run_dir`` (any method: variational, deterministic, ensemble, fisher).

        Args:
            run_dir: a folder written by ``uncertsplat train``; its scene folder must be where ``scene.json`` says
                (the side terms are fitted on its training photos); a leading ``~`` is the home folder, as in a shell.
            device: ``auto``, ``cpu``, ``cuda[:n]`` or a torch.device.
            cfg: an ``EvalConfig`` (None: the settings of the run's evaluation, ``RUN/eval/config.json``, so that the
                predictive is the one ``evaluate`` scored; ``evaluate``'s defaults when the run has none;
                ``cfg.num_samples`` is ``predict``'s default K), or a dict of its keys (``{"num_samples": 4}``, as
                ``evaluate --set`` takes them) over those of the run's evaluation.

        Raises:
            UserError: not a run, its scene is gone or its cameras changed since training, no CUDA device, a ``cfg``
                dict with a key or value ``EvalConfig`` does not take.
            TypeError: a ``cfg`` that is neither an ``EvalConfig`` nor a dict.
        """
        from uncertsplat import native
        from uncertsplat.device import resolve_device

        if str(run_dir).startswith("~"):  # "~/runs/x", as a shell reads it (it was "run folder not found")
            try:
                run_dir = Path(run_dir).expanduser()
            except RuntimeError:  # "~nosuchuser/x": no such home folder, so no such run folder (said below)
                pass
        if not Path(run_dir).exists():  # (as the commands say it: "not a training run" sent users looking for a file)
            raise UserError("run folder not found", path=run_dir,
                            hint="Pass the folder written by `uncertsplat train` (or `prune`).")
        if Path(run_dir).is_file():  # (it said "config.json is missing" of RUN/config.json)
            raise UserError("Predictor.load takes a run folder, not a file in it", path=run_dir,
                            hint=f"Pass the folder: Predictor.load({str(Path(run_dir).parent)!r}).")
        from uncertsplat.stages.predictive_cache import evaluation_config

        device = resolve_device(device)
        evaluation = evaluation_config(Path(run_dir))
        cfg = _eval_config(cfg, evaluation) if cfg is not None else evaluation
        with native.single_threaded_torch(device):  # as evaluate runs (its sums, so its maps, to the last bit)
            return cls._load(Path(run_dir), device, cfg, evaluation)

    @classmethod
    def _load(cls, run_dir: Path, device: torch.device, cfg, evaluation) -> Predictor:
        from uncertsplat.baselines import load_run
        from uncertsplat.console import console
        from uncertsplat.eval.engine import StdFit, residual_from_state, scored_sampler
        from uncertsplat.io.atomic import run_lock
        from uncertsplat.stages.predictive_cache import keep_predictive, plain_versions, read_predictive
        from uncertsplat.stages.residual_cache import fitted_residual, same_residual_settings

        loaded = load_run(run_dir, device)
        loaded.warn_if_unfinished()  # (a run still training: its newest checkpoint is what is predicted)
        # what an evaluation of this model with these settings fitted on the photos (RUN/eval/predictive.pt): read
        # instead of fitted, and all there is where the scene folder is not (a robot has the run, not the photos)
        kept, problem = read_predictive(loaded, cfg, loaded.scene_path or run_dir)
        on_file = kept is not None  # the evaluation's, whatever device it was fitted on: never replaced here
        try:
            scene = loaded.load_scene()
        except UserError as err:
            if kept is None:
                ensemble = problem.startswith("an ensemble")
                raise UserError(f"{err.message}; and the predictive kept beside the run cannot stand in for it: "
                                f"{problem}", path=err.path,
                                hint=(err.hint or "Restore the scene folder.") if ensemble else
                                (f"{err.hint} Or r" if err.hint else "R")
                                + f"un `uncertsplat evaluate {q(run_dir)}` where the scene is, with the settings you load "
                                "(it keeps what the predictive needs in eval/predictive.pt), and copy the run folder "
                                "with its eval/ folder.") from err
            scene = kept.scene
            loaded = loaded.with_scene(scene)  # what reads the scene (the empty-ray term's coverage) reads this one
            where = (f"; on {device.type} the maps differ from evaluate's by the devices' rounding"
                     if kept.device != device.type else "")
            other = ", by another version or build of uncertsplat" if kept.versions != plain_versions() else ""
            console.print(f"[yellow]note:[/] the scene cannot be loaded ({err.message}): the predictive is the one "
                          f"kept in {run_dir / 'eval' / 'predictive.pt'} (fitted on {kept.device}{other}{where})")
        else:
            if kept is not None and (kept.device != device.type or kept.versions != plain_versions()):
                kept = None  # fitted on another device or by another version: fitted again, as evaluate would
            if kept is None and (" cannot be read (" in problem or " is of another format" in problem):
                console.print(f"[yellow]note:[/] {problem}: the predictive is fitted again on the training photos")
        new_sampler = partial(loaded.sampler, scene.scene_scale, device)
        if kept is not None:
            if scene is not kept.scene:
                console.print(f"predictive: the pixel noise and std factor read from {run_dir / 'eval' / 'predictive.pt'}"
                              " (fitted earlier for this model and these settings)")
            residual = (residual_from_state(new_sampler(), kept.residual_state, device)
                        if kept.residual_state is not None else None)
            sampler, fit = scored_sampler(new_sampler, residual, scene.cameras, scene.split, cfg, device,
                                          load_views=None, known_fit=StdFit(kept.scale, kept.dof, list(kept.names)))
            return cls(run_dir, loaded, scene, sampler, fit, cfg, device)
        train_views = loaded.training_views(scene)  # as evaluate loads them
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
        sampler, fit = scored_sampler(new_sampler, residual, scene.cameras, scene.split, cfg, device,
                                      load_views=train_views, set_aside_maps=set_aside)
        if not on_file and cfg.model_dump() == evaluation.model_dump():  # the evaluation's: kept for the next load
            try:
                with run_lock(run_dir, "predict"):
                    keep_predictive(loaded, scene, cfg, residual, fit, device)
            except (UserError, OSError):
                pass  # a read-only run, or one another process holds: only read
        return cls(run_dir, loaded, scene, sampler, fit, cfg, device)

    def cameras_from_source(self, cam_from_source: Tensor, K: Tensor, width: int, height: int,
                            names: tuple[str, ...] = (), *, transform: str = "cam_from_world",
                            axes: str = "opencv", principal_point_outside: bool = False) -> Cameras:
        """Cameras given in the scene's own frame (the COLMAP model's, your map's), in the run's normalised world.

        Args:
            cam_from_source: N poses, [N,4,4] or [N,3,4] (or one, [4,4] or [3,4]; a [3,4] gets the row [0, 0, 0, 1]):
                rigid transforms (a rotation and a translation), translations in the scene's units. By default
                world-to-camera with OpenCV axes (x right, y down, z forward), as pycolmap's
                ``Image.cam_from_world().matrix()`` gives them; ``transform`` and ``axes`` take the others.
            K: [N,3,3] or [3,3] pinhole intrinsics in pixels of a ``width`` x ``height`` image (any size: the render
                takes it; the run's own is ``scene.cameras.width`` x ``height``): positive finite focal lengths, a
                finite principal point, no skew, last row [0, 0, 1].
            width, height: the image size in pixels (whole numbers).
            names: N names, texts (default, or None: ``pose_0``, ``pose_1``, ...; whole numbers are taken as texts).
            transform: ``"cam_from_world"`` (world-to-camera, COLMAP's) or ``"world_from_cam"`` (camera-to-world: the
                camera's pose in the world, as Blender, NeRF's ``transforms.json`` and most robot frames give it).
            axes: the camera's axes, ``"opencv"`` (x right, y down, z forward: COLMAP, OpenCV, ROS optical frames) or
                ``"opengl"`` (x right, y up, z backward: OpenGL, Blender, NeRF's ``transforms.json``; ``"blender"``
                is the same).
            principal_point_outside: accept a principal point outside the image or in its outer 5 % (a crop of a
                larger view); refused by default, as ``train`` refuses it (``SceneConfig.principal_point_outside``): it
                is what the full-size photo's K given with a smaller image size looks like. Also one at the centre of
                a ``height`` x ``width`` image, off this one's centre: what width and height swapped look like.

        Raises:
            UserError: a pose or K that is not a tensor or array, of the wrong shape, not rigid or not finite,
                unusable intrinsics or a principal point outside the image, near its edge or where width and height
                swapped put it (the message names the pose's index), names that do not match the poses, an image size
                that is not a positive whole number.
        """
        from uncertsplat.sfm.scene import normalized_cam_from_world

        cfs = _cam_from_world(cam_from_source, transform, axes)
        width, height = _whole(width, "width", 1), _whole(height, "height", 1)
        Ks = _intrinsics(K, len(cfs), width, height, principal_point_outside)
        names = _names(names)
        names = names or tuple(f"pose_{i}" for i in range(len(cfs)))
        if len(names) != len(cfs):
            raise UserError(f"{len(names)} name(s) for {len(cfs)} pose(s): give one name per pose (or none)")
        cfw = normalized_cam_from_world(cfs, self._world_from_source)
        cams = Cameras(cfw.float(), Ks.expand(len(cfs), 3, 3).float().clone(), width, height, names)
        note = self._blind_poses_note(cams)
        if note is not None:
            from uncertsplat.console import console

            console.print(f"[yellow]note:[/] {note}")
        return cams

    def _blind_poses_note(self, cams: Cameras) -> str | None:
        """A note on the poses that see under a tenth of what the training views see of the model's Gaussians
        (their median): most often a pose in another convention (camera-to-world given as world-to-camera, OpenGL
        axes as OpenCV's), whose maps otherwise look like an honest, uncertain view (a review's OpenGL pose on the
        demo scene: alpha 0.50 and a high std, no word). None when each sees the model, or without a model or
        training cameras (``select.candidates.seen_fraction``; at most ``BLIND_POINTS`` of the means, evenly)."""
        from uncertsplat.select.candidates import seen_fraction

        if self.loaded is None or self.scene is None or not len(cams):
            return None
        means = self.loaded.model.params["means"].detach()
        if not len(means):
            return None
        points = means[:: max(1, len(means) // BLIND_POINTS)]
        if self._train_seen is None:
            train = list(self.scene.split.get("train", ()))
            ref = seen_fraction(self.scene.cameras[train], points) if train else torch.zeros(0)
            self._train_seen = float(ref.median()) if len(ref) else 0.0
        if self._train_seen <= 0.0:
            return None
        seen = seen_fraction(cams, points)
        blind = [j for j in range(len(seen)) if float(seen[j]) < 0.1 * self._train_seen]
        if not blind:
            return None
        names = cams.image_names or tuple(f"pose {j}" for j in range(len(seen)))
        listed = ", ".join(f"{names[j]} {100 * float(seen[j]):.1f} %" for j in blind[:6]) + (
            ", ..." if len(blind) > 6 else "")
        return (f"{len(blind)} of {len(seen)} pose(s) see almost none of the model ({listed} of its Gaussians in view, "
                f"the training views {100 * self._train_seen:.0f} %): where they face what no photo showed, the maps "
                "hold little (low alpha, the empty rays' std); otherwise check the poses' convention: "
                "transform=\"world_from_cam\" for camera-to-world poses, axes=\"opengl\" for x right, y up, z backward")

    def seen_free(self, points, frame: str = "source") -> Tensor:
        """[P] bool: whether a training photo's ray passed through each point on its way to the surface the model
        renders there (the point in that photo's image, in front of its camera, nearer than the rendered depth by
        more than 3 % of it, or where the ray meets nothing): space a photo showed empty. False inside objects and
        behind walls, where a render is confident but means nothing, and where no photo looked; a planner keeps its
        poses and paths in the True part. Tested against the renders of up to 64 training views (the
        view-consistency term's, else rendered once on the first call).

        Args:
            points: [P,3] or [3] positions, in the scene's own frame and units (``frame="source"``, as
                ``cameras_from_source`` takes poses) or the run's normalised world (``frame="world"``, as
                ``scene.cameras``).
            frame: ``"source"`` or ``"world"``.

        Raises:
            UserError: points not [P,3] or not finite, an unknown frame.
        """
        if frame not in ("source", "world"):
            raise UserError(f"frame must be 'source' or 'world', got {frame!r}")
        try:
            pts = torch.as_tensor(_contiguous(points), dtype=torch.float64)
        except (TypeError, ValueError, RuntimeError) as e:
            raise UserError(f"points must be a tensor or array of [P,3] positions, got {type(points).__name__}: {e}"
                            ) from None
        given = tuple(pts.shape)
        if pts.ndim == 1 and pts.numel() == 0:  # an empty list of points (a planner's empty waypoint list): [0,3]
            pts = pts.reshape(0, 3)
        elif pts.ndim == 1:
            pts = pts[None]
        if pts.ndim != 2 or pts.shape[-1] != 3:
            raise UserError(f"points must be [P,3] or [3], got {given}")
        if not bool(torch.isfinite(pts).all()):
            bad = int((~torch.isfinite(pts).all(-1)).nonzero()[0, 0])
            raise UserError(f"point {bad} is not finite: {pts[bad].tolist()}")
        if frame == "source":
            T = self._world_from_source
            pts = pts @ T[:3, :3].T + T[:3, 3]
        return self._free_space().seen_free(pts.float().to(self.device)).cpu()

    def _free_space(self):
        """The training renders ``seen_free`` tests against: the view-consistency term's (``ViewConsistency``), or
        one built for it on the first call when the predictive has none (``consistency_views = 0``)."""
        from uncertsplat.config import EvalConfig
        from uncertsplat.eval.engine import view_consistency

        if self._sampler.consistency is not None:
            return self._sampler.consistency
        with self._free_lock:
            if self._free is None:
                train = self.scene.cameras[list(self.scene.split.get("train", ()))]
                if len(train) == 0:
                    raise UserError("the run has no training view to tell free space by")
                # every training view up to the default 64 (what the docstring says), as select-views' poses
                self._free = view_consistency(self._sampler, train, EvalConfig(finer_detail=False), self.device)
        return self._free

    def predict(self, cameras: Cameras, num_samples: int | None = None, seed: int | None = None, *,
                terms: bool = False) -> Prediction:
        """``evaluate``'s mean and std maps of ``cameras`` (normalised world: ``cameras_from_source`` or
        ``scene.cameras``), one view at a time. Each view's generator is seeded as ``evaluate`` seeds it
        (``eval.engine.view_seed``): a camera named as one of the scene's views by its index there, so that ``seed``
        = evaluate's ``--seed`` gives its EXR maps; any other camera by its pose and intrinsics
        (``eval.engine.pose_index``), so that a pose gets the same maps wherever it stands in a batch.

        Args:
            cameras: a ``Cameras`` batch; an empty one gives an empty ``Prediction`` (maps [0,H,W,C]).
            num_samples: posterior samples (None: the config's K). The std factor and tails were fitted at the
                config's K: for another K load with ``cfg=EvalConfig(num_samples=k)``, which fits them at k.
            seed: the evaluation seed (None: the config's, ``config.seed``: the run's evaluation's unless ``load``
                was given a ``cfg``, so that the scene's views get ``evaluate``'s EXR maps); 0 to 2**32 - 1.
            terms: also return each part's variance map (``Prediction.rgb_terms`` / ``depth_terms``); the other maps
                are the same.

        Calls may come from several threads at once (a thread pool over candidate views), each getting the maps a
        serial call gets; on a CPU each call runs torch's own ops on one thread, so a pool of about as many threads
        as cores is what makes use of them.

        Raises:
            TypeError: ``cameras`` is not a ``Cameras`` (poses as matrices go through ``cameras_from_source``).
            UserError: ``num_samples`` or ``seed`` not a whole number in range; a ``Cameras`` built by hand whose image
                size is not a positive whole number, whose poses are not finite or not rigid (within 1e-3), or
                whose intrinsics are not finite or have a focal length that is not positive (``cameras_from_source``
                refuses these and more).
        """
        from uncertsplat import native

        if not isinstance(cameras, Cameras):
            raise TypeError(f"predict takes a Cameras batch, got {type(cameras).__name__}: give poses as matrices to "
                            "cameras_from_source(cam_from_source, K, width, height) first, or pass scene.cameras[...]")
        cameras = _check_cameras(cameras)
        k = _whole(num_samples if num_samples is not None else self._cfg.num_samples, "num_samples", 1)
        seed = _whole(seed if seed is not None else self._cfg.seed, "seed", 0)
        if seed > MAX_SEED:  # torch's CPU generator keeps a seed's low 32 bits (config.EVAL_SEED_MAX)
            raise UserError(f"seed must be at most {MAX_SEED} (2**32 - 1), got {seed}")
        with native.single_threaded_torch(self.device):  # as evaluate runs (its sums, so its maps, to the last bit)
            return self._predict(cameras, k, seed, bool(terms))

    def _predict(self, cameras: Cameras, k: int, seed: int, terms: bool = False) -> Prediction:
        from uncertsplat.eval.engine import pose_index, predictive_terms, view_seed
        from uncertsplat.uncertainty.mc import mc_render

        out = []
        gen = torch.Generator(device=self.device)
        with torch.no_grad():
            index = {n: i for i, n in enumerate(self.scene.cameras.image_names)}
            for j in range(len(cameras)):
                # in float32, the scene's cameras' and the renderer's precision: a pose given in float64 renders to
                # the bit as the same pose in float32 (the terms that read the camera in its own dtype made the std
                # maps of the two differ in their last bit on an Intel VM)
                cam = cameras[[j]].to(self.device, torch.float32)
                name = cameras.image_names[j] if cameras.image_names else None
                # a pose of one's own: an index from its bytes, past the scene's (which count from 0)
                at = index[name] if name in index else len(index) + pose_index(cameras.cam_from_world[j],
                                                                               cameras.K[j])
                gen.manual_seed(view_seed(seed, at))
                maps, _ = mc_render(self._sampler.sample_fn, self._sampler.render_fn, cam, k, gen, terms=terms,
                                    **predictive_terms(self._sampler, self._cfg, cam))
                # each view's maps to the CPU as it is done: kept on the device, a batch of poses would hold them
                # all there (75 MB a view at 1920x1080), and joined there, twice that
                out.append({n: getattr(maps, n).cpu() for n in _PREDICTED})
                if terms:
                    out[-1]["terms"] = ({k: t.cpu() for k, t in maps.rgb_terms.items()},
                                        {k: t.cpu() for k, t in maps.depth_terms.items()})
                del maps  # (not held on the device while the next view renders)
        to_source = 1.0 / self.scale

        def join(views: list[dict], name: str) -> Tensor:
            # each view's piece is let go once joined (popped: the list below holds the last reference), so that a
            # batch peaks at what it returns plus one map, not at twice what it returns (every view's pieces kept
            # until the last map was joined)
            pieces = [v.pop(name) for v in views]
            joined = torch.cat(pieces)
            del pieces
            return joined

        def cat(name: str, channels: int, scale: float = 1.0) -> Tensor:
            if not out:  # no camera: empty maps of the cameras' size
                return torch.zeros(0, cameras.height, cameras.width, channels)
            return join(out, name).mul_(scale) if scale != 1.0 else join(out, name)

        rgb_terms = depth_terms = None
        if terms and out:
            rgb_parts = [m["terms"][0] for m in out]
            depth_parts = [m.pop("terms")[1] for m in out]
            rgb_terms = {k: join(rgb_parts, k) for k in list(rgb_parts[0])}
            depth_terms = {k: join(depth_parts, k).mul_(to_source**2) for k in list(depth_parts[0])}
        elif terms:
            rgb_terms, depth_terms = {}, {}
        return Prediction(rgb_mean=cat("rgb_mean", 3), rgb_std=cat("rgb_std", 3),
                          depth_mean=cat("depth_mean", 1, to_source), depth_std=cat("depth_std", 1, to_source),
                          alpha=cat("alpha_mean", 1), std_factor=self.std_factor, dof=self.dof,
                          depth_to_source=to_source,
                          image_names=tuple(cameras.image_names) or tuple(f"pose_{i}" for i in range(len(cameras))),
                          seen_free=self._free_space().seen_free(cameras.centers.to(self.device)).cpu()
                          if len(cameras) else torch.zeros(0, dtype=torch.bool),
                          rgb_terms=rgb_terms, depth_terms=depth_terms)


__all__ = ["Prediction", "Predictor"]
