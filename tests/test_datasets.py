"""Loaders reproduce the cameras, pixels and SMPL parameters their tiny fixtures were written with."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from stg_node.data import DatasetError, detect_layout, open_dataset
from stg_node.data.splits import FrameRange, SplitSpec
from stg_node.data.views import project
from tests.fixtures.datasets import (
    DOT_SIGMA,
    MASK_RADIUS,
    RAW_SIZE,
    write_folder,
    write_thuman4,
    write_zju_original,
    write_zju_refined,
)

WRITERS = {
    "zju_377": (write_zju_original, {}),
    "zju_313": (write_zju_original, {"naming": "313"}),
    "zju_refined": (write_zju_refined, {}),
    "thuman4": (write_thuman4, {}),
    "folder": (write_folder, {"num_cams": 2}),
}


def dot_centroid(image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Sub-pixel centre of the bright dot: intensity-weighted mean in a window around the peak."""
    grey = image.astype(np.float64).mean(axis=2) * (mask > 0)
    y0, x0 = np.unravel_index(np.argmax(grey), grey.shape)
    half = max(3, math.ceil(3.5 * DOT_SIGMA * image.shape[1] / RAW_SIZE[0]))
    window = np.zeros_like(grey, dtype=bool)
    window[max(y0 - half, 0) : y0 + half + 1, max(x0 - half, 0) : x0 + half + 1] = True
    weight = np.clip(grey - 25.0, 0, None) * window
    yy, xx = np.mgrid[0 : grey.shape[0], 0 : grey.shape[1]]
    return np.array([(weight * xx).sum() / weight.sum(), (weight * yy).sum() / weight.sum()])


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    out = {}
    for key, (writer, kwargs) in WRITERS.items():
        root = tmp_path_factory.mktemp(key) / ("CoreView_313" if key == "zju_313" else "subject")
        root.mkdir()
        out[key] = (root, writer(root, **kwargs))
    return out


@pytest.mark.parametrize("key", list(WRITERS))
@pytest.mark.parametrize("size", [None, 40, (80, 60)], ids=["native", "40", "80x60"])
def test_written_point_lands_where_loaded_camera_projects_it(written, key, size):
    # The dot was drawn with cv2.projectPoints through the distorted raw camera; after
    # undistortion and resizing it must sit where the delivered pinhole K, R, t put the point.
    # The common K[:2] *= s rescaling would miss by (1 - s) / 2 px (0.375 px at size 40).
    root, truth = written[key]
    dataset = open_dataset(root, split="all", size=size, check=True)
    assert len(dataset) == len(truth.points) * len(truth.cameras)
    for sample in dataset:
        expected = project(truth.points[sample.index][None], sample.camera)[0]
        np.testing.assert_allclose(dot_centroid(sample.image, sample.mask), expected, atol=0.08)


@pytest.mark.parametrize("key", list(WRITERS))
def test_cameras_poses_and_masks_come_back_as_written(written, key):
    root, truth = written[key]
    dataset = open_dataset(root, split="all", size=40)
    by_name = {c.name: c for c in truth.cameras}
    assert set(dataset.camera_names) == set(by_name)
    for sample in dataset[: len(truth.cameras) * 2]:
        cam = by_name[sample.camera.name]
        np.testing.assert_allclose(sample.camera.R, cam.R, atol=1e-9)
        np.testing.assert_allclose(sample.camera.t, cam.t, atol=1e-9)  # ZJU: mm on disk, metres here
        assert (sample.camera.width, sample.camera.height) == (40, 40)
        assert sample.image.shape == (40, 40, 3) and sample.image.dtype == np.uint8
        assert sample.mask.dtype == np.uint8 and set(np.unique(sample.mask)) <= {0, 255}
        assert np.all(sample.image[sample.mask == 0] == 0), "background must be black outside the mask"
        # the disc mask keeps its area through undistortion and resizing (within a few edge pixels)
        disc_area = math.pi * MASK_RADIUS**2 * (40 / RAW_SIZE[0]) * (40 / RAW_SIZE[1])
        assert abs((sample.mask > 0).sum() - disc_area) < 0.25 * disc_area
        written_smpl = truth.smpl[sample.index]
        np.testing.assert_allclose(sample.smpl.poses, written_smpl["poses"], atol=1e-6)
        np.testing.assert_allclose(sample.smpl.Rh, written_smpl["Rh"], atol=1e-6)
        np.testing.assert_allclose(sample.smpl.Th, written_smpl["Th"], atol=1e-6)
        np.testing.assert_allclose(sample.smpl.betas, written_smpl["betas"], atol=1e-6)
        assert sample.smpl.model == ("smplx" if key == "thuman4" else "smpl")
        assert sample.time == pytest.approx(sample.index / dataset.fps)


