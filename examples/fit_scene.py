"""Fit one scene: generate the small synthetic scene and train a variational 3DGS model on it.

    python examples/fit_scene.py [OUT]        # OUT defaults to example_out/; seconds on a 2-core CPU

Writes OUT/scene (images, GT depth, COLMAP model) and OUT/run (config.json, stats.jsonl, checkpoints,
point_cloud.ply, variational.ply). The same as `uncertsplat synth` followed by `uncertsplat train`.
"""

import sys
from pathlib import Path

from uncertsplat.config import SynthConfig, train_config_from
from uncertsplat.device import resolve_device
from uncertsplat.errors import UserError
from uncertsplat.stages import synth, train


def main(out: Path) -> None:
    scene = synth.run(out / "scene", SynthConfig(preset="tiny", seed=0))  # the same scene again: kept as it is
    cfg = train_config_from("tiny", overrides=["iterations=300"])  # presets: tiny, demo, paper
    # a second call continues the run (it is already finished: nothing to do) instead of refusing the folder
    resume = (out / "run" / "config.json").is_file()
    train.run(scene, out / "run", cfg, device=resolve_device("auto"), resume=resume)
    print(f"trained run: {out / 'run'}")


if __name__ == "__main__":
    try:
        main(Path(sys.argv[1] if len(sys.argv) > 1 else "example_out"))
    except UserError as err:  # e.g. a folder that holds something else: the message, not a traceback
        sys.exit(f"error: {err.render()}")
