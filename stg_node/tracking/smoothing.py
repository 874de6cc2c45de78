"""Temporal smoothing of the fitted parameters: the One-Euro filter, on rotations and translations.

The One-Euro filter (Casiez, Roussel, Vogel, CHI 2012) is a low-pass filter whose cutoff rises
with speed: ``cutoff = min_cutoff + beta * |speed|``. A still person gets a low cutoff (no jitter);
a fast limb a high one (little lag). It needs the frame times, so it copes with dropped frames.

Rotations are filtered as unit quaternions: each new one is first put on the same hemisphere as
the previous output (q and -q are the same rotation), filtered per component, then renormalised.
This is accurate for the small frame-to-frame changes the filter sees and never wraps at pi,
which filtering axis-angle vectors directly would.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from stg_node.body import lbs


@dataclass(frozen=True)
class OneEuroConfig:
    min_cutoff_hz: float = 2.0  # cutoff at rest: lower = smoother, more lag
    beta: float = 10.0  # how fast the cutoff rises with speed (per unit of the signal per second)
    derivative_cutoff_hz: float = 1.0

    def validate(self) -> None:
        if not (self.min_cutoff_hz > 0 and self.derivative_cutoff_hz > 0 and self.beta >= 0):
            raise ValueError(f"One-Euro cutoffs must be positive and beta >= 0, got {self}")


def _alpha(cutoff_hz: float | np.ndarray, dt: float) -> float | np.ndarray:
    tau = 1.0 / (2.0 * math.pi * cutoff_hz)
    return 1.0 / (1.0 + tau / dt)


class OneEuroFilter:
    """One-Euro filter of a fixed-shape array signal; ``filter(x, t) -> smoothed x``."""

    def __init__(self, config: OneEuroConfig | None = None):
        self.config = config or OneEuroConfig()
        self.config.validate()
        self.reset()

    def reset(self) -> None:
        self._value: np.ndarray | None = None
        self._speed: np.ndarray | None = None
        self._time: float | None = None

    def filter(self, value: np.ndarray, timestamp: float) -> np.ndarray:
        value = np.asarray(value, dtype=np.float64)
        if self._value is None or self._time is None or timestamp <= self._time:
            if self._value is not None and self._value.shape != value.shape:
                raise ValueError(f"signal shape changed from {self._value.shape} to {value.shape}")
            self._value = value.copy()
            self._speed = np.zeros_like(value)
            self._time = float(timestamp)
            return value.copy()
        if value.shape != self._value.shape:
            raise ValueError(f"signal shape changed from {self._value.shape} to {value.shape}")
        cfg = self.config
        dt = float(timestamp) - self._time
        speed = (value - self._value) / dt
        a_d = _alpha(cfg.derivative_cutoff_hz, dt)
        self._speed = self._speed + a_d * (speed - self._speed)
        cutoff = cfg.min_cutoff_hz + cfg.beta * np.abs(self._speed)
        a = _alpha(cutoff, dt)
        self._value = self._value + a * (value - self._value)
        self._time = float(timestamp)
        return self._value.copy()


def _to_quaternions(axis_angle: np.ndarray) -> np.ndarray:
    rotations = lbs.axis_angle_to_matrix(torch.as_tensor(axis_angle, dtype=torch.float64))
    return lbs.matrix_to_quaternion(rotations).numpy()


def _to_axis_angle(quaternions: np.ndarray) -> np.ndarray:
    rotations = lbs.quaternion_to_matrix(torch.as_tensor(quaternions, dtype=torch.float64))
    return lbs.matrix_to_axis_angle(rotations).numpy()


class RotationFilter:
    """One-Euro filtering of (N, 3) axis-angle rotations through quaternions (see the module doc)."""

    def __init__(self, config: OneEuroConfig | None = None):
        self._filter = OneEuroFilter(config)
        self._last: np.ndarray | None = None

    def reset(self) -> None:
        self._filter.reset()
        self._last = None

    def filter(self, axis_angle: np.ndarray, timestamp: float) -> np.ndarray:
        quats = _to_quaternions(np.asarray(axis_angle, dtype=np.float64).reshape(-1, 3))
        if self._last is not None and self._last.shape == quats.shape:
            flip = np.sum(quats * self._last, axis=-1) < 0
            quats[flip] *= -1.0
        smoothed = self._filter.filter(quats, timestamp)
        smoothed /= np.linalg.norm(smoothed, axis=-1, keepdims=True)
        self._last = smoothed
        return _to_axis_angle(smoothed).reshape(np.shape(axis_angle))


class PoseSmoother:
    """Smooths a stream of (body pose, Rh, Th): rotations as quaternions, Th directly."""

    def __init__(self, rotation: OneEuroConfig | None = None, translation: OneEuroConfig | None = None):
        self._pose = RotationFilter(rotation)
        self._global = RotationFilter(rotation)
        self._translation = OneEuroFilter(translation or OneEuroConfig(min_cutoff_hz=1.0, beta=2.0))

    def reset(self) -> None:
        self._pose.reset()
        self._global.reset()
        self._translation.reset()

    def __call__(self, body_pose: np.ndarray, Rh: np.ndarray, Th: np.ndarray, timestamp: float):
        return (
            self._pose.filter(body_pose, timestamp),
            self._global.filter(np.asarray(Rh).reshape(1, 3), timestamp).reshape(3),
            self._translation.filter(Th, timestamp),
        )
