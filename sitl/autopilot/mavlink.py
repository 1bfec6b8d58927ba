"""The autopilot's MAVLink endpoint: incoming commands, setpoints, external vision, parameters and the rest.

The third layer of :class:`sitl.autopilot.autopilot.Autopilot`: :meth:`handle_message` dispatches one message
(:data:`MESSAGE_HANDLERS`), commands go through :data:`_COMMANDS`, acknowledged where they came from.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import Any, Final

from pymavlink.dialects.v20 import common as mavlink

from sitl.autopilot import telemetry
from sitl.autopilot.commander import mode_can_run
from sitl.autopilot.control import NAN
from sitl.autopilot.estimator import VisionSample
from sitl.autopilot.flight import AutopilotFlight
from sitl.autopilot.modes import NavState, nav_state_from_mode
from sitl.autopilot.offboard import OffboardSetpoint, parse_attitude_target, parse_global_int, parse_local_ned
from sitl.autopilot.params import PARAM_TYPE_INT32, decode_value, encode_value
from sitl.autopilot.signing import VehicleSigning
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
    Home,
)
from sitl.physics.gps import GpsFailure

log = logging.getLogger("sitl.autopilot")

FORCE_MAGIC: Final = 21196
INJECT_UNIT_GPS: Final = 4
_INJECT_TYPES = {0: None, 1: GpsFailure.OFF, 2: GpsFailure.STUCK, 4: GpsFailure.WRONG}
#: Frames PX4 accepts external-vision poses in: LOCAL_NED 1, LOCAL_FRD 20, and the deprecated
#: MOCAP_NED 14 / VISION_NED 16 that older clients still send (gone from pymavlink's common).
_EV_FRAMES = frozenset({1, 20, 14, 16})


def _text(value: Any) -> str:
    """A MAVLink char[] field as clean text (pymavlink may hand bytes or a str with NULs)."""
    if isinstance(value, bytes | bytearray):
        value = value.decode("ascii", errors="replace")
    return str(value).split("\x00", 1)[0]


def _fin(value: Any) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        return NAN
    return v if math.isfinite(v) else NAN


class AutopilotMavlink(AutopilotFlight):
    """The MAVLink endpoint of an autopilot (see :class:`~sitl.autopilot.autopilot.Autopilot`)."""

    #: MAVLink 2 signing, once SETUP_SIGNING gave a key (None: everything is accepted, nothing signed).
    signing: VehicleSigning | None = None

    # ------------------------------------------------------------------ incoming
    def handle_message(self, msg: Any, link: int | None, src_system: int, src_component: int) -> None:
        """Process one incoming MAVLink message (a pymavlink message object).

        ``link`` is the link index it arrived on (None for in-process senders, which get no reply).
        Never raises on hostile content: a handler bug is counted in ``counters['handler_errors']``
        and logged, and the message is dropped.
        """
        self.counters["messages_in"] += 1
        handler = MESSAGE_HANDLERS.get(msg.get_type())
        if handler is None:
            self.counters["ignored_messages"] += 1
            return
        try:
            handler(self, msg, link, src_system, src_component)
        except Exception:
            # The boundary to untrusted input: never let one message take the vehicle down.
            self.counters["handler_errors"] += 1
            log.exception("%s: error handling %s", self.name, msg.get_type())

    def _for_us(self, target_system: int, target_component: int | None = None) -> bool:
        if target_system not in (0, self.sysid):
            self.counters["other_target"] += 1
            return False
        if target_component is not None and target_component not in (0, 1):
            self.counters["other_target"] += 1
            return False
        return True

    def _on_heartbeat(self, msg: Any, link: int | None, src_system: int, src_component: int) -> None:
        self.counters["heartbeats_in"] += 1

    # --- commands
    def _on_command_long(self, msg: Any, link: int | None, src_system: int, src_component: int) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        params = tuple(_fin(getattr(msg, f"param{i}")) for i in range(1, 8))
        self._command(int(msg.command), params, link, src_system, src_component)

    def _on_command_int(self, msg: Any, link: int | None, src_system: int, src_component: int) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        params = (
            _fin(msg.param1), _fin(msg.param2), _fin(msg.param3), _fin(msg.param4),
            int(msg.x) * 1e-7, int(msg.y) * 1e-7, _fin(msg.z),
        )  # fmt: skip
        self._command(int(msg.command), params, link, src_system, src_component)

    def _ack(self, command: int, result: int, link: int | None, src_system: int, src_component: int) -> None:
        self._reply(
            link, mavlink.MAVLink_command_ack_message(command, result, 0, 0, src_system, src_component)
        )

    def _command(
        self, command: int, p: tuple[float, ...], link: int | None, src_system: int, src_component: int
    ) -> None:
        handler = _COMMANDS.get(command)
        if handler is None:
            result = UNSUPPORTED
        else:
            # Decide on the current state: a setpoint that arrived since the last 50 Hz update counts
            # (MAVSDK sends its first setpoint and the mode switch back to back).
            self._update_flags()
            result = handler(self, p, link)
        self._ack(command, result, link, src_system, src_component)

    def _cmd_arm_disarm(self, p: tuple[float, ...], link: int | None) -> int:
        forced = p[1] == FORCE_MAGIC
        if p[0] == 1.0:
            result, text = self._arm(forced)
            if text:
                self.statustext(SEV_CRITICAL, text)
            return result
        if p[0] == 0.0:
            if not self.armed:
                return ACCEPTED
            if not forced and not self.landed:
                self.statustext(SEV_CRITICAL, "Disarming denied: not landed")
                return TEMPORARILY_REJECTED
            self._disarm("Disarmed by external command")
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
        if nav is NavState.AUTO_LAND or not self.armed or mode_can_run(nav, self.flags):
            if nav is NavState.AUTO_LAND and self.armed and nav is not self.user_mode:
                self.statustext(SEV_INFO, "Landing at current position")
            self._set_user_mode(nav)
            return ACCEPTED
        self.statustext(SEV_CRITICAL, f"Switching to {nav.ui_name} is currently not available")
        return TEMPORARILY_REJECTED

    def _cmd_takeoff(self, p: tuple[float, ...], link: int | None) -> int:
        if self.armed and not mode_can_run(NavState.AUTO_TAKEOFF, self.flags):
            self.statustext(SEV_CRITICAL, "Switching to Takeoff is currently not available")
            return TEMPORARILY_REJECTED
        self._takeoff_target_d_m = self._takeoff_d_from_alt(p[6])
        self._set_user_mode(NavState.AUTO_TAKEOFF)
        return ACCEPTED

    def _cmd_land(self, p: tuple[float, ...], link: int | None) -> int:
        return self._request_mode(NavState.AUTO_LAND)

    def _cmd_rtl(self, p: tuple[float, ...], link: int | None) -> int:
        return self._request_mode(NavState.AUTO_RTL)

    def _cmd_reposition(self, p: tuple[float, ...], link: int | None) -> int:
        lat, lon, alt = p[4], p[5], p[6]
        if not self.flags.global_position_valid or math.isnan(lat) or math.isnan(lon):
            return TEMPORARILY_REJECTED
        if abs(lat) > 90.0 or abs(lon) > 180.0:
            return DENIED
        n, e, _ = self.origin.to_ned(lat, lon, 0.0)
        d = self.origin.alt0_m - alt if not math.isnan(alt) else self.est.d_m
        if abs(n) > 1e6 or abs(e) > 1e6:
            return DENIED
        if p[0] == p[0] and p[0] > 0:
            self.navigator.set_cruise_speed(p[0])
        self._hold_target = (n, e, d)
        result = self._request_mode(NavState.AUTO_LOITER)
        if result == ACCEPTED:
            self.navigator.set_hold_target((n, e, d), p[3])
        return result

    def _cmd_change_speed(self, p: tuple[float, ...], link: int | None) -> int:
        speed = p[1]
        if math.isnan(speed):
            return DENIED
        self.navigator.set_cruise_speed(min(speed, self._pv["MPC_XY_VEL_MAX"]) if speed > 0 else None)
        return ACCEPTED

    def _cmd_set_home(self, p: tuple[float, ...], link: int | None) -> int:
        if p[0] == 1.0:
            if not self.flags.global_position_valid:
                return DENIED
            self._set_home_here()
            return ACCEPTED
        lat, lon, alt = p[4], p[5], p[6]
        if (
            not (math.isfinite(lat) and math.isfinite(lon) and math.isfinite(alt))
            or abs(lat) > 90
            or abs(lon) > 180
        ):
            return DENIED
        n, e, d = self.origin.to_ned(lat, lon, alt)
        self.home = Home(lat, lon, alt, n, e, d)
        self._broadcast(telemetry.home_position(self))
        return ACCEPTED

    def _cmd_terminate(self, p: tuple[float, ...], link: int | None) -> int:
        if p[0] == p[0] and p[0] > 0.5:
            self.statustext(SEV_EMERGENCY, "Flight termination active")
            self._disarm(None)
        return ACCEPTED

    def _cmd_set_message_interval(self, p: tuple[float, ...], link: int | None) -> int:
        if link is None or not (p[0] == p[0] and p[1] == p[1]):
            return FAILED
        return ACCEPTED if self.links[link].set_interval(int(p[0]), p[1]) else FAILED

    def _cmd_request_message(self, p: tuple[float, ...], link: int | None) -> int:
        if p[0] != p[0]:
            return DENIED
        return self._send_requested(int(p[0]), link)

    def _send_requested(self, msg_id: int, link: int | None) -> int:
        builder = telemetry.BUILDERS.get(msg_id)
        msg = builder(self) if builder is not None else None
        if msg is None:
            return DENIED
        self._reply(link, msg)
        return ACCEPTED

    def _cmd_request_autopilot_capabilities(self, p: tuple[float, ...], link: int | None) -> int:
        return self._send_requested(mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION, link)

    def _cmd_get_home_position(self, p: tuple[float, ...], link: int | None) -> int:
        return self._send_requested(mavlink.MAVLINK_MSG_ID_HOME_POSITION, link)

    def _cmd_inject_failure(self, p: tuple[float, ...], link: int | None) -> int:
        if int(self._pv["SYS_FAILURE_EN"]) != 1:
            self.statustext(SEV_WARNING, "Failure injection disabled")
            return DENIED
        unit = int(p[0]) if p[0] == p[0] else -1
        ftype = int(p[1]) if p[1] == p[1] else -1
        if unit != INJECT_UNIT_GPS or ftype not in _INJECT_TYPES:
            return UNSUPPORTED
        failure = _INJECT_TYPES[ftype]
        self.gps.injected = None if failure is None else failure
        if failure is None:
            self.statustext(SEV_INFO, "CMD_INJECT_FAILURE, GPS ok")
        else:
            self.statustext(SEV_WARNING, f"CMD_INJECT_FAILURE, GPS {failure.value}")
        return ACCEPTED

    # --- setpoints
    def _on_set_position_target_local_ned(
        self, msg: Any, link: int | None, src_system: int, src_component: int
    ) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        parsed = parse_local_ned(msg, self.t_s, self.yaw_est_rad(), self.attitude_q())
        self._accept_setpoint(parsed)

    def _on_set_position_target_global_int(
        self, msg: Any, link: int | None, src_system: int, src_component: int
    ) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        origin = self.origin if self.est.origin_valid else None
        home_alt = self.home.alt_m if self.home is not None else self.origin.alt0_m
        self._accept_setpoint(parse_global_int(msg, self.t_s, origin, home_alt))

    def _on_set_attitude_target(
        self, msg: Any, link: int | None, src_system: int, src_component: int
    ) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        parsed = parse_attitude_target(msg, self.t_s)
        if parsed is not None:
            self._accept_setpoint(parsed)

    def _accept_setpoint(self, parsed: OffboardSetpoint | str) -> None:
        if isinstance(parsed, str):
            self.counters["setpoints_refused"] += 1
            self.statustext(SEV_CRITICAL, parsed)
            return
        self.counters["setpoints"] += 1
        self.offboard_sp = parsed

    # --- external vision
    def _on_vision_position_estimate(
        self, msg: Any, link: int | None, src_system: int, src_component: int
    ) -> None:
        x, y, z = _fin(msg.x), _fin(msg.y), _fin(msg.z)
        if math.isnan(x) or math.isnan(y) or abs(x) > 1e6 or abs(y) > 1e6:
            self.counters["vision_refused"] += 1
            return
        cov = list(msg.covariance) if msg.covariance is not None else []
        std = NAN
        if len(cov) >= 7:
            vx, vy = _fin(cov[0]), _fin(cov[6])
            if not math.isnan(vx) and not math.isnan(vy) and vx > 0 and vy > 0:
                std = math.sqrt(max(vx, vy))
        self._vision = VisionSample(self.t_s, x, y, z, std)
        self.counters["vision"] += 1

    def _on_odometry(self, msg: Any, link: int | None, src_system: int, src_component: int) -> None:
        if int(msg.frame_id) not in _EV_FRAMES:
            self.counters["vision_refused"] += 1
            return
        x, y, z = _fin(msg.x), _fin(msg.y), _fin(msg.z)
        if math.isnan(x) or math.isnan(y) or abs(x) > 1e6 or abs(y) > 1e6:
            self.counters["vision_refused"] += 1
            return
        cov = list(msg.pose_covariance) if msg.pose_covariance is not None else []
        std = NAN
        if len(cov) >= 7:
            vx, vy = _fin(cov[0]), _fin(cov[6])
            if not math.isnan(vx) and not math.isnan(vy) and vx > 0 and vy > 0:
                std = math.sqrt(max(vx, vy))
        vel: tuple[float, float, float] | None = None
        bvx, bvy, bvz = _fin(msg.vx), _fin(msg.vy), _fin(msg.vz)
        if max(abs(bvx), abs(bvy), abs(bvz)) < 100.0:  # False for NaN
            if int(msg.child_frame_id) in (mavlink.MAV_FRAME_BODY_FRD, mavlink.MAV_FRAME_BODY_NED):
                w, qx, qy, qz = self.attitude_q()
                vel = (
                    (1 - 2 * (qy * qy + qz * qz)) * bvx
                    + 2 * (qx * qy - w * qz) * bvy
                    + 2 * (qx * qz + w * qy) * bvz,
                    2 * (qx * qy + w * qz) * bvx
                    + (1 - 2 * (qx * qx + qz * qz)) * bvy
                    + 2 * (qy * qz - w * qx) * bvz,
                    2 * (qx * qz - w * qy) * bvx
                    + 2 * (qy * qz + w * qx) * bvy
                    + (1 - 2 * (qx * qx + qy * qy)) * bvz,
                )
            else:
                vel = (bvx, bvy, bvz)
        self._vision = VisionSample(self.t_s, x, y, z, std, vel)
        self.counters["vision"] += 1

    # --- parameters
    def _param_value(self, name: str) -> mavlink.MAVLink_message:
        spec = self.params.spec(name)
        if spec is None:
            raise KeyError(name)
        index = self.params.index_of(name)
        return mavlink.MAVLink_param_value_message(
            name.encode("ascii"), encode_value(self.params[name], spec.type), spec.type, len(self.params),
            index if index is not None else 65535,
        )  # fmt: skip

    def _on_param_request_list(self, msg: Any, link: int | None, src_system: int, src_component: int) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        for name in self.params.names:
            self._reply(link, self._param_value(name))

    def _on_param_request_read(self, msg: Any, link: int | None, src_system: int, src_component: int) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        index = int(msg.param_index)
        if index == -1:
            name = _text(msg.param_id)
            if self.params.spec(name) is None:
                return  # PX4 stays silent on unknown names
        elif 0 <= index < len(self.params):
            name = self.params.names[index]
        else:
            return
        self._reply(link, self._param_value(name))

    def _on_param_set(self, msg: Any, link: int | None, src_system: int, src_component: int) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        name = _text(msg.param_id)
        spec = self.params.spec(name)
        if spec is None:
            return
        value = decode_value(float(msg.param_value), int(msg.param_type))
        if value is not None:
            if spec.type == PARAM_TYPE_INT32 and int(msg.param_type) == 9:
                value = round(value)  # a float sent for an int parameter: take its value
            self.params.set(name, value)
        # PX4 answers every set (changed or not) with the stored value, on every link.
        self._broadcast(self._param_value(name))

    # --- signing
    def _on_setup_signing(self, msg: Any, link: int | None, src_system: int, src_component: int) -> None:
        """A signing key, as PX4 takes it: only while disarmed; an all-zero key and timestamp turn it off."""
        if not self._for_us(msg.target_system, msg.target_component):
            return
        if self.armed:
            self.counters["signing_refused_armed"] += 1
            log.warning("%s: SETUP_SIGNING refused while armed", self.name)
            return
        key = bytes(msg.secret_key)
        if len(key) != 32:
            self.counters["signing_refused"] += 1
            return
        if not any(key) and int(msg.initial_timestamp) == 0:
            self.signing = None
            log.info("%s: MAVLink signing off", self.name)
            return
        self.signing = VehicleSigning(key, int(msg.initial_timestamp))
        self.counters["signing_key_set"] += 1
        log.info("%s: MAVLink signing key accepted", self.name)

    # --- misc
    def _on_timesync(self, msg: Any, link: int | None, src_system: int, src_component: int) -> None:
        if int(msg.tc1) == 0:
            self._reply(link, mavlink.MAVLink_timesync_message(int(self.t_s * 1e9), int(msg.ts1)))

    def _on_ping(self, msg: Any, link: int | None, src_system: int, src_component: int) -> None:
        if int(msg.target_system) == 0:
            self._reply(
                link,
                mavlink.MAVLink_ping_message(int(self.t_s * 1e6), int(msg.seq), src_system, src_component),
            )

    def _on_mission_request_list(
        self, msg: Any, link: int | None, src_system: int, src_component: int
    ) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        mission_type = int(getattr(msg, "mission_type", 0) or 0)
        self._reply(link, mavlink.MAVLink_mission_count_message(src_system, src_component, 0, mission_type))

    def _on_mission_count(self, msg: Any, link: int | None, src_system: int, src_component: int) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        mission_type = int(getattr(msg, "mission_type", 0) or 0)
        self._reply(
            link,
            mavlink.MAVLink_mission_ack_message(
                src_system, src_component, mavlink.MAV_MISSION_UNSUPPORTED, mission_type
            ),
        )


_CommandHandler = Callable[[AutopilotMavlink, tuple[float, ...], "int | None"], int]

_COMMANDS: Final[dict[int, _CommandHandler]] = {
    mavlink.MAV_CMD_COMPONENT_ARM_DISARM: AutopilotMavlink._cmd_arm_disarm,
    mavlink.MAV_CMD_DO_SET_MODE: AutopilotMavlink._cmd_set_mode,
    mavlink.MAV_CMD_NAV_TAKEOFF: AutopilotMavlink._cmd_takeoff,
    mavlink.MAV_CMD_NAV_LAND: AutopilotMavlink._cmd_land,
    mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH: AutopilotMavlink._cmd_rtl,
    mavlink.MAV_CMD_DO_REPOSITION: AutopilotMavlink._cmd_reposition,
    mavlink.MAV_CMD_DO_CHANGE_SPEED: AutopilotMavlink._cmd_change_speed,
    mavlink.MAV_CMD_DO_SET_HOME: AutopilotMavlink._cmd_set_home,
    mavlink.MAV_CMD_DO_FLIGHTTERMINATION: AutopilotMavlink._cmd_terminate,
    mavlink.MAV_CMD_SET_MESSAGE_INTERVAL: AutopilotMavlink._cmd_set_message_interval,
    mavlink.MAV_CMD_REQUEST_MESSAGE: AutopilotMavlink._cmd_request_message,
    mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES: AutopilotMavlink._cmd_request_autopilot_capabilities,
    mavlink.MAV_CMD_GET_HOME_POSITION: AutopilotMavlink._cmd_get_home_position,
    mavlink.MAV_CMD_INJECT_FAILURE: AutopilotMavlink._cmd_inject_failure,
}


_MessageHandler = Callable[[AutopilotMavlink, Any, "int | None", int, int], None]

#: The messages an autopilot handles, by type name; every other message is counted and ignored.
MESSAGE_HANDLERS: Final[dict[str, _MessageHandler]] = {
    "COMMAND_LONG": AutopilotMavlink._on_command_long,
    "COMMAND_INT": AutopilotMavlink._on_command_int,
    "SET_POSITION_TARGET_LOCAL_NED": AutopilotMavlink._on_set_position_target_local_ned,
    "SET_POSITION_TARGET_GLOBAL_INT": AutopilotMavlink._on_set_position_target_global_int,
    "SET_ATTITUDE_TARGET": AutopilotMavlink._on_set_attitude_target,
    "PARAM_REQUEST_LIST": AutopilotMavlink._on_param_request_list,
    "PARAM_REQUEST_READ": AutopilotMavlink._on_param_request_read,
    "PARAM_SET": AutopilotMavlink._on_param_set,
    "VISION_POSITION_ESTIMATE": AutopilotMavlink._on_vision_position_estimate,
    "ODOMETRY": AutopilotMavlink._on_odometry,
    "TIMESYNC": AutopilotMavlink._on_timesync,
    "PING": AutopilotMavlink._on_ping,
    "MISSION_REQUEST_LIST": AutopilotMavlink._on_mission_request_list,
    "MISSION_COUNT": AutopilotMavlink._on_mission_count,
    "HEARTBEAT": AutopilotMavlink._on_heartbeat,
    "SETUP_SIGNING": AutopilotMavlink._on_setup_signing,
}
