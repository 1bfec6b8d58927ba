"""The paper's metrics and ours, computed from a :class:`FlightLog` (pure numpy, no I/O).

Definitions (the report.json contract documents them too):
    * relative position error: the service's estimate of leader-minus-follower (NED) minus the truth,
      over formation ticks where an estimate exists.
    * relative yaw (bearing) error: the leader's azimuth in the follower's heading frame, estimated minus
      true; both use the follower's true heading so the figure isolates the relative estimate.
    * formation error: the true leader position in the follower's level heading frame minus the desired
      slot (the configured camera-frame offset, e.g. leader 5 m ahead on the camera axis, level).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.lab.evaluation.log import F64, FlightLog

#: The paper's Table (position RMSE m, yaw RMSE deg, maximum deviation m).
PAPER_TABLE: Mapping[str, tuple[float, float, float]] = {
    "straight": (0.25, 2.5, 0.60),
    "circle": (0.32, 3.1, 0.75),
    "gps-loss": (0.45, 3.8, 0.95),
    "visibility": (0.58, 4.6, 1.20),
}
PAPER_ROW_NAMES: Mapping[str, str] = {
    "straight": "Straight line",
    "circle": "Circular path",
    "gps-loss": "Sensor failure (GPS)",
    "visibility": "Visibility stress test",
}
#: The project's targets: about 2x better than the paper.
TARGETS: Mapping[str, Mapping[str, float]] = {
    "straight": {
        "relative_position_rmse_m": 0.12,
        "relative_yaw_rmse_deg": 1.5,
        "formation_max_deviation_m": 0.30,
    },
    "circle": {
        "relative_position_rmse_m": 0.15,
        "relative_yaw_rmse_deg": 1.5,
        "formation_max_deviation_m": 0.38,
    },
    "gps-loss": {
        "relative_position_rmse_m": 0.22,
        "relative_yaw_rmse_deg": 1.5,
        "formation_max_deviation_m": 0.48,
    },
    "visibility": {
        "relative_position_rmse_m": 0.30,
        "relative_yaw_rmse_deg": 1.5,
        "formation_max_deviation_m": 0.60,
    },
}
#: Scenarios built to end otherwise than ``completed``: the outcome they are meant to end in, and why. A
#: run that ends so did what the scenario tests; every other scenario is meant to complete.
INTENDED_OUTCOMES: Mapping[str, tuple[str, str]] = {
    "link-loss": (
        "aborted",
        "the link's 1.5 s cut trips PX4's offboard-loss failsafe (Hold, as the service set it), which keeps "
        "the vehicle",
    ),
}
FORMATION_STATES = frozenset({"FOLLOW", "FOLLOW_VISION"})
OUTCOMES = ("completed", "strayed", "landed_safely", "aborted", "crashed")


def intended_outcome(scenario: str) -> tuple[str, str]:
    """The outcome ``scenario`` is meant to end in, and why ("" for a plain completion)."""
    return INTENDED_OUTCOMES.get(scenario, ("completed", ""))


def outcome_words(report: Mapping[str, Any]) -> str:
    """The outcome as a summary shows it: marked where it is the scenario's intended one, or not."""
    outcome = str(report["outcome"])
    intended = report.get("intended_outcome", "completed")
    if intended == "completed":
        return outcome
    return f"{outcome} (as intended)" if outcome == intended else f"{outcome} (intended: {intended})"


#: A run that ends in formation this far from its slot (m) followed something else than the leader.
STRAYED_M = 5.0


def offset_cam_to_level_body(offset_cam_m: Sequence[float]) -> F64:
    """Camera-frame offset (x right, y down, z forward) as a level-body FRD vector."""
    x, y, z = (float(c) for c in offset_cam_m)
    return np.array([z, x, y])


