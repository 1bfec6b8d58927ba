"""``VehicleLink``: what the mission needs from the autopilot, and nothing else.

The real implementation is :class:`companion.vehicle.mavsdk_link.MavsdkVehicleLink`; tests of pure logic use
fakes. Commands raise :class:`~companion.kernel.errors.CommandRejectedError` when the autopilot refuses or
does not answer, and :class:`~companion.kernel.errors.LinkLostError` only when there is no link at all.
Telemetry never raises: a lost link shows as ``VehicleState.connected == False`` and stale stamps.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Protocol

from companion.kernel.flight import ExternalPosition, Setpoint, Severity, VehicleState


class VehicleLink(Protocol):
    """The autopilot, as the mission sees it."""

    def snapshot(self) -> VehicleState:
        """The latest telemetry, assembled now (never blocks)."""
        ...

    async def arm(self) -> None: ...

    async def disarm(self) -> None: ...

    async def takeoff(self, altitude_m: float) -> None:
        """Climb to ``altitude_m`` above home in PX4's Takeoff mode (then PX4 holds)."""
        ...

    async def land(self) -> None:
        """PX4 Land at the current position (needs a position estimate; PX4 falls to Descend without)."""
        ...

    async def hold(self) -> None: ...

    async def return_to_launch(self) -> None: ...

    async def set_setpoint(self, setpoint: Setpoint) -> None:
        """Replace the offboard setpoint. MAVSDK resends it at 20 Hz until replaced or stopped."""
        ...

    async def start_offboard(self, setpoint: Setpoint) -> None:
        """Enter offboard with ``setpoint`` as the first setpoint (handles MAVSDK's start race)."""
        ...

    async def stop_offboard(self) -> None:
        """Stop the setpoint stream now and ask PX4 for Hold."""
        ...

    async def release_offboard(self) -> None:
        """Stop refreshing without asking for any mode: PX4 already left offboard (pilot or failsafe).

        MAVSDK's own watchdog ends its resend once PX4's heartbeats stop saying Offboard.
        """
        ...

    async def send_external_position(self, fix: ExternalPosition) -> None:
        """Give PX4's estimator a position fix from outside (VISION_POSITION_ESTIMATE)."""
        ...

    async def send_status_text(self, text: str, severity: Severity) -> None:
        """Send a STATUSTEXT to the ground station (truncated to MAVLink's 50 characters)."""
        ...

    async def send_onboard_computer_status(self, fields: Mapping[str, int | list[int]]) -> None:
        """Send ONBOARD_COMPUTER_STATUS (390): ``fields`` by MAVLink's names, in its units and sentinels.

        Nothing is sent before the link is connected (the next one goes out once it is).
        """
        ...
