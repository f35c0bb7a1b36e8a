"""Benchmark ``uncertsplat reconstruct``: seconds per stage, registered fraction and pose accuracy.

Scenes: the synthetic demo scene (generated here; GT cameras), LLFF fern (reference poses in
poses_bounds.npy) and Mip-NeRF 360 bonsai (no reference), from ``../shared/datasets``.

    .venv/bin/python benchmarks/bench_reconstruct.py [--scenes synthetic-demo fern bonsai] [--threads -1]

Writes ``benchmarks/results/reconstruct.json`` and prints the Markdown rows for BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import add_overwrite_option, refuse_overwrite

from uncertsplat.config import ReconstructConfig, SynthConfig
from uncertsplat.sfm import reconstruct as sfm
from uncertsplat.stages import reconstruct as stage

ROOT = Path(__file__).resolve().parents[1]
DATASETS = ROOT / "../shared/datasets"
RESULTS = ROOT / "benchmarks" / "results" / "reconstruct.json"


def llff_centres(folder: Path) -> dict[str, np.ndarray]:
    """Image name -> camera centre from LLFF's poses_bounds.npy (column 3 of each 3x5 matrix)."""
    mats = np.load(folder / "poses_bounds.npy")[:, :15].reshape(-1, 3, 5)
    names = sorted(p.name for p in (folder / "images").iterdir())
    return {n: m[:, 3].astype(np.float64) for n, m in zip(names, mats, strict=True)}


def centre_error(ws: Path, gt: dict[str, np.ndarray]) -> dict[str, float]:
    """Max and mean camera-centre error after a similarity alignment, as fractions of the scene radius."""
    est = sfm.camera_centers(ws / "sparse" / "0")
    names = sorted(set(est) & set(gt))
    src, dst = np.stack([est[n] for n in names]), np.stack([gt[n] for n in names])
    s, r, t = sfm.similarity_align(src, dst)
    err = np.linalg.norm(s * src @ r.T + t - dst, axis=1)
    radius = float(np.linalg.norm(dst - dst.mean(0), axis=1).max())
    return {"centre_err_max": float(err.max() / radius), "centre_err_mean": float(err.mean() / radius)}


def bench_scene(name: str, work: Path, threads: int) -> dict:
    cfg = ReconstructConfig(num_threads=threads)
    gt = None
    extra: dict = {}
    if name == "synthetic-demo":
        from uncertsplat.data.synthetic import generate_scene

        t0 = time.perf_counter()
        scene = generate_scene(work / "synthetic-demo", SynthConfig(preset="demo"))
        extra["generate_seconds"] = round(time.perf_counter() - t0, 2)
        photos = scene / "images"
        gt = sfm.camera_centers(scene / "sparse" / "0")
    else:
        folder = DATASETS / name
        if not (folder / "images").is_dir():
            print(f"skip {name}: {folder.resolve()} not found")
            return {}
        photos = folder / "images"
        if (folder / "poses_bounds.npy").is_file():
            gt = llff_centres(folder)
    report = stage.run(photos, work / f"ws-{name}", cfg)
    row = {
        "scene": name,
        "images": len(report.images_found),
        "registered": len(report.images_registered),
        "registered_fraction": report.registered_fraction,
        "models_found": report.models_found,
        "points3d": report.num_points3d,
        "mean_reprojection_error": report.mean_reprojection_error,
        "mean_track_length": report.mean_track_length,
        "matcher": report.matcher,
        "retried_relaxed": report.retried_relaxed,
        "stage_seconds": report.stage_seconds,
        "total_seconds": report.total_seconds,
        **extra,
    }
    if gt is not None:
        row.update(centre_error(work / f"ws-{name}", gt))
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["synthetic-demo", "fern", "bonsai"])
    ap.add_argument("--threads", type=int, default=-1)
    ap.add_argument("--machine", default=platform.processor() or platform.machine())
    ap.add_argument("--date", default=time.strftime("%Y-%m-%d"))
    ap.add_argument("--out", type=Path, default=RESULTS)
    add_overwrite_option(ap)
    args = ap.parse_args()
    refuse_overwrite(args.out, overwrite=args.overwrite)

    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-reconstruct-") as tmp:
        for name in args.scenes:
            row = bench_scene(name, Path(tmp), args.threads)
            if row:
                rows.append(row)
    pycolmap_version, _ = sfm.versions()
    result = {"benchmark": "reconstruct", "machine": args.machine, "date": args.date,
              "pycolmap": pycolmap_version, "threads": args.threads, "rows": rows}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.out}")
    print("| scene | registered | points | reproj. error (px) | extract (s) | match (s) | map (s) "
          "| undistort (s) | total (s) | centre error (max, % radius) | machine | date |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        st = r["stage_seconds"]
        cerr = f"{100 * r['centre_err_max']:.2f}" if "centre_err_max" in r else "n/a"
        print(f"| {r['scene']} | {r['registered']}/{r['images']} | {r['points3d']} | "
              f"{r['mean_reprojection_error']:.2f} | {st.get('extract', 0):.1f} | {st.get('match', 0):.1f} | "
              f"{st.get('map', 0):.1f} | {st.get('undistort', 0):.1f} | {r['total_seconds']:.1f} | {cerr} | "
              f"{args.machine} | {args.date} |")


if __name__ == "__main__":
    main()
