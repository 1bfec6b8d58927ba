"""The local status endpoint: a Unix socket (mode 0660) that answers one JSON line per request.

Protocol: the client sends one request and a newline: a word (``status``, ``health``, ``start``) or a JSON
object naming its request, ``{"request": "command", "name": "set_offset", "offset_cam_m": [0, 0, 6]}``
(commands come only so: their numbers stay numbers); the server answers with one JSON object and a
newline, then closes. ``start`` and ``command`` are answered once the mission has acted on them
(``{"ok", "detail"}``).
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
#: A request sent as a JSON object (``{"request": "command", ...}``): gets the whole object.
CommandHandler = Callable[[Mapping[str, Any]], Reply]


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
            text = line[:_MAX_REQUEST_BYTES].decode("utf-8", "replace").strip() or "status"
            obj = _json_request(text)
            handler = self._handlers.get(text)
            command = self._commands.get(str(obj.get("request"))) if obj is not None else None
            reply: Reply
            if handler is not None:
                reply = handler()
            elif command is not None and obj is not None:
                reply = command(obj)
            else:
                reply = {
                    "error": f"unknown request {text!r}",
                    "known": sorted(self._handlers),
                    "commands": 'a JSON object, e.g. {"request": "command", "name": "hold"}',
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


def _json_request(text: str) -> dict[str, Any] | None:
    """A request sent as a JSON object (numbers must be finite), or None."""
    if not text.startswith("{"):
        return None
    try:
        obj = json.loads(text, parse_constant=_no_constant)
    except ValueError:
        return None
    return obj if isinstance(obj, dict) else None


def _no_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a number here")


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
