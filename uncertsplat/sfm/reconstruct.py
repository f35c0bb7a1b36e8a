"""Structure-from-motion with COLMAP (pycolmap 4.2.1): photos to an undistorted PINHOLE workspace.

The steps are plain functions so that each can be tested and timed on its own:

``scan_photos`` (which files, their sizes and EXIF orientation) -> ``stage_inputs`` (rotated copies
where EXIF asks for it) -> ``extract_features`` (SIFT, one camera per image size) -> ``match_features``
(exhaustive or sequential pairs) -> ``map_incremental`` (keep the largest model; run again with other seeds
until two runs agree, ``choose_attempt`` keeps the one that explains the most feature observations; relaxed options
when too few images register) -> ``undistort`` (PINHOLE images into ``WS/images`` and the model into ``WS/sparse/0``).

``uncertsplat.stages.reconstruct.run`` chains them, owns the workspace and writes the report.
This package is the only one that imports pycolmap.
"""

from __future__ import annotations

import contextlib
import hashlib
import math
import os
import re
import shutil
import time
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from uncertsplat.config import ReconstructConfig
from uncertsplat.console import console, list_names
from uncertsplat.errors import UserError
from uncertsplat.io.images import decode_error
from uncertsplat.provenance import file_sha256
from uncertsplat.sfm.align import similarity_align

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".jfif", ".jpe", ".png", ".tif", ".tiff")
"""Accepted photo extensions, compared case-insensitively (IMG_0001.JPG is fine)."""
OTHER_PHOTO_EXTENSIONS = (".heic", ".heif", ".avif", ".webp", ".jxl", ".gif", ".bmp", ".dng", ".cr2", ".cr3",
                          ".nef", ".arw", ".raf", ".orf", ".rw2", ".pef", ".srw")
"""Photo formats (phones' HEIC, camera RAW, web formats) that are not read: named in a note, not silently ignored."""

ProgressFn = Callable[[int, str], None]
"""``advance(n, info)``: n more units done, ``info`` a short status text."""


def _noop(n: int, info: str) -> None:
    return None


# ------------------------------------------------------------------------------------------- logging
@contextlib.contextmanager
def colmap_logging(verbose: bool = False) -> Iterator[None]:
    """Silence COLMAP's glog chatter (hundreds of lines per image) unless ``verbose``.

    Set ``UNCERTSPLAT_COLMAP_LOG=1`` to see COLMAP's own log when diagnosing a failure.
    """
    verbose = verbose or bool(os.environ.get("UNCERTSPLAT_COLMAP_LOG"))
    old = pycolmap.logging.minloglevel
    if not verbose:
        pycolmap.logging.minloglevel = 3  # FATAL only: our own messages explain failures
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = old


# ---------------------------------------------------------------------------------------------- scan
@dataclass(frozen=True)
class PhotoInfo:
    """One input photo: its name (relative to the photo folder), pixel size and EXIF orientation."""

    name: str
    path: Path
    width: int
    height: int
    orientation: int = 1
    """EXIF orientation 1..8 (1: upright). 5..8 swap width and height when applied."""
    alpha: bool = False
    """The file has an alpha channel (COLMAP and training read its colour channels as they are)."""
    gray: bool = False
    """The file has one colour channel (training reads it as R = G = B)."""
    lens: str = ""
    """The EXIF camera, lens and focal length that took it ("" when the file has none): a phone's main and tele
    lenses make photos of one size with different focal lengths (``PhotoScan.camera_groups``)."""

    @property
    def oriented_size(self) -> tuple[int, int]:
        """(width, height) after applying the EXIF orientation."""
        return (self.height, self.width) if self.orientation in (5, 6, 7, 8) else (self.width, self.height)


