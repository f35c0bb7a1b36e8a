// Adam: on selected rows of a row-major tensor (the sparse updates of train/adam.py), and on whole tensors, several
// in one call (the dense step).
//
// Only the listed rows are read or written: parameters, gradients and moments of every other row stay
// untouched, so the cost follows the rows a training view touched, not the model size. The arithmetic is
// torch.optim.Adam's (bias-corrected, eps added to the corrected square root), in float, with the bias
// corrections in double. With `last` given (lazy decay), a row skipped for k steps first has its moments
// multiplied by beta1^k and beta2^k: what k dense steps with zero gradients would have left of them (their
// parameter updates are not replayed).
//
// Two ways to visit the rows, with the same arithmetic: when few rows are listed, each run of consecutive rows
// is one flat span of memory; when many are (a view sees most of a model), one vectorised sweep over the whole
// tensor computes every element and keeps the new value only where its row is listed (a per-element byte
// mask), which costs what a dense step costs instead of a short loop and its scalar tail per run.
//
// Rows are independent, so the result does not depend on the number of threads.

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <vector>

#include "parallel.h"

namespace {

// Constants of one step (bias corrections folded in).
struct AdamStep {
    float c1, b2, c2, step_size, sqrt_bc2, eps;
};

// One element: torch's arithmetic (lerp for the first moment, eps added to the corrected square root).
inline void adam_element(const AdamStep& s, float g, float m0, float v0, float p0, float& m, float& v, float& p) {
    m = m0 + s.c1 * (g - m0);
    v = s.b2 * v0 + s.c2 * g * g;
    p = p0 - s.step_size * m / (std::sqrt(v) / s.sqrt_bc2 + s.eps);
}

// One Adam step on elements [lo, hi), kept only where keep[j] != 0. A plain function with restrict pointers:
// inside a lambda's captures the compiler could not rule out aliasing and did not vectorise the loop.
void masked_sweep(int64_t lo, int64_t hi, float* __restrict param, float* __restrict exp_avg,
                  float* __restrict exp_avg_sq, const float* __restrict grad, const uint8_t* __restrict keep,
                  const AdamStep s) {
#pragma omp simd
    for (int64_t j = lo; j < hi; ++j) {
        const float m0 = exp_avg[j], v0 = exp_avg_sq[j], p0 = param[j];
        float m, v, p;
        adam_element(s, grad[j], m0, v0, p0, m, v, p);
        const bool on = keep[j] != 0;
        exp_avg[j] = on ? m : m0;
        exp_avg_sq[j] = on ? v : v0;
        param[j] = on ? p : p0;
    }
}

// The same step on every element of one span.
void adam_span(int64_t n, float* __restrict param, float* __restrict exp_avg, float* __restrict exp_avg_sq,
               const float* __restrict grad, const AdamStep s) {
#pragma omp simd
    for (int64_t j = 0; j < n; ++j) adam_element(s, grad[j], exp_avg[j], exp_avg_sq[j], param[j], exp_avg[j],
                                                 exp_avg_sq[j], param[j]);
}

// The dense step with the arithmetic of torch 2.13's fused CPU Adam on one thread (as training calls it), so that
// the default optimiser's result is the one it replaced to the last bit (training runs stay reproducible across the
// change; `tests/unit/test_adam.py` compares the two): float operations in its order with its float-rounded
// constants, the two moments' updates as its fused multiply-adds (the first moment as lerp(m, g, 1 - beta1)) and
// nothing else fused; past its last full vector (a tensor's last n % width elements, `vector_end` on) its scalar
// loop fuses the second moment's update differently. Elements [lo, hi) of a tensor. (Found by comparing the bits
// with torch's results; a torch that computes otherwise gives results one rounding apart.)
struct TorchAdamStep {
    float c1, beta2, c2, step_size, bc2_sqrt, eps;
};

#if !defined(__clang__)
#pragma GCC push_options
#pragma GCC optimize("fp-contract=off")
#endif
inline void torch_adam_vector(int64_t lo, int64_t hi, float* __restrict param, float* __restrict exp_avg,
                              float* __restrict exp_avg_sq, const float* __restrict grad, const TorchAdamStep& s) {
#if defined(__clang__)
#pragma clang fp contract(off)
#endif
#pragma omp simd
    for (int64_t j = lo; j < hi; ++j) {
        const float g = grad[j], m0 = exp_avg[j];
        const float m = std::fma(s.c1, g - m0, m0);
        const float v = std::fma(g, g * s.c2, exp_avg_sq[j] * s.beta2);
        exp_avg[j] = m;
        exp_avg_sq[j] = v;
        const float denom = std::sqrt(v) / s.bc2_sqrt + s.eps;
        param[j] = param[j] - s.step_size * m / denom;
    }
}

// Whether the gradient and both moments of elements [j, j + n) are all zero (either sign): then Adam leaves every
// one of them, and the parameter, as it is (m = lerp(0, 0) = 0, v = 0, the step 0 / eps = 0; with eps = 0 torch
// would write 0 / 0 = NaN there, which no caller asks for: the optimiser's eps is 1e-15).
inline bool inert(const float* __restrict g, const float* __restrict m, const float* __restrict v, int64_t n) {
    uint32_t acc = 0;
#pragma omp simd reduction(| : acc)
    for (int64_t k = 0; k < n; ++k) {
        uint32_t a, b, c;
        std::memcpy(&a, g + k, 4);
        std::memcpy(&b, m + k, 4);
        std::memcpy(&c, v + k, 4);
        acc |= (a | b | c) & 0x7fffffffu;
    }
    return acc == 0;
}

void torch_adam_span(int64_t lo, int64_t hi, int64_t vector_end, float* __restrict param, float* __restrict exp_avg,
                     float* __restrict exp_avg_sq, const float* __restrict grad, const TorchAdamStep s) {
#if defined(__clang__)
#pragma clang fp contract(off)
#endif
    // Cache lines whose gradient and moments are all zero are skipped, their parameters not even read: SH bands not
    // switched on yet (sh_degree_interval) are three quarters of a model's numbers, and rows of zeros were most of
    // the optimiser's memory traffic in the first thousands of steps. The rest is computed as torch computes it.
    constexpr int64_t LINE = 16;
    const int64_t mid = std::min(hi, std::max(lo, vector_end));
    int64_t j = std::min(mid, (lo + LINE - 1) / LINE * LINE);
    torch_adam_vector(lo, j, param, exp_avg, exp_avg_sq, grad, s);
    for (; j + LINE <= mid; j += LINE) {
        if (!inert(grad + j, exp_avg + j, exp_avg_sq + j, LINE))
            torch_adam_vector(j, j + LINE, param, exp_avg, exp_avg_sq, grad, s);
    }
    torch_adam_vector(j, mid, param, exp_avg, exp_avg_sq, grad, s);
    for (j = mid; j < hi; ++j) {  // its scalar loop: the second moment fused the other way round
        const float g = grad[j], m0 = exp_avg[j];
        const float m = std::fma(s.c1, g - m0, m0);
        const float v = std::fma(exp_avg_sq[j], s.beta2, g * (g * s.c2));
        exp_avg[j] = m;
        exp_avg_sq[j] = v;
        const float denom = std::sqrt(v) / s.bc2_sqrt + s.eps;
        param[j] = param[j] - s.step_size * m / denom;
    }
}
#if !defined(__clang__)
#pragma GCC pop_options
#endif

// Whether every element of [lo, hi) is finite: NaN and Inf times 0 are NaN, which a sum keeps (no overflow, unlike
// a sum of the values themselves).
bool all_finite(int64_t lo, int64_t hi, const float* __restrict g) {
    float acc = 0.0f;
#pragma omp simd reduction(+ : acc)
    for (int64_t j = lo; j < hi; ++j) acc += g[j] * 0.0f;
    return acc == 0.0f;
}

// Runs fn(tensor, lo, hi) over the part of the tensors' concatenated elements that worker `id` of `workers` owns
// (contiguous ranges of about equal length: one step's work is split by elements, not by tensors, whose sizes differ
// by 45x between a Gaussian's opacity and its SH coefficients).
template <typename Fn>
void for_worker_range(int64_t count, const int64_t* sizes, int64_t total, int64_t id, int64_t workers, Fn fn) {
    const int64_t lo = total * id / workers, hi = total * (id + 1) / workers;
    int64_t start = 0;
    for (int64_t t = 0; t < count && start < hi; start += sizes[t], ++t) {
        const int64_t a = std::max(lo, start), b = std::min(hi, start + sizes[t]);
        if (a < b) fn(t, a - start, b - start);
    }
}

}  // namespace

