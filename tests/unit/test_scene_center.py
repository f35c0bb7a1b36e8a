"""The scene centre (sfm/center.py): the optical-axes point of inward-facing rigs, the fallbacks, and what
each kind of scene picks."""

from __future__ import annotations

import math

import pytest
import torch

from uncertsplat.config import SceneConfig, SynthConfig
from uncertsplat.errors import UserError
from uncertsplat.sfm.center import choose_center, fit_optical_axes, random_points
from uncertsplat.sfm.scene import load_scene, normalization
from uncertsplat.types import Cameras

W, H, F = 64, 48, 64.0


def _look_at(center: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """cam_from_world [4,4] (OpenCV axes) of a camera at ``center`` looking at ``target`` (world z up)."""
    z = (target - center) / (target - center).norm()
    up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    x = torch.linalg.cross(z, up)
    x = x / x.norm()
    R = torch.stack([x, torch.linalg.cross(z, x), z])
    M = torch.eye(4, dtype=torch.float64)
    M[:3, :3] = R
    M[:3, 3] = -R @ center
    return M


def _cameras(mats: list[torch.Tensor]) -> Cameras:
    K = torch.tensor([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1]], dtype=torch.float64).expand(len(mats), 3, 3)
    return Cameras(torch.stack(mats), K.clone(), W, H)


def _inward_rig(target, n=12, radius=3.0) -> Cameras:
    """An irregular inward-facing rig: cameras at several elevations and distances, all looking at ``target``."""
    target = torch.tensor(target, dtype=torch.float64)
    mats = []
    for i in range(n):
        az, el = 2 * math.pi * i / n + 0.1 * i, math.radians(15 + 50 * (i % 3) / 2)
        r = radius * (1 + 0.1 * (i % 4))
        c = target + r * torch.tensor([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)],
                                      dtype=torch.float64)
        mats.append(_look_at(c, target))
    return _cameras(mats)


