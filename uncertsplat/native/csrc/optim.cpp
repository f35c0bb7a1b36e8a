// Adam on selected rows of a row-major tensor (the sparse updates of train/sparse_adam.py).
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

}  // namespace

extern "C" {

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
