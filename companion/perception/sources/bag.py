"""RealSense recordings as a frame source (ROS1 ``.bag`` and rosbag2 ``.db3``), and ``.bag`` writing.

The SDK's current rosbag2 format is read by :mod:`companion.perception.sources.rosbag2`. Older SDKs
record a ROS1 bag with one topic family per stream (file format version 3)::

    /file_version                                         std_msgs/UInt32 (3)
    /device_0/info, /device_0/sensor_<s>/info             diagnostic_msgs/KeyValue (Name, ...)
    /device_0/sensor_<s>/<Depth|Color>_<i>/info            realsense_msgs/StreamInfo (fps, encoding)
    /device_0/sensor_<s>/<Depth|Color>_<i>/info/camera_info  sensor_msgs/CameraInfo (intrinsics K)
    /device_0/sensor_<s>/<Depth|Color>_<i>/tf/<group>      geometry_msgs/Transform (reference -> stream)
    /device_0/sensor_<s>/<Depth|Color>_<i>/image/data      sensor_msgs/Image (mono16 depth, rgb8 colour)
    /device_0/sensor_<s>/<Depth|Color>_<i>/image/metadata  diagnostic_msgs/KeyValue
    /device_0/sensor_<s>/option/Depth Units/value          std_msgs/Float32 (m per depth unit)

:class:`BagSource` reads it with ``rosbags`` (pure Python; no librealsense needed), pairs each colour
image with the depth image nearest in time, and aligns depth to the colour camera when the recording
kept them separate (as the SDK does). Stamps are the images' header stamps (the frame timestamps).
:mod:`companion.perception.sources.bag_writer` writes the same layout with depth already aligned to
colour; the SDK's own playback (pyrealsense2) reads it. Decoding and the message types are in
:mod:`companion.perception.sources.bag_format`.
"""

from __future__ import annotations

import asyncio
from collections import deque
from collections.abc import AsyncIterator, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np

from companion.kernel.camera import Intrinsics, RgbdFrame
from companion.kernel.clock import Clock
from companion.kernel.compat import Self
from companion.kernel.errors import CameraError
from companion.kernel.frames import Mat3, R_from_quat, Vec3
from companion.perception.sources import rosbag2
from companion.perception.sources._pacing import Pacer
from companion.perception.sources.bag_format import (
    STREAM_TOPIC,
    align_depth_to_color,
    decode_depth_units,
    decode_rgb,
    header_stamp_s,
    intrinsics_of,
    typestore,
)
from companion.perception.sources.rosbag2 import Db3Image, Db3Recording


@dataclass(frozen=True, slots=True)
class _StreamLayout:
    depth_topic: str
    color_topic: str
    depth_intr: Intrinsics
    color_intr: Intrinsics
    depth_scale_m: float
    #: None when depth is already aligned to colour (same intrinsics, identity extrinsics).
    R_color_depth: Mat3 | None
    t_color_depth_m: Vec3 | None
    pair_tolerance_s: float


