"""The signing relay and an autopilot whose signing timestamp is behind, as PX4's is after a boot.

PX4 keeps the timestamp SETUP_SIGNING gave it (in its key file) and starts from it at every boot; it moves
on by one unit per frame it sends and up to the newest valid frame it receives, never by its own clock
(measured on PX4 SITL: booted again 20 s after it was keyed, its first frames were 30 s behind the wall
clock; one signed frame from us and they were current). :class:`Px4LikeAutopilot` does the same on UDP.

The relay listens (``udpin``), so it sends only to where valid frames came from. Frames signed with our
key but older than the relay's clock (a new stream more than a minute behind) or than the stream's last
(a reboot) are dropped, as replays would be; the relay still sends our frames there, the autopilot
catches up, and its frames pass again. None of it is reported as an impostor.
"""

from __future__ import annotations

import asyncio
import secrets
import socket
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from pymavlink.dialects.v20 import common as mavlink2

from companion.config import LinkConfig
from companion.kernel import compat
from companion.vehicle import signing_relay
from companion.vehicle.mavlink_signing import (
    Signer,
    SigningClock,
    Verdict,
    Verifier,
    parse_header,
    split_frames,
    unix_to_units,
)
from companion.vehicle.signing_relay import TIMESTAMP_FILE, SigningRelay

pytestmark = pytest.mark.timeout(60)

FOLLOWER = 2
#: How long before now the autopilot was keyed, s (it boots with that timestamp).
KEYED_AGO_S = 600.0


class Px4LikeAutopilot(asyncio.DatagramProtocol):
    """System 2 on UDP: heartbeats signed with its own timestamp (+1 a frame, lifted by what it verifies)."""

    def __init__(self, key: bytes, timestamp: int) -> None:
        self.key = key
        self.clock = SigningClock(timestamp)
        self.signer = Signer(key, self.clock, link_id=1)  # PX4 signs with its MAVLink instance as link id
        self.verifier = Verifier(key, self.clock)  # lifts the clock to each valid frame's timestamp
        self.packer = mavlink2.MAVLink(None, srcSystem=FOLLOWER, srcComponent=1)
        self.transport: asyncio.DatagramTransport | None = None
        self.valid_in = 0
        self.refused_in = 0
        #: Booting: sends nothing.
        self.silent = False

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        frames, _, _ = split_frames(data)
        for frame in frames:
            info = parse_header(frame)
            if info is not None and self.verifier.check(frame, info) is Verdict.OK:
                self.valid_in += 1
            else:
                self.refused_in += 1

    def reboot(self, timestamp: int) -> None:
        """Start again from ``timestamp`` (the key file's), forgetting every stream it has seen."""
        self.clock.timestamp = timestamp
        self.verifier = Verifier(self.key, self.clock)

    def beat(self, port: int) -> None:
        assert self.transport is not None
        if self.silent:
            return
        hb = mavlink2.MAVLink_heartbeat_message(2, 12, 1, 0, 3, 3)
        signed = self.signer.sign(bytes(hb.pack(self.packer)), 0.0)  # never the wall clock
        assert signed is not None
        self.transport.sendto(signed, ("127.0.0.1", port))


class Mavsdk(asyncio.DatagramProtocol):
    """Where MAVSDK would sit: sends a companion heartbeat now and then; counts system 2's heartbeats."""

    def __init__(self) -> None:
        self.transport: asyncio.DatagramTransport | None = None
        self.packer = mavlink2.MAVLink(None, srcSystem=FOLLOWER, srcComponent=195)
        self.parser = mavlink2.MAVLink(None)
        self.parser.robust_parsing = True
        self.heartbeats = 0

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        for m in self.parser.parse_buffer(data) or []:
            if m.get_type() == "HEARTBEAT" and m.get_srcSystem() == FOLLOWER:
                self.heartbeats += 1

    def beat(self, port: int) -> None:
        assert self.transport is not None
        hb = mavlink2.MAVLink_heartbeat_message(18, 8, 0, 0, 4, 3)
        self.transport.sendto(bytes(hb.pack(self.packer)), ("127.0.0.1", port))


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


