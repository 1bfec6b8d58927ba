"""Frame stamps on the service clock.

Perception looks the follower's attitude up at each frame's stamp, and the mission judges an estimate's
age from it, both on the service clock (telemetry is stamped on arrival there). The simulator's camera
stamps frames on the *sim* clock, a recording on its own: :class:`StampMapper` maps them with the offset
``arrival - stamp`` at its minimum over a sliding window. The minimum is the transport delay without
the queueing jitter (the idea behind NTP's clock filter), so relative timing between frames is kept
exactly and a source that slips (a simulator falling behind real time) is followed within the window.

Why not simply the arrival time: on a loaded host the rendered camera arrives 0.3-0.8 s after the
instant it shows (measured on the 2-core test machine), while telemetry arrives within milliseconds.
Stamped on arrival, a frame would be paired with an attitude 0.3-0.8 s too new (wrong NED measurements
while the follower manoeuvres) and would look fresher than it is; mapped, it is paired with the right
attitude and its true age reaches the mission, which hovers on a stale estimate as it should.
"""

from __future__ import annotations

import dataclasses
from collections import deque
from collections.abc import AsyncIterator
from types import TracebackType

from companion.kernel.camera import RgbdFrame
from companion.kernel.clock import Clock
from companion.kernel.compat import Self
from companion.perception.types import FrameSource


class StampMapper:
    """Maps source stamps to the service clock; pure (arrival times are passed in)."""

    def __init__(self, window_s: float = 2.0) -> None:
        self.window_s = window_s
        self._samples: deque[tuple[float, float]] = deque()  # (arrival_s, offset_s)

    def map(self, stamp_s: float, arrival_s: float) -> float:
        """The service-clock time of a frame stamped ``stamp_s`` that arrived at ``arrival_s``."""
        self._samples.append((arrival_s, arrival_s - stamp_s))
        while self._samples and self._samples[0][0] < arrival_s - self.window_s:
            self._samples.popleft()
        offset_s = min(o for _, o in self._samples)
        return stamp_s + offset_s


class ServiceClockSource:
    """Wraps a frame source so its frames carry service-clock stamps (see the module docstring)."""

    def __init__(self, source: FrameSource, clock: Clock, window_s: float = 2.0) -> None:
        self._source = source
        self._clock = clock
        self.mapper = StampMapper(window_s)

    async def __aenter__(self) -> Self:
        await self._source.__aenter__()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self._source.__aexit__(exc_type, exc, tb)

    def __aiter__(self) -> AsyncIterator[RgbdFrame]:
        return self._frames()

    async def _frames(self) -> AsyncIterator[RgbdFrame]:
        async for frame in self._source:
            stamp_s = self.mapper.map(frame.stamp_s, self._clock.now_s())
            yield dataclasses.replace(frame, stamp_s=stamp_s)
