// Native CPU rasterizer kernels of uncertsplat: tile binning and the per-pixel front-to-back loop of 3DGS,
// forward and backward.
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
// Vectorisation: the pixel loop of a tile is the inner loop (SIMD across pixels, like a warp), with
// branch-free selects; exp is vmath.h's polynomial (float), which the compiler vectorises.

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <vector>

#include "parallel.h"
#include "vmath.h"

namespace {

template <typename S>
inline S expo(S x);

template <>
inline float expo<float>(float x) {
    return uskern::vexp(x);
}

template <>
inline double expo<double>(double x) {
    return std::exp(x);
}

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

template <typename S>
void pixel_centres(const Params& prm, int64_t tile, S* px, S* py) {
    const int64_t ts = prm.tile_size;
    const int64_t local = tile % prm.tiles_per_cam;
    const int64_t tx = local % prm.tiles_x, ty = local / prm.tiles_x;
    for (int64_t r = 0; r < ts; ++r)
        for (int64_t c = 0; c < ts; ++c) {
            px[r * ts + c] = static_cast<S>(tx * ts + c) + S(0.5);
            py[r * ts + c] = static_cast<S>(ty * ts + r) + S(0.5);
        }
}

template <typename S, int F>
void forward_tile(const Params& prm, int64_t tile, const S* gp, const S* feat, const int64_t* pair_gauss,
                  const int64_t* tile_start, const int64_t* tile_count, S* out, S* t_final, int32_t* last,
                  std::vector<S>& scratch) {
    const int64_t P = prm.tile_size * prm.tile_size;
    scratch.assign(P * (3 + F + 1), S(0));
    S* px = scratch.data();
    S* py = px + P;
    S* T = py + P;
    S* acc = T + P;  // [F][P]
    S* live = acc + F * P;
    int32_t* lst = last + tile * P;
    pixel_centres(prm, tile, px, py);
    for (int64_t p = 0; p < P; ++p) {
        T[p] = S(1);
        live[p] = S(1);
        lst[p] = 0;
    }
    const S amin = static_cast<S>(prm.alpha_min), amax = static_cast<S>(prm.alpha_max);
    const S tmin = static_cast<S>(prm.t_min);
    const int64_t start = tile_start[tile], count = tile_count[tile];
    for (int64_t j = 0; j < count; ++j) {
        const int64_t g = pair_gauss[start + j];
        const S* q = gp + g * 6;
        const S mx = q[0], my = q[1], a = q[2], b = q[3], c = q[4], lo = q[5];
        S fv[F];
        for (int f = 0; f < F; ++f) fv[f] = feat[g * F + f];
        const int32_t jn = static_cast<int32_t>(j + 1);
#pragma omp simd
        for (int64_t p = 0; p < P; ++p) {
            const S dx = px[p] - mx, dy = py[p] - my;
            const S power = lo - S(0.5) * (a * dx * dx + c * dy * dy) - b * dx * dy;
            S alpha = expo<S>(power);
            alpha = alpha < amax ? alpha : amax;
            const S Tp = T[p];
            const S Tn = Tp * (S(1) - alpha);
            const bool use = (alpha >= amin) & (live[p] > S(0));
            const bool stop = use & (Tn < tmin);
            const bool add = use & !stop;
            const S w = add ? alpha * Tp : S(0);
            for (int f = 0; f < F; ++f) acc[f * P + p] += w * fv[f];
            T[p] = add ? Tn : Tp;
            lst[p] = add ? jn : lst[p];
            live[p] = stop ? S(0) : live[p];
        }
        if ((j & 7) == 7) {  // every 8 entries: stop when every ray of the tile has stopped
            S any = 0;
            for (int64_t p = 0; p < P; ++p) any += live[p];
            if (any == S(0)) break;
        }
    }
    S* o = out + tile * P * F;
    for (int64_t p = 0; p < P; ++p) {
        for (int f = 0; f < F; ++f) o[p * F + f] = acc[f * P + p];
        t_final[tile * P + p] = T[p];
    }
}

template <typename S, int F>
void backward_tile(const Params& prm, int64_t tile, const S* gp, const S* feat, const int64_t* pair_gauss,
                   const int64_t* tile_start, const int64_t* tile_count, const S* t_final, const int32_t* last,
                   const S* g_out, S* g_pair, std::vector<S>& scratch) {
    const int64_t P = prm.tile_size * prm.tile_size;
    const int32_t* lst = last + tile * P;
    int32_t maxlast = 0;
    for (int64_t p = 0; p < P; ++p) maxlast = std::max(maxlast, lst[p]);
    // pairs behind every ray of the tile get exactly zero gradient
    std::fill(g_pair + (tile_start[tile] + maxlast) * (6 + F),
              g_pair + (tile_start[tile] + tile_count[tile]) * (6 + F), S(0));
    if (maxlast == 0) return;
    scratch.assign(P * (6 + F), S(0));
    S* px = scratch.data();
    S* py = px + P;
    S* T = py + P;
    S* suf = T + P;
    S* wbuf = suf + P;
    S* dbuf = wbuf + P;
    S* go = dbuf + P;  // [F][P]
    pixel_centres(prm, tile, px, py);
    const S* gt = g_out + tile * P * F;
    for (int64_t p = 0; p < P; ++p) {
        T[p] = t_final[tile * P + p];
        for (int f = 0; f < F; ++f) go[f * P + p] = gt[p * F + f];
    }
    const S amin = static_cast<S>(prm.alpha_min), amax = static_cast<S>(prm.alpha_max);
    const int64_t start = tile_start[tile];
    for (int64_t j = maxlast - 1; j >= 0; --j) {
        const int64_t g = pair_gauss[start + j];
        const S* q = gp + g * 6;
        const S mx = q[0], my = q[1], a = q[2], b = q[3], c = q[4], lo = q[5];
        S fv[F];
        for (int f = 0; f < F; ++f) fv[f] = feat[g * F + f];
        const int32_t jj = static_cast<int32_t>(j);
        // Pass 1: per-pixel weight and d loss / d power (and whether any pixel used this Gaussian).
        S used = 0;
#pragma omp simd reduction(max : used)
        for (int64_t p = 0; p < P; ++p) {
            const S dx = px[p] - mx, dy = py[p] - my;
            const S power = lo - S(0.5) * (a * dx * dx + c * dy * dy) - b * dx * dy;
            const S raw = expo<S>(power);
            const S alpha = raw < amax ? raw : amax;
            const bool use = (jj < lst[p]) & (alpha >= amin);
            const S inv = S(1) / (S(1) - alpha);  // alpha <= alpha_max < 1
            const S Tb = use ? T[p] * inv : T[p];  // transmittance in front of this Gaussian
            const S w = use ? alpha * Tb : S(0);
            S h = 0;
            for (int f = 0; f < F; ++f) h += go[f * P + p] * fv[f];
            // d loss / d power = alpha d loss / d alpha = w h - alpha / (1 - alpha) * suffix
            const S dpow = w * h - (alpha * inv) * suf[p];
            dbuf[p] = (use & (raw < amax)) ? dpow : S(0);
            wbuf[p] = w;
            T[p] = Tb;
            suf[p] += w * h;
            used = use ? S(1) : used;
        }
        S* row = g_pair + (start + j) * (6 + F);
        if (used == S(0)) {  // no pixel of the tile took this Gaussian: its gradient here is 0
            std::fill(row, row + 6 + F, S(0));
            continue;
        }
        // Pass 2: moments of d loss / d power over the tile's pixels, then the chain rule once per pair:
        // d power / d mean = (a dx + b dy, b dx + c dy), d power / d(a, b, c) = -(dx^2 / 2, dx dy, dy^2 / 2).
        S m0 = 0, mx1 = 0, my1 = 0, mxx = 0, mxy = 0, myy = 0;
#pragma omp simd reduction(+ : m0, mx1, my1, mxx, mxy, myy)
        for (int64_t p = 0; p < P; ++p) {
            const S dx = px[p] - mx, dy = py[p] - my, d = dbuf[p];
            const S ddx = d * dx, ddy = d * dy;
            m0 += d;
            mx1 += ddx;
            my1 += ddy;
            mxx += ddx * dx;
            mxy += ddx * dy;
            myy += ddy * dy;
        }
        const S glo = m0, gmx = a * mx1 + b * my1, gmy = b * mx1 + c * my1, ga = mxx, gb = mxy, gc = myy;
        S gf[F];
        for (int f = 0; f < F; ++f) {
            S sum = 0;
            const S* gof = go + f * P;
#pragma omp simd reduction(+ : sum)
            for (int64_t p = 0; p < P; ++p) sum += wbuf[p] * gof[p];
            gf[f] = sum;
        }
        row[0] = gmx;
        row[1] = gmy;
        row[2] = S(-0.5) * ga;
        row[3] = -gb;
        row[4] = S(-0.5) * gc;
        row[5] = glo;
        for (int f = 0; f < F; ++f) row[6 + f] = gf[f];
    }
}

template <typename S, int F>
void forward_all(const Params& prm, const S* gp, const S* feat, const int64_t* pair_gauss, const int64_t* tile_start,
                 const int64_t* tile_count, S* out, S* t_final, int32_t* last) {
    const int64_t workers = num_workers(prm.num_tiles, prm.num_threads, CHUNK);
    std::vector<std::vector<S>> scratch(workers);
    for_each_tile(prm.num_tiles, workers, CHUNK, [&](int64_t id, int64_t t) {
        forward_tile<S, F>(prm, t, gp, feat, pair_gauss, tile_start, tile_count, out, t_final, last, scratch[id]);
    });
}

// Per-pair gradients first (one thread owns a tile), then per-Gaussian sums in pair order: worker w
// adds the pairs of the Gaussians in its index range, so every sum is taken in the same order whatever
// the number of threads (backward is deterministic, and resumed training is bit-identical).
template <typename S, int F>
void backward_all(const Params& prm, int64_t G, int64_t M, const S* gp, const S* feat, const int64_t* pair_gauss,
                  const int64_t* tile_start, const int64_t* tile_count, const S* t_final, const int32_t* last,
                  const S* g_out, S* g_pair, S* g_gauss) {
    const int64_t workers = num_workers(prm.num_tiles, prm.num_threads, CHUNK);
    std::vector<std::vector<S>> scratch(workers);
    for_each_tile(prm.num_tiles, workers, CHUNK, [&](int64_t id, int64_t t) {
        backward_tile<S, F>(prm, t, gp, feat, pair_gauss, tile_start, tile_count, t_final, last, g_out, g_pair,
                            scratch[id]);
    });
    const int64_t reducers = std::max<int64_t>(1, std::min<int64_t>(prm.num_threads, G / 4096 + 1));
    uskern::run_workers(reducers, [&](int64_t w) {
        const int64_t lo = G * w / reducers, hi = G * (w + 1) / reducers;
        for (int64_t k = 0; k < M; ++k) {
            const int64_t g = pair_gauss[k];
            if (g < lo || g >= hi) continue;
            const S* src = g_pair + k * (6 + F);
            S* dst = g_gauss + g * (6 + F);
            for (int f = 0; f < 6 + F; ++f) dst[f] += src[f];
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
int forward_any(int64_t F, const Params& prm, const S* gp, const S* feat, const int64_t* pair_gauss,
                const int64_t* tile_start, const int64_t* tile_count, S* out, S* t_final, int32_t* last) {
    US_DISPATCH_F(F, (forward_all<S, F>(prm, gp, feat, pair_gauss, tile_start, tile_count, out, t_final, last)));
    return 0;
}

template <typename S>
int backward_any(int64_t F, const Params& prm, int64_t G, int64_t M, const S* gp, const S* feat,
                 const int64_t* pair_gauss, const int64_t* tile_start, const int64_t* tile_count, const S* t_final,
                 const int32_t* last, const S* g_out, S* g_pair, S* g_gauss) {
    US_DISPATCH_F(F, (backward_all<S, F>(prm, G, M, gp, feat, pair_gauss, tile_start, tile_count, t_final, last, g_out,
                                         g_pair, g_gauss)));
    return 0;
}


// ------------------------------------------------------------------------------------------ binning
// The (tile, Gaussian) pairs of rasterize.bin_gaussians, in the same order: visible Gaussians (flat
// indices camera * N + n) are sorted front to back by a stable radix sort of their depth, each lists the
// tiles of its opacity-aware box whose pixel-centre rectangle its alpha >= 1/255 ellipse reaches (the
// same conservative test), and a counting sort by tile keeps the depth order inside every tile. Workers
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

// True when the alpha >= alpha_min ellipse may reach the tile's pixel-centre rectangle (conservative,
// NaN keeps the pair): the minimum of the conic form over the rectangle lies on an edge the mean is
// outside of, so it is the smaller of two clamped 1D minima. nb_c = -b / c and nb_a = -b / a.
template <typename S>
bool ellipse_meets_tile(S mx, S my, S ca, S cb, S cc, S nb_c, S nb_a, S limit, int64_t tx, int64_t ty, int64_t ts) {
    const S x0 = static_cast<S>(tx * ts) + S(0.5) - mx, y0 = static_cast<S>(ty * ts) + S(0.5) - my;
    const S x1 = x0 + static_cast<S>(ts - 1), y1 = y0 + static_cast<S>(ts - 1);
    auto clampv = [](S v, S lo, S hi) { return std::min(std::max(v, lo), hi); };
    const S dxs = clampv(S(0), x0, x1), dys = clampv(S(0), y0, y1);
    const S dy1 = clampv(nb_c * dxs, y0, y1);
    const S q1 = ca * dxs * dxs + S(2) * cb * dxs * dy1 + cc * dy1 * dy1;
    const S dx2 = clampv(nb_a * dys, x0, x1);
    const S q2 = ca * dx2 * dx2 + S(2) * cb * dx2 * dys + cc * dys * dys;
    return !(std::min(q1, q2) > limit);
}

// Calls emit(g, tile) for every pair of the Gaussians order[lo, hi), in that order.
template <typename S, typename Emit>
void visit_pairs(const BinArgs& a, const int64_t* order, int64_t lo, int64_t hi, const S* means2d, const S* extents,
                 const S* conics, const S* opac, Emit emit) {
    const int64_t tpc = a.tiles_x * a.tiles_y;
    for (int64_t i = lo; i < hi; ++i) {
        const int64_t g = order[i];
        const S mx = means2d[2 * g], my = means2d[2 * g + 1];
        int64_t tx0, tx1, ty0, ty1;
        tile_box<S>(a, mx, my, extents[2 * g], extents[2 * g + 1], tx0, tx1, ty0, ty1);
        const S o = opac[a.C > 1 ? g % a.N : g];
        const S ratio = o / static_cast<S>(a.alpha_min);
        const S thr = S(2) * std::log(ratio > S(1) ? ratio : S(1));
        const S limit = thr * S(1.001) + S(1e-3);  // margin against float rounding, as in rasterize.py
        const S ca = conics[3 * g], cb = conics[3 * g + 1], cc = conics[3 * g + 2];
        const S nb_c = -cb / cc, nb_a = -cb / ca;
        const int64_t base = (g / a.N) * tpc;
        for (int64_t ty = ty0; ty < ty1; ++ty)
            for (int64_t tx = tx0; tx < tx1; ++tx)
                if (ellipse_meets_tile<S>(mx, my, ca, cb, cc, nb_c, nb_a, limit, tx, ty, a.tile_size))
                    emit(g, base + ty * a.tiles_x + tx);
    }
}

// Pass 1: the depth order, and per worker the number of pairs of each tile (counts [workers, T]).
template <typename S>
int64_t bin_count(const BinArgs& a, const S* means2d, const S* extents, const S* conics, const S* opac,
                  const S* depths, const uint8_t* valid, int64_t* order, int64_t* num_visible, int64_t* counts) {
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
    std::fill(counts, counts + a.workers * T, int64_t{0});
    uskern::run_workers(a.workers, [&](int64_t w) {
        int64_t* cnt = counts + w * T;
        visit_pairs<S>(a, order, V * w / a.workers, V * (w + 1) / a.workers, means2d, extents, conics, opac,
                       [&](int64_t, int64_t t) { ++cnt[t]; });
    });
    int64_t total = 0;
    for (int64_t i = 0; i < a.workers * T; ++i) total += counts[i];
    return total;
}

// Pass 2: with tile_start (cumulative counts over all workers), every worker writes its pairs after
// those of the workers before it (its slice is nearer), so every tile stays in depth order.
template <typename S>
void bin_fill(const BinArgs& a, const S* means2d, const S* extents, const S* conics, const S* opac,
              const int64_t* order, int64_t V, const int64_t* counts, const int64_t* tile_start, int64_t* pair_gauss,
              int64_t* pair_tile) {
    const int64_t T = a.C * a.tiles_x * a.tiles_y;
    uskern::run_workers(a.workers, [&](int64_t w) {
        std::vector<int64_t> cursor(tile_start, tile_start + T);
        for (int64_t v = 0; v < w; ++v)
            for (int64_t t = 0; t < T; ++t) cursor[t] += counts[v * T + t];
        visit_pairs<S>(a, order, V * w / a.workers, V * (w + 1) / a.workers, means2d, extents, conics, opac,
                       [&](int64_t g, int64_t t) {
                           const int64_t k = cursor[t]++;
                           pair_gauss[k] = g;
                           pair_tile[k] = t;
                       });
    });
}
}  // namespace

extern "C" {

// Interface version: native.py refuses a library whose version differs from its own.
int us_version() { return 9; }

int us_max_features() { return 8; }

#define US_PARAMS                                                                                     \
    Params prm{num_tiles, tiles_x, tiles_per_cam, tile_size, num_threads, alpha_min, alpha_max, t_min};

int us_forward_f32(int64_t num_tiles, int64_t tiles_x, int64_t tiles_per_cam, int64_t tile_size, int64_t num_threads,
                   double alpha_min, double alpha_max, double t_min, int64_t F, const float* gp, const float* feat,
                   const int64_t* pair_gauss, const int64_t* tile_start, const int64_t* tile_count, float* out,
                   float* t_final, int32_t* last) {
    US_PARAMS
    return forward_any<float>(F, prm, gp, feat, pair_gauss, tile_start, tile_count, out, t_final, last);
}

int us_forward_f64(int64_t num_tiles, int64_t tiles_x, int64_t tiles_per_cam, int64_t tile_size, int64_t num_threads,
                   double alpha_min, double alpha_max, double t_min, int64_t F, const double* gp, const double* feat,
                   const int64_t* pair_gauss, const int64_t* tile_start, const int64_t* tile_count, double* out,
                   double* t_final, int32_t* last) {
    US_PARAMS
    return forward_any<double>(F, prm, gp, feat, pair_gauss, tile_start, tile_count, out, t_final, last);
}

int us_backward_f32(int64_t num_tiles, int64_t tiles_x, int64_t tiles_per_cam, int64_t tile_size, int64_t num_threads,
                    double alpha_min, double alpha_max, double t_min, int64_t F, int64_t G, int64_t M,
                    const float* gp, const float* feat, const int64_t* pair_gauss, const int64_t* tile_start,
                    const int64_t* tile_count, const float* t_final, const int32_t* last, const float* g_out,
                    float* g_pair, float* g_gauss) {
    US_PARAMS
    return backward_any<float>(F, prm, G, M, gp, feat, pair_gauss, tile_start, tile_count, t_final, last, g_out, g_pair,
                              g_gauss);
}

int us_backward_f64(int64_t num_tiles, int64_t tiles_x, int64_t tiles_per_cam, int64_t tile_size, int64_t num_threads,
                    double alpha_min, double alpha_max, double t_min, int64_t F, int64_t G, int64_t M,
                    const double* gp, const double* feat, const int64_t* pair_gauss, const int64_t* tile_start,
                    const int64_t* tile_count, const double* t_final, const int32_t* last, const double* g_out,
                    double* g_pair, double* g_gauss) {
    US_PARAMS
    return backward_any<double>(F, prm, G, M, gp, feat, pair_gauss, tile_start, tile_count, t_final, last, g_out, g_pair,
                              g_gauss);
}

// Binning, in two calls. us_bin_count: the depth order of the valid entries (order [G], num_visible),
// per-worker tile counts [workers, T]; returns the number of pairs M. us_bin_fill: with tile_start [T]
// (cumulative sum of the counts summed over workers), writes pair_gauss and pair_tile [M].
#define US_BIN_ARGS BinArgs args{G, N, C, width, height, tile_size, tiles_x, tiles_y, workers, alpha_min};
#define US_BIN_HEAD                                                                                             \
    int64_t G, int64_t N, int64_t C, int64_t width, int64_t height, int64_t tile_size, int64_t tiles_x,       \
        int64_t tiles_y, int64_t workers, double alpha_min

int64_t us_bin_count_f32(US_BIN_HEAD, const float* means2d, const float* extents, const float* conics,
                         const float* opac, const float* depths, const uint8_t* valid, int64_t* order,
                         int64_t* num_visible, int64_t* counts) {
    US_BIN_ARGS
    return bin_count<float>(args, means2d, extents, conics, opac, depths, valid, order, num_visible, counts);
}

int64_t us_bin_count_f64(US_BIN_HEAD, const double* means2d, const double* extents, const double* conics,
                         const double* opac, const double* depths, const uint8_t* valid, int64_t* order,
                         int64_t* num_visible, int64_t* counts) {
    US_BIN_ARGS
    return bin_count<double>(args, means2d, extents, conics, opac, depths, valid, order, num_visible, counts);
}

int us_bin_fill_f32(US_BIN_HEAD, const float* means2d, const float* extents, const float* conics, const float* opac,
                    const int64_t* order, int64_t num_visible, const int64_t* counts, const int64_t* tile_start,
                    int64_t* pair_gauss, int64_t* pair_tile) {
    US_BIN_ARGS
    bin_fill<float>(args, means2d, extents, conics, opac, order, num_visible, counts, tile_start, pair_gauss, pair_tile);
    return 0;
}

int us_bin_fill_f64(US_BIN_HEAD, const double* means2d, const double* extents, const double* conics,
                    const double* opac, const int64_t* order, int64_t num_visible, const int64_t* counts,
                    const int64_t* tile_start, int64_t* pair_gauss, int64_t* pair_tile) {
    US_BIN_ARGS
    bin_fill<double>(args, means2d, extents, conics, opac, order, num_visible, counts, tile_start, pair_gauss,
                     pair_tile);
    return 0;
}

}  // extern "C"
