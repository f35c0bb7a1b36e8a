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
// Zero-padded "same" separable blur of one plane: out = sum_ij w_i w_j in[y + i - r, x + j - r], in = 0 outside.
void blur_plane(const float* in, float* out, float* tmp, int64_t H, int64_t W, const float* w, int64_t K) {
    const int64_t r = (K - 1) / 2;
    std::fill(tmp, tmp + H * W, 0.0f);
    for (int64_t y = 0; y < H; ++y) {
        const float* src = in + y * W;
        float* dst = tmp + y * W;
        for (int64_t k = 0; k < K; ++k) {
            const int64_t off = k - r;
            const int64_t x0 = std::max<int64_t>(0, -off), x1 = std::min<int64_t>(W, W - off);
            const float wk = w[k];
            for (int64_t x = x0; x < x1; ++x) dst[x] += wk * src[x + off];
        }
    }
    std::fill(out, out + H * W, 0.0f);
    for (int64_t y = 0; y < H; ++y) {
        float* dst = out + y * W;
        const int64_t k0 = std::max<int64_t>(0, r - y), k1 = std::min<int64_t>(K, H - y + r);
        for (int64_t k = k0; k < k1; ++k) {
            const float* src = tmp + (y + k - r) * W;
            const float wk = w[k];
            for (int64_t x = 0; x < W; ++x) dst[x] += wk * src[x];
        }
    }
}

// SSIM of planes x, y [B, H, W] (B = images x channels): per-plane mean of the SSIM map into
// plane_mean [B]; with `partials` [3, B, H, W] given, also the per-pixel partial derivatives of the
// map w.r.t. (mu_x, E[x^2], E[xy]), which ssim_backward turns into d loss / d x.
void ssim_forward(int64_t B, int64_t H, int64_t W, int64_t K, const float* x, const float* y, const float* w,
                  float c1, float c2, double* plane_mean, float* partials, int64_t num_threads) {
    const int64_t HW = H * W;
    const int64_t workers = std::max<int64_t>(1, std::min(num_threads, B));
    uskern::run_workers(workers, [&](int64_t id) {
        std::vector<float> buf(HW * 7);
        float *tmp = buf.data(), *prod = tmp + HW, *mx = prod + HW, *my = mx + HW, *exx = my + HW,
              *eyy = exx + HW, *exy = eyy + HW;
        for (int64_t b = id; b < B; b += workers) {
            const float* xb = x + b * HW;
            const float* yb = y + b * HW;
            blur_plane(xb, mx, tmp, H, W, w, K);
            blur_plane(yb, my, tmp, H, W, w, K);
            for (int64_t i = 0; i < HW; ++i) prod[i] = xb[i] * xb[i];
            blur_plane(prod, exx, tmp, H, W, w, K);
            for (int64_t i = 0; i < HW; ++i) prod[i] = yb[i] * yb[i];
            blur_plane(prod, eyy, tmp, H, W, w, K);
            for (int64_t i = 0; i < HW; ++i) prod[i] = xb[i] * yb[i];
            blur_plane(prod, exy, tmp, H, W, w, K);
            float* dmu = partials ? partials + b * HW : nullptr;
            float* dxx = partials ? partials + (B + b) * HW : nullptr;
            float* dxy = partials ? partials + (2 * B + b) * HW : nullptr;
            double total = 0.0;
            for (int64_t lo = 0; lo < HW; lo += BLOCK) {
                const int64_t hi = std::min(HW, lo + BLOCK);
                double sum = 0.0;
#pragma omp simd reduction(+ : sum)
                for (int64_t i = lo; i < hi; ++i) {
                    const float ux = mx[i], uy = my[i];
                    const float sxx = exx[i] - ux * ux, syy = eyy[i] - uy * uy, sxy = exy[i] - ux * uy;
                    const float a1 = 2.0f * ux * uy + c1, a2 = 2.0f * sxy + c2;
                    const float b1 = ux * ux + uy * uy + c1, b2 = sxx + syy + c2;
                    // Divide only by b1 b2 >= c1 c2 > 0: a2 = 2 sxy + c2 can be 0 (anti-correlated windows)
                    const float inv_d = 1.0f / (b1 * b2);
                    const float s = a1 * a2 * inv_d;
                    sum += s;
                    if (partials != nullptr) {
                        dmu[i] = (2.0f * uy * (a2 - a1) - 2.0f * ux * s * (b2 - b1)) * inv_d;
                        dxx[i] = -s * b1 * inv_d;
                        dxy[i] = 2.0f * a1 * inv_d;
                    }
                }
                total += sum;
            }
            plane_mean[b] = total / static_cast<double>(HW);
        }
    });
}

// d loss / d x for loss = sum_b g_plane[b] * plane_mean[b]:
// g_plane[b] / HW * (blur(d_mu) + 2 x blur(d_exx) + y blur(d_exy)) (the blur is its own adjoint).
void ssim_backward(int64_t B, int64_t H, int64_t W, int64_t K, const float* x, const float* y, const float* w,
                   const float* partials, const float* g_plane, float* g_x, int64_t num_threads) {
    const int64_t HW = H * W;
    const int64_t workers = std::max<int64_t>(1, std::min(num_threads, B));
    uskern::run_workers(workers, [&](int64_t id) {
        std::vector<float> buf(HW * 4);
        float *tmp = buf.data(), *bmu = tmp + HW, *bxx = bmu + HW, *bxy = bxx + HW;
        for (int64_t b = id; b < B; b += workers) {
            blur_plane(partials + b * HW, bmu, tmp, H, W, w, K);
            blur_plane(partials + (B + b) * HW, bxx, tmp, H, W, w, K);
            blur_plane(partials + (2 * B + b) * HW, bxy, tmp, H, W, w, K);
            const float scale = g_plane[b] / static_cast<float>(HW);
            const float* xb = x + b * HW;
            const float* yb = y + b * HW;
            float* gb = g_x + b * HW;
            for (int64_t i = 0; i < HW; ++i) gb[i] = scale * (bmu[i] + 2.0f * xb[i] * bxx[i] + yb[i] * bxy[i]);
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

int us_ssim_forward_f32(int64_t B, int64_t H, int64_t W, int64_t K, const float* x, const float* y, const float* w,
                        double c1, double c2, double* plane_mean, float* partials, int64_t num_threads) {
    ssim_forward(B, H, W, K, x, y, w, static_cast<float>(c1), static_cast<float>(c2), plane_mean, partials,
                 num_threads);
    return 0;
}

int us_ssim_backward_f32(int64_t B, int64_t H, int64_t W, int64_t K, const float* x, const float* y, const float* w,
                         const float* partials, const float* g_plane, float* g_x, int64_t num_threads) {
    ssim_backward(B, H, W, K, x, y, w, partials, g_plane, g_x, num_threads);
    return 0;
}

}  // extern "C"
