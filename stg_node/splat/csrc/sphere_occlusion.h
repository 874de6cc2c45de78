// CPU kernel of the avatar's ambient-occlusion term: the share of each point's cosine-weighted
// hemisphere that a set of spheres leaves open (stg_node/avatar/occlusion.py has the maths, the
// torch reference this is tested against, and the Python side). Plain C++17 on raw arrays (no
// torch headers), like edge_loss.h; splat_bindings.cpp wraps it for torch.
//
// One pass per point over the S spheres (eight at a time): no (M, S) temporaries, which is what
// the torch reference spends most of its time allocating and reading back.
#pragma once

#include <cstdint>

namespace stg_occ {

// visible[i] = prod_s (1 - mask[group[i], s] * clamp(n_i . (c_s - p_i) / d, 0, 1) * min(1, r2_s / d^2))
// with d = |c_s - p_i| (d^2 clamped to 1e-12). points, normals (M, 3) row-major; centres (S, 3);
// radii2 (S,) the squared radii; mask (G, S) the 0/1 weight of each sphere for each group; group
// (M,) each point's row of the mask (checked by the caller to lie in [0, G)).
void sphere_visibility(const float* points, const float* normals, const int64_t* group, int64_t m,
                       const float* centres, const float* radii2, const float* mask, int64_t spheres,
                       int64_t groups, float* visible, int threads);

}  // namespace stg_occ
