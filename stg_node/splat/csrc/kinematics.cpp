// Skeleton kinematics in double (see kinematics.h; stg_node/avatar/kinematics.py has the maths).
#include "kinematics.h"

#include <algorithm>
#include <cmath>
#include <vector>

namespace stg_kin {
namespace {

// 4x4 products, row-major: c = a b, a b^T, a^T b.
inline void mul(const double* a, const double* b, double* c) {
    for (int r = 0; r < 4; ++r)
        for (int k = 0; k < 4; ++k) {
            double s = 0.0;
            for (int t = 0; t < 4; ++t) s += a[r * 4 + t] * b[t * 4 + k];
            c[r * 4 + k] = s;
        }
}

inline void mul_bt(const double* a, const double* b, double* c) {
    for (int r = 0; r < 4; ++r)
        for (int k = 0; k < 4; ++k) {
            double s = 0.0;
            for (int t = 0; t < 4; ++t) s += a[r * 4 + t] * b[k * 4 + t];
            c[r * 4 + k] = s;
        }
}

inline void mul_at(const double* a, const double* b, double* c) {
    for (int r = 0; r < 4; ++r)
        for (int k = 0; k < 4; ++k) {
            double s = 0.0;
            for (int t = 0; t < 4; ++t) s += a[t * 4 + r] * b[t * 4 + k];
            c[r * 4 + k] = s;
        }
}

inline void cross(const double* a, const double* b, double* c) {
    c[0] = a[1] * b[2] - a[2] * b[1];
    c[1] = a[2] * b[0] - a[0] * b[2];
    c[2] = a[0] * b[1] - a[1] * b[0];
}

// R (3x3, stride ld) = I + sinc [a]x + cosc [a]x^2.
inline void rotation(const double* a, double* R, int ld) {
    const double theta2 = a[0] * a[0] + a[1] * a[1] + a[2] * a[2];
    const bool small = theta2 < 1e-8;
    const double safe = small ? 1.0 : theta2;
    const double theta = std::sqrt(safe);
    const double sinc = small ? 1.0 - theta2 / 6.0 : std::sin(theta) / theta;
    const double cosc = small ? 0.5 - theta2 / 24.0 : (1.0 - std::cos(theta)) / safe;
    const double K[9] = {0.0, -a[2], a[1], a[2], 0.0, -a[0], -a[1], a[0], 0.0};
    for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c) {
            double kk = 0.0;
            for (int t = 0; t < 3; ++t) kk += K[r * 3 + t] * K[t * 3 + c];
            R[r * ld + c] = (r == c ? 1.0 : 0.0) + sinc * K[r * 3 + c] + cosc * kk;
        }
}

// w with <G, [omega]x R> = w . omega (G, R 3x3 with strides ldg, ldr).
inline void rotation_grad(const double* G, int ldg, const double* R, int ldr, double* w) {
    double M[9];
    for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c) {
            double s = 0.0;
            for (int t = 0; t < 3; ++t) s += G[r * ldg + t] * R[c * ldr + t];
            M[r * 3 + c] = s;
        }
    w[0] = M[7] - M[5];
    w[1] = M[2] - M[6];
    w[2] = M[3] - M[1];
}

// J_l(p)^T w.
inline void left_jacobian_t_times(const double* p, const double* w, double* out) {
    const double theta2 = p[0] * p[0] + p[1] * p[1] + p[2] * p[2];
    const bool small = theta2 < 1e-8;
    const double safe = small ? 1.0 : theta2;
    const double theta = std::sqrt(safe);
    const double a = small ? 0.5 - theta2 / 24.0 : (1.0 - std::cos(theta)) / safe;
    const double b = small ? 1.0 / 6.0 - theta2 / 120.0 : (theta - std::sin(theta)) / (safe * theta);
    double pxw[3], ppxw[3];
    cross(p, w, pxw);
    cross(p, pxw, ppxw);
    for (int k = 0; k < 3; ++k) out[k] = w[k] - a * pxw[k] + b * ppxw[k];
}

