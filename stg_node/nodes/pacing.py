"""A render-rate cap that does not drop frames arriving at the cap's own rate.

The renderer renders at most ``max_rate_hz`` images a second on new poses. A cap checked as "at
least 1/rate since the last render" drops every pose that arrives a little early: poses from a
30 fps camera arrive 33 ms apart on average but jitter by a few ms (capture, tracking, transport),
so under a 30 Hz cap about a third of them came early, waited for the next poll and were replaced
by the next pose (the live pipeline rendered 21.7 of 30 poses a second on an idle box, render
17 ms). A token bucket caps the average rate the same way and absorbs the jitter: a credit of
one render accrues every 1/rate seconds, up to ``burst`` credits, and a render spends one.
"""

from __future__ import annotations

BURST = 2.0  # credits held at most: one early pose renders at once, the average stays at the rate


class Pacer:
    """Token bucket: at most ``rate_hz`` on average, ``burst`` at once."""

    def __init__(self, rate_hz: float, burst: float = BURST, now: float = 0.0):
        if rate_hz <= 0 or burst < 1:
            raise ValueError(f"Pacer needs rate_hz > 0 and burst >= 1, got {rate_hz}, {burst}")
        self.rate = float(rate_hz)
        self.burst = float(burst)
        self.credit = 1.0  # the first render goes at once
        self.at = now

    def _refill(self, now: float) -> None:
        self.credit = min(self.burst, self.credit + max(0.0, now - self.at) * self.rate)
        self.at = now

    def ready(self, now: float) -> bool:
        self._refill(now)
        return self.credit >= 1.0

    def take(self, now: float) -> None:
        self._refill(now)
        self.credit -= 1.0

    def wait_s(self, now: float) -> float:
        """Seconds until the next render may go (0 if it may now)."""
        self._refill(now)
        return max(0.0, (1.0 - self.credit) / self.rate)
