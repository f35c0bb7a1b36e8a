"""Benchmark ``uncertsplat train``: seconds per step, total time, Gaussians, memory, held-out PSNR/SSIM.

Scenes: the synthetic demo scene (generated here) with the ``demo`` preset, the ``tiny`` scene with the
``tiny`` preset, LLFF fern at 1/8 resolution with the ``paper`` preset (reconstructed here with
``uncertsplat reconstruct`` unless ``--fern-workspace`` points to an existing workspace), and bonsai as
``pipelines/photos.toml`` trains it (``paper`` preset, ``scene.downscale=2``; ``--bonsai-workspace``).

    .venv/bin/python benchmarks/bench_train.py --scenes tiny synthetic-demo [--iterations N] [--device cpu]
    .venv/bin/python benchmarks/bench_train.py --scenes fern --fern-workspace WS \
        --set scene.downscale=1.5873 densify.max_gaussians=60000 --compare-kernels 30

``--compare-kernels K``: after training, K steps from the final checkpoint with the native CPU kernels and
K steps with the PyTorch ones, in the same process (the reference for the speed-up ratio).

Every run also scores three deterministic ways to show the trained model on the held-out views
(``render_modes``): the parameter posterior mean (``variational.posterior_mean``), the expected render
(``variational.expected_render_sample``, what ``train`` reports and ``point_cloud.ply`` holds) and the mean of
``--mc-samples`` posterior samples (what ``evaluate`` predicts), so the deterministic render is compared with its
reference in the same run.

Every run is trained with ``profile=true`` (``train_summary.json`` ``profile``: seconds per phase of the
steps: data, sample, render, loss, backward, optimizer, densify, posterior, eval, checkpoint), and
``--backward-steps`` steps after training are run under ``torch.profiler`` to split the backward pass by autograd
node (rasterizer, SSIM, table sampling, KL, other); one posterior update is split the same way
(``posterior_breakdown``) and one periodic test of each kind (``checks_breakdown``: the growth and SH band tests), and
``outside_rasterizer`` gives the share of the training time outside the rasterizer.

Writes ``benchmarks/results/train_{scene}.json`` (``train_{scene}-{label}.json`` with ``--label``) and prints the Markdown rows for BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
from datetime import date
from pathlib import Path

import torch
from _common import add_overwrite_option, refuse_overwrite

from uncertsplat.config import ReconstructConfig, SynthConfig, train_config_from
from uncertsplat.stages import train as train_stage

ROOT = Path(__file__).resolve().parents[1]
DATASETS = ROOT / "../shared/datasets"
RESULTS = ROOT / "benchmarks" / "results"
# torch.profiler (the phase timings) prints Kineto's "USDT: ... profiler_start / profiler_stop" lines on every
# profiled step; Kineto reads its level when the profiler starts, and 6 is above its highest (USDT = 5). A level set
# in the environment wins.
os.environ.setdefault("KINETO_LOG_LEVEL", "6")

SCENES = {"tiny": "tiny", "synthetic-demo": "demo", "fern": "paper", "bonsai": "paper"}
SCENE_OVERRIDES = {"bonsai": ["scene.downscale=2"]}  # as pipelines/photos.toml trains it


def scene_folder(name: str, work: Path, fern_ws: Path | None, bonsai_ws: Path | None = None) -> Path:
    if name in ("tiny", "synthetic-demo"):
        from uncertsplat.stages import synth

        out = work / name
        synth.run(out, SynthConfig(preset="tiny" if name == "tiny" else "demo"), overwrite=True)
        return out
    given = fern_ws if name == "fern" else bonsai_ws
    if given is not None:
        return given
    from uncertsplat.stages import reconstruct

    ws = work / f"{name}_ws"
    # bonsai as pipelines/photos.toml reconstructs it
    cfg = ReconstructConfig() if name == "fern" else ReconstructConfig(matcher="auto", single_camera=True,
                                                                        max_image_size=1600)
    reconstruct.run(DATASETS / name / "images", ws, cfg)
    return ws


def result_path(scene: str, label: str | None) -> Path:
    """The results file of ``scene``: ``train_<scene>.json``, or ``train_<scene>-<label>.json``."""
    return RESULTS / (f"train_{scene}-{label}.json" if label else f"train_{scene}.json")


def bench(name: str, work: Path, args) -> dict:
    scene = scene_folder(name, work, args.fern_workspace, args.bonsai_workspace)
    overrides = list(SCENE_OVERRIDES.get(name, []))
    overrides += [f"iterations={args.iterations}"] if args.iterations else []
    overrides += [] if args.no_profile else ["profile=true"]
    overrides += args.set or []
    cfg = train_config_from(SCENES[name], None, overrides)
    run = work / f"run_{name}"
    if (run / "config.json").is_file():  # this script's own run from an earlier call with the same --work
        import shutil

        shutil.rmtree(run)
    train_stage.run(scene, run, cfg, torch.device(args.device))
    summary = json.loads((run / "train_summary.json").read_text(encoding="utf-8"))
    stats = [json.loads(x) for x in (run / "stats.jsonl").read_text(encoding="utf-8").splitlines()]
    result = {
        **summary, "scene_path": summary.get("scene"),
        "scene": name, "preset": SCENES[name], "overrides": overrides, "device": args.device,
        "machine": args.machine or platform.processor() or platform.machine(), "date": date.today().isoformat(),
        "torch": torch.__version__, "initial_test_psnr": stats[0].get("eval_psnr"),
        "curve": [{k: r[k] for k in ("step", "eval_psnr", "num_gaussians", "num_carriers") if k in r}
                  for r in stats if "eval_psnr" in r],
    }
    result["render_modes"] = render_modes(run, torch.device(args.device), args.mc_samples)
    if args.backward_steps and not args.no_profile:
        result["backward"] = backward_breakdown(scene, run, cfg, args.backward_steps, torch.device(args.device))
    if result.get("profile") and result.get("posterior_updates"):
        result["posterior_update_split"] = posterior_breakdown(scene, run, cfg, torch.device(args.device))
        result["curvature_pass"] = curvature_pass(scene, run, cfg, torch.device(args.device))
    if result.get("profile"):
        result["checks_split"] = checks_breakdown(scene, run, cfg, torch.device(args.device))
    share = rasterizer_share(result)
    if share is not None:
        result["outside_rasterizer"] = share
        print(f"outside the rasterizer: {100 * share['outside']:.1f} % of the phases "
              f"({100 * share['outside_checks_counted_outside']:.1f} % counting the periodic tests outside, "
              f"{100 * share['outside_posterior_counted_outside']:.1f} % the posterior updates too)")
    if result.get("profile"):
        print(profile_line(result))
    if args.compare_kernels:
        result["kernel_comparison"] = compare_kernels(scene, run, cfg, args.compare_kernels, torch.device(args.device))
    RESULTS.mkdir(parents=True, exist_ok=True)
    result_path(name, args.label).write_text(json.dumps(result, indent=2) + "\n")
    return result


def trainer_from_run(scene: Path, run: Path, cfg, device: torch.device, extra_steps: int = 0):
    """A ``Trainer`` at the run's last checkpoint (no run folder: nothing is written), allowed ``extra_steps``
    steps past the run's length."""
    from uncertsplat.data.dataset import load_images
    from uncertsplat.io.checkpoints import load_latest
    from uncertsplat.sfm.scene import load_scene
    from uncertsplat.train.trainer import Trainer

    data = load_scene(scene, cfg.scene)
    images = load_images(data, data.split["train"], device)
    _, state = load_latest(run, map_location=device)
    cfg = cfg.model_copy(update={"iterations": cfg.iterations + extra_steps})
    return Trainer(data, cfg, images, None, run_dir=None, state=state)


