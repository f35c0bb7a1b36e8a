"""PARAM_SPECS, initialisation from points, nearest-neighbour scales, memory accounting."""

import math

import torch

from uncertsplat.gaussians.params import (
    PARAM_SPECS,
    init_from_points,
    memory_per_gaussian,
    nearest_neighbor_distance,
    trailing_shape,
)
from uncertsplat.gaussians.variational import random_model


def test_nearest_neighbor_chunked_matches_brute_force():
    g = torch.Generator().manual_seed(0)
    pts = torch.rand(300, 3, generator=g)
    d = torch.cdist(pts, pts).square()
    d.fill_diagonal_(float("inf"))
    ref = d.topk(3, largest=False).values.mean(1).sqrt()
    for chunk in (7, 64, 4096):
        torch.testing.assert_close(nearest_neighbor_distance(pts, chunk=chunk), ref, rtol=1e-5, atol=1e-6)


def test_nearest_neighbor_small_inputs():
    assert nearest_neighbor_distance(torch.zeros(0, 3)).shape == (0,)
    assert nearest_neighbor_distance(torch.zeros(1, 3)).tolist() == [0.0]
    two = nearest_neighbor_distance(torch.tensor([[0.0, 0, 0], [3.0, 4, 0]]))
    torch.testing.assert_close(two, torch.tensor([5.0, 5.0]))


def test_init_from_points_layout():
    g = torch.Generator().manual_seed(1)
    pts = torch.rand(50, 3, generator=g)
    rgb = torch.rand(50, 3, generator=g)
    m = init_from_points(pts, rgb, sh_degree=2, num_entries=7, init_opacity=0.1)
    m.check()
    assert len(m) == 50 and m.num_carriers == 0 and m.num_entries == 7
    for spec in PARAM_SPECS:
        assert m.params[spec.name].shape == (50, *trailing_shape(spec, 2))
    assert torch.allclose(torch.sigmoid(m.params["opacities"]), torch.tensor(0.1))
    # isotropic scale = mean distance to the 3 nearest neighbours
    torch.testing.assert_close(m.params["scales"].exp()[:, 0], nearest_neighbor_distance(pts))
    # SH DC encodes the colour: 0.5 + C0 * dc
    torch.testing.assert_close(0.5 + 0.28209479177387814 * m.params["sh0"][:, 0], rgb, rtol=1e-5, atol=1e-6)
    assert (m.params["shN"] == 0).all() and m.params["shN"].shape == (50, 8, 3)


def test_duplicate_points_get_finite_scales():
    pts = torch.zeros(10, 3)
    m = init_from_points(pts, torch.rand(10, 3), sh_degree=0, num_entries=10, extent=2.0)
    assert torch.isfinite(m.params["scales"]).all()


def test_memory_per_gaussian_counts_only_carriers():
    g = torch.Generator().manual_seed(2)
    none = random_model(100, g, carrier_fraction=0.0, sh_degree=3)
    half = random_model(100, g, carrier_fraction=0.5, sh_degree=3)
    m0, m1 = memory_per_gaussian(none), memory_per_gaussian(half)
    # 3 + 3 + 4 + 1 + 3 + 45 floats of parameters
    assert m0["params"] == 59 * 4 and m0["tables"] == 0
    assert m1["table_bytes_per_carrier"] == 10 * 14 * 4
    assert math.isclose(m1["tables"], half.num_carriers * 560 / 100)
    assert m1["total"] > m0["total"]
    assert memory_per_gaussian(none, optimizer_moments=False)["optimizer"] == 0
