"""The view-consistency term: what a model renders for a surface point from a new direction, against what it renders
for the same point from the training view that looked at it from the nearest direction.

Every other term of the predictive is fitted on, or derived from, the training views, and a view far from them
inherits their confidence: trained on one half of the demo scene's camera ring, the surfaces the training views saw
are rendered from the other half with squared errors 1.4x the predicted variance within 14 degrees of a training
direction but 5-6x beyond 45 degrees, on flat regions as much as on edges and where the rendered depth is right
(BENCHMARKS.md, "Surfaces seen from a new direction"). The model is fitted to reproduce each surface point as its
training views saw it; from far off their directions, the blend of Gaussians a ray meets is one no image checked.

The term measures that directly, with no parameter fitted to the data: for each pixel of the evaluated view with a
surface (alpha >= ``MIN_ALPHA``, not on an object's outline: ``DEPTH_JUMP``), its point at the rendered depth is
projected into every compared training view (their renders are kept: ``ViewConsistency.of``), kept where that view
renders it unoccluded (its rendered depth there, interpolated bilinearly, within ``DEPTH_TOLERANCE``), and the
squared difference between the two renders of the point (mean over the channels) is taken from the view at the
smallest angle. Its weight grows with that angle: 0 up to the ``gate``, ``GATE_SPACINGS`` times the capture's own
spacing (the median angle between a training view and its nearest neighbour, seen from the model's median Gaussian),
1 from twice the gate on, linearly in between: a view as close to a training view as a gap in the capture leaves is
what the rest of the predictive was fitted for, and the difference there is resampling. The squared differences are
averaged over a ``(2 BLUR + 1)^2`` window with binomial weights (a single difference is a noisy estimate of a variance). Where the surface
is Lambertian and its depth right, the training view's render is what the photo showed, so the difference is the
evaluated view's error itself; where the surface's colour changes with the direction, it is a change no training
view showed either.

A surface point that lies outside the image of every training camera (``frustum_cameras``: all of them, compared or
not) was never looked at: no direction is near it, no render of it can be compared, and what colour it has is unknown.
It gets the variance of a colour drawn from the scene's own: the variance over the surface pixels of the compared
training views' renders (mean over the channels, ``ViewConsistency.palette_var``), the prior predictive of a colour
the data say nothing about. Nothing is fitted. It replaced the mean of the view's own full-weight differences (the
error of a point seen only from afar), which is a floor rather than the level: on the demo ring trained on one half,
the unobserved pixels' squared error was 1.13x the predicted variance with it and 0.87x with the palette's, the
unseen-surface ROC AUC 0.932 -> 0.954, and views with too few far differences to average (sparse captures) got the
level at all (BENCHMARKS.md, "A colour nobody saw"). A point inside some compared training image but seen by none
(hidden there by the model's own surfaces: the far side of an object, where every camera looks at the object) gets
the palette's variance weighted as a seen point's difference is, by the angle to the nearest compared view whose image
holds it (0 within the gate, in full from twice it): on real photos the visibility test fails on depth noise as often
as on occlusion, but there the views that hold the point are near (fern's extrapolated arc: AUSE-MAE 0.187 -> 0.213
when every hidden point got a level, 0.188 -> 0.215 with the palette's and no gate, 0.188 unchanged with the gate;
the object half-hemisphere's unseen-surface RGB AUC 0.678 -> 0.821).

Rays that meet little of the model on a scene whose training images are transparent (``unseen_empty``: the empty-ray
term is off there, the background being data): where a ray's alpha is below ``EMPTY_MAX_ALPHA`` and some of its
``EMPTY_SAMPLES`` points between the model's nearest and farthest Gaussians lies in space no compared training view
saw empty (``seen_free``), a surface there would have been seen by no photo: the pixel gets ``(1 - alpha)^2
palette_var`` (the far side of an object that SfM never triangulated, rendered as background), and where alpha is
below ``MIN_ALPHA`` (no surface point of its own) the depth variance ``(1 - alpha)^2 (hi - lo)^2 / 12`` of a surface
anywhere between the model's nearest and farthest Gaussians. On such scenes a hidden surface point's depth stretch
(``_free_gap``) also counts the space behind it up to where a photo saw empty: the silhouettes carve the space in front
of an object's far side, so the gap in front alone was short (the unseen side's depth AUC 0.815 -> 0.928 with both;
BENCHMARKS.md, "The far side of an object").

Detail finer than any photo recorded (``ViewConsistency.finer_detail``). A view nearer than the capture, or zoomed in,
resolves a surface point r times finer than the finest compared training view that sees it (r: that view's pixel
footprint at the point, depth / focal length, over this view's). The model was fitted at the photos' resolution, and
its render of an edge the photos recorded across one of their pixels is a ramp r of this view's pixels wide, whatever
the edge is. Two things follow, per pixel with g(p) the squared gradient of this view's render: the edge term's
misplacement delta is in training pixels, r delta in this view's, so that term grows to ``delta^2 r^2 g``; and the
surface may hold a sharp edge where the model renders the ramp: a step of contrast C = r |grad I| against a linear
ramp of r pixels differs by C^2 / 12 on average over the ramp, the part of it beyond what the photos' own pixels
already averaged (r = 1) being ``(r^2 - 1) g / 12``. Together ``(r^2 - 1) (delta^2 + 1/12) g(p)`` is added where r > 1
(nothing elsewhere; nothing is fitted). Measured on views moved along their optical axes to half their distance
(``benchmarks/bench_near.py``): 5 sparse views, NLL -1.75 -> -2.11 and AUSE-MAE 0.115 -> 0.111; the dense demo,
NLL -3.07 -> -3.17, AUSE-MAE 0.120 -> 0.114; the held-out views at the capture's distance unchanged (BENCHMARKS.md,
"Detail finer than any photo recorded").

A surface no photo saw (``ViewConsistency.hidden_depth_variance``, for the depth std). A surface point of the
evaluated view that no compared training view sees (hidden behind what every photo holding it saw in front of it, or
outside them all) has a depth the photos did not pin down: a surface anywhere on the stretch of the view's ray in
front of it that no compared view's ray passed through empty (``seen_free``) would have looked the same to every
photo. With L that stretch's length (``_free_gap``; the whole depth where no photo saw any of the ray empty), the
point gets the depth variance ``L^2 / 12``, that of a point uniform on the stretch; nothing is fitted. (The mean
squared distance of such a point from the stretch's end, where the render puts the surface, is ``L^2 / 3``: measured
too, it made the depth std too wide where the model's surface came from points other photos triangulated.) Seen
points get nothing: the photos that see them put the surface there. Not covered: a floater, a surface the model
renders where the photos saw through (its point is not seen, but the space just in front of it is: it gets the
tolerance's stretch only, while the real surface lies behind; ``prune``'s free-space score finds those). Measured
(BENCHMARKS.md, "A depth no photo pinned down"): trained on one half of the demo ring, the unseen-surface depth ROC
AUC 0.925 -> 0.939 with every initial point, 0.949 -> 0.952 with the training views' points; 5 sparse views 0.896 ->
0.937; depth NLL and AUSE within 0.03 nats and 0.002.

Pure tensors: a sample, cameras and a renderer (``render_fn(sample, cameras) -> RenderOutput``). On a CPU the lookups
of the points in the compared views run in a native kernel (``native/csrc/consistency.cpp``: the term of a 1280x960
view against the demo's 35 views 0.65 s, 2.1 s as tensor ops); elsewhere, or with ``UNCERTSPLAT_RASTERIZER=torch``,
as blocks of tensor ops, the same values to rounding.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F
from torch import Tensor

from uncertsplat.render.project import project_points, unproject
from uncertsplat.types import Cameras, GaussianSample, RenderOutput
from uncertsplat.uncertainty.residual import image_gradient_sq

MIN_ALPHA = 0.5
"""Pixels whose rendered alpha is below this have no surface to project (the empty-ray term speaks there)."""
DEPTH_TOLERANCE = 0.03
"""A point counts as seen by a training view when its depth there is within this fraction of the view's rendered
depth where it lands."""
DEPTH_JUMP = 0.1
"""Pixels whose 3x3 neighbourhood spans a larger fraction of their depth are not compared (``_depth_edges``). Measured
on the demo scene at 160x120 (with the gate at twice the spacing): without the test, the outlines of every object
in a dense capture's held-out views got the term (AUSE-MAE 0.143 -> 0.148, NLL -2.635 -> -2.617); at 0.03 the
half-ring's silhouettes, whose errors are real, lost it too (NLL -1.17 -> -0.90, gate at one spacing)."""
GATE_SPACINGS = 2.0
"""The gate in capture spacings: a held-out view in a gap of a regular capture lies about one spacing from the
nearest training view; at one spacing the term fired on a dense capture's held-out views (demo scene at 160x120:
NLL -2.635 -> -2.597), at two it leaves them as they were and still finds the half ring's other side."""
BLUR = 2
"""Half-width in pixels of the window the squared differences are averaged over (``_window_mean``)."""
MIN_GATE = 1.0
"""Degrees: the smallest ``gate`` (a capture of one view, or of views from one place)."""
VIEW_CHUNK = 8
"""Training views a pixel's point is projected into at once by the tensor ops (``ViewConsistency._lookup_torch``; the
native kernel takes them all in one pass): their renders are sampled as one batch (4 float32 channels per pixel of
each)."""
STACK_BYTES = 256 * 2**20
"""The compared renders are kept as the ready [C,4,H,W] stacks each lookup samples (``_compared_at``) when all of them
fit in this many bytes: rebuilding a chunk's stack from the float16 renders for each evaluated view cost more than
the lookup itself on a small view (44 of 162 ms of a 32x24 prediction on the demo run). (The native kernel reads
the kept renders themselves.)"""
POINTS_CHUNK = 65536
"""Surface points of an evaluated view the tensor ops look up at once (their [C,S] lookups took about 0.6 KB a pixel
for a whole view; the native kernel keeps a point's lookups in registers)."""
FREE_AROUND = 1
"""Pixels around a point's own whose nearest rendered surface ``seen_free`` compares it with: a point counts as seen
free by a view only where the view's ray and its neighbours' passed it (measured in BENCHMARKS.md, "Space a photo
looked through, inside the objects")."""
FREE_POINTS_CHUNK = 65536
"""Points ``seen_free`` tests at once (about 600 bytes each while they are looked up: 4M points took 2.8 GB)."""
GAP_SAMPLES = 20
"""Points along an evaluated view's ray at which ``_free_gap`` tests whether a compared training view saw the space
empty: fractions of the rendered depth from 1 - ``DEPTH_TOLERANCE`` toward the camera, each 1.19x the last's distance
from the surface (the gap is found to within a fifth of itself; ``_gap_fractions``)."""
GAP_POINTS = 65536
"""At most this many hidden points of a view are marched (``_free_gap``; 20 points each); beyond, one per square
cell of the view, the cell's others taking its stretch."""
MAX_FINER = 1e6
"""The largest r the finer-detail term takes (its square stays a float32 number)."""
EMPTY_MAX_ALPHA = 0.99
"""``ViewConsistency._unseen_empty`` marches the rays whose rendered alpha is below this."""
EMPTY_SAMPLES = 12
"""Points ``ViewConsistency._unseen_empty`` tests along each marched ray."""
QUANTILE_POINTS = 1_000_000
"""``_unseen_empty`` takes the depth percentiles of at most about this many Gaussians (every k-th)."""
STEP_VARIANCE = 1.0 / 12.0
"""Pixels^2: the mean squared difference between a step and a linear ramp one pixel wide over that pixel, per squared
gradient of the ramp (the finer-detail term's ``(r^2 - 1) / 12``; module docstring)."""


