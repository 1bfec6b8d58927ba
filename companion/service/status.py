"""The local status endpoint: a Unix socket (mode 0660) that answers one JSON line per request.

Protocol: the client sends one request and a newline (``status``, ``health``, ``start``, or ``command`` with
its words, e.g. ``command set_offset 0 0 6``); the server answers with one JSON object and a newline, then
closes. ``start`` and ``command`` are answered once the mission has acted on them (``{"ok", "detail"}``).
The socket's mode and its directory's group decide who may ask (the unit makes ``/run/wingman`` owned by
the service's group).
"""

from __future__ import annotations

import asyncio
import contextlib
import inspect
import json
import logging
import os
import socket
import stat
from collections.abc import Awaitable, Callable, Mapping
from pathlib import Path
from types import TracebackType
from typing import Any

from companion.kernel import compat
from companion.kernel.compat import Self
from companion.kernel.errors import CompanionError

log = logging.getLogger(__name__)

SOCKET_MODE = 0o660
_MAX_REQUEST_BYTES = 256
_REQUEST_TIMEOUT_S = 2.0

#: A request's answer, or (an operator's request) a coroutine that answers once the mission has acted.
Reply = Mapping[str, Any] | Awaitable[Mapping[str, Any]]
Handler = Callable[[], Reply]
#: A request with words after its name (``command set_offset 0 0 6``): gets those words.
CommandHandler = Callable[[list[str]], Reply]


#: Exit code of a client command (``status``, ``start``, ``command``) that found no service to answer it.
EXIT_NOT_RUNNING = 5


class ServiceNotRunningError(CompanionError):
    """No service answers on the status socket: not running, not answering, or not ours to open."""

    exit_code = EXIT_NOT_RUNNING


class StatusSocketError(CompanionError):
    """The status socket cannot be created (another instance holds it, or the path is wrong)."""

    exit_code = 2


class StatusServer:
    """Serves snapshots from ``handlers`` (request word -> function returning a JSON-able mapping)."""

    def __init__(
        self,
        path: Path,
        handlers: Mapping[str, Handler],
        commands: Mapping[str, CommandHandler] | None = None,
    ) -> None:
        self.path = path
        self._handlers = dict(handlers)
        self._commands = dict(commands or {})
        self._server: asyncio.Server | None = None
        self.requests_served = 0

    async def __aenter__(self) -> Self:
        sock = _bind_socket(self.path)
        try:
            self._server = await asyncio.start_unix_server(self._serve, sock=sock)
        except BaseException:
            sock.close()
            raise
        log.info("status endpoint on %s", self.path)
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if self._server is not None:
            self._server.close()
            with contextlib.suppress(TimeoutError):
                async with compat.timeout(1.0):
                    await self._server.wait_closed()
            self._server = None
        with contextlib.suppress(FileNotFoundError):
            self.path.unlink()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            async with compat.timeout(_REQUEST_TIMEOUT_S):
                line = await reader.readline()
            words = line[:_MAX_REQUEST_BYTES].decode("utf-8", "replace").split() or ["status"]
            request, args = words[0], words[1:]
            handler = self._handlers.get(request) if not args else None
            command = self._commands.get(request)
            reply: Reply
            if handler is not None:
                reply = handler()
            elif command is not None:
                reply = command(args)
            else:
                reply = {
                    "error": f"unknown request {' '.join(words)!r}",
                    "known": sorted([*self._handlers, *self._commands]),
                }
            if inspect.isawaitable(reply):
                reply = await reply
            writer.write(json.dumps(reply, default=_json_default).encode() + b"\n")
            async with compat.timeout(_REQUEST_TIMEOUT_S):
                await writer.drain()
            self.requests_served += 1
        except (TimeoutError, ConnectionError) as exc:
            log.debug("status client dropped: %s", exc)
        finally:
            writer.close()
            with contextlib.suppress(TimeoutError, ConnectionError):
                async with compat.timeout(1.0):
                    await writer.wait_closed()


def _json_default(obj: object) -> object:
    tolist = getattr(obj, "tolist", None)  # numpy arrays and scalars
    if callable(tolist):
        return tolist()
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def _bind_socket(path: Path) -> socket.socket:
    """Bind and chmod before listen(): nobody can connect while the mode is still the umask's."""
    path.parent.mkdir(mode=0o750, parents=True, exist_ok=True)
    if path.exists() or path.is_symlink():
        if not stat.S_ISSOCK(path.lstat().st_mode):
            raise StatusSocketError(f"status.socket_path: {path} exists and is not a socket")
        if _answers(path):
            raise StatusSocketError(f"status.socket_path: {path} is in use (is another service running?)")
        path.unlink()  # left by a process that died
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM | socket.SOCK_CLOEXEC)
    try:
        sock.bind(str(path))
        os.chmod(path, SOCKET_MODE)
        sock.listen(8)
        sock.setblocking(False)
    except OSError as exc:
        sock.close()
        raise StatusSocketError(f"status.socket_path: cannot listen on {path}: {exc.strerror}") from None
    return sock


def _answers(path: Path) -> bool:
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as probe:
        probe.settimeout(0.5)
        try:
            probe.connect(str(path))
        except OSError:
            return False
    return True


def query_status(path: Path, request: str = "status", timeout_s: float = 3.0) -> dict[str, Any]:
    """Ask the running service (blocking; for the CLI). Raises :class:`ServiceNotRunningError`."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM | socket.SOCK_CLOEXEC) as sock:
        sock.settimeout(timeout_s)
        try:
            sock.connect(str(path))
        except (FileNotFoundError, ConnectionRefusedError):
            raise ServiceNotRunningError(
                f"service not running: nothing listens on {path} (start it with `companion run`; "
                "a service with another config: --config PATH)"
            ) from None
        except PermissionError:
            raise ServiceNotRunningError(
                f"no permission to open {path} (run as the service's user or a member of its group)"
            ) from None
        try:
            sock.sendall(request.encode() + b"\n")
            chunks: list[bytes] = []
            while chunk := sock.recv(65536):
                chunks.append(chunk)
        except TimeoutError:
            raise ServiceNotRunningError(f"service did not answer on {path} within {timeout_s} s") from None
    data = b"".join(chunks)
    try:
        reply = json.loads(data)
    except json.JSONDecodeError:
        raise ServiceNotRunningError(f"unreadable answer on {path} ({len(data)} bytes)") from None
    if not isinstance(reply, dict):
        raise ServiceNotRunningError(f"unexpected answer on {path}")
    return reply
