"""Schedules and densify / prune / spawn decisions, table-driven."""

import math
from types import SimpleNamespace

import pytest
import torch

from uncertsplat.config import DensifyConfig
from uncertsplat.gaussians.variational import Prior, random_model
from uncertsplat.strategy.densify import (
    Densifier,
    densify_decisions,
    limit_growth,
    prune_decisions,
    spawn_decisions,
)
from uncertsplat.strategy.schedule import (
    is_densify_step,
    is_opacity_reset_step,
    is_spawn_step,
    is_stats_step,
    position_lr,
    sh_degree_at,
)

CFG = DensifyConfig(start=100, until=400, interval=100, spawn_interval=200, opacity_reset_interval=300)


@pytest.mark.parametrize(
    "step, densify, reset, spawn, stats",
    [
        (1, False, False, False, True),
        (100, False, False, False, True),  # start itself is excluded (3DGS: iteration > from_iter)
        (150, False, False, False, True),
        (200, True, False, True, True),
        (300, True, True, False, True),
        (399, False, False, False, True),
        (400, False, False, True, False),  # until excluded for densify, included for spawn
        (500, False, False, False, False),
        (600, False, False, False, False),
    ],
)
def test_schedule_table(step, densify, reset, spawn, stats):
    assert is_densify_step(step, CFG) == densify
    assert is_opacity_reset_step(step, CFG) == reset
    assert is_spawn_step(step, CFG) == spawn
    assert is_stats_step(step, CFG) == stats


def test_opacity_reset_disabled_by_zero():
    cfg = SimpleNamespace(opacity_reset_interval=0, until=1000)
    assert not any(is_opacity_reset_step(s, cfg) for s in range(1, 1000))


def test_no_opacity_reset_at_until():
    """Opacity resets happen while densifying, strictly before ``until``: none at ``until`` itself when it is a
    multiple of the interval (the table's ``until``, 400, is no multiple of 300, so it could not tell)."""
    cfg = DensifyConfig(start=100, until=400, opacity_reset_interval=200)
    assert is_opacity_reset_step(400, cfg) is False
    assert is_opacity_reset_step(200, cfg) is True


@pytest.mark.parametrize("step, interval, max_deg, expected",
                         [(0, 1000, 3, 0), (999, 1000, 3, 0), (1000, 1000, 3, 1), (5000, 1000, 3, 3),
                          (250, 100, 1, 1), (50, 100, 0, 0)])
def test_sh_degree_schedule(step, interval, max_deg, expected):
    assert sh_degree_at(step, max_deg, interval) == expected


def test_position_lr_decays_exponentially_and_scales_with_extent():
    assert position_lr(0, 100, 1e-4, 1e-6, 2.0) == pytest.approx(2e-4)
    assert position_lr(100, 100, 1e-4, 1e-6, 2.0) == pytest.approx(2e-6)
    assert position_lr(50, 100, 1e-4, 1e-6, 1.0) == pytest.approx(1e-5)  # geometric midpoint
    assert position_lr(500, 100, 1e-4, 1e-6, 1.0) == pytest.approx(1e-6)


def test_position_table_rate_is_in_units_of_the_extent():
    """``train.optim.base_rates``: in variant "ours" the position tables are in units of the extent, so their rate
    is ``table_lr_factor`` x the position rate / extent (the position rate itself grows with it); at the demo
    scenes' extent (~1.1) a missing division hid. The paper's tables are in world units; the rest ignore it."""
    from uncertsplat.config import LearningRates
    from uncertsplat.train.optim import base_rates

    lr = LearningRates()
    ours = base_rates(lr, 0, 100, 5.0, table_lr_factor=0.1, variant="ours")
    assert ours["means"] == pytest.approx(lr.means_init * 5.0)
    assert ours["pos_spread_raw"] == ours["pos_loc"] == pytest.approx(0.1 * lr.means_init)
    assert ours["scale_width_raw"] == ours["scale_left"] == pytest.approx(0.1 * lr.scales)
    assert ours["gate_spread_raw"] == ours["gate_loc"] == pytest.approx(0.1 * lr.opacities)
    paper = base_rates(lr, 0, 100, 5.0, table_lr_factor=0.1, variant="paper")
    assert paper["pos_loc"] == pytest.approx(0.1 * lr.means_init * 5.0)


