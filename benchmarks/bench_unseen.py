"""Does the uncertainty find what the training views never saw? (issue 18, protocol "unseen regions")

The synthetic scene (exact GT depth) is trained on the cameras of one half of its ring only, with initial
points from those views only (``scene.points_from = "train"``), and tested on views of the other half, which
see both surface the training views saw and surface none of them saw. Every test pixel is labelled
observed / unobserved from GT depth (``eval.observed.observed_mask``). Per method:

* ROC AUC of the per-pixel RGB std (mean over channels) and depth std for unobserved (positive) against
  observed pixels, over the pixels with surface; with the empty-ray term (``eval.empty_rays``, the default)
  and without it (the samples' spread alone);
* mean std on unobserved / observed pixels, and on pixels whose rays meet no Gaussian (alpha < 0.5);
* the evaluation metrics on those views: PSNR, AUSE-MAE, NLL, calibration error, the fitted std factor.

Each run is evaluated with every one of the ``PREDICTIVES`` (``--predictives`` picks some): ``full`` (what ``evaluate``
writes), ``before`` (the predictive before the coverage and resolution terms: every alpha < 1 counts as empty, no
resolution term), ``spread`` (the samples' spread alone) and ``leverage`` (``full`` with
``EvalConfig.residual_leverage = "full"``); ``no-leverage`` is ``full`` without the relative leverage (the default
since 2026-11-27); ``no-colour`` is ``full`` without the colour posterior
(``EvalConfig.colour_posterior``, the default since 2026-11-26); ``colour-block`` / ``colour-diagonal`` are
``full`` with the colour posterior's two forms (``EvalConfig.colour_covariance``); ``edge`` / ``no-edge`` are ``full`` with and
without the edge term (``EvalConfig.edge_noise``); ``no-depth-spread`` is ``full`` without the spread of the depths
each ray blends (``EvalConfig.depth_spread``); ``resolution-1`` is ``full`` with one render of the resolution
term per sample (``EvalConfig.resolution_renders``, 2 since 2026-11-27); ``no-consistency`` is ``full`` without
the view-consistency term (``EvalConfig.consistency_views``); ``no-finer`` is ``full`` without the finer-detail term
(``EvalConfig.finer_detail``); ``no-hidden-depth`` is ``full`` without the depth variance of the surface points no
compared training view sees (``EvalConfig.hidden_depth``); ``noise-fit`` is ``full`` with the pixel noise's level
fitted (``EvalConfig.residual_scale = "fit"``: on the training views, or on the views set aside where there are
some, as the default does; without them the default's level is 1).

Every method trains with the same seed, scene, split and schedule (``--iterations`` steps of the demo preset,
its densification window scaled to the length). Methods: ``variational`` (our default, informed posterior),
``expected`` (the informed posterior with the Gaussians fitted to the expected render, the default until 2026-11-28),
``sgd`` (the tables learned by SGD with the KL in the loss, the default before issue 18: the prior-only
reference), ``sandwich`` (the informed posterior with ``variational.sandwich``), ``paper``, ``vi-single``, ``fisher``,
``ensemble-N``, ``vensemble-NxF`` (an ensemble of N of our variational models, each trained for F times the steps),
``imported`` (the ``deterministic`` row's plain 3DGS model given the informed posterior afterwards, as ``train
--from-ply`` gives one to a model trained elsewhere; its train s: the plain training plus the posterior's build).

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/bench_unseen.py --out /tmp/unseen [--iterations 1500]

A method whose run folder already exists under ``--out`` is evaluated again, not trained again (e.g. to compare
predictives on one model); its saved configuration must be the one this call asks for (else the script stops and
says so: a run of another protocol or ``--set`` would be scored as if it were this one's).

Other protocols (``--protocol``): ``dense`` (every 8th view held out: the uncertainty metrics of a dense capture),
``sparse`` (5 interleaved training views on an arc, tested between them, as the paper's light-field protocol), and
``arc`` with ``--scene WS`` (real photos, e.g. a ``reconstruct`` workspace of fern: the last 20 % of the capture by
name held out, so the test views extrapolate; no GT depth there, so per view: PSNR, mean std, RMSE, NLL, and the
correlation over views of mean std with RMSE)::

    .venv/bin/python benchmarks/bench_unseen.py --protocol arc --scene WS --preset paper --downscale 1.5873 \
        --iterations 3000 --max-gaussians 60000 --methods variational sgd --label fern-arc --out /tmp/fern_arc

Photos of different exposure (``--exposure-jitter S``: every generated photo's brightness scaled by a random gain
of log-std S, held-out photos too, as with automatic exposure), with and without ``exposure = "affine"``::

    .venv/bin/python benchmarks/bench_unseen.py --protocol dense --methods variational --predictives full \
        --exposure-jitter 0.25 --out /tmp/exposure_off --label exposure-off
    .venv/bin/python benchmarks/bench_unseen.py --protocol dense --methods variational --predictives full \
        --exposure-jitter 0.25 --set exposure=affine --out /tmp/exposure_affine --label exposure-affine

Writes ``benchmarks/results/unseen_<label>.json`` and prints the Markdown rows for BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import time
from pathlib import Path

import torch
from _common import add_overwrite_option, refuse_overwrite

ROOT = Path(__file__).resolve().parents[1]

METHODS = {  # name -> TrainConfig overrides on top of the demo preset
    "deterministic": {"method": "deterministic"},
    "variational": {"variational": {"posterior": "informed"}},
    # the default until 2026-11-28: the Gaussians fitted to the expected render, spawned carriers dimmed by the prior
    "expected": {"variational": {"posterior": "informed", "train_on": "expected", "spawn_keeps_render": False}},
    "sandwich": {"variational": {"posterior": "informed", "sandwich": True}},
    "sgd": {"variational": {"posterior": "sgd"}},
    "paper": {"variant": "paper"},
    "vi-single": {"variational": {"num_entries": 1, "posterior": "sgd"}},
    "fisher": {"method": "fisher"},
}


def by_azimuth(scene) -> list[int]:
    """Camera indices ordered by azimuth about the camera centroid (the synthetic scene is z-up)."""
    c = scene.cameras.centers.double()
    az = torch.atan2(c[:, 1] - c[:, 1].mean(), c[:, 0] - c[:, 0].mean())
    return torch.argsort(az).tolist()


def half_ring_split(scene, test_every: int) -> tuple[list[int], list[int]]:
    """Training views: the cameras whose azimuth about the look-at centre lies in one half-turn; held out:
    every ``test_every``-th camera of the other half (by azimuth)."""
    order = by_azimuth(scene)
    half = len(order) // 2
    train = sorted(order[:half])
    test = sorted(order[half:][::test_every])
    return train, test


def sparse_split(scene, n: int) -> tuple[list[int], list[int]]:
    """The paper's light-field protocol: ``n`` interleaved training views on a contiguous arc of cameras (by
    azimuth) and the ``n - 1`` views between them held out (e.g. train 43, 45, 47, 49 / test 42, 44, 46, 48)."""
    order = by_azimuth(scene)[: 2 * n - 1]
    return sorted(order[0::2]), sorted(order[1::2])


def roc(score: torch.Tensor, positive: torch.Tensor) -> float | None:
    from uncertsplat.eval.floaters import ranking_auc

    if positive.all() or not positive.any():
        return None
    return ranking_auc(score.double(), positive)


PREDICTIVES = {  # name -> (EvalConfig overrides, the coverage of 1 = every alpha < 1 counts as empty)
    "full": ({}, False),  # what `evaluate` writes: spread + pixel noise + resolution term + empty rays
    "before": ({"resolution": 0.0, "consistency_views": 0}, True),  # the predictive before the coverage and resolution terms (2026-11-24)
    "spread": ({"empty_rays": False, "residual_views": 0, "resolution": 0.0, "depth_spread": False,
                "consistency_views": 0}, False),  # spread only
    "leverage": ({"residual_leverage": "full"}, False),  # full, each Gaussian's pixel noise / (1 - its leverage)
    "no-leverage": ({"residual_leverage": "none"}, False),  # full without the relative leverage (before 11-27)
    "no-colour": ({"colour_posterior": False}, False),  # full without the colour posterior (the default before)
    "colour-block": ({"colour_covariance": "block"}, False),  # the DC term and band 1 of the colour posterior jointly
    "colour-diagonal": ({"colour_covariance": "diagonal"}, False),  # every SH coefficient on its own
    "edge": ({"edge_noise": True}, False),  # full with the pixel noise split into the edge term and the rest
    "no-edge": ({"edge_noise": False}, False),  # full without the edge term
    "no-depth-spread": ({"depth_spread": False}, False),  # full without the depths a ray blends
    "resolution-1": ({"resolution_renders": 1}, False),  # full with one resolution render per sample (before 11-27)
    "no-consistency": ({"consistency_views": 0}, False),  # full without the view-consistency term (before 11-27)
    "no-finer": ({"finer_detail": False}, False),  # full without the finer-detail term (before 11-28)
    "no-hidden-depth": ({"hidden_depth": False}, False),  # full without the hidden points' depth term (before 11-30)
    "noise-fit": ({"residual_scale": "fit"}, False),  # full with the pixel noise's level fitted on training views
}


def evaluate_run(run_dir: Path, device: torch.device, ecfg, full_coverage: bool = False) -> dict:
    """Evaluate one run on its held-out views as ``evaluate`` scores them (``ecfg``; ``full_coverage``: every alpha
    < 1 counts as empty). Returns the scene, its train / test indices, the held-out views, the training views' GT
    depth (None for real photos), the report, the per-view maps and the fitted std factor."""
    import dataclasses
    from functools import partial

    from uncertsplat.baselines import load_run
    from uncertsplat.data.dataset import load_depths, load_view_set
    from uncertsplat.eval.engine import evaluate_views, fit_residual, scored_sampler

    loaded = load_run(run_dir, device)
    scene = loaded.load_scene()
    train, test = list(scene.split["train"]), list(scene.split["test"])
    views = load_view_set(scene, test)
    maps: list = []
    train_views = partial(load_view_set, scene, depth=False)
    residual = fit_residual(loaded.sampler(scene.scene_scale, device), train, ecfg, device, load_views=train_views,
                            calibration_indices=scene.split.get("calibration", ()))

    def new_sampler():
        base = loaded.sampler(scene.scene_scale, device)
        return dataclasses.replace(base, coverage=1.0 if full_coverage else base.coverage)

    sampler, fit = scored_sampler(new_sampler, residual, scene.cameras, scene.split, ecfg, device,
                                  load_views=train_views)
    scale = fit.scale
    report = evaluate_views(sampler, views, ecfg, device, show_progress=False, on_view=maps.append, dof=fit.dof)
    return {"scene": scene, "train": train, "test": test, "views": views,
            "train_depth": load_depths(scene, train),  # [T,H,W,1] or None for real photos
            "report": report, "maps": maps, "std_scale": scale}


def observed(run: dict, j: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The GT labels of held-out view ``j`` of ``evaluate_run``'s result: [H,W] observed (some training view sees
    the GT surface point) and [H,W] valid (the pixel has GT surface); ``eval.observed.observed_mask``."""
    from uncertsplat.eval.observed import observed_mask

    cams, train, views = run["scene"].cameras, run["train"], run["views"]
    i = run["test"][j]
    return observed_mask(views.depths[j, ..., 0].double(), cams.cam_from_world[i], cams.K[i],
                         run["train_depth"][..., 0].double(), cams.cam_from_world[train], cams.K[train])


