"""Where the recorder's messages go: the live Foxglove WebSocket server and MCAP flight-log files.

Both are used from the recorder's worker thread only. A sink that fails (a port taken, a full disk, a
folder it may not write) raises :class:`SinkError` with one line; the recorder then turns that sink off and
the flight goes on.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Iterable
from pathlib import Path
from typing import IO, Any

import foxglove
from mcap.writer import CompressionType, Writer

from companion import __version__
from companion.viz.channels import Topic

log = logging.getLogger(__name__)


class SinkError(Exception):
    """A sink cannot go on (the message is one line)."""


class LiveSink:
    """Foxglove's WebSocket server (the SDK's) with one channel per topic, advertised from the start.

    Images are only encoded while a viewer is subscribed to them (:meth:`wants`).
    """

    name = "live view"

    def __init__(self, topics: Iterable[Topic], *, host: str, port: int, server_name: str) -> None:
        self._context = foxglove.Context()
        try:
            self._server = foxglove.start_server(
                name=server_name, host=host, port=port, context=self._context, message_backlog_size=64
            )
        except Exception as exc:  # the SDK raises its own error types for a taken port or a bad address
            raise SinkError(f"cannot serve on {host}:{port}: {exc}") from None
        self._channels: dict[str, Any] = {
            t.name: foxglove.Channel(
                t.name,
                schema=foxglove.Schema(name=t.schema_name, encoding=t.schema_encoding, data=t.schema_data),
                message_encoding=t.message_encoding,
                context=self._context,
            )
            for t in topics
        }

    @property
    def port(self) -> int:
        """The port it listens on (the configured one, or the one the system chose for port 0)."""
        return int(self._server.port)

    def wants(self, topic: str) -> bool:
        """Whether a viewer is subscribed to ``topic`` now."""
        ch = self._channels.get(topic)
        return ch is not None and bool(ch.has_sinks())

    def write(self, topic: str, log_time_ns: int, data: bytes) -> None:
        ch = self._channels.get(topic)
        if ch is not None:
            ch.log(data, log_time=log_time_ns)

    def close(self) -> None:
        self._server.stop()


class McapSink:
    """MCAP files in one folder: ``STEM.mcap``, then ``STEM-002.mcap`` and so on beyond ``file_max_bytes``.

    Before each file is opened, the oldest ``*.mcap`` files of the folder are deleted until the folder
    holds less than ``budget_bytes`` (never the file being written). Messages are zstd-compressed in chunks;
    a file that was not closed (a crash) is still readable up to its last whole chunk.
    """

    name = "flight log"

    def __init__(
        self,
        folder: Path,
        stem: str,
        topics: Iterable[Topic],
        *,
        file_max_bytes: int,
        budget_bytes: int,
        metadata: dict[str, str] | None = None,
    ) -> None:
        self.folder = folder
        self.stem = stem
        self.topics = {t.name: t for t in topics}
        self.file_max_bytes = file_max_bytes
        self.budget_bytes = budget_bytes
        self.metadata = {"wingman_version": __version__, **(metadata or {})}
        self.paths: list[Path] = []
        self.bytes_written = 0
        self._file: IO[bytes] | None = None
        self._writer: Writer | None = None
        self._channel_ids: dict[str, int] = {}
        self._part = 0
        try:
            folder.mkdir(parents=True, exist_ok=True)
            self._open()
        except OSError as exc:
            raise SinkError(f"cannot write {folder}: {exc}") from None

    def wants(self, topic: str) -> bool:
        return topic in self.topics

    def _open(self) -> None:
        self._part += 1
        path = self.folder / (
            f"{self.stem}.mcap" if self._part == 1 else f"{self.stem}-{self._part:03d}.mcap"
        )
        self._trim(keep_free=self.file_max_bytes)
        f = path.open("wb")
        writer = Writer(f, compression=CompressionType.ZSTD)
        writer.start(profile="", library=f"wingman {__version__}")
        writer.add_metadata("wingman", {**self.metadata, "part": str(self._part)})
        self._file, self._writer = f, writer
        self._channel_ids = {}
        self.paths.append(path)

    def _trim(self, keep_free: int) -> None:
        """Delete the oldest logs until the folder plus a new file fits the budget."""
        files = sorted(self.folder.glob("*.mcap"), key=lambda p: p.stat().st_mtime)
        total = sum(p.stat().st_size for p in files)
        for old in files:
            if total + keep_free <= self.budget_bytes:
                break
            total -= old.stat().st_size
            old.unlink()
            log.info("flight log: deleted %s to stay within %d bytes", old, self.budget_bytes)

    def write(self, topic: str, log_time_ns: int, data: bytes) -> None:
        writer, f = self._writer, self._file
        if writer is None or f is None:
            return
        try:
            cid = self._channel_ids.get(topic)
            if cid is None:
                t = self.topics[topic]
                sid = writer.register_schema(t.schema_name, t.schema_encoding, t.schema_data)
                cid = writer.register_channel(topic, t.message_encoding, sid)
                self._channel_ids[topic] = cid
            writer.add_message(cid, log_time_ns, data, log_time_ns)
            if f.tell() >= self.file_max_bytes:
                self._finish()
                self._open()
        except OSError as exc:
            self._abandon()
            raise SinkError(
                f"writing {self.paths[-1] if self.paths else self.folder} failed: {exc}"
            ) from None
        self.bytes_written += len(data)

    def _finish(self) -> None:
        writer, f = self._writer, self._file
        self._writer = self._file = None
        if writer is not None and f is not None:
            try:
                writer.finish()  # type: ignore[no-untyped-call]
            finally:
                f.close()

    def _abandon(self) -> None:
        """After a write error: close what can be closed, quietly (the disk may be full)."""
        f = self._file
        self._writer = self._file = None
        if f is not None:
            with contextlib.suppress(OSError):
                f.close()

    def close(self) -> None:
        try:
            self._finish()
        except OSError as exc:
            self._abandon()
            raise SinkError(f"closing {self.paths[-1]} failed: {exc}") from None


def flight_stem(vehicle_id: str, wall_time_s: float | None = None) -> str:
    """A flight log's name: the vehicle and the start time in UTC (``follower1-20260101-120000``)."""
    return f"{vehicle_id}-{time.strftime('%Y%m%d-%H%M%S', time.gmtime(wall_time_s))}"
