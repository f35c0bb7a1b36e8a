"""Trainer on an in-memory toy scene: exact resume, scene-scale equivariance, interrupt + checkpoint."""

import math

import pytest
import torch

from tests.fixtures import tiny_scene_path  # noqa: F401
from tests.run_fixtures import tiny_run_path  # noqa: F401
from uncertsplat.config import train_config_from
from uncertsplat.gaussians.variational import random_model
from uncertsplat.render import render
from uncertsplat.train.trainer import Trainer
from uncertsplat.types import Cameras, SceneData


def look_at(eye: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """cam_from_world [4,4] (OpenCV axes) of a camera at ``eye`` looking at ``target`` (z up world)."""
    z = torch.nn.functional.normalize(target - eye, dim=0)
    x = torch.nn.functional.normalize(torch.linalg.cross(z, torch.tensor([0.0, 0.0, 1.0])), dim=0)
    y = torch.linalg.cross(z, x)
    R = torch.stack([x, y, z])
    m = torch.eye(4)
    m[:3, :3] = R
    m[:3, 3] = -R @ eye
    return m


def toy_scene(scale: float = 1.0, n_views: int = 8, width: int = 48, height: int = 36, seed: int = 0):
    """Cameras on a ring of radius 1 (x scale) around ~150 random Gaussians; images rendered from them."""
    g = torch.Generator().manual_seed(seed)
    gt = random_model(150, g, sh_degree=0, carrier_fraction=0.0, extent=0.8)
    with torch.no_grad():
        gt.params["opacities"].fill_(2.0)
        gt.params["sh0"].mul_(3.0)
    mats = []
    for i in range(n_views):
        a = 2 * math.pi * i / n_views
        eye = torch.tensor([math.cos(a), math.sin(a), 0.3]) * 2.0
        mats.append(look_at(eye, torch.zeros(3)))
    cam_from_world = torch.stack(mats)
    f = 0.9 * width
    K = torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]]).expand(n_views, 3, 3).clone()
    cams = Cameras(cam_from_world, K, width, height, tuple(f"v{i}.png" for i in range(n_views)))
    from uncertsplat.gaussians.variational import posterior_mean

    with torch.no_grad():
        images = render(posterior_mean(gt), cams, background=torch.zeros(3)).rgb.clamp(0, 1)
    # start from noisy copies of the true centres (the "sparse points")
    pts = gt.params["means"].detach() + 0.03 * torch.randn(150, 3, generator=g)
    rgb = torch.rand(150, 3, generator=g)
    cams_s = Cameras(cam_from_world.clone(), K, width, height, cams.image_names)
    cams_s.cam_from_world[:, :3, 3] *= scale
    test = tuple(range(0, n_views, 4))
    train = tuple(i for i in range(n_views) if i not in test)
    scene = SceneData(cameras=cams_s, image_paths=tuple(), split={"train": train, "test": test},
                      points=pts * scale, points_rgb=rgb, scene_scale=2.0 * scale, world_from_source=torch.eye(4))
    return scene, images[list(train)], images[list(test)]


def toy_config(**extra):
    data = {"iterations": 30, "sh_degree": 1, "sh_degree_interval": 10, "log_every": 5, "eval_every": 20,
            "checkpoint_every": 10,
            "densify": {"start": 5, "until": 25, "interval": 10, "spawn_interval": 10, "opacity_reset_interval": 20,
                        "spawn_scale_fraction": 0.005, "grad_threshold": 2e-3, "max_gaussians": 400}}
    data.update(extra)
    return train_config_from(None, data)


def assert_same_parameters(a, b, atol: float = 1e-6) -> None:
    """Every parameter tensor of model ``b`` equals model ``a``'s to ``atol``."""
    for name, p in a.parameters().items():
        torch.testing.assert_close(b.parameters()[name], p, rtol=0, atol=atol, msg=name)


