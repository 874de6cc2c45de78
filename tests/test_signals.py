"""StopSignals under signals that land anywhere: inside the stop event's own lock (where a plain
threading.Event deadlocked the process for ever) and inside the handler itself."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _run(code: str) -> subprocess.CompletedProcess:
    """``code`` in a fresh process (a deadlock there fails this test by its timeout, not the suite)."""
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
        env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"},
    )


def test_a_signal_inside_the_stop_events_own_lock_stops_instead_of_deadlocking():
    """The main thread is inside the event's set()/wait() (its lock held) when SIGTERM lands: the
    handler, which runs right there, must still set it."""
    result = _run(
        """
        import os, signal, time
        from stg_node.signals import StopSignals
        stop = StopSignals().install()
        with stop.event._cond:  # what Event.set and Event.wait hold for a moment
            os.kill(os.getpid(), signal.SIGTERM)
            for _ in range(200):
                time.sleep(0.001)  # the handler runs between these bytecodes
        print("stopped" if stop.requested else "running", stop.signal_name, flush=True)
        """
    )
    assert result.returncode == 0 and result.stdout.split() == ["stopped", "SIGTERM"], result


def test_a_signal_landing_while_the_handler_runs_is_part_of_the_same_stop():
    """A launcher killed outright can send its node the parent-death signal more than once: the
    ones that land while the first is being handled must neither deadlock nor count as the second
    Ctrl-C that aborts the node's flush."""
    result = _run(
        """
        import os, signal, time
        from stg_node.signals import StopSignals
        def again():  # called from inside the handler: another SIGTERM lands right then
            os.kill(os.getpid(), signal.SIGTERM)
            for _ in range(200):
                time.sleep(0.001)
        stop = StopSignals(on_stop=again).install()
        os.kill(os.getpid(), signal.SIGTERM)
        for _ in range(500):
            time.sleep(0.001)
        print("stopped" if stop.requested else "running", flush=True)
        try:
            os.kill(os.getpid(), signal.SIGTERM)  # a later, separate second signal still aborts
            for _ in range(500):
                time.sleep(0.001)
        except KeyboardInterrupt:
            print("aborted", flush=True)
        """
    )
    assert result.returncode == 0 and result.stdout.split() == ["stopped", "aborted"], result
