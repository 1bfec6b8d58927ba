"""The service commands only its own vehicle, only after a start, and only through its mission machine.

Against `sitl serve` (leader system 1, follower system 2), with `companion run` as a process on the
shipped `config/wingman.toml` (the environment overrides only what a test machine needs: ports, sockets,
the simulator's ground-truth boxes instead of the network, a closer slot). Both vehicles' API links reach
the service through one hostile UDP link (tests/service/hostile_mux.py): junk, truncated frames and a
spoofed third autopilot arrive beside them. One flight, in phases:

1. Only the leader on the link: the service refuses it in one line, exits 4 (systemd does not restart
   on it), never says READY=1, and ``companion health`` fails the autopilot check with the same line.
2. Both vehicles and the hostile traffic: the service flies system 2 to FOLLOW.
3. It is killed in flight (PX4 holds). Restarted with ``service.auto_start = true``, it observes: state
   ``observe``, no control message, an operator's land refused; ``companion start`` takes the vehicle.
4. Operator commands over MQTT go through the mission machine: a slot inside the minimum separation is
   refused; with GPS lost (MAV_CMD_INJECT_FAILURE from the ground station) a hold is refused.

Throughout, no control message (setpoint, mode, arming, navigation command, parameter) is addressed to
any system but 2.
"""

from __future__ import annotations

import asyncio
import json
import os
import secrets
import signal
import socket
import sys
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from pymavlink.dialects.v20 import common as mavlink2

from companion.kernel import compat
from companion.lab.evaluation.procs import Child
from companion.service.status import ServiceNotRunningError, query_status
from companion.telemetry.commands import sign_command
from tests.mosquitto import Collector, Mosquitto
from tests.service.hostile_mux import Mux, open_mux
from tests.service.sitl_service import REPO, Ports, open_gcs, sim_process

pytestmark = [pytest.mark.sitl, pytest.mark.mqtt_broker, pytest.mark.slow, pytest.mark.timeout(420)]

#: PX4's AUTO.LOITER (Hold) custom mode, as the follower reports it while nobody commands it.
CUSTOM_MODE_HOLD = 0x3040000


async def until(cond: Callable[[], bool], timeout_s: float, what: str, logs: Callable[[], str]) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}\n--- logs ---\n{logs()[-5000:]}")
        await asyncio.sleep(0.1)


def service_env(tmp_path: Path, ports: Ports, cam: Path, broker_port: int, key: Path) -> dict[str, str]:
    """The shipped config's overrides for this machine, as an operator would set them."""
    return {
        **os.environ,
        "PYTHONPATH": str(REPO),
        "WINGMAN_LINK__URL": f"udpin://127.0.0.1:{ports.client}",
        "WINGMAN_LINK__CONNECT_TIMEOUT_S": "3.0",
        "WINGMAN_CAMERA__PATH": str(cam),
        "WINGMAN_DETECTOR__RUNTIME": '"truth"',
        "WINGMAN_FORMATION__OFFSET_CAM_M": "[0.0, 0.0, 8.0]",
        "WINGMAN_MISSION__STALE_ESTIMATE_S": "1.5",
        "WINGMAN_MQTT__ENABLED": "true",
        "WINGMAN_MQTT__PORT": str(broker_port),
        "WINGMAN_MQTT__COMMAND_TOPIC": "true",
        "WINGMAN_MQTT__COMMAND_KEYS_FILE": str(key),
        "WINGMAN_SERVICE__STATE_DIR": str(tmp_path / "state"),
        "WINGMAN_MQTT__RECONNECT_MAX_S": "1.0",
        "WINGMAN_STATUS__SOCKET_PATH": str(tmp_path / "run" / "status.sock"),
        "WINGMAN_SERVICE__AUTO_START": "true",
        "WINGMAN_LOGGING__FORMAT": '"json"',
    }


def service(tmp_path: Path, env: dict[str, str], name: str, notify: Path) -> Child:
    args = [sys.executable, "-m", "companion", "run", "--config", str(REPO / "config/wingman.toml")]
    return Child(args, {**env, "NOTIFY_SOCKET": str(notify)}, tmp_path / f"{name}.log")


async def cli(env: dict[str, str], *args: str) -> tuple[int, str, str]:
    proc = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "companion",
        *args,
        "--config",
        str(REPO / "config/wingman.toml"),
        cwd=REPO,
        env=env,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
    )
    out, err = await asyncio.wait_for(proc.communicate(), 60)
    assert proc.returncode is not None
    return proc.returncode, out.decode(), err.decode()


