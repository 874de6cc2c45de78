// CPU kernels of stg_node's Gaussian rasterizer (see splat_kernels.h for the contract).
//
// Layout of the work:
//   project   one pass over all Gaussians (double precision inside, so extreme scales and
//             near-plane depths neither overflow nor lose the covariance), parallel.
//   sort      the visible Gaussians by camera depth with an LSD radix sort on the float bits
//             (depths are >= the near plane, hence positive, so bit order == value order),
//             then gathered into depth-ordered records of one cache line each (what a tile
//             needs of a Gaussian: centre, conic, opacity, box, up to 6 colours).
//   bin       per-tile intersection counts by row difference arrays (O(rows), not O(tiles),
//             per Gaussian), int64 prefix sums, and a fill in depth order, so every tile list
//             comes out sorted without a key sort. Tiles are processed in chunks of at most
//             `max_intersections_per_chunk` intersections: memory stays bounded.
//   raster    parallel over tiles (dynamic schedule); empty tiles are written directly. Within
//             a tile each Gaussian visits only the rows of its clipped box and, per row, only
//             the 8-lane halves (one vector each) the box touches, skipping rows whose pixels
//             are all finished. The lanes are explicit 8-float vectors, branch-free (the exp is
//             a polynomial, not libm), with the channel count compiled in for 3-6 channels.
//             A tile's list jumps through the records in depth order; the records a few places
//             ahead are prefetched (the hardware cannot follow the indirection: without it
//             a third of the forward time was spent waiting on these loads at 50k Gaussians).
//   backward  the same tiles back to front (transmittance recovered by division, as in 3DGS),
//             skipping halves where no pixel blended the Gaussian; per half one pass on 8-lane
//             vectors (for 3-6 channels; three scalar-lane loops otherwise) whose per-lane
//             accumulators are reduced once per Gaussian into per-thread gradient buffers
//             indexed by depth rank (no atomics), summed at the end.
//
// Floating-point contraction is disabled at build time (-ffp-contract=off); multiply-adds are
// fused explicitly (STG_MADD) in inline helpers that both passes share, so the forward and
// backward passes evaluate alpha bit-identically, which the backward relies on to know which
// Gaussians were blended.
#include "splat_kernels.h"

#include <omp.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstring>
#include <vector>

#include "fast_math.h"

