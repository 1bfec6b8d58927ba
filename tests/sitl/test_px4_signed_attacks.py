"""A signed flight against real PX4 SITL on ``udpin`` while a second process attacks the service three ways.

``companion sim --autopilot px4`` with signing, provisioning and a leader that shares its position over
MQTT. From the moment the service's status page says where its signing relay listens
(``mavlink_signing``: ``mavsdk_port``, ``autopilot_url``) until the follower has been watched in FOLLOW:

- a process of the user ``nobody`` sends unsigned NAV_LAND commands to the relay's MAVSDK port (the relay
  would sign whatever its MAVSDK side sends), 25 a second;
- the same process sends unsigned, armed HEARTBEATs of system 99 to the service's autopilot port,
  about 200 a second, each pair from a fresh source port (the relay's send list used to keep the 8 last
  senders, PX4 pushed off it);
- this test, once the service has taken the leader's genuine shares, publishes forged leader positions
  50 km away at 10 Hz on the run's broker and replays each genuine share 0.3 s and 2.2 s late.

The attacker counts what it sent, and the relay what it refused. A packet socket on the loopback
interface (root) sees what reaches PX4's offboard port (``14580 + i``): the follower's setpoints and their
largest gap in FOLLOW, PX4's COMMAND_ACKs to the service, and that no NAV_LAND of the attacker's (its
``param3`` carries a marker) ever reached PX4. The follower must keep flying on its own commands.
Skipped without a PX4 build, and without root (the packet socket, the user ``nobody``).
"""

from __future__ import annotations

import asyncio
import itertools
import json
import os
import pwd
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
MSG_COMMAND_LONG = 76
MSG_COMMAND_ACK = 77
#: The attacker's NAV_LAND carries this in param3 (unused by NAV_LAND), to tell it from the service's.
MARKER = 4242.0
#: How late genuine leader shares are replayed, s: within the age limit (replayed), past it (stale).
REPLAY_AFTER_S = (0.3, 2.2)

