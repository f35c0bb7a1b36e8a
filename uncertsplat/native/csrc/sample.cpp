// The Gaussians a training step renders when the informed posterior's Gaussians are fitted to its mean
// (gaussians/variational.py, posterior_mean with the table terms kept between steps): means + offset,
// exp(log scales) x factor, sigmoid(opacity logits) x gate, in one pass, and the backward in one pass. Five tensor
// ops and four autograd nodes of every step otherwise (0.5 ms of a bonsai step on a 2-core CPU).
//
// exp and sigmoid are vmath.h's (within a few ulp of torch's): the render differs from the tensor ops' in the
// last bits only.

#include <cstdint>

#include "vmath.h"

namespace {

using uskern::vexp;
using uskern::vsigmoid;

}  // namespace

extern "C" {

// means, offset [N, 3]; scales (log), factor [N, 3]; opacities (logits), gate [N] -> out_means, out_scales [N, 3],
// out_opacities [N].
int us_mean_sample_forward_f32(int64_t n, const float* means, const float* offset, const float* scales,
                               const float* factor, const float* opacities, const float* gate, float* out_means,
                               float* out_scales, float* out_opacities) {
#pragma omp simd
    for (int64_t i = 0; i < 3 * n; ++i) {
        out_means[i] = means[i] + offset[i];
        out_scales[i] = vexp(scales[i]) * factor[i];
    }
#pragma omp simd
    for (int64_t i = 0; i < n; ++i) out_opacities[i] = vsigmoid(opacities[i]) * gate[i];
    return 0;
}

// d loss / d (log scales, opacity logits) from d loss / d (out_scales, out_opacities) (either may be null: 0);
// out_scales is the forward's (its own derivative w.r.t. the log scale). The means' gradient is the output's.
int us_mean_sample_backward_f32(int64_t n, const float* out_scales, const float* opacities, const float* gate,
                                const float* g_scales, const float* g_opacities, float* d_scales,
                                float* d_opacities) {
    if (g_scales != nullptr) {
#pragma omp simd
        for (int64_t i = 0; i < 3 * n; ++i) d_scales[i] = g_scales[i] * out_scales[i];
    } else {
        for (int64_t i = 0; i < 3 * n; ++i) d_scales[i] = 0.0f;
    }
    if (g_opacities != nullptr) {
#pragma omp simd
        for (int64_t i = 0; i < n; ++i) {
            const float s = vsigmoid(opacities[i]);
            d_opacities[i] = g_opacities[i] * gate[i] * (s * (1.0f - s));
        }
    } else {
        for (int64_t i = 0; i < n; ++i) d_opacities[i] = 0.0f;
    }
    return 0;
}

}  // extern "C"
