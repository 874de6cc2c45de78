"""``stg-launch launch/demo.yaml foxglove:=PORT web:=PORT2``: the session seen live.

- a raw client of the published Foxglove WebSocket protocol (websockets + JSON + protobuf from
  the advertised schema: nothing of ours, nothing of foxglove-sdk) receives avatar images and
  they are not blank;
- headless Chromium (Debian's ``chromium``; the test skips, saying so, where there is none) shows
  the avatar on /avatar, and the operator page shows the camera, the nodes and the trainer;
- Ctrl-C then stops everything: the launch exits 0 and no process survives, Chromium's included.

One launch serves both (a module fixture): the demo with the fake avatar (a disc of the
subject's colour) on a tiny synthetic subject, trained slowly enough to keep running until the
test stops it.
"""

from __future__ import annotations

import re
import signal
import socket
import sys
import threading

import cv2
import numpy as np
import pytest
from foxglove_client import FoxgloveClient
from nodehelpers import ROOT, describe_pids, ignore_sigint, pid_alive, spawn, wait_until

sys.path.insert(0, str(ROOT / "tools"))
from headless_chromium import BrowserError, HeadlessChromium, find_chromium  # noqa: E402

AVATAR_VIEW = "view/avatar/image/image"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class DemoRun:
    """The launch in the background, its output collected."""

    def __init__(self, tmp, foxglove_port: int, web_port: int):
        self.foxglove_port, self.web_port = foxglove_port, web_port
        self.lines: list[str] = []
        self.process = spawn(
            ["-m", "stg_node.cli.launch", str(ROOT / "launch" / "demo.yaml"), f"out:={tmp}/demo",
             f"bus:=ipc://{tmp}/bus", "frames:=8", "size:=64", "iters:=1000000", "preset:=slow",
             "avatar:=tests.nodes.fake_avatar", f"foxglove:={foxglove_port}", f"web:={web_port}",
             "--no-color"],
            preexec_fn=ignore_sigint,
        )  # fmt: skip
        self.reader = threading.Thread(
            target=lambda: self.lines.extend(iter(self.process.stdout.readline, ""))
        )
        self.reader.daemon = True
        self.reader.start()

    @property
    def log(self) -> str:
        return "".join(self.lines)

    def ready(self, name: str) -> bool:
        return f"{name} is ready" in self.log

    def pids(self) -> list[int]:
        return [int(p) for p in re.findall(r"started \w+: pid (\d+)", self.log)]

    def stop(self) -> int:
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGINT)
        code = self.process.wait(timeout=90)
        self.reader.join(5)
        return code


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("views")
    run = DemoRun(tmp, free_port(), free_port())
    try:
        assert wait_until(lambda: run.ready("ingest") or run.process.poll() is not None, timeout=240), run.log
        assert run.process.poll() is None, run.log
        yield run
    finally:
        code = run.stop()
        pids = run.pids()
        assert code == 0, run.log[-4000:]
        assert wait_until(lambda: not any(pid_alive(p) for p in pids), timeout=10), describe_pids(pids)


def test_a_raw_foxglove_client_receives_non_blank_avatar_images(demo):
    with FoxgloveClient(f"ws://127.0.0.1:{demo.foxglove_port}") as client:
        client.wait_for_channels([AVATAR_VIEW, "view/trainer/metrics/fields"])
        channel = client.channels[AVATAR_VIEW]
        assert (channel["encoding"], channel["schemaName"]) == ("protobuf", "foxglove.CompressedImage")
        client.subscribe(AVATAR_VIEW, "view/trainer/metrics/fields")
        images, metrics = [], []
        while len(images) < 3 or not metrics:
            got = client.receive(timeout=60)
            (images if got.topic == AVATAR_VIEW else metrics).append(got.message)
    for image in images:
        assert image.format == "jpeg" and image.frame_id == "avatar/image/camera"
        bgr = cv2.imdecode(np.frombuffer(image.data, np.uint8), cv2.IMREAD_COLOR)
        assert bgr is not None and bgr.shape[:2] == (64, 64)
        lit = (bgr.max(axis=2) > 40).mean()  # the fake avatar's disc on black
        assert 0.02 < lit < 0.9, lit
    assert metrics[-1]["iteration"] > 0 and metrics[-1]["src"] == "trainer"


def open_browser():
    if find_chromium() is None:
        pytest.skip("no Chromium: install Debian's chromium package (apt-get install chromium; .ci/run does)")
    return HeadlessChromium(width=900, height=700)


def test_headless_chromium_shows_the_avatar_and_the_operator_page(demo):
    browser = open_browser()
    pids: list[int] = []
    try:
        with browser:
            pids = browser.pids
            browser.open(f"http://127.0.0.1:{demo.web_port}/avatar")
            shown = browser.wait_for(
                "window.stgStats && window.stgStats.avatar.shown >= 3 && window.stgStats.avatar"
            )
            assert (shown["width"], shown["height"]) == (64, 64)
            png = browser.screenshot()
            browser.open(f"http://127.0.0.1:{demo.web_port}/")
            status = browser.wait_for(
                "window.stgStats && window.stgStats.camera.shown >= 2 && window.stgStats.status "
                "&& window.stgStats.status.trainer && window.stgStats.status",
            )
            rows = browser.evaluate(
                "[...document.querySelectorAll('#nodes tr td:first-child')].map(e => e.textContent)"
            )
    except BrowserError as exc:
        pytest.fail(f"{exc}\nlaunch log tail:\n{demo.log[-3000:]}")
    # What Chromium drew (decoded by OpenCV): the avatar fills the window's height, centred,
    # a lit disc on black, and nothing of the page's text over it.
    screen = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    assert screen.shape[:2] == (700, 900)
    lit = screen.max(axis=2) > 40
    assert 0.02 < lit.mean() < 0.9, lit.mean()
    ys, xs = np.nonzero(lit)
    assert 100 < xs.mean() < 800 and lit[:, :100].mean() < 0.01 and lit[:, -100:].mean() < 0.01
    assert {"trainer", "renderer", "ingest", "tracker", "web", "foxglove"} <= set(rows)
    renderer = status["nodes"]["renderer"]
    assert renderer["state"] == "running" and renderer["heartbeat_age_s"] < 10, renderer
    assert status["trainer"]["iteration"] > 0
    assert wait_until(lambda: not any(pid_alive(p) for p in pids), timeout=10), describe_pids(pids)
