// Fused linear blend skinning (see skinning.h for the maths and the contract).
//
// One pass per point: its B effective weights (the log-space correction included), the blended
// 3x4 transform and quaternion as one 16-float blend of the bones' rows, the world centre, the
// product with the point's local rotation and the canonical view direction. The backward pass
// recomputes the blend from the saved weights, runs the chain rule per point, and accumulates
// the bones' gradients in per-thread buffers (float over blocks of points, then double), summed
// in thread order at the end.
#include "skinning.h"

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <vector>

#include "fast_math.h"

namespace stg_skin {
namespace {

constexpr int kFlushEvery = 256;  // points between float -> double flushes of the bone gradients

// max_b x[b] over b < B >= 1, eight lanes at a time (a maximum is exact in any order; the compiler
// left the reduction scalar, a chain of B dependent maxima per point).
inline float row_max(const float* x, int B) {
    using stg_math::v8f;
    float m = x[0];
    int b = 1;
    if (B >= 8) {
        v8f v = stg_math::v8_load(x);
        for (b = 8; b + 8 <= B; b += 8) {
            const v8f y = stg_math::v8_load(x + b);
            v = v < y ? y : v;
        }
        m = v[0];
        for (int l = 1; l < 8; ++l) m = m < v[l] ? v[l] : m;
    }
    for (; b < B; ++b) m = m < x[b] ? x[b] : m;
    return m;
}

// Effective weights of one point into w (B floats); returns nothing, never divides by zero
// (the body's weights plus eps are positive).
inline void point_weights(const SkinShape& s, const float* sw, const float* delta, float* w) {
    const int B = s.bones;
    if (!s.has_delta) {
        for (int b = 0; b < B; ++b) w[b] = sw[b];
        return;
    }
    // (s + eps) exp(d - max d) / sum: the same ratio as without the shift, never overflowing.
    const float dmax = row_max(delta, B);
    float total = 0.0f;
#pragma omp simd reduction(+ : total)
    for (int b = 0; b < B; ++b) {
        const float e = (sw[b] + s.weight_eps) * stg_math::fast_exp(delta[b] - dmax);
        w[b] = e;
        total += e;
    }
    const float inv = 1.0f / total;
    for (int b = 0; b < B; ++b) w[b] *= inv;
}

// blend[16] = sum_b w_b bones[b, :], in four interleaved partial sums (a chain of B dependent
// multiply-adds would wait on each one's latency).
inline void blend_bones(int B, const float* w, const float* bones, float* blend) {
    using stg_math::v8_load;
    using stg_math::v8_madd;
    using stg_math::v8_splat;
    using stg_math::v8f;
    static_assert(kBoneStride == 16, "two vectors per bone");
    v8f acc[4][2] = {};
    int b = 0;
    for (; b + 4 <= B; b += 4) {
        for (int j = 0; j < 4; ++j) {
            const float* row = bones + static_cast<int64_t>(b + j) * kBoneStride;
            const v8f wb = v8_splat(w[b + j]);
            acc[j][0] = v8_madd(wb, v8_load(row), acc[j][0]);
            acc[j][1] = v8_madd(wb, v8_load(row + 8), acc[j][1]);
        }
    }
    for (; b < B; ++b) {
        const float* row = bones + static_cast<int64_t>(b) * kBoneStride;
        const v8f wb = v8_splat(w[b]);
        acc[0][0] = v8_madd(wb, v8_load(row), acc[0][0]);
        acc[0][1] = v8_madd(wb, v8_load(row + 8), acc[0][1]);
    }
    stg_math::v8_store(blend, (acc[0][0] + acc[1][0]) + (acc[2][0] + acc[3][0]));
    stg_math::v8_store(blend + 8, (acc[0][1] + acc[1][1]) + (acc[2][1] + acc[3][1]));
}

// gw[b] (+)= sum_k g[k] cols[k * B + b] over k < K for every b < B, in k order per b with fused
// multiply-adds (the same values as an axpy over b per k), the sums held in registers for up to 32
// bones at a time: an axpy per k through memory waits on a store-to-load forward per k.
template <int NV>
inline void weight_grads_block(int B, int K, const float* g, const float* cols, float* gw, bool accumulate) {
    using stg_math::v8_load;
    using stg_math::v8_madd;
    using stg_math::v8_splat;
    using stg_math::v8f;
    v8f acc[NV];
    for (int v = 0; v < NV; ++v) acc[v] = accumulate ? v8_load(gw + 8 * v) : v8_splat(0.0f);
    for (int k = 0; k < K; ++k) {
        const v8f gk = v8_splat(g[k]);
        const float* col = cols + static_cast<int64_t>(k) * B;
        for (int v = 0; v < NV; ++v) acc[v] = v8_madd(gk, v8_load(col + 8 * v), acc[v]);
    }
    for (int v = 0; v < NV; ++v) stg_math::v8_store(gw + 8 * v, acc[v]);
}

inline void weight_grads(int B, int K, const float* g, const float* cols, float* gw, bool accumulate) {
    int b = 0;
    for (; b + 32 <= B; b += 32) weight_grads_block<4>(B, K, g, cols + b, gw + b, accumulate);
    switch ((B - b) / 8) {
        case 3:
            weight_grads_block<3>(B, K, g, cols + b, gw + b, accumulate);
            break;
        case 2:
            weight_grads_block<2>(B, K, g, cols + b, gw + b, accumulate);
            break;
        case 1:
            weight_grads_block<1>(B, K, g, cols + b, gw + b, accumulate);
            break;
        default:
            break;
    }
    for (b += (B - b) / 8 * 8; b < B; ++b) {
        float a = accumulate ? gw[b] : 0.0f;
        for (int k = 0; k < K; ++k) a = STG_MADD(g[k], cols[static_cast<int64_t>(k) * B + b], a);
        gw[b] = a;
    }
}

inline float norm4(const float* q) {
    return std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
}

// Hamilton product a * b of wxyz quaternions.
inline void quat_mul(const float* a, const float* b, float* o) {
    o[0] = a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3];
    o[1] = a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2];
    o[2] = a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1];
    o[3] = a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0];
}

