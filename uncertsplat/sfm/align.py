"""Point sets placed on each other by a similarity (x_dst = s R x_src + t).

``similarity_align`` is the least-squares similarity of matched points (Umeyama 1991: SfM cameras on reference
poses). ``register_clouds`` finds one for two clouds of the same surfaces without matches: the Gaussians of a 3DGS
model that another tool trained in a frame of its own (normalised, turned to its principal axes) and the scene's
sparse points (``train --from-ply``, ``TrainConfig.init_ply_frame = "align"``). It starts from the principal axes
of both clouds in every proper axis order and sign (and turned by 30 and 60 degrees about each axis, for clouds
whose principal axes are nearly equal; at three scales) and refines the best starts by trimmed ICP: each source
point matched to its nearest destination point, the nearest share of the matches kept, the similarity of those
solved again (point to point, then point to plane).

The residual that ranks the starts is the kept matches' mean distance over the source cloud's radius as placed
(its size in the destination's units): a similarity that shrinks the source onto a dense patch of the destination
makes its distances small, but not relative to its own size. A small residual does not say the placement is the
only one: ``Registration.firmness`` says whether the clouds pin it (points on one plane or line do not).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from itertools import permutations, product

import numpy as np


def similarity_align(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity (Umeyama 1991) with ``dst ~ s * R @ src + t``.

    Args:
        src: [N,3] points. dst: [N,3] corresponding points, N >= 3 not collinear.
    Returns:
        (s, R [3,3], t [3]).
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or src.shape[0] < 3:
        raise ValueError("similarity_align needs two [N,3] arrays with N >= 3")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)  # [3,3]
    u, d, vt = np.linalg.svd(cov)
    sign = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:  # reflection: flip the weakest axis
        sign[2, 2] = -1.0
    rot = u @ sign @ vt
    var_s = (xs ** 2).sum() / len(src)
    scale = float(np.trace(np.diag(d) @ sign) / var_s)
    t = mu_d - scale * rot @ mu_s
    return scale, rot, t


KEEP = 0.7
"""The share of a start's matches (the nearest) that its ICP solves the similarity from: the rest are the source's
points where the destination has no surface (an SfM point in the sky, a part of the scene the model left out)."""
MIN_POINTS = 50
"""Fewer points than this in either cloud: nothing to register."""
SLIDE = 0.2
"""The RMS distance, over the placed source's radius, by which ``Registration.firmness`` moves the source."""
MIN_FIRMNESS = 1.1
"""A registration whose ``firmness`` is below this is not pinned by the clouds: a motion of ``SLIDE`` of the points'
radius leaves the residual within 10 % (measured on synthetic clouds: flat and line-like ones 0.96-1.06, a floor
whose few objects hold 3 % of the points 1.02, one whose objects hold 15 % 1.2, the tiny scene 1.8, a room 2.7; on
real models' Gaussians against their scenes' SfM points: bonsai (a plain 3DGS model at 1/4, 3000 steps: a table on
a floor) 1.30, the demo scene 1.9, fern 4.4)."""


@dataclass(frozen=True)
class Registration:
    """``register_clouds``' answer.

    Attributes:
        dst_from_src: [4,4] float64, x_dst = s R x_src + t.
        scale: s.
        residual: the kept matches' mean distance over the placed source's radius (0: every kept point on a
            destination point; two clouds of one surface sampled alike: about 0.01).
        starts: the starts tried.
        firmness: the residual after the least constrained motion of the placed source by ``SLIDE`` of its radius
            (RMS), over ``residual``: near 1 where the source slides along the destination's surfaces without
            leaving them (points on one plane or along one line), so that they do not pin the similarity
            (``MIN_FIRMNESS``).
    """

    dst_from_src: np.ndarray
    scale: float
    residual: float
    starts: int
    firmness: float = math.inf


def _rms_radius(points: np.ndarray) -> float:
    """The points' RMS distance from their mean."""
    return float(np.sqrt(((points - points.mean(0)) ** 2).sum(1).mean()))


def _kept(n: int) -> int:
    """How many of n matches (the nearest) count: ``KEEP`` of them, at least 3."""
    return max(3, int(KEEP * n))


def _finite(points) -> np.ndarray:
    """[N,3] float64 rows of ``points`` without a value that is not finite."""
    points = np.asarray(points, dtype=np.float64)
    return points[np.isfinite(points).all(1)]


