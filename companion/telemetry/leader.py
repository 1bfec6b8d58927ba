"""The leader's shared geodetic position (from MQTT) in the follower's local NED frame.

PX4's local NED frame has its origin at the EKF origin. We learn that origin from the follower's own
telemetry while its GPS is good (geodetic position minus local position) and keep it through a GPS
loss, which is exactly when the shared position is needed (the ``vision_external_position`` fallback).
A flat-earth (local tangent plane) conversion is used: the error is below 1 cm per km of separation
squared over the Earth's radius, far below GPS noise at formation distances.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

#: WGS-84 semi-major axis (m) and first eccentricity squared.
_A_M = 6378137.0
_E2 = 6.69437999014e-3

Vec3T = tuple[float, float, float]


@dataclass(frozen=True, slots=True)
class GeoOrigin:
    """The geodetic point of local NED (0, 0, 0)."""

    lat_deg: float
    lon_deg: float
    alt_amsl_m: float

    def _radii_m(self) -> tuple[float, float]:
        s = math.sin(math.radians(self.lat_deg))
        w = math.sqrt(1.0 - _E2 * s * s)
        r_meridian = _A_M * (1.0 - _E2) / w**3
        r_normal = _A_M / w
        return r_meridian, r_normal

    def to_ned(self, lat_deg: float, lon_deg: float, alt_amsl_m: float) -> Vec3T:
        """Local NED of a geodetic point, m."""
        r_m, r_n = self._radii_m()
        north = math.radians(lat_deg - self.lat_deg) * r_m
        dlon = (lon_deg - self.lon_deg + 540.0) % 360.0 - 180.0
        east = math.radians(dlon) * r_n * math.cos(math.radians(self.lat_deg))
        return (north, east, self.alt_amsl_m - alt_amsl_m)

    def to_geodetic(self, p_ned_m: Vec3T) -> tuple[float, float, float]:
        """Geodetic point of a local NED position (inverse of :meth:`to_ned`)."""
        r_m, r_n = self._radii_m()
        lat = self.lat_deg + math.degrees(p_ned_m[0] / r_m)
        lon = self.lon_deg + math.degrees(p_ned_m[1] / (r_n * math.cos(math.radians(self.lat_deg))))
        return lat, lon, self.alt_amsl_m - p_ned_m[2]


#: The local position is carried to the geodetic report's sample time over at most this long, s: the two
#: reports are sampled milliseconds apart; a larger gap is a stale stream, not a delay to bridge.
MAX_PAIRING_GAP_S = 0.25


def local_at(p_ned_m: Vec3T, v_ned_m_s: Vec3T, local_stamp_s: float, at_s: float) -> Vec3T:
    """The local position sampled at ``local_stamp_s`` carried at ``v_ned_m_s`` to ``at_s`` (NED, m).

    PX4 samples GLOBAL_POSITION_INT and LOCAL_POSITION_NED apart (5-25 ms on the wire); pairing them as
    they are moves the origin by the vehicle's speed times that gap, a few centimetres at 2 m/s, and
    jittering report to report.
    """
    dt_s = at_s - local_stamp_s
    if not math.isfinite(dt_s) or abs(dt_s) > MAX_PAIRING_GAP_S:
        return p_ned_m
    return (
        p_ned_m[0] + v_ned_m_s[0] * dt_s,
        p_ned_m[1] + v_ned_m_s[1] * dt_s,
        p_ned_m[2] + v_ned_m_s[2] * dt_s,
    )


def origin_from_fix(lat_deg: float, lon_deg: float, alt_amsl_m: float, p_ned_m: Vec3T) -> GeoOrigin:
    """The NED origin implied by one simultaneous geodetic fix and local position of the same vehicle."""
    here = GeoOrigin(lat_deg, lon_deg, alt_amsl_m)
    origin = GeoOrigin(*here.to_geodetic((-p_ned_m[0], -p_ned_m[1], -p_ned_m[2])))
    for _ in range(3):  # the radii depend on the origin's latitude: refine until consistent
        n, e, d = origin.to_ned(lat_deg, lon_deg, alt_amsl_m)
        origin = GeoOrigin(*origin.to_geodetic((n - p_ned_m[0], e - p_ned_m[1], d - p_ned_m[2])))
    return origin


class OriginTracker:
    """Keeps the follower's NED origin, refreshed from telemetry only while its GPS fix is good."""

    def __init__(self) -> None:
        self.origin: GeoOrigin | None = None

    def update(
        self,
        gps_fix_type: int,
        lat_deg: float | None,
        lon_deg: float | None,
        alt_amsl_m: float | None,
        p_ned_m: Vec3T | None,
    ) -> None:
        if gps_fix_type < 3 or lat_deg is None or lon_deg is None or alt_amsl_m is None or p_ned_m is None:
            return
        if not all(math.isfinite(v) for v in (lat_deg, lon_deg, alt_amsl_m, *p_ned_m)):
            return
        self.origin = origin_from_fix(lat_deg, lon_deg, alt_amsl_m, p_ned_m)
