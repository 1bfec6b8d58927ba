"""The mission's inputs and outputs: plain values, so the machine can be driven by anything.

The leader's estimate and the depth guard's reading come as estimation's types
(:mod:`companion.estimation.leader`); the shared-leader feed and the service convert their own types into
these. The mission depends on no module that produces them.
"""

from __future__ import annotations

from dataclasses import dataclass

from companion.estimation.leader import LeaderEstimate, ObstacleAhead
from companion.kernel.compat import StrEnum
from companion.kernel.flight import ExternalPosition, Setpoint, Severity, Vec3T, VehicleState


@dataclass(frozen=True, slots=True)
class AirframeDrag:
    """The follower's drag as learnt in flight (companion/estimation/ego_velocity.py).

    Horizontal, per unit mass: holding a velocity ``v`` (NED m/s) takes ``drag_per_s * v - push_ne_m_s2``
    of thrust acceleration (m/s^2), ``push_ne_m_s2`` being the steady wind's push.
    """

    drag_per_s: float
    push_ne_m_s2: tuple[float, float]


@dataclass(frozen=True, slots=True)
class SharedLeaderPosition:
    """The leader's own position, shared over MAVLink or MQTT, in the follower's local NED frame, m."""

    stamp_s: float
    p_ned_m: Vec3T
    variance_m2: Vec3T = (1.0, 1.0, 4.0)
    #: The leader's heading (its own estimate), rad from north; None when it does not share one. With a
    #: formation plan it turns the follower's slot with the leader.
    yaw_rad: float | None = None
    #: The leader's velocity (NED, m/s), when shared.
    v_ned_m_s: Vec3T | None = None
    #: The leader's yaw rate (its gyro, rad/s), when shared: turns the slot without differencing headings.
    yaw_rate_rad_s: float | None = None


@dataclass(frozen=True, slots=True)
class SharedNeighbour:
    """Another follower's shared position, in this follower's local NED frame, m and m/s."""

    name: str
    stamp_s: float
    p_ned_m: Vec3T
    v_ned_m_s: Vec3T = (0.0, 0.0, 0.0)


class CommandKind(StrEnum):
    """One-shot commands the machine asks the runner to send."""

    ARM = "arm"
    DISARM = "disarm"
    TAKEOFF = "takeoff"
    START_OFFBOARD = "start_offboard"
    STOP_OFFBOARD = "stop_offboard"
    #: PX4 already left offboard (pilot or failsafe): stop refreshing without asking for any mode.
    RELEASE_OFFBOARD = "release_offboard"
    HOLD = "hold"
    LAND = "land"
    RTL = "rtl"


@dataclass(frozen=True, slots=True)
class Command:
    """A command for the autopilot; ``altitude_m`` only for TAKEOFF."""

    kind: CommandKind
    altitude_m: float | None = None


@dataclass(frozen=True, slots=True)
class CommandResult:
    """What became of a command: ``ok`` and, when not, why (the autopilot's or MAVSDK's words)."""

    kind: CommandKind
    ok: bool
    detail: str = ""


class OperatorCommand(StrEnum):
    """What an operator may ask for (over MQTT or the status socket)."""

    #: From the ground: arm, take off and follow; in the air: take the vehicle back and follow again.
    START = "start"
    LAND = "land"
    HOLD = "hold"
    #: A new formation slot (``OperatorRequest.offset_cam_m``).
    SET_OFFSET = "set_offset"

    @property
    def takes_offset(self) -> bool:
        """The command carries a slot (camera frame, m: right, down, forward)."""
        return self is OperatorCommand.SET_OFFSET


#: What ``companion command`` and MQTT's ``cmd`` carry; a start has its own request (``companion start``,
#: the status socket only).
SENT_COMMANDS = (OperatorCommand.LAND, OperatorCommand.HOLD, OperatorCommand.SET_OFFSET)


@dataclass(frozen=True, slots=True)
class OperatorRequest:
    """One operator command as the mission takes it; ``offset_cam_m`` (camera frame, m) for SET_OFFSET."""

    command: OperatorCommand
    offset_cam_m: Vec3T | None = None