def to_heading_frame(rel_ned_m: F64, yaw_rad: F64) -> F64:
    """Rotate N x 3 NED vectors into each tick's level heading frame (x forward, y right, z down)."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    out = np.empty_like(rel_ned_m)
    out[:, 0] = c * rel_ned_m[:, 0] + s * rel_ned_m[:, 1]
    out[:, 1] = -s * rel_ned_m[:, 0] + c * rel_ned_m[:, 1]
    out[:, 2] = rel_ned_m[:, 2]
    return out


def rms(x: NDArray[np.float64]) -> float | None:
    """Root mean square of a 1-D array; None for an empty one (no data is not zero error)."""
    return float(np.sqrt(np.mean(np.square(x)))) if x.size else None


def percentiles_ms(x: F64) -> dict[str, float | None]:
    """p50/p95/p99 of the finite values, or None each when there are none."""
    x = x[np.isfinite(x)]
    if not x.size:
        return {"p50": None, "p95": None, "p99": None}
    p50, p95, p99 = np.percentile(x, [50, 95, 99])
    return {"p50": float(p50), "p95": float(p95), "p99": float(p99)}


@dataclass(frozen=True, slots=True)
class FlightMetrics:
    """The numbers a report carries (None where the run produced no data for a metric)."""

    relative_position_rmse_m: float | None
    relative_yaw_rmse_deg: float | None
    formation_rmse_m: float | None
    formation_max_deviation_m: float | None
    min_separation_m: float | None
    detection_recall: float | None
    false_positive_rate: float | None
    perception_latency_ms: dict[str, float | None]
    frames: int
    formation_s: float
    outcome: str
    #: From the first FOLLOW tick into the slot (s), and how far past the slot's range it went then (m).
    join_s: float | None = None
    join_overshoot_m: float | None = None


def _bearing_errors(rel_est: F64, rel_true: F64, yaw: F64) -> F64:
    h_true = to_heading_frame(rel_true, yaw)
    h_est = to_heading_frame(rel_est, yaw)
    az_err = np.arctan2(h_est[:, 1], h_est[:, 0]) - np.arctan2(h_true[:, 1], h_true[:, 0])
    wrapped: F64 = (az_err + math.pi) % (2 * math.pi) - math.pi
    return wrapped


def relative_errors(log: FlightLog) -> tuple[F64, F64]:
    """Relative position error norms (m) and bearing errors (rad) of the estimate against the truth.

    Per camera frame when the log has per-frame estimates (the tracker's estimate at the frame's stamp,
    scored against the truth at that instant, over frames in formation); otherwise per control tick.
    """
    if log.frame_rel_est_ned_m.size and np.isfinite(log.frame_rel_est_ned_m).all(axis=1).any():
        have = (
            log.frame_formation
            & np.all(np.isfinite(log.frame_rel_est_ned_m), axis=1)
            & np.all(np.isfinite(log.frame_rel_true_ned_m), axis=1)
        )
        est, true = log.frame_rel_est_ned_m[have], log.frame_rel_true_ned_m[have]
        err = np.linalg.norm(est - true, axis=1)
        return err, _bearing_errors(est, true, log.frame_yaw_follower_rad[have])
    return tick_relative_errors(log)


def tick_relative_errors(log: FlightLog) -> tuple[F64, F64]:
    """Per control tick: the estimate the mission held at the tick against the truth at the tick."""
    rel_true = log.p_ned_leader_m - log.p_ned_follower_m
    have = log.formation & np.all(np.isfinite(log.rel_ned_est_m), axis=1)
    err = np.linalg.norm(log.rel_ned_est_m[have] - rel_true[have], axis=1)
    return err, _bearing_errors(log.rel_ned_est_m[have], rel_true[have], log.yaw_follower_rad[have])


def formation_errors(log: FlightLog, offset_cam_m: Sequence[float]) -> F64:
    """Per-tick formation error norms (m) over formation ticks."""
    rel_true = log.p_ned_leader_m - log.p_ned_follower_m
    sel = log.formation
    h = to_heading_frame(rel_true[sel], log.yaw_follower_rad[sel])
    err: F64 = np.linalg.norm(h - offset_cam_to_level_body(offset_cam_m), axis=1)
    return err


#: The join is done when the formation error first falls under this (m).
JOIN_DONE_M = 0.3
#: The join's overshoot is looked for over this long after it is done (s).
JOIN_SETTLE_S = 5.0


def join_figures(log: FlightLog, offset_cam_m: Sequence[float]) -> tuple[float | None, float | None]:
    """How the follower got into its slot: the join's time (s) and its overshoot (m).

    The time runs from the first FOLLOW tick until the formation error first falls under ``JOIN_DONE_M``.
    The overshoot is how far past the slot's range the follower went over the ``JOIN_SETTLE_S`` after (on
    the other side of the slot from where it started; 0 when never past). None, None when it never
    followed or never got there.
    """
    follow = np.flatnonzero(np.array([s == "FOLLOW" for s in log.state], dtype=bool))
    if follow.size == 0:
        return None, None
    i0 = int(follow[0])
    rel_true = log.p_ned_leader_m[i0:] - log.p_ned_follower_m[i0:]
    slot = offset_cam_to_level_body(offset_cam_m)
    err = np.linalg.norm(to_heading_frame(rel_true, log.yaw_follower_rad[i0:]) - slot, axis=1)
    e_range = np.hypot(rel_true[:, 0], rel_true[:, 1]) - math.hypot(slot[0], slot[1])
    t = log.t_s[i0:] - log.t_s[i0]
    done = np.flatnonzero(err < JOIN_DONE_M)
    if done.size == 0:
        return None, None
    k = int(done[0])
    settle = (t >= t[k]) & (t <= t[k] + JOIN_SETTLE_S)
    past = -math.copysign(1.0, float(e_range[0])) * e_range[settle]
    return float(t[k]), max(0.0, float(past.max()))


def outcome_of(log: FlightLog, end_error_m: float | None = None) -> str:
    """How a run ended: completed, strayed, landed_safely, aborted or crashed.

    Completed: in formation; strayed: in formation but over ``STRAYED_M`` from the slot (``end_error_m``,
    the last formation error, m); aborted: otherwise in the air.
    """
    if log.crashed:
        return "crashed"
    if log.landed:
        return "landed_safely"
    if log.state and log.state[-1] in FORMATION_STATES:
        return "strayed" if end_error_m is not None and end_error_m > STRAYED_M else "completed"
    return "aborted"


def compute_metrics(log: FlightLog, offset_cam_m: Sequence[float]) -> FlightMetrics:
    """All report metrics of one run."""
    pos_err, az_err = relative_errors(log)
    form_err = formation_errors(log, offset_cam_m)
    sep = np.linalg.norm(log.p_ned_leader_m - log.p_ned_follower_m, axis=1)
    visible = log.frame_leader_visible
    n_frames = int(log.frame_t_s.size)
    dt = np.diff(log.t_s, append=log.t_s[-1] if log.t_s.size else 0.0)
    yaw_rms = rms(az_err)
    join_s, join_overshoot_m = join_figures(log, offset_cam_m)
    return FlightMetrics(
        relative_position_rmse_m=rms(pos_err),
        relative_yaw_rmse_deg=math.degrees(yaw_rms) if yaw_rms is not None else None,
        formation_rmse_m=rms(form_err),
        formation_max_deviation_m=float(form_err.max()) if form_err.size else None,
        min_separation_m=float(sep.min()) if sep.size else None,
        detection_recall=float(log.frame_detected[visible].mean()) if visible.any() else None,
        false_positive_rate=float(log.frame_false_positive.mean()) if n_frames else None,
        perception_latency_ms=percentiles_ms(log.frame_latency_ms),
        frames=n_frames,
        formation_s=float(dt[log.formation].sum()) if log.t_s.size else 0.0,
        outcome=outcome_of(log, float(form_err[-1]) if form_err.size else None),
        join_s=join_s,
        join_overshoot_m=join_overshoot_m,
    )


def monte_carlo_summary(reports: Iterable[Mapping[str, Any]]) -> dict[str, Any]:
    """Min, p5, p50, p95 and max of each numeric metric over runs, and the count of each outcome."""
    runs = list(reports)
    keys = (
        "relative_position_rmse_m",
        "relative_yaw_rmse_deg",
        "formation_rmse_m",
        "formation_max_deviation_m",
        "min_separation_m",
        "min_obstacle_clearance_m",
        "detection_recall",
    )
    out: dict[str, Any] = {"runs": len(runs), "outcomes": {o: 0 for o in OUTCOMES}}
    for r in runs:
        out["outcomes"][r["outcome"]] = out["outcomes"].get(r["outcome"], 0) + 1
    for key in keys:
        vals = np.array([r[key] for r in runs if r.get(key) is not None], dtype=np.float64)
        if vals.size:
            p5, p50, p95 = np.percentile(vals, [5, 50, 95])
            out[key] = {
                "min": float(vals.min()),
                "p5": float(p5),
                "p50": float(p50),
                "p95": float(p95),
                "max": float(vals.max()),
            }
        else:
            out[key] = None
    return out
