"""How much memory this process may still take: what sizes its work by the machine (SfM's feature threads, the
warning before `train` loads its photos)."""

from __future__ import annotations

import ctypes
import functools
import resource
from pathlib import Path

V1_UNLIMITED = 1 << 60
"""cgroup v1 writes "no limit" as a number near 2^63: a limit at or above this is none."""


def available_memory() -> int | None:
    """Bytes this process may still allocate, or None where nothing says: the least of the system's available
    memory (``MemAvailable``), the room left under its cgroup's limit (``cgroup_room``: a container's, a cluster
    job's) and its address-space limit (``ulimit -v``, less what it maps already)."""
    found = _rooms()
    return min(found) if found else None


def room_beyond_peak(size_peak_before: int | None = None) -> int | None:
    """Bytes this process may still take beyond the most it took since its resident peak was last reset
    (``trainer.reset_peak_memory``), or None where nothing says: what a loop that repeats (a training step: a
    render's buffers are given back after it and taken again by the next) can add for good. ``available_memory``
    less what the resident peak (``VmHWM``) holds above the resident memory now (``VmRSS``). Under ``ulimit -v``:
    the limit less the process's size, plus what the C allocator holds free inside it (what an earlier loop freed,
    an ensemble's other member: it stays mapped and is taken again), but never more than the limit less the largest
    size the process had (``VmPeak``) once the loop itself set that peak (after ``size_peak_before``,
    ``process_size_peak`` when the loop began): freed in small pieces, free memory cannot serve a large buffer (a
    checkpoint's), and counted alone it let a run grow until its last checkpoint failed."""
    status = process_status()
    again = max(status.get("VmHWM", 0) - status.get("VmRSS", 0), 0)
    found = [room - again for room in _rooms(status, allocator_free=True)]
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    peak = status.get("VmPeak", 0)
    if soft != resource.RLIM_INFINITY and size_peak_before is not None and peak > size_peak_before:
        found.append(max(soft - peak, 0))
    return min(found) if found else None


def process_size_peak() -> int | None:
    """The largest size this process had so far (``VmPeak``, bytes; None where ``/proc`` does not say)."""
    return process_status().get("VmPeak")


def process_status() -> dict[str, int]:
    """``VmRSS``, ``VmHWM`` (the resident peak), ``VmSize`` and ``VmPeak`` of this process in bytes, those Linux's
    ``/proc/self/status`` gives (none elsewhere)."""
    status = {}
    for line in _read(Path("/proc/self/status")).splitlines():
        key, _, rest = line.partition(":")
        if key in ("VmRSS", "VmHWM", "VmSize", "VmPeak") and rest.split() and rest.split()[0].isdigit():
            status[key] = int(rest.split()[0]) * 1024  # kB
    return status


def _rooms(status: dict[str, int] | None = None, *, allocator_free: bool = False) -> list[int]:
    """Bytes left under each limit that says (``available_memory``'s); under ``ulimit -v`` the limit less the
    process's size (``VmSize`` of ``status``, read when None), with what the C allocator holds free counted as free
    where ``allocator_free``."""
    found: list[int] = []
    for line in _read(Path("/proc/meminfo")).splitlines():
        if line.startswith("MemAvailable:"):
            found.append(int(line.split()[1]) * 1024)
    room = cgroup_room()
    if room is not None:
        found.append(room)
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    if soft != resource.RLIM_INFINITY:
        size = (status if status is not None else process_status()).get("VmSize", 0)
        found.append(max(soft - size + (allocator_free_bytes() if allocator_free else 0), 0))
    return found


class _MallInfo2(ctypes.Structure):
    """glibc's ``struct mallinfo2`` (2.33 and newer)."""

    _fields_ = [(name, ctypes.c_size_t) for name in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                                      "fsmblks", "uordblks", "fordblks", "keepcost")]


@functools.cache
def _glibc():
    """The C library when it is glibc (``malloc_trim``), else None. Looked up once: ``find_library`` runs
    ``ldconfig -p`` (or a compiler) each time, a process started from a large one where memory is short."""
    import ctypes.util

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.malloc_trim  # noqa: B018 (it must be there)
    except (OSError, AttributeError):
        return None
    if hasattr(libc, "mallinfo2"):
        libc.mallinfo2.restype = _MallInfo2
    return libc


def allocator_free_bytes() -> int:
    """Bytes the C allocator holds free inside the process (glibc's ``mallinfo2().fordblks``; 0 where unknown):
    memory freed tensors left mapped, which later allocations take again."""
    libc = _glibc()
    if libc is None or not hasattr(libc, "mallinfo2"):  # (glibc 2.33 and newer)
        return 0
    return int(libc.mallinfo2().fordblks)


def release_free_memory() -> None:
    """Give the pages the C allocator holds free back to the system (glibc's ``malloc_trim``): what an earlier
    training in this process freed (an ensemble's member, a sweep's point) otherwise stays resident and counts
    against the next one's room."""
    libc = _glibc()
    if libc is not None:
        libc.malloc_trim(0)


def cgroup_room(root: Path = Path("/")) -> int | None:
    """Bytes left under the memory limit of this process's own cgroup (v2's ``memory.max``, v1's
    ``memory.limit_in_bytes``; the group ``/proc/self/cgroup`` names, else the mount's root), counting what its
    processes hold themselves (``anon``, v1's ``total_rss``: the page cache they read through is given back under
    pressure); None without a limit. ``root``: where the file system is (a test's copy)."""
    for line in _read(root / "proc/self/cgroup").splitlines():
        hierarchy, controllers, group = (line.split(":", 2) + ["", ""])[:3]
        v2 = hierarchy == "0" and controllers == ""
        if not v2 and "memory" not in controllers.split(","):
            continue
        mount = root / "sys/fs/cgroup" if v2 else root / "sys/fs/cgroup/memory"
        for folder in (mount / group.strip().lstrip("/"), mount):
            limit = _read(folder / ("memory.max" if v2 else "memory.limit_in_bytes")).strip()
            if not limit.isdigit() or int(limit) >= V1_UNLIMITED:
                continue
            stat = dict(row.split(" ", 1) for row in _read(folder / "memory.stat").splitlines() if " " in row)
            held = stat.get("anon" if v2 else "total_rss", "").strip()
            used = held if held.isdigit() else _read(
                folder / ("memory.current" if v2 else "memory.usage_in_bytes")).strip()
            return max(int(limit) - (int(used) if used.isdigit() else 0), 0)
    return None


def _read(path: Path) -> str:
    try:
        return path.read_text(encoding="ascii", errors="replace")
    except OSError:
        return ""
