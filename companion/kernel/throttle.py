"""Rate limits for reports about bad input: a flood of junk must not become a flood of log lines or events."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass


@dataclass(slots=True)
class _Window:
    start_s: float
    used: int = 0
    suppressed: int = 0


class Throttle:
    """At most ``burst`` reports per ``window_s`` and key; the rest are counted, not reported.

    ``allow(key)`` returns None when the report must be left out, otherwise how many reports of that key
    were left out since the last one that went through (say so in it: "... and 1999 more").

    Args:
        window_s: length of a window, s (monotonic clock).
        burst: reports allowed per window and key.
        now_s: the clock (monotonic, s).
        max_keys: bound on the keys remembered (an attacker choosing keys cannot grow memory).
    """

    def __init__(
        self,
        window_s: float = 10.0,
        burst: int = 3,
        now_s: Callable[[], float] = time.monotonic,
        max_keys: int = 256,
    ) -> None:
        if window_s <= 0 or burst < 1:
            raise ValueError("need window_s > 0 and burst >= 1")
        self.window_s = window_s
        self.burst = burst
        self._now_s = now_s
        self._max_keys = max_keys
        self._windows: dict[str, _Window] = {}

    def allow(self, key: str) -> int | None:
        """None: leave this report out; else the number left out since the last report of ``key``."""
        now = self._now_s()
        w = self._windows.get(key)
        if w is None or now - w.start_s >= self.window_s:
            suppressed = w.suppressed if w is not None else 0
            if w is None and len(self._windows) >= self._max_keys:
                oldest = min(self._windows, key=lambda k: self._windows[k].start_s)
                del self._windows[oldest]
            self._windows[key] = _Window(now, used=1)
            return suppressed
        if w.used < self.burst:
            w.used += 1
            suppressed, w.suppressed = w.suppressed, 0
            return suppressed
        w.suppressed += 1
        return None


def and_more(suppressed: int) -> str:
    """The tail of a throttled line: ``" (and 12 more)"`` or nothing."""
    return f" (and {suppressed} more)" if suppressed else ""
