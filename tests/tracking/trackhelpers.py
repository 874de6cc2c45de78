"""Shared pieces of the tracking tests: a small synthetic sequence, projected ground truth, skips."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch

from stg_node.body.lbs import axis_angle_to_matrix
from stg_node.safe_load import load_npy
from stg_node.tracking.body_points import BodyKeypoints
from stg_node.tracking.layouts import KeypointLayout
from stg_node.tracking.model_files import PoseModelError, pose_model_paths
from stg_node.tracking.types import Keypoints


def blazepose_installed() -> bool:
    try:
        pose_model_paths()
    except PoseModelError:
        return False
    try:
        import ai_edge_litert  # noqa: F401
    except ImportError:
        return False
    return True


needs_blazepose = pytest.mark.skipif(
    not blazepose_installed(),
    reason="BlazePose networks or ai-edge-litert not installed (python tools/install_pose_models.py)",
)


@dataclass
class GroundTruth:
    """One synthetic sequence's training camera and its per-frame SMPL parameters."""

    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    size: int
    poses: np.ndarray  # (N, 24, 3)
    Rh: np.ndarray  # (N, 3) world
    Th: np.ndarray  # (N, 3) world
    betas: np.ndarray  # (S,)
    folder: Path

    def __len__(self) -> int:
        return len(self.poses)

    def camera_params(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """(Rh, Th) of frame i in the camera's frame: x_cam = R (R(Rh) x + Th) + t."""
        rotation = self.R @ axis_angle_to_matrix(torch.as_tensor(self.Rh[i], dtype=torch.float64)).numpy()
        from stg_node.body.lbs import matrix_to_axis_angle

        return matrix_to_axis_angle(torch.as_tensor(rotation)).numpy(), self.R @ self.Th[i] + self.t


def load_ground_truth(folder: Path) -> GroundTruth:
    from stg_node.data.synth import open_synth
    from stg_node.data.synth.writer import read_metadata

    metadata = read_metadata(folder)
    dataset = open_synth(folder, "train", size=None)
    camera = dataset.camera(dataset.camera_names[0])
    frames = range(int(metadata["num_frames"]))
    params = [load_npy(folder / "new_params" / f"{i}.npy") for i in frames]
    return GroundTruth(
        K=camera.K,
        R=camera.R,
        t=camera.t,
        size=camera.width,
        poses=np.stack([p["poses"].reshape(24, 3) for p in params]).astype(np.float64),
        Rh=np.stack([p["Rh"].reshape(3) for p in params]).astype(np.float64),
        Th=np.stack([p["Th"].reshape(3) for p in params]).astype(np.float64),
        betas=params[0]["shapes"].reshape(-1).astype(np.float64),
        folder=folder,
    )


def camera_joints(body, truth: GroundTruth) -> np.ndarray:
    """(N, 24, 3) ground-truth SMPL joints in the camera frame."""
    with torch.no_grad():
        out = body(
            betas=torch.as_tensor(truth.betas, dtype=torch.float32),
            poses=torch.as_tensor(truth.poses.reshape(-1, 72), dtype=torch.float32),
            Rh=torch.as_tensor(truth.Rh, dtype=torch.float32),
            Th=torch.as_tensor(truth.Th, dtype=torch.float32),
        )
    return out.joints.double().numpy() @ truth.R.T + truth.t


def projected_keypoints(
    body, layout: KeypointLayout, truth: GroundTruth, i: int, *, noise_px: float = 0.0, rng=None
) -> Keypoints:
    """The layout's keypoints at their true body points, projected by the camera, plus noise."""
    model = BodyKeypoints(body, [target.point for target in layout.targets]).double()
    with torch.no_grad():
        points = model(
            torch.as_tensor(truth.betas)[None],
            torch.as_tensor(truth.poses[i, 1:])[None],
            torch.as_tensor(truth.Rh[i])[None],
            torch.as_tensor(truth.Th[i])[None],
        )[0].numpy()
    camera = points @ truth.R.T + truth.t
    uv = camera @ truth.K.T
    uv = uv[:, :2] / uv[:, 2:]
    xy = np.zeros((layout.num_points, 2))
    score = np.zeros(layout.num_points)
    for k, target in enumerate(layout.targets):
        for source in target.sources:  # averaged sources all sit on the body point
            xy[source] = uv[k]
            score[source] = 1.0
    if noise_px:
        xy = xy + (rng or np.random.default_rng(0)).normal(0.0, noise_px, xy.shape)
    return Keypoints(layout=layout.name, xy=xy.astype(np.float32), score=score.astype(np.float32))
