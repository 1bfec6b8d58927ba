"""TEST-ONLY: attack the signing relay and the share gate in-process and print what got through.

Run ``python -m tests.relay_attack_probe``: each line is one attack and its figure. The relay is driven
through its frame handlers with a recording transport (no sockets toward the autopilot); the racing local
sender is a real UDP socket owned by another user (needs root to drop to ``nobody``), since the relay
judges local senders by who owns their socket.
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import secrets
import socket
import statistics
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any

from pymavlink.dialects.v20 import common as mavlink2

from companion.config import LinkConfig
from companion.telemetry.inbound import InboundRejectedError, Keyring, sign
from companion.telemetry.shares import SHARE_DOMAIN, ShareGate, ShareLimits, sign_share
from companion.vehicle import signing_relay
from companion.vehicle.mavlink_signing import unix_to_units
from companion.vehicle.relay_transports import Transport
from companion.vehicle.signing_relay import SigningRelay

FOLLOWER = 2
PX4: tuple[str, int] = ("10.0.0.2", 14580)


class Recorder(Transport):
    """The autopilot side: remembers every send and where it went."""

    def __init__(self) -> None:
        self.sent: list[tuple[bytes, list[tuple[str, int]]]] = []

    def send(self, data: bytes, dests: list[tuple[str, int]]) -> None:
        self.sent.append((data, list(dests)))

    def close(self) -> None:
        pass


class LocalRecorder:
    def __init__(self) -> None:
        self.sent: list[tuple[bytes, Any]] = []

    def sendto(self, data: bytes, addr: Any) -> None:
        self.sent.append((data, addr))

    def close(self) -> None:
        pass


class FakeMonotonic:
    """Stands in for the relay module's ``time`` (monotonic only moves when told)."""

    def __init__(self) -> None:
        self.t = 1000.0

    def monotonic(self) -> float:
        return self.t


class LineCounter(logging.Handler):
    def __init__(self) -> None:
        super().__init__()
        self.lines = 0

    def emit(self, record: logging.LogRecord) -> None:
        self.lines += 1


def packer(sys_id: int, comp_id: int, key: bytes | None = None, ts: int | None = None) -> Any:
    p = mavlink2.MAVLink(None, srcSystem=sys_id, srcComponent=comp_id)
    if key is not None:
        p.signing.secret_key = key
        p.signing.sign_outgoing = True
        p.signing.timestamp = ts if ts is not None else unix_to_units(time.time())
    return p


def heartbeat(p: Any, armed: bool = False) -> bytes:
    mode = mavlink2.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0
    return bytes(mavlink2.MAVLink_heartbeat_message(2, 12, mode | 1, 0, 4, 3).pack(p))


def command_long(p: Any) -> bytes:
    return bytes(mavlink2.MAVLink_command_long_message(FOLLOWER, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0).pack(p))


def setpoint(p: Any) -> bytes:
    return bytes(
        mavlink2.MAVLink_set_position_target_local_ned_message(
            0, FOLLOWER, 1, 1, 0b0000_1111_1100_0111, 0, 0, 0, 1.0, 0.5, -0.1, 0, 0, 0, 0, 0
        ).pack(p)
    )


def relay(key: bytes, state: Path, url: str, provision: bool = False) -> SigningRelay:
    cfg = LinkConfig(
        url=url, system_id=FOLLOWER, signing=True, signing_key_file="x", signing_provision=provision
    )
    r = SigningRelay(cfg, key, state)
    r._autopilot = Recorder()
    r._local = LocalRecorder()  # type: ignore[assignment]
    return r


def sent(r: SigningRelay) -> list[tuple[bytes, list[tuple[str, int]]]]:
    """What the relay sent toward the autopilot, and where."""
    recorder: Any = r._autopilot
    return recorder.sent  # type: ignore[no-any-return]


def local_socket() -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    return s


def bind_mavsdk(r: SigningRelay, mav: socket.socket) -> None:
    r._from_mavsdk(heartbeat(packer(FOLLOWER, 195)), mav.getsockname())


