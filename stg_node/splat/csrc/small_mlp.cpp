// The small MLP kernels (see small_mlp.h for the contract).
//
// Rows are processed in blocks of kBlock: a block's activations stay in the first-level caches
// from one layer to the next, and every product is one register-tiled loop (4 rows x 16 columns
// of accumulators, the weights' row broadcast against 8-lane vectors). Bias and activation are
// applied in the same pass over the block. Widths are padded to 8 floats inside (padding columns
// hold zeros). The backward pass gathers the rows whose output gradient is not all zero, and
// per block: the activation derivative from the saved outputs, dW += gz^T h and db += sum gz
// into per-thread buffers, and gz W for the layer below. The per-thread buffers are summed in
// thread order at the end.
#include "small_mlp.h"

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <vector>

#include "fast_math.h"

namespace stg_mlp {
namespace {

using stg_math::v8_load;
using stg_math::v8_madd;
using stg_math::v8_splat;
using stg_math::v8_store;
using stg_math::v8f;

constexpr int kBlock = 64;  // rows per block
constexpr float kPi = 3.14159265358979323846f;

// C[RT x 8CT] (+)= A[RT x K] B[K x 8CT], strides in floats (A's entry (r, k) at r lda + k ka).
template <int RT, int CT>
inline void gemm_tile(int K, const float* A, int64_t lda, int64_t ka, const float* B, int64_t ldb, float* C,
                      int64_t ldc, bool accumulate) {
    v8f c[RT][CT];
    for (int r = 0; r < RT; ++r)
        for (int t = 0; t < CT; ++t) c[r][t] = accumulate ? v8_load(C + r * ldc + t * 8) : v8_splat(0.0f);
    for (int k = 0; k < K; ++k) {
        v8f b[CT];
        for (int t = 0; t < CT; ++t) b[t] = v8_load(B + k * ldb + t * 8);
        for (int r = 0; r < RT; ++r) {
            const v8f a = v8_splat(A[r * lda + k * ka]);
            for (int t = 0; t < CT; ++t) c[r][t] = v8_madd(a, b[t], c[r][t]);
        }
    }
    for (int r = 0; r < RT; ++r)
        for (int t = 0; t < CT; ++t) v8_store(C + r * ldc + t * 8, c[r][t]);
}

#if defined(__x86_64__) && defined(__GNUC__) && defined(__FMA__)
// The same products on 16-lane AVX-512 vectors, for CPUs that have them (chosen at run time, see
// wide_vectors(): the build stays portable). Each output column still sums its K products in the
// same order with the same fused multiply-adds, so the result equals the 8-lane path's bit for bit;
// what changes is how many columns one instruction carries (a 64-wide layer is one row of 4 vectors).
#define STG_MLP_WIDE 1
#define STG_WIDE_TARGET __attribute__((target("avx512f")))

template <int RT, int CT>
STG_WIDE_TARGET inline void gemm_tile16(int K, const float* A, int64_t lda, int64_t ka, const float* B, int64_t ldb, float* C,
                                        int64_t ldc, bool accumulate) {
    __m512 c[RT][CT];
    for (int r = 0; r < RT; ++r)
        for (int t = 0; t < CT; ++t) c[r][t] = accumulate ? _mm512_loadu_ps(C + r * ldc + t * 16) : _mm512_setzero_ps();
    for (int k = 0; k < K; ++k) {
        __m512 b[CT];
        for (int t = 0; t < CT; ++t) b[t] = _mm512_loadu_ps(B + k * ldb + t * 16);
        for (int r = 0; r < RT; ++r) {
            const __m512 a = _mm512_set1_ps(A[r * lda + k * ka]);
            for (int t = 0; t < CT; ++t) c[r][t] = _mm512_fmadd_ps(a, b[t], c[r][t]);
        }
    }
    for (int r = 0; r < RT; ++r)
        for (int t = 0; t < CT; ++t) _mm512_storeu_ps(C + r * ldc + t * 16, c[r][t]);
}

template <int RT>
STG_WIDE_TARGET inline void gemm_rows16(int nc, int K, const float* A, int64_t lda, int64_t ka, const float* B, int64_t ldb,
                                        float* C, int64_t ldc, bool accumulate) {
    int j = 0;
    for (; j + 64 <= nc; j += 64) gemm_tile16<RT, 4>(K, A, lda, ka, B + j, ldb, C + j, ldc, accumulate);
    switch ((nc - j) / 16) {
        case 3:
            gemm_tile16<RT, 3>(K, A, lda, ka, B + j, ldb, C + j, ldc, accumulate);
            break;
        case 2:
            gemm_tile16<RT, 2>(K, A, lda, ka, B + j, ldb, C + j, ldc, accumulate);
            break;
        case 1:
            gemm_tile16<RT, 1>(K, A, lda, ka, B + j, ldb, C + j, ldc, accumulate);
            break;
        default:
            break;
    }
}

// C[m x nc] (+)= A[m x K] B[K x nc] with nc a multiple of 16.
STG_WIDE_TARGET void gemm16(int m, int nc, int K, const float* A, int64_t lda, int64_t ka, const float* B, int64_t ldb, float* C,
                            int64_t ldc, bool accumulate) {
    int i = 0;
    for (; i + 4 <= m; i += 4) gemm_rows16<4>(nc, K, A + i * lda, lda, ka, B, ldb, C + i * ldc, ldc, accumulate);
    for (; i < m; ++i) gemm_rows16<1>(nc, K, A + i * lda, lda, ka, B, ldb, C + i * ldc, ldc, accumulate);
}
#endif

// Whether the products run on 16-lane vectors: the CPU (and its OS) has AVX-512F and
// STG_SPLAT_NO_AVX512 is not set (the switch the tests use to compare the two paths).
bool wide_vectors() {
#ifdef STG_MLP_WIDE
    return stg_avx512_allowed();
#else
    return false;
#endif
}

// C[m x nc] (+)= A[m x K] B[K x nc] with nc a multiple of 8; `wide`: wide_vectors().
void gemm(int m, int nc, int K, const float* A, int64_t lda, int64_t ka, const float* B, int64_t ldb, float* C,
          int64_t ldc, bool accumulate, bool wide) {
#ifdef STG_MLP_WIDE
    if (wide && nc % 16 == 0) {
        gemm16(m, nc, K, A, lda, ka, B, ldb, C, ldc, accumulate);
        return;
    }
#else
    (void)wide;
#endif
    int i = 0;
    for (; i + 4 <= m; i += 4) {
        int j = 0;
        for (; j + 16 <= nc; j += 16)
            gemm_tile<4, 2>(K, A + i * lda, lda, ka, B + j, ldb, C + i * ldc + j, ldc, accumulate);
        for (; j < nc; j += 8) gemm_tile<4, 1>(K, A + i * lda, lda, ka, B + j, ldb, C + i * ldc + j, ldc, accumulate);
    }
    for (; i < m; ++i) {
        int j = 0;
        for (; j + 16 <= nc; j += 16)
            gemm_tile<1, 2>(K, A + i * lda, lda, ka, B + j, ldb, C + i * ldc + j, ldc, accumulate);
        for (; j < nc; j += 8) gemm_tile<1, 1>(K, A + i * lda, lda, ka, B + j, ldb, C + i * ldc + j, ldc, accumulate);
    }
}

inline float activate(int act, float z) {
    switch (act) {
        case kRelu:
            return z > 0.0f ? z : 0.0f;
        case kSigmoid:
            return 1.0f / (1.0f + stg_math::fast_exp(-z));
        case kTanh: {
            const float e = stg_math::fast_exp(-2.0f * std::fabs(z));
            const float t = (1.0f - e) / (1.0f + e);
            return z < 0.0f ? -t : t;
        }
        default:
            return z;
    }
}

// d act / d z from the activation's output y.
inline float derivative(int act, float y) {
    switch (act) {
        case kRelu:
            return y > 0.0f ? 1.0f : 0.0f;
        case kSigmoid:
            return y * (1.0f - y);
        case kTanh:
            return 1.0f - y * y;
        default:
            return 1.0f;
    }
}

// rows x width (stride `ld`) <- act(rows + bias), padding columns [width, ld) set to zero.
void bias_activation(int rows, int width, int ld, const float* bias, int act, float* y) {
    for (int r = 0; r < rows; ++r) {
        float* row = y + static_cast<int64_t>(r) * ld;
        switch (act) {
            case kRelu:
#pragma omp simd
                for (int j = 0; j < width; ++j) {
                    const float z = row[j] + bias[j];
                    row[j] = z > 0.0f ? z : 0.0f;
                }
                break;
            case kIdentity:
#pragma omp simd
                for (int j = 0; j < width; ++j) row[j] += bias[j];
                break;
            default:
#pragma omp simd
                for (int j = 0; j < width; ++j) row[j] = activate(act, row[j] + bias[j]);
        }
        for (int j = width; j < ld; ++j) row[j] = 0.0f;
    }
}

// The weights in the two layouts the products need, padded with zeros:
//   wt[l]: W_l^T, dims[l] x padded(dims[l+1])      (forward: x W^T)
//   wp[l]: W_l,   dims[l+1] x padded(dims[l])      (backward: gz W)
struct PaddedWeights {
    std::vector<std::vector<float>> wt, wp, bias;
};

PaddedWeights pad_weights(const MlpShape& s, const float* const* weights, const float* const* biases,
                          bool transposed, bool plain) {
    PaddedWeights p;
    p.wt.resize(s.layers);
    p.wp.resize(s.layers);
    p.bias.resize(s.layers);
    for (int l = 0; l < s.layers; ++l) {
        const int din = s.dims[l], dout = s.dims[l + 1];
        const float* W = weights[l];
        p.bias[l].assign(padded(dout), 0.0f);
        if (biases != nullptr && biases[l] != nullptr) std::copy(biases[l], biases[l] + dout, p.bias[l].begin());
        if (transposed) {
            const int ld = padded(dout);
            p.wt[l].assign(static_cast<size_t>(din) * ld, 0.0f);
            for (int j = 0; j < dout; ++j)
                for (int k = 0; k < din; ++k) p.wt[l][static_cast<size_t>(k) * ld + j] = W[j * din + k];
        }
        if (plain) {
            const int ld = padded(din);
            p.wp[l].assign(static_cast<size_t>(dout) * ld, 0.0f);
            for (int j = 0; j < dout; ++j)
                std::copy(W + static_cast<size_t>(j) * din, W + static_cast<size_t>(j + 1) * din,
                          p.wp[l].begin() + static_cast<size_t>(j) * ld);
        }
    }
    return p;
}

// sin and cos of a (|a| well under 1e6) in double, without a libm call or a branch (loops over it
// vectorise): the quadrant by the nearest multiple of pi/2, then Taylor polynomials on
// [-pi/4, pi/4] (error under 1e-13).
inline void sincos_double(double a, double* sin_out, double* cos_out) {
    const double q = std::nearbyint(a * 0.63661977236758134308);  // 2 / pi
    const double r = a - q * 1.57079632679489661923;
    const double r2 = r * r;
    const double sr =
        r * (1.0 + r2 * (-1.0 / 6 + r2 * (1.0 / 120 + r2 * (-1.0 / 5040 + r2 * (1.0 / 362880 +
        r2 * (-1.0 / 39916800 + r2 * (1.0 / 6227020800.0)))))));
    const double cr = 1.0 + r2 * (-1.0 / 2 + r2 * (1.0 / 24 + r2 * (-1.0 / 720 + r2 * (1.0 / 40320 +
                      r2 * (-1.0 / 3628800 + r2 * (1.0 / 479001600.0 + r2 * (-1.0 / 87178291200.0)))))));
    // a = r + quadrant pi/2: (sin, cos) = (sr, cr), (cr, -sr), (-sr, -cr), (-cr, sr)
    const double quadrant = q - 4.0 * std::floor(q * 0.25);  // 0, 1, 2 or 3
    const bool odd = quadrant == 1.0 || quadrant == 3.0;
    const double s = odd ? cr : sr;
    const double c = odd ? sr : cr;
    *sin_out = quadrant >= 2.0 ? -s : s;
    *cos_out = (quadrant == 1.0 || quadrant == 2.0) ? -c : c;
}

// The real SH basis of 3DGS (stg_node/splat/sh.py, its reference) of a unit direction (x, y, z):
// the first `bands` of the (degree + 1)^2 values, the rest zero.
constexpr float kShC0 = 0.28209479177387814f, kShC1 = 0.4886025119029199f;
constexpr float kShC2[5] = {1.0925484305920792f, -1.0925484305920792f, 0.31539156525252005f,
                            -1.0925484305920792f, 0.5462742152960396f};
constexpr float kShC3[7] = {-0.5900435899266435f, 2.890611442640554f, -0.4570457994644658f, 0.3731763325901154f,
                            -0.4570457994644658f, 1.445305721320277f, -0.5900435899266435f};

inline void sh_basis(int degree, int bands, float x, float y, float z, float* out) {
    float v[16];
    v[0] = kShC0;
    if (degree >= 1) {
        v[1] = -kShC1 * y;
        v[2] = kShC1 * z;
        v[3] = -kShC1 * x;
    }
    const float xx = x * x, yy = y * y, zz = z * z;
    if (degree >= 2) {
        v[4] = kShC2[0] * (x * y);
        v[5] = kShC2[1] * (y * z);
        v[6] = kShC2[2] * (2.0f * zz - xx - yy);
        v[7] = kShC2[3] * (x * z);
        v[8] = kShC2[4] * (xx - yy);
    }
    if (degree >= 3) {
        v[9] = kShC3[0] * y * (3.0f * xx - yy);
        v[10] = kShC3[1] * (x * y) * z;
        v[11] = kShC3[2] * y * (4.0f * zz - xx - yy);
        v[12] = kShC3[3] * z * (2.0f * zz - 3.0f * xx - 3.0f * yy);
        v[13] = kShC3[4] * x * (4.0f * zz - xx - yy);
        v[14] = kShC3[5] * z * (xx - yy);
        v[15] = kShC3[6] * x * (xx - 3.0f * yy);
    }
    const int k = (degree + 1) * (degree + 1);
    for (int j = 0; j < k; ++j) out[j] = j < bands ? v[j] : 0.0f;
}

// dL/d(x, y, z) of sh_basis given dL/d(each value) `g` (the first `bands` count; the zeros take none).
inline void sh_basis_backward(int bands, float x, float y, float z, const float* g, float* g_dir) {
    float gx = 0.0f, gy = 0.0f, gz = 0.0f;
    auto at = [&](int j) { return j < bands ? g[j] : 0.0f; };
    if (bands > 1) {
        gx -= kShC1 * at(3);
        gy -= kShC1 * at(1);
        gz += kShC1 * at(2);
    }
    const float xx = x * x, yy = y * y, zz = z * z;
    if (bands > 4) {
        gx += kShC2[0] * y * at(4) + kShC2[3] * z * at(7) + kShC2[2] * -2.0f * x * at(6) + kShC2[4] * 2.0f * x * at(8);
        gy += kShC2[0] * x * at(4) + kShC2[1] * z * at(5) + kShC2[2] * -2.0f * y * at(6) - kShC2[4] * 2.0f * y * at(8);
        gz += kShC2[1] * y * at(5) + kShC2[3] * x * at(7) + kShC2[2] * 4.0f * z * at(6);
    }
    if (bands > 9) {
        const float g9 = at(9), g10 = at(10), g11 = at(11), g12 = at(12), g13 = at(13), g14 = at(14), g15 = at(15);
        gx += kShC3[0] * 6.0f * x * y * g9 + kShC3[1] * y * z * g10 + kShC3[2] * -2.0f * x * y * g11 +
              kShC3[3] * -6.0f * x * z * g12 + kShC3[4] * (4.0f * zz - 3.0f * xx - yy) * g13 +
              kShC3[5] * 2.0f * x * z * g14 + kShC3[6] * 3.0f * (xx - yy) * g15;
        gy += kShC3[0] * 3.0f * (xx - yy) * g9 + kShC3[1] * x * z * g10 + kShC3[2] * (4.0f * zz - xx - 3.0f * yy) * g11 +
              kShC3[3] * -6.0f * y * z * g12 + kShC3[4] * -2.0f * x * y * g13 + kShC3[5] * -2.0f * y * z * g14 +
              kShC3[6] * -6.0f * x * y * g15;
        gz += kShC3[1] * x * y * g10 + kShC3[2] * 8.0f * y * z * g11 + kShC3[3] * (6.0f * zz - 3.0f * xx - 3.0f * yy) * g12 +
              kShC3[4] * 8.0f * x * z * g13 + kShC3[5] * (xx - yy) * g14;
    }
    g_dir[0] = gx;
    g_dir[1] = gy;
    g_dir[2] = gz;
}

// `rows` raw rows (row r at raw + row(r) * raw_width) -> their encoded rows (see MlpShape) at
// dst (stride ld), padding columns [dims[0], ld) set to zero. torch's angle 2^k pi x is
// float(x * float(pi)) times 2^k exactly, so each frequency's sine and cosine follow from the
// first's by the double-angle formulas, carried in double and rounded once (one polynomial per
// value, over the block's rows at once, instead of 2 x freqs libm calls). A view direction's SH
// basis (MlpShape::view_degree) closes the row.
template <typename RowOf>
void encode_rows(const MlpShape& s, const float* raw, int rows, RowOf row, float* dst, int ld) {
    const int c = s.enc_cols, f = s.enc_freqs, d0 = s.dims[0], raw0 = raw_width(s), cf = c * f;
    const int k_view = view_columns(s), raw_dir = raw0 - (s.view_degree < 0 ? 0 : 3);
    double sn[kBlock], cs[kBlock];
    for (int i = 0; i < c; ++i) {
#pragma omp simd
        for (int r = 0; r < rows; ++r)
            sincos_double(static_cast<double>(raw[row(r) * raw0 + i] * kPi), &sn[r], &cs[r]);
        for (int k = 0; k < f; ++k) {
            const int j = c + i * f + k;
#pragma omp simd
            for (int r = 0; r < rows; ++r) {
                float* e = dst + static_cast<int64_t>(r) * ld;
                e[j] = static_cast<float>(sn[r]);
                e[j + cf] = static_cast<float>(cs[r]);
                const double doubled_sin = 2.0 * sn[r] * cs[r];
                cs[r] = (cs[r] - sn[r]) * (cs[r] + sn[r]);
                sn[r] = doubled_sin;
            }
        }
    }
    const int bands = (s.view_active + 1) * (s.view_active + 1);
    for (int r = 0; r < rows; ++r) {
        const float* in = raw + row(r) * raw0;
        float* e = dst + static_cast<int64_t>(r) * ld;
        std::copy(in, in + c, e);
        std::copy(in + c, in + raw_dir, e + c + 2 * cf);
        if (k_view > 0) sh_basis(s.view_degree, bands, in[raw_dir], in[raw_dir + 1], in[raw_dir + 2], e + d0 - k_view);
        std::fill(e + d0, e + ld, 0.0f);
    }
}

// dL/d(raw row) from dL/d(encoded row) `g`, the encoded row `e` (its sines and cosines) and the
// raw row `raw_row` (its view direction):
// dL/dx_i = g_i + sum_k 2^k pi (g_sin_ik cos_ik - g_cos_ik sin_ik); dL/dd through the SH basis;
// the rest passes through.
void encode_row_backward(const MlpShape& s, const float* raw_row, const float* e, const float* g, float* g_raw) {
    const int c = s.enc_cols, f = s.enc_freqs, cf = c * f;
    for (int i = 0; i < c; ++i) {
        float sum = g[i];
        float scale = kPi;  // 2^k pi
        for (int k = 0; k < f; ++k, scale *= 2.0f) {
            const int j = c + i * f + k;
            sum += scale * (g[j] * e[j + cf] - g[j + cf] * e[j]);
        }
        g_raw[i] = sum;
    }
    const int k_view = view_columns(s), raw0 = raw_width(s);
    const int raw_dir = raw0 - (k_view > 0 ? 3 : 0);
    std::copy(g + c + 2 * cf, g + c + 2 * cf + (raw_dir - c), g_raw + c);
    if (k_view > 0) {
        const int bands = (s.view_active + 1) * (s.view_active + 1);
        const float* d = raw_row + raw_dir;
        sh_basis_backward(bands, d[0], d[1], d[2], g + s.dims[0] - k_view, g_raw + raw_dir);
    }
}

// The raw rows rows_of(0..rows-1) (positions in the evaluated rows) gathered from the groups into
// dst [rows x raw_width], contiguous.
template <typename RowOf>
void gather_raw(const RawRows& x, int raw0, int rows, RowOf row, float* dst) {
    for (int r = 0; r < rows; ++r) {
        const int64_t i = row(r);
        const int64_t t = x.index != nullptr ? x.index[i] : i;
        float* d = dst + static_cast<int64_t>(r) * raw0;
        for (int g = 0; g < x.groups; ++g) {
            const int w = x.widths[g];
            std::copy(x.data[g] + t * w, x.data[g] + (t + 1) * w, d);
            d += w;
        }
    }
}

// One evaluated row's dL/d(raw row) `g_raw` handed to the groups that want it, at its table row.
void scatter_raw(const RawRows& x, int64_t i, const float* g_raw, float* const* g_groups) {
    const int64_t t = x.index != nullptr ? x.index[i] : i;
    for (int g = 0; g < x.groups; ++g) {
        const int w = x.widths[g];
        if (g_groups[g] != nullptr) std::copy(g_raw, g_raw + w, g_groups[g] + t * w);
        g_raw += w;
    }
}

}  // namespace

void mlp_forward(const MlpShape& s, const RawRows& x, const float* const* weights,
                 const float* const* biases, float* out, float* const* hidden) {
    const int L = s.layers;
    const PaddedWeights p = pad_weights(s, weights, biases, true, false);
    const bool wide = wide_vectors();
    const int64_t blocks = (s.rows + kBlock - 1) / kBlock;
    int widest = 0;
    for (int l = 1; l <= L; ++l) widest = std::max(widest, padded(s.dims[l]));
#pragma omp parallel num_threads(s.threads)
    {
        // two ping-pong buffers for the layers whose outputs are not kept
        std::vector<float> buf0(static_cast<size_t>(kBlock) * widest), buf1(buf0.size());
        // the block's raw rows, and its encoded input rows when the kernel encodes its input
        const int raw0 = raw_width(s);
        std::vector<float> raw(static_cast<size_t>(kBlock) * raw0);
        std::vector<float> enc(encodes(s) ? static_cast<size_t>(kBlock) * padded(s.dims[0]) : 0);
#pragma omp for schedule(static)
        for (int64_t blk = 0; blk < blocks; ++blk) {
            const int64_t r0 = blk * kBlock;
            const int rows = static_cast<int>(std::min<int64_t>(kBlock, s.rows - r0));
            gather_raw(x, raw0, rows, [r0](int r) { return r0 + r; }, raw.data());
            const float* in = raw.data();
            int64_t ld_in = raw0;
            if (encodes(s)) {
                const int ld = padded(s.dims[0]);
                encode_rows(s, raw.data(), rows, [](int r) { return static_cast<int64_t>(r); }, enc.data(), ld);
                in = enc.data();
                ld_in = ld;
            }
            for (int l = 0; l < L; ++l) {
                const int dout = s.dims[l + 1], ld = padded(dout);
                float* y;
                if (l < L - 1 && hidden != nullptr) {
                    y = hidden[l] + r0 * ld;
                } else {
                    y = (l % 2 == 0) ? buf0.data() : buf1.data();
                }
                gemm(rows, ld, s.dims[l], in, ld_in, 1, p.wt[l].data(), ld, y, ld, false, wide);
                bias_activation(rows, dout, ld, p.bias[l].data(), s.acts[l], y);
                in = y;
                ld_in = ld;
            }
            const int dl = s.dims[L];
            for (int r = 0; r < rows; ++r)
                std::copy(in + r * ld_in, in + r * ld_in + dl, out + (r0 + r) * dl);
        }
    }
}

void mlp_backward(const MlpShape& s, const RawRows& x, const float* const* weights,
                  const float* const* hidden, const float* out, const float* g_out, float* const* g_groups,
                  float* const* g_weights, float* const* g_biases) {
    const int L = s.layers;
    const int threads = std::max(1, s.threads);
    const int d0 = s.dims[0], dl = s.dims[L], raw0 = raw_width(s);
    const PaddedWeights p = pad_weights(s, weights, nullptr, false, true);
    const bool wide = wide_vectors();
    bool want_gx = false;
    for (int g = 0; g < x.groups; ++g) want_gx |= g_groups != nullptr && g_groups[g] != nullptr;
    // Rows with a non-zero output gradient; the others contribute nothing (their dL/dx stays zero).
    std::vector<int64_t> active;
    active.reserve(s.rows);
    for (int64_t r = 0; r < s.rows; ++r) {
        const float* g = g_out + r * dl;
        bool any = false;
        for (int j = 0; j < dl; ++j) any |= g[j] != 0.0f;
        if (any) active.push_back(r);
    }
    const int64_t n_active = static_cast<int64_t>(active.size());
    const int64_t blocks = (n_active + kBlock - 1) / kBlock;
    int widest = 0;
    for (int l = 0; l <= L; ++l) widest = std::max(widest, padded(s.dims[l]));
    // per-thread gradient buffers: dW_l (dims[l+1] x padded(dims[l])) and db_l
    std::vector<std::vector<std::vector<float>>> tw(threads), tb(threads);
#pragma omp parallel num_threads(threads)
    {
        const int tid = omp_get_thread_num();
        auto& dW = tw[tid];
        auto& db = tb[tid];
        dW.resize(L);
        db.resize(L);
        for (int l = 0; l < L; ++l) {
            dW[l].assign(static_cast<size_t>(s.dims[l + 1]) * padded(s.dims[l]), 0.0f);
            db[l].assign(padded(s.dims[l + 1]), 0.0f);
        }
        // the block's inputs (layer 0's and each hidden layer's), and its gradient
        std::vector<std::vector<float>> h(L);
        for (int l = 0; l < L; ++l) h[l].assign(static_cast<size_t>(kBlock) * padded(s.dims[l]), 0.0f);
        std::vector<float> gz(static_cast<size_t>(kBlock) * widest), gh(gz.size());
        std::vector<float> raw(static_cast<size_t>(kBlock) * raw0), g_raw(raw0);
#pragma omp for schedule(dynamic, 4)
        for (int64_t blk = 0; blk < blocks; ++blk) {
            const int64_t a0 = blk * kBlock;
            const int rows = static_cast<int>(std::min<int64_t>(kBlock, n_active - a0));
            const int64_t* idx = active.data() + a0;
            // gather: h[0] = the raw rows, encoded or padded; h[l] = hidden[l-1] rows
            gather_raw(x, raw0, rows, [idx](int r) { return idx[r]; }, raw.data());
            {
                const int ld = padded(d0);
                if (encodes(s)) {
                    encode_rows(s, raw.data(), rows, [](int r) { return static_cast<int64_t>(r); }, h[0].data(), ld);
                } else {
                    for (int r = 0; r < rows; ++r) {
                        float* dst = h[0].data() + static_cast<size_t>(r) * ld;
                        std::copy(raw.data() + static_cast<size_t>(r) * d0, raw.data() + static_cast<size_t>(r + 1) * d0,
                                  dst);
                        std::fill(dst + d0, dst + ld, 0.0f);
                    }
                }
            }
            for (int l = 1; l < L; ++l) {
                const int ld = padded(s.dims[l]);
                for (int r = 0; r < rows; ++r)
                    std::copy(hidden[l - 1] + idx[r] * ld, hidden[l - 1] + (idx[r] + 1) * ld,
                              h[l].data() + static_cast<size_t>(r) * ld);
            }
            // gz = dL/dout * act'(out)
            {
                const int ld = padded(dl);
                for (int r = 0; r < rows; ++r) {
                    const float* y = out + idx[r] * dl;
                    const float* g = g_out + idx[r] * dl;
                    float* dst = gz.data() + static_cast<size_t>(r) * ld;
                    for (int j = 0; j < dl; ++j) dst[j] = g[j] * derivative(s.acts[L - 1], y[j]);
                    for (int j = dl; j < ld; ++j) dst[j] = 0.0f;
                }
            }
            for (int l = L - 1; l >= 0; --l) {
                const int din = s.dims[l], dout = s.dims[l + 1];
                const int ldi = padded(din), ldo = padded(dout);
                // db += column sums of gz; dW += gz^T h[l]
                for (int r = 0; r < rows; ++r) {
                    const float* g = gz.data() + static_cast<size_t>(r) * ldo;
#pragma omp simd
                    for (int j = 0; j < dout; ++j) db[l][j] += g[j];
                }
                // gz^T read in place: row j of A is column j of gz (stride 1), its k-th entry row k's
                gemm(dout, ldi, rows, gz.data(), 1, ldo, h[l].data(), ldi, dW[l].data(), ldi, true, wide);
                if (l == 0 && !want_gx) break;
                // gh = gz W_l (rows x padded(din))
                gemm(rows, ldi, dout, gz.data(), ldo, 1, p.wp[l].data(), ldi, gh.data(), ldi, false, wide);
                if (l == 0) {
                    for (int r = 0; r < rows; ++r) {
                        const float* g = gh.data() + static_cast<size_t>(r) * ldi;
                        if (encodes(s)) {
                            encode_row_backward(s, raw.data() + static_cast<size_t>(r) * raw0,
                                                h[0].data() + static_cast<size_t>(r) * ldi, g, g_raw.data());
                            scatter_raw(x, idx[r], g_raw.data(), g_groups);
                        } else {
                            scatter_raw(x, idx[r], g, g_groups);
                        }
                    }
                    break;
                }
                // gz for the layer below: gh * act'_{l-1}(its output, = h[l])
                const int act = s.acts[l - 1];
                for (int r = 0; r < rows; ++r) {
                    const float* y = h[l].data() + static_cast<size_t>(r) * ldi;
                    const float* g = gh.data() + static_cast<size_t>(r) * ldi;
                    float* dst = gz.data() + static_cast<size_t>(r) * ldi;
                    if (act == kRelu) {
#pragma omp simd
                        for (int j = 0; j < ldi; ++j) dst[j] = y[j] > 0.0f ? g[j] : 0.0f;
                    } else {
                        for (int j = 0; j < din; ++j) dst[j] = g[j] * derivative(act, y[j]);
                        for (int j = din; j < ldi; ++j) dst[j] = 0.0f;
                    }
                }
            }
        }
    }
    for (int l = 0; l < L; ++l) {
        const int din = s.dims[l], dout = s.dims[l + 1], ldi = padded(din);
        if (g_weights != nullptr && g_weights[l] != nullptr) {
            for (int j = 0; j < dout; ++j)
                for (int k = 0; k < din; ++k) {
                    float sum = 0.0f;
                    for (int t = 0; t < threads; ++t)
                        if (!tw[t].empty()) sum += tw[t][l][static_cast<size_t>(j) * ldi + k];
                    g_weights[l][j * din + k] = sum;
                }
        }
        if (g_biases != nullptr && g_biases[l] != nullptr) {
            for (int j = 0; j < dout; ++j) {
                float sum = 0.0f;
                for (int t = 0; t < threads; ++t)
                    if (!tb[t].empty()) sum += tb[t][l][j];
                g_biases[l][j] = sum;
            }
        }
    }
}

}  // namespace stg_mlp
