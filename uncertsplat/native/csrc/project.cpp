// Per-Gaussian front end of the rasterizer, forward and backward: SH colours seen from each camera
// (uncertsplat/render/sh.py) and the EWA projection (uncertsplat/render/project.py, the reference; see
// its docstring for the model). The PyTorch versions are the reference and the path on other devices;
// these replace dozens of elementwise tensor ops (and their autograd graph) by one pass per Gaussian. The
// projection and its gradient run on LANES Gaussians at a time (one SIMD register of floats per value).
//
// Layouts (row-major, float32): means [N,3], quats [N,4] wxyz, scales [N,3], opacities [N], sh [N,B,3],
// cam_from_world [C,4,4], K [C,3,3], centres [C,3]; per camera outputs [C,N,...].

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

#include "parallel.h"
#include "vmath.h"

namespace {

// SH colours and the projection are written once for T = float (one Gaussian) or a vector of LANES floats
// (LANES Gaussians at once, what the kernels run). Comparisons give bool or a lane mask, and `m ? a : b`
// selects per lane for both; these helpers cover the rest.
using uskern::LANES;
using VF = uskern::floatv;

inline float vsqrt(float x) { return std::sqrt(x); }
inline VF vsqrt(VF x) {
    for (int l = 0; l < LANES; ++l) x[l] = std::sqrt(x[l]);  // one vector sqrt (-fno-math-errno)
    return x;
}
template <typename T>
inline T vmax(T a, T b) {
    return a > b ? a : b;
}
template <typename T>
inline T vmin(T a, T b) {
    return a < b ? a : b;
}
// b where m else a, for a mask or a bool m (GCC vectors: a lane mask; scalars: a bool)
template <typename T, typename Mask>
inline T select(Mask m, T a, T b) {
    return m ? b : a;
}

// A float as a T.
template <typename T>
inline T bc(float v) {
    return T{} + v;
}

constexpr float SH_C0 = 0.28209479177387814f;
constexpr float SH_C1 = 0.4886025119029199f;
constexpr float SH_C2[5] = {1.0925484305920792f, -1.0925484305920792f, 0.31539156525252005f, -1.0925484305920792f,
                            0.5462742152960396f};
constexpr float SH_C3[7] = {-0.5900435899266435f, 2.890611442640554f, -0.4570457994644658f, 0.3731763325901154f,
                            -0.4570457994644658f, 1.445305721320277f, -0.5900435899266435f};

// Basis values Y[0..nb) at the unit direction (x, y, z) and, when dY is given, their partial
// derivatives w.r.t. x, y, z (dY[b][0..3)), treating the components as independent.
template <typename T>
inline void sh_basis(int degree, T x, T y, T z, T* Y, T (*dY)[3]) {
    Y[0] = bc<T>(SH_C0);
    if (dY) dY[0][0] = dY[0][1] = dY[0][2] = T{};
    if (degree < 1) return;
    Y[1] = -SH_C1 * y;
    Y[2] = SH_C1 * z;
    Y[3] = -SH_C1 * x;
    if (dY) {
        dY[1][0] = T{}; dY[1][1] = bc<T>(-SH_C1); dY[1][2] = T{};
        dY[2][0] = T{}; dY[2][1] = T{}; dY[2][2] = bc<T>(SH_C1);
        dY[3][0] = bc<T>(-SH_C1); dY[3][1] = T{}; dY[3][2] = T{};
    }
    if (degree < 2) return;
    const T xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
    Y[4] = SH_C2[0] * xy;
    Y[5] = SH_C2[1] * yz;
    Y[6] = SH_C2[2] * (2.0f * zz - xx - yy);
    Y[7] = SH_C2[3] * xz;
    Y[8] = SH_C2[4] * (xx - yy);
    if (dY) {
        dY[4][0] = SH_C2[0] * y; dY[4][1] = SH_C2[0] * x; dY[4][2] = T{};
        dY[5][0] = T{}; dY[5][1] = SH_C2[1] * z; dY[5][2] = SH_C2[1] * y;
        dY[6][0] = -2.0f * SH_C2[2] * x; dY[6][1] = -2.0f * SH_C2[2] * y; dY[6][2] = 4.0f * SH_C2[2] * z;
        dY[7][0] = SH_C2[3] * z; dY[7][1] = T{}; dY[7][2] = SH_C2[3] * x;
        dY[8][0] = 2.0f * SH_C2[4] * x; dY[8][1] = -2.0f * SH_C2[4] * y; dY[8][2] = T{};
    }
    if (degree < 3) return;
    Y[9] = SH_C3[0] * y * (3.0f * xx - yy);
    Y[10] = SH_C3[1] * xy * z;
    Y[11] = SH_C3[2] * y * (4.0f * zz - xx - yy);
    Y[12] = SH_C3[3] * z * (2.0f * zz - 3.0f * xx - 3.0f * yy);
    Y[13] = SH_C3[4] * x * (4.0f * zz - xx - yy);
    Y[14] = SH_C3[5] * z * (xx - yy);
    Y[15] = SH_C3[6] * x * (xx - 3.0f * yy);
    if (dY) {
        dY[9][0] = SH_C3[0] * 6.0f * xy; dY[9][1] = SH_C3[0] * (3.0f * xx - 3.0f * yy); dY[9][2] = T{};
        dY[10][0] = SH_C3[1] * yz; dY[10][1] = SH_C3[1] * xz; dY[10][2] = SH_C3[1] * xy;
        dY[11][0] = SH_C3[2] * -2.0f * xy; dY[11][1] = SH_C3[2] * (4.0f * zz - xx - 3.0f * yy);
        dY[11][2] = SH_C3[2] * 8.0f * yz;
        dY[12][0] = SH_C3[3] * -6.0f * xz; dY[12][1] = SH_C3[3] * -6.0f * yz;
        dY[12][2] = SH_C3[3] * (6.0f * zz - 3.0f * xx - 3.0f * yy);
        dY[13][0] = SH_C3[4] * (4.0f * zz - 3.0f * xx - yy); dY[13][1] = SH_C3[4] * -2.0f * xy;
        dY[13][2] = SH_C3[4] * 8.0f * xz;
        dY[14][0] = SH_C3[5] * 2.0f * xz; dY[14][1] = SH_C3[5] * -2.0f * yz; dY[14][2] = SH_C3[5] * (xx - yy);
        dY[15][0] = SH_C3[6] * (3.0f * xx - 3.0f * yy); dY[15][1] = SH_C3[6] * -6.0f * xy; dY[15][2] = T{};
    }
}

// Unit direction from the camera centre to the mean; the norm is clamped at 1e-12 as in sh.py.
template <typename T>
inline T view_dir(const T* mean, const float* centre, T* d) {
    const T vx = mean[0] - centre[0], vy = mean[1] - centre[1], vz = mean[2] - centre[2];
    const T n = vmax<T>(vsqrt(vx * vx + vy * vy + vz * vz), bc<T>(1e-12f));
    d[0] = vx / n;
    d[1] = vy / n;
    d[2] = vz / n;
    return n;
}

// The means [3] and coefficients [nb * 3] of LANES Gaussians n0 .. (lanes past N repeat the last one).
// The coefficients of Gaussian n: the DC at dc + n * dc_stride (3 floats), bases 1.. at rest + n * rest_stride (3 each).
// One [N,B,3] array: dc = sh, rest = sh + 3, both strides B * 3; the parameter table's two arrays sh0 [N,1,3] and
// shN [N,B-1,3]: strides 3 and (B - 1) * 3 (no concatenated copy of them per step).
struct ShLayout {
    const float* dc;
    int64_t dc_stride;
    const float* rest;
    int64_t rest_stride;
};

struct ShGradLayout {
    float* dc;
    int64_t dc_stride;
    float* rest;
    int64_t rest_stride;
};

inline void load_sh_lanes(int64_t n0, int64_t N, int nb, const ShLayout& sh, const float* means, VF* m, VF* s) {
    // coefficient-major, lanes inner: each vector is one gather (lane l reads Gaussian n0 + l, the last one repeated
    // past N) instead of LANES scalar stores that the vector load after them must wait for
    int32_t n[LANES];
    for (int l = 0; l < LANES; ++l) n[l] = static_cast<int32_t>(std::min<int64_t>(n0 + l, N - 1));
    for (int i = 0; i < 3; ++i)
        for (int l = 0; l < LANES; ++l) m[i][l] = means[3 * static_cast<int64_t>(n[l]) + i];
    for (int i = 0; i < 3; ++i)
        for (int l = 0; l < LANES; ++l) s[i][l] = sh.dc[n[l] * sh.dc_stride + i];
    for (int i = 3; i < nb * 3; ++i)
        for (int l = 0; l < LANES; ++l) s[i][l] = sh.rest[n[l] * sh.rest_stride + i - 3];
}

void sh_forward(int64_t C, int64_t N, int64_t B, int degree, const ShLayout& sh, const float* means,
                const float* centres, float* out, int64_t num_threads) {
    const int nb = (degree + 1) * (degree + 1);
    const int64_t blocks = (N + LANES - 1) / LANES;
    const int64_t workers = std::max<int64_t>(1, std::min<int64_t>(num_threads, N / 2048 + 1));
    uskern::run_workers(workers, [&](int64_t w) {
        VF m[3], s[48], Y[16], d[3] = {};
        for (int64_t blk = blocks * w / workers; blk < blocks * (w + 1) / workers; ++blk) {
            const int64_t n0 = blk * LANES;
            load_sh_lanes(n0, N, nb, sh, means, m, s);
            for (int64_t c = 0; c < C; ++c) {
                if (degree > 0) view_dir<VF>(m, centres + 3 * c, d);
                sh_basis<VF>(degree, d[0], d[1], d[2], Y, nullptr);
                VF v[3];
                for (int k = 0; k < 3; ++k) {
                    v[k] = bc<VF>(0.5f);
                    for (int b = 0; b < nb; ++b) v[k] += Y[b] * s[b * 3 + k];
                    v[k] = vmax<VF>(v[k], VF{});
                }
                for (int l = 0; l < LANES && n0 + l < N; ++l)
                    for (int k = 0; k < 3; ++k) out[(c * N + n0 + l) * 3 + k] = v[k][l];
            }
        }
    });
}

// g_sh [N,B,3] and g_means [N,3] are overwritten (bases above the degree get 0). A (camera, Gaussian)
// whose incoming gradient is 0 contributes nothing.
void sh_backward(int64_t C, int64_t N, int64_t B, int degree, const ShLayout& sh, const float* means,
                 const float* centres, const float* g_out, const ShGradLayout& g_sh, float* g_means,
                 int64_t num_threads) {
    const int nb = (degree + 1) * (degree + 1);
    const int64_t blocks = (N + LANES - 1) / LANES;
    const int64_t workers = std::max<int64_t>(1, std::min<int64_t>(num_threads, N / 2048 + 1));
    uskern::run_workers(workers, [&](int64_t w) {
        VF m[3], s[48], Y[16], dY[16][3], d[3] = {};
        for (int64_t blk = blocks * w / workers; blk < blocks * (w + 1) / workers; ++blk) {
            const int64_t n0 = blk * LANES;
            load_sh_lanes(n0, N, nb, sh, means, m, s);
            VF gs[48] = {}, gm[3] = {};
            for (int64_t c = 0; c < C; ++c) {
                VF g[3] = {};
                for (int l = 0; l < LANES && n0 + l < N; ++l)
                    for (int k = 0; k < 3; ++k) g[k][l] = g_out[(c * N + n0 + l) * 3 + k];
                const auto act = (g[0] != 0) | (g[1] != 0) | (g[2] != 0);
                VF norm = bc<VF>(1.0f);
                if (degree > 0) norm = view_dir<VF>(m, centres + 3 * c, d);
                sh_basis<VF>(degree, d[0], d[1], d[2], Y, degree > 0 ? dY : nullptr);
                VF gk[3];
                for (int k = 0; k < 3; ++k) {  // the clamp at 0 passes the gradient where the value is >= 0
                    VF v = bc<VF>(0.5f);
                    for (int b = 0; b < nb; ++b) v += Y[b] * s[b * 3 + k];
                    gk[k] = select(act & (v >= 0.0f), VF{}, g[k]);
                }
                VF gd[3] = {};
                for (int b = 0; b < nb; ++b) {
                    VF dv{};  // d loss / d Y_b
                    for (int k = 0; k < 3; ++k) {
                        gs[b * 3 + k] += select(act, VF{}, gk[k] * Y[b]);  // 0 * NaN stays out
                        dv += gk[k] * s[b * 3 + k];
                    }
                    if (degree > 0)
                        for (int i = 0; i < 3; ++i) gd[i] += dv * dY[b][i];
                }
                if (degree > 0) {  // through d = v / |v|: (gd - d (d . gd)) / |v|
                    const VF dot = gd[0] * d[0] + gd[1] * d[1] + gd[2] * d[2];
                    for (int i = 0; i < 3; ++i) gm[i] += select(act, VF{}, (gd[i] - d[i] * dot) / norm);
                }
            }
            for (int l = 0; l < LANES && n0 + l < N; ++l) {
                const int64_t n = n0 + l;
                float* gdc = g_sh.dc + n * g_sh.dc_stride;
                for (int i = 0; i < 3; ++i) gdc[i] = gs[i][l];
                if (g_sh.rest != nullptr) {  // null: no gradient of the higher bands asked for (degree 0)
                    float* grest = g_sh.rest + n * g_sh.rest_stride;
                    for (int i = 3; i < nb * 3; ++i) grest[i - 3] = gs[i][l];
                    std::fill(grest + std::max(nb - 1, 0) * 3, grest + (B - 1) * 3, 0.0f);
                }
                for (int i = 0; i < 3; ++i) g_means[3 * n + i] = gm[i][l];
            }
        }
    });
}


// ------------------------------------------------------------------------------------- projection
// A camera as the kernels read it, in float (projection) or double (the peak factor, as its reference).
template <typename S>
struct CameraT {
    S R[9], t[3], fx, fy, cx, cy, lo_u, hi_u, lo_v, hi_v;
};
using Camera = CameraT<float>;

template <typename S>
inline CameraT<S> load_camera(const float* cam, const float* K, int64_t W, int64_t H) {
    CameraT<S> c;
    for (int i = 0; i < 3; ++i) {
        for (int j = 0; j < 3; ++j) c.R[3 * i + j] = cam[4 * i + j];
        c.t[i] = cam[4 * i + 3];
    }
    c.fx = K[0];
    c.fy = K[4];
    c.cx = K[2];
    c.cy = K[5];
    // the view angle at which the Jacobian is evaluated is clamped to 1.3x the field of view (3DGS)
    c.hi_u = (static_cast<S>(W) - c.cx) / c.fx + S(0.15) * static_cast<S>(W) / c.fx;
    c.lo_u = -c.cx / c.fx - S(0.15) * static_cast<S>(W) / c.fx;
    c.hi_v = (static_cast<S>(H) - c.cy) / c.fy + S(0.15) * static_cast<S>(H) / c.fy;
    c.lo_v = -c.cy / c.fy - S(0.15) * static_cast<S>(H) / c.fy;
    return c;
}

// Rotation matrix (row-major) of the normalised quaternion q (wxyz); qn receives the unit quaternion and
// the norm is clamped at 1e-12 as in project.py.
template <typename T>
inline void quat_rotmat(const T* q, T* qn, T* Rq) {
    const T n = vmax<T>(vsqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]), T{} + 1e-12f);
    for (int i = 0; i < 4; ++i) qn[i] = q[i] / n;
    const T w = qn[0], x = qn[1], y = qn[2], z = qn[3];
    Rq[0] = 1 - 2 * (y * y + z * z); Rq[1] = 2 * (x * y - w * z); Rq[2] = 2 * (x * z + w * y);
    Rq[3] = 2 * (x * y + w * z); Rq[4] = 1 - 2 * (x * x + z * z); Rq[5] = 2 * (y * z - w * x);
    Rq[6] = 2 * (x * z - w * y); Rq[7] = 2 * (y * z + w * x); Rq[8] = 1 - 2 * (x * x + y * y);
}

