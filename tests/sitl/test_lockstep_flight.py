"""Closed-loop flights in lockstep (no sockets): the autopilot, estimator and failsafes together."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from sitl.autopilot.modes import NavState
from sitl.config import SitlConfig
from sitl.world.lockstep import World
from sitl.world.scenario import Scenario
from tests.sitl.harness import NAN, Client, world_with

pytestmark = pytest.mark.slow

GPS_BIT = 32


def test_hover_at_5_m_with_gps_noise_holds_position() -> None:
    # The default GPS error model is on (white noise + wandering bias); truth is compared with the
    # commanded hold point, so estimator error counts against the vehicle, as it would in the field.
    world = world_with(seed=11)
    c = Client(world)
    c.take_off(5.0)
    c.run(10.0)
    ap = c.ap
    target = ap.navigator.target
    off = world.origin_offset_ned_m("follower")
    err_alt, err_h = [], []

    def sample(_t: float) -> None:
        p = world.truth("follower").p_ned_m
        err_alt.append(p[2] - (target[2] + off[2]))
        err_h.append(math.hypot(p[0] - target[0] - off[0], p[1] - target[1] - off[1]))

    c.run(60.0, each=sample, every_s=0.1)
    alt_rms = float(np.sqrt(np.mean(np.square(err_alt))))
    h_rms = float(np.sqrt(np.mean(np.square(err_h))))
    print(f"hover 60 s: altitude RMS {alt_rms:.3f} m, horizontal RMS {h_rms:.3f} m")
    assert ap.nav_state is NavState.AUTO_LOITER
    assert alt_rms <= 0.15
    assert h_rms <= 0.30
    assert -target[2] == pytest.approx(5.0 - ap.home.d_m, abs=0.01)


def test_gps_loss_in_offboard_velocity_follows_px4_timeline() -> None:
    world = world_with(seed=3)
    c = Client(world)
    c.take_off(5.0)
    stream = c.start_offboard_velocity(1.0, 0.0, 0.0)
    c.run(2.0, each=stream)
    assert c.ap.nav_state is NavState.OFFBOARD
    assert c.command(mavlink.MAV_CMD_INJECT_FAILURE, 4.0, 1.0, 0.0) == 0  # GPS off
    t0 = world.t_s
    c.log.clear()
    c.run(12.0, each=stream)
    # GPS_RAW_INT: "no GPS" (fix 0, 65535s) within about a second.
    no_fix = [t for t, m in c.log if m.get_type() == "GPS_RAW_INT" and m.fix_type == 0]
    assert no_fix
    assert no_fix[0] - t0 <= 1.2
    assert all(m.eph == 65535 for _, m in c.log if m.get_type() == "GPS_RAW_INT" and m.fix_type == 0)
    # Descend (reported as AUTO.LAND, system_status CRITICAL) at EKF2_NOAID_TOUT = 5 s after the last GPS
    # fusion, which can be one GPS period (0.1 s) before the injection; seen on the next 1 Hz HEARTBEAT.
    land = [t for t, mode in c.heartbeat_modes() if mode is NavState.AUTO_LAND]
    assert land
    assert 4.9 <= land[0] - t0 <= 6.1
    assert c.ap.nav_state is NavState.DESCEND
    crit = [m.system_status for t, m in c.log if m.get_type() == "HEARTBEAT" and t > t0 + 6.5]
    assert crit
    assert all(s == 5 for s in crit)
    # GNSS fusion stops at 7 s with PX4's STATUSTEXT; the SYS_STATUS GPS bit goes with it.
    stop = [t for t, text in c.texts() if text == "GNSS data fusion stopped"]
    assert len(stop) == 1
    assert 6.9 <= stop[0] - t0 <= 7.3
    gps_present = [
        (t, bool(m.onboard_control_sensors_present & GPS_BIT))
        for t, m in c.log
        if m.get_type() == "SYS_STATUS"
    ]
    assert all(p for t, p in gps_present if t < t0 + 6.9)
    assert not any(p for t, p in gps_present if t > t0 + 7.3)
    flags = [(t, m.flags) for t, m in c.log if m.get_type() == "ESTIMATOR_STATUS"]
    assert all(f & 8 for t, f in flags if t < t0 + 4.9)  # POS_HORIZ_REL while valid
    assert not any(f & 8 for t, f in flags if t > t0 + 5.1)
    # The position estimate keeps streaming, drifting (PX4 flags nothing in LOCAL_POSITION_NED).
    assert any(m.get_type() == "LOCAL_POSITION_NED" for t, m in c.log if t > t0 + 8)
    # Descend lands and disarms by itself.
    c.run_until(lambda: not c.ap.armed, 20.0)
    assert world.truth("follower").p_ned_m[2] > -0.2


@pytest.mark.parametrize("message", ["VISION_POSITION_ESTIMATE", "ODOMETRY"])
def test_external_vision_keeps_position_valid_after_gps_loss(message: str) -> None:
    world = world_with(seed=4)
    c = Client(world)
    # PX4 ships external-vision aiding off (EKF2_EV_CTRL 0): turn horizontal position on, as the service does.
    one = struct.unpack("<f", struct.pack("<i", 1))[0]  # PX4 sends INT32 parameters bytewise
    c.send(mavlink.MAVLink_param_set_message(1, 1, b"EKF2_EV_CTRL", one, mavlink.MAV_PARAM_TYPE_INT32))
    c.take_off(5.0)
    assert c.ap.params["EKF2_EV_CTRL"] == 1
    off = world.origin_offset_ned_m("follower")
    rng = np.random.default_rng(0)

    def stream(t: float) -> None:
        c.velocity_setpoint(0.5, 0.0, 0.0)
        p = world.truth("follower").p_ned_m
        n, e = p[0] - off[0] + rng.normal(0, 0.05), p[1] - off[1] + rng.normal(0, 0.05)
        cov = [0.01] + [0.0] * 5 + [0.01] + [0.0] * 14
        if message == "ODOMETRY":
            c.send(
                mavlink.MAVLink_odometry_message(
                    int(t * 1e6),
                    mavlink.MAV_FRAME_LOCAL_NED,
                    mavlink.MAV_FRAME_BODY_FRD,
                    n,
                    e,
                    p[2],
                    [1.0, 0.0, 0.0, 0.0],
                    NAN,
                    NAN,
                    NAN,
                    NAN,
                    NAN,
                    NAN,
                    cov,
                    [NAN] * 21,
                    0,
                    0,
                    100,
                )
            )
        else:
            c.send(
                mavlink.MAVLink_vision_position_estimate_message(int(t * 1e6), n, e, p[2], 0, 0, 0, cov, 0)
            )

    c.run(1.0, each=stream)
    assert c.command(mavlink.MAV_CMD_DO_SET_MODE, 129.0, 6.0, 0.0) == 0
    assert c.command(mavlink.MAV_CMD_INJECT_FAILURE, 4.0, 1.0, 0.0) == 0
    c.run(15.0, each=stream)
    assert c.ap.nav_state is NavState.OFFBOARD  # no failsafe: vision aids the estimate
    assert c.ap.est.xy_valid
    assert not c.ap.est.gnss_fusing
    status = c.ap.status()
    assert status.local_position_ok
    assert not status.global_position_ok
    est = c.ap.position_ned()
    truth = world.truth("follower").p_ned_m
    assert math.hypot(est[0] + off[0] - truth[0], est[1] + off[1] - truth[1]) < 0.3


def test_attitude_offboard_keeps_flying_without_gps() -> None:
    # The companion's vision fallback: attitude + thrust setpoints need only attitude.
    world = world_with(seed=5)
    c = Client(world)
    c.take_off(5.0)
    hover = c.ap.params["MPC_THR_HOVER"]

    def stream(_t: float) -> None:
        c.send(mavlink.MAVLink_set_attitude_target_message(0, 1, 1, 7, [1.0, 0.0, 0.0, 0.0], 0, 0, 0, hover))

    c.run(1.0, each=stream)
    assert c.command(mavlink.MAV_CMD_DO_SET_MODE, 129.0, 6.0, 0.0) == 0
    assert c.command(mavlink.MAV_CMD_INJECT_FAILURE, 4.0, 1.0, 0.0) == 0
    c.run(10.0, each=stream)
    assert c.ap.nav_state is NavState.OFFBOARD
    assert not c.ap.est.xy_valid
    assert world.truth("follower").p_ned_m[2] < -3.0  # still up (open-loop thrust drifts a little)


def test_offboard_rules_refusal_loss_and_resume() -> None:
    world = world_with(seed=6)
    c = Client(world)
    c.run_until(lambda: c.ap.status().global_position_ok, 30.0)
    # Disarmed: any mode change is accepted; arming in offboard without a signal is not.
    assert c.command(mavlink.MAV_CMD_DO_SET_MODE, 1.0, 6.0, 0.0) == 0
    assert c.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0) == 1
    assert c.command(mavlink.MAV_CMD_DO_SET_MODE, 1.0, 4.0, 3.0) == 0
    c.take_off(5.0)
    # In the air without a setpoint stream: TEMPORARILY_REJECTED with PX4's text.
    c.log.clear()
    assert c.command(mavlink.MAV_CMD_DO_SET_MODE, 129.0, 6.0, 0.0) == 1
    assert "Switching to Offboard is currently not available" in [x for _, x in c.texts()]
    stream = c.start_offboard_velocity()
    c.run(2.0, each=stream)
    assert c.ap.nav_state is NavState.OFFBOARD
    t_stop = world.t_s
    c.log.clear()
    c.run(3.0)  # the stream stops
    rtl = [t for t, mode in c.heartbeat_modes() if mode is NavState.AUTO_RTL]
    assert c.ap.nav_state is NavState.AUTO_RTL  # COM_OBL_RC_ACT 0 -> no RC -> NAV_RCL_ACT 2 = Return
    assert rtl
    assert rtl[0] - t_stop <= 1.0 + 1.05
    # The failsafe is a mode fallback: it clears when the signal comes back.
    c.run(1.0, each=stream)
    assert c.ap.nav_state is NavState.OFFBOARD


def test_hostile_messages_never_crash_and_never_fly() -> None:
    world = world_with(seed=7)
    c = Client(world)
    c.take_off(5.0)
    stream = c.start_offboard_velocity()
    rng = np.random.default_rng(1)
    weird = [NAN, math.inf, -math.inf, 1e38, -1e38, 0.0, 3.4e38]

    def junk(_t: float) -> None:
        stream(_t)
        w = lambda: float(rng.choice(weird))  # noqa: E731
        c.send(
            mavlink.MAVLink_set_position_target_local_ned_message(
                0, 2, 1, int(rng.integers(0, 20)), int(rng.integers(0, 4096)), *(w() for _ in range(11))
            )
        )
        c.send(
            mavlink.MAVLink_set_attitude_target_message(
                0, 9, 1, int(rng.integers(0, 256)), [w(), w(), w(), w()], w(), w(), w(), w()
            )
        )
        c.send(
            mavlink.MAVLink_command_long_message(1, 1, int(rng.integers(0, 600)), 0, *(w() for _ in range(7)))
        )
        c.send(mavlink.MAVLink_param_set_message(1, 1, b"MPC_XY_VEL_MAX", w(), 9))
        c.send(mavlink.MAVLink_vision_position_estimate_message(0, w(), w(), w(), 0, 0, 0, [w()] * 21, 0))

    c.run(5.0, each=junk)
    assert c.ap.counters["handler_errors"] == 0
    assert c.ap.armed
    assert c.ap.nav_state is NavState.OFFBOARD
    assert world.truth("follower").p_ned_m[2] < -4.0
    # Messages for another system never reach the vehicle (no ACK at all).
    c.log.clear()
    c.send(mavlink.MAVLink_command_long_message(42, 1, 400, 0, 0, 0, 0, 0, 0, 0, 0))
    c.run(0.1)
    assert not [m for _, m in c.log if m.get_type() == "COMMAND_ACK"]


def test_same_seed_same_flight_other_seed_other_noise() -> None:
    sc = Scenario.model_validate(
        {
            "name": "det",
            "leader": {"type": "circle", "start_s": 18.0, "speed_m_s": 3.0},
            "wind": {
                "mean_speed_m_s": 2.0,
                "gust_max_m_s": 4.0,
                "gust_interval_s": 3.0,
                "turbulence_m_s": 0.3,
            },
        }
    )

    def fly(seed: int) -> np.ndarray:
        w = World(SitlConfig(), sc, seed=seed)
        w.run_until(30.0)
        return w.truth("leader").p_ned_m

    a, b, other = fly(1), fly(1), fly(2)
    assert np.array_equal(a, b)
    assert not np.allclose(a, other, atol=1e-6)


def test_scenario_leader_flies_its_straight_line() -> None:
    sc = Scenario.model_validate(
        {"name": "s", "leader": {"type": "straight", "start_s": 16.0, "speed_m_s": 2.0}}
    )
    w = World(SitlConfig(), sc, seed=2)
    speeds_m_s = []
    for k in range(1, 41):
        w.run_until(16.0 + 0.1 * k)
        speeds_m_s.append(float(np.hypot(*w.truth("leader").v_ned_m_s[:2])))
    n0 = w.truth("leader").p_ned_m[0]
    w.run_until(30.0)
    # The path's acceleration is fed forward as PX4's trajectory follower does: without it the speed
    # ramp wound up the velocity integrator and the leader overshot its 2 m/s by a quarter.
    assert max(speeds_m_s) < 2.3  # 2.17 with, 2.51 without
    assert w.autopilot("leader").state.nav_state is NavState.OFFBOARD
    assert w.truth("leader").p_ned_m[0] - n0 == pytest.approx(20.0, abs=1.5)
    assert w.truth("leader").p_ned_m[2] == pytest.approx(-5.09, abs=0.3)


def test_wrong_gps_is_rejected_as_a_glitch_then_position_fails() -> None:
    world = world_with(seed=8)
    c = Client(world)
    c.take_off(5.0)
    assert c.command(mavlink.MAV_CMD_INJECT_FAILURE, 4.0, 4.0, 0.0) == 0  # GPS wrong (120 m off)
    t0 = world.t_s
    c.log.clear()
    c.run(6.5)
    glitch = [t for t, m in c.log if m.get_type() == "ESTIMATOR_STATUS" and m.flags & 1024]
    assert glitch
    assert glitch[0] - t0 <= 1.05  # ESTIMATOR_STATUS comes at 1 Hz
    assert c.ap.nav_state is NavState.DESCEND  # the fix is never fused: dead reckoning times out
    # The vehicle did not follow the wrong fix while it was rejected.
    off = world.origin_offset_ned_m("follower")
    est = c.ap.position_ned()
    truth = world.truth("follower").p_ned_m
    assert math.hypot(est[0] + off[0] - truth[0], est[1] + off[1] - truth[1]) < 2.0
    # SYS_STATUS reports the GPS unhealthy while it glitches (present, not healthy).
    last = [m for _, m in c.log if m.get_type() == "SYS_STATUS"][-1]
    assert last.onboard_control_sensors_present & GPS_BIT
    assert not last.onboard_control_sensors_health & GPS_BIT
    assert c.command(mavlink.MAV_CMD_INJECT_FAILURE, 4.0, 0.0, 0.0) == 0  # GPS ok again


def test_default_streams_at_px4_onboard_rates_and_set_message_interval() -> None:
    world = world_with(seed=9)
    c = Client(world)
    c.run(12.0)  # past the GPS checks: global position and home exist
    c.log.clear()
    c.run(10.0)
    counts: dict[str, int] = {}
    for _, m in c.log:
        counts[m.get_type()] = counts.get(m.get_type(), 0) + 1
    expected_hz = {
        "HEARTBEAT": 1, "ATTITUDE": 100, "ATTITUDE_QUATERNION": 50, "LOCAL_POSITION_NED": 30,
        "GLOBAL_POSITION_INT": 50, "ODOMETRY": 30, "HIGHRES_IMU": 50, "GPS_RAW_INT": 10,
        "SYS_STATUS": 5, "EXTENDED_SYS_STATE": 5, "ALTITUDE": 10, "VFR_HUD": 10,
        "ESTIMATOR_STATUS": 1, "SYSTEM_TIME": 1, "TIMESYNC": 10, "HOME_POSITION": 0.5, "BATTERY_STATUS": 0.5,
    }  # fmt: skip
    for name, hz in expected_hz.items():
        assert counts.get(name, 0) / 10.0 == pytest.approx(hz, rel=0.12, abs=0.11), name
    # SET_MESSAGE_INTERVAL (per link, in microseconds) and REQUEST_MESSAGE.
    assert c.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 30.0, 1e6 / 20.0) == 0
    assert c.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 105.0, -1.0) == 0
    assert c.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 999.0, 1e5) == 4  # FAILED: no such stream
    c.log.clear()
    c.run(5.0)
    att = sum(1 for _, m in c.log if m.get_type() == "ATTITUDE")
    assert att / 5.0 == pytest.approx(20.0, rel=0.1)
    assert not any(m.get_type() == "HIGHRES_IMU" for _, m in c.log)
    assert c.command(mavlink.MAV_CMD_REQUEST_MESSAGE, 242.0) == 0  # HOME_POSITION
    assert c.command(mavlink.MAV_CMD_REQUEST_MESSAGE, 397.0) == 2  # COMPONENT_METADATA: DENIED
    # time_boot_ms and SYSTEM_TIME follow sim time.
    st = [m for _, m in c.log if m.get_type() == "SYSTEM_TIME"][-1]
    assert st.time_boot_ms / 1000.0 == pytest.approx(world.t_s, abs=1.05)
    assert st.time_unix_usec == pytest.approx((1_767_225_600.0 + st.time_boot_ms / 1000.0) * 1e6, abs=2e3)


def test_every_handled_message_type_with_random_values_is_harmless() -> None:
    import random

    from sitl.autopilot.mavlink import MESSAGE_HANDLERS
    from tests.fuzz_messages import random_message

    world = world_with(seed=10)
    c = Client(world)
    handled = set(MESSAGE_HANDLERS)
    classes = [cls for cls in mavlink.mavlink_map.values() if cls.msgname in handled]
    assert len(classes) == len(handled)
    rng = random.Random(5)
    for _ in range(200):
        for _ in range(100):
            c.link.send(random_message(rng, classes), rng.randint(0, 255), rng.randint(0, 255))
        c.run(0.1)
    # A random SETUP_SIGNING gives the vehicle a random key (PX4 takes one while disarmed); from then on the
    # fuzzed messages, unsigned, are refused at the link.
    assert c.ap.counters["messages_in"] + c.link.dropped_unsigned == 20_000
    assert c.ap.counters["handler_errors"] == 0


def test_command_int_reposition_and_global_setpoints_fly_to_lat_lon() -> None:
    world = world_with(seed=12)
    c = Client(world)
    c.take_off(5.0)
    ap = c.ap
    off = world.origin_offset_ned_m("follower")
    lat, lon, _ = ap.origin.to_geodetic(10.0, 0.0, 0.0)
    c.send(
        mavlink.MAVLink_command_int_message(
            c.sysid,
            1,
            mavlink.MAV_FRAME_GLOBAL,
            mavlink.MAV_CMD_DO_REPOSITION,
            0,
            0,
            -1,
            0,
            0,
            NAN,
            int(lat * 1e7),
            int(lon * 1e7),
            ap.home.alt_m + 6.0,
        )
    )
    c.run(12.0)
    p = world.truth("follower").p_ned_m
    assert ap.nav_state is NavState.AUTO_LOITER
    assert p[0] - off[0] == pytest.approx(10.0, abs=0.6)
    assert -p[2] == pytest.approx(6.0 + 0.09, abs=0.4)
    # SET_POSITION_TARGET_GLOBAL_INT (MAVSDK's set_position_global) in offboard.
    lat2, lon2, _ = ap.origin.to_geodetic(10.0, 8.0, 0.0)

    def stream(_t: float) -> None:
        c.send(
            mavlink.MAVLink_set_position_target_global_int_message(
                0,
                c.sysid,
                1,
                mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                0b110111111000,
                int(lat2 * 1e7),
                int(lon2 * 1e7),
                5.0,
                0,
                0,
                0,
                0,
                0,
                0,
                0,
                0,
            )
        )

    c.run(1.0, each=stream)
    assert c.command(mavlink.MAV_CMD_DO_SET_MODE, 129.0, 6.0, 0.0) == 0
    c.run(10.0, each=stream)
    p = world.truth("follower").p_ned_m
    assert (p[0] - off[0], p[1] - off[1]) == pytest.approx((10.0, 8.0), abs=0.6)
    assert -p[2] == pytest.approx(5.0 + 0.09, abs=0.4)


def test_return_climbs_flies_home_lands_and_disarms() -> None:
    world = world_with(seed=13)
    c = Client(world)
    c.take_off(5.0)

    def stream(_t: float) -> None:
        c.position_setpoint(20.0, 10.0, -5.0)

    stream(0.0)
    c.run(1.0, each=stream)
    assert c.command(mavlink.MAV_CMD_DO_SET_MODE, 129.0, 6.0, 0.0) == 0
    c.run(12.0, each=stream)
    assert c.command(mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH) == 0
    peak = [0.0]

    def watch(_t: float) -> None:
        peak[0] = max(peak[0], -world.truth("follower").p_ned_m[2])

    c.run_until(lambda: not c.ap.armed, 120.0, each=watch)
    p = world.truth("follower").p_ned_m
    off = world.origin_offset_ned_m("follower")
    # PX4 defaults: climb to at least RTL_DESCEND_ALT (30 m), return, descend, land at home.
    assert peak[0] == pytest.approx(30.0, abs=1.5)
    assert math.hypot(p[0] - off[0], p[1] - off[1]) < 1.0
    assert p[2] > -0.2
    assert "Disarmed by landing" in [x for _, x in c.texts()]
