// Fused training losses: SSIM (mean per image, with its gradient) and the KL terms of the offset tables.
//
// Both are written in torch in uncertsplat/eval/image.py and uncertsplat/gaussians/variational.py (the
// reference and the path on other devices); here each is one pass over memory instead of a dozen
// elementwise tensor ops, and the gradient comes out of the same pass.
//
// Determinism: every sum is taken over fixed blocks in a fixed order, so results do not depend on the
// number of threads.

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <vector>

#include "parallel.h"
#include "vmath.h"

namespace {

using uskern::vlog;
using uskern::vsigmoid;
using uskern::vsoftplus;

constexpr int64_t BLOCK = 8192;  // elements per partial sum

template <typename Fn>
void parallel_blocks(int64_t n, int64_t num_threads, Fn fn) {
    const int64_t blocks = (n + BLOCK - 1) / BLOCK;
    const int64_t workers = std::max<int64_t>(1, std::min(num_threads, blocks));
    uskern::run_workers(workers, [&](int64_t id) {
        for (int64_t b = id; b < blocks; b += workers) fn(b, b * BLOCK, std::min(n, (b + 1) * BLOCK));
    });
}

// ------------------------------------------------------------------------------------------ KL
// Elementwise KL(N(loc, softplus(raw)^2) || N(mu_p, sd_p^2)) summed over [lo, hi); with GRAD, also
// d kl / d loc and d kl / d raw per element. log softplus(raw) is raw below -15 (no underflow), as in
// variational.log_softplus. Pointers are __restrict locals so that the loop vectorises.
template <bool GRAD>
double gaussian_kl_block(int64_t lo, int64_t hi, const float* __restrict loc, const float* __restrict raw, float mu_p,
                         float inv_var, float log_sd, float* __restrict g_loc, float* __restrict g_raw) {
    double sum = 0.0;
#pragma omp simd reduction(+ : sum)
    for (int64_t i = lo; i < hi; ++i) {
        const float s = raw[i], d = loc[i] - mu_p;
        const float sp = vsoftplus(s), sig = vsigmoid(s);
        const bool low = s < -15.0f;
        const float lsp = low ? s : vlog(sp);
        sum += log_sd - lsp + 0.5f * (sp * sp + d * d) * inv_var - 0.5f;
        if (GRAD) {
            g_loc[i] = d * inv_var;
            g_raw[i] = -(low ? 1.0f : sig / sp) + sp * sig * inv_var;
        }
    }
    return sum;
}

double gaussian_kl(int64_t n, const float* loc, const float* raw, float mu_p, float sd_p, float* g_loc,
                   float* g_raw, int64_t num_threads) {
    std::vector<double> part((n + BLOCK - 1) / BLOCK, 0.0);
    const float inv_var = 1.0f / (sd_p * sd_p), log_sd = std::log(sd_p);
    parallel_blocks(n, num_threads, [&](int64_t b, int64_t lo, int64_t hi) {
        part[b] = g_loc != nullptr ? gaussian_kl_block<true>(lo, hi, loc, raw, mu_p, inv_var, log_sd, g_loc, g_raw)
                                   : gaussian_kl_block<false>(lo, hi, loc, raw, mu_p, inv_var, log_sd, g_loc, g_raw);
    });
    double total = 0.0;
    for (double v : part) total += v;
    return total;
}

// The scale-multiplier term: "ours" (PAPER false) the KL between the moment-matched Gaussians of
// U[l, l + w] and U[1 - w_p, 1]; "paper" the L1 distance between interval end points.
// w = clamp(softplus(raw), w_min, w_max), whose gradient is 0 outside the clamp (as torch.clamp).
template <bool GRAD, bool PAPER>
double scale_kl_block(int64_t lo, int64_t hi, const float* __restrict left, const float* __restrict raw, float wp,
                      float inv_var, float log_wp, float w_min, float w_max, float* __restrict g_left,
                      float* __restrict g_raw) {
    double sum = 0.0;
#pragma omp simd reduction(+ : sum)
    for (int64_t i = lo; i < hi; ++i) {
        const float s = raw[i], l = left[i];
        const float sp = vsoftplus(s);
        const float w = std::min(std::max(sp, w_min), w_max);
        const float dw_ds = (sp >= w_min && sp <= w_max) ? vsigmoid(s) : 0.0f;
        float v, gl, gw;
        if (!PAPER) {
            const float dm = (l + 0.5f * w) - (1.0f - 0.5f * wp);
            v = log_wp - vlog(w) + 0.5f * (w * w + 12.0f * dm * dm) * inv_var - 0.5f;
            gl = 12.0f * dm * inv_var;
            gw = -1.0f / w + (w + 6.0f * dm) * inv_var;
        } else {
            const float a = l - (1.0f - wp), c = l + w - 1.0f;
            v = std::fabs(a) + std::fabs(c);
            const float sa = a > 0.0f ? 1.0f : (a < 0.0f ? -1.0f : 0.0f);
            const float sc = c > 0.0f ? 1.0f : (c < 0.0f ? -1.0f : 0.0f);
            gl = sa + sc;
            gw = sc;
        }
        sum += v;
        if (GRAD) {
            g_left[i] = gl;
            g_raw[i] = gw * dw_ds;
        }
    }
    return sum;
}

double scale_kl(int64_t n, const float* left, const float* raw, float wp, int variant, float w_min, float w_max,
                float* g_left, float* g_raw, int64_t num_threads) {
    std::vector<double> part((n + BLOCK - 1) / BLOCK, 0.0);
    const float inv_var = 1.0f / (wp * wp), log_wp = std::log(wp);
    parallel_blocks(n, num_threads, [&](int64_t b, int64_t lo, int64_t hi) {
        const bool grad = g_left != nullptr;
        auto run = [&](auto fn) { return fn(lo, hi, left, raw, wp, inv_var, log_wp, w_min, w_max, g_left, g_raw); };
        if (variant == 0)
            part[b] = grad ? run(scale_kl_block<true, false>) : run(scale_kl_block<false, false>);
        else
            part[b] = grad ? run(scale_kl_block<true, true>) : run(scale_kl_block<false, true>);
    });
    double total = 0.0;
    for (double v : part) total += v;
    return total;
}

// ---------------------------------------------------------------------------------------- SSIM
// Separable zero-padded "same" blurs with the window w [K] (K odd, r = (K - 1) / 2). The forward runs one pass
// per task (SsimTasks: a run of rows of one plane): each row is blurred horizontally into a ring of the last K
// rows, and each output row vertically from the ring as soon as it holds the row's window, keeping the sums in
// registers (LANES pixels at a time) and applying the per-pixel formula right away, so neither blurred plane is
// stored. The backward runs two phases over rows (every thread takes rows of every plane): the horizontal pass of
// its three inputs into padded row buffers, then the vertical pass (one pass with a ring measured 3-6 % slower
// there on HWC images: the rows around each run are blurred twice, and its planes are read once anyway). Each
// plane's mean is summed per row, then over rows in a fixed order (any thread count gives the same result).

constexpr int SSIM_LANES = uskern::LANES;
using VS = uskern::floatv;

inline VS load_vs(const float* p) {
    VS v;
    std::memcpy(&v, p, sizeof(VS));
    return v;
}

inline void store_vs(float* p, VS v) { std::memcpy(p, &v, sizeof(VS)); }

// Row geometry: rows of padded width Wp (a multiple of the lanes); a padded input row holds r zeros, the
// W values, then zeros up to Wp + 2 r. The B planes are the CH channels of B / CH images in HWC layout
// (CH = 1: planes [B, H, W]): plane b is channel b % CH of image b / CH, its pixels CH floats apart, so
// the caller's images need no copy into planes.
struct SsimRows {
    int64_t B, H, W, K, r, Wp, CH;
    SsimRows(int64_t B_, int64_t H_, int64_t W_, int64_t K_, int64_t CH_)
        : B(B_), H(H_), W(W_), K(K_), r((K_ - 1) / 2), Wp((W_ + SSIM_LANES - 1) / SSIM_LANES * SSIM_LANES),
          CH(CH_) {}
    // Offset of plane b's row y, pixel 0, in the caller's images.
    int64_t row(int64_t b, int64_t y) const { return (b / CH * H + y) * W * CH + b % CH; }
};

// Runs fn(item, buffer) for item in [0, n) on `workers` threads (contiguous ranges); buffer is the worker's own
// scratch of buf_size floats (zeros at first).
template <typename Fn>
void parallel_ranges(int64_t n, int64_t workers, size_t buf_size, Fn fn) {
    workers = std::max<int64_t>(1, std::min<int64_t>(workers, n));
    uskern::run_workers(workers, [&](int64_t w) {
        std::vector<float> buf(buf_size);
        for (int64_t i = n * w / workers; i < n * (w + 1) / workers; ++i) fn(i, buf.data());
    });
}

// What a horizontal pass blurs, from the padded input rows a, b, c: kFull the SSIM forward's a, b, a^2, b^2, a b
// (products formed on the fly); kPred the forward's a, a^2, a b when the target's own blurs are given (its b and b^2
// never change from step to step); kTarget those, b and b^2; kInputs the backward's a, b, c. Each quantity is summed
// with the same operations in every mode, so a blur is the same to the bit whichever pass computes it.
enum class HQ { kFull, kPred, kTarget, kInputs };
template <HQ Q>
constexpr int num_quantities() {
    return Q == HQ::kFull ? 5 : (Q == HQ::kTarget ? 2 : 3);
}

// Horizontal blur of one row: out[q][x] = sum_k w[k] f_q(a[x + k], b[x + k], c[x + k]) for the padded rows a, b, c
// and the quantities f_q of mode Q.
template <HQ Q>
inline void hblur_row(const SsimRows& g, const float* w, const float* a, const float* b, const float* c,
                      float* const* out) {
    constexpr int NQ = num_quantities<Q>();
    for (int64_t x0 = 0; x0 < g.Wp; x0 += SSIM_LANES) {
        VS acc[NQ] = {};
        for (int64_t k = 0; k < g.K; ++k) {
            const float wk = w[k];
            if constexpr (Q == HQ::kFull) {
                const VS va = load_vs(a + x0 + k), vb = load_vs(b + x0 + k);
                acc[0] += wk * va;
                acc[1] += wk * vb;
                acc[2] += wk * (va * va);
                acc[3] += wk * (vb * vb);
                acc[4] += wk * (va * vb);
            } else if constexpr (Q == HQ::kPred) {
                const VS va = load_vs(a + x0 + k), vb = load_vs(b + x0 + k);
                acc[0] += wk * va;
                acc[1] += wk * (va * va);
                acc[2] += wk * (va * vb);
            } else if constexpr (Q == HQ::kTarget) {
                const VS vb = load_vs(b + x0 + k);
                acc[0] += wk * vb;
                acc[1] += wk * (vb * vb);
            } else {
                acc[0] += wk * load_vs(a + x0 + k);
                acc[1] += wk * load_vs(b + x0 + k);
                acc[2] += wk * load_vs(c + x0 + k);
            }
        }
        for (int q = 0; q < NQ; ++q) store_vs(out[q] + x0, acc[q]);
    }
}

// A padded copy of a row of W values `stride` floats apart (zeros around it).
inline void pad_row(const SsimRows& g, const float* src, int64_t stride, float* dst) {
    std::fill(dst, dst + g.Wp + 2 * g.r, 0.0f);
    if (stride == 1) {
        std::memcpy(dst + g.r, src, sizeof(float) * g.W);
    } else {
        for (int64_t i = 0; i < g.W; ++i) dst[g.r + i] = src[i * stride];
    }
}

// Vertical blur at output row y of NQ horizontally blurred rows, LANES pixels from x0: sum over the rows y + k - r
// inside the image. Quantity q's rows start at hb[q], row `row` being the slot(row)-th of Wp floats there (full planes
// in the backward: slot(row) = row; a ring of the last K rows in the forward: row % K).
template <int NQ, typename Slot>
inline void vblur(const SsimRows& g, const float* w, const float* const* hb, Slot slot, int64_t y, int64_t x0,
                  VS* acc) {
    const int64_t k0 = std::max<int64_t>(0, g.r - y), k1 = std::min<int64_t>(g.K, g.H - y + g.r);
    for (int q = 0; q < NQ; ++q) acc[q] = VS{};
    for (int64_t k = k0; k < k1; ++k) {
        const float wk = w[k];
        const int64_t off = slot(y + k - g.r) * g.Wp + x0;
        for (int q = 0; q < NQ; ++q) acc[q] += wk * load_vs(hb[q] + off);
    }
}

// The SSIM passes' tasks: each plane's rows in `chunks` contiguous runs, task t = plane t / chunks, run t % chunks.
// A task blurs the rows of its run (and the r rows on either side it needs) horizontally into a ring of K rows and
// blurs each output row vertically as soon as the ring holds its window, so the horizontally blurred planes never
// leave the cache (they were 5 full planes, 6.6 MB for a 401x266 RGB image, written and read back). Runs of about
// H / chunks rows: the r rows above and below a run are blurred twice, so the runs are long (2 per plane for 3
// planes on 2 threads).
struct SsimTasks {
    int64_t chunks, count;
    SsimTasks(const SsimRows& g, int64_t num_threads) {
        const int64_t threads = std::max<int64_t>(1, num_threads);
        chunks = std::max<int64_t>(1, std::min<int64_t>(g.H, (2 * threads + g.B - 1) / g.B));
        count = g.B * chunks;
    }
    int64_t plane(int64_t t) const { return t / chunks; }
    int64_t y0(const SsimRows& g, int64_t t) const { return g.H * (t % chunks) / chunks; }
    int64_t y1(const SsimRows& g, int64_t t) const { return g.H * (t % chunks + 1) / chunks; }
};

// Stores the first n (<= LANES) lanes of v at p.
inline void store_lanes(float* p, VS v, int64_t n) {
    if (n == SSIM_LANES) {
        store_vs(p, v);
    } else {
        for (int64_t l = 0; l < n; ++l) p[l] = v[l];
    }
}

// The calling thread's buffer of at least n floats, kept between calls: a training step's SSIM backward needs some
// MB of it (2.8 MB for three 320x240 planes), and a fresh std::vector is zero-filled on every call, though every
// element the caller reads it writes first. One per calling thread (views may be scored on threads).
std::vector<float>& scratch(size_t n) {
    thread_local std::vector<float> buf;
    if (buf.size() < n) buf.resize(n);
    return buf;
}

// The rows of task t (SsimTasks) streamed through a ring of the last K horizontally blurred rows of NQ quantities
// (`ring`: NQ K Wp floats): before output row oy, every input row its vertical window needs is passed once, in
// order, to blur_row(row, out) (out[q]: that row's slot of quantity q in the ring); then row_done(oy, ring_q, slot)
// (ring_q[q]: quantity q's K rows; slot(row): a row's place among them).
template <int NQ, typename BlurRow, typename RowDone>
void stream_rows(const SsimRows& g, const SsimTasks& tasks, int64_t t, float* ring, BlurRow blur_row,
                 RowDone row_done) {
    const int64_t y0 = tasks.y0(g, t), y1 = tasks.y1(g, t);
    float* ring_q[NQ];
    for (int q = 0; q < NQ; ++q) ring_q[q] = ring + q * g.K * g.Wp;
    auto slot = [&](int64_t row) { return row % g.K; };
    int64_t next = std::max<int64_t>(0, y0 - g.r);  // the next row to blur horizontally into the ring
    for (int64_t oy = y0; oy < y1; ++oy) {
        for (const int64_t last = std::min<int64_t>(g.H - 1, oy + g.r); next <= last; ++next) {
            float* out[NQ];
            for (int q = 0; q < NQ; ++q) out[q] = ring_q[q] + slot(next) * g.Wp;
            blur_row(next, out);
        }
        row_done(oy, ring_q, slot);
    }
}

// Loads the first n (<= LANES) floats at p into the lanes of a vector (the others 0).
inline VS load_lanes(const float* p, int64_t n) {
    if (n == SSIM_LANES) return load_vs(p);
    VS v{};
    std::memcpy(&v, p, sizeof(float) * n);
    return v;
}

// The SSIM map of LANES pixels from their local statistics; with `partials` given (the first of LANES pixels of the
// first of three planes `stride` floats apart), also its partial derivatives w.r.t. (mu_x, E[x^2], E[xy]) there
// (n of the lanes stored). Not inlined: both forwards (the target blurred or given) run this one compiled formula,
// so the compiler's choice of fused multiply-adds cannot make them differ.
__attribute__((noinline)) VS ssim_pixels(VS ux, VS uy, VS exx, VS eyy, VS exy, float c1, float c2, float* partials,
                                         int64_t stride, int64_t n) {
    const VS sxx = exx - ux * ux, syy = eyy - uy * uy, sxy = exy - ux * uy;
    const VS a1 = 2.0f * ux * uy + c1, a2 = 2.0f * sxy + c2;
    const VS b1 = ux * ux + uy * uy + c1, b2 = sxx + syy + c2;
    // Divide only by b1 b2 >= c1 c2 > 0: a2 = 2 sxy + c2 can be 0 (anti-correlated windows)
    const VS inv_d = 1.0f / (b1 * b2);
    const VS s = a1 * a2 * inv_d;
    if (partials != nullptr) {
        store_lanes(partials, (2.0f * uy * (a2 - a1) - 2.0f * ux * s * (b2 - b1)) * inv_d, n);
        store_lanes(partials + stride, -s * b1 * inv_d, n);
        store_lanes(partials + 2 * stride, 2.0f * a1 * inv_d, n);
    }
    return s;
}

// SSIM of the B planes of x, y (SsimRows: B = images x channels): per-plane mean of the SSIM map into
// plane_mean [B]; with `partials` [3, B, H, W] given, also the per-pixel partial derivatives of the
// map w.r.t. (mu_x, E[x^2], E[xy]), which ssim_backward turns into d loss / d x. With `plane_l1` [B] given,
// also each plane's mean |x - y| (the L1 term of the training loss, from the rows this pass reads anyway).
// With `ystats` [2, B, H, W] given (ssim_target_stats of y: its blurred mean and mean square), those are read
// instead of blurred (TARGET = true): three quantities blurred instead of five, the same result to the bit.
template <bool TARGET>
void ssim_forward_impl(int64_t B, int64_t H, int64_t W, int64_t K, int64_t CH, const float* x, const float* y,
                       const float* ystats, const float* w, float c1, float c2, double* plane_mean, float* partials,
                       double* plane_l1, int64_t num_threads) {
    constexpr HQ MODE = TARGET ? HQ::kPred : HQ::kFull;
    constexpr int NQ = num_quantities<MODE>();
    const SsimRows g(B, H, W, K, CH);
    const SsimTasks tasks(g, num_threads);
    std::vector<double> row_l1(plane_l1 != nullptr ? static_cast<size_t>(B * H) : 0, 0.0);
    std::vector<double> row_sum(static_cast<size_t>(B * H), 0.0);
    const int64_t HW = H * W;
    const int64_t row_len = g.Wp + 2 * g.r + SSIM_LANES;  // a padded row and the lanes read past it
    const size_t ring_len = static_cast<size_t>(NQ * K * g.Wp);  // the horizontally blurred quantities
    parallel_ranges(tasks.count, num_threads, 2 * row_len + ring_len, [&](int64_t t, float* buf) {
        const int64_t b = tasks.plane(t), y0 = tasks.y0(g, t), y1 = tasks.y1(g, t);
        float *pa = buf, *pb = buf + row_len;
        auto blur_row = [&](int64_t row, float* const* out) {
            pad_row(g, x + g.row(b, row), CH, pa);
            pad_row(g, y + g.row(b, row), CH, pb);
            if (plane_l1 != nullptr && row >= y0 && row < y1) {  // each row's L1 in the task that owns it
                VS acc{};
                for (int64_t i = 0; i < g.Wp; i += SSIM_LANES) {
                    const VS d = load_vs(pa + g.r + i) - load_vs(pb + g.r + i);  // zeros past W on both
                    acc += d < 0.0f ? -d : d;
                }
                float sum = 0.0f;
                for (int l = 0; l < SSIM_LANES; ++l) sum += acc[l];
                row_l1[b * H + row] = sum;
            }
            hblur_row<MODE>(g, w, pa, pb, nullptr, out);
        };
        auto row_done = [&](int64_t oy, float* const* ring_q, auto slot) {
            VS sum{};
            for (int64_t x0 = 0; x0 < W; x0 += SSIM_LANES) {
                const int64_t n = std::min<int64_t>(SSIM_LANES, W - x0);
                VS m[NQ];
                vblur<NQ>(g, w, ring_q, slot, oy, x0, m);
                VS ux, uy, exx, eyy, exy;
                if constexpr (TARGET) {
                    const int64_t o = b * HW + oy * W + x0;
                    ux = m[0], exx = m[1], exy = m[2];
                    uy = load_lanes(ystats + o, n), eyy = load_lanes(ystats + B * HW + o, n);
                } else {
                    ux = m[0], uy = m[1], exx = m[2], eyy = m[3], exy = m[4];
                }
                const VS s = ssim_pixels(ux, uy, exx, eyy, exy, c1, c2,
                                         partials != nullptr ? partials + b * HW + oy * W + x0 : nullptr, B * HW, n);
                if (n == SSIM_LANES) {
                    sum += s;
                } else {
                    for (int64_t l = 0; l < n; ++l) sum[l] += s[l];
                }
            }
            double total = 0.0;
            for (int l = 0; l < SSIM_LANES; ++l) total += sum[l];
            row_sum[b * H + oy] = total;
        };
        stream_rows<NQ>(g, tasks, t, buf + 2 * row_len, blur_row, row_done);
    });
    for (int64_t b = 0; b < B; ++b) {
        double total = 0.0, l1 = 0.0;
        for (int64_t yy = 0; yy < H; ++yy) total += row_sum[b * H + yy];
        plane_mean[b] = total / static_cast<double>(HW);
        if (plane_l1 == nullptr) continue;
        for (int64_t yy = 0; yy < H; ++yy) l1 += row_l1[b * H + yy];
        plane_l1[b] = l1 / static_cast<double>(HW);
    }
}

// The blurred mean and mean square of each plane of y into out [2, B, H, W]: what the SSIM forward computes of its
// target every time, kept by a caller whose targets repeat (the training photos), with the forward's operations.
void ssim_target_stats(int64_t B, int64_t H, int64_t W, int64_t K, int64_t CH, const float* y, const float* w,
                       float* out, int64_t num_threads) {
    const SsimRows g(B, H, W, K, CH);
    const SsimTasks tasks(g, num_threads);
    const int64_t HW = H * W;
    const int64_t row_len = g.Wp + 2 * g.r + SSIM_LANES;
    parallel_ranges(tasks.count, num_threads, row_len + static_cast<size_t>(2 * K * g.Wp), [&](int64_t t,
                                                                                           float* buf) {
        const int64_t b = tasks.plane(t);
        auto blur_row = [&](int64_t row, float* const* out) {
            pad_row(g, y + g.row(b, row), CH, buf);
            hblur_row<HQ::kTarget>(g, w, nullptr, buf, nullptr, out);
        };
        auto row_done = [&](int64_t oy, float* const* ring_q, auto slot) {
            for (int64_t x0 = 0; x0 < W; x0 += SSIM_LANES) {
                const int64_t n = std::min<int64_t>(SSIM_LANES, W - x0);
                VS m[2];
                vblur<2>(g, w, ring_q, slot, oy, x0, m);
                const int64_t o = b * HW + oy * W + x0;
                store_lanes(out + o, m[0], n);
                store_lanes(out + B * HW + o, m[1], n);
            }
        };
        stream_rows<2>(g, tasks, t, buf + row_len, blur_row, row_done);
    });
}

// d loss / d x for loss = sum_b g_plane[b] * plane_mean[b] (+ g_l1[b] * plane_l1[b] when g_l1 is given):
// g_plane[b] / HW * (blur(d_mu) + 2 x blur(d_exx) + y blur(d_exy)) (the blur is its own adjoint), plus
// g_l1[b] / HW * sign(x - y) (0 where x == y, as torch's abs).
void ssim_backward(int64_t B, int64_t H, int64_t W, int64_t K, int64_t CH, const float* x, const float* y,
                   const float* w, const float* partials, const float* g_plane, const float* g_l1, float* g_x,
                   int64_t num_threads) {
    const SsimRows g(B, H, W, K, CH);
    const int64_t HWp = H * g.Wp, HW = H * W;
    std::vector<float>& hbuf = scratch(static_cast<size_t>(3 * B * HWp));
    const int64_t row_len = g.Wp + 2 * g.r + SSIM_LANES;
    const int64_t workers = std::min<int64_t>(num_threads, B * H / 16 + 1);  // at least 16 rows each
    parallel_ranges(B * H, workers, 3 * row_len, [&](int64_t row, float* buf) {
        const int64_t b = row / H, yy = row % H;
        float *pa = buf, *pb = buf + row_len, *pc = buf + 2 * row_len;
        pad_row(g, partials + b * HW + yy * W, 1, pa);
        pad_row(g, partials + (B + b) * HW + yy * W, 1, pb);
        pad_row(g, partials + (2 * B + b) * HW + yy * W, 1, pc);
        float* out[3];
        for (int q = 0; q < 3; ++q) out[q] = hbuf.data() + (q * B + b) * HWp + yy * g.Wp;
        hblur_row<HQ::kInputs>(g, w, pa, pb, pc, out);
    });
    parallel_ranges(B * H, workers, 0, [&](int64_t row, float*) {
        const int64_t b = row / H, yy = row % H;
        const float* hb[3];
        for (int q = 0; q < 3; ++q) hb[q] = hbuf.data() + (q * B + b) * HWp;
        const float scale = g_plane[b] / static_cast<float>(HW);
        const float l1_scale = g_l1 != nullptr ? g_l1[b] / static_cast<float>(HW) : 0.0f;
        const float* xr = x + g.row(b, yy);
        const float* yr = y + g.row(b, yy);
        float* gr = g_x + g.row(b, yy);
        for (int64_t x0 = 0; x0 < W; x0 += SSIM_LANES) {
            const int64_t n = std::min<int64_t>(SSIM_LANES, W - x0);
            VS m[3];
            vblur<3>(g, w, hb, [](int64_t row) { return row; }, yy, x0, m);
            VS xv{}, yv{};
            if (CH == 1) {
                std::memcpy(&xv, xr + x0, sizeof(float) * n);
                std::memcpy(&yv, yr + x0, sizeof(float) * n);
            } else {
                for (int64_t l = 0; l < n; ++l) xv[l] = xr[(x0 + l) * CH], yv[l] = yr[(x0 + l) * CH];
            }
            VS gv = scale * (m[0] + 2.0f * xv * m[1] + yv * m[2]);
            if (g_l1 != nullptr) {
                const VS d = xv - yv;
                gv += (d > 0.0f ? VS{} + l1_scale : VS{}) - (d < 0.0f ? VS{} + l1_scale : VS{});
            }
            if (CH == 1) {
                store_lanes(gr + x0, gv, n);
            } else {
                for (int64_t l = 0; l < n; ++l) gr[(x0 + l) * CH] = gv[l];
            }
        }
    });
}

}  // namespace

