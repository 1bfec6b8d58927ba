"""What a closed-loop run records: per control tick, per camera frame, and per mission transition.

Frames: world is local NED; ``rel`` vectors are leader minus follower in NED, m. Everything is on the
simulator's clock (s). The recorder appends to Python lists (cheap per tick) and freezes into numpy arrays.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
Vec3T = tuple[float, float, float]
_NAN3: Vec3T = (float("nan"), float("nan"), float("nan"))
# t, follower, leader, yaw, estimate, formation, gps_ok, state, follower velocity, service's yaw, command
_Tick = tuple[float, Vec3T, Vec3T, float, Vec3T, bool, bool, str, Vec3T, float, Vec3T]
# t, visible, detected, false positive, latency, estimate, truth, follower yaw, formation, measured range
_Frame = tuple[float, bool, bool, bool, float, Vec3T, Vec3T, float, bool, float]


@dataclass(frozen=True, slots=True)
class Transition:
    """A mission state change: when, from, to, and the reason's name."""

    t_s: float
    from_state: str
    to_state: str
    reason: str


@dataclass(slots=True)
class FlightLog:
    """Frozen arrays of one run. Tick arrays have length N, frame arrays length M."""

    # per control tick
    t_s: F64
    p_ned_follower_m: F64  # N x 3, truth
    p_ned_leader_m: F64  # N x 3, truth
    yaw_follower_rad: F64  # N, truth
    rel_ned_est_m: F64  # N x 3, the service's estimate of leader - follower; NaN when it has none
    formation: NDArray[np.bool_]  # N, True while the mission is in a formation-keeping state
    gps_ok: NDArray[np.bool_]  # N, the follower's true GPS availability (fault schedule)
    state: list[str]  # N, mission state names
    v_ned_follower_m_s: F64  # N x 3, truth
    # per camera frame (the service-side tick series follow the frame arrays: they have defaults)
    frame_t_s: F64  # M
    frame_leader_visible: NDArray[np.bool_]  # M, truth: some of the leader is in the image
    frame_detected: NDArray[np.bool_]  # M, the detector's box matched the truth box (IoU >= 0.5)
    frame_false_positive: NDArray[np.bool_]  # M, a box was reported that matches no leader
    frame_latency_ms: F64  # M, frame arrival -> estimate, NaN when not measured
    #: M x 3: the tracker's estimate of leader - follower (NED) at the frame's stamp, after this frame; NaN
    #: when it had none. Scored against ``frame_rel_true_ned_m`` (the truth at the same instant).
    frame_rel_est_ned_m: F64 = field(default_factory=lambda: np.empty((0, 3)))
    frame_rel_true_ned_m: F64 = field(default_factory=lambda: np.empty((0, 3)))  # M x 3, truth
    frame_yaw_follower_rad: F64 = field(default_factory=lambda: np.empty(0))  # M, truth
    frame_formation: NDArray[np.bool_] = field(default_factory=lambda: np.empty(0, dtype=bool))  # M
    #: M: the range of the measurement that updated the track at the frame (camera to leader), m; NaN: none.
    frame_range_meas_m: F64 = field(default_factory=lambda: np.empty(0))
    #: N: the heading the service flew on (the autopilot's, less any correction), rad; NaN: unknown.
    yaw_service_rad: F64 = field(default_factory=lambda: np.empty(0))
    #: N x 3: the velocity setpoint in NED as the service meant it; NaN for an attitude setpoint or none.
    v_cmd_ned_m_s: F64 = field(default_factory=lambda: np.empty((0, 3)))
    transitions: list[Transition] = field(default_factory=list)
    gps_loss_t_s: float | None = None
    crashed: bool = False
    landed: bool = False


