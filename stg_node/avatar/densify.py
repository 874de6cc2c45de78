"""Densification: where the avatar gains and loses Gaussians (gsplat-style strategy, one hook).

The trainer calls :meth:`DensifyStrategy.step_post_backward` after every optimiser step with
what the step saw (:class:`StepContext`); the strategy keeps per-Gaussian statistics and, on its
schedule, edits the table through the optimiser (so Adam moments follow the rows).

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
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from stg_node.avatar.config import DensifyConfig
from stg_node.avatar.gaussians import new_columns, sample_surface, surface_skin_weights
from stg_node.avatar.model import conjugate, rotate
from stg_node.avatar.rigid import blend, blend_rotation
from stg_node.body import lbs

log = logging.getLogger(__name__)

W_DECAY = 0.9


@dataclass
class StepContext:
    """What one training step hands to the strategy."""

    iteration: int
    model: object  # AvatarModel
    optimizer: object  # TableOptimizer
    info: dict  # rasterize() info of the step (means2d with .grad/.absgrad, radii, depths)
    index: torch.Tensor | None  # table rows of the rendered Gaussians (None = all)
    camera: object  # Camera3 of the rendered crop
    crop: tuple[int, int, int, int]
    render: torch.Tensor  # (h, w, 3) rendered RGB, detached
    target: torch.Tensor  # (h, w, 3)
    mask: torch.Tensor | None  # (h, w) bool
    flow: object | None  # FlowPair of the frame (full image), or None
    frame: object  # StoredFrame
    u: float
    bones: object
    generator: torch.Generator
    trainer: object
    rendered_flow: torch.Tensor | None = None  # (h, w, 2) per-pixel Gaussian motion, detached


class DensifyStrategy:
    def __init__(self, config: DensifyConfig, total_iterations: int):
        self.config = config
        self.total = int(total_iterations)
        self.initial_part_counts: torch.Tensor | None = None
        self.counts: dict[str, int] = {}

    # --- state -----------------------------------------------------------------------------------
    def reset(self, model) -> None:
        n = model.table.num
        dev = model.device
        self.grad_sum = torch.zeros(n, device=dev)
        self.vis_count = torch.zeros(n, device=dev)
        self.steps_seen = 0
        self.flow_w = torch.zeros(n, device=dev)  # W_i, px per frame
        gate = model.table.motion_gate()
        self.was_dynamic = (
            torch.zeros(n, device=dev) if gate is None else gate.float()
        )  # at the last density step
        if self.initial_part_counts is None:
            self.initial_part_counts = self._part_counts(model)

    STATE = ("grad_sum", "vis_count", "flow_w", "was_dynamic")

    def state_arrays(self) -> dict[str, torch.Tensor]:
        return {name: getattr(self, name) for name in self.STATE}

    def load_state_arrays(self, arrays: dict[str, torch.Tensor], steps_seen: int) -> None:
        for name in self.STATE:
            if name in arrays:
                setattr(self, name, arrays[name])
        self.steps_seen = int(steps_seen)

    def _resize(self, keep: torch.Tensor | None = None, added: int = 0) -> None:
        for name in self.STATE:
            t = getattr(self, name)
            if keep is not None:
                t = t[keep]
            if added:
                t = torch.cat([t, t.new_zeros(added)])
            setattr(self, name, t)

    @staticmethod
    def _part_counts(model) -> torch.Tensor:
        parts = model.table["skin_weights"].argmax(dim=1)
        return torch.bincount(parts, minlength=24).float()

    # --- the hook --------------------------------------------------------------------------------
    def active(self, iteration: int) -> bool:
        c = self.config
        return c.enabled and c.start_iter <= iteration < int(c.stop_fraction * self.total)

    def step_post_backward(self, ctx: StepContext) -> dict[str, int]:
        c = self.config
        if not c.enabled:
            return {}
        self._accumulate(ctx)
        report: dict[str, int] = {}
        it = ctx.iteration
        if not self.active(it):
            return report
        if c.flow_guided and ctx.flow is not None and (it - c.start_iter) % c.flow_interval == 0:
            report["flow_added"] = self._flow_guided(ctx)
        if (it - c.start_iter) % c.interval == 0 and it > c.start_iter:
            report.update(self._adaptive_density(ctx))
        for k, v in report.items():
            self.counts[k] = self.counts.get(k, 0) + v
        return report

    @torch.no_grad()
    def _accumulate(self, ctx: StepContext) -> None:
        info = ctx.info
        radii = info["radii"]
        visible = (radii > 0).all(dim=-1) if radii.dim() == 2 else radii > 0
        rows = visible.nonzero().squeeze(1)
        table_rows = rows if ctx.index is None else ctx.index[rows]
        means2d = info["means2d"]
        grad = getattr(means2d, "absgrad", None)
        if grad is None:
            grad = means2d.grad
        if grad is None:
            return
        pixels = float(ctx.crop[2] * ctx.crop[3])
        self.grad_sum.index_add_(0, table_rows, grad[rows].norm(dim=-1) * pixels)
        self.vis_count.index_add_(0, table_rows, torch.ones_like(table_rows, dtype=self.vis_count.dtype))
        self.steps_seen += 1
        if ctx.flow is None:
            return
        x0, y0, w, h = ctx.crop
        xy = means2d.detach()[rows]
        px = xy[:, 0].round().long().clamp(0, w - 1)
        py = xy[:, 1].round().long().clamp(0, h - 1)
        fwd = torch.from_numpy(ctx.flow.forward[y0 : y0 + h, x0 : x0 + w]).to(xy.device)
        valid = torch.from_numpy(ctx.flow.valid_forward[y0 : y0 + h, x0 : x0 + w]).to(xy.device)
        ok = valid[py, px]
        mag = fwd[py, px].norm(dim=-1)
        sel = table_rows[ok]
        self.flow_w[sel] = W_DECAY * self.flow_w[sel] + (1 - W_DECAY) * mag[ok]

    # --- flow-guided densification ---------------------------------------------------------------
    @torch.no_grad()
    def _flow_guided(self, ctx: StepContext) -> int:
        c = self.config
        model = ctx.model
        room = self._room(model)
        if room <= 0:
            return 0
        x0, y0, w, h = ctx.crop
        err = (ctx.render - ctx.target).abs().mean(-1)  # (h, w)
        r = c.region_px
        tiles = F.avg_pool2d(err[None, None], r, r, ceil_mode=True)[0, 0]  # mean error per region
        info = ctx.info
        radii = info["radii"]
        visible = (radii > 0).all(dim=-1) if radii.dim() == 2 else radii > 0
        rows = visible.nonzero().squeeze(1)
        if rows.numel() == 0:
            return 0
        table_rows = rows if ctx.index is None else ctx.index[rows]
        xy = info["means2d"].detach()[rows]
        px = xy[:, 0].round().long()
        py = xy[:, 1].round().long()
        inside = (px >= 0) & (px < w) & (py >= 0) & (py < h)
        px, py, rows, table_rows = px[inside], py[inside], rows[inside], table_rows[inside]
        tile_err = tiles[py // r, px // r]
        delta = self.motion_threshold(ctx.trainer)
        seeds = (tile_err > c.error_threshold) & (self.flow_w[table_rows] > delta)
        if not bool(seeds.any()):
            return 0
        fwd = torch.from_numpy(ctx.flow.forward[y0 : y0 + h, x0 : x0 + w]).to(xy.device)
        valid = torch.from_numpy(ctx.flow.valid_forward[y0 : y0 + h, x0 : x0 + w]).to(xy.device)
        seeds &= valid[py, px]
        idx = seeds.nonzero().squeeze(1)
        if idx.numel() == 0:
            return 0
        # Strongest seeds first: error x motion.
        score = tile_err[idx] * self.flow_w[table_rows[idx]]
        idx = idx[score.argsort(descending=True)][: min(c.flow_max_new, room)]
        sx, sy, srow = px[idx], py[idx], table_rows[idx]
        observed = fwd[sy, sx]
        if ctx.rendered_flow is not None:
            residual = observed - ctx.rendered_flow[sy, sx]
        else:
            residual = observed
        depth = info["depths"].detach()[rows[idx]]
        K = ctx.camera.K
        # Lift the pixel residual to a camera-space displacement at the seed's depth, then to world.
        d_cam = torch.stack(
            [residual[:, 0] * depth / K[0, 0], residual[:, 1] * depth / K[1, 1], torch.zeros_like(depth)], 1
        )
        d_world = d_cam @ ctx.camera.viewmat[:3, :3]  # R^T d
        # Into the canonical frame of each seed: inverse of its blended rotation.
        weights = model.skin_weights()[srow]
        blended = blend(weights, ctx.bones)
        d_canon = rotate(conjugate(blend_rotation(weights, ctx.bones)), d_world)
        noise = torch.randn(d_canon.shape, generator=ctx.generator).to(d_canon.device)
        new_means = model.table["means"][srow] + c.flow_step * d_canon + c.flow_noise_m * noise
        # Temporal consistency with the flow: where the new centre projects, the observed flow must
        # be valid, on the person, and close to the seed's.
        posed_new = (blended[:, :3, :3] @ new_means[..., None]).squeeze(-1) + blended[:, :3, 3]
        p_new = ctx.camera.project(posed_new)
        nx, ny = p_new[:, 0].round().long(), p_new[:, 1].round().long()
        ok = (nx >= 0) & (nx < w) & (ny >= 0) & (ny < h)
        nxc, nyc = nx.clamp(0, w - 1), ny.clamp(0, h - 1)
        ok &= valid[nyc, nxc]
        if ctx.mask is not None:
            ok &= ctx.mask[nyc, nxc]
        ok &= (fwd[nyc, nxc] - observed).norm(dim=-1) <= c.flow_consistency_px
        keep = ok.nonzero().squeeze(1)
        self.counts["flow_rejected"] = self.counts.get("flow_rejected", 0) + int((~ok).sum())
        if keep.numel() == 0:
            return 0
        srow = srow[keep]
        rows_new = self._copy_rows(model, srow)
        rows_new["means"] = new_means[keep]
        rows_new["log_scales"] = rows_new["log_scales"] + torch.log(torch.tensor(0.8))
        rows_new["opacity_logits"] = torch.full_like(rows_new["opacity_logits"], -1.0)
        for name in ("motion", "rot_motion"):
            if name in rows_new:
                rows_new[name] = torch.zeros_like(rows_new[name])
        if "motion_gate" in rows_new:
            rows_new["motion_gate"] = torch.ones_like(rows_new["motion_gate"])  # non-rigid detail: may move
        if "t_center" in rows_new:
            rows_new["t_center"] = torch.full_like(rows_new["t_center"], ctx.u)
            rows_new["t_log_scale"] = torch.full_like(
                rows_new["t_log_scale"], float(torch.log(torch.tensor(c.new_time_scale)))
            )
        self._append(ctx, rows_new)
        return int(keep.numel())

    # --- clone / split / prune / re-sample -------------------------------------------------------
    @torch.no_grad()
    def _adaptive_density(self, ctx: StepContext) -> dict[str, int]:
        c = self.config
        model = ctx.model
        table = model.table
        report = {"cloned": 0, "split": 0, "pruned": 0, "resampled": 0}
        grads = self.grad_sum / self.vis_count.clamp_min(1)
        was_dynamic = self.was_dynamic > 0.5  # dynamic for a whole interval already
        report.update(self._gate_motion(ctx, grads))
        scales = table.scales().max(dim=1).values
        small = scales <= c.percent_dense * model.extent
        hot = (grads > c.grad_threshold) & (self.vis_count > 0)
        room = self._room(model)
        # Dynamic Gaussians on long temporal windows are refined in time first (they fail because
        # one polynomial cannot follow the motion), the rest in space as in 3DGS.
        tsplit_rows = self._temporal_split_rows(ctx, hot & was_dynamic, grads, room)
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
            self._append(ctx, self._copy_rows(model, clone))
            report["cloned"] = int(clone.numel())
        if split.numel():
            rows = self._copy_rows(model, split)
            rows2 = {k: v.clone() for k, v in rows.items()}
            std = table.scales()[split]
            rot = lbs.quaternion_to_matrix(table["quats"][split])
            for r in (rows, rows2):
                offset = torch.randn(std.shape, generator=ctx.generator).to(std.device) * std
                r["means"] = table["means"][split] + (rot @ offset[..., None]).squeeze(-1)
                r["log_scales"] = r["log_scales"] - torch.log(torch.tensor(1.6))
            both = {k: torch.cat([rows[k], rows2[k]]) for k in rows}
            self._append(ctx, both)
            report["split"] = int(split.numel())
        if tsplit_rows is not None:
            sources, rows = tsplit_rows
            self._append(ctx, rows)
            report["time_split"] = int(sources.numel())
            split = torch.cat([split, sources])
        # Prune (the split originals, plus what contributes nothing).
        n = model.table.num
        prune = torch.zeros(n, dtype=torch.bool, device=model.device)
        prune[split] = True
        opacity = model.table.opacities()
        seen = self.vis_count / max(self.steps_seen, 1)
        delta = self.motion_threshold(ctx.trainer)
        score = opacity * seen * (1.0 + c.motion_protect_gamma * self.flow_w / delta)
        old = torch.arange(n, device=model.device) < n_before  # new rows have no statistics yet
        prune |= old & (opacity < c.prune_opacity)
        prune |= old & (score < c.prune_score) & (self.steps_seen >= c.interval)
        prune |= model.table.scales().max(dim=1).values > c.prune_scale_m
        if bool(prune.all()):
            prune[opacity.argmax()] = False  # never prune the model away entirely
        if bool(prune.any()):
            ctx.optimizer.keep(~prune)
            self._resize(keep=~prune)
            report["pruned"] = int(prune.sum()) - int(split.numel())
        report["resampled"] = self._resample(ctx)
        self.grad_sum.zero_()
        self.vis_count.zero_()
        self.steps_seen = 0
        return report

    @torch.no_grad()
    def _temporal_split_rows(
        self, ctx: StepContext, candidates: torch.Tensor, grads: torch.Tensor, room: int
    ):
        """Copies on shorter temporal windows of the dynamic, still-pulled Gaussians (sources, rows).

        A Gaussian present at all times becomes up to ``temporal_split_max`` copies centred evenly over
        the training time range, a finite window becomes two copies at ``mu +- s/2``; the windows are
        0.6x their spacing, so neighbouring copies cross at about half opacity. Each copy keeps the
        source's other attributes (its polynomial then fits its own part of the motion).
        """
        c = self.config
        table = ctx.model.table
        gate = table.motion_gate()
        if not c.temporal_split or gate is None or "t_center" not in table or room <= 0:
            return None
        times = [ctx.model.time_axis(f.frame.time) for f in ctx.trainer.store.frames]
        lo, hi = min(times), max(times)
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
        rows = self._copy_rows(ctx.model, source)
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
    def _resample(self, ctx: StepContext) -> int:
        c = self.config
        model = ctx.model
        trainer = ctx.trainer
        if c.resample_fraction <= 0 or self.initial_part_counts is None:
            return 0
        counts = self._part_counts(model)
        low = (counts < c.resample_fraction * self.initial_part_counts).nonzero().squeeze(1)
        if low.numel() == 0:
            return 0
        vertices, faces = trainer.canonical_vertices, trainer.canonical_faces
        vertex_part = trainer.body.weights.argmax(dim=1)
        face_part = vertex_part[faces[:, 0]]
        added = 0
        for part in low.tolist():
            want = int(c.resample_fraction * self.initial_part_counts[part] - counts[part])
            want = min(want, self._room(model))
            sel = (face_part == part).nonzero().squeeze(1)
            if want <= 0 or sel.numel() == 0:
                continue
            # Random draws on the CPU (the step's generator lives there), whatever the model's device.
            points, face, bary = sample_surface(vertices.cpu(), faces[sel].cpu(), want, ctx.generator)
            weights = surface_skin_weights(
                faces[sel].cpu(), trainer.body.weights.cpu(), face, bary, model.config.skin_init
            )
            scale = (
                float(model.table.scales()[model.table["skin_weights"].argmax(1) == part].mean())
                if (counts[part] > 0)
                else 0.01
            )
            rows = new_columns(model.config, points, weights, scale, t_center=ctx.u, generator=ctx.generator)
            self._append(ctx, {k: v.to(model.device) for k, v in rows.items()})
            added += want
        return added

    @torch.no_grad()
    def _gate_motion(self, ctx: StepContext, grads: torch.Tensor) -> dict[str, int]:
        """Decide which Gaussians may move, so motion terms exist only where the scene needs them.

        A static Gaussian becomes dynamic when it sits on sustained motion (``W_i > delta``) and the
        image still pulls on it (mean screen gradient above half the clone threshold): the rigid part
        does not explain it. A dynamic one whose motion terms stayed below ``motion_min_m``
        (metres at |tau| = 1) since the last density step goes back to static: its terms and their
        Adam moments become exact zeros.
        """
        table = ctx.model.table
        gate = table.motion_gate()
        if gate is None:
            return {}
        # On sustained motion and still badly explained by the rigid part. (Opening the gate on any
        # motion above the 1 px floor fits the training view's cloth better, +6 dB in the garment
        # region of the dance benchmark, but novel views got worse: from one camera the extra freedom
        # is spent on placements other views disagree with. docs/AVATAR.md.)
        moving = self.flow_w > self.motion_threshold(ctx.trainer)
        activate = ~gate & moving & (grads > 0.5 * self.config.grad_threshold)
        amplitude = torch.zeros(table.num, device=gate.device)
        if "motion" in table:
            amplitude = amplitude + table["motion"].norm(dim=-1).sum(dim=1)
        if "rot_motion" in table:
            amplitude = amplitude + 0.1 * table["rot_motion"].norm(dim=-1).sum(dim=1)  # ~0.1 m per radian
        settle = gate & (self.was_dynamic > 0.5) & (amplitude < self.config.motion_min_m)
        for name in ("motion", "rot_motion"):
            if name in table:
                ctx.optimizer.zero_rows(name, settle)
        table["motion_gate"].data[activate] = 1.0
        table["motion_gate"].data[settle] = 0.0
        self.was_dynamic = table["motion_gate"].detach().clone()
        return {"motion_on": int(activate.sum()), "motion_off": int(settle.sum())}

    def motion_threshold(self, trainer) -> float:
        """delta (px per frame): see DensifyConfig.motion_floor_px / motion_relative."""
        c = self.config
        mags = [f.flow_magnitude for f in trainer.store.frames if f.flow is not None]
        median = float(sorted(mags)[len(mags) // 2]) if mags else 0.0
        return max(c.motion_floor_px, c.motion_relative * median)

    # --- helpers ---------------------------------------------------------------------------------
    def _room(self, model) -> int:
        return max(model.config.max_gaussians - model.table.num, 0)

    @staticmethod
    def _copy_rows(model, rows: torch.Tensor) -> dict[str, torch.Tensor]:
        return {name: model.table[name].detach()[rows].clone() for name in model.table.names()}

    def _append(self, ctx: StepContext, rows: dict[str, torch.Tensor]) -> None:
        n = next(iter(rows.values())).shape[0]
        ctx.optimizer.append(rows)
        self._resize(added=n)
