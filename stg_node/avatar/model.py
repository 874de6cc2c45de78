"""The STG-Avatar model: Gaussian table + rigid LBS + spacetime terms + colour, composed.

``AvatarModel.pose(...)`` turns the canonical table into world-space Gaussians for one body
pose and one instant (rigid part: :mod:`rigid`; non-rigid part: :mod:`spacetime`; colour:
:mod:`color`, then the light it is seen under: :mod:`shading`), and :func:`render` splats them
into a camera through ``stg_node.splat``.
Everything a renderer needs lives in the model (the skeleton, not the body mesh), so
:mod:`snapshot` can rebuild it from a GaussianSnapshot alone.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from stg_node.avatar import kernels, kinematics, spacetime
from stg_node.avatar.color import ColorMLP, sh_color
from stg_node.avatar.color_cache import ColorCache, TrainingColorTurns
from stg_node.avatar.config import ModelConfig
from stg_node.avatar.gaussians import MOTION_COLUMNS, GaussianTable
from stg_node.avatar.motion_basis import MotionBases
from stg_node.avatar.rigid import (
    QUAT_EPS,
    PosedBones,
    Skeleton,
    blend_weights,
    joint_shrink,
    skin,
    skin_with_kernel,
    squeeze_of_blend,
)
from stg_node.avatar.scale_ops import capped_scales
from stg_node.avatar.shading import LightSpec, Shading, gaussian_normals
from stg_node.avatar.spacetime import TimeAxis
from stg_node.avatar.timecode import PoseTimeIndex, pose_key
from stg_node.body import lbs
from stg_node.splat import rasterize
from stg_node.splat.constants import ALPHA_MIN
from stg_node.splat.culling import may_be_visible


@dataclass
class BodyState:
    """One frame's body parameters as tensors: poses (1, 24, 3), Rh (1, 3), Th (1, 3)."""

    poses: torch.Tensor
    Rh: torch.Tensor
    Th: torch.Tensor

    @classmethod
    def from_smpl(cls, smpl, device="cpu") -> BodyState:
        def t(a, shape):
            return torch.as_tensor(np.array(a, np.float32), device=device).reshape(
                shape
            )  # a copy: bus arrays are read-only

        return cls(t(smpl.poses, (1, 24, 3)), t(smpl.Rh, (1, 3)), t(smpl.Th, (1, 3)))


@dataclass
class PosedGaussians:
    """World-space Gaussians ready for the rasterizer (rows: the Gaussians kept, see ``index``)."""

    means: torch.Tensor  # (M, 3) world
    quats: torch.Tensor  # (M, 4) wxyz world
    scales: torch.Tensor  # (M, 3)
    opacities: torch.Tensor  # (M,) including temporal opacity
    colors: torch.Tensor  # (M, 3)
    index: torch.Tensor | None  # (M,) rows of the table, or None when every row is kept
    canonical: torch.Tensor | None = None  # (M, 3) canonical centres (with offsets) the means came from
    next_means: torch.Tensor | None = None  # (M, 3) world centres at the pose's next_frame (if asked)


