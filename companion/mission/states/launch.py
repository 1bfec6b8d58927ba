"""From the link to the formation (WAIT_LINK to ACQUIRE), and DISARMED and LINK_LOST.

PREFLIGHT arms on an operator's start once GPS and home are good; a companion (re)started in flight
OBSERVEs until told to take over. ACQUIRE waits in the air for a confirmed track, then enters the
formation (:mod:`companion.mission.states.follow`). DISARMED waits for the next start; LINK_LOST waits for
the link and then says where the vehicle is.
"""

from __future__ import annotations

import math

from companion.kernel.flight import FlightMode, LandedState, VehicleState
from companion.mission.states.base import ARM_RETRY_S, MachineBase
from companion.mission.types import CommandKind, MissionInputs, MissionState, Reason

ARM_ATTEMPTS = 3
#: Takeoff counts as done at this fraction of the target altitude.
TAKEOFF_DONE_FRAC = 0.9


class LaunchStates(MachineBase):
    """The handlers from WAIT_LINK to ACQUIRE, and of DISARMED and LINK_LOST."""

    def _wait_link(self, veh: VehicleState) -> None:
        if self._link_ok(veh):
            self._go(MissionState.PREFLIGHT, Reason.LINK_UP)

    def _preflight_problems(self, veh: VehicleState) -> list[str]:
        problems = []
        if not self.gps.ok:
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
        if self.gps.ok:
            self._start_latched = False
            self._takeover_latched = False
            self._go(MissionState.ACQUIRE, Reason.ALREADY_FLYING)
        elif self.gps.loss_confirmed(veh, self._now_s):
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
        if not self.gps.ok:
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
        if not self.gps.ok:
            self._on_gps_lost(inp)
        elif self._tracked(inp, confirmed_only=True):
            self._enter_follow(inp, Reason.LEADER_ACQUIRED)
        elif self._t_in_state() > self.m.acquire_timeout_s:
            self._abort(Reason.ACQUIRE_TIMEOUT)
        elif inp.vehicle.landed_state == LandedState.ON_GROUND and self._t_in_state() > 1.0:
            self._go(MissionState.LANDED, Reason.TOUCHDOWN, "landed while acquiring")

    def _disarmed(self, veh: VehicleState) -> None:
        if self._start_latched and not self._shutting_down and self._link_ok(veh):
            self._start_latched = False
            self._go(MissionState.PREFLIGHT, Reason.START_REQUESTED)

    def _link_lost(self, veh: VehicleState) -> None:
        if not self._link_ok(veh):
            return
        if not veh.armed:
            self._go(MissionState.DISARMED, Reason.LINK_RESTORED, "disarmed")
        elif not veh.in_air:
            self._go(MissionState.LANDED, Reason.LINK_RESTORED, "on the ground")
        else:
            self._go(MissionState.PX4_IN_CONTROL, Reason.LINK_RESTORED, veh.flight_mode.value)