def assert_resume_is_exact(cfg, until: int):
    """A toy-scene run stopped at step ``until``, its state through a checkpoint's bytes, resumed to the end,
    ends with the parameters of the run that was never stopped; returns that uninterrupted trainer."""
    from uncertsplat.io.checkpoints import decode, encode

    scene, tr, te = toy_scene()
    full = Trainer(scene, cfg, tr, te)
    full.fit()
    part = Trainer(scene, cfg, tr, te)
    part.fit(until=until)
    resumed = Trainer(scene, cfg, tr, te, state=decode(encode(part.state_dict())))
    resumed.fit()
    assert resumed.step == full.step == cfg.iterations
    assert_same_parameters(full.model, resumed.model)
    return full


def test_resume_equals_uninterrupted(tmp_path):
    scene, tr, te = toy_scene()
    cfg = toy_config()
    full = Trainer(scene, cfg, tr, te)
    full.fit()
    assert full.model.num_carriers > 0 and len(full.model) != 150  # the test exercises spawn and densify

    part = Trainer(scene, cfg, tr, te, run_dir=tmp_path)
    part.fit(until=17)  # stop mid-way between densify/spawn steps
    state = part.state_dict()
    # round-trip through the on-disk checkpoint format
    from uncertsplat.io.checkpoints import decode, encode

    resumed = Trainer(scene, cfg, tr, te, state=decode(encode(state)))
    resumed.fit()
    assert resumed.step == full.step == 30
    a, b = full.model, resumed.model
    assert torch.equal(a.posterior_row, b.posterior_row)
    assert_same_parameters(a, b)
    sa, sb = full.optimizer.state_dict()["state"], resumed.optimizer.state_dict()["state"]
    for i in sa:
        torch.testing.assert_close(sb[i]["exp_avg_sq"], sa[i]["exp_avg_sq"], rtol=0, atol=1e-9)


