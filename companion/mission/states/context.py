"""The context every phase of the mission machine reads: time, the state, the health verdicts, the law.

:class:`MissionContext` holds what more than one phase reads (the monitors, the command book, the offboard
stream, the law and the join, the leader's last estimate and shared motion). Each phase
(:mod:`~companion.mission.states.launch`, ``follow``, ``recovery``, ``landing``) is an object holding this
context and its own memory (launch its retries, FOLLOW_VISION its external-fix probation, REACQUIRE its
coast and scan, landing its touchdown timer); it returns its setpoint and at most one transition request
(:mod:`~companion.mission.states.request`), which only the machine applies
(:mod:`companion.mission.transitions`).
"""

from __future__ import annotations

import math

import numpy as np

from companion.config import Config
from companion.estimation.leader import LeaderEstimate
from companion.kernel.flight import VehicleState
from companion.kernel.frames import Vec3
from companion.kernel.stall import StallAwareAge
from companion.mission.ego import EgoMotion
from companion.mission.formation import FormationLaw
from companion.mission.geometry import FollowerState
from companion.mission.monitors import GpsMonitor, LinkMonitor, TrackMonitor
from companion.mission.offboard import CommandBook, OffboardStream
from companion.mission.plan_slot import neighbours_now
from companion.mission.safety import SafetyLimits
from companion.mission.shared_motion import LeaderMotion
from companion.mission.states.start_latch import StartLatch
from companion.mission.types import (
    AirframeDrag,
    CommandKind,
    CommandResult,
    MissionInputs,
    MissionState,
)

#: States in which the companion flies the vehicle through offboard setpoints.
OFFBOARD_STATES = frozenset(
    {
        MissionState.FOLLOW,
        MissionState.FOLLOW_VISION,
        MissionState.REACQUIRE,
        MissionState.HOVER,
        MissionState.CONTROLLED_LANDING,
    }
)
#: States in which the vehicle is (or may be) flying.
AIRBORNE_STATES = OFFBOARD_STATES | {
    MissionState.TAKEOFF,
    MissionState.ACQUIRE,
    MissionState.PX4_HOLD,
    MissionState.PX4_LAND,
    MissionState.PX4_RTL,
    MissionState.PX4_IN_CONTROL,
}
PX4_STATES = frozenset(
    {MissionState.PX4_HOLD, MissionState.PX4_LAND, MissionState.PX4_RTL, MissionState.PX4_IN_CONTROL}
)
#: States where the companion has nothing of the vehicle's to hand back on shutdown.
NOT_IN_CONTROL = frozenset(
    {
        MissionState.WAIT_LINK,
        MissionState.PREFLIGHT,
        MissionState.OBSERVE,
        MissionState.DISARMED,
        MissionState.LINK_LOST,
    }
)

#: Retry an arm, or a LAND that PX4 refused, this long after the last try, s.
ARM_RETRY_S = 2.0
#: A depth-guard reading older than this is dropped (the camera runs at 15-30 Hz), s.
OBSTACLE_STALE_S = 0.5
#: Control ticks missed in a row that make a stall of the service itself (ages then restart, see
#: companion.kernel.stall).
STALL_TICKS = 4


class Retries:
    """A state's retries of a command (arm, disarm, land): how many and when the last went out.

    Each state starts with none: the machine clears them on every change of state.
    """

    def __init__(self) -> None:
        self.attempts = 0
        self.last_attempt_s = -math.inf

    def clear(self) -> None:
        self.attempts = 0
        self.last_attempt_s = -math.inf

    def due(self, now_s: float, period_s: float) -> bool:
        """Whether ``period_s`` has passed since the last try."""
        return now_s - self.last_attempt_s >= period_s

    def tried(self, now_s: float) -> None:
        self.attempts += 1
        self.last_attempt_s = now_s


