"""The STG-Avatar trainer as a library object: add frames, step, snapshot, save, load.

``stg-train`` and the online trainer node drive this very class: the command adds a dataset's
frames then steps a fixed number of times; the node adds frames as they arrive (bounded store)
and steps in between. One step renders one training view (the crop around the person), takes
the loss of :mod:`losses`, and lets the densification strategy (:mod:`densify`, gsplat-style
hooks) grow and prune the table. A step whose loss or gradients are not finite is skipped,
logged, and never written into the model.

Determinism: every random choice of step k comes from a generator seeded by (seed, k), so a run
resumed from a checkpoint at step k continues exactly as the uninterrupted run would (same
backend and thread count).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from stg_node.avatar import losses as L
from stg_node.avatar import spacetime
from stg_node.avatar.config import TrainConfig
from stg_node.avatar.densify import DensifyStrategy, StepContext
from stg_node.avatar.exposure import ExposureCorrection
from stg_node.avatar.frames import FrameStore, StoredFrame, TrainFrame
from stg_node.avatar.gaussians import init_table, scale_ratio_percentile
from stg_node.avatar.isometry import IsometryGraph
from stg_node.avatar.model import AvatarModel, BodyState, Camera3, render
from stg_node.avatar.optim import TableOptimizer
from stg_node.avatar.pose_refine import PoseTrack
from stg_node.avatar.rigid import Skeleton
from stg_node.avatar.rigidity import NeighbourGraph
from stg_node.avatar.spacetime import TimeAxis
from stg_node.body.canonical import big_pose_output

log = logging.getLogger(__name__)

_SEED_MIX = 0x9E3779B97F4A7C15
PHASES = ("data", "pose", "flow_target", "render", "loss", "backward", "update", "densify")


class StepProfile:
    """Wall time of each phase of a step, summed over steps (``Trainer.profile = StepProfile()``).

    ``clock=time.thread_time`` counts this thread's CPU time instead: on a machine shared with
    other processes, what the step itself costs."""

    def __init__(self, clock=time.perf_counter):
        self.seconds = dict.fromkeys(PHASES, 0.0)
        self.steps = 0
        self.clock = clock
        self._last = 0.0

    def start(self) -> None:
        self._last = self.clock()

    def mark(self, phase: str) -> None:
        now = self.clock()
        self.seconds[phase] += now - self._last
        self._last = now

    def per_step_ms(self) -> dict[str, float]:
        return {k: 1e3 * v / max(self.steps, 1) for k, v in self.seconds.items()}


class _NoProfile:
    def start(self) -> None:
        pass

    def mark(self, phase: str) -> None:
        pass


@dataclass
class StepResult:
    """What one call to :meth:`Trainer.step` did."""

    iteration: int  # the iteration count after this step
    loss: float  # total loss (NaN if the step was skipped for non-finite values)
    losses: dict[str, float] = field(default_factory=dict)
    psnr: float = float("nan")  # of the rendered crop against the training image
    num_gaussians: int = 0
    it_per_s: float = 0.0
    elapsed_s: float = 0.0  # training time so far (steps only)
    skipped: bool = False
    frame: int = -1
    weights: dict[str, float] = field(default_factory=dict)
    densify: dict[str, int] = field(default_factory=dict)


def step_generator(seed: int, iteration: int, device="cpu") -> torch.Generator:
    """The generator of step ``iteration``: a pure function of (seed, iteration)."""
    mixed = (int(seed) * _SEED_MIX + int(iteration) * 0xBF58476D1CE4E5B9 + 1) % (1 << 63)
    gen = torch.Generator(device=device)
    gen.manual_seed(mixed)
    return gen


class Trainer:
    """Train an STG-Avatar from frames (see module docstring)."""

    def __init__(
        self,
        config: TrainConfig,
        body_model=None,
        *,
        device: str | torch.device = "cpu",
        backend: str = "auto",
        seed: int = 0,
        flow_cache=None,
    ):
        config.validate()
        self.config = config
        self.device = torch.device(device)
        self.backend = backend
        self.seed = int(seed)
        self.body = _load_body(body_model, self.device)
        self.body_reference = _body_reference(body_model)
        want_flow = config.loss.flow > 0 or (config.densify.enabled and config.densify.flow_guided)
        self.store = FrameStore(
            capacity=config.max_frames,  # its one home: a checkpoint keeps it with the config
            crop_margin=config.crop_margin_px,
            flow=want_flow and config.model.spacetime or config.loss.flow > 0,
            flow_cache=flow_cache,
            seed=seed,
        )
        self.model: AvatarModel | None = None
        self.optimizer: TableOptimizer | None = None
        self.densifier = DensifyStrategy(config.densify, config.iterations)
        self.weights = L.AdaptiveWeights(config.loss)
        self.iteration = 0
        self.train_seconds = 0.0
        self.skipped_steps = 0
        self.model_version = 0
        self.pose_deltas: torch.nn.Parameter | None = (
            None  # (slots, 75) per-frame pose (72) and Th (3) correction
        )
        self.pose_slots: dict[int, int] = {}
        self.pose_track = PoseTrack()  # the tracked poses, for the refined poses' smoothness
        self.exposure = ExposureCorrection(  # per-frame colour correction, training only
            config.lr_exposure, config.loss.exposure, config.loss.warmup_iters, self.device
        )
        self.neighbours = NeighbourGraph()  # local rigidity of the non-rigid motion
        self.isometry = IsometryGraph()  # canonical neighbours keep their distances when posed
        self.profile: StepProfile | None = None  # set to a StepProfile to time the phases of each step
        #: Numbers the caller keeps with the checkpoint, written and restored in the same file (the
        #: trainer node's wall time): nothing beside a checkpoint can disagree with it after a kill.
        self.notes: dict[str, float] = {}

    # --- frames ----------------------------------------------------------------------------------
    def add_frame(self, frame: TrainFrame) -> None:
        """Add one training view (the first one also initialises the model from its body shape)."""
        stored = self.store.add(frame)
        if self.model is None:
            self._initialize(stored.frame)
        u = self.model.time_axis(frame.time)
        index = self.model.pose_index
        if not np.any(np.isclose(index.times, u, atol=1e-6)):  # a frame not seen before (resume: seen)
            index.add(np.asarray(frame.smpl.poses), u)
            if self.model.shading is not None:  # the mean training orientation (the baked light mode)
                self.model.shading.add_orientation(_root_rotation(frame.smpl))
        if self.config.lr_pose > 0:
            self._pose_slot(frame.index)
            if self.config.loss.pose_smooth > 0:
                self.pose_track.add(frame.index, frame.smpl, self.device)
        if self.exposure.enabled:
            self.exposure.add(frame.index)

    def add_frames(self, frames) -> None:
        for frame in frames:
            self.add_frame(frame if isinstance(frame, TrainFrame) else TrainFrame.from_sample(frame))

    # --- model -----------------------------------------------------------------------------------
    def _initialize(self, frame: TrainFrame) -> None:
        cfg = self.config.model
        betas = torch.as_tensor(np.array(frame.smpl.betas, np.float32), device=self.device)[None]
        with torch.no_grad():
            vertices = big_pose_output(self.body, betas).vertices[0]
        skeleton = Skeleton.from_body(self.body, betas)
        gen = step_generator(self.seed, -1)
        table = init_table(cfg, vertices.cpu(), self.body.faces.cpu(), self.body.weights.cpu(), gen)
        pad = 0.05
        bounds = torch.stack([vertices.min(0).values - pad, vertices.max(0).values + pad])
        axis = TimeAxis(origin_s=float(frame.time), unit_s=cfg.time_unit_s)
        # nn.Linear draws its initial weights from torch's global generator: seed it for this run
        # (without touching the caller's random state) so the same seed gives the same model.
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(int(torch.randint(1 << 62, (1,), generator=gen)))
            model = AvatarModel(cfg, table, skeleton, bounds, axis)
        self.attach_model(model, betas)
        self._build_optimizer()
        self.densifier.reset(self.model)
        log.info(
            "initialised %d Gaussians on %s (%s colour, n_p=%d, n_q=%d%s)",
            table.num,
            self.body.name,
            cfg.color,
            cfg.n_p,
            cfg.n_q,
            ", temporal opacity" if cfg.uses_temporal_opacity else "",
        )

    def attach_model(self, model: AvatarModel, betas: torch.Tensor) -> None:
        """Use ``model`` (fresh, or rebuilt from a checkpoint) for the subject with shape ``betas``."""
        self.model = model.to(self.device)
        self.betas = betas.to(self.device)
        with torch.no_grad():
            self.canonical_vertices = big_pose_output(self.body, self.betas).vertices[0]
        self.canonical_faces = self.body.faces

    def _build_optimizer(self) -> None:
        c = self.config
        extent = self.model.extent
        lrs = {
            "means": c.lr_means * extent,
            "log_scales": c.lr_scales,
            "quats": c.lr_quats,
            "opacity_logits": c.lr_opacity,
            "sh": c.lr_color,
            "features": c.lr_color,
            "skin_delta": c.lr_skin,
            "motion": c.lr_motion,
            "rot_motion": c.lr_rot_motion,
            "t_center": c.lr_time,
            "t_log_scale": c.lr_time,
        }
        dense = {}
        if self.model.color_mlp is not None:
            dense["mlp"] = (list(self.model.color_mlp.parameters()), c.lr_mlp)
        if self.pose_deltas is not None:
            dense["pose"] = ([self.pose_deltas], c.lr_pose)
        if self.model.shading is not None:
            dense["light"] = (list(self.model.shading.light.parameters()), c.lr_light)
        self.optimizer = TableOptimizer(self.model.table, lrs, dense)

    def _pose_slot(self, frame_index: int) -> int:
        if frame_index in self.pose_slots:
            return self.pose_slots[frame_index]
        slot = len(self.pose_slots)
        self.pose_slots[frame_index] = slot
        grow = self.pose_deltas is None or slot >= self.pose_deltas.shape[0]
        if grow:
            old = None if self.pose_deltas is None else self.pose_deltas.detach()
            size = 64 if old is None else old.shape[0] * 2
            new = torch.zeros(size, 75, device=self.device)
            if old is not None:
                new[: old.shape[0]] = old
            self.pose_deltas = torch.nn.Parameter(new)
            if self.optimizer is not None:
                self._rebuild_dense()
        return slot

    def _rebuild_dense(self) -> None:
        table_state = self.optimizer.table_state()
        self._build_optimizer()
        self.optimizer.load_table_state(table_state)

    def body_state(self, stored_frame: TrainFrame, smpl=None, refine: bool = True) -> BodyState:
        """Tensors of a frame's SMPL parameters, with its learned pose correction when there is one."""
        body = BodyState.from_smpl(smpl if smpl is not None else stored_frame.smpl, self.device)
        if refine and self.pose_deltas is not None and smpl is None and stored_frame.index in self.pose_slots:
            delta = self.pose_deltas[self.pose_slots[stored_frame.index]]
            if not self.config.pose_refine_joints:  # the frame's alignment only: root rotation, Th
                delta = torch.cat([delta[:3], torch.zeros_like(delta[3:72]), delta[72:75]])
            body = BodyState(
                body.poses + delta[: 24 * 3].reshape(1, 24, 3), body.Rh, body.Th + delta[72:75][None]
            )
        return body

    # --- one step --------------------------------------------------------------------------------
    def step(self) -> StepResult:
        if self.model is None or len(self.store) == 0:
            raise RuntimeError("Trainer.step() needs at least one frame: call add_frame() first")
        started = time.perf_counter()
        timer = self.profile or _NoProfile()
        timer.start()
        c = self.config
        it = self.iteration
        gen = step_generator(self.seed, it)
        stored = self.store.frames[int(torch.randint(len(self.store), (1,), generator=gen))]
        progress = it / max(c.iterations, 1)
        self.optimizer.set_schedule(progress, 0.01, c.lr_schedule_final)
        sh_degree = min(c.model.sh_degree, it // max(c.sh_increase_every, 1))

        full = c.full_frame_every > 0 and it % c.full_frame_every == 0
        crop = None if full else stored.crop
        camera = Camera3.from_camera(stored.frame.camera, crop, self.device)
        x0, y0, w, h = crop or (0, 0, camera.width, camera.height)
        target = torch.from_numpy(stored.image[y0 : y0 + h, x0 : x0 + w]).to(self.device).float() / 255.0
        mask = None
        if stored.frame.mask is not None:
            m = stored.frame.mask[y0 : y0 + h, x0 : x0 + w]
            mask = torch.from_numpy(m > 127).to(self.device)

        body = self.body_state(stored.frame)
        u = self.model.time_axis(stored.frame.time)
        bones, key = self._frame_bones(stored, body, "now")
        timer.mark("data")
        state = self.model.spacetime(u)
        posed = self.model.pose(
            body, u, camera.center, sh_degree=sh_degree, bones=bones, key=key, state=state, camera=camera
        )
        timer.mark("pose")

        terms: dict[str, torch.Tensor] = {}
        extra = None
        flow_pair = stored.flow if stored.next_smpl is not None else None
        use_flow = flow_pair is not None and c.loss.flow > 0
        table = self.model.table
        want_temporal = c.loss.temporal > 0 and "t_center" in table and stored.next_time is not None
        next_state = None  # the next frame's spacetime terms: one evaluation for the flow and temporal terms
        if use_flow or want_temporal:
            next_state = self.model.spacetime(self.model.time_axis(stored.next_time))
        if use_flow:
            u_next = self.model.time_axis(stored.next_time)
            next_body = self.body_state(stored.frame, smpl=stored.next_smpl)
            means_next = self.model.posed_means(
                self._frame_bones(stored, next_body, "next")[0], u_next, state=next_state
            )
            if posed.index is not None:
                means_next = means_next[posed.index]
            extra = camera.project(means_next) - camera.project(posed.means)
        timer.mark("flow_target")

        image, alpha, info = render(posed, camera, background=0.0, backend=self.backend, extra_channels=extra)
        timer.mark("render")
        rgb = self.exposure.apply(image[..., :3], stored.frame.index, it)
        l1, dssim = L.photometric(rgb, target, c.loss.ssim)
        terms["photo"] = (1 - c.loss.ssim) * l1 + c.loss.ssim * dssim
        if mask is not None and c.loss.mask > 0:
            terms["mask"] = (alpha[..., 0] - mask.float()).abs().mean()
        if use_flow:
            fwd = torch.from_numpy(flow_pair.forward[y0 : y0 + h, x0 : x0 + w]).to(self.device)
            valid = torch.from_numpy(flow_pair.valid_forward[y0 : y0 + h, x0 : x0 + w]).to(self.device)
            terms["flow"] = L.flow_loss(image[..., 3:5], alpha, fwd, valid)
        if want_temporal:
            terms["temporal"] = self._temporal_term(state, next_state)
        if c.loss.rigidity > 0 and state.offsets is not None:
            terms["rigidity"] = self.neighbours.loss(table, state.offsets, state.temporal)
        if c.loss.isometry > 0:
            terms["isometry"] = self.isometry.loss(table, posed.means, posed.canonical, posed.index)
        terms.update(self._regularisers(body))
        if c.loss.pose_smooth > 0 and self.pose_deltas is not None:
            smooth = self.pose_track.smoothness(self.pose_deltas, self.pose_slots, stored.frame.index)
            if smooth is not None:
                terms["pose_smooth"] = smooth
        gauge = self.exposure.penalty()
        if gauge is not None:
            terms["exposure"] = gauge
        weights = {
            "mask": c.loss.mask,
            "flow": c.loss.flow,
            "temporal": c.loss.temporal,
            "rigidity": c.loss.rigidity,
            "motion_smooth": c.loss.motion_smooth,
            "scale": c.loss.scale,
            "opacity": c.loss.opacity,
            "skin": c.loss.skin,
            "pose": c.loss.pose_refine,
            "isometry": c.loss.isometry,
            "light": c.loss.light,
            "pose_smooth": c.loss.pose_smooth,
            "exposure": c.loss.exposure,
        }
        total, applied = self.weights.combine(terms, weights, it)
        timer.mark("loss")

        self.optimizer.zero_grad()
        skipped = not bool(torch.isfinite(total))
        if not skipped:
            total.backward()
            skipped = not self._grads_finite()
        timer.mark("backward")
        report: dict[str, int] = {}
        if skipped:
            self.skipped_steps += 1
            log.warning(
                "step %d: non-finite loss or gradients (frame %d); step skipped", it, stored.frame.index
            )
            self.optimizer.zero_grad()
            self.exposure.discard()
        else:
            gate = self.model.table.motion_gate()
            if gate is not None:  # static Gaussians keep exactly zero motion terms
                for name in ("motion", "rot_motion"):
                    self.optimizer.freeze_rows(name, ~gate)
            self.optimizer.step()
            self.exposure.step()
            self.optimizer.soft_threshold("motion", c.loss.motion_sparsity)
            self.optimizer.soft_threshold("rot_motion", c.loss.motion_sparsity)
            timer.mark("update")
            ctx = StepContext(
                iteration=it,
                model=self.model,
                optimizer=self.optimizer,
                info=info,
                index=posed.index,
                camera=camera,
                crop=(x0, y0, w, h),
                render=rgb.detach(),
                target=target,
                mask=mask,
                flow=flow_pair,
                frame=stored,
                u=u,
                bones=bones,
                generator=gen,
                trainer=self,
                rendered_flow=(image[..., 3:5] / alpha.clamp_min(0.5)).detach() if use_flow else None,
            )
            report = self.densifier.step_post_backward(ctx)
            timer.mark("densify")
        if self.profile is not None:
            self.profile.steps += 1
        self.iteration += 1
        elapsed = time.perf_counter() - started
        self.train_seconds += elapsed
        with torch.no_grad():
            mse = float(((rgb.detach() - target) ** 2).mean())
        return StepResult(
            iteration=self.iteration,
            loss=float("nan") if skipped else float(total.detach()),
            losses={k: float(v.detach()) for k, v in terms.items()} | {"l1": float(l1.detach())},
            psnr=-10.0 * math.log10(max(mse, 1e-12)),
            num_gaussians=self.model.table.num,
            it_per_s=1.0 / max(elapsed, 1e-9),
            elapsed_s=self.train_seconds,
            skipped=skipped,
            frame=stored.frame.index,
            weights=applied,
            densify=report,
        )

    def _frame_bones(self, stored: StoredFrame, body: BodyState, which: str):
        """A frame's bones and pose code; cached on the frame unless its pose is being refined."""
        if body.poses.requires_grad:
            return self.model.bones(body), None
        cache = stored.extras.get(which)
        if cache is None:
            from stg_node.avatar.timecode import pose_key

            with torch.no_grad():
                bones = self.model.bones(body).detach()
            key = torch.as_tensor(pose_key(body.poses.cpu().numpy()), device=self.device)
            cache = stored.extras[which] = (bones, key)
        return cache

    def _temporal_term(self, now: spacetime.SpacetimeState, nxt: spacetime.SpacetimeState) -> torch.Tensor:
        table = self.model.table
        out = table["means"].new_zeros(())
        if now.offsets is not None:
            out = out + 100.0 * (nxt.offsets - now.offsets).abs().sum(1).mean()
        if now.temporal is not None:
            out = out + (nxt.temporal - now.temporal).abs().mean()
        return out

    def _regularisers(self, body: BodyState) -> dict[str, torch.Tensor]:
        c = self.config.loss
        table = self.model.table
        out = {}
        motion = table.get("motion")
        if motion is not None and motion.shape[1] > 1:
            order = torch.arange(1, motion.shape[1] + 1, device=motion.device, dtype=motion.dtype)
            out["motion_smooth"] = (motion.abs().sum(-1) * (order - 1)).sum(1).mean()
        if c.scale > 0:
            out["scale"] = torch.relu(table.scales().max(dim=1).values - c.scale_max_m).mean() * 100.0
        if c.opacity > 0:
            o = table.opacities()
            out["opacity"] = (-(o * (o + 1e-6).log() + (1 - o) * (1 - o + 1e-6).log())).mean()
        if "skin_delta" in table and c.skin > 0:
            out["skin"] = table["skin_delta"].pow(2).mean()
        if self.pose_deltas is not None and c.pose_refine > 0:
            out["pose"] = self.pose_deltas.pow(2).sum(1).mean()
        if self.model.shading is not None and c.light > 0:
            out["light"] = self.model.shading.penalty()
        return out

    def _grads_finite(self) -> bool:
        for group in self.optimizer.groups():
            for p in group["params"]:
                if p.grad is not None and not bool(torch.isfinite(p.grad).all()):
                    return False
        return True

    # --- snapshots and checkpoints ----------------------------------------------------------------
    def snapshot(self):
        """The current model as a GaussianSnapshot (what the trainer node publishes); bumps model_version."""
        from stg_node.avatar.snapshot import to_snapshot

        if self.model is None:
            raise RuntimeError("no model yet: add a frame first")
        self.model_version += 1
        return to_snapshot(self.model, iteration=self.iteration, model_version=self.model_version)

    def save(self, path: str | Path) -> Path:
        """Checkpoint everything needed to resume exactly (one GaussianSnapshot file, atomic)."""
        from stg_node.avatar import checkpoint

        return checkpoint.save(self, path)

    @classmethod
    def load(
        cls, path: str | Path, *, body_model=None, device="cpu", backend="auto", flow_cache=None
    ) -> Trainer:
        """Resume from a checkpoint written by :meth:`save`; frames must be added again."""
        from stg_node.avatar import checkpoint

        return checkpoint.load(
            path, body_model=body_model, device=device, backend=backend, flow_cache=flow_cache
        )

    # --- reporting -------------------------------------------------------------------------------
    def stats(self) -> dict:
        """Gaussian count, fraction with active motion terms, model size."""
        if self.model is None:
            return {"gaussians": 0, "active_motion_fraction": 0.0, "model_mb": 0.0}
        from stg_node.avatar.snapshot import model_nbytes

        table = self.model.table
        n = table.num
        active = float(table.motion_active().float().mean()) if n and ("motion" in table) else 0.0
        return {
            "gaussians": n,
            "active_motion_fraction": active,
            "model_mb": model_nbytes(self.model) / 1e6,
            # largest / smallest axis of the Gaussians as rendered (skinning turns them, never stretches)
            "scale_ratio_p99": scale_ratio_percentile(self.model.scales().detach()),
        }


def _root_rotation(smpl) -> torch.Tensor:
    """(3, 3) a frame's body orientation in the world: ``R(Rh) @ R(poses[0])``."""
    from stg_node.body import lbs

    poses = torch.as_tensor(np.array(smpl.poses, np.float32)).reshape(24, 3)
    Rh = torch.as_tensor(np.array(smpl.Rh, np.float32)).reshape(3)
    return lbs.axis_angle_to_matrix(Rh) @ lbs.axis_angle_to_matrix(poses[0])


def _load_body(body_model, device):
    from stg_node.body import BodyModel, load_body_model

    if isinstance(body_model, BodyModel):
        return body_model.to(device)
    return load_body_model(body_model, device=device)


def _body_reference(body_model) -> str:
    """What a checkpoint records to find the body again: a path, or 'open'."""
    from stg_node.body import BodyModel

    if body_model is None:
        return "open"
    if isinstance(body_model, BodyModel):
        return "open" if body_model.name == "open_body" else body_model.name
    return str(body_model)


def default_run_files(run_dir: str | Path) -> dict[str, Path]:
    run = Path(run_dir)
    return {
        "checkpoint": run / "checkpoint.stgsnap",
        "config": run / "config.json",
        "log": run / "train_log.jsonl",
        "summary": run / "summary.json",
    }
