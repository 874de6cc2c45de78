"""How far each held-out pose is from what training showed: in body pose, and in orientation.

A held-out frame can be new in two separate ways, and an avatar fails them for separate reasons:

- **pose** (geometry): the joints bend in a way no training frame did. Measured as the distance
  to the nearest training frame in the avatar's own pose space (the Frobenius distance between
  the 23 local joint rotation matrices, root and global rotation left out: the metric the
  novel-pose time code uses, stg_node/avatar/timecode.py), and, easier to read, the RMS over
  those joints of the rotation angle between the two poses, in degrees.
- **orientation** (shading): the body as a whole faces a way no training frame did, so a light
  fixed in the room falls on it from a direction never seen. Measured as the smallest rotation
  angle between the frame's global orientation (``Rh`` after SMPL's root joint) and any training
  frame's, in degrees; ``yaw_deg`` is the frame's heading about the world's up axis, 0 when the
  body faces the training camera (the benchmark's world: z up, the camera on -y).
- **joint extrapolation**: the RMS above dilutes a motion that takes a few joints far (raised arms
  with folded elbows move 4 of 23 joints) among the joints that stay where training had them.
  ``joint_max_deg`` is, over the joints, the largest angle between the joint's rotation and the
  nearest rotation *that joint* had in any training frame (``joint_max_name`` names the joint):
  how far beyond anything seen the most extrapolated joint goes.

``stg-synth`` writes both for every held-out frame into ``synth.json``; ``stg-eval`` and the
trade-off study report them beside the scores.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from stg_node.body import SMPL_JOINT_NAMES
from stg_node.data.synth.rotations import axis_angle_to_matrix


@dataclass(frozen=True)
class HeldOutDistance:
    """One held-out frame against the training frames."""

    frame: int
    nearest_pose_frame: int  # the training frame nearest in pose space
    pose_distance: float  # Frobenius distance of the 23 local joint rotations to it
    pose_rms_deg: float  # RMS over the 23 joints of the rotation angle to it, degrees
    nearest_orientation_frame: int  # the training frame whose global orientation is nearest
    orientation_deg: float  # rotation angle between the two global orientations, degrees
    yaw_deg: float  # heading about world up, 0 = facing the training camera, (-180, 180]
    # the most extrapolated joint: its angle to its own nearest training rotation (None: not recorded)
    joint_max_deg: float | None = None
    joint_max_name: str | None = None

    def to_dict(self) -> dict:
        return asdict(self)


def local_rotations(poses: np.ndarray) -> np.ndarray:
    """(N, 24, 3) axis-angle -> (N, 23, 3, 3) local rotations of joints 1..23 (float64)."""
    p = np.asarray(poses, dtype=np.float64).reshape(-1, 24, 3)
    return axis_angle_to_matrix(p[:, 1:])


def global_orientations(poses: np.ndarray, Rh: np.ndarray) -> np.ndarray:
    """(N, 3, 3) world orientation of the body's root: ``R(Rh) @ R(poses[:, 0])``."""
    p = np.asarray(poses, dtype=np.float64).reshape(-1, 24, 3)
    return axis_angle_to_matrix(np.asarray(Rh, dtype=np.float64).reshape(-1, 3)) @ axis_angle_to_matrix(
        p[:, 0]
    )


def rotation_angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle (degrees) of ``a^T b`` for rotation matrices (..., 3, 3), broadcasting."""
    cosine = (np.einsum("...ij,...ij->...", a, b) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))


def heading_deg(orientation: np.ndarray) -> np.ndarray:
    """Yaw (degrees) of the body's forward axis (SMPL +z) about world z; 0 when it faces -y."""
    forward = orientation @ np.array([0.0, 0.0, 1.0])
    return np.degrees(np.arctan2(forward[..., 0], -forward[..., 1]))


def held_out_distances(poses: np.ndarray, Rh: np.ndarray, train_frames, test_frames) -> list[HeldOutDistance]:
    """Distances of every frame in ``test_frames`` to the frames in ``train_frames`` (indices into
    ``poses`` (N, 24, 3) and ``Rh`` (N, 3))."""
    train = np.asarray(list(train_frames), dtype=np.int64)
    test = np.asarray(list(test_frames), dtype=np.int64)
    if train.size == 0:
        raise ValueError("held_out_distances needs at least one training frame")
    local = local_rotations(poses)
    keys = local.reshape(local.shape[0], -1)
    orient = global_orientations(poses, Rh)
    out = []
    for frame in test.tolist():
        per_joint = rotation_angle_deg(local[train], local[frame][None]).min(axis=0)  # (23,)
        worst = int(per_joint.argmax())
        dist = np.linalg.norm(keys[train] - keys[frame], axis=1)
        k = int(dist.argmin())
        joint_angles = rotation_angle_deg(local[train[k]], local[frame])
        angles = rotation_angle_deg(orient[train], orient[frame])
        j = int(angles.argmin())
        out.append(
            HeldOutDistance(
                frame=int(frame),
                nearest_pose_frame=int(train[k]),
                pose_distance=float(dist[k]),
                pose_rms_deg=float(np.sqrt(np.mean(joint_angles**2))),
                nearest_orientation_frame=int(train[j]),
                orientation_deg=float(angles[j]),
                yaw_deg=float(heading_deg(orient[frame])),
                joint_max_deg=float(per_joint[worst]),
                joint_max_name=SMPL_JOINT_NAMES[worst + 1],
            )
        )
    return out


def summarise(distances: list[HeldOutDistance]) -> dict:
    """Median and maximum of the pose and orientation distances (NaN when there are none)."""

    def stats(values: list[float]) -> dict:
        if not values:
            return {"median": float("nan"), "max": float("nan")}
        return {"median": float(np.median(values)), "max": float(np.max(values))}

    out = {
        "frames": len(distances),
        "pose_rms_deg": stats([d.pose_rms_deg for d in distances]),
        "orientation_deg": stats([d.orientation_deg for d in distances]),
    }
    joint = [d.joint_max_deg for d in distances if d.joint_max_deg is not None]
    if joint or not distances:
        out["joint_max_deg"] = stats(joint)
    return out


def benchmark_condition(metadata: dict, frames=None) -> dict:
    """What a generated benchmark tests (from its ``synth.json``): the light, the motions, the
    orientations held out, and the held-out frames' distances (over ``frames`` when given, e.g. the
    frames a split evaluates; all held-out frames otherwise). Folders written before held-out
    distances were recorded give what they have."""
    held = metadata.get("held_out") or {}
    record = {
        "shading": (metadata.get("shading") or {}).get("mode"),
        "motion": metadata.get("motion"),
        "test_motion": held.get("test_motion"),
        "train_yaw_deg": held.get("train_yaw_deg"),
        "test_yaw_deg": held.get("test_yaw_deg"),
    }
    if "distances" in held:
        wanted = None if frames is None else {int(f) for f in frames}
        chosen = [
            HeldOutDistance(**d) for d in held["distances"] if wanted is None or int(d["frame"]) in wanted
        ]
        record["held_out"] = summarise(chosen)
    return record
