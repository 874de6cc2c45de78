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
    def posed_points(
        self, smpl, time: float | None = None, *, min_opacity: float = 0.1, max_points: int = 4096
    ) -> np.ndarray:
        """(N, 3) world centres of Gaussians that show (opacity >= ``min_opacity``) in this pose, at
        most ``max_points`` of them (an even stride): what a camera must keep in view to show the
        avatar whole (stg_node.avatar.framing). Cheap: skins only the rows it returns."""
        from stg_node.avatar.rigid import blend_weights, skin

        model = self.model
        table = model.table
        u = self.time_for(smpl, time)
        state = model.spacetime(u, skip_inactive=True)
        opacity = table.opacities()
        if state.temporal is not None:
            opacity = opacity * state.temporal
        rows = (opacity >= min_opacity).nonzero().squeeze(1)
        if rows.numel() == 0:  # a blank model: every centre, so a camera can still be placed
            rows = torch.arange(table.num, device=self.device)
        if rows.numel() > max_points:
            rows = rows[torch.linspace(0, rows.numel() - 1, max_points, device=self.device).round().long()]
        means = table["means"][rows]
        if state.offsets is not None:
            means = means + state.offsets[rows]
        delta = table.get("skin_delta")
        weights = blend_weights(table["skin_weights"][rows], None if delta is None else delta[rows])
        bones = model.bones(BodyState.from_smpl(smpl, self.device))
        return skin(means, weights, bones, rotations=False).means.cpu().numpy().astype(np.float64)

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


def _now() -> float:
    return time.perf_counter()
