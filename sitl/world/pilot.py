"""Scripted pilots: fly a vehicle through its own autopilot, as an onboard computer would.

A pilot talks to the autopilot only in MAVLink messages (COMMAND_LONG, SET_POSITION_TARGET_LOCAL_NED)
from component 191 (MAV_COMP_ID_ONBOARD_COMPUTER) and reads only what HEARTBEAT, SYS_STATUS and
LOCAL_POSITION_NED carry (its :class:`PilotPort`'s ``status``). So the leader in a scenario is flown by
PX4-like control with PX4's limits, exactly as a real leader would be.
"""

from __future__ import annotations

import logging
import math
from enum import Enum
from typing import Any, Protocol

from pymavlink.dialects.v20 import common as mavlink

from sitl.autopilot.autopilot import Autopilot
from sitl.autopilot.modes import MAIN_OFFBOARD, NavState
from sitl.autopilot.offboard import MASK_YAW_RATE
from sitl.autopilot.state import AutopilotStatus, Home
from sitl.world.scenario import LeaderSpec
from sitl.world.trajectory import Trajectory

log = logging.getLogger(__name__)

COMP_ONBOARD = 191
SETPOINT_PERIOD_S = 0.05  # 20 Hz, like MAVSDK's offboard plugin
#: Cap on the path's acceleration sent as feed-forward (m/s^2, PX4's MPC_ACC_HOR): a waypoint corner is a
#: velocity step whose finite difference would otherwise ask for tens of m/s^2.
ACCEL_FF_MAX_M_S2 = 3.0
# type_mask: position, velocity, acceleration (force bit clear) and yaw; only the yaw rate ignored.
_MASK_POS_VEL_ACC_YAW = MASK_YAW_RATE


class PilotPhase(Enum):
    """Where a scripted pilot is in its flight."""

    WAIT_READY = "wait_ready"
    ARMING = "arming"
    CLIMBING = "climbing"
    HOVER = "hover"
    FOLLOW_PATH = "follow_path"
    DONE = "done"


class PilotPort(Protocol):
    """What a pilot needs of a vehicle's autopilot: what an onboard MAVLink client reads and sends."""

    @property
    def name(self) -> str: ...
    @property
    def sysid(self) -> int: ...
    @property
    def home(self) -> Home | None: ...
    def time_boot_ms(self) -> int: ...
    def status(self) -> AutopilotStatus: ...
    def handle_message(self, msg: Any, link: int | None, src_system: int, src_component: int) -> None:
        """Deliver one message from the vehicle's onboard computer (no link: no reply comes back)."""


class AutopilotPort:
    """The simulator's own autopilot as a :class:`PilotPort`: its state read, its endpoint written."""

    def __init__(self, autopilot: Autopilot) -> None:
        self._autopilot = autopilot
        self._endpoint = autopilot.mavlink
        self.name = autopilot.name
        self.sysid = autopilot.sysid

    @property
    def home(self) -> Home | None:
        return self._autopilot.home

    def time_boot_ms(self) -> int:
        return self._autopilot.time_boot_ms()

    def status(self) -> AutopilotStatus:
        return self._autopilot.status()

    def handle_message(self, msg: Any, link: int | None, src_system: int, src_component: int) -> None:
        """Deliver one message from the vehicle's onboard computer (no link: no reply comes back)."""
        self._endpoint.handle_message(msg, link, src_system, src_component)