@pytest.mark.parametrize("scale", [1e-3, 1e3])
def test_scene_scale_gives_same_result_up_to_scale(scale):
    """Priors, learning rates, thresholds and the near plane are scene-relative, so a scaled scene trains
    the same model, scaled. Only float rounding differs; Adam amplifies it for near-zero gradients and a
    densification decision at its threshold may flip, so after densification we compare outcomes."""
    cfg = toy_config(iterations=24)
    scene1, tr, te = toy_scene(1.0)
    scene2, _, _ = toy_scene(scale)
    t1 = Trainer(scene1, cfg, tr, te)
    t2 = Trainer(scene2, cfg, tr, te)
    for _ in range(9):  # before the first densification: parameters agree closely
        t1.train_step()
        t2.train_step()
    m1, m2 = t1.mean_sample(), t2.mean_sample()
    torch.testing.assert_close(m2.means / scale, m1.means, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(m2.scales / scale, m1.scales, rtol=5e-3, atol=0)
    torch.testing.assert_close(m2.opacities, m1.opacities, rtol=0, atol=1e-4)
    t1.fit()
    t2.fit()
    assert t1.model.num_carriers > 0
    assert abs(len(t1.model) - len(t2.model)) <= 0.02 * len(t1.model)
    assert abs(t1.model.num_carriers - t2.model.num_carriers) <= 0.02 * len(t1.model)
    assert t2.evaluate()["psnr"] == pytest.approx(t1.evaluate()["psnr"], abs=0.1)


def test_interrupt_writes_checkpoint(tmp_path):
    from uncertsplat.io.checkpoints import list_checkpoints, load_latest
    from uncertsplat.train.trainer import TrainingInterrupted

    scene, tr, te = toy_scene()
    t = Trainer(scene, toy_config(), tr, te, run_dir=tmp_path)
    t.on_log = lambda rec: setattr(t, "_stop", rec["step"] >= 15)  # as if SIGTERM arrived at step 15
    with pytest.raises(TrainingInterrupted) as info:
        t.fit()
    assert info.value.step == 15
    assert [s for s, _ in list_checkpoints(tmp_path)] == [10, 15]
    path, state = load_latest(tmp_path)
    assert state["step"] == 15 and path.name == "step_000015.pt"


def test_a_stop_during_the_last_step_skips_its_test_renders(tmp_path):
    """SIGTERM during a run's last step: the checkpoint is written at once, without the step's test renders (every
    test view: minutes for hundreds of large photos, while `timeout` waited)."""
    from uncertsplat.io.checkpoints import load_latest
    from uncertsplat.train.trainer import TrainingInterrupted

    scene, tr, te = toy_scene()
    cfg = toy_config()
    t = Trainer(scene, cfg, tr, te, run_dir=tmp_path)
    step = t.train_step

    def last_step_then_signal():
        terms = step()
        if t.step == cfg.iterations:
            t._stop = True  # as the signal handler does
        return terms

    t.train_step = last_step_then_signal
    renders = []
    evaluate = t.evaluate
    t.evaluate = lambda *a, **kw: renders.append(t.step) or evaluate(*a, **kw)
    with pytest.raises(TrainingInterrupted) as info:
        t.fit()
    assert info.value.step == cfg.iterations and cfg.iterations not in renders
    state = load_latest(tmp_path)[1]
    assert state["step"] == cfg.iterations and state["eval_pending"]
    # the resume renders the skipped test views first and logs them as that step's record, once
    resumed = Trainer(scene, cfg, tr, te, state=state)
    logged = []
    resumed.on_log = logged.append
    resumed.fit()
    assert [r["step"] for r in logged if "eval_psnr" in r] == [cfg.iterations] and not resumed.eval_pending
    again = Trainer(scene, cfg, tr, te, state=resumed.state_dict())
    again.on_log = logged.append
    again.fit()
    assert [r["step"] for r in logged if "eval_psnr" in r] == [cfg.iterations]  # a finished run: nothing more


def test_the_model_starts_within_its_size_limit():
    """An initial cloud above densify.max_gaussians is thinned to it (the limit printed is the limit kept), the same
    points for the same seed, and the trainer says so."""
    scene, tr, te = toy_scene()
    n = scene.points.shape[0]
    cfg = toy_config(densify={"max_gaussians": n // 3})
    a, b = Trainer(scene, cfg, tr, te), Trainer(scene, cfg, tr, te)
    assert len(a.model) == n // 3 and torch.equal(a.model.params["means"], b.model.params["means"])
    (note,) = [t for t in a.init_notes if "more than the model may hold" in t]
    assert f"{n:,} initial points" in note
    full = Trainer(scene, toy_config(), tr, te)  # under the limit: every point, no note
    assert len(full.model) == n and full.init_notes == []


def test_few_initial_points_and_points_no_view_sees_are_named():
    from dataclasses import replace

    from uncertsplat.train.trainer import few_points_notes

    scene, tr, te = toy_scene()
    cams = scene.cameras[list(scene.split["train"])]
    assert few_points_notes(scene.points, cams, 0) == []  # ~150 points
    (note,) = few_points_notes(scene.points[:5], cams, 0)
    assert "only 5 point(s), 5 of them in view of a training camera" in note and "init_num_random" in note
    above = torch.tensor([[0.0, 0.0, 50.0]])  # far above the ring of cameras, which look at its centre
    (note,) = few_points_notes(above, cams, 0)
    assert "only 1 point(s), 0 of them in view" in note
    t = Trainer(replace(scene, points=above, points_rgb=torch.ones(1, 3)), toy_config(), tr, te)
    assert any("0 of them in view" in n for n in t.init_notes)


def test_a_lone_far_point_starts_no_gaussian():
    """A sparse point far outside the cloud (a bad triangulation at 1e6) starts no Gaussian, with a note that says
    how to keep it; the random points' box is the rest's; a cloud whose far part is a real share of it keeps it."""
    from dataclasses import replace

    from uncertsplat.gaussians.params import far_points

    scene, tr, te = toy_scene()
    n = scene.points.shape[0]
    far = torch.cat([scene.points, torch.tensor([[1e6, 1e6, 1e6]])])
    flags = far_points(far, factor=10.0, extent=scene.scene_scale)
    assert flags.tolist() == [False] * n + [True]
    background = torch.cat([scene.points, scene.points[: n // 5] * 30])  # a sixth of the cloud 30x out: kept
    assert not far_points(background, factor=10.0).any()
    assert not far_points(far, factor=0.0).any() and not far_points(far[-5:], factor=10.0).any()  # off; too few
    moved = replace(scene, points=far, points_rgb=torch.rand(n + 1, 3))
    t = Trainer(moved, toy_config(init_num_random=50), tr, te)
    assert len(t.model) == n + 50 and t.model.params["means"].abs().max() < 100
    (note,) = [m for m in t.init_notes if "far outside the rest" in m]
    assert f"1 of the scene's {n + 1:,} sparse points" in note and "init_outlier_factor=0" in note
    centers = scene.cameras.centers.double()
    reach = float((torch.tensor([1e6] * 3, dtype=torch.float64) - centers.mean(0)).norm()) / float(
        (centers - centers.mean(0)).norm(dim=-1).max())
    assert f"up to {reach:.3g}x the cameras' radius from their centre" in note
    # the same scene in millimetres, not normalised (scene.normalize = false): the same ratio (it was the point's
    # distance from the origin in the scene's units, 1000x larger)
    cams = scene.cameras
    cfw = cams.cam_from_world.clone()
    cfw[:, :3, 3] *= 1000.0
    mm = replace(moved, points=moved.points * 1000.0,
                 cameras=type(cams)(cfw, cams.K, cams.width, cams.height, cams.image_names))
    (note_mm,) = [m for m in Trainer(mm, toy_config(init_num_random=50), tr, te).init_notes if "far outside" in m]
    assert f"up to {reach:.3g}x the cameras' radius" in note_mm
    kept = Trainer(moved, toy_config(init_outlier_factor=0), tr, te)
    assert len(kept.model) == n + 1 and not any("far outside" in m for m in kept.init_notes)


def test_a_surface_near_the_cameras_moves_the_near_plane_and_every_stage_renders_with_it(tiny_run_path):  # noqa: F811
    """A rig radius far larger than the cameras' distance to the surface (a few cameras far out; a close-range
    capture) would put 1 % of it beyond the surface: the near plane comes in front of the sparse points, train says
    so, and the run's loaders render with what scene.json records (a run without the record: 1 % of the radius)."""
    from dataclasses import replace

    from uncertsplat.baselines.runs import load_run
    from uncertsplat.render import near_plane
    from uncertsplat.schemas import RunScene

    scene, tr, te = toy_scene()
    t = Trainer(scene, toy_config(), tr, te)
    assert t.near == near_plane(scene.scene_scale) and not any("near plane" in m for m in t.init_notes)
    wide = replace(scene, scene_scale=200.0)  # the radius of two stray cameras 100x out
    t = Trainer(wide, toy_config(), tr, te)
    assert t.near < 0.2 * near_plane(200.0) and any("near plane is at" in m for m in t.init_notes)
    info = RunScene.read(tiny_run_path / "scene.json")
    assert info.near == pytest.approx(near_plane(info.scene_scale))  # the tiny scene: the plane stays at 1 %
    loaded = load_run(tiny_run_path, "cpu")
    assert loaded.near == info.near
    assert replace(loaded, near=0.123).render_fn(1.0, torch.device("cpu")).keywords["near"] == 0.123
    assert replace(loaded, near=None).render_fn(2.0, torch.device("cpu")).keywords["near"] == pytest.approx(0.02)


def test_a_model_whose_gaussians_carry_no_posterior_says_why():
    """Gaussians all narrower than the spawn rule's fraction of the rig radius (a small scene seen from far) carry no
    posterior: train warns, with a fraction that gives half of them one; not before the first spawn step, not for a
    model without offset tables, not when carriers are common."""
    from uncertsplat.train.trainer import few_carriers_warning

    scene, tr, te = toy_scene()
    cfg = toy_config()
    t = Trainer(scene, cfg, tr, te)
    assert t.model.num_carriers == 0
    with torch.no_grad():
        t.model.params["scales"].fill_(math.log(1e-4 * t.extent))
    (warning,) = few_carriers_warning(t.model, cfg, t.extent, t.prior, step=30)
    assert f"only 0 of the {len(t.model):,} Gaussians carry a posterior" in warning
    suggested = float(warning.split("spawn_scale_fraction=")[1].split()[0])
    assert suggested < 1.732e-4 < 2 * suggested  # below the median width (sqrt(3) x 1e-4), same order
    # before the first spawn step (10): why, and what to do (a helper's 80-step runs and --set densify.until=0 said
    # nothing, and evaluate's note said "train longer", which cannot help the second)
    (early,) = few_carriers_warning(t.model, cfg, t.extent, t.prior, step=5)
    assert "the run stopped at step 5, before Gaussians first get a posterior (step 10)" in early
    assert "N >= 10" in early

    off = toy_config(densify={"start": 5, "until": 0})  # densification off in a run that reaches its start
    late = toy_config(densify={"until": 0})  # ... and one that ends before its start (100)
    (never_late,) = few_carriers_warning(t.model, late, t.extent, t.prior, step=30)
    assert "densification starts at step 100 (densify.start), after the run's 30 steps" in never_late
    assert "with densify.until past the first densification step after it (densify.until is 0)" in never_late
    (never,) = few_carriers_warning(t.model, off, t.extent, t.prior, step=30)
    # (its densify settings replace toy_config's: interval 100, spawn_interval 1000)
    assert "densification has no step before densify.until = 0 (the first would be step 100)" in never
    assert "the first would be step 1000" in never and "densify.until to 101 or more " in never
    det = toy_config(method="deterministic")
    assert few_carriers_warning(t.model, det, t.extent, t.prior, step=30) == []


@pytest.mark.parametrize(("iterations", "stopped", "said"), [
    (300, None, None),  # split children carry a posterior from step 200 (a helper's 300-step fern run: 1042 of 1326)
    (150, None, "the run's 150 steps end before Gaussians first get a posterior"),
    (7000, 150, "the run stopped at step 150, before Gaussians first get a posterior (step 200)"),
    (7000, 250, "no densification step split a Gaussian"),  # (asked of a model without one: no split made any)
    (7000, 1000, None)])
def test_a_posterior_comes_with_the_first_split_not_only_the_first_spawn(iterations, stopped, said):
    """Gaussians first carry a posterior as the children of a split, at the first densification step: the paper
    preset's step 200, not its first spawn step (1000). A 300-step run was told it would have none."""
    from uncertsplat.config import train_config_from
    from uncertsplat.train.session import _posterior_notes
    from uncertsplat.train.trainer import no_carriers_reason, posterior_steps_needed

    cfg = train_config_from("paper", None, [f"iterations={iterations}"])
    reason = no_carriers_reason(cfg, stopped or iterations, planned=stopped is None)
    assert (reason is None) == (said is None) and (said is None or said in reason)
    assert bool(_posterior_notes(cfg)) == (iterations < 200)
    # the fewest steps: the first split (200) must come before the run's last 10 %, which never densifies
    assert posterior_steps_needed(cfg) == 222
    if iterations == 150:
        assert "--iterations 222 or more" in reason


def test_the_first_posterior_step_with_a_spawn_before_any_split_and_splits_that_made_none():
    """A first spawn step before the first split (spawn_interval 50) looped for ever before training (a review); a
    model that had its densification steps but no carrier (at its budget from the start: nothing split) was told
    its Gaussians were too narrow, though its first spawn step never came."""
    from uncertsplat.config import train_config_from
    from uncertsplat.train.trainer import no_carriers_reason, posterior_steps_needed

    early_spawn = train_config_from(None, {"densify": {"spawn_interval": 50}})  # spawn 150, split 200
    assert posterior_steps_needed(early_spawn) == 150
    wide = train_config_from(None, {"densify": {"interval": 1500}})  # split 1500, spawn 1000
    assert posterior_steps_needed(wide) == 1000
    cfg = train_config_from("paper", None, ["iterations=7000"])  # split at 200, spawn at 1000
    said = no_carriers_reason(cfg, 500)  # (asked of a model with no carrier)
    assert said.startswith("no densification step split a Gaussian") and "before its first spawn step (1000)" in said
    assert "N >= 1000" in said
    assert no_carriers_reason(cfg, 500, planned=True) is None  # before training a split may yet come
    assert no_carriers_reason(cfg, 1500) is None  # past the spawn step: the spawn rule's widths (its own warning)


def test_a_very_wide_view_is_named():
    """A camera that sees more than 150 degrees across gets a note (splatting's linearisation at the edges)."""
    from dataclasses import replace

    from uncertsplat.train.trainer import wide_view_notes

    scene, tr, te = toy_scene()
    cams = scene.cameras
    assert wide_view_notes(cams) == []  # fx 0.9 w: 58 degrees
    K = cams.K.clone()
    K[:, 0, 0] = 0.05 * cams.width  # 169 degrees across
    (note,) = wide_view_notes(replace(cams, K=K))
    assert note.startswith("a training camera sees 169 degrees across")


def test_gaussians_that_grew_after_the_last_spawn_get_no_larger_fraction_advised():
    """Wide Gaussians without carriers (they grew after spawning stopped): no advice to raise the fraction, which
    would give fewer carriers; the warning names densify.until instead."""
    from uncertsplat.train.trainer import few_carriers_warning

    scene, tr, te = toy_scene()
    cfg = toy_config()
    t = Trainer(scene, cfg, tr, te)
    with torch.no_grad():
        t.model.params["scales"].fill_(math.log(0.5 * t.extent))
    (warning,) = few_carriers_warning(t.model, cfg, t.extent, t.prior, step=30)
    assert "spawn_scale_fraction=" not in warning and "densify.until = 25" in warning


def test_a_resumed_run_keeps_the_near_plane_it_was_trained_with(tiny_run_path, tiny_scene_path, tmp_path):  # noqa: F811
    """A resume renders with the plane scene.json records (one a run recorded, or 1 % for a run that recorded
    none), not one computed again from the scene: the model was fitted in front of that plane."""
    import json
    import shutil

    from uncertsplat.config import train_config_from
    from uncertsplat.render import near_plane
    from uncertsplat.schemas import RunScene
    from uncertsplat.train.session import train_model

    run = tmp_path / "run"
    shutil.copytree(tiny_run_path, run, ignore=shutil.ignore_patterns("eval"))
    info = RunScene.read(run / "scene.json")
    info.near = 0.5 * near_plane(info.scene_scale)  # as if recorded by the run
    info.write(run / "scene.json")
    step = json.loads((run / "train_summary.json").read_text(encoding="utf-8"))["steps"]
    train_model(tiny_scene_path, run, train_config_from("tiny", {}), torch.device("cpu"), resume=True,
                extend_to=step + 1)
    assert RunScene.read(run / "scene.json").near == info.near


class TestResumeAtTheEdges:
    """What a review of resume found (2026-11-29): a stop while the last checkpoint is written, a resume told to
    stop at its checkpoint's step, views that joined since the checkpoint, counters and generators the checkpoint
    did not carry, a finished low-resolution phase."""

    def test_a_ctrl_c_while_the_last_checkpoint_is_written_keeps_it(self, tmp_path):
        """The handlers were restored before the last checkpoint: a Ctrl-C while it was written (seconds for a large
        model) lost every step since the last periodic one. Now the write finishes, then the stop is honoured."""
        import os
        import signal

        from uncertsplat.io.checkpoints import list_checkpoints
        from uncertsplat.train.trainer import TrainingInterrupted

        scene, tr, te = toy_scene()
        cfg = toy_config()
        t = Trainer(scene, cfg, tr, te, run_dir=tmp_path)
        save = t.save_checkpoint

        def save_with_a_signal():
            if t.step == cfg.iterations:
                os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C while the last checkpoint is being written
            return save()

        t.save_checkpoint = save_with_a_signal
        with pytest.raises(TrainingInterrupted) as info:
            t.fit()
        assert info.value.step == cfg.iterations
        assert list_checkpoints(tmp_path)[-1][0] == cfg.iterations

    def test_a_resume_told_to_stop_at_its_checkpoint_makes_the_last_update(self):
        """--resume --iterations N with N the checkpoint's step trains no step, and the update of a run's last step
        is made inside one: the tables kept the last refresh's (the prior before the first)."""
        from uncertsplat.io.checkpoints import decode, encode

        scene, tr, te = toy_scene()
        cfg = toy_config()
        part = Trainer(scene, cfg, tr, te)
        part.fit(until=17)
        assert part.informed and all(u["step"] != 17 for u in part.posterior_updates)
        short = cfg.model_copy(update={"iterations": 17})
        resumed = Trainer(scene, short, tr, te, state=decode(encode(part.state_dict())))
        resumed.fit()
        last = resumed.posterior_updates[-1]
        assert (last["step"], last["views"], last["probes"]) == (17, len(resumed.train_idx), short.variational.probes)
        again = Trainer(scene, short, tr, te, state=resumed.state_dict())
        again.fit()  # finished with its update: none more
        assert len(again.posterior_updates) == len(resumed.posterior_updates)

    def test_views_that_joined_since_the_checkpoint_start_a_new_pass_and_keep_their_exposures_by_name(self):
        """The checkpoint's queue holds positions in its own list of training views: a view added (or a resume after
        an --add-views killed before its first checkpoint) indexed other views. And photos that joined the scene
        (reconstruct --extend) move the others' indices: exposures are matched by name."""
        from dataclasses import replace

        from uncertsplat.io.checkpoints import decode, encode

        scene, tr, te = toy_scene()  # train views 1, 2, 3, 5, 6, 7
        cfg = toy_config(exposure="affine")
        fewer = replace(scene, split={**scene.split, "train": (1, 2, 3, 6, 7)})
        part = Trainer(fewer, cfg, tr[[0, 1, 2, 4, 5]], te)
        part.fit(until=12)
        with torch.no_grad():
            part.exposure.copy_(torch.randn(part.exposure.shape, generator=torch.Generator().manual_seed(0)) * 0.1)
        state = decode(encode(part.state_dict()))
        assert part.view_queue  # (mid-pass)
        same = Trainer(fewer, cfg, tr[[0, 1, 2, 4, 5]], te, state=state)
        assert same.view_queue == part.view_queue
        grown = Trainer(scene, cfg, tr, te, state=state)
        assert grown.view_queue == []
        # a photo that sorts first joined the scene: every index moved by one, the names did not
        cams = scene.cameras
        new = Cameras(torch.cat([cams.cam_from_world[:1], cams.cam_from_world]), torch.cat([cams.K[:1], cams.K]),
                      cams.width, cams.height, ("a_new.png", *cams.image_names))
        shifted = replace(fewer, cameras=new, split={"train": (2, 3, 4, 7, 8), "test": (1, 5)})
        moved = Trainer(shifted, cfg, tr[[0, 1, 2, 4, 5]], te, state=state)
        assert moved.view_queue == part.view_queue
        torch.testing.assert_close(moved.exposure, part.exposure, rtol=0, atol=0)

    def test_another_device_types_generator_state_is_reseeded_with_a_note(self):
        """A CPU generator's state is 5056 bytes, a CUDA one's 16: a run resumed with another --device failed in
        set_state with a traceback. It goes on, seeded from the saved state, and says so."""
        scene, tr, te = toy_scene()
        cfg = toy_config()
        part = Trainer(scene, cfg, tr, te)
        part.fit(until=5)
        state = part.state_dict()
        state["gen_noise"] = torch.arange(16, dtype=torch.uint8)  # as a CUDA generator writes it
        t = Trainer(scene, cfg, tr, te, state=state)
        assert any("another device type" in n for n in t.init_notes)
        t.fit(until=8)
        again = Trainer(scene, cfg, tr, te, state=state)  # the same seed from the same state
        again.fit(until=8)
        assert_same_parameters(t.model, again.model, atol=0)

    def test_an_extended_run_past_its_low_resolution_phase_stays_at_full_resolution(self):
        """The phase is a fraction of the run's steps: extending a run that had left it sent it back to half
        resolution for the stretched part. It stretches only while the run is still in it."""
        scene, tr, te = toy_scene()
        cfg = toy_config(low_res_fraction=0.3)  # steps 1-9 of 30
        longer = cfg.model_copy(update={"iterations": 60})
        done = Trainer(scene, cfg, tr, te)
        done.fit(until=12)
        past = Trainer(scene, longer, tr, te, state=done.state_dict())
        assert past.low_res_until == 9 and past.low_images is None
        early = Trainer(scene, cfg, tr, te)
        early.fit(until=5)
        within = Trainer(scene, longer, tr, te, state=early.state_dict())
        assert within.low_res_until == 18 and within.low_images is not None


def test_a_run_folder_removed_under_a_training_is_named_as_such(tmp_path):
    """A run folder moved away by another command while training wrote to it was 'could not append to the training
    log (No such file or directory)... Free some space': a full disk, wrongly."""
    from uncertsplat.errors import UserError

    scene, tr, te = toy_scene()
    t = Trainer(scene, toy_config(), tr, te, run_dir=tmp_path / "gone")
    with pytest.raises(UserError, match="the run folder is gone while training wrote to it") as err:
        t._log({"step": 1})
    assert "Free some space" not in err.value.hint


def test_resume_in_a_folder_of_other_files_does_not_advise_a_start_that_is_refused(tmp_path, tiny_scene_path):  # noqa: F811
    """`train SCENE -o FOLDER --resume` on a folder of other files (a prune's sweep, a scene) said "Start a new run
    without --resume", which the same folder then refused ("holds files that are not a training run"): it says what
    the folder holds and to give a run's folder or a new one; a folder that is not there keeps the short advice."""
    from uncertsplat.errors import UserError
    from uncertsplat.stages.train import run as train_run

    cfg = train_config_from("tiny", overrides=["iterations=5"])
    (tmp_path / "sweep_only").mkdir()
    (tmp_path / "sweep_only" / "prune.json").write_text("{}")
    with pytest.raises(UserError, match="nothing to resume") as err:
        train_run(tiny_scene_path, tmp_path / "sweep_only", cfg, torch.device("cpu"), resume=True)
    said = err.value.render()
    assert "holds files that are not a training run" in said and "in a new or empty output folder" in said
    assert sorted(p.name for p in (tmp_path / "sweep_only").iterdir()) == ["prune.json"]  # (nothing written)
    with pytest.raises(UserError, match="nothing to resume") as err:
        train_run(tiny_scene_path, tmp_path / "none", cfg, torch.device("cpu"), resume=True)
    assert err.value.hint == "Start a new run without --resume."
