"""A signed flight against real PX4 SITL on ``udpin`` while a second process attacks the service three ways.

``companion sim --autopilot px4`` with signing, provisioning and a leader that shares its position over
MQTT. From the moment the service's signing relay opens its port until the run ends:

- a process of the user ``nobody`` sends unsigned NAV_LAND commands to the relay's MAVSDK port, racing
  MAVSDK to it (the relay would sign whatever its MAVSDK side sends);
- the same process sends unsigned HEARTBEATs of system 99 to the service's port (``14540 + i``), about
  200 a second, each burst from fresh source ports (the relay's send list kept 8 addresses);
- this test publishes forged leader positions 50 km away and replays the leader's genuine shares 2.2 s
  late on the run's broker.

A packet socket on the loopback interface (root) sees what reaches PX4's port (``14580 + i``): the
follower's setpoints, their largest gap, and PX4's COMMAND_ACKs to the service. The follower must keep
flying on its own commands. Skipped without a PX4 build or without root.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import os
import secrets
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import aiomqtt
import pytest
from pymavlink.dialects.v20 import common as mavlink2

from companion.vehicle.mavlink_signing import parse_header, split_frames
from tests.signing_probe import write_key
from tests.sitl.test_px4_signed_flight import (
    BANNER,
    FLYING,
    LANDING_MODES,
    NOT_FLOWN,
    REPO,
    RUN_TIMEOUT_S,
    SCENARIO,
    SHARED_PX4,
    Run,
    _px4_binary,
    flown_by_the_service,
    status_of,
    until,
)

FOLLOWER = 2
#: How long the follower is watched in formation under the attacks, s (wall).
WATCH_S = 12.0
#: SET_POSITION_TARGET_LOCAL_NED, SET_ATTITUDE_TARGET, SET_POSITION_TARGET_GLOBAL_INT.
SETPOINT_IDS = {84, 82, 86}
MSG_COMMAND_ACK = 77

#: The second process: hex frames on argv, the relay's port and the service's port on stdin.
ATTACKER = """
import socket, sys, time
land, beat = bytes.fromhex(sys.argv[1]), bytes.fromhex(sys.argv[2])
relay_port, service_port = (int(v) for v in sys.stdin.readline().split())
local = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
local.bind(("127.0.0.1", 0))
sent = 0
while True:
    local.sendto(land, ("127.0.0.1", relay_port))
    for _ in range(4):  # a new source port for every burst of heartbeats
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            for _ in range(2):
                s.sendto(beat, ("127.0.0.1", service_port))
                sent += 1
    time.sleep(0.04)