// kinematics.matrix_to_quaternion of the 3x3 block of a 4x4 matrix.
inline void matrix_to_quaternion(const double* m, double* q) {
    const double m00 = m[0], m01 = m[1], m02 = m[2], m10 = m[4], m11 = m[5], m12 = m[6];
    const double m20 = m[8], m21 = m[9], m22 = m[10];
    const double q4[4] = {1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22};
    double qa[4];
    for (int k = 0; k < 4; ++k) qa[k] = std::sqrt(std::max(q4[k], 0.0));
    int best = 0;
    for (int k = 1; k < 4; ++k)
        if (qa[k] > qa[best]) best = k;
    double c[4];
    switch (best) {
        case 0:
            c[0] = qa[0] * qa[0], c[1] = m21 - m12, c[2] = m02 - m20, c[3] = m10 - m01;
            break;
        case 1:
            c[0] = m21 - m12, c[1] = qa[1] * qa[1], c[2] = m10 + m01, c[3] = m02 + m20;
            break;
        case 2:
            c[0] = m02 - m20, c[1] = m10 + m01, c[2] = qa[2] * qa[2], c[3] = m21 + m12;
            break;
        default:
            c[0] = m10 - m01, c[1] = m20 + m02, c[2] = m21 + m12, c[3] = qa[3] * qa[3];
    }
    const double den = 2.0 * std::max(qa[best], 0.1);
    for (double& v : c) v /= den;
    const double norm = std::max(std::sqrt(c[0] * c[0] + c[1] * c[1] + c[2] * c[2] + c[3] * c[3]), 1e-12);
    const double sign = c[0] / norm < 0.0 ? -1.0 : 1.0;
    for (int k = 0; k < 4; ++k) q[k] = sign * (c[k] / norm);
}

}  // namespace

void rodrigues(int64_t n, const double* aa, double* R) {
    for (int64_t i = 0; i < n; ++i) rotation(aa + 3 * i, R + 9 * i, 3);
}

void rodrigues_backward(int64_t n, const double* aa, const double* R, const double* G, double* g_aa) {
    for (int64_t i = 0; i < n; ++i) {
        double w[3];
        rotation_grad(G + 9 * i, 3, R + 9 * i, 3, w);
        left_jacobian_t_times(aa + 3 * i, w, g_aa + 3 * i);
    }
}

void bones_forward(int64_t batch, int joints, const double* poses, const double* rh, const double* th,
                   const double* rest, const int64_t* parents, const double* big_inv, double* transforms,
                   double* quats, double* local, double* world, double* bone, double* root) {
    const int J = joints;
    std::vector<double> unsigned_q(static_cast<size_t>(J) * 4), sign(J);
    for (int64_t b = 0; b < batch; ++b) {
        double* L = local + b * J * 16;
        double* W = world + b * J * 16;
        double* Bn = bone + b * J * 16;
        double* T = transforms + b * J * 16;
        double* Q = quats + b * J * 4;
        double* Rt = root + b * 16;
        for (int j = 0; j < J; ++j) {
            double* l = L + j * 16;
            std::fill(l, l + 16, 0.0);
            rotation(poses + (b * J + j) * 3, l, 4);
            for (int k = 0; k < 3; ++k) l[k * 4 + 3] = rest[j * 3 + k] - (j > 0 ? rest[parents[j] * 3 + k] : 0.0);
            l[15] = 1.0;
            if (j == 0)
                std::copy(l, l + 16, W);
            else
                mul(W + parents[j] * 16, l, W + j * 16);
            double* bn = Bn + j * 16;
            const double* w = W + j * 16;
            std::copy(w, w + 16, bn);
            for (int r = 0; r < 3; ++r)
                bn[r * 4 + 3] -= w[r * 4] * rest[j * 3] + w[r * 4 + 1] * rest[j * 3 + 1] + w[r * 4 + 2] * rest[j * 3 + 2];
        }
        std::fill(Rt, Rt + 16, 0.0);
        rotation(rh + b * 3, Rt, 4);
        for (int k = 0; k < 3; ++k) Rt[k * 4 + 3] = th[b * 3 + k];
        Rt[15] = 1.0;
        for (int j = 0; j < J; ++j) {
            double tmp[16];
            mul(Rt, Bn + j * 16, tmp);
            mul(tmp, big_inv + j * 16, T + j * 16);
            matrix_to_quaternion(T + j * 16, unsigned_q.data() + j * 4);
        }
        // each joint's quaternion in its parent's (already flipped) hemisphere
        sign[0] = 1.0;
        for (int j = 1; j < J; ++j) {
            const double* q = unsigned_q.data() + j * 4;
            const double* p = unsigned_q.data() + parents[j] * 4;
            const double dot = q[0] * p[0] + q[1] * p[1] + q[2] * p[2] + q[3] * p[3];
            sign[j] = dot * sign[parents[j]] < 0.0 ? -1.0 : 1.0;
        }
        for (int j = 0; j < J; ++j)
            for (int k = 0; k < 4; ++k) Q[j * 4 + k] = unsigned_q[j * 4 + k] * sign[j];
    }
}

