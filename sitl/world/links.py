"""Message-level MAVLink links with scripted faults (pure: sim time in, seeded randomness).

A :class:`MessageLink` is one of a vehicle's MAVLink links (API or GCS) seen from the client side:
``send`` hands the autopilot a message as if it had arrived over the wire, ``receive`` returns what
the autopilot sent. Both directions pass through the vehicle's :class:`LinkFaults` (loss, latency,
jitter, cuts from the scenario). The UDP server puts sockets on the same objects, so the lockstep
harness and the wire see identical behaviour, faults included.

MAVLink 2 signing, as PX4 does it: once a vehicle has a key (SETUP_SIGNING while disarmed, see
:class:`~sitl.autopilot.signing.VehicleSigning`), a message reaches its autopilot only with a valid
signature, except HEARTBEAT, RADIO_STATUS, ADSB_VEHICLE and COLLISION; everything else is dropped and
counted. What the vehicle sends is signed on every link.
"""

from __future__ import annotations

import heapq
import itertools
from collections import deque
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from sitl.autopilot.signing import SignedOutgoing
from sitl.world.scenario import LinkSpec

if TYPE_CHECKING:
    from sitl.autopilot.autopilot import Autopilot

#: Bound on undelivered outgoing messages per link: a harness that stops reading must not grow memory.
MAX_QUEUED = 20_000


class LinkFaults:
    """Decides each message's fate: dropped, or delivered after a delay (s)."""

    def __init__(self, spec: LinkSpec, rng: np.random.Generator) -> None:
        self.spec = spec
        self._rng = rng
        self.perfect = spec.is_perfect

    def delay_s(self, t_s: float) -> float | None:
        """The delivery delay for a message sent at ``t_s``, or None if it is lost."""
        if self.perfect:
            return 0.0
        spec = self.spec
        loss, latency_ms = spec.loss, spec.latency_ms
        for w in spec.windows:
            if w.start_s <= t_s < w.end_s:
                if w.cut:
                    return None
                loss = max(loss, w.loss)
                latency_ms = max(latency_ms, w.latency_ms)
        if loss > 0 and self._rng.random() < loss:
            return None
        jitter = abs(float(self._rng.normal(0.0, spec.jitter_ms))) if spec.jitter_ms > 0 else 0.0
        return (latency_ms + jitter) * 1e-3


class MessageLink:
    """A client's view of one autopilot link, in sim time.

    Args:
        autopilot: The vehicle's autopilot.
        index: Link index (0 API, 1 GCS).
        faults_in: Faults client -> vehicle.
        faults_out: Faults vehicle -> client.
        clock: Returns the current sim time (s).
    """

    def __init__(
        self,
        autopilot: Autopilot,
        index: int,
        faults_in: LinkFaults,
        faults_out: LinkFaults,
        clock: Callable[[], float],
    ) -> None:
        self._ap = autopilot
        self.index = index
        self._faults_in = faults_in
        self._faults_out = faults_out
        self._clock = clock
        self._inbound: list[tuple[float, int, Any, int, int]] = []
        self._outbound: deque[tuple[float, Any]] = deque(maxlen=MAX_QUEUED)
        self._outbound_delayed: list[tuple[float, int, Any]] = []
        self._seq = itertools.count()
        self.sent = 0
        self.dropped_in = 0
        self.dropped_out = 0
        #: Messages refused for their signature (or its absence) once the vehicle signs.
        self.dropped_unsigned = 0

    @property
    def active(self) -> bool:
        return self._ap.link_active(self.index)

    def open(self) -> MessageLink:
        """Start the link's streams (PX4 always streams on a configured link; a harness opts in)."""
        self._ap.open_link(self.index)
        return self

    def close(self) -> None:
        self._ap.close_link(self.index)
        self._outbound.clear()
        self._outbound_delayed.clear()

    def send(self, msg: Any, src_system: int = 255, src_component: int = 190) -> None:
        """Deliver ``msg`` to the autopilot as if received on this link from (src_system, src_component).

        Once the vehicle signs, only what :meth:`~sitl.autopilot.signing.VehicleSigning.accept` passes is
        delivered.
        """
        signing = self._ap.mavlink.signing
        if signing is not None and not signing.accept(msg, src_system, src_component):
            self.dropped_unsigned += 1
            return
        t = self._clock()
        delay = self._faults_in.delay_s(t)
        if delay is None:
            self.dropped_in += 1
            return
        self.sent += 1
        if delay <= 0.0:
            self._ap.mavlink.handle_message(msg, self.index, src_system, src_component)
        else:
            heapq.heappush(self._inbound, (t + delay, next(self._seq), msg, src_system, src_component))

    def deliver_due(self, t_s: float) -> None:
        """Hand the autopilot the delayed inbound messages that are due (the world calls this)."""
        q = self._inbound
        while q and q[0][0] <= t_s:
            _, _, msg, sys_id, comp_id = heapq.heappop(q)
            self._ap.mavlink.handle_message(msg, self.index, sys_id, comp_id)

    def collect(self, t_s: float) -> None:
        """Move the autopilot's outbox through the outgoing faults (the world calls this)."""
        box = self._ap.drain_outbox(self.index)
        if box:
            faults = self._faults_out
            if faults.perfect:
                self._outbound.extend((t_s, m) for m in box)
            else:
                for m in box:
                    delay = faults.delay_s(t_s)
                    if delay is None:
                        self.dropped_out += 1
                    elif delay <= 0.0:
                        self._outbound.append((t_s, m))
                    else:
                        heapq.heappush(self._outbound_delayed, (t_s + delay, next(self._seq), m))
        q = self._outbound_delayed
        while q and q[0][0] <= t_s:
            due, _, m = heapq.heappop(q)
            self._outbound.append((due, m))

    def receive(self) -> list[Any]:
        """Everything the autopilot sent that has arrived by now (oldest first); signed once it signs."""
        out = [m for _, m in self._outbound]
        self._outbound.clear()
        signing = self._ap.mavlink.signing
        if signing is not None:
            return [SignedOutgoing(m, signing.mav_signing) for m in out]
        return out
