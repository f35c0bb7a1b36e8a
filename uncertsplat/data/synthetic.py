"""A procedural synthetic scene with exact ground truth, rendered by our own ray caster.

The scene is a closed, textured room with a few objects on its floor (spheres, boxes, a cylinder).
Textures are solid (3D) procedural patterns: multi-octave value noise, checkers and stripes in varied
colours, and soft-edged speckles a few pixels across at demo resolution: enough corners for SIFT to match
every view, yet band-limited so that a Gaussian model can learn them (the room's walls, seen far away and at
grazing angles, get fainter detail than the objects). Generator version 1 had pixel-sized hard-edged
speckles: SfM was as easy, but the demo model plateaued far below what it reaches on version 2 (BENCHMARKS.md,
"The synthetic demo scene (v2 textures)"). Shading
is Lambertian with fixed lights, so the appearance does not depend on the viewing direction (what a
3DGS model with low SH degree can represent exactly).

Geometry is intersected analytically, in float64, for whole batches of rays at once. Rays are built as
``d = R^T K^-1 [u, v, 1]``, so the ray parameter ``t`` of a hit *is* the camera-space depth ``z``.
Colour uses 2x2 supersampling per pixel; depth and the validity mask come from the pixel-centre ray.

World frame: z up, the floor at ``z = -1``, objects within a radius of about 1.8 of the origin,
cameras at a distance of about 4 looking at the centre. Units are arbitrary ("metres"). Two camera rigs
(``SynthConfig.rig``): ``ring``, a jittered orbit at 22 +- 10 degrees elevation, and ``hemisphere``, cameras
spread over the upper hemisphere of radius 4 (10 to 75 degrees elevation), all looking exactly at
``LOOK_AT``, like the NeRF-synthetic scenes. With ``backdrop = "transparent"`` the room is left out: images
are RGBA with alpha = the fraction of a pixel's subsamples that hit an object, and the RGB is the mean
colour of those hits (straight alpha), so that compositing over any background is exact up to rounding.

Outputs of :func:`generate_scene` (``OUT/``), ``layout = "colmap"``::

    images/view_000.png   8-bit RGB (RGBA with the transparent backdrop)
    depth/view_000.npy    float32 [H,W] camera z of the surface at the pixel centre (0: nothing hit)
    masks/view_000.png    8-bit, 255 where depth is valid (every pixel with the room)
    sparse/0/*.bin        COLMAP model: PINHOLE camera, GT poses, visible surface points with tracks
    scene.json            ``SynthScene``: preset, seed, layout, rig, intrinsics, image names, test views, ...

``layout = "blender"`` (the NeRF-synthetic layout; no sparse points, as in those datasets)::

    transforms_train.json, transforms_test.json   camera_angle_x, frames [file_path, transform_matrix]
                                                  (camera-to-world, OpenGL camera axes)
    train/view_001.png, test/view_000.png         8-bit RGBA (opaque with the room)
    depth/, masks/, scene.json                    as above (one file per view, by stem)
"""

from __future__ import annotations

import contextlib
import math
import os
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from uncertsplat.config import SynthConfig
from uncertsplat.errors import UserError
from uncertsplat.io.folders import holds_files
from uncertsplat.schemas.scene import SynthScene

GENERATOR_VERSION = 2
SCENE_KIND = "uncertsplat-synthetic"

PRESETS: dict[str, dict] = {
    # for tests: a couple of seconds on a laptop CPU
    "tiny": {"num_views": 24, "width": 128, "points_per_view": 120},
    # the embedded demo scene
    "demo": {"num_views": 40, "width": 320, "points_per_view": 200},
}

_CHUNK = 1 << 17  # rays per batch: bounds memory for large image sizes
_EPS = 1e-9

# Room: x, y in [-ROOM, ROOM], z in [FLOOR, CEIL].
ROOM = 6.0
FLOOR = -1.0
CEIL = 5.0

# The hemisphere rig: every camera looks exactly at LOOK_AT from HEMI_RADIUS away.
LOOK_AT = (0.0, 0.0, FLOOR + 0.6)
HEMI_RADIUS = 4.0
HEMI_ELEVATION = (10.0, 75.0)  # degrees: none at floor level, none straight overhead (z up has no azimuth there)


@dataclass(frozen=True)
class Primitive:
    """One analytic object. ``kind`` is sphere | box | cylinder.

    sphere: ``size`` = (radius, -, -); box: ``size`` = half extents in its local frame, ``rot`` =
    world_from_local [3,3]; cylinder: vertical axis through ``center``, ``size`` = (radius, half height, -).
    """

    kind: str
    center: tuple[float, float, float]
    size: tuple[float, float, float]
    rot: tuple[tuple[float, ...], ...]
    colors: tuple[tuple[float, float, float], ...]  # three RGB colours of its texture
    pattern: str  # checker | stripes | noise
    freq: float  # base frequency of its pattern (cycles per unit)
    stripe_dir: tuple[float, float, float]


@dataclass(frozen=True)
class SceneSpec:
    """Everything that defines the synthetic scene's geometry and appearance (seeded, deterministic)."""

    objects: tuple[Primitive, ...]
    room_colors: tuple[tuple[float, float, float], ...]  # six faces x one colour each, plus accents
    noise_table: Tensor  # [G*G*G] float64 lattice values in [0, 1]
    grid: int
    room: bool = True  # False: the objects alone (rays that miss them hit nothing)

    def describe(self) -> list[dict]:
        return [
            {"kind": o.kind, "center": list(o.center), "size": list(o.size), "pattern": o.pattern} for o in self.objects
        ]