namespace stg_splat {
namespace {

using Clock = std::chrono::steady_clock;

inline double ms_since(Clock::time_point t0) {
    return std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
}

using stg_math::fast_exp;
using stg_math::fast_exp8;
using stg_math::v8_load;
using stg_math::v8_madd;
using stg_math::v8_splat;
using stg_math::v8_store;
using stg_math::v8f;
using stg_math::v8i;

// The Gaussian's exponent at a pixel, sigma = a/2 dx^2 + b dx dy + c/2 dy^2, as
// (ha dx + b dy) dx + c/2 dy^2 with the row terms hoisted (dx = mean_x - pixel_x).
inline float sigma_at(float ha, float bdy, float rowc, float dx) {
    return STG_MADD(STG_MADD(ha, dx, bdy), dx, rowc);
}

// sigma_at on eight lanes (bit-identical per lane).
inline v8f sigma_at8(float ha, float bdy, float rowc, v8f dx) {
    return v8_madd(v8_madd(v8_splat(ha), dx, v8_splat(bdy)), dx, v8_splat(rowc));
}

// ---------------------------------------------------------------------------------------
// Projection math, shared by forward and backward (double precision).
struct ProjectedGaussian {
    double p[3];       // camera-space mean
    double qn[4];      // normalised quaternion (w, x, y, z)
    double qnorm;      // |q| before normalisation
    double Rq[9];      // rotation of the Gaussian
    double M[9];       // Rq * diag(scale)
    double RM[9];      // camera rotation * M
    double cov_c[9];   // camera-space covariance = RM RM^T
    double tx, ty;     // frustum-clamped camera x, y used by the Jacobian
    bool clamp_x, clamp_y;
    double J[6];       // 2x3 EWA Jacobian, row-major
    double a, b, c;    // 2D covariance before dilation
    double a1, c1;     // after dilation
    double det0, det1;
    double comp;
    double mx, my;
};

inline void quat_to_rotmat(const double q[4], double R[9]) {
    const double w = q[0], x = q[1], y = q[2], z = q[3];
    R[0] = 1.0 - 2.0 * (y * y + z * z);
    R[1] = 2.0 * (x * y - w * z);
    R[2] = 2.0 * (x * z + w * y);
    R[3] = 2.0 * (x * y + w * z);
    R[4] = 1.0 - 2.0 * (x * x + z * z);
    R[5] = 2.0 * (y * z - w * x);
    R[6] = 2.0 * (x * z - w * y);
    R[7] = 2.0 * (y * z + w * x);
    R[8] = 1.0 - 2.0 * (x * x + y * y);
}

// Returns false if the Gaussian is culled by depth or a degenerate 2D covariance.
inline bool project_one(int64_t i, const float* means, const float* quats, const float* scales,
                        const Camera& cam, const Settings& s, ProjectedGaussian& g) {
    const double m[3] = {means[i * 3], means[i * 3 + 1], means[i * 3 + 2]};
    for (int r = 0; r < 3; ++r) {
        g.p[r] = cam.R[r * 3] * m[0] + cam.R[r * 3 + 1] * m[1] + cam.R[r * 3 + 2] * m[2] + cam.t[r];
    }
    const double z = g.p[2];
    if (!(z >= s.near_plane && z <= s.far_plane)) return false;

    const double q[4] = {quats[i * 4], quats[i * 4 + 1], quats[i * 4 + 2], quats[i * 4 + 3]};
    g.qnorm = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
    const double qden = std::max(g.qnorm, s.quat_norm_eps);
    const double qinv = 1.0 / qden;
    for (int k = 0; k < 4; ++k) g.qn[k] = q[k] * qinv;
    quat_to_rotmat(g.qn, g.Rq);
    const double sc[3] = {scales[i * 3], scales[i * 3 + 1], scales[i * 3 + 2]};
    for (int r = 0; r < 3; ++r)
        for (int k = 0; k < 3; ++k) g.M[r * 3 + k] = g.Rq[r * 3 + k] * sc[k];
    // cov_c = R cov R^T = (R M)(R M)^T with RM = R * M: fewer products than forming cov.
    for (int r = 0; r < 3; ++r)
        for (int k = 0; k < 3; ++k)
            g.RM[r * 3 + k] = cam.R[r * 3] * g.M[k] + cam.R[r * 3 + 1] * g.M[3 + k] +
                              cam.R[r * 3 + 2] * g.M[6 + k];
    for (int r = 0; r < 3; ++r)
        for (int k = r; k < 3; ++k) {
            const double v = g.RM[r * 3] * g.RM[k * 3] + g.RM[r * 3 + 1] * g.RM[k * 3 + 1] +
                             g.RM[r * 3 + 2] * g.RM[k * 3 + 2];
            g.cov_c[r * 3 + k] = g.cov_c[k * 3 + r] = v;
        }

    const double W = cam.width, H = cam.height;
    const double tan_x = 0.5 * W / cam.fx, tan_y = 0.5 * H / cam.fy;
    const double lim_xp = (W - cam.cx) / cam.fx + s.frustum_margin * tan_x;
    const double lim_xn = cam.cx / cam.fx + s.frustum_margin * tan_x;
    const double lim_yp = (H - cam.cy) / cam.fy + s.frustum_margin * tan_y;
    const double lim_yn = cam.cy / cam.fy + s.frustum_margin * tan_y;
    const double rz = 1.0 / z;  // reciprocals: one division instead of many
    const double ux = g.p[0] * rz, uy = g.p[1] * rz;
    g.clamp_x = !(ux >= -lim_xn && ux <= lim_xp);
    g.clamp_y = !(uy >= -lim_yn && uy <= lim_yp);
    g.tx = z * std::min(std::max(ux, -lim_xn), lim_xp);
    g.ty = z * std::min(std::max(uy, -lim_yn), lim_yp);
    g.J[0] = cam.fx * rz;
    g.J[1] = 0.0;
    g.J[2] = -cam.fx * g.tx * (rz * rz);
    g.J[3] = 0.0;
    g.J[4] = cam.fy * rz;
    g.J[5] = -cam.fy * g.ty * (rz * rz);
    double JS[6];  // J cov_c
    for (int r = 0; r < 2; ++r)
        for (int k = 0; k < 3; ++k)
            JS[r * 3 + k] = g.J[r * 3] * g.cov_c[k] + g.J[r * 3 + 1] * g.cov_c[3 + k] +
                            g.J[r * 3 + 2] * g.cov_c[6 + k];
    double cov2d[4];
    for (int r = 0; r < 2; ++r)
        for (int k = 0; k < 2; ++k)
            cov2d[r * 2 + k] = JS[r * 3] * g.J[k * 3] + JS[r * 3 + 1] * g.J[k * 3 + 1] +
                               JS[r * 3 + 2] * g.J[k * 3 + 2];
    g.a = cov2d[0];
    g.b = 0.5 * (cov2d[1] + cov2d[2]);
    g.c = cov2d[3];
    g.det0 = g.a * g.c - g.b * g.b;
    g.a1 = g.a + s.eps2d;
    g.c1 = g.c + s.eps2d;
    g.det1 = g.a1 * g.c1 - g.b * g.b;
    if (!(g.det1 > 0.0) || !std::isfinite(g.det1)) return false;
    if (s.antialiased) {
        const double ratio = g.det0 / g.det1;
        g.comp = ratio > 0.0 ? std::sqrt(ratio) : 0.0;
    } else {
        g.comp = 1.0;
    }
    g.mx = cam.fx * ux + cam.cx;
    g.my = cam.fy * uy + cam.cy;
    return true;
}

}  // namespace

void project_forward(int64_t n, const float* means, const float* quats, const float* scales,
                     const float* opacities, const Camera& cam, const Settings& s, float* means2d,
                     float* conics, float* depths, float* opac_eff, float* comp, int32_t* radii,
                     int32_t* bbox, uint8_t* visible) {
#pragma omp parallel for num_threads(s.threads) schedule(static)
    for (int64_t i = 0; i < n; ++i) {
        means2d[i * 2] = means2d[i * 2 + 1] = 0.0f;
        conics[i * 3] = conics[i * 3 + 1] = conics[i * 3 + 2] = 0.0f;
        depths[i] = 0.0f;
        opac_eff[i] = 0.0f;
        comp[i] = 1.0f;
        radii[i * 2] = radii[i * 2 + 1] = 0;
        bbox[i * 4] = bbox[i * 4 + 2] = 0;
        bbox[i * 4 + 1] = bbox[i * 4 + 3] = -1;
        visible[i] = 0;

        ProjectedGaussian g;
        if (!project_one(i, means, quats, scales, cam, s, g)) continue;
        const double o_eff = static_cast<double>(opacities[i]) * g.comp;
        if (!(o_eff >= s.alpha_min)) continue;
        const double extent =
            std::min(s.sigma_extent_max, std::sqrt(2.0 * std::log(o_eff / s.alpha_min)));
        const double rx = std::ceil(extent * std::sqrt(g.a1));
        const double ry = std::ceil(extent * std::sqrt(g.c1));
        if (rx <= s.radius_clip && ry <= s.radius_clip) continue;
        // gsplat's image test (ProjectionEWA3DGSFused.cu): culled when [mean - radius,
        // mean + radius] misses (0, W) x (0, H). Written so that a NaN centre is culled too.
        const double W = cam.width, H = cam.height;
        const bool on_image = (g.mx + rx > 0.0) & (g.mx - rx < W) & (g.my + ry > 0.0) & (g.my - ry < H);
        if (!on_image) continue;
        // Pixel j (centre j + 0.5) is covered when |mx - (j + 0.5)| <= rx. Clip in double
        // before converting to int, so huge radii or far-off centres cannot overflow. The box
        // is empty (0, -1, 0, -1) for a visible Gaussian that reaches less than half a pixel
        // into the image.
        const double x0 = std::max(std::ceil(g.mx - rx - 0.5), 0.0);
        const double x1 = std::min(std::floor(g.mx + rx - 0.5), W - 1.0);
        const double y0 = std::max(std::ceil(g.my - ry - 0.5), 0.0);
        const double y1 = std::min(std::floor(g.my + ry - 0.5), H - 1.0);
        const bool covers = (x0 <= x1) & (y0 <= y1);

        means2d[i * 2] = static_cast<float>(g.mx);
        means2d[i * 2 + 1] = static_cast<float>(g.my);
        const double inv_det = 1.0 / g.det1;
        conics[i * 3] = static_cast<float>(g.c1 * inv_det);
        conics[i * 3 + 1] = static_cast<float>(-g.b * inv_det);
        conics[i * 3 + 2] = static_cast<float>(g.a1 * inv_det);
        depths[i] = static_cast<float>(g.p[2]);
        opac_eff[i] = static_cast<float>(o_eff);
        comp[i] = static_cast<float>(g.comp);
        const double rmax = static_cast<double>(s.radius_report_max);
        radii[i * 2] = static_cast<int32_t>(std::min(rx, rmax));
        radii[i * 2 + 1] = static_cast<int32_t>(std::min(ry, rmax));
        bbox[i * 4] = covers ? static_cast<int32_t>(x0) : 0;
        bbox[i * 4 + 1] = covers ? static_cast<int32_t>(x1) : -1;
        bbox[i * 4 + 2] = covers ? static_cast<int32_t>(y0) : 0;
        bbox[i * 4 + 3] = covers ? static_cast<int32_t>(y1) : -1;
        visible[i] = 1;
    }
}

void may_be_visible(int64_t n, const float* means, const float* scales, const Camera& cam,
                    const Settings& s, double margin_px, uint8_t* out) {
    const double W = cam.width, H = cam.height;
    const double tan_x = 0.5 * W / cam.fx, tan_y = 0.5 * H / cam.fy;
    const double lim_xp = (W - cam.cx) / cam.fx + s.frustum_margin * tan_x;
    const double lim_xn = cam.cx / cam.fx + s.frustum_margin * tan_x;
    const double lim_yp = (H - cam.cy) / cam.fy + s.frustum_margin * tan_y;
    const double lim_yn = cam.cy / cam.fy + s.frustum_margin * tan_y;
    const double e = s.sigma_extent_max;
#pragma omp parallel for num_threads(s.threads) schedule(static)
    for (int64_t i = 0; i < n; ++i) {
        const double m[3] = {means[i * 3], means[i * 3 + 1], means[i * 3 + 2]};
        double p[3];
        for (int r = 0; r < 3; ++r)
            p[r] = cam.R[r * 3] * m[0] + cam.R[r * 3 + 1] * m[1] + cam.R[r * 3 + 2] * m[2] + cam.t[r];
        const double z = p[2];
        const bool out_of_depth = (z < s.near_plane) | (z > s.far_plane);
        const double zs = std::max(z, s.near_plane);
        const double ux = p[0] / zs, uy = p[1] / zs;
        const double tx = std::min(std::max(ux, -lim_xn), lim_xp), ty = std::min(std::max(uy, -lim_yn), lim_yp);
        const double smax = std::max({static_cast<double>(scales[i * 3]), static_cast<double>(scales[i * 3 + 1]),
                                      static_cast<double>(scales[i * 3 + 2])});
        const double jx2 = (cam.fx / zs) * (cam.fx / zs) * (1.0 + tx * tx);
        const double jy2 = (cam.fy / zs) * (cam.fy / zs) * (1.0 + ty * ty);
        const double rx = e * std::sqrt(jx2 * smax * smax + s.eps2d) + margin_px;
        const double ry = e * std::sqrt(jy2 * smax * smax + s.eps2d) + margin_px;
        const double mx = cam.fx * ux + cam.cx, my = cam.fy * uy + cam.cy;
        const bool off_image = (mx + rx <= 0.0) | (mx - rx >= W) | (my + ry <= 0.0) | (my - ry >= H);
        out[i] = (out_of_depth | off_image) ? 0 : 1;
    }
}

void project_backward(int64_t n, const float* means, const float* quats, const float* scales,
                      const float* opacities, const Camera& cam, const Settings& s,
                      const uint8_t* visible, const float* g_means2d, const float* g_conics,
                      const float* g_depths, const float* g_opac_eff, float* g_means,
                      float* g_quats, float* g_scales, float* g_opacities) {
#pragma omp parallel for num_threads(s.threads) schedule(static)
    for (int64_t i = 0; i < n; ++i) {
        for (int k = 0; k < 3; ++k) g_means[i * 3 + k] = 0.0f;
        for (int k = 0; k < 4; ++k) g_quats[i * 4 + k] = 0.0f;
        for (int k = 0; k < 3; ++k) g_scales[i * 3 + k] = 0.0f;
        g_opacities[i] = 0.0f;
        if (!visible[i]) continue;
        ProjectedGaussian g;
        if (!project_one(i, means, quats, scales, cam, s, g)) continue;

        const double o = opacities[i];
        const double goe = g_opac_eff[i];
        double g_comp = 0.0;
        if (s.antialiased) {
            g_opacities[i] = static_cast<float>(goe * g.comp);
            g_comp = goe * o;
        } else {
            g_opacities[i] = static_cast<float>(goe);
        }

        // conic = inverse of the dilated covariance S = [[a1, b], [b, c1]]:
        // dL/dS = -S^-1 G S^-1 with G = [[gA, gB/2], [gB/2, gC]].
        const double inv_det = 1.0 / g.det1;
        const double A = g.c1 * inv_det, B = -g.b * inv_det, C = g.a1 * inv_det;
        const double gA = g_conics[i * 3], gB = g_conics[i * 3 + 1], gC = g_conics[i * 3 + 2];
        const double G00 = gA, G01 = 0.5 * gB, G11 = gC;
        const double P00 = A * G00 + B * G01, P01 = A * G01 + B * G11;
        const double P10 = B * G00 + C * G01, P11 = B * G01 + C * G11;
        const double dS00 = -(P00 * A + P01 * B);
        const double dS01 = -(P00 * B + P01 * C);
        const double dS11 = -(P10 * B + P11 * C);
        double ga = dS00, gc = dS11, gb = 2.0 * dS01;
        if (s.antialiased) {
            const double ratio = g.det0 / g.det1;
            if (ratio > 0.0) {
                const double g_ratio = g_comp * 0.5 / (g.comp + s.compensation_grad_eps);
                const double d2 = g.det1 * g.det1;
                ga += g_ratio * (g.c * g.det1 - g.det0 * g.c1) / d2;
                gc += g_ratio * (g.a * g.det1 - g.det0 * g.a1) / d2;
                gb += g_ratio * (-2.0 * g.b * (g.det1 - g.det0)) / d2;
            }
        }
        // (a, b, c) of cov2d = J cov_c J^T, b the symmetrised off-diagonal.
        const double G2[4] = {ga, 0.5 * gb, 0.5 * gb, gc};
        // dL/dJ = 2 G2 J cov_c ; dL/dcov_c = J^T G2 J
        double JS[6];
        for (int r = 0; r < 2; ++r)
            for (int k = 0; k < 3; ++k)
                JS[r * 3 + k] = g.J[r * 3] * g.cov_c[k] + g.J[r * 3 + 1] * g.cov_c[3 + k] +
                                g.J[r * 3 + 2] * g.cov_c[6 + k];
        double gJ[6];
        for (int r = 0; r < 2; ++r)
            for (int k = 0; k < 3; ++k)
                gJ[r * 3 + k] = 2.0 * (G2[r * 2] * JS[k] + G2[r * 2 + 1] * JS[3 + k]);
        double GJ[6];  // G2 J
        for (int r = 0; r < 2; ++r)
            for (int k = 0; k < 3; ++k) GJ[r * 3 + k] = G2[r * 2] * g.J[k] + G2[r * 2 + 1] * g.J[3 + k];
        double gcov_c[9];
        for (int r = 0; r < 3; ++r)
            for (int k = 0; k < 3; ++k) gcov_c[r * 3 + k] = g.J[r] * GJ[k] + g.J[3 + r] * GJ[3 + k];

        const double z = g.p[2];
        const double gmx = g_means2d[i * 2], gmy = g_means2d[i * 2 + 1];
        double gp[3];
        const double rz = 1.0 / z, rz2 = rz * rz, rz3 = rz2 * rz;
        gp[0] = gmx * cam.fx * rz;
        gp[1] = gmy * cam.fy * rz;
        gp[2] = -gmx * cam.fx * g.p[0] * rz2 - gmy * cam.fy * g.p[1] * rz2;
        gp[2] += -gJ[0] * cam.fx * rz2 - gJ[4] * cam.fy * rz2 + gJ[2] * 2.0 * cam.fx * g.tx * rz3 +
                 gJ[5] * 2.0 * cam.fy * g.ty * rz3;
        const double g_tx = -gJ[2] * cam.fx * rz2, g_ty = -gJ[5] * cam.fy * rz2;
        if (g.clamp_x) gp[2] += g_tx * (g.tx * rz); else gp[0] += g_tx;
        if (g.clamp_y) gp[2] += g_ty * (g.ty * rz); else gp[1] += g_ty;
        gp[2] += g_depths[i];

        // p = R m + t ; cov_c = R cov R^T
        for (int k = 0; k < 3; ++k)
            g_means[i * 3 + k] = static_cast<float>(cam.R[k] * gp[0] + cam.R[3 + k] * gp[1] +
                                                    cam.R[6 + k] * gp[2]);
        // cov_c = RM RM^T -> dRM = (gcov_c + gcov_c^T) RM ; RM = R M -> dM = R^T dRM
        double gRM[9];
        for (int r = 0; r < 3; ++r)
            for (int k = 0; k < 3; ++k) {
                double acc = 0.0;
                for (int j = 0; j < 3; ++j) acc += (gcov_c[r * 3 + j] + gcov_c[j * 3 + r]) * g.RM[j * 3 + k];
                gRM[r * 3 + k] = acc;
            }
        double gM[9];
        for (int r = 0; r < 3; ++r)
            for (int k = 0; k < 3; ++k)
                gM[r * 3 + k] = cam.R[r] * gRM[k] + cam.R[3 + r] * gRM[3 + k] + cam.R[6 + r] * gRM[6 + k];
        const double sc[3] = {scales[i * 3], scales[i * 3 + 1], scales[i * 3 + 2]};
        double gR[9];
        for (int k = 0; k < 3; ++k) {
            double acc = 0.0;
            for (int r = 0; r < 3; ++r) {
                acc += gM[r * 3 + k] * g.Rq[r * 3 + k];
                gR[r * 3 + k] = gM[r * 3 + k] * sc[k];
            }
            g_scales[i * 3 + k] = static_cast<float>(acc);
        }
        const double w = g.qn[0], x = g.qn[1], y = g.qn[2], zq = g.qn[3];
        double gq[4];
        gq[0] = 2.0 * (-zq * gR[1] + y * gR[2] + zq * gR[3] - x * gR[5] - y * gR[6] + x * gR[7]);
        gq[1] = 2.0 * (y * gR[1] + zq * gR[2] + y * gR[3] - 2.0 * x * gR[4] - w * gR[5] + zq * gR[6] +
                       w * gR[7] - 2.0 * x * gR[8]);
        gq[2] = 2.0 * (-2.0 * y * gR[0] + x * gR[1] + w * gR[2] + x * gR[3] + zq * gR[5] - w * gR[6] +
                       zq * gR[7] - 2.0 * y * gR[8]);
        gq[3] = 2.0 * (-2.0 * zq * gR[0] - w * gR[1] + x * gR[2] + w * gR[3] - 2.0 * zq * gR[4] +
                       y * gR[5] + x * gR[6] + y * gR[7]);
        // qn = q / max(|q|, eps)
        if (g.qnorm > s.quat_norm_eps) {
            const double dot = g.qn[0] * gq[0] + g.qn[1] * gq[1] + g.qn[2] * gq[2] + g.qn[3] * gq[3];
            for (int k = 0; k < 4; ++k)
                g_quats[i * 4 + k] = static_cast<float>((gq[k] - g.qn[k] * dot) / g.qnorm);
        } else {
            for (int k = 0; k < 4; ++k) g_quats[i * 4 + k] = static_cast<float>(gq[k] / s.quat_norm_eps);
        }
    }
}

// ---------------------------------------------------------------------------------------
// Sorting and binning
namespace {

// Everything a tile needs of one Gaussian in one cache line (the tile loops visit Gaussians in
// depth order but sparsely: one line per visit instead of one per attribute).
constexpr int kPackedColors = 6;  // colours held in the record (more go to `col`)
struct alignas(64) PackedGaussian {
    float mx, my, a, b, c, op;
    int32_t x0, x1, y0, y1;
    float col[kPackedColors];
};
static_assert(sizeof(PackedGaussian) == 64, "one cache line per Gaussian");
constexpr int kPrefetch = 8;  // records fetched ahead in a tile's list

struct SortedGaussians {
    int64_t count = 0;
    int channels = 0;
    std::vector<int32_t> gid;  // original index, in depth order
    std::vector<float> col;    // [count * channels], only when channels > kPackedColors
    std::vector<int32_t> x0, x1, y0, y1;
    std::vector<PackedGaussian> packed;

