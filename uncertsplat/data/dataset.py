"""Pixel data of a loaded scene as tensors: images, GT depth and validity masks.

Everything is resized to the size of ``scene.cameras`` (after the scene's downscale factor) with area
averaging, and returned on the requested device.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from uncertsplat.console import list_names, q
from uncertsplat.conventions import NO_SURFACE_DEPTH
from uncertsplat.errors import UserError
from uncertsplat.io.images import (
    is_opaque_8bit,
    read_depth_image,
    read_exr,
    read_image,
    read_image_8bit,
    read_image_size,
    read_mask,
    resize_image,
    resize_mask,
)
from uncertsplat.types import PhotoFit, Photos, SceneData, ViewSet, as_float_photos


def _indices(scene: SceneData, indices: Sequence[int] | None) -> list[int]:
    return list(range(len(scene.cameras))) if indices is None else [int(i) for i in indices]


def load_images(scene: SceneData, indices: Sequence[int] | None = None, device=None,
                on_photo: Callable[[], None] | None = None) -> Tensor:
    """Images of the cameras ``indices`` (all when None) as [C,H,W,3] float32 in [0, 1].

    Transparent pixels are composited over the scene's background colour (``SceneConfig.background``); photos
    of another size than the scene's are turned and cropped first (``SceneData.photo_fits``). An 8-bit photo
    without alpha that is resized (``scene.downscale``) is rounded back to 8 bits (``resized_8bit``), so that
    ``load_photos`` keeps it as uint8. ``on_photo``: called as each photo is loaded (a progress bar).
    """
    bg = tuple(scene.source.get("background", (0.0, 0.0, 0.0)))
    W, H = scene.cameras.width, scene.cameras.height
    idx = _indices(scene, indices)
    # filled one photo at a time: a list of photos then np.stack held every photo twice at the peak (12 GB for 300
    # photos of 1600x1200 instead of 6)
    out = torch.empty((len(idx), H, W, 3), dtype=torch.float32, device=device)  # [C,H,W,3]
    for k, i in enumerate(idx):
        if is_opaque_8bit(scene.image_paths[i]) and not _at_size(scene, i):
            out[k] = as_float_photos(torch.from_numpy(resized_8bit(scene, i)))
        else:
            out[k] = torch.from_numpy(resize_image(read_photo(scene, i, background=bg), W, H))
        if on_photo is not None:
            on_photo()
    return out


def load_photos(scene: SceneData, indices: Sequence[int] | None = None, device=None,
                on_photo: Callable[[], None] | None = None) -> Photos:
    """The images of ``load_images`` as ``Photos``: their 8-bit values (uint8, a quarter of the memory) when every
    one is an 8-bit file without alpha (resized ones rounded back to 8 bits: ``resized_8bit``), else the same
    float32 tensor ``load_images`` gives. Indexing gives float32 equal to ``load_images``'s to the bit either way."""
    idx = _indices(scene, indices)
    if not all(is_opaque_8bit(scene.image_paths[i]) for i in idx):
        return Photos(load_images(scene, idx, device, on_photo))
    W, H = scene.cameras.width, scene.cameras.height
    out = torch.empty((len(idx), H, W, 3), dtype=torch.uint8, device=device)  # [C,H,W,3], one photo at a time
    for k, i in enumerate(idx):
        if not _at_size(scene, i):
            out[k] = torch.from_numpy(resized_8bit(scene, i))
        else:
            image = read_image_8bit(scene.image_paths[i])
            if scene.photo_fits is not None:
                image = fit_photo(scene.photo_fits[i], image)  # turned and cropped only (_at_size): stays uint8
            out[k] = torch.from_numpy(image)
        if on_photo is not None:
            on_photo()
    return Photos(out)


def resized_8bit(scene: SceneData, index: int) -> np.ndarray:
    """[H,W,3] uint8: the 8-bit photo ``index`` (``is_opaque_8bit``) resized to the cameras' size (the area under
    each pixel averaged: ``io.images.resize_image``) and rounded back to 8 bits. Kept as float32, a photo resized by
    ``scene.downscale`` took four times the memory of one that was not (``downscale = 1.25`` needed more than 1: a
    user's 300 photos of 2016x1512 at downscale 2 are 2.7 GB instead of 11); the rounding is at most half a level,
    a noise of 0.0011 RMS in [0, 1], below any photo's own."""
    image = resize_image(read_photo(scene, index), scene.cameras.width, scene.cameras.height)
    return np.clip(np.rint(image * 255.0), 0, 255).astype(np.uint8)


