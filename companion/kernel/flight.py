"""Value types between the mission and the autopilot link: the vehicle snapshot and the setpoints.

Frames follow :mod:`companion.kernel.frames`: local NED for positions and velocities, body FRD for body
velocities, yaw about NED down (zero north, clockwise positive). Every telemetry group carries the stamp (on
the service's monotonic clock) of the message it came from, so a consumer can tell a fresh value from a
stale one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from companion.kernel.compat import StrEnum

NEVER_S = -math.inf
"""The stamp of a telemetry group that has never been received."""

Vec3T = tuple[float, float, float]


class FlightMode(StrEnum):
    """The autopilot's flight mode as MAVSDK decodes it (PX4's Descend failsafe shows as ``LAND``)."""

    UNKNOWN = "unknown"
    READY = "ready"
    TAKEOFF = "takeoff"
    HOLD = "hold"
    MISSION = "mission"
    RETURN_TO_LAUNCH = "return_to_launch"
    LAND = "land"
    OFFBOARD = "offboard"
    FOLLOW_ME = "follow_me"
    MANUAL = "manual"
    ALTCTL = "altctl"
    POSCTL = "posctl"
    ACRO = "acro"
    STABILIZED = "stabilized"
    RATTITUDE = "rattitude"


class LandedState(StrEnum):
    """PX4's land detector (EXTENDED_SYS_STATE.landed_state)."""

    UNKNOWN = "unknown"
    ON_GROUND = "on_ground"
    IN_AIR = "in_air"
    TAKING_OFF = "taking_off"
    LANDING = "landing"


class Severity(StrEnum):
    """MAVLink STATUSTEXT severities (MAV_SEVERITY), most severe first."""

    EMERGENCY = "emergency"
    ALERT = "alert"
    CRITICAL = "critical"
    ERROR = "error"
    WARNING = "warning"
    NOTICE = "notice"
    INFO = "info"
    DEBUG = "debug"


@dataclass(frozen=True, slots=True)
class StatusText:
    """One STATUSTEXT from the autopilot, stamped when it arrived (s)."""

    stamp_s: float
    severity: Severity
    text: str


