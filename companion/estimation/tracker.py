"""TargetTracker: the leader's position and velocity relative to the follower, from pose measurements.

State and frame:
    A constant-velocity Kalman filter (filterpy) on ``[p_ned_rel_m, v_ned_rel_m_s]``: the leader's
    position minus the follower's, and its rate of change, in local NED *axes* (origin at the follower's
    centre). Only the follower's attitude is needed to place a measurement there, so the track survives
    GPS loss; relative motion is close to constant-velocity whatever the follower's heading does.

Per frame, :meth:`TargetTracker.step` takes the frame's stamp, the pose measurements of every detection
(camera frame) and the follower's attitude at that stamp, and:

1. predicts to the stamp (white-noise acceleration of ``process_accel_std_m_s2``; along the line of
   sight ``size_range_accel_std_m_s2`` while the last measurement was ranged by box size);
2. rejects boxes whose pixel size disagrees with their depth (``size_ratio`` outside
   ``[1/size_ratio_tolerance, size_ratio_tolerance]``; a box cut by the image border may be small);
3. selects the leader: with a track, among measurements inside the Mahalanobis gate
   (``d^2 < gate_chi2``) the one with the least ``d^2 - 2 ln(score)``; without one, the best score
   (a size-ranged track gates returning depth with a 15 % range error added);
4. updates, or coasts: no update, so the covariance grows with the prediction;
5. follows up to three objects outside the gate, each with its own filter (challengers), and hands the
   track to one when it is seen in ``switch_hits`` of the last ``quality_window_frames`` frames while
   the track is seen in at most ``switch_max_track_ratio`` of them (a false track confirmed before the
   leader came into view otherwise gated the leader out for as long as the false one was re-detected
   now and then); or sooner, after ``switch_fast_hits``, when its hit ratio beats the track's by
   ``switch_ratio_margin`` (the leader crossing the view for under a second while a tree-crown track
   blinks on);
   while the track is still tentative, a challenger seen as often with a higher mean score takes it over
   (``contend_tentative``: a false box seen alone on the first frame otherwise started the track).

Opt-in (``leader_accel_filter``): a constant-acceleration (Singer) filter runs beside the track on the
measurements the track accepts, with the same ego-motion; the estimate's position, velocity and the
leader's acceleration then come from it (less lag behind a leader speeding up), while association, gating,
confirmation and coasting stay the constant-velocity track's. Off by default: see docs/evaluation.md.

:meth:`TargetTracker.predict_cam` gives the predicted camera-frame position at a new frame's stamp
without changing the track (the pose stage uses it to pick the leader's depth behind an occluder).

Output: a :class:`TrackState` every step. Its ``status``:
    * ``TENTATIVE``: a new track, not yet ``confirm_hits`` hits in its first ``confirm_window`` frames.
      Not to be flown on. Dropped when it cannot reach the count any more.
    * ``CONFIRMED``: confirmed and updated by a measurement at this step.
    * ``COASTING``: confirmed, no measurement at this step, the last one at most ``coast_timeout_s`` ago.
      The estimate is the prediction; its covariance grows. Fit to fly on with care.
    * ``LOST``: no measurement for more than ``coast_timeout_s``. ``estimate`` still holds the prediction
      (for a search toward it) until ``lost_timeout_s``, then the track is dropped and ``estimate`` is
      None. A measurement inside the gate before that resumes the track as ``CONFIRMED``; one outside
      starts a new tentative track. ``LOST`` with ``estimate=None`` also means "never acquired".

``estimate`` (:class:`~companion.estimation.estimate.RelativeEstimate`) gives the same relative position in
NED axes, in body FRD and in the camera frame (``p_body_leader_m``/``p_cam_leader_m`` are positions of the
leader's centre as those frames see it, i.e. including the mount offset), the relative velocity in each
frame's axes (the NED relative velocity rotated, not the velocity seen by a rotating observer),
covariances in each frame, the camera bearing and range. Everything here is pure: time comes in as
``stamp_s``; the motion models are in :mod:`companion.estimation.motion`.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from filterpy.kalman import KalmanFilter

from companion.config import TrackerConfig
from companion.estimation.estimate import RelativeEstimate, TrackState
from companion.estimation.leader import TrackStatus
from companion.estimation.motion import (
    ego_shift,
    height_deweighted,
    mahalanobis2,
    new_filter,
    process_noise,
    transition,
)
from companion.kernel.frames import Mat3, Vec3
from companion.perception.pose import LeaderMeasurement
from companion.perception.transform import CameraGeometry, rotate_cov

__all__ = ["RelativeEstimate", "TargetTracker", "TrackState"]

#: Range error (relative) a size-ranged track may carry, added to the gate when depth comes back.
_SIZE_RANGE_GATE_REL = 0.15
#: Scores below this are clamped before the log in the selection cost.
_MIN_SCORE = 1e-3
#: A measurement whose fusion would put the track nearer than this share of both the track's range and its
#: own is refused: two detections loose in range (box-size ranging) on different bearings meet near the
#: camera in a Cartesian filter, which took a 23 m track to 0.04 m in one frame (leader-occluded).
_RANGE_COLLAPSE_FRACTION = 0.5
#: Objects followed outside the track's gate at once: one slot held by a blinking tree kept the leader,
#: seen in 6 straight frames beside it, from ever counting (leader-occluded seed 8).
_MAX_CHALLENGERS = 3


@dataclass(frozen=True, slots=True)
class _Candidate:
    meas: LeaderMeasurement
    p_ned_m: Vec3
    R_ned_m2: Mat3


@dataclass(slots=True)
class _Challenger:
    """Something seen outside the track's gate: its filter and its hit (True) per frame since first seen."""

    kf: KalmanFilter
    recent: deque[bool]
    #: Sum of the detector scores of its hits (a tentative track's contest is decided on the mean).
    score_sum: float = 0.0


