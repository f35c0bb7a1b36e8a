"""The observed-pixel labelling (``eval.observed``) on hand-built cameras and depth maps with known answers."""

from __future__ import annotations

import math

import pytest
import torch

from uncertsplat.eval.observed import observed_mask
from uncertsplat.render.project import project_points, unproject

H, W, F, D = 12, 16, 20.0, 5.0
K = torch.tensor([[F, 0.0, W / 2], [0.0, F, H / 2], [0.0, 0.0, 1.0]], dtype=torch.float64)


def cam_at(x: float = 0.0, yaw_deg: float = 0.0) -> torch.Tensor:
    """cam_from_world of a camera at (x, 0, 0), turned by ``yaw_deg`` about the y axis (0: looking at +z)."""
    a = math.radians(yaw_deg)
    R = torch.tensor([[math.cos(a), 0.0, -math.sin(a)], [0.0, 1.0, 0.0], [math.sin(a), 0.0, math.cos(a)]],
                     dtype=torch.float64)
    M = torch.eye(4, dtype=torch.float64)
    M[:3, :3] = R
    M[:3, 3] = -R @ torch.tensor([x, 0.0, 0.0], dtype=torch.float64)
    return M


def plane() -> torch.Tensor:
    """GT depth [H,W] of the wall z = D seen by a camera at the origin looking at +z."""
    return torch.full((H, W), D, dtype=torch.float64)


def label(train_depths, train_cams, depth=None, **kw):
    return observed_mask(plane() if depth is None else depth, cam_at(), K, torch.stack(train_depths),
                         torch.stack(train_cams), K, **kw)


def test_unproject_then_project_gives_the_pixel_centres():
    cam = cam_at(0.3, 20.0)
    pts = unproject(plane() * 1.5, cam, K)  # [H,W,3]
    p = pts @ cam[:3, :3].T + cam[:3, 3]
    uv = p[..., :2] / p[..., 2:] @ K[:2, :2].T + K[:2, 2]
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    torch.testing.assert_close(uv, torch.stack([xs + 0.5, ys + 0.5], -1))
    torch.testing.assert_close(p[..., 2], plane() * 1.5)


def test_project_points_in_several_cameras_at_once_is_each_camera_alone():
    cams = torch.stack([cam_at(0.3, 20.0), cam_at(-1.0, -35.0), cam_at(2.0, 90.0)])  # the last: the wall edge-on
    Ks = torch.stack([K, K * 1.5, K])
    Ks[1, 2, 2] = 1.0
    pts = unproject(plane(), cam_at(), K)  # [H,W,3]
    uv, z = project_points(pts, cams, Ks)
    assert uv.shape == (3, H, W, 2) and z.shape == (3, H, W)
    for c in range(3):
        one_uv, one_z = project_points(pts, cams[c], Ks[c])
        torch.testing.assert_close(uv[c], one_uv, rtol=0, atol=1e-9)
        torch.testing.assert_close(z[c], one_z, rtol=0, atol=1e-12)
    # flat points too, and the round trip of the first camera
    flat_uv, _ = project_points(pts.reshape(-1, 3), cams, Ks)
    torch.testing.assert_close(flat_uv, uv.reshape(3, -1, 2), rtol=0, atol=0)
    back, back_z = project_points(unproject(plane() * 1.5, cams[0], K), cams[0], K)
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    torch.testing.assert_close(back, torch.stack([xs + 0.5, ys + 0.5], -1))
    torch.testing.assert_close(back_z, plane() * 1.5)


def test_the_same_view_observes_everything():
    observed, valid = label([plane()], [cam_at()])
    assert valid.all() and observed.all()


def test_a_shifted_view_observes_only_the_overlap():
    # a camera moved by tx sees the wall shifted by F * tx / D = 10 pixels: test columns >= 10 fall inside it
    observed, _ = label([plane()], [cam_at(x=10 * D / F)])
    assert observed[:, 10:].all() and not observed[:, :10].any()


