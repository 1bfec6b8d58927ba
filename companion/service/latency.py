"""Per-stage latency over a sliding window: p50/p99 for the status endpoint and MQTT health.

Stages follow the frame: capture -> detect (pre/infer/post) -> pose -> track -> setpoint, plus end_to_end.
The control tick adds the age of what it flies on, per link (:class:`TickAges`): ``telemetry_age`` (the
autopilot's attitude, from when the autopilot sampled it), ``camera_age`` (the leader estimate, from its
frame's capture) and ``mavlink_rtt`` (the link's TIMESYNC round trip).
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any

import numpy as np

from companion.kernel.clock import Clock
from companion.mission.types import MissionInputs, StepOutput, Transition

#: Ages beyond this are a stale input (the mission's business), not a latency, s.
_MAX_AGE_S = 5.0


class LatencyStats:
    """The last ``window`` samples of each stage, ms; old samples fall out (bounded memory)."""

    def __init__(self, window: int = 512) -> None:
        if window < 1:
            raise ValueError("window must be >= 1")
        self._window = window
        self._samples: dict[str, deque[float]] = {}
        self._counts: dict[str, int] = {}

    def record(self, stage: str, ms: float) -> None:
        buf = self._samples.get(stage)
        if buf is None:
            buf = self._samples[stage] = deque(maxlen=self._window)
        buf.append(ms)
        self._counts[stage] = self._counts.get(stage, 0) + 1

    def summary(self) -> dict[str, dict[str, float | int]]:
        """``{stage: {"p50_ms", "p95_ms", "p99_ms", "max_ms", "count"}}`` over the window (count: ever)."""
        out: dict[str, dict[str, float | int]] = {}
        for stage, buf in self._samples.items():
            arr = np.fromiter(buf, dtype=np.float64, count=len(buf))
            p50, p95, p99 = np.percentile(arr, [50.0, 95.0, 99.0])
            out[stage] = {
                "p50_ms": round(float(p50), 2),
                "p95_ms": round(float(p95), 2),
                "p99_ms": round(float(p99), 2),
                "max_ms": round(float(arr.max()), 2),
                "count": self._counts[stage],
            }
        return out


class TickAges:
    """A flight observer: the ages of the inputs each control tick flies on, into :class:`LatencyStats`.

    ``telemetry_age``: now minus the autopilot attitude's arrival; ``camera_age``: now minus the capture
    of the frame behind the leader estimate (detection, tracking and the wait for the tick). Service
    clock, ms.
    """

    def __init__(self, latency: LatencyStats, clock: Clock) -> None:
        self._latency = latency
        self._clock = clock
        self._rtt_stamp_s = -math.inf

    def on_frame(self, frame: Any, result: Any, track: Any) -> None:
        return None

    def on_step(self, inputs: MissionInputs, out: StepOutput) -> None:
        now_s = self._clock.now_s()
        veh = inputs.vehicle
        age_s = now_s - veh.attitude_stamp_s
        if 0.0 <= age_s <= _MAX_AGE_S:
            self._latency.record("telemetry_age", age_s * 1e3)
        if veh.link_rtt_stamp_s > self._rtt_stamp_s:
            self._rtt_stamp_s = veh.link_rtt_stamp_s
            self._latency.record("mavlink_rtt", veh.link_rtt_s * 1e3)
        est = inputs.leader
        if est is not None and est.usable and 0.0 <= now_s - est.stamp_s <= _MAX_AGE_S:
            self._latency.record("camera_age", (now_s - est.stamp_s) * 1e3)

    def on_transition(self, tr: Transition) -> None:
        return None
