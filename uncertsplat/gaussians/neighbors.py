"""Distances to the k nearest neighbours of every point of a cloud (the initial Gaussian scales).

Small clouds (up to ``GRID_MIN_POINTS``) are taken by brute force, in row blocks; larger ones through a uniform
grid whose cell size adapts per point: a point is answered from the 27 cells around its own once its k-th
neighbour lies within one cell size (then no nearer point can lie outside them), else it is asked again on a
grid twice as coarse; a point whose 27 cells hold too many candidates (a dense clump on a grid set by the rest
of the cloud) is asked again on a finer grid. Each grid level costs a sort of the cloud, so the time grows about as
P log P (``benchmarks/bench_init.py``: 96k points 8x faster than the brute force, 1M points in 60-90 s on
2 cores where the brute force would take about an hour); the result is exact, from differences of float64
coordinates (the brute force's ``cdist`` expands the square and loses the distances inside a clump far smaller
than the cloud).
"""

from __future__ import annotations

import torch
from torch import Tensor

NN_BLOCK_ELEMENTS = 2**26
"""The distance block the brute force holds at once (256 MB of float32): its rows shrink for a cloud of more
than 16,384 points (a 48k-point one took 1.8 GB in rows of 4096)."""

GRID_MIN_POINTS = 16_384
"""Clouds of more points go through the grid; smaller ones keep the brute force (the same values to the bit as
before the grid; every shipped scene's cloud is smaller)."""

GRID_PAIR_BUDGET = 2**20
"""Candidate pairs (query, point) one grid block holds at once (about 100 MB with their coordinates and indices;
a 1M-point cloud's whole peak is about 0.65 GB above the cloud's, most of it the sample's brute-force block)."""

GRID_MAX_CANDIDATES = 2048
"""A point with more candidates than this in its 27 cells is asked again on a finer grid, as long as each finer
grid halves its count (exact duplicates never separate) and no finer grid has failed it; else it is answered where
it stands, whatever the count."""

_FINER_LEVELS = 3  # a point with too many candidates goes 3 levels (8x) finer
_QUERY_ROWS = 1 << 14  # queries whose 27 neighbour cells are looked up at once (about 4 MB per table)
_SAMPLE = 256  # points whose exact distances choose the first cell size

# the 27 cells around (and including) a point's own
_OFFSETS = torch.tensor([(i, j, m) for i in (-1, 0, 1) for j in (-1, 0, 1) for m in (-1, 0, 1)])


def nearest_neighbor_distance(points: Tensor, k: int = 3, chunk: int = 4096) -> Tensor:
    """[P] mean distance of each point to its ``k`` nearest other points (root of the mean squared distance).

    Up to ``GRID_MIN_POINTS`` points: brute force in row blocks of at most ``chunk`` rows (fewer for a cloud
    past 16,384 points: ``NN_BLOCK_ELEMENTS``). Above: the adaptive grid (module docstring). A single point (no
    neighbours) gets distance 0 (the caller clamps); so does a point with ``k`` exact duplicates.
    """
    n = points.shape[0]
    if n <= 1:
        return torch.zeros(n, dtype=points.dtype, device=points.device)
    k = min(k, n - 1)
    if n <= GRID_MIN_POINTS:
        every = torch.arange(n, device=points.device)
        return _brute_mean_sq(points, every, k, chunk).clamp_min(0).sqrt()
    return _grid_mean_sq(points, k).clamp_min(0).sqrt()