# ------------------------------------------------------------------------------------------ scene layout
def _hsv_to_rgb(h: float, s: float, v: float) -> tuple[float, float, float]:
    i = int(h * 6.0) % 6
    f = h * 6.0 - math.floor(h * 6.0)
    p, q, t = v * (1 - s), v * (1 - f * s), v * (1 - (1 - f) * s)
    return [(v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q)][i]


def _rand(g: torch.Generator, lo: float = 0.0, hi: float = 1.0) -> float:
    return lo + (hi - lo) * float(torch.rand((), generator=g, dtype=torch.float64))


def _palette(g: torch.Generator) -> tuple[tuple[float, float, float], ...]:
    """Three clearly different colours (hues apart by random steps, varied saturation and value)."""
    h = _rand(g)
    out = []
    for _ in range(3):
        out.append(_hsv_to_rgb(h % 1.0, _rand(g, 0.45, 0.95), _rand(g, 0.6, 1.0)))
        h += _rand(g, 0.15, 0.45)
    return tuple(out)


def make_scene_spec(seed: int, grid: int = 64, room: bool = True) -> SceneSpec:
    """The scene for ``seed``: object shapes, sizes, placement, colours and the noise lattice (``room``:
    inside the closed room, else the objects alone; the objects are the same either way)."""
    g = torch.Generator().manual_seed(int(seed) * 7919 + 17)
    patterns = ("checker", "stripes", "noise")

    def unit_dir() -> tuple[float, float, float]:
        v = torch.randn(3, generator=g, dtype=torch.float64)
        v = v / v.norm()
        return tuple(float(x) for x in v)

    def rot_z(a: float) -> tuple[tuple[float, ...], ...]:
        c, s = math.cos(a), math.sin(a)
        return ((c, -s, 0.0), (s, c, 0.0), (0.0, 0.0, 1.0))

    identity = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    objects: list[Primitive] = []
    # A large sphere near the centre.
    r = _rand(g, 0.6, 0.8)
    objects.append(Primitive("sphere", (_rand(g, -0.2, 0.2), _rand(g, -0.2, 0.2), FLOOR + r), (r, 0.0, 0.0),
                             identity, _palette(g), patterns[int(_rand(g, 0, 3)) % 3], _rand(g, 3.0, 5.0), unit_dir()))
    # Four smaller objects around it, at spread-out angles.
    a0 = _rand(g, 0.0, 2 * math.pi)
    kinds = ["box", "cylinder", "sphere", "box"]
    for k, kind in enumerate(kinds):
        ang = a0 + k * (2 * math.pi / len(kinds)) + _rand(g, -0.3, 0.3)
        dist = _rand(g, 1.15, 1.45)
        cx, cy = dist * math.cos(ang), dist * math.sin(ang)
        pattern = patterns[(k + int(_rand(g, 0, 3))) % 3]
        freq = _rand(g, 2.0, 4.0)
        if kind == "box":
            hx, hy, hz = _rand(g, 0.25, 0.45), _rand(g, 0.25, 0.45), _rand(g, 0.2, 0.55)
            objects.append(Primitive("box", (cx, cy, FLOOR + hz), (hx, hy, hz), rot_z(_rand(g, 0, math.pi)),
                                     _palette(g), pattern, freq, unit_dir()))
        elif kind == "cylinder":
            rc, hh = _rand(g, 0.25, 0.38), _rand(g, 0.5, 0.8)
            objects.append(Primitive("cylinder", (cx, cy, FLOOR + hh), (rc, hh, 0.0), identity, _palette(g),
                                     pattern, freq, unit_dir()))
        else:
            rs = _rand(g, 0.25, 0.4)
            objects.append(Primitive("sphere", (cx, cy, FLOOR + rs), (rs, 0.0, 0.0), identity, _palette(g),
                                     pattern, freq, unit_dir()))
    room_colors = _palette(g) + _palette(g)
    noise_table = torch.rand(grid**3, generator=g, dtype=torch.float64)
    return SceneSpec(tuple(objects), room_colors, noise_table, grid, room)


# ------------------------------------------------------------------------------------------ intersection
def _intersect_sphere(o: Tensor, d: Tensor, c: Tensor, r: float) -> tuple[Tensor, Tensor]:
    """Nearest positive hit of rays o + t d ([R,3]) with a sphere; t = inf on a miss. Returns t [R], n [R,3]."""
    oc = o - c
    a = (d * d).sum(-1)
    b = 2.0 * (oc * d).sum(-1)
    cc = (oc * oc).sum(-1) - r * r
    disc = b * b - 4 * a * cc
    sq = disc.clamp_min(0).sqrt()
    t0 = (-b - sq) / (2 * a)
    t1 = (-b + sq) / (2 * a)
    t = torch.where(t0 > _EPS, t0, t1)
    t = torch.where((disc >= 0) & (t > _EPS), t, torch.full_like(t, math.inf))
    p = o + t.nan_to_num(posinf=0.0)[:, None] * d
    n = (p - c) / r
    return t, n