extern "C" {

double us_gaussian_kl_f32(int64_t n, const float* loc, const float* raw, double mu_p, double sd_p, float* g_loc,
                          float* g_raw, int64_t num_threads) {
    return gaussian_kl(n, loc, raw, static_cast<float>(mu_p), static_cast<float>(sd_p), g_loc, g_raw, num_threads);
}

double us_scale_kl_f32(int64_t n, const float* left, const float* raw, double wp, int64_t variant, double w_min,
                       double w_max, float* g_left, float* g_raw, int64_t num_threads) {
    return scale_kl(n, left, raw, static_cast<float>(wp), static_cast<int>(variant), static_cast<float>(w_min),
                    static_cast<float>(w_max), g_left, g_raw, num_threads);
}

// The B planes are the CH channels of B / CH images [H, W, CH] (CH = 1: planes [B, H, W]); returns 1 when B is
// not a multiple of CH. plane_l1 (forward) and g_l1 (backward) may be null: no L1 term.
int us_ssim_forward_f32(int64_t B, int64_t H, int64_t W, int64_t K, int64_t CH, const float* x, const float* y,
                        const float* ystats, const float* w, double c1, double c2, double* plane_mean,
                        float* partials, double* plane_l1, int64_t num_threads) {
    if (CH < 1 || B % CH != 0) return 1;
    auto run = [&](auto impl) {
        impl(B, H, W, K, CH, x, y, ystats, w, static_cast<float>(c1), static_cast<float>(c2), plane_mean, partials,
             plane_l1, num_threads);
    };
    if (ystats != nullptr)
        run(ssim_forward_impl<true>);
    else
        run(ssim_forward_impl<false>);
    return 0;
}

// ystats [2, B, H, W]: the blurred mean and mean square of y's planes, for us_ssim_forward_f32's `ystats`.
int us_ssim_target_stats_f32(int64_t B, int64_t H, int64_t W, int64_t K, int64_t CH, const float* y, const float* w,
                             float* ystats, int64_t num_threads) {
    if (CH < 1 || B % CH != 0) return 1;
    ssim_target_stats(B, H, W, K, CH, y, w, ystats, num_threads);
    return 0;
}

int us_ssim_backward_f32(int64_t B, int64_t H, int64_t W, int64_t K, int64_t CH, const float* x, const float* y,
                         const float* w, const float* partials, const float* g_plane, const float* g_l1, float* g_x,
                         int64_t num_threads) {
    if (CH < 1 || B % CH != 0) return 1;
    ssim_backward(B, H, W, K, CH, x, y, w, partials, g_plane, g_l1, g_x, num_threads);
    return 0;
}

}  // extern "C"
