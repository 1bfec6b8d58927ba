"""MavsdkVehicleLink end to end against ``sitl serve`` through real MAVSDK over UDP.

Arm, take off, offboard velocity, attitude+thrust, the setpoint guard, PX4 Land and the auto-disarm, with
what reached the vehicle checked on the wire.
"""

from __future__ import annotations

import asyncio
import math
import time
from pathlib import Path

import numpy as np
import pytest
from mavsdk.plugins.offboard import OffboardResult

from companion.config import Config
from companion.kernel.errors import CommandRejectedError
from companion.kernel.flight import (
    AttitudeSetpoint,
    FlightMode,
    LandedState,
    Severity,
    VelocityNedSetpoint,
)

from .harness import FOLLOWER, bare_link, sitl_missing_reason
from .wiretap import CUSTOM_MODE_OFFBOARD

pytestmark = [
    pytest.mark.sitl,
    pytest.mark.slow,
    pytest.mark.skipif(sitl_missing_reason() is not None, reason=str(sitl_missing_reason())),
]


async def _until(pred: object, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not pred():  # type: ignore[operator]
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        await asyncio.sleep(0.05)


async def test_link_arm_takeoff_velocity_attitude_guard_land(tmp_path: Path) -> None:
    cfg = Config()
    async with bare_link(tmp_path, cfg) as (link, tap, feed, _ports):
        await _until(
            lambda: link.snapshot().position_valid and link.snapshot().home_position_ok, 30, "a position"
        )
        s = link.snapshot()
        assert s.connected
        # Attitude is stamped when PX4 sampled it (time_boot_ms mapped onto our clock): recent, never ahead.
        age_s = link.clock.now_s() - s.attitude_stamp_s
        assert 0.0 <= age_s < 0.5, age_s
        assert s.gps_fix_type >= 3
        assert s.hover_thrust_norm is not None
        # The offboard-loss failsafe was set to Hold through MAVSDK's param plugin and read back from PX4.
        await _until(lambda: link.snapshot().offboard_loss_param == 5, 10, "COM_OBL_RC_ACT = 5 (Hold)")
        await link.send_status_text("WM link test", Severity.INFO)

        await link.arm()
        await link.takeoff(4.0)
        await _until(lambda: link.snapshot().alt_rel_m > 3.6, 20, "takeoff altitude")
        await _until(lambda: link.snapshot().flight_mode == FlightMode.HOLD, 10, "hold after takeoff")

        # MAVSDK's start race: a setpoint set while PX4 is not in offboard is dropped by MAVSDK's watchdog
        # at the next non-offboard heartbeat, and a bare start() then fails with NO_SETPOINT_SET.
        still = VelocityNedSetpoint((0.0, 0.0, 0.0), 0.0)
        await link.set_setpoint(still)
        await link.release_offboard()  # keep the guard out of this experiment
        await asyncio.sleep(2.5)  # two Hold heartbeats
        try:
            await link._result_of("start", link._offboard.start_async, OffboardResult.SUCCESS)
            bare_start = "SUCCESS"
        except CommandRejectedError as exc:
            bare_start = exc.result
        print(f"\nbare offboard start() 2.5 s after the last set_*(): {bare_start}")
        if bare_start == "SUCCESS":
            await link.stop_offboard()
            await _until(lambda: link.snapshot().flight_mode == FlightMode.HOLD, 5, "Hold")
        else:
            assert bare_start == "NO_SETPOINT_SET"
        # Our start sets the setpoint right before start() and retries on NO_SETPOINT_SET: it always works.
        sp = VelocityNedSetpoint((1.0, 0.0, 0.0), 0.0)
        await link.set_setpoint(still)
        await link.release_offboard()
        await asyncio.sleep(2.5)
        await link.start_offboard(sp)
        t_end = time.monotonic() + 4.0
        while time.monotonic() < t_end:
            await link.set_setpoint(sp)
            await asyncio.sleep(0.05)
        assert link.snapshot().flight_mode == FlightMode.OFFBOARD
        v = feed.latest[FOLLOWER].v
        assert v[0] == pytest.approx(1.0, abs=0.25)
        assert abs(v[1]) < 0.25

        # Attitude + thrust: level at the hover thrust; PX4 holds the attitude, altitude drifts little.
        hover = link.snapshot().hover_thrust_norm or 0.5
        alt0 = -feed.latest[FOLLOWER].p[2]
        t_end = time.monotonic() + 3.0
        while time.monotonic() < t_end:
            await link.set_setpoint(AttitudeSetpoint(0.0, math.radians(5.0), 0.0, hover))
            await asyncio.sleep(0.05)
        fol = feed.latest[FOLLOWER]
        assert link.snapshot().flight_mode == FlightMode.OFFBOARD
        assert abs(-fol.p[2] - alt0) < 1.0
        assert fol.v[0] < 0.6  # pitched up 5 deg: braking northward motion
        att = [s for s in tap.setpoints() if s.msg.get_type() == "SET_ATTITUDE_TARGET"]
        assert att
        assert att[-1].msg.thrust == pytest.approx(hover, abs=1e-3)

        # The mission goes silent: the link's guard must stop the stream and PX4 must leave offboard.
        t_silent = time.monotonic()
        await _until(lambda: link.guard_trips == 1, 2.0, "the setpoint guard")
        await _until(lambda: link.snapshot().flight_mode == FlightMode.HOLD, 3.0, "Hold after the guard")
        t_hold = time.monotonic()
        await asyncio.sleep(2.5)
        last = tap.setpoints()[-1].t_s
        assert last - t_silent <= cfg.link.setpoint_timeout_s + 0.2, "setpoints kept flowing after the guard"
        modes = [m for _, m in tap.vehicle_modes(since_s=t_hold)]
        assert modes
        assert all(m != CUSTOM_MODE_OFFBOARD for m in modes)

        await link.land()
        await _until(lambda: link.snapshot().landed_state == LandedState.ON_GROUND, 25, "touchdown")
        await _until(lambda: not link.snapshot().armed, 10, "auto-disarm")
        assert np.linalg.norm(feed.latest[FOLLOWER].v) < 0.3
