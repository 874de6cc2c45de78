"""The multi-view tracker: one instant of a calibrated rig in, SMPL in the rig's world frame out.

Per instant: keypoints from every view (a detector per camera: each follows the person in its
own picture), undistorted with that camera's lens, one SMPL fit to all of them in the world frame
(multiview_fit.py: triangulation to start, multi-view reprojection, the single-view fit's priors),
One-Euro smoothing, a person mask per view, and a confidence:

``confidence = presence x visibility x fit x views x people x continuity``

- presence: the mean of the views' detector presence (a view that found nobody counts 0);
- visibility: the torso score (shoulders, hips) of the two best views: one camera may lose the
  person behind a chair while the others still see them;
- fit: ``1 / (1 + (rms / bad_fit_units)^2)`` over every view's keypoints;
- views: ``single_view_factor`` when only one view had usable keypoints (the depth is then a
  guess again: flag ``single_view``);
- people, continuity: as in one view (tracker.py).

:class:`MultiViewTracker.estimate` takes the frames of one instant in the rig's camera order
(the offline pipeline and the tracker node match them by time stamp first: sync.py).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
import torch

from stg_node.body import BodyModel, lbs
from stg_node.calibration.rig import Rig
from stg_node.tracking.camera import Intrinsics
from stg_node.tracking.detectors import KeypointDetector
from stg_node.tracking.fitting import FitConfig, FitResult
from stg_node.tracking.layouts import get_layout
from stg_node.tracking.masks import Masker, SegmentationMasker, clean_mask
from stg_node.tracking.multiview_fit import MultiViewFitter
from stg_node.tracking.smoothing import OneEuroConfig, PoseSmoother
from stg_node.tracking.types import Keypoints, SmplParams

log = logging.getLogger(__name__)

TORSO = ("left_shoulder", "right_shoulder", "left_hip", "right_hip")


@dataclass(frozen=True)
class MultiViewConfig:
    max_side: int = 512  # detect and mask on frames scaled to at most this long side (0 = native)
    smoothing: bool = True
    # Lighter than one camera's (2 Hz / 1 Hz): several views leave little noise to remove, and
    # the filter's lag costs more than it saves (docs/TRACKING.md#several-cameras).
    rotation_filter: OneEuroConfig = field(
        default_factory=lambda: OneEuroConfig(min_cutoff_hz=12.0, beta=20.0)
    )
    translation_filter: OneEuroConfig = field(
        default_factory=lambda: OneEuroConfig(min_cutoff_hz=8.0, beta=4.0)
    )
    bad_fit_units: float = 4.0
    single_view_factor: float = 0.5
    multi_person_factor: float = 0.1
    max_jump_deg: float = 60.0
    jump_factor: float = 0.2
    clean_masks: bool = True
    fit: FitConfig = field(default_factory=FitConfig)

    def validate(self) -> None:
        if self.max_side < 0 or 0 < self.max_side < 64:
            raise ValueError(f"max_side must be 0 (native) or at least 64 pixels, got {self.max_side}")
        if not self.bad_fit_units > 0:
            raise ValueError(f"bad_fit_units must be positive, got {self.bad_fit_units}")
        self.fit.validate()


@dataclass(frozen=True)
class MultiViewEstimate:
    """One instant's answer: SMPL parameters in the world frame, a mask per view, a confidence."""

    smpl: SmplParams  # poses (24, 3) with poses[0] = 0; Rh/Th in the rig's world frame
    masks: tuple[np.ndarray, ...]  # (H_v, W_v) uint8 per view, 255 on the person
    confidence: float
    timestamp: float
    keypoints: tuple[Keypoints | None, ...]  # per view, full-resolution pixels (None: nobody found)
    views_used: int = 0  # views whose keypoints entered the fit
    reprojection_px: float = float("nan")  # weighted RMS keypoint residual over the views
    flags: tuple[str, ...] = ()


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    ra = lbs.axis_angle_to_matrix(torch.as_tensor(a, dtype=torch.float64))
    rb = lbs.axis_angle_to_matrix(torch.as_tensor(b, dtype=torch.float64))
    cosine = float(((torch.trace(ra.T @ rb) - 1.0) / 2.0).clamp(-1.0, 1.0))
    return math.degrees(math.acos(cosine))


