"""Builds the real parts (vehicle link, frame source, detector, flight core) for the service.

With :mod:`companion.service.flight_core` (the glue from a frame to a setpoint, shared with the lockstep
harness) this is where the service meets the flight and perception packages; it adapts them to
:mod:`companion.service.ports`. The CLI imports it when the service starts, not before.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from companion.config import Config, resolve_state_dir
from companion.kernel import compat
from companion.kernel.camera import RgbdFrame
from companion.kernel.clock import Clock, MonotonicClock
from companion.kernel.errors import CompanionError, ConfigError, first_companion_error
from companion.kernel.flight import NEVER_S, Severity, VehicleState
from companion.mission.types import (
    MissionInputs,
    SharedLeaderPosition,
    SharedNeighbour,
    StepOutput,
    Transition,
)
from companion.perception.sources import open_source
from companion.perception.truth_detector import TruthDetector
from companion.perception.types import DetectorResult, DetectStage
from companion.service.flight_core import FlightCore
from companion.service.health_checks import CheckResult
from companion.service.latency import TickAges
from companion.service.parts import Parts, PartsContext, PartsFactory
from companion.service.perception_loop import PerceptionLoop
from companion.service.ports import (
    FlightSnapshot,
    LeaderSummary,
    OnboardComputerStatus,
    StateChange,
    VehicleSummary,
)
from companion.service.stamps import ServiceClockSource
from companion.telemetry.leader import OriginTracker
from companion.telemetry.payloads import LeaderPositionMsg, PoseMsg
from companion.vehicle import failsafe
from companion.vehicle.external_vision import ev_position_bits_for
from companion.vehicle.link import VehicleLink

log = logging.getLogger(__name__)

#: How often the follower's attitude is copied from telemetry into the perception's history.
_ATTITUDE_POLL_S = 0.01


def _finite(x: float) -> float | None:
    return x if math.isfinite(x) else None


def vehicle_summary(v: VehicleState, now_s: float, system_id: int | None = None) -> VehicleSummary:
    """The link's snapshot as the status endpoint shows it."""
    has_local = v.local_position_stamp_s > NEVER_S
    has_global = v.global_position_stamp_s > NEVER_S
    return VehicleSummary(
        connected=v.connected,
        heartbeat_age_s=None if v.heartbeat_stamp_s == NEVER_S else max(0.0, now_s - v.heartbeat_stamp_s),
        armed=v.armed,
        in_air=v.in_air,
        flight_mode=v.flight_mode.value,
        offboard_loss_failsafe=None
        if v.offboard_loss_param is None
        else failsafe.describe(v.offboard_loss_param),
        gps_fix_type=v.gps_fix_type,
        gps_satellites=v.gps_satellites,
        position_valid=v.position_valid,
        p_ned_m=v.p_ned_m if has_local else None,
        v_ned_m_s=v.v_ned_m_s if v.velocity_stamp_s > NEVER_S else None,
        yaw_deg=math.degrees(v.yaw_rad) if v.attitude_stamp_s > NEVER_S else None,
        lat_deg=_finite(v.lat_deg) if has_global else None,
        lon_deg=_finite(v.lon_deg) if has_global else None,
        alt_amsl_m=_finite(v.alt_amsl_m) if has_global else None,
        system_id=system_id,
        battery_remaining_frac=_finite(v.battery_remaining_frac),
        battery_voltage_v=_finite(v.battery_voltage_v),
    )


