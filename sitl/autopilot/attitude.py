"""Attitude maths of the control cascade in plain floats: quaternions, headings, thrust to attitude.

Quaternions are (w, x, y, z) tuples, body -> NED (frames: NED world, FRD body). These run in the
simulator's control loops at the outer and physics rates, which is why they avoid numpy: a 3-vector
through numpy costs more than the arithmetic on it.
"""

from __future__ import annotations

import math

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
    # Body z = -thrust direction (plain floats throughout: this runs at the outer rate per vehicle).
    if thrust < 1e-06:
        m02, m12, m22 = 0.0, 0.0, 1.0
    else:
        m02, m12, m22 = -thr_n / thrust, -thr_e / thrust, -thr_d / thrust
    # y axis of the heading-only frame, then body x = y_c x body z.
    ycx, ycy = -math.sin(yaw_rad), math.cos(yaw_rad)
    m00, m10, m20 = ycy * m22, -ycx * m22, ycx * m12 - ycy * m02
    if m22 < 0.0:
        m00, m10, m20 = -m00, -m10, -m20
    n = math.sqrt(m00 * m00 + m10 * m10 + m20 * m20)
    if n < 1e-06:
        m00, m10, m20 = 1.0, 0.0, 0.0
    else:
        m00, m10, m20 = m00 / n, m10 / n, m20 / n
    # Body y = body z x body x.
    m01, m11, m21 = m12 * m20 - m22 * m10, m22 * m00 - m02 * m20, m02 * m10 - m12 * m00
    # Rotation matrix columns bx, by, bz -> quaternion (Shepperd).
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
