"""A lean MCAP writer: chunks written straight from the received buffers, records by the mcap package.

Why not ``mcap.writer.Writer`` as is: it takes each message as one ``bytes`` object and
copies it three more times on the way to the file (into the chunk's BytesIO, into the
chunk record's BytesIO, into the file), each into freshly allocated memory. For 6 MB camera
frames that held recording to ~300 MB/s here. This writer keeps the chunk as a list of
buffers (the ZeroMQ frames themselves: record headers, bus header bytes, array buffers),
computes the chunk CRC over them and writes them to the file: one copy, into the page cache.
Compressed chunks are joined once and compressed exactly as the mcap package does
(``zstandard.compress``, ``lz4.frame.compress``).

Every record other than the chunk framing and message headers (schemas, channels,
metadata, message indexes, chunk indexes, statistics, summary offsets, footer) is written
by the mcap package's own record classes, and tests read every file with the mcap
package's readers (indexed and streaming, CRCs checked). The layout follows mcap's Writer:
schemas and channels inside chunks, a message index per channel after each chunk, a
summary with schemas, channels, statistics, chunk and metadata indexes, summary offsets.
"""

from __future__ import annotations

import struct
import zlib
from collections import defaultdict

from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    Channel,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    MessageIndex,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)

MAGIC = b"\x89MCAP0\r\n"
COMPRESSIONS = ("none", "zstd", "lz4")
_MESSAGE_HEAD = struct.Struct("<BQHIQQ")  # opcode, record length, channel, sequence, log time, publish time
_CHUNK_HEAD = struct.Struct("<BQQQQI")  # opcode, record length, start, end, uncompressed size, crc
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")
_FOOTER_PREFIX = struct.Struct("<BQQQ")


def _bytes_view(part) -> memoryview:
    view = memoryview(part)
    if view.ndim != 1 or view.format != "B":
        view = view.cast("B")
    return view


def _record(record) -> bytes:
    builder = RecordBuilder()
    record.write(builder)
    return builder.end()


def _compressor(compression: str):
    if compression == "zstd":
        import zstandard  # noqa: PLC0415 (optional until used)

        return "zstd", zstandard.compress
    if compression == "lz4":
        import lz4.frame  # noqa: PLC0415

        return "lz4", lz4.frame.compress
    if compression == "none":
        return "", None
    raise ValueError(f"compression {compression!r} is not one of {COMPRESSIONS}")


