// CPU kernel of an edge-length loss over a graph of points, forward and analytic backward: the
// as-isometric-as-possible term of stg_node/avatar/isometry.py. Plain C++17 on raw arrays (no
// torch headers), like image_filter.h; splat_bindings.cpp wraps it for torch and
// stg_node/splat/edge_ops.py is the Python side (with the torch reference it is tested against).
//
// Points are (M, 3) float32 row-major; edges are two (E,) int64 arrays of row indices.
#pragma once

#include <cstdint>

namespace stg_edge {

// Mean over the E edges (a_e, b_e) of | |x_a - x_b| - |c_a - c_b| |, summed in double in edge order.
// lengths (2 E floats), when not null, receives |x_a - x_b| then |c_a - c_b| of every edge: what the
// backward would otherwise gather again.
double edge_length_forward(const float* x, const float* c, const int64_t* a, const int64_t* b, int64_t edges,
                           float* lengths = nullptr);

// Adds g * d(mean)/dx into grad_x and g * d(mean)/dc into grad_c (either may be null: not wanted),
// both (M, 3) and zeroed by the caller. Where a length is 0 its derivative is 0, and where the two
// lengths are equal |.| has derivative 0 (torch's conventions for norm and abs).
// lengths: the forward's (2 E floats).
void edge_length_backward(const float* x, const float* c, const int64_t* a, const int64_t* b, int64_t edges,
                          double g, float* grad_x, float* grad_c, const float* lengths);

}  // namespace stg_edge
