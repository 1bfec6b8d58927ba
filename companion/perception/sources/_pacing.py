"""Real-time pacing of recorded frames by their stamps, on an injected clock."""

from __future__ import annotations

import asyncio

from companion.kernel.clock import Clock, MonotonicClock


class Pacer:
    """Releases frames at the pace their stamps say (``realtime``), or as fast as they are read.

    The first frame fixes the offset between the recording's stamps and the clock; later frames wait
    until ``stamp_s + offset``. A slow consumer is never made to catch up by skipping frames here.
    """

    def __init__(self, *, realtime: bool, clock: Clock | None = None) -> None:
        self.realtime = realtime
        self._clock: Clock = clock if clock is not None else MonotonicClock()
        self._offset_s: float | None = None

    async def wait(self, stamp_s: float) -> None:
        """Return when a frame stamped ``stamp_s`` is due (at once, after a loop yield, when not realtime)."""
        if not self.realtime:
            await asyncio.sleep(0)
            return
        if self._offset_s is None:
            self._offset_s = self._clock.now_s() - stamp_s
        await self._clock.sleep_until(stamp_s + self._offset_s)
