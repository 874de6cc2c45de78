// CPU edge-length loss (see edge_loss.h for the contract). Forward: one pass over the edges.
// Backward: the lengths the forward pass kept (when asked to: a gradient will come), turned into the two differences' factors in a vectorised pass, and the gradients are
// scattered into the two ends of every edge in edge order, so the result is the same every run.
#include "edge_loss.h"

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <vector>

namespace stg_edge {
namespace {

struct Edge {
    float dx[3], dc[3];
    float lx, lc;
};

inline Edge edge_at(const float* x, const float* c, int64_t i, int64_t j) {
    Edge e;
    for (int k = 0; k < 3; ++k) {
        e.dx[k] = x[3 * i + k] - x[3 * j + k];
        e.dc[k] = c[3 * i + k] - c[3 * j + k];
    }
    e.lx = std::sqrt(e.dx[0] * e.dx[0] + e.dx[1] * e.dx[1] + e.dx[2] * e.dx[2]);
    e.lc = std::sqrt(e.dc[0] * e.dc[0] + e.dc[1] * e.dc[1] + e.dc[2] * e.dc[2]);
    return e;
}

}  // namespace

double edge_length_forward(const float* x, const float* c, const int64_t* a, const int64_t* b, int64_t edges,
                           float* lengths) {
    double total = 0.0;
    for (int64_t e = 0; e < edges; ++e) {
        const Edge d = edge_at(x, c, a[e], b[e]);
        total += std::fabs(static_cast<double>(d.lx) - static_cast<double>(d.lc));
        if (lengths != nullptr) {
            lengths[e] = d.lx;
            lengths[edges + e] = d.lc;
        }
    }
    return edges > 0 ? total / static_cast<double>(edges) : 0.0;
}

void edge_length_backward(const float* x, const float* c, const int64_t* a, const int64_t* b, int64_t edges,
                          double g, float* grad_x, float* grad_c, const float* lengths) {
    if (edges <= 0) return;
    const float scale = static_cast<float>(g / static_cast<double>(edges));
    // Two passes over the forward's lengths: the factors of the two differences (independent
    // elements: the divisions vectorise, where one edge at a time they cost five times the
    // gathers), then the scatter into both ends in edge order (the same sums every run).
    std::vector<float> buffer(static_cast<std::size_t>(2 * edges));
    float* __restrict fx = buffer.data();
    float* __restrict fc = fx + edges;
    std::copy(lengths, lengths + 2 * edges, fx);
#pragma omp simd
    for (int64_t e = 0; e < edges; ++e) {
        const float lx = fx[e], lc = fc[e];
        // d|r|/dr = sign(r), 0 at r = 0 (torch's sign); d|v|/dv = v / |v|, 0 at v = 0
        const float r = lx - lc;
        const float s = scale * (static_cast<float>(r > 0.0f) - static_cast<float>(r < 0.0f));
        fx[e] = lx > 0.0f ? s / lx : 0.0f;
        fc[e] = lc > 0.0f ? -s / lc : 0.0f;
    }
    for (int pass = 0; pass < 2; ++pass) {
        float* out = pass == 0 ? grad_x : grad_c;
        if (out == nullptr) continue;
        const float* p = pass == 0 ? x : c;
        const float* f = pass == 0 ? fx : fc;
        for (int64_t e = 0; e < edges; ++e) {
            const int64_t i = a[e], j = b[e];
            for (int k = 0; k < 3; ++k) {
                const float v = f[e] * (p[3 * i + k] - p[3 * j + k]);
                out[3 * i + k] += v;
                out[3 * j + k] -= v;
            }
        }
    }
}

}  // namespace stg_edge
