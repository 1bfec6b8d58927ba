"""MCAP recordings as a frame source: the service's flight logs, or any RGB-D recording in Foxglove's schemas.

A frame is the colour image (``foxglove.CompressedImage``, JPEG or PNG, or ``foxglove.RawImage`` rgb8 /
bgr8), the depth image logged at the same instant (``foxglove.RawImage`` 16UC1 millimetres or 32FC1
metres, on a topic with ``depth`` in its name; none: a frame without depth) and the newest
``foxglove.CameraCalibration`` (its K). Messages are read in log-time order and grouped by log time, as the
service writes them (:mod:`companion.viz`). Of several cameras (a formation's log) the first colour topic in
the file is played. A flight log's ``/perception/frame`` records give each frame its live sequence number
and the follower's attitude at the frame (:attr:`McapSource.attitude`, for the tracker's NED frame).

Stamps are the messages' own timestamps, s. Protobuf messages are decoded with the schema each file carries
(:func:`protobuf_class`), so no generated code is needed.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from types import TracebackType
from typing import IO, Any

import cv2
import numpy as np

from companion.kernel.camera import Intrinsics, RgbdFrame
from companion.kernel.clock import Clock
from companion.kernel.compat import Self
from companion.kernel.errors import CameraError
from companion.perception.sources._pacing import Pacer

COMPRESSED = "foxglove.CompressedImage"
RAW = "foxglove.RawImage"
CALIBRATION = "foxglove.CameraCalibration"
#: The service's per-frame record (JSON): seq, stamp, detections, attitude.
PERCEPTION_SUFFIX = "/perception/frame"


def protobuf_class(schema_name: str, schema_data: bytes) -> Any:
    """The message class of a protobuf schema as MCAP and Foxglove carry it (a FileDescriptorSet)."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory  # noqa: PLC0415

    fds = descriptor_pb2.FileDescriptorSet.FromString(schema_data)
    pool = descriptor_pool.DescriptorPool()
    for fd in fds.file:
        pool.Add(fd)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(schema_name))


def _stamp_s(msg: Any) -> float:
    return float(msg.timestamp.seconds) + 1e-9 * float(msg.timestamp.nanos)


def decode_colour(msg: Any, schema: str) -> np.ndarray:
    """RGB pixels (H x W x 3, uint8) of a CompressedImage or an rgb8/bgr8 RawImage."""
    if schema == COMPRESSED:
        bgr = cv2.imdecode(np.frombuffer(msg.data, np.uint8), cv2.IMREAD_COLOR)
        if bgr is None:
            raise CameraError(f"mcap source: an image in {msg.format!r} could not be decoded")
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    if msg.encoding not in ("rgb8", "bgr8"):
        raise CameraError(f"mcap source: colour encoding {msg.encoding!r} (expected rgb8 or bgr8)")
    img = np.frombuffer(msg.data, np.uint8).reshape(msg.height, msg.step)[:, : msg.width * 3]
    img = img.reshape(msg.height, msg.width, 3)
    return np.ascontiguousarray(img[:, :, ::-1] if msg.encoding == "bgr8" else img)


