"""Value types of the service's per-frame path: detections, the detect stage, the frame source protocol.

Frames, intrinsics and ground truth are :mod:`companion.kernel.camera`'s (the simulator makes them too).
"""

from __future__ import annotations

from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any, Protocol

from companion.kernel.camera import RgbdFrame, RgbImage
from companion.kernel.compat import Self


@dataclass(frozen=True, slots=True)
class Detection:
    """A detector output box in pixels of the original frame, with its confidence in [0, 1]."""

    box_xyxy_px: tuple[float, float, float, float]
    score: float
    #: Network input px per frame px the box was found at (0.5: a 640 px frame at 320; ~1.5: the window).
    #: Box tightness depends on it, so range from size is calibrated per scale.
    scale: float = 1.0

    @property
    def center_px(self) -> tuple[float, float]:
        x0, y0, x1, y1 = self.box_xyxy_px
        return (x0 + x1) / 2.0, (y0 + y1) / 2.0

    @property
    def size_px(self) -> tuple[float, float]:
        x0, y0, x1, y1 = self.box_xyxy_px
        return x1 - x0, y1 - y0


@dataclass(frozen=True, slots=True)
class DetectorTiming:
    """Per-stage time of one detector call, ms."""

    preprocess_ms: float
    inference_ms: float
    postprocess_ms: float


@dataclass(slots=True)
class DetectorResult:
    """Detections of one frame, best first, with the time each stage took."""

    detections: list[Detection] = field(default_factory=list)
    timing: DetectorTiming | None = None


def _no_feedback(_track: Any) -> None:
    return None


@dataclass(frozen=True, slots=True)
class DetectStage:
    """The per-frame detection step and its feedback.

    ``detect`` runs on a frame; ``after_track`` gets the tracker's state for that frame (a
    :class:`companion.estimation.tracker.TrackState`) before the next ``detect``, so a detector can look
    where the tracked leader is (:mod:`companion.perception.detector.roi`).
    """

    detect: Callable[[RgbdFrame], DetectorResult]
    after_track: Callable[[Any], None] = _no_feedback
    description: str = ""


class Detector(Protocol):
    """Finds the leader in an RGB image. Implementations load weights once and are not thread-safe."""

    def detect(self, rgb: RgbImage) -> DetectorResult: ...


class FrameSource(Protocol):
    """An async iterator of RGB-D frames; an async context manager that owns the device or file.

    ``async with source: async for frame in source: ...``. Opening a missing device or file raises
    :class:`companion.kernel.errors.CameraError` with one clear line. Iteration ends at the end of a recording
    (unless looping) and never yields a frame twice.
    """

    async def __aenter__(self) -> Self: ...

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None: ...

    def __aiter__(self) -> AsyncIterator[RgbdFrame]: ...