async def until(cond: Callable[[], bool], timeout_s: float, what: str, relay: SigningRelay) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}: {relay.stats()}")
        await asyncio.sleep(0.02)


async def fly(tmp_path: Path, key: bytes, autopilot_timestamp: int, body: Callable[..., Any]) -> SigningRelay:
    """A relay listening for the autopilot, MAVSDK and the autopilot beating at 20 Hz, then ``body``."""
    loop = asyncio.get_running_loop()
    port = free_udp_port()
    cfg = LinkConfig(
        url=f"udpin://127.0.0.1:{port}", system_id=FOLLOWER, signing=True, signing_key_file="given-below"
    )
    ap_transport, ap = await loop.create_datagram_endpoint(
        lambda: Px4LikeAutopilot(key, autopilot_timestamp), local_addr=("127.0.0.1", 0)
    )
    mv_transport, mavsdk = await loop.create_datagram_endpoint(Mavsdk, local_addr=("127.0.0.1", 0))
    try:
        async with SigningRelay(cfg, key, tmp_path / "state") as relay, compat.TaskGroup() as tg:

            async def beats() -> None:
                while True:
                    ap.beat(port)
                    mavsdk.beat(relay.local_port)
                    await asyncio.sleep(0.05)

            task = tg.create_task(beats(), name="test.beats")
            await body(relay, ap, mavsdk)
            task.cancel()
    finally:
        ap_transport.close()
        mv_transport.close()
    return relay


async def test_an_autopilot_keyed_long_ago_is_heard_once_it_has_our_frames(tmp_path: Path) -> None:
    """The relay's clock is where the last flight left it; the autopilot booted with its key's timestamp."""
    key = secrets.token_bytes(32)
    state = tmp_path / "state"
    state.mkdir()
    (state / TIMESTAMP_FILE).write_text(f"{unix_to_units(time.time())}\n")

    async def body(relay: SigningRelay, ap: Px4LikeAutopilot, mavsdk: Mavsdk) -> None:
        await until(lambda: relay.autopilot_signs, 5, "the autopilot's frames to pass", relay)
        await until(lambda: mavsdk.heartbeats >= 5, 5, "its heartbeats at MAVSDK", relay)
        assert ap.valid_in > 0

    relay = await fly(tmp_path, key, unix_to_units(time.time() - KEYED_AGO_S), body)
    assert relay.counters["in_behind"] >= 1  # its first frames: a new stream ten minutes behind our clock
    assert relay.impostors == {}


async def test_an_autopilot_that_reboots_is_heard_again_and_is_no_impostor(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A reboot longer than the relay keeps a silent peer: the frames after it are behind their stream."""
    monkeypatch.setattr(signing_relay, "PEER_TIMEOUT_S", 0.3)
    key = secrets.token_bytes(32)
    keyed_at = unix_to_units(time.time() - KEYED_AGO_S)

    async def body(relay: SigningRelay, ap: Px4LikeAutopilot, mavsdk: Mavsdk) -> None:
        await until(lambda: mavsdk.heartbeats >= 5, 5, "its heartbeats at MAVSDK", relay)
        assert ap.clock.timestamp >= unix_to_units(time.time()) - 100_000  # lifted to our clock
        ap.silent = True  # booting, longer than the relay keeps sending to a silent peer
        await asyncio.sleep(0.6)
        ap.reboot(keyed_at)
        ap.silent = False
        seen = mavsdk.heartbeats
        await until(lambda: mavsdk.heartbeats >= seen + 5, 5, "its heartbeats after the reboot", relay)

    relay = await fly(tmp_path, key, keyed_at, body)
    assert relay.counters["in_behind"] >= 1
    assert relay.impostors == {}
