"""The mission flying the simulator through real MAVSDK: GPS loss, controlled landing, stale estimates.

The leader-relative state comes from the TEST-ONLY truth tracker (see ``harness.py``): these figures are
the flight side's (link + machine + law against PX4-like behaviour), not vision results.
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from companion.config import Config, LeaderConfig, MissionConfig
from companion.kernel.flight import FlightMode
from companion.mission.types import MissionState, OperatorCommand, OperatorRequest

from .harness import Flight, fly, inject_gps, rmse, sitl_missing_reason
from .wiretap import CUSTOM_MODE_AUTO_LAND

pytestmark = [
    pytest.mark.sitl,
    pytest.mark.slow,
    pytest.mark.skipif(sitl_missing_reason() is not None, reason=str(sitl_missing_reason())),
]

S = MissionState


def circle_scenario(start_s: float, radius_m: float = 15.0, speed_m_s: float = 3.0) -> str:
    return f"""
schema_version = 1
name = "test-circle"
[leader]
type = "circle"
start_s = {start_s}
altitude_m = 5.0
speed_m_s = {speed_m_s}
radius_m = {radius_m}
"""


STRAIGHT_SCENARIO = """
schema_version = 1
name = "test-straight"
[leader]
type = "straight"
start_s = 20.0
altitude_m = 5.0
speed_m_s = 1.5
heading_deg = 0.0
"""

HOVER_SCENARIO = """
schema_version = 1
name = "test-hover"
[leader]                # takes off and holds (its path would only start after the test)
type = "straight"
start_s = 1000.0
altitude_m = 5.0
"""


def mission_cfg(**mission: object) -> Config:
    base = {"gps_restore_s": 2.0, "takeoff_altitude_m": 5.0}
    base.update(mission)
    # The harness hands the runner the leader's shares itself; the config must still say they come.
    shared = "mqtt" if base.get("gps_loss_policy") == "vision_external_position" else "none"
    return Config(mission=MissionConfig(**base), leader=LeaderConfig(shared_position=shared))  # type: ignore[arg-type]


async def test_circle_on_gps_then_gps_loss_on_vision_attitude(tmp_path: Path) -> None:
    """One flight: follow the 15 m / 3 m/s circle on GPS, cut the GPS, keep formation 60 s on attitude."""
    cfg = mission_cfg(gps_loss_policy="vision_attitude")
    gps_follow_s, vision_s = 30.0, 60.0
    figures: dict[str, float] = {}

    async def body(f: Flight) -> None:
        await f.reach(S.FOLLOW, timeout_s=60)
        await f.sim_time(25.0)  # the leader is up to speed on its circle
        t0 = f.clock.now_s()
        await f.sim_time(25.0 + gps_follow_s)
        rows = f.rec.rows_in(S.FOLLOW, since_s=t0)
        assert all(r.setpoint == "VelocityBodySetpoint" for r in rows)
        errs = [r.formation_err_m for r in rows if r.formation_err_m is not None]
        figures["gps_rmse_m"] = rmse(errs)
        figures["gps_max_dev_m"] = max(errs)
        figures["gps_min_separation_m"] = min(r.separation_m for r in rows if r.separation_m is not None)

        assert await inject_gps(f.ports, 1) == 0
        t_cut = f.clock.now_s()
        await f.reach(S.FOLLOW_VISION, timeout_s=3.0)
        t_vision = f.clock.now_s()
        figures["gps_loss_to_attitude_s"] = t_vision - t_cut
        await asyncio.sleep(vision_s)
        assert f.runner.state == S.FOLLOW_VISION, f.rec.reasons()
        rows = f.rec.rows_in(S.FOLLOW_VISION, since_s=t_vision)
        # PX4 really lost its position estimate (we fly without it) ...
        figures["px4_position_invalid_frac"] = sum(r.position_valid is False for r in rows) / max(
            1, len(rows)
        )
        # ... and never fell back to Descend (reported as AUTO.LAND), nor left offboard.
        assert CUSTOM_MODE_AUTO_LAND not in [m for _, m in f.tap.vehicle_modes(since_s=t_cut)]
        assert all(r.mode == FlightMode.OFFBOARD.value for r in rows)
        assert all(r.setpoint == "AttitudeSetpoint" for r in rows)
        settled = [r for r in rows if r.t_s >= t_vision + 5.0 and r.formation_err_m is not None]
        errs = [r.formation_err_m for r in settled if r.formation_err_m is not None]
        figures["vision_rmse_m"] = rmse(errs)
        figures["vision_max_dev_m"] = max(errs)
        figures["vision_height_err_rmse_m"] = rmse([r.err_heading[2] for r in settled if r.err_heading])
        figures["vision_min_separation_m"] = min(r.separation_m for r in rows if r.separation_m is not None)
        f.runner.request_shutdown()
        await f.reach(S.PX4_LAND, timeout_s=3.0)

    await fly(tmp_path, cfg, circle_scenario(start_s=18.0), body)
    print("\ncircle figures (TEST-ONLY truth tracker):", {k: round(v, 3) for k, v in figures.items()})
    assert figures["gps_rmse_m"] <= 0.3
    assert figures["gps_max_dev_m"] <= 0.6
    assert figures["gps_loss_to_attitude_s"] < 2.5  # PX4 invalidates velocity at 5 s
    assert figures["px4_position_invalid_frac"] > 0.8
    assert figures["vision_rmse_m"] <= 0.45
    assert figures["vision_max_dev_m"] <= 1.0
    assert (
        min(figures["gps_min_separation_m"], figures["vision_min_separation_m"]) > cfg.safety.min_separation_m
    )


async def test_gps_loss_with_land_policy_lands_softly_without_gps(tmp_path: Path) -> None:
    cfg = mission_cfg(gps_loss_policy="land")
    figures: dict[str, float] = {}

    async def body(f: Flight) -> None:
        await f.reach(S.FOLLOW, timeout_s=60)
        await f.sim_time(f.feed.sim_t_s + 4.0)
        assert await inject_gps(f.ports, 1) == 0
        t_cut = f.clock.now_s()
        await f.reach(S.CONTROLLED_LANDING, timeout_s=3.0)
        t_land = f.clock.now_s()
        await f.reach(S.DISARMED, timeout_s=40.0)
        rows = f.rec.rows_in(S.CONTROLLED_LANDING, since_s=t_land)
        assert all(r.setpoint == "AttitudeSetpoint" for r in rows)
        assert CUSTOM_MODE_AUTO_LAND not in [m for _, m in f.tap.vehicle_modes(since_s=t_cut)]
        airborne = [r for r in f.rec.rows if r.t_s >= t_land and r.alt_true_m is not None]
        ground = min(r.alt_true_m for r in airborne if r.alt_true_m is not None)
        t_td = next(r.t_s for r in airborne if r.alt_true_m is not None and r.alt_true_m <= ground + 0.02)
        window = [r for r in airborne if t_td - 0.5 <= r.t_s <= t_td and r.vz_true_m_s is not None]
        figures["touchdown_v_m_s"] = max(r.vz_true_m_s for r in window if r.vz_true_m_s is not None)
        descent = [r for r in airborne if r.t_s >= t_land + 3.0 and r.t_s < t_td - 0.5]
        figures["max_descent_v_m_s"] = max(r.vz_true_m_s or 0.0 for r in descent)
        figures["descent_s"] = t_td - t_land
        figures["px4_position_invalid_at_touchdown"] = float(
            next(r for r in reversed(f.rec.rows) if r.t_s <= t_td).position_valid is False
        )

    flight = await fly(tmp_path, cfg, HOVER_SCENARIO, body)
    print("\nland-policy figures:", {k: round(v, 3) for k, v in figures.items()})
    assert flight.rec.transitions[-1].reason.name == "DISARMED"
    assert figures["touchdown_v_m_s"] <= 1.0
    assert figures["max_descent_v_m_s"] <= 0.85
    assert figures["px4_position_invalid_at_touchdown"] == 1.0


async def test_gps_loss_external_position_keeps_px4_estimate_valid(tmp_path: Path) -> None:
    """Policy (b): the follower's position for PX4 = the leader's shared position minus the seen vector."""
    cfg = mission_cfg(gps_loss_policy="vision_external_position")
    figures: dict[str, float] = {}

    async def body(f: Flight) -> None:
        f.tracker.share_leader_position = True
        await f.reach(S.FOLLOW, timeout_s=60)
        await f.sim_time(26.0)
        assert await inject_gps(f.ports, 1) == 0
        t_cut = f.clock.now_s()
        await f.reach(S.FOLLOW_VISION, timeout_s=3.0)
        # Attitude first, then velocity once PX4 has accepted the external fix.
        for _ in range(100):
            if any(t.reason.name == "VISION_MODE_CHANGED" for t in f.rec.transitions):
                break
            await asyncio.sleep(0.1)
        t_ext = f.clock.now_s()
        figures["gps_loss_to_external_s"] = t_ext - t_cut
        await asyncio.sleep(15.0)
        assert f.runner.state == S.FOLLOW_VISION, f.rec.reasons()
        rows = f.rec.rows_in(S.FOLLOW_VISION, since_s=t_ext)
        assert rows
        assert all(r.setpoint == "VelocityBodySetpoint" for r in rows)
        figures["px4_position_valid_frac"] = sum(r.position_valid is True for r in rows) / len(rows)
        assert CUSTOM_MODE_AUTO_LAND not in [m for _, m in f.tap.vehicle_modes(since_s=t_cut)]
        errs = [r.formation_err_m for r in rows if r.t_s > t_ext + 3.0 and r.formation_err_m is not None]
        figures["external_rmse_m"] = rmse(errs)
        figures["external_max_dev_m"] = max(errs)
        f.runner.request_shutdown()
        await f.reach(S.PX4_LAND, timeout_s=3.0)

    await fly(tmp_path, cfg, STRAIGHT_SCENARIO, body)
    print(
        "\nexternal-position figures (TEST-ONLY truth tracker):", {k: round(v, 3) for k, v in figures.items()}
    )
    assert figures["gps_loss_to_external_s"] < 6.0
    assert figures["px4_position_valid_frac"] > 0.95
    assert figures["external_rmse_m"] <= 0.45


async def test_stale_estimates_never_reach_the_vehicle(tmp_path: Path) -> None:
    """The tracker stops: within a tick of ``stale_estimate_s`` the wire carries only hover setpoints."""
    cfg = mission_cfg(leader_lost_action="land", stall_hover_s=3.0)
    stale_s = cfg.mission.stale_estimate_s
    tick_s = 1.0 / cfg.link.setpoint_rate_hz
    figures: dict[str, float] = {}

    async def body(f: Flight) -> None:
        await f.reach(S.FOLLOW, timeout_s=60)
        await f.sim_time(27.0)  # the leader flies north at 1.5 m/s: the follower chases it
        moving = f.tap.setpoints(since_s=f.clock.now_s() - 1.0)
        assert max(abs(s.msg.vx) for s in moving) > 1.0
        f.tracker.paused = True
        t_stall = f.clock.now_s()
        await f.reach(S.HOVER, timeout_s=stale_s + 0.5)
        figures["stall_to_hover_s"] = f.clock.now_s() - t_stall
        await f.reach(S.PX4_LAND, timeout_s=cfg.mission.stall_hover_s + 1.0)
        t_abort = f.clock.now_s()
        await asyncio.sleep(2.0)
        late = f.tap.setpoints(since_s=t_stall + stale_s + 2 * tick_s)
        hover = [s for s in late if s.t_s < t_abort]
        assert hover
        for s in hover:
            m = s.msg
            assert m.get_type() == "SET_POSITION_TARGET_LOCAL_NED"
            assert (m.vx, m.vy, m.vz, m.yaw_rate) == (0.0, 0.0, 0.0, 0.0)
        after = [s for s in late if s.t_s >= t_abort]
        figures["last_setpoint_after_abort_s"] = max((s.t_s - t_abort for s in after), default=0.0)
        speeds = [r.speed_h_true_m_s for r in f.rec.rows if t_stall + 3.0 <= r.t_s <= t_abort]
        figures["speed_after_3s_hover_m_s"] = max(v for v in speeds if v is not None)
        assert f.link.snapshot().flight_mode == FlightMode.LAND

    await fly(tmp_path, cfg, STRAIGHT_SCENARIO, body)
    print("\nstale-estimate figures:", {k: round(v, 3) for k, v in figures.items()})
    assert figures["stall_to_hover_s"] <= stale_s + 2 * tick_s + 0.05
    assert figures["last_setpoint_after_abort_s"] <= 0.3  # the stream stops with the abort
    assert figures["speed_after_3s_hover_m_s"] <= 0.3


async def test_an_operators_hold_then_start_follows_again(tmp_path: Path) -> None:
    """Through real MAVSDK: hold hands the follower to PX4's Hold, and start takes it back into offboard."""
    cfg = mission_cfg(shutdown_action="land")
    answers: list[str] = []

    async def body(f: Flight) -> None:
        await f.reach(S.FOLLOW, timeout_s=60)
        await asyncio.sleep(2.0)
        answers.append(str(await f.runner.command(OperatorRequest(OperatorCommand.HOLD))))
        await asyncio.sleep(3.0)
        assert f.link.snapshot().flight_mode == FlightMode.HOLD
        assert f.runner.state == S.PX4_HOLD  # nothing resumes by itself
        answers.append(str(await f.runner.command(OperatorRequest(OperatorCommand.START))))
        await asyncio.sleep(3.0)
        assert f.runner.state == S.FOLLOW, f.rec.reasons()
        assert f.link.snapshot().flight_mode == FlightMode.OFFBOARD
        answers.append(str(await f.runner.command(OperatorRequest(OperatorCommand.START))))
        f.runner.request_shutdown()
        await f.reach(S.PX4_LAND, timeout_s=3.0)

    await fly(tmp_path, cfg, HOVER_SCENARIO, body)
    assert answers[0] == (
        "hold: follow -> px4_hold (operator asked to hold). Next: PX4 holds position until companion start "
        "(follow again) or companion command land"
    )
    assert answers[1].startswith("start: px4_hold -> acquire (operator asked to follow again: from px4_hold)")
    assert answers[2] == "start refused: the mission is already under way (state follow)"


