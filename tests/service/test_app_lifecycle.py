"""FollowerService lifecycle with a scripted mission (pure state logic), real sockets and a real broker."""

from __future__ import annotations

import asyncio
import contextlib
import gc
import json
import os
import socket
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import aiomqtt
import pytest

from companion.app import FollowerService, Parts, PartsContext
from companion.config import Config
from companion.kernel import compat
from companion.kernel.clock import MonotonicClock
from companion.kernel.errors import LinkLostError
from companion.mission.types import OperatorCommand, OperatorRequest, OperatorVerdict
from companion.service.ports import (
    FlightSnapshot,
    LeaderSummary,
    OnboardComputerStatus,
    StateChange,
    VehicleSummary,
)
from companion.service.status import query_status
from companion.service.systemd import NotifyConfig, SystemdNotifier
from tests.mosquitto import Mosquitto

pytestmark = pytest.mark.timeout(60)


class ScriptedMission:
    """A stand-in for flight's runner: walks a fixed state list at 20 Hz; no physics, no I/O."""

    def __init__(
        self, clock: MonotonicClock, *, land_s: float = 0.3, fail_after_s: float | None = None
    ) -> None:
        self.clock = clock
        self.state = "wait_link"
        self.reason = "starting"
        self.since_s = clock.now_s()
        self.last_step_s: float | None = None
        self.on_change: Callable[[StateChange], None] = lambda c: None
        self.shutdown = False
        self.land_s = land_s
        self.fail_after_s = fail_after_s
        self.hang = False
        self.commands: list[str] = []
        self.history: list[str] = [self.state]
        self.started = False

    def set_on_change(self, callback: Callable[[StateChange], None]) -> None:
        self.on_change = callback

    def _go(self, state: str, reason: str) -> None:
        change = StateChange(self.clock.now_s(), self.state, state, reason, reason.upper(), "notice")
        self.state, self.reason, self.since_s = state, reason, self.clock.now_s()
        self.history.append(state)
        self.on_change(change)

    def _touched_down(self) -> bool:
        return self.state == "px4_land" and self.clock.now_s() - self.since_s > self.land_s

    def snapshot(self) -> FlightSnapshot:
        flying = self.state in ("follow", "px4_hold", "px4_land") and not self._touched_down()
        mode = {"follow": "offboard", "px4_land": "land"}.get(self.state, "hold")
        return FlightSnapshot(
            state=self.state,
            reason=self.reason,
            state_age_s=self.clock.now_s() - self.since_s,
            last_step_s=self.last_step_s,
            vehicle=VehicleSummary(
                connected=True,
                heartbeat_age_s=0.1,
                armed=self.state not in ("wait_link", "disarmed") and not self._touched_down(),
                in_air=flying,
                flight_mode=mode,
                gps_fix_type=3,
                gps_satellites=10,
                position_valid=True,
                p_ned_m=(1.0, 2.0, -5.0),
            ),
            leader=LeaderSummary(
                "confirmed", (5.0, 0.0, 0.0), cov_ned_m2=((0.04, 0, 0), (0, 0.04, 0), (0, 0, 0.09))
            )
            if self.state == "follow"
            else None,
        )

    async def run(self) -> None:
        start = self.clock.now_s()
        t_land = None
        while True:
            if not self.hang:
                self.last_step_s = self.clock.now_s()
            now = self.clock.now_s()
            if self.fail_after_s is not None and now - start > self.fail_after_s:
                raise LinkLostError("autopilot link lost for good")
            if self.state == "wait_link":
                self._go("follow", "leader acquired")
            elif self.shutdown and self.state == "follow":
                self._go("px4_hold", "shutdown requested")
                t_land = now
            elif self.state == "px4_hold" and t_land is not None and now - t_land > self.land_s:
                self._go("px4_land", "shutdown hold elapsed: landing")
                return  # like flight's runner: PX4 lands by itself from here
            await asyncio.sleep(0.05)

    def request_start(self, *, takeover: bool = True) -> None:
        self.started = True

    def request_shutdown(self) -> None:
        self.shutdown = True

    async def command(self, req: OperatorRequest) -> OperatorVerdict:
        await asyncio.sleep(0.05)  # answered after the next step, as the real runner does
        if req.command == OperatorCommand.START:
            self.started = True
            return OperatorVerdict(req.command, True, f"{self.state} -> {self.state} (scripted)")
        self.commands.append(req.command.value)
        return OperatorVerdict(req.command, True, "done")


class RecordingGcs:
    def __init__(self) -> None:
        self.texts: list[tuple[str, str]] = []
        self.onboard: list[OnboardComputerStatus] = []

    async def send_status_text(self, text: str, severity: str) -> None:
        self.texts.append((text, severity))

    async def send_onboard_computer_status(self, status: OnboardComputerStatus) -> None:
        self.onboard.append(status)


