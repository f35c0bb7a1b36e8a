"""The native CPU kernels (rasterizer, fused SSIM, fused KL): the same values and gradients as the PyTorch
reference; build, cache, determinism and fallback.

Tolerances: float32 within 1e-5 (absolute for images, relative L2 for gradients) of the PyTorch path (the
same float32 formulas evaluated in another order; measured ~3e-7); float64 within 1e-12.
"""

from __future__ import annotations

import ctypes
import os
import shutil
import signal
import struct
import subprocess
import time
import warnings
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace

import pytest
import torch
from torch import Tensor

from tests.reference.naive_render import look_at_cameras, random_scene
from uncertsplat import native
from uncertsplat.errors import UserError
from uncertsplat.eval.image import ssim
from uncertsplat.gaussians.variational import TABLE_NAMES, Prior, kl_terms, random_model
from uncertsplat.render import render
from uncertsplat.render.project import project_gaussians
from uncertsplat.render.rasterize import bin_gaussians, composite
from uncertsplat.render.sh import num_sh_bases, sh_colors, sh_colors_split

PARAMS = ("means", "quats", "scales", "opacities", "sh")


@pytest.fixture(autouse=True)
def needs_native():
    if native.library() is None:
        pytest.skip(f"native compositor unavailable: {native.unavailable_reason()}")


def _render_and_grads(sample, cams, backend, tile_size=8):
    leaves = {k: getattr(sample, k).detach().clone().requires_grad_() for k in PARAMS}
    out = render(replace(sample, **leaves), cams, background=torch.tensor([0.1, 0.2, 0.3], dtype=sample.means.dtype),
                 tile_size=tile_size, backend=backend)
    g = torch.Generator().manual_seed(3)
    w = [torch.randn(t.shape, generator=g, dtype=t.dtype) for t in (out.rgb, out.depth, out.alpha)]
    ((out.rgb * w[0]).sum() + (out.depth * w[1]).sum() + (out.alpha * w[2]).sum()).backward()
    return out, {k: v.grad for k, v in leaves.items()}


def _scene(n, dtype, seed=4, opacity_range=(0.05, 0.95)):
    s = random_scene(n, torch.Generator().manual_seed(seed), sh_degree=2, dtype=dtype, opacity_range=opacity_range)
    return s, look_at_cameras(2, 61, 47, focal=55.0, dtype=dtype)


@pytest.mark.parametrize("tile_size", [4, 8, 16])
@pytest.mark.parametrize("dtype,tol", [(torch.float32, 1e-5), (torch.float64, 1e-12)])
def test_native_matches_torch_images_and_gradients(dtype, tol, tile_size):
    s, cams = _scene(600, dtype)
    a, ga = _render_and_grads(s, cams, "torch", tile_size)
    b, gb = _render_and_grads(s, cams, "native", tile_size)
    assert (a.alpha > 0.5).float().mean() > 0.2, "the scene must cover the image for the check to mean anything"
    for k in ("rgb", "alpha", "depth", "depth_expected"):
        err = (getattr(a, k) - getattr(b, k)).abs().max().item()
        assert err <= tol * max(1.0, getattr(a, k).abs().max().item()), f"{k}: {err}"
    for k in PARAMS:
        rel = ((ga[k] - gb[k]).norm() / ga[k].norm()).item()
        assert rel <= tol, f"grad {k}: relative error {rel}"


def test_saturated_scene_with_capped_alpha_and_early_stop():
    """Opaque Gaussians: alphas hit the 0.99 cap and rays stop early; both paths must agree."""
    s, cams = _scene(400, torch.float32, seed=7, opacity_range=(0.985, 1.0))
    a, ga = _render_and_grads(s, cams, "torch")
    b, gb = _render_and_grads(s, cams, "native")
    assert (a.alpha > 0.999).any()
    assert (a.rgb - b.rgb).abs().max() <= 1e-5
    for k in PARAMS:
        assert ((ga[k] - gb[k]).norm() / ga[k].norm()).item() <= 1e-5, k


@pytest.mark.parametrize("opacity_range", [(0.01, 0.03), (0.05, 0.1), (0.3, 0.6)])
def test_tile_lists_longer_than_a_list_chunk(opacity_range):
    """The forward takes a tile's list in chunks of 128 entries: faint Gaussians keep rays alive across several
    chunks (the state carries over), denser ones stop them in the first chunks (the rest is never listed); every
    case as the PyTorch path, in float64."""
    s, cams = _scene(1500, torch.float64, seed=9, opacity_range=opacity_range)
    p = project_gaussians(s.means, s.quats, s.scales, s.opacities, cams.cam_from_world, cams.K, 61, 47)
    bins = bin_gaussians(p.means2d, p.extents, p.valid, p.depths, 61, 47, 8, p.conics, s.opacities)
    assert int(bins.tile_count.max()) > 2 * 128
    a, ga = _render_and_grads(s, cams, "torch")
    b, gb = _render_and_grads(s, cams, "native")
    for k in ("rgb", "alpha", "depth"):
        assert (getattr(a, k) - getattr(b, k)).abs().max().item() <= 1e-12, k
    for k in PARAMS:
        assert ((ga[k] - gb[k]).norm() / ga[k].norm()).item() <= 1e-12, k


def test_rays_that_a_whole_list_chunk_passes_by_go_on_to_the_next():
    """One 8 x 8 tile: 139 flat Gaussians over its first two pixel rows only (the first slice of lanes), in front,
    stop those rays within the first chunk of 128 entries, in which the other slices' rays get no entry at all; the
    140th, behind, covers the whole tile. The chunk loop goes on while any ray of the tile is live, whether or not the
    chunk reached it: the lower rows get the last Gaussian, as on the PyTorch path."""
    n = 140
    means2d = torch.tensor([4.0, 1.0], dtype=torch.float64).repeat(1, n, 1)  # between pixel rows 0 and 1
    conics = torch.tensor([1e-4, 0.0, 1 / 0.09], dtype=torch.float64).repeat(1, n, 1)  # 100 px wide, 0.3 px high
    means2d[0, -1] = torch.tensor([4.0, 4.0])
    conics[0, -1] = torch.tensor([0.01, 0.0, 0.01])
    opac = torch.full((n,), 0.9, dtype=torch.float64)
    bins = bin_gaussians(means2d, torch.full_like(means2d, 100.0), torch.ones(1, n, dtype=torch.bool),
                         torch.arange(1.0, n + 1, dtype=torch.float64)[None], 8, 8, 8, conics, opac)
    assert bins.tile_count.tolist() == [n]
    gparams = torch.cat([means2d[0], conics[0], opac.log()[:, None]], -1)
    feat = torch.ones(n, 1, dtype=torch.float64)
    a, b = (composite(gparams, feat, bins, backend=be)[0, :, 0].view(8, 8) for be in ("torch", "native"))
    assert float(b[:2].min()) > 0.9998 and float(b[2:].min()) > 0.7
    assert (a - b).abs().max().item() <= 1e-12

def test_binning_lists_the_same_pairs_in_the_same_order():
    s, cams = _scene(800, torch.float32)
    p = project_gaussians(s.means, s.quats, s.scales, s.opacities, cams.cam_from_world, cams.K, 61, 47)
    args = (p.means2d, p.extents, p.valid, p.depths, 61, 47, 8, p.conics, s.opacities)
    a = bin_gaussians(*args, backend="torch")
    b = bin_gaussians(*args, backend="native")
    assert a.pair_gauss.numel() > 800
    for k in ("pair_gauss", "pair_tile", "tile_start", "tile_count"):
        assert torch.equal(getattr(a, k), getattr(b, k)), k