class FlightAdapter:
    """The :class:`FlightCore` (mission, runner, perception glue) behind the service's ``MissionPort``."""

    def __init__(
        self,
        cfg: Config,
        link: VehicleLink,
        clock: Clock,
        stage: DetectStage | None = None,
        wall_time_s: Callable[[], float] = time.time,
    ) -> None:
        self.cfg = cfg
        self.link = link
        self.clock = clock
        self._wall_time_s = wall_time_s
        self.core = FlightCore(
            cfg,
            link,
            clock,
            stage if stage is not None else DetectStage(_no_detection),
            on_transition=self._on_transition,
            on_step=self._on_step,
        )
        self.machine = self.core.machine
        self.runner = self.core.runner
        self._on_change: Callable[[StateChange], None] | None = None
        self._last: Transition | None = None
        self._entered_s = clock.now_s()
        self._last_step_s: float | None = None
        self._last_output: StepOutput | None = None
        self._origin = OriginTracker()
        self.leader_positions_used = 0

    # ---- MissionPort ----------------------------------------------------------------------------------

    def set_on_change(self, callback: Callable[[StateChange], None]) -> None:
        self._on_change = callback

    def snapshot(self) -> FlightSnapshot:
        now_s = self.clock.now_s()
        v = self.link.snapshot()
        tr = self._last
        leader = None
        track = self.core.track
        if track is not None and track.estimate is not None:
            est = track.estimate
            cov = est.cov_ned_m2
            leader = LeaderSummary(
                status=track.status.value,
                p_rel_ned_m=(float(est.p_ned_rel_m[0]), float(est.p_ned_rel_m[1]), float(est.p_ned_rel_m[2])),
                v_rel_ned_m_s=(
                    float(est.v_ned_rel_m_s[0]),
                    float(est.v_ned_rel_m_s[1]),
                    float(est.v_ned_rel_m_s[2]),
                ),
                cov_ned_m2=tuple(tuple(round(float(c), 5) for c in row) for row in cov),  # type: ignore[arg-type]
                age_s=max(0.0, now_s - track.last_measurement_s)
                if track.last_measurement_s is not None
                else None,
                range_m=float(est.range_m),
            )
        out = self._last_output
        return FlightSnapshot(
            state=self.machine.state.value,
            reason=tr.reason.value if tr is not None else "starting",
            detail=tr.detail if tr is not None else "",
            state_age_s=now_s - self._entered_s,
            last_step_s=self._last_step_s,
            vehicle=vehicle_summary(v, now_s, getattr(self.link, "system_id", None)),
            leader=leader,
            formation_error_ned_m=out.formation_error_ned_m if out is not None else None,
            preflight_problems=self.machine.preflight_problems(v),
        )

    async def run(self) -> None:
        await self.core.run()

    def request_start(self, *, takeover: bool = True) -> None:
        self.core.request_start(takeover=takeover)

    def request_shutdown(self) -> None:
        self.core.request_shutdown()

    async def operator_start(self) -> str:
        """An operator's start through the mission machine's checks; what it did, in one line."""
        reply = await self.core.operator_start()
        (log.info if " refused: " not in reply else log.warning)("operator: %s", reply)
        return reply

    async def request_command(self, name: str, offset_cam_m: tuple[float, float, float] | None = None) -> str:
        """Land, hold or set_offset through the mission machine's checks; what it did, in one line."""
        reply = await self.core.request_command(name, offset_cam_m)
        (log.info if " refused: " not in reply else log.warning)("operator: %s", reply)
        return reply

    # ---- inputs from the other parts ------------------------------------------------------------------

    def on_frame(self, frame: RgbdFrame, result: DetectorResult) -> Any:
        """Every detector result: to the tracker and the mission (the flight core); the track state."""
        return self.core.on_frame(frame, result)

    def on_leader_position(self, msg: LeaderPositionMsg) -> None:
        """A leader position from MQTT, placed in the follower's local NED frame."""
        v = self.link.snapshot()
        self._origin.update(
            v.gps_fix_type, _finite(v.lat_deg), _finite(v.lon_deg), _finite(v.alt_amsl_m), v.p_ned_m
        )
        origin = self._origin.origin
        if origin is None:
            return  # no GPS fix seen yet: the frame is unknown
        age_s = max(0.0, self._wall_time_s() - msg.time_unix_s)
        p = origin.to_ned(msg.lat_deg, msg.lon_deg, msg.alt_amsl_m)
        self.core.submit_leader_shared(
            SharedLeaderPosition(
                stamp_s=self.clock.now_s() - age_s,
                p_ned_m=p,
                yaw_rad=None if msg.yaw_deg is None else math.radians(msg.yaw_deg),
                v_ned_m_s=msg.v_ned_m_s,
                yaw_rate_rad_s=None if msg.yaw_rate_deg_s is None else math.radians(msg.yaw_rate_deg_s),
            )
        )
        self.leader_positions_used += 1

    def on_neighbour_pose(self, name: str, msg: PoseMsg) -> None:
        """Another follower's pose from MQTT (formations), placed in this follower's local NED frame."""
        origin = self._origin.origin
        if origin is None or msg.time_unix_s is None or msg.p_ned_m is None:
            return  # our frame is unknown yet, or the neighbour's own position is not valid
        if msg.lat_deg is None or msg.lon_deg is None or msg.alt_amsl_m is None:
            return
        age_s = max(0.0, self._wall_time_s() - msg.time_unix_s)
        p = origin.to_ned(msg.lat_deg, msg.lon_deg, msg.alt_amsl_m)
        v = msg.v_ned_m_s if msg.v_ned_m_s is not None else (0.0, 0.0, 0.0)
        self.core.submit_neighbour(SharedNeighbour(name, self.clock.now_s() - age_s, p, v))

    # ---- internals ------------------------------------------------------------------------------------

    def _on_transition(self, tr: Transition) -> None:
        if tr.to_state != tr.from_state:
            self._entered_s = self.clock.now_s()
        self._last = tr
        if self._on_change is not None:
            self._on_change(
                StateChange(
                    stamp_s=tr.stamp_s,
                    from_state=tr.from_state.value,
                    to_state=tr.to_state.value,
                    reason=tr.reason.value,
                    reason_code=tr.reason.name,
                    severity=tr.severity.value,
                    detail=tr.detail,
                    statustext=tr.statustext(),
                )
            )

    def _on_step(self, inputs: MissionInputs, out: StepOutput) -> None:
        self._last_step_s = self.clock.now_s()
        self._last_output = out

    async def feed_telemetry(self) -> None:
        """The follower's attitude and velocity into perception's histories, polled on the link's clock."""
        while True:
            self.core.feed_telemetry()
            await asyncio.sleep(_ATTITUDE_POLL_S)


