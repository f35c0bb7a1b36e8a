"""The active-learning loop of ``select-views``: which policy's views train the best model?

Protocol (FisherRF's, with our round length): the pool is the scene's training images (the held-out views
stay held out); the start set is the pool's first image plus ``--start - 1`` more by farthest-point sampling
of the camera centres (the same for every policy and seed). The model trains ``--init-steps`` steps on it;
then each round the policy chooses one unused pool image (``uncertsplat.stages.select``), the run resumes
with it added (``train --resume --add-views``) and trains ``--steps-per-round`` more steps, until
``--budget`` views. Every policy runs with the same seeds (the training seed and the random policy's).
At the end: held-out PSNR / SSIM of the expected render, AUSE-MAE (K = ``--eval-samples``) and, for a scene
with GT depth, the depth MAE of the mean render (``evaluate``); and the time spent choosing against the
time spent training the rounds.

Policies are ``select-views`` scores with the settings of the tables before 2026-11-27: ``fisher`` here is the
Fisher over every candidate (``gaps = 0``); ``fisher-gaps`` is the command's default since then (``gaps = 0.5``),
``fisher-logdet`` / ``fisher-predictive`` the other ``information`` settings.

    .venv/bin/python benchmarks/bench_select.py --scene demo_out/synth --label synthetic --downscale 2
    .venv/bin/python benchmarks/bench_select.py --scene /tmp/fernws --label fern --downscale 16 --preset paper

Writes ``benchmarks/results/select_<label>.json`` and prints the rows for BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import json
import platform
import shutil
import statistics
import time
from datetime import date
from pathlib import Path

import torch
from _common import add_overwrite_option, refuse_overwrite

from uncertsplat.baselines import train_run
from uncertsplat.config import EvalConfig, SceneConfig, SelectConfig, deep_update, train_config_from
from uncertsplat.select.scores import coverage_choice
from uncertsplat.sfm.scene import load_scene
from uncertsplat.stages import evaluate as evaluate_stage
from uncertsplat.stages import select as select_stage

ROOT = Path(__file__).resolve().parents[1]
CPU = torch.device("cpu")


def start_set(scene, pool: list[int], k: int) -> list[int]:
    """The pool's first view plus k - 1 by farthest-point sampling of camera centres (deterministic)."""
    centres = scene.cameras.centers[pool]
    chosen, _, _ = coverage_choice(centres[1:], centres[:1], k - 1)
    return [pool[0]] + [pool[1 + j] for j in chosen]


FISHER_VARIANTS = {"fisher-logdet": ("log-det", 0.0), "fisher-predictive": ("predictive", 0.0),
                   "fisher-gaps": ("trace", 0.5)}
"""Policies that are the fisher score with another ``SelectConfig.information`` / ``gaps``."""


