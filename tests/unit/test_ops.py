"""Topology changes keep parameters, posterior rows, tables and Adam moments row-aligned."""

import math

import pytest
import torch

from uncertsplat.gaussians import ops
from uncertsplat.gaussians.prior import prior_rows
from uncertsplat.gaussians.variational import Prior, random_model
from uncertsplat.train.optim import make_optimizer


def setup(n=40, seed=0):
    g = torch.Generator().manual_seed(seed)
    model = random_model(n, g, carrier_fraction=0.5, perturb_tables=0.1)
    # tag every row: Gaussian i has means[:,0] = i; its table rows have pos_loc[..., 0] = i
    with torch.no_grad():
        model.params["means"][:, 0] = torch.arange(n, dtype=torch.float32)
        idx = model.carrier_index()
        model.tables["pos_loc"][:, :, 0] = idx[:, None].float()
    opt = make_optimizer(model, {k: 1e-3 for k in model.parameters()})
    # one Adam step whose gradient tags each row, so moments identify their owner too
    for p in model.parameters().values():
        p.grad = torch.zeros_like(p)
    model.params["means"].grad[:, 0] = torch.arange(n, dtype=torch.float32) + 1
    model.tables["pos_loc"].grad[:, :, 0] = model.carrier_index()[:, None].float() + 1
    opt.step()
    opt.zero_grad()
    return model, opt, g


def tag(model):
    # Adam moved the tags by ~lr; they stay integers after rounding
    return torch.round(model.params["means"].detach()[:, 0])


def moment_tag(opt, p):
    # exp_avg = (1 - beta1) * grad = 0.1 * (tag + 1) for rows that lived through the tagging step
    return opt.state[p]["exp_avg"][..., 0] / 0.1 - 1


def check_aligned(model, opt, fresh_rows=()):
    model.check()
    params = list(model.parameters().values())
    in_opt = [p for g in opt.param_groups for p in g["params"]]
    assert len(params) == len(in_opt) and all(any(p is q for q in in_opt) for p in params)
    for p in params:
        st = opt.state[p]
        assert st["exp_avg"].shape == p.shape and st["exp_avg_sq"].shape == p.shape
    # table rows and moments follow their owner
    idx = model.carrier_index()
    owner_tag = tag(model)[idx]
    # a Gaussian's table rows carry its tag (clones/children keep the parent's tag)
    torch.testing.assert_close(torch.round(model.tables["pos_loc"].detach()[:, 0, 0]), owner_tag)
    mt = moment_tag(opt, model.params["means"])
    old = mt > -0.5  # rows with moments (new rows start at zero -> tag -1)
    torch.testing.assert_close(mt[old], tag(model)[old], atol=1e-4, rtol=0)
    tmt = moment_tag(opt, model.tables["pos_loc"])[:, 0]
    old_t = tmt > -0.5
    torch.testing.assert_close(tmt[old_t], owner_tag[old_t].round(), atol=1e-4, rtol=0)


def test_remove_keeps_rows_aligned():
    model, opt, _ = setup()
    mask = torch.zeros(40, dtype=torch.bool)
    mask[::3] = True
    before = tag(model)[~mask].clone()
    ops.remove(model, opt, mask)
    assert len(model) == 40 - int(mask.sum())
    torch.testing.assert_close(tag(model), before)
    check_aligned(model, opt)


def test_clone_copies_rows_and_tables():
    model, opt, _ = setup()
    p0 = model.num_carriers
    mask = torch.zeros(40, dtype=torch.bool)
    mask[:10] = True
    carriers_cloned = int((model.posterior_row[:10] >= 0).sum())
    ops.clone(model, opt, mask)
    assert len(model) == 50 and model.num_carriers == p0 + carriers_cloned
    torch.testing.assert_close(tag(model)[40:], tag(model)[:10])
    # clones start with zero moments
    assert (opt.state[model.params["means"]]["exp_avg"][40:] == 0).all()
    check_aligned(model, opt)


