"""The mission state machine: pure, time passed in, one ``step(inputs, now_s)`` per control tick.

States and the ladder (see :class:`~companion.mission.types.MissionState`)::

    WAIT_LINK -> PREFLIGHT -> ARMING -> TAKEOFF -> ACQUIRE -> FOLLOW
    FOLLOW --GPS lost, leader tracked--> FOLLOW_VISION (attitude+thrust, or velocity on an external fix)
    FOLLOW / FOLLOW_VISION --leader lost--> REACQUIRE (coast, then yaw scan) --timeout--> abort
    FOLLOW / FOLLOW_VISION / REACQUIRE --estimate stale--> HOVER --stall timeout--> abort
    abort: GPS healthy -> PX4_HOLD | PX4_LAND | PX4_RTL (leader_lost_action); no GPS -> CONTROLLED_LANDING
    CONTROLLED_LANDING -> LANDED -> DISARMED

Rules that hold in every state:

* A setpoint is computed from this tick's inputs or not at all: ``StepOutput.setpoint`` is None whenever
  the companion must not be streaming, and the machine emits STOP_OFFBOARD the tick it stops wanting one.
  A stale estimate never reaches the law: the machine hovers on fresh vehicle telemetry instead.
* Velocity setpoints are used only while GPS is healthy; PX4 declares its velocity invalid ~5 s after a GPS
  loss and would then fail offboard over to Descend, so the machine switches to attitude setpoints as soon
  as the fix is lost (``gps_loss_confirm_s`` after PX4 reports no fix).
* Once PX4 has confirmed offboard, any other mode means a pilot or a failsafe took over: the machine goes
  hands-off (PX4_IN_CONTROL) and never fights it.
* Every transition carries a :class:`~companion.mission.types.Reason`; the runner logs it once and emits it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.config import Config
from companion.estimation.leader import LeaderEstimate, TrackStatus
from companion.kernel.frames import Vec3, wrap_pi
from companion.mission.ego import HOLD_S as EGO_STALE_S
from companion.mission.ego import EgoMotion
from companion.mission.formation import FollowerState, FormationLaw, Slot
from companion.mission.safety import SafetyLimits
from companion.mission.types import (
    Command,
    CommandKind,
    CommandResult,
    MissionInputs,
    MissionState,
    OperatorCommand,
    Reason,
    StepOutput,
    Transition,
    VisionMode,
)
from companion.vehicle.types import (
    AttitudeSetpoint,
    ExternalPosition,
    FlightMode,
    LandedState,
    Setpoint,
    VehicleState,
    VelocityNedSetpoint,
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
_NOT_IN_CONTROL = frozenset(
    {
        MissionState.WAIT_LINK,
        MissionState.PREFLIGHT,
        MissionState.OBSERVE,
        MissionState.DISARMED,
        MissionState.LINK_LOST,
    }
)

#: Re-send a command that got no result after this long (the link's own timeouts are shorter), s.
COMMAND_STALE_S = 10.0
ARM_ATTEMPTS = 3
ARM_RETRY_S = 2.0
OFFBOARD_ATTEMPTS = 3
OFFBOARD_RETRY_S = 1.0
DISARM_RETRY_S = 2.0
#: GPS fix data older than this counts as no fix, s.
GPS_STALE_S = 2.0
#: Attitude telemetry older than this makes the attitude law unavailable, s.
ATTITUDE_STALE_S = 0.5
#: Time constant of the attitude-age average that tells a late link (FormationConfig.steady_link_age_s), s.
LINK_AGE_TAU_S = 1.0
#: A depth-guard reading older than this is dropped (the camera runs at 15-30 Hz), s.
OBSTACLE_STALE_S = 0.5
#: PX4 must report a valid estimate this long before velocity setpoints ride on an external fix, s.
EXTERNAL_PROBATION_S = 1.0
#: A shared leader position older than this is not used, s.
SHARED_STALE_S = 1.0
#: Touchdown: PX4's land detector, or no vertical motion (|v| below this) while commanding a descent.
TOUCHDOWN_V_M_S = 0.15
TOUCHDOWN_CONFIRM_S = 1.0
#: Takeoff counts as done at this fraction of the target altitude.
TAKEOFF_DONE_FRAC = 0.9
#: Altitude-hold gain of the attitude hover (1/s).
ALT_HOLD_KP_1_S = 0.8


@dataclass(slots=True)
class _Pending:
    """A command sent and not answered yet."""

    kind: CommandKind
    sent_s: float


class MissionMachine:
    """The follower's mission: ``step(inputs, now_s) -> StepOutput``. No I/O, no clock, no asyncio."""

    def __init__(self, cfg: Config, law: FormationLaw | None = None) -> None:
        self.cfg = cfg
        self.m = cfg.mission
        self.limits = SafetyLimits.from_config(cfg.safety, cfg.formation.max_accel_m_s2)
        self.law = law or FormationLaw(cfg.formation, self.limits, cfg.mission.hover_thrust_norm)
        self.state = MissionState.WAIT_LINK
        self.entered_s = 0.0
        self.vision_mode: VisionMode | None = None
        # Per-step scratch.
        self._now_s = 0.0
        self._commands: list[Command] = []
        self._transitions: list[Transition] = []
        # Commands in flight and the last result of each kind.
        self._pending: dict[CommandKind, _Pending] = {}
        self._last_result: dict[CommandKind, CommandResult] = {}
        self._attempts = 0
        self._last_attempt_s = -math.inf
        # Offboard bookkeeping.
        self._streaming = False
        self._offboard_confirmed = False
        self._offboard_attempts = 0
        self._offboard_last_try_s = -math.inf
        # GPS debounce.
        self._gps_ok = False
        self._gps_bad_since: float | None = None
        self._gps_good_since: float | None = None
        #: The attitude's age averaged over LINK_AGE_TAU_S, and until when the link counts as late (s).
        self._link_age_avg_s = 0.0
        self._link_age_stamp_s = -math.inf
        self._link_late_until_s = -math.inf
        # Per-state memory.
        self._attitude_kind = False
        self._last_leader: LeaderEstimate | None = None
        #: The follower's own velocity history, to bring camera-time estimates to the control instant.
        self._ego = EgoMotion()
        self._leader_lost_p_ned_m: Vec3 | None = None
        self._leader_lost_v_ned_m_s: Vec3 | None = None
        self._scan_sign = 1.0
        self._alt_hold_m = math.nan
        self._ext_valid_since: float | None = None
        self._ext_since: float | None = None
        self._ext_gave_up = False
        self._ext_reset_counter = 0
        self._touchdown_since: float | None = None
        self._shutting_down = False
        self._start_latched = False
        self._prev_start = False
        self._takeover_latched = False
        self._prev_takeover = False
        self._home_hover_thrust_seeded = False

    # ------------------------------------------------------------------ public
    def step(self, inp: MissionInputs, now_s: float) -> StepOutput:
        """Advance the mission to ``now_s`` with this tick's inputs."""
        self._now_s = now_s
        self._commands = []
        self._transitions = []
        self._absorb(inp.command_results)
        veh = inp.vehicle
        self._seed_hover_thrust(veh)
        self._update_gps(veh, now_s)
        if self._gps_ok and veh.position_valid is not False:
            if now_s - veh.velocity_stamp_s <= EGO_STALE_S:
                self._ego.push(min(veh.velocity_stamp_s, now_s), np.array(veh.v_ned_m_s))
        else:
            self._ego.clear()
        if inp.start_requested and not self._prev_start:
            self._start_latched = True
        self._prev_start = inp.start_requested
        if inp.takeover_requested and not self._prev_takeover:
            self._takeover_latched = True
        self._prev_takeover = inp.takeover_requested
        if inp.leader is not None and inp.leader.usable and self._fresh(inp.leader):
            self._last_leader = inp.leader

        self._global_checks(inp)
        setpoint: Setpoint | None = None
        ext: ExternalPosition | None = None
        err: Vec3 | None = None
        for _ in range(4):  # a transition re-runs the new state's handler in the same tick
            before = self.state
            setpoint, ext, err = self._handle(inp)
            if self.state == before:
                break
        if self._manage_offboard(veh, setpoint is not None):
            setpoint, ext, err = None, None, None
        ready = self._ready_to_exit(veh)
        return StepOutput(
            state=self.state,
            setpoint=setpoint,
            commands=tuple(self._commands),
            external_position=ext,
            transitions=tuple(self._transitions),
            ready_to_exit=ready,
            vision_mode=self.vision_mode if self.state == MissionState.FOLLOW_VISION else None,
            formation_error_ned_m=None if err is None else (float(err[0]), float(err[1]), float(err[2])),
        )

    @property
    def gps_ok(self) -> bool:
        """The debounced GPS verdict the machine flies on."""
        return self._gps_ok

    # ------------------------------------------------------------------ plumbing
    def _go(self, state: MissionState, reason: Reason, detail: str = "") -> None:
        if state == self.state and reason != Reason.VISION_MODE_CHANGED:
            return
        self._transitions.append(Transition(self._now_s, self.state, state, reason, detail))
        if state != self.state:
            self.state = state
            self.entered_s = self._now_s
            self._attempts = 0
            self._last_attempt_s = -math.inf
            self._touchdown_since = None
            self.law.reset()

    def _t_in_state(self) -> float:
        return self._now_s - self.entered_s

    def _send(self, kind: CommandKind, altitude_m: float | None = None) -> None:
        self._pending[kind] = _Pending(kind, self._now_s)
        self._last_result.pop(kind, None)
        self._commands.append(Command(kind, altitude_m))

    def _in_flight(self, kind: CommandKind) -> bool:
        p = self._pending.get(kind)
        return p is not None and self._now_s - p.sent_s < COMMAND_STALE_S

    def _absorb(self, results: tuple[CommandResult, ...]) -> None:
        for r in results:
            self._pending.pop(r.kind, None)
            self._last_result[r.kind] = r
            if r.kind == CommandKind.START_OFFBOARD and not r.ok:
                self._offboard_last_try_s = self._now_s

    def _failed(self, kind: CommandKind) -> CommandResult | None:
        r = self._last_result.get(kind)
        return r if r is not None and not r.ok else None

    def _fresh(self, est: LeaderEstimate | None) -> bool:
        return est is not None and self._now_s - est.stamp_s <= self.m.stale_estimate_s

    def _seed_hover_thrust(self, veh: VehicleState) -> None:
        if not self._home_hover_thrust_seeded and veh.hover_thrust_norm is not None:
            self.law.thrust.hover_thrust_norm = veh.hover_thrust_norm
            self._home_hover_thrust_seeded = True

    # ------------------------------------------------------------------ monitors
    def _link_ok(self, veh: VehicleState) -> bool:
        return veh.connected and self._now_s - veh.attitude_stamp_s <= self.cfg.link.telemetry_timeout_s

    def _gps_good_now(self, veh: VehicleState) -> bool:
        fix = veh.gps_fix_type >= 3 and self._now_s - veh.gps_stamp_s <= GPS_STALE_S
        return fix and veh.position_valid is not False

    def _update_gps(self, veh: VehicleState, now_s: float) -> None:
        if self._gps_good_now(veh):
            self._gps_bad_since = None
            if self._gps_good_since is None:
                self._gps_good_since = now_s
            if not self._gps_ok and now_s - self._gps_good_since >= self.m.gps_restore_s:
                self._gps_ok = True
        else:
            self._gps_good_since = None
            if self._gps_bad_since is None:
                self._gps_bad_since = now_s
            # PX4 saying its position estimate is invalid is final at once; a missing fix needs confirming.
            if veh.position_valid is False or now_s - self._gps_bad_since >= self.m.gps_loss_confirm_s:
                self._gps_ok = False

    def _gps_loss_confirmed(self, veh: VehicleState) -> bool:
        """GPS has been bad long enough to call it lost (independent of the debounced verdict)."""
        if veh.position_valid is False:
            return True
        return (
            self._gps_bad_since is not None and self._now_s - self._gps_bad_since >= self.m.gps_loss_confirm_s
        )

    def _attitude_available(self, veh: VehicleState) -> bool:
        return self._now_s - veh.attitude_stamp_s <= ATTITUDE_STALE_S and math.isfinite(veh.alt_rel_m)

    def _tracked(self, inp: MissionInputs, *, confirmed_only: bool = False) -> bool:
        est = inp.leader
        if not self._fresh(est) or est is None:
            return False
        if confirmed_only:
            return est.status == TrackStatus.CONFIRMED
        return est.usable

    def _steady(self, est: LeaderEstimate | None) -> bool:
        """Whether a track is old enough and seen often enough to be the leader found again after a loss."""
        return (
            est is not None
            and est.track_age_s >= self.m.reacquire_min_track_s
            and est.recent_hit_ratio >= self.m.reacquire_min_hit_ratio
        )

    def _follower(self, veh: VehicleState, *, velocity_valid: bool) -> FollowerState:
        return FollowerState(
            yaw_rad=veh.yaw_rad,
            v_ned_m_s=np.array(veh.v_ned_m_s) if velocity_valid else None,
            v_down_m_s=veh.v_ned_m_s[2],
            alt_rel_m=veh.alt_rel_m,
            p_ned_m=np.array(veh.p_ned_m) if velocity_valid else None,
            roll_rad=veh.roll_rad,
            pitch_rad=veh.pitch_rad,
        )

    # ------------------------------------------------------------------ global checks
    def _global_checks(self, inp: MissionInputs) -> None:
        veh = inp.vehicle
        st = self.state
        self._watch_link_age(veh)
        if st != MissionState.WAIT_LINK and not self._link_ok(veh):
            if st in AIRBORNE_STATES or st == MissionState.LANDED:
                self._go(MissionState.LINK_LOST, Reason.LINK_LOST)
            elif st != MissionState.LINK_LOST:
                self._go(MissionState.WAIT_LINK, Reason.LINK_LOST)
            return
        if inp.shutdown_requested and not self._shutting_down:
            self._shutting_down = True
            self._on_shutdown(veh)
            return
        if inp.operator is not None and self._on_operator(inp.operator, veh):
            return
        if (
            st in OFFBOARD_STATES
            and self._offboard_confirmed
            and veh.flight_mode not in (FlightMode.OFFBOARD, FlightMode.UNKNOWN)
            and not self._in_flight(CommandKind.START_OFFBOARD)
        ):
            # Never STOP_OFFBOARD here: MAVSDK's stop() asks for Hold and would override the pilot.
            self._offboard_confirmed = False
            self._streaming = False
            self._commands.append(Command(CommandKind.RELEASE_OFFBOARD))
            if veh.armed:
                self._go(MissionState.PX4_IN_CONTROL, Reason.MODE_CHANGED_EXTERNALLY, veh.flight_mode.value)
            else:
                self._go(MissionState.DISARMED, Reason.DISARMED, "disarmed by the autopilot")
            return
        if st in OFFBOARD_STATES and self._gps_ok and st != MissionState.CONTROLLED_LANDING:
            r = math.hypot(veh.p_ned_m[0], veh.p_ned_m[1])
            if r > self.limits.geofence_radius_m:
                self._go_px4(MissionState.PX4_RTL, Reason.GEOFENCE_BREACH, f"{r:.0f} m from home")

    def _on_shutdown(self, veh: VehicleState) -> None:
        st = self.state
        if st in _NOT_IN_CONTROL:
            self._transitions.append(Transition(self._now_s, st, st, Reason.SHUTDOWN_REQUESTED))
            return
        if st in (MissionState.ARMING, MissionState.LANDED) or (veh.armed and not veh.in_air):
            self._go(MissionState.LANDED, Reason.SHUTDOWN_REQUESTED)
            return
        if st in PX4_STATES and st != MissionState.PX4_HOLD:
            self._transitions.append(Transition(self._now_s, st, st, Reason.SHUTDOWN_REQUESTED))
            return
        action = self.m.shutdown_action
        if not self._gps_ok or action == "land":
            self._go_px4(MissionState.PX4_LAND, Reason.SHUTDOWN_REQUESTED, "" if self._gps_ok else "no GPS")
        elif st == MissionState.PX4_HOLD:
            self.entered_s = self._now_s  # the hold period starts now
            self._transitions.append(Transition(self._now_s, st, st, Reason.SHUTDOWN_REQUESTED))
        else:
            self._go_px4(MissionState.PX4_HOLD, Reason.SHUTDOWN_REQUESTED, action)

    def _on_operator(self, cmd: OperatorCommand, veh: VehicleState) -> bool:
        """An operator's land or hold, in flight only. True when it changed the state."""
        st = self.state
        if st not in AIRBORNE_STATES or not veh.in_air:
            return False
        if cmd == OperatorCommand.LAND:
            if not self._gps_ok:
                self._go(MissionState.CONTROLLED_LANDING, Reason.OPERATOR_LAND, "no GPS")
            elif st != MissionState.PX4_LAND:
                self._go_px4(MissionState.PX4_LAND, Reason.OPERATOR_LAND)
            return True
        if cmd == OperatorCommand.HOLD and self._gps_ok and st != MissionState.PX4_HOLD:
            self._go_px4(MissionState.PX4_HOLD, Reason.OPERATOR_HOLD)
            return True
        return False  # hold without GPS is impossible on PX4: refused (the runner says so)

    def operator_refusal(self, cmd: OperatorCommand) -> str | None:
        """Why the machine would refuse an operator's land or hold now (None: it will act on it)."""
        st = self.state
        if st == MissionState.OBSERVE:
            return "the companion is only observing this vehicle (run companion start to take it)"
        if st not in AIRBORNE_STATES:
            return f"the companion is not flying the vehicle (state {st.value})"
        if cmd == OperatorCommand.HOLD and not self._gps_ok:
            return "hold needs GPS (PX4 cannot hold without a position); land instead"
        return None

    def set_slot(self, offset_cam_m: tuple[float, float, float]) -> str | None:
        """Change the formation slot in flight. Returns why it is refused, or None when applied.

        The slot must lie ahead of the camera (the leader stays in view) and outside the separation bubble
        with a metre to spare, so the law and the separation barrier never fight at rest.
        """
        slot = Slot.from_offset_cam(offset_cam_m)
        if not all(math.isfinite(c) for c in offset_cam_m):
            return "offset must be finite"
        if slot.forward_m <= 0.0:
            return "the leader must be ahead of the camera (z > 0)"
        dist = math.sqrt(slot.forward_m**2 + slot.right_m**2 + slot.down_m**2)
        if dist < self.limits.min_separation_m + 1.0:
            return f"slot {dist:.1f} m from the leader: closer than min_separation_m + 1 m"
        if abs(slot.bearing_offset_rad) > math.radians(30.0):
            return "the leader would leave the image (more than 30 deg off the axis)"
        self.law.slot = slot
        return None

    def _ready_to_exit(self, veh: VehicleState) -> bool:
        if not self._shutting_down:
            return False
        st = self.state
        if st in _NOT_IN_CONTROL:
            return not self._streaming
        if st == MissionState.PX4_LAND:
            return veh.flight_mode == FlightMode.LAND or not veh.armed
        if st == MissionState.PX4_HOLD:
            return self.m.shutdown_action == "hold" and veh.flight_mode == FlightMode.HOLD
        return st in (MissionState.PX4_RTL, MissionState.PX4_IN_CONTROL)

    # ------------------------------------------------------------------ offboard
    def _manage_offboard(self, veh: VehicleState, wants: bool) -> bool:
        """Start offboard when a state streams setpoints; stop the stream the tick it no longer does.

        Returns True when offboard could not be started and the machine gave up (drop this tick's setpoint).
        """
        if not wants:
            if self._streaming:
                self._stop_stream()
            return False
        self._streaming = True
        if veh.flight_mode == FlightMode.OFFBOARD:
            self._offboard_confirmed = True
            self._offboard_attempts = 0
            return False
        if self._offboard_confirmed or self._in_flight(CommandKind.START_OFFBOARD):
            return False
        if self._now_s - self._offboard_last_try_s < OFFBOARD_RETRY_S:
            return False
        if self._offboard_attempts >= OFFBOARD_ATTEMPTS:
            failed = self._failed(CommandKind.START_OFFBOARD)
            detail = failed.detail if failed else "mode never became offboard"
            self._stop_stream()
            if self._gps_ok:
                self._abort(Reason.OFFBOARD_REJECTED, detail)
            else:
                self._go_px4(MissionState.PX4_LAND, Reason.OFFBOARD_REJECTED, detail)
            return True
        self._offboard_attempts += 1
        self._offboard_last_try_s = self._now_s
        self._send(CommandKind.START_OFFBOARD)
        return False

    def _stop_stream(self) -> None:
        """STOP_OFFBOARD goes out first, before any PX4 mode command of the same tick."""
        self._streaming = False
        self._offboard_confirmed = False
        self._offboard_attempts = 0
        self._offboard_last_try_s = -math.inf
        self._commands.insert(0, Command(CommandKind.STOP_OFFBOARD))
        self._pending[CommandKind.STOP_OFFBOARD] = _Pending(CommandKind.STOP_OFFBOARD, self._now_s)

    def _go_px4(self, state: MissionState, reason: Reason, detail: str = "") -> None:
        """Hand the vehicle to one of PX4's own modes (Hold, Land, RTL); the stream stops the same tick."""
        self._go(state, reason, detail)
        kind = {
            MissionState.PX4_HOLD: CommandKind.HOLD,
            MissionState.PX4_LAND: CommandKind.LAND,
            MissionState.PX4_RTL: CommandKind.RTL,
        }[state]
        self._send(kind)

    def _abort(self, reason: Reason, detail: str = "") -> None:
        """The configured abort: a PX4 mode while GPS is healthy, our controlled landing when it is not."""
        if not self._gps_ok:
            self._go(MissionState.CONTROLLED_LANDING, reason, detail or "no GPS")
            return
        target = {
            "hold": MissionState.PX4_HOLD,
            "land": MissionState.PX4_LAND,
            "rtl": MissionState.PX4_RTL,
        }[self.cfg.mission.leader_lost_action]
        self._go_px4(target, reason, detail)

    def _flying_attitude(self) -> bool:
        """Whether the current flight uses attitude setpoints (no GPS, or vision on attitude)."""
        if not self._gps_ok:
            return True
        return self.state == MissionState.FOLLOW_VISION and self.vision_mode == VisionMode.ATTITUDE

    def _enter_follow(self, inp: MissionInputs, reason: Reason, detail: str = "") -> None:
        """Go to FOLLOW or FOLLOW_VISION, whichever the GPS allows."""
        if self._gps_ok:
            self._go(MissionState.FOLLOW, reason, detail)
            self.law.seed_velocity(np.array(inp.vehicle.v_ned_m_s))
        elif self.m.gps_loss_policy == "land":
            self._go(MissionState.CONTROLLED_LANDING, Reason.GPS_LOST, "policy land")
        else:
            self.vision_mode = VisionMode.ATTITUDE
            self._reset_external()
            self._go(MissionState.FOLLOW_VISION, reason, detail or f"policy {self.m.gps_loss_policy}")

    def _on_gps_lost(self, inp: MissionInputs) -> None:
        """GPS went bad in flight: vision formation if the policy and the leader allow it, else land."""
        veh = inp.vehicle
        if self.m.gps_loss_policy == "land":
            self._go(MissionState.CONTROLLED_LANDING, Reason.GPS_LOST, "policy land")
        elif not self._tracked(inp):
            self._go(MissionState.CONTROLLED_LANDING, Reason.GPS_LOST, "leader not tracked")
        elif not self._attitude_available(veh):
            self._go(MissionState.CONTROLLED_LANDING, Reason.NO_VISION_FALLBACK, "no attitude or altitude")
        else:
            self.vision_mode = VisionMode.ATTITUDE
            self._reset_external()
            self._go(MissionState.FOLLOW_VISION, Reason.GPS_LOST, f"policy {self.m.gps_loss_policy}")

    # ------------------------------------------------------------------ states
    def _handle(self, inp: MissionInputs) -> tuple[Setpoint | None, ExternalPosition | None, Vec3 | None]:
        st = self.state
        veh = inp.vehicle
        if st == MissionState.WAIT_LINK:
            if self._link_ok(veh):
                self._go(MissionState.PREFLIGHT, Reason.LINK_UP)
            return None, None, None
        if st == MissionState.PREFLIGHT:
            self._preflight(inp)
            return None, None, None
        if st == MissionState.OBSERVE:
            self._observe(inp)
            return None, None, None
        if st == MissionState.ARMING:
            self._arming(veh)
            return None, None, None
        if st == MissionState.TAKEOFF:
            self._takeoff(inp)
            return None, None, None
        if st == MissionState.ACQUIRE:
            self._acquire(inp)
            return None, None, None
        if st == MissionState.FOLLOW:
            return self._follow(inp)
        if st == MissionState.FOLLOW_VISION:
            return self._follow_vision(inp)
        if st == MissionState.REACQUIRE:
            return self._reacquire(inp), None, None
        if st == MissionState.HOVER:
            return self._hover(inp), None, None
        if st == MissionState.CONTROLLED_LANDING:
            return self._controlled_landing(inp), None, None
        if st in PX4_STATES:
            self._px4(inp)
            return None, None, None
        if st == MissionState.LINK_LOST:
            self._link_lost(veh)
            return None, None, None
        if st == MissionState.LANDED:
            return self._landed(veh), None, None
        if st == MissionState.DISARMED:
            if self._start_latched and not self._shutting_down and self._link_ok(veh):
                self._start_latched = False
                self._go(MissionState.PREFLIGHT, Reason.START_REQUESTED)
            return None, None, None
        raise AssertionError(f"unhandled state {st}")  # pragma: no cover

    def _preflight_problems(self, veh: VehicleState) -> list[str]:
        problems = []
        if not self._gps_ok:
            problems.append("no GPS")
        if not veh.home_position_ok:
            problems.append("no home")
        if veh.in_air:
            problems.append("in air")
        return problems

    def _preflight(self, inp: MissionInputs) -> None:
        veh = inp.vehicle
        if veh.armed and veh.in_air:
            # A companion (re)started in flight: PX4 flies on its own meanwhile. Take it only when told.
            if self.m.resume_in_air or self._takeover_latched:
                self._take_over(veh)
            else:
                self._go(MissionState.OBSERVE, Reason.AIRBORNE_NOT_STARTED, veh.flight_mode.value)
            return
        if self._start_latched and not self._shutting_down and not self._preflight_problems(veh):
            self._start_latched = False
            self._takeover_latched = False
            self._go(MissionState.ARMING, Reason.PREFLIGHT_OK)

    def _observe(self, inp: MissionInputs) -> None:
        """Airborne, not ours: report, and take over on an operator's start once GPS gives a verdict."""
        veh = inp.vehicle
        if not (veh.armed and veh.in_air):
            self._start_latched = False
            self._takeover_latched = False
            self._go(MissionState.PREFLIGHT, Reason.LANDED_WHILE_OBSERVED)
            return
        if self._takeover_latched and not self._shutting_down:
            self._take_over(veh)

    def _take_over(self, veh: VehicleState) -> None:
        """Into the formation from the air (a start once GPS is good), or down without GPS."""
        if self._gps_ok:
            self._start_latched = False
            self._takeover_latched = False
            self._go(MissionState.ACQUIRE, Reason.ALREADY_FLYING)
        elif self._gps_loss_confirmed(veh):
            self._start_latched = False
            self._takeover_latched = False
            self._go(MissionState.CONTROLLED_LANDING, Reason.ALREADY_FLYING, "no GPS")

    def _arming(self, veh: VehicleState) -> None:
        if veh.armed:
            self._go(MissionState.TAKEOFF, Reason.ARMED)
            return
        if self._in_flight(CommandKind.ARM) or self._now_s - self._last_attempt_s < ARM_RETRY_S:
            return
        if self._attempts >= ARM_ATTEMPTS:
            failed = self._failed(CommandKind.ARM)
            self._go(MissionState.DISARMED, Reason.ARM_FAILED, failed.detail if failed else "still disarmed")
            return
        self._attempts += 1
        self._last_attempt_s = self._now_s
        self._send(CommandKind.ARM)

    def _takeoff(self, inp: MissionInputs) -> None:
        veh = inp.vehicle
        target = self.m.takeoff_altitude_m
        if not veh.armed:
            self._go(MissionState.DISARMED, Reason.DISARMED, "disarmed during takeoff")
            return
        if not self._gps_ok:
            if veh.in_air:
                self._go(MissionState.CONTROLLED_LANDING, Reason.GPS_LOST, "during takeoff")
            else:
                self._go(MissionState.LANDED, Reason.GPS_LOST, "before takeoff")
            return
        if self._attempts == 0:
            self._attempts = 1
            self._send(CommandKind.TAKEOFF, target)
            return
        failed = self._failed(CommandKind.TAKEOFF)
        if failed is not None and not veh.in_air:
            self._go(MissionState.LANDED, Reason.TAKEOFF_FAILED, failed.detail)
            return
        reached = math.isfinite(veh.alt_rel_m) and veh.alt_rel_m >= TAKEOFF_DONE_FRAC * target
        settled = veh.in_air and veh.flight_mode == FlightMode.HOLD and self._t_in_state() > 3.0
        if reached or (settled and veh.alt_rel_m > 1.0):
            self._go(MissionState.ACQUIRE, Reason.TAKEOFF_DONE, f"{veh.alt_rel_m:.1f} m")
        elif self._t_in_state() > self.m.takeoff_timeout_s:
            if veh.in_air:
                self._go_px4(MissionState.PX4_LAND, Reason.TAKEOFF_FAILED, "timeout")
            else:
                self._go(MissionState.LANDED, Reason.TAKEOFF_FAILED, "timeout")

    def _acquire(self, inp: MissionInputs) -> None:
        if not self._gps_ok:
            self._on_gps_lost(inp)
        elif self._tracked(inp, confirmed_only=True):
            self._enter_follow(inp, Reason.LEADER_ACQUIRED)
        elif self._t_in_state() > self.m.acquire_timeout_s:
            self._abort(Reason.ACQUIRE_TIMEOUT)
        elif inp.vehicle.landed_state == LandedState.ON_GROUND and self._t_in_state() > 1.0:
            self._go(MissionState.LANDED, Reason.TOUCHDOWN, "landed while acquiring")

    def _leader_or_transition(self, inp: MissionInputs) -> LeaderEstimate | None:
        """The estimate to fly on, or None after going to HOVER (stale) or REACQUIRE (lost)."""
        est = inp.leader
        if est is None or not self._fresh(est):
            self._enter_hover(inp)
            return None
        if not est.usable:
            self._enter_reacquire(inp, est.status.value)
            return None
        return est

    def _follow(self, inp: MissionInputs) -> tuple[Setpoint | None, ExternalPosition | None, Vec3 | None]:
        veh = inp.vehicle
        if not self._gps_ok:
            self._on_gps_lost(inp)
            return None, None, None
        est = self._leader_or_transition(inp)
        if est is None:
            return None, None, None
        p_rel, v_rel = self._relative_now(est)
        cmd = self.law.velocity(
            p_rel,
            v_rel,
            self._follower(veh, velocity_valid=True),
            self._now_s,
            a_leader_ned_m_s2=est.a_ned_leader_m_s2,
            obstacle_ned_m=self._obstacle_now(inp),
            slew_m_s2=self._slew(est),
            coasting=est.status == TrackStatus.COASTING,
        )
        return cmd.setpoint, None, cmd.error.error_ned_m

    def _slew(self, est: LeaderEstimate) -> float:
        """The command slew, m/s^2: the faster one only while the leader is seen steadily on a clean link."""
        f = self.cfg.formation
        steady = est.status == TrackStatus.CONFIRMED and est.recent_hit_ratio >= f.steady_hit_ratio
        clean = self._now_s >= self._link_late_until_s
        return f.command_slew_steady_m_s2 if steady and clean else f.command_slew_m_s2

    def _watch_link_age(self, veh: VehicleState) -> None:
        """Note late telemetry, which keeps the fast slew off.

        Late: the attitude's age averaged over ~1 s above ``steady_link_age_s``, and for
        ``steady_link_hold_s`` after (a lossy or slow link; the fast slew swung the follower there).
        """
        f = self.cfg.formation
        age_s = min(max(self._now_s - veh.attitude_stamp_s, 0.0), 1.0)
        dt_s = min(max(self._now_s - self._link_age_stamp_s, 0.0), 1.0)
        self._link_age_stamp_s = self._now_s
        self._link_age_avg_s += dt_s / (LINK_AGE_TAU_S + dt_s) * (age_s - self._link_age_avg_s)
        if self._link_age_avg_s > f.steady_link_age_s:
            self._link_late_until_s = self._now_s + f.steady_link_hold_s

    def _obstacle_now(self, inp: MissionInputs) -> Vec3 | None:
        """The depth guard's obstacle relative to the follower now (static: shifted by our own motion)."""
        ob = inp.obstacle
        if ob is None or not 0.0 <= self._now_s - ob.stamp_s <= OBSTACLE_STALE_S:
            return None
        p = np.array(ob.p_ned_rel_m)
        disp = self._ego.displacement(ob.stamp_s, self._now_s)
        return p if disp is None else p - disp

    def _relative_now(self, est: LeaderEstimate) -> tuple[Vec3, Vec3]:
        """The estimate brought from its frame's capture instant to now (see :mod:`companion.mission.ego`)."""
        a_leader = (
            self.law.leader_accel_ned_m_s2
            if est.a_ned_leader_m_s2 is None
            else np.array(est.a_ned_leader_m_s2)
        )
        rel = self._ego.predict(
            est.stamp_s, np.array(est.p_ned_rel_m), np.array(est.v_ned_rel_m_s), self._now_s, a_leader
        )
        return rel.p_ned_rel_m, rel.v_ned_rel_m_s

    def _external_fix(self, inp: MissionInputs) -> ExternalPosition | None:
        """The follower's position for PX4: the leader's shared position minus the seen relative vector."""
        est, shared = inp.leader, inp.leader_shared
        if est is None or shared is None or self._now_s - shared.stamp_s > SHARED_STALE_S:
            return None
        p = np.array(shared.p_ned_m) - np.array(est.p_ned_rel_m)
        var = np.array(shared.variance_m2) + np.array(est.var_ned_rel_m2)
        veh = inp.vehicle
        return ExternalPosition(
            stamp_s=est.stamp_s,
            p_ned_m=(float(p[0]), float(p[1]), float(p[2])),
            variance_m2=(float(var[0]), float(var[1]), float(var[2])),
            yaw_rad=veh.yaw_rad,
            roll_rad=veh.roll_rad,
            pitch_rad=veh.pitch_rad,
            reset_counter=self._ext_reset_counter,
        )

    def _follow_vision(
        self, inp: MissionInputs
    ) -> tuple[Setpoint | None, ExternalPosition | None, Vec3 | None]:
        veh = inp.vehicle
        if self._gps_ok:
            self._go(MissionState.FOLLOW, Reason.GPS_RESTORED)
            self.law.seed_velocity(np.array(veh.v_ned_m_s))
            return None, None, None
        if not self._attitude_available(veh):
            self._go(MissionState.CONTROLLED_LANDING, Reason.NO_VISION_FALLBACK, "no attitude or altitude")
            return None, None, None
        est = self._leader_or_transition(inp)
        if est is None:
            return None, None, None
        p_rel, v_rel = self._relative_now(est)
        ext = self._external_fix(inp) if self.m.gps_loss_policy == "vision_external_position" else None

        if self.vision_mode == VisionMode.EXTERNAL_POSITION:
            if ext is None or veh.position_valid is not True:
                why = "shared leader position stale" if ext is None else "PX4 rejected the external fix"
                self.vision_mode = VisionMode.ATTITUDE
                self._reset_external()
                self.law.reset()
                self._go(MissionState.FOLLOW_VISION, Reason.VISION_MODE_CHANGED, f"attitude: {why}")
            else:
                vcmd = self.law.velocity(
                    p_rel,
                    v_rel,
                    self._follower(veh, velocity_valid=True),
                    self._now_s,
                    a_leader_ned_m_s2=est.a_ned_leader_m_s2,
                    obstacle_ned_m=self._obstacle_now(inp),
                )
                return vcmd.setpoint, ext, vcmd.error.error_ned_m
        elif ext is not None and not self._ext_gave_up:
            # Attitude mode while PX4 digests the external fix; switch once it has been valid a while.
            if self._ext_since is None:
                self._ext_since = self._now_s
            if veh.position_valid is True:
                if self._ext_valid_since is None:
                    self._ext_valid_since = self._now_s
                if self._now_s - self._ext_valid_since >= EXTERNAL_PROBATION_S:
                    self.vision_mode = VisionMode.EXTERNAL_POSITION
                    self.law.reset()
                    self.law.seed_velocity(np.array(veh.v_ned_m_s))
                    self._go(
                        MissionState.FOLLOW_VISION, Reason.VISION_MODE_CHANGED, "external position accepted"
                    )
                    vcmd = self.law.velocity(
                        p_rel,
                        v_rel,
                        self._follower(veh, velocity_valid=True),
                        self._now_s,
                        a_leader_ned_m_s2=est.a_ned_leader_m_s2,
                        obstacle_ned_m=self._obstacle_now(inp),
                    )
                    return vcmd.setpoint, ext, vcmd.error.error_ned_m
            else:
                self._ext_valid_since = None
                if self._now_s - self._ext_since > self.m.external_position_accept_s:
                    # PX4 does not take the fix: stop sending it and stay on attitude (said once).
                    self._ext_gave_up = True
                    why = (
                        f"attitude: external position not accepted in {self.m.external_position_accept_s:g} s"
                    )
                    self._go(MissionState.FOLLOW_VISION, Reason.VISION_MODE_CHANGED, why)
                    ext = None
        elif self._ext_gave_up:
            ext = None
        acmd = self.law.attitude(p_rel, v_rel, self._follower(veh, velocity_valid=False), self._now_s)
        err = acmd.error.error_ned_m if acmd.error is not None else None
        return acmd.setpoint, ext, err

    def _reset_external(self) -> None:
        self._ext_valid_since = None
        self._ext_since = None
        self._ext_gave_up = False

    def _enter_reacquire(self, inp: MissionInputs, detail: str) -> None:
        veh = inp.vehicle
        self._attitude_kind = self._flying_attitude()
        last = self._last_leader
        if last is not None:
            p_rel, v_rel = np.array(last.p_ned_rel_m), np.array(last.v_ned_rel_m_s)
            age = max(0.0, self._now_s - last.stamp_s)
            self._leader_lost_p_ned_m = (
                np.array(veh.p_ned_m) + p_rel + (np.array(veh.v_ned_m_s) + v_rel) * age
            )
            self._leader_lost_v_ned_m_s = np.array(veh.v_ned_m_s) + v_rel
            bearing = math.atan2(p_rel[1], p_rel[0])
            self._scan_sign = 1.0 if wrap_pi(bearing - veh.yaw_rad) >= 0.0 else -1.0
        else:
            self._leader_lost_p_ned_m = None
            self._leader_lost_v_ned_m_s = None
            self._scan_sign = 1.0
        self._alt_hold_m = veh.alt_rel_m
        self._go(MissionState.REACQUIRE, Reason.LEADER_LOST, detail)

    def _reacquire(self, inp: MissionInputs) -> Setpoint | None:
        veh = inp.vehicle
        if self._tracked(inp, confirmed_only=True) and self._steady(inp.leader):
            self._enter_follow(inp, Reason.LEADER_REACQUIRED)
            return None
        if not self._attitude_kind and not self._gps_ok:
            self._go(MissionState.CONTROLLED_LANDING, Reason.GPS_LOST, "while re-acquiring")
            return None
        t = self._t_in_state()
        if t > self.m.reacquire_coast_s + self.m.reacquire_scan_s:
            self._abort(Reason.REACQUIRE_TIMEOUT)
            return None
        scanning = t > self.m.reacquire_coast_s
        scan_rate = self._scan_sign * math.radians(self.m.scan_yaw_rate_deg_s) if scanning else 0.0
        candidate = self._candidate_rel(inp)
        if candidate is not None and scanning:
            # Look at what the tracker has found, not yet steady, so it stays in view while it proves
            # itself; never fly toward it (a phantom must not pull the follower).
            scan_rate = self._look_rate(candidate, veh.yaw_rad)
        if self._attitude_kind:
            fol = self._follower(veh, velocity_valid=False)
            v_down = self._alt_hold_v_down(veh)
            return self.law.hover_attitude(fol, v_down, self._now_s, yaw_rate_rad_s=scan_rate).setpoint
        if not scanning and self._leader_lost_p_ned_m is not None and self._leader_lost_v_ned_m_s is not None:
            # Coast: the leader's last velocity, looking where it dead-reckons to (GPS is healthy), without
            # closing on that guess (see FormationLaw.coast_velocity); looking at a candidate instead
            # when there is one, which the separation barrier then also holds off.
            p_leader = self._leader_lost_p_ned_m + self._leader_lost_v_ned_m_s * t
            p_rel = p_leader - np.array(veh.p_ned_m) if candidate is None else candidate
            return self.law.coast_velocity(
                self._leader_lost_v_ned_m_s,
                p_rel,
                self._follower(veh, velocity_valid=True),
                self._obstacle_now(inp),
            )
        return self.law.hover_velocity(yaw_rate_rad_s=scan_rate)

    def _candidate_rel(self, inp: MissionInputs) -> Vec3 | None:
        """Where a fresh track the mission has not taken (yet) puts the leader, relative NED, m."""
        est = inp.leader
        if est is None or not self._fresh(est) or est.status == TrackStatus.LOST:
            return None
        return np.array(est.p_ned_rel_m, dtype=np.float64)

    def _look_rate(self, p_rel_ned_m: Vec3, yaw_rad: float) -> float:
        """A yaw rate that turns the camera onto a relative position, bounded by the scan rate, rad/s."""
        bearing = math.atan2(p_rel_ned_m[1], p_rel_ned_m[0])
        max_rate = math.radians(self.m.scan_yaw_rate_deg_s)
        return float(np.clip(self.cfg.formation.kp_yaw * wrap_pi(bearing - yaw_rad), -max_rate, max_rate))

    def _alt_hold_v_down(self, veh: VehicleState) -> float:
        if not math.isfinite(self._alt_hold_m):
            self._alt_hold_m = veh.alt_rel_m
        v = ALT_HOLD_KP_1_S * (veh.alt_rel_m - self._alt_hold_m)
        lim = self.limits.max_vertical_speed_m_s
        return float(np.clip(v, -lim, lim))

    def _enter_hover(self, inp: MissionInputs) -> None:
        self._attitude_kind = self._flying_attitude()
        self._alt_hold_m = inp.vehicle.alt_rel_m
        est = inp.leader
        age = "never" if est is None else f"{self._now_s - est.stamp_s:.2f} s old"
        self._go(MissionState.HOVER, Reason.PERCEPTION_STALL, age)

    def _hover(self, inp: MissionInputs) -> Setpoint | None:
        veh = inp.vehicle
        est = inp.leader
        if self._fresh(est) and est is not None:
            if est.usable:
                self._enter_follow(inp, Reason.PERCEPTION_RESUMED)
                return None
            if est.status == TrackStatus.LOST:
                self._enter_reacquire(inp, "after stall")
                return None
        if not self._attitude_kind and not self._gps_ok:
            self._go(MissionState.CONTROLLED_LANDING, Reason.GPS_LOST, "while hovering")
            return None
        if self._t_in_state() > self.m.stall_hover_s:
            self._abort(Reason.STALL_TIMEOUT)
            return None
        if self._attitude_kind:
            fol = self._follower(veh, velocity_valid=False)
            return self.law.hover_attitude(fol, self._alt_hold_v_down(veh), self._now_s).setpoint
        return self.law.hover_velocity()

    def _controlled_landing(self, inp: MissionInputs) -> Setpoint | None:
        veh = inp.vehicle
        if self._touched_down(veh):
            self._go(MissionState.LANDED, Reason.TOUCHDOWN)
            return None
        v_land = self.m.landing_speed_m_s
        if self._gps_ok:
            return VelocityNedSetpoint(v_ned_m_s=(0.0, 0.0, v_land), yaw_rad=veh.yaw_rad)
        est = inp.leader if self._tracked(inp) else None
        fol = self._follower(veh, velocity_valid=False)
        p_rel = None if est is None else np.array(est.p_ned_rel_m)
        v_rel = None if est is None else np.array(est.v_ned_rel_m_s)
        return self.law.hover_attitude(
            fol, v_land, self._now_s, p_ned_rel_m=p_rel, v_ned_rel_m_s=v_rel
        ).setpoint

    def _touched_down(self, veh: VehicleState) -> bool:
        """PX4's land detector, or no vertical motion for a while although we command a descent."""
        if veh.landed_state == LandedState.ON_GROUND and self._t_in_state() > 1.0:
            return True
        still = abs(veh.v_ned_m_s[2]) < TOUCHDOWN_V_M_S and self._t_in_state() > 2.0
        low = not math.isfinite(veh.alt_rel_m) or veh.alt_rel_m < 3.0
        if not (still and low):
            self._touchdown_since = None
            return False
        if self._touchdown_since is None:
            self._touchdown_since = self._now_s
        return self._now_s - self._touchdown_since >= TOUCHDOWN_CONFIRM_S

    def _landed(self, veh: VehicleState) -> Setpoint | None:
        """On the ground and armed: idle thrust (when streaming) and disarm."""
        if not veh.armed:
            self._go(MissionState.DISARMED, Reason.DISARMED)
            return None
        # PX4 refuses to disarm before its land detector agrees; give it a moment before insisting.
        on_ground = veh.landed_state == LandedState.ON_GROUND or self._t_in_state() > DISARM_RETRY_S
        if (
            on_ground
            and not self._in_flight(CommandKind.DISARM)
            and self._now_s - self._last_attempt_s >= DISARM_RETRY_S
        ):
            self._last_attempt_s = self._now_s
            self._send(CommandKind.DISARM)
        if self._streaming:
            # Motors to idle while PX4 disarms: a fresh zero-thrust setpoint, never the last descent one.
            return AttitudeSetpoint(0.0, 0.0, veh.yaw_rad, 0.0)
        return None

    def _px4(self, inp: MissionInputs) -> None:
        veh = inp.vehicle
        st = self.state
        if not veh.armed and self._t_in_state() > 0.5:
            self._go(MissionState.DISARMED, Reason.DISARMED)
            return
        if veh.landed_state == LandedState.ON_GROUND and self._t_in_state() > 1.0 and veh.armed:
            self._go(MissionState.LANDED, Reason.TOUCHDOWN)
            return
        if st in (MissionState.PX4_HOLD, MissionState.PX4_RTL) and not self._gps_ok:
            # PX4 would fall to Descend in these modes; land under our own control instead.
            self._go(MissionState.CONTROLLED_LANDING, Reason.GPS_LOST, f"in {st.value}")
            return
        kind = {MissionState.PX4_HOLD: CommandKind.HOLD, MissionState.PX4_RTL: CommandKind.RTL}.get(st)
        failed = self._failed(kind) if kind is not None else None
        if failed is not None:
            self._go_px4(MissionState.PX4_LAND, Reason.PX4_MODE_REFUSED, f"{st.value}: {failed.detail}")
            return
        if st == MissionState.PX4_LAND and self._failed(CommandKind.LAND) is not None and veh.in_air:
            if not self._in_flight(CommandKind.LAND) and self._now_s - self._last_attempt_s >= ARM_RETRY_S:
                self._last_attempt_s = self._now_s
                self._send(CommandKind.LAND)
            return
        if (
            st == MissionState.PX4_HOLD
            and self._shutting_down
            and self.m.shutdown_action == "hold_then_land"
            and self._t_in_state() >= self.m.shutdown_hold_s
        ):
            self._go_px4(MissionState.PX4_LAND, Reason.HOLD_TIMEOUT)

    def _link_lost(self, veh: VehicleState) -> None:
        if not self._link_ok(veh):
            return
        if not veh.armed:
            self._go(MissionState.DISARMED, Reason.LINK_RESTORED, "disarmed")
        elif not veh.in_air:
            self._go(MissionState.LANDED, Reason.LINK_RESTORED, "on the ground")
        else:
            self._go(MissionState.PX4_IN_CONTROL, Reason.LINK_RESTORED, veh.flight_mode.value)