def compare_kernels(scene: Path, run: Path, cfg, steps: int, device: torch.device) -> dict:
    """Seconds per step from the run's last checkpoint with the native and the PyTorch kernels."""
    import os
    import time

    out = {"steps": steps}
    before = os.environ.get("UNCERTSPLAT_RASTERIZER")
    try:
        for backend in ("native", "torch"):
            os.environ["UNCERTSPLAT_RASTERIZER"] = backend
            trainer = trainer_from_run(scene, run, cfg, device, extra_steps=2 * steps + 10)
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


BACKWARD_GROUPS = {  # autograd node name fragment -> group
    # the expected render's peak factor is part of render(), whose forward is the "render" phase (before
    # 2026-11-26 it was tensor ops, counted in "other")
    "Composite": "rasterize", "Projection": "rasterize", "NativeSH": "rasterize", "BlurPeak": "rasterize",
    "SSIM": "ssim", "FusedTables": "sample", "FusedKL": "kl"}


def backward_breakdown(scene: Path, run: Path, cfg, steps: int, device: torch.device) -> dict:
    """Seconds per step of the backward pass by autograd node group (rasterizer, SSIM, sampling of the tables,
    KL, the rest), from ``steps`` steps after the run's last checkpoint under ``torch.profiler``."""
    from torch.profiler import ProfilerActivity, profile

    trainer = trainer_from_run(scene, run, cfg, device, extra_steps=steps + 10)
    for _ in range(3):  # warm-up
        trainer.train_step()
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
    with profile(activities=activities) as prof:
        for _ in range(steps):
            trainer.train_step()
    groups: dict[str, float] = {}
    for e in prof.key_averages():
        if not e.key.startswith("autograd::engine::evaluate_function: "):
            continue
        node = e.key.split(": ", 1)[1]
        group = next((g for frag, g in BACKWARD_GROUPS.items() if frag in node), "other")
        groups[group] = groups.get(group, 0.0) + e.cpu_time_total / 1e6 / steps
    return {"steps": steps, "num_gaussians": len(trainer.model), "sec_per_step": groups}


