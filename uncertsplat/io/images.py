"""Image reading and writing through OpenImageIO.

Images are returned as float32 HWC arrays in [0, 1] (RGB), whatever the file's bit depth or channel
layout: grayscale is replicated to RGB, an alpha channel is composited over a background colour, and
the EXIF orientation of photos is applied. Every write is atomic (temp file in the same folder, then
rename), so an interrupted run never leaves a half-written image under its final name.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import OpenImageIO as oiio

from uncertsplat.errors import UserError
from uncertsplat.io.atomic import atomic_write_via

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr")


MAX_PIXELS = 250_000_000
"""Refuse images above this many pixels (250 MP is 3 GB as float RGB): a huge or forged header would
otherwise exhaust memory while decoding instead of giving an error."""

_UNREADABLE_HINT = "Check that the file is a complete PNG, JPEG, TIFF or EXR image (re-export or remove it)."



def _oiio_error(obj=None) -> str:
    """OpenImageIO's pending error message; damaged files can put raw bytes in it, which the binding
    fails to decode (UnicodeDecodeError): then a generic text stands in."""
    try:
        return (obj.geterror() if obj is not None else oiio.geterror()) or ""
    except UnicodeDecodeError:
        return "the decoder reported an unreadable error message"

def _clean_error(text: str) -> str:
    """OIIO repeats its messages; keep the first distinct line."""
    lines = [ln.strip() for ln in (text or "").splitlines() if ln.strip()]
    return lines[0] if lines else "unknown error"


def _nameable(path: Path | str) -> str:
    """``path`` as the text OpenImageIO takes; a name the file system's encoding could not decode (non-ASCII names
    under a C/POSIX locale with Python's UTF-8 mode off) is refused with the fix, not a TypeError from the binding."""
    text = str(path)
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        raise UserError("this path cannot be passed to the image library under the current locale (its name is not "
                        f"valid in the file system encoding {sys.getfilesystemencoding()})", path=path,
                        hint="Run under a UTF-8 locale, e.g. LC_ALL=C.UTF-8, or with PYTHONUTF8=1.") from None
    return text


def _open(path: Path) -> oiio.ImageInput:
    if not path.exists():
        raise UserError("image file not found", path=path, hint="Check the path and the image folder.")
    if path.is_file() and path.stat().st_size == 0:
        raise UserError("image file is empty (0 bytes)", path=path, hint=_UNREADABLE_HINT)
    inp = oiio.ImageInput.open(_nameable(path))
    if inp is None:
        error = _clean_error(_oiio_error())
        if path.is_file() and not os.access(path, os.R_OK):  # (OpenImageIO says "could not open": read as damaged)
            raise UserError("the image cannot be opened: permission denied", path=path,
                            hint="Give yourself read permission (e.g. chmod a+r on the photos), or run as a user "
                                 "who has it.")
        raise UserError(f"cannot read the image ({error})", path=path, hint=_UNREADABLE_HINT)
    return inp


def _oriented_size(spec: oiio.ImageSpec) -> tuple[int, int]:
    orientation = spec.get_int_attribute("Orientation", 1)
    if orientation in (5, 6, 7, 8):  # rotated by 90 degrees: width and height swap when displayed
        return spec.height, spec.width
    return spec.width, spec.height


def decode_error(inp: oiio.ImageInput) -> str | None:
    """None when every pixel of the opened image decodes, else the decoder's message (a truncated JPEG or PNG, say,
    whose header reads well: other programs would fill the missing part with grey or black without a word)."""
    data = inp.read_image("uint8")
    err = _oiio_error(inp)
    if data is None or err:
        return _clean_error(err or _oiio_error())
    return None


def _header(path: Path) -> oiio.ImageSpec:
    """The image's header (a copy: the file is closed)."""
    inp = _open(path)
    try:
        return inp.spec()
    finally:
        inp.close()


# The readers below ignore the EXIF orientation tag by default, as COLMAP and the other tools that give a scene
# its cameras do: a photo's camera describes its pixels as stored. A workspace's photo carrying a tag (COLMAP's
# undistorter keeps it) was read turned against its camera, upside down without a word for tag 3, refused as the
# wrong size for 6 and 8. ``reconstruct`` stages tagged photos with the tag applied and reset, so its workspaces
# read the same either way.
def _orientation(spec: oiio.ImageSpec, exif_orientation: bool) -> int:
    """The EXIF orientation to apply: the tag's with ``exif_orientation``, else 1 (the pixels as stored)."""
    return spec.get_int_attribute("Orientation", 1) if exif_orientation else 1


