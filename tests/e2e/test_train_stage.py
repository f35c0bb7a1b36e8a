"""`uncertsplat train` on the tiny synthetic scene: outputs, PSNR gain, refusal, exact resume."""

import json
import shutil

import pytest
import torch

from tests.e2e.test_train_resume import assert_same_parameters
from tests.fixtures import tiny_scene_path  # noqa: F401
from uncertsplat.baselines import load_run
from uncertsplat.config import train_config_from
from uncertsplat.console import q
from uncertsplat.errors import UserError
from uncertsplat.io.checkpoints import list_checkpoints
from uncertsplat.stages import train as stage

# a short schedule on the tiny scene at half resolution (64x48): ~80 steps on a CPU
SHORT = ["iterations=80", "scene.downscale=2.0", "eval_every=40", "checkpoint_every=40", "log_every=20",
         "densify.start=20", "densify.until=60", "densify.interval=20", "densify.spawn_interval=40",
         "densify.max_gaussians=6000"]


@pytest.fixture(scope="module")
def trained(tiny_scene_path, tmp_path_factory):  # noqa: F811
    run = tmp_path_factory.mktemp("train") / "run"
    cfg = train_config_from("tiny", None, SHORT)
    stage.run(tiny_scene_path, run, cfg, torch.device("cpu"))
    return run, cfg


def test_outputs_and_psnr_gain(trained):
    run, cfg = trained
    for name in ("config.json", "scene.json", "stats.jsonl", "point_cloud.ply", "variational.ply",
                 "train_summary.json"):
        assert (run / name).is_file(), name
    assert json.loads((run / "config.json").read_text(encoding="utf-8")) == json.loads(cfg.model_dump_json())
    lines = [json.loads(x) for x in (run / "stats.jsonl").read_text(encoding="utf-8").splitlines()]
    initial = lines[0]["eval_psnr"]
    summary = json.loads((run / "train_summary.json").read_text(encoding="utf-8"))
    assert summary["steps"] == 80 and summary["num_carriers"] > 0
    # the point cloud holds the SH bands the run renders with (80 steps: degree 0, while the model stores 3)
    from plyfile import PlyData

    rest = [p.name for p in PlyData.read(str(run / "point_cloud.ply"))["vertex"].properties
            if p.name.startswith("f_rest_")]
    assert len(rest) == 3 * ((summary["sh_degree_active"] + 1) ** 2 - 1), (len(rest), summary["sh_degree_active"])
    assert summary["test_psnr"] > initial + 2.0, (initial, summary["test_psnr"])
    # the fit of its own photos is recorded, and above the held-out views' (those it never saw)
    assert summary["train_psnr"] > summary["test_psnr"], (summary["train_psnr"], summary["test_psnr"])
    assert summary["memory_per_gaussian_bytes"] > 0 and summary["sec_per_step"] > 0
    post = summary["posterior"]  # how far the posteriors moved from the prior, per carrier
    assert post["carriers"] == summary["num_carriers"] and 0.0 <= post["moved_fraction"] <= 1.0
    assert post["kl_nats"]["q10"] <= post["kl_nats"]["q50"] <= post["kl_nats"]["q90"]
    assert [s for s, _ in list_checkpoints(run)] == [40, 80]
    assert all("num_gaussians" in r for r in lines) and lines[-1]["step"] == 80


def test_load_run_matches_checkpoint(trained):
    run, cfg = trained
    loaded = load_run(run, "cpu")
    assert loaded.source.name == "variational.ply" and loaded.step == 80 and loaded.config == cfg
    assert loaded.scene_path is not None and loaded.scene_path.is_dir()
    from uncertsplat.io.checkpoints import load_latest

    _, state = load_latest(run)
    for name, p in loaded.model.parameters().items():
        assert torch.equal(p.detach(), state["model"]["params" if name in state["model"]["params"] else "tables"][name])


def test_existing_run_is_refused(trained, tiny_scene_path, tmp_path):  # noqa: F811
    run, cfg = trained
    with pytest.raises(UserError, match="already exists") as e:
        stage.run(tiny_scene_path, run, cfg, torch.device("cpu"))
    assert "--resume" in e.value.hint
    # a folder of other files: --resume could not continue it, so it is not suggested
    other = tmp_path / "junk"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    with pytest.raises(UserError, match="not a training run") as e:
        stage.run(tiny_scene_path, other, cfg, torch.device("cpu"))
    assert "--resume" not in e.value.hint and (other / "notes.txt").read_text(encoding="utf-8") == "mine"
    with pytest.raises(UserError, match="the output path is a file, not a folder"):  # (it was called a folder)
        stage.run(tiny_scene_path, other / "notes.txt", cfg, torch.device("cpu"))
    assert (other / "notes.txt").read_text(encoding="utf-8") == "mine"
    # a run of another scene: --resume would be refused on this one, so its own scene is named instead
    elsewhere = tmp_path / "elsewhere"
    shutil.copytree(tiny_scene_path, elsewhere)
    with pytest.raises(UserError, match=r"holds a run of another scene \(") as e:
        stage.run(elsewhere, run, cfg, torch.device("cpu"))
    assert f"uncertsplat train {q(tiny_scene_path.resolve())} -o {q(run)} --resume" in e.value.hint


