"""Camera -> body -> local NED, with the follower's attitude interpolated at each frame's timestamp.

A frame is exposed at ``stamp_s``; telemetry brings attitude samples at other times (50-250 Hz). The
:class:`AttitudeHistory` keeps recent samples and slerps between the two that bracket the frame, so a
yawing follower does not smear the leader's NED position by the yaw rate times the frame's latency.

The tracker works with the leader's position *relative to the follower*, expressed in NED axes
(``p_ned_rel_m = p_ned_leader - p_ned_follower``): attitude alone places it, so it survives GPS loss.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from companion.kernel.camera import MountConfig
from companion.kernel.frames import Mat3, R_body_cam_from_mount, R_from_quat, Vec3

Quat = NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class CameraGeometry:
    """The camera's mount on the follower: ``p_body = R_body_cam @ p_cam + t_body_cam_m``."""

    R_body_cam: Mat3
    #: Camera origin in body FRD, m.
    t_body_cam_m: Vec3

    @classmethod
    def from_mount(cls, mount: MountConfig) -> CameraGeometry:
        return cls(
            R_body_cam=R_body_cam_from_mount(mount.roll_deg, mount.pitch_deg, mount.yaw_deg),
            t_body_cam_m=np.array([mount.x_m, mount.y_m, mount.z_m], dtype=np.float64),
        )

    def cam_to_body(self, p_cam_m: Vec3) -> Vec3:
        """A point seen by the camera, in body FRD (origin at the follower's centre), m."""
        return self.R_body_cam @ p_cam_m + self.t_body_cam_m

    def body_to_cam(self, p_body_m: Vec3) -> Vec3:
        """A body-frame point in the camera frame, m."""
        return self.R_body_cam.T @ (p_body_m - self.t_body_cam_m)

    def R_ned_cam(self, R_ned_body: Mat3) -> Mat3:
        """Camera -> NED rotation for the follower's attitude ``R_ned_body``."""
        return R_ned_body @ self.R_body_cam

    def cam_to_ned_rel(self, p_cam_m: Vec3, R_ned_body: Mat3) -> Vec3:
        """A camera-frame point relative to the follower's centre, in NED axes, m."""
        return R_ned_body @ self.cam_to_body(p_cam_m)

    def ned_rel_to_cam(self, p_ned_rel_m: Vec3, R_ned_body: Mat3) -> Vec3:
        """Inverse of :meth:`cam_to_ned_rel`."""
        return self.body_to_cam(R_ned_body.T @ p_ned_rel_m)


def rotate_cov(R: Mat3, cov: Mat3) -> Mat3:
    """Covariance of ``R @ x`` given that of ``x``; re-symmetrised against float drift."""
    out = R @ cov @ R.T
    return 0.5 * (out + out.T)


def slerp(q0_wxyz: Quat, q1_wxyz: Quat, t: float) -> Quat:
    """Spherical interpolation between unit quaternions (shortest path), ``t`` in [0, 1]."""
    q1 = q1_wxyz
    dot = float(np.dot(q0_wxyz, q1))
    if dot < 0.0:  # q and -q are the same rotation: go the short way
        q1 = -q1
        dot = -dot
    if dot > 0.9995:  # nearly parallel: linear is exact to float precision and avoids 0/0
        q = q0_wxyz + t * (q1 - q0_wxyz)
        return q / np.linalg.norm(q)
    theta = math.acos(dot)
    s = math.sin(theta)
    return (math.sin((1.0 - t) * theta) * q0_wxyz + math.sin(t * theta) * q1) / s