def read_image_size(path: str | Path, exif_orientation: bool = False) -> tuple[int, int]:
    """(width, height) of an image, reading the header only: as stored (the note above ``_orientation``), or as
    displayed with ``exif_orientation`` (the tag applied)."""
    spec = _header(Path(path))
    return _oriented_size(spec) if exif_orientation else (spec.width, spec.height)


def _reorient(arr: np.ndarray, orientation: int) -> np.ndarray:
    """Apply an EXIF orientation (1..8) to an HWC float32 or uint8 array (kept in its type: the pixels only move),
    using OIIO's own definition of each code."""
    if orientation == 1:
        return arr
    h, w, c = arr.shape
    fmt, dtype = (oiio.UINT8, np.uint8) if arr.dtype == np.uint8 else (oiio.FLOAT, np.float32)
    spec = oiio.ImageSpec(w, h, c, fmt)
    spec.attribute("Orientation", int(orientation))
    buf = oiio.ImageBuf(spec)
    buf.set_pixels(oiio.ROI(0, w, 0, h, 0, 1, 0, c), np.ascontiguousarray(arr, dtype=dtype))
    out = oiio.ImageBufAlgo.reorient(buf)
    return out.get_pixels(fmt).reshape(out.spec().height, out.spec().width, c)


def _alpha_index(spec: oiio.ImageSpec) -> int:
    """The alpha channel's index, -1 for none: the named one, else an unnamed extra channel of a 2/4-channel file."""
    if spec.alpha_channel < 0 and spec.nchannels in (2, 4):
        return spec.nchannels - 1
    return spec.alpha_channel


def _opaque_8bit(spec: oiio.ImageSpec) -> bool:
    """Whether ``read_image`` gives this file's pixels as its 8-bit values / 255 exactly: every channel 8-bit
    unsigned, no alpha to composite (which mixes in the background), one or at least three colour channels."""
    return (str(spec.format) == "uint8" and not list(spec.channelformats) and _alpha_index(spec) < 0
            and (spec.nchannels == 1 or spec.nchannels >= 3))


def has_alpha(path: str | Path) -> bool:
    """Whether the image has an alpha channel (``read_image`` composites it over a background), from the header."""
    return _alpha_index(_header(Path(path))) >= 0


def is_opaque_8bit(path: str | Path) -> bool:
    """Whether ``read_image_8bit`` reads the image (header only): an 8-bit file without alpha."""
    return _opaque_8bit(_header(Path(path)))


def _read_pixels(path: Path, fmt: str, check=None):
    """(the pixels as OpenImageIO gives them in ``fmt``, the file's spec); ``check(spec)`` may refuse the file first.

    Raises:
        UserError: the file is missing, not an image, larger than ``MAX_PIXELS`` or cannot be read, naming it.
    """
    inp = _open(path)
    try:
        spec = inp.spec()
        if check is not None:
            check(spec)
        if spec.width * spec.height > MAX_PIXELS:
            raise UserError(f"the image is {spec.width}x{spec.height} pixels, more than the "
                            f"{MAX_PIXELS / 1e6:.0f} megapixels read at once", path=path,
                            hint="Downscale the photo (or check that its header is not corrupted).")
        data = inp.read_image(fmt)
        err = _oiio_error(inp)
        if data is None or err:
            raise UserError(f"cannot read the image ({_clean_error(err or _oiio_error())}); it may be truncated",
                            path=path, hint=_UNREADABLE_HINT)
    finally:
        inp.close()
    return data, spec


def read_image_8bit(path: str | Path, exif_orientation: bool = False) -> np.ndarray:
    """Read an 8-bit image without alpha (``is_opaque_8bit``) as its stored values: [H,W,3] uint8.

    ``read_image`` of the same file is this times ``types.UINT8_PHOTO_SCALE`` (float32(1/255), OpenImageIO's
    conversion: one multiplication, not a division by 255) in float32, to the bit: the same channels (grey
    replicated, the first three of more) and orientation (``exif_orientation`` as there), at a quarter of the memory.

    Raises:
        UserError: like ``read_image``, naming the file.
        ValueError: the file is not 8-bit or has alpha (``is_opaque_8bit``): read it with ``read_image``.
    """
    path = Path(path)

    def refuse(spec) -> None:
        if not _opaque_8bit(spec):
            raise ValueError(f"{path} is not an 8-bit image without alpha: read it with read_image")

    data, spec = _read_pixels(path, "uint8", check=refuse)
    orientation = _orientation(spec, exif_orientation)
    arr = np.asarray(data, dtype=np.uint8)
    if arr.ndim == 2:
        arr = arr[..., None]
    if arr.ndim == 4:  # volume images: first slice, as read_image
        arr = arr[0]
    rgb = np.repeat(arr, 3, axis=-1) if arr.shape[-1] == 1 else arr[..., :3]
    return np.ascontiguousarray(_reorient(np.ascontiguousarray(rgb), orientation))