def test_an_output_folder_among_the_scene_s_photos_is_refused(tiny_scene_path, tmp_path):  # noqa: F811
    """`train SCENE -o SCENE/images/run` trained there, and the next `reconstruct` of those photos (which reads
    subfolders) took the run's renders and maps for photos; refused before anything is written, as `reconstruct` and
    `select-views` refuse it, for the photo folder `reconstruct_report.json` names too."""
    from uncertsplat.schemas import ReconstructReport

    scene = tmp_path / "scene"
    shutil.copytree(tiny_scene_path, scene)
    images = scene / "images"
    before = sorted(p.name for p in images.iterdir())
    cfg = train_config_from("tiny", {"iterations": 2})
    for out in (images, images / "run"):
        with pytest.raises(UserError, match=r"inside the folder of the scene's photos \(.*images\)"):
            stage.run(scene, out, cfg, torch.device("cpu"))
    assert sorted(p.name for p in images.iterdir()) == before
    photos = tmp_path / "photos"  # the folder the workspace was reconstructed from
    photos.mkdir()
    ReconstructReport(success=True, photos=str(photos), images_found=before,
                      registered_fraction=1.0).write(scene / "reconstruct_report.json")
    with pytest.raises(UserError, match=r"inside the folder of the scene's photos \(.*photos\)"):
        stage.run(scene, photos / "run", cfg, torch.device("cpu"))
    assert not list(photos.iterdir())


def test_resume_from_middle_checkpoint_is_exact(trained, tiny_scene_path, tmp_path):  # noqa: F811
    run, cfg = trained
    copy = tmp_path / "run"
    shutil.copytree(run, copy)
    for name in ("point_cloud.ply", "variational.ply", "train_summary.json"):
        (copy / name).unlink()
    (copy / "ckpts" / "step_000080.pt").unlink()
    # a truncated newer checkpoint must be skipped with a message
    (copy / "ckpts" / "step_000060.pt").write_bytes(b"USPLCKPT garbage")
    stage.run(tiny_scene_path, copy, cfg, torch.device("cpu"), resume=True)
    a, b = load_run(run).model, load_run(copy).model
    assert torch.equal(a.posterior_row, b.posterior_row)
    assert_same_parameters(a, b)
    steps = [json.loads(x)["step"] for x in (copy / "stats.jsonl").read_text(encoding="utf-8").splitlines()]
    assert steps == sorted(steps) and len(steps) == len(set(steps))  # no duplicated log lines


def test_resume_with_more_iterations_trains_on(tiny_scene_path, tmp_path):  # noqa: F811
    run = tmp_path / "run"
    cfg = train_config_from("tiny", None, ["iterations=6", "scene.downscale=4.0", "checkpoint_every=3",
                                           "log_every=1", "eval_every=1000"])
    stage.run(tiny_scene_path, run, cfg, torch.device("cpu"))
    stage.run(tiny_scene_path, run, cfg, torch.device("cpu"), resume=True, extend_to=9)
    steps = [json.loads(line)["step"] for line in (run / "stats.jsonl").read_text(encoding="utf-8").splitlines()]
    assert max(steps) == 9
    assert json.loads((run / "config.json").read_text(encoding="utf-8"))["iterations"] == 9
    with pytest.raises(UserError, match="cannot shorten"):
        stage.run(tiny_scene_path, run, cfg, torch.device("cpu"), resume=True, extend_to=4)


def test_resume_on_another_scene_is_refused(trained, tiny_scene_path, tmp_path):  # noqa: F811
    """A run continues on the scene it was trained on: another scene's photos (or the same scene copied with an
    image missing) are refused and nothing in the run changes; a scene folder that moved, with every image, is
    accepted."""
    run, cfg = trained
    copy = tmp_path / "run"
    shutil.copytree(run, copy)
    before = {n: (copy / n).read_bytes() for n in ("config.json", "scene.json", "stats.jsonl")}
    other = tmp_path / "other"
    shutil.copytree(tiny_scene_path, other)
    with pytest.raises(UserError, match="was trained on .*: that scene is still at"):
        stage.run(other, copy, cfg, torch.device("cpu"), resume=True, extend_to=85)
    # moved: the recorded folder is gone; a scene without one of the run's images is not the same scene
    info = json.loads((copy / "scene.json").read_text(encoding="utf-8"))
    info.update(scene=str(tmp_path / "moved-away"), scene_from_run=None)  # (the copy's relative path finds the scene)
    (copy / "scene.json").write_text(json.dumps({**info, "test": [*info["test"], "elsewhere.png"]}))
    with pytest.raises(UserError, match="1 of its images are not in .*elsewhere.png"):
        stage.run(other, copy, cfg, torch.device("cpu"), resume=True, extend_to=85)
    assert json.loads((copy / "config.json").read_bytes()) == json.loads(before["config.json"])
    assert (copy / "stats.jsonl").read_bytes() == before["stats.jsonl"]
    (copy / "scene.json").write_text(json.dumps(info))
    stage.run(other, copy, cfg, torch.device("cpu"), resume=True, extend_to=85)
    assert json.loads((copy / "scene.json").read_text(encoding="utf-8"))["scene"] == str(other.resolve())
    # a finished run moved with its scene: `train NEW_SCENE -o RUN --resume` (what evaluate advises) records the new
    # folder, though it has nothing left to train
    (copy / "scene.json").write_text(json.dumps({**info, "scene": str(tmp_path / "gone-too")}))
    stage.run(other, copy, cfg, torch.device("cpu"), resume=True)
    assert json.loads((copy / "scene.json").read_text(encoding="utf-8"))["scene"] == str(other.resolve())


