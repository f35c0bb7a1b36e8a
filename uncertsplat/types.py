"""Core data types shared by every stage (frozen dataclasses of tensors).

Shapes follow ``uncertsplat.conventions``: C cameras, N Gaussians, H, W image size, B SH bases.
"""

from __future__ import annotations

from dataclasses import InitVar, dataclass, field, fields, replace
from pathlib import Path

import torch
from torch import Tensor


def _map_tensors(obj, fn):
    """Return a copy of a frozen dataclass with ``fn`` applied to every tensor field."""
    changes = {}
    for f in fields(obj):
        value = getattr(obj, f.name)
        if isinstance(value, Tensor):
            changes[f.name] = fn(value)
    return replace(obj, **changes)


def principal_point_outside(K: Tensor, width: int, height: int) -> Tensor:
    """[C] bool: which of the [C,3,3] intrinsics ``K`` put the principal point outside a ``width`` x ``height``
    image (the edges count as inside). Both ``train``'s scene check and the ``Predictor`` refuse such cameras unless
    told they are crops: usually a full-size photo's intrinsics given with a smaller image."""
    c = K[..., :2, 2].double()  # [C,2]
    return (c[..., 0] < 0) | (c[..., 0] > width) | (c[..., 1] < 0) | (c[..., 1] > height)


EDGE_MARGIN = 0.05
"""``principal_point_near_edge``: the outer fraction of an image's width and height (each side) a photo's principal
point is not expected in."""


def principal_point_near_edge(K: Tensor, width: int, height: int) -> Tensor:
    """[C] bool: which of the [C,3,3] intrinsics ``K`` put the principal point in the outer ``EDGE_MARGIN`` of a
    ``width`` x ``height`` image, or outside it: a photo's optical centre lies near its middle, and one at the corner
    is mostly the intrinsics of photos twice the size given with halved files (their principal point lands exactly on
    the corner, which ``principal_point_outside`` counts as inside)."""
    c = K[..., :2, 2].double()  # [C,2]
    m = EDGE_MARGIN
    return ((c[..., 0] < m * width) | (c[..., 0] > (1 - m) * width)
            | (c[..., 1] < m * height) | (c[..., 1] > (1 - m) * height))


def principal_point_place(K: Tensor, width: int, height: int, whose: str = "the") -> str:
    """Where the [3,3] intrinsics ``K`` put the principal point that ``principal_point_near_edge`` refused, for an
    error message: "at (cx, cy), outside (or at the edge of) WHOSE WxH image", with the image size the intrinsics
    suggest where both coordinates point there (``intrinsics_size_guess``; near one edge only: no guess)."""
    cx, cy = float(K[0, 2]), float(K[1, 2])
    beyond = bool(principal_point_outside(K, width, height))
    size = intrinsics_size_guess(cx, cy) if beyond or (cx > width / 2 and cy > height / 2) else ""
    return f"at ({cx:g}, {cy:g}), {'outside' if beyond else 'at the edge of'} {whose} {width}x{height} image{size}"


def focal_unusable(K: Tensor) -> Tensor:
    """[C] bool: which of the [C,3,3] intrinsics ``K`` have a focal length (fx or fy) the renderer cannot use: not
    finite, not positive, or beyond float32's range (the renderer works in float32: 1e39 px became inf and drew
    nothing). ``train``'s scene check and the ``Predictor`` refuse them."""
    f = torch.stack([K[..., 0, 0], K[..., 1, 1]], dim=-1).double()  # [C,2]
    return (~torch.isfinite(f) | (f <= 0) | (f >= torch.finfo(torch.float32).max)).any(-1)


def intrinsics_size_guess(cx: float, cy: float) -> str:
    """The size a principal point at (``cx``, ``cy``) suggests (it sits near the image centre), as a clause for an
    error message; empty when the point gives no guess."""
    return f"; the intrinsics seem to belong to images of about {2 * cx:.0f}x{2 * cy:.0f} pixels" if cx > 0 and cy > 0 else ""


