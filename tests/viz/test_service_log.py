"""The service with ``[viz]``: a flight log in the state folder; a live view it cannot serve is one line."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import socket
import time
from pathlib import Path

import pytest
from mcap.reader import make_reader

from companion.app import FollowerService, Parts, PartsContext
from companion.config import Config
from companion.kernel import compat
from companion.kernel.clock import MonotonicClock
from companion.perception.sources.mcap_file import protobuf_class
from companion.service.flight import FlightService
from companion.service.systemd import NotifyConfig, SystemdNotifier
from companion.service.wiring import open_recorder
from tests.service.test_wiring import LandingAutopilot
from tests.unit.mission_harness import leader
from tests.unit.test_mission_runner import RecordingLink


async def test_the_service_logs_its_flight_and_flies_on_without_a_live_view_it_cannot_serve(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    taken = socket.socket()
    taken.bind(("127.0.0.1", 0))
    taken.listen()
    port = taken.getsockname()[1]
    clock = MonotonicClock()
    cfg = Config.model_validate(
        {
            "mission": {"shutdown_action": "land"},
            "status": {"socket_path": str(tmp_path / "status.sock")},
            "service": {"auto_start": True, "shutdown_timeout_s": 10.0, "state_dir": str(tmp_path)},
            "viz": {"live": True, "port": port, "log": True},
        }
    )
    link = RecordingLink(LandingAutopilot(), clock)
    flight = FlightService(cfg, link, clock)  # type: ignore[arg-type]

    async def open_parts(stack: contextlib.AsyncExitStack, ctx: PartsContext) -> Parts:
        rec = open_recorder(cfg, flight, clock, ctx, stack)
        return Parts(mission=flight, extra_status={"viz": rec.counters})

    async def feed() -> None:
        while True:
            flight.runner.submit_leader(leader(clock.now_s()))
            await asyncio.sleep(0.02)

    with caplog.at_level(logging.WARNING), SystemdNotifier(NotifyConfig()) as notifier:
        svc = FollowerService(cfg, open_parts, clock=clock, wall_time_s=time.time, notifier=notifier)
        async with compat.timeout(30), compat.TaskGroup() as tg:
            feeder = tg.create_task(feed())
            task = tg.create_task(svc.run())
            for _ in range(400):
                if flight.snapshot().state == "follow":
                    break
                await asyncio.sleep(0.05)
            await asyncio.sleep(1.2)  # a health sample
            svc.request_stop("SIGTERM")
            code = await task
            feeder.cancel()
    taken.close()
    assert code == 0
    said = [r.getMessage() for r in caplog.records if r.name.startswith("companion.viz")]
    assert said == [f"live view off: cannot serve on 127.0.0.1:{port}: " + said[0].split(f"{port}: ", 1)[1]]
    assert said[0].endswith("; the flight goes on without it")
    logs = list((tmp_path / "flights").glob("follower1-*.mcap"))
    assert len(logs) == 1
    with logs[0].open("rb") as f:
        reader = make_reader(f)
        lines = [
            protobuf_class(s.name, s.data).FromString(m.data).message
            for s, _, m in reader.iter_messages(topics=["/mission/log"])
        ]
        f.seek(0)
        health = [json.loads(m.data) for _, _, m in make_reader(f).iter_messages(topics=["/service/health"])]
    assert "acquire -> follow: leader acquired" in lines
    assert any("land" in line for line in lines[lines.index("acquire -> follow: leader acquired") :])
    assert any("mission" in h.get("components", {}) for h in health)
