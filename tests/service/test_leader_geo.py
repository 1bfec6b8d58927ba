from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from companion.telemetry.leader import MAX_PAIRING_GAP_S, GeoOrigin, OriginTracker, local_at, origin_from_fix


@given(
    st.floats(-80, 80),
    st.floats(-179, 179),
    st.floats(-2000, 2000),
    st.floats(-2000, 2000),
    st.floats(-200, 50),
)
def test_ned_round_trip(lat: float, lon: float, n: float, e: float, d: float) -> None:
    o = GeoOrigin(lat, lon, 400.0)
    back = o.to_ned(*o.to_geodetic((n, e, d)))
    assert back == pytest.approx((n, e, d), abs=1e-6)


def test_known_distance_near_zurich() -> None:
    o = GeoOrigin(47.397742, 8.545594, 488.0)
    n, e, d = o.to_ned(47.397742 + 0.001, 8.545594 + 0.001, 498.0)
    assert n == pytest.approx(111.2, abs=0.3)  # 0.001 deg of latitude
    assert e == pytest.approx(75.4, abs=0.3)  # times cos(47.4 deg)
    assert d == pytest.approx(-10.0)


def test_origin_is_kept_through_gps_loss() -> None:
    o = GeoOrigin(47.0, 8.0, 500.0)
    lat, lon, alt = o.to_geodetic((30.0, -20.0, -10.0))
    tr = OriginTracker()
    tr.update(3, lat, lon, alt, (30.0, -20.0, -10.0))
    assert tr.origin is not None
    assert tr.origin.to_ned(47.0, 8.0, 500.0) == pytest.approx((0.0, 0.0, 0.0), abs=1e-6)
    tr.update(1, 0.0, 0.0, 0.0, (0.0, 0.0, 0.0))  # no fix: ignored
    assert tr.origin.lat_deg == pytest.approx(47.0)
    assert origin_from_fix(47.0, 8.0, 500.0, (0.0, 0.0, 0.0)) == GeoOrigin(47.0, 8.0, 500.0)


def test_the_local_position_is_brought_to_the_geodetic_reports_sample_time() -> None:
    """At 2 m/s north a local report 20 ms older than the geodetic one is 0.04 m behind it; a gap past the
    pairing limit is a stale stream and is not bridged."""
    p, v = (10.0, 0.0, -5.0), (2.0, 0.0, 0.0)
    assert local_at(p, v, 100.00, 100.02) == pytest.approx((10.04, 0.0, -5.0))
    assert local_at(p, v, 100.02, 100.00) == pytest.approx((9.96, 0.0, -5.0))
    assert local_at(p, v, 100.0, 100.0 + MAX_PAIRING_GAP_S + 0.1) == p
    assert local_at(p, v, float("-inf"), 100.0) == p
