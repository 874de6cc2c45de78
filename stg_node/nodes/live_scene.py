"""What the live views (the ``foxglove`` and ``web`` nodes) work out from the bus beyond format
conversions: where the body's joints are in the world, where a camera sees them, and the avatar's
Gaussians posed as a coloured point cloud.

- :class:`BodySkeleton`: the 24 joint positions of a BodyPose in the world. A pose that carries
  ``joints`` is taken as it is; otherwise forward kinematics (``stg_node.body.lbs.rigid_chain``,
  then the ``Rh``/``Th`` of the ZJU-MoCap convention, as ``stg_node.body`` poses a body) on the
  subject's rest joints: those of the latest avatar snapshot (the trainer's body and shape, so
  the skeleton sits inside the avatar), else those of ``body_model`` (default: the open body)
  shaped by the pose's own betas.
- :func:`project_points`: pixel positions of world points in a camera (OpenCV convention).
- :class:`AvatarCloud`: the latest snapshot rebuilt in a background thread (the renderer node's
  :class:`~stg_node.nodes.renderer.SnapshotLoader`) and posed with the latest body pose into
  centres, colours and opacities (:meth:`RendererAdapter.points`), the most opaque
  ``max_points`` kept: what an operator needs to see the avatar in 3D, at a few Hz.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass

import numpy as np

from stg_node.bus import BodyPose, GaussianSnapshot

log = logging.getLogger(__name__)

NUM_JOINTS = 24


class BodySkeleton:
    """World joint positions of BodyPose messages; see the module docstring for the sources."""

    def __init__(self, body_model: str | None = None):
        self.body_model = body_model
        self._body = None  # stg_node.body.BodyModel, loaded on first use
        self._snapshot_rest: np.ndarray | None = None  # (24, 3) from the latest snapshot
        self._snapshot_parents: np.ndarray | None = None
        self._shaped: dict[bytes, np.ndarray] = {}  # betas bytes -> rest joints (body model)
        self.ready = threading.Event()  # set once torch and the body model are loaded
        self.failure: str | None = None

    def warm_up(self) -> None:
        """Load torch and the body model (seconds on a busy CPU): run it in a thread at start, so
        that a node's loop never stalls on the first skeleton; :attr:`ready` is set at the end
        (also on failure, with :attr:`failure` saying why: the joints then raise)."""
        try:
            self.rest_joints(np.zeros(10, np.float32))
            posed_joints(
                np.zeros((NUM_JOINTS, 3)), self.parents, np.zeros((NUM_JOINTS, 3)), np.zeros(3), np.zeros(3)
            )
        except Exception as exc:  # a missing or unreadable body model: said once, here
            self.failure = (
                f"the skeleton's body model ({self.body_model or 'the open body'}) did not load: {exc}"
            )
            log.error("%s", self.failure)
        finally:
            self.ready.set()

    def start_warm_up(self) -> None:
        threading.Thread(target=self.warm_up, name="skeleton-warm-up", daemon=True).start()

    def use_snapshot(self, msg: GaussianSnapshot) -> bool:
        """Take the rest joints of an avatar snapshot (True if it has them)."""
        rest, parents = msg.arrays.get("body.rest_joints"), msg.arrays.get("body.parents")
        if rest is None or parents is None or rest.shape != (NUM_JOINTS, 3) or parents.shape != (NUM_JOINTS,):
            return False
        self._snapshot_rest = np.array(rest, np.float32)
        self._snapshot_parents = np.array(parents, np.int64)
        return True

    @property
    def parents(self) -> tuple[int, ...]:
        if self._snapshot_parents is not None:
            return tuple(int(p) for p in self._snapshot_parents)
        from stg_node.body.smpl_io import SMPL_PARENTS

        return SMPL_PARENTS

    def rest_joints(self, betas: np.ndarray) -> np.ndarray:
        if self._snapshot_rest is not None:
            return self._snapshot_rest
        key = np.asarray(betas, np.float32).tobytes()
        if key not in self._shaped:
            import torch

            if self._body is None:
                from stg_node.body import load_body_model

                self._body = load_body_model(self.body_model or None)
            b = torch.as_tensor(np.array(betas, np.float32)).reshape(1, -1)[:, : self._body.num_betas]
            with torch.no_grad():
                self._shaped = {key: self._body.rest_joints(b)[0].numpy()}  # one shape at a time
        return self._shaped[key]

    def joints(self, pose: BodyPose) -> np.ndarray:
        """(24, 3) float32 joint positions in the world."""
        if pose.joints is not None:
            return np.asarray(pose.joints, np.float32)
        return posed_joints(self.rest_joints(pose.betas), self.parents, pose.poses, pose.Rh, pose.Th)


def posed_joints(rest_joints, parents, poses, Rh, Th) -> np.ndarray:
    """Forward kinematics: rest joints (24, 3) posed by SMPL axis-angles (24, 3), then rotated by
    ``Rh`` and moved by ``Th`` (world = R(Rh) @ x + Th) -> (24, 3) float32."""
    import torch

    from stg_node.body import lbs

    with torch.no_grad():
        rotations = lbs.axis_angle_to_matrix(torch.as_tensor(np.array(poses, np.float32)).reshape(1, -1, 3))
        rest = torch.as_tensor(np.array(rest_joints, np.float32)).reshape(1, -1, 3)
        joints, _ = lbs.rigid_chain(rotations, rest, torch.as_tensor(np.array(parents, np.int64)))
        root = lbs.axis_angle_to_matrix(torch.as_tensor(np.array(Rh, np.float32)).reshape(1, 3))[0]
        world = joints[0] @ root.T + torch.as_tensor(np.array(Th, np.float32)).reshape(1, 3)
    return world.numpy().astype(np.float32)


def project_points(points: np.ndarray, K, R, t) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (N, 2) of world points in the camera (K, R, t: world -> camera, OpenCV
    axes) and whether each lies in front of it (N,)."""
    cam = np.asarray(points, np.float64) @ np.asarray(R, np.float64).T + np.asarray(t, np.float64).reshape(
        1, 3
    )
    pix = cam @ np.asarray(K, np.float64).T
    depth = pix[:, 2]
    front = depth > 1e-6
    uv = pix[:, :2] / np.where(front, depth, 1.0)[:, None]
    return uv, front


