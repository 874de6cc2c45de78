"""Clean shutdown: Ctrl-C / SIGTERM end every bus program promptly; closing never waits on peers."""

from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
import zmq
from bushelpers import free_base_port

from stg_node.bus import Bus, BusConfig, Frame, Subscriber

ROOT = Path(__file__).resolve().parents[2]


def _ignore_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # as a shell does for a job started with '&'


def _default_sigint() -> None:
    # A foreground start, even when the suite itself runs as a background job (which would hand
    # the child SIGINT ignored, and Python then installs no KeyboardInterrupt handler).
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _spawn(args: list[str], ready: str, background: bool = False) -> subprocess.Popen:
    """Start a Python program from this checkout and wait (at most 60 s) until it prints ``ready``.

    ``background``: start it with SIGINT ignored, as a non-interactive shell starts ``cmd &``."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(
        [sys.executable, *args],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        preexec_fn=_ignore_sigint if background else _default_sigint,
    )
    deadline = time.monotonic() + 60
    seen = b""
    while (remaining := deadline - time.monotonic()) > 0:
        readable, _, _ = select.select([proc.stdout], [], [], remaining)  # never block past the deadline
        chunk = os.read(proc.stdout.fileno(), 65536) if readable else b""
        if not chunk:
            break
        seen += chunk
        if ready.encode() in seen:
            proc.startup_output = seen.decode(errors="replace")
            return proc
    proc.kill()
    proc.communicate()
    raise AssertionError(f"never printed {ready!r}: {seen.decode(errors='replace')}")


def _stop(proc: subprocess.Popen, sig: int, within: float = 30.0) -> tuple[int, str, float]:
    start = time.monotonic()
    proc.send_signal(sig)
    try:
        out, _ = proc.communicate(timeout=within)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
        raise AssertionError(f"did not stop within {within} s after signal {sig}: {out!r}") from None
    return proc.returncode, out.decode(errors="replace"), time.monotonic() - start


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_broker_cli_stops_cleanly(ipc_dir, sig):
    url = f"ipc://{ipc_dir}/bus"
    proc = _spawn(["-m", "stg_node.cli.broker", "--bus", url, "--status-period", "0.1"], "serving", True)
    code, out, took = _stop(proc, sig)
    assert code == 0, out
    assert "Traceback" not in out
    assert os.listdir(ipc_dir) == []  # no stale socket files


def test_broker_cli_still_takes_a_positional_url_with_a_warning(ipc_dir):
    url = f"ipc://{ipc_dir}/bus"
    proc = _spawn(["-m", "stg_node.cli.broker", url, "--status-period", "0.1"], f"serving {url}")
    code, out, _ = _stop(proc, signal.SIGINT)
    assert code == 0, out
    assert "deprecated; use --bus URL" in proc.startup_output


@pytest.mark.parametrize("background", [False, True])
def test_topic_hz_stops_on_ctrl_c(ipc_url, background):
    from stg_node.bus import Broker

    with Broker(ipc_url, status_period_s=0):
        args = ["-m", "stg_node.cli.topic", "--bus", ipc_url, "hz", "body/pose"]
        proc = _spawn(args, "subscribed", background)
        code, out, _ = _stop(proc, signal.SIGINT)
    assert code == 0 and "Traceback" not in out


NODE = textwrap.dedent(
    """
    import sys
    from stg_node.bus import Bus
    with Bus(sys.argv[1], node="looping", heartbeat_s=0.1) as bus:
        frames = bus.subscribe("camera/frame", "body/pose")
        try:
            print("ready", flush=True)  # and straight into the loop
            for msg in frames:      # blocks: only Ctrl-C gets us out
                pass
        except KeyboardInterrupt:
            pass
    print("closed", flush=True)
    """
)


def test_a_node_blocked_in_its_message_loop_stops_on_ctrl_c(ipc_url, tmp_path):
    script = tmp_path / "node.py"
    script.write_text(NODE)
    proc = _spawn([str(script), ipc_url], "ready")  # no broker at all: connects, waits
    code, out, _took = _stop(proc, signal.SIGINT)  # _stop fails if it does not end
    assert code == 0 and "closed" in out, out


def test_closing_with_undeliverable_messages_does_not_wait():
    """1 MB frames queued for a tcp peer that never answers: LINGER 0 drops them at once."""
    config = BusConfig(url=f"tcp://127.0.0.1:{free_base_port()}")  # nothing listens there
    frame = Frame(index=0, image=np.zeros((512, 683, 3), np.uint8), K=np.eye(3), R=np.eye(3), t=np.zeros(3))
    bus = Bus(config, node="lonely", heartbeat_s=0.05)
    sub = bus.subscribe("camera/frame")
    for i in range(20):
        frame.index = i
        bus.publish(frame, "bench/frames")
    assert sub.recv(timeout=0.1) is None
    sockets = [bus.publisher._sockets[name] for name in bus.publisher._sockets]
    assert all(sock.getsockopt(zmq.LINGER) == 0 for sock in sockets)  # what makes close not wait
    bus.close()  # with LINGER -1 this would block for ever on the 20 undeliverable frames
    assert all(sock.closed for sock in sockets)


def test_subscriber_close_is_prompt_and_idempotent(ipc_url):
    sub = Subscriber(BusConfig(url=ipc_url), ["camera/frame", "body/pose"])  # a keep-last thread and a socket
    sub.close()  # joins its keep-last thread; a thread that never stops would hang it
    sub.close()
    assert all(sock.closed for sock in sub.sockets)
