"""Native CPU kernels: built from ``csrc/*.cpp`` on first use into one library, loaded with ctypes.

``composite.h``: tile binning and the per-pixel compositing loop of the rasterizer, forward and backward
(``render/rasterize.py``), behind the C interface in ``composite_forward.cpp`` and ``composite_backward.cpp``.
``project.cpp``: the per-Gaussian front end, EWA projection and SH colours, forward and backward
(``render/project.py``, ``render/sh.py``). ``losses.cpp``: fused SSIM (``eval/image.py``) and the KL terms of the
offset tables (``gaussians/variational.py``), each with its gradient. ``optim.cpp``: Adam, dense over
several tensors in one call or on selected rows (``train/adam.py``). ``densify.cpp``: a step's densification
statistics (``strategy/densify.py``). ``sample.cpp``: a training step's Gaussians from the parameters and the
posterior's table terms (``gaussians/variational.py``), forward and backward. ``consistency.cpp``: the
view-consistency term's lookups of surface points in the compared training views (``uncertainty/consistency.py``).
``vmath.h``: vectorisable exp/log;
``parallel.h``: fork-join over threads.

The C++ files have a C ABI and no torch headers, so they need no Python build step: the system C++ compiler
(``$CXX``, else ``c++``) compiles each file in a process of its own, side by side, and links them (17.5 s on
2 cores; 25.5 s as one compiler call). The shared library is cached under ``$UNCERTSPLAT_CACHE_DIR`` (default
``$XDG_CACHE_HOME/uncertsplat`` or ``~/.cache/uncertsplat``) in a file named by a hash of the source, the
compiler, the flags and the CPU, so a change to any of them builds a new one and machines sharing a home folder
never load a library built for another CPU.

When no compiler is found, or the build fails, ``library()`` returns None once with a warning that says
why, and every caller uses its PyTorch implementation (same results, slower on CPU).
``UNCERTSPLAT_RASTERIZER=torch`` selects the PyTorch paths without trying.
"""

from __future__ import annotations

import contextlib
import ctypes
import hashlib
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import threading
import warnings
from pathlib import Path

import torch

INTERFACE_VERSION = 21
CSRC = Path(__file__).with_name("csrc")
# compiled side by side, one process each (``_build``): the two halves of the rasterizer take most of the time
SOURCES = (CSRC / "composite_forward.cpp", CSRC / "composite_backward.cpp", CSRC / "losses.cpp", CSRC / "project.cpp",
           CSRC / "optim.cpp", CSRC / "densify.cpp", CSRC / "sample.cpp", CSRC / "consistency.cpp")
HEADERS = (CSRC / "composite.h", CSRC / "vmath.h", CSRC / "parallel.h")
# -fno-trapping-math lets the compiler vectorise the float->int conversion inside the exp polynomial;
# -fopenmp-simd honours the `omp simd` hints without linking an OpenMP runtime (torch brings its own).
# -Wno-psabi: GCC notes that vectors wider than the target's registers are passed differently than by
# older GCCs; these are inlined internal helpers, never part of the library's C interface.
BASE_FLAGS = ("-O3", "-std=c++17", "-fPIC", "-shared", "-pthread", "-fopenmp-simd", "-fno-trapping-math",
              "-fno-math-errno", "-Wno-psabi")
ARCH_FLAGS = ("-march=native",)

_state: dict = {}
_per_thread = threading.local()  # single_threaded_torch's nesting depth and the count it lowered, per OS thread


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
    """``$CXX``, else the first of c++, g++ and clang++ on the PATH; a ``$CXX`` that is not found is said (it was
    passed over without a word, the kernels built with another compiler)."""
    given = os.environ.get("CXX", "").strip()
    if given and shutil.which(given):
        return shutil.which(given)
    for name in ("c++", "g++", "clang++"):
        if shutil.which(name):
            if given:
                print(f"warning: CXX={given} is not a compiler found on the PATH; building with {shutil.which(name)}",
                      file=sys.stderr, flush=True)
            return shutil.which(name)
    return None


def _compiler_version(cxx: str) -> str:
    try:
        return subprocess.run([cxx, "--version"], capture_output=True, text=True, timeout=30).stdout
    except (OSError, subprocess.SubprocessError):
        return ""


def _failure(cmd: list[str], output: str | None) -> str:
    """A failed compiler or linker call, for the reason ``library()`` reports: the command and its last output."""
    return f"{' '.join(cmd)}\n{(output or '').strip()[-2000:]}"


