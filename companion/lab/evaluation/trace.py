"""What the service did during a run, step by step and frame by frame: for scoring and a trace file.

:class:`RunObserver` is fed by the control loop's ``on_step`` and the perception path's per-frame hook; it
only records (it never feeds anything back). ``write_trace`` writes every step and frame as JSON lines
(``trace.jsonl``: estimate age, setpoint, vehicle velocity, what the tracker did with each frame, the
truth beside the estimate) for a post-mortem.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion.kernel.camera import GroundTruth, RgbdFrame
from companion.kernel.flight import Setpoint, VelocityBodySetpoint, VelocityNedSetpoint
from companion.kernel.frames import heading_to_ned
from companion.mission.types import MissionInputs, StepOutput
from companion.perception.types import Detection, DetectorResult


@dataclass(slots=True)
class TraceTick:
    """One control tick as the run observer saw it (service clock, s; NED m)."""

    t_s: float
    rel_est_ned_m: tuple[float, float, float] | None
    transitions: list[tuple[float, str, str, str]]
    #: For the run's trace file: the estimate's age, the setpoint, the vehicle's velocity and height.
    trace: dict[str, Any] = field(default_factory=dict)
    #: The heading the service flew on (PX4's, less any heading correction), rad.
    yaw_service_rad: float = math.nan
    #: The velocity setpoint in NED as the service meant it (its heading applied); None for an attitude
    #: setpoint or none, m/s.
    v_cmd_ned_m_s: tuple[float, float, float] | None = None


@dataclass(slots=True)
class TraceFrame:
    """One processed camera frame as the run observer saw it (capture stamp, s; NED m)."""

    t_s: float
    truth: GroundTruth | None
    detections: list[Detection]
    rel_est_ned_m: tuple[float, float, float] | None
    compute_ms: float
    rgb: np.ndarray | None
    #: For the trace file: what the tracker did with this frame.
    track: dict[str, Any] = field(default_factory=dict)
    #: The range of the measurement that updated the track at this frame (camera to leader), m; NaN: none.
    range_meas_m: float = math.nan


@dataclass(slots=True)
class RunObserver:
    """Records the service's control steps and processed frames (on its loop; never feeds back)."""

    clock: Any
    snapshot_times_s: list[float]
    ticks: list[TraceTick] = field(default_factory=list)
    frames: list[TraceFrame] = field(default_factory=list)
    #: Per tick: the attitude telemetry's age and the leader estimate's age (capture to control), s.
    telemetry_age_s: list[float] = field(default_factory=list)
    estimate_age_s: list[float] = field(default_factory=list)
    #: Per tick with a leader share: its age (shared to control), s; and the ticks flown on it.
    share_age_s: list[float] = field(default_factory=list)
    ticks_led_on_share: int = 0
    ticks_coasted_on_share: int = 0
    _next_snapshot: int = 0

    def on_step(self, inputs: MissionInputs, out: StepOutput) -> None:
        est = inputs.leader
        now_s = self.clock.now_s()
        v = inputs.vehicle
        sp = out.setpoint
        att_age_s = now_s - v.attitude_stamp_s
        if 0.0 <= att_age_s < 10.0:
            self.telemetry_age_s.append(att_age_s)
        if est is not None and est.usable:
            self.estimate_age_s.append(now_s - est.stamp_s)
        if inputs.leader_shared is not None:
            self.share_age_s.append(now_s - inputs.leader_shared.stamp_s)
        self.ticks_led_on_share += out.led_on_shared_motion
        self.ticks_coasted_on_share += out.coasted_on_shared_position
        trace = {
            "state": out.state.name,
            "att_age_s": round(att_age_s, 4),
            "est_age_s": None if est is None else round(now_s - est.stamp_s, 3),
            "est_status": None if est is None else est.status.value,
            "v_ned_m_s": [round(c, 3) for c in v.v_ned_m_s],
            "alt_rel_m": round(v.alt_rel_m, 3),
            "setpoint": None if sp is None else {k: getattr(sp, k) for k in type(sp).__slots__},
            "led_on_share": out.led_on_shared_motion,
            "coasted_on_share": out.coasted_on_shared_position,
        }
        transitions = [
            (tr.stamp_s, tr.from_state.name, tr.to_state.name, tr.reason.name) for tr in out.transitions
        ]
        rel = est.p_ned_rel_m if est is not None and est.usable else None
        trace["yaw_rad"] = round(v.yaw_rad, 5)
        self.ticks.append(
            TraceTick(now_s, rel, transitions, trace, v.yaw_rad, velocity_command_ned(sp, v.yaw_rad))
        )

    def timing(self) -> dict[str, dict[str, float | None]]:
        """The ages the control ticks saw, ms (p50/p95/max).

        The attitude telemetry's age at the tick, the leader estimate's age (from its frame's capture) and,
        where the leader shares its position, the share's age (from the leader's fix).
        """
        return {
            "telemetry_age_ms": _pcts_ms(self.telemetry_age_s),
            "leader_estimate_age_ms": _pcts_ms(self.estimate_age_s),
            "leader_share_age_ms": _pcts_ms(self.share_age_s),
        }

    def write_trace(self, path: Path) -> None:
        """Every tick and frame as JSON lines (no pixels): the run's record for a post-mortem."""
        with path.open("w") as f:
            for tk in self.ticks:
                f.write(json.dumps({"tick": round(tk.t_s, 4), "est": tk.rel_est_ned_m, **tk.trace}) + "\n")
            for fr in self.frames:
                tr = fr.truth
                rel = None
                if tr is not None and tr.p_ned_leader_m is not None and tr.p_ned_follower_m is not None:
                    rel = [
                        round(float(a - b), 4)
                        for a, b in zip(tr.p_ned_leader_m, tr.p_ned_follower_m, strict=True)
                    ]
                row = {
                    "frame": round(fr.t_s, 4),
                    "visible": None if tr is None else round(tr.visible_fraction, 3),
                    "boxes": [[round(c, 1) for c in d.box_xyxy_px] for d in fr.detections],
                    "est": fr.rel_est_ned_m,
                    "true": rel,
                    "compute_ms": round(fr.compute_ms, 2),
                    **fr.track,
                }
                f.write(json.dumps(row) + "\n")

    def on_frame(self, frame: RgbdFrame, result: DetectorResult, track: Any, process_ms: float) -> None:
        est = track.leader_estimate()
        meas = track.measurement
        range_meas_m = math.nan if meas is None else float(np.linalg.norm(meas.p_cam_leader_m))
        timing = result.timing
        detector_ms = (
            0.0 if timing is None else timing.preprocess_ms + timing.inference_ms + timing.postprocess_ms
        )
        keep = (
            self._next_snapshot < len(self.snapshot_times_s)
            and frame.stamp_s >= self.snapshot_times_s[self._next_snapshot]
        )
        if keep:
            self._next_snapshot += 1
        self.frames.append(
            TraceFrame(
                frame.stamp_s,
                frame.truth,
                list(result.detections),
                est.p_ned_rel_m if est is not None and est.usable else None,
                detector_ms + process_ms,
                frame.rgb.copy() if keep else None,
                {
                    "status": track.status.value,
                    "candidates": track.n_candidates,
                    "size_rejected": track.n_size_rejected,
                    "updated": meas is not None,
                    "range_m": None if meas is None else round(range_meas_m, 3),
                },
                range_meas_m,
            )
        )


def velocity_command_ned(sp: Setpoint | None, yaw_rad: float) -> tuple[float, float, float] | None:
    """A velocity setpoint in NED, m/s: a body-frame one turned by the service's heading ``yaw_rad``."""
    if isinstance(sp, VelocityNedSetpoint):
        return sp.v_ned_m_s
    if isinstance(sp, VelocityBodySetpoint):
        n, e, d = (float(c) for c in heading_to_ned(np.asarray(sp.v_body_m_s, dtype=np.float64), yaw_rad))
        return (n, e, d)
    return None


def _pcts_ms(values_s: list[float]) -> dict[str, float | None]:
    if not values_s:
        return {"p50": None, "p95": None, "max": None}
    a = np.asarray(values_s) * 1e3
    p50, p95 = np.percentile(a, [50.0, 95.0])
    return {"p50": round(float(p50), 2), "p95": round(float(p95), 2), "max": round(float(a.max()), 2)}
