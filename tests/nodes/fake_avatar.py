"""A stand-in for stg_node.avatar with the same names (AVATAR_API.md), for the node tests.

Node processes load it with the param ``avatar: tests.nodes.fake_avatar``. Its behaviour is
simple enough to check from outside:

- Trainer: ``step()`` is skipped until a frame arrives, then counts iterations; the loss is
  1 / (1 + iteration); the buffer keeps at most ``config.max_frames`` frames; ``snapshot()`` carries
  the iteration and the mean colour of the buffered images' masked pixels; ``save``/``load``
  round-trip the iteration, the config and the notes exactly (np.savez).
- evaluate_trainer: held-out figures that name the trainer's iteration (PSNR 20 + 0.001 k).
- AvatarRenderer: draws a disc of the snapshot's colour at the projection of the body root
  (``Th``) through the camera, radius = focal * 0.25 m / depth; alpha 255 inside. Its posed
  points (what a framing camera keeps in view) are a sphere of that radius around ``Th``.
  ``points``: a ring of ``POINTS`` points of radius 0.25 m around ``Th`` (in the world's x-y
  plane), in that colour, fully opaque.
"""

from __future__ import annotations

import json
import threading
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from stg_node.bus import GaussianSnapshot

BODY_RADIUS_M = 0.25
#: A snapshot with meta ``gate`` 1 loads only once this is set (a test holds a load open as long as
#: it needs, instead of guessing how long is long enough). Set it through the module the node
#: imported: ``tests.nodes.fake_avatar``.
LOAD_GATE = threading.Event()
POINTS = 32


@dataclass
class TrainConfig:
    step_s: float = 0.0  # time one step takes
    load_s: float = 0.0  # time AvatarRenderer.from_snapshot takes (hot-swap tests)
    num_gaussians: int = 100
    max_frames: int = 0  # frames kept (0: all), as the real config


def preset(name: str) -> TrainConfig:
    presets = {"fast": TrainConfig(), "slow": TrainConfig(step_s=0.05), "heavy": TrainConfig(load_s=0.3)}
    if name not in presets:
        raise ValueError(f"unknown preset {name!r}")
    return presets[name]


@dataclass
class TrainFrame:
    index: int
    time: float
    image: np.ndarray
    mask: np.ndarray | None
    camera: object
    smpl: object


@dataclass
class StepResult:
    iteration: int
    loss: float
    losses: dict = field(default_factory=dict)
    psnr: float = float("nan")
    num_gaussians: int = 0
    it_per_s: float = 0.0
    skipped: bool = False


class Trainer:
    def __init__(self, config: TrainConfig, body_model=None, device="cpu", backend="auto", seed=0):
        self.config = config
        self.frames: deque = deque(maxlen=config.max_frames or None)
        self.iteration = 0
        self.frames_seen = 0
        self.notes: dict[str, float] = {}

    def add_frame(self, frame: TrainFrame) -> None:
        self.frames.append(frame)
        self.frames_seen += 1

    def _color(self) -> np.ndarray:
        if not self.frames:
            return np.full(3, 0.5, np.float32)
        f = self.frames[-1]
        pixels = f.image[f.mask > 0] if f.mask is not None and (f.mask > 0).any() else f.image.reshape(-1, 3)
        return (pixels.mean(axis=0) / 255.0).astype(np.float32)

    def step(self) -> StepResult:
        if not self.frames:
            return StepResult(iteration=self.iteration, loss=float("nan"), skipped=True)
        if self.config.step_s:
            time.sleep(self.config.step_s)
        self.iteration += 1
        loss = 1.0 / (1.0 + self.iteration)
        return StepResult(
            iteration=self.iteration,
            loss=loss,
            losses={"l1": loss},
            psnr=10.0 + 0.01 * self.iteration,
            num_gaussians=self.config.num_gaussians,
            it_per_s=100.0,
        )

    def snapshot(self) -> GaussianSnapshot:
        n = self.config.num_gaussians
        return GaussianSnapshot(
            format="fake/1",
            model_version=0,
            iteration=self.iteration,
            num_gaussians=n,
            meta={"load_s": float(self.config.load_s)},
            arrays={"xyz": np.zeros((n, 3), np.float32), "color": self._color().reshape(1, 3)},
        )

    def save(self, path: str) -> None:
        with open(path, "wb") as f:
            np.savez(
                f,
                iteration=self.iteration,
                step_s=self.config.step_s,
                load_s=self.config.load_s,
                max_frames=self.config.max_frames,
                color=self._color(),
                notes=json.dumps(self.notes),
            )

    @classmethod
    def load(cls, path: str, body_model=None, device="cpu", backend="auto") -> Trainer:
        data = np.load(path)
        config = TrainConfig(
            step_s=float(data["step_s"]), load_s=float(data["load_s"]), max_frames=int(data["max_frames"])
        )
        trainer = cls(config)
        trainer.iteration = int(data["iteration"])
        trainer.notes = json.loads(str(data["notes"]))
        return trainer


