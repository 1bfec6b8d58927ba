"""The leader's own velocity and acceleration from what it shares, brought to now; pure.

A leader that shares its autopilot's velocity (``leader.shared_position = "mqtt"``: 10 Hz, a tenth of a
second late) tells the follower when it speeds up far sooner than the camera can: the camera's positions
have to be differentiated twice, and a filter steady enough to lead on reads a start 0.3-0.5 s late. The
acceleration here is the change between consecutive shares, low-passed per share, and the shared velocity
is carried forward by it over the share's age.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.kernel.flight import VehicleState
from companion.kernel.frames import Vec3
from companion.mission.types import SharedLeaderPosition

#: Shares further apart than this start the acceleration afresh (a gap in the link), s.
MAX_SHARE_GAP_S = 0.5
#: The camera-to-shares offset is dropped when the camera has not renewed it for this long, s.
OFFSET_MAX_AGE_S = 10.0
#: The follower's own reported position is carried forward at its velocity at most this long, s: a
#: position report is tens of milliseconds old; an older one is a link in trouble, not a delay to plan on.
OWN_CARRY_MAX_S = 0.25
#: Through camera misses the camera's last relative position is carried on at the shares' relative
#: velocity this long; after it, the shares' position with its offset from the camera stands in, s.
DEAD_RECKON_MAX_S = 2.0


@dataclass(frozen=True, slots=True)
class LeaderMotion:
    """The leader's velocity at the control instant and its acceleration, NED (m/s, m/s^2)."""

    v_ned_m_s: Vec3
    a_ned_m_s2: Vec3


class SharedLeaderMotion:
    """The leader's motion from its shares: ``tau_s`` low-pass per share, unused past ``max_age_s``."""

    def __init__(self, tau_s: float, max_age_s: float, max_accel_m_s2: float) -> None:
        self.tau_s = tau_s
        self.max_age_s = max_age_s
        self.max_accel_m_s2 = max_accel_m_s2
        self._stamp_s: float | None = None
        self._v = np.zeros(3)
        self._a = np.zeros(3)

    def reset(self) -> None:
        self._stamp_s = None
        self._a = np.zeros(3)

    def update(self, share: SharedLeaderPosition | None, now_s: float) -> LeaderMotion | None:
        """The motion at ``now_s`` (same clock as ``share.stamp_s``), or None without a fresh share."""
        if share is None or share.v_ned_m_s is None:
            self.reset()
            return None
        if share.stamp_s != self._stamp_s:
            v = np.asarray(share.v_ned_m_s, dtype=np.float64)
            gap_s = None if self._stamp_s is None else share.stamp_s - self._stamp_s
            if gap_s is not None and 0.0 < gap_s <= MAX_SHARE_GAP_S:
                raw = (v - self._v) / gap_s
                n = float(np.linalg.norm(raw))
                if n > self.max_accel_m_s2:
                    raw *= self.max_accel_m_s2 / n
                self._a += (gap_s / (self.tau_s + gap_s)) * (raw - self._a)
            else:
                self._a = np.zeros(3)
            self._stamp_s, self._v = share.stamp_s, v
        age_s = now_s - share.stamp_s
        if not 0.0 <= age_s <= self.max_age_s:
            return None
        return LeaderMotion(self._v + self._a * age_s, self._a.copy())


def shared_rel_now(
    share: SharedLeaderPosition, motion: LeaderMotion, own: VehicleState, now_s: float
) -> Vec3:
    """Where a fresh share puts the leader now, relative to the follower (NED, m).

    The shared position is carried over its age at the shared velocity, and the follower's own reported
    position (LOCAL_POSITION_NED, sampled tens of milliseconds ago) over its age at its own velocity: left
    behind, it put a leader flying at 2 m/s about 0.05 m too far. Both ends' GPS errors are in it.
    """
    age_s = max(0.0, now_s - share.stamp_s)
    own_age_s = min(max(0.0, now_s - own.local_position_stamp_s), OWN_CARRY_MAX_S)
    p_own = np.asarray(own.p_ned_m) + np.asarray(own.v_ned_m_s) * own_age_s
    rel: Vec3 = np.asarray(share.p_ned_m) + motion.v_ned_m_s * age_s - p_own
    return rel


class SharedRelativeFix:
    """What stands in for the camera while it misses the leader, from the shares (pure).

    For up to ``DEAD_RECKON_MAX_S`` of misses: the camera's last relative position carried on at the
    relative velocity the shares give (the leader's shared velocity minus the follower's own). Both
    autopilots' position estimates wander against each other by 0.1-0.2 m over a second or two as the
    vehicles speed up, which shares plus an averaged offset carried into the gap; velocities are steadier,
    and over a second of misses their error adds a few centimetres.

    Past that, the shares' relative position plus its offset from the camera's: the difference between the
    two is the two GPS receivers' errors (slow: they drift over tens of seconds) plus the camera's noise,
    averaged over ``tau_s`` while the camera sees the leader. An offset not renewed for ``max_age_s`` is
    dropped: the receivers' errors have moved on.
    """

    def __init__(self, tau_s: float, max_age_s: float = OFFSET_MAX_AGE_S) -> None:
        self.tau_s = tau_s
        self.max_age_s = max_age_s
        self._offset_m: Vec3 | None = None
        self._seen_s = -math.inf
        self._carried_m: Vec3 | None = None
        self._carried_s = -math.inf

    def reset(self) -> None:
        self._offset_m = None
        self._seen_s = -math.inf
        self._carried_m = None
        self._carried_s = -math.inf

    def observe(self, rel_camera_m: Vec3, rel_shared_m: Vec3, now_s: float) -> None:
        """The camera sees the leader at ``rel_camera_m`` while the shares put it at ``rel_shared_m``."""
        d = np.asarray(rel_camera_m, dtype=np.float64) - rel_shared_m
        dt = now_s - self._seen_s
        if self._offset_m is None or not 0.0 <= dt <= self.max_age_s:
            self._offset_m = d
        elif dt > 0.0:
            self._offset_m = self._offset_m + (dt / (self.tau_s + dt)) * (d - self._offset_m)
        self._seen_s = now_s
        self._carried_m = np.array(rel_camera_m, dtype=np.float64)
        self._carried_s = now_s

    def fix(self, rel_shared_m: Vec3, v_rel_shared_m_s: Vec3, now_s: float) -> Vec3 | None:
        """The leader's relative position without the camera (NED, m); None without a recent sighting.

        ``rel_shared_m``: where the shares put the leader now; ``v_rel_shared_m_s``: the leader's shared
        velocity minus the follower's own (NED, m/s). Call once per control tick while the camera misses.
        """
        if self._offset_m is None or not 0.0 <= now_s - self._seen_s <= self.max_age_s:
            return None
        if self._carried_m is not None and now_s - self._seen_s <= DEAD_RECKON_MAX_S:
            dt = now_s - self._carried_s
            if dt > 0.0:
                self._carried_m = self._carried_m + np.asarray(v_rel_shared_m_s, dtype=np.float64) * dt
                self._carried_s = now_s
            carried: Vec3 = self._carried_m.copy()
            return carried
        out: Vec3 = rel_shared_m + self._offset_m
        return out
