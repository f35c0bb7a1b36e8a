"""The informed posterior knows what its training views never saw (issue 18).

The tiny scene is trained on the cameras of one half of its ring and rendered from the other half. Every
pixel of those views is labelled observed / unobserved from GT depth (``eval.observed``). The posterior's
own spread (no empty-ray term, no pixel noise) must be higher on the surface no training view saw: true for
the informed posterior, false for the prior-only posterior of the SGD tables.
"""

from __future__ import annotations

import json

import pytest
import torch
import torch.nn.functional as F

from tests.e2e.test_train_resume import toy_config, toy_scene
from tests.fixtures import tiny_scene_path  # noqa: F401
from tests.run_fixtures import resume_without_key, tiny_run_path  # noqa: F401
from uncertsplat.baselines import load_run, train_run
from uncertsplat.config import EvalConfig, train_config_from
from uncertsplat.data.dataset import load_depths, load_view_set
from uncertsplat.eval.engine import evaluate_views
from uncertsplat.eval.observed import observed_mask
from uncertsplat.sfm.scene import load_scene
from uncertsplat.train.trainer import Trainer

CPU = torch.device("cpu")


def _half_ring(scene) -> tuple[list[int], list[int]]:
    c = scene.cameras.centers.double()
    az = torch.atan2(c[:, 1] - c[:, 1].mean(), c[:, 0] - c[:, 0].mean())
    order = torch.argsort(az).tolist()
    return sorted(order[: len(order) // 2]), sorted(order[len(order) // 2:])


def _std_unobserved_over_observed(run, train, test) -> float:
    loaded = load_run(run, CPU)
    scene = loaded.load_scene()
    views = load_view_set(scene, test)
    maps = []
    cfg = EvalConfig(num_samples=8, empty_rays=False, residual_views=0, resolution=0,  # the posterior's spread alone
                     depth_spread=False)
    evaluate_views(loaded.sampler(scene.scene_scale, CPU), views, cfg, CPU, show_progress=False, on_view=maps.append)
    depths = load_depths(scene, train)[..., 0].double()
    cams = scene.cameras
    unobserved, observed = [], []
    for j, i in enumerate(test):
        obs, valid = observed_mask(views.depths[j, ..., 0].double(), cams.cam_from_world[i], cams.K[i], depths,
                                   cams.cam_from_world[train], cams.K[train])
        std = maps[j].rgb_std.mean(-1)
        unobserved.append(std[valid & ~obs])
        observed.append(std[valid & obs])
    u, o = torch.cat(unobserved), torch.cat(observed)
    assert u.numel() > 1000 and o.numel() > 1000, "the split must leave both kinds of pixels"
    return float(u.mean() / o.mean())


@pytest.fixture(scope="module")
def half_ring_runs(tiny_scene_path, tmp_path_factory):  # noqa: F811
    train, test = _half_ring(load_scene(tiny_scene_path))
    out = {}
    for posterior in ("informed", "sgd"):
        # updates before the last one use 5 of the 12 training views (the last one all of them)
        cfg = train_config_from("tiny", {"scene": {"train_indices": train, "test_indices": test},
                                         "variational": {"posterior": posterior, "refresh_interval": 100,
                                                         "refresh_views": 5}})
        run = tmp_path_factory.mktemp(posterior)
        train_run(tiny_scene_path, run, cfg, CPU)
        out[posterior] = run
    return out, train, test


def test_unobserved_surface_gets_more_spread(half_ring_runs):
    runs, train, test = half_ring_runs
    informed = _std_unobserved_over_observed(runs["informed"], train, test)
    prior_only = _std_unobserved_over_observed(runs["sgd"], train, test)
    assert informed > 1.3, f"informed posterior: unobserved / observed mean std {informed:.2f}"
    assert prior_only < 1.1 < informed, f"prior-only posterior {prior_only:.2f} against informed {informed:.2f}"


def test_updates_are_recorded(half_ring_runs):
    runs, train, _ = half_ring_runs
    summary = json.loads((runs["informed"] / "train_summary.json").read_text(encoding="utf-8"))
    steps = [u["step"] for u in summary["posterior_updates"]]
    assert steps == [100, 200, 300]
    assert [u["views"] for u in summary["posterior_updates"]] == [5, 5, len(train)]
    # the updates in between take refresh_probes (1) probes per view, the last one `probes` (2)
    assert [u["probes"] for u in summary["posterior_updates"]] == [1, 1, 2]
    last = summary["posterior_updates"][-1]
    assert 0.0 < last["data_dominated"] < 1.0 and last["noise_std"] > 0
    assert json.loads((runs["sgd"] / "train_summary.json").read_text(encoding="utf-8"))["posterior_updates"] == []


def test_a_run_from_before_the_informed_posterior_resumes_with_sgd_tables(tiny_scene_path, tiny_run_path,  # noqa: F811
                                                                        tmp_path):
    """config.json files written before ``variational.posterior`` existed trained SGD tables; resuming one must not
    switch it to the informed posterior halfway."""
    import shutil

    from uncertsplat.train.session import train_model

    run = tmp_path / "old"
    shutil.copytree(tiny_run_path, run, ignore=shutil.ignore_patterns("eval"))
    cfg_path = run / "config.json"
    data = json.loads(cfg_path.read_text(encoding="utf-8"))
    data["variational"].pop("posterior")
    data["variational"].pop("refresh_interval"), data["variational"].pop("refresh_views")
    data["variational"].pop("probes"), data["variational"].pop("position_prior_scale")
    data["scene"].pop("train_names"), data["scene"].pop("train_indices"), data["scene"].pop("points_from")
    cfg_path.write_text(json.dumps(data))
    step = json.loads((run / "train_summary.json").read_text(encoding="utf-8"))["steps"]
    cfg = train_config_from("tiny", {})
    train_model(tiny_scene_path, run, cfg, CPU, resume=True, extend_to=step + 100)
    summary = json.loads((run / "train_summary.json").read_text(encoding="utf-8"))
    # no informed update after the resume (those before it came with the checkpoint)
    assert summary["steps"] == step + 100 and all(u["step"] <= step for u in summary["posterior_updates"])
    assert json.loads(cfg_path.read_text(encoding="utf-8"))["variational"]["posterior"] in (None, "sgd")


def test_an_informed_run_from_before_train_on_resumes_on_samples(tiny_scene_path, tiny_run_path,  # noqa: F811
                                                                 tmp_path):
    """config.json files written before ``variational.train_on`` existed fitted their Gaussians to posterior samples;
    a resumed one keeps doing so (the default for new runs is the expected render)."""
    assert train_config_from("tiny", {}).variational.train_on == "mean"
    cfg = resume_without_key(tiny_scene_path, tiny_run_path, tmp_path, "variational", "train_on", 20)
    assert cfg["variational"]["train_on"] == "samples"


def test_sandwich_widens_only_the_last_update(tmp_path):
    """``variational.sandwich``: identical training (the updates before the last are Laplace), then spreads at
    least the Laplace ones, wider where the views disagree (the cap at the prior: the unit tests)."""
    scene, tr, te = toy_scene()
    spreads, params = {}, {}
    for sandwich in (False, True):
        cfg = toy_config(variational={"posterior": "informed", "refresh_interval": 10, "sandwich": sandwich})
        t = Trainer(scene, cfg, tr, te)
        t.fit()
        assert [u["step"] for u in t.posterior_updates] == [10, 20, 30]
        spreads[sandwich] = F.softplus(t.model.tables["pos_spread_raw"]).detach()
        params[sandwich] = t.model.params["sh0"].detach()
    torch.testing.assert_close(params[True], params[False], rtol=0, atol=0)  # same training
    assert torch.all(spreads[True] >= spreads[False] * (1 - 1e-5))
    assert float((spreads[True] > spreads[False] * 1.01).float().mean()) > 0.1


def test_no_carrier_spreads_past_a_fraction_of_its_depth():
    """Trained end to end, every carrier's position std (world units) is at most ``position_depth_fraction`` x its
    distance to the nearest training camera (the posterior std is below the capped prior's); a fraction small
    enough to bind narrows the spreads."""
    from uncertsplat.gaussians.variational import posterior_mean

    scene, tr, te = toy_scene()
    medians = {}
    for fraction in (0.1, 0.005):
        cfg = toy_config(variational={"posterior": "informed", "refresh_interval": 10,
                                      "position_depth_fraction": fraction})
        t = Trainer(scene, cfg, tr, te)
        t.fit()
        idx = t.model.carrier_index()
        with torch.no_grad():
            means = posterior_mean(t.model, extent=t.extent).means[idx]
            std = F.softplus(t.model.tables["pos_spread_raw"]).amax((1, 2)) * t.extent  # [P] (the 'ours' unit)
        depth = torch.cdist(means, t.train_cams.centers).amin(1)
        assert torch.all(std <= fraction * depth * (1 + 1e-4)), fraction
        medians[fraction] = float(std.median())
    assert medians[0.005] < 0.5 * medians[0.1]


def test_training_on_the_expected_render(tmp_path):
    """``variational.train_on = "expected"``: the Gaussians are fitted to the expected render (no random numbers, so
    two runs are identical), the tables are still set by the updates only (never by the optimiser), and the fit
    differs from training on samples."""
    scene, tr, te = toy_scene()
    sh0 = {}
    for run, train_on in enumerate(("expected", "expected", "samples")):
        cfg = toy_config(variational={"posterior": "informed", "refresh_interval": 10, "train_on": train_on})
        t = Trainer(scene, cfg, tr, te)
        t.fit()
        assert [u["step"] for u in t.posterior_updates] == [10, 20, 30]
        assert all(p.grad is None for p in t.model.tables.values())
        assert all(not t.optimizer.state.get(p) for p in t.model.tables.values())
        sh0[run] = t.model.params["sh0"].detach().clone()
    torch.testing.assert_close(sh0[0], sh0[1], rtol=0, atol=0)
    assert sh0[0].shape != sh0[2].shape or not torch.equal(sh0[0], sh0[2])


def test_training_on_the_posterior_mean():
    """``variational.train_on = "mean"``: the Gaussians are fitted to the posterior mean's render, the mode the
    posterior is spread around (no random numbers: two runs are identical; no position spread folded into the
    training renders), the tables are set by the updates only, and the fit differs from the expected render's."""
    scene, tr, te = toy_scene()
    sh0 = {}
    for run, train_on in enumerate(("mean", "mean", "expected")):
        cfg = toy_config(variational={"posterior": "informed", "refresh_interval": 10, "train_on": train_on})
        t = Trainer(scene, cfg, tr, te)
        spreads = []
        render = t.render

        def spy(g, cams, render=render, spreads=spreads):
            if torch.is_grad_enabled():  # training renders: the steps and the updates (not the held-out checks)
                spreads.append(g.position_var)
            return render(g, cams)

        t.render = spy
        t.fit()
        assert [u["step"] for u in t.posterior_updates] == [10, 20, 30]
        assert all(p.grad is None for p in t.model.tables.values())
        assert all(not t.optimizer.state.get(p) for p in t.model.tables.values())
        if train_on == "mean":
            assert len(spreads) >= 30 and all(v is None for v in spreads)
        else:  # the expected render folds each carrier's position spread into its footprint
            assert any(v is not None for v in spreads)
        sh0[run] = t.model.params["sh0"].detach().clone()
    torch.testing.assert_close(sh0[0], sh0[1], rtol=0, atol=0)
    assert sh0[0].shape != sh0[2].shape or not torch.equal(sh0[0], sh0[2])


@pytest.mark.parametrize("train_on", ["expected", "mean"])
def test_the_table_terms_kept_between_steps_are_never_stale(monkeypatch, train_on):
    """Training on the expected render or the posterior mean keeps their table terms between steps
    (``ExpectedConstants``); at every step of a run with posterior updates, densification, spawning and an opacity
    reset, the sample they give is the one computed from the tables afresh."""
    import uncertsplat.train.trainer as trainer_module

    name = "expected_render_sample" if train_on == "expected" else "posterior_mean"
    original = getattr(trainer_module, name)
    checked = []

    def both(model, **kw):
        fast = original(model, **kw)
        slow = original(model, **{**kw, "constants": None})
        for k in ("means", "scales", "opacities", "position_var"):
            a, b = getattr(fast, k), getattr(slow, k)
            if a is None or b is None:
                assert a is None and b is None, k
                continue
            torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-7, msg=k)
        torch.testing.assert_close(fast.full_sh(), slow.full_sh(), rtol=0, atol=0)
        assert fast.sh_degree == slow.sh_degree
        if kw.get("tables_grad") is False:  # a training step's sample (evaluation renders take the tables afresh)
            checked.append(kw.get("constants") is not None)
        return fast

    monkeypatch.setattr(trainer_module, name, both)
    scene, tr, te = toy_scene()
    # updates at steps 7, 14, 21, 28 and 30: between densification steps (10, 20), so that each must drop the terms
    cfg = toy_config(variational={"posterior": "informed", "refresh_interval": 7, "train_on": train_on})
    t = Trainer(scene, cfg, tr, te)
    t.fit()
    assert len(checked) == 30 and all(checked)
    assert [u["step"] for u in t.posterior_updates] == [7, 14, 21, 28, 30]


def test_an_informed_run_from_before_spawn_keeps_render_resumes_without_it(tiny_scene_path, tiny_run_path,  # noqa: F811
                                                                              tmp_path):
    """config.json files written before ``variational.spawn_keeps_render`` existed spawned carriers at the prior's
    gate and multiplier; a resumed one keeps doing so (new runs keep the spawned Gaussians' render)."""
    assert train_config_from("tiny", {}).variational.spawn_keeps_render is True
    cfg = resume_without_key(tiny_scene_path, tiny_run_path, tmp_path, "variational", "spawn_keeps_render", 20)
    assert cfg["variational"]["spawn_keeps_render"] is False


def test_an_informed_run_from_before_refresh_probes_keeps_its_probes(tiny_scene_path, tiny_run_path,  # noqa: F811
                                                                      tmp_path):
    """config.json files written before ``variational.refresh_probes`` existed used ``probes`` at every update; a
    resumed one keeps doing so (new runs take 1 between updates)."""
    assert train_config_from("tiny", {}).variational.refresh_probes == 1
    cfg = resume_without_key(tiny_scene_path, tiny_run_path, tmp_path, "variational", "refresh_probes", 20)
    assert cfg["variational"]["refresh_probes"] == cfg["variational"]["probes"] == 2
