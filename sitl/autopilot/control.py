"""PX4's multicopter control cascade in plain floats (pure: time steps are arguments, no I/O).

Position -> velocity -> thrust vector -> attitude -> body rates -> torques -> motor thrusts.

This module is the outer part, position and velocity to a thrust vector, after PX4's
``mc_pos_control/PositionControl``; :mod:`sitl.autopilot.attitude` turns the thrust vector into an attitude
and :mod:`sitl.autopilot.inner_loop` runs attitude, rates and the mixer (``mc_att_control`` with
MC_YAW_WEIGHT's reduced-attitude control, and ``mc_rate_control``). The rate loop works in physical units
(angular acceleration times inertia) instead of PX4's per-airframe normalised gains, so it needs no tuning
file. Frames: NED world, FRD body. These functions run in the simulator's loops, which is why they avoid
numpy: a 3-vector through numpy costs more than the arithmetic on it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

NAN = math.nan
_G = 9.80665


_finite = math.isfinite  # (a plain alias: no Python call frame in the hot paths)


@dataclass(frozen=True, slots=True)
class PositionLimits:
    """Gains and limits of the position/velocity loops (from MPC_* parameters)."""

    pos_p_xy: float = 0.95
    pos_p_z: float = 1.0
    vel_p_xy: float = 1.8
    vel_i_xy: float = 0.4
    vel_d_xy: float = 0.2
    vel_p_z: float = 4.0
    vel_i_z: float = 2.0
    vel_d_z: float = 0.0
    vel_max_xy_m_s: float = 12.0
    vel_max_up_m_s: float = 3.0
    vel_max_down_m_s: float = 1.5
    tilt_max_rad: float = math.radians(45.0)
    thr_min: float = 0.12
    thr_max: float = 1.0
    hover_thrust: float = 0.5


class TrajectorySetpoint:
    """PX4's ``trajectory_setpoint``: NED position, velocity, acceleration, yaw; NaN = not controlled.

    Per axis the position loop runs if the position is finite, the velocity (plus feed-forward) loop
    if position or velocity is, and the acceleration is a feed-forward (or the only input).
    """

    __slots__ = ("ax", "ay", "az", "vx", "vy", "vz", "x", "y", "yaw", "yawspeed", "z")

    def __init__(self) -> None:
        self.x = self.y = self.z = NAN
        self.vx = self.vy = self.vz = NAN
        self.ax = self.ay = self.az = NAN
        self.yaw = NAN
        self.yawspeed = NAN

    def set(
        self,
        pos: tuple[float, float, float] = (NAN, NAN, NAN),
        vel: tuple[float, float, float] = (NAN, NAN, NAN),
        acc: tuple[float, float, float] = (NAN, NAN, NAN),
        yaw: float = NAN,
        yawspeed: float = NAN,
    ) -> TrajectorySetpoint:
        self.x, self.y, self.z = pos
        self.vx, self.vy, self.vz = vel
        self.ax, self.ay, self.az = acc
        self.yaw = yaw
        self.yawspeed = yawspeed
        return self

    def is_valid(self) -> bool:
        """PX4 ``PositionControl::_inputValid``: every axis controlled, and x/y controlled alike."""
        ok = True
        for p, v, a in ((self.x, self.vx, self.ax), (self.y, self.vy, self.ay), (self.z, self.vz, self.az)):
            ok = ok and (_finite(p) or _finite(v) or _finite(a))
        ok = ok and (_finite(self.x) == _finite(self.y))
        ok = ok and (_finite(self.vx) == _finite(self.vy))
        return ok and (_finite(self.ax) == _finite(self.ay))


class PositionController:
    """PX4 ``PositionControl``: P on position, PID on velocity, acceleration -> thrust vector.

    ``update`` returns the normalised thrust vector in NED (negative down = up); ``reset`` clears the
    integrators (PX4 does so while landed).
    """

    def __init__(self, limits: PositionLimits) -> None:
        self.limits = limits
        self._int_n = self._int_e = self._int_d = 0.0
        self._vdot_n = self._vdot_e = self._vdot_d = 0.0
        self._v_prev: tuple[float, float, float] | None = None
        self.vel_sp_ned_m_s: tuple[float, float, float] = (0.0, 0.0, 0.0)
        # cos/sin of the tilt limit, for the limits object they were computed from.
        self._tilt_of: PositionLimits | None = None
        self._cos_tilt = self._sin_tilt = 0.0

    def reset(self, hover_integral_m_s2: float = 0.0) -> None:
        self._int_n = self._int_e = 0.0
        self._int_d = hover_integral_m_s2
        self._v_prev = None
        self._vdot_n = self._vdot_e = self._vdot_d = 0.0

    def update(
        self,
        sp: TrajectorySetpoint,
        pos_ned_m: tuple[float, float, float],
        vel_ned_m_s: tuple[float, float, float],
        dt_s: float,
    ) -> tuple[float, float, float]:
        lim = self.limits
        if lim is not self._tilt_of:
            self._tilt_of = lim
            self._cos_tilt = math.cos(lim.tilt_max_rad)
            self._sin_tilt = math.sin(lim.tilt_max_rad)
        pn, pe, pd = pos_ned_m
        vn, ve, vd = vel_ned_m_s
        # Velocity derivative for the D term (low-passed, as PX4 filters vel_dot).
        v_prev = self._v_prev
        if v_prev is not None and dt_s > 0:
            a = dt_s / 0.05
            a = a if a < 1.0 else 1.0
            self._vdot_n += a * ((vn - v_prev[0]) / dt_s - self._vdot_n)
            self._vdot_e += a * ((ve - v_prev[1]) / dt_s - self._vdot_e)
            self._vdot_d += a * ((vd - v_prev[2]) / dt_s - self._vdot_d)
        self._v_prev = (vn, ve, vd)

        # Position loop: velocity setpoint = feed-forward + P * position error, per finite axis.
        # (Each of vsn, vse, vsd is finite or NaN here, so isnan is the finiteness test.)
        vsn = sp.vx if _finite(sp.vx) else NAN
        vse = sp.vy if _finite(sp.vy) else NAN
        vsd = sp.vz if _finite(sp.vz) else NAN
        if _finite(sp.x):
            vsn = (0.0 if math.isnan(vsn) else vsn) + (sp.x - pn) * lim.pos_p_xy
            vse = (0.0 if math.isnan(vse) else vse) + (sp.y - pe) * lim.pos_p_xy
        if _finite(sp.z):
            vsd = (0.0 if math.isnan(vsd) else vsd) + (sp.z - pd) * lim.pos_p_z
        # Limit the velocity setpoint (horizontal norm, vertical up/down separately). Neither limit
        # changes whether a component is finite, so the flags below hold for the rest of the update.
        fin_xy = _finite(vsn)
        fin_z = _finite(vsd)
        if fin_xy:
            h = math.sqrt(vsn * vsn + vse * vse)
            if h > lim.vel_max_xy_m_s:
                vsn *= lim.vel_max_xy_m_s / h
                vse *= lim.vel_max_xy_m_s / h
        if fin_z:
            vsd = min(lim.vel_max_down_m_s, max(-lim.vel_max_up_m_s, vsd))
        self.vel_sp_ned_m_s = (vsn, vse, vsd)

        # Velocity loop -> acceleration setpoint; feed-forward acceleration added where finite.
        if fin_xy:
            en, ee = vsn - vn, vse - ve
            an = en * lim.vel_p_xy + self._int_n - self._vdot_n * lim.vel_d_xy
            ae = ee * lim.vel_p_xy + self._int_e - self._vdot_e * lim.vel_d_xy
        else:
            en = ee = 0.0
            an = ae = 0.0
        if fin_z:
            ed = vsd - vd
            ad = ed * lim.vel_p_z + self._int_d - self._vdot_d * lim.vel_d_z
        else:
            ed = 0.0
            ad = 0.0
        if _finite(sp.ax):
            an += sp.ax
            ae += sp.ay
        if _finite(sp.az):
            ad += sp.az

        # Acceleration -> thrust (PX4 _accelerationControl): tilt from the horizontal demand against
        # gravity plus the vertical demand, magnitude scaled by the hover thrust.
        bzn, bze, bzd = -an, -ae, _G - ad
        n = math.sqrt(bzn * bzn + bze * bze + bzd * bzd)
        if n < 1e-6:
            bzn, bze, bzd = 0.0, 0.0, 1.0
        else:
            bzn, bze, bzd = bzn / n, bze / n, bzd / n
        # Limit tilt: the angle between body z (up-thrust) and vertical.
        c = self._cos_tilt
        if bzd < c:
            h = math.sqrt(bzn * bzn + bze * bze)
            if h > 1e-9:
                s = self._sin_tilt
                bzn, bze, bzd = bzn / h * s, bze / h * s, c
            else:
                bzn, bze, bzd = 0.0, 0.0, 1.0
        hover = lim.hover_thrust
        collective = ad * (hover / _G) - hover
        collective /= bzd
        collective = min(collective, -lim.thr_min)
        tn, te, td = bzn * collective, bze * collective, bzd * collective

        # Saturate vertical, then give horizontal what is left (vertical priority).
        thr_max = lim.thr_max
        td = max(td, -thr_max)
        xy_max_sq = thr_max * thr_max - td * td
        xy_max = math.sqrt(xy_max_sq) if xy_max_sq > 0 else 0.0
        h = math.sqrt(tn * tn + te * te)
        if h > xy_max:
            tn, te = tn / h * xy_max, te / h * xy_max

        # Anti-windup: tracking on xy, conditional on z (PX4).
        if fin_xy and lim.vel_p_xy > 0:
            arw = 2.0 / lim.vel_p_xy
            a_prod = _G / hover
            en -= arw * (an - tn * a_prod)
            ee -= arw * (ae - te * a_prod)
            self._int_n += en * lim.vel_i_xy * dt_s
            self._int_e += ee * lim.vel_i_xy * dt_s
        if fin_z:
            if (td >= -lim.thr_min and ed >= 0) or (td <= -thr_max and ed <= 0):
                ed = 0.0
            i_d = self._int_d + ed * lim.vel_i_z * dt_s
            # PX4 bounds the vertical integral to +-g.
            self._int_d = min(_G, max(-_G, i_d))
        return tn, te, td
