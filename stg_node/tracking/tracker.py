"""The live tracker: frame in, SMPL parameters + person mask + confidence out (a PoseEstimator).

Per frame: keypoints from the detector (on a copy scaled to at most ``max_side`` pixels, mapped
back to full resolution), undistorted, fitted (fitting.py), smoothed (One-Euro), a mask from the
masker, cleaned to the person's connected parts, and a confidence:

``confidence = presence x visibility x fit x people x continuity x border x blur``

- presence: the detector's belief that a person is there (0 when none was found);
- visibility: mean score of the torso points (shoulders, hips): low when the person is cut off;
- fit: ``1 / (1 + (rms / bad_fit_units)^2)``, rms the fit's keypoint residual in units of 1 %
  of the person's height: low when no anatomical pose explains the keypoints;
- people: ``multi_person_factor`` when the detector sees more than one person (the mask and
  the keypoints may mix them up);
- continuity: ``jump_factor`` when the global rotation jumped by more than ``max_jump_deg`` since
  the last frame (a left/right swap or a re-initialisation that flipped the body);
- border, blur: the person cut by the image border, or smeared by motion blur (frame_checks.py).

When nobody is found the last good parameters are held (never a wild pose), the mask is empty
and the confidence is 0. The trainer skips frames below its threshold (docs/TRACKING.md).
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
from stg_node.tracking.camera import Intrinsics
from stg_node.tracking.detectors import KeypointDetector
from stg_node.tracking.fitting import FACING_CAMERA, FitConfig, FitResult, SmplFitter
from stg_node.tracking.frame_checks import FrameChecks
from stg_node.tracking.layouts import get_layout
from stg_node.tracking.masks import Masker, SegmentationMasker, clean_mask
from stg_node.tracking.smoothing import OneEuroConfig, PoseSmoother
from stg_node.tracking.types import Keypoints, SmplParams, TrackEstimate

log = logging.getLogger(__name__)

TORSO = ("left_shoulder", "right_shoulder", "left_hip", "right_hip")
DEFAULT_DISTANCE_M = 3.0  # where the body is put before anyone was ever seen


@dataclass(frozen=True)
class TrackerConfig:
    max_side: int = 512  # detect and mask on frames scaled to at most this long side (0 = native)
    smoothing: bool = True
    rotation_filter: OneEuroConfig = field(default_factory=OneEuroConfig)
    translation_filter: OneEuroConfig = field(
        default_factory=lambda: OneEuroConfig(min_cutoff_hz=1.0, beta=2.0)
    )
    bad_fit_units: float = 4.0
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


@dataclass
class StageTimes:
    """Seconds spent in each stage of the last frame."""

    detect: float = 0.0
    fit: float = 0.0
    mask: float = 0.0
    total: float = 0.0


def scaled_frame(frame: np.ndarray, max_side: int) -> tuple[np.ndarray, float]:
    """The frame shrunk to at most ``max_side`` on its long side (0: as it is) and the scale used."""
    height, width = frame.shape[:2]
    if max_side == 0 or max(height, width) <= max_side:
        return frame, 1.0
    scale = max_side / max(height, width)
    size = (max(1, round(width * scale)), max(1, round(height * scale)))
    return cv2.resize(frame, size, interpolation=cv2.INTER_AREA), scale


def person_mask(
    masker: Masker, frame, small, scale: float, keypoints: Keypoints, distance_m: float, config: TrackerConfig
) -> np.ndarray:
    """The person's mask at ``frame``'s size, made on the ``scale``-d ``small`` copy (keypoints in
    full-resolution pixels), cleaned around the confident keypoints when the config asks."""
    small_keypoints = keypoints
    if scale != 1.0:
        small_keypoints = replace(keypoints, xy=((keypoints.xy + 0.5) * scale - 0.5).astype(np.float32))
    mask = masker(small, small_keypoints, distance_m)
    if config.clean_masks:
        confident = small_keypoints.xy[np.asarray(small_keypoints.score) >= config.fit.min_keypoint_score]
        mask = clean_mask(mask, confident)
    if scale != 1.0:
        mask = cv2.resize(mask, (frame.shape[1], frame.shape[0]), interpolation=cv2.INTER_LINEAR)
        mask = np.where(mask >= 128, np.uint8(255), np.uint8(0))
    return mask


def smoothed_params(
    fit: FitResult, smoother: PoseSmoother, timestamp: float, smoothing: bool, betas: np.ndarray
) -> tuple[SmplParams, np.ndarray]:
    """A fit as SMPL parameters with the fitter's shape ``betas``: smoothed when ``smoothing`` (the
    filter restarted when the fit started over); also the smoothed translation at full precision."""
    body_pose, Rh, Th = fit.body_pose, fit.Rh, fit.Th
    if fit.reinitialised:
        smoother.reset()
    if smoothing:
        body_pose, Rh, Th = smoother(body_pose, Rh, Th, timestamp)
    smpl = SmplParams(
        poses=np.concatenate([np.zeros((1, 3)), body_pose]).astype(np.float32),
        Rh=np.asarray(Rh, np.float32),
        Th=np.asarray(Th, np.float32),
        betas=betas.astype(np.float32),
    )
    return smpl, Th


def rotation_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """The angle between two axis-angle rotations, degrees."""
    ra = lbs.axis_angle_to_matrix(torch.as_tensor(a, dtype=torch.float64))
    rb = lbs.axis_angle_to_matrix(torch.as_tensor(b, dtype=torch.float64))
    cosine = float(((torch.trace(ra.T @ rb) - 1.0) / 2.0).clamp(-1.0, 1.0))
    return math.degrees(math.acos(cosine))


class Tracker:
    """Implements :class:`~stg_node.tracking.types.PoseEstimator` for one camera and one person."""

    def __init__(
        self,
        detector: KeypointDetector,
        body: BodyModel,
        intrinsics: Intrinsics,
        config: TrackerConfig | None = None,
        masker: Masker | None = None,
        *,
        betas: np.ndarray | None = None,
    ):
        self.config = config or TrackerConfig()
        self.config.validate()
        self.detector = detector
        self.layout = get_layout(detector.layout)
        self.intrinsics = intrinsics
        self.masker = masker if masker is not None else SegmentationMasker()
        self.fitter = SmplFitter(body, self.layout, intrinsics.K, self.config.fit, betas=betas)
        self.smoother = PoseSmoother(self.config.rotation_filter, self.config.translation_filter)
        self._torso = [self.layout.index(name) for name in TORSO if name in self.layout.names]
        self.checks = FrameChecks()  # cut by the border, motion blur (frame_checks.py)
        self.times = StageTimes()
        self._last: TrackEstimate | None = None
        self._last_raw_rh: np.ndarray | None = None

    def reset(self) -> None:
        """Forget tracking and smoothing (a cut in the video); the calibrated shape is kept."""
        self.detector.reset()
        self.fitter.lose()
        self.smoother.reset()
        self.masker.reset()
        self.checks.reset()
        self._last = None
        self._last_raw_rh = None

    # ---- helpers ----------------------------------------------------------------------------
    def _hold(self, frame_shape, timestamp: float, flags: tuple[str, ...], keypoints=None) -> TrackEstimate:
        """Nobody usable this frame: the last good parameters, an empty mask, confidence 0."""
        height, width = frame_shape[:2]
        if self._last is not None:
            smpl = self._last.smpl
        else:
            smpl = SmplParams(
                poses=np.zeros((24, 3), np.float32),
                Rh=lbs.matrix_to_axis_angle(torch.as_tensor(FACING_CAMERA)).numpy().astype(np.float32),
                Th=np.array([0.0, 0.0, DEFAULT_DISTANCE_M], np.float32),
                betas=self.fitter.betas.astype(np.float32),
            )
        return TrackEstimate(
            smpl=smpl,
            mask=np.zeros((height, width), np.uint8),
            confidence=0.0,
            timestamp=float(timestamp),
            keypoints=keypoints,
            flags=flags,
        )

    def _confidence(self, keypoints: Keypoints, fit: FitResult) -> tuple[float, list[str]]:
        cfg = self.config
        flags = []
        score = np.asarray(keypoints.score, dtype=np.float64)
        visibility = float(np.mean(score[self._torso])) if self._torso else float(np.mean(score))
        quality = 1.0 / (1.0 + (fit.rms_units / cfg.bad_fit_units) ** 2)
        confidence = float(np.clip(keypoints.presence, 0.0, 1.0)) * visibility * quality
        if visibility < 0.5:
            flags.append("partly_visible")
        if quality < 0.5:
            flags.append("bad_fit")
        if keypoints.people > 1:
            confidence *= cfg.multi_person_factor
            flags.append("multiple_people")
        if self._last_raw_rh is not None and not fit.reinitialised:
            if rotation_angle_deg(self._last_raw_rh, fit.Rh) > cfg.max_jump_deg:
                confidence *= cfg.jump_factor
                flags.append("jump")
        return float(np.clip(confidence, 0.0, 1.0)), flags

    # ---- the estimator ------------------------------------------------------------------------
    def estimate(self, frame_rgb: np.ndarray, timestamp: float) -> TrackEstimate:
        frame = np.asarray(frame_rgb)
        if frame.ndim != 3 or frame.shape[2] != 3 or frame.dtype != np.uint8:
            raise ValueError(f"expected an (H, W, 3) uint8 RGB frame, got {frame.dtype} {frame.shape}")
        if (frame.shape[1], frame.shape[0]) != (self.intrinsics.width, self.intrinsics.height):
            raise ValueError(
                f"frame is {frame.shape[1]}x{frame.shape[0]} but the intrinsics are for "
                f"{self.intrinsics.width}x{self.intrinsics.height}"
            )
        if not math.isfinite(timestamp):
            raise ValueError(f"timestamp must be finite, got {timestamp}")
        t_start = time.perf_counter()
        small, scale = scaled_frame(frame, self.config.max_side)
        keypoints = self.detector(small)
        t_detect = time.perf_counter()
        self.times = StageTimes(detect=t_detect - t_start)
        if keypoints is None:
            self.fitter.lose()
            self.smoother.reset()
            self.times.total = time.perf_counter() - t_start
            return self._hold(frame.shape, timestamp, ("no_person",))
        if scale != 1.0:
            # Back to full-resolution pixel centres.
            keypoints = replace(keypoints, xy=((keypoints.xy + 0.5) / scale - 0.5).astype(np.float32))
        masks: list[np.ndarray] = []
        silhouette = None
        if self.fitter.uses_silhouette:
            # The mask is made at the keypoint fit's distance, then refines that fit.
            def silhouette(fit: FitResult) -> np.ndarray:
                masks.append(self._mask(frame, small, scale, keypoints, float(fit.Th[2])))
                return self.intrinsics.undistort_mask(masks[0])

        estimate = self.fit_keypoints(keypoints, timestamp, frame.shape, silhouette=silhouette)
        t_fit = time.perf_counter()
        self.times.fit = t_fit - t_detect
        if "too_few_keypoints" in estimate.flags:
            self.times.total = time.perf_counter() - t_start
            return estimate
        mask = masks[0] if masks else self._mask(frame, small, scale, keypoints, float(estimate.smpl.Th[2]))
        factor, image_flags = self.checks.check(small, mask, keypoints, self.layout)
        estimate = replace(
            estimate,
            mask=mask,
            confidence=float(estimate.confidence * factor),
            flags=estimate.flags + tuple(image_flags),
        )
        self.times.mask = time.perf_counter() - t_fit
        self.times.total = time.perf_counter() - t_start
        self._last = estimate
        return estimate

    def skip(self, frame_shape, timestamp: float, flags: tuple[str, ...]) -> TrackEstimate:
        """Nobody usable in this frame (what :meth:`estimate` does when the detector finds no one):
        tracking and smoothing start over, the last good parameters are held, confidence 0."""
        self.fitter.lose()
        self.smoother.reset()
        return self._hold(frame_shape, timestamp, flags)

    def fit_keypoints(
        self, keypoints: Keypoints, timestamp: float, frame_shape, *, silhouette=None
    ) -> TrackEstimate:
        """The fit, smoothing and keypoint-based confidence of one frame's (full-resolution) keypoints,
        with an empty mask: what :meth:`estimate` does after detection, and what a second pass over
        stored keypoints (another camera model, stg_node.tracking.focal) runs alone. ``silhouette``:
        a function from the keypoint fit to the person's (undistorted) mask, which then refines the
        fit (fitting.SmplFitter.refine_with_mask)."""
        xy = self.intrinsics.undistort_points(keypoints.xy)
        fit = self.fitter.fit(keypoints, timestamp, xy_undistorted=xy)
        if fit is None:
            self.fitter.lose()
            self.smoother.reset()
            return self._hold(frame_shape, timestamp, ("too_few_keypoints",), keypoints)
        if silhouette is not None:
            fit = self.fitter.refine_with_mask(silhouette(fit), timestamp) or fit
        confidence, flags = self._confidence(keypoints, fit)
        self.fitter.add_calibration(fit, confidence)
        self._last_raw_rh = fit.Rh
        smpl, _ = smoothed_params(fit, self.smoother, timestamp, self.config.smoothing, self.fitter.betas)
        estimate = TrackEstimate(
            smpl=smpl,
            mask=np.zeros(tuple(frame_shape[:2]), np.uint8),
            confidence=confidence,
            timestamp=float(timestamp),
            keypoints=keypoints,
            reprojection_px=fit.rms_px,
            flags=tuple(flags),
        )
        self._last = estimate
        return estimate

    def _mask(self, frame, small, scale, keypoints: Keypoints, distance_m: float) -> np.ndarray:
        return person_mask(self.masker, frame, small, scale, keypoints, distance_m, self.config)