def _timed_trainer(scene: Path, run: Path, cfg, device: torch.device):
    """A trainer at the run's last checkpoint whose ``render`` calls add their wall time to ``spent[0]``."""
    import time

    trainer = trainer_from_run(scene, run, cfg, device, extra_steps=10)
    render, spent = trainer.render, [0.0]

    def timed_render(*a, **k):
        t0 = time.perf_counter()
        out = render(*a, **k)
        spent[0] += time.perf_counter() - t0
        return out

    trainer.render = timed_render
    return trainer, spent


def _rasterizer_backward_s(prof) -> float:
    """Seconds of the rasterizer's autograd nodes under a ``torch.profiler`` run."""
    return sum(e.cpu_time_total / 1e6 for e in prof.key_averages()
               if e.key.startswith("autograd::engine::evaluate_function: ")
               and any(frag in e.key for frag, g in BACKWARD_GROUPS.items() if g == "rasterize"))


def posterior_breakdown(scene: Path, run: Path, cfg, device: torch.device) -> dict:
    """What share of an informed posterior update (``Trainer.update_posterior``, an update before the last) is the
    rasterizer, measured as the training step's share is: the wall time of its ``render`` calls plus the rasterizer's
    autograd nodes of its backward passes (``torch.profiler``), over the update's wall time in the same call."""
    import time

    from torch.profiler import ProfilerActivity, profile

    from uncertsplat import native

    trainer, spent = _timed_trainer(scene, run, cfg, device)
    with native.single_threaded_torch(device):  # as train_step calls it
        t0 = time.perf_counter()
        trainer.update_posterior()
        plain = time.perf_counter() - t0
        spent[0] = 0.0
        activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
        with profile(activities=activities) as prof:
            t0 = time.perf_counter()
            trainer.update_posterior()
            wall = time.perf_counter() - t0
    backward = _rasterizer_backward_s(prof)
    out = {"seconds": plain, "seconds_profiled": wall, "render_forward_s": spent[0], "rasterizer_backward_s": backward,
           "rasterizer_fraction": (spent[0] + backward) / wall}
    print(f"posterior update: {plain:.2f} s, rasterizer {100 * out['rasterizer_fraction']:.1f} % (render calls "
          f"{spent[0]:.2f} s + its backward {backward:.2f} s of {wall:.2f} s under the profiler)")
    return out