@pytest.mark.parametrize(
    "grad, max_scale, clone, split",
    [
        (1e-4, 0.001, False, False),  # cold
        (2e-4, 0.001, True, False),  # at the threshold, small -> clone
        (5e-4, 0.011, True, False),  # 0.011 <= 0.01 * 1.1 -> still small
        (5e-4, 0.02, False, True),  # large -> split
        (1e-5, 0.5, False, False),
    ],
)
def test_densify_decisions_table(grad, max_scale, clone, split):
    c, s = densify_decisions(torch.tensor([grad]), torch.tensor([max_scale]), grad_threshold=2e-4,
                             percent_dense=0.01, extent=1.1)
    assert bool(c) == clone and bool(s) == split


@pytest.mark.parametrize(
    "opacity, radius, scale, max_screen, expected",
    [
        (0.004, 1.0, 0.01, None, True),
        (0.006, 1.0, 0.01, None, False),
        (0.5, 30.0, 0.01, None, False),  # big on screen but no screen limit
        (0.5, 30.0, 0.01, 20.0, True),
        (0.5, 1.0, 0.2, 20.0, True),  # larger than 0.1 x extent
        (0.5, 1.0, 0.05, 20.0, False),
    ],
)
def test_prune_decisions_table(opacity, radius, scale, max_screen, expected):
    out = prune_decisions(torch.tensor([opacity]), min_opacity=0.005, max_scale=torch.tensor([scale]),
                          screen_radius=torch.tensor([radius]), max_screen_size=max_screen, extent=1.0)
    assert bool(out) == expected


@pytest.mark.parametrize(
    "scale, opacity, expected",
    [
        (0.02, 0.5, True),  # ||(.02,.02,.02)|| = 0.035 > 0.011
        (0.005, 0.5, False),  # 0.0087 < 0.011
        (0.02, 0.0004, False),  # transparent
        (0.02, 0.0005, True),
    ],
)
def test_spawn_decisions_table(scale, opacity, expected):
    out = spawn_decisions(torch.full((1, 3), scale), torch.tensor([opacity]), scale_fraction=0.01,
                          min_opacity=0.0005, extent=1.1)
    assert bool(out) == expected


def test_limit_growth_keeps_highest_gradients():
    grad = torch.tensor([5.0, 4.0, 3.0, 2.0, 1.0])
    clone = torch.tensor([True, False, True, False, True])
    split = torch.tensor([False, True, False, True, False])
    c, s = limit_growth(clone, split, grad, n=10, max_gaussians=13)
    assert c.tolist() == [True, False, True, False, False] and s.tolist() == [False, True, False, False, False]
    c2, s2 = limit_growth(clone, split, grad, n=10, max_gaussians=100)
    assert torch.equal(c2, clone) and torch.equal(s2, split)


def test_densifier_uses_posterior_mean_and_keeps_stats_aligned():
    from uncertsplat.train.optim import make_optimizer

    g = torch.Generator().manual_seed(0)
    model = random_model(30, g, carrier_fraction=0.5, perturb_tables=0.05)
    with torch.no_grad():
        model.params["opacities"][:3] = -10.0  # transparent -> pruned
        model.params["scales"][3:6] = math.log(0.3)  # large -> split when hot
        model.params["scales"][6:10] = math.log(0.001)  # small -> clone when hot
        model.params["opacities"][3:] = model.params["opacities"][3:].clamp_min(0.0)
    opt = make_optimizer(model, {k: 1e-3 for k in model.parameters()})
    cfg = DensifyConfig(start=0, until=1000, interval=10, spawn_interval=10, opacity_reset_interval=0,
                        grad_threshold=1e-3)
    d = Densifier(cfg, Prior(), extent=1.0, n=len(model), device=model.device)
    grad = torch.zeros(1, 30, 2)
    grad[0, 3:10] = 1.0  # hot
    radii = torch.ones(1, 30)
    d.accumulate(10, grad, radii, 64, 48)
    # the pruned (0:3) and split (3:6) Gaussians' posteriors go; the 6 split children carry one each, a clone of a
    # carrier (6:10) one of its own
    rows = model.posterior_row
    carriers_without_spawns = model.num_carriers - int((rows[:6] >= 0).sum()) + 6 + int((rows[6:10] >= 0).sum())
    state_before = torch.get_rng_state()
    done = d.step(10, model, opt, g)
    assert torch.equal(torch.get_rng_state(), state_before)  # no global RNG use
    assert done["split"] == 3 and done["cloned"] == 4 and done["pruned"] == 3
    assert len(model) == 30 + 4 + 3 - 3
    assert d.stats.grad_sum.shape == (len(model),)
    model.check()
    # split children carry posteriors; large Gaussians spawned (they carry one too, and nothing else gained one)
    assert (model.posterior_row[-6:] >= 0).all()
    assert done["spawned"] > 0
    assert model.num_carriers == carriers_without_spawns + done["spawned"]


