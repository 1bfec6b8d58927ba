"""The autopilot's boot clock mapped onto ours, so attitude is stamped when it was sampled, not received.

Why: the camera frames are stamped at capture and looked up against the follower's attitude. Stamped on
arrival, every attitude sample is late by the link's latency, and the camera's rotation comes
out of step with its images: with 40 ms of it (link-loss's bursts, lockstep) the leader's height
estimate erred by 0.035 m (median) and, with a brisker velocity command, up to 1 m.

With MAVLink TIMESYNC (:meth:`BootClockMap.sync`: the companion's request echoed with the autopilot's
boot time) the map is the offset of the exchange with the shortest round trip among the recent ones, half
the round trip taken as the one-way delay, as NTP does: the link's own latency is then taken out of every
stamp. The fastest delivery still bounds it (no sample arrives before it was taken). Stamped by the
fastest delivery alone, every sample stayed late by the link's shortest latency: 12 ms of it (lockstep,
telemetry 12 ms plus a 10 ms spread) doubled the leader's height error, 0.026 -> 0.055 m, and shook the
follower's climb rate (0.03 -> 0.18 m/s RMS).

Without TIMESYNC (an autopilot that does not answer) the map is the lowest ``arrival - boot time`` seen (the
fastest delivery), allowed to creep up slowly so a clock drift or an autopilot reboot is followed. Pure:
times in, a stamp out.
"""

from __future__ import annotations

import math
from collections import deque

#: How fast the offset may grow when every sample arrives later than the best seen (s per s): covers
#: crystal drift (<= 100 ppm) with margin, while a latency burst of tens of ms barely moves it.
DRIFT_S_PER_S = 1e-3
#: A boot time that goes backwards by more than this is an autopilot reboot: start again, s.
REBOOT_STEP_S = 1.0
#: How often a link asks the autopilot for its boot time (MAVLink TIMESYNC), s.
TIMESYNC_PERIOD_S = 0.5
#: TIMESYNC exchanges kept; the one with the shortest round trip among them sets the map.
SYNC_WINDOW = 8
#: A round trip longer than this is no measure of the clocks (a reply held up, or not ours), s.
MAX_RTT_S = 1.0


class BootClockMap:
    """Maps autopilot ``time_boot_ms`` to the local clock (s) through the minimum observed offset."""

    def __init__(self) -> None:
        self._offset_s = math.inf
        self._last_arrival_s: float | None = None
        self._last_boot_s = -math.inf
        #: Recent TIMESYNC exchanges: (round trip, local minus boot time), s.
        self._syncs: deque[tuple[float, float]] = deque(maxlen=SYNC_WINDOW)
        #: The one of them with the shortest round trip (None: unsynced), chosen once per exchange.
        self._best: tuple[float, float] | None = None
        #: The last exchange's round trip, s (NaN: none yet).
        self.last_rtt_s = math.nan

    @property
    def synced(self) -> bool:
        """Whether TIMESYNC sets the map (else the fastest delivery does)."""
        return self._best is not None

    @property
    def one_way_s(self) -> float:
        """The link's one-way delay by the best recent exchange (half its round trip), s; NaN unsynced."""
        return self._best[0] / 2.0 if self._best is not None else math.nan

    def sync(self, boot_s: float, sent_s: float, received_s: float) -> bool:
        """Take one TIMESYNC exchange; False when it cannot be a measure (ignored).

        Our request left at ``sent_s`` and came back at ``received_s`` (local s) with the autopilot's boot
        time ``boot_s``.
        """
        rtt_s = received_s - sent_s
        if not (0.0 <= rtt_s <= MAX_RTT_S) or boot_s <= 0.0:
            return False
        if boot_s < self._last_boot_s - REBOOT_STEP_S:
            self._reboot()
        self.last_rtt_s = rtt_s
        self._syncs.append((rtt_s, 0.5 * (sent_s + received_s) - boot_s))
        self._best = min(self._syncs)
        return True

    def _reboot(self) -> None:
        self._offset_s = math.inf
        self._syncs.clear()
        self._best = None

    def stamp(self, boot_ms: int, arrival_s: float) -> float:
        """The local time at which a sample stamped ``boot_ms`` was taken: never after ``arrival_s``.

        A sender that leaves the field at 0 gets its samples stamped on arrival.
        """
        if boot_ms <= 0:
            return arrival_s
        boot_s = boot_ms * 1e-3
        if boot_s < self._last_boot_s - REBOOT_STEP_S:
            self._reboot()
        self._last_boot_s = boot_s
        if self._last_arrival_s is not None and math.isfinite(self._offset_s):
            self._offset_s += DRIFT_S_PER_S * max(0.0, arrival_s - self._last_arrival_s)
        self._last_arrival_s = arrival_s
        self._offset_s = min(self._offset_s, arrival_s - boot_s)
        offset_s = self._offset_s
        if self._best is not None:
            # No sample arrives before it was taken, so the fastest delivery bounds the offset from above:
            # it wins where the round trip is lopsided (an answer that waits for the autopilot's next step).
            offset_s = min(offset_s, self._best[1])
        return min(arrival_s, boot_s + offset_s)