_NON_FINITE_SAID: set[str] = set()
"""The files whose non-finite values ``read_image`` has said (once a file and process: a photo is read many times)."""


def _say_non_finite(path: Path, bad: int, total: int) -> None:
    """Say (once per file) that a float image holds NaN or inf values, which are read as 0 (NaN, -inf) and 1 (+inf):
    a renderer's or a denoiser's fault the training and scores would otherwise take in without a word."""
    key = str(path)
    if bad and key not in _NON_FINITE_SAID:
        from uncertsplat.console import console, esc

        _NON_FINITE_SAID.add(key)
        console.print(f"[yellow]warning:[/] {esc(key)} holds {bad:,} NaN or infinite values ({bad / total:.2%} of its "
                      "channel values): read as 0 (NaN, -inf) and 1 (+inf); re-export it if they are not meant")


def read_image(path: str | Path, background: Sequence[float] = (0.0, 0.0, 0.0),
               exif_orientation: bool = False) -> np.ndarray:
    """Read an image as float32 RGB in [0, 1].

    Args:
        path: a PNG (8/16-bit), JPEG, TIFF or EXR file.
        background: RGB colour in [0, 1] under transparent pixels (alpha is composited over it).
        exif_orientation: apply the file's EXIF orientation tag (the image as displayed); by default the pixels
            as stored, as the scene's cameras describe them (the note above ``_orientation``).

    Returns:
        [H,W,3] float32. Grayscale files are replicated to three channels; EXR values are clipped to
        [0, 1].

    Raises:
        UserError: naming the file when it is missing, empty, truncated or not an image.
    """
    path = Path(path)
    data, spec = _read_pixels(path, "float")
    orientation = _orientation(spec, exif_orientation)
    alpha_index = _alpha_index(spec)
    arr = np.asarray(data, dtype=np.float32)
    if arr.ndim == 2:
        arr = arr[..., None]
    if arr.ndim == 4:  # volume images: first slice
        arr = arr[0]
    if spec.format.basetype in (oiio.FLOAT, oiio.HALF, oiio.DOUBLE):  # (integer formats hold no NaN)
        _say_non_finite(path, int(np.count_nonzero(~np.isfinite(arr))), arr.size)
    arr = np.nan_to_num(arr, nan=0.0, posinf=1.0, neginf=0.0)
    c = arr.shape[-1]
    alpha = None
    if 0 <= alpha_index < c:
        alpha = np.clip(arr[..., alpha_index : alpha_index + 1], 0.0, 1.0)
        arr = np.delete(arr, alpha_index, axis=-1)
        c = arr.shape[-1]
    if c == 1:
        rgb = np.repeat(arr, 3, axis=-1)
    elif c >= 3:
        rgb = arr[..., :3]
    else:  # two colour channels without alpha: not a photo layout we know
        raise UserError(f"unsupported channel layout ({c} channels)", path=path,
                        hint="Convert the image to RGB or grayscale.")
    if alpha is not None:
        # OIIO returns associated (premultiplied) colour, so "over" is rgb + bg * (1 - alpha).
        bg = np.asarray(background, dtype=np.float32).reshape(1, 1, 3)
        rgb = rgb + bg * (1.0 - alpha)
    rgb = np.clip(rgb, 0.0, 1.0).astype(np.float32)
    rgb = _reorient(rgb, orientation)
    return np.ascontiguousarray(rgb)


