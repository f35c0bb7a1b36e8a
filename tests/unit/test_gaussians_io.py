"""Checkpoints (atomic, checksummed, fallback) and PLY files (viewer layout, exact round trip)."""

import numpy as np
import pytest
import torch
from plyfile import PlyData

from tests.fixtures import tiny_scene_path  # noqa: F401
from tests.run_fixtures import tiny_run_path  # noqa: F401
from uncertsplat.errors import UserError
from uncertsplat.gaussians.variational import posterior_mean, random_model
from uncertsplat.io.checkpoints import (
    CorruptCheckpoint,
    list_checkpoints,
    load_checkpoint,
    load_latest,
    save_checkpoint,
)
from uncertsplat.io.ply import read_variational_ply, write_point_cloud_ply, write_variational_ply


def test_checkpoint_round_trip_and_keep(tmp_path):
    for step in (10, 20, 30, 40):
        save_checkpoint(tmp_path, step, {"step": step, "x": torch.arange(step)}, keep=3)
    assert [s for s, _ in list_checkpoints(tmp_path)] == [20, 30, 40]
    path, state = load_latest(tmp_path)
    assert path.name == "step_000040.pt" and state["step"] == 40 and torch.equal(state["x"], torch.arange(40))
    assert not list(tmp_path.joinpath("ckpts").glob(".*tmp"))  # no temp files left behind


def test_checkpoints_past_a_million_steps_are_ordered_by_step(tmp_path):
    """``step_{:06d}`` takes seven digits at a million: by name, step_1000000 sorts before step_999999 (the newest
    would be deleted and the older one resumed from)."""
    for step in (999_998, 999_999, 1_000_000, 1_000_001):
        save_checkpoint(tmp_path, step, {"step": step}, keep=2)
    assert [s for s, _ in list_checkpoints(tmp_path)] == [1_000_000, 1_000_001]
    path, state = load_latest(tmp_path)
    assert path.name == "step_1000001.pt" and state["step"] == 1_000_001


