"""Keep masks: aligned rows after pruning, non-carriers never removed, exact counts, reproducible randomness."""

import pytest
import torch

from tests.reference.naive_render import look_at_cameras
from uncertsplat.gaussians.variational import posterior_mean, random_model
from uncertsplat.prune import (
    apply_keep,
    keep_ratio_mask,
    keep_top,
    kept_indices,
    mask_from_indices,
    num_to_remove,
    random_mask,
    threshold_mask,
)
from uncertsplat.render import render
from uncertsplat.uncertainty.scores import carrier_mask, posterior_scores


def tagged_model(n=60, seed=0, device="cpu"):
    g = torch.Generator().manual_seed(seed)
    model = random_model(n, g, carrier_fraction=0.6, perturb_tables=0.3, device=torch.device(device))
    with torch.no_grad():  # tag rows: Gaussian i has means[:,0] = i, its table rows pos_loc[..., 0] = i
        model.params["means"][:, 0] = torch.arange(n, dtype=torch.float32, device=model.device)
        idx = model.carrier_index()
        model.tables["pos_loc"][:, :, 0] = idx[:, None].float()
    return model


def test_apply_keep_keeps_every_tensor_aligned(device):
    model = tagged_model(device=device)
    carriers = carrier_mask(model)
    score = torch.rand(len(model), generator=torch.Generator().manual_seed(1)).to(device)
    keep = keep_ratio_mask(score, carriers, 0.7)
    pruned = apply_keep(model, keep)
    pruned.check()
    kept = kept_indices(keep)
    assert len(pruned) == kept.numel()
    for name, t in model.params.items():  # every per-Gaussian row is the original row at its kept index
        torch.testing.assert_close(pruned.params[name].detach(), t.detach()[kept], rtol=0, atol=0)
    # table rows follow their owner (the tag written into pos_loc) and carry the owner's whole row
    idx = pruned.carrier_index()
    torch.testing.assert_close(pruned.tables["pos_loc"].detach()[:, 0, 0], pruned.params["means"].detach()[idx, 0])
    orig_rows = model.posterior_row[kept]
    assert torch.equal(pruned.posterior_row >= 0, orig_rows >= 0)
    for name, t in model.tables.items():
        orig = t.detach()[orig_rows[orig_rows >= 0]]  # [P',K,D] in kept-Gaussian order
        new = pruned.tables[name].detach()[pruned.posterior_row[pruned.posterior_row >= 0]]
        torch.testing.assert_close(new, orig, rtol=0, atol=0)
    # the original is untouched
    assert len(model) == 60 and model.params["means"].shape[0] == 60


def test_keeping_everything_changes_nothing(device):
    model = tagged_model(device=device)
    carriers = carrier_mask(model)
    score = posterior_scores(model)["position"]
    keep = keep_ratio_mask(score, carriers, 1.0)
    assert bool(keep.all())
    pruned = apply_keep(model, keep)
    cams = look_at_cameras(2, 48, 36, 40.0, radius=80.0).to(device)  # the tagged means span x in [0, 60)
    with torch.no_grad():
        a = render(posterior_mean(model), cams)
        b = render(posterior_mean(pruned), cams)
    assert float(a.alpha.sum()) > 0  # the view sees something
    assert torch.equal(a.rgb, b.rgb) and torch.equal(a.alpha, b.alpha)
    assert torch.equal(threshold_mask(score, carriers, float("inf")), keep)


def test_score_never_removes_non_carriers():
    model = tagged_model()
    carriers = carrier_mask(model)
    score = torch.full((len(model),), 5.0)
    score[~carriers] = 100.0  # even when non-carriers would score highest
    keep = keep_ratio_mask(score, carriers, 0.1)
    assert bool(keep[~carriers].all())
    assert int((~keep).sum()) == int(carriers.sum())  # capped at the number of carriers
    assert bool(threshold_mask(score, carriers, 1.0)[~carriers].all())