// The normalised local rotation (identity when its norm is at most eps); returns the norm.
inline float local_rotation(const SkinShape& s, const float* l, float* ln) {
    const float norm = norm4(l);
    if (norm > s.quat_eps) {
        const float inv = 1.0f / norm;
        for (int k = 0; k < 4; ++k) ln[k] = l[k] * inv;
    } else {
        ln[0] = 1.0f;
        ln[1] = ln[2] = ln[3] = 0.0f;
    }
    return norm;
}

}  // namespace

void skin_forward(const SkinShape& s, const float* means, const float* skin_weights,
                  const float* skin_delta, const float* bones, const float* local_quats,
                  const float* camera, float* world, float* quats, float* view, float* weights,
                  float* blend_norm2, float* blends, const SecondFrame& second) {
    const int B = s.bones;
    const int frames = second.bones != nullptr ? 2 : 1;
#pragma omp parallel num_threads(s.threads)
    {
        std::vector<float> wbuf(B);
#pragma omp for schedule(static)
        for (int64_t i = 0; i < s.n; ++i) {
            float* w = weights ? weights + i * B : wbuf.data();
            point_weights(s, skin_weights + i * B, s.has_delta ? skin_delta + i * B : nullptr, w);
            float bl[kBoneStride];
            blend_bones(B, w, bones, bl);
            if (blends != nullptr) std::copy(bl, bl + kBoneStride, blends + i * frames * kBoneStride);
            const float* x = means + i * 3;
            float p[3];
            for (int r = 0; r < 3; ++r)
                p[r] = bl[r * 4] * x[0] + bl[r * 4 + 1] * x[1] + bl[r * 4 + 2] * x[2] + bl[r * 4 + 3];
            for (int r = 0; r < 3; ++r) world[i * 3 + r] = p[r];
            if (second.bones != nullptr) {  // the other frame, same weights
                float bl2[kBoneStride];
                blend_bones(B, w, second.bones, bl2);
                if (blends != nullptr) std::copy(bl2, bl2 + kBoneStride, blends + (i * 2 + 1) * kBoneStride);
                const float* x2 = second.means + i * 3;
                for (int r = 0; r < 3; ++r)
                    second.world[i * 3 + r] =
                        bl2[r * 4] * x2[0] + bl2[r * 4 + 1] * x2[1] + bl2[r * 4 + 2] * x2[2] + bl2[r * 4 + 3];
            }
            if (!s.rotations) continue;
            const float* qr = bl + 12;
            if (blend_norm2 != nullptr)
                blend_norm2[i] = qr[0] * qr[0] + qr[1] * qr[1] + qr[2] * qr[2] + qr[3] * qr[3];
            const float inv = 1.0f / std::max(norm4(qr), s.quat_eps);
            const float qn[4] = {qr[0] * inv, qr[1] * inv, qr[2] * inv, qr[3] * inv};
            if (s.has_local) {
                float ln[4];
                local_rotation(s, local_quats + i * 4, ln);
                quat_mul(qn, ln, quats + i * 4);
            } else {
                for (int k = 0; k < 4; ++k) quats[i * 4 + k] = qn[k];
            }
            if (camera == nullptr) continue;
            float v[3] = {p[0] - camera[0], p[1] - camera[1], p[2] - camera[2]};
            const float vinv = 1.0f / std::max(std::sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]), 1e-9f);
            for (float& c : v) c *= vinv;
            // rotate by conj(qn): v + 2 (w (u x v) + u x (u x v)) with w = qn_w, u = -qn_xyz
            const float qw = qn[0], u[3] = {-qn[1], -qn[2], -qn[3]};
            const float uv[3] = {u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2],
                                 u[0] * v[1] - u[1] * v[0]};
            const float uuv[3] = {u[1] * uv[2] - u[2] * uv[1], u[2] * uv[0] - u[0] * uv[2],
                                  u[0] * uv[1] - u[1] * uv[0]};
            for (int r = 0; r < 3; ++r) view[i * 3 + r] = v[r] + 2.0f * (qw * uv[r] + uuv[r]);
        }
    }
}

