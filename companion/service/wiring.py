"""Builds the real parts (vehicle link, mission runner, frame source, detector, tracker) for the service.

This is the only module of the service that imports the flight and perception packages; it adapts them
to :mod:`companion.service.ports`. Everything is imported when the service starts, not at import time.
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib
import json
import logging
import math
import time
from collections.abc import Callable
from typing import Any

from companion.app import Parts, PartsContext, PartsFactory
from companion.clock import Clock, MonotonicClock
from companion.config import Config
from companion.errors import CompanionError, NotBuiltError
from companion.frames import quat_from_euler
from companion.mission.formation import Slot
from companion.mission.machine import MissionMachine
from companion.mission.runner import MissionRunner
from companion.mission.types import (
    MissionInputs,
    SharedLeaderPosition,
    StepOutput,
    Transition,
)
from companion.perception.types import DetectorResult, DetectStage, RgbdFrame
from companion.service.health_checks import CheckResult
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
from companion.telemetry.payloads import LeaderPositionMsg
from companion.vehicle import failsafe
from companion.vehicle.link import VehicleLink
from companion.vehicle.types import NEVER_S, Severity, VehicleState

log = logging.getLogger(__name__)

#: Perception modules the service needs, and which part of the project owns each.
PERCEPTION_MODULES = {
    "companion.perception.detector": "detector",
    "companion.perception.pipeline": "perception",
    "companion.perception.sources": "perception",
}
#: How often the follower's attitude is copied from telemetry into the perception's history.
_ATTITUDE_POLL_S = 0.01


def missing_modules(modules: dict[str, str]) -> list[str]:
    """Modules that are not importable yet, as ``module (owner)``."""
    missing = []
    for module, owner in modules.items():
        try:
            importlib.import_module(module)
        except ModuleNotFoundError as exc:
            if exc.name is not None and module.startswith(exc.name):
                missing.append(f"{module} ({owner})")
            else:
                raise
    return missing


def _finite(x: float) -> float | None:
    return x if math.isfinite(x) else None


def vehicle_summary(v: VehicleState, now_s: float) -> VehicleSummary:
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
    )


class FlightAdapter:
    """Flight's :class:`MissionRunner` and :class:`VehicleLink` behind the service's ``MissionPort``."""

    def __init__(
        self, cfg: Config, link: VehicleLink, clock: Clock, wall_time_s: Callable[[], float] = time.time
    ) -> None:
        self.cfg = cfg
        self.link = link
        self.clock = clock
        self._wall_time_s = wall_time_s
        self.machine = MissionMachine(cfg)
        self.runner = MissionRunner(
            link,
            self.machine,
            clock,
            rate_hz=cfg.link.setpoint_rate_hz,
            command_timeout_s=cfg.link.command_timeout_s,
            on_transition=self._on_transition,
            on_step=self._on_step,
        )
        self._on_change: Callable[[StateChange], None] | None = None
        self._last: Transition | None = None
        self._entered_s = clock.now_s()
        self._last_step_s: float | None = None
        self._last_output: StepOutput | None = None
        self._track: Any = None
        self._origin = OriginTracker()
        self._operator: asyncio.Queue[str] = asyncio.Queue(maxsize=8)
        self.leader_positions_used = 0

    # ---- MissionPort ----------------------------------------------------------------------------------

    def set_on_change(self, callback: Callable[[StateChange], None]) -> None:
        self._on_change = callback

    def snapshot(self) -> FlightSnapshot:
        now_s = self.clock.now_s()
        v = self.link.snapshot()
        tr = self._last
        leader = None
        track = self._track
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
            vehicle=vehicle_summary(v, now_s),
            leader=leader,
            formation_error_ned_m=out.formation_error_ned_m if out is not None else None,
        )

    async def run(self) -> None:
        async with asyncio.TaskGroup() as tg:
            ops = tg.create_task(self._operator_commands(), name="companion.mission.operator")
            try:
                await self.runner.run()
            finally:
                ops.cancel()

    def request_start(self) -> None:
        self.runner.request_start()

    def request_shutdown(self) -> None:
        self.runner.request_shutdown()

    def request_command(self, name: str, offset_cam_m: tuple[float, float, float] | None = None) -> str:
        if name == "set_offset":
            assert offset_cam_m is not None  # noqa: S101 (the verifier guarantees it)
            if offset_cam_m[2] < self.cfg.safety.min_separation_m:
                return (
                    f"set_offset refused: forward offset below safety.min_separation_m ({offset_cam_m[2]} m)"
                )
            self.machine.law.slot = Slot.from_offset_cam(offset_cam_m)
            log.warning("operator: formation offset now %s m (camera frame)", offset_cam_m)
            return f"formation offset now {list(offset_cam_m)} m"
        try:
            self._operator.put_nowait(name)
        except asyncio.QueueFull:
            return f"{name} refused: operator commands backed up"
        return f"{name} requested: PX4 takes over from the companion"

    # ---- inputs from the other parts ------------------------------------------------------------------

    def submit_track(self, track: Any) -> None:
        """Every tracker output: kept for the status, and handed to the mission when there is an estimate."""
        self._track = track
        est = track.leader_estimate()
        if est is not None:
            self.runner.submit_leader(est)

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
        self.runner.submit_leader_shared(SharedLeaderPosition(stamp_s=self.clock.now_s() - age_s, p_ned_m=p))
        self.leader_positions_used += 1

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

    async def _operator_commands(self) -> None:
        while True:
            name = await self._operator.get()
            try:
                if name == "land":
                    await self.link.land()
                elif name == "hold":
                    await self.link.hold()
                log.warning("operator: %s sent to PX4", name)
            except CompanionError as exc:
                log.error("operator: %s failed: %s", name, exc)

    async def feed_attitude(self, history: Any, velocity: Any = None) -> None:
        """Copy each new attitude (and velocity) sample from telemetry into perception's histories.

        Same clock as the frames. The velocity is the follower's own, for the tracker's ego-motion.
        """
        last_stamp_s = NEVER_S
        last_v_stamp_s = NEVER_S
        while True:
            v = self.link.snapshot()
            if v.attitude_stamp_s > last_stamp_s:
                last_stamp_s = v.attitude_stamp_s
                history.push(last_stamp_s, quat_from_euler(v.roll_rad, v.pitch_rad, v.yaw_rad))
            if velocity is not None and v.velocity_stamp_s > last_v_stamp_s:
                last_v_stamp_s = v.velocity_stamp_s
                velocity.push(last_v_stamp_s, v.v_ned_m_s)
            await asyncio.sleep(_ATTITUDE_POLL_S)


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
        mavlink_direct = importlib.import_module("mavsdk.plugins.mavlink_direct")
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
        needed = dict(PERCEPTION_MODULES)
        if cfg.detector.runtime == "truth":
            del needed["companion.perception.detector"]
        missing = missing_modules(needed)
        if missing:
            raise NotBuiltError("run: not built yet: waiting on " + ", ".join(missing))
        # Cheapest to fail first: the model (exit 2), then the camera (exit 3), then the link.
        stage = await asyncio.to_thread(load_detect, cfg)  # reads and checks the weights: off the loop
        pipeline_mod: Any = importlib.import_module("companion.perception.pipeline")
        sources_mod: Any = importlib.import_module("companion.perception.sources")
        pipeline = pipeline_mod.PerceptionPipeline.from_config(cfg)
        source: Any = sources_mod.open_source(cfg.camera, clock=ctx.clock)
        # The RealSense source already stamps on arrival, our clock; "source" stamps are on it already too.
        if cfg.camera.source != "realsense" and cfg.camera.stamps == "mapped":
            source = ServiceClockSource(source, ctx.clock)
        source = await stack.enter_async_context(source)

        from companion.vehicle.mavsdk_link import MavsdkVehicleLink  # noqa: PLC0415 (mavsdk: heavy)

        link = await stack.enter_async_context(MavsdkVehicleLink(cfg.link, clock))
        flight = FlightAdapter(cfg, link, clock)

        def process(frame: RgbdFrame, result: DetectorResult) -> Any:
            t0_s = time.perf_counter()
            track = pipeline.process(frame, result.detections)
            stage.after_track(track)
            flight.submit_track(track)
            flight.runner.submit_obstacle(pipeline.obstacle(frame, track))
            if on_frame is not None:
                on_frame(frame, result, track, (time.perf_counter() - t0_s) * 1e3)
            return track

        perception: PerceptionLoop[Any] = PerceptionLoop(
            source, stage.detect, process, clock=ctx.clock, latency=ctx.latency, health=ctx.health
        )
        return Parts(
            mission=flight,
            gcs=LinkGcs(link),
            perception=perception,
            on_leader_position=flight.on_leader_position,
            background={
                "companion.vehicle": link.run,
                "companion.attitude": lambda: flight.feed_attitude(pipeline.attitude, pipeline.velocity),
            },
        )

    return open_parts


def load_detect(cfg: Config) -> DetectStage:
    """The per-frame detection ``detector.runtime`` selects (blocking: loads the weights)."""
    if cfg.detector.runtime == "truth":
        evaluate: Any = importlib.import_module("companion.perception.evaluate")
        truth = evaluate.TruthDetector()
        log.warning(
            "detector: ground-truth boxes from the simulator (detector.runtime = truth), not the network"
        )
        return DetectStage(truth.detect_frame, description="ground-truth boxes")
    detector_mod: Any = importlib.import_module("companion.perception.detector")
    stage: DetectStage = detector_mod.detect_stage(cfg.detector)
    log.info("detector: %s", stage.description)
    return stage


def autopilot_probe(cfg: Config, timeout_s: float) -> list[CheckResult]:
    """Standalone autopilot and GPS checks (no service running): listen on the link for ``timeout_s``."""
    return asyncio.run(_probe(cfg, timeout_s))


async def _probe(cfg: Config, timeout_s: float) -> list[CheckResult]:
    from companion.vehicle.mavsdk_link import MavsdkVehicleLink  # noqa: PLC0415 (mavsdk: heavy)

    clock = MonotonicClock()
    # A health check reads PX4's offboard-loss action and never changes it.
    link_cfg = cfg.link.model_copy(update={"offboard_loss_action": "autopilot"})
    try:
        async with MavsdkVehicleLink(link_cfg, clock) as link, asyncio.TaskGroup() as tg:
            task = tg.create_task(link.run(), name="companion.health.link")
            try:
                async with asyncio.timeout(timeout_s):
                    await link.wait_ready()
                    for _ in range(30):  # GPS_RAW_INT comes at 1-5 Hz: give it up to 3 s
                        s = link.snapshot()
                        if s.gps_stamp_s > NEVER_S and s.offboard_loss_param is not None:
                            break
                        await asyncio.sleep(0.1)
            except TimeoutError:
                pass
            finally:
                task.cancel()
            v = link.snapshot()
    except CompanionError as exc:
        return [
            CheckResult("autopilot", False, str(exc)),
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
            v.gps_fix_type >= 3,
            f"fix type {v.gps_fix_type}, {v.gps_satellites} satellites",
        ),
    ]
