// Branch-free float math that the compiler vectorises inside SIMD loops (no calls into libm).
// Constants: Cephes single-precision expf/logf polynomials.
#pragma once

#include <cstdint>
#include <cstring>

namespace uskern {

// exp for |x| <= 87 (clamped outside), within 2 ulp of expf: Cody-Waite reduction and a degree-6
// polynomial, branch-free so that loops calling it vectorise (build with -fno-trapping-math).
inline float vexp(float x) {
    x = x < -87.0f ? -87.0f : x;
    x = x > 87.0f ? 87.0f : x;
    const float t = x * 1.44269504088896341f + 128.5f;
    const int k = static_cast<int>(t) - 128;
    const float kf = static_cast<float>(k);
    const float r = (x - kf * 0.693359375f) - kf * (-2.12194440e-4f);
    float p = 1.9875691500e-4f;
    p = p * r + 1.3981999507e-3f;
    p = p * r + 8.3334519073e-3f;
    p = p * r + 4.1665795894e-2f;
    p = p * r + 1.6666665459e-1f;
    p = p * r + 5.0000001201e-1f;
    const float y = p * (r * r) + r + 1.0f;
    const int32_t bits = (k + 127) << 23;
    float scale;
    std::memcpy(&scale, &bits, sizeof(scale));
    return y * scale;
}

// vexp on a vector of floats at once (GCC/Clang vector extension types: VF of floats, VI the int32
// vector of the same size), the same operations lane by lane.
template <typename VF, typename VI>
inline VF vexp_vec(VF x) {
    x = x < -87.0f ? VF{} - 87.0f : x;
    x = x > 87.0f ? VF{} + 87.0f : x;
    const VF t = x * 1.44269504088896341f + 128.5f;
    const VI k = __builtin_convertvector(t, VI) - 128;
    const VF kf = __builtin_convertvector(k, VF);
    const VF r = (x - kf * 0.693359375f) - kf * (-2.12194440e-4f);
    VF p = VF{} + 1.9875691500e-4f;
    p = p * r + 1.3981999507e-3f;
    p = p * r + 8.3334519073e-3f;
    p = p * r + 4.1665795894e-2f;
    p = p * r + 1.6666665459e-1f;
    p = p * r + 5.0000001201e-1f;
    const VF y = p * (r * r) + r + 1.0f;
    const VI bits = (k + 127) << 23;
    return y * (VF)bits;  // a vector cast reinterprets the bits
}

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
