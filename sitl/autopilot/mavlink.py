"""The autopilot's MAVLink endpoint: incoming messages, setpoints, external vision, parameters, streams.

:class:`MavlinkEndpoint` is one part of :class:`sitl.autopilot.autopilot.Autopilot`:
:meth:`~MavlinkEndpoint.handle_message` dispatches one message (:data:`MESSAGE_HANDLERS`), commands go to
its :class:`~sitl.autopilot.commands.Commands` and are acknowledged where they came from, and
:meth:`~MavlinkEndpoint.service_links` queues the streams that are due.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import Any, Final

from pymavlink.dialects.v20 import common as mavlink

from sitl.autopilot import telemetry
from sitl.autopilot.commands import Commands
from sitl.autopilot.control import NAN
from sitl.autopilot.estimator import VisionSample
from sitl.autopilot.flight import FlightLogic
from sitl.autopilot.offboard import OffboardSetpoint, parse_attitude_target, parse_global_int, parse_local_ned
from sitl.autopilot.params import PARAM_TYPE_INT32, decode_value, encode_value
from sitl.autopilot.signing import VehicleSigning
from sitl.autopilot.state import SEV_CRITICAL, AutopilotState

log = logging.getLogger("sitl.autopilot")

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


class MavlinkEndpoint:
    """The MAVLink endpoint of one vehicle's autopilot, on its state ``s`` and flight logic."""

    def __init__(self, s: AutopilotState, flight: FlightLogic) -> None:
        self.s = s
        self.commands = Commands(s, flight)
        #: MAVLink 2 signing, once SETUP_SIGNING gave a key (None: everything is accepted, nothing signed).
        self.signing: VehicleSigning | None = None

    # ------------------------------------------------------------------ incoming
    def handle_message(self, msg: Any, link: int | None, src_system: int, src_component: int) -> None:
        """Process one incoming MAVLink message (a pymavlink message object).

        ``link`` is the link index it arrived on (None for in-process senders, which get no reply).
        Never raises on hostile content: a handler bug is counted in ``counters['handler_errors']``
        and logged, and the message is dropped.
        """
        self.s.counters["messages_in"] += 1
        handler = MESSAGE_HANDLERS.get(msg.get_type())
        if handler is None:
            self.s.counters["ignored_messages"] += 1
            return
        try:
            handler(self, msg, link, src_system, src_component)
        except Exception:
            # The boundary to untrusted input: never let one message take the vehicle down.
            self.s.counters["handler_errors"] += 1
            log.exception("%s: error handling %s", self.s.name, msg.get_type())

    def _for_us(self, target_system: int, target_component: int | None = None) -> bool:
        if target_system not in (0, self.s.sysid):
            self.s.counters["other_target"] += 1
            return False
        if target_component is not None and target_component not in (0, 1):
            self.s.counters["other_target"] += 1
            return False
        return True

    def _on_heartbeat(self, msg: Any, link: int | None, src_system: int, src_component: int) -> None:
        self.s.counters["heartbeats_in"] += 1

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

    def _command(
        self, command: int, p: tuple[float, ...], link: int | None, src_system: int, src_component: int
    ) -> None:
        self._ack(command, self.commands.run(command, p, link), link, src_system, src_component)

    def _ack(self, command: int, result: int, link: int | None, src_system: int, src_component: int) -> None:
        self.s.reply(
            link, mavlink.MAVLink_command_ack_message(command, result, 0, 0, src_system, src_component)
        )

    # --- setpoints
    def _on_set_position_target_local_ned(
        self, msg: Any, link: int | None, src_system: int, src_component: int
    ) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        parsed = parse_local_ned(msg, self.s.t_s, self.s.yaw_est_rad(), self.s.attitude_q())
        self._accept_setpoint(parsed)

    def _on_set_position_target_global_int(
        self, msg: Any, link: int | None, src_system: int, src_component: int
    ) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        origin = self.s.origin if self.s.est.origin_valid else None
        home_alt = self.s.home.alt_m if self.s.home is not None else self.s.origin.alt0_m
        self._accept_setpoint(parse_global_int(msg, self.s.t_s, origin, home_alt))

    def _on_set_attitude_target(
        self, msg: Any, link: int | None, src_system: int, src_component: int
    ) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        parsed = parse_attitude_target(msg, self.s.t_s)
        if parsed is not None:
            self._accept_setpoint(parsed)

    def _accept_setpoint(self, parsed: OffboardSetpoint | str) -> None:
        if isinstance(parsed, str):
            self.s.counters["setpoints_refused"] += 1
            self.s.statustext(SEV_CRITICAL, parsed)
            return
        self.s.counters["setpoints"] += 1
        self.s.offboard_sp = parsed

    # --- external vision
    def _on_vision_position_estimate(
        self, msg: Any, link: int | None, src_system: int, src_component: int
    ) -> None:
        x, y, z = _fin(msg.x), _fin(msg.y), _fin(msg.z)
        if math.isnan(x) or math.isnan(y) or abs(x) > 1e6 or abs(y) > 1e6:
            self.s.counters["vision_refused"] += 1
            return
        cov = list(msg.covariance) if msg.covariance is not None else []
        std = NAN
        if len(cov) >= 7:
            vx, vy = _fin(cov[0]), _fin(cov[6])
            if not math.isnan(vx) and not math.isnan(vy) and vx > 0 and vy > 0:
                std = math.sqrt(max(vx, vy))
        self.s.vision = VisionSample(self.s.t_s, x, y, z, std)
        self.s.counters["vision"] += 1

    def _on_odometry(self, msg: Any, link: int | None, src_system: int, src_component: int) -> None:
        if int(msg.frame_id) not in _EV_FRAMES:
            self.s.counters["vision_refused"] += 1
            return
        x, y, z = _fin(msg.x), _fin(msg.y), _fin(msg.z)
        if math.isnan(x) or math.isnan(y) or abs(x) > 1e6 or abs(y) > 1e6:
            self.s.counters["vision_refused"] += 1
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
                w, qx, qy, qz = self.s.attitude_q()
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
        self.s.vision = VisionSample(self.s.t_s, x, y, z, std, vel)
        self.s.counters["vision"] += 1

    # --- parameters
    def _param_value(self, name: str) -> mavlink.MAVLink_message:
        spec = self.s.params.spec(name)
        if spec is None:
            raise KeyError(name)
        index = self.s.params.index_of(name)
        return mavlink.MAVLink_param_value_message(
            name.encode("ascii"), encode_value(self.s.params[name], spec.type), spec.type, len(self.s.params),
            index if index is not None else 65535,
        )  # fmt: skip

    def _on_param_request_list(self, msg: Any, link: int | None, src_system: int, src_component: int) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        for name in self.s.params.names:
            self.s.reply(link, self._param_value(name))

    def _on_param_request_read(self, msg: Any, link: int | None, src_system: int, src_component: int) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        index = int(msg.param_index)
        if index == -1:
            name = _text(msg.param_id)
            if self.s.params.spec(name) is None:
                return  # PX4 stays silent on unknown names
        elif 0 <= index < len(self.s.params):
            name = self.s.params.names[index]
        else:
            return
        self.s.reply(link, self._param_value(name))

    def _on_param_set(self, msg: Any, link: int | None, src_system: int, src_component: int) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        name = _text(msg.param_id)
        spec = self.s.params.spec(name)
        if spec is None:
            return
        value = decode_value(float(msg.param_value), int(msg.param_type))
        if value is not None:
            if spec.type == PARAM_TYPE_INT32 and int(msg.param_type) == 9:
                value = round(value)  # a float sent for an int parameter: take its value
            self.s.params.set(name, value)
        # PX4 answers every set (changed or not) with the stored value, on every link.
        self.s.broadcast(self._param_value(name))

    # --- signing
    def _on_setup_signing(self, msg: Any, link: int | None, src_system: int, src_component: int) -> None:
        """A signing key, as PX4 takes it: only while disarmed; an all-zero key and timestamp turn it off."""
        if not self._for_us(msg.target_system, msg.target_component):
            return
        if self.s.armed:
            self.s.counters["signing_refused_armed"] += 1
            log.warning("%s: SETUP_SIGNING refused while armed", self.s.name)
            return
        key = bytes(msg.secret_key)
        if len(key) != 32:
            self.s.counters["signing_refused"] += 1
            return
        if not any(key) and int(msg.initial_timestamp) == 0:
            self.signing = None
            log.info("%s: MAVLink signing off", self.s.name)
            return
        self.signing = VehicleSigning(key, int(msg.initial_timestamp))
        self.s.counters["signing_key_set"] += 1
        log.info("%s: MAVLink signing key accepted", self.s.name)

    # --- misc
    def _on_timesync(self, msg: Any, link: int | None, src_system: int, src_component: int) -> None:
        if int(msg.tc1) == 0:
            self.s.reply(link, mavlink.MAVLink_timesync_message(int(self.s.t_s * 1e9), int(msg.ts1)))

    def _on_ping(self, msg: Any, link: int | None, src_system: int, src_component: int) -> None:
        if int(msg.target_system) == 0:
            self.s.reply(
                link,
                mavlink.MAVLink_ping_message(int(self.s.t_s * 1e6), int(msg.seq), src_system, src_component),
            )

    def _on_mission_request_list(
        self, msg: Any, link: int | None, src_system: int, src_component: int
    ) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        mission_type = int(getattr(msg, "mission_type", 0) or 0)
        self.s.reply(link, mavlink.MAVLink_mission_count_message(src_system, src_component, 0, mission_type))

    def _on_mission_count(self, msg: Any, link: int | None, src_system: int, src_component: int) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        mission_type = int(getattr(msg, "mission_type", 0) or 0)
        self.s.reply(
            link,
            mavlink.MAVLink_mission_ack_message(
                src_system, src_component, mavlink.MAV_MISSION_UNSUPPORTED, mission_type
            ),
        )

    # ------------------------------------------------------------------ outgoing
    def service_links(self, t_s: float) -> None:
        """Queue the streams that are due at ``t_s`` on every active link."""
        self.s.t_s = t_s
        gps = self.s.gps_last
        for link in self.s.links:
            if not link.active:
                continue
            due = link.next_due_s
            for msg_id, interval in link.intervals_s.items():
                if interval == telemetry.ON_UPDATE:
                    # On every receiver update; at 1 Hz with "no fix" once data stops.
                    fresh = gps is not None and gps.t_s > link._gps_sent_t_s and t_s - gps.t_s <= 1.0
                    if fresh and gps is not None:
                        link._gps_sent_t_s = gps.t_s
                    elif t_s >= due.get(msg_id, 0.0) and (gps is None or t_s - gps.t_s > 1.0):
                        due[msg_id] = t_s + 1.0
                    else:
                        continue
                else:
                    next_s = due.get(msg_id, 0.0)
                    if t_s < next_s:
                        continue
                    next_s += interval
                    due[msg_id] = next_s if next_s > t_s else t_s + interval
                msg = telemetry.BUILDERS[msg_id](self.s)
                if msg is not None:
                    link.outbox.append(msg)