void skin_backward(const SkinShape& s, const float* means, const float* weights,
                   const float* bones, const float* local_quats, const float* g_world,
                   const float* g_quats, float* g_means, float* g_delta, float* g_bones,
                   float* g_local_quats, const float* blends, const SecondFrame& second) {
    const int B = s.bones;
    const int threads = std::max(1, s.threads);
    const bool two = second.bones != nullptr;
    const int frames = two ? 2 : 1;
    // bones transposed (16 x B per frame): dL/dw_b = <bones[b], g16> for all b as 16 axpys over b.
    std::vector<float> bones_t(static_cast<size_t>(frames) * kBoneStride * B);
    for (int b = 0; b < B; ++b)
        for (int k = 0; k < kBoneStride; ++k) {
            bones_t[k * B + b] = bones[b * kBoneStride + k];
            if (two) bones_t[(kBoneStride + k) * B + b] = second.bones[b * kBoneStride + k];
        }
    // accumulators: frame f's bone b at (f * B + b) * 16
    const size_t acc_size = static_cast<size_t>(frames) * B * kBoneStride;
    std::vector<std::vector<double>> totals(threads);
#pragma omp parallel num_threads(threads)
    {
        const int tid = omp_get_thread_num();
        std::vector<double>& total = totals[tid];
        total.assign(acc_size, 0.0);
        std::vector<float> acc(acc_size, 0.0f);
        std::vector<float> gw(B);
        int since_flush = 0;
        auto flush = [&]() {
            for (size_t k = 0; k < acc.size(); ++k) {
                total[k] += acc[k];
                acc[k] = 0.0f;
            }
            since_flush = 0;
        };
#pragma omp for schedule(static)
        for (int64_t i = 0; i < s.n; ++i) {
            const float* w = weights + i * B;
            float own[kBoneStride];
            const float* bl = own;
            if (blends != nullptr)
                bl = blends + i * frames * kBoneStride;
            else
                blend_bones(B, w, bones, own);
            const float* x = means + i * 3;
            const float* gp = g_world + i * 3;
            // world = M x + t: dL/dx = M^T g, dL/dM = g x^T, dL/dt = g
            for (int k = 0; k < 3; ++k)
                g_means[i * 3 + k] = bl[k] * gp[0] + bl[4 + k] * gp[1] + bl[8 + k] * gp[2];
            float g16[kBoneStride];
            for (int r = 0; r < 3; ++r) {
                g16[r * 4] = gp[r] * x[0];
                g16[r * 4 + 1] = gp[r] * x[1];
                g16[r * 4 + 2] = gp[r] * x[2];
                g16[r * 4 + 3] = gp[r];
            }
            g16[12] = g16[13] = g16[14] = g16[15] = 0.0f;
            if (s.rotations) {
                const float* qr = bl + 12;
                const float qnorm = norm4(qr);
                const float den = std::max(qnorm, s.quat_eps);
                const float inv = 1.0f / den;
                const float qn[4] = {qr[0] * inv, qr[1] * inv, qr[2] * inv, qr[3] * inv};
                const float* g = g_quats + i * 4;
                float gq[4];  // dL/dqn
                if (s.has_local) {
                    const float* l = local_quats + i * 4;
                    float ln[4];
                    const float lnorm = local_rotation(s, l, ln);
                    // o = qn * ln
                    gq[0] = g[0] * ln[0] + g[1] * ln[1] + g[2] * ln[2] + g[3] * ln[3];
                    gq[1] = -g[0] * ln[1] + g[1] * ln[0] - g[2] * ln[3] + g[3] * ln[2];
                    gq[2] = -g[0] * ln[2] + g[1] * ln[3] + g[2] * ln[0] - g[3] * ln[1];
                    gq[3] = -g[0] * ln[3] - g[1] * ln[2] + g[2] * ln[1] + g[3] * ln[0];
                    float gl[4];  // dL/dln
                    gl[0] = g[0] * qn[0] + g[1] * qn[1] + g[2] * qn[2] + g[3] * qn[3];
                    gl[1] = -g[0] * qn[1] + g[1] * qn[0] + g[2] * qn[3] - g[3] * qn[2];
                    gl[2] = -g[0] * qn[2] - g[1] * qn[3] + g[2] * qn[0] + g[3] * qn[1];
                    gl[3] = -g[0] * qn[3] + g[1] * qn[2] - g[2] * qn[1] + g[3] * qn[0];
                    float* out = g_local_quats + i * 4;
                    if (lnorm > s.quat_eps) {
                        const float dot = ln[0] * gl[0] + ln[1] * gl[1] + ln[2] * gl[2] + ln[3] * gl[3];
                        const float linv = 1.0f / lnorm;
                        for (int k = 0; k < 4; ++k) out[k] = (gl[k] - ln[k] * dot) * linv;
                    } else {
                        out[0] = out[1] = out[2] = out[3] = 0.0f;  // the identity does not depend on l
                    }
                } else {
                    for (int k = 0; k < 4; ++k) gq[k] = g[k];
                }
                // qn = qr / max(|qr|, eps)
                if (qnorm > s.quat_eps) {
                    const float dot = qn[0] * gq[0] + qn[1] * gq[1] + qn[2] * gq[2] + qn[3] * gq[3];
                    for (int k = 0; k < 4; ++k) g16[12 + k] = (gq[k] - qn[k] * dot) * inv;
                } else {
                    for (int k = 0; k < 4; ++k) g16[12 + k] = gq[k] * inv;
                }
            }
            // dL/dw_b = <bones[b], g16> (only the correction takes it); dL/dbones[b] += w_b g16
            if (s.has_delta) weight_grads(B, kBoneStride, g16, bones_t.data(), gw.data(), false);
            if (s.bone_grads) {
                for (int b = 0; b < B; ++b) {
                    const float wb = w[b];
                    float* a = acc.data() + static_cast<size_t>(b) * kBoneStride;
#pragma omp simd
                    for (int k = 0; k < kBoneStride; ++k) a[k] = STG_MADD(wb, g16[k], a[k]);
                }
            }
            if (two) {  // the other frame: centres only, the same weights
                float own2[kBoneStride];
                const float* bl2 = own2;
                if (blends != nullptr)
                    bl2 = blends + (i * 2 + 1) * kBoneStride;
                else
                    blend_bones(B, w, second.bones, own2);
                const float* x2 = second.means + i * 3;
                const float* gp2 = second.g_world + i * 3;
                for (int k = 0; k < 3; ++k)
                    second.g_means[i * 3 + k] = bl2[k] * gp2[0] + bl2[4 + k] * gp2[1] + bl2[8 + k] * gp2[2];
                float h16[12];
                for (int r = 0; r < 3; ++r) {
                    h16[r * 4] = gp2[r] * x2[0];
                    h16[r * 4 + 1] = gp2[r] * x2[1];
                    h16[r * 4 + 2] = gp2[r] * x2[2];
                    h16[r * 4 + 3] = gp2[r];
                }
                if (s.has_delta)
                    weight_grads(B, 12, h16, bones_t.data() + static_cast<size_t>(kBoneStride) * B, gw.data(), true);
                if (s.next_bone_grads) {
                    for (int b = 0; b < B; ++b) {
                        const float wb = w[b];
                        float* a = acc.data() + static_cast<size_t>(B + b) * kBoneStride;
#pragma omp simd
                        for (int k = 0; k < 12; ++k) a[k] = STG_MADD(wb, h16[k], a[k]);
                    }
                }
            }
            if (++since_flush == kFlushEvery) flush();
            if (s.has_delta) {
                // w = e / sum e with de_b/dd_b = e_b: dL/dd_b = w_b (dL/dw_b - sum_k w_k dL/dw_k)
                float mean = 0.0f;
                for (int b = 0; b < B; ++b) mean += w[b] * gw[b];
                float* gd = g_delta + i * B;
#pragma omp simd
                for (int b = 0; b < B; ++b) gd[b] = w[b] * (gw[b] - mean);
            }
        }
        flush();
    }
    for (size_t k = 0; k < acc_size; ++k) {
        double sum = 0.0;
        for (int t = 0; t < threads; ++t)
            if (!totals[t].empty()) sum += totals[t][k];
        const size_t first = static_cast<size_t>(B) * kBoneStride;
        if (k < first)
            g_bones[k] = static_cast<float>(sum);
        else
            second.g_bones[k - first] = static_cast<float>(sum);  // its quaternions' entries are 0
    }
}

