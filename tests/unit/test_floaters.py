"""Free-space labels against GT depth, and the ranking AUC used by the pruning benchmark."""

import math

import pytest
import torch

from uncertsplat.eval.floaters import label_floaters, ranking_auc
from uncertsplat.types import Cameras


def _cams(num: int, width=40, height=30, focal=40.0) -> Cameras:
    """``num`` cameras at the origin looking down +z (identity pose), translated along x by 0.1 each."""
    cw = torch.eye(4).repeat(num, 1, 1)
    cw[:, 0, 3] = -0.1 * torch.arange(num, dtype=torch.float32)
    K = torch.tensor([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1.0]]).repeat(num, 1, 1)
    return Cameras(cw, K, width, height)


class TestLabelFloaters:
    def test_wall_in_front_on_and_behind(self):
        cams = _cams(2)
        depths = torch.full((2, 30, 40), 2.0)  # a wall at z = 2 in both views
        means = torch.tensor([[0.0, 0.0, 1.0],  # in free space, half-way to the wall
                              [0.0, 0.0, 2.0],  # on the wall
                              [0.0, 0.0, 3.0],  # behind the wall
                              [0.0, 0.0, 1.99]])  # 1 cm in front of the wall: inside the margin
        scales = torch.full((4, 3), 0.01)
        lab = label_floaters(means, scales, cams, depths, extent=1.0)
        assert lab.is_floater.tolist() == [True, False, False, False]
        assert lab.num_views.tolist() == [2, 2, 2, 2]
        assert lab.gap.tolist() == pytest.approx([1.0, 0.0, -1.0, 0.01], abs=1e-6)

    def test_one_view_on_the_surface_is_enough(self):
        cams = _cams(2)
        depths = torch.stack([torch.full((30, 40), 2.0), torch.full((30, 40), 5.0)])
        lab = label_floaters(torch.tensor([[0.05, 0.0, 2.0]]), torch.full((1, 3), 0.01), cams, depths, extent=1.0)
        assert not lab.is_floater[0] and lab.num_views[0] == 2

    def test_large_gaussians_get_a_larger_margin(self):
        cams = _cams(1)
        depths = torch.full((1, 30, 40), 2.0)
        means = torch.tensor([[0.0, 0.0, 1.8], [0.0, 0.0, 1.8]])
        scales = torch.tensor([[0.01] * 3, [0.1] * 3])  # margins 0.04 and 0.31
        assert label_floaters(means, scales, cams, depths, extent=1.0).is_floater.tolist() == [True, False]

    def test_a_flat_gaussian_gets_the_margin_of_its_largest_axis(self):
        """A flat Gaussian (a splat lying along a surface) 0.25 in front of a wall: its largest axis, 0.1, gives a
        margin of 3 x 0.1 + 0.01 = 0.31 and keeps it off the floaters; its mean axis (0.067) would give 0.211."""
        cams = _cams(1)
        depths = torch.full((1, 30, 40), 2.0)
        lab = label_floaters(torch.tensor([[0.0, 0.0, 1.75]]), torch.tensor([[0.1, 0.1, 0.001]]), cams, depths,
                             extent=1.0)
        assert lab.gap.tolist() == pytest.approx([0.25], abs=1e-6)
        assert lab.is_floater.tolist() == [False]

    def test_outside_every_view_or_behind_the_camera_is_not_labelled(self):
        cams = _cams(1)
        depths = torch.full((1, 30, 40, 1), 2.0)  # [C,H,W,1] is accepted too
        means = torch.tensor([[50.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
        lab = label_floaters(means, torch.full((2, 3), 0.01), cams, depths, extent=1.0)
        assert lab.is_floater.tolist() == [False, False] and lab.num_views.tolist() == [0, 0]
        assert math.isinf(lab.gap[0]) and math.isinf(lab.gap[1])

    def test_no_surface_means_free_space(self):
        cams = _cams(1)
        depths = torch.zeros(1, 30, 40)  # no GT surface anywhere (e.g. sky)
        lab = label_floaters(torch.tensor([[0.0, 0.0, 1.0]]), torch.full((1, 3), 0.01), cams, depths, extent=1.0)
        assert lab.is_floater[0]


class TestRankingAuc:
    def test_perfect_inverted_and_random(self):
        pos = torch.tensor([True, True, False, False])
        assert ranking_auc(torch.tensor([3.0, 4.0, 1.0, 2.0]), pos) == 1.0
        assert ranking_auc(torch.tensor([1.0, 2.0, 3.0, 4.0]), pos) == 0.0
        assert ranking_auc(torch.zeros(4), pos) == 0.5  # all tied

    def test_matches_pairwise_count(self):
        g = torch.Generator().manual_seed(0)
        s = torch.randint(0, 5, (60,), generator=g).float()  # many ties
        pos = torch.rand(60, generator=g) < 0.3
        sp, sn = s[pos], s[~pos]
        pairs = (sp[:, None] > sn[None, :]).double() + 0.5 * (sp[:, None] == sn[None, :]).double()
        assert ranking_auc(s, pos) == pytest.approx(float(pairs.mean()), abs=1e-12)

    def test_candidates_and_empty_sets(self):
        pos = torch.tensor([True, False, True])
        cand = torch.tensor([True, True, False])
        assert ranking_auc(torch.tensor([2.0, 1.0, -5.0]), pos, cand) == 1.0
        assert math.isnan(ranking_auc(torch.ones(3), torch.zeros(3, dtype=torch.bool)))
