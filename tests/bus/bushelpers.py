"""Helpers shared by the bus tests (fixtures are in conftest.py)."""

from __future__ import annotations

import subprocess
import threading
import time

import msgpack
import numpy as np
import zmq

from stg_node.bus import Ack, BodyPose, Frame, GaussianSnapshot, RenderedImage, ViewRequest
from stg_node.bus.config import free_tcp_base_port
from stg_node.bus.messages import NodeStatus, TrainerMetrics

free_base_port = free_tcp_base_port  # the library helper, under the tests' short name


def wait_until(predicate, timeout: float = 5.0, step: float = 0.01) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(step)
    return predicate()


def expect_first_line(proc: subprocess.Popen, text: str, timeout: float = 60.0) -> str:
    """The first line ``proc`` prints (text-mode stdout), asserted to hold ``text``. Read in a thread
    so that a child hanging silently fails the test at ``timeout`` s with its output instead of
    blocking in ``readline``; on failure the child is killed. Reads that one line only (unlike
    tests/nodes' LineReader), so the caller can still ``communicate`` with the child afterwards."""
    got: list[str] = []
    reader = threading.Thread(target=lambda: got.append(proc.stdout.readline()), daemon=True)
    reader.start()
    reader.join(timeout)
    timed_out = reader.is_alive()
    if not timed_out and text in got[0]:
        return got[0]
    proc.kill()
    reader.join(30)  # the kill closes the pipe: readline returns
    out, err = proc.communicate(timeout=30)
    waited = f"printed no full line in {timeout:g} s" if timed_out else "printed"
    raise AssertionError(
        f"{proc.args} {waited} {''.join(got)!r} (expected {text!r}); "
        f"then stdout {out!r}, stderr {err!r}, exit {proc.returncode}"
    )


def recv_until(sub, predicate, timeout: float = 30.0, seen: list | None = None):
    """Read ``sub`` as a subscriber would until a message satisfies ``predicate``: that message,
    or None after ``timeout`` s. Every message read goes to ``seen`` when given (what came before).

    A test that waits on another process waits for the message it asserts on, never for the
    first message or for whatever arrives in a fixed time: a backlog or a loaded machine makes
    those an older message."""
    deadline = time.monotonic() + timeout
    while (left := deadline - time.monotonic()) > 0:
        msg = sub.recv(timeout=min(left, 0.5))
        if msg is None:
            continue
        if seen is not None:
            seen.append(msg)
        if predicate(msg):
            return msg
    return None


def keep_last_holds(sub, topic: str, seq: int) -> bool:
    """Whether a subscriber's keep-last reader thread has taken message ``seq`` (or a later one) of
    ``topic`` off its socket; every message sent before it on that lane has then reached it too."""
    for channel in sub._channel_list:
        if not channel.keep_last:
            continue
        with channel._lock:
            frames = channel._mailbox.get(topic.encode())
        if frames is not None and msgpack.unpackb(frames[1].bytes)["seq"] >= seq:
            return True
    return False


def recv_raw(sock: zmq.Socket, timeout_ms: int = 30_000) -> list:
    assert sock.poll(timeout_ms), "nothing received in time"
    return sock.recv_multipart(copy=False)


# --- sample messages, one per type, deterministic -------------------------------------------------


def sample_messages(seed: int = 0) -> dict[str, object]:
    rng = np.random.default_rng(seed)
    h, w = 6, 8
    K = np.array([[500.0, 0, w / 2], [0, 500.0, h / 2], [0, 0, 1]])
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    t = rng.normal(size=3)
    return {
        "Frame": Frame(
            index=7,
            time=0.25,
            camera_id="cam0",
            image=rng.integers(0, 256, (h, w, 3), dtype=np.uint8),
            mask=(rng.random((h, w)) > 0.5).astype(np.uint8) * 255,
            depth=rng.random((h, w)).astype(np.float32),
            K=K,
            R=R,
            t=t,
        ),
        "BodyPose": BodyPose(
            frame_seq=3,
            frame_index=7,
            time=0.25,
            confidence=0.9,
            poses=rng.normal(size=(24, 3)).astype(np.float32),
            Rh=rng.normal(size=3).astype(np.float32),
            Th=rng.normal(size=3).astype(np.float32),
            betas=rng.normal(size=10).astype(np.float32),
        ),
        "GaussianSnapshot": GaussianSnapshot(
            format="stg-avatar/1",
            model_version=4,
            iteration=1200,
            num_gaussians=50,
            meta={"sh_degree": 0.0, "t_max": 2.5},
            arrays={
                "xyz": rng.normal(size=(50, 3)).astype(np.float32),
                "rotation": rng.normal(size=(50, 4)).astype(np.float32),
                "mlp.0.weight": rng.normal(size=(16, 8)).astype(np.float16),
            },
        ),
        "ViewRequest": ViewRequest(
            request_id=5,
            width=w,
            height=h,
            follow_live=False,
            poses=np.zeros((24, 3), np.float32),
            K=K,
            R=R,
            t=t,
        ),
        "RenderedImage": RenderedImage(
            request_id=5,
            request_src="robot",
            pose_seq=-1,
            snapshot_version=4,
            source_stamp_ns=123,
            render_ms=3.5,
            latency_ms=9.0,
            image=rng.integers(0, 256, (h, w, 3), dtype=np.uint8),
            alpha=rng.integers(0, 256, (h, w), dtype=np.uint8),
            K=K,
            R=R,
            t=t,
        ),
        "TrainerMetrics": TrainerMetrics(
            iteration=100, loss=float("nan"), losses={"l1": 0.1, "ssim": 0.2}, psnr=24.5, it_per_s=3.0
        ),
        "NodeStatus": NodeStatus(node="tracker", published={"body/pose": 10}, drops={"lost": 2}),
        "Ack": Ack(msg_topic="rig1/camera/frame", msg_seq=41, msg_src="ingest"),
    }


def assert_same_message(a, b) -> None:
    """Field-by-field equality of two messages (arrays exactly, NaN equal to NaN)."""
    assert type(a) is type(b)
    for s in a.SPEC.scalars:
        va, vb = getattr(a, s.name), getattr(b, s.name)
        if isinstance(va, float) and va != va:
            assert vb != vb, s.name
        else:
            assert va == vb, s.name
    for spec in a.SPEC.arrays:
        va, vb = getattr(a, spec.name), getattr(b, spec.name)
        if va is None:
            assert vb is None, spec.name
        else:
            np.testing.assert_array_equal(np.asarray(va, dtype=spec.np_dtype), vb, err_msg=spec.name)
    if a.SPEC.array_set is not None:
        ma, mb = getattr(a, a.SPEC.array_set.name), getattr(b, b.SPEC.array_set.name)
        assert ma.keys() == mb.keys()
        for name in ma:
            np.testing.assert_array_equal(ma[name], mb[name], err_msg=name)
