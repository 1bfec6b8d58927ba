"""Bring a camera-time leader estimate to the control instant, with the follower's own motion in between.

A :class:`~companion.mission.types.LeaderEstimate` is valid at its frame's capture instant, 0.05-0.8 s
before the law runs (rendering, detection, a loaded CPU). Flying on it as if it were current adds that
delay to the loop, and mixing it with the follower's *current* velocity (``v_leader = v_follower(now) +
v_rel(stamp)``) closes a positive-feedback path through the feed-forward: the follower's own acceleration
shows up as leader acceleration until the next frame, which made the closed loop oscillate vertically and
overshoot the leader's speed by 60 %. So, all in local NED:

    v_leader   = v_follower(stamp) + v_rel(stamp)              (both at the capture instant)
    p_rel(now) = p_rel(stamp) + v_leader * age - integral_{stamp}^{now} v_follower dt
    v_rel(now) = v_leader - v_follower(now)

``v_follower`` is PX4's velocity estimate, recorded here per control tick; it is only trusted while PX4's
position estimate is valid (GPS healthy). Without it (after a GPS loss) the estimate is flown as captured:
carried forward at its own relative velocity, a derivative of noisy positions, it destabilised the GPS-lost
attitude law once telemetry and setpoints took 12 ms plus a 10 ms spread each way (lockstep, `gps-loss`
seeds 1-4 with config/timing/real-path.toml: max deviation 2.05 / 1.64 / 1.25 / 0.53 m carried forward,
0.25 / 0.31 / 0.46 / 0.34 m as captured; without injected timing both 0.22-0.34 m). Pure: time comes in as
arguments.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass

import numpy as np

from companion.kernel.frames import Vec3

#: Never predict an estimate further ahead than this (s); older ones are the mission's "stale" problem.
MAX_PREDICT_S = 1.0
#: Never predict further past the control instant than this (s): a setpoint's transport delay is
#: milliseconds; a larger figure is a link in trouble, not a delay to plan on.
MAX_AHEAD_S = 0.1
#: How much follower velocity history is kept (s): longer than any estimate may be old.
HISTORY_S = 2.0
#: The newest sample stands for the velocity this long after it (s): telemetry arrives at 30-50 Hz.
HOLD_S = 0.25


@dataclass(frozen=True, slots=True)
class RelativeNow:
    """The relative state at the control instant (leader minus follower, NED)."""

    p_ned_rel_m: Vec3
    v_ned_rel_m_s: Vec3
    #: The leader's own velocity (NED, m/s) when the follower's velocity was known at the stamp, else None.
    v_ned_leader_m_s: Vec3 | None


class EgoMotion:
    """The follower's recent velocities (NED, m/s, PX4's estimate) and the prediction that uses them."""

    def __init__(self) -> None:
        self._t_s: list[float] = []
        self._v: list[Vec3] = []

    def clear(self) -> None:
        """Forget the history (PX4's velocity stopped being valid)."""
        self._t_s.clear()
        self._v.clear()

    def push(self, t_s: float, v_ned_m_s: Vec3) -> None:
        """Record the follower's velocity at ``t_s`` (service clock); out-of-order samples are dropped."""
        v = np.asarray(v_ned_m_s, dtype=np.float64)
        if (self._t_s and t_s <= self._t_s[-1]) or not np.all(np.isfinite(v)):
            return
        self._t_s.append(t_s)
        self._v.append(v)
        cut = bisect.bisect_left(self._t_s, t_s - HISTORY_S)
        if cut > 64:
            del self._t_s[:cut]
            del self._v[:cut]

    def v_at(self, t_s: float) -> Vec3 | None:
        """The velocity at ``t_s`` (linear between samples, the newest held ``HOLD_S``), or None."""
        ts = self._t_s
        if not ts or t_s < ts[0] or t_s > ts[-1] + HOLD_S:
            return None
        if t_s >= ts[-1]:
            return self._v[-1]
        i = bisect.bisect_left(ts, t_s)
        if ts[i] == t_s:
            return self._v[i]
        a = (t_s - ts[i - 1]) / (ts[i] - ts[i - 1])
        out: Vec3 = (1.0 - a) * self._v[i - 1] + a * self._v[i]
        return out

    def displacement(self, t0_s: float, t1_s: float) -> Vec3 | None:
        """The follower's displacement from ``t0_s`` to ``t1_s`` (trapezoid over the samples), or None."""
        v0 = self.v_at(t0_s)
        v1 = self.v_at(t1_s)
        if v0 is None or v1 is None:
            return None
        i0 = bisect.bisect_right(self._t_s, t0_s)
        i1 = bisect.bisect_left(self._t_s, t1_s, lo=i0)
        t = [t0_s, *self._t_s[i0:i1], t1_s]
        v = [v0, *self._v[i0:i1], v1]
        d = np.zeros(3)
        for k in range(len(t) - 1):
            d += 0.5 * (t[k + 1] - t[k]) * (v[k] + v[k + 1])
        return d

    def predict(
        self,
        stamp_s: float,
        p_rel: Vec3,
        v_rel: Vec3,
        now_s: float,
        *,
        a_leader: Vec3 | None = None,
        ahead_s: float = 0.0,
    ) -> RelativeNow:
        """The estimate taken at ``stamp_s`` brought to ``now_s + ahead_s`` (see the module doc).

        ``a_leader`` (NED, m/s^2), when given, carries the leader's velocity forward over the age too.
        ``ahead_s``: how long after ``now_s`` the command made from it acts (the setpoint's transport
        delay); over it the follower keeps its newest velocity, the leader its velocity and acceleration.
        """
        p = np.asarray(p_rel, dtype=np.float64)
        v = np.asarray(v_rel, dtype=np.float64)
        age = min(max(0.0, now_s - stamp_s), MAX_PREDICT_S)
        ahead = min(max(0.0, ahead_s), MAX_AHEAD_S)
        t0 = now_s - age
        v_f0 = self.v_at(t0)
        v_f1 = self.v_at(now_s)
        disp = self.displacement(t0, now_s)
        if v_f0 is None or v_f1 is None or disp is None:
            return RelativeNow(p, v, None)
        v_leader = v_f0 + v
        a = np.zeros(3) if a_leader is None else np.asarray(a_leader, dtype=np.float64)
        span = age + ahead
        p_now = p + v_leader * span + 0.5 * a * span * span - disp - v_f1 * ahead
        v_leader_now = v_leader + a * span
        return RelativeNow(p_now, v_leader_now - v_f1, v_leader_now)
