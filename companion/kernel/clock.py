"""Clocks: pure cores take time as an argument; the edges get it from one of these.

``MonotonicClock`` is the real one (never ``time.time()``: wall-clock steps would corrupt rates and
timeouts). ``ManualClock`` is for tests and the lockstep simulation, where time only moves when told.
"""

from __future__ import annotations

import asyncio
import time
from typing import Protocol


class Clock(Protocol):
    """Source of time in seconds on a monotonic timeline."""

    def now_s(self) -> float: ...

    async def sleep_until(self, t_s: float) -> None: ...


class MonotonicClock:
    """Real time from ``time.monotonic``."""

    def now_s(self) -> float:
        return time.monotonic()

    async def sleep_until(self, t_s: float) -> None:
        delay_s = t_s - time.monotonic()
        await asyncio.sleep(max(0.0, delay_s))


class ManualClock:
    """Time that advances only through :meth:`advance`; sleepers wake when their time has come."""

    def __init__(self, start_s: float = 0.0) -> None:
        self._now_s = start_s

    def now_s(self) -> float:
        return self._now_s

    def advance(self, dt_s: float) -> None:
        if dt_s < 0:
            raise ValueError(f"time cannot go backwards (dt_s={dt_s})")
        self._now_s += dt_s

    def set(self, t_s: float) -> None:
        if t_s < self._now_s:
            raise ValueError(f"time cannot go backwards ({t_s} < {self._now_s})")
        self._now_s = t_s

    async def sleep_until(self, t_s: float) -> None:
        # Polling with sleep(0) is deliberate: whoever drives the clock calls advance() from the same
        # loop, and an Event per sleeper would add bookkeeping for no gain in tests.
        while self._now_s < t_s:  # noqa: ASYNC110
            await asyncio.sleep(0)