def _forward_rig(n=12) -> Cameras:
    """An LLFF-like capture: cameras on a small plane grid, all looking roughly along +y (a few degrees apart)."""
    g = torch.Generator().manual_seed(0)
    mats = []
    for i in range(n):
        c = torch.tensor([0.3 * (i % 4), 0.0, 0.2 * (i // 4)], dtype=torch.float64)
        jitter = (torch.rand(3, generator=g, dtype=torch.float64) - 0.5) * 0.1  # about +-3 degrees
        mats.append(_look_at(c, c + torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64) + jitter))
    return _cameras(mats)


def test_inward_rig_centre_is_the_target():
    target = (0.7, -1.2, 0.4)
    cams = _inward_rig(target)
    fit = fit_optical_axes(cams)
    assert fit.inward, fit.why
    torch.testing.assert_close(fit.point, torch.tensor(target, dtype=torch.float64), atol=1e-9, rtol=0)
    choice = choose_center(cams, has_points=False)
    assert choice.method == "optical_axes" and "inward-facing" in choice.reason
    # the camera centroid lies well above the target (the bug of issue 17)
    assert (cams.centers.double().mean(0) - choice.center).norm() > 1.0
    # the depth it reports (and measures against the rig's radius) is the median of the cameras' depths
    assert f"{float(fit.depths.median()):.3g} in front of the cameras" in fit.why, fit.why
    assert f"{float(fit.depths.median()) / fit.rig_radius:.2f} x the rig radius" in fit.why, fit.why
    # with sparse points the centroid is kept: COLMAP scenes normalise exactly as before
    kept = choose_center(cams, has_points=True)
    assert kept.method == "camera_centroid" and "sparse points" in kept.reason
    torch.testing.assert_close(kept.center, cams.centers.double().mean(0))


def test_forward_facing_rig_falls_back_to_the_centroid():
    cams = _forward_rig()
    fit = fit_optical_axes(cams)
    assert not fit.inward and "forward-facing" in fit.why, fit.why
    choice = choose_center(cams, has_points=False)
    assert choice.method == "camera_centroid" and "not an inward-facing rig" in choice.reason
    torch.testing.assert_close(choice.center, cams.centers.double().mean(0))


def test_parallel_and_outward_rigs():
    # exactly parallel axes: no point at all; asking for it is a clear error
    mats = [_look_at(torch.tensor([float(i), 0.0, 0.0], dtype=torch.float64),
                     torch.tensor([float(i), 1.0, 0.0], dtype=torch.float64)) for i in range(5)]
    cams = _cameras(mats)
    assert fit_optical_axes(cams).point is None
    with pytest.raises(UserError, match="optical axes"):
        choose_center(cams, has_points=False, mode="optical_axes")
    # cameras on a ring looking outward (a panorama-like rig): the axes meet behind every camera
    out = []
    for i in range(8):
        c = torch.tensor([math.cos(i * math.pi / 4), math.sin(i * math.pi / 4), 0.0], dtype=torch.float64)
        out.append(_look_at(c, 3 * c))
    fit = fit_optical_axes(_cameras(out))
    assert not fit.inward and "in view of only 0%" in fit.why, fit.why
    # forcing a method overrides the test
    assert choose_center(_cameras(out), False, mode="optical_axes").method == "optical_axes"
    assert choose_center(_inward_rig((0, 0, 0)), False, mode="camera_centroid").method == "camera_centroid"


def test_normalisation_moves_the_centre_to_the_origin_and_keeps_the_scale():
    cams = _inward_rig((1.0, 2.0, 3.0))
    T0, s0 = normalization(cams)
    center = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    T, s = normalization(cams, center)
    assert s == s0  # the scale comes from the rig about its centroid, whatever the centre
    torch.testing.assert_close(T[:3, :3], T0[:3, :3])
    torch.testing.assert_close((T @ torch.cat([center, torch.ones(1, dtype=torch.float64)]))[:3],
                               torch.zeros(3, dtype=torch.float64), atol=1e-12, rtol=0)


def test_random_points_fill_the_cube_every_camera_sees():
    cams = _inward_rig((0.5, 0.0, -0.2), radius=4.0)
    choice = choose_center(cams, has_points=False)
    pts, rgb, what = random_points(cams, choice, 5000, torch.Generator().manual_seed(0))
    half = choice.fit.look_distance * (H / 2) / F  # the narrower (vertical) half field of view
    assert pts.shape == (5000, 3) and rgb.shape == (5000, 3) and "optical-axes centre" in what
    d = (pts.double() - choice.center).abs()
    assert d.max() <= half + 1e-5 and d.max() > 0.95 * half
    again, _, _ = random_points(cams, choice, 5000, torch.Generator().manual_seed(0))
    assert torch.equal(pts, again)


def test_random_points_of_a_rig_that_is_not_inward_fill_a_third_of_it():
    """No inward-facing rig: a box around the camera centroid whose side is a third of the rig's extent per axis."""
    cams = _forward_rig()
    choice = choose_center(cams, has_points=False)
    assert choice.method == "camera_centroid"
    pts, _, what = random_points(cams, choice, 4000, torch.Generator().manual_seed(1))
    centres = cams.centers.double()
    half = (centres.max(0).values - centres.min(0).values) / 6.0  # 0.15, 0, 0.067 (the grid: 0.9 x 0 x 0.4)
    d = (pts.double() - centres.mean(0)).abs()
    assert "a third of the camera rig" in what
    assert bool((d <= half + 1e-9).all()) and bool((d.max(0).values >= 0.95 * half).all())


def test_what_each_scene_kind_picks(tmp_path):
    """Synthetic ring/hemisphere scenes in both layouts: COLMAP (sparse points) keeps the camera centroid,
    Blender (no points) takes the optical axes; the hemisphere's centre is its exact look-at point."""
    from uncertsplat.data.synthetic import LOOK_AT, generate_scene

    small = dict(preset="tiny", num_views=8, width=32)
    picks = {}
    for layout in ("colmap", "blender"):
        for rig in ("ring", "hemisphere"):
            out = generate_scene(tmp_path / f"{layout}_{rig}", SynthConfig(**small, layout=layout, rig=rig))
            scene = load_scene(out, SceneConfig(normalize=False))
            picks[layout, rig] = scene.center_method
            if (layout, rig) == ("blender", "hemisphere"):
                torch.testing.assert_close(torch.tensor(scene.center, dtype=torch.float64), torch.tensor(LOOK_AT, dtype=torch.float64),
                                           atol=1e-9, rtol=0)
                assert scene.source["initial_points"].startswith(f"{len(scene.points)} random points")
                norm = load_scene(out)  # normalised: the centre is the world origin
                look = torch.tensor([*LOOK_AT, 1.0], dtype=torch.float64)
                assert (norm.world_from_source.double() @ look)[:3].abs().max() < 1e-6
                assert norm.scene_scale == pytest.approx(1.0, abs=1e-6)
    assert picks == {("colmap", "ring"): "camera_centroid", ("colmap", "hemisphere"): "camera_centroid",
                     ("blender", "ring"): "optical_axes", ("blender", "hemisphere"): "optical_axes"}


def _disc_masks(cams: Cameras, radius: float, scale: int = 1) -> list[torch.Tensor]:
    """Each view's silhouette of a sphere of ``radius`` at the world origin (a disc around its projection, of
    the sphere's angular radius), at 1/``scale`` of the camera resolution."""
    masks = []
    h, w = H // scale, W // scale
    rows, cols = torch.meshgrid(torch.arange(h) + 0.5, torch.arange(w) + 0.5, indexing="ij")
    for M, K in zip(cams.cam_from_world.double(), cams.K.double(), strict=True):
        c = M[:3, 3]  # the origin in camera coordinates
        u, v = (K[0, 0] * c[0] / c[2] + K[0, 2]) / scale, (K[1, 1] * c[1] / c[2] + K[1, 2]) / scale
        r = K[0, 0] * radius / (c.norm() ** 2 - radius**2).sqrt() / scale
        masks.append((cols - u) ** 2 + (rows - v) ** 2 <= r**2)
    return masks


def test_carving_keeps_the_visual_hull():
    """A point inside the object's silhouette in every view survives; one outside it in some view is carved
    away; a view judges only the points in its frustum (a camera looking away, with an empty mask, carves
    nothing) and a view without a mask (None) judges nothing, but a point that no masked view sees goes; masks
    may be smaller than the images."""
    from uncertsplat.sfm.center import carve_points

    rig = _inward_rig((0.0, 0.0, 0.0), radius=3.0)
    away = _look_at(torch.tensor([0.0, 0.0, 5.0], dtype=torch.float64), torch.tensor([0.0, 0.0, 9.0], dtype=torch.float64))
    cams = _cameras([*rig.cam_from_world.double(), away])
    masks = [*_disc_masks(rig, 0.5, scale=2), torch.zeros(H // 2, W // 2, dtype=torch.bool)]
    inside = torch.tensor([[0.0, 0.0, 0.0], [0.2, -0.1, 0.15], [0.0, 0.3, -0.2]])
    outside = torch.tensor([[1.2, 0.0, 0.0], [0.0, -0.9, 0.3], [0.6, 0.6, 0.0]])
    keep = carve_points(torch.cat([inside, outside]), cams, masks)
    assert keep.tolist() == [True] * 3 + [False] * 3
    # A view that sees the point inside its frustum but outside its silhouette: the point goes.
    looked_at = _cameras([_look_at(torch.tensor([3.0, 0.0, 0.0], dtype=torch.float64),
                                   torch.tensor([0.0, 0.0, 0.0], dtype=torch.float64))])
    assert carve_points(outside[2:], looked_at, _disc_masks(looked_at, 0.5)).tolist() == [False]
    assert not carve_points(outside, cams, [None] * len(masks)).any()  # seen by no view with a mask
    assert carve_points(outside, cams, [*[None] * len(rig), masks[-1]]).tolist() == [False] * 3
    assert carve_points(inside, cams, [masks[0], *[None] * len(rig)]).all()


def test_carving_scales_a_mask_by_its_own_width_and_height_and_stops_at_its_edge():
    """A mask of another aspect than the image (4 x 4 for a 8 x 4 image: columns halved, rows kept) is read at
    u w / width, v h / height; a point exactly on the image's right edge (u = width) lies outside it (pixel c covers
    [c, c + 1)), so that view does not judge it."""
    from uncertsplat.sfm.center import carve_points

    K = torch.tensor([[8.0, 0, 4], [0, 8.0, 2], [0, 0, 1]], dtype=torch.float64)
    cams = Cameras(torch.eye(4, dtype=torch.float64)[None], K[None], 8, 4)
    mask = torch.zeros(4, 4, dtype=torch.bool)
    mask[:, 1] = True  # image columns 2-3
    # u = 8 x + 4 at z = 1, v = 8 y + 2: u 2.5 (mask column 1.25), u 5 (2.5), v 2.5 (row 2.5) for both
    pts = torch.tensor([[-0.1875, 0.0625, 1.0], [0.125, 0.0625, 1.0]])
    assert carve_points(pts, cams, [mask]).tolist() == [True, False]
    wide = torch.ones(4, 4, dtype=torch.bool)
    edge = torch.tensor([[0.5, 0.0, 1.0], [0.0, 0.25, 1.0]])  # u = 8 exactly; v = 4 exactly
    both = Cameras(torch.eye(4, dtype=torch.float64).expand(2, 4, 4).clone(), K.expand(2, 3, 3).clone(), 8, 4)
    # seen by neither view (on the edges): carved as seen by no view with a mask, not an index error
    assert carve_points(edge, both, [wide, wide]).tolist() == [False, False]


def test_carved_random_points_lie_in_the_hull():
    """random_points with masks: n points, all inside the visual hull, deterministic, and described."""
    from uncertsplat.sfm.center import carve_points

    cams = _inward_rig((0.0, 0.0, 0.0), radius=3.0)
    choice = choose_center(cams, has_points=False)
    masks = _disc_masks(cams, 0.4)
    pts, rgb, what = random_points(cams, choice, 2000, torch.Generator().manual_seed(0), carve=(cams, masks))
    assert pts.shape == (2000, 3) and rgb.shape == (2000, 3)
    assert carve_points(pts, cams, masks).all()
    assert pts.double().norm(dim=-1).max() < 0.6  # the hull of 12 views hugs the sphere of radius 0.4
    assert f"carved with the alpha masks of {len(cams)} views" in what and "candidates fell inside them" in what
    again, _, _ = random_points(cams, choice, 2000, torch.Generator().manual_seed(0), carve=(cams, masks))
    assert torch.equal(pts, again)
    # No candidate inside the masks: the points are not carved, and the description says so.
    empty = [torch.zeros(H, W, dtype=torch.bool)] * len(cams)
    pts, _, what = random_points(cams, choice, 100, torch.Generator().manual_seed(0), carve=(cams, empty))
    assert pts.shape == (100, 3) and "not carved" in what


def test_scenes_carve_only_with_transparent_images(tmp_path):
    """A Blender folder with a transparent backdrop carves its random points; an opaque one does not, and
    scene.carve = false turns carving off."""
    from uncertsplat.data.synthetic import generate_scene

    small = dict(preset="tiny", num_views=8, width=32, layout="blender", rig="hemisphere")
    clear = load_scene(generate_scene(tmp_path / "clear", SynthConfig(**small, backdrop="transparent")))
    assert "carved with the alpha masks of" in clear.source["initial_points"]
    off = load_scene(tmp_path / "clear", SceneConfig(carve=False))
    assert "carved" not in off.source["initial_points"]
    opaque = load_scene(generate_scene(tmp_path / "opaque", SynthConfig(**small)))
    assert "carved" not in opaque.source["initial_points"]


def test_rendering_loads_skip_the_initial_points(tmp_path, monkeypatch):
    """``initial_points=False`` (what loading a trained run does) reads no alpha mask and makes no points, and
    leaves the cameras, split, normalisation and centre exactly as a training load has them."""
    from uncertsplat.data.synthetic import generate_scene
    from uncertsplat.io import images

    path = generate_scene(tmp_path / "clear", SynthConfig(preset="tiny", num_views=8, width=32, layout="blender",
                                                         rig="hemisphere", backdrop="transparent"))
    full = load_scene(path)
    assert full.points.shape[0] > 0

    def no_alpha(p):
        raise AssertionError(f"read the alpha of {p}")

    monkeypatch.setattr(images, "read_alpha", no_alpha)
    light = load_scene(path, initial_points=False)
    assert light.points.shape == (0, 3)
    torch.testing.assert_close(light.cameras.cam_from_world, full.cameras.cam_from_world, rtol=0, atol=0)
    torch.testing.assert_close(light.world_from_source, full.world_from_source, rtol=0, atol=0)
    assert light.split == full.split and light.center == full.center and light.scene_scale == full.scene_scale


class TestInwardBounds:
    """The acceptance tests' edges: in view of exactly ``MIN_IN_VIEW`` of the cameras is enough, and a point
    nearer to the cameras than ``MIN_LOOK_DISTANCE`` x the rig radius is no inward rig's centre."""

    def test_in_view_of_exactly_the_minimum_fraction_is_enough(self):
        from uncertsplat.sfm.center import MIN_IN_VIEW

        target = (0.2, 0.1, -0.3)
        for hidden, inward in ((2, True), (3, False)):
            rig = _inward_rig(target, n=10)
            K = rig.K.clone()
            K[:hidden, 0, 2] = -10.0  # the point (on every optical axis) lands at u = -10 there: out of view
            fit = fit_optical_axes(Cameras(rig.cam_from_world, K, W, H))
            assert fit.in_view == pytest.approx(1 - hidden / 10, abs=0)
            assert fit.inward is inward, fit.why
        assert MIN_IN_VIEW == 0.8

    def test_a_point_nearer_than_the_minimum_look_distance_is_refused(self):
        from uncertsplat.sfm.center import MIN_LOOK_DISTANCE

        target = torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64)
        near = [(1.0, 0.2, 0.3), (-1.0, 0.1, 0.2), (0.2, 1.0, -0.3), (0.1, -1.0, 0.4), (0.3, 0.2, 1.0)]
        far = [(1.0, 0.3, 0.3), (1.0, -0.3, 0.3), (1.0, 0.3, -0.3), (1.0, -0.3, -0.3)]
        mats = []
        # five cameras 0.01 from the point, four 100 away on one side
        for dirs, dist in ((near, 0.01), (far, 100.0)):
            for d in dirs:
                d = torch.tensor(d, dtype=torch.float64)
                mats.append(_look_at(target + dist * d / d.norm(), target))
        fit = fit_optical_axes(_cameras(mats))
        torch.testing.assert_close(fit.point, target, atol=1e-9, rtol=0)
        assert fit.in_view == 1.0 and fit.spread > 0.1
        assert fit.look_distance == pytest.approx(0.01, rel=1e-6)  # the median camera is a near one
        assert fit.look_distance / fit.rig_radius < MIN_LOOK_DISTANCE
        assert not fit.inward and "x the rig radius from the cameras (outside 0.05..4.0)" in fit.why, fit.why
