"""RealSense recordings as the SDK writes them today: a rosbag2 SQLite file (``.db3``, file version 4).

librealsense 2.55 and later record to one ``.db3`` with no ``metadata.yaml``; every message is CDR::

    /file_version                                            std_msgs/UInt32 (4)
    /device_0/sensor_<s>/<Depth|Color>_<i>/info               std_msgs/String  "encoding=Z16;fps=30"
    /device_0/sensor_<s>/<Depth|Color>_<i>/camera_info        std_msgs/String  "width=..;fx=..;ppx=..;..."
    /device_0/sensor_<s>/<Depth|Color>_<i>/tf/ref_<n>         std_msgs/String  "rotation=<9>;translation=<3>"
    /device_0/sensor_<s>/option/Depth_Units/value             std_msgs/String  "0.001000"
    /device_0/sensor_<s>/Depth_<i>/image/data/compressedDepth sensor_msgs/CompressedImage (16UC1 PNG)
    /device_0/sensor_<s>/Color_<i>/image/data/compressed      sensor_msgs/CompressedImage (PNG or JPEG)
    /device_0/sensor_<s>/<Depth|Color>_<i>/image/metadata     std_msgs/String  "Frame number=..;..."

:class:`Db3Recording` reads it with the standard library's ``sqlite3`` and ``rosbags``' CDR decoder (no
librealsense), and hands :class:`~companion.perception.sources.bag.BagSource` the same stream layout and
(colour, depth) messages as a ROS1 ``.bag``.
"""

from __future__ import annotations

import re
import sqlite3
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from companion.kernel.camera import Intrinsics, RgbImage
from companion.kernel.errors import CameraError

_STREAM = re.compile(r"^/device_(\d+)/sensor_(\d+)/(Depth|Color)_(\d+)/(.+)$")
#: compressed_depth_image_transport's header before the PNG: format (int32) and two float32 parameters.
_DEPTH_HEADER_BYTES = 12


@dataclass(frozen=True, slots=True)
class Db3Image:
    """One image message: when, which frame, and its compressed bytes."""

    stamp_s: float
    seq: int
    format: str
    data: bytes


def _fields(text: str) -> dict[str, str]:
    """``"a=1;b=x"`` -> ``{"a": "1", "b": "x"}``."""
    return dict(part.split("=", 1) for part in text.split(";") if "=" in part)


def _intrinsics(text: str) -> Intrinsics:
    f = _fields(text)
    return Intrinsics(
        float(f["fx"]), float(f["fy"]), float(f["ppx"]), float(f["ppy"]), int(f["width"]), int(f["height"])
    )


def _transform(text: str) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The SDK's extrinsics string: rotation column-major (as ``rs2_extrinsics``), translation in m."""
    f = _fields(text)
    rot = np.array([float(v) for v in f["rotation"].split(",")], dtype=np.float64).reshape(3, 3).T
    t = np.array([float(v) for v in f["translation"].split(",")], dtype=np.float64)
    return rot, t


