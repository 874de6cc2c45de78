"""SMPL fitting to 2D keypoints: a few Levenberg-Marquardt steps per frame, warm-started from the last.

Unknowns per frame: the global rotation (kept as a fixed base rotation times a small update, so
a body turning round never meets the axis-angle wrap at pi), the translation ``Th`` and the 23
joint rotations (axis-angle; SMPL's root rotation stays zero, ``Rh`` carries it). During shape
calibration the body's shape coefficients join them. The cost (each term a residual vector; the
solver minimises the sum of squares):

- **reprojection**: projected body point minus detected point, in units of
  ``noise_fraction`` of the person's height in the image (so the balance with the priors does
  not depend on resolution), times sqrt(weight x detector score), with a Cauchy IRLS weight
  against outliers (a left/right swap, a hand lost in the background);
- **world** (when the network gives 3D points, as BlazePose does): the direction of each body
  segment (upper arm, shin, shoulder line, ...; layouts.WORLD_BONES) minus the network's, unit
  vectors, in units of ``world_sigma`` (about the sine of the network's typical angular error).
  Directions, not positions: the network's skeleton has its own size, but it knows whether an
  arm points towards the camera or away, which the 2D points cannot say;
- **pose prior** and **joint limits** (priors.py); **temporal**: change since the previous frame
  in units of the motion a body plausibly makes in that time (opt-in: per joint loosened where the
  detector's points show the limb turned further, limb_motion.py); **shape prior** while calibrating.

The Jacobian is taken by forward differences on one batched evaluation (parameters + 1 rows of
the tiny body-point model, ~2 ms), cheaper on a CPU than autograd for 75-85 unknowns.

Initialisation (first frame, or after the person was lost): translation from the ratio of known
body segment lengths to their image lengths, rotation from the network's 3D points (Kabsch) when
it has them and from four upright yaw hypotheses always; each is refined over rotation and
translation alone and the best starts the full fit.

Shape: the first ``calibration_frames`` confident frames fit shape too; their confidence-weighted
mean is then held for the rest of the sequence. A monocular camera cannot separate a large
person far away from a small one near: the shape prior (the body's mean) fixes that scale.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
import torch

from stg_node.body import BodyModel, lbs
from stg_node.tracking.body_points import BodyKeypoints
from stg_node.tracking.layouts import KeypointLayout
from stg_node.tracking.limb_motion import LimbMotion
from stg_node.tracking.priors import limit_excess, prior_sigma
from stg_node.tracking.silhouette import MaskTarget, MeshSamples, silhouette_residuals
from stg_node.tracking.types import Keypoints

log = logging.getLogger(__name__)

NUM_BODY_JOINTS = 23
GLOBAL_PARAMS = 6  # rotation update (3) + translation (3)
POSE_PARAMS = NUM_BODY_JOINTS * 3
MIN_DEPTH_M = 0.1
# Upright, facing the camera: SMPL's y (up) to the camera's -y (up on screen), z (front) to -z.
FACING_CAMERA = np.diag([1.0, -1.0, -1.0])
YAW_HYPOTHESES_DEG = (0.0, 90.0, 180.0, 270.0)
# A third starting pose for (re)initialisation: standing with the arms down, elbows a little bent.
RELAXED_POSE = np.zeros(POSE_PARAMS)
RELAXED_POSE[(16 - 1) * 3 + 2] = -1.1  # left shoulder lowers the arm (z < 0)
RELAXED_POSE[(17 - 1) * 3 + 2] = 1.1
RELAXED_POSE[(18 - 1) * 3 + 1] = -0.3  # left elbow flexes (y < 0)
RELAXED_POSE[(19 - 1) * 3 + 1] = 0.3
DTYPE = torch.float64


@dataclass(frozen=True)
class FitConfig:
    iterations: int = 2  # LM steps on a tracked frame
    init_iterations: int = 12  # LM steps after (re)initialisation
    global_iterations: int = 6  # rotation + translation steps per initial hypothesis
    calibration_frames: int = 30  # confident frames that fit shape; their mean is then held
    calibration_min_confidence: float = 0.6
    min_keypoint_score: float = 0.3  # detector points below this are ignored
    min_targets: int = 6  # fewer usable targets: no fit
    noise_fraction: float = 0.01  # 2D residual unit, as a fraction of the person's image height
    robust_scale: float = 4.0  # Cauchy scale of the 2D residuals, in those units
    world_sigma: float = 0.25  # unit-vector difference (~ sin 15 degrees)
    # Half weight: the network's torso and leg directions are 12-14 degrees off (median, the
    # benchmark's mixed motion), and at full weight they pulled the body's turn with them (global
    # orientation 12.5 degrees off at 1.0, 11.4 at 0.5, 14.9 at 2.0; docs/BENCHMARKS.md).
    world_weight: float = 0.5
    prior_weight: float = 3.0
    limit_weight: float = 100.0  # per radian outside a joint's range
    temporal_rad_per_s: float = 3.0  # plausible joint rotation speed (sigma of the temporal term)
    temporal_m_per_s: float = 1.0  # plausible body speed
    # Where the detector's points say a limb turned faster (limb_motion.py: the image-plane turn
    # of its points about the joint, less the jitter), that joint's temporal sigma follows the
    # evidence up to this speed; equal to temporal_rad_per_s (the default) turns it off. Off: at
    # 12 rad/s it tracked a dancer 80.7 -> 77.6 mm and a mixed motion 46.2 -> 45.9 mm MPJPE, but
    # the dancer's held-out frames trained 0.06 and 0.25 dB worse (two seeds; docs/BENCHMARKS.md).
    temporal_max_rad_per_s: float = 3.0
    temporal_jitter_units: float = 4.0  # point displacement read as jitter, in 2D units
    temporal_min_length_units: float = 5.0  # shorter segments count as this long (a hand's points)
    max_temporal_gap_s: float = 0.5  # longer gaps: no temporal term
    rescue_units: float = 3.0  # a tracked fit worse than this (RMS, noise units) is redone from scratch
    rescue_cooldown_s: float = 0.5  # at most one rescue per this time (each costs ~10 frames' fitting)
    shape_sigma: float = 1.0
    # The silhouette term (silhouette.py): after the keypoint fit, a few more LM steps that also ask
    # the posed mesh to cover the person's mask and no more; 0 turns it off.
    silhouette_weight: float = 50.0  # each chamfer half counts like this many keypoints
    silhouette_iterations: int = 3
    silhouette_samples: int = 400  # mesh vertices projected
    silhouette_outline_points: int = 200  # points along the mask's outline
    silhouette_robust_units: float = 10.0  # Cauchy scale of a silhouette distance, in 2D units
    # Where the keypoint fit and the mask disagree (RMS silhouette distance, 2D units) the pose
    # network's 3D bone directions lose weight: 1 / (1 + (disagreement / this)^2).
    silhouette_trust_units: float = 3.0
    damping: float = 1e-2
    step_eps: float = 1e-6  # forward-difference step
    # The depth-order test (issue 26, round 10): on a tracked frame, each of ``order_test_bones``
    # (SMPL (joint, child) pairs) that leans towards or away from the camera by more than
    # order_min_lean_deg is also tried the other way round (its far end slid along its ray to
    # the other depth of the same length: the same pixels) and re-solved without the temporal
    # term; the lower cost wins. The temporal term otherwise holds a limb on whichever side of
    # the image plane it was first fitted. Off by default: docs/BENCHMARKS.md (round 10).
    order_test_bones: tuple = ()
    order_min_lean_deg: float = 10.0
    order_iterations: int = 3

    def validate(self) -> None:
        if self.iterations < 1 or self.init_iterations < 1 or self.global_iterations < 0:
            raise ValueError("fit iterations must be >= 1 (global_iterations >= 0)")
        if self.calibration_frames < 0:
            raise ValueError(f"calibration_frames must be >= 0, got {self.calibration_frames}")
        if self.silhouette_weight < 0 or self.silhouette_iterations < 1:
            raise ValueError("silhouette_weight must be >= 0 and silhouette_iterations >= 1")
        if self.silhouette_samples < 1 or self.silhouette_outline_points < 1:
            raise ValueError("silhouette_samples and silhouette_outline_points must be >= 1")
        if not self.temporal_max_rad_per_s >= self.temporal_rad_per_s or self.temporal_jitter_units < 0:
            raise ValueError(
                "temporal_max_rad_per_s must be >= temporal_rad_per_s and temporal_jitter_units >= 0"
            )
        if self.order_iterations < 1 or not 0.0 <= self.order_min_lean_deg < 90.0:
            raise ValueError("order_iterations must be >= 1 and order_min_lean_deg in [0, 90)")
        for bone in self.order_test_bones:
            if len(bone) != 2 or not all(isinstance(k, int) and 1 <= k < 1 + NUM_BODY_JOINTS for k in bone):
                raise ValueError(
                    f"order_test_bones holds (joint, child) pairs of SMPL joints 1..23, got {bone!r}"
                )
        for name in ("noise_fraction", "robust_scale", "world_sigma", "shape_sigma", "step_eps",
                     "silhouette_robust_units", "silhouette_trust_units",
                     "temporal_min_length_units"):  # fmt: skip
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")


@dataclass(frozen=True)
class FitResult:
    """One frame's fitted parameters (camera frame) and how well they explain the keypoints."""

    body_pose: np.ndarray  # (23, 3) axis-angle, joints 1..23
    Rh: np.ndarray  # (3,) axis-angle about the model origin
    Th: np.ndarray  # (3,) metres
    betas: np.ndarray  # (S,)
    rms_px: float  # weight-averaged RMS reprojection error of the used points, pixels
    rms_units: float  # the same in units of noise_fraction x person height
    used_targets: int
    reinitialised: bool
    cost: float = float("nan")  # the robust cost of the solution (2D, 3D directions, priors; no temporal)

    @property
    def poses(self) -> np.ndarray:
        """(24, 3) SMPL poses with a zero root."""
        return np.concatenate([np.zeros((1, 3)), self.body_pose], axis=0)