def test_keep_top_removes_highest_with_stable_ties():
    score = torch.tensor([0.1, 0.9, 0.5, 0.9, 0.2, float("nan")])
    cand = torch.tensor([True, True, True, True, True, True])
    keep = keep_top(score, cand, 3)
    # NaN counts as most uncertain, then the two 0.9 (lower index first)
    assert keep.tolist() == [True, False, True, False, True, False]
    assert keep_top(score, cand, 2).tolist() == [True, False, True, True, True, False]
    assert bool(keep_top(score, cand, 0).all())


def test_threshold_mask():
    score = torch.tensor([0.1, 0.9, 0.5, 0.3])
    cand = torch.tensor([True, True, False, True])
    assert threshold_mask(score, cand, 0.4).tolist() == [True, False, True, True]


@pytest.mark.parametrize("ratio", [0.0, -0.1, 1.01])
def test_bad_keep_ratio(ratio):
    with pytest.raises(ValueError, match="keep_ratio"):
        num_to_remove(10, ratio)


def test_num_to_remove_rounds_and_keeps_one():
    assert num_to_remove(10, 1.0) == 0
    assert num_to_remove(10, 0.75) == 2  # round(7.5) = 8 kept (banker's rounding)
    assert num_to_remove(10, 0.01) == 9  # at least one kept


def test_random_mask_is_reproducible_and_exact():
    a = random_mask(100, 30, torch.Generator().manual_seed(3))
    b = random_mask(100, 30, torch.Generator().manual_seed(3))
    c = random_mask(100, 30, torch.Generator().manual_seed(4))
    assert torch.equal(a, b) and not torch.equal(a, c)
    assert int((~a).sum()) == 30
    cand = torch.arange(100) % 2 == 0
    d = random_mask(100, 80, torch.Generator().manual_seed(3), candidates=cand)
    assert int((~d).sum()) == 50 and bool(d[~cand].all())


def test_mask_indices_round_trip():
    keep = torch.tensor([True, False, True, True, False])
    idx = kept_indices(keep)
    assert idx.tolist() == [0, 2, 3]
    assert torch.equal(mask_from_indices(idx, 5), keep)
    with pytest.raises(ValueError, match="out of range"):
        mask_from_indices(torch.tensor([0, 5]), 5)
    with pytest.raises(ValueError, match="repeat"):
        mask_from_indices(torch.tensor([1, 1]), 5)


def test_apply_keep_rejects_wrong_shape():
    model = tagged_model(n=10)
    with pytest.raises(ValueError, match="keep mask"):
        apply_keep(model, torch.ones(9, dtype=torch.bool))