def _with_threads(n, fn):
    """``fn()`` with torch (and so the native kernels) on ``n`` threads, the thread count restored after."""
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(n)
        return fn()
    finally:
        torch.set_num_threads(before)


def test_backward_is_deterministic_for_any_thread_count():
    """Bit-identical gradients run to run and with 1 or 2 threads (resume relies on it)."""
    s, cams = _scene(600, torch.float32)

    def grads():
        return _render_and_grads(s, cams, "native")[1]

    g1, g2, g3 = _with_threads(2, grads), _with_threads(2, grads), _with_threads(1, grads)
    for k in PARAMS:
        assert torch.equal(g1[k], g2[k]) and torch.equal(g1[k], g3[k]), k


def test_every_kernel_is_the_same_with_one_or_two_threads(monkeypatch):
    """Projection, SH, the expected render's peak factor, compositing, SSIM and the KL terms, forward and backward:
    bit-identical with 1 and 2 threads. Sizes past each kernel's split threshold (9,000 Gaussians, 3 x 64 image rows,
    20,000 table elements), so 2 threads take 2 workers. `make test` runs its workers single-threaded
    (OMP_NUM_THREADS=1), so this is where the threaded paths are checked."""
    monkeypatch.setenv("UNCERTSPLAT_RASTERIZER", "native")
    s, cams = _scene(9000, torch.float32)
    s = replace(s, position_var=torch.rand(9000, generator=torch.Generator().manual_seed(5)) * 0.01)
    g = torch.Generator().manual_seed(6)
    target = torch.rand(64, 80, 3, generator=g)
    pred = (target + 0.1 * torch.randn(64, 80, 3, generator=g)).clamp(0, 1)
    model = random_model(20000, torch.Generator().manual_seed(7), num_entries=2, perturb_tables=0.5)

    def run():
        out, grads = _render_and_grads(s, cams, "native")
        x = pred.clone().requires_grad_()
        value = ssim(x, target)
        value.backward()
        for t in model.tables.values():
            t.grad = None
        kl = kl_terms(model, Prior())
        (kl["position"] + 2 * kl["scale"] + 3 * kl["gate"]).backward()
        return [t.detach() for t in (out.rgb, out.alpha, out.depth, *grads.values(), value, x.grad, *kl.values(),
                                     *(model.tables[k].grad for k in TABLE_NAMES))]

    one, two = _with_threads(1, run), _with_threads(2, run)
    assert float(one[1].mean()) > 0.2 and 0.1 < float(one[len(PARAMS) + 3]) < 0.99  # covered image, SSIM not trivial
    for a, b in zip(one, two, strict=True):
        assert torch.equal(a, b)


def test_more_features_than_the_kernel_takes():
    s, cams = _scene(50, torch.float32)
    p = project_gaussians(s.means, s.quats, s.scales, s.opacities, cams.cam_from_world, cams.K, 61, 47)
    bins = bin_gaussians(p.means2d, p.extents, p.valid, p.depths, 61, 47, 8, p.conics, s.opacities)
    gparams = torch.cat([p.means2d, p.conics, s.opacities.log().expand(2, -1)[..., None]], -1).reshape(-1, 6)
    feat = torch.rand(gparams.shape[0], 9)
    out = composite(gparams, feat, bins)  # auto: the PyTorch compositor takes over
    assert out.shape[-1] == 9
    with pytest.raises(ValueError, match="at most 8 features"):
        composite(gparams, feat, bins, backend="native")


def _image_inputs(dtype, seed=11):
    s, cams = _scene(700, dtype, seed=seed)
    p = project_gaussians(s.means, s.quats, s.scales, s.opacities, cams.cam_from_world, cams.K, 61, 47)
    bins = bin_gaussians(p.means2d, p.extents, p.valid, p.depths, 61, 47, 8, p.conics, s.opacities)
    centers = -(cams.cam_from_world[:, :3, :3].transpose(1, 2) @ cams.cam_from_world[:, :3, 3:])[..., 0]
    colors = sh_colors(s.sh_degree, s.sh, s.means, centers)
    log_o = s.opacities.log().expand(2, -1)
    return [t.detach().clone().requires_grad_() for t in (p.means2d, p.conics, log_o, colors, p.depths)], bins


@pytest.mark.parametrize("background", [None, (0.3, 0.6, 0.9)])
@pytest.mark.parametrize("dtype,tol", [(torch.float32, 1e-5), (torch.float64, 1e-12)])
@pytest.mark.parametrize("used", ["all", "rgb"])
def test_image_compositing_equals_tiles_then_image(background, dtype, tol, used):
    """render's fused path (``composite_image``: the kernel writes images and blends the background) against the
    packed inputs through ``composite``, ``tiles_to_image``, the slices and the blend: same images, same gradients
    to every input, also when the loss reads rgb only (the other outputs get no gradient) and with partial tiles
    (61 x 47 in 8 x 8 tiles) on two cameras."""
    from uncertsplat.render.rasterize import composite_image, tiles_to_image

    bg = torch.tensor(background, dtype=dtype) if background is not None else None
    g = torch.Generator().manual_seed(12)
    weights = [torch.randn(2, 47, 61, k, generator=g, dtype=dtype) for k in (3, 1, 1)]

    def loss(outs):
        return sum((o * w).sum() for o, w in zip(outs, weights, strict=True) if used == "all" or o.shape[-1] == 3)

    ins, bins = _image_inputs(dtype)
    fused = composite_image(*ins, bins, 47, 61, bg)
    loss(fused).backward()
    g_fused = [t.grad for t in ins]

    ins2, _ = _image_inputs(dtype)
    m2, con, lo, col, dep = ins2
    feat = torch.cat([col, dep[..., None], torch.ones_like(dep)[..., None]], -1).reshape(-1, 5)
    gp = torch.cat([m2, con, lo[..., None]], -1).reshape(-1, 6)
    img = tiles_to_image(composite(gp, feat, bins, backend="native"), 2, bins, 47, 61)
    rgb, de, al = img[..., 0:3], img[..., 3:4], img[..., 4:5]
    if bg is not None:
        rgb = rgb + (1.0 - al) * bg
    loss((rgb, de, al)).backward()
    assert float(al.detach().mean()) > 0.3, "the scene must cover the images"
    for a, b in zip(fused, (rgb, de, al), strict=True):
        assert (a - b).abs().max().item() <= tol
    for name, a, b in zip(("means2d", "conics", "log_o", "colors", "depths"), g_fused, [t.grad for t in ins2],
                          strict=True):
        if used == "rgb" and name == "depths":  # only the expected depth and alpha read the depths
            assert all(t is None or float(t.abs().max()) == 0.0 for t in (a, b))
            continue
        assert ((a - b).norm() / b.norm()).item() <= tol, name


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_image_backward_of_the_colour_only_equals_the_full_loop_exactly(dtype):
    """A loss of the colour alone (a training step's) takes the backward's colour-only loop, which leaves out the
    depth and alpha features: every gradient is the full loop's to the bit (the full loop runs when the depth and
    alpha gradients are given, here as zeros), and the depths get exactly 0."""
    from uncertsplat.render.rasterize import composite_image

    g = torch.Generator().manual_seed(5)
    weight = torch.randn(2, 47, 61, 3, generator=g, dtype=dtype)
    grads = []
    for zeros in (False, True):
        ins, bins = _image_inputs(dtype, seed=3)
        rgb, depth, alpha = composite_image(*ins, bins, 47, 61, torch.tensor([0.3, 0.6, 0.9], dtype=dtype))
        loss = (rgb * weight).sum()
        if zeros:  # non-null gradients of 0 for depth and alpha: the full loop
            loss = loss + (depth * 0.0).sum() + (alpha * 0.0).sum()
        loss.backward()
        grads.append([t.grad for t in ins])
    assert float(grads[0][0].abs().max()) > 0.0 and float(grads[0][3].abs().max()) > 0.0
    for name, a, b in zip(("means2d", "conics", "log_o", "colors", "depths"), *grads, strict=True):
        assert torch.equal(a, b), name
    assert float(grads[0][4].abs().max()) == 0.0


