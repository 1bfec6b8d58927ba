"""Which detection is the leader when other followers of the same airframe are in view; pure.

In a formation every camera may see neighbours as well as the leader. Between the pose stage and the
tracker, :class:`LeaderIdentity` keeps only the measurements that fit where the leader is expected better
than where any neighbour is expected, and after the tracker it checks that the track itself still fits the
leader: a track that drifts onto a neighbour is a swap, reported and reset, never flown silently.

Expectations (:func:`expectations`) come from what a real formation has:

* GPS healthy: the leader's and the neighbours' shared positions minus the follower's own (tight);
* GPS lost on this follower: the formation plan turned by the leader's shared heading (loose);
* neither: none, and the tracker's gating and continuity decide alone.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from companion.kernel.frames import Vec3, heading_to_ned

log = logging.getLogger(__name__)

#: A measurement or track farther than this many combined sigmas from the leader's expectation is not it.
GATE_SIGMA = 3.0
#: Consecutive frames a track must misfit before it counts as a swap.
SWAP_FRAMES = 4
#: 1-sigma of a shared-position expectation, m (GPS on both ends) and its growth with the share's age, m/s.
SHARED_SIGMA_M = 1.0
#: 1-sigma of a plan expectation, m: how well followers hold their slots, plus the heading's error.
PLAN_SIGMA_M = 2.0


@dataclass(frozen=True, slots=True)
class Expectation:
    """Where a vehicle should be relative to this follower (NED, m) and how sure (1-sigma, m)."""

    p_ned_rel_m: Vec3
    sigma_m: float


@dataclass(slots=True)
class IdentityCounters:
    """Measurements left out (fitting a neighbour, or nowhere near the leader) and swaps found."""

    neighbour_rejected: int = 0
    far_rejected: int = 0
    swaps: int = 0


def expectations(
    *,
    own_p_ned_m: Vec3 | None,
    leader_p_ned_m: Vec3 | None,
    leader_age_s: float,
    leader_yaw_rad: float | None,
    neighbour_p_ned_m: Sequence[Vec3] = (),
    slot_leader_m: Sequence[float] | None = None,
    neighbour_slots_m: Sequence[Sequence[float]] = (),
) -> tuple[Expectation | None, list[Expectation]]:
    """The leader's and the neighbours' expected places relative to this follower (see module doc).

    ``own_p_ned_m``: the follower's position while its GPS is healthy (None after loss). ``leader_p_ned_m``:
    the leader's shared position brought to now, ``leader_age_s`` old. Positions in this follower's local
    NED frame. ``slot_leader_m`` / ``neighbour_slots_m``: the plan's slots (forward, right, down) of this
    follower and of the others, turned by ``leader_yaw_rad``.
    """
    if own_p_ned_m is not None and leader_p_ned_m is not None:
        own = np.asarray(own_p_ned_m, dtype=np.float64)
        leader = Expectation(np.asarray(leader_p_ned_m) - own, SHARED_SIGMA_M + 0.5 * leader_age_s)
        return leader, [Expectation(np.asarray(p) - own, SHARED_SIGMA_M) for p in neighbour_p_ned_m]
    if slot_leader_m is not None and leader_yaw_rad is not None:
        me = heading_to_ned(np.asarray(slot_leader_m, dtype=np.float64), leader_yaw_rad)
        leader = Expectation(-me, PLAN_SIGMA_M)
        others = [
            Expectation(heading_to_ned(np.asarray(s, dtype=np.float64), leader_yaw_rad) - me, PLAN_SIGMA_M)
            for s in neighbour_slots_m
        ]
        return leader, others
    return None, []


class LeaderIdentity:
    """Filters measurements by the expectations and watches the track for a swap."""

    def __init__(self, gate_sigma: float = GATE_SIGMA, swap_frames: int = SWAP_FRAMES) -> None:
        self.gate_sigma = gate_sigma
        self.swap_frames = swap_frames
        self.leader: Expectation | None = None
        self.neighbours: list[Expectation] = []
        self.counters = IdentityCounters()
        self._misfit = 0

    def set(self, leader: Expectation | None, neighbours: list[Expectation]) -> None:
        self.leader = leader
        self.neighbours = neighbours

    @staticmethod
    def _distance(p: Vec3, e: Expectation, sigma_m: float) -> float:
        return float(np.linalg.norm(p - e.p_ned_rel_m)) / math.hypot(e.sigma_m, sigma_m)

    def fits(self, p_ned_rel_m: Vec3, sigma_m: float) -> tuple[bool, bool]:
        """(fits the leader, fits a neighbour better): what a measurement or track at ``p`` looks like."""
        d_leader = math.inf if self.leader is None else self._distance(p_ned_rel_m, self.leader, sigma_m)
        d_near = min((self._distance(p_ned_rel_m, e, sigma_m) for e in self.neighbours), default=math.inf)
        neighbour = d_near < d_leader and d_near <= self.gate_sigma
        leader = (self.leader is None or d_leader <= self.gate_sigma) and not neighbour
        return leader, neighbour

    def keep(self, p_ned_rel_m: Vec3, sigma_m: float) -> bool:
        """Whether a measurement at ``p`` (relative NED, m; 1-sigma ``sigma_m``) may be the leader."""
        if self.leader is None and not self.neighbours:
            return True
        leader, neighbour = self.fits(p_ned_rel_m, sigma_m)
        if neighbour:
            self.counters.neighbour_rejected += 1
        elif not leader:
            self.counters.far_rejected += 1
        return leader

    def check_track(self, stamp_s: float, p_ned_rel_m: Vec3 | None, sigma_m: float) -> bool:
        """True once the confirmed track has misfit the leader for ``swap_frames`` frames: a swap."""
        if p_ned_rel_m is None or self.leader is None:
            self._misfit = 0
            return False
        leader, _ = self.fits(p_ned_rel_m, sigma_m)
        self._misfit = 0 if leader else self._misfit + 1
        if self._misfit < self.swap_frames:
            return False
        self._misfit = 0
        self.counters.swaps += 1
        log.warning(
            "leader identity: the track at %s m left the leader's expected place %s m at t=%.2f s; "
            "track reset (swap %d)",
            np.round(p_ned_rel_m, 1).tolist(),
            np.round(self.leader.p_ned_rel_m, 1).tolist(),
            stamp_s,
            self.counters.swaps,
        )
        return True
