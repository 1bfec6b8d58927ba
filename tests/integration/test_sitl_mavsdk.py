"""Unmodified MAVSDK 4 (native) scripts against ``sitl serve`` over real UDP, as against PX4 SITL.

Each test starts its own simulator (one vehicle, 4x real time) on free ports. Timelines are checked
in sim time, read from the vehicle's own ``time_boot_ms`` on the GCS link (a QGC-like listener), so
a loaded host that slows the simulator down cannot fake or break them.
"""

from __future__ import annotations

import asyncio
import contextlib
import re
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.integration.sitl_process import GcsListener, SitlProcess, open_gcs_listener, sitl_serve

mavsdk = pytest.importorskip("mavsdk")
from mavsdk.asyncio import ComponentType, Configuration, Mavsdk  # noqa: E402
from mavsdk.asyncio.plugins.action import ActionAsync  # noqa: E402
from mavsdk.asyncio.plugins.failure import FailureAsync  # noqa: E402
from mavsdk.asyncio.plugins.offboard import OffboardAsync, VelocityNedYaw  # noqa: E402
from mavsdk.asyncio.plugins.telemetry import TelemetryAsync  # noqa: E402
from mavsdk.plugins.failure import FailureType, FailureUnit  # noqa: E402
from mavsdk.plugins.offboard import OffboardError, OffboardResult  # noqa: E402
from mavsdk.plugins.telemetry import FixType, FlightMode  # noqa: E402

pytestmark = [pytest.mark.sitl, pytest.mark.slow, pytest.mark.timeout(240)]

SPEED = 4.0
SYSID = 1
AUTO_LAND = 100925440
GPS_BIT = 32  # MAV_SYS_STATUS_SENSOR_GPS
AUTO_RTL = 84148224


@pytest.fixture
def one_vehicle(tmp_path: Path) -> Iterator[SitlProcess]:
    cfg = tmp_path / "sitl.toml"
    cfg.write_text('schema_version = 1\n[[vehicles]]\nname = "follower"\n')
    with sitl_serve(speed=SPEED, config=cfg, vehicles=1) as sim:
        yield sim
    out = "\n".join(sim.output)
    errors = [int(x) for x in re.findall(r"handler errors (\d+)", out)]
    assert errors, out[-3000:]
    assert errors == [0] * len(errors), errors


@contextlib.asynccontextmanager
async def connected(sim: SitlProcess) -> AsyncIterator[Any]:
    cfg = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
    async with Mavsdk(cfg) as sdk:
        await sdk.add_any_connection(sim.api_url(0))
        system = await sdk.first_autopilot(timeout_s=20.0)
        assert system is not None, "MAVSDK found no autopilot"
        yield system


async def sim_sleep(gcs: GcsListener, seconds: float) -> float:
    """Sleep ``seconds`` of *sim* time; returns the sim time reached."""
    end = gcs.sim_s[SYSID] + seconds
    await gcs.wait_for(lambda r: r[0] == SYSID and r[1] >= end, timeout_s=seconds / SPEED * 4 + 10)
    return gcs.sim_s[SYSID]


async def until(gen: Any, pred: Any, timeout_s: float) -> Any:
    async with asyncio.timeout(timeout_s), contextlib.aclosing(gen) as it:
        async for item in it:
            if pred(item):
                return item
    raise AssertionError("stream ended")


async def take_off(system: Any, gcs: GcsListener) -> tuple[TelemetryAsync, ActionAsync, OffboardAsync]:
    tel, act, off = TelemetryAsync(system), ActionAsync(system), OffboardAsync(system)
    await until(tel.subscribe_health(), lambda h: h.is_global_position_ok and h.is_home_position_ok, 60)
    await act.set_takeoff_altitude(5.0)
    assert await act.get_takeoff_altitude() == pytest.approx(5.0)
    await act.arm()
    await act.takeoff()
    await until(tel.subscribe_position(), lambda p: p.relative_altitude_m > 4.6, 60)
    await until(tel.subscribe_flight_mode(), lambda m: m == FlightMode.HOLD, 30)
    await sim_sleep(gcs, 3.0)
    return tel, act, off


