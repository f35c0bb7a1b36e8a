"""Benchmark ``uncertsplat prune``: held-out PSNR and Gaussian count vs keep ratio, per score and for random
removal, the largest removal within 0.1 dB, and planted floaters (which score removes them best).

    .venv/bin/uncertsplat synth /tmp/x/scene --preset demo
    .venv/bin/uncertsplat train /tmp/x/scene -o /tmp/x/run --preset demo
    .venv/bin/python benchmarks/bench_prune.py --run /tmp/x/run --label synthetic-demo

Planted floaters: ``--floaters`` (fraction of N) Gaussians are added in free space in front of the training
cameras (at 20-50 % of the way from a random training camera to the scene centre, so that camera and its
neighbours see them), twice the median size of the model's Gaussians, opacity 0.7, random colours, each
carrying a posterior at the prior (what a Gaussian the data never constrained has). For each score, the
top-F carriers are removed (F = number of floaters): recall = fraction of floaters among them, and the
held-out PSNR after removal is compared with the clean model and with the planted one.

Real floaters (scenes with GT depth, i.e. the synthetic ones; ``--no-real-floaters`` skips them): the
trained model's own Gaussians are labelled by ``eval.floaters.label_floaters`` (centre in front of the GT
surface, beyond a margin, in every training view that contains it). For each score: the ROC AUC of
floaters against the other carriers, the recall of the top-F carriers (F = number of floater carriers),
and held-out PSNR / depth AUSE after removing them, beside removing exactly the labelled floaters (the
oracle) and F random Gaussians.

Writes ``benchmarks/results/prune_<label>.json`` and prints the Markdown rows for BENCHMARKS.md.
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

from uncertsplat.baselines import load_run
from uncertsplat.config import PruneConfig
from uncertsplat.data.dataset import load_depths
from uncertsplat.eval.floaters import label_floaters, ranking_auc
from uncertsplat.gaussians import ops
from uncertsplat.gaussians.variational import posterior_mean, prior_rows
from uncertsplat.prune import apply_keep, copy_model, keep_ratio_mask, keep_top
from uncertsplat.prune.policy import random_keep as _random_keep
from uncertsplat.render.sh import rgb_to_sh
from uncertsplat.stages.prune import _Measure as _SchemaMeasure
from uncertsplat.uncertainty.scores import SCORE_NAMES, carrier_mask, compute_scores, spread_views

ROOT = Path(__file__).resolve().parents[1]


class _Measure(_SchemaMeasure):
    """The stage's measurement as plain dicts (this script indexes and serialises them)."""

    def __call__(self, model, keep=None) -> dict:
        return super().__call__(model, keep).model_dump()


def plant_floaters(model, scene, fraction: float, prior, generator: torch.Generator):
    """A copy of ``model`` with floaters appended (see the module docstring); returns (model, is_floater [N])."""
    n_f = max(1, round(fraction * len(model)))
    dev = model.device
    cams = scene.cameras[list(scene.split["train"])]
    centres = cams.centers.to(dev)
    target = centres.mean(0)  # the rigs look inwards: the centroid is inside the scene
    pick = torch.randint(0, len(cams), (n_f,), generator=generator).to(dev)
    t = (0.2 + 0.3 * torch.rand(n_f, generator=generator)).to(dev)
    jitter = 0.05 * (centres - target).norm(dim=1).mean() * torch.randn(n_f, 3, generator=generator).to(dev)
    means = centres[pick] + t[:, None] * (target - centres[pick]) + jitter
    size = 2.0 * torch.exp(model.params["scales"].detach()).amax(1).median()
    quats = torch.zeros(n_f, 4, device=dev)
    quats[:, 0] = 1.0
    params = {
        "means": means,
        "scales": torch.full((n_f, 3), float(torch.log(size)), device=dev),
        "quats": quats,
        "opacities": torch.full((n_f,), math.log(0.7 / 0.3), device=dev),
        "sh0": rgb_to_sh(torch.rand(n_f, 3, generator=generator).to(dev))[:, None, :],
        "shN": torch.zeros(n_f, *model.params["shN"].shape[1:], device=dev),
    }
    out = copy_model(model)
    tables = prior_rows(n_f, model.num_entries, prior, device=dev)
    ops.append(out, None, params, tables, torch.ones(n_f, dtype=torch.bool, device=dev))
    is_floater = torch.zeros(len(out), dtype=torch.bool, device=dev)
    is_floater[len(model):] = True
    return out, is_floater


