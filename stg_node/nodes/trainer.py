"""The trainer node: trains the avatar online from camera/frame + body/pose, publishes what it learns.

- Pairs each frame with its pose (BodyPose names its frame: ``frame_index`` and ``frame_seq``);
  unpaired messages wait in bounded tables (``pending``), so memory stays flat on an endless
  stream; the avatar trainer itself keeps at most ``max_frames`` frames (a reservoir sample of the stream).
- Skips frames whose pose has a confidence below ``min_confidence`` (a live tracker that lost
  the person, saw two, or fitted badly), counted as drops ``low_confidence``: the frame and its
  pose never reach the avatar.
- Steps whenever it holds ``min_frames`` frames; trainer/metrics every ``metrics_every`` steps.
  With ``steps_per_frame`` N > 0 it steps exactly N times per new frame and then waits: the
  model then depends only on the frames and their order, not on how fast they came, which is
  what a lockstep replay (``stg-bag play --lockstep``) needs to reproduce a run exactly.
- Acknowledgements (the runtime's ``ack``, for lockstep replay): a frame or pose that waits for
  its partner is acknowledged when stored; the one that completes a pair once the frame is in
  the trainer and, with ``steps_per_frame``, once its N steps are done (and their metrics out).
- avatar/snapshot every ``snapshot_every`` iterations and/or ``snapshot_every_s`` seconds, and at
  the end (latched by the broker: a renderer started later gets it at once).
- Checkpoints to ``checkpoint_dir``/trainer.ckpt every ``checkpoint_every_s`` s and at the end,
  atomically (write, then rename): one file holds the model, the optimiser, the frame store's
  bound (``max_frames``, in the avatar's config) and the node's own numbers (its wall time), so
  no two files can disagree after a kill. When respawned with ``resume`` it continues from the
  last checkpoint, iteration and bound included.
- Ends on its own after ``iters`` iterations (0: never), writing ``out``/summary.json: the
  training-view PSNR as a running mean over the last ``PSNR_WINDOW`` steps (one step's crop swings
  by several dB from frame to frame), and, with ``eval_data``, the final model's quality on that
  dataset's held-out cameras (novel-view PSNR / SSIM / LPIPS), which is what a user should judge.

All calls into the avatar package go through :mod:`.avatar_adapter`.
"""

from __future__ import annotations

import json
import math
import os
import time
from collections import OrderedDict, deque
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from stg_node.bus import TrainerMetrics
from stg_node.nodes.avatar_adapter import DEFAULT_MODULE, StepInfo, TrainerAdapter, avatar_module
from stg_node.nodes.convert import frame_camera
from stg_node.nodes.params import param
from stg_node.nodes.runtime import Node

CHECKPOINT_NAME = "trainer.ckpt"
PSNR_WINDOW = 100  # steps the summary's training-view PSNR is averaged over


@dataclass
class TrainerParams:
    avatar: str = param(DEFAULT_MODULE, doc="package implementing the avatar API (tests: a fake)")
    preset: str = param("fast", doc="training preset: fast, balanced, quality")
    body_model: str | None = param(None, doc="SMPL model file or folder (default: the open body)")
    device: str = param("cpu", doc="torch device")
    backend: str = param("auto", doc="rasterizer backend: auto, cpu, cuda, torch")
    seed: int = param(0, doc="random seed")
    exposure_correction: bool = param(
        False,
        doc="learn a per-frame exposure/white-balance correction: on for a live camera that sets "
        "its own exposure, off for data filmed at a fixed one (avatar/exposure.py)",
    )
    # Live, every new frame pair's flow is computed as it arrives (offline, once into a cache): at
    # the frames' own pixels (level 0, stg-train's default) DIS costs about 10x a quarter
    # resolution (level 2) at 512 px, more than a live trainer can spend per frame on 2 cores.
    flow_level: int = param(
        2,
        min=0,
        max=8,
        doc="finest pyramid level of each new frame pair's optical flow (0: the frames' own pixels, "
        "as stg-train, about 10x the time of 2 at 512 px; 2: a quarter of the resolution, its error "
        "can read a near-still body as missed motion)",
    )
    iters: int = param(0, min=0, doc="stop after this many iterations (0: train until stopped)")
    max_frames: int = param(
        64, min=1, doc="frames the trainer keeps (a reservoir sample: old and new frames stay)"
    )
    min_confidence: float = param(
        0.5, min=0.0, max=1.0, doc="skip frames whose pose's tracker confidence is below this"
    )
    min_frames: int = param(1, min=1, doc="frames needed before the first step")
    steps_per_frame: int = param(
        0,
        min=0,
        doc="0: train continuously; N: exactly N steps per new frame, then wait for the next "
        "(deterministic under lockstep replay)",
    )
    pending: int = param(256, min=1, doc="frames / poses waiting for their partner, at most")
    metrics_every: int = param(1, min=1, doc="publish trainer/metrics every N steps")
    snapshot_every: int = param(0, min=0, doc="publish avatar/snapshot every N iterations (0: off)")
    snapshot_every_s: float = param(10.0, min=0.0, unit="s", doc="... and every S seconds (0: off)")
    checkpoint_dir: str = param("", doc="folder for checkpoints (empty: none)")
    checkpoint_every_s: float = param(60.0, min=0.0, unit="s", doc="checkpoint period (0: only at the end)")
    resume: Literal["respawn", "always", "never"] = param(
        "respawn",
        doc="continue from checkpoint_dir's checkpoint: when respawned by stg-launch, always, or never",
    )
    out: str = param("", doc="folder for summary.json at the end (empty: none)")
    rig: str = param("", doc="a rig.json: train from each of its cameras' NAME/camera/frame (docs/RIGS.md)")
    eval_data: str = param(
        "",
        doc="when the iterations are done, score the model on this dataset's held-out cameras "
        "(a stg-synth or ZJU-MoCap folder; empty: no)",
    )


