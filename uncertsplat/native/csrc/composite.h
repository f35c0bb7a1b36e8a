// Native CPU rasterizer kernels of uncertsplat: tile binning and the per-pixel front-to-back loop of 3DGS,
// forward and backward. This header holds the kernels; composite_forward.cpp (binning, forward) and
// composite_backward.cpp (backward) instantiate them behind the C interface, as two files so that the build
// compiles them side by side (the templates of either take most of the library's build time).
//
// Plain C++17 with a C ABI (called through ctypes with tensor data pointers): no torch headers, so it
// builds in seconds with the system compiler. uncertsplat/native/__init__.py builds and loads it;
// uncertsplat/render/rasterize.py holds the semantics (the PyTorch compositor is the reference).
//
// Layout. Pairs (tile, Gaussian) are sorted by tile, then front to back; tile t owns the pairs
// [tile_start[t], tile_start[t] + tile_count[t]). A tile is ts x ts pixels, pixel p = row * ts + col,
// with centre (tx * ts + col + 0.5, ty * ts + row + 0.5). Per Gaussian: gparams [G,6] = (mean x, mean y,
// conic a, b, c, log opacity), feat [G,F]. Outputs are per tile: out [T,P,F], and for backward the
// transmittance after the last added Gaussian t_final [T,P] and the count of list entries up to and
// including it, last [T,P].
//
// Semantics (identical to the PyTorch compositor): alpha = min(exp(power), alpha_max) with
// power = log o - (a dx^2 + 2 b dx dy + c dy^2) / 2; entries with alpha < alpha_min (or NaN) are
// skipped; a ray stops before the first Gaussian that would take its transmittance under t_min, which
// is not added; w_i = alpha_i T_i. The gradient of a capped alpha (raw >= alpha_max) w.r.t. the
// Gaussian's parameters is 0.
//
// Backward walks each pixel's list back to front from its last added entry, recovering
// T_i = T_{i+1} / (1 - alpha_i) (as 3DGS does) and accumulating the suffix sum_{k>i} w_k h_k, so
// Gaussians behind a stopped ray get exactly zero gradient. Gradients are written per pair (one thread
// owns a tile), then summed per Gaussian in pair order (deterministic for any number of threads).
//
// Vectorisation: a tile is cut into slices of LANES consecutive pixels (one SIMD register of floats:
// two rows of an 8 x 8 tile with AVX-512, one with AVX2). Forward runs slice by slice over the entries
// whose rows reach the slice (per-slice lists, built without branches), with the slice's state in
// registers and the alphas of a few entries computed ahead (their exp polynomials overlap); backward
// runs entry by entry over the slices its rows reach. Selects are branch-free; exp is vmath.h's
// polynomial (float).

#pragma once

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <new>
#include <type_traits>
#include <utility>
#include <vector>
#if defined(__SSE__)
#include <immintrin.h>
#endif

#include "parallel.h"
#include "vmath.h"

namespace {

struct Params {
    int64_t num_tiles, tiles_x, tiles_per_cam, tile_size, num_threads;
    double alpha_min, alpha_max, t_min;
};

int64_t num_workers(int64_t num_tiles, int64_t num_threads, int64_t chunk) {
    return std::max<int64_t>(1, std::min<int64_t>(num_threads, (num_tiles + chunk - 1) / chunk));
}

// Runs fn(worker, tile) for every tile on `workers` threads, handing out small chunks dynamically (tile
// workloads differ by orders of magnitude between empty and crowded tiles).
template <typename Fn>
void for_each_tile(int64_t num_tiles, int64_t workers, int64_t chunk, Fn fn) {
    std::atomic<int64_t> next{0};
    uskern::run_workers(workers, [&](int64_t id) {
        for (;;) {
            const int64_t begin = next.fetch_add(chunk);
            if (begin >= num_tiles) break;
            const int64_t end = std::min(begin + chunk, num_tiles);
            for (int64_t t = begin; t < end; ++t) fn(id, t);
        }
    });
}

constexpr int64_t CHUNK = 4;

// The lanes of one SIMD register of floats (uskern::LANES): a slice of that many consecutive pixels of a
// tile (row-major; e.g. two rows of an 8 x 8 tile with AVX-512).
using uskern::LANES;

template <typename S>
struct Lanes {
    typedef S V __attribute__((vector_size(LANES * sizeof(S))));
    using I = std::conditional_t<sizeof(S) == 4, int32_t, int64_t>;
    typedef I M __attribute__((vector_size(LANES * sizeof(S))));  // comparison results: all ones or 0
};

template <typename V>
inline V vexp_lanes(V x);

template <>
inline Lanes<float>::V vexp_lanes<Lanes<float>::V>(Lanes<float>::V x) {
    return uskern::vexp_t<Lanes<float>::V, Lanes<float>::M>(x);
}

template <>
inline Lanes<double>::V vexp_lanes<Lanes<double>::V>(Lanes<double>::V x) {
    for (int l = 0; l < LANES; ++l) x[l] = std::exp(x[l]);
    return x;
}

template <typename M>
inline bool any_lane(M m) {
    uint64_t words[sizeof(M) / 8];
    std::memcpy(words, &m, sizeof(M));
    uint64_t any = 0;
    for (uint64_t w : words) any |= w;
    return any != 0;
}

// Lane sums of several vectors at once. combine(a, b) halves the partial sums per quantity: a and b each
// hold Q quantities in blocks of K lanes; the result holds a's Q quantities then b's, in blocks of K / 2
// (the low half of each block plus its high half). log2(LANES) rounds of this turn LANES vectors into one
// whose lane i is the sum of vector i: about 3 operations per vector instead of 2 log2(LANES) for one
// tree per vector.
#if defined(__clang__) || (defined(__GNUC__) && __GNUC__ >= 12)
#define US_HAVE_SHUFFLEVECTOR 1
#endif

#ifdef US_HAVE_SHUFFLEVECTOR
constexpr int half_lane(int o, int K, bool hi) {
    const int half = LANES / 2, sub = K / 2;
    const int src = o < half ? 0 : LANES, r = o % half;
    return src + (r / sub) * K + (hi ? sub : 0) + r % sub;
}

template <int K, typename V, int... O>
inline V combine_impl(V a, V b, std::integer_sequence<int, O...>) {
    return __builtin_shufflevector(a, b, half_lane(O, K, false)...) +
           __builtin_shufflevector(a, b, half_lane(O, K, true)...);
}

// v[0 .. n) (n <= G) reduced in place to v[0] whose lane i is the lane sum of input i; the inputs hold
// blocks of K lanes per quantity (K = LANES for plain vectors).
template <int K, int G, typename V>
inline void combine_rounds(V* v) {
    if constexpr (K > 1) {
        for (int i = 0; i < G / 2; ++i)
            v[i] = combine_impl<K>(v[2 * i], v[2 * i + 1], std::make_integer_sequence<int, LANES>{});
        combine_rounds<K / 2, G / 2>(v);
    }
}
#endif

// out[i] = the sum of the lanes of v[i], for i < n (v is overwritten).
template <typename S, typename V>
inline void lane_sums(V* v, int n, S* out) {
#ifdef US_HAVE_SHUFFLEVECTOR
    for (int g0 = 0; g0 < n; g0 += LANES) {
        V grp[LANES];
        for (int i = 0; i < LANES; ++i) grp[i] = g0 + i < n ? v[g0 + i] : V{};
        combine_rounds<LANES, LANES>(grp);
        for (int i = 0; i < LANES && g0 + i < n; ++i) out[g0 + i] = grp[0][i];
    }
#else
    for (int i = 0; i < n; ++i) {
        S s = 0;
        for (int l = 0; l < LANES; ++l) s += v[i][l];
        out[i] = s;
    }
#endif
}

// Calls fn(std::integral_constant<int, f>) for f = 0 .. F - 1. Per-feature lane arrays indexed only by
// these constants stay in registers (a runtime loop index makes GCC keep the array in memory).
template <typename Fn, int... I>
inline void each_feature_impl(Fn&& fn, std::integer_sequence<int, I...>) {
    (fn(std::integral_constant<int, I>{}), ...);
}

template <int F, typename Fn>
inline void each_feature(Fn&& fn) {
    each_feature_impl(fn, std::make_integer_sequence<int, F>{});
}

// Per-Gaussian records, built once per call (forward_any / backward_any return 2 when they do not fit in
// memory): (mean x, mean y, conic a, b, c, log opacity, rlo, rhi) and
// the F features. [rlo, rhi] are the first and last pixel rows whose centres lie in the bounding box
// (with a margin) of the ellipse where alpha can reach alpha_min; empty (rlo > rhi) when it never does,
// or for NaN parameters (whose NaN alpha would be skipped anyway); every row for a degenerate conic.
// A slice outside those rows skips the Gaussian, which changes no result (alpha < alpha_min is skipped).
constexpr int PK = 8;

// Floats (doubles) from one record to the next: PK + F rounded up to whole 64-byte cache lines, so that reading a
// record (in list order, i.e. at random in Gaussian order) touches one line, not two (13 floats took 52 bytes).
template <typename S>
constexpr int64_t record_stride(int64_t F) {
    return ((PK + F) * static_cast<int64_t>(sizeof(S)) + 63) / 64 * (64 / static_cast<int64_t>(sizeof(S)));
}

// The records of G Gaussians, the first at a 64-byte boundary.
template <typename S>
struct Records {
    std::vector<S> store;
    S* data;
    Records(int64_t G, int64_t F) : store(static_cast<size_t>(G * record_stride<S>(F) + 64 / sizeof(S))) {
        const auto addr = reinterpret_cast<std::uintptr_t>(store.data());
        data = store.data() + ((64 - addr % 64) % 64) / sizeof(S);
    }
};

// The standard render's compositing in image layout (us_forward_image / us_backward_image): the Gaussians'
// columns come as separate arrays and the features are fixed, (colour r, g, b, camera depth, 1), so F = 5;
// the outputs are images [C,H,W,.] (a tile's pixels beyond the image's right or bottom edge are neither written
// nor read): rgb with the background behind the Gaussians (+ T_final bg), the expected depth and alpha. This
// saves render() the packing of [G,6] / [G,5] inputs, the tile-to-image copy, the channel slices and the
// background's tensor ops, and their backward. In backward the background is the last entry of every ray
// (weight T_final, d loss / d its value g_rgb . bg), so it enters the suffix sum from the start.
constexpr int IMAGE_F = 5;

template <typename S>
struct ImageIO {
    const S *means2d, *conics, *log_o, *colors, *depths;  // [G,2], [G,3], [G], [G,3], [G]
    int64_t height, width;
    S bg[3];                  // 0 without a background
    S *rgb, *depth, *alpha;   // forward: [C,H,W,3], [C,H,W], [C,H,W]
    const S *g_rgb, *g_depth, *g_alpha;  // backward: d loss / d those (null: 0)