class TargetTracker:
    """Constant-velocity Kalman tracker of one leader, with gating, N-of-M confirmation and coasting."""

    def __init__(self, cfg: TrackerConfig, camera: CameraGeometry) -> None:
        self.cfg = cfg
        self.camera = camera
        self._kf: KalmanFilter | None = None
        self._stamp_s = 0.0
        self._start_s = 0.0
        self._last_meas_s = 0.0
        self._confirmed = False
        self._window: deque[bool] = deque(maxlen=cfg.confirm_window)
        #: Hit (True) or miss per frame over the last ``quality_window_frames`` of this track.
        self._recent: deque[bool] = deque(maxlen=cfg.quality_window_frames)
        self._hits = 0
        #: Sum of the detector scores the track accepted while tentative (its contest with challengers).
        self._tentative_score_sum = 0.0
        self._track_id = 0
        #: The last accepted measurement was ranged from box size (no stereo depth).
        self._size_ranged = False
        #: The follower's velocity at the filter's current time (ego-motion), NED m/s; None if unknown.
        self._v_follower: Vec3 | None = None
        #: The constant-acceleration filter beside the track (``leader_accel_filter``), or None.
        self._kf_acc: KalmanFilter | None = None
        #: Challengers: what is seen outside the track's gate, each followed by its own filter (predicted
        #: with the track's) with its hits over the same window as ``_recent`` (``switch_hits``).
        self._chals: list[_Challenger] = []

    @property
    def has_track(self) -> bool:
        return self._kf is not None

    def reset(self) -> None:
        """Forget the current track (e.g. when the mission starts a new acquisition)."""
        self._kf = None
        self._kf_acc = None
        self._chals.clear()
        self._confirmed = False
        self._window.clear()
        self._recent.clear()
        self._hits = 0

    def predict_cam(
        self, stamp_s: float, R_ned_body: Mat3, v_ned_follower_m_s: Vec3 | None = None
    ) -> tuple[Vec3, Mat3] | None:
        """Where a usable track expects the leader at ``stamp_s`` (camera frame, m) and its covariance.

        Does not change the track. None without a confirmed track or once it is lost.
        """
        kf = self._kf
        if kf is None or not self._confirmed or stamp_s - self._last_meas_s > self.cfg.coast_timeout_s:
            return None
        dt = max(0.0, stamp_s - self._stamp_s)
        F = transition(self.cfg, dt, 6)
        x = F @ kf.x[:, 0] + ego_shift(dt, v_ned_follower_m_s, self._v_follower, 6)
        P = F @ kf.P @ F.T + process_noise(self.cfg, dt, x[:3], 6, size_ranged=self._size_ranged)
        est = RelativeEstimate(x[:3], x[3:], P, R_ned_body, self.camera)
        return est.p_cam_leader_m, est.cov_cam_m2

    def step(
        self,
        stamp_s: float,
        measurements: Sequence[LeaderMeasurement],
        R_ned_body: Mat3,
        v_ned_follower_m_s: Vec3 | None = None,
    ) -> TrackState:
        """Advance to ``stamp_s`` with this frame's measurements (may be empty) and attitude.

        Args:
            stamp_s: the frame's capture time, s; steps with an earlier stamp than the last do not
                predict backwards (the measurement is applied at the filter's current time).
            measurements: pose of every detection in this frame, camera frame.
            R_ned_body: the follower's attitude at ``stamp_s`` (from :class:`AttitudeHistory`).
            v_ned_follower_m_s: the follower's own velocity at ``stamp_s`` (telemetry, NED), or None.
                Its change since the previous step is the follower's own manoeuvre: the prediction
                subtracts it from the relative velocity (ego-motion), so the track does not lag behind
                the follower's accelerations, and coasting follows them. Only the change is used, so a
                drifting but smooth estimate (PX4 dead-reckoning after a GPS loss) still serves.
        """
        cfg = self.cfg
        if self._kf is not None:
            self._predict(self._kf, stamp_s, v_ned_follower_m_s)
            since = self._stamp_s - self._last_meas_s
            if since > cfg.lost_timeout_s or (not self._confirmed and since > cfg.coast_timeout_s):
                self.reset()
        candidates, n_rejected = self._candidates(measurements, R_ned_body)
        accepted: _Candidate | None = None
        if self._kf is not None:
            accepted = self._select_gated(self._kf, candidates)
            self._recent.append(accepted is not None)
            if accepted is not None:
                self._update(self._kf, accepted)
            elif candidates and self._confirmed and self._stamp_s - self._last_meas_s > cfg.coast_timeout_s:
                self.reset()  # the old track is unusable and something else is seen: start over
            if self._kf is not None and not self._confirmed:
                self._window.append(accepted is not None)
                if accepted is not None:
                    self._tentative_score_sum += accepted.meas.score
            if self._kf is not None and (cfg.switch_hits > 0 if self._confirmed else cfg.contend_tentative):
                others = [c for c in candidates if c is not accepted]
                switched = self._challenge(others)
                if switched is not None:
                    accepted = switched
            if not self._confirmed and self._kf is not None:
                if sum(self._window) >= cfg.confirm_hits:
                    self._confirmed = True
                elif len(self._window) == cfg.confirm_window:
                    self.reset()
        if self._kf is None and candidates:
            accepted = max(candidates, key=lambda c: c.meas.score)
            self._start(stamp_s, accepted)
            self._v_follower = None if v_ned_follower_m_s is None else np.asarray(v_ned_follower_m_s, float)
            if cfg.confirm_hits <= 1:
                self._confirmed = True
        return self._state(stamp_s, R_ned_body, accepted, len(measurements), n_rejected)

    # -- internals -------------------------------------------------------------------------------

    def _candidates(
        self, measurements: Sequence[LeaderMeasurement], R_ned_body: Mat3
    ) -> tuple[list[_Candidate], int]:
        tol = self.cfg.size_ratio_tolerance
        R_ned_cam = self.camera.R_ned_cam(R_ned_body)
        out = []
        rejected = 0
        for m in measurements:
            if m.size_ratio > tol or (m.size_ratio < 1.0 / tol and not m.truncated):
                rejected += 1
                continue
            p_ned = R_ned_body @ self.camera.cam_to_body(m.p_cam_leader_m)
            out.append(_Candidate(m, p_ned, rotate_cov(R_ned_cam, m.cov_cam_m2)))
        return out, rejected

    def _select_gated(self, kf: KalmanFilter, candidates: list[_Candidate]) -> _Candidate | None:
        best: _Candidate | None = None
        best_cost = math.inf
        for c in candidates:
            cost = self._gated_cost(kf, c)
            if cost is not None and cost < best_cost:
                best, best_cost = c, cost
        return best

    def _gated_cost(self, kf: KalmanFilter, c: _Candidate) -> float | None:
        """``d^2 - 2 ln(score)`` of a candidate for a filter, or None outside its gate."""
        x = kf.x[:3, 0]
        S = kf.P[:3, :3] + c.R_ned_m2
        # A track ranged by box size can be off in range by far more than its covariance says (the
        # size calibration's error persists): depth coming back is gated with that error added.
        if self._size_ranged and c.meas.range_source == "depth":
            S = S + (_SIZE_RANGE_GATE_REL**2) * np.outer(x, x)
        d2 = mahalanobis2(c.p_ned_m - x, S)
        if d2 >= self.cfg.gate_chi2 or _range_collapses(kf.P[:3, :3], x, c):
            return None
        return d2 - 2.0 * math.log(max(c.meas.score, _MIN_SCORE))

    def _challenge(self, others: list[_Candidate]) -> _Candidate | None:
        """Follow what is seen outside the track's gate; take it over when it is steady and the track is not.

        A tentative track is taken over by a challenger seen in at least as many frames with a higher mean
        score (``contend_tentative``). Returns the challenger's measurement when it replaced the track (the
        track is then the challenger's filter, with a new id, confirmed if the track was), else None.
        """
        cfg = self.cfg
        window = cfg.quality_window_frames
        # Each box to at most one challenger, the cheapest pairs first: a young challenger's wide gate
        # otherwise took the leader's box from the challenger that had followed it.
        pairs = sorted(
            (cost, i, j)
            for i, ch in enumerate(self._chals)  # already predicted to this stamp with the track (_predict)
            for j, c in enumerate(others)
            if (cost := self._gated_cost(ch.kf, c)) is not None
        )
        hits: list[_Candidate | None] = [None] * len(self._chals)
        taken: set[int] = set()
        for _, i, j in pairs:
            if hits[i] is None and j not in taken:
                hits[i] = others[j]
                taken.add(j)
        for ch, hit in zip(self._chals, hits, strict=True):
            if hit is not None:
                ch.kf.update(hit.p_ned_m.reshape(3, 1), R=hit.R_ned_m2)
                ch.score_sum += hit.meas.score
            ch.recent.append(hit is not None)
        free = [c for j, c in enumerate(others) if j not in taken]
        # A challenger that can no longer reach ``switch_hits`` in its window is dropped.
        keep = [sum(ch.recent) + window - len(ch.recent) >= cfg.switch_hits for ch in self._chals]
        track_ratio = self._recent_ratio()
        best: tuple[float, _Challenger, _Candidate] | None = None
        # While tentative, ``_hits`` counts the track's frames (those of its confirmation window).
        track_mean_score = self._tentative_score_sum / max(1, self._hits)
        for ch, hit, kept in zip(self._chals, hits, keep, strict=True):
            if hit is None or not kept:
                continue
            n_hits = sum(ch.recent)
            ratio = n_hits / len(ch.recent)
            if not self._confirmed:
                # Nothing flies on a tentative track yet: what is seen as often and scores better wins.
                mean_score = ch.score_sum / n_hits
                wins = n_hits >= self._hits and mean_score > track_mean_score
                if wins and (best is None or mean_score > best[0]):
                    best = (mean_score, ch, hit)
                continue
            steadier = n_hits >= cfg.switch_hits and track_ratio <= cfg.switch_max_track_ratio
            clearly_better = (
                cfg.switch_fast_hits > 0
                and n_hits >= cfg.switch_fast_hits
                and ratio >= track_ratio + cfg.switch_ratio_margin
            )
            if (steadier or clearly_better) and (best is None or ratio > best[0]):
                best = (ratio, ch, hit)
        self._chals = [ch for ch, kept in zip(self._chals, keep, strict=True) if kept]
        if best is None:
            for c in sorted(free, key=lambda c: c.meas.score, reverse=True):
                if len(self._chals) >= _MAX_CHALLENGERS:
                    break
                ch = _Challenger(self._new_filter(c, 6), deque([True], maxlen=window), c.meas.score)
                self._chals.append(ch)
            return None
        _, ch, hit = best
        self._kf = ch.kf
        self._kf_acc = self._new_filter(hit, 9) if self.cfg.leader_accel_filter else None
        self._recent.clear()
        self._recent.extend(ch.recent)
        if not self._confirmed:
            # The winner stays tentative, its own frames counting towards confirmation.
            self._window.clear()
            self._window.extend(ch.recent)
            self._tentative_score_sum = ch.score_sum
        self._chals.clear()
        self._track_id += 1
        self._start_s = self._last_meas_s = self._stamp_s
        self._size_ranged = hit.meas.range_source == "size"
        self._hits = sum(self._recent)
        return hit

    def _recent_ratio(self) -> float:
        """The track's hit ratio over the last ``quality_window_frames`` frames."""
        return sum(self._recent) / len(self._recent) if self._recent else 0.0

    def _new_filter(self, c: _Candidate, n: int) -> KalmanFilter:
        """A filter of ``n`` states (6: p, v; 9: p, v, a) started at measurement ``c``, at rest."""
        return new_filter(self.cfg, c.p_ned_m, c.R_ned_m2, n)

    def _start(self, stamp_s: float, c: _Candidate) -> None:
        self._kf = self._new_filter(c, 6)
        self._kf_acc = self._new_filter(c, 9) if self.cfg.leader_accel_filter else None
        self._track_id += 1
        self._stamp_s = self._start_s = self._last_meas_s = stamp_s
        self._confirmed = False
        self._window.clear()
        self._window.append(True)
        self._recent.clear()
        self._recent.append(True)
        self._hits = 1
        self._tentative_score_sum = c.meas.score
        self._size_ranged = c.meas.range_source == "size"
        self._chals.clear()

    def _predict(self, kf: KalmanFilter, stamp_s: float, v_follower: Vec3 | None) -> None:
        dt = stamp_s - self._stamp_s
        if dt <= 0.0:
            return
        for f in (kf, self._kf_acc, *(ch.kf for ch in self._chals)):
            if f is not None:
                n = f.dim_x
                f.predict(
                    F=transition(self.cfg, dt, n),
                    Q=process_noise(self.cfg, dt, f.x[:3, 0], n, size_ranged=self._size_ranged),
                )
                f.x[:, 0] += ego_shift(dt, v_follower, self._v_follower, n)
        self._v_follower = None if v_follower is None else np.asarray(v_follower, dtype=np.float64)
        self._stamp_s = stamp_s

    def _update(self, kf: KalmanFilter, c: _Candidate) -> None:
        y_down_m = float(c.p_ned_m[2] - kf.x[2, 0])
        s_down_m2 = float(kf.P[2, 2] + c.R_ned_m2[2, 2])
        R = height_deweighted(c.R_ned_m2, y_down_m, s_down_m2, self.cfg.height_outlier_dof)
        for f in (kf, self._kf_acc):
            if f is not None:
                f.update(c.p_ned_m.reshape(3, 1), R=R)
                f.P = 0.5 * (f.P + f.P.T)
        self._size_ranged = c.meas.range_source == "size"
        self._last_meas_s = self._stamp_s
        self._hits += 1

    def _state(
        self,
        stamp_s: float,
        R_ned_body: Mat3,
        accepted: _Candidate | None,
        n_candidates: int,
        n_rejected: int,
    ) -> TrackState:
        if self._kf is None:
            return TrackState(
                stamp_s=stamp_s,
                status=TrackStatus.LOST,
                track_id=self._track_id,
                estimate=None,
                age_s=0.0,
                last_measurement_s=None,
                hits=0,
                measurement=None,
                n_candidates=n_candidates,
                n_size_rejected=n_rejected,
            )
        since = self._stamp_s - self._last_meas_s
        if not self._confirmed:
            status = TrackStatus.TENTATIVE
        elif accepted is not None:
            status = TrackStatus.CONFIRMED
        elif since <= self.cfg.coast_timeout_s:
            status = TrackStatus.COASTING
        else:
            status = TrackStatus.LOST
        return TrackState(
            stamp_s=stamp_s,
            status=status,
            track_id=self._track_id,
            estimate=self._estimate(self._kf, R_ned_body),
            age_s=self._stamp_s - self._start_s,
            last_measurement_s=self._last_meas_s,
            hits=self._hits,
            measurement=None if accepted is None else accepted.meas,
            n_candidates=n_candidates,
            n_size_rejected=n_rejected,
            recent_hit_ratio=self._recent_ratio(),
        )

    def _estimate(self, kf: KalmanFilter, R_ned_body: Mat3) -> RelativeEstimate:
        x = kf.x[:, 0]
        acc = self._kf_acc
        if acc is None:
            return RelativeEstimate(x[:3].copy(), x[3:].copy(), kf.P.copy(), R_ned_body, self.camera)
        xa = acc.x[:, 0]
        return RelativeEstimate(
            xa[:3].copy(), xa[3:6].copy(), acc.P[:6, :6].copy(), R_ned_body, self.camera, xa[6:9].copy()
        )


def _range_collapses(P_pos: np.ndarray, x: np.ndarray, c: _Candidate) -> bool:
    """Whether fusing ``c`` would leave the track far nearer than both the track and ``c`` put it.

    The update's position is ``x + P (P + R)^-1 (z - x)``; with both ellipsoids long along their lines of
    sight it lands where the two rays cross, at the camera when the bearings differ: a triangulation from
    one viewpoint, never a range either of them measured.
    """
    z = c.p_ned_m
    post = x + P_pos @ np.linalg.solve(P_pos + c.R_ned_m2, z - x)
    near = _RANGE_COLLAPSE_FRACTION * min(float(np.linalg.norm(x)), float(np.linalg.norm(z)))
    return float(np.linalg.norm(post)) < near