// Everything the forward computes for one (camera, Gaussian), or LANES of them; backward recomputes it.
template <typename T>
struct Proj {
    using Mask = decltype(T{} < T{});
    T p[3], zs, u, v, uc, vc;
    Mask in_depth;
    T J[6], RM[9], A[6], qn[4], Rq[9];
    T m2[2], conic[3], s;  // s: the normalisation of A, also the scale of the 2D covariance
    T a, b, c;             // normalised covariance entries (covariance = s [[a, b], [b, c]])
};

template <typename T>
inline void project_one(const Camera& cam, const T* x, const T* q, const T* sc, float near, float far, float eps2d,
                        Proj<T>& r) {
    for (int i = 0; i < 3; ++i)
        r.p[i] = cam.R[3 * i] * x[0] + cam.R[3 * i + 1] * x[1] + cam.R[3 * i + 2] * x[2] + cam.t[i];
    const T z = r.p[2];
    r.in_depth = (z > near) & (z < far);
    r.zs = select(r.in_depth, T{} + 1.0f, z);  // culled Gaussians get a harmless z
    r.u = r.p[0] / r.zs;
    r.v = r.p[1] / r.zs;
    r.m2[0] = cam.fx * r.u + cam.cx;
    r.m2[1] = cam.fy * r.v + cam.cy;
    r.uc = vmax<T>(vmin<T>(r.u, T{} + cam.hi_u), T{} + cam.lo_u);
    r.vc = vmax<T>(vmin<T>(r.v, T{} + cam.hi_v), T{} + cam.lo_v);
    r.J[0] = cam.fx / r.zs; r.J[1] = T{}; r.J[2] = -cam.fx * r.uc / r.zs;
    r.J[3] = T{}; r.J[4] = cam.fy / r.zs; r.J[5] = -cam.fy * r.vc / r.zs;
    quat_rotmat<T>(q, r.qn, r.Rq);
    T M[9];
    for (int i = 0; i < 3; ++i)
        for (int k = 0; k < 3; ++k) M[3 * i + k] = r.Rq[3 * i + k] * sc[k];
    for (int i = 0; i < 3; ++i)
        for (int k = 0; k < 3; ++k)
            r.RM[3 * i + k] = cam.R[3 * i] * M[k] + cam.R[3 * i + 1] * M[3 + k] + cam.R[3 * i + 2] * M[6 + k];
    for (int i = 0; i < 2; ++i)
        for (int k = 0; k < 3; ++k)
            r.A[3 * i + k] = r.J[3 * i] * r.RM[k] + r.J[3 * i + 1] * r.RM[3 + k] + r.J[3 * i + 2] * r.RM[6 + k];
    // Covariance A A^T + eps I, normalised by its overall size s (no overflow for huge Gaussians), with
    // the determinant from the Lagrange identity (no cancellation for needles), as in project.py.
    T ss = T{} + eps2d;
    for (int i = 0; i < 6; ++i) ss += r.A[i] * r.A[i];
    r.s = ss;
    const T inv = 1.0f / vsqrt(ss), e = eps2d / ss;
    T a1[3], a2[3];
    for (int k = 0; k < 3; ++k) {
        a1[k] = r.A[k] * inv;
        a2[k] = r.A[3 + k] * inv;
    }
    r.a = a1[0] * a1[0] + a1[1] * a1[1] + a1[2] * a1[2] + e;
    r.c = a2[0] * a2[0] + a2[1] * a2[1] + a2[2] * a2[2] + e;
    r.b = a1[0] * a2[0] + a1[1] * a2[1] + a1[2] * a2[2];
    const T cx = a1[1] * a2[2] - a1[2] * a2[1], cy = a1[2] * a2[0] - a1[0] * a2[2], cz = a1[0] * a2[1] - a1[1] * a2[0];
    const T det = cx * cx + cy * cy + cz * cz + e * (r.a + r.c - 2 * e) + e * e;
    const T denom = vmax<T>(det * ss, T{} + 1.17549435e-38f);
    r.conic[0] = r.c / denom;
    r.conic[1] = -r.b / denom;
    r.conic[2] = r.a / denom;
}

