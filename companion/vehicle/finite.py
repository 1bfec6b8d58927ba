"""The last check before the autopilot: nothing that is not a finite number leaves the service.

MAVSDK packs whatever float it is given; PX4 treats NaN in some setpoint fields as "ignore this field"
and rejects others, so a NaN that slipped through the mission would change what the vehicle does in ways
nobody chose. The link refuses such a setpoint (CommandRejectedError, which the mission runner counts and
reports) and the previous one stays in force until MAVSDK's stream guard ends it.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

from companion.kernel.errors import CommandRejectedError
from companion.kernel.flight import (
    AttitudeSetpoint,
    ExternalPosition,
    Setpoint,
    VelocityBodySetpoint,
    VelocityNedSetpoint,
)


def setpoint_values(setpoint: Setpoint) -> tuple[float, ...]:
    """Every number a setpoint puts on the wire."""
    if isinstance(setpoint, VelocityBodySetpoint):
        return (*setpoint.v_body_m_s, setpoint.yaw_rate_rad_s)
    if isinstance(setpoint, VelocityNedSetpoint):
        return (*setpoint.v_ned_m_s, setpoint.yaw_rad, *(setpoint.a_ned_m_s2 or ()))
    a: AttitudeSetpoint = setpoint
    return (a.roll_rad, a.pitch_rad, a.yaw_rad, a.thrust_norm)


def _all_finite(values: Iterable[float]) -> bool:
    try:
        return all(math.isfinite(v) for v in values)
    except TypeError:
        return False


def require_finite_setpoint(setpoint: Setpoint) -> None:
    """CommandRejectedError ``NON_FINITE`` unless every number of ``setpoint`` is finite."""
    if not _all_finite(setpoint_values(setpoint)):
        raise CommandRejectedError("set_setpoint", "NON_FINITE")


def require_finite_position(fix: ExternalPosition) -> None:
    """CommandRejectedError ``NON_FINITE`` unless every number of ``fix`` is finite."""
    values = (*fix.p_ned_m, *fix.variance_m2, fix.yaw_rad, fix.roll_rad, fix.pitch_rad)
    if not _all_finite(values):
        raise CommandRejectedError("vision_position_estimate", "NON_FINITE")
