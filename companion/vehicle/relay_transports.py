"""The signing relay's autopilot side: a UDP endpoint (listening or connected) or a raw serial port.

Each transport hands whole datagrams (UDP) or whole MAVLink frames (serial, re-framed from the byte stream)
to the relay and sends what the relay gives it; none blocks the event loop.
"""

from __future__ import annotations

import asyncio
import logging
import os
import termios
from collections.abc import Callable
from typing import Any

from companion.kernel.errors import LinkLostError
from companion.vehicle.mavlink_signing import take_stream_frames

log = logging.getLogger("companion.vehicle.signing")

Addr = tuple[str, int]
#: Where frames from a serial link come from (it has no address).
SERIAL: Addr = ("serial", 0)
_BAUDS = {
    int(name[1:]): getattr(termios, name) for name in dir(termios) if name[:1] == "B" and name[1:].isdigit()
}


def where(addr: Addr | None) -> str:
    """An address as log lines and the status write it (a serial link has none)."""
    return "the serial link" if addr is None or addr == SERIAL else f"{addr[0]}:{addr[1]}"


class Transport:
    """The autopilot side: ``send(data, dests)`` and ``close()``."""

    def send(self, data: bytes, dests: list[Addr]) -> None:
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError


class Datagrams(asyncio.DatagramProtocol):
    """Hands each datagram and its sender to ``on_data``."""

    def __init__(self, on_data: Callable[[bytes, Addr], None]) -> None:
        self._on_data = on_data

    def datagram_received(self, data: bytes, addr: tuple[str | Any, int]) -> None:
        self._on_data(data, (str(addr[0]), int(addr[1])))

    def error_received(self, exc: Exception) -> None:
        log.debug("signing relay: %s", exc)  # ICMP port unreachable while nobody listens


class _Udp(Transport):
    def __init__(self, transport: asyncio.DatagramTransport, fixed: Addr | None) -> None:
        self._transport = transport
        self._fixed = fixed

    def send(self, data: bytes, dests: list[Addr]) -> None:
        if self._fixed is not None:
            self._transport.sendto(data)  # connected: the kernel drops every other sender's datagrams
            return
        for addr in dests:
            self._transport.sendto(data, addr)

    def close(self) -> None:
        self._transport.close()


class _Serial(Transport):
    """A serial port in raw mode, read and written without blocking on the event loop."""

    def __init__(self, fd: int, on_data: Callable[[bytes, Addr | None], None], key: bytes) -> None:
        self._fd = fd
        self._on_data = on_data
        self._key = key
        self._loop = asyncio.get_running_loop()
        self._buffer = bytearray()
        self._pending = bytearray()
        self._loop.add_reader(fd, self._readable)

    def _readable(self) -> None:
        try:
            chunk = os.read(self._fd, 4096)
        except BlockingIOError:
            return
        except OSError as exc:
            log.error("signing relay: serial read failed: %s", exc)
            self._loop.remove_reader(self._fd)
            return
        self._buffer += chunk
        frames, rest = take_stream_frames(self._buffer, self._key)
        self._buffer = bytearray(rest)
        if frames:
            self._on_data(b"".join(frames), None)

    def send(self, data: bytes, dests: list[Addr]) -> None:
        if self._pending:
            self._pending += data
            return
        try:
            written = os.write(self._fd, data)
        except BlockingIOError:
            written = 0
        if written < len(data):
            self._pending += data[written:]
            self._loop.add_writer(self._fd, self._writable)

    def _writable(self) -> None:
        try:
            written = os.write(self._fd, self._pending)
        except BlockingIOError:
            return
        del self._pending[:written]
        if not self._pending:
            self._loop.remove_writer(self._fd)

    def close(self) -> None:
        self._loop.remove_reader(self._fd)
        self._loop.remove_writer(self._fd)
        os.close(self._fd)


def _open_serial(device: str, baud: int) -> int:
    fd = os.open(device, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    try:
        attrs = termios.tcgetattr(fd)
        speed = _BAUDS.get(baud)
        if speed is None:
            raise LinkLostError(f"signing relay: unsupported baud rate {baud}")
        attrs[0] = 0  # iflag: raw
        attrs[1] = 0  # oflag
        attrs[2] = termios.CS8 | termios.CREAD | termios.CLOCAL  # cflag
        attrs[3] = 0  # lflag
        attrs[4] = attrs[5] = speed
        attrs[6][termios.VMIN] = 0
        attrs[6][termios.VTIME] = 0
        termios.tcsetattr(fd, termios.TCSANOW, attrs)
    except BaseException:
        os.close(fd)
        raise
    return fd


async def open_autopilot(url: str, on_data: Callable[[bytes, Addr | None], None], key: bytes) -> Transport:
    """The transport ``url`` names (udpin, udpout, serial); one LinkLostError line if it cannot open."""
    scheme, _, rest = url.partition("://")
    loop = asyncio.get_running_loop()
    try:
        if scheme == "serial":
            device, _, baud = rest.partition(":")
            return _Serial(_open_serial(device, int(baud or 57600)), on_data, key)
        host, _, port = rest.rpartition(":")
        if scheme == "udpin":
            transport, _ = await loop.create_datagram_endpoint(
                lambda: Datagrams(on_data), local_addr=(host, int(port))
            )
            return _Udp(transport, None)
        if scheme == "udpout":
            transport, _ = await loop.create_datagram_endpoint(
                lambda: Datagrams(on_data), remote_addr=(host, int(port))
            )
            return _Udp(transport, (host, int(port)))
    except OSError as exc:
        raise LinkLostError(f"signing relay: cannot open {url}: {exc.strerror or exc}") from exc
    raise LinkLostError(f"signing relay: {url}: only udpin://, udpout:// and serial:// links can be signed")