// LANES Gaussians n0 .. n0 + LANES - 1 of camera c (lanes past N repeat the last Gaussian and are not
// stored): the projection and the opacity-aware footprint.
void project_lanes(const Camera& cam, int64_t c, int64_t n0, int64_t N, const float* means, const float* quats,
                   const float* scales, const float* opac, int64_t W, int64_t H, float near, float far, float eps2d,
                   float alpha_min, float* means2d, float* conics, float* depths, float* extents, uint8_t* valid) {
    VF x[3], q[4], sc[3], o;
    for (int l = 0; l < LANES; ++l) {
        const int64_t n = std::min<int64_t>(n0 + l, N - 1);
        for (int i = 0; i < 3; ++i) x[i][l] = means[3 * n + i], sc[i][l] = scales[3 * n + i];
        for (int i = 0; i < 4; ++i) q[i][l] = quats[4 * n + i];
        o[l] = opac[n];
    }
    Proj<VF> r;
    project_one<VF>(cam, x, q, sc, near, far, eps2d, r);
    // opacity-aware footprint: o exp(-q/2) >= alpha_min <=> q <= 2 ln(o / alpha_min)
    VF thr = vmax<VF>(o / alpha_min, VF{} + 1.0f);
    for (int l = 0; l < LANES; ++l) thr[l] = 2.0f * std::log(thr[l]);
    const VF ex = vsqrt(thr * r.a * r.s) * 1.001f + 1e-3f;
    const VF ey = vsqrt(thr * r.c * r.s) * 1.001f + 1e-3f;
    for (int l = 0; l < LANES && n0 + l < N; ++l) {
        const int64_t cn = c * N + n0 + l;
        means2d[2 * cn] = r.m2[0][l];
        means2d[2 * cn + 1] = r.m2[1][l];
        for (int i = 0; i < 3; ++i) conics[3 * cn + i] = r.conic[i][l];
        depths[cn] = r.p[2][l];
        bool ok = r.in_depth[l] && o[l] >= alpha_min && std::isfinite(ex[l]) && std::isfinite(ey[l]);
        ok = ok && r.m2[0][l] + ex[l] > 0.5f && r.m2[0][l] - ex[l] < static_cast<float>(W) - 0.5f;
        ok = ok && r.m2[1][l] + ey[l] > 0.5f && r.m2[1][l] - ey[l] < static_cast<float>(H) - 0.5f;
        valid[cn] = ok ? 1 : 0;
        extents[2 * cn] = ok ? ex[l] : 0.0f;
        extents[2 * cn + 1] = ok ? ey[l] : 0.0f;
    }
}