@dataclass
class _Observation:
    xy: torch.Tensor  # (T, 2) target image points (undistorted pixels)
    weight: torch.Tensor  # (T,) fit weight x detector score, 0 = unused
    unit_px: float  # pixels per 2D residual unit
    world: torch.Tensor | None  # (N, 3) unit directions of the layout's bones, or None
    world_weight: torch.Tensor | None  # (N,) 0 where a bone end is unusable


def project(camera: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """(..., 2) pixel positions of (..., 3) camera-frame points (depth clamped at MIN_DEPTH_M)."""
    depth = camera[..., 2].clamp(min=MIN_DEPTH_M)
    return torch.stack(
        [K[0, 0] * camera[..., 0] / depth + K[0, 2], K[1, 1] * camera[..., 1] / depth + K[1, 2]], dim=-1
    )


def _rotation_from_vector(vec: np.ndarray) -> np.ndarray:
    return lbs.axis_angle_to_matrix(torch.as_tensor(vec, dtype=DTYPE)).numpy()


def _vector_from_rotation(rot: np.ndarray) -> np.ndarray:
    return lbs.matrix_to_axis_angle(torch.as_tensor(rot, dtype=DTYPE)).numpy()


def _yaw(deg: float) -> np.ndarray:
    a = math.radians(deg)
    return np.array([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]])


