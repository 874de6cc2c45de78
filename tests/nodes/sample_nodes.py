"""Small nodes for the runtime and launcher tests (imported as tests.nodes.sample_nodes:NAME)."""

from __future__ import annotations

import os
import signal
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from stg_node.bus import BodyPose, TrainerMetrics
from stg_node.nodes.params import param
from stg_node.nodes.runtime import Node


@dataclass
class EchoParams:
    flush_file: str = param("", doc="written at teardown (proves the flush ran)")
    setup_s: float = param(0.0, min=0.0, doc="time setup takes")
    exit_after_s: float = param(0.0, min=0.0, doc="stop on its own after this long (0: never)")
    exit_code: int = param(0, doc="exit code when stopping on its own")
    ignore_signals: bool = param(False, doc="ignore SIGINT and SIGTERM (escalation test)")
    teardown_s: float = param(0.0, min=0.0, doc="time teardown takes")
    child: bool = param(False, doc="start a grandchild process (sleep) in the node's group")


class Echo(Node):
    """Republishes body/pose as trainer/metrics (iteration = frame_index); ticks at 20 Hz."""

    kind = "echo"
    Params = EchoParams
    tick_s = 0.05

    def setup(self):
        if self.params.ignore_signals:
            signal.signal(signal.SIGINT, signal.SIG_IGN)
            signal.signal(signal.SIGTERM, signal.SIG_IGN)
        if self.params.child:
            import subprocess

            self.grandchild = subprocess.Popen(["sleep", "300"])
            print(f"grandchild {self.grandchild.pid}", flush=True)
        time.sleep(self.params.setup_s)
        self.subscribe("body/pose")
        self.started = time.monotonic()
        print(f"echo ready pid {os.getpid()}", flush=True)

    def on_message(self, topic, msg):
        self.publish(TrainerMetrics(iteration=max(0, msg.frame_index), loss=0.0))

    def on_tick(self):
        if self.params.exit_after_s and time.monotonic() - self.started > self.params.exit_after_s:
            self.exit_code = self.params.exit_code
            self.stop("done")

    def teardown(self):
        if self.params.teardown_s:
            print("teardown started", flush=True)  # what a test sends a second signal after
        time.sleep(self.params.teardown_s)
        if self.params.flush_file:
            Path(self.params.flush_file).write_text("flushed")


def pose(index: int) -> BodyPose:
    return BodyPose(
        frame_index=index,
        poses=np.zeros((24, 3), np.float32),
        Rh=np.zeros(3, np.float32),
        Th=np.zeros(3, np.float32),
        betas=np.zeros(10, np.float32),
    )