void project_forward(int64_t C, int64_t N, const float* means, const float* quats, const float* scales,
                     const float* opac, const float* cams, const float* Ks, int64_t W, int64_t H, float near,
                     float far, float eps2d, float alpha_min, float* means2d, float* conics, float* depths,
                     float* extents, uint8_t* valid, int64_t num_threads) {
    const int64_t blocks = (N + LANES - 1) / LANES;
    const int64_t workers = std::max<int64_t>(1, std::min<int64_t>(num_threads, N / 2048 + 1));
    uskern::run_workers(workers, [&](int64_t w) {
        for (int64_t c = 0; c < C; ++c) {
            const Camera cam = load_camera<float>(cams + 16 * c, Ks + 9 * c, W, H);
            for (int64_t blk = blocks * w / workers; blk < blocks * (w + 1) / workers; ++blk)
                project_lanes(cam, c, blk * LANES, N, means, quats, scales, opac, W, H, near, far, eps2d, alpha_min,
                              means2d, conics, depths, extents, valid);
        }
    });
}

inline bool any_lane(bool m) { return m; }
inline bool any_lane(decltype(VF{} < VF{}) m) {
    for (int l = 0; l < LANES; ++l)
        if (m[l]) return true;
    return false;
}

// Gradients of LANES Gaussians n0 .. n0 + LANES - 1 (lanes past N get no gradient and are not stored) w.r.t.
// means, quats and scales from those of means2d [C,N,2], conics [C,N,3] and depths [C,N] (any may be null).
// A (camera, Gaussian) whose incoming gradients are all 0 contributes nothing (its projection may not be
// finite), as a lane mask.
void project_backward_lanes(int64_t C, int64_t N, int64_t n0, const float* means, const float* quats,
                            const float* scales, const float* cams, const float* Ks, int64_t W, int64_t H, float near,
                            float far, float eps2d, const float* g_means2d, const float* g_conics,
                            const float* g_depths, float* g_means, float* g_quats, float* g_scales) {
    using T = VF;
    T x[3], q[4], sc[3];
    for (int l = 0; l < LANES; ++l) {
        const int64_t n = std::min<int64_t>(n0 + l, N - 1);
        for (int i = 0; i < 3; ++i) x[i][l] = means[3 * n + i], sc[i][l] = scales[3 * n + i];
        for (int i = 0; i < 4; ++i) q[i][l] = quats[4 * n + i];
    }
    T gx[3] = {}, gRq[9] = {}, gs[3] = {};
    Proj<T> r;
    bool projected = false;
    for (int64_t c = 0; c < C; ++c) {
        T gm0{}, gm1{}, gk0{}, gk1{}, gk2{}, gz{};
        for (int l = 0; l < LANES && n0 + l < N; ++l) {
            const int64_t cn = c * N + n0 + l;
            if (g_means2d) gm0[l] = g_means2d[2 * cn], gm1[l] = g_means2d[2 * cn + 1];
            if (g_conics) gk0[l] = g_conics[3 * cn], gk1[l] = g_conics[3 * cn + 1], gk2[l] = g_conics[3 * cn + 2];
            if (g_depths) gz[l] = g_depths[cn];
        }
        const auto act = (gm0 != 0) | (gm1 != 0) | (gk0 != 0) | (gk1 != 0) | (gk2 != 0) | (gz != 0);
        if (!any_lane(act)) continue;
        const Camera cam = load_camera<float>(cams + 16 * c, Ks + 9 * c, W, H);
        project_one<T>(cam, x, q, sc, near, far, eps2d, r);
        projected = true;
        // d loss / d Sigma = -K G K, G = [[gk0, gk1 / 2], [gk1 / 2, gk2]] (b is both off-diagonals)
        const T k0 = r.conic[0], k1 = r.conic[1], k2 = r.conic[2];
        const T h = 0.5f * gk1;
        const T t00 = k0 * gk0 + k1 * h, t01 = k0 * h + k1 * gk2;  // K G
        const T t10 = k1 * gk0 + k2 * h, t11 = k1 * h + k2 * gk2;
        const T S00 = -(t00 * k0 + t01 * k1), S01 = -(t00 * k1 + t01 * k2);
        const T S11 = -(t10 * k1 + t11 * k2);
        // Sigma = A A^T + eps I: d loss / d A = 2 S A
        T gA[6];
        for (int k = 0; k < 3; ++k) {
            gA[k] = 2.0f * (S00 * r.A[k] + S01 * r.A[3 + k]);
            gA[3 + k] = 2.0f * (S01 * r.A[k] + S11 * r.A[3 + k]);
        }
        // A = J RM: d J = gA RM^T, d RM = J^T gA
        T gJ[6], gRM[9];
        for (int i = 0; i < 2; ++i)
            for (int j = 0; j < 3; ++j)
                gJ[3 * i + j] = gA[3 * i] * r.RM[3 * j] + gA[3 * i + 1] * r.RM[3 * j + 1] + gA[3 * i + 2] * r.RM[3 * j + 2];
        for (int j = 0; j < 3; ++j)
            for (int k = 0; k < 3; ++k) gRM[3 * j + k] = r.J[j] * gA[k] + r.J[3 + j] * gA[3 + k];
        // RM = R M: d M = R^T d RM; M = Rq diag(s)
        for (int i = 0; i < 3; ++i)
            for (int k = 0; k < 3; ++k) {
                const T gM = cam.R[i] * gRM[k] + cam.R[3 + i] * gRM[3 + k] + cam.R[6 + i] * gRM[6 + k];
                gRq[3 * i + k] += select(act, T{}, gM * sc[k]);
                gs[k] += select(act, T{}, gM * r.Rq[3 * i + k]);
            }
        // J entries -> zs, uc, vc; then u, v, p
        const T zs = r.zs, iz = 1.0f / zs, iz2 = iz * iz;
        T gzs = gJ[0] * (-cam.fx * iz2) + gJ[2] * (cam.fx * r.uc * iz2) + gJ[4] * (-cam.fy * iz2) +
                gJ[5] * (cam.fy * r.vc * iz2);
        const T guc = gJ[2] * (-cam.fx * iz), gvc = gJ[5] * (-cam.fy * iz);
        const T gu = gm0 * cam.fx + select((r.u > cam.lo_u) & (r.u < cam.hi_u), T{}, guc);
        const T gv = gm1 * cam.fy + select((r.v > cam.lo_v) & (r.v < cam.hi_v), T{}, gvc);
        gzs += -(gu * r.p[0] + gv * r.p[1]) * iz2;
        const T gp[3] = {gu * iz, gv * iz, gz + select(r.in_depth, T{}, gzs)};
        for (int j = 0; j < 3; ++j)
            gx[j] += select(act, T{}, cam.R[j] * gp[0] + cam.R[3 + j] * gp[1] + cam.R[6 + j] * gp[2]);
    }
    // Rq(qn) -> qn -> q (through the normalisation, blocked where the norm was clamped). r holds these
    // Gaussians' unit quaternions whenever some camera contributed (otherwise every gradient is 0).
    auto any = gRq[0] != 0;
    for (int i = 1; i < 9; ++i) any = any | (gRq[i] != 0);
    T gq4[4] = {};
    if (projected && any_lane(any)) {
        const T qw = r.qn[0], qx = r.qn[1], qy = r.qn[2], qz = r.qn[3];
        const T* G = gRq;
        T gq[4];
        gq[0] = 2 * (-qz * G[1] + qy * G[2] + qz * G[3] - qx * G[5] - qy * G[6] + qx * G[7]);
        gq[1] = 2 * (qy * G[1] + qz * G[2] + qy * G[3] - 2 * qx * G[4] - qw * G[5] + qz * G[6] + qw * G[7] -
                     2 * qx * G[8]);
        gq[2] = 2 * (-2 * qy * G[0] + qx * G[1] + qw * G[2] + qx * G[3] + qz * G[5] - qw * G[6] + qz * G[7] -
                     2 * qy * G[8]);
        gq[3] = 2 * (-2 * qz * G[0] - qw * G[1] + qx * G[2] + qw * G[3] - 2 * qz * G[4] + qy * G[5] +
                     qx * G[6] + qy * G[7]);
        const T raw = vsqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
        const T dot = select(raw >= 1e-12f, T{}, gq[0] * qw + gq[1] * qx + gq[2] * qy + gq[3] * qz);
        const T nq = vmax<T>(raw, T{} + 1e-12f);
        for (int i = 0; i < 4; ++i) gq4[i] = select(any, T{}, (gq[i] - r.qn[i] * dot) / nq);
    }
    for (int l = 0; l < LANES && n0 + l < N; ++l) {
        const int64_t n = n0 + l;
        for (int i = 0; i < 4; ++i) g_quats[4 * n + i] = gq4[i][l];
        for (int j = 0; j < 3; ++j) {
            g_means[3 * n + j] = gx[j][l];
            g_scales[3 * n + j] = gs[j][l];
        }
    }
}

