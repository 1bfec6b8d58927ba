"""Per-stage latency over a sliding window: p50/p99 for the status endpoint and MQTT health.

Stages follow the frame: capture -> detect (pre/infer/post) -> pose -> track -> setpoint, plus end_to_end.
"""

from __future__ import annotations

from collections import deque

import numpy as np


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
        """``{stage: {"p50_ms", "p99_ms", "max_ms", "count"}}`` over the window; count is all-time."""
        out: dict[str, dict[str, float | int]] = {}
        for stage, buf in self._samples.items():
            arr = np.fromiter(buf, dtype=np.float64, count=len(buf))
            p50, p99 = np.percentile(arr, [50.0, 99.0])
            out[stage] = {
                "p50_ms": round(float(p50), 2),
                "p99_ms": round(float(p99), 2),
                "max_ms": round(float(arr.max()), 2),
                "count": self._counts[stage],
            }
        return out