def read_alpha(path: str | Path, exif_orientation: bool = False) -> np.ndarray | None:
    """The alpha channel of an image as [H,W] float32 in [0, 1] (oriented as ``read_image`` with the same
    ``exif_orientation``), or None when the file has no alpha channel (found from the header alone, without decoding
    the pixels).

    Raises:
        UserError: like ``read_image``, naming the file.
    """
    path = Path(path)
    inp = _open(path)
    try:
        spec = inp.spec()
        alpha_index = spec.alpha_channel
        if alpha_index < 0 and spec.nchannels in (2, 4):  # as read_image: an unnamed extra channel is alpha
            alpha_index = spec.nchannels - 1
        if not 0 <= alpha_index < spec.nchannels:
            return None
        if spec.width * spec.height > MAX_PIXELS:
            raise UserError(f"the image is {spec.width}x{spec.height} pixels, more than the "
                            f"{MAX_PIXELS / 1e6:.0f} megapixels read at once", path=path,
                            hint="Downscale the photo (or check that its header is not corrupted).")
        data = inp.read_image(0, 0, alpha_index, alpha_index + 1, "float")
        err = _oiio_error(inp)
        if data is None or err:
            raise UserError(f"cannot read the image ({_clean_error(err or _oiio_error())}); it may be truncated",
                            path=path, hint=_UNREADABLE_HINT)
        orientation = _orientation(spec, exif_orientation)
    finally:
        inp.close()
    arr = np.asarray(data, dtype=np.float32).reshape(spec.height, spec.width, 1)
    arr = np.clip(np.nan_to_num(arr, nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0)
    return np.ascontiguousarray(_reorient(arr, orientation)[..., 0])


def read_mask(path: str | Path) -> np.ndarray:
    """A mask file as [H,W] bool, True where a pixel counts (as stored: no EXIF orientation applied).

    White counts: a value above half the file's range in any colour channel (a palette mask's index colour, green
    or red, counts as white), or, for a mask saved as 0 and 1 (a boolean, as many tools save it), its ones. With an
    alpha channel that is not opaque everywhere, only where alpha is at least 0.5; and where the colour is one value
    wherever alpha is (the mask held in the alpha alone, painted black or white), the alpha alone decides.

    Raises:
        UserError: like ``read_image``, naming the file.
    """
    level = read_image(path).max(axis=-1)  # [H,W] (premultiplied by its alpha: 0 where alpha is 0)
    alpha = read_alpha(path)
    if alpha is not None and not bool((alpha >= 0.5).all()):  # (an alpha opaque everywhere says nothing)
        held = alpha >= 0.5
        shown = level[held]
        if shown.size == 0 or float(shown.max() - shown.min()) < 1.5 / 255.0:
            return held
        level = np.where(held, level / np.maximum(alpha, 0.5), 0.0)  # the colour itself where alpha holds it
    top = float(level.max()) if level.size else 0.0
    cut = 0.0 if 0.0 < top <= 1.5 / 255.0 else 0.5
    return level > cut


# ------------------------------------------------------------------------------------------------ writing
def _atomic_oiio(path: Path, write: Callable[[str], None]) -> Path:
    """Let ``write(tmp_name)`` create the image under a temp name with the same extension, then rename."""
    return atomic_write_via(path, write, what="image")


def _write_array(path: Path, arr: np.ndarray, fmt, channel_names: Sequence[str] | None = None,
                 attributes: dict | None = None) -> Path:
    h, w, c = arr.shape
    spec = oiio.ImageSpec(w, h, c, fmt)
    if channel_names is not None:
        spec.channelnames = tuple(channel_names)
    for k, v in (attributes or {}).items():
        spec.attribute(k, v)

    _nameable(path)

    def write(tmp: str) -> None:
        out = oiio.ImageOutput.create(tmp)
        if out is None or not out.open(tmp, spec):
            raise UserError(f"cannot write the image ({_clean_error(_oiio_error())})", path=path)
        ok = out.write_image(np.ascontiguousarray(arr))
        err = _oiio_error(out)
        out.close()
        if not ok:
            raise UserError(f"cannot write the image ({_clean_error(err)})", path=path,
                            hint="Check free disk space and permissions.")

    return _atomic_oiio(path, write)


PNG_COMPRESSION = 3
"""zlib level of the PNGs we write (lossless at every level; 1-9)."""


def to_uint8(arr: np.ndarray) -> np.ndarray:
    """Float values in [0, 1] as 8-bit (rounded; clipped; NaN as 0), what ``write_png`` stores."""
    return np.round(np.clip(np.nan_to_num(np.asarray(arr, dtype=np.float32), nan=0.0), 0.0, 1.0) * 255.0).astype(
        np.uint8)


def write_png(path: str | Path, arr: np.ndarray) -> Path:
    """Write an 8-bit PNG atomically.

    Args:
        arr: [H,W,3], [H,W,1] or [H,W] float in [0, 1] (rounded to 8 bits) or uint8.
    """
    arr = np.asarray(arr)
    if arr.ndim == 2:
        arr = arr[..., None]
    if arr.ndim != 3 or arr.shape[-1] not in (1, 3, 4):
        raise ValueError(f"write_png expects [H,W,1|3|4], got {arr.shape}")
    if arr.dtype == bool:
        arr = arr.astype(np.uint8) * 255
    elif arr.dtype != np.uint8:
        arr = to_uint8(arr)
    # zlib level 3 instead of the writer's 6: a 320x240 view in 13 ms instead of 29-35 ms, 8 % larger (the synthetic
    # scene writes 80 of them, `evaluate` several per view)
    attrs = {"png:compressionLevel": PNG_COMPRESSION}
    if arr.shape[-1] == 4:  # our RGBA arrays are straight (unassociated) alpha: the writer must not un-premultiply
        attrs["oiio:UnassociatedAlpha"] = 1
    return _write_array(Path(path), arr, oiio.UINT8, attributes=attrs)


def write_exr(path: str | Path, channels: dict[str, np.ndarray], attributes: dict | None = None) -> Path:
    """Write named float32 channels (each [H,W]) to an OpenEXR file atomically (zip compression), with header
    ``attributes`` (name -> str / int / float) beside them."""
    if not channels:
        raise ValueError("write_exr needs at least one channel")
    names = list(channels)
    planes = [np.asarray(channels[n], dtype=np.float32) for n in names]
    shape = planes[0].shape
    if any(p.shape != shape or p.ndim != 2 for p in planes):
        raise ValueError("write_exr channels must all be [H,W] of the same size")
    arr = np.stack(planes, axis=-1)
    return _write_array(Path(path), arr, oiio.FLOAT, channel_names=names,
                        attributes={"compression": "zip", **(attributes or {})})


def read_depth_image(path: str | Path) -> np.ndarray:
    """A depth map stored as an image: [H,W] float32 of a one-channel 16-bit integer (a depth camera's, nerfstudio's
    or TUM RGB-D's PNG, in millimetres or another fixed step; 0 for no depth) or float (TIFF) file, the stored values
    themselves, not scaled to [0, 1]: the unit is fitted or given by ``evaluate --depth-scale``.

    Raises:
        UserError: the file is not one channel (a colour picture of depth cannot be read as depth), or has 8-bit
            values (256 levels: a picture of depth, not its measurement), naming it.
    """
    path = Path(path)

    def refuse(spec) -> None:
        channels = spec.nchannels - (1 if _alpha_index(spec) >= 0 else 0)
        if channels != 1:
            raise UserError(f"the depth map has {spec.nchannels} channels, not one: a colour image (a photo, or a "
                            "colour picture of depth) cannot be read as depth", path=path,
                            hint="Give the depth itself: a one-channel 16-bit PNG (e.g. millimetres), a float TIFF "
                                 "or EXR, or an HxW .npy array.")
        if spec.format.basetype in (oiio.UINT8, oiio.INT8):
            raise UserError("the depth map has 8-bit values (256 levels): a picture of depth, not its measurement",
                            path=path, hint="Give the depth as a 16-bit PNG (e.g. millimetres), a float TIFF or EXR, "
                                            "or an HxW .npy array.")

    # read in its own type: OpenImageIO's conversion of integers to float scales them to [0, 1]
    stored = {oiio.UINT16: "uint16", oiio.INT16: "int16", oiio.UINT32: "uint32", oiio.INT32: "int32"}
    fmt = stored.get(_header(path).format.basetype, "float")
    data, spec = _read_pixels(path, fmt, check=refuse)
    arr = np.asarray(data).astype(np.float32)
    if arr.ndim == 3:
        arr = arr[..., 0]  # (a grey + alpha file: the grey)
    return arr


def read_exr_attribute(path: str | Path, name: str):
    """One header attribute of an image file (``write_exr``'s ``attributes``), or None when it has none."""
    path = Path(path)
    inp = _open(path)
    try:
        return inp.spec().getattribute(name)
    finally:
        inp.close()


def read_exr(path: str | Path) -> dict[str, np.ndarray]:
    """Read every channel of an EXR (or any float image) as {name: [H,W] float32}."""
    path = Path(path)
    inp = _open(path)
    try:
        names = list(inp.spec().channelnames)
        data = inp.read_image("float")
        err = _oiio_error(inp)
    finally:
        inp.close()
    if data is None or err:
        raise UserError(f"cannot read the file ({_clean_error(err)}); it may be truncated", path=path,
                        hint=_UNREADABLE_HINT)
    arr = np.asarray(data, dtype=np.float32)
    if arr.ndim == 2:
        arr = arr[..., None]
    return {n: np.ascontiguousarray(arr[..., i]) for i, n in enumerate(names)}


# ----------------------------------------------------------------------------------------------- resizing
def resize_mask(mask: np.ndarray, width: int, height: int) -> np.ndarray:
    """A validity mask [H,W] or [H,W,1] (bool or 0/1) at ``width`` x ``height``, bool, of the same layout: a resized
    pixel counts only where every source pixel under it does (``resize_image``'s area average is 1 there)."""
    return resize_image(np.asarray(mask, dtype=np.float32), width, height) >= 1.0 - 1e-6


def resize_image(arr: np.ndarray, width: int, height: int) -> np.ndarray:
    """Resize an [H,W,C] (or [H,W]) float array to (width, height).

    Downscaling averages the source area under each target pixel (``area_resize``: no aliasing, and each pixel
    centre where the camera's scaled intrinsics put it); upscaling is bilinear. Returns float32 of the input's
    channel layout.
    """
    import torch
    import torch.nn.functional as F

    arr = np.asarray(arr)
    squeeze = arr.ndim == 2
    a = arr[..., None] if squeeze else arr
    h, w = a.shape[:2]
    if (w, h) == (width, height):
        out = a.astype(np.float32)
    else:
        t = torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32)).permute(2, 0, 1)[None]  # [1,C,H,W]
        if width <= w and height <= h:
            r = area_resize(t, height, width)
        else:
            r = F.interpolate(t, size=(height, width), mode="bilinear", align_corners=False, antialias=False)
        out = r[0].permute(1, 2, 0).numpy()
    out = np.ascontiguousarray(out, dtype=np.float32)
    return out[..., 0] if squeeze else out


