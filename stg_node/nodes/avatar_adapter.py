"""The only place the nodes call the avatar package (stg_node.avatar; API in AVATAR_API.md).

The trainer and renderer nodes hold a :class:`TrainerAdapter` / :class:`RendererAdapter` and
never touch the avatar's classes themselves, so a change in the avatar's API is a change here.
``module`` names the package that implements the API: ``stg_node.avatar`` in production, a
fake in the tests (tests/nodes/fake_avatar.py).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from stg_node.bus import GaussianSnapshot
from stg_node.data.types import Camera, SmplParams

DEFAULT_MODULE = "stg_node.avatar"


def avatar_module(name: str = DEFAULT_MODULE):
    try:
        return importlib.import_module(name)
    except ImportError as exc:
        raise RuntimeError(f"the avatar implementation {name!r} cannot be imported: {exc}") from exc


@dataclass(frozen=True)
class StepInfo:
    """One training step, as the trainer node publishes it."""

    iteration: int
    loss: float
    losses: dict[str, float]
    psnr: float
    num_gaussians: int
    it_per_s: float
    skipped: bool


@dataclass(frozen=True)
class RenderOutput:
    image: np.ndarray  # (H, W, 3) uint8
    alpha: np.ndarray | None  # (H, W) uint8
    depth: np.ndarray | None  # (H, W) float32
    render_ms: float


class TrainerAdapter:
    """Online training: frames in, steps, snapshots, checkpoints."""

    def __init__(self, trainer, module):
        self._trainer = trainer
        self._module = module

    @classmethod
    def create(
        cls,
        *,
        module: str = DEFAULT_MODULE,
        preset: str = "fast",
        body_model: str | None = None,
        device: str = "cpu",
        backend: str = "auto",
        seed: int = 0,
        max_frames: int = 64,
    ) -> TrainerAdapter:
        avatar = avatar_module(module)
        config = avatar.preset(preset)
        trainer = avatar.Trainer(
            config, body_model=body_model, device=device, backend=backend, seed=seed, max_frames=max_frames
        )
        return cls(trainer, avatar)

    @classmethod
    def load(
        cls, path: str | Path, *, module: str = DEFAULT_MODULE, device: str = "cpu", backend: str = "auto"
    ):
        avatar = avatar_module(module)
        return cls(avatar.Trainer.load(str(path), device=device, backend=backend), avatar)

    def add_frame(self, *, index: int, time: float, image, mask, camera: Camera, smpl: SmplParams) -> None:
        frame = self._module.TrainFrame(
            index=index, time=time, image=image, mask=mask, camera=camera, smpl=smpl
        )
        self._trainer.add_frame(frame)

    def step(self) -> StepInfo:
        r = self._trainer.step()
        return StepInfo(
            iteration=int(r.iteration),
            loss=float(r.loss),
            losses={str(k): float(v) for k, v in dict(r.losses).items()},
            psnr=float(r.psnr),
            num_gaussians=int(r.num_gaussians),
            it_per_s=float(r.it_per_s),
            skipped=bool(r.skipped),
        )

    def snapshot(self, version: int) -> GaussianSnapshot:
        msg = self._trainer.snapshot()
        msg.model_version = int(version)
        return msg

    def save(self, path: str | Path) -> None:
        self._trainer.save(str(path))

    def evaluate(self, data: str | Path) -> dict:
        """The current model on the held-out cameras of the dataset at ``data``: ``split``,
        ``views``, ``psnr``, ``ssim``, ``lpips`` (None when unavailable)."""
        evaluate = getattr(self._module, "evaluate_trainer", None)
        if evaluate is None:
            raise RuntimeError(f"the avatar implementation {self._module.__name__} cannot evaluate")
        report = dict(evaluate(self._trainer, str(data)))
        return {
            "split": str(report["split"]),
            "views": int(report["views"]),
            "psnr": float(report["psnr"]),
            "ssim": float(report["ssim"]),
            "lpips": None if report.get("lpips") is None else float(report["lpips"]),
        }


class RendererAdapter:
    """Renders one snapshot for any camera and pose."""

    def __init__(self, renderer, version: int):
        self._renderer = renderer
        self.version = version

    @classmethod
    def from_snapshot(
        cls,
        msg: GaussianSnapshot,
        *,
        module: str = DEFAULT_MODULE,
        device: str = "cpu",
        backend: str = "auto",
    ) -> RendererAdapter:
        avatar = avatar_module(module)
        return cls(
            avatar.AvatarRenderer.from_snapshot(msg, device=device, backend=backend), msg.model_version
        )

    def render(
        self, camera: Camera, smpl: SmplParams, time: float | None = None, background=(0, 0, 0)
    ) -> RenderOutput:
        out = self._renderer.render(camera, smpl, time=time, background=background)
        return RenderOutput(
            image=np.ascontiguousarray(out.image, dtype=np.uint8),
            alpha=None if out.alpha is None else np.ascontiguousarray(out.alpha, dtype=np.uint8),
            depth=None
            if getattr(out, "depth", None) is None
            else np.ascontiguousarray(out.depth, np.float32),
            render_ms=float(out.render_ms),
        )

    def posed_points(self, smpl: SmplParams, time: float | None = None) -> np.ndarray | None:
        """(N, 3) world points of the posed avatar (what a framing camera keeps in view), or None
        when the implementation cannot tell."""
        posed = getattr(self._renderer, "posed_points", None)
        if posed is None:
            return None
        points = np.asarray(posed(smpl, time), np.float64).reshape(-1, 3)
        return points if len(points) and np.all(np.isfinite(points)) else None