namespace {

// One Gaussian's shading normal (stg_node.avatar.shading.gaussian_normals): its shortest axis a of
// scales (the first of equal ones, as torch.argmin) turned by q (v + 2 (w (u x v) + u x (u x v))),
// written to nrm before the flip; returns the sign that makes it face the camera from the centre p.
inline float turned_axis(const float* sc, const float* q, const float* p, const float* camera, float* a,
                         float* nrm) {
    // the axis as selects (no indexed store), so the loops over points vectorise
    const bool k1 = sc[1] < sc[0];
    const float smallest = k1 ? sc[1] : sc[0];
    const bool k2 = sc[2] < smallest;
    a[0] = (!k1 && !k2) ? 1.0f : 0.0f;
    a[1] = (k1 && !k2) ? 1.0f : 0.0f;
    a[2] = k2 ? 1.0f : 0.0f;
    const float w = q[0], u[3] = {q[1], q[2], q[3]};
    const float uv[3] = {u[1] * a[2] - u[2] * a[1], u[2] * a[0] - u[0] * a[2], u[0] * a[1] - u[1] * a[0]};
    const float uuv[3] = {u[1] * uv[2] - u[2] * uv[1], u[2] * uv[0] - u[0] * uv[2], u[0] * uv[1] - u[1] * uv[0]};
    for (int r = 0; r < 3; ++r) nrm[r] = a[r] + 2.0f * (w * uv[r] + uuv[r]);
    const float t[3] = {camera[0] - p[0], camera[1] - p[1], camera[2] - p[2]};
    const float dot = nrm[0] * t[0] + nrm[1] * t[1] + nrm[2] * t[2];
    return dot < 0.0f ? -1.0f : 1.0f;
}

}  // namespace

