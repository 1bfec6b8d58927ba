"""``FollowerService``: the one asyncio service. Builds the parts, owns the TaskGroup and the lifecycle.

Resources (autopilot link, camera, detector, status socket) are entered on one ``AsyncExitStack`` and
closed in reverse order whatever happens. Work runs as named tasks in one ``TaskGroup``:

- ``companion.mission``     the flight (critical: if it raises, the service ends and PX4's offboard-loss
                            failsafe takes over; a lost link is a state the mission handles, not an error)
- ``companion.perception``  camera -> detector -> tracker (supervised: restarted with backoff)
- ``companion.mqtt``        telemetry (supervised)
- ``companion.monitor``     machine readings, liveness, sd_notify STATUS=
- ``companion.gcs``         STATUSTEXT and ONBOARD_COMPUTER_STATUS to the ground station
- ``companion.watchdog``    WATCHDOG=1 while the critical loops are alive
- ``companion.lifecycle``   waits for SIGTERM/SIGINT, then the safe action, bounded

A stop request (SIGTERM) never just cancels the flight: the mission performs ``mission.shutdown_action``
(hold, then land and disarm, by default) and the service exits 0 once it has, or 1 when it could not
within ``service.shutdown_timeout_s``.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
import random
from collections.abc import Awaitable, Callable, Mapping
from pathlib import Path
from typing import Any

from companion.config import Config
from companion.kernel import compat
from companion.kernel.clock import Clock
from companion.mission.types import OperatorCommand, OperatorRequest, OperatorVerdict
from companion.service.ground_station import GroundStation
from companion.service.health import HealthBoard
from companion.service.latency import LatencyStats
from companion.service.operator import parse_command
from companion.service.parts import Parts, PartsContext, PartsFactory
from companion.service.perception_loop import PerceptionLoop
from companion.service.ports import FlightPort, FlightSnapshot, StateChange
from companion.service.reports import (
    STATUS_SCHEMA_VERSION,
    health_msg,
    live_health_json,
    mqtt_severity,
    pose_msg,
    state_msg,
    status_json,
    status_line,
)
from companion.service.status import StatusServer
from companion.service.supervise import Backoff, supervise
from companion.service.sysinfo import SystemMonitor, SystemReading
from companion.service.systemd import SystemdNotifier
from companion.telemetry.commands import Command, HighWaterMarks
from companion.telemetry.mqtt import MqttReporter, TelemetrySources
from companion.telemetry.mqtt_setup import MqttCredentials
from companion.telemetry.payloads import HealthMsg, PoseMsg, StateMsg

log = logging.getLogger(__name__)

__all__ = ["STATUS_SCHEMA_VERSION", "FollowerService", "Parts", "PartsContext", "PartsFactory"]

MISSION = "mission"
MQTT = "mqtt"
MONITOR = "monitor"
#: The mission steps at the setpoint rate (>= 2 Hz); this long without a step means it hangs.
_MISSION_STALE_S = 3.0


class _Finished(Exception):  # noqa: N818 (a control-flow signal, not an error)
    """Raised inside the TaskGroup to end it once the mission is over."""


class FollowerService:
    """The service. ``await run()`` returns the process exit code.

    Args:
        cfg: the whole config (validated at the CLI edge).
        open_parts: opens the mission/perception parts on the service's exit stack.
        clock: the service clock.
        wall_time_s: wall-clock time for MQTT stamps and command freshness.
        notifier: sd_notify (a no-op when not under systemd); entered by the caller.
        system_monitor: machine readings.
        mqtt_credentials: password, TLS, command and formation keys, loaded at the edge.
        command_marks: the operators' last command times, kept in ``service.state_dir`` (None: memory).
        rng: jitter for backoffs.
        freeze_heap: once everything is open, move it out of the garbage collector's reach (``gc.freeze``):
            the daemon and the lab's real path ask it (undone when the service returns).
    """

    def __init__(
        self,
        cfg: Config,
        open_parts: PartsFactory,
        *,
        clock: Clock,
        wall_time_s: Callable[[], float],
        notifier: SystemdNotifier,
        system_monitor: SystemMonitor | None = None,
        mqtt_credentials: MqttCredentials | None = None,
        command_marks: HighWaterMarks | None = None,
        rng: random.Random | None = None,
        freeze_heap: bool = False,
    ) -> None:
        self.cfg = cfg
        self._freeze_heap = freeze_heap
        self._open_parts = open_parts
        self.clock = clock
        self._wall_time_s = wall_time_s
        self.notifier = notifier
        self._sysmon = system_monitor or SystemMonitor()
        self._mqtt_credentials = mqtt_credentials or MqttCredentials()
        self._command_marks = command_marks
        self._rng = rng or random.Random()  # noqa: S311 (jitter, not crypto)
        self.health = HealthBoard(clock)
        self.latency = LatencyStats()
        self._parts: Parts | None = None
        self.mqtt: MqttReporter | None = None
        self._system: SystemReading | None = None
        self.ground_station = GroundStation(
            cfg.service.onboard_status_rate_hz,
            system=lambda: self._system,
            uptime_s=lambda: self.clock.now_s() - self._started_s,
            wall_time_s=wall_time_s,
        )
        self._stop_reason: str | None = None
        self._stop = asyncio.Event()
        self._mission_done = asyncio.Event()
        self._farewell_done = False
        self._started_s = clock.now_s()
        self.exit_code = 0
        self.transitions = 0

    # ---- control from the edge ------------------------------------------------------------------------

    def request_stop(self, reason: str) -> None:
        """Begin the safe shutdown (idempotent; call from a signal handler on the loop)."""
        if self._stop_reason is not None:
            log.warning("%s: already stopping (%s); the safe action continues", reason, self._stop_reason)
            return
        self._stop_reason = reason
        self._stop.set()

    @property
    def stopping(self) -> bool:
        return self._stop_reason is not None

    # ---- the service ----------------------------------------------------------------------------------

    async def run(self) -> int:
        """Open everything, run until the mission is over, close everything; the exit code."""
        self._started_s = self.clock.now_s()
        self.health.register(MISSION, critical=True, stale_after_s=_MISSION_STALE_S)
        self.health.register(MONITOR, critical=True, stale_after_s=max(5.0, 3 * self._monitor_period_s))
        async with contextlib.AsyncExitStack() as stack:
            self.notifier.status("starting: opening link, camera and detector")
            parts = await self._open_parts(stack, PartsContext(self.clock, self.health, self.latency))
            self._parts = parts
            if parts.perception is not None:
                PerceptionLoop.register(self.health)
                stack.callback(parts.perception.close)
            await stack.enter_async_context(
                StatusServer(
                    self._socket_path(),
                    {
                        "status": self.status_snapshot,
                        "health": self.live_health,
                        "start": self._request_start,
                    },
                    commands={"command": self._operator_command},
                )
            )
            if self.cfg.mqtt.enabled:
                self.mqtt = self._build_mqtt(parts)
                self.health.register(MQTT, critical=False)
            parts.mission.set_on_change(self._on_change)
            if self._freeze_heap:
                # What is open now (torch, the model, the link) lives as long as the process. A full
                # collection walks all of it (70-150 ms for ~200k objects on a 2-core x86), holding the
                # control loop: rare in flight, but never needed for these. Garbage is collected first.
                gc.collect()
                gc.freeze()
                stack.callback(gc.unfreeze)
            try:
                async with compat.TaskGroup() as tg:
                    for name, loop in parts.background.items():
                        tg.create_task(_run_background(name, loop), name=name)
                    tg.create_task(self._run_mission(parts.mission), name="companion.mission")
                    if parts.perception is not None:
                        tg.create_task(
                            self._supervised("perception", parts.perception.run), name="companion.perception"
                        )
                    if self.mqtt is not None:
                        tg.create_task(self._supervised(MQTT, self.mqtt.run), name="companion.mqtt")
                    tg.create_task(self._monitor(), name="companion.monitor")
                    if parts.gcs is not None:
                        tg.create_task(self.ground_station.run(parts.gcs), name="companion.gcs")
                    tg.create_task(self._watchdog(), name="companion.watchdog")
                    tg.create_task(self._lifecycle(parts.mission), name="companion.lifecycle")
                    tg.create_task(self._ready(parts), name="companion.ready")
            except compat.BaseExceptionGroup as group:
                # The mission's end ends the group; anything else that failed with it is re-raised.
                _, rest = group.split(_Finished)
                if rest is not None:
                    raise rest from None
        log.info("service stopped (exit %d)", self.exit_code)
        return self.exit_code

    async def _ready(self, parts: Parts) -> None:
        """READY=1 for systemd once the link to the configured vehicle is up (the right system id)."""
        if parts.link_ready is not None:
            await parts.link_ready()
        self.notifier.ready(self._status_line(parts.mission.snapshot()))
        log.info(
            "service ready: vehicle %s, status on %s, mqtt %s",
            self.cfg.vehicle_id,
            self._socket_path(),
            "on" if self.mqtt else "off",
        )

    async def _run_mission(self, mission: FlightPort) -> None:
        if self.cfg.service.auto_start:
            # From the ground only: a vehicle found flying waits for an operator's start.
            mission.request_start(takeover=False)
        try:
            await mission.run()
            await self._until_down(mission)
        except Exception as exc:
            await self._farewell(f"mission failed: {type(exc).__name__}: {exc}")
            raise
        self._mission_done.set()
        snap = mission.snapshot()
        log.info("mission over: %s (%s)", snap.state, snap.reason)
        await self._farewell(f"mission over: {snap.state}")
        raise _Finished

    async def _until_down(self, mission: FlightPort) -> None:
        """The mission handed a landing to PX4 and returned: watch it until touchdown and disarm."""
        v = mission.snapshot().vehicle
        if not (v.armed and v.flight_mode == "land"):
            return
        log.info("PX4 is landing the vehicle; waiting for touchdown and disarm")
        while True:
            v = mission.snapshot().vehicle
            if not v.armed:
                log.info("vehicle disarmed")
                return
            if not v.connected:
                log.warning("autopilot link lost while PX4 lands; not waiting for the disarm")
                return
            self.health.beat(MISSION, detail="PX4 landing")
            await asyncio.sleep(0.2)

    async def _request_start(self) -> dict[str, Any]:
        """``start`` over the status socket: what the mission did with it, or why it refused."""
        assert self._parts is not None  # noqa: S101
        if self.stopping:
            verdict = OperatorVerdict(
                OperatorCommand.START, False, f"the service is stopping ({self._stop_reason})"
            )
        else:
            verdict = await self._parts.mission.command(OperatorRequest(OperatorCommand.START))
        return self._answered(verdict)

    async def _operator_command(self, req: Mapping[str, Any]) -> dict[str, Any]:
        """A command from the status socket (operator.py's JSON): through the mission machine's checks."""
        assert self._parts is not None  # noqa: S101
        cmd = parse_command(req)
        if isinstance(cmd, str):
            return {"ok": False, "detail": cmd}
        return self._answered(await self._parts.mission.command(cmd))

    def _answered(self, verdict: OperatorVerdict) -> dict[str, Any]:
        """The status socket's answer to an operator, also on MQTT's ``events`` as an MQTT command's is."""
        reply, name = str(verdict), verdict.command.value
        if self.mqtt is not None:
            if verdict.taken:
                self.mqtt.event("command", reply, "notice", cmd=name, source="status socket")
            else:
                self.mqtt.event("command_refused", reply, "warning", cmd=name, source="status socket")
        return {"ok": verdict.taken, "detail": reply}

    async def _lifecycle(self, mission: FlightPort) -> None:
        await self._stop.wait()
        timeout_s = self.cfg.service.shutdown_timeout_s
        action = self.cfg.mission.shutdown_action
        log.warning(
            "%s: performing the safe action (%s), at most %.0f s", self._stop_reason, action, timeout_s
        )
        self.notifier.stopping(f"{self._stop_reason}: {action}")
        self.notifier.extend_timeout(timeout_s + 10.0)
        if self.mqtt is not None:
            self.mqtt.event("shutdown", f"{self._stop_reason}: {action}", "notice", action=action)
        mission.request_shutdown()
        try:
            async with compat.timeout(timeout_s):
                await self._mission_done.wait()
        except TimeoutError:
            snap = mission.snapshot()
            log.error(
                "safe action not complete after %.0f s (state %s); exiting anyway", timeout_s, snap.state
            )
            self.exit_code = 1
            await self._farewell(f"shutdown timed out in {snap.state}")
            raise _Finished from None

    async def _farewell(self, reason: str) -> None:
        """Last words on MQTT (final state, ``online: false``), bounded; once."""
        if self._farewell_done:
            return
        self._farewell_done = True
        if self.mqtt is not None:
            await self.mqtt.stop(reason, timeout_s=2.0)

    async def _supervised(self, name: str, run: Callable[[], Awaitable[None]]) -> None:
        backoff = Backoff(0.5, 30.0, self._rng)
        await supervise(name, run, self.health, self.clock, backoff)

    @property
    def _monitor_period_s(self) -> float:
        return min(1.0, self.cfg.service.system_sample_period_s)

    async def _monitor(self) -> None:
        """Machine readings, mission liveness, and the one-line systemd STATUS=; never per frame."""
        period_s = self._monitor_period_s
        next_sample_s = self.clock.now_s()
        last_step_s: float | None = None
        last_line = ""
        assert self._parts is not None  # noqa: S101 (set before the TaskGroup starts)
        mission = self._parts.mission
        while True:
            now_s = self.clock.now_s()
            if now_s >= next_sample_s:
                self._system = self._sysmon.read()
                next_sample_s = now_s + self.cfg.service.system_sample_period_s
            snap = mission.snapshot()
            if snap.last_step_s is not None and snap.last_step_s != last_step_s:
                last_step_s = snap.last_step_s
                self.health.beat(MISSION, detail=snap.state)
            if self.mqtt is not None:
                self.health.beat(MQTT, ok=self.mqtt.connected, detail=self._mqtt_detail())
            self.health.beat(MONITOR)
            line = self._status_line(snap)
            if line != last_line:
                self.notifier.status(line)
                last_line = line
            await asyncio.sleep(period_s)

    async def _watchdog(self) -> None:
        interval_s = self.notifier.watchdog_interval_s
        if interval_s is None:
            return
        withheld = False
        while True:
            if self.health.critical_alive():
                self.notifier.watchdog()
                if withheld:
                    log.warning("watchdog resumed")
                withheld = False
            elif not withheld:
                hung = [c.name for c in self.health.snapshot() if c.critical and not c.alive]
                log.error(
                    "watchdog withheld: %s not alive; systemd will restart the service", ", ".join(hung)
                )
                withheld = True
            await asyncio.sleep(interval_s)

    # ---- transitions ----------------------------------------------------------------------------------

    def _on_change(self, change: StateChange) -> None:
        self.transitions += 1
        if self.mqtt is not None:
            self.mqtt.state_changed()
            self.mqtt.event(
                "state_change",
                f"{change.from_state} -> {change.to_state}: {change.reason}",
                mqtt_severity(change.severity),
                **{
                    "from": change.from_state,
                    "to": change.to_state,
                    "reason": change.reason_code,
                    "detail": change.detail,
                },
            )
        parts = self._parts
        if (
            self.cfg.service.statustext
            and parts is not None
            and parts.gcs is not None
            and not parts.mission_sends_statustext
        ):
            text = change.statustext or f"WM {change.to_state}: {change.reason}"[:50]
            self.ground_station.queue_statustext(text, change.severity)

    @property
    def statustext_dropped(self) -> int:
        """STATUSTEXTs dropped because the ground station's queue was full."""
        return self.ground_station.statustext_dropped

    # ---- snapshots ------------------------------------------------------------------------------------

    def _socket_path(self) -> Path:
        return Path(self.cfg.status.socket_path)

    def _status_line(self, snap: FlightSnapshot) -> str:
        return status_line(snap, self._stop_reason)

    def _mqtt_detail(self) -> str:
        m = self.mqtt
        if m is None:
            return "off"
        s = m.stats()
        link = "connected" if s["connected"] else "disconnected"
        return f"{link}, {s['buffered']} buffered, {s['dropped']} dropped"

    def frames(self) -> dict[str, int]:
        p = self._parts.perception if self._parts is not None else None
        return p.counters() if p is not None else {}

    def status_snapshot(self) -> dict[str, Any]:
        """The JSON the status endpoint serves (``companion status``)."""
        assert self._parts is not None  # noqa: S101 (the server starts after the parts)
        return status_json(
            self.cfg,
            self._parts.mission.snapshot(),
            self.clock,
            started_s=self._started_s,
            stop_reason=self._stop_reason,
            transitions=self.transitions,
            latency_ms=self.latency.summary,
            frames=self.frames,
            system=self._system,
            components=self.health.snapshot,
            mqtt=self.mqtt.stats if self.mqtt is not None else None,
            extra_status=self._parts.extra_status,
        )

    def live_health(self) -> dict[str, Any]:
        """The running service's own checks (``companion health`` merges them with its preflight)."""
        assert self._parts is not None  # noqa: S101
        snap = self._parts.mission.snapshot()
        mqtt = self.mqtt
        return live_health_json(
            snap,
            [c for c in self.health.snapshot() if c.name != MQTT],
            (lambda: (mqtt.connected, self._mqtt_detail())) if mqtt is not None else None,
        )

    # ---- MQTT -----------------------------------------------------------------------------------------

    def _build_mqtt(self, parts: Parts) -> MqttReporter:
        on_leader = parts.on_leader_position if self.cfg.leader.shared_position == "mqtt" else None
        return MqttReporter(
            self.cfg.mqtt,
            self.cfg.vehicle_id,
            TelemetrySources(state=self._state_msg, pose=self._pose_msg, health=self._health_msg),
            self.clock,
            self._wall_time_s,
            credentials=self._mqtt_credentials,
            rng=self._rng,
            on_command=self._on_command if self.cfg.mqtt.command_topic else None,
            on_leader_position=on_leader,
            on_neighbour_pose=parts.on_neighbour_pose,
            neighbour_ids=self.cfg.formation.neighbour_ids,
            command_marks=self._command_marks,
        )

    async def _on_command(self, cmd: Command) -> OperatorVerdict:
        """An MQTT operator command: through the mission machine's checks, like the CLI's."""
        assert self._parts is not None  # noqa: S101
        return await self._parts.mission.command(OperatorRequest(cmd.name, cmd.offset_cam_m))

    def _state_msg(self) -> StateMsg:
        assert self._parts is not None  # noqa: S101
        return state_msg(self._parts.mission.snapshot())

    def _pose_msg(self) -> PoseMsg | None:
        assert self._parts is not None  # noqa: S101
        return pose_msg(self._parts.mission.snapshot())

    def _health_msg(self) -> HealthMsg:
        return health_msg(
            self.health.snapshot(),
            self._system,
            self.latency.summary,
            self.frames,
            self.mqtt.stats if self.mqtt is not None else None,
        )


async def _run_background(name: str, loop: Callable[[], Awaitable[None]]) -> None:
    await loop()
    log.info("%s finished", name)
