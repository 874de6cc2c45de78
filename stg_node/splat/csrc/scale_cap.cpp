// The capped scales and the largest axis (see scale_cap.h; scale_ops.py's torch is the reference).
#include "scale_cap.h"

#include <cmath>

namespace stg_scale {
namespace {

// torch.maximum: NaN if either is NaN.
inline float nan_max(float a, float b) {
    if (std::isnan(a)) return a;
    if (std::isnan(b)) return b;
    return a > b ? a : b;
}

struct RowMax {
    float largest;
    float one_hot[3];
};

// scale_ops._row_max of one row.
inline RowMax row_max_of(const float* x) {
    const float a = x[0], b = x[1], c = x[2];
    const float ab = nan_max(a, b);
    const bool third = c > ab;
    const bool first = (a >= b) && !third;
    return {nan_max(ab, c), {first ? 1.0f : 0.0f, !(first || third) ? 1.0f : 0.0f, third ? 1.0f : 0.0f}};
}

}  // namespace

void row_max(int64_t n, const float* x, float* largest, float* one_hot) {
    for (int64_t i = 0; i < n; ++i) {
        const RowMax m = row_max_of(x + 3 * i);
        largest[i] = m.largest;
        for (int k = 0; k < 3; ++k) one_hot[3 * i + k] = m.one_hot[k];
    }
}

void capped_forward(int64_t n, const float* s, float ratio, float* out) {
    for (int64_t i = 0; i < n; ++i) {
        const float* row = s + 3 * i;
        const float floor = row_max_of(row).largest / ratio;
        for (int k = 0; k < 3; ++k) out[3 * i + k] = nan_max(row[k], floor);
    }
}

void capped_backward(int64_t n, const float* s, float ratio, const float* grad, float* g_log) {
    for (int64_t i = 0; i < n; ++i) {
        const float* row = s + 3 * i;
        const float* g = grad + 3 * i;
        const RowMax m = row_max_of(row);
        const float floor = m.largest / ratio;
        float to_axis[3], rest[3];
        for (int k = 0; k < 3; ++k) {
            // the axis where it is above the floor, the floor where below, half each on a tie
            const float own = row[k] > floor ? 1.0f : (row[k] == floor ? 0.5f : 0.0f);
            to_axis[k] = g[k] * own;
            rest[k] = g[k] - to_axis[k];
        }
        const float to_floor = (rest[0] + rest[1] + rest[2]) / ratio;
        for (int k = 0; k < 3; ++k) g_log[3 * i + k] = (to_axis[k] + m.one_hot[k] * to_floor) * row[k];
    }
}

}  // namespace stg_scale
