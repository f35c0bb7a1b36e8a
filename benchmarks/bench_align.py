"""A model trained in a frame of its own, found on the scene's sparse points (``train --from-ply``, issue 18's
models trained elsewhere; ``init_ply_frame`` auto / align).

A trained run's ``point_cloud.ply`` stands for another tool's output: written in the scene's source frame (as INRIA's
code writes it: the reference), then moved by random similarities (a turn, a scale from 1/20 to 20, a shift: as a
trainer that normalises its world writes it without saying how), positions, sizes, rotations and SH colours alike.
Each file is imported with ``init_ply_frame = "auto"`` and no transform; the row says how far the frame found is from
the true one (the largest move of a Gaussian over the scene's extent, the turn in degrees, the scale), the seconds
of the import against the reference's, and the PSNR of the training views (on the 8 views the fit uses: before and
after the photometric fit; the run's) and of the held-out views against the reference import.

    .venv/bin/python benchmarks/bench_align.py --run demo_out/train --scene demo_out/synth --label demo
    .venv/bin/python benchmarks/bench_align.py --run FERN_RUN --scene FERN_WS --label fern --trials 2

Writes ``benchmarks/results/align_{label}.json`` and prints the Markdown rows.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import sys
import tempfile
import time
from datetime import date
from pathlib import Path

import numpy as np
import torch
from _common import add_overwrite_option, refuse_overwrite
from plyfile import PlyData

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.foreign_ply import in_source_frame, moved  # noqa: E402
from uncertsplat.config import train_config_from  # noqa: E402
from uncertsplat.gaussians.ops import quat_to_rotmat  # noqa: E402
from uncertsplat.stages import train as train_stage  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results"


def import_run(scene: Path, ply: Path, out: Path, scene_cfg: dict) -> tuple[dict, float]:
    cfg = train_config_from(None, {"init_ply": str(ply), "iterations": 0, "scene": scene_cfg})
    t0 = time.perf_counter()
    train_stage.run(scene, out, cfg, torch.device("cpu"))
    return json.loads((out / "train_summary.json").read_text(encoding="utf-8")), time.perf_counter() - t0


def frame_error(found: torch.Tensor, truth: torch.Tensor, means_source: torch.Tensor, extent_source: float):
    """(largest move of a Gaussian between the two frames over the extent, turn in degrees, scale ratio)."""
    a = means_source @ found[:3, :3].T + found[:3, 3]
    b = means_source @ truth[:3, :3].T + truth[:3, 3]
    s_t = float(torch.linalg.det(truth[:3, :3])) ** (1 / 3)
    s_f = float(torch.linalg.det(found[:3, :3])) ** (1 / 3)
    rel = (found[:3, :3] / s_f) @ (truth[:3, :3] / s_t).T
    angle = math.degrees(math.acos(max(-1.0, min(1.0, (float(torch.trace(rel)) - 1) / 2))))
    return float((a - b).norm(dim=-1).max()) / (s_t * extent_source), angle, s_f / s_t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", type=Path, required=True, help="a trained run (its point_cloud.ply is the model)")
    ap.add_argument("--scene", type=Path, required=True, help="the run's scene")
    ap.add_argument("--trials", type=int, default=3, help="random frames")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--label", default="run")
    ap.add_argument("--machine", default=platform.processor() or platform.machine())
    add_overwrite_option(ap)
    args = ap.parse_args()
    path = RESULTS / f"align_{args.label}.json"
    refuse_overwrite(path, overwrite=args.overwrite)
    scene_cfg = json.loads((args.run / "config.json").read_text(encoding="utf-8"))["scene"]
    g = torch.Generator().manual_seed(args.seed)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        src = in_source_frame(args.run, tmp / "source.ply")
        v = PlyData.read(str(src))["vertex"].data
        means = torch.from_numpy(np.stack([v[a] for a in "xyz"], -1).astype(np.float64))
        w = np.asarray(json.loads((args.run / "scene.json").read_text(encoding="utf-8"))["world_from_source"])
        ref, ref_s = import_run(args.scene, src, tmp / "ref", scene_cfg)
        extent = float(ref["extent"]) / float(np.cbrt(abs(np.linalg.det(w[:3, :3]))))  # in source units
        rows.append({"frame": "source (reference)", "seconds": ref_s, "test_psnr": ref["test_psnr"],
                     "train_psnr": ref["train_psnr"], "gaussians": ref["num_gaussians"]})
        for trial in range(args.trials):
            q = torch.randn(1, 4, generator=g, dtype=torch.float64)
            r = quat_to_rotmat(q / q.norm())[0]
            scale = float(torch.exp(torch.empty(1, dtype=torch.float64).uniform_(-3.0, 3.0, generator=g)))
            truth = torch.eye(4, dtype=torch.float64)
            truth[:3, :3] = scale * r
            truth[:3, 3] = torch.randn(3, generator=g, dtype=torch.float64) * 10.0 * scale
            ply = moved(src, tmp / f"turned{trial}.ply", truth)
            summary, seconds = import_run(args.scene, ply, tmp / f"run{trial}", scene_cfg)
            im = summary["imported"]
            row = {"frame": im["frame"], "scale": scale, "seconds": seconds, "test_psnr": summary["test_psnr"],
                   "train_psnr": summary["train_psnr"], "gaussians": summary["num_gaussians"]}
            if im["alignment"] is not None:
                al = im["alignment"]
                move, angle, ratio = frame_error(torch.tensor(al["file_from_source"], dtype=torch.float64), truth,
                                                 means, extent)
                row.update(residual=al["residual"], source_residual=al["source_residual"],
                           refined_psnr=al["refined_psnr"], max_move_over_extent=move, angle_deg=angle,
                           scale_ratio=ratio)
            rows.append(row)
            print(row, flush=True)
    out = {"label": args.label, "machine": args.machine, "date": date.today().isoformat(), "torch": torch.__version__,
           "run": str(args.run), "scene": str(args.scene), "rows": rows}
    RESULTS.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=2) + "\n", encoding="utf-8")
    print("| frame | Gaussians | import s | fit PSNR before -> after (8 views) | training / held-out PSNR | "
          "frame error: largest move / extent, turn, scale | machine | date |")
    print("|---|---|---|---|---|---|---|---|")
    for row in rows:
        fit = ("-" if "refined_psnr" not in row or row["refined_psnr"] is None else
               f"{row['refined_psnr'][0]:.2f} -> {row['refined_psnr'][1]:.2f}")
        err = ("-" if "angle_deg" not in row else
               f"{row['max_move_over_extent']:.4f}, {row['angle_deg']:.3f} deg, x{row['scale_ratio']:.4f}")
        print(f"| {row['frame']} | {row['gaussians']:,} | {row['seconds']:.1f} | {fit} | {row['train_psnr']:.2f} / "
              f"{row['test_psnr']:.2f} | {err} | {args.machine} | {out['date']} |")


if __name__ == "__main__":
    main()