_MessageHandler = Callable[[MavlinkEndpoint, Any, "int | None", int, int], None]

#: The messages an autopilot handles, by type name; every other message is counted and ignored.
MESSAGE_HANDLERS: Final[dict[str, _MessageHandler]] = {
    "COMMAND_LONG": MavlinkEndpoint._on_command_long,
    "COMMAND_INT": MavlinkEndpoint._on_command_int,
    "SET_POSITION_TARGET_LOCAL_NED": MavlinkEndpoint._on_set_position_target_local_ned,
    "SET_POSITION_TARGET_GLOBAL_INT": MavlinkEndpoint._on_set_position_target_global_int,
    "SET_ATTITUDE_TARGET": MavlinkEndpoint._on_set_attitude_target,
    "PARAM_REQUEST_LIST": MavlinkEndpoint._on_param_request_list,
    "PARAM_REQUEST_READ": MavlinkEndpoint._on_param_request_read,
    "PARAM_SET": MavlinkEndpoint._on_param_set,
    "VISION_POSITION_ESTIMATE": MavlinkEndpoint._on_vision_position_estimate,
    "ODOMETRY": MavlinkEndpoint._on_odometry,
    "TIMESYNC": MavlinkEndpoint._on_timesync,
    "PING": MavlinkEndpoint._on_ping,
    "MISSION_REQUEST_LIST": MavlinkEndpoint._on_mission_request_list,
    "MISSION_COUNT": MavlinkEndpoint._on_mission_count,
    "HEARTBEAT": MavlinkEndpoint._on_heartbeat,
    "SETUP_SIGNING": MavlinkEndpoint._on_setup_signing,
}
