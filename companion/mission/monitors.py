"""The mission machine's health checks: GPS (debounced), the telemetry link, and the leader track.

Each monitor is pure: time comes in as ``now_s``, and only :class:`GpsMonitor` and :class:`LinkMonitor`
remember anything between ticks (the GPS debounce, the link's age average). Staleness is judged on ages
that leave out the service's own stalls (:class:`~companion.kernel.stall.StallAwareAge`, ticked by the
machine): a paused service must not take its own pause for a lost link, GPS or leader.
"""

from __future__ import annotations

import math

import numpy as np

from companion.config import FormationConfig, LinkConfig, MissionConfig
from companion.estimation.leader import LeaderEstimate, TrackStatus
from companion.kernel.flight import VehicleState
from companion.kernel.frames import Vec3
from companion.kernel.stall import StallAwareAge

#: GPS fix data older than this counts as no fix, s.
GPS_STALE_S = 2.0
#: Attitude telemetry older than this makes the attitude law unavailable, s.
ATTITUDE_STALE_S = 0.5
#: Time constant of the attitude-age average that tells a late link (FormationConfig.steady_link_age_s), s.
LINK_AGE_TAU_S = 1.0


class GpsMonitor:
    """The debounced GPS verdict the machine flies on (``ok``), and how long the fix has been bad or good."""

    def __init__(self, m: MissionConfig, ages: StallAwareAge) -> None:
        self.m = m
        self.ages = ages
        self.ok = False
        self.bad_since: float | None = None
        self.good_since: float | None = None

    def good_now(self, veh: VehicleState, now_s: float) -> bool:
        """A 3D fix that is not stale, and PX4 not saying its position estimate is invalid."""
        fix = veh.gps_fix_type >= 3 and self.ages.age_s(veh.gps_stamp_s, now_s) <= GPS_STALE_S
        return fix and veh.position_valid is not False

    def update(self, veh: VehicleState, now_s: float) -> None:
        if self.good_now(veh, now_s):
            self.bad_since = None
            if self.good_since is None:
                self.good_since = now_s
            if not self.ok and now_s - self.good_since >= self.m.gps_restore_s:
                self.ok = True
        else:
            self.good_since = None
            if self.bad_since is None:
                self.bad_since = now_s
            # PX4 saying its position estimate is invalid is final at once; a missing fix needs confirming.
            if veh.position_valid is False or now_s - self.bad_since >= self.m.gps_loss_confirm_s:
                self.ok = False

    def loss_confirmed(self, veh: VehicleState, now_s: float) -> bool:
        """GPS has been bad long enough to call it lost (independent of the debounced verdict)."""
        if veh.position_valid is False:
            return True
        return self.bad_since is not None and now_s - self.bad_since >= self.m.gps_loss_confirm_s


class LinkMonitor:
    """Whether the vehicle's telemetry is fresh, and whether the link has been late lately.

    Late: the attitude's age averaged over ~1 s above ``steady_link_age_s``, and for
    ``steady_link_hold_s`` after (a lossy or slow link; the fast slew swung the follower there).
    """

    def __init__(self, link: LinkConfig, formation: FormationConfig, ages: StallAwareAge) -> None:
        self.link = link
        self.formation = formation
        self.ages = ages
        #: The attitude's age averaged over LINK_AGE_TAU_S, and until when the link counts as late (s).
        self.age_avg_s = 0.0
        self.age_stamp_s = -math.inf
        self.late_until_s = -math.inf

    def ok(self, veh: VehicleState, now_s: float) -> bool:
        """Connected, with attitude telemetry within the link's timeout."""
        return veh.connected and self.ages.age_s(veh.attitude_stamp_s, now_s) <= self.link.telemetry_timeout_s

    def attitude_available(self, veh: VehicleState, now_s: float) -> bool:
        """Attitude fresh enough, and an altitude, for the attitude law."""
        return self.ages.age_s(veh.attitude_stamp_s, now_s) <= ATTITUDE_STALE_S and math.isfinite(
            veh.alt_rel_m
        )

    def watch_age(self, veh: VehicleState, now_s: float) -> None:
        """Note late telemetry, which keeps the fast slew off.

        Late is what arrives later than the link's measured one-way delay (lost and held-up samples): a
        steady delay is taken out of every stamp already (companion/vehicle/boottime.py).
        """
        f = self.formation
        age_s = min(max(now_s - veh.attitude_stamp_s - veh.link_delay_or_zero_s, 0.0), 1.0)
        dt_s = min(max(now_s - self.age_stamp_s, 0.0), 1.0)
        self.age_stamp_s = now_s
        self.age_avg_s += dt_s / (LINK_AGE_TAU_S + dt_s) * (age_s - self.age_avg_s)
        if self.age_avg_s > f.steady_link_age_s:
            self.late_until_s = now_s + f.steady_link_hold_s

    def clean(self, now_s: float) -> bool:
        """No late telemetry within the hold."""
        return now_s >= self.late_until_s


class TrackMonitor:
    """The leader track's health as the mission sees it: fresh, tracked, steady."""

    def __init__(self, m: MissionConfig, ages: StallAwareAge) -> None:
        self.m = m
        self.ages = ages

    def fresh(self, est: LeaderEstimate | None, now_s: float) -> bool:
        return est is not None and self.ages.age_s(est.stamp_s, now_s) <= self.m.stale_estimate_s

    def tracked(self, est: LeaderEstimate | None, now_s: float, *, confirmed_only: bool = False) -> bool:
        if not self.fresh(est, now_s) or est is None:
            return False
        if confirmed_only:
            return est.status == TrackStatus.CONFIRMED
        return est.usable

    def steady(self, est: LeaderEstimate | None) -> bool:
        """Whether a track is old enough and seen often enough to be the leader found again after a loss."""
        return (
            est is not None
            and est.track_age_s >= self.m.reacquire_min_track_s
            and est.recent_hit_ratio >= self.m.reacquire_min_hit_ratio
        )

    def candidate_rel(self, est: LeaderEstimate | None, now_s: float) -> Vec3 | None:
        """Where a fresh track the mission has not taken (yet) puts the leader, relative NED, m."""
        if est is None or not self.fresh(est, now_s) or est.status == TrackStatus.LOST:
            return None
        return np.array(est.p_ned_rel_m, dtype=np.float64)