def _no_detection(frame: RgbdFrame) -> DetectorResult:
    raise AssertionError("this flight adapter was built without a detector")  # pragma: no cover


class LinkGcs:
    """STATUSTEXT and ONBOARD_COMPUTER_STATUS over the vehicle link."""

    def __init__(self, link: Any) -> None:
        self.link = link

    async def send_status_text(self, text: str, severity: str) -> None:
        await self.link.send_status_text(text, Severity(severity))

    async def send_onboard_computer_status(self, status: OnboardComputerStatus) -> None:
        # MAVSDK has no ONBOARD_COMPUTER_STATUS API; its MavlinkDirect plugin sends any common message.
        # The link does not expose it publicly yet, so this reaches for its plugin (see docs/service.md).
        direct = getattr(self.link, "_direct", None)
        if direct is None:
            return  # not connected yet
        from mavsdk.plugins import mavlink_direct  # noqa: PLC0415 (mavsdk: heavy)

        msg = mavlink_direct.MavlinkMessage(
            message_name="ONBOARD_COMPUTER_STATUS", fields_json=json.dumps(status.fields)
        )
        await direct.send_message(msg)


#: An observer of the per-frame path: (frame, detector result, tracker state, pose + tracker wall ms).
FrameObserver = Callable[[RgbdFrame, DetectorResult, Any, float], None]


