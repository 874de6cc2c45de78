"""View channels for Foxglove: a copy of a recording that Foxglove can show, not just list.

    export_foxglove(BagReader("session.mcap"), "session.view.mcap")

Foxglove opens an stg-bus recording but sees each message as opaque bytes (it does not
know the ``stg-bus`` encoding). This export writes a new MCAP file holding the original
channels unchanged (so the file still plays back with ``stg-bag play``) plus, for each
message, view channels in Foxglove's own schemas (protobuf, from the
foxglove-schemas-protobuf package, each schema a FileDescriptorSet):

| from | view channel | Foxglove schema |
|---|---|---|
| ``image`` (Frame, RenderedImage) | ``view/<topic>/image`` | foxglove.CompressedImage (jpeg, png) or |
| | | foxglove.RawImage (rgb8, ``--image-format raw``) |
| ``mask``, ``alpha`` | ``view/<topic>/mask``, ``view/<topic>/alpha`` | foxglove.RawImage (mono8) |
| ``K`` (+ image size) | ``view/<topic>/calibration`` | foxglove.CameraCalibration |
| ``R``, ``t`` | ``view/<topic>/tf`` | foxglove.FrameTransform world -> ``<topic>/camera`` |
| ``Rh``, ``Th`` (BodyPose) | ``view/<topic>/root`` | foxglove.PoseInFrame in ``world`` |
| ``joints`` (BodyPose) | ``view/<topic>/joints`` | foxglove.PosesInFrame in ``world`` |
| scalar fields (every type) | ``view/<topic>/fields`` | JSON (a JSON Schema from proto/), for plots |

Why at export and not at record time: encoding views (JPEG of a 1080p frame: ~10 ms)
would cost the recorder CPU on the hot path and risk drops, and the recording stays
exactly what crossed the bus. Why protobuf for images: binary bytes (JSON would need
base64, a third larger and slow), and the schemas come from Foxglove's own package.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from stg_node.bus import REGISTRY
from stg_node.bus.recording.format import RecordingError
from stg_node.bus.recording.mcapfile import COMPRESSIONS, McapFile
from stg_node.bus.recording.reader import BagReader
from stg_node.progress import progress

IMAGE_FORMATS = ("jpeg", "png", "raw")
WORLD_FRAME = "world"
_JSON_KINDS = {
    "int": {"type": "integer"},
    "float": {"type": ["number", "null"]},  # NaN/Inf become null: JSON has no non-finite numbers
    "str": {"type": "string"},
    "bool": {"type": "boolean"},
    "map[str,float]": {"type": "object", "additionalProperties": {"type": ["number", "null"]}},
    "map[str,int]": {"type": "object", "additionalProperties": {"type": "integer"}},
}


@dataclass
class FoxgloveStats:
    messages: int = 0  # original messages copied
    views: dict[str, int] = field(default_factory=dict)  # view channel -> messages
    out: str = ""


def _descriptor_set(message_class) -> bytes:
    """The FileDescriptorSet of a protobuf message class (its file and every dependency, in order)."""
    from google.protobuf.descriptor_pb2 import FileDescriptorSet  # noqa: PLC0415

    fds = FileDescriptorSet()
    seen: set[str] = set()

    def add(file_descriptor) -> None:
        if file_descriptor.name in seen:
            return
        seen.add(file_descriptor.name)
        for dependency in file_descriptor.dependencies:
            add(dependency)
        file_descriptor.CopyToProto(fds.file.add())

    add(message_class.DESCRIPTOR.file)
    return fds.SerializeToString()


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


def _json_safe(value):
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    if isinstance(value, bytes):
        return value.hex()
    return value


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


class _Views:
    """Builds the view messages of one recorded message (protobuf objects or JSON bytes)."""

    def __init__(self, image_format: str, jpeg_quality: int):
        import cv2  # noqa: PLC0415 (heavy; only this export needs it)
        from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration  # noqa: PLC0415
        from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage  # noqa: PLC0415
        from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform  # noqa: PLC0415
        from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame  # noqa: PLC0415
        from foxglove_schemas_protobuf.PosesInFrame_pb2 import PosesInFrame  # noqa: PLC0415
        from foxglove_schemas_protobuf.RawImage_pb2 import RawImage  # noqa: PLC0415

        self.cv2 = cv2
        self.pb = {
            "CameraCalibration": CameraCalibration,
            "CompressedImage": CompressedImage,
            "FrameTransform": FrameTransform,
            "PoseInFrame": PoseInFrame,
            "PosesInFrame": PosesInFrame,
            "RawImage": RawImage,
        }
        self.image_format = image_format
        self.jpeg_quality = jpeg_quality

    @staticmethod
    def _stamp(msg, stamp_ns: int) -> None:
        msg.timestamp.seconds, msg.timestamp.nanos = divmod(int(stamp_ns), 1_000_000_000)

    def _image(self, arr: np.ndarray, stamp_ns: int, frame_id: str):
        if self.image_format == "raw" or arr.ndim == 2:
            msg = self.pb["RawImage"]()
            msg.width, msg.height = int(arr.shape[1]), int(arr.shape[0])
            msg.encoding = "mono8" if arr.ndim == 2 else "rgb8"
            msg.step = int(arr.shape[1] * (1 if arr.ndim == 2 else 3))
            msg.data = np.ascontiguousarray(arr).tobytes()
        else:
            cv2 = self.cv2
            bgr = cv2.cvtColor(np.ascontiguousarray(arr), cv2.COLOR_RGB2BGR)
            params = [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality] if self.image_format == "jpeg" else []
            ok, encoded = cv2.imencode(".jpg" if self.image_format == "jpeg" else ".png", bgr, params)
            if not ok:
                raise RecordingError(f"OpenCV could not encode a {self.image_format} image")
            msg = self.pb["CompressedImage"]()
            msg.format = self.image_format
            msg.data = encoded.tobytes()
        self._stamp(msg, stamp_ns)
        msg.frame_id = frame_id
        return msg

    def build(self, topic: str, header: dict, arrays: dict) -> list[tuple[str, object]]:
        """[(view channel, protobuf message or JSON bytes)] for one message."""
        stamp = header["stamp_ns"]
        camera = f"{topic}/camera"
        views: list[tuple[str, object]] = []
        image = arrays.get("image")
        if image is not None and image.dtype == np.uint8 and image.ndim == 3 and image.shape[2] == 3:
            views.append((f"view/{topic}/image", self._image(image, stamp, camera)))
        for name in ("mask", "alpha"):
            plane = arrays.get(name)
            if plane is not None and plane.dtype == np.uint8 and plane.ndim == 2:
                views.append((f"view/{topic}/{name}", self._image(plane, stamp, camera)))
        K, R, t = arrays.get("K"), arrays.get("R"), arrays.get("t")
        if K is not None and K.shape == (3, 3):
            height = header.get("height", image.shape[0] if image is not None else 0)
            width = header.get("width", image.shape[1] if image is not None else 0)
            cal = self.pb["CameraCalibration"]()
            self._stamp(cal, stamp)
            cal.frame_id = camera
            cal.width, cal.height = int(width), int(height)
            cal.distortion_model = "plumb_bob"
            cal.D.extend([0.0] * 5)
            cal.K.extend(float(v) for v in K.reshape(-1))
            cal.R.extend(float(v) for v in np.eye(3).reshape(-1))
            cal.P.extend(float(v) for v in np.hstack([K, np.zeros((3, 1))]).reshape(-1))
            views.append((f"view/{topic}/calibration", cal))
        if R is not None and t is not None and R.shape == (3, 3) and t.shape == (3,):
            tf = self.pb["FrameTransform"]()
            self._stamp(tf, stamp)
            tf.parent_frame_id, tf.child_frame_id = WORLD_FRAME, camera
            center = -R.T.astype(np.float64) @ t.astype(np.float64)  # camera centre in the world
            tf.translation.x, tf.translation.y, tf.translation.z = (float(v) for v in center)
            x, y, z, w = quaternion_xyzw(R.T)  # camera -> world rotation
            tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w = x, y, z, w
            views.append((f"view/{topic}/tf", tf))
        Rh, Th = arrays.get("Rh"), arrays.get("Th")
        if Rh is not None and Th is not None and Rh.shape == (3,) and Th.shape == (3,):
            pose = self.pb["PoseInFrame"]()
            self._stamp(pose, stamp)
            pose.frame_id = WORLD_FRAME
            pose.pose.position.x, pose.pose.position.y, pose.pose.position.z = (float(v) for v in Th)
            rotation, _ = self.cv2.Rodrigues(Rh.astype(np.float64).reshape(3, 1))
            o = pose.pose.orientation
            o.x, o.y, o.z, o.w = quaternion_xyzw(rotation)
            views.append((f"view/{topic}/root", pose))
        joints = arrays.get("joints")
        if joints is not None and joints.ndim == 2 and joints.shape[1] == 3:
            poses = self.pb["PosesInFrame"]()
            self._stamp(poses, stamp)
            poses.frame_id = WORLD_FRAME
            for joint in joints:
                p = poses.poses.add()
                p.position.x, p.position.y, p.position.z = (float(v) for v in joint)
                p.orientation.w = 1.0
            views.append((f"view/{topic}/joints", poses))
        fields = {k: v for k, v in header.items() if k not in ("type", "v", "arrays")}
        views.append((f"view/{topic}/fields", json.dumps(_json_safe(fields)).encode()))
        return views


def export_foxglove(
    reader: BagReader,
    out: str | Path,
    *,
    topics=None,
    image_format: str = "jpeg",
    jpeg_quality: int = 90,
    compression: str = "zstd",
    keep_original: bool = True,
    show_progress: bool = True,
) -> FoxgloveStats:
    """Write ``out``: the recording's messages (``keep_original``) plus Foxglove view channels."""
    from stg_node.bus.recording.format import MESSAGE_ENCODING, META_END, SCHEMA_ENCODING  # noqa: PLC0415
    from stg_node.bus.recording.schemas import schema_data  # noqa: PLC0415

    if image_format not in IMAGE_FORMATS:
        raise RecordingError(f"image format {image_format!r} is not one of {IMAGE_FORMATS}")
    if compression not in COMPRESSIONS:
        raise RecordingError(f"compression {compression!r} is not one of {list(COMPRESSIONS)}")
    try:
        views = _Views(image_format, jpeg_quality)
    except ImportError as exc:
        raise RecordingError(
            f"the Foxglove export needs foxglove-schemas-protobuf and protobuf ({exc})"
        ) from exc
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    stats = FoxgloveStats(out=str(out))
    types = reader.types()
    total = reader.message_count
    with open(out, "wb") as f:
        writer = McapFile(f, compression=compression)
        writer.start(profile="", library="stg_node stg-bag export --foxglove")
        schemas: dict[str, int] = {}
        channels: dict[str, int] = {}

        def schema_id(name: str, encoding: str, data: bytes) -> int:
            if name not in schemas:
                schemas[name] = writer.register_schema(name, encoding, data)
            return schemas[name]

        def channel(topic: str, encoding: str, sid: int, meta: dict | None = None) -> int:
            if topic not in channels:
                channels[topic] = writer.register_channel(topic, encoding, sid, meta or {})
            return channels[topic]

        for bag in reader.files:
            for name, meta in bag.metadata.items():
                if name != META_END:  # its counts describe the source file, not this one
                    writer.add_metadata(name, meta)
        with progress(total=total, desc="foxglove views", unit="msg", enabled=show_progress) as bar:
            for msg in reader.messages(topics):
                bar.update(1)
                env = msg.envelope()
                if keep_original:
                    type_name = types.get(msg.topic, env.type)
                    yaml_schema = schema_data(type_name)
                    sid = schema_id(type_name, SCHEMA_ENCODING, yaml_schema) if yaml_schema is not None else 0
                    cid = channel(msg.topic, MESSAGE_ENCODING, sid, {"type": type_name})
                    writer.add_message(cid, msg.log_time_ns, msg.publish_time_ns, msg.sequence, [msg.data])
                    stats.messages += 1
                for view_topic, view in views.build(env.topic, env.header, env.arrays):
                    if isinstance(view, bytes):
                        name = f"stg.{env.type}.fields"
                        sid = schemas.get(name) or schema_id(
                            name, "jsonschema", json.dumps(fields_json_schema(env.type)).encode()
                        )
                        cid = channel(view_topic, "json", sid)
                        data = view
                    else:
                        full_name = view.DESCRIPTOR.full_name
                        sid = schemas.get(full_name) or schema_id(
                            full_name, "protobuf", _descriptor_set(type(view))
                        )
                        cid = channel(view_topic, "protobuf", sid)
                        data = view.SerializeToString()
                    writer.add_message(cid, msg.log_time_ns, msg.publish_time_ns, msg.sequence, [data])
                    stats.views[view_topic] = stats.views.get(view_topic, 0) + 1
        writer.finish()
    return stats
