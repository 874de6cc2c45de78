"""BlazePose (MediaPipe's pose landmarker, "full" model) re-implemented around two plain networks.

MediaPipe runs BlazePose as a graph of C++ calculators; here the same steps are numpy around
two TFLite networks (docs/TRACKING.md says why and where the files come from):

1. **Person detector** (``pose_detection.tflite``, 224x224, only when no person is tracked, and
   every ``redetect_every`` frames to notice a second person): the whole image letterboxed,
   values in [-1, 1]; 2254 SSD anchors; each row = box (cx, cy, w, h) + 4 keypoints relative to
   its anchor; sigmoid scores; weighted non-maximum suppression. Keypoint 0 is the hip centre,
   keypoint 1 a point above the head that encodes size and rotation.
2. **Landmark network** (``pose_landmark_full.tflite``, 256x256, every frame): the rotated
   square ROI around the person, values in [0, 1]. Outputs 39 landmarks x (x, y, z, visibility,
   presence) in crop pixels (33 body points + 2 alignment points + 4 unused), a pose-presence
   score, a 256x256 segmentation (logits), 64x64x39 heatmaps (refine the landmarks: a 7x7
   sigmoid-weighted mean around each) and 39 world landmarks in metres (hip-centred,
   camera-aligned axes, rotated back by the ROI's rotation).
3. **Tracking**: the next frame's ROI comes from this frame's alignment landmarks 33 and 34, so
   the detector is skipped while the person stays found.

Everything numerical here is pure numpy and takes the networks as callables
(``runner(input) -> list of arrays``), so the tests check the pre- and post-processing against
fake networks whose output is known.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from stg_node.tracking.roi import (
    Letterbox,
    Roi,
    roi_from_alignment,
    roi_to_image,
    warp_from_input,
    warp_to_input,
)
from stg_node.tracking.types import Keypoints

# ---- the networks' fixed geometry (MediaPipe pose_detection_cpu / pose_landmark_by_roi_cpu) -----
DETECTOR_INPUT = 224
LANDMARK_INPUT = 256
NUM_ANCHORS = 2254
DETECTOR_COORDS = 12  # box (4) + 4 keypoints x (x, y)
NUM_DETECTOR_KEYPOINTS = 4
ANCHOR_STRIDES = (8, 16, 32, 32, 32)
ANCHOR_MIN_SCALE = 0.1484375
ANCHOR_MAX_SCALE = 0.75
SCORE_CLIP = 100.0
DETECTION_SCORE_THRESHOLD = 0.5
NMS_IOU_THRESHOLD = 0.3
NUM_LANDMARKS = 39  # 33 body points, 2 alignment points, 4 unused
NUM_BODY_LANDMARKS = 33
ALIGN_CENTER, ALIGN_SCALE = 33, 34
HEATMAP_KERNEL = 7
HEATMAP_MIN_CONFIDENCE = 0.5
POSE_PRESENCE_THRESHOLD = 0.5

# The 33 BlazePose body landmarks (MediaPipe's PoseLandmark enum), in output order.
BLAZEPOSE_NAMES = (
    "nose",
    "left_eye_inner",
    "left_eye",
    "left_eye_outer",
    "right_eye_inner",
    "right_eye",
    "right_eye_outer",
    "left_ear",
    "right_ear",
    "mouth_left",
    "mouth_right",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
    "left_pinky",
    "right_pinky",
    "left_index",
    "right_index",
    "left_thumb",
    "right_thumb",
    "left_hip",
    "right_hip",
    "left_knee",
    "right_knee",
    "left_ankle",
    "right_ankle",
    "left_heel",
    "right_heel",
    "left_foot_index",
    "right_foot_index",
)

Runner = Callable[[np.ndarray], Sequence[np.ndarray]]


def sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-np.clip(x, -SCORE_CLIP, SCORE_CLIP)))


def ssd_anchor_centers(
    input_size: int = DETECTOR_INPUT,
    strides: Sequence[int] = ANCHOR_STRIDES,
    anchors_per_layer: int = 2,
) -> np.ndarray:
    """(N, 2) anchor centres, normalised, in MediaPipe's SsdAnchorsCalculator order.

    BlazePose's detector uses fixed-size anchors (width = height = 1), one aspect ratio plus one
    interpolated scale per layer: 2 anchors per layer; consecutive layers with the same stride
    share a grid, so the 7x7 grid of the three stride-32 layers carries 6 anchors per cell.
    """
    centers = []
    layer = 0
    while layer < len(strides):
        last = layer
        while last < len(strides) and strides[last] == strides[layer]:
            last += 1
        per_cell = anchors_per_layer * (last - layer)
        grid = math.ceil(input_size / strides[layer])
        ys, xs = np.meshgrid(np.arange(grid), np.arange(grid), indexing="ij")
        cell = np.stack([(xs + 0.5) / grid, (ys + 0.5) / grid], axis=-1).reshape(-1, 1, 2)
        centers.append(np.repeat(cell, per_cell, axis=1).reshape(-1, 2))
        layer = last
    return np.concatenate(centers, axis=0)


ANCHORS = ssd_anchor_centers()


@dataclass(frozen=True)
class PersonDetection:
    """One person found by the detector, in image pixels."""

    score: float
    box: np.ndarray  # (4,) x_min, y_min, x_max, y_max
    keypoints: np.ndarray  # (4, 2): hip centre, scale point above the head, shoulder centre, upper-body point

    def roi(self) -> Roi:
        return roi_from_alignment(self.keypoints[0], self.keypoints[1])


def decode_detections(
    raw_boxes: np.ndarray,
    raw_scores: np.ndarray,
    letterbox: Letterbox,
    *,
    score_threshold: float = DETECTION_SCORE_THRESHOLD,
    iou_threshold: float = NMS_IOU_THRESHOLD,
) -> list[PersonDetection]:
    """Raw detector outputs ``(1, 2254, 12)``, ``(1, 2254, 1)`` -> detections in image pixels, best first."""
    boxes = np.asarray(raw_boxes, dtype=np.float64).reshape(-1, DETECTOR_COORDS)
    scores = sigmoid(np.asarray(raw_scores, dtype=np.float64).reshape(-1))
    if boxes.shape[0] != ANCHORS.shape[0] or scores.shape[0] != ANCHORS.shape[0]:
        raise ValueError(
            f"pose detector output has {boxes.shape[0]} boxes and {scores.shape[0]} scores, "
            f"expected {ANCHORS.shape[0]} (is this MediaPipe's pose_detection.tflite?)"
        )
    keep = scores >= score_threshold
    if not np.any(keep):
        return []
    boxes, scores, anchors = boxes[keep], scores[keep], ANCHORS[keep]
    # reverse_output_order: (x, y, w, h); everything is relative to the anchor, in input pixels.
    centers = boxes[:, 0:2] / DETECTOR_INPUT + anchors
    sizes = boxes[:, 2:4] / DETECTOR_INPUT
    corners = np.concatenate([centers - sizes / 2, centers + sizes / 2], axis=1)  # normalised
    points = boxes[:, 4:].reshape(-1, NUM_DETECTOR_KEYPOINTS, 2) / DETECTOR_INPUT + anchors[:, None]
    detections = []
    for group_score, box, kps in _weighted_nms(scores, corners, points, iou_threshold):
        image_box = letterbox.to_image(box.reshape(2, 2)).reshape(4)
        detections.append(PersonDetection(group_score, image_box, letterbox.to_image(kps)))
    return detections


def _iou(box: np.ndarray, others: np.ndarray) -> np.ndarray:
    lo = np.maximum(box[:2], others[:, :2])
    hi = np.minimum(box[2:], others[:, 2:])
    inter = np.prod(np.clip(hi - lo, 0.0, None), axis=1)
    area = np.prod(np.clip(box[2:] - box[:2], 0, None))
    areas = np.prod(np.clip(others[:, 2:] - others[:, :2], 0, None), axis=1)
    union = area + areas - inter
    return np.where(union > 0, inter / np.where(union > 0, union, 1.0), 0.0)


def _weighted_nms(scores, corners, points, iou_threshold):
    """MediaPipe's WEIGHTED suppression: each kept detection is the score-weighted mean of its cluster."""
    order = np.argsort(-scores, kind="stable")
    remaining = order
    while remaining.size:
        top = remaining[0]
        overlap = _iou(corners[top], corners[remaining])
        cluster = remaining[overlap > iou_threshold]
        cluster = cluster if cluster.size else remaining[:1]
        weights = scores[cluster] / scores[cluster].sum()
        box = (corners[cluster] * weights[:, None]).sum(axis=0)
        kps = (points[cluster] * weights[:, None, None]).sum(axis=0)
        yield float(scores[top]), box, kps
        remaining = remaining[overlap <= iou_threshold]
        remaining = remaining[remaining != top]


