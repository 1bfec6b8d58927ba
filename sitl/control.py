"""PX4's multicopter control cascade in plain floats (pure: time steps are arguments, no I/O).

Position -> velocity -> thrust vector -> attitude -> body rates -> torques -> motor thrusts.

The structure and the limits follow PX4's ``mc_pos_control/PositionControl``, ``mc_att_control``
(reduced-attitude control with MC_YAW_WEIGHT) and ``mc_rate_control``; the rate loop works in
physical units (angular acceleration times inertia) instead of PX4's per-airframe normalised gains,
so it needs no tuning file. Frames: NED world, FRD body. Quaternions are (w, x, y, z) tuples, body ->
NED. These functions run in the simulator's inner loop at the physics rate, which is why they avoid
numpy: a 3-vector through numpy costs more than the arithmetic on it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from sitl.dynamics import QuadModel

NAN = math.nan
_G = 9.80665

Quat = tuple[float, float, float, float]


_finite = math.isfinite  # (a plain alias: no Python call frame in the hot paths)


def quat_from_euler(roll_rad: float, pitch_rad: float, yaw_rad: float) -> Quat:
    """ZYX Euler angles -> quaternion (w, x, y, z), body -> NED."""
    cr, sr = math.cos(roll_rad * 0.5), math.sin(roll_rad * 0.5)
    cp, sp = math.cos(pitch_rad * 0.5), math.sin(pitch_rad * 0.5)
    cy, sy = math.cos(yaw_rad * 0.5), math.sin(yaw_rad * 0.5)
    return (
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    )


def quat_mul(a: Quat, b: Quat) -> Quat:
    """Hamilton product a * b."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


def quat_conj(q: Quat) -> Quat:
    """Conjugate (the inverse of a unit quaternion)."""
    return (q[0], -q[1], -q[2], -q[3])


def quat_dcm_z(q: Quat) -> tuple[float, float, float]:
    """Third column of the rotation matrix: the body z axis expressed in NED."""
    w, x, y, z = q
    return (2.0 * (w * y + x * z), 2.0 * (y * z - w * x), w * w - x * x - y * y + z * z)


def quat_between(u: tuple[float, float, float], v: tuple[float, float, float]) -> Quat:
    """Shortest rotation taking unit vector ``u`` onto unit vector ``v``.

    Built from the half-way vector h = (u + v) / |u + v|: q = (u.h, u x h). Unlike (1 + u.v, u x v) it
    stays accurate when u and v are nearly opposite, where 1 + u.v loses every significant digit.
    """
    hx, hy, hz = u[0] + v[0], u[1] + v[1], u[2] + v[2]
    hn = math.sqrt(hx * hx + hy * hy + hz * hz)
    if hn < 1e-12:
        # Exactly opposite: rotate 180 deg about any axis orthogonal to u.
        ax, ay, az = (1.0, 0.0, 0.0) if abs(u[0]) < 0.9 else (0.0, 1.0, 0.0)
        cx, cy, cz = u[1] * az - u[2] * ay, u[2] * ax - u[0] * az, u[0] * ay - u[1] * ax
        n = math.sqrt(cx * cx + cy * cy + cz * cz)
        return (0.0, cx / n, cy / n, cz / n)
    hx, hy, hz = hx / hn, hy / hn, hz / hn
    w = u[0] * hx + u[1] * hy + u[2] * hz
    cx = u[1] * hz - u[2] * hy
    cy = u[2] * hx - u[0] * hz
    cz = u[0] * hy - u[1] * hx
    n = math.sqrt(w * w + cx * cx + cy * cy + cz * cz)
    return (w / n, cx / n, cy / n, cz / n)


def quat_normalized(q: Quat) -> Quat | None:
    """Unit quaternion, or None if ``q`` is not finite or not near unit length (bad input)."""
    w, x, y, z = q
    if not (_finite(w) and _finite(x) and _finite(y) and _finite(z)):
        return None
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if not 0.5 < n < 2.0:
        return None
    return (w / n, x / n, y / n, z / n)


def yaw_of(q: Quat) -> float:
    """Heading (rad, NED: 0 north, clockwise positive) of a body -> NED quaternion."""
    w, x, y, z = q
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def wrap_pi(angle_rad: float) -> float:
    """Wrap an angle into [-pi, pi)."""
    return (angle_rad + math.pi) % (2.0 * math.pi) - math.pi


