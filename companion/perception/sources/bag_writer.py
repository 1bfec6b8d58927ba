"""Frames to a RealSense-SDK-format ``.bag`` (depth aligned to colour), which the SDK's own playback reads.

``companion record --out X.bag`` writes with :class:`RealSenseBagWriter`; tests write fixtures with
:func:`write_realsense_bag`. The format is :mod:`companion.perception.sources.bag_format`'s.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterable
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np

from companion.kernel.camera import Intrinsics, RgbdFrame
from companion.kernel.compat import Self
from companion.kernel.errors import CameraError
from companion.perception.sources.bag_format import FILE_VERSION, STATIC_TIME_NS, typestore
from companion.perception.sources.file import depth_to_u16


class RealSenseBagWriter:
    """Writes frames as a RealSense-SDK-format bag (depth aligned to colour), one :meth:`write` at a time.

    Header stamps carry ``stamp_s`` (to the nanosecond), header seq carries ``seq``. Depth is stored as
    mono16 in ``depth_scale_m`` units, so depth reads back rounded to that unit. The SDK's player
    (pyrealsense2) and :class:`BagSource` both read the result.
    """

    def __init__(
        self,
        path: Path,
        *,
        fps: int = 30,
        device_name: str = "Intel RealSense D435I",
        depth_scale_m: float = 0.001,
    ) -> None:
        self.path = path
        self.fps = fps
        self.device_name = device_name
        self.depth_scale_m = depth_scale_m
        self.frames_written = 0
        self._ts: Any = None
        self._writer: Any = None
        self._conns: dict[str, Any] = {}
        self._intr: Intrinsics | None = None

    def __enter__(self) -> Self:
        from rosbags.rosbag1 import Writer  # noqa: PLC0415

        self._ts = typestore()
        with contextlib.suppress(FileNotFoundError):
            self.path.unlink()
        self._writer = Writer(self.path)
        self._writer.open()
        T = self._ts.types
        kv = T["diagnostic_msgs/msg/KeyValue"]
        t0 = STATIC_TIME_NS
        self._put("/file_version", "std_msgs/msg/UInt32", T["std_msgs/msg/UInt32"](data=FILE_VERSION), t0)
        for key, value in (
            ("Name", self.device_name),
            ("Serial Number", "000000000000"),
            ("Product Line", "D400"),
        ):
            self._put("/device_0/info", "diagnostic_msgs/msg/KeyValue", kv(key=key, value=value), t0)
        for s, name in ((0, "Stereo Module"), (1, "RGB Camera")):
            self._put(
                f"/device_0/sensor_{s}/info", "diagnostic_msgs/msg/KeyValue", kv(key="Name", value=name), t0
            )
        units = T["std_msgs/msg/Float32"](data=self.depth_scale_m)
        self._put("/device_0/sensor_0/option/Depth Units/value", "std_msgs/msg/Float32", units, t0)
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None

    def _put(self, topic: str, msgtype: str, msg: Any, t_ns: int) -> None:
        if topic not in self._conns:
            self._conns[topic] = self._writer.add_connection(topic, msgtype, typestore=self._ts)
        self._writer.write(self._conns[topic], t_ns, self._ts.serialize_ros1(msg, msgtype))

    def _header(self, seq: int, t_ns: int) -> Any:
        T = self._ts.types
        stamp = T["builtin_interfaces/msg/Time"](sec=t_ns // 10**9, nanosec=t_ns % 10**9)
        return T["std_msgs/msg/Header"](seq=seq, stamp=stamp, frame_id="0")

    def _write_streams(self, intr: Intrinsics) -> None:
        T = self._ts.types
        t0 = STATIC_TIME_NS
        for s, stream, enc in BAG_STREAMS:
            prefix = f"/device_0/sensor_{s}/{stream}"
            info = T["realsense_msgs/msg/StreamInfo"](fps=self.fps, encoding=enc, is_recommended=True)
            self._put(f"{prefix}/info", "realsense_msgs/msg/StreamInfo", info, t0)
            cam = T["sensor_msgs/msg/CameraInfo"](
                header=self._header(0, 0),
                height=intr.height_px,
                width=intr.width_px,
                distortion_model="Brown Conrady",
                D=np.zeros(5),
                K=intr.K.ravel(),
                R=np.eye(3).ravel(),
                P=np.zeros(12),
                binning_x=0,
                binning_y=0,
                roi=T["sensor_msgs/msg/RegionOfInterest"](
                    x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
                ),
            )
            self._put(f"{prefix}/info/camera_info", "sensor_msgs/msg/CameraInfo", cam, t0)
            tf = T["geometry_msgs/msg/Transform"](
                translation=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                rotation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
            )
            self._put(f"{prefix}/tf/0", "geometry_msgs/msg/Transform", tf, t0)

    def write(self, frame: RgbdFrame) -> None:
        """Append one frame (stamps must be >= 0 and the intrinsics constant)."""
        if self._writer is None:
            raise CameraError("bag writer: write() outside `with RealSenseBagWriter(...)`")
        if frame.stamp_s < 0:
            raise ValueError(f"bag stamps must be >= 0 (frame {frame.seq}: {frame.stamp_s})")
        intr = frame.intrinsics
        if self._intr is None:
            self._write_streams(intr)
            self._intr = intr
        elif intr != self._intr:
            raise ValueError(f"intrinsics changed at frame {frame.seq}; start a new bag")
        T = self._ts.types
        kv = T["diagnostic_msgs/msg/KeyValue"]
        t_ns = max(round(frame.stamp_s * 1e9), STATIC_TIME_NS + 1)
        depth_bytes = np.frombuffer(
            depth_to_u16(frame.depth_m, self.depth_scale_m).astype("<u2").tobytes(), np.uint8
        )
        rgb = np.ascontiguousarray(frame.rgb).reshape(-1)
        for s, stream, enc in BAG_STREAMS:
            data, step = (depth_bytes, 2 * intr.width_px) if enc == "mono16" else (rgb, 3 * intr.width_px)
            img = T["sensor_msgs/msg/Image"](
                header=self._header(frame.seq, t_ns),
                height=intr.height_px,
                width=intr.width_px,
                encoding=enc,
                is_bigendian=0,
                step=step,
                data=data,
            )
            prefix = f"/device_0/sensor_{s}/{stream}"
            self._put(f"{prefix}/image/data", "sensor_msgs/msg/Image", img, t_ns)
            for key, value in (("Frame Counter", str(frame.seq)), ("timestamp_domain", "System Time")):
                self._put(
                    f"{prefix}/image/metadata", "diagnostic_msgs/msg/KeyValue", kv(key=key, value=value), t_ns
                )
        self.frames_written += 1


BAG_STREAMS = ((0, "Depth_0", "mono16"), (1, "Color_0", "rgb8"))


def write_realsense_bag(path: Path, frames: Iterable[RgbdFrame], *, fps: int = 30) -> int:
    """Write frames to a RealSense bag with :class:`RealSenseBagWriter`; returns the frame count."""
    with RealSenseBagWriter(path, fps=fps) as writer:
        for frame in frames:
            writer.write(frame)
        return writer.frames_written
