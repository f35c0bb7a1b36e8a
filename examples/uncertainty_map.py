"""Render the uncertainty of a trained run for a held-out view and for a pose no photo was taken from.

    python examples/uncertainty_map.py RUN [VIEW] [K]    # e.g. example_out/run 0 10 (K: the evaluation's)

VIEW is a held-out (test) view: its position among them (0, 1, ...) or its image name. The second pose lies halfway
between that view and the training view nearest to it, given in the scene's own coordinates (your COLMAP model's
frame and units), as a robot's planner would give it. Both get evaluate's whole predictive (``uncertsplat.predict``;
without K, at the run's evaluation's K and seed: the held-out view's maps are its EXR files'). Writes
RUN/example_maps/{view,between}_{mean,rgb_std,depth_std}.png.
"""

import sys
from pathlib import Path

import torch

from uncertsplat.errors import UserError
from uncertsplat.io.images import write_png
from uncertsplat.predict import Predictor
from uncertsplat.report.colormaps import colorize


def main(run: Path, view: str, k: int | None) -> None:
    pred = Predictor.load(run, "auto")  # any method; fits (or reads) the side terms evaluate fits
    scene = pred.scene  # the run's scene as trained: cameras in its normalised world, split, world_from_source
    test = list(scene.split.get("test", ()))
    names = [scene.cameras.image_names[i] for i in test]
    j = int(view) if view.isdigit() else (names.index(view) if view in names else -1)
    if not 0 <= j < len(names):
        raise UserError(f"no held-out view '{view}'", path=run,
                        hint=f"Give 0..{len(names) - 1} or one of: {', '.join(names)}." if names else
                             "The run holds out no view.")
    i = test[j]
    cams = scene.cameras

    # a pose between the view and its nearest training view, in the scene's own frame: what a user's map gives
    def centre(m: torch.Tensor) -> torch.Tensor:  # camera centre of a world-to-camera matrix [4,4]
        return -m[:3, :3].T @ m[:3, 3]

    # the photos' poses in the scene's frame (what its COLMAP model holds): the normalised ones composed with
    # world_from_source, the camera frame scaled back by its factor s so that each matrix is rigid again
    cam_from_source = [cams.cam_from_world[n].double() @ scene.world_from_source.double() for n in range(len(cams))]
    for m in cam_from_source:
        m[:3] /= pred.scale
    train = list(scene.split["train"])
    nearest = min(train, key=lambda n: float((centre(cam_from_source[n]) - centre(cam_from_source[i])).norm()))
    between = cam_from_source[i].clone()
    between[:3, 3] = -between[:3, :3] @ ((centre(cam_from_source[i]) + centre(cam_from_source[nearest])) / 2)
    new = pred.cameras_from_source(between, cams.K[i], cams.width, cams.height, names=("between",))

    out = run / "example_maps"
    for tag, cam in (("view", cams[[i]]), ("between", new)):
        maps = pred.predict(cam, num_samples=k)  # None: the evaluation's K; its seed
        write_png(out / f"{tag}_mean.png", maps.rgb_mean[0].clamp(0, 1).numpy())
        write_png(out / f"{tag}_rgb_std.png", colorize(maps.rgb_std[0].mean(-1)))  # percentile colour scale
        write_png(out / f"{tag}_depth_std.png", colorize(maps.depth_std[0, ..., 0]))
        print(f"{tag} ({cam.image_names[0]}): mean RGB std {maps.rgb_std.mean():.4f} (x{maps.std_factor or 1:.2f} "
              f"calibrated), median depth {maps.depth_mean.median():.3g} +- {maps.depth_std.median():.3g} in the "
              f"scene's units; "
              + ("a photo looked through the pose" if bool(maps.seen_free[0]) else
                 "no photo looked through the pose: the photos cannot tell whether a camera can stand there (inside "
                 "an object or behind a wall its maps are what the Gaussians around it look like from inside, with a "
                 "confident std; in space no photo looked into they are as good as the model)"))
    print(f"the pose between {names[j]} and {scene.cameras.image_names[nearest]}; maps in {out}")


if __name__ == "__main__":
    args = sys.argv[1:]
    if not 1 <= len(args) <= 3:
        sys.exit(__doc__ + f"\nGive RUN, and optionally VIEW and K ({len(args)} arguments given).")
    if len(args) == 3 and not (args[2].isdigit() and int(args[2]) >= 1):
        sys.exit(__doc__ + f"\nK must be a whole number of samples, 1 or more, not {args[2]}.")
    try:
        main(Path(args[0]), args[1] if len(args) > 1 else "0", int(args[2]) if len(args) > 2 else None)
    except UserError as err:  # a wrong path or view: the message, not a traceback
        sys.exit(f"error: {err.render()}")
