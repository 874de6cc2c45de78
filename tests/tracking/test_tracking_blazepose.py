"""BlazePose's pre- and post-processing against fake networks whose output is known, then the real one.

The fakes stand in for the two TFLite networks: the detector fake emits raw SSD regressions that
encode a chosen box; the landmark fake finds coloured dots in the crop it is given and reports
them in the network's coordinates. If the crop, the rotation, the letterbox or the decoding were
wrong, the points would not come back where the dots are.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from trackhelpers import needs_blazepose

from stg_node.tracking import blazepose as bp
from stg_node.tracking.roi import (
    Letterbox,
    Roi,
    crop_affine,
    image_to_normalized,
    normalized_to_image,
    roi_from_alignment,
)

# Stated accuracy of the shipped detector on the synthetic renders (512 px, body ~360 px tall),
# limb joints (shoulders .. ankles) against the projected SMPL joints. Measured when written:
# median 5.5 px; 90th percentile ~10-11 px.
DETECTOR_MEDIAN_PX = 9.0
DETECTOR_P90_PX = 25.0


def _mediapipe_anchors_reference() -> np.ndarray:
    """A direct transcription of MediaPipe's SsdAnchorsCalculator for pose_detection's options."""
    options = dict(num_layers=5, min_scale=0.1484375, max_scale=0.75, size=224, strides=[8, 16, 32, 32, 32])

    def scale(index, count):
        if count == 1:
            return (options["min_scale"] + options["max_scale"]) * 0.5
        return options["min_scale"] + (options["max_scale"] - options["min_scale"]) * index / (count - 1)

    anchors = []
    layer = 0
    strides = options["strides"]
    while layer < options["num_layers"]:
        heights = []
        last = layer
        while last < len(strides) and strides[last] == strides[layer]:
            s = scale(last, len(strides))
            heights.append(s)  # aspect ratio 1.0
            nxt = 1.0 if last == len(strides) - 1 else scale(last + 1, len(strides))
            heights.append(math.sqrt(s * nxt))  # interpolated scale
            last += 1
        size = math.ceil(options["size"] / strides[layer])
        for y in range(size):
            for x in range(size):
                for _ in heights:
                    anchors.append(((x + 0.5) / size, (y + 0.5) / size))
        layer = last
    return np.array(anchors)


def test_anchor_grid_matches_mediapipes_calculator():
    reference = _mediapipe_anchors_reference()
    assert bp.ANCHORS.shape == (bp.NUM_ANCHORS, 2) == reference.shape
    assert np.allclose(bp.ANCHORS, reference)


def _raw_detection(width, height, box_xyxy, keypoints_xy, score_logit=5.0, anchor_shift=(0, 0)):
    """Raw outputs (1, 2254, 12), (1, 2254, 1) that encode one person at a chosen anchor."""
    letterbox = Letterbox.fit(width, height, bp.DETECTOR_INPUT)

    def to_norm(points):  # image pixels -> normalised letterboxed input (inverse of to_image)
        points = np.asarray(points, dtype=np.float64)
        return (
            (points + 0.5) * letterbox.scale + np.array([letterbox.pad_x, letterbox.pad_y])
        ) / bp.DETECTOR_INPUT

    corners = to_norm(np.reshape(box_xyxy, (2, 2)))
    center, size = corners.mean(axis=0), corners[1] - corners[0]
    anchor = int(np.argmin(np.linalg.norm(bp.ANCHORS - center - np.array(anchor_shift), axis=1)))
    raw = np.zeros((1, bp.NUM_ANCHORS, 12), np.float32)
    scores = np.full((1, bp.NUM_ANCHORS, 1), -10.0, np.float32)
    raw[0, anchor, 0:2] = (center - bp.ANCHORS[anchor]) * bp.DETECTOR_INPUT
    raw[0, anchor, 2:4] = size * bp.DETECTOR_INPUT
    raw[0, anchor, 4:] = ((to_norm(keypoints_xy) - bp.ANCHORS[anchor]) * bp.DETECTOR_INPUT).reshape(-1)
    scores[0, anchor, 0] = score_logit
    return raw, scores, letterbox


def test_detections_decode_back_to_the_encoded_box_and_keypoints_through_the_letterbox():
    width, height = 640, 360  # wide: letterboxed with padding above and below
    box = np.array([200.0, 40.0, 330.0, 340.0])
    keypoints = np.array([[265.0, 200.0], [268.0, 20.0], [262.0, 110.0], [266.0, 60.0]])
    raw, scores, letterbox = _raw_detection(width, height, box, keypoints)
    detections = bp.decode_detections(raw, scores, letterbox)
    assert len(detections) == 1
    assert np.allclose(detections[0].box, box, atol=1e-3)
    assert np.allclose(detections[0].keypoints, keypoints, atol=1e-3)
    assert detections[0].score == pytest.approx(1 / (1 + math.exp(-5.0)))


def test_weighted_nms_merges_overlapping_anchors_and_keeps_separate_people():
    width = height = 480
    first = _raw_detection(
        width, height, [100, 100, 200, 400], [[150, 250], [150, 90], [150, 160], [150, 120]]
    )
    shifted = _raw_detection(
        width, height, [104, 100, 204, 400], [[154, 250], [154, 90], [154, 160], [154, 120]], 3.0, (0.03, 0)
    )
    other = _raw_detection(
        width, height, [320, 80, 420, 420], [[370, 250], [370, 70], [370, 150], [370, 110]]
    )
    raw = first[0] + shifted[0] + other[0]
    scores = np.maximum(np.maximum(first[1], shifted[1]), other[1])
    detections = bp.decode_detections(raw, scores, first[2])
    assert len(detections) == 2
    merged = min(detections, key=lambda d: d.box[0])
    w1, w2 = 1 / (1 + math.exp(-5.0)), 1 / (1 + math.exp(-3.0))
    expected_x0 = (w1 * 100 + w2 * 104) / (w1 + w2)  # score-weighted mean of the cluster
    assert merged.box[0] == pytest.approx(expected_x0, abs=1e-3)
    assert not bp.decode_detections(raw, np.full_like(scores, -10.0), first[2])
    with pytest.raises(ValueError, match="2254"):
        bp.decode_detections(raw[:, :100], scores[:, :100], first[2])


def test_roi_maps_are_inverse_and_the_crop_affine_agrees_with_them():
    roi = Roi(center_x=210.0, center_y=180.0, side=150.0, rotation=0.6)
    points = np.random.default_rng(0).uniform(0, 1, size=(50, 2))
    assert np.allclose(image_to_normalized(normalized_to_image(points, roi), roi), points)
    affine = crop_affine(roi, 256)
    image_points = normalized_to_image(points, roi)
    net = image_points @ affine[:, :2].T + affine[:, 2]  # OpenCV pixel centres of the network input
    assert np.allclose((net + 0.5) / 256, points, atol=1e-9)
    # Alignment points: hip centre below the scale point -> upright box, side 2 * 1.25 * distance.
    upright = roi_from_alignment((100, 200), (100, 120))
    assert upright.rotation == pytest.approx(0.0) and upright.side == pytest.approx(200.0)
    tilted = roi_from_alignment((100, 200), (180, 200))  # body axis pointing right: rotated +90 deg
    assert tilted.rotation == pytest.approx(math.pi / 2)


DOT_COLOURS = [(255, 0, 0), (0, 255, 0), (0, 0, 255), (255, 255, 0), (0, 255, 255)]


def _dot_image(width, height, positions):
    image = np.full((height, width, 3), 40, np.uint8)
    for (x, y), colour in zip(positions, DOT_COLOURS, strict=False):
        cv2.circle(image, (int(round(x * 8)), int(round(y * 8))), 3 * 8, colour, -1, cv2.LINE_AA, shift=3)
    return image


def _find_dots(crop: np.ndarray) -> np.ndarray:
    """Centroid of each coloured dot in a (256, 256, 3) float crop, in MediaPipe's network coordinates."""
    found = []
    for colour in DOT_COLOURS:
        target = np.asarray(colour, np.float32) / 255.0
        closeness = np.clip(1.0 - np.abs(crop - target).max(axis=2) * 2.0, 0.0, None)
        ys, xs = np.nonzero(closeness > 0.5)
        w = closeness[ys, xs]
        if w.sum() == 0:
            found.append((np.nan, np.nan))
            continue
        found.append(((xs * w).sum() / w.sum() + 0.5, (ys * w).sum() / w.sum() + 0.5))
    return np.array(found)


