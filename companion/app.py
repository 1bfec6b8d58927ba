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
import logging
import math
import os
import random
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from companion import __version__
from companion.config import Config
from companion.kernel import compat
from companion.kernel.clock import Clock
from companion.service.gcs import OnboardStatusBuilder
from companion.service.health import HealthBoard
from companion.service.latency import LatencyStats
from companion.service.perception_loop import PerceptionLoop
from companion.service.ports import FlightSnapshot, GcsPort, MissionPort, StateChange
from companion.service.status import StatusServer
from companion.service.supervise import Backoff, supervise
from companion.service.sysinfo import SystemMonitor, SystemReading
from companion.service.systemd import SystemdNotifier
from companion.telemetry.commands import Command
from companion.telemetry.mqtt import MqttCredentials, MqttReporter, TelemetrySources
from companion.telemetry.payloads import HealthMsg, LeaderMsg, LeaderPositionMsg, PoseMsg, StateMsg

log = logging.getLogger(__name__)

STATUS_SCHEMA_VERSION = 1
MISSION = "mission"
MQTT = "mqtt"
MONITOR = "monitor"
#: The mission steps at the setpoint rate (>= 2 Hz); this long without a step means it hangs.
_MISSION_STALE_S = 3.0
_STATUSTEXT_QUEUE = 32


@dataclass(slots=True)
class Parts:
    """The flight and perception parts, opened by a :data:`PartsFactory` on the service's exit stack."""

    mission: MissionPort
    gcs: GcsPort | None = None
    perception: PerceptionLoop[Any] | None = None
    #: Where leader positions received on MQTT go (``leader.shared_position = "mqtt"``).
    on_leader_position: Callable[[LeaderPositionMsg], None] | None = None
    #: Does the mission runner send STATUSTEXT on transitions itself? Then the service does not.
    mission_sends_statustext: bool = False
    #: Loops the parts need while the service runs (e.g. the link's telemetry), by task name. Critical:
    #: if one raises, the service ends. They are cancelled when the service stops.
    background: dict[str, Callable[[], Awaitable[None]]] = field(default_factory=dict)
    extra_status: dict[str, Callable[[], Any]] = field(default_factory=dict)
    #: Returns once the link to the configured vehicle is up (READY=1 waits for it); None: at once.
    link_ready: Callable[[], Awaitable[None]] | None = None


@dataclass(frozen=True, slots=True)
class PartsContext:
    """What the service lends the parts it opens."""

    clock: Clock
    health: HealthBoard
    latency: LatencyStats


#: Opens the parts on the given stack (closed when the service ends).
PartsFactory = Callable[[contextlib.AsyncExitStack, PartsContext], Awaitable[Parts]]


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
        mqtt_credentials: password, TLS and command key, loaded at the edge.
        rng: jitter for backoffs.
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
        rng: random.Random | None = None,
    ) -> None:
        self.cfg = cfg
        self._open_parts = open_parts
        self.clock = clock
        self._wall_time_s = wall_time_s
        self.notifier = notifier
        self._sysmon = system_monitor or SystemMonitor()
        self._mqtt_credentials = mqtt_credentials or MqttCredentials()
        self._rng = rng or random.Random()  # noqa: S311 (jitter, not crypto)
        self.health = HealthBoard(clock)
        self.latency = LatencyStats()
        self._onboard = OnboardStatusBuilder()
        self._parts: Parts | None = None
        self.mqtt: MqttReporter | None = None
        self._system: SystemReading | None = None
        self._statustext: asyncio.Queue[tuple[str, str]] = asyncio.Queue(maxsize=_STATUSTEXT_QUEUE)
        self.statustext_dropped = 0
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
                        tg.create_task(self._gcs(parts.gcs), name="companion.gcs")
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

    async def _run_mission(self, mission: MissionPort) -> None:
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

    async def _until_down(self, mission: MissionPort) -> None:
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

    def _request_start(self) -> dict[str, Any]:
        assert self._parts is not None  # noqa: S101
        if self.stopping:
            return {"ok": False, "detail": f"stopping ({self._stop_reason})"}
        self._parts.mission.request_start()
        log.info("mission start requested over the status socket")
        return {"ok": True, "detail": "start requested"}

    def _operator_command(self, args: list[str]) -> dict[str, Any]:
        """``command land|hold|set_offset X Y Z`` from the CLI: through the mission machine's checks."""
        assert self._parts is not None  # noqa: S101
        if not args:
            return {"ok": False, "detail": "command refused: name one of land, hold, set_offset"}
        name, rest = args[0], args[1:]
        offset: tuple[float, float, float] | None = None
        if name == "set_offset":
            try:
                x, y, z = (float(a) for a in rest)
            except ValueError:
                return {"ok": False, "detail": "set_offset refused: it needs three numbers X Y Z (m)"}
            offset = (x, y, z)
        elif rest:
            return {"ok": False, "detail": f"{name} refused: it takes no arguments"}
        reply = self._parts.mission.request_command(name, offset)
        return {"ok": " refused: " not in reply, "detail": reply}

    async def _lifecycle(self, mission: MissionPort) -> None:
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

    async def _gcs(self, gcs: GcsPort) -> None:
        async with compat.TaskGroup() as tg:
            tg.create_task(self._statustext_sender(gcs), name="companion.gcs.statustext")
            if self.cfg.service.onboard_status_rate_hz > 0:
                tg.create_task(self._onboard_sender(gcs), name="companion.gcs.onboard")

    async def _statustext_sender(self, gcs: GcsPort) -> None:
        failures = 0
        while True:
            text, severity = await self._statustext.get()
            try:
                await gcs.send_status_text(text, severity)
                failures = 0
            except Exception as exc:  # the link may be down; the mission handles that, we just count
                failures += 1
                if failures == 1:
                    log.warning("STATUSTEXT not sent (%s: %s)", type(exc).__name__, exc)

    async def _onboard_sender(self, gcs: GcsPort) -> None:
        period_s = 1.0 / self.cfg.service.onboard_status_rate_hz
        failures = 0
        while True:
            await asyncio.sleep(period_s)
            if self._system is None:
                continue
            status = self._onboard.build(
                self._system, self.clock.now_s() - self._started_s, self._wall_time_s()
            )
            try:
                await gcs.send_onboard_computer_status(status)
                failures = 0
            except Exception as exc:  # as above: counted, logged once per run of failures
                failures += 1
                if failures == 1:
                    log.warning("ONBOARD_COMPUTER_STATUS not sent (%s: %s)", type(exc).__name__, exc)

    # ---- transitions ----------------------------------------------------------------------------------

    def _on_change(self, change: StateChange) -> None:
        self.transitions += 1
        if self.mqtt is not None:
            self.mqtt.state_changed()
            self.mqtt.event(
                "state_change",
                f"{change.from_state} -> {change.to_state}: {change.reason}",
                _mqtt_severity(change.severity),
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
            try:
                self._statustext.put_nowait((text, change.severity))
            except asyncio.QueueFull:
                self.statustext_dropped += 1

    # ---- snapshots ------------------------------------------------------------------------------------

    def _socket_path(self) -> Path:
        return Path(self.cfg.status.socket_path)

    def _status_line(self, snap: FlightSnapshot) -> str:
        v = snap.vehicle
        link = "link ok" if v.connected else "no link"
        gps = f"gps fix {v.gps_fix_type}"
        leader = snap.leader.status if snap.leader is not None else "no leader"
        stop = f" | stopping ({self._stop_reason})" if self._stop_reason else ""
        return f"{snap.state}: {snap.reason} | {link} | {gps} | leader {leader}{stop}"

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
        snap = self._parts.mission.snapshot()
        v = snap.vehicle
        leader = None
        if snap.leader is not None:
            leader = _leader_msg(snap).model_dump(mode="json")
        out: dict[str, Any] = {
            "schema_version": STATUS_SCHEMA_VERSION,
            "vehicle_id": self.cfg.vehicle_id,
            "version": __version__,
            "pid": os.getpid(),
            "uptime_s": round(self.clock.now_s() - self._started_s, 3),
            "stopping": self._stop_reason,
            "mission": {
                "state": snap.state,
                "reason": snap.reason,
                "detail": snap.detail,
                "state_age_s": round(snap.state_age_s, 3),
                #: Seconds since the mission's last control step (it steps at link.setpoint_rate_hz).
                "step_age_s": _r(self.clock.now_s() - snap.last_step_s)
                if snap.last_step_s is not None
                else None,
                "transitions": self.transitions,
                "formation_error_ned_m": snap.formation_error_ned_m,
            },
            "link": {
                "system_id": v.system_id,
                "connected": v.connected,
                "heartbeat_age_s": _r(v.heartbeat_age_s),
                "armed": v.armed,
                "in_air": v.in_air,
                "flight_mode": v.flight_mode,
                "offboard_loss_failsafe": v.offboard_loss_failsafe,
            },
            "gps": {
                "fix_type": v.gps_fix_type,
                "satellites": v.gps_satellites,
                "position_valid": v.position_valid,
            },
            "position": {
                "p_ned_m": v.p_ned_m,
                "v_ned_m_s": v.v_ned_m_s,
                "yaw_deg": _r(v.yaw_deg),
                #: Height above home, m (up positive).
                "altitude_m": _r(-v.p_ned_m[2]) if v.p_ned_m is not None else None,
            },
            "battery": {
                "remaining_frac": _r(v.battery_remaining_frac),
                "voltage_v": _r(v.battery_voltage_v),
            },
            "leader": leader,
            "latency_ms": self.latency.summary(),
            "frames": self.frames(),
            "system": self._system.to_json() if self._system is not None else None,
            "components": [c.to_json() for c in self.health.snapshot()],
            "mqtt": self.mqtt.stats() if self.mqtt is not None else {"enabled": False},
        }
        for key, fn in self._parts.extra_status.items():
            out[key] = fn()
        return out

    def live_health(self) -> dict[str, Any]:
        """The running service's own checks (``companion health`` merges them with its preflight)."""
        assert self._parts is not None  # noqa: S101
        snap = self._parts.mission.snapshot()
        v = snap.vehicle
        checks: list[dict[str, Any]] = []

        def check(name: str, ok: bool, detail: str) -> None:
            checks.append({"name": name, "ok": ok, "detail": detail})

        age = v.heartbeat_age_s
        check(
            "autopilot",
            v.connected and age is not None and age < 3.0,
            f"heartbeat {age:.1f} s ago, {v.flight_mode}" if age is not None else "never heard",
        )
        check(
            "gps",
            v.gps_fix_type >= 3,
            f"fix type {v.gps_fix_type}, {v.gps_satellites} satellites, position valid {v.position_valid}",
        )
        for c in self.health.snapshot():
            if c.name == MQTT:
                continue
            check(c.name, c.ok, c.detail)
        if self.mqtt is not None:
            check("broker", self.mqtt.connected, self._mqtt_detail())
        return {"service_running": True, "state": snap.state, "checks": checks}

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
        )

    def _on_command(self, cmd: Command) -> str:
        """An MQTT operator command: through the mission machine's checks, like the CLI's."""
        assert self._parts is not None  # noqa: S101
        return self._parts.mission.request_command(cmd.name.value, cmd.offset_cam_m)

    def _state_msg(self) -> StateMsg:
        assert self._parts is not None  # noqa: S101
        snap = self._parts.mission.snapshot()
        v = snap.vehicle
        return StateMsg(
            online=True,
            state=snap.state,
            reason=snap.reason,
            state_age_s=round(snap.state_age_s, 3),
            link_ok=v.connected,
            armed=v.armed,
            in_air=v.in_air,
            flight_mode=v.flight_mode,
            gps_fix_type=v.gps_fix_type,
            gps_ok=v.gps_fix_type >= 3,
            leader_tracked=snap.leader is not None and snap.leader.status in ("confirmed", "coasting"),
        )

    def _pose_msg(self) -> PoseMsg | None:
        assert self._parts is not None  # noqa: S101
        snap = self._parts.mission.snapshot()
        v = snap.vehicle
        if v.p_ned_m is None and snap.leader is None:
            return None
        return PoseMsg(
            p_ned_m=v.p_ned_m,
            v_ned_m_s=v.v_ned_m_s,
            yaw_deg=v.yaw_deg,
            lat_deg=v.lat_deg,
            lon_deg=v.lon_deg,
            alt_amsl_m=v.alt_amsl_m,
            leader=_leader_msg(snap) if snap.leader is not None else None,
        )

    def _health_msg(self) -> HealthMsg:
        comps = self.health.snapshot()
        return HealthMsg(
            healthy=all(c.ok for c in comps),
            components=[c.to_json() for c in comps],
            system=self._system.to_json() if self._system is not None else {},
            latency_ms=self.latency.summary(),
            frames=self.frames(),
            mqtt=self.mqtt.stats() if self.mqtt is not None else {},
        )


async def _run_background(name: str, loop: Callable[[], Awaitable[None]]) -> None:
    await loop()
    log.info("%s finished", name)


def _leader_msg(snap: FlightSnapshot) -> LeaderMsg:
    assert snap.leader is not None  # noqa: S101
    ld = snap.leader
    return LeaderMsg(
        status=ld.status,
        p_rel_ned_m=_round3(ld.p_rel_ned_m),
        v_rel_ned_m_s=_round3(ld.v_rel_ned_m_s) if ld.v_rel_ned_m_s is not None else None,
        cov_ned_m2=ld.cov_ned_m2,
        age_s=_r(ld.age_s),
        range_m=_r(ld.range_m) if ld.range_m is not None else _r(math.dist(ld.p_rel_ned_m, (0.0, 0.0, 0.0))),
    )


def _round3(v: tuple[float, float, float]) -> tuple[float, float, float]:
    return (round(v[0], 3), round(v[1], 3), round(v[2], 3))


def _r(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(x) else round(x, 3)


def _mqtt_severity(severity: str) -> Any:
    known = ("debug", "info", "notice", "warning", "error", "critical", "emergency")
    return severity if severity in known else ("critical" if severity == "alert" else "info")