class FramePairs:
    """Frames and poses waiting for each other, keyed by (frame_index, frame_seq); bounded.

    ``camera_of(msg)``: which camera a message belongs to, for a rig whose cameras each have their
    own frame and pose topics (seq numbers count per topic, so they repeat across cameras); the
    key then starts with it. Default: one camera."""

    def __init__(self, limit: int, camera_of=None):
        self.limit = limit
        self.camera_of = camera_of or (lambda msg: "")
        self.frames: OrderedDict = OrderedDict()
        self.poses: OrderedDict = OrderedDict()
        self.rejected: OrderedDict = OrderedDict()  # keys of frames whose pose was refused
        self.evicted_frames = 0

    @staticmethod
    def _bounded(table: OrderedDict, key, value, limit: int) -> int:
        table[key] = value
        table.move_to_end(key)
        evicted = 0
        while len(table) > limit:
            table.popitem(last=False)
            evicted += 1
        return evicted

    def add_frame(self, frame):
        key = (self.camera_of(frame), frame.index, frame.header.seq)
        if self.rejected.pop(key, None) is not None:
            return None
        pose = self.poses.pop(key, None)
        if pose is not None:
            return frame, pose
        self.evicted_frames += self._bounded(self.frames, key, frame, self.limit)
        return None

    def add_pose(self, pose):
        key = (self.camera_of(pose), pose.frame_index, pose.frame_seq)
        frame = self.frames.pop(key, None)
        if frame is not None:
            return frame, pose
        self._bounded(self.poses, key, pose, self.limit)  # poses of frames we never took: expected
        return None

    def reject(self, pose) -> None:
        """``pose``'s frame is not wanted: drop it if it waits, else drop it when it comes."""
        key = (self.camera_of(pose), pose.frame_index, pose.frame_seq)
        if self.frames.pop(key, None) is None:
            self._bounded(self.rejected, key, True, self.limit)


