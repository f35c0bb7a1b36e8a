"""Tile binning and exact front-to-back alpha compositing with a closed-form backward.

Layout. The image of each camera is cut into ``tile_size`` x ``tile_size`` tiles. Every (tile, Gaussian)
pair whose opacity-aware footprint (the ellipse where alpha >= 1/255) reaches the tile is listed once
(box candidates, then an exact ellipse/rectangle test), and one stable sort by tile id (the
Gaussians were already in depth order) gives each tile its front-to-back list. Tiles are then grouped
into chunks of similar list length L and processed as padded dense blocks [nt, P, L] (P = tile_size^2
pixels, list position last so that the scans run along contiguous memory): the per-pixel exponent is one
small batched matmul, transmittance is one in-place cumprod along L, and the colour reduction is a batched
matmul. Nothing per pixel is stored for backward: ``_Composite.backward``
recomputes the block and applies the closed-form gradient.

Exponent as a polynomial. With pixel coordinates (u, v) relative to the tile centre, the log-alpha of a
Gaussian, ``ln o - (a du^2 + 2 b du dv + c dv^2) / 2`` with du = u - mu, dv = v - mv, is a quadratic
in (u, v): ``coef . phi(u, v)`` with phi = (1, u, v, u^2, v^2, u v), so alpha for a whole block is one
matmul and one exp. The compositor takes per-Gaussian (mean, conic, log-opacity) [G,6] and features
[G,F], forms the pair coefficients itself, and maps their gradients back in closed form (no autograd
graph over pairs or pixels).

Gradient of the composite. For a pixel, out = sum_i w_i f_i with w_i = alpha_i T_i, T_i = prod_{j<i}
(1 - alpha_j), f_i the feature row (r, g, b, z, 1). With g = dL/dout and h_i = g . f_i:
    dL/df_i     = w_i g
    dL/dalpha_i = T_i h_i - (sum_{k>i} w_k h_k) / (1 - alpha_i)
    dL/dcoef_i  = sum_pixels dL/dalpha_i * alpha_i * phi(u, v)     (0 where alpha was clamped/skipped)
alpha_i dL/dalpha_i = w_i h_i - r_i sum_{k>i} w_k h_k with r = alpha / (1 - alpha); the suffix sum is the
block's total minus one cumsum, so it is exactly 0 behind a stopped ray.

Two implementations. On CPU tensors the native kernels (``uncertsplat/native/csrc/composite.h``: binning
by radix and counting sorts, a per-pixel loop with early stop, a back-to-front backward) compute the
same pairs, images and gradients; the PyTorch blocks below are the reference and the path on other
devices (``backend`` / ``UNCERTSPLAT_RASTERIZER`` choose, see ``use_native``).

Limits. A block holds whole tile lists, so a single tile with an enormous list (L x P elements) is one
block; memory is bounded by ``block_elements`` only while lists are shorter than block_elements / P.
"""

from __future__ import annotations

import bisect
import ctypes
import math
import threading
from dataclasses import dataclass

import torch
from torch import Tensor

from uncertsplat import native

from .project import ALPHA_MAX, ALPHA_MIN, T_MIN

# Elements (pairs x pixels) per dense block: bounds memory (a few blocks of this size are alive in
# backward) and keeps the working set near the CPU caches.
DEFAULT_BLOCK_ELEMENTS = 1 << 17
# On a GPU a block costs a few dozen kernel launches whatever its size, and small blocks leave the
# device idle between them (at 512x384 / 50k with CPU-sized blocks: 8000 launches, the GPU busy 21 of
# 115 ms, H100 2026-11-26); larger blocks trade memory (a few [nt,P,L] float tensors) for launches.
DEFAULT_BLOCK_ELEMENTS_GPU = 1 << 22
PAD_LOG_ALPHA = -1.0e4  # exp() of this is exactly 0: padded rows contribute nothing


def default_block_elements(device: torch.device) -> int:
    """Pair-pixel elements per block of the PyTorch compositor: cache-sized on the CPU, larger on GPUs."""
    return DEFAULT_BLOCK_ELEMENTS if device.type == "cpu" else DEFAULT_BLOCK_ELEMENTS_GPU


# The native kernels' index type of TileBins.pair_gauss (interface >= 17; benchmarks/bench_kernels.py sets it to
# int64 while it times a reference library of an older interface).
PAIR_INDEX_DTYPE = torch.int32


@dataclass
class TileBins:
    """Sorted (tile, Gaussian) pairs.

    Attributes:
        pair_gauss: [M] int32 flat Gaussian index (camera * N + n), sorted by tile then depth (int32: the
            compositor reads it once per pair and the binning writes it, half the bytes of int64).
        pair_tile: [M] global tile index (camera * tiles_per_camera + ty * tiles_x + tx); the native
            binning leaves it to be derived from ``tile_count`` on first use (the native compositor never
            reads it, and writing it cost M int64 stores).
        tile_start: [T] first pair of each tile. tile_count: [T] pairs per tile.
        tiles_x, tiles_y, tile_size: the tile grid of one camera.
    """

    pair_gauss: Tensor
    _pair_tile: Tensor | None
    tile_start: Tensor
    tile_count: Tensor
    tiles_x: int
    tiles_y: int
    tile_size: int

    @property
    def pair_tile(self) -> Tensor:
        if self._pair_tile is None:
            tiles = torch.arange(self.tile_count.numel(), device=self.tile_count.device)
            self._pair_tile = torch.repeat_interleave(tiles, self.tile_count, output_size=self.pair_gauss.numel())
        return self._pair_tile