def attitude_from_thrust(thr_n: float, thr_e: float, thr_d: float, yaw_rad: float) -> tuple[Quat, float]:
    """PX4 ``bodyzToAttitude``: attitude and collective thrust for a thrust vector and a heading.

    The attitude points -body z along the (NED, normalised) thrust vector with heading ``yaw_rad``;
    the collective thrust is the vector's norm (0..1).
    """
    thrust = math.sqrt(thr_n * thr_n + thr_e * thr_e + thr_d * thr_d)
    bz = (0.0, 0.0, 1.0) if thrust < 1e-06 else (-thr_n / thrust, -thr_e / thrust, -thr_d / thrust)
    # y axis of the heading-only frame, then body x = y_c x body z.
    ycx, ycy = -math.sin(yaw_rad), math.cos(yaw_rad)
    bx = (ycy * bz[2], -ycx * bz[2], ycx * bz[1] - ycy * bz[0])
    if bz[2] < 0.0:
        bx = (-bx[0], -bx[1], -bx[2])
    n = math.sqrt(bx[0] * bx[0] + bx[1] * bx[1] + bx[2] * bx[2])
    bx = (1.0, 0.0, 0.0) if n < 1e-06 else (bx[0] / n, bx[1] / n, bx[2] / n)
    by = (bz[1] * bx[2] - bz[2] * bx[1], bz[2] * bx[0] - bz[0] * bx[2], bz[0] * bx[1] - bz[1] * bx[0])
    # Rotation matrix columns bx, by, bz -> quaternion (Shepperd).
    m00, m01, m02 = bx[0], by[0], bz[0]
    m10, m11, m12 = bx[1], by[1], bz[1]
    m20, m21, m22 = bx[2], by[2], bz[2]
    tr = m00 + m11 + m22
    if tr > 0.0:
        s = math.sqrt(tr + 1.0) * 2.0
        q = (0.25 * s, (m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s)
    elif m00 > m11 and m00 > m22:
        s = math.sqrt(1.0 + m00 - m11 - m22) * 2.0
        q = ((m21 - m12) / s, 0.25 * s, (m01 + m10) / s, (m02 + m20) / s)
    elif m11 > m22:
        s = math.sqrt(1.0 + m11 - m00 - m22) * 2.0
        q = ((m02 - m20) / s, (m01 + m10) / s, 0.25 * s, (m12 + m21) / s)
    else:
        s = math.sqrt(1.0 + m22 - m00 - m11) * 2.0
        q = ((m10 - m01) / s, (m02 + m20) / s, (m12 + m21) / s, 0.25 * s)
    return q, thrust


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
        pn, pe, pd = pos_ned_m
        vn, ve, vd = vel_ned_m_s
        # Velocity derivative for the D term (low-passed, as PX4 filters vel_dot).
        if self._v_prev is not None and dt_s > 0:
            a = min(1.0, dt_s / 0.05)
            self._vdot_n += a * ((vn - self._v_prev[0]) / dt_s - self._vdot_n)
            self._vdot_e += a * ((ve - self._v_prev[1]) / dt_s - self._vdot_e)
            self._vdot_d += a * ((vd - self._v_prev[2]) / dt_s - self._vdot_d)
        self._v_prev = (vn, ve, vd)

        # Position loop: velocity setpoint = feed-forward + P * position error, per finite axis.
        vsn = sp.vx if _finite(sp.vx) else NAN
        vse = sp.vy if _finite(sp.vy) else NAN
        vsd = sp.vz if _finite(sp.vz) else NAN
        if _finite(sp.x):
            vsn = (vsn if _finite(vsn) else 0.0) + (sp.x - pn) * lim.pos_p_xy
            vse = (vse if _finite(vse) else 0.0) + (sp.y - pe) * lim.pos_p_xy
        if _finite(sp.z):
            vsd = (vsd if _finite(vsd) else 0.0) + (sp.z - pd) * lim.pos_p_z
        # Limit the velocity setpoint (horizontal norm, vertical up/down separately).
        if _finite(vsn):
            h = math.sqrt(vsn * vsn + vse * vse)
            if h > lim.vel_max_xy_m_s:
                vsn *= lim.vel_max_xy_m_s / h
                vse *= lim.vel_max_xy_m_s / h
        if _finite(vsd):
            vsd = min(lim.vel_max_down_m_s, max(-lim.vel_max_up_m_s, vsd))
        self.vel_sp_ned_m_s = (vsn, vse, vsd)

        # Velocity loop -> acceleration setpoint; feed-forward acceleration added where finite.
        if _finite(vsn):
            en, ee = vsn - vn, vse - ve
            an = en * lim.vel_p_xy + self._int_n - self._vdot_n * lim.vel_d_xy
            ae = ee * lim.vel_p_xy + self._int_e - self._vdot_e * lim.vel_d_xy
        else:
            en = ee = 0.0
            an = ae = 0.0
        if _finite(vsd):
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
        if bzd < math.cos(lim.tilt_max_rad):
            h = math.sqrt(bzn * bzn + bze * bze)
            s = math.sin(lim.tilt_max_rad)
            c = math.cos(lim.tilt_max_rad)
            if h > 1e-9:
                bzn, bze, bzd = bzn / h * s, bze / h * s, c
            else:
                bzn, bze, bzd = 0.0, 0.0, 1.0
        collective = ad * (lim.hover_thrust / _G) - lim.hover_thrust
        collective /= bzd
        collective = min(collective, -lim.thr_min)
        tn, te, td = bzn * collective, bze * collective, bzd * collective

        # Saturate vertical, then give horizontal what is left (vertical priority).
        td = max(td, -lim.thr_max)
        xy_max_sq = lim.thr_max * lim.thr_max - td * td
        xy_max = math.sqrt(xy_max_sq) if xy_max_sq > 0 else 0.0
        h = math.sqrt(tn * tn + te * te)
        if h > xy_max:
            tn, te = tn / h * xy_max, te / h * xy_max

        # Anti-windup: tracking on xy, conditional on z (PX4).
        if _finite(vsn) and lim.vel_p_xy > 0:
            arw = 2.0 / lim.vel_p_xy
            a_prod = _G / lim.hover_thrust
            en -= arw * (an - tn * a_prod)
            ee -= arw * (ae - te * a_prod)
            self._int_n += en * lim.vel_i_xy * dt_s
            self._int_e += ee * lim.vel_i_xy * dt_s
        if _finite(vsd):
            if (td >= -lim.thr_min and ed >= 0) or (td <= -lim.thr_max and ed <= 0):
                ed = 0.0
            self._int_d += ed * lim.vel_i_z * dt_s
            # PX4 bounds the vertical integral to +-g.
            self._int_d = min(_G, max(-_G, self._int_d))
        return tn, te, td


@dataclass(frozen=True, slots=True)
class AttitudeGains:
    """Attitude P gains (MC_*_P), yaw weight and rate limits (rad/s)."""

    roll_p: float = 6.5
    pitch_p: float = 6.5
    yaw_p: float = 2.8
    yaw_weight: float = 0.4
    roll_rate_max: float = math.radians(220.0)
    pitch_rate_max: float = math.radians(220.0)
    yaw_rate_max: float = math.radians(200.0)


class InnerLoop:
    """Attitude -> rate -> torque -> motor loop, run every physics tick.

    * Attitude: PX4 ``AttitudeControl`` (reduced attitude first, then yaw blended in with
      MC_YAW_WEIGHT, so tilt errors are fixed before heading errors), P gains MC_ROLL_P etc.
    * Rates: a PID per axis in angular acceleration (bandwidth ~20 rad/s against the 30 ms motor lag)
      times the model's inertia, i.e. PX4 ``RateControl`` in physical units.
    * Allocation: quad-X mixer with PX4-like desaturation (airmode off): roll/pitch keep priority,
      collective thrust shifts to make room, yaw gets what is left.

    Each stage is one method of inlined plain-float arithmetic on purpose: this is the simulator's
    hottest code, and Python function calls cost as much as the arithmetic they wrap.
    """

    __slots__ = (
        "_fmax", "_int_p", "_int_q", "_int_r", "_ixx", "_iyy", "_izz", "_k_rp", "_k_y", "_prev_p",
        "_prev_q", "gains",
    )  # fmt: skip

    KP_RP = 20.0
    KI_RP = 10.0
    KD_RP = 0.05
    KP_YAW = 8.0
    KI_YAW = 4.0
    INT_LIMIT_RAD_S2 = 15.0

    def __init__(self, model: QuadModel, gains: AttitudeGains | None = None) -> None:
        self.gains = gains or AttitudeGains()
        self._ixx = model.ixx_kg_m2
        self._iyy = model.iyy_kg_m2
        self._izz = model.izz_kg_m2
        self._fmax = model.max_thrust_per_motor_n
        self._k_rp = 1.0 / (4.0 * model.arm_xy_m)
        self._k_y = 1.0 / (4.0 * model.yaw_moment_per_thrust_m)
        self._int_p = self._int_q = self._int_r = 0.0
        self._prev_p = self._prev_q = 0.0

    def reset_integrators(self) -> None:
        self._int_p = self._int_q = self._int_r = 0.0

    def attitude_to_rates(self, q: Quat, q_sp: Quat, yawspeed_ff_rad_s: float) -> tuple[float, float, float]:
        """PX4 ``AttitudeControl::update``: body-rate setpoint (rad/s) from the attitude error."""
        g = self.gains
        w, x, y, z = q
        sw, sx, sy, sz = q_sp
        # Body z axes (third DCM columns) of the current and desired attitude.
        ezx, ezy, ezz = 2.0 * (w * y + x * z), 2.0 * (y * z - w * x), w * w - x * x - y * y + z * z
        dzx, dzy, dzz = (
            2.0 * (sw * sy + sx * sz),
            2.0 * (sy * sz - sw * sx),
            sw * sw - sx * sx - sy * sy + sz * sz,
        )
        # Shortest rotation ez -> ezd (in NED), then applied to q: the reduced desired attitude.
        cx, cy, cz = ezy * dzz - ezz * dzy, ezz * dzx - ezx * dzz, ezx * dzy - ezy * dzx
        rw = 1.0 + ezx * dzx + ezy * dzy + ezz * dzz
        n = math.sqrt(rw * rw + cx * cx + cy * cy + cz * cz)
        if n < 1e-6:
            rw_, rx_, ry_, rz_ = sw, sx, sy, sz
        else:
            rw, cx, cy, cz = rw / n, cx / n, cy / n, cz / n
            if abs(cx) > 1.0 - 1e-5 or abs(cy) > 1.0 - 1e-5:
                rw_, rx_, ry_, rz_ = sw, sx, sy, sz
            else:
                rw_ = rw * w - cx * x - cy * y - cz * z
                rx_ = rw * x + cx * w + cy * z - cz * y
                ry_ = rw * y - cx * z + cy * w + cz * x
                rz_ = rw * z + cx * y - cy * x + cz * w
        # q_mix = qd_red^-1 * q_sp: the remaining rotation, a pure yaw about body z.
        mw = rw_ * sw + rx_ * sx + ry_ * sy + rz_ * sz
        mz = rw_ * sz - rx_ * sy + ry_ * sx - rz_ * sw
        if mw < 0.0:
            mw, mz = -mw, -mz
        mw = 1.0 if mw > 1.0 else (-1.0 if mw < -1.0 else mw)
        mz = 1.0 if mz > 1.0 else (-1.0 if mz < -1.0 else mz)
        yw = g.yaw_weight
        bw, bz = math.cos(yw * math.acos(mw)), math.sin(yw * math.asin(mz))
        # qd = qd_red * (bw, 0, 0, bz)
        dw = rw_ * bw - rz_ * bz
        dx = rx_ * bw + ry_ * bz
        dy = ry_ * bw - rx_ * bz
        dz = rw_ * bz + rz_ * bw
        # qe = q^-1 * qd
        ew = w * dw + x * dx + y * dy + z * dz
        ex = w * dx - x * dw - y * dz + z * dy
        ey = w * dy + x * dz - y * dw - z * dx
        ez = w * dz - x * dy + y * dx - z * dw
        if ew < 0.0:
            ex, ey, ez = -ex, -ey, -ez
        rx = 2.0 * ex * g.roll_p
        ry = 2.0 * ey * g.pitch_p
        rz = 2.0 * ez * g.yaw_p
        if not math.isnan(yawspeed_ff_rad_s):  # not NaN: world yaw rate as body rates, R^T e_z
            rx += 2.0 * (x * z - w * y) * yawspeed_ff_rad_s
            ry += 2.0 * (y * z + w * x) * yawspeed_ff_rad_s
            rz += ezz * yawspeed_ff_rad_s
        lim = g.roll_rate_max
        rx = lim if rx > lim else (-lim if rx < -lim else rx)
        lim = g.pitch_rate_max
        ry = lim if ry > lim else (-lim if ry < -lim else ry)
        lim = g.yaw_rate_max
        rz = lim if rz > lim else (-lim if rz < -lim else rz)
        return rx, ry, rz

    def rates_to_motors(  # noqa: PLR0917 - the hottest call in the simulator: positional on purpose
        self,
        sp_p: float,
        sp_q: float,
        sp_r: float,
        thrust: float,
        p: float,
        q: float,
        r: float,
        dt_s: float,
        integrate: bool,
    ) -> tuple[float, float, float, float]:
        """Rate PID + allocation: motor commands 0..1 in PX4 order (FR, RL, FL, RR)."""
        ep, eq, er = sp_p - p, sp_q - q, sp_r - r
        dp = (p - self._prev_p) / dt_s
        dq = (q - self._prev_q) / dt_s
        self._prev_p, self._prev_q = p, q
        tx = (self.KP_RP * ep + self._int_p - self.KD_RP * dp) * self._ixx
        ty = (self.KP_RP * eq + self._int_q - self.KD_RP * dq) * self._iyy
        tz = (self.KP_YAW * er + self._int_r) * self._izz
        if integrate:
            lim = self.INT_LIMIT_RAD_S2
            ip = self._int_p + self.KI_RP * ep * dt_s
            iq = self._int_q + self.KI_RP * eq * dt_s
            ir = self._int_r + self.KI_YAW * er * dt_s
            self._int_p = lim if ip > lim else (-lim if ip < -lim else ip)
            self._int_q = lim if iq > lim else (-lim if iq < -lim else iq)
            self._int_r = lim if ir > lim else (-lim if ir < -lim else ir)
        # Allocation (per-motor thrust, N).
        fmax = self._fmax
        base = thrust * fmax
        rx = tx * self._k_rp
        ry = ty * self._k_rp
        r0, r1, r2, r3 = ry - rx, rx - ry, rx + ry, -rx - ry
        hi = r0 if r0 > r1 else r1
        hi = hi if hi > r2 else r2
        hi = hi if hi > r3 else r3
        lo = r0 if r0 < r1 else r1
        lo = lo if lo < r2 else r2
        lo = lo if lo < r3 else r3
        if hi - lo > fmax:
            s = fmax / (hi - lo)
            r0, r1, r2, r3, lo, hi = r0 * s, r1 * s, r2 * s, r3 * s, lo * s, hi * s
        if base + lo < 0.0:
            base = -lo
        elif base + hi > fmax:
            base = fmax - hi
        f0, f1, f2, f3 = base + r0, base + r1, base + r2, base + r3
        yv = tz * self._k_y
        if yv > 0.0:  # raises the CCW rotors 0, 1; lowers 2, 3
            room = min(fmax - f0, fmax - f1, f2, f3)
            yv = yv if yv < room else (room if room > 0.0 else 0.0)
        elif yv < 0.0:
            room = min(f0, f1, fmax - f2, fmax - f3)
            yv = yv if -yv < room else (-room if room > 0.0 else 0.0)
        inv = 1.0 / fmax
        u0 = (f0 + yv) * inv
        u1 = (f1 + yv) * inv
        u2 = (f2 - yv) * inv
        u3 = (f3 - yv) * inv
        return (
            1.0 if u0 > 1.0 else (0.0 if u0 < 0.0 else u0),
            1.0 if u1 > 1.0 else (0.0 if u1 < 0.0 else u1),
            1.0 if u2 > 1.0 else (0.0 if u2 < 0.0 else u2),
            1.0 if u3 > 1.0 else (0.0 if u3 < 0.0 else u3),
        )