def test_truncated_checkpoint_falls_back(tmp_path, capsys):
    save_checkpoint(tmp_path, 1, {"step": 1}, keep=5)
    p2 = save_checkpoint(tmp_path, 2, {"step": 2, "big": torch.zeros(1000)}, keep=5)
    data = p2.read_bytes()
    p2.write_bytes(data[: len(data) // 2])
    with pytest.raises(CorruptCheckpoint, match="checksum"):
        load_checkpoint(p2)
    path, state = load_latest(tmp_path)
    assert state["step"] == 1
    p2.write_bytes(b"")
    with pytest.raises(CorruptCheckpoint, match="header"):
        load_checkpoint(p2)
    assert load_latest(tmp_path / "nothing") is None


def test_variational_ply_round_trip(tmp_path):
    m = random_model(64, torch.Generator().manual_seed(0), sh_degree=2, num_entries=5, carrier_fraction=0.4,
                     perturb_tables=0.3)
    path = write_variational_ply(tmp_path / "variational.ply", m, meta={"extent": 1.5, "step": 7})
    back, meta = read_variational_ply(path)
    assert meta["extent"] == "1.5" and meta["step"] == "7"
    assert torch.equal(back.posterior_row, m.posterior_row)
    for name, p in m.parameters().items():
        assert torch.equal(back.parameters()[name], p.detach()), name
    # the offset element as the module docstring lays it out (what another tool reads): carrier-major rows in
    # table-row order, each with its Gaussian (owner) and its entry 0..K-1
    o = PlyData.read(str(path))["offset"]
    P = m.num_carriers
    assert len(o.data) == P * 5
    owners = {int(r): g for g, r in enumerate(m.posterior_row.tolist()) if r >= 0}
    assert o["owner"].tolist() == [owners[r] for r in range(P) for _ in range(5)]
    assert o["entry"].tolist() == list(range(5)) * P
    np.testing.assert_array_equal(o["pos_loc_1"].reshape(P, 5), m.tables["pos_loc"][:, :, 1].detach().numpy())


def test_variational_ply_without_carriers(tmp_path):
    m = random_model(10, torch.Generator().manual_seed(1), carrier_fraction=0.0)
    back, _ = read_variational_ply(write_variational_ply(tmp_path / "v.ply", m))
    assert back.num_carriers == 0 and len(back) == 10


def test_point_cloud_ply_standard_layout(tmp_path):
    m = random_model(30, torch.Generator().manual_seed(2), sh_degree=3, carrier_fraction=0.5, perturb_tables=0.2)
    path = write_point_cloud_ply(tmp_path / "point_cloud.ply", m, extent=2.0)
    v = PlyData.read(str(path))["vertex"]
    names = [p.name for p in v.properties]
    expected = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(45)]
                + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
    assert names[: len(expected)] == expected
    assert {"uncertainty_position", "has_posterior"} <= set(names)
    pm = posterior_mean(m, extent=2.0)
    np.testing.assert_allclose(np.stack([v["x"], v["y"], v["z"]], 1), pm.means.detach().numpy(), rtol=1e-6)
    np.testing.assert_allclose(np.exp(v["scale_0"]), pm.scales.detach()[:, 0].numpy(), rtol=1e-5)
    np.testing.assert_allclose(1 / (1 + np.exp(-v["opacity"])), pm.opacities.detach().numpy(), rtol=1e-4)
    # f_rest is channel-major (3DGS): f_rest_0..14 are the 15 red coefficients
    np.testing.assert_allclose(v["f_rest_1"], m.params["shN"].detach()[:, 1, 0].numpy())
    has = np.asarray(v["has_posterior"]) > 0
    assert (np.asarray(v["uncertainty_position"])[has] > 0).all() and (np.asarray(v["uncertainty_position"])[~has] == 0).all()
    # the switch-off chance is prune's gate score, a probability, 0 for a Gaussian without a posterior
    from uncertsplat.uncertainty.scores import posterior_scores

    off = np.asarray(v["uncertainty_switch_off"])
    np.testing.assert_allclose(off, posterior_scores(m, extent=2.0)["gate"].numpy(), rtol=1e-5, atol=1e-7)
    assert ((off >= 0) & (off <= 1)).all() and (off[~has] == 0).all() and off[has].std() > 0


def test_point_cloud_ply_position_uncertainty_is_the_rms_of_the_axes_std(tmp_path):
    """``uncertainty_position``: sqrt(mean over x, y, z of sigma^2), sigma = softplus of the entries' mean raw spread
    x the extent (world units); here every carrier's axes are 1, 2 and 2 x 0.01 in table units."""
    from uncertsplat.gaussians.prior import inverse_softplus

    m = random_model(20, torch.Generator().manual_seed(4), sh_degree=0, num_entries=3, carrier_fraction=0.5)
    sigma = torch.tensor([0.01, 0.02, 0.02], dtype=torch.float64)
    m.tables["pos_spread_raw"].data.copy_(inverse_softplus(sigma).float().expand_as(m.tables["pos_spread_raw"]))
    v = PlyData.read(str(write_point_cloud_ply(tmp_path / "pc.ply", m, extent=2.0)))["vertex"]
    has = np.asarray(v["has_posterior"]) > 0
    assert has.any()
    rms = 2.0 * float(sigma.square().mean().sqrt())  # 0.0346, where the mean std is 0.0333
    np.testing.assert_allclose(np.asarray(v["uncertainty_position"])[has], rms, rtol=1e-5)


@pytest.mark.parametrize("degree", [0, 1, 2])
def test_point_cloud_ply_holds_the_bands_the_model_renders_with(tmp_path, degree):
    """A run shorter than the first SH band test stores degree 3 while rendering with degree 0: its point cloud had
    45 all-zero f_rest columns (a viewer read degree 3; INRIA's load_ply, given the run's degree 0, asserted)."""
    m = random_model(20, torch.Generator().manual_seed(2), sh_degree=3)
    v = PlyData.read(str(write_point_cloud_ply(tmp_path / "p.ply", m, sh_degree=degree)))["vertex"]
    rest = sorted(int(p.name.removeprefix("f_rest_")) for p in v.properties if p.name.startswith("f_rest_"))
    bands = (degree + 1) ** 2 - 1
    assert rest == list(range(3 * bands))
    if bands:  # channel-major over the kept bands: f_rest_{bands} is the first green coefficient
        np.testing.assert_allclose(v[f"f_rest_{bands}"], m.params["shN"].detach()[:, 0, 1].numpy())


def test_a_cut_short_variational_ply_says_how_to_write_it_again(tmp_path):
    """A truncated variational.ply said "cannot read the PLY file (line 39: early end-of-file)" and nothing to do: the
    file is called damaged, with what writes it again (a run with checkpoints: `train --resume` once it is moved
    aside, which writes it again bit for bit; a pruned run: prune; else train again)."""
    import json

    from uncertsplat.console import q

    m = random_model(64, torch.Generator().manual_seed(0), num_entries=5, carrier_fraction=0.4)
    run = tmp_path / "run"
    path = write_variational_ply(run / "variational.ply", m)
    path.write_bytes(path.read_bytes()[:3000])
    hints = []
    for extra in (None, "ckpts", "prune.json"):
        if extra == "ckpts":
            (run / "ckpts").mkdir()
            (run / "ckpts" / "step_000200.pt").write_bytes(b"x")
            (run / "scene.json").write_text(json.dumps({"scene": "/data/my scene"}))
        elif extra == "prune.json":
            (run / "prune.json").write_text("{}")
        with pytest.raises(UserError) as err:
            read_variational_ply(path)
        said = err.value.render()
        assert "cannot read the PLY file" in said and "The file is damaged (cut short" in said, said
        hints.append(said)
    assert "Train the run again (it has no checkpoint to write it from)" in hints[0]
    assert (f"Move it aside (or delete it), then `uncertsplat train {q('/data/my scene')} -o {q(run)} --resume` "
            "writes it again from the run's last checkpoint") in hints[1], hints[1]
    assert "`uncertsplat prune` wrote it: prune the source run again" in hints[2]


def test_reading_a_point_cloud_as_variational_fails_clearly(tmp_path):
    m = random_model(5, torch.Generator().manual_seed(3))
    path = write_point_cloud_ply(tmp_path / "point_cloud.ply", m)
    with pytest.raises(UserError, match="not a variational.ply"):
        read_variational_ply(path)


def test_inconsistent_model_in_a_checkpoint_is_reported(tmp_path):
    """A checkpoint with a good checksum but misaligned rows: CorruptCheckpoint naming the field, no traceback."""
    from uncertsplat.baselines import load_run
    from uncertsplat.config import TrainConfig

    m = random_model(12, torch.Generator().manual_seed(5), num_entries=2, carrier_fraction=0.5)
    state = m.state_dict()
    state["params"]["opacities"] = state["params"]["opacities"][:-1]
    (tmp_path / "config.json").write_text(TrainConfig().model_dump_json())
    save_checkpoint(tmp_path, 1, {"model": state, "step": 1, "extent": 1.0})
    with pytest.raises(CorruptCheckpoint, match=r"inconsistent .*params\['opacities'\] has shape \(11,\)"):
        load_run(tmp_path)


def test_a_model_with_nan_parameters_is_refused_by_every_command(tiny_run_path, tmp_path):  # noqa: F811
    """5 NaN positions of 9,428 Gaussians (a helper's hand-edited PLY, its checksum written again) gave finite
    metrics over maps whose std was NaN in 98 % of the pixels, and `prune` a traceback: the load refuses it, naming
    the file and what is wrong. An infinite opacity logit or scale is no NaN and loads."""
    import shutil

    from uncertsplat.baselines.runs import load_run, refuse_non_finite

    run = tmp_path / "run"
    shutil.copytree(tiny_run_path, run)
    model, meta = read_variational_ply(run / "variational.ply")
    with torch.no_grad():
        model.params["means"][[1, 4], 0] = float("nan")
    write_variational_ply(run / "variational.ply", model, meta=meta)
    with pytest.raises(UserError, match=r"not numbers \(means of 2 Gaussians;") as err:
        load_run(run)
    assert err.value.path == run / "variational.ply" and "Train it again" in err.value.hint
    m = random_model(10, torch.Generator().manual_seed(0))
    with torch.no_grad():
        m.params["opacities"][0] = float("inf")
        m.params["scales"][1] = float("-inf")
    refuse_non_finite(m, tmp_path / "m.ply")  # (no NaN, no infinite position)
    with torch.no_grad():
        m.params["means"][2, 1] = float("-inf")
        next(iter(m.tables.values()))[0, 0, 0] = float("nan")
    with pytest.raises(UserError, match=r"means of 1 Gaussian, .* of 1 posterior carrier;"):
        refuse_non_finite(m, tmp_path / "m.ply")
