"""One leader and N followers in lockstep: one simulator, one camera and one flight per follower.

Each follower runs the service's own :class:`~companion.service.flight.FlightService` (its config from the
formation plan: its slot, the neighbours' slots), its own detector stage and a camera that renders every
other vehicle with the leader's airframe, in the one lockstep loop
(:class:`~companion.lab.evaluation.lockstep.LockstepFlight`). The vehicles share their own estimates as MQTT
would (:mod:`companion.lab.evaluation.shares`): the leader's position, velocity and heading, and each
follower's position to the others, while each one's GPS is good. Truth reaches only the scorers.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from companion.config import Config
from companion.kernel.clock import ManualClock
from companion.kernel.flight import Vec3T
from companion.lab.evaluation.lockstep import (
    TRUTH_RATE_HZ,
    LockstepFlight,
    LockstepFollower,
    lockstep_follower,
)
from companion.lab.evaluation.runlog import recorder_for, run_sink
from companion.lab.evaluation.scoring import RunScorer
from companion.lab.evaluation.shares import ShareBus
from companion.lab.formation.score import FollowerScore
from companion.mission.types import MissionState
from companion.perception.types import DetectStage
from companion.service.flight import FlightService
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
class FollowerRun:
    """One follower of the formation: its place in the lockstep loop and its formation figures."""

    lockstep: LockstepFollower
    score: FollowerScore

    @property
    def name(self) -> str:
        return self.lockstep.name

    @property
    def flight(self) -> FlightService:
        return self.lockstep.flight

    @property
    def scorer(self) -> RunScorer:
        return self.lockstep.scorer

    @property
    def compute_ms(self) -> list[float]:
        return self.lockstep.compute_ms


@dataclass(slots=True)
class FormationResult:
    """The followers (their flights and scorers) and the formation's truth track."""

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
        self.followers: list[FollowerRun] = []
        for i, (name, cfg, stage, renderer) in enumerate(followers):
            self.followers.append(self._follower(i, name, cfg, stage, renderer))
        self.names = [v.name for v in world.vehicles]
        self._t_log: list[float] = []
        self._p_log: dict[str, list[Vec3T]] = {n: [] for n in self.names}
        self._yaw_log: list[float] = []
        self.loop = LockstepFlight(
            world,
            self.clock,
            [f.lockstep for f in self.followers],
            shares=ShareBus(options.share_rate_hz, options.share_latency_s),
            progress=options.progress,
        )
        self.loop.every(1.0 / TRUTH_RATE_HZ, self._truth)
        self.loop.every(1.0 / SLOT_RATE_HZ, self._slot)
        self.recorders = [] if options.mcap_path is None else self._recorders(options.mcap_path)

    def _recorders(self, path: Path) -> list[FlightRecorder]:
        """One recorder per follower, all writing one file, each placed in the shared world by its origin."""
        recorders = []
        for f in self.followers:
            o = self.world.origin_offset_ned_m(f.name)
            ns = Namespace(f.name, (float(o[0]), float(o[1]), float(o[2])))
            recorders.append(
                recorder_for(f.lockstep.cfg, f.flight, self.clock, synchronous=True, namespace=ns)
            )
        meta = {"scenario": str(self.scenario.name), "harness": "lockstep", "followers": ",".join(self.names)}
        sink = run_sink(path, [t for r in recorders for t in r.topics], meta)
        if sink is None:
            for f, r in zip(self.followers, recorders, strict=True):
                f.flight.observers.remove(r)
            return []
        for r in recorders:
            r.add_log(sink)
        return recorders

    def _follower(self, i: int, name: str, cfg: Config, stage: DetectStage, renderer: Any) -> FollowerRun:
        slot = cfg.formation.slot_leader_m
        if slot is None:
            raise ValueError(f"{name}: the config has no formation slot (formation.plan)")
        scorer = RunScorer.for_scenario(self.scenario, 0, vehicle=name)
        lf = lockstep_follower(
            self.world, self.clock, name, cfg, stage=stage, renderer=renderer, scorer=scorer, stream=i
        )
        run = FollowerRun(lf, FollowerScore(name, slot))
        lf.frame_hooks.append(lambda item, p_est: self._frame(run, p_est))
        return run

    async def run(self) -> FormationResult:
        wall0 = time.perf_counter()
        with ExitStack() as stack:
            for r in self.recorders:
                stack.enter_context(r)
            await self.loop.fly(self.scenario.run.duration_s)
        return FormationResult(
            self.followers, self._t_log, self._p_log, self._yaw_log, time.perf_counter() - wall0
        )

    # ------------------------------------------------------------------ formation figures
    def _frame(self, f: FollowerRun, p_est: Any) -> None:
        """Which vehicle the follower's estimate is on (truth, for the score only)."""
        me = np.asarray(self.world.truth(f.name).p_ned_m)
        true_rel = {n: np.asarray(self.world.truth(n).p_ned_m) - me for n in self.names if n != f.name}
        f.score.frame(None if p_est is None else np.asarray(p_est), true_rel)

    def _truth(self, t_s: float) -> None:
        truths = {n: self.world.truth(n) for n in self.names}
        self._t_log.append(t_s)
        self._yaw_log.append(float(self.world.vehicle("leader").dyn.yaw_rad))
        for n, tr in truths.items():
            self._p_log[n].append((float(tr.p_ned_m[0]), float(tr.p_ned_m[1]), float(tr.p_ned_m[2])))
        for f in self.followers:
            p = np.asarray(truths[f.name].p_ned_m)
            for n, other in truths.items():
                if n != f.name:
                    f.score.separation(float(np.linalg.norm(np.asarray(other.p_ned_m) - p)), n)

    def _slot(self, t_s: float) -> None:
        leader = self.world.vehicle("leader")
        p_leader = self.world.truth("leader").p_ned_m
        for f in self.followers:
            if f.flight.state in FORMATION_STATES and f.scorer.in_window(t_s):
                f.score.slot_sample(
                    t_s, self.world.truth(f.name).p_ned_m, p_leader, float(leader.dyn.yaw_rad)
                )


__all__ = ["FollowerRun", "FormationOptions", "FormationResult", "FormationRun"]
