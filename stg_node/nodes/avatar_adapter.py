"""The only place the nodes call the avatar package (stg_node.avatar; API in AVATAR_API.md).

The trainer and renderer nodes hold a :class:`TrainerAdapter` / :class:`RendererAdapter` and
never touch the avatar's classes themselves, so a change in the avatar's API is a change here.
``module`` names the package that implements the API: ``stg_node.avatar`` in production, a
fake in the tests (tests/nodes/fake_avatar.py).
"""

from __future__ import annotations

import dataclasses
import importlib
import inspect
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
        footage: bool = False,
        flow_level: int | None = None,
    ) -> TrainerAdapter:
        """``footage``: frames from a camera that sets its own exposure (the avatar's ``for_footage``
        settings, where the avatar package has them). ``flow_level``: the optical flow's finest
        pyramid level (None: the avatar package's default)."""
        avatar = avatar_module(module)
        # The frame store's bound lives in the config, the one thing a checkpoint keeps: a trainer
        # resumed from one is bounded as the one that wrote it.
        config = dataclasses.replace(avatar.preset(preset), max_frames=int(max_frames))
        if footage and hasattr(avatar, "for_footage"):
            config = avatar.for_footage(config)
        trainer = avatar.Trainer(
            config,
            body_model=body_model,
            device=device,
            backend=backend,
            seed=seed,
            **_flow(avatar.Trainer, flow_level),
        )
        return cls(trainer, avatar)

    @classmethod
    def load(
        cls,
        path: str | Path,
        *,
        module: str = DEFAULT_MODULE,
        device: str = "cpu",
        backend: str = "auto",
        flow_level: int | None = None,
    ):
        avatar = avatar_module(module)
        return cls(
            avatar.Trainer.load(
                str(path), device=device, backend=backend, **_flow(avatar.Trainer.load, flow_level)
            ),
            avatar,
        )

    @property
    def iteration(self) -> int:
        return int(self._trainer.iteration)

    @property
    def max_frames(self) -> int:
        """Frames the trainer keeps at most (0: no bound), as its config says."""
        return int(self._trainer.config.max_frames)

    @property
    def notes(self) -> dict[str, float]:
        """What :meth:`save` kept beside the model (the node's wall time), restored by :meth:`load`."""
        return dict(self._trainer.notes)

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

    def model_stats(self) -> dict[str, float]:
        """Figures of the model now (``active_motion_fraction``, ...) when the implementation
        reports them (``stats()``); numbers only."""
        stats = getattr(self._trainer, "stats", None)
        if stats is None:
            return {}
        return {str(k): float(v) for k, v in stats().items() if isinstance(v, (int, float))}

    def snapshot(self, version: int) -> GaussianSnapshot:
        msg = self._trainer.snapshot()
        msg.model_version = int(version)
        return msg

    def save(self, path: str | Path, notes: dict[str, float] | None = None) -> None:
        """A checkpoint at ``path`` holding ``notes`` too (one file: they cannot disagree)."""
        self._trainer.notes = {str(k): float(v) for k, v in (notes or {}).items()}
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


def _flow(fn, level: int | None) -> dict:
    """The flow keyword for ``fn`` at this pyramid level (none where it takes none or level is None)."""
    if level is None or not _accepts(fn, "flow_settings"):
        return {}
    from stg_node.data.flow import FlowSettings

    return {"flow_settings": FlowSettings(finest_scale=int(level))}


def _accepts(fn, name: str) -> bool:
    """Whether ``fn`` takes the keyword ``name`` (optional parts of the avatar API)."""
    try:
        return name in inspect.signature(fn).parameters
    except (TypeError, ValueError):
        return False


class RendererAdapter:
    """Renders one snapshot for any camera and pose."""

    def __init__(self, renderer, version: int):
        self._renderer = renderer
        self.version = version
        self._streams = _accepts(renderer.render, "stream")

    @classmethod
    def from_snapshot(
        cls,
        msg: GaussianSnapshot,
        *,
        module: str = DEFAULT_MODULE,
        device: str = "cpu",
        backend: str = "auto",
        color_refresh_every: int = 1,
        light: str = "learned",
    ) -> RendererAdapter:
        avatar = avatar_module(module)
        load = avatar.AvatarRenderer.from_snapshot
        options = {}
        if _accepts(load, "color_refresh_every"):
            options["color_refresh_every"] = color_refresh_every
        if light != "learned":  # the default needs nothing of a plug-in avatar package
            from stg_node.avatar.shading import parse_light

            options["light"] = parse_light(light)
        return cls(load(msg, device=device, backend=backend, **options), msg.model_version)

    def render(
        self,
        camera: Camera,
        smpl: SmplParams,
        time: float | None = None,
        background=(0, 0, 0),
        stream: str | None = None,
    ) -> RenderOutput:
        """``stream`` names a live stream (one camera following the body) whose colours the avatar
        may carry between frames; None (one-shot requests) renders exactly."""
        extra = {"stream": stream} if self._streams and stream is not None else {}
        out = self._renderer.render(camera, smpl, time=time, background=background, **extra)
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

    def points(
        self, smpl: SmplParams, time: float | None = None, camera_center=None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The posed avatar as coloured points: positions (N, 3) float32 world, colours (N, 3)
        uint8, opacities (N,) uint8; None when the implementation has no ``points``."""
        points = getattr(self._renderer, "points", None)
        if points is None:
            return None
        out = points(smpl, time=time, camera_center=camera_center)
        return (
            np.ascontiguousarray(out.positions, np.float32).reshape(-1, 3),
            np.ascontiguousarray(out.colors, np.uint8).reshape(-1, 3),
            np.ascontiguousarray(out.alpha, np.uint8).reshape(-1),
        )
