"""Two clouds of the same surfaces placed on each other without matches (``sfm.align.register_clouds``).

What a 3DGS model trained in a frame of its own needs (``train --from-ply``, ``init_ply_frame = "align"``): the
scene's sparse points (the source cloud) found on the model's Gaussians (the destination) whatever the similarity
between them, including turns that principal axes alone cannot tell apart (a half turn flips two of them; nearly
equal axes leave the turn about the third free), clouds that hold points the other lacks, and a few far outliers.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from uncertsplat.sfm.align import MIN_FIRMNESS, MIN_POINTS, Registration, placement_residual, register_clouds


def _room(rng: np.random.Generator, n: int, size=(4.0, 2.5, 3.0)) -> np.ndarray:
    """Points on the floor and walls of a box room with a few objects: planes and a sphere, unequal sides."""
    sx, sy, sz = size
    face = rng.integers(0, 6, n)
    u, v = rng.random(n), rng.random(n)
    pts = np.zeros((n, 3))
    pts[face == 0] = np.stack([u * sx, np.zeros(n), v * sz], -1)[face == 0]  # floor
    pts[face == 1] = np.stack([u * sx, v * sy, np.zeros(n)], -1)[face == 1]  # back wall
    pts[face == 2] = np.stack([np.zeros(n), u * sy, v * sz], -1)[face == 2]  # left wall
    pts[face == 3] = np.stack([np.full(n, sx), u * sy, v * sz], -1)[face == 3]  # right wall
    d = rng.normal(size=(n, 3))
    sphere = 0.4 * d / np.linalg.norm(d, axis=1, keepdims=True) + np.array([1.2, 0.4, 1.5])
    pts[face == 4] = sphere[face == 4]
    pts[face == 5] = np.stack([2.5 + 0.6 * u, 0.3 * v, 0.8 + 0.5 * rng.random(n)], -1)[face == 5]  # a box
    return pts


def _turn(rng: np.random.Generator) -> np.ndarray:
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def _about(axis: np.ndarray, degrees: float) -> np.ndarray:
    k = axis / np.linalg.norm(axis)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    a = math.radians(degrees)
    return np.eye(3) + math.sin(a) * kx + (1 - math.cos(a)) * kx @ kx


def _similarity(s: float, r: np.ndarray, t) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = s * r, t
    return m


def _place(points: np.ndarray, m: np.ndarray) -> np.ndarray:
    return points @ m[:3, :3].T + m[:3, 3]


def _errors(found: Registration, truth: np.ndarray, src: np.ndarray) -> tuple[float, float]:
    """(the largest distance between the two placements of ``src`` over the placed cloud's radius, the turn's angle
    between them in degrees)."""
    a, b = _place(src, found.dst_from_src), _place(src, truth)
    radius = float(np.sqrt(((b - b.mean(0)) ** 2).sum(1).mean()))
    ra, rb = found.dst_from_src[:3, :3], truth[:3, :3]
    rel = (ra / np.cbrt(np.linalg.det(ra))) @ (rb / np.cbrt(np.linalg.det(rb))).T
    angle = math.degrees(math.acos(np.clip((np.trace(rel) - 1) / 2, -1, 1)))
    return float(np.linalg.norm(a - b, axis=1).max()) / radius, angle


class TestRegisterClouds:
    @pytest.mark.parametrize("case", range(4))
    def test_finds_a_random_similarity(self, case):
        """Any turn, a scale from 1/20 to 20 and a far shift: the sparse points (a sample of the surfaces) land on
        the Gaussians (a denser sample with their own noise) to a fraction of a percent."""
        rng = np.random.default_rng(case)
        surface = _room(rng, 12000)
        src = surface[:1000] + rng.normal(scale=0.005, size=(1000, 3))
        dst_run = surface[1000:] + rng.normal(scale=0.005, size=(11000, 3))
        truth = _similarity(float(np.exp(rng.uniform(-3, 3))), _turn(rng), rng.normal(scale=50.0, size=3))
        found = register_clouds(src, _place(dst_run, truth))
        shift, angle = _errors(found, truth, src)
        assert shift < 0.01 and angle < 0.3, (shift, angle)
        assert found.scale == pytest.approx(np.cbrt(np.linalg.det(truth[:3, :3])), rel=0.005)
        assert found.residual < 0.02  # a sparse sample of the surfaces: the NN distances of 11k points

    @pytest.mark.parametrize("seed, size, axis, degrees, scale, shift", [
        # a half turn about the longest axis maps the principal axes onto themselves up to sign: the search must try
        # the signs, not take the axes as they come
        (7, (6.0, 2.0, 3.0), (1.0, 0.0, 0.0), 180.0, 1.0, (0.3, 0.0, 0.0)),
        # a cube-like room (equal sides: its principal axes are any axes of the plane of two equal ones) turned by 45
        # degrees about one axis, halfway between the starts of the signed permutations
        (11, (3.0, 3.0, 3.0), (0.0, 1.0, 0.0), 45.0, 2.0, (1.0, 2.0, 3.0)),
    ], ids=["half-turn", "equal-axes"])
    def test_turns_the_principal_axes_cannot_tell(self, seed, size, axis, degrees, scale, shift):
        """Turns that the two clouds' principal axes alone do not give are found from the other starts."""
        rng = np.random.default_rng(seed)
        surface = _room(rng, 10000, size=size)
        src, dst_run = surface[:1000], surface[1000:]
        truth = _similarity(scale, _about(np.array(axis), degrees), list(shift))
        found = register_clouds(src, _place(dst_run, truth))
        shift_err, angle = _errors(found, truth, src)
        assert shift_err < 0.01 and angle < 0.3, (shift_err, angle)

    def test_clouds_with_parts_the_other_lacks(self):
        """The Gaussians hold a background the SfM points lack (a far sky shell, a tenth of them) and the points hold
        outliers the Gaussians lack (3 % lone far points): the trimmed matches leave both out."""
        rng = np.random.default_rng(5)
        surface = _room(rng, 10000)
        d = rng.normal(size=(1000, 3))
        sky = 30.0 * d / np.linalg.norm(d, axis=1, keepdims=True) + surface.mean(0)
        dst_run = np.concatenate([surface[1000:], sky])
        src = np.concatenate([surface[:1000], rng.uniform(-40, 40, size=(30, 3))])
        truth = _similarity(0.3, _turn(rng), [5.0, -1.0, 2.0])
        found = register_clouds(src, _place(dst_run, truth))
        shift, angle = _errors(found, truth, surface[:1000])
        assert shift < 0.01 and angle < 0.3, (shift, angle)

    @pytest.mark.parametrize("sky", [0.5, 1.0])
    def test_a_background_as_large_as_the_surfaces(self, sky):
        """A sky shell of half as many Gaussians as the surfaces, or as many (an unbounded scene's model): the shell
        swells the model's 90 % core, whose radius alone set the scale's bounds 8x around a ratio 9x the true
        scale, which then stuck at the bound with the points a third of their radius off (residual 0.03)."""
        rng = np.random.default_rng(5)
        surface = _room(rng, 10000)
        d = rng.normal(size=(int(sky * 9000), 3))
        shell = 30.0 * d / np.linalg.norm(d, axis=1, keepdims=True) + surface.mean(0)
        truth = _similarity(0.3, _turn(rng), [5.0, -1.0, 2.0])
        found = register_clouds(surface[:1000], _place(np.concatenate([surface[1000:], shell]), truth))
        shift, angle = _errors(found, truth, surface[:1000])
        assert shift < 0.01 and angle < 0.3, (shift, angle)

    def test_residual_tells_a_placement_from_a_wrong_one(self):
        """``placement_residual`` of the true similarity is the found one's; of the identity (a model read in the
        wrong frame) it is tens of times larger."""
        rng = np.random.default_rng(2)
        surface = _room(rng, 10000)
        src, dst_run = surface[:1000], surface[1000:]
        truth = _similarity(0.5, _turn(rng), [1.0, 1.0, 1.0])
        dst = _place(dst_run, truth)
        found = register_clouds(src, dst)
        right = placement_residual(src, dst, truth)
        assert right == pytest.approx(found.residual, rel=0.2)
        assert placement_residual(src, dst, np.eye(4)) > 20 * right

    def test_deterministic(self):
        rng = np.random.default_rng(9)
        surface = _room(rng, 10000)
        dst = _place(surface[1000:], _similarity(2.0, _turn(rng), [0.0, 1.0, 0.0]))
        a = register_clouds(surface[:1000], dst, seed=3)
        b = register_clouds(surface[:1000], dst, seed=3)
        np.testing.assert_array_equal(a.dst_from_src, b.dst_from_src)

    def test_too_few_points(self):
        rng = np.random.default_rng(0)
        few = rng.normal(size=(MIN_POINTS - 1, 3))
        many = rng.normal(size=(500, 3))
        with pytest.raises(ValueError, match="at least"):
            register_clouds(few, many)
        with pytest.raises(ValueError, match="at least"):
            register_clouds(many, np.concatenate([few, np.full((10, 3), np.nan)]))


