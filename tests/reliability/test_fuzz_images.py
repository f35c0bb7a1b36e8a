"""Property-based fuzzing of image files: damaged, odd and forged images end in an image or a clear error.

Kinds tried: 8/16-bit PNG, grayscale, grayscale+alpha, RGBA, 1x1, JPEG, 16-bit and float TIFF, EXR; damaged by
truncation, bit flips, emptying, a wrong extension, text content, and forged headers declaring huge sizes.
``read_image`` must return [H,W,3] float32 in [0, 1] (finite) or raise ``UserError`` naming the file,
within a deadline (no hang, no memory blow-up).
"""

from __future__ import annotations

import shutil
import struct
import tempfile
import zlib
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.fixtures import tiny_scene_path  # noqa: F401
from uncertsplat.errors import UserError
from uncertsplat.io import images
from uncertsplat.io.images import read_image, read_image_size


def _png_bytes(w: int, h: int, bitdepth: int = 8, color: int = 2, raw: bytes = b"") -> bytes:
    """A PNG whose header declares w x h (valid CRCs), with whatever (small) pixel data."""
    def chunk(t, d):
        return struct.pack(">I", len(d)) + t + d + struct.pack(">I", zlib.crc32(t + d) & 0xFFFFFFFF)

    ihdr = struct.pack(">IIBBBBB", w, h, bitdepth, color, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(raw or b"\0" * 64))
            + chunk(b"IEND", b""))


def _oiio_write(path: Path, arr: np.ndarray, fmt) -> None:
    h, w, c = arr.shape
    out = oiio.ImageOutput.create(str(path))
    assert out is not None and out.open(str(path), oiio.ImageSpec(w, h, c, fmt)), oiio.geterror()
    assert out.write_image(np.ascontiguousarray(arr))
    out.close()


@pytest.fixture(scope="module")
def samples(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("images")
    rng = np.random.default_rng(0)
    rgb = rng.random((24, 32, 3)).astype(np.float32)
    made = {
        "png8.png": (rgb, oiio.UINT8), "png16.png": (rgb, oiio.UINT16), "gray.png": (rgb[..., :1], oiio.UINT8),
        "gray_alpha.png": (rgb[..., :2], oiio.UINT8), "rgba.png": (np.concatenate([rgb, rgb[..., :1]], -1), oiio.UINT8),
        "one.png": (rgb[:1, :1], oiio.UINT8), "photo.jpg": (rgb, oiio.UINT8), "tiff16.tif": (rgb, oiio.UINT16),
        "float.tif": (rgb * 3 - 1, oiio.FLOAT), "map.exr": (rgb, oiio.HALF),
    }
    out = {}
    for name, (arr, fmt) in made.items():
        _oiio_write(d / name, arr, fmt)
        out[name] = d / name
    (d / "huge.png").write_bytes(_png_bytes(100_000, 100_000))
    (d / "wide.png").write_bytes(_png_bytes(2**31 - 1, 1))
    (d / "big_forged.png").write_bytes(_png_bytes(30_000, 30_000))
    (d / "text.png").write_text("this is not an image\n")
    (d / "empty.jpg").write_bytes(b"")
    for n in ("huge.png", "wide.png", "big_forged.png", "text.png", "empty.jpg"):
        out[n] = d / n
    return out


def _assert_image_or_clear_error(path: Path) -> str:
    try:
        arr = read_image(path)
    except UserError as err:
        assert str(path) in str(err), str(err)
        return "error"
    assert arr.dtype == np.float32 and arr.ndim == 3 and arr.shape[2] == 3
    assert np.isfinite(arr).all() and arr.min() >= 0.0 and arr.max() <= 1.0
    try:
        w, h = read_image_size(path)
        assert (h, w) == arr.shape[:2]
    except UserError as err:
        assert str(path) in str(err)
    return "image"


def test_every_sample_kind_reads_or_fails_clearly(samples):
    results = {name: _assert_image_or_clear_error(p) for name, p in samples.items()}
    good = ["png8.png", "png16.png", "gray.png", "gray_alpha.png", "rgba.png", "one.png", "photo.jpg",
            "tiff16.tif", "float.tif", "map.exr"]
    assert all(results[n] == "image" for n in good), results
    assert all(results[n] == "error" for n in results if n not in good), results
    assert read_image(samples["one.png"]).shape == (1, 1, 3)


@settings(max_examples=150, deadline=3000, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_damaged_images_read_or_fail_clearly(samples, data):
    name = data.draw(st.sampled_from(sorted(samples)))
    raw = bytearray(samples[name].read_bytes())
    kind = data.draw(st.sampled_from(["truncate", "flip", "flips", "zero", "ext", "ext+truncate"]))
    ext = Path(name).suffix
    if kind in ("truncate", "ext+truncate") and raw:
        raw = raw[: data.draw(st.integers(0, len(raw) - 1))]
    elif kind in ("flip", "flips") and raw:
        for _ in range(1 if kind == "flip" else data.draw(st.integers(2, 16))):
            i = data.draw(st.integers(0, len(raw) - 1))
            raw[i] ^= 1 << data.draw(st.integers(0, 7))
    elif kind == "zero":
        raw = bytearray()
    if kind.startswith("ext"):
        ext = data.draw(st.sampled_from([".png", ".jpg", ".tif", ".exr", ".JPG", ".txt"]))
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / f"img {kind}{ext}"
        p.write_bytes(bytes(raw))
        _assert_image_or_clear_error(p)


def test_pixel_limit_guards_memory(samples, monkeypatch):
    monkeypatch.setattr(images, "MAX_PIXELS", 100)
    with pytest.raises(UserError, match="32x24 pixels") as err:
        read_image(samples["png8.png"])
    assert str(samples["png8.png"]) in str(err.value)


def test_a_damaged_image_in_a_scene_fails_the_cli_clearly(tiny_scene_path, tmp_path):
    """End to end: a truncated training image stops `train` with exit 2 naming the file."""
    from tests.reliability.helpers import FAST, assert_clean_error, run_cli

    scene = tmp_path / "scene"
    shutil.copytree(tiny_scene_path, scene)
    victim = sorted((scene / "images").iterdir())[5]
    victim.write_bytes(victim.read_bytes()[:200])
    res = run_cli("train", scene, "-o", tmp_path / "run", *FAST, "--set", "iterations=2")
    assert_clean_error(res.returncode, res.stderr, victim.name)
    assert not (tmp_path / "run" / "ckpts").exists()
