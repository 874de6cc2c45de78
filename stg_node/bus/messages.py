"""The typed messages of the bus, one class per proto/*.yaml schema.

Each class is a keyword-only dataclass whose fields carry their wire spec (kind or dtype,
shape, unit, bounds); :func:`message` turns them into a :class:`MessageSpec` the codec
enforces, and tests/test_bus_proto.py checks every class against its proto/ file.
Arrays hold numpy arrays; after decoding they are read-only views of the received
ZeroMQ frames (no copies): copy one before writing to it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from stg_node.bus.spec import (
    ArraySetSpec,
    ArraySpec,
    DimSpec,
    MessageError,
    MessageSpec,
    ScalarSpec,
)

if TYPE_CHECKING:
    from stg_node.body.params import SmplParams

#: type name -> message class, filled by :func:`message`.
REGISTRY: dict[str, type[Message]] = {}
#: standard topic name -> message class.
TOPIC_TYPES: dict[str, type[Message]] = {}

_REQUIRED = object()


@dataclass(slots=True)
class Header:
    """The envelope of a received (or to-be-sent) message. ``stamp_ns`` 0 means 'now' when
    publishing; ``seq``, ``src`` and ``topic`` are filled in by the publisher / decoder."""

    stamp_ns: int = 0
    seq: int = -1
    src: str = ""
    topic: str = ""


@dataclass(kw_only=True, eq=False, repr=False)
class Message:
    """Base of all typed messages."""

    SPEC: ClassVar[MessageSpec]
    header: Header = field(default_factory=Header)

    def check(self) -> None:
        """Cross-field rules beyond types and shapes; raise MessageError('field', ...)."""

    def __repr__(self) -> str:
        parts = []
        for f in dataclasses.fields(self):
            if f.name == "header":
                continue
            value = getattr(self, f.name)
            if isinstance(value, np.ndarray):
                parts.append(f"{f.name}={value.dtype}{list(value.shape)}")
            elif isinstance(value, dict) and value and isinstance(next(iter(value.values())), np.ndarray):
                inner = ", ".join(f"{k}={v.dtype}{list(v.shape)}" for k, v in value.items())
                parts.append(f"{f.name}={{{inner}}}")
            else:
                parts.append(f"{f.name}={value!r}")
        return f"{type(self).__name__}({', '.join(parts)})"


def scalar(
    kind: str,
    default=_REQUIRED,
    *,
    unit: str = "",
    doc: str = "",
    min=None,
    max=None,
    choices=None,
    finite: bool = True,
):
    """A scalar header field. Without ``default`` it is required."""
    spec = ScalarSpec(
        kind=kind,
        default=None if default is _REQUIRED else default,
        required=default is _REQUIRED,
        min=min,
        max=max,
        choices=tuple(choices) if choices else None,
        finite=finite,
        unit=unit,
        doc=doc,
    )
    meta = {"scalar": spec}
    if default is _REQUIRED:
        return field(metadata=meta)
    if isinstance(default, dict):
        return field(default_factory=lambda: dict(default), metadata=meta)
    return field(default=default, metadata=meta)


def array(dtype: str, shape, *, required: bool = True, finite: bool = True, unit: str = "", doc: str = ""):
    """An array field (one buffer on the wire). Optional arrays default to None."""
    spec = ArraySpec(dtype=dtype, shape=tuple(shape), required=required, finite=finite, unit=unit, doc=doc)
    if required:
        return field(metadata={"array": spec})
    return field(default=None, metadata={"array": spec})


def array_set(dtypes, *, max_count: int, max_ndim: int, max_dim: int, name_pattern: str, doc: str = ""):
    spec = ArraySetSpec(
        dtypes=tuple(dtypes),
        max_count=max_count,
        max_ndim=max_ndim,
        max_dim=max_dim,
        name_pattern=name_pattern,
        doc=doc,
    )
    return field(default_factory=dict, metadata={"array_set": spec})


def message(*, type: str, version: int, topic: str, lane: str, max_bytes: int, dims=None, latched=False):
    """Class decorator: make a keyword-only dataclass, build its MessageSpec, register it."""

    def wrap(cls):
        cls = dataclass(kw_only=True, eq=False, repr=False)(cls)
        scalars, arrays, aset = [], [], None
        for f in dataclasses.fields(cls):
            meta = f.metadata
            if "scalar" in meta:
                scalars.append(dataclasses.replace(meta["scalar"], name=f.name))
            elif "array" in meta:
                arrays.append(dataclasses.replace(meta["array"], name=f.name))
            elif "array_set" in meta:
                aset = dataclasses.replace(meta["array_set"], name=f.name)
        cls.SPEC = MessageSpec(
            type=type,
            version=version,
            topic=topic,
            lane=lane,
            latched=latched,
            max_bytes=max_bytes,
            dims={k: DimSpec(*v) for k, v in (dims or {}).items()},
            scalars=tuple(scalars),
            arrays=tuple(arrays),
            array_set=aset,
            doc=(cls.__doc__ or "").strip(),
        )
        if type in REGISTRY or topic in TOPIC_TYPES:
            raise ValueError(f"message type {type!r} or topic {topic!r} registered twice")
        REGISTRY[type] = cls
        TOPIC_TYPES[topic] = cls
        return cls

    return wrap


MiB = 1 << 20
MAX_GAUSSIANS = 1 << 21  # 2,097,152: 4x headroom over the 500k an avatar typically reaches

# --- the messages -----------------------------------------------------------------------------


@message(
    type="Frame",
    version=1,
    topic="camera/frame",
    lane="latest",
    max_bytes=160 * MiB,
    dims={"H": (1, 4096, "image height, pixels"), "W": (1, 4096, "image width, pixels")},
)
class Frame(Message):
    """One calibrated camera image (ingest -> tracker, trainer)."""

    index: int = scalar("int", min=0, unit="1", doc="frame index within the sequence")
    time: float = scalar("float", 0.0, unit="s", doc="time since the first frame of the sequence")
    camera_id: str = scalar("str", "", doc="camera name within the rig")
    image: np.ndarray = array("uint8", ("H", "W", 3), unit="RGB 0-255", doc="RGB image")
    K: np.ndarray = array("float64", (3, 3), unit="px", doc="pinhole intrinsics of this image")
    R: np.ndarray = array("float64", (3, 3), unit="1", doc="rotation world -> camera (OpenCV axes)")
    t: np.ndarray = array("float64", (3,), unit="m", doc="translation world -> camera")
    mask: np.ndarray | None = array(
        "uint8", ("H", "W"), required=False, unit="0/255", doc="person mask, 255 on the person"
    )
    depth: np.ndarray | None = array(
        "float32",
        ("H", "W"),
        required=False,
        finite=False,
        unit="m",
        doc="depth along the optical axis; 0 or NaN = no measurement",
    )


@message(
    type="BodyPose",
    version=1,
    topic="body/pose",
    lane="reliable",
    max_bytes=64 * 1024,
    dims={"B": (1, 300, "number of shape coefficients")},
)
class BodyPose(Message):
    """SMPL body parameters of one frame (tracker -> trainer, renderer)."""

    frame_seq: int = scalar(
        "int",
        -1,
        min=-1,
        unit="1",
        doc="seq of the camera/frame message this pose was estimated from; -1 if none",
    )
    frame_index: int = scalar("int", -1, min=-1, unit="1", doc="Frame.index of that frame; -1 if none")
    time: float = scalar("float", 0.0, unit="s", doc="time since the first frame of the sequence")
    confidence: float = scalar("float", 1.0, min=0.0, max=1.0, unit="1", doc="tracker confidence")
    poses: np.ndarray = array("float32", (24, 3), unit="rad", doc="per-joint axis-angle, SMPL joint order")
    Rh: np.ndarray = array("float32", (3,), unit="rad", doc="global rotation, axis-angle")
    Th: np.ndarray = array("float32", (3,), unit="m", doc="global translation")
    betas: np.ndarray = array("float32", ("B",), unit="1", doc="SMPL shape coefficients")
    joints: np.ndarray | None = array(
        "float32", (24, 3), required=False, unit="m", doc="posed joint positions in world coordinates"
    )

    # The one conversion between the bus and stg_node.body.params.SmplParams (imported on use:
    # a bus-only process never loads it). Both directions copy nothing and change no value.
    @classmethod
    def from_smpl(cls, params: SmplParams, **fields) -> BodyPose:
        """A BodyPose carrying ``params`` (an SMPL :class:`~stg_node.body.params.SmplParams`);
        ``fields`` sets the rest (``frame_seq``, ``frame_index``, ``time``, ``confidence``, ``joints``).

        The wire has no body-model tag, so parameters of another model (THuman4.0's SMPL-X fits,
        ``model="smplx"``) are refused rather than passed on as SMPL's; the sender converts them
        (``stg_node.body.smplx_as_smpl``, as the tracker node's replay does).
        """
        from stg_node.body.params import SmplParams

        if not isinstance(params, SmplParams):
            raise TypeError(f"BodyPose.from_smpl takes SmplParams, got {type(params).__name__}")
        if params.model != "smpl":
            raise ValueError(
                f"BodyPose carries SMPL parameters; these are {params.model!r} parameters, whose betas "
                "mean something else (stg_node.body.smplx_as_smpl gives the nearest SMPL ones)"
            )
        return cls(poses=params.poses, Rh=params.Rh, Th=params.Th, betas=params.betas, **fields)

    def to_smpl(self) -> SmplParams:
        """This pose as :class:`~stg_node.body.params.SmplParams` (``model="smpl"``), checked on the way.

        The arrays are the message's own (read-only views of the received frames): copy one
        before writing to it."""
        from stg_node.body.params import SmplParams

        return SmplParams(poses=self.poses, Rh=self.Rh, Th=self.Th, betas=self.betas)


@message(
    type="GaussianSnapshot",
    version=1,
    topic="avatar/snapshot",
    lane="bulk",
    latched=True,
    max_bytes=1024 * MiB,
)
class GaussianSnapshot(Message):
    """A complete, versioned avatar model (trainer -> renderer), latched by the broker.

    Generic on purpose: a named set of float arrays (the canonical Gaussian table including
    its spacetime parameters, the colour MLP's weights, ...) whose meaning ``format`` names,
    so that a renderer can render any pose and time from this message alone.
    """

    format: str = scalar("str", doc="layout of the arrays, e.g. 'stg-avatar/1'")
    model_version: int = scalar("int", min=0, unit="1", doc="increases with every published model")
    iteration: int = scalar("int", 0, min=0, unit="1", doc="trainer iteration the model comes from")
    num_gaussians: int = scalar("int", min=0, max=MAX_GAUSSIANS, unit="1", doc="rows of per-Gaussian arrays")
    meta: dict = scalar("map[str,float]", {}, doc="numeric model settings (e.g. sh_degree, t_min, t_max)")
    arrays: dict = array_set(
        ("float32", "float16"),
        max_count=128,
        max_ndim=4,
        max_dim=MAX_GAUSSIANS,
        name_pattern=r"[A-Za-z_][A-Za-z0-9_.:\-]{0,127}",
        doc="the model's parameters by name; per-Gaussian arrays have num_gaussians rows",
    )


@message(type="ViewRequest", version=1, topic="avatar/view", lane="reliable", max_bytes=64 * 1024)
class ViewRequest(Message):
    """A camera (and optionally a pose) the robot wants the avatar rendered from."""

    request_id: int = scalar("int", 0, min=0, unit="1", doc="echoed in RenderedImage.request_id")
    width: int = scalar("int", min=1, max=4096, unit="px", doc="image width")
    height: int = scalar("int", min=1, max=4096, unit="px", doc="image height")
    follow_live: bool = scalar(
        "bool", True, doc="true: render the latest body/pose, continuously; false: the pose given here"
    )
    time: float = scalar("float", -1.0, unit="s", doc="sequence time for spacetime terms; < 0 = live")
    near: float = scalar("float", 0.01, min=0.0, unit="m", doc="near clipping distance")
    far: float = scalar("float", 100.0, min=0.0, unit="m", doc="far clipping distance")
    K: np.ndarray = array("float64", (3, 3), unit="px", doc="intrinsics of the wanted image")
    R: np.ndarray = array("float64", (3, 3), unit="1", doc="rotation world -> camera (OpenCV axes)")
    t: np.ndarray = array("float64", (3,), unit="m", doc="translation world -> camera")
    poses: np.ndarray | None = array(
        "float32", (24, 3), required=False, unit="rad", doc="body pose to render when follow_live is false"
    )
    Rh: np.ndarray | None = array("float32", (3,), required=False, unit="rad", doc="global rotation")
    Th: np.ndarray | None = array("float32", (3,), required=False, unit="m", doc="global translation")

    def check(self) -> None:
        if not self.follow_live and self.poses is None:
            raise MessageError("field", "ViewRequest.poses is required when follow_live is false")
        if self.far <= self.near:
            raise MessageError("field", f"ViewRequest.far={self.far} must exceed near={self.near}")


@message(
    type="RenderedImage",
    version=1,
    topic="avatar/image",
    lane="latest",
    max_bytes=160 * MiB,
    dims={"H": (1, 4096, "image height, pixels"), "W": (1, 4096, "image width, pixels")},
)
class RenderedImage(Message):
    """The avatar rendered for a view (renderer -> robot)."""

    request_id: int = scalar("int", -1, min=-1, unit="1", doc="ViewRequest.request_id served; -1 = live view")
    request_src: str = scalar("str", "", doc="src of the ViewRequest served")
    pose_seq: int = scalar(
        "int", -1, min=-1, unit="1", doc="seq of the body/pose used; -1 = pose from request"
    )
    snapshot_version: int = scalar("int", -1, min=-1, unit="1", doc="GaussianSnapshot.model_version used")
    source_stamp_ns: int = scalar("int", 0, min=0, unit="ns", doc="stamp_ns of the pose or request rendered")
    render_ms: float = scalar("float", 0.0, min=0.0, unit="ms", doc="rasterization time")
    latency_ms: float = scalar("float", 0.0, unit="ms", doc="source_stamp_ns to publication")
    image: np.ndarray = array("uint8", ("H", "W", 3), unit="RGB 0-255", doc="rendered RGB image")
    K: np.ndarray = array("float64", (3, 3), unit="px", doc="intrinsics the image was rendered with")
    R: np.ndarray = array("float64", (3, 3), unit="1", doc="rotation world -> camera")
    t: np.ndarray = array("float64", (3,), unit="m", doc="translation world -> camera")
    alpha: np.ndarray | None = array(
        "uint8", ("H", "W"), required=False, unit="0-255", doc="accumulated opacity"
    )
    depth: np.ndarray | None = array(
        "float32",
        ("H", "W"),
        required=False,
        finite=False,
        unit="m",
        doc="expected depth; 0 where alpha is 0",
    )


@message(type="TrainerMetrics", version=1, topic="trainer/metrics", lane="reliable", max_bytes=0)
class TrainerMetrics(Message):
    """Progress of the online trainer."""

    iteration: int = scalar("int", min=0, unit="1", doc="optimisation step")
    model_version: int = scalar(
        "int", 0, min=0, unit="1", doc="last GaussianSnapshot.model_version published"
    )
    num_gaussians: int = scalar("int", 0, min=0, unit="1", doc="Gaussians in the model now")
    loss: float = scalar("float", finite=False, unit="1", doc="total loss of this step (NaN if it diverged)")
    losses: dict = scalar("map[str,float]", {}, finite=False, doc="loss terms by name (l1, ssim, flow, ...)")
    psnr: float = scalar(
        "float", float("nan"), finite=False, unit="dB", doc="training-view PSNR; NaN if not computed"
    )
    it_per_s: float = scalar("float", 0.0, min=0.0, unit="1/s", doc="iterations per second")
    elapsed_s: float = scalar("float", 0.0, min=0.0, unit="s", doc="training time so far")
    extra: dict = scalar("map[str,float]", {}, finite=False, doc="anything else (learning rates, ...)")


NODE_STATES = ("starting", "running", "degraded", "stopping", "error")


@message(type="NodeStatus", version=1, topic="node/status", lane="reliable", max_bytes=0)
class NodeStatus(Message):
    """Heartbeat of a node (or the broker): liveness, traffic, drops and errors."""

    node: str = scalar("str", doc="node id (the src of its messages)")
    state: str = scalar("str", "running", choices=NODE_STATES, doc="life-cycle state")
    pid: int = scalar("int", 0, min=0, unit="1", doc="process id")
    host: str = scalar("str", "", doc="host name")
    uptime_s: float = scalar("float", 0.0, min=0.0, unit="s", doc="time since the node started")
    period_s: float = scalar(
        "float", 1.0, min=0.0, unit="s", doc="heartbeat period; silent for 3 periods = presumed dead"
    )
    published: dict = scalar("map[str,int]", {}, doc="messages published per topic, since start")
    received: dict = scalar("map[str,int]", {}, doc="messages received per topic, since start")
    rates_hz: dict = scalar(
        "map[str,float]", {}, unit="1/s", doc="messages per second per topic, last period"
    )
    bytes_per_s: dict = scalar("map[str,float]", {}, unit="B/s", doc="payload bytes per second per topic")
    drops: dict = scalar("map[str,int]", {}, doc="messages dropped per reason (see envelope drop_reasons)")
    errors: int = scalar("int", 0, min=0, unit="1", doc="errors since start")
    last_error: str = scalar("str", "", doc="the latest error, one line")


@message(type="Ack", version=1, topic="node/ack", lane="reliable", max_bytes=0)
class Ack(Message):
    """A consumer's acknowledgement that it has consumed one message (lockstep playback)."""

    msg_topic: str = scalar("str", doc="full topic of the message consumed")
    msg_seq: int = scalar("int", min=0, unit="1", doc="header seq of the message consumed")
    msg_src: str = scalar("str", doc="header src of the message consumed")
