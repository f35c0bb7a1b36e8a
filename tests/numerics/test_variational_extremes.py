"""KL and samplers stay finite at extreme spreads, saturated gates, huge/tiny scenes and P = 0."""

import pytest
import torch

from uncertsplat.gaussians.variational import (
    Prior,
    carrier_uncertainty,
    expected_render_sample,
    inverse_softplus,
    kl_terms,
    posterior_mean,
    random_model,
    sample,
)


def _set(model, name, value):
    with torch.no_grad():
        model.tables[name].fill_(value)


@pytest.mark.parametrize("variant", ["ours", "paper"])
@pytest.mark.parametrize("spread", [1e-8, 1e3])
@pytest.mark.parametrize("gate_loc", [-1e4, 0.0, 1e4])
def test_extremes_are_finite(variant, spread, gate_loc):
    prior = Prior(variant=variant)
    model = random_model(16, torch.Generator().manual_seed(0), carrier_fraction=1.0, prior=prior)
    raw = float(inverse_softplus(torch.tensor(spread, dtype=torch.float64)))
    for name in ("pos_spread_raw", "scale_width_raw", "gate_spread_raw"):
        _set(model, name, raw)
    _set(model, "gate_loc", gate_loc)
    kl = kl_terms(model, prior)
    s = sample(model, torch.Generator().manual_seed(1), variant=variant)
    pm = posterior_mean(model, variant=variant)
    er = expected_render_sample(model, variant=variant)
    total = (kl["total"] + s.means.sum() + s.opacities.sum() + pm.opacities.sum() + pm.means.sum()
             + er.opacities.sum() + er.means.sum())
    assert torch.isfinite(total), {k: float(v) for k, v in kl.items()}
    if variant == "ours":  # the paper's exp(s * o) with o up to 100 legitimately overflows
        assert torch.isfinite(s.scales).all()
        assert torch.isfinite(er.scales).all() and (er.scales > 0).all()
    assert ((er.opacities >= 0) & (er.opacities <= 1)).all()
    total.backward()
    for name, p in model.parameters().items():
        assert p.grad is None or torch.isfinite(p.grad).all(), name
    for v in carrier_uncertainty(model, variant=variant).values():
        assert torch.isfinite(v).all()


def test_very_negative_raw_spread_is_finite():
    model = random_model(4, torch.Generator().manual_seed(0), carrier_fraction=1.0)
    _set(model, "pos_spread_raw", -200.0)
    _set(model, "gate_spread_raw", -200.0)
    kl = kl_terms(model, Prior())
    assert torch.isfinite(kl["total"])
    kl["total"].backward()
    assert torch.isfinite(model.tables["pos_spread_raw"].grad).all()


def test_empty_posterior_set():
    model = random_model(8, torch.Generator().manual_seed(0), carrier_fraction=0.0)
    assert model.num_carriers == 0
    kl = kl_terms(model, Prior())
    assert all(float(v.detach()) == 0.0 for v in kl.values())
    s = sample(model, torch.Generator().manual_seed(0))
    torch.testing.assert_close(s.means, model.params["means"].detach())
    pm = posterior_mean(model)
    torch.testing.assert_close(pm.scales, model.params["scales"].detach().exp())


def test_empty_model():
    model = random_model(0, torch.Generator().manual_seed(0))
    assert len(model) == 0 and model.num_carriers == 0
    assert len(sample(model, torch.Generator().manual_seed(0))) == 0
    assert torch.isfinite(kl_terms(model, Prior())["total"])


@pytest.mark.parametrize("scale", [1e-3, 1e3])
def test_offsets_are_in_units_of_the_extent(scale):
    """Ours draws the position offsets in units of the scene extent (which is why its KL, taken in those units, does
    not depend on the scene's scale); the paper's draws them in world units, whatever the extent."""
    m = random_model(10, torch.Generator().manual_seed(2), carrier_fraction=1.0, perturb_tables=0.2)
    base = m.params["means"].detach()
    unit = sample(m, torch.Generator().manual_seed(3), extent=1.0).means - base
    scaled = sample(m, torch.Generator().manual_seed(3), extent=scale).means - base
    assert unit.abs().max() > 1e-3  # the samples move the Gaussians: the comparison below is not of zeros
    torch.testing.assert_close(scaled, unit * scale, rtol=1e-3, atol=1e-6 * max(scale, 1.0))
    paper = random_model(10, torch.Generator().manual_seed(2), carrier_fraction=1.0, perturb_tables=0.2,
                         prior=Prior(variant="paper"))
    draw = lambda extent: sample(paper, torch.Generator().manual_seed(3), variant="paper", extent=extent).means  # noqa: E731
    torch.testing.assert_close(draw(scale), draw(1.0))
    assert torch.isfinite(kl_terms(m, Prior())["total"])
