"""From the link to the formation (WAIT_LINK to ACQUIRE), and DISARMED and LINK_LOST.

PREFLIGHT arms on an operator's start once GPS and home are good; a companion (re)started in flight
OBSERVEs until told to take over. ACQUIRE waits in the air for a confirmed track, then enters the
formation (:mod:`companion.mission.states.follow`). DISARMED waits for the next start, which goes on
through PREFLIGHT to arming; LINK_LOST waits for the link and then says where the vehicle is.
"""

from __future__ import annotations

import math

from companion.kernel.flight import FlightMode, LandedState, VehicleState
from companion.mission.states.context import ARM_RETRY_S, MissionContext
from companion.mission.types import CommandKind, MissionInputs, MissionState, Reason

ARM_ATTEMPTS = 3
#: Takeoff counts as done at this fraction of the target altitude.
TAKEOFF_DONE_FRAC = 0.9


class LaunchPhase:
    """The handlers from WAIT_LINK to ACQUIRE, and of DISARMED and LINK_LOST."""

    def __init__(self, ctx: MissionContext) -> None:
        self.c = ctx

    def wait_link(self, veh: VehicleState) -> None:
        if self.c.link_ok(veh):
            self.c.go(MissionState.PREFLIGHT, Reason.LINK_UP)

    def preflight_problems(self, veh: VehicleState) -> list[str]:
        problems = []
        if not self.c.gps.ok:
            problems.append("no GPS")
        if not veh.home_position_ok:
            problems.append("no home")
        if veh.in_air:
            problems.append("in air")
        return problems

    def preflight(self, inp: MissionInputs) -> None:
        veh = inp.vehicle
        if veh.armed and veh.in_air:
            # A companion (re)started in flight: PX4 flies on its own meanwhile. Take it only when told.
            if self.c.m.resume_in_air or self.c.start.takeover:
                self._take_over(veh)
            else:
                self.c.go(MissionState.OBSERVE, Reason.AIRBORNE_NOT_STARTED, veh.flight_mode.value)
            return
        if self.c.start.requested and not self.c.shutting_down and not self.preflight_problems(veh):
            self.c.start.spend()
            self.c.go(MissionState.ARMING, Reason.PREFLIGHT_OK)

    def observe(self, inp: MissionInputs) -> None:
        """Airborne, not ours: report, and take over on an operator's start once GPS gives a verdict."""
        veh = inp.vehicle
        if not (veh.armed and veh.in_air):
            self.c.start.spend()
            self.c.go(MissionState.PREFLIGHT, Reason.LANDED_WHILE_OBSERVED)
            return
        if self.c.start.takeover and not self.c.shutting_down:
            self._take_over(veh)

    def _take_over(self, veh: VehicleState) -> None:
        """Into the formation from the air (a start once GPS is good), or down without GPS."""
        if self.c.gps.ok:
            self.c.start.spend()
            self.c.go(MissionState.ACQUIRE, Reason.ALREADY_FLYING)
        elif self.c.gps.loss_confirmed(veh, self.c.now_s):
            self.c.start.spend()
            self.c.go(MissionState.CONTROLLED_LANDING, Reason.ALREADY_FLYING, "no GPS")

    def arming(self, veh: VehicleState) -> None:
        if veh.armed:
            self.c.go(MissionState.TAKEOFF, Reason.ARMED)
            return
        if self.c.in_flight(CommandKind.ARM) or self.c.now_s - self.c.last_attempt_s < ARM_RETRY_S:
            return
        if self.c.attempts >= ARM_ATTEMPTS:
            failed = self.c.failed(CommandKind.ARM)
            self.c.go(MissionState.DISARMED, Reason.ARM_FAILED, failed.detail if failed else "still disarmed")
            return
        self.c.attempts += 1
        self.c.last_attempt_s = self.c.now_s
        self.c.send(CommandKind.ARM)

    def takeoff(self, inp: MissionInputs) -> None:
        veh = inp.vehicle
        target = self.c.m.takeoff_altitude_m
        if not veh.armed:
            self.c.go(MissionState.DISARMED, Reason.DISARMED, "disarmed during takeoff")
            return
        if not self.c.gps.ok:
            if veh.in_air:
                self.c.go(MissionState.CONTROLLED_LANDING, Reason.GPS_LOST, "during takeoff")
            else:
                self.c.go(MissionState.LANDED, Reason.GPS_LOST, "before takeoff")
            return
        if self.c.attempts == 0:
            self.c.attempts = 1
            self.c.send(CommandKind.TAKEOFF, target)
            return
        failed = self.c.failed(CommandKind.TAKEOFF)
        if failed is not None and not veh.in_air:
            self.c.go(MissionState.LANDED, Reason.TAKEOFF_FAILED, failed.detail)
            return
        reached = math.isfinite(veh.alt_rel_m) and veh.alt_rel_m >= TAKEOFF_DONE_FRAC * target
        settled = veh.in_air and veh.flight_mode == FlightMode.HOLD and self.c.t_in_state() > 3.0
        if reached or (settled and veh.alt_rel_m > 1.0):
            self.c.go(MissionState.ACQUIRE, Reason.TAKEOFF_DONE, f"{veh.alt_rel_m:.1f} m")
        elif self.c.t_in_state() > self.c.m.takeoff_timeout_s:
            if veh.in_air:
                self.c.go_px4(MissionState.PX4_LAND, Reason.TAKEOFF_FAILED, "timeout")
            else:
                self.c.go(MissionState.LANDED, Reason.TAKEOFF_FAILED, "timeout")

    def acquire(self, inp: MissionInputs) -> None:
        if not self.c.gps.ok:
            self.c.on_gps_lost(inp)
        elif self.c.tracked(inp, confirmed_only=True):
            self.c.enter_follow(inp, Reason.LEADER_ACQUIRED)
        elif self.c.t_in_state() > self.c.m.acquire_timeout_s:
            self.c.abort(Reason.ACQUIRE_TIMEOUT)
        elif inp.vehicle.landed_state == LandedState.ON_GROUND and self.c.t_in_state() > 1.0:
            self.c.go(MissionState.LANDED, Reason.TOUCHDOWN, "landed while acquiring")

    def disarmed(self, veh: VehicleState) -> None:
        # The start stays latched: PREFLIGHT arms on it in the same tick once its checks pass, so one
        # start after a landing flies again.
        if self.c.start.requested and not self.c.shutting_down and self.c.link_ok(veh):
            self.c.go(MissionState.PREFLIGHT, Reason.START_REQUESTED)

    def link_lost(self, veh: VehicleState) -> None:
        if not self.c.link_ok(veh):
            return
        if not veh.armed:
            self.c.go(MissionState.DISARMED, Reason.LINK_RESTORED, "disarmed")
        elif not veh.in_air:
            self.c.go(MissionState.LANDED, Reason.LINK_RESTORED, "on the ground")
        else:
            self.c.go(MissionState.PX4_IN_CONTROL, Reason.LINK_RESTORED, veh.flight_mode.value)