void gaussian_normals(int64_t n, const float* quats, const float* scales, const float* means,
                      const float* camera, float* normals, int threads) {
#pragma omp parallel for simd schedule(static) num_threads(threads)
    for (int64_t i = 0; i < n; ++i) {
        float a[3], nrm[3];
        const float sign = turned_axis(scales + i * 3, quats + i * 4, means + i * 3, camera, a, nrm);
        for (int r = 0; r < 3; ++r) normals[i * 3 + r] = nrm[r] * sign;
    }
}

void gaussian_normals_backward(int64_t n, const float* quats, const float* scales, const float* means,
                               const float* camera, const float* g_normals, float* g_quats, int threads) {
#pragma omp parallel for simd schedule(static) num_threads(threads)
    for (int64_t i = 0; i < n; ++i) {
        float a[3], nrm[3];  // the forward's axis and sign, found again
        const float* q = quats + i * 4;
        const float sign = turned_axis(scales + i * 3, q, means + i * 3, camera, a, nrm);
        const float w = q[0], u[3] = {q[1], q[2], q[3]};
        const float ua[3] = {u[1] * a[2] - u[2] * a[1], u[2] * a[0] - u[0] * a[2], u[0] * a[1] - u[1] * a[0]};
        // n = sign (a + 2 (w (u x a) + u (u.a) - a (u.u)))
        const float* gn = g_normals + i * 3;
        const float g[3] = {sign * gn[0], sign * gn[1], sign * gn[2]};
        const float ag[3] = {a[1] * g[2] - a[2] * g[1], a[2] * g[0] - a[0] * g[2], a[0] * g[1] - a[1] * g[0]};
        const float u_a = u[0] * a[0] + u[1] * a[1] + u[2] * a[2];
        const float u_g = u[0] * g[0] + u[1] * g[1] + u[2] * g[2];
        const float a_g = a[0] * g[0] + a[1] * g[1] + a[2] * g[2];
        float* out = g_quats + i * 4;
        out[0] = 2.0f * (ua[0] * g[0] + ua[1] * g[1] + ua[2] * g[2]);
        for (int r = 0; r < 3; ++r) out[1 + r] = 2.0f * (w * ag[r] + u_a * g[r] + u_g * a[r] - 2.0f * a_g * u[r]);
    }
}

