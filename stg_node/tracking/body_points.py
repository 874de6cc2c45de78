"""The body's keypoints as a tiny differentiable function of SMPL parameters: what the fitter moves.

A pose network reports joints (shoulders, knees, ...) and surface points (nose, ears, heels,
toes). On an SMPL-format body the first are SMPL joints and the second are mesh vertices. Fitting
needs only these few points, never the 7k-14k vertex mesh: with the shape fixed, the joints come
from the kinematic chain and each surface point is one vertex skinned with its own weights. So
:class:`BodyKeypoints` precomputes, from any :class:`~stg_node.body.BodyModel`,

- the rest joints and their shape directions (``J_regressor`` applied to the template and to
  each shape direction), and
- the surface landmarks (:func:`surface_landmarks`: found on the rest mesh by geometry, so the
  same code serves the official SMPL and the open body; face, heels, toes and the hand's index
  and pinky knuckles and thumb, which give the palm's turn about the forearm), with their shape
  directions and skinning weights,

and poses them with the body package's own forward kinematics (``lbs.rigid_chain``) and skinning
(``lbs.skin_points``). SMPL's pose-corrective blend shapes are left out (millimetres at these
points). Placement follows ZJU-MoCap: ``points = R(Rh) @ body_points + Th``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from stg_node.body import BodyModel, lbs
from stg_node.body.smpl_io import SMPL_JOINT_NAMES

JOINT_INDEX = {name: i for i, name in enumerate(SMPL_JOINT_NAMES)}
HEAD = JOINT_INDEX["head"]
LANDMARK_NAMES = (
    "nose",
    "left_eye",
    "right_eye",
    "left_ear",
    "right_ear",
    "left_heel",
    "right_heel",
    "left_toe",
    "right_toe",
    "left_index",
    "right_index",
    "left_pinky",
    "right_pinky",
    "left_thumb",
    "right_thumb",
)
# Rough face geometry of an adult (metres, SMPL axes at rest: x = the body's left, y up, z front),
# used only to pick vertices; any body's own mesh decides where the points actually are.
EYE_HALF_SPACING_M = 0.032
EYE_ABOVE_NOSE_M = 0.035
EAR_ABOVE_NOSE_M = 0.01
SEARCH_BAND_M = 0.03
# Hand landmarks: the knuckle line is the slice of hand vertices within this distance of the hand
# joint along the forearm's axis; the fingers' outer part is the hand beyond the knuckles by more
# than this share of the longest finger (the thumb, shorter, ends before it).
KNUCKLE_BAND_M = 0.015
FINGERTIP_SHARE = 0.6


def _region(weights: np.ndarray, joints: list[int]) -> np.ndarray:
    """Vertices whose strongest skinning weight belongs to one of ``joints``."""
    return np.isin(np.argmax(weights, axis=1), joints)


def surface_landmarks(vertices: np.ndarray, weights: np.ndarray, rest_joints: np.ndarray) -> dict[str, int]:
    """Vertex index of each of :data:`LANDMARK_NAMES` on a rest-pose (T-pose, SMPL axes) mesh.

    Geometric rules: the nose is the head's most forward vertex; eyes the most forward head
    vertices near ``(+-3.2 cm, 3.5 cm above the nose)``; ears the most lateral head vertices near
    nose height; heels the rearmost and toes the foremost vertices of each foot below its ankle.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    head = np.flatnonzero(_region(weights, [HEAD]))
    if head.size < 10:
        raise ValueError("the body has too few head vertices to place face landmarks on")
    nose = head[np.argmax(vertices[head, 2])]
    nose_xyz = vertices[nose]
    found = {"nose": int(nose)}
    for side, sign in (("left", 1.0), ("right", -1.0)):
        near_eye = head[
            (np.abs(vertices[head, 0] - sign * EYE_HALF_SPACING_M) < SEARCH_BAND_M / 2)
            & (np.abs(vertices[head, 1] - nose_xyz[1] - EYE_ABOVE_NOSE_M) < SEARCH_BAND_M / 2)
        ]
        candidates = near_eye if near_eye.size else head
        found[f"{side}_eye"] = int(candidates[np.argmax(vertices[candidates, 2])])
        ear_band = head[np.abs(vertices[head, 1] - nose_xyz[1] - EAR_ABOVE_NOSE_M) < SEARCH_BAND_M]
        candidates = ear_band if ear_band.size else head
        found[f"{side}_ear"] = int(candidates[np.argmax(sign * vertices[candidates, 0])])
        ankle = JOINT_INDEX[f"{side}_ankle"]
        foot = np.flatnonzero(_region(weights, [ankle, JOINT_INDEX[f"{side}_foot"]]))
        below = foot[vertices[foot, 1] < rest_joints[ankle, 1]]
        if below.size == 0:
            raise ValueError(f"the body has no {side} foot vertices below the ankle joint")
        # Heel: rearmost vertex in the lower half of the foot (not the back of the ankle).
        low = below[vertices[below, 1] < np.median(vertices[below, 1])]
        low = low if low.size else below
        found[f"{side}_heel"] = int(low[np.argmin(vertices[low, 2])])
        found[f"{side}_toe"] = int(below[np.argmax(vertices[below, 2])])
        found.update(hand_landmarks(vertices, weights, rest_joints, side))
    return found