def test_layout_detection(written, tmp_path):
    expected = {
        "zju_377": "zju",
        "zju_313": "zju",
        "zju_refined": "zju",
        "thuman4": "thuman4",
        "folder": "folder",
    }
    for key, (root, _) in written.items():
        assert detect_layout(root) == expected[key]
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(DatasetError, match="matches no known layout") as err:
        open_dataset(tmp_path)
    assert "annots.npy" in str(err.value) and "cameras.json" in str(err.value)


def test_zju_split_protocol_uses_camera_1_for_training_and_others_every_30th_frame(tmp_path):
    root = tmp_path / "CoreView_377"
    root.mkdir()
    write_zju_original(root, num_frames=3, num_cams=3)
    train = open_dataset(root, split="train")
    assert train.camera_names == ["1"] and train.frames == [0, 1, 2]
    novel_view = open_dataset(root, split="novel_view")
    assert novel_view.camera_names == ["2", "3"] and novel_view.frames == [0]
    with pytest.raises(DatasetError, match="novel_pose"):
        open_dataset(root, split="novel_pose")  # 377 trains on frames 0..569: none held out here
    custom = open_dataset(root, split=SplitSpec("mine", FrameRange(1, 3), cameras=("3",)))
    assert [(v.frame, v.camera) for v in custom.views] == [(1, "3"), (2, "3")]
    with pytest.raises(DatasetError, match="camera"):
        open_dataset(root, split=SplitSpec("bad", FrameRange(), cameras=("9",)))


def test_zju_training_range_can_be_given(tmp_path):
    root = tmp_path / "synthetic"
    root.mkdir()
    write_zju_original(root, num_frames=3, num_cams=2)
    assert open_dataset(root, split="train").frames == [0, 1, 2]  # unknown subject: every frame
    held_out = open_dataset(root, split="novel_pose", train_frames=FrameRange(0, 2))
    assert held_out.frames == [2] and held_out.camera_names == ["1", "2"]


def test_313_naming_maps_one_based_files_and_camera_numbers(written):
    root, truth = written["zju_313"]
    dataset = open_dataset(root, split="all", size=None)
    assert dataset.camera_names == ["1", "2", "22"]
    assert dataset.smpl_path(0).name == "1.npy"
    assert dataset.image_path(2, "22").name.startswith("CoreView_313_Camera_(22)_0003")