def bin_gaussians(
    means2d: Tensor,  # [C,N,2]
    extents: Tensor,  # [C,N,2]
    valid: Tensor,  # [C,N]
    depths: Tensor,  # [C,N]
    width: int,
    height: int,
    tile_size: int,
    conics: Tensor | None = None,  # [C,N,3]
    opacities: Tensor | None = None,  # [N]
    backend: str | None = None,
) -> TileBins:
    """List the tiles each visible Gaussian touches, sorted by (tile, depth). No Python loops.

    Candidates come from the opacity-aware box; with ``conics`` and ``opacities`` given, each (tile,
    Gaussian) pair is also tested exactly: the ellipse where alpha >= 1/255 must reach the rectangle of
    the tile's pixel centres (drops the box corners, and most of the box of thin slanted Gaussians). In each
    row of the box the tiles from the first to the last that pass are kept (a convex ellipse reaches a run of
    tiles; the native kernel tests only the row's ends).
    ``backend`` as in ``use_native``: the native kernel lists the same pairs in the same order.
    """
    C, N = valid.shape
    if C * N >= 2**31:
        raise ValueError(f"{C} cameras x {N} Gaussians: the tile lists index at most 2^31 - 1 Gaussians per render")
    dev = means2d.device
    ts = tile_size
    tiles_x, tiles_y = math.ceil(width / ts), math.ceil(height / ts)
    tpc = tiles_x * tiles_y
    if conics is not None and opacities is not None and use_native(means2d, extents, conics, opacities,
                                                                    backend=backend):
        return _bin_native(means2d, extents, valid, depths, conics, opacities, width, height, tile_size)
    with torch.no_grad():
        vidx = valid.reshape(-1).nonzero().squeeze(1)  # [V]
        z = depths.reshape(-1).index_select(0, vidx)
        order = vidx.index_select(0, torch.argsort(z, stable=True))  # visible Gaussians, front to back
        m = means2d.reshape(-1, 2).index_select(0, order).float()
        e = extents.reshape(-1, 2).index_select(0, order).float()
        lim = torch.tensor([width - 1, height - 1], device=dev, dtype=m.dtype)
        # Pixel index range whose centres (i + 0.5) lie in [m - e, m + e], clamped to the image.
        lo = torch.minimum(torch.maximum((m - e - 0.5).ceil(), torch.zeros_like(m)), lim)
        hi = torch.minimum(torch.maximum((m + e - 0.5).floor(), torch.zeros_like(m)), lim)
        t0 = (lo / ts).floor()
        span = ((hi / ts).floor() - t0 + 1).clamp_min(0)  # [V,2] tiles along x, y (small exact floats)
        counts = (span[:, 0] * span[:, 1]).long()
        M = int(counts.sum())
        src = torch.repeat_interleave(torch.arange(order.numel(), device=dev), counts, output_size=M)
        first = torch.cumsum(counts, 0) - counts
        # k-th tile of a Gaussian's box, row-major. The subtraction is in int64 (the pair index passes
        # 2^24 at 1080p with a few 100k Gaussians, where float32 is no longer exact); the tile arithmetic
        # is in float32, exact while tile indices stay below 2^24, and much faster than int64 on CPU.
        fdt = torch.float32 if tpc < 2**24 else torch.float64
        k = (torch.arange(M, device=dev) - first.index_select(0, src)).to(fdt)
        span, t0 = span.to(fdt), t0.to(fdt)
        bw = span[:, 0].index_select(0, src)
        ky = ((k + 0.5) / bw).floor()
        kx = k - ky * bw
        tx = t0[:, 0].index_select(0, src) + kx
        ty = t0[:, 1].index_select(0, src) + ky
        gauss = order.index_select(0, src)
        if conics is not None and opacities is not None:
            keep = _ellipse_meets_tile(
                m.index_select(0, src),
                conics.reshape(-1, 3).index_select(0, gauss).float(),
                opacities.index_select(0, gauss % N if C > 1 else gauss).float(),
                tx,
                ty,
                ts,
            )
            keep = _row_runs(keep, src, span, ky, kx).nonzero().squeeze(1)
            gauss, tx, ty = gauss.index_select(0, keep), tx.index_select(0, keep), ty.index_select(0, keep)
        cam = gauss // N if C > 1 else torch.zeros_like(gauss)
        tile = (cam * tpc + (ty * tiles_x + tx).long()).int()
        # Pairs are in depth order already; a stable sort by tile keeps that order inside each tile
        # (int32 keys sort several times faster than int64 on CPU).
        tile, perm = torch.sort(tile, stable=True)
        tile = tile.long()
        gauss = gauss.index_select(0, perm).int()
        tile_count = torch.bincount(tile, minlength=C * tpc)
        tile_start = torch.cumsum(tile_count, 0) - tile_count
    return TileBins(gauss, tile, tile_start, tile_count, tiles_x, tiles_y, ts)


