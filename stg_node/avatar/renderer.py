"""Rendering a trained avatar in any camera, pose and time: what stg-eval, stg-render and the
renderer node call.

Built from a model or straight from a GaussianSnapshot (the renderer node hot-swaps those).
Without a time the pose's time code comes from the nearest training pose (timecode.py); with
``follow`` state kept between calls, an animation keeps its time code stable (hysteresis). A pose
without a time that is beyond the index's reach (farther from every training pose than training
poses adjacent in time are from each other) has no training instant whose garment state stands for
it (timecode.py): from twice the reach on (timecode.FADE_END) it renders the model's mean
placement, its rigid part (nonrigid.rigid_part), and between the two the instant's non-rigid part
fades out with the distance (PoseTimeIndex.trust, nonrigid.faded_state), in the same one render,
so an animation crossing the reach changes continuously instead of popping.
Rendering runs without gradients, evaluates the motion terms only on the rows that move (found
once per model state, AvatarModel._render_spacetime), and colours only the Gaussians the camera
can see. A live
stream (``render(..., stream=name)``: one camera following one body, frame after frame) can carry
its colours from frame to frame and recompute them in turns (``color_refresh_every``;
color_cache.py); a render without a stream is always exact.
A model with shading is lit by its learned light (fixed in the world), by a light the caller gives,
with the light carried along with the body (``baked``), or not at all (``albedo``): :mod:`shading`.
"""

from __future__ import annotations

import time
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
import torch

from stg_node.avatar.color_cache import ColorCache
from stg_node.avatar.model import AvatarModel, BodyState, Camera3, render
from stg_node.avatar.nonrigid import faded_state, mean_offsets, rigid_part
from stg_node.avatar.shading import LightSpec
from stg_node.avatar.spacetime import SpacetimeState


@dataclass
class RenderOutput:
    image: np.ndarray  # (H, W, 3) uint8 RGB
    alpha: np.ndarray  # (H, W) uint8
    depth: np.ndarray | None  # (H, W) float32 metres (0 where alpha is 0), when asked
    render_ms: float  # pose + splat, wall time
    time_u: float  # the normalised time rendered
    num_rendered: int  # Gaussians that reached the rasterizer


MAX_STREAMS = 8  # colour caches kept per renderer (the least recently used goes first)


@dataclass
class PointsOutput:
    positions: np.ndarray  # (N, 3) float32 world centres of the Gaussians kept (opacity >= ALPHA_MIN)
    colors: np.ndarray  # (N, 3) uint8 RGB, as seen from the camera centre given
    alpha: np.ndarray  # (N,) uint8 opacity (temporal opacity included)


