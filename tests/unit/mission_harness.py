"""Drives MissionMachine with a ManualClock and a scripted fake autopilot (pure logic only, no I/O).

The fake reacts to commands the way PX4 does at the level the machine sees: ARM arms, TAKEOFF climbs,
START_OFFBOARD switches to Offboard, STOP_OFFBOARD and HOLD switch to Hold, LAND lands. Tests refuse a command
by putting its kind in ``refuse``; results reach the machine on the next step, as with the real runner.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from companion.config import Config
from companion.estimation.leader import LeaderEstimate, ObstacleAhead, TrackStatus
from companion.kernel.clock import ManualClock
from companion.kernel.flight import FlightMode, LandedState, VehicleState
from companion.mission.machine import MissionMachine
from companion.mission.types import (
    Command,
    CommandKind,
    CommandResult,
    MissionInputs,
    MissionState,
    OperatorCommand,
    OperatorRequest,
    Reason,
    SharedLeaderPosition,
    StepOutput,
    Transition,
)

DT_S = 0.05


@dataclass
class FakeAutopilot:
    """What the machine can observe of a PX4, changed by its commands."""

    connected: bool = True
    telemetry: bool = True
    armed: bool = False
    mode: FlightMode = FlightMode.HOLD
    landed: LandedState = LandedState.ON_GROUND
    alt_rel_m: float = 0.0
    v_ned_m_s: tuple[float, float, float] = (0.0, 0.0, 0.0)
    p_ned_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    yaw_rad: float = 0.0
    gps_fix: int = 3
    position_valid: bool | None = True
    home_ok: bool = True
    refuse: dict[CommandKind, str] = field(default_factory=dict)
    #: Commands that get no answer at all (in flight forever).
    mute: set[CommandKind] = field(default_factory=set)
    climb_m_s: float = 2.0
    #: How old the attitude sample is on arrival (a slow or lossy link), s.
    attitude_lag_s: float = 0.0
    target_alt_m: float = 0.0
    #: Telemetry stamped at this time whatever the clock says (messages not read since), s.
    frozen_at_s: float | None = None
    sent: list[Command] = field(default_factory=list)

    def apply(self, cmd: Command) -> CommandResult | None:
        self.sent.append(cmd)
        if cmd.kind in self.mute:
            return None
        if cmd.kind in self.refuse:
            return CommandResult(cmd.kind, False, self.refuse[cmd.kind])
        k = cmd.kind
        if k == CommandKind.ARM:
            self.armed = True
        elif k == CommandKind.DISARM:
            self.armed = False
        elif k == CommandKind.TAKEOFF:
            self.mode = FlightMode.TAKEOFF
            self.landed = LandedState.TAKING_OFF
            self.target_alt_m = cmd.altitude_m or 2.5
        elif k == CommandKind.START_OFFBOARD:
            self.mode = FlightMode.OFFBOARD
        elif k in (CommandKind.STOP_OFFBOARD, CommandKind.HOLD):
            self.mode = FlightMode.HOLD
        elif k == CommandKind.LAND:
            self.mode = FlightMode.LAND
        elif k == CommandKind.RTL:
            self.mode = FlightMode.RETURN_TO_LAUNCH
        return CommandResult(k, True)

    def advance(self, dt_s: float) -> None:
        if self.mode == FlightMode.TAKEOFF:
            self.alt_rel_m = min(self.target_alt_m, self.alt_rel_m + self.climb_m_s * dt_s)
            if self.alt_rel_m >= self.target_alt_m:
                self.mode = FlightMode.HOLD
                self.landed = LandedState.IN_AIR

    def state(self, now_s: float) -> VehicleState:
        stamp = now_s if self.telemetry else now_s - 100.0
        if self.frozen_at_s is not None:
            stamp = self.frozen_at_s
        return VehicleState(
            stamp_s=now_s,
            connected=self.connected,
            heartbeat_stamp_s=stamp,
            armed=self.armed,
            flight_mode=self.mode,
            landed_state=self.landed,
            yaw_rad=self.yaw_rad,
            attitude_stamp_s=stamp - self.attitude_lag_s,
            v_ned_m_s=self.v_ned_m_s,
            velocity_stamp_s=stamp,
            p_ned_m=self.p_ned_m,
            local_position_stamp_s=stamp,
            alt_rel_m=self.alt_rel_m,
            global_position_stamp_s=stamp,
            gps_fix_type=self.gps_fix,
            gps_satellites=10 if self.gps_fix >= 3 else 0,
            gps_stamp_s=stamp,
            global_position_ok=self.gps_fix >= 3,
            local_position_ok=self.gps_fix >= 3,
            home_position_ok=self.home_ok,
            armable=True,
            health_stamp_s=stamp,
            position_valid=self.position_valid,
            estimator_stamp_s=stamp,
        )

    def fly(self, alt_m: float = 5.0) -> None:
        """Put the fake in the air, armed, holding."""
        self.armed = True
        self.mode = FlightMode.HOLD
        self.landed = LandedState.IN_AIR
        self.alt_rel_m = alt_m


def leader(
    now_s: float,
    status: TrackStatus = TrackStatus.CONFIRMED,
    p: tuple[float, float, float] = (5.0, 0.0, 0.0),
    v: tuple[float, float, float] = (0.0, 0.0, 0.0),
    *,
    track_age_s: float = math.inf,
    hit_ratio: float = 1.0,
    last_measurement_s: float | None = None,
) -> LeaderEstimate:
    return LeaderEstimate(
        stamp_s=now_s,
        status=status,
        p_ned_rel_m=p,
        v_ned_rel_m_s=v,
        last_measurement_s=now_s if last_measurement_s is None else last_measurement_s,
        track_age_s=track_age_s,
        recent_hit_ratio=hit_ratio,
    )


class Harness:
    """One machine, one fake autopilot, one ManualClock; records everything that came out."""

    def __init__(self, cfg: Config | None = None, ap: FakeAutopilot | None = None) -> None:
        self.cfg = cfg or Config()
        self.clock = ManualClock(100.0)
        self.machine = MissionMachine(self.cfg)
        self.ap = ap or FakeAutopilot()
        self.results: list[CommandResult] = []
        self.outputs: list[StepOutput] = []
        self.transitions: list[Transition] = []
        self.start = False
        #: The start came from an operator (may take a vehicle already flying).
        self.takeover = False
        self.shutdown = False
        #: None: no tracker output at all; "fresh": a fresh estimate each step with ``status``; "frozen":
        #: the last estimate keeps being offered (a stalled pipeline).
        self.leader_mode: str | None = None
        self.leader_status = TrackStatus.CONFIRMED
        self.leader_p = (5.0, 0.0, 0.0)
        self.leader_v = (0.0, 0.0, 0.0)
        #: The track's age and recent hit ratio offered with a fresh estimate (the tracker's quality).
        self.leader_track_age_s = math.inf
        self.leader_hit_ratio = 1.0
        #: When the track last had a detection (None: at every step's frame).
        self.leader_last_measurement_s: float | None = None
        self.shared: tuple[float, float, float] | None = None
        #: The velocity the leader shares with its position (NED, m/s), if any.
        self.shared_v: tuple[float, float, float] | None = None
        #: The depth guard's reading offered each step (relative NED, m) and how old it is, s.
        self.obstacle: tuple[float, float, float] | None = None
        self.obstacle_age_s = 0.0
        #: One-shot operator command for the next step.
        self.operator: OperatorCommand | None = None
        self._frozen: LeaderEstimate | None = None

    @property
    def now_s(self) -> float:
        return self.clock.now_s()

    @property
    def state(self) -> MissionState:
        return self.machine.state

    def _leader(self) -> LeaderEstimate | None:
        if self.leader_mode == "fresh":
            self._frozen = leader(
                self.now_s,
                self.leader_status,
                self.leader_p,
                self.leader_v,
                track_age_s=self.leader_track_age_s,
                hit_ratio=self.leader_hit_ratio,
                last_measurement_s=self.leader_last_measurement_s,
            )
            return self._frozen
        if self.leader_mode == "frozen":
            return self._frozen
        return None

    def step(self) -> StepOutput:
        self.clock.advance(DT_S)
        self.ap.advance(DT_S)
        shared = None
        if self.shared is not None:
            shared = SharedLeaderPosition(stamp_s=self.now_s, p_ned_m=self.shared, v_ned_m_s=self.shared_v)
        inp = MissionInputs(
            vehicle=self.ap.state(self.now_s),
            leader=self._leader(),
            leader_shared=shared,
            obstacle=None
            if self.obstacle is None
            else ObstacleAhead(stamp_s=self.now_s - self.obstacle_age_s, p_ned_rel_m=self.obstacle),
            start_requested=self.start or self.takeover,
            takeover_requested=self.takeover,
            shutdown_requested=self.shutdown,
            command_results=tuple(self.results),
            operator=None if self.operator is None else OperatorRequest(self.operator),
        )
        self.results = []
        self.operator = None
        out = self.machine.step(inp, self.now_s)
        self.outputs.append(out)
        self.transitions.extend(out.transitions)
        for cmd in out.commands:
            r = self.ap.apply(cmd)
            if r is not None:
                self.results.append(r)
        return out

    def stall(self, seconds: float) -> StepOutput:
        """The service paused for ``seconds`` (no step), then one step on what it had read before."""
        before_s = self.now_s
        self.ap.frozen_at_s = before_s
        self.leader_mode = "frozen" if self.leader_mode == "fresh" else self.leader_mode
        self.clock.advance(seconds - DT_S)
        return self.step()

    def run(self, seconds: float) -> list[StepOutput]:
        n = max(1, round(seconds / DT_S))
        return [self.step() for _ in range(n)]

    def run_until(self, state: MissionState, timeout_s: float = 60.0) -> StepOutput:
        t_end = self.now_s + timeout_s
        while self.now_s < t_end:
            out = self.step()
            if out.state == state:
                return out
        raise AssertionError(f"never reached {state}; stuck in {self.state}; transitions {self.reasons()}")

    def reasons(self) -> list[tuple[str, str, str]]:
        return [(t.from_state.value, t.to_state.value, t.reason.name) for t in self.transitions]

    def last_transition(self) -> Transition:
        return self.transitions[-1]

    def has(self, to: MissionState, reason: Reason) -> bool:
        return any(t.to_state == to and t.reason == reason for t in self.transitions)

    # ------------------------------------------------------------------ canned paths
    def to_follow(self) -> None:
        """Boot, arm, take off, acquire: ends in FOLLOW with offboard confirmed."""
        self.start = True
        self.leader_mode = "fresh"
        self.run_until(MissionState.FOLLOW, timeout_s=60.0)
        self.run(0.5)
        assert self.state == MissionState.FOLLOW
        assert self.ap.mode == FlightMode.OFFBOARD

    def lose_gps(self) -> None:
        self.ap.gps_fix = 0


def all_commands(outputs: list[StepOutput]) -> list[CommandKind]:
    return [c.kind for o in outputs for c in o.commands]


def isclose3(a: tuple[float, float, float], b: tuple[float, float, float], tol: float = 1e-9) -> bool:
    return all(math.isclose(x, y, abs_tol=tol) for x, y in zip(a, b, strict=True))
