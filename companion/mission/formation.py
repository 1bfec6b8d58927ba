"""The formation law: the paper's decoupled PID on the offset error, made to work on PX4 with and without GPS.

Geometry. The desired slot comes from ``FormationConfig.offset_cam_m``: the leader's position in a *level*
camera frame (x right, y down, z forward; the camera's mount tilt is not applied), i.e. ``forward = z``,
``right = x``, ``down = y`` in the follower's heading frame. Yaw keeps the leader at the slot's bearing
(centred in the image for the default slot), so the horizontal slot is the point on the current line of
sight at the slot's range: the translational error is radial (``e_r = range - slot_range``) plus vertical
(``e_z``), and the lateral error is the yaw loop's job. The two loops never fight over the same error.

Two outputs share that error:

* :meth:`FormationLaw.velocity` (GPS healthy): ``v = ff * v_leader + (kp e_r + kd de_r/dt + I_r) u_los``
  horizontally and ``ff * v_leader_z + kp_z e_z + I_z`` vertically, with ``v_leader = v_follower + v_rel``
  and the derivative taken from the tracker's filtered relative velocity (not a finite difference of noisy
  positions). PX4's velocity loop does the rest. Sent as a body-frame velocity with a yaw *rate*, so the
  leader's bearing rate is fed forward.
* :meth:`FormationLaw.attitude` (GPS lost): the same outer PI gives a desired *relative* velocity; an inner
  loop turns the relative-velocity error into an acceleration, hence a tilt, and a vertical-speed loop on the
  baro-aided vertical speed gives the thrust. Nothing here reads PX4's horizontal position or velocity,
  which are invalid without GPS.

Every output goes through :mod:`companion.mission.safety` last, in this order of precedence: the altitude
band (the ground is harder than the leader), the geofence, the separation barrier, then acceleration and
speed limits.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.config import FormationConfig
from companion.kernel.frames import Vec3, wrap_pi
from companion.mission.safety import (
    G_M_S2,
    SafetyLimits,
    altitude_limit,
    clamp_horizontal_accel,
    clamp_speed,
    geofence_limit,
    separation_limit,
    separation_limit_accel,
)
from companion.vehicle.types import AttitudeSetpoint, Vec3T, VelocityBodySetpoint, VelocityNedSetpoint

#: A gap between two law updates longer than this restarts the integrators and the slew (s).
MAX_DT_S = 0.5
#: The first command after :meth:`FormationLaw.seed_velocity` slews from the seeded velocity over this
#: long (one control period at the default 20 Hz): without it the first command of FOLLOW jumped straight
#: to the full PID output, and the vehicle pitched past 40 deg and lost the leader from view (s).
FIRST_SLEW_DT_S = 0.05
#: Below this horizontal range the line-of-sight bearing is meaningless (m).
MIN_BEARING_RANGE_M = 0.5
#: PX4's velocity loop reaches a new setpoint with about this time constant (1 / MPC_XY_VEL_P_ACC), s: the
#: depth guard's model of the path the follower will fly.
PX4_VEL_TAU_S = 1.0 / 1.8
#: How far ahead in time the depth guard follows that path (the guard's 4 m at 2 m/s), s.
GUARD_HORIZON_S = 2.0
_GUARD_T_S = np.linspace(0.0, GUARD_HORIZON_S, 21)
#: How far the present velocity still carries at those times, s (the first-order lag's integral).
_GUARD_LAG_S = PX4_VEL_TAU_S * (1.0 - np.exp(-_GUARD_T_S / PX4_VEL_TAU_S))
#: How hard the follower steps aside from an obstacle it would pass too close: m/s per m short of the
#: depth guard's corridor (at most 0.45 m/s with the defaults: corridor 0.8 m, hit radius 0.35 m).
STATIC_SLIDE_GAIN_1_S = 1.0


@dataclass(frozen=True, slots=True)
class Slot:
    """The desired leader position in the follower's level heading frame (forward, right, down), m."""

    forward_m: float
    right_m: float
    down_m: float

    @classmethod
    def from_offset_cam(cls, offset_cam_m: tuple[float, float, float]) -> Slot:
        x_right, y_down, z_forward = offset_cam_m
        return cls(forward_m=z_forward, right_m=x_right, down_m=y_down)

    @property
    def range_h_m(self) -> float:
        return math.hypot(self.forward_m, self.right_m)

    @property
    def bearing_offset_rad(self) -> float:
        """Where the leader should sit relative to the nose, rad (positive right)."""
        return math.atan2(self.right_m, self.forward_m)

    def p_ned_m(self, yaw_rad: float) -> Vec3:
        """The slot in local NED for a follower heading ``yaw_rad``."""
        c, s = math.cos(yaw_rad), math.sin(yaw_rad)
        return np.array(
            [c * self.forward_m - s * self.right_m, s * self.forward_m + c * self.right_m, self.down_m]
        )