def checks_breakdown(scene: Path, run: Path, cfg, device: torch.device) -> dict:
    """What share of the training's periodic tests (the ``eval`` phase: ``Trainer.check_growth``, whose blending
    weights are one render and backward per view and whose halving cost renders each view twice, and
    ``Trainer.check_sh_band``, two renders per view) is the rasterizer, measured as ``posterior_breakdown`` measures
    an update: one test of each kind forced at the run's last checkpoint (their due-step rules patched), the wall
    time of the ``render`` calls plus the rasterizer's autograd nodes, over the tests' wall time."""
    import time

    from torch.profiler import ProfilerActivity, profile

    import uncertsplat.train.trainer as trainer_module
    from uncertsplat import native

    trainer, spent = _timed_trainer(scene, run, cfg, device)
    tests = {"growth": lambda: trainer.check_growth(trainer.step + 1)}
    if min(trainer.model.sh_degree, trainer.sh_degree) >= 1:  # a run shorter than the first band has none to test
        tests["sh_band"] = lambda: trainer.check_sh_band(trainer.step + 1)
    out, wall_all, raster_all = {}, 0.0, 0.0
    saved = (trainer_module.growth_check_due, trainer_module.at_budget, trainer_module.check_due,
             trainer_module.skipped)
    class_render = trainer_module.Trainer.render

    def fork_render(self, *a, **k):  # the growth test's copies (new trainers) render through the class's method
        t0 = time.perf_counter()
        out = class_render(self, *a, **k)
        spent[0] += time.perf_counter() - t0
        return out

    trainer_module.Trainer.render = fork_render
    try:
        trainer_module.growth_check_due = lambda step, dcfg, iterations=None: True
        trainer_module.at_budget = lambda n, budget: False
        trainer_module.skipped = lambda *args: False  # (a test far above the threshold skips the next)
        trainer_module.check_due = lambda step, interval, degree, min_gain, done: trainer.model.sh_degree
        with native.single_threaded_torch(device):  # as train_step calls them
            for name, test in tests.items():
                trainer.densifier.grow = True
                test()  # a warm-up, untimed
                trainer.densifier.grow = True
                spent[0] = 0.0
                activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
                with profile(activities=activities) as prof:
                    t0 = time.perf_counter()
                    test()
                    wall = time.perf_counter() - t0
                backward = _rasterizer_backward_s(prof)
                out[name] = {"seconds_profiled": wall, "render_forward_s": spent[0], "rasterizer_backward_s": backward,
                             "rasterizer_fraction": (spent[0] + backward) / wall}
                wall_all += wall
                raster_all += spent[0] + backward
    finally:
        (trainer_module.growth_check_due, trainer_module.at_budget, trainer_module.check_due,
         trainer_module.skipped) = saved
        trainer_module.Trainer.render = class_render
    out["rasterizer_fraction"] = raster_all / max(wall_all, 1e-12)
    print("periodic tests: " + ", ".join(f"{k} {v['seconds_profiled']:.2f} s, rasterizer "
                                         f"{100 * v['rasterizer_fraction']:.1f} %" for k, v in out.items()
                                         if isinstance(v, dict)))
    return out


