"""What a recording holds, as numbers (:func:`bag_info`) and as the text ``stg-bag info`` prints.

Topics with their type, message count, rate and size; duration, files, compression,
chunks; drops the recorder counted; versions and the launch file; and, for a file whose
recorder was killed, that it is truncated and how many messages were recovered.
"""

from __future__ import annotations

import datetime
import json
from dataclasses import dataclass, field

from stg_node.bus.recording.format import META_END, META_LAUNCH, META_RECORDING
from stg_node.bus.recording.reader import BagReader, scan_records
from stg_node.bus.stats import format_bytes, per_second


@dataclass
class TopicInfo:
    topic: str
    type: str
    messages: int
    bytes: int | None  # payload bytes; None when unknown
    rate_hz: float  # (messages - 1) / (last - first receive time) of this topic

    @property
    def avg_bytes(self) -> float | None:
        return None if self.bytes is None or not self.messages else self.bytes / self.messages


@dataclass
class FileInfo:
    path: str
    size: int
    messages: int
    truncated: bool
    problem: str
    clean_stop: bool  # the recorder finished this file (stg.recording.end present)


@dataclass
class BagInfo:
    files: list[FileInfo]
    topics: list[TopicInfo]
    messages: int
    start_ns: int | None
    end_ns: int | None
    chunks: int
    compressions: list[str]
    drops: dict[str, int] = field(default_factory=dict)
    recording: dict[str, str] = field(default_factory=dict)  # first file's stg.recording metadata
    launch_path: str = ""

    @property
    def duration_s(self) -> float:
        if self.start_ns is None or self.end_ns is None:
            return 0.0
        return (self.end_ns - self.start_ns) / 1e9

    @property
    def truncated(self) -> bool:
        return any(f.truncated for f in self.files)

    @property
    def size(self) -> int:
        return sum(f.size for f in self.files)


def bag_info(reader: BagReader) -> BagInfo:
    """Summarise ``reader``'s files. Sizes come from the recorder's end metadata; where a file has
    none (another writer's, or truncated files, which are scanned anyway) they are measured."""
    types = reader.types()
    counts: dict[str, int] = {}
    sizes: dict[str, int] = {}
    spans: dict[str, tuple[int, int]] = {}
    drops: dict[str, int] = {}
    files = []
    for bag in reader.files:
        if bag.topic_bytes is None or bag.topic_times is None:
            for _ in scan_records(bag, collect=True):
                pass
        for topic, n in bag.topic_messages.items():
            counts[topic] = counts.get(topic, 0) + n
        for topic, n in (bag.topic_bytes or {}).items():
            sizes[topic] = sizes.get(topic, 0) + n
        for topic, (first, last) in (bag.topic_times or {}).items():
            known = spans.get(topic, (first, last))
            spans[topic] = (min(known[0], first), max(known[1], last))
        end = bag.metadata.get(META_END, {})
        if "drops" in end:
            try:
                # each file's end record holds the session's drops so far: keep the largest
                for reason, n in json.loads(end["drops"]).items():
                    drops[reason] = max(drops.get(reason, 0), int(n))
            except (ValueError, TypeError, AttributeError):
                pass
        files.append(
            FileInfo(
                path=str(bag.path),
                size=bag.size,
                messages=bag.message_count,
                truncated=bag.truncated,
                problem=bag.problem,
                clean_stop=bool(end),
            )
        )
    start, end_ns = reader.start_ns, reader.end_ns

    def rate(topic: str, n: int) -> float:
        first, last = spans.get(topic, (start, end_ns))
        if first is None or last is None or last <= first or n < 2:
            return 0.0
        return per_second(n - 1, (last - first) / 1e9)  # the bus's one rate definition

    topics = [
        TopicInfo(
            topic=topic,
            type=types.get(topic, "?"),
            messages=n,
            bytes=sizes.get(topic),
            rate_hz=rate(topic, n),
        )
        for topic, n in sorted(counts.items())
    ]
    first = reader.files[0]
    return BagInfo(
        files=files,
        topics=topics,
        messages=sum(counts.values()),
        start_ns=start,
        end_ns=end_ns,
        chunks=sum(f.chunks for f in reader.files),
        compressions=sorted({c for f in reader.files for c in f.compressions}),
        drops=drops,
        recording=dict(first.metadata.get(META_RECORDING, {})),
        launch_path=first.metadata.get(META_LAUNCH, {}).get("path", ""),
    )