@pytest.mark.parametrize("n,size,tile_size", [(0, (61, 47), 8), (1, (61, 47), 8), (200, (1, 1), 8),
                                               (200, (5, 3), 16), (200, (17, 9), 4)])
def test_image_compositing_at_the_extremes(n, size, tile_size):
    """No Gaussian (the background everywhere), one, a one-pixel image, an image smaller than one tile, and
    images that end inside their last tiles: the fused path equals the PyTorch one (float64), gradients too."""
    w, h = size
    s = random_scene(max(n, 1), torch.Generator().manual_seed(1), sh_degree=1, dtype=torch.float64)
    if n == 0:
        s = replace(s, **{k: getattr(s, k)[:0] for k in PARAMS})
    cams = look_at_cameras(2, w, h, focal=55.0 * w / 61, dtype=torch.float64)
    outs = {}
    for backend in ("native", "torch"):
        leaves = {k: getattr(s, k).detach().clone().requires_grad_() for k in PARAMS}
        out = render(replace(s, **leaves), cams, background=torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64),
                     tile_size=tile_size, backend=backend)
        (out.rgb.sum() + out.alpha.sum() + out.depth.sum()).backward()
        outs[backend] = (out, {k: v.grad for k, v in leaves.items()})
    (a, ga), (b, gb) = outs["native"], outs["torch"]
    for k in ("rgb", "alpha", "depth"):
        assert (getattr(a, k) - getattr(b, k)).abs().max().item() <= 1e-12, k
    if n == 0:
        assert torch.equal(a.rgb, torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64).expand_as(a.rgb))
    for k in PARAMS:
        if n > 0 and gb[k] is not None and float(gb[k].norm()) > 0:
            assert ((ga[k] - gb[k]).norm() / gb[k].norm()).item() <= 1e-10, k


def test_a_grey_background_given_as_one_value_takes_the_tile_path():
    """A background of one value broadcasts over the channels as before (the fused path reads exactly 3)."""
    s, cams = _scene(300, torch.float32)
    grey = render(s, cams, background=torch.tensor(0.4), backend="native")
    rgb = render(s, cams, background=torch.tensor([0.4, 0.4, 0.4]), backend="native")
    assert (grey.rgb - rgb.rgb).abs().max().item() <= 1e-6


def test_a_background_that_learns_takes_the_tile_path():
    """The fused path gives the background no gradient; render keeps the general path when it needs one."""
    s, cams = _scene(300, torch.float32)
    bg = torch.tensor([0.2, 0.4, 0.6], requires_grad=True)
    out = render(s, cams, background=bg, backend="native")
    out.rgb.sum().backward()
    fixed = render(s, cams, background=bg.detach(), backend="native")
    assert (out.rgb - fixed.rgb).abs().max().item() <= 1e-5
    # d sum(rgb) / d bg_c = sum over the pixels of (1 - alpha)
    assert torch.allclose(bg.grad, (1.0 - fixed.alpha).sum().expand(3), rtol=1e-4)


def test_compositor_return_codes_become_clear_errors():
    """2 is the kernel running out of memory for its per-Gaussian records; any other failure names its code."""
    from uncertsplat.render.rasterize import _check_composite

    _check_composite(0, "")
    with pytest.raises(MemoryError, match="compositor backward ran out of memory.*fewer cameras"):
        _check_composite(2, " backward")
    with pytest.raises(RuntimeError, match=r"compositor failed \(code 1\)"):
        _check_composite(1, "")


def test_bad_backend_setting_is_refused(monkeypatch):
    s, cams = _scene(10, torch.float32)
    monkeypatch.setenv("UNCERTSPLAT_RASTERIZER", "fastest")
    with pytest.raises(UserError, match="UNCERTSPLAT_RASTERIZER must be auto, native or torch"):
        render(s, cams)


@pytest.mark.parametrize("value", ["fast", "-5", "2.5", ""])
def test_a_bad_poll_time_setting_is_refused(monkeypatch, value):
    """The thread pool reads UNCERTSPLAT_KERNEL_SPIN_US in C, where a typo would become 0 without a word."""
    monkeypatch.setattr(native, "_state", {})
    monkeypatch.setenv("UNCERTSPLAT_KERNEL_SPIN_US", value)
    with pytest.raises(UserError, match="UNCERTSPLAT_KERNEL_SPIN_US must be a whole number of microseconds"):
        native.library()
    monkeypatch.setenv("UNCERTSPLAT_KERNEL_SPIN_US", " 0 ")
    assert native.library() is not None


def test_without_a_compiler_it_warns_once_and_uses_pytorch(monkeypatch):
    s, cams = _scene(100, torch.float32)
    ref = render(s, cams, backend="torch").rgb
    monkeypatch.setattr(native, "_state", {})
    monkeypatch.setattr(native, "_compiler", lambda: None)
    with pytest.warns(UserWarning, match="no C\\+\\+ compiler found"):
        out = render(s, cams).rgb
    assert torch.equal(out, ref)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the second render does not warn again
        render(s, cams)
    with pytest.raises(UserError, match="native kernels are unavailable: no C\\+\\+ compiler") as err:
        render(s, cams, backend="native")
    assert "unset UNCERTSPLAT_RASTERIZER" in err.value.hint


def test_native_asked_for_without_a_compiler_is_refused_before_any_work(monkeypatch, tmp_path, capsys):
    """UNCERTSPLAT_RASTERIZER=native without a compiler warned of a fallback to PyTorch, then failed with a
    traceback at the first kernel call, a half-made run folder left: refused at once, as one message, no fallback
    warning; a CXX that is not found is said, not passed over."""
    from uncertsplat.config import train_config_from
    from uncertsplat.train.session import train_model

    monkeypatch.setenv("UNCERTSPLAT_RASTERIZER", "native")
    monkeypatch.setattr(native, "_state", {})
    monkeypatch.setattr(native, "_compiler", lambda: None)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no "using the PyTorch implementations" warning: it would not
        with pytest.raises(UserError, match="UNCERTSPLAT_RASTERIZER=native, but the native kernels are unavailable"):
            train_model(tmp_path / "scene", tmp_path / "run", train_config_from("tiny"), torch.device("cpu"))
    assert not (tmp_path / "run").exists()
    monkeypatch.undo()
    monkeypatch.setenv("CXX", str(tmp_path / "no-such-c++"))
    capsys.readouterr()
    assert native._compiler() is not None  # (this machine has c++)
    assert f"CXX={tmp_path / 'no-such-c++'} is not a compiler found on the PATH" in capsys.readouterr().err