def rasterizer_share(r: dict) -> dict | None:
    """The training time's split between the rasterizer and the rest (issue 19: the rest at most 25 %): the render
    phase, the rasterizer's share of the backward phase (its share of the backward's autograd nodes under the
    profiler, ``backward``, applied to the phase's wall time: the profiler's own overhead inflates the nodes'
    times, 7.8 ms of nodes against 7.2 ms of a bonsai backward) and of the posterior updates (their rasterizer
    fraction, ``posterior_update_split``) and of the periodic tests (the ``eval`` phase: ``checks_split``), against
    the sum of the phases; also the counts that put the periodic tests (the twenty-ninth session's) and the
    posterior updates too (the twenty-eighth's) wholly outside."""
    prof = r.get("profile")
    if not prof or "backward" not in r:
        return None
    sec = prof["seconds"]
    total = sum(sec.values())
    nodes = r["backward"]["sec_per_step"]
    backward = sec.get("backward", 0.0) * nodes.get("rasterize", 0.0) / max(sum(nodes.values()), 1e-12)
    base = sec.get("render", 0.0) + backward
    split = r.get("posterior_update_split") or {}
    post = sec.get("posterior", 0.0) * split.get("rasterizer_fraction", 0.0)
    checks = sec.get("eval", 0.0) * (r.get("checks_split") or {}).get("rasterizer_fraction", 0.0)
    return {"outside": 1.0 - (base + post + checks) / total,
            "outside_checks_counted_outside": 1.0 - (base + post) / total,
            "outside_posterior_counted_outside": 1.0 - base / total}


def curvature_pass(scene: Path, run: Path, cfg, device: torch.device, repeats: int = 2) -> dict:
    """Seconds of the informed update's data pass on the final model over every training view: the noise and
    the Fisher from one render per view (``curvature``) against the two passes it replaced (``residual_noise_std``
    then ``fisher_diagonal``), alternating, in this process."""
    import time

    from uncertsplat.gaussians.variational import mean_params
    from uncertsplat.uncertainty.curvature import curvature, fisher_diagonal, residual_noise_std

    t = trainer_from_run(scene, run, cfg, device)
    images = t.train_images
    params = mean_params(t.model, variant=cfg.variant, extent=t.extent, temperature=t.prior.temperature)
    names, kw = ("means", "scales", "opacities"), {"sh_degree": t.sh_degree}
    times: dict[str, list[float]] = {"one_pass": [], "two_passes": []}
    for _ in range(repeats):
        t0 = time.perf_counter()
        curvature(params, t.train_cams, images, t.render, names=names, generator=torch.Generator(device).manual_seed(0),
                  **kw)
        times["one_pass"].append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        noise = residual_noise_std(params, t.train_cams, images, t.render, **kw)
        fisher_diagonal(params, t.train_cams, images, t.render, names=names, noise_std=noise,
                        generator=torch.Generator(device).manual_seed(0), **kw)
        times["two_passes"].append(time.perf_counter() - t0)
    out = {k: min(v) for k, v in times.items()}
    out["ratio"] = out["one_pass"] / out["two_passes"]
    print(f"informed update's data pass ({len(t.train_idx)} views): one pass {out['one_pass']:.2f} s, the two it "
          f"replaced {out['two_passes']:.2f} s (x{out['ratio']:.2f})")
    return out


def profile_line(r: dict) -> str:
    """Share of each phase in the training time, and the backward's split when measured."""
    prof = r["profile"]
    total = sum(prof["seconds"].values())
    parts = [f"{k} {100 * v / total:.1f}%" for k, v in sorted(prof["seconds"].items(), key=lambda kv: -kv[1])]
    line = f"{r['scene']}: {total:.0f} s in phases: " + ", ".join(parts)
    if "backward" in r:
        b = r["backward"]["sec_per_step"]
        line += "\n  backward per step: " + ", ".join(f"{k} {1000 * v:.1f} ms" for k, v in
                                                    sorted(b.items(), key=lambda kv: -kv[1]))
    return line


