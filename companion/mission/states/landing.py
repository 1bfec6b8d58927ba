"""The way down and out: CONTROLLED_LANDING, LANDED, and PX4's own modes (Hold, Land, RTL, a pilot's).

The controlled landing descends on velocity with GPS, on attitude and thrust without it (keeping the
leader in view while it is tracked); touchdown is PX4's land detector or no vertical motion for a while.
LANDED idles and disarms. In a PX4 mode the machine only watches: disarm, touchdown, a mode refused, or
no GPS in a mode that needs it.
"""

from __future__ import annotations

import math

import numpy as np

from companion.kernel.flight import AttitudeSetpoint, LandedState, VehicleState, VelocityNedSetpoint
from companion.mission.states.context import ARM_RETRY_S, MissionContext, Retries
from companion.mission.states.request import STAY, PhaseStep, go, go_px4, moving
from companion.mission.types import CommandKind, MissionInputs, MissionState, Reason

DISARM_RETRY_S = 2.0
#: Touchdown: PX4's land detector, or no vertical motion (|v| below this) while commanding a descent.
TOUCHDOWN_V_M_S = 0.15
TOUCHDOWN_CONFIRM_S = 1.0


class LandingPhase:
    """The handlers of CONTROLLED_LANDING, LANDED and the PX4 modes."""

    def __init__(self, ctx: MissionContext) -> None:
        self.c = ctx
        #: Since when the controlled landing has looked touched down (still and low), s; None: it does not.
        #: Each entry starts afresh: the first 2 s of the state never look still.
        self.touchdown_since_s: float | None = None
        #: LANDED's disarms and PX4_LAND's LAND again (cleared on every change of state).
        self.retries = Retries()

    def controlled_landing(self, inp: MissionInputs) -> PhaseStep:
        veh = inp.vehicle
        if self._touched_down(veh):
            return moving(go(MissionState.LANDED, Reason.TOUCHDOWN))
        v_land = self.c.m.landing_speed_m_s
        if self.c.gps.ok:
            return PhaseStep(VelocityNedSetpoint(v_ned_m_s=(0.0, 0.0, v_land), yaw_rad=veh.yaw_rad))
        est = inp.leader if self.c.tracked(inp) else None
        fol = self.c.follower(veh, velocity_valid=False)
        p_rel = None if est is None else np.array(est.p_ned_rel_m)
        v_rel = None if est is None else np.array(est.v_ned_rel_m_s)
        return PhaseStep(
            self.c.law.hover_attitude(
                fol, v_land, self.c.now_s, p_ned_rel_m=p_rel, v_ned_rel_m_s=v_rel
            ).setpoint
        )

    def _touched_down(self, veh: VehicleState) -> bool:
        """PX4's land detector, or no vertical motion for a while although we command a descent."""
        if veh.landed_state == LandedState.ON_GROUND and self.c.t_in_state() > 1.0:
            return True
        still = abs(veh.v_ned_m_s[2]) < TOUCHDOWN_V_M_S and self.c.t_in_state() > 2.0
        low = not math.isfinite(veh.alt_rel_m) or veh.alt_rel_m < 3.0
        if not (still and low):
            self.touchdown_since_s = None
            return False
        if self.touchdown_since_s is None:
            self.touchdown_since_s = self.c.now_s
        return self.c.now_s - self.touchdown_since_s >= TOUCHDOWN_CONFIRM_S

    def landed(self, veh: VehicleState) -> PhaseStep:
        """On the ground and armed: idle thrust (when streaming) and disarm."""
        if not veh.armed:
            return moving(go(MissionState.DISARMED, Reason.DISARMED))
        # PX4 refuses to disarm before its land detector agrees; give it a moment before insisting.
        on_ground = veh.landed_state == LandedState.ON_GROUND or self.c.t_in_state() > DISARM_RETRY_S
        if (
            on_ground
            and not self.c.in_flight(CommandKind.DISARM)
            and self.retries.due(self.c.now_s, DISARM_RETRY_S)
        ):
            self.retries.tried(self.c.now_s)
            self.c.send(CommandKind.DISARM)
        if self.c.offboard.streaming:
            # Motors to idle while PX4 disarms: a fresh zero-thrust setpoint, never the last descent one.
            return PhaseStep(AttitudeSetpoint(0.0, 0.0, veh.yaw_rad, 0.0))
        return STAY

    def px4(self, inp: MissionInputs) -> PhaseStep:
        veh = inp.vehicle
        st = self.c.state
        if not veh.armed and self.c.t_in_state() > 0.5:
            return moving(go(MissionState.DISARMED, Reason.DISARMED))
        if veh.landed_state == LandedState.ON_GROUND and self.c.t_in_state() > 1.0 and veh.armed:
            return moving(go(MissionState.LANDED, Reason.TOUCHDOWN))
        if st in (MissionState.PX4_HOLD, MissionState.PX4_RTL) and not self.c.gps.ok:
            # PX4 would fall to Descend in these modes; land under our own control instead.
            return moving(go(MissionState.CONTROLLED_LANDING, Reason.GPS_LOST, f"in {st.value}"))
        if st in (MissionState.PX4_HOLD, MissionState.PX4_IN_CONTROL) and self.c.start.takeover:
            # An operator's start: take the vehicle back and find the leader again (GPS is good here).
            self.c.start.spend()
            if veh.armed and veh.in_air and self.c.gps.ok and not self.c.shutting_down:
                return moving(go(MissionState.ACQUIRE, Reason.OPERATOR_START, f"from {st.value}"))
        kind = {MissionState.PX4_HOLD: CommandKind.HOLD, MissionState.PX4_RTL: CommandKind.RTL}.get(st)
        failed = self.c.failed(kind) if kind is not None else None
        if failed is not None:
            return moving(
                go_px4(MissionState.PX4_LAND, Reason.PX4_MODE_REFUSED, f"{st.value}: {failed.detail}")
            )
        if st == MissionState.PX4_LAND and self.c.failed(CommandKind.LAND) is not None and veh.in_air:
            if not self.c.in_flight(CommandKind.LAND) and self.retries.due(self.c.now_s, ARM_RETRY_S):
                self.retries.tried(self.c.now_s)
                self.c.send(CommandKind.LAND)
            return STAY
        if (
            st == MissionState.PX4_HOLD
            and self.c.shutting_down
            and self.c.m.shutdown_action == "hold_then_land"
            and self.c.t_in_state() >= self.c.m.shutdown_hold_s
        ):
            return moving(go_px4(MissionState.PX4_LAND, Reason.HOLD_TIMEOUT))
        return STAY