class MultiViewTracker:
    """Tracks one person in the frames of a calibrated rig (one detector and masker per camera)."""

    def __init__(
        self,
        detectors: list[KeypointDetector],
        body: BodyModel,
        rig: Rig,
        config: MultiViewConfig | None = None,
        maskers: list[Masker] | None = None,
        *,
        betas: np.ndarray | None = None,
    ):
        self.config = config or MultiViewConfig()
        self.config.validate()
        if len(detectors) != len(rig):
            raise ValueError(f"{len(detectors)} detectors for a rig of {len(rig)} cameras")
        layouts = {d.layout for d in detectors}
        if len(layouts) != 1:
            raise ValueError(f"every view's detector must use one keypoint layout, got {sorted(layouts)}")
        self.rig = rig
        self.detectors = list(detectors)
        self.layout = get_layout(detectors[0].layout)
        self.maskers = list(maskers) if maskers is not None else [SegmentationMasker() for _ in rig.cameras]
        if len(self.maskers) != len(rig):
            raise ValueError(f"{len(self.maskers)} maskers for a rig of {len(rig)} cameras")
        self.intrinsics = [
            Intrinsics(c.K, c.dist if c.dist.size else None, c.width, c.height, f"rig:{c.name}")
            for c in rig.cameras
        ]
        self.fitter = MultiViewFitter(
            body, self.layout, [(c.K, c.R, c.t) for c in rig.cameras], self.config.fit, betas=betas
        )
        self.smoother = PoseSmoother(self.config.rotation_filter, self.config.translation_filter)
        self._torso = [self.layout.index(n) for n in TORSO if n in self.layout.names]
        self._last: MultiViewEstimate | None = None
        self._last_raw_rh: np.ndarray | None = None
        self.seconds = {"detect": 0.0, "fit": 0.0, "mask": 0.0}  # the last instant's stages

    def reset(self) -> None:
        """Forget tracking and smoothing (a cut); the calibrated shape is kept."""
        for detector in self.detectors:
            detector.reset()
        for masker in self.maskers:
            masker.reset()
        self.fitter.lose()
        self.smoother.reset()
        self._last = None
        self._last_raw_rh = None

    # ---- helpers --------------------------------------------------------------------------------
    def _scaled(self, frame: np.ndarray) -> tuple[np.ndarray, float]:
        side = self.config.max_side
        height, width = frame.shape[:2]
        if side == 0 or max(height, width) <= side:
            return frame, 1.0
        scale = side / max(height, width)
        size = (max(1, round(width * scale)), max(1, round(height * scale)))
        return cv2.resize(frame, size, interpolation=cv2.INTER_AREA), scale

    def _check(self, frames: list[np.ndarray]) -> None:
        if len(frames) != len(self.rig):
            raise ValueError(f"expected {len(self.rig)} frames (one per camera), got {len(frames)}")
        for frame, camera in zip(frames, self.rig.cameras, strict=True):
            frame = np.asarray(frame)
            if frame.ndim != 3 or frame.shape[2] != 3 or frame.dtype != np.uint8:
                raise ValueError(
                    f"camera {camera.name}: expected an (H, W, 3) uint8 RGB frame, got {frame.shape}"
                )
            if (frame.shape[1], frame.shape[0]) != camera.image_size:
                raise ValueError(
                    f"camera {camera.name}: frame is {frame.shape[1]}x{frame.shape[0]} but the rig is "
                    f"calibrated for {camera.width}x{camera.height}"
                )

    def _confidence(self, keypoints, fit: FitResult, views_used: int) -> tuple[float, list[str]]:
        cfg = self.config
        flags = []
        presence = float(np.mean([0.0 if k is None else np.clip(k.presence, 0, 1) for k in keypoints]))
        torso = sorted(
            (float(np.mean(np.asarray(k.score)[self._torso])) for k in keypoints if k is not None),
            reverse=True,
        )
        visibility = float(np.mean(torso[:2])) if torso else 0.0
        quality = 1.0 / (1.0 + (fit.rms_units / cfg.bad_fit_units) ** 2)
        confidence = presence * visibility * quality
        if visibility < 0.5:
            flags.append("partly_visible")
        if quality < 0.5:
            flags.append("bad_fit")
        if views_used < 2:
            confidence *= cfg.single_view_factor
            flags.append("single_view")
        if any(k is not None and k.people > 1 for k in keypoints):
            confidence *= cfg.multi_person_factor
            flags.append("multiple_people")
        if self._last_raw_rh is not None and not fit.reinitialised:
            if _angle_deg(self._last_raw_rh, fit.Rh) > cfg.max_jump_deg:
                confidence *= cfg.jump_factor
                flags.append("jump")
        return float(np.clip(confidence, 0.0, 1.0)), flags

    def _hold(self, frames, timestamp, flags, keypoints) -> MultiViewEstimate:
        if self._last is not None:
            smpl = self._last.smpl
        else:
            smpl = SmplParams(
                poses=np.zeros((24, 3), np.float32),
                Rh=np.zeros(3, np.float32),
                Th=np.zeros(3, np.float32),
                betas=self.fitter.betas.astype(np.float32),
            )
        masks = tuple(np.zeros(f.shape[:2], np.uint8) for f in frames)
        return MultiViewEstimate(smpl, masks, 0.0, float(timestamp), tuple(keypoints), 0, float("nan"), flags)

    # ---- the estimator ------------------------------------------------------------------------------
    def estimate(self, frames: list[np.ndarray], timestamp: float) -> MultiViewEstimate:
        """Track one instant: ``frames`` in the rig's camera order, ``timestamp`` in seconds."""
        self._check(frames)
        if not math.isfinite(timestamp):
            raise ValueError(f"timestamp must be finite, got {timestamp}")
        t0 = time.perf_counter()
        smalls, keypoints, undistorted = [], [], []
        for frame, detector, intrinsics in zip(frames, self.detectors, self.intrinsics, strict=True):
            small, scale = self._scaled(np.asarray(frame))
            found = detector(small)
            if found is not None and scale != 1.0:
                found = replace(found, xy=((found.xy + 0.5) / scale - 0.5).astype(np.float32))
            smalls.append((small, scale))
            keypoints.append(found)
            undistorted.append(None if found is None else intrinsics.undistort_points(found.xy))
        t1 = time.perf_counter()
        self.seconds["detect"] = t1 - t0
        if all(k is None for k in keypoints):
            self.fitter.lose()
            self.smoother.reset()
            return self._hold(frames, timestamp, ("no_person",), keypoints)
        fit_inputs = [
            (k, u) if k is not None else (None, None) for k, u in zip(keypoints, undistorted, strict=True)
        ]
        fit = self.fitter.fit_views([k for k, _ in fit_inputs], [u for _, u in fit_inputs], timestamp)
        t2 = time.perf_counter()
        self.seconds["fit"] = t2 - t1
        if fit is None:
            self.fitter.lose()
            self.smoother.reset()
            return self._hold(frames, timestamp, ("too_few_keypoints",), keypoints)
        views_used = sum(
            1
            for v, k in enumerate(keypoints)
            if k is not None
            and v not in self.fitter.dropped_views
            and int((np.asarray(k.score) >= self.config.fit.min_keypoint_score).sum()) >= 4
        )
        confidence, flags = self._confidence(keypoints, fit, views_used)
        if self.fitter.dropped_views:
            flags.append("view_disagrees")
        self.fitter.add_calibration(fit, confidence)
        self._last_raw_rh = fit.Rh
        body_pose, Rh, Th = fit.body_pose, fit.Rh, fit.Th
        if fit.reinitialised:
            self.smoother.reset()
        if self.config.smoothing:
            body_pose, Rh, Th = self.smoother(body_pose, Rh, Th, timestamp)
        smpl = SmplParams(
            poses=np.concatenate([np.zeros((1, 3)), body_pose]).astype(np.float32),
            Rh=np.asarray(Rh, np.float32),
            Th=np.asarray(Th, np.float32),
            betas=self.fitter.betas.astype(np.float32),
        )
        masks = tuple(
            self._mask(frame, small, scale, kp, camera, Th, masker)
            for frame, (small, scale), kp, camera, masker in zip(
                frames, smalls, keypoints, self.rig.cameras, self.maskers, strict=True
            )
        )
        self.seconds["mask"] = time.perf_counter() - t2
        estimate = MultiViewEstimate(
            smpl, masks, confidence, float(timestamp), tuple(keypoints), views_used, fit.rms_px, tuple(flags)
        )
        self._last = estimate
        return estimate

    def _mask(self, frame, small, scale, keypoints, camera, Th, masker) -> np.ndarray:
        if keypoints is None:
            return np.zeros(frame.shape[:2], np.uint8)
        small_keypoints = keypoints
        if scale != 1.0:
            small_keypoints = replace(keypoints, xy=((keypoints.xy + 0.5) * scale - 0.5).astype(np.float32))
        distance = float((camera.R @ np.asarray(Th, np.float64) + camera.t)[2])
        mask = masker(small, small_keypoints, distance)
        if self.config.clean_masks:
            confident = small_keypoints.xy[
                np.asarray(small_keypoints.score) >= self.config.fit.min_keypoint_score
            ]
            mask = clean_mask(mask, confident)
        if scale != 1.0:
            mask = cv2.resize(mask, (frame.shape[1], frame.shape[0]), interpolation=cv2.INTER_LINEAR)
            mask = np.where(mask >= 128, np.uint8(255), np.uint8(0))
        return mask
