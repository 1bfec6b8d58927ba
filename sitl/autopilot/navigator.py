"""Setpoints of PX4's automatic modes (Takeoff, Hold, Land, Return, Descend), pure.

PX4 feeds its position controller from flight tasks with jerk-limited trajectories
(``flight_mode_manager``); here a simpler smoother moves the position setpoint towards the mode's
target with the same speed and acceleration limits (MPC_XY_CRUISE, MPC_ACC_HOR, MPC_Z_V_AUTO_UP/DN,
MPC_TKO_SPEED, MPC_LAND_SPEED...), and hands the position controller position + velocity feed-forward.

Heights: ``d`` is local NED down (negative up); altitudes relative to home are ``-d``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum

from sitl.autopilot.attitude import wrap_pi
from sitl.autopilot.control import NAN, TrajectorySetpoint
from sitl.autopilot.modes import NavState

#: PX4 SITL (SIH quadrotor, MPC_TKO_SPEED 1.5 m/s, take-off to 5 m) left the ground 3.0-3.5 s after the
#: take-off command (spool-up, then MPC_TKO_RAMP_T's ramp) and climbed at 1.0-1.1 m/s at most: the ramp and
#: PX4's jerk-limited altitude approach keep it below MPC_TKO_SPEED all the way.
TAKEOFF_SPOOLUP_S = 3.0
TAKEOFF_CLIMB_FRAC = 0.72


@dataclass(frozen=True, slots=True)
class NavLimits:
    """The MPC_*/NAV_*/RTL_* values the automatic modes use (m, m/s, m/s^2, rad/s)."""

    cruise_m_s: float = 5.0
    acc_hor_m_s2: float = 3.0
    up_m_s: float = 3.0
    down_m_s: float = 1.5
    acc_up_m_s2: float = 4.0
    acc_down_m_s2: float = 3.0
    takeoff_speed_m_s: float = 1.5
    land_speed_m_s: float = 0.7
    land_alt1_m: float = 10.0
    land_alt2_m: float = 5.0
    alt_acceptance_m: float = 0.8
    rtl_return_alt_m: float = 60.0
    rtl_descend_alt_m: float = 30.0
    rtl_land_delay_s: float = 0.0
    yaw_rate_max_rad_s: float = math.radians(45.0)


class RtlPhase(Enum):
    """Return mode phases (PX4 ``RtlDirect``)."""

    CLIMB = "climb"
    RETURN = "return"
    DESCEND = "descend"
    LOITER = "loiter"
    LAND = "land"


class Navigator:
    """Generates the trajectory setpoint of the current automatic mode.

    Call :meth:`enter` on every mode change (it captures the entry position and heading) and
    :meth:`update` at the outer-loop rate. ``takeoff_done`` turns true once a takeoff reached its
    altitude (the commander then switches to Hold, COM_TAKEOFF_ACT=0).
    """

    def __init__(self) -> None:
        self.limits = NavLimits()
        self.sp = TrajectorySetpoint()
        self.mode: NavState | None = None
        self._sp_n = self._sp_e = self._sp_d = 0.0
        self._sp_vn = self._sp_ve = self._sp_vd = 0.0
        self._target: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self._yaw_sp = 0.0
        self._yaw_target = 0.0
        self.takeoff_done = False
        self.rtl_phase = RtlPhase.CLIMB
        self._phase_since_s = 0.0
        self._cruise_override_m_s: float | None = None
        self.is_landing = False

    @property
    def target(self) -> tuple[float, float, float]:
        """Where the current automatic mode is heading (local NED, m)."""
        return self._target

    def set_cruise_speed(self, speed_m_s: float | None) -> None:
        """MAV_CMD_DO_CHANGE_SPEED (None or <= 0 restores MPC_XY_CRUISE)."""
        self._cruise_override_m_s = speed_m_s if speed_m_s and speed_m_s > 0 else None

    def enter(
        self,
        mode: NavState,
        t_s: float,
        pos: tuple[float, float, float],
        vel: tuple[float, float, float],
        yaw_rad: float,
        *,
        takeoff_d_m: float = NAN,
        hold_target: tuple[float, float, float] | None = None,
    ) -> None:
        self.mode = mode
        self._sp_n, self._sp_e, self._sp_d = pos
        self._sp_vn, self._sp_ve, self._sp_vd = vel
        self._yaw_sp = self._yaw_target = yaw_rad
        self.takeoff_done = False
        self.is_landing = False
        self._phase_since_s = t_s
        if mode is NavState.AUTO_TAKEOFF:
            self._target = (pos[0], pos[1], takeoff_d_m if math.isfinite(takeoff_d_m) else pos[2])
        elif mode is NavState.AUTO_LOITER:
            if hold_target is not None:
                self._target = hold_target
            else:
                # Brake to a stop first: hold where a constant deceleration would stop us.
                a = self.limits.acc_hor_m_s2
                self._target = (
                    pos[0] + vel[0] * abs(vel[0]) / (2 * a),
                    pos[1] + vel[1] * abs(vel[1]) / (2 * a),
                    pos[2],
                )
        elif mode is NavState.AUTO_RTL:
            self.rtl_phase = RtlPhase.CLIMB
            self._target = pos
        else:
            self._target = pos

    def set_hold_target(self, target: tuple[float, float, float], yaw_rad: float = NAN) -> None:
        """Move the Hold target (MAV_CMD_DO_REPOSITION)."""
        self._target = target
        if math.isfinite(yaw_rad):
            self._yaw_target = yaw_rad

    def _slew(self, dt_s: float, cruise_m_s: float, up_m_s: float, down_m_s: float) -> None:
        """Move the setpoint towards ``_target``: braking-curve speed, acceleration-limited."""
        lim = self.limits
        tn, te, td = self._target
        # Horizontal.
        dn, de = tn - self._sp_n, te - self._sp_e
        dist = math.hypot(dn, de)
        a = lim.acc_hor_m_s2
        if dist > 1e-4:
            speed = min(cruise_m_s, math.sqrt(2.0 * a * dist))
            vdn, vde = dn / dist * speed, de / dist * speed
        else:
            vdn = vde = 0.0
        ddv_n, ddv_e = vdn - self._sp_vn, vde - self._sp_ve
        ddv = math.hypot(ddv_n, ddv_e)
        step = a * dt_s
        if ddv > step:
            ddv_n, ddv_e = ddv_n / ddv * step, ddv_e / ddv * step
        self._sp_vn += ddv_n
        self._sp_ve += ddv_e
        if dist <= 1e-4 and math.hypot(self._sp_vn, self._sp_ve) < step:
            self._sp_n, self._sp_e, self._sp_vn, self._sp_ve = tn, te, 0.0, 0.0
        else:
            self._sp_n += self._sp_vn * dt_s
            self._sp_e += self._sp_ve * dt_s
        # Vertical (down positive).
        dd = td - self._sp_d
        if dd > 0:
            vdd = min(down_m_s, math.sqrt(2.0 * lim.acc_down_m_s2 * dd))
            av = lim.acc_down_m_s2
        elif dd < 0:
            vdd = -min(up_m_s, math.sqrt(2.0 * lim.acc_up_m_s2 * -dd))
            av = lim.acc_up_m_s2
        else:
            vdd, av = 0.0, lim.acc_up_m_s2
        dv = vdd - self._sp_vd
        step = av * dt_s
        dv = max(-step, min(step, dv))
        self._sp_vd += dv
        if abs(dd) < 1e-3 and abs(self._sp_vd) < step:
            self._sp_d, self._sp_vd = td, 0.0
        else:
            self._sp_d += self._sp_vd * dt_s

    def _yaw(self, dt_s: float) -> None:
        err = wrap_pi(self._yaw_target - self._yaw_sp)
        step = self.limits.yaw_rate_max_rad_s * dt_s
        self._yaw_sp = wrap_pi(self._yaw_sp + max(-step, min(step, err)))

    def _land_speed(self, alt_rel_home_m: float) -> float:
        lim = self.limits
        if alt_rel_home_m >= lim.land_alt1_m:
            return lim.down_m_s
        if alt_rel_home_m <= lim.land_alt2_m or lim.land_alt1_m <= lim.land_alt2_m:
            return lim.land_speed_m_s
        f = (alt_rel_home_m - lim.land_alt2_m) / (lim.land_alt1_m - lim.land_alt2_m)
        return lim.land_speed_m_s + f * (lim.down_m_s - lim.land_speed_m_s)

    def update(
        self,
        t_s: float,
        dt_s: float,
        pos: tuple[float, float, float],
        home: tuple[float, float, float],
    ) -> TrajectorySetpoint:
        """The setpoint for the current automatic mode. ``home`` is in the same local NED frame."""
        lim = self.limits
        cruise = self._cruise_override_m_s or lim.cruise_m_s
        mode = self.mode
        sp = self.sp
        self.is_landing = False
        if mode is NavState.AUTO_TAKEOFF:
            if t_s - self._phase_since_s < TAKEOFF_SPOOLUP_S:
                # Motors spooling up and PX4's take-off ramp: the setpoint stays on the ground.
                self._sp_vd = 0.0
            else:
                self._slew(dt_s, cruise, lim.takeoff_speed_m_s * TAKEOFF_CLIMB_FRAC, lim.down_m_s)
            if (
                abs(self._sp_d - self._target[2]) < 1e-3
                and abs(pos[2] - self._target[2]) < lim.alt_acceptance_m
            ):
                self.takeoff_done = True
        elif mode is NavState.AUTO_LOITER:
            self._slew(dt_s, cruise, lim.up_m_s, lim.down_m_s)
        elif mode is NavState.AUTO_LAND:
            self.is_landing = True
            self._target = (self._target[0], self._target[1], self._sp_d)
            self._slew(dt_s, cruise, lim.up_m_s, lim.down_m_s)
            self._yaw(dt_s)
            vz = self._land_speed(home[2] - pos[2])
            return sp.set(
                pos=(self._sp_n, self._sp_e, NAN),
                vel=(self._sp_vn, self._sp_ve, vz),
                yaw=self._yaw_sp,
            )
        elif mode is NavState.AUTO_RTL:
            return self._rtl(t_s, dt_s, pos, home, cruise)
        elif mode is NavState.DESCEND:
            # FlightTaskDescend: level attitude (no horizontal control) and a fixed sink rate.
            self.is_landing = True
            return sp.set(acc=(0.0, 0.0, NAN), vel=(NAN, NAN, lim.land_speed_m_s), yaw=self._yaw_sp)
        else:
            return sp.set()
        self._yaw(dt_s)
        return sp.set(
            pos=(self._sp_n, self._sp_e, self._sp_d),
            vel=(self._sp_vn, self._sp_ve, self._sp_vd),
            yaw=self._yaw_sp,
        )

    def _rtl(
        self,
        t_s: float,
        dt_s: float,
        pos: tuple[float, float, float],
        home: tuple[float, float, float],
        cruise: float,
    ) -> TrajectorySetpoint:
        lim = self.limits
        alt_rel = home[2] - pos[2]
        dist_xy = math.hypot(home[0] - pos[0], home[1] - pos[1])
        if self.rtl_phase is RtlPhase.CLIMB:
            # Return altitude: at least RTL_DESCEND_ALT, at most RTL_RETURN_ALT, never below us.
            ret_alt = max(alt_rel, min(lim.rtl_return_alt_m, max(lim.rtl_descend_alt_m, dist_xy)))
            self._target = (self._target[0], self._target[1], home[2] - ret_alt)
            if abs(pos[2] - self._target[2]) < lim.alt_acceptance_m:
                self.rtl_phase = RtlPhase.RETURN
                self._target = (home[0], home[1], self._target[2])
                if dist_xy > 1.0:
                    self._yaw_target = math.atan2(home[1] - pos[1], home[0] - pos[0])
        elif self.rtl_phase is RtlPhase.RETURN:
            if dist_xy < 1.0 and math.hypot(self._sp_vn, self._sp_ve) < 0.2:
                self.rtl_phase = RtlPhase.DESCEND
                self._target = (home[0], home[1], home[2] - min(alt_rel, lim.rtl_descend_alt_m))
        elif self.rtl_phase is RtlPhase.DESCEND:
            if abs(pos[2] - self._target[2]) < lim.alt_acceptance_m:
                self.rtl_phase = RtlPhase.LOITER
                self._phase_since_s = t_s
        elif self.rtl_phase is RtlPhase.LOITER:
            delay = lim.rtl_land_delay_s
            if delay >= 0 and t_s - self._phase_since_s >= delay:
                self.rtl_phase = RtlPhase.LAND
        if self.rtl_phase is RtlPhase.LAND:
            self.is_landing = True
            self._target = (home[0], home[1], self._sp_d)
            self._slew(dt_s, cruise, lim.up_m_s, lim.down_m_s)
            self._yaw(dt_s)
            return self.sp.set(
                pos=(self._sp_n, self._sp_e, NAN),
                vel=(self._sp_vn, self._sp_ve, self._land_speed(alt_rel)),
                yaw=self._yaw_sp,
            )
        self._slew(dt_s, cruise, lim.up_m_s, lim.down_m_s)
        self._yaw(dt_s)
        return self.sp.set(
            pos=(self._sp_n, self._sp_e, self._sp_d),
            vel=(self._sp_vn, self._sp_ve, self._sp_vd),
            yaw=self._yaw_sp,
        )