@dataclass(frozen=True)
class Cloud:
    positions: np.ndarray  # (N, 3) float32 world
    colors: np.ndarray  # (N, 3) uint8 RGB
    alpha: np.ndarray  # (N,) uint8
    snapshot_version: int


class AvatarCloud:
    """The latest avatar snapshot as a posed point cloud (see the module docstring)."""

    def __init__(self, *, module: str, device: str = "cpu", max_points: int = 50_000, on_error=None):
        from stg_node.nodes.avatar_adapter import RendererAdapter
        from stg_node.nodes.renderer import SnapshotLoader

        self.max_points = max_points
        self._on_error = on_error
        self._build_adapter = lambda msg: RendererAdapter.from_snapshot(msg, module=module, device=device)
        self._loader = SnapshotLoader(self._build_adapter, self._failed)
        self.current = None  # RendererAdapter
        self._latest_version = -1

    def _failed(self, msg: GaussianSnapshot, exc: Exception) -> None:
        log.warning("point cloud: snapshot v%d not loaded: %s", msg.model_version, exc)
        if self._on_error is not None:
            self._on_error(f"snapshot v{msg.model_version} not loaded for the point cloud: {exc}")

    def submit(self, msg: GaussianSnapshot) -> None:
        """Build this snapshot in the background (a newer one replaces one not yet started)."""
        if msg.model_version > self._latest_version:
            self._latest_version = msg.model_version
            self._loader.submit(msg)

    def cloud(self, pose: BodyPose, camera_center: np.ndarray | None) -> Cloud | None:
        """The posed cloud of the newest loaded snapshot (None before the first one is loaded, or
        when the avatar implementation cannot give points)."""
        built = self._loader.take()
        if built is not None and (self.current is None or built.version >= self.current.version):
            self.current = built
        if self.current is None:
            return None
        points = self.current.points(pose.to_smpl(), time=pose.time, camera_center=camera_center)
        if points is None:
            return None
        positions, colors, alpha = points
        if len(positions) > self.max_points:
            keep = np.argsort(-alpha.astype(np.int32), kind="stable")[: self.max_points]
            positions, colors, alpha = positions[keep], colors[keep], alpha[keep]
        return Cloud(positions, colors, alpha, self.current.version)

    def close(self) -> None:
        self._loader.close()
