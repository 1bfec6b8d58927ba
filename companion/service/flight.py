"""``FlightService``: from frames, shares and operator commands to setpoints, once for every harness.

The service (MAVSDK over UDP or serial, wall clock), the real-path and lockstep evaluation harnesses and
the formation runs all fly this one object; they differ only in the clock and the link they hand it and in
how often they call it. Its input surface:

* :meth:`FlightService.on_frame`: every detector result (pose, tracker, the detector's feedback, the
  mission's leader estimate and the depth guard's reading);
* shares: :meth:`~FlightService.on_leader_position` and :meth:`~FlightService.on_neighbour_pose` as MQTT
  brings them, or :meth:`~FlightService.submit_leader_shared` / :meth:`~FlightService.submit_neighbour`
  already in the follower's frame;
* :meth:`~FlightService.command`: every operator command (CLI, MQTT), checked once by the mission machine
  on the control tick that takes it and answered with that verdict;
* :meth:`~FlightService.request_start` / :meth:`~FlightService.request_shutdown`;
* :meth:`~FlightService.feed_telemetry` whenever telemetry may have moved (attitude and velocity into
  perception's histories, on the frames' clock).

Its only asyncio edge is :meth:`~FlightService.run`, the mission runner's control tick. Observers
(:attr:`FlightService.observers`: the live view, the flight log, the harnesses' scorers) see every
processed frame, control step and transition after the flight has used it; they never feed anything back.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from companion.config import Config
from companion.estimation.identity import Expectation, LeaderIdentity, expectations
from companion.estimation.own_velocity import OwnVelocity
from companion.estimation.pipeline import PerceptionPipeline
from companion.kernel.camera import RgbdFrame
from companion.kernel.clock import Clock
from companion.kernel.flight import NEVER_S, Vec3T, VehicleState
from companion.kernel.frames import Mat3, R_from_euler, Vec3, quat_from_euler
from companion.mission.machine import MissionMachine
from companion.mission.types import (
    AirframeDrag,
    MissionInputs,
    MissionState,
    OperatorRequest,
    OperatorVerdict,
    SharedLeaderPosition,
    SharedNeighbour,
    StepOutput,
    Transition,
)
from companion.perception.transform import AttitudeHistory, CameraGeometry
from companion.perception.types import DetectorResult, DetectStage
from companion.service.autolabel_tap import AutoLabelTap
from companion.service.heading import HeadingCorrectedLink
from companion.service.mission_runner import MissionRunner
from companion.service.ports import FlightSnapshot, LeaderSummary, StateChange, VehicleSummary
from companion.telemetry.payloads import LeaderPositionMsg, PoseMsg
from companion.telemetry.share_frame import ShareFrame
from companion.vehicle import failsafe
from companion.vehicle.link import VehicleLink

log = logging.getLogger(__name__)

#: A shared position (leader's or a neighbour's) older than this is not used to tell them apart, s.
SHARE_STALE_S = 1.0
#: How often the follower's attitude is copied from telemetry into the perception's history, s.
TELEMETRY_POLL_S = 0.01


class FlightObserver(Protocol):
    """Sees the flight without touching it. Called on the flight loop: must return at once and never raise."""

    def on_frame(self, frame: RgbdFrame, result: DetectorResult, track: Any) -> None: ...

    def on_step(self, inputs: MissionInputs, out: StepOutput) -> None: ...

    def on_transition(self, tr: Transition) -> None: ...


@dataclass(frozen=True, slots=True)
class Callbacks:
    """A :class:`FlightObserver` made of plain functions; any of them may be left out."""

    frame: Callable[[RgbdFrame, DetectorResult, Any], None] | None = None
    step: Callable[[MissionInputs, StepOutput], None] | None = None
    transition: Callable[[Transition], None] | None = None

    def on_frame(self, frame: RgbdFrame, result: DetectorResult, track: Any) -> None:
        if self.frame is not None:
            self.frame(frame, result, track)

    def on_step(self, inputs: MissionInputs, out: StepOutput) -> None:
        if self.step is not None:
            self.step(inputs, out)

    def on_transition(self, tr: Transition) -> None:
        if self.transition is not None:
            self.transition(tr)


class FlightService:
    """The mission, its runner and perception after the detector, as one object with one input surface.

    Args:
        cfg: the service config.
        link: the autopilot (``MavsdkVehicleLink`` in the service, ``MessageVehicleLink`` in lockstep).
        clock: the clock the link, the frames and the mission share.
        stage: the detection step (its ``after_track`` feedback is called here); None: no detector (a
            flight fed no frames).
        wall_time_s: Unix time now (MQTT shares carry Unix stamps), s.
    """

    def __init__(
        self,
        cfg: Config,
        link: VehicleLink,
        clock: Clock,
        stage: DetectStage | None = None,
        *,
        wall_time_s: Callable[[], float] = time.time,
    ) -> None:
        self.cfg = cfg
        #: The autopilot as it reports, and as the mission and the camera see it: its heading error out.
        self.raw_link = link
        self.link = HeadingCorrectedLink(link)
        self.clock = clock
        self.stage = stage if stage is not None else DetectStage(_no_detection)
        self._wall_time_s = wall_time_s
        self.machine = MissionMachine(cfg)
        #: Called after the flight used each frame, step and transition (see :class:`FlightObserver`).
        self.observers: list[FlightObserver] = []
        self._on_change: Callable[[StateChange], None] | None = None
        self._last: Transition | None = None
        self._entered_s = clock.now_s()
        self._last_step_s: float | None = None
        self._last_output: StepOutput | None = None
        #: Where MQTT's geodetic shares sit in our local frame.
        self._share_frame = ShareFrame()
        #: Leader positions from MQTT placed in the follower's frame and handed to the mission.
        self.leader_positions_used = 0
        self.runner = MissionRunner(
            self.link,
            self.machine,
            clock,
            rate_hz=cfg.link.setpoint_rate_hz,
            command_timeout_s=cfg.link.command_timeout_s,
            on_transition=self._transition,
            on_step=self._step,
        )
        # The depth guard looks out as far as the mission's separation barrier needs to brake.
        self.pipeline = PerceptionPipeline.from_config(cfg, guard_brake_m_s2=self.machine.limits.brake_m_s2)
        #: The tracker's latest output (for the status endpoint).
        self.track: Any = None
        self._attitude_stamp_s = NEVER_S
        self._velocity_stamp_s = NEVER_S
        #: The follower's own velocity for the tracker's ego-motion, with and without GPS.
        self.own_velocity = OwnVelocity()
        #: Auto-labelling while GPS is good (``[autolabel] enabled``); its writer runs with :meth:`run`.
        self.autolabel = AutoLabelTap(cfg, self.pipeline.camera) if cfg.autolabel.enabled else None
        # Formations: the leader told apart from neighbours by shares and the plan.
        if cfg.formation.slot_leader_m is not None:
            self.pipeline.identity = LeaderIdentity()

    def on_frame(self, frame: RgbdFrame, result: DetectorResult) -> Any:
        """One detector result through pose and tracker to the mission; returns the tracker's state."""
        if self.pipeline.identity is not None:
            self.pipeline.identity.set(*self._expect(frame.stamp_s))
        track = self.pipeline.process(frame, result.detections)
        if self.pipeline.far_field_rejection is not None:
            log.warning("%s", self.pipeline.far_field_rejection.describe())
        self.stage.after_track(track)
        self.track = track
        est = track.leader_estimate()
        if est is not None:
            self.runner.submit_leader(est)
        self.runner.submit_obstacle(self.pipeline.obstacle(frame, track))
        if self.autolabel is not None:
            self.autolabel.on_frame(frame, self.link.snapshot(), self.pipeline.attitude)
        for observer in self.observers:
            observer.on_frame(frame, result, track)
        return track

    def _transition(self, tr: Transition) -> None:
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
        for observer in self.observers:
            observer.on_transition(tr)

    def _step(self, inputs: MissionInputs, out: StepOutput) -> None:
        self._last_step_s = self.clock.now_s()
        self._last_output = out
        for observer in self.observers:
            observer.on_step(inputs, out)

    def feed_telemetry(self) -> None:
        """Copy each new attitude and velocity sample from the link into perception's histories.

        The velocity is the tracker's ego-motion, PX4's or, after a GPS loss, the drag model's
        (:class:`~companion.estimation.own_velocity.OwnVelocity` decides, on the mission's GPS verdict).
        """
        v = self.raw_link.snapshot()
        if v.attitude_stamp_s > self._attitude_stamp_s:
            self._attitude_stamp_s = v.attitude_stamp_s
            ego_model = self.own_velocity.ego.model() if self.machine.gps_ok else None
            said = self.link.update(ego_model, v.attitude_stamp_s)
            if said is not None:
                log.info("%s", said)
            yaw = v.yaw_rad - self.link.applied_rad
            self.pipeline.attitude.push(v.attitude_stamp_s, quat_from_euler(v.roll_rad, v.pitch_rad, yaw))
        if v.velocity_stamp_s > self._velocity_stamp_s:
            stamp_s = self._velocity_stamp_s = v.velocity_stamp_s
            aided = self.machine.gps_ok and v.position_valid is not False
            sample = self.own_velocity.update(stamp_s, v.v_ned_m_s, _R_raw(v), aided=aided)
            if sample.learnt:
                m = self.own_velocity.ego.model()
                self.runner.submit_airframe(None if m is None else AirframeDrag(m.drag_per_s, m.push_ne_m_s2))
            if sample.v_ned_m_s is not None:
                self.pipeline.velocity.push(stamp_s, sample.v_ned_m_s)

    def _expect(self, stamp_s: float) -> tuple[Expectation | None, list[Expectation]]:
        """Where the leader and the neighbours should be at a frame's stamp (see estimation.identity)."""
        v = self.link.snapshot()
        own = v.p_ned_m if self.machine.gps_ok and v.position_valid is True else None
        sh = self.runner.leader_shared
        leader_p, age, yaw = None, 0.0, None
        if sh is not None and 0.0 <= stamp_s - sh.stamp_s <= SHARE_STALE_S:
            age = stamp_s - sh.stamp_s
            leader_p = _brought_to(sh.p_ned_m, sh.v_ned_m_s or (0.0, 0.0, 0.0), age)
            yaw = sh.yaw_rad
        neighbours = [
            _brought_to(n.p_ned_m, n.v_ned_m_s, stamp_s - n.stamp_s)
            for n in self.runner.neighbours.values()
            if 0.0 <= stamp_s - n.stamp_s <= SHARE_STALE_S
        ]
        f = self.cfg.formation
        return expectations(
            own_p_ned_m=None if own is None else np.asarray(own, dtype=np.float64),
            leader_p_ned_m=leader_p,
            leader_age_s=age,
            leader_yaw_rad=yaw,
            neighbour_p_ned_m=neighbours,
            slot_leader_m=f.slot_leader_m,
            neighbour_slots_m=f.neighbour_slots_m,
        )

    def submit_neighbour(self, neighbour: SharedNeighbour) -> None:
        """Another follower's shared position (formations): separation and the leader's identity."""
        self.runner.submit_neighbour(neighbour)

    def submit_leader_shared(self, position: SharedLeaderPosition) -> None:
        """The leader's shared position, to the mission and the auto-labeller."""
        self.runner.submit_leader_shared(position)
        if self.autolabel is not None:
            self.autolabel.share(position)

    def on_leader_position(self, msg: LeaderPositionMsg) -> None:
        """A leader position from MQTT, placed in the follower's local NED frame (the autopilot's own)."""
        own = self.raw_link.snapshot()
        shared = self._share_frame.leader(msg, own, self._wall_time_s(), self.clock.now_s())
        if shared is not None:
            self.submit_leader_shared(shared)
            self.leader_positions_used += 1

    def on_neighbour_pose(self, name: str, msg: PoseMsg) -> None:
        """Another follower's pose from MQTT (formations), placed in this follower's local NED frame."""
        neighbour = self._share_frame.neighbour(name, msg, self._wall_time_s(), self.clock.now_s())
        if neighbour is not None:
            self.submit_neighbour(neighbour)

    def request_start(self, *, takeover: bool = True) -> None:
        """Start without waiting for an answer (``service.auto_start``, the harnesses).

        See :meth:`MissionRunner.request_start`; an operator's start goes through :meth:`command`.
        """
        self.runner.request_start(takeover=takeover)

    def request_shutdown(self) -> None:
        """Perform the configured safe action; :meth:`run` returns once it is under way."""
        self.runner.request_shutdown()

    async def command(self, req: OperatorRequest) -> OperatorVerdict:
        """An operator's start, land, hold or new slot: the mission's verdict on its tick."""
        verdict = await self.runner.command(req)
        (log.info if verdict.taken else log.warning)("operator: %s", verdict)
        return verdict

    # ---- what the service reports -------------------------------------------------------------------

    @property
    def state(self) -> MissionState:
        """The mission's state now."""
        return self.machine.state

    @property
    def camera(self) -> CameraGeometry:
        """The camera perception measures with (intrinsics and mount), for recorders and labellers."""
        return self.pipeline.camera

    @property
    def attitude(self) -> AttitudeHistory:
        """The follower's attitude as perception reads it (heading-corrected), by frame stamp."""
        return self.pipeline.attitude

    @property
    def identity(self) -> LeaderIdentity | None:
        """The leader told apart from neighbours (formations only; None for a lone follower)."""
        return self.pipeline.identity

    def set_on_change(self, callback: Callable[[StateChange], None]) -> None:
        """Have ``callback`` called for every transition, in order (the service's STATUSTEXT and MQTT)."""
        self._on_change = callback

    def snapshot(self) -> FlightSnapshot:
        """The flight as the status endpoint and MQTT show it, read without blocking."""
        now_s = self.clock.now_s()
        v = self.raw_link.snapshot()
        tr = self._last
        out = self._last_output
        shared = self.runner.leader_shared
        return FlightSnapshot(
            state=self.machine.state.value,
            reason=tr.reason.value if tr is not None else "starting",
            detail=tr.detail if tr is not None else "",
            state_age_s=now_s - self._entered_s,
            last_step_s=self._last_step_s,
            vehicle=vehicle_summary(v, now_s, getattr(self.raw_link, "system_id", None)),
            leader=self._leader_summary(now_s),
            formation_error_ned_m=out.formation_error_ned_m if out is not None else None,
            leader_share_age_s=None if shared is None else now_s - shared.stamp_s,
            led_on_leader_share=out is not None and out.led_on_shared_motion,
            on_leader_share_position=out is not None and out.coasted_on_shared_position,
            preflight_problems=self.machine.preflight_problems(v),
        )

    def _leader_summary(self, now_s: float) -> LeaderSummary | None:
        track = self.track
        if track is None or track.estimate is None:
            return None
        est = track.estimate
        return LeaderSummary(
            status=track.status.value,
            p_rel_ned_m=(float(est.p_ned_rel_m[0]), float(est.p_ned_rel_m[1]), float(est.p_ned_rel_m[2])),
            v_rel_ned_m_s=(
                float(est.v_ned_rel_m_s[0]),
                float(est.v_ned_rel_m_s[1]),
                float(est.v_ned_rel_m_s[2]),
            ),
            cov_ned_m2=tuple(tuple(round(float(c), 5) for c in row) for row in est.cov_ned_m2),  # type: ignore[arg-type]
            age_s=max(0.0, now_s - track.last_measurement_s)
            if track.last_measurement_s is not None
            else None,
            range_m=float(est.range_m),
        )

    async def poll_telemetry(self) -> None:
        """:meth:`feed_telemetry` every ``TELEMETRY_POLL_S`` (the service's link streams on its own)."""
        while True:
            self.feed_telemetry()
            await asyncio.sleep(TELEMETRY_POLL_S)

    async def run(self) -> None:
        """The mission until its shutdown action is under way."""
        if self.autolabel is not None:
            try:
                self.autolabel.__enter__()
            except OSError as exc:  # a full disk or a folder it may not write: fly on without labels
                log.warning("auto-labels off: %s", exc)
                self.autolabel = None
        try:
            await self.runner.run()
        finally:
            if self.autolabel is not None:
                self.autolabel.__exit__(None, None, None)


def _brought_to(p_ned_m: Vec3T, v_ned_m_s: Vec3T, age_s: float) -> Vec3:
    """A shared position ``age_s`` old, moved on at its shared velocity (NED, m)."""
    return np.asarray(p_ned_m, dtype=np.float64) + age_s * np.asarray(v_ned_m_s, dtype=np.float64)


def _R_raw(v: VehicleState) -> Mat3 | None:
    """``R_ned_body`` from the autopilot's own attitude (None when it is not finite)."""
    if not all(math.isfinite(x) for x in (v.roll_rad, v.pitch_rad, v.yaw_rad)):
        return None
    return R_from_euler(v.roll_rad, v.pitch_rad, v.yaw_rad)


def _finite(x: float) -> float | None:
    return x if math.isfinite(x) else None


def _no_detection(frame: RgbdFrame) -> DetectorResult:
    raise AssertionError("this flight was built without a detector")  # pragma: no cover


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
