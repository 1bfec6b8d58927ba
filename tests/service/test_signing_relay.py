"""The signing relay on real sockets: against ``sitl serve`` over UDP, and against a pty as a serial port.

The MAVSDK side is a plain UDP socket that sends what MAVSDK would (a companion heartbeat, a parameter
read) and records what the relay hands it.
"""

from __future__ import annotations

import asyncio
import os
import pty
import secrets
import time
import tty
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from pymavlink.dialects.v20 import common as mavlink2

from companion.config import LinkConfig
from companion.kernel import compat
from companion.vehicle.mavlink_signing import unix_to_units
from companion.vehicle.signing_relay import TIMESTAMP_FILE, SigningRelay
from tests.integration.sitl_process import sitl_serve
from tests.signing_probe import MavPeer, send_impostor_heartbeats, send_unsigned_land

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(120)]

FOLLOWER = 2


class FakeMavsdk(asyncio.DatagramProtocol):
    """Where MAVSDK would sit: sends unsigned frames as system 2, component 195; keeps what arrives."""

    def __init__(self) -> None:
        self.transport: asyncio.DatagramTransport | None = None
        self.packer = mavlink2.MAVLink(None, srcSystem=FOLLOWER, srcComponent=195)
        self.parser = mavlink2.MAVLink(None)
        self.parser.robust_parsing = True
        self.received: list[tuple[Any, bool]] = []

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        for m in self.parser.parse_buffer(data) or []:
            buf = m.get_msgbuf()
            self.received.append((m, bool(buf[0] == 0xFD and buf[2] & 1)))

    def send(self, port: int, msg: Any) -> None:
        assert self.transport is not None
        self.transport.sendto(bytes(msg.pack(self.packer)), ("127.0.0.1", port))

    def heartbeats_from(self, sys_id: int) -> list[bool]:
        return [
            signed
            for m, signed in self.received
            if m.get_type() == "HEARTBEAT" and m.get_srcSystem() == sys_id
        ]


async def fake_mavsdk() -> FakeMavsdk:
    loop = asyncio.get_running_loop()
    _, proto = await loop.create_datagram_endpoint(FakeMavsdk, local_addr=("127.0.0.1", 0))
    return proto


def companion_heartbeat() -> Any:
    return mavlink2.MAVLink_heartbeat_message(18, 8, 0, 0, 4, 3)


