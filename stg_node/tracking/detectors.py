"""Keypoint detectors, pluggable: the :class:`KeypointDetector` protocol and the ones that ship.

- ``blazepose`` (default): MediaPipe's BlazePose full model under LiteRT (blazepose.py); 33
  points with visibility, metric 3D points and a person segmentation; its two network files are
  installed at setup (model_files.py).
- ``onnx``: a top-down COCO-17 pose network the user supplies (RTMPose, ViTPose, ... exported to
  ONNX), run by OpenCV's dnn module. Its output is recognised by shape: two SimCC vectors
  ``(1, 17, W*k)`` and ``(1, 17, H*k)`` (RTMPose), or heatmaps ``(1, 17, h, w)`` (ViTPose,
  HRNet). The person box comes from the previous frame's keypoints; on the first frame, or when
  the person was lost, the whole frame is used (so start with the person in view).

A detector is a callable ``detector(image_rgb) -> Keypoints | None`` with a ``layout`` name and
``reset()``. Anything with that shape plugs into :class:`~stg_node.tracking.tracker.Tracker`
(an OAK running the network on the device would be one).
"""

from __future__ import annotations

from pathlib import Path
from typing import Protocol, runtime_checkable

import cv2
import numpy as np

from stg_node.tracking.types import Keypoints

DETECTORS = ("blazepose", "onnx")
IMAGENET_MEAN = np.array([123.675, 116.28, 103.53], dtype=np.float32)
IMAGENET_STD = np.array([58.395, 57.12, 57.375], dtype=np.float32)
ONNX_INPUT_SIZE = (192, 256)  # width, height: RTMPose and ViTPose body models
BOX_MARGIN = 1.25
ONNX_MIN_SCORE = 0.3  # keypoints below this do not define the next frame's box


@runtime_checkable
class KeypointDetector(Protocol):
    layout: str

    def __call__(self, image_rgb: np.ndarray) -> Keypoints | None: ...

    def reset(self) -> None: ...


def _box_affine(center: np.ndarray, size: np.ndarray, input_size: tuple[int, int]) -> np.ndarray:
    """2x3 map of image pixel centres into a (w, h) network input showing the box (no rotation)."""
    width, height = input_size
    scale = np.array([width / size[0], height / size[1]])
    offset = np.array([width, height]) / 2.0 - 0.5 - scale * (center)
    return np.array([[scale[0], 0.0, offset[0]], [0.0, scale[1], offset[1]]])


def _aspect_box(center: np.ndarray, size: np.ndarray, input_size: tuple[int, int]) -> np.ndarray:
    """Grow ``size`` to the network input's aspect ratio."""
    aspect = input_size[0] / input_size[1]
    w, h = float(size[0]), float(size[1])
    if w > aspect * h:
        h = w / aspect
    else:
        w = h * aspect
    return np.array([w, h])


def decode_simcc(simcc_x: np.ndarray, simcc_y: np.ndarray, input_size: tuple[int, int]):
    """SimCC vectors -> (K, 2) network-input pixel positions and (K,) scores in [0, 1]."""
    sx = np.asarray(simcc_x, dtype=np.float64).reshape(-1, np.shape(simcc_x)[-1])
    sy = np.asarray(simcc_y, dtype=np.float64).reshape(-1, np.shape(simcc_y)[-1])
    ratio_x = sx.shape[1] / input_size[0]
    ratio_y = sy.shape[1] / input_size[1]
    x = np.argmax(sx, axis=1) / ratio_x
    y = np.argmax(sy, axis=1) / ratio_y
    score = np.clip(np.minimum(sx.max(axis=1), sy.max(axis=1)), 0.0, 1.0)
    return np.stack([x, y], axis=1), score


def decode_heatmaps(heatmaps: np.ndarray, input_size: tuple[int, int]):
    """(1, K, h, w) heatmaps -> (K, 2) network-input pixel positions and (K,) scores.

    Argmax with the usual quarter-pixel shift towards the higher neighbour; heatmap pixel centres
    map to input pixel centres (``x_in = (x_hm + 0.5) * stride - 0.5``).
    """
    maps = np.asarray(heatmaps, dtype=np.float64)
    maps = maps.reshape(-1, maps.shape[-2], maps.shape[-1])
    count, height, width = maps.shape
    flat = maps.reshape(count, -1).argmax(axis=1)
    ys, xs = np.divmod(flat, width)
    pos = np.stack([xs, ys], axis=1).astype(np.float64)
    for k in range(count):
        x, y = xs[k], ys[k]
        if 0 < x < width - 1:
            pos[k, 0] += 0.25 * np.sign(maps[k, y, x + 1] - maps[k, y, x - 1])
        if 0 < y < height - 1:
            pos[k, 1] += 0.25 * np.sign(maps[k, y + 1, x] - maps[k, y - 1, x])
    stride = np.array([input_size[0] / width, input_size[1] / height])
    score = np.clip(maps.reshape(count, -1).max(axis=1), 0.0, 1.0)
    return (pos + 0.5) * stride - 0.5, score


