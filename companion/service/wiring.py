"""Builds the real parts (vehicle link, frame source, detector, the flight) for the service.

With :mod:`companion.service.flight` (the one object from a frame to a setpoint, shared with the
harnesses) this is where the service meets the vehicle link, the camera and the detector. The CLI
imports it when the service starts, not before.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
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
from companion.kernel.flight import NEVER_S, Severity
from companion.perception.sources import open_source
from companion.perception.truth_detector import TruthDetector
from companion.perception.types import DetectorResult, DetectStage
from companion.service.flight import FlightService
from companion.service.health_checks import CheckResult
from companion.service.latency import TickAges
from companion.service.parts import Parts, PartsContext, PartsFactory
from companion.service.perception_loop import PerceptionLoop
from companion.service.ports import (
    OnboardComputerStatus,
)
from companion.service.stamps import ServiceClockSource
from companion.vehicle import failsafe
from companion.vehicle.external_vision import ev_position_bits_for
from companion.vehicle.link import VehicleLink

log = logging.getLogger(__name__)


class LinkGcs:
    """STATUSTEXT and ONBOARD_COMPUTER_STATUS over the vehicle link."""

    def __init__(self, link: VehicleLink) -> None:
        self.link = link

    async def send_status_text(self, text: str, severity: str) -> None:
        await self.link.send_status_text(text, Severity(severity))

    async def send_onboard_computer_status(self, status: OnboardComputerStatus) -> None:
        await self.link.send_onboard_computer_status(status.fields)


#: An observer of the per-frame path: (frame, detector result, tracker state, pose + tracker wall ms).
FrameObserver = Callable[[RgbdFrame, DetectorResult, Any, float], None]


#: Called once the flight is built, with the service's exit stack and context (a harness adds observers).
FlightHook = Callable[[FlightService, contextlib.AsyncExitStack, PartsContext], None]


def make_parts_factory(
    cfg: Config,
    clock: Clock,
    *,
    on_frame: FrameObserver | None = None,
    on_flight: FlightHook | None = None,
) -> PartsFactory:
    """The factory ``FollowerService`` calls to open the parts on its exit stack.

    ``on_frame`` (optional, for ``companion sim``'s scoring) sees every processed frame after the mission
    got its estimate, with its processing time; ``on_flight`` sees the flight once it is built (to add
    observers). Neither may block, and neither feeds anything back.
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
        flight = FlightService(cfg, link, clock, stage)
        flight.observers.append(TickAges(ctx.latency, clock))
        recorder = open_recorder(cfg, flight, clock, ctx, stack)
        if on_flight is not None:
            on_flight(flight, stack, ctx)
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
                "companion.attitude": flight.poll_telemetry,
            },
            extra_status=extra_status,
            link_ready=link.wait_ready,
        )

    return open_parts


def open_recorder(
    cfg: Config, flight: FlightService, clock: Clock, ctx: PartsContext, stack: contextlib.AsyncExitStack
) -> Any:
    """The live view and the flight log (``[viz]``) observing ``flight``, entered on ``stack``; None when off.

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
        flight.camera,
        clock,
        log_place=place,
        server_name=f"wingman {cfg.vehicle_id}",
        time_offset_s=wall_offset_s(clock),
        health=health_flags(ctx.health),
    )
    if recorder is not None:
        stack.enter_context(recorder)
        flight.observers.append(recorder)
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