def all_scores(model, loaded, scene, cfg, device):
    prior = loaded.prior
    render_fn = loaded.render_fn(scene.scene_scale, device)  # as the prune stage scores
    cams = scene.cameras[spread_views(scene.split["train"], cfg.score_views)].to(device)
    free_cams = scene.cameras[spread_views(scene.split["train"], cfg.free_space_views)].to(device)
    t0 = time.perf_counter()
    s = compute_scores(model, cams, torch.Generator(device=device).manual_seed(cfg.seed), render_fn=render_fn,
                       names=SCORE_NAMES, num_samples=cfg.score_samples,
                       subset_size=loaded.config.variational.subset_size, variant=prior.variant,
                       extent=loaded.extent, temperature=prior.temperature, free_space_cameras=free_cams,
                       free_space_margin=cfg.free_space_margin)
    return s, time.perf_counter() - t0


def curves(model, measure, before, scores, score_s, cfg, ratios, tol):
    """Held-out metrics vs keep ratio per score and for random removal (``measure``: a ``_Measure`` of the
    unpruned run, ``before`` its metrics, ``scores`` from ``all_scores``)."""
    carriers = carrier_mask(model)
    n = len(model)
    out = {"unpruned": before, "score_seconds": score_s, "curves": {}, "within_tolerance": {}}
    for name in (*SCORE_NAMES, "random"):
        pts = []
        for r in ratios:
            if name == "random":
                removed = n - round(r * n) if r < 1 else 0
                keep = _random_keep(n, removed, cfg.seed)
            else:
                keep = keep_ratio_mask(scores[name], carriers, r)
            removed = int((~keep).sum())
            m = before if removed == 0 else measure(apply_keep(model, keep), keep)
            pts.append({"keep_ratio": r, "num_removed": removed, **m})
            print(f"  {name:10s} keep {r:.2f}: N {m['num_gaussians']:6d} PSNR {m['psnr']:.3f} SSIM {m['ssim']:.4f} "
                  f"AUSE {m.get('ause_mae', float('nan')):.4f}", flush=True)
        out["curves"][name] = pts
        best = None
        for p in pts:  # descending ratios, stop at the first failure (what --auto does)
            if p["num_removed"] == 0:
                continue
            if p["psnr"] >= before["psnr"] - tol:
                best = p
            else:
                break
        out["within_tolerance"][name] = None if best is None else {
            "keep_ratio": best["keep_ratio"], "num_removed": best["num_removed"],
            "removed_fraction": best["num_removed"] / n, "psnr_loss_db": before["psnr"] - best["psnr"]}
    return out


def floaters(loaded, scene, indices, cfg, device, fraction, seed):
    g = torch.Generator().manual_seed(seed)
    planted, is_floater = plant_floaters(loaded.model, scene, fraction, loaded.prior, g)
    import dataclasses

    lp = dataclasses.replace(loaded, model=planted)
    measure = _Measure(lp, scene, indices, cfg, device)
    clean = _Measure(loaded, scene, indices, cfg, device)(loaded.model)
    dirty = measure(planted)
    scores, _ = all_scores(planted, lp, scene, cfg, device)
    carriers = carrier_mask(planted)
    n_f = int(is_floater.sum())
    out = {"num_floaters": n_f, "num_gaussians": len(planted), "clean_psnr": clean["psnr"],
           "planted_psnr": dirty["psnr"], "scores": {}}
    for name in (*SCORE_NAMES, "random"):
        if name == "random":
            keep = _random_keep(len(planted), n_f, cfg.seed)
        else:
            keep = keep_top(scores[name], carriers, n_f)
        recall = float((~keep[is_floater]).float().mean())
        m = measure(apply_keep(planted, keep), keep)
        out["scores"][name] = {"recall": recall, "psnr_after": m["psnr"], "ssim_after": m["ssim"],
                               "floater_score_median": None if name == "random" else
                               float(scores[name][is_floater].median()),
                               "other_score_median": None if name == "random" else
                               float(scores[name][carriers & ~is_floater].median())}
        print(f"  floaters {name:10s} recall {recall:.3f} PSNR {m['psnr']:.3f} (clean {clean['psnr']:.3f}, "
              f"planted {dirty['psnr']:.3f})", flush=True)
    return out


