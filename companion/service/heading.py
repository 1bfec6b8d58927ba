"""PX4's heading error taken out of what the mission and the camera see, and put back into what PX4 gets.

Why: PX4's heading estimate is off the true heading by several degrees (in PX4 SITL 6-12 deg in formation
flight; real magnetometers give a few degrees). The camera's bearings are turned into NED with that
heading, so the leader's relative position comes out turned by the error against GPS's north, where PX4's
velocities and positions live: at a 5 m slot, 10 deg is 0.9 m of relative-position error, and the
formation law mixes the two frames. :class:`~companion.estimation.ego_velocity.EgoVelocityObserver` fits
the error while GPS is good (from how the attitude's thrust direction explains GPS's accelerations);
:class:`HeadingCorrectedLink` applies it once the fit is trustworthy:

* ``snapshot()`` reports ``yaw_rad`` minus the error (the true heading as well as it is known), so the
  camera's bearings, the mission's heading frame and GPS's velocities share one frame;
* setpoints go out in PX4's frame: a body-frame velocity turned by minus the error (PX4 turns it by its
  own heading), an absolute yaw plus the error.

The applied error follows the fit at a bounded rate, so the frame never jumps under the tracker. Anything
not listed passes through to the wrapped link unchanged.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import replace

from companion.estimation.ego_velocity import EgoModel
from companion.kernel.flight import (
    ExternalPosition,
    Setpoint,
    Severity,
    VehicleState,
    VelocityBodySetpoint,
)
from companion.kernel.frames import wrap_pi
from companion.vehicle.link import VehicleLink

#: The applied heading correction moves towards the fit at most this fast, rad/s.
MAX_SLEW_RAD_S = math.radians(1.0)


class HeadingCorrectedLink:
    """A :class:`VehicleLink` seen through the fitted heading error (see the module's docstring)."""

    def __init__(self, link: VehicleLink) -> None:
        self.link = link
        #: The correction applied now, rad (PX4's heading minus the true one).
        self.applied_rad = 0.0
        self._stamp_s: float | None = None

    def update(self, model: EgoModel | None, now_s: float) -> str | None:
        """Move the applied correction towards a trustworthy fit; hold it without a fit (GPS lost).

        A fit no longer trusted holds the correction while it still agrees with it (within three sigma)
        and takes it back towards itself once it clearly does not: a heading error the fit has stopped
        seeing is not kept for the rest of the flight. Returns a line for the operator when a correction
        starts or ends (it turns every bearing the camera gives), else None.
        """
        was_on = self.applied_rad != 0.0
        target = self.applied_rad
        if model is not None:
            e = model.heading_error_rad
            if model.heading_trusted:
                target = e
            elif abs(e - self.applied_rad) > 3.0 * model.heading_sigma_rad:
                target = 0.0 if e * self.applied_rad <= 0.0 else e  # towards the fit, never past zero
        dt = 0.0 if self._stamp_s is None else max(0.0, now_s - self._stamp_s)
        self._stamp_s = now_s
        step = MAX_SLEW_RAD_S * dt
        self.applied_rad += max(-step, min(step, target - self.applied_rad))
        if was_on == (self.applied_rad != 0.0):
            return None
        if was_on:
            return "heading correction off: the fit no longer sees PX4's heading error"
        sigma_deg = math.degrees(model.heading_sigma_rad) if model is not None else math.nan
        return (
            f"heading correction on: PX4's heading is off the true one by {math.degrees(target):+.1f} deg "
            f"(fit sigma {sigma_deg:.1f} deg); applying it at "
            f"{math.degrees(MAX_SLEW_RAD_S):.0f} deg/s"
        )

    def snapshot(self) -> VehicleState:
        st = self.link.snapshot()
        if self.applied_rad == 0.0 or not math.isfinite(st.yaw_rad):
            return st
        return replace(st, yaw_rad=wrap_pi(st.yaw_rad - self.applied_rad))

    def to_px4(self, setpoint: Setpoint) -> Setpoint:
        """A setpoint in the corrected frame, as PX4 must get it."""
        e = self.applied_rad
        if e == 0.0:
            return setpoint
        if isinstance(setpoint, VelocityBodySetpoint):
            f, r, d = setpoint.v_body_m_s
            c, s = math.cos(e), math.sin(e)
            return replace(setpoint, v_body_m_s=(c * f + s * r, -s * f + c * r, d))
        return replace(setpoint, yaw_rad=wrap_pi(setpoint.yaw_rad + e))

    async def set_setpoint(self, setpoint: Setpoint) -> None:
        await self.link.set_setpoint(self.to_px4(setpoint))

    async def start_offboard(self, setpoint: Setpoint) -> None:
        await self.link.start_offboard(self.to_px4(setpoint))

    async def send_external_position(self, fix: ExternalPosition) -> None:
        if self.applied_rad != 0.0 and math.isfinite(fix.yaw_rad):
            fix = replace(fix, yaw_rad=wrap_pi(fix.yaw_rad + self.applied_rad))
        await self.link.send_external_position(fix)

    # The rest is the wrapped link's own.
    async def arm(self) -> None:
        await self.link.arm()

    async def disarm(self) -> None:
        await self.link.disarm()

    async def takeoff(self, altitude_m: float) -> None:
        await self.link.takeoff(altitude_m)

    async def land(self) -> None:
        await self.link.land()

    async def hold(self) -> None:
        await self.link.hold()

    async def return_to_launch(self) -> None:
        await self.link.return_to_launch()

    async def stop_offboard(self) -> None:
        await self.link.stop_offboard()

    async def release_offboard(self) -> None:
        await self.link.release_offboard()

    async def send_status_text(self, text: str, severity: Severity) -> None:
        await self.link.send_status_text(text, severity)

    async def send_onboard_computer_status(self, fields: Mapping[str, int | list[int]]) -> None:
        await self.link.send_onboard_computer_status(fields)
