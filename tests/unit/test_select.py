"""``select-views`` building blocks: deterministic ranking, greedy coverage, candidate pose files."""

from __future__ import annotations

import math
import zlib

import pytest
import torch

from tests.fixtures import tiny_scene_path  # noqa: F401
from uncertsplat.config import SceneConfig
from uncertsplat.errors import UserError
from uncertsplat.select import scores as scores_mod
from uncertsplat.select.candidates import around_views, candidates_from_spec, read_pose_file, unused_views
from uncertsplat.select.scores import coverage_choice, fisher_choice, gap_eligible, rank_order
from uncertsplat.sfm.scene import load_scene
from uncertsplat.uncertainty import curvature as curvature_mod
from uncertsplat.view.frames import rotmat_to_wxyz


class TestRanking:
    def test_descending_ties_by_position_nan_last(self):
        s = torch.tensor([1.0, 3.0, float("nan"), 3.0, 2.0, 1.0])
        assert rank_order(s) == [1, 3, 4, 0, 5, 2]

    def test_all_equal_keeps_candidate_order(self):
        assert rank_order(torch.zeros(5)) == [0, 1, 2, 3, 4]

    def test_coverage_is_greedy_farthest_point(self):
        used = torch.tensor([[0.0, 0.0, 0.0]])
        cands = torch.tensor([[1.0, 0, 0], [5.0, 0, 0], [-5.0, 0, 0], [4.9, 0, 0]])
        chosen, at, first = coverage_choice(cands, used, 3)
        # 5 and -5 tie at distance 5: the first listed wins; then -5 (10 away from it), then 1
        assert chosen == [1, 2, 0] and at == pytest.approx([5.0, 5.0, 1.0])
        torch.testing.assert_close(first, torch.tensor([1.0, 5.0, 5.0, 4.9], dtype=torch.float64))

    def test_coverage_measures_from_the_nearest_of_several_used_cameras(self):
        """Cameras used at 0 and 10: a candidate at 9.5 lies 0.5 from the nearest (not 9.5 from the first, nor 10
        from the farthest), so the one midway (5 from both) is the gap."""
        from uncertsplat.select.scores import nearest_used_distance

        used = torch.tensor([[0.0, 0, 0], [10.0, 0, 0]])
        cands = torch.tensor([[1.0, 0, 0], [5.0, 0, 0], [9.5, 0, 0], [3.0, 4.0, 0]])
        expect = torch.tensor([1.0, 5.0, 0.5, 5.0], dtype=torch.float64)
        torch.testing.assert_close(nearest_used_distance(cands, used), expect)
        chosen, at, first = coverage_choice(cands, used, 2)
        torch.testing.assert_close(first, expect)
        # 5 ties with (3, 4, 0) at 5 (the first listed wins); then (3, 4, 0) is 4.47 from it and 5 from the cameras
        assert chosen == [1, 3] and at == pytest.approx([5.0, math.sqrt(20.0)])
        assert torch.isinf(nearest_used_distance(cands, torch.zeros(0, 3))).all()

    def test_coverage_never_repeats_and_stops_at_the_pool(self):
        cands = torch.zeros(3, 3)  # identical cameras: distances 0 after the first pick
        chosen, _, _ = coverage_choice(cands, torch.ones(1, 3), 5)
        assert chosen == [0, 1, 2]


def test_a_candidates_variance_score_depends_on_neither_its_place_in_the_list_nor_its_poses_last_digits(monkeypatch):
    """Every candidate is scored with the same draws (one seed): a plan file read in reverse gives every pose the same
    score (seeded by position, a pose's score moved by up to 3.5 % on the demo), and so does a pose one float32
    rounding away (seeded by the pose's values, a pose read back from selection.json's pose_line moved by up to
    8.7 %). The fake score is the generator's draw plus the camera's x offset."""
    from types import SimpleNamespace

    from uncertsplat.types import Cameras
    from uncertsplat.uncertainty import mc

    def draws(sample_fn, render_fn, cams, k, gen, **kw):
        x = torch.rand(1, cams.height, cams.width, 1, generator=gen, dtype=torch.float64) + cams.cam_from_world[0, 0, 3]
        return SimpleNamespace(rgb_std=x.expand(-1, -1, -1, 3), depth_std=x), None

    monkeypatch.setattr(mc, "mc_render", draws)
    w2c = torch.eye(4).repeat(5, 1, 1)
    w2c[:, 0, 3] = torch.arange(5.0)
    K = torch.tensor([[20.0, 0, 8], [0, 20.0, 6], [0, 0, 1]]).repeat(5, 1, 1)
    cams = Cameras(w2c, K, 16, 12)
    rgb, depth = scores_mod.variance_scores(None, None, cams, 2, 7, empty_std=None)
    back = list(range(4, -1, -1))
    rgb_rev, depth_rev = scores_mod.variance_scores(None, None, cams[back], 2, 7, empty_std=None)
    torch.testing.assert_close(rgb_rev, rgb[back], rtol=0, atol=0)
    torch.testing.assert_close(depth_rev, depth[back], rtol=0, atol=0)
    nudged = w2c.clone()
    nudged[:, :3, :3] = torch.nextafter(nudged[:, :3, :3], torch.tensor(2.0))  # a rotation read back from its quaternion
    rgb_nudged, _ = scores_mod.variance_scores(None, None, Cameras(nudged, K, 16, 12), 2, 7, empty_std=None)
    torch.testing.assert_close(rgb_nudged, rgb, rtol=0, atol=0)
    assert not torch.equal(scores_mod.variance_scores(None, None, cams, 2, 8, empty_std=None)[0], rgb)  # the seed