@dataclass(frozen=True, slots=True)
class OperatorVerdict:
    """What the mission made of an operator's request: taken (``detail`` says what it did) or refused (why).

    Carried as it is to the edges (status socket, MQTT, logs), which print it with ``str()``.
    """

    command: OperatorCommand
    taken: bool
    detail: str

    def __str__(self) -> str:
        return f"{self.command.value}{'' if self.taken else ' refused'}: {self.detail}"


@dataclass(frozen=True, slots=True)
class MissionInputs:
    """Everything one step of the machine reads.

    ``leader`` is the *latest* tracker output however old (the machine judges staleness from its stamp);
    ``command_results`` are the outcomes that arrived since the previous step.
    """

    vehicle: VehicleState
    leader: LeaderEstimate | None = None
    leader_shared: SharedLeaderPosition | None = None
    #: The depth guard's latest reading (None: nothing near, or the guard is off).
    obstacle: ObstacleAhead | None = None
    #: The other followers' latest shared positions (formations), one per neighbour.
    neighbours: tuple[SharedNeighbour, ...] = ()
    start_requested: bool = False
    #: The start came from an operator (``companion start``), not from ``service.auto_start``: only such a
    #: start takes over a vehicle that is already flying.
    takeover_requested: bool = False
    shutdown_requested: bool = False
    command_results: tuple[CommandResult, ...] = ()
    #: A one-shot operator request, delivered on one step only; the step checks it and answers it
    #: (``StepOutput.operator_refused``).
    operator: OperatorRequest | None = None
    #: The follower's drag, once learnt (None before): the velocity law's acceleration feed-forward.
    airframe: AirframeDrag | None = None


class MissionState(StrEnum):
    """The states of the mission. ``PX4_*`` states are flown by PX4 itself; the companion only watches."""

    WAIT_LINK = "wait_link"
    PREFLIGHT = "preflight"
    #: The vehicle was already flying when the service came up: watched and reported, never commanded,
    #: until an explicit start (or ``mission.resume_in_air``).
    OBSERVE = "observe"
    ARMING = "arming"
    TAKEOFF = "takeoff"
    ACQUIRE = "acquire"
    FOLLOW = "follow"
    FOLLOW_VISION = "follow_vision"
    REACQUIRE = "reacquire"
    HOVER = "hover"
    CONTROLLED_LANDING = "controlled_landing"
    PX4_HOLD = "px4_hold"
    PX4_LAND = "px4_land"
    PX4_RTL = "px4_rtl"
    PX4_IN_CONTROL = "px4_in_control"
    LINK_LOST = "link_lost"
    LANDED = "landed"
    DISARMED = "disarmed"


class Reason(StrEnum):
    """Why a transition happened. The value is the one-line text for logs, STATUSTEXT and MQTT."""

    LINK_UP = "autopilot link up"
    LINK_LOST = "autopilot link lost"
    LINK_RESTORED = "autopilot link restored"
    START_REQUESTED = "mission start requested"
    PREFLIGHT_OK = "preflight checks passed"
    ALREADY_FLYING = "vehicle already armed and in air"
    AIRBORNE_NOT_STARTED = "in air: waiting for companion start"
    LANDED_WHILE_OBSERVED = "vehicle landed while observed"
    ARMED = "armed"
    ARM_FAILED = "arming refused"
    TAKEOFF_DONE = "takeoff altitude reached"
    TAKEOFF_FAILED = "takeoff refused or timed out"
    LEADER_ACQUIRED = "leader acquired"
    ACQUIRE_TIMEOUT = "leader not found in time"
    OFFBOARD_REJECTED = "offboard refused"
    GPS_LOST = "GPS lost"
    GPS_RESTORED = "GPS restored"
    VISION_MODE_CHANGED = "vision fallback switched mode"
    NO_VISION_FALLBACK = "no vision fallback available"
    LEADER_LOST = "leader lost"
    LEADER_REACQUIRED = "leader re-acquired"
    REACQUIRE_TIMEOUT = "leader not re-acquired in time"
    PERCEPTION_STALL = "estimate stale: hovering"
    PERCEPTION_RESUMED = "estimate fresh again"
    STALL_TIMEOUT = "estimate stale too long"
    GEOFENCE_BREACH = "geofence breached"
    MODE_CHANGED_EXTERNALLY = "autopilot left offboard (pilot or failsafe)"
    PX4_MODE_REFUSED = "autopilot refused the mode: landing"
    TOUCHDOWN = "touchdown"
    DISARMED = "disarmed"
    SHUTDOWN_REQUESTED = "shutdown requested"
    HOLD_TIMEOUT = "shutdown hold elapsed: landing"
    OPERATOR_LAND = "operator asked to land"
    OPERATOR_HOLD = "operator asked to hold"
    OPERATOR_START = "operator asked to follow again"