def test_a_run_moved_with_its_scene_finds_the_scene_beside_it(trained, tiny_scene_path, tmp_path, capsys):  # noqa: F811
    """A project folder (a pipeline's output: the scene and the run side by side) moved elsewhere: every command finds
    the scene beside the run once the place it was trained at is gone, and says so. Never while that place exists: a
    folder beside a run copied alone into another project, or beside a run kept inside its scene and moved out of
    it, may be another scene with the same cameras (a helper's runs scored against another project's photos)."""
    run, cfg = trained
    first = tmp_path / "first"
    shutil.copytree(tiny_scene_path, first / "scene")
    shutil.copytree(run, first / "run")
    info = json.loads((first / "run" / "scene.json").read_text(encoding="utf-8"))
    assert info["scene_from_run"] is not None  # written by train
    info.update(scene=str((first / "scene").resolve()), scene_from_run="../scene")
    (first / "run" / "scene.json").write_text(json.dumps(info))
    assert load_run(first / "run").scene_path == (first / "scene").resolve()
    # copied: the original is still there, and read (the copy's own folder beside it could be anything)
    copy = tmp_path / "copy"
    shutil.copytree(first, copy)
    assert load_run(copy / "run").scene_path == (first / "scene").resolve()
    with pytest.raises(UserError, match="that scene is still at .*first"):
        stage.run(copy / "scene", copy / "run", cfg, torch.device("cpu"), resume=True)
    # the original moved away: each project reads its own scene, and says which
    moved = tmp_path / "moved"
    first.rename(moved)
    for project in (moved, copy):
        loaded = load_run(project / "run")
        assert loaded.scene_path == project.resolve() / "scene"
        capsys.readouterr()
        assert loaded.load_scene().cameras.image_names
        said = " ".join(capsys.readouterr().err.split())
        assert "is gone; reading the folder at the same place relative to the run" in said, said
    stage.run(copy / "scene", copy / "run", cfg, torch.device("cpu"), resume=True)  # recorded, nothing trained
    recorded = json.loads((copy / "run" / "scene.json").read_text(encoding="utf-8"))
    assert (recorded["scene"], recorded["scene_from_run"]) == (str((copy / "scene").resolve()), "../scene")
    # a run moved alone finds nothing beside it: the recorded folder (gone, said as before)
    alone = tmp_path / "alone"
    shutil.copytree(moved / "run", alone)
    assert load_run(alone).scene_path == first.resolve() / "scene"
    with pytest.raises(UserError, match="is gone"):
        load_run(alone).load_scene()
    # another scene beside a run whose own scene exists is never read
    other = tmp_path / "other"
    shutil.copytree(tiny_scene_path, other / "scene")
    shutil.copytree(copy / "run", other / "run")
    assert load_run(other / "run").scene_path == (copy / "scene").resolve()
    # a run kept inside its scene records no relative path: moved out, any folder above it would pass for the scene
    from uncertsplat.schemas.scene import RunScene

    assert RunScene.relative_path(tmp_path, tmp_path / "runs" / "r1") is None
    assert RunScene.relative_path(tmp_path / "scene", tmp_path / "runs" / "r1") == "../../scene"
    # a scene.json of schema version 4 (no scene_from_run) reads the recorded folder
    old = {k: v for k, v in info.items() if k != "scene_from_run"}
    (moved / "run" / "scene.json").write_text(json.dumps({**old, "schema_version": 4}))
    assert load_run(moved / "run").scene_path == first.resolve() / "scene"


def test_a_resumed_run_keeps_its_posterior_updates(tiny_scene_path, tmp_path):  # noqa: F811
    """train_summary.json lists every informed update of the run, those before the checkpoint it resumed from
    too (they are in the checkpoint), so `train`'s posterior line and the report read the same record."""
    run = tmp_path / "run"
    cfg = train_config_from("tiny", None, ["iterations=40", "scene.downscale=4.0", "checkpoint_every=20",
                                           "log_every=10", "eval_every=1000", "variational.refresh_interval=10"])
    stage.run(tiny_scene_path, run, cfg, torch.device("cpu"))
    full = json.loads((run / "train_summary.json").read_text(encoding="utf-8"))["posterior_updates"]
    assert [u["step"] for u in full] == [10, 20, 30, 40]
    (run / "ckpts" / "step_000040.pt").unlink()
    (run / "train_summary.json").unlink()
    stage.run(tiny_scene_path, run, cfg, torch.device("cpu"), resume=True)
    resumed = json.loads((run / "train_summary.json").read_text(encoding="utf-8"))["posterior_updates"]
    assert [u["step"] for u in resumed] == [10, 20, 30, 40]
    assert [u["noise_std"] for u in resumed] == pytest.approx([u["noise_std"] for u in full])


