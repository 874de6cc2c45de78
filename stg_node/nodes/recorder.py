"""The recorder node: what crosses the bus, into an MCAP recording (stg-bag record as a node).

A thin node around :class:`stg_node.bus.recording.Recorder`, so a launch file can record its
own session (``record:=FILE`` in launch/demo.yaml and launch/replay_zju.yaml):

- ``setup`` starts the recorder on the node's own zmq context (it subscribes to every lane and
  opens the file) and adds its whole-bus subscriber to the heartbeat, so the node's NodeStatus
  shows every topic recorded, its rate and the bus's drop counters;
- ``run`` polls it (the writes happen in the node's thread; a reader thread only receives) and
  logs progress every ``report_every_s``;
- ``teardown`` stops it: what is queued is written and the file finished (summary, indexes,
  the drop counts), also after Ctrl-C / SIGTERM from stg-launch. A recorder killed with
  kill -9 leaves a file that reads back up to its last complete chunk (docs/RECORDING.md).

Recorder drops the bus itself did not count (``recorder_overflow``: the disk fell behind for
longer than ``max_queue_mb`` could absorb) are fed into the heartbeat's drop counters.
The launch file that started the node (``STG_LAUNCH_FILE``, set by stg-launch) is stored in
the recording unless ``launch_file`` names another.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from typing import Literal

from stg_node.bus.recording import Recorder, RecordingError
from stg_node.bus.recording.recorder import OVERFLOW
from stg_node.bus.stats import format_bytes
from stg_node.nodes.params import param
from stg_node.nodes.runtime import ENV_LAUNCH_FILE, Node, NodeError

MB = 1 << 20


@dataclass
class RecorderParams:
    path: str = param(doc="the MCAP file to write (with splitting: the base name, NAME_0000.mcap ...)")
    topics: list[str] = param(
        [], doc="record only topics matching one of these regexes (searched; empty: every topic)"
    )
    compression: Literal["none", "zstd", "lz4"] = param("none", doc="chunk compression")
    split_size_mb: float = param(0.0, min=0.0, unit="MB", doc="start a new file after this much (0: never)")
    split_duration_s: float = param(0.0, min=0.0, unit="s", doc="start a new file this often (0: never)")
    chunk_size_mb: float = param(4.0, min=0.01, unit="MB", doc="chunk size")
    flush_interval_s: float = param(
        1.0, min=0.01, unit="s", doc="write a chunk at least this often (what a kill -9 can lose)"
    )
    max_queue_mb: float = param(512.0, min=1.0, unit="MB", doc="messages held in memory while the disk lags")
    launch_file: str = param("", doc="launch file to store in the recording (empty: the one that started us)")
    report_every_s: float = param(10.0, min=0.0, unit="s", doc="log what was recorded this often (0: never)")

    def validate(self) -> None:
        if not self.path.strip():
            raise ValueError("path is empty: name the MCAP file to write")


class RecorderNode(Node):
    """Records the bus into an MCAP file (stg-bag record as a node)."""

    kind = "recorder"
    Params = RecorderParams

    def setup(self) -> None:
        p = self.params
        launch_file = p.launch_file or os.environ.get(ENV_LAUNCH_FILE) or None
        self.recorder: Recorder | None = None
        self.overflow_counted = 0
        try:
            self.recorder = Recorder(
                p.path,
                config=self.bus.config,
                context=self.bus.context,
                topics=p.topics,
                compression=p.compression,
                split_size=int(p.split_size_mb * MB) or None,
                split_duration_s=p.split_duration_s or None,
                chunk_size=int(p.chunk_size_mb * MB),
                flush_interval_s=p.flush_interval_s,
                max_queue_bytes=int(p.max_queue_mb * MB),
                launch_file=launch_file,
                metadata={"recorder_node": self.name},
            ).start()
        except (RecordingError, OSError) as exc:
            self.recorder = None
            raise NodeError(f"cannot record to {p.path}: {exc}") from exc
        if self.heartbeat is not None:
            self.heartbeat.add(self.recorder.subscriber)

    def _count_overflow(self) -> None:
        overflow = self.recorder.stats().drops.get(OVERFLOW, 0)
        if overflow > self.overflow_counted:
            self.drop(OVERFLOW, overflow - self.overflow_counted)
            self.overflow_counted = overflow

    def run(self) -> None:
        every = self.params.report_every_s
        next_report = time.monotonic() + every if every else None
        while not self.stopping:
            try:
                self.recorder.poll(0.1)
            except RecordingError as exc:
                raise NodeError(str(exc)) from exc
            self._count_overflow()
            if next_report is not None and time.monotonic() >= next_report:
                s = self.recorder.stats()
                self.log.info(
                    "%d messages, %s written, %d queued, drops %s",
                    s.written,
                    format_bytes(s.bytes_written),
                    s.queued,
                    s.drops or 0,
                )
                next_report += every

    def teardown(self) -> None:
        if self.recorder is None:
            return
        stats = self.recorder.stop()
        self._count_overflow()
        detail = ", ".join(f"{n} {reason}" for reason, n in sorted(stats.drops.items())) or "no drops"
        self.log.info(
            "recorded %d messages (%s) to %s; %s",
            stats.written,
            format_bytes(stats.bytes_written),
            ", ".join(stats.files),
            detail,
        )
