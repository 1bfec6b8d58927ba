"""``FlightCore``: from a frame, telemetry and operator commands to setpoints, once for every harness.

The service (:mod:`companion.service.wiring`, MAVSDK over UDP or serial, wall clock) and the lockstep
evaluation harness (:mod:`companion.lab.evaluation.lockstep`, MAVLink message objects, simulated clock) both
fly this class; they differ only in the clock and the link they hand it and in how often they call it:

* :meth:`on_frame` for every detector result (pose, tracker, the detector's feedback, the mission's leader
  estimate and the depth guard's reading);
* :meth:`feed_telemetry` whenever telemetry may have moved (the follower's attitude and velocity into
  perception's histories, on the frames' clock);
* :meth:`request_command` and :meth:`operator_start` for every operator command (CLI, MQTT): always
  through the mission machine's checks, never straight to the autopilot; answered with what was done.

Observers (:attr:`FlightCore.observers`, e.g. the live view and the flight log) see every processed frame,
control step and transition after the flight has used it; they never feed anything back.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np

from companion.config import Config
from companion.estimation.ego_velocity import EgoVelocityObserver
from companion.estimation.identity import Expectation, LeaderIdentity, expectations
from companion.estimation.pipeline import PerceptionPipeline
from companion.kernel.camera import RgbdFrame
from companion.kernel.clock import Clock
from companion.kernel.flight import NEVER_S, Vec3T, VehicleState
from companion.kernel.frames import Mat3, R_from_euler, Vec3, quat_from_euler
from companion.mission.machine import MissionMachine
from companion.mission.types import (
    MissionInputs,
    SharedLeaderPosition,
    SharedNeighbour,
    StepOutput,
    Transition,
)
from companion.perception.types import DetectorResult, DetectStage
from companion.service.autolabel_tap import AutoLabelTap
from companion.service.heading import HeadingCorrectedLink
from companion.service.mission_runner import MissionRunner
from companion.vehicle.link import VehicleLink

log = logging.getLogger(__name__)

#: A shared position (leader's or a neighbour's) older than this is not used to tell them apart, s.
SHARE_STALE_S = 1.0


class FlightObserver(Protocol):
    """Sees the flight without touching it. Called on the flight loop: must return at once and never raise."""

    def on_frame(self, frame: RgbdFrame, result: DetectorResult, track: Any) -> None: ...

    def on_step(self, inputs: MissionInputs, out: StepOutput) -> None: ...

    def on_transition(self, tr: Transition) -> None: ...


class FlightCore:
    """The mission, its runner and perception after the detector, glued as the service flies them.

    Args:
        cfg: the service config.
        link: the autopilot (``MavsdkVehicleLink`` in the service, ``MessageVehicleLink`` in lockstep).
        clock: the clock the link, the frames and the mission share.
        stage: the detection step (its ``after_track`` feedback is called here).
        on_transition: every mission transition, once.
        on_step: every control tick's inputs and output.
    """

    def __init__(
        self,
        cfg: Config,
        link: VehicleLink,
        clock: Clock,
        stage: DetectStage,
        *,
        on_transition: Callable[[Transition], None] | None = None,
        on_step: Callable[[MissionInputs, StepOutput], None] | None = None,
    ) -> None:
        self.cfg = cfg
        #: The autopilot as it reports, and as the mission and the camera see it: its heading error out.
        self.raw_link = link
        self.link = HeadingCorrectedLink(link)
        self.stage = stage
        self.machine = MissionMachine(cfg)
        #: Called after the flight used each frame, step and transition (see :class:`FlightObserver`).
        self.observers: list[FlightObserver] = []
        self._on_transition = on_transition
        self._on_step = on_step
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
        #: The follower's own velocity without GPS (the tracker's ego-motion), and the last aided one.
        self.ego = EgoVelocityObserver()
        self._v_aided: Vec3T | None = None
        self._ego_said = False
        #: Auto-labelling while GPS is good (``[autolabel] enabled``); its writer runs with :meth:`run`.
        self.autolabel = AutoLabelTap(cfg, self.pipeline.camera) if cfg.autolabel.enabled else None
        # Formations: the leader told apart from neighbours by shares and the plan.
        if cfg.formation.slot_leader_m is not None:
            self.pipeline.identity = LeaderIdentity()
        self._shared: SharedLeaderPosition | None = None
        self._neighbours: dict[str, SharedNeighbour] = {}

    def on_frame(self, frame: RgbdFrame, result: DetectorResult) -> Any:
        """One detector result through pose and tracker to the mission; returns the tracker's state."""
        if self.pipeline.identity is not None:
            self.pipeline.identity.set(*self._expect(frame.stamp_s))
        track = self.pipeline.process(frame, result.detections)
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
        if self._on_transition is not None:
            self._on_transition(tr)
        for observer in self.observers:
            observer.on_transition(tr)

    def _step(self, inputs: MissionInputs, out: StepOutput) -> None:
        if self._on_step is not None:
            self._on_step(inputs, out)
        for observer in self.observers:
            observer.on_step(inputs, out)

    def feed_telemetry(self) -> None:
        """Copy each new attitude and velocity sample from the link into perception's histories.

        The velocity is the tracker's ego-motion: PX4's only while its estimate is GPS-aided; after a GPS
        loss PX4's dead-reckoned velocity runs off by metres per second within seconds. Then the
        :class:`EgoVelocityObserver`'s, from the drag model it learnt meanwhile and the attitude; without a
        model, none (the track predicts on its own relative velocity).
        """
        v = self.raw_link.snapshot()
        if v.attitude_stamp_s > self._attitude_stamp_s:
            self._attitude_stamp_s = v.attitude_stamp_s
            self.link.update(self.ego.model() if self.machine.gps_ok else None, v.attitude_stamp_s)
            yaw = v.yaw_rad - self.link.applied_rad
            self.pipeline.attitude.push(v.attitude_stamp_s, quat_from_euler(v.roll_rad, v.pitch_rad, yaw))
        if v.velocity_stamp_s > self._velocity_stamp_s:
            stamp_s = self._velocity_stamp_s = v.velocity_stamp_s
            # The ego model learns PX4's own attitude, heading error and all.
            R = _R_raw(v)
            ego = self.ego
            if self.machine.gps_ok and v.position_valid is not False:
                if R is not None:
                    ego.learn(stamp_s, v.v_ned_m_s, R)
                self._v_aided = v.v_ned_m_s
                self._ego_said = False
                self.pipeline.velocity.push(stamp_s, v.v_ned_m_s)
            elif R is not None and self._v_aided is not None:
                if not self._ego_said:
                    self._ego_said = True
                    _say_ego_model(ego)
                v_own = ego.step(stamp_s, R, self._v_aided)
                if v_own is not None:
                    self.pipeline.velocity.push(stamp_s, v_own)

    def _expect(self, stamp_s: float) -> tuple[Expectation | None, list[Expectation]]:
        """Where the leader and the neighbours should be at a frame's stamp (see estimation.identity)."""
        v = self.link.snapshot()
        own = v.p_ned_m if self.machine.gps_ok and v.position_valid is True else None
        sh = self._shared
        leader_p, age, yaw = None, 0.0, None
        if sh is not None and 0.0 <= stamp_s - sh.stamp_s <= SHARE_STALE_S:
            age = stamp_s - sh.stamp_s
            leader_p = _brought_to(sh.p_ned_m, sh.v_ned_m_s or (0.0, 0.0, 0.0), age)
            yaw = sh.yaw_rad
        neighbours = [
            _brought_to(n.p_ned_m, n.v_ned_m_s, stamp_s - n.stamp_s)
            for n in self._neighbours.values()
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
        self._neighbours[neighbour.name] = neighbour
        self.runner.submit_neighbour(neighbour)

    def submit_leader_shared(self, position: SharedLeaderPosition) -> None:
        """The leader's shared position, to the mission and the auto-labeller."""
        self._shared = position
        self.runner.submit_leader_shared(position)
        if self.autolabel is not None:
            self.autolabel.share(position)

    def request_start(self, *, takeover: bool = True) -> None:
        """See :meth:`MissionRunner.request_start`."""
        self.runner.request_start(takeover=takeover)

    def request_shutdown(self) -> None:
        self.runner.request_shutdown()

    async def operator_start(self) -> str:
        """See :meth:`MissionRunner.operator_start`."""
        return await self.runner.operator_start()

    async def request_command(self, name: str, offset_cam_m: tuple[float, float, float] | None = None) -> str:
        """An operator command through the mission machine's checks; the one-line answer."""
        return await self.runner.request_command(name, offset_cam_m)

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


def _say_ego_model(ego: EgoVelocityObserver) -> None:
    """One line at a GPS loss: what the follower's velocity will come from now."""
    m = ego.model()
    if m is None:
        log.warning("ego velocity: no drag model learnt before the GPS loss; the track predicts alone")
        return
    log.info(
        "ego velocity without GPS: drag %.2f 1/s, wind push (%.2f, %.2f) m/s^2, heading error %.1f deg "
        "(%d samples)",
        m.drag_per_s,
        *m.push_ne_m_s2,
        math.degrees(m.heading_error_rad),
        m.samples,
    )


def _R_raw(v: VehicleState) -> Mat3 | None:
    """``R_ned_body`` from the autopilot's own attitude (None when it is not finite)."""
    if not all(math.isfinite(x) for x in (v.roll_rad, v.pitch_rad, v.yaw_rad)):
        return None
    return R_from_euler(v.roll_rad, v.pitch_rad, v.yaw_rad)
