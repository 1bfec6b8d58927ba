"""Offboard setpoint messages -> what PX4 would do with them (``mavlink_receiver.cpp``), pure.

* SET_POSITION_TARGET_LOCAL_NED: frames LOCAL_NED (1) and BODY_NED (8) only; masked fields become
  NaN; a group (position, velocity, acceleration) counts if any component is finite; BODY_NED rotates
  velocity by the current yaw and acceleration by the full attitude and ignores position; FORCE with
  acceleration is refused; no finite group -> "invalid". No ACK is ever sent for setpoints.
* SET_POSITION_TARGET_GLOBAL_INT: GLOBAL_INT (5), GLOBAL_RELATIVE_ALT_INT (6), GLOBAL_TERRAIN_ALT_INT
  (11; terrain taken as home altitude), positions converted to the local frame.
* SET_ATTITUDE_TARGET: an attitude quaternion (+ thrust), or body rates (+ thrust) when the attitude
  is masked; a non-finite or degenerate quaternion is dropped.

Each parse returns an :class:`OffboardSetpoint` (what offboard_control_mode + the setpoint carry) or a
refusal text PX4 would log.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import Enum
from typing import Any

from sitl.autopilot.attitude import Quat, quat_normalized
from sitl.autopilot.control import NAN, TrajectorySetpoint
from sitl.physics.geo import LocalProjection

FRAME_GLOBAL_INT = 5
FRAME_GLOBAL_RELATIVE_ALT_INT = 6
FRAME_LOCAL_NED = 1
FRAME_BODY_NED = 8
FRAME_GLOBAL_TERRAIN_ALT_INT = 11

# POSITION_TARGET_TYPEMASK bits (1 = ignore).
MASK_X, MASK_Y, MASK_Z = 1, 2, 4
MASK_VX, MASK_VY, MASK_VZ = 8, 16, 32
MASK_AX, MASK_AY, MASK_AZ = 64, 128, 256
MASK_FORCE = 512
MASK_YAW, MASK_YAW_RATE = 1024, 2048

# ATTITUDE_TARGET_TYPEMASK bits.
ATT_MASK_ROLL_RATE, ATT_MASK_PITCH_RATE, ATT_MASK_YAW_RATE = 1, 2, 4
ATT_MASK_THRUST_BODY_SET = 32
ATT_MASK_THROTTLE = 64
ATT_MASK_ATTITUDE = 128


class SetpointKind(Enum):
    """Which controller an offboard setpoint drives."""

    TRAJECTORY = "trajectory"
    ATTITUDE = "attitude"
    RATES = "rates"


@dataclass(slots=True)
class OffboardSetpoint:
    """A parsed setpoint and the estimates it needs (``offboard_control_mode`` flags)."""

    kind: SetpointKind
    t_s: float
    position: bool = False
    velocity: bool = False
    acceleration: bool = False
    trajectory: TrajectorySetpoint = field(default_factory=TrajectorySetpoint)
    q_sp: Quat = (1.0, 0.0, 0.0, 0.0)
    rates_sp: tuple[float, float, float] = (NAN, NAN, NAN)
    thrust: float = 0.0
    yawspeed_rad_s: float = NAN
    #: For trajectories: PX4's position-controller input check, done once on arrival.
    valid: bool = True


def _fin(x: Any) -> float:
    """A float from a message field, NaN unless finite (inf and absurd types count as 'not given')."""
    try:
        v = float(x)
    except (TypeError, ValueError):
        return NAN
    return v if math.isfinite(v) else NAN


def parse_local_ned(msg: Any, t_s: float, yaw_rad: float, q_body: Quat) -> OffboardSetpoint | str:
    """SET_POSITION_TARGET_LOCAL_NED -> setpoint, or PX4's refusal text."""
    frame = int(msg.coordinate_frame)
    mask = int(msg.type_mask)
    if frame not in (FRAME_LOCAL_NED, FRAME_BODY_NED):
        return f"SET_POSITION_TARGET_LOCAL_NED coordinate frame {frame} unsupported"
    px = NAN if mask & MASK_X else _fin(msg.x)
    py = NAN if mask & MASK_Y else _fin(msg.y)
    pz = NAN if mask & MASK_Z else _fin(msg.z)
    vx = NAN if mask & MASK_VX else _fin(msg.vx)
    vy = NAN if mask & MASK_VY else _fin(msg.vy)
    vz = NAN if mask & MASK_VZ else _fin(msg.vz)
    ax = NAN if mask & MASK_AX else _fin(msg.afx)
    ay = NAN if mask & MASK_AY else _fin(msg.afy)
    az = NAN if mask & MASK_AZ else _fin(msg.afz)
    if frame == FRAME_BODY_NED:
        px = py = pz = NAN
        c, s = math.cos(yaw_rad), math.sin(yaw_rad)
        if not math.isnan(vx) and not math.isnan(vy):
            vx, vy = c * vx - s * vy, s * vx + c * vy
        else:
            vx = vy = NAN
        if not math.isnan(ax) and not math.isnan(ay) and not math.isnan(az):
            ax, ay, az = _rotate(q_body, ax, ay, az)
        else:
            ax = ay = az = NAN
    yaw = NAN if mask & MASK_YAW else _fin(msg.yaw)
    yawspeed = NAN if mask & MASK_YAW_RATE else _fin(msg.yaw_rate)
    return _trajectory(
        t_s, (px, py, pz), (vx, vy, vz), (ax, ay, az), yaw=yaw, yawspeed=yawspeed, mask=mask, name="LOCAL_NED"
    )