async def until(cond: Callable[[], bool], timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        await asyncio.sleep(0.05)


async def test_relay_provisions_the_simulator_and_passes_only_signed_frames(tmp_path: Path) -> None:
    key = secrets.token_bytes(32)
    with sitl_serve(speed=1.0) as sim:
        port = sim.ports.api_remote + 1  # where the simulator sends the follower's API link
        cfg = LinkConfig(
            url=f"udpin://127.0.0.1:{port}",
            system_id=FOLLOWER,
            signing=True,
            signing_key_file="given-below",
            signing_provision=True,
        )
        mavsdk = await fake_mavsdk()
        async with SigningRelay(cfg, key, tmp_path / "state") as relay, compat.TaskGroup() as tg:
            task = tg.create_task(relay.run(), name="test.relay")

            async def beat() -> None:
                while True:
                    mavsdk.send(relay.local_port, companion_heartbeat())
                    await asyncio.sleep(0.2)

            beats = tg.create_task(beat(), name="test.beat")
            await until(lambda: relay.autopilot_signs, 15, "the simulator to sign")
            assert relay.provision_attempts >= 1
            # The status says where MAVSDK's side listens (for `companion status` and the PX4 attack test).
            assert relay.stats()["mavsdk_port"] == relay.local_port != 0
            await until(lambda: len(mavsdk.heartbeats_from(FOLLOWER)) >= 2, 5, "signed heartbeats for MAVSDK")
            assert all(mavsdk.heartbeats_from(FOLLOWER)), "nothing unsigned of system 2 reached MAVSDK"
            # MAVSDK's plain request goes out signed and its answer comes back.
            mavsdk.send(
                relay.local_port,
                mavlink2.MAVLink_param_request_read_message(FOLLOWER, 1, b"MPC_XY_VEL_MAX", -1),
            )
            await until(
                lambda: any(m.get_type() == "PARAM_VALUE" for m, _ in mavsdk.received),
                5,
                "the parameter's value",
            )
            # Unsigned traffic to the relay's port: an impostor of system 2 and a land from system 200.
            send_impostor_heartbeats(("127.0.0.1", port), FOLLOWER)
            send_unsigned_land(("127.0.0.1", port), FOLLOWER)
            await until(lambda: sum(relay.impostors.values()) >= 3, 5, "the impostor to be reported")
            await asyncio.sleep(0.3)
            assert all(mavsdk.heartbeats_from(FOLLOWER))
            assert not [m for m, _ in mavsdk.received if m.get_type() == "COMMAND_LONG"]
            assert relay.counters["in_unsigned_dropped"] >= 1
            # The simulator takes nothing unsigned any more (the relay signs for MAVSDK; a bare peer is not).
            bare = await MavPeer.open(("127.0.0.1", sim.ports.api_local + 1))
            assert not await bare.param_answered(FOLLOWER, "MPC_XY_VEL_MAX")
            bare.close()
            stamp = relay.clock.timestamp
            for t in (task, beats):
                t.cancel()
        stored = int((tmp_path / "state" / TIMESTAMP_FILE).read_text())
        assert stored >= stamp
        # A restart starts above what was stored, whatever the wall clock says.
        again = SigningRelay(cfg, key, tmp_path / "state", wall_time_s=lambda: 1_500_000_000.0)
        assert again.clock.timestamp > stored
        assert again.clock.next(1_500_000_000.0) > stored
    log = "\n".join(sim.output)
    assert "MAVLink signing key accepted" in log


async def test_relay_never_sends_the_key_to_an_armed_autopilot(tmp_path: Path) -> None:
    key = secrets.token_bytes(32)
    with sitl_serve(speed=1.0) as sim:
        gcs = await MavPeer.open(("127.0.0.1", sim.ports.api_local + 1))
        try:
            for _ in range(40):  # arm it unsigned (no key yet), once its estimator is ready
                gcs.send(
                    mavlink2.MAVLink_command_long_message(
                        FOLLOWER, 1, mavlink2.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0
                    )
                )
                await asyncio.sleep(0.5)
                acks = [m for m in gcs.received if m.get_type() == "COMMAND_ACK" and m.command == 400]
                if any(a.result == 0 for a in acks):
                    break
            else:
                pytest.fail("the follower never armed")
        finally:
            gcs.close()
        cfg = LinkConfig(
            url=f"udpin://127.0.0.1:{sim.ports.api_remote + 1}",
            system_id=FOLLOWER,
            signing=True,
            signing_key_file="given-below",
            signing_provision=True,
        )
        async with SigningRelay(cfg, key, tmp_path / "state") as relay, compat.TaskGroup() as tg:
            task = tg.create_task(relay.run(), name="test.relay")
            await until(
                lambda: relay.counters["in_unsigned_before_signing"] >= 3, 10, "the autopilot's heartbeats"
            )
            await asyncio.sleep(2.5)
            task.cancel()
        assert relay.provision_attempts == 0
        assert not relay.autopilot_signs
    assert "MAVLink signing key accepted" not in "\n".join(sim.output)


async def test_relay_on_a_serial_link_resynchronises_through_noise(tmp_path: Path) -> None:
    """A pty stands in for the autopilot's UART: the relay provisions over it and checks what comes back."""
    key = secrets.token_bytes(32)
    master, slave = pty.openpty()
    tty.setraw(master)
    os.set_blocking(master, False)
    device = os.ttyname(slave)
    cfg = LinkConfig(
        url=f"serial://{device}:921600",
        system_id=FOLLOWER,
        signing=True,
        signing_key_file="given-below",
        signing_provision=True,
    )
    autopilot = mavlink2.MAVLink(None, srcSystem=FOLLOWER, srcComponent=1)
    parser = mavlink2.MAVLink(None)
    parser.robust_parsing = True
    heard: list[Any] = []

    def read_master() -> None:
        try:
            data = os.read(master, 4096)
        except BlockingIOError:
            return
        heard.extend(m for m in parser.parse_buffer(data) or [] if m.get_type() != "BAD_DATA")

    loop = asyncio.get_running_loop()
    loop.add_reader(master, read_master)
    mavsdk = await fake_mavsdk()
    hb = mavlink2.MAVLink_heartbeat_message(2, 12, 1, 0, 3, 3)
    try:
        async with SigningRelay(cfg, key, tmp_path / "state") as relay, compat.TaskGroup() as tg:
            task = tg.create_task(relay.run(), name="test.relay")
            mavsdk.send(relay.local_port, companion_heartbeat())
            deadline = time.monotonic() + 10
            while not any(m.get_type() == "SETUP_SIGNING" for m in heard):
                assert time.monotonic() < deadline, "no SETUP_SIGNING on the serial link"
                os.write(master, b"\xfd\x30\x00noise" + bytes(hb.pack(autopilot)))
                await asyncio.sleep(0.2)
            setup = next(m for m in heard if m.get_type() == "SETUP_SIGNING")
            assert bytes(setup.secret_key) == key
            assert setup.target_system == FOLLOWER
            autopilot.signing.secret_key = bytes(setup.secret_key)
            autopilot.signing.sign_outgoing = True
            autopilot.signing.timestamp = int(setup.initial_timestamp)
            # Signed now, as a live stream, with noise between frames that looks like frame starts (one
            # claims 267 bytes: the frames it covers come through once the stream has moved past it).
            deadline = time.monotonic() + 5
            while len(mavsdk.heartbeats_from(FOLLOWER)) < 3:
                assert time.monotonic() < deadline, (
                    f"no signed heartbeats through the relay: {relay.counters}"
                )
                os.write(master, b"\xfd\xff\xfe\x10junk" + bytes(hb.pack(autopilot)) + b"\xfe\x05")
                await asyncio.sleep(0.02)
            assert relay.autopilot_signs
            mavsdk.send(relay.local_port, companion_heartbeat())
            await until(
                lambda: any(m.get_type() == "HEARTBEAT" and m.get_srcComponent() == 195 for m in heard),
                5,
                "ours",
            )
            ours = [m for m in heard if m.get_type() == "HEARTBEAT" and m.get_srcComponent() == 195][-1]
            buf = ours.get_msgbuf()
            assert buf[2] & 1, "what the relay sends over the serial link is signed"
            assert int.from_bytes(bytes(buf[-12:-6]), "little") >= unix_to_units(time.time()) - 100_000
            task.cancel()
    finally:
        loop.remove_reader(master)
        os.close(master)
        os.close(slave)
        if mavsdk.transport is not None:
            mavsdk.transport.close()


class Arrivals(asyncio.DatagramProtocol):
    """Records when each datagram arrives (perf_counter) and what it carried."""

    def __init__(self) -> None:
        self.times: list[float] = []
        self.data: list[bytes] = []

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        self.times.append(time.perf_counter())
        self.data.append(data)


async def test_latency_a_setpoint_pays_for_the_relay(tmp_path: Path) -> None:
    """The figure docs/service.md quotes: one setpoint's trip through the relay against a direct send."""
    loop = asyncio.get_running_loop()
    ap_transport, ap = await loop.create_datagram_endpoint(Arrivals, local_addr=("127.0.0.1", 0))
    ap_port = ap_transport.get_extra_info("sockname")[1]
    cfg = LinkConfig(
        url=f"udpout://127.0.0.1:{ap_port}", system_id=FOLLOWER, signing=True, signing_key_file="given-below"
    )
    mavsdk = await fake_mavsdk()
    sp = mavlink2.MAVLink_set_position_target_local_ned_message(
        0, FOLLOWER, 1, 8, 0b0000_0101_1100_0111, 0, 0, 0, 1.0, 0.5, -0.1, 0, 0, 0, 0, 0.2
    )
    n = 400

    async def trip(port: int) -> list[float]:
        ap.times.clear()
        ap.data.clear()
        sent = []
        for _ in range(n):
            sent.append(time.perf_counter())
            mavsdk.send(port, sp)
            await asyncio.sleep(0.002)
        await until(lambda: len(ap.times) >= n, 5, "every setpoint")
        return sorted(b - a for a, b in zip(sent, ap.times, strict=True))

    try:
        async with SigningRelay(cfg, secrets.token_bytes(32), tmp_path / "state") as relay:
            mavsdk.send(relay.local_port, companion_heartbeat())  # the relay learns where MAVSDK is
            await until(lambda: len(ap.times) >= 1, 5, "the first frame")
            via_relay = await trip(relay.local_port)
            assert all(d[2] & 1 for d in ap.data), "every frame reached the autopilot signed"
            direct = await trip(ap_port)
    finally:
        ap_transport.close()
        if mavsdk.transport is not None:
            mavsdk.transport.close()
    med_relay, med_direct = via_relay[n // 2] * 1e6, direct[n // 2] * 1e6
    print(
        f"\nsetpoint over loopback: direct median {med_direct:.0f} us, through the signing relay median "
        f"{med_relay:.0f} us (p99 {via_relay[int(n * 0.99)] * 1e6:.0f} us): +{med_relay - med_direct:.0f} us"
    )
    assert med_relay - med_direct < 5000  # a bound for a loaded machine; the docs quote the figure


async def test_the_health_probe_reads_a_signing_autopilot_through_the_relay(tmp_path: Path) -> None:
    """``companion health`` without a running service: it reads the autopilot's parameters over the
    signed link (unsigned reads would be dropped) and never sends the key."""
    from companion.config import Config, ServiceConfig
    from companion.service.wiring import autopilot_probe
    from tests.signing_probe import write_key

    key = secrets.token_bytes(32)
    key_file = write_key(tmp_path / "signing.key", key)
    with sitl_serve(speed=1.0) as sim:
        operator = await MavPeer.open(("127.0.0.1", sim.ports.api_local + 1))
        operator.setup_signing(FOLLOWER, key)  # provisioned beforehand, as on a vehicle in service
        operator.close()
        cfg = Config(
            link=LinkConfig(
                url=f"udpin://127.0.0.1:{sim.ports.api_remote + 1}",
                system_id=FOLLOWER,
                signing=True,
                signing_key_file=str(key_file),
                signing_provision=True,  # the probe turns it off
            ),
            service=ServiceConfig(state_dir=str(tmp_path / "state")),
        )
        checks = await asyncio.to_thread(autopilot_probe, cfg, 10.0)
    autopilot = next(c for c in checks if c.name == "autopilot")
    assert autopilot.ok, autopilot
    assert "offboard loss: unknown" not in autopilot.detail, autopilot.detail
    log = "\n".join(sim.output)
    assert log.count("MAVLink signing key accepted") == 1  # the operator's, not the probe's
