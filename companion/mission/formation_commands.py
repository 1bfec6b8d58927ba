"""What the formation law returns, and the small numeric pieces it is built from (pure)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.kernel.flight import AttitudeSetpoint, Vec3T, VelocityBodySetpoint, VelocityNedSetpoint
from companion.kernel.frames import Vec3, wrap_pi
from companion.mission.geometry import FollowerState, SlotError
from companion.mission.plan_slot import NeighbourNow, SlotTarget
from companion.mission.safety import SafetyLimits, altitude_limit, geofence_limit, separation_limit
from companion.mission.static_pass import pass_static

#: The error reported with a hover that replaced a non-finite command (nothing is known of the slot).
NO_ERROR = SlotError(
    u_los=np.zeros(3),
    bearing_rad=0.0,
    bearing_rate_rad_s=0.0,
    e_range_m=0.0,
    e_range_rate_m_s=0.0,
    e_down_m=0.0,
    yaw_des_rad=0.0,
    error_ned_m=np.zeros(3),
)


def all_finite(*values: object) -> bool:
    """Are all these inputs (numbers, vectors, follower states, slots, neighbours; None skipped) finite?"""
    for v in values:
        if v is None:
            continue
        if isinstance(v, FollowerState):
            # alt_rel_m may be NaN: "height unknown", which the altitude band handles by standing aside.
            if not all_finite(v.yaw_rad, v.v_ned_m_s, v.v_down_m_s, v.p_ned_m, v.roll_rad, v.pitch_rad):
                return False
        elif isinstance(v, SlotTarget):
            if not all_finite(v.p_ned_rel_m, v.v_ned_rel_m_s):
                return False
        elif isinstance(v, NeighbourNow):
            if not all_finite(v.p_ned_rel_m, v.v_ned_m_s, v.v_ned_rel_m_s):
                return False
        elif isinstance(v, list):
            if not all_finite(*v):
                return False
        elif not np.all(np.isfinite(np.asarray(v, dtype=np.float64))):
            return False
    return True


@dataclass(frozen=True, slots=True)
class VelocityCommand:
    """The velocity law's output: the setpoint to send and what went into it."""

    setpoint: VelocityBodySetpoint | VelocityNedSetpoint
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


def clamp_norm(a: Vec3, limit: float) -> Vec3:
    """``a`` scaled down to norm ``limit`` if longer."""
    n = float(np.linalg.norm(a))
    return a * (limit / n) if n > limit else a


def integrate(value: float, rate: float, dt_s: float, limit: float, saturated_same_sign: bool) -> float:
    """Bounded integral with conditional integration (no growth while the output saturates that way)."""
    if saturated_same_sign:
        return value
    return float(np.clip(value + rate * dt_s, -limit, limit))


def low_passed_rate(a_prev: Vec3, v: Vec3, v_prev: Vec3, dt: float, *, tau_s: float, limit: float) -> Vec3:
    """The low-passed (``tau_s``) derivative of ``v``, its norm capped at ``limit``; one step of ``dt``."""
    k = dt / (tau_s + dt)
    return clamp_norm(a_prev + k * ((v - v_prev) / dt - a_prev), limit)


def bounded_velocity(  # noqa: PLR0917 (the law's state passed in, so this stays pure)
    v: Vec3,
    p_ned_rel_m: Vec3,
    v_leader: Vec3 | None,
    follower: FollowerState,
    limits: SafetyLimits,
    neighbours: list[NeighbourNow],
    obstacle_ned_m: Vec3 | None = None,
) -> Vec3:
    """The velocity laws' last limits, in precedence order: separation, geofence, altitude band.

    Separation holds against the leader (with its velocity), the neighbours (with theirs) and the depth
    guard's obstacle (static: nothing is known of its motion).
    """
    v = separation_limit(v, p_ned_rel_m, v_leader, limits, follower.v_ned_m_s)
    for n in neighbours:
        v = separation_limit(v, n.p_ned_rel_m, n.v_ned_m_s, limits, follower.v_ned_m_s)
    if obstacle_ned_m is not None:
        v = pass_static(v, np.asarray(obstacle_ned_m, dtype=np.float64), follower, limits)
    v = geofence_limit(v, follower.p_ned_m, limits)
    v[2] = altitude_limit(float(v[2]), follower.alt_rel_m, limits)
    return v


def ned_with_feedforward(
    v_ned_m_s: Vec3,
    a_leader_ned_m_s2: Vec3,
    follower: FollowerState,
    yaw_lead_rad: float,
    max_accel_m_s2: float,
) -> VelocityNedSetpoint:
    """A velocity setpoint in NED with the acceleration PX4 should add to its velocity loop.

    PX4's velocity loop is a PID with no model of drag: at a new speed its integrator must first build up
    the tilt the drag asks for (on SIH's 1 /s drag the velocity trailed the command by about a second and
    1.3 m/s RMS in ``circle``). The feed-forward is the leader's acceleration (the law's estimate) plus the
    thrust the learnt drag needs at the commanded velocity (``drag * v - push``), horizontal, at most
    ``max_accel_m_s2`` plus the drag's part. The yaw is absolute: the heading now plus ``yaw_lead_rad``
    (PX4 turns at MC_YAW_P times the error, so a lead of ``rate / MC_YAW_P`` flies that rate).
    """
    a = np.zeros(3)
    a[:2] = np.asarray(a_leader_ned_m_s2, dtype=np.float64)[:2]
    n = math.hypot(a[0], a[1])
    if n > max_accel_m_s2:
        a[:2] *= max_accel_m_s2 / n
    drag = follower.airframe
    if drag is not None:
        a[0] += drag.drag_per_s * float(v_ned_m_s[0]) - drag.push_ne_m_s2[0]
        a[1] += drag.drag_per_s * float(v_ned_m_s[1]) - drag.push_ne_m_s2[1]
    if not np.all(np.isfinite(a)):
        a = np.zeros(3)
    return VelocityNedSetpoint(
        v_ned_m_s=(float(v_ned_m_s[0]), float(v_ned_m_s[1]), float(v_ned_m_s[2])),
        yaw_rad=wrap_pi(follower.yaw_rad + yaw_lead_rad),
        a_ned_m_s2=(float(a[0]), float(a[1]), 0.0),
    )


def slewed(v: Vec3, v_prev: Vec3, step_s: float, slew_h_m_s2: float, slew_z_m_s2: float) -> Vec3:
    """``v`` moved from ``v_prev`` by at most ``slew * step_s``: the horizontal and the vertical apart.

    Only the horizontal follows the leader's speed changes at a fast slew; a fast vertical slew swung the
    height under a lossy link (measured in lockstep).
    """
    dv = v - v_prev
    n_h = math.hypot(dv[0], dv[1])
    max_h = slew_h_m_s2 * step_s
    if n_h > max_h:
        dv[:2] *= max_h / n_h
    max_z = slew_z_m_s2 * step_s
    dv[2] = min(max(dv[2], -max_z), max_z)
    out: Vec3 = v_prev + dv
    return out
