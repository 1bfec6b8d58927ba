"""The lockstep closed loop: the simulator, the cameras and the service's flights on one clock, no sockets.

Fast and repeatable (Monte Carlo): a :class:`sitl.world.lockstep.World` steps the physics and the PX4-like
autopilots; for each of N followers an in-process :class:`sitl.render.renderer.Renderer` draws its camera,
and the *same* detector and the service's own :class:`~companion.service.flight.FlightService` (pose,
tracker, mission machine and runner) fly it through a
:class:`~companion.vehicle.message_link.MessageVehicleLink` that speaks MAVLink messages to
``world.link(name)``. Everything runs on sim time (a :class:`ManualClock` set from the world).
:class:`LockstepFlight` is that loop for any number of followers; :class:`LockstepRun` is the lone follower
(N = 1) with its report figures, and :mod:`companion.lab.formation.run` the formation.

What differs from the real path (``companion sim`` over UDP with MAVSDK) and why:

* Compute is instantaneous in sim time, so the camera pipeline's timing is modelled (the scenario's
  ``[timing]``, :mod:`companion.lab.evaluation.camera_timing`): by default a frame captured at ``t`` reaches
  the tracker and the mission at ``t + 60 ms`` (the D435i's own latency plus detection); jitter, dropped
  frames and a loaded detector are drawn from the run's seed. The real path measures its own. MAVLink
  latency and jitter (telemetry and setpoints) come from the scenario's ``[vehicles.follower.link]``.
* The camera renders only once the follower is armed (nothing before takeoff reaches the mission).
* Shares (:mod:`companion.lab.evaluation.shares`): every vehicle's own estimate as MQTT would bring it, at
  ``LEADER_SHARE_HZ``, to the followers that take them (``leader.shared_position = "mqtt"``, or a formation).

Truth reaches only the :class:`~companion.lab.evaluation.scoring.RunScorer`.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections import deque
from collections.abc import Callable, Sequence
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion.config import Config
from companion.kernel.camera import RgbdFrame
from companion.kernel.clock import ManualClock
from companion.kernel.flight import Vec3T
from companion.lab.evaluation.autolabel_check import AutoLabelCheck
from companion.lab.evaluation.camera_timing import CameraTiming
from companion.lab.evaluation.log import FlightLog
from companion.lab.evaluation.plots import Snapshot
from companion.lab.evaluation.runlog import attach_run_log
from companion.lab.evaluation.scoring import RunScorer
from companion.lab.evaluation.shares import Share, ShareBus
from companion.lab.evaluation.trace import RunObserver
from companion.mission.types import (
    MissionInputs,
    SharedLeaderPosition,
    SharedNeighbour,
    StepOutput,
    Transition,
)
from companion.perception.autolabel import AutoLabelConfig
from companion.perception.types import DetectorResult, DetectStage
from companion.service.flight import Callbacks, FlightService
from companion.vehicle.external_vision import ev_position_bits_for
from companion.vehicle.message_link import MessageVehicleLink
from sitl.render.faults import DepthGlitches, offset_leader_depth

log = logging.getLogger(__name__)

#: Truth samples for crash and landing detection, per sim second.
TRUTH_RATE_HZ = 50.0
#: How often the leader's companion shares its position, Hz (both harnesses; the service's default share
#: limits take 2 s of age).
LEADER_SHARE_HZ = 10.0
#: How late a share arrives (MQTT between two companions), s.
LEADER_SHARE_LATENCY_S = 0.1


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
class InFlight:
    """A frame whose estimate reaches the mission at ``due_s``; ``compute_ms``: the detector's wall time."""

    due_s: float
    frame: RgbdFrame
    result: DetectorResult
    compute_ms: float


#: Extra scoring of each delivered frame: the frame and the mission's estimate (NED relative, m; None).
FrameHook = Callable[[InFlight, Any], None]


@dataclass(slots=True)
class LockstepFollower:
    """One follower in the loop: its link and flight, its camera and detector, its scorers."""

    name: str
    cfg: Config
    link: MessageVehicleLink
    flight: FlightService
    stage: DetectStage
    renderer: Any
    scorer: RunScorer
    #: When each frame's estimate reaches this follower's mission (the scenario's ``[timing]``).
    camera_timing: CameraTiming
    observer: RunObserver
    #: Takes the vehicles' shares (the leader's position; a formation's neighbours).
    takes_shares: bool
    in_flight: deque[InFlight] = field(default_factory=deque)
    compute_ms: list[float] = field(default_factory=list)
    frame_hooks: list[FrameHook] = field(default_factory=list)
    autolabel: AutoLabelCheck | None = None
    #: The scenario's depth glitches on this follower's camera (sitl/render/faults.py).
    glitches: DepthGlitches = field(default_factory=lambda: DepthGlitches(()))


