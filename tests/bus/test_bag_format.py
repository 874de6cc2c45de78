"""The stg-bus MCAP format, checked with the mcap package's own reader: channels, schemas, exact
bytes, times, compression, splitting, metadata; and clear errors for files that are not recordings."""

from __future__ import annotations

import json

import msgpack
import numpy as np
import pytest
from baghelpers import ROOT, encoded_stream, mcap_messages, raw_frames
from bushelpers import sample_messages
from mcap.reader import make_reader

from stg_node.bus.recording import BagReader, BagWriter, RecordingError, bag_info
from stg_node.bus.recording.format import MESSAGE_ENCODING, SCHEMA_ENCODING, split_payload


def _write(path, stream, **options):
    with BagWriter(path, **options) as bag:
        for log_time, frames in stream:
            bag.write_frames(frames, log_time)
    return bag


@pytest.mark.parametrize("compression", ["none", "zstd", "lz4"])
def test_mcap_reader_sees_one_channel_per_topic_and_the_exact_bytes(tmp_path, compression):
    stream = encoded_stream(5)
    path = tmp_path / "s.mcap"
    _write(path, stream, compression=compression, chunk_size=2000)
    got = mcap_messages(path)
    assert len(got) == len(stream)
    for (log_time, frames), (topic, channel, message) in zip(stream, got, strict=True):
        header = msgpack.unpackb(frames[1])
        assert topic == frames[0].decode()
        assert channel.message_encoding == MESSAGE_ENCODING == "stg-bus"
        assert message.data == b"".join(frames[1:])  # header bytes + buffers, in order
        assert message.log_time == log_time
        assert message.publish_time == header["stamp_ns"]
        assert message.sequence == header["seq"]
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert (
        len({c.topic for c in summary.channels.values()}) == len(summary.channels) == len(sample_messages())
    )
    assert {i.compression for i in summary.chunk_indexes} == {"" if compression == "none" else compression}
    assert len(summary.chunk_indexes) > 1


def test_each_type_has_its_proto_yaml_as_schema(tmp_path):
    path = tmp_path / "s.mcap"
    _write(path, encoded_stream(1))
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert len(summary.schemas) == len(sample_messages())
    for schema in summary.schemas.values():
        assert schema.encoding == SCHEMA_ENCODING
        assert schema.data == (ROOT / "proto" / f"{schema.name.lower()}.yaml").read_bytes()
    for channel in summary.channels.values():
        assert summary.schemas[channel.schema_id].name == channel.metadata["type"]


def test_data_splits_back_into_header_and_buffers_by_the_arrays_entries(tmp_path):
    """What proto/recording.md tells other languages to do, done with msgpack and numpy only."""
    stream = encoded_stream(1)
    path = tmp_path / "s.mcap"
    _write(path, stream)
    for (_t, frames), (topic, _c, message) in zip(stream, mcap_messages(path), strict=True):
        unpacker = msgpack.Unpacker()
        unpacker.feed(message.data)
        header = unpacker.unpack()
        offset = unpacker.tell()
        buffers = []
        for desc in header["arrays"]:
            n = int(np.prod(desc["shape"])) * np.dtype(desc["dtype"]).itemsize
            buffers.append(message.data[offset : offset + n])
            offset += n
        assert offset == len(message.data)
        assert [message.data[: unpacker.tell()], *buffers] == frames[1:]
        assert raw_frames(split_payload(topic, message.data)) == frames


def test_metadata_holds_versions_launch_file_and_end_counts(tmp_path):
    launch = tmp_path / "demo.yaml"
    launch.write_text("nodes:\n  - name: trainer\n")
    path = tmp_path / "s.mcap"
    stream = encoded_stream(2)
    with BagWriter(path, launch_file=launch, metadata={"bus": "ipc:///x"}) as bag:
        for log_time, frames in stream:
            bag.write_frames(frames, log_time)
    with open(path, "rb") as f:
        meta = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    assert meta["stg.recording"]["mcap"] and meta["stg.recording"]["stg_node"] == "0.1.0"
    assert meta["stg.recording"]["bus"] == "ipc:///x"
    assert meta["stg.launch"] == {"path": str(launch.resolve()), "text": launch.read_text()}
    end = meta["stg.recording.end"]
    assert int(end["messages"]) == len(stream)
    sizes = json.loads(end["topic_bytes"])
    assert sum(sizes.values()) == sum(len(b"".join(f[1:])) for _t, f in stream)


def test_split_by_size_gives_complete_files_that_read_back_as_one(tmp_path):
    stream = encoded_stream(12)
    bag = _write(tmp_path / "s.mcap", stream, split_size=3000)
    assert len(bag.files) > 2
    assert [p.name for p in bag.files] == [f"s_{i:04d}.mcap" for i in range(len(bag.files))]
    assert not (tmp_path / "s.mcap").exists()
    together = []
    for path in bag.files:
        with open(path, "rb") as f:
            assert make_reader(f).get_summary() is not None  # each file finished on its own
        together += [m.data for _t, _c, m in mcap_messages(path)]
    assert together == [b"".join(f[1:]) for _t, f in stream]
    reader = BagReader(tmp_path / "s.mcap")  # the set's base name finds every file
    assert [m.data for m in reader.messages()] == together


