"""The densification statistics of a training step on the CPU (C++ kernels, csrc/densify_stats.cpp).

After each step's backward the density strategy (``stg_node.avatar.densify``) adds every rendered
Gaussian's screen gradient, visibility, pixel span, the flow under its centre and the flow its
own motion misses into running per-Gaussian statistics, and (with shared motion bases) how much a
static Gaussian's loss would fall if it moved with the bases. In torch that is a chain of
gathers, scatters and per-pixel lookups (advanced indexing, ~4 ms a step at 20k Gaussians on one
core); the kernels make one pass over the rows. ``DensifyStrategy``'s torch methods are the
reference (any device and dtype) and the kernels' test oracle (tests/test_densify_kernel.py).
No gradients: these read a step's gradients, they make none.
"""

from __future__ import annotations

import torch

from .build import kernels_take, load_kernels


def _or_empty(t: torch.Tensor | None, dtype=torch.float32) -> torch.Tensor:
    """The kernels read an empty tensor as "absent"."""
    return torch.empty(0, dtype=dtype) if t is None else t.contiguous()


def densify_kernels_apply(*tensors: torch.Tensor | None) -> bool:
    """Whether the kernels take these tensors: contiguous float32 CPU ones (the statistics are
    written in place, so no copy may stand in for them), and kernels that build here."""
    return all(t is None or t.is_contiguous() for t in tensors) and kernels_take(*tensors)


def accumulate_sightings(
    state: dict[str, torch.Tensor],
    *,
    radii: torch.Tensor,
    means2d: torch.Tensor,
    grad: torch.Tensor,
    index: torch.Tensor | None,
    crop_size: tuple[int, int],
    tiles: torch.Tensor | None,
    region_px: int,
    error_threshold: float,
    depths: torch.Tensor | None,
    focal: float,
    rendered_depth: torch.Tensor | None,
    occlusion_m: float,
    flow: torch.Tensor | None,
    valid: torch.Tensor | None,
    crop_origin: tuple[int, int],
    rendered_flow: torch.Tensor | None,
    camera_slot: int,
    decay: float,
) -> None:
    """Adds one step's sightings into ``state``'s (N,) statistics in place, as
    ``DensifyStrategy._accumulate_torch`` does: ``radii`` (n,) or (n, k) int32, ``means2d`` and
    ``grad`` (n, 2) of the rendered rows (table rows ``index``, or 0..n-1); ``tiles`` the tile
    errors of ``clone_on_error`` or None; ``depths`` (n,) or None; ``rendered_depth`` (h, w), given
    only where the occlusion test applies; ``flow`` (H, W, 2) and ``valid`` (H, W) of the full frame
    with the crop at ``crop_origin``, or None; ``rendered_flow`` (h, w, 2) or None (then
    ``state["resid_cam"]`` need not exist)."""
    w, h = crop_size
    x0, y0 = crop_origin
    resid_cam = state.get("resid_cam") if rendered_flow is not None else None
    load_kernels().ops.densify_accumulate(
        radii.to(torch.int32).contiguous(),
        means2d.detach().contiguous(),
        grad.contiguous(),
        _or_empty(index, torch.int64),
        int(w),
        int(h),
        float(w * h),
        _or_empty(tiles),
        int(region_px),
        float(error_threshold),
        _or_empty(None if depths is None else depths.detach().reshape(-1)),
        float(focal),
        _or_empty(rendered_depth),
        float(occlusion_m),
        _or_empty(flow),
        _or_empty(valid, torch.bool),
        int(x0),
        int(y0),
        _or_empty(rendered_flow),
        float(decay),
        state["grad_sum"],
        state["vis_count"],
        state["front_count"],
        state["m_per_px"],
        state["flow_w"],
        state["resid_w"],
        _or_empty(resid_cam),
        int(camera_slot),
    )


def motion_help(
    skin_weights: torch.Tensor,
    skin_delta: torch.Tensor | None,
    weight_eps: float,
    motions: torch.Tensor,
    means: torch.Tensor,
    grad: torch.Tensor,
    moving: torch.Tensor,
    help_dot: torch.Tensor,
    help_norm: torch.Tensor,
) -> None:
    """Adds ``<g, m>`` and ``|g| |m|`` into ``help_dot`` and ``help_norm`` for the rows not
    ``moving``: ``m`` the offset the shared motion bases ``motions`` (count, 3, 4) at this time give
    a row (its blended skinning weights summed per basis; ``DensifyStrategy._accumulate_help``)."""
    load_kernels().ops.densify_motion_help(
        skin_weights.detach().contiguous(),
        _or_empty(None if skin_delta is None else skin_delta.detach()),
        float(weight_eps),
        motions.detach().contiguous(),
        means.detach().contiguous(),
        grad.contiguous(),
        moving.contiguous(),
        help_dot,
        help_norm,
    )