def refine_from_heatmap(
    xy_norm: np.ndarray,
    heatmap: np.ndarray,
    *,
    kernel: int = HEATMAP_KERNEL,
    min_confidence: float = HEATMAP_MIN_CONFIDENCE,
) -> np.ndarray:
    """MediaPipe's RefineLandmarksFromHeatmap: sigmoid-weighted mean of a kxk window per landmark.

    ``xy_norm`` (K, 2) normalised crop coordinates; ``heatmap`` (H, W, >=K) logits. The window
    is clipped at the map's border; landmarks whose window peaks below ``min_confidence`` (or
    that lie outside the map) are left alone. Vectorised over landmarks.
    """
    refined = np.array(xy_norm, dtype=np.float64, copy=True)
    height, width = heatmap.shape[:2]
    count = min(refined.shape[0], heatmap.shape[2])
    half = (kernel - 1) // 2
    finite = np.all(np.isfinite(refined[:count]), axis=1)
    scaled = np.where(finite[:, None], refined[:count] * np.array([width, height]), -1.0)
    cols = scaled[:, 0].astype(np.int64)  # truncation, as MediaPipe's int cast
    rows = scaled[:, 1].astype(np.int64)
    inside = finite & (cols >= 0) & (cols < width) & (rows >= 0) & (rows < height)
    offsets = np.arange(-half, half + 1)
    win_rows = rows[:, None] + offsets  # (K, k)
    win_cols = cols[:, None] + offsets
    valid = ((win_rows >= 0) & (win_rows < height))[:, :, None] & ((win_cols >= 0) & (win_cols < width))[
        :, None, :
    ]
    channel = np.arange(count)[:, None, None]
    values = heatmap[
        np.clip(win_rows, 0, height - 1)[:, :, None], np.clip(win_cols, 0, width - 1)[:, None, :], channel
    ]
    confidence = np.where(valid, sigmoid(values), 0.0)  # (K, k, k)
    total = confidence.sum(axis=(1, 2))
    peak = confidence.max(axis=(1, 2))
    use = inside & (peak >= min_confidence) & (total > 0)
    safe = np.where(total > 0, total, 1.0)
    mean_col = (confidence * win_cols[:, None, :]).sum(axis=(1, 2)) / safe
    mean_row = (confidence * win_rows[:, :, None]).sum(axis=(1, 2)) / safe
    refined[:count, 0] = np.where(use, mean_col / width, refined[:count, 0])
    refined[:count, 1] = np.where(use, mean_row / height, refined[:count, 1])
    return refined