// Gradients w.r.t. means, quats and scales (overwritten) from those of means2d [C,N,2], conics [C,N,3]
// and depths [C,N] (any may be null). The conic is inv(A A^T + eps I): d conic = -K dSigma K.
void project_backward(int64_t C, int64_t N, const float* means, const float* quats, const float* scales,
                      const float* cams, const float* Ks, int64_t W, int64_t H, float near, float far, float eps2d,
                      const float* g_means2d, const float* g_conics, const float* g_depths, float* g_means,
                      float* g_quats, float* g_scales, int64_t num_threads) {
    const int64_t blocks = (N + LANES - 1) / LANES;
    const int64_t workers = std::max<int64_t>(1, std::min<int64_t>(num_threads, N / 2048 + 1));
    uskern::run_workers(workers, [&](int64_t w) {
        for (int64_t blk = blocks * w / workers; blk < blocks * (w + 1) / workers; ++blk)
            project_backward_lanes(C, N, blk * LANES, means, quats, scales, cams, Ks, W, H, near, far, eps2d,
                                   g_means2d, g_conics, g_depths, g_means, g_quats, g_scales);
    });
}

// ------------------------------------------------------------------ the expected render's peak factor
// render._blur_log_peak (the reference; its docstring has the model): per camera and Gaussian, the log of
// sqrt(det Sigma2d / det Sigma2d') = 0.5 (log det(Sigma2d' - v J J^T) + log det C'), C' the blurred conic,
// at most 0, and 0 behind the camera or for a degenerate conic. In double, as the reference: the
// difference cancels when the blur dominates. One pass per Gaussian replaces some 20 float64 tensor ops
// and their graph. Backward: the same steps in reverse, with the reference's clamp and selection rules.