class _Views:
    """Stand-in cameras: a list of labels, indexable like ``Cameras``."""

    height = width = 1

    def __init__(self, labels):
        self.labels = list(labels)
        # a pose per label (the fake curvatures read it)
        self.cam_from_world = torch.eye(4).repeat(len(self.labels), 1, 1)
        self.cam_from_world[:, 0, 3] = torch.tensor([zlib.crc32(str(v).encode()) % 1000 for v in self.labels],
                                                     dtype=torch.float32)
        self.K = torch.eye(3).repeat(len(self.labels), 1, 1)

    def __len__(self):
        return len(self.labels)

    def __getitem__(self, idx):
        return _Views([self.labels[i] for i in idx])


class TestFisherInformation:
    """``fisher_choice``'s counts of a candidate's information, with the curvature replaced by known diagonals:
    one parameter ``a`` that one candidate pins sharply, one ``b`` that three candidates see."""

    FISHER = {"train": [1.0, 0.0], 0: [10.0, 0.0], 1: [0.0, 4.0], 2: [0.0, 4.0], 3: [0.0, 4.0]}

    @pytest.fixture
    def choose(self, monkeypatch):
        def fake(params, cameras, images, render_fn, *, noise_std=None, **_):
            f = torch.tensor(self.FISHER["train" if noise_std is None else cameras.labels[0]], dtype=torch.float64)
            return curvature_mod.Curvature({"means": f}, 0.1, None)

        monkeypatch.setattr(curvature_mod, "curvature", fake)

        def run(information, n, eligible=None, prior=1.0, competing=None):
            return fisher_choice({}, _Views(["train"]), torch.zeros(1, 1, 1, 3), _Views(range(4)), None,
                                 names=["means"], prior_std={"means": prior}, sh_degree=0, probes=1, seed=0, n=n,
                                 information=information, eligible=eligible, competing=competing)
        return run

    def test_gaps_keep_the_choice_among_the_far_candidates(self, choose):
        # candidates on a line at 1, 4, 5, 9 from the one camera used (at 0); view 0 is the most informative
        centres = torch.tensor([[1.0, 0, 0], [4.0, 0, 0], [5.0, 0, 0], [9.0, 0, 0]])
        eligible = gap_eligible(centres, torch.zeros(1, 3), 0.5)
        assert eligible([]).tolist() == [False, False, True, True]  # at least 0.5 x 9 from the camera
        # after choosing view 3, the distances are 1, 4, 4, - and 0.5 x 4 lets views 1 and 2 in
        assert eligible([3]).tolist() == [False, True, True, False]
        # views 2 and 3 tie at 4 (the first wins); then view 3 alone lies in the gap (4 from view 2, 1 for the others)
        chosen, at, first, _ = choose("trace", 2, eligible)
        assert chosen == [2, 3] and at == pytest.approx([4.0, 4.0 / 5.0])  # view 2 pinned b: precision 1 + 4
        assert math.isnan(first[0]) and math.isnan(first[1])  # not scored
        # without the gaps the sharp view 0, next to the camera, wins
        assert choose("trace", 1)[0] == [0]
        # fraction 0 lets every candidate compete; 1 only the farthest (coverage's choice)
        assert gap_eligible(centres, torch.zeros(1, 3), 0.0)([]).all()
        assert gap_eligible(centres, torch.zeros(1, 3), 1.0)([]).tolist() == [False, False, False, True]

    def test_trace_takes_the_sharp_view(self, choose):
        chosen, at, first, _ = choose("trace", 1)
        # precision = training Fisher + 1 / prior^2 = [2, 1]: 10 / 2 = 5 against 4 / 1
        assert chosen == [0] and at == pytest.approx([5.0])
        torch.testing.assert_close(first, torch.tensor([5.0, 4.0, 4.0, 4.0], dtype=torch.float64))

    def test_the_prior_adds_its_precision_one_over_its_variance(self, choose):
        # prior std 0.5: precision = training Fisher + 1 / 0.5^2 = [5, 4]: 10 / 5 = 2 against 4 / 4 = 1
        chosen, at, first, _ = choose("trace", 1, prior=0.5)
        assert chosen == [0] and at == pytest.approx([2.0])
        torch.testing.assert_close(first, torch.tensor([2.0, 1.0, 1.0, 1.0], dtype=torch.float64))
        # a wide prior (std 4: precision [1.0625, 0.0625]) leaves b unknown: the views that see it win
        chosen, at, _, _ = choose("trace", 1, prior=4.0)
        assert chosen == [1] and at == pytest.approx([4.0 / 0.0625])

    def test_predictive_weighs_what_the_capture_shows(self, choose):
        chosen, at, first, _ = choose("predictive", 2)
        # G = training + every candidate = [11, 12]; score = G F / (P (P + F)):
        # view 0: 11 * 10 / (2 * 12) = 4.583, views 1-3: 12 * 4 / (1 * 5) = 9.6 (the first of the tie wins)
        torch.testing.assert_close(first, torch.tensor([110 / 24, 9.6, 9.6, 9.6], dtype=torch.float64))
        # then view 1's Fisher joins the precision ([2, 5]): views 2-3 drop to 12 * 4 / (5 * 9), view 0 is next
        assert chosen == [1, 0] and at == pytest.approx([9.6, 110 / 24])

    def test_only_the_competing_candidates_join_the_predictive_s_reference(self, choose):
        # views 2 and 3 do not compete (poses inside an object): G = training + views 0 and 1 = [11, 4], so b's
        # views score 4 x 4 / (1 x 5) = 3.2 and the sharp view 0 (11 x 10 / (2 x 12)) wins
        chosen, at, first, _ = choose("predictive", 1, competing=torch.tensor([True, True, False, False]))
        torch.testing.assert_close(first, torch.tensor([110 / 24, 3.2, 3.2, 3.2], dtype=torch.float64))
        assert chosen == [0] and at == pytest.approx([110 / 24])

    def test_a_candidates_information_depends_on_neither_its_place_nor_its_poses_last_digits(self, monkeypatch):
        """Every candidate's probes come from one seed: the candidates in reverse get the same information, and so
        does a pose one float32 rounding away (the fake curvature returns its generator's draw plus the candidate's
        x offset); seeded by position, or by the pose's values, they did not."""
        def fake(params, cameras, images, render_fn, *, noise_std=None, generator=None, **_):
            shift = 0.0 if noise_std is None else float(cameras.cam_from_world[0, 0, 3])
            return curvature_mod.Curvature({"means": torch.rand(2, generator=generator, dtype=torch.float64) + shift},
                                           0.1, None)

        monkeypatch.setattr(curvature_mod, "curvature", fake)

        def first(views, seed=3):
            return fisher_choice({}, _Views(["train"]), torch.zeros(1, 1, 1, 3), views, None,
                                 names=["means"], prior_std={"means": 1.0}, sh_degree=0, probes=1, seed=seed, n=1)[2]

        forward, backward = first(_Views(["a", "b", "c", "d"])), first(_Views(["d", "c", "b", "a"]))
        torch.testing.assert_close(backward, forward.flip(0), rtol=0, atol=0)
        assert len(set(forward.tolist())) == 4
        nudged = _Views(["a", "b", "c", "d"])
        nudged.cam_from_world[:, :3, :3] = torch.nextafter(nudged.cam_from_world[:, :3, :3], torch.tensor(2.0))
        torch.testing.assert_close(first(nudged), forward, rtol=0, atol=0)
        assert not torch.equal(first(_Views(["a", "b", "c", "d"]), seed=4), forward)

    @pytest.mark.parametrize("information", ["trace", "log-det", "predictive"])
    @pytest.mark.parametrize("gaps", [False, True])
    def test_lazy_greedy_chooses_what_recomputing_every_candidate_chooses(self, monkeypatch, information, gaps):
        """The choice recomputes only the candidate on top each round (a gain only falls as the precision grows):
        the same views, gains and first scores as the plain greedy that recomputes every candidate every round
        (written out here), on random diagonals with ties, and far fewer curvatures past the cache."""
        num, n = 40, 8
        g = torch.Generator().manual_seed(5)
        # each candidate sees a window of 12 of 200 parameters, overlapping its neighbours' (a view sees part of
        # a scene); rounded values: ties
        diag = torch.zeros(num, 200, dtype=torch.float64)
        for c in range(num):
            diag[c, 4 * c: 4 * c + 12] = (torch.rand(12, generator=g, dtype=torch.float64) * 3).round()
        train = torch.rand(200, generator=g, dtype=torch.float64)
        calls = []

        def fake(params, cameras, images, render_fn, *, noise_std=None, **_):
            if noise_std is None:
                return curvature_mod.Curvature({"means": train.clone()}, 0.1, None)
            calls.append(cameras.labels[0])
            return curvature_mod.Curvature({"means": diag[cameras.labels[0]].clone()}, 0.1, None)

        monkeypatch.setattr(curvature_mod, "curvature", fake)
        monkeypatch.setattr(scores_mod, "CACHE_ELEMENTS", 0)  # every Fisher computed again when needed
        centres = torch.rand(num, 3, generator=g, dtype=torch.float64)
        eligible = gap_eligible(centres, torch.zeros(1, 3, dtype=torch.float64), 0.5) if gaps else None
        chosen, at, first, _ = fisher_choice({}, _Views(["train"]), torch.zeros(1, 1, 1, 3), _Views(range(num)), None,
                                             names=["means"], prior_std={"means": 1.0}, sh_degree=0, probes=1,
                                             seed=0, n=n, information=information, eligible=eligible)

        precision = train + 1.0
        reference_sum = train + diag.sum(0)

        def plain_gain(f):
            if information == "trace":
                return float((f / precision).sum())
            if information == "log-det":
                return float((0.5 * torch.log1p(f / precision)).sum())
            return float((reference_sum * f / (precision * (precision + f))).sum())

        want, want_at, want_first = [], [], None
        for _ in range(n):
            ok = eligible(want).tolist() if eligible is not None else [True] * num
            scores = torch.tensor([plain_gain(diag[c]) if ok[c] and c not in want else float("nan")
                                   for c in range(num)], dtype=torch.float64)
            want_first = scores if want_first is None else want_first
            j = scores_mod.best_unchosen(scores, want)
            want.append(j)
            want_at.append(float(scores[j]))
            precision = precision + diag[j]
        assert chosen == want
        assert at == pytest.approx(want_at, rel=1e-12)
        torch.testing.assert_close(first, want_first, equal_nan=True)
        computed = len(calls) - (num if information == "predictive" else 0)  # predictive sums every candidate first
        assert computed <= num + 4 * n < n * num / 2, computed  # the plain greedy: about n * num

    def test_cache_off_gives_the_same_choice(self, choose, monkeypatch):
        cached = choose("predictive", 3)
        monkeypatch.setattr(scores_mod, "CACHE_ELEMENTS", 0)
        assert choose("predictive", 3)[:2] == cached[:2]

    def test_unknown_information_is_refused(self, choose):
        with pytest.raises(ValueError, match="predictive"):
            choose("entropy", 1)