"""


class LoopbackTap:
    """Datagrams to and from one UDP port on ``lo``, with their arrival times (a packet socket: root)."""

    def __init__(self, port: int) -> None:
        self.port = port
        self.to_port: list[tuple[float, bytes]] = []
        self.from_port: list[tuple[float, bytes]] = []
        self._sock = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(0x0800))
        self._sock.bind(("lo", 0))
        self._sock.settimeout(0.2)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="test.tap", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                frame, addr = self._sock.recvfrom(65535)
            except TimeoutError:
                continue
            if addr[2] == socket.PACKET_OUTGOING:
                continue  # lo shows each datagram twice: once going out, once coming in
            t = time.monotonic()
            ihl = (frame[14] & 0x0F) * 4
            if frame[23] != 17:  # not UDP
                continue
            udp = 14 + ihl
            src, dst = struct.unpack("!HH", frame[udp : udp + 4])
            payload = frame[udp + 8 :]
            if dst == self.port:
                self.to_port.append((t, payload))
            elif src == self.port:
                self.from_port.append((t, payload))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self._sock.close()


def messages(datagrams: list[tuple[float, bytes]]) -> list[tuple[float, int, bytes]]:
    """(time, message id, payload) of every MAVLink frame in the datagrams."""
    out = []
    for t, data in datagrams:
        frames, _, _ = split_frames(data)
        for frame in frames:
            info = parse_header(frame)
            if info is not None:
                out.append((t, info.msg_id, info.payload))
    return out


async def forge_shares(host: str, port: int, topic: str, stop: asyncio.Event) -> dict[str, int]:
    """Forged leader positions 50 km north at 10 Hz, and each genuine share replayed 2.2 s late."""
    counts = {"forged": 0, "replayed": 0}
    genuine: list[tuple[float, bytes]] = []
    async with aiomqtt.Client(host, port, identifier=f"attacker-{secrets.token_hex(4)}") as client:
        await client.subscribe(topic)

        async def listen() -> None:
            async for msg in client.messages:
                if isinstance(msg.payload, bytes) and b"47.9" not in msg.payload[:40]:
                    genuine.append((time.monotonic(), msg.payload))

        listener = asyncio.create_task(listen())
        try:
            while not stop.is_set():
                share = {"lat_deg": 47.397742 + 0.45, "lon_deg": 8.545594, "alt_amsl_m": 500.0}
                share["time_unix_s"] = time.time()
                await client.publish(topic, json.dumps(share))
                counts["forged"] += 1
                while genuine and time.monotonic() - genuine[0][0] >= 2.2:
                    await client.publish(topic, genuine.pop(0)[1])
                    counts["replayed"] += 1
                await asyncio.sleep(0.1)
        finally:
            listener.cancel()
    return counts


async def attack_and_watch(run: Run, attacker: subprocess.Popen[str]) -> dict[str, Any]:
    def relay_port() -> int | None:
        for line in run.err_path.read_text(errors="replace").splitlines():
            if "signing relay:" in line and "MAVSDK on 127.0.0.1:" in line:
                return int(line.split("MAVSDK on 127.0.0.1:")[1].split(";")[0])
        return None

    def banner() -> int | None:
        m = BANNER.search(run.text("sitl.log"))
        return int(m.group(2)) if m else None

    instance = await until("the simulator's banner", run, banner, 120.0)
    tap = LoopbackTap(14580 + instance)
    port = await until("the relay's port", run, relay_port, 120.0)
    assert attacker.stdin is not None
    attacker.stdin.write(f"{port} {14540 + instance}\n")
    attacker.stdin.flush()
    cfg = json.loads(run.text("service-config.json"))
    status_path = Path(cfg["status"]["socket_path"])
    stop = asyncio.Event()
    shares = asyncio.create_task(
        forge_shares("127.0.0.1", cfg["mqtt"]["port"], cfg["mqtt"]["leader_topic"], stop)
    )
    try:

        def following() -> dict[str, Any] | None:
            st = status_of(status_path)
            return st if st is not None and flown_by_the_service(st, ("follow",)) else None

        await until("FOLLOW over the signed link", run, following, 150.0)
        t_watch = time.monotonic()
        watched = []
        while time.monotonic() - t_watch < WATCH_S:
            st = await asyncio.to_thread(status_of, status_path)
            assert st is not None, run.tail()
            watched.append(st)
            await asyncio.sleep(0.5)
        stop.set()
        forged = await shares
    finally:
        stop.set()
        tap.close()
    out = messages(tap.to_port)
    setpoints = [t for t, msg_id, _ in out if msg_id in SETPOINT_IDS and t >= t_watch]
    gaps_ms = [1000.0 * (b - a) for a, b in itertools.pairwise(setpoints)]
    acks = [
        struct.unpack("<HB", payload.ljust(3, b"\x00")[:3])
        for _, msg_id, payload in messages(tap.from_port)
        if msg_id == MSG_COMMAND_ACK
    ]
    return {
        "instance": instance,
        "relay_port": port,
        "watched": watched,
        "setpoints": len(setpoints),
        "gap_max_ms": max(gaps_ms, default=float("nan")),
        "acks": acks,
        "shares": forged,
    }


@pytest.mark.sitl
@pytest.mark.slow
@pytest.mark.lab
@pytest.mark.timeout(360)
@pytest.mark.skipif(os.geteuid() != 0, reason="the attacker runs as nobody and the tap needs root")
def test_px4_flies_signed_through_spoofed_heartbeats_forged_shares_and_a_racing_local_sender(
    tmp_path: Path,
) -> None:
    binary = _px4_binary()
    if binary is None:
        pytest.skip(f"no PX4 SITL build: set SITL_PX4__BINARY or put one at {SHARED_PX4}")
    scenario = tmp_path / "px4-signed-straight.toml"
    scenario.write_text(SCENARIO)
    key_file = write_key(tmp_path / "signing.key", secrets.token_bytes(32))
    out = tmp_path / "run"
    env = {**os.environ, "PYTHONPATH": str(REPO), "SITL_PX4__BINARY": binary}
    cmd = [sys.executable, "-m", "companion", "sim", "--scenario", str(scenario), "--autopilot", "px4",
           "--no-plots", "--out", str(out), "--set", 'leader.shared_position="mqtt"',
           "--set", "link.signing=true", "--set", f'link.signing_key_file="{key_file}"',
           "--set", "link.signing_provision=true"]  # fmt: skip
    land = mavlink2.MAVLink_command_long_message(
        FOLLOWER, 1, mavlink2.MAV_CMD_NAV_LAND, 0, 0, 0, 0, 0, 0, 0, 0
    )
    beat = mavlink2.MAVLink_heartbeat_message(2, 12, mavlink2.MAV_MODE_FLAG_SAFETY_ARMED | 1, 0, 4, 3)
    frames = [
        bytes(land.pack(mavlink2.MAVLink(None, srcSystem=FOLLOWER, srcComponent=195))).hex(),
        bytes(beat.pack(mavlink2.MAVLink(None, srcSystem=99, srcComponent=1))).hex(),
    ]
    attacker = subprocess.Popen(
        ["/usr/bin/python3", "-c", ATTACKER, *frames], stdin=subprocess.PIPE, user="nobody", text=True
    )
    err_path = tmp_path / "sim.err"
    with (tmp_path / "sim.out").open("wb") as stdout, err_path.open("wb") as stderr:
        proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=stdout, stderr=stderr)
    run = Run(proc, out, err_path)
    try:
        seen = asyncio.run(attack_and_watch(run, attacker))
        assert proc.wait(timeout=RUN_TIMEOUT_S) == 0, run.tail()
    finally:
        attacker.kill()
        attacker.wait(timeout=10)
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout=10)
    service_log = err_path.read_text(errors="replace")
    report = json.loads((out / "report.json").read_text())
    ap = report["autopilot"]
    watched = seen["watched"]
    last = watched[-1]
    signing = last["mavlink_signing"]
    rejected = (last.get("health", {}).get("mqtt") or last.get("mqtt") or {}).get("shares_rejected")
    states = [(t[1], t[2]) for t in report["transitions"]]
    modes = [m["mode"] for m in ap["follower_modes"]]
    raced_first = service_log.find("is not MAVSDK") < service_log.find("signing relay: MAVSDK is")
    print(
        f"\npx4 signed flight under attack: {report['outcome']}; relative position RMSE "
        f"{report['relative_position_rmse_m']:.3f} m, formation max deviation "
        f"{report['formation_max_deviation_m']:.3f} m; follower modes {modes}\n"
        f"setpoints reaching PX4 in {WATCH_S:g} s of FOLLOW: {seen['setpoints']}, largest gap "
        f"{seen['gap_max_ms']:.0f} ms; COMMAND_ACKs from PX4 (command, result): {seen['acks']}\n"
        f"the racing sender spoke before MAVSDK: {raced_first}; forged/replayed shares published "
        f"{seen['shares']}, rejected by reason {rejected}\n"
        f"signing relay: {json.dumps(signing)}"
    )
    # The follower flew on its own commands, in formation, all along.
    assert all(flown_by_the_service(st, FLYING) for st in watched), [st["mission"]["state"] for st in watched]
    assert report["outcome"] == "completed", (report["outcome"], states)
    assert not [s for s in states if s[1].lower() in NOT_FLOWN], states
    assert not LANDING_MODES & set(modes), modes
    assert seen["setpoints"] >= 10 * WATCH_S
    assert seen["gap_max_ms"] < 500.0
    assert [a for a in seen["acks"] if a[1] == 0], seen["acks"]  # the service's commands were accepted
    assert not [a for a in seen["acks"] if a[0] == mavlink2.MAV_CMD_NAV_LAND]
    # The relay: locked onto PX4, the racer refused, the heartbeats of system 99 passed but sent nothing.
    assert signing["autopilot_address"] == f"127.0.0.1:{14580 + seen['instance']}"
    assert signing["counters"]["local_refused"] + signing["counters"].get("local_foreign", 0) > 10
    assert signing["counters"]["in_unsigned_passed"] > 100
    assert seen["shares"]["forged"] > 50
