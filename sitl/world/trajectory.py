"""Leader trajectories (pure): position, velocity and heading as functions of time since the start.

All are horizontal paths at constant altitude, relative to an anchor (the leader's hover point),
in NED metres. Speed ramps up from rest at ``accel_m_s2`` so the leader never demands a velocity step.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

Sample = tuple[float, float, float, float, float]  # north_m, east_m, vn_m_s, ve_m_s, heading_rad


class Trajectory(Protocol):
    """A horizontal path: ``sample(tau_s)`` -> (north, east, vn, ve, heading) relative to its anchor."""

    def sample(self, tau_s: float) -> Sample: ...


@dataclass(frozen=True, slots=True)
class SpeedProfile:
    """Arc length along the path: a constant-acceleration ramp from rest, then ``speed_m_s``."""

    speed_m_s: float
    accel_m_s2: float = 1.0

    def at(self, tau_s: float) -> tuple[float, float]:
        """(arc length m, speed m/s) at ``tau_s`` (0 before the start)."""
        if tau_s <= 0.0:
            return 0.0, 0.0
        t_ramp = self.speed_m_s / self.accel_m_s2
        if tau_s < t_ramp:
            return 0.5 * self.accel_m_s2 * tau_s * tau_s, self.accel_m_s2 * tau_s
        return self.speed_m_s * tau_s - 0.5 * self.speed_m_s * t_ramp, self.speed_m_s


@dataclass(frozen=True, slots=True)
class Straight:
    """A straight line along ``heading_rad``."""

    profile: SpeedProfile
    heading_rad: float = 0.0

    def sample(self, tau_s: float) -> Sample:
        s, v = self.profile.at(tau_s)
        c, si = math.cos(self.heading_rad), math.sin(self.heading_rad)
        return s * c, s * si, v * c, v * si, self.heading_rad


def _arc(s: float, radius_m: float, heading0_rad: float, clockwise: bool) -> tuple[float, float, float]:
    """Point and heading after arc length ``s`` on a circle tangent to ``heading0_rad`` at the origin."""
    sign = 1.0 if clockwise else -1.0
    side = heading0_rad + sign * math.pi / 2.0
    cn, ce = radius_m * math.cos(side), radius_m * math.sin(side)
    heading = heading0_rad + sign * s / radius_m
    back = heading - sign * math.pi / 2.0
    return cn + radius_m * math.cos(back), ce + radius_m * math.sin(back), heading


@dataclass(frozen=True, slots=True)
class Circle:
    """A circle of ``radius_m`` entered tangentially at the anchor (clockwise seen from above)."""

    profile: SpeedProfile
    radius_m: float
    heading_rad: float = 0.0
    clockwise: bool = True

    def sample(self, tau_s: float) -> Sample:
        s, v = self.profile.at(tau_s)
        n, e, heading = _arc(s, self.radius_m, self.heading_rad, self.clockwise)
        return n, e, v * math.cos(heading), v * math.sin(heading), heading


@dataclass(frozen=True, slots=True)
class FigureEight:
    """Two tangent circles of ``radius_m`` meeting at the anchor: one clockwise, one counter-clockwise.

    Constant speed, continuous position and velocity; the turn direction flips at the crossing.
    """

    profile: SpeedProfile
    radius_m: float
    heading_rad: float = 0.0

    def sample(self, tau_s: float) -> Sample:
        s, v = self.profile.at(tau_s)
        lap = 2.0 * math.pi * self.radius_m
        s_mod = s % (2.0 * lap)
        if s_mod < lap:
            n, e, heading = _arc(s_mod, self.radius_m, self.heading_rad, True)
        else:
            n, e, heading = _arc(s_mod - lap, self.radius_m, self.heading_rad, False)
        return n, e, v * math.cos(heading), v * math.sin(heading), heading


@dataclass(frozen=True, slots=True)
class Waypoints:
    """A polyline through ``points_ne_m`` (relative to the anchor; the anchor is the first point)."""

    profile: SpeedProfile
    points_ne_m: tuple[tuple[float, float], ...]
    loop: bool = True

    def __post_init__(self) -> None:
        if len(self.points_ne_m) < 2:
            raise ValueError("a waypoint path needs at least two points")

    def _legs(self) -> Sequence[tuple[tuple[float, float], tuple[float, float]]]:
        pts = list(self.points_ne_m)
        if self.loop:
            pts.append(pts[0])
        return list(itertools.pairwise(pts))

    def sample(self, tau_s: float) -> Sample:
        s, v = self.profile.at(tau_s)
        legs = self._legs()
        lengths = [math.hypot(b[0] - a[0], b[1] - a[1]) for a, b in legs]
        total = sum(lengths)
        if total <= 0.0:
            p = self.points_ne_m[0]
            return p[0], p[1], 0.0, 0.0, 0.0
        if self.loop:
            s %= total
        elif s >= total:
            a, b = legs[-1]
            heading = math.atan2(b[1] - a[1], b[0] - a[0])
            return b[0], b[1], 0.0, 0.0, heading
        for (a, b), length in zip(legs, lengths, strict=True):
            if s <= length and length > 0:
                f = s / length
                heading = math.atan2(b[1] - a[1], b[0] - a[0])
                return (
                    a[0] + f * (b[0] - a[0]),
                    a[1] + f * (b[1] - a[1]),
                    v * math.cos(heading),
                    v * math.sin(heading),
                    heading,
                )
            s -= length
        a, b = legs[-1]
        heading = math.atan2(b[1] - a[1], b[0] - a[0])
        return b[0], b[1], v * math.cos(heading), v * math.sin(heading), heading