@dataclass(frozen=True)
class Cameras:
    """A batch of pinhole cameras sharing one image size.

    Attributes:
        cam_from_world: [C,4,4] world-to-camera rigid transforms (OpenCV axes).
        K: [C,3,3] intrinsics in pixels.
        width: image width in pixels.
        height: image height in pixels.
        image_names: C image names (file names relative to the images folder).
    """

    cam_from_world: Tensor  # [C,4,4]
    K: Tensor  # [C,3,3]
    width: int
    height: int
    image_names: tuple[str, ...] = ()

    def __post_init__(self):
        if self.cam_from_world.ndim != 3 or self.cam_from_world.shape[-2:] != (4, 4):
            raise ValueError(f"cam_from_world must be [C,4,4], got {tuple(self.cam_from_world.shape)}")
        if self.K.shape != (self.cam_from_world.shape[0], 3, 3):
            raise ValueError(f"K must be [C,3,3] matching cam_from_world, got {tuple(self.K.shape)}")
        if self.image_names and len(self.image_names) != self.cam_from_world.shape[0]:
            raise ValueError("image_names must have one name per camera")

    def __len__(self) -> int:
        return self.cam_from_world.shape[0]

    def __getitem__(self, idx) -> Cameras:
        """Select cameras as numpy and torch index: an integer (Python, numpy or a 0-d tensor, e.g. ``score.argmax()``),
        a slice, a sequence of integers (list, array, long tensor; negative ones count from the end) or a mask of
        ``len(self)`` booleans (list, array or bool tensor, e.g. ``Prediction.seen_free``). Always a ``Cameras``.

        Raises:
            IndexError: an index out of range, a mask of another length, or something that is neither.
        """
        sel = self._selection(idx)
        index = torch.as_tensor(sel, dtype=torch.long, device=self.K.device)
        names = tuple(self.image_names[i] for i in sel) if self.image_names else ()
        return Cameras(self.cam_from_world[index], self.K[index], self.width, self.height, names)

    def _selection(self, idx) -> list[int]:
        """``idx`` (as ``__getitem__`` takes it) as a list of indices in [0, len(self))."""
        import numpy as np

        n = len(self)
        if isinstance(idx, slice):
            return list(range(n))[idx]
        if isinstance(idx, Tensor):
            idx = idx.detach().cpu().numpy()
        try:
            arr = np.asarray(idx)
        except (TypeError, ValueError) as err:  # (a ragged list)
            raise IndexError(f"cameras are selected by integers, a slice or a mask of booleans, not {idx!r}") from err
        if arr.dtype == np.bool_:
            if arr.ndim != 1 or arr.shape[0] != n:  # a single True would select camera 1 as an integer
                raise IndexError(f"a mask of booleans selecting cameras must hold one per camera ({n}), found "
                                 f"shape {list(arr.shape)}")
            return np.flatnonzero(arr).tolist()
        if arr.size == 0 and arr.ndim == 1:
            return []
        if arr.ndim > 1 or not np.issubdtype(arr.dtype, np.integer):
            raise IndexError(f"cameras are selected by integers, a slice or a mask of booleans, not {idx!r}")
        flat = arr.reshape(-1).tolist()
        bad = [i for i in flat if not -n <= i < n]
        if bad:
            raise IndexError(f"camera index {bad[0]} is out of range for {n} camera(s)")
        return [i % n for i in flat]

    @property
    def device(self) -> torch.device:
        return self.K.device

    @property
    def world_from_cam(self) -> Tensor:  # [C,4,4]
        return torch.linalg.inv(self.cam_from_world)

    @property
    def centers(self) -> Tensor:  # [C,3] camera centres in world coordinates
        R = self.cam_from_world[:, :3, :3]
        t = self.cam_from_world[:, :3, 3]
        return -(R.transpose(1, 2) @ t[..., None])[..., 0]

    def to(self, device=None, dtype=None) -> Cameras:
        return _map_tensors(self, lambda t: t.to(device=device, dtype=dtype))

    def scaled(self, factor: float) -> Cameras:
        """Cameras for images resized by ``factor`` (e.g. 0.5 halves width and height).

        The size is rounded to whole pixels, and an image is resized to that size edge to edge, so each axis is
        scaled by its own ratio (new size / old size), not by ``factor``: 533 rows halved are 266, a scale of
        0.49906, and intrinsics scaled by 0.5 would put the bottom rows half a pixel off their photo.
        """
        w = max(1, round(self.width * factor))
        h = max(1, round(self.height * factor))
        K = self.K.clone()
        K[:, 0, :] *= w / self.width
        K[:, 1, :] *= h / self.height
        return Cameras(self.cam_from_world, K, w, h, self.image_names)