class MissionContext:
    """What the phases read: time, the state, the health verdicts, the law and the command book.

    No I/O, time passed in. The state changes only where transitions are applied
    (:class:`~companion.mission.transitions.Transitions`); each phase keeps its own memory.
    """

    def __init__(self, cfg: Config, law: FormationLaw | None = None) -> None:
        self.cfg = cfg
        self.m = cfg.mission
        self.limits = SafetyLimits.from_config(cfg.safety, cfg.formation.max_accel_m_s2)
        self.law = law or FormationLaw(cfg.formation, self.limits, cfg.mission.hover_thrust_norm)
        #: The state and when it was entered, s: written only where transitions are applied
        #: (:class:`~companion.mission.transitions.Transitions`).
        self.state = MissionState.WAIT_LINK
        self.entered_s = 0.0
        #: This tick's time, s.
        self.now_s = 0.0
        # Commands of this tick, in flight, and the last result of each kind; the offboard stream.
        self.book = CommandBook()
        self.offboard = OffboardStream(self.book)
        # Health checks.
        self.ages = StallAwareAge(STALL_TICKS / cfg.link.setpoint_rate_hz)
        self.gps = GpsMonitor(cfg.mission, self.ages)
        self.link = LinkMonitor(cfg.link, cfg.formation, self.ages)
        self.track = TrackMonitor(cfg.mission, self.ages)
        # Per-state memory.
        self.last_leader: LeaderEstimate | None = None
        #: The follower's own velocity history, to bring camera-time estimates to the control instant.
        self.ego = EgoMotion()
        self.shutting_down = False
        #: An operator's start until a state acts on it (launch, or PX4's modes after a hold).
        self.start = StartLatch()
        #: The leader's own motion from its shares this tick (``formation.lead_on_shared_motion``).
        self.leader_motion: LeaderMotion | None = None

    # ------------------------------------------------------------------ plumbing
    def t_in_state(self) -> float:
        return self.now_s - self.entered_s

    def send(self, kind: CommandKind, altitude_m: float | None = None) -> None:
        self.book.send(kind, self.now_s, altitude_m)

    def in_flight(self, kind: CommandKind) -> bool:
        return self.book.in_flight(kind, self.now_s)

    def failed(self, kind: CommandKind) -> CommandResult | None:
        return self.book.failed(kind)

    def link_ok(self, veh: VehicleState) -> bool:
        return self.link.ok(veh, self.now_s)

    def fresh(self, est: LeaderEstimate | None) -> bool:
        return self.track.fresh(est, self.now_s)

    def tracked(self, inp: MissionInputs, *, confirmed_only: bool = False) -> bool:
        return self.track.tracked(inp.leader, self.now_s, confirmed_only=confirmed_only)

    def follower(
        self, veh: VehicleState, *, velocity_valid: bool, airframe: AirframeDrag | None = None
    ) -> FollowerState:
        return FollowerState(
            yaw_rad=veh.yaw_rad,
            v_ned_m_s=np.array(veh.v_ned_m_s) if velocity_valid else None,
            v_down_m_s=veh.v_ned_m_s[2],
            alt_rel_m=veh.alt_rel_m,
            p_ned_m=np.array(veh.p_ned_m) if velocity_valid else None,
            roll_rad=veh.roll_rad,
            pitch_rad=veh.pitch_rad,
            airframe=airframe,
        )

    def update_neighbours(self, inp: MissionInputs) -> None:
        """The other followers relative to this one now, for the law's separation barrier."""
        if not inp.neighbours:
            if self.law.neighbours:
                self.law.neighbours = []
            return
        veh = inp.vehicle
        own_ok = self.gps.ok and veh.position_valid is True
        est = self.last_leader
        self.law.neighbours = neighbours_now(
            inp.neighbours,
            self.now_s,
            p_own_ned_m=np.array(veh.p_ned_m) if own_ok else None,
            v_own_ned_m_s=np.array(veh.v_ned_m_s) if own_ok else None,
            leader_shared=inp.leader_shared,
            p_ned_rel_leader_m=None if est is None else np.array(est.p_ned_rel_m),
            v_ned_rel_leader_m_s=None if est is None else np.array(est.v_ned_rel_m_s),
        )

    def obstacle_now(self, inp: MissionInputs) -> Vec3 | None:
        """The depth guard's obstacle relative to the follower now (static: shifted by our own motion)."""
        ob = inp.obstacle
        if ob is None or not 0.0 <= self.ages.age_s(ob.stamp_s, self.now_s) <= OBSTACLE_STALE_S:
            return None
        p = np.array(ob.p_ned_rel_m)
        disp = self.ego.displacement(ob.stamp_s, self.now_s)
        return p if disp is None else p - disp
