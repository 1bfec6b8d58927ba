"""The service end to end in the simulator: `companion run` as a process against `sitl serve`.

One flight covers it all: MQTT state/pose/health from a real mosquitto, a broker stop and
restart mid-flight (nothing lost beyond the buffer, the flight goes on), `companion status --json` and
`companion health --json` against the running service, and SIGTERM during FOLLOW (the vehicle lands and
disarms, the service exits 0). sd_notify READY/STATUS/WATCHDOG/STOPPING go to a socket of the test's.

Perception runs for real (renderer -> latest-frame mailbox -> pose -> tracker -> mission) except the
detector: ``detector.runtime = "truth"`` takes the renderer's ground-truth boxes, as no trained weights are
in the repository yet. The leader hovers 8 m ahead, then drifts north at 0.5 m/s.
"""

from __future__ import annotations

import asyncio
import json
import os
import signal
import socket
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from companion.kernel import compat
from companion.service.status import ServiceNotRunningError, query_status
from tests.flight.wiretap import WireTap, open_wiretap
from tests.mosquitto import Collector, Mosquitto
from tests.service.sitl_service import (
    Ports,
    open_gcs,
    service_config,
    service_process,
    sim_process,
)

pytestmark = [pytest.mark.sitl, pytest.mark.mqtt_broker, pytest.mark.slow, pytest.mark.timeout(300)]


async def until(cond: Callable[[], bool], timeout_s: float, what: str, logs: Callable[[], str]) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}\n--- logs ---\n{logs()[-4000:]}")
        await asyncio.sleep(0.1)


async def cli(repo_root: Path, *args: str) -> tuple[int, Any]:
    proc = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "companion",
        *args,
        cwd=repo_root,
        env={**os.environ, "PYTHONPATH": str(repo_root)},
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
    )
    out, err = await asyncio.wait_for(proc.communicate(), 60)
    assert proc.returncode is not None
    try:
        return proc.returncode, json.loads(out)
    except json.JSONDecodeError:
        raise AssertionError(f"not JSON: {out!r} {err!r}") from None


def status(path: Path) -> dict[str, Any] | None:
    try:
        return query_status(path, timeout_s=2.0)
    except ServiceNotRunningError:
        return None