class AttitudeHistory:
    """Recent follower attitudes (``q_ned_body``) from telemetry, looked up at frame timestamps.

    Fed in time order by the vehicle link; samples older than the newest are ignored. Lookups between
    two samples slerp; lookups up to ``max_extrapolation_s`` outside the held span take the nearest
    sample (no rate extrapolation: attitude telemetry is fast enough); farther ones return None.
    """

    def __init__(self, capacity: int = 512, max_extrapolation_s: float = 0.1) -> None:
        if capacity < 2:
            raise ValueError("capacity must be >= 2")
        self._capacity = capacity
        self._max_extrapolation_s = max_extrapolation_s
        self._stamps_s: list[float] = []
        self._quats: list[Quat] = []

    def __len__(self) -> int:
        return len(self._stamps_s)

    @property
    def latest_stamp_s(self) -> float | None:
        return self._stamps_s[-1] if self._stamps_s else None

    def push(self, stamp_s: float, q_ned_body_wxyz: Quat | tuple[float, float, float, float]) -> None:
        """Add an attitude sample taken at ``stamp_s`` (same clock as the frames)."""
        if self._stamps_s and stamp_s <= self._stamps_s[-1]:
            return
        q = np.asarray(q_ned_body_wxyz, dtype=np.float64)
        n = float(np.linalg.norm(q))
        if not math.isfinite(n) or n == 0.0:
            raise ValueError(f"not a quaternion: {q_ned_body_wxyz!r}")
        self._stamps_s.append(stamp_s)
        self._quats.append(q / n)
        if len(self._stamps_s) > 2 * self._capacity:  # trim in halves: amortised O(1) per push
            del self._stamps_s[: self._capacity]
            del self._quats[: self._capacity]

    def q_at(self, stamp_s: float) -> Quat | None:
        """Attitude quaternion (w, x, y, z) at ``stamp_s``, or None when too far from every sample."""
        b = _bracket(self._stamps_s, stamp_s, self._max_extrapolation_s)
        if b is None:
            return None
        i, a = b
        return self._quats[i] if a == 0.0 else slerp(self._quats[i], self._quats[i + 1], a)

    def R_at(self, stamp_s: float) -> Mat3 | None:
        """``R_ned_body`` at ``stamp_s``, or None (see :meth:`q_at`)."""
        q = self.q_at(stamp_s)
        return None if q is None else R_from_quat(q)


class VelocityHistory:
    """Recent follower velocities (NED, m/s) from telemetry, looked up at frame timestamps.

    The tracker uses their *changes* between frames as the follower's own manoeuvre (ego-motion). Fed in
    time order; lookups between two samples interpolate linearly, up to ``max_extrapolation_s`` outside
    the held span take the nearest sample, farther ones return None.
    """

    def __init__(self, capacity: int = 512, max_extrapolation_s: float = 0.1) -> None:
        if capacity < 2:
            raise ValueError("capacity must be >= 2")
        self._capacity = capacity
        self._max_extrapolation_s = max_extrapolation_s
        self._stamps_s: list[float] = []
        self._values: list[Vec3] = []

    def __len__(self) -> int:
        return len(self._stamps_s)

    def push(self, stamp_s: float, v_ned_m_s: Vec3 | tuple[float, float, float]) -> None:
        """Add a velocity sample taken at ``stamp_s`` (the frames' clock); non-finite ones are ignored."""
        v = np.asarray(v_ned_m_s, dtype=np.float64)
        if (self._stamps_s and stamp_s <= self._stamps_s[-1]) or not np.all(np.isfinite(v)):
            return
        self._stamps_s.append(stamp_s)
        self._values.append(v)
        if len(self._stamps_s) > 2 * self._capacity:
            del self._stamps_s[: self._capacity]
            del self._values[: self._capacity]

    def v_at(self, stamp_s: float) -> Vec3 | None:
        """Velocity at ``stamp_s``, or None when too far from every sample."""
        b = _bracket(self._stamps_s, stamp_s, self._max_extrapolation_s)
        if b is None:
            return None
        i, a = b
        if a == 0.0:
            return self._values[i]
        out: Vec3 = (1.0 - a) * self._values[i] + a * self._values[i + 1]
        return out


def _bracket(stamps_s: list[float], stamp_s: float, max_extrapolation_s: float) -> tuple[int, float] | None:
    """Where ``stamp_s`` falls in sorted ``stamps_s``: ``(i, a)`` to blend samples i and i+1 by ``a``.

    Outside the held span the nearest sample is taken (``a`` = 0) up to ``max_extrapolation_s`` away;
    farther, or with no samples, None.
    """
    if not stamps_s:
        return None
    i = bisect.bisect_left(stamps_s, stamp_s)
    if i == 0:
        return (0, 0.0) if stamps_s[0] - stamp_s <= max_extrapolation_s else None
    if i == len(stamps_s):
        return (i - 1, 0.0) if stamp_s - stamps_s[-1] <= max_extrapolation_s else None
    t0, t1 = stamps_s[i - 1], stamps_s[i]
    return i - 1, (stamp_s - t0) / (t1 - t0)
