"""The autopilot's boot clock mapped onto ours, so attitude is stamped when it was sampled, not received.

Why: the camera frames are stamped at capture and looked up against the follower's attitude. Stamped on
arrival, every attitude sample is late by the link's latency, and the camera's rotation comes
out of step with its images: with 40 ms of it (link-loss's bursts, lockstep) the leader's height
estimate erred by 0.035 m (median) and, with a brisker velocity command, up to 1 m.

The map is the lowest ``arrival - boot time`` seen (the fastest delivery: the shortest latency), allowed to
creep up slowly so a clock drift or an autopilot reboot is followed. Pure: times in, a stamp out.
"""

from __future__ import annotations

import math

#: How fast the offset may grow when every sample arrives later than the best seen (s per s): covers
#: crystal drift (<= 100 ppm) with margin, while a latency burst of tens of ms barely moves it.
DRIFT_S_PER_S = 1e-3
#: A boot time that goes backwards by more than this is an autopilot reboot: start again, s.
REBOOT_STEP_S = 1.0


class BootClockMap:
    """Maps autopilot ``time_boot_ms`` to the local clock (s) through the minimum observed offset."""

    def __init__(self) -> None:
        self._offset_s = math.inf
        self._last_arrival_s: float | None = None
        self._last_boot_s = -math.inf

    def stamp(self, boot_ms: int, arrival_s: float) -> float:
        """The local time at which a sample stamped ``boot_ms`` was taken: never after ``arrival_s``.

        A sender that leaves the field at 0 gets its samples stamped on arrival.
        """
        if boot_ms <= 0:
            return arrival_s
        boot_s = boot_ms * 1e-3
        if boot_s < self._last_boot_s - REBOOT_STEP_S:
            self._offset_s = math.inf
        self._last_boot_s = boot_s
        if self._last_arrival_s is not None and math.isfinite(self._offset_s):
            self._offset_s += DRIFT_S_PER_S * max(0.0, arrival_s - self._last_arrival_s)
        self._last_arrival_s = arrival_s
        self._offset_s = min(self._offset_s, arrival_s - boot_s)
        return min(arrival_s, boot_s + self._offset_s)
