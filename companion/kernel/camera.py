"""The camera model shared by the simulator and the service: intrinsics, the mount, frames and their truth.

Arrays are not copied when these are built: a frame owns the buffers its source produced. Axes follow
:mod:`companion.kernel.frames` (camera x right, y down, z forward; body FRD).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from companion.kernel.config import Section
from companion.kernel.frames import Mat3, Vec3

RgbImage = NDArray[np.uint8]  # H x W x 3, RGB order (not OpenCV's BGR)
DepthImage = NDArray[np.float32]  # H x W, metres along the optical axis, 0 = invalid


@dataclass(frozen=True, slots=True)
class Intrinsics:
    """Pinhole intrinsics of the colour camera (depth is aligned to it), pixels."""

    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    width_px: int
    height_px: int

    @property
    def K(self) -> Mat3:
        """The 3x3 camera matrix."""
        return np.array([[self.fx_px, 0.0, self.cx_px], [0.0, self.fy_px, self.cy_px], [0.0, 0.0, 1.0]])

    @classmethod
    def from_hfov(cls, width_px: int, height_px: int, hfov_deg: float) -> Intrinsics:
        """Square pixels, principal point at the centre, focal length from the horizontal field of view."""
        f = (width_px / 2.0) / np.tan(np.radians(hfov_deg) / 2.0)
        return cls(float(f), float(f), (width_px - 1) / 2.0, (height_px - 1) / 2.0, width_px, height_px)


@dataclass(frozen=True, slots=True)
class GroundTruth:
    """What the simulator knows about the leader at a frame's timestamp (never fed to the service's estimate).

    ``box_xyxy_px`` is the tight box of the leader's *visible* pixels, None when none are visible.
    """

    box_xyxy_px: tuple[float, float, float, float] | None
    visible_fraction: float
    #: Leader centre in the camera frame (x right, y down, z forward), m.
    p_cam_leader_m: Vec3
    #: Leader yaw minus follower yaw, rad, wrapped to [-pi, pi).
    yaw_rel_rad: float
    #: Follower and leader true poses in local NED at the frame's timestamp.
    p_ned_follower_m: Vec3 | None = None
    p_ned_leader_m: Vec3 | None = None
    q_ned_follower_wxyz: NDArray[np.float64] | None = None


@dataclass(frozen=True, slots=True)
class RgbdFrame:
    """One aligned colour + depth frame with its capture time on the source's clock (s)."""

    rgb: RgbImage
    depth_m: DepthImage
    intrinsics: Intrinsics
    stamp_s: float
    seq: int = 0
    truth: GroundTruth | None = None


class MountConfig(Section):
    """Camera extrinsics: position of the camera in body FRD and its angles relative to body."""

    x_m: float = 0.10
    y_m: float = 0.0
    z_m: float = 0.0
    roll_deg: float = 0.0
    #: Positive tilts the camera up: a follower flies nose-down, so a small up-tilt centres the leader.
    pitch_deg: float = 5.0
    yaw_deg: float = 0.0