def probe_send_list(key: bytes, state: Path) -> str:
    r = relay(key, state, "udpin://0.0.0.0:14540")
    mav = local_socket()
    bind_mavsdk(r, mav)
    r._from_autopilot(heartbeat(packer(FOLLOWER, 1, key)), PX4)
    attacker = packer(99, 1)
    for i in range(10_000):
        r._from_autopilot(heartbeat(attacker), ("10.0.0.66", 40_000 + i % 1000))
    r._from_mavsdk(command_long(packer(FOLLOWER, 195)), mav.getsockname())
    dests = sent(r)[-1][1]
    mav.close()
    return (
        f"1 send list: PX4 still on it after 10,000 unsigned HEARTBEATs of system 99 from 1,000 ports: "
        f"{'yes' if PX4 in dests else 'no'}; the next COMMAND_LONG went to {len(dests)} address(es)"
    )


def probe_provisioning(key: bytes, tmp: Path) -> str:
    clock = FakeMonotonic()
    real = getattr(signing_relay, "time")  # noqa: B009 (the module's clock, swapped for the probe)
    setattr(signing_relay, "time", clock)  # noqa: B010
    out = []
    try:
        # a) PX4 signs but is behind (keyed long ago); a spoofer's unsigned disarmed HEARTBEAT as system 2.
        r = relay(key, tmp / "a", "udpin://0.0.0.0:14540", provision=True)
        r.clock.next(time.time())  # the relay has signed MAVSDK's frames: its clock is current
        old = unix_to_units(time.time() - 600)
        r._from_autopilot(heartbeat(packer(FOLLOWER, 1, key, ts=old)), PX4)
        spoof = ("10.0.0.66", 4444)
        for _ in range(10):
            r._from_autopilot(heartbeat(packer(FOLLOWER, 1)), spoof)
            clock.t += 1.0
            r._provision()
        out.append(f"PX4 behind: {_setup_dests(r)}")
        # b) PX4 not heard yet: the spoofer alone, from the network, for 10 s.
        r = relay(key, tmp / "b", "udpin://0.0.0.0:14540", provision=True)
        for _ in range(10):
            r._from_autopilot(heartbeat(packer(FOLLOWER, 1)), spoof)
            clock.t += 1.0
            r._provision()
        out.append(f"PX4 not heard, spoofer alone: {_setup_dests(r)}")
        # c) a provisioned autopilot later heard unsigned again (its key wiped): the key goes once only.
        r = relay(key, tmp / "c", "serial:///dev/null:57600", provision=True)
        for _ in range(3):
            r._from_autopilot(heartbeat(packer(FOLLOWER, 1)), None)
            clock.t += 1.0
            r._provision()
        r._from_autopilot(heartbeat(packer(FOLLOWER, 1, key)), None)
        if hasattr(r, "_mark_provisioned"):
            asyncio.run(r._mark_provisioned())  # what the relay's task does once the autopilot signs
        first = len(_setups(r))
        r2 = relay(key, tmp / "c", "serial:///dev/null:57600", provision=True)
        for _ in range(5):
            r2._from_autopilot(heartbeat(packer(FOLLOWER, 1)), None)
            clock.t += 1.0
            r2._provision()
        out.append(f"serial: sent {first} time(s) the first run, {len(_setups(r2))} after a restart")
    finally:
        setattr(signing_relay, "time", real)  # noqa: B010
    return "2 SETUP_SIGNING: " + "; ".join(out)


def _setups(r: SigningRelay) -> list[list[tuple[str, int]]]:
    return [d for data, d in sent(r) if data[7:10] == (256).to_bytes(3, "little")]


def _setup_dests(r: SigningRelay) -> str:
    s = _setups(r)
    return f"sent {len(s)} time(s)" + (f" to {s[0]}" if s else "")


RACER = """
import os, socket, sys, time
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
s.bind(("127.0.0.1", 0))
if os.fork():
    os._exit(0)  # the child holds the socket, no longer a descendant of the prober
print(os.getpid(), s.getsockname()[1], flush=True)
time.sleep(float(sys.argv[1]))
"""


