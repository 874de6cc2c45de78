// CPU image-space kernels that splatting losses need: SSIM with a separable Gaussian window
// over the 'valid' region, and its analytic backward. Plain C++17 + OpenMP on raw arrays (no
// torch headers), like splat_kernels.h; splat_bindings.cpp wraps it for torch and
// stg_node/splat/image_ops.py is the Python side (taps and constants come from there).
//
// Images are (H, W, C) float32, row-major with interleaved channels, so one image row is W*C
// contiguous floats and a horizontal tap is an offset of C floats.
#pragma once

#include <cstdint>

namespace stg_image {

// Taps of the separable window; the taps themselves arrive from Python (image_ops.py owns the
// window's size and sigma) and the bindings check their count against this.
constexpr int kWindow = 11;

// Mean SSIM over the valid region: per channel, the window statistics mu_a, mu_b, E[a^2],
// E[b^2], E[ab] (population), then
//   S = (2 mu_a mu_b + c1)(2 cov + c2) / ((mu_a^2 + mu_b^2 + c1)(var_a + var_b + c2)).
// Writes row_sums[q] = sum of S over output row q (Ho = H - kWindow + 1 rows, Wo*C values per
// row, Wo = W - kWindow + 1), each row summed in double. If d_mu is not null, also writes the
// derivatives of `scale * S` with respect to the window statistics of `a`, as (Ho, Wo*C) maps:
//   d_mu  = d(scale S)/d mu_a     (E[a^2] and E[ab] held fixed)
//   d_var = d(scale S)/d E[a^2]   (= d/d var_a)
//   d_cov = d(scale S)/d E[ab]    (= d/d cov)
// so that d(scale S)/da = T(d_mu) + 2 a T(d_var) + b T(d_cov), T the transposed window filter.
void ssim_forward(const float* a, const float* b, int64_t height, int64_t width, int64_t channels,
                  const float* taps, float c1, float c2, float scale, int threads, double* row_sums,
                  float* d_mu, float* d_var, float* d_cov);

// grad_a (H, W*C) = g * (T(d_mu) + 2 a T(d_var) + b T(d_cov)) + l1_grad * sign(a - b), with T the
// 'full' (transposed 'valid') separable filter of the (Ho, Wo*C) maps that ssim_forward wrote: the
// gradient of g * SSIM plus that of an L1 term whose derivative per pixel is l1_grad |a - b|' (the
// photometric loss's two terms in one pass; sign(0) = 0, torch's abs backward).
void ssim_backward(const float* a, const float* b, int64_t height, int64_t width, int64_t channels,
                   const float* taps, const float* d_mu, const float* d_var, const float* d_cov, float g,
                   float l1_grad, int threads, float* grad_a);

// sum_j |a_j - b_j| over count floats (float sums of blocks, added in double).
double abs_diff_sum(const float* a, const float* b, int64_t count);

// Charbonnier distance between a rendered motion field and an observed one, over n pixels: where
// valid[p] and alpha[p] > alpha_min, d_p = sqrt(|r_p / alpha_p - o_p|^2 + eps^2) (r, o: 2 floats a
// pixel). Returns the sum of d_p (in double) and writes the number of pixels used to *count. With
// g_r not null (then g_alpha too), writes the gradients of scale * sum d_p with respect to r
// (n x 2) and alpha (n), 0 at the pixels not used.
double charbonnier_flow(const float* r, const float* alpha, const float* o, const bool* valid, int64_t n,
                        float alpha_min, float eps, float scale, int64_t* count, float* g_r, float* g_alpha);

}  // namespace stg_image