def test_split_children_carry_posteriors():
    model, opt, g = setup()
    mask = torch.zeros(40, dtype=torch.bool)
    mask[5:15] = True
    parent_tags = tag(model)[5:15].clone()
    parent_logscale = model.params["scales"].detach()[5:15].clone()
    parent_row = model.posterior_row[5:15].clone()
    assert (parent_row >= 0).any() and (parent_row < 0).any()  # both cases below are exercised
    parent_tables = {k: v.detach()[parent_row.clamp_min(0)].clone() for k, v in model.tables.items()}
    scales = model.params["scales"].detach().exp()
    ops.split(model, opt, mask, g, scales=scales, prior=Prior(), factor=1.6)
    assert len(model) == 40 - 10 + 20
    children = model.posterior_row[-20:]
    assert (children >= 0).all()
    # children sit near their parent (within a few sigma) and are 1.6x smaller
    torch.testing.assert_close(model.params["scales"].detach()[-20:], parent_logscale.repeat(2, 1) - math.log(1.6))
    assert set(torch.round(tag(model)[-20:]).tolist()) <= set(parent_tags.tolist()) | set()
    # child j is a child of parent j % 10: it copies every table row of a parent that had a posterior
    # (all keys, not just the tagged pos_loc), and gets the prior's rows when the parent had none
    had = parent_row.repeat(2) >= 0
    fresh = prior_rows(20, model.num_entries, Prior(), device=model.device, dtype=model.dtype)
    for k, v in model.tables.items():
        rows = v.detach()[children]
        assert torch.equal(rows[had], parent_tables[k].repeat(2, *([1] * (v.ndim - 1)))[had]), k
        assert torch.equal(rows[~had], fresh[k][~had]), k
    model.check()
    assert (opt.state[model.params["means"]]["exp_avg"][-20:] == 0).all()


