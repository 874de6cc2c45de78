"""The fit preview (stg_node.tracking.preview): one frame per input frame, the mesh where the body is,
the mask tinted, skipped frames marked; and the checks that mark frames untrustworthy."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from trackhelpers import load_ground_truth

from stg_node.data.synth import SynthConfig, generate
from stg_node.tracking.frame_checks import BORDER_CONTACT, FrameChecks, border_contact, image_factor
from stg_node.tracking.pipeline import TrackSummary, skip_reasons
from stg_node.tracking.poses_file import TrackedPoses, read_poses, write_poses
from stg_node.tracking.preview import MASK_RGB, mesh_overlay, write_preview


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    out = tmp_path_factory.mktemp("preview") / "seq"
    generate(
        SynthConfig(out=out, seed=5, num_frames=6, size=128, num_novel_views=0, supersample=1), progress=False
    )
    return load_ground_truth(out)


def truth_poses(truth, confidence, flags) -> TrackedPoses:
    """The ground truth as a POSES.npz would hold it: parameters in the camera's frame."""
    n = len(truth)
    Rh, Th = zip(*(truth.camera_params(i) for i in range(n)), strict=True)
    return TrackedPoses(
        poses=truth.poses.reshape(n, 72).astype(np.float32),
        Rh=np.stack(Rh).astype(np.float32),
        Th=np.stack(Th).astype(np.float32),
        shapes=np.tile(truth.betas, (n, 1)).astype(np.float32),
        confidence=np.asarray(confidence, np.float32),
        frames=np.arange(n),
        times=np.arange(n) / 30.0,
        K=truth.K,
        dist=np.zeros(0),
        image_size=(truth.size, truth.size),
        fps=30.0,
        flags=np.asarray(flags, dtype=str),
    )


def read_video(path):
    cap = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, frame = cap.read()
        if not ok:
            return frames
        frames.append(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))


def test_the_mesh_overlay_covers_the_rendered_body(clip, body):
    """The preview's mesh is the fitted body seen by the tracking camera: on the ground truth it covers
    the benchmark's own mask (which adds the garment's few centimetres) almost exactly."""
    import torch

    from stg_node.data.io import read_mask

    poses = truth_poses(clip, [1.0] * len(clip), [""] * len(clip))
    for i in (0, 3):
        with torch.no_grad():
            vertices = (
                body(
                    betas=torch.as_tensor(poses.shapes[i : i + 1]),
                    poses=torch.as_tensor(poses.poses[i : i + 1]),
                    Rh=torch.as_tensor(poses.Rh[i : i + 1]),
                    Th=torch.as_tensor(poses.Th[i : i + 1]),
                )
                .vertices[0]
                .double()
                .numpy()
            )
        _, covered = mesh_overlay(vertices, body.faces.numpy(), clip.K, clip.size, clip.size)
        mask = read_mask(clip.folder / "mask" / "Camera_B1" / f"{i:06d}.png") > 0
        iou = (covered & mask).sum() / (covered | mask).sum()
        assert iou > 0.9, (i, iou)


def test_the_preview_has_a_frame_per_input_frame_with_mesh_mask_and_skips(clip, tmp_path):
    n = len(clip)
    confidence = [0.9, 0.8, 0.2, 0.9, 0.0, 0.7]
    flags = ["", "", "cut_by_border", "", "no_person", ""]
    poses = write_poses(tmp_path / "POSES.npz", truth_poses(clip, confidence, flags))
    masks = tmp_path / "masks"
    masks.mkdir()
    for i in range(n):  # the benchmark's masks, as if the tracker had made them
        mask = cv2.imread(str(clip.folder / "mask" / "Camera_B1" / f"{i:06d}.png"), cv2.IMREAD_GRAYSCALE)
        cv2.imwrite(str(masks / f"{i:06d}.png"), mask)
    out = tmp_path / "fit.mp4"
    written = write_preview(clip.folder / "Camera_B1", poses, out, masks_dir=masks, progress=False)
    frames = read_video(out)
    assert written == len(frames) == n
    inputs = [cv2.cvtColor(cv2.imread(str(clip.folder / "Camera_B1" / f"{i:06d}.png")), cv2.COLOR_BGR2RGB)
              for i in range(n)]  # fmt: skip
    inside = (slice(30, clip.size - 3), slice(3, clip.size - 3))  # below the status bar, inside the frame
    for i, (frame, image) in enumerate(zip(frames, inputs, strict=True)):
        on = cv2.imread(str(masks / f"{i:06d}.png"), cv2.IMREAD_GRAYSCALE)[inside] > 0
        diff = np.abs(frame[inside].astype(int) - image[inside].astype(int)).sum(-1)
        assert diff[on].mean() > 40, i  # the mesh and the mask are drawn over the person ...
        assert diff[~on].mean() < 12, i  # ... and little else changes (codec noise, the outline)
        border = np.concatenate([frame[:, 0], frame[:, -1]]).astype(int)
        red = (border[:, 0] > 150) & (border[:, 1] < 100)
        assert (red.mean() > 0.5) == (confidence[i] < 0.5), i  # skipped frames framed in red
    # The mesh is blue, the mask green: on the person, frame 0 is bluer and greener than its input.
    on = cv2.imread(str(masks / "000000.png"), cv2.IMREAD_GRAYSCALE) > 0
    delta = frames[0][on].astype(int).mean(0) - inputs[0][on].astype(int).mean(0)
    assert delta[2] > 20 and MASK_RGB[1] > 200


