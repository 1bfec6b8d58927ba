"""TEST-ONLY: probe an autopilot's MAVLink 2 signing over UDP, and the service's settings for a signed flight.

Works against any autopilot UDP port (the project's simulator, PX4 SITL's ``14580 + i``):

    peer = await MavPeer.open(("127.0.0.1", port), src=(255, 190))     # unsigned ground station
    assert await peer.param_answered(sysid, "MPC_XY_VEL_MAX")            # an unsigned read is answered
    signed = await MavPeer.open(addr, src=(255, 190), key=KEY)
    signed.setup_signing(sysid, KEY)                                     # SETUP_SIGNING (disarmed only)
    assert not await peer.param_answered(sysid, "MPC_XY_VEL_MAX")        # unsigned: dropped now
    assert await signed.param_answered(sysid, "MPC_XY_VEL_MAX")          # signed: answered, and signed
    send_unsigned_land(addr, sysid)                                      # from another system id

:func:`signed_service_env` gives ``companion run`` the overrides for a signed flight (key file, state
folder, provisioning), so a PX4 flight can reuse what the simulator's flight uses.
"""

from __future__ import annotations

import asyncio
import socket
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pymavlink.dialects.v20 import common as mavlink2

Addr = tuple[str, int]


def mavlink_now_units() -> int:
    """Now as a MAVLink signing timestamp (10 us since 2015-01-01 UTC)."""
    return int((time.time() - 1_420_070_400) * 100_000)


@dataclass
class MavPeer(asyncio.DatagramProtocol):
    """A MAVLink endpoint on an ephemeral UDP port, talking to one autopilot address.

    With ``key`` it signs what it sends; it records everything that comes back, with whether it was
    signed (``signed_from``/``unsigned_from`` count frames per source system).
    """

    addr: Addr = ("127.0.0.1", 0)
    src: tuple[int, int] = (255, 190)
    key: bytes | None = None
    received: list[Any] = field(default_factory=list)
    signed_from: dict[int, int] = field(default_factory=dict)
    unsigned_from: dict[int, int] = field(default_factory=dict)
    transport: asyncio.DatagramTransport | None = None
    _packer: Any = None
    _parser: Any = None

    @classmethod
    async def open(cls, addr: Addr, src: tuple[int, int] = (255, 190), key: bytes | None = None) -> MavPeer:
        loop = asyncio.get_running_loop()
        _, peer = await loop.create_datagram_endpoint(
            lambda: cls(addr=addr, src=src, key=key), local_addr=("127.0.0.1", 0)
        )
        return peer

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]
        self._packer = mavlink2.MAVLink(None, srcSystem=self.src[0], srcComponent=self.src[1])
        if self.key is not None:
            self._packer.signing.secret_key = self.key
            self._packer.signing.sign_outgoing = True
            self._packer.signing.timestamp = mavlink_now_units()
        self._parser = mavlink2.MAVLink(None)
        self._parser.robust_parsing = True

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        try:
            msgs = self._parser.parse_buffer(data) or []
        except mavlink2.MAVError:
            return
        for m in msgs:
            if m.get_type() == "BAD_DATA":
                continue
            buf = m.get_msgbuf()
            signed = bool(buf) and buf[0] == 0xFD and bool(buf[2] & 0x01)
            book = self.signed_from if signed else self.unsigned_from
            book[m.get_srcSystem()] = book.get(m.get_srcSystem(), 0) + 1
            self.received.append(m)

    def send(self, msg: Any) -> None:
        assert self.transport is not None
        self.transport.sendto(bytes(msg.pack(self._packer)), self.addr)

    def close(self) -> None:
        if self.transport is not None:
            self.transport.close()

    def sign_outgoing(self, on: bool) -> None:
        """Sign what is sent from now on (``on``: with ``key``), or send it unsigned from the same port.

        One port for both matters where the autopilot answers only its link's first partner (PX4's UDP
        links): a signed and an unsigned request then get their answers, if any, at the same place.
        """
        if on and self.key is None:
            raise ValueError("this peer has no key to sign with")
        self._packer.signing.sign_outgoing = on

    def setup_signing(self, target_system: int, key: bytes, target_component: int = 1) -> None:
        """SETUP_SIGNING: the autopilot signs with ``key`` from now on (it refuses while armed)."""
        self.send(
            mavlink2.MAVLink_setup_signing_message(
                target_system, target_component, list(key), mavlink_now_units()
            )
        )

    async def param_answered(self, target_system: int, name: str, timeout_s: float = 1.5) -> bool:
        """Send PARAM_REQUEST_READ; True when a PARAM_VALUE for ``name`` comes back in time."""
        start = len(self.received)
        self.send(mavlink2.MAVLink_param_request_read_message(target_system, 1, name.encode(), -1))
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for m in self.received[start:]:
                if m.get_type() == "PARAM_VALUE" and _text(m.param_id) == name:
                    return True
            await asyncio.sleep(0.05)
        return False

    def last_signed(self, kind: str) -> bool | None:
        """Was the newest ``kind`` message received signed? None when none came."""
        for m in reversed(self.received):
            if m.get_type() == kind:
                buf = m.get_msgbuf()
                return bool(buf) and buf[0] == 0xFD and bool(buf[2] & 0x01)
        return None


def _text(value: Any) -> str:
    if isinstance(value, bytes | bytearray):
        value = value.decode("ascii", errors="replace")
    return str(value).split("\x00", 1)[0]


def send_unsigned_land(
    addr: Addr, target_system: int, src_system: int = 200, src_component: int = 190
) -> None:
    """An unsigned COMMAND_LONG NAV_LAND from another system id: what a signing autopilot must ignore."""
    packer = mavlink2.MAVLink(None, srcSystem=src_system, srcComponent=src_component)
    cmd = mavlink2.MAVLink_command_long_message(
        target_system, 1, mavlink2.MAV_CMD_NAV_LAND, 0, 0, 0, 0, 0, 0, 0, 0
    )
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.sendto(bytes(cmd.pack(packer)), addr)


def send_impostor_heartbeats(addr: Addr, system_id: int, count: int = 3) -> None:
    """Unsigned HEARTBEATs claiming to be autopilot ``system_id``, armed: a second vehicle with our id."""
    packer = mavlink2.MAVLink(None, srcSystem=system_id, srcComponent=1)
    hb = mavlink2.MAVLink_heartbeat_message(2, 12, mavlink2.MAV_MODE_FLAG_SAFETY_ARMED | 1, 0, 4, 3)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        for _ in range(count):
            s.sendto(bytes(hb.pack(packer)), addr)


def write_key(path: Path, key: bytes) -> Path:
    """A signing key file as the service wants it: 64 hex digits, mode 0600."""
    path.write_text(key.hex() + "\n")
    path.chmod(0o600)
    return path


def signed_service_env(key_file: Path, state_dir: Path, *, provision: bool = True) -> dict[str, str]:
    """``WINGMAN_*`` overrides that make ``companion run`` fly over a signed link."""
    return {
        "WINGMAN_LINK__SIGNING": "true",
        "WINGMAN_LINK__SIGNING_KEY_FILE": str(key_file),
        "WINGMAN_LINK__SIGNING_PROVISION": "true" if provision else "false",
        "WINGMAN_SERVICE__STATE_DIR": str(state_dir),
    }
