"""The simulator's clock, shared with the service in another process (as ROS nodes use ``/clock``).

``sitl serve --speed X`` runs X times faster than real time, and slips when the host cannot keep up. A service
on the wall clock would then see telemetry rates, frame ages and its own control period all off by the speed
factor. So in ``companion sim`` the service runs on the simulator's time: a component inside ``sitl serve``
publishes ``(sim time, monotonic time)`` into a small memory-mapped file each time the simulation advances
(:class:`SimClockWriter`), and :class:`SimClock` (a :class:`~companion.kernel.clock.Clock`) reads it,
extrapolating between publications at the nominal speed, never past ``max_lead_s`` ahead of the last
published sim time (a stalled simulator stops the service's time too), and never backwards.

The file is a seqlock: ``seq`` (uint64, odd while a write is in progress), ``sim_s``, ``mono_s`` (float64).
Only time crosses this boundary; no state of the vehicle does.
"""

from __future__ import annotations

import asyncio
import mmap
import os
import struct
import time
from pathlib import Path
from types import TracebackType
from typing import Self

_LAYOUT = struct.Struct("<Qdd")
SIZE = _LAYOUT.size


class SimClockWriter:
    """Publishes the sim time (in the simulator's process). A context manager that owns the file."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._fd = -1
        self._map: mmap.mmap | None = None
        self._seq = 0

    def __enter__(self) -> Self:
        self._fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_TRUNC, 0o644)
        os.ftruncate(self._fd, SIZE)
        self._map = mmap.mmap(self._fd, SIZE)
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if self._map is not None:
            self._map.close()
            self._map = None
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1

    def publish(self, sim_s: float, mono_s: float) -> None:
        """Write one sample (readers retry while it is half written)."""
        assert self._map is not None  # noqa: S101 (inside the context)
        self._seq += 1
        _LAYOUT.pack_into(self._map, 0, self._seq * 2 - 1, sim_s, mono_s)
        _LAYOUT.pack_into(self._map, 0, self._seq * 2, sim_s, mono_s)


class SimClock:
    """A :class:`companion.kernel.clock.Clock` that follows the simulator's published time.

    Args:
        path: the file :class:`SimClockWriter` publishes into (it must exist).
        speed: the simulator's nominal speed factor (sim seconds per wall second).
        max_lead_s: how far past the last publication extrapolation may go, sim s.
    """

    def __init__(self, path: Path, speed: float, max_lead_s: float = 0.05) -> None:
        self.path = path
        self.speed = speed
        self.max_lead_s = max_lead_s
        fd = os.open(path, os.O_RDONLY)
        try:
            self._map = mmap.mmap(fd, SIZE, prot=mmap.PROT_READ)
        finally:
            os.close(fd)
        self._last_s = 0.0

    def close(self) -> None:
        self._map.close()

    def _read(self) -> tuple[float, float]:
        while True:
            seq, sim_s, mono_s = _LAYOUT.unpack_from(self._map, 0)
            if seq % 2 == 0 and _LAYOUT.unpack_from(self._map, 0)[0] == seq:
                return sim_s, mono_s

    def now_s(self) -> float:
        sim_s, mono_s = self._read()
        lead_s = min(self.max_lead_s, max(0.0, (time.monotonic() - mono_s) * self.speed))
        self._last_s = max(self._last_s, sim_s + lead_s)
        return self._last_s

    async def sleep_until(self, t_s: float) -> None:
        while (remaining_s := t_s - self.now_s()) > 0.0:  # noqa: ASYNC110 (a clock in a file, no event)
            await asyncio.sleep(max(0.0005, remaining_s / self.speed))