// Everything forward computes for one (camera, Gaussian), kept for backward.
struct BlurPeakState {
    bool ok, pass;  // ok: a value (else 0); pass: the value is not clamped at 0 (gradient flows)
    double x, y, zs, u, v, uc, vc, iz2, jxx, jxy, jyy, a, b, c, dc, var, sxx, sxy, syy, raw, ds, out;
};

// VALUE: also the output (one log); the backward needs only ``pass``, which the determinant ratio gives without it.
template <bool VALUE>
inline BlurPeakState blur_peak_one(const CameraT<double>& k, const float* m, const float* con, float v, double near,
                                   double far, double eps2d) {
    BlurPeakState s{};
    const double mx = m[0], my = m[1], mz = m[2];
    s.x = k.R[0] * mx + k.R[1] * my + k.R[2] * mz + k.t[0];
    s.y = k.R[3] * mx + k.R[4] * my + k.R[5] * mz + k.t[1];
    const double z = k.R[6] * mx + k.R[7] * my + k.R[8] * mz + k.t[2];
    const bool inside = z > near && z < far;
    s.zs = inside ? z : 1.0;
    s.u = s.x / s.zs, s.v = s.y / s.zs;
    s.uc = std::max(std::min(s.u, k.hi_u), k.lo_u);
    s.vc = std::max(std::min(s.v, k.hi_v), k.lo_v);
    s.iz2 = 1.0 / (s.zs * s.zs);
    s.jxx = k.fx * k.fx * s.iz2 * (1 + s.uc * s.uc);
    s.jxy = k.fx * k.fy * s.iz2 * s.uc * s.vc;
    s.jyy = k.fy * k.fy * s.iz2 * (1 + s.vc * s.vc);
    s.a = con[0], s.b = con[1], s.c = con[2];
    const double det = s.a * s.c - s.b * s.b;
    s.ok = inside && det > static_cast<double>(std::numeric_limits<float>::min());
    s.dc = s.ok ? det : 1.0;
    s.var = std::max(static_cast<double>(v), 0.0);
    s.sxx = s.c / s.dc - s.var * s.jxx;
    s.sxy = -s.b / s.dc - s.var * s.jxy;
    s.syy = s.a / s.dc - s.var * s.jyy;
    s.raw = s.sxx * s.syy - s.sxy * s.sxy;
    s.ds = std::max(s.raw, eps2d * eps2d);
    // log sqrt(det Sigma2d / det Sigma2d'): det Sigma2d' = 1 / dc, so the ratio is ds dc (one log, not two)
    const double ratio = s.ds * s.dc;
    s.pass = s.ok && ratio <= 1.0;
    if (VALUE) s.out = s.pass ? 0.5 * std::log(ratio) : 0.0;
    return s;
}

