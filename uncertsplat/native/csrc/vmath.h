// Branch-free float math that the compiler vectorises inside SIMD loops (no calls into libm).
// Constants: Cephes single-precision expf/logf polynomials.
#pragma once

#include <cstdint>
#include <cstring>
#include <type_traits>

namespace uskern {

// Floats per SIMD register of the target (16 with AVX-512, 8 with AVX, else 4: SSE, NEON), and that many
// floats / int32 as a GCC/Clang vector type. The kernels that run across pixels or Gaussians use it rather
// than intrinsics, so the same code builds for any target; wider vectors than this are avoided (GCC lowers
// some of their operations lane by lane).
#if defined(__AVX512F__)
constexpr int LANES = 16;
#elif defined(__AVX__)
constexpr int LANES = 8;
#else
constexpr int LANES = 4;
#endif
typedef float floatv __attribute__((vector_size(LANES * sizeof(float))));
typedef int32_t int32v __attribute__((vector_size(LANES * sizeof(int32_t))));

// Value conversions (float <-> int32, rounding toward zero) and bit reinterpretation, for a float / int32
// or a GCC/Clang vector of them.
template <typename To, typename From>
inline To convert(From x) {
    if constexpr (std::is_arithmetic_v<From>) {
        return static_cast<To>(x);
    } else {
        return __builtin_convertvector(x, To);
    }
}

template <typename To, typename From>
inline To bit_cast(From x) {
    static_assert(sizeof(To) == sizeof(From), "same size");
    To y;
    std::memcpy(&y, &x, sizeof(y));
    return y;
}

// exp for |x| <= 87 (clamped outside), within 2 ulp of expf: Cody-Waite reduction and a degree-6
// polynomial, branch-free so that loops calling it vectorise (build with -fno-trapping-math). F is float
// (I int32_t) or a vector of floats (I the int32 vector of its size), computed lane by lane alike.
template <typename F, typename I>
inline F vexp_t(F x) {
    x = x < -87.0f ? F{} - 87.0f : x;
    x = x > 87.0f ? F{} + 87.0f : x;
    const F t = x * 1.44269504088896341f + 128.5f;
    const I k = convert<I>(t) - 128;
    const F kf = convert<F>(k);
    const F r = (x - kf * 0.693359375f) - kf * (-2.12194440e-4f);
    F p = F{} + 1.9875691500e-4f;
    p = p * r + 1.3981999507e-3f;
    p = p * r + 8.3334519073e-3f;
    p = p * r + 4.1665795894e-2f;
    p = p * r + 1.6666665459e-1f;
    p = p * r + 5.0000001201e-1f;
    const F y = p * (r * r) + r + 1.0f;
    return y * bit_cast<F>(I((k + 127) << 23));
}

inline float vexp(float x) { return vexp_t<float, int32_t>(x); }

inline float vlog(float x) {  // natural log of a positive normal float, within a few ulp
    int32_t bits;
    std::memcpy(&bits, &x, sizeof(bits));
    int e = ((bits >> 23) & 0xff) - 127;
    const int32_t mbits = (bits & 0x007fffff) | 0x3f800000;
    float m;
    std::memcpy(&m, &mbits, sizeof(m));  // [1, 2)
    const bool big = m > 1.41421356f;
    m = big ? 0.5f * m : m;
    e = big ? e + 1 : e;
    const float f = m - 1.0f;
    const float z = f * f;
    float y = 7.0376836292e-2f;
    y = y * f - 1.1514610310e-1f;
    y = y * f + 1.1676998740e-1f;
    y = y * f - 1.2420140846e-1f;
    y = y * f + 1.4249322787e-1f;
    y = y * f - 1.6668057665e-1f;
    y = y * f + 2.0000714765e-1f;
    y = y * f - 2.4999993993e-1f;
    y = y * f + 3.3333331174e-1f;
    y = y * f * z;
    const float ef = static_cast<float>(e);
    y += -2.12194440e-4f * ef;
    y += -0.5f * z;
    return f + y + 0.693359375f * ef;
}

inline float vlog1p(float z) {  // log(1 + z) for z >= 0, accurate for tiny z (u - 1 is exact)
    const float u = 1.0f + z;
    const float d = u - 1.0f;
    return d == 0.0f ? z : vlog(u) * (z / d);
}

inline float vsoftplus(float x) {  // log(1 + exp(x)), stable for any x
    const float ax = x < 0.0f ? -x : x;
    return (x > 0.0f ? x : 0.0f) + vlog1p(vexp(-ax));
}

inline float vsigmoid(float x) { return 1.0f / (1.0f + vexp(-x)); }

}  // namespace uskern
