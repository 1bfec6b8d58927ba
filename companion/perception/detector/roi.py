"""Region-of-interest detection while a track is held: the network looks at a magnified window on the leader.

Why: in formation the leader is small. A 450-class quad 5 m ahead is about 50x30 px of a 640x480 frame,
25x15 px after a whole-frame letterbox to a 320 px input, and a network scores it low there. A window of
about three box widths around the tracked leader, scaled up (``roi_magnification``, 1.75x by default: about
90 px), shows it at the size the network knows. On the follower's frames of a closed-loop straight run
(docs/perception.md) recall at conf 0.35 went from 0.37 (whole frame) to 0.96-0.98 (window) with a 320 px
network at 1.5x, and the smaller input also costs less (a 128x96 window at 192 px: ~4.4 ms against ~9.3 ms).

The window follows the box of the measurement that the tracker accepted into a confirmed track, never the
detector's own best guess, so a false positive steers it only if the tracker takes it. Without such a box,
or when the window finds nothing usable, the whole frame is searched, in the same call, at
``search_input_px`` (1:1 for a 640 px frame: a lost leader is small too); without a window, every other
search is at the network's own input (``search_alternate``: a close leader is found there). A lower threshold
inside the window (``roi_conf_threshold``, for the best box, only when none passes the usual one and within
``roi_low_conf_misses`` frames of the last tracked box) is available but off by default: at 0.2 it raised
closed-loop recall by 0.02-0.04, but in a network leader-occluded run the window kept finding the tree
behind the hidden leader, the tracker took it, the window followed it, and the follower flew past the leader
at 1.23 m.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from companion.config import DetectorConfig
from companion.kernel.camera import RgbImage
from companion.perception.detector.letterbox import STRIDE
from companion.perception.detector.runtime import FrameDetector
from companion.perception.types import DetectorResult, DetectorTiming

Box = tuple[float, float, float, float]

#: Window sizes are rounded up to this step (px) so that only a few letterbox buffers are ever allocated.
WINDOW_STEP_PX = 32
#: A detection within this many pixels of a window edge that is not a frame edge may be cut by the window.
EDGE_MARGIN_PX = 1.0


@dataclass(frozen=True, slots=True)
class RoiWindow:
    """A window of the frame (pixels, top-left origin) and the network input size it is letterboxed to."""

    x0_px: int
    y0_px: int
    w_px: int
    h_px: int
    input_size_px: int


def roi_window(
    box_xyxy_px: Box,
    frame_w_px: int,
    frame_h_px: int,
    cfg: DetectorConfig,
) -> RoiWindow | None:
    """The window around ``box_xyxy_px`` at the frame's aspect ratio; None when it would be most of the frame.

    Width = ``roi_box_multiple`` box widths (or the height's equivalent, whichever is larger), at least
    ``roi_min_width_px``, rounded up to :data:`WINDOW_STEP_PX`; input size = ``roi_magnification`` x width,
    rounded up to the stride, at most ``input_size_px`` (a near leader is big enough without magnification).
    """
    x0, y0, x1, y1 = box_xyxy_px
    aspect = frame_w_px / frame_h_px
    need_w = cfg.roi_box_multiple * max(x1 - x0, (y1 - y0) * aspect)
    w = max(cfg.roi_min_width_px, math.ceil(need_w / WINDOW_STEP_PX) * WINDOW_STEP_PX)
    if w > cfg.roi_max_frame_fraction * frame_w_px:
        return None
    h = min(frame_h_px, round(w / aspect))
    cx, cy = (x0 + x1) / 2.0, (y0 + y1) / 2.0
    wx = int(min(max(round(cx - w / 2.0), 0), frame_w_px - w))
    wy = int(min(max(round(cy - h / 2.0), 0), frame_h_px - h))
    size = min(cfg.input_size_px, math.ceil(cfg.roi_magnification * w / STRIDE) * STRIDE)
    return RoiWindow(wx, wy, w, h, size)


def window_note(cfg: DetectorConfig) -> str:
    """What a run's detector description adds for the window ("" when it is off)."""
    if not cfg.roi_enabled:
        return ""
    search = ""
    if cfg.search_input_px != cfg.input_size_px:
        other = f" and {cfg.input_size_px}" if cfg.search_alternate else ""
        search = f", whole frame at {cfg.search_input_px}{other} px"
    return f", {cfg.roi_magnification:g}x window on the tracked leader{search}"


def cut_by_window(box_xyxy_px: Box, win: RoiWindow, frame_w_px: int, frame_h_px: int) -> bool:
    """Whether a box (frame pixels) touches a window edge that lies inside the frame: it may be cut off."""
    x0, y0, x1, y1 = box_xyxy_px
    m = EDGE_MARGIN_PX
    return (
        (win.x0_px > 0 and x0 <= win.x0_px + m)
        or (win.y0_px > 0 and y0 <= win.y0_px + m)
        or (win.x0_px + win.w_px < frame_w_px and x1 >= win.x0_px + win.w_px - m)
        or (win.y0_px + win.h_px < frame_h_px and y1 >= win.y0_px + win.h_px - m)
    )


def focus_box(track: Any) -> Box | None:
    """The box to centre the next window on: the measurement a confirmed track accepted this frame, else None.

    ``track`` is a :class:`companion.estimation.estimate.TrackState` (typed loosely: this module stays free of
    the tracker's imports).
    """
    m = getattr(track, "measurement", None)
    status = getattr(getattr(track, "status", None), "name", "")
    if m is None or status != "CONFIRMED":
        return None
    box: Box = m.box_xyxy_px
    return box


class RoiDetector:
    """A :class:`~companion.perception.types.Detector` that searches a window on the tracked leader first.

    Call :meth:`focus` after each frame's tracker step with :func:`focus_box` of its state. The window is kept
    through up to ``roi_hold_frames`` frames without a focus box (a missed detection, a short occlusion), then
    dropped. Not thread-safe, like the detector it wraps; the service calls ``detect`` from its one detector
    thread and ``focus`` between two ``detect`` calls.
    """

    def __init__(self, inner: FrameDetector, cfg: DetectorConfig) -> None:
        self.inner = inner
        self.cfg = cfg
        self._focus: Box | None = None
        self._misses = 0
        #: Frames searched in a window, and those where the window found nothing and the frame was searched.
        self.window_frames = 0
        self.fallback_frames = 0
        #: Searches without a window so far (their parity picks the input when ``search_alternate``).
        self.searches = 0

    @property
    def runtime(self) -> str:
        return self.inner.runtime

    @property
    def input_size_px(self) -> int:
        return self.inner.input_size_px

    def focus(self, box_xyxy_px: Box | None) -> None:
        """The tracked leader's box in the frame just processed (None: none accepted this frame)."""
        if box_xyxy_px is not None:
            self._focus, self._misses = box_xyxy_px, 0
            return
        self._misses += 1
        if self._misses > self.cfg.roi_hold_frames:
            self._focus = None

    def reset(self) -> None:
        """Forget the window (a new source, a restart)."""
        self._focus, self._misses = None, 0
        self.searches = 0

    def detect(self, rgb: RgbImage) -> DetectorResult:
        h, w = rgb.shape[0], rgb.shape[1]
        win = None if self._focus is None else roi_window(self._focus, w, h, self.cfg)
        if win is None:
            return self._search(rgb, alternate=self.cfg.search_alternate)
        self.window_frames += 1
        # The lower threshold only just after the tracker placed the leader here: once it has missed a few
        # frames (an occlusion, say), whatever the window holds is no likelier the leader than anything else.
        fresh = self._misses <= self.cfg.roi_low_conf_misses
        conf = self.cfg.roi_conf_threshold if fresh else None
        first = self.inner.detect_window(
            rgb, (win.x0_px, win.y0_px, win.w_px, win.h_px), win.input_size_px, conf
        )
        # The window's lower threshold only speaks when nothing in it passes the usual one, and then for one
        # box, the best: one leader is expected there, not a crowd of weak boxes.
        usable = [d for d in first.detections if not cut_by_window(d.box_xyxy_px, win, w, h)]
        floor = self.inner.conf_threshold
        kept = [d for d in usable if d.score >= floor] or usable[:1]
        if kept:
            return DetectorResult(kept, first.timing) if len(kept) < len(first.detections) else first
        self.fallback_frames += 1
        whole = self._search(rgb, alternate=False)
        return DetectorResult(whole.detections, _sum_timing(first.timing, whole.timing))

    def _search(self, rgb: RgbImage, *, alternate: bool) -> DetectorResult:
        """The whole frame at ``search_input_px``; ``alternate``: every other time at the detector's input.

        Only a search without a window alternates: a window that found nothing was on a leader last seen
        there, small and far more often than close (a leader hidden for seconds, flying away).
        """
        size = self.cfg.search_input_px
        if alternate:
            if self.searches % 2 == 1:
                size = self.inner.input_size_px
            self.searches += 1
        if size == self.inner.input_size_px:
            return self.inner.detect(rgb)
        return self.inner.detect_window(rgb, (0, 0, rgb.shape[1], rgb.shape[0]), size)


def _sum_timing(a: DetectorTiming | None, b: DetectorTiming | None) -> DetectorTiming | None:
    if a is None or b is None:
        return b or a
    return DetectorTiming(
        a.preprocess_ms + b.preprocess_ms,
        a.inference_ms + b.inference_ms,
        a.postprocess_ms + b.postprocess_ms,
    )