def decode_depth_m(msg: Any) -> np.ndarray:
    """Depth in metres (float32, 0 = none) of a 16UC1 (mm) or 32FC1 (m) RawImage."""
    if msg.encoding in ("16UC1", "mono16"):
        mm = np.frombuffer(msg.data, "<u2").reshape(msg.height, msg.step // 2)[:, : msg.width]
        out: np.ndarray = mm.astype(np.float32) * np.float32(0.001)
        return out
    if msg.encoding == "32FC1":
        m = np.frombuffer(msg.data, "<f4").reshape(msg.height, msg.step // 4)[:, : msg.width]
        metres: np.ndarray = np.nan_to_num(m, nan=0.0).astype(np.float32)
        return metres
    raise CameraError(f"mcap source: depth encoding {msg.encoding!r} (expected 16UC1 or 32FC1)")


class McapSource:
    """Plays an MCAP recording as a :class:`~companion.perception.types.FrameSource` (see the module)."""

    def __init__(
        self, path: Path, *, realtime: bool = False, loop: bool = False, clock: Clock | None = None
    ) -> None:
        self.path = path
        self.loop = loop
        self._pacer = Pacer(realtime=realtime, clock=clock)
        self._file: IO[bytes] | None = None
        self._classes: dict[int, Any] = {}
        self.colour_topic = ""
        self.depth_topic: str | None = None
        self.calibration_topic: str | None = None
        self.perception_topic: str | None = None
        #: (stamp_s, q_ned_body_wxyz) of the frames the log has it for (the follower's attitude), stamped
        #: with the frame record's log time, the images' time base.
        self.attitude: list[tuple[float, np.ndarray]] = []
        self.intrinsics: Intrinsics | None = None

    def _reader(self) -> Any:
        from mcap.reader import make_reader  # noqa: PLC0415

        assert self._file is not None  # noqa: S101 (opened)
        self._file.seek(0)
        return make_reader(self._file)

    def _open(self) -> None:
        if not self.path.is_file():
            raise CameraError(f"mcap source: {self.path} does not exist")
        self._file = self.path.open("rb")
        try:
            summary = self._reader().get_summary()
        except Exception as exc:  # the mcap library's own errors for a file that is not MCAP
            raise CameraError(f"mcap source: {self.path} is not a readable MCAP file ({exc})") from None
        if summary is None:
            raise CameraError(f"mcap source: {self.path} has no summary (a log cut short: not playable)")
        by_topic = {c.topic: summary.schemas.get(c.schema_id) for c in summary.channels.values()}
        for c in summary.channels.values():
            s = summary.schemas.get(c.schema_id)
            if s is not None and s.encoding == "protobuf" and s.name in (COMPRESSED, RAW, CALIBRATION):
                self._classes[c.id] = protobuf_class(s.name, s.data)
        colour = [
            t
            for t, s in by_topic.items()
            if s is not None and s.name in (COMPRESSED, RAW) and "depth" not in t
        ]
        if not colour:
            raise CameraError(f"mcap source: {self.path} has no colour images (foxglove.CompressedImage)")
        self.colour_topic = colour[0]
        ns = self.colour_topic.rsplit("/camera/", 1)[0] if "/camera/" in self.colour_topic else ""
        depth = [t for t, s in by_topic.items() if s is not None and s.name == RAW and "depth" in t]
        calib = [t for t, s in by_topic.items() if s is not None and s.name == CALIBRATION]
        self.depth_topic = next((t for t in depth if t.startswith(ns)), depth[0] if depth else None)
        self.calibration_topic = next((t for t in calib if t.startswith(ns)), calib[0] if calib else None)
        if self.calibration_topic is None:
            raise CameraError(
                f"mcap source: {self.path} has no camera calibration (foxglove.CameraCalibration)"
            )
        perception = ns + PERCEPTION_SUFFIX
        if perception in by_topic:
            self.perception_topic = perception
            for _s, _c, m in self._reader().iter_messages(topics=[perception]):
                rec = json.loads(m.data)
                q = rec.get("q_ned_body_wxyz")
                if q is not None:
                    # On the images' time base (the log's), whatever the service clock's origin was.
                    self.attitude.append((m.log_time / 1e9, np.asarray(q, np.float64)))

    async def __aenter__(self) -> Self:
        try:
            await asyncio.to_thread(self._open)
        except BaseException:
            self._close()
            raise
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self._close()

    def _close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None

    def __aiter__(self) -> AsyncIterator[RgbdFrame]:
        return self._frames()

    def _groups(self) -> Iterator[dict[str, Any]]:
        """The messages of each log time: ``{"t": ns, topic: (channel id, data)}``."""
        if self._file is None:
            raise CameraError("mcap source: iterated before it was opened (use `async with`)")
        topics = [
            t
            for t in (self.colour_topic, self.depth_topic, self.calibration_topic, self.perception_topic)
            if t
        ]
        group: dict[str, Any] = {}
        for _s, c, m in self._reader().iter_messages(topics=topics, log_time_order=True):
            if group and group["t"] != m.log_time:
                yield group
                group = {}
            group.setdefault("t", m.log_time)
            group[c.topic] = (c.id, m.data)
        if group:
            yield group

    def _frame(self, group: dict[str, Any], seq: int, shift_s: float) -> RgbdFrame | None:
        if self.calibration_topic in group:
            cid, data = group[self.calibration_topic]
            k = self._classes[cid].FromString(data)
            self.intrinsics = Intrinsics(k.K[0], k.K[4], k.K[2], k.K[5], int(k.width), int(k.height))
        if self.colour_topic not in group:
            return None
        if self.intrinsics is None:
            raise CameraError(f"mcap source: {self.path}: an image before any camera calibration")
        cid, data = group[self.colour_topic]
        cls = self._classes[cid]
        msg = cls.FromString(data)
        rgb = decode_colour(msg, cls.DESCRIPTOR.full_name)
        h, w = rgb.shape[:2]
        depth = np.zeros((h, w), np.float32)
        if self.depth_topic is not None and self.depth_topic in group:
            did, ddata = group[self.depth_topic]
            depth = decode_depth_m(self._classes[did].FromString(ddata))
            if depth.shape != (h, w):
                raise CameraError(f"mcap source: depth {depth.shape} and colour {(h, w)} sizes differ")
        if self.perception_topic is not None and self.perception_topic in group:
            seq = int(json.loads(group[self.perception_topic][1]).get("seq", seq))
        return RgbdFrame(rgb, depth, self.intrinsics, _stamp_s(msg) + shift_s, seq)

    async def _frames(self) -> AsyncIterator[RgbdFrame]:
        shift_s = 0.0
        n = 0
        while True:
            groups = self._groups()
            first_s = last_s = None
            while (group := await asyncio.to_thread(next, groups, None)) is not None:
                frame = await asyncio.to_thread(self._frame, group, n, shift_s)
                if frame is None:
                    continue
                n += 1
                first_s = frame.stamp_s if first_s is None else first_s
                last_s = frame.stamp_s
                await self._pacer.wait(frame.stamp_s)
                yield frame
            if not self.loop or first_s is None or last_s is None:
                return
            shift_s += last_s - first_s + 0.05  # a looped pass goes on after the last frame