class TrainerNode(Node):
    """Online STG-Avatar training on the bus."""

    kind = "trainer"
    Params = TrainerParams

    @classmethod
    def prepare(cls, params: TrainerParams) -> None:
        from stg_node.threads import configure_threads

        configure_threads()
        avatar_module(params.avatar)  # torch and the avatar package
        import torch

        # torch.optim imports torch._dynamo on the first optimiser it builds: seconds on a busy
        # machine, which a resumed trainer would otherwise spend before its first step
        torch.optim.Adam([torch.zeros(1, requires_grad=True)])

    def setup(self) -> None:
        from stg_node.threads import configure_threads

        configure_threads()
        p = self.params
        self.checkpoint = Path(p.checkpoint_dir) / CHECKPOINT_NAME if p.checkpoint_dir else None
        self.elapsed_before = 0.0
        self.resumed_from = None
        resume = p.resume == "always" or (p.resume == "respawn" and self.respawned)
        if self.checkpoint is not None and resume and self.checkpoint.is_file():
            self.trainer = TrainerAdapter.load(
                self.checkpoint, module=p.avatar, device=p.device, backend=p.backend, flow_level=p.flow_level
            )
            self.elapsed_before = float(self.trainer.notes.get("elapsed_s", 0.0))
            self.iteration = self.trainer.iteration
            self.resumed_from = str(self.checkpoint)
            self.log.info("resumed from %s at iteration %d", self.checkpoint, self.iteration)
        else:
            self.trainer = TrainerAdapter.create(
                module=p.avatar,
                preset=p.preset,
                body_model=p.body_model,
                device=p.device,
                backend=p.backend,
                seed=p.seed,
                max_frames=p.max_frames,
                footage=p.exposure_correction,
                flow_level=p.flow_level,
            )
            self.iteration = 0
        self.pairs = FramePairs(p.pending)  # a rig: replaced below, keyed by camera too
        self.owed_steps = 0  # steps_per_frame: steps still owed to the frames received
        self.owed_acks: list = []  # messages acknowledged once the steps they brought are done
        self.frames_in_buffer = 0
        self.frames_added = 0
        self.frames_unsure = 0  # skipped: pose confidence below min_confidence
        self.last: StepInfo | None = None
        self.recent_psnr: deque[float] = deque(maxlen=PSNR_WINDOW)  # training view, per step
        self.published_version = -1
        self.model_figures: dict[str, float] = {}  # active_motion_fraction, model_mb: at each snapshot
        self.finished = False
        if p.rig:  # each camera its own frame and pose topics (docs/RIGS.md)
            from stg_node.nodes.rig import rig_camera_names, rig_subscriptions

            self.frames, self.poses, self.pairs.camera_of = rig_subscriptions(self, rig_camera_names(p.rig))
        else:
            self.frames = self.subscribe("camera/frame")  # keep-last: the newest frame when we have time
            self.poses = self.subscribe("body/pose")
        self.started = time.monotonic()
        self.last_snapshot_time = self.started
        self.last_checkpoint_time = self.started

    # -- input ----------------------------------------------------------------------------------------

    def _add_pose(self, pose):
        if pose.confidence < self.params.min_confidence:
            self.pairs.reject(pose)
            self.frames_unsure += 1
            self.drop("low_confidence")
            return None
        return self.pairs.add_pose(pose)

    def _take_input(self) -> None:
        for sub, add in ((self.poses, self._add_pose), (self.frames, self.pairs.add_frame)):
            for _ in range(1024):
                msg = sub.recv(timeout=0)
                if msg is None:
                    break
                pair = add(msg)
                if pair is None:
                    self.acknowledge(msg)  # stored until its partner comes: done with it for now
                    continue
                self._add(*pair)
                if self.params.steps_per_frame and self.frames_in_buffer >= self.params.min_frames:
                    self.owed_steps += self.params.steps_per_frame
                    self.owed_acks.append(msg)
                else:
                    self.acknowledge(msg)

    def _add(self, frame, pose) -> None:
        self.trainer.add_frame(
            index=frame.index,
            time=frame.time,
            image=frame.image,
            mask=frame.mask,
            camera=frame_camera(frame),
            smpl=pose.to_smpl(),
        )
        self.frames_added += 1
        bound = self.trainer.max_frames
        self.frames_in_buffer = min(self.frames_in_buffer + 1, bound) if bound else self.frames_in_buffer + 1

    # -- output ---------------------------------------------------------------------------------------

    @property
    def elapsed(self) -> float:
        return self.elapsed_before + time.monotonic() - self.started

    def _metrics(self, info: StepInfo) -> None:
        self.publish(
            TrainerMetrics(
                iteration=info.iteration,
                model_version=max(self.published_version, 0),
                num_gaussians=info.num_gaussians,
                loss=info.loss,
                losses=info.losses,
                psnr=info.psnr,
                it_per_s=max(info.it_per_s, 0.0),
                elapsed_s=self.elapsed,
                extra={
                    "frames_added": float(self.frames_added),
                    "frames_buffered": float(self.frames_in_buffer),
                    "frames_low_confidence": float(self.frames_unsure),
                    **self.model_figures,
                },
            )
        )

    def _snapshot(self) -> None:
        if self.iteration == self.published_version:
            return
        msg = self.trainer.snapshot(version=self.iteration)
        self.publish(msg)
        self.model_figures = self.trainer.model_stats()  # with the snapshot: it walks the model too
        self.model_figures.pop("gaussians", None)  # num_gaussians has its own field
        self.published_version = self.iteration
        self.last_snapshot_time = time.monotonic()
        self.log.info("snapshot v%d (%d Gaussians)", self.iteration, msg.num_gaussians)

    def _save_checkpoint(self) -> None:
        if self.checkpoint is None:
            return
        self.checkpoint.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.checkpoint.with_name(self.checkpoint.name + ".tmp")
        self.trainer.save(tmp, notes={"elapsed_s": self.elapsed})
        os.replace(tmp, self.checkpoint)  # a kill mid-write leaves the previous checkpoint intact
        self.last_checkpoint_time = time.monotonic()
        self.log.info("checkpoint at iteration %d: %s", self.iteration, self.checkpoint)

    # -- loop -----------------------------------------------------------------------------------------

    def _settle_acks(self) -> None:
        for msg in self.owed_acks:
            self.acknowledge(msg)
        self.owed_acks.clear()

    def run(self) -> None:
        p = self.params
        while not self.stopping:
            self._take_input()
            if self.frames_in_buffer < p.min_frames or (p.steps_per_frame and not self.owed_steps):
                self.wait_for_messages(0.1)
                continue
            info = self.trainer.step()
            if p.steps_per_frame:
                self.owed_steps -= 1  # a skipped step counts too: the next one is another draw
            if info.skipped:
                if p.steps_per_frame and not self.owed_steps:
                    self._settle_acks()
                self.wait_for_messages(0.01)
                continue
            self.iteration = info.iteration
            self.last = info
            if math.isfinite(info.psnr):
                self.recent_psnr.append(info.psnr)
            if self.iteration % p.metrics_every == 0:
                self._metrics(info)
            now = time.monotonic()
            due_iter = p.snapshot_every and self.iteration % p.snapshot_every == 0
            due_time = p.snapshot_every_s and now - self.last_snapshot_time >= p.snapshot_every_s
            if due_iter or due_time:
                self._snapshot()
            if p.checkpoint_every_s and now - self.last_checkpoint_time >= p.checkpoint_every_s:
                self._save_checkpoint()
            if not self.owed_steps:
                self._settle_acks()
            if p.iters and self.iteration >= p.iters:
                self.finished = True
                self.log.info("reached %d iterations", p.iters)
                break
        self._settle_acks()  # stopped or done: nothing more will be done for them

    def teardown(self) -> None:
        if getattr(self, "trainer", None) is None or self.iteration == 0:
            return
        self._snapshot()
        self._save_checkpoint()
        psnr = float(sum(self.recent_psnr) / len(self.recent_psnr)) if self.recent_psnr else None
        heldout = self._evaluate() if self.finished and self.params.eval_data else None
        summary = {
            "iterations": self.iteration,
            "elapsed_s": round(self.elapsed, 2),
            "psnr": psnr,
            "psnr_note": f"training view: mean over the last {len(self.recent_psnr)} steps' crops",
            "psnr_last_step": None if self.last is None else self.last.psnr,
            "heldout": heldout,
            "num_gaussians": None if self.last is None else self.last.num_gaussians,
            "frames_added": self.frames_added,
            "frames_low_confidence": self.frames_unsure,
            "finished": self.finished,
            "resumed_from": self.resumed_from,
        }
        self.log.info(
            "summary: %d iterations in %.1f s, PSNR %s dB (training view, mean of the last %d steps), "
            "%s Gaussians",
            self.iteration,
            self.elapsed,
            "n/a" if psnr is None else f"{psnr:.2f}",
            len(self.recent_psnr),
            summary["num_gaussians"],
        )
        if heldout is not None:
            self.log.info(
                "summary: held-out cameras (%s, %d views): PSNR %.2f dB, SSIM %.4f, LPIPS %s",
                heldout["split"],
                heldout["views"],
                heldout["psnr"],
                heldout["ssim"],
                "n/a" if heldout["lpips"] is None else f"{heldout['lpips']:.4f}",
            )
        if self.params.out:
            out = Path(self.params.out)
            out.mkdir(parents=True, exist_ok=True)
            (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")

    def _evaluate(self) -> dict | None:
        """The final model on ``eval_data``'s held-out cameras; None (and a warning) if that fails."""
        try:
            return self.trainer.evaluate(self.params.eval_data)
        except Exception as exc:  # a summary without held-out figures beats no summary
            self.log.warning("held-out evaluation on %s failed: %s", self.params.eval_data, exc)
            return None
