"""BagReader: recordings (one file, a split set, a folder) back into bus messages, in time order.

    reader = BagReader("session.mcap")        # or a split set's base name, a folder, several paths
    for msg in reader.messages(topics=r"camera/"):
        frames = msg.frames()                  # [topic, header, *buffers]: the bytes that were sent
        env = msg.envelope()                   # checked, with numpy views of the arrays

A finished file is read through its summary (indexes: fast, seekable). A file whose writer
was killed has no summary: it is scanned record by record with the mcap package's record
parsers, up to the last complete chunk whose CRC checks out; :attr:`BagFile.truncated`
and :attr:`BagFile.problem` say so, and :attr:`BagFile.message_count` counts what was
recovered. Anything that is not an MCAP file raises :class:`RecordingError` naming the path.
"""

from __future__ import annotations

import heapq
import io
import json
import re
import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.reader import SeekingReader
from mcap.records import Channel, Chunk, Footer, Message, Metadata, Schema, Statistics
from mcap.stream_reader import breakup_chunk

from stg_node.bus import Envelope
from stg_node.bus.recording.format import META_END, RecordingError, envelope_of, split_path, split_payload

MAGIC = b"\x89MCAP0\r\n"
_RECORD_HEAD = struct.Struct("<BQ")


@dataclass(frozen=True, slots=True)
class RecordedMessage:
    """One recorded bus message: its topic, MCAP times and sequence, and its data (header + buffers)."""

    topic: str
    log_time_ns: int  # when the recorder received it
    publish_time_ns: int  # the header's stamp_ns
    sequence: int  # the header's seq modulo 2**32
    data: bytes

    def frames(self) -> list:
        """``[topic, header, *buffers]`` as memoryviews into :attr:`data` (exactly what was sent)."""
        return split_payload(self.topic, self.data)

    def envelope(self) -> Envelope:
        """The checked envelope: header dict and read-only numpy views of the arrays."""
        return envelope_of(self.topic, self.data)


@dataclass
class BagFile:
    """What one MCAP file holds, from its summary or, for a truncated file, from a scan."""

    path: Path
    size: int
    truncated: bool = False
    problem: str = ""  # why the file is truncated or damaged, and where
    readable_bytes: int = 0  # bytes up to the end of the last complete record
    channels: dict[int, Channel] = field(default_factory=dict)
    schemas: dict[int, Schema] = field(default_factory=dict)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    topic_messages: dict[str, int] = field(default_factory=dict)
    topic_bytes: dict[str, int] | None = None  # None until known (META_END or a scan)
    topic_times: dict[str, tuple[int, int]] | None = None  # first and last receive time per topic
    chunks: int = 0
    compressions: set[str] = field(default_factory=set)
    start_ns: int | None = None
    end_ns: int | None = None
    indexed: bool = False  # its summary was read and trusted: messages can be read through its index

    @property
    def message_count(self) -> int:
        return sum(self.topic_messages.values())

    def types(self) -> dict[str, str]:
        """topic -> message type (the channel's ``type`` metadata, else its schema's name)."""
        out = {}
        for channel in self.channels.values():
            schema = self.schemas.get(channel.schema_id)
            out[channel.topic] = channel.metadata.get("type") or (schema.name if schema else "?")
        return out


# --- opening -------------------------------------------------------------------------------------


def resolve_paths(paths) -> list[Path]:
    """Files of the recording(s) named by ``paths``: files, folders (their *.mcap), or the base
    name of a split set (``session.mcap`` -> ``session_0000.mcap``, ``session_0001.mcap``, ...)."""
    if isinstance(paths, (str, Path)):
        paths = [paths]
    out: list[Path] = []
    for item in paths:
        path = Path(item)
        if path.is_dir():
            found = sorted(path.glob("*.mcap"))
            if not found:
                raise RecordingError(f"folder {path} holds no .mcap files")
            out.extend(found)
        elif path.exists():
            out.append(path)
        elif split_path(path, 0).exists():
            index = 0
            while split_path(path, index).exists():
                out.append(split_path(path, index))
                index += 1
        else:
            raise RecordingError(f"no recording at {path} (nor a split set {split_path(path, 0).name}, ...)")
    if not out:
        raise RecordingError("no recording given")
    return out


def _read_metadata(record: Metadata, into: dict[str, dict[str, str]]) -> None:
    into.setdefault(record.name, {}).update(record.metadata)