def _flat(rng: np.random.Generator, n: int, lo=(-2.0, -1.0), hi=(1.0, 1.0)) -> np.ndarray:
    """Points on one plane (a facade, a table top seen from above): texture blobs, as SfM finds them, in a
    rectangle, with a little noise off the plane."""
    centres = rng.uniform(lo, hi, (30, 2))
    xy = centres[rng.integers(0, 30, n)] + rng.normal(scale=0.15, size=(n, 2))
    return np.concatenate([xy, rng.normal(scale=0.005, size=(n, 1))], axis=1)


class TestFirmness:
    """``Registration.firmness``: clouds that do not pin a similarity (all points on one plane or along one line, so
    that the placed points slide along the surfaces without leaving them) are told from ones that do, whatever the
    small residual both get."""

    def test_a_flat_cloud_is_not_pinned(self):
        """The points on a plane, the Gaussians on a larger part of it: the residual is that of a right placement,
        yet the found one is far off (measured: twice the scale, turned half round), so firmness says so."""
        rng = np.random.default_rng(1)
        src = _flat(rng, 1500)
        plane = np.concatenate([rng.uniform((-3, -2), (3, 2), (30000, 2)),
                                rng.normal(scale=0.005, size=(30000, 1))], axis=1)
        found = register_clouds(src, _place(plane, _similarity(0.37, _turn(rng), [1.0, -2.0, 0.5])))
        assert found.residual < 0.02  # as low as a right placement's: the residual alone cannot tell
        assert found.firmness < MIN_FIRMNESS, found.firmness

    def test_a_line_like_cloud_is_not_pinned(self):
        """Points along a corridor (a line with a little spread), the Gaussians on a long thin tube about it."""
        rng = np.random.default_rng(2)
        src = np.stack([rng.uniform(-3, 3, 1500), *rng.normal(scale=0.03, size=(2, 1500))], axis=1)
        ang = rng.uniform(0, 2 * np.pi, 30000)
        tube = np.stack([rng.uniform(-4, 4, 30000), 0.04 * np.cos(ang), 0.04 * np.sin(ang)], axis=1)
        found = register_clouds(src, _place(tube, _similarity(2.0, _turn(rng), [0.0, 1.0, 0.0])))
        assert found.firmness < MIN_FIRMNESS, found.firmness

    @pytest.mark.parametrize("points", [80, 1000])
    def test_a_room_is_pinned(self, points):
        """Floor, walls and objects pin every motion, from few sparse points too."""
        rng = np.random.default_rng(3)
        surface = _room(rng, 11000 + points)
        truth = _similarity(0.5, _turn(rng), [1.0, 2.0, 3.0])
        found = register_clouds(surface[:points], _place(surface[points:], truth))
        shift, angle = _errors(found, truth, surface[:points])
        assert shift < 0.02 and angle < 1.0, (shift, angle)
        assert found.firmness > MIN_FIRMNESS, found.firmness
