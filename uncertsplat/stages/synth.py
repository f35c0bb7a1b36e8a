"""Stage ``synth``: generate the procedural multi-view scene with ground truth (issue 2)."""

from __future__ import annotations

import json
import time
from pathlib import Path

from rich.table import Table

from uncertsplat.config import SynthConfig
from uncertsplat.console import console, progress
from uncertsplat.data.synthetic import GENERATOR_VERSION, generate_scene, is_synthetic_scene, resolve_size
from uncertsplat.errors import UserError
from uncertsplat.io.atomic import run_lock


def _existing_config(out: Path) -> dict | None:
    try:
        meta = json.loads((out / "scene.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if meta.get("generator_version") != GENERATOR_VERSION:
        return None
    return meta.get("config")


def run(out: Path, cfg: SynthConfig, overwrite: bool = False) -> Path:
    """Write the synthetic scene for ``cfg`` to ``out``.

    An existing scene made with the same config and generator version is kept as it is (nothing to
    do). A non-empty folder that holds anything else is refused unless ``overwrite``; with
    ``overwrite`` only the generator's own outputs in it are replaced.

    Returns:
        ``out``.
    """
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise UserError("the output path exists and is not a folder", path=out, hint="Choose a folder path.")
    non_empty = out.is_dir() and any(p.name != ".lock" for p in out.iterdir())
    if non_empty and not overwrite:
        if is_synthetic_scene(out):
            if _existing_config(out) == cfg.model_dump(mode="json"):
                console.print(f"[green]synth:[/] {out} already holds this scene (same config); nothing to do.")
                return out
            raise UserError("the folder holds a synthetic scene made with a different config", path=out,
                            hint="Pass --overwrite to replace it, or choose another folder.")
        raise UserError("the output folder is not empty and is not a synthetic scene", path=out,
                        hint="Choose a new folder, or pass --overwrite to write the scene into it anyway.")

    num_views, width, height, _ = resolve_size(cfg)
    t0 = time.perf_counter()
    with run_lock(out, "synth"), progress() as bar:
        task = bar.add_task("rendering views", total=num_views, info="")
        generate_scene(out, cfg, overwrite=True,
                       on_view=lambda done, total: bar.update(task, completed=done, info=f"{width}x{height}"))
    elapsed = time.perf_counter() - t0

    meta = json.loads((out / "scene.json").read_text(encoding="utf-8"))
    table = Table(title=f"synthetic scene '{cfg.preset}' (seed {cfg.seed}) in {elapsed:.1f} s", show_header=False)
    table.add_column(style="bold")
    table.add_column()
    table.add_row("folder", str(out))
    table.add_row("views", f"{num_views} at {width}x{height}, test views: {len(meta['test_views'])} "
                  f"(every {cfg.test_every}th)")
    table.add_row("images/", "8-bit PNG per view")
    table.add_row("depth/", "float32 .npy camera z per view (exact)")
    table.add_row("masks/", "valid-depth mask PNG per view")
    table.add_row("sparse/0/", f"COLMAP model: PINHOLE camera, GT poses, {meta['num_points']} points")
    table.add_row("scene.json", "preset, seed, intrinsics, image names, test views")
    console.print(table)
    console.print(f"Next: [bold]uncertsplat train {out} -o RUN --preset {cfg.preset}[/]")
    return out
