"""The SMPL fit to several calibrated views at once, in the rig's world frame; and triangulation.

With two or more cameras the depth a single view cannot see is in the data: a body point must
project onto its detected keypoint in every view. :class:`MultiViewFitter` is the single-view
:class:`~stg_node.tracking.fitting.SmplFitter` with its reprojection term taken over every view
(each view's residuals in units of 1 % of the person's height in that view, weighted by the
detector's score, Cauchy-robust, so a view that mistook left for right is outvoted), in world
coordinates: ``x_world = R(Rh) @ body + Th``, ``x_cam_v = R_v x_world + t_v``, projected with
``K_v`` (keypoints are undistorted first). The priors, joint limits, temporal and shape terms and
the Levenberg-Marquardt solver are the single-view fitter's own. The network's 3D points are not
used: the views give the depth.

Initialisation needs no guessing of the body's turn: the detected keypoints are triangulated
(:func:`triangulate`, confidence-weighted DLT, the worst view dropped when it disagrees) and the
body's rest torso is turned onto the triangulated shoulders and hips (Kabsch).

Shape: the first ``calibration_frames`` confident frames fit the shape coefficients too, as in
one view; here the scale is observed (the views agree on a size only for the right one), so the
fitted shape is the person's, not the body model's mean.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from stg_node.body import BodyModel, lbs
from stg_node.tracking.fitting import (
    DTYPE,
    GLOBAL_PARAMS,
    NUM_BODY_JOINTS,
    POSE_PARAMS,
    RELAXED_POSE,
    FitConfig,
    FitResult,
    SmplFitter,
    kabsch,
)
from stg_node.tracking.layouts import KeypointLayout
from stg_node.tracking.priors import limit_excess

MIN_VIEW_TARGETS = 4  # a view with fewer usable targets adds nothing
TORSO = ("left_shoulder", "right_shoulder", "left_hip", "right_hip")
MIN_DEPTH_M = 0.05
DISAGREE_UNITS = 8.0  # a view's fit RMS (1 % of the person's height) beyond which it may be left out ...
DISAGREE_FACTOR = 3.0  # ... if it is also this many times the other views' median


@dataclass(frozen=True)
class Triangulation:
    """Points triangulated from several views."""

    points: np.ndarray  # (K, 3) world metres (NaN where fewer than two views saw the point)
    residual_px: np.ndarray  # (K,) RMS reprojection error over the views used (NaN: none)
    views: np.ndarray  # (K,) number of views used


def triangulate(
    projections: np.ndarray,
    xy: np.ndarray,
    weight: np.ndarray,
    *,
    outlier_px: float = 20.0,
) -> Triangulation:
    """Confidence-weighted linear triangulation of K points seen by V cameras.

    ``projections`` (V, 3, 4) pinhole matrices ``K [R | t]``; ``xy`` (V, K, 2) undistorted pixels;
    ``weight`` (V, K) detector scores (0 = not seen). Each view's two DLT rows are scaled by its
    weight; with three or more views, the view whose reprojection error is largest is dropped
    when that error exceeds ``outlier_px`` (a swapped or misplaced keypoint) and the point is
    solved again.
    """
    projections = np.asarray(projections, dtype=np.float64)
    xy = np.asarray(xy, dtype=np.float64)
    weight = np.where(np.isfinite(xy).all(-1), np.asarray(weight, dtype=np.float64), 0.0)
    xy = np.nan_to_num(xy)
    views, count = weight.shape
    points = np.full((count, 3), np.nan)
    residual = np.full(count, np.nan)
    used_views = np.zeros(count, dtype=np.int64)
    active = weight > 0
    for _round in range(max(1, views - 1)):
        solvable = active.sum(0) >= 2
        if not solvable.any():
            break
        # Rows: w (x P3 - P1), w (y P3 - P2) per view; (K, 2V, 4).
        rows_x = xy[:, :, 0, None] * projections[:, None, 2, :] - projections[:, None, 0, :]
        rows_y = xy[:, :, 1, None] * projections[:, None, 2, :] - projections[:, None, 1, :]
        w = np.where(active, weight, 0.0)[:, :, None]
        A = np.concatenate([rows_x * w, rows_y * w], axis=0).transpose(1, 0, 2)
        _, _, vt = np.linalg.svd(A[solvable])
        homogeneous = vt[:, -1]
        with np.errstate(divide="ignore", invalid="ignore"):
            solved = homogeneous[:, :3] / homogeneous[:, 3:4]
        points[solvable] = solved
        # Reprojection per view.
        h = np.concatenate([points, np.ones((count, 1))], axis=1)
        proj = np.einsum("vij,kj->vki", projections, np.nan_to_num(h))
        depth = proj[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            errors = np.linalg.norm(proj[..., :2] / depth[..., None] - xy, axis=-1)
        errors = np.where(active & (depth > 0), errors, np.where(active, np.inf, np.nan))
        used_views = active.sum(0)
        with np.errstate(invalid="ignore"):
            residual = np.sqrt(np.nanmean(np.where(active, errors, np.nan) ** 2, axis=0))
        worst = np.nanargmax(np.where(active, errors, -1.0), axis=0)
        worst_error = errors[worst, np.arange(count)]
        drop = solvable & (used_views >= 3) & (worst_error > outlier_px)
        if not drop.any():
            break
        active[worst[drop], np.flatnonzero(drop)] = False
    unsolved = used_views < 2
    points[unsolved] = np.nan
    residual[unsolved] = np.nan
    return Triangulation(points, residual, np.where(unsolved, 0, used_views))


@dataclass
class _MultiObservation:
    """The targets of every view, stacked view-major: rows v*T .. (v+1)*T - 1 belong to view v."""

    xy: torch.Tensor  # (V*T, 2) undistorted pixels
    weight: torch.Tensor  # (V*T,) fit weight x detector score, 0 = unused
    unit_px: torch.Tensor  # (V*T,) pixels per residual unit (1 % of the person's height in that view)
    views: int
    targets: int
    points: np.ndarray  # (T, 3) triangulated targets (NaN where unsolved)
    world: None = None  # no network 3D term here
    world_weight: None = None


class MultiViewFitter(SmplFitter):
    """Fits SMPL to one person's keypoints in several calibrated views (world frame); see the module."""

    def __init__(
        self,
        body: BodyModel,
        layout: KeypointLayout,
        cameras: list,
        config: FitConfig | None = None,
        *,
        betas: np.ndarray | None = None,
        offsets: dict | None = None,
    ):
        """``cameras``: (K, R, t) per view, world-to-camera, pinhole ``K`` of undistorted pixels.
        ``offsets``: where the detector's keypoints sit relative to the SMPL points (body_points.py's
        form; default: the measured table of keypoint_offsets.py for this layout)."""
        from stg_node.tracking.body_points import BodyKeypoints
        from stg_node.tracking.keypoint_offsets import offsets_for

        if not cameras:
            raise ValueError("MultiViewFitter needs at least one camera")
        super().__init__(body, layout, cameras[0][0], config, betas=betas)
        offsets = offsets_for(layout) if offsets is None else offsets
        if offsets:
            self.model = BodyKeypoints(body, [t.point for t in layout.targets], offsets).to(DTYPE)
        self.Ks = torch.as_tensor(np.stack([np.asarray(K, np.float64) for K, _, _ in cameras]), dtype=DTYPE)
        self.Rs = torch.as_tensor(np.stack([np.asarray(R, np.float64) for _, R, _ in cameras]), dtype=DTYPE)
        self.ts = torch.as_tensor(
            np.stack([np.asarray(t, np.float64).reshape(3) for _, _, t in cameras]), dtype=DTYPE
        )
        self.projections = np.stack(
            [
                np.asarray(K) @ np.column_stack([np.asarray(R), np.asarray(t).reshape(3)])
                for K, R, t in cameras
            ]
        )
        names = [t.point.name for t in layout.targets]
        self._torso_targets = [names.index(n) for n in TORSO if n in names]
        self._rotation = np.eye(3)
        self._translation = np.zeros(3)
        self.dropped_views: tuple[int, ...] = ()  # the last fit's views left out as disagreeing

    @property
    def num_views(self) -> int:
        return int(self.Ks.shape[0])

    def reset(self, *, keep_shape: bool = True) -> None:
        super().reset(keep_shape=keep_shape)
        self._rotation = np.eye(3)
        self._translation = np.zeros(3)

    # ---- observation ---------------------------------------------------------------------------
    def observe_views(self, keypoints: list, xy_undistorted: list) -> _MultiObservation | None:
        """Targets of every view (None when fewer than two views, or too few targets in all)."""
        per_view = []
        for kp, xy in zip(keypoints, xy_undistorted, strict=True):
            obs = None if kp is None else self.observe(kp, xy)
            if obs is not None and int((obs.weight > 0).sum()) < MIN_VIEW_TARGETS:
                obs = None
            per_view.append(obs)
        seen = [o for o in per_view if o is not None]
        if not seen:
            return None
        T = len(self._sources)
        xy = torch.zeros(len(per_view), T, 2, dtype=DTYPE)
        weight = torch.zeros(len(per_view), T, dtype=DTYPE)
        unit = torch.ones(len(per_view), T, dtype=DTYPE)
        for v, obs in enumerate(per_view):
            if obs is None:
                continue
            xy[v], weight[v] = obs.xy, obs.weight
            unit[v] = obs.unit_px
        scores = weight.numpy() / np.maximum(self._target_weight.numpy(), 1e-9)
        tri = triangulate(self.projections, xy.numpy(), scores)
        return _MultiObservation(
            xy.reshape(-1, 2), weight.reshape(-1), unit.reshape(-1), len(per_view), T, tri.points
        )

    # ---- residuals --------------------------------------------------------------------------------
    def _residuals(self, thetas, obs: _MultiObservation, ctx: dict) -> tuple[torch.Tensor, torch.Tensor]:
        cfg = self.config
        batch = thetas.shape[0]
        betas = thetas[:, GLOBAL_PARAMS + POSE_PARAMS :] if ctx["calibrating"] else ctx["betas"]
        world, _, pose, body_rotations = self._points(thetas, ctx["base_rotation"], betas)  # (B, T, 3)
        cam = torch.einsum("vij,btj->bvti", self.Rs, world) + self.ts[None, :, None, :]
        depth = cam[..., 2].clamp(min=MIN_DEPTH_M)
        K = self.Ks
        u = K[None, :, None, 0, 0] * cam[..., 0] / depth + K[None, :, None, 0, 2]
        v = K[None, :, None, 1, 1] * cam[..., 1] / depth + K[None, :, None, 1, 2]
        predicted = torch.stack([u, v], dim=-1).reshape(batch, -1, 2)
        diff = (predicted - obs.xy) / obs.unit_px[:, None]
        norms = diff.norm(dim=-1)
        parts = [(diff * (obs.weight * ctx["robust"]).sqrt()[:, None]).reshape(batch, -1)]
        flat_pose = pose.reshape(batch, -1)
        parts.append(flat_pose * self._prior_scale)
        parts.append(limit_excess(body_rotations).reshape(batch, -1) * cfg.limit_weight)
        if ctx["previous"] is not None:
            prev_pose, rad_sigma, m_sigma = ctx["previous"]
            parts.append((flat_pose - prev_pose) / rad_sigma)
            parts.append(thetas[:, :3] / rad_sigma)
            parts.append((thetas[:, 3:6] - ctx["prev_translation"]) / m_sigma)
        if ctx["calibrating"]:
            parts.append(betas / cfg.shape_sigma)
        return torch.cat(parts, dim=1), norms

    def view_errors(self, theta, obs: _MultiObservation, ctx) -> np.ndarray:
        """(V,) weighted RMS residual of each view in its noise units (NaN: the view has no targets)."""
        with torch.no_grad():
            _, norms = self._residuals(theta[None], obs, dict(ctx, robust=torch.ones_like(obs.weight)))
        weight = obs.weight.reshape(obs.views, obs.targets)
        squares = (weight * norms[0].reshape(obs.views, obs.targets) ** 2).sum(1)
        total = weight.sum(1)
        return np.where(total.numpy() > 0, np.sqrt((squares / total.clamp(min=1e-9)).numpy()), np.nan)

    def _drop_disagreeing_view(
        self, theta, obs: _MultiObservation, ctx, active
    ) -> tuple[torch.Tensor, tuple]:
        """With three or more views, a view the fit cannot explain (its RMS above
        ``max(DISAGREE_UNITS, DISAGREE_FACTOR x the others' median)``: the detector found someone
        else, or a mirror image) is left out and the fit refined without it; up to one view."""
        errors = self.view_errors(theta, obs, ctx)
        seen = np.flatnonzero(np.isfinite(errors))
        if len(seen) < 3:
            return theta, ()
        worst = int(seen[np.argmax(errors[seen])])
        others = np.median(errors[seen[seen != worst]])
        if errors[worst] <= max(DISAGREE_UNITS, DISAGREE_FACTOR * others):
            return theta, ()
        rows = slice(worst * obs.targets, (worst + 1) * obs.targets)
        obs.weight[rows] = 0.0
        theta, _ = self._solve(theta, active, obs, ctx, self.config.init_iterations)
        return theta, (worst,)
        with torch.no_grad():
            ctx = dict(ctx, robust=torch.ones_like(obs.weight))
            _, norms = self._residuals(theta[None], obs, ctx)
        weight = obs.weight
        total = weight.sum().clamp(min=1e-9)
        rms_units = math.sqrt(float((weight * norms[0] ** 2).sum() / total))
        rms_px = math.sqrt(float((weight * (norms[0] * obs.unit_px) ** 2).sum() / total))
        return rms_units, rms_px, int((weight > 0).sum())

    # ---- fitting -----------------------------------------------------------------------------------
    def fit_views(self, keypoints: list, xy_undistorted: list, timestamp: float) -> FitResult | None:
        """Fit this instant from every view's keypoints; None when they say too little (state untouched)."""
        obs = self.observe_views(keypoints, xy_undistorted)
        if obs is None:
            return None
        cfg = self.config
        calibrating = not self.calibrated
        ctx = {
            "betas": torch.as_tensor(self.betas, dtype=DTYPE)[None],
            "calibrating": calibrating,
            "previous": None,
            "robust": torch.ones(obs.xy.shape[0], dtype=DTYPE),
        }
        gap = None if self._last_time is None else timestamp - self._last_time
        reinit = not self._tracking or gap is None or gap < 0 or gap > cfg.max_temporal_gap_s
        active = torch.arange(GLOBAL_PARAMS + POSE_PARAMS + (self.num_betas if calibrating else 0))
        rescued = False
        if reinit:
            started = self._initialise_views(obs, ctx, active)
            if started is None:
                return None
            theta, ctx = started
        else:
            dt = max(gap, 1e-3)
            ctx["previous"] = (
                torch.as_tensor(self._pose, dtype=DTYPE),
                max(cfg.temporal_rad_per_s * dt, 1e-3),
                max(cfg.temporal_m_per_s * dt, 1e-3),
            )
            ctx["prev_translation"] = torch.as_tensor(self._translation, dtype=DTYPE)
            ctx["base_rotation"] = torch.as_tensor(self._rotation, dtype=DTYPE)
            theta_np = np.concatenate([np.zeros(3), self._translation, self._pose])
            if calibrating:
                theta_np = np.concatenate([theta_np, self.betas])
            theta, _ = self._solve(torch.as_tensor(theta_np, dtype=DTYPE), active, obs, ctx, cfg.iterations)
            since = None if self._last_rescue is None else timestamp - self._last_rescue
            cooled = since is None or not 0 <= since < cfg.rescue_cooldown_s
            if cooled and self._reprojection_error(theta, obs, ctx)[0] > cfg.rescue_units:
                self._last_rescue = timestamp
                fresh = self._initialise_views(obs, dict(ctx, previous=None), active)
                if fresh is not None and self._cost(fresh[0], obs, fresh[1]) < self._cost(theta, obs, ctx):
                    (theta, ctx), rescued = fresh, True
        theta, self.dropped_views = self._drop_disagreeing_view(theta, obs, ctx, active)
        rotation = ctx["base_rotation"].numpy() @ lbs.axis_angle_to_matrix(theta[:3]).numpy()
        self._rotation = rotation
        self._translation = theta[3:6].numpy().copy()
        self._pose = theta[GLOBAL_PARAMS : GLOBAL_PARAMS + POSE_PARAMS].numpy().copy()
        betas = theta[GLOBAL_PARAMS + POSE_PARAMS :].numpy().copy() if calibrating else self.betas
        self._last_time = timestamp
        self._tracking = True
        rms_units, rms_px, used = self._reprojection_error(theta, obs, ctx)
        return FitResult(
            body_pose=self._pose.reshape(NUM_BODY_JOINTS, 3).copy(),
            Rh=lbs.matrix_to_axis_angle(torch.as_tensor(rotation)).numpy(),
            Th=self._translation.copy(),
            betas=np.asarray(betas, dtype=np.float64).copy(),
            rms_px=rms_px,
            rms_units=rms_units,
            used_targets=used,
            reinitialised=reinit or rescued,
        )

    def _initialise_views(self, obs: _MultiObservation, ctx: dict, active: torch.Tensor):
        """From the triangulated torso: for each starting pose (the current one, rest, arms down),
        the rotation (Kabsch) and translation that put its torso on the triangulated one, a short
        global refinement, then the full fit; the lowest cost wins. None without a triangulated torso."""
        torso = [i for i in self._torso_targets if np.all(np.isfinite(obs.points[i]))]
        solved = np.flatnonzero(np.all(np.isfinite(obs.points), axis=1))
        anchors = torso if len(torso) >= 3 else list(solved)
        if len(anchors) < 3:
            return None
        cfg = self.config
        best = None
        seen = []
        for start in (self._pose, np.zeros(POSE_PARAMS), RELAXED_POSE):
            if any(np.allclose(start, other) for other in seen):
                continue
            seen.append(start)
            with torch.no_grad():
                local = self.model(
                    ctx["betas"],
                    torch.as_tensor(start, dtype=DTYPE).reshape(1, NUM_BODY_JOINTS, 3),
                    torch.zeros(1, 3, dtype=DTYPE),
                    torch.zeros(1, 3, dtype=DTYPE),
                )[0].numpy()
            source, target = local[anchors], obs.points[anchors]
            rotation = kabsch(source, target)
            translation = target.mean(axis=0) - rotation @ source.mean(axis=0)
            local_ctx = dict(ctx, base_rotation=torch.as_tensor(rotation, dtype=DTYPE))
            theta_np = np.concatenate([np.zeros(3), translation, start])
            global_ctx = dict(local_ctx, calibrating=False, previous=None)
            theta, _ = self._solve(
                torch.as_tensor(theta_np, dtype=DTYPE),
                torch.arange(GLOBAL_PARAMS),
                obs,
                global_ctx,
                max(cfg.global_iterations, 1),
            )
            if ctx["calibrating"]:
                theta = torch.cat([theta, torch.as_tensor(self.betas, dtype=DTYPE)])
            theta, _ = self._solve(theta, active, obs, local_ctx, cfg.init_iterations)
            cost = self._cost(theta, obs, local_ctx)
            if best is None or cost < best[0]:
                best = (cost, theta, local_ctx)
        return best[1], best[2]