def _subset(points: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """At most ``n`` of the points, drawn by ``rng`` and kept in their order."""
    return points if len(points) <= n else points[np.sort(rng.choice(len(points), n, replace=False))]


def _matrix(s: float, r: np.ndarray, t: np.ndarray) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = s * r
    m[:3, 3] = t
    return m


def _core(points: np.ndarray, share: float) -> tuple[np.ndarray, float, np.ndarray]:
    """(centre [3], radius, principal axes [3,3] as columns, largest first, right-handed) of the ``share`` of the
    points nearest their median: far points (lone SfM points, the background a model holds and the points lack) do
    not set them."""
    med = np.median(points, axis=0)
    dist = np.linalg.norm(points - med, axis=1)
    core = points[dist <= np.quantile(dist, share)]
    centre = core.mean(0)
    evals, evecs = np.linalg.eigh(np.cov((core - centre).T))
    axes = evecs[:, np.argsort(evals)[::-1]]
    if np.linalg.det(axes) < 0:
        axes[:, 2] = -axes[:, 2]
    return centre, _rms_radius(core), axes


def _turn(axis: int, degrees: float) -> np.ndarray:
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    i, j = [k for k in range(3) if k != axis]
    r = np.eye(3)
    r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
    return r


def _starting_turns() -> list[np.ndarray]:
    """The 24 proper signed permutations of three axes, each also turned by +-30 and +-60 degrees about each axis."""
    base = []
    for perm in permutations(range(3)):
        for signs in product((1.0, -1.0), repeat=3):
            m = np.zeros((3, 3))
            for row, (col, sign) in enumerate(zip(perm, signs, strict=True)):
                m[row, col] = sign
            if np.linalg.det(m) > 0:
                base.append(m)
    turns = [np.eye(3)] + [_turn(axis, deg) for axis in range(3) for deg in (30.0, -30.0, 60.0, -60.0)]
    return [t @ m for m in base for t in turns]


def _rotation(w: np.ndarray) -> np.ndarray:
    """The rotation exp([w]x) (Rodrigues)."""
    angle = float(np.linalg.norm(w))
    if angle < 1e-12:
        return np.eye(3)
    k = w / angle
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(angle) * kx + (1.0 - math.cos(angle)) * kx @ kx


class _Matcher:
    """Nearest destination points of placed source points, the trimmed residual, and ICP rounds."""

    def __init__(self, dst: np.ndarray):
        from scipy.spatial import cKDTree

        self.dst = dst
        self.tree = cKDTree(dst)
        self._normals: np.ndarray | None = None

    def normals(self) -> np.ndarray:
        """[M,3] the destination's surface normals: the least axis of each point's 12 nearest neighbours."""
        if self._normals is None:
            _, nn = self.tree.query(self.dst, k=min(12, len(self.dst)), workers=-1)
            nb = self.dst[nn] - self.dst[nn].mean(1, keepdims=True)  # [M,k,3]
            self._normals = np.linalg.eigh(np.einsum("mki,mkj->mij", nb, nb))[1][:, :, 0]
        return self._normals

    def icp(self, src: np.ndarray, s: float, r: np.ndarray, t: np.ndarray, iterations: int,
            scale_range: tuple[float, float], tol: float = 0.0, plane: bool = False, reach: float = 1.0
            ) -> tuple[float, np.ndarray, np.ndarray, float]:
        """(s, R, t, residual) after at most ``iterations`` rounds of trimmed ICP from (s, R, t), fewer once a round
        lowers the residual by less than ``tol`` of it; s stays in ``scale_range``. ``plane``: each round minimises
        the kept matches' distances to the destination's tangent planes (linearised about their centre), which
        slide along flat surfaces in a few rounds where point-to-point rounds creep (hundreds on a room's walls).
        ``reach``: matches farther than this share of the placed source's radius count as that far (a start's score
        needs no more, and the tree's search stops there)."""
        keep, radius = _kept(len(src)), _rms_radius(src)
        residual = math.inf
        for it in range(iterations + 1):
            placed = src @ (s * r).T + t
            # a match farther than the placed source's radius counts as that far: the tree stops looking there
            # (a poor start's points lie far off the destination, where an unbounded search visits most of it)
            bound = max(s * radius, 1e-300)
            dist, idx = self.tree.query(placed, distance_upper_bound=reach * bound)
            dist = np.minimum(dist, reach * bound)
            order = np.argpartition(dist, keep - 1)[:keep]
            before, residual = residual, float(dist[order].mean()) / bound
            if it == iterations or (tol > 0 and before - residual < tol * residual):
                break
            order = order[idx[order] < len(self.dst)]  # matched within the bound
            if len(order) < 7:
                break
            if plane:
                s_new, r_new, t_new = self._plane_round(placed[order], idx[order], s, r, t)
            else:
                s_new, r_new, t_new = similarity_align(src[order], self.dst[idx[order]])
            if not (math.isfinite(s_new) and s_new > 0):
                break
            s_clamped = min(max(s_new, scale_range[0]), scale_range[1])
            if s_clamped != s_new:  # keep the rotation, place the kept points' centre with the bounded scale
                t_new = self.dst[idx[order]].mean(0) - s_clamped * r_new @ src[order].mean(0)
            s, r, t = s_clamped, r_new, t_new
        return s, r, t, residual

    def scores(self, src: np.ndarray, placements: list[tuple[float, np.ndarray, np.ndarray]], reach: float
               ) -> list[float]:
        """``icp``'s residual with no round for each placement (s, R, t) of ``src``: every placement's points in one
        query of the tree (thousands of starts: one query each was most of the search's time)."""
        keep, radius = _kept(len(src)), _rms_radius(src)
        sr = np.stack([s * r for s, r, _ in placements])  # [S,3,3]
        t = np.stack([t for _, _, t in placements])  # [S,3]
        bound = np.maximum(np.array([s for s, _, _ in placements]) * radius, 1e-300)  # [S]
        placed = np.einsum("sij,nj->sni", sr, src) + t[:, None, :]  # [S,N,3]
        dist = np.empty(placed.shape[:2])  # [S,N]
        # one query per bound (the starts come at a few scales): a search bounded by the largest scale's reach
        # visits far more of the tree for the smaller ones, most of all above a dense flat cloud (x2.5 on one)
        for b in np.unique(bound):
            at = bound == b
            dist[at] = self.tree.query(placed[at].reshape(-1, 3), distance_upper_bound=reach * float(b),
                                       workers=-1)[0].reshape(-1, placed.shape[1])
        dist = np.minimum(dist, reach * bound[:, None])  # [S,N]
        nearest = np.partition(dist, keep - 1, axis=1)[:, :keep]
        return list(nearest.mean(1) / bound)

    def firmness(self, src: np.ndarray, s: float, r: np.ndarray, t: np.ndarray) -> float:
        """``Registration.firmness`` of the placement (s, R, t): the motions (a turn and a scale about the kept
        matches' centre, a shift) that move the kept points least off the destination's tangent planes (the
        point-to-plane normal equations' weakest directions; the normals' noise leaves none at 0), each tried by
        ``SLIDE`` of the radius both ways, and the smallest residual of them over the placement's."""
        placed = src @ (s * r).T + t
        dist, idx = self.tree.query(placed)
        keep = np.argpartition(dist, _kept(len(src)) - 1)[:_kept(len(src))]
        n = self.normals()[idx[keep]]
        c = placed[keep].mean(0)
        radius = _rms_radius(placed[keep])
        q = (placed[keep] - c) / max(radius, 1e-300)  # (in radii: a turn, a shift and a log-scale of 1 move alike)
        jac = np.concatenate([np.cross(q, n), n, (q * n).sum(1, keepdims=True)], axis=1)  # [K,7]
        _, vecs = np.linalg.eigh(jac.T @ jac)
        slides = []
        for u in vecs.T[:4]:  # a plane leaves 4 motions free (2 shifts, the turn about its normal, the scale)
            size = float(np.sqrt(((np.cross(u[:3], q) + u[3:6] + u[6] * q) ** 2).sum(1).mean()))
            for sign in (1.0, -1.0):
                p = sign * SLIDE / max(size, 1e-12) * u
                turn, grow = _rotation(p[:3]), math.exp(float(p[6]))
                slides.append((s * grow, turn @ r, c + grow * turn @ (t - c) + p[3:6] * radius))
        base, *moved = self.scores(src, [(s, r, t), *slides], reach=1.0)
        if not (base > 0 and radius > 0):
            return math.inf
        return min(moved) / base

    def _plane_round(self, placed: np.ndarray, idx: np.ndarray, s: float, r: np.ndarray, t: np.ndarray
                     ) -> tuple[float, np.ndarray, np.ndarray]:
        """One point-to-plane step: placed' = c + e^sigma exp([w]x) (placed - c) + v, (w, v, sigma) by linear least
        squares of ((placed' - dst) . n)."""
        n = self.normals()[idx]  # [K,3]
        c = placed.mean(0)
        q = placed - c
        res = ((placed - self.dst[idx]) * n).sum(1)  # [K]
        jac = np.concatenate([np.cross(q, n), n, (q * n).sum(1, keepdims=True)], axis=1)  # [K,7]
        lhs = jac.T @ jac
        lhs += 1e-9 * np.trace(lhs) / 7.0 * np.eye(7)
        p = np.linalg.solve(lhs, -jac.T @ res)
        turn, grow = _rotation(p[:3]), math.exp(float(p[6]))
        return s * grow, turn @ r, c + grow * turn @ (t - c) + p[3:6]


def register_clouds(src: np.ndarray, dst: np.ndarray, *, seed: int = 0, start_points: int = 300,
                    coarse_points: int = 2000,
                    fine_points: int = 20000, max_dst: int = 100_000, refine: int = 24) -> Registration:
    """The similarity that places the cloud ``src`` [N,3] on the cloud ``dst`` [M,3] of the same surfaces (no
    matches known; either may hold points the other lacks).

    Every start (``_starting_turns`` between the two clouds' principal axes, the scale of their radii and half and
    twice it; for 90 % of each cloud and for its half nearest its median) is scored
    after one match on ``start_points`` source points; the ``refine`` best run 10 rounds of trimmed ICP on
    ``coarse_points``, and the best three of those up to 100 point-to-plane rounds on ``fine_points`` (until a
    round gains under 1e-4 of the residual); the best of the three is the answer, with its ``firmness`` (whether the
    clouds pin it at all: a flat or line-like cloud fits as well slid along itself). Deterministic for a ``seed``.

    Raises:
        ValueError: fewer than ``MIN_POINTS`` finite points in either cloud.
    """
    src, dst = _finite(src), _finite(dst)
    if len(src) < MIN_POINTS or len(dst) < MIN_POINTS:
        raise ValueError(f"register_clouds needs at least {MIN_POINTS} points in each cloud ({len(src)}, {len(dst)})")
    rng = np.random.default_rng(seed)
    dst = _subset(dst, max_dst, rng)
    few, coarse, fine = (_subset(src, n, rng) for n in (start_points, coarse_points, fine_points))
    # starts from two views of each cloud: 90 % of it (the shape as a whole) and the half nearest its median (where
    # one cloud holds far parts the other lacks, up to about half of it); at the cores' radii ratio, half and twice
    cores = [(_core(src, share), _core(dst, share)) for share in (0.9, 0.5)]
    # the scale stays within 8x of both cores' ratios: a background as large as the surfaces (a sky the points lack)
    # swells the 90 % core, whose ratio alone was measured 9x the true scale (the scale then stuck at its bound,
    # the points a third of their radius off, at a residual that passed for placed)
    ratios = [c_dst[1] / max(c_src[1], 1e-300) for c_src, c_dst in cores]
    scale_range = (min(ratios) / 8.0, max(ratios) * 8.0)
    matcher = _Matcher(dst)
    starts = []
    for (c_src, rad_src, ax_src), (c_dst, rad_dst, ax_dst) in cores:
        ratio = rad_dst / max(rad_src, 1e-300)
        for turn in _starting_turns():
            r = ax_dst @ turn @ ax_src.T
            for grow in (0.5, 1.0, 2.0):
                starts.append((grow * ratio, r, c_dst - grow * ratio * r @ c_src))
    starts = [(s, r, t, res) for (s, r, t), res in zip(starts, matcher.scores(few, starts, reach=0.25), strict=True)]
    starts.sort(key=lambda x: x[3])
    refined = sorted((matcher.icp(coarse, s, r, t, 10, scale_range, plane=True) for s, r, t, _ in starts[:refine]),
                     key=lambda x: x[3])
    # the best three to the end: a start can sit in a basin a few degrees off that 10 rounds did not leave
    finals = [matcher.icp(fine, s, r, t, 100, scale_range, tol=1e-4, plane=True) for s, r, t, _ in refined[:3]]
    s, r, t, residual = min(finals, key=lambda x: x[3])
    return Registration(_matrix(s, r, t), s, residual, len(starts), matcher.firmness(fine, s, r, t))


def placement_residual(src: np.ndarray, dst: np.ndarray, dst_from_src: np.ndarray, *, seed: int = 0,
                       points: int = 20000, max_dst: int = 100_000) -> float:
    """``register_clouds``' residual of a given similarity (no ICP): how well ``dst_from_src`` already places
    ``src`` on ``dst`` (the same subsets of either cloud as ``register_clouds`` with the same arguments takes, so
    that the two residuals compare)."""
    rng = np.random.default_rng(seed)
    dst = _subset(_finite(dst), max_dst, rng)
    src = _subset(_finite(src), points, rng)
    m = np.asarray(dst_from_src, dtype=np.float64)
    s = float(np.cbrt(abs(np.linalg.det(m[:3, :3]))))
    return _Matcher(dst).scores(src, [(s, m[:3, :3] / s, m[:3, 3])], reach=1.0)[0]
