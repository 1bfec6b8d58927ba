"""TEST-ONLY: one UDP link that carries the leader and the follower together, plus hostile traffic.

    sim leader API  -> leader_port   \\
                                       Mux --- client socket <-> the service (MAVSDK on client_port)
    sim follower API -> follower_port /

What the simulator's two vehicles send is forwarded to the service on one socket, as on a shared radio
or a misconfigured router. What the service sends is decoded and routed by its target system (broadcasts
to both), and every message is kept, so a test can prove which system each command was addressed to.
While ``hostile`` is set, the service also receives, twice a second, random bytes, a truncated MAVLink 2
frame, and HEARTBEATs of a spoofed third autopilot (system 3).
"""

from __future__ import annotations

import asyncio
import contextlib
import random
import time
from dataclasses import dataclass, field
from typing import Any

from pymavlink.dialects.v20 import common as mavlink2

#: Commands that only ask for information: sent by MAVSDK to every system it discovers.
READ_ONLY_COMMANDS = frozenset(
    {
        mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL,
        mavlink2.MAV_CMD_REQUEST_MESSAGE,
        mavlink2.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES,
        mavlink2.MAV_CMD_REQUEST_PROTOCOL_VERSION,
        mavlink2.MAV_CMD_GET_HOME_POSITION,
    }
)
_SETPOINTS = frozenset(
    {"SET_POSITION_TARGET_LOCAL_NED", "SET_POSITION_TARGET_GLOBAL_INT", "SET_ATTITUDE_TARGET"}
)


@dataclass(slots=True)
class Sent:
    """A message from the service, when (time.monotonic) and to which system."""

    t_s: float
    target_system: int | None
    msg: Any


def is_control(msg: Any) -> bool:
    """Does this message change what a vehicle does (setpoints, modes, arming, navigation, parameters)?"""
    kind = msg.get_type()
    if kind in _SETPOINTS or kind in ("SET_MODE", "PARAM_SET", "MISSION_ITEM_INT", "MISSION_COUNT"):
        return True
    if kind in ("COMMAND_LONG", "COMMAND_INT"):
        return int(msg.command) not in READ_ONLY_COMMANDS
    return False


class _Side(asyncio.DatagramProtocol):
    def __init__(self, mux: Mux, role: str) -> None:
        self.mux = mux
        self.role = role
        self.transport: asyncio.DatagramTransport | None = None
        self.sim_addr: tuple[str, int] | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        self.sim_addr = addr
        self.mux.from_sim(self.role, data)


class _Client(asyncio.DatagramProtocol):
    def __init__(self, mux: Mux) -> None:
        self.mux = mux
        self.transport: asyncio.DatagramTransport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        self.mux.from_service(data)


@dataclass
class Mux:
    """See the module docstring. ``follower_enabled`` False: only the leader is on the link."""

    client_port: int
    follower_enabled: bool = True
    hostile: bool = False
    sent: list[Sent] = field(default_factory=list)
    #: (time, custom_mode) of each vehicle's autopilot HEARTBEATs, by system id.
    modes: dict[int, list[tuple[float, int]]] = field(default_factory=dict)
    hostile_datagrams: int = 0
    #: Datagrams from the service, and those of them that held no whole message (never forwarded).
    service_datagrams: int = 0
    unparsed_datagrams: int = 0
    _sides: dict[str, _Side] = field(default_factory=dict)
    _client: _Client | None = None
    _up: Any = None
    _down: Any = None
    _spoof: Any = None
    _rng: random.Random = field(default_factory=lambda: random.Random(7))

    def from_sim(self, role: str, data: bytes) -> None:
        if role == "follower" and not self.follower_enabled:
            return
        with contextlib.suppress(mavlink2.MAVError):
            for m in self._down.parse_buffer(data) or []:
                if m.get_type() == "HEARTBEAT" and m.get_srcComponent() == 1:
                    self.modes.setdefault(m.get_srcSystem(), []).append(
                        (time.monotonic(), int(m.custom_mode))
                    )
        self._to_service(data)

    def from_service(self, data: bytes) -> None:
        try:
            msgs = self._up.parse_buffer(data) or []
        except mavlink2.MAVError:
            msgs = []
        self.service_datagrams += 1
        if not msgs:
            self.unparsed_datagrams += 1
        now = time.monotonic()
        targets: set[int] = set()
        for m in msgs:
            target = getattr(m, "target_system", None)
            self.sent.append(Sent(now, None if target is None else int(target), m))
            targets.add(0 if target is None else int(target))
        for role, side in self._sides.items():
            sysid = 1 if role == "leader" else 2
            if role == "follower" and not self.follower_enabled:
                continue
            if (targets & {0, sysid}) and side.transport is not None and side.sim_addr is not None:
                side.transport.sendto(data, side.sim_addr)

    def _to_service(self, data: bytes) -> None:
        if self._client is not None and self._client.transport is not None:
            self._client.transport.sendto(data, ("127.0.0.1", self.client_port))

    def control_to(self, system: int, since_s: float = 0.0) -> list[Sent]:
        """Control messages the service addressed to ``system`` (or broadcast) after ``since_s``."""
        return [
            s for s in self.sent if s.t_s >= since_s and s.target_system in (system, 0) and is_control(s.msg)
        ]

    def control_not_to(self, system: int) -> list[Sent]:
        """Control messages addressed to any other system than ``system``."""
        return [s for s in self.sent if s.target_system not in (system, None) and is_control(s.msg)]

    async def run_hostile(self) -> None:
        """While ``hostile``: junk and a spoofed autopilot toward the service, twice a second."""
        while True:
            await asyncio.sleep(0.5)
            if not self.hostile:
                continue
            junk = self._rng.randbytes(self._rng.randint(1, 120))
            truncated = bytes([0xFD, 40, 0, 0, 9, 1, 1, 0, 0, 0]) + self._rng.randbytes(5)
            beat = self._spoof.heartbeat_encode(
                mavlink2.MAV_TYPE_QUADROTOR, mavlink2.MAV_AUTOPILOT_PX4, 0, 0x4040000, 4
            )
            for data in (junk, truncated, beat.pack(self._spoof)):
                self._to_service(data)
                self.hostile_datagrams += 1

    def close(self) -> None:
        for side in self._sides.values():
            if side.transport is not None:
                side.transport.close()
        if self._client is not None and self._client.transport is not None:
            self._client.transport.close()


async def open_mux(leader_port: int, follower_port: int, client_port: int) -> Mux:
    """Listen where the simulator sends each vehicle's API link; talk to the service on ``client_port``."""
    loop = asyncio.get_running_loop()
    mux = Mux(client_port=client_port)
    mux._up = mavlink2.MAVLink(None)
    mux._down = mavlink2.MAVLink(None)
    mux._up.robust_parsing = True
    mux._down.robust_parsing = True
    mux._spoof = mavlink2.MAVLink(None, srcSystem=3, srcComponent=1)
    for role, port in (("leader", leader_port), ("follower", follower_port)):
        side = _Side(mux, role)
        await loop.create_datagram_endpoint(lambda s=side: s, local_addr=("127.0.0.1", port))  # type: ignore[misc]
        mux._sides[role] = side
    client = _Client(mux)
    await loop.create_datagram_endpoint(lambda: client, local_addr=("127.0.0.1", 0))
    mux._client = client
    return mux
