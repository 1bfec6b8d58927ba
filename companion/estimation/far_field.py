"""FarFieldCheck: a track that never comes closer, however far the follower flies toward it, is dropped.

A box on something at infinity (a gap between clouds, glare, a far ridge) has no stereo depth, so its
range comes from the box's size and stays whatever the size says, and its bearing in NED never changes
however the follower moves. Taken for the leader, it keeps the same relative position while the follower
flies at it: the law adds closing speed, the "leader" seems to fly away as fast, and the follower climbs
toward the cloud until its altitude limit (a track re-acquired on a gap between clouds took a follower
134 m from the leader and 32 m up in 30 s).

A real leader that the follower flies toward comes closer. So a track that has never had stereo depth is
watched while it stays more than ``margin_m`` beyond the slot's range: once the follower has flown
``flown_m`` toward it (its own velocity along the line of sight, integrated) and the range fell by less
than ``closure_fraction`` of that, it is far-field. The tracker drops it, and boxes without depth within
``cone_deg`` of its NED bearing are ignored for ``ignore_s`` (a far-field object keeps its bearing; a
leader near enough to have depth passes). A leader fleeing straight away as fast as the follower chases
it, out of stereo range, is dropped too: it is lost either way.

Pure: time comes from the frames' stamps.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.kernel.frames import Vec3

#: Longest gap between two steps integrated as flown (s): a longer one is a pause, not flight.
_MAX_STEP_S = 1.0
#: Bearings ignored at once; the oldest goes first.
_MAX_IGNORED = 8


@dataclass(frozen=True, slots=True)
class FarFieldRejection:
    """A track dropped as far-field: where it was (NED unit bearing) and what showed it."""

    stamp_s: float
    u_ned: Vec3
    flown_m: float
    range_start_m: float
    range_now_m: float
    ignore_s: float
    cone_deg: float

    def describe(self) -> str:
        """One line for the service log."""
        el_deg = math.degrees(math.asin(max(-1.0, min(1.0, -float(self.u_ned[2])))))
        az_deg = math.degrees(math.atan2(float(self.u_ned[1]), float(self.u_ned[0]))) % 360.0
        return (
            f"dropped a leader track that never came closer (far-field: sky, glare or far background): "
            f"flew {self.flown_m:.1f} m toward it, its range {self.range_start_m:.1f} -> "
            f"{self.range_now_m:.1f} m without stereo depth; boxes without depth within "
            f"{self.cone_deg:.0f} deg of bearing {az_deg:.0f} deg, elevation {el_deg:+.0f} deg are ignored "
            f"for {self.ignore_s:.0f} s"
        )


class FarFieldCheck:
    """Watches tracks without stereo depth for closure; keeps the bearings of those it dropped."""

    def __init__(
        self,
        *,
        flown_m: float,
        closure_fraction: float,
        min_range_m: float,
        cone_deg: float,
        ignore_s: float,
    ) -> None:
        self.flown_m = flown_m
        self.closure_fraction = closure_fraction
        self.min_range_m = min_range_m
        self.cone_deg = cone_deg
        self.ignore_s = ignore_s
        self._cos_cone = math.cos(math.radians(cone_deg))
        #: The last track id that had a stereo-depth measurement (it is the leader's range, not a size's).
        self._depth_track_id: int | None = None
        #: The watched bearing (NED unit), the follower's flight toward it (m), the range then (m), and the
        #: last step's stamp (s).
        self._u_ned: Vec3 | None = None
        self._flown_m = 0.0
        self._range_start_m = 0.0
        self._last_s = math.nan
        #: Ignored bearings: (NED unit, until stamp s).
        self._ignored: list[tuple[Vec3, float]] = []
        #: Tracks dropped so far.
        self.rejections = 0

    @property
    def ignoring(self) -> bool:
        """Whether any bearing is (or was, until :meth:`ignores` next prunes it) being ignored."""
        return bool(self._ignored)

    def ignores(self, stamp_s: float, p_ned_rel_m: Vec3) -> bool:
        """Whether a measurement without depth here (relative NED, m) lies on an ignored bearing."""
        if not self._ignored:
            return False
        self._ignored = [(u, until) for u, until in self._ignored if until > stamp_s]
        n = float(np.linalg.norm(p_ned_rel_m))
        if n <= 0.0:
            return False
        return any(float(np.dot(u, p_ned_rel_m)) >= self._cos_cone * n for u, _ in self._ignored)

    def step(
        self,
        stamp_s: float,
        track_id: int,
        depth_hit: bool,
        p_ned_rel_m: Vec3 | None,
        v_ned_follower_m_s: Vec3 | None,
    ) -> FarFieldRejection | None:
        """One tracker step: returns a rejection when the track is to be dropped as far-field.

        Args:
            stamp_s: the frame's stamp, s.
            track_id: the tracker's track id at this step.
            depth_hit: the track accepted a stereo-depth measurement at this step.
            p_ned_rel_m: the track's leader position relative to the follower (NED, m); None: no track.
            v_ned_follower_m_s: the follower's velocity at the stamp (NED, m/s); None: unknown (nothing
                is integrated).
        """
        if depth_hit:
            self._depth_track_id = track_id
        last_s, self._last_s = self._last_s, stamp_s
        if p_ned_rel_m is None or track_id == self._depth_track_id:
            self._u_ned = None
            return None
        range_m = float(np.linalg.norm(p_ned_rel_m))
        if range_m <= self.min_range_m:
            self._u_ned = None
            return None
        u = p_ned_rel_m / range_m
        if self._u_ned is None or float(np.dot(u, self._u_ned)) < self._cos_cone:
            self._u_ned, self._flown_m, self._range_start_m = u, 0.0, range_m
            return None
        self._u_ned = u
        dt = stamp_s - last_s
        if v_ned_follower_m_s is not None and 0.0 < dt <= _MAX_STEP_S:
            self._flown_m += dt * float(np.dot(v_ned_follower_m_s, u))
        flown = self._flown_m
        if flown < self.flown_m or self._range_start_m - range_m >= self.closure_fraction * flown:
            return None
        self._ignored.append((u, stamp_s + self.ignore_s))
        del self._ignored[:-_MAX_IGNORED]
        self._u_ned = None
        self.rejections += 1
        return FarFieldRejection(
            stamp_s, u, flown, self._range_start_m, range_m, self.ignore_s, self.cone_deg
        )