def test_an_unwritable_cache_folder_means_pytorch_kernels_not_a_crash(monkeypatch, tmp_path):
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("")
    monkeypatch.setenv("UNCERTSPLAT_CACHE_DIR", str(blocker))
    monkeypatch.setattr(native, "_state", {})
    with pytest.warns(UserWarning, match="could not write"):
        assert native.library() is None
    assert "could not write" in native.describe("cpu")
    s, cams = _scene(50, torch.float32)
    assert torch.isfinite(render(s, cams).rgb).all()


def test_library_is_built_into_the_cache_folder_and_reused(monkeypatch, tmp_path):
    monkeypatch.setenv("UNCERTSPLAT_CACHE_DIR", str(tmp_path))
    # unoptimised: the build is what is tested, and -O0 compiles in a third of the time (8 s against 25-40 s on 2
    # cores); every other test runs the library `make setup` built with the real flags
    monkeypatch.setattr(native, "BASE_FLAGS", tuple("-O0" if f == "-O3" else f for f in native.BASE_FLAGS))
    monkeypatch.setattr(native, "_state", {})
    assert native.library() is not None
    built = list((tmp_path / "native").glob("kernels-*.so"))
    assert len(built) == 1
    stamp = built[0].stat().st_mtime_ns
    monkeypatch.setattr(native, "_state", {})
    assert native.library() is not None  # loads the cached file, no rebuild
    assert [p.stat().st_mtime_ns for p in (tmp_path / "native").glob("kernels-*.so")] == [stamp]
    assert not list((tmp_path / "native").glob("*.so.tmp*")) and len(list((tmp_path / "native").iterdir())) == 1