def _apply_end_metadata(bag: BagFile) -> None:
    end = bag.metadata.get(META_END)
    if not end:
        return
    try:
        if "topic_bytes" in end:
            bag.topic_bytes = {str(k): int(v) for k, v in json.loads(end["topic_bytes"]).items()}
        if "topic_times" in end:
            bag.topic_times = {
                str(k): (int(a), int(b)) for k, (a, b) in json.loads(end["topic_times"]).items()
            }
    except (ValueError, TypeError, AttributeError):  # another writer's metadata: measure instead
        bag.topic_bytes = bag.topic_times = None


def open_bag_file(path: str | Path) -> BagFile:
    """Read a file's summary, or scan it when it has none (a recorder killed mid-session)."""
    path = Path(path)
    try:
        size = path.stat().st_size
        with open(path, "rb") as f:
            head = f.read(8)
            f.seek(max(0, size - 8))
            tail = f.read(8)
    except OSError as exc:
        raise RecordingError(f"cannot read {path}: {exc.strerror}") from exc
    if head != MAGIC:
        raise RecordingError(f"{path} is not an MCAP file (it does not start with the MCAP magic bytes)")
    bag = BagFile(path=path, size=size)
    if size >= 16 and tail == MAGIC and _read_summary(bag):
        return bag
    for _ in scan_records(bag, collect=True):
        pass
    return bag


def _read_summary(bag: BagFile) -> bool:
    """Fill ``bag`` from the file's summary; False when there is none to trust."""
    try:
        with open(bag.path, "rb") as f:
            reader = SeekingReader(f)
            summary = reader.get_summary()
            if summary is None or summary.statistics is None:
                return False
            metadata: dict[str, dict[str, str]] = {}
            for record in reader.iter_metadata():
                _read_metadata(record, metadata)
    except Exception:  # a damaged summary: fall back to scanning, which says what is wrong
        return False
    stats: Statistics = summary.statistics
    bag.channels = dict(summary.channels)
    bag.schemas = dict(summary.schemas)
    bag.metadata = metadata
    bag.readable_bytes = bag.size
    for channel_id, count in stats.channel_message_counts.items():
        channel = bag.channels.get(channel_id)
        if channel is not None and count:
            bag.topic_messages[channel.topic] = bag.topic_messages.get(channel.topic, 0) + count
    bag.chunks = stats.chunk_count
    bag.indexed = True
    bag.compressions = {index.compression or "none" for index in summary.chunk_indexes}
    if stats.message_count:
        bag.start_ns, bag.end_ns = stats.message_start_time, stats.message_end_time
    _apply_end_metadata(bag)
    return True


def scan_records(bag: BagFile, *, collect: bool = False) -> Iterator[tuple[Channel, Message]]:
    """Every message of the file in file order, read record by record up to the first incomplete or
    damaged one. With ``collect``, fills ``bag`` (channels, schemas, metadata, counts, truncation)."""
    topic_bytes: dict[str, int] = {}
    topic_times: dict[str, tuple[int, int]] = {}
    channels: dict[int, Channel] = {}
    offset = 8
    clean_end = False
    problem = ""

    def counted(channel: Channel, message: Message):
        if collect:
            topic = channel.topic
            bag.topic_messages[topic] = bag.topic_messages.get(topic, 0) + 1
            topic_bytes[topic] = topic_bytes.get(topic, 0) + len(message.data)
            t = message.log_time
            first, last = topic_times.get(topic, (t, t))
            topic_times[topic] = (min(first, t), max(last, t))
            bag.start_ns = t if bag.start_ns is None else min(bag.start_ns, t)
            bag.end_ns = t if bag.end_ns is None else max(bag.end_ns, t)
        return channel, message

    if collect:
        bag.topic_messages.clear()
        bag.start_ns = bag.end_ns = None
        bag.chunks = 0
    with open(bag.path, "rb") as f:
        f.seek(8)
        while True:
            head = f.read(_RECORD_HEAD.size)
            if not head:
                problem = "the file ends without a footer"
                break
            if len(head) < _RECORD_HEAD.size:
                problem = f"an incomplete record header at byte {offset}"
                break
            opcode, length = _RECORD_HEAD.unpack(head)
            if offset + _RECORD_HEAD.size + length > bag.size:
                name = Opcode(opcode).name.lower() if opcode in Opcode._value2member_map_ else f"op {opcode}"
                problem = (
                    f"an incomplete {name} record at byte {offset} "
                    f"({bag.size - offset} of {_RECORD_HEAD.size + length} bytes present)"
                )
                break
            body = f.read(length)
            stream = ReadDataStream(io.BytesIO(body))
            try:
                if opcode == Opcode.CHUNK:
                    chunk = Chunk.read(stream)
                    records = breakup_chunk(chunk, validate_crc=True)
                    if collect:
                        bag.chunks += 1
                        bag.compressions.add(chunk.compression or "none")
                elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE, Opcode.METADATA):
                    reader = {
                        Opcode.SCHEMA: Schema.read,
                        Opcode.CHANNEL: Channel.read,
                        Opcode.METADATA: Metadata.read,
                    }.get(opcode)
                    records = [reader(stream) if reader else Message.read(stream, length)]
                elif opcode == Opcode.FOOTER:
                    Footer.read(stream)
                    clean_end = True
                    records = []
                else:
                    records = []  # indexes, statistics, data end: nothing a scan needs
            except Exception as exc:  # CRC mismatch, bad compression, a malformed record
                problem = f"a damaged record at byte {offset} ({type(exc).__name__}: {exc})"
                break
            for record in records:
                if isinstance(record, Schema):
                    if collect:
                        bag.schemas[record.id] = record
                elif isinstance(record, Channel):
                    channels[record.id] = record
                    if collect:
                        bag.channels[record.id] = record
                elif isinstance(record, Metadata):
                    if collect:
                        _read_metadata(record, bag.metadata)
                elif isinstance(record, Message):
                    channel = channels.get(record.channel_id)
                    if channel is not None:
                        yield counted(channel, record)
            offset += _RECORD_HEAD.size + length
            if clean_end:
                break
    if collect:
        bag.readable_bytes = offset
        bag.truncated = not clean_end
        bag.problem = "" if clean_end else problem
        bag.topic_bytes = topic_bytes
        bag.topic_times = topic_times


