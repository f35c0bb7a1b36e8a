"""Unit tests of the baselines: method table, ensemble sampler, Fisher diagonal, Laplace samples."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch

from uncertsplat.baselines import METHODS, method_label, method_overrides
from uncertsplat.baselines.ensemble import ensemble_sample_fn
from uncertsplat.baselines.fisher import fisher_diagonal, perturbed_sample, posterior_variance
from uncertsplat.config import TrainConfig, build_config, deep_update
from uncertsplat.errors import UserError
from uncertsplat.gaussians.variational import random_model
from uncertsplat.uncertainty.curvature import curvature, residual_noise_std


def test_every_method_resolves_to_a_valid_config_and_label():
    labels = {}
    for name in METHODS:
        cfg = build_config(TrainConfig, deep_update({}, method_overrides(name)))
        labels[name] = method_label(cfg)
    assert labels["vi-single"] == "vi-single" and labels["paper"] == "paper"
    assert labels["ensemble"] == "ensemble-10" and labels["fisher"] == "fisher"
    ours = build_config(TrainConfig, {"method": "ensemble", "ensemble_size": 2, "ensemble_members": "variational"})
    assert method_label(ours) == "ensemble-2-variational"
    assert len(set(labels.values())) == len(labels)
    cfg = build_config(TrainConfig, method_overrides("vi-single"))
    assert cfg.method == "variational" and cfg.variational.num_entries == 1


def test_unknown_method():
    with pytest.raises(UserError, match="unknown method"):
        method_overrides("dropout")


def test_method_overrides_is_a_copy():
    method_overrides("vi-single")["variational"]["num_entries"] = 99
    assert METHODS["vi-single"]["variational"]["num_entries"] == 1


# ------------------------------------------------------------------------------------------- ensemble
def test_ensemble_sampler_uses_each_member_once_per_cycle():
    members = [object() for _ in range(3)]
    fn = ensemble_sample_fn(members)
    g = torch.Generator().manual_seed(5)
    first = [members.index(fn(g)) for _ in range(3)]
    assert sorted(first) == [0, 1, 2]
    more = [members.index(fn(g)) for _ in range(3)]  # the next cycle: again each member once
    assert sorted(more) == [0, 1, 2]
    # re-seeding starts a new sequence: the same seed gives the same members, in the same order
    g.manual_seed(5)
    assert [members.index(fn(g)) for _ in range(3)] == first
    # another seed gives some other order (over a few seeds at least one differs)
    orders = set()
    for s in range(8):
        g.manual_seed(100 + s)
        orders.add(tuple(members.index(fn(g)) for _ in range(3)))
    assert len(orders) > 1


def test_variational_members_are_drawn_from_and_still_cycled():
    """A member given as a function (a variational member's posterior) is drawn from with the view's generator; the
    draw moving the generator does not break the cycle (each member once per N samples), and the same seed gives the
    same members and the same draws."""
    calls = []

    def member(i):
        def draw(g):
            x = float(torch.rand((), generator=g))
            calls.append(i)
            return (i, x)
        return draw

    fn = ensemble_sample_fn([member(i) for i in range(3)])
    g = torch.Generator().manual_seed(7)
    first = [fn(g) for _ in range(6)]
    assert sorted(i for i, _ in first[:3]) == [0, 1, 2] and sorted(i for i, _ in first[3:]) == [0, 1, 2]
    assert len({x for _, x in first}) == 6  # every sample its own draw
    g.manual_seed(7)
    assert [fn(g) for _ in range(6)] == first


def test_ensemble_sampler_gives_each_thread_its_serial_sequence():
    """Two threads drawing from one sampler at once, each with its own generator (``Predictor.predict`` from a
    thread pool), get the members a serial draw gives: one thread's draws do not restart the other's cycle."""
    import threading

    members = [object() for _ in range(3)]
    seeds, draws = (11, 12), 6
    serial = {}
    for s in seeds:
        fn = ensemble_sample_fn(members)
        g = torch.Generator().manual_seed(s)
        serial[s] = [members.index(fn(g)) for _ in range(draws)]
    shared = ensemble_sample_fn(members)
    turns = [threading.Event() for _ in range(2 * draws + 1)]  # the draws alternate: thread 0, 1, 0, 1, ...
    got: dict[int, list[int]] = {}

    def work(t: int) -> None:
        g = torch.Generator().manual_seed(seeds[t])
        out = []
        for d in range(draws):
            assert turns[2 * d + t].wait(10)
            out.append(members.index(shared(g)))
            turns[2 * d + t + 1].set()
        got[seeds[t]] = out

    threads = [threading.Thread(target=work, args=(t,)) for t in range(2)]
    for th in threads:
        th.start()
    turns[0].set()
    for th in threads:
        th.join(20)
    assert got == serial


def test_ensemble_of_one_returns_the_same_sample():
    only = object()
    fn = ensemble_sample_fn([only])
    g = torch.Generator().manual_seed(0)
    assert all(fn(g) is only for _ in range(4))
    with pytest.raises(ValueError):
        ensemble_sample_fn([])


# -------------------------------------------------------------------------------------------- fisher
class _Cams:
    """A stand-in for Cameras: T 'views', each a fixed linear map of the means to a 4x5 image."""

    def __init__(self, maps):
        self.maps = maps  # [T,3,60]

    def __len__(self):
        return self.maps.shape[0]

    def __getitem__(self, idx):
        return _Cams(self.maps[idx])


def _linear_render(sample, cams):
    # rgb depends on the sum of the means only: d rgb / d means[i,a] = maps[a] for every Gaussian i
    flat = sample.means.sum(0) @ cams.maps[0]  # [60]
    return SimpleNamespace(rgb=flat.reshape(1, 4, 5, 3))


def _params(n=4, gen=None):
    model = random_model(n, gen or torch.Generator().manual_seed(0), sh_degree=0, carrier_fraction=0.0)
    return {k: v.detach() for k, v in model.params.items()}


def test_ggn_fisher_is_an_unbiased_estimate_of_diag_jtj():
    gen = torch.Generator().manual_seed(1)
    params = _params()
    maps = torch.randn(8, 3, 60, generator=gen)
    cams = _Cams(maps)
    images = torch.zeros(8, 4, 5, 3)
    noise = 0.5
    f = fisher_diagonal(params, cams, images, _linear_render, names=("means", "scales"), noise_std=noise,
                        generator=gen, sh_degree=0, estimator="ggn", probes=64)
    exact = maps.square().sum(-1).sum(0) / noise**2  # [3]: sum over views and pixels of J^2
    assert f["means"].shape == params["means"].shape
    for i in range(params["means"].shape[0]):
        assert torch.allclose(f["means"][i], exact, rtol=0.2), (f["means"][i], exact)
    assert torch.all(f["scales"] == 0), "parameters the render ignores carry no information"
    assert "opacities" not in f


def test_empirical_fisher_is_the_squared_view_gradient():
    gen = torch.Generator().manual_seed(2)
    params = _params()
    maps = torch.randn(3, 3, 60, generator=gen)
    images = torch.rand(3, 4, 5, 3, generator=gen)
    noise = 0.2
    f = fisher_diagonal(params, _Cams(maps), images, _linear_render, names=("means",), noise_std=noise,
                        generator=gen, sh_degree=0, estimator="empirical")
    s = params["means"].sum(0)
    expected = torch.zeros(3)
    for t in range(3):
        r = s @ maps[t] - images[t].reshape(-1)
        expected += (maps[t] @ r / noise**2).square()
    assert torch.allclose(f["means"][0], expected, rtol=1e-4)
    assert torch.allclose(f["means"], f["means"][:1].expand_as(f["means"]))


def test_posterior_variance_between_zero_and_the_prior():
    fisher = {"means": torch.tensor([0.0, 1.0, 1e6])}
    v = posterior_variance(fisher, {"means": 0.5})
    assert v["means"][0] == pytest.approx(0.25)  # no information: the prior
    assert v["means"][1] == pytest.approx(1.0 / (1.0 + 4.0))
    assert v["means"][2] < 1e-5


def test_a_gaussian_without_information_has_the_prior_variance_in_units_of_the_extent():
    """``compute_fisher``'s prior (``prior_stds``): the position prior std is ``prior_std_means`` x the scene extent
    (the others are in their own units), so a Gaussian with no Fisher information keeps (prior_std_means x extent)^2
    as its position variance. At an extent near 1 a missing factor hid."""
    from uncertsplat.baselines.fisher import prior_stds
    from uncertsplat.config import FisherConfig

    fcfg = FisherConfig(prior_std_means=0.02, prior_std_scales=0.3)
    v = posterior_variance({"means": torch.zeros(2, 3), "scales": torch.zeros(2, 3)}, prior_stds(fcfg, 5.0))
    assert v["means"].tolist() == [[pytest.approx((0.02 * 5.0) ** 2)] * 3] * 2
    assert v["scales"].tolist() == [[pytest.approx(0.3 ** 2)] * 3] * 2


def test_perturbed_sample_is_repeatable_and_zero_variance_is_the_mean():
    params = _params(6)
    var = {k: torch.full_like(params[k], 0.01) for k in ("means", "scales", "opacities", "sh0")}
    a = perturbed_sample(params, var, torch.Generator().manual_seed(3), sh_degree=0)
    b = perturbed_sample(params, var, torch.Generator().manual_seed(3), sh_degree=0)
    c = perturbed_sample(params, var, torch.Generator().manual_seed(4), sh_degree=0)
    assert torch.equal(a.means, b.means) and torch.equal(a.opacities, b.opacities)
    assert not torch.equal(a.means, c.means)
    assert torch.all(a.scales > 0) and torch.all((a.opacities > 0) & (a.opacities < 1))
    zero = {k: torch.zeros_like(v) for k, v in var.items()}
    m = perturbed_sample(params, zero, torch.Generator().manual_seed(3), sh_degree=0)
    assert torch.equal(m.means, params["means"]) and torch.allclose(m.scales, params["scales"].exp())
    # spread of the means matches the variance (std 0.1) over many Gaussians
    big = _params(2000)
    var = {"means": torch.full_like(big["means"], 0.01)}
    d = perturbed_sample(big, var, torch.Generator().manual_seed(0), sh_degree=0).means - big["means"]
    assert d.std().item() == pytest.approx(0.1, rel=0.05)


def test_perturbed_sample_adds_its_noise_in_the_documented_order_to_every_perturbed_parameter():
    """``perturbed_sample`` is ``theta + sqrt(var) * eps`` with eps drawn from the generator in ``PARAM_ORDER``
    (means, scales, opacities, sh0), each added to its own stored parameter before the activation: the DC colour too,
    and with the sign given (an offset subtracted has the same spread and would pass a test of the spread alone)."""
    from uncertsplat.baselines.fisher import PARAM_ORDER

    params = _params(5)
    gen = torch.Generator().manual_seed(11)
    var = {k: torch.rand(params[k].shape, generator=gen) * 0.04 + 0.01 for k in PARAM_ORDER}
    got = perturbed_sample(params, var, torch.Generator().manual_seed(12), sh_degree=0)
    draws = torch.Generator().manual_seed(12)
    moved = {k: params[k] + var[k].sqrt() * torch.randn(var[k].shape, generator=draws) for k in PARAM_ORDER}
    torch.testing.assert_close(got.means, moved["means"], rtol=0, atol=1e-6)
    torch.testing.assert_close(got.scales, moved["scales"].exp(), rtol=1e-6, atol=0)
    torch.testing.assert_close(got.opacities, torch.sigmoid(moved["opacities"]), rtol=0, atol=1e-6)
    torch.testing.assert_close(got.sh[:, :1], moved["sh0"], rtol=0, atol=1e-6)
    assert torch.equal(got.sh[:, 1:], params["shN"]) and torch.equal(got.quats, params["quats"])


# ------------------------------------------------------------------- deterministic = plain 3DGS
def test_plain_3dgs_split_creates_no_posteriors():
    from uncertsplat.gaussians import ops
    from uncertsplat.gaussians.variational import Prior
    from uncertsplat.train.optim import make_optimizer

    g = torch.Generator().manual_seed(0)
    model = random_model(30, g, sh_degree=1, num_entries=4, carrier_fraction=0.3)
    opt = make_optimizer(model, {k: 1e-3 for k in model.parameters()})
    carriers_before = model.num_carriers
    parents_carry = model.posterior_row[:10] >= 0
    mask = torch.zeros(30, dtype=torch.bool)
    mask[:10] = True
    ops.split(model, opt, mask, g, scales=model.params["scales"].detach().exp(), prior=Prior(), carry=False)
    model.check()
    # children of carriers keep a posterior (2 each), children of plain Gaussians get none
    assert model.num_carriers == carriers_before - int(parents_carry.sum()) + 2 * int(parents_carry.sum())
    assert torch.equal(model.posterior_row[-20:] >= 0, parents_carry.repeat(2))


def test_deterministic_trainer_densifier_never_gives_posteriors():
    from uncertsplat.gaussians.variational import Prior
    from uncertsplat.strategy.densify import Densifier

    cfg = TrainConfig().densify
    assert Densifier(cfg, Prior(), 1.0, 5, torch.device("cpu"), posteriors=False).posteriors is False
    assert Densifier(cfg, Prior(), 1.0, 5, torch.device("cpu")).posteriors is True


def test_one_pass_gives_the_noise_the_fisher_and_the_disagreement():
    """``curvature``: the noise is ``residual_noise_std``'s, the Fisher (scaled by that noise at the end) estimates
    its closed form, and the disagreement is its closed form (linear render)."""
    gen = torch.Generator().manual_seed(3)
    params = _params()
    maps = torch.randn(5, 3, 60, generator=gen)
    images = torch.rand(5, 4, 5, 3, generator=gen)
    c = curvature(params, _Cams(maps), images, _linear_render, names=("means", "scales"),
                  generator=torch.Generator().manual_seed(9), sh_degree=0, probes=64, disagreement=True)
    noise = residual_noise_std(params, _Cams(maps), images, _linear_render, sh_degree=0)
    assert c.noise_std == pytest.approx(noise, rel=1e-6)
    exact = maps.square().sum(-1).sum(0) / noise**2  # [3]: sum over views and pixels of J^2
    for i in range(params["means"].shape[0]):
        assert torch.allclose(c.fisher["means"][i], exact, rtol=0.2), (c.fisher["means"][i], exact)
    s = params["means"].sum(0)
    g = torch.stack([maps[t] @ (s @ maps[t] - images[t].reshape(-1)) / noise**2 for t in range(5)])  # [T,3]
    expected = g.var(0, unbiased=True) * 5
    torch.testing.assert_close(c.disagreement["means"][0], expected, rtol=1e-4, atol=1e-6)
    assert torch.all(c.disagreement["scales"] == 0), "parameters the render ignores: no disagreement"
    calls = []
    fixed = curvature(params, _Cams(maps), images, _linear_render, names=("means",),
                      generator=torch.Generator().manual_seed(9), sh_degree=0, noise_std=0.5,
                      on_view=lambda done, views: calls.append((done, views)))
    assert fixed.noise_std == 0.5 and fixed.disagreement is None
    assert calls == [(1, 5), (2, 5), (3, 5), (4, 5), (5, 5)], "on_view(done, views) as each view is done"
    # two probes per view unless told: the same draws, so the same estimate as probes=2
    two = curvature(params, _Cams(maps), images, _linear_render, names=("means",),
                    generator=torch.Generator().manual_seed(9), sh_degree=0, noise_std=0.5, probes=2)
    assert torch.equal(fixed.fisher["means"], two.fisher["means"])


def test_a_perfect_fit_gets_the_noise_floor_not_zero():
    """Images the render reproduces exactly: a noise of 0 would make the Fisher infinite (1 / s^2), so the noise is
    ``floor`` (1/255 unless given), from ``residual_noise_std`` as from ``curvature``."""
    params = _params()
    maps = torch.randn(2, 3, 60, generator=torch.Generator().manual_seed(4))
    images = torch.stack([(params["means"].sum(0) @ maps[t]).reshape(4, 5, 3) for t in range(2)])
    assert residual_noise_std(params, _Cams(maps), images, _linear_render, sh_degree=0) == 1.0 / 255.0
    assert residual_noise_std(params, _Cams(maps), images, _linear_render, sh_degree=0, floor=0.1) == 0.1
    c = curvature(params, _Cams(maps), images, _linear_render, names=("means",),
                  generator=torch.Generator().manual_seed(0), sh_degree=0, probes=1)
    assert c.noise_std == 1.0 / 255.0 and bool(torch.isfinite(c.fisher["means"]).all())

def test_masked_pixels_count_in_neither_the_noise_nor_the_fisher():
    """``masks``: the noise is the RMS over the pixel channels inside the mask (each pixel's three channels count),
    and a parameter seen only in pixels outside it gets no Fisher (its probes are masked too). Each coordinate of the
    means drives single pixel channels, so the probe estimate is exact: (w z)^2 = w^2."""
    params = _params(n=2)
    maps = torch.zeros(1, 3, 60)
    inside, outside = (0 * 5 + 0) * 3 + 0, (3 * 5 + 4) * 3 + 1  # flat index (row * 5 + col) * 3 + channel
    maps[0, 0, inside] = 2.0  # x: a pixel inside the mask
    maps[0, 1, outside] = 3.0  # y: only a pixel outside it
    maps[0, 2, inside + 1] = 0.5  # z: inside (the pixel's next channel) and outside (the other pixel's)
    maps[0, 2, outside + 1] = 7.0
    mask = torch.ones(1, 4, 5, 1, dtype=torch.bool)
    mask[0, 3, 4] = False
    s = params["means"].sum(0)
    rendered = (s @ maps[0]).reshape(1, 4, 5, 3)
    images = rendered + torch.linspace(-0.2, 0.3, 60).reshape(1, 4, 5, 3)  # residuals of every pixel channel
    images[0, 3, 4] += 5.0  # outside the mask: would dominate the noise
    c = curvature(params, _Cams(maps), images, _linear_render, names=("means",),
                  generator=torch.Generator().manual_seed(0), sh_degree=0, probes=3, masks=mask)
    r = (rendered - images)[0][mask[0, ..., 0]]  # [19,3]: the pixels inside
    noise = float(r.double().square().mean().sqrt())
    assert c.noise_std == pytest.approx(noise, rel=1e-5)
    assert residual_noise_std(params, _Cams(maps), images, _linear_render, sh_degree=0,
                              masks=mask) == pytest.approx(noise, rel=1e-5)
    expected = torch.tensor([4.0, 0.0, 0.25]) / noise**2
    for i in range(2):
        torch.testing.assert_close(c.fisher["means"][i], expected, rtol=1e-4, atol=0)


def test_disagreement_of_a_well_specified_model_is_its_fisher():
    """Images = render + independent pixel noise of the stated std: the views disagree only by the noise, and
    the disagreement's expectation is the Fisher (so the sandwich variance is the Laplace one)."""
    gen = torch.Generator().manual_seed(4)
    params = _params(n=1)
    t, noise = 400, 0.1
    maps = torch.randn(t, 3, 60, generator=gen)
    s = params["means"].sum(0)
    images = torch.stack([(s @ maps[i]).reshape(4, 5, 3) for i in range(t)])
    images = images + noise * torch.randn(images.shape, generator=gen)
    c = curvature(params, _Cams(maps), images, _linear_render, names=("means",), noise_std=noise, generator=gen,
                  sh_degree=0, probes=16, disagreement=True)
    assert torch.allclose(c.disagreement["means"], c.fisher["means"], rtol=0.15), (c.disagreement, c.fisher)
    # a bias the model cannot fit, different in every view, makes them disagree far more than the noise does
    biased = images + 0.3 * torch.randn(t, 1, 1, 1, generator=gen)
    c2 = curvature(params, _Cams(maps), biased, _linear_render, names=("means",), noise_std=noise, generator=gen,
                   sh_degree=0, disagreement=True)
    assert torch.all(c2.disagreement["means"] > 3 * c.fisher["means"])