@pytest.fixture
def notify_socket(tmp_path: Path) -> Iterator[tuple[str, socket.socket]]:
    path = tmp_path / "notify.sock"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as rx:
        rx.bind(str(path))
        rx.setblocking(False)
        yield str(path), rx


def exists(path: str | Path) -> bool:
    return os.path.exists(path)


def drain(rx: socket.socket) -> list[str]:
    out = []
    with contextlib.suppress(BlockingIOError):
        while True:
            out.append(rx.recv(4096).decode())
    return out


def make_service(
    tmp_path: Path,
    mission: ScriptedMission,
    notify_path: str | None,
    *,
    freeze_heap: bool = False,
    **cfg_kw: Any,
) -> tuple[FollowerService, RecordingGcs]:
    data: dict[str, Any] = {
        "status": {"socket_path": str(tmp_path / "run" / "status.sock")},
        "service": {"shutdown_timeout_s": 5.0, "onboard_status_rate_hz": 10.0, "system_sample_period_s": 0.2},
    }
    for k, v in cfg_kw.items():
        data.setdefault(k, {}).update(v)
    cfg = Config.model_validate(data)
    gcs = RecordingGcs()

    async def open_parts(stack: contextlib.AsyncExitStack, ctx: PartsContext) -> Parts:
        return Parts(mission=mission, gcs=gcs)

    notifier = SystemdNotifier(NotifyConfig(notify_path, 0.4))
    notifier.__enter__()
    svc = FollowerService(
        cfg,
        open_parts,
        clock=mission.clock,
        wall_time_s=time.time,
        notifier=notifier,
        freeze_heap=freeze_heap,
    )
    return svc, gcs


