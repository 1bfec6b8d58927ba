"""OS edges with real sockets and files: sd_notify datagrams, the status socket, /proc and /sys readers."""

from __future__ import annotations

import asyncio
import json
import os
import socket
import stat
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pytest

from companion.service.operator import command_request
from companion.service.status import (
    ServiceNotRunningError,
    StatusServer,
    StatusSocketError,
    query_status,
)
from companion.service.sysinfo import SystemMonitor, cpu_percent, parse_meminfo, parse_proc_stat
from companion.service.systemd import NotifyConfig, SystemdNotifier


def test_notify_config_from_environ() -> None:
    env = {"NOTIFY_SOCKET": "/run/x.sock", "WATCHDOG_USEC": "10000000", "WATCHDOG_PID": "42"}
    assert NotifyConfig.from_environ(env, pid=42) == NotifyConfig("/run/x.sock", 10.0)
    assert NotifyConfig.from_environ(env, pid=7).watchdog_s is None  # meant for another process
    assert NotifyConfig.from_environ({}, pid=1) == NotifyConfig(None, None)


def test_notifier_sends_datagrams(tmp_path: Path) -> None:
    path = tmp_path / "notify.sock"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as rx:
        rx.bind(str(path))
        rx.settimeout(1)
        with SystemdNotifier(NotifyConfig(str(path), 4.0)) as n:
            assert n.watchdog_interval_s == 2.0
            assert n.ready("following\nleader")
            assert n.watchdog()
            assert n.stopping("landing")
        msgs = [rx.recv(4096).decode() for _ in range(3)]
    assert msgs[0].splitlines()[:2] == ["READY=1", "STATUS=following leader"]
    assert msgs[1] == "WATCHDOG=1"
    assert msgs[2].startswith("STOPPING=1\n")


def test_notifier_without_socket_is_a_noop() -> None:
    with SystemdNotifier(NotifyConfig()) as n:
        assert not n.enabled
        assert not n.ready("x")


def test_notifier_survives_a_vanished_socket(tmp_path: Path) -> None:
    with SystemdNotifier(NotifyConfig(str(tmp_path / "gone.sock"))) as n:
        assert not n.watchdog()
        assert not n.watchdog()


async def test_status_server_roundtrip_mode_and_cleanup(tmp_path: Path) -> None:
    path = tmp_path / "run" / "status.sock"
    served = {"n": 0}

    def snapshot() -> dict[str, object]:
        served["n"] += 1
        return {"state": "FOLLOW", "n": served["n"]}

    async with StatusServer(path, {"status": snapshot}):
        assert stat.S_IMODE(path.stat().st_mode) == 0o660
        reply = await asyncio.to_thread(query_status, path, "status")
        assert reply == {"state": "FOLLOW", "n": 1}
        unknown = await asyncio.to_thread(query_status, path, "reboot")
        assert "unknown request" in unknown["error"]
        with pytest.raises(StatusSocketError, match="in use"):
            async with StatusServer(path, {}):
                pass
    assert not path.exists()
    with pytest.raises(ServiceNotRunningError, match="not running"):
        query_status(path)


async def test_status_server_hands_a_command_its_json_object(tmp_path: Path) -> None:
    """Commands travel as JSON objects (numbers stay numbers); words are for the plain requests only."""
    path = tmp_path / "s.sock"
    seen: list[Mapping[str, Any]] = []

    def command(req: Mapping[str, Any]) -> dict[str, object]:
        seen.append(req)
        return {"ok": True}

    request = json.dumps(command_request("set_offset", (0.0, 0.0, 6.0)))
    async with StatusServer(path, {"status": lambda: {"ok": True}}, commands={"command": command}):
        assert (await asyncio.to_thread(query_status, path, request))["ok"] is True
        for bad in (
            "status now",
            "command set_offset 0 0 6",
            '{"request": "command", "x": NaN}',
            "{not json",
        ):
            unknown = await asyncio.to_thread(query_status, path, bad)
            assert unknown["error"] == f"unknown request {bad!r}", bad
    assert seen == [{"request": "command", "name": "set_offset", "offset_cam_m": [0.0, 0.0, 6.0]}]