def _at_size(scene: SceneData, index: int) -> bool:
    """Whether photo ``index`` needs no resize (headers only): the photo, turned, is at the size its fit scales it
    to, and its crop or itself is the cameras' size."""
    path = scene.image_paths[index]
    w, h = read_image_size(path)  # as stored, as read_image gives it
    fit = scene.photo_fits[index] if scene.photo_fits is not None else None
    if fit is not None:
        if fit.turns % 2:
            w, h = h, w
        if (w, h) != tuple(fit.scaled):
            return False
        w, h = fit.width, fit.height
    return (w, h) == (scene.cameras.width, scene.cameras.height)


def read_photo(scene: SceneData, index: int,
               background: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """The photo of camera ``index`` [H,W,3] float32 at its full size, turned and cropped as the scene's cameras
    are (``SceneData.photo_fits``)."""
    image = read_image(scene.image_paths[index], background=background)
    return image if scene.photo_fits is None else fit_photo(scene.photo_fits[index], image)


def photo_turns(scene: SceneData) -> dict[str, int]:
    """{image name: clockwise quarter turns} of the photos the scene turned to its common orientation
    (``SceneData.photo_fits``); empty when none was turned. ``turned_back`` lays a map of such a view as its photo
    lies."""
    if scene.photo_fits is None:
        return {}
    return {name: fit.turns % 4 for name, fit in zip(scene.cameras.image_names, scene.photo_fits, strict=True)
            if fit.turns % 4}


def turned_back(image: np.ndarray | Tensor, turns: int) -> np.ndarray | Tensor:
    """``image`` [H,W,...] of a view the scene turned by ``turns`` clockwise quarter turns (``photo_turns``), turned
    back as its photo lies: how ``evaluate`` writes such a view's maps, so a reader comparing them with the
    scene's images turns the images the same way."""
    k = turns % 4
    if k == 0:
        return image
    if isinstance(image, Tensor):
        return torch.rot90(image, k=k, dims=(0, 1))
    return np.ascontiguousarray(np.rot90(image, k=k, axes=(0, 1)))


def fit_photo(fit: PhotoFit, image: np.ndarray) -> np.ndarray:
    """The copy of ``image`` [H,W,...] float that ``fit`` makes: turned, brought to the photo's (scaled) size when it
    differs (a resized photo, or a map of it at another resolution such as a GT depth map), then cropped."""
    if fit.turns % 4:
        image = np.rot90(image, k=-(fit.turns % 4), axes=(0, 1))  # clockwise
    sw, sh = fit.scaled
    if image.shape[:2] != (sh, sw):
        image = resize_image(np.ascontiguousarray(image, dtype=np.float32), sw, sh)
    return np.ascontiguousarray(image[fit.y0:fit.y0 + fit.height, fit.x0:fit.x0 + fit.width])


def depth_channel(channels: dict[str, np.ndarray], path: Path) -> str:
    """The channel of an EXR that holds depth: ``Z`` or ``depth``; else the one channel whose last name part is ``Z``
    (a layered file: Blender's ``ViewLayer.Depth.Z``; of several, the one named for depth and not a std, as
    ``depth_mean.Z`` of ``evaluate``'s maps); else the only channel, or ``Y`` / ``R`` of a grey image. A layered
    file read its first channel (Blender's red, evaluate's alpha) without a word.

    Raises:
        UserError: no channel can be told to be depth, naming the channels.
    """
    names = list(channels)
    for exact in ("Z", "depth", "Depth", "DEPTH"):
        if exact in channels:
            return exact
    zs = [k for k in names if k.split(".")[-1] in ("Z", "z", "depth", "Depth")]
    if len(zs) > 1:
        zs = [k for k in zs if "depth" in k.lower() and "std" not in k.lower()] or zs
    if len(zs) == 1:
        return zs[0]
    if len(names) == 1:
        return names[0]
    if not zs:
        grey = [k for k in ("Y", "R") if k in channels]
        if grey == ["Y"] or (grey == ["R"] and all(np.array_equal(channels["R"], channels[c]) for c in ("G", "B")
                                                   if c in channels)):
            return grey[0]
    raise UserError(f"cannot tell which channel of the EXR holds depth: {', '.join(names)}", path=path,
                    hint="Write the depth as a channel named Z (or depth), or as a one-channel EXR or a .npy file.")


DEPTH_EXTENSIONS = (".npy", ".exr", ".png", ".tif", ".tiff")
"""The GT depth maps read, in the order a name is looked up (``load_depth_folder``)."""


def read_depth_file(path: Path) -> np.ndarray:
    """A GT depth map [H,W] float32 from .npy, from .exr (the channel ``depth_channel`` finds), or from a one-channel
    16-bit PNG or float TIFF (``io.images.read_depth_image``: the stored values, e.g. millimetres)."""
    path = Path(path)
    if path.suffix.lower() in (".png", ".tif", ".tiff"):
        arr = read_depth_image(path)
    elif path.suffix.lower() == ".npy":
        try:
            arr = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as err:
            raise UserError(f"cannot read the depth map ({err})", path=path,
                            hint="The file may be truncated or not a NumPy array: write it again (np.save of an "
                                 "HxW float array), or regenerate the scene if `uncertsplat synth` wrote it.") from None
    else:
        channels = read_exr(path)
        arr = channels[depth_channel(channels, path)]
    arr = np.asarray(arr, dtype=np.float32)
    if arr.ndim == 3 and arr.shape[-1] == 1:
        arr = arr[..., 0]
    if arr.ndim != 2:
        raise UserError(f"depth map must be 2-D (one depth per pixel), got shape {arr.shape}", path=path,
                        hint="Save one channel per map: an HxW array in .npy, or an EXR with a Z (or depth) channel; "
                             "a colour-coded depth image cannot be read as depth.")
    return arr


SHAPE_TOLERANCE = 0.02
"""A depth map whose width / height differs from its photo's by more than this fraction is another shape, refused:
resized to the photo it was stretched (a transposed map: AbsRel 0.55 against 0.07, no word)."""


def shape_fits(width: int, height: int, photo_width: int, photo_height: int, slack: float = 0.0) -> bool:
    """Whether a map of ``width`` x ``height`` is of the shape of a photo ``photo_width`` x ``photo_height`` (any
    resolution of it): their aspects within ``SHAPE_TOLERANCE`` plus ``slack`` (in log ratio)."""
    return abs(np.log((width / height) / (photo_width / photo_height))) <= SHAPE_TOLERANCE + slack


def _check_shape(shape: tuple[int, int], width: int, height: int, fit: PhotoFit | None, path: Path, what: str,
                 why: str, hint: str) -> None:
    """Refuse a map of a photo (``what``: "the depth map", "the mask") of ``shape`` (h, w) whose aspect is not its
    photo's (``SHAPE_TOLERANCE``): the photo as stored, which its ``fit`` turns to turned_width x turned_height;
    without one, the view's ``width`` x ``height`` (the photo downscaled, each side rounded: a pixel's slack)."""
    w, h = ((fit.turned_width, fit.turned_height) if fit.turns % 2 == 0 else (fit.turned_height, fit.turned_width)) \
        if fit is not None else (width, height)
    if not shape_fits(shape[1], shape[0], w, h, 0.0 if fit is not None else 1.0 / w + 1.0 / h):
        whose = "its photo's" if fit is not None else "its view's"
        raise UserError(f"{what} is {shape[1]}x{shape[0]}, another shape than {whose} {w}x{h} ({why})", path=path,
                        hint=hint)


def load_depth_map(path: Path, width: int, height: int, fit: PhotoFit | None = None) -> np.ndarray:
    """One depth map [H,W] float32 resized to ``width`` x ``height``; non-finite, <= 0 or ``NO_SURFACE_DEPTH`` and
    beyond becomes 0 (invalid), and so does a resized pixel any invalid source pixel contributes to. ``fit``: its
    photo's ``PhotoFit``, applied first (the map turned and cropped as the photo is).

    Raises:
        UserError: the map is not of its photo's shape (``SHAPE_TOLERANCE``), naming both sizes.
    """
    d = read_depth_file(path)
    d = np.where(np.isfinite(d) & (d > 0) & (d < NO_SURFACE_DEPTH), d, 0.0).astype(np.float32)
    _check_shape(d.shape[:2], width, height, fit, path, "the depth map",
                 "stretched to it, it would be scored against the wrong pixels",
                 "Give each photo a depth map of its own shape (any resolution of it); a transposed or cropped map "
                 "needs turning or padding first.")
    # resized with its validity: a pixel keeps a depth only where every source pixel it is made of has one (a depth
    # camera's holes, 0, were averaged into their neighbours: a map at half the photos' size scored abs_rel 0.28
    # where the same depth at full size scored 0.02, pixels at 402 mm where the surface lies at 9 m)
    valid = (d > 0).astype(np.float32)
    if fit is not None:
        d, valid = fit_photo(fit, d), fit_photo(fit, valid)
    d, valid = resize_image(d, width, height), resize_image(valid, width, height)
    return np.where(valid >= 1.0 - 1e-5, d, 0.0).astype(np.float32)


def load_depths(scene: SceneData, indices: Sequence[int] | None = None, device=None) -> Tensor | None:
    """GT depth [C,H,W,1] in normalised world units (GT depth x the normalisation scale), or None.

    0 marks pixels without a valid depth. Downscaling averages depth over each target pixel's area
    (exact for smooth surfaces; mixes the two sides at depth edges, which ``load_masks`` excludes).
    """
    if scene.depth_paths is None:
        return None
    scale = 1.0 / scene.depth_scale_to_gt if scene.depth_scale_to_gt else 1.0
    W, H = scene.cameras.width, scene.cameras.height
    idx = _indices(scene, indices)
    out = torch.empty((len(idx), H, W, 1), dtype=torch.float32, device=device)  # [C,H,W,1], filled as load_images
    for k, i in enumerate(idx):
        out[k, ..., 0] = torch.from_numpy(load_depth_map(scene.depth_paths[i], W, H) * scale)
    return out


ALPHA_MASK_AT = 0.5
"""A transparent photo's pixel is scored where its alpha (averaged over the source pixels under it) reaches this:
the object, not the background it is composited over."""


def load_masks(scene: SceneData, indices: Sequence[int] | None = None, device=None) -> Tensor | None:
    """Validity masks [C,H,W,1] bool, or None when the scene has none.

    A scene's own masks (a synthetic scene's ``masks/``): a downscaled pixel is valid only when every source pixel
    under it is valid. Without them, photos with real transparency (an alpha channel below 1 somewhere: an object
    capture with its background removed, NeRF-synthetic's RGBA) are scored on their objects, alpha >=
    ``ALPHA_MASK_AT``: the background they are composited over is trivially right, and counted in it made a model's
    AUSE 0.048 and NLL -4.7 where its objects scored 0.285 and -0.46.
    """
    if scene.mask_paths is None:
        return _object_masks(scene, indices, device)
    W, H = scene.cameras.width, scene.cameras.height
    idx = _indices(scene, indices)
    out = torch.ones((len(idx), H, W, 1), dtype=torch.bool, device=device)  # [C,H,W,1], filled as load_images
    for k, i in enumerate(idx):
        if scene.mask_paths[i] is not None:  # (a photo without a mask: every pixel valid)
            fit = scene.photo_fits[i] if scene.photo_fits is not None else None
            out[k, ..., 0] = torch.from_numpy(load_mask(scene.mask_paths[i], W, H, fit))
            if scene.masks_train and not bool(out[k].any()):  # (its photo would train and score on nothing)
                raise UserError(f"the mask leaves no pixel of its photo ({scene.cameras.image_names[i]}) at "
                                f"{W}x{H}: it is all black there", path=scene.mask_paths[i],
                                hint="White marks the pixels that count; is it inverted, or held in an alpha channel "
                                     "that is 0 everywhere? Give that photo no mask to count every pixel, or leave "
                                     "the photo out.")
    return out


def load_mask(path: Path, width: int, height: int, fit: PhotoFit | None = None) -> np.ndarray:
    """One mask [H,W] bool at ``width`` x ``height``: valid where the file is white (``io.images.read_mask``: a 0/1
    mask's ones, a palette's colour, alpha), and a resized pixel only where every source pixel under it is. ``fit``:
    its photo's ``PhotoFit``, applied first.

    Raises:
        UserError: the mask is not of its photo's shape (``SHAPE_TOLERANCE``), naming both sizes.
    """
    valid = read_mask(path)  # [h,w]
    _check_shape(valid.shape[:2], width, height, fit, path, "the mask",
                 "stretched to it, it would leave out other pixels than it marks",
                 "Give each photo a mask of its own shape (any resolution of it), white where the pixels count and "
                 "black where they do not.")
    if fit is not None:
        valid = fit_photo(fit, valid.astype(np.float32))
    return resize_mask(valid, width, height)


def _object_masks(scene: SceneData, indices: Sequence[int] | None, device) -> Tensor | None:
    """``load_masks`` from the photos' alpha channels, or None when none of these photos is transparent."""
    from uncertsplat.io.images import read_alpha

    W, H = scene.cameras.width, scene.cameras.height
    idx = _indices(scene, indices)
    out = torch.ones((len(idx), H, W, 1), dtype=torch.bool, device=device)
    transparent = False
    for k, i in enumerate(idx):
        a = read_alpha(scene.image_paths[i])
        if a is None or bool((a >= 1.0).all()):
            continue
        transparent = True
        if scene.photo_fits is not None:  # turned and cropped as its photo (read_photo)
            a = fit_photo(scene.photo_fits[i], a[..., None])[..., 0]
        out[k, ..., 0] = torch.from_numpy(resize_image(np.ascontiguousarray(a, dtype=np.float32), W, H)
                                          >= ALPHA_MASK_AT)
    return out if transparent else None


def depth_map_names(name: str, names: Sequence[str]) -> list[str]:
    """The file names (without extension) ``--depth-gt`` looks up for image ``name`` among the scene's ``names``, in
    order: its path without the extension (``camA/frame`` for ``camA/frame.jpg``: the maps laid out as the images
    are), its maps' stem (``io.maps.map_stem``: ``camA__frame``, ``IMG_1_jpg`` beside an ``IMG_1.png``) and its bare
    stem (``frame``) when no other image has it. A name another image shares is never looked up: two views read
    one map without a word (``camA/frame.jpg`` and ``camB/frame.jpg`` both read ``frame.npy``)."""
    from uncertsplat.io.maps import map_stem

    rel = Path(name).with_suffix("").as_posix()
    stem = Path(name).stem
    out = []
    if not any(o != name and Path(o).with_suffix("").as_posix() == rel for o in names):
        out.append(rel)
    out.append(map_stem(name, names))
    if not any(o != name and Path(o).stem == stem for o in names):
        out.append(stem)
    return list(dict.fromkeys(out))


def _other_depth_files(folder: Path, looked: Sequence[str], photos: Sequence[Path] = ()) -> str:
    """For ``load_depth_folder``'s error: the files of a looked-up name with an extension that is not read, and how to
    convert them; else "". The scene's own ``photos`` are not depth maps: a folder of them (``--depth-gt`` given the
    images) is said to be that."""
    found = []
    for n in looked:
        where = (folder / n).parent
        if where.is_dir():
            found += sorted(p for p in where.iterdir() if p.stem == Path(n).name and p.is_file()
                            and p.suffix.lower() not in DEPTH_EXTENSIONS)
    own = {Path(p).resolve() for p in photos}
    if found and all(p.resolve() in own for p in found):
        return f"; {found[0].relative_to(folder).as_posix()} there is the scene's own photo: give the GT depth's folder"
    found = [p for p in found if p.resolve() not in own]
    if not found:
        return ""
    rel = found[0].relative_to(folder).as_posix()
    npy = Path(rel).with_suffix(".npy").as_posix()
    return (f"; {list_names([p.relative_to(folder).as_posix() for p in found], 3)} exists, but only "
            f"{', '.join(DEPTH_EXTENSIONS)} maps are read: convert each map to an HxW float array, "
            f"np.save('{npy}', depth) (--depth-scale auto fits the scale of any unit)")


def _sub_folder_with_map(folder: Path, looked: Sequence[str], own: set[Path]) -> str:
    """For ``load_depth_folder``'s error when no file has a looked-up name: a sub-folder that holds the map (a
    synthetic scene's folder given for its ``depth/``), named as the folder to give; else ""."""
    for sub in sorted(p for p in folder.iterdir() if p.is_dir() and not p.name.startswith(".")):
        for n in looked:
            for ext in DEPTH_EXTENSIONS:
                if (sub / f"{n}{ext}").is_file() and (sub / f"{n}{ext}").resolve() not in own:
                    return (f"; its sub-folder {sub.name}/ holds {n}{ext}: give that folder, --depth-gt "
                            f"{q(sub)}")
    return ""


def _folder_holds(folder: Path) -> str:
    """For ``load_depth_folder``'s error when no file has a looked-up name: a few of the files the folder holds (maps
    named otherwise, ``depth_000.png`` for ``view_000.png``, need renaming), or that it holds none."""
    entries = sorted(p.name + ("/" if p.is_dir() else "") for p in folder.iterdir() if not p.name.startswith("."))
    if not entries:
        return "; the folder is empty"
    shown = ", ".join(entries[:4]) + (", ..." if len(entries) > 4 else "")
    if not any(not e.endswith("/") for e in entries):  # (the maps one level down)
        return f"; the folder holds only folders ({shown}): give the one that holds the maps"
    return f"; the folder holds {shown}: a map is found by its photo's name (rename the maps after the photos)"


def load_depth_folder(folder: Path, scene: SceneData, indices: Sequence[int]) -> Tensor:
    """GT depth [C,H,W,1] of the cameras ``indices`` from ``folder/{name}.npy|.exr|.png|.tif`` (``--depth-gt``;
    ``name`` one of ``depth_map_names``; ``DEPTH_EXTENSIONS``).

    The maps stay in their own units (their scale to the scene is estimated by evaluation) and are
    resized to the cameras like ``load_depths``.

    Raises:
        UserError: the folder is missing, or holds no map for one of the images (naming it and the names looked
            up).
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise UserError("GT depth folder not found", path=folder,
                        hint="Give --depth-gt a folder of depth maps (.npy, .exr, 16-bit .png or float .tif).")
    W, H = scene.cameras.width, scene.cameras.height
    names = scene.cameras.image_names
    paths = []  # every map found before any is read: a missing one fails at once
    own = {Path(p).resolve() for p in getattr(scene, "image_paths", ())}
    for i in indices:
        looked = depth_map_names(names[i], names)
        cands = [c for c in (folder / f"{n}{ext}" for n in looked for e in DEPTH_EXTENSIONS for ext in (e, e.upper()))
                 if c.is_file()]
        # the scene's own photos are no depth maps (a view_000.tif depth beside its view_000.png photo is read)
        path = next((c for c in cands if c.resolve() not in own), None)
        if path is None and cands:  # (--depth-gt given the photos' folder)
            raise UserError(f"{cands[0].name} in the GT depth folder is the scene's own photo", path=folder,
                            hint="Give --depth-gt the folder of the depth maps, not of the photos.")
        if path is None:
            shared = [o for o in names if o != names[i] and Path(o).stem == Path(names[i]).stem]
            raise UserError(f"no GT depth map for image '{names[i]}'", path=folder,
                            hint=f"Expected {' or '.join(f'{n}.npy' for n in looked)} (or .exr, .png, .tif)"
                                 + (f"; {Path(names[i]).stem}.npy alone would be ambiguous: {list_names(shared)} "
                                    "has the same name" if shared else "")
                                 + (_sub_folder_with_map(folder, looked, own)
                                    or _other_depth_files(folder, looked, getattr(scene, "image_paths", ()))
                                    or _folder_holds(folder)) + ".")
        paths.append(path)
    out = torch.empty((len(paths), H, W, 1), dtype=torch.float32)  # [C,H,W,1], filled one map at a time
    for k, (i, path) in enumerate(zip(indices, paths, strict=True)):
        out[k, ..., 0] = torch.from_numpy(
            load_depth_map(path, W, H, scene.photo_fits[i] if scene.photo_fits is not None else None))
    return out


TRANSIENTS_FOLDER = "transients"
"""``RUN/transients/``: the training photos' transient regions ``train`` found (``TrainConfig.transients``), one
mask per photo with any, under COLMAP's name (``IMG_1.jpg.png``), black on the regions: ``evaluate``, ``prune``,
``view`` and ``predict`` leave them out of the fits on the training views as training left them out."""


def transient_mask_files(run_dir: Path) -> dict[str, Path]:
    """{image name: its mask} of every mask in ``RUN/transients/`` (``IMG_1.jpg.png`` is ``IMG_1.jpg``'s), in name
    order; empty without the folder."""
    folder = Path(run_dir) / TRANSIENTS_FOLDER
    if not folder.is_dir():
        return {}
    return {p.relative_to(folder).as_posix().removesuffix(".png"): p for p in sorted(folder.rglob("*.png"))}


def write_transient_masks(folder: Path, regions: Mapping[str, Tensor]) -> None:
    """Write ``regions`` ({image name: [H,W] bool, white where the pixels count}) as the masks of a ``TRANSIENTS_FOLDER``
    into ``folder`` (``IMG_1.jpg.png`` for ``IMG_1.jpg``, as ``transient_mask_files`` reads them back)."""
    # (looked up at each call: tests stand in for it to fail a write)
    from uncertsplat.io.images import write_png

    for name, keep in regions.items():
        write_png(Path(folder) / f"{name}.png", keep.cpu().numpy())


def transient_mask_paths(run_dir: Path, names: Sequence[str]) -> dict[str, Path]:
    """{image name: its mask in ``RUN/transients/``} of the training photos ``names`` with one."""
    wanted = set(names)
    return {n: p for n, p in transient_mask_files(run_dir).items() if n in wanted}


def without_transients(masks: Tensor | None, scene: SceneData, indices: Sequence[int],
                       runs: Path | Sequence[Path | Mapping[str, Tensor]]) -> Tensor | None:
    """``masks`` [C,H,W,1] bool of the views ``indices`` (None: every pixel counts) without the transient regions
    the run folder(s) ``runs`` found in them (``TRANSIENTS_FOLDER``; an ensemble's members: a region any of them
    left out; an entry may be the regions themselves, {photo name: [H,W] bool, its pixels that count}: a checkpoint's,
    ``baselines.runs.checkpoint_transients``); ``masks`` itself when none was found there."""
    import torch.nn.functional as F

    names = [scene.cameras.image_names[i] for i in indices]
    out = masks
    W, H = scene.cameras.width, scene.cameras.height

    def keep(found, n) -> Tensor:  # [H,W] bool
        if not isinstance(found[n], Tensor):
            return torch.from_numpy(load_mask(found[n], W, H))
        m = found[n].cpu()
        if tuple(m.shape) != (H, W):  # (the photos' size differs from the checkpoint's: nearest, as load_mask)
            m = F.interpolate(m[None, None].float(), size=(H, W), mode="nearest")[0, 0] > 0.5
        return m

    for run in [runs] if isinstance(runs, (str, Path)) else runs:
        found = ({n: run[n] for n in names if n in run} if isinstance(run, Mapping)
                 else transient_mask_paths(run, names))
        if found and out is masks:
            out = torch.ones((len(names), H, W, 1), dtype=torch.bool) if masks is None else masks.clone()
        for k, n in enumerate(names):
            if n in found:
                out[k, ..., 0] &= keep(found, n).to(out.device)
    return out


def load_view_set(scene: SceneData, indices: Sequence[int], *, depth: bool = True,
                  depth_folder: Path | None = None, folder_in_scene_units: bool = False,
                  keep_8bit: bool = False, transients: Path | Sequence[Path | Mapping[str, Tensor]] | None = None
                  ) -> ViewSet:
    """The views ``indices`` of ``scene`` with their images, masks and GT depth, for evaluation (CPU).

    Args:
        keep_8bit: images as ``load_photos`` gives them (``Photos``: 8-bit photos as uint8, read as float32 equal
            to ``load_images``'s), for a reader that only indexes them; else a float32 tensor (``load_images``).
        depth: load the scene's own GT depth (in its normalised units, so ``depth_known_scale``).
        depth_folder: take GT depth from this folder instead (``load_depth_folder``; scale unknown).
        folder_in_scene_units: ``depth_folder``'s maps are in the scene's own (source) units: converted to its
            normalised units as the scene's own GT depth is (``depth_known_scale``).
        transients: a run folder (or several: an ensemble's members; or a checkpoint's regions, as
            ``without_transients`` takes them): the transient regions its training found in these views
            (``TRANSIENTS_FOLDER``) are left out of their masks.
    """
    indices = [int(i) for i in indices]
    depths, known = None, False
    if depth_folder is not None:  # first: a wrong folder fails before any image is read
        depths = load_depth_folder(depth_folder, scene, indices)
        if folder_in_scene_units:
            depths = depths / (scene.depth_scale_to_gt or 1.0)
            known = True
    elif depth:
        depths = load_depths(scene, indices)
        known = depths is not None
    images = load_photos(scene, indices) if keep_8bit else load_images(scene, indices)
    masks = load_masks(scene, indices)
    if transients is not None:
        masks = without_transients(masks, scene, indices, transients)
    return ViewSet(indices=tuple(indices), cameras=scene.cameras[indices], images=images,
                   masks=masks, depths=depths, depth_known_scale=known,
                   masks_trained=scene.masks_train)