def parse_global_int(
    msg: Any, t_s: float, origin: LocalProjection | None, home_alt_m: float
) -> OffboardSetpoint | str:
    """SET_POSITION_TARGET_GLOBAL_INT -> setpoint (needs the EKF origin), or a refusal text."""
    frame = int(msg.coordinate_frame)
    mask = int(msg.type_mask)
    if frame not in (FRAME_GLOBAL_INT, FRAME_GLOBAL_RELATIVE_ALT_INT, FRAME_GLOBAL_TERRAIN_ALT_INT):
        return f"SET_POSITION_TARGET_GLOBAL_INT coordinate frame {frame} unsupported"
    px = py = pz = NAN
    if not mask & (MASK_X | MASK_Y | MASK_Z):
        if origin is None:
            return "SET_POSITION_TARGET_GLOBAL_INT: no global position reference"
        lat = _fin(msg.lat_int) * 1e-7
        lon = _fin(msg.lon_int) * 1e-7
        alt = _fin(msg.alt)
        if math.isnan(lat + lon + alt) or abs(lat) > 90.0 or abs(lon) > 180.0:
            return "SET_POSITION_TARGET_GLOBAL_INT invalid"
        if frame != FRAME_GLOBAL_INT:
            alt += home_alt_m
        px, py, pz = origin.to_ned(lat, lon, alt)
    vx = NAN if mask & MASK_VX else _fin(msg.vx)
    vy = NAN if mask & MASK_VY else _fin(msg.vy)
    vz = NAN if mask & MASK_VZ else _fin(msg.vz)
    ax = NAN if mask & MASK_AX else _fin(msg.afx)
    ay = NAN if mask & MASK_AY else _fin(msg.afy)
    az = NAN if mask & MASK_AZ else _fin(msg.afz)
    yaw = NAN if mask & MASK_YAW else _fin(msg.yaw)
    yawspeed = NAN if mask & MASK_YAW_RATE else _fin(msg.yaw_rate)
    return _trajectory(
        t_s,
        (px, py, pz),
        (vx, vy, vz),
        (ax, ay, az),
        yaw=yaw,
        yawspeed=yawspeed,
        mask=mask,
        name="GLOBAL_INT",
    )


