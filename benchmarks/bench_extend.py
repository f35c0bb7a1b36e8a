"""New photos joining a trained run: ``reconstruct --extend`` then ``train --resume --add-views``.

Protocol: a photo folder without ``--withhold`` of its photos is reconstructed and a run trained on it
(``--steps`` steps, held-out views every 8th as usual); the withheld photos are then put into the folder,
``reconstruct --extend`` registers them into the workspace (timed against a full reconstruction of all the photos
into another workspace, whose cameras it is compared with: centre, rotation and focal differences after a
similarity alignment), and the run goes on for ``--more`` steps twice from the same checkpoint: with the new photos
added (``--add-views``) and without them. Both are evaluated on the run's held-out views (``evaluate``, K =
``--samples``): what the photos taken afterwards bring, against training longer on the photos there were.

    .venv/bin/python benchmarks/bench_extend.py --photos ../shared/datasets/fern/images --label fern \\
        --set scene.downscale=1.5873

Writes ``benchmarks/results/extend_<label>.json`` and prints the rows for BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import json
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

from _common import RESULTS, add_overwrite_option, refuse_overwrite

UNCERTSPLAT = [sys.executable, "-m", "uncertsplat"]


def call(*args: str) -> float:
    """Run an uncertsplat command (its output to the log), return its wall seconds."""
    t0 = time.perf_counter()
    with open(LOG, "a", encoding="utf-8") as log:
        log.write(f"\n$ uncertsplat {' '.join(args)}\n")
        log.flush()
        subprocess.run([*UNCERTSPLAT, *args], check=True, stdout=log, stderr=subprocess.STDOUT)
    return time.perf_counter() - t0


def metrics(run: Path) -> dict:
    m = json.loads((run / "eval" / "metrics.json").read_text(encoding="utf-8"))["mean"]
    return {k: m.get(k) for k in ("psnr", "psnr_render", "ause_mae", "nll", "calibration_error")}


def main() -> None:
    global LOG
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--photos", type=Path, required=True, help="the whole photo folder")
    ap.add_argument("--withhold", nargs="*", default=None,
                    help="photos taken 'afterwards' (default: every 6th from the 4th by name)")
    ap.add_argument("--label", default="fern")
    ap.add_argument("--out", type=Path, default=Path("/tmp/bench_extend"))
    ap.add_argument("--preset", default="paper")
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--more", type=int, default=2000)
    ap.add_argument("--samples", type=int, default=10)
    ap.add_argument("--set", action="append", default=[], help="key=value for train")
    ap.add_argument("--machine", default=platform.processor() or platform.machine())
    add_overwrite_option(ap)
    args = ap.parse_args()
    result_path = RESULTS / f"extend_{args.label}.json"
    refuse_overwrite(result_path, overwrite=args.overwrite)
    if args.out.exists():
        shutil.rmtree(args.out)
    args.out.mkdir(parents=True)
    LOG = args.out / "log.txt"
    names = sorted(p.name for p in args.photos.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png"))
    withheld = args.withhold if args.withhold is not None else names[3::6]
    photos, full = args.out / "photos", args.out / "all_photos"
    photos.mkdir()
    full.mkdir()
    for n in names:
        (full / n).symlink_to((args.photos / n).resolve())
        if n not in withheld:
            (photos / n).symlink_to((args.photos / n).resolve())
    ws, ws_full, run = args.out / "ws", args.out / "ws_full", args.out / "run"
    sets = [x for s in args.set for x in ("--set", s)]
    t_first = call("reconstruct", str(photos), "-o", str(ws))
    call("train", str(ws), "-o", str(run), "--preset", args.preset, "--iterations", str(args.steps), *sets)
    call("evaluate", str(run), "--num-samples", str(args.samples))
    before = metrics(run)
    plain = args.out / "run_plain"
    shutil.copytree(run, plain)
    for n in withheld:
        (photos / n).symlink_to((args.photos / n).resolve())
    t_extend = call("reconstruct", str(photos), "-o", str(ws), "--extend")
    t_full = call("reconstruct", str(full), "-o", str(ws_full))
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from uncertsplat.sfm import reconstruct as sfm

    agreement = sfm.pose_accuracy(ws / "sparse" / "0", ws_full / "sparse" / "0")
    report = json.loads((ws / "reconstruct_report.json").read_text(encoding="utf-8"))
    added = sorted(set(withheld) & set(report["images_registered"]))
    total = str(args.steps + args.more)
    t_added = call("train", str(ws), "-o", str(run), "--resume", "--iterations", total, "--add-views", ",".join(added))
    t_plain = call("train", str(ws), "-o", str(plain), "--resume", "--iterations", total)
    for r in (run, plain):
        call("evaluate", str(r), "--num-samples", str(args.samples))
    held = json.loads((run / "scene.json").read_text(encoding="utf-8"))["test"]
    assert held == json.loads((plain / "scene.json").read_text(encoding="utf-8"))["test"]
    out = {"label": args.label, "machine": args.machine, "date": time.strftime("%Y-%m-%d"), "photos": len(names),
           "withheld": withheld, "added": added, "held_out": held, "steps": args.steps, "more": args.more,
           "set": args.set, "seconds": {"reconstruct_first": t_first, "extend": t_extend, "reconstruct_all": t_full,
                                        "resume_added": t_added, "resume_plain": t_plain},
           "extended_vs_full_reconstruction": agreement,
           "metrics": {"before": before, "added": metrics(run), "plain": metrics(plain)}}
    result_path.write_text(json.dumps(out, indent=1))
    print(f"wrote {result_path}")
    print(f"extend {t_extend:.1f} s against a full reconstruction {t_full:.1f} s (x{t_extend / t_full:.2f}); "
          f"cameras against it: centres {agreement['centre_error_max_pct']:.3f} % max, rotations "
          f"{agreement['rotation_error_max_deg']:.3f} deg max, focal {agreement['focal_error_mean_pct']:.2f} %")
    print("| run | steps | held-out PSNR (expected render) | AUSE-MAE | NLL | cal. err | machine | date |")
    print("|---|---|---|---|---|---|---|---|")
    for key, what, steps in (("before", f"{len(names) - len(withheld)} photos", args.steps),
                             ("plain", "the same photos, trained on", total),
                             ("added", f"+ {len(added)} photos joined (--extend, --add-views)", total)):
        m = out["metrics"][key]
        print(f"| {what} | {steps} | {m['psnr_render']:.2f} | {m['ause_mae']:.3f} | {m['nll']:.3f} | "
              f"{m['calibration_error']:.3f} | {args.machine} | {out['date']} |")


if __name__ == "__main__":
    main()
