"""How often one incremental-mapping run finds the right geometry, and how often ``reconstruct``'s runs do.

Maps the features and matches of a ``reconstruct`` workspace (its ``database.db``) once per seed with the options
``reconstruct`` uses (``sfm.map_incremental``), summarises each run (``sfm.attempt_summary``: images, feature
observations, focal lengths), and calls a run right when it agrees (``sfm.attempts_agree``) with the run that
explains the most observations. Then it replays ``reconstruct``'s search for every start seed s of the list: runs
s, s+1, ... (at most ``--attempts``) until two agree, keep the one with the most observations
(``sfm.choose_attempt``), and counts how often the kept run is right and how many runs that took.

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/bench_mapping_seeds.py WORKSPACE PHOTOS [--seeds 8] [--tag bonsai]
    .venv/bin/python benchmarks/bench_mapping_seeds.py --runs benchmarks/results/mapping_seeds_bonsai.json

(``--runs``: the runs of an earlier results file, summarised and replayed again with today's rules, nothing mapped.)

Writes ``benchmarks/results/mapping_seeds_{tag}.json``.
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
import time
from datetime import date
from pathlib import Path

from _common import add_overwrite_option, refuse_overwrite

from uncertsplat.config import ReconstructConfig
from uncertsplat.sfm import reconstruct as sfm

ROOT = Path(__file__).resolve().parents[1]


def replay(runs: list[dict], start: int, attempts: int) -> tuple[int, int] | None:
    """(index of the kept run, runs used) of ``reconstruct``'s search starting at run ``start`` (seeds in order);
    None when the list ends before the search would."""
    done: list[dict] = []
    for k in range(attempts):
        if start + k >= len(runs):
            return None
        done.append(runs[start + k])
        if sfm.agreeing(done, len(done) - 1):
            break
    return start + sfm.choose_attempt(done, needed=0), len(done)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("workspace", type=Path, nargs="?", help="a reconstruct workspace (its database.db is read)")
    ap.add_argument("photos", type=Path, nargs="?", help="the photo folder it was made from")
    ap.add_argument("--runs", type=Path, help="replay the runs of an earlier results file instead of mapping")
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--attempts", type=int, default=ReconstructConfig().mapping_attempts)
    ap.add_argument("--tag", default="scene", help="results go to mapping_seeds_<tag>.json (with --runs: the replayed file's tag, so give --overwrite or another --tag)")
    ap.add_argument("--machine", default=platform.processor() or platform.machine())
    add_overwrite_option(ap)
    args = ap.parse_args()
    cfg = ReconstructConfig()
    runs, seconds = [], []
    if args.runs is not None:
        earlier = json.loads(args.runs.read_text(encoding="utf-8"))
        runs = [{k: v for k, v in r.items() if k not in ("right", "seconds")} for r in earlier["runs"]]
        seconds = [r["seconds"] for r in earlier["runs"]]
        args.workspace, args.machine = earlier["workspace"], earlier["machine"]
        args.tag = args.tag if args.tag != "scene" else args.runs.stem.removeprefix("mapping_seeds_")
        refuse_overwrite(ROOT / "benchmarks" / "results" / f"mapping_seeds_{args.tag}.json", overwrite=args.overwrite)
    elif args.workspace is None or args.photos is None:
        ap.error("give WORKSPACE and PHOTOS, or --runs")
    else:
        refuse_overwrite(ROOT / "benchmarks" / "results" / f"mapping_seeds_{args.tag}.json", overwrite=args.overwrite)
    with tempfile.TemporaryDirectory(prefix="uncertsplat-mapping-") as tmp:
        for seed in range(args.seeds if args.runs is None else 0):
            t0 = time.perf_counter()
            result = sfm.map_incremental(args.workspace / "database.db", args.photos, Path(tmp) / "models", cfg,
                                         seed=seed)
            seconds.append(time.perf_counter() - t0)
            runs.append(sfm.attempt_summary(result))
            r = runs[-1]
            print(f"seed {seed}: {seconds[-1]:.0f} s, {r['num_images']} images, {r['num_observations']} observations, "
                  f"focal {list(r['focal_lengths'].values())}, reprojection {r['mean_reprojection_error']}", flush=True)
    best = sfm.choose_attempt(runs, needed=0)
    right = [i == best or sfm.attempts_agree(runs[i], runs[best]) for i in range(len(runs))]
    replays = [replay(runs, s, args.attempts) for s in range(len(runs))]
    replays = [r for r in replays if r is not None]
    out = {"workspace": str(args.workspace), "date": str(date.today()), "machine": args.machine,
           "attempts": args.attempts, "agree": {"observations": sfm.AGREE_OBSERVATIONS, "focal": sfm.AGREE_FOCAL,
                                                "images": sfm.AGREE_IMAGES}, "runs": [{**r, "right": ok, "seconds": s}
                                               for r, ok, s in zip(runs, right, seconds, strict=True)],
           "single_run_right": sum(right) / len(right),
           "search_right": sum(right[k] for k, _ in replays) / len(replays) if replays else None,
           "search_runs_mean": sum(n for _, n in replays) / len(replays) if replays else None,
           "searches": len(replays), "map_seconds_mean": sum(seconds) / len(seconds)}
    print(json.dumps({k: v for k, v in out.items() if k != "runs"}, indent=1))
    path = ROOT / "benchmarks" / "results" / f"mapping_seeds_{args.tag}.json"
    path.write_text(json.dumps(out, indent=1) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