def make_parts_factory(cfg: Config, clock: Clock, *, on_frame: FrameObserver | None = None) -> PartsFactory:
    """The factory ``FollowerService`` calls to open the parts on its exit stack.

    ``on_frame`` (optional, for ``companion sim``'s scoring) sees every processed frame after the mission
    got its estimate; it must not block and never feeds anything back.
    """

    async def open_parts(stack: contextlib.AsyncExitStack, ctx: PartsContext) -> Parts:
        # Cheapest to fail first: the model (exit 2), then the camera (exit 3), then the link.
        stage = await asyncio.to_thread(load_detect, cfg)  # reads and checks the weights: off the loop
        source: Any = open_source(cfg.camera, clock=ctx.clock)
        # The RealSense source already stamps on arrival, our clock; "source" stamps are on it already too.
        if cfg.camera.source != "realsense" and cfg.camera.stamps == "mapped":
            source = ServiceClockSource(source, ctx.clock)
        source = await stack.enter_async_context(source)

        from companion.vehicle.mavsdk_link import MavsdkVehicleLink  # noqa: PLC0415 (mavsdk: heavy)

        background: dict[str, Callable[[], Any]] = {}
        extra_status: dict[str, Callable[[], Any]] = {}
        link_cfg = cfg.link
        if cfg.link.signing:
            # MAVSDK cannot sign: it talks to the relay, which signs and checks for it (signing_relay.py).
            relay = await open_signing_relay(cfg, stack)
            link_cfg = cfg.link.model_copy(update={"url": relay.mavsdk_url})
            background["companion.signing"] = relay.run
            extra_status["mavlink_signing"] = relay.stats
        link = await stack.enter_async_context(
            MavsdkVehicleLink(
                link_cfg,
                clock,
                leader_system_id=cfg.leader.mavlink_system_id,
                ev_position_bits=ev_position_bits_for(cfg.mission.gps_loss_policy),
            )
        )
        flight = FlightAdapter(cfg, link, clock, stage)
        flight.core.observers.append(TickAges(ctx.latency, clock))
        recorder = open_recorder(cfg, flight.core, clock, ctx, stack)
        if recorder is not None:
            extra_status["viz"] = recorder.counters

        def process(frame: RgbdFrame, result: DetectorResult) -> Any:
            t0_s = time.perf_counter()
            track = flight.on_frame(frame, result)
            if on_frame is not None:
                on_frame(frame, result, track, (time.perf_counter() - t0_s) * 1e3)
            return track

        perception: PerceptionLoop = PerceptionLoop(
            source, stage.detect, process, clock=ctx.clock, latency=ctx.latency, health=ctx.health
        )
        return Parts(
            mission=flight,
            gcs=LinkGcs(link),
            perception=perception,
            on_leader_position=flight.on_leader_position,
            on_neighbour_pose=flight.on_neighbour_pose if cfg.formation.neighbour_ids else None,
            background={
                **background,
                "companion.vehicle": link.run,
                "companion.attitude": flight.feed_telemetry,
            },
            extra_status=extra_status,
            link_ready=link.wait_ready,
        )

    return open_parts


def open_recorder(
    cfg: Config, core: FlightCore, clock: Clock, ctx: PartsContext, stack: contextlib.AsyncExitStack
) -> Any:
    """The live view and the flight log (``[viz]``) observing ``core``, entered on ``stack``; None when off.

    The log goes to ``viz.log_dir`` (default ``flights/`` in the state folder), one file set per start, its
    times on the wall clock.
    """
    if not (cfg.viz.live or cfg.viz.log):
        return None
    from companion.viz.recorder import wall_offset_s  # noqa: PLC0415 (the Foxglove SDK: only when on)
    from companion.viz.setup import LogPlace, build_recorder, health_flags  # noqa: PLC0415
    from companion.viz.sinks import flight_stem  # noqa: PLC0415

    place = None
    if cfg.viz.log:
        folder = (
            Path(cfg.viz.log_dir) if cfg.viz.log_dir else resolve_state_dir(cfg.service.state_dir, os.environ)
        )
        if not cfg.viz.log_dir:
            folder = folder / "flights"
        place = LogPlace(folder, flight_stem(cfg.vehicle_id), {"vehicle_id": cfg.vehicle_id})
    recorder = build_recorder(
        cfg.viz,
        core.pipeline.camera,
        clock,
        log_place=place,
        server_name=f"wingman {cfg.vehicle_id}",
        time_offset_s=wall_offset_s(clock),
        health=health_flags(ctx.health),
    )
    if recorder is not None:
        stack.enter_context(recorder)
        core.observers.append(recorder)
    return recorder


async def open_signing_relay(cfg: Config, stack: contextlib.AsyncExitStack) -> Any:
    """The MAVLink signing relay for ``cfg.link`` on ``stack``; a key that cannot be used is a ConfigError."""
    from companion.vehicle.mavlink_signing import load_key  # noqa: PLC0415 (only with signing)
    from companion.vehicle.signing_relay import SigningRelay  # noqa: PLC0415

    try:
        key = await asyncio.to_thread(load_key, cfg.link.signing_key_file)
    except (OSError, ValueError) as exc:
        raise ConfigError("[link] signing_key_file", [str(exc)]) from None
    state_dir = resolve_state_dir(cfg.service.state_dir, os.environ)
    return await stack.enter_async_context(SigningRelay(cfg.link, key, state_dir))


