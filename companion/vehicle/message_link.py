"""``MessageVehicleLink``: the :class:`~companion.vehicle.link.VehicleLink` over MAVLink *message objects*.

No sockets, no threads: it sends pymavlink message objects to a :class:`MessageTransport` and reads what comes
back when its owner calls :meth:`MessageVehicleLink.pump`. For lockstep (``sitl.world.lockstep.World.link``
is such a transport): one clock for simulation and service, where MAVSDK (real UDP, real time) cannot run.

It does on the wire what :class:`~companion.vehicle.mavsdk_link.MavsdkVehicleLink` makes MAVSDK 4 do, so the
mission sees the same vehicle through either link:

* telemetry is assembled as MAVSDK's telemetry plugin does (mode from HEARTBEAT, health from SYS_STATUS,
  ``position_valid`` from ESTIMATOR_STATUS), samples stamped when taken (TIMESYNC, vehicle/boottime.py);
* commands are COMMAND_LONG resent every 0.5 s up to three times, matched to their COMMAND_ACK;
  ``takeoff`` sets MIS_TAKEOFF_ALT first, as MAVSDK's ``set_takeoff_altitude`` + ``takeoff`` do;
* setpoints are sent at once and then resent at 20 Hz (MAVSDK's offboard plugin), with the same setpoint
  guard as the MAVSDK link (no fresh setpoint for ``setpoint_timeout_s``: stop offboard) and MAVSDK's
  watchdog (a non-offboard HEARTBEAT more than 3 s after start ends the stream).

Time: the clock passed in (sim time in lockstep); :meth:`pump` must be called often (every physics step in
the harness): retries, resends and timeouts are checked there. Telemetry: vehicle/mavlink_telemetry.py.
"""

from __future__ import annotations

import asyncio
import logging
import math
import struct
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

from pymavlink.dialects.v20 import common as mavlink

from companion.config import LinkConfig
from companion.kernel.clock import Clock
from companion.kernel.errors import CommandRejectedError, LinkLostError
from companion.kernel.flight import (
    AttitudeSetpoint,
    ExternalPosition,
    FlightMode,
    Setpoint,
    Severity,
    VehicleState,
    VelocityBodySetpoint,
    VelocityNedSetpoint,
)
from companion.kernel.frames import quat_from_euler
from companion.vehicle import failsafe
from companion.vehicle.boottime import TIMESYNC_PERIOD_S
from companion.vehicle.external_vision import EV_CTRL_PARAM
from companion.vehicle.mavlink_telemetry import (
    AUTOPILOT_COMPONENT,
    SEVERITY_CODE,
    MavlinkTelemetry,
    param_int,
    text_of,
)

log = logging.getLogger("companion.vehicle")

#: MAVSDK's companion-computer identity: the autopilot's system id, component 195.
COMPANION_COMPONENT = mavlink.MAV_COMP_ID_ONBOARD_COMPUTER
#: MAVSDK resends offboard setpoints at this rate.
RESEND_PERIOD_S = 0.05
#: MAVSDK's command protocol: COMMAND_LONG timeout and retries.
COMMAND_RETRY_S = 0.5
COMMAND_RETRIES = 3
#: MAVSDK declares the system disconnected after this long without a HEARTBEAT.
HEARTBEAT_TIMEOUT_S = 3.0
#: MAVSDK's offboard watchdog grace after start.
OFFBOARD_GRACE_S = 3.0
#: MAVSDK asks for HOME_POSITION this often until it has one.
HOME_REQUEST_PERIOD_S = 2.0
_HEARTBEAT_PERIOD_S = 1.0

# POSITION_TARGET_TYPEMASK as MAVSDK's offboard plugin sets it (with an acceleration: position NaN, unmasked).
_IGNORE_POS, _IGNORE_ACC, _IGNORE_YAW, _IGNORE_YAW_RATE = 1 | 2 | 4, 64 | 128 | 256, 1024, 2048
VELOCITY_BODY_MASK = _IGNORE_POS | _IGNORE_ACC | _IGNORE_YAW
VELOCITY_NED_MASK = _IGNORE_POS | _IGNORE_ACC | _IGNORE_YAW_RATE
#: SET_ATTITUDE_TARGET: body rates ignored, attitude + thrust used.
ATTITUDE_MASK = 1 | 2 | 4