@dataclass(frozen=True)
class LandmarkResult:
    """What the landmark network says about one ROI, mapped back to the image."""

    presence: float  # pose presence score in [0, 1]
    xy: np.ndarray  # (39, 2) image pixels
    visibility: np.ndarray  # (39,) in [0, 1]
    presence_per_point: np.ndarray  # (39,) in [0, 1]: the point is inside the image
    world: np.ndarray  # (39, 3) metres, hip-centred, camera-aligned axes (x right, y down, z away)
    segmentation: np.ndarray | None  # (H, W) float32 person probability in the image, or None
    roi: Roi


def decode_landmarks(
    outputs: Sequence[np.ndarray],
    roi: Roi,
    width: int,
    height: int,
    *,
    refine: bool = True,
    segmentation: bool = True,
) -> LandmarkResult:
    """The landmark network's five outputs -> image-space landmarks (see the module docstring)."""
    if len(outputs) < 5:
        raise ValueError(f"pose landmark network gave {len(outputs)} outputs, expected 5")
    raw, flag, seg, heatmap, world_raw = outputs[:5]
    raw = np.asarray(raw, dtype=np.float64).reshape(NUM_LANDMARKS, 5)
    xy_norm = raw[:, 0:2] / LANDMARK_INPUT
    heatmap = np.asarray(heatmap).reshape(heatmap.shape[-3:])
    if refine:
        xy_norm = refine_from_heatmap(xy_norm, heatmap)
    xy = roi_to_image(xy_norm * LANDMARK_INPUT, roi, LANDMARK_INPUT)
    world = np.asarray(world_raw, dtype=np.float64).reshape(NUM_LANDMARKS, 3)
    c, s = math.cos(roi.rotation), math.sin(roi.rotation)
    world = np.stack(
        [c * world[:, 0] - s * world[:, 1], s * world[:, 0] + c * world[:, 1], world[:, 2]], axis=1
    )
    mask = None
    if segmentation:
        logits = np.asarray(seg, dtype=np.float32).reshape(LANDMARK_INPUT, LANDMARK_INPUT)
        probability = (1.0 / (1.0 + np.exp(-np.clip(logits, -30, 30)))).astype(np.float32)
        mask = warp_from_input(probability, roi, LANDMARK_INPUT, width, height)
    return LandmarkResult(
        presence=float(np.asarray(flag).reshape(-1)[0]),
        xy=xy,
        visibility=sigmoid(raw[:, 3]),
        presence_per_point=sigmoid(raw[:, 4]),
        world=world,
        segmentation=mask,
        roi=roi,
    )


