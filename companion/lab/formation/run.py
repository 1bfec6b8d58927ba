"""One leader and N followers in lockstep: one simulator, one camera and one service core per follower.

Each follower runs the service's own :class:`~companion.service.flight_core.FlightCore` (its config from the
formation plan: its slot, the neighbours' slots), its own detector stage and a camera that renders every
other vehicle with the leader's airframe. The vehicles share their own estimates as MQTT would
(:mod:`companion.lab.formation.shares`): the leader's position, velocity and heading, and each follower's
position to the others, while each one's GPS is good. Truth reaches only the scorers.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion.config import Config
from companion.kernel.camera import RgbdFrame
from companion.kernel.clock import ManualClock
from companion.kernel.flight import Vec3T
from companion.lab.evaluation.camera_timing import CameraTiming
from companion.lab.evaluation.lockstep import TRUTH_RATE_HZ
from companion.lab.evaluation.runlog import recorder_for, run_sink
from companion.lab.evaluation.scoring import RunScorer
from companion.lab.formation.score import FollowerScore
from companion.lab.formation.shares import Share, ShareBus
from companion.mission.types import (
    MissionInputs,
    MissionState,
    SharedLeaderPosition,
    SharedNeighbour,
    StepOutput,
    Transition,
)
from companion.perception.types import DetectorResult, DetectStage
from companion.service.flight_core import FlightCore
from companion.vehicle.external_vision import ev_position_bits_for
from companion.vehicle.message_link import MessageVehicleLink
from companion.viz.messages import Namespace
from companion.viz.recorder import FlightRecorder

#: Slot deviation is sampled this often, per sim second.
SLOT_RATE_HZ = 10.0
FORMATION_STATES = frozenset({MissionState.FOLLOW, MissionState.FOLLOW_VISION})


@dataclass(frozen=True, slots=True)
class FormationOptions:
    """The harness's knobs: the shares' rate and latency (the camera's timing is the scenario's)."""

    share_rate_hz: float = 10.0
    share_latency_s: float = 0.1
    progress: Callable[[float], None] | None = None
    #: The run's MCAP log, every follower under its vehicle id (:mod:`companion.lab.evaluation.runlog`).
    mcap_path: Path | None = None


@dataclass(slots=True)
class _InFlight:
    due_s: float
    frame: RgbdFrame
    result: DetectorResult


@dataclass(slots=True)
class FollowerRun:
    """One follower: its service core and link, its camera, its scorers."""

    name: str
    cfg: Config
    link: MessageVehicleLink
    core: FlightCore
    stage: DetectStage
    renderer: Any
    scorer: RunScorer
    score: FollowerScore
    #: When each frame's estimate reaches this follower's mission (the scenario's ``[timing]``).
    camera_timing: CameraTiming
    in_flight: deque[_InFlight] = field(default_factory=deque)
    compute_ms: list[float] = field(default_factory=list)


@dataclass(slots=True)
class FormationResult:
    """The followers (their cores and scorers) and the formation's truth track."""

    followers: list[FollowerRun]
    #: Sim time, s, and every vehicle's true world NED position, m (for the plot from above).
    t_s: list[float]
    p_ned_m: dict[str, list[Vec3T]]
    #: The leader's true heading at the same instants, rad.
    leader_yaw_rad: list[float]
    wall_s: float


