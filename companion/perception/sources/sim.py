"""The simulator's camera as a frame source: RGB-D frames rendered inside ``sitl serve``, over a Unix socket.

The server is :class:`sitl.render.camera_server.CameraServer`; the wire format is
:mod:`companion.kernel.camera_wire`'s, so that the service never imports ``sitl``.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator
from pathlib import Path
from types import TracebackType

from companion.config import CameraConfig
from companion.kernel import compat
from companion.kernel.camera import RgbdFrame
from companion.kernel.camera_wire import MAGIC, MAX_HEADER_BYTES, PREFIX, WIRE_VERSION, decode_frame
from companion.kernel.clock import Clock
from companion.kernel.compat import Self
from companion.kernel.errors import CameraError


class SimFrameSource:
    """Frames from ``sitl serve``'s camera server (a :class:`~companion.perception.types.FrameSource`).

    Frames carry sim-clock stamps and the simulator's ground truth. The server drops frames for a
    reader that falls behind (latest wins), so a slow pipeline sees fresh frames, never a backlog.
    Iteration ends when the server closes the socket.
    """

    def __init__(self, socket_path: str | Path, *, connect_timeout_s: float = 5.0) -> None:
        self.socket_path = Path(socket_path)
        self.connect_timeout_s = connect_timeout_s
        self._reader: asyncio.StreamReader | None = None
        self._writer: asyncio.StreamWriter | None = None

    async def __aenter__(self) -> Self:
        path = self.socket_path
        try:
            async with compat.timeout(self.connect_timeout_s):
                self._reader, self._writer = await asyncio.open_unix_connection(str(path))
        except (FileNotFoundError, ConnectionRefusedError) as exc:
            raise CameraError(
                f"sim camera: no camera server at {path} ({exc.strerror}); is `sitl serve` running with "
                "its camera (not --no-camera)?"
            ) from None
        except TimeoutError:
            raise CameraError(
                f"sim camera: {path} did not accept a connection in {self.connect_timeout_s} s"
            ) from None
        except OSError as exc:
            raise CameraError(f"sim camera: cannot connect to {path}: {exc}") from None
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if self._writer is not None:
            self._writer.close()
            try:
                async with compat.timeout(1.0):
                    await self._writer.wait_closed()
            except (TimeoutError, ConnectionError):
                pass
            self._writer = self._reader = None

    def __aiter__(self) -> AsyncIterator[RgbdFrame]:
        return self._frames()

    async def _frames(self) -> AsyncIterator[RgbdFrame]:
        reader = self._reader
        if reader is None:
            raise CameraError("sim camera: iterate inside `async with SimFrameSource(...)`")
        while True:
            try:
                prefix = await reader.readexactly(PREFIX.size)
            except asyncio.IncompleteReadError as exc:
                if exc.partial:
                    raise CameraError("sim camera: stream ended inside a frame") from None
                return
            magic, n = PREFIX.unpack(prefix)
            if magic != MAGIC or n > MAX_HEADER_BYTES:
                raise CameraError(f"sim camera: bad frame prefix {prefix!r} (not a Wingman camera stream?)")
            try:
                header = json.loads(await reader.readexactly(n))
                if header.get("v") != WIRE_VERSION:
                    raise CameraError(f"sim camera: wire version {header.get('v')}, expected {WIRE_VERSION}")
                rgb = await reader.readexactly(int(header["rgb_bytes"]))
                depth = await reader.readexactly(int(header["depth_bytes"]))
            except asyncio.IncompleteReadError:
                raise CameraError("sim camera: stream ended inside a frame") from None
            yield decode_frame(header, rgb, depth)


def open_sim_source(camera: CameraConfig, *, clock: Clock | None = None) -> SimFrameSource:
    """The sim source for a camera config (``camera.path`` is the socket).

    Frames carry sim time, so no clock is needed; the argument matches the other sources' factories.
    """
    del clock
    return SimFrameSource(camera.path)