    // Image offset (camera, row, column) of pixel p of a tile, or -1 beyond the image.
    int64_t pixel(const Params& prm, int64_t ts, int64_t tile, int64_t p) const {
        const int64_t cam = tile / prm.tiles_per_cam, local = tile % prm.tiles_per_cam;
        const int64_t row = local / prm.tiles_x * ts + p / ts, col = local % prm.tiles_x * ts + p % ts;
        return (row < height && col < width) ? (cam * height + row) * width + col : -1;
    }
};

// An ImageIO of the Gaussians' columns and the background ([3], or null: black); outputs and gradients null.
template <typename S>
ImageIO<S> image_inputs(const S* means2d, const S* conics, const S* log_o, const S* colors, const S* depths,
                        int64_t height, int64_t width, const S* background) {
    ImageIO<S> io{means2d, conics, log_o, colors, depths, height, width, {S(0), S(0), S(0)},
                  nullptr, nullptr, nullptr, nullptr, nullptr, nullptr};
    if (background != nullptr) io.bg[0] = background[0], io.bg[1] = background[1], io.bg[2] = background[2];
    return io;
}

// Builds the records; fill(g, e) writes e[0 .. 6) (mean x, mean y, conic a, b, c, log opacity) and the F
// features e[PK .. PK + F).
template <typename S, typename Fill>
void gaussian_records_with(const Params& prm, int64_t G, int64_t F, Fill fill, S* rec) {
    const S lmin = std::log(static_cast<S>(prm.alpha_min));
    const S big = S(1 << 24);  // rows are exact integers in S up to here
    const int64_t workers = std::max<int64_t>(1, std::min<int64_t>(prm.num_threads, G / 16384 + 1));
    uskern::run_workers(workers, [&](int64_t w) {
        for (int64_t g = G * w / workers; g < G * (w + 1) / workers; ++g) {
            S* e = rec + g * record_stride<S>(F);
            fill(g, e);
            const S a = e[2], b = e[3], c = e[4];
            const S thr = S(2) * (e[5] - lmin);  // alpha >= alpha_min  <=>  conic form <= thr
            const S det = a * c - b * b;
            S rlo = 1, rhi = 0;
            if (thr >= S(0)) {
                rlo = -1, rhi = big;
                if (det > S(0) && a > S(0) && c > S(0) && std::isfinite(det) && std::isfinite(e[1])) {
                    // |dy| <= sqrt(thr * Sigma_yy), Sigma = conic^-1, so Sigma_yy = a / det
                    const S ey = std::sqrt(thr * (a / det) * S(1.002)) + S(0.01);
                    rlo = std::min(std::max(std::ceil(e[1] - ey - S(0.5)), S(-1)), big);
                    rhi = std::min(std::max(std::floor(e[1] + ey - S(0.5)), S(-1)), big);
                }
            }
            e[6] = rlo;
            e[7] = rhi;
        }
    });
}

// Records from gparams [G,6] and feat [G,F], or (io not null) from an ImageIO's arrays.
template <typename S>
void gaussian_records(const Params& prm, int64_t G, int64_t F, const S* gp, const S* feat, const ImageIO<S>* io,
                      S* rec) {
    if (io == nullptr) {
        gaussian_records_with<S>(prm, G, F, [&](int64_t g, S* e) {
            for (int k = 0; k < 6; ++k) e[k] = gp[g * 6 + k];
            for (int64_t f = 0; f < F; ++f) e[PK + f] = feat[g * F + f];
        }, rec);
        return;
    }
    gaussian_records_with<S>(prm, G, IMAGE_F, [&](int64_t g, S* e) {
        e[0] = io->means2d[2 * g], e[1] = io->means2d[2 * g + 1];
        e[2] = io->conics[3 * g], e[3] = io->conics[3 * g + 1], e[4] = io->conics[3 * g + 2];
        e[5] = io->log_o[g];
        e[PK] = io->colors[3 * g], e[PK + 1] = io->colors[3 * g + 1], e[PK + 2] = io->colors[3 * g + 2];
        e[PK + 3] = io->depths[g];
        e[PK + 4] = S(1);
    }, rec);
}

// The lanes of the tiles of one call: slice s holds pixels p = LANES s + lane of a tile, at offsets
// (col, row) from the tile's first pixel centre; padding lanes (p >= P) are inactive.
template <typename S>
struct LaneGrid {
    using V = typename Lanes<S>::V;
    using M = typename Lanes<S>::M;
    int64_t ts, P, NS;
    std::vector<V> col, row;
    std::vector<M> active;