class TestScoreChoice:
    """``--score auto``: the default and its alternatives are swept with the same measure, and the one that removes
    the most within the tolerance (``--auto``, the cheaper among equal removals) or keeps the higher PSNR at the asked
    ratio (``--keep-ratio``) is used; the default wins full ties."""

    @staticmethod
    def sweeps(ratios, tolerance_db=0.1, full=False):
        from uncertsplat.prune.policy import keep_ratio_sweep
        from uncertsplat.schemas.prune import PruneMetrics

        model = tagged_model(n=60)
        carriers = carrier_mask(model)
        important = model.params["means"][:, 0].detach() < 30  # the first 30 rows carry the image

        def measure(m, keep, full_=True):
            # 30 dB, less 0.05 dB per important Gaussian removed
            lost = int((~keep & important).sum())
            return PruneMetrics(num_gaussians=len(m), num_carriers=m.num_carriers, psnr_render=30.0 - 0.05 * lost,
                                coverage=1.0, variational_ply_bytes=0, point_cloud_ply_bytes=0, seconds=0.0)

        unpruned = measure(model, torch.ones(60, dtype=torch.bool))
        rows = model.params["means"][:, 0].detach()
        scores = {"free-space": -rows, "gate": rows}  # free-space removes the important rows first, gate the others
        return {name: keep_ratio_sweep(model, s, carriers, ratios, measure, unpruned=unpruned, seed=0,
                                       tolerance_db=tolerance_db, score_name=name, split="test", full=full)
                for name, s in scores.items()}

    def test_the_score_that_removes_more_within_the_tolerance_is_chosen(self):
        from uncertsplat.prune.policy import choose_score_by_removal

        sweeps = self.sweeps([1.0, 0.9, 0.8])
        assert sweeps["free-space"].largest_removal_within_tolerance is None  # 6 important rows: 0.3 dB
        assert sweeps["gate"].largest_removal_within_tolerance.keep_ratio == 0.8
        chosen, note = choose_score_by_removal(sweeps)
        assert chosen == "gate" and "'free-space' 0 Gaussians, its smallest removal 0.3" in note
        assert "'gate' 12 Gaussians for 0.0" in note

    def test_equal_removals_go_to_the_cheaper_then_to_the_default(self):
        from uncertsplat.prune.policy import choose_score_by_removal

        sweeps = self.sweeps([1.0, 0.9], tolerance_db=100.0)  # both remove 6: free-space 0.3 dB, gate nothing
        assert choose_score_by_removal(sweeps)[0] == "gate"  # (the default won and kept the worse model)
        same = {"free-space": sweeps["gate"], "gate": sweeps["gate"]}  # removal and cost equal: the default
        assert choose_score_by_removal(same)[0] == "free-space"
        assert choose_score_by_removal(self.sweeps([1.0, 0.9], tolerance_db=0.0))[0] == "gate"

    def test_where_none_removes_anything_the_nearest_miss_is_quoted(self):
        """Neither score's smallest removal stays within the tolerance: the note of ``--auto`` quoted the default's
        cost (0.40 dB on a helper's fern run) where the other's cost 0.06; now the score whose smallest removal cost
        least is kept, and its cost quoted."""
        from uncertsplat.prune.policy import auto_keep_ratio, choose_score_by_removal

        sweeps = self.sweeps([1.0, 0.6])  # 24 removed: free-space 1.15 dB, gate 0.35 dB, both over 0.1
        assert all(sw.largest_removal_within_tolerance is None for sw in sweeps.values())
        chosen, said = choose_score_by_removal(sweeps)
        assert chosen == "gate"  # (each one's smallest removal said, which decided: "0 Gaussians" alone did not)
        assert "'free-space' 0 Gaussians, its smallest removal 1.15 dB; 'gate' 0 Gaussians, its smallest removal 0.35 dB" in said
        keep, note = auto_keep_ratio(sweeps[chosen])
        assert keep == 1.0 and "the smallest removal tried, 40 %, cost 0.35 dB" in note

    def test_at_a_keep_ratio_the_higher_psnr_is_chosen(self):
        from uncertsplat.prune.policy import choose_score_at_ratio

        sweeps = self.sweeps([0.9])
        chosen, note = choose_score_at_ratio(sweeps, 0.9)
        assert chosen == "gate" and "'free-space' 29.70 dB" in note and "'gate' 30.00 dB" in note
        assert choose_score_at_ratio(self.sweeps([1.0]), 1.0)[0] == "free-space"  # nothing removed: a tie


def test_a_threshold_that_removes_most_carriers_is_noted():
    from uncertsplat.prune.policy import choose_mask

    score = torch.tensor([0.1, 0.2, 0.3, 0.4, 5.0])
    carriers = torch.tensor([True, True, True, True, False])
    keep, notes = choose_mask(score, carriers, threshold=0.15, keep_ratio=None)
    assert int((~keep).sum()) == 3 and len(notes) == 1
    assert notes[0].startswith("--threshold 0.15 removes 3 of the 4 Gaussians that carry a posterior (75%)")
    # every carrier removed, only those without a posterior left (a review's 7 of 15,810 Gaussians at 7 dB, written
    # with a note): refused
    from uncertsplat.errors import UserError

    with pytest.raises(UserError, match=r"--threshold -1 removes every one of the 4 Gaussians that carry a posterior "
                                        r"\(this score ranges from 0.1 on them\), leaving only the 1 without one"):
        choose_mask(score, carriers, threshold=-1.0, keep_ratio=None)
    keep, notes = choose_mask(score, carriers, threshold=0.35, keep_ratio=None)
    assert int((~keep).sum()) == 1 and notes == []
    # every Gaussian a carrier and every one above the threshold: refused (writing an empty model raised deep in
    # the PLY writer, a traceback)
    with pytest.raises(UserError, match=r"--threshold -1 removes every one of the 5 Gaussians \(this score ranges "
                                        r"from 0.1 to 5"):
        choose_mask(score, torch.ones(5, dtype=torch.bool), threshold=-1.0, keep_ratio=None)
    keep, notes = choose_mask(score, carriers, threshold=0.5, keep_ratio=None)  # above every carrier's score
    assert keep.all() and len(notes) == 1
    assert notes[0].startswith("--threshold 0.5 is above every score (0.4 at most, median")


