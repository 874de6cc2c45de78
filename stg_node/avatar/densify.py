"""Densification: where the avatar gains and loses Gaussians (gsplat-style strategy, one hook).

As gsplat's strategies (``gsplat/strategy/default.py``), the strategy holds only its settings:
its statistics live in a *state dict* the caller owns (:meth:`DensifyStrategy.initialize_state`;
every entry a tensor, so a checkpoint stores it as it is), and everything one step saw comes in
explicitly as :class:`DensifyInputs` (the rendered view, the body's canonical surface, the
training frames' time range, the motion threshold). The trainer calls
:meth:`DensifyStrategy.step_post_backward` after every optimiser step; on its schedule the
strategy edits the table through the optimiser (so Adam moments follow the rows) and resizes the
per-Gaussian entries of the state alike.

Underneath, 3DGS's adaptive density control: Gaussians with a large mean screen-space gradient
(AbsGS: |dL/dmeans2d| summed over pixels) are cloned when small and split in two when large.
Pruning is harder than 3DGS: a Gaussian goes when its opacity is below ``prune_opacity``
(3DGS: 0.005), when it is larger than ``prune_scale_m``, or when its contribution score
``C_i (1 + gamma W_i / delta)`` falls below ``prune_score``; ``C_i`` is its opacity times the
fraction of recent steps it was visible in, and ``W_i`` its time-integrated flow (below), so
Gaussians on fast-moving parts are protected.

STG-Avatar's flow-guided densification, on top:

- *sustained motion*: every step, each visible Gaussian samples the optical flow magnitude
  under its projected centre; ``W_i`` is the running mean of it (pixels per frame), the flow
  integrated over the frames the Gaussian was seen in. Regions with ``W_i > delta`` move.
- *render error per region*: the image is cut into ``region_px`` tiles; a tile's error is the
  mean ``|render - gt|`` over it. Every ``flow_interval`` steps, visible Gaussians in a tile with
  error ``> tau`` and ``W_i > delta`` are seeds.
- *add along the flow*: at each seed pixel the flow residual ``r`` (observed minus rendered
  Gaussian motion) says where the surface went that the model did not follow; ``r`` is lifted to
  3D at the seed's depth and carried into the canonical frame, ``v``; the new Gaussian is placed
  at ``mu_seed + Delta v + N(0, sigma^2)`` with the seed's appearance, a short temporal window
  centred on this frame (it models this moment of the non-rigid motion), and zero motion terms.
- *temporal consistency*: a new Gaussian whose projected position has no valid flow, lies off
  the person, or whose observed flow differs from the seed's by more than
  ``flow_consistency_px`` (it landed across a motion boundary) is rejected.
- *re-sampling*: where the number of Gaussians of a body part (the bone with the largest
  skinning weight) fell below ``resample_fraction`` of its initial count, new Gaussians are drawn
  on that part's canonical surface.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from stg_node.avatar.config import DensifyConfig
from stg_node.avatar.gaussians import MOTION_COLUMNS, new_columns, sample_surface, surface_skin_weights
from stg_node.avatar.model import conjugate, rotate
from stg_node.avatar.motion_basis import NUM_BONES, MotionBases, initial_coefficients
from stg_node.avatar.rigid import SKIN_WEIGHT_EPS, blend, blend_rotation, blend_weights
from stg_node.body import lbs
from stg_node.splat.densify_ops import accumulate_sightings, densify_kernels_apply, motion_help

log = logging.getLogger(__name__)

W_DECAY = 0.9


@dataclass(frozen=True)
class CanonicalSurface:
    """The body's surface in the canonical (big) pose: where re-sampling draws new Gaussians."""

    vertices: torch.Tensor  # (V, 3)
    faces: torch.Tensor  # (F, 3) long
    vertex_weights: torch.Tensor  # (V, 24) skinning weights of the body


@dataclass
class DensifyInputs:
    """What one training step hands to the strategy: everything it reads, explicitly."""

    iteration: int
    info: dict  # rasterize() info of the step (means2d with .grad/.absgrad, radii, depths)
    index: torch.Tensor | None  # table rows of the rendered Gaussians (None = all)
    camera: object  # Camera3 of the rendered crop
    crop: tuple[int, int, int, int]
    render: torch.Tensor  # (h, w, 3) rendered RGB, detached
    target: torch.Tensor  # (h, w, 3)
    mask: torch.Tensor | None  # (h, w) bool
    flow: object | None  # FlowPair of the frame (full image), or None
    u: float  # normalised time of the frame
    bones: object  # PosedBones of the frame
    generator: torch.Generator
    motion_threshold_px: float  # delta: sustained motion (see motion_threshold)
    time_range: tuple[float, float]  # normalised times of the first and last training frame
    surface: CanonicalSurface
    rendered_flow: torch.Tensor | None = None  # (h, w, 2) per-pixel Gaussian motion, detached
    # (h, w) camera depth of the surface each pixel sees (inf where nothing is), detached: a Gaussian
    # behind it reads the flow of what hides it, not its own (occlusion-aware flow statistics)
    rendered_depth: torch.Tensor | None = None
    grow_in_time: bool = True  # temporal copies and flow-guided additions (off while the trainer decides)
    camera_slot: int = 0  # which training camera the step renders: 0, 1, ... in order of arrival


# Per-Gaussian entries of the state (resized with the table's rows).
ROW_STATE = (
    "grad_sum",
    "vis_count",
    "front_count",
    "flow_w",
    "resid_w",
    "help_dot",
    "help_norm",
    "was_dynamic",
    "m_per_px",
    "alive_count",
    "depth_total",
    "front_total",
)
# Per-Gaussian, per-training-camera entries (n, cameras): motion seen in pixels depends on the view
# (across one camera's image is along another's rays), so it is kept per camera, never averaged.
CAMERA_STATE = ("resid_cam",)
# The row statistics the sightings kernel updates in place (float32 CPU: it applies).
STATISTICS_IN_KERNEL = ("grad_sum", "vis_count", "front_count", "m_per_px", "flow_w", "resid_w")
# What a cover of surface never seen takes from its cube's rows (opacity-weighted means): _thin_unseen.
MERGED_COLUMNS = ("means", "features", "sh", "skin_weights", "skin_delta")
COUNT_PREFIX = "count."


