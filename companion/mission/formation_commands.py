"""What the formation law returns, and the small numeric pieces it is built from (pure)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from companion.kernel.flight import AttitudeSetpoint, Vec3T, VelocityBodySetpoint
from companion.kernel.frames import Vec3
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