def test_auto_on_a_model_too_small_to_remove_any_gaussian_says_so():
    """Every keep ratio of a 1-Gaussian model rounds to no removal: --auto must not blame the tolerance."""
    from uncertsplat.prune.policy import auto_keep_ratio
    from uncertsplat.schemas.prune import PruneMetrics, PruneSweep, SweepPoint

    m = PruneMetrics(num_gaussians=1, num_carriers=1, psnr=7.19, psnr_render=7.19, coverage=0.01,
                     variational_ply_bytes=900, point_cloud_ply_bytes=300, seconds=0.1)
    points = [SweepPoint(keep_ratio=r, num_removed=0, keep_ratio_achieved=1.0, score=m, random=m) for r in (0.9, 0.7)]
    sweep = PruneSweep(ratios=[1.0, 0.9, 0.7], score="gate", split="test", unpruned=m, points=points,
                       tolerance_db=0.1, metric="psnr_render")
    ratio, note = auto_keep_ratio(sweep)
    assert ratio == 1.0 and "none of the evaluated keep ratios removes a Gaussian" in note
    assert "--tolerance-db" not in note


def _sweep_point(keep, psnr):
    """A sweep point of 100 carriers at ``keep`` whose score and random removal both render at ``psnr``."""
    from uncertsplat.schemas.prune import PruneMetrics, SweepPoint

    m = PruneMetrics(num_gaussians=100, num_carriers=100, psnr_render=psnr, coverage=0.9,
                     variational_ply_bytes=900, point_cloud_ply_bytes=300, seconds=0.1)
    n = round(100 * (1 - keep))
    return SweepPoint(keep_ratio=keep, num_removed=n, keep_ratio_achieved=keep, score=m, random=m)


def test_largest_removal_stops_at_the_first_ratio_that_fails():
    """``--auto`` walks the keep ratios downward and stops at the first that loses more than the tolerance: a
    larger removal that passes again (0.7 here) is noise, not a plateau, and must not be chosen."""
    from uncertsplat.prune.policy import largest_removal_within

    point = _sweep_point
    points = [point(1.0, 30.0), point(0.9, 29.8), point(0.8, 29.0), point(0.7, 29.9)]
    choice = largest_removal_within(points, 30.0, 0.5)
    assert choice.keep_ratio == 0.9 and choice.num_removed == 10
    assert choice.psnr_loss_db == pytest.approx(0.2) and choice.tolerance_db == 0.5
    # without the failing 0.8 the walk goes on to 0.7; a first ratio that fails gives no removal at all
    assert largest_removal_within([points[0], points[1], points[3]], 30.0, 0.5).keep_ratio == 0.7
    assert largest_removal_within([points[0], points[2], points[3]], 30.0, 0.5) is None
    assert largest_removal_within(points, None, 0.5) is None


def test_a_score_that_loses_to_random_removal_is_noted():
    from types import SimpleNamespace

    from uncertsplat.config import PruneConfig
    from uncertsplat.stages.prune import RANDOM_NOTE, _random_note

    def result(after, random, removed=5):
        m = SimpleNamespace(after=SimpleNamespace(psnr_render=after), random=SimpleNamespace(psnr_render=random))
        return SimpleNamespace(metrics=m, counts=SimpleNamespace(removed=removed), notes=[])

    notes = ["other"]
    r = result(20.31, 23.43)
    _random_note(r, notes, "predictive", PruneConfig(keep_ratio=0.8, score="predictive"))
    assert r.notes == notes and notes[0] == "other"
    assert notes[1].startswith(f"{RANDOM_NOTE}: 23.43 dB held out against 20.31 dB by 'predictive'")
    assert "--score auto measures the scores" in notes[1]
    _random_note(r, notes, "predictive", PruneConfig(keep_ratio=0.8, score="predictive"))
    assert len(notes) == 2  # replaced, not repeated
    for quiet in (result(23.40, 23.43), result(23.5, 23.43), result(20.0, 23.4, removed=0)):
        _random_note(quiet, notes, "gate", PruneConfig(keep_ratio=0.8))
        assert notes == ["other"]