#: The second process: hex frames on argv; the relay's MAVSDK port and the service's port on the first line
#: of stdin, any second line (or its end) stops it; what it sent, as JSON on stdout.
ATTACKER = """
import json, socket, sys, threading, time
land, beat = bytes.fromhex(sys.argv[1]), bytes.fromhex(sys.argv[2])
relay_port, service_port = (int(v) for v in sys.stdin.readline().split())
stop = threading.Event()
threading.Thread(target=lambda: (sys.stdin.readline(), stop.set()), daemon=True).start()
local = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
local.bind(("127.0.0.1", 0))
lands = beats = 0
ports = set()
while not stop.is_set():
    local.sendto(land, ("127.0.0.1", relay_port))
    lands += 1
    for _ in range(4):  # a new source port for every pair of heartbeats
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.bind(("127.0.0.1", 0))
            ports.add(s.getsockname()[1])
            for _ in range(2):
                s.sendto(beat, ("127.0.0.1", service_port))
                beats += 1
    time.sleep(0.04)
print(json.dumps({"lands": lands, "land_from": local.getsockname()[1], "heartbeats": beats,
                  "heartbeat_ports": len(ports)}), flush=True)
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
            if frame[23] != 17:  # not UDP
                continue
            udp = 14 + (frame[14] & 0x0F) * 4
            src, dst = struct.unpack("!HH", frame[udp : udp + 4])
            if dst == self.port:
                self.to_port.append((t, frame[udp + 8 :]))
            elif src == self.port:
                self.from_port.append((t, frame[udp + 8 :]))

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


def command_long(payload: bytes) -> tuple[int, float]:
    """(command, param3) of a COMMAND_LONG payload (MAVLink 2 cuts its trailing zeros)."""
    full = payload.ljust(33, b"\x00")
    return struct.unpack_from("<H", full, 28)[0], struct.unpack_from("<f", full, 8)[0]


def mqtt_stats(st: dict[str, Any] | None) -> dict[str, Any]:
    return (st or {}).get("mqtt") or {}


async def forge_shares(
    host: str, port: int, topic: str, status_path: Path, stop: asyncio.Event
) -> dict[str, int]:
    """Once the service took a genuine share: forged positions 50 km north at 10 Hz, genuine ones replayed."""
    counts = {"forged": 0, "replayed": 0, "accepted_before": 0}
    ours: set[bytes] = set()  # everything published here comes back on the subscription
    genuine: list[tuple[float, bytes, int]] = []
    async with aiomqtt.Client(host, port, identifier=f"attacker-{secrets.token_hex(4)}") as client:
        await client.subscribe(topic)

        async def listen() -> None:
            async for msg in client.messages:
                if isinstance(msg.payload, bytes) and msg.payload not in ours:
                    for i in range(len(REPLAY_AFTER_S)):
                        genuine.append((time.monotonic(), msg.payload, i))

        listener = asyncio.create_task(listen())
        try:
            # The first share a sender is heard with anchors its jump check: forge only after the real one.
            while not stop.is_set():
                st = await asyncio.to_thread(status_of, status_path)
                accepted = mqtt_stats(st).get("shares_accepted") or 0
                if accepted >= 3:
                    counts["accepted_before"] = accepted
                    break
                await asyncio.sleep(0.5)
            while not stop.is_set():
                share = {"lat_deg": 47.397742 + 0.45, "lon_deg": 8.545594, "alt_amsl_m": 500.0}
                share["time_unix_s"] = time.time()
                forged = json.dumps(share).encode()
                ours.add(forged)
                await client.publish(topic, forged)
                counts["forged"] += 1
                now = time.monotonic()
                for item in [g for g in genuine if now - g[0] >= REPLAY_AFTER_S[g[2]]]:
                    genuine.remove(item)
                    ours.add(item[1])
                    await client.publish(topic, item[1])
                    counts["replayed"] += 1
                await asyncio.sleep(0.1)
        finally:
            listener.cancel()
    return counts


async def attack_and_watch(run: Run, attacker: subprocess.Popen[str]) -> dict[str, Any]:
    def banner() -> int | None:
        m = BANNER.search(run.text("sitl.log"))
        return int(m.group(2)) if m else None

    instance = await until("the simulator's banner", run, banner, 120.0)
    tap = LoopbackTap(14580 + instance)
    try:
        cfg = await until(
            "the service's configuration", run, lambda: run.text("service-config.json") or None, 60.0
        )
        status_path = Path(json.loads(cfg)["status"]["socket_path"])
        mqtt_cfg = json.loads(cfg)["mqtt"]

        def relay() -> dict[str, Any] | None:
            st = status_of(status_path)
            return None if st is None else st.get("mavlink_signing")

        # Where the relay listens, from the service's status page (it is up once the link is open).
        first = await until("the relay on the status page", run, relay, 150.0)
        service_port = int(str(first["autopilot_url"]).rsplit(":", 1)[1])
        assert attacker.stdin is not None
        attacker.stdin.write(f"{first['mavsdk_port']} {service_port}\n")
        attacker.stdin.flush()
        stop = asyncio.Event()
        shares = asyncio.create_task(
            forge_shares("127.0.0.1", mqtt_cfg["port"], mqtt_cfg["leader_topic"], status_path, stop)
        )
        try:

            def following() -> dict[str, Any] | None:
                st = status_of(status_path)
                return st if st is not None and flown_by_the_service(st, ("follow",)) else None

            start = await until("FOLLOW over the signed link", run, following, 150.0)
            t_watch = time.monotonic()
            watched = []
            while time.monotonic() - t_watch < WATCH_S:
                st = await asyncio.to_thread(status_of, status_path)
                assert st is not None, run.tail()
                watched.append(st)
                await asyncio.sleep(0.5)
            t_end = time.monotonic()
        finally:
            stop.set()
            forged = await shares
            out, _ = await asyncio.to_thread(attacker.communicate, "stop\n", 10.0)
        sent = json.loads(out)
        await asyncio.sleep(1.0)  # the last datagrams counted
        final = status_of(status_path)
        assert final is not None, run.tail()
    finally:
        tap.close()
    to_px4 = messages(tap.to_port)
    setpoints = [t for t, msg_id, _ in to_px4 if msg_id in SETPOINT_IDS and t_watch <= t <= t_end]
    gaps_ms = [1000.0 * (b - a) for a, b in itertools.pairwise(setpoints)]
    commands = [(t, *command_long(p)) for t, msg_id, p in to_px4 if msg_id == MSG_COMMAND_LONG]
    acks = [
        struct.unpack("<HB", payload.ljust(3, b"\x00")[:3])
        for _, msg_id, payload in messages(tap.from_port)
        if msg_id == MSG_COMMAND_ACK
    ]
    return {
        "instance": instance,
        "service_port": service_port,
        "relay_first": first,
        "watched": [start, *watched],
        "final": final,
        "setpoints": len(setpoints),
        "gap_max_ms": max(gaps_ms, default=float("nan")),
        "frames_to_px4": len(to_px4),
        "attacker_lands_at_px4": [
            c for c in commands if c[1] == mavlink2.MAV_CMD_NAV_LAND and c[2] == MARKER
        ],
        "lands_in_watch": [
            c for c in commands if c[1] == mavlink2.MAV_CMD_NAV_LAND and t_watch <= c[0] <= t_end
        ],
        "acks": acks,
        "shares": forged,
        "sent": sent,
    }


def _root_and_nobody() -> str | None:
    """Why the attacks cannot be made here (None: they can)."""
    if os.geteuid() != 0:
        return "needs root: a packet socket on lo, and the attacker runs as the user nobody"
    try:
        pwd.getpwnam("nobody")
    except KeyError:
        return "needs the user nobody for the attacker"
    try:  # a container may run as root without CAP_NET_RAW
        socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(0x0800)).close()
    except OSError as exc:
        return f"needs a packet socket on lo (CAP_NET_RAW): {exc}"
    return None


@pytest.mark.sitl
@pytest.mark.slow
@pytest.mark.lab
@pytest.mark.mqtt_broker
@pytest.mark.timeout(360)
def test_px4_flies_signed_through_spoofed_heartbeats_forged_shares_and_a_racing_local_sender(
    tmp_path: Path,
) -> None:
    binary = _px4_binary()
    if binary is None:
        pytest.skip(f"no PX4 SITL build: set SITL_PX4__BINARY or put one at {SHARED_PX4}")
    missing = _root_and_nobody()
    if missing is not None:
        pytest.skip(missing)
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
        FOLLOWER, 1, mavlink2.MAV_CMD_NAV_LAND, 0, 0, 0, MARKER, 0, 0, 0, 0
    )
    beat = mavlink2.MAVLink_heartbeat_message(2, 12, mavlink2.MAV_MODE_FLAG_SAFETY_ARMED | 1, 0, 4, 3)
    frames = [
        bytes(land.pack(mavlink2.MAVLink(None, srcSystem=FOLLOWER, srcComponent=195))).hex(),
        bytes(beat.pack(mavlink2.MAVLink(None, srcSystem=99, srcComponent=1))).hex(),
    ]
    python = "/usr/bin/python3" if Path("/usr/bin/python3").exists() else sys.executable
    attacker = subprocess.Popen(
        [python, "-c", ATTACKER, *frames],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        user="nobody",
        cwd="/",
        text=True,
    )
    err_path = tmp_path / "sim.err"
    with (tmp_path / "sim.out").open("wb") as stdout, err_path.open("wb") as stderr:
        proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=stdout, stderr=stderr)
    run = Run(proc, out, err_path)
    try:
        seen = asyncio.run(attack_and_watch(run, attacker))
        assert proc.wait(timeout=RUN_TIMEOUT_S) == 0, run.tail()
    finally:
        if attacker.poll() is None:
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
    watched, final = seen["watched"], seen["final"]
    signing, mqtt = final["mavlink_signing"], mqtt_stats(final)
    counters = signing["counters"]
    refused_local = counters.get("local_refused", 0) + counters.get("local_foreign", 0)
    others_heard = counters.get("in_unsigned_passed", 0) + counters.get("in_unsigned_held", 0)
    rejected = mqtt.get("shares_rejected") or {}
    sent, shares = seen["sent"], seen["shares"]
    states = [(t[1], t[2]) for t in report["transitions"]]
    modes = [m["mode"] for m in ap["follower_modes"]]
    accepted_ok = sorted({a for a in seen["acks"] if a[1] == 0})
    print(
        f"\npx4 signed flight under three attacks: {report['outcome']}; relative position RMSE "
        f"{report['relative_position_rmse_m']:.3f} m, formation max deviation "
        f"{report['formation_max_deviation_m']:.3f} m; follower modes {modes}\n"
        f"attacker sent: {sent['lands']} NAV_LAND to the relay's MAVSDK port "
        f"{seen['relay_first']['mavsdk_port']}, "
        f"{sent['heartbeats']} HEARTBEATs of system 99 from {sent['heartbeat_ports']} ports to "
        f"{seen['service_port']}; {shares['forged']} forged shares, {shares['replayed']} replayed\n"
        f"relay: {refused_local} local frames refused ({counters.get('local_refused', 0)} before MAVSDK "
        f"spoke, "
        f"{counters.get('local_foreign', 0)} after), MAVSDK is {signing['mavsdk_address']}; "
        f"{others_heard} unsigned frames of other systems (held {counters.get('in_unsigned_held', 0)}, "
        f"passed {counters.get('in_unsigned_passed', 0)}), locked onto {signing['autopilot_address']}\n"
        f"shares: {mqtt.get('shares_accepted')} accepted ({shares['accepted_before']} before the forging), "
        f"rejected {rejected}\n"
        f"at PX4's port in {WATCH_S:g} s of FOLLOW: {seen['setpoints']} setpoints, largest gap "
        f"{seen['gap_max_ms']:.0f} ms; NAV_LAND of the attacker's: {len(seen['attacker_lands_at_px4'])}; "
        f"{len(seen['acks'])} COMMAND_ACKs from PX4, {sum(a[1] == 0 for a in seen['acks'])} accepted: "
        f"(command, result) {accepted_ok}\n"
        f"signing relay: {json.dumps(signing)}"
    )
    # The attacks were made, in volume.
    assert sent["lands"] >= 20 * WATCH_S, sent
    assert sent["heartbeats"] >= 100 * WATCH_S, sent
    assert sent["heartbeat_ports"] >= 50 * WATCH_S, sent
    assert shares["forged"] >= 5 * WATCH_S, shares
    assert shares["replayed"] >= 5 * WATCH_S, shares
    # The follower flew on its own commands, in formation, all along.
    assert all(flown_by_the_service(st, FLYING) for st in watched), [st["mission"]["state"] for st in watched]
    assert report["outcome"] == "completed", (report["outcome"], states)
    assert not [s for s in states if s[1].lower() in NOT_FLOWN], states
    assert not LANDING_MODES & set(modes), modes
    assert seen["setpoints"] >= 10 * WATCH_S, seen["setpoints"]
    assert seen["gap_max_ms"] < 500.0, seen["gap_max_ms"]
    assert accepted_ok, seen["acks"]  # PX4 accepted the service's commands (arming, take-off, offboard)
    assert not [a for a in seen["acks"] if a[0] == mavlink2.MAV_CMD_NAV_LAND], seen["acks"]
    assert seen["attacker_lands_at_px4"] == []
    assert seen["lands_in_watch"] == []
    # The relay: locked onto PX4, MAVSDK's own socket its local side, the attacker's frames refused and
    # reported; the heartbeats of system 99 were heard (as the leader's presence would be) but put no one
    # on the send list.
    assert signing["autopilot_address"] == f"127.0.0.1:{14580 + seen['instance']}"
    assert signing["mavsdk_address"] != f"127.0.0.1:{sent['land_from']}"
    assert refused_local >= 0.9 * sent["lands"], (refused_local, sent)
    assert "is not MAVSDK" in service_log or "a second local sender" in service_log
    assert others_heard >= 0.9 * sent["heartbeats"], (others_heard, sent)
    assert signing["impostors"] == {}  # system 99 is not ours: heard, never an impostor
    # The shares: the forged and replayed ones refused, the real leader's taken all along.
    assert rejected.get("jump", 0) >= 0.9 * shares["forged"], rejected
    assert rejected.get("replayed", 0) + rejected.get("stale", 0) >= 0.9 * shares["replayed"], rejected
    assert mqtt["shares_accepted"] - shares["accepted_before"] >= 5 * WATCH_S, mqtt
