"""Live Intel RealSense D435i frames through pyrealsense2: depth aligned to colour, device intrinsics.

Opening fails with one :class:`CameraError` line when pyrealsense2 or its system library (libusb-1.0)
is missing, when no device is connected, or when the device refuses the requested mode. Frames are
waited for in a worker thread (the SDK blocks). Stamps are the host's monotonic clock when the frameset
arrives: the SDK's own timestamps run on the device clock, which telemetry does not share, so attitude
lookups would be off by an unknown offset; arrival time is late by the transfer (a few ms) instead.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator
from types import TracebackType
from typing import Any

import numpy as np

from companion.config import CameraConfig
from companion.kernel.camera import Intrinsics, RgbdFrame
from companion.kernel.compat import Self
from companion.kernel.errors import CameraError

#: How long one wait for a frameset may take before the camera counts as stalled, ms.
_WAIT_TIMEOUT_MS = 2000


def import_pyrealsense2() -> Any:
    """The pyrealsense2 module, or a one-line CameraError saying what is missing."""
    try:
        import pyrealsense2  # noqa: PLC0415
    except ImportError as exc:
        if "libusb" in str(exc):
            raise CameraError(
                "realsense: pyrealsense2 cannot load libusb-1.0 (apt-get install libusb-1.0-0)"
            ) from None
        raise CameraError(
            "realsense: pyrealsense2 is not installed (pip install 'wingman[realsense]')"
        ) from None
    return pyrealsense2


class RealSenseSource:
    """A live D435/D435i as a :class:`FrameSource` (colour RGB8 + Z16 depth aligned to colour)."""

    def __init__(self, cfg: CameraConfig) -> None:
        self.cfg = cfg
        self._rs: Any = None
        self._pipeline: Any = None
        self._align: Any = None
        self._depth_scale_m = 0.001
        self.intrinsics: Intrinsics | None = None
        self.device_name = ""

    def _start(self) -> None:
        rs = import_pyrealsense2()
        self._rs = rs
        devices = rs.context().query_devices()
        if len(devices) == 0:
            raise CameraError("realsense: no RealSense device found (is it plugged in, with the udev rules?)")
        cfg = self.cfg
        config = rs.config()
        config.enable_stream(rs.stream.depth, cfg.width_px, cfg.height_px, rs.format.z16, round(cfg.fps))
        config.enable_stream(rs.stream.color, cfg.width_px, cfg.height_px, rs.format.rgb8, round(cfg.fps))
        pipeline = rs.pipeline()
        try:
            profile = pipeline.start(config)
        except RuntimeError as exc:
            raise CameraError(
                f"realsense: cannot stream {cfg.width_px}x{cfg.height_px}@{cfg.fps:g} ({exc})"
            ) from None
        self._pipeline = pipeline
        device = profile.get_device()
        self.device_name = str(device.get_info(rs.camera_info.name))
        depth_sensor = device.first_depth_sensor()
        self._depth_scale_m = float(depth_sensor.get_depth_scale())
        if depth_sensor.supports(rs.option.visual_preset):
            preset = getattr(rs.rs400_visual_preset, cfg.preset)
            depth_sensor.set_option(rs.option.visual_preset, float(preset))
        if depth_sensor.supports(rs.option.emitter_enabled):
            depth_sensor.set_option(rs.option.emitter_enabled, 1.0)
        color_profile = profile.get_stream(rs.stream.color).as_video_stream_profile()
        k = color_profile.get_intrinsics()
        self.intrinsics = Intrinsics(float(k.fx), float(k.fy), float(k.ppx), float(k.ppy), k.width, k.height)
        self._align = rs.align(rs.stream.color)

    def _stop(self) -> None:
        if self._pipeline is not None:
            self._pipeline.stop()
            self._pipeline = None

    async def __aenter__(self) -> Self:
        await asyncio.to_thread(self._start)
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await asyncio.to_thread(self._stop)

    def __aiter__(self) -> AsyncIterator[RgbdFrame]:
        return self._frames()

    def _next(self, seq: int) -> RgbdFrame:
        if self._pipeline is None or self.intrinsics is None:
            raise CameraError("realsense: iterated before it was opened (use `async with`)")
        ok, frames = self._pipeline.try_wait_for_frames(_WAIT_TIMEOUT_MS)
        stamp_s = time.monotonic()
        if not ok:
            raise CameraError(f"realsense: no frames for {_WAIT_TIMEOUT_MS} ms (camera stalled or unplugged)")
        aligned = self._align.process(frames)
        depth, color = aligned.get_depth_frame(), aligned.get_color_frame()
        rgb = np.asanyarray(color.get_data()).copy()
        depth_m = np.asanyarray(depth.get_data()).astype(np.float32) * np.float32(self._depth_scale_m)
        return RgbdFrame(rgb, depth_m, self.intrinsics, stamp_s, seq)

    async def _frames(self) -> AsyncIterator[RgbdFrame]:
        seq = 0
        while True:
            yield await asyncio.to_thread(self._next, seq)
            seq += 1