def surface_depth(depth: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """(h, w) depth of the surface each pixel sees: the render's expected depth (h, w, 1), inf where
    the pixel is under half covered (nothing there to hide a Gaussian)."""
    covered = alpha[..., 0].detach() > 0.5
    return torch.where(covered, depth[..., 0].detach(), torch.full_like(depth[..., 0], math.inf))


def motion_threshold(config: DensifyConfig, flow_magnitudes) -> float:
    """delta (px per frame) from the frames' mean flow magnitudes: see DensifyConfig.motion_floor_px."""
    mags = sorted(float(m) for m in flow_magnitudes)
    median = mags[len(mags) // 2] if mags else 0.0
    return max(config.motion_floor_px, config.motion_relative * median)


def counts(state: dict[str, torch.Tensor]) -> dict[str, int]:
    """What the strategy did so far (cloned, split, pruned, flow_added, ...), from its state."""
    return {k[len(COUNT_PREFIX) :]: int(v) for k, v in state.items() if k.startswith(COUNT_PREFIX)}


class DensifyStrategy:
    def __init__(self, config: DensifyConfig, total_iterations: int):
        self.config = config
        self.total = int(total_iterations)

    # --- state -----------------------------------------------------------------------------------
    def initialize_state(self, model) -> dict[str, torch.Tensor]:
        """A fresh state for ``model`` (the caller keeps it and hands it to every step)."""
        n = model.table.num
        dev = model.device
        gate = model.table.motion_gate()
        return {
            "grad_sum": torch.zeros(n, device=dev),
            "vis_count": torch.zeros(n, device=dev),
            "front_count": torch.zeros(n, device=dev),  # of those, steps it was the surface seen (_in_front)
            "flow_w": torch.zeros(n, device=dev),  # W_i, px per frame
            "resid_w": torch.zeros(n, device=dev),  # R_i: flow the model's own motion misses, px per frame
            "help_dot": torch.zeros(n, device=dev),  # sum of <dL/dx_i, m_i(t)>: would moving help (< 0)
            "help_norm": torch.zeros(n, device=dev),  # sum of |dL/dx_i| |m_i(t)|
            "was_dynamic": torch.zeros(n, device=dev)
            if gate is None
            else gate.float(),  # at the last density step
            "m_per_px": torch.zeros(n, device=dev),  # metres one pixel spans at the Gaussian (running mean)
            # steps of the current interval the row existed in: what its visibility is a fraction of
            # (a row added along the flow mid-interval is judged on the steps it was there for)
            "alive_count": torch.zeros(n, device=dev),
            # over the row's whole life (never reset): the depth-tested steps it existed in, and those in
            # which it was the surface seen (_in_front); 0 of >= unseen_after_views: surface never shown
            "depth_total": torch.zeros(n, device=dev),
            "front_total": torch.zeros(n, device=dev),
            "steps_seen": torch.zeros(1, device=dev),  # scalars are 1-element tensors (as stored)
            "initial_part_counts": self._part_counts(model),
        }

    @staticmethod
    def _resize(state: dict, keep: torch.Tensor | None = None, added: int = 0) -> None:
        for name in (n for n in ROW_STATE + CAMERA_STATE if n in state):
            t = state[name]
            if keep is not None:
                t = t[keep]
            if added:
                t = torch.cat([t, t.new_zeros((added, *t.shape[1:]))])
            state[name] = t

    @staticmethod
    def _count(state: dict, name: str, value: int) -> None:
        key = COUNT_PREFIX + name
        state[key] = state.get(key, torch.zeros(1)) + int(value)

    @staticmethod
    def _part_counts(model) -> torch.Tensor:
        parts = model.table["skin_weights"].argmax(dim=1)
        return torch.bincount(parts, minlength=24).float()

    # --- the hook --------------------------------------------------------------------------------
    def active(self, iteration: int) -> bool:
        c = self.config
        return c.enabled and c.start_iter <= iteration < int(c.stop_fraction * self.total)

    def flow_round(self, iteration: int) -> bool:
        """Whether this step may add Gaussians along the flow (it then needs the rendered motion)."""
        c = self.config
        return c.flow_guided and self.active(iteration) and (iteration - c.start_iter) % c.flow_interval == 0

    def step_post_backward(
        self, model, optimizer, state: dict[str, torch.Tensor], inputs: DensifyInputs
    ) -> dict[str, int]:
        """Accumulate this step's statistics into ``state``; on schedule, grow and prune ``model``
        through ``optimizer`` (``state``'s per-Gaussian entries follow). What it did this step."""
        c = self.config
        if not c.enabled:
            return {}
        if inputs.iteration >= int(c.stop_fraction * self.total) and inputs.grow_in_time:
            # the schedule is over (no density step, gate or flow round reads them any more) and
            # no non-rigid trial is deciding on the flow residual: no statistics to keep (issue 24)
            return {}
        if "m_per_px" not in state:  # a state saved before it was kept
            state["m_per_px"] = torch.zeros_like(state["vis_count"])
        if "front_count" not in state:  # likewise: every sighting counted as seen
            state["front_count"] = state["vis_count"].clone()
        if "alive_count" not in state:  # likewise: every row there for the whole interval
            state["alive_count"] = torch.full_like(state["vis_count"], float(state["steps_seen"]))
        for name in ("depth_total", "front_total"):  # likewise: sightings counted from now on
            if name not in state:
                state[name] = torch.zeros_like(state["vis_count"])
        self._accumulate(state, inputs)
        self._accumulate_help(model, state, inputs)
        report: dict[str, int] = {}
        it = inputs.iteration
        gate_round = c.gate_start_iter <= it < int(c.stop_fraction * self.total)
        gate_round &= (it - c.gate_start_iter) % c.interval == 0
        if not self.active(it):
            if gate_round:
                report.update(self._gate_round(model, optimizer, state, inputs))
                self._tally(state, report)
            return report
        if c.flow_guided and inputs.grow_in_time and inputs.flow is not None and self.flow_round(it):
            report["flow_added"] = self._flow_guided(model, optimizer, state, inputs)
        density_step = (it - c.start_iter) % c.interval == 0 and it > c.start_iter
        # A density step judges at least half an interval of statistics: after a restart of them (the
        # non-rigid part switched off: what the model with motion terms saw does not judge the rigid
        # one) the interval runs on to the next step instead of cloning on a step or two of gradients.
        density_step &= float(state["steps_seen"]) >= c.interval / 2
        if density_step:
            report.update(self._adaptive_density(model, optimizer, state, inputs))
        if gate_round:  # after the density step: its temporal split saw who was dynamic all interval
            report.update(self._gate_round(model, optimizer, state, inputs))
        if density_step:  # a new interval starts only once both have read the one that ends
            self._reset_interval(state)
        self._tally(state, report)
        return report

    @staticmethod
    def _reset_interval(state: dict) -> None:
        """Start a new density interval: the screen-gradient and visibility statistics start from zero
        (the flow's running means and the pixel spans carry on)."""
        for name in ("grad_sum", "vis_count", "front_count", "steps_seen", "alive_count"):
            if name in state:
                state[name].zero_()

    def _tally(self, state: dict, report: dict[str, int]) -> None:
        for k, v in report.items():
            self._count(state, k, v)

    def _gate_round(self, model, optimizer, state: dict, inputs: DensifyInputs) -> dict[str, int]:
        # The image's pull on a Gaussian while it is seen: hidden, it gets no gradient, and with
        # several cameras around it is hidden from about half of them, which would halve its mean.
        grads = state["grad_sum"] / state["front_count"].clamp_min(1)
        c = self.config
        last = inputs.iteration + c.interval >= int(c.stop_fraction * self.total)  # no round follows
        out = self._gate_motion(model, optimizer, state, inputs, grads, last_round=last)
        state["help_dot"].zero_()
        state["help_norm"].zero_()
        return out

    @torch.no_grad()
    def _accumulate(self, state: dict, inputs: DensifyInputs) -> None:
        """This step's sightings into the interval's statistics: the C++ kernel in one pass where it
        applies (float32 CPU, densify_ops), else the torch reference."""
        means2d = inputs.info["means2d"]
        grad = getattr(means2d, "absgrad", None)
        if grad is None:
            grad = means2d.grad
        if grad is None:
            return
        if not self._accumulate_kernel(state, inputs, grad):
            self._accumulate_torch(state, inputs, grad)
        state["steps_seen"] += 1
        if "alive_count" in state:
            state["alive_count"] += 1

    def _accumulate_kernel(self, state: dict, inputs: DensifyInputs, grad: torch.Tensor) -> bool:
        """``_accumulate_torch`` in one C++ pass; False (nothing done) where the kernel does not apply."""
        info, c = inputs.info, self.config
        radii, means2d, depths = info["radii"], info["means2d"], info.get("depths")
        flow = valid = rendered_flow = None
        if inputs.flow is not None:
            flow = torch.from_numpy(inputs.flow.forward)
            valid = torch.from_numpy(inputs.flow.valid_forward)
            rendered_flow = inputs.rendered_flow
        in_front = inputs.rendered_depth is not None and depths is not None and c.occlusion_m > 0
        if (
            c.unseen_cell_m > 0  # the opt-in unseen-surface counters live in the torch path only
            or radii.dtype != torch.int32
            or radii.dim() > 2
            or (depths is not None and depths.numel() != means2d.shape[0])
            or (flow is not None and (flow.dtype != torch.float32 or valid.dtype != torch.bool))
            or not densify_kernels_apply(means2d, grad, depths, inputs.rendered_depth if in_front else None)
            or not densify_kernels_apply(flow, rendered_flow)
            or not all(densify_kernels_apply(state[k]) for k in STATISTICS_IN_KERNEL)
        ):
            return False
        slot = 0
        if rendered_flow is not None:
            slot = inputs.camera_slot
            if not densify_kernels_apply(self._camera_residuals(state, slot)):
                return False
        x0, y0, w, h = inputs.crop
        accumulate_sightings(
            state,
            radii=radii,
            means2d=means2d,
            grad=grad,
            index=inputs.index,
            crop_size=(w, h),
            tiles=self._tile_errors(inputs) if c.clone_on_error else None,
            region_px=c.region_px,
            error_threshold=c.error_threshold,
            depths=depths,
            focal=float(inputs.camera.K[0, 0]) if depths is not None else 1.0,
            rendered_depth=inputs.rendered_depth if in_front else None,
            occlusion_m=c.occlusion_m,
            flow=flow,
            valid=valid,
            crop_origin=(x0, y0),
            rendered_flow=rendered_flow,
            camera_slot=slot,
            decay=W_DECAY,
        )
        return True

    @torch.no_grad()
    def _accumulate_torch(self, state: dict, inputs: DensifyInputs, grad: torch.Tensor) -> None:
        """The sightings in torch (any device and dtype): the kernel's reference."""
        info = inputs.info
        radii = info["radii"]
        visible = (radii > 0).all(dim=-1) if radii.dim() == 2 else radii > 0
        rows = visible.nonzero().squeeze(1)
        table_rows = rows if inputs.index is None else inputs.index[rows]
        means2d = info["means2d"]
        pixels = float(inputs.crop[2] * inputs.crop[3])
        vis_count = state["vis_count"]
        pull = grad[rows].norm(dim=-1) * pixels
        if self.config.clone_on_error:
            pull = pull * self._error_weight(inputs, means2d.detach()[rows])
        state["grad_sum"].index_add_(0, table_rows, pull)
        vis_count.index_add_(0, table_rows, torch.ones_like(table_rows, dtype=vis_count.dtype))
        x0, y0, w, h = inputs.crop
        xy = means2d.detach()[rows]
        px = xy[:, 0].round().long().clamp(0, w - 1)
        py = xy[:, 1].round().long().clamp(0, h - 1)
        front = self._in_front(info, rows, px, py, inputs)
        state["front_count"].index_add_(
            0, table_rows[front], torch.ones_like(table_rows[front], dtype=vis_count.dtype)
        )
        if self.config.unseen_cell_m > 0 and self._depth_tested(info, inputs) and "front_total" in state:
            state["depth_total"] += 1
            state["front_total"].index_add_(
                0, table_rows[front], torch.ones_like(table_rows[front], dtype=vis_count.dtype)
            )
        depths = info.get("depths")
        if depths is not None:  # what a pixel spans at the Gaussian: depth / focal length
            span = depths.detach()[rows].reshape(-1) / float(inputs.camera.K[0, 0])
            m_per_px = state["m_per_px"]
            old = m_per_px[table_rows]
            m_per_px[table_rows] = torch.where(old > 0, W_DECAY * old + (1 - W_DECAY) * span, span)
        if inputs.flow is None:
            return
        fwd = torch.from_numpy(inputs.flow.forward[y0 : y0 + h, x0 : x0 + w]).to(xy.device)
        valid = torch.from_numpy(inputs.flow.valid_forward[y0 : y0 + h, x0 : x0 + w]).to(xy.device)
        ok = valid[py, px] & front
        seen_flow = fwd[py, px]
        mag = seen_flow.norm(dim=-1)
        sel = table_rows[ok]
        flow_w = state["flow_w"]
        flow_w[sel] = W_DECAY * flow_w[sel] + (1 - W_DECAY) * mag[ok]
        if inputs.rendered_flow is not None:
            missed = (seen_flow - inputs.rendered_flow[py, px]).norm(dim=-1)
            per_camera = self._camera_residuals(state, inputs.camera_slot)
            column = per_camera[:, inputs.camera_slot]
            column[sel] = W_DECAY * column[sel] + (1 - W_DECAY) * missed[ok]  # a view: writes per_camera
            # R_i: the most any training camera sees missed. Averaged over cameras, motion across one
            # view's image would be diluted by the views it runs along the rays of (near zero pixels).
            state["resid_w"][sel] = per_camera[sel].amax(dim=1)

    @staticmethod
    def _camera_residuals(state: dict, slot: int) -> torch.Tensor:
        """(n, cameras) running missed flow per training camera, with a column for ``slot``."""
        per_camera = state.get("resid_cam")
        if per_camera is None:  # a fresh state, or one saved before cameras were told apart
            per_camera = state["resid_w"][:, None].clone()
        if slot >= per_camera.shape[1]:
            pad = per_camera.new_zeros((per_camera.shape[0], slot + 1 - per_camera.shape[1]))
            per_camera = torch.cat([per_camera, pad], dim=1)
        state["resid_cam"] = per_camera
        return per_camera

    def _error_weight(self, inputs: DensifyInputs, xy: torch.Tensor) -> torch.Tensor:
        """(len(xy),) in [0, 1]: how badly the region under each projected centre is explained,
        its tile's mean ``|render - gt|`` over ``error_threshold`` (tau), capped at 1.

        Under an L1 loss the screen gradient's size does not shrink as the fit improves (each
        pixel pulls with the residual's sign), so AbsGS's summed ``|dL/dmeans2d|`` stays high on
        fine texture that is already reproduced: a still subject kept cloning as much as a moving
        one. Weighted by the remaining error, the clone signal follows what the image still gets
        wrong (motion the model misses, unresolved detail), as tau already says for the seeds.
        """
        tiles = self._tile_errors(inputs)
        r = self.config.region_px
        h, w = inputs.render.shape[:2]
        px = xy[:, 0].round().long().clamp(0, w - 1)
        py = xy[:, 1].round().long().clamp(0, h - 1)
        return (tiles[py // r, px // r] / self.config.error_threshold).clamp(max=1.0)

    def _tile_errors(self, inputs: DensifyInputs) -> torch.Tensor:
        """Mean ``|render - gt|`` per ``region_px`` square tile of the step's crop (ceil-divided)."""
        err = (inputs.render - inputs.target).abs().mean(-1)  # (h, w)
        r = self.config.region_px
        return F.avg_pool2d(err[None, None], r, r, ceil_mode=True)[0, 0]

    @torch.no_grad()
    def _accumulate_help(self, model, state: dict, inputs: DensifyInputs) -> None:
        """Shared motion bases: would a static Gaussian's loss fall if it moved with the bases?

        A static Gaussian that started to move would get the offset ``m_i(t)`` its bones' shared
        motions give (its initial coefficients, motion_basis.initial_coefficients); to first order
        that changes the loss by ``<dL/dx_i, m_i(t)>``. Summed over the steps it is seen in and
        normalised, ``-sum <g, m> / sum |g| |m|`` near 1 says the image keeps pulling it the way
        the garment around it moves.
        """
        table, bases = model.table, model.motion_bases
        gate = table.motion_gate()
        grad = table["means"].grad
        if bases is None or gate is None or grad is None:
            return
        table_delta = table.get("skin_delta")
        motions = bases.at(inputs.u).detach()
        if (
            table["skin_weights"].shape[1] == NUM_BONES
            and densify_kernels_apply(table["skin_weights"], table_delta, motions, table["means"], grad)
            and densify_kernels_apply(state["help_dot"], state["help_norm"])
        ):  # one C++ pass over the rows (densify_ops); the torch below is its reference
            motion_help(
                table["skin_weights"],
                table_delta,
                SKIN_WEIGHT_EPS,
                motions,
                table["means"],
                grad,
                gate,
                state["help_dot"],
                state["help_norm"],
            )
            return
        self._accumulate_help_torch(table, bases, gate, grad, state, inputs)

    @staticmethod
    def _accumulate_help_torch(table, bases, gate, grad, state: dict, inputs: DensifyInputs) -> None:
        """``_accumulate_help`` in torch (any device and dtype): the kernel's reference."""
        static = ~gate
        table_delta = table.get("skin_delta")
        if 2 * int(static.sum()) > table.num:
            # Most rows static (the usual case; the regularisers give every centre a gradient): every
            # row at once, the moving ones masked to zero, no gathers and scatters. A static row
            # without gradient adds exactly zero, as if it were left out.
            weights = blend_weights(
                table["skin_weights"].detach(), None if table_delta is None else table_delta.detach()
            )
            coef = initial_coefficients(weights, bases.count)
            would = MotionBases.apply(bases.at(inputs.u).detach(), coef, table["means"].detach())
            zero = grad.new_zeros(())
            state["help_dot"].add_(torch.where(static, (grad * would).sum(dim=1), zero))
            state["help_norm"].add_(torch.where(static, grad.norm(dim=1) * would.norm(dim=1), zero))
            return
        rows = (static & (grad.abs().sum(dim=1) > 0)).nonzero().squeeze(1)
        if rows.numel() == 0:
            return
        weights = blend_weights(  # of these rows only: the blend is row by row
            table["skin_weights"].detach()[rows], None if table_delta is None else table_delta.detach()[rows]
        )
        coef = initial_coefficients(weights, bases.count)
        would = MotionBases.apply(bases.at(inputs.u).detach(), coef, table["means"].detach()[rows])
        g = grad[rows]
        state["help_dot"].index_add_(0, rows, (g * would).sum(dim=1))
        state["help_norm"].index_add_(0, rows, g.norm(dim=1) * would.norm(dim=1))

    # --- flow-guided densification ---------------------------------------------------------------
    @torch.no_grad()
    def _flow_guided(self, model, optimizer, state: dict, inputs: DensifyInputs) -> int:
        c = self.config
        room = self._room(model)
        if room <= 0:
            return 0
        x0, y0, w, h = inputs.crop
        r = c.region_px
        tiles = self._tile_errors(inputs)  # mean error per region
        info = inputs.info
        radii = info["radii"]
        visible = (radii > 0).all(dim=-1) if radii.dim() == 2 else radii > 0
        rows = visible.nonzero().squeeze(1)
        if rows.numel() == 0:
            return 0
        table_rows = rows if inputs.index is None else inputs.index[rows]
        xy = info["means2d"].detach()[rows]
        px = xy[:, 0].round().long()
        py = xy[:, 1].round().long()
        inside = (px >= 0) & (px < w) & (py >= 0) & (py < h)
        px, py, rows, table_rows = px[inside], py[inside], rows[inside], table_rows[inside]
        tile_err = tiles[py // r, px // r]
        flow_w = state["flow_w"]
        seeds = (tile_err > c.error_threshold) & self._seed_motion(state, table_rows, inputs)
        if not bool(seeds.any()):
            return 0
        fwd = torch.from_numpy(inputs.flow.forward[y0 : y0 + h, x0 : x0 + w]).to(xy.device)
        valid = torch.from_numpy(inputs.flow.valid_forward[y0 : y0 + h, x0 : x0 + w]).to(xy.device)
        seeds &= valid[py, px] & self._in_front(info, rows, px, py, inputs)
        idx = seeds.nonzero().squeeze(1)
        if idx.numel() == 0:
            return 0
        # Strongest seeds first: error x motion.
        score = tile_err[idx] * flow_w[table_rows[idx]]
        idx = idx[score.argsort(descending=True)][: min(c.flow_max_new, room)]
        sx, sy, srow = px[idx], py[idx], table_rows[idx]
        observed = fwd[sy, sx]
        if inputs.rendered_flow is not None:
            residual = observed - inputs.rendered_flow[sy, sx]
        else:
            residual = observed
        depth = info["depths"].detach()[rows[idx]]
        K = inputs.camera.K
        # Lift the pixel residual to a camera-space displacement at the seed's depth, then to world.
        d_cam = torch.stack(
            [residual[:, 0] * depth / K[0, 0], residual[:, 1] * depth / K[1, 1], torch.zeros_like(depth)], 1
        )
        d_world = d_cam @ inputs.camera.viewmat[:3, :3]  # R^T d
        # Into the canonical frame of each seed: inverse of its blended rotation.
        weights = model.skin_weights()[srow]
        blended = blend(weights, inputs.bones)
        d_canon = rotate(conjugate(blend_rotation(weights, inputs.bones)), d_world)
        noise = torch.randn(d_canon.shape, generator=inputs.generator).to(d_canon.device)
        new_means = model.table["means"][srow] + c.flow_step * d_canon + c.flow_noise_m * noise
        # Temporal consistency with the flow: where the new centre projects, the observed flow must
        # be valid, on the person, and close to the seed's.
        posed_new = (blended[:, :3, :3] @ new_means[..., None]).squeeze(-1) + blended[:, :3, 3]
        p_new = inputs.camera.project(posed_new)
        nx, ny = p_new[:, 0].round().long(), p_new[:, 1].round().long()
        ok = (nx >= 0) & (nx < w) & (ny >= 0) & (ny < h)
        nxc, nyc = nx.clamp(0, w - 1), ny.clamp(0, h - 1)
        ok &= valid[nyc, nxc]
        if inputs.mask is not None:
            ok &= inputs.mask[nyc, nxc]
        ok &= (fwd[nyc, nxc] - observed).norm(dim=-1) <= c.flow_consistency_px
        keep = ok.nonzero().squeeze(1)
        self._count(state, "flow_rejected", int((~ok).sum()))
        if keep.numel() == 0:
            return 0
        srow = srow[keep]
        rows_new = self._copy_rows(model, srow)
        rows_new["means"] = new_means[keep]
        rows_new["log_scales"] = rows_new["log_scales"] + torch.log(torch.tensor(0.8))
        rows_new["opacity_logits"] = torch.full_like(rows_new["opacity_logits"], -1.0)
        for name in MOTION_COLUMNS:
            if name in rows_new:
                rows_new[name] = torch.zeros_like(rows_new[name])
        if "motion_coef" in rows_new:
            skin = blend_weights(rows_new["skin_weights"], rows_new.get("skin_delta"))
            rows_new["motion_coef"] = initial_coefficients(skin, rows_new["motion_coef"].shape[1])
        if "motion_gate" in rows_new:
            rows_new["motion_gate"] = torch.ones_like(rows_new["motion_gate"])  # non-rigid detail: may move
        if "t_center" in rows_new:
            rows_new["t_center"] = torch.full_like(rows_new["t_center"], inputs.u)
            rows_new["t_log_scale"] = torch.full_like(
                rows_new["t_log_scale"], float(torch.log(torch.tensor(c.new_time_scale)))
            )
        self._append(optimizer, state, rows_new)
        return int(keep.numel())

    def _in_front(self, info: dict, rows: torch.Tensor, px, py, inputs: DensifyInputs) -> torch.Tensor:
        """(len(rows),) bool: rendered Gaussians ``rows`` that are (part of) the surface seen at their
        pixel, not hidden behind it by more than ``occlusion_m``; all of them without a depth render.

        The flow under a hidden Gaussian's centre is its occluder's. With one camera the hidden side
        is never seen, so a wrong reading there costs little; with several, every camera's hidden
        side is another's visible one, and the occluder's motion would open its gate and seed
        Gaussians behind the surface that the other cameras then see.
        """
        if not self._depth_tested(info, inputs):
            return torch.ones(rows.shape[0], dtype=torch.bool, device=rows.device)
        depth = info["depths"].detach()[rows].reshape(-1)
        return depth <= inputs.rendered_depth[py, px] + self.config.occlusion_m

    def _depth_tested(self, info: dict, inputs: DensifyInputs) -> bool:
        """Whether this step can tell the surface seen from what hides behind it (:meth:`_in_front`)."""
        return (
            inputs.rendered_depth is not None
            and info.get("depths") is not None
            and self.config.occlusion_m > 0
        )

    def _seed_motion(self, state: dict, rows: torch.Tensor, inputs: DensifyInputs) -> torch.Tensor:
        """(len(rows),) bool: rows on motion a flow-guided seed needs: flow the model's own rendered
        motion misses (``flow_seed_missed``, when the step rendered its motion) as this step's camera
        sees it (the seed moves along this camera's flow), else raw flow > delta."""
        c = self.config
        if c.flow_seed_missed and inputs.rendered_flow is not None:
            own = self._camera_residuals(state, inputs.camera_slot)[:, inputs.camera_slot]
            return own[rows] > c.residual_motion_px
        return state["flow_w"][rows] > inputs.motion_threshold_px

    # --- clone / split / prune / re-sample -------------------------------------------------------
    @torch.no_grad()
    def _adaptive_density(self, model, optimizer, state: dict, inputs: DensifyInputs) -> dict[str, int]:
        c = self.config
        table = model.table
        report = {"cloned": 0, "split": 0, "pruned": 0, "resampled": 0}
        vis_count = state["vis_count"]
        grads = state["grad_sum"] / vis_count.clamp_min(1)
        was_dynamic = state["was_dynamic"] > 0.5  # dynamic for a whole interval already
        scales = table.scales().max(dim=1).values
        small = scales <= c.percent_dense * model.extent
        hot = (grads > c.grad_threshold) & (vis_count > 0)
        room = self._room(model)
        # Dynamic Gaussians on long temporal windows are refined in time first (they fail because
        # one polynomial cannot follow the motion), the rest in space as in 3DGS.
        tsplit_rows = (
            self._temporal_split_rows(model, inputs.time_range, hot & was_dynamic, grads, room)
            if inputs.grow_in_time
            else None
        )
        taken = torch.zeros(table.num, dtype=torch.bool, device=model.device)
        if tsplit_rows is not None:
            taken[tsplit_rows[0]] = True
            room -= tsplit_rows[1]["means"].shape[0] - tsplit_rows[0].numel()
        clone = (hot & small & ~taken).nonzero().squeeze(1)
        split = (hot & ~small & ~taken).nonzero().squeeze(1)
        split = split[grads[split].argsort(descending=True)][: max(room, 0)]
        room -= split.numel()  # a split removes one and adds two
        clone = clone[grads[clone].argsort(descending=True)][: max(room, 0)]
        n_before = table.num
        if clone.numel():
            self._append(optimizer, state, self._copy_rows(model, clone))
            report["cloned"] = int(clone.numel())
        if split.numel():
            rows = self._copy_rows(model, split)
            rows2 = {k: v.clone() for k, v in rows.items()}
            std = table.scales()[split]
            rot = lbs.quaternion_to_matrix(table["quats"][split])
            for r in (rows, rows2):
                offset = torch.randn(std.shape, generator=inputs.generator).to(std.device) * std
                r["means"] = table["means"][split] + (rot @ offset[..., None]).squeeze(-1)
                r["log_scales"] = r["log_scales"] - torch.log(torch.tensor(1.6))
            both = {k: torch.cat([rows[k], rows2[k]]) for k in rows}
            self._append(optimizer, state, both)
            report["split"] = int(split.numel())
        if tsplit_rows is not None:
            sources, rows = tsplit_rows
            self._append(optimizer, state, rows)
            report["time_split"] = int(sources.numel())
            split = torch.cat([split, sources])
        # Prune (the split originals, plus what contributes nothing). Each row is judged on the steps
        # it existed in: a row added along the flow this step has no statistics yet, and one added
        # mid-interval is seen in a fraction of the steps it was there for, not of the interval's.
        n = model.table.num
        prune = torch.zeros(n, dtype=torch.bool, device=model.device)
        prune[split] = True
        opacity = model.table.opacities()
        alive = state.get("alive_count")
        if alive is None:  # a state without it: every row there for the whole interval (as before)
            alive = torch.full_like(state["vis_count"], float(state["steps_seen"]))
        seen = state["vis_count"] / alive.clamp_min(1.0)
        delta = inputs.motion_threshold_px
        score = opacity * seen * (1.0 + c.motion_protect_gamma * state["flow_w"] / delta)
        old = (torch.arange(n, device=model.device) < n_before) & (alive > 0)  # new rows: no statistics yet
        prune |= old & (opacity < c.prune_opacity)
        prune |= old & (score < c.prune_score) & (alive >= c.interval)
        prune |= model.table.scales().max(dim=1).values > c.prune_scale_m
        thinned = self._thin_unseen(model, state) & ~prune
        prune |= thinned
        if bool(thinned.any()):
            report["unseen_thinned"] = int(thinned.sum())
        if bool(prune.all()):
            prune[opacity.argmax()] = False  # never prune the model away entirely
        if bool(prune.any()):
            optimizer.keep(~prune)
            self._resize(state, keep=~prune)
            report["pruned"] = int(prune.sum()) - int(split.numel()) - report.get("unseen_thinned", 0)
        report["resampled"] = self._resample(model, optimizer, state, inputs)
        return report  # the caller starts the next interval (_reset_interval) after the gate round

    @torch.no_grad()
    def _thin_unseen(self, model, state: dict) -> torch.Tensor:
        """(n,) bool: rows to drop so surface no training view shows keeps one Gaussian per cube.

        A row is *unseen* when it existed in at least ``unseen_after_views`` depth-tested steps (those
        that render depth: the flow term's, every ``loss.flow_every``-th) and was the surface seen in
        none (state ``depth_total``, ``front_total``; :meth:`_in_front`). Unseen rows are grouped by
        the ``unseen_cell_m`` cube of the canonical space their centre lies in; each cube keeps one
        row, its most opaque, which takes the cube's opacity-weighted mean centre, appearance and
        skinning, keeps its own opacity, and widens its two larger axes to at least
        ``model.init_scale_factor`` times the cube (as the initial samples are sized to their
        spacing); the others go. The thin axis and the orientation stay: the silhouette and the
        prior's colour are what such a cover keeps. A cover later seen gets the image's gradient and
        is split as any large Gaussian. Idempotent: a cube reduced to one cover is left as it is.
        """
        c = self.config
        table = model.table
        drop = torch.zeros(table.num, dtype=torch.bool, device=model.device)
        if c.unseen_cell_m <= 0 or "front_total" not in state:
            return drop
        unseen = (state["depth_total"] >= c.unseen_after_views) & (state["front_total"] == 0)
        rows = unseen.nonzero().squeeze(1)
        if rows.numel() == 0:
            return drop
        cube = torch.floor(table["means"].detach()[rows] / c.unseen_cell_m).long()
        _, group = torch.unique(cube, dim=0, return_inverse=True)
        by_opacity = torch.argsort(table.opacities().detach()[rows], descending=True, stable=True)
        order = by_opacity[torch.argsort(group[by_opacity], stable=True)]  # by cube, most opaque first
        g = group[order]
        first = torch.ones_like(g, dtype=torch.bool)
        first[1:] = g[1:] != g[:-1]
        drop[rows[order[~first]]] = True
        kept = rows[order[first]]  # kept[g]: the cover of cube g (unique's ids are sorted, as ``order``)
        # The cover stands for its cube: its centre, appearance and skinning are the opacity-weighted
        # means of the cube's rows (one row's colour alone would carry that sample's deviation).
        weight = table.opacities().detach()[rows].clamp_min(1e-6)
        total = torch.zeros(kept.shape[0], device=weight.device).index_add_(0, group, weight)
        for name in MERGED_COLUMNS:
            if name in table:
                col = table[name].data
                flat = col[rows].reshape(rows.shape[0], -1) * weight[:, None]
                summed = torch.zeros((kept.shape[0], flat.shape[1]), device=flat.device, dtype=flat.dtype)
                summed.index_add_(0, group, flat)
                col[kept] = (summed / total[:, None]).reshape(col[kept].shape)
        # Sized to the cube as the initial samples are to their spacing (model.init_scale_factor).
        log_scales = table["log_scales"].data
        widened = log_scales[kept].clamp_min(math.log(model.config.init_scale_factor * c.unseen_cell_m))
        thin_axis = log_scales[kept].argmin(dim=1, keepdim=True)
        widened.scatter_(1, thin_axis, log_scales[kept].gather(1, thin_axis))
        log_scales[kept] = widened
        return drop

    @torch.no_grad()
    def _temporal_split_rows(
        self, model, time_range: tuple[float, float], candidates: torch.Tensor, grads: torch.Tensor, room: int
    ):
        """Copies on shorter temporal windows of the dynamic, still-pulled Gaussians (sources, rows).

        A Gaussian present at all times becomes up to ``temporal_split_max`` copies centred evenly over
        the training time range (``time_range``: the first and last frame's normalised time), a finite
        window becomes two copies at ``mu +- s/2``; the windows are 0.6x their spacing, so
        neighbouring copies cross at about half opacity. Each copy keeps the source's other
        attributes (its polynomial then fits its own part of the motion).
        """
        c = self.config
        table = model.table
        gate = table.motion_gate()
        if not c.temporal_split or gate is None or "t_center" not in table or room <= 0:
            return None
        if "motion_coef" in table:  # shared bases follow the motion at every knot: no copies needed
            return None
        lo, hi = time_range
        span = max(hi - lo, 1e-3)
        scale = table["t_log_scale"].exp()
        cand = candidates & gate & (scale > c.min_time_scale / 0.6)
        idx = cand.nonzero().squeeze(1)
        if idx.numel() == 0:
            return None
        idx = idx[grads[idx].argsort(descending=True)]
        always = scale[idx] >= span
        k_always = int(min(max(round(span / (2 * c.min_time_scale)), 2), c.temporal_split_max))
        copies = torch.where(always, k_always, 2)
        keep = torch.cumsum(copies, 0) <= room
        idx, always, copies = idx[keep], always[keep], copies[keep]
        if idx.numel() == 0:
            return None
        source = torch.repeat_interleave(idx, copies)
        rows = self._copy_rows(model, source)
        slot = torch.cat([torch.arange(int(k), device=idx.device) for k in copies.tolist()])
        a = torch.repeat_interleave(always, copies)
        k = torch.repeat_interleave(copies, copies).float()
        mu = table["t_center"].detach()[source]
        s = scale[source]
        spacing = torch.where(a, span / k, s)
        centre = torch.where(a, lo + (slot + 0.5) * spacing, mu + (slot - 0.5) * s)
        rows["t_center"] = centre
        rows["t_log_scale"] = (0.6 * spacing).clamp_min(c.min_time_scale).log()
        return idx, rows

    @torch.no_grad()
    def _resample(self, model, optimizer, state: dict, inputs: DensifyInputs) -> int:
        c = self.config
        initial = state.get("initial_part_counts")
        if c.resample_fraction <= 0 or initial is None:
            return 0
        counts = self._part_counts(model)
        low = (counts < c.resample_fraction * initial).nonzero().squeeze(1)
        if low.numel() == 0:
            return 0
        surface = inputs.surface
        vertices, faces = surface.vertices, surface.faces
        vertex_part = surface.vertex_weights.argmax(dim=1)
        face_part = vertex_part[faces[:, 0]]
        added = 0
        for part in low.tolist():
            want = int(c.resample_fraction * initial[part] - counts[part])
            want = min(want, self._room(model))
            sel = (face_part == part).nonzero().squeeze(1)
            if want <= 0 or sel.numel() == 0:
                continue
            # Random draws on the CPU (the step's generator lives there), whatever the model's device.
            points, face, bary = sample_surface(vertices.cpu(), faces[sel].cpu(), want, inputs.generator)
            weights = surface_skin_weights(
                faces[sel].cpu(), surface.vertex_weights.cpu(), face, bary, model.config.skin_init
            )
            scale = (
                float(model.table.scales()[model.table["skin_weights"].argmax(1) == part].mean())
                if (counts[part] > 0)
                else 0.01
            )
            rows = new_columns(
                model.config, points, weights, scale, t_center=inputs.u, generator=inputs.generator
            )
            self._append(optimizer, state, {k: v.to(model.device) for k, v in rows.items()})
            added += want
        return added

    @torch.no_grad()
    def _gate_motion(
        self,
        model,
        optimizer,
        state: dict,
        inputs: DensifyInputs,
        grads: torch.Tensor,
        last_round: bool = False,
    ) -> dict[str, int]:
        """Decide which Gaussians may move, so motion terms exist only where the scene needs them.

        A static Gaussian becomes dynamic when it sits on motion its rendered (skinned) motion misses
        (``R_i > residual_motion_px``; raw flow ``W_i > delta`` with ``motion_signal="flow"``) and the
        image still pulls on it (mean screen gradient above half the clone threshold), or, with shared
        bases, where moving with its bones' shared motions would lower the loss. A dynamic one whose motion
        varied over time by less than ``motion_min_px`` pixels of the views it is seen in (and at
        least ``motion_min_m``; shared bases: the spread of its offset over the knots around their
        mean, polynomials: ``sum |b_ik|``) goes back to static: its centre keeps the mean offset, its
        terms and their Adam moments become exact zeros. With ``motion_min_px`` > 0 the last round opens
        no gate: a gate opened then would keep its motion unchecked to the end of training.
        """
        table = model.table
        gate = table.motion_gate()
        if gate is None:
            return {}
        # On sustained motion and still badly explained by the rigid part. (Opening the gate on any
        # motion above the 1 px floor fits the training view's cloth better, +6 dB in the garment
        # region of the dance benchmark, but novel views got worse: from one camera the extra freedom
        # is spent on placements other views disagree with. docs/AVATAR.md.)
        c = self.config
        if c.motion_signal == "flow":
            moving = state["flow_w"] > inputs.motion_threshold_px
        else:
            moving = state["resid_w"] > c.residual_motion_px
        activate = ~gate & moving & (grads > 0.5 * c.grad_threshold)
        if "motion_coef" in table:  # shared bases: also where moving with them would lower the loss
            helps = -state["help_dot"] / state["help_norm"].clamp_min(1e-20)
            activate |= ~gate & (helps > c.motion_help) & (state["help_norm"] > 0)
        amplitude = torch.zeros(table.num, device=gate.device)
        mean_offset = None
        if "motion" in table:
            amplitude = amplitude + table["motion"].norm(dim=-1).sum(dim=1)
        if "motion_coef" in table and model.motion_bases is not None:
            rows = gate.nonzero().squeeze(1)
            coef = table["motion_coef"].detach()[rows]
            swing, mean = model.motion_bases.variation(coef, table["means"].detach()[rows])
            amplitude[rows] += swing
            mean_offset = torch.zeros_like(table["means"]).index_put((rows,), mean)
        if "rot_motion" in table:
            amplitude = amplitude + 0.1 * table["rot_motion"].norm(dim=-1).sum(dim=1)  # ~0.1 m per radian
        # Motion no view can measure: below motion_min_px of the views the Gaussian is seen in.
        floor = torch.clamp_min(c.motion_min_px * state["m_per_px"], c.motion_min_m)
        if last_round and c.motion_min_px > 0:
            activate[:] = False
        settle = gate & (state["was_dynamic"] > 0.5) & (amplitude < floor)
        if mean_offset is not None and bool(settle.any()):  # keep where the motion held it on average
            table["means"].data[settle] += mean_offset[settle]
        for name in MOTION_COLUMNS:
            if name in table:
                optimizer.zero_rows(name, settle)
        table["motion_gate"].data[activate] = 1.0
        if "motion_coef" in table and bool(activate.any()):
            coef = table["motion_coef"]
            coef.data[activate] = initial_coefficients(model.skin_weights().detach()[activate], coef.shape[1])
        table["motion_gate"].data[settle] = 0.0
        state["was_dynamic"] = table["motion_gate"].detach().clone()
        return {"motion_on": int(activate.sum()), "motion_off": int(settle.sum())}

    # --- helpers ---------------------------------------------------------------------------------
    def _room(self, model) -> int:
        return max(model.config.max_gaussians - model.table.num, 0)

    @staticmethod
    def _copy_rows(model, rows: torch.Tensor) -> dict[str, torch.Tensor]:
        return {name: model.table[name].detach()[rows].clone() for name in model.table.names()}

    def _append(self, optimizer, state: dict, rows: dict[str, torch.Tensor]) -> None:
        n = next(iter(rows.values())).shape[0]
        optimizer.append(rows)
        self._resize(state, added=n)
