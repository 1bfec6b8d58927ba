"""The mission state machine: pure, time passed in, one ``step(inputs, now_s)`` per control tick.

States and the ladder (see :class:`~companion.mission.types.MissionState`)::

    WAIT_LINK -> PREFLIGHT -> ARMING -> TAKEOFF -> ACQUIRE -> FOLLOW
    FOLLOW --GPS lost, leader tracked--> FOLLOW_VISION (attitude+thrust, or velocity on an external fix)
    FOLLOW / FOLLOW_VISION --leader lost--> REACQUIRE (coast, then yaw scan) --timeout--> abort
    FOLLOW / FOLLOW_VISION / REACQUIRE --estimate stale--> HOVER --stall timeout--> abort
    abort: GPS healthy -> PX4_HOLD | PX4_LAND | PX4_RTL (leader_lost_action); no GPS -> CONTROLLED_LANDING
    PX4_HOLD / PX4_IN_CONTROL --operator start, GPS healthy--> ACQUIRE (follow again)
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

This module holds the tick, the rules above and the operator's checks; the health checks are in
:mod:`companion.mission.monitors`, the command and offboard bookkeeping in :mod:`companion.mission.offboard`,
and the state handlers in :mod:`companion.mission.states`: one object per flight phase (launch, follow,
recovery, landing), each with its own memory, reading the
:class:`~companion.mission.states.context.MissionContext` and returning its setpoint and at most one
transition request. Only :class:`~companion.mission.transitions.Transitions` changes the state.
"""

from __future__ import annotations

import math

import numpy as np

from companion.config import Config, slot_refusal
from companion.kernel.flight import FlightMode, VehicleState
from companion.mission.ego import HOLD_S as EGO_STALE_S
from companion.mission.formation import FormationLaw
from companion.mission.geometry import Slot
from companion.mission.next_step import next_step
from companion.mission.offboard import OffboardStream
from companion.mission.safety import SafetyLimits
from companion.mission.shared_motion import SharedLeaderMotion
from companion.mission.states import (
    AIRBORNE_STATES,
    NOT_IN_CONTROL,
    OFFBOARD_STATES,
    PX4_STATES,
    FollowPhase,
    LandingPhase,
    LaunchPhase,
    MissionContext,
    RecoveryPhase,
)
from companion.mission.states.launch import ARM_ATTEMPTS
from companion.mission.states.request import STAY, PhaseStep, TransitionRequest, abort, go, go_px4
from companion.mission.transitions import Transitions
from companion.mission.types import (
    CommandKind,
    CommandResult,
    MissionInputs,
    MissionState,
    OperatorCommand,
    OperatorRequest,
    Reason,
    StepOutput,
    VisionMode,
)

__all__ = ["AIRBORNE_STATES", "OFFBOARD_STATES", "PX4_STATES", "START_IGNORED", "MissionMachine"]

#: States where a start has nothing to act on: the mission is under way, or the vehicle is coming down.
START_IGNORED = OFFBOARD_STATES | {
    MissionState.ARMING,
    MissionState.TAKEOFF,
    MissionState.ACQUIRE,
    MissionState.PX4_LAND,
    MissionState.PX4_RTL,
    MissionState.LANDED,
    MissionState.LINK_LOST,
}