def test_resume_names_only_the_values_the_command_gave(tiny_scene_path, tmp_path):  # noqa: F811
    """`train --resume` uses the run's stored configuration; its note names what this command set that differs
    (here --set seed=5), not the defaults it never gave (the run used the tiny preset's)."""
    from typer.testing import CliRunner

    from uncertsplat.cli import app

    run = tmp_path / "run"
    args = ["train", str(tiny_scene_path), "-o", str(run), "--device", "cpu"]
    first = CliRunner().invoke(app, [*args, "--preset", "tiny", "--set", "iterations=6", "--set", "scene.downscale=4"])
    assert first.exit_code == 0, first.output
    plain = CliRunner().invoke(app, [*args, "--resume"])
    assert plain.exit_code == 0 and "ignoring" not in plain.output, plain.output
    seeded = CliRunner().invoke(app, [*args, "--resume", "--set", "seed=5"])
    assert seeded.exit_code == 0, seeded.output
    note = " ".join(seeded.output.split())
    assert "ignoring the given values of: seed" in note and "densify" not in note
    # --set iterations=N on --resume trains on to N, as --iterations N does
    longer = CliRunner().invoke(app, [*args, "--resume", "--set", "iterations=8"])
    assert longer.exit_code == 0 and "continuing to 8 steps" in " ".join(longer.output.split()), longer.output
    assert json.loads((run / "train_summary.json").read_text(encoding="utf-8"))["steps"] == 8
    # a finished run resumed again says so and trains nothing; without --resume the error says how to go on
    again = CliRunner().invoke(app, [*args, "--resume"])
    assert again.exit_code == 0 and "already trained for its 8 steps, nothing to do" in " ".join(again.output.split())
    assert "resuming from" not in again.output
    fresh = CliRunner().invoke(app, args)
    assert fresh.exit_code == 2 and "trained for 8 steps" in fresh.output and "--iterations N" in fresh.output


def test_a_run_without_a_posterior_is_named_by_evaluate(tiny_scene_path, tmp_path):  # noqa: F811
    """Stopped before any Gaussian carries a posterior, a variational run's samples are all the same render: the
    evaluation notes say so (its metrics looked like any other's); a run with carriers gets no such note."""
    import dataclasses

    from uncertsplat.gaussians.variational import random_model

    run = tmp_path / "run"
    stage.run(tiny_scene_path, run, train_config_from("tiny", None, ["iterations=2", "scene.downscale=4.0"]),
              torch.device("cpu"))
    loaded = load_run(run)
    assert loaded.model.num_carriers == 0
    (note,) = loaded.eval_notes(4)
    assert "no Gaussian carries a posterior" in note
    assert "the run's 2 steps end before Gaussians first get a posterior" in note
    from uncertsplat.config import EvalConfig
    from uncertsplat.stages import evaluate

    report = evaluate.run(run, EvalConfig(num_samples=2, max_views=1, save_maps=False), device=torch.device("cpu"))
    (std,) = [n for n in report.notes if n.startswith("std² = ")]  # its formula agrees: the spread term is 0
    assert std.startswith("std² = the variance of the K samples (0 for this model: every sample is the same render) + ")
    carriers = dataclasses.replace(loaded, model=random_model(20, torch.Generator().manual_seed(0)))
    assert carriers.model.num_carriers > 0 and carriers.eval_notes(4) == []
    # prune refuses it with the same reason (it said: train "for at least one spawn interval")
    # (NoPosterior: a pipeline skips the stage and goes on to its report)
    from uncertsplat.config import PruneConfig
    from uncertsplat.errors import NoPosterior
    from uncertsplat.stages import prune

    with pytest.raises(NoPosterior, match="no uncertainty to prune by: the run's 2 steps end before Gaussians first"):
        prune.run(run, tmp_path / "pruned", PruneConfig(keep_ratio=0.9), torch.device("cpu"))
    # a prune's output with no carrier left: pruning removed them (not the spawn rule, of which train said nothing)
    (run / "prune.json").write_text("{}")
    (note,) = load_run(run).eval_notes(4)
    assert "pruning removed every Gaussian that carried one" in note and "spawn" not in note


def _trained_on_a_workspace(tiny_scene_path, tmp_path, *settings: str):
    """(workspace, run, config): the tiny scene's images and COLMAP model copied to ``ws``, a run of 6 steps on it."""
    ws = tmp_path / "ws"
    ws.mkdir()
    shutil.copytree(tiny_scene_path / "images", ws / "images")
    shutil.copytree(tiny_scene_path / "sparse", ws / "sparse")
    run = tmp_path / "run"
    cfg = train_config_from("tiny", None, ["iterations=6", "scene.downscale=4.0", "eval_every=1000", *settings])
    stage.run(ws, run, cfg, torch.device("cpu"))
    return ws, run, cfg


