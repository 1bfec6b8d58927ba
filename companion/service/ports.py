"""What the service needs from the flight side, as small protocols and plain snapshot types.

The flight part (:class:`companion.service.flight.FlightService`) meets these; the service itself (status
endpoint, MQTT, systemd, GCS reports) depends only on this module, so it can be built and tested on its
own.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

from companion.mission.types import OperatorRequest, OperatorVerdict

Vec3T = tuple[float, float, float]


@dataclass(frozen=True, slots=True)
class VehicleSummary:
    """The autopilot as the status endpoint shows it (values straight from telemetry)."""

    connected: bool = False
    #: Seconds since the last message from the autopilot; None if never heard.
    heartbeat_age_s: float | None = None
    armed: bool = False
    in_air: bool = False
    flight_mode: str = "unknown"
    #: What PX4 does if our setpoints stop (COM_OBL_RC_ACT in words); None until read.
    offboard_loss_failsafe: str | None = None
    gps_fix_type: int = 0
    gps_satellites: int = 0
    position_valid: bool | None = None
    p_ned_m: Vec3T | None = None
    v_ned_m_s: Vec3T | None = None
    yaw_deg: float | None = None
    lat_deg: float | None = None
    lon_deg: float | None = None
    alt_amsl_m: float | None = None
    #: The autopilot's MAVLink system id once the link has chosen it (``link.system_id``).
    system_id: int | None = None
    #: Battery charge left, 0..1, and voltage, V (None until reported).
    battery_remaining_frac: float | None = None
    battery_voltage_v: float | None = None


@dataclass(frozen=True, slots=True)
class LeaderSummary:
    """The tracker's leader estimate relative to the follower, NED axes."""

    status: str
    p_rel_ned_m: Vec3T
    v_rel_ned_m_s: Vec3T | None = None
    #: 3x3 position covariance, m^2 (None when only variances are known: see ``var_ned_m2``).
    cov_ned_m2: tuple[Vec3T, Vec3T, Vec3T] | None = None
    age_s: float | None = None
    range_m: float | None = None


@dataclass(frozen=True, slots=True)
class FlightSnapshot:
    """Everything the service reports about the flight, read without blocking."""

    state: str
    reason: str
    detail: str = ""
    #: Seconds in the current state.
    state_age_s: float = 0.0
    #: Service-clock time of the mission's last step (liveness for the watchdog); None before the first.
    last_step_s: float | None = None
    vehicle: VehicleSummary = field(default_factory=VehicleSummary)
    leader: LeaderSummary | None = None
    #: Leader position minus the formation slot, NED, m (when the formation law ran).
    formation_error_ned_m: Vec3T | None = None
    #: How old the leader's last shared position is, s (None: none received), and whether the last step
    #: flew on the leader's shared motion (``formation.lead_on_shared_motion``).
    leader_share_age_s: float | None = None
    led_on_leader_share: bool = False
    #: ...and whether it flew on where the shares put the leader, the camera missing it
    #: (``formation.coast_on_shared_position``).
    on_leader_share_position: bool = False
    #: True once a requested shutdown has reached a safe end (landed and disarmed, or held).
    shutdown_complete: bool = False
    #: On the ground waiting for a start: what keeps the mission from arming now (empty: a start would
    #: arm); None in every other state.
    preflight_problems: tuple[str, ...] | None = None


@dataclass(frozen=True, slots=True)
class StateChange:
    """One mission transition, as logs, STATUSTEXT, MQTT events and sd_notify STATUS= report it."""

    stamp_s: float
    from_state: str
    to_state: str
    reason: str
    reason_code: str
    severity: str = "info"
    detail: str = ""
    #: The STATUSTEXT line (at most 50 characters).
    statustext: str = ""


class FlightPort(Protocol):
    """The flight side: runs the mission, reports it, and takes requests from the service."""

    def snapshot(self) -> FlightSnapshot: ...

    def set_on_change(self, callback: Callable[[StateChange], None]) -> None:
        """Have ``callback`` called (on the loop) for every transition, in order."""
        ...

    async def run(self) -> None:
        """Fly until the mission is over: after a shutdown request, once safe; raises on link failure."""
        ...

    def request_start(self, *, takeover: bool = True) -> None:
        """Start the mission (arm, take off, acquire, follow) once preflight passes, without an answer.

        ``takeover``: an operator's start, which also takes a vehicle found already flying; the service's
        ``auto_start`` passes False (it arms and takes off from the ground only).
        """
        ...

    def request_shutdown(self) -> None:
        """Perform the configured safe action (``mission.shutdown_action``), then let :meth:`run` return."""
        ...

    async def command(self, req: OperatorRequest) -> OperatorVerdict:
        """An operator's ``start``, ``land``, ``hold`` or ``set_offset``, checked by the mission on its tick.

        From the ground a start arms and takes off; in the air it takes the vehicle back. Returns the
        mission's verdict: what it did, or why it refused.
        """
        ...


@dataclass(frozen=True, slots=True)
class OnboardComputerStatus:
    """The MAVLink ONBOARD_COMPUTER_STATUS (390) fields, already in MAVLink's units and sentinels."""

    fields: dict[str, int | list[int]]


class GcsPort(Protocol):
    """Reports to the ground station over the autopilot's MAVLink link."""

    async def send_status_text(self, text: str, severity: str) -> None:
        """STATUSTEXT (``severity`` is a MAV_SEVERITY name in lower case, e.g. ``warning``)."""
        ...

    async def send_onboard_computer_status(self, status: OnboardComputerStatus) -> None: ...
