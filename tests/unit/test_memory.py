"""``io.memory``: the least of what the system, the cgroup and the address-space limit leave (``available_memory``),
and of it what a process that repeats its peaks may still add (``room_beyond_peak``)."""

import subprocess
import sys

UNDER_A_LIMIT = ("hard = resource.getrlimit(resource.RLIMIT_AS)[1]; "
                 "cap = 8 << 30 if hard == resource.RLIM_INFINITY else min(8 << 30, hard); "
                 "resource.setrlimit(resource.RLIMIT_AS, (cap, hard)); ")
"""Python that sets an address-space limit of at most 8 GiB (``cap``) in the process it runs in."""


def _run_ok(code: str) -> None:
    """Run ``code`` in a fresh interpreter (its limits and peaks its own); it prints "ok" at its end."""
    out = subprocess.run([sys.executable, "-c", code + "; print('ok')"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr


def test_available_memory_is_bounded_by_an_address_space_limit():
    _run_ok("import resource; from uncertsplat.io.memory import available_memory; "
            "free = available_memory(); assert free is not None and free > 0, free; " + UNDER_A_LIMIT +
            "under = available_memory(); assert 0 <= under < cap and under <= free, (under, free)")


def test_the_room_beyond_the_peak_leaves_out_what_the_process_takes_again():
    # a peak of 200 MB given back counts against the room though it is free now, until the peak is reset (a new
    # training's own peaks: trainer.reset_peak_memory); under an address-space limit the room is what the limit
    # leaves beyond the process's size now, less the same peak, and at most what it leaves beyond the largest size
    # the process had since the loop began
    _run_ok("import resource, torch; from uncertsplat.io.memory import available_memory, room_beyond_peak; "
            "from uncertsplat.train.trainer import reset_peak_memory; "
            "before = room_beyond_peak(); assert before is not None and before > 0, before; "
            "b = bytearray(200 << 20); b[::4096] = b'x' * len(b[::4096]); del b; "
            # the limits fixed, so the test reads what the peak takes off them and not other processes' memory
            "import uncertsplat.io.memory as m; rooms = m._rooms; m._rooms = lambda *a, **k: [10 << 30]; "
            "held = (10 << 30) - room_beyond_peak(); assert held >= 150 << 20, held; "
            "top = m.process_status()['VmHWM']; reset_peak_memory(torch.device('cpu')); "
            # (where /proc/self/clear_refs cannot be written the peak stays: nothing to check)
            "held = (10 << 30) - room_beyond_peak(); "
            "assert abs(held) < 50 << 20 or m.process_status()['VmHWM'] >= top, held; m._rooms = rooms; "
            + UNDER_A_LIMIT +
            "under = room_beyond_peak(); assert 0 <= under < cap, under; "
            # a size peak reached after the loop began (here: before any) is the loop's own: the room is below it;
            # one reached before it is not (the other limits fixed at 10 GiB, above the cap)
            "from uncertsplat.io.memory import process_size_peak; peak = process_size_peak(); "
            "m._rooms = lambda *a, **k: [10 << 30]; "
            "own = room_beyond_peak(0); assert own <= max(cap - peak, 0), (own, cap, peak); "
            "assert room_beyond_peak(peak) > cap, 'a peak of before is not the loop own'")


def _tree(root, cgroup: str, files: dict[str, str]):
    (root / "proc/self").mkdir(parents=True)
    (root / "proc/self/cgroup").write_text(cgroup)
    for rel, text in files.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_text(text)


def test_the_cgroup_room_is_read_from_the_process_s_own_group(tmp_path):
    """Only the mount's root files were read (a job's group and cgroup v1 were missed), and the usage counted the page
    cache the photos were read through (one thread of SfM left after hashing them)."""
    from uncertsplat.io.memory import cgroup_room

    v2 = tmp_path / "v2"
    _tree(v2, "0::/job.slice/job_7\n", {"sys/fs/cgroup/job.slice/job_7/memory.max": "8000000000\n",
                                         "sys/fs/cgroup/job.slice/job_7/memory.current": "7000000000\n",
                                         "sys/fs/cgroup/job.slice/job_7/memory.stat": "anon 1000000000\nfile 6000000000\n"})
    assert cgroup_room(v2) == 7_000_000_000
    v1 = tmp_path / "v1"
    _tree(v1, "12:cpu:/x\n4:memory:/process_api/abc\n", {
        "sys/fs/cgroup/memory/process_api/abc/memory.limit_in_bytes": "4000000000\n",
        "sys/fs/cgroup/memory/process_api/abc/memory.stat": "cache 10\nrss 5\ntotal_rss 1000000000\n"})
    assert cgroup_room(v1) == 3_000_000_000
    none = tmp_path / "none"
    _tree(none, "4:memory:/a\n", {"sys/fs/cgroup/memory/a/memory.limit_in_bytes": "9223372036854771712\n"})
    assert cgroup_room(none) is None
    max_v2 = tmp_path / "max"
    _tree(max_v2, "0::/\n", {"sys/fs/cgroup/memory.max": "max\n"})
    assert cgroup_room(max_v2) is None and cgroup_room(tmp_path / "nothing") is None


def test_the_room_beyond_the_peak_under_an_address_space_limit_in_numbers():
    """The limit less the process's size, plus what the C allocator holds free (taken again by the next loop), less
    what the resident peak holds above the resident memory now; and at most the limit less the largest size once the
    loop set that peak. The process's numbers are fixed, the other limits left out."""
    _run_ok("import resource; import uncertsplat.io.memory as m; " + UNDER_A_LIMIT +
            "MB = 1 << 20; "
            "m.process_status = lambda: {'VmRSS': 100 * MB, 'VmHWM': 150 * MB, 'VmSize': 1024 * MB, "
            "'VmPeak': 2048 * MB}; "
            "m._read = lambda path: ''; m.cgroup_room = lambda root=None: None; "
            "m.allocator_free_bytes = lambda: 300 * MB; "
            "got = m.room_beyond_peak(); want = cap - 1024 * MB + 300 * MB - 50 * MB; assert got == want, (got, want); "
            "got = m.room_beyond_peak(4096 * MB); assert got == want, (got, want); "  # the peak came before the loop
            "got = m.room_beyond_peak(0); want = min(want, cap - 2048 * MB); assert got == want, (got, want); "
            "got = m.available_memory(); assert got == cap - 1024 * MB, got")  # (nothing freed counted there)