def lockstep_follower(
    world: Any,
    clock: ManualClock,
    name: str,
    cfg: Config,
    *,
    stage: DetectStage,
    renderer: Any,
    scorer: RunScorer,
    stream: int = 0,
) -> LockstepFollower:
    """Follower ``name`` of ``world``: its link, its flight (scored on every step) and camera timing.

    ``stream``: the follower's index, so each draws its own camera timing from the run's seed.
    """
    link = MessageVehicleLink(
        world.link(name),
        clock,
        cfg.link,
        world.vehicle(name).sysid,
        ev_position_bits=ev_position_bits_for(cfg.mission.gps_loss_policy),
    )
    flight = FlightService(cfg, link, clock, stage)
    observer = RunObserver(clock, [])

    def on_transition(tr: Transition) -> None:
        scorer.transition(tr.stamp_s, tr.from_state.name, tr.to_state.name, tr.reason.name)

    def on_step(inputs: MissionInputs, out: StepOutput) -> None:
        observer.on_step(inputs, out)
        f, ld = world.truth(name), world.truth("leader")
        est = inputs.leader
        seen = observer.ticks[-1]
        scorer.tick(
            clock.now_s(),
            f.p_ned_m,
            f.v_ned_m_s,
            f.q_ned_body_wxyz,
            ld.p_ned_m,
            None if est is None or not est.usable else est.p_ned_rel_m,
            yaw_service_rad=seen.yaw_service_rad,
            v_cmd_ned_m_s=seen.v_cmd_ned_m_s,
        )

    flight.observers.append(Callbacks(step=on_step, transition=on_transition))
    takes_shares = cfg.leader.shared_position == "mqtt" or cfg.formation.slot_leader_m is not None
    timing = CameraTiming(world.scenario.timing, world.seed, stream=stream)
    glitches = DepthGlitches(world.scenario.faults(name).camera.glitches())
    return LockstepFollower(
        name, cfg, link, flight, stage, renderer, scorer, timing, observer, takes_shares, glitches=glitches
    )