def hand_landmarks(
    vertices: np.ndarray, weights: np.ndarray, rest_joints: np.ndarray, side: str
) -> dict[str, int]:
    """Vertex index of one hand's index knuckle, pinky knuckle and thumb on a rest-pose mesh.

    In SMPL's rest pose the arms are straight out, palms down, both thumbs forward (+z). In the
    hand's frame (axis: wrist joint to hand joint, SMPL's knuckle line; lateral: +z made
    orthogonal to it, the thumb's side) the knuckles are the two vertices of the knuckle slice
    (within ``KNUCKLE_BAND_M`` of the hand joint along the axis) nearest to the fingers' lateral
    extremes, measured where the thumb has ended (the fingers' outer ``FINGERTIP_SHARE``), at the slice's
    mid height: index on the thumb's side, pinky on the other. The thumb is the most lateral hand
    vertex (its tip). BlazePose's index and pinky points are those knuckles; its thumb point is the
    thumb's second knuckle, a little short of the tip. What matters for the fit is the palm's
    lateral line, index to pinky: it turns with the forearm's twist, which no joint point shows.
    """
    wrist, hand = rest_joints[JOINT_INDEX[f"{side}_wrist"]], rest_joints[JOINT_INDEX[f"{side}_hand"]]
    region = np.flatnonzero(_region(weights, [JOINT_INDEX[f"{side}_wrist"], JOINT_INDEX[f"{side}_hand"]]))
    axis = hand - wrist
    length = float(np.linalg.norm(axis))
    if region.size < 10 or length < 1e-3:
        raise ValueError(f"the body has no {side} hand to place knuckle landmarks on")
    axis /= length
    lateral = np.array([0.0, 0.0, 1.0]) - axis[2] * axis
    lateral /= max(float(np.linalg.norm(lateral)), 1e-9)
    normal = np.cross(axis, lateral)
    offset = vertices[region] - hand
    along, across = offset @ axis, offset @ lateral
    knuckles = region[np.abs(along) < KNUCKLE_BAND_M]
    fingers = along > FINGERTIP_SHARE * along.max()
    if knuckles.size < 4 or fingers.sum() < 4:
        raise ValueError(
            f"the body's {side} hand has no fingers beyond its knuckles (a hand joint misplaced?)"
        )
    k_across = (vertices[knuckles] - hand) @ lateral
    k_up = (vertices[knuckles] - hand) @ normal
    mid = 0.5 * (k_up.max() + k_up.min())
    found = {}
    for name, extreme in (("index", across[fingers].max()), ("pinky", across[fingers].min())):
        found[f"{side}_{name}"] = int(knuckles[np.argmin(np.hypot(k_across - extreme, k_up - mid))])
    found[f"{side}_thumb"] = int(region[np.argmax(across)])
    return found


@dataclass(frozen=True)
class PointSpec:
    """Where a fitted point lives on the body: an SMPL joint, or a named surface landmark."""

    name: str
    joint: int | None = None
    landmark: str | None = None

    def __post_init__(self):
        if (self.joint is None) == (self.landmark is None):
            raise ValueError(f"point {self.name!r} needs exactly one of joint / landmark")
        if self.landmark is not None and self.landmark not in LANDMARK_NAMES:
            raise ValueError(f"unknown landmark {self.landmark!r}; known: {LANDMARK_NAMES}")


