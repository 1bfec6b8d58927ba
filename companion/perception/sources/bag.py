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
:func:`write_realsense_bag` writes the same layout with depth already aligned to colour; the SDK's own
playback (pyrealsense2) reads it.
"""

from __future__ import annotations

import asyncio
import contextlib
import re
from collections import deque
from collections.abc import AsyncIterator, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from companion.kernel.camera import DepthImage, Intrinsics, RgbdFrame, RgbImage
from companion.kernel.clock import Clock
from companion.kernel.compat import Self
from companion.kernel.errors import CameraError
from companion.kernel.frames import Mat3, R_from_quat, Vec3
from companion.perception.sources import rosbag2
from companion.perception.sources._pacing import Pacer
from companion.perception.sources.file import depth_to_u16
from companion.perception.sources.rosbag2 import Db3Image, Db3Recording

FILE_VERSION = 3
_STREAM_TOPIC = re.compile(r"^/device_(\d+)/sensor_(\d+)/(Depth|Color)_(\d+)/(.+)$")
_STREAM_INFO_MSG = "uint32 fps\nstring encoding\nbool is_recommended\n"
#: ROS1 bags refuse a zero time; the SDK writes its static device description at this one.
_STATIC_TIME_NS = 1


def _typestore() -> Any:
    """The ROS1 Noetic type store plus realsense_msgs/StreamInfo (imports rosbags lazily)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore  # noqa: PLC0415

    ts = get_typestore(Stores.ROS1_NOETIC)
    ts.register(get_types_from_msg(_STREAM_INFO_MSG, "realsense_msgs/msg/StreamInfo"))
    return ts


def _stamp_s(header: Any) -> float:
    return float(header.stamp.sec) + float(header.stamp.nanosec) * 1e-9


def _intrinsics(info: Any) -> Intrinsics:
    K = np.asarray(info.K, dtype=np.float64)
    return Intrinsics(float(K[0]), float(K[4]), float(K[2]), float(K[5]), int(info.width), int(info.height))


def decode_depth_units(img: Any) -> NDArray[np.uint16]:
    """A mono16 / 16UC1 / z16 sensor_msgs/Image as an H x W uint16 array (a view where possible)."""
    if img.encoding.lower() not in ("mono16", "16uc1", "z16"):
        raise CameraError(f"bag source: depth encoding {img.encoding!r} is not supported (want mono16)")
    dtype = np.dtype(">u2" if img.is_bigendian else "<u2")
    rows = np.frombuffer(img.data, dtype=np.uint8).reshape(img.height, img.step)[:, : img.width * 2]
    return np.ascontiguousarray(rows).view(dtype).reshape(img.height, img.width).astype(np.uint16, copy=False)


_COLOR_CHANNELS = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "yuv422": 2, "yuyv": 2, "uyvy": 2}


def decode_rgb(img: Any) -> RgbImage:
    """A colour sensor_msgs/Image (rgb8, bgr8, rgba8, bgra8, yuyv, uyvy) as H x W x 3 RGB uint8."""
    enc = img.encoding.lower()
    ch = _COLOR_CHANNELS.get(enc)
    if ch is None:
        raise CameraError(f"bag source: colour encoding {img.encoding!r} is not supported")
    rows = np.frombuffer(img.data, dtype=np.uint8).reshape(img.height, img.step)[:, : img.width * ch]
    px = rows.reshape(img.height, img.width, ch)
    if enc == "rgb8":
        return np.ascontiguousarray(px)
    if enc == "bgr8":
        return np.ascontiguousarray(px[..., ::-1])
    if enc == "rgba8":
        return np.ascontiguousarray(px[..., :3])
    if enc == "bgra8":
        return np.ascontiguousarray(px[..., 2::-1])
    code = cv2.COLOR_YUV2RGB_UYVY if enc == "uyvy" else cv2.COLOR_YUV2RGB_YUYV
    return np.asarray(cv2.cvtColor(np.ascontiguousarray(px), code), dtype=np.uint8)