class LockstepFlight:
    """The leader and N followers stepped on one clock until the scenario ends or every mission is over.

    Per physics step, in this order: the world; each follower's link and telemetry; the shares; the cameras
    (each follower's frame is detected at capture and delivered when its timing says); truth to the
    scorers (``TRUTH_RATE_HZ``); the hooks added with :meth:`every`. Then the flights' tasks run.
    """

    def __init__(
        self,
        world: Any,
        clock: ManualClock,
        followers: Sequence[LockstepFollower],
        *,
        shares: ShareBus | None,
        progress: Callable[[float], None] | None = None,
    ) -> None:
        self.world = world
        self.clock = clock
        self.followers = list(followers)
        self.shares = shares
        self.progress = progress
        self.names = [v.name for v in world.vehicles]
        self._others = {
            f.name: [n for n in self.names if n not in (f.name, "leader")] for f in self.followers
        }
        self._every: list[tuple[float, Callable[[float], None]]] = []

    def every(self, period_s: float, hook: Callable[[float], None]) -> None:
        """Call ``hook(t_s)`` every ``period_s`` of sim time, after truth (formation figures)."""
        self._every.append((period_s, hook))

    async def fly(self, end_s: float) -> None:
        world = self.world
        sc = world.scenario
        frame_period_s = 1.0 / sc.run.camera_rate_hz
        truth_period_s = 1.0 / TRUTH_RATE_HZ
        next_frame_s = next_truth_s = next_progress_s = 0.0
        next_hook_s = [0.0] * len(self._every)
        followers = self.followers
        for f in followers:
            f.flight.request_start()
        async with asyncio.TaskGroup() as tg:
            missions = [tg.create_task(f.flight.run(), name=f"lockstep.{f.name}.mission") for f in followers]
            while world.t_s < end_s - 1e-9 and not all(m.done() for m in missions):
                world.step()
                t_s = world.t_s
                self.clock.set(t_s)
                for f in followers:
                    f.link.pump()
                    f.flight.feed_telemetry()
                self._share(t_s)
                if t_s >= next_frame_s - 1e-9:
                    next_frame_s += frame_period_s
                    for f in followers:
                        if f.link.snapshot().armed or f.in_flight:
                            self._capture(f, t_s)
                for f in followers:
                    while f.in_flight and f.in_flight[0].due_s <= t_s + 1e-9:
                        self._deliver(f, f.in_flight.popleft())
                if t_s >= next_truth_s - 1e-9:
                    next_truth_s += truth_period_s
                    leader_p = world.truth("leader").p_ned_m
                    for f in followers:
                        tr = world.truth(f.name)
                        f.scorer.truth(t_s, tr.p_ned_m, tr.v_ned_m_s, tr.q_ned_body_wxyz, leader_p)
                for k, (period_s, hook) in enumerate(self._every):
                    if t_s >= next_hook_s[k] - 1e-9:
                        next_hook_s[k] += period_s
                        hook(t_s)
                if self.progress is not None and t_s >= next_progress_s:
                    next_progress_s += 5.0
                    self.progress(t_s)
                await asyncio.sleep(0)  # the runners and their command executors run here
            for m in missions:
                m.cancel()

    # ------------------------------------------------------------------ shares
    def _local(self, p_world_ned_m: Vec3T, name: str) -> Vec3T:
        off = self.world.origin_offset_ned_m(name)
        return (p_world_ned_m[0] - off[0], p_world_ned_m[1] - off[1], p_world_ned_m[2] - off[2])

    def _share(self, t_s: float) -> None:
        """Each vehicle's own estimate, as MQTT would share it, to the followers that take shares.

        The auto-labeller's check samples the leader's estimate on its own schedule.
        """
        for f in self.followers:
            if f.autolabel is not None and f.autolabel.share.due(t_s):
                own = self.world.autopilot("leader").own_estimate()
                p = self._local(self._world_estimate("leader"), f.name)
                f.autolabel.share.sample(t_s, p, own.global_valid)
        bus = self.shares
        if bus is None:
            return
        if bus.due(t_s):
            shares = []
            for v in self.world.vehicles:
                own = v.autopilot.own_estimate()
                if not own.global_valid:
                    continue
                vn, ve, vd = own.v_ned_m_s
                v_ned = (float(vn), float(ve), float(vd))
                yaw = float(own.yaw_rad)
                shares.append(
                    Share(v.name, t_s, self._world_estimate(v.name), v_ned, yaw, float(v.dyn.r_rad_s))
                )
            bus.publish(t_s, shares)
        for s in bus.arrived(t_s):
            for f in self.followers:
                if s.name == f.name or not f.takes_shares:
                    continue
                p = self._local(s.p_world_ned_m, f.name)
                if s.name == "leader":
                    f.flight.submit_leader_shared(
                        SharedLeaderPosition(
                            s.t_s,
                            p,
                            yaw_rad=s.yaw_rad,
                            v_ned_m_s=s.v_ned_m_s,
                            yaw_rate_rad_s=s.yaw_rate_rad_s,
                        )
                    )
                else:
                    f.flight.submit_neighbour(SharedNeighbour(s.name, s.t_s, p, s.v_ned_m_s))

    def _world_estimate(self, name: str) -> Vec3T:
        """Vehicle ``name``'s own position estimate in the shared world frame (NED from home), m."""
        n, e, d = self.world.autopilot(name).own_estimate().p_local_ned_m
        off = self.world.origin_offset_ned_m(name)
        return (float(n + off[0]), float(e + off[1]), float(d + off[2]))

    # ------------------------------------------------------------------ cameras
    def _capture(self, f: LockstepFollower, t_s: float) -> None:
        due_s = f.camera_timing.due_s(t_s)
        if due_s is None:
            return
        world = self.world
        leader = None if world.scenario.run.leader_hidden(t_s) else world.truth("leader")
        others = [world.truth(n) for n in self._others[f.name]]
        frame = f.renderer.render(world.truth(f.name), leader, t_s, others=others)
        if dz := f.glitches.take(t_s):
            frame = offset_leader_depth(frame, dz)
        c0 = time.perf_counter()
        result = f.stage.detect(frame)
        f.in_flight.append(InFlight(due_s, frame, result, (time.perf_counter() - c0) * 1e3))

    def _deliver(self, f: LockstepFollower, item: InFlight) -> None:
        c0 = time.perf_counter()
        track = f.flight.on_frame(item.frame, item.result)
        process_ms = (time.perf_counter() - c0) * 1e3
        compute_ms = item.compute_ms + process_ms
        f.compute_ms.append(compute_ms)
        f.observer.on_frame(item.frame, item.result, track, process_ms)
        if f.autolabel is not None:
            f.autolabel.on_frame(self.clock.now_s(), item.frame, f.link.snapshot(), f.flight.attitude)
        est = track.leader_estimate()
        p_est = est.p_ned_rel_m if est is not None and est.usable else None
        for hook in f.frame_hooks:
            hook(item, p_est)
        stamp_s = item.frame.stamp_s
        f.scorer.frame(
            stamp_s,
            item.frame.truth,
            item.result.detections,
            p_est,
            latency_ms=compute_ms,
            rgb=item.frame.rgb if f.scorer.wants_snapshot(stamp_s) else None,
            range_meas_m=f.observer.frames[-1].range_meas_m,
        )


