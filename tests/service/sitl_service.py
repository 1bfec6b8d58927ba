"""TEST-ONLY harness for the service end to end: ``sitl serve`` with its camera, ``companion run``, a GCS.

Every process is started here and stopped by its PID (SIGTERM, then SIGKILL) whatever happens.
"""

from __future__ import annotations

import asyncio
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pymavlink.dialects.v20 import common as mavlink2

from companion.lab.evaluation.procs import Child
from companion.lab.evaluation.procs import SitlPorts as Ports

REPO = Path(__file__).resolve().parents[2]

#: The leader climbs to 5 m 8 m ahead of the follower, hovers, then drifts north at 0.5 m/s.
SCENARIO = """
schema_version = 1
name = "service-e2e"
description = "Service end-to-end: leader hovers, then flies north slowly."
seed = 7

[run]
duration_s = 600.0
formation_start_s = 20.0
formation_duration_s = 500.0
takeoff_altitude_m = 5.0

[leader]
type = "straight"
start_s = 45.0
altitude_m = 5.0
speed_m_s = 0.5
heading_deg = 0.0

[wind]
mean_speed_m_s = 0.5
from_deg = 270.0
turbulence_m_s = 0.1
"""


def sim_process(tmp_path: Path, ports: Ports, camera_sock: Path, scenario_toml: str = SCENARIO) -> Child:
    scenario = tmp_path / "scenario.toml"
    scenario.write_text(scenario_toml)
    env = {
        **os.environ,
        "PYTHONPATH": str(REPO),
        "SITL_MAVLINK__API_LOCAL_PORT_BASE": str(ports.api_local),
        "SITL_MAVLINK__API_REMOTE_PORT_BASE": str(ports.api_remote),
        "SITL_MAVLINK__GCS_LOCAL_PORT_BASE": str(ports.gcs_local),
        "SITL_MAVLINK__GCS_REMOTE_PORT": str(ports.gcs_remote),
        "SITL_MAVLINK__REMOTE_HOST": "127.0.0.1",
        "WINGMAN_TEST_CAMERA_SOCK": str(camera_sock),
    }
    args = [
        sys.executable,
        "-m",
        "tests.service.sitl_camera",  # sitl, its camera passed in
        "--log-level",
        "INFO",
        "serve",
        "--no-camera",
        "--config",
        str(REPO / "config/sitl.toml"),
    ]
    args += ["--scenario", str(scenario)]
    return Child(args, env, tmp_path / "sitl.log")


def service_config(
    tmp_path: Path, link_port: int, camera_sock: Path, broker_port: int | None, extra_toml: str = ""
) -> Path:
    """The service's config beside the simulator: its MQTT on ``broker_port`` (None: no MQTT), plus
    ``extra_toml`` (further tables, e.g. the live view's)."""
    mqtt = (
        f"""[mqtt]
enabled = true
port = {broker_port}
state_rate_hz = 5.0
pose_rate_hz = 5.0
health_rate_hz = 1.0
reconnect_min_s = 0.2
reconnect_max_s = 1.0
"""
        if broker_port is not None
        else ""
    )
    cfg = tmp_path / "wingman.toml"
    cfg.write_text(
        f"""
vehicle_id = "follower1"
[link]
url = "udpin://0.0.0.0:{link_port}"
[camera]
source = "sim"
path = "{camera_sock}"
[detector]
runtime = "truth"
[formation]
offset_cam_m = [0.0, 0.0, 8.0]   # the leader spawns 8 m ahead: the slot is where the follower starts
[mission]
shutdown_hold_s = 1.0
# The rendered camera lags 0.3-0.8 s behind the simulation on the shared 2-core test machine (frames
# carry that true age, see companion/service/stamps.py); the default 0.5 s would hover on every lag.
stale_estimate_s = 1.5
{mqtt}[status]
socket_path = "{tmp_path}/run/status.sock"
[service]
auto_start = true
shutdown_timeout_s = 90.0
[logging]
format = "json"
{extra_toml}"""
    )
    return cfg


def service_process(tmp_path: Path, cfg: Path, notify_sock: Path) -> Child:
    env = {
        **os.environ,
        "PYTHONPATH": str(REPO),
        "NOTIFY_SOCKET": str(notify_sock),
        "WATCHDOG_USEC": "10000000",
    }
    args = [sys.executable, "-m", "companion", "run", "--config", str(cfg)]
    return Child(args, env, tmp_path / "service.log")


@dataclass
class GcsObserver(asyncio.DatagramProtocol):
    """A ground station on the simulator's GCS link: what the follower (system 2) says about itself."""

    sysid: int = 2
    armed: bool | None = None
    landed_state: int | None = None
    relative_alt_m: float | None = None
    seen: dict[str, int] = field(default_factory=dict)
    #: STATUSTEXTs from the follower's companion computer, forwarded by its autopilot.
    companion_texts: list[str] = field(default_factory=list)
    _parser: Any = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self._parser = mavlink2.MAVLink(None)
        self._parser.robust_parsing = True

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        try:
            msgs = self._parser.parse_buffer(data) or []
        except mavlink2.MAVError:
            return
        for m in msgs:
            if m.get_srcSystem() != self.sysid:
                continue
            kind = m.get_type()
            self.seen[kind] = self.seen.get(kind, 0) + 1
            if kind == "STATUSTEXT" and m.get_srcComponent() != 1:
                self.companion_texts.append(m.text)
            if kind == "HEARTBEAT" and m.get_srcComponent() == 1:
                self.armed = bool(m.base_mode & mavlink2.MAV_MODE_FLAG_SAFETY_ARMED)
            elif kind == "EXTENDED_SYS_STATE":
                self.landed_state = int(m.landed_state)
            elif kind == "GLOBAL_POSITION_INT":
                self.relative_alt_m = m.relative_alt / 1000.0

    @property
    def on_ground(self) -> bool:
        return self.landed_state == mavlink2.MAV_LANDED_STATE_ON_GROUND


async def open_gcs(port: int) -> tuple[asyncio.DatagramTransport, GcsObserver]:
    loop = asyncio.get_running_loop()
    transport, proto = await loop.create_datagram_endpoint(GcsObserver, local_addr=("127.0.0.1", port))
    return transport, proto
