// The view-consistency term's lookups (uncertainty/consistency.py, ViewConsistency): every surface point of an
// evaluated view projected into every compared training view, tested for being seen there (its depth against the
// view's rendered depth, sampled bilinearly), and the seeing view at the smallest angle to the evaluated view's
// direction chosen. The PyTorch path does it in about 40 tensor ops per block of points and chunk of views, each
// writing a [views, points] array; here one pass per point keeps its running best in registers (a 1280x960 view
// against 35 views: 42M point-view pairs), reading the renders as they are kept (float16 colours, float32 depths: no
// float32 copy of every view). The same arithmetic as the PyTorch path in the same order (projection,
// grid_sample's bilinear weights with border padding and align_corners=False, the tolerance test), except that the
// nearest view is found by the largest cosine and only its angle is taken (acos is decreasing: the same view but
// where two cosines differ by less than acos can tell apart).

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>

#include "parallel.h"

namespace {

constexpr int64_t kBlock = 64;  // points looked up together: one view's texels stay in cache across them
constexpr float kDepthTolerance = 0.03f;  // consistency.DEPTH_TOLERANCE (as torch rounds it for a float32 tensor)

struct View {
    float r[9], t[3], k[6], c[3], fx;  // rotation (row-major), translation, K's first two rows, centre, K[0][0]
};

// grid_sample's source coordinate for a pixel coordinate u in an image of `size` pixels, as torch computes it from
// the normalised grid value u / size * 2 - 1 (align_corners=False), clipped to the border.
inline float source_coord(float u, int64_t size) {
    const float s = static_cast<float>(size);
    const float g = u / s * 2.0f - 1.0f;
    const float x = ((g + 1.0f) * s - 1.0f) / 2.0f;
    return std::min(s - 1.0f, std::max(x, 0.0f));
}

// A float16 number's value (exact: every float16 is a float32).
inline float half_to_float(uint16_t h) {
    const uint32_t sign = static_cast<uint32_t>(h & 0x8000u) << 16;
    uint32_t exponent = (h >> 10) & 0x1fu, mantissa = h & 0x3ffu, bits;
    if (exponent == 0) {
        if (mantissa == 0) {
            bits = sign;
        } else {  // subnormal: normalise it
            exponent = 127 - 15 + 1;
            while (!(mantissa & 0x400u)) mantissa <<= 1, --exponent;
            bits = sign | (exponent << 23) | ((mantissa & 0x3ffu) << 13);
        }
    } else if (exponent == 31) {
        bits = sign | 0x7f800000u | (mantissa << 13);  // inf, NaN
    } else {
        bits = sign | ((exponent + 127 - 15) << 23) | (mantissa << 13);
    }
    float f;
    std::memcpy(&f, &bits, sizeof f);
    return f;
}

inline float load(const float* p) { return *p; }
inline float load(const uint16_t* p) { return half_to_float(*p); }

// Bilinear sample of channel `ch` of one view's [H, W, C] values at source coordinates (x, y) (in the image after
// source_coord's clip; corners outside it weigh nothing, as in grid_sample).
template <typename T>
inline float bilinear(const T* img, int64_t H, int64_t W, int64_t C, float x, float y, int64_t ch) {
    const float x0f = std::floor(x), y0f = std::floor(y);
    const int64_t x0 = static_cast<int64_t>(x0f), y0 = static_cast<int64_t>(y0f);
    const float x1f = x0f + 1.0f, y1f = y0f + 1.0f;
    const float nw = (x1f - x) * (y1f - y), ne = (x - x0f) * (y1f - y);
    const float sw = (x1f - x) * (y - y0f), se = (x - x0f) * (y - y0f);
    const bool x1in = x0 + 1 < W, y1in = y0 + 1 < H;
    float v = load(img + (y0 * W + x0) * C + ch) * nw;
    if (x1in) v += load(img + (y0 * W + x0 + 1) * C + ch) * ne;
    if (y1in) v += load(img + ((y0 + 1) * W + x0) * C + ch) * sw;
    if (x1in && y1in) v += load(img + ((y0 + 1) * W + x0 + 1) * C + ch) * se;
    return v;
}

}  // namespace

