// CPU kernels of the densification statistics a training step keeps (stg_node/avatar/densify.py):
// one pass over the rendered Gaussians instead of a chain of torch gathers and scatters (~4 ms a
// step at 20k Gaussians, most of it in torch's advanced indexing). No gradients: the statistics
// read the step's gradients after its backward. Plain C++17 on raw arrays, like edge_loss.h;
// splat_bindings.cpp wraps them for torch, stg_node/splat/densify_ops.py is the Python side, and
// densify.py's torch code is the reference they are tested against (tests/test_densify_kernel.py).
#pragma once

#include <cstdint>

namespace stg_densify {

// One step's sightings: the rendered Gaussians (n rows) of a crop w x h.
struct Sightings {
    int64_t n = 0;
    const int32_t* radii = nullptr;  // (n, radii_cols): visible where every column is > 0
    int64_t radii_cols = 1;
    const float* means2d = nullptr;  // (n, 2) crop pixels
    const float* grad = nullptr;     // (n, 2) the screen gradient (absgrad or grad)
    const int64_t* index = nullptr;  // (n,) table row of each rendered row; null: row i is table row i
    int64_t w = 0, h = 0;            // crop size
    float pixels = 0.0f;             // w * h: the pull's scale
    // the tile error weight (clone_on_error): tiles (tiles_h, tiles_w) of region px; null: weight 1
    const float* tiles = nullptr;
    int64_t tiles_h = 0, tiles_w = 0, region = 1;
    float error_threshold = 1.0f;
    // camera depth of each rendered row (n,), or null (no pixel span, every row in front)
    const float* depths = nullptr;
    float focal = 1.0f;  // K[0, 0]: a pixel spans depth / focal metres
    // the surface each crop pixel sees (h, w), or null: every row in front
    const float* rendered_depth = nullptr;
    float occlusion_m = 0.0f;
    // the frame's optical flow (H, W, 2) and its validity (H, W), full frame, the crop at (x0, y0);
    // null: no flow statistics
    const float* flow = nullptr;
    const bool* valid = nullptr;
    int64_t frame_w = 0, x0 = 0, y0 = 0;
    // the step's rendered motion (h, w, 2), or null: no residual statistics
    const float* rendered_flow = nullptr;
    float decay = 0.9f;  // running means: decay * old + (1 - decay) * new
};

// The per-Gaussian state (table rows): every pointer (N,), resid_cam (N, cameras).
struct SightingState {
    float* grad_sum = nullptr;
    float* vis_count = nullptr;
    float* front_count = nullptr;
    float* m_per_px = nullptr;
    float* flow_w = nullptr;
    float* resid_w = nullptr;
    float* resid_cam = nullptr;
    int64_t cameras = 1, slot = 0;
};

// Adds the step's sightings into the state, as densify.DensifyStrategy._accumulate does (its
// docstring and comments give the why). Table rows must be unique (a rendered subset).
void accumulate_sightings(const Sightings& in, const SightingState& state);

// Shared motion bases' help statistics (densify.DensifyStrategy._accumulate_help): for every row
// with moving[i] false, the motion m_i it would get from the bases at this time (its blended
// skinning weights, rigid.blend_weights, summed per basis, motion_basis.initial_coefficients; the
// bases' affine motions mixed by them and applied to its centre), and adds <g_i, m_i> into
// help_dot and |g_i| |m_i| into help_norm. skin_weights, skin_delta (null: the body's weights
// unchanged) (N, 24); motions (count, 3, 4); means, grad (N, 3).
void motion_help(int64_t rows, const float* skin_weights, const float* skin_delta, float weight_eps,
                 const float* motions, int64_t count, const float* means, const float* grad, const bool* moving,
                 float* help_dot, float* help_norm);

}  // namespace stg_densify