async def wait_until(cond: Callable[[], bool], timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < deadline, "timed out"
        await asyncio.sleep(0.02)


async def test_stop_request_lands_then_exits_zero(
    tmp_path: Path, notify_socket: tuple[str, socket.socket]
) -> None:
    path, rx = notify_socket
    clock = MonotonicClock()
    mission = ScriptedMission(clock)
    svc, gcs = make_service(tmp_path, mission, path, freeze_heap=True)
    sock = Path(svc.cfg.status.socket_path)
    frozen_before = gc.get_freeze_count()
    async with compat.TaskGroup() as tg:
        task = tg.create_task(svc.run())
        await wait_until(lambda: mission.state == "follow" and exists(sock))
        # The daemon's heap as it flies: what was open at start is out of the collector's reach.
        assert gc.get_freeze_count() > frozen_before + 10_000
        await asyncio.sleep(0.5)
        started = await asyncio.to_thread(query_status, sock, "start")
        assert started == {"ok": True, "detail": "start: follow -> follow (scripted)"}
        assert mission.started
        snap = await asyncio.to_thread(query_status, sock, "status")
        health = await asyncio.to_thread(query_status, sock, "health")
        svc.request_stop("SIGTERM")
        svc.request_stop("SIGTERM")  # a second signal changes nothing
    assert task.result() == 0
    assert gc.get_freeze_count() == frozen_before  # given back when the service returns
    assert mission.history == ["wait_link", "follow", "px4_hold", "px4_land"]
    assert not mission.snapshot().vehicle.armed  # the service waited for the disarm before exiting
    assert not exists(sock)
    # status snapshot
    assert snap["mission"]["state"] == "follow"
    assert snap["link"]["connected"] is True
    assert snap["gps"]["fix_type"] == 3
    assert snap["leader"]["status"] == "confirmed"
    assert snap["leader"]["range_m"] == 5.0
    assert snap["system"]["mem_total_mib"] > 0
    assert {c["name"] for c in snap["components"]} >= {"mission", "monitor"}
    assert health["service_running"] is True
    assert all(c["ok"] for c in health["checks"]), health
    # systemd saw READY, STATUS, WATCHDOG and STOPPING
    msgs = "\n".join(drain(rx))
    assert "READY=1" in msgs
    assert "WATCHDOG=1" in msgs
    assert "STOPPING=1" in msgs
    assert "STATUS=follow: leader acquired" in msgs
    assert "EXTEND_TIMEOUT_USEC=15000000" in msgs
    # the ground station got one STATUSTEXT per transition and computer status
    assert [t for t, _ in gcs.texts] == [
        "WM follow: leader acquired",
        "WM px4_hold: shutdown requested",
        "WM px4_land: shutdown hold elapsed: landing",
    ]
    assert gcs.onboard
    f = gcs.onboard[-1].fields
    assert isinstance(f["ram_total"], int)
    assert f["ram_total"] > 0


async def test_safe_action_that_never_completes_exits_one(tmp_path: Path) -> None:
    mission = ScriptedMission(MonotonicClock(), land_s=60.0)
    svc, _ = make_service(tmp_path, mission, None, service={"shutdown_timeout_s": 0.5})
    async with compat.TaskGroup() as tg:
        task = tg.create_task(svc.run())
        await wait_until(lambda: mission.state == "follow")
        svc.request_stop("SIGINT")
    assert task.result() == 1
    assert mission.state == "px4_hold"


async def test_mission_failure_propagates_and_socket_is_removed(tmp_path: Path) -> None:
    mission = ScriptedMission(MonotonicClock(), fail_after_s=0.3)
    svc, _ = make_service(tmp_path, mission, None)
    with pytest.raises(compat.ExceptionGroup) as eg:
        await svc.run()
    assert eg.group_contains(LinkLostError)
    assert not exists(svc.cfg.status.socket_path)


async def test_watchdog_withheld_when_the_mission_hangs(
    tmp_path: Path, notify_socket: tuple[str, socket.socket]
) -> None:
    path, rx = notify_socket
    mission = ScriptedMission(MonotonicClock())
    svc, _ = make_service(tmp_path, mission, path)
    async with compat.TaskGroup() as tg:
        task = tg.create_task(svc.run())
        await wait_until(lambda: mission.state == "follow")
        await asyncio.sleep(0.5)
        assert "WATCHDOG=1" in drain(rx)
        mission.hang = True
        await asyncio.sleep(3.5)  # > the 3 s mission staleness
        drain(rx)
        await asyncio.sleep(1.0)
        assert "WATCHDOG=1" not in drain(rx)
        mission.hang = False
        await asyncio.sleep(1.0)
        assert "WATCHDOG=1" in drain(rx)
        svc.request_stop("SIGTERM")
    assert task.result() == 0


@pytest.mark.mqtt_broker
async def test_mqtt_telemetry_and_commands_through_the_service(tmp_path: Path) -> None:
    key = tmp_path / "cmd.keys"
    key.write_text(f"gcs {(b's' * 32).hex()}\n")
    key.chmod(0o600)
    with Mosquitto(tmp_path) as broker:
        mission = ScriptedMission(MonotonicClock())
        svc, _ = make_service(
            tmp_path,
            mission,
            None,
            mqtt={
                "enabled": True,
                "port": broker.port,
                "command_topic": True,
                "command_keys_file": str(key),
                "reconnect_min_s": 0.1,
                "reconnect_max_s": 0.2,
            },
        )
        from companion.telemetry.commands import sign_command
        from companion.telemetry.mqtt_setup import load_mqtt_credentials

        svc._mqtt_credentials = load_mqtt_credentials(svc.cfg.mqtt)
        got: list[tuple[str, dict[str, Any]]] = []
        subscribed = asyncio.Event()

        async def collect() -> None:
            async with aiomqtt.Client("127.0.0.1", broker.port) as c:
                await c.subscribe("wingman/follower1/#", qos=1)
                subscribed.set()
                async for m in c.messages:
                    assert isinstance(m.payload, bytes)
                    got.append((str(m.topic).rsplit("/", 1)[1], json.loads(m.payload)))

        async with compat.TaskGroup() as tg:
            col = tg.create_task(collect())
            # Events are not retained: the first state change is only seen by a subscriber
            # that is already there when the service starts.
            await asyncio.wait_for(subscribed.wait(), 10.0)
            task = tg.create_task(svc.run())
            await wait_until(lambda: any(t == "pose" for t, _ in got) and any(t == "health" for t, _ in got))
            async with aiomqtt.Client("127.0.0.1", broker.port) as gcs:
                msg = {"cmd": "hold", "time_unix_s": time.time(), "nonce": "x1"}
                topic = "wingman/follower1/cmd"
                await gcs.publish(topic, sign_command(b"s" * 32, "gcs", topic, msg), qos=1)
            await wait_until(lambda: mission.commands == ["hold"])
            svc.request_stop("SIGTERM")
            await task
            await wait_until(lambda: any(t == "state" and not p["online"] for t, p in got))
            col.cancel()
    assert task.result() == 0
    states = [p["state"] for t, p in got if t == "state"]
    assert "follow" in states
    assert states[-1] == "OFFLINE"
    assert states[-2] == "px4_land"
    events = [p for t, p in got if t == "events"]
    kinds = [e["kind"] for e in events]
    assert kinds.count("state_change") == 3
    assert "shutdown" in kinds
    assert "command" in kinds
    pose = next(p for t, p in got if t == "pose" and p["leader"])
    assert pose["leader"]["cov_ned_m2"][2][2] == 0.09
