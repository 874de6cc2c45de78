"""Progress bars for long work: rate and ETA on a terminal, a sparse line in logs and CI.

tqdm redraws several times a second; written to a file or a CI log that becomes thousands of
carriage-return fragments. Off a terminal we redraw at most every ``LOG_INTERVAL_S`` seconds.
`wait_with_progress` shows the elapsed time of one long call that reports no progress of its
own (a compiler build).
"""

from __future__ import annotations

import sys
import threading
from collections.abc import Callable
from typing import TypeVar

from tqdm import tqdm

T = TypeVar("T")

LOG_INTERVAL_S = 10.0


def progress(
    iterable=None, *, desc: str, unit: str = "it", total: int | None = None, enabled: bool = True, file=None
) -> tqdm:
    """A tqdm bar (rate and ETA) suited to where its output goes."""
    stream = file or sys.stderr
    interactive = hasattr(stream, "isatty") and stream.isatty()
    return tqdm(
        iterable,
        desc=desc,
        unit=unit,
        total=total,
        disable=not enabled,
        file=stream,
        dynamic_ncols=interactive,
        mininterval=0.1 if interactive else LOG_INTERVAL_S,
        ascii=not interactive,
    )


def wait_with_progress(work: Callable[[], T], *, desc: str, enabled: bool = True, file=None) -> T:
    """``work()``, run in a helper thread while a bar counts the elapsed seconds; its result is
    returned and its exception raised here. Ctrl-C interrupts the wait (the daemon thread is
    abandoned, as the process is about to end)."""
    if not enabled:
        return work()
    outcome: dict[str, object] = {}

    def run() -> None:
        try:
            outcome["value"] = work()
        except BaseException as exc:  # handed to the caller below
            outcome["error"] = exc

    thread = threading.Thread(target=run, name=desc, daemon=True)
    with progress(desc=desc, unit="s", file=file) as bar:
        bar.bar_format = "{desc}: {elapsed} elapsed"
        thread.start()
        while thread.is_alive():
            thread.join(1.0)
            bar.update(1)
    if "error" in outcome:
        raise outcome["error"]
    return outcome["value"]