def measure(run_dir: Path, device: torch.device, num_samples: int, predictive: str = "full") -> dict:
    """Evaluate one run on its held-out views with one of the ``PREDICTIVES`` and score its std maps against the
    observed labels."""
    from uncertsplat.config import EvalConfig

    overrides, full_coverage = PREDICTIVES[predictive]
    run = evaluate_run(run_dir, device, EvalConfig(num_samples=num_samples, **overrides), full_coverage)
    report, maps, views, scale = run["report"], run["maps"], run["views"], run["std_scale"]
    per_view = per_view_agreement(report, maps)
    if views.depths is None:  # real photos: no GT depth, no observed labels; per-view agreement only
        m = report.mean
        return {"psnr": m.psnr, "ause_mae": m.ause_mae, "nll": m.nll, "calibration_error": m.calibration_error,
                "depth_ause": None, "std_scale": scale, "degrees_of_freedom": report.degrees_of_freedom,
                "nll_gaussian": m.nll_gaussian, "calibration_error_gaussian": m.calibration_error_gaussian,
                "variance_shares": report.variance_shares, **per_view}
    rgb, dep, unobs, empty = [], [], [], []
    parts: dict[str, list[torch.Tensor]] = {}  # each part of the RGB variance on the pixels with surface
    for j, m in enumerate(maps):
        obs, valid = observed(run, j)
        for k, t in (m.rgb_terms or {}).items():
            parts.setdefault(k, []).append(t[..., 0][valid].double())
        rgb.append(m.rgb_std.mean(-1)[valid])
        dep.append(m.depth_std[..., 0][valid])
        unobs.append(~obs[valid])
        empty.append((m.alpha_mean[..., 0] < 0.5)[valid])  # rays that meet (almost) no Gaussian
    rgb, dep, unobs, empty = (torch.cat(x) for x in (rgb, dep, unobs, empty))
    parts = {k: torch.cat(v) for k, v in parts.items()}
    mean = report.mean
    hit = ~empty

    def shares(where: torch.Tensor) -> dict[str, float] | None:  # each part's share of the mean variance there
        if not parts or not bool(where.any()):
            return None
        means = {k: float(v[where].mean()) for k, v in parts.items()}
        total = sum(means.values())
        return {k: v / total for k, v in means.items()} if total > 0 else None

    return {
        "auc_rgb": roc(rgb, unobs), "auc_depth": roc(dep, unobs),
        # the Gaussians' own spread, where the rays meet the model (alpha >= 0.5)
        "auc_rgb_covered": roc(rgb[hit], unobs[hit]), "auc_depth_covered": roc(dep[hit], unobs[hit]),
        "unobserved_covered_fraction": float(unobs[hit].float().mean()) if hit.any() else None,
        "unobserved_fraction": float(unobs.float().mean()), "empty_fraction": float(empty.float().mean()),
        "rgb_std_unobserved": float(rgb[unobs].mean()), "rgb_std_observed": float(rgb[~unobs].mean()),
        "psnr": mean.psnr, "ause_mae": mean.ause_mae, "nll": mean.nll, "calibration_error": mean.calibration_error,
        "depth_ause": getattr(mean, "depth_ause_mae", None), "std_scale": scale,
        "degrees_of_freedom": report.degrees_of_freedom, "nll_gaussian": mean.nll_gaussian,
        "calibration_error_gaussian": mean.calibration_error_gaussian, "depth_nll": mean.depth_nll,
        "depth_calibration_error": report.calibration["depth"].calibration_error if "depth" in report.calibration
        else None, "variance_shares": report.variance_shares,
        # the parts' shares of the RGB variance on the unobserved and on the observed pixels, and each part's ROC AUC
        # alone for the unobserved ones (which part finds what no training view saw)
        "rgb_shares_unobserved": shares(unobs), "rgb_shares_observed": shares(~unobs),
        "auc_rgb_by_part": {k: roc(v, unobs) for k, v in parts.items()},
        "auc_rgb_by_part_covered": {k: roc(v[hit], unobs[hit]) for k, v in parts.items()},
        "rgb_shares_unobserved_covered": shares(unobs & hit), **per_view,
    }


