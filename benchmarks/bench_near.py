"""Views closer than any training view: does the std grow where the render fails? (issue 18)

Tried as a new user would on an outdoor capture, a held-out photo taken closer than the training photos rendered
through a haze of floaters at 10 dB while its std stayed low. This measures that case on the synthetic scene, where
the truth is known: a run trained on a synthetic ring scene (its GT cameras, e.g. ``make demo``'s
``demo_out/train``) is evaluated as ``evaluate`` does (the same sampler, side terms, noise level and std factor) on
its held-out ring views and on new views the scene generator ray-traces: each held-out camera moved along its
optical axis towards the point it looks at, to ``--fractions`` of its distance (closer than any training camera),
with the same intrinsics and image size. Per set of views: PSNR, AUSE-MAE, NLL and calibration error (raw), the
mean RGB std and RMSE; over all views, the correlation of a view's mean std with its RMSE (a view rendered badly
should be a view the model says it is unsure about).

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/bench_near.py demo_out/train [--fractions 0.75 0.5] [--label demo]

Writes ``benchmarks/results/near_<label>.json`` and prints the Markdown rows for BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import time
from datetime import date
from functools import partial
from pathlib import Path

import torch
from _common import add_overwrite_option, refuse_overwrite

ROOT = Path(__file__).resolve().parents[1]


def near_cameras(cam_from_world: torch.Tensor, targets: torch.Tensor, fraction: float) -> torch.Tensor:
    """cam_from_world [C,4,4] (float64, source frame) of cameras moved along their optical axes to ``fraction`` of
    their distance to ``targets`` [C,3] (the points they look at), the orientation kept."""
    out = cam_from_world.clone()
    for i in range(len(out)):
        R, t = out[i, :3, :3], out[i, :3, 3]
        centre = -R.T @ t
        ahead = R[2]  # the optical axis in world coordinates
        dist = float((targets[i] - centre) @ ahead)
        moved = centre + (1.0 - fraction) * dist * ahead
        out[i, :3, 3] = -R @ moved
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path, help="a run trained on a synthetic ring scene (uncertsplat synth)")
    ap.add_argument("--fractions", type=float, nargs="+", default=[0.75, 0.5])
    ap.add_argument("--num-samples", type=int, default=10)
    ap.add_argument("--label", default="demo")
    ap.add_argument("--set", nargs="*", default=[], help="EvalConfig overrides, e.g. num_samples=10")
    ap.add_argument("--maps", type=Path, default=None, help="also write every view's maps (evaluate's PNGs) here")
    ap.add_argument("--out", type=Path, default=None)
    add_overwrite_option(ap)
    args = ap.parse_args()
    out = args.out or ROOT / "benchmarks" / "results" / f"near_{args.label}.json"
    refuse_overwrite(out, overwrite=args.overwrite)

    from uncertsplat.baselines import load_run
    from uncertsplat.config import EvalConfig, SynthConfig
    from uncertsplat.data.dataset import load_view_set
    from uncertsplat.data.synthetic import (
        make_cameras,
        make_scene_spec,
        read_scene_meta,
        render_view,
        resolve_size,
    )
    from uncertsplat.eval.engine import evaluate_views, scored_sampler
    from uncertsplat.io.images import resize_image
    from uncertsplat.sfm.scene import normalized_cam_from_world
    from uncertsplat.stages.residual_cache import fitted_residual
    from uncertsplat.types import Cameras, ViewSet

    device = torch.device("cpu")
    overrides = {k: json.loads(v) for k, v in (kv.split("=", 1) for kv in args.set)}
    cfg = EvalConfig(num_samples=args.num_samples, save_maps=False, **overrides)
    loaded = load_run(args.run, device)
    scene = loaded.load_scene()
    meta = read_scene_meta(Path(scene.source["path"]))
    if meta is None or meta.rig != "ring":
        raise SystemExit(f"{args.run} was not trained on a synthetic ring scene")
    synth = SynthConfig(preset=meta.preset, seed=meta.seed, rig=meta.rig, backdrop=meta.backdrop)
    num_views, width, height, _ = resolve_size(synth)
    src_c2w, K = make_cameras(synth, num_views, width, height)
    spec = make_scene_spec(meta.seed, room=meta.backdrop == "room")
    test = list(scene.split["test"])
    names = [scene.cameras.image_names[i] for i in test]
    # every orbit camera looks at a point near the room's centre at table height: its optical axis passes within a
    # jitter of the scene's look-at target; the point on the axis nearest the room's vertical centre line is used
    targets = []
    for i in test:
        R, t = src_c2w[i, :3, :3], src_c2w[i, :3, 3]
        centre, ahead = -R.T @ t, R[2]
        # nearest point of the axis to the z axis (x = y = 0)
        a = ahead[:2]
        lam = float(-(centre[:2] @ a) / (a @ a))
        targets.append(centre + lam * ahead)
    targets = torch.stack(targets)

    train_views = partial(load_view_set, scene, depth=False)
    residual = fitted_residual(loaded, scene.scene_scale, scene.split.get("train", ()), cfg, device,
                               load_views=train_views, write=False,
                               calibration_indices=scene.split.get("calibration", ()))
    sampler, fit = scored_sampler(partial(loaded.sampler, scene.scene_scale, device), residual, scene.cameras,
                                  scene.split, cfg, device, load_views=train_views)

    def view_set(fraction: float) -> ViewSet:
        if fraction == 1.0:
            return load_view_set(scene, test)
        c2w = near_cameras(src_c2w[test], targets, fraction)
        W, H = scene.cameras.width, scene.cameras.height  # the run's size (after its downscale): as load_view_set
        images, depths = [], []
        for j in range(len(test)):
            rgb, depth, _valid, _alpha = render_view(spec, c2w[j], K, width, height)
            rgb8 = (torch.round(rgb.clamp(0, 1) * 255) / 255.0).float().numpy()  # as the scene's PNGs hold them
            images.append(torch.from_numpy(resize_image(rgb8, W, H)))
            depths.append(torch.from_numpy(resize_image(depth.float().numpy(), W, H)))
        cams = Cameras(normalized_cam_from_world(c2w, scene.world_from_source).float(), K.float().expand(len(test), 3, 3).clone(),
                       width, height, tuple(f"{n} at {fraction:g}" for n in names))
        cams = cams.scaled(scene.cameras.width / width)
        scale = 1.0 / scene.depth_scale_to_gt if scene.depth_scale_to_gt else 1.0
        return ViewSet(indices=tuple(100_000 + j for j in range(len(test))), cameras=cams,
                       images=torch.stack(images).float(), depths=(torch.stack(depths) * scale).float()[..., None],
                       depth_known_scale=True)

    rows, per_view = [], []
    for fraction in [1.0, *args.fractions]:
        views = view_set(fraction)
        stats: list[tuple[float, float]] = []

        def keep(maps, stats=stats):
            err = (maps.rgb_mean.clamp(0, 1) - maps.gt).square().mean().sqrt()
            stats.append((float(maps.rgb_std.mean()), float(err)))
            if args.maps is not None:
                from uncertsplat.stages.evaluate import write_view_maps

                write_view_maps(args.maps, maps, cfg.preview)

        t0 = time.perf_counter()
        report = evaluate_views(sampler, views, cfg, device, on_view=keep, std_scale=fit.scale,
                                calibration_views=fit.names, dof=fit.dof, show_progress=False)
        m = report.mean
        finer = [sampler.consistency.reach(views.cameras[[j]], sampler.render_fn)[1] if sampler.consistency else None
                 for j in range(len(views.indices))]  # what evaluate's note reads (ViewConsistency.reach)
        rows.append({"finer_scale": finer, "fraction": fraction, "views": len(views.indices), "psnr": m.psnr, "ause_mae": m.ause_mae,
                     "nll": m.nll, "calibration_error": m.calibration_error, "nll_calibrated": m.nll_calibrated,
                     "depth_ause_mae": m.depth_ause_mae,
                     "mean_std": sum(s for s, _ in stats) / len(stats), "rmse": sum(e for _, e in stats) / len(stats),
                     "seconds": time.perf_counter() - t0})
        per_view += [{"fraction": fraction, "name": n, "mean_std": s, "rmse": e,
                      "psnr": report.per_view[n].psnr}
                     for n, (s, e) in zip(views.cameras.image_names, stats, strict=True)]
        print(f"distance x{fraction:g}: PSNR {m.psnr:.2f}, AUSE-MAE {m.ause_mae:.3f}, NLL {m.nll:.3f}, "
              f"cal. err {m.calibration_error:.3f}, mean std {rows[-1]['mean_std']:.4f}, RMSE {rows[-1]['rmse']:.4f}, "
              f"finer scale {', '.join('-' if f is None else f'{f:.2f}' for f in finer)}")
    s = torch.tensor([v["mean_std"] for v in per_view], dtype=torch.float64)
    e = torch.tensor([v["rmse"] for v in per_view], dtype=torch.float64)
    corr = float(torch.corrcoef(torch.stack([s, e]))[0, 1]) if len(per_view) > 2 else math.nan
    result = {"run": str(args.run.resolve()), "set": args.set, "std_scale": fit.scale, "degrees_of_freedom": fit.dof,
              "fractions": rows, "per_view": per_view,
              "correlation_mean_std_rmse": corr, "machine": f"{platform.machine()}, {torch.get_num_threads()} threads",
              "torch": torch.__version__, "date": date.today().isoformat()}
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"correlation over the {len(per_view)} views of the mean std with the RMSE: {corr:.2f}")
    print("\n| distance | PSNR | AUSE-MAE | NLL | cal. err | mean RGB std | RMSE |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| x{r['fraction']:g} | {r['psnr']:.2f} | {r['ause_mae']:.3f} | {r['nll']:.3f} | "
              f"{r['calibration_error']:.3f} | {r['mean_std']:.4f} | {r['rmse']:.4f} |")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
