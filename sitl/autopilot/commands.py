"""The autopilot's MAVLink commands (COMMAND_LONG / COMMAND_INT), each decided as PX4 decides it.

:class:`Commands` is the part of :class:`sitl.autopilot.mavlink.MavlinkEndpoint` that answers commands:
:meth:`Commands.run` returns the MAV_RESULT the endpoint acknowledges on the link the command came from.
Arming, modes and takeoff go through the vehicle's :class:`~sitl.autopilot.flight.FlightLogic`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Final

from pymavlink.dialects.v20 import common as mavlink

from sitl.autopilot import telemetry
from sitl.autopilot.commander import mode_can_run
from sitl.autopilot.flight import FlightLogic
from sitl.autopilot.modes import NavState, nav_state_from_mode
from sitl.autopilot.state import (
    ACCEPTED,
    DENIED,
    FAILED,
    SEV_CRITICAL,
    SEV_EMERGENCY,
    SEV_INFO,
    SEV_WARNING,
    TEMPORARILY_REJECTED,
    UNSUPPORTED,
    AutopilotState,
    Home,
)
from sitl.physics.gps import GpsFailure

FORCE_MAGIC: Final = 21196
INJECT_UNIT_GPS: Final = 4
_INJECT_TYPES = {0: None, 1: GpsFailure.OFF, 2: GpsFailure.STUCK, 4: GpsFailure.WRONG}


class Commands:
    """The command handlers of one vehicle's autopilot, on its state ``s`` and flight logic."""

    def __init__(self, s: AutopilotState, flight: FlightLogic) -> None:
        self.s = s
        self.flight = flight

    def run(self, command: int, p: tuple[float, ...], link: int | None) -> int:
        """Decide one command (params ``p``: param1..7, x/y as degrees for COMMAND_INT); a MAV_RESULT."""
        handler = _COMMANDS.get(command)
        if handler is None:
            return UNSUPPORTED
        # Decide on the current state: a setpoint that arrived since the last 50 Hz update counts
        # (MAVSDK sends its first setpoint and the mode switch back to back).
        self.flight.update_flags()
        return handler(self, p, link)

    def _cmd_arm_disarm(self, p: tuple[float, ...], link: int | None) -> int:
        forced = p[1] == FORCE_MAGIC
        if p[0] == 1.0:
            result, text = self.flight.arm(forced)
            if text:
                self.s.statustext(SEV_CRITICAL, text)
            return result
        if p[0] == 0.0:
            if not self.s.armed:
                return ACCEPTED
            if not forced and not self.s.landed:
                self.s.statustext(SEV_CRITICAL, "Disarming denied: not landed")
                return TEMPORARILY_REJECTED
            self.flight.disarm("Disarmed by external command")
            return ACCEPTED
        return UNSUPPORTED

    def _cmd_set_mode(self, p: tuple[float, ...], link: int | None) -> int:
        base, main, sub = p[0], p[1], p[2]
        if math.isnan(base) or math.isnan(main) or not int(base) & 1:
            return DENIED
        nav = nav_state_from_mode(int(main), int(sub) if not math.isnan(sub) else 0)
        if nav is None:
            return DENIED
        return self._request_mode(nav)

    def _request_mode(self, nav: NavState) -> int:
        if nav is NavState.AUTO_LAND or not self.s.armed or mode_can_run(nav, self.s.flags):
            if nav is NavState.AUTO_LAND and self.s.armed and nav is not self.s.user_mode:
                self.s.statustext(SEV_INFO, "Landing at current position")
            self.flight.set_user_mode(nav)
            return ACCEPTED
        self.s.statustext(SEV_CRITICAL, f"Switching to {nav.ui_name} is currently not available")
        return TEMPORARILY_REJECTED

    def _cmd_takeoff(self, p: tuple[float, ...], link: int | None) -> int:
        if self.s.armed and not mode_can_run(NavState.AUTO_TAKEOFF, self.s.flags):
            self.s.statustext(SEV_CRITICAL, "Switching to Takeoff is currently not available")
            return TEMPORARILY_REJECTED
        self.s.takeoff_target_d_m = self.flight.takeoff_d_from_alt(p[6])
        self.flight.set_user_mode(NavState.AUTO_TAKEOFF)
        return ACCEPTED

    def _cmd_land(self, p: tuple[float, ...], link: int | None) -> int:
        return self._request_mode(NavState.AUTO_LAND)

    def _cmd_rtl(self, p: tuple[float, ...], link: int | None) -> int:
        return self._request_mode(NavState.AUTO_RTL)

    def _cmd_reposition(self, p: tuple[float, ...], link: int | None) -> int:
        lat, lon, alt = p[4], p[5], p[6]
        if not self.s.flags.global_position_valid or math.isnan(lat) or math.isnan(lon):
            return TEMPORARILY_REJECTED
        if abs(lat) > 90.0 or abs(lon) > 180.0:
            return DENIED
        n, e, _ = self.s.origin.to_ned(lat, lon, 0.0)
        d = self.s.origin.alt0_m - alt if not math.isnan(alt) else self.s.est.d_m
        if abs(n) > 1e6 or abs(e) > 1e6:
            return DENIED
        if p[0] == p[0] and p[0] > 0:
            self.s.navigator.set_cruise_speed(p[0])
        self.s.hold_target = (n, e, d)
        result = self._request_mode(NavState.AUTO_LOITER)
        if result == ACCEPTED:
            self.s.navigator.set_hold_target((n, e, d), p[3])
        return result

    def _cmd_change_speed(self, p: tuple[float, ...], link: int | None) -> int:
        speed = p[1]
        if math.isnan(speed):
            return DENIED
        self.s.navigator.set_cruise_speed(min(speed, self.s.pv["MPC_XY_VEL_MAX"]) if speed > 0 else None)
        return ACCEPTED

    def _cmd_set_home(self, p: tuple[float, ...], link: int | None) -> int:
        if p[0] == 1.0:
            if not self.s.flags.global_position_valid:
                return DENIED
            self.flight.set_home_here()
            return ACCEPTED
        lat, lon, alt = p[4], p[5], p[6]
        if (
            not (math.isfinite(lat) and math.isfinite(lon) and math.isfinite(alt))
            or abs(lat) > 90
            or abs(lon) > 180
        ):
            return DENIED
        n, e, d = self.s.origin.to_ned(lat, lon, alt)
        self.s.home = Home(lat, lon, alt, n, e, d)
        self.s.broadcast(telemetry.home_position(self.s))
        return ACCEPTED

    def _cmd_terminate(self, p: tuple[float, ...], link: int | None) -> int:
        if p[0] == p[0] and p[0] > 0.5:
            self.s.statustext(SEV_EMERGENCY, "Flight termination active")
            self.flight.disarm(None)
        return ACCEPTED

    def _cmd_set_message_interval(self, p: tuple[float, ...], link: int | None) -> int:
        if link is None or not (p[0] == p[0] and p[1] == p[1]):
            return FAILED
        return ACCEPTED if self.s.links[link].set_interval(int(p[0]), p[1]) else FAILED

    def _cmd_request_message(self, p: tuple[float, ...], link: int | None) -> int:
        if p[0] != p[0]:
            return DENIED
        return self._send_requested(int(p[0]), link)

    def _send_requested(self, msg_id: int, link: int | None) -> int:
        builder = telemetry.BUILDERS.get(msg_id)
        msg = builder(self.s) if builder is not None else None
        if msg is None:
            return DENIED
        self.s.reply(link, msg)
        return ACCEPTED

    def _cmd_request_autopilot_capabilities(self, p: tuple[float, ...], link: int | None) -> int:
        return self._send_requested(mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION, link)

    def _cmd_get_home_position(self, p: tuple[float, ...], link: int | None) -> int:
        return self._send_requested(mavlink.MAVLINK_MSG_ID_HOME_POSITION, link)

    def _cmd_inject_failure(self, p: tuple[float, ...], link: int | None) -> int:
        if int(self.s.pv["SYS_FAILURE_EN"]) != 1:
            self.s.statustext(SEV_WARNING, "Failure injection disabled")
            return DENIED
        unit = int(p[0]) if p[0] == p[0] else -1
        ftype = int(p[1]) if p[1] == p[1] else -1
        if unit != INJECT_UNIT_GPS or ftype not in _INJECT_TYPES:
            return UNSUPPORTED
        failure = _INJECT_TYPES[ftype]
        self.s.gps.injected = None if failure is None else failure
        if failure is None:
            self.s.statustext(SEV_INFO, "CMD_INJECT_FAILURE, GPS ok")
        else:
            self.s.statustext(SEV_WARNING, f"CMD_INJECT_FAILURE, GPS {failure.value}")
        return ACCEPTED


