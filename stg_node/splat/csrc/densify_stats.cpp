// CPU densification statistics (see densify_stats.h for the contract): one pass over the rendered
// Gaussians, each visible one's pixel looked up once, every running mean updated in place. The
// arithmetic follows densify.py's torch code step by step (float32, the same rounding of the
// pixel, no fused multiply-adds), so the two agree to the last bit or two.
#include "densify_stats.h"

#include <algorithm>
#include <cmath>
#include <vector>

#include "fast_math.h"

namespace stg_densify {
namespace {

constexpr int kBones = 24;

// torch's round (half to even), .long() and clamp(0, size - 1); NaN reads as pixel 0.
inline int64_t pixel_of(float v, int64_t size) {
    const float r = std::nearbyint(v);
    if (!(r >= 0.0f)) return 0;
    if (r > static_cast<float>(size - 1)) return size - 1;
    return static_cast<int64_t>(r);
}

inline float norm2(float x, float y) { return std::sqrt(x * x + y * y); }

}  // namespace

void accumulate_sightings(const Sightings& in, const SightingState& st) {
    const float keep = in.decay;
    const float take = static_cast<float>(1.0 - static_cast<double>(in.decay));
    for (int64_t i = 0; i < in.n; ++i) {
        bool visible = true;
        for (int64_t c = 0; c < in.radii_cols; ++c) visible = visible && in.radii[i * in.radii_cols + c] > 0;
        if (!visible) continue;
        const int64_t t = in.index != nullptr ? in.index[i] : i;
        const int64_t px = pixel_of(in.means2d[2 * i], in.w);
        const int64_t py = pixel_of(in.means2d[2 * i + 1], in.h);
        float pull = norm2(in.grad[2 * i], in.grad[2 * i + 1]) * in.pixels;
        if (in.tiles != nullptr) {
            const float e = in.tiles[(py / in.region) * in.tiles_w + px / in.region] / in.error_threshold;
            pull = pull * std::min(e, 1.0f);
        }
        st.grad_sum[t] += pull;
        st.vis_count[t] += 1.0f;
        bool front = true;
        if (in.rendered_depth != nullptr && in.depths != nullptr) {
            front = in.depths[i] <= in.rendered_depth[py * in.w + px] + in.occlusion_m;
        }
        if (front) st.front_count[t] += 1.0f;
        if (in.depths != nullptr) {
            const float span = in.depths[i] / in.focal;
            const float old = st.m_per_px[t];
            st.m_per_px[t] = old > 0.0f ? keep * old + take * span : span;
        }
        if (in.flow == nullptr) continue;
        const int64_t at = (in.y0 + py) * in.frame_w + (in.x0 + px);
        if (!(in.valid[at] && front)) continue;
        const float fx = in.flow[2 * at], fy = in.flow[2 * at + 1];
        st.flow_w[t] = keep * st.flow_w[t] + take * norm2(fx, fy);
        if (in.rendered_flow == nullptr) continue;
        const int64_t q = py * in.w + px;
        const float missed = norm2(fx - in.rendered_flow[2 * q], fy - in.rendered_flow[2 * q + 1]);
        float* row = st.resid_cam + t * st.cameras;
        row[st.slot] = keep * row[st.slot] + take * missed;
        float most = row[0];
        for (int64_t c = 1; c < st.cameras; ++c) most = std::max(most, row[c]);
        st.resid_w[t] = most;
    }
}

void motion_help(int64_t rows, const float* skin_weights, const float* skin_delta, float weight_eps,
                 const float* motions, int64_t count, const float* means, const float* grad, const bool* moving,
                 float* help_dot, float* help_norm) {
    using stg_math::v8f;
    // Row by row, in registers: the torch way's (N, 24) and (N, 12) temporaries cost more in fresh
    // pages than the arithmetic. Each basis' 3x4 motion padded to 16 lanes (two vectors).
    std::vector<float> padded(static_cast<size_t>(16 * count), 0.0f);
    for (int64_t k = 0; k < count; ++k) std::copy(motions + 12 * k, motions + 12 * k + 12, padded.data() + 16 * k);
    int64_t group[kBones];
    for (int b = 0; b < kBones; ++b) group[b] = static_cast<int64_t>(b) * count / kBones;
    std::vector<float> coef_buf(static_cast<size_t>(std::max<int64_t>(count, kBones)), 0.0f);
    float* coef = coef_buf.data();
    alignas(32) float w[kBones];
    const v8f eps = stg_math::v8_splat(weight_eps);
    for (int64_t i = 0; i < rows; ++i) {
        if (moving[i]) continue;
        const float* sw = skin_weights + i * kBones;
        // rigid.blend_weights, (s + eps) exp(d) / sum, with the division by the sum left to the mixed
        // motion below (16 lanes instead of 24; the same value to rounding)
        float sum = 1.0f;
        if (skin_delta != nullptr) {
            const float* d = skin_delta + i * kBones;
            v8f total = stg_math::v8_splat(0.0f);
            for (int q = 0; q < kBones; q += 8) {
                const v8f v = (stg_math::v8_load(sw + q) + eps) * stg_math::fast_exp8(stg_math::v8_load(d + q));
                stg_math::v8_store(w + q, v);
                total = total + v;
            }
            sum = ((total[0] + total[1]) + (total[2] + total[3])) + ((total[4] + total[5]) + (total[6] + total[7]));
        } else {
            std::copy(sw, sw + kBones, w);
        }
        const float* c = w;  // motion_basis.initial_coefficients: the weights summed per basis
        if (count != kBones) {
            for (int64_t k = 0; k < count; ++k) coef[k] = 0.0f;
            for (int b = 0; b < kBones; ++b) coef[group[b]] += w[b];
            c = coef;
        }
        // the mixed motion sum_k c_k A_k, in two independent chains per half (latency, not lanes)
        v8f lo0 = stg_math::v8_splat(0.0f), hi0 = lo0, lo1 = lo0, hi1 = lo0;
        int64_t k = 0;
        for (; k + 1 < count; k += 2) {
            const float* a0 = padded.data() + 16 * k;
            const v8f c0 = stg_math::v8_splat(c[k]), c1 = stg_math::v8_splat(c[k + 1]);
            lo0 = stg_math::v8_madd(c0, stg_math::v8_load(a0), lo0);
            hi0 = stg_math::v8_madd(c0, stg_math::v8_load(a0 + 8), hi0);
            lo1 = stg_math::v8_madd(c1, stg_math::v8_load(a0 + 16), lo1);
            hi1 = stg_math::v8_madd(c1, stg_math::v8_load(a0 + 24), hi1);
        }
        if (k < count) {
            const v8f c0 = stg_math::v8_splat(c[k]);
            lo0 = stg_math::v8_madd(c0, stg_math::v8_load(padded.data() + 16 * k), lo0);
            hi0 = stg_math::v8_madd(c0, stg_math::v8_load(padded.data() + 16 * k + 8), hi0);
        }
        const v8f norm = stg_math::v8_splat(sum);
        const v8f lo = (lo0 + lo1) / norm, hi = (hi0 + hi1) / norm;
        float m[16];
        stg_math::v8_store(m, lo);
        stg_math::v8_store(m + 8, hi);
        const float* p = means + 3 * i;
        const float* g = grad + 3 * i;
        float would[3];
        for (int r = 0; r < 3; ++r) {
            would[r] = m[4 * r] * p[0] + m[4 * r + 1] * p[1] + m[4 * r + 2] * p[2] + m[4 * r + 3];
        }
        const float dot = g[0] * would[0] + g[1] * would[1] + g[2] * would[2];
        const float gn = std::sqrt(g[0] * g[0] + g[1] * g[1] + g[2] * g[2]);
        const float wn = std::sqrt(would[0] * would[0] + would[1] * would[1] + would[2] * would[2]);
        help_dot[i] += dot;
        help_norm[i] += gn * wn;
    }
}

}  // namespace stg_densify