def probe_local_race(key: bytes, state: Path) -> str:
    if os.geteuid() != 0:
        return "3 MAVSDK side: skipped (needs root to hold a socket as another user)"
    racer = subprocess.Popen(
        ["/usr/bin/python3", "-c", RACER, "5"], stdout=subprocess.PIPE, user="nobody", text=True
    )
    assert racer.stdout is not None
    pid, port = (int(v) for v in racer.stdout.readline().split())
    racer.wait()
    try:
        r = relay(key, state, "udpin://0.0.0.0:14540")
        r._from_autopilot(heartbeat(packer(FOLLOWER, 1, key)), PX4)
        before = len(sent(r))
        r._from_mavsdk(command_long(packer(FOLLOWER, 195)), ("127.0.0.1", port))
        signed_for_racer = len(sent(r)) - before
        mav = local_socket()
        bind_mavsdk(r, mav)
        r._from_mavsdk(command_long(packer(FOLLOWER, 195)), mav.getsockname())
        mavsdk_sent = len(sent(r)) - before - signed_for_racer
        r._from_mavsdk(command_long(packer(FOLLOWER, 195)), ("127.0.0.1", port))
        after = len(sent(r)) - before - signed_for_racer - mavsdk_sent
        mav.close()
    finally:
        os.kill(pid, 9)
    return (
        f"3 MAVSDK side: a COMMAND_LONG from another user's socket that spoke first: "
        f"{'signed and sent' if signed_for_racer else 'refused'}; MAVSDK's own afterwards: "
        f"{'sent' if mavsdk_sent else 'dropped'}; the other socket again: {'sent' if after else 'refused'} "
        f"(counters: {dict((k, v) for k, v in r.counters.items() if k.startswith('local'))})"
    )


def probe_shares() -> str:
    now = [1_800_000_000.0]
    gate = ShareGate(ShareLimits(), lambda: now[0])
    topic = "wingman/leader/position"

    def share(lat: float, t: float) -> bytes:
        msg = {"lat_deg": lat, "lon_deg": 8.5, "alt_amsl_m": 500.0, "time_unix_s": t}
        return json.dumps(msg).encode()

    def offer(raw: bytes) -> str:
        try:
            gate.leader_position(topic, raw)
            return "accepted"
        except InboundRejectedError as exc:
            return f"refused ({exc.reason})"

    offer(share(47.0, now[0]))
    now[0] += 2.01
    forged_at = now[0]
    forged = offer(share(47.45, now[0]))  # 50 km north, after 2.01 s of silence
    now[0] += 0.1
    genuine = offer(share(47.0, now[0]))
    real_after_s: float | None = 0.1 if genuine == "accepted" else None
    while real_after_s is None and now[0] - forged_at < 3600:
        now[0] += 0.1  # the real leader keeps publishing at 10 Hz
        if offer(share(47.0, now[0])) == "accepted":
            real_after_s = now[0] - forged_at
    # A share stamped 0.5 s ahead, offered again byte for byte 2.2 s later.
    gate2 = ShareGate(ShareLimits(), lambda: now[0])
    ahead = share(47.0, now[0] + 0.5)
    first = offer_with(gate2, topic, ahead)
    now[0] += 2.2
    again = offer_with(gate2, topic, ahead)
    return (
        f"4 shares: forged 50 km jump after 2.01 s silence: {forged}; the real leader 0.1 s later: "
        f"{genuine}; real leader accepted again "
        f"{'never' if real_after_s is None else f'{real_after_s:.1f} s after the forged share'}; "
        f"a share 0.5 s ahead: {first}, the same bytes 2.2 s later: {again}"
    )


def offer_with(gate: ShareGate, topic: str, raw: bytes) -> str:
    try:
        gate.leader_position(topic, raw)
        return "accepted"
    except InboundRejectedError as exc:
        return f"refused ({exc.reason})"