@pytest.mark.parametrize("grown_to, size", [(None, 27), (33, 30), (40, 34), (10, 27)])
def test_after_the_growth_test_stops_growth_densification_refills_up_to_the_size_it_stopped_at(grown_to, size):
    """30 Gaussians, 3 of them transparent, 7 hot clone candidates (30 + 7 - 3 = 34 unbounded). Stopped with
    ``grown_to`` = None (a checkpoint from before the refill): it only prunes; with a size, the clones fill the model
    up to that size (the room pruning made at earlier steps), never past it, as a budget of that size does; a size
    below the model's is not cut down to (pruning alone decides that)."""
    from uncertsplat.train.optim import make_optimizer

    g = torch.Generator().manual_seed(0)
    model = random_model(30, g, carrier_fraction=0.0)
    with torch.no_grad():
        model.params["opacities"][:] = 2.0
        model.params["opacities"][:3] = -10.0  # transparent -> pruned
        model.params["scales"][:] = math.log(0.001)  # small -> clone when hot
    opt = make_optimizer(model, {k: 1e-3 for k in model.parameters()})
    cfg = DensifyConfig(start=0, until=1000, interval=10, spawn_interval=10**6, opacity_reset_interval=0,
                        grad_threshold=1e-3)
    d = Densifier(cfg, Prior(), extent=1.0, n=len(model), device=model.device)
    d.grow, d.grown_to = False, grown_to
    grad = torch.zeros(1, 30, 2)
    grad[0, 3:10] = 1.0  # 7 hot ones
    d.accumulate(10, grad, torch.ones(1, 30), 64, 48)
    done = d.step(10, model, opt, g)
    assert len(model) == size
    assert done["cloned"] == size - 27 and done["pruned"] == 3


def test_accumulate_converts_pixel_gradients_to_ndc():
    cfg = DensifyConfig(start=0, until=100)
    d = Densifier(cfg, Prior(), extent=1.0, n=3, device=torch.device("cpu"))
    grad = torch.tensor([[[1.0, 0.0], [0.0, 1.0], [5.0, 5.0]]])  # [C=1,N=3,2] pixels
    radii = torch.tensor([[2.0, 3.0, 0.0]])  # the third is culled: no statistics
    d.accumulate(1, grad, radii, width=64, height=48)
    d.accumulate(2, grad, radii, width=64, height=48)
    torch.testing.assert_close(d.stats.grad_sum, torch.tensor([64.0, 48.0, 0.0]))  # 2 x (32, 24, -)
    torch.testing.assert_close(d.stats.count, torch.tensor([2.0, 2.0, 0.0]))
    torch.testing.assert_close(d.stats.max_radius, torch.tensor([2.0, 3.0, 0.0]))
    d.accumulate(100, grad, radii, width=64, height=48)  # after `until`: ignored
    torch.testing.assert_close(d.stats.count, torch.tensor([2.0, 2.0, 0.0]))