def test_a_scene_whose_cameras_changed_is_refused(tiny_scene_path, tmp_path):  # noqa: F811
    """A workspace reconstructed again after training (here: the same COLMAP model moved by a similarity, as a new
    SfM run's arbitrary frame would be) no longer lines up with the model: evaluate's scene load and a resume are
    refused and name the change, and the run's files stay as they were; the model written back unchanged loads."""
    pycolmap = pytest.importorskip("pycolmap")
    import numpy as np

    ws, run, cfg = _trained_on_a_workspace(tiny_scene_path, tmp_path, "checkpoint_every=3", "log_every=3")
    recorded = json.loads((run / "scene.json").read_text(encoding="utf-8"))["cameras"]
    assert len(recorded) == 24 and all(len(v) == 13 for v in recorded.values())
    model = pycolmap.Reconstruction(str(ws / "sparse" / "0"))
    model.write(str(ws / "sparse" / "0"))  # the same cameras written again: nothing changed
    load_run(run).load_scene()
    a = np.deg2rad(0.05)  # a tenth of a pixel at the tiny scene's 32 px across: below what SfM runs agree to
    turn = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    model.transform(pycolmap.Sim3d(1.0, pycolmap.Rotation3d(turn), np.zeros(3)))
    model.write(str(ws / "sparse" / "0"))
    before = {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()}
    with pytest.raises(UserError, match=r"cameras have changed since this run was trained: 24 of its 24 views' "
                                        r"cameras .*turned 0\.05 degrees") as err:
        load_run(run).load_scene()
    assert "reconstructed again" in err.value.hint and "train" in err.value.hint
    with pytest.raises(UserError, match="cameras have changed .*training on would spoil it"):
        stage.run(ws, run, cfg, torch.device("cpu"), resume=True, extend_to=9)
    assert {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()} == before


def test_a_scene_aligned_to_other_units_after_training_is_evaluated_in_them(tiny_scene_path, tmp_path):  # noqa: F811
    """The COLMAP model scaled x1000 after training (aligned to millimetres): its cameras agree in the run's frame, so
    the run loads, with a note; evaluate scores it again in the new units (it kept the old evaluation, whose maps'
    depths were in the old ones, while the Predictor used the new), and keeps an evaluation made in them."""
    pycolmap = pytest.importorskip("pycolmap")
    import numpy as np

    from uncertsplat.config import EvalConfig
    from uncertsplat.io.images import read_exr_attribute
    from uncertsplat.io.maps import EXR_DEPTH_TO_SOURCE
    from uncertsplat.schemas import EvalReport
    from uncertsplat.sfm.scene import frame_change
    from uncertsplat.stages import evaluate

    ws, run, cfg = _trained_on_a_workspace(tiny_scene_path, tmp_path)
    subset = tmp_path / "subset"  # a run on some of the photos (the others unused, as select-views grows them)
    stage.run(ws, subset, train_config_from("tiny", None, ["iterations=3", "scene.downscale=4.0", "eval_every=1000",
                                                           "scene.train_names=[view_001.png,view_005.png,view_009.png]"]),
              torch.device("cpu"))
    ecfg = EvalConfig(num_samples=2, max_views=1)
    evaluate.run(run, ecfg, device=torch.device("cpu"))

    def factor():
        return read_exr_attribute(next((run / "eval" / "maps").glob("*.exr")), EXR_DEPTH_TO_SOURCE)

    before = factor()

    def scale(s):
        model = pycolmap.Reconstruction(str(ws / "sparse" / "0"))
        model.transform(pycolmap.Sim3d(s, pycolmap.Rotation3d(), np.zeros(3)))
        model.write(str(ws / "sparse" / "0"))

    scale(1000.0)
    loaded = load_run(run)
    loaded.load_scene()
    assert "its units are 1000x the ones the run was trained in" in loaded.frame_note
    part = load_run(subset)  # its unused photos are no photos joined since: the same frame change, not a refusal
    part.load_scene()
    assert "its units are 1000x" in part.frame_note
    evaluate.run(run, ecfg, device=torch.device("cpu"))
    assert factor() == pytest.approx(1000.0 * before, rel=1e-5)
    report = EvalReport.read(run / "eval" / "metrics.json")
    assert any("frame is not the one the run was trained in" in n for n in report.notes)
    written = (run / "eval" / "metrics.json").read_bytes()
    evaluate.run(run, ecfg, device=torch.device("cpu"))  # made in these units: kept
    assert (run / "eval" / "metrics.json").read_bytes() == written
    scale(0.001)  # back to the frame it was trained in: the mm evaluation is not kept
    again = load_run(run)
    again.load_scene()
    assert again.frame_note is None
    evaluate.run(run, ecfg, device=torch.device("cpu"))
    assert factor() == pytest.approx(before, rel=1e-5)
    # the comparison itself
    T = np.eye(4)
    T[:3, :3] *= 0.25
    moved = T.copy()
    moved[:3, :3] *= 1e-3
    moved[:3, 3] = [0.5, 0.0, 0.0]
    assert frame_change(T, T) is None
    assert frame_change(T, moved) == "its units are 1000x the ones the run was trained in, its origin moved"


