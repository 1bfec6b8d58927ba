"""MAVLink telemetry assembled as MAVSDK's telemetry plugin does, for the message-object link.

Flight mode from HEARTBEAT custom mode, health from SYS_STATUS present/health bits, velocity from
GLOBAL_POSITION_INT, position from LOCAL_POSITION_NED, ``position_valid`` from ESTIMATOR_STATUS, each
stamped on arrival (attitude when the autopilot sampled it, see vehicle/boottime.py). Also the PX4 mode and
severity vocabulary :class:`~companion.vehicle.message_link.MessageVehicleLink` speaks.
"""

from __future__ import annotations

import logging
import math
import struct
from dataclasses import replace
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

from companion.kernel.flight import FlightMode, LandedState, Severity, StatusText, VehicleState
from companion.vehicle.boottime import BootClockMap

log = logging.getLogger("companion.vehicle")

AUTOPILOT_COMPONENT = 1

# SYS_STATUS sensor bits MAVSDK's health reads.
_GPS_BIT, _FLOW_BIT, _VISION_BIT = 32, 64, 128
_PREARM_BIT = 1 << 28
#: ESTIMATOR_STATUS flags PX4's offboard velocity/position checks depend on (VELOCITY_HORIZ | POS_HORIZ_REL).
_EST_POS_VEL_FLAGS = 2 | 8

# PX4 custom modes (main << 16 | sub << 24), as MAVSDK decodes them.
_AUTO_SUB_MODES = {
    1: FlightMode.READY,
    2: FlightMode.TAKEOFF,
    3: FlightMode.HOLD,
    4: FlightMode.MISSION,
    5: FlightMode.RETURN_TO_LAUNCH,
    6: FlightMode.LAND,
    8: FlightMode.FOLLOW_ME,
}
_MAIN_MODES = {
    1: FlightMode.MANUAL,
    2: FlightMode.ALTCTL,
    3: FlightMode.POSCTL,
    5: FlightMode.ACRO,
    6: FlightMode.OFFBOARD,
    7: FlightMode.STABILIZED,
    8: FlightMode.RATTITUDE,
}
_LANDED = {
    1: LandedState.ON_GROUND,
    2: LandedState.IN_AIR,
    3: LandedState.TAKING_OFF,
    4: LandedState.LANDING,
}
_SEVERITY = {
    0: Severity.EMERGENCY,
    1: Severity.ALERT,
    2: Severity.CRITICAL,
    3: Severity.ERROR,
    4: Severity.WARNING,
    5: Severity.NOTICE,
    6: Severity.INFO,
    7: Severity.DEBUG,
}
SEVERITY_CODE = {s: c for c, s in _SEVERITY.items()}


def param_int(value: float, param_type: int) -> int:
    """An integer PARAM_VALUE: PX4 sends INT32 bytewise in the float field; others send the number."""
    if param_type == mavlink.MAV_PARAM_TYPE_INT32:
        return int(struct.unpack("<i", struct.pack("<f", value))[0])
    return round(value)


def flight_mode_of(base_mode: int, custom_mode: int) -> FlightMode:
    """PX4's custom mode as MAVSDK names it (UNKNOWN without the custom-mode flag or for other modes)."""
    if not base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
        return FlightMode.UNKNOWN
    main = (custom_mode >> 16) & 0xFF
    sub = (custom_mode >> 24) & 0xFF
    if main == 4:
        return _AUTO_SUB_MODES.get(sub, FlightMode.UNKNOWN)
    return _MAIN_MODES.get(main, FlightMode.UNKNOWN)


def text_of(raw: Any) -> str:
    """A MAVLink char array as text (bytes or str, NUL padding dropped)."""
    if isinstance(raw, bytes):
        raw = raw.decode("utf-8", "replace")
    return str(raw).rstrip("\x00")


