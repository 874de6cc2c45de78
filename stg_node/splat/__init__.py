"""Differentiable 3D Gaussian splatting: one API, three backends (docs/SPLAT.md).

``rasterize(means, quats, scales, opacities, colors, viewmat, K, width, height)`` renders
Gaussians into one OpenCV pinhole camera and returns ``(image, alpha, info)``. Backends:
``cpu`` (C++/OpenMP kernels, built on first use), ``cuda`` (gsplat), ``torch`` (the pure
PyTorch reference). ``save_ply``/``load_ply`` read and write the standard 3DGS PLY layout.

This package knows nothing of avatars, datasets or buses.
"""

from . import constants
from .api import BACKENDS, available_backends, rasterize, resolve_backend
from .ply import GaussianPly, load_ply, rgb_to_sh, save_ply, sh_to_rgb

__all__ = [
    "BACKENDS",
    "GaussianPly",
    "available_backends",
    "constants",
    "load_ply",
    "rasterize",
    "resolve_backend",
    "rgb_to_sh",
    "save_ply",
    "sh_to_rgb",
]
