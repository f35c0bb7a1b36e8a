"""``io.memory.available_memory``: the least of what the system, the cgroup and the address-space limit leave."""

import subprocess
import sys


def test_available_memory_is_bounded_by_an_address_space_limit():
    code = ("import resource; from uncertsplat.io.memory import available_memory; "
            "free = available_memory(); assert free is not None and free > 0, free; "
            "hard = resource.getrlimit(resource.RLIMIT_AS)[1]; "
            "cap = 8 << 30 if hard == resource.RLIM_INFINITY else min(8 << 30, hard); "
            "resource.setrlimit(resource.RLIMIT_AS, (cap, hard)); "
            "under = available_memory(); assert 0 <= under < cap and under <= free, (under, free); print('ok')")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr
