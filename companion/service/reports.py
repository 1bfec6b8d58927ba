"""What the service tells the outside about the flight, built from a :class:`FlightSnapshot`; pure.

The status endpoint's JSON (``companion status``), the running service's own health checks
(``companion health``), the MQTT state, pose and health messages, and the one-line systemd ``STATUS=``.
:class:`~companion.app.FollowerService` gathers the readings and hands them in.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence
from typing import Any

from companion import __version__
from companion.config import Config
from companion.kernel.clock import Clock
from companion.service.health import ComponentHealth
from companion.service.ports import FlightSnapshot
from companion.service.sysinfo import SystemReading
from companion.telemetry.payloads import HealthMsg, LeaderMsg, PoseMsg, StateMsg

STATUS_SCHEMA_VERSION = 1


def status_line(snap: FlightSnapshot, stop_reason: str | None) -> str:
    """The one-line systemd ``STATUS=`` (and the READY=1 message)."""
    v = snap.vehicle
    link = "link ok" if v.connected else "no link"
    gps = f"gps fix {v.gps_fix_type}"
    leader = snap.leader.status if snap.leader is not None else "no leader"
    stop = f" | stopping ({stop_reason})" if stop_reason else ""
    return f"{snap.state}: {snap.reason} | {link} | {gps} | leader {leader}{stop}"


def status_json(
    cfg: Config,
    snap: FlightSnapshot,
    clock: Clock,
    *,
    started_s: float,
    stop_reason: str | None,
    transitions: int,
    latency_ms: Callable[[], Any],
    frames: Callable[[], dict[str, int]],
    system: SystemReading | None,
    components: Callable[[], Sequence[ComponentHealth]],
    mqtt: Callable[[], dict[str, Any]] | None,
    extra_status: dict[str, Callable[[], Any]],
) -> dict[str, Any]:
    """The JSON the status endpoint serves (``companion status``).

    The readings that cost something (``latency_ms``, ``frames``, ``components``, ``mqtt``) are taken as
    the JSON is built, in its order; ``mqtt`` None: MQTT is off.
    """
    v = snap.vehicle
    leader = None
    if snap.leader is not None:
        leader = leader_msg(snap).model_dump(mode="json")
    out: dict[str, Any] = {
        "schema_version": STATUS_SCHEMA_VERSION,
        "vehicle_id": cfg.vehicle_id,
        "version": __version__,
        "pid": os.getpid(),
        "uptime_s": round(clock.now_s() - started_s, 3),
        "stopping": stop_reason,
        "mission": {
            "state": snap.state,
            "reason": snap.reason,
            "detail": snap.detail,
            "state_age_s": round(snap.state_age_s, 3),
            #: Seconds since the mission's last control step (it steps at link.setpoint_rate_hz).
            "step_age_s": _r(clock.now_s() - snap.last_step_s) if snap.last_step_s is not None else None,
            "transitions": transitions,
            "formation_error_ned_m": snap.formation_error_ned_m,
            "leader_share_age_s": _r(snap.leader_share_age_s),
            "led_on_leader_share": snap.led_on_leader_share,
            "on_leader_share_position": snap.on_leader_share_position,
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
        "latency_ms": latency_ms(),
        "frames": frames(),
        "system": system.to_json() if system is not None else None,
        "components": [c.to_json() for c in components()],
        "mqtt": mqtt() if mqtt is not None else {"enabled": False},
    }
    for key, fn in extra_status.items():
        out[key] = fn()
    return out


def live_health_json(
    snap: FlightSnapshot, components: Sequence[ComponentHealth], broker: Callable[[], tuple[bool, str]] | None
) -> dict[str, Any]:
    """The running service's own checks (``companion health`` merges them with its preflight).

    ``components``: the health board's, less MQTT's (reported as ``broker``: connected and its detail,
    None when MQTT is off).
    """
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
        v.gps_fix_type >= 3 and v.position_valid is not False,
        f"fix type {v.gps_fix_type}, {v.gps_satellites} satellites, position valid {v.position_valid}",
    )
    if snap.preflight_problems is not None:
        # What `companion start` would answer now: healthy on the ground means a start would arm.
        problems = snap.preflight_problems
        check("preflight", not problems, ", ".join(problems) if problems else "passed: a start would arm")
    for c in components:
        check(c.name, c.ok, c.detail)
    if broker is not None:
        check("broker", *broker())
    return {"service_running": True, "state": snap.state, "checks": checks}


def state_msg(snap: FlightSnapshot) -> StateMsg:
    """The MQTT state message."""
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


def pose_msg(snap: FlightSnapshot) -> PoseMsg | None:
    """The MQTT pose message; None while neither the follower's position nor the leader is known."""
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
        leader=leader_msg(snap) if snap.leader is not None else None,
    )


def health_msg(
    comps: Sequence[ComponentHealth],
    system: SystemReading | None,
    latency_ms: Callable[[], Any],
    frames: Callable[[], dict[str, int]],
    mqtt: Callable[[], dict[str, Any]] | None,
) -> HealthMsg:
    """The MQTT health message (``mqtt`` None: MQTT is off)."""
    return HealthMsg(
        healthy=all(c.ok for c in comps),
        components=[c.to_json() for c in comps],
        system=system.to_json() if system is not None else {},
        latency_ms=latency_ms(),
        frames=frames(),
        mqtt=mqtt() if mqtt is not None else {},
    )


def leader_msg(snap: FlightSnapshot) -> LeaderMsg:
    """The leader as MQTT and the status endpoint show it (the snapshot must have one)."""
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


def mqtt_severity(severity: str) -> Any:
    """A transition's severity as an MQTT event's (MAVLink's ``alert`` is ``critical`` there)."""
    known = ("debug", "info", "notice", "warning", "error", "critical", "emergency")
    return severity if severity in known else ("critical" if severity == "alert" else "info")


def _round3(v: tuple[float, float, float]) -> tuple[float, float, float]:
    return (round(v[0], 3), round(v[1], 3), round(v[2], 3))


def _r(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(x) else round(x, 3)
