"""A signed flight: `companion run` flies `sitl serve` over MAVLink 2 signing; unsigned input is ignored.

The service starts with ``link.signing`` and ``link.signing_provision``: its relay gives the simulator's
follower the key while it is disarmed, then everything between them is signed. In FOLLOW:

- an unsigned COMMAND_LONG (land) from another system id, sent to the follower's own port and to its
  ground-station port, goes unanswered, and the follower keeps following in the air;
- unsigned HEARTBEATs claiming the follower's system id, sent to the service's port, are reported as
  an impostor and never reach MAVSDK;
- ``companion status --json`` shows the relay's counters.

SIGTERM then lands the follower through the signed link (the service's land and disarm are obeyed).
The helpers (``tests/signing_probe.py``) take any autopilot UDP address, so the same flight runs against
PX4 SITL.
"""

from __future__ import annotations

import asyncio
import json
import os
import secrets
import signal
import socket
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from pymavlink.dialects.v20 import common as mavlink2

from companion.kernel import compat
from companion.lab.evaluation.procs import SitlPorts as Ports
from tests.mosquitto import Collector, Mosquitto
from tests.service.sitl_service import open_gcs, service_config, service_process, sim_process
from tests.signing_probe import MavPeer, send_impostor_heartbeats, write_key

pytestmark = [pytest.mark.sitl, pytest.mark.mqtt_broker, pytest.mark.slow, pytest.mark.timeout(300)]

FOLLOWER = 2


async def until(cond: Callable[[], bool], timeout_s: float, what: str, logs: Callable[[], str]) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}\n--- logs ---\n{logs()[-4000:]}")
        await asyncio.sleep(0.1)


async def status_json(repo_root: Path, cfg: Path) -> dict[str, Any]:
    proc = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "companion",
        "status",
        "--json",
        "--config",
        str(cfg),
        cwd=repo_root,
        env={**os.environ, "PYTHONPATH": str(repo_root)},
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
    )
    out, _ = await asyncio.wait_for(proc.communicate(), 60)
    data: dict[str, Any] = json.loads(out)
    return data


def signed_config(tmp_path: Path, ports: Ports, cam: Path, broker_port: int, key_file: Path) -> Path:
    """The end-to-end test's service config, flying over a signed link straight to the simulator."""
    cfg = service_config(tmp_path, ports.follower_api, cam, broker_port)
    text = cfg.read_text().replace(
        "[link]\n",
        f'[link]\nsystem_id = {FOLLOWER}\nsigning = true\nsigning_key_file = "{key_file}"\n'
        "signing_provision = true\n",
        1,
    )
    text = text.replace("[service]\n", f'[service]\nstate_dir = "{tmp_path / "state"}"\n', 1)
    cfg.write_text(text)
    return cfg


async def test_the_service_flies_signed_and_unsigned_commands_do_not_land_it(
    tmp_path: Path, repo_root: Path
) -> None:
    ports = Ports.pick()
    cam = tmp_path / "cam.sock"
    key_file = write_key(tmp_path / "signing.key", secrets.token_bytes(32))
    notify_path = tmp_path / "notify.sock"
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    notify.bind(str(notify_path))
    sim = sim_process(tmp_path, ports, cam)
    svc = None
    gcs_transport = None
    attacker: MavPeer | None = None
    with Mosquitto(tmp_path) as broker, notify:
        collector = Collector(broker.port, "wingman/follower1/state")

        def logs() -> str:
            return (svc.log() if svc else "") + "\n--- sitl ---\n" + sim.log()[-1500:]

        try:
            sim.start()
            gcs_transport, gcs = await open_gcs(ports.gcs_remote)
            await until(lambda: "running at" in sim.log() and cam.exists(), 90, "the simulator", logs)
            cfg = signed_config(tmp_path, ports, cam, broker.port, key_file)
            async with compat.TaskGroup() as tg:
                collecting = tg.create_task(collector.run(), name="test.collector")
                await asyncio.wait_for(collector.subscribed.wait(), 10)
                svc = service_process(tmp_path, cfg, notify_path)
                svc.start()

                def state() -> str | None:
                    states = collector.payloads("state")
                    return str(states[-1]["state"]) if states else None

                await until(lambda: state() == "follow", 150, "FOLLOW over the signed link", logs)
                assert "MAVLink signing key accepted" in sim.log()
                await asyncio.sleep(2.0)

                # An unsigned land from system 200 at the follower's own port and at its GCS port.
                follower_port = ("127.0.0.1", ports.api_local + 1)
                attacker = await MavPeer.open(follower_port, src=(200, 190))
                land = mavlink2.MAVLink_command_long_message(
                    FOLLOWER, 1, mavlink2.MAV_CMD_NAV_LAND, 0, 0, 0, 0, 0, 0, 0, 0
                )
                for port in (ports.api_local + 1, ports.follower_gcs):
                    attacker.addr = ("127.0.0.1", port)
                    for _ in range(3):
                        attacker.send(land)
                # Unsigned heartbeats claiming to be the follower, at the service's own port.
                send_impostor_heartbeats(("127.0.0.1", ports.follower_api), FOLLOWER, count=5)
                alts: list[float] = []
                t_end = time.monotonic() + 5.0
                while time.monotonic() < t_end:
                    assert state() == "follow", f"left FOLLOW: {state()}\n{logs()[-3000:]}"
                    if gcs.relative_alt_m is not None:
                        alts.append(gcs.relative_alt_m)
                    await asyncio.sleep(0.2)
                acks = [m for m in attacker.received if m.get_type() == "COMMAND_ACK"]
                assert acks == [], "an unsigned command was answered"
                assert bool(gcs.armed)
                assert gcs.landed_state == mavlink2.MAV_LANDED_STATE_IN_AIR
                assert min(alts) > 3.0, alts

                st = await status_json(repo_root, cfg)
                signing = st["mavlink_signing"]
                print("signing relay:", json.dumps(signing))
                assert signing["autopilot_signs"] is True
                assert signing["counters"]["out_signed"] > 200
                assert signing["counters"]["in_signed"] > 200
                assert sum(signing["impostors"].values()) == 5, "exactly the impostor's heartbeats"
                assert signing["provision_attempts"] >= 1
                # The follower's streams reached the land's sender too (the simulator answers any peer):
                # all signed.
                assert attacker.signed_from.get(FOLLOWER, 0) > 10
                assert attacker.unsigned_from.get(FOLLOWER, 0) == 0

                svc.signal(signal.SIGTERM)
                rc = await svc.wait(150)
                collecting.cancel()
            assert rc == 0, logs()
            assert gcs.armed is False
            assert gcs.on_ground
        except BaseException:
            print(
                "--- service log ---\n",
                svc.log()[-8000:] if svc else "",
                "\n--- sitl log ---\n",
                sim.log()[-2000:],
            )
            raise
        finally:
            if svc is not None:
                await svc.stop()
            await sim.stop()
            if attacker is not None:
                attacker.close()
            if gcs_transport is not None:
                gcs_transport.close()
    log = svc.log() if svc else ""
    assert "sent the key to autopilot system 2" in log
    assert "claimed by a frame that is not signed with our key" in log