def _when(stamp_ns: int | None) -> str:
    if stamp_ns is None:
        return "-"
    when = datetime.datetime.fromtimestamp(stamp_ns / 1e9)
    return f"{when:%Y-%m-%d %H:%M:%S}.{stamp_ns % 1_000_000_000 // 1_000_000:03d}"


def format_info(info: BagInfo) -> str:
    lines = []
    for f in info.files:
        state = "TRUNCATED" if f.truncated else ("complete" if f.clean_stop else "complete (no end record)")
        lines.append(f"File:         {f.path}  ({format_bytes(f.size)}, {f.messages} messages, {state})")
        if f.truncated:
            lines.append(f"  truncated:  the recorder did not finish this file (killed?): {f.problem}")
            lines.append(f"              {f.messages} messages recovered from its complete chunks")
    lines += [
        f"Duration:     {info.duration_s:.3f} s",
        f"Start:        {_when(info.start_ns)}",
        f"End:          {_when(info.end_ns)}",
        f"Messages:     {info.messages}",
        f"Size:         {format_bytes(info.size)}",
        f"Chunks:       {info.chunks} ({', '.join(info.compressions) or 'none'})",
    ]
    if info.recording:
        r = info.recording
        lines.append(
            f"Recorded by:  stg_node {r.get('stg_node', '?')} (mcap {r.get('mcap', '?')}, "
            f"python {r.get('python', '?')}) on {r.get('host', '?')} from {r.get('bus', '?')}"
        )
    if info.launch_path:
        lines.append(f"Launch file:  {info.launch_path}")
    if info.drops:
        detail = ", ".join(f"{n} {reason}" for reason, n in sorted(info.drops.items()))
        lines.append(f"Drops:        {sum(info.drops.values())} ({detail})")
    elif any(f.clean_stop for f in info.files):
        lines.append("Drops:        0")
    else:
        lines.append("Drops:        unknown (the recorder did not stop cleanly)")
    if info.truncated:
        recovered = sum(f.messages for f in info.files if f.truncated)
        lines.append(f"TRUNCATED:    yes; {recovered} messages recovered from truncated file(s)")
    rows = [("TOPIC", "TYPE", "MSGS", "HZ", "SIZE", "AVG")]
    for t in info.topics:
        rows.append(
            (
                t.topic,
                t.type,
                str(t.messages),
                f"{t.rate_hz:.2f}",
                format_bytes(t.bytes),
                format_bytes(t.avg_bytes),
            )
        )
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines.append("Topics:")
    for row in rows:
        lines.append("  " + "  ".join(cell.ljust(w) for cell, w in zip(row, widths, strict=True)).rstrip())
    return "\n".join(lines)


def info_dict(info: BagInfo) -> dict:
    """JSON-friendly form (``stg-bag info --json``)."""
    return {
        "files": [f.__dict__ for f in info.files],
        "duration_s": info.duration_s,
        "start_ns": info.start_ns,
        "end_ns": info.end_ns,
        "messages": info.messages,
        "size": info.size,
        "chunks": info.chunks,
        "compressions": info.compressions,
        "truncated": info.truncated,
        "drops": info.drops,
        "recording": info.recording,
        "launch_path": info.launch_path,
        "topics": [{**t.__dict__, "avg_bytes": t.avg_bytes} for t in info.topics],
    }