def _compile_all(cmds: list[list[str]]) -> str | None:
    """Run the compiler commands side by side (one process per source file: the build is bound by the compiler's
    single-threaded optimiser, so ``len(SOURCES)`` processes take about the longest file's time on enough cores).
    Returns None when every one succeeded, else the first failure's command and its last output."""
    procs: list[subprocess.Popen] = []
    try:
        for cmd in cmds:
            procs.append(subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True))
    except OSError:
        for proc in procs:  # none left running behind a failed start
            proc.kill()
            proc.wait()
        raise
    failure = None
    for cmd, proc in zip(cmds, procs, strict=True):
        try:
            out, _ = proc.communicate(timeout=300)
        except subprocess.TimeoutExpired:
            proc.kill()
            out = proc.communicate()[0] + "\n(stopped after 300 s)"
        if proc.returncode != 0 and failure is None:
            failure = _failure(cmd, out)
    return failure


def _build(cxx: str, target: Path) -> str | None:
    """Compile into ``target`` atomically; returns None on success, else the reason.

    Each source file is compiled to an object in a private temporary folder, all at once, then linked: the first
    use on a new machine waits for the compiler's work divided over the cores, not for its sum (the temporary
    folder goes, whatever happens)."""
    target.parent.mkdir(parents=True, exist_ok=True)
    last_err = ""
    compile_flags = tuple(f for f in BASE_FLAGS if f != "-shared")
    for arch in (ARCH_FLAGS, ()):  # retry without -march=native for compilers that lack it
        with tempfile.TemporaryDirectory(dir=target.parent, prefix=".build-") as work:
            objs = [str(Path(work) / f"{src.stem}.o") for src in SOURCES]
            cmds = [[cxx, *compile_flags, *arch, "-c", str(src), "-o", obj]
                    for src, obj in zip(SOURCES, objs, strict=True)]
            tmp = str(Path(work) / "kernels.so")
            try:
                err = _compile_all(cmds)
                if err is None:
                    link = [cxx, *BASE_FLAGS, *arch, *objs, "-o", tmp]
                    res = subprocess.run(link, capture_output=True, text=True, timeout=300)
                    if res.returncode != 0:
                        err = _failure(link, res.stderr or res.stdout)
            except (OSError, subprocess.SubprocessError) as exc:
                err = str(exc)
            if err is None:
                os.replace(tmp, target)
                return None
            last_err = err
    return f"the build failed: {last_err}"


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
        fwd_img = getattr(lib, f"us_forward_image_{suffix}")
        fwd_img.argtypes = head + [i64, i64, i64] + [ptr] * 14
        fwd_img.restype = ctypes.c_int
        bwd_img = getattr(lib, f"us_backward_image_{suffix}")
        bwd_img.argtypes = head + [i64, i64, i64, i64] + [ptr] * 16
        bwd_img.restype = ctypes.c_int
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
    lib.us_ssim_forward_f32.argtypes = [i64] * 5 + [ptr] * 4 + [f64, f64, ptr, ptr, ptr, i64]
    lib.us_ssim_forward_f32.restype = ctypes.c_int
    lib.us_ssim_target_stats_f32.argtypes = [i64] * 5 + [ptr] * 3 + [i64]
    lib.us_ssim_target_stats_f32.restype = ctypes.c_int
    lib.us_mean_sample_forward_f32.argtypes = [i64] + [ptr] * 9
    lib.us_mean_sample_forward_f32.restype = ctypes.c_int
    lib.us_mean_sample_backward_f32.argtypes = [i64] + [ptr] * 7
    lib.us_mean_sample_backward_f32.restype = ctypes.c_int
    lib.us_ssim_backward_f32.argtypes = [i64] * 5 + [ptr] * 7 + [i64]
    lib.us_ssim_backward_f32.restype = ctypes.c_int
    lib.us_sh_forward_f32.argtypes = [i64] * 4 + [ptr] * 4 + [i64]
    lib.us_sh_forward_f32.restype = ctypes.c_int
    lib.us_sh_backward_f32.argtypes = [i64] * 4 + [ptr] * 6 + [i64]
    lib.us_sh_backward_f32.restype = ctypes.c_int
    lib.us_sh2_forward_f32.argtypes = [i64] * 4 + [ptr] * 5 + [i64]
    lib.us_sh2_forward_f32.restype = ctypes.c_int
    lib.us_sh2_backward_f32.argtypes = [i64] * 4 + [ptr] * 8 + [i64]
    lib.us_sh2_backward_f32.restype = ctypes.c_int
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
    lib.us_adam_multi_f32.argtypes = [i64] + [ptr] * 7 + [f64, f64, f64, i64, i64, i64]
    lib.us_adam_multi_f32.restype = ctypes.c_int
    lib.us_densify_accumulate_f32.argtypes = [i64, i64, ptr, ptr, f64, f64, ptr, ptr, ptr]
    lib.us_densify_accumulate_f32.restype = ctypes.c_int
    lib.us_consistency_lookup_f32.argtypes = [i64] * 4 + [ptr] * 7 + [i64] + [f64] * 3 + [ptr] * 5 + [i64]
    lib.us_consistency_lookup_f32.restype = ctypes.c_int
    lib.us_version.restype = ctypes.c_int
    lib.us_max_features.restype = ctypes.c_int


