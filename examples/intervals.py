"""Per-pixel intervals from `evaluate`'s maps alone: the EXR's std and the predictive its header names.

    python examples/intervals.py RUN [P]    # e.g. demo_out/train 0.95

For each evaluated view, reads RUN/eval/maps/{view}.exr (`rgb_mean`, `rgb_std`, and the header attributes
`uncertsplat:rgb_predictive` / `uncertsplat:rgb_degrees_of_freedom`), builds the central interval of probability P
around the mean (mean +- w std, w the Student-t's half-width, or the Gaussian's), writes its lower and upper
bounds as RUN/example_intervals/{view}.exr, and prints how often the photo's pixels fall inside.
"""

import sys
from pathlib import Path

import numpy as np

from uncertsplat.baselines import load_run
from uncertsplat.data.dataset import load_view_set, photo_turns, turned_back
from uncertsplat.errors import UserError
from uncertsplat.eval.tails import half_width
from uncertsplat.io.images import read_exr, read_exr_attribute, write_exr
from uncertsplat.io.maps import EXR_RGB_DOF, EXR_RGB_PREDICTIVE, map_stem
from uncertsplat.schemas.metrics import EvalReport


def main(run: Path, p: float) -> None:
    loaded = load_run(run, "cpu")  # (first: a folder that is no run is said as such, not as a missing evaluation)
    report = EvalReport.read(run / "eval" / "metrics.json")
    scene = loaded.load_scene()
    names = list(scene.cameras.image_names)
    views = load_view_set(scene, [names.index(n) for n in report.image_names], depth=False)
    turns = photo_turns(scene)  # a photo the scene turned has its maps written as the photo lies
    out = run / "example_intervals"
    for j, name in enumerate(report.image_names):
        exr = run / "eval" / "maps" / f"{map_stem(name, report.image_names)}.exr"
        maps = read_exr(exr)
        mean = np.stack([maps[f"rgb_mean.{c}"] for c in "RGB"], -1)
        std = np.stack([maps[f"rgb_std.{c}"] for c in "RGB"], -1)
        # maps written before the header named the predictive are Gaussian
        dof = (read_exr_attribute(exr, EXR_RGB_DOF) if read_exr_attribute(exr, EXR_RGB_PREDICTIVE) == "student-t"
               else None)
        w = half_width(p, dof)  # in stds
        lower, upper = mean - w * std, mean + w * std
        bounds = {f"{b}.{c}": v[..., i] for b, v in (("lower", lower), ("upper", upper)) for i, c in enumerate("RGB")}
        write_exr(out / f"{map_stem(name, report.image_names)}.exr", bounds)
        photo = turned_back(views.images[j].numpy(), turns.get(name, 0))
        inside = float(((photo >= lower) & (photo <= upper)).mean())
        kind = "Gaussian" if dof is None else f"Student-t, {dof:.3g} degrees of freedom"
        print(f"{name}: {kind}: mean +- {w:.2f} std holds {100 * inside:.1f} % of the pixels (nominal {100 * p:.1f} %)")
    print(f"bounds in {out}")


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    try:
        prob = float(sys.argv[2]) if len(sys.argv) > 2 else 0.95
    except ValueError:
        prob = -1.0
    if not 0.0 < prob < 1.0:
        sys.exit(__doc__ + f"\nP must be a probability between 0 and 1 (exclusive), not {sys.argv[2]}.")
    try:
        main(Path(sys.argv[1]), prob)
    except UserError as err:  # e.g. a run not evaluated yet: the message names the file and the command to run
        sys.exit(f"error: {err.render()}")
