"""Image I/O through OpenImageIO: bit depths, channel layouts, orientation, broken files, atomic writes."""

from __future__ import annotations

import numpy as np
import OpenImageIO as oiio
import pytest
import torch

from uncertsplat.errors import UserError
from uncertsplat.io.images import (
    read_exr,
    read_exr_attribute,
    read_image,
    read_image_size,
    resize_image,
    write_exr,
    write_png,
)


def _raw_write(path, arr, fmt, attrs=None):
    """Write pixels with OIIO directly (a stand-in for files made by other programs)."""
    h, w, c = arr.shape
    spec = oiio.ImageSpec(w, h, c, fmt)
    for k, v in (attrs or {}).items():
        spec.attribute(k, v)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec)
    assert out.write_image(np.ascontiguousarray(arr))
    out.close()


@pytest.fixture
def rng():
    return np.random.default_rng(0)


def test_png8_roundtrip(tmp_path, rng):
    a = rng.random((12, 17, 3), dtype=np.float32)
    write_png(tmp_path / "a.png", a)
    b = read_image(tmp_path / "a.png")
    assert b.shape == (12, 17, 3) and b.dtype == np.float32
    assert np.abs(a - b).max() <= 0.5 / 255 + 1e-6
    assert read_image_size(tmp_path / "a.png") == (17, 12)


def test_png16_keeps_16_bit_precision(tmp_path, rng):
    a16 = rng.integers(0, 65536, size=(9, 11, 3), dtype=np.uint16)
    _raw_write(tmp_path / "a16.png", a16, oiio.UINT16)
    b = read_image(tmp_path / "a16.png")
    np.testing.assert_allclose(b, a16.astype(np.float32) / 65535.0, atol=1e-6)


def test_grayscale_becomes_rgb(tmp_path, rng):
    g = rng.integers(0, 256, size=(8, 10, 1), dtype=np.uint8)
    _raw_write(tmp_path / "g.png", g, oiio.UINT8)
    b = read_image(tmp_path / "g.png")
    assert b.shape == (8, 10, 3)
    for c in range(3):
        np.testing.assert_allclose(b[..., c], g[..., 0] / 255.0, atol=1e-6)


@pytest.mark.parametrize("bg", [(0.0, 0.0, 0.0), (1.0, 0.5, 0.25)])
def test_rgba_composited_over_background(tmp_path, rng, bg):
    rgb = rng.integers(0, 256, size=(6, 7, 3), dtype=np.uint8)
    alpha = np.full((6, 7, 1), 255, np.uint8)
    alpha[:3] = 0
    alpha[3:, :3] = 128
    write_png(tmp_path / "rgba.png", np.concatenate([rgb, alpha], -1))
    b = read_image(tmp_path / "rgba.png", background=bg)
    a = alpha.astype(np.float32) / 255.0
    expect = rgb / 255.0 * a + np.asarray(bg, np.float32) * (1 - a)
    np.testing.assert_allclose(b, expect, atol=2.5 / 255)
    np.testing.assert_allclose(b[0, 0], bg, atol=1e-6)  # fully transparent pixel = background


