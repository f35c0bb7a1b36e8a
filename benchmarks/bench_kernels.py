"""The native CPU kernels of this checkout against those of another revision, in one process.

The reference library is built from ``git show REF:uncertsplat/native/csrc/*`` with this checkout's compiler
flags, loaded beside the current one, and the two are called alternately on the same inputs (min and median of
``--repeats`` rounds; the machines are shared and noisy, so only ratios within a run are reported):

- ``render``: the whole ``render`` forward and forward + backward (projection, SH, binning, compositing, L1
  loss) of ``bench_render.make_scene``'s random scene (``--scene-n``, ``--width``, ``--height``);
- ``binning``: ``bin_gaussians`` alone on that scene and, with ``--run``, on a training view;
- ``composite``: the compositor's forward and backward alone on that scene's (tile, Gaussian) lists;
- ``ssim``: the fused SSIM forward and backward of three 320x240 planes, and of one 401x266 RGB image in its
  HWC layout (a bonsai training step's: the kernel reads the channels as planes in place);
- ``dense`` (with ``--dense``): the same on a denser scene (the Gaussians in the middle third of the view, sizes
  around 3 % of their depth), with a 2048^3 float32 matmul timed in the same run as the machine's yardstick;
- ``train`` (with ``--run RUN --scene SCENE``): training steps of a run from its last checkpoint, the two
  libraries taking turns every ``--block`` steps (the model keeps training across the turns), and the
  compositor alone on one of its training views (packed with a gradient on every feature, and into images with
  a loss on the rgb image alone, as a training step calls it).

A reference library of an older interface version is wrapped so that the current Python code can call it (the
compositor's forward took no Gaussian count before version 10, binning kept no state between its two calls
before 11); images and gradients of both are compared.

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/bench_kernels.py --ref 3adb8f7 [--run demo_out/train
        --scene demo_out/synth] [--threads 2] [--repeats 20] [--dense] [--one-thread-torch]

``--one-thread-torch`` times the kernels as training, ``evaluate`` and ``prune`` call them (torch's own ops on one
thread, the kernels on ``--threads``); without it torch's intra-op threads wait, spinning, between its ops while the
kernels' threads run, which on a 2-core machine slows both libraries alike.

Writes ``--out`` (default ``benchmarks/results/kernels.json``) and prints the Markdown rows for BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from datetime import date
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from _common import add_overwrite_option, refuse_overwrite  # noqa: E402
from bench_render import PARAMS, make_scene  # noqa: E402

from uncertsplat import native  # noqa: E402
from uncertsplat.eval.image import SSIM_C1_DEFAULT, SSIM_C2_DEFAULT, gaussian_window  # noqa: E402
from uncertsplat.render import rasterize, render  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results"
RENDER_MODULE = sys.modules["uncertsplat.render.render"]


_image_available = rasterize.composite_image_available


def _image_path_if_the_library_has_it(*args, **kw) -> bool:
    """render's fused image compositing only with a library that has its entry points: a reference built from a
    revision of interface < 14 has not, and renders through the packed compositor as the code of its day did."""
    return hasattr(native.library(), "us_forward_image_f32") and _image_available(*args, **kw)


RENDER_MODULE.composite_image_available = _image_path_if_the_library_has_it


def capture_render_inputs(fn) -> tuple:
    """(the arguments of render's bin_gaussians call, those of its compositor call as packed (gparams [G,6],
    feat [G,5], bins)) during ``fn()``; render's image-layout compositing (``composite_image``) is packed the
    same way, so that both libraries' compositors run on the same inputs."""
    captured = {}
    bin_original, comp_original = RENDER_MODULE.bin_gaussians, rasterize._CompositeNative.apply
    image_original = rasterize._CompositeImageNative.apply

    def bin_spy(*args, **kw):
        captured.setdefault("bin", (tuple(a.detach() if isinstance(a, torch.Tensor) else a for a in args), kw))
        return bin_original(*args, **kw)

    def comp_spy(gp, feat, bins):
        captured.setdefault("composite", (gp.detach().clone(), feat.detach().clone(), bins))
        return comp_original(gp, feat, bins)

    def image_spy(means2d, conics, log_o, colors, depths, background, bins, height, width):
        m2, con, lo, col, dep = (t.detach() for t in (means2d, conics, log_o, colors, depths))
        gp = torch.cat([m2, con, lo[..., None]], -1).reshape(-1, 6)
        feat = torch.cat([col, dep[..., None], torch.ones_like(dep)[..., None]], -1).reshape(-1, 5)
        captured.setdefault("composite", (gp, feat, bins))
        return image_original(means2d, conics, log_o, colors, depths, background, bins, height, width)

    RENDER_MODULE.bin_gaussians, rasterize._CompositeNative.apply = bin_spy, comp_spy
    rasterize._CompositeImageNative.apply = image_spy
    try:
        fn()
    finally:
        RENDER_MODULE.bin_gaussians, rasterize._CompositeNative.apply = bin_original, comp_original
        rasterize._CompositeImageNative.apply = image_original
    return captured["bin"], captured["composite"]