@dataclass(frozen=True, slots=True)
class VehicleState:
    """A snapshot of everything the mission reads from the autopilot.

    ``*_stamp_s`` are service-clock times (``NEVER_S`` if never received): attitude, velocity and local
    position are stamped when the autopilot sampled them (its boot time mapped through MAVLink TIMESYNC,
    companion/vehicle/boottime.py), the rest on arrival. Positions and
    velocities are PX4's own estimate: after a GPS loss they keep streaming while drifting, so the validity
    flags (``position_valid``, ``gps_fix_type``) must be read before trusting them.
    """

    stamp_s: float = NEVER_S
    connected: bool = False
    #: Last HEARTBEAT (or any telemetry) from the autopilot, s.
    heartbeat_stamp_s: float = NEVER_S
    armed: bool = False
    flight_mode: FlightMode = FlightMode.UNKNOWN
    landed_state: LandedState = LandedState.UNKNOWN

    roll_rad: float = 0.0
    pitch_rad: float = 0.0
    yaw_rad: float = 0.0
    attitude_stamp_s: float = NEVER_S

    #: Velocity in local NED (GLOBAL_POSITION_INT vx, vy, vz), m/s.
    v_ned_m_s: Vec3T = (0.0, 0.0, 0.0)
    velocity_stamp_s: float = NEVER_S
    #: Position in local NED relative to the EKF origin (LOCAL_POSITION_NED), m.
    p_ned_m: Vec3T = (0.0, 0.0, 0.0)
    local_position_stamp_s: float = NEVER_S

    lat_deg: float = math.nan
    lon_deg: float = math.nan
    alt_amsl_m: float = math.nan
    #: Height above home from the estimator (baro-aided; stays meaningful after a GPS loss), m.
    alt_rel_m: float = math.nan
    global_position_stamp_s: float = NEVER_S

    #: GPS_RAW_INT fix type: 0 no GPS, 1 no fix, 2 2D, 3 3D, 4 DGPS, 5 RTK float, 6 RTK fixed.
    gps_fix_type: int = 0
    gps_satellites: int = 0
    gps_stamp_s: float = NEVER_S

    #: MAVSDK health: GPS fused (SYS_STATUS GPS present and healthy).
    global_position_ok: bool = False
    #: MAVSDK health: local position usable (GPS, flow or vision).
    local_position_ok: bool = False
    home_position_ok: bool = False
    armable: bool = False
    health_stamp_s: float = NEVER_S

    #: ESTIMATOR_STATUS: horizontal position and velocity valid (the flags PX4's offboard checks use).
    #: ``None`` until an ESTIMATOR_STATUS arrives; then it is the truth about PX4's estimate.
    position_valid: bool | None = None
    estimator_stamp_s: float = NEVER_S

    battery_remaining_frac: float = math.nan
    battery_voltage_v: float = math.nan

    #: The autopilot's hover thrust (PX4 MPC_THR_HOVER) if it could be read, normalised 0..1.
    hover_thrust_norm: float | None = None
    #: PX4's COM_OBL_RC_ACT (offboard-loss action) as read back from it; None until known.
    offboard_loss_param: int | None = None

    #: The last MAVLink TIMESYNC round trip to the autopilot and when it came back, s (NaN: none yet).
    link_rtt_s: float = math.nan
    link_rtt_stamp_s: float = NEVER_S
    #: The link's one-way delay: half the shortest recent round trip, s (NaN: not measured).
    link_delay_s: float = math.nan

    last_status_text: StatusText | None = None
    #: Counts STATUSTEXTs received, so a reader can tell a new one from the same one.
    status_text_seq: int = 0

    @property
    def link_delay_or_zero_s(self) -> float:
        """The link's measured one-way delay, s; 0 while unmeasured."""
        return self.link_delay_s if math.isfinite(self.link_delay_s) else 0.0

    @property
    def in_air(self) -> bool:
        """PX4's in-air flag as MAVSDK computes it (IN_AIR, TAKING_OFF or LANDING)."""
        return self.landed_state in (LandedState.IN_AIR, LandedState.TAKING_OFF, LandedState.LANDING)


@dataclass(frozen=True, slots=True)
class VelocityNedSetpoint:
    """Offboard velocity in local NED with an absolute yaw (PX4 position controller tracks both).

    ``a_ned_m_s2``: an acceleration PX4 adds to its velocity loop's output (feed-forward), NED m/s^2; None
    sends none. Needs PX4's local velocity to be valid: never use it after a GPS loss.
    """

    v_ned_m_s: Vec3T
    yaw_rad: float
    a_ned_m_s2: Vec3T | None = None


@dataclass(frozen=True, slots=True)
class VelocityBodySetpoint:
    """Offboard velocity in the body frame (forward, right, down) with a yaw rate.

    PX4 rotates it into NED by the current yaw only (not roll or pitch), so it is a heading-frame velocity.
    A yaw *rate* lets the formation law feed forward the leader's bearing rate.
    """

    v_body_m_s: Vec3T
    yaw_rate_rad_s: float


@dataclass(frozen=True, slots=True)
class AttitudeSetpoint:
    """Offboard attitude (ZYX Euler, rad) and collective thrust normalised to 0..1.

    Needs only PX4's attitude estimate, so it is the one setpoint kind that keeps working with no GPS.
    """

    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    thrust_norm: float


Setpoint = VelocityNedSetpoint | VelocityBodySetpoint | AttitudeSetpoint


@dataclass(frozen=True, slots=True)
class ExternalPosition:
    """A position fix for PX4's estimator from outside (VISION_POSITION_ESTIMATE), local NED.

    ``variance_m2`` is the per-axis variance of the position; ``yaw_rad`` the vehicle's yaw at ``stamp_s``.
    """

    stamp_s: float
    p_ned_m: Vec3T
    variance_m2: Vec3T
    yaw_rad: float
    roll_rad: float = 0.0
    pitch_rad: float = 0.0
    #: Bumped when the position jumps (e.g. a new leader fix) so the estimator resets instead of fusing.
    reset_counter: int = 0
