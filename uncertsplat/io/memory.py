"""How much memory this process may still take: what sizes its work by the machine (SfM's feature threads)."""

from __future__ import annotations

import resource
from pathlib import Path


def available_memory() -> int | None:
    """Bytes this process may still allocate, or None where nothing says: the least of the system's available
    memory (``MemAvailable``), the room left under its cgroup's limit (a container's, a cluster job's) and its
    address-space limit (``ulimit -v``, less what it maps already)."""
    found: list[int] = []
    meminfo = _read("/proc/meminfo")
    for line in meminfo.splitlines():
        if line.startswith("MemAvailable:"):
            found.append(int(line.split()[1]) * 1024)
    limit, used = _read("/sys/fs/cgroup/memory.max").strip(), _read("/sys/fs/cgroup/memory.current").strip()
    if limit.isdigit() and used.isdigit():
        found.append(max(int(limit) - int(used), 0))
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    if soft != resource.RLIM_INFINITY:
        mapped = _read("/proc/self/statm").split()
        size = int(mapped[0]) * resource.getpagesize() if mapped and mapped[0].isdigit() else 0
        found.append(max(soft - size, 0))
    return min(found) if found else None


def _read(path: str) -> str:
    try:
        return Path(path).read_text(encoding="ascii", errors="replace")
    except OSError:
        return ""