def binning_alone(libs: dict, args: tuple, kw: dict, repeats: int) -> dict:
    """``bin_gaussians`` with each library; the pairs must be the same."""
    outs = {k: with_lib(lib, lambda: rasterize.bin_gaussians(*args, **kw))() for k, lib in libs.items()}
    a, b = outs.values()
    if not (torch.equal(a.pair_gauss, b.pair_gauss) and torch.equal(a.pair_tile, b.pair_tile)):
        raise AssertionError("the two libraries list different (tile, Gaussian) pairs")
    return {"pairs": int(a.pair_gauss.numel()),
            "time": alternate({k: with_lib(lib, lambda: rasterize.bin_gaussians(*args, **kw))
                               for k, lib in libs.items()}, repeats)}


class _OldInterface:
    """A library of an older interface behind the current calls: before version 10 the compositor forward took
    no Gaussian count; before version 11 binning kept no state between its two calls (pass 2 tested again);
    before version 12 pass 2 always wrote pair_tile (today's callers pass a null pointer); before version 14
    SSIM read planes [B,H,W] only (today's callers pass HWC images and their channel count: the stand-in copies
    them into planes and the gradient back, as the Python code before version 14 did) and the compositor had no
    image entry points (``_image_path_if_the_library_has_it``: render takes the tile path); before version
    15 SSIM had no L1 term (the stand-in adds it with the tensor ops the Python code used before) and the
    compositor backward added into per-Gaussian sums its caller had zeroed (the stand-in zeroes them); before
    version 17 the pair indices were int64 (``pair_index_dtype``: the binning writes them so while it runs, and
    lists made by the other library are converted before it is timed on them)."""

    def __init__(self, lib: ctypes.CDLL, version: int):
        self._lib, self._version = lib, version
        self.pair_index_dtype = torch.int64 if version < 17 else torch.int32
        self._pairs = 0  # M of the last pass 1, for the pair_tile buffer an older pass 2 needs
        self._pair_tile = None

    def __getattr__(self, name):
        if name == "us_bin_free" and self._version < 11:
            return lambda state: None
        fn = getattr(self._lib, name)
        if self._version < 15 and name in ("us_ssim_forward_f32", "us_ssim_backward_f32"):
            older = _older_ssim(fn, backward=name.endswith("backward_f32"), planar=self._version < 14)
            return older if name.endswith("backward_f32") else _without_target_stats(older)
        if self._version < 19 and name == "us_ssim_forward_f32":
            return _without_target_stats(fn)
        if self._version < 19 and name.startswith("us_backward_image_"):
            return _rows_to_blocks(fn, torch.float64 if name.endswith("f64") else torch.float32)
        if self._version < 15 and name in ("us_backward_f32", "us_backward_f64"):
            size = 8 if name.endswith("f64") else 4

            def backward(*args):  # (head with F last, G, M, 10 pointers, g_gauss [G, 6 + F] last)
                ctypes.memset(args[-1], 0, args[9] * (6 + args[8]) * size)
                return fn(*args)
            return backward
        if self._version < 10 and name in ("us_forward_f32", "us_forward_f64"):
            return lambda *args: fn(*args[:9], *args[10:])  # (head, F, G, pointers) -> (head, F, pointers)
        if name.startswith("us_bin_count_"):
            def count(*args):
                self._pairs = fn(*(args if self._version >= 11 else args[:-1]))  # no state argument
                return self._pairs
            return count
        if name.startswith("us_bin_fill_"):
            def fill(*args):
                args = list(args)
                if args[-2] is None and self._version < 12:
                    self._pair_tile = torch.empty(max(self._pairs, 1), dtype=torch.long)
                    args[-2] = self._pair_tile.data_ptr()
                return fn(*(args if self._version >= 11 else args[:-1]))
            return fill
        return fn