class FakeLandmarker:
    """Finds the coloured dots in its input and reports them as landmarks 0..4 (others at 128, 128)."""

    def __init__(self, presence=0.99):
        self.presence = presence
        self.calls = 0

    def __call__(self, tensor):
        self.calls += 1
        crop = tensor[0]
        landmarks = np.zeros((bp.NUM_LANDMARKS, 5), np.float32)
        landmarks[:, :2] = 128.0
        dots = _find_dots(crop)
        landmarks[:, 3:5] = 8.0  # visibility and presence logits: sigmoid(8) ~ 1
        missing = ~np.isfinite(dots).all(axis=1)
        landmarks[:5, :2] = np.where(missing[:, None], 128.0, dots)
        landmarks[:5, 3][missing] = -8.0
        # Alignment points: the crop's centre and a point straight above it at 256 / 2.5, so the
        # next frame's ROI (side 2 x 1.25 x their distance) is this one again.
        landmarks[bp.ALIGN_CENTER, :2] = (128.0, 128.0)
        landmarks[bp.ALIGN_SCALE, :2] = (128.0, 128.0 - 256.0 / 2.5)
        seg = np.full((1, 256, 256, 1), -8.0, np.float32)
        seg[0, 64:192, 64:192, 0] = 8.0  # the middle quarter of the crop is "person"
        heatmap = np.full((1, 64, 64, 39), -8.0, np.float32)  # no peak: no refinement
        world = np.zeros((1, 117), np.float32)
        world[0, 0:3] = (0.1, 0.0, 0.0)  # landmark 0 points along the crop's x axis
        return [landmarks.reshape(1, -1), np.array([[self.presence]], np.float32), seg, heatmap, world]