@torch.no_grad()
def _bin_native(means2d: Tensor, extents: Tensor, valid: Tensor, depths: Tensor, conics: Tensor, opacities: Tensor,
                width: int, height: int, tile_size: int) -> TileBins:
    """``bin_gaussians`` by the native kernel: a radix sort by depth, then a counting sort by tile."""
    lib = native.library()
    C, N = valid.shape
    G = C * N
    tiles_x, tiles_y = math.ceil(width / tile_size), math.ceil(height / tile_size)
    T = C * tiles_x * tiles_y
    dt = means2d.dtype
    m2, ext, con, dep = (t.detach().to(dt).contiguous() for t in (means2d, extents, conics, depths))
    opac = opacities.detach().to(dt).contiguous()
    vis = valid.to(torch.uint8).contiguous()
    workers = max(1, min(native.kernel_threads(), G // 4096 + 1))
    head = (G, N, C, width, height, tile_size, tiles_x, tiles_y, workers, ALPHA_MIN)
    ptrs = (m2.data_ptr(), ext.data_ptr(), con.data_ptr(), opac.data_ptr())
    f64 = dt == torch.float64
    order = torch.empty(G, dtype=torch.long)
    num_visible = torch.zeros(1, dtype=torch.long)
    counts = torch.empty(workers, T, dtype=torch.long)
    state = ctypes.c_void_p()  # what pass 1 found, held by the kernel until us_bin_fill (or us_bin_free)
    M = (lib.us_bin_count_f64 if f64 else lib.us_bin_count_f32)(
        *head, *ptrs, dep.data_ptr(), vis.data_ptr(), order.data_ptr(), num_visible.data_ptr(), counts.data_ptr(),
        ctypes.byref(state))
    try:
        if M < 0:
            raise MemoryError("the native binning ran out of memory")
        tile_count = counts.sum(0)
        tile_start = torch.cumsum(tile_count, 0) - tile_count
        pair_gauss = torch.empty(M, dtype=PAIR_INDEX_DTYPE)
    except BaseException:
        lib.us_bin_free(state)
        raise
    rc = (lib.us_bin_fill_f64 if f64 else lib.us_bin_fill_f32)(
        *head, *ptrs, order.data_ptr(), int(num_visible), counts.data_ptr(), tile_start.data_ptr(),
        pair_gauss.data_ptr(), None, state)  # no pair_tile: TileBins derives it if asked
    if rc != 0:
        raise RuntimeError(f"native binning failed (code {rc})")
    return TileBins(pair_gauss, None, tile_start, tile_count, tiles_x, tiles_y, tile_size)


def _row_runs(hit: Tensor, src: Tensor, span: Tensor, ky: Tensor, kx: Tensor) -> Tensor:
    """[M] bool: the candidates from the first to the last ``hit`` of their row of their Gaussian's box.

    src [M] the candidate's Gaussian (index into the box spans [V,2]), ky, kx [M] its row and column in the box.
    Mathematically the hits of a row are already one run; in floats a tile between two hits whose test lands
    on the limit could fail, and the native kernel (which scans each row from both ends) keeps it.
    """
    heights = span[:, 1].long()
    row = (torch.cumsum(heights, 0) - heights).index_select(0, src) + ky.long()  # [M] (Gaussian, box row)
    R = int(heights.sum())
    none = float(2**30)  # a row without a hit: first > last
    first = kx.new_full((R,), none).scatter_reduce(0, row, torch.where(hit, kx, none), "amin")
    last = kx.new_full((R,), -none).scatter_reduce(0, row, torch.where(hit, kx, -none), "amax")
    return (kx >= first.index_select(0, row)) & (kx <= last.index_select(0, row))


def _ellipse_meets_tile(m: Tensor, conic: Tensor, opac: Tensor, tx: Tensor, ty: Tensor, ts: int) -> Tensor:
    """[M] bool: min over the tile's pixel-centre rectangle of the conic form <= 2 ln(255 o).

    For a convex quadratic whose minimiser (the mean) lies outside a box, the minimum over the box lies
    on a face the mean is outside of; so with dx*, dy* the nearest offsets per axis, it is the smaller
    of the minima along the edge dx = dx* and along dy = dy* (each a clamped 1D quadratic). When the
    mean is inside along an axis, that candidate is just a feasible value >= the true minimum.
    """
    a, b, c = conic.unbind(-1)
    x0 = tx * ts + 0.5 - m[:, 0]
    y0 = ty * ts + 0.5 - m[:, 1]
    x1, y1 = x0 + (ts - 1), y0 + (ts - 1)
    dxs = torch.minimum(torch.maximum(torch.zeros_like(x0), x0), x1)
    dys = torch.minimum(torch.maximum(torch.zeros_like(y0), y0), y1)
    dy1 = torch.minimum(torch.maximum(-b * dxs / c, y0), y1)
    q1 = a * dxs * dxs + 2 * b * dxs * dy1 + c * dy1 * dy1
    dx2 = torch.minimum(torch.maximum(-b * dys / a, x0), x1)
    q2 = a * dx2 * dx2 + 2 * b * dx2 * dys + c * dys * dys
    thr = 2.0 * torch.log((opac / ALPHA_MIN).clamp_min(1.0))
    # Conservative margin against float32 rounding; the compositor applies the exact per-pixel test.
    # Written as "not above" so that a NaN (degenerate conic) keeps the pair.
    return ~(torch.minimum(q1, q2) > thr * (1 + 1e-3) + 1e-3)


def pixel_basis(tile_size: int, dtype, device) -> Tensor:
    """[8,P] phi(u, v) = (1, u, v, u^2, v^2, u v, 0, 0) for a tile's pixel centres, relative to its centre.

    The two zero rows let the per-pair rows (6 coefficients + the local mean offset) multiply phi directly.
    """
    r = torch.arange(tile_size, device=device, dtype=dtype) + 0.5 - tile_size / 2
    v, u = torch.meshgrid(r, r, indexing="ij")  # pixel p = row * tile_size + col
    u, v = u.reshape(-1), v.reshape(-1)
    z = torch.zeros_like(u)
    return torch.stack([torch.ones_like(u), u, v, u * u, v * v, u * v, z, z])


def pair_rows(gparams: Tensor, pair_gauss: Tensor, pair_centre: Tensor) -> Tensor:
    """[M+1,8] per pair: the log-alpha polynomial coefficients (6) and the mean relative to the tile centre (2).

    gparams: [G,6] per Gaussian (mean x, mean y, conic a, b, c, log opacity). The last row is padding
    (log alpha = PAD_LOG_ALPHA). Columns are written in place: no stack/cat copies of [M,8].
    """
    M = pair_gauss.numel()
    gp = gparams.index_select(0, pair_gauss)
    out = gparams.new_zeros(M + 1, 8)
    out[M, 0] = PAD_LOG_ALPHA
    o = out[:M]
    dx = torch.sub(gp[:, 0], pair_centre[:, 0], out=o[:, 6])
    dy = torch.sub(gp[:, 1], pair_centre[:, 1], out=o[:, 7])
    a, b, c = gp[:, 2], gp[:, 3], gp[:, 4]
    k1 = torch.mul(a, dx, out=o[:, 1]).addcmul_(b, dy)
    k2 = torch.mul(b, dx, out=o[:, 2]).addcmul_(c, dy)
    torch.mul(k1, dx, out=o[:, 0]).addcmul_(k2, dy).mul_(-0.5).add_(gp[:, 5])
    torch.mul(a, -0.5, out=o[:, 3])
    torch.mul(c, -0.5, out=o[:, 4])
    torch.neg(b, out=o[:, 5])
    return out


def _rows_backward(pb: Tensor, g: Tensor, out: Tensor) -> None:
    """Chain rule from d(coefficients) g [K,6] to d(mean x, mean y, a, b, c, log o), written into out [K,6].

    pb: [K,8] rows. out may alias g (each output column is written after the inputs it needs are read).
    """
    k1, k2 = pb[:, 1], pb[:, 2]
    a, c, b = pb[:, 3] * -2, pb[:, 4] * -2, -pb[:, 5]
    dx, dy = pb[:, 6], pb[:, 7]
    g0, g1, g2, g3, g4, g5 = (x.clone() for x in g.unbind(-1))
    torch.mul(g1, a, out=out[:, 0]).addcmul_(g2, b).addcmul_(g0, k1, value=-1.0)
    torch.mul(g1, b, out=out[:, 1]).addcmul_(g2, c).addcmul_(g0, k2, value=-1.0)
    g0dx = g0 * dx
    torch.mul(g0dx, dx, out=out[:, 2]).add_(g3).mul_(-0.5).addcmul_(g1, dx)
    torch.mul(g0dx, dy, out=out[:, 3]).neg_().addcmul_(g1, dy).addcmul_(g2, dx).sub_(g5)
    torch.mul(g0, dy, out=out[:, 4]).mul_(dy).add_(g4).mul_(-0.5).addcmul_(g2, dy)
    out[:, 5].copy_(g0)


@dataclass
class _Block:
    tiles: Tensor  # [nt] global tile ids
    rows: Tensor  # [nt*L] pair index (M = padding row)
    gauss: Tensor  # [nt*L] flat Gaussian index (G = padding row)
    L: int
    clamp: bool  # some Gaussian of the block may reach the 0.99 alpha cap


@dataclass
class CompositePlan:
    blocks: list
    pair_gauss: Tensor  # [M]
    pair_centre: Tensor  # [M,2] tile centre of each pair, pixels
    num_gaussians: int  # G = C * N
    num_tiles: int
    phi: Tensor  # [8,P]
    gauss_all: Tensor  # [sum of block sizes] the blocks' Gaussian indices, concatenated
    rows_all: Tensor  # the same for the pair rows
    num_padded: int
    kernels: tuple


def make_plan(
    bins: TileBins, num_gaussians: int, high_opacity: Tensor, phi: Tensor, block_elements: int, kernels
) -> CompositePlan:
    """Group tiles of similar list length into padded blocks of at most ~block_elements pair-pixels.

    high_opacity: [G] bool, Gaussians whose alpha may reach the 0.99 cap.
    """
    dev = bins.tile_count.device
    P = phi.shape[1]
    M = bins.pair_gauss.numel()
    ts = bins.tile_size
    counts, tile_order = torch.sort(bins.tile_count, descending=True)
    cl = counts.tolist()
    neg = [-c for c in cl]  # ascending, for bisect
    n_nonzero = bisect.bisect_left(neg, 0)
    gauss_ext = torch.cat([bins.pair_gauss, bins.pair_gauss.new_full((1,), num_gaussians)])
    on_host = dev.type == "cpu"
    high_ext = torch.cat([high_opacity, high_opacity.new_zeros(1)])
    ar = torch.arange(max(cl[0], 1) if cl else 1, device=dev)
    blocks = []
    i = 0
    while i < n_nonzero:
        L = cl[i]
        nt = max(1, block_elements // (L * P))
        # Keep padding below 2x: stop the block where lists get shorter than half of L.
        j = min(i + nt, bisect.bisect_right(neg, -((L + 1) // 2), lo=i), n_nonzero)
        j = max(j, i + 1)
        tiles = tile_order[i:j]
        rows = bins.tile_start[tiles, None] + ar[:L]
        rows = torch.where(ar[:L] < bins.tile_count[tiles, None], rows, torch.full_like(rows, M)).reshape(-1)
        gauss = gauss_ext.index_select(0, rows)
        # On GPU, avoid a host sync per block: always apply the cap.
        clamp = bool(high_ext.index_select(0, gauss).any()) if on_host else True
        blocks.append(_Block(tiles, rows, gauss, L, clamp))
        i = j
    local = bins.pair_tile % (bins.tiles_x * bins.tiles_y)
    centre = torch.stack([local % bins.tiles_x, local // bins.tiles_x], -1).to(phi.dtype) * ts + ts / 2
    gauss_all = torch.cat([b.gauss for b in blocks]) if blocks else gauss_ext[:0]
    rows_all = torch.cat([b.rows for b in blocks]) if blocks else gauss_ext[:0]
    return CompositePlan(
        blocks,
        bins.pair_gauss,
        centre,
        num_gaussians,
        bins.tile_count.numel(),
        phi,
        gauss_all,
        rows_all,
        gauss_all.numel(),
        kernels,
    )


def _below(value: float, dtype: torch.dtype) -> float:
    """The largest number of ``dtype`` under ``value`` (as ``dtype`` rounds it). ``threshold_(x, t, 0)`` zeroes
    x <= t, so with t = ``_below(v)`` it zeroes x < v and keeps x == v: the comparisons of 3DGS, the native kernels
    and the oracle (alpha < ALPHA_MIN skipped, a ray stopped where T would fall under T_MIN). A threshold of v itself
    also dropped the values equal to it (a ray whose T reached exactly T_MIN lost that Gaussian)."""
    v = torch.tensor(value, dtype=dtype)
    return float(torch.nextafter(v, torch.zeros_like(v)))


def _cuts(dtype: torch.dtype) -> tuple[float, float]:
    """The block kernels' thresholds for ``threshold_`` on alpha and T (``_below`` ALPHA_MIN and T_MIN), taken once
    per call outside the kernels (which torch.compile may wrap)."""
    return _below(ALPHA_MIN, dtype), _below(T_MIN, dtype)


def _alpha(pb: Tensor, phi_t: Tensor, nt: int, L: int, clamp: bool, cut: float) -> Tensor:
    """[nt,P,L] alpha of a block (list position last, so that the scans run along contiguous memory); ``cut``: the
    alpha threshold of ``_cuts``."""
    alpha = torch.bmm(phi_t.expand(nt, -1, -1), pb.view(nt, L, pb.shape[1]).transpose(1, 2))
    alpha.exp_()
    torch.nn.functional.threshold_(alpha, cut, 0.0)  # skip contributions below 1/255
    if clamp:
        alpha.clamp_max_(ALPHA_MAX)
    return alpha


def _weights(alpha: Tensor, need_r: bool, cut: float):
    """Weights w [nt,P,L] (and r = alpha / (1 - alpha) when asked) of a block, from alpha [nt,P,L]; ``cut``: the T
    threshold of ``_cuts``.

    T (transmittance) is one in-place cumprod of 1 - alpha along the list, which is the contiguous
    last dim. 3DGS stops a ray before the first Gaussian that would push T under T_MIN and does not add
    that one. Zeroing T where it is under T_MIN and writing w_i = alpha_i T_i = r_i T_{i+1} gives exactly
    that: w = 0 from the stopping Gaussian on, with no per-ray bookkeeping (T is non-increasing).
    """
    nt, P, L = alpha.shape
    T = alpha.new_empty(nt, P, L)  # T[..., i] = T_{i+1}, after Gaussian i
    torch.sub(1.0, alpha, out=T)
    r = torch.div(alpha, T, out=alpha if not need_r else None)
    T.cumprod_(-1)
    torch.nn.functional.threshold_(T, cut, 0.0)
    w = T.mul_(r) if not need_r else T * r
    return w, r


def block_forward(pb: Tensor, ft: Tensor, phi_t: Tensor, nt: int, L: int, clamp: bool,
                  cuts: tuple[float, float]) -> Tensor:
    """Rows pb [nt*L,8], features ft [nt,L,F] -> [nt,P,F] composited features; ``cuts``: ``_cuts(pb.dtype)``."""
    w, _ = _weights(_alpha(pb, phi_t, nt, L, clamp, cuts[0]), need_r=False, cut=cuts[1])
    return torch.bmm(w, ft)


def block_backward(
    pb: Tensor,
    ft: Tensor,
    go: Tensor,
    phi_t: Tensor,
    nt: int,
    L: int,
    clamp: bool,
    g_rows: Tensor,
    g_feat: Tensor,
    cuts: tuple[float, float],
) -> None:
    """Closed-form gradients of one block, written into g_rows [nt,L,8] and g_feat [nt,L,F]. go: [nt,P,F]; ``cuts``:
    ``_cuts(pb.dtype)``."""
    alpha = _alpha(pb, phi_t, nt, L, clamp, cuts[0])
    capped = alpha >= ALPHA_MAX if clamp else None
    w, r = _weights(alpha, need_r=True, cut=cuts[1])
    torch.bmm(w.transpose(1, 2), go, out=g_feat)  # dL/df_i = sum_pixels w_i g
    wh = torch.bmm(go, ft.transpose(1, 2), out=alpha).mul_(w)  # [nt,P,L]  w_i (g . f_i)
    # Suffix sums sum_{k>i} w_k h_k = total - prefix_i; with the block's own total (not g . out) the
    # suffix is exactly 0 after a ray stops (only zeros were added).
    neg_suffix = torch.cumsum(wh, dim=-1, out=w)
    neg_suffix.sub_(neg_suffix[..., -1:].clone())
    # dL/dlog-alpha = alpha dL/dalpha = w h - alpha / (1 - alpha) * suffix.
    q = wh.addcmul_(r, neg_suffix)
    if capped is not None:
        q.masked_fill_(capped, 0.0)
    torch.bmm(q.transpose(1, 2), phi_t.expand(nt, -1, -1), out=g_rows)


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, gparams: Tensor, feat: Tensor, plan: CompositePlan) -> Tensor:
        fwd, _ = plan.kernels
        F = feat.shape[1]
        P = plan.phi.shape[1]
        phi_t = plan.phi.t().contiguous()
        rows = pair_rows(gparams.detach(), plan.pair_gauss, plan.pair_centre)  # [M+1,8]
        feat_ext = torch.cat([feat.detach(), feat.new_zeros(1, F)])
        out = feat.new_zeros(plan.num_tiles, P, F)
        cuts = _cuts(rows.dtype)
        for b in plan.blocks:
            pb = rows.index_select(0, b.rows)
            ft = feat_ext.index_select(0, b.gauss).view(-1, b.L, F)
            out[b.tiles] = fwd(pb, ft, phi_t, b.tiles.numel(), b.L, b.clamp, cuts)
        ctx.save_for_backward(rows, feat_ext)
        ctx.plan = plan
        return out

    @staticmethod
    def backward(ctx, g_out: Tensor):
        rows, feat_ext = ctx.saved_tensors
        plan: CompositePlan = ctx.plan
        _, bwd = plan.kernels
        F = feat_ext.shape[1]
        phi_t = plan.phi.t().contiguous()
        g_out = g_out.contiguous()
        # Per padded pair: gradients of (mean x, mean y, a, b, c, log o) and of the features; summed
        # per Gaussian with one index_add at the end (one big scatter is much cheaper than many).
        g_rows = feat_ext.new_empty(plan.num_padded, 8)
        g_pairs = feat_ext.new_empty(plan.num_padded, 6 + F)
        off = 0
        cuts = _cuts(rows.dtype)
        for b in plan.blocks:
            nt = b.tiles.numel()
            k = nt * b.L
            pb = rows.index_select(0, b.rows)
            ft = feat_ext.index_select(0, b.gauss).view(nt, b.L, F)
            gr = g_rows[off : off + k].view(nt, b.L, 8)
            gf = ft.new_empty(nt, b.L, F)
            bwd(pb, ft, g_out[b.tiles], phi_t, nt, b.L, b.clamp, gr, gf, cuts)
            g_pairs[off : off + k, 6:] = gf.view(k, F)
            off += k
        # Chain rule from the polynomial coefficients to the Gaussian's 2D parameters, for all pairs at once.
        _rows_backward(rows.index_select(0, plan.rows_all), g_rows[:, :6], g_pairs[:, :6])
        g_all = feat_ext.new_zeros(feat_ext.shape[0], 6 + F)
        g_all.index_add_(0, plan.gauss_all, g_pairs)
        return g_all[:-1, :6], g_all[:-1, 6:], None


_COMPILED: dict = {}


def get_kernels(compile: bool):
    """(block_forward, block_backward), optionally wrapped in torch.compile (built once, cached)."""
    if not compile:
        return block_forward, block_backward
    if "k" not in _COMPILED:
        _COMPILED["k"] = (
            torch.compile(block_forward, dynamic=True),
            torch.compile(block_backward, dynamic=True),
        )
    return _COMPILED["k"]


class _CompositeNative(torch.autograd.Function):
    """The same compositing as ``_Composite``, by the native CPU kernel (``native/csrc/composite.h``)."""

    @staticmethod
    def forward(ctx, gparams: Tensor, feat: Tensor, bins: TileBins) -> Tensor:
        lib = native.library()
        gp, ft = gparams.detach().contiguous(), feat.detach().contiguous()
        T, P, F = bins.tile_count.numel(), bins.tile_size**2, ft.shape[1]
        out = gp.new_empty(T, P, F)
        t_final = gp.new_empty(T, P)
        last = torch.empty(T, P, dtype=torch.int32, device=gp.device)
        fn = lib.us_forward_f64 if gp.dtype == torch.float64 else lib.us_forward_f32
        rc = fn(*_native_head(bins, F), gp.shape[0], gp.data_ptr(), ft.data_ptr(), bins.pair_gauss.data_ptr(),
                bins.tile_start.data_ptr(), bins.tile_count.data_ptr(), out.data_ptr(), t_final.data_ptr(),
                last.data_ptr())
        _check_composite(rc, "")
        ctx.save_for_backward(gp, ft, t_final, last)
        ctx.bins = bins
        return out

    @staticmethod
    def backward(ctx, g_out: Tensor):
        gp, ft, t_final, last = ctx.saved_tensors
        bins: TileBins = ctx.bins
        lib = native.library()
        F = ft.shape[1]
        g_out = g_out.to(gp.dtype).contiguous()
        M = bins.pair_gauss.numel()
        g_pair = _scratch(M * (6 + F), gp.dtype).view(M, 6 + F)  # every row is written by the kernel
        g_all = gp.new_empty(gp.shape[0], 6 + F)  # [G, 6+F]: the kernel sums every pair of each Gaussian
        fn = lib.us_backward_f64 if gp.dtype == torch.float64 else lib.us_backward_f32
        rc = fn(*_native_head(bins, F), gp.shape[0], M, gp.data_ptr(), ft.data_ptr(), bins.pair_gauss.data_ptr(),
                bins.tile_start.data_ptr(), bins.tile_count.data_ptr(), t_final.data_ptr(), last.data_ptr(),
                g_out.data_ptr(), g_pair.data_ptr(), g_all.data_ptr())
        _check_composite(rc, " backward")
        return g_all[:, :6], g_all[:, 6:], None


class _CompositeImageNative(torch.autograd.Function):
    """``render``'s compositing by the native kernel in image layout (``composite_image``): the features are
    (colour, camera depth, 1), the outputs images, the background blended in by the kernel. Gradients to the
    means, conics, log opacities, colours and depths; none to the background (a constant in every caller)."""

    @staticmethod
    def forward(ctx, means2d, conics, log_o, colors, depths, background, bins: TileBins, height: int, width: int):
        lib = native.library()
        ctx.set_materialize_grads(False)
        C, N = means2d.shape[:2]
        ins = [t.detach().contiguous() for t in (means2d, conics, log_o, colors, depths)]
        bg = background.detach().to(ins[0].dtype).contiguous() if background is not None else None
        rgb = ins[0].new_empty(C, height, width, 3)
        depth_expected = ins[0].new_empty(C, height, width, 1)
        alpha = ins[0].new_empty(C, height, width, 1)
        T, P = bins.tile_count.numel(), bins.tile_size**2
        t_final = ins[0].new_empty(T, P)
        last = torch.empty(T, P, dtype=torch.int32)
        fn = lib.us_forward_image_f64 if ins[0].dtype == torch.float64 else lib.us_forward_image_f32
        rc = fn(*_native_head(bins, 5), C * N, height, width, *(t.data_ptr() for t in ins),
                bg.data_ptr() if bg is not None else None, bins.pair_gauss.data_ptr(), bins.tile_start.data_ptr(),
                bins.tile_count.data_ptr(), rgb.data_ptr(), depth_expected.data_ptr(), alpha.data_ptr(),
                t_final.data_ptr(), last.data_ptr())
        _check_composite(rc, "")
        ctx.save_for_backward(*ins, t_final, last, *([bg] if bg is not None else []))
        ctx.bins, ctx.size = bins, (C, N, height, width)
        return rgb, depth_expected, alpha

    @staticmethod
    def backward(ctx, g_rgb, g_depth, g_alpha):
        means2d, conics, log_o, colors, depths, t_final, last, *bg = ctx.saved_tensors
        bins: TileBins = ctx.bins
        C, N, height, width = ctx.size
        if g_rgb is None and g_depth is None and g_alpha is None:
            return (None,) * 9
        grads = [g.to(means2d.dtype).contiguous() if g is not None else None for g in (g_rgb, g_depth, g_alpha)]
        M, G = bins.pair_gauss.numel(), C * N
        g_pair = _scratch(M * 11, means2d.dtype).view(M, 11)  # every row is written by the kernel
        # [11 G]: the kernel sums every pair of each Gaussian into one block per input (means [G,2], conics [G,3],
        # log opacities [G], colours [G,3], depths [G], the constant feature [G]), so each gradient is contiguous
        g_all = means2d.new_empty(11 * G)
        lib = native.library()
        fn = lib.us_backward_image_f64 if means2d.dtype == torch.float64 else lib.us_backward_image_f32
        rc = fn(*_native_head(bins, 5), G, M, height, width,
                *(t.data_ptr() for t in (means2d, conics, log_o, colors, depths)),
                bg[0].data_ptr() if bg else None, bins.pair_gauss.data_ptr(), bins.tile_start.data_ptr(),
                bins.tile_count.data_ptr(), t_final.data_ptr(), last.data_ptr(),
                *(g.data_ptr() if g is not None else None for g in grads), g_pair.data_ptr(), g_all.data_ptr())
        _check_composite(rc, " backward")
        return (g_all[:2 * G].view(C, N, 2), g_all[2 * G:5 * G].view(C, N, 3), g_all[5 * G:6 * G].view(C, N),
                g_all[6 * G:9 * G].view(C, N, 3), g_all[9 * G:10 * G].view(C, N), None, None, None, None)


def composite_image(means2d: Tensor, conics: Tensor, log_o: Tensor, colors: Tensor, depths: Tensor,
                    bins: TileBins, height: int, width: int,
                    background: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """What ``render`` composites, by the native CPU kernel straight into images: the features (colour,
    camera depth, 1) of the Gaussians ``means2d`` [C,N,2], ``conics`` [C,N,3], ``log_o`` [C,N], ``colors``
    [C,N,3], ``depths`` [C,N] over ``bins``; returns rgb [C,H,W,3] (``background`` [3] behind the Gaussians:
    + (1 - alpha) background), depth_expected [C,H,W,1] and alpha [C,H,W,1].

    The same function and gradient as ``composite`` of the packed [C*N,6] / [C*N,5] inputs followed by
    ``tiles_to_image``, the channel slices and the background's blend, without those tensor ops and their
    backward (a few ms of every training step). The background gets no gradient. Use
    ``composite_image_available`` first: CPU tensors, float32 or float64, the native kernels loaded."""
    return _CompositeImageNative.apply(means2d, conics, log_o, colors, depths, background, bins, height, width)


def composite_image_available(*tensors: Tensor, background: Tensor | None = None, backend: str | None = None,
                              compile: bool = False) -> bool:
    """Whether ``composite_image`` takes these inputs: ``use_native`` holds and the background (if any) is a
    constant of 3 values (another shape broadcasts in the general path)."""
    if background is not None and (background.requires_grad or background.numel() != 3):
        return False
    return use_native(*tensors, backend=backend, compile=compile, num_features=5)


def _check_composite(rc: int, what: str) -> None:
    """Raise for a native compositor return code (0: done; 2: out of memory; else an unsupported input)."""
    if rc == 2:
        raise MemoryError(f"the native compositor{what} ran out of memory (its per-Gaussian records); render fewer "
                          "cameras at once or use fewer Gaussians")
    if rc != 0:
        raise RuntimeError(f"native compositor{what} failed (code {rc})")


_SCRATCH = threading.local()


def _scratch(n: int, dtype: torch.dtype) -> Tensor:
    """A reused per-thread CPU buffer of at least ``n`` elements (the per-pair gradients of the native
    backward: tens of MB per call, whose fresh allocation and page faults cost as much as filling them)."""
    buf = getattr(_SCRATCH, "buf", None)
    if buf is None or buf.dtype != dtype or not n <= buf.numel() <= 2 * n + (1 << 20):
        buf = torch.empty(n, dtype=dtype)
        _SCRATCH.buf = buf
    return buf[:n]


def _native_head(bins: TileBins, F: int) -> tuple:
    """The scalar arguments shared by the native forward and backward."""
    return (bins.tile_count.numel(), bins.tiles_x, bins.tiles_x * bins.tiles_y, bins.tile_size,
            native.kernel_threads(), ALPHA_MIN, ALPHA_MAX, T_MIN, F)


def use_native(*tensors: Tensor, backend: str | None = None, compile: bool = False,
               num_features: int = 1) -> bool:
    """Whether the native CPU kernels (binning and compositing) take these inputs (``native.use_for``)."""
    if compile:
        return False
    return native.use_for(*tensors, backend=backend, supported=1 <= num_features <= NATIVE_MAX_FEATURES,
                          unsupported=f" and at most {NATIVE_MAX_FEATURES} features")


NATIVE_MAX_FEATURES = 8


def composite(
    gparams: Tensor,  # [G,6] mean x, mean y (pixels), conic a, b, c, log opacity
    feat: Tensor,  # [G,F]
    bins: TileBins,
    high_opacity: Tensor | None = None,  # [G] bool; None = any Gaussian may hit the cap
    block_elements: int | None = None,
    compile: bool = False,
    backend: str | None = None,
) -> Tensor:
    """Composite features front to back; returns [T,P,F] per tile (T = C * tiles_per_camera).

    ``backend`` picks the native CPU kernel or the PyTorch blocks (see ``use_native``); both compute
    the same function and gradient.
    """
    if use_native(gparams, feat, backend=backend, compile=compile, num_features=feat.shape[1]):
        return _CompositeNative.apply(gparams, feat, bins)
    phi = pixel_basis(bins.tile_size, gparams.dtype, gparams.device)
    if block_elements is None:
        block_elements = default_block_elements(gparams.device)
    if high_opacity is None:
        high_opacity = torch.ones(feat.shape[0], dtype=torch.bool, device=feat.device)
    plan = make_plan(bins, feat.shape[0], high_opacity, phi, block_elements, get_kernels(compile))
    return _Composite.apply(gparams, feat, plan)


def tiles_to_image(tiles: Tensor, C: int, bins: TileBins, height: int, width: int) -> Tensor:
    """[T,P,F] -> [C,H,W,F]."""
    ts = bins.tile_size
    F = tiles.shape[-1]
    img = tiles.view(C, bins.tiles_y, bins.tiles_x, ts, ts, F).permute(0, 1, 3, 2, 4, 5)
    return img.reshape(C, bins.tiles_y * ts, bins.tiles_x * ts, F)[:, :height, :width]