@pytest.fixture(scope="module")
def scene(tiny_scene_path):
    return load_scene(tiny_scene_path, SceneConfig(train_names=["view_001.png", "view_002.png", "view_003.png"]))


def _source_lines(scene, indices):
    """COLMAP-style lines of the scene's own cameras in source coordinates (inverse of the normalisation)."""
    W = scene.world_from_source.double()
    s = float(torch.linalg.det(W[:3, :3]) ** (1 / 3))
    R0, t0 = W[:3, :3] / s, W[:3, 3]
    lines = []
    for i in indices:
        T = scene.cameras.cam_from_world[i].double()
        R = T[:3, :3] @ R0
        t = (T[:3, 3] + T[:3, :3] @ t0) / s
        q = rotmat_to_wxyz(R.numpy())
        lines.append(f"cand_{i} " + " ".join(f"{v:.12g}" for v in [*q, *t.tolist()]))
    return lines


class TestCandidates:
    def test_unused_are_neither_trained_nor_held_out(self, scene):
        idx = unused_views(scene)
        assert idx and not set(idx) & (set(scene.split["train"]) | set(scene.split["test"]))
        c = candidates_from_spec("unused", scene, scene.world_from_source, radius=1.0, generator=torch.Generator())
        assert c.kind == "unused" and list(c.scene_indices) == idx
        # views set aside for calibration are no candidates either (adding them would change which are set aside)
        from dataclasses import replace

        aside = replace(scene, split={**scene.split, "calibration": (idx[0],)})
        assert unused_views(aside) == idx[1:]

    def test_pose_file_round_trips_to_the_scenes_cameras(self, scene, tmp_path):
        f = tmp_path / "poses.txt"
        f.write_text("# name qw qx qy qz tx ty tz\n\n" + "\n".join(_source_lines(scene, [0, 5, 9])) + "\n")
        cams = read_pose_file(f, scene, scene.world_from_source)
        assert cams.image_names == ("cand_0", "cand_5", "cand_9")
        torch.testing.assert_close(cams.cam_from_world, scene.cameras.cam_from_world[[0, 5, 9]], atol=1e-5, rtol=0)

    def test_a_chosen_view_s_pose_line_reads_back_as_the_same_camera(self, scene, tmp_path):
        """selection.json's pose_line is in the scene's own frame, the one a --candidates file is read in: written
        and read back, the camera of the run's normalised world comes back."""
        from uncertsplat.render.project import quat_to_rotmat
        from uncertsplat.select.candidates import pose_line, rotmat_to_quat

        lines = [pose_line(f"c{i}", scene.cameras.cam_from_world[i], scene.world_from_source) for i in (0, 5, 9)]
        f = tmp_path / "plan.txt"
        f.write_text("\n".join(lines) + "\n")
        cams = read_pose_file(f, scene, scene.world_from_source)
        torch.testing.assert_close(cams.cam_from_world, scene.cameras.cam_from_world[[0, 5, 9]], atol=1e-5, rtol=0)
        g = torch.Generator().manual_seed(0)
        for _ in range(50):  # every branch of the conversion, including rotations by about 180 degrees
            q = torch.randn(4, generator=g, dtype=torch.float64)
            q = q / q.norm()
            q = -q if q[0] < 0 else q
            torch.testing.assert_close(rotmat_to_quat(quat_to_rotmat(q[None].float())[0].double()), q, atol=1e-6,
                                       rtol=0)
        for q in ([0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]):
            q = torch.tensor(q, dtype=torch.float64)
            torch.testing.assert_close(rotmat_to_quat(quat_to_rotmat(q[None].float())[0].double()), q, atol=1e-6,
                                       rtol=0)

    def test_names_with_spaces_and_a_byte_order_mark_read_back(self, scene, tmp_path):
        """A photo's name may hold spaces (`--candidates unused` on "Photo 1.jpg"): its pose_line reads back under
        that name; a file an editor saved with a byte-order mark reads as without it (its first comment was read as
        a pose, its first name began with the mark)."""
        from uncertsplat.select.candidates import pose_line

        names = ["IMG 0042.jpg", "two  spaces", "c9"]
        lines = [pose_line(n, scene.cameras.cam_from_world[i], scene.world_from_source)
                 for n, i in zip(names, (0, 5, 9), strict=True)]
        for head in ("# planned poses\n", ""):
            f = tmp_path / "plan.txt"
            f.write_text(head + "\n".join(lines) + "\n", encoding="utf-8-sig")
            cams = read_pose_file(f, scene, scene.world_from_source)
            assert cams.image_names == tuple(names)
            torch.testing.assert_close(cams.cam_from_world, scene.cameras.cam_from_world[[0, 5, 9]], atol=1e-5,
                                       rtol=0)

    @pytest.mark.parametrize("offset", [0.0, 1e5, 1e6, 1e7])
    def test_a_pose_line_far_from_the_scene_s_origin_reads_back_at_its_centre(self, scene, tmp_path, offset):
        """A georeferenced scene (translations of 1e6): the float32 rotation's departure from a rotation times the
        translation, and 9 digits, put a candidate read back from its own pose_line 0.016 of the scene's radius
        away at 1e6 (0.17 at 1e7); its centre now comes back to 1e-5 of the radius (15 digits)."""
        from uncertsplat.select.candidates import pose_line

        far = scene.world_from_source.double().clone()
        far[:3, 3] -= far[:3, :3] @ torch.tensor([offset, -offset, 0.5 * offset], dtype=torch.float64)
        g = torch.Generator().manual_seed(1)
        cands = around_views(scene, 8, 1.0, g)
        # float32 rotations a float32 round off a rotation, as a run's cameras are
        T = cands.cam_from_world.clone()
        T[:, :3, :3] += 1e-7 * torch.randn(8, 3, 3, generator=g)
        lines = [pose_line(f"c{i}", T[i], far) for i in range(8)]
        f = tmp_path / "plan.txt"
        f.write_text("\n".join(lines) + "\n")
        back = read_pose_file(f, scene, far)
        centres = -torch.linalg.solve(T[:, :3, :3].double(), T[:, :3, 3:].double())[..., 0]
        assert float((back.centers.double() - centres).norm(dim=1).max()) < 1e-5 * scene.scene_scale
        torch.testing.assert_close(back.cam_from_world[:, :3, :3], cands.cam_from_world[:, :3, :3], atol=1e-5, rtol=0)

    @pytest.mark.parametrize("line, message", [
        ("a 1 0 0 0 0 0", "8 fields"),
        ("a 1 0 0 0 1 0 0 5", "8 fields.*found 9"),  # (a column too many: read as the name 'a 1', numbers shifted)
        ("a 1 0 0 0 0 0 x", "not 7 numbers"),
        ("a 0 0 0 0 1 2 3", "quaternion is zero"),
        ("a 2 0 0 0 1 2 3", "norm 2"),
        ("a 1.002 0 0 0 1 2 3", "norm 1.002"),  # (past 1e-3: a pose typed with too few digits is not guessed at)
        ("a 1 0 0 0 nan 0 0", "non-finite"),
        ("a 1 0 0 0 0 0 1e300", "too far away to compute with"),  # (finite, inf in float32: ranked first)
    ])
    def test_a_bad_pose_names_its_line(self, scene, tmp_path, line, message):
        f = tmp_path / "poses.txt"
        f.write_text("ok 1 0 0 0 0 0 1\n# comment\n" + line + "\n")
        with pytest.raises(UserError, match=rf"line 3: .*{message}") as err:
            read_pose_file(f, scene, scene.world_from_source)
        assert str(f) in err.value.render()

    def test_colmap_s_images_txt_is_named_with_the_line_that_converts_it(self, scene, tmp_path):
        """COLMAP's images.txt itself (the format is described after it) said "8 fields, found 10 ... A name with spaces
        must not end in a number": its layout is named, with a command that writes the pose file from it."""
        import shutil
        import subprocess

        f = tmp_path / "images.txt"
        f.write_text("# Image list with two lines of data per image:\n#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, "
                     "NAME\n#   POINTS2D[] as (X, Y, POINT3D_ID)\n# Number of images: 2\n"
                     "1 1 0 0 0 0 0 1 1 a.png\n10.5 20.5 3 11.5 2.5 4\n2 1 0 0 0 0 0 2 1 b.png\n\n")
        with pytest.raises(UserError, match=r"line 5 is in the layout of COLMAP's images.txt \(IMAGE_ID QW") as err:
            read_pose_file(f, scene, scene.world_from_source)
        assert "A name with spaces" not in err.value.render()
        command = err.value.hint.split("from images.txt: ", 1)[1].split(" (every", 1)[0]
        if shutil.which("awk") and shutil.which("sh"):
            subprocess.run(["sh", "-c", command], cwd=tmp_path, check=True)
            cams = read_pose_file(tmp_path / "plan.txt", scene, scene.world_from_source)
            assert cams.image_names == ("a.png", "b.png")

    def test_empty_file_duplicates_and_unknown_spec(self, scene, tmp_path):
        empty = tmp_path / "empty.txt"
        empty.write_text("# nothing\n")
        with pytest.raises(UserError, match="holds no pose"):
            read_pose_file(empty, scene, scene.world_from_source)
        dup = tmp_path / "dup.txt"
        dup.write_text("a 1 0 0 0 0 0 1\na 1 0 0 0 0 0 2\n")
        with pytest.raises(UserError, match="repeat: a"):
            read_pose_file(dup, scene, scene.world_from_source)
        with pytest.raises(UserError, match="neither"):
            candidates_from_spec("everything", scene, scene.world_from_source, radius=1.0, generator=torch.Generator())
        for spec in ("around:x", "around:0", "around:100000000000"):  # (the last ran on without a word)
            with pytest.raises(UserError, match="N must be a whole number from 1 to 10,000"):
                candidates_from_spec(spec, scene, scene.world_from_source, radius=1.0, generator=torch.Generator())

    def test_a_folder_given_for_the_pose_file_is_named_a_folder(self, scene, tmp_path):
        """`--candidates scenes/x` (a folder) was "candidate pose file not found", though the path is there."""
        (tmp_path / "photos").mkdir()
        for call in (lambda: read_pose_file(tmp_path / "photos", scene, scene.world_from_source),
                     lambda: candidates_from_spec(str(tmp_path / "photos"), scene, scene.world_from_source, radius=1.0,
                                                  generator=torch.Generator())):
            with pytest.raises(UserError, match="names a folder, not a file of poses") as err:
                call()
            assert "not found" not in err.value.render()

    def test_around_views_are_near_the_training_cameras_and_seeded(self, scene):
        a = around_views(scene, 12, 1.0, torch.Generator().manual_seed(3))
        b = around_views(scene, 12, 1.0, torch.Generator().manual_seed(3))
        assert torch.equal(a.cam_from_world, b.cam_from_world) and len(a) == 12
        R = a.cam_from_world[:, :3, :3].double()
        torch.testing.assert_close(R @ R.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(12, 3, 3),
                                   atol=1e-5, rtol=0)
        train = scene.cameras[scene.split["train"]].centers
        spacing = float(torch.cdist(train, train).add(torch.eye(len(train)) * 1e9).min(1).values.median())
        assert float(torch.cdist(a.centers, train).min(1).values.max()) <= spacing * 1.0 + 1e-5
        assert math.isfinite(float(a.cam_from_world.sum()))
        # without a move, a candidate is its source camera exactly (same orientation: y down, looking forward)
        still = around_views(scene, 6, 1e-12, torch.Generator().manual_seed(0))
        src = scene.cameras[scene.split["train"]].cam_from_world
        for T in still.cam_from_world:
            assert float((src - T).abs().amax((1, 2)).min()) < 1e-4

    def test_around_views_move_by_the_median_spacing_of_the_training_cameras(self):
        """Training cameras at x = 0, 1, 2 and 10 (nearest neighbours 1, 1, 1, 8): the median spacing is 1, so a
        candidate lies within 1 (radius 1) of its source camera, however far the one outlier stands."""
        from types import SimpleNamespace

        from uncertsplat.types import Cameras

        x = torch.tensor([0.0, 1.0, 2.0, 10.0])
        w2c = torch.eye(4).repeat(4, 1, 1)
        w2c[:, 0, 3] = -x  # identity rotation: the centre is -t
        K = torch.tensor([[50.0, 0, 16], [0, 50.0, 12], [0, 0, 1]]).repeat(4, 1, 1)
        scene = SimpleNamespace(cameras=Cameras(w2c, K, 32, 24, tuple(f"c{i}.png" for i in range(4))),
                                split={"train": [0, 1, 2, 3]}, scene_scale=1.0)
        a = around_views(scene, 40, 1.0, torch.Generator().manual_seed(1))
        train = torch.stack([x, torch.zeros(4), torch.zeros(4)], 1)
        moved = torch.cdist(a.centers.double(), train.double()).min(1).values
        assert float(moved.max()) <= 1.0 + 1e-5 and float(moved.max()) > 0.5
        half = around_views(scene, 40, 0.5, torch.Generator().manual_seed(1))  # the radius scales the move
        torch.testing.assert_close(torch.cdist(half.centers.double(), train.double()).min(1).values.max(),
                                   moved.max() * 0.5, atol=0.05, rtol=0)

    def test_around_views_turn_with_the_scene(self, scene):
        """A scene turned (the same capture in another frame: the run's cameras turned with it) gets its candidates
        turned: the offsets are drawn in each camera's axes (along the world's, they moved by up to 0.38 of the
        scene's radius and another view was chosen)."""
        import dataclasses

        from uncertsplat.gaussians.ops import quat_to_rotmat

        turn = torch.eye(4, dtype=torch.float64)
        turn[:3, :3] = quat_to_rotmat(torch.tensor([[0.8, 0.1, -0.5, 0.3]], dtype=torch.float64))[0]
        world_from_turned = torch.linalg.inv(turn)  # x_turned = turn x: a camera's cam_from_turned = T turn^-1
        cams = scene.cameras
        turned = dataclasses.replace(scene, cameras=dataclasses.replace(
            cams, cam_from_world=(cams.cam_from_world.double() @ world_from_turned).float()))
        a = around_views(scene, 10, 1.0, torch.Generator().manual_seed(4))
        b = around_views(turned, 10, 1.0, torch.Generator().manual_seed(4))
        torch.testing.assert_close(b.cam_from_world.double(), a.cam_from_world.double() @ world_from_turned,
                                   atol=2e-5, rtol=0)

    def test_around_views_are_named_apart_from_the_scene_s_photos(self, scene):
        """A capture naming each photo by its candidate (around_012.png) was offered around_012 again the next
        round: the names then take the next round's prefix."""
        import dataclasses

        assert around_views(scene, 3, 1.0, torch.Generator()).image_names == ("around_000", "around_001", "around_002")
        names = list(scene.cameras.image_names)
        names[0], names[1] = "around_001.png", "around2_000.jpg"
        taken = dataclasses.replace(scene, cameras=dataclasses.replace(scene.cameras, image_names=tuple(names)))
        assert around_views(taken, 3, 1.0, torch.Generator()).image_names == ("around3_000", "around3_001",
                                                                               "around3_002")


