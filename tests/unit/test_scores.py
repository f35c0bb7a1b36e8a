"""Per-Gaussian uncertainty scores: hand-checked values, the blending-weight identity, planted floaters."""

import math

import pytest
import torch

from tests.reference.naive_render import look_at_cameras
from uncertsplat.gaussians.params import GaussianModel
from uncertsplat.gaussians.variational import Prior, inverse_softplus, prior_rows
from uncertsplat.prune import keep_ratio_mask
from uncertsplat.render import render
from uncertsplat.render.sh import rgb_to_sh
from uncertsplat.uncertainty.scores import (
    DEFAULT_SCORE,
    SCORE_NAMES,
    blending_weights,
    carrier_mask,
    centre_gap,
    compute_scores,
    free_space_depth,
    posterior_scores,
    resolve_score_name,
    spread_views,
)


def _set_rows(tables, rows, *, pos_std, width, gate_loc, gate_std):
    with torch.no_grad():
        tables["pos_spread_raw"][rows] = inverse_softplus(pos_std)
        tables["pos_loc"][rows] = 0.0
        tables["scale_width_raw"][rows] = inverse_softplus(width)
        tables["scale_left"][rows] = 1.0 - width
        tables["gate_spread_raw"][rows] = inverse_softplus(gate_std)
        tables["gate_loc"][rows] = gate_loc


def planted_scene(n_surface=150, n_floaters=15, seed=0, device="cpu", non_carriers=10):
    """Opaque surface Gaussians on a sphere with tight posteriors, floaters in free space in front of a few
    cameras with wide posteriors, and a few non-carriers on the surface. Returns (model, is_floater, cams)."""
    g = torch.Generator().manual_seed(seed)
    cams = look_at_cameras(8, 64, 48, 60.0, radius=4.0)
    d = torch.randn(n_surface, 3, generator=g)
    surface = 0.8 * d / d.norm(dim=1, keepdim=True)
    eyes = cams.centers
    # floaters: between cameras 0-1 and the object, in free space (1.5 to 2.8 from the centre)
    pick = torch.randint(0, 2, (n_floaters,), generator=g)
    t = 0.4 + 0.3 * torch.rand(n_floaters, generator=g)
    floaters = eyes[pick] * t[:, None] + 0.15 * torch.randn(n_floaters, 3, generator=g)
    means = torch.cat([surface, floaters])
    n = means.shape[0]
    scales = torch.cat([torch.full((n_surface, 3), math.log(0.12)), torch.full((n_floaters, 3), math.log(0.05))])
    quats = torch.zeros(n, 4)
    quats[:, 0] = 1
    opac = torch.cat([torch.full((n_surface,), 4.0), torch.full((n_floaters,), 0.5)])
    colors = torch.rand(n, 3, generator=g)
    params = {"means": means, "scales": scales, "quats": quats, "opacities": opac,
              "sh0": rgb_to_sh(colors)[:, None, :], "shN": torch.zeros(n, 3, 3)}
    carriers = torch.ones(n, dtype=torch.bool)
    carriers[:non_carriers] = False
    P = int(carriers.sum())
    tables = prior_rows(P, 10, Prior())
    row = torch.full((n,), -1, dtype=torch.long)
    row[carriers] = torch.randperm(P, generator=g)
    is_floater = torch.zeros(n, dtype=torch.bool)
    is_floater[n_surface:] = True
    surf_rows = row[carriers & ~is_floater]
    flo_rows = row[is_floater]
    _set_rows(tables, surf_rows, pos_std=0.003, width=0.02, gate_loc=4.0, gate_std=0.3)
    _set_rows(tables, flo_rows, pos_std=0.04, width=0.3, gate_loc=0.3, gate_std=2.0)
    model = GaussianModel({k: v.to(device) for k, v in params.items()}, {k: v.to(device) for k, v in tables.items()},
                          row.to(device), 1, 10)
    model.check()
    return model, is_floater.to(device), cams.to(device)