class TrajectoryPilot:
    """Flies a scenario's leader path through the vehicle's autopilot.

    Arms, takes off to ``spec.altitude_m``, holds until ``spec.start_s``, then flies the path in
    offboard position+velocity+acceleration control, as PX4's own trajectory follower (FlightTaskAuto)
    feeds its position controller; holds again after ``spec.end_s``. Without the path's acceleration the
    velocity loop's integrator wound up on each speed ramp and the leader overshot its 2 m/s to 2.5 m/s.
    """

    def __init__(self, autopilot: PilotPort, spec: LeaderSpec, trajectory: Trajectory) -> None:
        self.ap = autopilot
        self.spec = spec
        self.trajectory = trajectory
        self.phase = PilotPhase.WAIT_READY
        self._next_cmd_s = 0.0
        self._next_sp_s = 0.0
        self._next_tick_s = 0.0
        self._stream_since_s: float | None = None
        self._anchor: tuple[float, float, float] | None = None

    def _command(self, command: int, *params: float) -> None:
        p = list(params) + [math.nan] * (7 - len(params))
        msg = mavlink.MAVLink_command_long_message(self.ap.sysid, 1, command, 0, *p)
        self.ap.handle_message(msg, None, self.ap.sysid, COMP_ONBOARD)

    def update(self, t_s: float) -> None:
        """Advance the pilot at sim time ``t_s`` (call at the outer-loop rate; it acts at 20 Hz)."""
        if t_s < self._next_tick_s:
            return
        self._next_tick_s = t_s + SETPOINT_PERIOD_S - 1e-9
        st = self.ap.status()
        spec = self.spec
        if self.phase is PilotPhase.WAIT_READY:
            if st.global_position_ok and st.home_set:
                self.phase = PilotPhase.ARMING
        elif self.phase is PilotPhase.ARMING:
            if (st.armed and not st.landed) or (st.armed and st.nav_state is NavState.AUTO_TAKEOFF):
                self.phase = PilotPhase.CLIMBING
            elif t_s >= self._next_cmd_s:
                self._next_cmd_s = t_s + 1.0
                if not st.armed:
                    self._command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
                home = self.ap.home
                if home is not None:
                    self._command(
                        mavlink.MAV_CMD_NAV_TAKEOFF, *([math.nan] * 6), home.alt_m + spec.altitude_m
                    )
        elif self.phase is PilotPhase.CLIMBING:
            if st.nav_state is NavState.AUTO_LOITER and -st.p_ned_m[2] > spec.altitude_m - 0.5:
                self.phase = PilotPhase.HOVER
                home_d = self.ap.home.d_m if self.ap.home is not None else 0.0
                # Anchor at the commanded altitude, not wherever the takeoff overshoot happens to be.
                self._anchor = (st.p_ned_m[0], st.p_ned_m[1], home_d - spec.altitude_m)
        elif self.phase is PilotPhase.HOVER:
            if t_s >= spec.start_s - 1.0:
                self.phase = PilotPhase.FOLLOW_PATH
        elif self.phase is PilotPhase.FOLLOW_PATH:
            if spec.end_s is not None and t_s >= spec.end_s:
                self._command(mavlink.MAV_CMD_DO_SET_MODE, 1.0, 4.0, 3.0)
                self.phase = PilotPhase.DONE
                return
            self._stream(t_s, st.nav_state)
        if not st.armed and self.phase in (PilotPhase.HOVER, PilotPhase.FOLLOW_PATH, PilotPhase.CLIMBING):
            log.warning("%s pilot: vehicle disarmed during %s; stopping", self.ap.name, self.phase.value)
            self.phase = PilotPhase.DONE

    def _accel_ff(self, tau_s: float) -> tuple[float, float]:
        """The path's horizontal acceleration at ``tau_s``, NED m/s^2.

        A central difference over one setpoint period, so every path shape gets it without an analytic
        second derivative.
        """
        h = 0.5 * SETPOINT_PERIOD_S
        _, _, vn0, ve0, _ = self.trajectory.sample(tau_s - h)
        _, _, vn1, ve1, _ = self.trajectory.sample(tau_s + h)
        a_n, a_e = (vn1 - vn0) / (2 * h), (ve1 - ve0) / (2 * h)
        k = min(1.0, ACCEL_FF_MAX_M_S2 / max(math.hypot(a_n, a_e), 1e-9))
        return a_n * k, a_e * k

    def _stream(self, t_s: float, nav: NavState) -> None:
        if t_s < self._next_sp_s:
            return
        self._next_sp_s = t_s + SETPOINT_PERIOD_S - 1e-9
        if self._anchor is None:
            return
        tau_s = t_s - self.spec.start_s
        n, e, vn, ve, heading = self.trajectory.sample(tau_s)
        an_ff, ae_ff = self._accel_ff(tau_s)
        an, ae, ad = self._anchor
        yaw = heading if self.spec.yaw == "path" else math.radians(self.spec.heading_deg)
        msg = mavlink.MAVLink_set_position_target_local_ned_message(
            self.ap.time_boot_ms(), self.ap.sysid, 1, mavlink.MAV_FRAME_LOCAL_NED, _MASK_POS_VEL_ACC_YAW,
            an + n, ae + e, ad, vn, ve, 0.0, an_ff, ae_ff, 0.0, yaw, 0.0,
        )  # fmt: skip
        self.ap.handle_message(msg, None, self.ap.sysid, COMP_ONBOARD)
        if self._stream_since_s is None:
            self._stream_since_s = t_s
        # PX4 wants the stream running before the switch; ask once a second until it is accepted.
        if nav is not NavState.OFFBOARD and t_s - self._stream_since_s >= 0.5 and t_s >= self._next_cmd_s:
            self._next_cmd_s = t_s + 1.0
            self._command(mavlink.MAV_CMD_DO_SET_MODE, 129.0, float(MAIN_OFFBOARD), 0.0)
