// Small numeric helpers shared by the CPU kernels: an explicit multiply-add and an exp() that
// vectorises. The build turns floating-point contraction off (-ffp-contract=off, see build.py),
// so every fused multiply-add is written out here, and code that two passes must evaluate
// bit-identically goes through the same inline helper.
#pragma once

#include <cstdint>
#include <cstdlib>
#include <cstring>

#if defined(__AVX__)
#include <immintrin.h>
#endif

// a * b + c, fused when the target has FMA.
#ifdef __FMA__
#define STG_MADD(a, b, c) __builtin_fmaf((a), (b), (c))
#else
#define STG_MADD(a, b, c) ((a) * (b) + (c))
#endif

namespace stg_math {

// exp(x) for x in [-87, 88] to ~1 ulp (clamped outside), with no libm call and no branch, so
// that loops over it vectorise.
inline float fast_exp(float x) {
    x = x < -60.0f ? -60.0f : x;
    x = x > 88.0f ? 88.0f : x;
    float k = x * 1.44269504088896341f;
    k = (k + 12582912.0f) - 12582912.0f;  // round to nearest integer
    float r = STG_MADD(k, -0.693145751953125f, x);  // Cody-Waite: ln2 = hi + lo
    r = STG_MADD(k, -1.42860682030941723212e-6f, r);
    float p = 1.0f / 720.0f;
    p = STG_MADD(p, r, 1.0f / 120.0f);
    p = STG_MADD(p, r, 1.0f / 24.0f);
    p = STG_MADD(p, r, 1.0f / 6.0f);
    p = STG_MADD(p, r, 0.5f);
    p = STG_MADD(p, r, 1.0f);
    p = STG_MADD(p, r, 1.0f);
    int32_t bits = (static_cast<int32_t>(k) + 127) << 23;
    float scale;
    std::memcpy(&scale, &bits, sizeof(float));
    return p * scale;
}

// Eight floats in one vector register (AVX) or two (SSE): GCC/Clang vector extensions, so the
// code is the same on every x86-64 level and on other targets.
typedef float v8f __attribute__((vector_size(32)));

inline v8f v8_load(const float* p) {
    v8f v;
    std::memcpy(&v, p, sizeof(v));
    return v;
}

inline void v8_store(float* p, v8f v) { std::memcpy(p, &v, sizeof(v)); }

inline v8f v8_splat(float x) { return v8f{x, x, x, x, x, x, x, x}; }

// a * b + c on eight lanes, fused when the target has FMA (the compiler emits vfmadd).
inline v8f v8_madd(v8f a, v8f b, v8f c) {
#if defined(__FMA__) && defined(__AVX__)
    return (v8f)_mm256_fmadd_ps((__m256)a, (__m256)b, (__m256)c);
#else
    return a * b + c;
#endif
}

typedef int32_t v8i __attribute__((vector_size(32)));

inline v8i v8i_splat(int32_t x) { return v8i{x, x, x, x, x, x, x, x}; }

inline v8i v8i_load(const int32_t* p) {
    v8i v;
    std::memcpy(&v, p, sizeof(v));
    return v;
}

inline void v8i_store(int32_t* p, v8i v) { std::memcpy(p, &v, sizeof(v)); }

// fast_exp on eight lanes: the same operations in the same order, so every lane equals
// fast_exp of that lane bit for bit (the rasterizer's passes rely on it).
inline v8f fast_exp8(v8f x) {
    const v8f lo = v8_splat(-60.0f), hi = v8_splat(88.0f);
    x = x < lo ? lo : x;
    x = x > hi ? hi : x;
    v8f k = x * v8_splat(1.44269504088896341f);
    k = (k + v8_splat(12582912.0f)) - v8_splat(12582912.0f);
    v8f r = v8_madd(k, v8_splat(-0.693145751953125f), x);
    r = v8_madd(k, v8_splat(-1.42860682030941723212e-6f), r);
    v8f p = v8_splat(1.0f / 720.0f);
    p = v8_madd(p, r, v8_splat(1.0f / 120.0f));
    p = v8_madd(p, r, v8_splat(1.0f / 24.0f));
    p = v8_madd(p, r, v8_splat(1.0f / 6.0f));
    p = v8_madd(p, r, v8_splat(0.5f));
    p = v8_madd(p, r, v8_splat(1.0f));
    p = v8_madd(p, r, v8_splat(1.0f));
    const v8i bits = (__builtin_convertvector(k, v8i) + 127) << 23;
    v8f scale;
    std::memcpy(&scale, &bits, sizeof(scale));
    return p * scale;
}

// Bit l set where lane l of the mask is true (all bits set).
inline uint32_t v8_movemask(v8i mask) {
#if defined(__AVX__)
    return static_cast<uint32_t>(_mm256_movemask_ps((__m256)mask));
#else
    uint32_t bits = 0;
    for (int l = 0; l < 8; ++l) bits |= (mask[l] != 0 ? 1u : 0u) << l;
    return bits;
#endif
}

}  // namespace stg_math

// Whether a kernel's 16-lane AVX-512 path may run (a run-time choice: the build stays portable
// x86-64-v3 and each wide path is compiled with a function-level target): the CPU and its OS have
// AVX-512F and STG_SPLAT_NO_AVX512 is not set (the switch the tests use to compare the two paths).
inline bool stg_avx512_allowed() {
    static const bool cpu = __builtin_cpu_supports("avx512f");
    if (!cpu) return false;
    const char* off = std::getenv("STG_SPLAT_NO_AVX512");
    return off == nullptr || off[0] == '\0' || off[0] == '0';
}
