"""What the tracker hands on: :class:`TrackState` each step, with its :class:`RelativeEstimate` of the leader.

The status rules and frames are the tracker's contract (:mod:`companion.estimation.tracker`);
:meth:`TrackState.leader_estimate` turns a state into the mission's input
(:class:`~companion.estimation.leader.LeaderEstimate`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

from companion.estimation.leader import LeaderEstimate, TrackStatus
from companion.kernel.frames import Mat3, Vec3
from companion.perception.pose import LeaderMeasurement, bearing
from companion.perception.transform import CameraGeometry, rotate_cov

Mat6 = NDArray[np.float64]


@dataclass(frozen=True)
class RelativeEstimate:
    """The leader relative to the follower at one instant, in NED axes, body FRD and the camera frame.

    Stored in NED with the attitude it was taken at; the body and camera views are computed on first
    access (most consumers read one frame's view, and the per-frame budget is tight).
    """

    #: Leader centre minus follower centre, NED axes, m; and its rate, m/s.
    p_ned_rel_m: Vec3
    v_ned_rel_m_s: Vec3
    #: 6x6 covariance of (p_ned_rel_m, v_ned_rel_m_s), m^2, m^2/s, m^2/s^2.
    cov_ned: Mat6
    #: The follower's attitude at the estimate's stamp, and the camera mount.
    R_ned_body: Mat3
    camera: CameraGeometry
    #: The leader's own acceleration, NED m/s^2 (``leader_accel_filter``; else None).
    a_ned_leader_m_s2: Vec3 | None = None

    @property
    def cov_ned_m2(self) -> Mat3:
        """Position block of :attr:`cov_ned`, m^2."""
        return self.cov_ned[:3, :3]

    @cached_property
    def p_body_leader_m(self) -> Vec3:
        """Leader centre in body FRD (origin: the follower's centre), m."""
        return self.R_ned_body.T @ self.p_ned_rel_m

    @cached_property
    def v_body_rel_m_s(self) -> Vec3:
        """Relative velocity in body axes, m/s (the NED relative velocity rotated)."""
        return self.R_ned_body.T @ self.v_ned_rel_m_s

    @cached_property
    def cov_body_m2(self) -> Mat3:
        """Covariance of :attr:`p_body_leader_m`, m^2."""
        return rotate_cov(self.R_ned_body.T, self.cov_ned_m2)

    @cached_property
    def p_cam_leader_m(self) -> Vec3:
        """Leader centre in the camera frame (x right, y down, z forward), m."""
        return self.camera.body_to_cam(self.p_body_leader_m)

    @cached_property
    def v_cam_rel_m_s(self) -> Vec3:
        """Relative velocity in camera axes, m/s."""
        return self.camera.R_body_cam.T @ self.v_body_rel_m_s

    @cached_property
    def cov_cam_m2(self) -> Mat3:
        """Covariance of :attr:`p_cam_leader_m`, m^2."""
        return rotate_cov(self.camera.R_ned_cam(self.R_ned_body).T, self.cov_ned_m2)

    @cached_property
    def azimuth_rad(self) -> float:
        """Camera bearing of the leader, positive right, rad."""
        return bearing(self.p_cam_leader_m)[0]

    @cached_property
    def elevation_rad(self) -> float:
        """Camera elevation of the leader, positive up, rad."""
        return bearing(self.p_cam_leader_m)[1]

    @cached_property
    def range_m(self) -> float:
        """Distance from the camera to the leader's centre, m."""
        return float(np.linalg.norm(self.p_cam_leader_m))


@dataclass(frozen=True, slots=True)
class TrackState:
    """What the tracker knows after one step; consumed by the formation law and the mission."""

    stamp_s: float
    status: TrackStatus
    #: Increments with each new track; 0 before the first.
    track_id: int
    #: None when there is no track (never acquired, or dropped after ``lost_timeout_s``).
    estimate: RelativeEstimate | None
    #: Time since the track started, s (0 without a track).
    age_s: float
    #: Stamp of the last measurement that updated the track, s (None without a track).
    last_measurement_s: float | None
    #: Measurements accepted by this track.
    hits: int
    #: The measurement that updated the track at this step, if any.
    measurement: LeaderMeasurement | None
    #: Measurements offered this step, and how many the size prior rejected.
    n_candidates: int = 0
    n_size_rejected: int = 0
    #: Share of this track's last ``quality_window_frames`` frames that had a detection in its gate
    #: (0 without a track): a phantom built of sporadic false detections stays low.
    recent_hit_ratio: float = 0.0
    #: The track was dropped at this step as far-field (it never came closer: sky, glare); status LOST.
    far_field: bool = False

    @property
    def usable(self) -> bool:
        """Confirmed and recent: the formation law may fly on it."""
        return self.status in (TrackStatus.CONFIRMED, TrackStatus.COASTING)

    @property
    def since_measurement_s(self) -> float:
        """Time since the last accepted measurement, s (inf without a track)."""
        return math.inf if self.last_measurement_s is None else self.stamp_s - self.last_measurement_s

    def leader_estimate(self) -> LeaderEstimate | None:
        """This state as the mission's input (None without a track): NED, m and m/s, service clock."""
        est = self.estimate
        if est is None or self.last_measurement_s is None:
            return None
        p, v, cov, a = est.p_ned_rel_m, est.v_ned_rel_m_s, est.cov_ned_m2, est.a_ned_leader_m_s2
        return LeaderEstimate(
            stamp_s=float(self.stamp_s),
            status=self.status,
            p_ned_rel_m=(float(p[0]), float(p[1]), float(p[2])),
            v_ned_rel_m_s=(float(v[0]), float(v[1]), float(v[2])),
            last_measurement_s=float(self.last_measurement_s),
            track_age_s=float(self.age_s),
            recent_hit_ratio=float(self.recent_hit_ratio),
            var_ned_rel_m2=(float(cov[0, 0]), float(cov[1, 1]), float(cov[2, 2])),
            a_ned_leader_m_s2=None if a is None else (float(a[0]), float(a[1]), float(a[2])),
            far_field=self.far_field,
        )
