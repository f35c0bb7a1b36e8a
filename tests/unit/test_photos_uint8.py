"""Training photos kept as their 8-bit values (``types.Photos``, ``data.dataset.load_photos``): the float view equals
the float32 path to the bit, other files stay float, and loading never holds the photos twice."""

from __future__ import annotations

import tracemalloc
from dataclasses import replace

import numpy as np
import OpenImageIO as oiio
import pytest
import torch

from tests.e2e.test_train_resume import assert_same_parameters, toy_config, toy_scene
from tests.fixtures import tiny_scene_path  # noqa: F401
from tests.unit.test_images import _raw_write
from uncertsplat.config import SceneConfig
from uncertsplat.data.dataset import load_images, load_photos
from uncertsplat.io.images import is_opaque_8bit, read_image, read_image_8bit
from uncertsplat.sfm.scene import load_scene
from uncertsplat.train.trainer import Trainer
from uncertsplat.types import UINT8_PHOTO_SCALE, Photos, as_float_photos


def _every_value(h: int = 16, w: int = 48) -> np.ndarray:
    """[h,w,3] uint8 holding each of the 256 values in each channel."""
    v = np.arange(h * w * 3, dtype=np.int64).reshape(h, w, 3)
    return ((v * 7) % 256).astype(np.uint8)


def test_the_scale_is_openimageios_conversion():
    assert UINT8_PHOTO_SCALE == float(np.float32(1.0) / np.float32(255.0))  # float32(1/255)
    v = torch.arange(256, dtype=torch.uint8)
    # a division by 255 differs from the multiplication in the last bit for some values: the test would see it
    assert not torch.equal(as_float_photos(v), v.float() / 255)


@pytest.mark.parametrize("name,attrs,grey", [("a.png", {}, False), ("a.jpg", {}, False), ("a.tif", {}, False),
                                             ("o.jpg", {"Orientation": 6}, False), ("g.png", {}, True)])
def test_8bit_read_times_the_scale_is_read_image_to_the_bit(tmp_path, name, attrs, grey):
    a = _every_value()
    if grey:
        a = a[..., :1]
    _raw_write(tmp_path / name, a, oiio.UINT8, attrs)
    assert is_opaque_8bit(tmp_path / name)
    u8 = read_image_8bit(tmp_path / name)
    ref = read_image(tmp_path / name)
    assert u8.dtype == np.uint8 and u8.shape == ref.shape
    assert torch.equal(as_float_photos(torch.from_numpy(u8)), torch.from_numpy(ref))


def test_16bit_float_and_alpha_files_are_not_read_as_8bit(tmp_path):
    a = _every_value()
    _raw_write(tmp_path / "a16.png", a.astype(np.uint16) * 257, oiio.UINT16)
    _raw_write(tmp_path / "a.exr", a.astype(np.float32) / 255, oiio.FLOAT)
    _raw_write(tmp_path / "rgba.png", np.concatenate([a, a[..., :1]], -1), oiio.UINT8)
    for name in ("a16.png", "a.exr", "rgba.png"):
        assert not is_opaque_8bit(tmp_path / name), name
        with pytest.raises(ValueError):
            read_image_8bit(tmp_path / name)


def test_load_photos_keeps_8bit_photos_as_uint8_equal_to_load_images(tiny_scene_path):  # noqa: F811
    scene = load_scene(tiny_scene_path, SceneConfig())
    idx = scene.split["train"]
    photos = load_photos(scene, idx)
    images = load_images(scene, idx)
    assert photos.data.dtype == torch.uint8 and photos.shape == images.shape and len(photos) == len(idx)
    assert torch.equal(photos.float(), images)
    assert torch.equal(photos[2], images[2]) and torch.equal(photos[1:3], images[1:3])
    assert torch.equal(photos[[0, 4]], images[[0, 4]])


@pytest.mark.parametrize("downscale", [2.0, 1.25])
def test_resized_8bit_photos_are_rounded_back_and_kept_as_uint8(tiny_scene_path, downscale):  # noqa: F811
    """Resized photos were kept as float32: four times the memory, so `scene.downscale = 1.25` (a user told to
    downscale a bit) needed more than no downscale. They are the area average rounded back to 8 bits, in both
    loaders, at most half a level from it."""
    from uncertsplat.io.images import resize_image

    scene = load_scene(tiny_scene_path, SceneConfig(downscale=downscale))
    photos = load_photos(scene, [0, 1])
    images = load_images(scene, [0, 1])
    assert photos.data.dtype == torch.uint8 and torch.equal(photos.float(), images)
    W, H = scene.cameras.width, scene.cameras.height
    average = torch.from_numpy(resize_image(read_image(scene.image_paths[1]), W, H))
    assert float((images[1] - average).abs().max()) <= 0.5 / 255 + 1e-6
    assert not torch.equal(images[1], average)  # (rounded, not as averaged)


