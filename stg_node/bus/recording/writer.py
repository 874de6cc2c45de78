"""BagWriter: bus messages into an MCAP file (or a split set of files), in the stg-bus format.

    with BagWriter("session.mcap", compression="zstd") as bag:
        bag.write(envelope, log_time_ns=time.time_ns())   # an Envelope received from the bus

Channels (one per topic) and schemas (one per message type, from proto/) are registered the
first time a file sees them. Messages go into chunks of ``chunk_size`` bytes (compressed per
chunk); a chunk reaches the disk when it is full and at least every ``flush_interval_s``
(call :meth:`maybe_flush`), so a writer killed with SIGKILL leaves a file whose complete
chunks read back (reader.py recovers them). A clean :meth:`close` writes the summary
(indexes, statistics) that makes the file seekable, and a :data:`META_END` metadata record.

Splitting: with ``split_size`` (bytes) or ``split_duration_s``, files are named
``session_0000.mcap``, ``session_0001.mcap``, ... (format.split_path); each is a complete
MCAP file with its own schemas, channels and metadata.
"""

from __future__ import annotations

import json
import logging
import os
import platform
import socket
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import stg_node
from stg_node.bus import BusConfig, Envelope, Message, decode_envelope, encode
from stg_node.bus.recording.format import (
    MESSAGE_ENCODING,
    META_END,
    META_LAUNCH,
    META_RECORDING,
    PROFILE,
    SCHEMA_ENCODING,
    SEQUENCE_MASK,
    RecordingError,
    payload_parts,
    split_path,
)
from stg_node.bus.recording.mcapfile import COMPRESSIONS, McapFile
from stg_node.bus.recording.schemas import schema_data

log = logging.getLogger(__name__)

MiB = 1 << 20
DEFAULT_CHUNK_SIZE = 4 * MiB
DEFAULT_FLUSH_INTERVAL_S = 1.0


def _package_version(name: str) -> str:
    try:
        return version(name)
    except PackageNotFoundError:
        return "unknown"


@dataclass
class TopicCounts:
    """Messages and payload bytes per topic, for one file or a whole recording."""

    messages: dict[str, int] = field(default_factory=dict)
    bytes: dict[str, int] = field(default_factory=dict)
    times: dict[str, list[int]] = field(default_factory=dict)  # [first, last] receive time, ns

    def add(self, topic: str, nbytes: int, log_time_ns: int) -> None:
        self.messages[topic] = self.messages.get(topic, 0) + 1
        self.bytes[topic] = self.bytes.get(topic, 0) + nbytes
        span = self.times.get(topic)
        if span is None:
            self.times[topic] = [log_time_ns, log_time_ns]
        else:
            span[0] = min(span[0], log_time_ns)
            span[1] = max(span[1], log_time_ns)

    @property
    def total_messages(self) -> int:
        return sum(self.messages.values())

    @property
    def total_bytes(self) -> int:
        return sum(self.bytes.values())