def test_posterior_scores_match_hand_values(device):
    model, is_floater, _ = planted_scene(device=device)
    s = posterior_scores(model, variant="ours", extent=2.0)
    carriers = carrier_mask(model)
    i = int(is_floater.nonzero()[0])
    # floater: sigma 0.04 x extent 2 = 0.08 world units; size = max posterior-mean scale = 0.05 x (0.7 + 0.15)
    torch.testing.assert_close(s["position"][i].cpu(), torch.tensor(0.08 / (0.05 * 0.85)), rtol=1e-4, atol=0)
    torch.testing.assert_close(s["scale"][i].cpu(), torch.tensor(0.3), rtol=1e-4, atol=0)
    phi = 0.5 * math.erfc(0.3 / 2.0 / math.sqrt(2))  # P(nu + tau eta < 0) = Phi(-nu/tau)
    torch.testing.assert_close(s["gate"][i].cpu(), torch.tensor(phi), rtol=1e-4, atol=0)
    for k in ("position", "scale", "gate"):
        assert bool((s[k][~carriers] == 0).all())  # non-carriers: lowest uncertainty
        assert bool((s[k][carriers] > 0).all())
    assert bool(((s["gate"] >= 0) & (s["gate"] <= 1)).all())


def test_position_score_divides_by_the_largest_axis(device):
    """The ``position`` score is the spread over the Gaussian's largest posterior-mean axis: a flat floater (0.05 x
    0.01 x 0.01) scores as the isotropic 0.05 one of test_posterior_scores_match_hand_values (its smallest axis
    would score it 5 x higher; isotropic Gaussians could not tell)."""
    model, is_floater, _ = planted_scene(device=device)
    i = int(is_floater.nonzero()[0])
    with torch.no_grad():
        model.params["scales"][i] = torch.tensor([0.05, 0.01, 0.01], device=device).log()
    s = posterior_scores(model, variant="ours", extent=2.0)
    torch.testing.assert_close(s["position"][i].cpu(), torch.tensor(0.08 / (0.05 * 0.85)), rtol=1e-4, atol=0)


def test_position_score_is_the_rms_spread_over_the_axes(device):
    """Per-axis spreads 0.03, 0.04 and 0.12 (x extent 2): the RMS over the axes, sqrt(mean of their squares) (0.079 of
    0.05 x 0.85 world units), not their mean (0.063)."""
    model, is_floater, _ = planted_scene(device=device)
    i = int(is_floater.nonzero()[0])
    row = int(model.posterior_row[i])
    with torch.no_grad():
        model.tables["pos_spread_raw"][row] = inverse_softplus(torch.tensor([0.03, 0.04, 0.12], device=device))
    s = posterior_scores(model, variant="ours", extent=2.0)
    rms = 2.0 * math.sqrt((0.03**2 + 0.04**2 + 0.12**2) / 3)
    torch.testing.assert_close(s["position"][i].cpu(), torch.tensor(rms / (0.05 * 0.85)), rtol=1e-4, atol=0)


def test_predictive_counts_a_move_of_more_than_its_size_as_one_size(device):
    """``predictive`` weighs the contribution by min(1, position): positions of 1 and of 100 give the same score (the
    same posterior samples), 0.5 a smaller one where a Gaussian contributes."""
    from uncertsplat.gaussians.variational import sample
    from uncertsplat.uncertainty.scores import predictive_score

    model, _, cams = planted_scene(device=device)
    cams = cams[[0, 1]]

    def score(position):
        return predictive_score(model, cams, torch.Generator(device=device).manual_seed(0), render_fn=render,
                                num_samples=2, position=torch.full((len(model),), position, device=device))

    one, far, half = score(1.0), score(100.0), score(0.5)
    assert torch.equal(one["predictive"], far["predictive"])
    seen = carrier_mask(model) & (one["contribution"] > 1e-3)
    assert bool(seen.any()) and bool((half["predictive"][seen] < one["predictive"][seen]).all())
    # position 0: the std of the weights over the samples (the unbiased variance of the two), the same samples drawn
    gen = torch.Generator(device=device).manual_seed(0)
    w = torch.stack([blending_weights(sample(model, gen, subset_size=2, variant="ours", extent=1.0, temperature=0.2,
                                             sh_degree=0), cams, render_fn=render) for _ in range(2)])
    got = score(0.0)["predictive"][seen]
    torch.testing.assert_close(got.square(), w.var(0, unbiased=True)[seen], rtol=1e-5, atol=1e-12)
    assert float(got.max()) > 0.0