@dataclass(frozen=True, slots=True)
class SlotError:
    """The formation error split the way the law uses it."""

    #: Unit horizontal line of sight to the leader (NED, z = 0).
    u_los: Vec3
    bearing_rad: float
    #: Rate of the bearing, from the relative velocity (rad/s).
    bearing_rate_rad_s: float
    #: Horizontal range minus the slot's range (m); positive: leader too far.
    e_range_m: float
    #: Its rate (m/s), from the filtered relative velocity.
    e_range_rate_m_s: float
    #: Leader below the slot by this much (m, NED down); positive: follower should descend.
    e_down_m: float
    #: The desired yaw: the bearing minus the slot's bearing offset (rad).
    yaw_des_rad: float
    #: Leader relative position minus the slot placed at the *current* yaw (what a camera sees), NED m.
    error_ned_m: Vec3


def slot_error(slot: Slot, p_ned_rel_m: Vec3, v_ned_rel_m_s: Vec3, yaw_rad: float) -> SlotError:
    """Decompose the relative state (leader minus follower, NED) against the slot."""
    p = np.asarray(p_ned_rel_m, dtype=np.float64)
    v = np.asarray(v_ned_rel_m_s, dtype=np.float64)
    r = math.hypot(p[0], p[1])
    if r >= MIN_BEARING_RANGE_M:
        bearing = math.atan2(p[1], p[0])
        bearing_rate = (p[0] * v[1] - p[1] * v[0]) / (r * r)
    else:
        bearing = yaw_rad + slot.bearing_offset_rad
        bearing_rate = 0.0
    u = np.array([math.cos(bearing), math.sin(bearing), 0.0])
    return SlotError(
        u_los=u,
        bearing_rad=bearing,
        bearing_rate_rad_s=bearing_rate,
        e_range_m=r - slot.range_h_m,
        e_range_rate_m_s=float(np.dot(v, u)),
        e_down_m=float(p[2] - slot.down_m),
        yaw_des_rad=wrap_pi(bearing - slot.bearing_offset_rad),
        error_ned_m=p - slot.p_ned_m(yaw_rad),
    )


@dataclass(frozen=True, slots=True)
class FollowerState:
    """What the law reads from the vehicle, NED and SI. ``None`` marks what is not valid now."""

    yaw_rad: float
    #: PX4's velocity estimate; only valid (not None) while its position estimate is.
    v_ned_m_s: Vec3 | None
    #: Vertical speed (NED down), baro-aided: valid without GPS.
    v_down_m_s: float
    #: Height above home (baro-aided), m.
    alt_rel_m: float
    #: Position relative to home, for the geofence; None when not valid.
    p_ned_m: Vec3 | None = None
    roll_rad: float = 0.0
    pitch_rad: float = 0.0


@dataclass(frozen=True, slots=True)
class VelocityCommand:
    """The velocity law's output: the setpoint to send and what went into it."""

    setpoint: VelocityBodySetpoint
    v_ned_m_s: Vec3T
    yaw_rate_rad_s: float
    error: SlotError


@dataclass(frozen=True, slots=True)
class AttitudeCommand:
    """The attitude law's output."""

    setpoint: AttitudeSetpoint
    a_ned_m_s2: Vec3T
    v_down_des_m_s: float
    error: SlotError | None


