"""The launch guard: a small process that outlives a launcher killed outright and ends what it left.

A launcher stops its nodes itself on Ctrl-C, SIGTERM or any error. Killed outright (SIGKILL, the
OOM killer) it can do nothing, and what reaches its children then is only ``PR_SET_PDEATHSIG``
(stg_node.launch.process), which is not enough: it reaches only the launcher's direct children,
never what they started themselves (a shell script's programs, a node's helper process), and it
misses a child forked in the instant before the launcher died (the death signal is set in the
child after the fork; the child then checks its parent, but a grandchild it has not started yet
is all it can protect).

So the launcher starts this guard first, in its own session (a Ctrl-C or a kill of the
launcher's process group does not reach it), reading a pipe whose only writer is the launcher:

    +PGID GRACE     a child's process group to stop if the launcher dies (GRACE: seconds after
                    SIGTERM before SIGKILL)
    -PGID           that group is finished with (the launcher stopped it)
    bye             the launcher ends normally: exit at once

End of file without ``bye`` means the launcher died: the guard sends SIGTERM to every group it
holds (nodes flush what they owe, as on a launcher's SIGTERM), SIGKILL to the groups still
populated after their grace, and exits. Standard library only: it starts in tens of milliseconds.

Run as a file (``python guard.py LAUNCHER_PID``), never imported by the launcher's children.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

POLL_S = 0.05


class Guard:
    """The launcher's end: starts the guard process and tells it which groups to watch."""

    def __init__(self) -> None:
        read_end, self._write_end = os.pipe()  # both non-inheritable: no node holds the pipe
        try:
            self.proc = subprocess.Popen(
                [sys.executable, "-I", "-S", os.path.abspath(__file__), str(os.getpid())],
                stdin=read_end,
                stdout=subprocess.DEVNULL,
                start_new_session=True,
            )
        except BaseException:
            os.close(self._write_end)
            raise
        finally:
            os.close(read_end)

    def _send(self, line: str) -> None:
        try:
            os.write(self._write_end, (line + "\n").encode())
        except OSError:  # the guard is gone: nothing to tell
            pass

    def watch(self, pgid: int, grace_s: float) -> None:
        self._send(f"+{pgid} {grace_s:g}")

    def forget(self, pgid: int) -> None:
        self._send(f"-{pgid}")

    def close(self) -> None:
        """The launch ended normally: the guard exits without touching anything."""
        self._send("bye")
        os.close(self._write_end)
        try:
            self.proc.wait(timeout=5.0)
        except subprocess.TimeoutExpired:  # pragma: no cover - it only reads a pipe
            self.proc.kill()
            self.proc.wait()


def group_alive(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # the group id now belongs to someone else's processes: not ours
        return False
    return True


def stop_groups(groups: dict[int, float], say) -> None:
    """SIGTERM to every group, SIGKILL to those still there after their grace."""
    started = time.monotonic()
    for pgid in groups:
        try:
            os.killpg(pgid, signal.SIGTERM)
        except (ProcessLookupError, PermissionError):
            pass
    waiting = {pgid: started + grace for pgid, grace in groups.items()}
    while waiting:
        now = time.monotonic()
        for pgid, deadline in list(waiting.items()):
            if not group_alive(pgid):
                del waiting[pgid]
            elif now >= deadline:
                say(f"process group {pgid} still running {now - started:.1f} s after SIGTERM: SIGKILL")
                try:
                    os.killpg(pgid, signal.SIGKILL)
                except (ProcessLookupError, PermissionError):
                    pass
                del waiting[pgid]
        time.sleep(POLL_S)


def main(argv: list[str]) -> int:
    launcher = argv[1] if len(argv) > 1 else "?"
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # only the pipe decides when the guard acts

    def say(text: str) -> None:
        try:
            sys.stderr.write(f"[stg-launch guard] {text}\n")
            sys.stderr.flush()
        except (OSError, ValueError):  # the launcher's terminal may be gone too
            pass

    groups: dict[int, float] = {}
    for raw in sys.stdin.buffer:
        line = raw.decode("ascii", "replace").strip()
        if line == "bye":
            return 0
        try:
            if line.startswith("+"):
                pgid, grace = line[1:].split()
                groups[int(pgid)] = float(grace)
            elif line.startswith("-"):
                groups.pop(int(line[1:]), None)
        except ValueError:
            say(f"ignoring a garbled line: {line!r}")
    live = {pgid: grace for pgid, grace in groups.items() if group_alive(pgid)}
    if live:
        say(f"launcher (pid {launcher}) is gone: stopping {len(live)} process group(s) it left")
        stop_groups(live, say)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