@pytest.mark.parametrize("suffix", ["jpg", "png"])
def test_exif_orientation_is_applied_only_when_asked(tmp_path, suffix):
    """By default the pixels as stored, as COLMAP reads them (a workspace photo with a tag was read turned against its
    camera); ``exif_orientation=True`` gives the photo as displayed."""
    from uncertsplat.io.images import read_alpha, read_image_8bit

    a = np.zeros((20, 40, 3), np.uint8)  # landscape, bright left half
    a[:, :20] = 255
    path = tmp_path / f"o.{suffix}"
    _raw_write(path, a, oiio.UINT8, {"Orientation": 6})  # "rotate 90 CW to display"
    assert read_image_size(path) == (40, 20) and read_image(path).shape == (20, 40, 3)
    np.testing.assert_allclose(read_image(path), a / 255.0, atol=0.02)  # (JPEG's rounding)
    assert np.array_equal(read_image_8bit(path), np.round(read_image(path) * 255).astype(np.uint8))
    assert read_image_size(path, exif_orientation=True) == (20, 40)
    b = read_image(path, exif_orientation=True)
    assert b.shape == (40, 20, 3) and read_image_8bit(path, exif_orientation=True).shape == (40, 20, 3)
    # rotated clockwise, the bright left half becomes the top half
    assert b[:15].mean() > 0.9 and b[25:].mean() < 0.1
    rgba = np.concatenate([a, np.full((20, 40, 1), 255, np.uint8)], -1)
    _raw_write(tmp_path / "a.png", rgba, oiio.UINT8, {"Orientation": 6})
    assert read_alpha(tmp_path / "a.png").shape == (20, 40)
    assert read_alpha(tmp_path / "a.png", exif_orientation=True).shape == (40, 20)


def test_tiff_and_exr_read(tmp_path, rng):
    a = rng.random((5, 6, 3), dtype=np.float32)
    _raw_write(tmp_path / "a.tif", (a * 65535).round().astype(np.uint16), oiio.UINT16)
    np.testing.assert_allclose(read_image(tmp_path / "a.tif"), a, atol=1e-4)
    _raw_write(tmp_path / "a.exr", a, oiio.FLOAT)
    np.testing.assert_allclose(read_image(tmp_path / "a.exr"), a, atol=1e-6)


def test_an_exr_photo_with_nan_or_inf_is_said_once(tmp_path, rng, capsys):
    """NaN and inf values of a float photo were read as 0 and 1 without a word (a renderer's or denoiser's fault the
    training would take in): said once a file, read as before."""
    a = rng.random((5, 6, 3), dtype=np.float32)
    a[0, 0, 0], a[1, 1, 1], a[2, 2, 2] = np.nan, np.inf, -np.inf
    _raw_write(tmp_path / "bad.exr", a, oiio.FLOAT)
    got = read_image(tmp_path / "bad.exr")
    assert (got[0, 0, 0], got[1, 1, 1], got[2, 2, 2]) == (0.0, 1.0, 0.0)
    read_image(tmp_path / "bad.exr")
    said = " ".join(capsys.readouterr().err.split())
    assert said.count("holds 3 NaN or infinite values") == 1 and "bad.exr" in said
    _raw_write(tmp_path / "good.exr", rng.random((5, 6, 3), dtype=np.float32), oiio.FLOAT)
    read_image(tmp_path / "good.exr")
    assert "NaN" not in capsys.readouterr().err


def test_exr_named_channels_roundtrip(tmp_path, rng):
    ch = {"depth_mean": rng.random((4, 5), dtype=np.float32), "depth_std": rng.random((4, 5), dtype=np.float32)}
    write_exr(tmp_path / "m.exr", ch)
    back = read_exr(tmp_path / "m.exr")
    assert set(back) == set(ch)
    for k in ch:
        np.testing.assert_array_equal(back[k], ch[k])


def test_exr_header_attributes_roundtrip(tmp_path, rng):
    """``write_exr``'s attributes read back by name (a float, a string); a name never written is None."""
    write_exr(tmp_path / "a.exr", {"Z": rng.random((3, 4))}, {"uncertsplat:nu": 3.5, "uncertsplat:kind": "student-t"})
    assert read_exr_attribute(tmp_path / "a.exr", "uncertsplat:nu") == pytest.approx(3.5)
    assert read_exr_attribute(tmp_path / "a.exr", "uncertsplat:kind") == "student-t"
    assert read_exr_attribute(tmp_path / "a.exr", "uncertsplat:absent") is None


def test_writes_leave_no_temp_files(tmp_path, rng):
    write_png(tmp_path / "x.png", rng.random((4, 4, 3)))
    write_exr(tmp_path / "x.exr", {"Z": rng.random((4, 4))})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.exr", "x.png"]