def kabsch(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Rotation R minimising sum |R @ (s - mean s) - (t - mean t)|^2 over matched point rows."""
    a = source - source.mean(axis=0)
    b = target - target.mean(axis=0)
    u, _, vt = np.linalg.svd(a.T @ b)
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    return vt.T @ np.diag([1.0, 1.0, d]) @ u.T


class SmplFitter:
    """Fits SMPL parameters to one person's keypoints frame after frame (keeps state between frames)."""

    def __init__(
        self,
        body: BodyModel,
        layout: KeypointLayout,
        K: np.ndarray,
        config: FitConfig | None = None,
        *,
        betas: np.ndarray | None = None,
    ):
        self.config = config or FitConfig()
        self.config.validate()
        self.layout = layout
        K = np.asarray(K, dtype=np.float64)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError(f"K must be a finite 3x3 intrinsic matrix with positive focal lengths, got {K}")
        self.K = K
        self.model = BodyKeypoints(body, [t.point for t in layout.targets]).to(DTYPE)
        self.num_betas = self.model.num_betas
        self._sources = [list(t.sources) for t in layout.targets]
        self._target_weight = torch.tensor([t.weight for t in layout.targets], dtype=DTYPE)
        self._bones = layout.bones()
        bone_index = torch.as_tensor(self._bones, dtype=torch.long).reshape(-1, 2)
        self._bone_start, self._bone_end = bone_index[:, 0], bone_index[:, 1]
        sigma = torch.as_tensor(prior_sigma().reshape(-1), dtype=DTYPE)
        self._prior_scale = math.sqrt(self.config.prior_weight) / sigma
        self._limb_motion = LimbMotion(self.model)
        self._last_targets: tuple[torch.Tensor, torch.Tensor] | None = None
        self._root_rotation = torch.eye(3, dtype=DTYPE)[None, None]
        self._mesh = (
            MeshSamples(body, self.config.silhouette_samples) if self.config.silhouette_weight > 0 else None
        )
        self._last_fit: tuple[_Observation, dict, bool] | None = None
        self._last_betas = np.zeros(self.num_betas)
        self._fixed_betas = betas is not None
        self.betas = np.zeros(self.num_betas) if betas is None else self._check_betas(betas)
        self.reset()

    def _check_betas(self, betas) -> np.ndarray:
        betas = np.asarray(betas, dtype=np.float64).reshape(-1)
        if betas.size > self.num_betas or not np.all(np.isfinite(betas)):
            raise ValueError(f"betas must be at most {self.num_betas} finite values, got {betas.shape}")
        return np.pad(betas, (0, self.num_betas - betas.size))

    # ---- state ------------------------------------------------------------------------------
    def reset(self, *, keep_shape: bool = True) -> None:
        """Forget the tracked pose (the next frame re-initialises); keep the calibrated shape unless told."""
        self._rotation = FACING_CAMERA.copy()
        self._translation = np.array([0.0, 0.0, 3.0])
        self._pose = np.zeros(POSE_PARAMS)
        self._last_time: float | None = None
        self._last_rescue: float | None = None
        self._tracking = False
        self._last_fit = None
        self._last_targets = None
        if not keep_shape and not self._fixed_betas:
            self.betas = np.zeros(self.num_betas)
            self._calibration: list[tuple[float, np.ndarray]] = []
            self.calibrated = self.config.calibration_frames == 0
        elif not hasattr(self, "_calibration"):
            self._calibration = []
            self.calibrated = self._fixed_betas or self.config.calibration_frames == 0

    @property
    def tracking(self) -> bool:
        return self._tracking

    def lose(self) -> None:
        """The person is gone: the next fit starts from scratch (shape is kept)."""
        self._tracking = False
        self._last_fit = None
        self._last_targets = None

    # ---- observation --------------------------------------------------------------------------
    def observe(self, keypoints: Keypoints, xy_undistorted: np.ndarray | None = None) -> _Observation | None:
        """Targets from keypoints (None when too few are usable)."""
        if keypoints.layout != self.layout.name:
            raise ValueError(
                f"keypoints are in layout {keypoints.layout!r}, the fitter expects {self.layout.name!r}"
            )
        xy = np.asarray(keypoints.xy if xy_undistorted is None else xy_undistorted, dtype=np.float64)
        score = np.nan_to_num(np.asarray(keypoints.score, dtype=np.float64), nan=0.0)
        if xy.shape != (self.layout.num_points, 2):
            raise ValueError(f"expected {self.layout.num_points} keypoints, got {xy.shape}")
        ok = np.all(np.isfinite(xy), axis=1) & (score >= self.config.min_keypoint_score)
        target_xy = np.zeros((len(self._sources), 2))
        target_score = np.zeros(len(self._sources))
        for i, sources in enumerate(self._sources):
            if all(ok[s] for s in sources):
                target_xy[i] = xy[sources].mean(axis=0)
                target_score[i] = min(score[s] for s in sources)
        used = target_score > 0
        if used.sum() < self.config.min_targets:
            return None
        extent = target_xy[used].max(axis=0) - target_xy[used].min(axis=0)
        person_px = max(float(extent.max()), 1.0)
        world = world_weight = None
        if keypoints.world is not None and self._bones:
            w = np.asarray(keypoints.world, dtype=np.float64)
            points = np.zeros((len(self._sources), 3))
            for i, sources in enumerate(self._sources):
                if target_score[i] > 0 and np.all(np.isfinite(w[sources])):
                    points[i] = w[sources].mean(axis=0)
            a, b = np.array(self._bones).T
            vectors = points[b] - points[a]
            length = np.linalg.norm(vectors, axis=1)
            usable = (target_score[a] > 0) & (target_score[b] > 0) & (length > 1e-3)
            if usable.any():
                world = torch.as_tensor(vectors / np.maximum(length, 1e-3)[:, None], dtype=DTYPE)
                bone_score = np.where(usable, np.minimum(target_score[a], target_score[b]), 0.0)
                world_weight = torch.as_tensor(bone_score, dtype=DTYPE)
        return _Observation(
            xy=torch.as_tensor(target_xy, dtype=DTYPE),
            weight=torch.as_tensor(target_score, dtype=DTYPE) * self._target_weight,
            unit_px=self.config.noise_fraction * person_px,
            world=world,
            world_weight=world_weight,
        )

    # ---- residuals ------------------------------------------------------------------------------
    def _points(self, thetas: torch.Tensor, base_rotation: torch.Tensor, betas: torch.Tensor):
        """Camera-frame points (B, T, 3), the same before translation, and local joint rotations."""
        batch = thetas.shape[0]
        rotation = base_rotation @ lbs.axis_angle_to_matrix(thetas[:, :3])
        pose = thetas[:, GLOBAL_PARAMS : GLOBAL_PARAMS + POSE_PARAMS].reshape(batch, NUM_BODY_JOINTS, 3)
        body_rotations = lbs.axis_angle_to_matrix(pose)
        all_rotations = torch.cat([self._root_rotation.expand(batch, 1, 3, 3), body_rotations], dim=1)
        rotated = self.model.local_points(betas, all_rotations) @ rotation.transpose(1, 2)
        return rotated + thetas[:, None, 3:6], rotated, pose, body_rotations

    def _residuals(self, thetas, obs: _Observation, ctx: dict) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, R) residuals, the 2D ones robustly weighted by ``ctx["robust"]``, and the (B, T)
        per-target 2D residual norms in noise units (what the robust weights are computed from)."""
        cfg = self.config
        batch = thetas.shape[0]
        betas = thetas[:, GLOBAL_PARAMS + POSE_PARAMS :] if ctx["calibrating"] else ctx["betas"]
        camera, rotated, pose, body_rotations = self._points(thetas, ctx["base_rotation"], betas)
        K = ctx["K"]
        depth = camera[..., 2].clamp(min=MIN_DEPTH_M)
        u = K[0, 0] * camera[..., 0] / depth + K[0, 2]
        v = K[1, 1] * camera[..., 1] / depth + K[1, 2]
        diff = (torch.stack([u, v], dim=-1) - obs.xy) / obs.unit_px  # (B, T, 2)
        norms = diff.norm(dim=-1)
        parts = [(diff * (obs.weight * ctx["robust"]).sqrt()[:, None]).reshape(batch, -1)]
        if obs.world is not None and cfg.world_weight > 0:
            bones = rotated[:, self._bone_end] - rotated[:, self._bone_start]
            directions = bones / bones.norm(dim=-1, keepdim=True).clamp(min=1e-6)
            rel = (directions - obs.world) / cfg.world_sigma
            world_weight = cfg.world_weight * ctx.get("world_scale", 1.0) * obs.world_weight
            parts.append((rel * world_weight.sqrt()[:, None]).reshape(batch, -1))
        if ctx.get("silhouette") is not None:
            parts += self._silhouette_rows(thetas, ctx, betas, body_rotations, obs.unit_px)
        parts += self._prior_terms(thetas, pose, body_rotations, betas, ctx)
        return torch.cat(parts, dim=1), norms

    def _silhouette_rows(
        self, thetas, ctx: dict, betas, body_rotations, unit_px: float
    ) -> list[torch.Tensor]:
        """The two chamfer halves of silhouette.py for the sampled mesh posed by ``thetas``."""
        cfg = self.config
        batch = thetas.shape[0]
        rotation = ctx["base_rotation"] @ lbs.axis_angle_to_matrix(thetas[:, :3])
        all_rotations = torch.cat([self._root_rotation.expand(batch, 1, 3, 3), body_rotations], dim=1)
        camera = self._mesh.local(betas, all_rotations) @ rotation.transpose(1, 2) + thetas[:, None, 3:6]
        uv = project(camera, ctx["K"])
        inside, reach = silhouette_residuals(
            uv, ctx["silhouette"], unit_px, cfg.silhouette_weight, cfg.silhouette_robust_units
        )
        return [inside, reach]

    def mesh_uv(self, result: FitResult) -> np.ndarray:
        """(V, 2) undistorted pixel positions of the sampled mesh vertices posed by ``result``."""
        if self._mesh is None:
            raise ValueError("the fitter has no mesh samples (silhouette_weight is 0)")
        with torch.no_grad():
            rotations = lbs.axis_angle_to_matrix(torch.as_tensor(result.poses, dtype=DTYPE))[None]
            local = self._mesh.local(torch.as_tensor(result.betas, dtype=DTYPE)[None], rotations)
            rotation = torch.as_tensor(_rotation_from_vector(result.Rh), dtype=DTYPE)
            camera = local @ rotation.T + torch.as_tensor(result.Th, dtype=DTYPE)
            return project(camera, torch.as_tensor(self.K, dtype=DTYPE))[0].numpy()

    @property
    def uses_silhouette(self) -> bool:
        return self._mesh is not None

    def refine_with_mask(self, mask: np.ndarray, timestamp: float) -> FitResult | None:
        """The last :meth:`fit` refined with the person's mask (undistorted, the image's size): a
        few LM steps with the silhouette rows added, the pose network's 3D directions down-weighted
        by how much the keypoint fit and the mask disagree (a body seen from the back or side,
        where the network's depth cues are least reliable, is where they disagree most). Replaces
        the tracked state and returns the refined result; None (state untouched) without a last
        fit, a term, or a non-empty mask."""
        cfg = self.config
        if self._mesh is None or self._last_fit is None:
            return None
        target = MaskTarget.from_mask(mask, cfg.silhouette_outline_points)
        if target is None:
            return None
        obs, ctx, reinitialised = self._last_fit
        ctx = dict(ctx, base_rotation=torch.as_tensor(self._rotation, dtype=DTYPE), silhouette=target)
        theta_np = np.concatenate([np.zeros(3), self._translation, self._pose])
        calibrating = ctx["calibrating"]
        if calibrating:
            theta_np = np.concatenate([theta_np, self._last_betas])
        theta = torch.as_tensor(theta_np, dtype=DTYPE)
        ctx["world_scale"] = self.world_trust(self.silhouette_disagreement(theta, obs, ctx))
        theta, _ = self._solve(theta, torch.arange(theta.numel()), obs, ctx, cfg.silhouette_iterations)
        ctx = dict(ctx, silhouette=None, world_scale=1.0)
        self._last_fit = None  # refined once
        betas = self._keep_state(theta, ctx, timestamp)
        return self._result(theta, obs, ctx, betas, reinitialised)

    def silhouette_disagreement(self, theta: torch.Tensor, obs: _Observation, ctx: dict) -> float:
        """RMS capped silhouette distance (2D units) of the solution ``theta`` against ``ctx``'s mask."""
        with torch.no_grad():
            betas = theta[None, GLOBAL_PARAMS + POSE_PARAMS :] if ctx["calibrating"] else ctx["betas"]
            _, _, _, body_rotations = self._points(theta[None], ctx["base_rotation"], betas)
            rows = torch.cat(
                self._silhouette_rows(theta[None], ctx, betas, body_rotations, obs.unit_px), dim=1
            )
        return math.sqrt(float(rows.pow(2).sum()) / (2.0 * self.config.silhouette_weight))

    def world_trust(self, disagreement: float) -> float:
        """The weight factor of the network's 3D directions at a silhouette disagreement (units)."""
        return 1.0 / (1.0 + (disagreement / self.config.silhouette_trust_units) ** 2)

    def _prior_terms(self, thetas, pose, body_rotations, betas, ctx: dict) -> list[torch.Tensor]:
        """The residual rows after the reprojection (every fitter's): pose prior, joint limits, the
        temporal terms when there is a previous frame, the shape prior while calibrating."""
        cfg = self.config
        batch = thetas.shape[0]
        flat_pose = pose.reshape(batch, -1)
        parts = [flat_pose * self._prior_scale]
        parts.append(limit_excess(body_rotations).reshape(batch, -1) * cfg.limit_weight)
        if ctx["previous"] is not None:
            prev_pose, rad_sigma, m_sigma = ctx["previous"]
            parts.append((flat_pose - prev_pose) / rad_sigma)
            # The body's turn keeps the base sigma (the per-joint one is never below it).
            parts.append(thetas[:, :3] / (rad_sigma.min() if torch.is_tensor(rad_sigma) else rad_sigma))
            parts.append((thetas[:, 3:6] - ctx["prev_translation"]) / m_sigma)
        if ctx["calibrating"]:
            parts.append(betas / cfg.shape_sigma)
        return parts

    def _solve(self, theta, active: torch.Tensor, obs, ctx, iterations: int) -> tuple[torch.Tensor, float]:
        """Levenberg-Marquardt over the ``active`` parameter indices; returns (theta, final cost).

        The Jacobian comes from one batched evaluation at theta and at theta + eps along every
        active parameter (forward differences); a trial step is evaluated together with the next
        Jacobian, so an accepted step costs one batched evaluation. Cauchy weights from the
        current 2D residuals re-weight the 2D rows after each accepted step (IRLS). A step is
        kept only if it lowers the cost; otherwise the damping grows and the step shrinks.
        """
        cfg = self.config
        eps = cfg.step_eps
        damping = cfg.damping
        count = int(active.numel())
        directions = eps * torch.eye(theta.numel(), dtype=DTYPE)[active]
        num_2d = 2 * obs.xy.shape[0]
        identity = torch.eye(count, dtype=DTYPE)
        ctx["robust"] = torch.ones(obs.xy.shape[0], dtype=DTYPE)

        def evaluate(point: torch.Tensor, with_jacobian: bool):
            batch = torch.cat([point[None], point[None] + directions]) if with_jacobian else point[None]
            return self._residuals(batch, obs, ctx)

        def reweight(res: torch.Tensor, norms: torch.Tensor) -> torch.Tensor:
            robust = 1.0 / (1.0 + (norms[0] / cfg.robust_scale) ** 2)
            res[:, :num_2d] *= (robust / ctx["robust"]).sqrt().repeat_interleave(2)
            ctx["robust"] = robust
            return res

        res = reweight(*evaluate(theta, True))
        cost = float(res[0] @ res[0])
        for iteration in range(iterations):
            last = iteration == iterations - 1
            jac = ((res[1:] - res[0]) / eps).T  # (R, count)
            hessian = jac.T @ jac
            gradient = jac.T @ res[0]
            regulariser = torch.diag(torch.diagonal(hessian)) + 1e-6 * identity
            accepted = None
            for _attempt in range(4):
                step = torch.linalg.solve(hessian + damping * regulariser, -gradient)
                trial = theta.clone()
                trial[active] += step
                trial_res, trial_norms = evaluate(trial, not last)
                trial_cost = float(trial_res[0] @ trial_res[0])
                if math.isfinite(trial_cost) and trial_cost < cost:
                    accepted = (trial, trial_res, trial_norms)
                    damping = max(damping / 3.0, 1e-7)
                    break
                damping *= 10.0
            if accepted is None:
                break
            theta, res, norms = accepted
            if last:
                cost = float(res[0] @ res[0])
                break
            res = reweight(res, norms)
            cost = float(res[0] @ res[0])
            if float(step.abs().max()) < 1e-6:
                break
        return theta, cost

    # ---- fitting ----------------------------------------------------------------------------------
    def _fit_frame(self, obs, ctx: dict, timestamp: float, initialise):
        """The per-frame fit every fitter shares: a fresh start after a gap (or before the first
        frame), else a warm start from the last frame with the temporal terms, and a rescue (start
        over, keep the better) when the tracked answer explains the keypoints badly.

        ``initialise(obs, ctx, active)`` returns (theta, ctx) or None when it cannot start. Returns
        (theta, ctx, active, reinitialised), or None when a fresh start was needed and failed.
        """
        cfg = self.config
        calibrating = ctx["calibrating"]
        gap = None if self._last_time is None else timestamp - self._last_time
        reinit = not self._tracking or gap is None or gap < 0 or gap > cfg.max_temporal_gap_s
        active = torch.arange(GLOBAL_PARAMS + POSE_PARAMS + (self.num_betas if calibrating else 0))
        rescued = False
        if reinit:
            started = initialise(obs, ctx, active)
            if started is None:
                return None
            theta, ctx = started
        else:
            dt = max(gap, 1e-3)
            ctx["previous"] = (
                torch.as_tensor(self._pose, dtype=DTYPE),
                self._joint_sigma(ctx.get("limb_turn"), dt),
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
                # Lost the thread (a fast move, a limb stuck in a mirror pose): start over from
                # several hypotheses, keep the best, the tracked answer included.
                tracked_cost = self._cost(theta, obs, ctx)
                fresh = initialise(obs, dict(ctx, previous=None), active)
                if fresh is not None and self._cost(fresh[0], obs, fresh[1]) < tracked_cost:
                    (theta, ctx), rescued = fresh, True
        return theta, ctx, active, reinit or rescued

    def _test_depth_order(self, theta, active, obs: _Observation, ctx: dict) -> torch.Tensor:
        """``theta`` or, bone by bone (FitConfig.order_test_bones), the other depth order of a
        leaning limb where, re-solved without the temporal term, it explains the frame at a lower
        cost than ``theta`` re-solved the same way."""
        cfg = self.config
        plain = dict(ctx, previous=None)
        settled, _ = self._solve(theta.clone(), active, obs, dict(plain), cfg.order_iterations)
        best_cost = self._cost(settled, obs, plain)
        chosen = theta
        for bone in cfg.order_test_bones:
            flipped = self._depth_flipped(chosen, ctx, bone)
            if flipped is None:
                continue
            trial, _ = self._solve(flipped, active, obs, dict(plain), cfg.order_iterations)
            cost = self._cost(trial, obs, plain)
            if cost < best_cost:
                chosen, best_cost = trial, cost
        return chosen

    def _depth_flipped(self, theta: torch.Tensor, ctx: dict, bone) -> torch.Tensor | None:
        """``theta`` with ``bone`` (SMPL joint, child) turned to the other direction that keeps its
        child's pixel and its length (the child slid along its ray to the second root of
        ``|s u - p| = L``), every other joint kept at its orientation in the camera's frame; None
        when the bone leans less than order_min_lean_deg or the other root is behind the camera."""
        j, c = bone
        with torch.no_grad():
            betas = theta[None, GLOBAL_PARAMS + POSE_PARAMS :] if ctx["calibrating"] else ctx["betas"]
            rotation = ctx["base_rotation"] @ lbs.axis_angle_to_matrix(theta[:3])
            pose = theta[GLOBAL_PARAMS : GLOBAL_PARAMS + POSE_PARAMS].reshape(NUM_BODY_JOINTS, 3)
            local = torch.cat([self._root_rotation[0], lbs.axis_angle_to_matrix(pose)])[None]
            joints, transforms = lbs.rigid_chain(local, self.model.rest_joints(betas), self.model.parents)
            camera = joints[0] @ rotation.T + theta[3:6]
            p, q = camera[j], camera[c]
            length = (q - p).norm()
            ray = q / q.norm()
            direction = (q - p) / length
            if abs(float(direction @ (p / p.norm()))) < math.sin(
                math.radians(self.config.order_min_lean_deg)
            ):
                return None
            depth = 2.0 * float(ray @ p) - float(q.norm())
            if depth <= MIN_DEPTH_M:
                return None
            other = depth * ray - p
            other = other / other.norm()
            axis = torch.linalg.cross(direction, other)
            if float(axis.norm()) < 1e-9:
                return None
            turn = lbs.axis_angle_to_matrix(axis / axis.norm() * torch.atan2(axis.norm(), direction @ other))
            world = rotation @ transforms[0, :, :3, :3]  # (24, 3, 3) in the camera's frame
            parents = self.model.parents.tolist()
            new_world = world.clone()
            new_world[j] = turn @ world[j]
            out = theta.clone()
            for k in [j] + [k for k in range(1, 24) if parents[k] == j]:
                rel = new_world[parents[k]].T @ new_world[k]
                start = GLOBAL_PARAMS + 3 * (k - 1)
                out[start : start + 3] = lbs.matrix_to_axis_angle(rel)
            return out

    def _joint_sigma(self, limb_turn: np.ndarray | None, dt: float):
        """The temporal term's sigma over a frame gap ``dt``: temporal_rad_per_s x dt, or per joint
        (a (69,) tensor) the evidence's turn where it says more, up to temporal_max_rad_per_s x dt."""
        cfg = self.config
        base = max(cfg.temporal_rad_per_s * dt, 1e-3)
        if limb_turn is None or cfg.temporal_max_rad_per_s <= cfg.temporal_rad_per_s:
            return base
        per_joint = np.clip(limb_turn, base, max(cfg.temporal_max_rad_per_s * dt, base))
        return torch.as_tensor(np.repeat(per_joint, 3), dtype=DTYPE)

    def _limb_turn(self, obs: _Observation) -> np.ndarray | None:
        """Per-joint turn (radians) the targets show since the last fitted frame (limb_motion.py)."""
        cfg = self.config
        if self._last_targets is None or cfg.temporal_max_rad_per_s <= cfg.temporal_rad_per_s:
            return None
        xy, ok = self._last_targets
        return self._limb_motion.turn(
            xy, ok, obs.xy, obs.weight > 0,
            jitter_px=cfg.temporal_jitter_units * obs.unit_px,
            min_length_px=cfg.temporal_min_length_units * obs.unit_px,
        )  # fmt: skip

    def _keep_state(self, theta: torch.Tensor, ctx: dict, timestamp: float) -> np.ndarray:
        """Hold a frame's solution as the next frame's warm start; returns the frame's betas."""
        # Fold the rotation update into the base rotation.
        self._rotation = ctx["base_rotation"].numpy() @ _rotation_from_vector(theta[:3].numpy())
        self._translation = theta[3:6].numpy().copy()
        self._pose = theta[GLOBAL_PARAMS : GLOBAL_PARAMS + POSE_PARAMS].numpy().copy()
        self._last_time = timestamp
        self._tracking = True
        if ctx["calibrating"]:
            return theta[GLOBAL_PARAMS + POSE_PARAMS :].numpy().copy()
        return self.betas

    def fit(
        self, keypoints: Keypoints, timestamp: float, xy_undistorted: np.ndarray | None = None
    ) -> FitResult | None:
        """Fit this frame; None when the keypoints are too few to say anything (state untouched)."""
        obs = self.observe(keypoints, xy_undistorted)
        if obs is None:
            return None
        calibrating = not self.calibrated
        ctx = {
            "K": torch.as_tensor(self.K, dtype=DTYPE),
            "betas": torch.as_tensor(self.betas, dtype=DTYPE)[None],
            "calibrating": calibrating,
            "previous": None,
            "robust": torch.ones(obs.xy.shape[0], dtype=DTYPE),
            "limb_turn": self._limb_turn(obs),
        }
        theta, ctx, active, reinitialised = self._fit_frame(obs, ctx, timestamp, self._initialise)
        if self.config.order_test_bones and ctx["previous"] is not None:
            theta = self._test_depth_order(theta, active, obs, ctx)
        betas = self._keep_state(theta, ctx, timestamp)
        self._last_targets = (obs.xy.clone(), obs.weight > 0)
        self._last_fit = (obs, ctx, reinitialised)
        self._last_betas = np.asarray(betas, dtype=np.float64).copy()
        return self._result(theta, obs, ctx, betas, reinitialised)

    def _result(self, theta, obs: _Observation, ctx: dict, betas, reinitialised: bool) -> FitResult:
        """The held state as a FitResult, with the keypoint fit's error and cost at ``theta``."""
        rms_units, rms_px, used = self._reprojection_error(theta, obs, ctx)
        cost = self._cost(theta, obs, dict(ctx, previous=None, calibrating=False, betas=torch.as_tensor(
            np.asarray(betas, dtype=np.float64))[None]))  # fmt: skip
        return FitResult(
            body_pose=self._pose.reshape(NUM_BODY_JOINTS, 3).copy(),
            Rh=_vector_from_rotation(self._rotation),
            Th=self._translation.copy(),
            betas=np.asarray(betas, dtype=np.float64).copy(),
            rms_px=rms_px,
            rms_units=rms_units,
            used_targets=used,
            reinitialised=reinitialised,
            cost=cost,
        )

    def add_calibration(self, result: FitResult, confidence: float) -> None:
        """Count a frame's fitted shape towards calibration (only confident frames count)."""
        if self.calibrated or confidence < self.config.calibration_min_confidence:
            return
        self._calibration.append((float(confidence), result.betas.copy()))
        weights = np.array([c for c, _ in self._calibration])
        stack = np.stack([b for _, b in self._calibration])
        self.betas = (weights[:, None] * stack).sum(axis=0) / weights.sum()
        if len(self._calibration) >= self.config.calibration_frames:
            self.calibrated = True
            log.info(
                "shape calibrated over %d frames: betas %s", len(self._calibration), np.round(self.betas, 2)
            )

    def _reprojection_error(self, theta, obs, ctx) -> tuple[float, float, int]:
        with torch.no_grad():
            ctx = dict(ctx, robust=torch.ones_like(obs.weight))
            _, norms = self._residuals(theta[None], obs, ctx)
        weight = obs.weight
        used = int((weight > 0).sum())
        mean_sq = float((weight * norms[0] ** 2).sum() / weight.sum().clamp(min=1e-9))
        rms_units = math.sqrt(mean_sq)
        return rms_units, rms_units * obs.unit_px, used

    def _initialise(self, obs: _Observation, ctx: dict, active: torch.Tensor) -> tuple[torch.Tensor, dict]:
        """Fit from scratch: for each starting pose (the current one, the rest pose, arms down),
        the best of several global rotations after a short rotation + translation refinement, then
        a full fit; the lowest cost wins. Returns theta and the context (its base rotation)."""
        cfg = self.config
        best = None
        starts = [self._pose, np.zeros(POSE_PARAMS), RELAXED_POSE]
        seen = []
        for start in starts:
            if any(np.allclose(start, other) for other in seen):
                continue
            seen.append(start)
            rotation, translation = self._best_placement(obs, ctx, start)
            local_ctx = dict(ctx, base_rotation=torch.as_tensor(rotation, dtype=DTYPE))
            theta_np = np.concatenate([np.zeros(3), translation, start])
            if ctx["calibrating"]:
                theta_np = np.concatenate([theta_np, self.betas])
            theta, _ = self._solve(
                torch.as_tensor(theta_np, dtype=DTYPE), active, obs, local_ctx, cfg.init_iterations
            )
            cost = self._cost(theta, obs, local_ctx)
            if best is None or cost < best[0]:
                best = (cost, theta, local_ctx)
        return best[1], best[2]

    def _cost(self, theta: torch.Tensor, obs: _Observation, ctx: dict) -> float:
        """The robust (Cauchy) cost of a solution, comparable between solutions of one frame."""
        with torch.no_grad():
            plain = dict(ctx, robust=torch.ones_like(obs.weight))
            res, norms = self._residuals(theta[None], obs, plain)
            num_2d = 2 * obs.xy.shape[0]
            c = self.config.robust_scale
            cauchy = (c * c * torch.log1p((norms[0] / c) ** 2) * obs.weight).sum()
            return float(cauchy + (res[0, num_2d:] ** 2).sum())

    def _local_points(self, betas: torch.Tensor, pose: np.ndarray) -> np.ndarray:
        """The targets' body points at ``pose`` with no global rotation or translation, (T, 3)."""
        with torch.no_grad():
            return self.model(
                betas,
                torch.as_tensor(pose, dtype=DTYPE).reshape(1, NUM_BODY_JOINTS, 3),
                torch.zeros(1, 3, dtype=DTYPE),
                torch.zeros(1, 3, dtype=DTYPE),
            )[0].numpy()

    def _best_placement(
        self, obs: _Observation, ctx: dict, pose: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Global rotation and translation hypotheses at ``pose``; the best after a short refinement."""
        cfg = self.config
        local = self._local_points(ctx["betas"], pose)
        candidates = [FACING_CAMERA @ _yaw(deg) for deg in YAW_HYPOTHESES_DEG]
        if obs.world is not None:
            candidate = self._rotation_from_bones(local, obs)
            if candidate is not None:
                candidates.insert(0, candidate)
        best = None
        global_ctx = dict(ctx, calibrating=False, previous=None)
        for rotation in candidates:
            translation = self._initial_translation(local, rotation, obs)
            theta = torch.as_tensor(np.concatenate([np.zeros(3), translation, pose]), dtype=DTYPE)
            global_ctx["base_rotation"] = torch.as_tensor(rotation, dtype=DTYPE)
            theta, cost = self._solve(
                theta, torch.arange(GLOBAL_PARAMS), obs, global_ctx, max(cfg.global_iterations, 1)
            )
            if best is None or cost < best[0]:
                refined = rotation @ _rotation_from_vector(theta[:3].numpy())
                best = (cost, refined, theta[3:6].numpy().copy())
        return best[1], best[2]

    def _rotation_from_bones(self, local: np.ndarray, obs: _Observation) -> np.ndarray | None:
        """The rotation taking the body's bone directions onto the network's (Kabsch), if enough agree."""
        usable = obs.world_weight.numpy() > 0
        if usable.sum() < 3:
            return None
        start, end = self._bone_start.numpy(), self._bone_end.numpy()
        body_dirs = local[end] - local[start]
        body_dirs /= np.maximum(np.linalg.norm(body_dirs, axis=1, keepdims=True), 1e-9)
        source = np.concatenate([body_dirs[usable], -body_dirs[usable]])
        target = np.concatenate([obs.world.numpy()[usable], -obs.world.numpy()[usable]])
        return kabsch(source, target)

    def _initial_translation(self, local: np.ndarray, rotation: np.ndarray, obs: _Observation) -> np.ndarray:
        """Depth from the ratio of 3D to 2D spans of the used points; x, y from their centroid."""
        used = obs.weight.numpy() > 0
        points = local[used] @ rotation.T
        xy = obs.xy.numpy()[used]
        span_3d = np.linalg.norm(points[:, None, :2] - points[None, :, :2], axis=-1).max()
        span_2d = np.linalg.norm(xy[:, None] - xy[None], axis=-1).max()
        focal = 0.5 * (self.K[0, 0] + self.K[1, 1])
        depth = float(np.clip(focal * span_3d / max(span_2d, 1.0), 0.3, 50.0))
        centre = xy.mean(axis=0)
        ray = np.array(
            [(centre[0] - self.K[0, 2]) / self.K[0, 0], (centre[1] - self.K[1, 2]) / self.K[1, 1], 1.0]
        )
        return ray * depth - points.mean(axis=0) * np.array([1.0, 1.0, 0.0])