@dataclass(frozen=True)
class PhotoFit:
    """How one photo is brought to the scene's common image size (``SceneData.photo_fits``): turned by ``turns``
    clockwise quarter turns (0; 1 or 3 for a portrait photo among landscape ones, the turn that puts the scene's up
    where the other photos have it) to ``turned_width`` x ``turned_height``,
    resized to ``scaled_width`` x ``scaled_height`` (another camera's resolution of the same shape; the turned size
    when not resized), then cropped to ``width`` x ``height`` pixels from column ``x0`` and row ``y0``
    (``data.dataset.fit_photo``). Its camera is turned, scaled and shifted to match when the scene is loaded."""

    turns: int
    x0: int
    y0: int
    width: int
    height: int
    turned_width: int
    turned_height: int
    scaled_width: int = 0
    scaled_height: int = 0

    @property
    def scaled(self) -> tuple[int, int]:
        """(width, height) after the resize (the turned size when there is none)."""
        return (self.scaled_width or self.turned_width, self.scaled_height or self.turned_height)


@dataclass(frozen=True)
class SceneData:
    """A loaded scene: cameras, image files, split, sparse points, normalisation.

    Attributes:
        cameras: all cameras, in the order of ``image_paths`` (sorted by image name).
        image_paths: one path per camera.
        split: {"train": indices, "test": indices} into the cameras, and "calibration" (views set aside from
            training for the std factor) when ``SceneConfig.calibration_holdout`` asks for it.
        points: [P,3] sparse points in the (normalised) world frame.
        points_rgb: [P,3] their colours in [0, 1].
        scene_scale: radius of the camera rig after normalisation (the "extent" of 3DGS is 1.1 x this).
        world_from_source: [4,4] similarity applied to the source coordinates (recorded, invertible).
        depth_paths: optional GT depth per camera (camera z in source units, .npy or .exr).
        mask_paths: optional validity mask per camera (None for a camera without one: every pixel valid). A pixel
            is valid where its mask is white; a downscaled pixel only where every source pixel under it is.
        masks_train: whether training leaves the pixels outside the masks out too (masks a user brought: a transient
            object, the rig, the sky), not only the scoring (a synthetic scene's masks mark where its GT is defined).
        depth_scale_to_gt: factor from world (normalised) depth to GT depth units, when known.
        source: what was loaded ("colmap", "nerf_synthetic", "nerfstudio", "synthetic") and from where.
        center: source coordinates of the scene centre (the world origin after normalisation, and the middle
            of random initial points); None when unknown.
        center_method: how ``center`` was found: "optical_axes" or "camera_centroid".
        center_reason: why that method was chosen (one sentence, recorded in RUN/scene.json).
        photo_fits: per camera, how its photo is turned and cropped to the common image size (``PhotoFit``), when
            the photos came in more than one size; None when every photo is read as it is.
        notes: what loading changed or left out that a user should know (printed by ``train``).
    """

    cameras: Cameras
    image_paths: tuple[Path, ...]
    split: dict[str, tuple[int, ...]]
    points: Tensor  # [P,3]
    points_rgb: Tensor  # [P,3]
    scene_scale: float
    world_from_source: Tensor  # [4,4]
    depth_paths: tuple[Path, ...] | None = None
    mask_paths: tuple[Path | None, ...] | None = None
    masks_train: bool = False
    depth_scale_to_gt: float | None = None
    source: dict = field(default_factory=dict)
    center: tuple[float, float, float] | None = None
    center_method: str = "camera_centroid"
    center_reason: str = ""
    photo_fits: tuple[PhotoFit, ...] | None = None
    notes: tuple[str, ...] = ()

    def subset(self, split: str) -> Cameras:
        return self.cameras[list(self.split[split])]

    @property
    def extent(self) -> float:
        """3DGS "cameras extent": 1.1 x the largest camera distance from the centroid."""
        return 1.1 * self.scene_scale

    @property
    def depth_to_source(self) -> float:
        """The factor from the run's normalised depth to the scene's own units: ``depth_scale_to_gt`` when known,
        else 1 / s of ``world_from_source`` (``similarity_scale``)."""
        if self.depth_scale_to_gt:
            return float(self.depth_scale_to_gt)
        return 1.0 / similarity_scale(self.world_from_source)