def _floater_labels(loaded, scene, device):
    """``eval.floaters.label_floaters`` of the run's posterior mean against the training views' GT depth (None
    without it)."""
    train = list(scene.split["train"])
    depths = load_depths(scene, train, device)
    if depths is None:
        return None
    prior = loaded.prior
    pm = posterior_mean(loaded.model, variant=prior.variant, extent=loaded.extent, temperature=prior.temperature)
    return label_floaters(pm.means.detach(), pm.scales.detach(), scene.cameras[train], depths, extent=loaded.extent)


def real_floaters(loaded, scene, measure, before, scores, cfg, device):
    """Score the model's own free-space Gaussians (see the module docstring); None without GT depth.

    ``measure``, ``before`` and ``scores`` as for ``curves``."""
    lab = _floater_labels(loaded, scene, device)
    if lab is None:
        return None
    model = loaded.model
    carriers = carrier_mask(model)
    is_f = lab.is_floater
    n_f = int((is_f & carriers).sum())
    contrib = scores["contribution"]
    out = {"num_gaussians": len(model), "num_floaters": int(is_f.sum()), "num_floater_carriers": n_f,
           "floater_contribution_share": float(contrib[is_f].sum() / contrib.sum().clamp_min(1e-12)),
           "median_views_floaters": float(lab.num_views[is_f].float().median()) if is_f.any() else None,
           "median_views_others": float(lab.num_views[~is_f].float().median()),
           "unpruned": {k: before.get(k) for k in ("psnr", "ssim", "ause_mae", "depth_ause_mae")}, "scores": {}}
    print(f"  real floaters: {out['num_floaters']} of {len(model)} ({n_f} carriers), "
          f"{100 * out['floater_contribution_share']:.2f} % of the blending weight", flush=True)
    if n_f == 0:
        return out
    for name in (*SCORE_NAMES, "random", "oracle"):
        if name == "random":
            keep = _random_keep(len(model), n_f, cfg.seed)
        elif name == "oracle":
            keep = ~(is_f & carriers)
        else:
            keep = keep_top(scores[name], carriers, n_f)
        m = measure(apply_keep(model, keep), keep)
        rec = {"recall": float((~keep[is_f & carriers]).float().mean()),
               "auc": None if name in ("random", "oracle") else ranking_auc(scores[name], is_f, carriers),
               **{k: m.get(k) for k in ("psnr", "ssim", "ause_mae", "depth_ause_mae")}}
        out["scores"][name] = rec
        auc = "-" if rec["auc"] is None else f"{rec['auc']:.3f}"
        print(f"  real floaters {name:10s} AUC {auc} recall {rec['recall']:.3f} PSNR {m['psnr']:.3f} "
              f"(unpruned {before['psnr']:.3f}) depth AUSE {m.get('depth_ause_mae', float('nan')):.4f}", flush=True)
    return out