@pytest.mark.parametrize("views", [1, 3])
def test_accumulate_native_pass_gives_the_bits_of_the_tensor_ops(views, monkeypatch):
    """The native pass (``native/csrc/densify.cpp``) and the tensor ops agree to the bit on gradients over nine
    decades, culled Gaussians and several views, so densification decides as it did before the kernel."""
    from uncertsplat import native

    if native.library() is None:
        pytest.skip("native kernels unavailable")
    g = torch.Generator().manual_seed(views)
    n = 5000
    grad = torch.randn(views, n, 2, generator=g) * 10.0 ** torch.randint(-7, 2, (views, n, 1), generator=g)
    radii = torch.rand(views, n, generator=g) * 40.0 * (torch.rand(views, n, generator=g) > 0.3)
    stats = {}
    for backend in ("torch", "native"):
        monkeypatch.setenv("UNCERTSPLAT_RASTERIZER", backend)
        d = Densifier(DensifyConfig(start=0, until=100), Prior(), extent=1.0, n=n, device=torch.device("cpu"))
        d.accumulate(1, grad, radii, width=401, height=266)
        d.accumulate(2, grad.flip(1), radii.flip(1), width=401, height=266)
        stats[backend] = d.stats
    for name in ("grad_sum", "count", "max_radius"):
        assert torch.equal(getattr(stats["native"], name), getattr(stats["torch"], name)), name
    assert (stats["native"].count == 0).any() and (stats["native"].count > 0).any()


def test_no_opacity_reset_in_the_last_steps_of_a_run():
    """A run cut inside the preset's densification window (e.g. --iterations 3000 with reset interval 3000 and
    densify until 4000) must not end on a reset: every opacity at 0.01 and no step left to recover."""
    from uncertsplat.gaussians.variational import random_model
    from uncertsplat.strategy.densify import RESET_RECOVERY_STEPS

    cfg = DensifyConfig(start=10**6, until=4000, opacity_reset_interval=1000, spawn_interval=10**6)
    for iterations, resets in ((3000, [1000, 2000]), (3500, [1000, 2000]), (10_000, [1000, 2000, 3000])):
        model = random_model(8, torch.Generator().manual_seed(0))
        d = Densifier(cfg, Prior(), extent=1.0, n=len(model), device=model.device, iterations=iterations)
        got = [s for s in (1000, 2000, 3000) if d.step(s, model, None, torch.Generator())["reset"]]
        assert got == resets, (iterations, got)
        assert all(s <= iterations - RESET_RECOVERY_STEPS for s in got)


def test_the_last_tenth_of_a_run_never_densifies():
    """A run shortened below its preset's densify.until densified at its last step (fern, 1500 of the paper's 7000
    steps: 14k untrained Gaussians, 1.5 dB held out). The last SETTLE_FRACTION grows nothing, nor tests growth; every
    preset's own schedule ends before it."""
    from uncertsplat.config import train_config_from
    from uncertsplat.strategy.growth import growth_check_due
    from uncertsplat.strategy.schedule import SETTLE_FRACTION, densify_end, densify_steps_after

    cfg = DensifyConfig(start=500, until=4000, interval=100)
    assert SETTLE_FRACTION == 0.1
    assert is_densify_step(1500, cfg) and not is_densify_step(1500, cfg, iterations=1500)
    assert is_densify_step(1300, cfg, iterations=1500) and is_densify_step(1350 // 100 * 100, cfg, iterations=1500)
    assert not is_densify_step(1400, cfg, iterations=1500)  # past 0.9 x 1500 + 1 = 1351
    # at its edge: the last tenth of 1000 steps is 901-1000, so step 900 still densifies
    assert is_densify_step(900, cfg, iterations=1000) and not is_densify_step(1000, cfg, iterations=1000)
    # densify_steps_after says whether is_densify_step holds at a later step up to the run's end, short runs too
    small = DensifyConfig(start=0, until=100, interval=5)
    for last in range(1, 40):
        for step in range(last + 1):
            expect = any(is_densify_step(s, small, iterations=last) for s in range(step + 1, last + 1))
            assert densify_steps_after(step, small, last_step=last) == expect, (step, last)
    assert densify_steps_after(1300, cfg) and not densify_steps_after(1300, cfg, last_step=1500)
    grow = cfg.model_copy(update={"growth_check_interval": 250})
    assert growth_check_due(1500, grow) and not growth_check_due(1500, grow, iterations=1500)
    for preset in ("tiny", "demo", "paper", None):
        c = train_config_from(preset)
        assert densify_end(c.densify, c.iterations) == c.densify.until, preset
