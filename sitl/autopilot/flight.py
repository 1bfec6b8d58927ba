"""The autopilot's flight logic: commander, land detector and control.

The commander keeps home, the estimate flags, the mode with its failsafes, and arming; the land detector
says when the vehicle is on the ground; control turns the offboard or navigator setpoint into the
position and attitude controllers' inputs.

:class:`FlightLogic` is one part of :class:`sitl.autopilot.autopilot.Autopilot`: it acts on the vehicle's
:class:`~sitl.autopilot.state.AutopilotState` and keeps only what no other part reads (the land
detector's timer, the held yaw, the last trajectory setpoint). The commander's pure decisions are
:mod:`sitl.autopilot.commander`'s, the auto modes' trajectories :mod:`sitl.autopilot.navigator`'s.
"""

from __future__ import annotations

import math

from sitl.autopilot import telemetry
from sitl.autopilot.attitude import attitude_from_thrust, wrap_pi
from sitl.autopilot.commander import Action, Flags, action_nav_state, resolve_failsafe
from sitl.autopilot.control import NAN, TrajectorySetpoint
from sitl.autopilot.modes import NavState
from sitl.autopilot.navigator import RtlPhase
from sitl.autopilot.offboard import OffboardSetpoint, SetpointKind
from sitl.autopilot.state import (
    ACCEPTED,
    MOTORS_IDLE,
    MOTORS_OFF,
    SEV_CRITICAL,
    SEV_INFO,
    TEMPORARILY_REJECTED,
    AutopilotState,
    Home,
)


