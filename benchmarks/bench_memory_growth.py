"""Training's memory as the model grows, and growth held before memory runs out (``Trainer._memory_limit``).

Two parts, each a set of ``uncertsplat train`` subprocesses on synthetic scenes (``uncertsplat synth --preset demo``
at the widths asked), one thread each:

1. ``--part cost``: the peak resident memory of short runs (120 steps, densification off, one posterior update and
   a checkpoint inside) with ``init_num_random`` = 0 and N random Gaussians at each width: the bytes an added
   Gaussian takes at a step's peak, against ``memory_per_gaussian`` (its parameters, table share and moments), is
   the factor ``strategy.budget.GROWN_GAUSSIAN_FACTOR`` must cover.
2. ``--part hold``: a run that densifies fast to a large budget, once without a limit and once under ``ulimit -v``
   below the first run's peak size: it must finish (memory holds its growth, ``budget.memory_hold`` in
   ``train_summary.json``) instead of running out.

Writes ``results/memory_growth_<label>.json``. Example (2-core CPU, about 25 minutes)::

    python benchmarks/bench_memory_growth.py --widths 320 640 1280 --gaussians 200000 --label s50

With ``--growth-test`` the hold part's runs keep the growth test on (a threshold no half reaches), so that its
copies of the training are made near the limit; ``--ulimit-v-kb`` runs only the limited run, at that limit (the
code before a change, by ``PYTHONPATH``, under the limit of a run of the code after it).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import RESULTS, add_overwrite_option, refuse_overwrite  # noqa: E402

CLI = [sys.executable, "-m", "uncertsplat"]


def scene(root: Path, width: int) -> Path:
    """The demo scene at ``width`` pixels wide (40 views), generated once under ``root``."""
    path = root / f"scene_w{width}"
    if not path.exists():
        subprocess.run([*CLI, "synth", str(path), "--preset", "demo", "--set", f"width={width}"], check=True,
                       stdout=subprocess.DEVNULL)
    return path


def train(scene_dir: Path, out: Path, args: list[str], vmem_kb: int | None = None) -> dict:
    """One ``train`` subprocess: its exit code, peak RSS and peak virtual size (MiB), seconds and summary."""
    shutil.rmtree(out, ignore_errors=True)

    def limit() -> None:
        if vmem_kb is not None:
            resource.setrlimit(resource.RLIMIT_AS, (vmem_kb * 1024, vmem_kb * 1024))

    t0 = time.perf_counter()
    log = out.parent / f"{out.name}.stderr.txt"
    with log.open("w") as err_file:
        proc = subprocess.Popen([*CLI, "train", str(scene_dir), "-o", str(out), *args], stdout=subprocess.DEVNULL,
                                stderr=err_file, env={**os.environ, "OMP_NUM_THREADS": "1"}, preexec_fn=limit)
        vm_peak = 0
        while True:
            pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
            if pid:
                break
            try:  # the peak virtual size: what ulimit -v bounds
                for line in Path(f"/proc/{proc.pid}/status").read_text().splitlines():
                    if line.startswith("VmPeak:"):
                        vm_peak = max(vm_peak, int(line.split()[1]))
            except OSError:
                pass
            time.sleep(0.3)
    proc.returncode = rc = os.waitstatus_to_exitcode(status)
    err = log.read_text(errors="replace")
    summary_file = out / "train_summary.json"
    summary = json.loads(summary_file.read_text()) if summary_file.exists() else {}
    row = {"rc": rc, "seconds": round(time.perf_counter() - t0, 1), "vm_peak_mb": round(vm_peak / 1024),
           "peak_rss_mb": round(usage.ru_maxrss / 1024, 1), "gaussians": summary.get("num_gaussians"),
           "memory_per_gaussian_bytes": summary.get("memory_per_gaussian_bytes"),
           "test_psnr": summary.get("test_psnr"), "budget": summary.get("budget"),
           "growth": [(g["step"], g["gaussians"], g["cost_db"]) for g in summary.get("growth", [])]}
    if rc:
        row["stderr_tail"] = err[-1500:]
    return row


def part_cost(root: Path, widths: list[int], gaussians: int) -> list[dict]:
    rows = []
    fixed = ["--iterations", "120", "--set", "densify.start=100000", "--set", "densify.until=100001",
             "--set", "variational.refresh_interval=100", "--set", "eval_every=100", "--set", "checkpoint_every=100"]
    for width in widths:
        sc = scene(root, width)
        runs = {n: train(sc, root / f"cost_{width}_{n}", [*fixed, "--set", f"init_num_random={n}"])
                for n in (0, gaussians)}
        a, b = runs[0], runs[gaussians]
        added = b["gaussians"] - a["gaussians"]
        per = (b["peak_rss_mb"] - a["peak_rss_mb"]) * 2**20 / added
        rows.append({"width": width, "runs": runs, "added": added, "peak_bytes_per_added_gaussian": round(per),
                     "factor": round(per / b["memory_per_gaussian_bytes"], 2)})
        print(json.dumps({k: v for k, v in rows[-1].items() if k != "runs"}), flush=True)
    return rows


def part_hold(root: Path, width: int, budget: int, iterations: int, under: float, growth_test: bool = False,
              vmem_kb: int | None = None) -> dict:
    """The free run, then one under ``ulimit -v`` at ``under`` x its peak size (or at ``vmem_kb`` given: the free run
    is skipped). ``growth_test``: the growth test on at a threshold no half reaches, a test at every interval, so its
    copies are made near the limit and none stops growth."""
    sc = scene(root, width)
    test = (["--set", "densify.growth_min_gain_db=0.000001", "--set", "densify.growth_skip_factor=null"]
            if growth_test else ["--set", "densify.growth_min_gain_db=0"])
    grow = ["--iterations", str(iterations), "--set", f"densify.max_gaussians={budget}",
            *test, "--set", "densify.grad_threshold=0.00003",
            "--set", f"eval_every={iterations // 2}", "--set", f"checkpoint_every={iterations // 2}"]
    free = None
    if vmem_kb is None:
        free = train(sc, root / "hold_free", grow)
        print(json.dumps({"free": {k: v for k, v in free.items() if k != "stderr_tail"}}), flush=True)
        vmem_kb = int(free["vm_peak_mb"] * under * 1024)
    limited = train(sc, root / "hold_limited", grow, vmem_kb=vmem_kb)
    print(json.dumps({"limited": limited, "ulimit_v_kb": vmem_kb}), flush=True)
    return {"width": width, "budget": budget, "iterations": iterations, "growth_test": growth_test,
            "ulimit_v_kb": vmem_kb, "free": free, "limited": limited}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--part", choices=["cost", "hold", "both"], default="both")
    ap.add_argument("--widths", type=int, nargs="+", default=[320, 640, 1280])
    ap.add_argument("--gaussians", type=int, default=200_000, help="random Gaussians added in the cost part")
    ap.add_argument("--hold-width", type=int, default=640)
    ap.add_argument("--hold-budget", type=int, default=400_000)
    ap.add_argument("--hold-iterations", type=int, default=1200)
    ap.add_argument("--under", type=float, default=0.73,
                    help="the limited run's ulimit -v as a share of the free run's peak virtual size")
    ap.add_argument("--growth-test", action="store_true",
                    help="hold part: the growth test on (its copies made near the limit) instead of off")
    ap.add_argument("--ulimit-v-kb", type=int, default=None,
                    help="hold part: this limit instead of --under x a free run's peak (no free run)")
    ap.add_argument("--workdir", type=Path, default=None, help="scenes and runs (default: a temporary folder)")
    ap.add_argument("--label", default="local")
    ap.add_argument("--machine", default=platform.processor() or platform.machine())
    add_overwrite_option(ap)
    args = ap.parse_args()
    out = RESULTS / f"memory_growth_{args.label}.json"
    refuse_overwrite(out, overwrite=args.overwrite)
    root = args.workdir or Path(tempfile.mkdtemp(prefix="bench_memory_growth_"))
    root.mkdir(parents=True, exist_ok=True)
    result = {"machine": args.machine, "date": datetime.date.today().isoformat(), "args": vars(args) | {
        "workdir": str(root)}}
    if args.part in ("cost", "both"):
        result["cost"] = part_cost(root, args.widths, args.gaussians)
    if args.part in ("hold", "both"):
        result["hold"] = part_hold(root, args.hold_width, args.hold_budget, args.hold_iterations, args.under,
                                   args.growth_test, args.ulimit_v_kb)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1, default=str) + "\n")
    print(f"wrote {out}")
    if args.workdir is None:
        shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
