"""The notes ``train`` prints about its own settings before training (``train.session``): settings the run does not
use, and opacity resets that the run's length leaves out. A helper's sweep of every knob found both taken silently."""

from __future__ import annotations

from types import SimpleNamespace

from tests.fixtures import tiny_scene_path  # noqa: F401
from uncertsplat.config import train_config_from
from uncertsplat.train.session import _reset_notes, _settle_notes, _unused_setting_notes


def test_settings_the_method_does_not_use_are_named():
    assert _unused_setting_notes(train_config_from(None, {})) == []
    cfg = train_config_from(None, {"method": "deterministic", "ensemble_size": 3, "fisher": {"probes": 4},
                                   "variational": {"kl_weight": 2.0}, "exposure_lr": 1e-2, "low_res_scale": 0.25})
    (note,) = _unused_setting_notes(cfg)
    assert note == ("settings this run does not use (method deterministic): ensemble_size, variational.*, "
                    "exposure_lr (exposure is off), low_res_scale (low_res_fraction is 0)")
    # an ensemble's member keeps its ensemble's keys (each member said they were unused); fisher.* is never named,
    # select-views' fisher score reads it for any run
    member = train_config_from(None, {"method": "deterministic", "ensemble_size": 3, "fisher": {"probes": 4}})
    assert _unused_setting_notes(member, member=True) == []
    used = train_config_from(None, {"method": "ensemble", "ensemble_size": 3, "ensemble_members": "variational",
                                    "variational": {"kl_weight": 2.0}, "exposure": "affine", "exposure_lr": 1e-2})
    assert _unused_setting_notes(used) == []
    informed = train_config_from(None, {"variational": {"num_entries": 5}})
    assert _unused_setting_notes(informed)[0].startswith("variational.num_entries = 5 is not used by the informed")


def test_a_run_whose_resets_all_fall_in_its_last_steps_says_so():
    """No reset is made in a run's last 1000 steps: a 900-step run with resets every 100 steps resets nothing."""
    short = train_config_from(None, {"iterations": 900, "densify": {"until": 800, "opacity_reset_interval": 100}})
    (note,) = _reset_notes(short)
    assert note.startswith("no opacity reset in this run") and "opacity_reset_interval = 100" in note
    long = short.model_copy(update={"iterations": 3000})
    assert _reset_notes(long) == []
    off = train_config_from(None, {"iterations": 900, "densify": {"opacity_reset_interval": 0}})
    assert _reset_notes(off) == []
    assert _settle_notes(train_config_from(None, {})) == []  # the default schedule fits its steps
    # a run too short for its densify.until: a resumed one is not told to set what the resume ignores
    short = train_config_from(None, {"iterations": 200})
    (fresh,) = _settle_notes(short)
    (resumed,) = _settle_notes(short, resume=True)
    assert "--set densify.until=N" in fresh and "--set" not in resumed and "keeps its stored densify.until" in resumed


def test_settings_that_give_no_posterior_are_said_before_training():
    """densify.start beyond the run's steps: the whole run trained, then "no posterior" came with advice to raise
    densify.until, which a run that ends first does not reach."""
    from uncertsplat.train.session import _posterior_notes

    assert _posterior_notes(train_config_from(None, {})) == []
    late = train_config_from(None, {"iterations": 150, "densify": {"start": 1000000}})
    (note,) = _posterior_notes(late)
    assert "densification starts at step 1000000 (densify.start), after the run's 150 steps" in note
    assert "lower densify.start" in note
    off = train_config_from(None, {"iterations": 5000, "densify": {"until": 0}})
    assert "set densify.until to" in _posterior_notes(off)[0]
    assert _posterior_notes(train_config_from(None, {"method": "deterministic", "densify": {"until": 0}})) == []

    short = train_config_from(None, {"iterations": 60, "densify": {"start": 50, "spawn_interval": 100}})
    (note,) = _posterior_notes(short)
    assert note.startswith("no Gaussian will carry a posterior in this run: the run's 60 steps end before Gaussians "
                           "first get a posterior") and note.endswith("give it --iterations 100 or more for a posterior")


def test_the_last_posterior_update_is_said_before_it_runs_on_large_captures(monkeypatch, capsys):
    """It runs inside the last step: 52 views of 2000x1500 took 100 s with the progress bar standing still. Said where
    the views hold more than LONG_UPDATE_PIXELS together; an update before the last is not."""
    import uncertsplat.train.trainer as trainer_module
    from tests.e2e.test_train_resume import toy_config, toy_scene
    from uncertsplat.train.trainer import Trainer

    scene, tr, te = toy_scene()
    t = Trainer(scene, toy_config(iterations=20), tr, te)
    t.fit()
    said = " ".join(capsys.readouterr().err.split())
    assert "the last update renders every training view" not in said  # (the toy scene's views are small)
    monkeypatch.setattr(trainer_module, "LONG_UPDATE_PIXELS", 0)
    t.step = 10  # an update before the last one: not said
    t.update_posterior()
    assert "the last update" not in " ".join(capsys.readouterr().err.split())
    t.step = 20
    t.update_posterior()
    w, h = scene.cameras.width, scene.cameras.height
    assert (f"posterior: the last update renders every training view ({len(scene.split['train'])} at {w}x{h}"
            in " ".join(capsys.readouterr().err.split()))
    # inside fit, the last update writes each view to the progress bar (a line a minute in a log)
    seen = []

    class Bar:
        def __init__(self, tasks=()):
            self.tasks = list(tasks)  # (rich's Progress.tasks, which the update reads)

        def update(self, task, **kw):
            seen.append((task, kw))

    t._bar = (Bar([SimpleNamespace(id=7, description="train")]), 7)
    t.update_posterior()
    n = len(scene.split["train"])
    assert seen == [(7, {"info": f"posterior update: view {i}/{n}"}) for i in range(1, n + 1)]
    # a bar of the update alone (a model given by init_ply trains no step) counts its views
    seen[:] = []
    t._bar = (Bar([SimpleNamespace(id=7, description="posterior")]), 7)
    t.update_posterior()
    assert seen == [(7, {"info": f"posterior update: view {i}/{n}", "completed": i}) for i in range(1, n + 1)]
    t.step, seen[:] = 10, []
    t.update_posterior()
    assert seen == []  # (an update before the last one is short)


def test_photos_that_would_fill_the_free_memory_are_warned_of(monkeypatch, tiny_scene_path):  # noqa: F811
    """A capture too large ran out of memory minutes into loading or training with an allocator's traceback: the
    photos' size (3 bytes a pixel for 8-bit ones) is weighed against the free memory before they are loaded."""
    import uncertsplat.io.memory as memory
    from uncertsplat.config import SceneConfig
    from uncertsplat.sfm.scene import load_scene
    from uncertsplat.train.session import _photo_memory_notes

    scene = load_scene(tiny_scene_path, SceneConfig())
    n = len(scene.split["train"]) + len(scene.split["test"])
    need = n * 128 * 96 * 3  # the tiny scene's 8-bit PNGs
    monkeypatch.setattr(memory, "available_memory", lambda: 2 * need + 1)
    assert _photo_memory_notes(scene, "cpu") == []
    monkeypatch.setattr(memory, "available_memory", lambda: need)
    (note,) = _photo_memory_notes(scene, "cpu")
    assert note.startswith(f"the {n} photos at 128x96 take 0.0 GB") and "--set scene.downscale=2" in note
    assert _photo_memory_notes(scene, "cuda") == []  # (the GPU's memory is another)
    monkeypatch.setattr(memory, "available_memory", lambda: None)
    assert _photo_memory_notes(scene, "cpu") == []