void blur_peak_forward(int64_t C, int64_t N, const float* means, const float* conics, const float* var,
                       const float* cams, const float* Ks, int64_t W, int64_t H, double near, double far, double eps2d,
                       float* out, int64_t num_threads) {
    const int64_t workers = std::max<int64_t>(1, std::min<int64_t>(num_threads, C * N / 8192 + 1));
    for (int64_t ci = 0; ci < C; ++ci) {
        const CameraT<double> k = load_camera<double>(cams + 16 * ci, Ks + 9 * ci, W, H);
        uskern::run_workers(workers, [&](int64_t w) {
            for (int64_t n = N * w / workers; n < N * (w + 1) / workers; ++n)
                out[ci * N + n] = static_cast<float>(
                    blur_peak_one<true>(k, means + 3 * n, conics + 3 * (ci * N + n), var[n], near, far, eps2d).out);
        });
    }
}

// g_means [N,3] and g_var [N] are sums over the cameras (a worker owns a range of Gaussians); g_conics [C,N,3].
void blur_peak_backward(int64_t C, int64_t N, const float* means, const float* conics, const float* var,
                        const float* cams, const float* Ks, int64_t W, int64_t H, double near, double far, double eps2d,
                        const float* g_out, float* g_means, float* g_conics, float* g_var, int64_t num_threads) {
    std::vector<CameraT<double>> ks(static_cast<size_t>(C));
    for (int64_t ci = 0; ci < C; ++ci) ks[ci] = load_camera<double>(cams + 16 * ci, Ks + 9 * ci, W, H);
    const int64_t workers = std::max<int64_t>(1, std::min<int64_t>(num_threads, C * N / 8192 + 1));
    uskern::run_workers(workers, [&](int64_t w) {
        for (int64_t n = N * w / workers; n < N * (w + 1) / workers; ++n) {
            double gm[3] = {0, 0, 0}, gv = 0;
            for (int64_t ci = 0; ci < C; ++ci) {
                const CameraT<double>& k = ks[ci];
                const int64_t cn = ci * N + n;
                float* gc = g_conics + 3 * cn;
                const double G = g_out[cn];
                if (G == 0.0) {  // every gradient below is proportional to G (in training: most Gaussians, unseen)
                    gc[0] = gc[1] = gc[2] = 0.0f;
                    continue;
                }
                const BlurPeakState s = blur_peak_one<false>(k, means + 3 * n, conics + 3 * cn, var[n], near, far, eps2d);
                if (!s.pass) {
                    gc[0] = gc[1] = gc[2] = 0.0f;
                    continue;
                }
                const double d_raw = s.raw >= eps2d * eps2d ? G * 0.5 / s.ds : 0.0;
                double d_dc = G * 0.5 / s.dc;
                const double d_sxx = d_raw * s.syy, d_syy = d_raw * s.sxx, d_sxy = -2.0 * d_raw * s.sxy;
                const double idc = 1.0 / s.dc, idc2 = idc * idc;
                double d_a = d_syy * idc, d_b = -d_sxy * idc, d_c = d_sxx * idc;
                d_dc += -d_sxx * s.c * idc2 + d_sxy * s.b * idc2 - d_syy * s.a * idc2;
                const double d_var = -(d_sxx * s.jxx + d_sxy * s.jxy + d_syy * s.jyy);
                const double d_jxx = -d_sxx * s.var, d_jxy = -d_sxy * s.var, d_jyy = -d_syy * s.var;
                d_a += d_dc * s.c;
                d_c += d_dc * s.a;
                d_b += -2.0 * s.b * d_dc;
                gc[0] = static_cast<float>(d_a), gc[1] = static_cast<float>(d_b), gc[2] = static_cast<float>(d_c);
                if (var[n] >= 0.0f) gv += d_var;
                const double fxx = k.fx * k.fx, fxy = k.fx * k.fy, fyy = k.fy * k.fy;
                const double d_iz2 = d_jxx * fxx * (1 + s.uc * s.uc) + d_jxy * fxy * s.uc * s.vc +
                                     d_jyy * fyy * (1 + s.vc * s.vc);
                const double d_uc = d_jxx * fxx * s.iz2 * 2 * s.uc + d_jxy * fxy * s.iz2 * s.vc;
                const double d_vc = d_jyy * fyy * s.iz2 * 2 * s.vc + d_jxy * fxy * s.iz2 * s.uc;
                // the clamps of the view angle pass the gradient only strictly inside their bounds
                const double du = (s.u < k.hi_u && s.u > k.lo_u) ? d_uc : 0.0;
                const double dv = (s.v < k.hi_v && s.v > k.lo_v) ? d_vc : 0.0;
                const double dx = du / s.zs, dy = dv / s.zs;
                const double dz = -(du * s.x + dv * s.y) / (s.zs * s.zs) - 2.0 * d_iz2 * s.iz2 / s.zs;  // ok: inside
                for (int j = 0; j < 3; ++j) gm[j] += k.R[j] * dx + k.R[3 + j] * dy + k.R[6 + j] * dz;
            }
            for (int j = 0; j < 3; ++j) g_means[3 * n + j] = static_cast<float>(gm[j]);
            g_var[n] = static_cast<float>(gv);
        }
    });
}

}  // namespace

