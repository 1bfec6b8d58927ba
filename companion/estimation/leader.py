"""What estimation hands the mission: the leader track's status and estimate, and the depth guard's reading.

The tracker (:mod:`companion.estimation.tracker`) and the perception pipeline produce these; the mission
reads them. They live here so that the mission depends on estimation, never the other way round.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from companion.kernel.compat import StrEnum
from companion.kernel.flight import Vec3T


class TrackStatus(StrEnum):
    """Where the leader track stands (see :mod:`companion.estimation.tracker` for the rules)."""

    TENTATIVE = "tentative"
    CONFIRMED = "confirmed"
    COASTING = "coasting"
    LOST = "lost"


@dataclass(frozen=True, slots=True)
class LeaderEstimate:
    """The tracker's estimate of the leader relative to the follower.

    ``p_ned_rel_m`` is leader minus follower expressed in local NED axes (the follower's attitude applied,
    never its GPS position), ``v_ned_rel_m_s`` its rate. ``stamp_s`` is when the estimate is valid for and
    ``last_measurement_s`` when the last detection went into it, both on the service clock.
    """

    stamp_s: float
    status: TrackStatus
    p_ned_rel_m: Vec3T
    v_ned_rel_m_s: Vec3T
    last_measurement_s: float
    #: How long the track has existed, s, and the share of its recent frames (about 1 s) with a detection
    #: in its gate. Defaults for producers that do not know (a shared or scripted estimate): taken as
    #: long-lived and always seen.
    track_age_s: float = math.inf
    recent_hit_ratio: float = 1.0
    #: Position covariance diagonal in NED, m^2 (for the external-position fix and logging).
    var_ned_rel_m2: Vec3T = (0.25, 0.25, 0.25)
    #: The leader's own acceleration, NED m/s^2, when the tracker estimates it
    #: (``tracker.leader_accel_filter``).
    a_ned_leader_m_s2: Vec3T | None = None
    #: The tracker dropped this track as far-field (it never came closer however far the follower flew at
    #: it: sky, glare); its status is LOST and where it was says nothing of where the leader is.
    far_field: bool = False

    @property
    def usable(self) -> bool:
        """Whether the law may fly on it: confirmed, or coasting through a short dropout."""
        return self.status in (TrackStatus.CONFIRMED, TrackStatus.COASTING)


@dataclass(frozen=True, slots=True)
class ObstacleAhead:
    """The nearest thing the depth camera sees ahead that is not the tracked leader (the depth guard).

    ``p_ned_rel_m``: its position minus the follower's, NED axes, m, at ``stamp_s`` (service clock).
    Taken as static by the separation barrier.
    """

    stamp_s: float
    p_ned_rel_m: Vec3T
