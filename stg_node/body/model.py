"""The SMPL-format body model: shape and pose parameters in, posed mesh, joints and bone transforms out.

One class serves every body the project knows: the official SMPL files (brought by the user) and
the open body that ships with stg_node (``assets/open_body``), because both are SMPL-format
models. Global placement follows ZJU-MoCap / EasyMocap: ``world = R(Rh) @ smpl_local + Th``,
where ``poses[0]`` is SMPL's own global orientation about the pelvis joint and ``Rh`` rotates
about the model's origin.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from stg_node.body import lbs
from stg_node.body.smpl_io import (
    SMPL_JOINT_NAMES,
    SMPL_NUM_JOINTS,
    BodyModelError,
    ModelArrays,
    read_model_file,
    resolve_model_file,
)

log = logging.getLogger(__name__)

OPEN_BODY_DIR = Path(__file__).resolve().parent / "assets" / "open_body"
OPEN_BODY_FILE = OPEN_BODY_DIR / "open_body.npz"
NUM_POSE_FEATURES = (SMPL_NUM_JOINTS - 1) * 9


@dataclass
class BodyOutput:
    """What a forward pass returns; positions and transforms are in WORLD space (after Rh, Th)."""

    vertices: torch.Tensor  # (B, V, 3) posed mesh
    joints: torch.Tensor  # (B, 24, 3) posed joints
    bone_transforms: torch.Tensor  # (B, 24, 4, 4) rest (shaped, zero pose) -> world, per joint
    shaped_vertices: torch.Tensor  # (B, V, 3) rest mesh after shape blend shapes (zero pose, model space)
    rest_joints: torch.Tensor  # (B, 24, 3) joints of shaped_vertices (model space)
    rotations: torch.Tensor  # (B, 24, 3, 3) local joint rotations (from poses)


def _as_batch(value, width: int, name: str, batch: int | None, like: torch.Tensor) -> torch.Tensor | None:
    """Turn None / (width,) / (B, width) / (B, J, 3) inputs into a (B, width) tensor, or None."""
    if value is None:
        return None
    tensor = torch.as_tensor(value, dtype=like.dtype, device=like.device)
    if tensor.dim() == 1:
        tensor = tensor[None]
    elif tensor.dim() == 3 and name == "poses":
        tensor = tensor.reshape(tensor.shape[0], -1)
    if tensor.dim() != 2 or tensor.shape[1] != width:
        hint = " (or (B, 24, 3))" if name == "poses" else ""
        raise ValueError(f"{name} must be ({width},) or (B, {width}){hint}, got shape {tuple(tensor.shape)}")
    if not torch.isfinite(tensor).all():
        raise ValueError(f"{name} contains NaN or infinite values")
    return tensor


class BodyModel(torch.nn.Module):
    """An SMPL-format body model (official SMPL or the shipped open body).

    Buffers (all on the model's device and dtype, integer ones as long):
        v_template (V, 3), shapedirs (V, 3, S), posedirs (207, V*3) (smplx's layout: row k is the
        displacement of the k-th pose feature ``(R_j - I)`` flattened, joints 1..23 in order),
        J_regressor (24, V) dense, weights (V, 24), parents (24,), faces (F, 3).
    Optional (the open body has them, SMPL files do not; ``None`` otherwise): uv (Vt, 2) in
    [0, 1], OBJ convention (v up), with uv_faces (F, 3) indexing it per face corner, and
    ``texture`` (H, W, 3) uint8 numpy, the albedo, whose row 0 is v = 1 (sample at
    ``texture[(1 - v) * H, u * W]``).
    """

    num_joints = SMPL_NUM_JOINTS
    joint_names = SMPL_JOINT_NAMES

    def __init__(
        self, arrays: ModelArrays, *, num_betas: int | None = None, dtype=torch.float32, device="cpu"
    ):
        super().__init__()
        available = arrays.shapedirs.shape[2]
        if num_betas is None:
            num_betas = available
        if not 0 <= num_betas <= available:
            raise BodyModelError(
                f"num_betas={num_betas} but the model {arrays.name!r} has {available} shape directions"
            )
        self.name = arrays.name
        self.num_betas = int(num_betas)
        num_verts = arrays.v_template.shape[0]

        def buf(name, array, dt=dtype):
            self.register_buffer(name, torch.as_tensor(np.ascontiguousarray(array), dtype=dt, device=device))

        buf("v_template", arrays.v_template)
        buf("shapedirs", arrays.shapedirs[:, :, :num_betas])
        buf("posedirs", arrays.posedirs.reshape(num_verts * 3, NUM_POSE_FEATURES).T)
        buf("J_regressor", arrays.J_regressor)
        buf("weights", arrays.weights)
        buf("parents", arrays.parents, torch.long)
        buf("faces", arrays.faces, torch.long)
        if arrays.uv is not None:
            buf("uv", arrays.uv)
            buf("uv_faces", arrays.uv_faces, torch.long)
        else:
            self.uv = None
            self.uv_faces = None
        self.texture = arrays.texture
        # The open body has no pose correctives: skip the (B, 207) x (207, 3V) product entirely.
        self.has_pose_blendshapes = bool(np.any(arrays.posedirs != 0))

    # ------------------------------------------------------------------------------------------

    @property
    def num_vertices(self) -> int:
        return int(self.v_template.shape[0])

    def extra_repr(self) -> str:
        return (
            f"name={self.name!r}, vertices={self.num_vertices}, faces={int(self.faces.shape[0])}, "
            f"num_betas={self.num_betas}, pose_blendshapes={self.has_pose_blendshapes}"
        )

    def _batch_betas(self, betas) -> torch.Tensor | None:
        if betas is None:
            return None
        like = self.v_template
        tensor = torch.as_tensor(betas, dtype=like.dtype, device=like.device)
        if tensor.dim() == 1:
            tensor = tensor[None]
        if tensor.dim() != 2:
            raise ValueError(f"betas must be (S,) or (B, S), got shape {tuple(tensor.shape)}")
        if not torch.isfinite(tensor).all():
            raise ValueError("betas contain NaN or infinite values")
        count = tensor.shape[1]
        if count > self.num_betas:
            if torch.any(tensor[:, self.num_betas :] != 0):
                raise ValueError(
                    f"betas have {count} coefficients but model {self.name!r} has {self.num_betas} shape "
                    "directions (pass fewer betas, or a larger num_betas to load_body_model)"
                )
            tensor = tensor[:, : self.num_betas]
        elif count < self.num_betas:
            tensor = torch.cat([tensor, tensor.new_zeros(tensor.shape[0], self.num_betas - count)], dim=1)
        return tensor

    def _batch_inputs(self, betas, poses, Rh, Th):
        like = self.v_template
        betas_t = self._batch_betas(betas)
        poses_t = _as_batch(poses, SMPL_NUM_JOINTS * 3, "poses", None, like)
        rh_t = _as_batch(Rh, 3, "Rh", None, like)
        th_t = _as_batch(Th, 3, "Th", None, like)
        sizes = {t.shape[0] for t in (betas_t, poses_t, rh_t, th_t) if t is not None}
        batch = max(sizes) if sizes else 1
        if any(s not in (1, batch) for s in sizes):
            raise ValueError(f"inconsistent batch sizes {sorted(sizes)} for betas/poses/Rh/Th")

        def full(t, width):
            if t is None:
                return like.new_zeros(batch, width)
            return t.expand(batch, -1)

        return full(betas_t, self.num_betas), full(poses_t, SMPL_NUM_JOINTS * 3), full(rh_t, 3), full(th_t, 3)

    def shape_vertices(self, betas: torch.Tensor) -> torch.Tensor:
        """Rest mesh for ``(B, S)`` betas: ``v_template + shapedirs . betas`` -> (B, V, 3)."""
        return self.v_template + torch.einsum("bs,vcs->bvc", betas, self.shapedirs)

    def rest_joints(self, betas=None) -> torch.Tensor:
        """Joints of the shaped rest pose (model space, no Rh/Th) -> (B, 24, 3)."""
        betas_t = self._batch_inputs(betas, None, None, None)[0]
        return torch.einsum("jv,bvc->bjc", self.J_regressor, self.shape_vertices(betas_t))

    def forward(self, betas=None, poses=None, Rh=None, Th=None, pose_blendshapes: bool = True) -> BodyOutput:
        """Pose the body.

        Args:
            betas: ``(S,)`` or ``(B, S)`` shape coefficients (fewer than S are zero-padded).
            poses: ``(72,)``, ``(B, 72)`` or ``(B, 24, 3)`` axis-angle per joint; ``poses[:, 0]`` is
                SMPL's global orientation about the pelvis joint.
            Rh: ``(3,)`` / ``(B, 3)`` axis-angle rotation about the model origin, applied after SMPL.
            Th: ``(3,)`` / ``(B, 3)`` translation, applied last.
            pose_blendshapes: add SMPL's pose corrective blend shapes (no-op for models without).

        Missing inputs are zeros; a batch of 1 broadcasts against the others.
        """
        betas_t, poses_t, rh_t, th_t = self._batch_inputs(betas, poses, Rh, Th)
        batch = poses_t.shape[0]
        shaped = self.shape_vertices(betas_t)
        rest_joints = torch.einsum("jv,bvc->bjc", self.J_regressor, shaped)
        rotations = lbs.axis_angle_to_matrix(poses_t.reshape(batch, SMPL_NUM_JOINTS, 3))
        posed_rest = shaped
        if pose_blendshapes and self.has_pose_blendshapes:
            eye = torch.eye(3, dtype=rotations.dtype, device=rotations.device)
            features = (rotations[:, 1:] - eye).reshape(batch, NUM_POSE_FEATURES)
            posed_rest = shaped + (features @ self.posedirs).reshape(batch, -1, 3)
        _, local_transforms = lbs.rigid_chain(rotations, rest_joints, self.parents)
        world = lbs.make_rigid(lbs.axis_angle_to_matrix(rh_t), th_t)  # (B, 4, 4)
        bone_transforms = world[:, None] @ local_transforms
        vertices = lbs.skin_points(posed_rest, self.weights, bone_transforms)
        joints = (bone_transforms[..., :3, :3] @ rest_joints[..., None]).squeeze(-1) + bone_transforms[
            ..., :3, 3
        ]
        return BodyOutput(
            vertices=vertices,
            joints=joints,
            bone_transforms=bone_transforms,
            shaped_vertices=shaped,
            rest_joints=rest_joints,
            rotations=rotations,
        )


def load_body_model(
    path: str | Path | None = None,
    gender: str = "neutral",
    *,
    num_betas: int | None = None,
    device="cpu",
    dtype=torch.float32,
) -> BodyModel:
    """Load an SMPL-format body model.

    Args:
        path: ``None`` or ``"open"`` for the open body shipped with stg_node; an SMPL ``.pkl`` /
            ``.npz`` file; or a directory holding the usual SMPL names (``SMPL_NEUTRAL.pkl``,
            ``basicmodel_neutral_lbs_10_207_0_v1.1.0.pkl``, ``basicModel_f_lbs_10_207_0_v1.0.0.pkl``, ...).
        gender: ``neutral``, ``male`` or ``female``: picks the file in a directory. The open body
            has one (neutral) shape; other genders are reached through its shape directions.
        num_betas: keep only the first shape directions (default: all in the file).
    """
    if path is None or (isinstance(path, str) and path.lower() == "open"):
        if not OPEN_BODY_FILE.is_file():
            raise BodyModelError(
                f"the open body asset is missing ({OPEN_BODY_FILE}); rebuild it with tools/make_open_body.py"
            )
        file = OPEN_BODY_FILE
    else:
        file = resolve_model_file(path, gender)
    arrays = read_model_file(file)
    if arrays.name == "smpl":
        arrays.name = f"smpl:{file.name}"
    model = BodyModel(arrays, num_betas=num_betas, dtype=dtype, device=device)
    log.debug("loaded body model %s from %s", model.name, file)
    return model