def test_seen_fraction_is_the_share_of_the_points_in_view():
    """``seen_fraction`` is a fraction in [0, 1] per camera (the blind-candidate note compares it with a tenth of
    the training views'): of four points, one camera looking down +z has two in its image (one is outside it, one
    behind it), one looking down -z has the one behind the first."""
    from uncertsplat.select.candidates import seen_fraction
    from uncertsplat.types import Cameras

    K = torch.tensor([[2.0, 0, 2.0], [0, 2.0, 2.0], [0, 0, 1.0]])
    back = torch.diag(torch.tensor([-1.0, 1.0, -1.0, 1.0]))  # turned half a turn about y
    cams = Cameras(torch.stack([torch.eye(4), back]), K[None].repeat(2, 1, 1), 4, 4, ("ahead", "back"))
    points = torch.tensor([[0.0, 0.0, 2.0], [0.1, 0.1, 1.0], [50.0, 0.0, 2.0], [0.0, 0.0, -1.0]])
    seen = seen_fraction(cams, points)
    assert seen.tolist() == [0.5, 0.25]
    assert seen_fraction(cams[[0]], points[:0]).tolist() == [0.0]


def test_a_candidate_behind_a_surface_from_every_nearby_camera_is_walled_off():
    """A pose under the floor lies where no photo's frame reached, so nothing said it was behind anything, and the
    fisher score ranked it first (2.3x the best real candidate): its way from each of its nearest training cameras
    crosses space the photos saw behind the floor. One clear way is enough (a pose behind a pillar seen from its
    nearest camera)."""
    from types import SimpleNamespace

    from uncertsplat.stages.select import _walled_off

    def seen_behind(points):  # under the floor (z < -1), and inside a thin pillar at x = 1 for y < 0.5
        return (points[:, 2] < -1.0) | ((points[:, 0] - 1.0).abs() < 0.05) & (points[:, 1] < 0.5) & (points[:, 2] > 0)

    looked = SimpleNamespace(seen_behind=seen_behind)
    used = torch.tensor([[0.0, 0.0, 1.0], [0.0, 1.0, 1.0], [0.0, 2.0, 1.0], [3.0, 5.0, 1.0]], dtype=torch.float64)
    cands = torch.tensor([[0.0, 0.5, -3.0],   # under the floor: walled off from all three nearest
                          [0.5, 1.0, 1.0],    # in the open
                          [2.0, 0.0, 1.0],    # behind the pillar from camera 0, clear from camera 1 and 2
                          [0.0, 0.5, -0.5]],  # low, above the floor
                         dtype=torch.float64)
    assert _walled_off(looked, cands, used, torch.device("cpu")).tolist() == [True, False, False, False]
    assert _walled_off(looked, cands[:0], used, torch.device("cpu")).tolist() == []


