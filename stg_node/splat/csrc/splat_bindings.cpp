// torch operator wrappers for the CPU splat kernels (splat_kernels.h), the image-space
// kernels of splatting losses (image_filter.h), and the per-Gaussian kernels of splatting models
// (skinning.h, small_mlp.h). Registered with
// TORCH_LIBRARY (no pybind11), so the extension compiles quickly and is called through
// torch.ops.<namespace>.*; the namespace is passed in as STG_SPLAT_NS by the build so that a
// rebuilt extension (new sources or flags) never clashes with an older one in one process.
#include <ATen/ATen.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <string>
#include <tuple>
#include <vector>

#include "densify_stats.h"
#include "edge_loss.h"
#include "image_filter.h"
#include "kinematics.h"
#include "scale_cap.h"
#include "skinning.h"
#include "small_mlp.h"
#include "distant_shading.h"
#include "sphere_occlusion.h"
#include "splat_kernels.h"

#ifndef STG_SPLAT_NS
#error "STG_SPLAT_NS must name the operator namespace"
#endif

namespace {

using stg_splat::Camera;
using stg_splat::Settings;

void check_cpu_float(const at::Tensor& t, const char* name, int64_t rows, int64_t cols) {
    TORCH_CHECK(t.device().is_cpu(), name, " must be a CPU tensor");
    TORCH_CHECK(t.scalar_type() == at::kFloat, name, " must be float32, got ", t.scalar_type());
    TORCH_CHECK(t.is_contiguous(), name, " must be contiguous");
    TORCH_CHECK(t.size(0) == rows, name, " must have ", rows, " rows, got ", t.size(0));
    if (cols > 0) {
        TORCH_CHECK(t.dim() == 2 && t.size(1) == cols, name, " must be [", rows, ", ", cols, "], got ",
                    t.sizes());
    }
}

Settings make_settings(c10::ArrayRef<double> v, int64_t threads) {
    TORCH_CHECK(static_cast<int64_t>(v.size()) == stg_splat::kNumSettings, "settings must have ",
                static_cast<int>(stg_splat::kNumSettings), " entries, got ", v.size());
    Settings s;
    s.near_plane = v[stg_splat::kNearPlane];
    s.far_plane = v[stg_splat::kFarPlane];
    s.eps2d = v[stg_splat::kEps2d];
    s.radius_clip = v[stg_splat::kRadiusClip];
    s.alpha_min = static_cast<float>(v[stg_splat::kAlphaMin]);
    s.alpha_max = static_cast<float>(v[stg_splat::kAlphaMax]);
    s.transmittance_min = static_cast<float>(v[stg_splat::kTransmittanceMin]);
    s.sigma_extent_max = v[stg_splat::kSigmaExtentMax];
    s.quat_norm_eps = v[stg_splat::kQuatNormEps];
    s.compensation_grad_eps = v[stg_splat::kCompensationGradEps];
    s.frustum_margin = v[stg_splat::kFrustumMargin];
    s.antialiased = v[stg_splat::kAntialiased] != 0.0;
    s.max_intersections_per_chunk = static_cast<int64_t>(v[stg_splat::kMaxIntersectionsPerChunk]);
    s.radius_report_max = static_cast<int64_t>(v[stg_splat::kRadiusReportMax]);
    TORCH_CHECK(threads >= 1, "threads must be >= 1");
    s.threads = static_cast<int>(threads);
    return s;
}

Camera make_camera(const at::Tensor& viewmat, const at::Tensor& K, int64_t width, int64_t height) {
    TORCH_CHECK(viewmat.scalar_type() == at::kDouble && viewmat.device().is_cpu() &&
                    viewmat.numel() == 16,
                "viewmat must be a float64 CPU [4, 4] tensor");
    TORCH_CHECK(K.scalar_type() == at::kDouble && K.device().is_cpu() && K.numel() == 9,
                "K must be a float64 CPU [3, 3] tensor");
    const at::Tensor vm = viewmat.contiguous(), kk = K.contiguous();
    const double* v = vm.data_ptr<double>();
    const double* k = kk.data_ptr<double>();
    Camera cam;
    for (int r = 0; r < 3; ++r) {
        for (int c = 0; c < 3; ++c) cam.R[r * 3 + c] = v[r * 4 + c];
        cam.t[r] = v[r * 4 + 3];
    }
    cam.fx = k[0];
    cam.cx = k[2];
    cam.fy = k[4];
    cam.cy = k[5];
    cam.width = static_cast<int>(width);
    cam.height = static_cast<int>(height);
    return cam;
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor,
           at::Tensor>
project_fwd(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
            const at::Tensor& opacities, const at::Tensor& viewmat, const at::Tensor& K,
            int64_t width, int64_t height, c10::ArrayRef<double> settings, int64_t threads) {
    const int64_t n = means.size(0);
    check_cpu_float(means, "means", n, 3);
    check_cpu_float(quats, "quats", n, 4);
    check_cpu_float(scales, "scales", n, 3);
    check_cpu_float(opacities, "opacities", n, 0);
    const Settings s = make_settings(settings, threads);
    const Camera cam = make_camera(viewmat, K, width, height);
    const auto f32 = means.options();
    at::Tensor means2d = at::empty({n, 2}, f32);
    at::Tensor conics = at::empty({n, 3}, f32);
    at::Tensor depths = at::empty({n}, f32);
    at::Tensor opac_eff = at::empty({n}, f32);
    at::Tensor comp = at::empty({n}, f32);
    at::Tensor radii = at::empty({n, 2}, f32.dtype(at::kInt));
    at::Tensor bbox = at::empty({n, 4}, f32.dtype(at::kInt));
    at::Tensor visible = at::empty({n}, f32.dtype(at::kBool));
    stg_splat::project_forward(n, means.data_ptr<float>(), quats.data_ptr<float>(),
                               scales.data_ptr<float>(), opacities.data_ptr<float>(), cam, s,
                               means2d.data_ptr<float>(), conics.data_ptr<float>(),
                               depths.data_ptr<float>(), opac_eff.data_ptr<float>(),
                               comp.data_ptr<float>(), radii.data_ptr<int32_t>(),
                               bbox.data_ptr<int32_t>(),
                               reinterpret_cast<uint8_t*>(visible.data_ptr<bool>()));
    return {means2d, conics, depths, opac_eff, comp, radii, bbox, visible};
}

at::Tensor visible_fwd(const at::Tensor& means, const at::Tensor& scales, const at::Tensor& viewmat,
                       const at::Tensor& K, int64_t width, int64_t height, c10::ArrayRef<double> settings,
                       double margin_px, int64_t threads) {
    const int64_t n = means.size(0);
    check_cpu_float(means, "means", n, 3);
    check_cpu_float(scales, "scales", n, 3);
    const Settings s = make_settings(settings, threads);
    const Camera cam = make_camera(viewmat, K, width, height);
    at::Tensor out = at::empty({n}, means.options().dtype(at::kBool));
    stg_splat::may_be_visible(n, means.data_ptr<float>(), scales.data_ptr<float>(), cam, s, margin_px,
                              reinterpret_cast<uint8_t*>(out.data_ptr<bool>()));
    return out;
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> project_bwd(
    const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
    const at::Tensor& opacities, const at::Tensor& viewmat, const at::Tensor& K, int64_t width,
    int64_t height, c10::ArrayRef<double> settings, int64_t threads, const at::Tensor& visible,
    const at::Tensor& g_means2d, const at::Tensor& g_conics, const at::Tensor& g_depths,
    const at::Tensor& g_opac_eff) {
    const int64_t n = means.size(0);
    check_cpu_float(means, "means", n, 3);
    check_cpu_float(quats, "quats", n, 4);
    check_cpu_float(scales, "scales", n, 3);
    check_cpu_float(opacities, "opacities", n, 0);
    check_cpu_float(g_means2d, "grad means2d", n, 2);
    check_cpu_float(g_conics, "grad conics", n, 3);
    check_cpu_float(g_depths, "grad depths", n, 0);
    check_cpu_float(g_opac_eff, "grad opacities", n, 0);
    TORCH_CHECK(visible.scalar_type() == at::kBool && visible.is_contiguous() && visible.numel() == n,
                "visible must be a contiguous bool [n] tensor");
    const Settings s = make_settings(settings, threads);
    const Camera cam = make_camera(viewmat, K, width, height);
    at::Tensor g_means = at::empty_like(means);
    at::Tensor g_quats = at::empty_like(quats);
    at::Tensor g_scales = at::empty_like(scales);
    at::Tensor g_opac = at::empty_like(opacities);
    stg_splat::project_backward(
        n, means.data_ptr<float>(), quats.data_ptr<float>(), scales.data_ptr<float>(),
        opacities.data_ptr<float>(), cam, s, reinterpret_cast<const uint8_t*>(visible.data_ptr<bool>()),
        g_means2d.data_ptr<float>(), g_conics.data_ptr<float>(), g_depths.data_ptr<float>(),
        g_opac_eff.data_ptr<float>(), g_means.data_ptr<float>(), g_quats.data_ptr<float>(),
        g_scales.data_ptr<float>(), g_opac.data_ptr<float>());
    return {g_means, g_quats, g_scales, g_opac};
}

void check_raster_inputs(const at::Tensor& means2d, const at::Tensor& conics,
                         const at::Tensor& opac_eff, const at::Tensor& colors,
                         const at::Tensor& depths, const at::Tensor& bbox, const at::Tensor& visible,
                         int64_t width, int64_t height) {
    const int64_t n = means2d.size(0);
    check_cpu_float(means2d, "means2d", n, 2);
    check_cpu_float(conics, "conics", n, 3);
    check_cpu_float(opac_eff, "opacities", n, 0);
    check_cpu_float(depths, "depths", n, 0);
    check_cpu_float(colors, "colors", n, colors.dim() == 2 ? colors.size(1) : -1);
    TORCH_CHECK(colors.dim() == 2 && colors.size(1) >= 1, "colors must be [n, C] with C >= 1");
    TORCH_CHECK(bbox.scalar_type() == at::kInt && bbox.is_contiguous() && bbox.numel() == n * 4,
                "bbox must be a contiguous int32 [n, 4] tensor");
    TORCH_CHECK(visible.scalar_type() == at::kBool && visible.is_contiguous() && visible.numel() == n,
                "visible must be a contiguous bool [n] tensor");
    TORCH_CHECK(width >= 1 && height >= 1, "image size must be positive, got ", width, "x", height);
    TORCH_CHECK(n < (int64_t(1) << 31), "at most 2^31 - 1 Gaussians, got ", n);
}

at::Tensor stats_tensor(const stg_splat::RasterStats& st) {
    at::Tensor out = at::empty({7}, at::TensorOptions().dtype(at::kDouble));
    double* p = out.data_ptr<double>();
    p[0] = st.ms_sort;
    p[1] = st.ms_bin;
    p[2] = st.ms_raster;
    p[3] = st.ms_reduce;
    p[4] = static_cast<double>(st.n_drawn);
    p[5] = static_cast<double>(st.n_intersections);
    p[6] = static_cast<double>(st.n_chunks);
    return out;
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> raster_fwd(
    const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opac_eff,
    const at::Tensor& colors, const at::Tensor& depths, const at::Tensor& bbox,
    const at::Tensor& visible, int64_t width, int64_t height, c10::ArrayRef<double> settings,
    int64_t threads) {
    check_raster_inputs(means2d, conics, opac_eff, colors, depths, bbox, visible, width, height);
    const Settings s = make_settings(settings, threads);
    const int64_t n = means2d.size(0), C = colors.size(1);
    const auto f32 = means2d.options();
    at::Tensor color = at::empty({height, width, C}, f32);
    at::Tensor T = at::empty({height, width}, f32);
    at::Tensor last = at::empty({height, width}, f32.dtype(at::kInt));
    stg_splat::RasterStats st;
    stg_splat::rasterize_forward(n, means2d.data_ptr<float>(), conics.data_ptr<float>(),
                                 opac_eff.data_ptr<float>(), colors.data_ptr<float>(),
                                 static_cast<int>(C), depths.data_ptr<float>(), bbox.data_ptr<int32_t>(),
                                 reinterpret_cast<const uint8_t*>(visible.data_ptr<bool>()),
                                 static_cast<int>(width), static_cast<int>(height), s,
                                 color.data_ptr<float>(), T.data_ptr<float>(), last.data_ptr<int32_t>(),
                                 &st);
    return {color, T, last, stats_tensor(st)};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> raster_bwd(
    const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opac_eff,
    const at::Tensor& colors, const at::Tensor& depths, const at::Tensor& bbox,
    const at::Tensor& visible, int64_t width, int64_t height, c10::ArrayRef<double> settings,
    int64_t threads, const at::Tensor& T_final, const at::Tensor& last, const at::Tensor& g_color,
    const at::Tensor& g_alpha) {
    check_raster_inputs(means2d, conics, opac_eff, colors, depths, bbox, visible, width, height);
    const Settings s = make_settings(settings, threads);
    const int64_t n = means2d.size(0), C = colors.size(1);
    TORCH_CHECK(T_final.scalar_type() == at::kFloat && T_final.is_contiguous() &&
                    T_final.numel() == width * height,
                "T_final must be a contiguous float32 [H, W] tensor");
    TORCH_CHECK(last.scalar_type() == at::kInt && last.is_contiguous() && last.numel() == width * height,
                "last must be a contiguous int32 [H, W] tensor");
    TORCH_CHECK(g_color.scalar_type() == at::kFloat && g_color.is_contiguous() &&
                    g_color.numel() == width * height * C,
                "grad of the image must be a contiguous float32 [H, W, C] tensor");
    TORCH_CHECK(g_alpha.scalar_type() == at::kFloat && g_alpha.is_contiguous() &&
                    g_alpha.numel() == width * height,
                "grad of alpha must be a contiguous float32 [H, W] tensor");
    at::Tensor g_means2d = at::empty_like(means2d);
    at::Tensor g_conics = at::empty_like(conics);
    at::Tensor g_opac = at::empty_like(opac_eff);
    at::Tensor g_colors = at::empty_like(colors);
    at::Tensor g_abs = at::empty_like(means2d);
    stg_splat::RasterStats st;
    stg_splat::rasterize_backward(
        n, means2d.data_ptr<float>(), conics.data_ptr<float>(), opac_eff.data_ptr<float>(),
        colors.data_ptr<float>(), static_cast<int>(C), depths.data_ptr<float>(),
        bbox.data_ptr<int32_t>(), reinterpret_cast<const uint8_t*>(visible.data_ptr<bool>()),
        static_cast<int>(width), static_cast<int>(height), s, T_final.data_ptr<float>(),
        last.data_ptr<int32_t>(), g_color.data_ptr<float>(), g_alpha.data_ptr<float>(),
        g_means2d.data_ptr<float>(), g_conics.data_ptr<float>(), g_opac.data_ptr<float>(),
        g_colors.data_ptr<float>(), g_abs.data_ptr<float>(), &st);
    return {g_means2d, g_conics, g_opac, g_colors, g_abs, stats_tensor(st)};
}

at::Tensor count_isect(const at::Tensor& bbox, const at::Tensor& visible, int64_t width, int64_t height,
                       int64_t max_per_chunk) {
    const int64_t n = visible.numel();
    TORCH_CHECK(bbox.scalar_type() == at::kInt && bbox.is_contiguous() && bbox.numel() == n * 4,
                "bbox must be a contiguous int32 [n, 4] tensor");
    TORCH_CHECK(visible.scalar_type() == at::kBool && visible.is_contiguous(), "visible must be contiguous bool");
    TORCH_CHECK(width >= 1 && height >= 1 && max_per_chunk >= 1, "bad image size or chunk budget");
    int64_t total = 0, chunks = 0;
    stg_splat::count_intersections(n, bbox.data_ptr<int32_t>(),
                                   reinterpret_cast<const uint8_t*>(visible.data_ptr<bool>()),
                                   static_cast<int>(width), static_cast<int>(height), max_per_chunk, &total,
                                   &chunks);
    at::Tensor out = at::empty({2}, at::TensorOptions().dtype(at::kLong));
    out[0] = total;
    out[1] = chunks;
    return out;
}

void check_image(const at::Tensor& t, const char* name) {
    TORCH_CHECK(t.device().is_cpu(), name, " must be a CPU tensor");
    TORCH_CHECK(t.scalar_type() == at::kFloat, name, " must be float32, got ", t.scalar_type());
    TORCH_CHECK(t.is_contiguous(), name, " must be contiguous");
    TORCH_CHECK(t.dim() == 3, name, " must be an (H, W, C) image, got shape ", t.sizes());
}

// The window's taps as float32, after checking their count against the compiled window.
std::vector<float> window_taps(c10::ArrayRef<double> taps) {
    TORCH_CHECK(static_cast<int64_t>(taps.size()) == stg_image::kWindow, "the window must have ",
                stg_image::kWindow, " taps (compiled in), got ", taps.size());
    return std::vector<float>(taps.begin(), taps.end());
}

void check_ssim_images(const at::Tensor& a, const at::Tensor& b) {
    check_image(a, "a");
    check_image(b, "b");
    TORCH_CHECK(a.sizes() == b.sizes(), "a and b must have the same shape, got ", a.sizes(), " and ",
                b.sizes());
    TORCH_CHECK(a.size(0) >= stg_image::kWindow && a.size(1) >= stg_image::kWindow,
                "SSIM needs images of at least ", stg_image::kWindow, "x", stg_image::kWindow,
                " pixels (the window), got ", a.size(0), "x", a.size(1));
    TORCH_CHECK(a.size(2) >= 1, "images need at least one channel");
}

// (mean SSIM as a float64 scalar, d_mu, d_var, d_cov): the maps are (Ho, Wo, C), the derivatives
// of the mean (so already divided by the number of windows); empty unless want_grad.
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> ssim_fwd(const at::Tensor& a, const at::Tensor& b,
                                                                    c10::ArrayRef<double> taps, double c1,
                                                                    double c2, bool want_grad,
                                                                    int64_t threads) {
    check_ssim_images(a, b);
    TORCH_CHECK(threads >= 1, "threads must be >= 1");
    const std::vector<float> k = window_taps(taps);
    const int64_t H = a.size(0), W = a.size(1), C = a.size(2);
    const int64_t Ho = H - stg_image::kWindow + 1, Wo = W - stg_image::kWindow + 1;
    const double count = static_cast<double>(Ho * Wo * C);
    at::Tensor rows = at::empty({Ho}, a.options().dtype(at::kDouble));
    const auto shape = want_grad ? std::vector<int64_t>{Ho, Wo, C} : std::vector<int64_t>{0};
    at::Tensor d_mu = at::empty(shape, a.options());
    at::Tensor d_var = at::empty(shape, a.options());
    at::Tensor d_cov = at::empty(shape, a.options());
    stg_image::ssim_forward(a.data_ptr<float>(), b.data_ptr<float>(), H, W, C, k.data(),
                            static_cast<float>(c1), static_cast<float>(c2), static_cast<float>(1.0 / count),
                            static_cast<int>(threads), rows.data_ptr<double>(),
                            want_grad ? d_mu.data_ptr<float>() : nullptr,
                            want_grad ? d_var.data_ptr<float>() : nullptr,
                            want_grad ? d_cov.data_ptr<float>() : nullptr);
    const double* r = rows.data_ptr<double>();
    double total = 0.0;
    for (int64_t q = 0; q < Ho; ++q) total += r[q];  // in row order: the same at any thread count
    at::Tensor value = at::empty({}, a.options().dtype(at::kDouble));
    *value.data_ptr<double>() = total / count;
    return {value, d_mu, d_var, d_cov};
}

// grad * d(SSIM)/da + l1_grad * sign(a - b) (image_filter.h).
at::Tensor ssim_bwd(const at::Tensor& a, const at::Tensor& b, c10::ArrayRef<double> taps, const at::Tensor& d_mu,
                    const at::Tensor& d_var, const at::Tensor& d_cov, double grad, double l1_grad, int64_t threads) {
    check_ssim_images(a, b);
    TORCH_CHECK(threads >= 1, "threads must be >= 1");
    const std::vector<float> k = window_taps(taps);
    const int64_t H = a.size(0), W = a.size(1), C = a.size(2);
    const int64_t Ho = H - stg_image::kWindow + 1, Wo = W - stg_image::kWindow + 1;
    for (const at::Tensor* d : {&d_mu, &d_var, &d_cov}) {
        check_image(*d, "an SSIM derivative map");
        TORCH_CHECK(d->size(0) == Ho && d->size(1) == Wo && d->size(2) == C,
                    "SSIM derivative maps must be (", Ho, ", ", Wo, ", ", C, "), got ", d->sizes());
    }
    at::Tensor grad_a = at::empty_like(a);
    stg_image::ssim_backward(a.data_ptr<float>(), b.data_ptr<float>(), H, W, C, k.data(),
                             d_mu.data_ptr<float>(), d_var.data_ptr<float>(), d_cov.data_ptr<float>(),
                             static_cast<float>(grad), static_cast<float>(l1_grad), static_cast<int>(threads),
                             grad_a.data_ptr<float>());
    return grad_a;
}

// sum |a - b| of two same-shaped contiguous float32 CPU tensors, as a float64 scalar.
at::Tensor abs_diff_sum(const at::Tensor& a, const at::Tensor& b) {
    check_image(a, "a");
    check_image(b, "b");
    TORCH_CHECK(a.sizes() == b.sizes(), "a and b must have the same shape, got ", a.sizes(), " and ", b.sizes());
    at::Tensor value = at::empty({}, a.options().dtype(at::kDouble));
    *value.data_ptr<double>() = stg_image::abs_diff_sum(a.data_ptr<float>(), b.data_ptr<float>(), a.numel());
    return value;
}

// (sum of the Charbonnier distances as float64, pixels used as int64, grad r, grad alpha): r and o
// (H, W, 2), alpha (H, W, 1), valid (H, W) bool; the gradients of scale * sum, empty unless want_grad.
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> charbonnier_flow(
    const at::Tensor& r, const at::Tensor& alpha, const at::Tensor& o, const at::Tensor& valid, double alpha_min,
    double eps, double scale, bool want_grad) {
    check_image(r, "rendered flow");
    check_image(alpha, "alpha");
    check_image(o, "observed flow");
    TORCH_CHECK(r.size(2) == 2 && o.sizes() == r.sizes(), "flows must be (H, W, 2) of one shape, got ", r.sizes(),
                " and ", o.sizes());
    TORCH_CHECK(alpha.size(0) == r.size(0) && alpha.size(1) == r.size(1) && alpha.size(2) == 1,
                "alpha must be (H, W, 1) of the flow's size, got ", alpha.sizes());
    TORCH_CHECK(valid.device().is_cpu() && valid.scalar_type() == at::kBool && valid.is_contiguous() &&
                    valid.dim() == 2 && valid.size(0) == r.size(0) && valid.size(1) == r.size(1),
                "valid must be a contiguous (H, W) bool CPU tensor, got ", valid.scalar_type(), " ", valid.sizes());
    const int64_t n = r.size(0) * r.size(1);
    at::Tensor g_r = want_grad ? at::empty_like(r) : at::empty({0}, r.options());
    at::Tensor g_alpha = want_grad ? at::empty_like(alpha) : at::empty({0}, alpha.options());
    int64_t count = 0;
    const double total = stg_image::charbonnier_flow(
        r.data_ptr<float>(), alpha.data_ptr<float>(), o.data_ptr<float>(), valid.data_ptr<bool>(), n,
        static_cast<float>(alpha_min), static_cast<float>(eps), static_cast<float>(scale), &count,
        want_grad ? g_r.data_ptr<float>() : nullptr, want_grad ? g_alpha.data_ptr<float>() : nullptr);
    at::Tensor value = at::empty({}, r.options().dtype(at::kDouble));
    *value.data_ptr<double>() = total;
    at::Tensor used = at::empty({}, r.options().dtype(at::kLong));
    *used.data_ptr<int64_t>() = count;
    return {value, used, g_r, g_alpha};
}

// ---- the edge-length loss (edge_loss.h) ----
void check_edges(const at::Tensor& x, const at::Tensor& c, const at::Tensor& a, const at::Tensor& b) {
    check_cpu_float(x, "x", x.size(0), 3);
    check_cpu_float(c, "c", x.size(0), 3);
    for (const at::Tensor* t : {&a, &b}) {
        TORCH_CHECK(t->device().is_cpu() && t->scalar_type() == at::kLong && t->dim() == 1 && t->is_contiguous(),
                    "edge ends must be contiguous 1-D int64 CPU tensors, got ", t->scalar_type(), " ", t->sizes());
    }
    TORCH_CHECK(a.size(0) == b.size(0), "edge ends must have one length, got ", a.size(0), " and ", b.size(0));
    const int64_t m = x.size(0);
    const int64_t* pa = a.data_ptr<int64_t>();
    const int64_t* pb = b.data_ptr<int64_t>();
    int64_t lo = 0, hi = 0;  // one pass over both ends (four reductions in torch cost 4x)
    for (int64_t e = 0; e < a.size(0); ++e) {
        lo = std::min(lo, std::min(pa[e], pb[e]));
        hi = std::max(hi, std::max(pa[e], pb[e]));
    }
    TORCH_CHECK(lo >= 0 && (a.size(0) == 0 || hi < m), "edge ends must index the ", m, " points, got [", lo, ", ",
                hi, "]");
}

// The mean edge-length residual as a float64 scalar, and with keep the (2, E) lengths the backward
// reads (else an empty tensor).
std::tuple<at::Tensor, at::Tensor> edge_length_fwd(const at::Tensor& x, const at::Tensor& c, const at::Tensor& a,
                                                   const at::Tensor& b, bool keep) {
    check_edges(x, c, a, b);
    at::Tensor value = at::empty({}, x.options().dtype(at::kDouble));
    at::Tensor lengths = keep ? at::empty({2, a.size(0)}, x.options()) : at::empty({0}, x.options());
    *value.data_ptr<double>() =
        stg_edge::edge_length_forward(x.data_ptr<float>(), c.data_ptr<float>(), a.data_ptr<int64_t>(),
                                      b.data_ptr<int64_t>(), a.size(0), keep ? lengths.data_ptr<float>() : nullptr);
    return {value, lengths};
}

// (grad_x, grad_c) of grad * mean; an unwanted one comes back empty. lengths: the forward's (keep).
std::tuple<at::Tensor, at::Tensor> edge_length_bwd(const at::Tensor& x, const at::Tensor& c, const at::Tensor& a,
                                                   const at::Tensor& b, const at::Tensor& lengths, double grad,
                                                   bool want_x, bool want_c) {
    check_edges(x, c, a, b);
    TORCH_CHECK(lengths.device().is_cpu() && lengths.scalar_type() == at::kFloat && lengths.is_contiguous() &&
                    lengths.numel() == 2 * a.size(0),
                "lengths must be the forward's contiguous (2, E) float32 tensor (keep), got ", lengths.sizes());
    at::Tensor gx = want_x ? at::zeros_like(x) : at::empty({0}, x.options());
    at::Tensor gc = want_c ? at::zeros_like(c) : at::empty({0}, c.options());
    stg_edge::edge_length_backward(x.data_ptr<float>(), c.data_ptr<float>(), a.data_ptr<int64_t>(),
                                   b.data_ptr<int64_t>(), a.size(0), grad, want_x ? gx.data_ptr<float>() : nullptr,
                                   want_c ? gc.data_ptr<float>() : nullptr, lengths.data_ptr<float>());
    return {gx, gc};
}

// ---- whether a step's gradients are all finite (the trainer's skip test) ----
// One read-only pass over float32 tensors, exponent bits only: an integer OR vectorises where a
// float sum may not, and nothing is written (torch's batched test writes a product of every one).
bool all_finite(at::TensorList tensors) {
    for (const at::Tensor& t : tensors) {
        TORCH_CHECK(t.device().is_cpu() && t.scalar_type() == at::kFloat && t.is_contiguous(),
                    "all_finite takes contiguous float32 CPU tensors, got ", t.scalar_type(), " ", t.sizes());
        const uint32_t* bits = reinterpret_cast<const uint32_t*>(t.data_ptr<float>());
        const int64_t n = t.numel();
        uint32_t bad = 0;
        for (int64_t i = 0; i < n; ++i) bad |= static_cast<uint32_t>((bits[i] & 0x7f800000u) == 0x7f800000u);
        if (bad != 0) return false;
    }
    return true;
}

// ---- the densification statistics (densify_stats.h) ----
// An empty tensor stands for "absent" (the header's null); present ones are checked here.
template <typename T>
T* optional_ptr(const at::Tensor& t, at::ScalarType type, const char* name, int64_t numel) {
    if (t.numel() == 0) return nullptr;
    TORCH_CHECK(t.device().is_cpu() && t.scalar_type() == type && t.is_contiguous(), name,
                " must be a contiguous CPU tensor of ", type, ", got ", t.scalar_type(), " ", t.sizes());
    TORCH_CHECK(t.numel() == numel, name, " must have ", numel, " elements, got ", t.numel());
    return t.data_ptr<T>();
}

// Adds one step's sightings into the state tensors in place (densify.DensifyStrategy._accumulate).
void densify_accumulate(const at::Tensor& radii, const at::Tensor& means2d, const at::Tensor& grad,
                        const at::Tensor& index, int64_t w, int64_t h, double pixels, const at::Tensor& tiles,
                        int64_t region, double error_threshold, const at::Tensor& depths, double focal,
                        const at::Tensor& rendered_depth, double occlusion_m, const at::Tensor& flow,
                        const at::Tensor& valid, int64_t x0, int64_t y0, const at::Tensor& rendered_flow, double decay,
                        const at::Tensor& grad_sum, const at::Tensor& vis_count, const at::Tensor& front_count,
                        const at::Tensor& m_per_px, const at::Tensor& flow_w, const at::Tensor& resid_w,
                        const at::Tensor& resid_cam, int64_t slot) {
    const int64_t n = means2d.size(0);
    TORCH_CHECK(w > 0 && h > 0, "the crop must be non-empty, got ", w, "x", h);
    TORCH_CHECK(radii.device().is_cpu() && radii.scalar_type() == at::kInt && radii.is_contiguous() &&
                    radii.size(0) == n && radii.dim() <= 2,
                "radii must be a contiguous (n,) or (n, k) int32 CPU tensor, got ", radii.sizes());
    check_cpu_float(means2d, "means2d", n, 2);
    check_cpu_float(grad, "grad", n, 2);
    const int64_t rows = grad_sum.numel();
    stg_densify::Sightings in;
    in.n = n;
    in.radii = radii.data_ptr<int32_t>();
    in.radii_cols = radii.dim() == 2 ? radii.size(1) : 1;
    in.means2d = means2d.data_ptr<float>();
    in.grad = grad.data_ptr<float>();
    in.index = optional_ptr<int64_t>(index, at::kLong, "index", n);
    const int64_t* idx = in.index;
    for (int64_t i = 0; idx != nullptr && i < n; ++i) {
        TORCH_CHECK(idx[i] >= 0 && idx[i] < rows, "index holds row ", idx[i], " of a ", rows, "-row state");
    }
    TORCH_CHECK(idx != nullptr || n <= rows, n, " rendered rows for a ", rows, "-row state");
    in.w = w;
    in.h = h;
    in.pixels = static_cast<float>(pixels);
    TORCH_CHECK(region >= 1, "region must be >= 1");
    in.region = region;
    in.tiles_h = (h + region - 1) / region;
    in.tiles_w = (w + region - 1) / region;
    in.tiles = optional_ptr<float>(tiles, at::kFloat, "tiles", in.tiles_h * in.tiles_w);
    in.error_threshold = static_cast<float>(error_threshold);
    in.depths = optional_ptr<float>(depths, at::kFloat, "depths", n);
    in.focal = static_cast<float>(focal);
    in.rendered_depth = optional_ptr<float>(rendered_depth, at::kFloat, "rendered_depth", h * w);
    in.occlusion_m = static_cast<float>(occlusion_m);
    if (flow.numel() > 0) {
        TORCH_CHECK(flow.dim() == 3 && flow.size(2) == 2, "flow must be (H, W, 2), got ", flow.sizes());
        TORCH_CHECK(x0 >= 0 && y0 >= 0 && x0 + w <= flow.size(1) && y0 + h <= flow.size(0), "the crop (", x0, ", ",
                    y0, ", ", w, ", ", h, ") must lie in the flow's frame ", flow.sizes());
        in.flow = optional_ptr<float>(flow, at::kFloat, "flow", flow.numel());
        in.valid = optional_ptr<bool>(valid, at::kBool, "valid", flow.size(0) * flow.size(1));
        TORCH_CHECK(in.valid != nullptr, "flow needs its validity");
        in.frame_w = flow.size(1);
        in.x0 = x0;
        in.y0 = y0;
        in.rendered_flow = optional_ptr<float>(rendered_flow, at::kFloat, "rendered_flow", h * w * 2);
    }
    in.decay = static_cast<float>(decay);
    stg_densify::SightingState st;
    st.grad_sum = optional_ptr<float>(grad_sum, at::kFloat, "grad_sum", rows);
    st.vis_count = optional_ptr<float>(vis_count, at::kFloat, "vis_count", rows);
    st.front_count = optional_ptr<float>(front_count, at::kFloat, "front_count", rows);
    TORCH_CHECK(st.grad_sum && st.vis_count && st.front_count, "the counts must be present");
    if (in.depths != nullptr) {
        st.m_per_px = optional_ptr<float>(m_per_px, at::kFloat, "m_per_px", rows);
        TORCH_CHECK(st.m_per_px != nullptr, "depths need m_per_px");
    }
    if (in.flow != nullptr) {
        st.flow_w = optional_ptr<float>(flow_w, at::kFloat, "flow_w", rows);
        TORCH_CHECK(st.flow_w != nullptr, "flow needs flow_w");
    }
    if (in.rendered_flow != nullptr) {
        TORCH_CHECK(resid_cam.dim() == 2 && resid_cam.size(0) == rows && slot >= 0 && slot < resid_cam.size(1),
                    "resid_cam must be (", rows, ", cameras > ", slot, "), got ", resid_cam.sizes());
        st.resid_cam = optional_ptr<float>(resid_cam, at::kFloat, "resid_cam", resid_cam.numel());
        st.resid_w = optional_ptr<float>(resid_w, at::kFloat, "resid_w", rows);
        TORCH_CHECK(st.resid_w != nullptr, "rendered_flow needs resid_w");
        st.cameras = resid_cam.size(1);
        st.slot = slot;
    }
    stg_densify::accumulate_sightings(in, st);
}

// Adds the shared motion bases' help statistics of the rows not moving (motion_help in the header).
void densify_motion_help(const at::Tensor& skin_weights, const at::Tensor& skin_delta, double weight_eps,
                         const at::Tensor& motions, const at::Tensor& means, const at::Tensor& grad,
                         const at::Tensor& moving, const at::Tensor& help_dot, const at::Tensor& help_norm) {
    const int64_t rows = means.size(0);
    check_cpu_float(skin_weights, "skin_weights", rows, 24);
    check_cpu_float(means, "means", rows, 3);
    check_cpu_float(grad, "grad", rows, 3);
    TORCH_CHECK(motions.dim() == 3 && motions.size(1) == 3 && motions.size(2) == 4 && motions.size(0) >= 1,
                "motions must be (count, 3, 4), got ", motions.sizes());
    optional_ptr<float>(motions, at::kFloat, "motions", motions.numel());
    const float* pd = optional_ptr<float>(skin_delta, at::kFloat, "skin_delta", rows * 24);
    const bool* pmove = optional_ptr<bool>(moving, at::kBool, "moving", rows);
    float* dot = optional_ptr<float>(help_dot, at::kFloat, "help_dot", rows);
    float* norm = optional_ptr<float>(help_norm, at::kFloat, "help_norm", rows);
    TORCH_CHECK(pmove && dot && norm, "moving, help_dot and help_norm must be present");
    stg_densify::motion_help(rows, skin_weights.data_ptr<float>(), pd, static_cast<float>(weight_eps),
                             motions.data_ptr<float>(), motions.size(0), means.data_ptr<float>(), grad.data_ptr<float>(),
                             pmove, dot, norm);
}

// ---- the spheres' occlusion of each point's hemisphere (sphere_occlusion.h) ----
// (M,) visible share; group values are checked to index mask's rows.
at::Tensor sphere_visibility_fwd(const at::Tensor& points, const at::Tensor& normals, const at::Tensor& group,
                                 const at::Tensor& centres, const at::Tensor& radii2, const at::Tensor& mask,
                                 int64_t threads) {
    const int64_t m = points.size(0);
    const int64_t spheres = centres.size(0);
    check_cpu_float(points, "points", m, 3);
    check_cpu_float(normals, "normals", m, 3);
    check_cpu_float(centres, "centres", spheres, 3);
    check_cpu_float(radii2, "radii2", spheres, 0);
    TORCH_CHECK(radii2.dim() == 1, "radii2 must be 1-D, got ", radii2.sizes());
    TORCH_CHECK(mask.dim() == 2 && mask.size(1) == spheres, "mask must be [groups, ", spheres, "], got ",
                mask.sizes());
    check_cpu_float(mask, "mask", mask.size(0), spheres);
    TORCH_CHECK(group.device().is_cpu() && group.scalar_type() == at::kLong && group.dim() == 1 &&
                    group.is_contiguous() && group.size(0) == m,
                "group must be a contiguous (", m, ",) int64 CPU tensor, got ", group.scalar_type(), " ",
                group.sizes());
    const int64_t* g = group.data_ptr<int64_t>();
    for (int64_t i = 0; i < m; ++i)
        TORCH_CHECK(g[i] >= 0 && g[i] < mask.size(0), "group ", g[i], " of point ", i, " is not a row of the ",
                    mask.size(0), "-row mask");
    at::Tensor visible = at::empty({m}, points.options());
    stg_occ::sphere_visibility(points.data_ptr<float>(), normals.data_ptr<float>(), g, m, centres.data_ptr<float>(),
                               radii2.data_ptr<float>(), mask.data_ptr<float>(), spheres, mask.size(0),
                               visible.data_ptr<float>(), static_cast<int>(threads));
    return visible;
}

// ---- the capped scales and the largest axis (scale_cap.h) ----
std::tuple<at::Tensor, at::Tensor> scale_row_max(const at::Tensor& x) {
    const int64_t n = x.size(0);
    check_cpu_float(x, "x", n, 3);
    at::Tensor largest = at::empty({n}, x.options()), one_hot = at::empty({n, 3}, x.options());
    stg_scale::row_max(n, x.data_ptr<float>(), largest.data_ptr<float>(), one_hot.data_ptr<float>());
    return {largest, one_hot};
}

at::Tensor scale_capped_fwd(const at::Tensor& s, double ratio) {
    const int64_t n = s.size(0);
    check_cpu_float(s, "scales", n, 3);
    at::Tensor out = at::empty({n, 3}, s.options());
    stg_scale::capped_forward(n, s.data_ptr<float>(), static_cast<float>(ratio), out.data_ptr<float>());
    return out;
}

at::Tensor scale_capped_bwd(const at::Tensor& s, double ratio, const at::Tensor& grad) {
    const int64_t n = s.size(0);
    check_cpu_float(s, "scales", n, 3);
    check_cpu_float(grad, "grad", n, 3);
    at::Tensor g = at::empty({n, 3}, s.options());
    stg_scale::capped_backward(n, s.data_ptr<float>(), static_cast<float>(ratio), grad.data_ptr<float>(),
                               g.data_ptr<float>());
    return g;
}

// ---- skeleton kinematics (kinematics.h), float64 ----
void check_cpu_double(const at::Tensor& t, const char* name, int64_t numel) {
    TORCH_CHECK(t.device().is_cpu() && t.scalar_type() == at::kDouble && t.is_contiguous(), name,
                " must be a contiguous float64 CPU tensor, got ", t.scalar_type(), " ", t.sizes());
    TORCH_CHECK(t.numel() == numel, name, " must hold ", numel, " values, got ", t.sizes());
}

at::Tensor kin_rodrigues_fwd(const at::Tensor& aa) {
    const int64_t n = aa.numel() / 3;
    check_cpu_double(aa, "axis-angles", n * 3);
    at::Tensor R = at::empty({n, 3, 3}, aa.options());
    stg_kin::rodrigues(n, aa.data_ptr<double>(), R.data_ptr<double>());
    return R;
}

at::Tensor kin_rodrigues_bwd(const at::Tensor& aa, const at::Tensor& R, const at::Tensor& G) {
    const int64_t n = aa.numel() / 3;
    check_cpu_double(aa, "axis-angles", n * 3);
    check_cpu_double(R, "rotations", n * 9);
    check_cpu_double(G, "the rotations' gradient", n * 9);
    at::Tensor g = at::empty({n, 3}, aa.options());
    stg_kin::rodrigues_backward(n, aa.data_ptr<double>(), R.data_ptr<double>(), G.data_ptr<double>(),
                                g.data_ptr<double>());
    return g;
}

void check_parents(const at::Tensor& parents, int64_t J) {
    TORCH_CHECK(parents.device().is_cpu() && parents.scalar_type() == at::kLong && parents.is_contiguous() &&
                    parents.numel() == J,
                "parents must be a contiguous (", J, ",) int64 CPU tensor, got ", parents.sizes());
    const int64_t* p = parents.data_ptr<int64_t>();
    for (int64_t j = 1; j < J; ++j)
        TORCH_CHECK(p[j] >= 0 && p[j] < j, "joint ", j, "'s parent ", p[j], " must be an earlier joint");
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> kin_bones_fwd(
    const at::Tensor& poses, const at::Tensor& rh, const at::Tensor& th, const at::Tensor& rest,
    const at::Tensor& parents, const at::Tensor& big_inv) {
    const int64_t J = rest.numel() / 3;
    const int64_t B = rh.numel() / 3;
    check_cpu_double(poses, "poses", B * J * 3);
    check_cpu_double(rh, "Rh", B * 3);
    check_cpu_double(th, "Th", B * 3);
    check_cpu_double(rest, "rest joints", J * 3);
    check_cpu_double(big_inv, "big_inv", J * 16);
    check_parents(parents, J);
    const auto f64 = poses.options();
    at::Tensor transforms = at::empty({B, J, 4, 4}, f64), quats = at::empty({B, J, 4}, f64);
    at::Tensor local = at::empty({B, J, 4, 4}, f64), world = at::empty({B, J, 4, 4}, f64);
    at::Tensor bone = at::empty({B, J, 4, 4}, f64), root = at::empty({B, 4, 4}, f64);
    stg_kin::bones_forward(B, static_cast<int>(J), poses.data_ptr<double>(), rh.data_ptr<double>(),
                           th.data_ptr<double>(), rest.data_ptr<double>(), parents.data_ptr<int64_t>(),
                           big_inv.data_ptr<double>(), transforms.data_ptr<double>(), quats.data_ptr<double>(),
                           local.data_ptr<double>(), world.data_ptr<double>(), bone.data_ptr<double>(),
                           root.data_ptr<double>());
    return {transforms, quats, local, world, bone, root};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> kin_bones_bwd(
    const at::Tensor& poses, const at::Tensor& rh, const at::Tensor& rest, const at::Tensor& parents,
    const at::Tensor& big_inv, const at::Tensor& transforms, const at::Tensor& quats, const at::Tensor& local,
    const at::Tensor& world, const at::Tensor& bone, const at::Tensor& root, const at::Tensor& g_transforms,
    const at::Tensor& g_quats) {
    const int64_t J = rest.numel() / 3;
    const int64_t B = rh.numel() / 3;
    check_cpu_double(poses, "poses", B * J * 3);
    check_cpu_double(rh, "Rh", B * 3);
    check_cpu_double(rest, "rest joints", J * 3);
    check_cpu_double(big_inv, "big_inv", J * 16);
    check_parents(parents, J);
    for (const auto* t : {&transforms, &local, &world, &bone}) check_cpu_double(*t, "a saved matrix", B * J * 16);
    check_cpu_double(quats, "quats", B * J * 4);
    check_cpu_double(root, "root", B * 16);
    const bool has_gt = g_transforms.numel() > 0, has_gq = g_quats.numel() > 0;
    if (has_gt) check_cpu_double(g_transforms, "the transforms' gradient", B * J * 16);
    if (has_gq) check_cpu_double(g_quats, "the quaternions' gradient", B * J * 4);
    at::Tensor g_poses = at::empty({B, J, 3}, poses.options()), g_rh = at::empty({B, 3}, poses.options()),
               g_th = at::empty({B, 3}, poses.options());
    stg_kin::bones_backward(B, static_cast<int>(J), poses.data_ptr<double>(), rh.data_ptr<double>(),
                            rest.data_ptr<double>(), parents.data_ptr<int64_t>(), big_inv.data_ptr<double>(),
                            transforms.data_ptr<double>(), quats.data_ptr<double>(), local.data_ptr<double>(),
                            world.data_ptr<double>(), bone.data_ptr<double>(), root.data_ptr<double>(),
                            has_gt ? g_transforms.data_ptr<double>() : nullptr,
                            has_gq ? g_quats.data_ptr<double>() : nullptr, g_poses.data_ptr<double>(),
                            g_rh.data_ptr<double>(), g_th.data_ptr<double>());
    return {g_poses, g_rh, g_th};
}

// ---- skinning (skinning.h); an absent optional tensor is passed as an empty one ----
bool given(const at::Tensor& t) { return t.defined() && t.numel() > 0; }

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> skin_fwd(
    const at::Tensor& means, const at::Tensor& skin_weights, const at::Tensor& skin_delta,
    const at::Tensor& bones, const at::Tensor& local_quats, const at::Tensor& camera, bool rotations,
    double weight_eps, double quat_eps, bool save_weights, bool blend_norms, const at::Tensor& next_means,
    const at::Tensor& next_bones, int64_t threads) {
    const int64_t n = means.size(0);
    check_cpu_float(means, "means", n, 3);
    TORCH_CHECK(bones.dim() == 2 && bones.size(1) == stg_skin::kBoneStride, "bones must be [B, ",
                stg_skin::kBoneStride, "], got ", bones.sizes());
    const int64_t B = bones.size(0);
    TORCH_CHECK(B >= 1, "skinning needs at least one bone");
    check_cpu_float(bones, "bones", B, stg_skin::kBoneStride);
    check_cpu_float(skin_weights, "skin_weights", n, B);
    const bool has_delta = given(skin_delta), has_local = given(local_quats), has_camera = given(camera);
    if (has_delta) check_cpu_float(skin_delta, "skin_delta", n, B);
    if (has_local) check_cpu_float(local_quats, "local_quats", n, 4);
    if (has_camera) {
        TORCH_CHECK(camera.numel() == 3, "camera must hold 3 values, got ", camera.numel());
        check_cpu_float(camera, "camera", camera.size(0), 0);
    }
    TORCH_CHECK(rotations || (!has_local && !has_camera && !blend_norms),
                "local rotations, the view and the blend norms need rotations");
    const bool two = given(next_bones);
    if (two) {
        check_cpu_float(next_bones, "next_bones", B, stg_skin::kBoneStride);
        check_cpu_float(next_means, "next_means", n, 3);
    }
    TORCH_CHECK(threads >= 1, "threads must be >= 1");
    const auto f32 = means.options();
    at::Tensor next_world = at::empty({two ? n : 0, 3}, f32);
    stg_skin::SecondFrame second;
    if (two) {
        second.bones = next_bones.data_ptr<float>();
        second.means = next_means.data_ptr<float>();
        second.world = next_world.data_ptr<float>();
    }
    at::Tensor world = at::empty({n, 3}, f32);
    at::Tensor quats = at::empty({rotations ? n : 0, 4}, f32);
    at::Tensor view = at::empty({has_camera ? n : 0, 3}, f32);
    at::Tensor weights = at::empty({save_weights ? n : 0, B}, f32);
    at::Tensor norms = at::empty({blend_norms ? n : 0}, f32);
    at::Tensor blends = at::empty({save_weights ? n : 0, two ? 2 : 1, stg_skin::kBoneStride}, f32);
    const stg_skin::SkinShape shape{n,         static_cast<int>(B),
                                    has_delta, rotations,
                                    has_local, static_cast<float>(weight_eps),
                                    static_cast<float>(quat_eps), static_cast<int>(threads)};
    stg_skin::skin_forward(shape, means.data_ptr<float>(), skin_weights.data_ptr<float>(),
                           has_delta ? skin_delta.data_ptr<float>() : nullptr, bones.data_ptr<float>(),
                           has_local ? local_quats.data_ptr<float>() : nullptr,
                           has_camera ? camera.data_ptr<float>() : nullptr, world.data_ptr<float>(),
                           rotations ? quats.data_ptr<float>() : nullptr,
                           has_camera ? view.data_ptr<float>() : nullptr,
                           save_weights ? weights.data_ptr<float>() : nullptr,
                           blend_norms ? norms.data_ptr<float>() : nullptr,
                           save_weights ? blends.data_ptr<float>() : nullptr, second);
    return {world, quats, view, weights, norms, next_world, blends};
}

// The normals kernels' inputs, checked once for the forward and the backward.
static void check_normals_inputs(const at::Tensor& quats, const at::Tensor& scales, const at::Tensor& means,
                                 const at::Tensor& camera, int64_t threads) {
    const int64_t n = quats.size(0);
    check_cpu_float(quats, "quats", n, 4);
    check_cpu_float(scales, "scales", n, 3);
    check_cpu_float(means, "means", n, 3);
    TORCH_CHECK(camera.numel() == 3, "camera must hold 3 values, got ", camera.numel());
    check_cpu_float(camera, "camera", camera.size(0), 0);
    TORCH_CHECK(threads >= 1, "threads must be >= 1");
}

at::Tensor gaussian_normals_fwd(const at::Tensor& quats, const at::Tensor& scales, const at::Tensor& means,
                                const at::Tensor& camera, int64_t threads) {
    const int64_t n = quats.size(0);
    check_normals_inputs(quats, scales, means, camera, threads);
    at::Tensor normals = at::empty({n, 3}, quats.options());
    stg_skin::gaussian_normals(n, quats.data_ptr<float>(), scales.data_ptr<float>(), means.data_ptr<float>(),
                               camera.data_ptr<float>(), normals.data_ptr<float>(), static_cast<int>(threads));
    return normals;
}

at::Tensor gaussian_normals_bwd(const at::Tensor& quats, const at::Tensor& scales, const at::Tensor& means,
                                const at::Tensor& camera, const at::Tensor& g_normals, int64_t threads) {
    const int64_t n = quats.size(0);
    check_normals_inputs(quats, scales, means, camera, threads);
    check_cpu_float(g_normals, "grad normals", n, 3);
    at::Tensor g_quats = at::empty({n, 4}, quats.options());
    stg_skin::gaussian_normals_backward(n, quats.data_ptr<float>(), scales.data_ptr<float>(),
                                        means.data_ptr<float>(), camera.data_ptr<float>(),
                                        g_normals.data_ptr<float>(), g_quats.data_ptr<float>(),
                                        static_cast<int>(threads));
    return g_quats;
}

void check_camera(const at::Tensor& view, const at::Tensor& K) {
    TORCH_CHECK(view.numel() == 16, "viewmat must be 4x4, got ", view.sizes());
    TORCH_CHECK(K.numel() == 9, "K must be 3x3, got ", K.sizes());
    check_cpu_float(view, "viewmat", view.size(0), 0);
    check_cpu_float(K, "K", K.size(0), 0);
}

at::Tensor pixel_motion_fwd(const at::Tensor& from, const at::Tensor& to, const at::Tensor& view, const at::Tensor& K,
                            int64_t threads) {
    const int64_t n = from.size(0);
    check_cpu_float(from, "from", n, 3);
    check_cpu_float(to, "to", n, 3);
    check_camera(view, K);
    TORCH_CHECK(threads >= 1, "threads must be >= 1");
    at::Tensor motion = at::empty({n, 2}, from.options());
    stg_skin::pixel_motion(n, from.data_ptr<float>(), to.data_ptr<float>(), view.data_ptr<float>(), K.data_ptr<float>(),
                           motion.data_ptr<float>(), static_cast<int>(threads));
    return motion;
}

std::tuple<at::Tensor, at::Tensor> pixel_motion_bwd(const at::Tensor& from, const at::Tensor& to,
                                                    const at::Tensor& view, const at::Tensor& K,
                                                    const at::Tensor& g_motion, int64_t threads) {
    const int64_t n = from.size(0);
    check_cpu_float(from, "from", n, 3);
    check_cpu_float(to, "to", n, 3);
    check_cpu_float(g_motion, "grad motion", n, 2);
    check_camera(view, K);
    TORCH_CHECK(threads >= 1, "threads must be >= 1");
    at::Tensor g_from = at::empty({n, 3}, from.options());
    at::Tensor g_to = at::empty({n, 3}, from.options());
    stg_skin::pixel_motion_backward(n, from.data_ptr<float>(), to.data_ptr<float>(), view.data_ptr<float>(),
                                    K.data_ptr<float>(), g_motion.data_ptr<float>(), g_from.data_ptr<float>(),
                                    g_to.data_ptr<float>(), static_cast<int>(threads));
    return {g_from, g_to};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> skin_bwd(
    const at::Tensor& means, const at::Tensor& weights, bool has_delta, const at::Tensor& bones,
    const at::Tensor& local_quats, bool rotations, double quat_eps, const at::Tensor& g_world,
    const at::Tensor& g_quats, const at::Tensor& next_means, const at::Tensor& next_bones,
    const at::Tensor& g_next_world, const at::Tensor& blends, bool bone_grads, bool next_bone_grads,
    int64_t threads) {
    const int64_t n = means.size(0);
    check_cpu_float(means, "means", n, 3);
    const int64_t B = bones.size(0);
    check_cpu_float(bones, "bones", B, stg_skin::kBoneStride);
    check_cpu_float(weights, "weights", n, B);
    check_cpu_float(g_world, "grad world", n, 3);
    const bool has_local = given(local_quats);
    if (has_local) check_cpu_float(local_quats, "local_quats", n, 4);
    if (rotations) check_cpu_float(g_quats, "grad quats", n, 4);
    TORCH_CHECK(rotations || !has_local, "local rotations need rotations");
    const bool two = given(next_bones);
    if (two) {
        check_cpu_float(next_bones, "next_bones", B, stg_skin::kBoneStride);
        check_cpu_float(next_means, "next_means", n, 3);
        check_cpu_float(g_next_world, "grad next world", n, 3);
    }
    TORCH_CHECK(threads >= 1, "threads must be >= 1");
    const auto f32 = means.options();
    at::Tensor g_next_means = at::empty({two ? n : 0, 3}, f32);
    at::Tensor g_next_bones = at::empty({two ? B : 0, stg_skin::kBoneStride}, f32);
    stg_skin::SecondFrame second;
    if (two) {
        second.bones = next_bones.data_ptr<float>();
        second.means = next_means.data_ptr<float>();
        second.g_world = g_next_world.data_ptr<float>();
        second.g_means = g_next_means.data_ptr<float>();
        second.g_bones = g_next_bones.data_ptr<float>();
    }
    at::Tensor g_means = at::empty({n, 3}, f32);
    at::Tensor g_delta = at::empty({has_delta ? n : 0, B}, f32);
    at::Tensor g_bones = at::empty({B, stg_skin::kBoneStride}, f32);
    at::Tensor g_local = at::empty({has_local ? n : 0, 4}, f32);
    const bool has_blends = given(blends);
    if (has_blends) check_cpu_float(blends, "blends", n, 0);
    TORCH_CHECK(!has_blends || blends.numel() == n * (two ? 2 : 1) * stg_skin::kBoneStride, "blends must be [",
                n, ", ", two ? 2 : 1, ", ", stg_skin::kBoneStride, "], got ", blends.sizes());
    stg_skin::SkinShape shape{n, static_cast<int>(B), has_delta, rotations, has_local, 0.0f,
                              static_cast<float>(quat_eps), static_cast<int>(threads)};
    shape.bone_grads = bone_grads;
    shape.next_bone_grads = next_bone_grads;
    if (!bone_grads) g_bones.zero_();
    if (two && !next_bone_grads) g_next_bones.zero_();
    stg_skin::skin_backward(shape, means.data_ptr<float>(), weights.data_ptr<float>(), bones.data_ptr<float>(),
                            has_local ? local_quats.data_ptr<float>() : nullptr, g_world.data_ptr<float>(),
                            rotations ? g_quats.data_ptr<float>() : nullptr, g_means.data_ptr<float>(),
                            has_delta ? g_delta.data_ptr<float>() : nullptr, g_bones.data_ptr<float>(),
                            has_local ? g_local.data_ptr<float>() : nullptr,
                            has_blends ? blends.data_ptr<float>() : nullptr, second);
    return {g_means, g_delta, g_bones, g_local, g_next_means, g_next_bones};
}

// ---- small MLP (small_mlp.h) ----
struct MlpArgs {
    std::vector<int> dims, acts, widths;
    std::vector<const float*> weights, biases, groups;
    int64_t table_rows = 0, rows = 0;  // rows of the groups, rows evaluated
    const int64_t* index = nullptr;    // the evaluated rows' table rows (null: every row in order)

    stg_mlp::RawRows raw() const {
        return {static_cast<int>(groups.size()), groups.data(), widths.data(), index};
    }
};

// x: the raw rows' column groups (each [table rows, width], concatenated in order); with `select`,
// `rows` (int64, distinct) are the table rows evaluated, else every row. enc_cols, enc_freqs: the
// input encoding the kernels apply (small_mlp.h; 0: none); view_degree, view_active: the SH basis
// of a view direction in the last 3 raw columns (-1: none). Layer 0 takes the encoded width.
MlpArgs mlp_args(at::TensorList x, const at::Tensor& rows, bool select, at::TensorList weights, at::TensorList biases,
                 c10::ArrayRef<int64_t> acts, int64_t enc_cols, int64_t enc_freqs, int64_t view_degree,
                 int64_t view_active) {
    TORCH_CHECK(!x.empty(), "x needs at least one column group");
    MlpArgs a;
    a.table_rows = x[0].size(0);
    int64_t width = 0;
    for (const at::Tensor& group : x) {
        TORCH_CHECK(group.dim() == 2, "x's groups must be [rows, width], got ", group.sizes());
        check_cpu_float(group, "x", a.table_rows, group.size(1));
        a.groups.push_back(group.data_ptr<float>());
        a.widths.push_back(static_cast<int>(group.size(1)));
        width += group.size(1);
    }
    a.rows = a.table_rows;
    if (select) {
        TORCH_CHECK(rows.device().is_cpu() && rows.scalar_type() == at::kLong && rows.dim() == 1 &&
                        rows.is_contiguous(), "rows must be a contiguous 1-D int64 CPU tensor");
        a.rows = rows.numel();
        a.index = rows.data_ptr<int64_t>();
        std::vector<char> seen(static_cast<size_t>(a.table_rows), 0);
        for (int64_t i = 0; i < a.rows; ++i) {
            const int64_t t = a.index[i];
            TORCH_CHECK(t >= 0 && t < a.table_rows, "rows: ", t, " is not a row of ", a.table_rows);
            TORCH_CHECK(!seen[t], "rows: ", t, " appears twice (the rows must be distinct)");
            seen[t] = 1;
        }
    }
    TORCH_CHECK(enc_cols >= 0 && enc_freqs >= 0 && enc_cols <= width && (enc_cols == 0) == (enc_freqs == 0),
                "encoding: need 0 <= enc_cols <= width and both zero or both positive, got ", enc_cols, ", ",
                enc_freqs);
    TORCH_CHECK(view_degree >= -1 && view_degree <= 3 && (view_degree < 0 ? view_active == -1
                : view_active >= 0 && view_active <= view_degree), "view direction: need -1 <= view_degree <= 3 "
                "and 0 <= view_active <= view_degree (both -1: none), got ", view_degree, ", ", view_active);
    const int64_t view_cols = view_degree < 0 ? 0 : (view_degree + 1) * (view_degree + 1);
    TORCH_CHECK(view_degree < 0 || enc_cols + 3 <= width, "a view direction needs 3 raw columns after the ",
                enc_cols, " encoded ones, got ", width);
    const size_t L = weights.size();
    TORCH_CHECK(L >= 1 && biases.size() == L && acts.size() == L, "need as many weights, biases and "
                "activations (>= 1), got ", L, ", ", biases.size(), ", ", acts.size());
    a.dims.push_back(static_cast<int>(width + 2 * enc_cols * enc_freqs + (view_degree < 0 ? 0 : view_cols - 3)));
    for (size_t l = 0; l < L; ++l) {
        const at::Tensor& w = weights[l];
        TORCH_CHECK(w.dim() == 2 && w.size(1) == a.dims.back(), "layer ", l, ": weight must be [out, ",
                    a.dims.back(), "], got ", w.sizes());
        check_cpu_float(w, "weight", w.size(0), w.size(1));
        if (given(biases[l])) check_cpu_float(biases[l], "bias", w.size(0), 0);
        TORCH_CHECK(acts[l] >= stg_mlp::kIdentity && acts[l] <= stg_mlp::kTanh, "unknown activation ", acts[l]);
        a.dims.push_back(static_cast<int>(w.size(0)));
        a.acts.push_back(static_cast<int>(acts[l]));
        a.weights.push_back(w.data_ptr<float>());
        a.biases.push_back(given(biases[l]) ? biases[l].data_ptr<float>() : nullptr);
    }
    return a;
}

stg_mlp::MlpShape mlp_shape(const MlpArgs& a, int64_t threads, int64_t enc_cols, int64_t enc_freqs,
                            int64_t view_degree, int64_t view_active) {
    TORCH_CHECK(threads >= 1, "threads must be >= 1");
    return stg_mlp::MlpShape{a.rows,
                             static_cast<int>(a.acts.size()),
                             a.dims.data(),
                             a.acts.data(),
                             static_cast<int>(threads),
                             static_cast<int>(enc_cols),
                             static_cast<int>(enc_freqs),
                             static_cast<int>(view_degree),
                             static_cast<int>(view_active)};
}

std::tuple<at::Tensor, std::vector<at::Tensor>> mlp_fwd(at::TensorList x, const at::Tensor& rows, bool select,
                                                        at::TensorList weights, at::TensorList biases,
                                                        c10::ArrayRef<int64_t> acts, int64_t enc_cols,
                                                        int64_t enc_freqs, int64_t view_degree, int64_t view_active,
                                                        bool keep_hidden, int64_t threads) {
    const MlpArgs a = mlp_args(x, rows, select, weights, biases, acts, enc_cols, enc_freqs, view_degree, view_active);
    const stg_mlp::MlpShape shape = mlp_shape(a, threads, enc_cols, enc_freqs, view_degree, view_active);
    const int64_t n = a.rows;
    at::Tensor out = at::empty({n, a.dims.back()}, x[0].options());
    std::vector<at::Tensor> hidden;
    std::vector<float*> hidden_ptr;
    if (keep_hidden) {
        for (int l = 0; l + 1 < shape.layers; ++l) {
            hidden.push_back(at::empty({n, stg_mlp::padded(a.dims[l + 1])}, x[0].options()));
            hidden_ptr.push_back(hidden.back().data_ptr<float>());
        }
    }
    stg_mlp::mlp_forward(shape, a.raw(), a.weights.data(), a.biases.data(), out.data_ptr<float>(),
                         keep_hidden ? hidden_ptr.data() : nullptr);
    return {out, hidden};
}

// want_gx: per column group, whether (1) or not (0) its gradient is wanted (an empty tensor in its
// place if not; rows not evaluated get zero).
std::tuple<std::vector<at::Tensor>, std::vector<at::Tensor>, std::vector<at::Tensor>> mlp_bwd(
    at::TensorList x, const at::Tensor& rows, bool select, at::TensorList weights, at::TensorList biases,
    c10::ArrayRef<int64_t> acts, int64_t enc_cols, int64_t enc_freqs, int64_t view_degree, int64_t view_active,
    at::TensorList hidden, const at::Tensor& out, const at::Tensor& g_out, c10::ArrayRef<int64_t> want_gx,
    int64_t threads) {
    const MlpArgs a = mlp_args(x, rows, select, weights, biases, acts, enc_cols, enc_freqs, view_degree, view_active);
    const stg_mlp::MlpShape shape = mlp_shape(a, threads, enc_cols, enc_freqs, view_degree, view_active);
    const int64_t n = a.rows;
    const int L = shape.layers;
    TORCH_CHECK(static_cast<int>(hidden.size()) == L - 1, "need ", L - 1, " hidden outputs, got ", hidden.size());
    TORCH_CHECK(want_gx.size() == x.size(), "want_gx: one flag per column group (", x.size(), "), got ",
                want_gx.size());
    std::vector<const float*> hidden_ptr;
    for (int l = 0; l + 1 < L; ++l) {
        check_cpu_float(hidden[l], "hidden", n, stg_mlp::padded(a.dims[l + 1]));
        hidden_ptr.push_back(hidden[l].data_ptr<float>());
    }
    check_cpu_float(out, "out", n, a.dims.back());
    check_cpu_float(g_out, "grad out", n, a.dims.back());
    std::vector<at::Tensor> g_x;
    std::vector<float*> g_x_ptr;
    for (size_t g = 0; g < x.size(); ++g) {
        g_x.push_back(want_gx[g] ? at::zeros_like(x[g]) : at::empty({0}, x[g].options()));
        g_x_ptr.push_back(want_gx[g] ? g_x.back().data_ptr<float>() : nullptr);
    }
    std::vector<at::Tensor> g_w, g_b;
    std::vector<float*> g_w_ptr, g_b_ptr;
    for (int l = 0; l < L; ++l) {
        g_w.push_back(at::empty({a.dims[l + 1], a.dims[l]}, x[0].options()));
        g_b.push_back(at::empty({a.dims[l + 1]}, x[0].options()));
        g_w_ptr.push_back(g_w.back().data_ptr<float>());
        g_b_ptr.push_back(g_b.back().data_ptr<float>());
    }
    stg_mlp::mlp_backward(shape, a.raw(), a.weights.data(), hidden_ptr.data(), out.data_ptr<float>(),
                          g_out.data_ptr<float>(), g_x_ptr.data(), g_w_ptr.data(), g_b_ptr.data());
    return {g_x, g_w, g_b};
}

// ---- shading under distant lights (distant_shading.h) ----
// The learned light from its parameters (stg_node/avatar/shading.py, DistantLights.parts: its
// reference), in double, and the chain rule back to them: a = softplus(ambient), c =
// softplus(colours), d = directions / max(|directions|, 1e-9), m = a + sum_l c_l / 4; the occlusion
// strength k = sigmoid(strength_logit).
struct LearnedLight {
    int count = 0;
    std::vector<double> a, c, d, m, norms;
    std::vector<float> af, cf, df, mf;
    double k = 0.0;

    stg_shade::Lights lights() const { return {count, af.data(), cf.data(), df.data(), mf.data()}; }
};

double softplus(double x) { return x > 20.0 ? x : std::log1p(std::exp(x)); }  // torch's threshold 20
double softplus_slope(double x) { return x > 20.0 ? 1.0 : 1.0 / (1.0 + std::exp(-x)); }

LearnedLight learned_light(const at::Tensor& ambient, const at::Tensor& colors, const at::Tensor& directions,
                           const at::Tensor& strength_logit) {
    const int64_t K = colors.size(0);
    TORCH_CHECK(colors.dim() == 2 && K >= 1 && K <= 8, "shading: 1 to 8 lights, got ", colors.sizes());
    check_cpu_float(colors, "light colours", K, 3);
    check_cpu_float(directions, "light directions", K, 3);
    TORCH_CHECK(ambient.numel() == 3, "shading: the ambient term needs 3 values, got ", ambient.numel());
    check_cpu_float(ambient, "ambient", ambient.size(0), 0);
    LearnedLight L;
    L.count = static_cast<int>(K);
    const float* amb = ambient.data_ptr<float>();
    const float* col = colors.data_ptr<float>();
    const float* dir = directions.data_ptr<float>();
    for (int j = 0; j < 3; ++j) L.a.push_back(softplus(amb[j]));
    L.m = L.a;
    for (int64_t l = 0; l < K; ++l) {
        const double n = std::sqrt(static_cast<double>(dir[3 * l]) * dir[3 * l] +
                                   static_cast<double>(dir[3 * l + 1]) * dir[3 * l + 1] +
                                   static_cast<double>(dir[3 * l + 2]) * dir[3 * l + 2]);
        L.norms.push_back(n);
        for (int j = 0; j < 3; ++j) {
            L.c.push_back(softplus(col[3 * l + j]));
            L.m[j] += L.c.back() / 4.0;
            L.d.push_back(dir[3 * l + j] / std::max(n, 1e-9));
        }
    }
    if (given(strength_logit)) {
        TORCH_CHECK(strength_logit.numel() == 1, "shading: one occlusion strength, got ", strength_logit.numel());
        check_cpu_float(strength_logit, "strength", strength_logit.size(0), 0);
        L.k = 1.0 / (1.0 + std::exp(-static_cast<double>(strength_logit.data_ptr<float>()[0])));
    }
    const auto to_float = [](const std::vector<double>& v) { return std::vector<float>(v.begin(), v.end()); };
    L.af = to_float(L.a);
    L.cf = to_float(L.c);
    L.df = to_float(L.d);
    L.mf = to_float(L.m);
    return L;
}

const float* shade_visible(const at::Tensor& visible, int64_t n) {
    if (!given(visible)) return nullptr;
    TORCH_CHECK(visible.dim() == 1, "visible must be [rows], got ", visible.sizes());
    check_cpu_float(visible, "visible", n, 0);
    return visible.data_ptr<float>();
}

// visible: (M,) or empty (no occlusion factor, and strength_logit empty).
at::Tensor shade_fwd(const at::Tensor& albedo, const at::Tensor& normals, const at::Tensor& visible,
                     const at::Tensor& strength_logit, const at::Tensor& ambient, const at::Tensor& colors,
                     const at::Tensor& directions, int64_t threads) {
    const int64_t n = albedo.size(0);
    check_cpu_float(albedo, "albedo", n, 3);
    check_cpu_float(normals, "normals", n, 3);
    TORCH_CHECK(threads >= 1, "threads must be >= 1");
    const LearnedLight L = learned_light(ambient, colors, directions, strength_logit);
    at::Tensor out = at::empty({n, 3}, albedo.options());
    stg_shade::shade_forward(albedo.data_ptr<float>(), normals.data_ptr<float>(), shade_visible(visible, n),
                             static_cast<float>(L.k), n, L.lights(), out.data_ptr<float>(), static_cast<int>(threads));
    return out;
}

// away: (M,) bool or empty. Returns dL/dalbedo, dL/dnormals (empty where not wanted), dL/dstrength_logit,
// dL/dambient, dL/dcolors, dL/ddirections (the parameters' shapes, float32).
std::vector<at::Tensor> shade_bwd(const at::Tensor& albedo, const at::Tensor& normals, const at::Tensor& visible,
                                  const at::Tensor& strength_logit, const at::Tensor& ambient,
                                  const at::Tensor& colors, const at::Tensor& directions, const at::Tensor& away,
                                  const at::Tensor& g_out, bool want_albedo, bool want_normals, int64_t threads) {
    const int64_t n = albedo.size(0);
    check_cpu_float(albedo, "albedo", n, 3);
    check_cpu_float(normals, "normals", n, 3);
    check_cpu_float(g_out, "grad out", n, 3);
    TORCH_CHECK(threads >= 1, "threads must be >= 1");
    const LearnedLight L = learned_light(ambient, colors, directions, strength_logit);
    const int K = L.count;
    const bool* away_ptr = nullptr;
    if (given(away)) {
        TORCH_CHECK(away.device().is_cpu() && away.scalar_type() == at::kBool && away.dim() == 1 && away.size(0) == n &&
                        away.is_contiguous(), "away must be a contiguous [", n, "] bool CPU tensor");
        away_ptr = away.data_ptr<bool>();
    }
    at::Tensor g_albedo = at::empty({want_albedo ? n : 0, 3}, albedo.options());
    at::Tensor g_normals = at::empty({want_normals ? n : 0, 3}, albedo.options());
    double g_k = 0.0, g_a[3], g_m[3];
    std::vector<double> g_c(3 * K), g_d(3 * K);
    stg_shade::shade_backward(albedo.data_ptr<float>(), normals.data_ptr<float>(), shade_visible(visible, n),
                              static_cast<float>(L.k), n, L.lights(), away_ptr, g_out.data_ptr<float>(),
                              want_albedo ? g_albedo.data_ptr<float>() : nullptr,
                              want_normals ? g_normals.data_ptr<float>() : nullptr, &g_k, g_a, g_c.data(), g_d.data(),
                              g_m, static_cast<int>(threads));
    // the chain rule back to the parameters
    at::Tensor g_logit = at::zeros_like(strength_logit);
    if (given(strength_logit)) g_logit.data_ptr<float>()[0] = static_cast<float>(g_k * L.k * (1.0 - L.k));
    at::Tensor g_ambient = at::empty_like(ambient), g_colors = at::empty_like(colors);
    at::Tensor g_directions = at::empty_like(directions);
    const float* amb = ambient.data_ptr<float>();
    const float* col = colors.data_ptr<float>();
    for (int j = 0; j < 3; ++j) g_ambient.data_ptr<float>()[j] = static_cast<float>((g_a[j] + g_m[j]) * softplus_slope(amb[j]));
    for (int l = 0; l < K; ++l) {
        double dot = 0.0;
        for (int q = 0; q < 3; ++q) dot += L.d[3 * l + q] * g_d[3 * l + q];
        const bool clamped = L.norms[l] < 1e-9;  // then d / 1e-9, the norm taking no gradient
        const double inv = 1.0 / std::max(L.norms[l], 1e-9);
        for (int q = 0; q < 3; ++q) {
            const int i = 3 * l + q;
            g_colors.data_ptr<float>()[i] = static_cast<float>((g_c[i] + g_m[q] / 4.0) * softplus_slope(col[i]));
            g_directions.data_ptr<float>()[i] =
                static_cast<float>(clamped ? g_d[i] * inv : (g_d[i] - L.d[i] * dot) * inv);
        }
    }
    return {g_albedo, g_normals, g_logit, g_ambient, g_colors, g_directions};
}

int64_t image_window() { return stg_image::kWindow; }

int64_t tile_size() { return stg_splat::kTileSize; }

int64_t num_settings() { return stg_splat::kNumSettings; }

}  // namespace

TORCH_LIBRARY(STG_SPLAT_NS, m) {
    m.def("scale_row_max(Tensor x) -> (Tensor, Tensor)", &scale_row_max);
    m.def("scale_capped_fwd(Tensor s, float ratio) -> Tensor", &scale_capped_fwd);
    m.def("scale_capped_bwd(Tensor s, float ratio, Tensor grad) -> Tensor", &scale_capped_bwd);
    m.def("kin_rodrigues_fwd(Tensor aa) -> Tensor", &kin_rodrigues_fwd);
    m.def("kin_rodrigues_bwd(Tensor aa, Tensor R, Tensor G) -> Tensor", &kin_rodrigues_bwd);
    m.def("kin_bones_fwd(Tensor poses, Tensor rh, Tensor th, Tensor rest, Tensor parents, Tensor big_inv) -> "
          "(Tensor, Tensor, Tensor, Tensor, Tensor, Tensor)",
          &kin_bones_fwd);
    m.def("kin_bones_bwd(Tensor poses, Tensor rh, Tensor rest, Tensor parents, Tensor big_inv, Tensor transforms, "
          "Tensor quats, Tensor local, Tensor world, Tensor bone, Tensor root, Tensor g_transforms, "
          "Tensor g_quats) -> (Tensor, Tensor, Tensor)",
          &kin_bones_bwd);
    m.def("tile_size() -> int", &tile_size);
    m.def("num_settings() -> int", &num_settings);
    m.def("image_window() -> int", &image_window);
    m.def("ssim_fwd(Tensor a, Tensor b, float[] taps, float c1, float c2, bool want_grad, int threads) -> "
          "(Tensor, Tensor, Tensor, Tensor)",
          &ssim_fwd);
    m.def("ssim_bwd(Tensor a, Tensor b, float[] taps, Tensor d_mu, Tensor d_var, Tensor d_cov, float grad, "
          "float l1_grad, int threads) -> Tensor",
          &ssim_bwd);
    m.def("abs_diff_sum(Tensor a, Tensor b) -> Tensor", &abs_diff_sum);
    m.def("charbonnier_flow(Tensor r, Tensor alpha, Tensor o, Tensor valid, float alpha_min, float eps, float scale, "
          "bool want_grad) -> (Tensor, Tensor, Tensor, Tensor)",
          &charbonnier_flow);
    m.def("sphere_visibility(Tensor points, Tensor normals, Tensor group, Tensor centres, Tensor radii2, "
          "Tensor mask, int threads) -> Tensor",
          &sphere_visibility_fwd);
    m.def(
        "densify_accumulate(Tensor radii, Tensor means2d, Tensor grad, Tensor index, int w, int h, float pixels, "
        "Tensor tiles, int region, float error_threshold, Tensor depths, float focal, Tensor rendered_depth, "
        "float occlusion_m, Tensor flow, Tensor valid, int x0, int y0, Tensor rendered_flow, float decay, "
        "Tensor(a!) grad_sum, Tensor(b!) vis_count, Tensor(c!) front_count, Tensor(d!) m_per_px, "
        "Tensor(e!) flow_w, Tensor(f!) resid_w, Tensor(g!) resid_cam, int slot) -> ()",
        &densify_accumulate);
    m.def(
        "densify_motion_help(Tensor skin_weights, Tensor skin_delta, float weight_eps, Tensor motions, "
        "Tensor means, Tensor grad, Tensor moving, Tensor(a!) help_dot, Tensor(b!) help_norm) -> ()",
        &densify_motion_help);
    m.def("all_finite(Tensor[] tensors) -> bool", &all_finite);
    m.def("edge_length_fwd(Tensor x, Tensor c, Tensor a, Tensor b, bool keep) -> (Tensor, Tensor)", &edge_length_fwd);
    m.def("edge_length_bwd(Tensor x, Tensor c, Tensor a, Tensor b, Tensor lengths, float grad, bool want_x, "
          "bool want_c) -> "
          "(Tensor, Tensor)",
          &edge_length_bwd);
    m.def("count_intersections(Tensor bbox, Tensor visible, int width, int height, int max_per_chunk) -> Tensor",
          &count_isect);
    m.def(
        "project_fwd(Tensor means, Tensor quats, Tensor scales, Tensor opacities, Tensor viewmat, "
        "Tensor K, int width, int height, float[] settings, int threads) -> (Tensor, Tensor, Tensor, "
        "Tensor, Tensor, Tensor, Tensor, Tensor)",
        &project_fwd);
    m.def(
        "may_be_visible(Tensor means, Tensor scales, Tensor viewmat, Tensor K, int width, int height, "
        "float[] settings, float margin_px, int threads) -> Tensor",
        &visible_fwd);
    m.def(
        "project_bwd(Tensor means, Tensor quats, Tensor scales, Tensor opacities, Tensor viewmat, "
        "Tensor K, int width, int height, float[] settings, int threads, Tensor visible, "
        "Tensor g_means2d, Tensor g_conics, Tensor g_depths, Tensor g_opacities) -> (Tensor, Tensor, "
        "Tensor, Tensor)",
        &project_bwd);
    m.def(
        "raster_fwd(Tensor means2d, Tensor conics, Tensor opacities, Tensor colors, Tensor depths, "
        "Tensor bbox, Tensor visible, int width, int height, float[] settings, int threads) -> "
        "(Tensor, Tensor, Tensor, Tensor)",
        &raster_fwd);
    m.def(
        "raster_bwd(Tensor means2d, Tensor conics, Tensor opacities, Tensor colors, Tensor depths, "
        "Tensor bbox, Tensor visible, int width, int height, float[] settings, int threads, "
        "Tensor T_final, Tensor last, Tensor g_color, Tensor g_alpha) -> (Tensor, Tensor, Tensor, "
        "Tensor, Tensor, Tensor)",
        &raster_bwd);
    m.def(
        "skin_fwd(Tensor means, Tensor skin_weights, Tensor skin_delta, Tensor bones, Tensor local_quats, "
        "Tensor camera, bool rotations, float weight_eps, float quat_eps, bool save_weights, bool blend_norms, "
        "Tensor next_means, Tensor next_bones, int threads) -> (Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, "
        "Tensor)",
        &skin_fwd);
    m.def("gaussian_normals_fwd(Tensor quats, Tensor scales, Tensor means, Tensor camera, int threads) -> Tensor",
          &gaussian_normals_fwd);
    m.def(
        "gaussian_normals_bwd(Tensor quats, Tensor scales, Tensor means, Tensor camera, Tensor g_normals, "
        "int threads) -> Tensor",
        &gaussian_normals_bwd);
    m.def("pixel_motion_fwd(Tensor from, Tensor to, Tensor viewmat, Tensor K, int threads) -> Tensor",
          &pixel_motion_fwd);
    m.def(
        "pixel_motion_bwd(Tensor from, Tensor to, Tensor viewmat, Tensor K, Tensor g_motion, int threads) -> "
        "(Tensor, Tensor)",
        &pixel_motion_bwd);
    m.def(
        "skin_bwd(Tensor means, Tensor weights, bool has_delta, Tensor bones, Tensor local_quats, "
        "bool rotations, float quat_eps, Tensor g_world, Tensor g_quats, Tensor next_means, Tensor next_bones, "
        "Tensor g_next_world, Tensor blends, bool bone_grads, bool next_bone_grads, int threads) -> (Tensor, "
        "Tensor, Tensor, Tensor, Tensor, Tensor)",
        &skin_bwd);
    m.def("shade_fwd(Tensor albedo, Tensor normals, Tensor visible, Tensor strength_logit, Tensor ambient, "
          "Tensor colors, Tensor directions, int threads) -> Tensor",
          &shade_fwd);
    m.def("shade_bwd(Tensor albedo, Tensor normals, Tensor visible, Tensor strength_logit, Tensor ambient, "
          "Tensor colors, Tensor directions, Tensor away, Tensor g_out, bool want_albedo, bool want_normals, "
          "int threads) -> Tensor[]",
          &shade_bwd);
    m.def(
        "mlp_fwd(Tensor[] x, Tensor rows, bool select, Tensor[] weights, Tensor[] biases, int[] acts, int enc_cols, "
        "int enc_freqs, int view_degree, int view_active, bool keep_hidden, "
        "int threads) -> "
        "(Tensor, Tensor[])",
        &mlp_fwd);
    m.def(
        "mlp_bwd(Tensor[] x, Tensor rows, bool select, Tensor[] weights, Tensor[] biases, int[] acts, int enc_cols, "
        "int enc_freqs, int view_degree, int view_active, Tensor[] hidden, "
        "Tensor out, "
        "Tensor g_out, int[] want_gx, int threads) -> (Tensor[], Tensor[], Tensor[])",
        &mlp_bwd);
}