class Db3Recording:
    """A RealSense ``.db3``: its streams' calibration, and their image messages in time order."""

    def __init__(self, path: Path) -> None:
        from rosbags.typesys import Stores, get_typestore  # noqa: PLC0415

        self.path = path
        self._ts = get_typestore(Stores.ROS2_HUMBLE)
        try:
            # Opened on one worker thread, read on others, one at a time (the source awaits each read).
            self._db = sqlite3.connect(f"file:{path}?mode=ro", uri=True, check_same_thread=False)
            rows = self._db.execute("SELECT id, name, type FROM topics").fetchall()
        except sqlite3.Error as exc:
            raise CameraError(f"bag source: {path} is not a readable rosbag2 file ({exc})") from None
        self.topics: dict[int, tuple[str, str]] = {int(i): (str(n), str(t)) for i, n, t in rows}
        self.streams: dict[str, dict[str, Any]] = {"Depth": {}, "Color": {}}
        self.depth_units_m = 0.001
        self._read_static()

    def close(self) -> None:
        self._db.close()

    def _decode(self, raw: bytes, msgtype: str) -> Any:
        return self._ts.deserialize_cdr(raw, msgtype)

    def _read_static(self) -> None:
        static = {i: nt for i, nt in self.topics.items() if "/image/" not in nt[0]}
        for tid, (name, msgtype) in static.items():
            row = self._db.execute(
                "SELECT data FROM messages WHERE topic_id = ? ORDER BY timestamp LIMIT 1", (tid,)
            ).fetchone()
            if row is None or msgtype != "std_msgs/msg/String":
                continue
            text = str(self._decode(row[0], msgtype).data)
            if name.endswith("/option/Depth_Units/value"):
                self.depth_units_m = float(text)
                continue
            m = _STREAM.match(name)
            if m is None:
                continue
            kind, rest = m.group(3), m.group(5)
            stream = self.streams[kind].setdefault(name[: -len(rest) - 1], {})
            if rest == "camera_info":
                stream["intr"] = _intrinsics(text)
            elif rest == "info":
                stream["fps"] = float(_fields(text).get("fps", "30") or 30)
            elif rest.startswith("tf/"):
                stream["tf"] = _transform(text)
        for tid, (name, _msgtype) in self.topics.items():
            m = _STREAM.match(name)
            if m is not None and m.group(5).startswith("image/data"):
                stream = self.streams[m.group(3)].setdefault(name[: -len(m.group(5)) - 1], {})
                stream.setdefault("data_topic", tid)
                stream.setdefault("data_name", name)
        for kind in ("Depth", "Color"):
            usable = {p: s for p, s in self.streams[kind].items() if "data_topic" in s and "intr" in s}
            if not usable:
                raise CameraError(
                    f"bag source: {self.path} is not a RealSense RGB-D recording (no {kind} images "
                    "with their calibration)"
                )
            first = sorted(usable)[0]
            self.streams[kind] = usable[first]

    def stream(self, kind: str) -> dict[str, Any]:
        """``intr``, ``fps``, ``tf`` (when recorded) and ``data_topic`` of the Depth or Color stream."""
        return self.streams[kind]

    def images(self) -> Iterator[tuple[bool, Db3Image]]:
        """(is colour, image) for every depth and colour image, in recording order."""
        depth_id, color_id = self.streams["Depth"]["data_topic"], self.streams["Color"]["data_topic"]
        numbers = {depth_id: self._frame_numbers("Depth"), color_id: self._frame_numbers("Color")}
        cur = self._db.execute(
            "SELECT topic_id, timestamp, data FROM messages WHERE topic_id IN (?, ?) ORDER BY timestamp",
            (depth_id, color_id),
        )
        counters = {depth_id: 0, color_id: 0}
        for tid, t_ns, raw in cur:
            msg = self._decode(raw, "sensor_msgs/msg/CompressedImage")
            stamp_s = float(msg.header.stamp.sec) + float(msg.header.stamp.nanosec) * 1e-9
            seq = numbers[tid].get(int(t_ns), counters[tid])
            counters[tid] += 1
            yield tid == color_id, Db3Image(stamp_s, seq, str(msg.format), bytes(msg.data))

    def _frame_numbers(self, kind: str) -> dict[int, int]:
        """Bag timestamp -> frame number, from the stream's metadata (written with the image's timestamp)."""
        name = str(self.streams[kind]["data_name"])
        meta_name = name[: name.index("/image/data")] + "/image/metadata"
        meta_id = next((i for i, (n, _t) in self.topics.items() if n == meta_name), None)
        out: dict[int, int] = {}
        if meta_id is None:
            return out
        for t_ns, raw in self._db.execute(
            "SELECT timestamp, data FROM messages WHERE topic_id = ?", (meta_id,)
        ):
            number = _fields(str(self._decode(raw, "std_msgs/msg/String").data)).get("Frame number", "")
            if number.isdigit():
                out[int(t_ns)] = int(number)
        return out


def decode_color(img: Db3Image) -> RgbImage:
    """A compressed colour image (PNG or JPEG, as the SDK writes it) as H x W x 3 RGB."""
    bgr = cv2.imdecode(np.frombuffer(img.data, dtype=np.uint8), cv2.IMREAD_COLOR)
    if bgr is None:
        raise CameraError(f"bag source: colour frame {img.seq} does not decode ({img.format!r})")
    return np.ascontiguousarray(bgr[..., ::-1])


def decode_depth_units(img: Db3Image) -> NDArray[np.uint16]:
    """A compressedDepth image (16UC1 PNG after a 12-byte header) as H x W uint16 depth units."""
    if "16UC1" not in img.format and "mono16" not in img.format.lower():
        raise CameraError(f"bag source: depth format {img.format!r} is not supported (want 16UC1)")
    png = img.data[_DEPTH_HEADER_BYTES:] if img.data[:1] != b"\x89" else img.data
    depth = cv2.imdecode(np.frombuffer(png, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if depth is None or depth.dtype != np.uint16 or depth.ndim != 2:
        raise CameraError(f"bag source: depth frame {img.seq} does not decode ({img.format!r})")
    return np.asarray(depth, dtype=np.uint16)