def ned_to_heading(v_ned: Vec3, yaw_rad: float) -> Vec3:
    """Rotate a NED vector into the heading frame (forward, right, down) of ``yaw_rad``."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array([c * v_ned[0] + s * v_ned[1], -s * v_ned[0] + c * v_ned[1], v_ned[2]])


def heading_to_ned(v_h: Vec3, yaw_rad: float) -> Vec3:
    """Inverse of :func:`ned_to_heading`."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array([c * v_h[0] - s * v_h[1], s * v_h[0] + c * v_h[1], v_h[2]])


def tilt_from_accel(a_ned_m_s2: Vec3, yaw_rad: float) -> tuple[float, float]:
    """Roll and pitch (rad) that give a horizontal acceleration ``a_ned`` at constant altitude."""
    a_h = ned_to_heading(a_ned_m_s2, yaw_rad)
    pitch = -math.atan2(a_h[0], G_M_S2)
    roll = math.atan2(a_h[1] * math.cos(pitch), G_M_S2)
    return roll, pitch


class ThrustController:
    """Vertical speed -> normalised collective thrust, with an adaptive hover-thrust estimate.

    ``thrust = hover * (1 + a_up / g) / (cos roll cos pitch)`` with ``a_up = kv (v_down - v_down_des)``.
    The hover estimate integrates the vertical-speed error, so a wrong initial guess (PX4's MPC_THR_HOVER,
    or the config default) is learned within seconds instead of leaving a steady climb or sink.
    """

    KV_1_S = 3.0
    K_HOVER = 0.15
    MIN_THRUST = 0.05
    MAX_THRUST = 0.95

    def __init__(self, hover_thrust_norm: float) -> None:
        self.hover_thrust_norm = hover_thrust_norm

    def thrust(
        self, v_down_des_m_s: float, v_down_m_s: float, roll_rad: float, pitch_rad: float, dt_s: float
    ) -> float:
        err = v_down_m_s - v_down_des_m_s
        a_up = self.KV_1_S * err
        self.hover_thrust_norm = float(np.clip(self.hover_thrust_norm + self.K_HOVER * err * dt_s, 0.1, 0.9))
        cos_tilt = max(0.5, math.cos(roll_rad) * math.cos(pitch_rad))
        t = self.hover_thrust_norm * (1.0 + a_up / G_M_S2) / cos_tilt
        return float(np.clip(t, self.MIN_THRUST, self.MAX_THRUST))