def per_view_agreement(report, maps) -> dict:
    """Per held-out view: PSNR, mean std and RMSE; and the Pearson correlation over views of mean std with RMSE
    (does a view the model renders badly also get a high std?)."""
    rows = []
    for m in maps:
        rmse = float((m.rgb_mean - m.gt).square().mean().sqrt())
        rows.append({"view": m.name, "psnr": report.per_view[m.name].psnr, "mean_std": float(m.rgb_std.mean()),
                     "rmse": rmse, "nll": report.per_view[m.name].nll})
    corr = None
    if len(rows) > 2:
        x = torch.tensor([r["mean_std"] for r in rows], dtype=torch.float64)
        y = torch.tensor([r["rmse"] for r in rows], dtype=torch.float64)
        if float(x.std()) > 0 and float(y.std()) > 0:
            corr = float(torch.corrcoef(torch.stack([x, y]))[0, 1])
    return {"per_view": rows, "std_error_correlation": corr}


def jitter_exposure(scene_dir: Path, sigma: float, seed: int) -> list[float]:
    """Scale each photo of a generated scene by a gain exp(N(0, sigma)) (in the order of its image names, seeded),
    clipped to [0, 1] as a camera saturates; returns the gains. The GT depth and sparse points stay as they were."""
    import numpy as np

    from uncertsplat.io.images import read_image, write_png

    meta = json.loads((scene_dir / "scene.json").read_text(encoding="utf-8"))
    rng = np.random.default_rng(seed)
    gains = [float(np.exp(rng.normal(0.0, sigma))) for _ in meta["image_names"]]
    for name, gain in zip(meta["image_names"], gains, strict=True):
        path = scene_dir / "images" / name
        pixels = np.clip(read_image(path)[..., :3] * gain, 0.0, 1.0).astype(np.float32)
        path.unlink()
        write_png(path, pixels)
    return gains


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("/tmp/bench_unseen"))
    ap.add_argument("--label", default="synthetic-demo-half-ring", help="results go to unseen_<label>.json")
    ap.add_argument("--iterations", type=int, default=1500)
    ap.add_argument("--width", type=int, default=160)
    ap.add_argument("--test-every", type=int, default=2)
    ap.add_argument("--max-gaussians", type=int, default=20000)
    ap.add_argument("--keep-schedule", action="store_true",
                    help="keep the demo preset's densification and spawn schedule (for its own 3500 steps)")
    ap.add_argument("--methods", nargs="+", default=["variational", "sgd", "paper", "vi-single", "fisher", "ensemble-3"])
    ap.add_argument("--samples", type=int, default=10)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--protocol", choices=["half-ring", "dense", "sparse", "arc"], default="half-ring",
                    help="half-ring: train on one half of the ring (the unseen-regions protocol); dense: every 8th "
                    "view held out (the dense-capture check: uncertainty metrics must not get worse); sparse: "
                    "--sparse-views interleaved training views on an arc, tested between them (the paper's LF "
                    "protocol)")
    ap.add_argument("--sparse-views", type=int, default=5)
    ap.add_argument("--scene", type=Path, default=None,
                    help="a scene folder to use instead of the synthetic one (e.g. a reconstruct workspace of real "
                    "photos; no GT depth: no observed labels, per-view agreement only)")
    ap.add_argument("--arc-fraction", type=float, default=0.2, help="arc protocol: the last fraction of the capture")
    ap.add_argument("--preset", default="demo", help="training preset (paper for LLFF-like photos)")
    ap.add_argument("--downscale", type=float, default=None)
    ap.add_argument("--rig", choices=["ring", "hemisphere"], default="ring",
                    help="the synthetic scene's cameras: a ring around a room, or a hemisphere over objects (with "
                    "--backdrop transparent, an object capture as NeRF-synthetic's)")
    ap.add_argument("--backdrop", choices=["room", "transparent"], default="room")
    ap.add_argument("--layout", choices=["colmap", "blender"], default="colmap",
                    help="blender: no sparse points (random initial points, carved by the photos' alpha)")
    ap.add_argument("--points", choices=["train", "all"], default="train",
                    help="initial points: those the training views see (as SfM on them would give), or all")
    ap.add_argument("--set", action="append", default=[], help="key=value for every method's TrainConfig")
    ap.add_argument("--machine", default=platform.processor() or platform.machine())
    ap.add_argument("--exposure-jitter", type=float, default=0.0,
                    help="scale each generated photo's brightness by exp(N(0, S)) (seeded; held-out photos too, as "
                    "in a capture with automatic exposure), keeping the clean photos' sparse points")
    ap.add_argument("--predictives", nargs="+", choices=list(PREDICTIVES), default=list(PREDICTIVES),
                    help="which predictives to evaluate every run with (default: all)")
    add_overwrite_option(ap)
    args = ap.parse_args()
    refuse_overwrite(ROOT / "benchmarks" / "results" / f"unseen_{args.label}.json", overwrite=args.overwrite)

    from uncertsplat.baselines import train_run
    from uncertsplat.config import SynthConfig, TrainConfig, train_config_from
    from uncertsplat.data.synthetic import generate_scene
    from uncertsplat.device import resolve_device
    from uncertsplat.sfm.scene import load_scene

    device = resolve_device("auto")
    args.out.mkdir(parents=True, exist_ok=True)
    scene_dir = args.scene if args.scene is not None else args.out / "scene"
    if args.scene is None and not (scene_dir / "scene.json").is_file():
        generate_scene(scene_dir, SynthConfig(preset="demo", seed=0, width=args.width, rig=args.rig,
                                              backdrop=args.backdrop, layout=args.layout))
        if args.exposure_jitter > 0:
            jitter_exposure(scene_dir, args.exposure_jitter, args.seed)
    if args.protocol == "half-ring":
        train, test = half_ring_split(load_scene(scene_dir), args.test_every)
    elif args.protocol == "sparse":
        train, test = sparse_split(load_scene(scene_dir), args.sparse_views)
    elif args.protocol == "arc":  # a contiguous run of the capture (by sorted name) held out: extrapolated views
        n = len(load_scene(scene_dir).cameras)
        k = max(2, round(n * args.arc_fraction))
        test = list(range(n - k, n))
        train = list(range(n - k))
    else:  # the dense capture: every 8th view held out, as the demo (nothing unobserved to find; AUSE matters)
        n = len(load_scene(scene_dir).cameras)
        test = list(range(0, n, 8))
        train = [i for i in range(n) if i not in test]
    its = args.iterations

    def schedule(its: int) -> dict:
        base = {"iterations": its, "seed": args.seed, "eval_every": 10**6, "checkpoint_every": 10**6,
                "scene": {"train_indices": train, "test_indices": test, "points_from": args.points},
                "densify": {"until": int(its * 0.65), "spawn_interval": max(its // 10, 1),
                            "max_gaussians": args.max_gaussians},
                "variational": {"refresh_interval": max(its // 5, 1)}}
        if args.downscale is not None:
            base["scene"]["downscale"] = args.downscale
        if args.keep_schedule:
            base["densify"] = {"max_gaussians": args.max_gaussians}
            del base["variational"]
        return base

    rows = []
    for name in args.methods:
        over = dict(METHODS.get(name, {}))
        base = schedule(its)
        if name.startswith("ensemble-"):
            over = {"method": "ensemble", "ensemble_size": int(name.split("-")[1])}
        elif name.startswith("vensemble-"):  # N variational members, each trained for F x the steps: vensemble-NxF
            n, _, frac = name.split("-")[1].partition("x")
            over = {"method": "ensemble", "ensemble_size": int(n), "ensemble_members": "variational"}
            base = schedule(max(1, round(its * float(frac or 1.0))))
        elif name not in METHODS and name != "imported":
            raise SystemExit(f"unknown method {name}")
        from uncertsplat.config import deep_update

        def trained(run_dir: Path, cfg) -> float:
            """Train ``cfg`` into ``run_dir`` unless it holds that run; its training seconds."""
            if not (run_dir / "train_summary.json").is_file():
                train_run(scene_dir, run_dir, cfg, device)
            elif TrainConfig.model_validate_json((run_dir / "config.json").read_text(encoding="utf-8")) != cfg:
                raise SystemExit(f"{run_dir} holds a run trained with another configuration (protocol, --set, "
                                 f"--iterations ...): choose another --out, or delete it to train again")
            return json.loads((run_dir / "train_summary.json").read_text(encoding="utf-8"))["seconds"]

        run_dir = args.out / name
        t0 = time.perf_counter()
        extra = {}
        if name == "imported":  # plain 3DGS (the deterministic row's run), then its posterior (`train --from-ply`)
            det = args.out / "deterministic"
            train_s = trained(det, train_config_from(args.preset, deep_update(base, METHODS["deterministic"]),
                                                     args.set))
            cfg = train_config_from(args.preset, {"scene": base["scene"], "init_ply": str(det / "point_cloud.ply"),
                                                  "iterations": 0}, args.set)
            t1 = time.perf_counter()
            trained(run_dir, cfg)
            extra = {"posterior_seconds": time.perf_counter() - t1}
            train_s += extra["posterior_seconds"]
        else:
            train_s = trained(run_dir, train_config_from(args.preset, deep_update(base, over), args.set))
        rec = {"method": name, "train_seconds": train_s, "wall_seconds": time.perf_counter() - t0, **extra}
        # the full predictive (the default), the one before the coverage and resolution terms, the spread alone
        for kind in args.predictives:
            rec[kind] = measure(run_dir, device, args.samples, kind)
        rows.append(rec)
        print(f"{name:12s} " + " | ".join(f"{kind}: {summary(rec[kind])}" for kind in args.predictives)
              + f" | train {train_s:.0f}s", flush=True)
    out = {"label": args.label, "machine": args.machine, "date": time.strftime("%Y-%m-%d"),
           "torch": torch.__version__, "iterations": its, "width": args.width, "train_views": train,
           "test_views": test, "seed": args.seed, "samples": args.samples, "set": args.set, "protocol": args.protocol,
           "exposure_jitter": args.exposure_jitter, "rig": args.rig, "backdrop": args.backdrop, "layout": args.layout,
           "rows": rows}
    path = ROOT / "benchmarks" / "results" / f"unseen_{args.label}.json"
    path.write_text(json.dumps(out, indent=1))
    print(f"\nwrote {path}\n")
    print("| method | predictive | ROC AUC RGB / depth std | PSNR | AUSE-MAE RGB / depth | NLL | cal. err | fitted std "
          "factor | train s | machine | date |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        for kind in args.predictives:
            w = r[kind]
            print(f"| {r['method']} | {kind} | {fmt(w.get('auc_rgb'))} / {fmt(w.get('auc_depth'))} | {w['psnr']:.2f} | "
                  f"{w['ause_mae']:.3f} / {fmt(w.get('depth_ause'))} | {w['nll']:.2f} | {w['calibration_error']:.3f} | "
                  f"x{fmt(w['std_scale'], 2)} | {r['train_seconds']:.0f} | {args.machine} | {out['date']} |")


def summary(w: dict) -> str:
    """One protocol result on a line."""
    auc = f"AUC {fmt(w['auc_rgb'])}/{fmt(w['auc_depth'])} " if "auc_rgb" in w else ""
    corr = f" corr(std, error) {fmt(w['std_error_correlation'])}" if "auc_rgb" not in w else ""
    depth = f" depth NLL {fmt(w.get('depth_nll'), 2)} cal {fmt(w.get('depth_calibration_error'))}" \
        if w.get("depth_nll") is not None else ""
    return (f"{auc}PSNR {w['psnr']:.2f} AUSE {w['ause_mae']:.3f}/{fmt(w.get('depth_ause'))} NLL {w['nll']:.2f} "
            f"cal {w['calibration_error']:.3f} x{fmt(w['std_scale'], 2)}{depth}{corr}")


def fmt(x, p=3):
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.{p}f}"


if __name__ == "__main__":
    main()
