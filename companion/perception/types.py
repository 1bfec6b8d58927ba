"""Value types that cross module boundaries on the per-frame path: frames, intrinsics, detections, truth.

Arrays are not copied when these are built: a frame owns the buffers its source produced.
"""

from __future__ import annotations

from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from companion.compat import Self
from companion.frames import Mat3, Vec3

RgbImage = NDArray[np.uint8]  # H x W x 3, RGB order (not OpenCV's BGR)
DepthImage = NDArray[np.float32]  # H x W, metres along the optical axis, 0 = invalid


@dataclass(frozen=True, slots=True)
class Intrinsics:
    """Pinhole intrinsics of the colour camera (depth is aligned to it), pixels."""

    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    width_px: int
    height_px: int

    @property
    def K(self) -> Mat3:
        """The 3x3 camera matrix."""
        return np.array([[self.fx_px, 0.0, self.cx_px], [0.0, self.fy_px, self.cy_px], [0.0, 0.0, 1.0]])

    @classmethod
    def from_hfov(cls, width_px: int, height_px: int, hfov_deg: float) -> Intrinsics:
        """Square pixels, principal point at the centre, focal length from the horizontal field of view."""
        f = (width_px / 2.0) / np.tan(np.radians(hfov_deg) / 2.0)
        return cls(float(f), float(f), (width_px - 1) / 2.0, (height_px - 1) / 2.0, width_px, height_px)


@dataclass(frozen=True, slots=True)
class GroundTruth:
    """What the simulator knows about the leader at a frame's timestamp (never fed to the service's estimate).

    ``box_xyxy_px`` is the tight box of the leader's *visible* pixels, None when none are visible.
    """

    box_xyxy_px: tuple[float, float, float, float] | None
    visible_fraction: float
    #: Leader centre in the camera frame (x right, y down, z forward), m.
    p_cam_leader_m: Vec3
    #: Leader yaw minus follower yaw, rad, wrapped to [-pi, pi).
    yaw_rel_rad: float
    #: Follower and leader true poses in local NED at the frame's timestamp.
    p_ned_follower_m: Vec3 | None = None
    p_ned_leader_m: Vec3 | None = None
    q_ned_follower_wxyz: NDArray[np.float64] | None = None


@dataclass(frozen=True, slots=True)
class RgbdFrame:
    """One aligned colour + depth frame with its capture time on the source's clock (s)."""

    rgb: RgbImage
    depth_m: DepthImage
    intrinsics: Intrinsics
    stamp_s: float
    seq: int = 0
    truth: GroundTruth | None = None


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
    :class:`companion.errors.CameraError` with one clear line. Iteration ends at the end of a recording
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