class McapFile:
    """Writes one MCAP file to ``stream`` (binary, writable). Not thread-safe: one writer thread."""

    def __init__(self, stream, *, chunk_size: int = 4 << 20, compression: str = "none"):
        self._out = stream
        self._chunk_size = chunk_size
        self._compression, self._compress = _compressor(compression)
        self._offset = 0
        self._pieces: list = []
        self._chunk_len = 0
        self._chunk_messages = 0
        self._chunk_start_time = 0
        self._chunk_end_time = 0
        self._message_index: dict[int, list[tuple[int, int]]] = {}
        self._schemas: dict[int, Schema] = {}
        self._channels: dict[int, Channel] = {}
        self._chunk_indexes: list[ChunkIndex] = []
        self._metadata_indexes: list[MetadataIndex] = []
        self._counts: dict[int, int] = defaultdict(int)
        self._messages = 0
        self._metadata_count = 0
        self._chunks = 0
        self._start_time = 0
        self._end_time = 0
        self._finished = False

    # -- output ---------------------------------------------------------------------------------

    def _write(self, data) -> None:
        self._out.write(data)
        self._offset += memoryview(data).nbytes

    def start(self, profile: str = "", library: str = "") -> None:
        self._write(MAGIC)
        self._write(_record(Header(profile=profile, library=library)))

    # -- chunk contents ---------------------------------------------------------------------------

    def _add_to_chunk(self, piece) -> None:
        self._pieces.append(piece)
        self._chunk_len += memoryview(piece).nbytes

    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        schema_id = len(self._schemas) + 1
        schema = Schema(id=schema_id, name=name, encoding=encoding, data=data)
        self._schemas[schema_id] = schema
        self._add_to_chunk(_record(schema))
        return schema_id

    def register_channel(self, topic: str, message_encoding: str, schema_id: int, metadata=None) -> int:
        channel_id = len(self._channels) + 1
        channel = Channel(
            id=channel_id,
            topic=topic,
            message_encoding=message_encoding,
            schema_id=schema_id,
            metadata=dict(metadata or {}),
        )
        self._channels[channel_id] = channel
        self._add_to_chunk(_record(channel))
        return channel_id

    def add_message(self, channel_id: int, log_time: int, publish_time: int, sequence: int, parts) -> int:
        """Add a message whose data is ``parts`` (buffers, concatenated in order; not copied until the
        chunk is written: keep them unchanged until then). Returns the data's length."""
        views = [_bytes_view(p) for p in parts]
        size = sum(v.nbytes for v in views)
        if self._chunk_messages == 0:
            self._chunk_start_time = self._chunk_end_time = log_time
        else:
            self._chunk_start_time = min(self._chunk_start_time, log_time)
            self._chunk_end_time = max(self._chunk_end_time, log_time)
        if self._messages == 0:
            self._start_time = self._end_time = log_time
        else:
            self._start_time = min(self._start_time, log_time)
            self._end_time = max(self._end_time, log_time)
        self._message_index.setdefault(channel_id, []).append((log_time, self._chunk_len))
        self._add_to_chunk(
            _MESSAGE_HEAD.pack(Opcode.MESSAGE, 22 + size, channel_id, sequence, log_time, publish_time)
        )
        for view in views:
            self._pieces.append(view)
        self._chunk_len += size
        self._chunk_messages += 1
        self._messages += 1
        self._counts[channel_id] += 1
        if self._chunk_len >= self._chunk_size:
            self._finish_chunk()
        return size

    def _finish_chunk(self) -> None:
        if self._chunk_messages == 0:
            return  # schemas and channels alone wait for their first message (and are in the summary)
        if self._compress is None:
            crc = 0
            for piece in self._pieces:
                crc = zlib.crc32(piece, crc)
            body = self._pieces
            stored = self._chunk_len
        else:
            records = b"".join(self._pieces)
            crc = zlib.crc32(records)
            body = [self._compress(records)]
            stored = len(body[0])
        compression = self._compression.encode()
        length = 8 + 8 + 8 + 4 + 4 + len(compression) + 8 + stored
        chunk_start = self._offset
        self._write(
            _CHUNK_HEAD.pack(
                Opcode.CHUNK, length, self._chunk_start_time, self._chunk_end_time, self._chunk_len, crc
            )
            + _U32.pack(len(compression))
            + compression
            + _U64.pack(stored)
        )
        for piece in body:
            self._write(piece)
        chunk_length = self._offset - chunk_start
        index_start = self._offset
        offsets = {}
        for channel_id, entries in self._message_index.items():
            offsets[channel_id] = self._offset
            self._write(_record(MessageIndex(channel_id=channel_id, records=entries)))
        self._chunk_indexes.append(
            ChunkIndex(
                message_start_time=self._chunk_start_time,
                message_end_time=self._chunk_end_time,
                chunk_start_offset=chunk_start,
                chunk_length=chunk_length,
                message_index_offsets=offsets,
                message_index_length=self._offset - index_start,
                compression=self._compression,
                compressed_size=stored,
                uncompressed_size=self._chunk_len,
            )
        )
        self._chunks += 1
        self._pieces = []
        self._chunk_len = 0
        self._chunk_messages = 0
        self._message_index = {}

    # -- outside chunks -----------------------------------------------------------------------------

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        offset = self._offset
        record = _record(Metadata(name=name, metadata=dict(data)))
        self._write(record)
        self._metadata_indexes.append(MetadataIndex(offset=offset, length=len(record), name=name))
        self._metadata_count += 1

    def flush(self) -> None:
        """Write the chunk in progress (if any) and flush the stream to the OS."""
        self._finish_chunk()
        self._out.flush()

    def finish(self) -> None:
        """The last chunk, the data end, the summary and the footer. The stream stays open."""
        if self._finished:
            return
        self._finished = True
        self._finish_chunk()
        self._write(_record(DataEnd(data_section_crc=0)))
        summary_start = self._offset
        builder = RecordBuilder()
        offsets: list[SummaryOffset] = []

        def group(opcode: Opcode, records) -> None:
            begin = builder.count
            for record in records:
                record.write(builder)
            if builder.count > begin:
                offsets.append(
                    SummaryOffset(
                        group_opcode=opcode,
                        group_start=summary_start + begin,
                        group_length=builder.count - begin,
                    )
                )

        statistics = Statistics(
            message_count=self._messages,
            schema_count=len(self._schemas),
            channel_count=len(self._channels),
            attachment_count=0,
            metadata_count=self._metadata_count,
            chunk_count=self._chunks,
            message_start_time=self._start_time,
            message_end_time=self._end_time,
            channel_message_counts=dict(self._counts),
        )
        group(Opcode.SCHEMA, self._schemas.values())
        group(Opcode.CHANNEL, self._channels.values())
        group(Opcode.STATISTICS, [statistics])
        group(Opcode.CHUNK_INDEX, self._chunk_indexes)
        group(Opcode.METADATA_INDEX, self._metadata_indexes)
        summary_offset_start = summary_start + builder.count
        for offset in offsets:
            offset.write(builder)
        summary = builder.end()
        crc = zlib.crc32(summary)
        crc = zlib.crc32(
            _FOOTER_PREFIX.pack(Opcode.FOOTER, 8 + 8 + 4, summary_start, summary_offset_start), crc
        )
        self._write(summary)
        self._write(
            _record(
                Footer(
                    summary_start=summary_start, summary_offset_start=summary_offset_start, summary_crc=crc
                )
            )
        )
        self._write(MAGIC)
        self._out.flush()
