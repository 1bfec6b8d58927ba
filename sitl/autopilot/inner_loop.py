"""PX4's attitude and rate control and the quad-X mixer, run every physics tick (plain floats, pure).

Attitude -> body rates -> torques -> motor thrusts, after PX4's ``mc_att_control`` (reduced attitude
first, yaw blended in with MC_YAW_WEIGHT) and ``mc_rate_control``; the rate loop works in physical units
(angular acceleration times inertia) instead of PX4's per-airframe normalised gains, so it needs no
tuning file. The position loop that feeds it is :mod:`sitl.autopilot.control`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from sitl.autopilot.attitude import Quat
from sitl.physics.dynamics import QuadModel


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


# The rate loop's gains (InnerLoop's class constants, as module globals for the per-tick path).
_KP_RP, _KI_RP, _KD_RP = 20.0, 10.0, 0.05
_KP_YAW, _KI_YAW = 8.0, 4.0
_INT_LIMIT_RAD_S2 = 15.0


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
        "_dzx", "_dzy", "_dzz", "_fmax", "_int_p", "_int_q", "_int_r", "_ixx", "_iyy", "_izz", "_k_rp",
        "_k_y", "_prev_p", "_prev_q", "_q_sp", "gains",
    )  # fmt: skip

    KP_RP = _KP_RP
    KI_RP = _KI_RP
    KD_RP = _KD_RP
    KP_YAW = _KP_YAW
    KI_YAW = _KI_YAW
    INT_LIMIT_RAD_S2 = _INT_LIMIT_RAD_S2

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
        # The attitude setpoint changes at the outer rate: its body z axis is kept until it does.
        self._q_sp: Quat | None = None
        self._dzx = self._dzy = self._dzz = 0.0

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
        # PX4 divides MC_YAW_P by the yaw weight (AttitudeControl::setProportionalGain), so a small heading
        # error turns at MC_YAW_P times it whatever the weight.
        rz = 2.0 * ez * (g.yaw_p / yw if yw > 1e-4 else g.yaw_p)
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

    def update(  # noqa: PLR0917 - per physics tick: positional on purpose
        self,
        roll_rad: float,
        pitch_rad: float,
        yaw_rad: float,
        p: float,
        q: float,
        r: float,
        q_sp: Quat,
        yawspeed_ff_rad_s: float,
        thrust: float,
        dt_s: float,
        integrate: bool,
    ) -> tuple[float, float, float, float]:
        """One tick from the attitude (ZYX Euler, rad) and body rates: motor commands 0..1, PX4 order.

        The same arithmetic, operation for operation (so bit for bit), as
        :func:`~sitl.autopilot.attitude.quat_from_euler`, :meth:`attitude_to_rates` and
        :meth:`rates_to_motors` in turn, in one Python frame: three calls, their tuples and the setpoint's
        body z axis (recomputed only when ``q_sp`` changes) cost a third of the inner loop otherwise.
        """
        g = self.gains
        # quat_from_euler (the shared products are the ones it computes first, left to right).
        cr, sr = math.cos(roll_rad * 0.5), math.sin(roll_rad * 0.5)
        cp, sp = math.cos(pitch_rad * 0.5), math.sin(pitch_rad * 0.5)
        cy, sy = math.cos(yaw_rad * 0.5), math.sin(yaw_rad * 0.5)
        crcp, srsp, srcp, crsp = cr * cp, sr * sp, sr * cp, cr * sp
        w = crcp * cy + srsp * sy
        x = srcp * cy - crsp * sy
        y = crsp * cy + srcp * sy
        z = crcp * sy - srsp * cy
        # attitude_to_rates
        sw, sx, sy_, sz = q_sp
        if q_sp is not self._q_sp:
            self._q_sp = q_sp
            self._dzx = 2.0 * (sw * sy_ + sx * sz)
            self._dzy = 2.0 * (sy_ * sz - sw * sx)
            self._dzz = sw * sw - sx * sx - sy_ * sy_ + sz * sz
        dzx, dzy, dzz = self._dzx, self._dzy, self._dzz
        ezx, ezy, ezz = 2.0 * (w * y + x * z), 2.0 * (y * z - w * x), w * w - x * x - y * y + z * z
        cx, cy_, cz = ezy * dzz - ezz * dzy, ezz * dzx - ezx * dzz, ezx * dzy - ezy * dzx
        rw = 1.0 + ezx * dzx + ezy * dzy + ezz * dzz
        n = math.sqrt(rw * rw + cx * cx + cy_ * cy_ + cz * cz)
        if n < 1e-6:
            rw_, rx_, ry_, rz_ = sw, sx, sy_, sz
        else:
            rw, cx, cy_, cz = rw / n, cx / n, cy_ / n, cz / n
            if abs(cx) > 1.0 - 1e-5 or abs(cy_) > 1.0 - 1e-5:
                rw_, rx_, ry_, rz_ = sw, sx, sy_, sz
            else:
                rw_ = rw * w - cx * x - cy_ * y - cz * z
                rx_ = rw * x + cx * w + cy_ * z - cz * y
                ry_ = rw * y - cx * z + cy_ * w + cz * x
                rz_ = rw * z + cx * y - cy_ * x + cz * w
        mw = rw_ * sw + rx_ * sx + ry_ * sy_ + rz_ * sz
        mz = rw_ * sz - rx_ * sy_ + ry_ * sx - rz_ * sw
        if mw < 0.0:
            mw, mz = -mw, -mz
        mw = 1.0 if mw > 1.0 else (-1.0 if mw < -1.0 else mw)
        mz = 1.0 if mz > 1.0 else (-1.0 if mz < -1.0 else mz)
        yw = g.yaw_weight
        bw, bz = math.cos(yw * math.acos(mw)), math.sin(yw * math.asin(mz))
        dw = rw_ * bw - rz_ * bz
        dx = rx_ * bw + ry_ * bz
        dy = ry_ * bw - rx_ * bz
        dz = rw_ * bz + rz_ * bw
        ew = w * dw + x * dx + y * dy + z * dz
        ex = w * dx - x * dw - y * dz + z * dy
        ey = w * dy + x * dz - y * dw - z * dx
        ez = w * dz - x * dy + y * dx - z * dw
        if ew < 0.0:
            ex, ey, ez = -ex, -ey, -ez
        sp_p = 2.0 * ex * g.roll_p
        sp_q = 2.0 * ey * g.pitch_p
        sp_r = 2.0 * ez * (g.yaw_p / yw if yw > 1e-4 else g.yaw_p)  # as attitude_to_rates
        if not math.isnan(yawspeed_ff_rad_s):
            sp_p += 2.0 * (x * z - w * y) * yawspeed_ff_rad_s
            sp_q += 2.0 * (y * z + w * x) * yawspeed_ff_rad_s
            sp_r += ezz * yawspeed_ff_rad_s
        lim = g.roll_rate_max
        sp_p = lim if sp_p > lim else (-lim if sp_p < -lim else sp_p)
        lim = g.pitch_rate_max
        sp_q = lim if sp_q > lim else (-lim if sp_q < -lim else sp_q)
        lim = g.yaw_rate_max
        sp_r = lim if sp_r > lim else (-lim if sp_r < -lim else sp_r)
        # rates_to_motors
        ep, eq, er = sp_p - p, sp_q - q, sp_r - r
        dp = (p - self._prev_p) / dt_s
        dq = (q - self._prev_q) / dt_s
        self._prev_p, self._prev_q = p, q
        tx = (_KP_RP * ep + self._int_p - _KD_RP * dp) * self._ixx
        ty = (_KP_RP * eq + self._int_q - _KD_RP * dq) * self._iyy
        tz = (_KP_YAW * er + self._int_r) * self._izz
        if integrate:
            lim = _INT_LIMIT_RAD_S2
            ip = self._int_p + _KI_RP * ep * dt_s
            iq = self._int_q + _KI_RP * eq * dt_s
            ir = self._int_r + _KI_YAW * er * dt_s
            self._int_p = lim if ip > lim else (-lim if ip < -lim else ip)
            self._int_q = lim if iq > lim else (-lim if iq < -lim else iq)
            self._int_r = lim if ir > lim else (-lim if ir < -lim else ir)
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
        if yv > 0.0:
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