class FlightLogic:
    """Commander, land detector and control of one vehicle's autopilot, acting on its state ``s``."""

    def __init__(self, s: AutopilotState) -> None:
        self.s = s
        self._flags_key: tuple[bool, ...] = ()
        self._ground_contact_since_s: float | None = None
        self._takeoff_ref_d_m = 0.0
        self._yaw_hold_rad = s.dyn.yaw_rad
        self._traj: TrajectorySetpoint | None = None

    def step(self, dt_s: float) -> None:
        """The commander, land detector and control for one 50 Hz update (the estimate is current)."""
        self._update_home()
        self.update_flags()
        self._update_land_detector()
        self._update_mode()
        self._control(dt_s)

    # ------------------------------------------------------------------ commander
    def _update_home(self) -> None:
        if self.s.home is None and not self.s.armed and self.s.flags.global_position_valid:
            self.set_home_here()

    def set_home_here(self) -> None:
        n, e, d = self.s.position_ned()
        lat, lon, alt = self.s.origin.to_geodetic(n, e, d)
        self.s.home = Home(lat, lon, alt, n, e, d)
        self.s.broadcast(telemetry.home_position(self.s))

    def update_flags(self) -> None:
        p = self.s.params
        lp, lr, lv, gp = self.s.validity.update(
            self.s.t_s,
            ekf_xy_valid=self.s.est.xy_valid,
            ekf_global_valid=self.s.est.global_valid,
            eph_m=self.s.est.eph_m,
            evh_m_s=self.s.est.evh_m_s,
            com_pos_fs_eph_m=p["COM_POS_FS_EPH"],
            com_vel_fs_evh_m_s=p["COM_VEL_FS_EVH"],
        )
        key = (lp, lr, lv, gp, self.s.home is not None, self._offboard_available(lp, lv))
        if key != self._flags_key:  # Flags is immutable; rebuild only when something changed
            self._flags_key = key
            self.s.flags = Flags(
                attitude_valid=True,
                local_position_valid=lp,
                local_position_relaxed_valid=lr,
                local_velocity_valid=lv,
                global_position_valid=gp,
                local_altitude_valid=True,
                home_valid=key[4],
                offboard_signal=key[5],
            )

    def _offboard_available(self, local_pos_valid: bool, local_vel_valid: bool) -> bool:
        sp = self.s.offboard_sp
        if sp is None:
            return False
        if self.s.t_s - sp.t_s >= self.s.pv["COM_OF_LOSS_T"] * self.s.speed_factor:
            return False
        if sp.position and not local_pos_valid:
            return False
        return not (sp.velocity and not local_vel_valid)

    def _update_mode(self) -> None:
        if not self.s.armed:
            self.s.failsafe_action = Action.NONE
            nav = self.s.user_mode
        else:
            if (
                self.s.nav_state is NavState.AUTO_TAKEOFF
                and self.s.user_mode is NavState.AUTO_TAKEOFF
                and self.s.navigator.takeoff_done
            ):
                # COM_TAKEOFF_ACT = 0: hold at the takeoff point once the altitude is reached.
                self.s.hold_target = self.s.navigator.target
                self.s.user_mode = NavState.AUTO_LOITER
            p = self.s.params
            action = resolve_failsafe(
                self.s.user_mode, self.s.flags, int(p["COM_OBL_RC_ACT"]), int(p["NAV_RCL_ACT"])
            )
            if action is Action.DISARM:
                self.disarm("Failsafe: disarming")
                return
            if action is not self.s.failsafe_action:
                if action is not Action.NONE:
                    target = action_nav_state(action)
                    name = target.ui_name if target is not None else action.name.title()
                    self.s.statustext(SEV_CRITICAL, f"Failsafe activated: switching to {name}")
                elif self.s.failsafe_action is not Action.NONE:
                    self.s.statustext(SEV_INFO, "Failsafe cleared")
            self.s.failsafe_action = action
            nav = action_nav_state(action) or self.s.user_mode
        if nav is not self.s.nav_state:
            self._enter(nav)

    def _enter(self, nav: NavState) -> None:
        self.s.nav_state = nav
        pos, vel = self.s.position_ned(), self.s.velocity_ned()
        yaw = self.s.yaw_est_rad()
        self._yaw_hold_rad = yaw
        hold_target, self.s.hold_target = self.s.hold_target, None
        if nav.is_auto:
            self.s.navigator.enter(
                nav, self.s.t_s, pos, vel, yaw, takeoff_d_m=self.s.takeoff_target_d_m, hold_target=hold_target
            )

    def set_user_mode(self, nav: NavState) -> None:
        self.s.user_mode = nav
        if nav is NavState.AUTO_TAKEOFF and not math.isfinite(self.s.takeoff_target_d_m):
            self.s.takeoff_target_d_m = self.takeoff_d_from_alt(NAN)
        # Re-enter even if the nav state stays (e.g. a second takeoff command) so targets refresh.
        self._update_mode()
        if self.s.nav_state is nav:
            self._enter(nav)

    def takeoff_d_from_alt(self, alt_amsl_m: float) -> float:
        home_d = self.s.home.d_m if self.s.home is not None else 0.0
        if math.isfinite(alt_amsl_m):
            target_d = self.s.origin.alt0_m - alt_amsl_m
        else:
            target_d = home_d - self.s.pv["MIS_TAKEOFF_ALT"]
        # Never take off downwards: PX4 holds when already above the takeoff altitude.
        return min(target_d, self.s.est.d_m)

    def arm(self, forced: bool) -> tuple[int, str | None]:
        if self.s.armed:
            return ACCEPTED, None
        del forced  # PX4 runs the checks on external arm requests even when forced
        if not self.s.armable():
            return TEMPORARILY_REJECTED, "Arming denied: Resolve system health failures first"
        self.s.armed = True
        self.s.landed = True
        self._takeoff_ref_d_m = self.s.est.d_m
        self.s.disarm_timer.reset()
        self.s.pos_ctrl.reset()
        self.s.inner.reset_integrators()
        if self.s.flags.global_position_valid:
            self.set_home_here()  # PX4 updates home on arming
        self._enter(self.s.nav_state)
        self.s.statustext(SEV_INFO, "Armed by external command")
        return ACCEPTED, None

    def disarm(self, text: str | None) -> None:
        was_failsafe = self.s.failsafe_action is not Action.NONE
        self.s.armed = False
        self.s.motors = MOTORS_OFF
        self.s.thrust_sp = 0.0
        self.s.landed = True
        self.s.takeoff_target_d_m = NAN
        if was_failsafe:
            self.s.user_mode = (
                NavState.AUTO_LAND if self.s.nav_state is NavState.DESCEND else self.s.nav_state
            )
        self.s.failsafe_action = Action.NONE
        if self.s.nav_state is not self.s.user_mode:
            self._enter(self.s.user_mode)
        self.s.disarm_timer.reset()
        if text:
            self.s.statustext(SEV_INFO, text)

    # ------------------------------------------------------------------ land detector
    def _descent_commanded(self) -> bool:
        nav = self.s.nav_state
        if nav in (NavState.AUTO_LAND, NavState.DESCEND):
            return True
        if nav is NavState.AUTO_RTL and self.s.navigator.rtl_phase is RtlPhase.LAND:
            return True
        sp = self._traj
        if sp is not None:
            if not math.isnan(sp.vz) and sp.vz > 0.05:
                return True
            return bool(not math.isnan(sp.z) and sp.z > self.s.est.d_m + 0.3)
        # Attitude/rate offboard: low thrust is the only hint, as for PX4's land detector.
        return self.s.thrust_sp < 0.6 * self.s.pv["MPC_THR_HOVER"]

    def _update_land_detector(self) -> None:
        if not self.s.armed:
            self.s.landed = True
            self._ground_contact_since_s = None
            return
        e = self.s.est
        if self.s.landed:
            if self.s.motors is None and (self._takeoff_ref_d_m - e.d_m > 0.3 or e.vd_m_s < -0.5):
                self.s.landed = False
                self._ground_contact_since_s = None
            return
        slow = abs(e.vd_m_s) < 0.25 and math.hypot(e.vn_m_s, e.ve_m_s) < 1.5
        low_thrust = self.s.thrust_sp < 0.9 * self.s.pv["MPC_THR_HOVER"]
        if slow and low_thrust and self._descent_commanded():
            if self._ground_contact_since_s is None:
                self._ground_contact_since_s = self.s.t_s
            elif self.s.t_s - self._ground_contact_since_s >= 1.0:  # LNDMC_TRIG_TIME
                self.s.landed = True
                self._takeoff_ref_d_m = e.d_m
        else:
            self._ground_contact_since_s = None

    # ------------------------------------------------------------------ control
    def _control(self, dt_s: float) -> None:
        if not self.s.armed or self.s.nav_state is NavState.TERMINATION:
            self.s.motors = MOTORS_OFF
            self.s.thrust_sp = 0.0
            self._traj = None
            return
        nav = self.s.nav_state
        self.s.rates_sp = None
        self.s.yawspeed_ff_rad_s = NAN
        traj: TrajectorySetpoint | None = None
        if nav is NavState.OFFBOARD and self.s.offboard_sp is not None:
            sp = self.s.offboard_sp
            if sp.kind is SetpointKind.TRAJECTORY:
                traj = sp.trajectory
                if not sp.valid:
                    # PX4: invalid position-control input -> hold level and stop vertically.
                    traj = TrajectorySetpoint().set(acc=(0.0, 0.0, NAN), vel=(NAN, NAN, 0.0))
            else:
                self._traj = None
                self._attitude_setpoint(sp, dt_s)
                return
        elif nav.is_auto:
            home = self.s.home
            home_ned = (home.n_m, home.e_m, home.d_m) if home is not None else (0.0, 0.0, 0.0)
            traj = self.s.navigator.update(self.s.t_s, dt_s, self.s.position_ned(), home_ned)
        else:
            traj = TrajectorySetpoint().set(acc=(0.0, 0.0, NAN), vel=(NAN, NAN, self.s.pv["MPC_LAND_SPEED"]))
        self._traj = traj
        if self.s.landed and not self._climb_demanded(traj):
            self._idle_on_ground()
            return
        if self.s.motors is not None:
            # Leaving the ground: start the position controller from a clean state.
            self.s.pos_ctrl.reset()
            self.s.inner.reset_integrators()
            self.s.motors = None
        thr = self.s.pos_ctrl.update(traj, self.s.position_ned(), self.s.velocity_ned(), dt_s)
        if not math.isnan(traj.yaw):
            self._yaw_hold_rad = traj.yaw
        elif not math.isnan(traj.yawspeed):
            self._yaw_hold_rad = wrap_pi(self._yaw_hold_rad + traj.yawspeed * dt_s)
        if not math.isnan(traj.yawspeed):
            self.s.yawspeed_ff_rad_s = traj.yawspeed
        self.s.q_sp, self.s.thrust_sp = attitude_from_thrust(thr[0], thr[1], thr[2], self._yaw_hold_rad)
        self.s.integrate = not self.s.landed

    def _attitude_setpoint(self, sp: OffboardSetpoint, dt_s: float) -> None:
        del dt_s
        self.s.thrust_sp = sp.thrust
        if sp.kind is SetpointKind.ATTITUDE:
            self.s.q_sp = sp.q_sp
            self.s.yawspeed_ff_rad_s = sp.yawspeed_rad_s
        else:
            r = sp.rates_sp
            self.s.rates_sp = (
                r[0] if r[0] == r[0] else 0.0,
                r[1] if r[1] == r[1] else 0.0,
                r[2] if r[2] == r[2] else 0.0,
            )
        if self.s.landed and sp.thrust < 0.5 * self.s.pv["MPC_THR_HOVER"]:
            self._idle_on_ground()
            return
        self.s.motors = None
        self.s.integrate = not self.s.landed

    def _climb_demanded(self, traj: TrajectorySetpoint) -> bool:
        d = self.s.est.d_m
        if not math.isnan(traj.z) and traj.z < d - 0.3:
            return True
        if not math.isnan(traj.vz) and traj.vz < -0.3:
            return True
        return not math.isnan(traj.az) and traj.az < -1.0

    def _idle_on_ground(self) -> None:
        self.s.motors = MOTORS_IDLE
        self.s.thrust_sp = 0.0
        self.s.pos_ctrl.reset()
        self.s.inner.reset_integrators()
        self.s.integrate = False
        self._yaw_hold_rad = self.s.yaw_est_rad()
