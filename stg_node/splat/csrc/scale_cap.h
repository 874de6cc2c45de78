// The scales a training step differentiates (stg_node/avatar/scale_ops.py): the capped scales
// (every axis raised to at least largest / ratio) and each row's largest axis, forward and backward
// in one pass over the rows where torch took ~10 elementwise ops over (N,) columns each way. The
// exponentials stay torch's (the callers pass exp(log_scales) in), so the results equal scale_ops'
// torch compositions bit for bit (tests/test_scale_ops.py). Plain C++17 on raw float32 arrays;
// splat_bindings.cpp wraps them for torch.
#pragma once

#include <cstdint>

namespace stg_scale {

// largest [n] and one_hot [n*3] (1 at the row's largest column, the first on ties, as torch.max)
// of the rows of x [n*3]; a NaN propagates into largest as torch.maximum's does.
void row_max(int64_t n, const float* x, float* largest, float* one_hot);

// out [n*3] = torch.maximum(s, (largest_row / ratio)) of scales s [n*3].
void capped_forward(int64_t n, const float* s, float ratio, float* out);

// dL/dlog_scales [n*3] of capped_forward(exp(log_scales)) given dL/dout `grad` [n*3] and s = the
// forward's scales: torch.maximum's split (half each on a tie), the floor's share to the largest axis.
void capped_backward(int64_t n, const float* s, float ratio, const float* grad, float* g_log);

}  // namespace stg_scale
