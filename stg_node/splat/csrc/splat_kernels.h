// CPU kernels of stg_node's Gaussian rasterizer: projection, binning, tile rasterization and
// their hand-written backward passes. Plain C++17 + OpenMP on raw arrays (no torch headers),
// so this translation unit compiles fast and can be read on its own; splat_bindings.cpp wraps
// it for torch. Every numeric constant arrives in `Settings` from stg_node/splat/constants.py
// at each call; only the tile size is compiled in (it sizes the per-tile buffers).
#pragma once

#include <cstdint>

namespace stg_splat {

constexpr int kTileSize = 16;
constexpr int kTilePixels = kTileSize * kTileSize;

// Indices into the `settings` vector passed from Python (stg_node/splat/cpu_backend.py
// builds it in this order).
enum SettingIndex : int {
    kNearPlane = 0,
    kFarPlane,
    kEps2d,
    kRadiusClip,
    kAlphaMin,
    kAlphaMax,
    kTransmittanceMin,
    kSigmaExtentMax,
    kQuatNormEps,
    kCompensationGradEps,
    kFrustumMargin,
    kAntialiased,
    kMaxIntersectionsPerChunk,
    kRadiusReportMax,
    kNumSettings
};

struct Settings {
    double near_plane, far_plane, eps2d, radius_clip;
    float alpha_min, alpha_max, transmittance_min;
    double sigma_extent_max, quat_norm_eps, compensation_grad_eps, frustum_margin;
    bool antialiased;
    int64_t max_intersections_per_chunk;
    int64_t radius_report_max;
    int threads;
};

struct Camera {
    double R[9];  // world -> camera rotation, row-major
    double t[3];
    double fx, fy, cx, cy;
    int width, height;
};

// ---- projection: world-space 3D Gaussians -> screen-space 2D Gaussians -------------------
// Per Gaussian i (arrays are row-major, float32):
//   means2d[i*2+{0,1}]  pixel coordinates of the projected centre (0 when culled)
//   conics[i*3+{0,1,2}] inverse 2D covariance (a, b, c) after the eps2d dilation
//   depths[i]           camera-space z (0 when culled)
//   opac_eff[i]         opacity times the anti-aliasing compensation (= opacity if off)
//   comp[i]             the compensation (1 when anti-aliasing is off)
//   radii[i*2+{0,1}]    screen radius in pixels along x and y (0 when culled)
//   bbox[i*4+{0..3}]    inclusive pixel box x0, x1, y0, y1 clipped to the image; empty
//                       (0, -1, 0, -1) when no pixel centre lies within the radius
//   visible[i]          1 if not culled (gsplat's rules: radius > 0, box overlapping the image)
void project_forward(int64_t n, const float* means, const float* quats, const float* scales,
                     const float* opacities, const Camera& cam, const Settings& s, float* means2d,
                     float* conics, float* depths, float* opac_eff, float* comp, int32_t* radii,
                     int32_t* bbox, uint8_t* visible);

// Chain rule from the screen-space gradients to the 3D parameters (float32 in and out,
// double inside). Culled Gaussians get zero gradients.
void project_backward(int64_t n, const float* means, const float* quats, const float* scales,
                      const float* opacities, const Camera& cam, const Settings& s,
                      const uint8_t* visible, const float* g_means2d, const float* g_conics,
                      const float* g_depths, const float* g_opac_eff, float* g_means,
                      float* g_quats, float* g_scales, float* g_opacities);

// Conservative frustum test before projection (stg_node/splat/culling.py is the reference):
// out[i] = 0 only for Gaussians project_forward culls by depth or whose screen box misses the
// image, bounding the box by `sigma_extent_max` x sqrt(|J_x|^2 max(scale)^2 + eps2d) + margin.
// NaN inputs are kept (the caller's checks see them).
void may_be_visible(int64_t n, const float* means, const float* scales, const Camera& cam,
                    const Settings& s, double margin_px, uint8_t* out);

// ---- rasterization ------------------------------------------------------------------------
// Stage timings (milliseconds) and counters reported back to Python.
struct RasterStats {
    double ms_sort = 0, ms_bin = 0, ms_raster = 0, ms_reduce = 0;
    int64_t n_drawn = 0, n_intersections = 0, n_chunks = 0;
};

// Counts tile intersections (int64) and the number of chunks rasterize_forward would use,
// without rasterizing: a cheap check that huge scenes stay within bounds.
void count_intersections(int64_t n, const int32_t* bbox, const uint8_t* visible, int width,
                         int height, int64_t max_per_chunk, int64_t* total, int64_t* chunks);

// Front-to-back alpha compositing of the visible Gaussians, depth sorted, in 16x16 tiles.
// Outputs: out_color [H*W*C] (no background), out_T [H*W] final transmittance, out_last [H*W]
// index (within its tile's depth-sorted list) of the last Gaussian blended there, -1 if none.
void rasterize_forward(int64_t n, const float* means2d, const float* conics, const float* opac_eff,
                       const float* colors, int channels, const float* depths, const int32_t* bbox,
                       const uint8_t* visible, int width, int height, const Settings& s,
                       float* out_color, float* out_T, int32_t* out_last, RasterStats* stats);

// Backward of rasterize_forward given dL/d(color) [H*W*C] and dL/d(alpha) [H*W]. Writes
// dL/d(means2d) [n*2], dL/d(conics) [n*3], dL/d(opac_eff) [n], dL/d(colors) [n*C] and the
// per-Gaussian sum over pixels of |dL/d(means2d)| (AbsGS) into g_abs_means2d [n*2].
void rasterize_backward(int64_t n, const float* means2d, const float* conics, const float* opac_eff,
                        const float* colors, int channels, const float* depths,
                        const int32_t* bbox, const uint8_t* visible, int width, int height,
                        const Settings& s, const float* T_final, const int32_t* last,
                        const float* g_color, const float* g_alpha, float* g_means2d,
                        float* g_conics, float* g_opac_eff, float* g_colors, float* g_abs_means2d,
                        RasterStats* stats);

}  // namespace stg_splat