    explicit LaneGrid(int64_t tile_size) : ts(tile_size), P(ts * ts), NS((P + LANES - 1) / LANES) {
        col.resize(NS), row.resize(NS), active.resize(NS);
        for (int64_t s = 0; s < NS; ++s)
            for (int l = 0; l < LANES; ++l) {
                const int64_t p = s * LANES + l, q = p < P ? p : P - 1;
                col[s][l] = static_cast<S>(q % ts);
                row[s][l] = static_cast<S>(q / ts);
                active[s][l] = p < P ? -1 : 0;
            }
    }
};

// One tile of a LaneGrid: its first pixel centre and the slices a record's rows fall in.
template <typename S>
struct TileLanes {
    const LaneGrid<S>& grid;
    int64_t row0;  // first pixel row of the tile
    S x0, y0;      // centre of its first pixel

    TileLanes(const LaneGrid<S>& g, const Params& prm, int64_t tile) : grid(g) {
        const int64_t local = tile % prm.tiles_per_cam;
        row0 = local / prm.tiles_x * g.ts;
        x0 = static_cast<S>(local % prm.tiles_x * g.ts) + S(0.5);
        y0 = static_cast<S>(row0) + S(0.5);
    }

    typename Lanes<S>::V px(int64_t s) const { return grid.col[s] + x0; }
    typename Lanes<S>::V py(int64_t s) const { return grid.row[s] + y0; }