class TestBoundaries:
    """The edges of the decisions: a score equal to the threshold stays, a loss of exactly the tolerance is
    within it, half of the carriers removed is already 'most', and a sweep always holds the unpruned point
    1.0."""

    def test_a_score_equal_to_the_threshold_is_kept(self):
        score = torch.tensor([0.1, 0.4, 0.5, float("nan")])
        cand = torch.ones(4, dtype=torch.bool)
        assert threshold_mask(score, cand, 0.4).tolist() == [True, True, False, False]

    def test_a_loss_of_exactly_the_tolerance_is_within_it(self):
        from uncertsplat.prune.policy import largest_removal_within

        point = _sweep_point
        points = [point(1.0, 30.0), point(0.9, 29.75), point(0.8, 29.5), point(0.7, 29.25)]
        choice = largest_removal_within(points, 30.0, 0.5)  # 30 - 0.5 = 29.5 exactly (all binary fractions)
        assert choice.keep_ratio == 0.8 and choice.psnr_loss_db == 0.5
        assert largest_removal_within(points, 30.0, 0.25).keep_ratio == 0.9

    def test_removing_exactly_half_of_the_carriers_is_noted(self):
        from uncertsplat.prune.policy import choose_mask

        score = torch.tensor([0.1, 0.2, 0.3, 0.4, 5.0])
        carriers = torch.tensor([True, True, True, True, False])
        keep, notes = choose_mask(score, carriers, threshold=0.25, keep_ratio=None)
        assert keep.tolist() == [True, True, False, False, True] and len(notes) == 1
        assert notes[0].startswith("--threshold 0.25 removes 2 of the 4 Gaussians that carry a posterior "
                                   "(50%)")

    def test_a_sweep_always_holds_the_unpruned_point(self):
        sweeps = TestScoreChoice.sweeps([0.9])
        for sweep in sweeps.values():
            assert sweep.ratios == [1.0, 0.9]
            assert [p.keep_ratio for p in sweep.points] == [1.0, 0.9]
            first = sweep.points[0]
            assert first.num_removed == 0 and first.keep_ratio_achieved == 1.0
            assert first.score == sweep.unpruned and first.random == sweep.unpruned
            removal = sweep.points[1]
            assert removal.num_removed == 6 and removal.keep_ratio_achieved == pytest.approx(0.9)