def test_a_failing_compiler_falls_back_to_pytorch_and_says_why(monkeypatch, tmp_path):
    """The reason names the failed command and its output, no file is left in the cache folder, and the renderer
    takes the PyTorch path."""
    fake = tmp_path / "bad-cxx"
    fake.write_text("#!/bin/sh\necho \"error: boom\"\nexit 1\n")
    fake.chmod(0o755)
    monkeypatch.setenv("CXX", str(fake))
    monkeypatch.setenv("UNCERTSPLAT_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setattr(native, "_state", {})
    with pytest.warns(UserWarning, match="the build failed"):
        assert native.library() is None
    reason = native.unavailable_reason()
    assert str(fake) in reason and "composite_forward.cpp" in reason and "boom" in reason
    assert not list((tmp_path / "cache" / "native").iterdir())
    assert "PyTorch kernels" in native.describe("cpu")
    s, cams = _scene(50, torch.float32)
    assert torch.isfinite(render(s, cams).rgb).all()


@pytest.mark.parametrize("shape", [(37, 53, 3), (2, 24, 19, 3), (11, 11, 1), (3, 20, 17, 2)])
def test_fused_ssim_matches_the_reference(monkeypatch, shape):
    g = torch.Generator().manual_seed(2)
    target = torch.rand(shape, generator=g)
    pred = (target + 0.2 * torch.randn(shape, generator=g)).clamp(0, 1)
    out = {}
    for backend in ("torch", "native"):
        monkeypatch.setenv("UNCERTSPLAT_RASTERIZER", backend)
        x = pred.clone().requires_grad_()
        value = ssim(x, target, reduction="none")
        (value * torch.arange(1, value.numel() + 1).view_as(value)).sum().backward()
        out[backend] = (value.detach(), x.grad)
    assert 0.1 < float(out["torch"][0].mean()) < 0.9
    assert torch.allclose(out["native"][0], out["torch"][0], atol=1e-5, rtol=1e-5)
    rel = (out["native"][1] - out["torch"][1]).norm() / out["torch"][1].norm()
    assert rel <= 1e-5


@pytest.mark.parametrize("shape", [(64, 45, 3), (5, 30, 3), (2, 13, 9, 1)])
def test_fused_ssim_is_the_same_on_any_number_of_threads(monkeypatch, shape):
    """The kernel splits each plane's rows into runs, one per task, blurring the r rows around a run twice: the
    value, the L1 term and the gradient do not depend on how many runs there are (threads 1-7, more runs than
    rows included), bit for bit."""
    from uncertsplat.eval.image import ssim_and_l1

    monkeypatch.setenv("UNCERTSPLAT_RASTERIZER", "native")
    g = torch.Generator().manual_seed(5)
    target = torch.rand(shape, generator=g)
    pred = (target + 0.2 * torch.randn(shape, generator=g)).clamp(0, 1)
    before = torch.get_num_threads()
    out = []
    try:
        for threads in (1, 2, 3, 7):
            torch.set_num_threads(threads)
            x = pred.clone().requires_grad_()
            s, l1 = ssim_and_l1(x, target)
            (0.8 * l1 + 0.2 * (1 - s)).backward()
            out.append((s.detach(), l1.detach(), x.grad))
    finally:
        torch.set_num_threads(before)
    for s, l1, grad in out[1:]:
        assert torch.equal(s, out[0][0]) and torch.equal(l1, out[0][1]) and torch.equal(grad, out[0][2])


def test_fused_ssim_gradient_where_the_structure_term_vanishes(monkeypatch):
    """Anti-correlated windows with 2 sigma_xy + C2 ~ 0: the gradient must stay finite and match the
    reference (a kernel dividing by that term gave NaN steps in training)."""
    checker = (torch.arange(40)[:, None] + torch.arange(40)[None, :]) % 2 * 2.0 - 1.0  # +-1
    e = (0.03**2 / 2) ** 0.5  # local sigma_xy ~ -e^2 = -C2 / 2
    pred = (0.5 + e * checker)[..., None].expand(40, 40, 3).contiguous()
    target = (0.5 - e * checker)[..., None].expand(40, 40, 3).contiguous()
    grads = {}
    for backend in ("torch", "native"):
        monkeypatch.setenv("UNCERTSPLAT_RASTERIZER", backend)
        x = pred.clone().requires_grad_()
        ssim(x, target).backward()
        grads[backend] = x.grad
    assert torch.isfinite(grads["native"]).all()
    assert ((grads["native"] - grads["torch"]).norm() / grads["torch"].norm()).item() <= 1e-4


def test_fused_ssim_leaves_other_cases_to_the_reference(monkeypatch):
    """valid padding, float64 and a target that needs a gradient take the PyTorch path, even when forced."""
    from uncertsplat.eval import image

    monkeypatch.setenv("UNCERTSPLAT_RASTERIZER", "native")
    calls = []
    fused = image._fused_ssim_l1
    monkeypatch.setattr(image, "_fused_ssim_l1", lambda *a: calls.append(1) or fused(*a))
    a, b = torch.rand(20, 20, 3), torch.rand(20, 20, 3)
    same = float(ssim(a, b))
    assert calls, "the fused kernel did not take the float32 'same' case"  # the spy sees it when it runs
    calls.clear()
    valid = ssim(a, b, padding="valid")
    torch.testing.assert_close(valid, image.ssim_map(a, b, padding="valid").mean())
    assert valid != pytest.approx(same, abs=1e-3)  # valid padding is not "same" padding's value
    torch.testing.assert_close(ssim(a.double(), b.double()), image.ssim_map(a.double(), b.double()).mean())
    t = b.clone().requires_grad_()
    ssim(a, t).backward()
    assert t.grad is not None and torch.isfinite(t.grad).all() and t.grad.abs().sum() > 0
    assert not calls


@pytest.mark.parametrize("shape", [(37, 53, 3), (2, 24, 19, 3), (3, 21, 17, 1), (1, 1, 3), (5, 30, 3)])
def test_fused_ssim_with_the_targets_statistics_given_is_the_same_to_the_bit(monkeypatch, shape):
    """``ssim_target_stats`` of the target, passed to ``ssim_and_l1``: the kernel reads them instead of blurring
    the target, and the value, the L1 term and the gradient are the same bits as without them, on 1-3 threads
    (image widths not a multiple of the lanes, one-pixel images and more tasks than rows included); statistics of
    another shape are refused."""
    from uncertsplat.eval.image import ssim_and_l1, ssim_target_stats

    monkeypatch.setenv("UNCERTSPLAT_RASTERIZER", "native")
    g = torch.Generator().manual_seed(7)
    target = torch.rand(shape, generator=g)
    pred = (target + 0.2 * torch.randn(shape, generator=g)).clamp(0, 1)
    stats = ssim_target_stats(target)
    planes = target[..., 0, 0, 0].numel() * shape[-1]
    assert stats.shape == (2, planes, shape[-3], shape[-2])
    before = torch.get_num_threads()
    try:
        for threads in (1, 2, 3):
            torch.set_num_threads(threads)
            out = []
            for given in (None, stats):
                x = pred.clone().requires_grad_()
                s, l1 = ssim_and_l1(x, target, given)
                (0.8 * l1 + 0.2 * (1 - s)).backward()
                out.append((s.detach(), l1.detach(), x.grad))
            assert all(torch.equal(a, b) for a, b in zip(out[0], out[1], strict=True))
    finally:
        torch.set_num_threads(before)
    with pytest.raises(ValueError, match="target_stats"):
        ssim_and_l1(pred, target, stats[:, :1])


def test_the_targets_statistics_are_its_blurred_mean_and_mean_square(monkeypatch):
    """What the kernel keeps of a target: the zero-padded 11x11 Gaussian blur of y and of y^2 per channel (the
    reference's tensor ops, float64); None where the fused kernel does not run (float64)."""
    from uncertsplat.eval.image import _blur, gaussian_window, ssim_target_stats

    monkeypatch.setenv("UNCERTSPLAT_RASTERIZER", "native")
    y = torch.rand(2, 23, 31, 3, generator=torch.Generator().manual_seed(3))
    stats = ssim_target_stats(y)
    planes = y.permute(0, 3, 1, 2).reshape(1, 6, 23, 31).double()
    ref = _blur(torch.cat([planes, planes * planes], dim=1), gaussian_window(dtype=torch.float64), "same")[0]
    assert torch.allclose(stats.reshape(12, 23, 31).double(), ref, atol=1e-6)
    assert ssim_target_stats(y.double()) is None


@pytest.mark.parametrize("weights", [(0.8, 0.2), (1.0, 0.0), (0.0, 1.0)])
@pytest.mark.parametrize("shape", [(37, 53, 3), (2, 24, 19, 3), (3, 21, 19, 1), (1, 1, 3), (3, 2, 1, 2)])
def test_the_l1_term_from_the_fused_ssim_pass(monkeypatch, shape, weights):
    """``ssim_and_l1``'s L1 comes out of the SSIM kernel's pass: the same value and gradient as
    ``(pred - target).abs().mean()`` for any mix of the two terms (only one of them used included), and zero
    gradient where pred == target (as torch's abs)."""
    from uncertsplat.eval.image import ssim_and_l1

    g = torch.Generator().manual_seed(4)
    target = torch.rand(shape, generator=g)
    pred = (target + 0.2 * torch.randn(shape, generator=g)).clamp(0, 1)
    # one pixel where pred == target (none in a one-pixel image)
    same = (3, 4) if shape[-3] > 3 and shape[-2] > 4 else (0, 0) if shape[-3] * shape[-2] > 1 else None
    if same is not None:
        pred[..., same[0], same[1], :] = target[..., same[0], same[1], :]
    out = {}
    for backend in ("torch", "native"):
        monkeypatch.setenv("UNCERTSPLAT_RASTERIZER", backend)
        x = pred.clone().requires_grad_()
        s, l1 = ssim_and_l1(x, target)
        (weights[0] * l1 + weights[1] * (1 - s)).backward()
        out[backend] = (s.detach(), l1.detach(), x.grad)
    (s_t, l1_t, g_t), (s_n, l1_n, g_n) = out["torch"], out["native"]
    assert float(l1_t) > 0.02
    assert abs(float(s_n - s_t)) <= 1e-5 and abs(float(l1_n - l1_t)) <= 1e-6
    assert ((g_n - g_t).norm() / g_t.norm()).item() <= 1e-5
    if weights[1] == 0 and same is not None:  # the L1 term alone: nothing pulls a pixel that already matches
        assert float(g_n[..., same[0], same[1], :].abs().max()) == 0.0


@pytest.mark.parametrize("variant", ["ours", "paper"])
def test_fused_kl_matches_the_reference_down_to_the_extremes(monkeypatch, variant):
    prior = Prior(variant=variant)
    model = random_model(3000, torch.Generator().manual_seed(0), carrier_fraction=0.8, perturb_tables=1.5,
                         prior=prior)
    extremes = torch.tensor([-120.0, -30.0, -16.0, -15.0, -14.0, -6.0, 0.0, 20.0, 90.0, 1e3])  # raw spreads
    for name in ("pos_spread_raw", "gate_spread_raw", "scale_width_raw"):
        model.tables[name].data[: len(extremes)] = extremes[:, None, None]
    out = {}
    for backend in ("torch", "native"):
        monkeypatch.setenv("UNCERTSPLAT_RASTERIZER", backend)
        for t in model.tables.values():
            t.grad = None
        kl = kl_terms(model, prior)
        (kl["position"] + 2 * kl["scale"] + 3 * kl["gate"]).backward()
        out[backend] = ({k: v.item() for k, v in kl.items()}, {k: model.tables[k].grad.clone() for k in TABLE_NAMES})
    for k, ref in out["torch"][0].items():
        assert out["native"][0][k] == pytest.approx(ref, rel=2e-6), k
    for k in TABLE_NAMES:
        ref, got = out["torch"][1][k], out["native"][1][k]
        assert torch.isfinite(got).all(), k
        assert ((got - ref).norm() / ref.norm().clamp_min(1e-30)).item() <= 1e-5, k


def test_fused_kl_needs_no_gradient_buffers_without_grad(monkeypatch):
    monkeypatch.setenv("UNCERTSPLAT_RASTERIZER", "native")
    model = random_model(100, torch.Generator().manual_seed(1), perturb_tables=0.5)
    with torch.no_grad():
        kl = kl_terms(model, Prior())
    assert not kl["total"].requires_grad and kl["total"].item() > 0


@pytest.mark.parametrize("degree,bases", [(0, 1), (1, 4), (2, 9), (2, 16), (3, 16)])
def test_native_sh_colours_match_the_reference(monkeypatch, degree, bases):
    """Includes a non-contiguous upstream gradient (as the renderer produces), which the kernel once read
    from freed memory."""
    g = torch.Generator().manual_seed(degree)
    sh, means = torch.randn(700, bases, 3, generator=g), torch.randn(700, 3, generator=g)
    centres = torch.randn(3, 3, generator=g) * 3
    weights = torch.randn(3, 700, 5, generator=g)
    out = {}
    for backend in ("torch", "native"):
        monkeypatch.setenv("UNCERTSPLAT_RASTERIZER", backend)
        a, b = sh.clone().requires_grad_(), means.clone().requires_grad_()
        colours = sh_colors(degree, a, b, centres)
        feat = torch.cat([colours, torch.ones_like(colours[..., :2])], -1)  # grad of colours: a strided view
        (feat * weights).sum().backward()
        out[backend] = (colours.detach(), a.grad, b.grad if b.grad is not None else torch.zeros_like(b))
    assert (out["torch"][0] == 0).any() and (out["torch"][0] > 0).any(), "both sides of the clamp at 0"
    assert torch.allclose(out["native"][0], out["torch"][0], atol=1e-5, rtol=1e-5)
    for ref, got in zip(out["torch"][1:], out["native"][1:], strict=True):
        assert ((got - ref).norm() / ref.norm().clamp_min(1e-30)).item() <= 1e-5


@pytest.mark.parametrize("degree,bases", [(0, 1), (0, 4), (1, 4), (2, 9), (3, 16)])
def test_sh_from_two_arrays_equals_sh_from_their_concatenation(monkeypatch, degree, bases):
    """``sh_colors_split`` (the DC and the higher bands as two tensors, the parameter table's layout) gives the
    colours and gradients of ``sh_colors`` on their concatenation, bit for bit with the native kernel, and its
    gradients come in the inputs' own contiguous layouts (so autograd stores them without a copy); the same on the
    PyTorch path. At degree 0 the native kernel gives the higher bands no gradient (none, not zeros: a training
    step's Adam then skips them, ``Trainer._idle_sh``)."""
    g = torch.Generator().manual_seed(10 + degree)
    sh, means = torch.randn(700, bases, 3, generator=g), torch.randn(700, 3, generator=g)
    centres = torch.randn(3, 3, generator=g) * 3
    weights = torch.randn(3, 700, 3, generator=g)
    for backend in ("native", "torch"):
        monkeypatch.setenv("UNCERTSPLAT_RASTERIZER", backend)
        a, b = sh.clone().requires_grad_(), means.clone().requires_grad_()
        joined = sh_colors(degree, a, b, centres)
        (joined * weights).sum().backward()
        dc, rest, m = sh[:, :1].clone().requires_grad_(), sh[:, 1:].clone().requires_grad_(), \
            means.clone().requires_grad_()
        split = sh_colors_split(degree, dc, rest, m, centres)
        (split * weights).sum().backward()
        assert torch.equal(split, joined), backend
        if backend == "native" and degree == 0:
            assert rest.grad is None and not a.grad[:, 1:].any(), "degree 0: no gradient for the bands"
            rest.grad = torch.zeros_like(rest)
        assert torch.equal(dc.grad, a.grad[:, :1]) and torch.equal(rest.grad, a.grad[:, 1:]), backend
        assert torch.equal(m.grad, b.grad) if b.grad is not None else m.grad is None or not m.grad.any()
        assert dc.grad.is_contiguous() and rest.grad.is_contiguous()
        if bases > 1:
            assert not rest.grad[:, num_sh_bases(degree) - 1:].any(), "bases above the degree get 0"


def test_a_training_sample_renders_as_its_concatenated_copy():
    """The expected render with the tables' constants (a training step's sample) keeps the SH as the table's two
    tensors; rendered, it equals the same sample with them concatenated, and ``full_sh`` is that concatenation."""
    from dataclasses import replace

    from uncertsplat.gaussians.variational import expected_constants, expected_render_sample
    from uncertsplat.render.render import render

    model = random_model(300, torch.Generator().manual_seed(4), perturb_tables=0.3)
    constants = expected_constants(model, extent=1.0, temperature=0.2)
    s = expected_render_sample(model, variant="ours", extent=1.0, temperature=0.2, tables_grad=False,
                               constants=constants)
    assert s.sh_rest is not None and s.sh.shape[1] == 1
    assert s.sh.data_ptr() == model.params["sh0"].data_ptr() and s.sh_rest.data_ptr() == model.params["shN"].data_ptr()
    joined = replace(s, sh=s.full_sh(), sh_rest=None)
    assert joined.sh.shape[1] == 1 + s.sh_rest.shape[1]
    cams = look_at_cameras(2, 40, 30, focal=35.0, radius=3.0)
    a, b = render(s, cams), render(joined, cams)
    assert torch.equal(a.rgb, b.rgb) and torch.equal(a.depth, b.depth)


def test_native_projection_matches_the_reference(monkeypatch):
    s = random_scene(800, torch.Generator().manual_seed(3), sh_degree=0, extent=2.5)
    quats = s.quats.clone()
    quats[:3] = 0.0  # degenerate rotations
    quats[3:6] *= 1e4
    cams = look_at_cameras(3, 64, 48, focal=50.0, radius=3.0)  # some Gaussians behind or beside cameras
    g = torch.Generator().manual_seed(8)
    out = {}
    for backend in ("torch", "native"):
        monkeypatch.setenv("UNCERTSPLAT_RASTERIZER", backend)
        leaves = [t.detach().clone().requires_grad_() for t in (s.means, quats, s.scales)]
        p = project_gaussians(*leaves, s.opacities, cams.cam_from_world, cams.K, 64, 48, near=0.5)
        w = [torch.randn(t.shape, generator=torch.Generator().manual_seed(i)) for i, t in
             enumerate((p.means2d, p.conics, p.depths))]
        keep = p.valid[..., None].float()  # culled Gaussians' conics are not used by the renderer
        ((p.means2d * w[0] * keep).sum() + (p.conics * w[1] * keep).sum() + (p.depths * w[2]).sum()).backward()
        out[backend] = (p, [t.grad for t in leaves])
    a, b = out["torch"][0], out["native"][0]
    assert torch.equal(a.valid, b.valid) and 0 < int(a.valid.sum()) < a.valid.numel()
    v = a.valid
    for k in ("means2d", "conics", "depths", "extents"):
        x, y = getattr(a, k).detach()[v], getattr(b, k).detach()[v]
        assert torch.allclose(y, x, rtol=1e-5, atol=1e-5 * float(x.abs().max())), k
    for name, ref, got in zip(("means", "quats", "scales"), out["torch"][1], out["native"][1], strict=True):
        assert torch.isfinite(got).all(), name
        assert ((got - ref).norm() / ref.norm()).item() <= 1e-4, name
    del g


def test_native_projection_culls_beyond_the_far_plane():
    """Gaussians at or beyond ``far`` are culled by both paths (not valid, no footprint), those before it kept."""
    s = random_scene(400, torch.Generator().manual_seed(5), sh_degree=0, extent=2.5)
    cams = look_at_cameras(2, 64, 48, focal=50.0, radius=3.0)
    out = {b: project_gaussians(s.means, s.quats, s.scales, s.opacities, cams.cam_from_world, cams.K, 64, 48,
                                near=0.5, far=3.2, backend=b) for b in ("torch", "native")}
    a, b = out["torch"], out["native"]
    beyond = a.depths >= 3.2
    assert bool(beyond.any()) and bool(a.valid[~beyond].any())
    assert torch.equal(a.valid, b.valid) and not bool(b.valid[beyond].any())
    assert torch.equal(b.extents[beyond], torch.zeros_like(b.extents[beyond]))

class TestSingleThreadedTorch:
    """``native.single_threaded_torch``: torch's own ops on one thread, the native kernels on torch's count."""

    def test_inside_torch_has_one_thread_and_the_kernels_keep_theirs(self):
        if native.library() is None:
            pytest.skip(f"native kernels unavailable: {native.unavailable_reason()}")

        def check():
            with native.single_threaded_torch("cpu"):
                inside = torch.get_num_threads(), native.kernel_threads()
                with native.single_threaded_torch("cpu"):  # nested: unchanged
                    nested = torch.get_num_threads(), native.kernel_threads()
                after = torch.get_num_threads()
            return inside, nested, after, torch.get_num_threads(), native.kernel_threads()

        assert _with_threads(2, check) == ((1, 2), (1, 2), 1, 2, 2)

    def test_threads_that_overlap_each_keep_their_own_count(self):
        """Two threads inside at once (a pool over Predictor.predict), the second one a thread that has run torch
        ops before (its own thread count): inside, each runs torch on one thread and the kernels on its count; after,
        each has its count back, whichever left first. (A count shared across threads left the first one out on
        one thread for good, and the second ran its sums on two.)"""
        if native.library() is None:
            pytest.skip(f"native kernels unavailable: {native.unavailable_reason()}")
        import threading

        x = torch.rand(2_000_000, generator=torch.Generator().manual_seed(0))
        b_ready, a_in, b_in, a_out = threading.Event(), threading.Event(), threading.Event(), threading.Event()
        seen = {}

        def b():
            torch.set_num_threads(2)  # a thread of its own count, torch's pool started (a pool thread's earlier work)
            x.sum()
            b_ready.set()
            a_in.wait(5)
            with native.single_threaded_torch("cpu"):
                b_in.set()
                a_out.wait(5)
                seen["b inside after a left"] = torch.get_num_threads(), native.kernel_threads()
            seen["b after"] = torch.get_num_threads(), native.kernel_threads()

        def check():
            t = threading.Thread(target=b)
            t.start()
            b_ready.wait(5)
            with native.single_threaded_torch("cpu"):
                a_in.set()
                b_in.wait(5)
                seen["a inside"] = torch.get_num_threads(), native.kernel_threads()
            a_out.set()
            t.join(10)
            return seen, torch.get_num_threads(), native.kernel_threads()

        got, after, kernels = _with_threads(2, check)
        assert got == {"a inside": (1, 2), "b inside after a left": (1, 2), "b after": (2, 2)}
        assert (after, kernels) == (2, 2)

    def test_restored_after_an_error(self):
        def fail():
            with native.single_threaded_torch("cpu"):
                raise KeyError("inside")

        def check():
            with pytest.raises(KeyError):
                fail()
            return torch.get_num_threads(), native.kernel_threads()

        assert _with_threads(2, check) == (2, 2)

    @pytest.mark.parametrize("case", ["one thread", "torch backend", "meta device"])
    def test_nothing_changes_where_it_cannot_pay(self, case, monkeypatch):
        if case == "torch backend":
            monkeypatch.setenv("UNCERTSPLAT_RASTERIZER", "torch")
        n = 1 if case == "one thread" else 2
        device = "meta" if case == "meta device" else "cpu"

        def check():
            with native.single_threaded_torch(device):
                return torch.get_num_threads(), native.kernel_threads()

        assert _with_threads(n, check) == (n, n)

    def test_a_training_step_runs_torch_on_one_thread_and_the_kernels_on_two(self):
        if native.library() is None:
            pytest.skip(f"native kernels unavailable: {native.unavailable_reason()}")
        from tests.e2e.test_train_resume import toy_config, toy_scene
        from uncertsplat.train.trainer import Trainer

        scene, tr, te = toy_scene()
        t = Trainer(scene, toy_config(iterations=4), tr, te)
        seen = []
        render = t.render

        def wrapped(g, cams):
            seen.append((torch.get_num_threads(), native.kernel_threads()))
            return render(g, cams)

        t.render = wrapped
        _with_threads(2, t.train_step)
        assert seen == [(1, 2)]
        assert _with_threads(2, torch.get_num_threads) == 2


class TestKernelThreads:
    """The kernels' worker threads (``parallel.h``): kept in a pool between calls, made afresh for a call that finds
    the pool taken, started anew in a child made by fork(). Which thread runs a worker must never change a result."""

    @staticmethod
    def _ssim_and_grad(seed: int) -> tuple[Tensor, Tensor]:
        g = torch.Generator().manual_seed(seed)
        target = torch.rand(96, 80, 3, generator=g)  # 3 x 96 rows: two workers on two threads
        x = (target + 0.1 * torch.randn(96, 80, 3, generator=g)).clamp(0, 1).requires_grad_()
        value = ssim(x, target)
        value.backward()
        return value.detach(), x.grad

    def test_calls_from_several_threads_at_once_each_get_their_own_result(self, monkeypatch):
        """Four Python threads calling kernels at once (ctypes lets them overlap): one holds the pool, the others
        make their own threads; every result is the one the call gives alone."""
        monkeypatch.setenv("UNCERTSPLAT_RASTERIZER", "native")  # (the module's needs_native skips without them)
        seeds = list(range(8))
        alone = {s: _with_threads(1, lambda s=s: self._ssim_and_grad(s)) for s in seeds}

        def many(seed):
            return [self._ssim_and_grad(seed) for _ in range(6)]

        def run():
            with ThreadPoolExecutor(4) as pool:
                return dict(zip(seeds, pool.map(many, seeds), strict=True))

        together = _with_threads(3, run)
        for s in seeds:
            for value, grad in together[s]:
                assert torch.equal(value, alone[s][0]) and torch.equal(grad, alone[s][1]), s

    def test_more_workers_than_the_pool_holds_so_far(self, monkeypatch):
        """The pool grows to the workers a call asks for (2, then 4 threads: one, then three helpers)."""
        monkeypatch.setenv("UNCERTSPLAT_RASTERIZER", "native")
        one = _with_threads(1, lambda: self._ssim_and_grad(3))
        for n in (2, 4, 2):
            value, grad = _with_threads(n, lambda: self._ssim_and_grad(3))
            assert torch.equal(value, one[0]) and torch.equal(grad, one[1]), n

    @pytest.mark.skipif(not hasattr(os, "fork"), reason="no fork() on this platform")
    def test_a_child_made_by_fork_runs_the_kernels(self, monkeypatch):
        """A child forked after the pool started has none of its threads: it must start its own, not wait forever
        for the parent's (the test fails on a timeout)."""
        monkeypatch.setenv("UNCERTSPLAT_RASTERIZER", "native")
        expected = _with_threads(2, lambda: self._ssim_and_grad(5))[0]  # the pool started in this process
        read, write = os.pipe()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)  # fork() of a process with threads
            pid = os.fork()
        if pid == 0:  # the child: no pytest machinery, only the kernel and the answer
            try:
                value = _with_threads(2, lambda: self._ssim_and_grad(5))[0]
                os.write(write, struct.pack("<d", float(value)))
            finally:
                os._exit(0)
        os.close(write)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            done, status = os.waitpid(pid, os.WNOHANG)
            if done:
                break
            time.sleep(0.05)
        else:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            pytest.fail("the forked child's kernel call did not return within 60 s")
        answer = os.read(read, 8)
        os.close(read)
        assert os.waitstatus_to_exitcode(status) == 0 and len(answer) == 8
        assert struct.unpack("<d", answer)[0] == float(expected)


