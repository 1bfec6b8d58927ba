"""sd_notify over ``$NOTIFY_SOCKET`` with the standard library only (no libsystemd binding).

The CLI edge reads ``NOTIFY_SOCKET``/``WATCHDOG_USEC``/``WATCHDOG_PID`` and builds a :class:`NotifyConfig`;
nothing below reads the environment. Without a socket (not under systemd) every call is a no-op.
"""

from __future__ import annotations

import logging
import os
import socket
from collections.abc import Mapping
from dataclasses import dataclass
from types import TracebackType

from companion.kernel.compat import Self

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class NotifyConfig:
    """Where to notify and how often systemd expects a watchdog ping."""

    socket_path: str | None = None
    #: ``WatchdogSec`` as systemd passes it; None when the watchdog is off (or meant for another PID).
    watchdog_s: float | None = None

    @classmethod
    def from_environ(cls, environ: Mapping[str, str], pid: int) -> NotifyConfig:
        """Read systemd's variables (call this at the CLI edge only)."""
        path = environ.get("NOTIFY_SOCKET") or None
        watchdog_s: float | None = None
        usec = environ.get("WATCHDOG_USEC", "")
        wd_pid = environ.get("WATCHDOG_PID", "")
        if usec.isdigit() and int(usec) > 0 and (not wd_pid or wd_pid == str(pid)):
            watchdog_s = int(usec) / 1e6
        return cls(socket_path=path, watchdog_s=watchdog_s)


class SystemdNotifier:
    """Sends ``READY=1``, ``STATUS=...``, ``WATCHDOG=1``, ``STOPPING=1`` datagrams; a context manager."""

    def __init__(self, config: NotifyConfig) -> None:
        self.config = config
        self._sock: socket.socket | None = None
        self._address: str | bytes | None = None
        self._warned = False

    @property
    def enabled(self) -> bool:
        return self.config.socket_path is not None

    @property
    def watchdog_interval_s(self) -> float | None:
        """How often to ping: half of ``WatchdogSec``, as sd_watchdog_enabled(3) advises."""
        return None if self.config.watchdog_s is None else self.config.watchdog_s / 2.0

    def __enter__(self) -> Self:
        path = self.config.socket_path
        if path is not None:
            if path.startswith("@"):  # abstract namespace
                self._address = b"\0" + path[1:].encode()
            else:
                self._address = path
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            self._sock.setblocking(False)
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def notify(self, *lines: str) -> bool:
        """Send one datagram of ``KEY=value`` lines; False when not sent (no socket, or it failed)."""
        if self._sock is None or self._address is None:
            return False
        try:
            self._sock.sendto("\n".join(lines).encode(), self._address)
        except OSError as exc:
            # systemd gone or its queue full: log once, never fail the service over a notification.
            if not self._warned:
                log.warning("sd_notify to %s failed: %s", self.config.socket_path, exc)
                self._warned = True
            return False
        return True

    def ready(self, status: str) -> bool:
        return self.notify("READY=1", f"STATUS={_one_line(status)}", f"MAINPID={os.getpid()}")

    def status(self, status: str) -> bool:
        return self.notify(f"STATUS={_one_line(status)}")

    def watchdog(self) -> bool:
        return self.notify("WATCHDOG=1")

    def stopping(self, status: str) -> bool:
        return self.notify("STOPPING=1", f"STATUS={_one_line(status)}")

    def extend_timeout(self, extra_s: float) -> bool:
        """Ask for ``extra_s`` more before systemd's start/stop timeout kills us (a landing takes time)."""
        return self.notify(f"EXTEND_TIMEOUT_USEC={int(extra_s * 1e6)}")


def _one_line(text: str) -> str:
    return " ".join(text.split())[:200]