def mission_state(sock: Path) -> str | None:
    try:
        return str(query_status(sock, timeout_s=2.0)["mission"]["state"])
    except ServiceNotRunningError:
        return None


async def publish(port: int, key: bytes, body: dict[str, Any]) -> None:
    import aiomqtt

    msg = {**body, "time_unix_s": time.time(), "nonce": secrets.token_hex(8)}
    topic = "wingman/follower1/cmd"
    async with aiomqtt.Client("127.0.0.1", port) as c:
        await c.publish(topic, sign_command(key, "gcs", topic, msg), qos=1)


def inject_gps_off(gcs_transport: asyncio.DatagramTransport, follower_gcs_port: int) -> None:
    mav = mavlink2.MAVLink(None, srcSystem=255, srcComponent=190)
    cmd = mav.command_long_encode(2, 1, mavlink2.MAV_CMD_INJECT_FAILURE, 0, 4, 1, 0, 0, 0, 0, 0)
    gcs_transport.sendto(cmd.pack(mav), ("127.0.0.1", follower_gcs_port))


async def test_the_service_flies_only_its_own_vehicle_only_when_started(tmp_path: Path) -> None:
    ports = Ports.pick()
    cam = tmp_path / "cam.sock"
    key_bytes = secrets.token_bytes(32)
    key = tmp_path / "cmd.keys"
    key.write_text(f"gcs {key_bytes.hex()}\n")
    key.chmod(0o600)
    notify_path = tmp_path / "notify.sock"
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    notify.bind(str(notify_path))
    notify.setblocking(False)
    sock = tmp_path / "run" / "status.sock"
    sim = sim_process(tmp_path, ports, cam)
    children: list[Child] = []
    mux: Mux | None = None
    gcs_transport = None
    datagrams: list[str] = []

    def logs() -> str:
        return "\n".join(c.tail(3000) for c in children) + "\n--- sitl ---\n" + sim.tail(1500)

    async def read_notify() -> None:
        loop = asyncio.get_running_loop()
        while True:
            datagrams.append((await loop.sock_recv(notify, 4096)).decode())

    with Mosquitto(tmp_path) as broker, notify:
        collector = Collector(broker.port, "wingman/follower1/#")
        env = service_env(tmp_path, ports, cam, broker.port, key)
        try:
            sim.start()
            gcs_transport, gcs = await open_gcs(ports.gcs_remote)
            mux = await open_mux(ports.api_remote, ports.follower_api, ports.client)
            async with compat.TaskGroup() as tg:
                tasks = [
                    tg.create_task(collector.run(), name="test.collector"),
                    tg.create_task(read_notify(), name="test.notify"),
                    tg.create_task(mux.run_hostile(), name="test.hostile"),
                ]
                await until(lambda: "running at" in sim.log() and cam.exists(), 90, "the simulator", logs)
                await asyncio.wait_for(collector.subscribed.wait(), 10)

                # -- 1. only the leader on the link: refused, exit 4, never READY
                mux.follower_enabled = False
                await until(lambda: 1 in mux.modes, 30, "the leader's heartbeat", logs)
                first = service(tmp_path, env, "refused", notify_path)
                children.append(first)
                first.start()
                rc = await first.wait(90)
                assert rc == 4, logs()
                refusal = [line for line in first.log().splitlines() if "refusing to command it" in line]
                assert refusal, first.log()[-3000:]
                assert "carries autopilot system 1 (the leader), not system 2" in refusal[-1]
                assert not any("READY=1" in d for d in datagrams)
                rc, out, _ = await cli(env, "health", "--timeout", "8")
                assert rc == 1
                autopilot = next(line for line in out.splitlines() if " autopilot " in line)
                assert autopilot.startswith("FAIL")
                assert "not system 2: refusing to command it" in autopilot

                # -- 2. both vehicles and hostile traffic: the service flies system 2
                mux.follower_enabled = True
                mux.hostile = True
                flying = service(tmp_path, env, "flying", notify_path)
                children.append(flying)
                flying.start()
                await until(lambda: mission_state(sock) == "follow", 180, "FOLLOW", logs)
                assert any("READY=1" in d for d in datagrams)
                assert mux.control_to(2), "the follower was never commanded"

                # -- 3. killed in flight; the restarted service only observes until started
                flying.signal(signal.SIGKILL)
                await flying.wait(10)
                await until(
                    lambda: mux.modes[2][-1][1] == CUSTOM_MODE_HOLD,
                    20,
                    "PX4's offboard-loss Hold",
                    logs,
                )
                t_restart = time.monotonic()
                restarted = service(tmp_path, env, "restarted", notify_path)
                children.append(restarted)
                restarted.start()
                await until(lambda: mission_state(sock) == "observe", 60, "OBSERVE", logs)
                await asyncio.sleep(8.0)
                assert mission_state(sock) == "observe"
                assert mux.control_to(2, since_s=t_restart) == [], [
                    s.msg.get_type() for s in mux.control_to(2, since_s=t_restart)
                ]
                assert all(mode == CUSTOM_MODE_HOLD for t, mode in mux.modes[2] if t > t_restart)
                rc, out, _ = await cli(env, "command", "land")
                assert rc == 1
                assert out.strip() == (
                    "land refused: the companion is only observing this vehicle "
                    "(run companion start to take it)"
                )
                rc, out, _ = await cli(env, "start")
                assert rc == 0, out
                await until(lambda: mission_state(sock) == "follow", 90, "FOLLOW after the start", logs)
                # The state turns before the first setpoint has crossed the link: wait for it to arrive.
                await until(
                    lambda: bool(mux.control_to(2, since_s=t_restart)), 20, "control after the start", logs
                )

                # -- 4. operator commands over MQTT go through the mission machine
                await publish(broker.port, key_bytes, {"cmd": "set_offset", "offset_cam_m": [0.0, 0.0, 1.5]})
                inject_gps_off(gcs_transport, ports.follower_gcs)
                await until(
                    lambda: mission_state(sock) == "follow_vision", 60, "vision-only flight (GPS lost)", logs
                )
                await publish(broker.port, key_bytes, {"cmd": "hold"})

                def events() -> list[dict[str, Any]]:
                    return [
                        e for e in collector.payloads("events") if e["kind"] in ("command", "command_refused")
                    ]

                # The land and start given over the status socket earlier are events too: wait for these two.
                await until(
                    lambda: {"set_offset", "hold"} <= {e["data"]["cmd"] for e in events()},
                    30,
                    "the replies to both MQTT commands",
                    logs,
                )
                for t in tasks:
                    t.cancel()
        except BaseException:
            print(logs())
            raise
        finally:
            for c in children:
                await c.stop(5.0)
            await sim.stop()
            if mux is not None:
                mux.close()
            if gcs_transport is not None:
                gcs_transport.close()

    # MQTT QoS 1 delivers at least once: a second copy of a command is rejected as a replay, and that is
    # the only rejection these signed, fresh commands may meet.
    rejected = [e for e in collector.payloads("events") if e["kind"] == "command_rejected"]
    assert all(e["data"]["reason"] == "REPLAYED" for e in rejected), rejected
    replies = {e["data"]["cmd"]: e for e in events()}
    assert replies["set_offset"]["kind"] == "command_refused"
    assert replies["set_offset"]["text"].startswith("set_offset refused: slot 1.5 m from the leader")
    assert replies["hold"]["kind"] == "command_refused"
    assert (
        replies["hold"]["text"]
        == "hold refused: hold needs GPS (PX4 cannot hold without a position); land instead"
    )
    assert mux.hostile_datagrams > 20
    print(
        json.dumps(
            {
                "messages_from_the_service": len(mux.sent),
                "control_to_system_2": len(mux.control_to(2)),
                "hostile_datagrams": mux.hostile_datagrams,
                "service_datagrams": mux.service_datagrams,
                "unparsed_datagrams": mux.unparsed_datagrams,
                "by_type": dict(Counter(s.msg.get_type() for s in mux.sent)),
                "sources": sorted({(s.msg.get_srcSystem(), s.msg.get_srcComponent()) for s in mux.sent}),
            }
        )
    )
    # The service's STATUSTEXTs reach the ground station's port, forwarded as PX4 forwards its onboard link.
    assert "WM follow: leader acquired" in gcs.companion_texts, gcs.companion_texts
    # Nothing that changes what a vehicle does went to the leader or the spoofed system 3.
    strays = mux.control_not_to(2)
    assert strays == [], [(s.target_system, s.msg.get_type()) for s in strays]
