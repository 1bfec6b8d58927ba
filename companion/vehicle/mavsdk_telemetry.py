"""The follower's telemetry from MAVSDK's subscriptions, assembled into one :class:`VehicleState`.

:class:`~companion.vehicle.mavsdk_link.MavsdkVehicleLink` feeds each subscription's items to the matching
``on_*`` handler; every item is stamped on arrival on the link's clock (attitude when the autopilot sampled
it, see vehicle/boottime.py). Plain Python over MAVSDK's message objects: nothing here imports mavsdk.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import replace
from typing import Any

from companion.kernel.clock import Clock
from companion.kernel.flight import FlightMode, LandedState, Severity, StatusText, VehicleState
from companion.vehicle.boottime import BootClockMap

log = logging.getLogger("companion.vehicle")

#: ESTIMATOR_STATUS flags PX4's offboard velocity/position checks depend on (VELOCITY_HORIZ | POS_HORIZ_REL).
_EST_POS_VEL_FLAGS = 2 | 8
_SEVERITY_BY_NAME = {s.name: s for s in Severity}


class MavsdkTelemetry:
    """The latest telemetry (:attr:`state`), updated by one handler per MAVSDK subscription."""

    def __init__(self, clock: Clock) -> None:
        self.clock = clock
        self.state = VehicleState()
        #: Attitude is stamped when the autopilot sampled it (see vehicle/boottime.py).
        self.boot_clock = BootClockMap()

    def update(self, **fields: Any) -> None:
        self.state = replace(self.state, **fields)

    def on_connected(self, connected: bool) -> None:
        if connected != self.state.connected:
            (log.info if connected else log.error)("vehicle link: %s", "connected" if connected else "LOST")
        self.update(connected=connected)

    def on_flight_mode(self, mode: Any) -> None:
        # MAVSDK re-emits the mode on every HEARTBEAT: this is also the heartbeat clock.
        try:
            fm = FlightMode[mode.name]
        except KeyError:
            fm = FlightMode.UNKNOWN
        self.update(flight_mode=fm, heartbeat_stamp_s=self.clock.now_s())

    def on_armed(self, armed: bool) -> None:
        self.update(armed=bool(armed))

    def on_landed_state(self, state: Any) -> None:
        try:
            ls = LandedState[state.name]
        except KeyError:
            ls = LandedState.UNKNOWN
        self.update(landed_state=ls)

    def on_attitude(self, e: Any) -> None:
        self.update(
            roll_rad=math.radians(e.roll_deg),
            pitch_rad=math.radians(e.pitch_deg),
            yaw_rad=math.radians(e.yaw_deg),
            # MAVSDK passes ATTITUDE's time_boot_ms on as timestamp_us: stamp when it was sampled.
            attitude_stamp_s=self.boot_clock.stamp(int(e.timestamp_us) // 1000, self.clock.now_s()),
        )

    def on_velocity(self, v: Any) -> None:
        self.update(v_ned_m_s=(v.north_m_s, v.east_m_s, v.down_m_s), velocity_stamp_s=self.clock.now_s())

    def on_position(self, p: Any) -> None:
        self.update(
            lat_deg=p.latitude_deg,
            lon_deg=p.longitude_deg,
            alt_amsl_m=p.absolute_altitude_m,
            alt_rel_m=p.relative_altitude_m,
            global_position_stamp_s=self.clock.now_s(),
        )

    def on_local_position(self, pv: Any) -> None:
        p = pv.position
        self.update(p_ned_m=(p.north_m, p.east_m, p.down_m), local_position_stamp_s=self.clock.now_s())

    def on_gps(self, g: Any) -> None:
        self.update(
            gps_fix_type=int(g.fix_type), gps_satellites=int(g.num_satellites), gps_stamp_s=self.clock.now_s()
        )

    def on_health(self, h: Any) -> None:
        self.update(
            global_position_ok=bool(h.is_global_position_ok),
            local_position_ok=bool(h.is_local_position_ok),
            home_position_ok=bool(h.is_home_position_ok),
            armable=bool(h.is_armable),
            health_stamp_s=self.clock.now_s(),
        )

    def on_battery(self, b: Any) -> None:
        remaining = b.remaining_percent
        frac = remaining / 100.0 if math.isfinite(remaining) else math.nan
        self.update(battery_remaining_frac=frac, battery_voltage_v=b.voltage_v)

    def on_status_text(self, st: Any) -> None:
        severity = _SEVERITY_BY_NAME.get(getattr(st.type, "name", ""), Severity.INFO)
        text = StatusText(self.clock.now_s(), severity, str(st.text))
        log.info("autopilot: [%s] %s", severity.value, text.text)
        self.update(last_status_text=text, status_text_seq=self.state.status_text_seq + 1)

    def on_timesync(self, msg: Any) -> None:
        """The autopilot's answer to our TIMESYNC request (see companion/vehicle/boottime.py)."""
        try:
            fields = json.loads(msg.fields_json)
            tc1, ts1 = int(fields["tc1"]), int(fields["ts1"])
        except (ValueError, KeyError, TypeError):
            return
        now_s = self.clock.now_s()
        if tc1 != 0 and self.boot_clock.sync(tc1 * 1e-9, ts1 * 1e-9, now_s):
            clock = self.boot_clock
            self.update(link_rtt_s=clock.last_rtt_s, link_rtt_stamp_s=now_s, link_delay_s=clock.one_way_s)

    def on_estimator_status(self, msg: Any) -> None:
        try:
            flags = int(json.loads(msg.fields_json)["flags"])
        except (ValueError, KeyError, TypeError):
            return
        valid = (flags & _EST_POS_VEL_FLAGS) == _EST_POS_VEL_FLAGS
        if self.state.position_valid is not None and valid != self.state.position_valid:
            log.warning("vehicle link: PX4 horizontal position estimate %s", "valid" if valid else "INVALID")
        self.update(position_valid=valid, estimator_stamp_s=self.clock.now_s())
