"""The view-consistency term (``uncertainty.consistency``) against closed forms, with a renderer of a plane whose
colour depends on the camera (so the two renders of a point differ by a known amount)."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from uncertsplat.types import Cameras, GaussianSample, RenderOutput
from uncertsplat.uncertainty import consistency
from uncertsplat.uncertainty.consistency import (
    DEPTH_JUMP,
    GATE_SPACINGS,
    MIN_GATE,
    ViewConsistency,
    _depth_edges,
    capture_spacing,
)

W, H = 32, 24


def _cameras(azimuths_deg, focal=40.0, width=W, height=H, device="cpu") -> Cameras:
    """Cameras 4 units from the origin at these azimuths (about the y axis, 0 = on the -z axis), looking at it."""
    mats = []
    for a in azimuths_deg:
        a = math.radians(a)
        eye = torch.tensor([4 * math.sin(a), 0.0, -4 * math.cos(a)], dtype=torch.float64)
        fwd = -eye / eye.norm()
        down = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
        right = torch.linalg.cross(down, fwd)
        rot = torch.stack([right, down, fwd])
        m = torch.eye(4, dtype=torch.float64)
        m[:3, :3] = rot
        m[:3, 3] = -rot @ eye
        mats.append(m)
    K = torch.tensor([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1.0]], dtype=torch.float64)
    n = len(mats)
    return Cameras(torch.stack(mats).float(), K.float().repeat(n, 1, 1), width, height,
                   tuple(f"v{i}.png" for i in range(n))).to(device)


def _colour(cam: Cameras) -> float:
    """The plane's colour seen from ``cam``: grows with the camera's azimuth."""
    c = cam.centers[0]
    return 0.3 + 0.4 * math.atan2(float(c[0]), -float(c[2]))


def _plane_render(nearer: frozenset = frozenset()):
    """A renderer of the plane z = 0 (every pixel covered) in the colour ``_colour`` of the camera; for cameras whose
    rounded azimuth is in ``nearer``, something at half the depth hides it."""
    def render_fn(sample: GaussianSample, cameras: Cameras) -> RenderOutput:
        assert len(cameras) == 1
        dev = cameras.cam_from_world.device  # the outputs go where the cameras are; the plane is traced on the CPU
        cameras = cameras.to("cpu")
        cw = cameras.cam_from_world[0].double()
        rot, centre = cw[:3, :3], cameras.centers[0].double()
        ys, xs = torch.meshgrid(torch.arange(cameras.height, dtype=torch.float64),
                                torch.arange(cameras.width, dtype=torch.float64), indexing="ij")
        pix = torch.stack([xs + 0.5, ys + 0.5, torch.ones_like(xs)], -1)
        ray_cam = pix @ torch.linalg.inv(cameras.K[0].double()).T  # z = 1
        ray_world = ray_cam @ rot  # R^T applied to each ray
        depth = -centre[2] / ray_world[..., 2]  # camera z of the ray's point on z = 0
        azimuth = round(math.degrees(math.atan2(float(centre[0]), -float(centre[2]))))
        if azimuth in nearer:
            depth = depth * 0.5
        rgb = torch.full((1, cameras.height, cameras.width, 3), _colour(cameras), dtype=torch.float32, device=dev)
        one = torch.ones(1, cameras.height, cameras.width, 1, device=dev)
        d = depth.float()[None, ..., None].to(dev)
        return RenderOutput(rgb=rgb, alpha=one, depth=d, depth_expected=d, means2d=torch.zeros(1, 1, 2, device=dev),
                            radii=torch.zeros(1, 1, device=dev))

    return render_fn


def _sample(device="cpu") -> GaussianSample:
    return GaussianSample(means=torch.zeros(1, 3), quats=torch.tensor([[1.0, 0, 0, 0]]), scales=torch.full((1, 3), 0.1),
                          opacities=torch.ones(1), sh=torch.zeros(1, 1, 3), sh_degree=0).to(device)


def _term(train_azimuths, gate, render_fn=None, device="cpu"):
    render_fn = render_fn or _plane_render()
    vc = ViewConsistency.of(_sample(device), _cameras(train_azimuths, focal=6.0, device=device),
                            render_fn)  # wide training views
    return dataclasses.replace(vc, gate=gate), render_fn


class TestViewConsistency:
    def test_beyond_twice_the_gate_it_is_the_squared_difference_from_the_nearest_training_direction(self):
        """Training views at 0 and 50 degrees, the evaluated one at 38 (a narrow view, inside both): the nearest
        direction is the 50-degree view's, 12 degrees off, beyond twice a 4-degree gate: the term is the squared
        difference of the two colours everywhere."""
        vc, render_fn = _term([0.0, 50.0], gate=4.0)
        test = _cameras([38.0], focal=60.0)
        var = vc.variance(test, render_fn)
        assert var.shape == (1, H, W, 1)
        expect = (_colour(test) - _colour(_cameras([50.0]))) ** 2
        torch.testing.assert_close(var, torch.full_like(var, expect), rtol=1e-2, atol=1e-6)  # the renders kept as float16

    def test_within_the_gate_nothing_and_in_between_part(self):
        vc, render_fn = _term([0.0, 50.0], gate=20.0)
        test = _cameras([38.0], focal=60.0)
        assert float(vc.variance(test, render_fn).abs().max()) == 0.0  # 12 degrees < 20
        part, _ = _term([0.0, 50.0], gate=8.0)  # 12 degrees: weight (12 - 8) / 8 = 0.5 at the image centre
        var = part.variance(test, render_fn)
        full = (_colour(test) - _colour(_cameras([50.0]))) ** 2
        assert float(var[0, H // 2, W // 2, 0]) == pytest.approx(0.5 * full, rel=0.05)

    def test_a_training_view_itself_gets_nothing(self):
        """Another camera at the place of a training view (narrower) is 0 degrees off it; a compared training view
        itself is 0 without a render."""
        vc, render_fn = _term([0.0, 50.0], gate=MIN_GATE)
        assert float(vc.variance(_cameras([50.0], focal=60.0), render_fn).abs().max()) == 0.0

        def no_render(sample, cameras):
            raise AssertionError("a compared training view needs no render")

        own = vc.cameras[[1]]
        assert vc.variance(own, no_render).shape == (1, own.height, own.width, 1)
        assert float(vc.variance(own, no_render).abs().max()) == 0.0

    def test_a_training_view_that_does_not_see_the_point_is_passed_over(self):
        """The 50-degree view renders something nearer than the plane: the point is hidden there, so the 0-degree
        view (38 degrees off) is the one compared."""
        render_fn = _plane_render(nearer=frozenset({50}))
        vc, _ = _term([0.0, 50.0], gate=4.0, render_fn=render_fn)
        test = _cameras([38.0], focal=60.0)
        expect = (_colour(test) - _colour(_cameras([0.0]))) ** 2
        var = vc.variance(test, render_fn)
        torch.testing.assert_close(var, torch.full_like(var, expect), rtol=1e-2, atol=1e-6)  # the renders kept as float16

    def test_views_compared_in_batches_choose_as_one_by_one(self, monkeypatch, device):
        """Ten training views (more than one batch of ``VIEW_CHUNK``), the nearest direction in the last batch and a
        hidden one nearer still: the same map with batches of 1, 3 and the default, and the expected colour."""
        azimuths = [-60.0, -45.0, -30.0, -20.0, -10.0, 0.0, 10.0, 20.0, 30.0, 52.0, -70.0, -80.0]  # farther ones last
        render_fn = _plane_render(nearer=frozenset({30}))
        vc, _ = _term(azimuths, gate=2.0, render_fn=render_fn, device=device)
        test = _cameras([40.0], focal=60.0, device=device)  # 10 degrees from the hidden 30, 12 from 52: the visible 52 wins
        monkeypatch.setenv("UNCERTSPLAT_RASTERIZER", "torch")  # (the native lookup takes every view in one pass)
        maps = {}
        for chunk in (1, 3, consistency.VIEW_CHUNK):
            monkeypatch.setattr(consistency, "VIEW_CHUNK", chunk)
            maps[chunk] = vc.variance(test, render_fn)
        assert len(azimuths) > consistency.VIEW_CHUNK
        assert torch.equal(maps[1], maps[3]) and torch.equal(maps[1], maps[consistency.VIEW_CHUNK])
        expect = (_colour(test) - _colour(_cameras([52.0]))) ** 2
        torch.testing.assert_close(maps[1], torch.full_like(maps[1], expect), rtol=1e-2, atol=1e-6)

    def test_no_surface_and_no_seeing_view_give_zeros_and_one_camera_at_a_time(self):
        vc, render_fn = _term([0.0], gate=4.0)

        def empty(sample, cameras):
            out = render_fn(sample, cameras)
            return dataclasses.replace(out, alpha=torch.zeros_like(out.alpha))

        test = _cameras([40.0], focal=60.0)
        assert float(vc.variance(test, empty).abs().max()) == 0.0
        hidden = _plane_render(nearer=frozenset({0}))
        vc_hidden, _ = _term([0.0], gate=4.0, render_fn=hidden)
        assert float(vc_hidden.variance(test, hidden).abs().max()) == 0.0
        with pytest.raises(ValueError, match="one camera"):
            vc.variance(_cameras([10.0, 20.0]), render_fn)
        with pytest.raises(ValueError, match="at least one training camera"):
            ViewConsistency.of(_sample(), _cameras([0.0])[[]], render_fn)

    def test_a_point_no_training_camera_looked_at_gets_the_palettes_variance(self, device):
        """Training views at 0 and 50 degrees, a wider evaluated one at 20: its centre is seen from both (20 and 30
        degrees off, beyond twice a 4-degree gate; the 0-degree view is the nearer), its corners lie outside both
        training images and get the variance of the training renders' colours (here two constants over equal
        areas: (c50 - c0)^2 / 4, times n / (n - 1)); nothing without a palette, or when another (not compared)
        training camera's image holds the corners."""
        render_fn = _plane_render()
        vc = dataclasses.replace(ViewConsistency.of(_sample(device), _cameras([0.0, 50.0], focal=30.0, device=device),
                                                    render_fn), gate=4.0)
        c0, c50 = _colour(_cameras([0.0])), _colour(_cameras([50.0]))
        n = 2 * H * W
        assert vc.palette_var == pytest.approx((c50 - c0) ** 2 / 4 * n / (n - 1), rel=1e-5)
        test = _cameras([20.0], focal=14.0, device=device)
        d0 = (_colour(test) - c0) ** 2
        var = vc.variance(test, render_fn)[0, ..., 0]
        assert var.device.type == torch.device(device).type
        assert float(var[H // 2, W // 2]) == pytest.approx(d0, rel=0.02)  # seen: its own difference
        for corner in (float(var[0, 0]), float(var[0, -1]), float(var[-1, -1])):
            assert corner == pytest.approx(vc.palette_var, rel=1e-3)
        assert float(dataclasses.replace(vc, palette_var=0.0).variance(test, render_fn)[0, 0, -1, 0]) == 0.0
        wide = dataclasses.replace(vc, frustum_cameras=_cameras([0.0, 50.0, 20.0], focal=6.0, device=device))
        looked = wide.variance(test, render_fn)[0, ..., 0]
        assert float(looked[0, -1]) == 0.0  # a training camera held the corner: not "never looked at"
        assert float(looked[H // 2, W // 2]) == pytest.approx(d0, rel=0.02)

    def test_a_point_every_compared_view_holds_but_none_sees_gets_the_palette_by_the_angle(self, device):
        """Both training views render something nearer than the plane (the far side of an object: every camera looks
        at it, so its points lie inside the images that do not see them): the plane's point is hidden in both, and gets
        the palette's variance weighted as a seen point's difference, by the angle to the nearest view whose image
        holds it (the evaluated view at 38 degrees, the 50-degree view 12 degrees off): in full beyond twice the gate,
        half at 12 / 8, nothing within it. (Before, such a point got nothing: an object capture's unseen side had
        less variance than its seen side, RGB AUC 0.68.)"""
        hidden = _plane_render(nearer=frozenset({0, 50}))
        base = ViewConsistency.of(_sample(device), _cameras([0.0, 50.0], focal=6.0, device=device), hidden)
        assert base.palette_var > 0.0
        test = _cameras([38.0], focal=60.0, device=device)
        centre = {g: float(dataclasses.replace(base, gate=g).variance(test, _plane_render())[0, H // 2, W // 2, 0])
                  for g in (4.0, 8.0, 20.0)}
        assert centre[4.0] == pytest.approx(base.palette_var, rel=1e-3)
        with pytest.MonkeyPatch.context() as mp:  # the angles in blocks of points: the same
            mp.setattr(consistency, "POINTS_CHUNK", 7)
            blocks = dataclasses.replace(base, gate=4.0).variance(test, _plane_render())
        torch.testing.assert_close(blocks, dataclasses.replace(base, gate=4.0).variance(test, _plane_render()))
        assert centre[8.0] == pytest.approx(0.5 * base.palette_var, rel=0.05)
        assert centre[20.0] == 0.0
        assert float(dataclasses.replace(base, gate=4.0, palette_var=0.0).variance(
            test, _plane_render()).abs().max()) == 0.0
        # only a view whose image holds the point counts: a narrow view at 40 degrees holds the plane's centre (2
        # degrees from a wide view at 38: within the gate) but not the far points at that view's right edge, which
        # take the angle to the wide 0-degree view (38 degrees: in full; its left half looks past the plane)
        wide, narrow = _cameras([0.0], focal=6.0, device=device), _cameras([40.0], focal=60.0, device=device)
        train = Cameras(torch.cat([wide.cam_from_world, narrow.cam_from_world]), torch.cat([wide.K, narrow.K]), W, H,
                        ("wide.png", "narrow.png")).to(device)
        held = dataclasses.replace(ViewConsistency.of(_sample(device), train, _plane_render(nearer=frozenset({0, 40}))),
                                   gate=4.0)
        var = held.variance(_cameras([38.0], focal=14.0, device=device), _plane_render())
        assert float(var[0, H // 2, W // 2, 0]) < 0.1 * held.palette_var
        assert float(var[0, 0, W - 1, 0]) == pytest.approx(held.palette_var, rel=1e-3)

    def test_rays_through_space_no_photo_saw_empty_on_transparent_scenes(self, device):
        """``unseen_empty`` (transparent training photos: no empty-ray term): a ray of the evaluated view that meets
        little of the model, through space behind what the training views rendered (no photo saw it empty), gets
        ``(1 - alpha)^2`` times the palette's variance; nothing without the flag or where the ray is opaque."""
        render_fn = _plane_render()
        sample = GaussianSample(means=torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, 1.5]]),
                                quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(2, 1), scales=torch.full((2, 3), 0.1),
                                opacities=torch.ones(2), sh=torch.zeros(2, 1, 3), sh_degree=0).to(device)
        vc = dataclasses.replace(ViewConsistency.of(sample, _cameras([0.0, 50.0], focal=6.0, device=device),
                                                    render_fn), gate=4.0)
        test = _cameras([20.0], focal=60.0, device=device)

        def faint(alpha):
            def fn(s, cameras):
                out = render_fn(s, cameras)
                return dataclasses.replace(out, alpha=torch.full_like(out.alpha, alpha),
                                           depth=torch.zeros_like(out.depth))
            return fn

        assert float(vc.variance(test, faint(0.0)).abs().max()) == 0.0  # (not asked for: an opaque-photo scene)
        on = dataclasses.replace(vc, unseen_empty=True)
        for alpha in (0.0, 0.5):
            var = on.variance(test, faint(alpha))[0, ..., 0]
            torch.testing.assert_close(var, torch.full_like(var, (1 - alpha) ** 2 * vc.palette_var), rtol=1e-4,
                                       atol=0)
        assert float(on.variance(test, faint(1.0)).abs().max()) == 0.0
        # the depth percentiles of a subsample of the Gaussians (torch.quantile takes at most 2^24 values)
        many = dataclasses.replace(on, sample=GaussianSample(
            means=torch.linspace(-1.0, 1.5, 1000)[:, None] * torch.tensor([[0.0, 0.0, 1.0]]),
            quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(1000, 1), scales=torch.full((1000, 3), 0.1),
            opacities=torch.ones(1000), sh=torch.zeros(1000, 1, 3), sh_degree=0).to(device))
        sizes, quantile = [], torch.quantile
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(consistency, "QUANTILE_POINTS", 100)
            mp.setattr(torch, "quantile", lambda x, *a, **k: sizes.append(x.numel()) or quantile(x, *a, **k))
            var = many.variance(test, faint(0.0))[0, ..., 0]
        assert sizes and max(sizes) <= 100
        # the depth of a faint ray through unseen space (no surface point: alpha < MIN_ALPHA): an unknown surface
        # anywhere between the model's nearest and farthest Gaussians, (1 - alpha)^2 (hi - lo)^2 / 12
        _, z = consistency.project_points(sample.means.float(), test.cam_from_world.float(), test.K.float())
        lo, hi = torch.quantile(z[0], torch.tensor([0.01, 0.99], device=z.device)).tolist()
        for alpha, weight in ((0.0, 1.0), (0.25, 0.5625), (0.6, 0.0)):  # (0.6: a surface point, its own terms)
            _, depth_var = on.variances(test, faint(alpha))
            torch.testing.assert_close(depth_var[0, ..., 0], torch.full((H, W), weight * (hi - lo) ** 2 / 12.0,
                                                                        device=depth_var.device), rtol=1e-4, atol=0)
        assert float(vc.variances(test, faint(0.0))[1].abs().max()) == 0.0  # (opaque photos: not this term)
        # a model of one flat colour (palette variance 0): no colour term, the depth term all the same
        flat_rgb, flat_depth = dataclasses.replace(on, palette_var=0.0).variances(test, faint(0.0))
        assert float(flat_rgb.abs().max()) == 0.0
        torch.testing.assert_close(flat_depth[0, ..., 0], torch.full((H, W), (hi - lo) ** 2 / 12.0,
                                                                     device=flat_depth.device), rtol=1e-4, atol=0)
        torch.testing.assert_close(var, torch.full_like(var, vc.palette_var), rtol=1e-4, atol=0)

    def test_the_palette_counts_only_surface_pixels(self, device):
        """Pixels without a surface (alpha below ``MIN_ALPHA``: the background of an object scene) are not colours of
        the scene; a single colour has no variance."""
        render_fn = _plane_render()

        def half_empty(sample, cameras):
            out = render_fn(sample, cameras)
            alpha = out.alpha.clone()
            alpha[:, :, : W // 2] = 0.0
            rgb = out.rgb.clone()
            rgb[:, :, : W // 2] = 0.9  # the background's colour
            return dataclasses.replace(out, alpha=alpha, rgb=rgb)

        one = ViewConsistency.of(_sample(device), _cameras([10.0], device=device), half_empty)
        assert one.palette_var == 0.0
        two = ViewConsistency.of(_sample(device), _cameras([0.0, 50.0], device=device), half_empty)
        full = ViewConsistency.of(_sample(device), _cameras([0.0, 50.0], device=device), render_fn)
        n, m = 2 * H * W, H * W
        assert two.palette_var == pytest.approx(full.palette_var * (n - 1) / n * m / (m - 1), rel=1e-5)

        def two_pixels(sample, cameras):  # the fewest surface pixels with a variance: 0.2 and 0.6
            out = render_fn(sample, cameras)
            alpha = torch.zeros_like(out.alpha)
            alpha[:, 0, :2] = 1.0
            rgb = out.rgb.clone()
            rgb[:, 0, 0], rgb[:, 0, 1] = 0.2, 0.6
            return dataclasses.replace(out, alpha=alpha, rgb=rgb)

        pair = ViewConsistency.of(_sample(device), _cameras([10.0], device=device), two_pixels)
        assert pair.palette_var == pytest.approx(0.08, rel=1e-5)  # ((0.2 - 0.4)^2 + (0.6 - 0.4)^2) / (2 - 1)

    def test_the_fraction_of_a_view_no_training_camera_looked_at(self, device):
        """The wide view at 20 degrees sees the plane beyond both narrow training images at its corners: a part of
        its surface, neither none nor all; none once a training camera's image holds it, none for a compared view
        and for a view without surface; ``evaluate`` names the views from 5 % on."""
        from types import SimpleNamespace

        from uncertsplat.stages.evaluate import UNLOOKED_NOTE, _reach_notes

        render_fn = _plane_render()
        narrow = _cameras([0.0, 50.0], focal=30.0, device=device)
        vc = ViewConsistency.of(_sample(device), narrow, render_fn)
        test = _cameras([20.0], focal=14.0, device=device)
        part = vc.unlooked_fraction(test, render_fn)
        assert 0.1 < part < 0.9
        wide = dataclasses.replace(vc, frustum_cameras=_cameras([0.0, 50.0, 20.0], focal=6.0, device=device))
        assert wide.unlooked_fraction(test, render_fn) == 0.0
        assert vc.unlooked_fraction(narrow[[1]], render_fn) == 0.0

        def empty(sample, cameras):
            out = render_fn(sample, cameras)
            return dataclasses.replace(out, alpha=torch.zeros_like(out.alpha))

        assert vc.unlooked_fraction(test, empty) == 0.0
        inside = _cameras([20.0], focal=60.0, device=device)  # narrow: all of it inside the training images
        assert vc.unlooked_fraction(inside, render_fn) < UNLOOKED_NOTE
        both = dataclasses.replace(test, cam_from_world=torch.cat([test.cam_from_world, inside.cam_from_world]),
                                   K=torch.cat([test.K, inside.K]), image_names=("wide.png", "narrow.png"))
        views = SimpleNamespace(cameras=both, names=["wide.png", "narrow.png"])
        notes = _reach_notes(SimpleNamespace(consistency=vc, render_fn=render_fn), views, torch.device(device))
        note = next(n for n in notes if "no training photo had in view" in n)
        assert note.startswith("1 of 2 views") and f"wide.png {100 * part:.0f} %" in note and "narrow" not in note
        assert _reach_notes(SimpleNamespace(consistency=None, render_fn=render_fn), views, torch.device(device)) == []

    def test_the_scale_at_which_a_view_resolves_the_surface(self, device):
        """Training views at 0 and 50 degrees with focal length 30, the plane 4 units away: a view between them
        with the same focal length resolves it as finely as they do (1; the footprint grows with the depth along
        the ray, which is the same at the same distance), one with focal length 60 twice as finely (zoomed in), one
        moved to half the distance too; ``evaluate`` names the views from ``FINER_NOTE`` on, and a compared view
        and a view without surface have 1."""
        from types import SimpleNamespace

        from uncertsplat.stages.evaluate import FINER_NOTE, _reach_notes

        render_fn = _plane_render()
        train = _cameras([0.0, 50.0], focal=30.0, device=device)
        vc = ViewConsistency.of(_sample(device), train, render_fn)
        same = _cameras([25.0], focal=30.0, device=device)
        zoom = _cameras([25.0], focal=60.0, device=device)
        assert vc.reach(same, render_fn)[1] == pytest.approx(1.0, rel=0.1)  # the plane seen at 25 degrees: 0.93
        assert vc.reach(zoom, render_fn)[1] == pytest.approx(2.0, rel=0.1)
        near = dataclasses.replace(zoom, cam_from_world=zoom.cam_from_world.clone())
        near.cam_from_world[0, 2, 3] -= 2.0  # along its optical axis, to 2 units from the plane's centre
        assert vc.reach(near, render_fn)[1] == pytest.approx(4.0, rel=0.1)
        assert vc.reach(train[[1]], render_fn) == (0.0, 1.0)
        # the footprint is the depth over the focal length along x for this view as for the training views: a view
        # whose pixels are only taller (fy = 60) resolves the surface across as they do
        tall = dataclasses.replace(same, K=same.K.clone())
        tall.K[0, 1, 1] = 60.0
        assert vc.reach(tall, render_fn)[1] == pytest.approx(1.0, rel=0.1)

        def empty(sample, cameras):
            out = render_fn(sample, cameras)
            return dataclasses.replace(out, alpha=torch.zeros_like(out.alpha))

        assert vc.reach(zoom, empty) == (0.0, 1.0)
        both = dataclasses.replace(same, cam_from_world=torch.cat([same.cam_from_world, zoom.cam_from_world]),
                                   K=torch.cat([same.K, zoom.K]), image_names=("same.png", "zoom.png"))
        notes = _reach_notes(SimpleNamespace(consistency=vc, render_fn=render_fn),
                             SimpleNamespace(cameras=both, names=["same.png", "zoom.png"]), torch.device(device))
        (note,) = [n for n in notes if "finer than any training photo" in n]
        assert note.startswith("1 of 2 views") and "zoom.png x1.9" in note and "same.png" not in note
        assert FINER_NOTE < 2.0

    def test_the_gate_is_twice_the_capture_spacing(self):
        ring = _cameras([30.0 * i for i in range(12)])
        assert capture_spacing(ring.centers, torch.zeros(3)) == pytest.approx(30.0, rel=1e-4)
        assert capture_spacing(ring.centers[:1], torch.zeros(3)) == MIN_GATE
        same = ring.centers[[0, 0, 0]]
        assert capture_spacing(same, torch.zeros(3)) == MIN_GATE  # three photos from one place
        vc = ViewConsistency.of(_sample(), ring, _plane_render())
        assert vc.gate == pytest.approx(GATE_SPACINGS * 30.0, rel=1e-4)
        assert vc.rgb.shape == (12, H, W, 3) and vc.depth.shape == (12, H, W)
        # the median, not the mean, of each camera's angle to its nearest neighbour: one camera far from the
        # others (10, 10, 10 and 40 degrees) leaves the spacing at 10
        uneven = _cameras([0.0, 10.0, 20.0, 60.0])
        assert capture_spacing(uneven.centers, torch.zeros(3)) == pytest.approx(10.0, rel=1e-4)
        # seen from the model's median Gaussian: a far outlier among its Gaussians does not move the point
        outlier = dataclasses.replace(_sample(), means=torch.tensor([[0.0, 0, 0], [0.1, 0, 0], [40.0, 0, 0]]),
                                      quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(3, 1),
                                      scales=torch.full((3, 3), 0.1), opacities=torch.ones(3),
                                      sh=torch.zeros(3, 1, 3))
        vc = ViewConsistency.of(outlier, uneven, _plane_render())
        assert vc.gate == pytest.approx(GATE_SPACINGS * capture_spacing(uneven.centers, torch.tensor([0.1, 0, 0])),
                                        rel=1e-4)


class TestSeenFree:
    """``ViewConsistency.seen_free``: space a training view's rays passed through before their surface."""

    def _free(self, depth_fn, azimuths=(0.0,)):
        """The term of cameras at these azimuths (4 units from the origin, looking at it) whose depth maps
        ``depth_fn(k)`` [H,W] gives, built by hand."""
        cams = _cameras(azimuths)
        depth = torch.stack([depth_fn(k) for k in range(len(cams))])
        rgb = torch.zeros(len(cams), H, W, 3, dtype=torch.float16)
        return ViewConsistency(_sample(), cams, rgb, depth, gate=1.0)

    def test_before_the_surface_within_the_image_only(self):
        """A camera on the -z axis 4 units out sees a wall at depth 4 (the plane z = 0): points on its way there
        are free, points at the wall (within the tolerance) or behind it, behind the camera or outside its image
        are not."""
        term = self._free(lambda k: torch.full((H, W), 4.0))
        pts = torch.tensor([[0.0, 0.0, -3.0],   # 1 unit out of the camera
                            [0.0, 0.0, -0.2],   # 3.8: 5 % before the wall
                            [0.0, 0.0, -0.05],  # 3.95: within 3 % of the wall
                            [0.0, 0.0, 1.0],    # behind the wall
                            [0.0, 0.0, -5.0],   # behind the camera
                            [30.0, 0.0, -3.0]])  # in front of it, outside its image
        assert term.seen_free(pts).tolist() == [True, True, False, False, False, False]

    def test_a_ray_that_meets_nothing_passes_through_everything_in_its_image(self):
        """Depth 0 (no Gaussian on the ray: sky, an opening) leaves every point in the image free, at any depth."""
        term = self._free(lambda k: torch.zeros(H, W))
        assert term.seen_free(torch.tensor([[0.0, 0.0, -3.0], [0.0, 0.0, 50.0]])).tolist() == [True, True]

    def test_one_view_that_saw_through_a_point_is_enough_in_any_chunk(self):
        """A point hidden from eight views (a wall at depth 1 in each) and seen through by the ninth, in another
        chunk of ``VIEW_CHUNK``, is free; without the ninth it is not."""
        assert consistency.VIEW_CHUNK == 8
        walls = lambda k: torch.full((H, W), 1.0 if k < 8 else 10.0)  # noqa: E731
        azimuths = [0.0] * 9
        assert self._free(walls, azimuths).seen_free(torch.tensor([[0.0, 0.0, 0.0]])).tolist() == [True]
        assert self._free(walls, azimuths[:8]).seen_free(torch.tensor([[0.0, 0.0, 0.0]])).tolist() == [False]

    def test_a_point_is_compared_with_the_pixel_it_lands_in(self):
        """The rendered depth a point is compared with is that of the pixel holding its projection (pixel c spans
        [c, c + 1)), not of the pixel whose centre is nearest: a point landing at u = 16.7 in front of a wall at depth 4
        in column 16 is free, whatever column 17, at depth 1, holds."""
        step = torch.full((H, W), 4.0)
        step[:, W // 2 + 1:] = 1.0
        term = self._free(lambda k: step)
        # the camera at (0, 0, -4) looking down +z with focal length 40: u = 40 x / (z + 4) + 16, at camera depth 2
        pts = torch.tensor([[0.7 * 2 / 40, 0.0, -2.0], [1.2 * 2 / 40, 0.0, -2.0]])  # u = 16.7 and 17.2
        assert term.seen_free(pts, around=0).tolist() == [True, False]

    def test_where_a_photo_was_taken_is_free(self):
        """A training camera's centre (z = 0 in its own view) and its surroundings within 3 % of the views' median
        depth are free, behind it too; farther behind it is not."""
        term = self._free(lambda k: torch.full((H, W), 4.0))
        pts = torch.tensor([[0.0, 0.0, -4.0], [0.0, 0.0, -4.1], [0.0, 0.0, -4.2]])  # centre, 0.1 and 0.2 behind
        assert term.seen_free(pts).tolist() == [True, True, False]
        # the median is over the pixels with a surface: most of the view empty (depth 0) leaves it at the wall's
        mostly_empty = torch.zeros(H, W)
        mostly_empty[: H // 4] = 4.0
        term = self._free(lambda k: mostly_empty)
        assert term.median_surface_depth() == 4.0
        assert term.seen_free(pts).tolist() == [True, True, False]

    def test_behind_what_every_view_that_holds_it_saw(self):
        """``seen_behind``: a point behind the wall of the one view that holds it is behind; in front of the wall,
        outside every image, behind the camera or where the ray met nothing (depth 0) it is not; a second view that
        sees through the point (its wall farther, in another chunk) clears it."""
        term = self._free(lambda k: torch.full((H, W), 4.0))
        pts = torch.tensor([[0.0, 0.0, 1.0],    # behind the wall (depth 5 against 4)
                            [0.0, 0.0, 0.05],   # within 3 % behind it: at the wall, not behind
                            [0.0, 0.0, -3.0],   # in front of it
                            [30.0, 0.0, 1.0],   # outside the image
                            [0.0, 0.0, -5.0]])  # behind the camera
        assert term.seen_behind(pts).tolist() == [True, False, False, False, False]
        assert self._free(lambda k: torch.zeros(H, W)).seen_behind(pts[:1]).tolist() == [False]
        walls = lambda k: torch.full((H, W), 4.0 if k < 8 else 10.0)  # noqa: E731
        assert self._free(walls, [0.0] * 9).seen_behind(pts[:1]).tolist() == [False]
        assert self._free(walls, [0.0] * 8).seen_behind(pts[:1]).tolist() == [True]
        assert term.seen_behind(torch.zeros(0, 3)).shape == (0,)

    def test_no_points_and_extreme_points(self):
        term = self._free(lambda k: torch.full((H, W), 4.0))
        assert term.seen_free(torch.zeros(0, 3)).shape == (0,)
        far = torch.tensor([[0.0, 0.0, -1e30], [1e30, 1e30, 1e30], [0.0, 0.0, 1e30]])
        assert term.seen_free(far).tolist() == [False, False, False]
        empty = self._free(lambda k: torch.zeros(H, W))  # no surface at all: no distance around a camera
        assert empty.seen_free(torch.tensor([[0.0, 0.0, -4.0], [0.0, 0.0, -2.0]])).tolist() == [False, True]



def _expected_gap(free_below: float) -> float:
    """The fraction of the depth ``_free_gap`` finds when the ray is seen empty exactly below ``free_below`` of the
    depth: 1 - s of its first sample s (from 1 - the tolerance toward the camera, geometrically) below that; 1 when
    no sample is."""
    g = consistency.DEPTH_TOLERANCE * (1.0 / consistency.DEPTH_TOLERANCE) ** (
        torch.arange(consistency.GAP_SAMPLES, dtype=torch.float64) / consistency.GAP_SAMPLES)
    below = g[(1.0 - g) < free_below]
    return float(below.min()) if below.numel() else 1.0


def _occluder_by_column(sample: GaussianSample, cameras: Cameras) -> RenderOutput:
    """The plane, hidden by something nearer whose depth grows across the image: 0.2 of the plane's at the left
    edge to 0.8 at the right (so a point behind it has a stretch seen empty that changes along each row)."""
    out = _plane_render()(sample, cameras)
    w = cameras.width
    frac = 0.2 + 0.6 * (torch.arange(w, dtype=torch.float32, device=out.depth.device) + 0.5) / w  # [W]
    depth = out.depth * frac[None, None, :, None]
    return dataclasses.replace(out, depth=depth, depth_expected=depth)


class TestHiddenDepth:
    """``ViewConsistency.hidden_depth_variance``: the depth variance of the surface points no compared view sees."""

    def test_a_point_every_photo_saw_has_nothing(self, device):
        vc, render_fn = _term([0.0, 50.0], gate=4.0, device=device)
        var = vc.hidden_depth_variance(_cameras([20.0], focal=60.0, device=device), render_fn)
        assert var.shape == (1, H, W, 1) and var.device.type == torch.device(device).type
        assert float(var.abs().max()) == 0.0

    def test_behind_an_occluder_the_stretch_no_photo_saw_empty(self, device):
        """The one training camera stands where the evaluated one does (a narrower view, so every evaluated ray is
        one of its rays) and rendered something at half the wall's depth: the wall's points are hidden from it, and
        along each evaluated ray it saw empty space only nearer than 0.485 of the depth (the occluder less the 3 %
        tolerance). So L is 0.515 of the depth, as the samples find it (at most one step, 1.2x, above), and the
        variance L^2 / 12 that of a point uniform on the stretch."""
        render_fn = _plane_render(nearer=frozenset({0}))
        vc, _ = _term([0.0], gate=4.0, render_fn=render_fn, device=device)
        test = _cameras([0.0], focal=20.0, device=device)
        var = vc.hidden_depth_variance(test, _plane_render())[0, ..., 0].cpu().double()  # [H,W] the wall itself
        gap = _expected_gap(0.5 * (1.0 - consistency.DEPTH_TOLERANCE))
        assert 0.515 <= gap <= 0.515 * 1.21
        torch.testing.assert_close(var, torch.full_like(var, (gap * 4.0) ** 2 / 12.0), rtol=1e-4, atol=0.0)
        # transparent photos (an object's far side): the stretch behind the point up to space a photo saw empty
        # counts too; here no photo saw behind the wall empty, so the whole marched stretch (to 1.84 of the depth)
        behind = float(consistency._behind_fractions()[-1]) - 1.0
        assert behind == pytest.approx(0.84, abs=0.01)
        far = dataclasses.replace(vc, unseen_empty=True).hidden_depth_variance(test, _plane_render())[0, ..., 0]
        torch.testing.assert_close(far.cpu().double(), torch.full_like(var, ((gap + behind) * 4.0) ** 2 / 12.0),
                                   rtol=1e-4, atol=0.0)

    def test_on_transparent_photos_the_stretch_behind_ends_where_a_photo_saw_empty(self):
        """``unseen_empty``: two training cameras where the evaluated one stands, one that rendered something at half
        the wall's depth, one that saw through to 3x it: the wall's points are seen by neither, and the space just in
        front (0.97 of the depth) and just behind (1.03) was seen empty by the second, so the stretch is 0.06 of the
        depth, the variance (0.06 z)^2 / 12."""
        cams = _cameras([0.0, 0.0], focal=6.0)
        wall = _plane_render()(_sample(), cams[[0]]).depth[0, ..., 0]
        vc = ViewConsistency(_sample(), cams, torch.zeros(2, H, W, 3, dtype=torch.float16),
                             torch.stack([0.5 * wall, 3.0 * wall]), gate=4.0, unseen_empty=True)
        test = _cameras([0.0], focal=20.0)
        z = _plane_render()(_sample(), test).depth[0, ..., 0].double()
        var = vc.hidden_depth_variance(test, _plane_render())[0, ..., 0].double()
        assert consistency._gap_fractions()[0] == pytest.approx(0.97)
        assert consistency._behind_fractions()[0] == pytest.approx(1.03)
        torch.testing.assert_close(var, (0.06 * z) ** 2 / 12.0, rtol=1e-4, atol=0.0)

    def test_outside_every_photo_the_whole_depth(self, device):
        """A wider evaluated view from the training camera's place: its corners lie outside the training image, so no
        photo saw any of those rays empty (but at the camera, where the photo was taken): L is the whole depth; its
        centre is seen and has nothing."""
        render_fn = _plane_render()
        narrow = ViewConsistency.of(_sample(device), _cameras([0.0], focal=60.0, device=device), render_fn)
        test = _cameras([0.0], focal=6.0, device=device)
        var = narrow.hidden_depth_variance(test, render_fn)[0, ..., 0].cpu()
        assert float(var[H // 2, W // 2]) == 0.0
        depth = render_fn(None, test).depth[0, 0, 0, 0].cpu()
        assert float(var[0, 0]) == pytest.approx(float(depth) ** 2 / 12.0, rel=1e-5)

    def test_above_the_cap_one_point_per_square_cell_is_marched(self, monkeypatch, device):
        """Above ``GAP_POINTS`` hidden points the view is cut into t x t cells (t the smallest, at least 2, that
        leaves at most ``GAP_POINTS`` cells with points), the first point of each cell (row order) is marched and the
        cell's others take its stretch as a fraction of their own depth. The occluder's depth changes across the
        training image, so the stretches differ from point to point and a wrong source shows."""
        vc = ViewConsistency.of(_sample(device), _cameras([0.0], focal=6.0, device=device), _occluder_by_column)
        test = _cameras([0.0], focal=20.0, device=device)
        plane = _plane_render()
        every = vc.hidden_depth_variance(test, plane)[0, ..., 0].cpu().double()  # [H,W]
        depth = plane(None, test).depth[0, ..., 0].cpu().double()
        rel = (12.0 * every).sqrt() / depth  # each point's stretch over its depth
        assert float(every.min()) > 0.0 and float(rel.max() - rel.min()) > 0.2  # every point hidden, stretches differ
        for cap in (7, 100, H * W - 1):
            monkeypatch.setattr(consistency, "GAP_POINTS", cap)
            some = vc.hidden_depth_variance(test, plane)[0, ..., 0].cpu().double()
            t = 2
            while math.ceil(H / t) * math.ceil(W / t) > cap:
                t += 1
            expect = torch.empty_like(every)
            for r in range(H):
                for c in range(W):
                    first = rel[r // t * t, c // t * t]  # every pixel is hidden: a cell's first is its corner
                    expect[r, c] = (first * depth[r, c]) ** 2 / 12.0
            torch.testing.assert_close(some, expect, rtol=1e-5, atol=0.0)
            assert len(torch.unique(some / depth.square())) <= cap

    def test_none_unless_asked_nothing_for_a_compared_view_or_without_surface(self, device):
        """``variance`` alone returns no depth term; a compared training view gets zeros without a render; a view
        without surface gets zeros; ``variances`` gives the RGB term of ``variance`` beside it."""
        render_fn = _plane_render(nearer=frozenset({0}))
        vc, _ = _term([0.0, 50.0], gate=4.0, render_fn=render_fn, device=device)
        test = _cameras([20.0], focal=60.0, device=device)
        rgb, depth = vc.variances(test, render_fn, hidden_depth=True)
        assert torch.equal(rgb, vc.variance(test, render_fn))
        assert vc.variances(test, render_fn, hidden_depth=False)[1] is None

        def no_render(sample, cameras):
            raise AssertionError("a compared training view needs no render")

        assert float(vc.hidden_depth_variance(vc.cameras[[0]], no_render).abs().max()) == 0.0

        def empty(sample, cameras):
            out = render_fn(sample, cameras)
            return dataclasses.replace(out, alpha=torch.zeros_like(out.alpha))

        assert float(vc.hidden_depth_variance(test, empty).abs().max()) == 0.0
        with pytest.raises(ValueError, match="one camera"):
            vc.hidden_depth_variance(_cameras([10.0, 20.0], device=device), render_fn)

    def test_the_predictive_adds_it_to_the_depth_variance_only_when_asked(self, monkeypatch):
        """``eval.engine.predictive_terms``: the hidden points' depth variance joins the depths a ray blends in
        ``extra_depth_var`` (named "hidden surface" and "depth spread"); not with ``hidden_depth`` off, nor for a
        caller of the RGB maps alone."""
        from types import SimpleNamespace

        from uncertsplat.eval import engine
        from uncertsplat.uncertainty.mc import sum_terms

        render_fn = _plane_render(nearer=frozenset({0}))
        vc, _ = _term([0.0], gate=4.0, render_fn=render_fn)
        test = _cameras([0.0], focal=20.0)
        sampler = SimpleNamespace(residual=None, consistency=vc, exposure=None, render_fn=_plane_render(),
                                  empty_std=None, coverage=1.0, det_sample=_sample(), mean_sample=None)
        cfg = SimpleNamespace(hidden_depth=True, depth_spread=False, empty_rays=False, resolution=0.0,
                              resolution_renders=1)
        terms = engine.predictive_terms(sampler, cfg, test)
        assert list(terms["extra_depth_var"]) == ["hidden surface"]
        torch.testing.assert_close(terms["extra_depth_var"]["hidden surface"],
                                   vc.hidden_depth_variance(test, _plane_render()))
        assert float(terms["extra_depth_var"]["hidden surface"].min()) > 0.0
        assert engine.predictive_terms(sampler, cfg, test, depth=False)["extra_depth_var"] is None
        cfg.hidden_depth = False
        assert engine.predictive_terms(sampler, cfg, test)["extra_depth_var"] is None
        cfg.hidden_depth, cfg.depth_spread = True, True
        monkeypatch.setattr(engine, "_representative", lambda s, d: s.det_sample)
        monkeypatch.setattr("uncertsplat.uncertainty.mc.depth_spread", lambda *a: torch.full((1, H, W, 1), 0.5))
        both = engine.predictive_terms(sampler, cfg, test)["extra_depth_var"]
        assert list(both) == ["depth spread", "hidden surface"]
        torch.testing.assert_close(sum_terms(both), vc.hidden_depth_variance(test, _plane_render()) + 0.5)

def test_depth_edges_flag_jumps_not_slopes():
    step = torch.ones(8, 10)
    step[:, 5:] = 1.5
    edges = _depth_edges(step)
    assert edges[:, 4:6].all() and not edges[:, :4].any() and not edges[:, 6:].any()
    slope = 1.0 + 0.5 * DEPTH_JUMP * torch.arange(10.0)[None].expand(8, 10) / 10  # well below the jump per window
    assert not _depth_edges(slope).any()
    # the surface points the term projects leave those pixels out (the point a blended depth gives lies on neither)
    cam = _cameras([0.0])
    out = _plane_render()(_sample(), cam)
    depth = out.depth.clone()
    depth[..., W // 2:, :] *= 1.5
    rgb, where, points, z = ViewConsistency._surface_of(dataclasses.replace(out, depth=depth), cam)
    kept = torch.zeros(H * W, dtype=torch.bool)
    kept[where] = True
    assert torch.equal(kept.reshape(H, W), ~_depth_edges(depth[0, ..., 0]))
    assert not bool(kept.reshape(H, W)[:, W // 2 - 1: W // 2 + 1].any()) and int(kept.sum()) == H * (W - 2)


def _textured_plane_render(slope: float = 0.05):
    """The plane of ``_plane_render`` coloured by position instead of by camera: 0.5 + ``slope`` x (world x), the same
    from every direction (so the view-consistency difference is 0 and the render's gradient is known)."""
    from uncertsplat.render.project import unproject

    base = _plane_render()

    def render_fn(sample: GaussianSample, cameras: Cameras) -> RenderOutput:
        out = base(sample, cameras)
        pts = unproject(out.depth[0, ..., 0].double(), cameras.cam_from_world[0].double(), cameras.K[0].double())
        rgb = (0.5 + slope * pts[..., 0]).float()[None, ..., None].expand(1, cameras.height, cameras.width, 3)
        return dataclasses.replace(out, rgb=rgb.contiguous().to(out.rgb.device))

    return render_fn


class TestFinerDetail:
    """The finer-detail term, ``(r^2 - 1) finer_detail g(p)``: training views at 0 and 50 degrees with focal length 30,
    4 units from the textured plane; r = 1 between them at their distance, about 2 zoomed in x2 and 4 moved to half
    the distance too (``test_the_scale_at_which_a_view_resolves_the_surface``)."""

    C = 0.1  # the term's coefficient (delta^2 + 1/12 in evaluate)

    def _added(self, vc, camera, render_fn):
        from uncertsplat.uncertainty.residual import image_gradient_sq

        added = vc.variance(camera, render_fn) - dataclasses.replace(vc, finer_detail=0.0).variance(camera, render_fn)
        g = image_gradient_sq(render_fn(vc.sample, camera).rgb)
        inner = (slice(None), slice(2, -2), slice(2, -2))  # away from the one-sided differences of the border
        return added[inner], g[inner]

    def test_the_variance_of_a_step_against_the_ramp_the_photos_recorded(self, device):
        render_fn = _textured_plane_render()
        train = _cameras([0.0, 50.0], focal=30.0, device=device)
        vc = ViewConsistency.of(_sample(device), train, render_fn, finer_detail=self.C)
        assert vc.finer_detail == self.C
        same = _cameras([25.0], focal=30.0, device=device)
        added, g = self._added(vc, same, render_fn)
        # as fine as the photos: nothing, but near the edge the oblique plane is a little nearer than in either photo
        assert (g > 0).all() and float((added == 0).float().mean()) > 0.5 and (added <= 0.5 * self.C * g).all()
        zoom = _cameras([25.0], focal=60.0, device=device)
        added, g = self._added(vc, zoom, render_fn)
        ratio = added / (self.C * g)  # r^2 - 1 per pixel
        assert float(ratio.median()) == pytest.approx(2.0**2 - 1.0, rel=0.2)
        near = dataclasses.replace(zoom, cam_from_world=zoom.cam_from_world.clone())
        near.cam_from_world[0, 2, 3] -= 2.0
        added_near, g_near = self._added(vc, near, render_fn)
        assert float((added_near / (self.C * g_near)).median()) == pytest.approx(4.0**2 - 1.0, rel=0.2)

    def test_nothing_without_a_gradient_a_surface_or_the_term(self, device):
        train = _cameras([0.0, 50.0], focal=30.0, device=device)
        zoom = _cameras([25.0], focal=60.0, device=device)
        flat = _plane_render()  # one colour per view: no gradient, only the view-consistency difference
        vc = ViewConsistency.of(_sample(device), train, flat, finer_detail=self.C)
        assert torch.equal(vc.variance(zoom, flat), dataclasses.replace(vc, finer_detail=0.0).variance(zoom, flat))
        textured = _textured_plane_render()

        def empty(sample, cameras):
            out = textured(sample, cameras)
            return dataclasses.replace(out, alpha=torch.zeros_like(out.alpha))

        vc = ViewConsistency.of(_sample(device), train, textured, finer_detail=self.C)
        assert not vc.variance(zoom, empty).any()
        assert not vc.variance(train[[0]], textured).any(), "a compared training view itself"
        assert ViewConsistency.of(_sample(device), train, textured).finer_detail == 0.0
        assert not ViewConsistency.of(_sample(device), train, textured).variance(zoom, textured).any()

    def test_evaluate_gives_the_term_the_edge_scale_and_the_step(self, monkeypatch):
        from types import SimpleNamespace

        from uncertsplat.eval import engine
        from uncertsplat.uncertainty.consistency import STEP_VARIANCE

        got = {}

        def of(*args, **kwargs):
            got.update(kwargs)
            return "term"

        monkeypatch.setattr(engine.ViewConsistency, "of", of)
        sampler = SimpleNamespace(det_sample=_sample(), mean_sample=None, render_fn=None, empty_std=(0.29, 1.0))
        cfg = SimpleNamespace(consistency_views=4, finer_detail=True, empty_rays=True)
        assert engine.view_consistency(sampler, _cameras([0.0, 50.0]), cfg, torch.device("cpu"), 0.04) == "term"
        assert got["finer_detail"] == pytest.approx(0.04 + STEP_VARIANCE) and STEP_VARIANCE == pytest.approx(1 / 12)
        assert got["unseen_empty"] is False  # opaque photos: the empty-ray term covers rays that meet nothing
        sampler.empty_std = None  # transparent photos: the rays through space no photo saw empty instead
        engine.view_consistency(sampler, _cameras([0.0, 50.0]), cfg, torch.device("cpu"), 0.04)
        assert got["unseen_empty"] is True
        cfg.empty_rays = False
        engine.view_consistency(sampler, _cameras([0.0, 50.0]), cfg, torch.device("cpu"), 0.04)
        assert got["unseen_empty"] is False
        cfg.empty_rays, sampler.empty_std = True, (0.29, 1.0)
        cfg.finer_detail = False
        engine.view_consistency(sampler, _cameras([0.0, 50.0]), cfg, torch.device("cpu"), 0.04)
        assert got["finer_detail"] == 0.0
        residual = SimpleNamespace(edge_scale=0.02)
        cfg.finer_detail = True
        monkeypatch.setattr(engine.dataclasses, "replace", lambda obj, **kw: kw)
        assert engine.with_side_terms(sampler, residual, _cameras([0.0, 50.0]), cfg, torch.device("cpu"))[
            "consistency"] == "term"
        assert got["finer_detail"] == pytest.approx(0.02 + STEP_VARIANCE)


def test_the_finer_detail_term_stays_finite_at_the_extremes(device, monkeypatch):
    """A camera almost touching the textured plane (a thousandth of the training distance, so r is about a thousand),
    a surface claimed at depth 0 and a footprint of 1e-30 (r about 1e29, capped at ``MAX_FINER``): the term is finite
    and not negative everywhere."""
    render_fn = _textured_plane_render()
    train = _cameras([0.0, 50.0], focal=30.0, device=device)
    vc = ViewConsistency.of(_sample(device), train, render_fn, finer_detail=0.1)
    near = _cameras([25.0], focal=30.0, device=device)
    near.cam_from_world[0, 2, 3] -= 4.0 - 4e-3  # to 4e-3 from the plane's centre along its optical axis
    var = vc.variance(near, render_fn)
    assert torch.isfinite(var).all() and (var >= 0).all() and var.any()

    def flat_at_zero(sample, cameras):  # a surface claimed at depth 0: footprint 0
        out = render_fn(sample, cameras)
        return dataclasses.replace(out, depth=torch.full_like(out.depth, 1e-30))

    var = vc.variance(_cameras([25.0], focal=60.0, device=device), flat_at_zero)
    assert torch.isfinite(var).all() and (var >= 0).all()
    footprint = consistency._footprint
    monkeypatch.setattr(consistency, "_footprint", lambda points, camera: footprint(points, camera) * 1e-30)
    var = vc.variance(_cameras([25.0], focal=60.0, device=device), render_fn)
    assert torch.isfinite(var).all() and (var >= 0).all() and float(var.max()) > 1.0  # r^2 = 1e12 times g


def test_seen_free_in_blocks_of_points_is_the_same(monkeypatch):
    """Many points are tested a block at a time (4M points took 2.8 GB at once): the same answer."""
    vc = ViewConsistency(_sample(), _cameras([0.0, 90.0]), torch.zeros(2, H, W, 3, dtype=torch.float16),
                         torch.full((2, H, W), 4.0), gate=1.0)
    pts = torch.randn(1000, 3, generator=torch.Generator().manual_seed(0)) * 3
    whole = vc.seen_free(pts)
    monkeypatch.setattr(consistency, "FREE_POINTS_CHUNK", 7)
    assert torch.equal(vc.seen_free(pts), whole) and 0 < int(whole.sum()) < 1000


def test_a_view_looked_up_in_blocks_of_points_is_the_same(monkeypatch):
    """An evaluated view's surface points are looked up a block at a time (a whole 1280x960 view's lookups took
    0.9 GB): the same map and the same reach, with the finer-detail term, the palette's variance for points outside
    every training image and views that see and views that do not."""
    render_fn = _textured_plane_render()
    train = _cameras([0.0, 50.0], focal=30.0)
    vc = dataclasses.replace(ViewConsistency.of(_sample(), train, render_fn, finer_detail=0.1), gate=2.0,
                             palette_var=0.25)
    wide = _cameras([-30.0], focal=6.0)  # far round: part of its plane outside both training images
    zoom = _cameras([25.0], focal=60.0)  # between them, finer than either photo
    monkeypatch.setenv("UNCERTSPLAT_RASTERIZER", "torch")  # (the native lookup takes every point in one pass)
    whole = {name: (vc.variance(cam, render_fn), vc.reach(cam, render_fn)) for name, cam in
             (("wide", wide), ("zoom", zoom))}
    monkeypatch.setattr(consistency, "POINTS_CHUNK", 7)
    for name, cam in (("wide", wide), ("zoom", zoom)):
        assert torch.equal(vc.variance(cam, render_fn), whole[name][0]) and vc.reach(cam, render_fn) == whole[name][1]
    assert 0.0 < whole["wide"][1][0] < 1.0 and float(whole["wide"][0].max()) > 0.1  # the palette (0.25) where none held it, blurred
    assert whole["zoom"][1] == (0.0, pytest.approx(2.0, rel=0.2)) and float(whole["zoom"][0].max()) > 0.0


def test_a_lone_difference_spreads_as_a_fading_blob_not_a_square():
    """``_window_mean``: one large squared difference falls off with the distance from its pixel (the box drew a
    hard-edged 5x5 square of equal values around it); a constant field stays constant up to the image's border;
    nothing leaves the window."""
    from uncertsplat.uncertainty.consistency import BLUR, _window_mean

    v = torch.zeros(15, 17)
    v[7, 8] = 1.0
    out = _window_mean(v)
    centre, side, edge, corner = float(out[7, 8]), float(out[7, 9]), float(out[7, 8 + BLUR]), float(out[9, 10])
    assert centre > side > edge > corner > 0.0
    assert float(out[7, 8 + BLUR + 1]) == 0.0 and float(out[7 + BLUR + 1, 8]) == 0.0
    assert float(out.sum()) == pytest.approx(1.0, rel=1e-6)  # inside the image the weights sum to 1
    torch.testing.assert_close(_window_mean(torch.full((6, 4), 0.3)), torch.full((6, 4), 0.3))


def test_the_window_mean_is_the_binomial_convolution_over_the_part_inside_the_image():
    """``_window_mean``'s shifted sums against the 5x5 binomial convolution they replaced (numerator and the window's
    weight inside the image, each a ``conv2d``), on images down to one pixel and in float64."""
    import torch.nn.functional as F

    from uncertsplat.uncertainty.consistency import BLUR, _window_mean

    k = 2 * BLUR + 1
    gen = torch.Generator().manual_seed(0)
    for shape, dtype in [((1, 1), torch.float32), ((1, 9), torch.float32), ((3, 2), torch.float32),
                         ((17, 5), torch.float32), ((48, 64), torch.float32), ((7, 6), torch.float64)]:
        v = torch.rand(shape, generator=gen, dtype=dtype)
        w1 = torch.tensor([math.comb(k - 1, i) for i in range(k)], dtype=dtype)
        w2 = (w1[:, None] * w1[None, :])[None, None]
        expect = (F.conv2d(v[None, None], w2, padding=BLUR) / F.conv2d(torch.ones_like(v)[None, None], w2,
                                                                       padding=BLUR))[0, 0]
        torch.testing.assert_close(_window_mean(v), expect)


class TestNativeLookup:
    """``native/csrc/consistency.cpp`` against the tensor ops (``ViewConsistency._lookup_torch``): random compared
    renders (colours and depths, some of them nearer than the points so that a view does not see them) and points
    in front of, beside and behind the cameras."""

    @pytest.fixture(autouse=True)
    def needs_native(self):
        from uncertsplat import native

        if native.library() is None:
            pytest.skip(f"native kernels unavailable: {native.unavailable_reason()}")

    def _case(self, seed: int, views: int = 11):
        gen = torch.Generator().manual_seed(seed)
        azimuths = (torch.rand(views, generator=gen) * 160 - 80).tolist()
        train = _cameras(azimuths, focal=20.0)
        points = torch.rand(3000, 3, generator=gen) * torch.tensor([6.0, 4.0, 2.0]) - torch.tensor([3.0, 2.0, 1.0])
        points[:50] = torch.rand(50, 3, generator=gen) * 20 - 10  # some behind or beside every camera
        # each view's depth at each pixel: the points' own depth there would be about 4; a random part nearer
        depth = torch.full((views, H, W), 4.0) + torch.randn(views, H, W, generator=gen) * 0.8
        depth[torch.rand(views, H, W, generator=gen) < 0.2] = 0.0  # rays that met nothing
        rgb = torch.rand(views, H, W, 3, generator=gen).half()
        vc = ViewConsistency(_sample(), train, rgb, depth, gate=3.0)
        test = _cameras([float(torch.rand(1, generator=gen)) * 100 - 50], focal=30.0)
        colour = torch.rand(points.shape[0], 3, generator=gen)
        return vc, test, points, colour

    @pytest.mark.parametrize("seed", [0, 1, 2])
    def test_the_same_views_differences_and_reach_as_the_tensor_ops(self, seed):
        vc, test, points, colour = self._case(seed)
        foot = consistency._footprint(points, test)
        assert vc._native(points)
        best, diff, inside, finest = vc._lookup_native(points, test, colour, foot)
        with torch.no_grad():
            ref = vc._lookup_torch(points, test, colour, foot)
        assert torch.equal(inside, ref[2]) and 0 < int(inside.sum()) < points.shape[0]
        seen = torch.isfinite(ref[0])
        assert torch.equal(torch.isfinite(best), seen) and 0 < int(seen.sum()) < int(inside.sum())
        # the angle of the nearest view: acos near 0 degrees resolves about 0.02 degrees of a float32 cosine
        torch.testing.assert_close(best[seen], ref[0][seen], atol=0.1, rtol=1e-4)
        torch.testing.assert_close(diff, ref[1], atol=1e-6, rtol=1e-4)
        torch.testing.assert_close(finest, ref[3], atol=0.0, rtol=1e-5)
        assert float(diff[~seen].abs().max()) == 0.0 and bool(torch.isinf(finest[~seen]).all())

    def test_a_view_from_the_far_side_of_the_point_is_found(self):
        """A training view more than 90 degrees round from the evaluated one (each at 70 degrees to the plane's normal,
        on either side) still sees the plane's points: the angle, 140 degrees, as the tensor ops give it."""
        vc = ViewConsistency.of(_sample(), _cameras([70.0], focal=20.0), _plane_render())
        test = _cameras([-70.0], focal=20.0)
        points = torch.tensor([[0.0, 0.0, 0.0], [0.1, 0.05, 0.0], [-0.1, -0.05, 0.0]])
        best = vc._lookup_native(points, test, None, None)[0]
        ref = vc._lookup_torch(points, test, None, None)[0]
        assert bool(torch.isfinite(ref).all()) and float(ref[0]) == pytest.approx(140.0, abs=0.1)
        torch.testing.assert_close(best, ref, atol=0.1, rtol=1e-4)

    def test_float16_renders_are_read_exactly_down_to_subnormals(self):
        """The kernel decodes the float16 renders itself: renders of dark colours (1e-4 and below: most of them
        float16 subnormals, under 6.1e-5) compared with a colour of 0 give the tensor ops' differences to float32
        rounding (a subnormal read at twice its value gave up to 4x the difference)."""
        vc, test, points, _ = self._case(6)
        rgb = (vc.rgb.float() * 1e-4).half()
        assert bool(((rgb > 0) & (rgb < 6.1e-5)).float().mean() > 0.5)
        vc = dataclasses.replace(vc, rgb=rgb)
        colour = torch.zeros_like(points)
        diff = vc._lookup_native(points, test, colour, None)[1]
        with torch.no_grad():
            ref = vc._lookup_torch(points, test, colour, None)[1]
        assert float(ref.max()) > 0.0
        torch.testing.assert_close(diff, ref, atol=0.0, rtol=1e-4)

    def test_without_colour_or_footprint_only_what_was_asked(self):
        vc, test, points, _ = self._case(3)
        best, diff, inside, finest = vc._lookup_native(points, test, None, None)
        assert float(diff.abs().max()) == 0.0 and bool(torch.isinf(finest).all())
        ref = vc._lookup_torch(points, test, None, None)
        assert torch.equal(inside, ref[2]) and torch.equal(torch.isfinite(best), torch.isfinite(ref[0]))

    def test_a_view_gets_the_same_term_and_reach_either_way(self, monkeypatch):
        """Through ``variance`` and ``reach``: the maps of the two paths agree to rounding."""
        render_fn = _plane_render(nearer=frozenset({30}))
        vc = dataclasses.replace(ViewConsistency.of(_sample(), _cameras([-40.0, 0.0, 30.0, 52.0], focal=12.0), render_fn,
                                                    finer_detail=0.1), gate=2.0, palette_var=0.25)
        for cam in (_cameras([40.0], focal=60.0), _cameras([-70.0], focal=6.0)):
            native_map, native_reach = vc.variance(cam, render_fn), vc.reach(cam, render_fn)
            monkeypatch.setenv("UNCERTSPLAT_RASTERIZER", "torch")
            torch.testing.assert_close(native_map, vc.variance(cam, render_fn), atol=1e-6, rtol=1e-4)
            assert native_reach == pytest.approx(vc.reach(cam, render_fn), rel=1e-5)
            monkeypatch.delenv("UNCERTSPLAT_RASTERIZER")
            assert float(native_map.max()) > 0.0

    def test_no_points_and_one_view(self):
        vc, test, points, colour = self._case(4, views=1)
        best, diff, inside, finest = vc._lookup_native(points[:0], test, colour[:0], None)
        assert best.shape == diff.shape == inside.shape == finest.shape == (0,)
        best, _, inside, _ = vc._lookup_native(points, test, colour, None)
        ref = vc._lookup_torch(points, test, colour, None)
        assert torch.equal(inside, ref[2]) and torch.equal(torch.isfinite(best), torch.isfinite(ref[0]))

    def test_float64_as_torch_default_dtype_changes_nothing(self):
        """The outputs are float32 whatever torch's default dtype (a float64 default read the kernel's float32 as
        doubles: angles of 89.7 against 9.8 degrees, a finest ratio of 1e306)."""
        vc, test, points, colour = self._case(5)
        expect = vc._lookup_native(points, test, colour, consistency._footprint(points, test))
        before = torch.get_default_dtype()
        torch.set_default_dtype(torch.float64)
        try:
            got = vc._lookup_native(points, test, colour, consistency._footprint(points, test))
        finally:
            torch.set_default_dtype(before)
        for a, b in zip(got, expect, strict=True):
            assert a.dtype == b.dtype and torch.equal(a, b)

    def test_an_image_without_pixels_is_refused_not_read(self):
        """A compared render of width or height 0: the kernel returns -1 before reading anything (its in-image test
        took u = 0 as inside and read before the buffer), and ``_native`` sends such renders to the tensor ops."""
        from uncertsplat import native

        vc = ViewConsistency(_sample(), _cameras([0.0], width=0), torch.zeros(1, H, 0, 3, dtype=torch.float16),
                             torch.zeros(1, H, 0), gate=1.0)
        pts = torch.zeros(4, 3)
        assert not vc._native(pts)
        out = torch.zeros(4)
        code = native.library().us_consistency_lookup_f32(
            4, 1, H, 0, pts.data_ptr(), 0, vc.cameras.cam_from_world.contiguous().data_ptr(),
            vc.cameras.K.contiguous().data_ptr(), vc.cameras.centers.contiguous().data_ptr(), 0, 0, 1, 0.0, 0.0,
            -4.0, 0, out.data_ptr(), 0, torch.zeros(4, dtype=torch.uint8).data_ptr(), 0, 1)
        assert code == -1


def test_seen_free_compares_with_the_nearest_surface_around_the_pixel():
    """At an object's outline the rendered depth blends the object with the wall behind it: a point inside the object
    there lay nearer than that blend and counted as seen through (2-4 % of the points inside the demo's objects, 11-28
    % on a 300-step model). With ``around`` = 1 the nearest surface within a pixel is compared; a ray that met nothing
    (depth 0) is no surface, and a point clear of the object in front of the wall stays free."""
    depth = torch.full((1, H, W), 10.0)
    depth[0, :, :16] = 2.0  # the object, left of the optical axis
    depth[0, :, 16] = 6.0  # its outline: object and wall blended
    vc = ViewConsistency(_sample(), _cameras([0.0]), torch.zeros(1, H, W, 3, dtype=torch.float16), depth, gate=1.0)
    inside = torch.tensor([[0.0, 0.0, -1.0]])  # on the optical axis at depth 3: behind the object's surface at 2
    assert bool(vc.seen_free(inside, around=0)[0]) and not bool(vc.seen_free(inside, around=1)[0])
    assert not bool(vc.seen_free(inside)[0])  # the default (FREE_AROUND)
    clear = torch.tensor([[0.5, 0.0, -1.0]])  # to the right, in front of the wall at 10: free either way
    assert bool(vc.seen_free(clear, around=0)[0]) and bool(vc.seen_free(clear, around=1)[0])
    near = consistency._nearest_surface(torch.tensor([[[0.0, 0.0, 5.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]]), 1)
    assert near[0].tolist() == [[0.0, 5.0, 5.0], [0.0, 5.0, 5.0], [0.0, 0.0, 0.0]]  # 0 where no surface is near
