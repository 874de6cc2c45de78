"""The stg-bus MCAP format: how one bus message becomes one MCAP message, and back.

The contract (proto/recording.md states it for other languages; docs/RECORDING.md for users):

- one MCAP channel per topic, ``message_encoding`` :data:`MESSAGE_ENCODING` (``stg-bus``);
- an MCAP message's ``data`` is the bus message's header bytes (one msgpack map) followed by
  its buffers concatenated in order: a reader unpacks one msgpack object and slices the
  rest by the header's ``arrays`` entries (dtype, shape);
- ``log_time`` = when the recorder received it, ``publish_time`` = the header's ``stamp_ns``,
  ``sequence`` = the header's ``seq`` (modulo 2**32: MCAP's field is 32-bit);
- a schema record per message type: name = the type, encoding :data:`SCHEMA_ENCODING`, data =
  the type's proto/ YAML file;
- metadata records :data:`META_RECORDING` (versions, bus, command), :data:`META_LAUNCH` (the
  launch file, when there is one) and :data:`META_END` (counts and drops, on a clean stop).

This module only converts; the writer and reader own files.
"""

from __future__ import annotations

import math
from pathlib import Path

import msgpack
import numpy as np

from stg_node.bus import Envelope, decode_envelope
from stg_node.bus.spec import MAX_HEADER_BYTES
from stg_node.safe_load import unpack_msgpack

MESSAGE_ENCODING = "stg-bus"
SCHEMA_ENCODING = "stg-proto-yaml"
PROFILE = "stg"
META_RECORDING = "stg.recording"
META_LAUNCH = "stg.launch"
META_END = "stg.recording.end"
#: MCAP's sequence field is a uint32; the header's seq is an int64.
SEQUENCE_MASK = 0xFFFF_FFFF


class RecordingError(ValueError):
    """A recording (file, message or option) that cannot be used; the text says where and why."""


def payload_parts(env: Envelope) -> list:
    """The exact bytes of a received message as [header, *buffers] (zero-copy views)."""
    if env.frames is not None:
        return list(env.frames[1:])
    raise RecordingError(f"message on {env.topic!r} has no frames to record (not a received envelope)")


def payload(env: Envelope) -> bytes:
    """The MCAP message data of a received message: header bytes + buffers, in order."""
    return b"".join(payload_parts(env))


def _array_nbytes(desc, index: int) -> int:
    if not isinstance(desc, dict):
        raise RecordingError(f"array descriptor {index} is not a map")
    try:
        dtype = np.dtype(desc["dtype"])
        shape = desc["shape"]
        if not isinstance(shape, list) or not all(isinstance(d, int) and d >= 0 for d in shape):
            raise ValueError(f"shape {shape!r}")
    except (KeyError, TypeError, ValueError) as exc:
        raise RecordingError(f"array descriptor {index} ({desc!r:.80}) is not valid: {exc}") from None
    return math.prod(shape) * dtype.itemsize


def split_payload(topic: str, data) -> list:
    """``[topic, header, *buffers]`` (memoryviews into ``data``, no copies) from MCAP message data.

    Raises RecordingError when the data is not one msgpack map followed by exactly the bytes
    its ``arrays`` entries describe.
    """
    view = memoryview(data)
    unpacker = msgpack.Unpacker(raw=False, max_buffer_size=MAX_HEADER_BYTES + 16)
    unpacker.feed(view[: MAX_HEADER_BYTES + 16])
    try:
        unpacker.skip()  # finds where the header ends
        head = unpacker.tell()
    except Exception as exc:  # OutOfData, FormatError, StackError, ...
        raise RecordingError(
            f"message on {topic!r}: data does not start with a msgpack header ({type(exc).__name__})"
        ) from None
    try:
        header = unpack_msgpack(view[:head])  # the one safe msgpack path (no extension types)
    except Exception as exc:
        raise RecordingError(f"message on {topic!r}: header refused: {exc}") from None
    if not isinstance(header, dict) or not isinstance(header.get("arrays"), list):
        raise RecordingError(f"message on {topic!r}: header is not a map with an 'arrays' list")
    frames = [topic.encode(), view[:head]]
    offset = head
    for index, desc in enumerate(header["arrays"]):
        nbytes = _array_nbytes(desc, index)
        frames.append(view[offset : offset + nbytes])
        offset += nbytes
    if offset != len(view):
        raise RecordingError(
            f"message on {topic!r}: {len(view) - head} bytes follow the header, its arrays describe "
            f"{offset - head}"
        )
    return frames


def envelope_of(topic: str, data) -> Envelope:
    """Split and check recorded data (:func:`split_payload`, then the bus's envelope checks)."""
    frames = split_payload(topic, data)
    try:
        return decode_envelope(frames)
    except ValueError as exc:
        raise RecordingError(f"message on {topic!r}: {exc}") from None


def split_path(path: str | Path, index: int) -> Path:
    """The name of file ``index`` of a split recording: ``session.mcap`` -> ``session_0003.mcap``."""
    path = Path(path)
    return path.with_name(f"{path.stem}_{index:04d}{path.suffix or '.mcap'}")
