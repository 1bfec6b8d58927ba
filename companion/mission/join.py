"""The join: a planned approach into the slot when the formation starts far from it (pure, time passed in).

Without it, FOLLOW entered 3 m from the slot flies the full PID on the whole error: the command steps to
``kp * error`` (slew-limited), the vehicle pitches hard and overshoots the slot. The join instead moves a
reference from where the follower is to the slot along one straight line in (range, down) error space, at
a bounded relative speed and acceleration (a rest-to-rest trapezoid), and the law flies the error to that
reference with the reference's own rate fed forward. The leader's motion is fed forward by the law as
always, so a join onto a moving leader is the same plan relative to it. The bearing is the yaw loop's
and is not planned.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from companion.kernel.frames import Vec3
from companion.mission.geometry import Slot, SlotError, slot_error

#: The plan's clock runs at full rate while the follower trails the reference by up to this much along the
#: plan (m), and stops at this plus ``LAG_SPAN_M``: a leader that starts off during the join, or a slow
#: vehicle, holds the reference back instead of leaving the gain to sprint after it and overshoot.
LAG_FREE_M = 0.2
LAG_SPAN_M = 0.3
#: A gap between two references longer than this does not advance the plan (s): after a pause of the
#: service the plan goes on from where it was.
MAX_STEP_S = 0.5


@dataclass(frozen=True, slots=True)
class JoinReference:
    """Where the join wants the follower now, as offsets of the slot error and their rates.

    ``range_offset_m``: the planned horizontal range minus the slot's (m; positive: still short of the
    slot's range, leader farther than planned at the end); ``down_offset_m``: the same for the vertical
    error (m, NED down). Rates in m/s, accelerations in m/s^2.
    """

    range_offset_m: float
    range_rate_m_s: float
    down_offset_m: float
    down_rate_m_s: float
    range_accel_m_s2: float = 0.0
    down_accel_m_s2: float = 0.0


def trapezoid(
    distance_m: float, speed_m_s: float, accel_m_s2: float, t_s: float
) -> tuple[float, float, float]:
    """Distance covered (m), speed (m/s) and acceleration (m/s^2) at ``t_s`` of a rest-to-rest move.

    Accelerates at ``accel_m_s2`` to ``speed_m_s`` (or to the triangle's peak on a short move), cruises,
    and brakes at the same rate to stop exactly at ``distance_m``.
    """
    if distance_m <= 0.0 or t_s <= 0.0:
        return 0.0, 0.0, 0.0
    v_peak = min(speed_m_s, math.sqrt(distance_m * accel_m_s2))
    t_ramp = v_peak / accel_m_s2
    t_cruise = (distance_m - v_peak * t_ramp) / v_peak
    total = 2.0 * t_ramp + t_cruise
    if t_s >= total:
        return distance_m, 0.0, 0.0
    if t_s < t_ramp:
        return 0.5 * accel_m_s2 * t_s * t_s, accel_m_s2 * t_s, accel_m_s2
    if t_s < t_ramp + t_cruise:
        return 0.5 * v_peak * t_ramp + v_peak * (t_s - t_ramp), v_peak, 0.0
    left_s = total - t_s
    return distance_m - 0.5 * accel_m_s2 * left_s * left_s, accel_m_s2 * left_s, -accel_m_s2


def trapezoid_duration_s(distance_m: float, speed_m_s: float, accel_m_s2: float) -> float:
    """How long :func:`trapezoid` takes to cover ``distance_m`` (s)."""
    if distance_m <= 0.0:
        return 0.0
    v_peak = min(speed_m_s, math.sqrt(distance_m * accel_m_s2))
    return v_peak / accel_m_s2 + distance_m / v_peak


class JoinPlanner:
    """Plans the join once per entry into the formation and gives its reference every tick.

    :meth:`arm` on entering FOLLOW; the first :meth:`reference` after it plans from the error then (an
    error under ``min_error_m`` needs no plan); :meth:`cancel` on leaving. ``speed_m_s`` 0 turns it off.
    """

    def __init__(self, speed_m_s: float, accel_m_s2: float, min_error_m: float) -> None:
        self.speed_m_s = speed_m_s
        self.accel_m_s2 = accel_m_s2
        self.min_error_m = min_error_m
        self._pending = False
        #: The plan's own clock (s since the start, slowed while the follower trails) and the last call.
        self._tau_s = 0.0
        self._last_s = 0.0
        #: The error at the start along (range, down), m, and its length.
        self._e0 = (0.0, 0.0)
        self._distance_m = 0.0
        self._duration_s = 0.0
        #: Joins planned since the service started.
        self.planned = 0

    @property
    def active(self) -> bool:
        return self._distance_m > 0.0

    def arm(self) -> None:
        """Plan from the next reference's error (entering the formation)."""
        self._pending = self.speed_m_s > 0.0
        self._distance_m = 0.0

    def cancel(self) -> None:
        self._pending = False
        self._distance_m = 0.0

    def reference(self, slot: Slot, p_ned_rel_m: Vec3, yaw_rad: float, now_s: float) -> JoinReference | None:
        """The join's reference now (None: no join, or it is over and the slot itself is flown)."""
        if not (self._pending or self.active):
            return None
        err = slot_error(slot, p_ned_rel_m, np.zeros(3), yaw_rad)
        if self._pending:
            self._pending = False
            self._plan(err, now_s)
            if not self.active:
                return None
        d_range, d_down = self._e0[0] / self._distance_m, self._e0[1] / self._distance_m
        covered_m = trapezoid(self._distance_m, self.speed_m_s, self.accel_m_s2, self._tau_s)[0]
        # How far the follower trails the reference along the plan (m; negative: ahead of it).
        lag_m = err.e_range_m * d_range + err.e_down_m * d_down - (self._distance_m - covered_m)
        clock = min(1.0, max(0.0, 1.0 - (lag_m - LAG_FREE_M) / LAG_SPAN_M))
        step_s = now_s - self._last_s
        self._last_s = now_s
        if 0.0 < step_s <= MAX_STEP_S:
            self._tau_s += clock * step_s
        if self._tau_s >= self._duration_s:
            self._distance_m = 0.0
            return None
        covered_m, speed_m_s, accel_m_s2 = trapezoid(
            self._distance_m, self.speed_m_s, self.accel_m_s2, self._tau_s
        )
        left = 1.0 - covered_m / self._distance_m
        # The reference moves at the plan's speed times its clock's rate.
        speed_m_s *= clock
        accel_m_s2 *= clock * clock
        return JoinReference(
            range_offset_m=self._e0[0] * left,
            range_rate_m_s=-d_range * speed_m_s,
            down_offset_m=self._e0[1] * left,
            down_rate_m_s=-d_down * speed_m_s,
            range_accel_m_s2=-d_range * accel_m_s2,
            down_accel_m_s2=-d_down * accel_m_s2,
        )

    def _plan(self, err: SlotError, now_s: float) -> None:
        distance = math.hypot(err.e_range_m, err.e_down_m)
        if not math.isfinite(distance) or distance < self.min_error_m:
            return
        self._tau_s = 0.0
        self._last_s = now_s
        self._e0 = (err.e_range_m, err.e_down_m)
        self._distance_m = distance
        self._duration_s = trapezoid_duration_s(distance, self.speed_m_s, self.accel_m_s2)
        self.planned += 1


def joined(err: SlotError, ref: JoinReference, accel_lead_s: float = 0.0) -> tuple[SlotError, Vec3]:
    """The error against the join's reference, and the reference's motion as a velocity to feed forward.

    The follower's velocity that keeps the planned range and height is the leader's plus
    ``-range_rate * u_los`` horizontally and ``-down_rate`` vertically (NED, m/s); the horizontal
    acceleration is led by ``accel_lead_s`` as the leader's is (PX4's velocity loop lags both alike).
    """
    shifted = replace(
        err,
        e_range_m=err.e_range_m - ref.range_offset_m,
        e_range_rate_m_s=err.e_range_rate_m_s - ref.range_rate_m_s,
        e_down_m=err.e_down_m - ref.down_offset_m,
    )
    ff = -(ref.range_rate_m_s + accel_lead_s * ref.range_accel_m_s2) * err.u_los
    ff[2] = -ref.down_rate_m_s
    return shifted, ff
