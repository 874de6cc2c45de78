// Forward kinematics of a skeleton (SMPL's 24 joints, any tree with parents before children) and its
// hand-written backward, in double: stg_node/avatar/kinematics.py's numpy maths (its module docstring
// has the chain rule) in one C++ pass, where numpy spends ~1 ms a training step on the per-call
// overhead of a few hundred operations on 4x4 matrices. The numpy functions are the reference these
// are tested against (tests/avatar/test_kinematics_kernel.py). Plain C++17 on raw arrays;
// splat_bindings.cpp wraps them for torch.
//
// Layouts (row-major): poses [B*J*3] axis-angles, rh/th [B*3] the root's rotation and translation,
// rest [J*3] rest joints, parents [J] (parents[0] ignored), big_inv [J*16]; 4x4 matrices as 16
// doubles.
#pragma once

#include <cstdint>

namespace stg_kin {

// rodrigues: R [n*9] of axis-angles aa [n*3] (lbs.axis_angle_to_matrix's small-angle series).
void rodrigues(int64_t n, const double* aa, double* R);

// Given dL/dR [n*9], dL/daa [n*3] (the left Jacobian's transpose on the rotation's gradient).
void rodrigues_backward(int64_t n, const double* aa, const double* R, const double* G, double* g_aa);

// transforms [B*J*16] canonical -> world, quats [B*J*4] their unit wxyz rotations, each in its
// parent's hemisphere (kinematics.matrix_to_quaternion, hemisphere_signs), and what the backward
// needs: local, world, bone [B*J*16], root [B*16].
void bones_forward(int64_t batch, int joints, const double* poses, const double* rh, const double* th,
                   const double* rest, const int64_t* parents, const double* big_inv, double* transforms,
                   double* quats, double* local, double* world, double* bone, double* root);

// dL/dposes [B*J*3], dL/drh, dL/dth [B*3] from dL/dtransforms (null: zero) and dL/dquats (null: zero).
void bones_backward(int64_t batch, int joints, const double* poses, const double* rh, const double* rest,
                    const int64_t* parents, const double* big_inv, const double* transforms, const double* quats,
                    const double* local, const double* world, const double* bone, const double* root,
                    const double* g_transforms, const double* g_quats, double* g_poses, double* g_rh,
                    double* g_th);

}  // namespace stg_kin