def _rows_to_blocks(fn, dtype):
    """The image backward of interface < 19 behind today's call: it summed each Gaussian's gradient into rows [G, 11],
    today's into one block per input (``composite.h`` PLANAR_START); the rows are rearranged into the blocks after
    the call (a copy of 11 G numbers, about 2 % of the compositor's backward, which the code of that interface made
    downstream anyway: each input's strided gradient was copied by the kernel that read it)."""
    import numpy as np

    def call(*args):
        G = args[9]
        rows = torch.empty(G, 11, dtype=dtype)
        rc = fn(*args[:-1], rows.data_ptr())
        ctype = ctypes.c_double if dtype == torch.float64 else ctypes.c_float
        out = torch.from_numpy(np.ctypeslib.as_array(ctypes.cast(args[-1], ctypes.POINTER(ctype)), shape=(11 * G,)))
        for start, stop in ((0, 2), (2, 5), (5, 6), (6, 9), (9, 10), (10, 11)):
            out[start * G:stop * G].view(G, stop - start).copy_(rows[:, start:stop])
        return rc
    return call


def _without_target_stats(fn):
    """The SSIM forward of interface < 19 behind today's call: no ``ystats`` argument (the target's blurred mean and
    mean square, given by a caller that keeps them, e.g. training); that kernel blurs the target itself, as it did
    in every step before."""
    def call(B, H, W, K, CH, x, y, ystats, *rest):
        return fn(B, H, W, K, CH, x, y, *rest)
    return call