def _slab(o: Tensor, d: Tensor, lo: Tensor, hi: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Slab test of rays against an axis-aligned box: per ray t_near, t_far and the axes reached."""
    safe = torch.where(d.abs() < 1e-12, torch.full_like(d, 1e-12), d)
    t1 = (lo - o) / safe
    t2 = (hi - o) / safe
    tmin = torch.minimum(t1, t2)
    tmax = torch.maximum(t1, t2)
    t_near, ax_near = tmin.max(-1)
    t_far, ax_far = tmax.min(-1)
    return t_near, t_far, ax_near, ax_far


def _intersect_box(o: Tensor, d: Tensor, c: Tensor, half: Tensor, rot: Tensor) -> tuple[Tensor, Tensor]:
    """Rays against an oriented box (rot = world_from_local [3,3]); hit from outside."""
    ol = (o - c) @ rot  # [R,3] local = rot^T (p - c)
    dl = d @ rot
    t_near, t_far, ax, _ = _slab(ol, dl, -half, half)
    hit = (t_far >= t_near) & (t_near > _EPS)
    t = torch.where(hit, t_near, torch.full_like(t_near, math.inf))
    n_local = torch.zeros_like(ol)
    sign = -torch.sign(dl.gather(1, ax[:, None]))
    n_local.scatter_(1, ax[:, None], sign)
    return t, n_local @ rot.T


def _intersect_cylinder(o: Tensor, d: Tensor, c: Tensor, r: float, hh: float) -> tuple[Tensor, Tensor]:
    """Rays against a closed vertical cylinder (axis z through c, radius r, half height hh)."""
    oc = o - c
    a = d[:, 0] ** 2 + d[:, 1] ** 2
    b = 2 * (oc[:, 0] * d[:, 0] + oc[:, 1] * d[:, 1])
    cc = oc[:, 0] ** 2 + oc[:, 1] ** 2 - r * r
    disc = b * b - 4 * a * cc
    a_safe = torch.where(a < 1e-12, torch.full_like(a, 1e-12), a)
    t_side = (-b - disc.clamp_min(0).sqrt()) / (2 * a_safe)
    z_side = oc[:, 2] + t_side * d[:, 2]
    ok_side = (disc >= 0) & (a > 1e-12) & (t_side > _EPS) & (z_side.abs() <= hh)
    t_side = torch.where(ok_side, t_side, torch.full_like(t_side, math.inf))
    dz = torch.where(d[:, 2].abs() < 1e-12, torch.full_like(a, 1e-12), d[:, 2])
    t_caps = []
    for zc in (hh, -hh):
        tc = (zc - oc[:, 2]) / dz
        px = oc[:, 0] + tc * d[:, 0]
        py = oc[:, 1] + tc * d[:, 1]
        ok = (tc > _EPS) & (px * px + py * py <= r * r)
        t_caps.append(torch.where(ok, tc, torch.full_like(tc, math.inf)))
    t = torch.minimum(t_side, torch.minimum(t_caps[0], t_caps[1]))
    p = oc + t.nan_to_num(posinf=0.0)[:, None] * d
    n_side = torch.stack([p[:, 0] / r, p[:, 1] / r, torch.zeros_like(a)], -1)
    n_cap = torch.zeros_like(p)
    n_cap[:, 2] = torch.sign(p[:, 2])
    n = torch.where((t == t_side)[:, None], n_side, n_cap)
    return t, n


def _intersect_room(o: Tensor, d: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Rays from inside against the room's walls: exit distance, inward normal and face index 0..5."""
    lo = torch.tensor([-ROOM, -ROOM, FLOOR], dtype=o.dtype, device=o.device)
    hi = torch.tensor([ROOM, ROOM, CEIL], dtype=o.dtype, device=o.device)
    _, t_far, _, ax = _slab(o, d, lo, hi)
    dir_sign = torch.sign(d.gather(1, ax[:, None]))[:, 0]  # leaving through the + or - face
    n = torch.zeros_like(o)
    n.scatter_(1, ax[:, None], -dir_sign[:, None])
    face = ax * 2 + (dir_sign > 0).long()
    t = torch.where(t_far > _EPS, t_far, torch.full_like(t_far, math.inf))
    return t, n, face


def trace(spec: SceneSpec, o: Tensor, d: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Closest hit of rays o + t d ([R,3] each, float64) with the scene.

    Returns:
        t [R] (inf where nothing is hit), normal [R,3], id [R] (0..5: room faces, 6+k: object k; 0 where
        nothing is hit).
    """
    if spec.room:
        t, n, ident = _intersect_room(o, d)
    else:
        t = torch.full_like(o[:, 0], math.inf)
        n = torch.zeros_like(o)
        ident = torch.zeros(o.shape[0], dtype=torch.long, device=o.device)
    for k, obj in enumerate(spec.objects):
        c = torch.tensor(obj.center, dtype=o.dtype, device=o.device)
        if obj.kind == "sphere":
            tk, nk = _intersect_sphere(o, d, c, obj.size[0])
        elif obj.kind == "box":
            half = torch.tensor(obj.size, dtype=o.dtype, device=o.device)
            rot = torch.tensor(obj.rot, dtype=o.dtype, device=o.device)
            tk, nk = _intersect_box(o, d, c, half, rot)
        elif obj.kind == "cylinder":
            tk, nk = _intersect_cylinder(o, d, c, obj.size[0], obj.size[1])
        else:  # pragma: no cover - the spec is built by make_scene_spec
            raise ValueError(obj.kind)
        closer = tk < t
        t = torch.where(closer, tk, t)
        n = torch.where(closer[:, None], nk, n)
        ident = torch.where(closer, torch.full_like(ident, 6 + k), ident)
    return t, n, ident


# --------------------------------------------------------------------------------------------- texturing
def _padded_table(spec: SceneSpec, device) -> Tensor:
    """The noise lattice [G,G,G] padded to [G+1]^3 by wrapping, flattened: corner i+1 needs no modulo."""
    G = spec.grid
    t = spec.noise_table.to(device=device, dtype=torch.float32).view(G, G, G)
    t = torch.cat([t, t[:1]], 0)
    t = torch.cat([t, t[:, :1]], 1)
    t = torch.cat([t, t[:, :, :1]], 2)
    return t.reshape(-1)


def _value_noise(spec: SceneSpec, table: Tensor, x: Tensor) -> Tensor:
    """Smooth 3D value noise in [0, 1] at lattice coordinates x [R,3] (trilinear with smoothstep).

    ``table`` is ``_padded_table(spec)``; one gather fetches all 8 corners.
    """
    G = spec.grid
    G1 = G + 1
    fl = torch.floor(x)
    f = x - fl
    f = f * f * (3 - 2 * f)
    i = fl.long() % G
    base = (i[:, 0] * G1 + i[:, 1]) * G1 + i[:, 2]  # [R]
    corners = torch.tensor([dx * G1 * G1 + dy * G1 + dz for dx in (0, 1) for dy in (0, 1) for dz in (0, 1)],
                           dtype=torch.long, device=x.device)
    v = table[base[:, None] + corners].view(-1, 2, 2, 2)  # [R,x,y,z]
    v = torch.lerp(v[..., 0], v[..., 1], f[:, 2, None, None])  # [R,2,2]
    v = torch.lerp(v[..., 0], v[..., 1], f[:, 1, None])  # [R,2]
    return torch.lerp(v[:, 0], v[:, 1], f[:, 0])


def _smoothstep(x: Tensor) -> Tensor:
    """0 below 0, 1 above 1, C1-smooth in between: soft thresholds keep textures band-limited."""
    x = x.clamp(0.0, 1.0)
    return x * x * (3 - 2 * x)


def _fbm(spec: SceneSpec, table: Tensor, x: Tensor, octaves: int) -> Tensor:
    total = torch.zeros(x.shape[0], dtype=x.dtype, device=x.device)
    amp, norm = 1.0, 0.0
    for k in range(octaves):
        # shift each octave so the lattices do not line up
        total = total + amp * _value_noise(spec, table, x * (2.0**k) + 17.3 * k)
        norm += amp
        amp *= 0.55
    return total / norm


def shade(spec: SceneSpec, p: Tensor, n: Tensor, ident: Tensor) -> Tensor:
    """Colour [R,3] in [0, 1] of surface points p [R,3] with normals n [R,3] on surfaces ``ident`` [R]."""
    dev, dt = p.device, torch.float32  # texture maths in float32: only geometry needs float64
    p = p.to(dt)
    n = n.to(dt)
    table = _padded_table(spec, dev)
    num = 6 + len(spec.objects)
    # Per-surface parameters gathered into per-ray rows.
    cols = torch.zeros(num, 3, 3, dtype=dt, device=dev)
    freq = torch.zeros(num, dtype=dt, device=dev)
    pat = torch.zeros(num, dtype=torch.long, device=dev)  # 0 checker, 1 stripes, 2 noise
    sdir = torch.zeros(num, 3, dtype=dt, device=dev)
    rc = spec.room_colors
    for f in range(6):
        cols[f] = torch.tensor([rc[f], rc[(f + 2) % 6], rc[(f + 4) % 6]], dtype=dt)
        freq[f] = 0.6 + 0.15 * f
        pat[f] = 0 if f >= 4 else (1 if f % 2 == 0 else 2)  # floor/ceiling checker, walls stripes/noise
        sdir[f] = torch.tensor([0.0, 0.0, 1.0] if f % 2 == 0 else [0.6, 0.6, 0.53], dtype=dt)
    for k, obj in enumerate(spec.objects):
        cols[6 + k] = torch.tensor(obj.colors, dtype=dt)
        freq[6 + k] = obj.freq
        pat[6 + k] = ("checker", "stripes", "noise").index(obj.pattern)
        sdir[6 + k] = torch.tensor(obj.stripe_dir, dtype=dt)
    c = cols[ident]  # [R,3,3]
    fr = freq[ident][:, None]
    offset = (ident.to(dt) * 11.7)[:, None]
    q = p * fr + offset

    coarse = _fbm(spec, table, q * 0.7, 2)  # [R] large blotches of colour
    fine = _fbm(spec, table, p * 2.5 + offset, 2)  # [R] detail of a few pixels at demo resolution
    checker = (torch.floor(q).long().sum(-1) % 2).to(dt)
    stripes = (torch.sin(2 * math.pi * (q * sdir[ident]).sum(-1) * 0.8) > 0).to(dt)
    pid = pat[ident]
    mask = torch.where(pid == 0, checker, torch.where(pid == 1, stripes, (coarse > 0.5).to(dt)))

    base = c[:, 0] * (1 - coarse[:, None]) + c[:, 1] * coarse[:, None]
    base = torch.where(mask[:, None] > 0.5, base, 0.55 * base + 0.45 * c[:, 2])
    # Speckles: dark/bright blobs of a few pixels give SIFT corners everywhere. The room (seen far away and
    # at grazing angles) gets fainter detail than the objects: its texture stays learnable at demo size.
    detail = torch.where(ident < 6, 0.4, 1.0).to(dt)[:, None]  # [R,1]
    speck = _value_noise(spec, table, p * 6.0 + offset + 3.1)
    base = base * (1.0 - 0.45 * detail + 0.6 * detail * fine[:, None])
    dark = _smoothstep((speck - 0.74) / 0.08)[:, None]
    bright = _smoothstep((0.24 - speck) / 0.08)[:, None]
    base = base * (1 - 0.65 * detail * dark)
    base = base + detail * bright * (0.5 - 0.5 * base)

    lights = torch.tensor([[0.4, 0.25, 0.88], [-0.6, -0.5, 0.62]], dtype=dt, device=dev)
    lights = lights / lights.norm(dim=-1, keepdim=True)
    lambert = (n @ lights.T).clamp_min(0) @ torch.tensor([0.55, 0.3], dtype=dt, device=dev)
    out = base * (0.45 + lambert)[:, None]
    return out.clamp(0.0, 1.0)


# ------------------------------------------------------------------------------------------------ cameras
def orbit_cameras(num_views: int, width: int, height: int, seed: int) -> tuple[Tensor, Tensor]:
    """GT cameras on a jittered orbit around the centre.

    Returns:
        cam_from_world [C,4,4] float64 (OpenCV axes), K [3,3] float64 (shared PINHOLE intrinsics).
    """
    g = torch.Generator().manual_seed(int(seed) * 104729 + 3)
    f = 1.0 * width  # horizontal field of view of about 53 degrees
    K = torch.tensor([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    step = 2 * math.pi / num_views
    mats = []
    for i in range(num_views):
        az = i * step + _rand(g, -0.25, 0.25) * step
        el = math.radians(22.0 + 10.0 * math.sin(2 * math.pi * 2 * i / num_views) + _rand(g, -3.0, 3.0))
        radius = 4.0 + _rand(g, -0.25, 0.25)
        center = torch.tensor([radius * math.cos(el) * math.cos(az), radius * math.cos(el) * math.sin(az),
                               FLOOR + 0.7 + radius * math.sin(el)], dtype=torch.float64)
        target = torch.tensor([_rand(g, -0.15, 0.15), _rand(g, -0.15, 0.15), FLOOR + 0.6], dtype=torch.float64)
        mats.append(look_at(center, target, up))
    return torch.stack(mats), K


def look_at(center: Tensor, target: Tensor, up: Tensor) -> Tensor:
    """cam_from_world [4,4] (OpenCV axes: z towards ``target``, y down) of a camera at ``center``."""
    z = target - center
    z = z / z.norm()
    x = torch.linalg.cross(z, up)
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    R = torch.stack([x, y, z])  # rows: camera axes in world coordinates
    M = torch.eye(4, dtype=torch.float64)
    M[:3, :3] = R
    M[:3, 3] = -R @ center
    return M


def hemisphere_cameras(num_views: int, width: int, height: int, seed: int,
                       test_every: int = 8) -> tuple[Tensor, Tensor]:
    """GT cameras spread over the upper hemisphere of radius ``HEMI_RADIUS`` around ``LOOK_AT``, all looking
    exactly at it (the NeRF-synthetic rig).

    The positions follow one golden-angle spiral (elevations even in area: sin(elevation) evenly spaced over
    ``HEMI_ELEVATION``, jittered), so the views cover the hemisphere evenly for any count. The held-out views (every
    ``test_every``-th) are the spiral's points chosen farthest from each other (from its middle), the others its
    remaining points in order: held-out views on every side, each as far from a training view as the spiral's
    spacing. (Every 8th point of the spiral itself lay 20 degrees of azimuth after the one before, since 8 golden
    angles are 20 degrees short of three turns: the held-out views of 40 sat within 100 degrees, on one side of the
    object; two spirals, one through each set, put a held-out view 4 degrees from a training one.)

    Returns:
        cam_from_world [C,4,4] float64 (OpenCV axes), K [3,3] float64 (shared PINHOLE intrinsics).
    """
    g = torch.Generator().manual_seed(int(seed) * 104729 + 7)
    f = 1.0 * width  # the same intrinsics as the ring
    K = torch.tensor([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    target = torch.tensor(LOOK_AT, dtype=torch.float64)
    lo, hi = (math.sin(math.radians(e)) for e in HEMI_ELEVATION)
    golden = math.pi * (3.0 - math.sqrt(5.0))
    az0 = _rand(g, 0.0, 2 * math.pi)
    dirs = []
    for j in range(num_views):
        u = (j + 0.5 + _rand(g, -0.3, 0.3)) / num_views
        el = math.asin(lo + (hi - lo) * u)
        az = az0 + j * golden
        dirs.append([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    dirs_t = torch.tensor(dirs, dtype=torch.float64).reshape(-1, 3)  # [C,3] unit directions from the target
    held = []
    if num_views:
        held = [num_views // 2]  # farthest-point sampling from the middle of the spiral
        near = (dirs_t @ dirs_t[held[0]]).clamp(-1.0, 1.0).acos()  # [C] angle to the nearest chosen point
        for _ in range((num_views + test_every - 1) // test_every - 1):
            held.append(int(torch.argmax(near)))
            near = torch.minimum(near, (dirs_t @ dirs_t[held[-1]]).clamp(-1.0, 1.0).acos())
    chosen = set(held)
    held_iter, rest_iter = iter(held), iter(j for j in range(num_views) if j not in chosen)
    order = [next(held_iter) if i % test_every == 0 else next(rest_iter) for i in range(num_views)]
    mats = [look_at(target + HEMI_RADIUS * dirs_t[j], target, up) for j in order]
    return torch.stack(mats), K


def pixel_rays(cam_from_world: Tensor, K: Tensor, uv: Tensor) -> tuple[Tensor, Tensor]:
    """World rays through pixel positions uv [R,2] (pixel centres at +0.5), with unit camera-z direction."""
    R = cam_from_world[:3, :3]
    center = -R.T @ cam_from_world[:3, 3]
    x = (uv[:, 0] - K[0, 2]) / K[0, 0]
    y = (uv[:, 1] - K[1, 2]) / K[1, 1]
    d_cam = torch.stack([x, y, torch.ones_like(x)], -1)
    d = d_cam @ R  # R^T d_cam for each row
    return center.expand_as(d), d


def render_view(spec: SceneSpec, cam_from_world: Tensor, K: Tensor, width: int, height: int,
                supersample: int = 2) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Ray-cast one view.

    Returns:
        rgb [H,W,3] float64 (mean colour of the supersample^2 rays per pixel that hit a surface: straight
        alpha; 0 where none does), depth [H,W] float64 camera z of the pixel-centre ray (0 where nothing is
        hit), valid [H,W] bool, alpha [H,W] float64 (fraction of the rays that hit; 1 everywhere in the room).
    """
    dt = torch.float64
    ys, xs = torch.meshgrid(torch.arange(height, dtype=dt), torch.arange(width, dtype=dt), indexing="ij")
    centres = torch.stack([xs + 0.5, ys + 0.5], -1).reshape(-1, 2)  # [H*W,2]
    s = supersample
    offs = (torch.arange(s, dtype=dt) + 0.5) / s - 0.5
    oy, ox = torch.meshgrid(offs, offs, indexing="ij")
    sub = torch.stack([ox, oy], -1).reshape(-1, 2)  # [S,2]

    depth = torch.empty(height * width, dtype=dt)
    for a in range(0, centres.shape[0], _CHUNK):
        o, d = pixel_rays(cam_from_world, K, centres[a : a + _CHUNK])
        t, _, _ = trace(spec, o, d)
        depth[a : a + _CHUNK] = t
    samples = (centres[:, None, :] + sub[None]).reshape(-1, 2)  # [H*W*S,2], pixel-major
    rgb = torch.empty(samples.shape[0], 3, dtype=dt)
    hits = torch.empty(samples.shape[0], dtype=dt)
    for a in range(0, samples.shape[0], _CHUNK):
        o, d = pixel_rays(cam_from_world, K, samples[a : a + _CHUNK])
        t, n, ident = trace(spec, o, d)
        hit = torch.isfinite(t)
        p = o + t.nan_to_num(posinf=0.0)[:, None] * d
        col = shade(spec, p, n, ident)
        rgb[a : a + _CHUNK] = torch.where(hit[:, None], col.to(dt), torch.zeros_like(o))
        hits[a : a + _CHUNK] = hit.to(dt)
    alpha = hits.reshape(height * width, s * s).mean(1)
    rgb = rgb.reshape(height * width, s * s, 3).mean(1)
    if not spec.room:  # straight alpha: the mean colour of the hits (with the room every ray hits: as is)
        rgb = torch.where(alpha[:, None] > 0, rgb / alpha.clamp_min(1e-12)[:, None], torch.zeros_like(rgb))
    valid = torch.isfinite(depth)
    depth = torch.where(valid, depth, torch.zeros_like(depth))
    return (rgb.reshape(height, width, 3), depth.reshape(height, width), valid.reshape(height, width),
            alpha.reshape(height, width))


# ---------------------------------------------------------------------------------------- sparse points
@dataclass(frozen=True)
class SparsePoints:
    """GT surface points and where they are seen. xyz [P,3], rgb [P,3] in [0,1];
    tracks[p] = ((view index, u, v), ...) with pixel coordinates (centres at +0.5)."""

    xyz: Tensor
    rgb: Tensor
    tracks: tuple[tuple[tuple[int, float, float], ...], ...]


def sample_sparse_points(spec: SceneSpec, cam_from_world: Tensor, K: Tensor, width: int, height: int,
                         depths: list[Tensor], images: list[Tensor], per_view: int, seed: int,
                         min_track: int = 2) -> SparsePoints:
    """Surface points seen in at least ``min_track`` views, like a perfect SfM would triangulate.

    In each view, ``per_view`` random pixels are lifted to the surface with their GT depth; a point is
    visible in another view when it projects inside the image and the ray from that camera to the point
    hits nothing closer (an exact occlusion test with the ray caster).
    """
    g = torch.Generator().manual_seed(int(seed) * 31 + 5)
    C = cam_from_world.shape[0]
    pts, cols = [], []
    for i in range(C):
        pix = torch.randperm(height * width, generator=g)[:per_view]
        v, u = pix // width, pix % width
        uv = torch.stack([u.to(torch.float64) + 0.5, v.to(torch.float64) + 0.5], -1)
        o, d = pixel_rays(cam_from_world[i], K, uv)
        z = depths[i][v, u]
        keep = z > 0
        pts.append((o + z[:, None] * d)[keep])
        cols.append(images[i][v, u][keep])
    xyz = torch.cat(pts)
    rgb = torch.cat(cols)
    P = xyz.shape[0]
    homog = torch.cat([xyz, torch.ones(P, 1, dtype=xyz.dtype)], -1)
    seen = torch.zeros(C, P, dtype=torch.bool)
    uvs = torch.zeros(C, P, 2, dtype=xyz.dtype)
    for j in range(C):
        pc = homog @ cam_from_world[j].T  # [P,4]
        z = pc[:, 2]
        uv = (pc[:, :3] @ K.T)[:, :2] / z.clamp_min(1e-9)[:, None]
        inside = (z > 1e-6) & (uv[:, 0] >= 0) & (uv[:, 0] <= width) & (uv[:, 1] >= 0) & (uv[:, 1] <= height)
        center = -cam_from_world[j, :3, :3].T @ cam_from_world[j, :3, 3]
        o = center.expand(P, 3)
        t, _, _ = trace(spec, o, xyz - o)  # t = 1 at the point itself
        seen[j] = inside & (t >= 1.0 - 1e-6)
        uvs[j] = uv
    keep = seen.sum(0) >= min_track
    # Python lists, not tensor indexing, for the per-observation loop: 100k observations in 0.1 s instead of 1 s
    seen_rows = seen[:, keep].T.tolist()  # [P_kept][C]
    uv_rows = uvs[:, keep].permute(1, 0, 2).tolist()  # [P_kept][C][2]
    tracks = tuple(
        tuple((j, uv[j][0], uv[j][1]) for j, s in enumerate(row) if s)
        for row, uv in zip(seen_rows, uv_rows, strict=True)
    )
    return SparsePoints(xyz[keep], rgb[keep], tracks)


# ------------------------------------------------------------------------------------------------ writing
def resolve_size(cfg: SynthConfig) -> tuple[int, int, int, int]:
    """(num_views, width, height, points_per_view) for a config: the preset, then explicit overrides."""
    preset = PRESETS[cfg.preset]
    width = cfg.width or preset["width"]
    height = max(1, round(width * 3 / 4))
    num_views = cfg.num_views or preset["num_views"]
    return num_views, width, height, preset["points_per_view"]


def _claims_to_be_synthetic(meta: Path) -> bool:
    """Whether a ``scene.json`` that failed validation says it is a synthetic scene's (its ``kind``)."""
    import json

    try:
        data = json.loads(meta.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError):
        return False
    return isinstance(data, dict) and data.get("kind") == SCENE_KIND


def read_scene_meta(path: Path) -> SynthScene | None:
    """The ``SynthScene`` of a folder written by :func:`generate_scene`, or None when ``path/scene.json`` is
    missing, unreadable, or another file of that name (a run's ``scene.json``, someone else's).

    Raises:
        UserError: the file says it is a synthetic scene's but does not match the schema (naming the key).
    """
    meta = Path(path) / "scene.json"
    if not meta.is_file():
        return None
    try:
        found = SynthScene.read(meta)
    except UserError:
        if _claims_to_be_synthetic(meta):
            raise
        return None
    return found if found.kind == SCENE_KIND else None


def is_synthetic_scene(path: Path) -> bool:
    """True when ``path`` holds a valid scene written by :func:`generate_scene`."""
    try:
        return read_scene_meta(path) is not None
    except UserError:
        return False


# What the generator writes, per layout: replaced on --overwrite, never anything else.
_OUTPUTS = {"colmap": ("images", "depth", "masks", "sparse", "scene.json"),
            "blender": ("train", "test", "transforms_train.json", "transforms_test.json", "depth", "masks",
                        "scene.json")}


def make_cameras(cfg: SynthConfig, num_views: int, width: int, height: int) -> tuple[Tensor, Tensor]:
    """The GT cameras of ``cfg.rig``: cam_from_world [C,4,4] float64 (OpenCV axes), K [3,3] float64."""
    if cfg.rig == "hemisphere":
        return hemisphere_cameras(num_views, width, height, cfg.seed, cfg.test_every)
    return orbit_cameras(num_views, width, height, cfg.seed)


def opengl_camera_to_world(cam_from_world: Tensor) -> Tensor:
    """Camera-to-world [C,4,4] in OpenGL camera axes (x right, y up, z backward), as Blender and nerfstudio
    write ``transform_matrix``, from OpenCV ``cam_from_world`` [C,4,4]."""
    c2w = torch.linalg.inv(cam_from_world.to(torch.float64))
    c2w[:, :3, 1:3] *= -1.0
    return c2w


@contextlib.contextmanager
def _one_thread():
    """Run the ray caster on one intra-op thread, restoring the caller's setting afterwards; yields the
    caller's thread count.

    On a machine whose cores are busy with other work, OpenMP's spinning barriers made the caster's
    elementwise ops an order of magnitude slower with two intra-op threads (BENCHMARKS.md, "Synthetic
    scenes"). The cores are used instead by rendering whole views on that many Python threads, each with
    one intra-op thread (:func:`_render_views`): no barrier to spin on, and torch releases the GIL inside
    every op.
    """
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield before
    finally:
        torch.set_num_threads(before)


def _render_views(spec: SceneSpec, cam_from_world: Tensor, K: Tensor, width: int, height: int, workers: int):
    """Yield ``render_view`` of every camera of ``cam_from_world`` [C,4,4], in order, rendered on up to
    ``workers`` threads with at most ``2 * workers`` views in flight (memory stays bounded for large images).

    Each view is a pure function of its camera, so the results are bit-identical to rendering one after another.
    """
    count = cam_from_world.shape[0]
    workers = max(1, min(int(workers), count))
    if workers == 1:
        for i in range(count):
            yield render_view(spec, cam_from_world[i], K, width, height)
        return
    from collections import deque
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(workers, thread_name_prefix="synth") as pool:
        pending: deque = deque()
        nxt = 0
        try:
            for _ in range(count):
                while nxt < count and len(pending) < 2 * workers:
                    pending.append(pool.submit(render_view, spec, cam_from_world[nxt], K, width, height))
                    nxt += 1
                yield pending.popleft().result()
        finally:  # an error or an abandoned generator: do not start the views not yet begun
            for future in pending:
                future.cancel()


def generate_scene(out: Path, cfg: SynthConfig, overwrite: bool = False,
                   on_view: Callable[[int, int], None] | None = None) -> Path:
    """Render the synthetic scene for ``cfg`` into ``out`` (layout in the module docstring).

    The scene is first written to a temporary sibling folder and moved into place at the end, so an
    interrupted run leaves no half-written scene behind.

    Args:
        out: output folder; must be missing or empty unless ``overwrite`` (then only the generator's own
            outputs in it are replaced).
        cfg: preset, seed and overrides.
        overwrite: replace an existing scene.
        on_view: called as ``on_view(done, total)`` after each rendered view (progress bars).

    Returns:
        ``out``.
    """
    with _one_thread() as cores:
        return _generate(Path(out), cfg, overwrite, on_view, workers=cores)


def _generate(out: Path, cfg: SynthConfig, overwrite: bool, on_view, workers: int = 1) -> Path:
    from uncertsplat.io.atomic import atomic_write, atomic_write_json, temp_folder, temp_stem
    from uncertsplat.io.images import write_png
    from uncertsplat.sfm.colmap_io import write_colmap_model

    if out.exists() and not out.is_dir():
        raise UserError("the output path exists and is not a folder", path=out, hint="Choose a folder path.")
    if holds_files(out) and not overwrite:
        raise UserError("the output folder is not empty", path=out,
                        hint="Choose a new folder or pass --overwrite to replace the scene in it.")

    num_views, width, height, per_view = resolve_size(cfg)
    room = cfg.backdrop == "room"
    blender = cfg.layout == "blender"
    spec = make_scene_spec(cfg.seed, room=room)
    cam_from_world, K = make_cameras(cfg, num_views, width, height)
    names = [f"view_{i:03d}" for i in range(num_views)]
    is_test = [i % cfg.test_every == 0 for i in range(num_views)]
    test = [f"{n}.png" for n, t in zip(names, is_test, strict=True) if t]

    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_folder(f".{temp_stem(out.name)}.synth-", out.parent)
    try:
        images, depths = [], []
        # closing(): an error while writing stops the render threads before the temporary folder goes
        with contextlib.closing(_render_views(spec, cam_from_world, K, width, height, workers)) as views:
            for i, (name, (rgb, depth, valid, alpha)) in enumerate(zip(names, views, strict=True)):
                rgb8 = torch.round(rgb.clamp(0, 1) * 255).to(torch.uint8)
                if blender or not room:  # RGBA: Blender scenes always are; alpha carries the transparent backdrop
                    a8 = torch.round(alpha.clamp(0, 1) * 255).to(torch.uint8)
                    pixels = torch.cat([rgb8, a8[..., None]], -1).numpy()
                else:
                    pixels = rgb8.numpy()
                folder = ("test" if is_test[i] else "train") if blender else "images"
                write_png(tmp / folder / f"{name}.png", pixels)
                d32 = depth.to(torch.float32).numpy()
                atomic_write(tmp / "depth" / f"{name}.npy", lambda f, a=d32: np.save(f, a, allow_pickle=False))
                write_png(tmp / "masks" / f"{name}.png", (valid.numpy()[..., None].astype(np.uint8) * 255))
                images.append(rgb8.to(torch.float64) / 255.0)
                depths.append(depth)
                if on_view is not None:
                    on_view(i + 1, num_views)
        num_points = 0
        if blender:
            # The NeRF-synthetic layout: no sparse points (training starts from random points, as for those).
            c2w = opengl_camera_to_world(cam_from_world)
            angle_x = 2.0 * math.atan(0.5 * width / float(K[0, 0]))
            for split, want in (("train", False), ("test", True)):
                frames = [{"file_path": f"./{split}/{n}", "transform_matrix": c2w[i].tolist()}
                          for i, n in enumerate(names) if is_test[i] == want]
                # an external format (read by other tools), not one of our schema files
                atomic_write_json(tmp / f"transforms_{split}.json", {"camera_angle_x": angle_x, "frames": frames})
        else:
            sparse = sample_sparse_points(spec, cam_from_world, K, width, height, depths, images, per_view, cfg.seed)
            write_colmap_model(tmp / "sparse" / "0", cam_from_world.numpy(), K.numpy(), width, height,
                               [f"{n}.png" for n in names], sparse.xyz.numpy(), sparse.rgb.numpy(), sparse.tracks)
            num_points = int(sparse.xyz.shape[0])
        valid_text = "every pixel (the room is closed)" if room else "pixels whose centre ray hits an object"
        units = "the units of the transforms files" if blender else "the units of sparse/0"
        SynthScene(
            kind=SCENE_KIND,
            layout=cfg.layout,
            rig=cfg.rig,
            backdrop=cfg.backdrop,
            look_at=list(LOOK_AT) if cfg.rig == "hemisphere" else None,
            generator_version=GENERATOR_VERSION,
            preset=cfg.preset,
            seed=cfg.seed,
            width=width,
            height=height,
            num_views=num_views,
            intrinsics={"model": "PINHOLE", "fx": float(K[0, 0]), "fy": float(K[1, 1]), "cx": float(K[0, 2]),
                        "cy": float(K[1, 2])},
            image_names=[f"{n}.png" for n in names],
            test_every=cfg.test_every,
            test_views=test,
            num_points=num_points,
            depth=f"depth/{{stem}}.npy: float32 camera z of the pixel-centre ray, in {units} (0: nothing hit)",
            mask=f"masks/{{stem}}.png: 255 where the depth is valid: {valid_text}",
            room={"half_width": ROOM, "floor": FLOOR, "ceiling": CEIL} if room else None,
            objects=spec.describe(),
            config=cfg.model_dump(mode="json"),
        ).write(tmp / "scene.json")
        # Move into place: replace only what the generator writes, never other files of the user.
        if not out.exists():
            os.replace(tmp, out)
        else:
            try:  # a scene of the other layout goes too: the folder holds one scene
                old = read_scene_meta(out)
            except UserError:
                old = None
            items = dict.fromkeys(_OUTPUTS[cfg.layout] + (_OUTPUTS[old.layout] if old is not None else ()))
            for item in items:
                target = out / item
                if target.is_dir():
                    shutil.rmtree(target)
                elif target.exists():
                    target.unlink()
                if (tmp / item).exists():
                    os.replace(tmp / item, target)
            shutil.rmtree(tmp, ignore_errors=True)
    except BaseException:
        with contextlib.suppress(OSError):
            shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out