@dataclass
class Camera3:
    """A camera as the rasterizer takes it."""

    viewmat: torch.Tensor  # (4, 4) world -> camera
    K: torch.Tensor  # (3, 3)
    width: int
    height: int

    @classmethod
    def from_camera(cls, camera, crop: tuple[int, int, int, int] | None = None, device="cpu") -> Camera3:
        """From a stg_node.data.types.Camera; ``crop`` = (x0, y0, w, h) renders only that window."""
        K = np.array(camera.K, np.float64, copy=True)
        width, height = int(camera.width), int(camera.height)
        if crop is not None:
            x0, y0, width, height = crop
            K[0, 2] -= x0
            K[1, 2] -= y0
        view = np.eye(4)
        view[:3, :3] = camera.R
        view[:3, 3] = np.asarray(camera.t).reshape(3)
        return cls(
            torch.as_tensor(view, dtype=torch.float32, device=device),
            torch.as_tensor(K, dtype=torch.float32, device=device),
            width,
            height,
        )

    @property
    def center(self) -> torch.Tensor:
        R, t = self.viewmat[:3, :3], self.viewmat[:3, 3]
        return -(R.T @ t)

    def project(self, points: torch.Tensor) -> torch.Tensor:
        """Pixel coordinates ``(N, 2)`` of world points (no culling)."""
        cam = points @ self.viewmat[:3, :3].T + self.viewmat[:3, 3]
        pix = cam @ self.K.T
        return pix[:, :2] / pix[:, 2:3].clamp_min(1e-6)

    def motion(self, points: torch.Tensor, next_points: torch.Tensor) -> torch.Tensor:
        """``project(next_points) - project(points)`` (N, 2): where the kernels run, in one fused pass
        (stg_node.splat.skin_ops.pixel_motion, its backward written out), else torch (the reference)."""
        fixed = not (self.viewmat.requires_grad or self.K.requires_grad)
        if fixed and kernels.use_kernels(points, next_points, self.viewmat, self.K):
            from stg_node.splat import skin_ops

            return skin_ops.pixel_motion(points, next_points, self.viewmat, self.K)
        return self.project(next_points) - self.project(points)


def quat_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product of wxyz quaternions ``a * b`` (rotation b, then a)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        dim=-1,
    )


def conjugate(q: torch.Tensor) -> torch.Tensor:
    return q * torch.tensor([1.0, -1.0, -1.0, -1.0], dtype=q.dtype, device=q.device)