async def test_one_start_after_a_landing_flies_again(tmp_path: Path) -> None:
    """Through real MAVSDK: land, PX4 disarms, and one start arms, takes off and follows again."""
    cfg = mission_cfg(shutdown_action="land")
    answers: list[str] = []

    async def body(f: Flight) -> None:
        await f.reach(S.FOLLOW, timeout_s=60)
        answers.append(str(await f.runner.command(OperatorRequest(OperatorCommand.LAND))))
        await f.reach(S.DISARMED, timeout_s=60)
        again = f.rec.state_events[S.FOLLOW] = asyncio.Event()  # set by the next FOLLOW only
        answers.append(str(await f.runner.command(OperatorRequest(OperatorCommand.START))))
        async with asyncio.timeout(90):
            await again.wait()
        await asyncio.sleep(2.0)  # PX4 confirms offboard after the mission asks for it
        assert f.runner.state == S.FOLLOW, f.rec.reasons()
        assert f.link.snapshot().flight_mode == FlightMode.OFFBOARD
        f.runner.request_shutdown()
        await f.reach(S.PX4_LAND, timeout_s=3.0)

    await fly(tmp_path, cfg, HOVER_SCENARIO, body)
    assert answers[0] == (
        "land: follow -> px4_land (operator asked to land). Next: PX4 lands and disarms; companion start "
        "once disarmed flies again"
    )
    assert answers[1].startswith(
        "start: disarmed -> preflight (mission start requested); preflight -> arming (preflight checks "
        "passed). Next: arms (up to 3 tries), takes off to 5 m"
    )
