"""The synthetic scene generator: determinism, exact GT depth, the COLMAP model, the `synth` stage and CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from tests.fixtures import tiny_scene_path  # noqa: F401
from uncertsplat.cli import app
from uncertsplat.config import SceneConfig, SynthConfig
from uncertsplat.data.synthetic import generate_scene, orbit_cameras, resolve_size
from uncertsplat.errors import UserError
from uncertsplat.sfm.scene import load_scene

SMALL = {"preset": "tiny", "num_views": 4, "width": 32}


def _files(root):
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_same_seed_same_bytes_other_seed_differs(tmp_path):
    a = generate_scene(tmp_path / "a", SynthConfig(**SMALL, seed=3))
    b = generate_scene(tmp_path / "b", SynthConfig(**SMALL, seed=3))
    c = generate_scene(tmp_path / "c", SynthConfig(**SMALL, seed=4))
    fa, fb, fc = _files(a), _files(b), _files(c)
    assert fa.keys() == fb.keys()
    assert len([k for k in fa if k.startswith("images/")]) == 4
    for k in fa:
        assert fa[k] == fb[k], k
    assert fa["images/view_000.png"] != fc["images/view_000.png"]


def test_every_folder_gets_the_permissions_of_any_output(tmp_path):
    """Folders built in a temporary folder and renamed into place (the scene, its COLMAP model) were left 0700 by
    mkdtemp: unreadable to the other users of a shared disk (a Ray sweep's workers)."""
    from uncertsplat.io.atomic import current_umask

    out = generate_scene(tmp_path / "new" / "scene", SynthConfig(**SMALL, seed=3))
    want = 0o777 & ~current_umask()
    folders = [out, *(p for p in out.rglob("*") if p.is_dir())]
    assert any(p.name == "0" and p.parent.name == "sparse" for p in folders)
    assert {p.relative_to(tmp_path).as_posix(): oct(p.stat().st_mode & 0o777) for p in folders} == \
        {p.relative_to(tmp_path).as_posix(): oct(want) for p in folders}


def test_layout_and_metadata(tiny_scene_path):  # noqa: F811
    meta = json.loads((tiny_scene_path / "scene.json").read_text(encoding="utf-8"))
    n, w, h, _ = resolve_size(SynthConfig(preset="tiny"))
    assert (meta["width"], meta["height"], meta["num_views"]) == (w, h, n) == (128, 96, 24)
    names = meta["image_names"]
    assert names == sorted(names)
    assert meta["test_views"] == names[::8]
    for name in names:
        stem = name[:-4]
        assert (tiny_scene_path / "images" / name).is_file()
        d = np.load(tiny_scene_path / "depth" / f"{stem}.npy")
        assert d.shape == (h, w) and d.dtype == np.float32
        assert np.all(d > 0) and np.all(np.isfinite(d))  # the room is closed: every pixel hits
        assert (tiny_scene_path / "masks" / f"{stem}.png").is_file()
    assert meta["num_points"] > 500


def test_images_are_textured(tiny_scene_path):  # noqa: F811
    from uncertsplat.io.images import read_image

    img = read_image(tiny_scene_path / "images" / "view_000.png")
    assert img.std() > 0.1  # not flat
    # high-frequency detail: neighbouring pixels differ noticeably on average
    assert np.abs(np.diff(img, axis=1)).mean() > 0.03
    # colour variety: several hues, not a grey image
    assert (img.max(-1) - img.min(-1)).mean() > 0.1


def test_loaded_cameras_equal_the_generator(tiny_scene_path):  # noqa: F811
    scene = load_scene(tiny_scene_path, SceneConfig(normalize=False))
    c2w, K = orbit_cameras(24, 128, 96, seed=0)
    torch.testing.assert_close(scene.cameras.cam_from_world, c2w.float(), atol=1e-5, rtol=0)
    torch.testing.assert_close(scene.cameras.K, K.float().expand(24, 3, 3), atol=1e-5, rtol=0)
    assert scene.cameras.image_names == tuple(f"view_{i:03d}.png" for i in range(24))
    assert scene.split["test"] == (0, 8, 16)
    assert scene.depth_paths is not None and scene.mask_paths is not None


def _bilinear(depth, uv):
    """Sample depth [H,W] at pixel positions uv [N,2] (centres at +0.5)."""
    H, W = depth.shape
    x = uv[:, 0] - 0.5
    y = uv[:, 1] - 0.5
    x0 = np.clip(np.floor(x).astype(int), 0, W - 2)
    y0 = np.clip(np.floor(y).astype(int), 0, H - 2)
    fx, fy = x - x0, y - y0
    d = depth
    return ((1 - fx) * (1 - fy) * d[y0, x0] + fx * (1 - fy) * d[y0, x0 + 1]
            + (1 - fx) * fy * d[y0 + 1, x0] + fx * fy * d[y0 + 1, x0 + 1])


def _reproject(scene, depths, i, j):
    """Lift every pixel of view i with its depth, project into view j: (agreement mask, rel. error)."""
    cams = scene.cameras
    H, W = cams.height, cams.width
    v, u = np.mgrid[0:H, 0:W]
    uv = np.stack([u + 0.5, v + 0.5], -1).reshape(-1, 2)
    K = cams.K.double().numpy()
    z = depths[i].reshape(-1)
    rays = np.concatenate([(uv - K[i, :2, 2]) / np.diag(K[i])[:2], np.ones((uv.shape[0], 1))], -1)
    p_cam = rays * z[:, None]
    world_from_i = np.linalg.inv(cams.cam_from_world[i].double().numpy())
    p_world = p_cam @ world_from_i[:3, :3].T + world_from_i[:3, 3]
    j_from_world = cams.cam_from_world[j].double().numpy()
    pj = p_world @ j_from_world[:3, :3].T + j_from_world[:3, 3]
    uvj = (pj @ K[j].T)[:, :2] / pj[:, 2:3]
    inside = (pj[:, 2] > 0) & (uvj[:, 0] > 1) & (uvj[:, 0] < W - 1) & (uvj[:, 1] > 1) & (uvj[:, 1] < H - 1)
    dj = _bilinear(depths[j], uvj[inside])
    return np.abs(dj - pj[inside, 2]) / pj[inside, 2], inside.mean()


def test_gt_depth_is_consistent_across_views(tiny_scene_path):  # noqa: F811
    """A pixel lifted with its depth and seen from a neighbouring view lands on that view's surface."""
    from uncertsplat.data.dataset import load_depths

    scene = load_scene(tiny_scene_path, SceneConfig(normalize=False))
    depths = load_depths(scene)[..., 0].double().numpy()
    for i, j in [(0, 1), (5, 6), (12, 11)]:
        err, frac_inside = _reproject(scene, depths, i, j)
        assert frac_inside > 0.5
        # most points are visible in the neighbour and agree to interpolation accuracy; the rest are
        # occluded or sit on depth edges
        assert np.median(err) < 2e-3, (i, j, np.median(err))
        assert (err < 1e-2).mean() > 0.7
    # the check can fail: with the wrong pose for view j the depths no longer agree
    err, _ = _reproject(scene, depths, 0, 1)
    wrong = scene.cameras.cam_from_world.clone()
    wrong[1] = scene.cameras.cam_from_world[3]
    from dataclasses import replace

    bad = replace(scene, cameras=replace(scene.cameras, cam_from_world=wrong))
    err_bad, _ = _reproject(bad, depths, 0, 1)
    assert np.median(err_bad) > 10 * max(np.median(err), 1e-4)
    assert (err_bad < 1e-2).mean() < 0.5 * (err < 1e-2).mean()


def test_sparse_points_lie_on_the_surface(tiny_scene_path):  # noqa: F811
    from uncertsplat.data.dataset import load_depths

    scene = load_scene(tiny_scene_path, SceneConfig())  # normalised: depths converted with the same scale
    depths = load_depths(scene)[..., 0].double().numpy()
    pts = scene.points.double().numpy()
    cams = scene.cameras
    agree = np.zeros((len(cams), len(pts)), dtype=bool)
    for i in range(len(cams)):
        M = cams.cam_from_world[i].double().numpy()
        pc = pts @ M[:3, :3].T + M[:3, 3]
        uv = (pc @ cams.K[i].double().numpy().T)[:, :2] / np.maximum(pc[:, 2:3], 1e-9)
        ok = (pc[:, 2] > 0) & (uv[:, 0] > 1) & (uv[:, 0] < cams.width - 1) & (uv[:, 1] > 1) & (uv[:, 1] < cams.height - 1)
        rel = np.abs(_bilinear(depths[i], uv[ok]) - pc[ok, 2]) / pc[ok, 2]
        agree[i, ok] = rel < 1e-2
    # every point is a surface point seen (unoccluded) in at least two views, like a triangulated point
    assert (agree.sum(0) >= 2).mean() > 0.95
    assert agree.sum(0).mean() > 4


# ------------------------------------------------------------------------------------------ stage + CLI
runner = CliRunner()


def test_cli_synth_writes_a_scene(tmp_path):
    out = tmp_path / "scene"
    result = runner.invoke(app, ["synth", str(out), "--preset", "tiny", "--seed", "2",
                                 "--set", "num_views=4", "--set", "width=32"])
    assert result.exit_code == 0, result.output
    meta = json.loads((out / "scene.json").read_text(encoding="utf-8"))
    assert (meta["seed"], meta["num_views"], meta["width"]) == (2, 4, 32)
    assert len(list((out / "images").glob("*.png"))) == 4
    assert not (out / ".lock").exists()
    assert [p.name for p in tmp_path.iterdir()] == ["scene"]  # no temp folders left behind
    # the same command again: nothing to do
    again = runner.invoke(app, ["synth", str(out), "--preset", "tiny", "--seed", "2",
                                "--set", "num_views=4", "--set", "width=32"])
    assert again.exit_code == 0 and "nothing to do" in again.output
    # another seed into the same folder is refused without --overwrite ...
    other = runner.invoke(app, ["synth", str(out), "--preset", "tiny", "--seed", "5",
                                "--set", "num_views=4", "--set", "width=32"])
    assert other.exit_code == 2 and "Traceback" not in other.output and "--overwrite" in other.output
    # ... and accepted with it
    forced = runner.invoke(app, ["synth", str(out), "--preset", "tiny", "--seed", "5", "--overwrite",
                                 "--set", "num_views=4", "--set", "width=32"])
    assert forced.exit_code == 0, forced.output
    assert json.loads((out / "scene.json").read_text(encoding="utf-8"))["seed"] == 5


def test_cli_synth_takes_its_folder_as_the_other_commands_do(tmp_path):
    """``-o OUT`` as in train, reconstruct, prune, ... (a user typing ``synth -o OUT`` got "No such option: -o"); one
    folder, not two, and none is a clear error."""
    out = tmp_path / "scene"
    small = ["--preset", "tiny", "--set", "num_views=4", "--set", "width=32"]
    result = runner.invoke(app, ["synth", "-o", str(out), *small])
    assert result.exit_code == 0, result.output
    assert (out / "scene.json").is_file()
    assert runner.invoke(app, ["synth", str(out), "-o", str(out), *small]).exit_code == 0  # the same folder twice
    assert runner.invoke(app, ["synth", str(out), "-o", str(out / ".." / "scene"), *small]).exit_code == 0
    two = runner.invoke(app, ["synth", str(out), "-o", str(tmp_path / "other"), *small])
    assert two.exit_code == 2 and "two output folders" in two.output and not (tmp_path / "other").exists()
    none = runner.invoke(app, ["synth", *small])
    assert none.exit_code == 2 and "synth OUT (or -o OUT)" in none.output and "Traceback" not in none.output


def test_cli_synth_stopped_says_what_is_on_disk(tmp_path, monkeypatch):
    """Ctrl-C during synth said "the scene folder is unfinished ... the same command with --overwrite writes it again"
    where no folder was left (the scene is rendered into a temporary folder) and the plain command works; into a
    folder that held a scene (--overwrite), that scene is left as it was. Each advice is followed."""
    from uncertsplat.stages import synth

    real = synth.generate_scene

    def stopped(out, cfg, overwrite=False, on_view=None):
        def stop(done, total):
            raise KeyboardInterrupt

        return real(out, cfg, overwrite=overwrite, on_view=stop)

    out = tmp_path / "scene"
    small = ["--preset", "tiny", "--set", "num_views=3", "--set", "width=16"]
    monkeypatch.setattr(synth, "generate_scene", stopped)
    result = runner.invoke(app, ["synth", str(out), *small])
    said = " ".join(result.output.split())
    assert result.exit_code == 130 and "interrupted:" in said and "nothing was written" in said, said
    assert "--overwrite" not in said and "The same command writes the scene." in said, said
    assert list(tmp_path.iterdir()) == []
    monkeypatch.setattr(synth, "generate_scene", real)
    assert runner.invoke(app, ["synth", str(out), *small]).exit_code == 0  # the same command
    scene = (out / "scene.json").read_bytes()
    monkeypatch.setattr(synth, "generate_scene", stopped)
    result = runner.invoke(app, ["synth", str(out), *small, "--seed", "3", "--overwrite"])
    said = " ".join(result.output.split())
    assert result.exit_code == 130 and "the folder holds what it held before" in said, said
    assert (out / "scene.json").read_bytes() == scene and [p.name for p in tmp_path.iterdir()] == ["scene"]
    monkeypatch.setattr(synth, "generate_scene", real)
    assert runner.invoke(app, ["synth", str(out), *small, "--seed", "3", "--overwrite"]).exit_code == 0
    assert json.loads((out / "scene.json").read_text(encoding="utf-8"))["seed"] == 3


def test_cli_synth_refuses_a_foreign_folder(tmp_path):
    (tmp_path / "notes.txt").write_text("mine")
    result = runner.invoke(app, ["synth", str(tmp_path), "--preset", "tiny", "--set", "num_views=3",
                                 "--set", "width=16"])
    assert result.exit_code == 2
    assert "not empty" in result.output and str(tmp_path.name) in result.output


def test_overwrite_keeps_unrelated_files(tmp_path):
    from uncertsplat.stages import synth

    (tmp_path / "notes.txt").write_text("mine")
    synth.run(tmp_path, SynthConfig(preset="tiny", num_views=3, width=16), overwrite=True)
    assert (tmp_path / "notes.txt").read_text(encoding="utf-8") == "mine"
    assert (tmp_path / "scene.json").is_file()


def test_a_training_run_is_refused_even_with_overwrite(tmp_path):
    (tmp_path / "config.json").write_text("{}")
    (tmp_path / "train_summary.json").write_text("{}")
    (tmp_path / "scene.json").write_text('{"scene": "elsewhere"}')
    result = runner.invoke(app, ["synth", str(tmp_path), "--preset", "tiny", "--overwrite", "--set", "num_views=3",
                                 "--set", "width=16"])
    flat = " ".join(result.output.split())
    assert result.exit_code == 2 and "holds a training run" in flat
    assert (tmp_path / "scene.json").read_text(encoding="utf-8") == '{"scene": "elsewhere"}' and not (tmp_path / "images").exists()


def test_unknown_synth_key_is_rejected():
    result = runner.invoke(app, ["synth", "x", "--set", "num_veiws=3"])
    assert result.exit_code == 2 and "num_veiws" in result.output


def test_generate_refuses_non_empty_without_overwrite(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "f").write_text("x")
    with pytest.raises(UserError):
        generate_scene(tmp_path / "a", SynthConfig(**SMALL))


class TestViewsOnThreads:
    """`generate_scene` renders views on as many Python threads as the caller's torch threads (one intra-op
    thread each); the scene must not depend on how many."""

    @staticmethod
    def _with_threads(n, fn):
        before = torch.get_num_threads()
        torch.set_num_threads(n)
        try:
            return fn()
        finally:
            torch.set_num_threads(before)

    def test_same_bytes_on_one_and_on_three_threads(self, tmp_path):
        cfg = SynthConfig(preset="tiny", num_views=7, width=24, seed=5)  # more views than twice the workers
        one = self._with_threads(1, lambda: generate_scene(tmp_path / "one", cfg))
        three = self._with_threads(3, lambda: generate_scene(tmp_path / "three", cfg))
        f1, f3 = _files(one), _files(three)
        assert f1.keys() == f3.keys() and len([k for k in f1 if k.startswith("images/")]) == 7
        for k in f1:
            assert f1[k] == f3[k], k

    def test_the_callers_thread_count_is_restored_and_progress_is_in_order(self, tmp_path):
        seen = []
        before = self._with_threads(3, lambda: (
            generate_scene(tmp_path / "s", SynthConfig(**SMALL), on_view=lambda i, n: seen.append((i, n))),
            torch.get_num_threads())[1])
        assert before == 3
        assert seen == [(i, 4) for i in range(1, 5)]

    def test_a_failed_write_leaves_no_folder_behind(self, tmp_path, monkeypatch):
        from tests.fixtures import fail_png_write

        fail_png_write(monkeypatch, 5)
        with pytest.raises(OSError, match="disk full"):
            self._with_threads(2, lambda: generate_scene(tmp_path / "s", SynthConfig(**SMALL)))
        assert not (tmp_path / "s").exists()
        assert [p.name for p in tmp_path.iterdir()] == []  # the temporary sibling is gone too
