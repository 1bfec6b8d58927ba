"""Local NED <-> WGS84 geodetic conversion around a reference point (pure, plain floats).

A tangent-plane (equirectangular) projection with the WGS84 meridian and prime-vertical radii at the
reference latitude. Over the few hundred metres a Wingman scenario spans, its error is well under a
millimetre, far below GPS noise; PX4's ``map_projection`` does the same job with an azimuthal
projection, and the difference between the two is irrelevant at this range.
"""

from __future__ import annotations

import math

_WGS84_A_M = 6378137.0
_WGS84_F = 1.0 / 298.257223563
_WGS84_E2 = _WGS84_F * (2.0 - _WGS84_F)


class LocalProjection:
    """Converts between geodetic (deg, deg, m above the ellipsoid) and local NED metres.

    Args:
        lat0_deg: Reference latitude (the origin of the local frame).
        lon0_deg: Reference longitude.
        alt0_m: Reference altitude; local down is ``alt0_m - alt_m``.
    """

    __slots__ = (
        "_lat0_rad",
        "_lon0_rad",
        "_m_per_rad_lat",
        "_m_per_rad_lon",
        "alt0_m",
        "lat0_deg",
        "lon0_deg",
    )

    def __init__(self, lat0_deg: float, lon0_deg: float, alt0_m: float) -> None:
        if not (-89.0 <= lat0_deg <= 89.0) or not (-180.0 <= lon0_deg <= 180.0):
            raise ValueError(f"reference out of range: lat {lat0_deg}, lon {lon0_deg}")
        self.lat0_deg = lat0_deg
        self.lon0_deg = lon0_deg
        self.alt0_m = alt0_m
        self._lat0_rad = math.radians(lat0_deg)
        self._lon0_rad = math.radians(lon0_deg)
        s = math.sin(self._lat0_rad)
        w = math.sqrt(1.0 - _WGS84_E2 * s * s)
        meridian_m = _WGS84_A_M * (1.0 - _WGS84_E2) / (w * w * w)
        prime_vertical_m = _WGS84_A_M / w
        self._m_per_rad_lat = meridian_m + alt0_m
        self._m_per_rad_lon = (prime_vertical_m + alt0_m) * math.cos(self._lat0_rad)

    def to_ned(self, lat_deg: float, lon_deg: float, alt_m: float) -> tuple[float, float, float]:
        """Geodetic -> local NED, metres."""
        north_m = (math.radians(lat_deg) - self._lat0_rad) * self._m_per_rad_lat
        east_m = (math.radians(lon_deg) - self._lon0_rad) * self._m_per_rad_lon
        return north_m, east_m, self.alt0_m - alt_m

    def to_geodetic(self, north_m: float, east_m: float, down_m: float) -> tuple[float, float, float]:
        """Local NED (m) -> (lat_deg, lon_deg, alt_m)."""
        lat_deg = math.degrees(self._lat0_rad + north_m / self._m_per_rad_lat)
        lon_deg = math.degrees(self._lon0_rad + east_m / self._m_per_rad_lon)
        return lat_deg, lon_deg, self.alt0_m - down_m