def area_resize(images, height: int, width: int):
    """Downscale ``images`` [..., H, W] (a float tensor) to [..., height, width], each target pixel the mean of the
    source area it covers, edge to edge: target pixel j spans source [j H / height, (j + 1) H / height].

    Whole-number ratios are torch's area pooling (the same numbers as before). Other ratios are not: torch's
    adaptive bins span whole source pixels, which moves each target pixel's content by up to half a source pixel,
    in a saw-tooth across the image (802 x 533 to 401 x 266: up to a quarter of a pixel in the rows), while the
    camera's intrinsics scale by the ratio (``Cameras.scaled``). Here each axis is integrated exactly instead: the
    cumulative sum of the rows (float64) read at the fractional edges, where it is linear.
    """
    import torch.nn.functional as F

    H, W = images.shape[-2:]
    if height > H or width > W:
        raise ValueError(f"area_resize only downscales: {W}x{H} -> {width}x{height}")
    if H % height == 0 and W % width == 0:
        lead = images.shape[:-2]
        t = images.reshape(-1, 1, H, W) if images.dim() != 4 else images
        out = F.interpolate(t, size=(height, width), mode="area")
        return out.reshape(*lead, height, width)
    def exact(image):  # both axes, float64
        return _area_axis(_area_axis(image, width, -1), height, -2)

    if images.dim() == 4 and images.shape[0] > 1:  # one image at a time: the float64 sums of a whole batch of
        out = images.new_empty((*images.shape[:2], height, width))  # training photos would be gigabytes
        for i in range(images.shape[0]):
            out[i] = exact(images[i])
        return out
    return exact(images).to(images.dtype)


def _area_axis(t, n: int, dim: int):
    """Exact area means of ``t`` along ``dim`` into ``n`` equal cells (float64)."""
    import torch

    N = t.shape[dim]
    if n == N:
        return t.double()
    shape = list(t.shape)
    shape[dim] = 1
    c = torch.cat([t.new_zeros(shape, dtype=torch.float64), torch.cumsum(t.double(), dim)], dim)  # [.., N+1, ..]
    edges = torch.arange(n + 1, dtype=torch.float64, device=t.device) * (N / n)
    i0 = edges.floor().long().clamp(max=N - 1)
    frac_shape = [1] * t.dim()
    frac_shape[dim] = n + 1
    frac = (edges - i0).reshape(frac_shape)
    lo, hi = c.index_select(dim, i0), c.index_select(dim, i0 + 1)
    area = lo + frac * (hi - lo)  # the integral up to each edge: linear between whole source pixels
    return (area.narrow(dim, 1, n) - area.narrow(dim, 0, n)) * (n / N)
