"""PARAM_SPECS, initialisation from points, nearest-neighbour scales, memory accounting."""

import math
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch

from uncertsplat.gaussians.params import (
    PARAM_SPECS,
    GaussianModel,
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


def test_nearest_neighbor_rows_shrink_for_a_large_cloud(monkeypatch):
    """The distance block is bounded (NN_BLOCK_ELEMENTS): a large cloud is taken in fewer rows at a time (a 48k
    cloud held 1.8 GB in rows of 4096), with the same distances; a small cloud keeps its rows."""
    from uncertsplat.gaussians import neighbors as params

    pts = torch.rand(300, 3, generator=torch.Generator().manual_seed(1))
    ref = nearest_neighbor_distance(pts)
    rows = []
    cdist = torch.cdist
    monkeypatch.setattr(torch, "cdist", lambda a, b: rows.append(a.shape[0]) or cdist(a, b))
    monkeypatch.setattr(params, "NN_BLOCK_ELEMENTS", 300 * 100)  # 100 rows of 300
    torch.testing.assert_close(nearest_neighbor_distance(pts), ref, rtol=1e-5, atol=1e-6)
    assert max(rows) == 100
    rows.clear()
    monkeypatch.setattr(params, "NN_BLOCK_ELEMENTS", 2**26)
    nearest_neighbor_distance(pts)
    assert rows == [300]


def test_nearest_neighbor_small_inputs():
    assert nearest_neighbor_distance(torch.zeros(0, 3)).shape == (0,)
    assert nearest_neighbor_distance(torch.zeros(1, 3)).tolist() == [0.0]
    two = nearest_neighbor_distance(torch.tensor([[0.0, 0, 0], [3.0, 4, 0]]))
    torch.testing.assert_close(two, torch.tensor([5.0, 5.0]))


def _exact_nn(pts: torch.Tensor, k: int = 3) -> torch.Tensor:
    """float64 differences, no matrix-product expansion: the reference the grid must equal."""
    p = pts.double()
    d2 = torch.cdist(p, p, compute_mode="donot_use_mm_for_euclid_dist").square()
    return d2.topk(k + 1, largest=False).values[:, 1:].mean(1).sqrt()


def _clouds() -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(3)
    uv = torch.rand(1500, 2, generator=g) * 6
    surface = torch.stack([uv[:, 0], uv[:, 1], torch.sin(uv[:, 0]) * torch.cos(uv[:, 1])], 1)
    clump = surface.clone()
    clump[:5] *= 1e4  # far points
    clump[5:300] = clump[5:300] * 1e-4 + 2.0  # a clump 1e-4 the size of the rest
    dupes = surface.clone()
    dupes[10:210] = dupes[10]  # 200 copies of one point
    line = torch.zeros(1500, 3)
    line[:, 0] = torch.rand(1500, generator=g)
    shells = torch.randn(1500, 3, generator=g) * torch.logspace(-3, 3, 1500)[:, None]
    return {"cube": torch.rand(1500, 3, generator=g), "clump and far points": clump, "duplicates": dupes,
            "line": line, "far from the origin": surface + 1e5, "shells from 1e-3 to 1e3": shells,
            "one place": torch.full((1500, 3), 7.0)}


@pytest.mark.parametrize("name", list(_clouds()))
def test_nearest_neighbor_grid_is_exact(monkeypatch, name):
    """The grid path (clouds above GRID_MIN_POINTS) equals the exact k-NN on clouds that stress each of its
    branches: small budgets force query chunks and block splits, descents to finer grids for clumps (and the stop for
    duplicates, which no finer grid separates) and climbs for sparse and far points."""
    from uncertsplat.gaussians import neighbors

    pts = _clouds()[name]
    ref = _exact_nn(pts).float()
    monkeypatch.setattr(neighbors, "GRID_MIN_POINTS", 0)
    monkeypatch.setattr(neighbors, "NN_BLOCK_ELEMENTS", 1500 * 5)  # brute force only for the last 5 points
    monkeypatch.setattr(neighbors, "GRID_PAIR_BUDGET", 4096)
    monkeypatch.setattr(neighbors, "GRID_MAX_CANDIDATES", 32)
    monkeypatch.setattr(neighbors, "_QUERY_ROWS", 400)
    for k in (1, 3):
        ref = _exact_nn(pts, k).float()
        got = nearest_neighbor_distance(pts, k=k)
        torch.testing.assert_close(got, ref, rtol=2e-6, atol=1e-30 if name != "one place" else 0.0)


def test_nearest_neighbor_grid_fixes_the_brute_force_in_a_clump():
    """A cloud past GRID_MIN_POINTS takes the grid, whose differences keep a clump's distances; cdist's
    expanded square gives them as noise (relative error about 1 here), so the brute force is no reference."""
    from uncertsplat.gaussians import neighbors

    g = torch.Generator().manual_seed(4)
    n = neighbors.GRID_MIN_POINTS + 500
    pts = torch.rand(n, 3, generator=g)
    pts[:400] = pts[:400] * 1e-5 + 0.5
    got = nearest_neighbor_distance(pts)
    ref = _exact_nn(pts[:400].double().cpu().clone()).float()  # the clump's own neighbours are in the clump
    torch.testing.assert_close(got[:400], ref, rtol=1e-5, atol=0.0)
    brute = neighbors._brute_mean_sq(pts, torch.arange(400), 3).clamp_min(0).sqrt()
    assert ((brute - ref).abs() / ref).max() > 0.1  # what the grid replaces


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
    # Adam's two moments of every parameter, and of the tables unless the informed posterior sets them itself
    table_bytes = half.num_carriers * 560
    assert m1["optimizer"] == pytest.approx(2 * (59 * 4 * 100 + table_bytes) / 100)
    informed = memory_per_gaussian(half, table_moments=False)
    assert informed["optimizer"] == pytest.approx(2 * 59 * 4)
    assert informed["total"] == pytest.approx(m1["total"] - 2 * table_bytes / 100)


# ------------------------------------------------------------------------ GaussianModel.check: ValueError
def _model(**kw):
    return random_model(12, torch.Generator().manual_seed(3), num_entries=4, carrier_fraction=0.5, **kw)


def _broken(what: str):
    """A model with one defect a user can hit (a hand-edited checkpoint, a foreign PLY, a bad ``ops`` call)."""
    m = _model()
    carriers = (m.posterior_row >= 0).nonzero().flatten()
    if what == "param_shape":
        m.params["scales"] = torch.nn.Parameter(m.params["scales"][:-1])
    elif what == "sh_degree":
        m.sh_degree = 2
    elif what == "missing_param":
        del m.params["quats"]
    elif what == "row_dtype":
        m.posterior_row = m.posterior_row.int()
    elif what == "row_shape":
        m.posterior_row = m.posterior_row[:-1]
    elif what == "missing_table":
        del m.tables["gate_loc"]
    elif what == "table_rows":
        m.tables["pos_loc"] = torch.nn.Parameter(m.tables["pos_loc"][:-1])
    elif what == "table_entries":
        m.num_entries = 5
    elif what == "table_width":
        m.tables["gate_loc"] = torch.nn.Parameter(m.tables["gate_loc"].repeat(1, 1, 2))
    elif what == "carrier_count":
        m.posterior_row[(m.posterior_row < 0).nonzero()[0]] = 0  # one more carrier than table rows
    elif what == "shared_row":
        m.posterior_row[carriers[0]] = m.posterior_row[carriers[1]]
    return m


@pytest.mark.parametrize("what,words", [
    ("param_shape", r"params\['scales'\] has shape \(11, 3\), expected \(12, 3\)"),
    ("sh_degree", r"params\['shN'\] has shape \(12, 3, 3\), expected \(12, 8, 3\)"),
    ("missing_param", r"params lacks quats"),
    ("row_dtype", r"posterior_row must be a torch.long tensor of shape \(12,\), not torch.int32"),
    ("row_shape", r"posterior_row must be .* not torch.int64 of shape \(11,\)"),
    ("missing_table", r"tables lacks gate_loc"),
    ("table_rows", r"tables\['pos_loc'\] has shape"),
    ("table_entries", r"num_entries K = 5"),
    ("table_width", r"tables\['gate_loc'\] has shape \(\d+, 4, 2\), expected \(\d+, 4, 1\)"),
    ("carrier_count", r"marks \d+ carriers .* but the offset tables have \d+ rows"),
    ("shared_row", r"not a permutation"),
])
def test_check_raises_value_error_naming_the_field(what, words):
    _model().check()  # the intact model passes
    with pytest.raises(ValueError, match=words):
        _broken(what).check()


def test_from_state_dict_refuses_an_inconsistent_state():
    state = _model().state_dict()
    state["posterior_row"][:] = -1  # carriers forgotten, tables kept
    with pytest.raises(ValueError, match="posterior_row marks 0 carriers"):
        GaussianModel.from_state_dict(state)


def test_check_still_raises_under_python_optimize(tmp_path):
    """``python -O`` strips ``assert``: the checks are plain ``if`` tests, so they survive it."""
    script = tmp_path / "bad_model.py"
    script.write_text(textwrap.dedent("""
        import torch
        from uncertsplat.gaussians.variational import random_model

        assert False, "this line proves that -O is in effect"
        m = random_model(8, torch.Generator().manual_seed(0), carrier_fraction=1.0)
        m.posterior_row[1] = m.posterior_row[0]
        try:
            m.check()
        except ValueError as err:
            print("ValueError:", err)
        else:
            print("no error")
    """))
    root = Path(__file__).resolve().parents[2]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(root), os.environ.get("PYTHONPATH")])),
           "OMP_NUM_THREADS": "1"}
    out = subprocess.run([sys.executable, "-O", str(script)], capture_output=True, text=True, timeout=120, env=env)
    assert out.returncode == 0, out.stderr
    assert "ValueError: GaussianModel.posterior_row" in out.stdout and "not a permutation" in out.stdout, out.stdout
