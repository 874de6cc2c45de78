// CPU edge-length loss (see edge_loss.h for the contract). One pass over the edges each way: the
// two differences, their lengths and the sign of the residual are recomputed in the backward pass
// rather than stored (cheaper than writing and reading E x 8 floats), and the gradients are
// scattered into the two ends of every edge in edge order, so the result is the same every run.
#include "edge_loss.h"

#include <cmath>

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

double edge_length_forward(const float* x, const float* c, const int64_t* a, const int64_t* b, int64_t edges) {
    double total = 0.0;
    for (int64_t e = 0; e < edges; ++e) {
        const Edge d = edge_at(x, c, a[e], b[e]);
        total += std::fabs(static_cast<double>(d.lx) - static_cast<double>(d.lc));
    }
    return edges > 0 ? total / static_cast<double>(edges) : 0.0;
}

void edge_length_backward(const float* x, const float* c, const int64_t* a, const int64_t* b, int64_t edges,
                          double g, float* grad_x, float* grad_c) {
    if (edges <= 0) return;
    const float scale = static_cast<float>(g / static_cast<double>(edges));
    for (int64_t e = 0; e < edges; ++e) {
        const int64_t i = a[e], j = b[e];
        const Edge d = edge_at(x, c, i, j);
        const float r = d.lx - d.lc;
        // d|r|/dr = sign(r), 0 at r = 0 (torch's sign); d|v|/dv = v / |v|, 0 at v = 0: selects,
        // not branches (the signs of the residuals are unpredictable).
        const float s = r > 0.0f ? scale : (r < 0.0f ? -scale : 0.0f);
        if (grad_x != nullptr) {
            const float f = d.lx > 0.0f ? s / d.lx : 0.0f;
            for (int k = 0; k < 3; ++k) {
                grad_x[3 * i + k] += f * d.dx[k];
                grad_x[3 * j + k] -= f * d.dx[k];
            }
        }
        if (grad_c != nullptr) {
            const float f = d.lc > 0.0f ? s / d.lc : 0.0f;
            for (int k = 0; k < 3; ++k) {
                grad_c[3 * i + k] -= f * d.dc[k];
                grad_c[3 * j + k] += f * d.dc[k];
            }
        }
    }
}

}  // namespace stg_edge