async def test_takeoff_offboard_velocity_land_and_auto_disarm(one_vehicle: SitlProcess) -> None:
    gcs = await open_gcs_listener(one_vehicle.ports.gcs_remote)
    async with connected(one_vehicle) as system:
        tel, act, off = await take_off(system, gcs)
        p0 = (await tel.position_velocity_ned()).position
        assert -p0.down_m == pytest.approx(5.0, abs=0.5)
        await off.set_velocity_ned(VelocityNedYaw(2.0, 0.0, 0.0, 0.0))
        await off.start()  # returns on the ACK: the vehicle is in offboard from here
        t_start = gcs.sim_s[SYSID]
        await gcs.wait_for(lambda r: r[0] == SYSID and r[1] >= t_start + 5.0, timeout_s=30)
        await off.set_velocity_ned(VelocityNedYaw(0.0, 0.0, 0.0, 0.0))
        assert gcs.of(SYSID, "HEARTBEAT", since_s=t_start + 1.0)[0][1].custom_mode == 393216
        await sim_sleep(gcs, 3.0)
        p1 = (await tel.position_velocity_ned()).position
        moved_n = p1.north_m - p0.north_m
        print(
            f"offboard north 2 m/s for 5 s: moved {moved_n:.2f} m north, {p1.east_m - p0.east_m:.2f} m east"
        )
        assert moved_n == pytest.approx(10.0, abs=1.5)
        assert abs(p1.east_m - p0.east_m) < 1.0
        await off.stop()
        await act.land()
        await until(tel.subscribe_armed(), lambda armed: not armed, 120)  # nobody disarms: PX4 does
        assert await tel.landed_state() is not None
    texts = [m.text for _, m in gcs.of(SYSID, "STATUSTEXT")]
    assert "Disarmed by landing" in texts


async def test_offboard_refused_without_stream_and_loss_failsafe(one_vehicle: SitlProcess) -> None:
    gcs = await open_gcs_listener(one_vehicle.ports.gcs_remote)
    async with connected(one_vehicle) as system:
        tel, _, off = await take_off(system, gcs)
        # MAVSDK refuses locally without a setpoint...
        with pytest.raises(OffboardError) as err:
            await off.start()
        assert err.value.result == OffboardResult.NO_SETPOINT_SET
        # ...and the vehicle refuses a raw switch in the air without a stream, as PX4 does.
        assert await gcs.command(SYSID, 176, 129.0, 6.0, 0.0) == 1  # TEMPORARILY_REJECTED
        await gcs.wait_for(
            lambda r: (
                r[2].get_type() == "STATUSTEXT"
                and "Switching to Offboard is currently not available" in r[2].text
            ),
            timeout_s=5,
        )
        assert await tel.flight_mode() == FlightMode.HOLD
        await off.set_velocity_ned(VelocityNedYaw(0.0, 0.0, 0.0, 0.0))
        await off.start()
        await until(tel.subscribe_flight_mode(), lambda m: m == FlightMode.OFFBOARD, 10)
        await sim_sleep(gcs, 2.0)
    # Closing MAVSDK stops the 20 Hz stream without a mode change: the offboard-loss failsafe.
    t_stop = gcs.sim_s[SYSID]
    rec = await gcs.wait_for(
        lambda r: r[0] == SYSID and r[2].get_type() == "HEARTBEAT" and r[2].custom_mode == AUTO_RTL,
        timeout_s=30,
    )
    delay = rec[1] - t_stop
    print(f"offboard loss -> Return after {delay:.2f} s sim (COM_OF_LOSS_T 1 s x speed {SPEED})")
    # COM_OF_LOSS_T scales with the speed factor, as in PX4 SITL; heartbeats come at 1 Hz.
    assert SPEED * 1.0 - 0.5 <= delay <= SPEED * 1.0 + 2.0
    texts = [m.text for _, m in gcs.of(SYSID, "STATUSTEXT")]
    assert "Failsafe activated: switching to Return" in texts