@torch.no_grad()
def render_modes(run: Path, device: torch.device, mc_samples: int) -> dict:
    """Held-out PSNR of the posterior mean, the expected render and the mean of ``mc_samples`` samples; and the
    uncertainty metrics (AUSE-MAE, Gaussian NLL, calibration error) of the samples' std with either the mean of
    the samples or the expected render as the prediction."""
    from uncertsplat.baselines import load_run
    from uncertsplat.data.dataset import load_images
    from uncertsplat.eval.calibration import calibration
    from uncertsplat.eval.image import psnr
    from uncertsplat.eval.nll import gaussian_nll
    from uncertsplat.eval.sparsification import sparsification_all
    from uncertsplat.gaussians import variational as V
    from uncertsplat.render import near_plane, render

    loaded = load_run(run, device)
    scene = loaded.load_scene()
    test = list(scene.split["test"])
    if not test:
        return {}
    gt = load_images(scene, test, device)  # [C,H,W,3]
    cams = scene.cameras[test].to(device)
    prior, model, cfg = loaded.prior, loaded.model, loaded.config
    kw = {"variant": prior.variant, "extent": loaded.extent, "temperature": prior.temperature,
          "sh_degree": loaded.sh_degree}
    bg = torch.tensor(cfg.scene.background, dtype=torch.float32, device=device)

    def images(g):  # [C,H,W,3]
        return torch.stack([render(g, cams[[c]], background=bg, tile_size=cfg.tile_size,
                                   near=near_plane(scene.scene_scale)).rgb[0] for c in range(len(test))])

    def mean_over_views(fn):
        return sum(fn(c) for c in range(len(test))) / len(test)

    gen = torch.Generator(device=device).manual_seed(0)
    samples = torch.stack([images(V.sample(model, gen, subset_size=cfg.variational.subset_size, **kw))
                           for _ in range(mc_samples)])  # [S,C,H,W,3]
    std = samples.std(0) if mc_samples > 1 else torch.zeros_like(samples[0])
    preds = {"posterior_mean": images(V.posterior_mean(model, **kw)),
             "expected_render": images(V.expected_render_sample(model, **kw)), "mc_mean": samples.mean(0)}
    out: dict = {"mc_samples": mc_samples}
    for name, rgb in preds.items():
        rgb = rgb.clamp(0, 1)
        out[f"{name}_psnr"] = mean_over_views(lambda c, rgb=rgb: float(psnr(rgb[c], gt[c])))
        if name != "posterior_mean" and mc_samples > 1:  # the samples' std with this prediction
            err = rgb - gt
            out[f"{name}_ause_mae"] = mean_over_views(lambda c, err=err: sparsification_all(err[c], std[c])["mae"].ause)
            out[f"{name}_nll"] = mean_over_views(
                lambda c, rgb=rgb: float(gaussian_nll(gt[c], rgb[c], std[c], std_floor=1e-3)))
            out[f"{name}_calibration_error"] = mean_over_views(
                lambda c, err=err: calibration(err[c], std[c]).calibration_error)
    print(f"held-out PSNR: posterior mean {out['posterior_mean_psnr']:.2f}, expected render "
          f"{out['expected_render_psnr']:.2f}, mean of {mc_samples} samples {out['mc_mean_psnr']:.2f}")
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
    ap.add_argument("--bonsai-workspace", type=Path, default=None,
                    help="a reconstruct workspace of ../shared/datasets/bonsai (default: reconstructed here)")
    ap.add_argument("--work", type=Path, default=None, help="keep scenes and runs here (default: a temp dir)")
    ap.add_argument("--mc-samples", type=int, default=10, help="posterior samples of the MC-mean reference")
    ap.add_argument("--compare-kernels", type=int, default=0, metavar="STEPS",
                    help="time STEPS steps from the final checkpoint with native and PyTorch kernels")
    ap.add_argument("--no-profile", action="store_true", help="do not time the phases of the steps")
    ap.add_argument("--backward-steps", type=int, default=20, metavar="STEPS",
                    help="profile STEPS steps from the final checkpoint to split the backward pass (0: skip)")
    ap.add_argument("--label", default=None,
                    help="results go to train_<scene>-<label>.json (default: train_<scene>.json)")
    add_overwrite_option(ap)
    args = ap.parse_args()
    refuse_overwrite(*(result_path(name, args.label) for name in args.scenes), overwrite=args.overwrite)
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
