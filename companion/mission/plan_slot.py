"""A formation plan's slot turned with the leader, and the neighbours to keep clear of; pure.

With a plan (``formation.slot_leader_m``) the follower's place is fixed in the leader's level heading
frame. :class:`SlotTurner` places it from the leader's shared heading and the rate at which that heading
turns (the slot sweeps round the leader in a turn: an outer slot 9 m out moves at 2 m/s across the line of
sight when the leader turns at 0.25 rad/s). :func:`neighbours_now` brings the other followers' shared
positions to the present, relative to this follower, with or without its own GPS.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from companion.kernel.frames import Vec3, heading_to_ned, wrap_pi
from companion.mission.types import SharedLeaderPosition, SharedNeighbour

#: A shared heading older than this is not used to place the slot, s.
HEADING_STALE_S = 2.0
#: A neighbour's shared position older than this is dropped, s.
NEIGHBOUR_STALE_S = 1.5
#: Low-pass on the heading's rate, s (shares come at about 10 Hz).
TURN_RATE_TAU_S = 0.2


@dataclass(frozen=True, slots=True)
class SlotTarget:
    """The relative position the slot asks for (leader minus follower, NED, m) and its rate (m/s)."""

    p_ned_rel_m: Vec3
    v_ned_rel_m_s: Vec3


@dataclass(frozen=True, slots=True)
class NeighbourNow:
    """A neighbour relative to this follower now: position (NED, m), its velocity and the relative one."""

    p_ned_rel_m: Vec3
    v_ned_m_s: Vec3
    v_ned_rel_m_s: Vec3


class SlotTurner:
    """``slot_leader_m`` (forward, right, down in the leader's heading frame) placed by the shared heading.

    The slot turns at the leader's shared yaw rate where it shares one, else at the low-passed rate of
    its shared headings (which lags the leader's turns by about ``TURN_RATE_TAU_S``).
    """

    def __init__(self, slot_leader_m: tuple[float, float, float]) -> None:
        self.slot = np.asarray(slot_leader_m, dtype=np.float64)
        self._yaw_rad: float | None = None
        self._stamp_s = -math.inf
        self.turn_rate_rad_s = 0.0

    def reset(self) -> None:
        self._yaw_rad = None
        self._stamp_s = -math.inf
        self.turn_rate_rad_s = 0.0

    def update(self, shared: SharedLeaderPosition | None, now_s: float) -> SlotTarget | None:
        """The slot now, or None without a fresh shared heading (the law then holds range and bearing)."""
        if shared is not None and shared.yaw_rad is not None and shared.stamp_s > self._stamp_s:
            if shared.yaw_rate_rad_s is not None:
                self.turn_rate_rad_s = shared.yaw_rate_rad_s
            elif self._yaw_rad is not None:
                dt = shared.stamp_s - self._stamp_s
                if 0.0 < dt < HEADING_STALE_S:
                    rate = wrap_pi(shared.yaw_rad - self._yaw_rad) / dt
                    k = dt / (TURN_RATE_TAU_S + dt)
                    self.turn_rate_rad_s += k * (rate - self.turn_rate_rad_s)
            self._yaw_rad = shared.yaw_rad
            self._stamp_s = shared.stamp_s
        if self._yaw_rad is None or now_s - self._stamp_s > HEADING_STALE_S:
            return None
        yaw = self._yaw_rad + self.turn_rate_rad_s * max(0.0, now_s - self._stamp_s)
        # The follower sits at leader + R(yaw) slot: the leader relative to it is the negative.
        slot_ned = heading_to_ned(self.slot, yaw)
        w = self.turn_rate_rad_s
        v_slot = np.array([-w * slot_ned[1], w * slot_ned[0], 0.0])
        return SlotTarget(-slot_ned, -v_slot)


def neighbours_now(
    neighbours: Sequence[SharedNeighbour],
    now_s: float,
    *,
    p_own_ned_m: Vec3 | None,
    v_own_ned_m_s: Vec3 | None,
    leader_shared: SharedLeaderPosition | None = None,
    p_ned_rel_leader_m: Vec3 | None = None,
    v_ned_rel_leader_m_s: Vec3 | None = None,
) -> list[NeighbourNow]:
    """The neighbours relative to this follower now.

    With its own position (GPS healthy): neighbour minus own. Without it: through the leader, whose shared
    position and the seen relative vector place this follower in the same frame as the neighbours'.
    Neither: none (the depth guard still holds off what the camera sees).
    """
    if not neighbours:
        return []
    if p_own_ned_m is not None:
        p_own = np.asarray(p_own_ned_m, dtype=np.float64)
        v_own = np.zeros(3) if v_own_ned_m_s is None else np.asarray(v_own_ned_m_s, dtype=np.float64)
    elif (
        leader_shared is not None
        and p_ned_rel_leader_m is not None
        and now_s - leader_shared.stamp_s <= NEIGHBOUR_STALE_S
    ):
        v_leader = np.zeros(3) if leader_shared.v_ned_m_s is None else np.asarray(leader_shared.v_ned_m_s)
        age = max(0.0, now_s - leader_shared.stamp_s)
        p_own = np.asarray(leader_shared.p_ned_m) + v_leader * age - np.asarray(p_ned_rel_leader_m)
        v_rel = np.zeros(3) if v_ned_rel_leader_m_s is None else np.asarray(v_ned_rel_leader_m_s)
        v_own = v_leader - v_rel
    else:
        return []
    out: list[NeighbourNow] = []
    for n in neighbours:
        age = now_s - n.stamp_s
        if not 0.0 <= age <= NEIGHBOUR_STALE_S:
            continue
        v_n = np.asarray(n.v_ned_m_s, dtype=np.float64)
        p = np.asarray(n.p_ned_m, dtype=np.float64) + v_n * age - p_own
        out.append(NeighbourNow(p, v_n, v_n - v_own))
    return out


def slot_velocity(p_rel_m: Vec3, u_los: Vec3, target: SlotTarget, kp_slot_1_s: float) -> Vec3:
    """The follower's velocity that flies out the error across the line of sight to a turning slot, m/s.

    The range is the radial law's; this adds ``kp_slot_1_s`` times the cross-range error and the slot's
    own motion (the relative velocity the slot asks for, with the follower's sign), horizontal only.
    """
    e = p_rel_m - np.asarray(target.p_ned_rel_m)
    e[2] = 0.0
    e_cross = e - float(np.dot(e, u_los)) * u_los
    v: Vec3 = kp_slot_1_s * e_cross - np.asarray(target.v_ned_rel_m_s)
    v[2] = 0.0
    return v
