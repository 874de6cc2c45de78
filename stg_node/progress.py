"""Progress bars for long work: rate and ETA on a terminal, a sparse line in logs and CI.

tqdm redraws several times a second; written to a file or a CI log that becomes thousands of
carriage-return fragments. Off a terminal we redraw at most every ``LOG_INTERVAL_S`` seconds.
"""

from __future__ import annotations

import sys

from tqdm import tqdm

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