def test_blending_weights_sum_to_the_rendered_alpha(device):
    model, _, cams = planted_scene(device=device)
    from uncertsplat.gaussians.variational import posterior_mean

    s = posterior_mean(model)
    w = blending_weights(s, cams, render_fn=render)  # [N]
    with torch.no_grad():
        alpha = render(s, cams).alpha  # [C,H,W,1]
    # sum_i T_i alpha_i over the Gaussians is the accumulated alpha of each pixel
    expected = alpha.sum() / (cams.width * cams.height)
    torch.testing.assert_close(w.sum(), expected, rtol=1e-4, atol=1e-6)
    assert bool((w >= -1e-7).all())
    # a Gaussian alone in a view: its weight is that view's alpha
    one = GaussianModel({k: v.detach()[:1].clone() for k, v in model.params.items()},
                        {k: v.detach()[:0].clone() for k, v in model.tables.items()},
                        torch.full((1,), -1, dtype=torch.long, device=device), 1, 10)
    s1 = posterior_mean(one)
    with torch.no_grad():
        a1 = render(s1, cams[[0]]).alpha.sum() / (cams.width * cams.height)
    torch.testing.assert_close(blending_weights(s1, cams[[0]], render_fn=render)[0], a1, rtol=1e-4, atol=1e-7)