class OnnxPoseDetector:
    """A top-down COCO-17 ONNX pose network (see the module docstring)."""

    layout = "coco17"

    def __init__(self, runner, input_size: tuple[int, int] = ONNX_INPUT_SIZE):
        self._runner = runner
        self.input_size = (int(input_size[0]), int(input_size[1]))
        self._box: tuple[np.ndarray, np.ndarray] | None = None

    def reset(self) -> None:
        self._box = None

    def preprocess(self, image_rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(1, 3, h, w) float32 network input and the 2x3 image -> input affine."""
        height, width = image_rgb.shape[:2]
        if self._box is None:
            center, size = np.array([(width - 1) / 2.0, (height - 1) / 2.0]), np.array([width, height], float)
        else:
            center, size = self._box
        size = _aspect_box(center, size, self.input_size)
        affine = _box_affine(center, size, self.input_size)
        crop = cv2.warpAffine(
            image_rgb, affine, self.input_size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT
        )
        tensor = (crop.astype(np.float32) - IMAGENET_MEAN) / IMAGENET_STD
        return np.ascontiguousarray(tensor.transpose(2, 0, 1)[None]), affine

    def postprocess(self, outputs, affine: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Network outputs -> (17, 2) image positions and (17,) scores."""
        shapes = [np.shape(o) for o in outputs]
        if len(outputs) >= 2 and all(len(s) == 3 for s in shapes[:2]):
            a, b = outputs[0], outputs[1]
            # SimCC: the longer vector belongs to the taller axis when the input is taller than wide.
            x_first = (np.shape(a)[-1] / self.input_size[0]) == (np.shape(b)[-1] / self.input_size[1])
            simcc_x, simcc_y = (a, b) if x_first else (b, a)
            xy, score = decode_simcc(simcc_x, simcc_y, self.input_size)
        elif len(outputs) >= 1 and len(shapes[0]) == 4:
            xy, score = decode_heatmaps(outputs[0], self.input_size)
        else:
            raise ValueError(
                f"ONNX pose network outputs {shapes}: expected SimCC (1, 17, W*k) and (1, 17, H*k) or "
                "heatmaps (1, 17, h, w)"
            )
        if xy.shape[0] != 17:
            raise ValueError(f"ONNX pose network gives {xy.shape[0]} keypoints; stg-track expects COCO's 17")
        linear, offset = affine[:, :2], affine[:, 2]
        image_xy = (xy - offset) @ np.linalg.inv(linear).T
        return image_xy, score

    def __call__(self, image_rgb: np.ndarray) -> Keypoints | None:
        tensor, affine = self.preprocess(np.ascontiguousarray(image_rgb))
        xy, score = self.postprocess(self._runner(tensor), affine)
        good = score >= ONNX_MIN_SCORE
        if good.sum() < 4:
            self._box = None
            return None
        lo, hi = xy[good].min(axis=0), xy[good].max(axis=0)
        self._box = ((lo + hi) / 2.0, np.maximum(hi - lo, 16.0) * BOX_MARGIN)
        return Keypoints(layout=self.layout, xy=xy.astype(np.float32), score=score.astype(np.float32))


def make_detector(
    kind: str = "blazepose",
    *,
    model: str | Path | None = None,
    threads: int | None = None,
    redetect_every: int = 10,
) -> KeypointDetector:
    """A ready detector. ``model``: for ``onnx`` the network file; for ``blazepose`` a folder with
    the two .tflite files (default: the installed ones, model_files.py)."""
    from stg_node.tracking.runtime import OnnxRunner, TfliteRunner

    if kind == "blazepose":
        from stg_node.tracking.blazepose import BlazePose
        from stg_node.tracking.model_files import pose_model_paths

        paths = pose_model_paths(Path(model) if model is not None else None)
        return BlazePose(
            TfliteRunner(paths["detector"], threads),
            TfliteRunner(paths["landmarker"], threads),
            redetect_every=redetect_every,
        )
    if kind == "onnx":
        if model is None:
            raise ValueError("the onnx detector needs a model file (--pose-model FILE.onnx)")
        return OnnxPoseDetector(OnnxRunner(model, threads))
    raise ValueError(f"unknown detector {kind!r}; choose one of {', '.join(DETECTORS)}")