class FormationRun:
    """The formation flown in lockstep; ``await run()``.

    Args:
        world: ``sitl.world.lockstep.World`` with the leader and the followers (named as in the plan).
        followers: ``(name, cfg, stage, renderer)`` per follower; ``cfg`` flies that follower's slot.
    """

    def __init__(
        self,
        world: Any,
        followers: list[tuple[str, Config, DetectStage, Any]],
        options: FormationOptions,
    ) -> None:
        self.world = world
        self.scenario = world.scenario
        self.options = options
        self.clock = ManualClock(world.t_s)
        self.bus = ShareBus(options.share_rate_hz, options.share_latency_s)
        self.followers: list[FollowerRun] = []
        for name, cfg, stage, renderer in followers:
            self.followers.append(self._follower(name, cfg, stage, renderer))
        self.names = [v.name for v in world.vehicles]
        self._yaw_log: list[float] = []
        self.recorders = [] if options.mcap_path is None else self._recorders(options.mcap_path)

    def _recorders(self, path: Path) -> list[FlightRecorder]:
        """One recorder per follower, all writing one file, each placed in the shared world by its origin."""
        recorders = []
        for f in self.followers:
            o = self.world.origin_offset_ned_m(f.name)
            ns = Namespace(f.name, (float(o[0]), float(o[1]), float(o[2])))
            recorders.append(recorder_for(f.cfg, f.core, self.clock, synchronous=True, namespace=ns))
        meta = {"scenario": str(self.scenario.name), "harness": "lockstep", "followers": ",".join(self.names)}
        sink = run_sink(path, [t for r in recorders for t in r.topics], meta)
        if sink is None:
            for f, r in zip(self.followers, recorders, strict=True):
                f.core.observers.remove(r)
            return []
        for r in recorders:
            r.add_log(sink)
        return recorders

    def _follower(self, name: str, cfg: Config, stage: DetectStage, renderer: Any) -> FollowerRun:
        veh = self.world.vehicle(name)
        link = MessageVehicleLink(
            self.world.link(name),
            self.clock,
            cfg.link,
            veh.sysid,
            ev_position_bits=ev_position_bits_for(cfg.mission.gps_loss_policy),
        )
        scorer = RunScorer.for_scenario(self.scenario, 0, vehicle=name)
        slot = cfg.formation.slot_leader_m
        if slot is None:
            raise ValueError(f"{name}: the config has no formation slot (formation.plan)")
        score = FollowerScore(name, slot)

        def on_transition(tr: Transition) -> None:
            scorer.transition(tr.stamp_s, tr.from_state.name, tr.to_state.name, tr.reason.name)

        def on_step(inputs: MissionInputs, out: StepOutput) -> None:
            f, ld = self.world.truth(name), self.world.truth("leader")
            est = inputs.leader
            scorer.tick(
                self.clock.now_s(),
                f.p_ned_m,
                f.v_ned_m_s,
                f.q_ned_body_wxyz,
                ld.p_ned_m,
                None if est is None or not est.usable else est.p_ned_rel_m,
            )

        core = FlightCore(cfg, link, self.clock, stage, on_transition=on_transition, on_step=on_step)
        timing = CameraTiming(self.scenario.timing, self.world.seed, stream=len(self.followers))
        return FollowerRun(name, cfg, link, core, stage, renderer, scorer, score, timing)

    async def run(self) -> FormationResult:
        wall0 = time.perf_counter()
        for f in self.followers:
            f.core.request_start()
        t_log: list[float] = []
        p_log: dict[str, list[Vec3T]] = {n: [] for n in self.names}
        with contextlib.ExitStack() as stack:
            for r in self.recorders:
                stack.enter_context(r)
            await self._fly(t_log, p_log)
        return FormationResult(self.followers, t_log, p_log, self._yaw_log, time.perf_counter() - wall0)

    async def _fly(self, t_log: list[float], p_log: dict[str, list[Vec3T]]) -> None:
        sc = self.scenario
        frame_period_s = 1.0 / sc.run.camera_rate_hz
        truth_period_s = 1.0 / TRUTH_RATE_HZ
        slot_period_s = 1.0 / SLOT_RATE_HZ
        next_frame_s = next_truth_s = next_slot_s = next_progress_s = 0.0
        end_s = sc.run.duration_s
        world = self.world
        async with asyncio.TaskGroup() as tg:
            missions = [
                tg.create_task(f.core.run(), name=f"formation.{f.name}.mission") for f in self.followers
            ]
            while world.t_s < end_s - 1e-9 and not all(m.done() for m in missions):
                world.step()
                t_s = world.t_s
                self.clock.set(t_s)
                for f in self.followers:
                    f.link.pump()
                    f.core.feed_telemetry()
                self._share(t_s)
                if t_s >= next_frame_s - 1e-9:
                    next_frame_s += frame_period_s
                    for f in self.followers:
                        if f.link.snapshot().armed or f.in_flight:
                            self._capture(f, t_s)
                for f in self.followers:
                    while f.in_flight and f.in_flight[0].due_s <= t_s + 1e-9:
                        self._deliver(f, f.in_flight.popleft())
                if t_s >= next_truth_s - 1e-9:
                    next_truth_s += truth_period_s
                    self._truth(t_s, t_log, p_log)
                if t_s >= next_slot_s - 1e-9:
                    next_slot_s += slot_period_s
                    self._slot(t_s)
                if self.options.progress is not None and t_s >= next_progress_s:
                    next_progress_s += 5.0
                    self.options.progress(t_s)
                await asyncio.sleep(0)
            for m in missions:
                m.cancel()

    # ------------------------------------------------------------------ shares
    def _share(self, t_s: float) -> None:
        if self.bus.due(t_s):
            shares = []
            for v in self.world.vehicles:
                est = v.autopilot.est
                if not est.global_valid:
                    continue
                off = self.world.origin_offset_ned_m(v.name)
                shares.append(
                    Share(
                        v.name,
                        t_s,
                        (float(est.n_m + off[0]), float(est.e_m + off[1]), float(est.d_m + off[2])),
                        (float(est.vn_m_s), float(est.ve_m_s), float(est.vd_m_s)),
                        float(v.dyn.yaw_rad),
                        float(v.dyn.r_rad_s),
                    )
                )
            self.bus.publish(t_s, shares)
        for s in self.bus.arrived(t_s):
            for f in self.followers:
                if s.name == f.name:
                    continue
                off = self.world.origin_offset_ned_m(f.name)
                p = (s.p_world_ned_m[0] - off[0], s.p_world_ned_m[1] - off[1], s.p_world_ned_m[2] - off[2])
                if s.name == "leader":
                    f.core.submit_leader_shared(
                        SharedLeaderPosition(
                            s.t_s,
                            p,
                            yaw_rad=s.yaw_rad,
                            v_ned_m_s=s.v_ned_m_s,
                            yaw_rate_rad_s=s.yaw_rate_rad_s,
                        )
                    )
                else:
                    f.core.submit_neighbour(SharedNeighbour(s.name, s.t_s, p, s.v_ned_m_s))

    # ------------------------------------------------------------------ camera
    def _capture(self, f: FollowerRun, t_s: float) -> None:
        due_s = f.camera_timing.due_s(t_s)
        if due_s is None:
            return
        me = self.world.truth(f.name)
        hidden = self.scenario.run.leader_hidden(t_s)
        leader = None if hidden else self.world.truth("leader")
        others = [self.world.truth(n) for n in self.names if n not in (f.name, "leader")]
        frame = f.renderer.render(me, leader, t_s, others=others)
        c0 = time.perf_counter()
        result = f.stage.detect(frame)
        f.compute_ms.append((time.perf_counter() - c0) * 1e3)
        f.in_flight.append(_InFlight(due_s, frame, result))

    def _deliver(self, f: FollowerRun, item: _InFlight) -> None:
        track = f.core.on_frame(item.frame, item.result)
        est = track.leader_estimate()
        p_est = np.asarray(est.p_ned_rel_m) if est is not None and est.usable else None
        me = np.asarray(self.world.truth(f.name).p_ned_m)
        true_rel = {n: np.asarray(self.world.truth(n).p_ned_m) - me for n in self.names if n != f.name}
        f.score.frame(p_est, true_rel)
        f.scorer.frame(
            item.frame.stamp_s,
            item.frame.truth,
            item.result.detections,
            p_est,
            latency_ms=0.0,
            rgb=None,
        )

    # ------------------------------------------------------------------ truth
    def _truth(
        self, t_s: float, t_log: list[float], p_log: dict[str, list[tuple[float, float, float]]]
    ) -> None:
        truths = {n: self.world.truth(n) for n in self.names}
        leader_p = truths["leader"].p_ned_m
        t_log.append(t_s)
        self._yaw_log.append(float(self.world.vehicle("leader").dyn.yaw_rad))
        for n, tr in truths.items():
            p_log[n].append((float(tr.p_ned_m[0]), float(tr.p_ned_m[1]), float(tr.p_ned_m[2])))
        for f in self.followers:
            tr = truths[f.name]
            f.scorer.truth(t_s, tr.p_ned_m, tr.v_ned_m_s, tr.q_ned_body_wxyz, leader_p)
            p = np.asarray(tr.p_ned_m)
            for n, other in truths.items():
                if n != f.name:
                    f.score.separation(float(np.linalg.norm(np.asarray(other.p_ned_m) - p)), n)

    def _slot(self, t_s: float) -> None:
        leader = self.world.vehicle("leader")
        p_leader = self.world.truth("leader").p_ned_m
        for f in self.followers:
            if f.core.machine.state in FORMATION_STATES and f.scorer.in_window(t_s):
                f.score.slot_sample(
                    t_s, self.world.truth(f.name).p_ned_m, p_leader, float(leader.dyn.yaw_rad)
                )
