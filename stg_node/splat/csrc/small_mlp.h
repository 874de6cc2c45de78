// A small multi-layer perceptron (Linear + activation layers, any widths) evaluated row block by
// row block, with its hand-written backward. For the per-Gaussian networks of splatting models
// (tens of thousands of rows, widths of tens), where torch spends its time on the memory of the
// (rows x width) intermediates between ops rather than on the products. Plain C++17 + OpenMP on
// raw float32 arrays; splat_bindings.cpp wraps it for torch, stg_node/splat/mlp_ops.py is the
// Python side, and torch.nn (Linear, ReLU, Sigmoid, Tanh) is the reference it must agree with.
//
// Layer l maps width dims[l] to dims[l + 1]: y = act_l(x W_l^T + b_l), W_l (dims[l+1], dims[l])
// row-major as torch.nn.Linear stores it.
#pragma once

#include <cstdint>

namespace stg_mlp {

enum Activation : int { kIdentity = 0, kRelu = 1, kSigmoid = 2, kTanh = 3 };

// Widths inside the kernel are padded to this many floats (one vector of 8 lanes).
constexpr int kLanes = 8;

inline int padded(int width) { return (width + kLanes - 1) / kLanes * kLanes; }

struct MlpShape {
    int64_t rows;
    int layers;        // L >= 1
    const int* dims;   // L + 1 widths
    const int* acts;   // L activations (Activation)
    int threads;
    // Optional input encoding (enc_cols = 0: none). The kernels then read `x` as the raw rows
    // [rows x (dims[0] - 2 enc_cols enc_freqs)] and feed layer 0 the encoded rows
    //   [x_0..x_{c-1}, sin(2^k pi x_i), cos(2^k pi x_i), x_c..]   (sin/cos indexed i * freqs + k)
    // built per block in the caches: the positional encoding gamma() of the first enc_cols
    // columns, the rest passed through. dL/dx is then with respect to the raw rows.
    int enc_cols = 0;
    int enc_freqs = 0;
    // Optional view direction (view_degree = -1: none): the last 3 raw columns are a unit
    // direction d, and the encoded row ends with its real SH basis of degree view_degree
    // ((view_degree + 1)^2 columns, 3DGS's signs as stg_node/splat/sh.py), the bands above
    // view_active fed as zeros; dL/dd is that basis's derivative. The encoded row is then
    //   [x_0..x_{c-1}, sines, cosines, x_c..x_{raw-4}, SH(d)].
    int view_degree = -1;
    int view_active = -1;
};

// Columns of the view direction's SH basis in the encoded row (0: no view direction).
inline int view_columns(const MlpShape& s) { return s.view_degree < 0 ? 0 : (s.view_degree + 1) * (s.view_degree + 1); }

// Whether the kernels build the encoded row (an input encoding or a view direction).
inline bool encodes(const MlpShape& s) { return s.enc_cols > 0 || s.view_degree >= 0; }

// Width of the raw rows the kernels read: dims[0] less the sines and cosines they add, with the
// 3 direction columns in place of the SH basis.
inline int raw_width(const MlpShape& s) {
    return s.dims[0] - 2 * s.enc_cols * s.enc_freqs - (s.view_degree < 0 ? 0 : view_columns(s) - 3);
}

// The raw rows the kernels read: row r is the concatenation of row index[r] (index null: row r)
// of `groups` column groups, group g [table rows x widths[g]] row-major; the widths sum to
// raw_width(). The rows of `index` must be distinct (the backward writes each one's gradient).
struct RawRows {
    int groups;
    const float* const* data;
    const int* widths;
    const int64_t* index;
};

// out [rows x dims[L]]. If `hidden` is not null, hidden[l] (l < L - 1) receives layer l's output
// [rows x padded(dims[l+1])] for the backward pass.
void mlp_forward(const MlpShape& s, const RawRows& x, const float* const* weights,
                 const float* const* biases, float* out, float* const* hidden);

// Given dL/dout [rows x dims[L]], writes dL/dx into the groups' gradients g_groups[g] (the
// groups' shapes; null: not wanted), at the rows read (the others are left as they are, zero from
// the caller), and dL/dW_l, dL/db_l (each may be null). `hidden` and `out` are what mlp_forward
// wrote. Rows whose dL/dout is all zero are skipped (their dL/dx is zero).
void mlp_backward(const MlpShape& s, const RawRows& x, const float* const* weights,
                  const float* const* hidden, const float* out, const float* g_out, float* const* g_groups,
                  float* const* g_weights, float* const* g_biases);

}  // namespace stg_mlp
