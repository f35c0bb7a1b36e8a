"""Stage ``synth``: generate the procedural multi-view scene with ground truth (issue 2)."""

from __future__ import annotations

import time
from pathlib import Path

from rich.table import Table

from uncertsplat.config import SynthConfig
from uncertsplat.console import console, esc, print_table, progress
from uncertsplat.data.synthetic import GENERATOR_VERSION, generate_scene, read_scene_meta, resolve_size
from uncertsplat.errors import UserError
from uncertsplat.io.atomic import run_lock
from uncertsplat.io.folders import holds_files
from uncertsplat.report.loader import RUN_MARKERS
from uncertsplat.schemas import SynthScene


def _same_scene(out: Path, cfg: SynthConfig) -> bool | None:
    """None: ``out`` holds no (valid) synthetic scene; else whether it is the one ``cfg`` generates."""
    try:
        meta = read_scene_meta(out)
    except UserError:
        return None
    if meta is None:
        return None
    if meta.generator_version != GENERATOR_VERSION:
        return False
    try:  # a scene written before a config key existed was made with that key's default
        return SynthConfig.model_validate(meta.config) == cfg
    except ValueError:
        return False


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
    non_empty = holds_files(out)
    if non_empty and (out / "config.json").is_file() and any(
            (out / name).exists() for name in RUN_MARKERS if name != "config.json"):
        # a training run: the scene's files would replace its scene.json and mix with its outputs
        raise UserError("the output folder holds a training run; a scene written into it would break the run "
                        "(even with --overwrite)", path=out, hint="Choose another folder for the scene.")
    if non_empty and not overwrite:
        same = _same_scene(out, cfg)
        if same is not None:
            if same:
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

    meta = SynthScene.read(out / "scene.json")
    table = Table(title=f"synthetic scene '{cfg.preset}' (seed {cfg.seed}) in {elapsed:.1f} s", show_header=False)
    table.add_column(style="bold")
    table.add_column()
    table.add_row("folder", esc(out))
    table.add_row("views", f"{num_views} at {width}x{height} on a {cfg.rig} rig, test views: {len(meta.test_views)} "
                  f"(every {cfg.test_every}th)")
    pixels = "RGB" if cfg.backdrop == "room" and cfg.layout == "colmap" else "RGBA"
    backdrop = "objects in a closed room" if cfg.backdrop == "room" else "objects only, transparent background"
    if cfg.layout == "blender":
        table.add_row("train/, test/", f"8-bit {pixels} PNG per view ({backdrop})")
        table.add_row("transforms_*.json", "Blender layout: camera_angle_x, GT camera-to-world (OpenGL axes)")
    else:
        table.add_row("images/", f"8-bit {pixels} PNG per view ({backdrop})")
    table.add_row("depth/", "float32 .npy camera z per view (exact)")
    table.add_row("masks/", "valid-depth mask PNG per view")
    if cfg.layout == "colmap":
        table.add_row("sparse/0/", f"COLMAP model: PINHOLE camera, GT poses, {meta.num_points} points")
    table.add_row("scene.json", "preset, seed, layout, rig, intrinsics, image names, test views")
    print_table(table)
    return out
