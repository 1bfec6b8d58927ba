"""Perception after the detector: pose stage + attitude lookup + track stage, for one frame at a time.

The service, ``companion replay`` and ``companion bench`` all drive perception through
:class:`PerceptionPipeline`. It sits in estimation because it ends in the tracker: perception (pose, depth
guard) never imports estimation. The two stages are separate methods so they can be timed separately::

    pipeline = PerceptionPipeline.from_config(cfg, guard_brake_m_s2=limits.brake_m_s2)
    pipeline.attitude.push(stamp_s, q_ned_body)                 # from telemetry, as it arrives
    pipeline.velocity.push(stamp_s, v_ned_m_s)                  # optional: ego-motion for the tracker
    measurements = pipeline.measure(frame, result.detections)   # pose stage (pure, per detection)
    state = pipeline.track(frame.stamp_s, measurements)         # attitude at the stamp + tracker step

Pure apart from the attitude history it owns: time comes from the frames' stamps.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from companion.config import Config, LeaderConfig, PoseConfig, SafetyConfig, TrackerConfig
from companion.estimation.estimate import TrackState
from companion.estimation.far_field import FarFieldCheck, FarFieldRejection
from companion.estimation.identity import LeaderIdentity
from companion.estimation.leader import ObstacleAhead, TrackStatus
from companion.estimation.tracker import TargetTracker
from companion.kernel.camera import RgbdFrame
from companion.kernel.frames import Mat3, Vec3
from companion.perception.obstacle import MIN_RANGE_M, guard_range_m, nearest_ahead
from companion.perception.pose import LeaderMeasurement, measure_all
from companion.perception.size_range import SizeCalibrator
from companion.perception.transform import AttitudeHistory, CameraGeometry, VelocityHistory
from companion.perception.types import Detection

#: The depth guard's sightings confirm each other when this close in time (s) and place (NED, m): the
#: follower's own motion between two 15 Hz frames at 3 m/s is 0.2 m.
OBSTACLE_CONFIRM_GAP_S = 0.25
OBSTACLE_CONFIRM_M = 0.5


@dataclass(slots=True)
class PipelineCounters:
    """Frames whose attitude was unknown (measurements dropped) or assumed level (no telemetry yet)."""

    attitude_missing: int = 0
    attitude_assumed_level: int = 0


class PerceptionPipeline:
    """Pose + tracker for the leader; owns the attitude history that telemetry feeds."""

    def __init__(
        self,
        leader: LeaderConfig,
        pose: PoseConfig,
        tracker: TrackerConfig,
        camera: CameraGeometry,
        attitude: AttitudeHistory | None = None,
        *,
        safety: SafetyConfig | None = None,
        guard_brake_m_s2: float | None = None,
        slot_range_m: float | None = None,
    ) -> None:
        self.leader = leader
        #: The depth guard's settings; None or ``depth_guard`` off: :meth:`obstacle` returns None.
        self.safety = safety
        #: The separation barrier's braking deceleration, m/s^2: the depth guard looks out to the stopping
        #: distance it gives (None: ``depth_guard_range_m`` whatever the speed).
        self.guard_brake_m_s2 = guard_brake_m_s2
        self.pose_cfg = pose
        self.camera = camera
        self.tracker = TargetTracker(tracker, camera)
        self.attitude = attitude if attitude is not None else AttitudeHistory()
        #: The follower's own velocity from telemetry (ego-motion for the tracker); may stay empty.
        self.velocity = VelocityHistory()
        self.counters = PipelineCounters()
        #: Drops a track that never comes closer (sky, glare); None without a slot range or when off.
        self.far_field = (
            FarFieldCheck(
                flown_m=tracker.far_field_flown_m,
                closure_fraction=tracker.far_field_closure,
                min_range_m=slot_range_m + tracker.far_field_margin_m,
                cone_deg=tracker.far_field_cone_deg,
                ignore_s=tracker.far_field_ignore_s,
            )
            if slot_range_m is not None and tracker.far_field_flown_m > 0.0
            else None
        )
        #: The far-field drop of the last :meth:`track` call, if it dropped one (for the service log).
        self.far_field_rejection: FarFieldRejection | None = None
        #: Formations: keeps the track on the leader among look-alike neighbours (None: a lone follower).
        self.identity: LeaderIdentity | None = None
        self.size = (
            SizeCalibrator(
                leader.span_m,
                min_depth_m=pose.size_learn_min_frac * pose.depth_max_m,
                max_depth_m=0.95 * pose.depth_max_m,
            )
            if pose.size_fallback
            else None
        )
        self._last_R_ned_body: Mat3 = np.eye(3)
        #: The depth guard's last sighting and how many frames in a row have seen it there.
        self._obstacle_seen: tuple[ObstacleAhead, int] | None = None
        self._att_key: tuple[float, float | None] = (math.nan, None)
        self._att_R: Mat3 | None = None

    @classmethod
    def from_config(cls, cfg: Config, *, guard_brake_m_s2: float | None) -> PerceptionPipeline:
        """The pipeline the config describes, its depth guard on ``safety``.

        ``guard_brake_m_s2``: the separation barrier's braking deceleration (the mission's
        :class:`~companion.mission.safety.SafetyLimits` ``brake_m_s2``), which sets how far ahead the guard
        looks at speed; None: ``depth_guard_range_m`` whatever the speed.
        """
        return cls(
            cfg.leader,
            cfg.pose,
            cfg.tracker,
            CameraGeometry.from_mount(cfg.camera.mount),
            safety=cfg.safety,
            guard_brake_m_s2=guard_brake_m_s2,
            slot_range_m=float(np.linalg.norm(cfg.formation.offset_cam_m)),
        )

    def measure(self, frame: RgbdFrame, detections: Sequence[Detection]) -> list[LeaderMeasurement]:
        """Pose stage: the leader's camera-frame position for every detection with a usable range."""
        R = self._attitude_at(frame.stamp_s)
        R_ned_body = R if R is not None else self._last_R_ned_body
        down_cam = self.camera.R_ned_cam(R_ned_body)[2]
        predicted = self.tracker.predict_cam(frame.stamp_s, R_ned_body, self.velocity.v_at(frame.stamp_s))
        return measure_all(
            frame.depth_m,
            frame.intrinsics,
            list(detections),
            frame.stamp_s,
            leader=self.leader,
            cfg=self.pose_cfg,
            size_prior=self.size,
            down_cam=down_cam,
            z_hint_m=None if predicted is None else float(predicted[0][2]),
            z_hint_std_m=math.inf if predicted is None else math.sqrt(float(predicted[1][2, 2])),
        )

    def _attitude_at(self, stamp_s: float) -> Mat3 | None:
        """``R_ned_body`` at a frame stamp (one lookup per stamp, shared by both stages)."""
        key = (stamp_s, self.attitude.latest_stamp_s)
        if key != self._att_key:
            self._att_key = key
            R = self.attitude.R_at(stamp_s)
            self._att_R = np.eye(3) if R is None and len(self.attitude) == 0 else R
        return self._att_R

    def track(self, stamp_s: float, measurements: Sequence[LeaderMeasurement]) -> TrackState:
        """Track stage: follower attitude at ``stamp_s``, then one tracker step.

        With no telemetry at all yet the follower is assumed level and facing north (replays of
        recordings without attitude); with telemetry that does not cover the stamp, the frame's
        measurements cannot be placed in NED and are dropped (the track coasts).
        """
        R = self._attitude_at(stamp_s)
        if len(self.attitude) == 0:
            self.counters.attitude_assumed_level += 1
        if R is None:
            self.counters.attitude_missing += 1
            measurements = ()
            R = self._last_R_ned_body
        self._last_R_ned_body = R
        ident = self.identity
        if ident is not None and measurements:
            measurements = [
                m for m in measurements if ident.keep(*self._ned_rel(m.p_cam_leader_m, m.cov_cam_m2, R))
            ]
        far = self.far_field
        if far is not None and far.ignoring and measurements:
            measurements = [
                m
                for m in measurements
                if m.range_source == "depth"
                or not far.ignores(stamp_s, self.camera.cam_to_ned_rel(m.p_cam_leader_m, R))
            ]
        v_ned_m_s = self.velocity.v_at(stamp_s)
        state = self.tracker.step(stamp_s, measurements, R, v_ned_m_s)
        if ident is not None and state.status == TrackStatus.CONFIRMED and state.estimate is not None:
            est = state.estimate
            if ident.check_track(stamp_s, est.p_ned_rel_m, _sigma_m(est.cov_ned_m2)):
                # Start again from this frame's measurements that fit the leader.
                self.tracker.reset()
                state = self.tracker.step(stamp_s, measurements, R, v_ned_m_s)
        self.far_field_rejection = None
        if far is not None:
            meas = state.measurement
            track_est = state.estimate
            rejection = far.step(
                stamp_s,
                state.track_id,
                meas is not None and meas.range_source == "depth",
                None if track_est is None else track_est.p_ned_rel_m,
                v_ned_m_s,
            )
            if rejection is not None:
                # Told as lost this once (the mission then searches without coasting toward it), then gone.
                self.far_field_rejection = rejection
                self.tracker.reset()
                state = replace(state, status=TrackStatus.LOST, far_field=True)
        if self.size is not None and state.measurement is not None and state.status == TrackStatus.CONFIRMED:
            self.size.update(state.measurement)
        return state

    def _ned_rel(self, p_cam_m: Vec3, cov_cam_m2: Mat3, R_ned_body: Mat3) -> tuple[Vec3, float]:
        """A camera-frame measurement relative to the follower in NED, m, and its 1-sigma, m."""
        return self.camera.cam_to_ned_rel(p_cam_m, R_ned_body), _sigma_m(cov_cam_m2)

    def process(self, frame: RgbdFrame, detections: Sequence[Detection]) -> TrackState:
        """Both stages for one frame."""
        return self.track(frame.stamp_s, self.measure(frame, detections))

    def obstacle(self, frame: RgbdFrame, track: TrackState) -> ObstacleAhead | None:
        """The depth guard after the track stage: the nearest thing ahead that is not the tracked leader.

        The tracked leader is left out where the track puts it (its box, grown by two sigma) and at the range
        it puts it (plus or minus a span and two sigma): a track on a phantom leaves the real leader in.
        """
        g = self.safety
        if g is None or not g.depth_guard:
            return None
        k = frame.intrinsics
        exclude_xyxy = exclude_range = None
        est = track.estimate
        if est is not None:
            p = est.p_cam_leader_m
            z = float(p[2])
            if z > MIN_RANGE_M:
                cov = est.cov_cam_m2
                half_m = 0.75 * self.leader.span_m + 2.0 * math.sqrt(max(float(cov[0, 0]), float(cov[1, 1])))
                u, v = k.fx_px * float(p[0]) / z + k.cx_px, k.fy_px * float(p[1]) / z + k.cy_px
                hu, hv = k.fx_px * half_m / z, k.fy_px * half_m / z
                exclude_xyxy = (u - hu, v - hv, u + hu, v + hv)
                dz = self.leader.span_m + 2.0 * math.sqrt(float(cov[2, 2]))
                exclude_range = (z - dz, z + dz)
        R = self._attitude_at(frame.stamp_s)
        R_ned_body = R if R is not None else self._last_R_ned_body
        p_cam = nearest_ahead(
            frame.depth_m,
            k,
            max_range_m=self._guard_range_m(g, frame.stamp_s, R_ned_body),
            window_frac=g.depth_guard_window_frac,
            min_px=g.depth_guard_min_px,
            exclude_xyxy=exclude_xyxy,
            exclude_range_m=exclude_range,
        )
        if p_cam is None:
            self._obstacle_seen = None
            return None
        p_ned = R_ned_body @ self.camera.cam_to_body(p_cam)
        return self._confirmed(
            ObstacleAhead(frame.stamp_s, (float(p_ned[0]), float(p_ned[1]), float(p_ned[2])))
        )

    def _confirmed(self, ob: ObstacleAhead) -> ObstacleAhead | None:
        """``ob`` once ``depth_guard_confirm_frames`` frames in a row have seen it in about the same place.

        One frame's depth can be wrong where the leader is: a range 2 m short there read as an obstacle 3 m
        ahead, and the separation barrier (which no slew holds back) reversed the follower at once. A real
        obstacle stays; within ``min_separation_m`` one frame is enough.
        """
        g = self.safety
        seen = self._obstacle_seen
        n = 1
        if seen is not None and 0.0 < ob.stamp_s - seen[0].stamp_s <= OBSTACLE_CONFIRM_GAP_S:
            moved = math.dist(ob.p_ned_rel_m, seen[0].p_ned_rel_m)
            n = seen[1] + 1 if moved <= OBSTACLE_CONFIRM_M else 1
        self._obstacle_seen = (ob, n)
        assert g is not None  # noqa: S101 (only called with the guard on)
        near = math.hypot(*ob.p_ned_rel_m) < g.min_separation_m
        return ob if near or n >= g.depth_guard_confirm_frames else None

    def _guard_range_m(self, g: SafetyConfig, stamp_s: float, R_ned_body: Mat3) -> float:
        """The depth guard's range at this frame: the stopping distance toward the camera's axis, m."""
        v_ned = self.velocity.v_at(stamp_s)
        if self.guard_brake_m_s2 is None or v_ned is None:
            return g.depth_guard_range_m
        v_ahead = float(np.dot(v_ned, self.camera.R_ned_cam(R_ned_body)[:, 2]))
        return guard_range_m(
            v_ahead,
            min_range_m=g.depth_guard_range_m,
            max_range_m=g.depth_guard_max_range_m,
            separation_m=g.min_separation_m,
            response_s=g.separation_response_s,
            brake_m_s2=self.guard_brake_m_s2,
        )


def _sigma_m(cov_m2: Mat3) -> float:
    """One sigma of a position covariance, all axes together (root of its trace), m."""
    return math.sqrt(max(float(np.trace(cov_m2)), 0.0))