def test_nearer_surface_hides_the_point():
    occluded = plane().clone()
    occluded[3:7, 4:9] = D / 2  # something in front of the wall in the training view
    observed, valid = label([occluded], [cam_at()])
    assert valid.all()
    assert not observed[3:7, 4:9].any() and observed.sum() == H * W - 4 * 5


def test_any_training_view_suffices():
    left, right = cam_at(x=-10 * D / F), cam_at(x=10 * D / F)  # each sees a different 6-column band
    observed, _ = label([plane(), plane()], [left, right])
    assert observed[:, :6].all() and observed[:, 10:].all() and not observed[:, 6:10].any()


def test_a_camera_looking_away_observes_nothing():
    observed, _ = label([plane()], [cam_at(yaw_deg=180.0)])
    assert not observed.any()


def test_pixels_without_surface_are_neither_valid_nor_observed():
    depth = plane().clone()
    depth[0, 0], depth[1, 1], depth[2, 2] = 0.0, float("inf"), float("nan")
    observed, valid = label([plane()], [cam_at()], depth=depth)
    assert valid.sum() == H * W - 3 and not valid[0, 0] and not valid[1, 1] and not valid[2, 2]
    assert not observed[0, 0] and observed.sum() == H * W - 3


def test_training_pixels_without_depth_do_not_observe():
    holes = plane().clone()
    holes[:, :8] = 0.0  # no GT surface there in the training view (e.g. a masked-out region)
    observed, _ = label([holes], [cam_at()])
    assert not observed[:, :8].any() and observed[:, 8:].all()
    # however wide the tolerance: a depth of 0 is no surface, not one within 100 % of the point's depth
    observed, _ = label([holes], [cam_at()], rel_tol=1.0)
    assert not observed[:, :8].any() and observed[:, 8:].all()


def test_tolerance_decides_at_its_edge():
    farther = plane() * 1.01  # the training view's surface 1 % behind the point
    assert label([farther], [cam_at()], rel_tol=0.02)[0].all()
    assert not label([farther], [cam_at()], rel_tol=0.005)[0].any()
    # relative to the point's depth, not the training view's: a surface 50 % behind is outside 40 % of the point's
    # depth (though inside 40 % of its own)
    assert not label([plane() * 1.5], [cam_at()], rel_tol=0.4)[0].any()
    assert label([plane() * 1.5], [cam_at()], rel_tol=0.5)[0].all()


def test_bad_inputs():
    with pytest.raises(ValueError, match="depth must be"):
        observed_mask(plane()[None], cam_at(), K, plane()[None], cam_at()[None], K)
    with pytest.raises(ValueError, match="train_cam_from_world must be"):
        observed_mask(plane(), cam_at(), K, plane()[None], cam_at(), K)
    with pytest.raises(ValueError, match="rel_tol"):
        observed_mask(plane(), cam_at(), K, plane()[None], cam_at()[None], K, rel_tol=-1.0)


class TestEdges:
    """A zero tolerance (an exact match) is a valid one, and a training view shifted vertically stops at its
    last row (the rows are checked against its height, not its width: H < W here)."""

    def test_a_zero_tolerance_observes_an_exact_match_only(self):
        assert label([plane()], [cam_at()], rel_tol=0.0)[0].all()
        assert not label([plane() * 1.001], [cam_at()], rel_tol=0.0)[0].any()

    def test_a_vertically_shifted_view_observes_only_the_overlap(self):
        # a camera at y = -1 sees the wall shifted by F * 1 / D = 4 rows down: test rows 0..7 land on its rows
        # 4..11, rows 8..11 below its last row (12..15: inside its width of 16, outside its height of 12)
        below = torch.eye(4, dtype=torch.float64)
        below[1, 3] = 4 * D / F
        observed, valid = label([plane()], [below])
        assert valid.all()
        assert observed[:8].all() and not observed[8:].any()