class BodyKeypoints(torch.nn.Module):
    """``forward(betas, body_pose, Rh, Th) -> (B, P, 3)`` positions of ``points`` on the body.

    ``body_pose`` is (B, 23, 3) axis-angle for joints 1..23 (SMPL's root rotation is kept at zero;
    the global rotation is ``Rh``). ``betas`` is (B, S) or (S,).
    """

    def __init__(self, body: BodyModel, points: list[PointSpec], offsets: dict | None = None):
        """``offsets``: point name -> (carrier joint index, (3,) metres in that joint's rest axes):
        the point is moved by the offset turned with the carrier joint (a detector's "hip" sits
        a few centimetres from SMPL's hip joint: keypoint_offsets.py). Default: none."""
        super().__init__()
        if not points:
            raise ValueError("BodyKeypoints needs at least one point")
        self.points = list(points)
        self.num_betas = int(body.num_betas)
        with torch.no_grad():
            regressor = body.J_regressor.double()
            template = body.v_template.double()
            shapedirs = body.shapedirs.double()
            rest_joints = (regressor @ template).numpy()
            weights = body.weights.double().numpy()
            landmark_index = surface_landmarks(template.numpy(), weights, rest_joints)
            self.landmark_vertices = landmark_index
            used = sorted({p.landmark for p in points if p.landmark is not None})
            vertex_ids = torch.as_tensor([landmark_index[name] for name in used], dtype=torch.long)
            dtype = torch.float64
            self.register_buffer("joint_template", regressor @ template)
            self.register_buffer("joint_shapedirs", torch.einsum("jv,vcs->jcs", regressor, shapedirs))
            self.register_buffer("landmark_template", template[vertex_ids].to(dtype))
            self.register_buffer("landmark_shapedirs", shapedirs[vertex_ids].to(dtype))
            self.register_buffer("landmark_weights", body.weights.double()[vertex_ids])
        self.parents = body.parents.clone()
        slot = {name: i for i, name in enumerate(used)}
        # Gather index into [joints (24) | landmarks (L)].
        index = [p.joint if p.joint is not None else 24 + slot[p.landmark] for p in points]
        self.register_buffer("gather_index", torch.as_tensor(index, dtype=torch.long))
        self.has_landmarks = bool(used)
        offsets = {
            name: value for name, value in (offsets or {}).items() if any(p.name == name for p in points)
        }
        carriers = [offsets[p.name][0] if p.name in offsets else 0 for p in points]
        vectors = [offsets[p.name][1] if p.name in offsets else (0.0, 0.0, 0.0) for p in points]
        self.register_buffer("offset_carrier", torch.as_tensor(carriers, dtype=torch.long))
        self.register_buffer(
            "offset_vector", torch.as_tensor(np.asarray(vectors, np.float64), dtype=torch.float64)
        )
        self.has_offsets = bool(offsets)

    def rest_joints(self, betas: torch.Tensor) -> torch.Tensor:
        """(B, 24, 3) shaped rest joints."""
        return self.joint_template + torch.einsum("jcs,bs->bjc", self.joint_shapedirs, betas)

    def local_points(self, betas: torch.Tensor, rotations: torch.Tensor) -> torch.Tensor:
        """(B, P, 3) points in model space (before Rh, Th) from (B, 24, 3, 3) local joint rotations."""
        dtype = self.joint_template.dtype
        batch = rotations.shape[0]
        betas = betas.to(dtype).reshape(-1, self.num_betas).expand(batch, -1)
        joints, bone_transforms = lbs.rigid_chain(rotations.to(dtype), self.rest_joints(betas), self.parents)
        if not self.has_landmarks:
            points = joints[:, self.gather_index]
        else:
            rest_points = self.landmark_template + torch.einsum("lcs,bs->blc", self.landmark_shapedirs, betas)
            landmarks = lbs.skin_points(rest_points, self.landmark_weights, bone_transforms)
            points = torch.cat([joints, landmarks], dim=1)[:, self.gather_index]
        if self.has_offsets:
            carrier_rotation = bone_transforms[:, self.offset_carrier, :3, :3]  # (B, P, 3, 3)
            points = points + (carrier_rotation @ self.offset_vector.to(dtype)[None, :, :, None]).squeeze(-1)
        return points

    def forward(
        self, betas: torch.Tensor, body_pose: torch.Tensor, Rh: torch.Tensor, Th: torch.Tensor
    ) -> torch.Tensor:
        dtype = self.joint_template.dtype
        batch = body_pose.shape[0]
        pose = torch.cat([body_pose.new_zeros(batch, 1, 3), body_pose.reshape(batch, 23, 3)], dim=1)
        local = self.local_points(betas, lbs.axis_angle_to_matrix(pose.to(dtype)))
        rotation = lbs.axis_angle_to_matrix(Rh.to(dtype).reshape(batch, 3))
        return local @ rotation.transpose(1, 2) + Th.to(dtype).reshape(batch, 1, 3)