# A program built from parallel.h alone: what cannot be brought about from Python on demand (an exception in a worker,
# a fork() at the moment another thread makes the first pool). `operator new` is replaced so that the first pool's
# allocation, once armed, takes 300 ms: a fork() then lands inside pool()'s first call.
_POOL_HARNESS = r"""
#include "parallel.h"
#include <dirent.h>
#include <sys/syscall.h>
#include <sys/wait.h>
#include <unistd.h>
#include <atomic>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <new>
#include <string>

static std::atomic<int> slow_new{0};
void* operator new(size_t n) {
    if (slow_new.load() == 1 && n == sizeof(uskern::detail::Pool)) { slow_new = 2; usleep(300000); }
    if (void* p = std::malloc(n ? n : 1)) return p;
    throw std::bad_alloc();
}
void operator delete(void* p) noexcept { std::free(p); }
void operator delete(void* p, size_t) noexcept { std::free(p); }

// Threads of this process in state R (running or runnable: polling), this one left out.
static int polling_threads() {
    int n = 0;
    DIR* dir = opendir("/proc/self/task");
    while (dirent* e = readdir(dir)) {
        if (e->d_name[0] == '.' || atoi(e->d_name) == static_cast<int>(syscall(SYS_gettid))) continue;
        std::ifstream stat(std::string("/proc/self/task/") + e->d_name + "/stat");
        std::string line((std::istreambuf_iterator<char>(stat)), std::istreambuf_iterator<char>());
        const size_t paren = line.rfind(')');
        if (paren != std::string::npos && paren + 2 < line.size() && line[paren + 2] == 'R') ++n;
    }
    closedir(dir);
    return n;
}

int main(int argc, char** argv) {
    if (argc > 1 && std::strcmp(argv[1], "idle") == 0) {  // run with UNCERTSPLAT_KERNEL_SPIN_US=10000000
        uskern::run_workers(6, [](int64_t) {});  // five threads, polling after their call
        uskern::run_workers(2, [](int64_t) {});  // needs one of them
        usleep(300000);
        std::printf("polling %d\n", polling_threads());
        std::fflush(stdout);
        _exit(0);
    }
    if (argc > 1 && std::strcmp(argv[1], "throw") == 0) {
        std::atomic<int> done{0};
        int caught = 0;
        try {
            uskern::run_workers(3, [&](int64_t id) {
                if (id == 0) throw std::bad_alloc();
                usleep(200000);
                ++done;
            });
        } catch (const std::bad_alloc&) {
            caught = 1;
        }
        const int done_when_caught = done.load();
        usleep(400000);  // the helpers of the pool as it was: done by now
        std::atomic<int> after{0};
        uskern::run_workers(3, [&](int64_t) { ++after; });
        std::printf("caught %d done_when_caught %d pool_free %d after %d\n", caught, done_when_caught,
                    (int)uskern::detail::pool()->acquire(), after.load());
        return 0;
    }
    slow_new = 1;
    std::thread first([] { uskern::run_workers(2, [](int64_t) {}); });
    usleep(100000);  // inside the first pool's making
    const pid_t pid = fork();
    if (pid == 0) {
        alarm(5);
        std::atomic<int> n{0};
        uskern::run_workers(2, [&](int64_t) { ++n; });
        _exit(n == 2 ? 0 : 3);
    }
    int status = 0;
    waitpid(pid, &status, 0);
    first.join();
    std::printf("child %s\n", WIFEXITED(status) && WEXITSTATUS(status) == 0 ? "ok"
                                : WIFSIGNALED(status) ? "hung" : "failed");
    return 0;
}
"""


