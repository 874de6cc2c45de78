// CPU SSIM kernels (see image_filter.h for the contract).
//
// Forward, one output row q at a time (rows are independent, so threads split them):
//   vertical   the kWindow input rows q..q+kWindow-1 of a and b are filtered column-wise into
//              five row buffers (a, b, a*a, b*b, a*b; the products are formed on the fly, never
//              stored as images), full width W*C.
//   horizontal each of the five buffers is filtered along the row (a tap is an offset of C
//              floats: channels stay interleaved), and the SSIM of the window, its row sum and
//              (when a gradient is wanted) its three derivative maps are computed in the same
//              loop: nothing of the blurred statistics is written to memory.
// Backward, one input row i at a time: the transposed ('full') filter of the three derivative
// maps, vertical first (rows outside the map read a shared zero row), into row buffers padded
// by (kWindow-1)*C zeros on both sides, then horizontal, combined with a and b in the same loop.
//
// The loops over a row have fixed tap counts and no branches, so they vectorise (AVX2 with the
// build's x86-64-v3 flags); row sums of S are vectorised reductions in double (omp simd).
// Floating-point contraction is off for the whole extension (build.py), so multiply-adds are
// fused explicitly where the target has FMA.
#include "image_filter.h"

#include <cmath>
#include <cstddef>
#include <vector>

