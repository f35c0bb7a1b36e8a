"""How much of a trained model the training views hardly see, and what removing it would save.

A question for issue 19's step time: do the Gaussians that contribute least to the training views hold a share of
the rasterizer's work worth a pruning rule during training? For a finished run, every Gaussian's blending weight
(sum over pixels of T_i alpha_i, ``uncertainty.scores.blending_weights``) is accumulated over the training views on
the expected render (the sample ``train``'s held-out test renders); the lowest ``--fractions`` by the total weight,
by the largest weight in one view, and by opacity are removed without any re-fit, and the script reports the
held-out PSNR of what is left and the (tile, Gaussian) pairs the binning lists for the training views (the
compositor's work scales with them)::

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/bench_contribution.py RUN --label fern

Writes ``benchmarks/results/contribution_<label>.json`` and prints the Markdown table for BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from dataclasses import replace
from pathlib import Path

import torch
from _common import RESULTS, add_overwrite_option, refuse_overwrite

FRACTIONS = (0.1, 0.2, 0.3, 0.4)


def _subset(sample, keep: torch.Tensor):
    """The Gaussians of ``sample`` where ``keep`` [N] bool is set."""
    return replace(sample, means=sample.means[keep], quats=sample.quats[keep], scales=sample.scales[keep],
                   opacities=sample.opacities[keep], sh=sample.sh[keep],
                   position_var=None if sample.position_var is None else sample.position_var[keep])


def main() -> None:
    from uncertsplat.baselines.runs import load_run
    from uncertsplat.data.dataset import load_view_set
    from uncertsplat.gaussians.variational import expected_render_sample
    from uncertsplat.sfm.scene import load_scene
    from uncertsplat.uncertainty.scores import blending_weights

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path, help="a finished variational run whose scene folder is where it was trained")
    ap.add_argument("--fractions", type=float, nargs="+", default=list(FRACTIONS))
    ap.add_argument("--label", required=True)
    ap.add_argument("--machine", default=platform.processor() or platform.machine())
    add_overwrite_option(ap)
    args = ap.parse_args()
    out_path = RESULTS / f"contribution_{args.label}.json"
    refuse_overwrite(out_path, overwrite=args.overwrite)

    run = load_run(args.run)
    if run.scene_path is None:
        sys.exit(f"{args.run}: no scene.json, so no scene to render the views of")
    scene = load_scene(run.scene_path, run.config.scene)
    train, test = list(scene.split["train"]), list(scene.split["test"])
    render_fn = run.render_fn(scene.scene_scale, torch.device("cpu"))  # background, tile size, near: training's
    render_module = sys.modules["uncertsplat.render.render"]  # (the package's ``render`` names the function)

    with torch.no_grad():
        mean = expected_render_sample(run.model, variant=run.config.variant, extent=run.extent,
                                      sh_degree=run.sh_degree, tables_grad=False)
    t0 = time.perf_counter()
    weights = torch.stack([blending_weights(mean, scene.cameras[[c]], render_fn=render_fn) for c in train])  # [V,N]
    weight_s = time.perf_counter() - t0
    pixels = scene.cameras.width * scene.cameras.height
    views = load_view_set(scene, test, depth=False)

    pairs_seen: list[int] = []
    binning = render_module.bin_gaussians

    def counting(*a, **k):
        bins = binning(*a, **k)
        pairs_seen.append(int(bins.tile_count.sum()))
        return bins

    def measure(sample) -> tuple[float, float]:
        """(held-out PSNR as train's test computes it, mean pairs per training view)."""
        psnrs = []
        with torch.no_grad():
            for i in range(len(test)):
                rgb = render_fn(sample, views.cameras[[i]]).rgb[0].clamp(0.0, 1.0)
                psnrs.append(float(-10.0 * torch.log10((rgb - views.images[i]).square().mean())))
            pairs_seen.clear()
            render_module.bin_gaussians = counting
            try:
                for c in train:
                    render_fn(sample, scene.cameras[[c]])
            finally:
                render_module.bin_gaussians = binning
        return sum(psnrs) / len(psnrs), sum(pairs_seen) / len(pairs_seen)

    base_psnr, base_pairs = measure(mean)
    rows = []
    scores = {"total weight": weights.sum(0), "largest weight in a view": weights.amax(0), "opacity": mean.opacities}
    for name, score in scores.items():
        order = torch.argsort(score)
        for frac in args.fractions:
            cut = int(frac * len(mean))
            keep = torch.ones(len(mean), dtype=torch.bool)
            keep[order[:cut]] = False
            psnr, pairs = measure(_subset(mean, keep))
            at = float(score[order[cut]])
            rows.append({"score": name, "removed": frac, "score_at_cut": at * (pixels if name != "opacity" else 1.0),
                         "psnr": psnr, "psnr_change": psnr - base_psnr, "pairs": pairs,
                         "pairs_ratio": pairs / base_pairs})
    result = {"run": str(args.run), "gaussians": len(mean), "train_views": len(train), "test_views": len(test),
              "base_psnr": base_psnr, "base_pairs": base_pairs, "weights_seconds": weight_s, "rows": rows,
              "machine": args.machine, "date": time.strftime("%Y-%m-%d"), "torch": torch.__version__}
    RESULTS.mkdir(parents=True, exist_ok=True)
    out_path.write_text(json.dumps(result, indent=1))
    print(f"{len(mean)} Gaussians, {len(train)} training views, held-out {base_psnr:.3f} dB, "
          f"{base_pairs:,.0f} pairs a view")
    print("| removed by | share removed | weight (px) or opacity at the cut | held-out PSNR change | pairs |")
    print("|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['score']} | {r['removed']:.0%} | {r['score_at_cut']:.3g} | {r['psnr_change']:+.3f} dB | "
              f"x{r['pairs_ratio']:.3f} |")
    print(f"wrote {out_path}")


if __name__ == "__main__":
    main()