def _brute_mean_sq(points: Tensor, queries: Tensor, k: int, chunk: int = 4096) -> Tensor:
    """[Q] mean squared distance of ``points[queries]`` to their k nearest other points, by brute force."""
    n = points.shape[0]
    # NN_BLOCK_ELEMENTS counts float32 elements: float64 takes half the rows
    rows = min(chunk, max(1, NN_BLOCK_ELEMENTS * 4 // (n * points.element_size())))
    out = torch.empty(queries.shape[0], dtype=points.dtype, device=points.device)
    for start in range(0, queries.shape[0], rows):
        d2 = torch.cdist(points[queries[start:start + rows]], points).square_()  # [rows,P]
        # the point itself sits at distance 0; take k + 1 smallest and drop the first
        out[start:start + rows] = torch.topk(d2, k + 1, dim=1, largest=False).values[:, 1:].clamp_min(0).mean(1)
    return out


def _cell_keys(cells: Tensor) -> Tensor:
    """[...] int64 hash of [...,3] cell coordinates. Any coordinates fit (a far point's cell index can pass
    2^40); int64 products wrap, and a collision only merges two cells: more candidates, never fewer."""
    return (cells[..., 0] * 73_856_093) ^ (cells[..., 1] * 19_349_663) ^ (cells[..., 2] * 83_492_791)


def _grid_mean_sq(points: Tensor, k: int) -> Tensor:
    """[P] as ``_brute_mean_sq`` for every point, through grids of cell size ``h0 * 2**level``."""
    n, dev = points.shape[0], points.device
    # float64 and near 0: the differences inside a clump far smaller than the cloud keep their precision
    pts = points.double()
    pts = pts - pts.mean(0)
    span = float((pts.max(0).values - pts.min(0).values).max())
    if not span > 0:  # every point at one place
        return torch.zeros(n, dtype=points.dtype, device=dev)
    # the first cell size: a low quantile of a sample's exact distances, so most points start on a grid fine
    # enough for few candidates and climb (each climb is one sort of the cloud)
    gen = torch.Generator().manual_seed(0)
    sample = torch.randperm(n, generator=gen)[:_SAMPLE].to(dev)
    kth = _brute_mean_sq(pts, sample, k).clamp_min(0).sqrt()  # a lower bound of each sample's k-th distance
    h0 = max(float(kth.quantile(0.5)), span * 1e-7)
    min_level = -30  # 1e-9 of h0: below it a clump is answered whatever its count

    out = torch.full((n,), float("nan"), dtype=pts.dtype, device=dev)
    level = torch.zeros(n, dtype=torch.long, device=dev)
    failed_at = torch.full((n,), min_level - 1, dtype=torch.long, device=dev)  # the highest level that failed
    # go finer while a point has more than GRID_MAX_CANDIDATES candidates and fewer than this (a finer grid
    # must halve them, else the clump is exact duplicates or a line of them: answer it where it stands)
    refine_below = torch.full((n,), torch.iinfo(torch.long).max, dtype=torch.long, device=dev)
    pending = torch.ones(n, dtype=torch.bool, device=dev)
    while bool(pending.any()):
        todo = pending.nonzero().squeeze(1)
        if todo.numel() * n <= NN_BLOCK_ELEMENTS:  # few left (the far points): brute force is cheaper
            out[todo] = _brute_mean_sq(pts, todo, k)
            break
        lv = int(level[todo].min())
        here = todo[level[todo] == lv]
        # a point that failed on the next finer grid, or is at the finest, is answered here
        limit = torch.where((failed_at[here] == lv - 1) | (lv <= min_level), 0, refine_below[here])
        grid = _Grid(pts, h0 * 2.0**lv)
        parts = [grid.answer(pts, here[i:i + _QUERY_ROWS], k, limit[i:i + _QUERY_ROWS])
                 for i in range(0, here.numel(), _QUERY_ROWS)]
        mean_sq, status, count = (torch.cat(column) for column in zip(*parts, strict=True))
        done = status == 0
        out[here[done]] = mean_sq[done]
        pending[here[done]] = False
        up = here[status == 1]
        failed_at[up] = lv
        level[up] = lv + 1
        down = status == 2
        refine_below[here[down]] = count[down] // 2
        down = here[down]
        level[down] = torch.maximum(failed_at[down] + 1, torch.full_like(down, lv - _FINER_LEVELS))
    return out.to(points.dtype)


class _Grid:
    """The cloud sorted by cell of size ``h``: cell keys (sorted, unique), each cell's count and first row in
    ``order``."""

    def __init__(self, pts: Tensor, h: float):
        self.h = h
        self.cells = torch.floor((pts - pts.min(0).values) / h).long()  # [P,3]
        sorted_keys, self.order = torch.sort(_cell_keys(self.cells))
        self.keys, self.counts = torch.unique_consecutive(sorted_keys, return_counts=True)
        self.starts = torch.cumsum(self.counts, 0) - self.counts

    def answer(self, pts: Tensor, queries: Tensor, k: int, refine_below: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Answer ``queries`` from the 27 cells around each.

        Returns [Q] mean squared distance where answered, [Q] status and [Q] candidate count. Status 0: answered;
        1: the k-th neighbour may lie beyond the 27 cells (ask on a coarser grid); 2: more candidates than
        ``GRID_MAX_CANDIDATES`` and fewer than ``refine_below`` (ask on a finer grid).
        """
        dev = pts.device
        keys, h, order = self.keys, self.h, self.order
        # the 27 neighbour cells' keys per query, sorted so two cells that hash alike are taken once
        near = _cell_keys(self.cells[queries][:, None, :] + _OFFSETS.to(dev)).sort(dim=1).values  # [Q,27]
        at = torch.searchsorted(keys, near).clamp_max(keys.numel() - 1)
        take = keys[at] == near
        take[:, 1:] &= near[:, 1:] != near[:, :-1]
        cell_count = torch.where(take, self.counts[at], 0)  # [Q,27]
        cell_start = self.starts[at]  # [Q,27]
        per_query = cell_count.sum(1)  # [Q]

        q = queries.numel()
        mean_sq = torch.full((q,), float("nan"), dtype=pts.dtype, device=dev)
        status = torch.where((per_query > GRID_MAX_CANDIDATES) & (per_query < refine_below), 2, 1)
        answer = (status == 1).nonzero().squeeze(1)
        # queries in order of candidate count, so each block pads its rows to a similar length
        answer = answer[torch.argsort(per_query[answer])]
        limit = (h * (1 - 1e-4)) ** 2  # a margin for the cells' rounding at their borders
        start = 0
        while start < answer.numel():
            width = max(int(per_query[answer[start]]), 1)
            stop = min(answer.numel(), start + max(1, GRID_PAIR_BUDGET // width))
            while stop - start > 1 and (stop - start) * int(per_query[answer[stop - 1]]) > GRID_PAIR_BUDGET:
                stop = start + (stop - start) // 2
            rows = answer[start:stop]
            width = int(per_query[rows].max())
            if width >= k + 1:
                counts_flat = cell_count[rows].reshape(-1)  # [R*27]
                total = int(counts_flat.sum())
                cell_of = torch.repeat_interleave(torch.arange(counts_flat.numel(), device=dev), counts_flat,
                                                  output_size=total)  # [T]
                first_in_cell = torch.cumsum(counts_flat, 0) - counts_flat
                rank = torch.arange(total, device=dev)
                candidate = order[cell_start[rows].reshape(-1)[cell_of] + rank - first_in_cell[cell_of]]  # [T]
                row = cell_of // _OFFSETS.shape[0]  # [T]
                first_of_row = torch.cumsum(per_query[rows], 0) - per_query[rows]
                d2 = (pts[queries[rows]][row] - pts[candidate]).square().sum(1)  # [T]
                padded = torch.full((rows.numel(), width), float("inf"), dtype=pts.dtype, device=dev)
                padded[row, rank - first_of_row[row]] = d2
                nearest = torch.topk(padded, k + 1, dim=1, largest=False).values[:, 1:]  # [R,k]
                ok = nearest[:, -1] <= limit
                mean_sq[rows[ok]] = nearest[ok].mean(1)
                status[rows[ok]] = 0
            start = stop
        return mean_sq, status, per_query
