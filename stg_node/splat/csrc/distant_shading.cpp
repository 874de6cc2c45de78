// The distant-light shading kernels (see distant_shading.h for the contract).
#include "distant_shading.h"

#include <omp.h>

#include <algorithm>
#include <vector>

namespace stg_shade {
namespace {

constexpr int kMaxLights = 8;

// E_j of row i, and the clamped cosines p_l and the raw cosines t_l.
inline void irradiance(const float* n, const Lights& L, float* e, float* p, float* t) {
    float sum[3] = {L.a[0], L.a[1], L.a[2]};
    for (int l = 0; l < L.count; ++l) {
        const float* d = L.d + 3 * l;
        t[l] = n[0] * d[0] + n[1] * d[1] + n[2] * d[2];
        p[l] = t[l] > 0.0f ? t[l] : 0.0f;
        for (int j = 0; j < 3; ++j) sum[j] += p[l] * L.c[3 * l + j];
    }
    for (int j = 0; j < 3; ++j) e[j] = sum[j] / L.m[j];
}

}  // namespace

void shade_forward(const float* albedo, const float* normals, const float* visible, float k, int64_t rows,
                   const Lights& lights, float* out, int threads) {
#pragma omp parallel for schedule(static) num_threads(threads)
    for (int64_t i = 0; i < rows; ++i) {
        float e[3], p[kMaxLights], t[kMaxLights];
        irradiance(normals + 3 * i, lights, e, p, t);
        const float f = visible != nullptr ? 1.0f - k + k * visible[i] : 1.0f;
        for (int j = 0; j < 3; ++j) out[3 * i + j] = albedo[3 * i + j] * f * e[j];
    }
}

void shade_backward(const float* albedo, const float* normals, const float* visible, float k, int64_t rows,
                    const Lights& lights, const bool* away, const float* g_out, float* g_albedo, float* g_normals,
                    double* g_k, double* g_a, double* g_c, double* g_d, double* g_m, int threads) {
    const int K = lights.count;
    threads = std::max(1, threads);
    // per-thread sums, in this order: k, a (3), c (3K), d (3K), m (3)
    const int width = 1 + 3 + 3 * K + 3 * K + 3;
    std::vector<double> sums(static_cast<size_t>(threads) * width, 0.0);
#pragma omp parallel num_threads(threads)
    {
        // the sums of this thread's rows in locals (no aliasing with the outputs: they stay in
        // registers), in float per block of rows and in double across blocks
        constexpr int64_t kChunk = 256;
        double total_k = 0.0, total_a[3] = {0, 0, 0}, total_m[3] = {0, 0, 0};
        double total_c[3 * kMaxLights] = {}, total_d[3 * kMaxLights] = {};
#pragma omp for schedule(static)
        for (int64_t i0 = 0; i0 < rows; i0 += kChunk) {
            const int64_t i1 = std::min(rows, i0 + kChunk);
            float sk = 0.0f, sa[3] = {0, 0, 0}, sm[3] = {0, 0, 0};
            float sc[3 * kMaxLights] = {}, sd[3 * kMaxLights] = {};
            for (int64_t i = i0; i < i1; ++i) {
                const float* n = normals + 3 * i;
                const float* al = albedo + 3 * i;
                const float* g = g_out + 3 * i;
                float e[3], p[kMaxLights], t[kMaxLights];
                irradiance(n, lights, e, p, t);
                const float f = visible != nullptr ? 1.0f - k + k * visible[i] : 1.0f;
                float g_f = 0.0f;
                float g_e[3];
                for (int j = 0; j < 3; ++j) {
                    if (g_albedo != nullptr) g_albedo[3 * i + j] = g[j] * f * e[j];
                    g_f += g[j] * al[j] * e[j];
                    g_e[j] = g[j] * al[j] * f;
                }
                if (visible != nullptr) sk += g_f * (visible[i] - 1.0f);
                float gn[3] = {0.0f, 0.0f, 0.0f};
                if (away == nullptr || !away[i]) {
                    float g_sum[3];  // dL/d(the numerator a + sum_l c_l p_l)
                    for (int j = 0; j < 3; ++j) {
                        g_sum[j] = g_e[j] / lights.m[j];
                        sa[j] += g_sum[j];
                        sm[j] -= g_sum[j] * e[j];
                    }
                    for (int l = 0; l < K; ++l) {
                        const float* c = lights.c + 3 * l;
                        float g_p = 0.0f;
                        for (int j = 0; j < 3; ++j) {
                            sc[3 * l + j] += g_sum[j] * p[l];
                            g_p += g_sum[j] * c[j];
                        }
                        if (t[l] >= 0.0f) {  // torch's clamp_min(0) passes the gradient at 0
                            const float* d = lights.d + 3 * l;
                            for (int q = 0; q < 3; ++q) {
                                gn[q] += g_p * d[q];
                                sd[3 * l + q] += g_p * n[q];
                            }
                        }
                    }
                }
                if (g_normals != nullptr)
                    for (int q = 0; q < 3; ++q) g_normals[3 * i + q] = gn[q];
            }
            total_k += sk;
            for (int j = 0; j < 3; ++j) {
                total_a[j] += sa[j];
                total_m[j] += sm[j];
            }
            for (int q = 0; q < 3 * K; ++q) {
                total_c[q] += sc[q];
                total_d[q] += sd[q];
            }
        }
        double* s = sums.data() + static_cast<size_t>(omp_get_thread_num()) * width;
        s[0] = total_k;
        for (int j = 0; j < 3; ++j) {
            s[1 + j] = total_a[j];
            s[4 + 6 * K + j] = total_m[j];
        }
        for (int q = 0; q < 3 * K; ++q) {
            s[4 + q] = total_c[q];
            s[4 + 3 * K + q] = total_d[q];
        }
    }
    std::fill(g_k, g_k + 1, 0.0);
    std::fill(g_a, g_a + 3, 0.0);
    std::fill(g_c, g_c + 3 * K, 0.0);
    std::fill(g_d, g_d + 3 * K, 0.0);
    std::fill(g_m, g_m + 3, 0.0);
    for (int th = 0; th < threads; ++th) {  // in thread order: the same sums on every run
        const double* s = sums.data() + static_cast<size_t>(th) * width;
        g_k[0] += s[0];
        for (int j = 0; j < 3; ++j) g_a[j] += s[1 + j];
        for (int q = 0; q < 3 * K; ++q) {
            g_c[q] += s[4 + q];
            g_d[q] += s[4 + 3 * K + q];
        }
        for (int j = 0; j < 3; ++j) g_m[j] += s[4 + 6 * K + j];
    }
}

}  // namespace stg_shade
