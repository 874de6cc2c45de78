// The spheres' occlusion of each point's hemisphere (see sphere_occlusion.h for the contract).
//
// The spheres are copied once into padded structure-of-arrays rows (x, y, z, r^2, and the mask
// per group), so the inner loop is eight lanes of plain arithmetic; padded spheres have mask 0
// and cover nothing. The eight partial products are multiplied together at the end of each point.
#include "sphere_occlusion.h"

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <vector>

#include "fast_math.h"

namespace stg_occ {

using stg_math::v8f;
using stg_math::v8_load;
using stg_math::v8_madd;
using stg_math::v8_splat;

namespace {

inline v8f sqrt8(v8f x) {
#if defined(__AVX__)
    return reinterpret_cast<v8f>(_mm256_sqrt_ps(reinterpret_cast<__m256>(x)));
#else
    v8f r;
    for (int k = 0; k < 8; ++k) r[k] = std::sqrt(x[k]);
    return r;
#endif
}

// The visible share of one point (v8 lanes over the spheres; the padded arrays of sphere_visibility).
inline float point_visibility(const float* p, const float* n, const float* wi, int64_t padded, const float* cx,
                              const float* cy, const float* cz, const float* r2) {
    const v8f zero = v8_splat(0.0f), one = v8_splat(1.0f), tiny = v8_splat(1e-12f);
    const v8f px = v8_splat(p[0]), py = v8_splat(p[1]), pz = v8_splat(p[2]);
    const v8f nx = v8_splat(n[0]), ny = v8_splat(n[1]), nz = v8_splat(n[2]);
    v8f acc = one;
    for (int64_t s = 0; s < padded; s += 8) {
        const v8f dx = v8_load(cx + s) - px;
        const v8f dy = v8_load(cy + s) - py;
        const v8f dz = v8_load(cz + s) - pz;
        v8f d2 = v8_madd(dz, dz, v8_madd(dy, dy, dx * dx));
        d2 = d2 < tiny ? tiny : d2;
        const v8f toward = v8_madd(nz, dz, v8_madd(ny, dy, nx * dx));
        const v8f d = sqrt8(d2);
        v8f cosine = toward / d;
        cosine = cosine < zero ? zero : cosine;
        cosine = cosine > one ? one : cosine;
        v8f share = v8_load(r2 + s) / d2;
        share = share > one ? one : share;
        acc = acc * (one - cosine * share * v8_load(wi + s));
    }
    float product = 1.0f;
    for (int k = 0; k < 8; ++k) product *= acc[k];
    return product;
}

#if defined(__x86_64__) && defined(__GNUC__) && defined(__FMA__)
#define STG_OCC_WIDE 1
// Two points at once on 16-lane AVX-512 vectors (chosen at run time: the build stays portable),
// lanes 0-7 the first point's eight spheres, 8-15 the second's: every lane computes what
// point_visibility's lane does, with the same operations in the same order, so the result is
// bit-identical. The sphere rows come doubled (16 floats per chunk of 8).
__attribute__((target("avx512f"))) void visibility_pair(const float* p, const float* n, const float* wa,
                                                        const float* wb, int64_t padded, const float* cx2,
                                                        const float* cy2, const float* cz2, const float* r22,
                                                        float* out) {
    const __m512 zero = _mm512_setzero_ps(), one = _mm512_set1_ps(1.0f), tiny = _mm512_set1_ps(1e-12f);
    constexpr __mmask16 kHigh = 0xFF00;
#define STG_OCC_PAIR(a, b) _mm512_mask_blend_ps(kHigh, _mm512_set1_ps(a), _mm512_set1_ps(b))
    const __m512 px = STG_OCC_PAIR(p[0], p[3]), py = STG_OCC_PAIR(p[1], p[4]), pz = STG_OCC_PAIR(p[2], p[5]);
    const __m512 nx = STG_OCC_PAIR(n[0], n[3]), ny = STG_OCC_PAIR(n[1], n[4]), nz = STG_OCC_PAIR(n[2], n[5]);
#undef STG_OCC_PAIR
    __m512 acc = one;
    for (int64_t s = 0; s < padded; s += 8) {
        const __m512 dx = _mm512_sub_ps(_mm512_loadu_ps(cx2 + 2 * s), px);
        const __m512 dy = _mm512_sub_ps(_mm512_loadu_ps(cy2 + 2 * s), py);
        const __m512 dz = _mm512_sub_ps(_mm512_loadu_ps(cz2 + 2 * s), pz);
        __m512 d2 = _mm512_fmadd_ps(dz, dz, _mm512_fmadd_ps(dy, dy, _mm512_mul_ps(dx, dx)));
        d2 = _mm512_mask_blend_ps(_mm512_cmp_ps_mask(d2, tiny, _CMP_LT_OQ), d2, tiny);
        const __m512 toward = _mm512_fmadd_ps(nz, dz, _mm512_fmadd_ps(ny, dy, _mm512_mul_ps(nx, dx)));
        const __m512 d = _mm512_sqrt_ps(d2);
        __m512 cosine = _mm512_div_ps(toward, d);
        cosine = _mm512_mask_blend_ps(_mm512_cmp_ps_mask(cosine, zero, _CMP_LT_OQ), cosine, zero);
        cosine = _mm512_mask_blend_ps(_mm512_cmp_ps_mask(cosine, one, _CMP_GT_OQ), cosine, one);
        __m512 share = _mm512_div_ps(_mm512_loadu_ps(r22 + 2 * s), d2);
        share = _mm512_mask_blend_ps(_mm512_cmp_ps_mask(share, one, _CMP_GT_OQ), share, one);
        const __m512 w = _mm512_castpd_ps(_mm512_insertf64x4(
            _mm512_castps_pd(_mm512_castps256_ps512(_mm256_loadu_ps(wa + s))), _mm256_castps_pd(_mm256_loadu_ps(wb + s)), 1));
        acc = _mm512_mul_ps(acc, _mm512_sub_ps(one, _mm512_mul_ps(_mm512_mul_ps(cosine, share), w)));
    }
    alignas(64) float lanes[16];
    _mm512_store_ps(lanes, acc);
    float first = 1.0f, second = 1.0f;
    for (int k = 0; k < 8; ++k) first *= lanes[k];
    for (int k = 8; k < 16; ++k) second *= lanes[k];
    out[0] = first;
    out[1] = second;
}
#endif

// Whether the points go in pairs on AVX-512 (fast_math.h: the CPU has it, STG_SPLAT_NO_AVX512 unset).
bool wide_vectors() {
#ifdef STG_OCC_WIDE
    return stg_avx512_allowed();
#else
    return false;
#endif
}

}  // namespace

void sphere_visibility(const float* points, const float* normals, const int64_t* group, int64_t m,
                       const float* centres, const float* radii2, const float* mask, int64_t spheres,
                       int64_t groups, float* visible, int threads) {
    const int64_t padded = (spheres + 7) / 8 * 8;
    std::vector<float> cx(padded, 0.0f), cy(padded, 0.0f), cz(padded, 0.0f), r2(padded, 0.0f);
    for (int64_t s = 0; s < spheres; ++s) {
        cx[s] = centres[3 * s];
        cy[s] = centres[3 * s + 1];
        cz[s] = centres[3 * s + 2];
        r2[s] = radii2[s];
    }
    std::vector<float> w(static_cast<size_t>(groups * padded), 0.0f);
    for (int64_t g = 0; g < groups; ++g)
        for (int64_t s = 0; s < spheres; ++s) w[g * padded + s] = mask[g * spheres + s];
    const bool wide = wide_vectors();
    const int64_t pairs = wide ? m / 2 : 0;
#ifdef STG_OCC_WIDE
    std::vector<float> cx2, cy2, cz2, r22;
    if (wide) {
        const std::vector<float>* sources[4] = {&cx, &cy, &cz, &r2};
        std::vector<float>* doubled[4] = {&cx2, &cy2, &cz2, &r22};
        for (int a = 0; a < 4; ++a) {
            doubled[a]->resize(2 * padded);
            for (int64_t c = 0; c < padded; c += 8)
                for (int half = 0; half < 2; ++half)
                    std::copy(sources[a]->begin() + c, sources[a]->begin() + c + 8, doubled[a]->begin() + 2 * c + 8 * half);
        }
    }
#pragma omp parallel for schedule(static) num_threads(std::max(1, threads))
    for (int64_t q = 0; q < pairs; ++q) {
        const int64_t i = 2 * q;
        visibility_pair(points + 3 * i, normals + 3 * i, w.data() + group[i] * padded,
                        w.data() + group[i + 1] * padded, padded, cx2.data(), cy2.data(), cz2.data(), r22.data(),
                        visible + i);
    }
#endif
#pragma omp parallel for schedule(static) num_threads(std::max(1, threads))
    for (int64_t i = 2 * pairs; i < m; ++i)
        visible[i] = point_visibility(points + 3 * i, normals + 3 * i, w.data() + group[i] * padded, padded,
                                      cx.data(), cy.data(), cz.data(), r2.data());
}

}  // namespace stg_occ