def test_relative_position_variance_is_the_variance_ratio_of_each_carrier():
    """Each carrier's posterior position std over the prior's (geometric mean over the axes, averaged over the
    entries as raw values), squared: a variance ratio, at most 1; 0 for the Gaussians without a posterior. The
    rows are shuffled against the Gaussians (``random_model``), so a Gaussian must get its own row's ratio."""
    from uncertsplat.gaussians.prior import Prior, inverse_softplus
    from uncertsplat.gaussians.variational import random_model
    from uncertsplat.select.scores import relative_position_variance

    prior = Prior()
    model = random_model(12, torch.Generator().manual_seed(5), sh_degree=0, num_entries=3, carrier_fraction=0.6,
                         prior=prior)
    rows = model.num_carriers
    assert 2 < rows < 12
    # per row, axis factors of the prior's std: geometric means 0.5, 0.8, ... and one above the prior (clamped)
    factors = torch.tensor([[0.25, 0.5, 2.0], [0.8, 0.8, 0.8], [1.5, 2.0, 3.0]]).repeat(rows // 3 + 1, 1)[:rows]
    sigma = (factors * prior.position_std).double()
    model.tables["pos_spread_raw"].data.copy_(inverse_softplus(sigma)[:, None, :].expand_as(
        model.tables["pos_spread_raw"]).float())
    expect_row = (factors.double().log().mean(1).exp().square()).clamp(max=1.0)  # 0.25, 0.64, 1 (9 clamped)
    u = relative_position_variance(model, prior)
    for g in range(len(model)):
        r = int(model.posterior_row[g])
        want = 0.0 if r < 0 else float(expect_row[r])
        assert float(u[g]) == pytest.approx(want, rel=1e-4, abs=1e-7), (g, r)
    # a prior of its own per carrier (the informed posterior's): twice the std, a quarter of the ratio
    own = torch.full((rows,), 2 * prior.position_std)
    u2 = relative_position_variance(model, prior, own)
    idx = model.carrier_index()
    torch.testing.assert_close(u2[idx].double(), (factors.double().log().mean(1).exp() / 2).square().clamp(max=1.0),
                               rtol=1e-4, atol=1e-7)