def test_split_by_duration(tmp_path):
    stream = encoded_stream(10, step_ns=10**8)  # 0.1 s apart
    bag = _write(tmp_path / "d.mcap", stream, split_duration_s=2.0)
    assert len(bag.files) == 4
    for path in bag.files:
        times = [m.log_time for _t, _c, m in mcap_messages(path)]
        assert times[-1] - times[0] < 2e9
    info = bag_info(BagReader(bag.files))
    assert info.messages == len(stream) and len(info.files) == 4


def test_topic_filter_and_start_time_when_reading(tmp_path):
    stream = encoded_stream(4)
    path = tmp_path / "s.mcap"
    _write(path, stream)
    reader = BagReader(path)
    poses = list(reader.messages(["body/pose"]))
    assert [m.sequence for m in poses] == [0, 1, 2, 3]
    later = list(reader.messages(start_ns=stream[10][0]))
    assert len(later) == len(stream) - 10


@pytest.mark.parametrize(
    "content, problem",
    [
        (b"", "not an MCAP file"),
        (b"hello world, not a recording", "not an MCAP file"),
        (b"\x89PNG\r\n\x1a\n" + bytes(100), "not an MCAP file"),
    ],
)
def test_files_that_are_not_recordings_give_clear_errors(tmp_path, content, problem):
    path = tmp_path / "bad.mcap"
    path.write_bytes(content)
    with pytest.raises(RecordingError, match=problem) as info:
        BagReader(path)
    assert str(path) in str(info.value)


def test_missing_recording_names_the_path(tmp_path):
    with pytest.raises(RecordingError, match="no recording at .*nothing.mcap"):
        BagReader(tmp_path / "nothing.mcap")


def test_a_foreign_payload_is_a_clear_error_not_a_crash(tmp_path):
    from mcap.writer import Writer

    path = tmp_path / "foreign.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        channel = w.register_channel("body/pose", MESSAGE_ENCODING, 0)
        w.add_message(channel, 1, b"\x92\x01\x02", 1, 0)  # msgpack, but a list, not a header
        header = msgpack.packb(
            {"type": "BodyPose", "arrays": [{"name": "x", "dtype": "float32", "shape": [4]}]}
        )
        w.add_message(channel, 2, header + b"abc", 2, 0)  # 3 bytes where 16 are described
        w.finish()
    first, second = BagReader(path).messages()
    with pytest.raises(RecordingError, match="not a map"):
        first.frames()
    with pytest.raises(RecordingError, match="3 bytes follow the header, its arrays describe 16"):
        second.frames()


def test_bad_writer_options_are_refused(tmp_path):
    with pytest.raises(RecordingError, match="compression 'gzip'"):
        BagWriter(tmp_path / "x.mcap", compression="gzip")
    with pytest.raises(RecordingError, match="split size"):
        BagWriter(tmp_path / "x.mcap", split_size=0)


@pytest.mark.parametrize("compression", ["none", "zstd", "lz4"])
def test_files_pass_the_mcap_readers_checks(tmp_path, compression):
    """Streamed with every CRC checked, indexed by topic both ways, summary CRC and statistics."""
    import struct
    import zlib

    from mcap.records import Footer, Header, Message
    from mcap.stream_reader import StreamReader

    stream = encoded_stream(6)
    path = tmp_path / "s.mcap"
    _write(path, stream, compression=compression, chunk_size=3000)
    records = list(StreamReader(str(path), validate_crcs=True).records)
    assert isinstance(records[0], Header) and records[0].profile == "stg" and isinstance(records[-1], Footer)
    assert sum(isinstance(r, Message) for r in records) == len(stream)
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        summary = reader.get_summary()
        poses = [m for _s, _c, m in reader.iter_messages(topics=["body/pose"])]
        backwards = [m for _s, _c, m in reader.iter_messages(topics=["body/pose"], reverse=True)]
    want = [b"".join(f[1:]) for _t, f in stream if f[0] == b"body/pose"]
    assert [m.data for m in poses] == want and [m.data for m in backwards] == want[::-1]
    stats = summary.statistics
    assert stats.message_count == len(stream) and sum(stats.channel_message_counts.values()) == len(stream)
    assert stats.chunk_count == len(summary.chunk_indexes) > 1
    assert (stats.message_start_time, stats.message_end_time) == (stream[0][0], stream[-1][0])
    data = path.read_bytes()
    footer = records[-1]
    summary_bytes = data[footer.summary_start : len(data) - 8 - 29]
    prefix = struct.pack("<BQQQ", 0x02, 20, footer.summary_start, footer.summary_offset_start)
    assert zlib.crc32(prefix, zlib.crc32(summary_bytes)) == footer.summary_crc


def test_a_header_with_msgpack_extension_types_is_refused(tmp_path):
    from mcap.writer import Writer

    path = tmp_path / "ext.mcap"
    header = msgpack.packb({"type": "BodyPose", "arrays": [], "x": msgpack.ExtType(5, b"\x00")})
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        w.add_message(w.register_channel("body/pose", MESSAGE_ENCODING, 0), 1, header, 1, 0)
        w.finish()
    (msg,) = BagReader(path).messages()
    with pytest.raises(RecordingError, match="header refused: msgpack extension type 5 refused"):
        msg.frames()