    const float* colors(int32_t v) const {
        return channels <= kPackedColors ? packed[v].col : &col[static_cast<size_t>(v) * channels];
    }
};

// Stable LSD radix sort of (key, value) pairs by 32-bit key, 11 bits per pass.
void radix_sort(std::vector<uint32_t>& keys, std::vector<int32_t>& vals) {
    const size_t n = keys.size();
    std::vector<uint32_t> k2(n);
    std::vector<int32_t> v2(n);
    constexpr int kBits = 11, kBuckets = 1 << kBits;
    for (int shift = 0; shift < 32; shift += kBits) {
        size_t count[kBuckets + 1] = {0};
        for (size_t i = 0; i < n; ++i) ++count[((keys[i] >> shift) & (kBuckets - 1)) + 1];
        for (int b = 0; b < kBuckets; ++b) count[b + 1] += count[b];
        for (size_t i = 0; i < n; ++i) {
            const size_t dst = count[(keys[i] >> shift) & (kBuckets - 1)]++;
            k2[dst] = keys[i];
            v2[dst] = vals[i];
        }
        keys.swap(k2);
        vals.swap(v2);
    }
}

// A visible Gaussian whose pixel box holds at least one pixel centre.
inline bool drawn(const int32_t* bbox, const uint8_t* visible, int64_t i) {
    return visible[i] && bbox[i * 4] <= bbox[i * 4 + 1] && bbox[i * 4 + 2] <= bbox[i * 4 + 3];
}

void sort_visible(int64_t n, const float* means2d, const float* conics, const float* opac_eff,
                  const float* colors, int channels, const float* depths, const int32_t* bbox,
                  const uint8_t* visible, int threads, SortedGaussians& out) {
    std::vector<uint32_t> keys;
    std::vector<int32_t> ids;
    for (int64_t i = 0; i < n; ++i) {
        if (!drawn(bbox, visible, i)) continue;
        uint32_t key;
        std::memcpy(&key, &depths[i], sizeof(key));
        keys.push_back(key);
        ids.push_back(static_cast<int32_t>(i));
    }
    radix_sort(keys, ids);
    const int64_t V = static_cast<int64_t>(ids.size());
    out.count = V;
    out.channels = channels;
    out.gid = std::move(ids);
    out.x0.resize(V); out.x1.resize(V); out.y0.resize(V); out.y1.resize(V);
    out.packed.resize(V);
    const bool separate = channels > kPackedColors;
    out.col.resize(separate ? static_cast<size_t>(V) * channels : 0);
#pragma omp parallel for num_threads(threads) schedule(static)
    for (int64_t v = 0; v < V; ++v) {
        const int64_t i = out.gid[v];
        PackedGaussian& g = out.packed[v];
        g.mx = means2d[i * 2];
        g.my = means2d[i * 2 + 1];
        g.a = conics[i * 3];
        g.b = conics[i * 3 + 1];
        g.c = conics[i * 3 + 2];
        g.op = opac_eff[i];
        out.x0[v] = g.x0 = bbox[i * 4];
        out.x1[v] = g.x1 = bbox[i * 4 + 1];
        out.y0[v] = g.y0 = bbox[i * 4 + 2];
        out.y1[v] = g.y1 = bbox[i * 4 + 3];
        float* dst = separate ? &out.col[static_cast<size_t>(v) * channels] : g.col;
        for (int c = 0; c < channels; ++c) dst[c] = colors[i * channels + c];
        for (int c = separate ? 0 : channels; c < kPackedColors; ++c) g.col[c] = 0.0f;
    }
}

struct TileGrid {
    int width, height, tiles_x, tiles_y;
    int64_t num_tiles;
    std::vector<int64_t> counts;               // intersections per tile
    std::vector<std::pair<int64_t, int64_t>> chunks;  // [begin, end) tile ranges
    int64_t total = 0;
};

void count_and_plan(const SortedGaussians& S, int width, int height, int64_t max_per_chunk,
                    TileGrid& grid) {
    grid.width = width;
    grid.height = height;
    grid.tiles_x = (width + kTileSize - 1) / kTileSize;
    grid.tiles_y = (height + kTileSize - 1) / kTileSize;
    grid.num_tiles = static_cast<int64_t>(grid.tiles_x) * grid.tiles_y;
    const int64_t stride = grid.tiles_x + 1;
    std::vector<int64_t> diff(static_cast<size_t>(grid.tiles_y) * stride, 0);
    for (int64_t v = 0; v < S.count; ++v) {
        const int tx0 = S.x0[v] / kTileSize, tx1 = S.x1[v] / kTileSize;
        const int ty0 = S.y0[v] / kTileSize, ty1 = S.y1[v] / kTileSize;
        for (int ty = ty0; ty <= ty1; ++ty) {
            diff[ty * stride + tx0] += 1;
            diff[ty * stride + tx1 + 1] -= 1;
        }
    }
    grid.counts.assign(grid.num_tiles, 0);
    grid.total = 0;
    for (int ty = 0; ty < grid.tiles_y; ++ty) {
        int64_t run = 0;
        for (int tx = 0; tx < grid.tiles_x; ++tx) {
            run += diff[ty * stride + tx];
            grid.counts[static_cast<int64_t>(ty) * grid.tiles_x + tx] = run;
            grid.total += run;
        }
    }
    grid.chunks.clear();
    int64_t begin = 0, acc = 0;
    for (int64_t t = 0; t < grid.num_tiles; ++t) {
        if (t > begin && acc + grid.counts[t] > max_per_chunk) {
            grid.chunks.emplace_back(begin, t);
            begin = t;
            acc = 0;
        }
        acc += grid.counts[t];
    }
    grid.chunks.emplace_back(begin, grid.num_tiles);
}

// Depth-ordered Gaussian lists (ranks into S) for tiles [tb, te).
void fill_chunk(const SortedGaussians& S, const TileGrid& grid, int64_t tb, int64_t te,
                std::vector<int64_t>& offsets, std::vector<int32_t>& list) {
    const int64_t nt = te - tb;
    offsets.assign(nt + 1, 0);
    for (int64_t t = 0; t < nt; ++t) offsets[t + 1] = offsets[t] + grid.counts[tb + t];
    list.resize(offsets[nt]);
    std::vector<int64_t> cursor(offsets.begin(), offsets.end() - 1);
    const int TW = grid.tiles_x;
    const int row_b = static_cast<int>(tb / TW), row_e = static_cast<int>((te - 1) / TW);
    for (int64_t v = 0; v < S.count; ++v) {
        const int ty0 = std::max(S.y0[v] / kTileSize, row_b);
        const int ty1 = std::min(S.y1[v] / kTileSize, row_e);
        if (ty0 > ty1) continue;
        const int tx0 = S.x0[v] / kTileSize, tx1 = S.x1[v] / kTileSize;
        for (int ty = ty0; ty <= ty1; ++ty) {
            const int64_t lo = std::max<int64_t>(static_cast<int64_t>(ty) * TW + tx0, tb);
            const int64_t hi = std::min<int64_t>(static_cast<int64_t>(ty) * TW + tx1, te - 1);
            for (int64_t t = lo; t <= hi; ++t) list[cursor[t - tb]++] = static_cast<int32_t>(v);
        }
    }
}

struct TileRect {
    int X0, Y0, w, h;
};

inline TileRect tile_rect(const TileGrid& grid, int64_t tile) {
    TileRect r;
    const int tx = static_cast<int>(tile % grid.tiles_x), ty = static_cast<int>(tile / grid.tiles_x);
    r.X0 = tx * kTileSize;
    r.Y0 = ty * kTileSize;
    r.w = std::min(kTileSize, grid.width - r.X0);
    r.h = std::min(kTileSize, grid.height - r.Y0);
    return r;
}

// A tile row is two 8-lane halves (one AVX2 vector each); a Gaussian only visits the halves
// its box touches, and whole halves are skipped when nothing there can change.
constexpr int kHalf = kTileSize / 2;

inline uint32_t span_bits(int lx0, int lx1) {
    return ((2u << lx1) - 1u) & ~((1u << lx0) - 1u);
}

// ---- forward, one tile ----
struct ForwardScratch {
    alignas(64) float T[kTilePixels];
    alignas(64) float thr[kTilePixels];  // alpha_min, or 2 once the pixel is finished
    alignas(64) int32_t last[kTilePixels];
    uint32_t done_bits[kTileSize];  // per row, bit l set once pixel l is finished (or outside)
    std::vector<float> acc;         // [C][256]
};

// One Gaussian on the 8 pixels of one half-row (lanes off .. off + 7): alpha, the blend test,
// transmittance, last index, finished pixels, and the colour accumulation, on one vector.
// Returns the lanes that finished here (bit l = pixel off + l). NC > 0: the channel count,
// known at compile time; NC == 0: `channels` at run time.
template <int NC>
inline uint32_t forward_half(float* T, float* thr, int32_t* last, float* acc, int channels, const float* col,
                             v8f dx, v8i inside, float ha, float bdy, float rowc, float op, float amax,
                             float tmin, int32_t k) {
    const v8f sigma = sigma_at8(ha, bdy, rowc, dx);
    v8f alpha = v8_splat(op) * fast_exp8(-sigma);
    alpha = alpha > v8_splat(amax) ? v8_splat(amax) : alpha;
    const v8f Tl = v8_load(T), th = v8_load(thr);
    const v8i valid = inside & (sigma >= v8_splat(0.0f)) & (alpha >= th);
    const v8f Tn = Tl * (v8_splat(1.0f) - alpha);
    const v8i below = Tn <= v8_splat(tmin);  // gsplat: next_T <= 1e-4f, exclusive
    const v8i stop = valid & below;
    const v8i blend = valid & ~below;
    const v8f w = blend ? alpha * Tl : v8_splat(0.0f);
    v8_store(T, blend ? Tn : Tl);
    stg_math::v8i_store(last, blend ? stg_math::v8i_splat(k) : stg_math::v8i_load(last));
    v8_store(thr, stop ? v8_splat(2.0f) : th);
    const int C = NC > 0 ? NC : channels;
    for (int ch = 0; ch < C; ++ch) {
        float* a = acc + static_cast<size_t>(ch) * kTilePixels;
        v8_store(a, v8_madd(w, v8_splat(col[ch]), v8_load(a)));
    }
    return stg_math::v8_movemask(stop);
}

template <int NC>
void forward_tile(const SortedGaussians& S, const TileRect& r, const int32_t* list, int64_t len,
                  const Settings& s, ForwardScratch& sc, float* out_color, float* out_T,
                  int32_t* out_last, int width) {
    const int C = S.channels;
    if (len == 0) {  // nothing here (most tiles of a sparse view): write the empty result directly
        for (int ly = 0; ly < r.h; ++ly) {
            const int64_t pix = static_cast<int64_t>(r.Y0 + ly) * width + r.X0;
            std::fill(out_T + pix, out_T + pix + r.w, 1.0f);
            std::fill(out_last + pix, out_last + pix + r.w, -1);
            std::fill(out_color + pix * C, out_color + (pix + r.w) * C, 0.0f);
        }
        return;
    }
    const float amin = s.alpha_min, amax = s.alpha_max, tmin = s.transmittance_min;
    float* acc = sc.acc.data();
    std::fill(acc, acc + static_cast<size_t>(C) * kTilePixels, 0.0f);
    for (int p = 0; p < kTilePixels; ++p) {
        sc.T[p] = 1.0f;
        sc.last[p] = -1;
        const int ly = p / kTileSize, lx = p % kTileSize;
        sc.thr[p] = (ly < r.h && lx < r.w) ? amin : 2.0f;
    }
    for (int ly = 0; ly < kTileSize; ++ly)
        sc.done_bits[ly] = ly < r.h ? ~span_bits(0, r.w - 1) & 0xFFFFu : 0xFFFFu;
    alignas(64) float px[kTileSize];
    for (int l = 0; l < kTileSize; ++l) px[l] = static_cast<float>(r.X0 + l) + 0.5f;
    const v8f px0 = v8_load(px), px1 = v8_load(px + kHalf);
    const v8i lane = {0, 1, 2, 3, 4, 5, 6, 7};
    const int active = r.w * r.h;
    int finished = 0;
    for (int64_t k = 0; k < len && finished < active; ++k) {
        // The tile's list jumps through the depth-sorted records: fetch a few ahead (the hardware
        // prefetcher cannot follow the indirection), or every visit waits on memory.
        if (k + kPrefetch < len) __builtin_prefetch(&S.packed[list[k + kPrefetch]]);
        const int32_t v = list[k];
        const PackedGaussian& g = S.packed[v];
        const float mx = g.mx, my = g.my, op = g.op;
        const float ha = 0.5f * g.a, b = g.b, hc = 0.5f * g.c;
        const int lx0 = std::max(g.x0 - r.X0, 0), lx1 = std::min(g.x1 - r.X0, kTileSize - 1);
        const int ly0 = std::max(g.y0 - r.Y0, 0), ly1 = std::min(g.y1 - r.Y0, r.h - 1);
        const float* col = S.colors(v);
        const int32_t kk = static_cast<int32_t>(k);
        const uint32_t span = span_bits(lx0, lx1);
        // The 8-lane halves the box touches, with the lanes inside the box, and dx per lane.
        const bool use0 = lx0 < kHalf, use1 = lx1 >= kHalf;
        const v8i in0 = (lane >= stg_math::v8i_splat(lx0)) & (lane <= stg_math::v8i_splat(lx1));
        const v8i in1 = (lane >= stg_math::v8i_splat(lx0 - kHalf)) & (lane <= stg_math::v8i_splat(lx1 - kHalf));
        const uint32_t span0 = span & 0xFFu, span1 = span >> kHalf;
        const v8f dx0 = v8_splat(mx) - px0, dx1 = v8_splat(mx) - px1;
        for (int ly = ly0; ly <= ly1; ++ly) {
            const uint32_t done = sc.done_bits[ly];
            if ((done & span) == span) continue;  // every pixel it could touch is done
            const float dy = my - (static_cast<float>(r.Y0 + ly) + 0.5f);
            const float bdy = b * dy, rowc = hc * dy * dy;
            const int row = ly * kTileSize;
            uint32_t stops = 0;
            if (use0 && (done & span0) != span0)
                stops |= forward_half<NC>(sc.T + row, sc.thr + row, sc.last + row, acc + row, C, col, dx0, in0,
                                          ha, bdy, rowc, op, amax, tmin, kk);
            if (use1 && ((done >> kHalf) & span1) != span1)
                stops |= forward_half<NC>(sc.T + row + kHalf, sc.thr + row + kHalf, sc.last + row + kHalf,
                                          acc + row + kHalf, C, col, dx1, in1, ha, bdy, rowc, op, amax, tmin, kk)
                         << kHalf;
            if (stops) {
                finished += __builtin_popcount(stops);
                sc.done_bits[ly] |= stops;
            }
        }
    }
    for (int ly = 0; ly < r.h; ++ly) {
        const int row = ly * kTileSize;
        const int64_t pix = static_cast<int64_t>(r.Y0 + ly) * width + r.X0;
        std::copy(sc.T + row, sc.T + row + r.w, out_T + pix);
        std::copy(sc.last + row, sc.last + row + r.w, out_last + pix);
        float* out = out_color + pix * C;
        for (int ch = 0; ch < C; ++ch) {
            const float* a = acc + static_cast<size_t>(ch) * kTilePixels + row;
            for (int lx = 0; lx < r.w; ++lx) out[lx * C + ch] = a[lx];
        }
    }
}

using ForwardTileFn = void (*)(const SortedGaussians&, const TileRect&, const int32_t*, int64_t,
                               const Settings&, ForwardScratch&, float*, float*, int32_t*, int);

// The forward tile for a channel count: unrolled for the counts renders use (RGB, + depth,
// + flow, + flow and depth), a run-time loop otherwise.
ForwardTileFn forward_tile_for(int channels) {
    switch (channels) {
        case 3:
            return forward_tile<3>;
        case 4:
            return forward_tile<4>;
        case 5:
            return forward_tile<5>;
        case 6:
            return forward_tile<6>;
        default:
            return forward_tile<0>;
    }
}

// ---- backward, one tile ----
constexpr int kGradStride = 8;  // mx, my, a, b, c, opacity, |mx|, |my|; then C colours

struct BackwardScratch {
    alignas(64) float T[kTilePixels];
    alignas(64) float q[kTilePixels];  // dL/dalpha_out * T_final
    alignas(64) int32_t last[kTilePixels];
    alignas(64) float w[kTileSize], Ti[kTileSize], ra[kTileSize], dA[kTileSize];
    alignas(64) float valid[kTileSize];
    int32_t half_last[kTileSize][2];  // per row and half: the largest `last` there
    std::vector<float> g;    // [C][256] dL/dcolor_out
    std::vector<float> buf;  // [C][256] colour accumulated behind the current Gaussian
    alignas(64) float lanes[kGradStride][kHalf];  // per-lane sums: mx, my, a, b, c, opacity, |mx|, |my|
    std::vector<float> gcol;  // [C][kHalf] per-lane colour gradient sums
};

void backward_tile(const SortedGaussians& S, const TileRect& r, const int32_t* list,
                   const Settings& s, BackwardScratch& sc, const float* T_final,
                   const int32_t* last_in, const float* g_color, const float* g_alpha, int width,
                   float* grads) {
    const int C = S.channels;
    const float amin = s.alpha_min, amax = s.alpha_max;
    std::fill(sc.g.begin(), sc.g.end(), 0.0f);
    std::fill(sc.buf.begin(), sc.buf.end(), 0.0f);
    int32_t kmax = -1;
    for (int p = 0; p < kTilePixels; ++p) {
        sc.T[p] = 1.0f;
        sc.q[p] = 0.0f;
        sc.last[p] = -1;
    }
    for (int ly = 0; ly < kTileSize; ++ly) sc.half_last[ly][0] = sc.half_last[ly][1] = -1;
    for (int ly = 0; ly < r.h; ++ly) {
        const int row = ly * kTileSize;
        const int64_t pix0 = static_cast<int64_t>(r.Y0 + ly) * width + r.X0;
        for (int lx = 0; lx < r.w; ++lx) {
            const int64_t pix = pix0 + lx;
            sc.T[row + lx] = T_final[pix];
            sc.last[row + lx] = last_in[pix];
            sc.q[row + lx] = g_alpha[pix] * T_final[pix];
            int32_t& hl = sc.half_last[ly][lx / kHalf];
            hl = std::max(hl, last_in[pix]);
        }
        kmax = std::max({kmax, sc.half_last[ly][0], sc.half_last[ly][1]});
        const float* g_in = g_color + pix0 * C;
        for (int ch = 0; ch < C; ++ch) {
            float* g = sc.g.data() + static_cast<size_t>(ch) * kTilePixels + row;
            for (int lx = 0; lx < r.w; ++lx) g[lx] = g_in[lx * C + ch];
        }
    }
    if (kmax < 0) return;  // nothing was blended in this tile
    alignas(64) float px[kTileSize];
    for (int l = 0; l < kTileSize; ++l) px[l] = static_cast<float>(r.X0 + l) + 0.5f;

    for (int32_t k = kmax; k >= 0; --k) {
        if (k >= kPrefetch) __builtin_prefetch(&S.packed[list[k - kPrefetch]]);
        const int32_t v = list[k];
        const PackedGaussian& pg = S.packed[v];
        const float mx = pg.mx, my = pg.my, op = pg.op;
        const float a = pg.a, b = pg.b, c = pg.c;
        const float ha = 0.5f * a, hc = 0.5f * c;
        const int lx0 = std::max(pg.x0 - r.X0, 0), lx1 = std::min(pg.x1 - r.X0, kTileSize - 1);
        const int ly0 = std::max(pg.y0 - r.Y0, 0), ly1 = std::min(pg.y1 - r.Y0, r.h - 1);
        const float* col = S.colors(v);
        bool any = false;
        for (int ly = ly0; ly <= ly1; ++ly) {
            const float dy = my - (static_cast<float>(r.Y0 + ly) + 0.5f);
            const float bdy = b * dy, rowc = hc * dy * dy;
            const int row = ly * kTileSize;
            float* T = sc.T + row;
            const float* q = sc.q + row;
            const int32_t* last = sc.last + row;
            for (int h = lx0 < kHalf ? 0 : kHalf; h <= lx1; h += kHalf) {
                if (k > sc.half_last[ly][h / kHalf]) continue;  // no pixel here blended it
                int nvalid = 0;
#pragma omp simd reduction(+ : nvalid)
                for (int l = h; l < h + kHalf; ++l) {
                    const float sigma = sigma_at(ha, bdy, rowc, mx - px[l]);
                    float alpha = op * fast_exp(-sigma);
                    alpha = alpha > amax ? amax : alpha;
                    const bool valid = (l >= lx0) & (l <= lx1) & (k <= last[l]) & (sigma >= 0.0f) &
                                       (alpha >= amin);
                    const float ra = 1.0f / (1.0f - alpha);
                    const float Ti = T[l] * ra;
                    sc.valid[l] = valid ? 1.0f : 0.0f;
                    sc.ra[l] = ra;
                    sc.Ti[l] = Ti;
                    sc.w[l] = valid ? alpha * Ti : 0.0f;
                    sc.dA[l] = valid ? q[l] * ra : 0.0f;
                    nvalid += valid ? 1 : 0;
                }
                if (nvalid == 0) continue;
                if (!any) {  // lane-wise accumulators, reduced once per Gaussian (not per row)
                    std::fill(sc.gcol.begin(), sc.gcol.end(), 0.0f);
                    std::fill(&sc.lanes[0][0], &sc.lanes[0][0] + kGradStride * kHalf, 0.0f);
                    any = true;
                }
                for (int ch = 0; ch < C; ++ch) {
                    const float cv = col[ch];
                    const float* g = sc.g.data() + static_cast<size_t>(ch) * kTilePixels + row;
                    float* buf = sc.buf.data() + static_cast<size_t>(ch) * kTilePixels + row;
                    float* gl = sc.gcol.data() + static_cast<size_t>(ch) * kHalf;
#pragma omp simd
                    for (int l = h; l < h + kHalf; ++l) {
                        gl[l - h] += sc.w[l] * g[l];
                        sc.dA[l] += sc.valid[l] * g[l] * (cv * sc.Ti[l] - buf[l] * sc.ra[l]);
                        buf[l] += cv * sc.w[l];
                    }
                }
                float* L0 = sc.lanes[0];
                float* L1 = sc.lanes[1];
                float* L2 = sc.lanes[2];
                float* L3 = sc.lanes[3];
                float* L4 = sc.lanes[4];
                float* L5 = sc.lanes[5];
                float* L6 = sc.lanes[6];
                float* L7 = sc.lanes[7];
#pragma omp simd
                for (int l = h; l < h + kHalf; ++l) {
                    const int j = l - h;
                    const float dx = mx - px[l];
                    const float sigma = sigma_at(ha, bdy, rowc, dx);
                    const float G = fast_exp(-sigma);
                    const float raw = op * G;
                    // Where the clamp was active alpha does not depend on opacity or sigma.
                    const bool live = (sc.valid[l] != 0.0f) & (raw <= amax);
                    const float dA = sc.dA[l];
                    const float dsig = live ? -raw * dA : 0.0f;
                    L5[j] += live ? G * dA : 0.0f;
                    const float gx = dsig * (a * dx + b * dy);
                    const float gy = dsig * (b * dx + c * dy);
                    L0[j] += gx;
                    L1[j] += gy;
                    L6[j] += std::fabs(gx);
                    L7[j] += std::fabs(gy);
                    L2[j] += 0.5f * dsig * dx * dx;
                    L3[j] += dsig * dx * dy;
                    L4[j] += 0.5f * dsig * dy * dy;
                    T[l] = sc.valid[l] != 0.0f ? sc.Ti[l] : T[l];
                }
            }
        }
        if (!any) continue;
        float* gv = grads + static_cast<size_t>(v) * (kGradStride + C);
        for (int q = 0; q < kGradStride; ++q) {
            float sum = 0.0f;
            for (int j = 0; j < kHalf; ++j) sum += sc.lanes[q][j];
            gv[q] += sum;
        }
        for (int ch = 0; ch < C; ++ch) {
            float sum = 0.0f;
            for (int j = 0; j < kHalf; ++j) sum += sc.gcol[static_cast<size_t>(ch) * kHalf + j];
            gv[kGradStride + ch] += sum;
        }
    }
}

// The backward tile for a channel count known at compile time: the three passes of
// backward_tile over a half-row fused into one on 8-lane vectors (exp evaluated once, nothing
// stored between passes), the per-lane accumulators held across the Gaussian's rows. Same
// arithmetic in the same order per lane as backward_tile, so the same gradients.
template <int NC>
void backward_tile_fused(const SortedGaussians& S, const TileRect& r, const int32_t* list,
                         const Settings& s, BackwardScratch& sc, const float* T_final,
                         const int32_t* last_in, const float* g_color, const float* g_alpha, int width,
                         float* grads) {
    constexpr int C = NC;
    const float amin = s.alpha_min, amax = s.alpha_max;
    std::fill(sc.g.begin(), sc.g.end(), 0.0f);
    std::fill(sc.buf.begin(), sc.buf.end(), 0.0f);
    int32_t kmax = -1;
    for (int p = 0; p < kTilePixels; ++p) {
        sc.T[p] = 1.0f;
        sc.q[p] = 0.0f;
        sc.last[p] = -1;
    }
    for (int ly = 0; ly < kTileSize; ++ly) sc.half_last[ly][0] = sc.half_last[ly][1] = -1;
    for (int ly = 0; ly < r.h; ++ly) {
        const int row = ly * kTileSize;
        const int64_t pix0 = static_cast<int64_t>(r.Y0 + ly) * width + r.X0;
        for (int lx = 0; lx < r.w; ++lx) {
            const int64_t pix = pix0 + lx;
            sc.T[row + lx] = T_final[pix];
            sc.last[row + lx] = last_in[pix];
            sc.q[row + lx] = g_alpha[pix] * T_final[pix];
            int32_t& hl = sc.half_last[ly][lx / kHalf];
            hl = std::max(hl, last_in[pix]);
        }
        kmax = std::max({kmax, sc.half_last[ly][0], sc.half_last[ly][1]});
        const float* g_in = g_color + pix0 * C;
        for (int ch = 0; ch < C; ++ch) {
            float* g = sc.g.data() + static_cast<size_t>(ch) * kTilePixels + row;
            for (int lx = 0; lx < r.w; ++lx) g[lx] = g_in[lx * C + ch];
        }
    }
    if (kmax < 0) return;  // nothing was blended in this tile
    alignas(64) float px[kTileSize];
    for (int l = 0; l < kTileSize; ++l) px[l] = static_cast<float>(r.X0 + l) + 0.5f;
    const v8i lane = {0, 1, 2, 3, 4, 5, 6, 7};
    const v8f zero = v8_splat(0.0f), one = v8_splat(1.0f);

    for (int32_t k = kmax; k >= 0; --k) {
        if (k >= kPrefetch) __builtin_prefetch(&S.packed[list[k - kPrefetch]]);
        const int32_t v = list[k];
        const PackedGaussian& pg = S.packed[v];
        const float mx = pg.mx, my = pg.my, op = pg.op;
        const float a = pg.a, b = pg.b, c = pg.c;
        const float ha = 0.5f * a, hc = 0.5f * c;
        const int lx0 = std::max(pg.x0 - r.X0, 0), lx1 = std::min(pg.x1 - r.X0, kTileSize - 1);
        const int ly0 = std::max(pg.y0 - r.Y0, 0), ly1 = std::min(pg.y1 - r.Y0, r.h - 1);
        const float* col = S.colors(v);
        v8f L[kGradStride], gcol[C];
        for (v8f& x : L) x = zero;
        for (v8f& x : gcol) x = zero;
        bool any = false;
        for (int ly = ly0; ly <= ly1; ++ly) {
            const float dy = my - (static_cast<float>(r.Y0 + ly) + 0.5f);
            const float bdy = b * dy, rowc = hc * dy * dy;
            const v8f vdy = v8_splat(dy);
            const int row = ly * kTileSize;
            for (int h = lx0 < kHalf ? 0 : kHalf; h <= lx1; h += kHalf) {
                if (k > sc.half_last[ly][h / kHalf]) continue;  // no pixel here blended it
                float* T = sc.T + row + h;
                const v8i inside = (lane >= stg_math::v8i_splat(lx0 - h)) & (lane <= stg_math::v8i_splat(lx1 - h));
                const v8f dx = v8_splat(mx) - v8_load(px + h);
                const v8f sigma = sigma_at8(ha, bdy, rowc, dx);
                const v8f G = fast_exp8(-sigma);
                const v8f raw = v8_splat(op) * G;
                const v8f alpha = raw > v8_splat(amax) ? v8_splat(amax) : raw;
                const v8i valid = inside & (stg_math::v8i_splat(k) <= stg_math::v8i_load(sc.last + row + h)) &
                                  (sigma >= zero) & (alpha >= v8_splat(amin));
                if (stg_math::v8_movemask(valid) == 0) continue;
                any = true;
                const v8f Tl = v8_load(T);
                const v8f ra = one / (one - alpha);
                const v8f Ti = Tl * ra;
                const v8f validf = valid ? one : zero;
                const v8f w = valid ? alpha * Ti : zero;
                v8f dA = valid ? v8_load(sc.q + row + h) * ra : zero;
                for (int ch = 0; ch < C; ++ch) {
                    const v8f cv = v8_splat(col[ch]);
                    const v8f g = v8_load(sc.g.data() + static_cast<size_t>(ch) * kTilePixels + row + h);
                    float* bp = sc.buf.data() + static_cast<size_t>(ch) * kTilePixels + row + h;
                    const v8f bufv = v8_load(bp);
                    gcol[ch] = gcol[ch] + w * g;
                    dA = dA + (validf * g) * (cv * Ti - bufv * ra);
                    v8_store(bp, bufv + cv * w);
                }
                // Where the clamp was active alpha does not depend on opacity or sigma.
                const v8i live = valid & (raw <= v8_splat(amax));
                const v8f dsig = live ? -raw * dA : zero;
                L[5] = L[5] + (live ? G * dA : zero);
                const v8f gx = dsig * (v8_splat(a) * dx + v8_splat(b) * vdy);
                const v8f gy = dsig * (v8_splat(b) * dx + v8_splat(c) * vdy);
                L[0] = L[0] + gx;
                L[1] = L[1] + gy;
                L[6] = L[6] + (gx < zero ? -gx : gx);
                L[7] = L[7] + (gy < zero ? -gy : gy);
                L[2] = L[2] + v8_splat(0.5f) * dsig * dx * dx;
                L[3] = L[3] + dsig * dx * vdy;
                L[4] = L[4] + v8_splat(0.5f) * dsig * vdy * vdy;
                v8_store(T, valid ? Ti : Tl);
            }
        }
        if (!any) continue;
        float* gv = grads + static_cast<size_t>(v) * (kGradStride + C);
        for (int q = 0; q < kGradStride; ++q) {
            float sum = 0.0f;
            for (int j = 0; j < kHalf; ++j) sum += L[q][j];
            gv[q] += sum;
        }
        for (int ch = 0; ch < C; ++ch) {
            float sum = 0.0f;
            for (int j = 0; j < kHalf; ++j) sum += gcol[ch][j];
            gv[kGradStride + ch] += sum;
        }
    }
}

using BackwardTileFn = void (*)(const SortedGaussians&, const TileRect&, const int32_t*, const Settings&,
                                BackwardScratch&, const float*, const int32_t*, const float*, const float*, int,
                                float*);

BackwardTileFn backward_tile_for(int channels) {
    switch (channels) {
        case 3:
            return backward_tile_fused<3>;
        case 4:
            return backward_tile_fused<4>;
        case 5:
            return backward_tile_fused<5>;
        case 6:
            return backward_tile_fused<6>;
        default:
            return backward_tile;
    }
}

}  // namespace

void count_intersections(int64_t n, const int32_t* bbox, const uint8_t* visible, int width,
                         int height, int64_t max_per_chunk, int64_t* total, int64_t* chunks) {
    SortedGaussians S;  // only the boxes matter for counting; order is irrelevant
    for (int64_t i = 0; i < n; ++i) {
        if (!drawn(bbox, visible, i)) continue;
        S.x0.push_back(bbox[i * 4]);
        S.x1.push_back(bbox[i * 4 + 1]);
        S.y0.push_back(bbox[i * 4 + 2]);
        S.y1.push_back(bbox[i * 4 + 3]);
    }
    S.count = static_cast<int64_t>(S.x0.size());
    TileGrid grid;
    count_and_plan(S, width, height, max_per_chunk, grid);
    *total = grid.total;
    *chunks = static_cast<int64_t>(grid.chunks.size());
}

void rasterize_forward(int64_t n, const float* means2d, const float* conics, const float* opac_eff,
                       const float* colors, int channels, const float* depths, const int32_t* bbox,
                       const uint8_t* visible, int width, int height, const Settings& s,
                       float* out_color, float* out_T, int32_t* out_last, RasterStats* stats) {
    auto t0 = Clock::now();
    SortedGaussians S;
    sort_visible(n, means2d, conics, opac_eff, colors, channels, depths, bbox, visible, s.threads, S);
    stats->ms_sort = ms_since(t0);
    stats->n_drawn = S.count;

    t0 = Clock::now();
    TileGrid grid;
    count_and_plan(S, width, height, s.max_intersections_per_chunk, grid);
    stats->n_intersections = grid.total;
    stats->n_chunks = static_cast<int64_t>(grid.chunks.size());
    double ms_bin = ms_since(t0), ms_raster = 0.0;

    std::vector<int64_t> offsets;
    std::vector<int32_t> list;
    for (const auto& chunk : grid.chunks) {
        t0 = Clock::now();
        fill_chunk(S, grid, chunk.first, chunk.second, offsets, list);
        ms_bin += ms_since(t0);
        t0 = Clock::now();
        const int64_t tb = chunk.first, nt = chunk.second - chunk.first;
#pragma omp parallel num_threads(s.threads)
        {
            ForwardScratch sc;
            sc.acc.resize(static_cast<size_t>(channels) * kTilePixels);
            const ForwardTileFn tile_fn = forward_tile_for(channels);
#pragma omp for schedule(dynamic, 1)
            for (int64_t t = 0; t < nt; ++t) {
                const TileRect r = tile_rect(grid, tb + t);
                tile_fn(S, r, list.data() + offsets[t], offsets[t + 1] - offsets[t], s, sc, out_color, out_T,
                        out_last, width);
            }
        }
        ms_raster += ms_since(t0);
    }
    stats->ms_bin = ms_bin;
    stats->ms_raster = ms_raster;
}

void rasterize_backward(int64_t n, const float* means2d, const float* conics, const float* opac_eff,
                        const float* colors, int channels, const float* depths,
                        const int32_t* bbox, const uint8_t* visible, int width, int height,
                        const Settings& s, const float* T_final, const int32_t* last,
                        const float* g_color, const float* g_alpha, float* g_means2d,
                        float* g_conics, float* g_opac_eff, float* g_colors, float* g_abs_means2d,
                        RasterStats* stats) {
    const int C = channels;
    std::fill(g_means2d, g_means2d + n * 2, 0.0f);
    std::fill(g_conics, g_conics + n * 3, 0.0f);
    std::fill(g_opac_eff, g_opac_eff + n, 0.0f);
    std::fill(g_colors, g_colors + n * C, 0.0f);
    std::fill(g_abs_means2d, g_abs_means2d + n * 2, 0.0f);

    auto t0 = Clock::now();
    SortedGaussians S;
    sort_visible(n, means2d, conics, opac_eff, colors, channels, depths, bbox, visible, s.threads, S);
    stats->ms_sort = ms_since(t0);
    stats->n_drawn = S.count;
    t0 = Clock::now();
    TileGrid grid;
    count_and_plan(S, width, height, s.max_intersections_per_chunk, grid);
    stats->n_intersections = grid.total;
    stats->n_chunks = static_cast<int64_t>(grid.chunks.size());
    double ms_bin = ms_since(t0), ms_raster = 0.0;

    const int threads = std::max(1, s.threads);
    const size_t stride = kGradStride + C;
    std::vector<std::vector<float>> per_thread(threads);
    std::vector<int64_t> offsets;
    std::vector<int32_t> list;
    for (const auto& chunk : grid.chunks) {
        t0 = Clock::now();
        fill_chunk(S, grid, chunk.first, chunk.second, offsets, list);
        ms_bin += ms_since(t0);
        t0 = Clock::now();
        const int64_t tb = chunk.first, nt = chunk.second - chunk.first;
#pragma omp parallel num_threads(threads)
        {
            const int tid = omp_get_thread_num();
            std::vector<float>& grads = per_thread[tid];
            if (grads.empty()) grads.assign(static_cast<size_t>(S.count) * stride, 0.0f);
            BackwardScratch sc;
            sc.g.resize(static_cast<size_t>(C) * kTilePixels);
            sc.buf.resize(static_cast<size_t>(C) * kTilePixels);
            sc.gcol.resize(static_cast<size_t>(C) * kHalf);
            const BackwardTileFn tile_fn = backward_tile_for(C);
#pragma omp for schedule(dynamic, 1)
            for (int64_t t = 0; t < nt; ++t) {
                if (offsets[t + 1] == offsets[t]) continue;
                const TileRect r = tile_rect(grid, tb + t);
                tile_fn(S, r, list.data() + offsets[t], s, sc, T_final, last, g_color, g_alpha, width, grads.data());
            }
        }
        ms_raster += ms_since(t0);
    }
    stats->ms_bin = ms_bin;
    stats->ms_raster = ms_raster;

    t0 = Clock::now();
#pragma omp parallel for num_threads(threads) schedule(static)
    for (int64_t v = 0; v < S.count; ++v) {
        float sum[kGradStride] = {0};
        const int64_t i = S.gid[v];
        for (int th = 0; th < threads; ++th) {
            if (per_thread[th].empty()) continue;
            const float* gv = per_thread[th].data() + static_cast<size_t>(v) * stride;
            for (int j = 0; j < kGradStride; ++j) sum[j] += gv[j];
            for (int ch = 0; ch < C; ++ch) g_colors[i * C + ch] += gv[kGradStride + ch];
        }
        g_means2d[i * 2] = sum[0];
        g_means2d[i * 2 + 1] = sum[1];
        g_conics[i * 3] = sum[2];
        g_conics[i * 3 + 1] = sum[3];
        g_conics[i * 3 + 2] = sum[4];
        g_opac_eff[i] = sum[5];
        g_abs_means2d[i * 2] = sum[6];
        g_abs_means2d[i * 2 + 1] = sum[7];
    }
    stats->ms_reduce = ms_since(t0);
}

}  // namespace stg_splat
