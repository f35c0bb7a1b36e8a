"""Render the uncertainty of one view of a trained run: K posterior samples -> mean and std maps.

    python examples/uncertainty_map.py RUN [VIEW] [K]    # e.g. example_out/run 0 10

VIEW is a held-out (test) view: its position among them (0, 1, ...) or its image name. Writes
RUN/example_maps/{mean,rgb_std,depth_std}.png.
"""

import sys
from pathlib import Path

import torch

from uncertsplat.baselines import load_run
from uncertsplat.errors import UserError
from uncertsplat.io.images import write_png
from uncertsplat.report.colormaps import colorize
from uncertsplat.uncertainty.mc import mc_render


def main(run: Path, view: str, k: int) -> None:
    loaded = load_run(run)  # any method: model, resolved TrainConfig, scene path, extent
    scene = loaded.load_scene()  # same normalisation as in training
    test = scene.subset("test")
    names = list(test.image_names)
    j = int(view) if view.isdigit() else (names.index(view) if view in names else -1)
    if not 0 <= j < len(names):
        raise UserError(f"no held-out view '{view}'", path=run,
                        hint=f"Give 0..{len(names) - 1} or one of: {', '.join(names)}.")
    cams = test[j]
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


if __name__ == "__main__":
    if len(sys.argv) < 2 or (len(sys.argv) > 3 and not (sys.argv[3].isdigit() and int(sys.argv[3]) >= 1)):
        sys.exit(__doc__ + "\nK must be a whole number of samples, 1 or more.")
    try:
        main(Path(sys.argv[1]), sys.argv[2] if len(sys.argv) > 2 else "0", int(sys.argv[3]) if len(sys.argv) > 3 else 10)
    except UserError as err:  # a wrong path or view: the message, not a traceback
        sys.exit(f"error: {err.render()}")
