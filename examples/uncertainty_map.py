"""Render the uncertainty of one view of a trained run: K posterior samples -> mean and std maps.

    python examples/uncertainty_map.py RUN [VIEW] [K]    # e.g. example_out/run 0 10

VIEW indexes the held-out (test) views. Writes RUN/example_maps/{mean,rgb_std,depth_std}.png.
"""

import sys
from pathlib import Path

import torch

from uncertsplat.baselines import load_run
from uncertsplat.io.images import write_png
from uncertsplat.report.colormaps import colorize
from uncertsplat.uncertainty.mc import mc_render

run = Path(sys.argv[1])
view = int(sys.argv[2]) if len(sys.argv) > 2 else 0
k = int(sys.argv[3]) if len(sys.argv) > 3 else 10

loaded = load_run(run)  # any method: model, resolved TrainConfig, scene path, extent
scene = loaded.load_scene()  # same normalisation as in training
cams = scene.subset("test")[view]
# one posterior sample per call (variational.sample for our model; a baseline's own sampler otherwise), and
# the renderer with the run's background, tile size and near plane
sampler = loaded.sampler(scene.scene_scale, loaded.model.device)

# the spread of k samples plus the unknown surface where rays are covered less than the model covers its
# training views (``evaluate`` also adds the pixel noise of the Gaussians, ``eval.engine.fit_residual``, fitted
# on the training views)
maps, _ = mc_render(sampler.sample_fn, sampler.render_fn, cams, k, torch.Generator().manual_seed(0),
                    empty_std=sampler.empty_std, coverage=sampler.coverage)
out = run / "example_maps"
write_png(out / "mean.png", maps.rgb_mean[0].clamp(0, 1).numpy())
write_png(out / "rgb_std.png", colorize(maps.rgb_std[0].mean(-1)))  # percentile colour scale
write_png(out / "depth_std.png", colorize(maps.depth_std[0, ..., 0]))
print(f"{cams.image_names[0]}: mean RGB std {maps.rgb_std.mean():.4f}; maps in {out}")