def align_depth_to_color(
    depth_m: DepthImage,
    depth_intr: Intrinsics,
    color_intr: Intrinsics,
    R_color_depth: Mat3,
    t_color_depth_m: Vec3,
) -> DepthImage:
    """Reproject a depth image into the colour camera (nearest surface wins; unfilled pixels are 0).

    Each valid depth pixel is back-projected, moved by ``p_color = R_color_depth @ p_depth + t`` and
    projected to the nearest colour pixel. Where the colour image is finer than the depth image some
    pixels stay empty, as with any point splat: the pose's robust depth ignores them.
    """
    v, u = np.nonzero(depth_m > 0)
    z = depth_m[v, u].astype(np.float64)
    pts = np.stack(
        [(u - depth_intr.cx_px) / depth_intr.fx_px * z, (v - depth_intr.cy_px) / depth_intr.fy_px * z, z]
    )
    pc = R_color_depth @ pts + t_color_depth_m.reshape(3, 1)
    front = pc[2] > 1e-6
    pc = pc[:, front]
    uc = np.rint(color_intr.fx_px * pc[0] / pc[2] + color_intr.cx_px).astype(np.int64)
    vc = np.rint(color_intr.fy_px * pc[1] / pc[2] + color_intr.cy_px).astype(np.int64)
    inside = (uc >= 0) & (uc < color_intr.width_px) & (vc >= 0) & (vc < color_intr.height_px)
    lin = vc[inside] * color_intr.width_px + uc[inside]
    zc = pc[2, inside]
    order = np.lexsort((zc, lin))  # by pixel, nearest first
    first = np.unique(lin[order], return_index=True)[1]
    out = np.zeros(color_intr.height_px * color_intr.width_px, dtype=np.float32)
    out[lin[order][first]] = zc[order][first]
    return out.reshape(color_intr.height_px, color_intr.width_px)


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
        m = _STREAM_TOPIC.match(conn.topic)
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
        m = _STREAM_TOPIC.match(conn.topic)
        if m is None:
            depth_units = float(msg.data)
            continue
        kind, rest = m.group(3), m.group(5)
        prefix = conn.topic[: -len(rest) - 1]
        if prefix + "/image/data" != streams[kind]["topic"]:
            continue  # another stream of the same kind (e.g. a second colour stream)
        if rest == "info/camera_info":
            streams[kind]["intr"] = _intrinsics(msg)
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
        self._ts = _typestore()
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
            yield conn.topic == layout.color_topic, _stamp_s(msg.header), msg

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
            stamp_s, seq = _stamp_s(color.header), int(color.header.seq)
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

        self._ts = _typestore()
        with contextlib.suppress(FileNotFoundError):
            self.path.unlink()
        self._writer = Writer(self.path)
        self._writer.open()
        T = self._ts.types
        kv = T["diagnostic_msgs/msg/KeyValue"]
        t0 = _STATIC_TIME_NS
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
        t0 = _STATIC_TIME_NS
        for s, stream, enc in _BAG_STREAMS:
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
        t_ns = max(round(frame.stamp_s * 1e9), _STATIC_TIME_NS + 1)
        depth_bytes = np.frombuffer(
            depth_to_u16(frame.depth_m, self.depth_scale_m).astype("<u2").tobytes(), np.uint8
        )
        rgb = np.ascontiguousarray(frame.rgb).reshape(-1)
        for s, stream, enc in _BAG_STREAMS:
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


_BAG_STREAMS = ((0, "Depth_0", "mono16"), (1, "Color_0", "rgb8"))


def write_realsense_bag(path: Path, frames: Iterable[RgbdFrame], *, fps: int = 30) -> int:
    """Write frames to a RealSense bag with :class:`RealSenseBagWriter`; returns the frame count."""
    with RealSenseBagWriter(path, fps=fps) as writer:
        for frame in frames:
            writer.write(frame)
        return writer.frames_written