def one_loop(scene_path: Path, scene, names, start: list[int], policy: str, seed: int, args, out: Path) -> dict:
    run = out / f"{policy}_seed{seed}"
    shutil.rmtree(run, ignore_errors=True)
    over = deep_update({"iterations": args.init_steps, "seed": seed, "eval_every": 10**6, "checkpoint_every": 10**6,
                        # initial points only from what the start views see: the unused views tell the model nothing
                        "scene": {"downscale": args.downscale, "train_names": [names[i] for i in start],
                                  "points_from": "train"}},
                       json.loads(args.set))
    cfg = train_config_from(args.preset, over)
    t = time.perf_counter()
    train_run(scene_path, run, cfg, CPU)
    train_seconds = [time.perf_counter() - t]
    choose_seconds, score_seconds, added = [], [], []
    step = args.init_steps
    for r in range(args.budget - len(start)):
        t = time.perf_counter()
        score, (info, gaps) = (("fisher", FISHER_VARIANTS[policy]) if policy in FISHER_VARIANTS
                               else (policy, ("trace", 0.0)))
        sel = select_stage.run(run, SelectConfig(score=score, information=info, gaps=gaps, seed=seed * 1000 + r,
                                                 num_samples=args.select_samples, max_side=args.select_side),
                               CPU, output=run / "select" / f"round{r}")
        choose_seconds.append(time.perf_counter() - t)
        score_seconds.append(sel.seconds)
        name = sel.chosen[0].name
        added.append(name)
        step += args.steps_per_round
        t = time.perf_counter()
        train_run(scene_path, run, cfg, CPU, resume=True, extend_to=step, add_views=[name])
        train_seconds.append(time.perf_counter() - t)
    rep = evaluate_stage.run(run, EvalConfig(num_samples=args.eval_samples, seed=0, calibration_views=0,
                                             residual_views=0, save_maps=False), CPU)
    m = rep.mean
    return {"policy": policy, "seed": seed, "added": added, "psnr": m.psnr_render or m.psnr, "psnr_mean": m.psnr,
            "ssim": m.ssim, "ause_mae": m.ause_mae, "depth_mae": m.depth_mae,
            "choose_seconds": choose_seconds, "score_seconds": score_seconds, "train_seconds": train_seconds,
            # the whole select-views command (loading the run and scene, plot) and the scoring alone, against the
            # rounds' training (each train call also reloads the scene and checkpoint)
            "choose_share": sum(choose_seconds) / max(sum(train_seconds[1:]), 1e-9),
            "score_share": sum(score_seconds) / max(sum(train_seconds[1:]), 1e-9)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", type=Path, required=True)
    ap.add_argument("--label", required=True)
    ap.add_argument("--preset", default="demo")
    ap.add_argument("--set", default="{}", help="JSON of train-config overrides")
    ap.add_argument("--downscale", type=float, default=1.0)
    ap.add_argument("--start", type=int, default=4)
    ap.add_argument("--budget", type=int, default=10)
    ap.add_argument("--init-steps", type=int, default=600)
    ap.add_argument("--steps-per-round", type=int, default=300)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--policies", nargs="+", default=["variance", "fisher", "coverage", "random"],
                    help="select-views scores, or fisher-logdet / fisher-predictive (fisher with that information) / "
                         "fisher-gaps (fisher with gaps = 0.5)")
    ap.add_argument("--select-samples", type=int, default=4)
    ap.add_argument("--select-side", type=int, default=96)
    ap.add_argument("--eval-samples", type=int, default=4)
    ap.add_argument("--tmp", type=Path, default=Path("/tmp/bench_select"))
    add_overwrite_option(ap)
    args = ap.parse_args()
    path = ROOT / "benchmarks" / "results" / f"select_{args.label}.json"
    refuse_overwrite(path, overwrite=args.overwrite)

    scene = load_scene(args.scene, SceneConfig(downscale=args.downscale), initial_points=False)
    names = scene.cameras.image_names
    pool = list(scene.split["train"])
    start = start_set(scene, pool, args.start)
    print(f"{args.label}: pool {len(pool)}, start {[names[i] for i in start]}, budget {args.budget}", flush=True)
    out = args.tmp / args.label
    out.mkdir(parents=True, exist_ok=True)
    results: list[dict] = []
    res: dict = {}

    def write() -> dict:
        """Summary over the results so far, written after every loop (a long run interrupted keeps them)."""
        summary = {}
        for policy in args.policies:
            rs = [r for r in results if r["policy"] == policy]

            def stat(key, rs=rs):
                vals = [r[key] for r in rs if r[key] is not None]
                if not vals:
                    return None
                return {"mean": statistics.fmean(vals), "std": statistics.stdev(vals) if len(vals) > 1 else 0.0,
                        "values": vals}

            summary[policy] = {k: stat(k) for k in ("psnr", "ssim", "ause_mae", "depth_mae", "choose_share",
                                                    "score_share")}
        res.update({"label": args.label, "scene": str(args.scene), "date": date.today().isoformat(),
                    "machine": platform.processor() or platform.machine(), "threads": torch.get_num_threads(),
                    "args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
                    "start": [names[i] for i in start], "pool": len(pool), "results": results, "summary": summary})
        path.write_text(json.dumps(res, indent=1) + "\n")
        return summary

    for seed in args.seeds:
        for policy in args.policies:
            r = one_loop(args.scene, scene, names, start, policy, seed, args, out)
            results.append(r)
            write()
            print(f"RESULT {policy} seed {seed}: PSNR {r['psnr']:.2f} SSIM {r['ssim']:.3f} AUSE {r['ause_mae']:.3f} "
                  f"depth MAE {r['depth_mae']} choose {sum(r['choose_seconds']):.1f} s "
                  f"({100 * r['choose_share']:.1f} % of the rounds' training), added {r['added']}", flush=True)
    summary = write()
    print(f"wrote {path}")
    for policy, s in summary.items():
        def f(x, p=2):
            return "-" if x is None else f"{x['mean']:.{p}f} ± {x['std']:.{p}f}"
        print(f"| {policy} | {f(s['psnr'])} | {f(s['ssim'], 3)} | {f(s['ause_mae'], 3)} | {f(s['depth_mae'], 3)} | "
              f"{f(s['score_share'], 3)} | {f(s['choose_share'], 3)} |")


if __name__ == "__main__":
    main()