def test_the_summary_counts_skipped_frames_by_reason():
    confidence = np.array([0.9, 0.1, 0.2, 0.0, 0.4, 0.95])
    flags = ["", "cut_by_border", "cut_by_border,motion_blur", "no_person", "", ""]
    counts = skip_reasons(confidence, flags)
    assert counts == {"cut_by_border": 2, "motion_blur": 1, "no_person": 1, "low_confidence": 1}
    summary = TrackSummary(
        out=None, frames=6, confident_frames=2, mean_confidence=0.4, seconds=1.0, skipped=counts
    )
    assert summary.describe_skipped().startswith("4 of 6 frames skipped")
    assert "2 cut_by_border" in summary.describe_skipped()


def test_a_person_cut_by_the_border_is_flagged_and_a_foot_on_it_is_not():
    mask = np.zeros((200, 120), np.uint8)
    mask[20:200, 40:80] = 255  # legs run out of the bottom of the image: 40 px on the edge of 180 tall
    assert border_contact(mask) == pytest.approx(40 / 180)
    foot = np.zeros_like(mask)
    foot[20:199, 40:80] = 255
    foot[199, 55:61] = 255  # 6 px of one foot on the edge
    assert border_contact(foot) < BORDER_CONTACT <= border_contact(mask)
    image = np.full((200, 120, 3), 128, np.uint8)
    factor, flags = FrameChecks().check(image, mask)
    assert flags == ["cut_by_border"] and factor < 0.5
    assert FrameChecks().check(image, foot) == (1.0, [])


def test_a_blurred_frame_is_flagged_against_the_persons_own_sharpness():
    rng = np.random.default_rng(0)
    texture = (rng.random((160, 100, 3)) * 255).astype(np.uint8)
    texture = cv2.resize(cv2.resize(texture, (25, 40), interpolation=cv2.INTER_NEAREST), (100, 160),
                         interpolation=cv2.INTER_NEAREST)  # fmt: skip  # blocks: a striped-shirt-like texture
    mask = np.zeros((160, 100), np.uint8)
    mask[10:150, 20:80] = 255
    checks = FrameChecks()
    for _ in range(12):  # the person's usual sharpness
        assert checks.check(texture, mask) == (1.0, [])
    kernel = np.zeros((15, 15), np.float32)
    kernel[7, :] = 1 / 15  # a 15 px horizontal motion smear
    smeared = cv2.filter2D(texture, -1, kernel)
    factor, flags = checks.check(smeared, mask)
    assert flags == ["motion_blur"] and factor < 0.5
    assert checks.check(texture, mask) == (1.0, [])  # the blurred frame did not lower the reference
    assert image_factor(["cut_by_border", "motion_blur"]) < image_factor(["motion_blur"]) < 1.0


def test_flags_and_camera_survive_the_poses_file(clip, tmp_path):
    tracked = truth_poses(clip, [0.9] * len(clip), ["", "motion_blur", "", "", "", ""])
    tracked.camera = '{"method": "fov", "fov_deg": 50.0}'
    back = read_poses(write_poses(tmp_path / "P.npz", tracked))
    assert list(back.flags) == list(tracked.flags) and back.camera == tracked.camera