@pytest.fixture(scope="module")
def pool_harness(tmp_path_factory):
    cxx = native._compiler()
    if cxx is None:
        pytest.skip("no C++ compiler")
    folder = tmp_path_factory.mktemp("pool_harness")
    (folder / "harness.cpp").write_text(_POOL_HARNESS)
    exe = folder / "harness"
    subprocess.run([cxx, "-std=c++17", "-O1", "-pthread", f"-I{native.CSRC}", str(folder / "harness.cpp"), "-o",
                    str(exe)], check=True, capture_output=True, timeout=300)
    return exe


@pytest.mark.skipif(not os.path.isdir("/proc/self/task"), reason="needs /proc")
def test_threads_a_call_does_not_need_sleep(pool_harness):
    """A pool of five threads serving a call that needs one: the other four sleep instead of polling a core for
    UNCERTSPLAT_KERNEL_SPIN_US (made 10 s here, so that a polling thread is seen in state R); the one that ran polls
    for the next call, as intended."""
    env = {**os.environ, "UNCERTSPLAT_KERNEL_SPIN_US": "10000000"}
    out = subprocess.run([str(pool_harness), "idle"], capture_output=True, text=True, timeout=60, env=env).stdout
    assert out.strip() == "polling 1", out


def test_a_kernel_that_throws_returns_only_when_its_workers_are_done(pool_harness):
    """A worker's exception (std::bad_alloc, which the rasterizer's entry points turn into return code 2) reaches the
    caller after every worker finished (the workers use the caller's stack), and the pool serves the next call."""
    out = subprocess.run([str(pool_harness), "throw"], capture_output=True, text=True, timeout=60).stdout
    assert out.split() == ["caught", "1", "done_when_caught", "2", "pool_free", "1", "after", "3"], out


def test_a_fork_while_another_thread_makes_the_first_pool(pool_harness):
    """The child of a fork() made while another thread was inside the first pool's making runs its kernels (it
    waited forever for a lock held, in the child, by a thread that does not exist there)."""
    out = subprocess.run([str(pool_harness), "fork"], capture_output=True, text=True, timeout=60).stdout
    assert out.strip() == "child ok", out


def test_two_copies_of_the_library_keep_their_own_pool(tmp_path):
    """Two kernel libraries loaded side by side (ctypes loads RTLD_LOCAL; say two cache folders) each keep their own
    pool: the pool's slot was an STB_GNU_UNIQUE symbol, which the dynamic linker binds once per process, so the second
    library ran its own code on the first one's Pool (a different Pool layout there would be undefined behaviour)."""
    source = native.library()._name
    copies = [ctypes.CDLL(shutil.copy(source, tmp_path / f"copy{i}.so")) for i in range(2)]
    slots = []
    for lib in copies:
        try:
            slots.append(ctypes.addressof(ctypes.c_void_p.in_dll(lib, "_ZZN6uskern6detail9pool_slotEvE4slot")))
        except ValueError:  # not exported: the library's own
            pass
    assert len(set(slots)) == len(slots), "both libraries use one pool slot"