def rotate(q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Rotate vectors ``v (N, 3)`` by unit quaternions ``q (N, 4)``: ``v + 2 w (u x v) + 2 u x (u x v)``."""
    w, u = q[:, :1], q[:, 1:]
    uv = torch.linalg.cross(u, v)
    return v + 2.0 * (w * uv + torch.linalg.cross(u, uv))


def _normalise(q: torch.Tensor) -> torch.Tensor:
    norm = q.norm(dim=-1, keepdim=True)
    identity = torch.zeros_like(q)
    identity[..., 0] = 1.0
    return torch.where(norm > QUAT_EPS, q / norm.clamp_min(QUAT_EPS), identity)


class AvatarModel(nn.Module):
    def __init__(
        self,
        config: ModelConfig,
        table: GaussianTable,
        skeleton: Skeleton,
        bounds: torch.Tensor,
        time_axis: TimeAxis | None = None,
        pose_index: PoseTimeIndex | None = None,
    ):
        super().__init__()
        config.validate()
        # names this model in colour caches: the key holds it, so unlike id() it cannot be taken by
        # another model once this one is freed, and a copy (deepcopy, pickle) gets its own
        self.cache_token = object()
        self.config = config
        self.table = table
        self.skeleton = skeleton
        self.register_buffer("bounds", bounds.float().clone())  # (2, 3) canonical body box
        self.color_mlp = ColorMLP(config, bounds) if config.color == "mlp" else None
        self.shading = (
            Shading(config.light_model, config.light_count, config.occlusion) if config.shading else None
        )
        self.time_axis = time_axis or TimeAxis(unit_s=config.time_unit_s)
        self.pose_index = pose_index or PoseTimeIndex()
        self.motion_bases = (
            MotionBases(config.n_b, config.basis_knot_s / self.time_axis.unit_s) if config.n_b else None
        )
        self._skin_weight_cache: tuple | None = None  # (key, weights): see _render_skin_weights
        self._moving_rows_cache: tuple | None = None  # (key, rows): see _render_spacetime
        self._scale_cache: tuple | None = None  # (key, scales): see _render_scales
        self._bone_cache: tuple | None = None  # (key, bones): see _dominant_bones

    @property
    def device(self) -> torch.device:
        return self.table["means"].device

    @property
    def extent(self) -> float:
        """Size of the body (diagonal of its canonical box, metres): the scale of 'large' and 'small'."""
        return float((self.bounds[1] - self.bounds[0]).norm())

    def skin_weights(self) -> torch.Tensor:
        return blend_weights(self.table["skin_weights"], self.table.get("skin_delta"))

    def _render_skin_weights(self) -> torch.Tensor | None:
        """The effective skinning weights without gradient, computed once for a model that does not
        change (a renderer's): frames then skin without redoing the correction. None while
        gradients are on."""
        if torch.is_grad_enabled():
            return None
        columns = [self.table["skin_weights"], self.table.get("skin_delta")]
        # the table's version (bumped by every row edit), never id() of a column: a column replaced
        # by a prune and an append may be a new tensor where the freed one was
        key = (self.table.version, *((c._version, c.shape[0]) for c in columns if c is not None))
        cached = self._skin_weight_cache
        if cached is None or cached[0] != key:
            cached = (key, self.skin_weights().detach())
            self._skin_weight_cache = cached
        return cached[1]

    def _render_spacetime(self, u: float, skip_inactive: bool) -> spacetime.SpacetimeState:
        """:meth:`spacetime` without gradient (a renderer's frames), the same terms: the rows that
        move and those with a finite temporal window are found once for a model that does not
        change, not every frame (that search cost more than the terms on a CPU). Only those rows are
        evaluated (every other row's offset is exactly zero, its rotation its own, its temporal
        factor exactly 1) unless most rows move, where the dense evaluation is cheaper."""
        table = self.table
        columns = [table.get(name) for name in (*MOTION_COLUMNS, "t_log_scale")]
        key = (table.version, *((c._version, c.shape[0]) for c in columns if c is not None))
        cached = self._moving_rows_cache
        if cached is None or cached[0] != key:
            moving = table.motion_active().nonzero().squeeze(1)
            log_scale = table.get("t_log_scale")
            windowed = None
            if log_scale is not None:
                windowed = (log_scale.detach().exp() < spacetime.PERSISTENT_SCALE).nonzero().squeeze(1)
            cached = (key, moving, windowed)
            self._moving_rows_cache = cached
        _, moving, windowed = cached
        dense = not skip_inactive and 2 * moving.numel() > table.num
        cfg = self.config
        return spacetime.evaluate(
            table,
            u,
            cfg.time_horizon,
            temporal_opacity=cfg.uses_temporal_opacity,
            bases=self.motion_bases,
            rows=None if dense else moving,
            windowed=windowed,
        )

    def scales(self) -> torch.Tensor:
        """(N, 3) the Gaussians' scales as rendered: the table's, largest / smallest axis capped."""
        return capped_scales(self.table["log_scales"], self.config.max_scale_ratio)

    def _render_scales(self) -> torch.Tensor:
        """:meth:`scales` computed once for a model that does not change (a renderer's frames);
        while gradients are on, every call (training differentiates them)."""
        if torch.is_grad_enabled():
            return self.scales()
        column = self.table["log_scales"]
        key = (self.table.version, column._version, column.shape[0], self.config.max_scale_ratio)
        cached = self._scale_cache
        if cached is None or cached[0] != key:
            cached = (key, self.scales().detach())
            self._scale_cache = cached
        return cached[1]

    def _dominant_bones(self) -> torch.Tensor:
        """(N,) each Gaussian's largest body skinning weight's bone (the occlusion term's own bone),
        found once per change of the table, not every frame (an argmax over (N, 24))."""
        column = self.table["skin_weights"]
        key = (self.table.version, column._version, column.shape[0])
        cached = self._bone_cache
        if cached is None or cached[0] != key:
            cached = (key, column.detach().argmax(dim=1))
            self._bone_cache = cached
        return cached[1]

    def bones(self, body: BodyState) -> PosedBones:
        return self.skeleton.bones(body.poses, body.Rh, body.Th)

    # --- deformation ---------------------------------------------------------------------------
    def spacetime(
        self, u: float, *, skip_inactive: bool = False, rows: torch.Tensor | None = None
    ) -> spacetime.SpacetimeState:
        """The spacetime terms of every Gaussian at normalised time ``u`` (None where a term is off;
        ``rows``/``skip_inactive``: see spacetime.evaluate)."""
        cfg = self.config
        return spacetime.evaluate(
            self.table,
            u,
            cfg.time_horizon,
            temporal_opacity=cfg.uses_temporal_opacity,
            skip_inactive=skip_inactive,
            bases=self.motion_bases,
            rows=rows,
        )

    def posed_means(
        self,
        bones: PosedBones,
        u: float,
        rows: torch.Tensor | None = None,
        state: spacetime.SpacetimeState | None = None,
    ) -> torch.Tensor:
        """World centres only (cheap: the flow loss and densification need the next frame's);
        ``rows``: the rows whose motion terms are evaluated (see spacetime.evaluate); ``state``: the
        spacetime terms at ``u`` when the caller has them already (then ``rows`` is not used)."""
        st = state or spacetime.evaluate(
            self.table,
            u,
            self.config.time_horizon,
            temporal_opacity=False,
            bases=self.motion_bases,
            rows=rows,
        )
        means = self.table["means"] if st.offsets is None else self.table["means"] + st.offsets
        fused = skin_with_kernel(
            means, self.table["skin_weights"], self.table.get("skin_delta"), bones, rotations=False
        )
        if fused is not None:
            return fused.means
        return skin(means, self.skin_weights(), bones, rotations=False).means

    def pose(
        self,
        body: BodyState,
        u: float,
        camera_center: torch.Tensor,
        *,
        sh_degree: int | None = None,
        skip_inactive: bool = False,
        cull_transparent: bool = True,
        bones: PosedBones | None = None,
        key: torch.Tensor | None = None,
        state: spacetime.SpacetimeState | None = None,
        camera: Camera3 | None = None,
        color_cache: ColorCache | None = None,
        light: LightSpec | None = None,
        color_turns: tuple[TrainingColorTurns, int] | None = None,
        next_frame: tuple[PosedBones, spacetime.SpacetimeState] | None = None,
        outward_normals: bool = False,
    ) -> PosedGaussians:
        """World-space Gaussians for one body pose at normalised time ``u``, seen from ``camera_center``.

        ``camera``: leave out the Gaussians it cannot see (splat.culling) before they are coloured.
        ``color_cache``: colours of a live stream, recomputed in turns (color_cache.py; rendering
        only, ignored when gradients are on).
        ``light``: how a model with shading is lit (default: its learned light, shading.py).
        ``color_turns``: (turns, iteration) in training: the colour MLP on this step's turn of the
        rows only, the others' colours carried (color_cache.TrainingColorTurns).
        ``next_frame``: (bones, spacetime terms) of another frame whose centres of the same rows are
        wanted too (``PosedGaussians.next_means``: the flow loss's next frame, as :meth:`posed_means`
        gives them): skinned in the same kernel pass, the weights computed once.

        ``outward_normals``: shading normals keep the side the disc initialisation gave them
        (shading.outward_normals; the trainer's choice, ``model.normal_sign``); else every normal
        faces the camera (renders)."""
        cfg = self.config
        table = self.table
        bones = bones or self.bones(body)
        if state is not None:
            st = state
        elif torch.is_grad_enabled():
            st = self.spacetime(u, skip_inactive=skip_inactive)
        else:
            st = self._render_spacetime(u, skip_inactive)
        opacity = table.opacities()
        if st.temporal is not None:
            opacity = opacity * st.temporal
        index = None
        if cull_transparent:
            keep = opacity.detach() >= ALPHA_MIN
            if not bool(keep.all()):
                index = keep.nonzero().squeeze(1)

        def rows(t):  # index_select: t[index]'s rows, a cheaper gather (and an index_add backward)
            return t if index is None or t is None else t.index_select(0, index)

        canonical = table["means"] if st.offsets is None else table["means"] + st.offsets
        canonical = rows(canonical)
        next_canonical = None
        if next_frame is not None:
            next_offsets = next_frame[1].offsets
            if next_offsets is None and st.offsets is None:
                next_canonical = canonical  # the same centres: the kernel reads them once
            else:
                next_canonical = rows(
                    table["means"] if next_offsets is None else table["means"] + next_offsets
                )
        # the joint squeeze from the skinning kernel's blend where the kernel runs (training too: the
        # torch factor re-blended every row's 24 weights, ~5 % of a step, to agree to float rounding)
        squeeze_from_kernel = cfg.joint_shrink
        means, quats, view_canonical, blend_norm2, next_means = self._skin(
            canonical,
            bones,
            rows(st.quats),
            camera_center,
            rows,
            blend_norms=squeeze_from_kernel,
            next_frame=None if next_frame is None else (next_frame[0], next_canonical),
        )
        scales = rows(self._render_scales())
        if blend_norm2 is not None:
            scales = scales * squeeze_of_blend(blend_norm2)[:, None]
        elif cfg.joint_shrink:
            weights = self._render_skin_weights()
            with torch.no_grad():  # the squeeze takes no gradient: no graph over (N, 24) weights
                weights = rows(self.skin_weights() if weights is None else weights)
            scales = scales * joint_shrink(weights, bones)[:, None]
        if camera is not None:  # what the camera cannot see needs no colour
            seen = may_be_visible(means, scales, camera.viewmat, camera.K, camera.width, camera.height)
            if not bool(seen.all()):
                keep = seen.nonzero().squeeze(1)
                index = keep if index is None else index[keep]
                canonical, means, quats, view_canonical, scales = (
                    t.index_select(0, keep) for t in (canonical, means, quats, view_canonical, scales)
                )
                next_means = None if next_means is None else next_means.index_select(0, keep)
        degree = cfg.sh_degree if sh_degree is None else min(sh_degree, cfg.sh_degree)
        if self.color_mlp is not None:
            if body.poses.requires_grad:  # pose refinement: keep the pose code differentiable
                joints = body.poses[0, 1:]
                uses_numpy = kernels.mode() != "torch" and joints.device.type == "cpu"
                mats = (
                    kinematics.rotation_matrices(joints) if uses_numpy else lbs.axis_angle_to_matrix(joints)
                )
                key = mats.reshape(1, 23 * 9)
            elif key is None:
                key = torch.as_tensor(pose_key(body.poses.detach().cpu().numpy()), device=self.device)
            features = rows(table["features"])

            def evaluate(sel):
                if sel is None:
                    return self.color_mlp(canonical, features, key, view_canonical, degree)
                # index_select: the same rows as t[sel], a cheaper gather (and an index_add backward)
                # than advanced indexing on a CPU
                means, feats, view = (t.index_select(0, sel) for t in (canonical, features, view_canonical))
                return self.color_mlp(means, feats, key, view, degree)

            if color_cache is not None and not torch.is_grad_enabled():
                versions = (table["features"]._version, *(p._version for p in self.color_mlp.parameters()))
                colors = color_cache.colors(evaluate, index, table.num, (self.cache_token, degree, versions))
            elif color_turns is not None and torch.is_grad_enabled():
                turns, iteration = color_turns
                rows_key = (self.cache_token, degree, table.version)
                colors = turns.colors(evaluate, index, table.num, iteration, rows_key)
            else:
                colors = evaluate(None)
        else:
            colors = sh_color(rows(table["sh"]), view_canonical, degree)
        if self.shading is not None:
            outward = outward_normals and cfg.init_flatness < 1.0  # only discs know their side
            normals = gaussian_normals(quats, scales, means, camera_center, outward)
            root = None
            if light is not None and light.mode == "baked":
                root = lbs.axis_angle_to_matrix(body.Rh[0]) @ lbs.axis_angle_to_matrix(body.poses[0, 0])
            visible = None
            if self.shading.occlusion is not None:  # what the posed body casts on each Gaussian
                bone = self._dominant_bones()
                visible = self.shading.occlusion.visibility(
                    means, normals, bone if index is None else bone[index], bones.transforms[0]
                )
            away = None  # discs seen from behind: their shade must not teach the light (shading.py)
            if outward:
                away = (normals.detach() * (camera_center.reshape(1, 3) - means).detach()).sum(dim=1) < 0
            colors = self.shading(colors, normals, light, root, visible, away)
        return PosedGaussians(means, quats, scales, rows(opacity), colors, index, canonical, next_means)

    def _skin(
        self,
        canonical,
        bones: PosedBones,
        local_quats,
        camera_center,
        rows,
        blend_norms=False,
        next_frame=None,
    ):
        """Posed centres, orientations (blended bones x local rotation), the viewing direction in
        each Gaussian's canonical frame (no gradient), with ``blend_norms`` where the kernel runs the
        squared norms of the blended bone quaternions (else None) and, given ``next_frame`` (bones,
        canonical centres), the centres under that frame's bones (else None): the fused kernel, or
        torch (the reference)."""
        table = self.table
        effective = self._render_skin_weights()
        next_bones, next_canonical = next_frame if next_frame is not None else (None, None)
        fused = skin_with_kernel(
            canonical,
            rows(table["skin_weights"] if effective is None else effective),
            rows(table.get("skin_delta")) if effective is None else None,
            bones,
            local_quats=local_quats,
            camera_center=camera_center,
            blend_norms=blend_norms,
            next_bones=next_bones,
            next_means=None if next_canonical is canonical else next_canonical,
        )
        if fused is not None:
            return fused.means, fused.quats, fused.view_dirs, fused.blend_norm2, fused.next_means
        weights = rows(self.skin_weights())
        skinned = skin(canonical, weights, bones)
        quats = quat_multiply(skinned.quats, _normalise(local_quats))
        with torch.no_grad():
            view = skinned.means - camera_center
            view = view / view.norm(dim=1, keepdim=True).clamp_min(1e-9)
            view_canonical = rotate(conjugate(skinned.quats), view)
        next_means = None
        if next_bones is not None:
            next_means = skin(next_canonical, weights, next_bones, rotations=False).means
        return skinned.means, quats, view_canonical, None, next_means


def render(
    posed: PosedGaussians,
    camera: Camera3,
    *,
    background=None,
    backend: str = "auto",
    extra_channels: torch.Tensor | None = None,
    render_depth: bool = False,
):
    """Splat posed Gaussians; ``extra_channels`` (N_table or M, C) are blended along with RGB."""
    colors = posed.colors
    if extra_channels is not None:
        if posed.index is not None and extra_channels.shape[0] != colors.shape[0]:
            extra_channels = extra_channels[posed.index]
        colors = torch.cat([colors, extra_channels], dim=1)
    black = isinstance(background, (int, float)) and background == 0  # rasterize skips its blend
    if background is not None and extra_channels is not None and not black:
        bg = torch.as_tensor(background, dtype=colors.dtype, device=colors.device).reshape(-1)
        if bg.numel() == 1:
            bg = bg.expand(3)
        background = torch.cat([bg, bg.new_zeros(extra_channels.shape[1])])
    return rasterize(
        posed.means,
        posed.quats,
        posed.scales,
        posed.opacities,
        colors,
        camera.viewmat,
        camera.K,
        camera.width,
        camera.height,
        background=background,
        backend=backend,
        render_depth=render_depth,
    )
