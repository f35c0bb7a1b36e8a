"""Benchmark ``uncertsplat train``: seconds per step, total time, Gaussians, memory, held-out PSNR/SSIM.

Scenes: the synthetic demo scene (generated here) with the ``demo`` preset, the ``tiny`` scene with the
``tiny`` preset, and LLFF fern at 1/8 resolution with the ``paper`` preset (reconstructed here with
``uncertsplat reconstruct`` unless ``--fern-workspace`` points to an existing workspace).

    .venv/bin/python benchmarks/bench_train.py --scenes tiny synthetic-demo [--iterations N] [--device cpu]
    .venv/bin/python benchmarks/bench_train.py --scenes fern --fern-workspace WS \
        --set scene.downscale=1.5873 densify.max_gaussians=60000 --compare-kernels 30

``--compare-kernels K``: after training, K steps from the final checkpoint with the native CPU kernels and
K steps with the PyTorch ones, in the same process (the reference for the speed-up ratio).

Writes ``benchmarks/results/train_{scene}.json`` and prints the Markdown rows for BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
from datetime import date
from pathlib import Path

import torch

from uncertsplat.config import ReconstructConfig, SynthConfig, train_config_from
from uncertsplat.stages import train as train_stage

ROOT = Path(__file__).resolve().parents[1]
DATASETS = ROOT / "../shared/datasets"
RESULTS = ROOT / "benchmarks" / "results"

SCENES = {"tiny": "tiny", "synthetic-demo": "demo", "fern": "paper"}


def scene_folder(name: str, work: Path, fern_ws: Path | None) -> Path:
    if name in ("tiny", "synthetic-demo"):
        from uncertsplat.stages import synth

        out = work / name
        synth.run(out, SynthConfig(preset="tiny" if name == "tiny" else "demo"), overwrite=True)
        return out
    if fern_ws is not None:
        return fern_ws
    from uncertsplat.stages import reconstruct

    ws = work / "fern_ws"
    reconstruct.run(DATASETS / "fern" / "images", ws, ReconstructConfig())
    return ws


def bench(name: str, work: Path, args) -> dict:
    scene = scene_folder(name, work, args.fern_workspace)
    overrides = [f"iterations={args.iterations}"] if args.iterations else []
    overrides += args.set or []
    cfg = train_config_from(SCENES[name], None, overrides)
    run = work / f"run_{name}"
    train_stage.run(scene, run, cfg, torch.device(args.device))
    summary = json.loads((run / "train_summary.json").read_text())
    stats = [json.loads(x) for x in (run / "stats.jsonl").read_text().splitlines()]
    result = {
        **summary, "scene_path": summary.get("scene"),
        "scene": name, "preset": SCENES[name], "overrides": overrides, "device": args.device,
        "machine": args.machine or platform.processor() or platform.machine(), "date": date.today().isoformat(),
        "torch": torch.__version__, "initial_test_psnr": stats[0].get("eval_psnr"),
        "curve": [{k: r[k] for k in ("step", "eval_psnr", "num_gaussians", "num_carriers") if k in r}
                  for r in stats if "eval_psnr" in r],
    }
    if args.compare_kernels:
        result["kernel_comparison"] = compare_kernels(scene, run, cfg, args.compare_kernels, torch.device(args.device))
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"train_{name}.json").write_text(json.dumps(result, indent=2) + "\n")
    return result


def compare_kernels(scene: Path, run: Path, cfg, steps: int, device: torch.device) -> dict:
    """Seconds per step from the run's last checkpoint with the native and the PyTorch kernels."""
    import os
    import time

    from uncertsplat.data.dataset import load_images
    from uncertsplat.io.checkpoints import load_latest
    from uncertsplat.sfm.scene import load_scene
    from uncertsplat.train.trainer import Trainer

    data = load_scene(scene, cfg.scene)
    images = load_images(data, data.split["train"], device)
    long_cfg = cfg.model_copy(update={"iterations": cfg.iterations + 2 * steps + 10})
    out = {"steps": steps}
    before = os.environ.get("UNCERTSPLAT_RASTERIZER")
    try:
        for backend in ("native", "torch"):
            os.environ["UNCERTSPLAT_RASTERIZER"] = backend
            _, state = load_latest(run, map_location=device)
            trainer = Trainer(data, long_cfg, images, None, run_dir=None, state=state)
            for _ in range(3):  # warm-up
                trainer.train_step()
            t0 = time.perf_counter()
            for _ in range(steps):
                trainer.train_step()
            out[f"{backend}_sec_per_step"] = (time.perf_counter() - t0) / steps
            out["num_gaussians"] = len(trainer.model)
    finally:
        if before is None:
            os.environ.pop("UNCERTSPLAT_RASTERIZER", None)
        else:
            os.environ["UNCERTSPLAT_RASTERIZER"] = before
    out["speedup"] = out["torch_sec_per_step"] / out["native_sec_per_step"]
    print(f"kernels at {out['num_gaussians']} Gaussians: native {out['native_sec_per_step']:.3f} s/step, PyTorch "
          f"{out['torch_sec_per_step']:.3f} s/step (x{out['speedup']:.2f})")
    return out


def row(r: dict) -> str:
    return (f"| {r['scene']} | {r['preset']} | {r['steps']} | {r['sec_per_step']:.3f} | {r['seconds']:.0f} | "
            f"{r['num_gaussians']} | {r['num_carriers']} | {r['memory_per_gaussian_bytes']:.0f} | "
            f"{r['peak_memory_mb']:.0f} | {r['initial_test_psnr']:.2f} | {r['test_psnr']:.2f} | "
            f"{r['test_ssim']:.3f} | {r['machine']} | {r['date']} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="+", default=["tiny", "synthetic-demo"], choices=list(SCENES))
    ap.add_argument("--iterations", type=int, default=None, help="override the preset's steps")
    ap.add_argument("--set", nargs="*", help="extra key=value overrides of the train config")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--machine", default=None, help="machine description for the table")
    ap.add_argument("--fern-workspace", type=Path, default=None)
    ap.add_argument("--work", type=Path, default=None, help="keep scenes and runs here (default: a temp dir)")
    ap.add_argument("--compare-kernels", type=int, default=0, metavar="STEPS",
                    help="time STEPS steps from the final checkpoint with native and PyTorch kernels")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        rows = [row(bench(name, work, args)) for name in args.scenes]
    print("| scene | preset | steps | s/step | total (s) | Gaussians | carriers | bytes/Gaussian | peak MiB | "
          "PSNR start | PSNR | SSIM | machine | date |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    print("\n".join(rows))


if __name__ == "__main__":
    main()