def similarity_scale(world_from_source) -> float:
    """s of a similarity [4,4] (x_world = s R x_source + t; a tensor, array or nested list): the cube root of its
    3x3 part's absolute determinant, in float64 (0 for a degenerate one)."""
    m = torch.as_tensor(world_from_source, dtype=torch.float64)
    return float(torch.linalg.det(m[:3, :3]).abs() ** (1.0 / 3.0))


@dataclass(frozen=True)
class GaussianSample:
    """Activated Gaussian parameters, ready to render.

    Attributes:
        means: [N,3] world positions.
        quats: [N,4] rotations, wxyz (need not be normalised).
        scales: [N,3] linear standard deviations along the local axes.
        opacities: [N] in [0, 1].
        sh: [N,B,3] spherical-harmonic coefficients (B = (sh_degree_max + 1) ** 2).
        sh_degree: the degree to evaluate (<= the degree the coefficients allow).
        position_var: optional [N] variance of an isotropic position noise N(0, var I) to average each
            Gaussian over (``variational.expected_render_sample``): ``render`` then draws the Gaussian
            convolved with it, i.e. covariance Sigma + var I, with its opacity scaled per view by
            sqrt(det Sigma2d / det Sigma2d') (both with the screen-space dilation) so that its footprint
            keeps the mass of the sharp one. None (the default) is a plain render.
        sh_rest: optional [N,B-1,3]: the higher SH bands apart, ``sh`` then holding the DC [N,1,3] only (a
            training step's sample: the parameter table's two tensors, rendered without a concatenated copy;
            ``render.sh.sh_colors_split``). ``full_sh`` gives [N,B,3] either way.
    """

    means: Tensor  # [N,3]
    quats: Tensor  # [N,4]
    scales: Tensor  # [N,3]
    opacities: Tensor  # [N]
    sh: Tensor  # [N,B,3], or [N,1,3] with sh_rest
    sh_degree: int = 0
    position_var: Tensor | None = None  # [N]
    sh_rest: Tensor | None = None  # [N,B-1,3]

    def __post_init__(self):
        # every tensor one row per Gaussian: the native kernels read N rows of each by pointer, so a [1,3] scales
        # beside [N,3] means rendered memory past its end (a developer's hand-built sample: images from run to run)
        n = self.means.shape[0] if self.means.ndim == 2 else -1
        want = {"means": (3,), "quats": (4,), "scales": (3,), "opacities": (), "position_var": ()}
        for name, tail in want.items():
            t = getattr(self, name)
            if t is not None and tuple(t.shape) != (n, *tail):
                raise ValueError(f"GaussianSample.{name} must be [N{''.join(f',{d}' for d in tail)}] with N = "
                                 f"{self.means.shape[0] if self.means.ndim else '?'} (the rows of means [N,3]), got "
                                 f"{tuple(t.shape)}")
        for name in ("sh", "sh_rest"):
            t = getattr(self, name)
            if t is not None and (t.ndim != 3 or t.shape[0] != n or t.shape[2] != 3):
                raise ValueError(f"GaussianSample.{name} must be [N,B,3] with N = {self.means.shape[0]} (the rows of "
                                 f"means), got {tuple(t.shape)}")

    def __len__(self) -> int:
        return self.means.shape[0]

    def full_sh(self) -> Tensor:
        """[N,B,3] every SH coefficient (``sh``, or ``sh`` and ``sh_rest`` concatenated)."""
        return self.sh if self.sh_rest is None else torch.cat([self.sh, self.sh_rest], dim=1)

    def to(self, device=None, dtype=None) -> GaussianSample:
        return _map_tensors(self, lambda t: t.to(device=device, dtype=dtype))

    def detach(self) -> GaussianSample:
        return _map_tensors(self, lambda t: t.detach())


