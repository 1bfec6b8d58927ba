"""Passing the depth guard's obstacle: the path the follower will fly, and the command that clears it; pure.

The obstacle is static (nothing is known of its motion), relative NED. The path is PX4's velocity loop
taking the follower from its velocity now toward the command (first order, :data:`PX4_VEL_TAU_S`), over
:data:`GUARD_HORIZON_S`: what comes within ``corridor_m`` of it is passed beside, what comes within
``hit_radius_m`` is held off by the separation barrier like the leader.
"""

from __future__ import annotations

import math

import numpy as np

from companion.kernel.frames import Vec3
from companion.mission.geometry import FollowerState
from companion.mission.safety import SafetyLimits, separation_limit

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


def pass_static(v: Vec3, obstacle_ned_m: Vec3, follower: FollowerState, lim: SafetyLimits) -> Vec3:
    """The depth guard's obstacle (static, relative NED): brake for it ahead, slide past it beside.

    On the path the follower will fly (:func:`path_approach`): nearer than ``hit_radius_m``, the
    separation barrier holds it off like the leader; nearer than ``corridor_m``, the command loses any
    part toward the obstacle's side and gains a push away of ``STATIC_SLIDE_GAIN_1_S`` times the
    shortfall; farther, nothing.
    """
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