class FakeDetector:
    def __init__(self, people):
        self.people = people  # list of (box, keypoints) in image pixels
        self.calls = 0
        self.size = None

    def __call__(self, tensor):
        self.calls += 1
        width, height = self.size
        raw = np.zeros((1, bp.NUM_ANCHORS, 12), np.float32)
        scores = np.full((1, bp.NUM_ANCHORS, 1), -10.0, np.float32)
        for box, keypoints in self.people:
            r, s, _ = _raw_detection(width, height, box, keypoints)
            raw += r
            scores = np.maximum(scores, s)
        return [raw, scores]


@pytest.mark.parametrize("rotation_deg", [0.0, 35.0, -120.0])
def test_landmarks_come_back_where_the_dots_are_through_a_rotated_crop(rotation_deg):
    width, height = 480, 360
    dots = np.array([[200.0, 150.0], [260.0, 170.0], [230.0, 220.0], [180.0, 200.0], [250.0, 120.0]])
    image = _dot_image(width, height, dots)
    roi = Roi(225.0, 170.0, 220.0, math.radians(rotation_deg))
    result = bp.BlazePose(FakeDetector([]), FakeLandmarker(), refine=True).landmarks(image, roi)
    assert np.abs(result.xy[:5] - dots).max() < 0.6, result.xy[:5] - dots
    assert np.all(result.visibility[:5] > 0.99)
    # The segmentation square comes back as the ROI's middle quarter, rotated with it.
    centre_value = result.segmentation[int(roi.center_y), int(roi.center_x)]
    corner = normalized_to_image(np.array([0.05, 0.05]), roi)
    assert centre_value > 0.99 and result.segmentation[int(corner[1]), int(corner[0])] < 0.01
    # World points are rotated by the ROI's rotation (x axis of the crop -> image direction).
    expected = 0.1 * np.array([math.cos(roi.rotation), math.sin(roi.rotation)])
    assert np.allclose(result.world[0, :2], expected, atol=1e-6)


def test_tracking_runs_the_detector_only_when_needed_and_counts_people():
    width, height = 480, 360
    dots = np.array([[200.0, 150.0], [260.0, 170.0], [230.0, 220.0], [180.0, 200.0], [250.0, 120.0]])
    image = _dot_image(width, height, dots)
    person = ([150, 60, 310, 330], [[230, 200], [230, 80], [230, 130], [230, 100]])
    detector = FakeDetector([person])
    detector.size = (width, height)
    landmarker = FakeLandmarker()
    tracker = bp.BlazePose(detector, landmarker, redetect_every=5)
    for _ in range(7):
        keypoints = tracker(image)
        assert keypoints is not None and keypoints.layout == "blazepose33"
    assert detector.calls == 2  # the first frame, then every 5th
    assert keypoints.people == 1 and keypoints.xy.shape == (33, 2)
    assert np.abs(keypoints.xy[:5] - dots).max() < 1.0
    # A second person: the next re-detection sees two.
    detector.people.append(([330, 60, 470, 330], [[400, 200], [400, 80], [400, 130], [400, 100]]))
    for _ in range(5):
        keypoints = tracker(image)
    assert keypoints.people == 2
    # Presence below threshold: no keypoints, and the next frame runs the detector again.
    landmarker.presence = 0.1
    calls = detector.calls
    assert tracker(image) is None
    landmarker.presence = 0.99
    assert tracker(image) is not None and detector.calls == calls + 1
    # Nobody found: None, no landmark call.
    tracker.reset()
    detector.people.clear()
    before = landmarker.calls
    assert tracker(image) is None and landmarker.calls == before