@dataclass(slots=True)
class FlightRecorder:
    """Append-only recorder used by the harness; :meth:`freeze` produces the :class:`FlightLog`."""

    _ticks: list[_Tick] = field(default_factory=list)
    _frames: list[_Frame] = field(default_factory=list)
    transitions: list[Transition] = field(default_factory=list)
    gps_loss_t_s: float | None = None
    crashed: bool = False
    landed: bool = False

    def tick(
        self,
        t_s: float,
        p_ned_follower_m: Vec3T,
        p_ned_leader_m: Vec3T,
        yaw_follower_rad: float,
        rel_ned_est_m: Vec3T | None,
        *,
        formation: bool,
        gps_ok: bool,
        state: str,
        v_ned_follower_m_s: Vec3T = (0.0, 0.0, 0.0),
        yaw_service_rad: float = float("nan"),
        v_cmd_ned_m_s: Vec3T | None = None,
    ) -> None:
        """Record one control tick."""
        self._ticks.append(
            (
                t_s,
                p_ned_follower_m,
                p_ned_leader_m,
                yaw_follower_rad,
                rel_ned_est_m if rel_ned_est_m is not None else _NAN3,
                formation,
                gps_ok,
                state,
                v_ned_follower_m_s,
                yaw_service_rad,
                v_cmd_ned_m_s if v_cmd_ned_m_s is not None else _NAN3,
            )
        )

    def frame(
        self,
        t_s: float,
        *,
        leader_visible: bool,
        detected: bool,
        false_positive: bool,
        latency_ms: float = float("nan"),
        rel_est_ned_m: Vec3T | None = None,
        rel_true_ned_m: Vec3T | None = None,
        yaw_follower_rad: float = float("nan"),
        formation: bool = False,
        range_meas_m: float = float("nan"),
    ) -> None:
        """Record one camera frame's detection outcome, and optionally its estimate, against the truth."""
        self._frames.append(
            (
                t_s,
                leader_visible,
                detected,
                false_positive,
                latency_ms,
                rel_est_ned_m if rel_est_ned_m is not None else _NAN3,
                rel_true_ned_m if rel_true_ned_m is not None else _NAN3,
                yaw_follower_rad,
                formation,
                range_meas_m,
            )
        )

    def transition(self, t_s: float, from_state: str, to_state: str, reason: str) -> None:
        """Record a mission transition."""
        self.transitions.append(Transition(t_s, from_state, to_state, reason))

    def freeze(self) -> FlightLog:
        """Arrays of everything recorded so far."""
        n = len(self._ticks)
        cols = list(zip(*self._ticks, strict=True)) if n else [()] * 11
        m = len(self._frames)
        fcols = list(zip(*self._frames, strict=True)) if m else [()] * 10

        def vec(i: int) -> F64:
            return np.array(cols[i], dtype=np.float64).reshape(n, 3)

        def fvec(i: int) -> F64:
            return np.array(fcols[i], dtype=np.float64).reshape(m, 3)

        return FlightLog(
            t_s=np.array(cols[0], dtype=np.float64),
            p_ned_follower_m=vec(1),
            p_ned_leader_m=vec(2),
            yaw_follower_rad=np.array(cols[3], dtype=np.float64),
            rel_ned_est_m=vec(4),
            formation=np.array(cols[5], dtype=bool),
            gps_ok=np.array(cols[6], dtype=bool),
            state=list(cols[7]),
            v_ned_follower_m_s=vec(8),
            frame_t_s=np.array(fcols[0], dtype=np.float64),
            frame_leader_visible=np.array(fcols[1], dtype=bool),
            frame_detected=np.array(fcols[2], dtype=bool),
            frame_false_positive=np.array(fcols[3], dtype=bool),
            frame_latency_ms=np.array(fcols[4], dtype=np.float64),
            frame_rel_est_ned_m=fvec(5),
            frame_rel_true_ned_m=fvec(6),
            frame_yaw_follower_rad=np.array(fcols[7], dtype=np.float64),
            frame_formation=np.array(fcols[8], dtype=bool),
            frame_range_meas_m=np.array(fcols[9], dtype=np.float64),
            yaw_service_rad=np.array(cols[9], dtype=np.float64),
            v_cmd_ned_m_s=vec(10),
            transitions=list(self.transitions),
            gps_loss_t_s=self.gps_loss_t_s,
            crashed=self.crashed,
            landed=self.landed,
        )


def save_log(log: FlightLog, path: Path) -> None:
    """The log's arrays as a compressed ``.npz`` (transitions as text rows) for analysis after a run."""
    arrays: dict[str, Any] = {}
    for f in fields(log):
        value = getattr(log, f.name)
        if isinstance(value, np.ndarray):
            arrays[f.name] = value
    arrays["state"] = np.array(log.state, dtype=str)
    arrays["transitions"] = np.array(
        [[f"{t.t_s:.3f}", t.from_state, t.to_state, t.reason] for t in log.transitions], dtype=str
    ).reshape(-1, 4)
    np.savez_compressed(path, **arrays)


def load_log(path: Path) -> FlightLog:
    """A log written by :func:`save_log`: its arrays, states and transitions.

    ``gps_loss_t_s``, ``crashed`` and ``landed`` are not in the file (the run's report has them); they
    come back as their defaults.
    """
    text = ("state", "transitions")
    with np.load(path) as npz:
        arrays = {
            f.name: npz[f.name] for f in fields(FlightLog) if f.name in npz.files and f.name not in text
        }
        state = [str(s) for s in npz["state"]]
        rows = npz["transitions"]
    transitions = [Transition(float(t), a, b, why) for t, a, b, why in rows.tolist()]
    return FlightLog(**arrays, state=state, transitions=transitions)
