"""Ground-truth boxes as a detector (``detector.runtime = "truth"``): pose and tracker, no network.

Frames from the simulator carry the leader's true box (``RgbdFrame.truth``);
this returns it, with optional jitter and misses, so flights and evaluations can isolate everything after
detection. Frames without truth (a real camera) give no detection.
"""

from __future__ import annotations

import numpy as np

from companion.kernel.camera import RgbdFrame, RgbImage
from companion.perception.types import Detection, DetectorResult


class TruthDetector:
    """A :class:`Detector` that returns the ground-truth box (with jitter and misses): isolates pose+tracker.

    Detections need a frame with truth, so call :meth:`detect_frame`; ``detect(rgb)`` alone finds nothing.
    """

    def __init__(
        self, *, jitter_px: float = 0.0, min_visible: float = 0.3, miss_rate: float = 0.0, seed: int = 0
    ) -> None:
        self.jitter_px = jitter_px
        self.min_visible = min_visible
        self.miss_rate = miss_rate
        self._rng = np.random.default_rng(seed)

    def detect(self, rgb: RgbImage) -> DetectorResult:
        return DetectorResult()

    def detect_frame(self, frame: RgbdFrame) -> DetectorResult:
        t = frame.truth
        if t is None or t.box_xyxy_px is None or t.visible_fraction < self.min_visible:
            return DetectorResult()
        if self.miss_rate > 0 and self._rng.random() < self.miss_rate:
            return DetectorResult()
        box = np.asarray(t.box_xyxy_px, dtype=np.float64)
        if self.jitter_px > 0:
            box = box + self._rng.normal(scale=self.jitter_px, size=4)
        x0, y0, x1, y1 = (float(c) for c in box)
        return DetectorResult([Detection((x0, y0, max(x1, x0 + 1.0), max(y1, y0 + 1.0)), 0.9)])