@pytest.mark.parametrize("variant", ["ours", "paper"])
@pytest.mark.parametrize("keep", [False, True])
def test_split_keep_render_gives_children_of_a_parent_without_rows_the_render_of_3dgs_split(keep, variant):
    """``keep_render`` (variant "ours"): a child whose parent had no posterior renders (posterior mean) with the
    parent's opacity and its scale / 1.6, as a child of a parent with a posterior does; without it (or with the
    paper's variant, where nothing is absorbed) the prior's expected gate and mean multiplier dim and shrink it.
    Children of parents with rows are the same either way."""
    from uncertsplat.gaussians.variational import expected_gate, posterior_mean

    model, opt, g = setup()
    with torch.no_grad():  # opacities from 0.02 to 0.8: below 1 / E[gate], so none is capped
        model.params["opacities"].copy_(torch.logit(torch.linspace(0.02, 0.8, 40)))
    prior = Prior(variant=variant)
    mask = torch.zeros(40, dtype=torch.bool)
    mask[5:15] = True
    had = (model.posterior_row[5:15] >= 0).repeat(2)  # [20]: child j's parent is 5 + j % 10
    assert had.any() and (~had).any()
    before = posterior_mean(model, variant=variant)
    parent_opacity, parent_scales = before.opacities[5:15].repeat(2), before.scales[5:15].repeat(2, 1)
    parent_logscale = model.params["scales"].detach()[5:15].repeat(2, 1)
    ops.split(model, opt, mask, g, scales=model.params["scales"].detach().exp(), prior=prior, factor=1.6,
              keep_render=keep)
    after = posterior_mean(model, variant=variant)
    op, sc = after.opacities[-20:], after.scales[-20:]
    if variant == "ours":  # (the paper's posterior mean is not linear in the base scale)
        torch.testing.assert_close(op[had], parent_opacity[had], rtol=1e-5, atol=1e-7)
        torch.testing.assert_close(sc[had], parent_scales[had] / 1.6, rtol=1e-5, atol=1e-7)
    if keep and variant == "ours":
        torch.testing.assert_close(op[~had], parent_opacity[~had], rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(sc[~had], parent_scales[~had] / 1.6, rtol=1e-5, atol=1e-7)
    elif variant == "ours":
        gate = float(expected_gate(torch.tensor(prior.gate_mean), torch.tensor(prior.gate_std), prior.temperature))
        torch.testing.assert_close(op[~had], parent_opacity[~had] * gate, rtol=1e-5, atol=1e-7)
        torch.testing.assert_close(sc[~had], parent_scales[~had] / 1.6 * (1.0 - 0.5 * prior.scale_width),
                                   rtol=1e-5, atol=1e-7)
    else:  # the paper's variant: nothing absorbed, the children's base parameters are 3DGS's split's
        logit = torch.logit(torch.linspace(0.02, 0.8, 40))[5:15].repeat(2)
        torch.testing.assert_close(model.params["opacities"].detach()[-20:], logit, rtol=0, atol=0)
        torch.testing.assert_close(model.params["scales"].detach()[-20:], parent_logscale - math.log(1.6),
                                   rtol=0, atol=1e-6)
    model.check()


def test_split_keep_render_gives_no_rows_without_carry():
    """With ``carry=False`` (plain 3DGS) a child of a parent without rows gets none, and keep_render changes
    nothing: its base parameters are 3DGS's split's."""
    model, opt, g = setup()
    mask = torch.zeros(40, dtype=torch.bool)
    mask[5:15] = True
    had = (model.posterior_row[5:15] >= 0).repeat(2)
    parent_logit = model.params["opacities"].detach()[5:15].repeat(2).clone()
    ops.split(model, opt, mask, g, scales=model.params["scales"].detach().exp(), prior=Prior(), carry=False,
              keep_render=True)
    assert (model.posterior_row[-20:] >= 0).tolist() == had.tolist()
    assert torch.equal(model.params["opacities"].detach()[-20:], parent_logit)
    model.check()


def test_spawn_adds_prior_rows_only_for_new_carriers():
    model, opt, _ = setup()
    p0 = model.num_carriers
    newly = int((model.posterior_row < 0).sum())
    n_new = ops.spawn(model, opt, torch.ones(40, dtype=torch.bool), Prior())
    assert n_new == newly and model.num_carriers == p0 + newly == 40
    added = model.tables["pos_loc"].detach()[p0:]
    assert (added == 0).all()  # prior location
    assert (opt.state[model.tables["pos_loc"]]["exp_avg"][p0:] == 0).all()
    assert ops.spawn(model, opt, torch.ones(40, dtype=torch.bool), Prior()) == 0
    model.check()


@pytest.mark.parametrize("keep", [False, True])
def test_spawn_keep_render_preserves_the_posterior_mean(keep):
    """``keep_render``: the new carriers' posterior-mean opacity and scale are what they were without a posterior
    (to float rounding; an opacity too high to divide by the prior's gate is capped); the old carriers and every
    other parameter are untouched. Without it the prior dims and shrinks them."""
    from uncertsplat.gaussians.variational import expected_gate, posterior_mean

    model, opt, _ = setup()
    with torch.no_grad():  # opacities from 0.02 to 0.8: below 1 / E[gate], so none is capped
        model.params["opacities"].copy_(torch.logit(torch.linspace(0.02, 0.8, 40)))
    prior = Prior()
    new = model.posterior_row < 0
    before = posterior_mean(model, variant="ours")
    means = model.params["means"].detach().clone()
    ops.spawn(model, opt, torch.ones(40, dtype=torch.bool), prior, keep_render=keep)
    after = posterior_mean(model, variant="ours")
    torch.testing.assert_close(after.opacities[~new], before.opacities[~new], rtol=1e-6, atol=0)
    torch.testing.assert_close(after.scales[~new], before.scales[~new], rtol=1e-6, atol=0)
    torch.testing.assert_close(model.params["means"].detach(), means, rtol=0, atol=0)
    gate = float(expected_gate(torch.tensor(prior.gate_mean), torch.tensor(prior.gate_std), prior.temperature))
    mult = 1.0 - 0.5 * prior.scale_width
    if keep:
        torch.testing.assert_close(after.opacities[new], before.opacities[new], rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(after.scales[new], before.scales[new], rtol=1e-5, atol=1e-7)
    else:
        torch.testing.assert_close(after.opacities[new], before.opacities[new] * gate, rtol=1e-5, atol=1e-7)
        torch.testing.assert_close(after.scales[new], before.scales[new] * mult, rtol=1e-5, atol=1e-7)
    model.check()


def test_spawn_keep_render_caps_an_opacity_the_gate_cannot_carry():
    model, opt, _ = setup()
    new = model.posterior_row < 0
    with torch.no_grad():
        model.params["opacities"].fill_(10.0)  # sigmoid 0.99995: more than E[gate] x 1 allows
    ops.spawn(model, opt, torch.ones(40, dtype=torch.bool), Prior(), keep_render=True)
    assert torch.isfinite(model.params["opacities"]).all()
    assert float(torch.sigmoid(model.params["opacities"].detach()[new]).max()) <= 1.0 - 1e-4 + 1e-7


def test_reset_opacity_caps_and_zeroes_moments():
    model, opt, _ = setup()
    with torch.no_grad():
        model.params["opacities"][0] = -10.0
    ops.reset_opacity(model, opt, 0.01)
    op = torch.sigmoid(model.params["opacities"].detach())
    assert (op <= 0.01 + 1e-6).all() and op[0] < 1e-4
    assert (opt.state[model.params["opacities"]]["exp_avg"] == 0).all()
    # the cap is the opacity itself, not a logit near it: the Gaussians that were above it sit at 0.01 exactly
    assert float(op.max()) == pytest.approx(0.01, rel=1e-5)
    ops.reset_opacity(model, opt, 0.3)  # (far from 0, where log p and the logit part)
    assert float(torch.sigmoid(model.params["opacities"].detach()).max()) <= 0.01 + 1e-6
    with torch.no_grad():
        model.params["opacities"].fill_(5.0)
    ops.reset_opacity(model, opt, 0.3)
    torch.testing.assert_close(torch.sigmoid(model.params["opacities"].detach()),
                               torch.full((len(model),), 0.3), rtol=1e-5, atol=0)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_random_sequences_stay_aligned(seed):
    model, opt, g = setup(60, seed)
    r = torch.Generator().manual_seed(seed + 100)
    for _ in range(6):
        n = len(model)
        choice = torch.randint(0, 4, (1,), generator=r).item()
        mask = torch.rand(n, generator=r) < 0.2
        if choice == 0:
            ops.clone(model, opt, mask)
        elif choice == 1:
            ops.split(model, opt, mask, g, scales=model.params["scales"].detach().exp(), prior=Prior())
        elif choice == 2:
            ops.remove(model, opt, mask)
        else:
            ops.spawn(model, opt, mask, Prior())
        model.check()
        idx = model.carrier_index()
        # split children of non-carriers get prior rows (tag 0), everything else keeps its owner's tag
        loc = torch.round(model.tables["pos_loc"].detach()[:, 0, 0])
        own = torch.round(tag(model)[idx])
        assert ((loc == own) | (loc == 0)).all()
    # optimisation still works after all that: every parameter and table row moves down its gradient
    params = model.parameters()
    before = {k: p.detach().clone() for k, p in params.items()}
    loss = sum(p.square().sum() for p in params.values())
    loss.backward()
    opt.step()
    for k, p in params.items():
        moved = (p.detach() - before[k]).reshape(len(p), -1).abs().amax(1) > 0
        assert moved[before[k].reshape(len(p), -1).abs().amax(1) > 0].all(), k
    assert sum(p.square().sum() for p in params.values()) < loss


def test_remove_without_optimizer():
    model, _, _ = setup()
    ops.remove(model, None, torch.arange(40) < 5)
    assert len(model) == 35
    model.check()
