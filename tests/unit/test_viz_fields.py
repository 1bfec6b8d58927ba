"""The viz channels' fields a viewer shows as they are: unknown values as null, not as MAVLink's sentinels."""

from __future__ import annotations

from companion.kernel.flight import VehicleState
from companion.viz.encode import vehicle_fields


def test_satellites_unknown_to_the_autopilot_are_null_not_255() -> None:
    assert vehicle_fields(1.0, VehicleState(gps_satellites=255))["gps_satellites"] is None
    assert vehicle_fields(1.0, VehicleState(gps_satellites=14))["gps_satellites"] == 14
    assert vehicle_fields(1.0, VehicleState(gps_satellites=0))["gps_satellites"] == 0
