"""Scoring a closed-loop run against the simulator's truth: what both harnesses feed, one frozen log out.

Truth is used here and nowhere else: the service (or the lockstep cores) never sees a value from this module.
A harness calls :meth:`RunScorer.tick` each control step, :meth:`RunScorer.frame` for each camera frame once
perception has processed it, :meth:`RunScorer.truth` with the follower's true state (for crashes and
landings), and :meth:`RunScorer.transition` for each mission transition; :meth:`RunScorer.freeze` gives the
:class:`~companion.lab.evaluation.log.FlightLog` the metrics read.

Definitions (the report documents them):

* the **formation window** is the scenario's ``[run] formation_start_s .. + formation_duration_s``; a tick or
  frame counts as formation when it lies in the window *and* the mission is in FOLLOW or FOLLOW_VISION;
* a frame's leader is **visible** when the truth box exists and at least ``MIN_VISIBLE_FRACTION`` of the
  leader is in view (the dataset's labelling rule); a **detection** is a box with IoU >= 0.5 against it; a
  **false positive** is a box overlapping no visible leader (IoU < 0.1, or no leader in view).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from companion.kernel.camera import GroundTruth, RgbImage
from companion.lab.evaluation.log import FlightLog, FlightRecorder, Vec3T
from companion.lab.evaluation.metrics import FORMATION_STATES
from companion.lab.evaluation.obstacles import Envelopes
from companion.lab.evaluation.outcome import TruthMonitor
from companion.lab.evaluation.plots import Snapshot
from companion.perception.types import Detection

MIN_VISIBLE_FRACTION = 0.25
MIN_VISIBLE_PX = 12.0
DETECTED_IOU = 0.5
FALSE_POSITIVE_IOU = 0.1


def iou(a: Sequence[float], b: Sequence[float]) -> float:
    """Intersection over union of two boxes (x0, y0, x1, y1), pixels."""
    ix = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    iy = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = ix * iy
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return inter / union if union > 0 else 0.0


def leader_visible(truth: GroundTruth | None) -> bool:
    """Enough of the leader in view to count in recall (the dataset's labelling rule)."""
    if truth is None or truth.box_xyxy_px is None:
        return False
    x0, y0, x1, y1 = truth.box_xyxy_px
    return truth.visible_fraction >= MIN_VISIBLE_FRACTION and (x1 - x0) * (y1 - y0) >= MIN_VISIBLE_PX


def judge_detections(truth: GroundTruth | None, detections: Sequence[Detection]) -> tuple[bool, bool, bool]:
    """(leader visible, leader detected, a false positive) for one frame."""
    visible = leader_visible(truth)
    box = truth.box_xyxy_px if truth is not None else None
    detected = (
        visible and box is not None and any(iou(d.box_xyxy_px, box) >= DETECTED_IOU for d in detections)
    )
    false_positive = any(box is None or iou(d.box_xyxy_px, box) < FALSE_POSITIVE_IOU for d in detections)
    return visible, detected, false_positive


def _vec(v: ArrayLike) -> Vec3T:
    a = np.asarray(v, dtype=np.float64)
    return (float(a[0]), float(a[1]), float(a[2]))


def yaw_of(q_ned_body_wxyz: ArrayLike) -> float:
    """Heading of a body FRD -> NED quaternion, rad."""
    w, x, y, z = (float(c) for c in np.asarray(q_ned_body_wxyz, dtype=np.float64))
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


@dataclass(slots=True)
class RunScorer:
    """Collects one run against the truth (see the module docstring).

    Args:
        window_s: the formation window (start, end), sim s.
        gps_outages_s: the follower's GPS outages as (start, end or None for good), sim s.
        snapshot_times_s: sim times at which to keep a camera frame for the report's strip.
    """

    window_s: tuple[float, float]
    gps_outages_s: Sequence[tuple[float, float | None]] = ()
    snapshot_times_s: Sequence[float] = ()
    recorder: FlightRecorder = field(default_factory=FlightRecorder)
    monitor: TruthMonitor = field(default_factory=TruthMonitor)
    snapshots: list[Snapshot] = field(default_factory=list)
    state: str = "WAIT_LINK"
    frames_seen: int = 0
    _next_snapshot: int = 0

    @classmethod
    def for_scenario(cls, scenario: Any, snapshots: int = 0, vehicle: str = "follower") -> RunScorer:
        """The scorer of a ``sitl.world.scenario.Scenario`` for the follower named ``vehicle``.

        Its formation window, the follower's GPS outages, ``snapshots`` evenly spaced camera frames, and
        its scene's structures for the crash check.
        """
        from sitl.render.config import visual_from_mapping  # noqa: PLC0415 (pydantic only; sitl at eval)
        from sitl.render.structures import solid_structures  # noqa: PLC0415

        run = scenario.run
        window = (run.formation_start_s, run.formation_start_s + run.formation_duration_s)
        outages = [
            (o.at_s, None if o.duration_s is None else o.at_s + o.duration_s)
            for o in scenario.faults(vehicle).gps.outages
        ]
        visual = visual_from_mapping(scenario.visual, f"scenario {scenario.name} [visual]")
        monitor = TruthMonitor(obstacles=Envelopes.from_specs(solid_structures(visual)))
        return cls(window, outages, snapshot_times(window, snapshots) if snapshots else [], monitor=monitor)

    def in_window(self, t_s: float) -> bool:
        return self.window_s[0] <= t_s <= self.window_s[1]

    def formation(self, t_s: float) -> bool:
        return self.state in FORMATION_STATES and self.in_window(t_s)

    def gps_ok(self, t_s: float) -> bool:
        """The follower's true GPS availability from the fault schedule."""
        return not any(a <= t_s and (b is None or t_s < b) for a, b in self.gps_outages_s)

    def transition(self, t_s: float, from_state: str, to_state: str, reason: str) -> None:
        self.state = to_state
        self.recorder.transition(t_s, from_state, to_state, reason)

    def truth(
        self,
        t_s: float,
        p_ned_follower_m: ArrayLike,
        v_ned_follower_m_s: ArrayLike,
        q_ned_follower_wxyz: ArrayLike,
        p_ned_leader_m: ArrayLike | None,
    ) -> None:
        self.monitor.update(t_s, p_ned_follower_m, v_ned_follower_m_s, q_ned_follower_wxyz, p_ned_leader_m)

    def tick(  # noqa: PLR0917 (truth and estimate of one instant, in the order the log keeps them)
        self,
        t_s: float,
        p_ned_follower_m: ArrayLike,
        v_ned_follower_m_s: ArrayLike,
        q_ned_follower_wxyz: ArrayLike,
        p_ned_leader_m: ArrayLike,
        rel_est_ned_m: ArrayLike | None,
        *,
        yaw_service_rad: float = math.nan,
        v_cmd_ned_m_s: ArrayLike | None = None,
    ) -> None:
        """One control step: the truth at the step and the estimate the mission held (None: none).

        ``yaw_service_rad`` and ``v_cmd_ned_m_s``: the heading the service flew on and its velocity setpoint
        in NED (None for an attitude setpoint), for the split of the deviation.
        """
        self.recorder.tick(
            t_s,
            _vec(p_ned_follower_m),
            _vec(p_ned_leader_m),
            yaw_of(q_ned_follower_wxyz),
            None if rel_est_ned_m is None else _vec(rel_est_ned_m),
            formation=self.formation(t_s),
            gps_ok=self.gps_ok(t_s),
            state=self.state,
            v_ned_follower_m_s=_vec(v_ned_follower_m_s),
            yaw_service_rad=yaw_service_rad,
            v_cmd_ned_m_s=None if v_cmd_ned_m_s is None else _vec(v_cmd_ned_m_s),
        )

    def frame(
        self,
        stamp_s: float,
        truth: GroundTruth | None,
        detections: Sequence[Detection],
        rel_est_ned_m: ArrayLike | None,
        *,
        latency_ms: float = math.nan,
        rgb: RgbImage | None = None,
        range_meas_m: float = math.nan,
    ) -> None:
        """One processed frame: its truth (at its stamp, sim time), the detections, the estimate after it.

        ``range_meas_m``: the range of the measurement that updated the track at this frame (NaN: none).
        """
        self.frames_seen += 1
        visible, detected, fp = judge_detections(truth, detections)
        rel_true: Vec3T | None = None
        yaw = math.nan
        if truth is not None and truth.p_ned_leader_m is not None and truth.p_ned_follower_m is not None:
            rel_true = _vec(np.asarray(truth.p_ned_leader_m) - np.asarray(truth.p_ned_follower_m))
            if not all(math.isfinite(c) for c in rel_true):
                rel_true = None
        if truth is not None and truth.q_ned_follower_wxyz is not None:
            yaw = yaw_of(truth.q_ned_follower_wxyz)
        self.recorder.frame(
            stamp_s,
            leader_visible=visible,
            detected=detected,
            false_positive=fp,
            latency_ms=latency_ms,
            rel_est_ned_m=None if rel_est_ned_m is None else _vec(rel_est_ned_m),
            rel_true_ned_m=rel_true,
            yaw_follower_rad=yaw,
            formation=self.formation(stamp_s),
            range_meas_m=range_meas_m,
        )
        if (
            rgb is not None
            and self._next_snapshot < len(self.snapshot_times_s)
            and stamp_s >= self.snapshot_times_s[self._next_snapshot]
        ):
            self._next_snapshot += 1
            best = max(detections, key=lambda d: d.score, default=None)
            self.snapshots.append(
                Snapshot(
                    stamp_s,
                    rgb.copy(),
                    None if best is None else best.box_xyxy_px,
                    None if truth is None else truth.box_xyxy_px,
                    None if best is None else best.score,
                )
            )

    def wants_snapshot(self, stamp_s: float) -> bool:
        """Whether the next frame at ``stamp_s`` would be kept (so a harness copies pixels only then)."""
        return (
            self._next_snapshot < len(self.snapshot_times_s)
            and stamp_s >= self.snapshot_times_s[self._next_snapshot]
        )

    def freeze(self) -> FlightLog:
        rec = self.recorder
        rec.crashed = self.monitor.crashed
        rec.landed = self.monitor.landed
        starts = [a for a, _ in self.gps_outages_s]
        rec.gps_loss_t_s = min(starts) if starts else None
        return rec.freeze()

    def extra(self) -> dict[str, object]:
        """Truth figures beyond the contract: touchdown speed, crash reason, heights."""
        m = self.monitor
        return {
            "touchdown_m_s": m.touchdown_m_s,
            "crash_reason": m.crash_reason or None,
            "max_height_m": round(m.max_height_m, 3),
            "min_obstacle_clearance_m": (
                round(m.min_obstacle_clearance_m, 3) if math.isfinite(m.min_obstacle_clearance_m) else None
            ),
        }


def snapshot_times(window_s: tuple[float, float], n: int = 5) -> list[float]:
    """``n`` evenly spaced instants inside the formation window, for the camera strip."""
    a, b = window_s
    return [a + (b - a) * (i + 0.5) / n for i in range(n)]
