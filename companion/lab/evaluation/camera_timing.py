"""When a captured frame's estimate reaches the mission in the lockstep harnesses (sim time, seeded).

Compute is instantaneous in lockstep, so the camera pipeline's timing is drawn: a base latency (the camera's
own plus detection), a spread around it, frames dropped before the detector, and an exponential extra for a
loaded computer (the scenario's ``[timing]``). Estimates arrive in capture order, as from one pipeline.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

#: Mixed into the run's seed so that the camera's draws do not share a stream with the simulator's.
_STREAM = 0x7113


class CameraTiming:
    """Per frame: when its estimate is due at the mission, or None for a dropped frame, sim s.

    Args:
        spec: the scenario's ``timing`` (``sitl.world.scenario.TimingSpec``).
        seed: the run's seed; ``stream`` tells followers of one formation apart.
    """

    def __init__(self, spec: Any, seed: int, stream: int = 0) -> None:
        self.spec = spec
        self._rng = np.random.default_rng([seed, _STREAM, stream])
        self._last_due_s = -math.inf
        self.dropped = 0
        self.delivered = 0

    def due_s(self, capture_s: float) -> float | None:
        """Draw this frame's fate (call once per captured frame, in capture order)."""
        sp = self.spec
        latency_ms = float(sp.camera_latency_ms)
        if not sp.is_fixed:
            if sp.frame_drop > 0.0 and self._rng.random() < sp.frame_drop:
                self.dropped += 1
                return None
            if sp.camera_jitter_ms > 0.0:
                latency_ms += float(self._rng.normal(0.0, sp.camera_jitter_ms))
            if sp.detector_load_ms > 0.0:
                latency_ms += float(self._rng.exponential(sp.detector_load_ms))
        due_s = max(capture_s + max(latency_ms, 0.0) * 1e-3, self._last_due_s)
        self._last_due_s = due_s
        self.delivered += 1
        return due_s

    def summary(self) -> dict[str, Any]:
        """The model and what it did, for the run's report."""
        return {**self.spec.model_dump(), "frames_dropped": self.dropped, "frames_delivered": self.delivered}