def test_truncated_png_is_a_user_error(tmp_path, rng):
    write_png(tmp_path / "full.png", rng.random((64, 64, 3)))
    data = (tmp_path / "full.png").read_bytes()
    (tmp_path / "cut.png").write_bytes(data[: len(data) // 2])
    with pytest.raises(UserError) as info:
        read_image(tmp_path / "cut.png")
    assert "cut.png" in str(info.value)


@pytest.mark.parametrize("content", [b"", b"this is not an image at all"])
def test_empty_or_garbage_file_is_a_user_error(tmp_path, content):
    p = tmp_path / "bad.png"
    p.write_bytes(content)
    with pytest.raises(UserError) as info:
        read_image(p)
    assert "bad.png" in str(info.value)
    with pytest.raises(UserError):
        read_image_size(p)


def test_missing_file_is_a_user_error(tmp_path):
    with pytest.raises(UserError) as info:
        read_image(tmp_path / "nope.jpg")
    assert "nope.jpg" in str(info.value)


def test_resize_area_average(rng):
    a = rng.random((8, 12, 3), dtype=np.float32)
    r = resize_image(a, 6, 4)
    expect = a.reshape(4, 2, 6, 2, 3).mean(axis=(1, 3))
    np.testing.assert_allclose(r, expect, atol=1e-6)
    assert resize_image(a[..., 0], 3, 2).shape == (2, 3)
    np.testing.assert_array_equal(resize_image(a, 12, 8), a)


def test_resize_down_along_one_axis_averages_the_area_too():
    """The width divided by 3, the height kept: each pixel is the mean of the three under it (a bilinear
    interpolation reads the middle one alone, which aliases)."""
    a = np.array([[0.0, 3.0, 0.0, 0.0, 6.0, 0.0], [3.0, 3.0, 3.0, 9.0, 0.0, 0.0]], dtype=np.float32)
    np.testing.assert_allclose(resize_image(a, 2, 2), [[1.0, 2.0], [3.0, 3.0]], rtol=0, atol=1e-6)
    np.testing.assert_allclose(resize_image(a.T.copy(), 2, 2), [[1.0, 3.0], [2.0, 3.0]], rtol=0, atol=1e-6)


def test_a_resized_mask_counts_a_pixel_only_where_every_pixel_under_it_counts():
    from uncertsplat.io.images import resize_mask

    m = np.ones((4, 6), dtype=bool)
    m[0, 1] = False  # one of the six under the top-left target pixel (3 x 2 of them)
    m[3, 5] = False
    assert resize_mask(m, 2, 2).tolist() == [[False, True], [True, False]]
    assert resize_mask(m[..., None], 2, 2).shape == (2, 2, 1)
    assert resize_mask(np.ones((4, 6)), 3, 2).all()  # (0/1 values: all count)


class TestAreaResize:
    """``area_resize``: each target pixel the exact mean of the source area it covers, edge to edge."""

    def test_whole_ratios_are_torch_area_pooling(self):
        import torch.nn.functional as F

        from uncertsplat.io.images import area_resize

        t = torch.rand(2, 3, 12, 18, generator=torch.Generator().manual_seed(0))
        assert torch.equal(area_resize(t, 4, 6), F.interpolate(t, size=(4, 6), mode="area"))
        assert torch.equal(area_resize(t[0, 0], 6, 9), F.interpolate(t[:1, :1], size=(6, 9), mode="area")[0, 0])

    @pytest.mark.parametrize("size", [(7, 5), (11, 13), (1, 1), (12, 17)])
    def test_other_ratios_integrate_exactly(self, size):
        from uncertsplat.io.images import area_resize

        H, W, h, w = 12, 18, *size
        t = torch.rand(3, H, W, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
        out = area_resize(t, h, w)
        # the same means from the image upsampled by h * w (nearest) and pooled by whole blocks
        fine = t.repeat_interleave(h, 1).repeat_interleave(w, 2)  # [3, H h, W w]
        ref = fine.reshape(3, h, H, w, W).mean((2, 4))
        torch.testing.assert_close(out, ref, atol=1e-12, rtol=0)
        torch.testing.assert_close(out.mean((1, 2)), t.mean((1, 2)), atol=1e-12, rtol=0)
        # a batch of images (resized one at a time) gives each image's own result
        batch = torch.stack([t, 1 - t])  # [2,3,H,W]
        torch.testing.assert_close(area_resize(batch, h, w), torch.stack([out, area_resize(1 - t, h, w)]),
                                   atol=1e-12, rtol=0)

    def test_a_ramp_keeps_its_pixel_centres(self):
        """802 x 533 to 401 x 266 (the rows by 2.0038): each pixel shows the photo where its centre falls."""
        from uncertsplat.io.images import resize_image

        ys, xs = np.meshgrid(np.arange(533) + 0.5, np.arange(802) + 0.5, indexing="ij")
        out = resize_image(np.stack([xs, ys], -1).astype(np.float32), 401, 266)  # [266,401,2]
        np.testing.assert_allclose(out[0, :, 0], (np.arange(401) + 0.5) * 2, atol=1e-3)
        np.testing.assert_allclose(out[:, 0, 1], (np.arange(266) + 0.5) * 533 / 266, atol=0.01)

    def test_upscaling_is_refused(self):
        from uncertsplat.io.images import area_resize

        with pytest.raises(ValueError, match="only downscales"):
            area_resize(torch.zeros(4, 4), 5, 4)


def test_a_photo_without_read_permission_is_named_as_such(tmp_path, rng, monkeypatch):
    """A photo of mode 000 was called a damaged file ("re-export or remove it"): OpenImageIO says only that it could
    not open it. (Run as root, which reads any file, the denial is simulated.)"""
    from uncertsplat.io import images

    path = tmp_path / "a.png"
    write_png(path, rng.random((4, 5, 3)).astype(np.float32))
    monkeypatch.setattr(oiio.ImageInput, "open", staticmethod(lambda name: None))
    monkeypatch.setattr(images.os, "access", lambda p, mode: False)
    with pytest.raises(UserError, match="permission denied") as err:
        read_image(path)
    assert "chmod" in err.value.hint
    monkeypatch.setattr(images.os, "access", lambda p, mode: True)  # readable, and still not opened: damaged
    with pytest.raises(UserError, match="cannot read the image") as err:
        read_image(path)
    assert "re-export" in err.value.hint


def test_read_alpha_is_clipped_and_finds_an_unnamed_extra_channel(tmp_path):
    """``read_alpha``: a float file's alpha as a value in [0, 1] (NaN as 0, as ``read_image`` reads it), and the
    last of two or four channels where the header names no alpha channel (as ``read_image`` composites it)."""
    from uncertsplat.io.images import read_alpha

    half = np.full((1, 4), 0.5, dtype=np.float32)
    write_exr(tmp_path / "rgba.exr", {"R": half, "G": half, "B": half,
                                      "A": np.array([[-0.5, 1.5, np.nan, 0.25]], dtype=np.float32)})
    np.testing.assert_array_equal(read_alpha(tmp_path / "rgba.exr"), [[0.0, 1.0, 0.0, 0.25]])
    extra = np.array([[0.0, 0.5, 1.0, 0.25]], dtype=np.float32)
    write_exr(tmp_path / "two.exr", {"Y0": half, "Y1": extra})
    np.testing.assert_array_equal(read_alpha(tmp_path / "two.exr"), extra)
    write_exr(tmp_path / "four.exr", {"C0": half, "C1": half, "C2": half, "C3": extra})
    np.testing.assert_array_equal(read_alpha(tmp_path / "four.exr"), extra)
    write_exr(tmp_path / "three.exr", {"C0": half, "C1": half, "C2": extra})
    assert read_alpha(tmp_path / "three.exr") is None
