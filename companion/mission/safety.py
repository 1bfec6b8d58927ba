"""Hard limits that every setpoint passes through (pure functions, NED, SI units).

The separation, altitude and geofence limits are *barriers*: the speed allowed toward a boundary shrinks as
``sqrt(2 a d)`` with the distance ``d`` left, so the vehicle can always brake before it, and inside the
boundary the allowed speed turns into a push back out. Applied after the formation law, so no gain setting
can fly the follower into the leader.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.config import SafetyConfig
from companion.kernel.frames import Vec3

G_M_S2 = 9.80665

#: Speed at which the follower is pushed back out when already inside a boundary, per metre inside (1/s).
PUSH_GAIN_1_S = 1.0


@dataclass(frozen=True, slots=True)
class SafetyLimits:
    """The configured limits plus the braking deceleration the barriers assume."""

    max_speed_m_s: float
    max_vertical_speed_m_s: float
    max_tilt_rad: float
    min_altitude_m: float
    max_altitude_m: float
    min_separation_m: float
    geofence_radius_m: float
    #: Deceleration the barriers count on: half of what the tilt limit allows, for margin, m/s^2.
    brake_m_s2: float
    #: How long the vehicle keeps closing after a new setpoint before it brakes, s: the separation barrier
    #: leaves room for it (``safety.separation_response_s``; see :class:`companion.config.SafetyConfig`).
    response_s: float = 1.0
    #: The depth guard holds off only what lies within this of the path ahead, m
    #: (``safety.depth_guard_corridor_m``).
    corridor_m: float = 0.8
    #: Nearer than this to the path the follower would hit it: brake; between this and ``corridor_m``,
    #: slide past (``safety.depth_guard_hit_radius_m``).
    hit_radius_m: float = 0.35

    @classmethod
    def from_config(cls, cfg: SafetyConfig, max_accel_m_s2: float) -> SafetyLimits:
        tilt_rad = math.radians(cfg.max_tilt_deg)
        brake = 0.5 * min(max_accel_m_s2, G_M_S2 * math.tan(tilt_rad))
        return cls(
            max_speed_m_s=cfg.max_speed_m_s,
            max_vertical_speed_m_s=cfg.max_vertical_speed_m_s,
            max_tilt_rad=tilt_rad,
            min_altitude_m=cfg.min_altitude_m,
            max_altitude_m=cfg.max_altitude_m,
            min_separation_m=cfg.min_separation_m,
            geofence_radius_m=cfg.geofence_radius_m,
            brake_m_s2=brake,
            response_s=cfg.separation_response_s,
            corridor_m=cfg.depth_guard_corridor_m,
            hit_radius_m=cfg.depth_guard_hit_radius_m,
        )

    @property
    def max_horizontal_accel_m_s2(self) -> float:
        """Horizontal acceleration a tilt of ``max_tilt_rad`` gives at hover thrust."""
        return G_M_S2 * math.tan(self.max_tilt_rad)


def barrier_speed_m_s(distance_left_m: float, brake_m_s2: float) -> float:
    """Largest speed toward a boundary ``distance_left_m`` away that can still stop before it.

    Negative inside the boundary: then the follower must move away at ``PUSH_GAIN_1_S`` per metre.
    """
    if distance_left_m >= 0.0:
        return math.sqrt(2.0 * brake_m_s2 * distance_left_m)
    return PUSH_GAIN_1_S * distance_left_m


def clamp_speed(v_ned_m_s: Vec3, lim: SafetyLimits) -> Vec3:
    """Scale the horizontal part to ``max_speed`` and clip the vertical part to ``max_vertical_speed``.

    A component that is not a finite number becomes 0 (no speed along it): NaN passes every comparison,
    so without this it would reach the setpoint unclipped.
    """
    out = np.array(v_ned_m_s, dtype=np.float64)
    out[~np.isfinite(out)] = 0.0
    h = math.hypot(out[0], out[1])
    if h > lim.max_speed_m_s:
        out[:2] *= lim.max_speed_m_s / h
    out[2] = float(np.clip(out[2], -lim.max_vertical_speed_m_s, lim.max_vertical_speed_m_s))
    return out


def separation_limit(
    v_ned_m_s: Vec3,
    p_ned_rel_m: Vec3,
    v_ned_leader_m_s: Vec3 | None,
    lim: SafetyLimits,
    v_follower_ned_m_s: Vec3 | None = None,
) -> Vec3:
    """Remove any closing speed toward the leader beyond what the separation barrier allows.

    ``p_ned_rel_m`` is leader minus follower. The closing speed is the follower's velocity toward the leader
    minus the leader's own velocity along the line of sight (taken as zero when unknown). With the
    follower's actual velocity, the distance it closes before it answers the setpoint (``response_s``) is
    taken off the braking distance: a barrier on the setpoint alone let a follower closing at 1.8 m/s come
    within 1.5 m of the leader (network circle run, after a coast on a wrong prediction).
    """
    d = float(np.linalg.norm(p_ned_rel_m))
    if d < 1e-6:
        return np.array(v_ned_m_s, dtype=np.float64)
    u = np.asarray(p_ned_rel_m, dtype=np.float64) / d
    v = np.array(v_ned_m_s, dtype=np.float64)
    leader_along = float(np.dot(v_ned_leader_m_s, u)) if v_ned_leader_m_s is not None else 0.0
    closing = float(np.dot(v, u)) - leader_along
    gap_m = d - lim.min_separation_m
    if v_follower_ned_m_s is not None:
        closing_now = float(np.dot(v_follower_ned_m_s, u)) - leader_along
        if closing_now > 0.0:
            gap_m -= closing_now * lim.response_s
    allowed = barrier_speed_m_s(gap_m, lim.brake_m_s2)
    if closing > allowed:
        v -= (closing - allowed) * u
    return v


def separation_limit_accel(
    a_ned_m_s2: Vec3, p_ned_rel_m: Vec3, v_ned_rel_m_s: Vec3, lim: SafetyLimits, gain_1_s: float = 2.0
) -> Vec3:
    """The separation barrier for attitude control: brake when closing faster than the barrier allows.

    Works on relative quantities only (no GPS needed): the closing speed is ``-v_rel . u``. When it exceeds
    the barrier speed, the acceleration toward the leader is replaced by a braking one proportional to the
    excess.
    """
    d = float(np.linalg.norm(p_ned_rel_m))
    a = np.array(a_ned_m_s2, dtype=np.float64)
    if d < 1e-6:
        return a
    u = np.asarray(p_ned_rel_m, dtype=np.float64) / d
    closing = -float(np.dot(v_ned_rel_m_s, u))
    allowed = barrier_speed_m_s(d - lim.min_separation_m, lim.brake_m_s2)
    excess = closing - allowed
    along = float(np.dot(a, u))
    if excess > 0.0:
        target = -gain_1_s * excess
        if along > target:
            a += (target - along) * u
    return a


def altitude_limit(v_down_m_s: float, alt_rel_m: float, lim: SafetyLimits) -> float:
    """Limit the vertical velocity (NED down) so the altitude stays within [min, max] altitude."""
    if not math.isfinite(alt_rel_m):
        return v_down_m_s
    max_down = barrier_speed_m_s(alt_rel_m - lim.min_altitude_m, lim.brake_m_s2)
    max_up = barrier_speed_m_s(lim.max_altitude_m - alt_rel_m, lim.brake_m_s2)
    return float(np.clip(v_down_m_s, -max_up, max_down))


def geofence_limit(v_ned_m_s: Vec3, p_ned_m: Vec3 | None, lim: SafetyLimits) -> Vec3:
    """Limit the outward horizontal speed near the geofence circle around home (needs a valid position)."""
    v = np.array(v_ned_m_s, dtype=np.float64)
    if p_ned_m is None:
        return v
    r = math.hypot(float(p_ned_m[0]), float(p_ned_m[1]))
    if r < 1e-6:
        return v
    out = np.array([p_ned_m[0] / r, p_ned_m[1] / r, 0.0])
    outward = float(np.dot(v, out))
    allowed = barrier_speed_m_s(lim.geofence_radius_m - r, lim.brake_m_s2)
    if outward > allowed:
        v -= (outward - allowed) * out
    return v


def clamp_horizontal_accel(a_ned_m_s2: Vec3, lim: SafetyLimits) -> Vec3:
    """Scale the horizontal acceleration so the tilt it needs stays within ``max_tilt``."""
    a = np.array(a_ned_m_s2, dtype=np.float64)
    h = math.hypot(a[0], a[1])
    a_max = lim.max_horizontal_accel_m_s2
    if h > a_max:
        a[:2] *= a_max / h
    return a