def test_blending_weights_count_only_the_pixels_a_mask_lets_count(device):
    """With masks the weights sum to the rendered alpha inside them: a Gaussian seen only where no pixel counts (a
    masked-out sky) weighs nothing, so the growth test picks its weakest half among the Gaussians the counted pixels
    see (its cost is taken inside the masks too: those others cost nothing either way)."""
    model, _, cams = planted_scene(device=device)
    from uncertsplat.gaussians.variational import posterior_mean

    s = posterior_mean(model)
    with torch.no_grad():
        alpha = render(s, cams).alpha  # [C,H,W,1]
    masks = torch.zeros_like(alpha, dtype=torch.bool)
    for c in range(len(cams)):  # a band of its own in each view
        masks[c, :, c * cams.width // (2 * len(cams)): cams.width // 2 + c * cams.width // (2 * len(cams))] = True
    w = blending_weights(s, cams, render_fn=render, masks=masks)
    torch.testing.assert_close(w.sum(), (alpha * masks).sum() / (cams.width * cams.height), rtol=1e-4, atol=1e-6)
    assert float(w.sum()) < float(blending_weights(s, cams, render_fn=render).sum())
    none = blending_weights(s, cams, render_fn=render, masks=torch.zeros_like(masks))
    assert bool((none == 0).all())
    every = blending_weights(s, cams, render_fn=render, masks=torch.ones_like(masks))
    torch.testing.assert_close(every, blending_weights(s, cams, render_fn=render))


@pytest.mark.parametrize("name", SCORE_NAMES)
def test_planted_floaters_rank_above_the_surface(device, name):
    model, is_floater, cams = planted_scene(device=device)
    scores = compute_scores(model, cams, torch.Generator(device=device).manual_seed(0), render_fn=render,
                            names=(name,), num_samples=6)
    score = scores[name]
    n_f = int(is_floater.sum())
    top = torch.topk(score, n_f).indices
    recall = float(is_floater[top].float().mean())
    assert recall >= 0.8, f"{name}: only {recall:.2f} of the top-{n_f} are planted floaters"
    # pruning to the surface count removes the floaters and never a non-carrier
    keep = keep_ratio_mask(score, carrier_mask(model), 1.0 - n_f / len(model))
    assert float((~keep[is_floater]).float().mean()) >= 0.8
    assert bool(keep[~carrier_mask(model)].all())


def test_predictive_is_zero_for_unseen_and_non_carriers(device):
    model, _, cams = planted_scene(device=device)
    with torch.no_grad():  # move Gaussian 200 (a floater, a carrier) far behind every camera
        model.params["means"][-1] = torch.tensor([0.0, 50.0, 0.0], device=device)
    s = compute_scores(model, cams, torch.Generator(device=device).manual_seed(0), render_fn=render,
                       names=("predictive",), num_samples=3)
    assert float(s["predictive"][-1]) == 0.0
    assert bool((s["predictive"][~carrier_mask(model)] == 0).all())
    assert float(s["contribution"][~carrier_mask(model)].sum()) > 0  # non-carriers are seen (on the surface)
    assert bool((s["predictive"][carrier_mask(model)] >= 0).all())


def test_names_and_helpers():
    assert resolve_score_name("auto") == DEFAULT_SCORE in SCORE_NAMES
    with pytest.raises(ValueError, match="unknown score"):
        resolve_score_name("entropy")
    assert spread_views(range(4), 8) == [0, 1, 2, 3]
    assert spread_views(range(10), 3) == [0, 3, 6]
    assert spread_views(range(10), 4) == [0, 2, 5, 7]  # a step of 2.5, not 2
    model, _, _ = planted_scene()
    with pytest.raises(ValueError, match="predictive"):
        compute_scores(model, None, None, names=("predictive",))

    with pytest.raises(ValueError, match="free-space"):
        compute_scores(model, None, None, names=("free-space",))


class TestFreeSpace:
    def test_centre_gap_hand_case(self):
        """One camera at the origin looking down +z (K = identity-like, 4x4 image): a centre at z = 2 over a surface
        at z = 5 is 3 in front; a centre outside the image or behind the camera counts in no view."""
        from uncertsplat.types import Cameras

        K = torch.tensor([[2.0, 0, 2.0], [0, 2.0, 2.0], [0, 0, 1.0]])
        cams = Cameras(torch.eye(4)[None].repeat(2, 1, 1), K[None].repeat(2, 1, 1), 4, 4, ("a", "b"))
        depth = [torch.full((4, 4), 5.0), torch.full((4, 4), 2.5)]
        means = torch.tensor([[0.0, 0.0, 2.0], [50.0, 0.0, 2.0], [0.0, 0.0, -1.0]])
        gap, views = centre_gap(means, cams, lambda c: depth[c])
        assert views.tolist() == [2, 0, 0]
        # the image spans [0, 4) in u and v: a centre at u = 0 or v = 0 is inside, at u = 4 or v = 4 outside
        edges = torch.tensor([[-2.0, 0.0, 2.0], [0.0, -2.0, 2.0], [2.0, 0.0, 2.0], [0.0, 2.0, 2.0]])
        assert centre_gap(edges, cams[[0]], lambda c: depth[c])[1].tolist() == [1, 1, 0, 0]
        assert float(gap[0]) == pytest.approx(0.5)  # the smaller gap over the two views
        assert math.isinf(float(gap[1])) and math.isinf(float(gap[2]))
        # no surface through the pixel (0 or non-finite depth): free space along the whole ray
        gap, views = centre_gap(means[:1], cams[[0]], lambda c: torch.zeros(4, 4))
        assert math.isinf(float(gap[0])) and int(views[0]) == 1

    def test_floaters_score_above_one_and_the_rest_by_gate(self, device):
        model, is_floater, cams = planted_scene(device=device)
        s = compute_scores(model, cams, None, render_fn=render, names=("free-space", "gate"))
        carriers = carrier_mask(model)
        free = s["free-space"]
        flagged = free > 1.0
        # the planted floaters sit in free space in every view that contains them; the surface never does
        assert float(flagged[is_floater].float().mean()) >= 0.8
        assert not bool(flagged[~is_floater].any())
        rest = carriers & ~flagged
        torch.testing.assert_close(free[rest], s["gate"][rest])
        assert bool((free[~carriers] == 0).all())

    def test_margin_and_hidden_gaussians(self, device):
        """A Gaussian hidden behind the surface (inside the sphere) is never in free space; a larger margin flags
        fewer floaters; every flagged Gaussian's depth d exceeds the margin."""
        model, is_floater, cams = planted_scene(device=device)
        with torch.no_grad():
            model.params["means"][20] = torch.zeros(3, device=device)  # the sphere's centre: behind every surface
        from uncertsplat.gaussians.variational import posterior_mean

        d, views = free_space_depth(posterior_mean(model), cams, render_fn=render)
        assert float(d[20]) < 0 and int(views[20]) == len(cams)
        n = [int((compute_scores(model, cams, None, render_fn=render, names=("free-space",),
                                 free_space_margin=m)["free-space"] > 1).sum()) for m in (1.0, 5.0, 1e9)]
        assert n[0] >= n[1] and n[2] == 0 and n[0] > 0

    def test_a_gaussian_no_view_sees_scores_its_gate(self, device):
        """A carrier outside every view has no surface to be in front of: its ``free-space`` score is its ``gate``
        score, not the +inf depth's 1e6 + 1 (which pruned it first)."""
        model, is_floater, cams = planted_scene(device=device)
        i = int(is_floater.nonzero()[0])
        with torch.no_grad():
            model.params["means"][i] = torch.tensor([0.0, 100.0, 0.0], device=device)  # far below every view
        from uncertsplat.gaussians.variational import posterior_mean

        _, views = free_space_depth(posterior_mean(model), cams, render_fn=render)
        assert int(views[i]) == 0
        s = compute_scores(model, cams, None, render_fn=render, names=("free-space", "gate"))
        assert 0 < float(s["free-space"][i]) == float(s["gate"][i]) < 1
