"""The service's messages to the ground station: STATUSTEXT on transitions, ONBOARD_COMPUTER_STATUS at a rate.

Transitions queue their STATUSTEXT (bounded: a burst drops the newest and counts it);
:meth:`GroundStation.run` sends them, and the machine's readings as ONBOARD_COMPUTER_STATUS, over the
autopilot's link. A send that fails (the link may be down; the mission handles that) is counted and
logged once per run of failures.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable

from companion.kernel import compat
from companion.service.gcs import OnboardStatusBuilder
from companion.service.ports import GcsPort
from companion.service.sysinfo import SystemReading

log = logging.getLogger("companion.app")  # the service's log, like its other loops

STATUSTEXT_QUEUE = 32


class GroundStation:
    """STATUSTEXT and ONBOARD_COMPUTER_STATUS senders.

    Args:
        onboard_status_rate_hz: ONBOARD_COMPUTER_STATUS rate (0: not sent).
        system: the latest machine reading (None until the first).
        uptime_s: the service's uptime, s.
        wall_time_s: wall-clock time for the message's stamp.
    """

    def __init__(
        self,
        onboard_status_rate_hz: float,
        *,
        system: Callable[[], SystemReading | None],
        uptime_s: Callable[[], float],
        wall_time_s: Callable[[], float],
    ) -> None:
        self.onboard_status_rate_hz = onboard_status_rate_hz
        self._system = system
        self._uptime_s = uptime_s
        self._wall_time_s = wall_time_s
        self._onboard = OnboardStatusBuilder()
        self._statustext: asyncio.Queue[tuple[str, str]] = asyncio.Queue(maxsize=STATUSTEXT_QUEUE)
        #: STATUSTEXTs dropped because the queue was full.
        self.statustext_dropped = 0

    def queue_statustext(self, text: str, severity: str) -> None:
        try:
            self._statustext.put_nowait((text, severity))
        except asyncio.QueueFull:
            self.statustext_dropped += 1

    async def run(self, gcs: GcsPort) -> None:
        async with compat.TaskGroup() as tg:
            tg.create_task(self._statustext_sender(gcs), name="companion.gcs.statustext")
            if self.onboard_status_rate_hz > 0:
                tg.create_task(self._onboard_sender(gcs), name="companion.gcs.onboard")

    async def _statustext_sender(self, gcs: GcsPort) -> None:
        failures = 0
        while True:
            text, severity = await self._statustext.get()
            try:
                await gcs.send_status_text(text, severity)
                failures = 0
            except Exception as exc:  # the link may be down; the mission handles that, we just count
                failures += 1
                if failures == 1:
                    log.warning("STATUSTEXT not sent (%s: %s)", type(exc).__name__, exc)

    async def _onboard_sender(self, gcs: GcsPort) -> None:
        period_s = 1.0 / self.onboard_status_rate_hz
        failures = 0
        while True:
            await asyncio.sleep(period_s)
            system = self._system()
            if system is None:
                continue
            status = self._onboard.build(system, self._uptime_s(), self._wall_time_s())
            try:
                await gcs.send_onboard_computer_status(status)
                failures = 0
            except Exception as exc:  # as above: counted, logged once per run of failures
                failures += 1
                if failures == 1:
                    log.warning("ONBOARD_COMPUTER_STATUS not sent (%s: %s)", type(exc).__name__, exc)
