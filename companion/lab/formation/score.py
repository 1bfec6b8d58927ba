"""Scoring a formation from the simulator's truth, per follower.

Each follower against its plan slot, its separation from every other vehicle, and whether its track ever
sat on a neighbour instead of the leader.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from companion.kernel.frames import Vec3, heading_to_ned

#: A track nearer a neighbour than the leader for this many delivered frames in a row is a swap.
SWAP_FRAMES = 3


def slot_world_ned_m(p_leader_ned_m: Vec3, yaw_leader_rad: float, slot_leader_m: Vec3) -> Vec3:
    """Where the plan puts a follower: the leader's position plus its slot turned by the leader's heading."""
    out: Vec3 = np.asarray(p_leader_ned_m, dtype=np.float64) + heading_to_ned(slot_leader_m, yaw_leader_rad)
    return out


@dataclass(slots=True)
class FollowerScore:
    """One follower's formation figures, accumulated from truth samples and delivered frames."""

    name: str
    slot_leader_m: tuple[float, float, float]
    dev_sq_sum_m2: float = 0.0
    dev_n: int = 0
    dev_max_m: float = 0.0
    min_separation_m: float = math.inf
    min_separation_to: str = ""
    swaps: int = 0
    frames_on_neighbour: int = 0
    frames_scored: int = 0
    _wrong_run: int = 0
    deviation_trace: list[tuple[float, float]] = field(default_factory=list)

    def slot_sample(self, t_s: float, p_follower_m: Vec3, p_leader_m: Vec3, yaw_leader_rad: float) -> None:
        """Distance from the plan slot at one instant in formation flight (world NED, m)."""
        want = slot_world_ned_m(p_leader_m, yaw_leader_rad, np.asarray(self.slot_leader_m))
        d = float(np.linalg.norm(np.asarray(p_follower_m) - want))
        self.dev_sq_sum_m2 += d * d
        self.dev_n += 1
        self.dev_max_m = max(self.dev_max_m, d)
        self.deviation_trace.append((t_s, d))

    def separation(self, d_m: float, other: str) -> None:
        if d_m < self.min_separation_m:
            self.min_separation_m = d_m
            self.min_separation_to = other

    def frame(self, p_est_rel_m: Vec3 | None, true_rel_m: dict[str, Vec3]) -> None:
        """A delivered frame's estimate (follower-relative NED, m) against every vehicle's true place."""
        if p_est_rel_m is None:
            self._wrong_run = 0
            return
        self.frames_scored += 1
        nearest = min(true_rel_m, key=lambda k: float(np.linalg.norm(true_rel_m[k] - p_est_rel_m)))
        if nearest == "leader":
            self._wrong_run = 0
            return
        self.frames_on_neighbour += 1
        self._wrong_run += 1
        if self._wrong_run == SWAP_FRAMES:
            self.swaps += 1

    @property
    def rmse_m(self) -> float | None:
        return math.sqrt(self.dev_sq_sum_m2 / self.dev_n) if self.dev_n else None