# --- reading -------------------------------------------------------------------------------------


def _matcher(topics):
    if topics is None:
        return None
    if isinstance(topics, str):
        topics = [topics]
    try:
        patterns = [re.compile(t) if isinstance(t, str) else t for t in topics]
    except re.error as exc:
        raise RecordingError(f"bad topic pattern: {exc}") from None
    return lambda topic: any(p.search(topic) for p in patterns)


class BagReader:
    """Messages of one or more recordings, merged in receive-time order; see the module docstring."""

    def __init__(self, paths):
        self.files = [open_bag_file(p) for p in resolve_paths(paths)]

    @property
    def truncated(self) -> bool:
        return any(f.truncated for f in self.files)

    @property
    def message_count(self) -> int:
        return sum(f.message_count for f in self.files)

    @property
    def start_ns(self) -> int | None:
        starts = [f.start_ns for f in self.files if f.start_ns is not None]
        return min(starts) if starts else None

    @property
    def end_ns(self) -> int | None:
        ends = [f.end_ns for f in self.files if f.end_ns is not None]
        return max(ends) if ends else None

    def types(self) -> dict[str, str]:
        out: dict[str, str] = {}
        for f in self.files:
            out.update(f.types())
        return out

    def topics(self, pattern=None) -> list[str]:
        match = _matcher(pattern)
        return sorted(t for t in self.types() if match is None or match(t))

    def _file_messages(self, bag: BagFile, match, start_ns: int | None) -> Iterator[RecordedMessage]:
        if bag.truncated or not bag.indexed:  # no summary to trust (e.g. bytes after the end): scan
            for channel, message in scan_records(bag):
                if (match is None or match(channel.topic)) and (
                    start_ns is None or message.log_time >= start_ns
                ):
                    yield _recorded(channel, message)
            return
        topics = [t for t in bag.types() if match is None or match(t)]
        if not topics:
            return
        with open(bag.path, "rb") as f:
            reader = SeekingReader(f)
            for _schema, channel, message in reader.iter_messages(
                topics=topics, log_time_order=True, starting_at=start_ns
            ):
                yield _recorded(channel, message)

    def messages(self, topics=None, start_ns: int | None = None) -> Iterator[RecordedMessage]:
        """Messages whose topic matches ``topics`` (regexes, searched; None = all), received at or
        after ``start_ns``, in receive-time order across every file."""
        match = _matcher(topics)
        streams = [self._file_messages(bag, match, start_ns) for bag in self.files]
        if len(streams) == 1:
            return streams[0]
        return heapq.merge(*streams, key=lambda m: m.log_time_ns)

    def metadata(self, name: str) -> list[dict[str, str]]:
        """The metadata record ``name`` of each file that has one, in file order."""
        return [f.metadata[name] for f in self.files if name in f.metadata]


def _recorded(channel: Channel, message: Message) -> RecordedMessage:
    return RecordedMessage(
        topic=channel.topic,
        log_time_ns=message.log_time,
        publish_time_ns=message.publish_time,
        sequence=message.sequence,
        data=message.data,
    )


def read_messages(paths, topics: Iterable[str] | str | None = None) -> list[RecordedMessage]:
    """Every message of a recording (small recordings and tests)."""
    return list(BagReader(paths).messages(topics))