extern "C" {

int us_blur_peak_forward_f32(int64_t C, int64_t N, const float* means, const float* conics, const float* var,
                             const float* cams, const float* Ks, int64_t W, int64_t H, double near, double far,
                             double eps2d, float* out, int64_t num_threads) {
    blur_peak_forward(C, N, means, conics, var, cams, Ks, W, H, near, far, eps2d, out, num_threads);
    return 0;
}

int us_blur_peak_backward_f32(int64_t C, int64_t N, const float* means, const float* conics, const float* var,
                              const float* cams, const float* Ks, int64_t W, int64_t H, double near, double far,
                              double eps2d, const float* g_out, float* g_means, float* g_conics, float* g_var,
                              int64_t num_threads) {
    blur_peak_backward(C, N, means, conics, var, cams, Ks, W, H, near, far, eps2d, g_out, g_means, g_conics, g_var,
                       num_threads);
    return 0;
}

int us_sh_forward_f32(int64_t C, int64_t N, int64_t B, int64_t degree, const float* sh, const float* means,
                      const float* centres, float* out, int64_t num_threads) {
    if (degree < 0 || degree > 3 || (degree + 1) * (degree + 1) > B) return 1;
    sh_forward(C, N, B, static_cast<int>(degree), ShLayout{sh, B * 3, sh + 3, B * 3}, means, centres, out,
               num_threads);
    return 0;
}

int us_sh_backward_f32(int64_t C, int64_t N, int64_t B, int64_t degree, const float* sh, const float* means,
                       const float* centres, const float* g_out, float* g_sh, float* g_means, int64_t num_threads) {
    if (degree < 0 || degree > 3 || (degree + 1) * (degree + 1) > B) return 1;
    sh_backward(C, N, B, static_cast<int>(degree), ShLayout{sh, B * 3, sh + 3, B * 3}, means, centres, g_out,
                ShGradLayout{g_sh, B * 3, g_sh + 3, B * 3}, g_means, num_threads);
    return 0;
}

// The same with the DC sh0 [N,1,3] and the higher bands shN [N,B-1,3] as two arrays (the parameter table's); the
// backward's g_shN may be null at degree 0 (no gradient of the bands, whose share of the render is nil, is written).
int us_sh2_forward_f32(int64_t C, int64_t N, int64_t B, int64_t degree, const float* sh0, const float* shN,
                       const float* means, const float* centres, float* out, int64_t num_threads) {
    if (degree < 0 || degree > 3 || (degree + 1) * (degree + 1) > B) return 1;
    sh_forward(C, N, B, static_cast<int>(degree), ShLayout{sh0, 3, shN, (B - 1) * 3}, means, centres, out,
               num_threads);
    return 0;
}

int us_sh2_backward_f32(int64_t C, int64_t N, int64_t B, int64_t degree, const float* sh0, const float* shN,
                        const float* means, const float* centres, const float* g_out, float* g_sh0, float* g_shN,
                        float* g_means, int64_t num_threads) {
    if (degree < 0 || degree > 3 || (degree + 1) * (degree + 1) > B || (g_shN == nullptr && degree > 0)) return 1;
    sh_backward(C, N, B, static_cast<int>(degree), ShLayout{sh0, 3, shN, (B - 1) * 3}, means, centres, g_out,
                ShGradLayout{g_sh0, 3, g_shN, (B - 1) * 3}, g_means, num_threads);
    return 0;
}

int us_project_forward_f32(int64_t C, int64_t N, const float* means, const float* quats, const float* scales,
                           const float* opac, const float* cams, const float* Ks, int64_t W, int64_t H, double near,
                           double far, double eps2d, double alpha_min, float* means2d, float* conics, float* depths,
                           float* extents, uint8_t* valid, int64_t num_threads) {
    project_forward(C, N, means, quats, scales, opac, cams, Ks, W, H, static_cast<float>(near), static_cast<float>(far),
                    static_cast<float>(eps2d), static_cast<float>(alpha_min), means2d, conics, depths, extents, valid,
                    num_threads);
    return 0;
}

int us_project_backward_f32(int64_t C, int64_t N, const float* means, const float* quats, const float* scales,
                            const float* cams, const float* Ks, int64_t W, int64_t H, double near, double far,
                            double eps2d, const float* g_means2d, const float* g_conics, const float* g_depths,
                            float* g_means, float* g_quats, float* g_scales, int64_t num_threads) {
    project_backward(C, N, means, quats, scales, cams, Ks, W, H, static_cast<float>(near), static_cast<float>(far),
                     static_cast<float>(eps2d), g_means2d, g_conics, g_depths, g_means, g_quats, g_scales, num_threads);
    return 0;
}

}  // extern "C"