class TestSweepAndNotes:
    """``--auto`` alone stops the sweep at the first failing ratio; a keep ratio notes a removal only when the
    carriers are too few for it."""

    @staticmethod
    def setup(calls):
        from uncertsplat.schemas.prune import PruneMetrics

        model = tagged_model(n=60)
        carriers = carrier_mask(model)
        rows = model.params["means"][:, 0].detach()

        def measure(m, keep, full=True):
            calls.append(int((~keep).sum()))
            lost = int((~keep & (rows < 30)).sum())  # 30 dB, less 0.05 dB per removed row of the first 30
            return PruneMetrics(num_gaussians=len(m), num_carriers=m.num_carriers,
                                psnr_render=30.0 - 0.05 * lost, coverage=1.0, variational_ply_bytes=0,
                                point_cloud_ply_bytes=0, seconds=0.0)

        return model, carriers, -rows, measure  # the score removes the important rows first

    def test_stop_at_first_failure_measures_no_further_ratio(self):
        from uncertsplat.prune.policy import keep_ratio_sweep

        for stop, keeps in ((True, [1.0, 0.9]), (False, [1.0, 0.9, 0.8])):
            calls = []
            model, carriers, score, measure = self.setup(calls)
            unpruned = measure(model, torch.ones(60, dtype=torch.bool))
            sweep = keep_ratio_sweep(model, score, carriers, [0.9, 0.8], measure, unpruned=unpruned, seed=0,
                                     tolerance_db=0.1, score_name="free-space", split="test",
                                     stop_at_first_failure=stop)
            # 0.9 removes 6 of the first 30 rows: 0.3 dB, over the 0.1 dB tolerance
            assert [p.keep_ratio for p in sweep.points] == keeps
            # the unpruned model, then the score's and the random removal of each ratio measured
            assert calls == [0] + [6, 6, 12, 12][: 2 * (len(keeps) - 1)]
            assert sweep.largest_removal_within_tolerance is None

    def test_a_keep_ratio_notes_only_a_removal_the_carriers_cannot_make(self):
        from uncertsplat.prune.policy import choose_mask

        score = torch.tensor([0.5, 0.1, 0.4, 0.2, 0.3, 0.9])
        carriers = torch.tensor([True, True, True, True, False, False])
        keep, notes = choose_mask(score, carriers, threshold=None, keep_ratio=0.5)  # 3 to remove, 4 carriers
        assert keep.tolist() == [False, True, False, False, True, True] and notes == []
        # 5 to remove (round(1.2) = 1 kept)
        keep, notes = choose_mask(score, carriers, threshold=None, keep_ratio=0.2)
        assert keep.tolist() == [False, False, False, False, True, True]
        assert notes == ["keep ratio 0.2 needs 5 removals but only 4 Gaussians carry a posterior; "
                         "non-carriers are never removed by a score"]
        assert choose_mask(score, carriers, threshold=None, keep_ratio=None) == (None, [])

    @staticmethod
    def sweep(first_psnr, name="s"):
        from uncertsplat.schemas.prune import PruneMetrics, PruneSweep, SweepPoint

        def metrics(psnr):
            return PruneMetrics(num_gaussians=100, num_carriers=100, psnr_render=psnr, coverage=0.9,
                                variational_ply_bytes=900, point_cloud_ply_bytes=300, seconds=0.1)

        ref = metrics(30.0)
        points = [SweepPoint(keep_ratio=1.0, num_removed=0, keep_ratio_achieved=1.0, score=ref, random=ref),
                  SweepPoint(keep_ratio=0.9, num_removed=10, keep_ratio_achieved=0.9,
                             score=metrics(first_psnr), random=metrics(29.0))]
        return PruneSweep(ratios=[1.0, 0.9], score=name, split="test", unpruned=ref, points=points,
                          tolerance_db=0.1, metric="psnr_render")

    def test_an_unmeasured_psnr_loses_to_a_measured_one(self):
        from uncertsplat.prune.policy import choose_score_at_ratio, choose_score_by_removal

        sweeps = {"free-space": self.sweep(None), "gate": self.sweep(29.5)}  # neither within 0.1 dB
        chosen, note = choose_score_at_ratio(sweeps, 0.9)
        assert chosen == "gate" and "'free-space' -inf dB; 'gate' 29.50 dB" in note
        # --auto: neither removes anything; the nearest miss is a measured one (0.50 dB), not the unknown
        chosen, note = choose_score_by_removal(sweeps)
        assert chosen == "gate"
        assert "('free-space' 0 Gaussians; 'gate' 0 Gaussians, its smallest removal 0.50 dB)" in note


def test_keep_top_clamps_the_count_to_the_candidates():
    """A negative count removes nothing (it sliced the order from its end: all but two removed), one above the
    candidates removes every candidate and nothing else."""
    score = torch.tensor([0.1, 0.9, 0.5, 0.3])
    cand = torch.tensor([True, True, False, True])
    assert keep_top(score, cand, -2).tolist() == [True, True, True, True]
    assert keep_top(score, cand, 10).tolist() == [False, False, True, False]
    assert random_mask(4, -1, torch.Generator().manual_seed(0), candidates=cand).all()
    every = random_mask(4, 10, torch.Generator().manual_seed(0), candidates=cand)
    assert every.tolist() == [False, False, True, False]
