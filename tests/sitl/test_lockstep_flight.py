"""Closed-loop flights in lockstep (no sockets): the autopilot, estimator and failsafes together."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from sitl.config import SitlConfig
from sitl.modes import NavState
from sitl.scenario import Scenario
from sitl.world import World
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
    # Descend (reported as AUTO.LAND, system_status CRITICAL) at EKF2_NOAID_TOUT = 5 s.
    land = [t for t, mode in c.heartbeat_modes() if mode is NavState.AUTO_LAND]
    assert land
    assert 5.0 <= land[0] - t0 <= 6.1
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


def test_external_vision_keeps_position_valid_after_gps_loss() -> None:
    world = world_with(seed=4)
    c = Client(world)
    c.take_off(5.0)
    off = world.origin_offset_ned_m("follower")
    rng = np.random.default_rng(0)

    def stream(t: float) -> None:
        c.velocity_setpoint(0.5, 0.0, 0.0)
        p = world.truth("follower").p_ned_m
        n, e = p[0] - off[0] + rng.normal(0, 0.05), p[1] - off[1] + rng.normal(0, 0.05)
        cov = [0.01] + [0.0] * 5 + [0.01] + [0.0] * 14
        c.send(mavlink.MAVLink_vision_position_estimate_message(int(t * 1e6), n, e, p[2], 0, 0, 0, cov, 0))

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
    w.run_until(20.0)
    n0 = w.truth("leader").p_ned_m[0]
    w.run_until(30.0)
    assert w.autopilot("leader").nav_state is NavState.OFFBOARD
    assert w.truth("leader").p_ned_m[0] - n0 == pytest.approx(20.0, abs=1.5)
    assert w.truth("leader").p_ned_m[2] == pytest.approx(-5.09, abs=0.3)