class LockstepRun:
    """One scenario flown in lockstep by its lone follower. ``await run()`` returns the :class:`RunResult`.

    Args:
        world: the simulation (``sitl.world.lockstep.World``) with the scenario loaded; nothing stepped yet.
        renderer: an entered ``sitl.render.renderer.Renderer`` for the follower's camera.
        cfg: the service config the flight is built from (the scenario's overrides applied).
        stage: the detection step (the detector on one frame, and its feedback from the tracker).
        options: harness knobs.
    """

    def __init__(
        self, world: Any, renderer: Any, cfg: Config, stage: DetectStage, options: LockstepOptions
    ) -> None:
        self.world = world
        self.options = options
        sc = world.scenario
        self.scenario = sc
        self.clock = ManualClock(world.t_s)
        scorer = RunScorer.for_scenario(sc, options.snapshots)
        self.follower = f = lockstep_follower(
            world, self.clock, "follower", cfg, stage=stage, renderer=renderer, scorer=scorer
        )
        self.recorder = None
        if options.mcap_path is not None:
            meta = {"scenario": str(sc.name), "harness": "lockstep"}
            self.recorder = attach_run_log(
                cfg, f.flight, self.clock, options.mcap_path, synchronous=True, metadata=meta
            )
        if options.auto_label:
            f.autolabel = AutoLabelCheck(
                options.auto_label_dir,
                AutoLabelConfig(leader_span_m=cfg.leader.span_m),
                f.flight.camera,
                options.auto_label_sequence,
                options.truth_label_dir,
            )
        shares = ShareBus(LEADER_SHARE_HZ, LEADER_SHARE_LATENCY_S) if f.takes_shares else None
        self.flight = LockstepFlight(world, self.clock, [f], shares=shares, progress=options.progress)

    async def run(self) -> RunResult:
        sc = self.scenario
        f = self.follower
        wall0 = time.perf_counter()
        with ExitStack() as stack:
            if self.recorder is not None:
                stack.enter_context(self.recorder)
            if f.autolabel is not None:
                stack.enter_context(f.autolabel)
            await self.flight.fly(sc.run.duration_s)
        extra = f.scorer.extra()
        if f.autolabel is not None:
            extra["auto_label"] = f.autolabel.summary()
        counters = f.link.counters
        extra.update(
            {
                "harness": "lockstep",
                "camera_timing": f.camera_timing.summary(),
                "detector_compute_ms": _percentiles(f.compute_ms),
                "control_tick_ages_ms": f.observer.timing(),
                "ticks_led_on_leader_share": f.observer.ticks_led_on_share,
                "ticks_coasted_on_leader_share": f.observer.ticks_coasted_on_share,
                "camera_rate_hz": sc.run.camera_rate_hz,
                "link": {
                    "setpoints_sent": counters.setpoints_sent,
                    "commands_sent": counters.commands_sent,
                    "command_retries": counters.command_retries,
                    "guard_trips": counters.guard_trips,
                },
                "run_wall_s": round(time.perf_counter() - wall0, 2),
            }
        )
        return RunResult(f.scorer.freeze(), f.scorer.snapshots, extra, f.observer)


def _percentiles(values: list[float]) -> dict[str, float | None]:
    if not values:
        return {"p50": None, "p95": None, "p99": None}
    p50, p95, p99 = np.percentile(np.asarray(values), [50, 95, 99])
    return {"p50": round(float(p50), 2), "p95": round(float(p95), 2), "p99": round(float(p99), 2)}