@dataclass(frozen=True)
class RenderOutput:
    """What ``render`` returns.

    Attributes:
        rgb: [C,H,W,3] composited colour including the background.
        alpha: [C,H,W,1] accumulated opacity.
        depth: [C,H,W,1] alpha-normalised camera z (0 where alpha == 0): given, or computed from ``depth_expected``
            and ``alpha`` when first read (a training step never reads it: five image-sized tensor ops saved).
        depth_expected: [C,H,W,1] sum of w_i z_i (not normalised).
        means2d: [C,N,2] projected means in pixels; its ``.grad`` after backward is what the
            densification strategy reads (the tensor retains its gradient).
        radii: [C,N] screen radius in pixels (0 = culled).
        depths: [C,N] camera z of each Gaussian's mean.
    """

    rgb: Tensor
    alpha: Tensor
    depth_expected: Tensor
    means2d: Tensor
    radii: Tensor
    depths: Tensor | None = None
    depth: InitVar[Tensor | None] = None

    def __post_init__(self, depth: Tensor | None) -> None:
        object.__setattr__(self, "_depth", depth)


def _render_depth(self: RenderOutput) -> Tensor:
    if self._depth is None:
        hit = self.alpha > 0
        # A hit pixel has alpha >= 1/255 (its first contribution alone), so the division is safe.
        object.__setattr__(self, "_depth", torch.where(
            hit, self.depth_expected / torch.where(hit, self.alpha, torch.ones_like(self.alpha)), 0.0))
    return self._depth


# set after the dataclass is built: its ``depth`` init argument reads the class attribute as the default
RenderOutput.depth = property(_render_depth, doc="[C,H,W,1] alpha-normalised camera z (0 where alpha == 0).")


@dataclass(frozen=True)
class UncertaintyMaps:
    """Monte-Carlo mean and standard deviation maps for a batch of views.

    Attributes:
        rgb_mean, rgb_std: [C,H,W,3]
        depth_mean, depth_std: [C,H,W,1]
        alpha_mean: [C,H,W,1]
        n_samples: number of posterior samples used.
        image_names: C names.
        rgb_terms, depth_terms: what each part of the predictive adds to the RGB variance (mean over the channels)
            and the depth variance, [C,H,W,1] each, keyed by the part's name in the order they are added; their sum
            is the variance (the RGB std before its cap, ``mc.RGB_STD_MAX``). None unless asked for
            (``mc_render``'s ``terms``).
    """

    rgb_mean: Tensor
    rgb_std: Tensor
    depth_mean: Tensor
    depth_std: Tensor
    alpha_mean: Tensor
    n_samples: int
    image_names: tuple[str, ...] = ()
    rgb_terms: dict[str, Tensor] | None = None
    depth_terms: dict[str, Tensor] | None = None


