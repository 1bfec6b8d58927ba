"""From the link to the formation (WAIT_LINK to ACQUIRE), and DISARMED and LINK_LOST.

PREFLIGHT arms on an operator's start once GPS and home are good; a companion (re)started in flight
OBSERVEs until told to take over. ACQUIRE waits in the air for a confirmed track, then enters the
formation (:mod:`companion.mission.states.follow`). DISARMED waits for the next start, which goes on
through PREFLIGHT to arming; LINK_LOST waits for the link and then says where the vehicle is.
"""

from __future__ import annotations

import math

from companion.kernel.flight import FlightMode, LandedState, VehicleState
from companion.mission.states.context import ARM_RETRY_S, MissionContext, Retries
from companion.mission.states.request import (
    STAY,
    PhaseStep,
    TransitionRequest,
    abort,
    enter_follow,
    go,
    go_px4,
    gps_lost,
    moving,
)
from companion.mission.types import CommandKind, MissionInputs, MissionState, Reason

ARM_ATTEMPTS = 3
#: Takeoff counts as done at this fraction of the target altitude.
TAKEOFF_DONE_FRAC = 0.9


class LaunchPhase:
    """The handlers from WAIT_LINK to ACQUIRE, and of DISARMED and LINK_LOST."""

    def __init__(self, ctx: MissionContext) -> None:
        self.c = ctx
        #: ARMING's tries to arm, TAKEOFF's one takeoff command (cleared on every change of state).
        self.retries = Retries()

    def wait_link(self, veh: VehicleState) -> PhaseStep:
        if self.c.link_ok(veh):
            return moving(go(MissionState.PREFLIGHT, Reason.LINK_UP))
        return STAY

    def preflight_problems(self, veh: VehicleState) -> list[str]:
        problems = []
        if not self.c.gps.ok:
            problems.append("no GPS")
        if not veh.home_position_ok:
            problems.append("no home")
        if veh.in_air:
            problems.append("in air")
        return problems

    def preflight(self, inp: MissionInputs) -> PhaseStep:
        veh = inp.vehicle
        if veh.armed and veh.in_air:
            # A companion (re)started in flight: PX4 flies on its own meanwhile. Take it only when told.
            if self.c.m.resume_in_air or self.c.start.takeover:
                return moving(self._take_over(veh))
            return moving(go(MissionState.OBSERVE, Reason.AIRBORNE_NOT_STARTED, veh.flight_mode.value))
        if self.c.start.requested and not self.c.shutting_down and not self.preflight_problems(veh):
            self.c.start.spend()
            return moving(go(MissionState.ARMING, Reason.PREFLIGHT_OK))
        return STAY

    def observe(self, inp: MissionInputs) -> PhaseStep:
        """Airborne, not ours: report, and take over on an operator's start once GPS gives a verdict."""
        veh = inp.vehicle
        if not (veh.armed and veh.in_air):
            self.c.start.spend()
            return moving(go(MissionState.PREFLIGHT, Reason.LANDED_WHILE_OBSERVED))
        if self.c.start.takeover and not self.c.shutting_down:
            return moving(self._take_over(veh))
        return STAY

    def _take_over(self, veh: VehicleState) -> TransitionRequest | None:
        """Into the formation from the air (a start once GPS is good), or down without GPS."""
        if self.c.gps.ok:
            self.c.start.spend()
            return go(MissionState.ACQUIRE, Reason.ALREADY_FLYING)
        if self.c.gps.loss_confirmed(veh, self.c.now_s):
            self.c.start.spend()
            return go(MissionState.CONTROLLED_LANDING, Reason.ALREADY_FLYING, "no GPS")
        return None

    def arming(self, veh: VehicleState) -> PhaseStep:
        if veh.armed:
            return moving(go(MissionState.TAKEOFF, Reason.ARMED))
        if self.c.in_flight(CommandKind.ARM) or not self.retries.due(self.c.now_s, ARM_RETRY_S):
            return STAY
        if self.retries.attempts >= ARM_ATTEMPTS:
            failed = self.c.failed(CommandKind.ARM)
            detail = failed.detail if failed else "still disarmed"
            return moving(go(MissionState.DISARMED, Reason.ARM_FAILED, detail))
        self.retries.tried(self.c.now_s)
        self.c.send(CommandKind.ARM)
        return STAY

    def takeoff(self, inp: MissionInputs) -> PhaseStep:
        veh = inp.vehicle
        target = self.c.m.takeoff_altitude_m
        if not veh.armed:
            return moving(go(MissionState.DISARMED, Reason.DISARMED, "disarmed during takeoff"))
        if not self.c.gps.ok:
            if veh.in_air:
                return moving(go(MissionState.CONTROLLED_LANDING, Reason.GPS_LOST, "during takeoff"))
            return moving(go(MissionState.LANDED, Reason.GPS_LOST, "before takeoff"))
        if self.retries.attempts == 0:
            self.retries.attempts = 1
            self.c.send(CommandKind.TAKEOFF, target)
            return STAY
        failed = self.c.failed(CommandKind.TAKEOFF)
        if failed is not None and not veh.in_air:
            return moving(go(MissionState.LANDED, Reason.TAKEOFF_FAILED, failed.detail))
        reached = math.isfinite(veh.alt_rel_m) and veh.alt_rel_m >= TAKEOFF_DONE_FRAC * target
        settled = veh.in_air and veh.flight_mode == FlightMode.HOLD and self.c.t_in_state() > 3.0
        if reached or (settled and veh.alt_rel_m > 1.0):
            return moving(go(MissionState.ACQUIRE, Reason.TAKEOFF_DONE, f"{veh.alt_rel_m:.1f} m"))
        if self.c.t_in_state() > self.c.m.takeoff_timeout_s:
            if veh.in_air:
                return moving(go_px4(MissionState.PX4_LAND, Reason.TAKEOFF_FAILED, "timeout"))
            return moving(go(MissionState.LANDED, Reason.TAKEOFF_FAILED, "timeout"))
        return STAY

    def acquire(self, inp: MissionInputs) -> PhaseStep:
        if not self.c.gps.ok:
            return moving(gps_lost())
        if self.c.tracked(inp, confirmed_only=True):
            return moving(enter_follow(Reason.LEADER_ACQUIRED))
        if self.c.t_in_state() > self.c.m.acquire_timeout_s:
            return moving(abort(Reason.ACQUIRE_TIMEOUT))
        if inp.vehicle.landed_state == LandedState.ON_GROUND and self.c.t_in_state() > 1.0:
            return moving(go(MissionState.LANDED, Reason.TOUCHDOWN, "landed while acquiring"))
        return STAY

    def disarmed(self, veh: VehicleState) -> PhaseStep:
        # The start stays latched: PREFLIGHT arms on it in the same tick once its checks pass, so one
        # start after a landing flies again.
        if self.c.start.requested and not self.c.shutting_down and self.c.link_ok(veh):
            return moving(go(MissionState.PREFLIGHT, Reason.START_REQUESTED))
        return STAY

    def link_lost(self, veh: VehicleState) -> PhaseStep:
        if not self.c.link_ok(veh):
            return STAY
        if not veh.armed:
            return moving(go(MissionState.DISARMED, Reason.LINK_RESTORED, "disarmed"))
        if not veh.in_air:
            return moving(go(MissionState.LANDED, Reason.LINK_RESTORED, "on the ground"))
        return moving(go(MissionState.PX4_IN_CONTROL, Reason.LINK_RESTORED, veh.flight_mode.value))
