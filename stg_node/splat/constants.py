"""The numbers that define what a splat render *is*, shared by every backend.

The torch reference and the C++ kernels (which receive these values as arguments at every
call, so they can never drift from this file) read them from here; the gsplat wrapper passes
the tunable ones (eps2d, planes, radius clip, tile size) to gsplat. The rest gsplat compiles
in, and ours are its values, read from the source of the version the ``cuda`` extra pins
(gsplat 1.5.3: ``ALPHA_THRESHOLD`` in cuda/include/Common.h; ``min(0.999f, ...)``,
``next_T <= 1e-4f`` in csrc/RasterizeToPixels3DGSFwd.cu; ``3.33f`` and the opacity-aware
extent in csrc/ProjectionEWA3DGSFused.cu), so a model trained on one backend renders the same
on another (docs/SPLAT.md, "Constants").
"""

from __future__ import annotations

import math

# Screen-space tiles: 16x16 pixels, as in 3DGS and gsplat. The C++ kernels hard-code this
# (it sizes their per-tile buffers) and refuse to run if the two ever disagree.
TILE_SIZE = 16

# EWA projection: a low-pass filter of this variance (pixels^2) is added to every projected
# 2D covariance, so a Gaussian never covers less than about one pixel ("0.3 dilation").
LOW_PASS_EPS2D = 0.3

# Depth culling, in metres along the camera's +z axis: a Gaussian whose centre is nearer
# than NEAR_PLANE or farther than FAR_PLANE is dropped (a centre exactly on the near plane
# is kept). gsplat's defaults.
NEAR_PLANE = 0.01
FAR_PLANE = 1e10

# Compositing (gsplat's rules and values): a Gaussian's alpha at a pixel is
# min(ALPHA_MAX, opacity * exp(-sigma)); a contribution below ALPHA_MIN is skipped; a pixel
# stops accepting Gaussians as soon as the next one would take its transmittance to
# TRANSMITTANCE_MIN or below (that one is not blended). Compared in float32 for float32 renders.
ALPHA_MAX = 0.999
ALPHA_MIN = 1.0 / 255.0
TRANSMITTANCE_MIN = 1e-4

# The gsplat release these values were read from; the cuda backend warns on another 1.5.x and
# refuses older ones (the ``cuda`` extra pins this range).
GSPLAT_VERSION = "1.5.3"

# Opacity-aware screen radius: a Gaussian with effective opacity o reaches ALPHA_MIN at
# sqrt(2 ln(o / ALPHA_MIN)) standard deviations, which is what its bounding box covers,
# capped at SIGMA_EXTENT_MAX. The cap equals sqrt(2 ln 255) (rounded up), i.e. the "3-sigma"
# box that can never cut off a visible contribution of a Gaussian with opacity <= 1 (the
# same bound gsplat uses).
SIGMA_EXTENT_MAX = 3.33

# Projection clamp for the EWA Jacobian (not for the means): camera-space x/z, y/z are
# clamped to the view frustum widened by this fraction of the half field of view, as in
# 3DGS/gsplat, so Gaussians far off-screen do not get absurd 2D covariances.
FRUSTUM_MARGIN = 0.3

# Quaternions: rasterize() replaces any whose every component is below QUAT_NORM_EPS in
# magnitude (a zero one) by the identity (1, 0, 0, 0) before a backend sees it (gsplat would
# turn it into NaN); every backend then normalises q / |q| (the C++ kernels as
# q / max(|q|, QUAT_NORM_EPS)).
QUAT_NORM_EPS = 1e-12

# Anti-aliased mode multiplies opacity by sqrt(det(S) / det(S + eps2d I)); its gradient uses
# 0.5 / (compensation + COMPENSATION_GRAD_EPS) so a degenerate Gaussian gets a finite one.
COMPENSATION_GRAD_EPS = 1e-6

# Memory bounds. Screen bounding boxes are clipped to the image in floating point before any
# integer conversion; reported radii saturate at RADIUS_REPORT_MAX. Tile intersections are
# counted in int64 and rasterised in chunks of at most this many (4 bytes each), so a
# pathological scene costs time, not unbounded memory.
RADIUS_REPORT_MAX = 1 << 30
MAX_INTERSECTIONS_PER_CHUNK = 1 << 26

# The torch reference evaluates (pixel, Gaussian) pairs densely, per pixel block, in chunks of
# at most this many pairs, which bounds its memory.
TORCH_MAX_PAIRS = 1 << 21

# Depth-dependent alpha thresholds used by the expected-depth output: where a pixel's alpha
# is below this, its expected depth is divided by this instead (as gsplat does).
DEPTH_ALPHA_EPS = 1e-10


def sigma_extent(opacity: float) -> float:
    """How many standard deviations a Gaussian of this effective opacity reaches (its box)."""
    if opacity < ALPHA_MIN:
        return 0.0
    return min(SIGMA_EXTENT_MAX, math.sqrt(2.0 * math.log(opacity / ALPHA_MIN)))
