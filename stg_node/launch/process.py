"""One supervised child process: started in its own process group, output pumped with its name.

Each process is the leader of a new session (``start_new_session``), so a terminal's Ctrl-C
reaches only the launcher, which stops the nodes in order, and so signals sent to the group
also reach anything the node started itself. When a process ends, what it left in its group
is killed (a respawned node must not find its predecessor's helpers still running).

A launcher killed outright (SIGKILL) cannot stop anything; three things stand in for it. The
child gets ``PR_SET_PDEATHSIG`` (SIGTERM when the launcher dies), and then checks that its
parent is still the launcher, since a launcher that died between the fork and that call would
never send it; nodes also watch their parent pid (stg_node.nodes.runtime); and the launch guard
(:mod:`.guard`), a separate process told of every group, stops the groups (grandchildren
included, which the death signal never reaches) once the launcher is gone. Nothing a node
starts can outlive the launch.
"""

from __future__ import annotations

import ctypes
import functools
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

from stg_node.launch.guard import Guard

PR_SET_PDEATHSIG = 1
try:  # resolved here, not in the child: preexec_fn must not import or allocate much
    _prctl = ctypes.CDLL(None, use_errno=True).prctl if sys.platform.startswith("linux") else None
except (OSError, AttributeError):  # pragma: no cover - not glibc
    _prctl = None


def _prepare_child(launcher_pid: int, nice: int = 0) -> None:
    """preexec_fn (in the child, between fork and exec): SIGTERM when the launcher dies, and exit
    now if it already has (then the death signal would never come). ``nice``: lower the child's CPU
    priority before exec, so every thread it starts inherits it (Linux keeps a niceness per thread:
    setpriority on the pid from outside would miss threads already started)."""
    if _prctl is not None:
        _prctl(PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0)
    if os.getppid() != launcher_pid:
        os._exit(1)
    if nice:
        os.nice(nice)


_COLORS = (36, 33, 32, 35, 34, 91, 92, 93, 94, 95, 96)


class OutputSink:
    """Where every process's output goes: one stream, whole lines, each prefixed ``[name] ``."""

    def __init__(self, stream: TextIO | None = None, log_dir: Path | None = None, color: bool | None = None):
        self.stream = stream or sys.stdout
        self.log_dir = log_dir
        self.color = self.stream.isatty() if color is None else color
        self._lock = threading.Lock()
        self._colors: dict[str, int] = {}
        self._files: dict[str, TextIO] = {}
        if log_dir is not None:
            log_dir.mkdir(parents=True, exist_ok=True)

    def prefix(self, name: str) -> str:
        if not self.color:
            return f"[{name}] "
        code = self._colors.setdefault(name, _COLORS[len(self._colors) % len(_COLORS)])
        return f"\033[{code}m[{name}]\033[0m "

    def line(self, name: str, text: str) -> None:
        with self._lock:
            try:
                self.stream.write(self.prefix(name) + text + "\n")
                self.stream.flush()
            except (OSError, ValueError):  # a closed terminal must not kill the launcher
                pass
            if self.log_dir is not None:
                file = self._files.get(name)
                if file is None:
                    file = self._files[name] = open(self.log_dir / f"{name.replace('/', '.')}.log", "a")  # noqa: SIM115
                file.write(text + "\n")
                file.flush()

    def close(self) -> None:
        with self._lock:
            for file in self._files.values():
                file.close()
            self._files.clear()


@dataclass
class RunRecord:
    """One run of a process."""

    pid: int
    started: float  # time.monotonic()
    ended: float | None = None
    returncode: int | None = None


@dataclass
class ChildProcess:
    """A started process, its output pumps and its runs."""

    name: str
    argv: list[str]
    env: dict[str, str]
    cwd: str | None
    sink: OutputSink
    guard: Guard | None = None  # told of each run's process group (stops it if the launcher dies)
    grace_s: float = 5.0  # for the guard: SIGTERM to SIGKILL
    standby: bool = False  # a standby copy: stdin is a pipe it waits on for "go" (stg_node.cli.node)
    nice: int = 0  # CPU niceness added in the child (NodeSpec.nice)
    popen: subprocess.Popen | None = None
    runs: list[RunRecord] = field(default_factory=list)
    _pumps: list[threading.Thread] = field(default_factory=list)

    def start(self) -> int:
        self.popen = subprocess.Popen(
            self.argv,
            env=self.env,
            cwd=self.cwd,
            stdin=subprocess.PIPE if self.standby else subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            start_new_session=True,
            preexec_fn=functools.partial(_prepare_child, os.getpid(), self.nice),
        )
        self.runs.append(RunRecord(self.popen.pid, time.monotonic()))
        if self.guard is not None:
            self.guard.watch(self.popen.pid, self.grace_s)
        self._pumps = [
            threading.Thread(target=self._pump, args=(stream,), name=f"out-{self.name}", daemon=True)
            for stream in (self.popen.stdout, self.popen.stderr)
        ]
        for pump in self._pumps:
            pump.start()
        return self.popen.pid

    def _pump(self, stream) -> None:
        with stream:
            for raw in iter(stream.readline, b""):
                self.sink.line(self.name, raw.decode("utf-8", "replace").rstrip("\r\n"))

    # -- standby copies -------------------------------------------------------------------------------

    def hand_over(self, respawns: int, name: str) -> bool:
        """Tell a standby copy to take over as respawn ``respawns`` of node ``name``; False if it
        cannot hear it. Its output carries ``name`` before the word is sent: the copy answers at
        once ("taking over"), and a prefix changed only afterwards raced that line."""
        if not self.standby or not self.running:
            return False
        standby_name, self.name = self.name, name
        try:
            self.popen.stdin.write(f"go {respawns}\n".encode())
            self.popen.stdin.flush()
            return True
        except (OSError, ValueError):  # it died meanwhile
            self.name = standby_name
            return False

    def dismiss(self) -> None:
        """A standby copy that is not needed: end of file on its stdin, and it exits."""
        if self.standby and self.popen is not None and self.popen.stdin is not None:
            try:
                self.popen.stdin.close()
            except OSError:
                pass

    def adopt(self, spare: ChildProcess) -> int:
        """Make ``spare`` (a standby copy that was just handed over) this node's current run."""
        spare.name = self.name  # already so since hand_over; a copy adopted otherwise gets it here
        self.popen, self._pumps = spare.popen, spare._pumps
        self.runs.append(RunRecord(self.popen.pid, time.monotonic()))
        return self.popen.pid

    @property
    def pid(self) -> int | None:
        return self.popen.pid if self.popen is not None else None

    @property
    def running(self) -> bool:
        return self.popen is not None and self.popen.poll() is None

    def poll(self) -> int | None:
        """The exit code once the process has ended (recorded once), else None."""
        if self.popen is None:
            return None
        code = self.popen.poll()
        if code is not None and self.runs and self.runs[-1].returncode is None:
            self.runs[-1].returncode = code
            self.runs[-1].ended = time.monotonic()
            self.signal_group(signal.SIGKILL)  # what it started and left behind
            if self.guard is not None:
                self.guard.forget(self.popen.pid)
            for pump in self._pumps:  # let the last lines out before anyone reports the exit
                pump.join(timeout=1.0)
        return code

    def signal_group(self, sig: int) -> bool:
        """Send ``sig`` to the process group; False when nothing is left to signal."""
        if self.popen is None:
            return False
        try:
            os.killpg(self.popen.pid, sig)
            return True
        except ProcessLookupError:
            return False
        except PermissionError:  # pragma: no cover - the group was reused by someone else's process
            return False
