"""Rendering a trained avatar in any camera, pose and time: what stg-eval, stg-render and the
renderer node call.

Built from a model or straight from a GaussianSnapshot (the renderer node hot-swaps those).
Without a time the pose's time code comes from the nearest training pose (timecode.py); with
``follow`` state kept between calls, an animation keeps its time code stable (hysteresis).
Rendering runs without gradients and skips motion terms that are exactly zero.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from stg_node.avatar.model import AvatarModel, BodyState, Camera3, render


@dataclass
class RenderOutput:
    image: np.ndarray  # (H, W, 3) uint8 RGB
    alpha: np.ndarray  # (H, W) uint8
    depth: np.ndarray | None  # (H, W) float32 metres (0 where alpha is 0), when asked
    render_ms: float  # pose + splat, wall time
    time_u: float  # the normalised time rendered
    num_rendered: int  # Gaussians that reached the rasterizer


@dataclass
class PointsOutput:
    positions: np.ndarray  # (N, 3) float32 world centres of the Gaussians kept (opacity >= ALPHA_MIN)
    colors: np.ndarray  # (N, 3) uint8 RGB, as seen from the camera centre given
    alpha: np.ndarray  # (N,) uint8 opacity (temporal opacity included)


class AvatarRenderer:
    def __init__(self, model: AvatarModel, *, backend: str = "auto"):
        self.model = model.eval()
        self.backend = backend
        self._last_key: int | None = None

    @classmethod
    def from_snapshot(cls, msg, device="cpu", backend: str = "auto") -> AvatarRenderer:
        from stg_node.avatar.snapshot import model_from_snapshot

        return cls(model_from_snapshot(msg, device=device), backend=backend)

    @property
    def device(self) -> torch.device:
        return self.model.device

    def time_for(self, smpl, time_s: float | None, *, follow: bool = False) -> float:
        """Normalised time: the given one, or the novel-pose rule (stable along a sequence with follow)."""
        if time_s is not None:
            return self.model.time_axis(time_s)
        previous = self._last_key if follow else None
        u, key = self.model.pose_index.time_for(np.asarray(smpl.poses), previous)
        if follow:
            self._last_key = key
        return u

    @torch.no_grad()
    def render(
        self,
        camera,
        smpl,
        time: float | None = None,
        *,
        background=(0.0, 0.0, 0.0),
        follow: bool = False,
        depth: bool = False,
    ) -> RenderOutput:
        """Render ``smpl`` (SmplParams) seen by ``camera`` (stg_node.data.types.Camera) at ``time`` (s)."""
        started = _now()
        u = self.time_for(smpl, time, follow=follow)
        cam = Camera3.from_camera(camera, device=self.device)
        body = BodyState.from_smpl(smpl, self.device)
        posed = self.model.pose(body, u, cam.center, skip_inactive=True)
        bg = torch.as_tensor(background, dtype=torch.float32, device=self.device)
        image, alpha, info = render(posed, cam, background=bg, backend=self.backend, render_depth=depth)
        out_depth = None
        if depth:
            d = info["depth"][..., 0]
            out_depth = (
                torch.where(alpha[..., 0] > 0, d, torch.zeros_like(d)).cpu().numpy().astype(np.float32)
            )
        img = (image.clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).cpu().numpy()
        a = (alpha[..., 0].clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).cpu().numpy()
        return RenderOutput(img, a, out_depth, (_now() - started) * 1e3, u, int(posed.means.shape[0]))

    @torch.no_grad()
    def points(self, smpl, time: float | None = None, *, camera_center=None) -> PointsOutput:
        """The Gaussians posed as :meth:`render` poses them, as coloured points (what a 3D viewer,
        the foxglove node's point cloud, shows). ``camera_center`` (world, metres; default 3 m
        along +z from the root) picks the viewing direction of view-dependent colours."""
        u = self.time_for(smpl, time)
        body = BodyState.from_smpl(smpl, self.device)
        if camera_center is None:
            camera_center = np.asarray(smpl.Th, np.float64).reshape(3) + np.array([0.0, 0.0, 3.0])
        center = torch.as_tensor(np.asarray(camera_center, np.float32).reshape(3), device=self.device)
        posed = self.model.pose(body, u, center, skip_inactive=True)

        def u8(t: torch.Tensor) -> np.ndarray:
            return (t.clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).cpu().numpy()

        return PointsOutput(
            positions=posed.means.cpu().numpy().astype(np.float32),
            colors=u8(posed.colors),
            alpha=u8(posed.opacities.reshape(-1)),
        )


def _now() -> float:
    return time.perf_counter()