def _read_layout(reader: Any, ts: Any, path: Path) -> _StreamLayout:
    """Find the depth and colour streams of a RealSense bag and their calibration."""
    streams: dict[str, dict[str, Any]] = {"Depth": {}, "Color": {}}
    depth_units = 0.001
    wanted = []
    for conn in reader.connections:
        m = STREAM_TOPIC.match(conn.topic)
        static = m is not None and m.group(5) not in ("image/data", "image/metadata")
        if static or (m is None and conn.topic.endswith("/option/Depth Units/value")):
            wanted.append(conn)
        if m is not None and m.group(5) == "image/data":
            streams[m.group(3)].setdefault("topic", conn.topic)
    if "topic" not in streams["Depth"] or "topic" not in streams["Color"]:
        raise CameraError(
            f"bag source: {path} is not a RealSense RGB-D recording (no Depth and Color images)"
        )
    for conn, _t, raw in reader.messages(connections=wanted):
        msg = ts.deserialize_ros1(raw, conn.msgtype)
        m = STREAM_TOPIC.match(conn.topic)
        if m is None:
            depth_units = float(msg.data)
            continue
        kind, rest = m.group(3), m.group(5)
        prefix = conn.topic[: -len(rest) - 1]
        if prefix + "/image/data" != streams[kind]["topic"]:
            continue  # another stream of the same kind (e.g. a second colour stream)
        if rest == "info/camera_info":
            streams[kind]["intr"] = intrinsics_of(msg)
        elif rest == "info":
            streams[kind]["fps"] = float(msg.fps)
        elif rest.startswith("tf/"):
            q = msg.rotation
            R = R_from_quat((q.w, q.x, q.y, q.z))
            t = np.array([msg.translation.x, msg.translation.y, msg.translation.z], dtype=np.float64)
            streams[kind]["tf"] = (R, t)
    for kind in ("Depth", "Color"):
        if "intr" not in streams[kind]:
            raise CameraError(f"bag source: {path} has no camera_info for its {kind} stream")
    depth_intr: Intrinsics = streams["Depth"]["intr"]
    color_intr: Intrinsics = streams["Color"]["intr"]
    eye = (np.eye(3), np.zeros(3))
    R_d, t_d = streams["Depth"].get("tf", eye)
    R_c, t_c = streams["Color"].get("tf", eye)
    R_cd = R_c @ R_d.T
    t_cd = t_c - R_cd @ t_d
    aligned = depth_intr == color_intr and np.allclose(R_cd, np.eye(3), atol=1e-9) and np.allclose(t_cd, 0.0)
    fps = min(streams["Depth"].get("fps", 30.0) or 30.0, streams["Color"].get("fps", 30.0) or 30.0)
    return _StreamLayout(
        depth_topic=streams["Depth"]["topic"],
        color_topic=streams["Color"]["topic"],
        depth_intr=depth_intr,
        color_intr=color_intr,
        depth_scale_m=depth_units,
        R_color_depth=None if aligned else R_cd,
        t_color_depth_m=None if aligned else t_cd,
        pair_tolerance_s=0.5 / fps,
    )


def _db3_layout(rec: Db3Recording) -> _StreamLayout:
    """The layout of a rosbag2 recording, in the terms of a ROS1 one (extrinsics: reference -> stream)."""
    d, c = rec.stream("Depth"), rec.stream("Color")
    eye = (np.eye(3), np.zeros(3))
    R_d, t_d = d.get("tf", eye)
    R_c, t_c = c.get("tf", eye)
    R_cd = R_c @ R_d.T
    t_cd = t_c - R_cd @ t_d
    aligned = d["intr"] == c["intr"] and np.allclose(R_cd, np.eye(3), atol=1e-9) and np.allclose(t_cd, 0.0)
    fps = min(d.get("fps", 30.0) or 30.0, c.get("fps", 30.0) or 30.0)
    return _StreamLayout(
        depth_topic=str(d["data_name"]),
        color_topic=str(c["data_name"]),
        depth_intr=d["intr"],
        color_intr=c["intr"],
        depth_scale_m=rec.depth_units_m,
        R_color_depth=None if aligned else R_cd,
        t_color_depth_m=None if aligned else t_cd,
        pair_tolerance_s=0.5 / fps,
    )


