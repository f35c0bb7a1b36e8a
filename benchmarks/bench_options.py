"""Train one scene under several settings, one after another in one process, and score each the same way.

For a training option whose effect must be measured against the default in the same run (issue 19: the SH band
test ``sh_min_gain_db``, the sparse Adam updates ``sparse_updates``): every variant trains from the same scene with
the same seed, then ``uncertsplat evaluate`` (default ``EvalConfig``, ``--samples`` posterior samples) scores it.
Each variant's time, seconds per step, optimiser time (``profile``), model size, PLY size, held-out PSNR / SSIM,
AUSE-MAE, NLL and calibration error are written, with its ratios to the first variant (the reference).

    .venv/bin/python benchmarks/bench_options.py --scene synthetic-demo \
        --variant dense: --variant visible:sparse_updates=visible --variant lazy:sparse_updates=lazy
    .venv/bin/python benchmarks/bench_options.py --scene WS --preset paper --label fern-1-8 \
        --set iterations=3000 scene.downscale=1.5873 densify.max_gaussians=60000 \
        --variant all-bands:sh_min_gain_db=0 --variant default:

A variant is ``NAME:key=value,key=value`` (empty after the colon: the defaults). Writes
``benchmarks/results/options_{label}.json`` and prints the Markdown rows for BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import platform
import tempfile
from datetime import date
from pathlib import Path

import torch
from _common import add_overwrite_option, refuse_overwrite

from uncertsplat.config import EvalConfig, SynthConfig, train_config_from
from uncertsplat.stages import evaluate as evaluate_stage
from uncertsplat.stages import train as train_stage

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"


def parse_variant(text: str) -> tuple[str, list[str]]:
    name, _, rest = text.partition(":")
    if not name:
        raise SystemExit(f"--variant {text!r}: give it a name, e.g. dense: or visible:sparse_updates=visible")
    return name, [kv for kv in rest.split(",") if kv]


def scene_folder(scene: str, work: Path) -> Path:
    if scene in ("tiny", "synthetic-demo"):
        from uncertsplat.stages import synth

        out = work / scene
        if not (out / "scene.json").is_file():
            synth.run(out, SynthConfig(preset="tiny" if scene == "tiny" else "demo"), overwrite=True)
        return out
    return Path(scene)


def run_variant(scene: Path, work: Path, preset: str | None, common: list[str], name: str, extra: list[str],
                device: torch.device, samples: int) -> dict:
    cfg = train_config_from(preset, None, [*common, "profile=true", *extra])
    run = work / f"run_{name}"
    if run.exists():
        import shutil

        shutil.rmtree(run)
    train_stage.run(scene, run, cfg, device)
    summary = json.loads((run / "train_summary.json").read_text(encoding="utf-8"))
    evaluate_stage.run(run, EvalConfig(num_samples=samples), device)
    metrics = json.loads((run / "eval" / "metrics.json").read_text(encoding="utf-8"))
    prof = summary.get("profile") or {}
    return {
        "name": name, "overrides": extra,
        "seconds": summary["seconds"], "sec_per_step": summary["sec_per_step"],
        "optimizer_seconds": (prof.get("seconds") or {}).get("optimizer"),
        "phase_seconds": prof.get("seconds"),
        "num_gaussians": summary["num_gaussians"], "sh_degree_active": summary.get("sh_degree_active"),
        "sh_bands": summary.get("sh_bands", []),
        "ply_mb": (run / "variational.ply").stat().st_size / 2**20,
        "point_cloud_mb": (run / "point_cloud.ply").stat().st_size / 2**20,
        "test_psnr": summary.get("test_psnr"),
        "growth": summary.get("growth", []),
        "variational_sha256": hashlib.sha256((run / "variational.ply").read_bytes()).hexdigest(),
        "eval": _eval_numbers(metrics),
    }


def _eval_numbers(metrics: dict) -> dict:
    """The headline numbers of ``metrics.json`` (``schemas.EvalReport``: the ``mean`` table and the std factor)."""
    mean = metrics["mean"]
    out = {k: mean.get(k) for k in ("psnr", "ssim", "ause_mae", "depth_ause_mae", "nll", "calibration_error")}
    out["std_scale"] = metrics.get("std_scale")
    return out


def _num(d: dict, key: str) -> float:
    v = d.get(key)
    return float("nan") if v is None else float(v)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", required=True, help="tiny, synthetic-demo (generated here) or a scene folder")
    ap.add_argument("--preset", default=None, help="training preset (default: demo for synthetic-demo, tiny for "
                                                   "tiny, none otherwise; 'none': the default config)")
    ap.add_argument("--label", default=None, help="name of the results file (default: the scene)")
    ap.add_argument("--set", nargs="*", default=[], help="key=value overrides shared by every variant")
    ap.add_argument("--variant", action="append", required=True, help="NAME:key=value,... (first = reference)")
    ap.add_argument("--samples", type=int, default=10, help="posterior samples of evaluate")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--work", type=Path, default=None, help="keep scenes and runs here (default: a temp dir)")
    ap.add_argument("--machine", default=None)
    add_overwrite_option(ap)
    args = ap.parse_args()
    preset = args.preset or {"synthetic-demo": "demo", "tiny": "tiny"}.get(args.scene)
    preset = None if preset == "none" else preset
    label = args.label or Path(args.scene).name
    refuse_overwrite(RESULTS / f"options_{label}.json", overwrite=args.overwrite)
    variants = [parse_variant(v) for v in args.variant]
    device = torch.device(args.device)
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        scene = scene_folder(args.scene, work)
        rows = [run_variant(scene, work, preset, args.set, n, extra, device, args.samples) for n, extra in variants]
    ref = rows[0]
    for r in rows:
        r["time_ratio"] = r["seconds"] / ref["seconds"]
        r["psnr_change_db"] = _num(r["eval"], "psnr") - _num(ref["eval"], "psnr")
    result = {"scene": args.scene, "label": label, "preset": preset, "common": args.set, "variants": rows,
              "machine": args.machine or platform.processor() or platform.machine(), "device": args.device,
              "torch": torch.__version__, "threads": torch.get_num_threads(), "date": date.today().isoformat()}
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / f"options_{label}.json"
    path.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {path}")
    print("| variant | train s (ratio) | s/step | optimiser s | Gaussians | SH degree | PLY MB (point_cloud / variational) | PSNR | AUSE-MAE | NLL "
          "| cal. err | growth tests (next skipped) | variational.ply as the first's |")
    for r in rows:
        e = r["eval"]
        print(f"| {r['name']} | {r['seconds']:.0f} (x{r['time_ratio']:.2f}) | {r['sec_per_step']:.4f} | "
              f"{r['optimizer_seconds'] or float('nan'):.2f} | {r['num_gaussians']:,} | {r['sh_degree_active']} | "
              f"{r['point_cloud_mb']:.1f} / {r['ply_mb']:.1f} | {_num(e, 'psnr'):.2f} | {_num(e, 'ause_mae'):.3f} | {_num(e, 'nll'):.2f} | "
              f"{_num(e, 'calibration_error'):.3f} | {len(r['growth'])} ({sum(g.get('skip_next', False) for g in r['growth'])}) | "
              f"{'same' if r['variational_sha256'] == ref['variational_sha256'] else 'differs'} |")


if __name__ == "__main__":
    main()