extern "C" {

// points [S, 3], colour [S, 3] (the evaluated view's render; null: no difference taken), cam_from_world [T, 4, 4],
// K [T, 3, 3], centers [T, 3], depth [T, H, W] (each compared view's rendered depth), rgb [T, H, W, 3] (its rendered
// colours: float16 when rgb_half, else float32; read only at each point's chosen view), eye: the evaluated
// camera's centre, foot [S] (its pixel footprint at each point; null: no finest ratio). Writes, per point: best_cos
// (the cosine of the nearest seeing view's angle; -2 where none sees it), diff (the mean over the channels of the
// squared difference to that view's render; 0 where none sees it; only with colour), inside_any (1 where some view's
// image holds the point, in front) and finest (the smallest seeing view's footprint z / K[0][0] over foot; inf where
// none sees it; only with foot). Returns -1 for an empty image (H or W 0), which no point lands in.
int us_consistency_lookup_f32(int64_t S, int64_t T, int64_t H, int64_t W, const float* points, const float* colour,
                              const float* cam_from_world, const float* K, const float* centers, const float* depth,
                              const void* rgb, int64_t rgb_half, double eye_x, double eye_y, double eye_z,
                              const float* foot, float* best_cos, float* diff, uint8_t* inside_any, float* finest,
                              int64_t threads) {
    if (H <= 0 || W <= 0) return -1;
    if (S <= 0) return 0;
    View* views = new View[T > 0 ? T : 1];
    for (int64_t t = 0; t < T; ++t) {
        View& v = views[t];
        for (int i = 0; i < 3; ++i) {
            for (int j = 0; j < 3; ++j) v.r[i * 3 + j] = cam_from_world[t * 16 + i * 4 + j];
            v.t[i] = cam_from_world[t * 16 + i * 4 + 3];
            v.c[i] = centers[t * 3 + i];
        }
        for (int i = 0; i < 6; ++i) v.k[i] = K[t * 9 + i];
        v.fx = K[t * 9];
    }
    const float eye[3] = {static_cast<float>(eye_x), static_cast<float>(eye_y), static_cast<float>(eye_z)};
    const float wf = static_cast<float>(W), hf = static_cast<float>(H);
    const float inf = std::numeric_limits<float>::infinity();
    const int64_t workers = std::max<int64_t>(1, std::min<int64_t>(threads, (S + kBlock - 1) / kBlock));
    uskern::run_workers<false>(workers, [&](int64_t id) {
        const int64_t per = (S + workers - 1) / workers;
        const int64_t lo = id * per, hi = std::min(S, lo + per);
        float to_view[kBlock][3], best[kBlock], fine[kBlock];
        int64_t best_t[kBlock];
        float best_x[kBlock], best_y[kBlock];
        bool any[kBlock];
        for (int64_t b0 = lo; b0 < hi; b0 += kBlock) {
            const int64_t n = std::min(kBlock, hi - b0);
            for (int64_t i = 0; i < n; ++i) {
                const float* p = points + (b0 + i) * 3;
                float d[3] = {eye[0] - p[0], eye[1] - p[1], eye[2] - p[2]};
                const float len = std::max(std::sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]), 1e-12f);
                for (int c = 0; c < 3; ++c) to_view[i][c] = d[c] / len;
                best[i] = -2.0f, fine[i] = inf, best_t[i] = -1, best_x[i] = best_y[i] = 0.0f, any[i] = false;
            }
            for (int64_t t = 0; t < T; ++t) {
                const View& v = views[t];
                const float* img = depth + t * H * W;
                for (int64_t i = 0; i < n; ++i) {
                    const float* p = points + (b0 + i) * 3;
                    const float x = p[0] * v.r[0] + p[1] * v.r[1] + p[2] * v.r[2] + v.t[0];
                    const float y = p[0] * v.r[3] + p[1] * v.r[4] + p[2] * v.r[5] + v.t[1];
                    const float z = p[0] * v.r[6] + p[1] * v.r[7] + p[2] * v.r[8] + v.t[2];
                    const float zc = std::max(z, 1e-9f);
                    const float xn = x / zc, yn = y / zc;
                    const float u = xn * v.k[0] + yn * v.k[1] + v.k[2];
                    const float w = xn * v.k[3] + yn * v.k[4] + v.k[5];
                    if (!(z > 1e-9f && u >= 0.0f && u <= wf && w >= 0.0f && w <= hf)) continue;
                    any[i] = true;
                    const float sx = source_coord(u, W), sy = source_coord(w, H);
                    const float there = bilinear(img, H, W, 1, sx, sy, 0);
                    if (!(std::fabs(z - there) <= kDepthTolerance * z)) continue;
                    if (foot != nullptr) fine[i] = std::min(fine[i], (z / v.fx) / foot[b0 + i]);
                    float d[3] = {v.c[0] - p[0], v.c[1] - p[1], v.c[2] - p[2]};
                    const float len = std::max(std::sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]), 1e-12f);
                    const float cos = std::min(1.0f, std::max(-1.0f, (d[0] / len) * to_view[i][0] +
                                                                         (d[1] / len) * to_view[i][1] +
                                                                         (d[2] / len) * to_view[i][2]));
                    if (cos > best[i]) best[i] = cos, best_t[i] = t, best_x[i] = sx, best_y[i] = sy;
                }
            }
            for (int64_t i = 0; i < n; ++i) {
                const int64_t s = b0 + i;
                best_cos[s] = best[i];
                inside_any[s] = any[i] ? 1 : 0;
                if (finest != nullptr) finest[s] = fine[i];
                if (diff == nullptr) continue;
                float sq = 0.0f;
                if (best_t[i] >= 0 && colour != nullptr) {
                    const int64_t at = best_t[i] * H * W * 3;
                    for (int c = 0; c < 3; ++c) {
                        const float there =
                            rgb_half ? bilinear(static_cast<const uint16_t*>(rgb) + at, H, W, 3, best_x[i], best_y[i], c)
                                     : bilinear(static_cast<const float*>(rgb) + at, H, W, 3, best_x[i], best_y[i], c);
                        const float e = colour[s * 3 + c] - there;
                        sq += e * e;
                    }
                    sq /= 3.0f;
                }
                diff[s] = sq;
            }
        }
    });
    delete[] views;
    return 0;
}

}  // extern "C"