extern "C" {

// One dense Adam step on `count` tensors at once (every element; the optimiser's groups, one tensor each), each
// with its own learning rate and step number (its bias correction): one call per training step instead of one
// kernel per tensor and the Python around each, on `num_threads` threads splitting the elements evenly, with
// torch's fused Adam's arithmetic (torch_adam_span; `vector_width`: the floats in one of torch's CPU vectors). With
// `check_finite`, every gradient is first checked and nothing is updated when one holds a NaN or Inf (returns 1;
// Adam would spread it into every parameter); returns 0 after the update. Denormals are kept, as torch keeps them
// (flushing them changed a quaternion of the tiny scene at its second step).
int us_adam_multi_f32(int64_t count, const int64_t* sizes, float* const* params, const float* const* grads,
                      float* const* exp_avgs, float* const* exp_avg_sqs, const double* lrs, const int64_t* steps,
                      double beta1, double beta2, double eps, int64_t vector_width, int64_t check_finite,
                      int64_t num_threads) {
    int64_t total = 0;
    for (int64_t t = 0; t < count; ++t) total += sizes[t];
    if (total == 0) return 0;
    const int64_t workers = std::max<int64_t>(1, std::min<int64_t>(num_threads, total / 32768 + 1));
    if (check_finite != 0) {
        std::vector<uint8_t> ok(static_cast<size_t>(workers), 1);
        uskern::run_workers<false>(workers, [&](int64_t id) {
            for_worker_range(count, sizes, total, id, workers, [&](int64_t t, int64_t a, int64_t b) {
                if (!all_finite(a, b, grads[t])) ok[id] = 0;
            });
        });
        for (uint8_t v : ok)
            if (v == 0) return 1;
    }
    std::vector<TorchAdamStep> s(static_cast<size_t>(count));
    for (int64_t t = 0; t < count; ++t) {  // the bias corrections in double, as torch
        const double bc1 = 1.0 - std::pow(beta1, static_cast<double>(steps[t]));
        const double bc2 = 1.0 - std::pow(beta2, static_cast<double>(steps[t]));
        s[t] = TorchAdamStep{static_cast<float>(1.0 - beta1), static_cast<float>(beta2),
                             static_cast<float>(1.0 - beta2), static_cast<float>(lrs[t] / bc1),
                             static_cast<float>(std::sqrt(bc2)), static_cast<float>(eps)};
    }
    const int64_t width = std::max<int64_t>(1, vector_width);
    uskern::run_workers<false>(workers, [&](int64_t id) {
        for_worker_range(count, sizes, total, id, workers, [&](int64_t t, int64_t a, int64_t b) {
            torch_adam_span(a, b, sizes[t] - sizes[t] % width, params[t], exp_avgs[t], exp_avg_sqs[t], grads[t],
                            s[t]);
        });
    });
    return 0;
}

int us_adam_rows_f32(int64_t total_rows, int64_t num_rows, int64_t width, const int64_t* rows, float* param,
                     const float* grad, float* exp_avg, float* exp_avg_sq, int64_t* last, int64_t step, double lr,
                     double beta1, double beta2, double eps, int64_t num_threads) {
    if (num_rows <= 0 || width <= 0) return 0;
    const double bc1 = 1.0 - std::pow(beta1, static_cast<double>(step));
    const double bc2 = 1.0 - std::pow(beta2, static_cast<double>(step));
    const float step_size = static_cast<float>(lr / bc1);
    const AdamStep s{static_cast<float>(1.0 - beta1), static_cast<float>(beta2), static_cast<float>(1.0 - beta2),
                     step_size, static_cast<float>(std::sqrt(bc2)), static_cast<float>(eps)};
    // at least ~16k elements per worker, so small updates stay on one thread
    const int64_t workers =
        std::max<int64_t>(1, std::min<int64_t>(num_threads, (num_rows * width) / 16384 + 1));

    if (last != nullptr) {  // lazy decay first: one pass over the listed rows
        uskern::run_workers(workers, [&](int64_t id) {
            const int64_t lo = num_rows * id / workers, hi = num_rows * (id + 1) / workers;
            for (int64_t i = lo; i < hi; ++i) {
                const int64_t r = rows[i];
                const int64_t skipped = step - 1 - last[r];
                if (skipped > 0) {
                    const float d1 = static_cast<float>(std::pow(beta1, static_cast<double>(skipped)));
                    const float d2 = static_cast<float>(std::pow(beta2, static_cast<double>(skipped)));
                    float* m = exp_avg + r * width;
                    float* v = exp_avg_sq + r * width;
                    for (int64_t j = 0; j < width; ++j) {
                        m[j] *= d1;
                        v[j] *= d2;
                    }
                }
                last[r] = step;
            }
        });
    }

    if (4 * num_rows >= total_rows) {  // many rows: a masked sweep over everything
        std::vector<uint8_t> keep(static_cast<size_t>(total_rows * width), 0);
        for (int64_t i = 0; i < num_rows; ++i) std::memset(keep.data() + rows[i] * width, 1, width);
        const int64_t n = total_rows * width;
        const int64_t sweep_workers = std::max<int64_t>(1, std::min<int64_t>(num_threads, n / 16384 + 1));
        const uint8_t* k = keep.data();
        uskern::run_workers(sweep_workers, [&](int64_t id) {
            const int64_t lo = n * id / sweep_workers, hi = n * (id + 1) / sweep_workers;
            masked_sweep(lo, hi, param, exp_avg, exp_avg_sq, grad, k, s);
        });
        return 0;
    }

    // few rows: each run of consecutive rows is one span
    uskern::run_workers(workers, [&](int64_t id) {
        const int64_t lo = num_rows * id / workers, hi = num_rows * (id + 1) / workers;
        int64_t i = lo;
        while (i < hi) {
            int64_t e = i + 1;
            while (e < hi && rows[e] == rows[e - 1] + 1) ++e;
            const int64_t begin = rows[i] * width, n = (rows[e - 1] + 1) * width - begin;
            adam_span(n, param + begin, exp_avg + begin, exp_avg_sq + begin, grad + begin, s);
            i = e;
        }
    });
    return 0;
}

}  // extern "C"
