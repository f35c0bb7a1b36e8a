// The densification statistics of one training step (strategy/densify.py, Densifier.accumulate): for every Gaussian
// drawn in a view, the length of its screen-space mean's gradient in NDC units, one count, and the largest screen
// radius. One pass over the step's [C, N] arrays instead of a dozen tensor ops; the same bits as those ops (torch's
// norm of two numbers is sqrt(fma(y, y, x * x)), the sum over the views in view order), so densification decides
// exactly as before.

#include <algorithm>
#include <cmath>
#include <cstdint>

extern "C" {

// grad [C, N, 2] (d loss / d screen mean, pixels), radii [C, N] (0: not drawn); sx, sy: the NDC scale of x and y
// (W / 2 x C and H / 2 x C). Adds into grad_sum, count and max_radius [N].
int us_densify_accumulate_f32(int64_t C, int64_t N, const float* grad, const float* radii, double sx, double sy,
                              float* grad_sum, float* count, float* max_radius) {
    const float fx = static_cast<float>(sx), fy = static_cast<float>(sy);
    // (a contraction could only fuse `norm * vis` into the sum, with vis 0 or 1: the same bits)
    for (int64_t n = 0; n < N; ++n) {
        float total = 0.0f, seen = 0.0f, widest = max_radius[n];
        for (int64_t c = 0; c < C; ++c) {
            const float r = radii[c * N + n];
            const float vis = r > 0.0f ? 1.0f : 0.0f;
            const float x = grad[(c * N + n) * 2] * fx, y = grad[(c * N + n) * 2 + 1] * fy;
            total += std::sqrt(std::fma(y, y, x * x)) * vis;
            seen += vis;
            widest = std::max(widest, r * vis);
        }
        grad_sum[n] += total;
        count[n] += seen;
        max_radius[n] = widest;
    }
    return 0;
}

}  // extern "C"
