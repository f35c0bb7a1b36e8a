"""Transient objects in the training photos, with and without their masks (a COLMAP workspace's ``masks/``).

A person walking through, a car parked for some of the photos: each training photo of a scene gets, with probability
``--fraction``, a disc of a random colour (``--radius`` of the image's short side) at a random place; the held-out
photos stay clean. Three workspaces of the same scene and model (images/ + sparse/): ``clean``, ``transients``
(painted, no masks: the discs are trained on, as every pixel was before masks were read) and ``masked`` (painted,
with masks/ black over each disc and a 2-pixel margin). Each is trained and evaluated with the same settings; the
held-out metrics show what the transients cost and how much of it the masks take back.

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/bench_masks.py [--scene WS] [--preset demo] [--iterations 1500]
        [--set densify.max_gaussians=30000] [--label demo]

Without ``--scene`` the synthetic demo scene is generated at ``--width`` pixels (default 160). Writes
``benchmarks/results/masks_<label>.json`` and prints the Markdown rows for BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import json
import platform
import shutil
import time
from datetime import date
from pathlib import Path

import numpy as np
from _common import add_overwrite_option, refuse_overwrite

ROOT = Path(__file__).resolve().parents[1]


def paint(src: Path, dst: Path, train_names: set[str], fraction: float, radius: float, seed: int,
          masks: bool) -> int:
    """``dst`` = workspace ``src`` (images/ copied, sparse/ copied) with discs painted into a ``fraction`` of the
    training photos and, with ``masks``, masks/ (COLMAP's names) black over each disc; returns how many were painted."""
    from uncertsplat.io.images import read_image, write_png

    rng = np.random.default_rng(seed)
    shutil.copytree(src / "sparse", dst / "sparse")
    painted = 0
    for photo in sorted((src / "images").rglob("*")):
        if not photo.is_file():
            continue
        name = photo.relative_to(src / "images").as_posix()
        target = dst / "images" / name
        target.parent.mkdir(parents=True, exist_ok=True)
        # every photo draws the same numbers in every workspace: the same discs, masked or not
        hit, u, v, colour = rng.random() < fraction, rng.random(), rng.random(), rng.random(3)
        if name not in train_names or not hit:
            shutil.copy2(photo, target)
            continue
        im = read_image(photo)
        h, w = im.shape[:2]
        r = radius * min(h, w)
        yy, xx = np.mgrid[0:h, 0:w]
        d2 = (xx - u * w) ** 2 + (yy - v * h) ** 2
        im[d2 <= r * r] = colour
        write_png(target.with_suffix(".png") if target.suffix.lower() != ".png" else target, im)
        if target.suffix.lower() != ".png":  # (the model names the photo: keep its name, PNG inside)
            target.with_suffix(".png").rename(target)
        painted += 1
        if masks:
            m = (d2 > (r + 2.0) ** 2).astype(np.float32)
            (dst / "masks" / name).parent.mkdir(parents=True, exist_ok=True)
            write_png(dst / "masks" / f"{name}.png", np.repeat(m[..., None], 3, axis=-1))
    return painted


VARIANTS = ("clean", "clean+detect", "transients", "transients+detect", "masked")


def count_painted(src: Path, ws: Path, train_names: set[str]) -> int:
    """How many training photos of workspace ``ws`` differ from the scene's."""
    return sum((ws / "images" / n).read_bytes() != (src / "images" / n).read_bytes() for n in train_names)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", type=Path, default=None, help="a COLMAP workspace (default: the synthetic demo scene)")
    ap.add_argument("--width", type=int, default=160, help="the generated scene's width")
    ap.add_argument("--preset", default="demo")
    ap.add_argument("--iterations", type=int, default=1500)
    ap.add_argument("--set", nargs="*", default=[], help="train config overrides key=value (JSON values)")
    ap.add_argument("--fraction", type=float, default=0.5, help="share of the training photos with a transient")
    ap.add_argument("--radius", type=float, default=0.15, help="the disc's radius over the image's short side")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--variants", nargs="+", choices=VARIANTS, default=list(VARIANTS),
                    help="clean / transients / masked photos; +detect: trained with transients.detect = true")
    ap.add_argument("--num-samples", type=int, default=10)
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench_masks"))
    ap.add_argument("--label", default="demo")
    ap.add_argument("--machine", default=platform.processor() or platform.machine())
    add_overwrite_option(ap)
    args = ap.parse_args()
    out = ROOT / "benchmarks" / "results" / f"masks_{args.label}.json"
    refuse_overwrite(out, overwrite=args.overwrite)

    import torch

    from uncertsplat.config import EvalConfig, SynthConfig, deep_update, train_config_from
    from uncertsplat.sfm.scene import load_scene
    from uncertsplat.stages import evaluate, synth, train

    device = torch.device("cpu")
    args.work.mkdir(parents=True, exist_ok=True)
    for photos in ("clean", "transients", "masked"):  # painted again: --fraction, --radius or --seed may differ
        if (args.work / photos).exists():
            shutil.rmtree(args.work / photos)
    scene = args.scene
    if scene is None:
        scene = args.work / "scene"
        if not (scene / "sparse").is_dir():
            synth.run(scene, SynthConfig(preset="demo", width=args.width))
    base = load_scene(scene)
    names = base.cameras.image_names
    train_names = {names[i] for i in base.split["train"]}
    overrides = {}
    for kv in args.set:
        key, value = kv.split("=", 1)
        node = overrides
        *path, last = key.split(".")
        for p in path:
            node = node.setdefault(p, {})
        node[last] = json.loads(value)
    cfg = train_config_from(args.preset, deep_update({"iterations": args.iterations}, overrides))
    detect = train_config_from(args.preset, deep_update(cfg.model_dump(), {"transients": {"detect": True}}))
    rows = []
    for variant in args.variants:
        photos = variant.removesuffix("+detect")
        ws = args.work / photos
        if not ws.exists():  # (the +detect variants train on the same workspace)
            ws.mkdir(parents=True)
            paint(scene, ws, train_names, 0.0 if photos == "clean" else args.fraction, args.radius, args.seed,
                  masks=photos == "masked")
        painted = count_painted(scene, ws, train_names)
        run = args.work / f"run_{variant}"
        if run.exists():
            shutil.rmtree(run)
        t0 = time.perf_counter()
        train.run(ws, run, detect if variant.endswith("+detect") else cfg, device=device)
        seconds = time.perf_counter() - t0
        report = evaluate.run(run, EvalConfig(num_samples=args.num_samples, seed=0, save_maps=False), device,
                              quiet=True)
        summary = json.loads((run / "train_summary.json").read_text(encoding="utf-8"))
        m = report.mean
        rows.append({"variant": variant, "painted_photos": painted, "train_views": len(train_names),
                     "psnr": m.psnr, "ssim": m.ssim, "ause_mae": m.ause_mae, "nll": m.nll,
                     "calibration_error": m.calibration_error, "std_factor": report.std_scale,
                     "gaussians": summary.get("num_gaussians"), "train_seconds": round(seconds, 1)})
        print(json.dumps(rows[-1]), flush=True)
    result = {"date": date.today().isoformat(), "machine": args.machine, "scene": str(args.scene or "synthetic demo"),
              "preset": args.preset, "iterations": args.iterations, "set": args.set, "fraction": args.fraction,
              "radius": args.radius, "seed": args.seed, "num_samples": args.num_samples, "rows": rows}
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {out}")
    print("| photos | PSNR | SSIM | AUSE-MAE | NLL | cal. err | std factor | Gaussians | train s | machine | date |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['variant']} ({r['painted_photos']} of {r['train_views']} painted) | {r['psnr']:.2f} | "
              f"{r['ssim']:.3f} | {r['ause_mae']:.3f} | {r['nll']:.2f} | {r['calibration_error']:.3f} | "
              f"x{r['std_factor']:.2f} | {r['gaussians']} | {r['train_seconds']} | {args.machine} | {result['date']} |")


if __name__ == "__main__":
    main()