class BagSource:
    """Plays a RealSense ``.bag`` as a :class:`FrameSource` (see the module docstring).

    ``seq`` is the colour image's frame number. Looping shifts later passes' stamps so they keep
    increasing; ``realtime`` paces frames by their stamps.
    """

    def __init__(
        self, path: Path, *, realtime: bool = False, loop: bool = False, clock: Clock | None = None
    ) -> None:
        self.path = path
        self.loop = loop
        self._pacer = Pacer(realtime=realtime, clock=clock)
        self._reader: Any = None
        self._ts: Any = None
        self._db3: Db3Recording | None = None
        self.layout: _StreamLayout | None = None

    @property
    def intrinsics(self) -> Intrinsics | None:
        return None if self.layout is None else self.layout.color_intr

    def _open(self) -> None:
        try:
            from rosbags.rosbag1 import Reader, ReaderError  # noqa: PLC0415
        except ImportError:
            raise CameraError(
                "bag source: the rosbags library is missing (pip install 'wingman[realsense]')"
            ) from None
        if not self.path.is_file():
            raise CameraError(f"bag source: {self.path} does not exist")
        if self.path.suffix.lower() == ".db3":
            db3 = Db3Recording(self.path)
            try:
                self.layout = _db3_layout(db3)
            except BaseException:
                db3.close()
                raise
            self._db3 = db3
            return
        self._ts = typestore()
        reader = Reader(self.path)
        try:
            reader.open()
        except ReaderError as exc:
            raise CameraError(f"bag source: {self.path} is not a readable ROS1 bag ({exc})") from None
        try:
            self.layout = _read_layout(reader, self._ts, self.path)
        except BaseException:
            reader.close()
            raise
        self._reader = reader

    async def __aenter__(self) -> Self:
        await asyncio.to_thread(self._open)
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if self._reader is not None:
            self._reader.close()
            self._reader = None
        if self._db3 is not None:
            self._db3.close()
            self._db3 = None

    def __aiter__(self) -> AsyncIterator[RgbdFrame]:
        return self._frames()

    def _images(self) -> Iterator[tuple[bool, float, Any]]:
        """(is colour, stamp, message) for every depth and colour image, in recording order."""
        layout, reader, ts = self.layout, self._reader, self._ts
        if self._db3 is not None:
            for is_color, img in self._db3.images():
                yield is_color, img.stamp_s, img
            return
        if layout is None or reader is None:
            raise CameraError("bag source: iterated before it was opened (use `async with`)")
        conns = [c for c in reader.connections if c.topic in (layout.depth_topic, layout.color_topic)]
        for conn, _t, raw in reader.messages(connections=conns):
            msg = ts.deserialize_ros1(raw, conn.msgtype)
            yield conn.topic == layout.color_topic, header_stamp_s(msg.header), msg

    def _pairs(self) -> Iterator[tuple[Any, Any]]:
        """(colour, depth) messages, each colour with the depth nearest in time within tolerance."""
        layout = self.layout
        if layout is None:
            raise CameraError("bag source: iterated before it was opened (use `async with`)")
        pending: deque[tuple[float, Any]] = deque()
        prev: tuple[float, Any] | None = None
        tol = layout.pair_tolerance_s
        for is_color, stamp, msg in self._images():
            if is_color:
                pending.append((stamp, msg))
                continue
            while pending and pending[0][0] <= stamp:
                c_stamp, c_msg = pending.popleft()
                best = (stamp, msg)
                if prev is not None and abs(prev[0] - c_stamp) < abs(stamp - c_stamp):
                    best = prev
                if abs(best[0] - c_stamp) <= tol:
                    yield c_msg, best[1]
            prev = (stamp, msg)
        for c_stamp, c_msg in pending:
            if prev is not None and abs(prev[0] - c_stamp) <= tol:
                yield c_msg, prev[1]

    def _frame(self, color: Any, depth: Any, stamp_shift_s: float) -> RgbdFrame:
        layout = self.layout
        if layout is None:
            raise CameraError("bag source: iterated before it was opened (use `async with`)")
        if isinstance(color, Db3Image):
            rgb, units = rosbag2.decode_color(color), rosbag2.decode_depth_units(depth)
            stamp_s, seq = color.stamp_s, color.seq
        else:
            rgb, units = decode_rgb(color), decode_depth_units(depth)
            stamp_s, seq = header_stamp_s(color.header), int(color.header.seq)
        depth_m = units.astype(np.float32) * np.float32(layout.depth_scale_m)
        if layout.R_color_depth is not None and layout.t_color_depth_m is not None:
            depth_m = align_depth_to_color(
                depth_m, layout.depth_intr, layout.color_intr, layout.R_color_depth, layout.t_color_depth_m
            )
        intr = layout.color_intr
        if rgb.shape[:2] != (intr.height_px, intr.width_px) or depth_m.shape != rgb.shape[:2]:
            raise CameraError(f"bag source: image sizes disagree with camera_info at frame {seq}")
        return RgbdFrame(rgb, depth_m, intr, stamp_s + stamp_shift_s, seq)

    async def _frames(self) -> AsyncIterator[RgbdFrame]:
        shift_s = 0.0
        seq_shift = 0
        while True:
            pairs = self._pairs()
            first_s = last_s = None
            last_seq = 0
            while (pair := await asyncio.to_thread(next, pairs, None)) is not None:
                frame = await asyncio.to_thread(self._frame, pair[0], pair[1], shift_s)
                if seq_shift:
                    frame = RgbdFrame(
                        frame.rgb, frame.depth_m, frame.intrinsics, frame.stamp_s, frame.seq + seq_shift
                    )
                first_s = frame.stamp_s if first_s is None else first_s
                last_s, last_seq = frame.stamp_s, frame.seq
                await self._pacer.wait(frame.stamp_s)
                yield frame
            if not self.loop or first_s is None or last_s is None:
                return
            assert self.layout is not None  # noqa: S101 (opened: pairs were read)
            shift_s += last_s - first_s + 2.0 * self.layout.pair_tolerance_s
            seq_shift = last_seq + 1
