"""The adapters between the service and the flight/perception parts, with flight's real runner and machine.

The vehicle is flight's scripted FakeAutopilot (pure logic, as in tests/unit); the SITL end-to-end tests
fly the same wiring against the simulator over MAVLink.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from companion.app import FollowerService, Parts, PartsContext
from companion.config import Config
from companion.estimation.estimate import RelativeEstimate, TrackState
from companion.estimation.leader import TrackStatus
from companion.kernel import compat
from companion.kernel.camera import MountConfig
from companion.kernel.clock import MonotonicClock
from companion.kernel.flight import NEVER_S, FlightMode, LandedState, VehicleState
from companion.mission.types import CommandKind, OperatorCommand, OperatorRequest
from companion.perception.transform import CameraGeometry
from companion.service.flight import FlightService, vehicle_summary
from companion.service.operator import command_request
from companion.service.status import query_status
from companion.service.systemd import NotifyConfig, SystemdNotifier
from companion.service.wiring import LinkGcs
from companion.telemetry.leader import GeoOrigin
from companion.telemetry.payloads import LeaderPositionMsg, PoseMsg
from tests.unit.mission_harness import FakeAutopilot, leader
from tests.unit.status_keys import keys_the_page_misses
from tests.unit.test_mission_runner import RecordingLink

pytestmark = pytest.mark.timeout(60)


def test_vehicle_summary_hides_what_never_arrived() -> None:
    s = vehicle_summary(VehicleState(), now_s=10.0)
    assert s.heartbeat_age_s is None
    assert s.p_ned_m is None
    assert s.lat_deg is None
    assert s.flight_mode == "unknown"
    v = VehicleState(connected=True, heartbeat_stamp_s=9.5, local_position_stamp_s=9.9, p_ned_m=(1, 2, -3))
    s = vehicle_summary(v, now_s=10.0)
    assert s.heartbeat_age_s == pytest.approx(0.5)
    assert s.p_ned_m == (1, 2, -3)


def test_track_state_becomes_a_leader_estimate() -> None:
    cov = np.diag([0.1, 0.2, 0.3, 1.0, 1.0, 1.0])
    est = RelativeEstimate(
        np.array([5.0, 1.0, -0.5]),
        np.array([0.5, 0.0, 0.0]),
        cov,
        np.eye(3),
        CameraGeometry.from_mount(MountConfig()),
    )
    track = TrackState(12.0, TrackStatus.COASTING, 1, est, 3.0, 11.8, 9, None)
    le = track.leader_estimate()
    assert le is not None
    assert le.status.value == "coasting"
    assert le.p_ned_rel_m == (5.0, 1.0, -0.5)
    assert le.var_ned_rel_m2 == (0.1, 0.2, 0.3)
    assert le.last_measurement_s == 11.8
    assert TrackState(12.0, TrackStatus.LOST, 0, None, 0.0, None, 0, None).leader_estimate() is None


class LandingAutopilot(FakeAutopilot):
    """Flight's fake PX4, plus a touchdown and auto-disarm 0.5 s after a LAND command."""

    land_since_s: float | None = None

    def state(self, now_s: float) -> VehicleState:
        if self.mode == FlightMode.LAND and self.armed:
            if self.land_since_s is None:
                self.land_since_s = now_s
            elif now_s - self.land_since_s > 0.5:
                self.armed = False
                self.landed = LandedState.ON_GROUND
        return super().state(now_s)


#: Over the status socket, in order: hold, hold again, start (follow again), start again.
HOLD = json.dumps(command_request("hold"))
ASK_HOLD_THEN_START = (HOLD, HOLD, "start", "start")