namespace {

// Pixel of world point x (camera = K (R x + t)), its depth clamped below at kMinDepth, and the
// rows of d pixel / d x (2 x 3) when jac is not nullptr.
constexpr float kMinDepth = 1e-6f;

inline void project_point(const float* view, const float* K, const float* x, float* pix, float* jac) {
    float c[3];
    for (int r = 0; r < 3; ++r) c[r] = view[r * 4] * x[0] + view[r * 4 + 1] * x[1] + view[r * 4 + 2] * x[2] + view[r * 4 + 3];
    float p[3];
    for (int r = 0; r < 3; ++r) p[r] = K[r * 3] * c[0] + K[r * 3 + 1] * c[1] + K[r * 3 + 2] * c[2];
    const bool clamped = !(p[2] > kMinDepth);
    const float z = clamped ? kMinDepth : p[2];
    pix[0] = p[0] / z;
    pix[1] = p[1] / z;
    if (jac == nullptr) return;
    // d pix / d p = [1/z, 0, -pix0/z; 0, 1/z, -pix1/z] (no depth term where clamped); times K R
    const float dz0 = clamped ? 0.0f : -pix[0] / z, dz1 = clamped ? 0.0f : -pix[1] / z;
    const float inv = 1.0f / z;
    float kr[9];  // K R
    for (int r = 0; r < 3; ++r)
        for (int k = 0; k < 3; ++k)
            kr[r * 3 + k] = K[r * 3] * view[k] + K[r * 3 + 1] * view[4 + k] + K[r * 3 + 2] * view[8 + k];
    for (int k = 0; k < 3; ++k) {
        jac[k] = inv * kr[k] + dz0 * kr[6 + k];
        jac[3 + k] = inv * kr[3 + k] + dz1 * kr[6 + k];
    }
}

}  // namespace

void pixel_motion(int64_t n, const float* from, const float* to, const float* view, const float* K, float* motion,
                  int threads) {
#pragma omp parallel for schedule(static) num_threads(threads)
    for (int64_t i = 0; i < n; ++i) {
        float a[2], b[2];
        project_point(view, K, from + i * 3, a, nullptr);
        project_point(view, K, to + i * 3, b, nullptr);
        motion[i * 2] = b[0] - a[0];
        motion[i * 2 + 1] = b[1] - a[1];
    }
}

void pixel_motion_backward(int64_t n, const float* from, const float* to, const float* view, const float* K,
                           const float* g_motion, float* g_from, float* g_to, int threads) {
#pragma omp parallel for schedule(static) num_threads(threads)
    for (int64_t i = 0; i < n; ++i) {
        float pix[2], ja[6], jb[6];
        project_point(view, K, from + i * 3, pix, ja);
        project_point(view, K, to + i * 3, pix, jb);
        const float* g = g_motion + i * 2;
        for (int k = 0; k < 3; ++k) {
            g_to[i * 3 + k] = g[0] * jb[k] + g[1] * jb[3 + k];
            g_from[i * 3 + k] = -(g[0] * ja[k] + g[1] * ja[3 + k]);
        }
    }
}

}  // namespace stg_skin
