"""Bus messages in Foxglove's own schemas: the one home for the conversions that
``stg-bag export --foxglove`` (a recording -> MCAP view channels) and the live ``foxglove`` node
(the bus -> Foxglove WebSocket) share, so a live session and its exported recording show the
same channels, under the same names, in the same schemas.

The messages are foxglove-sdk's (``foxglove.messages``): each carries its protobuf schema
(``get_schema()``, a FileDescriptorSet) and encodes itself (``encode()``). The export writes
those bytes and schemas into MCAP; the live node logs the same objects on SDK channels.

| from | view channel | Foxglove schema |
|---|---|---|
| ``image`` (Frame, RenderedImage) | ``view/<topic>/image`` | foxglove.CompressedImage (jpeg, png) or |
| | | foxglove.RawImage (rgb8, ``raw``) |
| ``mask``, ``alpha`` | ``view/<topic>/mask``, ``view/<topic>/alpha`` | foxglove.RawImage (mono8) |
| ``K`` (+ image size) | ``view/<topic>/calibration`` | foxglove.CameraCalibration |
| ``R``, ``t`` | ``view/<topic>/tf`` | foxglove.FrameTransform ``world`` -> ``<topic>/camera`` |
| ``Rh``, ``Th`` (BodyPose) | ``view/<topic>/root`` | foxglove.PoseInFrame in ``world`` |
| ``joints`` (BodyPose) | ``view/<topic>/joints`` | foxglove.PosesInFrame in ``world`` |
| ``joints`` (BodyPose) | ``view/<topic>/skeleton`` | foxglove.SceneUpdate in ``world`` (joints and bones) |
| Gaussian centres + colours | ``view/<topic>/cloud`` | foxglove.PointCloud in ``world`` (x, y, z float32; |
| | | red, green, blue, alpha uint8) |
| scalar fields (every type) | ``view/<topic>/fields`` | JSON (a JSON Schema from proto/), for plots |

``joints`` is optional in BodyPose; the live node fills it by forward kinematics before calling
:func:`message_views`, and the point cloud needs the avatar posed (nodes/live_scene.py), so
both come from the node's side; everything here is numpy, OpenCV (JPEG/PNG, imported on use)
and the SDK's message classes: the bus still imports no torch.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from stg_node.bus.messages import REGISTRY

WORLD_FRAME = "world"
IMAGE_FORMATS = ("jpeg", "png", "raw")
#: Joint and bone colours of the skeleton (RGBA 0-1): joints white, bones orange.
JOINT_COLOR = (1.0, 1.0, 1.0, 1.0)
BONE_COLOR = (1.0, 0.55, 0.1, 1.0)
JOINT_SIZE_M = 0.04
BONE_THICKNESS_PX = 3.0
#: PointCloud layout: x, y, z float32 then red, green, blue, alpha uint8 -> 16 bytes per point.
POINT_DTYPE = np.dtype(
    [
        ("x", "<f4"),
        ("y", "<f4"),
        ("z", "<f4"),
        ("red", "u1"),
        ("green", "u1"),
        ("blue", "u1"),
        ("alpha", "u1"),
    ]
)

_JSON_KINDS = {
    "int": {"type": "integer"},
    "float": {"type": ["number", "null"]},  # NaN/Inf become null: JSON has no non-finite numbers
    "str": {"type": "string"},
    "bool": {"type": "boolean"},
    "map[str,float]": {"type": "object", "additionalProperties": {"type": ["number", "null"]}},
    "map[str,int]": {"type": "object", "additionalProperties": {"type": "integer"}},
}


def _fm():
    """foxglove.messages (imported on use: a bus process that never shows views never loads it)."""
    import foxglove.messages  # noqa: PLC0415

    return foxglove.messages


# --- small pieces ---------------------------------------------------------------------------------


def timestamp(stamp_ns: int):
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    return _fm().Timestamp(sec=sec, nsec=nsec)


def camera_frame_id(topic: str) -> str:
    """The coordinate frame of the camera of the messages on ``topic`` (their images live in it)."""
    return f"{topic}/camera"


def view_topic(topic: str, view: str) -> str:
    return f"view/{topic}/{view}"


def quaternion_xyzw(rotation: np.ndarray) -> tuple[float, float, float, float]:
    """Unit quaternion (x, y, z, w) of a 3x3 rotation matrix (Shepperd's method, float64)."""
    m = np.asarray(rotation, dtype=np.float64)
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    if trace > 0:
        s = 2.0 * math.sqrt(1.0 + trace)
        q = (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s
    norm = math.sqrt(sum(c * c for c in q))
    return tuple(float(c / norm) for c in q)


def _quaternion(rotation: np.ndarray):
    x, y, z, w = quaternion_xyzw(rotation)
    return _fm().Quaternion(x=x, y=y, z=z, w=w)


def _vector(v) -> object:
    x, y, z = (float(c) for c in v)
    return _fm().Vector3(x=x, y=y, z=z)


# --- images ---------------------------------------------------------------------------------------


class ImageEncodeError(RuntimeError):
    """OpenCV could not encode an image (says which format)."""


def encode_image(arr: np.ndarray, image_format: str = "jpeg", jpeg_quality: int = 90) -> bytes:
    """JPEG or PNG bytes of an (H, W, 3) RGB or (H, W) uint8 image (OpenCV, imported on use)."""
    import cv2  # noqa: PLC0415 (heavy; only views need it)

    if image_format not in ("jpeg", "png"):
        raise ValueError(f"image format {image_format!r} is not jpeg or png")
    arr = np.ascontiguousarray(arr)
    if arr.ndim == 3 and arr.shape[2] == 3:
        arr = cv2.cvtColor(arr, cv2.COLOR_RGB2BGR)
    elif arr.ndim == 3 and arr.shape[2] == 4:
        arr = cv2.cvtColor(arr, cv2.COLOR_RGBA2BGRA)
    params = [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)] if image_format == "jpeg" else []
    ok, encoded = cv2.imencode(".jpg" if image_format == "jpeg" else ".png", arr, params)
    if not ok:
        raise ImageEncodeError(f"OpenCV could not encode a {image_format} image of shape {list(arr.shape)}")
    return encoded.tobytes()


def compressed_image(arr: np.ndarray, stamp_ns: int, frame_id: str, image_format="jpeg", jpeg_quality=90):
    return _fm().CompressedImage(
        timestamp=timestamp(stamp_ns),
        frame_id=frame_id,
        data=encode_image(arr, image_format, jpeg_quality),
        format=image_format,
    )


def raw_image(arr: np.ndarray, stamp_ns: int, frame_id: str):
    """rgb8 for (H, W, 3), mono8 for (H, W)."""
    arr = np.ascontiguousarray(arr)
    channels = 1 if arr.ndim == 2 else 3
    return _fm().RawImage(
        timestamp=timestamp(stamp_ns),
        frame_id=frame_id,
        width=int(arr.shape[1]),
        height=int(arr.shape[0]),
        encoding="mono8" if channels == 1 else "rgb8",
        step=int(arr.shape[1] * channels),
        data=arr.tobytes(),
    )


# --- cameras and bodies ---------------------------------------------------------------------------


def camera_calibration(K: np.ndarray, width: int, height: int, stamp_ns: int, frame_id: str):
    """A pinhole camera without distortion (our images are undistorted)."""
    K = np.asarray(K, np.float64)
    return _fm().CameraCalibration(
        timestamp=timestamp(stamp_ns),
        frame_id=frame_id,
        width=int(width),
        height=int(height),
        distortion_model="plumb_bob",
        D=[0.0] * 5,
        K=[float(v) for v in K.reshape(-1)],
        R=[float(v) for v in np.eye(3).reshape(-1)],
        P=[float(v) for v in np.hstack([K, np.zeros((3, 1))]).reshape(-1)],
    )


def camera_transform(R: np.ndarray, t: np.ndarray, stamp_ns: int, frame_id: str, parent: str = WORLD_FRAME):
    """The camera's pose in ``parent``, from the world -> camera extrinsics ``R``, ``t`` (OpenCV axes)."""
    R = np.asarray(R, np.float64)
    center = -R.T @ np.asarray(t, np.float64)  # the camera centre in the world
    return _fm().FrameTransform(
        timestamp=timestamp(stamp_ns),
        parent_frame_id=parent,
        child_frame_id=frame_id,
        translation=_vector(center),
        rotation=_quaternion(R.T),  # camera -> world
    )


def root_pose(Rh: np.ndarray, Th: np.ndarray, stamp_ns: int):
    """The body's global rotation and translation (SMPL ``Rh``, ``Th``) as a pose in ``world``."""
    import cv2  # noqa: PLC0415

    fm = _fm()
    rotation, _ = cv2.Rodrigues(np.asarray(Rh, np.float64).reshape(3, 1))
    pose = fm.Pose(position=_vector(Th), orientation=_quaternion(rotation))
    return fm.PoseInFrame(timestamp=timestamp(stamp_ns), frame_id=WORLD_FRAME, pose=pose)


def joint_poses(joints: np.ndarray, stamp_ns: int):
    fm = _fm()
    poses = [fm.Pose(position=_vector(j), orientation=fm.Quaternion(w=1.0)) for j in np.asarray(joints)]
    return fm.PosesInFrame(timestamp=timestamp(stamp_ns), frame_id=WORLD_FRAME, poses=poses)


def smpl_parents() -> tuple[int, ...]:
    from stg_node.body.smpl_io import SMPL_PARENTS  # noqa: PLC0415 (numpy only)

    return SMPL_PARENTS


def skeleton_scene(joints: np.ndarray, stamp_ns: int, parents=None, entity_id: str = "body"):
    """A SceneUpdate drawing the body's joints (spheres) and bones (a line list) in ``world``;
    the entity replaces the previous one of the same id."""
    fm = _fm()
    joints = np.asarray(joints, np.float64)
    parents = smpl_parents() if parents is None else [int(p) for p in parents]
    if len(parents) != len(joints):
        raise ValueError(f"skeleton: {len(joints)} joints but {len(parents)} parents")
    points = []
    for child, parent in enumerate(parents):
        if parent >= 0:
            points += [
                fm.Point3(x=float(a), y=float(b), z=float(c)) for a, b, c in (joints[parent], joints[child])
            ]
    bones = fm.LinePrimitive(
        type=fm.LinePrimitiveLineType.LineList,
        thickness=BONE_THICKNESS_PX,
        scale_invariant=True,
        points=points,
        color=fm.Color(r=BONE_COLOR[0], g=BONE_COLOR[1], b=BONE_COLOR[2], a=BONE_COLOR[3]),
    )
    size = fm.Vector3(x=JOINT_SIZE_M, y=JOINT_SIZE_M, z=JOINT_SIZE_M)
    color = fm.Color(r=JOINT_COLOR[0], g=JOINT_COLOR[1], b=JOINT_COLOR[2], a=JOINT_COLOR[3])
    spheres = [
        fm.SpherePrimitive(
            pose=fm.Pose(position=_vector(j), orientation=fm.Quaternion(w=1.0)), size=size, color=color
        )
        for j in joints
    ]
    entity = fm.SceneEntity(
        timestamp=timestamp(stamp_ns), frame_id=WORLD_FRAME, id=entity_id, lines=[bones], spheres=spheres
    )
    return fm.SceneUpdate(entities=[entity])


def point_cloud(positions: np.ndarray, colors: np.ndarray, stamp_ns: int, alpha: np.ndarray | None = None):
    """A coloured PointCloud in ``world``: ``positions`` (N, 3) metres, ``colors`` (N, 3) uint8 RGB
    (or float 0-1), ``alpha`` (N,) uint8 or float 0-1 (default opaque)."""
    fm = _fm()
    positions = np.asarray(positions, np.float32).reshape(-1, 3)
    n = positions.shape[0]
    points = np.empty(n, POINT_DTYPE)
    points["x"], points["y"], points["z"] = positions[:, 0], positions[:, 1], positions[:, 2]
    rgb = _as_uint8(colors).reshape(n, 3)
    points["red"], points["green"], points["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    points["alpha"] = 255 if alpha is None else _as_uint8(alpha).reshape(n)
    types = fm.PackedElementFieldNumericType
    fields = [
        fm.PackedElementField(name=name, offset=POINT_DTYPE.fields[name][1], type=kind)
        for name, kind in (
            ("x", types.Float32),
            ("y", types.Float32),
            ("z", types.Float32),
            ("red", types.Uint8),
            ("green", types.Uint8),
            ("blue", types.Uint8),
            ("alpha", types.Uint8),
        )
    ]
    return fm.PointCloud(
        timestamp=timestamp(stamp_ns),
        frame_id=WORLD_FRAME,
        pose=fm.Pose(position=fm.Vector3(), orientation=fm.Quaternion(w=1.0)),
        point_stride=POINT_DTYPE.itemsize,
        fields=fields,
        data=points.tobytes(),
    )


def _as_uint8(values) -> np.ndarray:
    arr = np.asarray(values)
    if arr.dtype == np.uint8:
        return arr
    return np.clip(np.rint(arr.astype(np.float64) * 255.0), 0, 255).astype(np.uint8)


# --- JSON fields ----------------------------------------------------------------------------------


def fields_json_schema(type_name: str) -> dict:
    """A JSON Schema for the scalar fields of a message type (plus seq, stamp_ns, src)."""
    properties = {
        "seq": {"type": "integer"},
        "stamp_ns": {"type": "integer"},
        "src": {"type": "string"},
    }
    cls = REGISTRY.get(type_name)
    if cls is not None:
        for s in cls.SPEC.scalars:
            properties[s.name] = {**_JSON_KINDS.get(s.kind, {}), "description": s.doc}
    return {"title": f"stg.{type_name} fields", "type": "object", "properties": properties}


def json_safe(value):
    """``value`` with NaN/Inf as None and bytes as hex: what JSON can carry."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, bytes):
        return value.hex()
    if isinstance(value, np.generic):
        return json_safe(value.item())
    return value


def wire_parts(msg) -> tuple[dict, dict]:
    """A typed message as the (header, arrays) a receiver of its wire form sees: the envelope's
    seq, stamp_ns and src, its scalar fields, and its fixed arrays (an array set, a snapshot's
    model, is left out: no view shows it as is)."""
    spec = msg.SPEC
    h = msg.header
    header = {"type": spec.type, "v": spec.version, "seq": h.seq, "stamp_ns": h.stamp_ns, "src": h.src}
    for s in spec.scalars:
        header[s.name] = getattr(msg, s.name)
    arrays = {a.name: getattr(msg, a.name) for a in spec.arrays if getattr(msg, a.name) is not None}
    return header, arrays


def header_fields(header: dict) -> dict:
    """The scalar fields of a wire header (seq, stamp_ns, src and the message's own), JSON-safe."""
    return json_safe({k: v for k, v in header.items() if k not in ("type", "v", "arrays")})


# --- one message -> its views ---------------------------------------------------------------------


@dataclass(frozen=True)
class ViewKind:
    """A view channel's last name and the Foxglove message class it carries (None: JSON fields)."""

    name: str
    schema: str  # Foxglove schema name, or "json"


#: The views each message type can have (what the live node advertises before anything arrives).
TYPE_VIEWS: dict[str, tuple[ViewKind, ...]] = {
    "Frame": (
        ViewKind("image", "foxglove.CompressedImage"),
        ViewKind("mask", "foxglove.RawImage"),
        ViewKind("calibration", "foxglove.CameraCalibration"),
        ViewKind("tf", "foxglove.FrameTransform"),
        ViewKind("fields", "json"),
    ),
    "RenderedImage": (
        ViewKind("image", "foxglove.CompressedImage"),
        ViewKind("alpha", "foxglove.RawImage"),
        ViewKind("calibration", "foxglove.CameraCalibration"),
        ViewKind("tf", "foxglove.FrameTransform"),
        ViewKind("fields", "json"),
    ),
    "BodyPose": (
        ViewKind("root", "foxglove.PoseInFrame"),
        ViewKind("joints", "foxglove.PosesInFrame"),
        ViewKind("skeleton", "foxglove.SceneUpdate"),
        ViewKind("fields", "json"),
    ),
    "GaussianSnapshot": (ViewKind("cloud", "foxglove.PointCloud"), ViewKind("fields", "json")),
}


def type_views(type_name: str) -> tuple[ViewKind, ...]:
    return TYPE_VIEWS.get(type_name, (ViewKind("fields", "json"),))


def message_class(schema: str):
    """The foxglove.messages class of a Foxglove schema name ('foxglove.CompressedImage')."""
    return getattr(_fm(), schema.rpartition(".")[2])


def _everything(_view_topic: str) -> bool:
    return True


def message_views(
    topic: str,
    header: dict,
    arrays: dict,
    *,
    image_format: str = "jpeg",
    jpeg_quality: int = 90,
    wanted: Callable[[str], bool] = _everything,
) -> list[tuple[str, object]]:
    """[(view channel, Foxglove message or JSON bytes)] for one bus message (its full ``topic``,
    wire ``header`` and decoded ``arrays``). ``wanted(view channel)`` False skips a view before
    any work is done for it: the live node asks whether a client subscribed (a JPEG costs ms)."""
    if image_format not in IMAGE_FORMATS:
        raise ValueError(f"image format {image_format!r} is not one of {IMAGE_FORMATS}")
    stamp = int(header.get("stamp_ns", 0))
    camera = camera_frame_id(topic)
    views: list[tuple[str, object]] = []

    def want(name: str) -> str | None:
        channel = view_topic(topic, name)
        return channel if wanted(channel) else None

    image = arrays.get("image")
    is_rgb = image is not None and image.dtype == np.uint8 and image.ndim == 3 and image.shape[2] == 3
    if is_rgb and (channel := want("image")):
        if image_format == "raw":
            views.append((channel, raw_image(image, stamp, camera)))
        else:
            views.append((channel, compressed_image(image, stamp, camera, image_format, jpeg_quality)))
    for name in ("mask", "alpha"):
        plane = arrays.get(name)
        if plane is not None and plane.dtype == np.uint8 and plane.ndim == 2 and (channel := want(name)):
            views.append((channel, raw_image(plane, stamp, camera)))
    K, R, t = arrays.get("K"), arrays.get("R"), arrays.get("t")
    if K is not None and K.shape == (3, 3) and (channel := want("calibration")):
        height = header.get("height", image.shape[0] if image is not None else 0)
        width = header.get("width", image.shape[1] if image is not None else 0)
        views.append((channel, camera_calibration(K, width, height, stamp, camera)))
    if R is not None and t is not None and R.shape == (3, 3) and t.shape == (3,) and (channel := want("tf")):
        views.append((channel, camera_transform(R, t, stamp, camera)))
    Rh, Th = arrays.get("Rh"), arrays.get("Th")
    if (
        Rh is not None
        and Th is not None
        and Rh.shape == (3,)
        and Th.shape == (3,)
        and (channel := want("root"))
    ):
        views.append((channel, root_pose(Rh, Th, stamp)))
    joints = arrays.get("joints")
    if joints is not None and joints.ndim == 2 and joints.shape[1] == 3:
        if channel := want("joints"):
            views.append((channel, joint_poses(joints, stamp)))
        if joints.shape[0] == len(smpl_parents()) and (channel := want("skeleton")):
            views.append((channel, skeleton_scene(joints, stamp)))
    if channel := want("fields"):
        views.append((channel, json.dumps(header_fields(header)).encode()))
    return views


__all__ = [
    "IMAGE_FORMATS",
    "TYPE_VIEWS",
    "WORLD_FRAME",
    "ImageEncodeError",
    "ViewKind",
    "camera_calibration",
    "camera_frame_id",
    "camera_transform",
    "compressed_image",
    "encode_image",
    "fields_json_schema",
    "header_fields",
    "joint_poses",
    "json_safe",
    "message_class",
    "message_views",
    "point_cloud",
    "quaternion_xyzw",
    "raw_image",
    "root_pose",
    "skeleton_scene",
    "timestamp",
    "type_views",
    "view_topic",
    "wire_parts",
]
