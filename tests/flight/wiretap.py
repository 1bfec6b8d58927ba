"""A UDP man-in-the-middle between MAVSDK and the simulator that decodes what goes over the wire.

TEST-ONLY. It proves properties at the place that matters, the autopilot's socket: which setpoints really
reached the vehicle and when, and which modes the vehicle reported. It can also cut the link (drop both
directions) to test link loss.

    sim (sends to proxy_port) <-> WireTap <-> MAVSDK listening on client_port
"""

from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass, field
from typing import Any

from pymavlink.dialects.v20 import common as mavlink2


@dataclass(slots=True)
class Seen:
    """One decoded message with its arrival time (time.monotonic) and direction."""

    t_s: float
    to_vehicle: bool
    msg: Any


@dataclass
class WireTap(asyncio.DatagramProtocol):
    """Forwards datagrams both ways and records the messages of interest."""

    client_port: int
    keep: frozenset[str] = frozenset(
        {"SET_POSITION_TARGET_LOCAL_NED", "SET_ATTITUDE_TARGET", "COMMAND_LONG", "HEARTBEAT"}
    )
    seen: list[Seen] = field(default_factory=list)
    cut: bool = False
    _transport: asyncio.DatagramTransport | None = None
    _sim_addr: tuple[str, int] | None = None
    _up: Any = None
    _down: Any = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self._transport = transport  # type: ignore[assignment]
        self._up = mavlink2.MAVLink(None)
        self._down = mavlink2.MAVLink(None)
        self._up.robust_parsing = True
        self._down.robust_parsing = True

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        assert self._transport is not None
        if self.cut:
            return
        to_vehicle = addr[1] == self.client_port
        if to_vehicle:
            if self._sim_addr is not None:
                self._transport.sendto(data, self._sim_addr)
        else:
            self._sim_addr = addr
            self._transport.sendto(data, ("127.0.0.1", self.client_port))
        parser = self._up if to_vehicle else self._down
        now = time.monotonic()
        try:
            msgs = parser.parse_buffer(data) or []
        except mavlink2.MAVError:  # a malformed frame must never stop the forwarding
            msgs = []
        for m in msgs:
            if m.get_type() in self.keep:
                self.seen.append(Seen(now, to_vehicle, m))

    def setpoints(self, since_s: float = 0.0) -> list[Seen]:
        """Setpoint messages that went to the vehicle after ``since_s``."""
        return [
            s
            for s in self.seen
            if s.to_vehicle
            and s.t_s >= since_s
            and s.msg.get_type() in ("SET_POSITION_TARGET_LOCAL_NED", "SET_ATTITUDE_TARGET")
        ]

    def vehicle_modes(self, since_s: float = 0.0) -> list[tuple[float, int]]:
        """(time, custom_mode) of the autopilot's heartbeats after ``since_s``."""
        return [
            (s.t_s, int(s.msg.custom_mode))
            for s in self.seen
            if not s.to_vehicle
            and s.t_s >= since_s
            and s.msg.get_type() == "HEARTBEAT"
            and s.msg.get_srcComponent() == 1
        ]

    def close(self) -> None:
        if self._transport is not None:
            self._transport.close()


async def open_wiretap(listen_port: int, client_port: int) -> WireTap:
    """Listen where the simulator sends (``listen_port``) and forward to MAVSDK on ``client_port``."""
    loop = asyncio.get_running_loop()
    tap = WireTap(client_port=client_port)
    await loop.create_datagram_endpoint(lambda: tap, local_addr=("127.0.0.1", listen_port))
    return tap


#: PX4 custom_mode of AUTO.LAND, which is also how the Descend failsafe is reported.
CUSTOM_MODE_AUTO_LAND = 0x6040000
CUSTOM_MODE_OFFBOARD = 0x60000
