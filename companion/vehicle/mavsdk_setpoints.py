"""A setpoint handed to MAVSDK's offboard plugin, which then streams it to PX4 at 20 Hz.

Plain translation: the kernel's setpoint types into the plugin's, angles in degrees as MAVSDK takes them.
"""

from __future__ import annotations

import math
from typing import Any

from mavsdk.plugins.offboard import (
    AccelerationNed,
    Attitude,
    PositionNedYaw,
    VelocityBodyYawspeed,
    VelocityNedYaw,
)

from companion.kernel.flight import AttitudeSetpoint, Setpoint, VelocityBodySetpoint, VelocityNedSetpoint


def set_offboard_setpoint(offboard: Any, setpoint: Setpoint) -> None:
    """Give ``setpoint`` to the offboard plugin ``offboard`` (raises MAVSDK's error on refusal)."""
    if isinstance(setpoint, VelocityBodySetpoint):
        f, r, d = setpoint.v_body_m_s
        offboard.set_velocity_body(VelocityBodyYawspeed(f, r, d, math.degrees(setpoint.yaw_rate_rad_s)))
    elif isinstance(setpoint, VelocityNedSetpoint):
        (n, e, d), yaw_deg = setpoint.v_ned_m_s, math.degrees(setpoint.yaw_rad)
        if setpoint.a_ned_m_s2 is None:
            offboard.set_velocity_ned(VelocityNedYaw(n, e, d, yaw_deg))
        else:
            # No position (NaN in every field): PX4 flies the velocity with the acceleration fed forward.
            nan = math.nan
            offboard.set_position_velocity_acceleration_ned(
                PositionNedYaw(nan, nan, nan, yaw_deg),
                VelocityNedYaw(n, e, d, yaw_deg),
                AccelerationNed(*setpoint.a_ned_m_s2),
            )
    else:
        a: AttitudeSetpoint = setpoint
        offboard.set_attitude(
            Attitude(
                math.degrees(a.roll_rad), math.degrees(a.pitch_rad), math.degrees(a.yaw_rad), a.thrust_norm
            )
        )