async def test_service_flies_reports_survives_a_broker_restart_and_lands_on_sigterm(
    tmp_path: Path, repo_root: Path
) -> None:
    ports = Ports.pick()
    cam = tmp_path / "cam.sock"
    notify_path = tmp_path / "notify.sock"
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    notify.bind(str(notify_path))
    notify.setblocking(False)
    sim = sim_process(tmp_path, ports, cam)
    svc = None
    gcs_transport = None
    tap: WireTap | None = None
    with Mosquitto(tmp_path) as broker, notify:
        collector = Collector(broker.port, "wingman/follower1/#")
        try:
            sim.start()
            gcs_transport, gcs = await open_gcs(ports.gcs_remote)

            def logs() -> str:
                return (svc.log() if svc else "") + "\n--- sitl ---\n" + sim.log()[-1500:]

            await until(lambda: "running at" in sim.log() and cam.exists(), 90, "the simulator", logs)
            # What the service says to the autopilot, decoded at the autopilot's socket.
            tap = await open_wiretap(ports.follower_api, ports.client)
            tap.keep = frozenset({"STATUSTEXT", "ONBOARD_COMPUTER_STATUS"})
            cfg = service_config(tmp_path, ports.client, cam, broker.port)
            sock = tmp_path / "run" / "status.sock"
            datagrams: list[str] = []

            async def read_notify() -> None:
                # Read as systemd does: a Unix datagram queue holds only ~10 messages.
                loop = asyncio.get_running_loop()
                while True:
                    datagrams.append((await loop.sock_recv(notify, 4096)).decode())

            async with compat.TaskGroup() as tg:
                collecting = tg.create_task(collector.run(), name="test.collector")
                notifying = tg.create_task(read_notify(), name="test.notify")
                await asyncio.wait_for(collector.subscribed.wait(), 10)
                svc = service_process(tmp_path, cfg, notify_path)
                svc.start()

                def state() -> str | None:
                    states = collector.payloads("state")
                    return states[-1]["state"] if states else None

                await until(lambda: state() == "follow", 150, "FOLLOW", logs)
                await asyncio.sleep(2.0)  # a little formation flight first

                # -- companion status / health against the running service
                rc, st = await cli(repo_root, "status", "--json", "--config", str(cfg))
                assert rc == 0
                assert st["mission"]["state"] == "follow", st["mission"]
                assert st["link"]["connected"] is True
                assert st["link"]["armed"] is True
                assert st["link"]["in_air"] is True
                # The service set PX4's offboard-loss action to Hold on connect (link.offboard_loss_action).
                assert st["link"]["offboard_loss_failsafe"] == "Hold"
                assert st["gps"]["fix_type"] >= 3
                assert st["leader"]["status"] in ("confirmed", "coasting")
                assert 5.0 < st["leader"]["range_m"] < 11.0
                assert len(st["leader"]["cov_ned_m2"]) == 3
                lat = st["latency_ms"]
                assert {"detect", "track", "end_to_end", "telemetry_age", "camera_age"} <= set(lat), lat
                # What the tick flies on: attitude telemetry streams at 50 Hz over the loopback, and the
                # leader estimate is one frame's pipeline old.
                assert 0.0 <= lat["telemetry_age"]["p50_ms"] <= lat["telemetry_age"]["p95_ms"] < 500.0
                assert lat["detect"]["p50_ms"] < lat["camera_age"]["p50_ms"] < 2000.0
                assert st["frames"]["received"] > 20
                assert st["frames"]["processed"] + st["frames"]["dropped"] <= st["frames"]["received"]
                assert st["system"]["mem_total_mib"] > 0
                assert st["mqtt"]["connected"] is True
                rc, health = await cli(repo_root, "health", "--json", "--config", str(cfg))
                checks = {c["name"]: c for c in health["checks"]}
                assert health["service_running"] is True
                assert set(checks) >= {
                    "config",
                    "model",
                    "autopilot",
                    "gps",
                    "mission",
                    "camera",
                    "perception",
                    "broker",
                }
                for name in ("config", "autopilot", "gps", "mission", "camera", "broker"):
                    assert checks[name]["ok"], checks[name]
                assert rc == (0 if health["healthy"] else 1)
                print("health:", rc, [(c["name"], c["ok"]) for c in health["checks"]])
                print(
                    "latency p50/p99 ms:",
                    {k: (v["p50_ms"], v["p99_ms"]) for k, v in st["latency_ms"].items()},
                )

                # -- the broker goes away for 3 s mid-flight, then comes back
                states_before = len(collector.payloads("state"))
                broker.stop()
                step_ages: list[float] = []
                airborne: list[bool] = []
                t_end = time.monotonic() + 3.0
                while time.monotonic() < t_end:
                    snap = await asyncio.to_thread(status, sock)
                    assert snap is not None, "the status endpoint must not depend on the broker"
                    step_ages.append(snap["mission"]["step_age_s"])
                    airborne.append(snap["link"]["armed"] and snap["link"]["in_air"])
                    await asyncio.sleep(0.2)
                buffered = snap["mqtt"]["buffered"]
                print(f"broker outage: {buffered} buffered, max control step gap {max(step_ages):.3f} s")
                broker.start()
                await until(
                    lambda: len(collector.payloads("state")) > states_before + buffered + 3,
                    30,
                    "state messages after the broker restart",
                    logs,
                )
                after = await asyncio.to_thread(status, sock)
                assert after is not None
                assert after["mqtt"]["connected"] is True
                assert after["mqtt"]["dropped"] == 0
                assert buffered >= 10  # the outage was real: messages waited in the buffer
                # The flight did not notice: the control loop kept stepping at its rate, still flying.
                assert max(step_ages) < 0.5, step_ages
                assert all(airborne)
                assert gcs.armed is True

                # -- SIGTERM during FOLLOW
                t_sig = time.monotonic()
                svc.signal(signal.SIGTERM)
                rc = await svc.wait(150)
                landing_s = time.monotonic() - t_sig
                collecting.cancel()
                notifying.cancel()
            assert rc == 0, logs()
            assert gcs.armed is False
            assert gcs.on_ground
            assert gcs.relative_alt_m is not None
            assert abs(gcs.relative_alt_m) < 0.5
        except BaseException:
            # Failures on the shared machine are hard to reproduce: leave the evidence in the report.
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
            if tap is not None:
                tap.close()
            if gcs_transport is not None:
                gcs_transport.close()

    print(f"SIGTERM to exit: {landing_s:.1f} s")
    states = collector.payloads("state")
    seqs = sorted({p["seq"] for p in states if p.get("seq") is not None})
    assert seqs == list(range(seqs[-1] + 1)), "a state message was lost"
    assert states[-1]["online"] is False
    final = [p for p in states if p.get("online")][-1]
    assert final["armed"] is False
    assert final["in_air"] is False
    assert any(p["state"] == "follow" for p in states)
    poses = collector.payloads("pose")
    assert any(p.get("leader") for p in poses)
    healths = collector.payloads("health")
    assert healths
    assert healths[-1]["frames"]["received"] > 0
    events = collector.payloads("events")
    kinds = [e["kind"] for e in events]
    assert "shutdown" in kinds
    shutdown_at = kinds.index("shutdown")
    after_stop = [e["data"].get("to") for e in events[shutdown_at:] if e["kind"] == "state_change"]
    assert "px4_land" in after_stop or "controlled_landing" in after_stop, after_stop
    # To the ground station over MAVLink: a STATUSTEXT per transition, ONBOARD_COMPUTER_STATUS at 1 Hz.
    assert tap is not None
    texts = [s.msg.text for s in tap.seen if s.to_vehicle and s.msg.get_type() == "STATUSTEXT"]
    assert "WM follow: leader acquired" in texts, texts
    assert "WM px4_hold: shutdown requested" in texts, texts
    onboard = [s.msg for s in tap.seen if s.to_vehicle and s.msg.get_type() == "ONBOARD_COMPUTER_STATUS"]
    assert len(onboard) >= 10
    assert onboard[-1].ram_total > 0
    assert 0 < onboard[-1].ram_usage <= onboard[-1].ram_total
    assert onboard[-1].uptime > 10_000
    assert onboard[-1].cpu_combined[0] <= 100
    text = "\n".join(datagrams)
    for line in ("READY=1", "WATCHDOG=1", "STOPPING=1", "STATUS=follow"):
        assert line in text, line
