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

import dataclasses
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from stg_node.avatar import checkpoint, nonrigid, normal_trial, spacetime
from stg_node.avatar import losses as L
from stg_node.avatar.color_cache import TrainingColorTurns
from stg_node.avatar.config import LBS_ONLY, TrainConfig
from stg_node.avatar.densify import (
    CanonicalSurface,
    DensifyInputs,
    DensifyStrategy,
    counts,
    motion_threshold,
    surface_depth,
)
from stg_node.avatar.exposure import ExposureCorrection
from stg_node.avatar.frames import FrameStore, StoredFrame, TrainFrame
from stg_node.avatar.gaussians import MOTION_COLUMNS, init_table, scale_ratio_percentile
from stg_node.avatar.isometry import IsometryGraph
from stg_node.avatar.model import AvatarModel, BodyState, Camera3, render
from stg_node.avatar.motion_priors import line_of_sight, world_offsets
from stg_node.avatar.optim import TableOptimizer, all_finite
from stg_node.avatar.pose_refine import PoseTrack, hold_unseen_rows, pose_warmup_factor, touched_slots
from stg_node.avatar.rigid import Skeleton, skin
from stg_node.avatar.rigidity import NeighbourGraph
from stg_node.avatar.scale_ops import largest_scale
from stg_node.avatar.spacetime import TimeAxis
from stg_node.avatar.stream_window import forget_unheld_frames, window_to_frames
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
        flow_settings=None,
    ):
        """``flow_settings`` (stg_node.data.flow.FlowSettings): how the flow of new frame pairs is
        computed where no ``flow_cache`` answers (a live trainer trades its accuracy for time)."""
        config.validate()
        if config.nonrigid == "off":
            config = config.replace(**LBS_ONLY)
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
            flow_settings=flow_settings,
            seed=seed,
        )
        self.model: AvatarModel | None = None
        self.optimizer: TableOptimizer | None = None
        self.densifier = DensifyStrategy(config.densify, config.iterations)
        self.densify_state: dict[str, torch.Tensor] = {}  # the strategy's state (ours, checkpointed)
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
            config.lr_exposure, config.exposure_start, self.device
        )
        self.neighbours = NeighbourGraph()  # local rigidity of the non-rigid motion
        self.isometry = IsometryGraph()  # canonical neighbours keep their distances when posed
        # the colour MLP in turns: a CPU economy (on a GPU the network costs little: every row)
        turns = config.color_every if self.device.type == "cpu" else 1
        self.color_turns = TrainingColorTurns(turns) if turns > 1 else None
        self.profile: StepProfile | None = None  # set to a StepProfile to time the phases of each step
        self.decision: nonrigid.Decision | None = None  # what "auto" chose for the non-rigid part
        # Training camera name -> its column in the per-camera motion statistics (order of first
        # arrival; checkpointed, so a resumed rig keeps each camera's column whatever order it
        # reconnects in).
        self.camera_slots: dict[str, int] = {}
        #: Numbers the caller keeps with the checkpoint, written and restored in the same file (the
        #: trainer node's wall time): nothing beside a checkpoint can disagree with it after a kill.
        self.notes: dict[str, float] = {}

    # --- frames ----------------------------------------------------------------------------------
    def add_frame(self, frame: TrainFrame) -> None:
        """Add one training view (the first one also initialises the model from its body shape)."""
        stored = self.store.add(frame)
        self.camera_slots.setdefault(frame.camera.name, len(self.camera_slots))
        if len(self.camera_slots) > 1 and self.color_turns is not None:
            self._end_color_turns()
        if self.model is None:
            self._initialize(stored.frame)
        u = self.model.time_axis(frame.time)
        self._cover_time(u)
        index = self.model.pose_index
        if not np.any(np.isclose(index.times, u, atol=1e-6)):  # a frame not seen before (resume: seen)
            index.add(np.asarray(frame.smpl.poses), u)
            if self.model.shading is not None:  # the mean training orientation (the baked light mode)
                self.model.shading.add_orientation(_root_rotation(frame.smpl))
        if self.model.shading is not None:  # the normals this view faces (every frame: idempotent)
            self.model.shading.add_view(_towards_camera(frame))
        if self.config.lr_pose > 0:
            self._pose_slot(frame.index)
            if self.config.loss.pose_smooth > 0:
                self.pose_track.add(frame.index, frame.smpl, self.device)
        if self.exposure.enabled:
            self.exposure.add(frame.index)
        if self.store.capacity > 0:  # a stream: keep only what the held frames need (stream_window.py)
            window_to_frames(self.model, self.optimizer, self.store, self.config.time_noise_frames)
            forget_unheld_frames(self.store, self.exposure, self.pose_track)

    def _end_color_turns(self) -> None:
        """The colour MLP on every row from a second camera on: a carried colour is another
        instant's and, in a rig, mostly another camera's view of a view-dependent colour (issue
        25's 4-camera study at 512 px: the non-rigid part's gain over LBS only fell from +0.93 to
        +0.43 dB with turns of 3). The features' rate drops back to ``lr_color``."""
        self.color_turns = None
        if self.optimizer is not None:
            self.optimizer.base_lrs["features"] = self.config.lr_color

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
        if model.shading is not None and model.shading.occlusion is not None:
            model.shading.occlusion.fit(vertices.cpu(), self.body.weights.cpu(), skeleton.parent_list)
        self.attach_model(model, betas)
        self._build_optimizer()
        self.densify_state = self.densifier.initialize_state(self.model)
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
        self.surface = CanonicalSurface(self.canonical_vertices, self.canonical_faces, self.body.weights)

    def _build_optimizer(self) -> None:
        c = self.config
        extent = self.model.extent
        lrs = {
            "means": c.lr_means * extent,
            "log_scales": c.lr_scales,
            "quats": c.lr_quats,
            "opacity_logits": c.lr_opacity,
            "sh": c.lr_color,
            # in turns a row's features take a step's gradient on 1 step in k: with Adam they would
            # move ~1/sqrt(k) as far, so their rate is x sqrt(k) (color_cache.TrainingColorTurns)
            "features": c.lr_color * math.sqrt(1 if self.color_turns is None else self.color_turns.every),
            "skin_delta": c.lr_skin,
            "motion": c.lr_motion,
            "motion_coef": c.lr_motion_coef,
            "rot_motion": c.lr_rot_motion,
            "t_center": c.lr_time,
            "t_log_scale": c.lr_time,
        }
        dense = {}
        if self.model.color_mlp is not None:
            dense["mlp"] = (list(self.model.color_mlp.parameters()), c.lr_mlp)
        if self.model.motion_bases is not None:
            dense["bases"] = ([self.model.motion_bases.values], c.lr_motion)
        if self.pose_deltas is not None:
            dense["pose"] = ([self.pose_deltas], c.lr_pose)
        if self.model.shading is not None:
            dense["light"] = (list(self.model.shading.light.parameters()), c.lr_light)
            if self.model.shading.occlusion is not None:  # its strength learns with the light
                dense["light"][0].extend(self.model.shading.occlusion.parameters())
        self.optimizer = TableOptimizer(self.model.table, lrs, dense)

    def _cover_time(self, u: float) -> None:
        """Grow the shared motion bases' knots to reach time ``u`` (a stream's new frames)."""
        bases = self.model.motion_bases
        grown = None if bases is None else bases.grown(u)
        if grown is None:
            return
        old = bases.install(grown, bases.grown_ids(grown.shape[1]))
        if self.optimizer is not None:
            self.optimizer.replace_dense(old, bases.values)

    def _pose_slot(self, frame_index: int) -> int:
        if frame_index in self.pose_slots:
            return self.pose_slots[frame_index]
        if (
            self.store.capacity > 0
            and self.pose_deltas is not None
            and len(self.pose_slots) >= len(self.pose_deltas)
        ):
            self._compact_pose_slots()  # a stream: reuse the slots of frames no longer held
        slot = len(self.pose_slots)
        self.pose_slots[frame_index] = slot
        grow = self.pose_deltas is None or slot >= self.pose_deltas.shape[0]
        if grow:
            old = self.pose_deltas
            size = 64 if old is None else old.shape[0] * 2
            new = torch.zeros(size, 75, device=self.device)
            if old is not None:
                new[: old.shape[0]] = old.detach()
            self.pose_deltas = torch.nn.Parameter(new)
            if self.optimizer is not None and old is not None:
                self.optimizer.replace_dense(old, self.pose_deltas)  # every other moment stays
            elif self.optimizer is not None:
                self._rebuild_dense()
        return slot

    def _compact_pose_slots(self) -> None:
        """Keep the pose corrections (and their Adam moments) of the frames the store still holds,
        in the first slots: a bounded trainer's corrections stay as many as its frames."""
        held = {stored.frame.index for stored in self.store.frames}
        kept = sorted((slot, f) for f, slot in self.pose_slots.items() if f in held)
        index = torch.tensor([slot for slot, _ in kept], dtype=torch.long, device=self.device)
        old = self.pose_deltas
        new = torch.zeros_like(old.detach())
        new[: len(kept)] = old.detach()[index]
        self.pose_deltas = torch.nn.Parameter(new)
        self.pose_slots = {f: i for i, (_, f) in enumerate(kept)}
        if self.optimizer is not None:
            self.optimizer.select_dense(old, self.pose_deltas, 0, index)

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
        if self._deciding() and self.iteration >= self.config.nonrigid_decide_iter:
            self._decide()
        if self._normal_sign_pending() and self.iteration >= self.config.normal_decide_iter:
            self._decide_normal_sign()
        c = self.config
        it = self.iteration
        gen = step_generator(self.seed, it)
        frames = self._training_frames()
        stored = frames[int(torch.randint(len(frames), (1,), generator=gen))]
        progress = it / max(c.iterations, 1)
        boost = {"pose": pose_warmup_factor(progress, c.pose_warmup, c.pose_warmup_boost)}
        self.optimizer.set_schedule(progress, 0.01, c.lr_schedule_final, boost)
        sh_degree = min(c.model.sh_degree, it // max(c.sh_increase_every, 1))

        full = c.full_frame_every > 0 and it % c.full_frame_every == 0
        crop = None if full else stored.crop
        camera = Camera3.from_camera(stored.frame.camera, crop, self.device)
        x0, y0, w, h = crop or (0, 0, camera.width, camera.height)
        image = torch.from_numpy(stored.image[y0 : y0 + h, x0 : x0 + w])
        target = image.to(self.device, torch.float32, copy=True).div_(255.0)  # one new tensor, in place
        mask = None
        if stored.frame.mask is not None:
            m = stored.frame.mask[y0 : y0 + h, x0 : x0 + w]
            mask = torch.from_numpy(m > 127).to(self.device)

        body = self.body_state(stored.frame)
        u = self.model.time_axis(stored.frame.time)
        jitter = self._time_jitter(stored, gen, progress)  # the spacetime terms see u + jitter
        bones, key = self._frame_bones(stored, body, "now")
        timer.mark("data")
        moving = self._moving_rows()  # only these carry motion terms (the gate); the rest are rigid
        state = self.model.spacetime(u + jitter, rows=moving)
        flow_pair = stored.flow if stored.next_smpl is not None else None
        use_flow = flow_pair is not None and c.loss.flow > 0 and self._flow_step(it)
        table = self.model.table
        want_temporal = c.loss.temporal > 0 and "t_center" in table and stored.next_time is not None
        # The next frame's spacetime terms (at its time + the same jitter, on the moving rows): one
        # evaluation for the flow and temporal terms. Its centres (the flow) are skinned in the
        # pose's own pass (AvatarModel.pose's next_frame: the weights once for both frames).
        next_state = next_frame = None
        if use_flow or want_temporal:
            u_next = self.model.time_axis(stored.next_time) + jitter
            next_state = self.model.spacetime(u_next, rows=moving)
        if use_flow:
            next_body = self.body_state(stored.frame, smpl=stored.next_smpl)
            next_frame = (self._frame_bones(stored, next_body, "next")[0], next_state)
        posed = self.model.pose(
            body,
            u,
            camera.center,
            sh_degree=sh_degree,
            bones=bones,
            key=key,
            state=state,
            camera=camera,
            color_turns=None if self.color_turns is None else (self.color_turns, it),
            next_frame=next_frame,
            outward_normals=c.model.normal_sign == "outward",
        )
        timer.mark("pose")

        terms: dict[str, torch.Tensor] = {}
        extra = None
        if use_flow:
            extra = camera.motion(posed.means, posed.next_means)
        timer.mark("flow_target")

        want_depth = use_flow and c.densify.occlusion_m > 0  # the surface each pixel sees (densify._in_front)
        image, alpha, info = render(
            posed, camera, background=0.0, backend=self.backend, extra_channels=extra, render_depth=want_depth
        )
        timer.mark("render")
        # The colour and the motion channels as two tensors (one split: its backward is one cat,
        # where two slices would each scatter into a zeroed image); no split without motion.
        rendered_rgb, rendered_flow = (
            image.split([3, image.shape[-1] - 3], dim=-1) if use_flow else (image, None)
        )
        region = None
        if self.exposure.enabled:  # where the person is rendered and seen: the gains' evidence
            region = alpha[..., 0].detach() > 0.95
            region = region & mask if mask is not None else region
        rgb = self.exposure.apply(rendered_rgb, stored.frame.index, it, target, region)
        l1, dssim = L.photometric(rgb, target, c.loss.ssim)
        terms["photo"] = (1 - c.loss.ssim) * l1 + c.loss.ssim * dssim
        if mask is not None and c.loss.mask > 0:
            terms["mask"] = L.mean_abs_difference(alpha.squeeze(-1), mask.float())
        if use_flow:
            fwd = torch.from_numpy(flow_pair.forward[y0 : y0 + h, x0 : x0 + w]).to(self.device)
            valid = torch.from_numpy(flow_pair.valid_forward[y0 : y0 + h, x0 : x0 + w]).to(self.device)
            terms["flow"] = L.flow_loss(rendered_flow, alpha, fwd, valid)
        if want_temporal:
            terms["temporal"] = self._temporal_term(state, next_state)
        if c.loss.line_of_sight > 0 and state.offsets is not None and len(self.camera_slots) == 1:
            # One camera only: several around the subject see depth, and holding each step's motion
            # off its own camera's rays would hold it off every camera's in turn.
            terms["line_of_sight"] = self._line_of_sight(state, bones, camera)
        if c.loss.rigidity > 0 and state.offsets is not None and self.model.motion_bases is None:
            terms["rigidity"] = self.neighbours.loss(table, state.offsets, state.temporal)
        if c.loss.isometry > 0 and it % c.loss.isometry_every == 0:
            terms["isometry"] = self.isometry.loss(table, posed.means, posed.canonical, posed.index)
        terms.update(self._regularisers(body))
        if c.loss.pose_smooth > 0 and self.pose_deltas is not None:
            smooth = self.pose_track.smoothness(self.pose_deltas, self.pose_slots, stored.frame.index)
            if smooth is not None:
                terms["pose_smooth"] = smooth
        weights = {
            "mask": c.loss.mask,
            "flow": c.loss.flow * max(c.loss.flow_every, 1),  # present on every k-th step only
            "temporal": c.loss.temporal,
            "rigidity": c.loss.rigidity,
            "line_of_sight": c.loss.line_of_sight,
            "motion_smooth": c.loss.motion_smooth,
            "basis_smooth": c.loss.basis_smooth,
            "scale": c.loss.scale,
            "opacity": c.loss.opacity,
            "skin": c.loss.skin,
            "pose": c.loss.pose_refine,
            "isometry": c.loss.isometry * c.loss.isometry_every,  # present on every k-th step only
            "light": c.loss.light,
            "light_unseen": c.loss.light_unseen,
            "pose_smooth": c.loss.pose_smooth,
        }
        total, applied = self.weights.combine(terms, weights, it)
        timer.mark("loss")

        self.optimizer.zero_grad()
        skipped = not math.isfinite(float(total.detach()))
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
        else:
            gate = self.model.table.motion_gate()
            if gate is not None:  # static Gaussians keep exactly zero motion terms
                for name in MOTION_COLUMNS:
                    self.optimizer.freeze_rows(name, ~gate)
            restore_unseen = None
            if self.pose_deltas is not None and c.lr_pose > 0:  # only the frames seen move (pose_refine.py)
                seen = touched_slots(self.pose_slots, stored.frame.index, "pose_smooth" in terms)
                restore_unseen = hold_unseen_rows(self.pose_deltas, seen)
            self.optimizer.step()
            if restore_unseen is not None:
                restore_unseen()
            for name in ("motion", "rot_motion"):  # a basis coefficient's sparsity is its row's gate
                self.optimizer.soft_threshold(name, c.loss.motion_sparsity)
            timer.mark("update")
            inputs = DensifyInputs(
                iteration=it,
                info=info,
                index=posed.index,
                camera=camera,
                crop=(x0, y0, w, h),
                render=rgb.detach(),
                target=target,
                mask=mask,
                flow=flow_pair,
                u=u,
                bones=bones,
                generator=gen,
                motion_threshold_px=self.motion_threshold(),
                time_range=self.time_range(),
                surface=self.surface,
                rendered_flow=(rendered_flow / alpha.clamp_min(0.5)).detach() if use_flow else None,
                rendered_depth=surface_depth(info["depth"], alpha) if want_depth else None,
                grow_in_time=not self._deciding(),
                camera_slot=self.camera_slots.get(stored.frame.camera.name, 0),
            )
            report = self.densifier.step_post_backward(self.model, self.optimizer, self.densify_state, inputs)
            timer.mark("densify")
        if self.profile is not None:
            self.profile.steps += 1
        self.iteration += 1
        elapsed = time.perf_counter() - started
        self.train_seconds += elapsed
        with torch.no_grad():
            mse = float(torch.nn.functional.mse_loss(rgb.detach(), target))  # one pass (the PSNR shown)
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

    # --- the non-rigid part earns its place (nonrigid.py) -------------------------------------------
    def _deciding(self) -> bool:
        """Whether the non-rigid part is on trial: "auto", still on, not decided yet, and a schedule
        long enough to reach the decision (a shorter one keeps the part on, with every frame)."""
        c = self.config
        return (
            c.nonrigid == "auto"
            and c.model.spacetime
            and self.decision is None
            and c.iterations > c.nonrigid_decide_iter
        )

    def _training_frames(self) -> list[StoredFrame]:
        """The frames a step draws from: all, less the held-out ones while the trial runs."""
        every = self.config.nonrigid_holdout_every
        if not self._deciding():
            return self.store.frames
        kept = [f for f in self.store.frames if not nonrigid.held_out(f.frame.index, every)]
        return kept or self.store.frames

    def _held_out_views(self):
        """(camera, body, u, target) of the held-out frames' crops (nonrigid.validation_gain)."""
        every = self.config.nonrigid_holdout_every
        for stored in self.store.frames:
            if not nonrigid.held_out(stored.frame.index, every):
                continue
            camera = Camera3.from_camera(stored.frame.camera, stored.crop, self.device)
            x0, y0, w, h = stored.crop
            target = torch.from_numpy(stored.image[y0 : y0 + h, x0 : x0 + w]).to(self.device).float() / 255.0
            body = self.body_state(stored.frame)
            yield camera, body, self.model.time_axis(stored.frame.time), target

    def _decide(self) -> None:
        """Keep the non-rigid part or switch it off, from the evidence so far (nonrigid.py)."""
        c = self.config
        state = self.densify_state
        seen = state["resid_w"] > 0
        # From several cameras, motion terms on at the decision count as motion the rigid model misses.
        learned = self.model.table.motion_gate() if len(self.camera_slots) > 1 else None
        evidence = {
            "moving_fraction": nonrigid.moving_fraction(
                state["resid_w"], seen, c.densify.residual_motion_px, learned
            ),
            "active_motion_fraction": self.stats()["active_motion_fraction"],
        }
        if evidence["moving_fraction"] < c.nonrigid_min_moving:
            why = (
                f"the rigid model explains the motion: {100 * evidence['moving_fraction']:.1f} % of the "
                f"Gaussians see flow it misses by more than {c.densify.residual_motion_px:.3g} px per frame "
                f"{'or move with their own terms ' if learned is not None else ''}"
                f"(needs >= {100 * c.nonrigid_min_moving:g} %)"
            )
            chose = "off"
        else:
            rigid, _ = nonrigid.rigid_part(self.model)
            evidence |= nonrigid.validation_gain(self.model, rigid, self._held_out_views(), self.backend)
            gain = evidence["gain_db"]
            pays = gain >= c.nonrigid_min_gain_db
            chose = "on" if pays else "off"
            why = (
                f"on held-out frames the non-rigid terms change {100 * evidence['changed_fraction']:.1f} % "
                f"of the pixels and gain {gain:+.2f} dB there ({'>=' if pays else '<'} "
                f"{c.nonrigid_min_gain_db:g} dB); {100 * evidence['moving_fraction']:.1f} % of the "
                "Gaussians see flow the rigid model misses"
                f"{' or move with their own terms' if learned is not None else ''}"
            )
        self.decision = nonrigid.Decision(chose, why, self.iteration, evidence)
        log.info("non-rigid part %s at iteration %d: %s", chose, self.iteration, why)
        if chose == "off":
            self._switch_off()

    def _switch_off(self) -> None:
        """Continue as LBS only: the rigid part of the model, its Adam state and statistics kept."""
        rigid, keep = nonrigid.rigid_part(self.model)
        table_state = {
            name: {k: (v[keep] if torch.is_tensor(v) and v.dim() > 0 else v) for k, v in s.items()}
            for name, s in self.optimizer.table_state().items()
            if name in rigid.table.names()
        }
        dense_state = {k: v for k, v in self.optimizer.dense_state().items() if not k.startswith("bases.")}
        self.config = self.config.replace(**LBS_ONLY)
        self.attach_model(rigid, self.betas)
        self._build_optimizer()
        self.optimizer.load_table_state(table_state)
        self.optimizer.load_dense_state(dense_state)
        self.densifier = DensifyStrategy(self.config.densify, self.config.iterations)
        DensifyStrategy._resize(self.densify_state, keep=keep)
        self.densify_state["was_dynamic"].zero_()
        # The interval's screen gradients are the switched-off model's misfit (its rows snapped back to
        # the rigid part): the rigid model is densified on statistics of its own (densify.step).
        DensifyStrategy._reset_interval(self.densify_state)
        self.neighbours = NeighbourGraph()

    # --- which way the training normals point (normal_trial.py) -------------------------------------
    def _normal_sign_pending(self) -> bool:
        """Whether model.normal_sign is "auto" and not decided yet on a shaded model."""
        c = self.config
        return c.model.normal_sign == "auto" and c.model.shading and self.model.shading is not None

    def _decide_normal_sign(self) -> None:
        """Outward normals from now on where the learned light has the contrast to need them."""
        contrast = normal_trial.light_contrast(self.model.shading)
        sign, why = normal_trial.choose(contrast, self.config.normal_min_contrast)
        self.notes[normal_trial.CONTRAST_NOTE] = contrast
        seen = normal_trial.light_contrast(self.model.shading, seen_only=True)  # a diagnostic, beside it
        self.notes[normal_trial.SEEN_CONTRAST_NOTE] = seen
        self.notes[normal_trial.ITERATION_NOTE] = float(self.iteration)
        self.config = self.config.replace(**{normal_trial.NORMAL_SIGN_KEY: sign})
        self.model.config = dataclasses.replace(self.model.config, normal_sign=sign)
        log.info("training normals %s at iteration %d: %s", sign, self.iteration, why)

    def normal_sign_report(self) -> dict:
        """What the run chose for the training normals' sign and why (the run's summary)."""
        return normal_trial.report(self.config, self.notes)

    def nonrigid_report(self) -> dict:
        """What the run chose for the non-rigid part and why (the run's summary)."""
        if self.decision is not None:
            return self.decision.to_dict()
        if not self.config.model.spacetime:
            how = "nonrigid=off" if self.config.nonrigid == "off" else "model.spacetime=false"
            return {"chose": "off", "why": f"{how}: LBS only from the start"}
        if self.config.nonrigid == "on":
            return {"chose": "on", "why": "nonrigid=on: kept whatever the evidence"}
        c = self.config
        if c.iterations <= c.nonrigid_decide_iter:
            return {
                "chose": "on",
                "why": f"no trial: {c.iterations} iterations end before nonrigid_decide_iter "
                f"({c.nonrigid_decide_iter})",
            }
        return {
            "chose": "on",
            "why": f"not decided yet: the trial ends at iteration {c.nonrigid_decide_iter}",
        }

    def motion_threshold(self) -> float:
        """delta (px per frame) of the frames held now (densify.motion_threshold)."""
        return motion_threshold(
            self.config.densify, [f.flow_magnitude for f in self.store.frames if f.flow is not None]
        )

    def time_range(self) -> tuple[float, float]:
        """Normalised times of the earliest and latest frame held now."""
        times = [self.model.time_axis(f.frame.time) for f in self.store.frames]
        return (min(times), max(times)) if times else (0.0, 0.0)

    @property
    def densify_counts(self) -> dict[str, int]:
        """What densification did so far (cloned, split, pruned, flow_added, ...)."""
        return counts(self.densify_state)

    def _flow_step(self, it: int) -> bool:
        """Whether step ``it`` renders the Gaussians' motion for the flow term (``loss.flow_every``)
        and densification (its flow rounds, which seed on the motion the model misses)."""
        every = max(self.config.loss.flow_every, 1)
        return it % every == 0 or self.densifier.flow_round(it)

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

    def _time_jitter(self, stored: StoredFrame, gen: torch.Generator, progress: float) -> float:
        """Annealed time noise (Deformable 3DGS): N(0, s^2) time units, s = ``time_noise_frames`` frame
        intervals at the start, falling linearly to 0 at ``time_noise_until`` of the schedule."""
        c = self.config
        if c.time_noise_frames <= 0 or progress >= c.time_noise_until:
            return 0.0
        interval_s = stored.next_time - stored.frame.time if stored.next_time is not None else 1 / 30
        scale = (
            c.time_noise_frames
            * (1.0 - progress / c.time_noise_until)
            * interval_s
            / self.model.time_axis.unit_s
        )
        return scale * float(torch.randn((), generator=gen))

    def _line_of_sight(self, state: spacetime.SpacetimeState, bones, camera: Camera3) -> torch.Tensor:
        """Motion along the training camera's rays, of the Gaussians that may move (motion_priors)."""
        table = self.model.table
        gate = table.motion_gate()
        rows = gate.nonzero().squeeze(1) if gate is not None else torch.arange(table.num, device=self.device)
        weights = self.model.skin_weights()[rows]
        offsets = state.offsets[rows]
        posed = skin(table["means"][rows] + offsets, weights, bones, rotations=False).means
        presence = state.temporal[rows] if state.temporal is not None else None
        return line_of_sight(world_offsets(offsets, weights, bones), posed, camera.center, presence)

    def _moving_rows(self) -> torch.Tensor | None:
        """Rows whose motion terms may be non-zero (the motion gate), or None without a gate."""
        gate = self.model.table.motion_gate()
        return None if gate is None else gate.nonzero().squeeze(1)

    def _temporal_term(self, now: spacetime.SpacetimeState, nxt: spacetime.SpacetimeState) -> torch.Tensor:
        table = self.model.table
        out = table["means"].new_zeros(())
        if now.offsets is not None and self.model.motion_bases is None:  # bases: their own smoothness
            out = out + 100.0 * (nxt.offsets - now.offsets).abs().sum(1).mean()
        if now.temporal is not None and nxt.temporal is not None:
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
        if self.model.motion_bases is not None and c.basis_smooth > 0:
            out["basis_smooth"] = self.model.motion_bases.roughness()
        if c.scale > 0:
            out["scale"] = torch.relu(largest_scale(table["log_scales"]) - c.scale_max_m).mean() * 100.0
        if c.opacity > 0:
            o = table.opacities()
            out["opacity"] = (-(o * (o + 1e-6).log() + (1 - o) * (1 - o + 1e-6).log())).mean()
        if "skin_delta" in table and c.skin > 0:
            out["skin"] = L.mean_square(table["skin_delta"])
        if self.pose_deltas is not None and c.pose_refine > 0:
            out["pose"] = self.pose_deltas.pow(2).sum(1).mean()
        if self.model.shading is not None and c.light > 0:
            out["light"] = self.model.shading.penalty()
        if self.model.shading is not None and c.light_unseen > 0:
            unseen = self.model.shading.unseen_penalty()
            if unseen is not None:
                out["light_unseen"] = unseen
        return out

    def _grads_finite(self) -> bool:
        """Whether every gradient is finite (optim.all_finite: one pass, no test per tensor)."""
        groups = self.optimizer.groups()
        return all_finite([p.grad for group in groups for p in group["params"] if p.grad is not None])

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
        if self.model is None:
            raise RuntimeError("no model yet: add a frame first")
        slots = sorted(self.pose_slots.items(), key=lambda kv: kv[1])
        state = checkpoint.TrainingState(
            model=self.model,
            config=self.config,
            body_model=self.body_reference,
            seed=self.seed,
            betas=self.betas,
            iteration=self.iteration,
            train_seconds=self.train_seconds,
            skipped_steps=self.skipped_steps,
            frames_seen=self.store.seen,
            model_version=self.model_version,
            table_adam=self.optimizer.table_state(),
            dense_adam=self.optimizer.dense_state(),
            pose_deltas=self.pose_deltas,
            pose_frames=[f for f, _ in slots],
            densify=self.densify_state,
            loss_ema=dict(self.weights.ema),
            nonrigid={} if self.decision is None else self.decision.to_dict(),
            isometry=self.isometry.state_arrays(self.model.table),
            notes=dict(self.notes),
            exposure=self.exposure.state_arrays(),
            color_turns={} if self.color_turns is None else self.color_turns.state_arrays(),
            camera_slots=dict(self.camera_slots),
        )
        return checkpoint.save(path, state)

    @classmethod
    def load(
        cls,
        path: str | Path,
        *,
        body_model=None,
        device="cpu",
        backend="auto",
        flow_cache=None,
        flow_settings=None,
    ) -> Trainer:
        """Resume from a checkpoint written by :meth:`save`; frames must be added again."""
        state = checkpoint.load(path, device=device)
        body = body_model if body_model is not None else state.body_model
        trainer = cls(
            state.config,
            body,
            device=device,
            backend=backend,
            seed=state.seed,
            flow_cache=flow_cache,
            flow_settings=flow_settings,
        )
        trainer._restore(state)
        return trainer

    def _restore(self, state: checkpoint.TrainingState) -> None:
        self.attach_model(state.model, state.betas)
        if state.pose_deltas is not None:
            self.pose_slots = {f: i for i, f in enumerate(state.pose_frames)}
            self.pose_deltas = torch.nn.Parameter(state.pose_deltas.to(self.device))
        self._build_optimizer()
        self.exposure.load_state_arrays(state.exposure)
        if self.color_turns is not None:
            self.color_turns.load_state_arrays(state.color_turns, self.device)
        self.optimizer.load_table_state(state.table_adam)
        self.optimizer.load_dense_state(state.dense_adam)
        self.densify_state = self.densifier.initialize_state(self.model) | {
            k: v.to(self.device) for k, v in state.densify.items()
        }
        self.weights.ema = dict(state.loss_ema)
        self.notes = dict(state.notes)
        self.isometry.load_state_arrays(state.isometry, self.model.table)
        self.iteration = state.iteration
        self.train_seconds = state.train_seconds
        self.skipped_steps = state.skipped_steps
        self.model_version = state.model_version
        self.decision = nonrigid.Decision.from_dict(state.nonrigid)
        # Frames come back after this, in any order: each known camera keeps its column (add_frame
        # numbers only new ones, and ends the colour turns for a rig).
        self.camera_slots = dict(state.camera_slots)

    # --- reporting -------------------------------------------------------------------------------
    def stats(self) -> dict:
        """Gaussian count, fraction with active motion terms, model size."""
        if self.model is None:
            return {"gaussians": 0, "active_motion_fraction": 0.0, "model_mb": 0.0}
        from stg_node.avatar.snapshot import model_nbytes

        table = self.model.table
        n = table.num
        active = float(table.motion_active().float().mean()) if n else 0.0
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


def _towards_camera(frame) -> torch.Tensor:
    """(3,) from the body's root to the frame's camera centre, world frame (not normalised)."""
    centre = -np.asarray(frame.camera.R, np.float64).T @ np.asarray(frame.camera.t, np.float64)
    return torch.as_tensor(centre - np.asarray(frame.smpl.Th, np.float64).reshape(3), dtype=torch.float32)


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