def _refine_reference(xy, heatmap, kernel=7, min_confidence=0.5):
    """MediaPipe's refine_landmarks_from_heatmap_calculator.cc, loop for loop."""
    out = xy.copy()
    h, w, _ = heatmap.shape
    offset = (kernel - 1) // 2
    for k in range(xy.shape[0]):
        col, row = int(xy[k, 0] * w), int(xy[k, 1] * h)
        if col < 0 or col >= w or row < 0 or row >= h:
            continue
        total = wc = wr = peak = 0.0
        for r in range(max(0, row - offset), min(h, row + offset + 1)):
            for c in range(max(0, col - offset), min(w, col + offset + 1)):
                conf = 1.0 / (1.0 + math.exp(-heatmap[r, c, k]))
                total += conf
                peak = max(peak, conf)
                wc += c * conf
                wr += r * conf
        if peak >= min_confidence and total > 0:
            out[k] = (wc / w / total, wr / h / total)
    return out


def test_heatmap_refinement_matches_mediapipes_loop():
    rng = np.random.default_rng(4)
    heatmap = rng.normal(-1.0, 2.0, size=(64, 64, 39))
    xy = rng.uniform(-0.05, 1.05, size=(39, 2))  # some outside, some at the borders
    xy[:3] = [[0.0, 0.0], [0.999, 0.5], [0.5, 0.999]]
    assert np.allclose(bp.refine_from_heatmap(xy, heatmap), _refine_reference(xy, heatmap), atol=1e-12)


@needs_blazepose
def test_real_detector_keypoints_match_the_projected_truth_on_synthetic_renders(synth_512, body):
    from trackhelpers import camera_joints

    from stg_node.data.io import read_image
    from stg_node.tracking.detectors import make_detector

    detector = make_detector("blazepose")
    joints = camera_joints(body, synth_512)
    uv = joints @ synth_512.K.T
    uv = uv[..., :2] / uv[..., 2:]
    pairs = {"left_shoulder": 16, "right_shoulder": 17, "left_elbow": 18, "right_elbow": 19, "left_wrist": 20,
             "right_wrist": 21, "left_hip": 1, "right_hip": 2, "left_knee": 4, "right_knee": 5,
             "left_ankle": 7, "right_ankle": 8}  # fmt: skip
    errors = []
    for i in range(len(synth_512)):
        keypoints = detector(read_image(synth_512.folder / "Camera_B1" / f"{i:06d}.png"))
        assert keypoints is not None, f"no person found in frame {i}"
        for name, joint in pairs.items():
            errors.append(np.linalg.norm(keypoints.xy[bp.BLAZEPOSE_NAMES.index(name)] - uv[i, joint]))
    errors = np.array(errors)
    assert np.median(errors) < DETECTOR_MEDIAN_PX, np.median(errors)
    assert np.percentile(errors, 90) < DETECTOR_P90_PX, np.percentile(errors, 90)


@needs_blazepose
def test_real_detector_finds_nobody_in_empty_frames_and_two_people_side_by_side(synth_512):
    from stg_node.data.io import read_image
    from stg_node.tracking.detectors import make_detector

    detector = make_detector("blazepose")
    assert detector(np.zeros((480, 640, 3), np.uint8)) is None
    noise = np.random.default_rng(0).integers(0, 255, size=(480, 640, 3), dtype=np.uint8)
    detector.reset()
    assert detector(noise) is None
    person = read_image(synth_512.folder / "Camera_B1" / "000000.png")[:, 96:416]
    detector.reset()
    two = detector(np.concatenate([person, person[:, ::-1]], axis=1))
    assert two is not None and two.people == 2
