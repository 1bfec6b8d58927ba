"""Child processes and private UDP port blocks for runs against ``sitl serve`` (the real path, the tests).

Every process started through :class:`Child` is stopped by its PID (SIGTERM, then SIGKILL) whatever
happens, and on Linux it is sent SIGTERM when its parent dies (:func:`die_with_parent`). Port blocks are
picked at random and probed, so runs side by side on one machine never collide.
"""

from __future__ import annotations

import asyncio
import os
import random
import shutil
import signal
import socket
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, ClassVar

from companion.kernel.children import die_with_parent
from companion.kernel.errors import CompanionError
from companion.kernel.shipped import project_root

if TYPE_CHECKING:
    from typing import Self  # Python 3.11; the service's tests import this module on 3.10 too

#: Children run here: the folder with config/ and models/ (companion/kernel/shipped.py).
REPO = project_root()


class SimRunError(CompanionError):
    """A closed-loop run could not be carried out (a process did not start, or died)."""

    exit_code = 1


def udp_port_free(port: int) -> bool:
    """Whether a UDP port can be bound on all interfaces (the simulator binds all of them)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.bind(("0.0.0.0", port))  # noqa: S104 (the simulator binds all interfaces)
        except OSError:
            return False
    return True


@dataclass(frozen=True, slots=True)
class PortBlock:
    """``SIZE`` consecutive UDP ports from ``base``; subclasses name the ports they use."""

    base: int
    SIZE: ClassVar[int] = 10

    @classmethod
    def pick(cls, rng: random.Random | None = None) -> Self:
        """A block whose every port is free now (tries 200 random bases in 20000-60000, steps of 10)."""
        draw = rng if rng is not None else random.Random()  # noqa: S311 (port choice, not crypto)
        for _ in range(200):
            base = draw.randrange(20000, 60000, 10)
            if all(udp_port_free(base + k) for k in range(cls.SIZE)):
                return cls(base)
        raise SimRunError("no free block of UDP ports")


@dataclass(frozen=True, slots=True)
class SitlPorts(PortBlock):
    """The ports of one ``sitl serve`` with two vehicles (leader 0, follower 1) and a GCS link.

    ``client``: where a MAVSDK behind a wiretap listens; ``truth``: a test's ground-truth feed.
    """

    @property
    def api_local(self) -> int:
        return self.base

    @property
    def api_remote(self) -> int:
        """Where the simulator sends the leader's API link (the follower's is the next port)."""
        return self.base + 2

    @property
    def follower_api(self) -> int:
        return self.api_remote + 1

    @property
    def gcs_local(self) -> int:
        return self.base + 4

    @property
    def follower_gcs(self) -> int:
        return self.gcs_local + 1

    @property
    def gcs_remote(self) -> int:
        return self.base + 6

    @property
    def client(self) -> int:
        return self.base + 7

    @property
    def truth(self) -> int:
        return self.base + 8


class Child:
    """A child process with its output in a log file, stopped by its PID (SIGTERM, then SIGKILL)."""

    def __init__(self, args: list[str], env: dict[str, str], log_path: Path, *, cwd: Path = REPO) -> None:
        self.args = args
        self.env = env
        self.log_path = log_path
        self.cwd = cwd
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        with self.log_path.open("ab") as out:
            self.proc = subprocess.Popen(
                self.args,
                cwd=self.cwd,
                env=self.env,
                stdout=out,
                stderr=subprocess.STDOUT,
                preexec_fn=die_with_parent,  # noqa: PLW1509 (one prctl call, no locks taken)
            )

    def log(self) -> str:
        """Everything the process wrote so far ("" before it started)."""
        return self.log_path.read_text(errors="replace") if self.log_path.exists() else ""

    def tail(self, n: int = 3000) -> str:
        return self.log()[-n:]

    @property
    def running(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    @property
    def returncode(self) -> int | None:
        return None if self.proc is None else self.proc.poll()

    def _started(self) -> subprocess.Popen[bytes]:
        if self.proc is None:
            raise SimRunError(f"{self.args[2:4]} was never started")
        return self.proc

    def signal(self, sig: int) -> None:
        self._started().send_signal(sig)

    async def wait(self, timeout_s: float) -> int:
        """The exit status, polled; TimeoutError if it still runs after ``timeout_s``."""
        proc = self._started()
        deadline = time.monotonic() + timeout_s
        while (rc := proc.poll()) is None:
            if time.monotonic() > deadline:
                raise TimeoutError(f"{self.args[2:4]} still running after {timeout_s} s")
            await asyncio.sleep(0.05)
        return rc

    async def wait_for_output(self, marker: str, timeout_s: float) -> None:
        """Until ``marker`` is in the log; SimRunError (and the process stopped) if it exits or times out."""
        deadline = time.monotonic() + timeout_s
        while marker not in self.log():
            if not self.running or time.monotonic() > deadline:
                await self.stop()
                raise SimRunError(f"{self.args[2:4]} did not say {marker!r}:\n{self.tail()}")
            await asyncio.sleep(0.1)

    async def stop(self, timeout_s: float = 15.0) -> None:
        """SIGTERM, up to ``timeout_s`` to exit, then SIGKILL. Idempotent."""
        proc, self.proc = self.proc, None
        if proc is None or proc.poll() is not None:
            return
        proc.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + timeout_s
        while proc.poll() is None and time.monotonic() < deadline:  # noqa: ASYNC110 (a Popen, no event)
            await asyncio.sleep(0.05)
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)


def free_tcp_port() -> int:
    """A TCP port on the loopback address that nothing listens on now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Broker(Child):
    """A private mosquitto on a free loopback port (the run's MQTT: shares between vehicles).

    Anonymous, loopback only, no persistence; stopped like any :class:`Child`.
    """

    def __init__(self, work_dir: Path, env: dict[str, str]) -> None:
        exe = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
        if not Path(exe).exists():
            raise SimRunError("mosquitto is not installed (scripts/setup installs it)")
        self.port = free_tcp_port()
        conf = work_dir / "mosquitto.conf"
        as_root = "user root\n" if os.geteuid() == 0 else ""
        conf.write_text(f"{as_root}listener {self.port} 127.0.0.1\nallow_anonymous true\nlog_dest stderr\n")
        super().__init__([exe, "-c", str(conf)], env, work_dir / "mosquitto.log")

    async def start_and_wait(self, timeout_s: float = 10.0) -> None:
        """Start it and return once it accepts connections; SimRunError if it does not."""
        self.start()
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if not self.running:
                break
            with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
                if s.connect_ex(("127.0.0.1", self.port)) == 0:
                    return
            await asyncio.sleep(0.05)
        await self.stop()
        raise SimRunError(f"mosquitto did not listen on {self.port}:\n{self.tail()}")