def probe_vehicle_keys() -> str:
    leader_key, follower_key = secrets.token_bytes(32), secrets.token_bytes(32)
    try:  # each key bound to the topics its vehicle publishes, where keyrings can say so
        ring = Keyring(
            {"leader": leader_key, "follower1": follower_key},
            {"leader": ("wingman/leader/#",), "follower1": ("wingman/follower1/pose",)},  # type: ignore[call-arg,unused-ignore]
        )
    except TypeError:
        ring = Keyring({"leader": leader_key, "follower1": follower_key})
    now = 1_800_000_000.0
    gate = ShareGate(ShareLimits(), lambda: now, ring)
    msg = {"lat_deg": 47.0, "lon_deg": 8.5, "alt_amsl_m": 500.0, "time_unix_s": now}
    raw = sign(follower_key, "follower1", SHARE_DOMAIN, "wingman/leader/position", msg)
    verdict = offer_with(gate, "wingman/leader/position", raw)
    own = sign_share(Keyring({"leader": leader_key}), "wingman/leader/position", {**msg, "time_unix_s": now})
    gate2 = ShareGate(ShareLimits(), lambda: now, ring)
    return (
        f"5 keys: the leader's position signed by follower1's key: {verdict}; signed by the leader's: "
        f"{offer_with(gate2, 'wingman/leader/position', own)}"
    )


def probe_impostor_logs(key: bytes, state: Path) -> str:
    r = relay(key, state, "udpin://0.0.0.0:14540")
    r._from_autopilot(heartbeat(packer(FOLLOWER, 1, key)), PX4)
    counter = LineCounter()
    logger = logging.getLogger("companion.vehicle.signing")
    logger.addHandler(counter)
    logger.setLevel(logging.INFO)
    logger.propagate = False
    spoof = packer(FOLLOWER, 1)
    try:
        for i in range(10_000):
            r._from_autopilot(heartbeat(spoof), ("10.0.0.66", 30_000 + i))
    finally:
        logger.removeHandler(counter)
        logger.propagate = True
    size = len(json.dumps(r.stats()))
    return (
        f"6 impostors: 10,000 unsigned frames claiming system {FOLLOWER} from 10,000 ports: "
        f"{counter.lines} log lines, status section {size:,} bytes"
    )


def probe_mac() -> str:
    ring = Keyring({"operator1": secrets.token_bytes(32)})
    answers = []
    for key_id in ("operator1", "nobody"):
        msg = {"cmd": "land", "time_unix_s": 1.0, "key_id": key_id, "mac": "é" * 64}
        try:
            ring.verify(b"d", "t", msg)
            answers.append("accepted")
        except InboundRejectedError as exc:
            answers.append(f"rejected ({exc.reason})")
        except Exception as exc:
            answers.append(type(exc).__name__)
    return f"7 mac: a non-ASCII mac with an existing key id: {answers[0]}; with an unknown one: {answers[1]}"


def probe_installer() -> str:
    text = (Path(__file__).parents[1] / "systemd" / "install.sh").read_text()
    on_cmdline = any("mosquitto_passwd -b" in line for line in text.splitlines())
    answer = "yes" if on_cmdline else "no"
    return f"8 installer: the broker password on mosquitto_passwd's command line: {answer}"


def bench_setpoint(key: bytes, state: Path, n: int = 20_000) -> str:
    r = relay(key, state, "udpin://0.0.0.0:14540")
    mav = local_socket()
    bind_mavsdk(r, mav)
    r._from_autopilot(heartbeat(packer(FOLLOWER, 1, key)), PX4)
    p = packer(FOLLOWER, 195)
    frames = [setpoint(p) for _ in range(256)]
    addr = mav.getsockname()
    times = []
    for i in range(n):
        t0 = time.perf_counter_ns()
        r._from_mavsdk(frames[i % 256], addr)
        times.append(time.perf_counter_ns() - t0)
        if len(sent(r)) > 1000:
            sent(r).clear()
    mav.close()
    median_us = statistics.median(times) / 1000
    return f"cost: relay time per setpoint (MAVSDK -> signed -> send), median of {n:,}: {median_us:.1f} us"


def main() -> None:
    key = secrets.token_bytes(32)
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        print(probe_send_list(key, tmp / "1"))
        print(probe_provisioning(key, tmp / "2"))
        print(probe_local_race(key, tmp / "3"))
        print(probe_shares())
        print(probe_vehicle_keys())
        print(probe_impostor_logs(key, tmp / "6"))
        print(probe_mac())
        print(probe_installer())
        print(bench_setpoint(key, tmp / "b"))


if __name__ == "__main__":
    asyncio.run(asyncio.sleep(0))
    main()
