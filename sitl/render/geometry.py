"""Pure camera geometry for the renderer: poses, GL matrices, truth from masks. No GL here.

Conventions (see :mod:`companion.kernel.frames`): camera x right, y down, z forward; body FRD; world NED.
Pixel coordinates follow the intrinsics: the centre of pixel column ``i`` is at ``u = i`` (OpenCV).
Boxes (``box_xyxy_px``) use the detector/COCO edge convention instead: pixel column ``i`` spans
``[i, i + 1)``, so a box covering columns ``c0..c1`` is ``x0 = c0, x1 = c1 + 1`` and its centre in
intrinsics coordinates is ``(x0 + x1) / 2 - 0.5``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from companion.kernel.camera import Intrinsics, MountConfig
from companion.kernel.frames import Mat3, R_body_cam_from_mount, R_from_quat, Vec3, euler_from_R, wrap_pi

Mat4 = NDArray[np.float64]
Box = tuple[float, float, float, float]


class PoseTruth(Protocol):
    """Anything with a true NED position and attitude (the SITL's ``VehicleTruth`` qualifies)."""

    @property
    def p_ned_m(self) -> ArrayLike: ...

    @property
    def q_ned_body_wxyz(self) -> ArrayLike: ...


@dataclass(frozen=True, slots=True)
class VehiclePose:
    """A minimal :class:`PoseTruth` for tests, datasets and stub truth callables."""

    p_ned_m: Vec3
    q_ned_body_wxyz: NDArray[np.float64]
    #: Body angular rate, rad/s (FRD); drives motion blur when present.
    omega_body_rad_s: Vec3 | None = None


@dataclass(frozen=True, slots=True)
class CameraPose:
    """Where the camera is: ``R_ned_cam`` maps camera vectors into NED; ``p_ned_cam_m`` its centre."""

    R_ned_cam: Mat3
    p_ned_cam_m: Vec3

    @property
    def R_cam_ned(self) -> Mat3:
        return self.R_ned_cam.T

    def to_cam(self, p_ned_m: ArrayLike) -> Vec3:
        """A NED point expressed in the camera frame, m."""
        return self.R_cam_ned @ (np.asarray(p_ned_m, dtype=np.float64) - self.p_ned_cam_m)


@dataclass(frozen=True, slots=True)
class LeaderPose:
    """The leader's attitude (body -> NED) and centre position in NED, m."""

    R_ned_body: Mat3
    p_ned_m: Vec3


def as_vec3(value: ArrayLike) -> Vec3:
    """A float64 3-vector from any array-like (tuples, lists, arrays)."""
    arr = np.asarray(value, dtype=np.float64).reshape(3)
    return arr


def camera_pose(follower: PoseTruth, mount: MountConfig) -> CameraPose:
    """Follower truth composed with the mount extrinsics: the camera's pose in NED."""
    R_ned_body = R_from_quat(np.asarray(follower.q_ned_body_wxyz, dtype=np.float64))
    R_body_cam = R_body_cam_from_mount(mount.roll_deg, mount.pitch_deg, mount.yaw_deg)
    p_body_cam_m = np.array([mount.x_m, mount.y_m, mount.z_m])
    p_ned_cam_m = as_vec3(follower.p_ned_m) + R_ned_body @ p_body_cam_m
    return CameraPose(R_ned_body @ R_body_cam, p_ned_cam_m)


def projection_matrix(intr: Intrinsics, near_m: float, far_m: float, scale: int = 1) -> Mat4:
    """Camera frame -> GL clip space such that image row ``v`` lands on framebuffer row ``v``.

    GL's window origin is bottom-left and ``glReadPixels`` returns the bottom row first; mapping camera
    +y (down) to window +y makes the read-back array come out top row first with no flip. The mirror
    reverses triangle winding, so outward faces are clockwise on screen. ``scale`` renders a
    supersampled framebuffer (pixel ``u`` at scale s covers ``[s u, s u + s)``).
    """
    W, H = intr.width_px * scale, intr.height_px * scale
    fx, fy = intr.fx_px * scale, intr.fy_px * scale
    # Pixel centre u (intrinsics) sits at window x = u + 0.5; at scale s, at s (u + 0.5).
    cx_win = (intr.cx_px + 0.5) * scale
    cy_win = (intr.cy_px + 0.5) * scale
    P = np.zeros((4, 4))
    P[0, 0] = 2.0 * fx / W
    P[0, 2] = 2.0 * cx_win / W - 1.0
    P[1, 1] = 2.0 * fy / H
    P[1, 2] = 2.0 * cy_win / H - 1.0
    P[2, 2] = (far_m + near_m) / (far_m - near_m)
    P[2, 3] = -2.0 * far_m * near_m / (far_m - near_m)
    P[3, 2] = 1.0
    return P


def shifted_intrinsics(intr: Intrinsics, u_px: float, v_px: float, size_px: int) -> Intrinsics:
    """Same focal length, principal point moved so that pixel (u, v) lands near a square canvas's centre.

    Shifting the principal point translates the image plane: silhouettes keep their exact pixel shape,
    which lets a leader-only pass count the pixels a clipped or occluded leader would have covered.
    """
    # Shift by whole pixels only, so both images sample the silhouette at the same sub-pixel phase.
    c = (size_px - 1) / 2.0
    du, dv = round(c - u_px), round(c - v_px)
    return Intrinsics(intr.fx_px, intr.fy_px, intr.cx_px + du, intr.cy_px + dv, size_px, size_px)


def view_matrix(pose: CameraPose) -> Mat4:
    """NED -> camera frame as a 4x4 homogeneous transform."""
    V = np.eye(4)
    V[:3, :3] = pose.R_cam_ned
    V[:3, 3] = -pose.R_cam_ned @ pose.p_ned_cam_m
    return V


def model_matrix(R_ned_body: Mat3, p_ned_m: Vec3) -> Mat4:
    """Body -> NED as a 4x4 homogeneous transform."""
    M = np.eye(4)
    M[:3, :3] = R_ned_body
    M[:3, 3] = p_ned_m
    return M


def project(intr: Intrinsics, p_cam_m: Vec3) -> tuple[float, float]:
    """Pixel (u, v) of a camera-frame point in front of the camera (intrinsics convention)."""
    return (
        intr.fx_px * p_cam_m[0] / p_cam_m[2] + intr.cx_px,
        intr.fy_px * p_cam_m[1] / p_cam_m[2] + intr.cy_px,
    )


def box_from_mask(mask: NDArray[np.uint8] | NDArray[np.bool_]) -> tuple[Box | None, int]:
    """Tight box (edge convention, px) of a mask's nonzero pixels and their count."""
    rows = np.flatnonzero(mask.any(axis=1))
    if rows.size == 0:
        return None, 0
    cols = np.flatnonzero(mask.any(axis=0))
    count = int(np.count_nonzero(mask))
    return (float(cols[0]), float(rows[0]), float(cols[-1] + 1), float(rows[-1] + 1)), count


def yaw_rel_rad(R_ned_leader: Mat3, R_ned_follower: Mat3) -> float:
    """Leader yaw minus follower yaw, wrapped to [-pi, pi)."""
    return wrap_pi(euler_from_R(R_ned_leader)[2] - euler_from_R(R_ned_follower)[2])


def rotation_vector_matrix(rotvec_rad: Vec3) -> Mat3:
    """Rotation matrix of a rotation vector (axis * angle), Rodrigues."""
    theta = float(np.linalg.norm(rotvec_rad))
    if theta < 1e-12:
        return np.eye(3)
    k = rotvec_rad / theta
    Kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    R: Mat3 = np.eye(3) + math.sin(theta) * Kx + (1.0 - math.cos(theta)) * (Kx @ Kx)
    return R


def blur_homographies(intr: Intrinsics, omega_cam_rad_s: Vec3, exposure_s: float) -> tuple[Mat3, Mat3, float]:
    """Pixel homographies at the start and end of the exposure for a rotating camera, and the blur length.

    A camera turning at ``omega_cam`` (camera frame) sees a distant point at pixel p at time t at
    ``K R(-omega t) K^-1 p``. Returns ``(H_start, H_end, longest_streak_px)`` over the image corners.
    """
    K = intr.K
    K_inv = np.linalg.inv(K)
    half = omega_cam_rad_s * (exposure_s / 2.0)
    H0 = K @ rotation_vector_matrix(half) @ K_inv
    H1 = K @ rotation_vector_matrix(-half) @ K_inv
    corners = np.array(
        [
            [0.0, 0.0, 1.0],
            [intr.width_px - 1.0, 0.0, 1.0],
            [0.0, intr.height_px - 1.0, 1.0],
            [intr.width_px - 1.0, intr.height_px - 1.0, 1.0],
            [intr.cx_px, intr.cy_px, 1.0],
        ]
    ).T
    a = H0 @ corners
    b = H1 @ corners
    a = a[:2] / a[2]
    b = b[:2] / b[2]
    streak = float(np.max(np.linalg.norm(a - b, axis=0)))
    return H0, H1, streak
