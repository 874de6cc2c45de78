// CPU densification statistics (see densify_stats.h for the contract): one pass over the rendered
// Gaussians, each visible one's pixel looked up once, every running mean updated in place. The
// arithmetic follows densify.py's torch code step by step (float32, the same rounding of the
// pixel, no fused multiply-adds), so the two agree to the last bit or two.
#include "densify_stats.h"

#include <algorithm>
#include <cmath>

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

void motion_coefficients(int64_t rows, const float* skin_weights, const float* skin_delta, float weight_eps,
                         int64_t count, float* blended, float* coef) {
    const int64_t cells = rows * kBones;
    if (skin_delta != nullptr) {
        // one flat pass over every row's weights (vectorises), then each row's sum in order
        for (int64_t j = 0; j < cells; ++j) blended[j] = (skin_weights[j] + weight_eps) * stg_math::fast_exp(skin_delta[j]);
        for (int64_t i = 0; i < rows; ++i) {
            float* w = blended + i * kBones;
            float sum = 0.0f;
            for (int b = 0; b < kBones; ++b) sum += w[b];
            for (int b = 0; b < kBones; ++b) w[b] = w[b] / sum;
        }
    } else {
        for (int64_t j = 0; j < cells; ++j) blended[j] = skin_weights[j];
    }
    if (coef == blended) return;  // one basis per bone: the weights themselves
    int64_t group[kBones];
    for (int b = 0; b < kBones; ++b) group[b] = static_cast<int64_t>(b) * count / kBones;
    for (int64_t i = 0; i < rows; ++i) {
        float* c = coef + i * count;
        for (int64_t k = 0; k < count; ++k) c[k] = 0.0f;
        for (int b = 0; b < kBones; ++b) c[group[b]] += blended[i * kBones + b];
    }
}

void motion_help(int64_t rows, const float* mixed, const float* means, const float* grad, const bool* moving,
                 float* help_dot, float* help_norm) {
    for (int64_t i = 0; i < rows; ++i) {
        if (moving[i]) continue;
        const float* m = mixed + 12 * i;
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
