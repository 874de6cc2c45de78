"""Helpers for the node tests: nodes in threads, waiting, processes from this checkout."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
from dataclasses import dataclass
from pathlib import Path

from tests.bus.bushelpers import recv_until, wait_until  # one helper for every suite

ROOT = Path(__file__).resolve().parents[2]

__all__ = [
    "ROOT",
    "LaunchRun",
    "LineReader",
    "NodeThread",
    "child_env",
    "ignore_sigint",
    "launch_file",
    "pid_alive",
    "recv_until",
    "run_launch",
    "spawn",
    "taken",
    "wait_until",
]


class NodeThread:
    """A Node executing in a thread (no signal handlers: stopped with node.stop())."""

    def __init__(self, node):
        self.node = node
        self.code: int | None = None
        self.thread = threading.Thread(target=self._run, name=f"node-{node.name}", daemon=True)

    def _run(self) -> None:
        self.code = self.node.execute()

    def __enter__(self) -> NodeThread:
        self.thread.start()
        return self

    def stop(self, timeout: float = 10.0) -> int | None:
        self.node.stop()
        self.thread.join(timeout)
        assert not self.thread.is_alive(), f"node {self.node.name} did not stop"
        return self.code

    def __exit__(self, *exc) -> None:
        if self.thread.is_alive():
            self.stop()


def taken(node, topic: str) -> int:
    """How many messages on ``topic`` (as the node subscribed it) a node running in a thread has
    taken so far. Sending on a keep-last lane one message at a time means waiting for this to
    grow: a second message sent before the node took the first replaces it."""
    full = node.bus.config.topic(node.topic(topic))
    return sum(sub.traffic.messages.get(full, 0) for sub, _names in list(node._subscribers))


def child_env(**extra) -> dict[str, str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "PYTHONUNBUFFERED": "1", "STG_THREADS": "1"}
    env.update(extra)
    return env


def ignore_sigint() -> None:
    """preexec_fn: start the child as a background job would, with SIGINT ignored."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def spawn(args: list[str], **kwargs) -> subprocess.Popen:
    """``python ARGS`` from this checkout, output captured as text."""
    return subprocess.Popen(
        [sys.executable, *args],
        cwd=ROOT,
        env=kwargs.pop("env", None) or child_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        **kwargs,
    )


class LineReader:
    """A spawned process's output read line by line in a thread: a test waiting for a line that
    never comes then fails at its deadline with what was printed, instead of blocking forever in
    ``readline`` while the process lives on silently."""

    def __init__(self, stream):
        self._lines: list[str] = []
        self._thread = threading.Thread(target=self._read, args=(stream,), daemon=True)
        self._thread.start()

    def _read(self, stream) -> None:
        for line in iter(stream.readline, ""):
            self._lines.append(line)

    def text(self) -> str:
        return "".join(self._lines)

    def wait_for(self, found, timeout: float = 60.0) -> bool:
        """True once ``found(text so far)`` holds, False at the deadline."""
        return wait_until(lambda: found(self.text()), timeout=timeout)

    def rest(self, proc: subprocess.Popen, timeout: float = 60.0) -> str:
        """Everything once ``proc`` has exited (its output read to the end)."""
        proc.wait(timeout=timeout)
        self._thread.join(timeout=timeout)
        return self.text()


def describe_pids(pids) -> dict[int, str]:
    """State and command line of each pid still alive: what a failed no-orphans check reports."""
    out = {}
    for pid in pids:
        if pid_alive(pid):
            try:
                stat = Path(f"/proc/{pid}/stat").read_text().split(") ", 1)[1].split()
                cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
                out[pid] = f"state {stat[0]}, parent {stat[1]}: {cmd.strip()}"
            except OSError:
                continue
    return out


def pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # a zombie is dead for our purpose (its parent has not reaped it yet)
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(") ", 1)[1][0] != "Z"
    except OSError:
        return False
    return True


def launch_file(folder: Path, body: str) -> Path:
    """``folder``/t.yaml: a launch file on a private ipc bus in ``folder`` (arg ``bus``), then ``body``
    (YAML: ``nodes:``, ``env:`` ...; dedented)."""
    import textwrap

    path = folder / "t.yaml"
    path.write_text(
        f'args: {{bus: "ipc://{folder}/bus"}}\nbus: {{url: $(arg bus)}}\n' + textwrap.dedent(body)
    )
    return path


@dataclass
class LaunchRun:
    code: int  # stg-launch's exit code
    log: str  # its output (every node's lines, prefixed)
    client_code: int | None = None  # tools/robot_client.py's, when one ran
    client_output: str = ""


def run_launch(
    launch_args: list[str],
    *,
    timeout: float,
    client_args: list[str] | None = None,
    client_timeout: float = 300.0,
) -> LaunchRun:
    """``stg-launch LAUNCH_ARGS --no-color`` from this checkout, started as a background job would be
    (SIGINT ignored), with ``tools/robot_client.py CLIENT_ARGS`` beside it when given; waits for the
    client, then for the launch to end on its own (a SIGINT after ``timeout`` s)."""
    launch = spawn(["-m", "stg_node.cli.launch", *launch_args, "--no-color"], preexec_fn=ignore_sigint)
    output: list[str] = []
    reader = threading.Thread(target=lambda: output.extend(iter(launch.stdout.readline, "")), daemon=True)
    reader.start()
    run = LaunchRun(code=-1, log="")
    try:
        if client_args is not None:
            client = spawn([str(ROOT / "tools" / "robot_client.py"), *client_args])
            run.client_output, _ = client.communicate(timeout=client_timeout)
            run.client_code = client.returncode
            if client.returncode != 0:
                return run
        launch.wait(timeout=timeout)
    finally:
        if launch.poll() is None:
            launch.send_signal(signal.SIGINT)
            launch.wait(timeout=60)
        reader.join(5)
        run.code, run.log = launch.returncode, "".join(output)
    return run