class FormationLaw:
    """The PID formation law with its integrators, slew state and thrust controller.

    Call :meth:`reset` whenever the law stops being used (another state took over), so integrators never
    carry over a stale history.
    """

    #: Inner loop of the attitude law: relative-velocity error -> acceleration (1/s), like PX4's
    #: MPC_XY_VEL_P_ACC.
    KV_XY_1_S = 1.8
    #: Its integral, in the heading frame (1/s^2): the acceleration a steady turn needs is constant there.
    KI_V_XY_1_S2 = 0.6
    I_ACC_LIMIT_M_S2 = 2.0
    #: An absolute yaw setpoint makes PX4 turn at MC_YAW_P (2.8/s) times the error, so a setpoint this far
    #: ahead of the desired yaw in time turns at the desired rate (1 / MC_YAW_P, s).
    YAW_LEAD_S = 1.0 / 2.8

    def __init__(self, cfg: FormationConfig, limits: SafetyLimits, hover_thrust_norm: float = 0.5) -> None:
        self.cfg = cfg
        self.limits = limits
        self.slot = Slot.from_offset_cam(cfg.offset_cam_m)
        self.thrust = ThrustController(hover_thrust_norm)
        self._last_s: float | None = None
        self._i_range_m_s = 0.0
        self._i_down_m_s = 0.0
        self._i_acc_heading = np.zeros(2)
        self._v_prev: Vec3 | None = None
        self._v_leader_prev: Vec3 | None = None
        self._a_leader = np.zeros(3)

    def reset(self) -> None:
        """Forget integrators and slew history (the hover-thrust estimate is a vehicle property: kept)."""
        self._last_s = None
        self._i_range_m_s = 0.0
        self._i_down_m_s = 0.0
        self._i_acc_heading = np.zeros(2)
        self._v_prev = None
        self._v_leader_prev = None
        self._a_leader = np.zeros(3)

    def _leader_accel(self, v_leader: Vec3 | None, dt: float, a_track: Vec3T | None = None) -> Vec3:
        """The leader's acceleration, bounded by the law's acceleration cap.

        The tracker's estimate ``a_track`` where it has one (``tracker.leader_accel_filter``), else the
        low-passed derivative of the leader's estimated velocity.
        """
        limit = self.cfg.max_accel_m_s2
        if a_track is not None:
            a = np.array(a_track, dtype=np.float64)
            n = float(np.linalg.norm(a))
            self._a_leader = a * (limit / n) if n > limit else a
            self._v_leader_prev = None if v_leader is None else np.array(v_leader, dtype=np.float64)
            return self._a_leader
        if v_leader is None:
            self._v_leader_prev = None
            self._a_leader = np.zeros(3)
            return self._a_leader
        if self._v_leader_prev is not None and dt > 0.0:
            a_raw = (v_leader - self._v_leader_prev) / dt
            k = dt / (self.cfg.leader_accel_tau_s + dt)
            a = self._a_leader + k * (a_raw - self._a_leader)
            n = float(np.linalg.norm(a))
            self._a_leader = a * (limit / n) if n > limit else a
        self._v_leader_prev = np.array(v_leader, dtype=np.float64)
        return self._a_leader

    @property
    def leader_accel_ned_m_s2(self) -> Vec3:
        """The law's current estimate of the leader's acceleration (NED, m/s^2; zero when unknown)."""
        return self._a_leader

    def seed_velocity(self, v_ned_m_s: Vec3 | None) -> None:
        """Start the acceleration slew from the vehicle's current velocity, not from zero."""
        self._v_prev = None if v_ned_m_s is None else np.array(v_ned_m_s, dtype=np.float64)

    def _dt(self, now_s: float) -> float:
        last, self._last_s = self._last_s, now_s
        if last is None or not 0.0 < now_s - last <= MAX_DT_S:
            self._i_range_m_s = 0.0
            self._i_down_m_s = 0.0
            self._i_acc_heading = np.zeros(2)
            return 0.0
        return now_s - last

    def _yaw_rate(self, err: SlotError, yaw_rad: float) -> float:
        max_rate = math.radians(self.cfg.max_yaw_rate_deg_s)
        rate = self.cfg.kp_yaw * wrap_pi(err.yaw_des_rad - yaw_rad) + err.bearing_rate_rad_s
        return float(np.clip(rate, -max_rate, max_rate))

    def _integrate(
        self, value: float, rate: float, dt_s: float, limit: float, saturated_same_sign: bool
    ) -> float:
        """Bounded integral with conditional integration (no growth while the output saturates that way)."""
        if saturated_same_sign:
            return value
        return float(np.clip(value + rate * dt_s, -limit, limit))

    def velocity(
        self,
        p_ned_rel_m: Vec3,
        v_ned_rel_m_s: Vec3,
        follower: FollowerState,
        now_s: float,
        *,
        a_leader_ned_m_s2: Vec3T | None = None,
        obstacle_ned_m: Vec3 | None = None,
        slew_m_s2: float | None = None,
        coasting: bool = False,
    ) -> VelocityCommand:
        """The GPS-healthy law: a body velocity and yaw rate that hold the slot (see module doc).

        ``a_leader_ned_m_s2``: the tracker's estimate of the leader's acceleration (NED, m/s^2), if it
        makes one; otherwise the law differentiates the leader's velocity. ``obstacle_ned_m``: the depth
        guard's nearest thing ahead (relative NED, m), held off like the leader but taken as static.
        ``slew_m_s2``: how fast the command may change (default ``command_slew_m_s2``). ``coasting``: the
        track has no detection now (the lead is dropped unless ``accel_lead_while_coasting``).
        """
        dt = self._dt(now_s)
        cfg, lim = self.cfg, self.limits
        err = slot_error(self.slot, p_ned_rel_m, v_ned_rel_m_s, follower.yaw_rad)
        v_rel = np.asarray(v_ned_rel_m_s, dtype=np.float64)
        v_leader = None if follower.v_ned_m_s is None else np.asarray(follower.v_ned_m_s) + v_rel
        a_leader = self._leader_accel(v_leader, dt, a_leader_ned_m_s2)
        if coasting and not cfg.accel_lead_while_coasting:
            a_leader = np.zeros(3)
        if v_leader is None:
            ff = np.zeros(3)
        else:
            ff = cfg.leader_velocity_ff * v_leader
            ff[:2] += cfg.leader_accel_ff_s * a_leader[:2]
            ff[2] += cfg.leader_accel_ff_z_s * a_leader[2]

        v_range = cfg.kp_xy * err.e_range_m + cfg.kd_xy * err.e_range_rate_m_s + self._i_range_m_s
        v_down = cfg.kp_z * err.e_down_m + self._i_down_m_s
        raw = ff + v_range * err.u_los + np.array([0.0, 0.0, v_down])

        v = clamp_speed(raw, lim)
        if self._v_prev is not None:
            # Horizontal and vertical slew apart: only the horizontal follows the leader's speed changes;
            # a fast vertical slew swung the height under a lossy link (measured in lockstep).
            step_s = dt if dt > 0.0 else FIRST_SLEW_DT_S
            slew = cfg.command_slew_m_s2 if slew_m_s2 is None else slew_m_s2
            dv = v - self._v_prev
            n_h = math.hypot(dv[0], dv[1])
            max_h = slew * step_s
            if n_h > max_h:
                dv[:2] *= max_h / n_h
            max_z = cfg.command_slew_m_s2 * step_s
            dv[2] = min(max(dv[2], -max_z), max_z)
            v = self._v_prev + dv
        v = self._bound(v, np.asarray(p_ned_rel_m, dtype=np.float64), v_leader, follower, obstacle_ned_m)
        # Separation wins over max speed: a leader rushing at us may push the command past it.
        self._v_prev = v

        # Anti-windup: hold an integral while the output is cut in the direction it would push.
        cut_h = float(np.dot(raw - v, err.u_los))
        cut_z = float(raw[2] - v[2])
        self._i_range_m_s = self._integrate(
            self._i_range_m_s, cfg.ki_xy * err.e_range_m, dt, cfg.i_limit_xy_m_s, cut_h * err.e_range_m > 1e-3
        )
        self._i_down_m_s = self._integrate(
            self._i_down_m_s, cfg.ki_z * err.e_down_m, dt, cfg.i_limit_z_m_s, cut_z * err.e_down_m > 1e-3
        )

        yaw_rate = self._yaw_rate(err, follower.yaw_rad)
        v_body = ned_to_heading(v, follower.yaw_rad)
        sp = VelocityBodySetpoint(
            v_body_m_s=(float(v_body[0]), float(v_body[1]), float(v_body[2])), yaw_rate_rad_s=yaw_rate
        )
        return VelocityCommand(sp, (float(v[0]), float(v[1]), float(v[2])), yaw_rate, err)

    def attitude(
        self,
        p_ned_rel_m: Vec3,
        v_ned_rel_m_s: Vec3,
        follower: FollowerState,
        now_s: float,
    ) -> AttitudeCommand:
        """The GPS-lost law: attitude and thrust from the relative estimate and the baro (see module doc)."""
        dt = self._dt(now_s)
        cfg, lim = self.cfg, self.limits
        p = np.asarray(p_ned_rel_m, dtype=np.float64)
        v_rel = np.asarray(v_ned_rel_m_s, dtype=np.float64)
        err = slot_error(self.slot, p, v_rel, follower.yaw_rad)

        # Outer loop: the relative velocity we want (radial only; tangential relative motion is unwanted).
        v_rel_des = -(cfg.kp_xy * err.e_range_m + self._i_range_m_s) * err.u_los
        dv = v_rel - v_rel_des
        dv[2] = 0.0
        dv_h = ned_to_heading(dv, follower.yaw_rad)
        a_h = self.KV_XY_1_S * dv_h[:2] + self._i_acc_heading
        a = heading_to_ned(np.array([a_h[0], a_h[1], 0.0]), follower.yaw_rad)
        a_max = min(cfg.max_accel_m_s2, lim.max_horizontal_accel_m_s2)
        raw_a = a.copy()
        h = math.hypot(a[0], a[1])
        if h > a_max:
            a[:2] *= a_max / h
        a = separation_limit_accel(a, p, v_rel, lim)
        a = clamp_horizontal_accel(a, lim)
        saturated = float(np.linalg.norm(raw_a - a)) > 1e-3

        # Vertical: follow the leader's height with the baro-aided vertical speed.
        v_leader_down = follower.v_down_m_s + float(v_rel[2])
        v_down_des = cfg.leader_velocity_ff * v_leader_down + cfg.kp_z * err.e_down_m + self._i_down_m_s
        v_down_des = float(np.clip(v_down_des, -lim.max_vertical_speed_m_s, lim.max_vertical_speed_m_s))
        v_down_des = altitude_limit(v_down_des, follower.alt_rel_m, lim)

        if dt > 0.0:
            if not saturated:
                self._i_acc_heading = np.clip(
                    self._i_acc_heading + self.KI_V_XY_1_S2 * dv_h[:2] * dt,
                    -self.I_ACC_LIMIT_M_S2,
                    self.I_ACC_LIMIT_M_S2,
                )
            self._i_range_m_s = self._integrate(
                self._i_range_m_s, cfg.ki_xy * err.e_range_m, dt, cfg.i_limit_xy_m_s, saturated
            )
            self._i_down_m_s = self._integrate(
                self._i_down_m_s, cfg.ki_z * err.e_down_m, dt, cfg.i_limit_z_m_s, False
            )

        roll, pitch = tilt_from_accel(a, follower.yaw_rad)
        thrust = self.thrust.thrust(v_down_des, follower.v_down_m_s, roll, pitch, dt)
        yaw_sp = self._attitude_yaw(err, follower.yaw_rad)
        sp = AttitudeSetpoint(roll_rad=roll, pitch_rad=pitch, yaw_rad=yaw_sp, thrust_norm=thrust)
        return AttitudeCommand(sp, (float(a[0]), float(a[1]), float(a[2])), v_down_des, err)

    def _attitude_yaw(self, err: SlotError, yaw_rad: float) -> float:
        """Absolute yaw setpoint: the desired yaw plus a lead, never more than a bounded step away."""
        target = err.yaw_des_rad + err.bearing_rate_rad_s * self.YAW_LEAD_S
        step_max = math.radians(self.cfg.max_yaw_rate_deg_s) / max(self.cfg.kp_yaw, 1e-3)
        step = float(np.clip(wrap_pi(target - yaw_rad), -step_max, step_max))
        return wrap_pi(yaw_rad + step)

    def hover_attitude(
        self,
        follower: FollowerState,
        v_down_des_m_s: float,
        now_s: float,
        *,
        yaw_rate_rad_s: float = 0.0,
        p_ned_rel_m: Vec3 | None = None,
        v_ned_rel_m_s: Vec3 | None = None,
    ) -> AttitudeCommand:
        """Level-ish attitude at a commanded vertical speed, for hovering, scanning and landing without GPS.

        Brakes on PX4's velocity estimate while it is still valid (``follower.v_ned_m_s`` not None),
        otherwise stays level. Keeps the separation barrier when a relative estimate is given.
        """
        dt = self._dt(now_s)
        lim = self.limits
        a = np.zeros(3)
        if follower.v_ned_m_s is not None:
            v = np.asarray(follower.v_ned_m_s, dtype=np.float64)
            a[:2] = -self.KV_XY_1_S * v[:2]
        if p_ned_rel_m is not None and v_ned_rel_m_s is not None:
            a = separation_limit_accel(a, np.asarray(p_ned_rel_m), np.asarray(v_ned_rel_m_s), lim)
        a_max = min(self.cfg.max_accel_m_s2, lim.max_horizontal_accel_m_s2) * 0.5
        h = math.hypot(a[0], a[1])
        if h > a_max:
            a[:2] *= a_max / h
        roll, pitch = tilt_from_accel(a, follower.yaw_rad)
        thrust = self.thrust.thrust(v_down_des_m_s, follower.v_down_m_s, roll, pitch, dt)
        yaw_sp = wrap_pi(follower.yaw_rad + yaw_rate_rad_s * self.YAW_LEAD_S)
        sp = AttitudeSetpoint(roll_rad=roll, pitch_rad=pitch, yaw_rad=yaw_sp, thrust_norm=thrust)
        return AttitudeCommand(sp, (float(a[0]), float(a[1]), float(a[2])), v_down_des_m_s, None)

    def _bound(
        self,
        v: Vec3,
        p_ned_rel_m: Vec3,
        v_leader: Vec3 | None,
        follower: FollowerState,
        obstacle_ned_m: Vec3 | None = None,
    ) -> Vec3:
        """The velocity laws' last limits, in precedence order: separation, geofence, altitude band.

        Separation holds against the leader (with its velocity) and against the depth guard's obstacle
        (static: nothing is known of its motion).
        """
        lim = self.limits
        v = separation_limit(v, p_ned_rel_m, v_leader, lim, follower.v_ned_m_s)
        if obstacle_ned_m is not None:
            v = self._pass_static(v, np.asarray(obstacle_ned_m, dtype=np.float64), follower)
        v = geofence_limit(v, follower.p_ned_m, lim)
        v[2] = altitude_limit(float(v[2]), follower.alt_rel_m, lim)
        return v

    def _pass_static(self, v: Vec3, obstacle_ned_m: Vec3, follower: FollowerState) -> Vec3:
        """The depth guard's obstacle (static, relative NED): brake for it ahead, slide past it beside.

        On the path the follower will fly (:func:`path_approach`): nearer than ``hit_radius_m``, the
        separation barrier holds it off like the leader; nearer than ``corridor_m``, the command loses any
        part toward the obstacle's side and gains a push away of ``STATIC_SLIDE_GAIN_1_S`` times the
        shortfall; farther, nothing.
        """
        lim = self.limits
        if follower.v_ned_m_s is None:
            if on_course(obstacle_ned_m, v, lim.corridor_m):
                return separation_limit(v, obstacle_ned_m, None, lim, None)
            return v
        cpa_m, q = path_approach(obstacle_ned_m, follower.v_ned_m_s, v)
        if cpa_m >= lim.corridor_m:
            return v
        # Sideways only: across the commanded direction, so the speed along it is kept.
        q_h = np.array([q[0], q[1], 0.0])
        v_h = np.array([v[0], v[1], 0.0])
        s_h = float(np.linalg.norm(v_h))
        if s_h > 1e-6:
            q_h -= (float(np.dot(q_h, v_h)) / (s_h * s_h)) * v_h
        n = float(np.linalg.norm(q_h))
        if cpa_m < lim.hit_radius_m or n < 1e-6:
            return separation_limit(v, obstacle_ned_m, None, lim, follower.v_ned_m_s)
        u = q_h / n
        toward = max(float(np.dot(v, u)), 0.0)
        out: Vec3 = v - (toward + STATIC_SLIDE_GAIN_1_S * (lim.corridor_m - cpa_m)) * u
        return out

    def coast_velocity(
        self,
        v_leader_ned_m_s: Vec3,
        p_ned_rel_m: Vec3,
        follower: FollowerState,
        obstacle_ned_m: Vec3 | None = None,
    ) -> VelocityBodySetpoint:
        """Coast with the leader unseen (GPS healthy): its last velocity, level, no closing on its guess.

        The camera is kept on the leader's dead-reckoned bearing. The dead-reckoned leader flies straight
        on while a real one may turn: closing on it brought a follower from 4.4 m to 1.7 m of a circling
        leader in 1.5 s (network circle runs). The separation barrier still applies against the
        dead-reckoned position.
        """
        lim = self.limits
        p = np.asarray(p_ned_rel_m, dtype=np.float64)
        v_leader = np.asarray(v_leader_ned_m_s, dtype=np.float64)
        v = self._bound(
            clamp_speed(np.array([v_leader[0], v_leader[1], 0.0]), lim), p, v_leader, follower, obstacle_ned_m
        )
        v_rel = v_leader - (np.zeros(3) if follower.v_ned_m_s is None else np.asarray(follower.v_ned_m_s))
        yaw_rate = self._yaw_rate(slot_error(self.slot, p, v_rel, follower.yaw_rad), follower.yaw_rad)
        v_body = ned_to_heading(v, follower.yaw_rad)
        return VelocityBodySetpoint(
            v_body_m_s=(float(v_body[0]), float(v_body[1]), float(v_body[2])), yaw_rate_rad_s=yaw_rate
        )

    def hover_velocity(self, v_down_m_s: float = 0.0, yaw_rate_rad_s: float = 0.0) -> VelocityBodySetpoint:
        """Stop in place (GPS healthy): zero horizontal velocity, a vertical speed and a yaw rate."""
        return VelocityBodySetpoint(v_body_m_s=(0.0, 0.0, v_down_m_s), yaw_rate_rad_s=yaw_rate_rad_s)