def test_mask_sources(tmp_path):
    root = tmp_path / "CoreView_386"
    root.mkdir()
    write_zju_original(root, num_frames=1, num_cams=1, mask_dirs=("mask", "mask_cihp"))
    # remove part of mask_cihp so the union differs from it
    import cv2

    cihp = root / "mask_cihp" / "Camera_B1" / "000000.png"
    m = cv2.imread(str(cihp), cv2.IMREAD_GRAYSCALE)
    m[:, : m.shape[1] // 2] = 0
    cv2.imwrite(str(cihp), m)
    area = {
        src: (open_dataset(root, split="all", size=None, mask_source=src)[0].mask > 0).sum()
        for src in ("auto", "mask", "mask_cihp", "union")
    }
    assert area["auto"] == area["mask_cihp"] < area["mask"] == area["union"]


def test_folder_flat_single_camera_and_times(tmp_path):
    write_folder(tmp_path, num_frames=3, num_cams=1, flat=True, first_frame=10)
    dataset = open_dataset(tmp_path, size=None)
    assert dataset.frames == [10, 11, 12]
    assert dataset.fps == 25
    assert [s.time for s in dataset] == pytest.approx([0.0, 0.04, 0.08])


def test_thuman4_skips_views_listed_missing(tmp_path):
    write_thuman4(tmp_path, num_frames=2, num_cams=2, missing=((1, 1),))
    dataset = open_dataset(tmp_path, split="all", size=None, check=True)
    assert [(v.frame, v.camera) for v in dataset.views] == [(0, "cam00"), (0, "cam01"), (1, "cam00")]


def test_opening_is_lazy(tmp_path, monkeypatch):
    write_folder(tmp_path, num_frames=3)
    import stg_node.data.base as base

    reads = []
    real = base.read_image
    monkeypatch.setattr(base, "read_image", lambda p: reads.append(p) or real(p))
    dataset = open_dataset(tmp_path)
    assert reads == [] and len(dataset) == 3
    dataset[1]
    assert len(reads) == 1 and reads[0].name == "000001.png"


# --- bad input ----------------------------------------------------------------------------------


def test_missing_image_is_named_at_check_and_at_load(tmp_path):
    root = tmp_path / "CoreView_377"
    root.mkdir()
    write_zju_original(root, num_frames=2, num_cams=2)
    gone = root / "Camera_B2" / "000001.jpg"
    gone.unlink()
    dataset = open_dataset(root, split="all")  # lazy: opening still works
    with pytest.raises(DatasetError, match="000001.jpg"):
        dataset.load(1, "2")
    with pytest.raises(DatasetError, match="missing for frame 1, camera 2"):
        open_dataset(root, split="all", check=True)


def test_corrupt_image_names_the_file(tmp_path):
    write_folder(tmp_path, num_frames=2)
    bad = tmp_path / "images" / "front" / "000001.png"
    bad.write_bytes(b"\x89PNG not really")
    dataset = open_dataset(tmp_path)
    with pytest.raises(DatasetError, match="000001.png.*cannot be decoded"):
        dataset[1]


def test_nan_smpl_parameters_name_the_file(tmp_path):
    root = tmp_path / "CoreView_377"
    root.mkdir()
    write_zju_original(root, num_frames=2, num_cams=1)
    path = root / "new_params" / "1.npy"
    params = np.load(path, allow_pickle=True).item()
    params["Th"][0, 1] = np.nan
    np.save(path, params, allow_pickle=True)
    dataset = open_dataset(root, split="all")
    with pytest.raises(DatasetError, match=r"1\.npy: Th contains NaN"):
        dataset[1]


def test_mismatched_camera_counts_in_annots(tmp_path):
    root = tmp_path / "CoreView_377"
    root.mkdir()
    write_zju_original(root, num_frames=2, num_cams=2)
    annots = np.load(root / "annots.npy", allow_pickle=True).item()
    annots["ims"][1]["ims"] = annots["ims"][1]["ims"][:1]
    np.save(root / "annots.npy", annots, allow_pickle=True)
    with pytest.raises(DatasetError, match="annots.npy: frame 1 has 1 image paths.*expected 2 paths"):
        open_dataset(root)


def test_zju_without_params_folder(tmp_path):
    root = tmp_path / "CoreView_377"
    root.mkdir()
    write_zju_original(root, num_frames=1, num_cams=1)
    (root / "new_params" / "0.npy").unlink()
    (root / "new_params").rmdir()
    with pytest.raises(DatasetError, match="new_params"):
        open_dataset(root, kind="zju")


def test_folder_extra_image_and_pose_count_mismatch(tmp_path):
    write_folder(tmp_path, num_frames=2, num_cams=2)
    extra = tmp_path / "images" / "side" / "000007.png"
    extra.write_bytes((tmp_path / "images" / "side" / "000000.png").read_bytes())
    with pytest.raises(DatasetError, match=r"side.*extra frames \[7\]"):
        open_dataset(tmp_path)
    extra.unlink()
    poses = dict(np.load(tmp_path / "poses.npz"))
    poses["poses"] = poses["poses"][:1]
    np.savez(tmp_path / "poses.npz", **poses)
    with pytest.raises(DatasetError, match="poses.npz: has 1 pose rows but images/ has 2 frames"):
        open_dataset(tmp_path)


def test_folder_camera_without_intrinsics(tmp_path):
    write_folder(tmp_path, num_frames=1)
    doc = json.loads((tmp_path / "cameras.json").read_text())
    del doc["cameras"]["front"]["K"]
    (tmp_path / "cameras.json").write_text(json.dumps(doc))
    dataset = open_dataset(tmp_path)
    with pytest.raises(DatasetError, match="cameras.json: camera 'front' lacks 'K'"):
        dataset[0]


def test_image_of_another_size_names_the_file(tmp_path):
    import cv2

    write_folder(tmp_path, num_frames=2)
    odd = tmp_path / "images" / "front" / "000001.png"
    cv2.imwrite(str(odd), np.zeros((RAW_SIZE[1] + 2, RAW_SIZE[0], 3), np.uint8))
    dataset = open_dataset(tmp_path)
    dataset[0]
    with pytest.raises(DatasetError, match=r"000001.png: image is 160x122 \(expected 160x120"):
        dataset[1]


def test_thuman4_image_size_mismatch_and_bad_json(tmp_path):
    write_thuman4(tmp_path, num_frames=1, num_cams=1)
    calib = json.loads((tmp_path / "calibration.json").read_text())
    calib["cam00"]["imgSize"] = [RAW_SIZE[1], RAW_SIZE[0]]
    (tmp_path / "calibration.json").write_text(json.dumps(calib))
    with pytest.raises(DatasetError, match="imgSize"):
        open_dataset(tmp_path)[0]
    (tmp_path / "calibration.json").write_text("{not json")
    with pytest.raises(DatasetError, match="calibration.json: is not valid JSON"):
        open_dataset(tmp_path)