async def test_status_server_replaces_a_dead_socket(tmp_path: Path) -> None:
    path = tmp_path / "status.sock"
    dead = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    dead.bind(str(path))
    dead.close()  # file left behind, nobody listening
    async with StatusServer(path, {"status": lambda: {"ok": True}}):
        assert (await asyncio.to_thread(query_status, path))["ok"] is True
    (tmp_path / "plain").write_text("x")
    with pytest.raises(StatusSocketError, match="not a socket"):
        async with StatusServer(tmp_path / "plain", {}):
            pass


async def test_status_server_survives_a_silent_client(tmp_path: Path) -> None:
    path = tmp_path / "s.sock"
    async with StatusServer(path, {"status": lambda: {"ok": True}}) as server:
        _reader, writer = await asyncio.open_unix_connection(str(path))
        writer.write(b"stat")  # no newline, then hang up
        writer.close()
        await asyncio.sleep(0.05)
        assert (await asyncio.to_thread(query_status, path))["ok"] is True
        assert server.requests_served >= 1


def test_proc_parsers() -> None:
    text = "cpu  100 0 100 800 0 0 0 0 0 0\ncpu0 50 0 50 400 0 0 0 0\ncpu1 50 0 50 400 0 0 0 0\nintr 1\n"
    total, cores = parse_proc_stat(text)
    assert total is not None
    assert total.busy == 200
    assert total.total == 1000
    assert len(cores) == 2
    later, _ = parse_proc_stat("cpu  150 0 150 900 0 0 0 0\n")
    assert later is not None
    assert cpu_percent(total, later) == pytest.approx(50.0)
    assert parse_meminfo("MemTotal: 2048 kB\nMemAvailable: 1024 kB\n") == (1.0, 2.0)


def test_system_monitor_reads_a_fake_jetson_tree(tmp_path: Path) -> None:
    (tmp_path / "proc").mkdir()
    (tmp_path / "proc/loadavg").write_text("0.52 0.40 0.30 1/200 999\n")
    (tmp_path / "proc/meminfo").write_text("MemTotal: 8000000 kB\nMemAvailable: 6000000 kB\n")
    stat_path = tmp_path / "proc/stat"
    stat_path.write_text("cpu  100 0 100 800\ncpu0 100 0 100 800\n")
    for i, (kind, milli) in enumerate(
        [("cpu-thermal", "45500"), ("GPU-therm", "41000"), ("PMIC-Die", "-256000")]
    ):
        z = tmp_path / f"sys/class/thermal/thermal_zone{i}"
        z.mkdir(parents=True)
        (z / "type").write_text(kind + "\n")
        (z / "temp").write_text(milli + "\n")
    gpu = tmp_path / "sys/devices/platform/gpu.0"
    gpu.mkdir(parents=True)
    (gpu / "load").write_text("613\n")
    mon = SystemMonitor(tmp_path)
    first = mon.read()
    assert first.cpu_percent is None  # no interval yet
    stat_path.write_text("cpu  200 0 100 900\ncpu0 200 0 100 900\n")
    r = mon.read()
    assert r.load_1m == 0.52
    assert r.cpu_percent == pytest.approx(50.0)
    assert r.cpu_core_percent == (50.0,)
    assert r.mem_total_mib == pytest.approx(7812.5)
    assert r.mem_used_mib == pytest.approx(1953.125)
    assert r.temperatures_c == {"cpu-thermal": 45.5, "GPU-therm": 41.0}
    assert r.gpu_percent == pytest.approx(61.3)


def test_system_monitor_on_this_machine() -> None:
    mon = SystemMonitor()
    mon.read()
    r = mon.read()
    assert r.mem_total_mib is not None
    assert r.mem_total_mib > 0
    assert r.load_1m is not None
    assert os.cpu_count()