def path_approach(p_ned_m: Vec3, v_now_ned_m_s: Vec3, v_cmd_ned_m_s: Vec3) -> tuple[float, Vec3]:
    """Closest approach of a static point ``p_ned_m`` (relative) to the path the follower will fly.

    The path: from ``v_now`` toward ``v_cmd`` as PX4's velocity loop takes it (first order,
    :data:`PX4_VEL_TAU_S`), over :data:`GUARD_HORIZON_S`. Returns the distance (m; inf when the path
    moves away from the point from the start: behind, or already passed) and the vector from the path's
    nearest point to the point (NED, m). Why a path, not the command's straight ray: the command's
    direction swings by 10 deg or more with the lateral corrections, and a ray 4 m long swings 0.7 m with
    it, onto a pole the follower then flies past 0.8 m away.
    """
    p = np.asarray(p_ned_m, dtype=np.float64)
    v0 = np.asarray(v_now_ned_m_s, dtype=np.float64)
    vc = np.asarray(v_cmd_ned_m_s, dtype=np.float64)
    disp = np.outer(_GUARD_T_S, vc) + np.outer(_GUARD_LAG_S, v0 - vc)
    q = p - disp
    d = np.linalg.norm(q, axis=1)
    k = int(np.argmin(d))
    if k == 0:
        return math.inf, q[0]
    return float(d[k]), q[k]


def on_course(p_ned_m: Vec3, v_ned_m_s: Vec3, corridor_m: float) -> bool:
    """Whether a static point ``p_ned_m`` (relative, m) lies ahead, within ``corridor_m`` of the path.

    The path is the straight line along ``v_ned_m_s``: what the follower would hit, not what it passes beside.
    """
    v = np.asarray(v_ned_m_s, dtype=np.float64)
    speed = float(np.linalg.norm(v))
    if speed < 1e-3:
        return False
    p = np.asarray(p_ned_m, dtype=np.float64)
    along = float(np.dot(p, v)) / speed
    if along <= 0.0:
        return False
    perp_sq = float(np.dot(p, p)) - along * along
    return perp_sq < corridor_m * corridor_m


def velocity_ned_setpoint(v_ned_m_s: Vec3T, yaw_rad: float) -> VelocityNedSetpoint:
    """A NED velocity setpoint (used where an absolute yaw is wanted, e.g. landing straight down)."""
    return VelocityNedSetpoint(v_ned_m_s=v_ned_m_s, yaw_rad=yaw_rad)