def _trajectory(
    t_s: float,
    pos: tuple[float, float, float],
    vel: tuple[float, float, float],
    acc: tuple[float, float, float],
    *,
    yaw: float,
    yawspeed: float,
    mask: int,
    name: str,
) -> OffboardSetpoint | str:
    has_pos = any(not math.isnan(v) for v in pos)
    has_vel = any(not math.isnan(v) for v in vel)
    has_acc = any(not math.isnan(v) for v in acc)
    if has_acc and mask & MASK_FORCE:
        return f"SET_POSITION_TARGET_{name} force not supported"
    if not (has_pos or has_vel or has_acc):
        return f"SET_POSITION_TARGET_{name} invalid"
    sp = OffboardSetpoint(
        kind=SetpointKind.TRAJECTORY, t_s=t_s, position=has_pos, velocity=has_vel, acceleration=has_acc
    )
    sp.trajectory.set(pos=pos, vel=vel, acc=acc, yaw=yaw, yawspeed=yawspeed)
    sp.valid = sp.trajectory.is_valid()
    return sp


def parse_attitude_target(msg: Any, t_s: float) -> OffboardSetpoint | str | None:
    """SET_ATTITUDE_TARGET -> setpoint; None when it carries nothing PX4 would use."""
    mask = int(msg.type_mask)
    thrust = NAN
    if not mask & ATT_MASK_THROTTLE:
        if mask & ATT_MASK_THRUST_BODY_SET:
            tb = getattr(msg, "thrust_body", None) or (0.0, 0.0, 0.0)
            thrust = -_fin(tb[2]) if len(tb) > 2 else NAN
        else:
            thrust = _fin(msg.thrust)
    thrust = min(1.0, max(0.0, thrust)) if not math.isnan(thrust) else NAN
    if not mask & ATT_MASK_ATTITUDE:
        raw = tuple(_fin(c) for c in msg.q)
        if len(raw) != 4:
            return "SET_ATTITUDE_TARGET invalid"
        q = quat_normalized((raw[0], raw[1], raw[2], raw[3]))
        if q is None:
            return "SET_ATTITUDE_TARGET invalid"
        yawspeed = NAN if mask & ATT_MASK_YAW_RATE else _fin(msg.body_yaw_rate)
        return OffboardSetpoint(
            kind=SetpointKind.ATTITUDE,
            t_s=t_s,
            q_sp=q,
            thrust=thrust if not math.isnan(thrust) else 0.0,
            yawspeed_rad_s=yawspeed,
        )
    rates = (
        NAN if mask & ATT_MASK_ROLL_RATE else _fin(msg.body_roll_rate),
        NAN if mask & ATT_MASK_PITCH_RATE else _fin(msg.body_pitch_rate),
        NAN if mask & ATT_MASK_YAW_RATE else _fin(msg.body_yaw_rate),
    )
    if mask & (ATT_MASK_ROLL_RATE | ATT_MASK_PITCH_RATE | ATT_MASK_YAW_RATE) == 7:
        return None
    return OffboardSetpoint(
        kind=SetpointKind.RATES, t_s=t_s, rates_sp=rates, thrust=thrust if not math.isnan(thrust) else 0.0
    )


def _rotate(q: Quat, x: float, y: float, z: float) -> tuple[float, float, float]:
    """Rotate a body vector into NED with the body -> NED quaternion ``q``."""
    w, qx, qy, qz = q
    # v' = v + 2w (u x v) + 2 u x (u x v), u = (qx, qy, qz)
    cx, cy, cz = qy * z - qz * y, qz * x - qx * z, qx * y - qy * x
    return (
        x + 2.0 * (w * cx + qy * cz - qz * cy),
        y + 2.0 * (w * cy + qz * cx - qx * cz),
        z + 2.0 * (w * cz + qx * cy - qy * cx),
    )