#: How each reason is reported to the ground station.
REASON_SEVERITY: dict[Reason, Severity] = {
    Reason.LINK_LOST: Severity.CRITICAL,
    Reason.ARM_FAILED: Severity.ERROR,
    Reason.TAKEOFF_FAILED: Severity.ERROR,
    Reason.ACQUIRE_TIMEOUT: Severity.WARNING,
    Reason.OFFBOARD_REJECTED: Severity.ERROR,
    Reason.GPS_LOST: Severity.CRITICAL,
    Reason.NO_VISION_FALLBACK: Severity.CRITICAL,
    Reason.VISION_MODE_CHANGED: Severity.WARNING,
    Reason.LEADER_LOST: Severity.WARNING,
    Reason.REACQUIRE_TIMEOUT: Severity.ERROR,
    Reason.PERCEPTION_STALL: Severity.WARNING,
    Reason.STALL_TIMEOUT: Severity.ERROR,
    Reason.GEOFENCE_BREACH: Severity.CRITICAL,
    Reason.MODE_CHANGED_EXTERNALLY: Severity.WARNING,
    Reason.PX4_MODE_REFUSED: Severity.ERROR,
    Reason.SHUTDOWN_REQUESTED: Severity.NOTICE,
    Reason.AIRBORNE_NOT_STARTED: Severity.WARNING,
    Reason.OPERATOR_LAND: Severity.NOTICE,
    Reason.OPERATOR_HOLD: Severity.NOTICE,
    Reason.OPERATOR_START: Severity.NOTICE,
}


@dataclass(frozen=True, slots=True)
class Transition:
    """One state change, with its reason and an optional detail (a mode name, a refusal text)."""

    stamp_s: float
    from_state: MissionState
    to_state: MissionState
    reason: Reason
    detail: str = ""

    @property
    def severity(self) -> Severity:
        return REASON_SEVERITY.get(self.reason, Severity.INFO)

    def statustext(self) -> str:
        """The STATUSTEXT line (MAVLink allows 50 characters): ``WM <state>: <reason>``."""
        text = f"WM {self.to_state.value}: {self.reason.value}"
        return text[:50]

    def as_dict(self) -> dict[str, str | float]:
        """The MQTT event payload."""
        return {
            "stamp_s": self.stamp_s,
            "from": self.from_state.value,
            "to": self.to_state.value,
            "reason": self.reason.name,
            "text": self.reason.value,
            "detail": self.detail,
            "severity": self.severity.value,
        }


class VisionMode(StrEnum):
    """How FOLLOW_VISION flies: attitude+thrust on the relative estimate, or velocity on an external fix."""

    ATTITUDE = "attitude"
    EXTERNAL_POSITION = "external_position"


@dataclass(frozen=True, slots=True)
class StepOutput:
    """What one step decided.

    ``setpoint`` is the setpoint to stream this tick (computed from this tick's inputs; ``None`` means the
    companion must not be streaming). ``commands`` are one-shot and go out in order. ``ready_to_exit`` says
    a requested shutdown has reached a state where the service may exit.
    """

    state: MissionState
    setpoint: Setpoint | None = None
    commands: tuple[Command, ...] = ()
    external_position: ExternalPosition | None = None
    transitions: tuple[Transition, ...] = ()
    ready_to_exit: bool = False
    vision_mode: VisionMode | None = None
    #: Formation error (leader relative position minus the slot) in NED when the law ran, m.
    formation_error_ned_m: Vec3T | None = None
    #: Why this step refused the operator's request (None: no request, or it was taken).
    operator_refused: str | None = None
    #: This step flew on the leader's own shared velocity and acceleration
    #: (``formation.lead_on_shared_motion``).
    led_on_shared_motion: bool = False
    #: This step flew on where the leader's shares put it while the camera missed it
    #: (``formation.coast_on_shared_position``).
    coasted_on_shared_position: bool = False
