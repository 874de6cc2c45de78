"""The single place that decides how many CPU threads torch and OpenCV use.

On a small shared machine (2 cores, other nodes busy) torch with 2 intra-op threads
can be several times slower than with 1, because its workers spin and contend with
the other processes. The default below was chosen by ``tools/bench_threads.py``
(figures in docs/BENCHMARKS.md); override it with ``STG_THREADS`` or ``--threads``.
"""

from __future__ import annotations

import logging
import os

ENV_THREADS = "STG_THREADS"
# Measured on the 2-core reference machine: see docs/BENCHMARKS.md, "Thread count".
DEFAULT_THREADS = 1

log = logging.getLogger(__name__)


def parse_threads(value: str | int | None) -> int:
    """Turn STG_THREADS / --threads into a positive count; 0 or 'all' means every core."""
    if value is None or value == "":
        return DEFAULT_THREADS
    text = str(value).strip().lower()
    if text in ("0", "all"):
        return os.cpu_count() or 1
    try:
        count = int(text)
    except ValueError:
        raise ValueError(f"{ENV_THREADS} must be a positive integer, 0 or 'all'; got {value!r}") from None
    if count < 0:
        raise ValueError(f"{ENV_THREADS} must be a positive integer, 0 or 'all'; got {value!r}")
    return count or (os.cpu_count() or 1)


def resolve_threads(threads: str | int | None = None) -> int:
    """The thread count to use: an explicit value wins over STG_THREADS, then the default."""
    return parse_threads(threads if threads is not None else os.environ.get(ENV_THREADS))


def configure_threads(threads: str | int | None = None) -> int:
    """Apply the thread count to torch (intra-op, and OpenMP in our extensions) and OpenCV.

    Safe to call more than once. Returns the count applied.
    """
    count = resolve_threads(threads)
    import torch

    torch.set_num_threads(count)
    try:
        # Only settable before any inter-op work has started; later calls keep the first value.
        torch.set_num_interop_threads(count)
    except RuntimeError:
        pass
    try:
        import cv2
    except ImportError:  # pragma: no cover - cv2 is a hard dependency, but a thin install may lack it
        pass
    else:
        cv2.setNumThreads(count)
    log.debug("using %d CPU thread(s) for torch and OpenCV", count)
    return count