class MessageTransport(Protocol):
    """Carries pymavlink message objects to and from one autopilot link (e.g. ``sitl`` ``MessageLink``)."""

    def send(self, msg: Any, src_system: int, src_component: int) -> None: ...

    def receive(self) -> list[Any]: ...


@dataclass(slots=True)
class _Pending:
    """A command waiting for its ACK (or a parameter write waiting for its echo)."""

    name: str
    msg: Any
    future: asyncio.Future[int]
    sent_s: float
    tries: int = 1
    #: For PARAM_SET: the parameter id whose PARAM_VALUE completes it.
    param_id: str | None = None
    command_id: int | None = None


@dataclass(slots=True)
class LinkCounters:
    """What went over the link (for reports and tests)."""

    setpoints_sent: int = 0
    commands_sent: int = 0
    command_retries: int = 0
    guard_trips: int = 0
    watchdog_stops: int = 0
    messages_in: int = 0
    by_type: dict[str, int] = field(default_factory=dict)


class MessageVehicleLink:
    """A :class:`~companion.vehicle.link.VehicleLink` over a message transport; see the module docstring.

    Args:
        transport: where messages go and come from.
        clock: the link's clock (sim time in lockstep); telemetry is stamped on it.
        cfg: the service's link config (setpoint guard, telemetry timeout).
        target_system: the autopilot's MAVLink system id.
    """

    def __init__(
        self,
        transport: MessageTransport,
        clock: Clock,
        cfg: LinkConfig,
        target_system: int,
        *,
        ev_position_bits: int = 0,
    ) -> None:
        self.transport = transport
        self.clock = clock
        self.cfg = cfg
        self.target_system = target_system
        #: The autopilot flown (the same name the MAVSDK link uses for its chosen system).
        self.system_id = target_system
        self.own_system = target_system
        #: The telemetry, assembled from what arrives.
        self.telemetry = MavlinkTelemetry(target_system)
        self._pending: list[_Pending] = []
        self._setpoint_msg: Any = None
        self._stream_active = False
        self._last_setpoint_s = -math.inf
        self._last_sent_s = -math.inf
        self._offboard_started_s: float | None = None
        self._last_heartbeat_out_s = -math.inf
        self._last_home_request_s = -math.inf
        self._hover_requested = False
        self._failsafe_done = False
        self._failsafe_tries = 0
        self._failsafe_sent_s = -math.inf
        #: EKF2_EV_CTRL bits the mission needs (external_vision.ev_position_bits_for); 0: leave it alone.
        self.ev_position_bits = ev_position_bits
        self._ev_done = ev_position_bits == 0
        self._ev_tries = 0
        self._ev_sent_s = -math.inf
        self.counters = LinkCounters()
        self._last_timesync_s = -math.inf

    # ------------------------------------------------------------------ the owner's side
    def pump(self) -> None:
        """Read what arrived, then do what is due: retries, timeouts, resends, the guards, heartbeats."""
        now_s = self.clock.now_s()
        for msg in self.transport.receive():
            self._handle(msg, now_s)
        self._due(now_s)

    def _send(self, msg: Any) -> None:
        self.transport.send(msg, self.own_system, COMPANION_COMPONENT)

    def _due(self, now_s: float) -> None:
        if now_s - self._last_heartbeat_out_s >= _HEARTBEAT_PERIOD_S:
            self._last_heartbeat_out_s = now_s
            self._send(
                mavlink.MAVLink_heartbeat_message(
                    mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3
                )
            )
        st = self.telemetry.state
        if st.connected:
            if now_s - self._last_timesync_s >= TIMESYNC_PERIOD_S:
                self._last_timesync_s = now_s
                self._send(mavlink.MAVLink_timesync_message(0, int(now_s * 1e9)))
            if not st.home_position_ok and now_s - self._last_home_request_s >= HOME_REQUEST_PERIOD_S:
                self._last_home_request_s = now_s
                self._command_msg(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_HOME_POSITION)
            self._failsafe_due(now_s)
            self._external_vision_due(now_s)
            if not self._hover_requested:
                self._hover_requested = True
                self._send(
                    mavlink.MAVLink_param_request_read_message(
                        self.target_system, AUTOPILOT_COMPONENT, b"MPC_THR_HOVER", -1
                    )
                )
        for p in list(self._pending):
            if now_s - p.sent_s < COMMAND_RETRY_S:
                continue
            if p.tries >= COMMAND_RETRIES:
                self._pending.remove(p)
                if not p.future.done():
                    p.future.set_exception(CommandRejectedError(p.name, "TIMEOUT"))
                continue
            p.tries += 1
            p.sent_s = now_s
            self.counters.command_retries += 1
            self._send(p.msg)
        if self._stream_active:
            if now_s - self._last_setpoint_s > self.cfg.setpoint_timeout_s:
                self._stream_active = False
                self.counters.guard_trips += 1
                log.error(
                    "vehicle link: no fresh setpoint for %.2f s: stopping offboard",
                    now_s - self._last_setpoint_s,
                )
                self._fire_and_forget_hold()
            elif (
                self._offboard_started_s is not None
                and now_s - self._offboard_started_s > OFFBOARD_GRACE_S
                and st.flight_mode != FlightMode.OFFBOARD
                and st.heartbeat_stamp_s > self._offboard_started_s + OFFBOARD_GRACE_S
            ):
                # MAVSDK's watchdog: the autopilot left offboard, so the resend stops by itself.
                self._stream_active = False
                self._offboard_started_s = None
                self.counters.watchdog_stops += 1
            elif now_s - self._last_sent_s >= RESEND_PERIOD_S - 1e-9:
                self._send_setpoint(now_s)

    def _send_setpoint(self, now_s: float) -> None:
        self._last_sent_s = now_s
        self.counters.setpoints_sent += 1
        self._send(self._setpoint_msg)

    # ------------------------------------------------------------------ telemetry
    def _handle(self, msg: Any, now_s: float) -> None:
        # Messages that never went through a codec (a lockstep world hands over objects) carry no source
        # (0): the transport is this autopilot's link, so they are its own.
        if msg.get_srcSystem() not in (self.target_system, 0):
            return
        kind = msg.get_type()
        c = self.counters
        c.messages_in += 1
        c.by_type[kind] = c.by_type.get(kind, 0) + 1
        if self.telemetry.handle(msg, kind, now_s):
            return
        if kind == "COMMAND_ACK":
            self._on_ack(int(msg.command), int(msg.result))
        elif kind == "PARAM_VALUE":
            name = text_of(msg.param_id)
            if name == failsafe.PARAM:
                self._on_failsafe_param(param_int(float(msg.param_value), int(msg.param_type)))
            elif name == EV_CTRL_PARAM:
                self._on_ev_param(param_int(float(msg.param_value), int(msg.param_type)))
            else:
                self._on_param(name, float(msg.param_value))

    def _on_ack(self, command: int, result: int) -> None:
        if result == mavlink.MAV_RESULT_IN_PROGRESS:
            return
        for p in self._pending:
            if p.command_id == command:
                self._pending.remove(p)
                if not p.future.done():
                    p.future.set_result(result)
                return

    def _failsafe_due(self, now_s: float) -> None:
        """Set (or read) COM_OBL_RC_ACT, resent like a command until PX4 echoes it (as mavsdk_link does)."""
        if self._failsafe_done or now_s - self._failsafe_sent_s < COMMAND_RETRY_S:
            return
        wanted = failsafe.wanted_value(self.cfg.offboard_loss_action)
        if self._failsafe_tries >= COMMAND_RETRIES:
            self._failsafe_done = True
            log.warning("vehicle link: %s", failsafe.not_applied(self.cfg.offboard_loss_action, "no reply"))
            return
        self._failsafe_tries += 1
        self._failsafe_sent_s = now_s
        pid = failsafe.PARAM.encode()
        if wanted is None:
            self._send(
                mavlink.MAVLink_param_request_read_message(self.target_system, AUTOPILOT_COMPONENT, pid, -1)
            )
        else:
            self._set_int_param(pid, wanted)

    def _set_int_param(self, param_id: bytes, value: int) -> None:
        """PARAM_SET of an INT32 parameter, its bytes sent as the float field (PX4's convention)."""
        as_float = struct.unpack("<f", struct.pack("<i", value))[0]
        self._send(
            mavlink.MAVLink_param_set_message(
                self.target_system, AUTOPILOT_COMPONENT, param_id, as_float, mavlink.MAV_PARAM_TYPE_INT32
            )
        )

    def _on_failsafe_param(self, value: int) -> None:
        if self._failsafe_done and self.telemetry.state.offboard_loss_param == value:
            return
        self._failsafe_done = True
        self.telemetry.update(offboard_loss_param=value)
        ok, line = failsafe.applied(self.cfg.offboard_loss_action, value)
        (log.info if ok else log.warning)("vehicle link: %s", line)

    def _external_vision_due(self, now_s: float) -> None:
        """Read EKF2_EV_CTRL until PX4 answers (resent like a command); :meth:`_on_ev_param` adds the bits."""
        if self._ev_done or now_s - self._ev_sent_s < COMMAND_RETRY_S:
            return
        if self._ev_tries >= COMMAND_RETRIES:
            self._ev_done = True
            log.warning(
                "vehicle link: %s not read (no reply); PX4 will not fuse external positions", EV_CTRL_PARAM
            )
            return
        self._ev_tries += 1
        self._ev_sent_s = now_s
        self._send(
            mavlink.MAVLink_param_request_read_message(
                self.target_system, AUTOPILOT_COMPONENT, EV_CTRL_PARAM.encode(), -1
            )
        )

    def _on_ev_param(self, value: int) -> None:
        bits = self.ev_position_bits
        if self._ev_done or bits == 0:
            return
        if value & bits == bits:
            self._ev_done = True
            log.info("vehicle link: %s %d", EV_CTRL_PARAM, value)
            return
        # Add the missing bits; PX4's echo of the write comes back here and ends it.
        self._ev_sent_s = self.clock.now_s()
        self._set_int_param(EV_CTRL_PARAM.encode(), value | bits)

    def _on_param(self, name: str, value: float) -> None:
        if name == "MPC_THR_HOVER" and 0.05 < value < 0.95 and self.telemetry.state.hover_thrust_norm is None:
            self.telemetry.update(hover_thrust_norm=value)
        for p in self._pending:
            if p.param_id == name:
                self._pending.remove(p)
                if not p.future.done():
                    p.future.set_result(mavlink.MAV_RESULT_ACCEPTED)
                return

    def snapshot(self) -> VehicleState:
        """The latest telemetry; ``connected`` also requires a heartbeat within the timeouts."""
        now_s = self.clock.now_s()
        st = self.telemetry.state
        alive = st.connected and now_s - st.heartbeat_stamp_s <= max(
            self.cfg.telemetry_timeout_s, HEARTBEAT_TIMEOUT_S
        )
        return replace(st, stamp_s=now_s, connected=alive)

    # ------------------------------------------------------------------ commands
    def _require(self) -> None:
        if not self.snapshot().connected:
            raise LinkLostError("no autopilot connected")

    def _command_msg(self, command: int, *params: float) -> Any:
        p = [float(x) for x in params] + [math.nan] * (7 - len(params))
        msg = mavlink.MAVLink_command_long_message(self.target_system, AUTOPILOT_COMPONENT, command, 0, *p)
        self._send(msg)
        return msg

    async def _command(self, name: str, command: int, *params: float) -> None:
        self._require()
        fut: asyncio.Future[int] = asyncio.get_running_loop().create_future()
        msg = self._command_msg(command, *params)
        self.counters.commands_sent += 1
        self._pending.append(_Pending(name, msg, fut, self.clock.now_s(), command_id=command))
        result = await fut
        if result != mavlink.MAV_RESULT_ACCEPTED:
            raise CommandRejectedError(name, _result_name(result))

    def _fire_and_forget_hold(self) -> None:
        self._command_msg(mavlink.MAV_CMD_DO_SET_MODE, *self._mode_params(4, 3))

    def _mode_params(self, main: int, sub: int) -> tuple[float, float, float]:
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (
            mavlink.MAV_MODE_FLAG_SAFETY_ARMED if self.telemetry.state.armed else 0
        )
        return float(base), float(main), float(sub)

    async def arm(self) -> None:
        await self._command("arm", mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0, 0.0)

    async def disarm(self) -> None:
        await self._command("disarm", mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0.0, 0.0)

    async def takeoff(self, altitude_m: float) -> None:
        self._require()
        fut: asyncio.Future[int] = asyncio.get_running_loop().create_future()
        msg = mavlink.MAVLink_param_set_message(
            self.target_system,
            AUTOPILOT_COMPONENT,
            b"MIS_TAKEOFF_ALT",
            float(altitude_m),
            mavlink.MAV_PARAM_TYPE_REAL32,
        )
        self._send(msg)
        self._pending.append(
            _Pending("set_takeoff_altitude", msg, fut, self.clock.now_s(), param_id="MIS_TAKEOFF_ALT")
        )
        try:
            await fut
        except CommandRejectedError:
            log.warning("vehicle link: takeoff altitude not set; PX4 uses MIS_TAKEOFF_ALT")
        await self._command("takeoff", mavlink.MAV_CMD_NAV_TAKEOFF)

    async def land(self) -> None:
        await self._command("land", mavlink.MAV_CMD_NAV_LAND)

    async def hold(self) -> None:
        await self._command("hold", mavlink.MAV_CMD_DO_SET_MODE, *self._mode_params(4, 3))

    async def return_to_launch(self) -> None:
        await self._command("return_to_launch", mavlink.MAV_CMD_DO_SET_MODE, *self._mode_params(4, 5))

    # ------------------------------------------------------------------ offboard
    async def set_setpoint(self, setpoint: Setpoint) -> None:
        self._require()
        self._setpoint_msg = self._setpoint_message(setpoint)
        now_s = self.clock.now_s()
        self._last_setpoint_s = now_s
        self._stream_active = True
        self._send_setpoint(now_s)

    def _setpoint_message(self, setpoint: Setpoint) -> Any:
        ts, tc = self.target_system, AUTOPILOT_COMPONENT
        if isinstance(setpoint, VelocityBodySetpoint):
            f, r, d = setpoint.v_body_m_s
            return mavlink.MAVLink_set_position_target_local_ned_message(
                0, ts, tc, mavlink.MAV_FRAME_BODY_NED, VELOCITY_BODY_MASK, 0, 0, 0, f, r, d, 0, 0, 0, 0,
                setpoint.yaw_rate_rad_s,
            )  # fmt: skip
        if isinstance(setpoint, VelocityNedSetpoint):
            (n, e, d), acc, nan = setpoint.v_ned_m_s, setpoint.a_ned_m_s2, math.nan
            mask, pos = (VELOCITY_NED_MASK, (0, 0, 0)) if acc is None else (_IGNORE_YAW_RATE, (nan, nan, nan))
            return mavlink.MAVLink_set_position_target_local_ned_message(
                0, ts, tc, mavlink.MAV_FRAME_LOCAL_NED, mask, *pos, n, e, d, *(acc or (0, 0, 0)),
                setpoint.yaw_rad, 0,
            )  # fmt: skip
        a: AttitudeSetpoint = setpoint
        q = quat_from_euler(a.roll_rad, a.pitch_rad, a.yaw_rad)
        return mavlink.MAVLink_set_attitude_target_message(
            0, ts, tc, ATTITUDE_MASK, [float(x) for x in q], 0.0, 0.0, 0.0, float(a.thrust_norm)
        )

    async def start_offboard(self, setpoint: Setpoint) -> None:
        await self.set_setpoint(setpoint)
        await self._command("start_offboard", mavlink.MAV_CMD_DO_SET_MODE, *self._mode_params(6, 0))
        self._offboard_started_s = self.clock.now_s()

    async def stop_offboard(self) -> None:
        self._stream_active = False
        self._offboard_started_s = None
        await self._command("stop_offboard", mavlink.MAV_CMD_DO_SET_MODE, *self._mode_params(4, 3))

    async def release_offboard(self) -> None:
        self._stream_active = False
        self._offboard_started_s = None

    @property
    def guard_trips(self) -> int:
        return self.counters.guard_trips

    # ------------------------------------------------------------------ estimator input, GCS text
    async def send_external_position(self, fix: ExternalPosition) -> None:
        self._require()
        cov = [math.nan] * 21
        cov[0], cov[6], cov[11] = fix.variance_m2
        cov[15] = cov[18] = cov[20] = 1.0
        self._send(
            mavlink.MAVLink_vision_position_estimate_message(
                int(max(0.0, fix.stamp_s) * 1e6), *fix.p_ned_m, fix.roll_rad, fix.pitch_rad, fix.yaw_rad,
                cov, fix.reset_counter,
            )
        )  # fmt: skip

    async def send_status_text(self, text: str, severity: Severity) -> None:
        self._require()
        self._send(mavlink.MAVLink_statustext_message(SEVERITY_CODE[severity], text[:50].encode(), 0, 0))

    async def send_onboard_computer_status(self, fields: Mapping[str, int | list[int]]) -> None:
        if self.snapshot().connected:
            self._send(mavlink.MAVLink_onboard_computer_status_message(**fields))


def _result_name(result: int) -> str:
    enum = mavlink.enums["MAV_RESULT"]
    return enum[result].name.removeprefix("MAV_RESULT_") if result in enum else str(result)