@dataclass(frozen=True)
class ViewSet:
    """Views of a scene with what they should show: the input of the evaluation engine.

    Built from a scene by ``data.dataset.load_view_set``; ``eval.engine`` only reads the tensors.

    Attributes:
        indices: the views' camera indices in their scene. Evaluation seeds each view's generator with
            its index, so a view gets the same samples whichever other views are evaluated with it.
        cameras: the C cameras (``scene.cameras[indices]``); their ``image_names`` name the views.
        images: [C,H,W,3] float32 GT images in [0, 1] (CPU), or ``Photos`` (8-bit photos kept as uint8; indexing
            gives float32 all the same: ``load_view_set(keep_8bit=True)``).
        masks: [C,H,W,1] bool, True where a pixel counts; None: every pixel counts.
        depths: [C,H,W,1] GT depth, 0 where unknown; None: no GT depth.
        depth_known_scale: ``depths`` are in the scene's own (normalised) world units, so evaluation uses
            them as they are instead of estimating a scale.
        masks_trained: the masks are the photos' own, which training left out too (``SceneData.masks_train``), or
            the transient regions training found (``transients_out``) where the views have no masks of their own.
        transients_out: the masks leave out the transient regions training found in these (training) views
            (``LoadedRun.scored_views``).
        own_masks_too: with ``transients_out``, the views' own masks are in the masks too (not the transient
            regions alone).
    """

    indices: tuple[int, ...]
    cameras: Cameras
    images: Tensor | Photos
    masks: Tensor | None = None
    depths: Tensor | None = None
    depth_known_scale: bool = False
    masks_trained: bool = False
    transients_out: bool = False
    own_masks_too: bool = False

    def __len__(self) -> int:
        return len(self.indices)

    @property
    def names(self) -> list[str]:
        """The image name of each view."""
        return list(self.cameras.image_names)


class Photos:
    """A stack of photos [C,H,W,3] kept as stored and read as float32 in [0, 1].

    ``data`` holds either the 8-bit values of 8-bit files (uint8: 3 bytes a pixel instead of 12; 300 photos of
    1600x1200 are 1.7 GB instead of 6.9) or float32 (16-bit and float files, resized or composited photos). Indexing
    gives float32, a photo converted where it is used: ``photos[i]`` [H,W,3], ``photos[a:b]`` or ``photos[[i, j]]``
    [B,H,W,3], the same values to the bit as a float32 stack of ``io.images.read_image`` (uint8 times
    float32(1/255), OpenImageIO's conversion). A float32 ``data`` is given back as it is (a slice shares its memory).

    Attributes:
        data: [C,H,W,3] uint8 or float32.
    """

    def __init__(self, data: Tensor):
        if data.dtype not in (torch.uint8, torch.float32):
            raise TypeError(f"Photos holds uint8 or float32, got {data.dtype}")
        self.data = data

    def __len__(self) -> int:
        return int(self.data.shape[0])

    def __getitem__(self, index) -> Tensor:
        return as_float_photos(self.data[index])

    @property
    def shape(self) -> torch.Size:
        return self.data.shape

    @property
    def device(self) -> torch.device:
        return self.data.device

    @property
    def dtype(self) -> torch.dtype:
        """The dtype indexing gives (float32), whatever ``data`` holds."""
        return torch.float32

    def to(self, device) -> Photos:
        """The photos on ``device`` (kept as stored)."""
        return Photos(self.data.to(device))

    def float(self) -> Tensor:
        """All the photos [C,H,W,3] float32 at once (a copy when stored as uint8: four times their memory)."""
        return as_float_photos(self.data)


UINT8_PHOTO_SCALE = torch.tensor(1.0 / 255.0, dtype=torch.float32).item()
"""float32(1/255), by which an 8-bit value becomes ``io.images.read_image``'s float32 (OpenImageIO's conversion: one
float32 multiplication, not a division by 255, which differs in the last bit for 126 of the 256 values)."""


def as_float_photos(images: Tensor) -> Tensor:
    """``images`` [...,H,W,3] as float32 in [0, 1]: uint8 times float32(1/255) (what OpenImageIO computes, to the
    bit: one float32 multiplication, not a division by 255), float32 as it is."""
    if images.dtype == torch.uint8:
        # the Python float becomes float32(1/255) in a float32 product (a scalar takes the tensor's dtype)
        return images.to(torch.float32).mul_(UINT8_PHOTO_SCALE)
    return images