def evaluate_trainer(trainer: Trainer, data: str) -> dict:
    return {"split": "novel_view", "views": 4, "psnr": 20.0 + 0.001 * trainer.iteration, "ssim": 0.5,
            "lpips": 0.1}  # fmt: skip


@dataclass
class PointsOut:
    positions: np.ndarray
    colors: np.ndarray
    alpha: np.ndarray


@dataclass
class RenderOut:
    image: np.ndarray
    alpha: np.ndarray
    depth: np.ndarray | None
    render_ms: float


def project(camera, point: np.ndarray) -> tuple[float, float, float]:
    """(u, v, depth) of a world point in ``camera``."""
    p = np.asarray(camera.R, np.float64) @ np.asarray(point, np.float64) + np.asarray(camera.t, np.float64)
    uvw = np.asarray(camera.K, np.float64) @ p
    return uvw[0] / uvw[2], uvw[1] / uvw[2], p[2]


class AvatarRenderer:
    def __init__(self, color: np.ndarray, iteration: int):
        self.color = color
        self.iteration = iteration

    @classmethod
    def from_snapshot(cls, msg: GaussianSnapshot, device="cpu", backend="auto") -> AvatarRenderer:
        if msg.format != "fake/1":
            raise ValueError(f"fake avatar cannot read snapshot format {msg.format!r}")
        time.sleep(float(msg.meta.get("load_s", 0.0)))
        if msg.meta.get("gate"):
            LOAD_GATE.wait(60)
        return cls(np.array(msg.arrays["color"]).reshape(3), msg.iteration)

    def posed_points(self, smpl, time=None) -> np.ndarray:
        """A sphere of radius BODY_RADIUS_M around the body root: 6 poles and 8 diagonals."""
        directions = np.concatenate(
            [np.eye(3), -np.eye(3), np.array(np.meshgrid(*[[-1, 1]] * 3)).reshape(3, -1).T]
        )
        directions = directions / np.linalg.norm(directions, axis=1, keepdims=True)
        return np.asarray(smpl.Th, np.float64) + BODY_RADIUS_M * directions

    def render(
        self, camera, smpl, time=None, *, background=(0, 0, 0), follow=False, depth=False
    ) -> RenderOut:
        start = _now()
        h, w = camera.height, camera.width
        image = np.empty((h, w, 3), np.uint8)
        image[:] = background
        alpha = np.zeros((h, w), np.uint8)
        u, v, depth = project(camera, smpl.Th)
        if depth > 1e-3:
            radius = camera.K[0, 0] * BODY_RADIUS_M / depth
            yy, xx = np.ogrid[:h, :w]
            inside = (xx + 0.5 - u) ** 2 + (yy + 0.5 - v) ** 2 <= radius**2
            image[inside] = np.clip(np.rint(self.color * 255), 0, 255).astype(np.uint8)
            alpha[inside] = 255
        return RenderOut(image=image, alpha=alpha, depth=None, render_ms=(_now() - start) * 1000)

    def points(self, smpl, time=None, *, camera_center=None) -> PointsOut:
        angles = np.linspace(0.0, 2 * np.pi, POINTS, endpoint=False)
        ring = np.stack([np.cos(angles), np.sin(angles), np.zeros_like(angles)], axis=1) * BODY_RADIUS_M
        color = np.clip(np.rint(self.color * 255), 0, 255).astype(np.uint8)
        return PointsOut(
            positions=(ring + np.asarray(smpl.Th, np.float64)).astype(np.float32),
            colors=np.tile(color, (POINTS, 1)),
            alpha=np.full(POINTS, 255, np.uint8),
        )


def _now() -> float:
    return time.perf_counter()
