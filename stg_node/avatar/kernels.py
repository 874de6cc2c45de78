"""Which implementation the avatar's per-Gaussian stages run: the fused C++ kernels or torch.

Skinning (:mod:`rigid`), the colour MLP (:mod:`color`) and the isometry term (:mod:`isometry`)
each have a fused CPU kernel with a hand-written backward (``stg_node.splat.skin_ops``,
``stg_node.splat.mlp_ops``, ``stg_node.splat.edge_ops``; the skinning kernel also carries the
flow loss's next frame, and ``skin_ops`` holds the shading normals and the flow target's image
motion with their backward passes), the occlusion term's visibility (:mod:`occlusion`, no
gradient) a forward-only one, the bones' kinematics with a gradient (:mod:`kinematics`) a float64
C++ pass with a hand-written backward, numpy its reference (so is the colour MLP's pose code with a
gradient), the
capped scales (:mod:`scale_ops`) and the distant lights' irradiance (:mod:`light_ops`) single
autograd nodes with their backward written out in torch, and each a torch
implementation, which is the reference the kernels are tested against and what runs on other
devices, in float64, or without a C++ compiler. The kernels are used wherever they apply (float32
CPU tensors, kernels built) unless switched off:

- ``STG_AVATAR_KERNELS=torch`` in the environment, for a whole process;
- ``with kernels.reference():`` for a block of code (benchmarks time both in one run this way).
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading

import torch

log = logging.getLogger(__name__)

ENV = "STG_AVATAR_KERNELS"
MODES = ("auto", "torch")

_local = threading.local()
_logged = False


def mode() -> str:
    """``auto`` (kernels where they apply) or ``torch`` (the reference everywhere)."""
    forced = getattr(_local, "forced", None)
    if forced is not None:
        return forced
    value = os.environ.get(ENV, "auto").strip().lower() or "auto"
    if value not in MODES:
        raise ValueError(f"{ENV} must be one of {', '.join(MODES)}, got {value!r}")
    return value


@contextlib.contextmanager
def reference():
    """Run the torch reference inside this block (in this thread)."""
    previous = getattr(_local, "forced", None)
    _local.forced = "torch"
    try:
        yield
    finally:
        _local.forced = previous


def use_kernels(*tensors: torch.Tensor | None) -> bool:
    """Whether a stage over these tensors should run its C++ kernel (``None`` entries ignored)."""
    global _logged
    if mode() == "torch":
        return False
    for t in tensors:
        if t is not None and (t.device.type != "cpu" or t.dtype != torch.float32):
            return False
    from stg_node.splat.build import load_kernels
    from stg_node.splat.types import BackendUnavailable

    try:
        load_kernels()
    except BackendUnavailable as exc:
        if not _logged:
            _logged = True
            log.warning("avatar kernels unavailable, using torch (%s)", exc)
        return False
    return True