void bones_backward(int64_t batch, int joints, const double* poses, const double* rh, const double* rest,
                    const int64_t* parents, const double* big_inv, const double* transforms, const double* quats,
                    const double* local, const double* world, const double* bone, const double* root,
                    const double* g_transforms, const double* g_quats, double* g_poses, double* g_rh,
                    double* g_th) {
    const int J = joints;
    std::vector<double> G(static_cast<size_t>(J) * 16), gw(static_cast<size_t>(J) * 16), gl(static_cast<size_t>(J) * 16);
    for (int64_t b = 0; b < batch; ++b) {
        const double* T = transforms + b * J * 16;
        const double* Q = quats + b * J * 4;
        const double* L = local + b * J * 16;
        const double* W = world + b * J * 16;
        const double* Bn = bone + b * J * 16;
        const double* Rt = root + b * 16;
        if (g_transforms != nullptr)
            std::copy(g_transforms + b * J * 16, g_transforms + (b + 1) * J * 16, G.begin());
        else
            std::fill(G.begin(), G.end(), 0.0);
        for (int j = 0; j < J; ++j) {
            double* g = G.data() + j * 16;
            g[12] = g[13] = g[14] = g[15] = 0.0;  // the constant bottom row
            if (g_quats == nullptr) continue;
            // dL/dq as a gradient of the rotation: [h/4]x R
            const double* q = Q + j * 4;
            const double* gq = g_quats + (b * J + j) * 4;
            double qxg[3];
            cross(q + 1, gq + 1, qxg);
            double h[3];
            for (int k = 0; k < 3; ++k) h[k] = (-gq[0] * q[1 + k] + q[0] * gq[1 + k] + qxg[k]) / 4.0;
            const double S[9] = {0.0, -h[2], h[1], h[2], 0.0, -h[0], -h[1], h[0], 0.0};
            const double* R = T + j * 16;
            for (int r = 0; r < 3; ++r)
                for (int c = 0; c < 3; ++c) {
                    double s = 0.0;
                    for (int t = 0; t < 3; ++t) s += S[r * 3 + t] * R[t * 4 + c];
                    g[r * 4 + c] += s;
                }
        }
        // T = root A B^-1
        double g_root[16] = {0.0};
        for (int j = 0; j < J; ++j) {
            double ab[16], part[16], tmp[16];
            mul(Bn + j * 16, big_inv + j * 16, ab);
            mul_bt(G.data() + j * 16, ab, part);
            for (int k = 0; k < 16; ++k) g_root[k] += part[k];
            // g_bone = root^T G big_inv^T
            mul_at(Rt, G.data() + j * 16, tmp);
            double* g_bone = gw.data() + j * 16;
            mul_bt(tmp, big_inv + j * 16, g_bone);
            // A = W C, C = [I, -rest; 0, 1]: dW[:, k] -= dA[:, 3] rest_k (k < 3)
            for (int r = 0; r < 4; ++r)
                for (int k = 0; k < 3; ++k) g_bone[r * 4 + k] -= g_bone[r * 4 + 3] * rest[j * 3 + k];
        }
        // W_j = W_parent local_j, back from the leaves
        for (int j = J - 1; j > 0; --j) {
            const int64_t parent = parents[j];
            mul_at(W + parent * 16, gw.data() + j * 16, gl.data() + j * 16);
            double tmp[16];
            mul_bt(gw.data() + j * 16, L + j * 16, tmp);
            for (int k = 0; k < 16; ++k) gw[parent * 16 + k] += tmp[k];
        }
        std::copy(gw.begin(), gw.begin() + 16, gl.begin());
        for (int j = 0; j < J; ++j) {
            double w[3];
            rotation_grad(gl.data() + j * 16, 4, L + j * 16, 4, w);
            left_jacobian_t_times(poses + (b * J + j) * 3, w, g_poses + (b * J + j) * 3);
        }
        double w[3];
        rotation_grad(g_root, 4, Rt, 4, w);
        left_jacobian_t_times(rh + b * 3, w, g_rh + b * 3);
        for (int k = 0; k < 3; ++k) g_th[b * 3 + k] = g_root[k * 4 + 3];
    }
}

}  // namespace stg_kin
