"""The lockstep closed loop: the simulator, the camera and the service's cores on one clock, no sockets.

Fast and repeatable (Monte Carlo): a :class:`sitl.world.lockstep.World` steps the physics and the PX4-like
autopilots; an in-process :class:`sitl.render.renderer.Renderer` draws the follower's camera; the *same*
detector and the service's own :class:`~companion.service.flight_core.FlightCore` (pose, tracker, mission
machine and runner, and the glue between them) fly the follower through a
:class:`~companion.vehicle.message_link.MessageVehicleLink` that speaks MAVLink messages to
``world.link("follower")``. Everything runs on sim time (a :class:`ManualClock` set from the world).

What differs from the real path (``companion sim`` over UDP with MAVSDK) and why:

* Compute is instantaneous in sim time, so the camera pipeline's timing is modelled (the scenario's
  ``[timing]``, :mod:`companion.lab.evaluation.camera_timing`): by default a frame captured at ``t`` reaches
  the tracker and the mission at ``t + 60 ms`` (the D435i's own latency plus detection); jitter, dropped
  frames and a loaded detector are drawn from the run's seed. The real path measures its own. MAVLink
  latency and jitter (telemetry and setpoints) come from the scenario's ``[vehicles.follower.link]``.
* The camera renders only once the follower is armed (nothing before takeoff reaches the mission).

Truth reaches only the :class:`~companion.lab.evaluation.scoring.RunScorer`.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections import deque
from collections.abc import Callable
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion.config import Config
from companion.kernel.camera import RgbdFrame
from companion.kernel.clock import ManualClock
from companion.lab.evaluation.autolabel_check import AutoLabelCheck
from companion.lab.evaluation.camera_timing import CameraTiming
from companion.lab.evaluation.log import FlightLog
from companion.lab.evaluation.plots import Snapshot
from companion.lab.evaluation.runlog import attach_run_log
from companion.lab.evaluation.scoring import RunScorer
from companion.lab.evaluation.trace import RunObserver
from companion.mission.types import MissionInputs, SharedLeaderPosition, StepOutput, Transition
from companion.perception.autolabel import AutoLabelConfig
from companion.perception.types import DetectorResult, DetectStage
from companion.service.flight_core import FlightCore
from companion.vehicle.external_vision import ev_position_bits_for
from companion.vehicle.message_link import MessageVehicleLink

log = logging.getLogger(__name__)

#: Truth samples for crash and landing detection, per sim second.
TRUTH_RATE_HZ = 50.0
#: How often the leader's companion shares its position, Hz (both harnesses; the service's default share
#: limits take 2 s of age).
LEADER_SHARE_HZ = 10.0


@dataclass(frozen=True, slots=True)
class LockstepOptions:
    """Knobs of the lockstep harness (the scenario and the service config carry everything else)."""

    #: Camera frames kept for the report's strip.
    snapshots: int = 5
    #: Called now and then with the sim time (a progress line).
    progress: Callable[[float], None] | None = None
    #: Auto-label every frame while GPS is good, scored against the renderer's boxes (``auto_label`` in
    #: the report's extra figures).
    auto_label: bool = False
    #: Also write the auto-labelled frames here as a detector dataset (None: score only).
    auto_label_dir: Path | None = None
    #: The auto-labelled frames' sequence name (the dataset's group: one flight).
    auto_label_sequence: str = "0"
    #: Also write every frame with the renderer's own box here (an evaluation set).
    truth_label_dir: Path | None = None
    #: The run's MCAP log (the service's channels, :mod:`companion.lab.evaluation.runlog`); None: none.
    mcap_path: Path | None = None


@dataclass(slots=True)
class RunResult:
    """One run: the frozen log, the camera strip and figures beyond the contract."""

    log: FlightLog
    snapshots: list[Snapshot]
    extra: dict[str, Any] = field(default_factory=dict)
    #: Every step and frame, for ``trace.jsonl`` (None when not recorded).
    trace: RunObserver | None = None


@dataclass(slots=True)
class _InFlight:
    """A frame whose estimate reaches the mission at ``due_s``."""

    due_s: float
    frame: RgbdFrame
    result: DetectorResult
    compute_ms: float


class LockstepRun:
    """One scenario flown in lockstep. ``await run()`` returns the :class:`RunResult`.

    Args:
        world: the simulation (``sitl.world.lockstep.World``) with the scenario loaded; nothing stepped yet.
        renderer: an entered ``sitl.render.renderer.Renderer`` for the follower's camera.
        cfg: the service config the cores are built from (the scenario's overrides applied).
        stage: the detection step (the detector on one frame, and its feedback from the tracker).
        options: harness knobs.
    """

    def __init__(
        self, world: Any, renderer: Any, cfg: Config, stage: DetectStage, options: LockstepOptions
    ) -> None:
        self.world = world
        self.renderer = renderer
        self.cfg = cfg
        self.stage = stage
        self.options = options
        sc = world.scenario
        self.scenario = sc
        self.clock = ManualClock(world.t_s)
        follower = world.vehicle("follower")
        self.link = MessageVehicleLink(
            world.link("follower"),
            self.clock,
            cfg.link,
            follower.sysid,
            ev_position_bits=ev_position_bits_for(cfg.mission.gps_loss_policy),
        )
        self.core = FlightCore(
            cfg, self.link, self.clock, stage, on_transition=self._on_transition, on_step=self._on_step
        )
        self.machine = self.core.machine
        self.runner = self.core.runner
        self.pipeline = self.core.pipeline
        self.scorer = RunScorer.for_scenario(sc, options.snapshots)
        self.camera_timing = CameraTiming(sc.timing, world.seed)
        self._in_flight: deque[_InFlight] = deque()
        self._compute_ms: list[float] = []
        self.observer = RunObserver(self.clock, [])
        self.recorder = None
        if options.mcap_path is not None:
            meta = {"scenario": str(sc.name), "harness": "lockstep"}
            self.recorder = attach_run_log(
                cfg, self.core, self.clock, options.mcap_path, synchronous=True, metadata=meta
            )
        #: The leader's share to the mission (None: the config takes none), and when the next is due, sim s.
        self._share_period_s = 1.0 / LEADER_SHARE_HZ if cfg.leader.shared_position == "mqtt" else None
        self._next_share_s = 0.0
        self.autolabel: AutoLabelCheck | None = None
        if options.auto_label:
            self.autolabel = AutoLabelCheck(
                options.auto_label_dir,
                AutoLabelConfig(leader_span_m=cfg.leader.span_m),
                self.pipeline.camera,
                options.auto_label_sequence,
                options.truth_label_dir,
            )

    # ------------------------------------------------------------------ mission callbacks
    def _on_transition(self, tr: Transition) -> None:
        self.scorer.transition(tr.stamp_s, tr.from_state.name, tr.to_state.name, tr.reason.name)

    def _on_step(self, inputs: MissionInputs, out: StepOutput) -> None:
        self.observer.on_step(inputs, out)
        f, ld = self.world.truth("follower"), self.world.truth("leader")
        est = inputs.leader
        self.scorer.tick(
            self.clock.now_s(),
            f.p_ned_m,
            f.v_ned_m_s,
            f.q_ned_body_wxyz,
            ld.p_ned_m,
            None if est is None or not est.usable else est.p_ned_rel_m,
        )

    # ------------------------------------------------------------------ the loop
    async def run(self) -> RunResult:
        sc = self.scenario
        frame_period_s = 1.0 / sc.run.camera_rate_hz
        truth_period_s = 1.0 / TRUTH_RATE_HZ
        end_s = sc.run.duration_s
        wall0 = time.perf_counter()
        self.core.request_start()
        with ExitStack() as stack:
            if self.recorder is not None:
                stack.enter_context(self.recorder)
            if self.autolabel is not None:
                stack.enter_context(self.autolabel)
            await self._loop(end_s, frame_period_s, truth_period_s)
        extra = self.scorer.extra()
        if self.autolabel is not None:
            extra["auto_label"] = self.autolabel.summary()
        extra.update(
            {
                "harness": "lockstep",
                "camera_timing": self.camera_timing.summary(),
                "detector_compute_ms": _percentiles(self._compute_ms),
                "control_tick_ages_ms": self.observer.timing(),
                "camera_rate_hz": sc.run.camera_rate_hz,
                "link": {
                    "setpoints_sent": self.link.counters.setpoints_sent,
                    "commands_sent": self.link.counters.commands_sent,
                    "command_retries": self.link.counters.command_retries,
                    "guard_trips": self.link.counters.guard_trips,
                },
                "run_wall_s": round(time.perf_counter() - wall0, 2),
            }
        )
        return RunResult(self.scorer.freeze(), self.scorer.snapshots, extra, self.observer)

    async def _loop(self, end_s: float, frame_period_s: float, truth_period_s: float) -> None:
        world = self.world
        next_frame_s = 0.0
        next_truth_s = 0.0
        next_progress_s = 0.0
        async with asyncio.TaskGroup() as tg:
            mission = tg.create_task(self.core.run(), name="lockstep.mission")
            while world.t_s < end_s - 1e-9 and not mission.done():
                world.step()
                t_s = world.t_s
                self.clock.set(t_s)
                self.link.pump()
                self.core.feed_telemetry()
                if self.autolabel is not None or self._share_period_s is not None:
                    self._share_leader(t_s)
                if t_s >= next_frame_s - 1e-9:
                    next_frame_s += frame_period_s
                    if self.link.snapshot().armed or self._in_flight:
                        self._capture(t_s)
                while self._in_flight and self._in_flight[0].due_s <= t_s + 1e-9:
                    self._deliver(self._in_flight.popleft())
                if t_s >= next_truth_s - 1e-9:
                    next_truth_s += truth_period_s
                    f = world.truth("follower")
                    self.scorer.truth(
                        t_s, f.p_ned_m, f.v_ned_m_s, f.q_ned_body_wxyz, world.truth("leader").p_ned_m
                    )
                if self.options.progress is not None and t_s >= next_progress_s:
                    next_progress_s += 5.0
                    self.options.progress(t_s)
                await asyncio.sleep(0)  # the runner and its command executor run here
            mission.cancel()

    def _share_leader(self, t_s: float) -> None:
        """The leader's own EKF estimate, moved into the follower's local frame, as MQTT would share it.

        To the auto-labeller when it checks labels; to the mission at ``LEADER_SHARE_HZ`` when the config
        takes the leader's shared position (``leader.shared_position``), as the real path's broker brings it.
        """
        label_due = self.autolabel is not None and self.autolabel.share.due(t_s)
        mission_due = self._share_period_s is not None and t_s >= self._next_share_s - 1e-9
        if not (label_due or mission_due):
            return
        ap = self.world.autopilot("leader")
        est = ap.est
        off_l = self.world.origin_offset_ned_m("leader")
        off_f = self.world.origin_offset_ned_m("follower")
        p = (
            float(est.n_m + off_l[0] - off_f[0]),
            float(est.e_m + off_l[1] - off_f[1]),
            float(est.d_m + off_l[2] - off_f[2]),
        )
        if label_due and self.autolabel is not None:
            self.autolabel.share.sample(t_s, p, bool(est.global_valid))
        if mission_due and self._share_period_s is not None:
            self._next_share_s = t_s + self._share_period_s
            if est.global_valid:
                v = (float(est.vn_m_s), float(est.ve_m_s), float(est.vd_m_s))
                self.core.submit_leader_shared(
                    SharedLeaderPosition(t_s, p, yaw_rad=ap.yaw_est_rad(), v_ned_m_s=v)
                )

    def _capture(self, t_s: float) -> None:
        due_s = self.camera_timing.due_s(t_s)
        if due_s is None:
            return
        follower = self.world.truth("follower")
        leader = None if self.scenario.run.leader_hidden(t_s) else self.world.truth("leader")
        frame = self.renderer.render(follower, leader, t_s)
        c0 = time.perf_counter()
        result = self.stage.detect(frame)
        self._in_flight.append(_InFlight(due_s, frame, result, 0.0))
        self._in_flight[-1].compute_ms = (time.perf_counter() - c0) * 1e3

    def _deliver(self, item: _InFlight) -> None:
        c0 = time.perf_counter()
        track = self.core.on_frame(item.frame, item.result)
        process_ms = (time.perf_counter() - c0) * 1e3
        compute_ms = item.compute_ms + process_ms
        self._compute_ms.append(compute_ms)
        self.observer.on_frame(item.frame, item.result, track, process_ms)
        if self.autolabel is not None:
            self.autolabel.on_frame(
                self.clock.now_s(), item.frame, self.link.snapshot(), self.pipeline.attitude
            )
        est = track.leader_estimate()
        stamp_s = item.frame.stamp_s
        self.scorer.frame(
            stamp_s,
            item.frame.truth,
            item.result.detections,
            est.p_ned_rel_m if est is not None and est.usable else None,
            latency_ms=compute_ms,
            rgb=item.frame.rgb if self.scorer.wants_snapshot(stamp_s) else None,
        )


def _percentiles(values: list[float]) -> dict[str, float | None]:
    if not values:
        return {"p50": None, "p95": None, "p99": None}
    p50, p95, p99 = np.percentile(np.asarray(values), [50, 95, 99])
    return {"p50": round(float(p50), 2), "p95": round(float(p95), 2), "p99": round(float(p99), 2)}
