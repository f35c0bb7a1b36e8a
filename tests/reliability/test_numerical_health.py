"""A loss or gradient going NaN/Inf is caught at the step it happens: the update is skipped with a message,
and a run that keeps producing them stops with a clear error while the checkpoints stay the last good state.
"""

from __future__ import annotations

import json
import math

import pytest
import torch

from tests.e2e.test_train_resume import toy_config, toy_scene
from uncertsplat.errors import UserError
from uncertsplat.io.checkpoints import list_checkpoints, load_checkpoint
from uncertsplat.train import trainer as trainer_mod
from uncertsplat.train.trainer import MAX_BAD_STEPS, Trainer


def _params(t: Trainer) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in t.model.parameters().items()}


def _poison(kind: str, t: Trainer, bad_steps: set[int], monkeypatch):
    """Make step s (for s in bad_steps) produce a NaN/Inf loss or gradient of the given kind."""
    orig_render = t.render
    orig_loss = trainer_mod.total_loss

    def due() -> bool:
        return t.step + 1 in bad_steps

    if kind == "nan-loss":
        def total_loss(*a, **k):
            out = orig_loss(*a, **k)
            if due():
                out["loss"] = out["loss"] * float("nan")
            return out

        monkeypatch.setattr(trainer_mod, "total_loss", total_loss)
    elif kind in ("nan-grad", "inf-grad"):
        value = float("nan") if kind == "nan-grad" else float("inf")

        def render(g, cams):
            out = orig_render(g, cams)
            if due() and out.rgb.requires_grad:  # the loss stays finite; the image gradient (and so every parameter's) is not
                out.rgb.register_hook(lambda grad: torch.full_like(grad, value))
            return out

        monkeypatch.setattr(t, "render", render)
    elif kind == "one-param-inf":
        def render(g, cams):
            if due():  # one-shot: a single entry of one parameter's gradient becomes +Inf
                handle = []

                def hook(grad):
                    handle[0].remove()
                    return grad.index_fill(0, torch.tensor([0]), math.inf)

                handle.append(t.model.params["opacities"].register_hook(hook))
            return orig_render(g, cams)

        monkeypatch.setattr(t, "render", render)


@pytest.mark.parametrize("kind", ["nan-loss", "nan-grad", "inf-grad", "one-param-inf"])
def test_non_finite_step_is_skipped_with_a_message(kind, tmp_path, monkeypatch, capsys):
    scene, tr, te = toy_scene()
    cfg = toy_config(iterations=8, checkpoint_every=4)
    t = Trainer(scene, cfg, tr, te, run_dir=tmp_path)
    _poison(kind, t, {3}, monkeypatch)
    t.fit(until=2)
    before = _params(t)
    last = t.fit(until=3)  # step 3: poisoned
    assert last.get("skipped") == 1.0
    after = _params(t)
    for k in before:
        assert torch.equal(before[k], after[k]), f"{k} changed by a skipped step"
    assert "step 3: the loss or a gradient is NaN/Inf" in " ".join(capsys.readouterr().err.split())
    t.fit()  # continues normally
    assert t.step == 8 and t.skipped_steps == 1
    for k, v in t.model.parameters().items():
        assert torch.isfinite(v).all(), k
    assert not any(torch.equal(before[k], v) for k, v in _params(t).items() if v.numel() and k == "means")
    for _, p in list_checkpoints(tmp_path):
        state = load_checkpoint(p)
        assert all(torch.isfinite(v).all() for v in state["model"]["params"].values())
    logged = [json.loads(line) for line in (tmp_path / "stats.jsonl").read_text(encoding="utf-8").splitlines()]
    assert [r["step"] for r in logged if r.get("skipped")] == [3]
    assert t.summary()["skipped_steps"] == 1


def test_a_model_pruned_to_nothing_stops_with_a_clear_error(tmp_path, monkeypatch):
    """Densification that removes every Gaussian (a threshold above every opacity): the run trained an empty model on
    and failed with a traceback writing its PLY; now it stops at that step, naming the threshold."""
    from uncertsplat.strategy import densify

    scene, tr, te = toy_scene()
    t = Trainer(scene, toy_config(iterations=30), tr, te, run_dir=tmp_path)
    monkeypatch.setattr(densify, "prune_decisions", lambda opacities, **kw: torch.ones_like(opacities, dtype=torch.bool))
    with pytest.raises(UserError, match=r"every Gaussian was removed at step 10: densification prunes those whose "
                                        r"opacity is below densify.min_opacity = 0.005"):
        t.fit()


