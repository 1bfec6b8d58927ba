"""Frames, rotations and the naming rules, written down once.

Frames:
    * camera: x right, y down, z forward (the optical axis), origin at the colour sensor.
    * body: FRD (x forward, y right, z down), origin at the centre of mass.
    * world: local NED (x north, y east, z down), origin at the home position.

Names:
    * ``p_<frame>_<what>_m``: position of ``what`` expressed in ``frame`` (``p_cam_leader_m``).
    * ``v_<frame>_m_s`` a velocity, ``R_<to>_<from>`` a rotation matrix that maps vectors in ``from``
      into ``to`` (``v_body = R_body_cam @ v_cam``), ``q_<to>_<from>`` the same rotation as a unit
      quaternion in (w, x, y, z) order, as MAVLink sends it.
    * Angles carry ``_rad`` or ``_deg``; yaw is about NED down: zero north, positive clockwise from above.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

Vec3 = NDArray[np.float64]
Mat3 = NDArray[np.float64]

#: Maps camera axes (x right, y down, z forward) into body FRD for a camera looking along body x.
R_BODY_CAM_LEVEL: Mat3 = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def wrap_pi(angle_rad: float) -> float:
    """Wrap an angle into [-pi, pi)."""
    return (angle_rad + math.pi) % (2.0 * math.pi) - math.pi


def R_from_euler(roll_rad: float, pitch_rad: float, yaw_rad: float) -> Mat3:
    """Rotation body -> NED from aerospace ZYX Euler angles (yaw, then pitch, then roll)."""
    cr, sr = math.cos(roll_rad), math.sin(roll_rad)
    cp, sp = math.cos(pitch_rad), math.sin(pitch_rad)
    cy, sy = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array(
        [
            [cp * cy, sr * sp * cy - cr * sy, cr * sp * cy + sr * sy],
            [cp * sy, sr * sp * sy + cr * cy, cr * sp * sy - sr * cy],
            [-sp, sr * cp, cr * cp],
        ]
    )


def euler_from_R(R: Mat3) -> tuple[float, float, float]:
    """(roll, pitch, yaw) in rad of a body -> NED rotation (inverse of :func:`R_from_euler`)."""
    pitch = -math.asin(max(-1.0, min(1.0, float(R[2, 0]))))
    roll = math.atan2(float(R[2, 1]), float(R[2, 2]))
    yaw = math.atan2(float(R[1, 0]), float(R[0, 0]))
    return roll, pitch, yaw


def R_from_quat(q_wxyz: NDArray[np.float64] | tuple[float, float, float, float]) -> Mat3:
    """Rotation matrix of a unit quaternion (w, x, y, z); normalises to absorb float drift."""
    w, x, y, z = (float(c) for c in q_wxyz)
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if n == 0.0:
        raise ValueError("zero quaternion")
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def quat_from_R(R: Mat3) -> NDArray[np.float64]:
    """Unit quaternion (w, x, y, z) with w >= 0 of a rotation matrix (Shepperd's method)."""
    m = R
    tr = float(m[0, 0] + m[1, 1] + m[2, 2])
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif m[1, 1] > m[2, 2]:
        s = math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    arr = np.array(q, dtype=np.float64)
    arr /= np.linalg.norm(arr)
    return arr if arr[0] >= 0 else -arr


def quat_from_euler(roll_rad: float, pitch_rad: float, yaw_rad: float) -> NDArray[np.float64]:
    """Quaternion (w, x, y, z) of ZYX Euler angles."""
    return quat_from_R(R_from_euler(roll_rad, pitch_rad, yaw_rad))


def R_body_cam_from_mount(roll_deg: float = 0.0, pitch_deg: float = 0.0, yaw_deg: float = 0.0) -> Mat3:
    """Camera -> body rotation for a camera mounted with the given angles relative to body FRD.

    Zero angles give a camera looking straight ahead; positive pitch tilts it up (nose-up convention).
    """
    R_body_mount = R_from_euler(math.radians(roll_deg), math.radians(pitch_deg), math.radians(yaw_deg))
    return R_body_mount @ R_BODY_CAM_LEVEL


def ned_to_heading(v_ned: Vec3, yaw_rad: float) -> Vec3:
    """Rotate a NED vector into the heading frame (forward, right, down) of ``yaw_rad``."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array([c * v_ned[0] + s * v_ned[1], -s * v_ned[0] + c * v_ned[1], v_ned[2]])


def heading_to_ned(v_h: Vec3, yaw_rad: float) -> Vec3:
    """Inverse of :func:`ned_to_heading`."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array([c * v_h[0] - s * v_h[1], s * v_h[0] + c * v_h[1], v_h[2]])