def _angle(a: Tensor, b: Tensor) -> Tensor:
    """Degrees between unit vectors ``a`` and ``b`` [...,3]."""
    return torch.rad2deg(torch.acos((a * b).sum(-1).clamp(-1.0, 1.0)))


def _footprint(points: Tensor, camera: Cameras) -> Tensor:
    """[S] the pixel footprint (depth / focal length) of one ``camera`` at ``points`` [S,3]."""
    _, z = project_points(points, camera.cam_from_world.to(points), camera.K.to(points))  # [1,S]
    return (z[0] / camera.K[0, 0, 0].to(points)).clamp_min(1e-30)


def _finest_ratio(cams: Cameras, z: Tensor, seen: Tensor, foot: Tensor) -> Tensor:
    """[S] the smallest, over the views ``cams`` that see each point (``seen`` [C,S], depths there ``z`` [C,S]), of
    their pixel footprint at the point over ``foot`` [S]; inf where none sees it."""
    ratio = (z / cams.K[:, 0, 0].to(z)[:, None]) / foot  # [C,S]
    return torch.where(seen, ratio, torch.full_like(ratio, float("inf"))).min(0).values


def capture_spacing(centers: Tensor, point: Tensor) -> float:
    """Degrees: the median over the cameras ``centers`` [T,3] of the angle to the nearest other camera, seen from
    ``point`` [3]; ``MIN_GATE`` when there are fewer than two cameras or it is smaller."""
    if centers.shape[0] < 2:
        return MIN_GATE
    d = F.normalize(centers.double() - point.double(), dim=-1)  # [T,3]
    ang = _angle(d[:, None], d[None])  # [T,T]
    ang.fill_diagonal_(float("inf"))
    return max(float(ang.min(1).values.median()), MIN_GATE)