class AvatarRenderer:
    def __init__(
        self,
        model: AvatarModel,
        *,
        backend: str = "auto",
        color_refresh_every: int = 1,
        light: LightSpec | None = None,
    ):
        if int(color_refresh_every) < 1:
            raise ValueError(f"color_refresh_every must be >= 1, got {color_refresh_every}")
        self.model = model.eval()
        self.backend = backend
        self.color_refresh_every = int(color_refresh_every)
        self.light = light  # None: the model's learned light (shading.py)
        self._last_key: int | None = None
        # (model, its rigid part, the rows that part keeps, its mean offsets): on first use
        self._mean: tuple[AvatarModel, AvatarModel, torch.Tensor, torch.Tensor] | None = None
        self._streams: OrderedDict[str, ColorCache] = OrderedDict()
        # The model evaluates the motion terms of the moving rows only unless most rows move; on a
        # CPU the dense terms are then cheaper than the index bookkeeping (docs/BENCHMARKS.md, "Live
        # rate"), on a GPU the subset is taken whatever its size.
        self.skip_inactive = self.device.type != "cpu"

    @classmethod
    def from_snapshot(
        cls,
        msg,
        device="cpu",
        backend: str = "auto",
        color_refresh_every: int = 1,
        light: LightSpec | None = None,
    ) -> AvatarRenderer:
        from stg_node.avatar.snapshot import model_from_snapshot

        return cls(
            model_from_snapshot(msg, device=device),
            backend=backend,
            color_refresh_every=color_refresh_every,
            light=light,
        )

    def _color_cache(self, stream: str | None) -> ColorCache | None:
        # The cache saves the MLP's arithmetic, which a CPU pays for; on a GPU its gathers and
        # scatters cost more launches than the MLP they save (docs/BENCHMARKS.md, "On a GPU").
        if stream is None or self.color_refresh_every == 1 or self.device.type != "cpu":
            return None
        cache = self._streams.pop(stream, None) or ColorCache(self.color_refresh_every)
        self._streams[stream] = cache
        while len(self._streams) > MAX_STREAMS:
            self._streams.popitem(last=False)
        return cache

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

    def model_for(self, smpl, time_s: float | None, u: float) -> tuple[AvatarModel, SpacetimeState | None]:
        """(model, spacetime terms or None: the model's own at ``u``) that render ``smpl``: the avatar
        (a time given, or a pose within the pose index's reach), its rigid part (the mean placement)
        for a pose without a time from ``FADE_END`` reaches on, the avatar with its terms at ``u``
        faded toward that part between the two (module docstring)."""
        model = self.model
        if time_s is not None or not model.config.spacetime:
            return model, None
        weight = model.pose_index.trust(np.asarray(smpl.poses))
        if weight == 1.0:
            return model, None
        if self._mean is None or self._mean[0] is not model:
            rigid, keep = rigid_part(model)
            self._mean = (model, rigid.eval(), keep, mean_offsets(model))
        _, rigid, keep, offsets = self._mean
        if weight == 0.0:
            return rigid, None
        state = model.spacetime(u, skip_inactive=True)
        return model, faded_state(model, state, weight, keep, offsets)

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
        stream: str | None = None,
        light: LightSpec | None = None,
    ) -> RenderOutput:
        """Render ``smpl`` (SmplParams) seen by ``camera`` (stg_node.data.types.Camera) at ``time`` (s).

        ``stream`` names a live stream whose colours may be carried between frames (see the
        module docstring); None renders exactly. ``light`` overrides the renderer's light for this
        render."""
        started = _now()
        u = self.time_for(smpl, time, follow=follow)
        model, state = self.model_for(smpl, time, u)
        cam = Camera3.from_camera(camera, device=self.device)
        body = BodyState.from_smpl(smpl, self.device)
        posed = model.pose(
            body,
            u,
            cam.center,
            skip_inactive=self.skip_inactive,
            state=state,
            camera=cam,
            color_cache=self._color_cache(stream) if model is self.model and state is None else None,
            light=light or self.light,
        )
        bg = torch.as_tensor(background, dtype=torch.float32, device=self.device)
        if not bool(bg.any()):  # black: nothing to blend
            bg = None
        image, alpha, info = render(posed, cam, background=bg, backend=self.backend, render_depth=depth)
        out_depth = None
        if depth:
            d = info["depth"][..., 0]
            out_depth = (
                torch.where(alpha[..., 0] > 0, d, torch.zeros_like(d)).cpu().numpy().astype(np.float32)
            )
        img = _to_uint8(image)
        a = _to_uint8(alpha[..., 0])
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
        model, state = self.model_for(smpl, time, u)
        posed = model.pose(body, u, center, skip_inactive=self.skip_inactive, state=state)
        return PointsOutput(
            positions=posed.means.cpu().numpy().astype(np.float32),
            colors=_to_uint8(posed.colors),
            alpha=_to_uint8(posed.opacities.reshape(-1)),
        )


_CONVERT_SLICE = 1 << 18  # floats (1 MB): every pass of a slice's conversion stays in the caches


def _to_uint8(values: torch.Tensor) -> np.ndarray:
    """[0, 1] floats -> uint8 levels, rounded; ``values`` is left as it was.

    On a CPU in cache-sized slices: the four passes (scale, round, clamp, narrow) over a whole
    2048x2048 frame went to memory each time (31 ms; 7 ms in slices, the same levels)."""
    if values.device.type != "cpu":
        return values.mul(255.0).add_(0.5).clamp_(0.0, 255.0).to(torch.uint8).cpu().numpy()
    flat = values.reshape(-1)
    out = torch.empty(flat.shape, dtype=torch.uint8)
    for start in range(0, flat.numel(), _CONVERT_SLICE):
        part = flat[start : start + _CONVERT_SLICE].mul(255.0)
        out[start : start + _CONVERT_SLICE].copy_(part.add_(0.5).clamp_(0.0, 255.0))
    return out.reshape(values.shape).numpy()


def _now() -> float:
    return time.perf_counter()
