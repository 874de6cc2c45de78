"""The ONNX detector path against a hand-made ONNX network (tiny_onnx.py) whose output is known."""

from __future__ import annotations

import numpy as np
import pytest
from tiny_onnx import dot_heatmap_model

from stg_node.tracking.detectors import OnnxPoseDetector, decode_heatmaps, decode_simcc, make_detector
from stg_node.tracking.runtime import OnnxRunner, RunnerError


def test_heatmap_decoding_maps_heatmap_pixels_to_input_pixels():
    maps = np.zeros((1, 2, 64, 48))
    maps[0, 0, 10, 20] = 1.0
    maps[0, 1, 30, 5] = 0.8
    maps[0, 1, 30, 6] = 0.4  # neighbour to the right: a quarter-pixel shift towards it
    xy, score = decode_heatmaps(maps, (192, 256))
    assert np.allclose(xy[0], [(20 + 0.5) * 4 - 0.5, (10 + 0.5) * 4 - 0.5])
    assert np.allclose(xy[1], [(5.25 + 0.5) * 4 - 0.5, (30 + 0.5) * 4 - 0.5])
    assert np.allclose(score, [1.0, 0.8])


def test_simcc_decoding_divides_by_the_split_ratio():
    sx, sy = np.zeros((1, 17, 384)), np.zeros((1, 17, 512))
    sx[0, :, 101] = 0.9
    sy[0, :, 300] = 0.7
    xy, score = decode_simcc(sx, sy, (192, 256))
    assert np.allclose(xy, [[50.5, 150.0]] * 17) and np.allclose(score, 0.7)


@pytest.fixture(scope="module")
def dot_model(tmp_path_factory):
    path = tmp_path_factory.mktemp("onnx") / "dots.onnx"
    dot_heatmap_model(path)
    return path


def test_onnx_detector_finds_the_dots_through_its_crop(dot_model):
    detector = make_detector("onnx", model=dot_model)
    height, width = 300, 400
    image = np.zeros((height, width, 3), np.float64)
    dots = {0: (150, 120), 1: (250, 80), 2: (210, 230)}  # channel -> (x, y): R, G, B
    ys, xs = np.mgrid[0:height, 0:width]
    for channel, (x, y) in dots.items():  # Gaussian blobs: one clear maximum at each centre
        image[..., channel] = 255 * np.exp(-((xs - x) ** 2 + (ys - y) ** 2) / (2 * 8.0**2))
    image = np.round(image).astype(np.uint8)
    keypoints = detector(image)
    assert keypoints is not None and keypoints.layout == "coco17" and keypoints.xy.shape == (17, 2)
    # The whole frame is the first box (300x400 letterboxed into 192x256: 2.08 image px per
    # input px; heatmaps are 4x coarser): within one heatmap cell of the dots.
    cell = 4 * max(width / 192, height / 256)
    for k in range(17):
        assert np.linalg.norm(keypoints.xy[k] - dots[k % 3]) < cell, (k, keypoints.xy[k])
    # The next frame crops around the keypoints: the dots come back more precisely.
    again = detector(image)
    for k in range(17):
        assert np.linalg.norm(again.xy[k] - dots[k % 3]) < cell / 2


def test_onnx_preprocessing_is_imagenet_normalised_nchw(dot_model):
    detector = OnnxPoseDetector(lambda x: [np.zeros((1, 17, 64, 48), np.float32)])
    tensor, affine = detector.preprocess(np.full((256, 192, 3), 255, np.uint8))
    assert tensor.shape == (1, 3, 256, 192) and tensor.dtype == np.float32
    expected = (255 - np.array([123.675, 116.28, 103.53])) / np.array([58.395, 57.12, 57.375])
    assert np.allclose(tensor[0, :, 128, 96], expected, atol=1e-4)
    assert np.allclose(affine, [[1, 0, 0], [0, 1, 0]], atol=1e-9)  # the frame is the box: identity


def test_onnx_errors_name_the_file_and_the_expected_outputs(tmp_path, dot_model):
    with pytest.raises(RunnerError, match="does not exist"):
        OnnxRunner(tmp_path / "missing.onnx")
    garbage = tmp_path / "garbage.onnx"
    garbage.write_bytes(b"not a model")
    with pytest.raises(RunnerError, match="garbage.onnx"):
        OnnxRunner(garbage)
    detector = OnnxPoseDetector(lambda x: [np.zeros((1, 17), np.float32)])
    with pytest.raises(ValueError, match="expected SimCC"):
        detector(np.zeros((64, 64, 3), np.uint8))
    with pytest.raises(ValueError, match="needs a model file"):
        make_detector("onnx")
    with pytest.raises(ValueError, match="unknown detector"):
        make_detector("openpose")