@dataclass(frozen=True)
class ViewConsistency:
    """The view-consistency term of one model (module docstring).

    Attributes:
        sample: the deterministic model whose renders are compared (the run's expected render).
        cameras: the training cameras compared with [T].
        rgb: [T,H,W,3] the model's render of each of them (float16: only differences of about 1e-2 and more matter).
        depth: [T,H,W] its rendered depth there (0 where alpha is 0).
        gate: degrees, ``GATE_SPACINGS`` x the capture's spacing (``capture_spacing``): no weight below it, full
            weight from twice it.
        frustum_cameras: every training camera (compared or not), for the test whether any looked at a point; None:
            ``cameras``.
        palette_var: the variance of the colours of the surface pixels (alpha >= ``MIN_ALPHA``, a depth) of
            ``rgb``, mean over the channels: what a point no training camera looked at gets (module docstring).
        finer_detail: pixels^2, the coefficient ``delta^2 + STEP_VARIANCE`` of the finer-detail term
            ``(r^2 - 1) finer_detail g(p)`` (module docstring; delta^2 the pixel noise's edge term, 0 without one);
            0: no such term.
    """

    sample: GaussianSample
    cameras: Cameras
    rgb: Tensor
    depth: Tensor
    gate: float
    frustum_cameras: Cameras | None = None
    palette_var: float = 0.0
    finer_detail: float = 0.0
    unseen_empty: bool = False
    """Transparent training images (no empty-ray term): rays that meet little of the model through space no photo saw
    empty get ``(1 - alpha)^2 palette_var`` and, below ``MIN_ALPHA``, a depth variance (``_unseen_empty``); a hidden
    point's depth stretch counts the space behind it too (``_free_gap``)."""
    # ``_stack``'s stacks and ``median_surface_depth``'s value
    _cache: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    @classmethod
    @torch.no_grad()
    def of(cls, sample: GaussianSample, cameras: Cameras,
           render_fn: Callable[[GaussianSample, Cameras], RenderOutput],
           frustum_cameras: Cameras | None = None, finer_detail: float = 0.0,
           unseen_empty: bool = False) -> ViewConsistency:
        """The term for ``sample`` and the training ``cameras`` (one render each, kept), the gate from their
        spacing seen from the model's median Gaussian; ``frustum_cameras``: all training cameras when ``cameras``
        is a subset of them; ``finer_detail``: the attribute of that name (0: no finer-detail term).

        Raises:
            ValueError: no camera (``eval.engine.view_consistency`` builds no term then).
        """
        if len(cameras) == 0:
            raise ValueError("the view-consistency term needs at least one training camera")
        point = sample.means.detach().median(0).values if sample.means.shape[0] else sample.means.new_zeros(3)
        rgb, depth = [], []
        count, total, total_sq = 0, 0.0, 0.0  # the surface pixels' colours: count, [3] sum, [3] sum of squares
        for k in range(len(cameras)):
            out = render_fn(sample, cameras[[k]])
            rgb.append(out.rgb[0].half())
            depth.append(out.depth[0, ..., 0].float())
            surface = (out.alpha[0, ..., 0] >= MIN_ALPHA) & (out.depth[0, ..., 0] > 0)  # [H,W]
            colours = out.rgb[0][surface].double()  # [P,3]
            count += colours.shape[0]
            total = total + colours.sum(0)
            total_sq = total_sq + colours.square().sum(0)
        palette = 0.0
        if count > 1:  # the unbiased variance of each channel, then their mean
            palette = float(((total_sq - total.square() / count) / (count - 1)).clamp_min(0.0).mean())
        return cls(sample, cameras, torch.stack(rgb), torch.stack(depth),
                   GATE_SPACINGS * capture_spacing(cameras.centers, point), frustum_cameras, palette, finer_detail,
                   unseen_empty)

    @torch.no_grad()
    def variance(self, camera: Cameras, render_fn: Callable[[GaussianSample, Cameras], RenderOutput]) -> Tensor:
        """[1,H,W,1] the term for one evaluated ``camera`` (module docstring); 0 where the pixel has no surface and
        within the gate; ``palette_var`` where no training camera holds the pixel's point, and weighted by the angle to
        the nearest compared view holding it where those views hold it but none sees it; plus the finer-detail term
        where the view resolves a point finer than the compared views that see it, and on transparent scenes the
        rays that meet little of the model through space no photo saw empty (``_unseen_empty``)."""
        return self.variances(camera, render_fn, hidden_depth=False)[0]

    @torch.no_grad()
    def variances(self, camera: Cameras, render_fn: Callable[[GaussianSample, Cameras], RenderOutput], *,
                  hidden_depth: bool = True) -> tuple[Tensor, Tensor | None]:
        """The RGB term ``variance`` [1,H,W,1] for one evaluated ``camera`` and, with ``hidden_depth``, the depth
        variance of its hidden surface points [1,H,W,1] (``hidden_depth_variance``; else None), from one render and
        one lookup of its surface points."""
        if len(camera) != 1:
            raise ValueError(f"one camera at a time, got {len(camera)}")
        zero = torch.zeros(1, camera.height, camera.width, 1, device=self.depth.device)
        no_depth = torch.zeros(1, camera.height, camera.width, 1, dtype=torch.float32, device=self.depth.device) \
            if hidden_depth else None
        if self._is_compared(camera):  # its own render is the nearest: 0 everywhere
            return zero, no_depth
        rendered = render_fn(self.sample, camera)  # (one render for both: the surface points and the faint rays)
        # (not gated on the palette: a model of one flat colour has no colour to be unsure of, but a depth still)
        empty, empty_depth = self._unseen_empty(camera, rendered) if self.unseen_empty else (None, None)
        if empty_depth is not None and no_depth is not None:
            no_depth = no_depth + empty_depth
        found = self._surface_of(rendered, camera)
        if found is None:
            return (zero if empty is None else empty.to(zero)), no_depth
        rgb, where, points, z = found  # [H,W,3], [S], [S,3], [S]
        h, w = rgb.shape[:2]
        colour = rgb.reshape(-1, 3)[where]  # [S,3]
        term, finest, seen = self._term_of(points, colour, camera)  # [S], [S], [S]
        depth_var = None
        if hidden_depth:
            hidden = (~seen).nonzero()[:, 0]  # [Q] indices into the surface points
            gap = self._free_gap(points[hidden], z[hidden], camera, where[hidden])  # [Q]
            depth_var = torch.zeros(h * w, dtype=torch.float32, device=rgb.device).index_copy_(
                0, where[hidden], (gap.square() / 12.0).float()).reshape(1, h, w, 1)
            if empty_depth is not None:  # the faint rays' unknown surface (alpha < MIN_ALPHA: no surface point)
                depth_var = depth_var + empty_depth
        full = torch.zeros(h * w, dtype=rgb.dtype, device=rgb.device).index_copy_(0, where, term)
        out = _window_mean(full.reshape(h, w))[None, ..., None]
        if self.finer_detail > 0.0:  # not averaged: the edges it follows are a pixel wide
            # r capped at 1e6 so that r^2 stays a float32 number (a footprint near 0 would overflow to inf, and
            # inf x a zero gradient is NaN); a view a million times finer than every photo is far past any capture
            r = finest.clamp(1.0, MAX_FINER)
            r2 = torch.where(torch.isfinite(finest), r.square(), torch.ones_like(finest))  # [S]
            g = image_gradient_sq(rgb).reshape(-1)[where]  # [S]
            detail = torch.zeros(h * w, dtype=rgb.dtype, device=rgb.device).index_copy_(
                0, where, ((r2 - 1.0) * self.finer_detail * g).to(rgb.dtype))
            out = out + detail.reshape(1, h, w, 1).to(out)
        if empty is not None:
            out = out + empty.to(out)
        return out, depth_var

    def _term_of(self, points: Tensor, colour: Tensor, camera: Cameras) -> tuple[Tensor, Tensor, Tensor]:
        """For surface ``points`` [S,3] of the evaluated ``camera`` with their rendered ``colour`` [S,3]: the
        consistency term before the window mean [S] (the gated squared difference to the nearest seeing view, the
        palette's variance where no training camera holds the point), the finest seeing view's footprint over
        this view's [S] (inf where none sees it; only with ``finer_detail``) and whether some compared view sees
        each point [S] bool."""
        best, diff, inside_any, finest = self._lookup(points, camera, colour, self.finer_detail > 0.0)
        weight = ((best - self.gate) / self.gate).clamp(0.0, 1.0).to(colour.dtype)  # diff is 0 where no view saw it
        if self.palette_var > 0.0:
            unlooked = self._unlooked(points, inside_any)  # [S] (best = inf there: no view saw them)
            diff = torch.where(unlooked, torch.full_like(diff, self.palette_var), diff)  # weight 1 there (best = inf)
            hidden = (~torch.isfinite(best) & inside_any).nonzero()[:, 0]  # held by compared images, seen by none
            if hidden.numel():
                far = ((self._holding_angle(points[hidden], camera) - self.gate) / self.gate).clamp(0.0, 1.0)
                diff = diff.index_copy(0, hidden, self.palette_var * far.to(diff.dtype))
        return diff * weight, finest, torch.isfinite(best)

    def _holding_angle(self, points: Tensor, camera: Cameras) -> Tensor:
        """[Q] degrees from the evaluated ``camera``'s direction at ``points`` [Q,3] to the nearest compared training
        view whose image holds the point (in front of it, seen or not); inf where none holds it. In blocks of
        ``POINTS_CHUNK`` points, as the lookups: a large view's far side held 581 MB at once."""
        best = torch.full_like(points[:, 0], float("inf"))
        for p0 in range(0, points.shape[0], POINTS_CHUNK):
            block = points[p0:p0 + POINTS_CHUNK]
            to_view = F.normalize(camera.centers[0].to(block) - block, dim=-1)  # [B,3]
            for k0 in range(0, len(self.cameras), VIEW_CHUNK):
                cams = self.cameras[k0:k0 + VIEW_CHUNK]
                uv, z = project_points(block, cams.cam_from_world.to(block), cams.K.to(block))  # [C,B,2], [C,B]
                inside = _in_image(uv, z, self.cameras.width, self.cameras.height)  # [C,B]
                angle = _angle(F.normalize(cams.centers.to(block)[:, None] - block, dim=-1), to_view)  # [C,B]
                nearest = torch.where(inside, angle, torch.full_like(angle, float("inf"))).min(0).values
                best[p0:p0 + POINTS_CHUNK] = torch.minimum(best[p0:p0 + POINTS_CHUNK], nearest)
        return best

    def _unseen_empty(self, camera: Cameras, rendered: RenderOutput) -> tuple[Tensor, Tensor]:
        """[1,H,W,1] ``(1 - alpha)^2 palette_var`` and, for the depth, [1,H,W,1] ``(1 - alpha)^2 (hi - lo)^2 / 12``
        on those of them with alpha < ``MIN_ALPHA`` (hi, lo: the depth percentiles below; an unknown surface anywhere
        between the model's nearest and farthest Gaussians) where the evaluated ``camera``'s ray (its render ``rendered``)
        meets little of the model (alpha < ``EMPTY_MAX_ALPHA``) and some of its ``EMPTY_SAMPLES`` points between the
        model's nearest and farthest Gaussians (their centres' 1st and 99th depth percentiles in this view) lies in
        space no compared training view saw empty (``seen_free``, ray by ray; a ray found so is not marched further);
        0 elsewhere (module docstring)."""
        alpha = rendered.alpha[0, ..., 0].float()  # [H,W]
        h, w = alpha.shape
        out = torch.zeros(1, h, w, 1, dtype=torch.float32, device=alpha.device)
        dout = torch.zeros_like(out)
        pix = (alpha < EMPTY_MAX_ALPHA).flatten().nonzero()[:, 0]  # [P]
        if pix.numel() == 0 or self.sample.means.shape[0] == 0:
            return out, dout
        _, zg = project_points(self.sample.means.detach().float(), camera.cam_from_world.float(), camera.K.float())
        zg = zg[0][zg[0] > 0]
        if zg.numel() < 2:
            return out, dout
        zg = zg[:: max(1, zg.numel() // QUANTILE_POINTS)]  # (torch.quantile takes at most 2^24 values)
        lo, hi = torch.quantile(zg, torch.tensor([0.01, 0.99], device=zg.device)).tolist()
        rays = unproject(torch.ones(h, w, dtype=torch.float32, device=alpha.device), camera.cam_from_world[0].float(),
                         camera.K[0].float()).reshape(-1, 3)[pix] - camera.centers[0].float()  # [P,3] per unit depth
        todo = torch.arange(pix.shape[0], device=alpha.device)  # rays not yet found to pass unseen space
        unseen = torch.zeros(pix.shape[0], dtype=torch.bool, device=alpha.device)
        for d in torch.linspace(lo, hi, EMPTY_SAMPLES).tolist():
            if todo.numel() == 0:
                break
            hit = ~self.seen_free(camera.centers[0].float() + d * rays[todo], around=0)  # [T]
            unseen[todo[hit]] = True
            todo = todo[~hit]
        a = alpha.flatten()[pix]
        weight = (1.0 - a).square() * unseen.float()  # [P]
        out.view(-1).index_copy_(0, pix, weight * self.palette_var)
        dout.view(-1).index_copy_(0, pix, weight * (a < MIN_ALPHA).float() * (hi - lo) ** 2 / 12.0)
        return out, dout

    @torch.no_grad()
    def hidden_depth_variance(self, camera: Cameras,
                              render_fn: Callable[[GaussianSample, Cameras], RenderOutput]) -> Tensor:
        """[1,H,W,1] the depth variance of one evaluated ``camera``'s hidden surface points (module docstring, "A
        surface no photo saw"): ``L^2 / 12`` where no compared training view sees the pixel's point, L the stretch of
        the view's ray in front of it that no compared training view saw empty (``_free_gap``; with ``unseen_empty``
        the stretch behind it too); 0 elsewhere, on the depth edges and where the pixel has no surface (but, with
        ``unseen_empty``, the faint rays through unseen space: ``_unseen_empty``); 0 everywhere for a compared
        training view."""
        return self.variances(camera, render_fn, hidden_depth=True)[1]

    def _free_gap(self, points: Tensor, z: Tensor, camera: Cameras, pixels: Tensor) -> Tensor:
        """[Q] the length, in the evaluated ``camera``'s depth units, of the stretch in front of each of ``points``
        [Q,3] (at depths ``z`` [Q], in the view's pixels ``pixels`` [Q], flat indices) along its ray from the camera
        that no compared training view saw empty (``seen_free``): the rendered depth times 1 - s, s the largest of
        ``GAP_SAMPLES`` fractions of the depth (``_gap_fractions``) at which the ray's point is seen empty; the whole
        depth when none is; with ``unseen_empty`` (transparent photos) plus the stretch behind the point up to the
        first of ``_behind_fractions`` at which the ray is seen empty (0.84 of the depth when none is). Above
        ``GAP_POINTS`` points, the view is cut into square cells of t x t pixels (t the
        smallest that leaves at most ``GAP_POINTS`` cells holding points), the first point of each cell (in the
        view's row order) is marched, and the cell's others take its stretch as a fraction of their own depth."""
        q = points.shape[0]
        if q == 0:
            return z.new_zeros(0)
        source = torch.arange(q, device=points.device)  # [Q] the point whose march each point takes
        if q > GAP_POINTS:
            source = _cell_firsts(pixels, camera.width, q)
        marched = torch.unique(source)  # [M] sorted
        start = points[marched]  # [M,3]
        eye = camera.centers[0].to(points)  # [3]
        nearest = torch.zeros(marched.shape[0], dtype=points.dtype, device=points.device)  # [M] 0: none free
        left = torch.arange(marched.shape[0], device=points.device)  # the marched points not found free yet
        for frac in _gap_fractions().tolist():  # from the surface toward the camera: the first free one is the largest
            free = self.seen_free(eye + frac * (start[left] - eye), around=0)  # [L] (as measured: ray by ray)
            nearest[left[free]] = frac
            left = left[~free]  # most points of a surface hidden by the model's own noise are done at the first
            if left.numel() == 0:
                break
        if self.unseen_empty:  # transparent photos: and the stretch behind, up to space some photo saw empty
            fractions = _behind_fractions()
            behind = torch.full_like(nearest, float(fractions[-1] - 1.0))  # none found: the last sample's
            left = torch.arange(marched.shape[0], device=points.device)
            for frac in fractions.tolist():  # from the surface away from the camera: the first free one
                free = self.seen_free(eye + frac * (start[left] - eye), around=0)
                behind[left[free]] = frac - 1.0
                left = left[~free]
                if left.numel() == 0:
                    break
            nearest = nearest - behind  # the stretch 1 - nearest + behind, as a fraction of the depth
        rel = (1.0 - nearest)[torch.searchsorted(marched, source)]  # [Q]
        return rel.to(z) * z

    def _lookup(self, points: Tensor, camera: Cameras, colour: Tensor | None, fine: bool
                ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """The compared views at surface ``points`` [S,3] of the evaluated ``camera``: the angle in degrees to the
        nearest view that sees each point [S] (inf where none does), the mean over the channels of the squared
        difference between ``colour`` [S,3] and that view's render there [S] (0 where none sees it; zeros without
        ``colour``), whether some compared view's image holds the point [S] and, with ``fine``, the finest seeing
        view's footprint over this view's [S] (inf where none sees it; all inf without ``fine``). On a CPU with the
        native kernels one pass over the points (``native/csrc/consistency.cpp``), else ``POINTS_CHUNK`` points and
        ``VIEW_CHUNK`` views of tensor ops at a time."""
        foot = _footprint(points, camera) if fine else None  # [S]
        if self._native(points):
            return self._lookup_native(points, camera, colour, foot)
        parts = [self._lookup_torch(points[b:b + POINTS_CHUNK], camera,
                                    None if colour is None else colour[b:b + POINTS_CHUNK],
                                    None if foot is None else foot[b:b + POINTS_CHUNK])
                 for b in range(0, points.shape[0], POINTS_CHUNK)]
        best, diff, inside_any, finest = (torch.cat([p[i] for p in parts]) for i in range(4))
        return best, diff, inside_any, finest

    def _lookup_torch(self, points: Tensor, camera: Cameras, colour: Tensor | None, foot: Tensor | None
                      ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """``_lookup`` of one block of points in tensor ops (``foot``: [S] or None for no finest ratio)."""
        to_view = F.normalize(camera.centers[0].to(points) - points, dim=-1)  # [S,3]
        best = torch.full_like(points[:, 0], float("inf"))  # [S] angle of the chosen view
        diff = torch.zeros_like(points[:, 0])  # [S]
        inside_any = torch.zeros_like(points[:, 0], dtype=torch.bool)  # [S] in some compared view's image
        finest = torch.full_like(points[:, 0], float("inf"))  # [S] the finest seeing view's footprint over this view's
        for k0 in range(0, len(self.cameras), VIEW_CHUNK):
            cams, z, inside, there, seen = self._compared_at(points, k0, points.dtype)
            inside_any |= inside.any(0)
            if foot is not None:
                finest = torch.minimum(finest, _finest_ratio(cams, z, seen, foot))
            angle = _angle(F.normalize(cams.centers.to(points)[:, None] - points, dim=-1), to_view)  # [C,S]
            angle = torch.where(seen, angle, torch.full_like(angle, float("inf")))
            nearest, k = angle.min(0)  # [S]: the first of equal angles, as views in order
            better = nearest < best
            if colour is not None:
                sq = (colour - there.gather(0, k[None, :, None].expand(1, -1, 4))[0, :, :3]).square().mean(-1)  # [S]
                diff = torch.where(better, sq, diff)
            best = torch.where(better, nearest, best)
        return best, diff, inside_any, finest

    def _lookup_native(self, points: Tensor, camera: Cameras, colour: Tensor | None, foot: Tensor | None
                       ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """``_lookup`` by the native kernel (``_native``), reading the kept renders as they are (float16 colours,
        float32 depths)."""
        from uncertsplat import native

        s, f32 = points.shape[0], torch.float32
        pts = points.contiguous()
        col = None if colour is None else colour.to(f32).contiguous()
        ft = None if foot is None else foot.to(f32).contiguous()
        cams = self.cameras
        world = cams.cam_from_world.to(f32).contiguous()
        K, centers = cams.K.to(f32).contiguous(), cams.centers.to(f32).contiguous()
        depth = self.depth.to(f32).contiguous()  # (the kept renders: already so)
        rgb = self.rgb.contiguous() if self.rgb.dtype == torch.float16 else self.rgb.to(f32).contiguous()
        eye = camera.centers[0].double().tolist()
        # float32 whatever torch's default dtype (a float64 default read the kernel's float32 as doubles)
        best_cos, diff = torch.empty(s, dtype=f32), torch.zeros(s, dtype=f32)
        inside_any, finest = torch.empty(s, dtype=torch.uint8), torch.full((s,), float("inf"), dtype=f32)
        done = native.library().us_consistency_lookup_f32(
            s, len(cams), cams.height, cams.width, pts.data_ptr(), 0 if col is None else col.data_ptr(),
            world.data_ptr(), K.data_ptr(), centers.data_ptr(), depth.data_ptr(), rgb.data_ptr(),
            int(rgb.dtype == torch.float16), *eye, 0 if ft is None else ft.data_ptr(), best_cos.data_ptr(),
            diff.data_ptr(), inside_any.data_ptr(), 0 if ft is None else finest.data_ptr(), native.kernel_threads())
        if done != 0:
            raise RuntimeError(f"the consistency lookup failed (code {done})")
        none = best_cos < -1.5  # no view sees the point
        best = torch.where(none, torch.full_like(best_cos, float("inf")), torch.rad2deg(torch.acos(best_cos)))
        return best, diff, inside_any.bool(), finest

    def _native(self, points: Tensor) -> bool:
        """Whether the native kernel looks up ``points``: float32 points on a CPU with the kernels (not
        ``UNCERTSPLAT_RASTERIZER=torch``), compared renders of a size with pixels."""
        from uncertsplat import native

        return (points.dtype == torch.float32 and self.depth.numel() > 0
                and native.use_for(points, self.depth, dtypes=(torch.float32,), strict=False))

    @torch.no_grad()
    def unlooked_fraction(self, camera: Cameras,
                          render_fn: Callable[[GaussianSample, Cameras], RenderOutput]) -> float:
        """The fraction of one evaluated ``camera``'s surface pixels (those ``variance`` compares) whose point lies
        outside the image of every training camera: how much of the view the capture never had in sight. 0 for a
        compared training view and a view without surface."""
        return self.reach(camera, render_fn)[0]

    @torch.no_grad()
    def reach(self, camera: Cameras, render_fn: Callable[[GaussianSample, Cameras], RenderOutput]
              ) -> tuple[float, float]:
        """How far one evaluated ``camera`` goes beyond the capture, from one render of it: (``unlooked_fraction``,
        the finer scale: the median, over its surface points that some compared training view sees, of the finest
        such view's pixel footprint at the point (depth / focal length) over this view's; above 1 the view resolves
        the surface finer than any training photo did, by that factor: nearer, or zoomed in). (0, 1) for a compared
        view and a view without surface; the scale is 1 when no compared view sees any of its points."""
        if len(camera) != 1:
            raise ValueError(f"one camera at a time, got {len(camera)}")
        found = None if self._is_compared(camera) else self._surface_points(camera, render_fn)
        if found is None:
            return 0.0, 1.0
        points = found[2]  # [S,3]
        _, _, inside_any, finest = self._lookup(points, camera, None, True)
        unlooked = float(self._unlooked(points, inside_any).float().mean())
        seen_any = torch.isfinite(finest)
        if not bool(seen_any.any()):
            return unlooked, 1.0
        return unlooked, float(finest[seen_any].median())

    def _surface_points(self, camera: Cameras, render_fn: Callable[[GaussianSample, Cameras], RenderOutput]
                        ) -> tuple[Tensor, Tensor, Tensor, Tensor] | None:
        """The model's render of one ``camera``: its rgb [H,W,3], the flat indices [S] of its surface pixels (alpha
        >= ``MIN_ALPHA``, a depth, off the depth edges), their points at the rendered depth [S,3] and that depth [S];
        None without surface."""
        return self._surface_of(render_fn(self.sample, camera), camera)

    @staticmethod
    def _surface_of(out: RenderOutput, camera: Cameras) -> tuple[Tensor, Tensor, Tensor, Tensor] | None:
        """``_surface_points`` of the render ``out`` of ``camera``."""
        # float32 throughout: a pixel's point and its projection need far less than float32's 1e-7 relative
        rgb, depth, alpha = out.rgb[0], out.depth[0, ..., 0], out.alpha[0, ..., 0]  # [H,W,3], [H,W], [H,W]
        surface = (alpha >= MIN_ALPHA) & (depth > 0) & ~_depth_edges(depth)
        if not bool(surface.any()):
            return None
        where = surface.flatten().nonzero()[:, 0]  # [S] only the pixels with a surface are projected
        points = unproject(torch.where(surface, depth, torch.zeros_like(depth)), camera.cam_from_world[0],
                           camera.K[0]).reshape(-1, 3)[where]  # [S,3]
        return rgb, where, points, depth.reshape(-1)[where]

    def _compared_at(self, points: Tensor, k0: int, dtype: torch.dtype
                     ) -> tuple[Cameras, Tensor, Tensor, Tensor, Tensor]:
        """The compared views ``k0`` .. ``k0 + VIEW_CHUNK`` at ``points`` [S,3]: their cameras, the points' depths in
        them z [C,S], whether their images hold the points (in front) [C,S], their renders there [C,S,4] (rgb and
        rendered depth, bilinearly: a surface at a grazing angle changes depth by more than the tolerance from one
        pixel to the next; in ``dtype``) and whether they see the points (held, the rendered depth within
        ``DEPTH_TOLERANCE``) [C,S]."""
        hk, wk = self.cameras.height, self.cameras.width
        cams = self.cameras[k0:k0 + VIEW_CHUNK]
        uv, z = project_points(points, cams.cam_from_world, cams.K)  # [C,S,2], [C,S]
        inside = _in_image(uv, z, wk, hk)  # [C,S]
        grid = torch.stack([uv[..., 0] / wk * 2 - 1, uv[..., 1] / hk * 2 - 1], -1).to(dtype)[:, None]
        there = F.grid_sample(self._stack(k0, dtype), grid, mode="bilinear", padding_mode="border",
                              align_corners=False)[:, :, 0].transpose(1, 2)  # [C,S,4]
        seen = inside & ((z - there[..., 3]).abs() <= DEPTH_TOLERANCE * z)
        return cams, z, inside, there, seen

    def median_surface_depth(self) -> float:
        """The compared renders' median rendered depth over their pixels with a surface (0 without one): the depth the
        photos see, a scale of the capture. Computed once (a median of every rendered pixel)."""
        depth = self._cache.get("median_depth")
        if depth is None:
            # (masked_select: indexing by a mask of the [C,H,W,1] stack built an index of 32 bytes a pixel first,
            # 3 GB for 64 views of 1600x1200)
            surface = torch.masked_select(self.depth, self.depth > 0)
            depth = self._cache["median_depth"] = float(surface.float().median()) if surface.numel() else 0.0
        return depth

    def _near(self) -> float:
        """``DEPTH_TOLERANCE`` x ``median_surface_depth``: how near a training camera ``seen_free`` counts as where a
        photo was taken."""
        return DEPTH_TOLERANCE * self.median_surface_depth()

    def _stack(self, k0: int, dtype: torch.dtype) -> Tensor:
        """[C,4,H,W] the compared views ``k0`` .. ``k0 + VIEW_CHUNK``'s rgb and depth in ``dtype`` (a view of the
        [C,H,W,4] stack), kept for the next lookup when every chunk's fits in ``STACK_BYTES`` (the same tensor, so
        the same samples to the bit)."""
        key = (k0, VIEW_CHUNK, dtype)
        found = self._cache.get(key)
        if found is not None:
            return found
        image = torch.cat([self.rgb[k0:k0 + VIEW_CHUNK].to(dtype),
                           self.depth[k0:k0 + VIEW_CHUNK].to(dtype)[..., None]], -1).permute(0, 3, 1, 2)
        if self.depth.numel() * 4 * image.element_size() <= STACK_BYTES:
            self._cache[key] = image  # (two threads may both build it: the same values)
        return image

    @torch.no_grad()
    def seen_free(self, points: Tensor, around: int = FREE_AROUND) -> Tensor:
        """[P] bool: whether a compared training view's ray passed through each of ``points`` [P,3] (world) on its way
        to the surface it rendered: the point lands in that view's image, in front of it, nearer than the rendered
        depth there by more than ``DEPTH_TOLERANCE`` of it (or where the ray meets no Gaussian: depth 0); or within
        ``DEPTH_TOLERANCE`` of the compared views' median rendered depth from a training camera (``frustum_cameras``),
        where a photo was taken. False for a point inside an object or behind a wall, and for one no training view
        looked through: space no photo showed empty. With ``around`` r > 0 the rendered depth compared is the nearest
        one within r pixels (``FREE_AROUND``: at an outline the render blends the object with what lies behind it)."""
        near = self._near()
        stood = self.frustum_cameras if self.frustum_cameras is not None else self.cameras
        free = torch.zeros(points.shape[0], dtype=torch.bool, device=points.device)
        at_f64 = points.double()
        for centre in stood.centers.to(points.device).double():  # one camera at a time: no [P,T] distances
            free |= (at_f64 - centre).norm(dim=-1) < near
        for sl, inside, z, at in self._rendered_depths_at(points, nearest_around=around):
            free[sl] |= (inside & ((at <= 0.0) | (z < at * (1.0 - DEPTH_TOLERANCE)))).any(0)
        return free

    def _rendered_depths_at(self, points: Tensor, nearest_around: int = 0):
        """For each chunk of ``VIEW_CHUNK`` compared views and each block of ``FREE_POINTS_CHUNK`` of ``points`` [P,3]
        (the [C,P] lookups of every point at once grew to GBs): the block's slice of the points, whether the views'
        images hold them (in front) [C,S], their depths in them [C,S] and the rendered depth at the pixel each lands
        in [C,S] (nearest); with ``nearest_around`` r > 0, the nearest surface rendered within r pixels of it
        (``_nearest_surface``, once per view chunk, not per block)."""
        w, h = self.cameras.width, self.cameras.height
        for k0 in range(0, len(self.cameras), VIEW_CHUNK):
            cams = self.cameras[k0:k0 + VIEW_CHUNK].to(points.device)
            depth = self.depth[k0:k0 + VIEW_CHUNK].to(points.device)  # [C,H,W]
            if nearest_around > 0:
                depth = _nearest_surface(depth.float(), nearest_around)
            views = torch.arange(len(cams), device=points.device)[:, None]
            for p0 in range(0, points.shape[0], FREE_POINTS_CHUNK):
                sl = slice(p0, p0 + FREE_POINTS_CHUNK)
                uv, z = project_points(points[sl].float(), cams.cam_from_world, cams.K)  # [C,S,2], [C,S]
                col = uv[..., 0].nan_to_num(0.0).floor().clamp(0, w - 1).long()
                row = uv[..., 1].nan_to_num(0.0).floor().clamp(0, h - 1).long()
                yield sl, _in_image(uv, z, w, h), z, depth[views, row, col]

    @torch.no_grad()
    def seen_behind(self, points: Tensor) -> Tensor:
        """[P] bool: whether every compared training view whose image holds each of ``points`` [P,3] (world), in front
        of it, rendered a surface nearer than the point (by more than ``DEPTH_TOLERANCE`` of its depth), and at least
        one holds it: every photo that looked toward the point saw something in front of it, so it lies inside an
        object or behind a wall. False for a point no compared view holds (nothing is known there: a photo's own
        camera stood at such places) and for one a view saw through (``seen_free``)."""
        held = torch.zeros(points.shape[0], dtype=torch.bool, device=points.device)
        passed = torch.zeros_like(held)  # some view holds it and does not see a surface in front of it
        for sl, inside, z, at in self._rendered_depths_at(points):
            behind = (at > 0.0) & (z > at * (1.0 + DEPTH_TOLERANCE))
            held[sl] |= inside.any(0)
            passed[sl] |= (inside & ~behind).any(0)
        return held & ~passed

    def _unlooked(self, points: Tensor, inside_any: Tensor) -> Tensor:
        """``_outside_every_image`` of ``POINTS_CHUNK`` points at a time (its projections of a whole large view into
        the other training cameras, [C,S] each, ran to hundreds of MB)."""
        return torch.cat([self._outside_every_image(points[b:b + POINTS_CHUNK], inside_any[b:b + POINTS_CHUNK])
                          for b in range(0, points.shape[0], POINTS_CHUNK)]) if points.shape[0] else ~inside_any

    def _outside_every_image(self, points: Tensor, inside_any: Tensor) -> Tensor:
        """[S] bool: the ``points`` [S,3] outside the image of every training camera, given ``inside_any`` [S] (inside
        some compared view's image): only the others are projected into the other training cameras (usually few)."""
        outside = ~inside_any
        if self.frustum_cameras is not None and bool(outside.any()):
            outside[outside.clone()] = ~self._looked_at(points[outside])
        return outside

    def _looked_at(self, points: Tensor) -> Tensor:
        """[S] bool: whether the image of some training camera (``frustum_cameras``) holds each point [S,3], in
        front of it."""
        cameras = self.frustum_cameras if self.frustum_cameras is not None else self.cameras
        cameras = cameras.to(points.device)
        looked = torch.zeros_like(points[:, 0], dtype=torch.bool)
        for k0 in range(0, len(cameras), VIEW_CHUNK):
            cams = cameras[k0:k0 + VIEW_CHUNK]
            uv, z = project_points(points, cams.cam_from_world, cams.K)  # [C,S,2], [C,S]
            looked |= _in_image(uv, z, cams.width, cams.height).any(0)
        return looked

    def _is_compared(self, camera: Cameras) -> bool:
        """Whether ``camera`` is one of the compared training views (e.g. one the std factor is fitted on)."""
        return bool(_same_camera(camera.to(self.cameras.cam_from_world.device), self.cameras).any())


def _cell_firsts(pixels: Tensor, width: int, count: int) -> Tensor:
    """[Q] for each of ``count`` points in the flat pixel indices ``pixels`` [Q] (ascending, of an image ``width``
    wide), the index of the first point in its square cell of t x t pixels, t the smallest that leaves at most
    ``GAP_POINTS`` cells holding points."""
    rows, cols = pixels // width, pixels % width
    t = max(2, math.ceil(math.sqrt(count / GAP_POINTS)))
    while True:
        cell = (rows // t) * (width // t + 1) + cols // t  # [Q]
        cells, inverse = torch.unique(cell, return_inverse=True)
        if cells.numel() <= GAP_POINTS:
            break
        t += 1
    first = torch.full((cells.numel(),), count, dtype=torch.long, device=pixels.device)
    first.scatter_reduce_(0, inverse, torch.arange(count, device=pixels.device), reduce="amin")
    return first[inverse]


def _behind_fractions() -> Tensor:
    """[GAP_SAMPLES] float64 the fractions s > 1 of the rendered depth behind a hidden surface point ``_free_gap``
    tests on transparent scenes: 1 + g, g as in ``_gap_fractions`` (the last s = 1.84)."""
    k = torch.arange(GAP_SAMPLES, dtype=torch.float64)
    return 1.0 + DEPTH_TOLERANCE * (1.0 / DEPTH_TOLERANCE) ** (k / GAP_SAMPLES)


def _gap_fractions() -> Tensor:
    """[GAP_SAMPLES] float64 the fractions s of the rendered depth ``_free_gap`` tests: 1 - g, g from
    ``DEPTH_TOLERANCE`` in geometric steps toward the camera (g = 1, the camera itself, is left out: a stretch that
    reaches it is the whole depth whatever is found there), 1.19x apart at 20 samples, the last s = 0.16."""
    k = torch.arange(GAP_SAMPLES, dtype=torch.float64)
    return 1.0 - DEPTH_TOLERANCE * (1.0 / DEPTH_TOLERANCE) ** (k / GAP_SAMPLES)


def _in_image(uv: Tensor, z: Tensor, width: int, height: int) -> Tensor:
    """[...] bool: projections ``uv`` [...,2] at camera depths ``z`` [...] that land in a ``width`` x ``height``
    image, in front of the camera."""
    return (z > 1e-9) & (uv[..., 0] >= 0) & (uv[..., 0] <= width) & (uv[..., 1] >= 0) & (uv[..., 1] <= height)


def _same_camera(a: Cameras, b: Cameras) -> Tensor:
    """[len(b)] bool: the cameras of ``b`` that are the one camera ``a`` (pose, intrinsics and image size)."""
    if (a.width, a.height) != (b.width, b.height):
        return torch.zeros(len(b), dtype=torch.bool)
    pose = (b.cam_from_world - a.cam_from_world.to(b.cam_from_world)).abs().flatten(1).amax(1) <= 1e-6
    return pose & ((b.K - a.K.to(b.K)).abs().flatten(1).amax(1) <= 1e-6)


def _nearest_surface(depth: Tensor, r: int) -> Tensor:
    """[C,H,W] the nearest rendered depth within ``r`` pixels of each pixel of ``depth`` [C,H,W] (0, a ray that met
    nothing, counts as no surface; 0 where none is near): at an object's outline the rendered depth blends the object
    with what lies behind it, and a point inside the object looked free from there."""
    far = torch.where(depth > 0, depth, torch.full_like(depth, float("inf")))
    near = -F.max_pool2d(-far[:, None], 2 * r + 1, stride=1, padding=r)[:, 0]
    return torch.where(torch.isfinite(near), near, torch.zeros_like(near))


def _depth_edges(depth: Tensor) -> Tensor:
    """[H,W] bool: the pixels whose 3x3 neighbourhood spans more than ``DEPTH_JUMP`` of their depth ``depth`` [H,W]:
    an object's outline, where the rendered depth blends two surfaces and the point it gives lies on neither."""
    d = depth[None, None]
    hi = F.max_pool2d(d, 3, stride=1, padding=1)
    lo = -F.max_pool2d(-d, 3, stride=1, padding=1)
    return ((hi - lo) > DEPTH_JUMP * depth[None, None])[0, 0]


def _window_mean(values: Tensor) -> Tensor:
    """[H,W] the weighted mean of ``values`` [H,W] over each ``(2 BLUR + 1)^2`` window (its part inside the image),
    with binomial weights (1 4 6 4 1 along each axis): a lone large difference spreads as a round blob that fades
    from its pixel, where a flat box drew a hard-edged square around it (a report panel showed one). The same
    numbers as the box within noise (2026-11-29: demo AUSE-MAE 0.1247 against 0.1249, NLL -3.4327 against -3.4321;
    half ring unseen-surface RGB AUC 0.948 against 0.949, AUSE-MAE 0.122 against 0.124; sparse views 0.121 against
    0.122). Pixels without a difference count as 0: averaged over the found ones alone, the few pixels at an
    occlusion's edge that find a view, often with a large difference, would spread over the whole window (half ring:
    AUSE-MAE 0.193 against 0.174, NLL -1.08 against -1.17)."""
    h, w = values.shape
    # shifted sums along each axis (separable): the two 5x5 conv2d of one channel took 130 ms at 1280x960 on the one
    # thread torch's ops get beside the native kernels, these 11 ms
    num = _binomial_sum(_binomial_sum(F.pad(values, (BLUR, BLUR, BLUR, BLUR)), 1, w), 0, h)  # [H,W]
    ones_w = _binomial_sum(values.new_ones(1, w + 2 * BLUR).index_fill_(1, _rim(w, values.device), 0.0), 1, w)[0]
    ones_h = _binomial_sum(values.new_ones(h + 2 * BLUR, 1).index_fill_(0, _rim(h, values.device), 0.0), 0, h)[:, 0]
    return num / (ones_h[:, None] * ones_w[None, :])  # the window's weight inside the image


def _binomial_sum(padded: Tensor, dim: int, size: int) -> Tensor:
    """The sum along ``dim`` of ``padded`` (``BLUR`` extra entries at each end) over each window of ``2 BLUR + 1``
    with binomial weights (1 4 6 4 1), ``size`` entries."""
    k = 2 * BLUR + 1
    out = padded.narrow(dim, 0, size).clone()  # (weight 1)
    for i in range(1, k):
        out.add_(padded.narrow(dim, i, size), alpha=math.comb(k - 1, i))
    return out


def _rim(size: int, device: torch.device) -> Tensor:
    """The indices of the ``BLUR`` padding entries at each end of an axis of ``size`` entries padded by them."""
    return torch.cat([torch.arange(BLUR), torch.arange(size + BLUR, size + 2 * BLUR)]).to(device)


__all__ = ["ViewConsistency", "capture_spacing"]