class MavlinkTelemetry:
    """The latest telemetry (:attr:`state`) of one autopilot, from its MAVLink messages."""

    def __init__(self, target_system: int) -> None:
        self.target_system = target_system
        self.state = VehicleState()
        #: Attitude is stamped when the autopilot sampled it (see vehicle/boottime.py).
        self.boot_clock = BootClockMap()

    def update(self, **fields: Any) -> None:
        self.state = replace(self.state, **fields)

    def handle(self, msg: Any, kind: str, now_s: float) -> bool:
        """Take a telemetry message (``kind``: its type) received at ``now_s``; False when it is none."""
        st = self.state
        if kind == "HEARTBEAT":
            if msg.get_srcComponent() not in (AUTOPILOT_COMPONENT, 0):
                return True
            if not st.connected:
                log.info("vehicle link: autopilot found (sysid %d)", self.target_system)
            self.update(
                connected=True,
                heartbeat_stamp_s=now_s,
                armed=bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED),
                flight_mode=flight_mode_of(int(msg.base_mode), int(msg.custom_mode)),
            )
        elif kind == "ATTITUDE":
            sampled_s = self.boot_clock.stamp(int(msg.time_boot_ms), now_s)
            if sampled_s < st.attitude_stamp_s:
                return True
            self.update(roll_rad=msg.roll, pitch_rad=msg.pitch, yaw_rad=msg.yaw, attitude_stamp_s=sampled_s)
        elif kind == "GLOBAL_POSITION_INT":
            sampled_s = self.boot_clock.stamp(int(msg.time_boot_ms), now_s)
            if sampled_s < st.velocity_stamp_s:
                return True  # overtaken by a newer sample (a jittery link reorders)
            self.update(
                v_ned_m_s=(msg.vx / 100.0, msg.vy / 100.0, msg.vz / 100.0),
                velocity_stamp_s=sampled_s,
                lat_deg=msg.lat * 1e-7,
                lon_deg=msg.lon * 1e-7,
                alt_amsl_m=msg.alt / 1000.0,
                alt_rel_m=msg.relative_alt / 1000.0,
                global_position_stamp_s=now_s,
            )
        elif kind == "LOCAL_POSITION_NED":
            sampled_s = self.boot_clock.stamp(int(msg.time_boot_ms), now_s)
            if sampled_s < st.local_position_stamp_s:
                return True
            self.update(
                p_ned_m=(msg.x, msg.y, msg.z), local_position_stamp_s=sampled_s, local_position_ok=True
            )
        elif kind == "GPS_RAW_INT":
            self.update(
                gps_fix_type=int(msg.fix_type), gps_satellites=int(msg.satellites_visible), gps_stamp_s=now_s
            )
        elif kind == "SYS_STATUS":
            present, health = (
                int(msg.onboard_control_sensors_present),
                int(msg.onboard_control_sensors_health),
            )
            ok = present & health
            global_ok = bool(ok & _GPS_BIT)
            self.update(
                global_position_ok=global_ok,
                local_position_ok=global_ok or bool(ok & (_FLOW_BIT | _VISION_BIT)),
                armable=bool(health & _PREARM_BIT),
                health_stamp_s=now_s,
            )
        elif kind == "HOME_POSITION":
            self.update(home_position_ok=True)
        elif kind == "EXTENDED_SYS_STATE":
            self.update(landed_state=_LANDED.get(int(msg.landed_state), LandedState.UNKNOWN))
        elif kind == "ESTIMATOR_STATUS":
            valid = (int(msg.flags) & _EST_POS_VEL_FLAGS) == _EST_POS_VEL_FLAGS
            self.update(position_valid=valid, estimator_stamp_s=now_s)
        elif kind == "BATTERY_STATUS":
            remaining = int(msg.battery_remaining)
            self.update(
                battery_remaining_frac=remaining / 100.0 if remaining >= 0 else math.nan,
                battery_voltage_v=msg.voltages[0] / 1000.0 if msg.voltages[0] != 65535 else math.nan,
            )
        elif kind == "TIMESYNC":
            # Only the answer to our own request (tc1 set, ts1 our send time); the autopilot's requests
            # (tc1 = 0) are not a measure of anything here.
            if int(msg.tc1) != 0 and self.boot_clock.sync(int(msg.tc1) * 1e-9, int(msg.ts1) * 1e-9, now_s):
                clock = self.boot_clock
                self.update(link_rtt_s=clock.last_rtt_s, link_rtt_stamp_s=now_s, link_delay_s=clock.one_way_s)
        elif kind == "STATUSTEXT":
            text = StatusText(now_s, _SEVERITY.get(int(msg.severity), Severity.INFO), text_of(msg.text))
            log.info("autopilot: [%s] %s", text.severity.value, text.text)
            self.update(last_status_text=text, status_text_seq=st.status_text_seq + 1)
        else:
            return False
        return True