def load_detect(cfg: Config) -> DetectStage:
    """The per-frame detection ``detector.runtime`` selects (blocking: loads the weights)."""
    if cfg.detector.runtime == "truth":
        truth = TruthDetector()
        log.warning(
            "detector: ground-truth boxes from the simulator (detector.runtime = truth), not the network"
        )
        return DetectStage(truth.detect_frame, description="ground-truth boxes")
    from companion.perception.detector import detect_stage  # noqa: PLC0415 (onnxruntime/torch: heavy)

    stage = detect_stage(cfg.detector)
    log.info("detector: %s", stage.description)
    return stage


def autopilot_probe(cfg: Config, timeout_s: float) -> list[CheckResult]:
    """Standalone autopilot and GPS checks (no service running): listen on the link for ``timeout_s``."""
    return asyncio.run(_probe(cfg, timeout_s))


async def _probe(cfg: Config, timeout_s: float) -> list[CheckResult]:
    from companion.vehicle.mavsdk_link import MavsdkVehicleLink  # noqa: PLC0415 (mavsdk: heavy)

    clock = MonotonicClock()
    # A health check reads PX4's offboard-loss action and never changes it; it judges the link's autopilots
    # (only the leader's: refused) within its own time.
    link_cfg = cfg.link.model_copy(
        update={
            "offboard_loss_action": "autopilot",
            "connect_timeout_s": min(cfg.link.connect_timeout_s, timeout_s / 2),
        }
    )
    try:
        async with contextlib.AsyncExitStack() as stack:
            if cfg.link.signing:
                # Through the signing relay, which never sends the key: a health check changes nothing.
                quiet = cfg.link.model_copy(update={"signing_provision": False})
                relay = await open_signing_relay(cfg.model_copy(update={"link": quiet}), stack)
                link_cfg = link_cfg.model_copy(update={"url": relay.mavsdk_url})
            link = await stack.enter_async_context(
                MavsdkVehicleLink(link_cfg, clock, leader_system_id=cfg.leader.mavlink_system_id)
            )
            tg = await stack.enter_async_context(compat.TaskGroup())
            task = tg.create_task(link.run(), name="companion.health.link")
            try:
                async with compat.timeout(timeout_s):
                    await link.wait_ready()
                    for _ in range(30):  # GPS_RAW_INT comes at 1-5 Hz: give it up to 3 s
                        s = link.snapshot()
                        if (
                            s.gps_stamp_s > NEVER_S
                            and s.offboard_loss_param is not None
                            and s.home_position_ok
                        ):
                            break
                        await asyncio.sleep(0.1)
            except TimeoutError:
                pass
            finally:
                task.cancel()
            v = link.snapshot()
    except (CompanionError, compat.ExceptionGroup) as exc:
        err = exc if isinstance(exc, CompanionError) else first_companion_error(exc)
        if err is None:
            raise
        return [
            CheckResult("autopilot", False, str(err)),
            CheckResult("gps", False, "unknown (no autopilot)"),
        ]
    if not v.connected:
        return [
            CheckResult("autopilot", False, f"no heartbeat on {cfg.link.url} within {timeout_s:.0f} s"),
            CheckResult("gps", False, "unknown (no autopilot)"),
        ]
    return [
        CheckResult(
            "autopilot",
            True,
            f"heartbeat on {cfg.link.url}, {v.flight_mode.value}, offboard loss: "
            + ("unknown" if v.offboard_loss_param is None else failsafe.describe(v.offboard_loss_param)),
        ),
        CheckResult(
            "gps",
            v.gps_fix_type >= 3 and v.position_valid is not False and v.home_position_ok,
            f"fix type {v.gps_fix_type}, {v.gps_satellites} satellites, "
            + ("position invalid, " if v.position_valid is False else "")
            + ("home set" if v.home_position_ok else "no home yet"),
        ),
    ]