def free_space_views(loaded, scene, scores, cfg, device, counts: list[int]) -> dict | None:
    """The ``free-space`` score from ``counts`` training views each (``prune``'s ``free_space_views``, 64 by
    default: every view of most captures): its time, its ROC AUC for the GT-depth floater labels (as
    ``real_floaters``) and the share of the default score's top-F carriers it also ranks top-F (F = the number of
    floater carriers). None without GT depth."""
    from uncertsplat.uncertainty.scores import free_space_score

    lab = _floater_labels(loaded, scene, device)
    if lab is None:
        return None
    train, model, prior, is_f = list(scene.split["train"]), loaded.model, loaded.prior, lab.is_floater
    carriers = carrier_mask(model)
    n_f = max(int((is_f & carriers).sum()), 1)
    render_fn = loaded.render_fn(scene.scene_scale, device)
    default_top = ~keep_top(scores["free-space"], carriers, n_f)
    out = {"training_views": len(train), "default_views": cfg.free_space_views, "num_floater_carriers": n_f,
           "by_views": []}
    for n in sorted(set(counts)):
        cams = scene.cameras[spread_views(train, n)].to(device)
        t0 = time.perf_counter()
        score = free_space_score(model, cams, render_fn=render_fn, gate=scores["gate"], margin=cfg.free_space_margin,
                                 variant=prior.variant, extent=loaded.extent, temperature=prior.temperature)
        seconds = time.perf_counter() - t0
        top = ~keep_top(score, carriers, n_f)
        row = {"views": len(cams), "seconds": seconds, "auc": ranking_auc(score, is_f, carriers),
               "top_f_shared_with_default": float((top & default_top).sum() / default_top.sum().clamp_min(1))}
        out["by_views"].append(row)
        print(f"  free-space from {row['views']:3d} views: {seconds:6.2f} s, floater AUC {row['auc']:.3f}, top-F "
              f"shared with the default's {100 * row['top_f_shared_with_default']:.1f} %", flush=True)
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", type=Path, required=True)
    ap.add_argument("--label", default="synthetic-demo", help="results go to prune_<label>.json")
    ap.add_argument("--ratios", type=float, nargs="+", default=[1.0, 0.95, 0.9, 0.8, 0.7, 0.6, 0.5])
    ap.add_argument("--num-samples", type=int, default=5)
    ap.add_argument("--floaters", type=float, default=0.02)
    ap.add_argument("--no-real-floaters", action="store_true", help="skip the GT-depth floater labels")
    ap.add_argument("--only-real-floaters", action="store_true", help="skip the keep-ratio sweep and planted floaters")
    ap.add_argument("--free-space-views", type=int, nargs="+", default=None,
                    help="also the free-space score from this many training views each (prune's free_space_views)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--machine", default=platform.processor() or platform.machine())
    add_overwrite_option(ap)
    args = ap.parse_args()
    path = ROOT / "benchmarks" / "results" / f"prune_{args.label}.json"
    refuse_overwrite(path, overwrite=args.overwrite)
    device = torch.device(args.device)
    cfg = PruneConfig(num_samples=args.num_samples)
    loaded = load_run(args.run, device)
    scene = loaded.load_scene()
    indices = list(scene.split["test"])
    t0 = time.perf_counter()
    print(f"{args.label}: {len(loaded.model)} Gaussians ({loaded.model.num_carriers} carriers), "
          f"{len(indices)} held-out views, K={cfg.num_samples}", flush=True)
    res = {"label": args.label, "run": str(args.run), "machine": args.machine, "torch": torch.__version__,
           "date": time.strftime("%Y-%m-%d"), "num_samples": cfg.num_samples, "seed": cfg.seed,
           "num_gaussians": len(loaded.model), "num_carriers": loaded.model.num_carriers,
           "train_step": loaded.step}
    # the unpruned metrics and the scores, once for the real floaters and the keep-ratio curves
    measure = _Measure(loaded, scene, indices, cfg, device)
    before = measure(loaded.model)
    scores, score_s = all_scores(loaded.model, loaded, scene, cfg, device)
    if not args.no_real_floaters:
        res["real_floaters"] = real_floaters(loaded, scene, measure, before, scores, cfg, device)
    if args.free_space_views:
        res["free_space_views"] = free_space_views(loaded, scene, scores, cfg, device, args.free_space_views)
    if not args.only_real_floaters:
        res["sweep"] = curves(loaded.model, measure, before, scores, score_s, cfg,
                              sorted(set(args.ratios), reverse=True), 0.1)
        res["floaters"] = floaters(loaded, scene, indices, cfg, device, args.floaters, seed=1)
    res["seconds"] = time.perf_counter() - t0
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(res, indent=2) + "\n")
    print(f"wrote {path}")
    # Markdown rows
    if "sweep" not in res:
        return
    sw = res["sweep"]
    print("\n| score | " + " | ".join(f"keep {p['keep_ratio']:.2f}" for p in sw["curves"]["random"]) +
          " | largest removal <= 0.1 dB |")
    print("|---" * (len(sw["curves"]["random"]) + 2) + "|")
    for name, pts in sw["curves"].items():
        w = sw["within_tolerance"][name]
        best = "none" if w is None else f"{100 * w['removed_fraction']:.0f}% (-{w['psnr_loss_db']:.3f} dB)"
        print(f"| {name} | " + " | ".join(f"{p['psnr']:.2f} ({p['num_gaussians']})" for p in pts) + f" | {best} |")
    fl = res["floaters"]
    print(f"\nfloaters: {fl['num_floaters']}, clean PSNR {fl['clean_psnr']:.2f}, planted {fl['planted_psnr']:.2f}")
    print("| score | recall of planted floaters | PSNR after removing top-F |\n|---|---|---|")
    for name, v in fl["scores"].items():
        print(f"| {name} | {v['recall']:.2f} | {v['psnr_after']:.2f} |")


if __name__ == "__main__":
    main()
