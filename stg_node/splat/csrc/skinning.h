// Linear blend skinning of points (Gaussian centres and orientations) by B bones, fused into one
// pass per point, with its hand-written backward. Plain C++17 + OpenMP on raw float32 arrays,
// like splat_kernels.h; splat_bindings.cpp wraps it for torch and stg_node/splat/skin_ops.py is
// the Python side. The torch reference it must agree with is stg_node/avatar/rigid.py
// (blend_weights, skin) and model.py (the local rotation, the canonical view direction).
//
// Per point i with canonical centre x_i, body weights s_ib and learned log-space correction d_ib:
//   w_ib   = (s_ib + eps) exp(d_ib) / sum_k (s_ik + eps) exp(d_ik)      (w_ib = s_ib without d)
//   B_i    = sum_b w_ib [R_b | t_b]      world_i = B_i[:, :3] x_i + B_i[:, 3]
//   q_i    = normalise(sum_b w_ib q_b)   (the blended bone rotation, unit wxyz)
//   quat_i = q_i * normalise(l_i)        (Hamilton product with the point's local rotation l_i;
//                                         a local rotation of norm <= quat_eps is the identity)
//   view_i = conj(q_i) normalise(world_i - camera)   (the viewing direction in the canonical frame)
// where normalise(q) = q / max(|q|, quat_eps).
//
// A second frame (SecondFrame: another set of bones and, optionally, other canonical centres x'_i)
// is skinned in the same pass with the same weights: world'_i = B'_i[:, :3] x'_i + B'_i[:, 3] (centres
// only; the flow loss's next frame). The weights, the costliest part of a point, are computed once,
// and the backward pass sums both frames' dL/dw before the correction's chain rule.
#pragma once

#include <cstdint>

namespace stg_skin {

// Per bone: 16 floats, the top three rows of its 4x4 transform row-major (R00 R01 R02 t0 R10 ...
// t2) then its rotation quaternion (w, x, y, z).
constexpr int kBoneStride = 16;

struct SkinShape {
    int64_t n;          // points
    int bones;          // B
    bool has_delta;     // skin_delta given (else the body's weights are used as they are)
    bool rotations;     // compute quat_i (else only world_i)
    bool has_local;     // local rotations given (else quat_i = q_i)
    float weight_eps;   // eps of the weight correction
    float quat_eps;     // normalisation floor of quaternions
    int threads;
    bool bone_grads = true;       // backward: dL/dbones wanted (else left zero)
    bool next_bone_grads = true;  // backward: dL/dthe second frame's bones wanted (else left zero)
};

// The second frame of one pass (all pointers nullptr when there is none): its bones [B*16] (the
// quaternions are not read), its canonical centres [n*3] (may be the first frame's), its world
// centres [n*3] (forward output), dL/dits world [n*3], dL/dits centres [n*3] and dL/dits bones [B*16]
// (backward outputs).
struct SecondFrame {
    const float* bones = nullptr;
    const float* means = nullptr;
    float* world = nullptr;
    const float* g_world = nullptr;
    float* g_means = nullptr;
    float* g_bones = nullptr;
};

// Outputs: world [n*3]; quats [n*4] (if rotations); view [n*3] (if camera != nullptr, needs
// rotations); weights [n*B] the effective weights (if not nullptr: the backward pass takes them);
// blend_norm2 [n] the squared norm of the blended bone quaternion (if not nullptr, needs
// rotations: how much the blend squeezes the body there, stg_node.avatar.rigid.joint_shrink);
// blends [n*F*16] each point's blended bones, F = 1 or 2 frames (if not nullptr: the backward pass
// takes them instead of blending again).
void skin_forward(const SkinShape& shape, const float* means, const float* skin_weights,
                  const float* skin_delta, const float* bones, const float* local_quats,
                  const float* camera, float* world, float* quats, float* view, float* weights,
                  float* blend_norm2, float* blends = nullptr, const SecondFrame& second = SecondFrame{});

// Given dL/dworld [n*3] and dL/dquats [n*4] (if rotations), writes dL/dmeans [n*3], dL/ddelta
// [n*B] (if has_delta), dL/dbones [B*16] and dL/dlocal_quats [n*4] (if has_local). `weights` are
// the effective weights skin_forward wrote, `blends` its blends (or nullptr: blended again).
void skin_backward(const SkinShape& shape, const float* means, const float* weights,
                   const float* bones, const float* local_quats, const float* g_world,
                   const float* g_quats, float* g_means, float* g_delta, float* g_bones,
                   float* g_local_quats, const float* blends = nullptr,
                   const SecondFrame& second = SecondFrame{});

// Shading normals of posed Gaussians (no gradient; the torch reference is
// stg_node.avatar.shading.gaussian_normals, which this follows operation for operation): each
// point's shortest axis (the first of equal ones) of scales [n*3], turned by its unit rotation
// quats [n*4] (v + 2 (w (u x v) + u x (u x v))), negated where it faces away from camera [3] as seen
// from the centre means [n*3]. Writes normals [n*3].
void gaussian_normals(int64_t n, const float* quats, const float* scales, const float* means,
                      const float* camera, float* normals, int threads);

// The backward pass of gaussian_normals: dL/dquats [n*4] from dL/dnormals [n*3] (the axis and the
// sign are constants for the gradient, as in the torch reference: scales and means take none).
void gaussian_normals_backward(int64_t n, const float* quats, const float* scales, const float* means,
                               const float* camera, const float* g_normals, float* g_quats, int threads);

// Image motion of points from world centres `from` [n*3] to `to` [n*3] under one pinhole camera
// (view [16] row-major world -> camera, K [9]): motion [n*2] = pixel(to) - pixel(from), pixel(x) =
// (K (R x + t))[:2] / max(depth, 1e-6) (stg_node.avatar.model.Camera3.project's maths). The backward
// gives dL/dfrom and dL/dto [n*3] (the camera takes none).
void pixel_motion(int64_t n, const float* from, const float* to, const float* view, const float* K, float* motion,
                  int threads);
void pixel_motion_backward(int64_t n, const float* from, const float* to, const float* view, const float* K,
                           const float* g_motion, float* g_from, float* g_to, int threads);

}  // namespace stg_skin
