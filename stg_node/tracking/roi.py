"""Rotated square regions of interest and the affine maps between them and a network's input.

Top-down pose networks look at a crop around the person, rotated so the body stands upright.
A :class:`Roi` is that crop in image pixels (project convention: pixel (r, c) has its centre at
(c, r)); :func:`crop_affine` gives the 2x3 map from the image to a ``size x size`` network input
and :func:`roi_to_image` takes points the network reports back to the image.

Conventions match MediaPipe's (``AlignmentPointsRectsCalculator``, ``RectTransformationCalculator``,
``LandmarkProjectionCalculator``): a network coordinate ``u`` in ``[0, size]`` (pixel ``i`` spans
``[i, i + 1)``) is the normalised position ``u / size`` in the crop, and normalised ``(s, t)`` lies
at ``centre + side * R(rotation) @ (s - 1/2, t - 1/2)`` in the image, rotation clockwise on screen
(image y points down).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

# MediaPipe's ROI margin around the alignment box of BlazePose (pose_detection_to_roi.pbtxt).
ROI_SCALE = 1.25
# The body's axis (hip centre -> the scale point above the head) points up in the crop.
TARGET_ANGLE_RAD = math.pi / 2


@dataclass(frozen=True)
class Roi:
    """A rotated square in image pixels: centre (x, y), side length, rotation (radians, clockwise)."""

    center_x: float
    center_y: float
    side: float
    rotation: float

    def corners(self) -> np.ndarray:
        """(4, 2) image positions of the crop's corners: top-left, top-right, bottom-right, bottom-left."""
        unit = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
        return normalized_to_image(unit, self)

    def contains(self, points: np.ndarray) -> np.ndarray:
        """Boolean (N,): which image points lie inside the square."""
        local = image_to_normalized(np.asarray(points, dtype=np.float64), self)
        return np.all((local >= 0.0) & (local <= 1.0), axis=-1)


def normalize_radians(angle: float) -> float:
    """Wrap to [-pi, pi)."""
    return angle - 2 * math.pi * math.floor((angle + math.pi) / (2 * math.pi))


def roi_from_alignment(
    center_xy, scale_xy, *, scale: float = ROI_SCALE, target_angle: float = TARGET_ANGLE_RAD
) -> Roi:
    """The ROI of two alignment points (MediaPipe's pose convention).

    ``center_xy`` (the hip centre) is the ROI centre; twice its distance to ``scale_xy`` (a point
    above the head) is the box side before the ``scale`` margin; the rotation turns the vector
    between them to ``target_angle`` (straight up on screen).
    """
    cx, cy = (float(v) for v in center_xy)
    sx, sy = (float(v) for v in scale_xy)
    side = 2.0 * math.hypot(sx - cx, sy - cy) * scale
    rotation = normalize_radians(target_angle - math.atan2(-(sy - cy), sx - cx))
    return Roi(cx, cy, side, rotation)


def _rotation(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s], [s, c]])


def normalized_to_image(points: np.ndarray, roi: Roi) -> np.ndarray:
    """(..., 2) normalised crop coordinates (0..1) -> image pixels."""
    points = np.asarray(points, dtype=np.float64)
    offset = (points - 0.5) @ _rotation(roi.rotation).T * roi.side
    return offset + np.array([roi.center_x, roi.center_y])


def image_to_normalized(points: np.ndarray, roi: Roi) -> np.ndarray:
    """(..., 2) image pixels -> normalised crop coordinates (0..1); the inverse of normalized_to_image."""
    points = np.asarray(points, dtype=np.float64)
    local = (points - np.array([roi.center_x, roi.center_y])) @ _rotation(roi.rotation) / roi.side
    return local + 0.5


def roi_to_image(points: np.ndarray, roi: Roi, input_size: int) -> np.ndarray:
    """(..., 2) network coordinates (0..input_size, MediaPipe's pixel convention) -> image pixels."""
    return normalized_to_image(np.asarray(points, dtype=np.float64) / input_size, roi)


def crop_affine(roi: Roi, input_size: int) -> np.ndarray:
    """2x3 affine taking image pixel centres to network pixel centres (for ``cv2.warpAffine``).

    Network pixel ``i`` (OpenCV integer centre) has normalised coordinate ``(i + 1/2) / size``;
    image pixel centres sit at integer positions in the project's convention.
    """
    # image = A @ net + b, with net the OpenCV pixel index; invert for warpAffine's forward map.
    rot = _rotation(roi.rotation)
    scale = roi.side / input_size
    linear = rot * scale
    origin = np.array([roi.center_x, roi.center_y]) + rot @ np.array([-0.5, -0.5]) * roi.side
    offset = origin + linear @ np.array([0.5, 0.5])
    inverse_linear = np.linalg.inv(linear)
    return np.hstack([inverse_linear, (-inverse_linear @ offset)[:, None]])


def warp_to_input(image: np.ndarray, roi: Roi, input_size: int, border=cv2.BORDER_REPLICATE) -> np.ndarray:
    """The ``input_size x input_size`` crop of ``image`` under ``roi`` (bilinear)."""
    return cv2.warpAffine(
        image,
        crop_affine(roi, input_size),
        (input_size, input_size),
        flags=cv2.INTER_LINEAR,
        borderMode=border,
    )


def warp_from_input(values: np.ndarray, roi: Roi, input_size: int, width: int, height: int) -> np.ndarray:
    """Put a network-input-sized map (e.g. a segmentation) back into the image frame; zero outside."""
    return cv2.warpAffine(
        values,
        crop_affine(roi, input_size),
        (width, height),
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0,
    )


@dataclass(frozen=True)
class Letterbox:
    """How a full image was fitted into a square network input: uniform scale plus padding."""

    scale: float  # network pixels per image pixel
    pad_x: float  # network pixels of padding on the left
    pad_y: float  # and at the top
    input_size: int

    @classmethod
    def fit(cls, width: int, height: int, input_size: int) -> Letterbox:
        scale = input_size / max(width, height)
        return cls(scale, (input_size - width * scale) / 2.0, (input_size - height * scale) / 2.0, input_size)

    def affine(self) -> np.ndarray:
        """2x3 map of image pixel centres to network pixel centres."""
        s = self.scale
        # continuous: net = s * (img + 1/2) + pad ; OpenCV centres: net_i + 1/2 = that.
        return np.array([[s, 0.0, s * 0.5 + self.pad_x - 0.5], [0.0, s, s * 0.5 + self.pad_y - 0.5]])

    def to_image(self, normalized: np.ndarray) -> np.ndarray:
        """(..., 2) normalised network coordinates (0..1) -> image pixel positions."""
        net = np.asarray(normalized, dtype=np.float64) * self.input_size
        return (net - np.array([self.pad_x, self.pad_y])) / self.scale - 0.5

    def apply(self, image: np.ndarray) -> np.ndarray:
        return cv2.warpAffine(
            image,
            self.affine(),
            (self.input_size, self.input_size),
            flags=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=0,
        )