namespace stg_image {
namespace {

#ifdef __FMA__
#define STG_IMG_MADD(a, b, c) __builtin_fmaf((a), (b), (c))
#else
#define STG_IMG_MADD(a, b, c) ((a) * (b) + (c))
#endif

constexpr int kHalo = kWindow - 1;  // rows/columns a window reaches beyond its first one

struct Taps {
    float k[kWindow];
    explicit Taps(const float* taps) {
        for (int t = 0; t < kWindow; ++t) k[t] = taps[t];
    }
};

// Column-wise filter of kWindow consecutive rows (stride n) of a and b, with the products.
void vertical_moments(const float* __restrict a, const float* __restrict b, int64_t n, const Taps& taps,
                      float* __restrict va, float* __restrict vb, float* __restrict vaa,
                      float* __restrict vbb, float* __restrict vab) {
    const float* k = taps.k;
#pragma omp simd
    for (int64_t j = 0; j < n; ++j) {
        float sa = 0.0f, sb = 0.0f, saa = 0.0f, sbb = 0.0f, sab = 0.0f;
#pragma GCC unroll 16
        for (int t = 0; t < kWindow; ++t) {
            const float x = a[t * n + j];
            const float y = b[t * n + j];
            const float wx = k[t] * x;
            const float wy = k[t] * y;
            sa += wx;
            sb += wy;
            saa = STG_IMG_MADD(wx, x, saa);
            sbb = STG_IMG_MADD(wy, y, sbb);
            sab = STG_IMG_MADD(wx, y, sab);
        }
        va[j] = sa;
        vb[j] = sb;
        vaa[j] = saa;
        vbb[j] = sbb;
        vab[j] = sab;
    }
}

// Horizontal filter of the five column-filtered rows and the SSIM of each window; returns the
// row's sum of S. With kGrad, also writes the derivatives of scale * S (see the header).
template <bool kGrad>
double horizontal_ssim(const float* __restrict va, const float* __restrict vb, const float* __restrict vaa,
                       const float* __restrict vbb, const float* __restrict vab, int64_t m, int64_t c,
                       const Taps& taps, float c1, float c2, float scale, float* __restrict d_mu,
                       float* __restrict d_var, float* __restrict d_cov) {
    const float* k = taps.k;
    double sum = 0.0;
#pragma omp simd reduction(+ : sum)
    for (int64_t j = 0; j < m; ++j) {
        float mu_a = 0.0f, mu_b = 0.0f, e_aa = 0.0f, e_bb = 0.0f, e_ab = 0.0f;
#pragma GCC unroll 16
        for (int t = 0; t < kWindow; ++t) {
            const int64_t at = j + t * c;
            mu_a = STG_IMG_MADD(k[t], va[at], mu_a);
            mu_b = STG_IMG_MADD(k[t], vb[at], mu_b);
            e_aa = STG_IMG_MADD(k[t], vaa[at], e_aa);
            e_bb = STG_IMG_MADD(k[t], vbb[at], e_bb);
            e_ab = STG_IMG_MADD(k[t], vab[at], e_ab);
        }
        const float mu_aa = mu_a * mu_a, mu_bb = mu_b * mu_b, mu_ab = mu_a * mu_b;
        const float num_l = 2.0f * mu_ab + c1;                     // luminance numerator
        const float num_cs = 2.0f * (e_ab - mu_ab) + c2;           // contrast-structure numerator
        const float inv_l = 1.0f / (mu_aa + mu_bb + c1);           // 1 / luminance denominator
        const float inv_cs = 1.0f / ((e_aa - mu_aa) + (e_bb - mu_bb) + c2);
        const float s = num_l * num_cs * inv_l * inv_cs;
        sum += static_cast<double>(s);
        if (kGrad) {
            const float dv = -s * inv_cs;                          // dS / d var_a
            const float dc = 2.0f * num_l * inv_l * inv_cs;        // dS / d cov
            // dS / d mu_a through the luminance term, then through var_a = E[a^2] - mu_a^2 and
            // cov = E[ab] - mu_a mu_b (E[a^2], E[ab] are the independent statistics).
            const float dm_direct = 2.0f * (mu_b * num_cs * inv_l * inv_cs - mu_a * s * inv_l);
            const float dm = dm_direct - 2.0f * mu_a * dv - mu_b * dc;
            d_mu[j] = scale * dm;
            d_var[j] = scale * dv;
            d_cov[j] = scale * dc;
        }
    }
    return sum;
}

// Column-wise transposed filter: out[j] = sum_t k[t] rows[t][j] (rows already chosen, zero rows
// standing in outside the map).
void vertical_transposed(const float* const* rm, const float* const* rv, const float* const* rc, int64_t m,
                         const Taps& taps, float* __restrict om, float* __restrict ov, float* __restrict oc) {
    const float* k = taps.k;
#pragma omp simd
    for (int64_t j = 0; j < m; ++j) {
        float sm = 0.0f, sv = 0.0f, sc = 0.0f;
#pragma GCC unroll 16
        for (int t = 0; t < kWindow; ++t) {
            sm = STG_IMG_MADD(k[t], rm[t][j], sm);
            sv = STG_IMG_MADD(k[t], rv[t][j], sv);
            sc = STG_IMG_MADD(k[t], rc[t][j], sc);
        }
        om[j] = sm;
        ov[j] = sv;
        oc[j] = sc;
    }
}

// Row-wise transposed filter of the three padded rows, combined into the gradient of the row.
void horizontal_transposed_grad(const float* __restrict pm, const float* __restrict pv,
                                const float* __restrict pc, const float* __restrict a,
                                const float* __restrict b, int64_t n, int64_t c, const Taps& taps, float g,
                                float l1_grad, float* __restrict out) {
    const float* k = taps.k;
#pragma omp simd
    for (int64_t j = 0; j < n; ++j) {
        float tm = 0.0f, tv = 0.0f, tc = 0.0f;
#pragma GCC unroll 16
        for (int t = 0; t < kWindow; ++t) {
            const int64_t at = j + (kHalo - t) * c;
            tm = STG_IMG_MADD(k[t], pm[at], tm);
            tv = STG_IMG_MADD(k[t], pv[at], tv);
            tc = STG_IMG_MADD(k[t], pc[at], tc);
        }
        // + the L1 term's l1_grad * sign(a - b), 0 where they are equal (torch's abs backward)
        const float sign = static_cast<float>(a[j] > b[j]) - static_cast<float>(a[j] < b[j]);
        out[j] = STG_IMG_MADD(l1_grad, sign, g * (tm + 2.0f * a[j] * tv + b[j] * tc));
    }
}

}  // namespace

double abs_diff_sum(const float* a, const float* b, int64_t count) {
    double total = 0.0;
    constexpr int64_t kBlock = 4096;  // float sums of short blocks, added in double: exact enough, vectorised
    for (int64_t start = 0; start < count; start += kBlock) {
        const int64_t end = start + kBlock < count ? start + kBlock : count;
        float block = 0.0f;
#pragma omp simd reduction(+ : block)
        for (int64_t j = start; j < end; ++j) block += a[j] > b[j] ? a[j] - b[j] : b[j] - a[j];
        total += static_cast<double>(block);
    }
    return total;
}

double charbonnier_flow(const float* r, const float* alpha, const float* o, const bool* valid, int64_t n,
                        float alpha_min, float eps, float scale, int64_t* count, float* g_r, float* g_alpha) {
    double total = 0.0;
    int64_t used = 0;
    const float eps2 = eps * eps;
    for (int64_t p = 0; p < n; ++p) {
        const float a = alpha[p];
        if (!valid[p] || !(a > alpha_min)) {  // also skips a NaN alpha, as alpha > alpha_min does
            if (g_r != nullptr) {
                g_r[2 * p] = g_r[2 * p + 1] = 0.0f;
                g_alpha[p] = 0.0f;
            }
            continue;
        }
        const float inv = 1.0f / a;
        const float dx = r[2 * p] * inv - o[2 * p];
        const float dy = r[2 * p + 1] * inv - o[2 * p + 1];
        const float d = std::sqrt(dx * dx + dy * dy + eps2);
        total += static_cast<double>(d);
        ++used;
        if (g_r != nullptr) {
            const float ux = scale * dx / d, uy = scale * dy / d;  // d(scale d) / d(r / alpha)
            g_r[2 * p] = ux * inv;
            g_r[2 * p + 1] = uy * inv;
            g_alpha[p] = -(ux * r[2 * p] + uy * r[2 * p + 1]) * inv * inv;
        }
    }
    *count = used;
    return total;
}

void ssim_forward(const float* a, const float* b, int64_t height, int64_t width, int64_t channels,
                  const float* taps, float c1, float c2, float scale, int threads, double* row_sums,
                  float* d_mu, float* d_var, float* d_cov) {
    const Taps k(taps);
    const int64_t n = width * channels;                    // floats per input row
    const int64_t out_rows = height - kHalo;
    const int64_t m = (width - kHalo) * channels;          // floats per output row
    const bool grad = d_mu != nullptr;
#pragma omp parallel num_threads(threads)
    {
        std::vector<float> scratch(static_cast<std::size_t>(5 * n));
        float* va = scratch.data();
        float* vb = va + n;
        float* vaa = vb + n;
        float* vbb = vaa + n;
        float* vab = vbb + n;
#pragma omp for schedule(static)
        for (int64_t q = 0; q < out_rows; ++q) {
            vertical_moments(a + q * n, b + q * n, n, k, va, vb, vaa, vbb, vab);
            if (grad) {
                row_sums[q] = horizontal_ssim<true>(va, vb, vaa, vbb, vab, m, channels, k, c1, c2, scale,
                                                    d_mu + q * m, d_var + q * m, d_cov + q * m);
            } else {
                row_sums[q] = horizontal_ssim<false>(va, vb, vaa, vbb, vab, m, channels, k, c1, c2, scale,
                                                     nullptr, nullptr, nullptr);
            }
        }
    }
}

void ssim_backward(const float* a, const float* b, int64_t height, int64_t width, int64_t channels,
                   const float* taps, const float* d_mu, const float* d_var, const float* d_cov, float g,
                   float l1_grad, int threads, float* grad_a) {
    const Taps k(taps);
    const int64_t n = width * channels;
    const int64_t out_rows = height - kHalo;
    const int64_t m = (width - kHalo) * channels;
    const int64_t pad = kHalo * channels;
    const std::vector<float> zeros(static_cast<std::size_t>(m), 0.0f);
#pragma omp parallel num_threads(threads)
    {
        const int64_t padded = m + 2 * pad;  // = n + pad
        std::vector<float> scratch(static_cast<std::size_t>(3 * padded), 0.0f);  // the pads stay zero
        float* pm = scratch.data();
        float* pv = pm + padded;
        float* pc = pv + padded;
        const float* rows_m[kWindow];
        const float* rows_v[kWindow];
        const float* rows_c[kWindow];
#pragma omp for schedule(static)
        for (int64_t i = 0; i < height; ++i) {
            for (int t = 0; t < kWindow; ++t) {  // output row i - t reads input row i with tap t
                const int64_t q = i - t;
                const bool inside = q >= 0 && q < out_rows;
                rows_m[t] = inside ? d_mu + q * m : zeros.data();
                rows_v[t] = inside ? d_var + q * m : zeros.data();
                rows_c[t] = inside ? d_cov + q * m : zeros.data();
            }
            vertical_transposed(rows_m, rows_v, rows_c, m, k, pm + pad, pv + pad, pc + pad);
            horizontal_transposed_grad(pm, pv, pc, a + i * n, b + i * n, n, channels, k, g, l1_grad,
                                       grad_a + i * n);
        }
    }
}

}  // namespace stg_image
