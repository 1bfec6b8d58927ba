"""Faults put into the camera's frames: a depth glitch on the leader (one frame's range made wrong).

Used by the lockstep harness and the camera server alike, so a scenario's camera faults fly the same on both
paths. Pure numpy on one frame; the schedule says which frame gets which fault.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from companion.kernel.camera import RgbdFrame

#: A glitched depth never reads nearer than this, m (the sensor's minimum range).
MIN_DEPTH_M = 0.1


def offset_leader_depth(frame: RgbdFrame, offset_m: float) -> RgbdFrame:
    """``frame`` with every valid depth inside the leader's true box moved by ``offset_m`` (negative: nearer).

    A frame without the leader in view (or a zero offset) comes back as it is; the depth array is copied.
    """
    box = frame.truth.box_xyxy_px if frame.truth is not None else None
    if box is None or offset_m == 0.0:
        return frame
    h, w = frame.depth_m.shape[:2]
    x0, y0 = max(int(np.floor(box[0])), 0), max(int(np.floor(box[1])), 0)
    x1, y1 = min(int(np.ceil(box[2])), w), min(int(np.ceil(box[3])), h)
    depth = frame.depth_m.copy()
    roi = depth[y0:y1, x0:x1]
    valid = np.isfinite(roi) & (roi > 0.0)
    roi[valid] = np.maximum(roi[valid] + offset_m, MIN_DEPTH_M)
    return replace(frame, depth_m=depth)


class DepthGlitches:
    """Each ``(at_s, offset_m)`` applied once, to the first frame stamped at or after ``at_s``."""

    def __init__(self, glitches: Sequence[tuple[float, float]]) -> None:
        self._due = sorted((float(t), float(dz)) for t, dz in glitches)

    def take(self, t_s: float) -> float:
        """The depth offset for a frame stamped ``t_s`` (m; 0.0 for none); a glitch is used up once taken."""
        offset = 0.0
        while self._due and self._due[0][0] <= t_s:
            offset += self._due.pop(0)[1]
        return offset