def _older_ssim(fn, backward: bool, planar: bool):
    """An SSIM entry point of interface < 15 behind today's call (HWC images and their channel count, the L1 term's
    output or gradient): before 14 (``planar``) the kernel read planes [B,H,W] only; the L1 term was tensor ops."""
    import numpy as np

    def view(ptr: int, shape: tuple, dtype=ctypes.c_float) -> torch.Tensor:
        return torch.from_numpy(np.ctypeslib.as_array(ctypes.cast(ptr, ctypes.POINTER(dtype)), shape=shape))

    def call(B, H, W, K, CH, x, y, w, *rest):
        shape = (B // CH, H, W, CH)
        xi, yi = view(x, shape), view(y, shape)
        if planar and CH > 1:
            xp, yp = (t.permute(0, 3, 1, 2).contiguous() for t in (xi, yi))
            x_arg, y_arg = xp.data_ptr(), yp.data_ptr()
        else:
            x_arg, y_arg = x, y
        head = (B, H, W, K) if planar else (B, H, W, K, CH)
        if not backward:
            c1, c2, plane_mean, partials, plane_l1, threads = rest
            rc = fn(*head, x_arg, y_arg, w, c1, c2, plane_mean, partials, threads)
            if plane_l1 is not None:
                view(plane_l1, (B,), ctypes.c_double).copy_((xi - yi).abs().mean(dim=(1, 2)).reshape(B))
            return rc
        partials, g_plane, g_l1, g_x, threads = rest
        gx = view(g_x, shape)
        if planar and CH > 1:
            gp = torch.empty(B // CH, CH, H, W)
            rc = fn(*head, x_arg, y_arg, w, partials, g_plane, gp.data_ptr(), threads)
            gx.copy_(gp.permute(0, 2, 3, 1))
        else:
            rc = fn(*head, x_arg, y_arg, w, partials, g_plane, g_x, threads)
        if g_l1 is not None:
            gx.add_(torch.sign(xi - yi) * view(g_l1, (B,)).view(B // CH, 1, 1, CH) / (H * W))
        return rc
    return call


class _Tolerant:
    """A library whose missing symbols are stand-ins (so that ``native._declare`` can run on an older one)."""

    def __init__(self, lib: ctypes.CDLL):
        self._lib = lib

    def __getattr__(self, name):
        try:
            return getattr(self._lib, name)
        except AttributeError:
            return type("Missing", (), {})()


def check_reference(ref: str) -> None:
    """Exit with a message when ``ref`` is no commit of this checkout (a shallow clone lacks the older ones) or has
    no native kernels, instead of a ``git`` traceback midway."""
    def git(*cmd: str) -> subprocess.CompletedProcess:
        return subprocess.run(["git", *cmd], cwd=ROOT, capture_output=True, text=True)

    if git("rev-parse", "--verify", "--quiet", f"{ref}^{{commit}}").returncode != 0:
        shallow = git("rev-parse", "--is-shallow-repository").stdout.strip() == "true"
        sys.exit(f"bench_kernels.py: the reference commit {ref!r} is not in this clone"
                 + (" (a shallow clone: fetch the full history with `git fetch --unshallow`, then run again)"
                    if shallow else " (check the revision; `git fetch` if it is on the remote)"))
    if git("ls-tree", "--name-only", f"{ref}:uncertsplat/native/csrc").returncode != 0:
        sys.exit(f"bench_kernels.py: revision {ref!r} has no uncertsplat/native/csrc (no native kernels to compare)")


def build_reference(ref: str, out_dir: Path):
    """Build the kernels of revision ``ref`` into ``out_dir``; returns the loaded library (wrapped if older)."""
    src = out_dir / "csrc"
    src.mkdir(parents=True, exist_ok=True)
    names = subprocess.run(["git", "ls-tree", "--name-only", f"{ref}:uncertsplat/native/csrc"], cwd=ROOT,
                           check=True, capture_output=True, text=True).stdout.split()
    for name in names:
        text = subprocess.run(["git", "show", f"{ref}:uncertsplat/native/csrc/{name}"], cwd=ROOT, check=True,
                              capture_output=True, text=True).stdout
        (src / name).write_text(text)
    target = out_dir / "reference.so"
    cmd = [native._compiler(), *native.BASE_FLAGS, *native.ARCH_FLAGS,
           *(str(src / n) for n in names if n.endswith(".cpp")), "-o", str(target)]
    subprocess.run(cmd, check=True, capture_output=True, text=True)
    lib = ctypes.CDLL(str(target))
    version = lib.us_version()
    native._declare(_Tolerant(lib))  # the symbols that kept their signatures
    i64, f64, ptr = ctypes.c_int64, ctypes.c_double, ctypes.c_void_p
    if version < 10:
        head = [i64, i64, i64, i64, i64, f64, f64, f64, i64]
        for suffix in ("f32", "f64"):
            getattr(lib, f"us_forward_{suffix}").argtypes = head + [ptr] * 8
    if version < 11:
        bin_head = [i64] * 9 + [f64]
        for suffix in ("f32", "f64"):
            getattr(lib, f"us_bin_count_{suffix}").argtypes = bin_head + [ptr] * 9
            getattr(lib, f"us_bin_fill_{suffix}").argtypes = bin_head + [ptr] * 5 + [i64] + [ptr] * 4
    if version < 15:
        k = 4 if version < 14 else 5  # the channel count came with version 14
        lib.us_ssim_forward_f32.argtypes = [i64] * k + [ptr] * 3 + [f64, f64, ptr, ptr, i64]
        lib.us_ssim_backward_f32.argtypes = [i64] * k + [ptr] * 6 + [i64]
    elif version < 19:  # no ystats
        lib.us_ssim_forward_f32.argtypes = [i64] * 5 + [ptr] * 3 + [f64, f64, ptr, ptr, ptr, i64]
    return (lib if version >= 19 else _OldInterface(lib, version)), version


def alternate(fns: dict, repeats: int) -> dict:
    """Seconds of each fn, called in turn ``repeats`` times after one warm-up each: min and median."""
    for fn in fns.values():
        fn()
    times = {k: [] for k in fns}
    for _ in range(repeats):
        for k, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            times[k].append(time.perf_counter() - t0)
    return {k: {"min_ms": 1e3 * min(v), "median_ms": 1e3 * statistics.median(v)} for k, v in times.items()}


def pair_index_dtype(lib) -> torch.dtype:
    return lib.pair_index_dtype if isinstance(lib, _OldInterface) else torch.int32


def with_lib(lib, fn):
    def call():
        native._state["lib"] = lib
        rasterize.PAIR_INDEX_DTYPE = pair_index_dtype(lib)
        return fn()
    return call


def bins_for(lib, bins: rasterize.TileBins) -> rasterize.TileBins:
    """``bins`` with the pair indices in the type ``lib`` reads (converted here, outside the timed calls)."""
    return replace(bins, pair_gauss=bins.pair_gauss.to(pair_index_dtype(lib)))


def make_dense_scene(n: int, width: int, height: int, seed: int = 0):
    """``make_scene`` with the Gaussians crowded into the middle third of the view and sizes around 3 % of their
    depth (issue 19's denser scene): many overlapping splats per tile, rays that stop early."""
    s, cams = make_scene(n, width, height, seed)
    g = torch.Generator().manual_seed(seed + 1)
    z = s.means[:, 2:3]
    xy = s.means[:, :2] / 3.0  # the middle third of the frustum at the same depths
    scales = 0.03 * z * torch.exp(0.2 * torch.randn(n, 3, generator=g))
    return replace(s, means=torch.cat([xy, z], -1), scales=scales), cams


def matmul_ms(repeats: int) -> dict:
    """A 2048^3 float32 matmul, the machine's yardstick in the same run."""
    a, b = torch.randn(2048, 2048), torch.randn(2048, 2048)
    return alternate({"matmul": lambda: a @ b}, repeats)["matmul"]


def bench_render_and_composite(libs: dict, n: int, width: int, height: int, repeats: int, dense: bool = False) -> dict:
    s, cams = (make_dense_scene if dense else make_scene)(n, width, height)
    target = torch.rand(1, height, width, 3, generator=torch.Generator().manual_seed(1))
    leaves = {k: getattr(s, k).detach().clone().requires_grad_() for k in PARAMS}
    sg = replace(s, **leaves)

    def fwd():
        with torch.no_grad():
            return render(s, cams)

    def fwd_bwd():
        for v in leaves.values():
            v.grad = None
        out = render(sg, cams)
        (out.rgb - target).abs().mean().backward()
        return out.rgb.detach(), {k: v.grad.clone() for k, v in leaves.items()}

    results = {"case": f"{width}x{height}, {n} Gaussians" + (", dense" if dense else "")}
    results["render_fwd"] = alternate({k: with_lib(lib, fwd) for k, lib in libs.items()}, repeats)
    results["render_fwd_bwd"] = alternate({k: with_lib(lib, fwd_bwd) for k, lib in libs.items()}, repeats)
    outs = {k: with_lib(lib, fwd_bwd)() for k, lib in libs.items()}
    (img_a, g_a), (img_b, g_b) = outs.values()
    results["max_image_difference"] = float((img_a - img_b).abs().max())
    results["max_relative_gradient_difference"] = max(
        float((g_a[k] - g_b[k]).abs().max() / g_a[k].abs().max().clamp_min(1e-30)) for k in g_a)
    (bin_args, bin_kw), comp = capture_render_inputs(with_lib(libs["current"], fwd))
    results["binning"] = binning_alone(libs, bin_args, bin_kw, repeats)
    results["composite"] = composite_alone(libs, *comp, repeats)
    return results


def composite_alone(libs: dict, gp, feat, bins, repeats: int) -> dict:
    """The compositor's forward, and forward + backward, on fixed lists (random gradient of the output)."""
    gpr, fr = gp.clone().requires_grad_(), feat.clone().requires_grad_()
    g = torch.randn(bins.tile_count.numel(), bins.tile_size ** 2, feat.shape[1],
                    generator=torch.Generator().manual_seed(0))

    def fwd(b):
        return lambda: rasterize._CompositeNative.apply(gp, feat, b)

    def fwd_bwd(b):
        def call():
            gpr.grad = fr.grad = None
            rasterize._CompositeNative.apply(gpr, fr, b).backward(g)
        return call

    own = {k: bins_for(lib, bins) for k, lib in libs.items()}
    out = {"pairs": int(bins.pair_gauss.numel()), "tiles": int(bins.tile_count.numel()),
           "forward": alternate({k: with_lib(lib, fwd(own[k])) for k, lib in libs.items()}, repeats),
           "forward_backward": alternate({k: with_lib(lib, fwd_bwd(own[k])) for k, lib in libs.items()}, repeats)}
    return out


def composite_image_alone(libs: dict, gp, feat, bins, height: int, width: int, repeats: int) -> dict:
    """The compositor as a training step calls it (``composite_image``: images, a loss on the rgb image alone),
    forward + backward on fixed lists; the two libraries' gradients are compared too."""
    n = gp.shape[0]
    ins = [gp[:, :2].reshape(1, n, 2), gp[:, 2:5].reshape(1, n, 3), gp[:, 5].reshape(1, n),
           feat[:, :3].reshape(1, n, 3), feat[:, 3].reshape(1, n)]
    g = torch.randn(1, height, width, 3, generator=torch.Generator().manual_seed(0))

    def fwd_bwd(b):
        def call():
            leaves = [t.clone().requires_grad_() for t in ins]
            rgb, _, _ = rasterize._CompositeImageNative.apply(*leaves, None, b, height, width)
            (rgb * g).sum().backward()
            return [t.grad for t in leaves]
        return call

    own = {k: bins_for(lib, bins) for k, lib in libs.items()}
    grads = {k: with_lib(lib, fwd_bwd(own[k]))() for k, lib in libs.items()}
    a, b = grads.values()
    return {"forward_backward": alternate({k: with_lib(lib, fwd_bwd(own[k])) for k, lib in libs.items()}, repeats),
            "max_gradient_difference": max(float((x - y).abs().max()) for x, y in zip(a, b, strict=True))}


def bench_ssim(libs: dict, repeats: int, planes: int = 3, height: int = 240, width: int = 320,
               channels: int = 1) -> dict:
    """SSIM forward and backward of ``planes`` planes: separate planes [planes,H,W] (``channels`` 1), or the
    ``channels`` of planes / channels HWC images."""
    gen = torch.Generator().manual_seed(0)
    shape = (planes, height, width) if channels == 1 else (planes // channels, height, width, channels)
    x = torch.rand(shape, generator=gen)
    y = (x + 0.1 * torch.randn(shape, generator=gen)).clamp(0, 1)
    win = gaussian_window(dtype=torch.float32)
    threads = native.kernel_threads()

    def forward(lib, ystats=None):
        def call():
            pm, part = torch.empty(planes, dtype=torch.float64), torch.empty(3, planes, height, width)
            lib.us_ssim_forward_f32(planes, height, width, win.numel(), channels, x.data_ptr(), y.data_ptr(),
                                    ystats.data_ptr() if ystats is not None else None, win.data_ptr(),
                                    SSIM_C1_DEFAULT, SSIM_C2_DEFAULT, pm.data_ptr(), part.data_ptr(), None, threads)
            return pm, part
        return call

    parts = {k: forward(lib)() for k, lib in libs.items()}

    def backward(lib, part):
        def call():
            gx, gp = torch.empty(shape), torch.ones(planes)
            lib.us_ssim_backward_f32(planes, height, width, win.numel(), channels, x.data_ptr(), y.data_ptr(),
                                     win.data_ptr(), part.data_ptr(), gp.data_ptr(), None, gx.data_ptr(), threads)
            return gx
        return call

    (pm_a, _), (pm_b, _) = parts.values()
    grads = [backward(lib, parts[k][1])() for k, lib in libs.items()]
    # the current kernels' forward with the target's blurred mean and mean square given (what training keeps for
    # its photos), against the reference's forward as it is
    ystats = torch.empty(2, planes, height, width)
    libs["current"].us_ssim_target_stats_f32(planes, height, width, win.numel(), channels, y.data_ptr(),
                                             win.data_ptr(), ystats.data_ptr(), threads)
    given = forward(libs["current"], ystats)()
    return {"case": f"{planes} planes of {width}x{height}" + (f", {channels} channels HWC" if channels > 1 else ""),
            "forward": alternate({k: forward(lib) for k, lib in libs.items()}, repeats),
            "forward_target_given": alternate({"reference": forward(libs["reference"]),
                                               "current": forward(libs["current"], ystats)}, repeats),
            "target_given_same_bits": bool(torch.equal(given[0], parts["current"][0])
                                           and torch.equal(given[1], parts["current"][1])),
            "backward": alternate({k: backward(lib, parts[k][1]) for k, lib in libs.items()}, repeats),
            "max_mean_difference": float((pm_a - pm_b).abs().max()),
            "max_gradient_difference": float((grads[0] - grads[1]).abs().max())}


def bench_training(libs: dict, run: Path, scene: Path, rounds: int, block: int) -> dict:
    """Training steps from the run's last checkpoint, the libraries taking turns every ``block`` steps."""
    from bench_train import trainer_from_run

    from uncertsplat.config import TrainConfig

    cfg = TrainConfig.model_validate_json((run / "config.json").read_text(encoding="utf-8"))
    trainer = trainer_from_run(scene, run, cfg, torch.device("cpu"), extra_steps=(rounds + 1) * block * len(libs) + 10)
    # every photo's SSIM statistics by the current library first (training keeps them from a photo's first step);
    # a reference of interface < 19 has no such kernel and blurs the photo in every step, as it did
    with_lib(libs["current"], lambda: [trainer.ssim_cache.get((i, False), trainer.train_images[i:i + 1])
                                       for i in range(trainer.train_images.shape[0])])()
    (bin_args, bin_kw), comp = capture_render_inputs(with_lib(libs["current"], trainer.train_step))
    per_step = {k: [] for k in libs}
    for r in range(rounds + 1):
        for k, lib in libs.items():
            native._state["lib"] = lib
            rasterize.PAIR_INDEX_DTYPE = pair_index_dtype(lib)
            t0 = time.perf_counter()
            for _ in range(block):
                trainer.train_step()
            if r:  # the first round warms up
                per_step[k].append((time.perf_counter() - t0) / block)
    return {"run": str(run), "num_gaussians": len(trainer.model), "block": block, "rounds": rounds,
            "step": {k: {"min_ms": 1e3 * min(v), "median_ms": 1e3 * statistics.median(v)}
                     for k, v in per_step.items()},
            "binning": binning_alone(libs, bin_args, bin_kw, 2 * rounds),
            "composite": composite_alone(libs, *comp, 2 * rounds),
            "composite_image": composite_image_alone(libs, *comp, trainer.train_cams.height, trainer.train_cams.width,
                                                     2 * rounds)}


def ratio(d: dict, key: str = "min_ms") -> float:
    return d["current"][key] / d["reference"][key]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--ref", required=True, help="git revision of the reference kernels")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--scene-n", type=int, default=50_000)
    ap.add_argument("--width", type=int, default=512)
    ap.add_argument("--height", type=int, default=384)
    ap.add_argument("--dense", action="store_true",
                    help="also the denser scene (middle third of the view, sizes ~3 %% of the depth) and a 2048^3 "
                         "matmul in the same run")
    ap.add_argument("--run", type=Path, help="a run folder: also time its training steps")
    ap.add_argument("--scene", type=Path, help="the scene of --run")
    ap.add_argument("--rounds", type=int, default=6)
    ap.add_argument("--block", type=int, default=10)
    ap.add_argument("--one-thread-torch", action="store_true",
                    help="render, binning, compositor and SSIM inside native.single_threaded_torch (torch's own "
                         "ops on one thread, the kernels on --threads), as training, evaluate and prune call them "
                         "since 2026-11-27; the matmul keeps torch's threads")
    ap.add_argument("--out", type=Path, default=RESULTS / "kernels.json")
    add_overwrite_option(ap)
    args = ap.parse_args()
    refuse_overwrite(args.out, overwrite=args.overwrite)
    torch.set_num_threads(args.threads)
    check_reference(args.ref)
    if native.library() is None:
        sys.exit(f"the native kernels are unavailable: {native.unavailable_reason()}")
    with tempfile.TemporaryDirectory() as tmp:
        ref_lib, ref_version = build_reference(args.ref, Path(tmp))
        libs = {"current": native.library(), "reference": ref_lib}
        result = {"date": date.today().isoformat(), "machine": platform.processor() or platform.machine(),
                  "cpu": native._cpu_signature()[:200], "torch": torch.__version__, "threads": args.threads,
                  "repeats": args.repeats, "reference": args.ref, "reference_interface": ref_version,
                  "load_average_start": os.getloadavg()}
        result["one_thread_torch"] = args.one_thread_torch

        def kernels_context():
            return native.single_threaded_torch("cpu") if args.one_thread_torch else contextlib.nullcontext()

        with kernels_context():
            result["render"] = bench_render_and_composite(libs, args.scene_n, args.width, args.height, args.repeats)
        if args.dense:
            with kernels_context():
                result["dense"] = bench_render_and_composite(libs, args.scene_n, args.width, args.height,
                                                             max(3, args.repeats // 4), dense=True)
            result["dense"]["matmul_2048"] = matmul_ms(args.repeats)
        with kernels_context():
            result["ssim"] = bench_ssim(libs, args.repeats)
            result["ssim_hwc"] = bench_ssim(libs, args.repeats, height=266, width=401, channels=3)
        if args.run:
            result["train"] = bench_training(libs, args.run, args.scene or Path(json.loads(
                (args.run / "train_summary.json").read_text(encoding="utf-8"))["scene"]), args.rounds, args.block)
        native._state["lib"] = libs["current"]
        rasterize.PAIR_INDEX_DTYPE = torch.int32
        result["load_average_end"] = os.getloadavg()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    r = result["render"]
    rows = [("render forward", r["render_fwd"]), ("render forward + backward", r["render_fwd_bwd"]),
            ("binning", r["binning"]["time"]),
            ("compositor forward", r["composite"]["forward"]),
            ("compositor forward + backward", r["composite"]["forward_backward"]),
            ("SSIM forward (3 x 320x240)", result["ssim"]["forward"]),
            ("SSIM backward", result["ssim"]["backward"]),
            ("SSIM forward (a 401x266 RGB image, HWC)", result["ssim_hwc"]["forward"]),
            ("SSIM forward, the target's statistics given (current) against blurred (reference)",
             result["ssim_hwc"]["forward_target_given"]),
            ("SSIM backward (the same)", result["ssim_hwc"]["backward"])]
    if "dense" in result:
        dn, mm = result["dense"], result["dense"]["matmul_2048"]
        rows += [("dense scene: render forward + backward", dn["render_fwd_bwd"]),
                 ("dense scene: compositor forward + backward", dn["composite"]["forward_backward"])]
        print(f"2048^3 float32 matmul in the same run: {mm['min_ms']:.1f} ({mm['median_ms']:.1f}) ms; dense render "
              f"fwd+bwd / matmul: reference x{dn['render_fwd_bwd']['reference']['min_ms'] / mm['min_ms']:.2f}, "
              f"current x{dn['render_fwd_bwd']['current']['min_ms'] / mm['min_ms']:.2f} (min)")
    if "train" in result:
        t = result["train"]
        rows += [(f"training step ({t['num_gaussians']} Gaussians)", t["step"]),
                 ("binning, a training view", t["binning"]["time"]),
                 ("compositor forward, a training view", t["composite"]["forward"]),
                 ("compositor forward + backward, a training view", t["composite"]["forward_backward"]),
                 ("compositor into images, forward + backward of an rgb loss (a training step's)",
                  t["composite_image"]["forward_backward"])]
    print(f"\n{r['case']}, {args.threads} threads, reference {args.ref}; min (median) ms")
    print("| what | reference | current | ratio (min) | ratio (median) |")
    print("|---|---|---|---|---|")
    for name, d in rows:
        print(f"| {name} | {d['reference']['min_ms']:.1f} ({d['reference']['median_ms']:.1f}) | "
              f"{d['current']['min_ms']:.1f} ({d['current']['median_ms']:.1f}) | x{ratio(d):.2f} | "
              f"x{ratio(d, 'median_ms'):.2f} |")
    print(f"images differ by at most {r['max_image_difference']:.2e}, gradients by {r['max_relative_gradient_difference']:.2e} "
          f"(relative); SSIM means by {result['ssim']['max_mean_difference']:.2e}")


if __name__ == "__main__":
    main()
