// CPU kernel of the avatar's shading under its learned distant lights: each Gaussian's albedo times
// its ambient-occlusion factor times the irradiance of an ambient term and K distant lights at its
// normal (stg_node/avatar/shading.py has the maths and the torch reference this is tested against;
// stg_node/splat/shade_ops.py is the Python side). Plain C++17 on raw arrays, like edge_loss.h;
// splat_bindings.cpp wraps it for torch.
//
//   out_ij = albedo_ij * f_i * E_ij,   f_i = 1 - k + k visible_i (1 without visibility),
//   E_ij = (a_j + sum_l c_lj max(0, n_i . d_l)) / m_j
//
// One pass per row, forward and backward, where torch runs a dozen ops over (M, 3) tensors each way.
#pragma once

#include <cstdint>

namespace stg_shade {

struct Lights {
    int count;         // K
    const float* a;    // (3,) ambient
    const float* c;    // (K, 3) colours
    const float* d;    // (K, 3) unit directions
    const float* m;    // (3,) the normaliser (the mean irradiance)
};

// out (M, 3). visible (M,) or null; k the occlusion strength.
void shade_forward(const float* albedo, const float* normals, const float* visible, float k, int64_t rows,
                   const Lights& lights, float* out, int threads);

// Given dL/dout (M, 3): dL/dalbedo, dL/dnormals (M, 3) (each may be null), and the sums over rows of
// dL/dk, dL/da (3), dL/dc (K, 3), dL/dd (K, 3), dL/dm (3) (float64, zeroed by the callee). Rows with
// `away` set (may be null) pass no gradient to the light or to their normal (their shade teaches
// the light nothing: shading.py), only to their albedo and k.
void shade_backward(const float* albedo, const float* normals, const float* visible, float k, int64_t rows,
                    const Lights& lights, const bool* away, const float* g_out, float* g_albedo, float* g_normals,
                    double* g_k, double* g_a, double* g_c, double* g_d, double* g_m, int threads);

}  // namespace stg_shade