def _check_spin_setting() -> None:
    """``UNCERTSPLAT_KERNEL_SPIN_US``, which the kernels' thread pool reads itself (``csrc/parallel.h``): microseconds
    its threads poll for the next call, a whole number >= 0. The C library would read a typo as 0 without a word."""
    value = os.environ.get("UNCERTSPLAT_KERNEL_SPIN_US")
    if value is not None and not value.strip().isdigit():
        from uncertsplat.errors import UserError

        raise UserError(f"UNCERTSPLAT_KERNEL_SPIN_US must be a whole number of microseconds >= 0, not {value!r}",
                        hint="Unset it (50 us) or set e.g. 0 (threads sleep at once between kernel calls).")


def library() -> ctypes.CDLL | None:
    """The loaded native kernels, building them on first use; None (with one warning) if unavailable."""
    if "lib" in _state:
        return _state["lib"]
    _check_spin_setting()
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
            # the first use on a machine waits for the compiler: said, not a silent pause
            print(f"building the native CPU kernels (once per machine and CPU, 15-40 s) into {target.parent}",
                  file=sys.stderr, flush=True)
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
    if lib is None and requested_backend() != "native":  # (native: the caller's error says it, not a fallback)
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
        # a setting of the user's environment: a message, not a traceback
        from uncertsplat.errors import UserError

        raise UserError(f"UNCERTSPLAT_RASTERIZER must be auto, native or torch, not {value!r}",
                        hint="Unset it (auto) or set one of those.")
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
            raise native_unavailable()
        return False
    return True


def native_unavailable():
    """The ``UserError`` of ``UNCERTSPLAT_RASTERIZER=native`` where the kernels cannot be built or loaded."""
    from uncertsplat.errors import UserError

    return UserError(f"UNCERTSPLAT_RASTERIZER=native, but the native kernels are unavailable: {unavailable_reason()}",
                     hint="Install a C++ compiler (g++, or set CXX to one), or unset UNCERTSPLAT_RASTERIZER to take the "
                          "PyTorch kernels (much slower on a CPU: docs/guide.md, \"Speed on a CPU\").")


def require_requested(device: torch.device | str) -> None:
    """Refuse ``UNCERTSPLAT_RASTERIZER=native`` on a CPU where the kernels are unavailable, before any work (a
    command's first kernel call raised it after the run folder was made); builds them if needed. Also refuses a
    bad value of the variable (``requested_backend``)."""
    if requested_backend() == "native" and torch.device(device).type == "cpu" and library() is None:
        raise native_unavailable()


def kernel_threads() -> int:
    """Threads a native kernel call uses: torch's intra-op thread count, or the count this thread had when
    ``single_threaded_torch`` lowered it."""
    return getattr(_per_thread, "kernel_threads", None) or torch.get_num_threads()


@contextlib.contextmanager
def single_threaded_torch(device: torch.device | str):
    """Inside: torch's own CPU ops run on one thread, the native kernels on as many threads as torch had.

    Between the kernels, a training step is a few hundred small torch ops on tensors of one value per
    Gaussian or per pixel (about 40k-300k elements); on 2 threads each one wakes the intra-op pool, which cost
    more than the arithmetic: a demo training step took x0.74 the time with those ops on one thread and the
    kernels on two (BENCHMARKS.md, "Torch's own ops on one thread"). The kernels run on their own threads, so
    they keep the parallelism where it pays. Nothing changes on other devices, without the native kernels,
    or when torch already runs on one thread.

    torch's thread count belongs to the OS thread that sets it (OpenMP's), so each thread lowers and restores its
    own, nested uses counted per thread: threads may enter and leave in any order (a pool over
    ``Predictor.predict`` calls) and each gets what it gets alone. torch also takes the count last set as the one a
    thread starts with: another thread whose first parallel torch op falls inside this window starts on one thread
    and keeps it (a host application's thread; docs/guide.md, "From Python")."""
    if torch.device(device).type != "cpu" or requested_backend() == "torch" or library() is None:
        yield
        return
    depth = getattr(_per_thread, "depth", 0)
    if depth == 0:
        before = torch.get_num_threads()
        _per_thread.kernel_threads = before if before > 1 else None
        if before > 1:
            torch.set_num_threads(1)
    _per_thread.depth = depth + 1
    try:
        yield
    finally:
        _per_thread.depth -= 1
        if _per_thread.depth == 0 and _per_thread.kernel_threads is not None:
            torch.set_num_threads(_per_thread.kernel_threads)
            _per_thread.kernel_threads = None


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