    // The slices [s0, s1] holding a row of a record's [rlo, rhi] (s0 > s1 when none).
    void slices(const S* e, int64_t& s0, int64_t& s1) const {
        const int64_t r0 = std::max<int64_t>(static_cast<int64_t>(e[6]) - row0, 0);
        const int64_t r1 = std::min<int64_t>(static_cast<int64_t>(e[7]) - row0, grid.ts - 1);
        s0 = r0 * grid.ts / LANES;
        s1 = r0 > r1 ? s0 - 1 : (r1 * grid.ts + grid.ts - 1) / LANES;
    }
};

// Per-thread buffers of the backward (vectors of lanes: aligned for their type).
template <typename S>
struct SliceScratch {
    std::vector<typename Lanes<S>::V> v;
    std::vector<typename Lanes<S>::M> m;
};

// The exponent of alpha = exp(power) at pixel offsets (dx, dy); forward and backward share it so that
// their skip decisions agree exactly.
template <typename V, typename S>
inline V pixel_power(V dx, V dy, S a, S b, S c, S lo) {
    return lo - S(0.5) * (a * dx * dx + c * dy * dy) - b * dx * dy;
}

// Forward: each slice of LANES pixels walks the entries that can reach it, front to back, with its state
// (transmittance, accumulated features, last added entry, live mask) in registers, and stops as soon
// as every ray of the slice has stopped. The tile's list is taken in chunks of LIST_CHUNK entries: the
// per-slice lists of a chunk are built without branches (skipping costs no mispredicted jumps), and no
// list is built past the chunk where the last ray of the tile stopped (on dense scenes rays stop after a
// small part of a tile's list, and building the whole list per slice cost more than compositing).
constexpr int64_t LIST_CHUNK = 128;
constexpr int64_t PREFETCH = 8;  // entries ahead whose record is fetched while one is read

template <typename S>
struct ForwardScratch {
    std::vector<int64_t> lists;        // [NS] entries per slice, then [NS][LIST_CHUNK] list positions
    std::vector<typename Lanes<S>::V> v;  // per slice: T, then F accumulated features
    std::vector<typename Lanes<S>::M> m;  // per slice: last added entry + 1, live rays
};

template <typename S, int F>
void forward_tile(const Params& prm, const LaneGrid<S>& grid, int64_t tile, const S* rec, const int32_t* pair_gauss,
                  const int64_t* tile_start, const int64_t* tile_count, S* out, S* t_final, int32_t* last,
                  const ImageIO<S>* io, ForwardScratch<S>& scratch) {
    using V = typename Lanes<S>::V;
    using M = typename Lanes<S>::M;
    using I = typename Lanes<S>::I;
    const TileLanes<S> tl(grid, prm, tile);
    const int64_t P = grid.P, NS = grid.NS;
    const int64_t start = tile_start[tile], count = tile_count[tile];
    scratch.lists.resize(static_cast<size_t>(NS * LIST_CHUNK + NS));
    scratch.v.resize(static_cast<size_t>(NS * (1 + F)));
    scratch.m.resize(static_cast<size_t>(2 * NS));
    int64_t* nlist = scratch.lists.data();  // [NS] entries per slice in this chunk
    int64_t* lists = nlist + NS;            // [NS][LIST_CHUNK] list positions j, per slice
    V* Ts = scratch.v.data();               // [NS]
    V* accs = Ts + NS;                      // [NS][F]
    M* lasts = scratch.m.data();            // [NS]
    M* lives = lasts + NS;                  // [NS]
    int64_t alive = 0;                      // slices with a live ray
    for (int64_t s = 0; s < NS; ++s) {
        Ts[s] = V{} + S(1);
        for (int f = 0; f < F; ++f) accs[s * F + f] = V{};
        lasts[s] = M{};
        lives[s] = grid.active[s];
        alive += any_lane(lives[s]);
    }
    const S amin = static_cast<S>(prm.alpha_min), amax = static_cast<S>(prm.alpha_max);
    const S tmin = static_cast<S>(prm.t_min);
    for (int64_t c0 = 0; c0 < count && alive > 0; c0 += LIST_CHUNK) {
        const int64_t c1 = std::min(count, c0 + LIST_CHUNK);
        std::fill(nlist, nlist + NS, int64_t{0});
        for (int64_t j = c0; j < c1; ++j) {
            int64_t s0, s1;
            // the records are read in list order but lie in Gaussian order: fetch a few entries ahead
            if (j + PREFETCH < count) __builtin_prefetch(rec + static_cast<int64_t>(pair_gauss[start + j + PREFETCH]) * record_stride<S>(F));
            tl.slices(rec + static_cast<int64_t>(pair_gauss[start + j]) * record_stride<S>(F), s0, s1);
            for (int64_t s = 0; s < NS; ++s) {
                lists[s * LIST_CHUNK + nlist[s]] = j;
                nlist[s] += (s >= s0) & (s <= s1);
            }
        }
        alive = 0;
        for (int64_t s = 0; s < NS; ++s) {
            M live = lives[s];
            const int64_t n = nlist[s];
            if (n == 0 || !any_lane(live)) {
                alive += any_lane(live);
                continue;
            }
            const V px = tl.px(s), py = tl.py(s);
            const int64_t* sl = lists + s * LIST_CHUNK;
            V T = Ts[s];
            V acc[F];
            each_feature<F>([&](auto f) { acc[f] = accs[s * F + f]; });
            M lastv = lasts[s];
            // Entries in batches of B: their alphas first (independent of each other, so the exp
            // polynomials overlap), then the compositing, whose transmittance chain is serial.
            constexpr int64_t B = 4;
            for (int64_t k0 = 0; k0 < n; k0 += B) {
                V alpha[B];
                const S* eb[B];
                for (int64_t i = 0; i < B; ++i) {
                    const int64_t k = std::min(k0 + i, n - 1);  // a repeated last entry is masked below
                    eb[i] = rec + static_cast<int64_t>(pair_gauss[start + sl[k]]) * record_stride<S>(F);
                    const S* e = eb[i];
                    const V raw = vexp_lanes<V>(pixel_power<V, S>(px - e[0], py - e[1], e[2], e[3], e[4], e[5]));
                    alpha[i] = raw < amax ? raw : amax;
                }
                for (int64_t i = 0; i < B && k0 + i < n; ++i) {
                    const S* e = eb[i];
                    const V Tn = T * (S(1) - alpha[i]);
                    const M use = (alpha[i] >= amin) & live;
                    const M stop = use & (Tn < tmin);
                    const M add = use & ~stop;
                    const V w = add ? alpha[i] * T : V{};
                    each_feature<F>([&](auto f) { acc[f] += w * e[PK + f]; });
                    T = add ? Tn : T;
                    lastv = add ? M{} + static_cast<I>(sl[k0 + i] + 1) : lastv;
                    live = stop ? M{} : live;
                }
                if ((k0 & 7) == 4 && !any_lane(live)) break;  // every 8 entries: every ray of the slice stopped
            }
            Ts[s] = T;
            each_feature<F>([&](auto f) { accs[s * F + f] = acc[f]; });
            lasts[s] = lastv;
            lives[s] = live;
            alive += any_lane(live);
        }
    }
    for (int64_t s = 0; s < NS; ++s)
        for (int l = 0; l < LANES; ++l) {
            const int64_t p = s * LANES + l;
            if (p >= P) break;
            t_final[tile * P + p] = Ts[s][l];
            last[tile * P + p] = static_cast<int32_t>(lasts[s][l]);
            if constexpr (F == IMAGE_F) {
                if (io != nullptr) {
                    const int64_t q = io->pixel(prm, grid.ts, tile, p);
                    if (q < 0) continue;
                    for (int c = 0; c < 3; ++c) io->rgb[3 * q + c] = accs[s * F + c][l] + Ts[s][l] * io->bg[c];
                    io->depth[q] = accs[s * F + 3][l];
                    io->alpha[q] = accs[s * F + 4][l];
                    continue;
                }
            }
            S* o = out + (tile * P + p) * F;
            for (int f = 0; f < F; ++f) o[f] = accs[s * F + f][l];
        }
}

// Backward: the tile's list back to front from its last added entry; per entry, each slice that can hold
// it and still has it in front of a last added entry recovers its transmittance T_i = T_{i+1} /
// (1 - alpha_i) and suffix sum_{k>i} w_k h_k, and adds its pixels' d loss / d power moments and
// feature weights to lane accumulators in registers (one horizontal sum per entry). Only the first FA features
// have a gradient (FA < F: the others' d loss / d out is 0, so their terms are left out and their rows are 0, the
// same numbers as the full loop's to the bit).
template <typename S, int F, int FA = F>
void backward_tile(const Params& prm, const LaneGrid<S>& grid, int64_t tile, const S* rec, const int32_t* pair_gauss,
                   const int64_t* tile_start, const S* t_final, const int32_t* last, const S* g_out, S* g_pair,
                   int32_t* tile_used, const ImageIO<S>* io, SliceScratch<S>& scratch) {
    using V = typename Lanes<S>::V;
    using M = typename Lanes<S>::M;
    using I = typename Lanes<S>::I;
    const TileLanes<S> tl(grid, prm, tile);
    const int64_t P = grid.P, NS = grid.NS;
    const int32_t* lst = last + tile * P;
    int32_t maxlast = 0;
    for (int64_t p = 0; p < P; ++p) maxlast = std::max(maxlast, lst[p]);
    const int64_t start = tile_start[tile];
    // The pairs behind every ray of the tile (from maxlast on) get exactly zero gradient: their rows are
    // neither written nor summed (on dense scenes most of a tile's list lies behind its stopped rays).
    tile_used[tile] = maxlast;
    if (maxlast == 0) return;
    // scratch: per slice T, suffix, d loss / d out [F]; lane integers: last; padding lanes are inert
    scratch.v.resize(static_cast<size_t>(NS) * (2 + F));
    scratch.m.resize(static_cast<size_t>(NS));
    V* T = scratch.v.data();
    V* suf = T + NS;
    V* go = suf + NS;  // [F][NS]
    M* lq = scratch.m.data();
    std::vector<int32_t> slicemax(static_cast<size_t>(NS), 0);
    for (int64_t s = 0; s < NS; ++s)
        for (int l = 0; l < LANES; ++l) {
            const int64_t p = s * LANES + l;
            const bool in = p < P;
            T[s][l] = in ? t_final[tile * P + p] : S(1);
            suf[s][l] = S(0);
            lq[s][l] = in ? lst[p] : 0;
            if (in) slicemax[s] = std::max(slicemax[s], lst[p]);
            for (int f = 0; f < F; ++f) go[f * NS + s][l] = S(0);
            if (!in) continue;
            if constexpr (F == IMAGE_F) {
                if (io != nullptr) {
                    const int64_t q = io->pixel(prm, grid.ts, tile, p);
                    if (q < 0) continue;
                    S gb = S(0);  // the background's share: the last entry of the ray, weight T_final
                    for (int c = 0; c < 3; ++c) {
                        const S g = io->g_rgb != nullptr ? io->g_rgb[3 * q + c] : S(0);
                        go[c * NS + s][l] = g;
                        gb += g * io->bg[c];
                    }
                    go[3 * NS + s][l] = io->g_depth != nullptr ? io->g_depth[q] : S(0);
                    go[4 * NS + s][l] = io->g_alpha != nullptr ? io->g_alpha[q] : S(0);
                    suf[s][l] = T[s][l] * gb;
                    continue;
                }
            }
            for (int f = 0; f < F; ++f) go[f * NS + s][l] = g_out[(tile * P + p) * F + f];
        }
    const S amin = static_cast<S>(prm.alpha_min), amax = static_cast<S>(prm.alpha_max);
    for (int64_t j = maxlast - 1; j >= 0; --j) {
        if (j >= PREFETCH) __builtin_prefetch(rec + static_cast<int64_t>(pair_gauss[start + j - PREFETCH]) * record_stride<S>(F));
        const S* e = rec + static_cast<int64_t>(pair_gauss[start + j]) * record_stride<S>(F);
        const S mx = e[0], my = e[1], a = e[2], b = e[3], c = e[4], lo = e[5];
        const M jj = M{} + static_cast<I>(j);
        V m0{}, mx1{}, my1{}, mxx{}, mxy{}, myy{};
        V gf[F];
        each_feature<F>([&](auto f) { gf[f] = V{}; });
        M used{};
        int64_t s0, s1;
        tl.slices(e, s0, s1);
        for (int64_t s = s0; s <= s1; ++s) {
            if (j >= slicemax[s]) continue;  // every pixel of the slice stopped before this entry
            const V dx = tl.px(s) - mx, dy = tl.py(s) - my;
            const V raw = vexp_lanes<V>(pixel_power<V, S>(dx, dy, a, b, c, lo));
            const V alpha = raw < amax ? raw : amax;
            const M use = (jj < lq[s]) & (alpha >= amin);
            const V inv = S(1) / (S(1) - alpha);  // alpha <= alpha_max < 1
            const V Tb = use ? T[s] * inv : T[s];  // transmittance in front of this Gaussian
            const V w = use ? alpha * Tb : V{};
            V h{};
            each_feature<FA>([&](auto f) { h += go[f * NS + s] * e[PK + f]; });
            // d loss / d power = alpha d loss / d alpha = w h - alpha / (1 - alpha) * suffix
            const V dpow = w * h - (alpha * inv) * suf[s];
            const V d = (use & (raw < amax)) ? dpow : V{};
            suf[s] += w * h;
            T[s] = Tb;
            used |= use;
            // moments of d loss / d power: d power / d mean = (a dx + b dy, b dx + c dy),
            // d power / d(a, b, c) = -(dx^2 / 2, dx dy, dy^2 / 2)
            const V ddx = d * dx, ddy = d * dy;
            m0 += d;
            mx1 += ddx;
            my1 += ddy;
            mxx += ddx * dx;
            mxy += ddx * dy;
            myy += ddy * dy;
            each_feature<FA>([&](auto f) { gf[f] += w * go[f * NS + s]; });
        }
        S* row = g_pair + (start + j) * (6 + F);
        if (!any_lane(used)) {  // no pixel of the tile took this Gaussian: its gradient here is 0
            std::fill(row, row + 6 + F, S(0));
            continue;
        }
        V sums_in[6 + F] = {mx1, my1, mxx, mxy, myy, m0};
        each_feature<FA>([&](auto f) { sums_in[6 + f] = gf[f]; });
        S sum[6 + F] = {};
        lane_sums<S>(sums_in, 6 + FA, sum);
        row[0] = a * sum[0] + b * sum[1];
        row[1] = b * sum[0] + c * sum[1];
        row[2] = S(-0.5) * sum[2];
        row[3] = -sum[3];
        row[4] = S(-0.5) * sum[4];
        row[5] = sum[5];
        for (int f = 0; f < F; ++f) row[6 + f] = sum[6 + f];
    }
}

template <typename S, int F>
void forward_all(const Params& prm, int64_t G, const S* gp, const S* feat, const int32_t* pair_gauss,
                 const int64_t* tile_start, const int64_t* tile_count, S* out, S* t_final, int32_t* last,
                 const ImageIO<S>* io = nullptr) {
    Records<S> rec(G, F);
    gaussian_records<S>(prm, G, F, gp, feat, io, rec.data);
    const LaneGrid<S> grid(prm.tile_size);
    const int64_t workers = num_workers(prm.num_tiles, prm.num_threads, CHUNK);
    std::vector<ForwardScratch<S>> scratch(workers);
    for_each_tile(prm.num_tiles, workers, CHUNK, [&](int64_t id, int64_t t) {
        forward_tile<S, F>(prm, grid, t, rec.data, pair_gauss, tile_start, tile_count, out, t_final, last, io,
                           scratch[id]);
    });
}

// Where the image backward's per-Gaussian sums go (PLANAR): one contiguous block per input, [G, 2] means, [G, 3]
// conics, [G] log opacities, [G, 3] colours, [G] depths, [G] the constant feature, so that each input's gradient is
// one contiguous tensor (the projection and SH kernels read them as they are; strided slices of [G, 11] rows cost
// a copy each, 0.4 ms of a bonsai training step). Per field f of a pair's row: its block's start (in units of G),
// the block's width, and f's column in it.
constexpr int PLANAR_START[11] = {0, 0, 2, 2, 2, 5, 6, 6, 6, 9, 10};
constexpr int PLANAR_WIDTH[11] = {2, 2, 3, 3, 3, 1, 3, 3, 3, 1, 1};
constexpr int PLANAR_COLUMN[11] = {0, 1, 0, 1, 2, 0, 0, 1, 2, 0, 0};

// Per-pair gradients first (one thread owns a tile), then per-Gaussian sums in pair order: worker w
// adds the pairs of the Gaussians in its index range, so every sum is taken in the same order whatever
// the number of threads (backward is deterministic, and resumed training is bit-identical). The sums go to
// g_gauss as rows [G, 6 + F], or (PLANAR, F = IMAGE_F only) as the blocks above.
template <typename S, int F, bool PLANAR = false, int FA = F>
void backward_all(const Params& prm, int64_t G, int64_t M, const S* gp, const S* feat, const int32_t* pair_gauss,
                  const int64_t* tile_start, const int64_t* tile_count, const S* t_final, const int32_t* last,
                  const S* g_out, S* g_pair, S* g_gauss, const ImageIO<S>* io = nullptr) {
    static_assert(!PLANAR || 6 + F == 11, "the planar layout is the image backward's");
    Records<S> rec(G, F);
    gaussian_records<S>(prm, G, F, gp, feat, io, rec.data);
    const LaneGrid<S> grid(prm.tile_size);
    const int64_t workers = num_workers(prm.num_tiles, prm.num_threads, CHUNK);
    std::vector<SliceScratch<S>> scratch(workers);
    std::vector<int32_t> tile_used(static_cast<size_t>(prm.num_tiles), 0);  // rows written per tile
    for_each_tile(prm.num_tiles, workers, CHUNK, [&](int64_t id, int64_t t) {
        backward_tile<S, F, FA>(prm, grid, t, rec.data, pair_gauss, tile_start, t_final, last, g_out, g_pair,
                                tile_used.data(), io, scratch[id]);
    });
    const int64_t reducers = std::max<int64_t>(1, std::min<int64_t>(prm.num_threads, G / 4096 + 1));
    uskern::run_workers(reducers, [&](int64_t w) {
        const int64_t lo = G * w / reducers, hi = G * (w + 1) / reducers;
        if constexpr (PLANAR) {  // the caller need not zero it
            for (int f = 0; f < 11; ++f)
                if (PLANAR_COLUMN[f] == 0)
                    std::fill(g_gauss + PLANAR_START[f] * G + lo * PLANAR_WIDTH[f],
                              g_gauss + PLANAR_START[f] * G + hi * PLANAR_WIDTH[f], S(0));
        } else {
            std::fill(g_gauss + lo * (6 + F), g_gauss + hi * (6 + F), S(0));
        }
        for (int64_t t = 0; t < prm.num_tiles; ++t)  // pairs in ascending order, the written rows only
            for (int64_t k = tile_start[t], k1 = k + tile_used[t]; k < k1; ++k) {
                const int64_t g = pair_gauss[k];
                if (g < lo || g >= hi) continue;
                const S* src = g_pair + k * (6 + F);
                if constexpr (PLANAR) {
                    for (int f = 0; f < 6 + FA; ++f)
                        g_gauss[PLANAR_START[f] * G + g * PLANAR_WIDTH[f] + PLANAR_COLUMN[f]] += src[f];
                } else {
                    S* dst = g_gauss + g * (6 + F);
                    for (int f = 0; f < 6 + F; ++f) dst[f] += src[f];
                }
            }
    });
}

#define US_DISPATCH_F(F_RUNTIME, CALL) \
    switch (F_RUNTIME) {                \
        case 1: { constexpr int F = 1; CALL; } break; \
        case 2: { constexpr int F = 2; CALL; } break; \
        case 3: { constexpr int F = 3; CALL; } break; \
        case 4: { constexpr int F = 4; CALL; } break; \
        case 5: { constexpr int F = 5; CALL; } break; \
        case 6: { constexpr int F = 6; CALL; } break; \
        case 7: { constexpr int F = 7; CALL; } break; \
        case 8: { constexpr int F = 8; CALL; } break; \
        default: return 1;              \
    }

template <typename S>
int forward_any(int64_t F, const Params& prm, int64_t G, const S* gp, const S* feat, const int32_t* pair_gauss,
                const int64_t* tile_start, const int64_t* tile_count, S* out, S* t_final, int32_t* last) {
    try {
        US_DISPATCH_F(F, (forward_all<S, F>(prm, G, gp, feat, pair_gauss, tile_start, tile_count, out, t_final, last)));
    } catch (const std::bad_alloc&) {  // the per-Gaussian records (G x (8 + F) values)
        return 2;
    }
    return 0;
}

template <typename S>
int backward_any(int64_t F, const Params& prm, int64_t G, int64_t M, const S* gp, const S* feat,
                 const int32_t* pair_gauss, const int64_t* tile_start, const int64_t* tile_count, const S* t_final,
                 const int32_t* last, const S* g_out, S* g_pair, S* g_gauss) {
    try {
        US_DISPATCH_F(F, (backward_all<S, F>(prm, G, M, gp, feat, pair_gauss, tile_start, tile_count, t_final, last,
                                             g_out, g_pair, g_gauss)));
    } catch (const std::bad_alloc&) {
        return 2;
    }
    return 0;
}

template <typename S>
int forward_image(const Params& prm, int64_t G, const ImageIO<S>& io, const int32_t* pair_gauss,
                  const int64_t* tile_start, const int64_t* tile_count, S* t_final, int32_t* last) {
    try {
        forward_all<S, IMAGE_F>(prm, G, nullptr, nullptr, pair_gauss, tile_start, tile_count, nullptr, t_final, last,
                                &io);
    } catch (const std::bad_alloc&) {
        return 2;
    }
    return 0;
}

template <typename S>
int backward_image(const Params& prm, int64_t G, int64_t M, const ImageIO<S>& io, const int32_t* pair_gauss,
                   const int64_t* tile_start, const int64_t* tile_count, const S* t_final, const int32_t* last,
                   S* g_pair, S* g_gauss) {
    try {
        // A loss of the colour only (every training step) leaves the depth and alpha features out of the loop:
        // a sixteenth less of the step's CPU time on fern, the same gradients to the bit (BENCHMARKS.md)
        if (io.g_depth == nullptr && io.g_alpha == nullptr)
            backward_all<S, IMAGE_F, true, 3>(prm, G, M, nullptr, nullptr, pair_gauss, tile_start, tile_count, t_final,
                                              last, nullptr, g_pair, g_gauss, &io);
        else
            backward_all<S, IMAGE_F, true>(prm, G, M, nullptr, nullptr, pair_gauss, tile_start, tile_count, t_final,
                                           last, nullptr, g_pair, g_gauss, &io);
    } catch (const std::bad_alloc&) {
        return 2;
    }
    return 0;
}

// ------------------------------------------------------------------------------------------ binning
// The (tile, Gaussian) pairs of rasterize.bin_gaussians, in the same order: visible Gaussians (flat
// indices camera * N + n) are sorted front to back by a stable radix sort of their depth, each lists, in
// every row of its opacity-aware box, the tiles from the first to the last whose pixel-centre rectangle its
// alpha >= 1/255 ellipse reaches (the same conservative test), and a counting sort by tile keeps the depth order inside every tile. Workers
// take contiguous slices of the depth order, so the result does not depend on the number of threads.

struct BinArgs {
    int64_t G, N, C, width, height, tile_size, tiles_x, tiles_y, workers;
    double alpha_min;
};

// Stable LSD radix sort (8-bit digits) of the valid entries by depth; returns their count V.
int64_t depth_order(const BinArgs& a, const float* depths, const uint8_t* valid, int64_t* order) {
    std::vector<uint32_t> key, key2;
    std::vector<int64_t> idx2;
    int64_t V = 0;
    for (int64_t g = 0; g < a.G; ++g)
        if (valid[g]) order[V++] = g;
    key.resize(V);
    for (int64_t i = 0; i < V; ++i) {
        uint32_t bits;
        std::memcpy(&bits, depths + order[i], sizeof(bits));
        key[i] = (bits & 0x80000000u) ? ~bits : (bits | 0x80000000u);  // float order as unsigned order
    }
    key2.resize(V);
    idx2.resize(V);
    for (int shift = 0; shift < 32; shift += 8) {
        int64_t count[257] = {0};
        for (int64_t i = 0; i < V; ++i) ++count[((key[i] >> shift) & 0xff) + 1];
        if (count[1] == V) continue;  // all in one bucket: this digit keeps the order
        for (int d = 0; d < 256; ++d) count[d + 1] += count[d];
        for (int64_t i = 0; i < V; ++i) {
            const int64_t k = count[(key[i] >> shift) & 0xff]++;
            key2[k] = key[i];
            idx2[k] = order[i];
        }
        key.swap(key2);
        std::copy(idx2.begin(), idx2.end(), order);
    }
    return V;
}

// Tile range [tx0, tx1) x [ty0, ty1) of one Gaussian's box, clamped to the image.
template <typename S>
void tile_box(const BinArgs& a, S mx, S my, S ex, S ey, int64_t& tx0, int64_t& tx1, int64_t& ty0, int64_t& ty1) {
    const S limx = static_cast<S>(a.width - 1), limy = static_cast<S>(a.height - 1);
    auto clampv = [](S v, S hi) { return std::min(std::max(v, S(0)), hi); };
    const S lox = clampv(std::ceil(mx - ex - S(0.5)), limx), hix = clampv(std::floor(mx + ex - S(0.5)), limx);
    const S loy = clampv(std::ceil(my - ey - S(0.5)), limy), hiy = clampv(std::floor(my + ey - S(0.5)), limy);
    const S ts = static_cast<S>(a.tile_size);
    tx0 = static_cast<int64_t>(std::floor(lox / ts));
    ty0 = static_cast<int64_t>(std::floor(loy / ts));
    tx1 = std::max(tx0, static_cast<int64_t>(std::floor(hix / ts)) + 1);
    ty1 = std::max(ty0, static_cast<int64_t>(std::floor(hiy / ts)) + 1);
}

// Sets bits k0..k1 (inclusive) of a mask of 64-bit words.
inline void set_bits(uint64_t* bits, int64_t k0, int64_t k1) {
    for (int64_t w = k0 >> 6; w <= (k1 >> 6); ++w) {
        const int64_t lo = std::max(k0, w * 64) - w * 64, hi = std::min(k1, w * 64 + 63) - w * 64;
        bits[w] |= (~uint64_t{0} >> (63 - (hi - lo))) << lo;
    }
}

// The tiles of one Gaussian's box that its ellipse reaches: box origin (tx0, ty0), width bw and height bh
// in tiles; bit k of the mask (row-major in the box) is set when tile k lies in its row's run of tiles from the
// first to the last that pass the ellipse test (``row_hits``). A box of up to 64
// tiles holds its mask in `mask`; a larger one (big = true) keeps ceil(bw bh / 64) words in its worker's
// pool from word `mask` on (pass 2 gives every worker the same Gaussians as pass 1, so it finds them there).
struct BoxTiles {
    uint64_t mask;
    int32_t tx0, ty0, bw, bh;
    int64_t area() const { return static_cast<int64_t>(bw) * bh; }
    bool big() const { return area() > 64; }
};

template <typename S>
struct EllipseTest {
    S mx, my, ca, cb, cc, nb_c, nb_a, limit;
    int64_t ts;
};

template <typename S>
EllipseTest<S> ellipse_test(const BinArgs& a, int64_t g, const S* means2d, const S* conics, const S* opac) {
    const S o = opac[a.C > 1 ? g % a.N : g];
    const S ratio = o / static_cast<S>(a.alpha_min);
    const S thr = S(2) * std::log(ratio > S(1) ? ratio : S(1));
    const S ca = conics[3 * g], cb = conics[3 * g + 1], cc = conics[3 * g + 2];
    // margin against float rounding, as in rasterize.py
    return {means2d[2 * g], means2d[2 * g + 1], ca, cb, cc, -cb / cc, -cb / ca, thr * S(1.001) + S(1e-3), a.tile_size};
}

// Bit l of the result: tile (tx + l, ty) passes the ellipse test, for l < n <= LANES, LANES tiles of a row at
// once. The test: the alpha >= alpha_min ellipse may reach the tile's pixel-centre rectangle (conservative, NaN
// keeps the pair); the minimum of the conic form over the rectangle lies on an edge the mean is outside of, so
// it is the smaller of two clamped 1D minima (nb_c = -b / c, nb_a = -b / a; rasterize._ellipse_meets_tile).
template <typename S>
__attribute__((always_inline)) inline uint64_t row_hits(const EllipseTest<S>& e, int64_t tx, int64_t n, int64_t ty) {
    using V = typename Lanes<S>::V;
    V lane;
    for (int l = 0; l < LANES; ++l) lane[l] = static_cast<S>(l);
    auto clampv = [](auto v, auto lo, auto hi) {  // std::min(std::max(v, lo), hi), lane by lane
        const auto m = v < lo ? lo : v;
        return hi < m ? hi : m;
    };
    const S ts = static_cast<S>(e.ts);
    const V x0 = (static_cast<S>(tx) + lane) * ts + S(0.5) - e.mx;
    const S y0 = static_cast<S>(ty * e.ts) + S(0.5) - e.my;
    const V x1 = x0 + static_cast<S>(e.ts - 1);
    const S y1 = y0 + static_cast<S>(e.ts - 1);
    const V zero = V{} + S(0);
    const V dxs = clampv(zero, x0, x1);
    const S dys = std::min(std::max(S(0), y0), y1);
    const V dy1 = clampv(e.nb_c * dxs, V{} + y0, V{} + y1);
    const V q1 = e.ca * dxs * dxs + S(2) * e.cb * dxs * dy1 + e.cc * dy1 * dy1;
    const V dx2 = clampv(V{} + e.nb_a * dys, x0, x1);
    const V q2 = e.ca * dx2 * dx2 + S(2) * e.cb * dx2 * dys + e.cc * dys * dys;
    const auto miss = (q2 < q1 ? q2 : q1) > e.limit;  // NaN keeps the pair
    uint64_t bits = 0;
    // The lanes' signs as bits in one instruction where the target has it: GCC turns the loop below into
    // one extract per lane, which cost more than the tests themselves.
#if defined(__AVX512F__)
    if constexpr (sizeof(S) == 4 && LANES == 16)
        bits = static_cast<uint16_t>(~_mm512_test_epi32_mask(reinterpret_cast<__m512i>(miss),
                                                             reinterpret_cast<__m512i>(miss)));
    else
#elif defined(__AVX__)
    if constexpr (sizeof(S) == 4 && LANES == 8)
        bits = ~static_cast<uint64_t>(_mm256_movemask_ps(reinterpret_cast<__m256>(miss))) & 0xffu;
    else
#elif defined(__SSE__)
    if constexpr (sizeof(S) == 4 && LANES == 4)
        bits = ~static_cast<uint64_t>(_mm_movemask_ps(reinterpret_cast<__m128>(miss))) & 0xfu;
    else
#endif
        for (int l = 0; l < LANES; ++l) bits |= static_cast<uint64_t>(miss[l] == 0) << l;
    return n >= 64 ? bits : bits & ((uint64_t{1} << n) - 1);
}

// How many Gaussians ahead pass 1 fetches the rows of the one it will read (random in memory: depth order).
constexpr int64_t PREFETCH_AHEAD = 16;

// Pass 1: the depth order, each visible Gaussian's box and tile mask (boxes [V]), and per worker the
// number of pairs of each tile (counts [workers, T]).
template <typename S>
int64_t bin_count(const BinArgs& a, const S* means2d, const S* extents, const S* conics, const S* opac,
                  const S* depths, const uint8_t* valid, int64_t* order, int64_t* num_visible, int64_t* counts,
                  std::vector<BoxTiles>& boxes, std::vector<std::vector<uint64_t>>& pools) {
    static_assert(sizeof(S) == 4 || sizeof(S) == 8, "float or double");
    int64_t V;
    if constexpr (sizeof(S) == 4) {
        V = depth_order(a, depths, valid, order);
    } else {  // float64 inputs (tests): sort by the float32 depth would lose ties; use a stable sort
        V = 0;
        for (int64_t g = 0; g < a.G; ++g)
            if (valid[g]) order[V++] = g;
        std::stable_sort(order, order + V, [&](int64_t x, int64_t y) { return depths[x] < depths[y]; });
    }
    *num_visible = V;
    const int64_t T = a.C * a.tiles_x * a.tiles_y;
    boxes.resize(static_cast<size_t>(V));
    pools.assign(static_cast<size_t>(a.workers), {});
    // A row's hits are one run of tiles (the ellipse's slice through a row of tiles is convex), so each row is
    // scanned from both ends to its first hit and the run between is counted in a difference array with one
    // extra column per row (tiles_x + 1), summed into the counts at the end.
    const int64_t W1 = a.tiles_x + 1;
    uskern::run_workers(a.workers, [&](int64_t w) {
        std::vector<int64_t> diff(static_cast<size_t>(a.C * a.tiles_y * W1), 0);
        std::vector<uint64_t>& pool = pools[w];
        const int64_t i_end = V * (w + 1) / a.workers;
        for (int64_t i = V * w / a.workers; i < i_end; ++i) {
            const int64_t g = order[i];
            if (i + PREFETCH_AHEAD < i_end) {
                // the Gaussians come in depth order, so their rows are read at random: fetch a later one's now
                const int64_t h = order[i + PREFETCH_AHEAD];
                __builtin_prefetch(means2d + 2 * h);
                __builtin_prefetch(extents + 2 * h);
                __builtin_prefetch(conics + 3 * h);
                __builtin_prefetch(opac + (a.C > 1 ? h % a.N : h));
            }
            int64_t tx0, tx1, ty0, ty1;
            tile_box<S>(a, means2d[2 * g], means2d[2 * g + 1], extents[2 * g], extents[2 * g + 1], tx0, tx1, ty0, ty1);
            const EllipseTest<S> meets = ellipse_test<S>(a, g, means2d, conics, opac);
            BoxTiles& box = boxes[i];
            box = {0, static_cast<int32_t>(tx0), static_cast<int32_t>(ty0), static_cast<int32_t>(tx1 - tx0),
                   static_cast<int32_t>(ty1 - ty0)};
            const int64_t rows = (g / a.N) * a.tiles_y * W1;
            uint64_t* bits = &box.mask;
            if (box.big()) {
                box.mask = pool.size();
                pool.resize(pool.size() + static_cast<size_t>((box.area() + 63) / 64), 0);
                bits = pool.data() + box.mask;
            }
            const int64_t last_chunk = tx0 + (tx1 - 1 - tx0) / LANES * LANES;
            for (int64_t ty = ty0; ty < ty1; ++ty) {
                int64_t lo = -1, hi = -1;
                uint64_t bits_lo = 0;
                for (int64_t c = tx0; c < tx1; c += LANES)
                    if ((bits_lo = row_hits<S>(meets, c, std::min<int64_t>(LANES, tx1 - c), ty)) != 0) {
                        lo = c + __builtin_ctzll(bits_lo);
                        break;
                    }
                if (lo < 0) continue;
                for (int64_t c = last_chunk;; c -= LANES) {
                    const uint64_t b = c <= lo ? bits_lo : row_hits<S>(meets, c, std::min<int64_t>(LANES, tx1 - c), ty);
                    if (b != 0) {
                        hi = c + 63 - __builtin_clzll(b);
                        break;
                    }
                }
                int64_t* d = diff.data() + rows + ty * W1;
                ++d[lo];
                --d[hi + 1];
                set_bits(bits, (ty - ty0) * box.bw + (lo - tx0), (ty - ty0) * box.bw + (hi - tx0));
            }
        }
        int64_t* cnt = counts + w * T;
        for (int64_t r = 0; r < a.C * a.tiles_y; ++r) {
            int64_t run = 0;
            for (int64_t tx = 0; tx < a.tiles_x; ++tx) cnt[r * a.tiles_x + tx] = run += diff[r * W1 + tx];
        }
    });
    int64_t total = 0;
    for (int64_t i = 0; i < a.workers * T; ++i) total += counts[i];
    return total;
}

// Pass 2: with tile_start (cumulative counts over all workers), every worker writes its pairs after
// those of the workers before it (its slice is nearer), so every tile stays in depth order. The tiles of a
// box come from its mask.
void bin_fill(const BinArgs& a, const int64_t* order, int64_t V, const std::vector<BoxTiles>& boxes,
              const std::vector<std::vector<uint64_t>>& pools, const int64_t* counts, const int64_t* tile_start,
              int32_t* pair_gauss, int64_t* pair_tile) {
    const int64_t T = a.C * a.tiles_x * a.tiles_y, tpc = a.tiles_x * a.tiles_y;
    uskern::run_workers(a.workers, [&](int64_t w) {
        std::vector<int64_t> cursor(tile_start, tile_start + T);
        for (int64_t v = 0; v < w; ++v)
            for (int64_t t = 0; t < T; ++t) cursor[t] += counts[v * T + t];
        auto emit = [&](int64_t g, int64_t t) {
            const int64_t k = cursor[t]++;
            pair_gauss[k] = static_cast<int32_t>(g);  // G < 2^31: rasterize.py checks
            if (pair_tile != nullptr) pair_tile[k] = t;  // optional: the Python side can derive it
        };
        for (int64_t i = V * w / a.workers; i < V * (w + 1) / a.workers; ++i) {
            const int64_t g = order[i];
            const BoxTiles& box = boxes[i];
            const int64_t base = (g / a.N) * tpc;
            const uint64_t* bits = box.big() ? pools[w].data() + box.mask : &box.mask;
            for (int64_t word = 0, words = (box.area() + 63) / 64; word < words; ++word)
                for (uint64_t m = bits[word]; m != 0; m &= m - 1) {
                    const int64_t k = word * 64 + __builtin_ctzll(m);
                    emit(g, base + (box.ty0 + k / box.bw) * a.tiles_x + box.tx0 + k % box.bw);
                }
        }
    });
}

// What pass 1 leaves for pass 2 (held by the caller between the two calls).
struct BinState {
    std::vector<BoxTiles> boxes;
    std::vector<std::vector<uint64_t>> pools;  // per worker, the masks of its big boxes
};

template <typename S>
int64_t bin_count_any(const BinArgs& args, const S* means2d, const S* extents, const S* conics, const S* opac,
                      const S* depths, const uint8_t* valid, int64_t* order, int64_t* num_visible, int64_t* counts,
                      void** state) {
    *state = nullptr;
    try {
        auto* st = new BinState();
        const int64_t M = bin_count<S>(args, means2d, extents, conics, opac, depths, valid, order, num_visible,
                                       counts, st->boxes, st->pools);
        *state = st;
        return M;
    } catch (const std::bad_alloc&) {
        return -1;
    }
}

template <typename S>
int bin_fill_any(const BinArgs& args, const S* means2d, const S* conics, const S* opac, const int64_t* order,
                 int64_t V, void* state, const int64_t* counts, const int64_t* tile_start, int32_t* pair_gauss,
                 int64_t* pair_tile) {
    auto* st = static_cast<BinState*>(state);
    if (st == nullptr || static_cast<int64_t>(st->boxes.size()) != V) return 1;
    (void)means2d, (void)conics, (void)opac;  // pass 1's masks hold the tests
    bin_fill(args, order, V, st->boxes, st->pools, counts, tile_start, pair_gauss, pair_tile);
    delete st;
    return 0;
}
}  // namespace

// The kernels' parameters from the C interface's arguments of the same names.
#define US_PARAMS                                                                                     \
    Params prm{num_tiles, tiles_x, tiles_per_cam, tile_size, num_threads, alpha_min, alpha_max, t_min};
