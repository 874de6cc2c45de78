"""Ctrl-C and SIGTERM for every stg_node process: installed explicitly, never inherited.

A process started in the background by a non-interactive shell, under ``nohup``, or by a
supervisor that ignores SIGINT inherits SIGINT *ignored*, and Python then never installs its
own KeyboardInterrupt handler: Ctrl-C (or a launcher's SIGINT) does nothing. So every entry
point installs its handlers itself, through this module:

- :func:`interrupt_on_signals`: SIGINT and SIGTERM raise ``KeyboardInterrupt`` (CLIs that
  block in a loop and clean up in ``finally``/``with``).
- :class:`StopSignals`: the first SIGINT/SIGTERM only sets an event (a node finishes its
  current step and flushes what it owes); a second one raises ``KeyboardInterrupt``.

A Python signal handler runs in the main thread between two bytecodes, wherever that thread is,
including inside the handler itself (a second signal) or inside ``threading.Event.set``/``wait``
of the very event the handler sets. ``threading.Event``'s lock is not re-entrant, so that was a
deadlock: a node whose launcher was killed (the kernel's parent-death signal can arrive several
times as the launcher's threads exit) hung for ever in its handler and survived the launch. The
stop event here takes a re-entrant lock, and a signal that lands while the handler runs is part
of the same stop.

Both restore the previous handlers on exit and do nothing outside the main thread (Python only
lets the main thread install signal handlers).
"""

from __future__ import annotations

import contextlib
import signal
import threading

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def _in_main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


def _raise_interrupt(signum, frame):
    raise KeyboardInterrupt


@contextlib.contextmanager
def interrupt_on_signals():
    """While active, SIGINT and SIGTERM raise KeyboardInterrupt in the main thread, even where
    SIGINT was inherited as ignored. Restores the previous handlers on exit."""
    if not _in_main_thread():
        yield
        return
    previous = {sig: signal.signal(sig, _raise_interrupt) for sig in STOP_SIGNALS}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


class StopEvent(threading.Event):
    """A ``threading.Event`` that a signal handler may set while the main thread is inside this
    event's own ``set``/``wait`` (its lock is re-entrant; see the module docstring)."""

    def __init__(self):
        super().__init__()
        self._cond = threading.Condition(threading.RLock())


class StopSignals:
    """Graceful stop on the first SIGINT/SIGTERM (sets :attr:`event`), KeyboardInterrupt on the next.

        with StopSignals() as stop:
            while not stop.requested:
                work()                          # finishes the step in hand, then the loop ends

    ``on_stop`` (optional) is called from the handler on the first signal, e.g. to wake a loop.
    """

    def __init__(self, on_stop=None):
        self.event = StopEvent()
        self.signal_name: str | None = None
        self._on_stop = on_stop
        self._previous: dict = {}
        self._handling = False  # a signal handler of ours is running (further signals join it)

    @property
    def requested(self) -> bool:
        return self.event.is_set()

    def request(self, reason: str = "requested") -> None:
        """Ask for a stop from code (same effect as the first signal)."""
        if not self.event.is_set():
            self.signal_name = self.signal_name or reason
            self.event.set()
            if self._on_stop is not None:
                self._on_stop()

    def _handle(self, signum, frame):
        if self._handling:  # landed while this handler runs: the same stop, already under way
            return
        if self.event.is_set():  # the second signal: stop now
            raise KeyboardInterrupt
        self._handling = True
        try:
            self.signal_name = signal.Signals(signum).name
            self.request(self.signal_name)
        finally:
            self._handling = False

    def install(self) -> StopSignals:
        if _in_main_thread() and not self._previous:
            self._previous = {sig: signal.signal(sig, self._handle) for sig in STOP_SIGNALS}
        return self

    def restore(self) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous = {}

    def __enter__(self) -> StopSignals:
        return self.install()

    def __exit__(self, *exc) -> None:
        self.restore()
