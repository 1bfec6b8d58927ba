"""The formation's geometry: the slot, the error against it, and the heading frame; pure.

The slot is the leader's desired position in the follower's level heading frame (forward, right, down),
from ``FormationConfig.offset_cam_m`` (x right, y down, z forward). :func:`slot_error` splits the relative
state the way :class:`~companion.mission.formation.FormationLaw` uses it: a radial and a vertical error,
and the yaw that keeps the leader at the slot's bearing. :class:`FollowerState` is what the law reads of
the vehicle.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.config import FormationConfig
from companion.kernel.frames import Vec3, ned_to_heading, wrap_pi
from companion.mission.safety import G_M_S2
from companion.mission.types import AirframeDrag

#: Below this horizontal range the line-of-sight bearing is meaningless (m).
MIN_BEARING_RANGE_M = 0.5


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
    #: The airframe's drag as learnt in flight; None before (the law then feeds no drag forward).
    airframe: AirframeDrag | None = None


def tilt_from_accel(a_ned_m_s2: Vec3, yaw_rad: float) -> tuple[float, float]:
    """Roll and pitch (rad) that give a horizontal acceleration ``a_ned`` at constant altitude."""
    a_h = ned_to_heading(a_ned_m_s2, yaw_rad)
    pitch = -math.atan2(a_h[0], G_M_S2)
    roll = math.atan2(a_h[1] * math.cos(pitch), G_M_S2)
    return roll, pitch


def accel_from_tilt(roll_rad: float, pitch_rad: float) -> tuple[float, float]:
    """Forward and right acceleration (heading frame, m/s^2) a tilt gives level: tilt_from_accel inverted."""
    c = math.cos(pitch_rad)
    return -G_M_S2 * math.tan(pitch_rad), G_M_S2 * math.tan(roll_rad) / (c if abs(c) > 0.2 else 0.2)


def faded(a_m_s2: Vec3, fade_m_s2: float) -> Vec3:
    """``a`` scaled by ``|a|^2 / (|a|^2 + fade^2)``: kept where it stands out of the noise, faded below.

    The leader's acceleration, differentiated from 15 Hz positions, wanders by +-0.5-1 m/s^2 while the
    leader hovers; led on in full (0.7 s of it) that commanded up to 0.7 m/s of jitter. A start's
    1-1.2 m/s^2 keeps 80-85 % of its lead at ``fade`` 0.5. ``fade`` 0 keeps ``a`` as it is.
    """
    if fade_m_s2 <= 0.0:
        return a_m_s2
    n2 = float(np.dot(a_m_s2, a_m_s2))
    out: Vec3 = a_m_s2 * (n2 / (n2 + fade_m_s2 * fade_m_s2))
    return out


def accel_lead(a_h_m_s2: Vec3, err: SlotError, cfg: FormationConfig) -> Vec3:
    """The leader's horizontal acceleration led as a velocity (m/s, NED x-y): ``leader_accel_ff_s`` of it.

    Faded below ``leader_accel_fade_m_s2``; its part along the line of sight fades out over
    ``leader_accel_yield_m`` of range error past ``leader_accel_yield_dead_m`` while that part pushes the
    range error the way it is already growing. A speed-up's lead then comes in whole (the follower falls
    behind and the lead closes it) and cannot carry the follower past its slot once the leader stops
    speeding up and the estimate has not seen it yet.
    """
    lead = cfg.leader_accel_ff_s * faded(a_h_m_s2, cfg.leader_accel_fade_m_s2)
    e_m, e_rate = err.e_range_m, err.e_range_rate_m_s
    if cfg.leader_accel_yield_m <= 0.0 or e_m * e_rate <= 0.0:
        return lead
    u = err.u_los[:2]
    along = float(lead[0] * u[0] + lead[1] * u[1])
    if along * e_m >= 0.0:  # the lead closes the error
        return lead
    cut = min(1.0, max(0.0, abs(e_m) - cfg.leader_accel_yield_dead_m) / cfg.leader_accel_yield_m)
    out: Vec3 = lead - cut * along * np.asarray(u, dtype=np.float64)
    return out


#: The trailing term fades in over this much leader speed above ``trail_min_speed_m_s``, m/s.
TRAIL_FADE_M_S = 0.5


def trail_velocity(err: SlotError, range_h_m: float, v_leader_ned_m_s: Vec3, cfg: FormationConfig) -> Vec3:
    """The velocity across the line of sight (NED m/s) that brings a lone follower behind its leader.

    The slot fixes the range and the bearing in the follower's frame, not where round the leader the
    follower sits. Left free, a turning leader (``circle``) ends beside and then in front of the follower,
    which then flies backwards at the leader's speed, nose up: a front camera loses the leader below its
    image on a draggy airframe. This flies out the angle ``d`` between the line of sight and the leader's
    course at ``trail_gain_1_s``: ``k r sin d`` across the line of sight (the full cap once ``d`` is past
    90 deg), capped at ``trail_max_m_s`` and faded in with the leader's speed.
    """
    v = np.asarray(v_leader_ned_m_s, dtype=np.float64)
    speed = math.hypot(v[0], v[1])
    w = min(1.0, max(0.0, (speed - cfg.trail_min_speed_m_s) / TRAIL_FADE_M_S))
    out = np.zeros(3)
    if w <= 0.0 or cfg.trail_gain_1_s <= 0.0 or cfg.trail_max_m_s <= 0.0:
        return out
    d = wrap_pi(err.bearing_rad - math.atan2(v[1], v[0]))
    past = min(max(abs(d) - math.radians(cfg.trail_free_deg), 0.0), 0.5 * math.pi)
    pull = math.copysign(math.sin(past), d)
    cross = float(np.clip(cfg.trail_gain_1_s * range_h_m * pull, -cfg.trail_max_m_s, cfg.trail_max_m_s))
    # Right of the line of sight: moving that way turns the bearing to the leader down (anticlockwise).
    u = err.u_los
    out[0], out[1] = -u[1] * cross * w, u[0] * cross * w
    return out