def test_a_divergence_before_any_checkpoint_says_there_is_none(tmp_path, monkeypatch):
    """Diverged at step 2 with no checkpoint written: the message said the checkpoints on disk were the last good state
    and suggested --resume, which takes the run's own (diverging) settings; now it says none was written and that the
    folder can be deleted or another one given."""
    scene, tr, te = toy_scene()
    t = Trainer(scene, toy_config(iterations=30, checkpoint_every=1000), tr, te, run_dir=tmp_path)
    _poison("nan-loss", t, set(range(1, 100)), monkeypatch)
    with pytest.raises(UserError) as err:
        t.fit()
    assert "no checkpoint was written before it" in str(err.value) and not list_checkpoints(tmp_path)
    assert "-o NEW_RUN" in err.value.hint and "--resume" not in err.value.hint
    assert "with no checkpoint written, the same command with the new settings starts" in err.value.hint


def test_persistent_nan_stops_with_a_clear_error_and_good_checkpoints(tmp_path, monkeypatch):
    scene, tr, te = toy_scene()
    cfg = toy_config(iterations=30, checkpoint_every=4)
    t = Trainer(scene, cfg, tr, te, run_dir=tmp_path)
    _poison("nan-loss", t, set(range(10, 100)), monkeypatch)
    with pytest.raises(UserError) as err:
        t.fit()
    msg = str(err.value)
    assert "training diverged" in msg and f"steps 10-{9 + MAX_BAD_STEPS}" in msg and "learning rate" in msg
    assert "the checkpoints on disk are the last good state" in msg and "-o NEW_RUN" in err.value.hint
    assert "--resume goes on from the last good checkpoint" in err.value.hint
    assert [s for s, _ in list_checkpoints(tmp_path)] == [4, 8, 12]  # step 12: parameters of step 9, unchanged
    # the log is strict JSON (the NaN losses of the skipped steps as null: bare NaN tokens broke jq)
    def refuse(token):
        raise ValueError(f"not strict JSON: {token}")

    rows = [json.loads(line, parse_constant=refuse)
            for line in (tmp_path / "stats.jsonl").read_text(encoding="utf-8").splitlines()]
    assert rows and any(r.get("loss", 0.0) is None for r in rows if "loss" in r)
    good = load_checkpoint(list_checkpoints(tmp_path)[-1][1])
    assert all(torch.isfinite(v).all() for v in good["model"]["params"].values())
    # the last good state resumes (and trains on once the cause is gone)
    monkeypatch.undo()
    resumed = Trainer(scene, cfg, tr, te, run_dir=tmp_path, state=good)
    resumed.fit()
    # the steps skipped before the checkpoint are the run's (steps 10-12): kept across the resume, the streak of bad
    # steps with them (it ends at the first good step)
    assert good["skipped_steps"] == 3 and good["bad_steps_in_a_row"] == 3
    assert resumed.step == 30 and resumed.skipped_steps == 3 and resumed.bad_steps_in_a_row == 0


def test_exploding_learning_rate_is_caught_not_saved_as_a_nan_model(tmp_path, capsys):
    """A real cause: an absurd learning rate blows the scales up until the render is NaN/Inf."""
    scene, tr, te = toy_scene()
    cfg = toy_config(iterations=40, checkpoint_every=2, lr={"scales": 1e4, "opacities": 1e4})
    t = Trainer(scene, cfg, tr, te, run_dir=tmp_path)
    with pytest.raises(UserError, match="training diverged|NaN/Inf parameters"):
        t.fit()
    assert "NaN/Inf" in capsys.readouterr().err
    for _, p in list_checkpoints(tmp_path):
        state = load_checkpoint(p)
        assert all(torch.isfinite(v).all() for v in state["model"]["params"].values()), p


def test_an_outlier_filter_that_takes_every_point_says_so(tmp_path):
    """``init_outlier_factor`` tiny: every sparse point is an outlier. It said "the scene has no sparse points", of
    a scene with thousands."""
    scene, tr, te = toy_scene()
    with pytest.raises(UserError, match="no sparse point is left to start from: .* sparse points lie far outside") as e:
        Trainer(scene, toy_config(init_outlier_factor=1e-12), tr, te, run_dir=tmp_path)
    assert "init_outlier_factor" in e.value.hint


def test_a_divergence_names_the_settings_the_run_changed():
    """Learning rates of 1e30 (or a prior std of 1e30) diverged, and the error said to lower lr.means_init and
    lr.scales, neither of which was changed; --resume, which takes the stored settings, diverges again."""
    from uncertsplat.config import TrainConfig
    from uncertsplat.train.session import _changed_fit_settings
    from uncertsplat.train.trainer import _diverged_hint

    cfg = TrainConfig.model_validate({"lr": {"opacities": 1e30}, "variational": {"position_prior_std": 1e30}})
    changed = _changed_fit_settings(cfg)
    assert changed == ["lr.opacities", "variational.position_prior_std"]
    hint = _diverged_hint(changed, "lr.means_init=..., lr.scales=...", True, None)
    assert "changed from their defaults (lr.opacities, variational.position_prior_std) set back" in hint
    assert "lr.means_init" not in hint and "--resume goes on from the last good checkpoint" in hint
    assert "(those that diverged)" in hint
    assert "lower learning rates (--set lr.means_init" in _diverged_hint([], "lr.means_init=..., lr.scales=...",
                                                                        False, "run")