async def test_service_flies_the_real_runner_and_lands_on_stop(tmp_path: Path) -> None:
    clock = MonotonicClock()
    cfg = Config.model_validate(
        {
            "mission": {"gps_restore_s": 0.2, "shutdown_action": "hold_then_land", "shutdown_hold_s": 0.3},
            "status": {"socket_path": str(tmp_path / "status.sock")},
            "service": {"auto_start": True, "shutdown_timeout_s": 10.0},
        }
    )
    ap = LandingAutopilot()
    link = RecordingLink(ap, clock)
    flight = FlightService(cfg, link, clock)  # type: ignore[arg-type]
    sock = Path(cfg.status.socket_path)

    async def open_parts(stack: contextlib.AsyncExitStack, ctx: PartsContext) -> Parts:
        return Parts(mission=flight, gcs=LinkGcs(link))

    async def feed() -> None:
        while True:
            flight.runner.submit_leader(leader(clock.now_s()))
            await asyncio.sleep(0.02)

    with SystemdNotifier(NotifyConfig()) as notifier:
        svc = FollowerService(cfg, open_parts, clock=clock, wall_time_s=time.time, notifier=notifier)
        async with compat.timeout(30), compat.TaskGroup() as tg:
            feeder = tg.create_task(feed())
            task = tg.create_task(svc.run())
            for _ in range(400):
                if flight.snapshot().state == "follow":
                    break
                await asyncio.sleep(0.05)
            snap: dict[str, Any] = await asyncio.to_thread(query_status, Path(cfg.status.socket_path))
            refused = await flight.command(OperatorRequest(OperatorCommand.SET_OFFSET, (0.0, 0.0, 1.0)))
            assert not refused.taken
            assert str(refused).startswith("set_offset refused: slot 1.0 m")
            taken = await flight.command(OperatorRequest(OperatorCommand.SET_OFFSET, (0.5, 0.0, 6.0)))
            assert taken.taken
            assert str(taken).startswith("set_offset: slot set to (0.5, 0.0, 6.0). Next: ")
            # An operator's hold, then start: each answered over the socket with what the mission did.
            answers = [await asyncio.to_thread(query_status, sock, r) for r in ASK_HOLD_THEN_START]
            after = flight.snapshot().state
            svc.request_stop("SIGTERM")
            code = await task
            feeder.cancel()
    assert code == 0
    assert answers == [
        {
            "ok": True,
            "detail": "hold: follow -> px4_hold (operator asked to hold). Next: PX4 holds position until "
            "companion start (follow again) or companion command land",
        },
        {"ok": False, "detail": "hold refused: already holding (PX4 Hold); companion start follows again"},
        {
            "ok": True,
            "detail": "start: px4_hold -> acquire (operator asked to follow again: from px4_hold); "
            "acquire -> follow (leader acquired). Next: follows the leader until companion command hold "
            "or land",
        },
        {"ok": False, "detail": "start refused: the mission is already under way (state follow)"},
    ]
    assert after == "follow"
    assert snap["mission"]["state"] == "follow"
    assert keys_the_page_misses(snap)[1] == {"mavlink_signing"}  # what the socket served, read by the page
    assert snap["link"]["armed"] is True
    assert snap["mission"]["transitions"] >= 5
    kinds = [k for _, k in link.calls]
    assert (
        kinds[-2:] == [CommandKind.HOLD.value, CommandKind.LAND.value] or kinds[-1] == CommandKind.LAND.value
    )
    assert not ap.armed  # the service exited after the disarm
    assert flight.machine.law.slot.range_h_m == pytest.approx(np.hypot(0.5, 6.0), rel=0.05)


ORIGIN = GeoOrigin(47.0, 8.0, 500.0)


def _flight_with_a_fix(clock: MonotonicClock) -> FlightService:
    """A flight whose autopilot reports a geodetic fix 10 m north of ``ORIGIN``."""
    ap = FakeAutopilot()
    flight = FlightService(Config(), RecordingLink(ap, clock), clock)  # type: ignore[arg-type]
    ap.p_ned_m = (10.0, 0.0, -5.0)
    lat, lon, alt = ORIGIN.to_geodetic(ap.p_ned_m)
    real_state = ap.state

    def with_geo(now_s: float) -> VehicleState:
        return replace(real_state(now_s), lat_deg=lat, lon_deg=lon, alt_amsl_m=alt)

    ap.state = with_geo  # type: ignore[method-assign]
    return flight


def test_leader_position_from_mqtt_lands_in_local_ned() -> None:
    clock = MonotonicClock()
    flight = _flight_with_a_fix(clock)
    origin = ORIGIN
    llat, llon, lalt = origin.to_geodetic((16.0, 2.0, -6.0))
    flight.on_leader_position(
        LeaderPositionMsg(lat_deg=llat, lon_deg=llon, alt_amsl_m=lalt, time_unix_s=time.time())
    )
    shared = flight.runner.leader_shared
    assert shared is not None
    assert shared.p_ned_m == pytest.approx((16.0, 2.0, -6.0), abs=1e-3)
    assert NEVER_S < shared.stamp_s <= clock.now_s()


def test_a_neighbour_pose_from_mqtt_lands_in_local_ned_and_reaches_the_mission() -> None:
    clock = MonotonicClock()
    flight = _flight_with_a_fix(clock)
    origin = ORIGIN
    # Our frame is learnt from our own fix (as the leader's position does it).
    llat, llon, lalt = origin.to_geodetic((16.0, 2.0, -6.0))
    flight.on_leader_position(
        LeaderPositionMsg(lat_deg=llat, lon_deg=llon, alt_amsl_m=lalt, time_unix_s=time.time(), yaw_deg=90.0)
    )
    shared = flight.runner.leader_shared
    assert shared is not None
    assert shared.yaw_rad == pytest.approx(math.pi / 2)
    nlat, nlon, nalt = origin.to_geodetic((12.0, -3.0, -5.0))
    pose = PoseMsg(
        p_ned_m=(0.0, 0.0, -5.0), v_ned_m_s=(1.0, 0.0, 0.0), lat_deg=nlat, lon_deg=nlon, alt_amsl_m=nalt,
        time_unix_s=time.time(),
    )  # fmt: skip
    flight.on_neighbour_pose("follower2", pose)
    # A neighbour whose own position is not valid is not used.
    flight.on_neighbour_pose("follower3", pose.model_copy(update={"p_ned_m": None}))
    got = flight.runner.neighbours
    assert set(got) == {"follower2"}
    assert got["follower2"].p_ned_m == pytest.approx((12.0, -3.0, -5.0), abs=1e-3)
    assert got["follower2"].v_ned_m_s == (1.0, 0.0, 0.0)
