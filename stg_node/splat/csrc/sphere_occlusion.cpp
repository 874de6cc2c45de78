// The spheres' occlusion of each point's hemisphere (see sphere_occlusion.h for the contract).
//
// The spheres are copied once into padded structure-of-arrays rows (x, y, z, r^2, and the mask
// per group), so the inner loop is eight lanes of plain arithmetic; padded spheres have mask 0
// and cover nothing. The eight partial products are multiplied together at the end of each point.
#include "sphere_occlusion.h"

#include <omp.h>

#include <algorithm>
#include <cmath>
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
    const v8f zero = v8_splat(0.0f), one = v8_splat(1.0f), tiny = v8_splat(1e-12f);

#pragma omp parallel for schedule(static) num_threads(std::max(1, threads))
    for (int64_t i = 0; i < m; ++i) {
        const float* p = points + 3 * i;
        const float* n = normals + 3 * i;
        const v8f px = v8_splat(p[0]), py = v8_splat(p[1]), pz = v8_splat(p[2]);
        const v8f nx = v8_splat(n[0]), ny = v8_splat(n[1]), nz = v8_splat(n[2]);
        const float* wi = w.data() + group[i] * padded;
        v8f acc = one;
        for (int64_t s = 0; s < padded; s += 8) {
            const v8f dx = v8_load(cx.data() + s) - px;
            const v8f dy = v8_load(cy.data() + s) - py;
            const v8f dz = v8_load(cz.data() + s) - pz;
            v8f d2 = v8_madd(dz, dz, v8_madd(dy, dy, dx * dx));
            d2 = d2 < tiny ? tiny : d2;
            const v8f toward = v8_madd(nz, dz, v8_madd(ny, dy, nx * dx));
            const v8f d = sqrt8(d2);
            v8f cosine = toward / d;
            cosine = cosine < zero ? zero : cosine;
            cosine = cosine > one ? one : cosine;
            v8f share = v8_load(r2.data() + s) / d2;
            share = share > one ? one : share;
            acc = acc * (one - cosine * share * v8_load(wi + s));
        }
        float product = 1.0f;
        for (int k = 0; k < 8; ++k) product *= acc[k];
        visible[i] = product;
    }
}

}  // namespace stg_occ