async def test_gps_failure_injection_follows_px4_timeline(one_vehicle: SitlProcess) -> None:
    gcs = await open_gcs_listener(one_vehicle.ports.gcs_remote)
    async with connected(one_vehicle) as system:
        tel, _, off = await take_off(system, gcs)
        await off.set_velocity_ned(VelocityNedYaw(1.0, 0.0, 0.0, 0.0))
        await off.start()
        await until(tel.subscribe_flight_mode(), lambda m: m == FlightMode.OFFBOARD, 10)
        await sim_sleep(gcs, 2.0)
        seen: set[str] = set()  # what MAVSDK reported; the timing is read off the wire below

        async def watch_gps() -> None:
            async for info in tel.subscribe_gps_info():
                if info.fix_type == FixType.NO_GPS:
                    seen.add("no_fix")

        async def watch_mode() -> None:
            async for mode in tel.subscribe_flight_mode():
                if mode == FlightMode.LAND:
                    seen.add("land")

        async def watch_health() -> None:
            async for health in tel.subscribe_health():
                if not health.is_global_position_ok:
                    seen.add("global_not_ok")

        async def watch_text() -> None:
            async for st in tel.subscribe_status_text():
                if st.text == "GNSS data fusion stopped":
                    seen.add("fusion_stopped")

        async with asyncio.TaskGroup() as tg:
            watchers = [
                tg.create_task(w(), name=f"test.{w.__name__}")
                for w in (watch_gps, watch_mode, watch_health, watch_text)
            ]
            since_s = gcs.sim_s[SYSID]
            await FailureAsync(system).inject(FailureUnit.SENSOR_GPS, FailureType.OFF, 0)
            await sim_sleep(gcs, 10.0)
            for w in watchers:
                w.cancel()
    # Times come from the SITL's own time_boot_ms on the GCS link, not from when a callback ran: at 4x
    # speed a 0.15 s scheduling stall on a loaded 2-core runner is 0.6 s of sim time.
    wire = [(t, m) for t, m in gcs.of(SYSID, "STATUSTEXT", since_s) if "GPS off" in m.text]
    assert wire, "no STATUSTEXT acknowledging the injected GPS failure"
    t0 = wire[0][0]

    def first(msg_type: str, pred: Any) -> float:
        hits = [t for t, m in gcs.of(SYSID, msg_type, t0) if pred(m)]
        assert hits, f"no {msg_type} on the wire showing the event"
        return hits[0] - t0

    rel = {
        "no_fix": first("GPS_RAW_INT", lambda m: m.fix_type <= 1),
        "land": first("HEARTBEAT", lambda m: m.custom_mode == AUTO_LAND),
        "global_not_ok": first("SYS_STATUS", lambda m: not m.onboard_control_sensors_health & GPS_BIT),
        "fusion_stopped": first("STATUSTEXT", lambda m: m.text == "GNSS data fusion stopped"),
    }
    print(f"GPS off at sim {t0:.2f} s; events after it (sim s): { {k: round(v, 2) for k, v in rel.items()} }")
    assert seen == set(rel), f"MAVSDK saw only {sorted(seen)}"
    # GPS_RAW_INT, HEARTBEAT and SYS_STATUS go at 1 Hz on the GCS link, so each can show up to 1 s late.
    assert rel["no_fix"] <= 2.1  # "no GPS" after 1 s without receiver data
    assert 4.5 <= rel["land"] <= 6.1  # Descend at EKF2_NOAID_TOUT, reported as AUTO.LAND
    # GNSS fusion stops 7 s after the last fused sample (reset_timeout_max); the GPS health bit goes with it.
    assert 6.5 <= rel["fusion_stopped"] <= 7.2
    assert 6.9 <= rel["global_not_ok"] <= 8.2
    # The raw wire agrees: AUTO.LAND with system_status CRITICAL.
    beats = [m for t, m in gcs.of(SYSID, "HEARTBEAT", since_s=t0 + 6.7)]
    assert beats
    assert all(m.custom_mode == AUTO_LAND and m.system_status == 5 for m in beats if m.base_mode & 128)


async def test_health_reads_the_offboard_loss_failsafe_and_never_writes_it(
    one_vehicle: SitlProcess, tmp_path: Path
) -> None:
    """`companion health` with no service running: the autopilot check says what PX4 does on offboard loss
    (the simulator keeps PX4's default, 0), and the probe leaves the parameter as it found it."""
    import json
    import os
    import subprocess
    import sys

    from mavsdk.asyncio.plugins.param import ParamAsync

    env = {
        **os.environ,
        "WINGMAN_STATUS__SOCKET_PATH": str(tmp_path / "none.sock"),
        "WINGMAN_DETECTOR__RUNTIME": "truth",
        "WINGMAN_LINK__URL": one_vehicle.api_url(0),
        # The lone simulated vehicle is system 1, the shipped config's leader id: name it as ours, and the
        # leader as another system, or the probe rightly refuses it.
        "WINGMAN_LINK__SYSTEM_ID": str(SYSID),
        "WINGMAN_LEADER__MAVLINK_SYSTEM_ID": "9",
        "WINGMAN_CAMERA__PATH": str(tmp_path / "cam.sock"),
    }
    r = await asyncio.to_thread(
        subprocess.run,
        [sys.executable, "-m", "companion", "health", "--json", "--timeout", "20"],
        env=env,
        capture_output=True,
        text=True,
        timeout=90,
        check=False,
    )
    checks = {c["name"]: c for c in json.loads(r.stdout)["checks"]}
    auto = checks["autopilot"]
    print("health autopilot:", auto["detail"])
    assert auto["ok"], auto
    assert "offboard loss: Position (without RC: NAV_RCL_ACT, default Return)" in auto["detail"], auto
    async with connected(one_vehicle) as system:
        assert await ParamAsync(system).get_param_int("COM_OBL_RC_ACT") == 0