class BagWriter:
    """Writes received bus messages (Envelopes with their frames) to MCAP; see the module docstring.

    ``metadata``: extra key/value strings for the :data:`META_RECORDING` record (bus URL,
    command line, ...). ``launch_file``: a launch file stored whole in :data:`META_LAUNCH`.
    ``bus_config``: the bus the messages came from (its lane overrides name each channel's lane).
    ``end_info``: called when a file is finished (each split too); its entries (the recorder's
    drops so far) go into that file's :data:`META_END` record.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        compression: str = "none",
        chunk_size: int = DEFAULT_CHUNK_SIZE,
        split_size: int | None = None,
        split_duration_s: float | None = None,
        flush_interval_s: float = DEFAULT_FLUSH_INTERVAL_S,
        metadata: dict[str, str] | None = None,
        launch_file: str | Path | None = None,
        bus_config: BusConfig | None = None,
        end_info: Callable[[], dict[str, str]] | None = None,
    ):
        if compression not in COMPRESSIONS:
            raise RecordingError(f"compression {compression!r} is not one of {list(COMPRESSIONS)}")
        if chunk_size <= 0:
            raise RecordingError(f"chunk size must be > 0 bytes, got {chunk_size}")
        if split_size is not None and split_size <= 0:
            raise RecordingError(f"split size must be > 0 bytes, got {split_size}")
        if split_duration_s is not None and split_duration_s <= 0:
            raise RecordingError(f"split duration must be > 0 s, got {split_duration_s}")
        self.path = Path(path)
        self.bus_config = bus_config or BusConfig(url="inproc://stg-recording")
        self.compression = compression
        self.chunk_size = chunk_size
        self.split_size = split_size
        self.split_duration_ns = None if split_duration_s is None else int(split_duration_s * 1e9)
        self.flush_interval_s = flush_interval_s
        self.files: list[Path] = []
        self.counts = TopicCounts()  # the whole recording
        self._extra_metadata = {str(k): str(v) for k, v in (metadata or {}).items()}
        self._launch = self._read_launch(launch_file)
        self._end_info = end_info
        self._written_seq: dict[tuple[str, str], int] = {}  # write_message's numbering
        self._file = None
        self._mcap: McapFile | None = None
        self._closed = False
        self._open_next()

    @staticmethod
    def _read_launch(launch_file) -> dict[str, str] | None:
        if launch_file is None:
            return None
        path = Path(launch_file)
        try:
            text = path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise RecordingError(f"cannot read launch file {path}: {exc}") from exc
        return {"path": str(path.resolve()), "text": text}

    @property
    def splitting(self) -> bool:
        return self.split_size is not None or self.split_duration_ns is not None

    # -- files ------------------------------------------------------------------------------

    def _open_next(self) -> None:
        index = len(self.files)
        path = split_path(self.path, index) if self.splitting else self.path
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            self._file = open(path, "wb")  # noqa: SIM115 (closed in _close_file)
        except OSError as exc:
            raise RecordingError(f"cannot write {path}: {exc.strerror or exc}") from exc
        self.files.append(path)
        self._mcap = McapFile(self._file, chunk_size=self.chunk_size, compression=self.compression)
        library = f"stg_node/{stg_node.__version__} mcap-python/{_package_version('mcap')}"
        self._mcap.start(profile=PROFILE, library=library)
        self._channels: dict[str, int] = {}
        self._schemas: dict[str, int] = {}
        self._file_counts = TopicCounts()
        self._file_first_ns: int | None = None
        self._last_flush = time.monotonic()
        self._mcap.add_metadata(META_RECORDING, self._recording_metadata(index))
        if self._launch is not None:
            self._mcap.add_metadata(META_LAUNCH, self._launch)
        self._mcap.flush()

    def _recording_metadata(self, index: int) -> dict[str, str]:
        meta = {
            "format": f"{MESSAGE_ENCODING} (proto/recording.md)",
            "stg_node": stg_node.__version__,
            "mcap": _package_version("mcap"),
            "pyzmq": _package_version("pyzmq"),
            "msgpack": _package_version("msgpack"),
            "python": platform.python_version(),
            "host": socket.gethostname(),
            "pid": str(os.getpid()),
            "started_ns": str(time.time_ns()),
            "compression": self.compression,
            "split_index": str(index),
        }
        meta.update(self._extra_metadata)
        return meta

    def _close_file(self, end: dict[str, str]) -> None:
        if self._mcap is None:
            return
        meta = {
            "messages": str(self._file_counts.total_messages),
            "topic_messages": json.dumps(self._file_counts.messages, sort_keys=True),
            "topic_bytes": json.dumps(self._file_counts.bytes, sort_keys=True),
            "topic_times": json.dumps(self._file_counts.times, sort_keys=True),
            "finished_ns": str(time.time_ns()),
        }
        if self._end_info is not None:
            meta.update(self._end_info())
        meta.update(end)
        try:
            self._mcap.add_metadata(META_END, meta)
            self._mcap.finish()
        finally:
            self._mcap = None
            self._file.close()
            self._file = None

    def _maybe_split(self, log_time_ns: int) -> None:
        if not self.splitting or self._file_first_ns is None:
            return
        full = self.split_size is not None and self._file_counts.total_bytes >= self.split_size
        late = (
            self.split_duration_ns is not None and log_time_ns - self._file_first_ns >= self.split_duration_ns
        )
        if full or late:
            self._close_file({"split": "true"})
            self._open_next()

    # -- channels and schemas ------------------------------------------------------------------

    def _channel(self, env: Envelope) -> int:
        type_name = env.type
        schema_id = self._schemas.get(type_name)
        if schema_id is None:
            data = schema_data(type_name)
            if data is None:  # a type this package does not know: record it without a schema
                schema_id = 0
            else:
                schema_id = self._mcap.register_schema(type_name, SCHEMA_ENCODING, data)
            self._schemas[type_name] = schema_id
        lane = self.bus_config.lane_of(env.topic).name
        channel_id = self._mcap.register_channel(
            env.topic, MESSAGE_ENCODING, schema_id, {"type": type_name, "lane": lane}
        )
        self._channels[env.topic] = channel_id
        return channel_id

    # -- writing ---------------------------------------------------------------------------------

    def write(self, env: Envelope, log_time_ns: int) -> None:
        """Write one received message (an Envelope that holds its frames), received at ``log_time_ns``."""
        if self._mcap is None:
            raise RecordingError(f"write() on a closed recording ({self.path})")
        parts = payload_parts(env)
        self._maybe_split(log_time_ns)
        channel_id = self._channels.get(env.topic)
        if channel_id is None:
            channel_id = self._channel(env)
        header = env.header
        nbytes = self._mcap.add_message(
            channel_id, log_time_ns, header["stamp_ns"], header["seq"] & SEQUENCE_MASK, parts
        )
        self._file_counts.add(env.topic, nbytes, log_time_ns)
        self.counts.add(env.topic, nbytes, log_time_ns)
        if self._file_first_ns is None:
            self._file_first_ns = log_time_ns

    def write_frames(self, frames, log_time_ns: int) -> Envelope:
        """Check and write one message given as ``[topic, header, *buffers]``; returns its envelope."""
        try:
            env = decode_envelope(frames)
        except ValueError as exc:
            raise RecordingError(f"not a valid bus message: {exc}") from None
        self.write(env, log_time_ns)
        return env

    def write_message(
        self,
        msg: Message,
        log_time_ns: int,
        *,
        src: str,
        topic: str | None = None,
        stamp_ns: int | None = None,
    ) -> int:
        """Write a typed message as a publisher named ``src`` would have sent it on ``topic`` (default:
        its standard topic): numbered per (topic, src) from 0 as a Publisher numbers, stamped
        ``stamp_ns`` (default ``log_time_ns``). For sessions made offline (a synthetic regression
        session); returns the message's seq (also set in ``msg.header.seq``)."""
        topic = topic or msg.SPEC.topic
        seq = self._written_seq.get((topic, src), 0)
        frames = encode(
            msg, topic=topic, seq=seq, src=src, stamp_ns=log_time_ns if stamp_ns is None else stamp_ns
        )
        self.write_frames(frames, log_time_ns)
        self._written_seq[(topic, src)] = seq + 1
        msg.header.seq, msg.header.src, msg.header.topic = seq, src, topic
        msg.header.stamp_ns = log_time_ns if stamp_ns is None else stamp_ns
        return seq

    def maybe_flush(self, now: float | None = None) -> bool:
        """Write the chunk in progress to disk if ``flush_interval_s`` passed since the last flush."""
        now = time.monotonic() if now is None else now
        if self._mcap is None or now - self._last_flush < self.flush_interval_s:
            return False
        self.flush()
        return True

    def flush(self) -> None:
        if self._mcap is not None:
            self._mcap.flush()
            self._last_flush = time.monotonic()

    def close(self, end: dict[str, str] | None = None) -> None:
        """Finish the file (summary, indexes, :data:`META_END` with ``end``'s entries added)."""
        if self._closed:
            return
        self._closed = True
        self._close_file({"clean": "true", **(end or {})})

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


__all__ = ["COMPRESSIONS", "BagWriter", "TopicCounts"]