def detector_input(image_rgb: np.ndarray) -> tuple[np.ndarray, Letterbox]:
    """(1, 224, 224, 3) float32 in [-1, 1] of the letterboxed image, and the letterbox used."""
    height, width = image_rgb.shape[:2]
    letterbox = Letterbox.fit(width, height, DETECTOR_INPUT)
    tensor = letterbox.apply(image_rgb).astype(np.float32) * (2.0 / 255.0) - 1.0
    return tensor[None], letterbox


def landmark_input(image_rgb: np.ndarray, roi: Roi) -> np.ndarray:
    """(1, 256, 256, 3) float32 in [0, 1] of the rotated ROI crop."""
    crop = warp_to_input(image_rgb, roi, LANDMARK_INPUT)
    return (crop.astype(np.float32) * (1.0 / 255.0))[None]


class BlazePose:
    """Two-stage BlazePose with tracking; ``__call__(image_rgb) -> Keypoints`` (33 points) or None.

    ``detector`` and ``landmarker`` are runners: ``f(input) -> list of output arrays``, in the
    TFLite models' output order (see the module docstring).
    """

    layout = "blazepose33"

    def __init__(
        self,
        detector: Runner,
        landmarker: Runner,
        *,
        redetect_every: int = 10,
        presence_threshold: float = POSE_PRESENCE_THRESHOLD,
        refine: bool = True,
        segmentation: bool = True,
    ):
        if redetect_every < 0:
            raise ValueError(f"redetect_every must be >= 0 (0 = never while tracking), got {redetect_every}")
        self._detector = detector
        self._landmarker = landmarker
        self.redetect_every = int(redetect_every)
        self.presence_threshold = float(presence_threshold)
        self.refine = refine
        self.segmentation = segmentation
        self._roi: Roi | None = None
        self._frames_since_detection = 0
        self.last_people = 0  # people the detector saw the last time it ran
        self.last_result: LandmarkResult | None = None

    def reset(self) -> None:
        self._roi = None
        self._frames_since_detection = 0
        self.last_people = 0
        self.last_result = None

    def detect_people(self, image_rgb: np.ndarray) -> list[PersonDetection]:
        tensor, letterbox = detector_input(image_rgb)
        outputs = self._detector(tensor)
        if len(outputs) < 2:
            raise ValueError(f"pose detector gave {len(outputs)} outputs, expected 2 (boxes, scores)")
        return decode_detections(outputs[0], outputs[1], letterbox)

    def landmarks(self, image_rgb: np.ndarray, roi: Roi) -> LandmarkResult:
        height, width = image_rgb.shape[:2]
        outputs = self._landmarker(landmark_input(image_rgb, roi))
        return decode_landmarks(
            outputs, roi, width, height, refine=self.refine, segmentation=self.segmentation
        )

    def __call__(self, image_rgb: np.ndarray) -> Keypoints | None:
        image_rgb = _check_image(image_rgb)
        self._frames_since_detection += 1
        due = self.redetect_every > 0 and self._frames_since_detection >= self.redetect_every
        if self._roi is None or due:
            people = self.detect_people(image_rgb)
            self._frames_since_detection = 0
            self.last_people = len(people)
            if self._roi is None:
                if not people:
                    self.last_result = None
                    return None
                self._roi = people[0].roi()
        result = self.landmarks(image_rgb, self._roi)
        self.last_result = result
        if result.presence < self.presence_threshold:
            self._roi = None
            return None
        self._roi = roi_from_alignment(result.xy[ALIGN_CENTER], result.xy[ALIGN_SCALE])
        body = slice(0, NUM_BODY_LANDMARKS)
        return Keypoints(
            layout=self.layout,
            xy=result.xy[body].astype(np.float32),
            score=(result.visibility[body] * result.presence_per_point[body]).astype(np.float32),
            world=result.world[body].astype(np.float32),
            presence=result.presence,
            people=self.last_people,
            segmentation=result.segmentation,
        )


def _check_image(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(f"expected an (H, W, 3) uint8 RGB image, got {image.dtype} {image.shape}")
    if image.shape[0] < 8 or image.shape[1] < 8:
        raise ValueError(f"image of {image.shape[1]}x{image.shape[0]} pixels is too small")
    return np.ascontiguousarray(image)


__all__ = [
    "ANCHORS",
    "BLAZEPOSE_NAMES",
    "BlazePose",
    "LandmarkResult",
    "PersonDetection",
    "decode_detections",
    "decode_landmarks",
    "refine_from_heatmap",
    "ssd_anchor_centers",
]
