"""``MavsdkVehicleLink``: the :class:`~companion.vehicle.link.VehicleLink` over MAVSDK 4 (native, asyncio).

The only module that imports mavsdk. Lifecycle::

    async with MavsdkVehicleLink(cfg.link, clock) as link:      # MAVSDK instance + UDP/serial connection
        async with compat.TaskGroup() as tg:
            tg.create_task(link.run(), name="companion.vehicle")  # discovery, telemetry, setpoint guard
            ...                                                   # snapshot() / commands from the mission

MAVSDK quirks handled here:

* **Its own 20 Hz resend.** Every ``set_*`` is resent by MAVSDK until replaced or stopped, so a dead mission
  would keep the vehicle on its last setpoint. The mission refreshes every tick; the *setpoint guard* task
  here stops offboard itself when no fresh setpoint came for ``LinkConfig.setpoint_timeout_s``.
* **The offboard start race.** MAVSDK's watchdog kills the stream on a non-offboard heartbeat between
  ``set_*`` and ``start()``, and ``start()`` then fails with NO_SETPOINT_SET: each start attempt sets the
  setpoint right before ``start()`` and retries on that error.
* **Its stdout logging.** MAVSDK's log lines go to the ``companion.vehicle.mavsdk`` logger instead.
* **Blocking calls.** The asyncio wrappers run commands as blocking C calls on executor threads; one that
  never returns (seen with ``stop()`` around teardown) pins a thread that interpreter exit then waits for.
  Commands here use the plugins' ``*_async`` callbacks instead, awaited with a timeout, and setpoints are
  plain non-blocking sends on the loop thread; telemetry uses the asyncio subscriptions.
* **Link loss.** A lost link is a state (``VehicleState.connected``, stale stamps), never an exception from
  telemetry; commands without a link raise :class:`~companion.kernel.errors.LinkLostError`.

The subscriptions' items become one :class:`~companion.kernel.flight.VehicleState` in
:mod:`companion.vehicle.mavsdk_telemetry`.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import time
from collections.abc import AsyncIterator, Callable, Coroutine, Mapping
from dataclasses import replace
from types import TracebackType
from typing import Any, TypeVar

from mavsdk import log_subscribe, log_unsubscribe
from mavsdk.asyncio import ComponentType, Configuration, Mavsdk, MavsdkError
from mavsdk.asyncio.plugins.mavlink_direct import MavlinkDirectAsync
from mavsdk.asyncio.plugins.param import ParamAsync
from mavsdk.asyncio.plugins.telemetry import TelemetryAsync
from mavsdk.plugins.action import Action, ActionResult
from mavsdk.plugins.mavlink_direct import MavlinkMessage
from mavsdk.plugins.mocap import AngleBody, Covariance, Mocap, PositionBody, VisionPositionEstimate
from mavsdk.plugins.offboard import Offboard, OffboardResult
from mavsdk.plugins.server_utility import ServerUtility

from companion.config import LinkConfig
from companion.kernel import compat
from companion.kernel.clock import Clock
from companion.kernel.compat import Self
from companion.kernel.errors import CommandRejectedError, LinkLostError, WrongVehicleError
from companion.kernel.flight import (
    ExternalPosition,
    Setpoint,
    Severity,
    VehicleState,
)
from companion.kernel.stall import StallAwareAge
from companion.vehicle import failsafe
from companion.vehicle.external_vision import EV_CTRL_PARAM
from companion.vehicle.finite import require_finite_position, require_finite_setpoint
from companion.vehicle.identity import choose_autopilot
from companion.vehicle.mavsdk_glue import (
    STATUSTEXT_SEVERITY,
    mavsdk_log,
    read_hover_thrust,
    request_timesync,
    result_name,
    route_mavsdk_log,
    settle,
)
from companion.vehicle.mavsdk_setpoints import set_offboard_setpoint
from companion.vehicle.mavsdk_telemetry import MavsdkTelemetry

log = logging.getLogger("companion.vehicle")

T = TypeVar("T")

#: How often the setpoint guard looks, s.
_GUARD_PERIOD_S = 0.05
#: A gap between the guard's looks longer than this is a stall of the whole service, s.
_GUARD_STALL_S = 4 * _GUARD_PERIOD_S
_START_ATTEMPTS = 3
_DISCOVERY_LOG_EVERY_S = 10.0
_DISCOVERY_POLL_S = 0.2
#: A MAVSDK "_async" start that holds the loop longer than this is reported (it should return at once).
_BLOCKING_WARN_S = 0.02

#: Wall time PX4 is given to apply a new MIS_TAKEOFF_ALT before the takeoff command, s.
TAKEOFF_PARAM_SETTLE_S = 0.3


class MavsdkVehicleLink:
    """The autopilot over MAVSDK 4. See the module docstring for the lifecycle and the quirks handled."""

    def __init__(
        self,
        cfg: LinkConfig,
        clock: Clock,
        *,
        leader_system_id: int | None = None,
        ev_position_bits: int = 0,
    ) -> None:
        self.cfg = cfg
        self.clock = clock
        #: EKF2_EV_CTRL bits the mission needs set (1: fuse external-vision horizontal position), 0: none.
        self.ev_position_bits = ev_position_bits
        #: Never flown, whatever ``cfg.system_id`` says (the config refuses that too).
        self.leader_system_id = leader_system_id
        #: The autopilot's system id once found.
        self.system_id: int | None = None
        self._sdk: Mavsdk | None = None
        self._system: Any = None
        self._telemetry_plugin: Any = None
        self._action: Any = None
        self._offboard: Any = None
        self._mocap: Any = None
        self._param: Any = None
        self._server_utility: Any = None
        self._direct: Any = None
        #: The telemetry, one handler per subscription.
        self.telemetry = MavsdkTelemetry(clock)
        self._stream_active = False
        self._last_setpoint_s = -math.inf
        self._ready = asyncio.Event()
        #: How many times the guard had to stop a stream the mission stopped refreshing.
        self.guard_trips = 0

    # ------------------------------------------------------------------ lifecycle
    async def __aenter__(self) -> Self:
        mavsdk_log.setLevel(self.cfg.mavsdk_log_level)
        log_subscribe(route_mavsdk_log)  # before Mavsdk(): it logs its version on construction
        cfg = Configuration.create_with_component_type(ComponentType.COMPANION_COMPUTER)
        if self.cfg.system_id:
            # A companion computer speaks as its autopilot's system (component 195). MAVSDK's default, 1,
            # is the leader's in a formation: every message would claim to come from the leader.
            cfg.system_id = self.cfg.system_id
        else:
            log.warning(
                "vehicle link: link.system_id = 0: this service's own MAVLink id stays MAVSDK's default "
                "(system %d); set link.system_id to the follower's",
                cfg.system_id,
            )
        self._sdk = Mavsdk(cfg)
        try:
            await self._sdk.add_any_connection(self.cfg.url)
        except MavsdkError as exc:
            self._sdk.destroy()
            self._sdk = None
            log_unsubscribe()
            raise LinkLostError(f"cannot open {self.cfg.url}: {exc}") from exc
        log.info("vehicle link: listening on %s", self.cfg.url)
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        try:
            if self._stream_active and self._offboard is not None:
                # Deliberate end of the stream (PX4 Hold): never leave MAVSDK resending a last setpoint.
                self._stream_active = False
                with contextlib.suppress(CommandRejectedError):
                    await self._result_of("stop_offboard", self._offboard.stop_async, OffboardResult.SUCCESS)
        finally:
            if self._sdk is not None:
                self._sdk.destroy()
                self._sdk = None
            log_unsubscribe()

    async def run(self) -> None:
        """Find the autopilot, then keep the telemetry snapshot current and guard the setpoint stream."""
        system = await self._discover()
        self._system = system
        self._telemetry_plugin = TelemetryAsync(system)
        self._param = ParamAsync(system)
        self._direct = MavlinkDirectAsync(system)
        # Commands and sends on the plain plugins (callbacks, no executor threads); mavsdk>=4,<5 keeps the
        # plain System on the asyncio wrapper as ``_system``.
        raw = system._system
        self._action = Action(raw)
        self._offboard = Offboard(raw)
        self._mocap = Mocap(raw)
        self._server_utility = ServerUtility(raw)
        self.telemetry.update(connected=True, heartbeat_stamp_s=self.clock.now_s())
        self._ready.set()
        t = self._telemetry_plugin
        h = self.telemetry
        streams: dict[str, Callable[[], Coroutine[Any, Any, None]]] = {
            "connection": lambda: self._each(system.is_connected_state(), h.on_connected),
            "flight_mode": lambda: self._each(t.subscribe_flight_mode(), h.on_flight_mode),
            "armed": lambda: self._each(t.subscribe_armed(), h.on_armed),
            "landed_state": lambda: self._each(t.subscribe_landed_state(), h.on_landed_state),
            "attitude": lambda: self._each(t.subscribe_attitude_euler(), h.on_attitude),
            "velocity": lambda: self._each(t.subscribe_velocity_ned(), h.on_velocity),
            "position": lambda: self._each(t.subscribe_position(), h.on_position),
            "local_position": lambda: self._each(t.subscribe_position_velocity_ned(), h.on_local_position),
            "gps": lambda: self._each(t.subscribe_gps_info(), h.on_gps),
            "health": lambda: self._each(t.subscribe_health(), h.on_health),
            "battery": lambda: self._each(t.subscribe_battery(), h.on_battery),
            "status_text": lambda: self._each(t.subscribe_status_text(), h.on_status_text),
            "estimator": lambda: self._each(
                self._direct.subscribe_message("ESTIMATOR_STATUS"), h.on_estimator_status
            ),
            "timesync": lambda: self._each(self._direct.subscribe_message("TIMESYNC"), h.on_timesync),
        }
        async with compat.TaskGroup() as tg:
            for name, factory in streams.items():
                tg.create_task(factory(), name=f"companion.vehicle.{name}")
            tg.create_task(self._setpoint_guard(), name="companion.vehicle.setpoint_guard")
            tg.create_task(request_timesync(self._direct, self.clock), name="companion.vehicle.timesync")
            tg.create_task(
                read_hover_thrust(self._param, self.cfg.command_timeout_s, self.telemetry),
                name="companion.vehicle.hover_thrust",
            )
            tg.create_task(self._configure_failsafe(), name="companion.vehicle.failsafe")
            if self.ev_position_bits:
                tg.create_task(self._configure_external_vision(), name="companion.vehicle.external_vision")

    async def wait_ready(self) -> None:
        """Until the autopilot has been found (use with a timeout)."""
        await self._ready.wait()

    async def _discover(self) -> Any:
        """The autopilot this service flies (``link.system_id``), never the leader's; see vehicle/identity.py.

        Raises :class:`WrongVehicleError` when, for ``connect_timeout_s`` after the first autopilot was heard,
        only other systems (the leader) are on the link.
        """
        assert self._sdk is not None, "use MavsdkVehicleLink as an async context manager"  # noqa: S101
        first_heard_s: float | None = None
        last_log_s = -math.inf
        systems: list[Any] = []
        while True:
            # One wrapper per discovered system, fetched again only when a new system appears: each
            # get_systems() call makes new wrappers, and the one flown must be the one its plugins use.
            if await self._sdk.system_count() != len(systems):
                systems = await self._sdk.get_systems()
            heard: dict[int, Any] = {}
            for system in systems:
                if await system.has_autopilot():
                    heard[await system.get_system_id()] = system
            now_s = self.clock.now_s()
            if heard and first_heard_s is None:
                first_heard_s = now_s
            verdict = choose_autopilot(
                heard,
                self.cfg.system_id,
                leader=self.leader_system_id,
                listened_s=0.0 if first_heard_s is None else now_s - first_heard_s,
                patience_s=self.cfg.connect_timeout_s,
                url=self.cfg.url,
            )
            if verdict.system_id is not None:
                log.info("vehicle link: flying autopilot system %d on %s", verdict.system_id, self.cfg.url)
                self.system_id = verdict.system_id
                return heard[verdict.system_id]
            if verdict.refusal is not None:
                raise WrongVehicleError(verdict.refusal)
            if now_s - last_log_s >= _DISCOVERY_LOG_EVERY_S:
                last_log_s = now_s
                (log.info if first_heard_s is None else log.warning)("vehicle link: %s", verdict.waiting)
            await asyncio.sleep(_DISCOVERY_POLL_S)

    # ------------------------------------------------------------------ telemetry
    async def _each(self, stream: AsyncIterator[T], handle: Callable[[T], None]) -> None:
        async with contextlib.aclosing(stream) as items:  # type: ignore[type-var]
            async for item in items:
                handle(item)

    async def _configure_failsafe(self) -> None:
        """Set PX4's offboard-loss action (``link.offboard_loss_action``) and read back what it is.

        Written only when it differs, so a service restarted over a flying vehicle that it only observes
        sends it nothing but reads. A refusal is one warning line, never an error: the flight goes on with
        PX4's own setting.
        """
        wanted = failsafe.wanted_value(self.cfg.offboard_loss_action)
        try:
            async with compat.timeout(self.cfg.command_timeout_s * 2):
                value = int(await self._param.get_param_int(failsafe.PARAM))
                if wanted is not None and value != wanted:
                    await self._param.set_param_int(failsafe.PARAM, wanted)
                    value = int(await self._param.get_param_int(failsafe.PARAM))
        except (MavsdkError, TimeoutError) as exc:
            log.warning(
                "vehicle link: %s", failsafe.not_applied(self.cfg.offboard_loss_action, str(exc) or "timeout")
            )
            return
        self.telemetry.update(offboard_loss_param=value)
        ok, line = failsafe.applied(self.cfg.offboard_loss_action, value)
        (log.info if ok else log.warning)("vehicle link: %s", line)

    async def _configure_external_vision(self) -> None:
        """Have PX4's EKF2 fuse the fixes the mission sends after a GPS loss (EKF2_EV_CTRL, off by default).

        Only bits are added, never taken away; written only when missing. A refusal is one warning line: the
        mission then finds its fixes not taken and flies on attitude.
        """
        bits = self.ev_position_bits
        try:
            async with compat.timeout(self.cfg.command_timeout_s * 2):
                value = int(await self._param.get_param_int(EV_CTRL_PARAM))
                if value & bits != bits:
                    await self._param.set_param_int(EV_CTRL_PARAM, value | bits)
                    value = int(await self._param.get_param_int(EV_CTRL_PARAM))
        except (MavsdkError, TimeoutError) as exc:
            log.warning(
                "vehicle link: %s not set (%s); PX4 will not fuse external positions", EV_CTRL_PARAM, exc
            )
            return
        (log.info if value & bits == bits else log.warning)("vehicle link: %s %d", EV_CTRL_PARAM, value)

    def snapshot(self) -> VehicleState:
        """The latest telemetry; ``connected`` also requires a heartbeat within the telemetry timeout."""
        now_s = self.clock.now_s()
        st = self.telemetry.state
        alive = st.connected and now_s - st.heartbeat_stamp_s <= max(self.cfg.telemetry_timeout_s, 3.0)
        return replace(st, stamp_s=now_s, connected=alive)

    # ------------------------------------------------------------------ commands
    def _require(self, plugin: Any) -> Any:
        if plugin is None or not self.telemetry.state.connected:
            raise LinkLostError("no autopilot connected")
        return plugin

    async def _result_of(self, what: str, start: Callable[..., None], success: Any, *args: Any) -> None:
        """Start a MAVSDK ``*_async`` call and await its result callback, bounded in time."""
        loop = asyncio.get_running_loop()
        fut: asyncio.Future[Any] = loop.create_future()

        def done(result: Any, _user_data: Any) -> None:  # on MAVSDK's thread
            with contextlib.suppress(RuntimeError):  # the loop may be closed by the time a late reply comes
                loop.call_soon_threadsafe(settle, fut, result)

        t0_s = time.monotonic()
        start(*args, done)
        blocked_s = time.monotonic() - t0_s
        if blocked_s > _BLOCKING_WARN_S:
            log.warning("vehicle link: MAVSDK %s blocked the event loop for %.3f s", what, blocked_s)
        try:
            async with compat.timeout(self.cfg.command_timeout_s * 2):
                result = await fut
        except TimeoutError:
            raise CommandRejectedError(what, "TIMEOUT") from None
        if result != success:
            raise CommandRejectedError(what, getattr(result, "name", str(result)))

    async def _action_call(self, what: str, method: str, *args: Any) -> None:
        action = self._require(self._action)
        await self._result_of(what, getattr(action, f"{method}_async"), ActionResult.SUCCESS, *args)

    async def arm(self) -> None:
        await self._action_call("arm", "arm")

    async def disarm(self) -> None:
        await self._action_call("disarm", "disarm")

    async def takeoff(self, altitude_m: float) -> None:
        action = self._require(self._action)
        try:
            # A parameter write: MAVSDK's "_async" variant of it blocks the calling thread through its
            # retries, so it goes to a worker thread (it always ends: MAVSDK times the write out itself).
            async with compat.timeout(self.cfg.command_timeout_s * 4):
                await asyncio.to_thread(action.set_takeoff_altitude, float(altitude_m))
        except (MavsdkError, TimeoutError) as exc:
            why = result_name(exc) if isinstance(exc, MavsdkError) else "TIMEOUT"
            log.warning("vehicle link: takeoff altitude not set (%s); PX4 uses MIS_TAKEOFF_ALT", why)
        else:
            # PX4's navigator takes a parameter change on one of its next cycles: a takeoff sent at once after
            # the write climbed to the old MIS_TAKEOFF_ALT (2.5 m) in one of three PX4 SITL flights.
            await asyncio.sleep(TAKEOFF_PARAM_SETTLE_S)
        await self._action_call("takeoff", "takeoff")

    async def land(self) -> None:
        await self._action_call("land", "land")

    async def hold(self) -> None:
        await self._action_call("hold", "hold")

    async def return_to_launch(self) -> None:
        await self._action_call("return_to_launch", "return_to_launch")

    # ------------------------------------------------------------------ offboard
    async def set_setpoint(self, setpoint: Setpoint) -> None:
        require_finite_setpoint(setpoint)
        offboard = self._require(self._offboard)
        try:
            set_offboard_setpoint(offboard, setpoint)
        except MavsdkError as exc:
            raise CommandRejectedError("set_setpoint", result_name(exc)) from exc
        self._last_setpoint_s = self.clock.now_s()
        self._stream_active = True

    async def start_offboard(self, setpoint: Setpoint) -> None:
        """Set ``setpoint``, then start; retry when MAVSDK lost the setpoint in the start race."""
        offboard = self._require(self._offboard)
        for attempt in range(1, _START_ATTEMPTS + 1):
            await self.set_setpoint(setpoint)
            try:
                await self._result_of("start_offboard", offboard.start_async, OffboardResult.SUCCESS)
            except CommandRejectedError as exc:
                if exc.result == OffboardResult.NO_SETPOINT_SET.name and attempt < _START_ATTEMPTS:
                    log.info("vehicle link: offboard start raced MAVSDK's watchdog; retrying (%d)", attempt)
                    await asyncio.sleep(0.1)
                    continue
                raise
            return

    async def stop_offboard(self) -> None:
        """Stop MAVSDK's resend and ask for Hold.

        Works with the link down too: stopping the local stream is what matters then (a one-way loss would
        otherwise keep feeding PX4 the last setpoint).
        """
        self._stream_active = False
        if self._offboard is None:
            raise LinkLostError("no autopilot connected")
        await self._result_of("stop_offboard", self._offboard.stop_async, OffboardResult.SUCCESS)

    async def release_offboard(self) -> None:
        self._stream_active = False

    async def _setpoint_guard(self) -> None:
        """Stop offboard when the mission stops refreshing (MAVSDK would resend the last one forever)."""
        # The guard's own stall (the whole service paused) is not the mission's: ages restart after it.
        ages = StallAwareAge(_GUARD_STALL_S)
        while True:
            await asyncio.sleep(_GUARD_PERIOD_S)
            now_s = self.clock.now_s()
            ages.tick(now_s)
            if not self._stream_active:
                continue
            age_s = ages.age_s(self._last_setpoint_s, now_s)
            if age_s <= self.cfg.setpoint_timeout_s:
                continue
            self._stream_active = False
            self.guard_trips += 1
            log.error("vehicle link: no fresh setpoint for %.2f s: stopping offboard (PX4 Hold)", age_s)
            try:
                await self._result_of("stop_offboard", self._offboard.stop_async, OffboardResult.SUCCESS)
            except CommandRejectedError as exc:
                log.error("vehicle link: offboard stop: %s", exc.result)

    # ------------------------------------------------------------------ estimator input, GCS text
    async def send_external_position(self, fix: ExternalPosition) -> None:
        require_finite_position(fix)
        mocap = self._require(self._mocap)
        cov = [0.0] * 21
        cov[0], cov[6], cov[11] = fix.variance_m2
        cov[15] = cov[18] = cov[20] = 1.0  # angles come from PX4 itself: tell it not to trust ours
        estimate = VisionPositionEstimate(
            time_usec=0,  # 0: MAVSDK stamps it "now" in autopilot time (our fix is fresh)
            position_body=PositionBody(*fix.p_ned_m),
            angle_body=AngleBody(fix.roll_rad, fix.pitch_rad, fix.yaw_rad),
            pose_covariance=Covariance(cov),
            reset_counter=fix.reset_counter,
        )
        try:
            mocap.set_vision_position_estimate(estimate)  # a plain send: returns at once
        except MavsdkError as exc:
            raise CommandRejectedError("vision_position_estimate", result_name(exc)) from exc

    async def send_status_text(self, text: str, severity: Severity) -> None:
        su = self._require(self._server_utility)
        try:
            su.send_status_text(STATUSTEXT_SEVERITY[severity], text[:50])  # a plain send
        except MavsdkError as exc:
            raise CommandRejectedError("status_text", result_name(exc)) from exc

    async def send_onboard_computer_status(self, fields: Mapping[str, int | list[int]]) -> None:
        if self._direct is None:
            return  # not connected yet
        # MAVSDK has no ONBOARD_COMPUTER_STATUS API; its MavlinkDirect plugin sends any common message.
        msg = MavlinkMessage(message_name="ONBOARD_COMPUTER_STATUS", fields_json=json.dumps(dict(fields)))
        await self._direct.send_message(msg)