def test_a_start_that_failed_before_training_can_be_run_again(tiny_scene_path, tmp_path):  # noqa: F811
    """train stopped by a photo it could not read left config.json and scene.json, and the same command said "the run
    folder already exists ... --resume"; it now records them once the photos read, so nothing is left to refuse:
    once the photo is mended the same command starts the run, while a run with a step trained is still refused."""
    scene = tmp_path / "scene"
    shutil.copytree(tiny_scene_path, scene)
    photo = scene / "images" / "view_001.png"
    good = photo.read_bytes()
    photo.write_bytes(good[: len(good) // 3])
    run = tmp_path / "run"
    cfg = train_config_from("tiny", None, ["iterations=2", "scene.downscale=4.0", "checkpoint_every=1000",
                                           "log_every=1", "eval_every=1000"])
    with pytest.raises(UserError):
        stage.run(scene, run, cfg, torch.device("cpu"))
    assert not (run / "config.json").is_file() and not list_checkpoints(run)
    photo.write_bytes(good)
    stage.run(scene, run, cfg, torch.device("cpu"))
    assert (run / "train_summary.json").is_file()
    with pytest.raises(UserError, match="already exists and holds a run trained for 2 steps"):
        stage.run(scene, run, cfg, torch.device("cpu"))


def test_a_run_that_failed_before_its_first_checkpoint_starts_again_with_new_settings(tiny_scene_path, tmp_path,
                                                                                      capsys):  # noqa: F811
    """Memory that ran out at step 5 left config.json, scene.json and a stats.jsonl with logged steps: the same
    command with a larger downscale was refused ("Add --resume"), and --resume ignored the new downscale and ran out
    again. With no checkpoint there is nothing to resume from: the command starts the run with its new settings."""
    done = tmp_path / "done"
    cfg = train_config_from("tiny", None, ["iterations=3", "scene.downscale=4.0", "checkpoint_every=1000",
                                           "log_every=1", "eval_every=1000"])
    stage.run(tiny_scene_path, done, cfg, torch.device("cpu"))
    run = tmp_path / "run"
    (run / "ckpts").mkdir(parents=True)
    for name in ("config.json", "scene.json", "stats.jsonl"):
        shutil.copy(done / name, run / name)
    capsys.readouterr()
    smaller = cfg.model_copy(update={"scene": cfg.scene.model_copy(update={"downscale": 8.0})})
    stage.run(tiny_scene_path, run, smaller, torch.device("cpu"))
    said = " ".join(capsys.readouterr().err.split())
    assert "holds a run that failed before its first checkpoint (step 3 logged), so there is nothing to resume from; " \
           "starting it again (its log kept as stats.failed.jsonl)" in said
    assert (run / "stats.failed.jsonl").read_bytes() == (done / "stats.jsonl").read_bytes()
    assert json.loads((run / "config.json").read_text(encoding="utf-8"))["scene"]["downscale"] == 8.0
    # a finished run is still refused
    with pytest.raises(UserError, match="already exists"):
        stage.run(tiny_scene_path, done, cfg, torch.device("cpu"))


def test_a_finished_run_without_its_checkpoints_is_not_trained_again(tiny_scene_path, tmp_path):  # noqa: F811
    """ckpts/ deleted to save disk: --resume says there is nothing to do, --resume --iterations N (more steps) is
    refused, and the finished model is kept (it trained from step 0 over it)."""
    run = tmp_path / "run"
    cfg = train_config_from("tiny", None, ["iterations=4", "scene.downscale=4.0", "checkpoint_every=2",
                                           "log_every=1", "eval_every=1000"])
    stage.run(tiny_scene_path, run, cfg, torch.device("cpu"))
    shutil.rmtree(run / "ckpts")
    model = (run / "variational.ply").read_bytes()
    stage.run(tiny_scene_path, run, cfg, torch.device("cpu"), resume=True)
    with pytest.raises(UserError, match="checkpoints are gone .*4 steps"):
        stage.run(tiny_scene_path, run, cfg, torch.device("cpu"), resume=True, extend_to=8)
    assert (run / "variational.ply").read_bytes() == model
    assert max(json.loads(x)["step"] for x in (run / "stats.jsonl").read_text(encoding="utf-8").splitlines()) == 4
    # its scene moved: the resume evaluate advises records the new folder (and trains nothing)
    moved = tmp_path / "moved"
    shutil.copytree(tiny_scene_path, moved)
    info = json.loads((run / "scene.json").read_text(encoding="utf-8"))
    (run / "scene.json").write_text(json.dumps({**info, "scene": str(tmp_path / "gone"), "scene_from_run": "../gone"}))
    stage.run(moved, run, cfg, torch.device("cpu"), resume=True)
    assert json.loads((run / "scene.json").read_text(encoding="utf-8"))["scene"] == str(moved.resolve())
    assert (run / "variational.ply").read_bytes() == model


def test_a_finished_run_whose_checkpoints_are_all_damaged_says_so(tiny_scene_path, tmp_path, capsys):  # noqa: F811
    """Every checkpoint truncated: --resume said "its checkpoints are gone (ckpts/ holds none)" with two damaged ones in
    ckpts/. It says they are damaged, and its advice (copy them back from a copy of the run) works."""
    run = tmp_path / "run"
    cfg = train_config_from("tiny", None, ["iterations=4", "scene.downscale=4.0", "checkpoint_every=2",
                                           "log_every=1", "eval_every=1000"])
    stage.run(tiny_scene_path, run, cfg, torch.device("cpu"))
    shutil.copytree(run, tmp_path / "copy")
    for path in (run / "ckpts").iterdir():
        path.write_bytes(path.read_bytes()[:1000])
    capsys.readouterr()
    stage.run(tiny_scene_path, run, cfg, torch.device("cpu"), resume=True)
    said = " ".join(capsys.readouterr().err.split())
    assert "nothing to do (its checkpoints are damaged, so it cannot be trained on)" in said, said
    with pytest.raises(UserError) as err:
        stage.run(tiny_scene_path, run, cfg, torch.device("cpu"), resume=True, extend_to=6)
    said = err.value.render()
    assert "the run's 2 checkpoints in ckpts/ are all damaged" in said and "holds none" not in said, said
    assert "Copy the checkpoints back into ckpts/ from a copy of the run" in said, said
    shutil.rmtree(run / "ckpts")
    shutil.copytree(tmp_path / "copy" / "ckpts", run / "ckpts")
    stage.run(tiny_scene_path, run, cfg, torch.device("cpu"), resume=True, extend_to=6)
    assert json.loads((run / "train_summary.json").read_text(encoding="utf-8"))["steps"] == 6


def test_views_held_out_by_index_are_named(tiny_scene_path, tmp_path, capsys):  # noqa: F811
    """Indices count the scene's views after any photo it left out, so `train` names the views they chose (a user's
    index 11 held out the 11th photo left, not the 11th file of the folder, without a word)."""
    cfg = train_config_from("tiny", None, ["iterations=2", "scene.downscale=4.0", "scene.test_indices=[3, 7]",
                                           "eval_every=1000"])
    stage.run(tiny_scene_path, tmp_path / "run", cfg, torch.device("cpu"))
    said = " ".join(capsys.readouterr().err.split())
    assert "held out (scene.test_indices / train_indices count the scene's 24 views, in name order): view_003.png, " \
           "view_007.png" in said


def test_a_batch_larger_than_the_views_is_said(tiny_scene_path, tmp_path, capsys):  # noqa: F811
    """batch_size above the training views was clamped to them without a word."""
    cfg = train_config_from("tiny", None, ["iterations=2", "scene.downscale=4.0", "batch_size=1000"])
    stage.run(tiny_scene_path, tmp_path / "run", cfg, torch.device("cpu"))
    said = " ".join(capsys.readouterr().err.split())
    assert "batch_size = 1000 is more than the" in said and "each step renders all" in said


def test_a_low_resolution_phase_of_a_few_pixels_is_said(tiny_scene_path, tmp_path, capsys):  # noqa: F811
    """low_res_scale = 1e-12 trained the phase on 1x1 images without a word."""
    cfg = train_config_from("tiny", None, ["iterations=4", "scene.downscale=4.0", "low_res_fraction=0.5",
                                           "low_res_scale=1e-12"])
    stage.run(tiny_scene_path, tmp_path / "run", cfg, torch.device("cpu"))
    said = " ".join(capsys.readouterr().err.split())
    assert "the low-resolution phase (its first 2 steps) trains on 1x1 images (low_res_scale = 1e-12)" in said


def test_a_reset_steps_test_is_of_the_model_before_the_reset(tiny_scene_path, tmp_path, monkeypatch):  # noqa: F811
    """An opacity reset leaves every Gaussian nearly transparent; the held-out test logged at that step read 5-8 dB
    (fern, bonsai: a collapse in the console, stats.jsonl and the report's curve, gone a few hundred steps later).
    The step's test is now rendered before the reset: every test sees opacities above the reset's 0.01, and the
    reset step's PSNR is no collapse. The informed posterior is not updated at that step."""
    from uncertsplat.strategy import schedule
    from uncertsplat.train.trainer import Trainer

    monkeypatch.setattr(schedule, "RESET_RECOVERY_STEPS", 10)  # (a reset in an 80-step run)
    seen = []
    evaluate = Trainer.evaluate

    def watched(self, *args, **kwargs):
        seen.append((self.step, float(self.mean_sample().opacities.detach().max())))
        return evaluate(self, *args, **kwargs)

    monkeypatch.setattr(Trainer, "evaluate", watched)
    cfg = train_config_from("tiny", None, SHORT + ["densify.opacity_reset_interval=40", "variational.refresh_interval=20"])
    assert schedule.is_opacity_reset_step(40, cfg.densify, cfg.iterations)
    stage.run(tiny_scene_path, tmp_path / "run", cfg, torch.device("cpu"))
    assert all(opacity > 0.02 for _, opacity in seen), seen
    records = map(json.loads, (tmp_path / "run" / "stats.jsonl").read_text(encoding="utf-8").splitlines())
    logged = {r["step"]: r["eval_psnr"] for r in records if "eval_psnr" in r}
    assert sorted(logged) == [0, 40, 80]
    assert logged[40] > logged[0], logged
    # nor is the posterior fitted to the reset model (its tables fell back to the prior for refresh_interval steps)
    summary = json.loads((tmp_path / "run" / "train_summary.json").read_text(encoding="utf-8"))
    assert [u["step"] for u in summary["posterior_updates"]] == [20, 60, 80]


def test_a_stop_during_a_reset_step_keeps_its_test_of_the_model_before_the_reset(tiny_scene_path, tmp_path,  # noqa: F811
                                                                               monkeypatch):
    """A Ctrl-C during the reset step's render and backward: the step completes, its test (rendered before the
    reset) is logged with it, and the resume does not test the reset model in its place."""
    from uncertsplat.errors import Interrupted
    from uncertsplat.strategy import schedule
    from uncertsplat.train.trainer import Trainer

    monkeypatch.setattr(schedule, "RESET_RECOVERY_STEPS", 10)
    seen = []
    evaluate, check = Trainer.evaluate, Trainer.check_exposure

    def watched(self, *args, **kwargs):
        seen.append(float(self.mean_sample().opacities.detach().max()))
        return evaluate(self, *args, **kwargs)

    def stop_at_40(self, step):  # a signal arriving mid-step (check_exposure runs after the backward)
        if step == 40:
            self._stop = True
        return check(self, step)

    monkeypatch.setattr(Trainer, "evaluate", watched)
    monkeypatch.setattr(Trainer, "check_exposure", stop_at_40)
    cfg = train_config_from("tiny", None, SHORT + ["densify.opacity_reset_interval=40"])
    run = tmp_path / "run"
    with pytest.raises(Interrupted, match="at step 40"):
        stage.run(tiny_scene_path, run, cfg, torch.device("cpu"))
    monkeypatch.setattr(Trainer, "check_exposure", check)
    stage.run(tiny_scene_path, run, cfg, torch.device("cpu"), resume=True)
    logged = [r for r in map(json.loads, (run / "stats.jsonl").read_text(encoding="utf-8").splitlines()) if "eval_psnr" in r]
    assert [r["step"] for r in logged] == [0, 40, 80]
    assert all(opacity > 0.02 for opacity in seen), seen
    assert logged[1]["eval_psnr"] > logged[0]["eval_psnr"]


def test_steps_outside_fit_leave_no_test_for_it(monkeypatch):
    """``train_step`` called directly (tests, benchmarks) through a reset step renders no test, so the next ``fit``
    tests its own steps, not with one kept from before."""
    from tests.e2e.test_train_resume import toy_config, toy_scene
    from uncertsplat.strategy import schedule
    from uncertsplat.train.trainer import Trainer

    monkeypatch.setattr(schedule, "RESET_RECOVERY_STEPS", 5)
    calls = []
    evaluate = Trainer.evaluate

    def watched(self, *args, **kwargs):
        calls.append(self.step)
        return evaluate(self, *args, **kwargs)

    monkeypatch.setattr(Trainer, "evaluate", watched)
    scene, tr, te = toy_scene()
    cfg = toy_config()
    trainer = Trainer(scene, cfg, tr, te)
    assert schedule.is_opacity_reset_step(20, cfg.densify, cfg.iterations) and 20 % cfg.eval_every == 0
    trainer.fit(until=5)  # (a fit before: what it knew of its own steps ends with it)
    calls.clear()
    for _ in range(15):
        trainer.train_step()
    assert trainer.step == 20 and calls == []
    logged = []
    trainer.on_log = logged.append
    trainer.fit(until=21)
    assert calls == [21] and [r["step"] for r in logged if "eval_psnr" in r] == [21]


def test_a_pruned_run_whose_scene_moved_is_not_advised_a_resume(trained, tiny_scene_path, tmp_path,  # noqa: F811
                                                                  capsys):
    """`train --resume` refuses a pruned model (no checkpoint to go on from), yet the scene-gone error advised
    `uncertsplat train NEW_SCENE_FOLDER -o PRUNED --resume` for one, and the moved-scene note said it "records" the
    new folder: they say where to put the scene instead. A training run keeps its advice."""
    run, _ = trained
    project = tmp_path / "project"
    for name in ("pruned", "run"):
        shutil.copytree(run, project / name, ignore=shutil.ignore_patterns("ckpts", ".lock", "eval"))
        info = json.loads((project / name / "scene.json").read_text(encoding="utf-8"))
        info.update(scene=str(tmp_path / "gone"), scene_from_run="../scene")
        (project / name / "scene.json").write_text(json.dumps(info))
    (project / "pruned" / "prune.json").write_text("{}")  # (a prune output, as its file marks it)
    with pytest.raises(UserError, match="the scene this run was trained on is gone") as err:
        load_run(project / "pruned").load_scene()
    assert "NEW_SCENE_FOLDER" not in err.value.hint and "has no checkpoint" in err.value.hint, err.value.hint
    assert f"or at {(project / 'scene').resolve()}, its place relative to the run" in err.value.hint, err.value.hint
    # recorded where its place relative to the run is: that place is named once
    moved = project / "pruned" / "scene.json"
    kept = moved.read_text(encoding="utf-8")
    moved.write_text(json.dumps({**json.loads(kept), "scene": str((project / "scene").resolve())}))
    with pytest.raises(UserError, match="the scene this run was trained on is gone") as err:
        load_run(project / "pruned").load_scene()
    assert "or at" not in err.value.hint and "has no checkpoint" in err.value.hint, err.value.hint
    moved.write_text(kept)
    with pytest.raises(UserError, match="the scene this run was trained on is gone") as err:
        load_run(project / "run").load_scene()
    assert "NEW_SCENE_FOLDER" in err.value.hint
    shutil.copytree(tiny_scene_path, project / "scene")
    capsys.readouterr()
    load_run(project / "pruned").load_scene()
    said = " ".join(capsys.readouterr().err.split())
    assert "reading the folder at the same place relative to the run" in said and "records it" not in said, said
    load_run(project / "run").load_scene()
    said = " ".join(capsys.readouterr().err.split())
    assert "reading the folder at the same place relative to the run" in said and "--resume` records it" in said, said