def test_load_photos_keeps_16bit_photos_float(tiny_scene_path, tmp_path):  # noqa: F811
    scene = load_scene(tiny_scene_path, SceneConfig())
    a = (read_image(scene.image_paths[0]) * 65535).round().astype(np.uint16)
    _raw_write(tmp_path / "p16.png", a, oiio.UINT16)
    scene16 = replace(scene, image_paths=(tmp_path / "p16.png", *scene.image_paths[1:]))
    photos = load_photos(scene16, [0, 1])
    assert photos.data.dtype == torch.float32
    assert torch.equal(photos.float(), load_images(scene16, [0, 1]))
    assert not torch.equal(photos[0], load_photos(scene, [0]).float()[0])  # its 16-bit values, not 8-bit ones


@pytest.mark.parametrize("loader", [load_images, lambda s, i: load_photos(s, i).data])
def test_loading_never_holds_the_photos_twice(tiny_scene_path, loader):  # noqa: F811
    """Photos are read one at a time into a preallocated tensor (not traced: torch's allocator): the traced numpy
    memory at the peak is a few photos' worth. A list of photos then np.stack held the whole stack twice."""
    scene = load_scene(tiny_scene_path, SceneConfig())
    idx = scene.split["train"]
    assert len(idx) >= 16  # enough photos that a few of them weigh well below the whole stack
    tracemalloc.start()
    try:
        out = loader(scene, idx)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    nbytes = out.numel() * out.element_size()
    assert peak < 0.5 * nbytes, f"loading traced {peak / 1e6:.2f} MB for a {nbytes / 1e6:.2f} MB stack"


def test_training_on_uint8_photos_gives_the_float_runs_model_to_the_bit():
    """With the low-resolution phase, learned exposures and the held-out PSNR, which each read the photos."""
    scene, tr, te = toy_scene()
    tr8, te8 = (tr * 255).round().to(torch.uint8), (te * 255).round().to(torch.uint8)
    cfg = toy_config(iterations=24, low_res_fraction=0.3, low_res_scale=0.5, exposure="affine", eval_every=10)
    a = Trainer(scene, cfg, as_float_photos(tr8), as_float_photos(te8))
    b = Trainer(scene, cfg, Photos(tr8), Photos(te8))
    assert torch.equal(a.low_images, b.low_images)
    a.fit()
    b.fit()
    assert_same_parameters(a.model, b.model, atol=0.0)
    # with exposures on, all the photos are unexposed one at a time as they are read: the same numbers
    assert b.exposure is not None
    lazy, full = b.photos(), b.photos(list(range(len(tr8))))
    assert all(torch.equal(lazy[i], full[i]) for i in range(len(tr8)))
    assert torch.equal(lazy[[0, 2]], full[[0, 2]]) and torch.equal(lazy[1:3], full[1:3])


@pytest.mark.parametrize("dtype", [torch.uint8, torch.float32])
def test_unexposed_images_never_write_into_the_photos(dtype):
    """Photos stored as float32 (16-bit, resized or transparent files) give their own tensor from ``float()``: the
    unexposed images are a new tensor all the same, the caller's photos untouched (they were overwritten)."""
    from uncertsplat.render.exposure import PhotoExposure

    data = torch.full((2, 3, 4, 3), 128, dtype=torch.uint8)
    photos = Photos(data if dtype == torch.uint8 else as_float_photos(data))
    before = photos.float().clone()
    ex = PhotoExposure((0, 1), torch.tensor([[2.0] * 3, [0.5] * 3]), torch.zeros(2, 3))
    out = ex.unexposed_images([0, 1], photos)
    assert not torch.equal(out, before)  # brought to the model's exposure
    torch.testing.assert_close(photos.float(), before, rtol=0, atol=0)


def test_unexposed_photos_take_a_negative_index():
    """``Trainer.photos()``'s stand-in indexes like a tensor: [-1] is the last photo (it was an empty slice)."""
    from uncertsplat.render.exposure import unexpose
    from uncertsplat.train.trainer import _Unexposed

    photos = torch.rand(3, 2, 2, 3, generator=torch.Generator().manual_seed(0))
    gain, offset = torch.rand(3, 3) + 0.5, torch.rand(3, 3) * 0.1
    stand_in = _Unexposed(photos, gain, offset)
    want = unexpose(photos, gain, offset)
    for i in (-1, -3, 0, 2):
        torch.testing.assert_close(stand_in[i], want[i], rtol=0, atol=0)
