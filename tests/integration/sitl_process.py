"""Run ``sitl serve`` as a subprocess on free ports, and listen to its GCS link like QGC would."""

from __future__ import annotations

import asyncio
import os
import random
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

REPO = Path(__file__).resolve().parents[2]


def _ports_free(ports: list[int]) -> bool:
    socks = []
    try:
        for p in ports:
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            socks.append(s)
            s.bind(("127.0.0.1", p))
        return True
    except OSError:
        return False
    finally:
        for s in socks:
            s.close()


@dataclass
class SitlPorts:
    api_remote: int
    api_local: int
    gcs_local: int
    gcs_remote: int

    def env(self) -> dict[str, str]:
        return {
            "SITL_MAVLINK__BIND_HOST": "127.0.0.1",
            "SITL_MAVLINK__API_REMOTE_PORT_BASE": str(self.api_remote),
            "SITL_MAVLINK__API_LOCAL_PORT_BASE": str(self.api_local),
            "SITL_MAVLINK__GCS_LOCAL_PORT_BASE": str(self.gcs_local),
            "SITL_MAVLINK__GCS_REMOTE_PORT": str(self.gcs_remote),
        }


def pick_ports(vehicles: int) -> SitlPorts:
    """Four free port ranges (other engineers' simulators may use the PX4 defaults)."""
    for _ in range(200):
        base = random.randrange(20000, 60000, 20)
        ports = SitlPorts(base, base + 4, base + 8, base + 12)
        needed = [base + i for i in range(vehicles)] + [base + 4 + i for i in range(vehicles)]
        needed += [base + 8 + i for i in range(vehicles)] + [base + 12]
        if _ports_free(needed):
            return ports
    raise RuntimeError("no free UDP port range found")


@dataclass
class SitlProcess:
    proc: subprocess.Popen[str]
    ports: SitlPorts
    speed: float
    output: list[str] = field(default_factory=list)

    def api_url(self, index: int) -> str:
        return f"udpin://0.0.0.0:{self.ports.api_remote + index}"

    def stop(self) -> str:
        """SIGTERM, wait, and return everything it printed (stdout + stderr)."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=5)
        time.sleep(0.1)
        return "\n".join(self.output)


@contextmanager
def sitl_serve(
    *,
    speed: float,
    config: Path | None = None,
    scenario: Path | None = None,
    extra_env: dict[str, str] | None = None,
    vehicles: int = 2,
    args: list[str] | None = None,
    camera: Path | None = None,
    host: str = "sitl",
) -> Iterator[SitlProcess]:
    """Start ``python -m sitl serve`` and wait until it says it is running; always stop it.

    ``host``: the module run with ``-m``, ``sitl`` or a program that hosts it with its own components.
    """
    ports = pick_ports(vehicles)
    env = os.environ.copy()
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    env.update(ports.env())
    env.update(extra_env or {})
    cmd = [sys.executable, "-m", host, "serve", "--speed", str(speed)]
    cmd += ["--camera", str(camera)] if camera is not None else ["--no-camera"]
    cmd += ["--config", str(config or REPO / "config" / "sitl.toml")]
    if scenario is not None:
        cmd += ["--scenario", str(scenario)]
    cmd += args or []
    proc = subprocess.Popen(
        cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1
    )
    sp = SitlProcess(proc, ports, speed)
    ready = threading.Event()

    def pump() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            sp.output.append(line.rstrip("\n"))
            if "sitl: running at" in line:
                ready.set()

    reader = threading.Thread(target=pump, name="sitl-output", daemon=True)
    reader.start()
    try:
        if not ready.wait(timeout=60):
            raise RuntimeError("sitl serve did not start:\n" + "\n".join(sp.output))
        yield sp
    finally:
        sp.stop()
        reader.join(timeout=5)


class GcsListener(asyncio.DatagramProtocol):
    """Binds the GCS remote port (QGroundControl's 14550) and records every message with the sim time
    of the latest ``time_boot_ms`` seen from that system."""

    def __init__(self) -> None:
        self.transport: asyncio.DatagramTransport | None = None
        self.records: list[tuple[int, float, Any]] = []  # (sysid, sim time s, msg)
        self.sim_s: dict[int, float] = {}
        self.peer: dict[int, tuple[str, int]] = {}
        self._mav = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
        self._new = asyncio.Event()

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        parser = mavlink.MAVLink(None)
        for msg in parser.parse_buffer(data) or []:
            sysid = msg.get_srcSystem()
            self.peer[sysid] = addr
            tb = getattr(msg, "time_boot_ms", None)
            if tb is not None:
                self.sim_s[sysid] = tb / 1000.0
            self.records.append((sysid, self.sim_s.get(sysid, 0.0), msg))
        self._new.set()
        self._new = asyncio.Event()

    def send(self, sysid: int, msg: Any) -> None:
        assert self.transport is not None
        self.transport.sendto(msg.pack(self._mav), self.peer[sysid])

    def of(self, sysid: int, msg_type: str, since_s: float = -1.0) -> list[tuple[float, Any]]:
        return [
            (t, m) for s, t, m in self.records if s == sysid and t >= since_s and m.get_type() == msg_type
        ]

    async def wait_for(self, pred: Any, timeout_s: float) -> Any:
        async with asyncio.timeout(timeout_s):
            while True:
                for rec in reversed(self.records):
                    if pred(rec):
                        return rec
                await self._new.wait()

    async def command(self, sysid: int, command: int, *params: float, timeout_s: float = 3.0) -> int:
        start = len(self.records)
        p = list(params) + [0.0] * (7 - len(params))
        self.send(sysid, mavlink.MAVLink_command_long_message(sysid, 1, command, 0, *p))
        async with asyncio.timeout(timeout_s):
            while True:
                for s, _, m in self.records[start:]:
                    if s == sysid and m.get_type() == "COMMAND_ACK" and m.command == command:
                        return int(m.result)
                await self._new.wait()

    async def set_rate(self, sysid: int, msg_id: int, hz: float) -> None:
        assert await self.command(sysid, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 1e6 / hz) == 0


async def open_gcs_listener(port: int) -> GcsListener:
    loop = asyncio.get_running_loop()
    _, proto = await loop.create_datagram_endpoint(GcsListener, local_addr=("127.0.0.1", port))
    return proto