@dataclass
class PhotoScan:
    """What ``scan_photos`` found in a folder."""

    folder: Path
    photos: list[PhotoInfo]
    ignored: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    _hashes: dict[str, str] | None = field(default=None, repr=False, compare=False)

    @property
    def names(self) -> list[str]:
        return [p.name for p in self.photos]

    def size_groups(self) -> dict[tuple[int, int], list[str]]:
        """(width, height) after orientation -> image names, in name order."""
        groups: dict[tuple[int, int], list[str]] = {}
        for p in self.photos:
            groups.setdefault(p.oriented_size, []).append(p.name)
        return groups

    def camera_groups(self) -> dict[tuple[int, int, str], list[str]]:
        """(width, height, lens) -> image names: the photos that share one COLMAP camera. Photos of one size are
        told apart by their EXIF lens and focal length when they name two or more (a phone's main and tele lens: one
        camera for both made a single focal length between them and a distortion of 0.71, half the field of view);
        photos of that size without EXIF go with the most common lens."""
        by_size: dict[tuple[int, int], list[PhotoInfo]] = {}
        for p in self.photos:
            by_size.setdefault(p.oriented_size, []).append(p)
        groups: dict[tuple[int, int, str], list[str]] = {}
        for (w, h), photos in by_size.items():
            counts: dict[str, int] = {}
            for p in photos:
                if p.lens:
                    counts[p.lens] = counts.get(p.lens, 0) + 1
            common = max(counts, key=lambda k: (counts[k], k)) if len(counts) > 1 else ""
            for p in photos:
                lens = (p.lens or common) if len(counts) > 1 else ""
                groups.setdefault((w, h, lens), []).append(p.name)
        return groups

    def photo_hashes(self) -> dict[str, str]:
        """{name: SHA-256 of the file} of every photo, read once (``fingerprint`` and the report share them)."""
        if self._hashes is None:
            self._hashes = {p.name: file_sha256(p.path) for p in self.photos}
        return dict(self._hashes)

    def fingerprint(self) -> str:
        """Hash of the photos' names and contents: changes when the photos change, not when a copy of the folder
        did not keep the modification times (``cp -r``, a sync, a restore)."""
        hashes = self.photo_hashes()
        h = hashlib.sha256()
        for p in self.photos:
            h.update(f"{p.name}\0{hashes[p.name]}\n".encode())
        return h.hexdigest()[:16]

    def legacy_fingerprint(self) -> str:
        """The hash of names, byte sizes and modification times that workspaces written before 2026-11-29 hold
        (``reconstruct`` still takes them for the same photos)."""
        h = hashlib.sha256()
        for p in self.photos:
            st = p.path.stat()
            h.update(f"{p.name}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
        return h.hexdigest()[:16]


def _lens(spec) -> str:
    """The EXIF camera, lens, focal length and digital zoom of a header ("" when it names none): a phone's digitally
    zoomed photo has the size and the lens of its others and another focal length in pixels."""
    parts = [str(spec.getattribute(k) or "").strip() for k in ("Make", "Model", "Exif:LensModel")]
    focal = spec.getattribute("Exif:FocalLength")
    if isinstance(focal, (int, float)) and focal > 0:
        parts.append(f"{float(focal):g} mm")
    zoom = spec.getattribute("Exif:DigitalZoomRatio")
    if isinstance(zoom, (int, float)) and zoom > 1.001:  # (0 and 1 both mean none)
        parts.append(f"digital zoom {float(zoom):.3g}x")
    return " ".join(p for p in parts if p)


def _read_header(path: Path) -> tuple[int, int, int, bool, bool, str] | str:
    """(width, height, orientation, has alpha, grayscale, lens) from the file header, or the reader's error message.

    Every pixel is decoded too, not only the header: COLMAP reads a truncated JPEG or PNG without a word, filling
    the missing rows with grey or black, and the model would then be trained on them."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        msg = oiio.geterror() or "unknown format"
        return msg.strip().splitlines()[0] if msg.strip() else "cannot be read"
    try:
        spec = inp.spec()
        orientation = int(spec.get_int_attribute("Orientation", 1))
        if spec.width <= 0 or spec.height <= 0:
            return "image has no pixels"
        err = decode_error(inp)
        if err is not None:
            return f"cannot be decoded to the end: {err}; it may be truncated"
        alpha = spec.alpha_channel >= 0 or spec.nchannels in (2, 4)
        gray = spec.nchannels - (1 if alpha else 0) == 1
        return spec.width, spec.height, orientation if 1 <= orientation <= 8 else 1, alpha, gray, _lens(spec)
    finally:
        inp.close()


def scan_photos(folder: str | Path, min_images: int = 3, prefer: set[str] | frozenset[str] = frozenset(),
                masks: Path | None = None) -> PhotoScan:
    """List the photos of ``folder`` (not recursive) and read their headers. ``masks``: the photos' masks folder
    (``reconstruct --masks``), not named among the ignored sub-folders when it lies in ``folder``.

    JPEG, PNG and TIFF files of any extension case are used; sub-folders, hidden files and other
    files are ignored (and named in ``ignored``). Of photos that are copies of each other or share a name stem, one
    is kept: a name in ``prefer`` first (a workspace's photos, when ``reconstruct --extend`` scans the grown folder).

    Raises:
        UserError: the folder is missing or empty, holds fewer than ``min_images`` photos, or some
            photos cannot be read (all of them are named).
    """
    folder = Path(folder)
    if not folder.exists():
        raise UserError("photo folder not found", path=folder, hint="Check the path.")
    if not folder.is_dir():
        raise UserError("expected a folder of photos, got a file", path=folder,
                        hint="Put the photos in a folder and pass the folder.")
    entries = sorted(folder.iterdir(), key=lambda p: p.name)
    ignored: list[str] = []
    notes: list[str] = []
    candidates: list[Path] = []
    subfolders = []
    for entry in entries:
        if entry.name.startswith("."):
            ignored.append(entry.name)  # .DS_Store, ._IMG_0001.JPG (macOS resource forks), ...
        elif entry.is_dir():
            if masks is None or entry.resolve() != Path(masks).resolve():  # (the masks folder: no photos there)
                subfolders.append(entry.name)
                ignored.append(entry.name + "/")
        elif entry.suffix.lower() in IMAGE_EXTENSIONS:
            candidates.append(entry)
        else:
            ignored.append(entry.name)
    if subfolders:
        notes.append(f"sub-folders are not searched: {', '.join(subfolders)} ignored "
                     "(move their photos into the top folder to use them)")
    skipped = [n for n in ignored if not n.startswith(".") and not n.endswith("/")]
    unread = [n for n in skipped if Path(n).suffix.lower() in OTHER_PHOTO_EXTENSIONS]
    if unread:  # a phone's HEIC beside its JPEGs, camera RAW files: photos the user meant to give
        notes.append(f"{len(unread)} photo(s) in a format this tool does not read left out: {list_names(unread)} "
                     "(convert them to JPEG or PNG to use them)")
    if len(skipped) > len(unread):
        notes.append(f"other files ignored: {list_names([n for n in skipped if n not in unread])}")
    if not candidates:
        what = "is empty" if not entries else "holds no JPEG, PNG or TIFF photos"
        # a common slip: pointing at a dataset folder whose photos live in a sub-folder (e.g. images/)
        with_photos = _folders_with_photos(folder)
        hint = (f"Put at least {min_images} overlapping photos ({', '.join(IMAGE_EXTENSIONS)}) "
                "directly in this folder.")
        if unread:
            hint = (f"It holds {len(unread)} photo(s) in a format this tool does not read ({list_names(unread)}): "
                    "convert them to JPEG or PNG.")
        if len(with_photos) == 1:
            hint = f"Its sub-folder {with_photos[0]} holds photos: pass that folder instead."
        elif with_photos:
            hint = (f"Its sub-folders {list_names([str(d) for d in with_photos], 4)} hold photos: pass one of them, "
                    "or move the photos of one scene into one folder and pass that.")
        raise UserError(f"the photo folder {what}", path=folder, hint=hint)
    photos: list[PhotoInfo] = []
    bad: list[str] = []
    with ThreadPoolExecutor(max_workers=min(4, os.cpu_count() or 1)) as pool:
        headers = list(pool.map(_read_header, candidates))
    for path, header in zip(candidates, headers, strict=True):
        if isinstance(header, str):
            if path.is_symlink() and not path.exists():  # (the reader only says it could not open the file)
                header = f"a link to {os.readlink(path)}, which does not exist"
            bad.append(f"{path.name} ({header})")
        else:
            w, h, o, alpha, gray, lens = header
            photos.append(PhotoInfo(path.name, path, w, h, o, alpha, gray, lens))
    if bad:  # before the count: a folder of one good and one broken photo names the broken one
        raise UserError(f"{len(bad)} photo(s) cannot be read: {'; '.join(bad)}", path=folder,
                        hint="Remove or re-export these files (JPEG, PNG or TIFF), then run again.")
    if len(candidates) < min_images:
        raise UserError(f"only {len(candidates)} photo(s) found; structure-from-motion needs at least {min_images}",
                        path=folder, hint="Add more overlapping photos of the scene (20 or more works best).")
    photos = _without_copies(photos, ignored, notes, prefer)
    photos = _one_per_stem(photos, ignored, notes, prefer)
    with_alpha = [p.name for p in photos if p.alpha]
    if with_alpha:
        notes.append(f"{len(with_alpha)} photo(s) have an alpha channel, which is not used: structure-from-motion "
                     f"and training see the colour stored under transparent pixels as it is ({list_names(with_alpha, 8)})")
    gray = [p.name for p in photos if p.gray]
    if gray and len(gray) < len(photos):
        notes.append(f"{len(gray)} photo(s) are grayscale among colour photos: training fits the model's colours to "
                     f"them as grey (R = G = B), which pulls the colour of what they show toward grey; use colour "
                     f"versions or leave them out ({list_names(gray, 8)})")
    if len(photos) < min_images:
        raise UserError(f"only {len(photos)} different photo(s) found; structure-from-motion needs at least "
                        f"{min_images}", path=folder, hint="Add more overlapping photos of the scene.")
    return PhotoScan(folder=folder, photos=photos, ignored=ignored, notes=notes)


def _one_per_stem(photos: list[PhotoInfo], ignored: list[str], notes: list[str],
                  prefer: set[str] | frozenset[str] = frozenset()) -> list[PhotoInfo]:
    """``photos`` with one photo per name stem (one in ``prefer``, else the first by name), the others named in
    ``ignored`` and a note.

    ``IMG_0001.jpg`` beside ``IMG_0001.png`` is most often one shot saved twice; and `evaluate` names a view's
    maps by the stem (``io.maps.map_stem``), so the two would write over each other's.
    """
    order = sorted(photos, key=lambda p: (p.name not in prefer, p.name))
    kept = {p.name for p in _first_of_each(
        order, lambda p: Path(p.name).stem.casefold(), ignored, notes,
        lambda dropped: (f"{len(dropped)} photo(s) share their name with another up to the extension and were left "
                         "out (often one shot saved in two formats; rename one to use both): "
                         + ", ".join(f"{d} (beside {k})" for d, k in sorted(dropped.items()))))}
    return [p for p in photos if p.name in kept]


def _first_of_each(photos: list[PhotoInfo], key: Callable[[PhotoInfo], object], ignored: list[str],
                   notes: list[str], note: Callable[[dict[str, str]], str]) -> list[PhotoInfo]:
    """``photos`` with the first (by name) of those that share a ``key`` (None: unique); each one left out is named
    in ``ignored``, and ``note({left out: the photo kept})`` is added to ``notes``."""
    kept: dict[object, str] = {}
    dropped: dict[str, str] = {}
    for p in photos:
        k = key(p)
        if k is None:
            continue
        if k in kept:
            dropped[p.name] = kept[k]
        else:
            kept[k] = p.name
    if not dropped:
        return photos
    ignored.extend(sorted(dropped))
    notes.append(note(dropped))
    return [p for p in photos if p.name not in dropped]


def _folders_with_photos(folder: Path, depth: int = 2) -> list[Path]:
    """The sub-folders of ``folder`` (down to ``depth`` levels, hidden ones skipped) that hold photos directly."""
    found: list[Path] = []
    level = [folder]
    for _ in range(depth):
        nxt = []
        for d in level:
            try:
                subs = sorted(e for e in d.iterdir() if e.is_dir() and not e.name.startswith("."))
            except OSError:
                continue
            for sub in subs:
                try:
                    if any(p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS for p in sub.iterdir()):
                        found.append(sub)
                except OSError:
                    continue
                nxt.append(sub)
        level = nxt
    return found


def _without_copies(photos: list[PhotoInfo], ignored: list[str], notes: list[str],
                    prefer: set[str] | frozenset[str] = frozenset()) -> list[PhotoInfo]:
    """``photos`` less the byte-for-byte copies of an earlier one (by name), each named in ``ignored`` and a note.

    A copy adds nothing to the reconstruction, and one copy in training with its twin held out would make the
    held-out scores measure memory (a 6-photo case: 22.1 dB held out with copies, 19.4 without).
    """
    size = {p.name: p.path.stat().st_size for p in photos}
    shared = Counter(size.values())
    # of a photo and its copies, the one whose name is no copy's ("IMG_1.jpg" beside "IMG_1 (1).jpg" or "IMG_1
    # copy.jpg", which sort before it by name) is kept, then the first by name
    order = sorted(photos, key=lambda p: (p.name not in prefer, _is_copy_name(Path(p.name).stem), p.name))
    kept = {p.name for p in _first_of_each(
        # a file of a size no other has is no copy: not read
        order, lambda p: file_sha256(p.path) if shared[size[p.name]] > 1 else None, ignored, notes,
        lambda dropped: (f"{len(dropped)} photo(s) are exact copies of another and were left out: "
                         + ", ".join(f"{c} (= {o})" for c, o in sorted(dropped.items()))))}
    return [p for p in photos if p.name in kept]


_COPY_NAME = re.compile(r"(\s*\(\d+\)|[\s_-]*copy(\s*\(?\d+\)?)?)$", re.IGNORECASE)
"""How file managers name a copy: "IMG_1 (1)" (Windows, browsers), "IMG_1 - Copy", "IMG_1 copy 2" (macOS)."""
_COPY_PREFIX = re.compile(r"^copy[\s_-]*(\(\d+\)[\s_-]*)?of[\s_-]+", re.IGNORECASE)
"""And in front of the name: "Copy of IMG_1", "Copy (2) of IMG_1" (older Windows), "copy_of_IMG_1"."""


def _is_copy_name(stem: str) -> bool:
    return _COPY_NAME.search(stem) is not None or _COPY_PREFIX.search(stem) is not None


def stage_inputs(scan: PhotoScan, staging: Path) -> tuple[Path, list[str]]:
    """Return the image folder COLMAP should read, and the names that were rotated.

    COLMAP (pycolmap 4.2.1) ignores EXIF orientation, so a phone photo taken in portrait would be
    read sideways. When any photo carries an orientation other than 1, a staging folder gets rotated
    copies of those photos and links (or copies) of the others; else the photo folder is used as is.
    """
    rotate = [p for p in scan.photos if p.orientation != 1]
    if not rotate:
        return scan.folder, []
    import OpenImageIO as oiio

    if staging.exists():
        shutil.rmtree(staging)
    staging.mkdir(parents=True)
    for p in scan.photos:
        dst = staging / p.name
        if p.orientation == 1:
            try:
                os.symlink(p.path.resolve(), dst)
            except OSError:  # file systems without symlinks
                shutil.copy2(p.path, dst)
            continue
        buf = oiio.ImageBufAlgo.reorient(oiio.ImageBuf(str(p.path)))
        buf.specmod().attribute("Orientation", 1)  # the pixels are upright now
        if p.path.suffix.lower() in (".jpg", ".jpeg"):
            buf.specmod().attribute("Compression", "jpeg:95")
        if not buf.write(str(dst)):
            raise UserError(f"cannot write a rotated copy ({buf.geterror()})", path=dst)
    return staging, [p.name for p in rotate]


def combined_fingerprint(*parts: str) -> str:
    """One fingerprint of several inputs' (the photos', their masks')."""
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()


def stage_masks(scan: PhotoScan, masks: Path, staging: Path) -> list[str]:
    """Write the masks of ``scan``'s photos from the user's folder ``masks`` (``sfm.scene.mask_file``'s names,
    ``io.images.read_mask``'s values) into ``staging`` as COLMAP reads them: ``NAME.png`` (0 or 255) at each photo's
    size as COLMAP reads the photo. A mask is drawn on its photo as stored (as most tools read a photo: without its
    EXIF orientation), and turned as ``stage_inputs`` turns the photo; one whose shape fits only the turned photo is
    taken as drawn on it. A photo without a mask gets a white one (COLMAP skips a photo whose mask is missing).
    Returns the names of the photos without one.

    Raises:
        UserError: a mask of another shape than its photo (either way up), or one that leaves no pixel, naming it.
    """
    from uncertsplat.data.dataset import shape_fits
    from uncertsplat.io.images import _reorient, read_mask, resize_image, write_png
    from uncertsplat.sfm.scene import mask_file

    if staging.exists():
        shutil.rmtree(staging)
    staging.mkdir(parents=True)
    without = []
    for p in scan.photos:
        found = mask_file(masks, p.name)
        w, h = p.oriented_size
        if found is None:
            without.append(p.name)
            valid = np.ones((h, w), dtype=bool)
        else:
            valid = read_mask(found)  # [h,w] as stored
            h_m, w_m = valid.shape
            same = lambda a, b: shape_fits(*b, *a, 1.0 / a[0] + 1.0 / a[1])  # noqa: E731 (b a map of photo a)
            turned_only = p.orientation in (5, 6, 7, 8) and same((w, h), (w_m, h_m)) \
                and not same((p.width, p.height), (w_m, h_m))
            if not same((p.width, p.height), (w_m, h_m)) and not turned_only:
                raise UserError(f"the mask is {w_m}x{h_m}, another shape than its photo {p.name} ({p.width}x"
                                f"{p.height} as stored)", path=found,
                                hint="Give each photo a mask of its own shape (any resolution of it), white where "
                                     "features may be found and the pixels trained on, black where not.")
            if p.orientation != 1 and not turned_only:  # drawn on the photo as stored: turned as COLMAP's copy is
                valid = _reorient(valid[..., None].astype(np.float32), p.orientation)[..., 0] >= 0.5
            valid = resize_image(np.ascontiguousarray(valid[..., None], dtype=np.float32), w, h)[..., 0] >= 0.5
            if not valid.any():
                raise UserError(f"the mask leaves no pixel of its photo {p.name}: it is all black", path=found,
                                hint="White marks the pixels that count; is it inverted, or held in an alpha channel "
                                     "that is 0 everywhere? Give that photo no mask to count every pixel.")
        target = staging / f"{p.name}.png"
        target.parent.mkdir(parents=True, exist_ok=True)
        write_png(target, np.repeat(valid[..., None].astype(np.float32), 3, axis=-1))
    return without


def undistort_masks(distorted_model: Path, model: Path, staged: Path, out: Path,
                    skip: Sequence[str] = ()) -> int:
    """The staged masks (``stage_masks``, of the photos as COLMAP read them) of the images registered in ``model``
    (the undistorted PINHOLE model ``undistort`` wrote), carried to its images: a pixel of an undistorted image counts
    where every mask pixel the undistorter can blend into it counts, so that no counted pixel mixes in what a mask
    left out. COLMAP warps each pixel centre's ray into the photo and interpolates bilinearly (a point whose four
    neighbours are not all inside the photo is left blank); an image less than half the photo's size
    (``max_image_size``) is warped at the photo's size, then filtered down: there every sub-pixel sample of the
    output pixel is tested and the result shrunk by one pixel. Written to ``out/NAME.png`` as ``sfm.scene`` reads a
    workspace's masks, except for the photos in ``skip`` (no mask of their own: every pixel counts); returns how many
    were written."""
    from uncertsplat.io.images import read_image, write_png

    before = pycolmap.Reconstruction(distorted_model)
    after = pycolmap.Reconstruction(model)
    cams_before = {im.name: im.camera for im in before.images.values()}
    if out.exists():
        shutil.rmtree(out)
    skip = set(skip)
    written = 0
    for image in after.images.values():
        src = staged / f"{image.name}.png"
        if image.name in skip or not src.is_file() or image.name not in cams_before:
            continue
        mask = read_image(src)[..., 0] >= 0.5  # [H0,W0] at the photo's size as COLMAP read it
        valid = undistorted_mask(mask, image.camera, cams_before[image.name])
        target = out / f"{image.name}.png"
        target.parent.mkdir(parents=True, exist_ok=True)
        write_png(target, np.repeat(valid[..., None].astype(np.float32), 3, axis=-1))
        written += 1
    return written


def undistorted_mask(mask: np.ndarray, cam, old) -> np.ndarray:
    """[H,W] bool: the pixels of the undistorted camera ``cam`` that ``undistort_masks`` keeps for the photo's
    ``mask`` [H0,W0] bool of the distorted camera ``old`` (pycolmap cameras)."""
    scale = min(cam.width / old.width, cam.height / old.height)
    sub = 1 if scale >= 0.5 else math.ceil(1.0 / scale)  # (pycolmap's direct_warp_min_scale: 0.5)
    valid = _undistorted_valid(mask, cam, old, sub)
    if sub > 1:  # the filter that brings the full-size warp down reaches a pixel beyond each output pixel
        pad = np.pad(valid, 1, constant_values=False)
        valid = np.logical_and.reduce([pad[1 + dy:1 + dy + valid.shape[0], 1 + dx:1 + dx + valid.shape[1]]
                                       for dy in (-1, 0, 1) for dx in (-1, 0, 1)])
    return valid


def _undistorted_valid(mask: np.ndarray, cam, old, sub: int, rows: int = 64) -> np.ndarray:
    """[H,W] bool for ``undistort_masks``: each pixel of ``cam`` (undistorted) whose ``sub`` x ``sub`` samples all map
    into ``old``'s photo (``mask`` [H0,W0], scaled to ``old``'s size) with their four bilinear neighbours inside and
    counted. In blocks of ``rows`` rows (a large image's samples at once held GBs)."""
    h0, w0 = mask.shape
    sx, sy = w0 / old.width, h0 / old.height
    offsets = (np.arange(sub) + 0.5) / sub  # sample positions inside a pixel (0.5: its centre, COLMAP's)
    out = np.zeros((cam.height, cam.width), dtype=bool)
    for r0 in range(0, cam.height, rows):
        r1 = min(r0 + rows, cam.height)
        v, u = np.mgrid[r0:r1, 0:cam.width]
        pu = (u[..., None, None] + offsets[None, None, None, :]).repeat(sub, axis=2)  # [R,W,sub,sub]
        pv = (v[..., None, None] + offsets[None, None, :, None]).repeat(sub, axis=3)
        pix = np.stack([pu.ravel(), pv.ravel()], axis=-1).astype(np.float64)
        xy = cam.cam_from_img(pix)  # [P,2] on the plane z = 1
        uv = old.img_from_cam(np.concatenate([xy, np.ones((len(xy), 1))], axis=-1))  # [P,2] in the photo
        x, y = uv[:, 0] * sx - 0.5, uv[:, 1] * sy - 0.5  # (pixel centres at +0.5)
        finite = np.isfinite(x) & np.isfinite(y)
        x0 = np.floor(np.where(finite, x, -2.0)).astype(np.int64)
        y0 = np.floor(np.where(finite, y, -2.0)).astype(np.int64)
        ok = finite & (x0 >= 0) & (y0 >= 0) & (x0 + 1 < w0) & (y0 + 1 < h0)
        xs, ys = np.clip(x0, 0, w0 - 2), np.clip(y0, 0, h0 - 2)
        ok &= mask[ys, xs] & mask[ys, xs + 1] & mask[ys + 1, xs] & mask[ys + 1, xs + 1]
        out[r0:r1] = ok.reshape(r1 - r0, cam.width, sub * sub).all(-1)
    return out


# ------------------------------------------------------------------------------------------ features
def _chunks(items: Sequence, size: int) -> Iterator[Sequence]:
    for i in range(0, len(items), size):
        yield items[i:i + size]


SIFT_BYTES_PER_PIXEL = 200
"""Feature extraction's memory per thread and pixel of the image it works on (``max_image_size``): 2.4 GB a thread
for photos of 4000x3000 (pycolmap 4, a helper's measurement, 2026-12-01); threads that together asked for more than
the machine had ended the process with a segmentation fault in SIFT, no message."""


def extraction_threads(cfg: ReconstructConfig, sizes: Sequence[tuple[int, int]],
                       available: int | None = None) -> tuple[int, str | None]:
    """The threads feature extraction may run on (``cfg.num_threads``, -1: every core), as many as half the memory
    ``available`` (``io.memory.available_memory`` when None) holds at ``SIFT_BYTES_PER_PIXEL`` for the largest of
    the photos' ``sizes`` (width, height) brought down to ``cfg.max_image_size``; and the note that says so where
    that is fewer (None otherwise)."""
    import os

    from uncertsplat.io.memory import available_memory

    asked = cfg.num_threads if cfg.num_threads > 0 else (os.cpu_count() or 1)
    if not sizes:
        return asked, None
    largest = max(w * h * min(1.0, cfg.max_image_size / max(w, h)) ** 2 for w, h in sizes)
    per_thread = SIFT_BYTES_PER_PIXEL * largest
    available = available_memory() if available is None else available
    if available is None:
        return asked, None
    fit = max(1, int(0.5 * available // per_thread))
    if fit >= asked:
        return asked, None
    return fit, (f"feature extraction on {fit} thread{'s' if fit > 1 else ''} instead of {asked}: each takes about "
                 f"{per_thread / 2**30:.1f} GB at {largest / 1e6:.1f} Mpx (--max-image-size {cfg.max_image_size}) and "
                 f"{available / 2**30:.1f} GB are free (more threads ran out of memory in SIFT)")


def extract_features(
    database: Path,
    image_dir: Path,
    groups: dict[tuple, list[str]],
    cfg: ReconstructConfig,
    advance: ProgressFn = _noop,
    chunk_size: int = 8,
    cameras: dict[tuple, int] | None = None,
    masks: Path | None = None,
) -> dict[str, int]:
    """SIFT features for every image into ``database``; returns name -> number of keypoints. ``masks``: a folder of
    COLMAP-named masks (``stage_masks``): no feature is taken under their black pixels.

    With ``cfg.single_camera`` every group (an image size, and a lens where their EXIF names several:
    ``PhotoScan.camera_groups``) gets one shared camera: pycolmap's SINGLE mode
    would otherwise skip (silently) every image whose size differs from the first. Images are fed
    in chunks so the progress bar moves; later chunks reuse the group's camera. ``cameras``: a group's camera already
    in the database (photos added to a workspace share the camera of their group's photos there).
    """
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = cfg.camera_model
    if masks is not None:
        reader.mask_path = str(masks)
    extraction = pycolmap.FeatureExtractionOptions()
    threads, note = extraction_threads(cfg, [key[:2] for key in groups])
    if note:
        console.print(f"[yellow]note:[/] {note}")
    extraction.num_threads = threads
    extraction.max_image_size = cfg.max_image_size
    if cfg.features == "dsp-sift":
        extraction.sift.estimate_affine_shape = True
        extraction.sift.domain_size_pooling = True
    mode = pycolmap.CameraMode.SINGLE if cfg.single_camera else pycolmap.CameraMode.PER_IMAGE
    for key, names in groups.items():
        camera_id = (cameras or {}).get(key, -1) if cfg.single_camera else -1
        for chunk in _chunks(names, chunk_size):
            reader.existing_camera_id = camera_id
            pycolmap.extract_features(database, image_dir, image_names=list(chunk), camera_mode=mode,
                                      reader_options=reader, extraction_options=extraction,
                                      device=pycolmap.Device.cpu)
            if cfg.single_camera and camera_id == -1:
                with pycolmap.Database.open(database) as db:
                    for img in db.read_all_images():
                        if img.name in chunk:
                            camera_id = img.camera_id
                            break
            advance(len(chunk), "")
    with pycolmap.Database.open(database) as db:
        return {img.name: db.num_keypoints_for_image(img.image_id) for img in db.read_all_images()}


# ------------------------------------------------------------------------------------------ matching
def resolve_matcher(cfg: ReconstructConfig, num_images: int) -> str:
    """auto: exhaustive for small sets, sequential for large (ordered, e.g. video) captures."""
    if cfg.matcher != "auto":
        return cfg.matcher
    return "exhaustive" if num_images <= cfg.exhaustive_max_images else "sequential"


def image_pairs(names: Sequence[str], matcher: str, overlap: int = 10) -> list[tuple[str, str]]:
    """Pairs to match. ``names`` in capture order (sorted by name).

    exhaustive: all pairs. sequential: each image with its ``overlap`` successors, plus successors at
    distances 2^k (k < overlap), as COLMAP's quadratic sequential overlap, to close loops cheaply.
    """
    n = len(names)
    if matcher == "exhaustive":
        return [(names[i], names[j]) for i in range(n) for j in range(i + 1, n)]
    if matcher != "sequential":
        raise ValueError(f"unknown matcher {matcher!r}")
    pairs: set[tuple[int, int]] = set()
    for i in range(n):
        for d in range(1, overlap + 1):
            if i + d < n:
                pairs.add((i, i + d))
        for k in range(overlap):
            d = 2 ** k
            if i + d < n:
                pairs.add((i, i + d))
    return [(names[i], names[j]) for i, j in sorted(pairs)]


def _verification_options(cfg: ReconstructConfig) -> pycolmap.TwoViewGeometryOptions:
    opts = pycolmap.TwoViewGeometryOptions()
    opts.ransac.random_seed = cfg.seed
    return opts


def count_verified_pairs(database: Path) -> int:
    """Image pairs with geometrically verified inlier matches.

    (``Database.num_verified_image_pairs`` also counts pairs whose verification failed.)
    """
    with pycolmap.Database.open(database) as db:
        _, inliers = db.read_two_view_geometry_num_inliers()
    return int(sum(1 for k in inliers if k > 0))


@contextlib.contextmanager
def _names_for_pair_lists(database: Path) -> Iterator[dict[str, str]]:
    """Photo names as an imported pair list may hold them: ``{name: alias}`` for the names with white space.

    COLMAP reads a pair list line by line and splits each at the first space, so a photo named ``IMG 01.jpg``
    would never be matched. Inside this block those images carry an alias in the database (matching reads
    only the database: keypoints, descriptors and cameras, never the image files); on leaving it, even by an
    error, they get their names back.
    """
    with pycolmap.Database.open(database) as db:
        images = db.read_all_images()
        taken = {im.name for im in images}
        aliases: dict[str, str] = {}
        for im in (im for im in images if any(c.isspace() for c in im.name)):
            alias = f"uncertsplat-image-{im.image_id}{Path(im.name).suffix.replace(' ', '')}"
            while alias in taken:
                alias = "_" + alias
            taken.add(alias)
            aliases[im.name] = alias
            im.name = alias
            db.update_image(im)
    try:
        yield aliases
    finally:
        if aliases:
            back = {alias: name for name, alias in aliases.items()}
            with pycolmap.Database.open(database) as db:
                for im in db.read_all_images():
                    if im.name in back:
                        im.name = back[im.name]
                        db.update_image(im)


def match_features(
    database: Path,
    pairs: Sequence[tuple[str, str]],
    cfg: ReconstructConfig,
    scratch: Path,
    advance: ProgressFn = _noop,
    block: int = 200,
) -> int:
    """Match and geometrically verify ``pairs``; returns the number of verified pairs.

    Pairs go to COLMAP in blocks (an imported pair list each) so that progress can be shown.
    """
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = cfg.num_threads
    matching.guided_matching = cfg.guided_matching
    pairing = pycolmap.ImportedPairingOptions()
    scratch.mkdir(parents=True, exist_ok=True)
    pair_file = scratch / "pairs.txt"
    verification = _verification_options(cfg)
    verified = count_verified_pairs(database)
    with _names_for_pair_lists(database) as alias:
        for chunk in _chunks(list(pairs), block):
            pair_file.write_text("".join(f"{alias.get(a, a)} {alias.get(b, b)}\n" for a, b in chunk),
                                 encoding="utf-8")
            pairing.match_list_path = str(pair_file)
            pycolmap.match_image_pairs(database, matching_options=matching, pairing_options=pairing,
                                       verification_options=verification, device=pycolmap.Device.cpu)
            verified = count_verified_pairs(database)
            advance(len(chunk), f"{verified} verified")
    pair_file.unlink(missing_ok=True)
    return verified


# ------------------------------------------------------------------------------------------- mapping
@dataclass
class MappingResult:
    """All models of one mapping run, largest first."""

    models: list[pycolmap.Reconstruction]
    relaxed: bool
    seed: int = 0
    seconds: float = 0.0

    @property
    def best(self) -> pycolmap.Reconstruction | None:
        return self.models[0] if self.models else None

    @property
    def num_registered(self) -> int:
        return self.best.num_reg_images() if self.best is not None else 0


def mapper_options(cfg: ReconstructConfig, relaxed: bool = False,
                   seed: int | None = None) -> pycolmap.IncrementalPipelineOptions:
    """Incremental mapping options; ``relaxed`` lowers the inlier and angle thresholds; ``seed`` (default
    ``cfg.seed``) seeds the mapper's RANSAC and triangulation.

    The relaxed set helps captures with little texture or small baselines, at the risk of admitting
    a wrongly posed image, which is why it is only tried when the normal set registers too few images.
    """
    seed = cfg.seed if seed is None else seed
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = cfg.num_threads
    opts.random_seed = seed
    opts.mapper.random_seed = seed
    opts.triangulation.random_seed = seed
    opts.min_model_size = 3
    if relaxed:
        opts.min_num_matches = 10
        opts.init_num_trials = 400
        opts.mapper.init_min_num_inliers = 50
        opts.mapper.init_min_tri_angle = 8.0
        opts.mapper.abs_pose_min_num_inliers = 15
        opts.mapper.abs_pose_min_inlier_ratio = 0.15
        opts.mapper.max_reg_trials = 5
    return opts


def map_incremental(
    database: Path,
    image_dir: Path,
    scratch: Path,
    cfg: ReconstructConfig,
    relaxed: bool = False,
    advance: ProgressFn = _noop,
    seed: int | None = None,
) -> MappingResult:
    """Incremental mapping (``mapper_options``); every model it finds, largest (most registered images) first."""
    seed = cfg.seed if seed is None else seed
    if scratch.exists():
        shutil.rmtree(scratch)
    scratch.mkdir(parents=True)
    count = [0]

    def on_initial_pair() -> None:
        count[0] += 2
        advance(2, "initial pair")

    def on_next_image() -> None:
        count[0] += 1
        advance(1, "")

    pycolmap.set_random_seed(seed)
    t0 = time.perf_counter()
    models = pycolmap.incremental_mapping(database, image_dir, scratch, mapper_options(cfg, relaxed, seed),
                                          initial_image_pair_callback=on_initial_pair,
                                          next_image_callback=on_next_image)
    ordered = sorted(models.values(), key=lambda r: (-r.num_reg_images(), -r.num_points3D()))
    return MappingResult(models=ordered, relaxed=relaxed, seed=seed, seconds=round(time.perf_counter() - t0, 3))


def map_into(database: Path, image_dir: Path, model_dir: Path, scratch: Path, cfg: ReconstructConfig,
             advance: ProgressFn = _noop, start: pycolmap.Reconstruction | None = None
             ) -> pycolmap.Reconstruction | None:
    """Register the database's images that the model in ``model_dir`` lacks into it: incremental mapping that starts
    from that model with its frames (poses) and cameras (intrinsics) held fixed, so every image already there keeps
    its camera (within rounding, 1e-15 measured) and the new ones are posed in the same frame. ``start``: that model,
    when the caller has read it. Returns the grown model (None: mapping found none), written nowhere."""
    if scratch.exists():
        shutil.rmtree(scratch)
    scratch.mkdir(parents=True)
    start = start if start is not None else pycolmap.Reconstruction(model_dir)
    opts = mapper_options(cfg)
    opts.fix_existing_frames = True
    opts.constant_cameras = set(start.cameras)  # a new camera (another lens) is refined, the ones there are not
    pycolmap.set_random_seed(cfg.seed)
    models = pycolmap.incremental_mapping(database, image_dir, scratch, opts, input_path=model_dir,
                                          next_image_callback=lambda: advance(1, ""))
    known = set(registered_names(start))
    # the model that grew from the given one holds its images (mapping may start further, separate models)
    grown = [m for m in models.values() if known <= set(registered_names(m))]
    return max(grown, key=lambda m: m.num_reg_images()) if grown else None


def read_model(model_dir: Path) -> pycolmap.Reconstruction:
    """The COLMAP model in ``model_dir``."""
    return pycolmap.Reconstruction(Path(model_dir))


def database_cameras(database: Path) -> dict[str, int]:
    """{image name: COLMAP camera id} of every image in ``database``."""
    with pycolmap.Database.open(database) as db:
        return {im.name: im.camera_id for im in db.read_all_images()}


def pose_changes(before: pycolmap.Reconstruction, after: pycolmap.Reconstruction) -> tuple[float, float]:
    """(the largest change of any camera pose matrix entry, of any camera parameter) between the images and cameras
    ``before`` holds and the same ones in ``after``; inf for an image ``after`` lost."""
    poses = {im.name: im.cam_from_world().matrix() for im in after.images.values() if im.has_pose}
    worst = 0.0
    for im in before.images.values():
        if im.has_pose:
            got = poses.get(im.name)
            worst = max(worst, float("inf") if got is None else float(np.abs(got - im.cam_from_world().matrix()).max()))
    params = 0.0
    for cid, cam in before.cameras.items():
        other = after.cameras[cid] if cid in after.cameras else None
        params = max(params, float("inf") if other is None
                     else float(np.abs(np.asarray(other.params) - np.asarray(cam.params)).max()))
    return worst, params


AGREE_OBSERVATIONS = 0.05
"""Two mapping runs agree when their feature observations differ by at most this fraction of the larger count,"""
AGREE_FOCAL = 0.05
"""every camera both estimated has focal lengths within this fraction of each other,"""
AGREE_IMAGES = 0.02
"""and their registered images differ by at most this fraction (at least one image). Runs of the same photos that found
the right geometry differ by a few percent: bonsai's matches mapped with 8 seeds, the 5 runs at the right focal length
within 2.1 % in observations and 4.2 % in focal length (50,491-51,570 observations, 800-834 px, 48-49 images);
runs caught in a wrong focal length explain about half as many observations and spread more among themselves
(24,157-27,236 at 524-537 px; BENCHMARKS.md, "Mapping runs that disagree")."""


def attempts_agree(a: dict, b: dict) -> bool:
    """Whether two mapping runs' summaries (``attempt_summary``) describe the same geometry: registered images within
    ``AGREE_IMAGES``, feature observations within ``AGREE_OBSERVATIONS`` and the focal length of every camera both
    estimated within ``AGREE_FOCAL`` (relative)."""
    if not a["num_observations"] or not b["num_observations"]:
        return False
    if abs(a["num_images"] - b["num_images"]) > max(1.0, AGREE_IMAGES * max(a["num_images"], b["num_images"])):
        return False
    if abs(a["num_observations"] - b["num_observations"]) > AGREE_OBSERVATIONS * max(a["num_observations"],
                                                                                     b["num_observations"]):
        return False
    shared = set(a["focal_lengths"]) & set(b["focal_lengths"])
    return all(abs(a["focal_lengths"][c] - b["focal_lengths"][c])
               <= AGREE_FOCAL * max(a["focal_lengths"][c], b["focal_lengths"][c]) for c in shared)


def agreeing(attempts: Sequence[dict], index: int) -> bool | None:
    """Whether mapping run ``index`` of ``attempts`` (``attempt_summary``) agrees (``attempts_agree``) with another
    run of the same options: ``reconstruct`` stops mapping when the newest one does. None when it is the only run of
    its options."""
    mine = attempts[index]
    others = [a for j, a in enumerate(attempts) if j != index and a["relaxed"] == mine["relaxed"]]
    if not others:
        return None
    return any(attempts_agree(mine, a) for a in others)


def choose_attempt(attempts: Sequence[dict], needed: float) -> int:
    """Index of the mapping run to keep: of the runs that registered at least ``needed`` images (all of them when
    none did), the one whose model explains the most feature observations (the sum of its points' track lengths),
    then the one with more images. Incremental mapping can settle in a wrong focal length and distortion (a local
    minimum of bundle adjustment); such a model keeps fewer observations within the reprojection threshold."""
    enough = [i for i, a in enumerate(attempts) if a["num_images"] >= needed] or list(range(len(attempts)))
    return max(enough, key=lambda i: (attempts[i]["num_observations"], attempts[i]["num_images"], -i))


def attempt_summary(result: MappingResult) -> dict:
    """What ``attempts_agree`` and ``choose_attempt`` compare, of one mapping run's largest model (the fields of
    ``schemas.reconstruct.MappingAttempt``)."""
    best = result.best
    out = {"seed": result.seed, "relaxed": result.relaxed, "num_images": 0, "num_points3d": 0, "num_observations": 0,
           "mean_reprojection_error": None, "focal_lengths": {}, "seconds": result.seconds}
    if best is None:
        return out
    used = {best.image(i).camera_id for i in best.reg_image_ids()}
    out.update(num_images=int(best.num_reg_images()), num_points3d=int(best.num_points3D()),
               num_observations=int(best.compute_num_observations()),
               mean_reprojection_error=float(best.compute_mean_reprojection_error()) if best.num_points3D() else None,
               focal_lengths={str(c): float(cam.mean_focal_length()) for c, cam in best.cameras.items() if c in used})
    return out


def registered_names(rec: pycolmap.Reconstruction) -> list[str]:
    return sorted(rec.image(i).name for i in rec.reg_image_ids())


def model_stats(rec: pycolmap.Reconstruction) -> dict:
    """Health numbers of one model (reprojection error in pixels of the distorted images)."""
    return {
        "num_points3d": int(rec.num_points3D()),
        "num_observations": int(rec.compute_num_observations()),
        "mean_reprojection_error": float(rec.compute_mean_reprojection_error()) if rec.num_points3D() else None,
        "mean_track_length": float(rec.compute_mean_track_length()) if rec.num_points3D() else None,
        "mean_observations_per_image": float(rec.compute_mean_observations_per_reg_image())
        if rec.num_reg_images() else None,
    }


WEAK_FRACTION = 0.2  # a photo with fewer than this fraction of the median photo's observations is named


def weakly_registered(rec: pycolmap.Reconstruction, fraction: float = WEAK_FRACTION) -> dict[str, int]:
    """Registered photos whose pose rests on fewer than ``fraction`` of the median photo's feature observations
    (name -> observations), fewest first. bonsai with SIFT: DSCF5763.JPG from 32 points where the median photo has
    753 (BENCHMARKS.md, "Features for photos far apart")."""
    counts = {rec.image(i).name: int(rec.image(i).num_points3D) for i in rec.reg_image_ids()}
    if len(counts) < 3:
        return {}
    median = float(np.median(list(counts.values())))
    return dict(sorted(((n, c) for n, c in counts.items() if c < fraction * median), key=lambda kv: (kv[1], kv[0])))


FAR_REGISTRATION = 10.0
"""``far_weak_registrations``: a weakly registered photo whose camera lies more than this many times the median
photo's distance from the cameras' median centre is taken for a wrong pose."""


def far_weak_registrations(rec: pycolmap.Reconstruction, weak: dict[str, int]) -> dict[str, float]:
    """Of the weakly registered photos ``weak`` (``weakly_registered``), those whose camera lies more than
    ``FAR_REGISTRATION`` times the median photo's distance from the median camera centre (name -> that ratio): a pose
    resting on a few points, far outside the capture, is not where the photo was taken (a helper's mirrored copy of a
    fern photo: 13 points, 60 units out where every other camera lies within 5, facing away; trained on, it grew a
    ghost scene and its distance shrank the run's frame 12x). Needs at least 5 registered photos."""
    ids = list(rec.reg_image_ids())
    if len(ids) < 5 or not weak:
        return {}
    centres = {rec.image(i).name: np.asarray(rec.image(i).projection_center(), dtype=np.float64) for i in ids}
    middle = np.median(np.stack(list(centres.values())), axis=0)
    dist = {n: float(np.linalg.norm(c - middle)) for n, c in centres.items()}
    typical = float(np.median(list(dist.values())))
    if not typical > 0:
        return {}
    return {n: dist[n] / typical for n in weak if n in dist and dist[n] > FAR_REGISTRATION * typical}


FOCAL_OUTLIER = 0.03
"""``focal_outliers``: a photo whose own focal length lies more than this (in log, about 3 %) from the median of the
photos sharing its camera is named, when that is also beyond ``FOCAL_OUTLIER_SPREAD`` robust deviations."""
FOCAL_OUTLIER_SPREAD = 6.0
FOCAL_MIN_POINTS = 30
"""``focal_outliers`` estimates a photo's own focal length only from at least this many of its points."""


def focal_outliers(rec: pycolmap.Reconstruction) -> dict[str, float]:
    """Photos that do not fit the camera they share (name -> the ratio of their own focal length to the shared one):
    for each camera of three or more registered photos, each photo's pose and focal length are estimated again from
    its own 2D-3D matches alone (P4Pf in LO-RANSAC, then refined); a photo whose focal length stands apart from the
    others' (``FOCAL_OUTLIER``, ``FOCAL_OUTLIER_SPREAD``) is a crop saved at full size, a digital zoom or another
    camera of the same image size. One such photo of 20 (fern at 200 px, a 1.5x crop) moved the shared focal length
    of every photo from 156 to 200 px; of 49 (bonsai at 400 px, a 1.25x crop) from 395 to 471. The ratio it gets
    here is smaller than the crop's (1.08 for both): the model has bent around it, while the others' stay within 1 %
    of 1 (on those scenes uncropped: at most 1.1 % from their median)."""
    by_camera: dict[int, list] = {}
    for i in rec.reg_image_ids():
        image = rec.image(i)
        by_camera.setdefault(image.camera_id, []).append(image)
    estimation = pycolmap.AbsolutePoseEstimationOptions()
    estimation.estimate_focal_length = True
    refinement = pycolmap.AbsolutePoseRefinementOptions()
    refinement.refine_focal_length = True
    refinement.refine_extra_params = False
    out: dict[str, float] = {}
    for camera_id, images in by_camera.items():
        if len(images) < 3:
            continue
        shared = rec.cameras[camera_id]
        logs: dict[str, float] = {}
        for image in images:
            seen = [p for p in image.points2D if p.has_point3D()]
            if len(seen) < FOCAL_MIN_POINTS:
                continue
            xy = np.array([p.xy for p in seen], dtype=np.float64)
            xyz = np.array([rec.points3D[p.point3D_id].xyz for p in seen], dtype=np.float64)
            own = pycolmap.Camera(model=shared.model, width=shared.width, height=shared.height,
                                  params=shared.params.copy())
            if pycolmap.estimate_and_refine_absolute_pose(xy, xyz, own, estimation, refinement) is None:
                continue
            if own.mean_focal_length() > 0:
                logs[image.name] = float(np.log(own.mean_focal_length() / shared.mean_focal_length()))
        if len(logs) < 3:
            continue
        values = np.array(list(logs.values()))
        middle = float(np.median(values))
        spread = 1.4826 * float(np.median(np.abs(values - middle)))
        for name, value in logs.items():
            if abs(value - middle) > max(FOCAL_OUTLIER, FOCAL_OUTLIER_SPREAD * spread):
                out[name] = float(np.exp(value - middle))
    return dict(sorted(out.items()))


def own_cameras(database: Path, names: Sequence[str]) -> None:
    """Give each of the photos ``names`` a camera of its own in ``database`` (a copy of the one it shared, on a rig
    of its own), so that the next mapping estimates its focal length apart from the others'."""
    with pycolmap.Database.open(database) as db:
        for name in names:
            image = db.read_image_with_name(name)
            shared = db.read_camera(image.camera_id)
            camera = pycolmap.Camera(model=shared.model, width=shared.width, height=shared.height,
                                     params=shared.params.copy(), has_prior_focal_length=shared.has_prior_focal_length)
            camera.camera_id = db.write_camera(camera)
            rig = pycolmap.Rig()
            rig.add_ref_sensor(camera.sensor_id)
            frame = db.read_frame(image.frame_id)
            frame.rig_id = db.write_rig(rig)
            image.camera_id = camera.camera_id
            frame.clear_data_ids()
            frame.add_data_id(image.data_id)
            db.update_frame(frame)
            db.update_image(image)


def leave_out(rec: pycolmap.Reconstruction, names: Sequence[str]) -> None:
    """Deregister the photos ``names`` from ``rec`` (their frames; their observations go with them)."""
    wanted = set(names)
    for i in list(rec.reg_image_ids()):
        image = rec.image(i)
        if image.name in wanted:
            rec.deregister_frame(image.frame_id)


def camera_summaries(rec: pycolmap.Reconstruction) -> list[dict]:
    counts: dict[int, int] = {}
    for i in rec.reg_image_ids():
        cid = rec.image(i).camera_id
        counts[cid] = counts.get(cid, 0) + 1
    out = []
    for cid, cam in sorted(rec.cameras.items()):
        out.append({"camera_id": int(cid), "model": cam.model_name, "width": int(cam.width),
                    "height": int(cam.height), "params": [float(v) for v in cam.params],
                    "num_images": counts.get(cid, 0)})
    return out


# --------------------------------------------------------------------------------------- undistortion
def undistort(model_dir: Path, image_dir: Path, workspace: Path, cfg: ReconstructConfig) -> dict[str, list[int]]:
    """Undistort the registered images to PINHOLE into ``WS/images`` and the model into ``WS/sparse/0``.

    pycolmap writes ``sparse/*.bin`` without the ``0/`` level (and a ``stereo/`` folder and scripts
    we do not need): it writes into a scratch folder, and we move the parts into place.
    Returns image name -> [width, height] of the undistorted image.
    """
    tmp = workspace / ".undistort_tmp"
    if tmp.exists():
        shutil.rmtree(tmp)
    options = pycolmap.UndistortCameraOptions()
    options.max_image_size = cfg.max_image_size
    pycolmap.undistort_images(tmp, model_dir, image_dir, output_type="COLMAP", undistort_options=options,
                              num_threads=cfg.num_threads)
    for name in ("images", "sparse"):
        target = workspace / name
        if target.exists():
            shutil.rmtree(target)
    (tmp / "images").rename(workspace / "images")
    sparse0 = workspace / "sparse" / "0"
    sparse0.mkdir(parents=True)
    for f in (tmp / "sparse").iterdir():
        f.rename(sparse0 / f.name)
    shutil.rmtree(tmp)
    rec = pycolmap.Reconstruction(sparse0)
    return {rec.image(i).name: [int(rec.image(i).camera.width), int(rec.image(i).camera.height)]
            for i in rec.reg_image_ids()}


# -------------------------------------------------------------------------------------------- misc
def set_seed(seed: int) -> None:
    """Seed COLMAP's global PRNG (RANSAC, initial pair sampling)."""
    pycolmap.set_random_seed(seed)


def versions() -> tuple[str, str]:
    """(pycolmap version, COLMAP build string)."""
    return pycolmap.__version__, str(pycolmap.COLMAP_version)


class Stopwatch:
    """Seconds per named stage."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}

    @contextlib.contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] = round(self.seconds.get(name, 0.0) + time.perf_counter() - t0, 3)


def camera_centers(rec_dir: str | Path) -> dict[str, np.ndarray]:
    """Image name -> camera centre [3] in world coordinates, from a COLMAP model folder."""
    rec = pycolmap.Reconstruction(Path(rec_dir))
    return {rec.image(i).name: np.asarray(rec.image(i).projection_center(), dtype=np.float64)
            for i in rec.reg_image_ids()}


def pose_accuracy(model_dir: str | Path, reference_dir: str | Path) -> dict[str, float | int]:
    """How far the cameras of a COLMAP model are from reference cameras (e.g. a synthetic scene's GT).

    Images are matched by name; the model is aligned to the reference by a similarity (Umeyama) on the
    camera centres, its rotation from the cameras' own rotations where the centres lie on a line (a straight drive:
    the rotation about the line is not fixed by them, and the comparison reported 94 degrees for cameras 0.06 off).
    Returns the number of matched images, the mean and max centre error in % of the
    reference radius (largest distance of a centre from their mean), the mean and max rotation error in
    degrees and the mean relative focal-length error in %.
    """
    rec, ref = pycolmap.Reconstruction(Path(model_dir)), pycolmap.Reconstruction(Path(reference_dir))

    def poses(r):
        out = {}
        for i in r.reg_image_ids():
            im = r.image(i)
            cam = r.camera(im.camera_id)
            out[im.name] = (np.asarray(im.projection_center(), dtype=np.float64),
                            np.asarray(im.cam_from_world().rotation.matrix(), dtype=np.float64),
                            float(np.mean([cam.focal_length_x, cam.focal_length_y])))
        return out

    a, b = poses(rec), poses(ref)
    names = sorted(set(a) & set(b))
    if len(names) < 3:
        raise ValueError(f"only {len(names)} images in common with the reference cameras")
    src = np.stack([a[n][0] for n in names])
    dst = np.stack([b[n][0] for n in names])
    s, rot, t = align_cameras(src, dst, [a[n][1] for n in names], [b[n][1] for n in names])
    radius = float(np.linalg.norm(dst - dst.mean(0), axis=1).max())
    centre = np.linalg.norm((s * (rot @ src.T)).T + t - dst, axis=1) / radius * 100.0
    # cam_from_ref = cam_from_model @ model_from_ref, and model_from_ref's rotation is rot^T
    angles = [np.degrees(np.arccos(np.clip((np.trace(a[n][1] @ rot.T @ b[n][1].T) - 1.0) / 2.0, -1.0, 1.0)))
              for n in names]
    focal = [abs(a[n][2] / b[n][2] - 1.0) * 100.0 for n in names]
    return {"num_images": len(names), "centre_error_mean_pct": float(centre.mean()),
            "centre_error_max_pct": float(centre.max()), "rotation_error_mean_deg": float(np.mean(angles)),
            "rotation_error_max_deg": float(np.max(angles)), "focal_error_mean_pct": float(np.mean(focal))}


def align_cameras(src: np.ndarray, dst: np.ndarray, model_rots: list, ref_rots: list) -> tuple[float, np.ndarray,
                                                                                                np.ndarray]:
    """The similarity ``dst ~ s * R @ src + t`` that takes a model's cameras (centres ``src`` [N,3], rotations
    ``model_rots``: cam_from_model) onto reference ones (``dst``, ``ref_rots``): Umeyama on the centres, but the
    rotation from the cameras' own rotations where the centres lie (nearly) on a line, across it less than 2 % of
    their extent along it: the rotation about the line is then left to the centres' noise."""
    def flatness(x):  # the centres' extent across their main axis, relative to along it
        spread = np.linalg.svd(x - x.mean(0), compute_uv=False)  # [3]
        return spread[1] / max(spread[0], 1e-300)

    if min(flatness(src), flatness(dst)) < 0.02:
        return _align_by_rotations(model_rots, ref_rots, src, dst)
    return similarity_align(src, dst)


def _align_by_rotations(model_rots: list, ref_rots: list, src: np.ndarray,
                        dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """The similarity ``dst ~ s * R @ src + t`` whose rotation is the mean of what each camera's pair of rotations
    (cam_from_model, cam_from_ref) gives, projected onto SO(3); scale and shift by least squares on the centres."""
    m = sum(r_ref.T @ r_model for r_model, r_ref in zip(model_rots, ref_rots, strict=True))
    u, _, vt = np.linalg.svd(m)
    rot = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
    xs, xd = src - src.mean(0), dst - dst.mean(0)
    scale = float((xd * (xs @ rot.T)).sum() / max((xs ** 2).sum(), 1e-300))
    return scale, rot, dst.mean(0) - scale * rot @ src.mean(0)
