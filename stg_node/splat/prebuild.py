"""Build the splat kernels ahead of first use, so no render waits minutes for a compiler.

The cpu backend compiles its C++ kernels on first use (about 30 s, build.py) and gsplat, behind
the cuda backend, JIT-compiles its CUDA kernels on first use (minutes; cuda_backend.py). Both
cache the result on disk. `prebuild` does both builds now; ``stg-splat-prebuild`` (or
``python -m stg_node.cli.splat_prebuild``) is its command line (docs/SPLAT.md).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import torch

from .build import load_kernels
from .types import BackendUnavailable

log = logging.getLogger(__name__)

PREBUILD_BACKENDS = ("cpu", "cuda")


@dataclass
class KernelBuild:
    """The outcome of one backend's build."""

    backend: str  # "cpu" or "cuda"
    ok: bool
    skipped: bool  # not applicable here (no CUDA-enabled torch), not a failure
    detail: str  # where the kernels are cached, or why they are not available
    cache_dir: Path | None = None


def prebuild_cpu() -> KernelBuild:
    try:
        kernels = load_kernels()
    except BackendUnavailable as exc:
        return KernelBuild("cpu", ok=False, skipped=False, detail=str(exc))
    return KernelBuild(
        "cpu",
        ok=True,
        skipped=False,
        detail=f"C++ kernels ready: {kernels.library}",
        cache_dir=kernels.library.parent,
    )


def prebuild_cuda(required: bool) -> KernelBuild:
    """gsplat's kernels. Needs CUDA-enabled torch and nvcc, not a GPU (set TORCH_CUDA_ARCH_LIST
    to choose the architectures when building on a machine without one)."""
    if torch.version.cuda is None:
        return KernelBuild(
            "cuda",
            ok=not required,
            skipped=not required,
            detail="torch is built without CUDA (install a CUDA build of torch to use the cuda backend)",
        )
    from .cuda_backend import GsplatUnavailable, ensure_kernels, gsplat_build_dir, import_gsplat

    try:
        gsplat = import_gsplat()
        ensure_kernels()
    except GsplatUnavailable as exc:
        return KernelBuild("cuda", ok=False, skipped=False, detail=str(exc))
    where = gsplat_build_dir()
    return KernelBuild(
        "cuda",
        ok=True,
        skipped=False,
        detail=f"gsplat {gsplat.__version__} kernels ready: {where}",
        cache_dir=where,
    )


def prebuild(backends: tuple[str, ...] = PREBUILD_BACKENDS, *, required: bool = False) -> list[KernelBuild]:
    """Build (or find cached) the kernels of `backends`. With required=False a cuda build on a
    machine whose torch has no CUDA is skipped, not failed."""
    unknown = set(backends) - set(PREBUILD_BACKENDS)
    if unknown:
        raise ValueError(f"unknown backends {sorted(unknown)}; choose from {PREBUILD_BACKENDS}")
    results = []
    for name in backends:
        results.append(prebuild_cpu() if name == "cpu" else prebuild_cuda(required))
    return results
