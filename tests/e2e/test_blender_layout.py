"""Training on the Blender layout (issue 17): the same synthetic object scene (hemisphere rig, transparent
backdrop) trains as well from transforms_*.json as from the COLMAP model, and the optical-axes centre puts the
random initial points where the object is (recorded in RUN/scene.json)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from uncertsplat.config import SceneConfig, SynthConfig, train_config_from
from uncertsplat.data.synthetic import LOOK_AT, generate_scene
from uncertsplat.schemas import RunScene, TrainSummary
from uncertsplat.sfm.scene import load_scene
from uncertsplat.stages import train as stage

WHITE = "scene.background=[1.0, 1.0, 1.0]"


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    """The tiny transparent hemisphere scene (24 views, 128x96) in both layouts."""
    root = tmp_path_factory.mktemp("blender_layout")
    cfg = dict(preset="tiny", rig="hemisphere", backdrop="transparent")
    return (generate_scene(root / "colmap", SynthConfig(**cfg)),
            generate_scene(root / "blender", SynthConfig(**cfg, layout="blender")), root)


def _train(scene, run, *overrides, steps=300):
    """(held-out PSNR, RUN/scene.json) of a `tiny`-preset run on a white background."""
    cfg = train_config_from("tiny", None, [f"iterations={steps}", WHITE, *overrides])
    stage.run(scene, run, cfg, torch.device("cpu"))
    return TrainSummary.read(run / "train_summary.json").test_psnr, RunScene.read(run / "scene.json")


@pytest.fixture(scope="module")
def colmap_run(scenes):
    """The reference: the COLMAP layout, starting from its exact sparse surface points."""
    colmap, _, root = scenes
    return _train(colmap, root / "run_colmap")


def _write_points(colmap, blender):
    """The COLMAP model's sparse points as the Blender folder's points3d.ply (the 3DGS convention)."""
    from plyfile import PlyData, PlyElement

    ref = load_scene(colmap, SceneConfig(normalize=False))
    v = np.empty(len(ref.points), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"),
                                         ("blue", "u1")])
    v["x"], v["y"], v["z"] = ref.points.numpy().T
    v["red"], v["green"], v["blue"] = np.round(ref.points_rgb.numpy() * 255).astype(np.uint8).T
    PlyData([PlyElement.describe(v, "vertex")]).write(str(blender / "points3d.ply"))


def test_same_points_same_psnr(scenes, tmp_path):
    """With the same initial points the two layouts train alike: the loaders agree on cameras, images,
    alpha compositing and the split.

    Densification is off: its discrete clone/split decisions turn float-rounding differences of the
    cameras (~1e-7) into different trajectories (with it, measured 22.39 vs 22.04 dB after 300 steps, the
    spread of changing the seed); without it both reach 18.52 dB, 0.001 dB apart.
    """
    import json
    import shutil

    colmap, blender, _ = scenes
    ws = tmp_path / "blender_with_points"
    shutil.copytree(blender, ws)
    _write_points(colmap, ws)
    psnr_c, info_c = _train(colmap, tmp_path / "c", "densify.until=0")
    psnr_b, info_b = _train(ws, tmp_path / "b", "densify.until=0")
    assert info_b.source["ply"] == "points3d.ply" and info_b.center_method == info_c.center_method
    assert info_b.test == [f"test/{n}" for n in info_c.test]
    first = [json.loads((tmp_path / r / "stats.jsonl").read_text(encoding="utf-8").splitlines()[0])["eval_psnr"] for r in "cb"]
    assert abs(first[0] - first[1]) < 1e-3  # the same initial render
    print(f"held-out PSNR after 300 steps: COLMAP layout {psnr_c:.3f} dB, Blender layout {psnr_b:.3f} dB")
    assert abs(psnr_b - psnr_c) < 0.1, (psnr_b, psnr_c)


def test_random_init_needs_the_optical_axes_centre(scenes, colmap_run, tmp_path):
    """Random initial points: around the camera centroid (before the fix) the model barely learns the object;
    around the optical-axes centre, carved with the alpha masks of the training views (the visual hull), it
    comes close to training from exact surface points.

    Measured (2-core CPU, `tiny` preset, 300 steps, white background, training seeds 0 / 1): centroid 8.4 dB;
    optical axes without carving 18.81 / 19.27 dB (2.6k points); carved 22.02 / 21.70 dB (5.2k points);
    COLMAP layout (GT sparse points) 22.39 / 21.94 dB: carving closes 2.8 of the 3.6 dB gap, leaving 0.2-0.4 dB.
    5-10 s per run.
    """
    _, blender, _ = scenes
    after, info = _train(blender, tmp_path / "after")
    uncarved, info_uncarved = _train(blender, tmp_path / "uncarved", "scene.carve=false")
    before, info_before = _train(blender, tmp_path / "before", "scene.center=camera_centroid")
    reference, _ = colmap_run
    assert info.center_method == "optical_axes" and info_before.center_method == "camera_centroid"
    assert "carved with the alpha masks of 21 views" in info.source["initial_points"]
    assert "carved" not in info_uncarved.source["initial_points"]
    print(f"held-out PSNR after 300 steps: centroid {before:.2f} dB, optical axes {uncarved:.2f} dB, carved "
          f"{after:.2f} dB, COLMAP layout {reference:.2f} dB")
    assert uncarved > before + 6.0, (uncarved, before)
    assert after > uncarved + 1.5, (after, uncarved)
    assert after > reference - 1.0, (after, reference)


def test_run_records_the_centre(scenes, tmp_path):
    """RUN/scene.json says which centre was used, why, and the normalisation (a few steps)."""
    _, blender, _ = scenes
    psnr, info = _train(blender, tmp_path / "run", steps=20)
    assert info.center_method == "optical_axes" and "inward-facing" in info.center_reason
    assert np.allclose(info.center, LOOK_AT, atol=1e-9)
    T = np.array(info.world_from_source)
    assert np.allclose(T @ np.array([*LOOK_AT, 1.0]), [0, 0, 0, 1], atol=1e-6)
    assert info.source["kind"] == "synthetic" and "random points" in info.source["initial_points"]
    assert info.scene_scale == pytest.approx(1.0, abs=1e-5)


def test_evaluate_says_its_metrics_are_taken_inside_the_masks(scenes, colmap_run):
    """The object scene's validity masks cover a third of each view: evaluate's PSNR (inside them) is not train's
    (whole images), and both the report's notes and the console line say so."""
    from typer.testing import CliRunner

    from uncertsplat.cli import app
    from uncertsplat.schemas.metrics import EvalReport

    _, _, root = scenes
    res = CliRunner().invoke(app, ["evaluate", str(root / "run_colmap"), "--num-samples", "2", "--set", "max_views=1",
                                   "--device", "cpu"])
    assert res.exit_code == 0, res.output
    assert ("what train reports for the held-out views; train's over whole images, these inside the scene's validity "
            "masks)") in " ".join(res.output.split())
    report = EvalReport.from_json((root / "run_colmap" / "eval" / "metrics.json").read_text(encoding="utf-8"))
    (note,) = [n for n in report.notes if n.startswith("the scene has validity masks")]
    share = float(note.split("(")[1].split("%")[0]) / 100
    assert 0.2 < share < 0.5 and "train's held-out PSNR over whole images" in note