class MissionMachine:
    """The follower's mission: ``step(inputs, now_s) -> StepOutput``. No I/O, no clock, no asyncio.

    It owns the :class:`MissionContext` (``c``) the phases read and one object per flight phase, each with
    its own memory; this class holds the tick, the rules that hold in every state and the operator's
    checks. Phases and checks ask for transitions; :class:`~companion.mission.transitions.Transitions`
    applies them, the only place the state changes.
    """

    def __init__(self, cfg: Config, law: FormationLaw | None = None) -> None:
        self.c = MissionContext(cfg, law)
        self.launch = LaunchPhase(self.c)
        self.recovery = RecoveryPhase(self.c)
        self.follow = FollowPhase(self.c)
        self.landing = LandingPhase(self.c)
        self.transitions = Transitions(self.c, self.launch, self.follow, self.recovery, self.landing)
        self._hover_thrust_seeded = False
        f = cfg.formation
        #: The leader's own motion from its shares (``formation.lead_on_shared_motion``).
        self._shared_motion = (
            SharedLeaderMotion(f.shared_accel_tau_s, f.shared_motion_max_age_s, f.max_accel_m_s2)
            if f.lead_on_shared_motion
            else None
        )

    @property
    def state(self) -> MissionState:
        return self.c.state

    @state.setter
    def state(self, state: MissionState) -> None:
        self.c.state = state

    @property
    def law(self) -> FormationLaw:
        """The formation law (its slot is the operator's ``set_offset``)."""
        return self.c.law

    @property
    def limits(self) -> SafetyLimits:
        return self.c.limits

    @property
    def vision_mode(self) -> VisionMode | None:
        return self.follow.vision_mode

    @property
    def offboard(self) -> OffboardStream:
        return self.c.offboard

    # ------------------------------------------------------------------ public
    def step(self, inp: MissionInputs, now_s: float) -> StepOutput:
        """Advance the mission to ``now_s`` with this tick's inputs."""
        self._begin_tick(inp, now_s)
        veh = inp.vehicle
        # An operator's request is checked once, here, on the tick that acts on it: the verdict is the answer.
        req = inp.operator
        refused = None if req is None else self._operator_verdict(req, veh)
        taken = req.command if req is not None and refused is None else None
        start = inp.start_requested or taken == OperatorCommand.START
        takeover = inp.takeover_requested or taken == OperatorCommand.START
        # A start is kept until a state can act on it; where none can, it is dropped (never kept for later).
        self.c.start.update(start, takeover, actionable=self.c.state not in START_IGNORED)
        if inp.leader is not None and inp.leader.usable and self.c.fresh(inp.leader):
            self.c.last_leader = inp.leader
        self.c.update_neighbours(inp)

        self._global_checks(inp, taken if taken in (OperatorCommand.LAND, OperatorCommand.HOLD) else None)
        step = self._run_phases(inp)
        setpoint, ext, err = step.setpoint, step.external, step.error_ned_m
        if self._manage_offboard(inp, setpoint is not None):
            setpoint, ext, err = None, None, None
        ready = self._ready_to_exit(veh)
        return StepOutput(
            state=self.c.state,
            setpoint=setpoint,
            commands=tuple(self.c.book.outgoing),
            external_position=ext,
            transitions=tuple(self.transitions.log),
            ready_to_exit=ready,
            vision_mode=self.follow.vision_mode if self.c.state == MissionState.FOLLOW_VISION else None,
            formation_error_ned_m=None if err is None else (float(err[0]), float(err[1]), float(err[2])),
            operator_refused=refused,
            # FOLLOW and REACQUIRE fly on it in their velocity modes only, which need GPS.
            led_on_shared_motion=self.c.leader_motion is not None
            and self.c.gps.ok
            and self.c.state in (MissionState.FOLLOW, MissionState.REACQUIRE),
            coasted_on_shared_position=self.follow.coasted_on_share and self.c.state == MissionState.FOLLOW,
        )

    @property
    def gps_ok(self) -> bool:
        """The debounced GPS verdict the machine flies on."""
        return self.c.gps.ok

    # ------------------------------------------------------------------ plumbing
    def _begin_tick(self, inp: MissionInputs, now_s: float) -> None:
        """The tick's time, the command results, the shared motion, the GPS verdict and our own velocity."""
        self.c.now_s = now_s
        self.c.ages.tick(now_s)
        self.c.book.outgoing = []
        self.transitions.begin_tick()
        self._absorb(inp.command_results)
        veh = inp.vehicle
        self.follow.coasted_on_share = False
        if self._shared_motion is not None:
            self.c.leader_motion = self._shared_motion.update(inp.leader_shared, now_s)
        self._seed_hover_thrust(veh)
        self.c.gps.update(veh, now_s)
        if self.c.gps.ok and veh.position_valid is not False:
            if now_s - veh.velocity_stamp_s <= EGO_STALE_S:
                self.c.ego.push(min(veh.velocity_stamp_s, now_s), np.array(veh.v_ned_m_s))
        else:
            self.c.ego.clear()

    def _run_phases(self, inp: MissionInputs) -> PhaseStep:
        """The state's handler, its request applied; a transition re-runs the new state's in the same tick."""
        step = STAY
        for _ in range(4):
            before = self.c.state
            step = self._handle(inp)
            self.transitions.apply(step.request, inp)
            if self.c.state == before:
                break
        return step

    def _absorb(self, results: tuple[CommandResult, ...]) -> None:
        for r in results:
            self.c.book.absorb(r)
            if r.kind == CommandKind.START_OFFBOARD and not r.ok:
                self.c.offboard.last_try_s = self.c.now_s

    def _seed_hover_thrust(self, veh: VehicleState) -> None:
        if not self._hover_thrust_seeded and veh.hover_thrust_norm is not None:
            self.c.law.thrust.hover_thrust_norm = veh.hover_thrust_norm
            self._hover_thrust_seeded = True

    # ------------------------------------------------------------------ global checks
    def _global_checks(self, inp: MissionInputs, land_or_hold: OperatorCommand | None) -> None:
        self.transitions.apply(self._global_request(inp, land_or_hold), inp)

    def _global_request(
        self, inp: MissionInputs, land_or_hold: OperatorCommand | None
    ) -> TransitionRequest | None:
        """The rules of every state, in order: the link, a shutdown, the operator, a pilot, the geofence."""
        veh = inp.vehicle
        st = self.c.state
        self.c.link.watch_age(veh, self.c.now_s)
        if st != MissionState.WAIT_LINK and not self.c.link_ok(veh):
            if st in AIRBORNE_STATES or st == MissionState.LANDED:
                return go(MissionState.LINK_LOST, Reason.LINK_LOST)
            if st != MissionState.LINK_LOST:
                return go(MissionState.WAIT_LINK, Reason.LINK_LOST)
            return None
        if inp.shutdown_requested and not self.c.shutting_down:
            self.c.shutting_down = True
            return self._on_shutdown(veh)
        if land_or_hold is not None:
            taken, req = self._on_operator(land_or_hold, veh)
            if taken:
                return req
        if (
            st in OFFBOARD_STATES
            and self.c.offboard.confirmed
            and veh.flight_mode not in (FlightMode.OFFBOARD, FlightMode.UNKNOWN)
            and not self.c.in_flight(CommandKind.START_OFFBOARD)
        ):
            self.c.offboard.release()  # never STOP_OFFBOARD: MAVSDK's stop() asks for Hold
            if veh.armed:
                return go(MissionState.PX4_IN_CONTROL, Reason.MODE_CHANGED_EXTERNALLY, veh.flight_mode.value)
            return go(MissionState.DISARMED, Reason.DISARMED, "disarmed by the autopilot")
        if st in OFFBOARD_STATES and self.c.gps.ok and st != MissionState.CONTROLLED_LANDING:
            r = math.hypot(veh.p_ned_m[0], veh.p_ned_m[1])
            if r > self.c.limits.geofence_radius_m:
                return go_px4(MissionState.PX4_RTL, Reason.GEOFENCE_BREACH, f"{r:.0f} m from home")
        return None

    def _on_shutdown(self, veh: VehicleState) -> TransitionRequest | None:
        st = self.c.state
        if st in NOT_IN_CONTROL:
            self.transitions.note(Reason.SHUTDOWN_REQUESTED)
            return None
        if st in (MissionState.ARMING, MissionState.LANDED) or (veh.armed and not veh.in_air):
            return go(MissionState.LANDED, Reason.SHUTDOWN_REQUESTED)
        if st in PX4_STATES and st != MissionState.PX4_HOLD:
            self.transitions.note(Reason.SHUTDOWN_REQUESTED)
            return None
        action = self.c.m.shutdown_action
        if not self.c.gps.ok or action == "land":
            return go_px4(MissionState.PX4_LAND, Reason.SHUTDOWN_REQUESTED, "" if self.c.gps.ok else "no GPS")
        if st == MissionState.PX4_HOLD:
            self.transitions.note(Reason.SHUTDOWN_REQUESTED, restart_clock=True)  # the hold period starts now
            return None
        return go_px4(MissionState.PX4_HOLD, Reason.SHUTDOWN_REQUESTED, action)

    def _on_operator(self, cmd: OperatorCommand, veh: VehicleState) -> tuple[bool, TransitionRequest | None]:
        """An operator's land or hold, in flight only: whether it is taken, and where it goes."""
        st = self.c.state
        if st not in AIRBORNE_STATES or not veh.in_air:
            return False, None
        if cmd == OperatorCommand.LAND:
            if not self.c.gps.ok:
                return True, go(MissionState.CONTROLLED_LANDING, Reason.OPERATOR_LAND, "no GPS")
            if st != MissionState.PX4_LAND:
                return True, go_px4(MissionState.PX4_LAND, Reason.OPERATOR_LAND)
            return True, None
        if cmd == OperatorCommand.HOLD and self.c.gps.ok and st != MissionState.PX4_HOLD:
            return True, go_px4(MissionState.PX4_HOLD, Reason.OPERATOR_HOLD)
        return False, None  # hold without GPS is impossible on PX4: refused (the runner says so)

    def _operator_verdict(self, req: OperatorRequest, veh: VehicleState) -> str | None:
        """Why this tick refuses ``req`` (None: taken; a new slot is applied here)."""
        cmd = req.command
        if cmd == OperatorCommand.START:
            return self.start_refusal(veh)
        if cmd == OperatorCommand.SET_OFFSET:
            return "it needs offset_cam_m" if req.offset_cam_m is None else self.set_slot(req.offset_cam_m)
        return self.operator_refusal(cmd)

    def operator_refusal(self, cmd: OperatorCommand) -> str | None:
        """Why the machine would refuse an operator's land or hold now (None: it will act on it)."""
        st = self.c.state
        if st == MissionState.OBSERVE:
            return "the companion is only observing this vehicle (run companion start to take it)"
        if st not in AIRBORNE_STATES:
            return f"the companion is not flying the vehicle (state {st.value})"
        if cmd == OperatorCommand.HOLD and not self.c.gps.ok:
            return "hold needs GPS (PX4 cannot hold without a position); land instead"
        if cmd == OperatorCommand.HOLD and st == MissionState.PX4_HOLD:
            return "already holding (PX4 Hold); companion start follows again"
        if cmd == OperatorCommand.LAND and st == MissionState.PX4_LAND:
            return "already landing (PX4 Land)"
        return None

    def preflight_problems(self, veh: VehicleState) -> tuple[str, ...] | None:
        """Before a start on the ground: what a start would be refused for now (``companion health``).

        In PREFLIGHT and DISARMED the same verdict as :meth:`start_refusal` (debounced GPS, home, on the
        ground); in WAIT_LINK and LINK_LOST on the ground, the link the mission does not trust yet (a
        heartbeat alone is not enough: telemetry must be fresh). None in the other states, where preflight
        does not apply.
        """
        st = self.c.state
        if veh.armed and veh.in_air:
            return None
        if st in (MissionState.WAIT_LINK, MissionState.LINK_LOST):
            return (f"no link to the autopilot (state {st.value})",)
        if st not in (MissionState.PREFLIGHT, MissionState.DISARMED):
            return None
        return tuple(self.launch.preflight_problems(veh))

    def start_refusal(self, veh: VehicleState) -> str | None:
        """Why an operator's start would do nothing now (None: the next step acts on it).

        From the ground a start arms once preflight passes; in the air (OBSERVE, after a hold, or after a
        pilot's or failsafe's mode change) it takes the vehicle back and acquires the leader again, with
        GPS only (no GPS and no verdict yet in OBSERVE: refused; a confirmed loss there lands under control).
        """
        st = self.c.state
        if self.c.shutting_down:
            return "the service is stopping"
        if st in (MissionState.WAIT_LINK, MissionState.LINK_LOST):
            return f"no link to the autopilot (state {st.value})"
        if st in (MissionState.PREFLIGHT, MissionState.DISARMED):
            if st == MissionState.PREFLIGHT and veh.armed and veh.in_air:
                return None  # found flying: the start takes it (OBSERVE's rules)
            problems = self.launch.preflight_problems(veh)
            if not problems:
                return None
            return (
                f"preflight: {', '.join(problems)}; start again once it passes "
                "(companion health --wait 60 waits for it)"
            )
        if st == MissionState.OBSERVE:
            if self.c.gps.ok or self.c.gps.loss_confirmed(veh, self.c.now_s):
                return None
            return "no GPS verdict yet (a fix, or a confirmed loss); try again in a few seconds"
        if st in (MissionState.PX4_HOLD, MissionState.PX4_IN_CONTROL):
            if not (veh.armed and veh.in_air):
                return f"the vehicle is not flying (state {st.value})"
            if not self.c.gps.ok:
                return "no GPS: the companion takes the vehicle back only with a position (land instead)"
            return None
        if st in (MissionState.PX4_LAND, MissionState.PX4_RTL):
            return f"PX4 is {'landing' if st == MissionState.PX4_LAND else 'returning'} the vehicle: " + (
                "companion command hold first, then start" if self.c.gps.ok else "no GPS to hold it"
            )
        if st == MissionState.CONTROLLED_LANDING:
            return "the companion is landing the vehicle (no GPS)"
        if st == MissionState.LANDED:
            return "landed and disarming: start again once disarmed"
        return f"the mission is already under way (state {st.value})"

    def next_step(self) -> str:
        """What the mission does next from its state and what it waits for (the tail of an answer)."""
        return next_step(self.c.state, self.c.m, arm_attempts=ARM_ATTEMPTS)

    def withdraw_start(self) -> None:
        """Forget a start that was not acted on (the operator was told it was refused)."""
        self.c.start.spend()

    def set_slot(self, offset_cam_m: tuple[float, float, float]) -> str | None:
        """Change the formation slot in flight. Returns why it is refused, or None when applied.

        The rule is the config's (:func:`companion.config.slot_refusal`): ahead of the camera, within
        reach of the detector and off the separation bubble.
        """
        problem = slot_refusal(offset_cam_m, self.c.limits.min_separation_m)
        if problem is None:
            self.c.law.slot = Slot.from_offset_cam(offset_cam_m)
        return problem

    def _ready_to_exit(self, veh: VehicleState) -> bool:
        if not self.c.shutting_down:
            return False
        st = self.c.state
        if st in NOT_IN_CONTROL:
            return not self.c.offboard.streaming
        if st == MissionState.PX4_LAND:
            return veh.flight_mode == FlightMode.LAND or not veh.armed
        if st == MissionState.PX4_HOLD:
            return self.c.m.shutdown_action == "hold" and veh.flight_mode == FlightMode.HOLD
        return st in (MissionState.PX4_RTL, MissionState.PX4_IN_CONTROL)

    # ------------------------------------------------------------------ offboard
    def _manage_offboard(self, inp: MissionInputs, wants: bool) -> bool:
        """Start offboard when a state streams setpoints; stop the stream the tick it no longer does.

        Returns True when offboard could not be started and the machine gave up (drop this tick's setpoint).
        """
        detail = self.c.offboard.manage(inp.vehicle, wants, self.c.now_s)
        if detail is None:
            return False
        if self.c.gps.ok:
            self.transitions.apply(abort(Reason.OFFBOARD_REJECTED, detail), inp)
        else:
            self.transitions.apply(go_px4(MissionState.PX4_LAND, Reason.OFFBOARD_REJECTED, detail), inp)
        return True

    # ------------------------------------------------------------------ states
    def _handle(self, inp: MissionInputs) -> PhaseStep:
        """The handler of the state the machine is in: its setpoint and at most one transition request."""
        st = self.c.state
        veh = inp.vehicle
        if st == MissionState.WAIT_LINK:
            return self.launch.wait_link(veh)
        if st == MissionState.PREFLIGHT:
            return self.launch.preflight(inp)
        if st == MissionState.OBSERVE:
            return self.launch.observe(inp)
        if st == MissionState.ARMING:
            return self.launch.arming(veh)
        if st == MissionState.TAKEOFF:
            return self.launch.takeoff(inp)
        if st == MissionState.ACQUIRE:
            return self.launch.acquire(inp)
        if st == MissionState.FOLLOW:
            return self.follow.follow(inp)
        if st == MissionState.FOLLOW_VISION:
            return self.follow.follow_vision(inp)
        if st == MissionState.REACQUIRE:
            return self.recovery.reacquire(inp)
        if st == MissionState.HOVER:
            return self.recovery.hover(inp)
        if st == MissionState.CONTROLLED_LANDING:
            return self.landing.controlled_landing(inp)
        if st in PX4_STATES:
            return self.landing.px4(inp)
        if st == MissionState.LINK_LOST:
            return self.launch.link_lost(veh)
        if st == MissionState.LANDED:
            return self.landing.landed(veh)
        if st == MissionState.DISARMED:
            return self.launch.disarmed(veh)
        raise AssertionError(f"unhandled state {st}")  # pragma: no cover