_CommandHandler = Callable[[Commands, tuple[float, ...], "int | None"], int]

_COMMANDS: Final[dict[int, _CommandHandler]] = {
    mavlink.MAV_CMD_COMPONENT_ARM_DISARM: Commands._cmd_arm_disarm,
    mavlink.MAV_CMD_DO_SET_MODE: Commands._cmd_set_mode,
    mavlink.MAV_CMD_NAV_TAKEOFF: Commands._cmd_takeoff,
    mavlink.MAV_CMD_NAV_LAND: Commands._cmd_land,
    mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH: Commands._cmd_rtl,
    mavlink.MAV_CMD_DO_REPOSITION: Commands._cmd_reposition,
    mavlink.MAV_CMD_DO_CHANGE_SPEED: Commands._cmd_change_speed,
    mavlink.MAV_CMD_DO_SET_HOME: Commands._cmd_set_home,
    mavlink.MAV_CMD_DO_FLIGHTTERMINATION: Commands._cmd_terminate,
    mavlink.MAV_CMD_SET_MESSAGE_INTERVAL: Commands._cmd_set_message_interval,
    mavlink.MAV_CMD_REQUEST_MESSAGE: Commands._cmd_request_message,
    mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES: Commands._cmd_request_autopilot_capabilities,
    mavlink.MAV_CMD_GET_HOME_POSITION: Commands._cmd_get_home_position,
    mavlink.MAV_CMD_INJECT_FAILURE: Commands._cmd_inject_failure,
}
