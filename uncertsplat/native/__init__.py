"""Native CPU kernels: built from ``csrc/*.cpp`` on first use into one library, loaded with ctypes.

``composite.cpp``: tile binning and the per-pixel compositing loop of the rasterizer, forward and
backward (``render/rasterize.py``). ``project.cpp``: the per-Gaussian front end, EWA projection and SH
colours, forward and backward (``render/project.py``, ``render/sh.py``). ``losses.cpp``: fused SSIM
(``eval/image.py``) and the KL terms of the offset tables (``gaussians/variational.py``), each with its
gradient. ``optim.cpp``: Adam on selected rows (``train/sparse_adam.py``). ``vmath.h``: vectorisable
exp/log; ``parallel.h``: fork-join over threads.

The C++ files have a C ABI and no torch headers, so they compile in a few seconds with the system C++
compiler (``$CXX``, else ``c++``) and need no Python build step. The shared library is cached under
``$UNCERTSPLAT_CACHE_DIR`` (default ``$XDG_CACHE_HOME/uncertsplat`` or ``~/.cache/uncertsplat``) in a
file named by a hash of the source, the compiler, the flags and the CPU, so a change to any of them
builds a new one and machines sharing a home folder never load a library built for another CPU.

When no compiler is found, or the build fails, ``library()`` returns None once with a warning that says
why, and every caller uses its PyTorch implementation (same results, slower on CPU).
``UNCERTSPLAT_RASTERIZER=torch`` selects the PyTorch paths without trying.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import shutil
import subprocess
import tempfile
import warnings
from pathlib import Path

import torch

INTERFACE_VERSION = 13
CSRC = Path(__file__).with_name("csrc")
SOURCES = (CSRC / "composite.cpp", CSRC / "losses.cpp", CSRC / "project.cpp", CSRC / "optim.cpp")
HEADERS = (CSRC / "vmath.h", CSRC / "parallel.h")
# -fno-trapping-math lets the compiler vectorise the float->int conversion inside the exp polynomial;
# -fopenmp-simd honours the `omp simd` hints without linking an OpenMP runtime (torch brings its own).
# -Wno-psabi: GCC notes that vectors wider than the target's registers are passed differently than by
# older GCCs; these are inlined internal helpers, never part of the library's C interface.
BASE_FLAGS = ("-O3", "-std=c++17", "-fPIC", "-shared", "-pthread", "-fopenmp-simd", "-fno-trapping-math",
              "-fno-math-errno", "-Wno-psabi")
ARCH_FLAGS = ("-march=native",)

_state: dict = {}


def cache_dir() -> Path:
    """Where built libraries are kept."""
    env = os.environ.get("UNCERTSPLAT_CACHE_DIR")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "uncertsplat"


def _cpu_signature() -> str:
    """Machine and CPU model/flags: part of the cache key because of -march=native."""
    sig = platform.machine()
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
            for line in f:
                if line.startswith(("model name", "flags", "Features")):
                    sig += line.strip()
                if line.strip() == "":
                    break  # the first processor is enough
    except OSError:
        sig += platform.processor()
    return sig


def _compiler() -> str | None:
    for name in (os.environ.get("CXX"), "c++", "g++", "clang++"):
        if name and shutil.which(name):
            return shutil.which(name)
    return None


def _compiler_version(cxx: str) -> str:
    try:
        return subprocess.run([cxx, "--version"], capture_output=True, text=True, timeout=30).stdout
    except (OSError, subprocess.SubprocessError):
        return ""


def _build(cxx: str, target: Path) -> str | None:
    """Compile into ``target`` atomically; returns None on success, else the reason."""
    target.parent.mkdir(parents=True, exist_ok=True)
    last_err = ""
    for arch in (ARCH_FLAGS, ()):  # retry without -march=native for compilers that lack it
        fd, tmp = tempfile.mkstemp(suffix=".so", dir=target.parent)
        os.close(fd)
        cmd = [cxx, *BASE_FLAGS, *arch, *(str(s) for s in SOURCES), "-o", tmp]
        try:
            res = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
        except (OSError, subprocess.SubprocessError) as err:
            res, last_err = None, str(err)
        if res is not None and res.returncode == 0:
            os.replace(tmp, target)
            return None
        if res is not None:
            last_err = (res.stderr or res.stdout).strip()[-2000:]
        Path(tmp).unlink(missing_ok=True)
    return f"the build failed: {' '.join(cmd)}\n{last_err}"


def _declare(lib: ctypes.CDLL) -> None:
    i64, f64, ptr = ctypes.c_int64, ctypes.c_double, ctypes.c_void_p
    head = [i64, i64, i64, i64, i64, f64, f64, f64, i64]
    for suffix in ("f32", "f64"):
        fwd = getattr(lib, f"us_forward_{suffix}")
        fwd.argtypes = head + [i64] + [ptr] * 8
        fwd.restype = ctypes.c_int
        bwd = getattr(lib, f"us_backward_{suffix}")
        bwd.argtypes = head + [i64, i64] + [ptr] * 10
        bwd.restype = ctypes.c_int
    bin_head = [i64] * 9 + [f64]
    for suffix in ("f32", "f64"):
        count = getattr(lib, f"us_bin_count_{suffix}")
        count.argtypes = bin_head + [ptr] * 9 + [ctypes.POINTER(ptr)]
        count.restype = i64
        fill = getattr(lib, f"us_bin_fill_{suffix}")
        fill.argtypes = bin_head + [ptr] * 5 + [i64] + [ptr] * 5
        fill.restype = ctypes.c_int
    lib.us_bin_free.argtypes = [ptr]
    lib.us_bin_free.restype = None
    lib.us_gaussian_kl_f32.argtypes = [i64, ptr, ptr, f64, f64, ptr, ptr, i64]
    lib.us_gaussian_kl_f32.restype = f64
    lib.us_scale_kl_f32.argtypes = [i64, ptr, ptr, f64, i64, f64, f64, ptr, ptr, i64]
    lib.us_scale_kl_f32.restype = f64
    lib.us_ssim_forward_f32.argtypes = [i64] * 4 + [ptr] * 3 + [f64, f64, ptr, ptr, i64]
    lib.us_ssim_forward_f32.restype = ctypes.c_int
    lib.us_ssim_backward_f32.argtypes = [i64] * 4 + [ptr] * 6 + [i64]
    lib.us_ssim_backward_f32.restype = ctypes.c_int
    lib.us_sh_forward_f32.argtypes = [i64] * 4 + [ptr] * 4 + [i64]
    lib.us_sh_forward_f32.restype = ctypes.c_int
    lib.us_sh_backward_f32.argtypes = [i64] * 4 + [ptr] * 6 + [i64]
    lib.us_sh_backward_f32.restype = ctypes.c_int
    lib.us_project_forward_f32.argtypes = [i64, i64] + [ptr] * 6 + [i64, i64, f64, f64, f64, f64] + [ptr] * 5 + [i64]
    lib.us_project_forward_f32.restype = ctypes.c_int
    lib.us_project_backward_f32.argtypes = [i64, i64] + [ptr] * 5 + [i64, i64, f64, f64, f64] + [ptr] * 6 + [i64]
    lib.us_project_backward_f32.restype = ctypes.c_int
    lib.us_blur_peak_forward_f32.argtypes = [i64, i64] + [ptr] * 5 + [i64, i64, f64, f64, f64, ptr, i64]
    lib.us_blur_peak_forward_f32.restype = ctypes.c_int
    lib.us_blur_peak_backward_f32.argtypes = [i64, i64] + [ptr] * 5 + [i64, i64, f64, f64, f64] + [ptr] * 4 + [i64]
    lib.us_blur_peak_backward_f32.restype = ctypes.c_int
    lib.us_adam_rows_f32.argtypes = [i64, i64, i64] + [ptr] * 6 + [i64, f64, f64, f64, f64, i64]
    lib.us_adam_rows_f32.restype = ctypes.c_int
    lib.us_version.restype = ctypes.c_int
    lib.us_max_features.restype = ctypes.c_int


def library() -> ctypes.CDLL | None:
    """The loaded native kernels, building them on first use; None (with one warning) if unavailable."""
    if "lib" in _state:
        return _state["lib"]
    lib, reason = None, None
    cxx = _compiler()
    if cxx is None:
        reason = "no C++ compiler found (set CXX, or install g++)"
    else:
        key = hashlib.sha256()
        for src in SOURCES + HEADERS:
            key.update(src.read_bytes())
        key.update(_compiler_version(cxx).encode())
        key.update(" ".join(BASE_FLAGS + ARCH_FLAGS).encode())
        key.update(_cpu_signature().encode())
        target = cache_dir() / "native" / f"kernels-{key.hexdigest()[:16]}.so"
        if not target.is_file():
            try:
                reason = _build(cxx, target)
            except OSError as err:  # unwritable cache folder, disk full
                reason = f"could not write {target.parent}: {err}"
        if reason is None:
            try:
                lib = ctypes.CDLL(str(target))
                _declare(lib)
                if lib.us_version() != INTERFACE_VERSION:
                    reason, lib = f"{target} has interface version {lib.us_version()}, not {INTERFACE_VERSION}", None
            except (OSError, AttributeError) as err:
                reason, lib = f"could not load {target}: {err}", None
    if lib is None:
        warnings.warn(f"native CPU kernels unavailable, using the PyTorch implementations (slower): {reason}", stacklevel=2)
    _state["lib"], _state["reason"] = lib, reason
    return lib


def unavailable_reason() -> str | None:
    """Why ``library()`` returned None (None when it is loaded or was not tried)."""
    return _state.get("reason")


def requested_backend() -> str:
    """``UNCERTSPLAT_RASTERIZER``: ``auto`` (default: native kernels on CPU when they build), ``native`` or
    ``torch``. It selects the implementation of every native kernel (rasterizer, SSIM, KL)."""
    value = os.environ.get("UNCERTSPLAT_RASTERIZER", "auto").strip().lower() or "auto"
    if value not in ("auto", "native", "torch"):
        raise ValueError(f"UNCERTSPLAT_RASTERIZER must be auto, native or torch, not {value!r}")
    return value


def use_for(*tensors: torch.Tensor, backend: str | None = None, supported: bool = True, unsupported: str = "",
            dtypes: tuple = (torch.float32, torch.float64), strict: bool = True) -> bool:
    """Whether a native kernel takes these inputs.

    backend: ``"auto"`` (native for CPU tensors of one of ``dtypes`` when the kernels build),
    ``"native"`` (the same, but an error when they cannot be used) or ``"torch"``; None reads
    ``UNCERTSPLAT_RASTERIZER``. ``supported``: the caller's own condition on the inputs, described by
    ``unsupported`` in the error message. ``strict=False``: ``"native"`` acts as ``"auto"`` (for helpers
    such as SSIM whose unsupported cases simply take the PyTorch path).
    """
    backend = backend or requested_backend()
    if backend == "torch":
        return False
    if backend == "native" and not strict:
        backend = "auto"
    found = {t.dtype for t in tensors}
    fits = (supported and all(t.device.type == "cpu" for t in tensors) and len(found) == 1
            and found <= set(dtypes))
    if not fits:
        if backend == "native":
            names = " or ".join(str(d).replace("torch.", "") for d in dtypes)
            raise ValueError(f"the native kernels need CPU tensors of one dtype ({names}){unsupported}")
        return False
    if library() is None:
        if backend == "native":
            raise RuntimeError(f"the native kernels are unavailable: {unavailable_reason()}")
        return False
    return True


def describe(device: torch.device | str) -> str:
    """Which kernels run on ``device``, in words (for logs and run summaries)."""
    if torch.device(device).type != "cpu":
        return "PyTorch kernels"
    backend = requested_backend()
    if backend == "torch":
        return "PyTorch kernels (UNCERTSPLAT_RASTERIZER=torch)"
    if library() is None:
        return f"PyTorch kernels (native unavailable: {unavailable_reason()})"
    return "native CPU kernels"
