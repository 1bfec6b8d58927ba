"""The mission state machine, step by step with a ManualClock: every transition and every reason."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.config import Config, FormationConfig, LeaderConfig, MissionConfig
from companion.estimation.leader import TrackStatus
from companion.kernel.flight import (
    AttitudeSetpoint,
    FlightMode,
    LandedState,
    VelocityBodySetpoint,
    VelocityNedSetpoint,
)
from companion.mission.safety import SafetyLimits, barrier_speed_m_s
from companion.mission.states.request import go
from companion.mission.types import (
    CommandKind,
    MissionInputs,
    MissionState,
    OperatorCommand,
    Reason,
    VisionMode,
)

from .mission_harness import DT_S, FakeAutopilot, Harness, all_commands, leader

S = MissionState
R = Reason


def cfg_with(**mission: object) -> Config:
    # The external-position fallback needs the leader's shared position (the config refuses it otherwise).
    leader = LeaderConfig(
        shared_position="mqtt" if mission.get("gps_loss_policy") == "vision_external_position" else "none"
    )
    return Config(mission=MissionConfig(**mission), leader=leader)  # type: ignore[arg-type]


# ---------------------------------------------------------------------- boot to FOLLOW
def test_boot_waits_for_link_then_preflight() -> None:
    h = Harness(ap=FakeAutopilot(connected=False))
    h.run(1.0)
    assert h.state == S.WAIT_LINK
    assert not h.transitions
    h.ap.connected = True
    h.step()
    assert h.last_transition().reason == R.LINK_UP
    assert h.state == S.PREFLIGHT


def test_preflight_waits_for_start_and_a_settled_gps() -> None:
    h = Harness()
    h.run(10.0)
    assert h.state == S.PREFLIGHT  # no start request: never arms on its own
    h.ap.gps_fix = 1
    h.run(1.0)
    h.start = True
    h.run(10.0)
    assert h.state == S.PREFLIGHT  # no GPS
    h.ap.gps_fix = 3
    h.run(h.cfg.mission.gps_restore_s - 0.5)
    assert h.state == S.PREFLIGHT  # GPS must be good for gps_restore_s first
    h.run(1.0)
    assert h.has(S.ARMING, R.PREFLIGHT_OK)


def test_arm_takeoff_acquire_follow() -> None:
    h = Harness()
    h.to_follow()
    assert [r[2] for r in h.reasons()] == [
        "LINK_UP",
        "PREFLIGHT_OK",
        "ARMED",
        "TAKEOFF_DONE",
        "LEADER_ACQUIRED",
    ]
    sent = [c.kind for c in h.ap.sent]
    assert sent[:3] == [CommandKind.ARM, CommandKind.TAKEOFF, CommandKind.START_OFFBOARD]
    takeoff = next(c for c in h.ap.sent if c.kind == CommandKind.TAKEOFF)
    assert takeoff.altitude_m == h.cfg.mission.takeoff_altitude_m
    out = h.step()
    assert isinstance(out.setpoint, VelocityBodySetpoint)


def test_acquire_needs_a_confirmed_track_not_a_tentative_one() -> None:
    h = Harness()
    h.start = True
    h.leader_mode = "fresh"
    h.leader_status = TrackStatus.TENTATIVE
    h.run_until(S.ACQUIRE)
    h.run(5.0)
    assert h.state == S.ACQUIRE
    assert all(o.setpoint is None for o in h.outputs)  # PX4 holds; nothing is streamed while acquiring
    h.leader_status = TrackStatus.CONFIRMED
    h.step()
    assert h.has(S.FOLLOW, R.LEADER_ACQUIRED)


def test_first_offboard_setpoint_comes_with_the_start_command() -> None:
    h = Harness()
    h.start = True
    h.leader_mode = "fresh"
    out = h.run_until(S.FOLLOW)
    assert out.setpoint is not None
    assert CommandKind.START_OFFBOARD in [c.kind for c in out.commands]


def test_a_service_restarted_in_the_air_observes_and_commands_nothing() -> None:
    ap = FakeAutopilot()
    ap.fly()
    h = Harness(ap=ap)
    h.start = True  # service.auto_start: a ground start, never a takeover
    h.leader_mode = "fresh"
    outs = h.run(20.0)
    assert h.state == S.OBSERVE
    assert h.has(S.OBSERVE, R.AIRBORNE_NOT_STARTED)
    assert ap.sent == []
    assert all(o.setpoint is None and o.external_position is None for o in outs)
    assert h.machine.operator_refusal(OperatorCommand.LAND) is not None
    h.operator = OperatorCommand.LAND
    h.run(1.0)
    assert h.state == S.OBSERVE
    assert ap.sent == []


def test_an_operator_start_takes_over_an_airborne_vehicle() -> None:
    ap = FakeAutopilot()
    ap.fly()
    h = Harness(ap=ap)
    h.run(3.0)
    assert h.state == S.OBSERVE
    h.takeover = True
    h.run(6.0)
    assert h.has(S.ACQUIRE, R.ALREADY_FLYING)
    assert CommandKind.ARM not in [c.kind for c in ap.sent]


def test_resume_in_air_takes_over_without_a_start() -> None:
    ap = FakeAutopilot()
    ap.fly()
    h = Harness(Config.model_validate({"mission": {"resume_in_air": True}}), ap=ap)
    h.run(6.0)
    assert h.has(S.ACQUIRE, R.ALREADY_FLYING)
    assert not h.has(S.OBSERVE, R.AIRBORNE_NOT_STARTED)


def test_an_observed_vehicle_that_lands_is_back_in_preflight_without_a_stale_start() -> None:
    ap = FakeAutopilot()
    ap.fly()
    h = Harness(ap=ap)
    h.start = True
    h.run(2.0)
    assert h.state == S.OBSERVE
    ap.armed = False
    ap.landed = LandedState.ON_GROUND
    h.run(2.0)
    assert h.has(S.PREFLIGHT, R.LANDED_WHILE_OBSERVED)
    h.run(5.0)
    assert h.state == S.PREFLIGHT  # the start that came before the landing is spent
    assert CommandKind.ARM not in [c.kind for c in ap.sent]


def test_already_flying_without_gps_lands_once_started() -> None:
    ap = FakeAutopilot(gps_fix=0, position_valid=False)
    ap.fly()
    h = Harness(ap=ap)
    h.run(1.0)
    assert h.state == S.OBSERVE
    h.takeover = True
    h.run(1.0)
    assert h.has(S.CONTROLLED_LANDING, R.ALREADY_FLYING)


def test_operator_hold_without_gps_is_refused_by_the_machine() -> None:
    h = Harness()
    h.start = True
    h.leader_mode = "fresh"
    h.to_follow()
    assert h.machine.operator_refusal(OperatorCommand.HOLD) is None
    h.lose_gps()
    h.run(2.0)
    assert h.machine.operator_refusal(OperatorCommand.HOLD) == (
        "hold needs GPS (PX4 cannot hold without a position); land instead"
    )
    assert h.machine.operator_refusal(OperatorCommand.LAND) is None


def test_arm_refused_three_times_gives_up() -> None:
    ap = FakeAutopilot(refuse={CommandKind.ARM: "Arming denied: Resolve system health failures first"})
    h = Harness(ap=ap)
    h.start = True
    h.run_until(S.DISARMED, timeout_s=30)
    t = h.last_transition()
    assert t.reason == R.ARM_FAILED
    assert "health" in t.detail
    assert [c.kind for c in ap.sent].count(CommandKind.ARM) == 3


def test_unanswered_arm_is_retried_after_the_command_goes_stale() -> None:
    ap = FakeAutopilot(mute={CommandKind.ARM})
    h = Harness(ap=ap)
    h.start = True
    h.run(30.0)
    assert [c.kind for c in ap.sent].count(CommandKind.ARM) >= 2


def test_takeoff_refused_on_the_ground_disarms() -> None:
    ap = FakeAutopilot(refuse={CommandKind.TAKEOFF: "COMMAND_DENIED"})
    h = Harness(ap=ap)
    h.start = True
    h.run_until(S.DISARMED, timeout_s=30)
    assert h.has(S.LANDED, R.TAKEOFF_FAILED)
    assert h.last_transition().reason == R.DISARMED
    assert CommandKind.DISARM in [c.kind for c in ap.sent]


def test_takeoff_timeout_in_air_lands_with_px4() -> None:
    ap = FakeAutopilot(climb_m_s=0.05)
    h = Harness(cfg=cfg_with(takeoff_timeout_s=5.0), ap=ap)
    h.start = True
    h.run_until(S.TAKEOFF)
    ap.landed = LandedState.IN_AIR
    h.run_until(S.PX4_LAND, timeout_s=10)
    assert h.last_transition().reason == R.TAKEOFF_FAILED
    assert ap.mode == FlightMode.LAND


def test_gps_lost_during_takeoff_goes_to_controlled_landing() -> None:
    ap = FakeAutopilot(climb_m_s=0.5)
    h = Harness(ap=ap)
    h.start = True
    h.run_until(S.TAKEOFF)
    h.run(1.0)
    ap.landed = LandedState.IN_AIR
    ap.gps_fix = 0
    h.run_until(S.CONTROLLED_LANDING, timeout_s=2)
    assert h.last_transition().reason == R.GPS_LOST


def test_disarmed_during_takeoff() -> None:
    h = Harness()
    h.start = True
    h.run_until(S.TAKEOFF)
    h.ap.armed = False
    h.step()
    assert h.state == S.DISARMED
    assert h.last_transition().reason == R.DISARMED


@pytest.mark.parametrize(
    ("action", "state", "mode"),
    [
        ("land", S.PX4_LAND, FlightMode.LAND),
        ("hold", S.PX4_HOLD, FlightMode.HOLD),
        ("rtl", S.PX4_RTL, FlightMode.RETURN_TO_LAUNCH),
    ],
)
def test_acquire_timeout_runs_the_configured_abort(
    action: str, state: MissionState, mode: FlightMode
) -> None:
    h = Harness(cfg=cfg_with(acquire_timeout_s=5.0, leader_lost_action=action))
    h.start = True
    h.run_until(S.ACQUIRE)
    h.run_until(state, timeout_s=6)
    assert h.last_transition().reason == R.ACQUIRE_TIMEOUT
    assert h.ap.mode == mode


def test_landed_while_acquiring() -> None:
    h = Harness()
    h.start = True
    h.run_until(S.ACQUIRE)
    h.run(2.0)
    h.ap.landed = LandedState.ON_GROUND
    h.run_until(S.LANDED, timeout_s=3)
    assert h.last_transition().reason == R.TOUCHDOWN


# ---------------------------------------------------------------------- GPS loss ladder
def test_gps_loss_switches_to_attitude_setpoints_well_before_px4_invalidates() -> None:
    h = Harness()
    h.to_follow()
    t_loss = h.now_s
    h.lose_gps()
    out = h.run_until(S.FOLLOW_VISION, timeout_s=2)
    assert h.last_transition().reason == R.GPS_LOST
    # PX4 invalidates velocity 5 s after GPS stops; we must be on attitude setpoints long before.
    assert h.now_s - t_loss <= h.cfg.mission.gps_loss_confirm_s + 2 * DT_S
    assert isinstance(out.setpoint, AttitudeSetpoint)
    assert out.vision_mode == VisionMode.ATTITUDE
    # Still offboard: no mode command went out, the setpoint kind just changed.
    assert CommandKind.STOP_OFFBOARD not in all_commands(h.outputs[-3:])
    for o in h.run(10.0):
        assert isinstance(o.setpoint, AttitudeSetpoint)


def test_px4_saying_position_invalid_is_a_gps_loss_at_once() -> None:
    h = Harness()
    h.to_follow()
    h.ap.position_valid = False
    h.step()
    assert h.state == S.FOLLOW_VISION
    assert h.last_transition().reason == R.GPS_LOST


def test_gps_loss_with_land_policy_lands_under_our_control() -> None:
    h = Harness(cfg=cfg_with(gps_loss_policy="land"))
    h.to_follow()
    h.lose_gps()
    out = h.run_until(S.CONTROLLED_LANDING, timeout_s=2)
    t = h.last_transition()
    assert t.reason == R.GPS_LOST
    assert t.detail == "policy land"
    assert isinstance(out.setpoint, AttitudeSetpoint)


def test_gps_loss_without_leader_lands() -> None:
    h = Harness()
    h.to_follow()
    h.leader_status = TrackStatus.LOST
    h.lose_gps()
    h.run_until(S.CONTROLLED_LANDING, timeout_s=2)
    assert h.has(S.CONTROLLED_LANDING, R.GPS_LOST)


def test_no_attitude_telemetry_means_no_vision_fallback() -> None:
    h = Harness()
    h.to_follow()
    h.lose_gps()
    h.run_until(S.FOLLOW_VISION, timeout_s=2)
    h.ap.alt_rel_m = math.nan
    h.step()
    assert h.state == S.CONTROLLED_LANDING
    assert h.last_transition().reason == R.NO_VISION_FALLBACK


def test_a_stall_of_the_service_is_not_a_lost_link_or_leader() -> None:
    """A paused service resumes on old telemetry and an old leader track: that is its pause, not the world's.

    The inputs get their whole timeout after the resume; the same silence without the pause is a loss.
    """
    h = Harness()
    h.to_follow()
    h.lose_gps()
    h.run_until(S.FOLLOW_VISION, timeout_s=2)
    n = len(h.transitions)
    out = h.stall(0.9)  # longer than the attitude (0.5 s) and leader (1.0 s with the gap) timeouts
    assert h.transitions[n:] == [], h.reasons()
    assert out.setpoint is not None
    # Still silent a whole timeout after the resume: now it is the link.
    h.run(h.cfg.link.telemetry_timeout_s + 0.1)
    assert h.has(S.CONTROLLED_LANDING, R.NO_VISION_FALLBACK), h.reasons()


def test_the_same_silence_without_a_stall_is_a_loss() -> None:
    h = Harness()
    h.to_follow()
    h.lose_gps()
    h.run_until(S.FOLLOW_VISION, timeout_s=2)
    h.ap.frozen_at_s = h.now_s
    h.run(0.9)
    assert h.has(S.CONTROLLED_LANDING, R.NO_VISION_FALLBACK), h.reasons()


def test_gps_restored_returns_to_velocity_follow_after_probation() -> None:
    h = Harness()
    h.to_follow()
    h.lose_gps()
    h.run_until(S.FOLLOW_VISION, timeout_s=2)
    h.run(3.0)
    h.ap.gps_fix = 3
    h.run(h.cfg.mission.gps_restore_s - 0.5)
    assert h.state == S.FOLLOW_VISION
    out = h.run_until(S.FOLLOW, timeout_s=1.0)
    assert h.last_transition().reason == R.GPS_RESTORED
    assert isinstance(out.setpoint, VelocityBodySetpoint)


def test_external_position_policy_upgrades_to_velocity_once_px4_accepts() -> None:
    h = Harness(cfg=cfg_with(gps_loss_policy="vision_external_position"))
    h.to_follow()
    h.shared = (20.0, 3.0, -5.0)
    h.leader_p = (5.0, 0.5, 0.0)
    h.lose_gps()
    h.ap.position_valid = False
    out = h.run_until(S.FOLLOW_VISION, timeout_s=2)
    assert isinstance(out.setpoint, AttitudeSetpoint)  # attitude first, whatever the policy
    assert out.external_position is not None
    assert out.external_position.p_ned_m == pytest.approx((15.0, 2.5, -5.0))
    h.run(3.0)
    assert h.machine.vision_mode == VisionMode.ATTITUDE  # PX4 has not accepted it yet
    h.ap.position_valid = True
    outs = h.run(1.5)
    assert h.has(S.FOLLOW_VISION, R.VISION_MODE_CHANGED)
    assert h.last_transition().detail == "external position accepted"
    assert isinstance(outs[-1].setpoint, VelocityBodySetpoint)
    assert outs[-1].vision_mode == VisionMode.EXTERNAL_POSITION
    # The shared leader position stops: back to attitude, at once.
    h.shared = None
    out = h.step()
    assert isinstance(out.setpoint, AttitudeSetpoint)
    assert h.last_transition().reason == R.VISION_MODE_CHANGED
    assert "stale" in h.last_transition().detail


def test_external_position_rejected_by_px4_falls_back_to_attitude() -> None:
    h = Harness(cfg=cfg_with(gps_loss_policy="vision_external_position"))
    h.to_follow()
    h.shared = (20.0, 0.0, -5.0)
    h.lose_gps()
    h.ap.position_valid = False
    h.run_until(S.FOLLOW_VISION, timeout_s=2)
    h.ap.position_valid = True
    h.run(1.5)
    assert h.machine.vision_mode == VisionMode.EXTERNAL_POSITION
    h.ap.position_valid = False
    out = h.step()
    assert isinstance(out.setpoint, AttitudeSetpoint)
    assert "rejected" in h.last_transition().detail


def test_external_position_never_accepted_stops_being_sent() -> None:
    h = Harness(cfg=cfg_with(gps_loss_policy="vision_external_position", external_position_accept_s=3.0))
    h.to_follow()
    h.shared = (20.0, 0.0, -5.0)
    h.lose_gps()
    h.ap.position_valid = False
    h.run_until(S.FOLLOW_VISION, timeout_s=2)
    outs = h.run(3.5)
    assert h.last_transition().reason == R.VISION_MODE_CHANGED
    assert "not accepted" in h.last_transition().detail
    assert outs[0].external_position is not None
    assert outs[-1].external_position is None
    assert all(isinstance(o.setpoint, AttitudeSetpoint) for o in outs)
    assert sum(t.reason == R.VISION_MODE_CHANGED for t in h.transitions) == 1
    h.run(3.0)
    assert sum(t.reason == R.VISION_MODE_CHANGED for t in h.transitions) == 1  # said once


# ---------------------------------------------------------------------- leader loss
def test_leader_lost_then_reacquired() -> None:
    h = Harness()
    h.to_follow()
    h.leader_status = TrackStatus.LOST
    out = h.step()
    assert h.state == S.REACQUIRE
    assert h.last_transition().reason == R.LEADER_LOST
    assert isinstance(out.setpoint, VelocityBodySetpoint)
    h.run(1.0)
    h.leader_status = TrackStatus.TENTATIVE
    h.run(0.5)
    assert h.state == S.REACQUIRE  # tentative is not enough
    h.leader_status = TrackStatus.CONFIRMED
    h.step()
    assert h.state == S.FOLLOW
    assert h.last_transition().reason == R.LEADER_REACQUIRED


def test_the_fast_slew_waits_for_a_clean_link() -> None:
    """Steady track: the horizontal command may change at the steady slew, but not while the attitude arrives
    late (averaged over ~1 s), nor for ``steady_link_hold_s`` after."""
    f = Config().formation
    h = Harness()
    h.to_follow()
    h.leader_mode, h.leader_status = "fresh", TrackStatus.CONFIRMED

    def step_after_jump_m_s(settle_s: float) -> float:
        """Hold the slot for ``settle_s``, then put the leader 10 m further: the command's first change."""
        h.leader_p = (5.0, 0.0, 0.0)
        h.run(settle_s)
        outs = [h.step() for _ in range(2)]
        h.leader_p = (15.0, 0.0, 0.0)
        outs += [h.step() for _ in range(2)]
        v = []
        for o in outs:
            assert isinstance(o.setpoint, VelocityBodySetpoint)
            v.append(o.setpoint.v_body_m_s)
        assert math.hypot(v[1][0] - v[0][0], v[1][1] - v[0][1]) < 1e-6  # settled before the jump
        return math.hypot(v[3][0] - v[2][0], v[3][1] - v[2][1])

    assert step_after_jump_m_s(1.0) == pytest.approx(f.command_slew_steady_m_s2 * DT_S, rel=0.02)
    h.ap.attitude_lag_s = 0.04  # link-loss's lossy spells: ~0.033 s on average
    assert step_after_jump_m_s(2.0) == pytest.approx(f.command_slew_m_s2 * DT_S, rel=0.02)
    h.ap.attitude_lag_s = 0.0  # clean again: still slow for the hold
    assert step_after_jump_m_s(1.0) == pytest.approx(f.command_slew_m_s2 * DT_S, rel=0.02)
    assert step_after_jump_m_s(f.steady_link_hold_s) == pytest.approx(
        f.command_slew_steady_m_s2 * DT_S, rel=0.02
    )


def test_the_steady_range_gain_is_flown_only_on_a_steady_track() -> None:
    """1 m beyond the slot: the command is ``kp_xy_steady`` x 1 m on a steady track, ``kp_xy`` x 1 m on a
    blinking one (seen in half its recent frames)."""
    f = FormationConfig(
        kp_xy=1.0, kp_xy_steady=2.0, ki_xy=0.0, kd_xy=0.0, leader_velocity_ff=0.0, leader_accel_ff_s=0.0
    )
    for hit_ratio, expect_m_s in ((1.0, 2.0), (0.5, 1.0)):
        h = Harness(cfg=Config(formation=f))
        h.to_follow()
        h.leader_mode, h.leader_status = "fresh", TrackStatus.CONFIRMED
        h.leader_hit_ratio = hit_ratio
        h.leader_p = (6.0, 0.0, 0.0)
        h.run(2.0)
        out = h.step()
        assert isinstance(out.setpoint, VelocityBodySetpoint)
        assert out.setpoint.v_body_m_s[0] == pytest.approx(expect_m_s, abs=1e-6)


def test_reacquire_waits_for_a_steady_track() -> None:
    """A new track after a loss must be old and seen often enough (a phantom of sporadic hits is not)."""
    h = Harness(cfg=cfg_with(reacquire_min_track_s=0.8, reacquire_min_hit_ratio=0.6))
    h.to_follow()
    h.leader_status = TrackStatus.LOST
    h.step()
    assert h.state == S.REACQUIRE
    h.run(0.5)
    h.leader_status = TrackStatus.CONFIRMED
    h.leader_p = (5.0, 3.0, 0.0)  # 3 m from where the leader was lost
    h.leader_track_age_s, h.leader_hit_ratio = 0.4, 1.0  # just confirmed: too young
    h.run(0.5)
    assert h.state == S.REACQUIRE
    h.leader_track_age_s, h.leader_hit_ratio = 2.0, 0.4  # old, but seen in 2 of 5 frames
    h.run(0.5)
    assert h.state == S.REACQUIRE
    h.leader_track_age_s, h.leader_hit_ratio = 0.8, 0.6  # both at their bounds
    h.step()
    assert h.state == S.FOLLOW
    assert h.last_transition().reason == R.LEADER_REACQUIRED


def test_a_young_track_where_the_leader_was_lost_is_the_leader_while_coasting() -> None:
    """A confirmed track where the lost leader dead-reckons to is taken at once during the coast (a
    hovering leader found after a short miss would otherwise start off while the track ages), not during
    the scan, and not 0.8 m away."""
    cfg = cfg_with(reacquire_min_track_s=0.8, reacquire_coast_s=2.0, reacquire_scan_s=10.0)
    for found_after_s, found_p, taken in (
        (0.5, (5.3, 0.2, 0.0), True),
        (0.5, (5.0, 0.8, 0.0), False),
        (2.5, (5.3, 0.2, 0.0), False),
    ):
        h = Harness(cfg=cfg)
        h.to_follow()
        h.leader_status = TrackStatus.LOST
        h.step()
        h.run(found_after_s)
        assert h.state == S.REACQUIRE
        h.leader_status, h.leader_p = TrackStatus.CONFIRMED, found_p
        h.leader_track_age_s = 0.3
        h.run(0.2)
        assert (h.state == S.FOLLOW) == taken, (found_after_s, found_p)


def test_coasting_on_a_leader_lost_hovering_holds_station() -> None:
    """A leader lost at 0.2 m/s (hovering: its velocity is noise) is not followed at that velocity: the
    follower holds where it lost it, flying back (at most 0.5 m/s) when pushed off. A leader lost at
    2 m/s is coasted on at its velocity, wherever the follower is."""
    for v_leader, drift_m, expect_n, expect_e in (
        ((0.2, 0.1, 0.0), (-0.3, 0.1, 0.0), 0.3, -0.1),
        ((0.2, 0.1, 0.0), (-2.0, 0.0, 0.0), 0.5, 0.0),
        ((2.0, 0.0, 0.0), (-0.3, 0.1, 0.0), 2.0, 0.0),
    ):
        h = Harness(cfg=cfg_with(reacquire_coast_s=2.0))
        h.to_follow()
        h.leader_v = v_leader
        h.run(0.2)
        h.leader_status = TrackStatus.LOST
        h.step()
        assert h.state == S.REACQUIRE
        p0 = h.ap.p_ned_m
        h.ap.p_ned_m = (p0[0] + drift_m[0], p0[1] + drift_m[1], p0[2])
        out = h.step()
        assert isinstance(out.setpoint, VelocityBodySetpoint)
        assert out.setpoint.v_body_m_s[:2] == pytest.approx((expect_n, expect_e), abs=1e-6), v_leader


def test_a_leader_that_shares_its_velocity_is_led_on_it() -> None:
    """The camera still sees the leader hovering in its slot while the leader's shares say it sets off
    north at 1 m/s^2: half a second later the follower is commanded north, at least the leader's shared
    speed (0.5 m/s) and then some for its acceleration; with ``lead_on_shared_motion`` off it waits for
    the camera (a lone follower: no formation plan)."""
    for on in (True, False):
        cfg = Config(formation=FormationConfig(lead_on_shared_motion=on))
        h = Harness(cfg=cfg)
        h.to_follow()
        h.shared = (5.0, 0.0, -5.0)
        h.shared_v = (0.0, 0.0, 0.0)
        h.run(0.5)
        t0 = h.now_s
        out = None
        for _ in range(10):
            h.shared_v = (1.0 * (h.now_s + 0.05 - t0), 0.0, 0.0)
            out = h.step()
        assert out is not None
        assert isinstance(out.setpoint, VelocityBodySetpoint)
        v_n = out.setpoint.v_body_m_s[0]
        if on:
            assert v_n > 0.6, v_n
        else:
            assert abs(v_n) < 0.1, v_n


def test_while_the_camera_misses_a_sharing_leader_the_follower_flies_on_its_shares() -> None:
    """The shares put the leader 0.8 m further and 0.3 m left of where the camera sees it (GPS errors).
    When the camera then misses the leader and the shares say it flies right at 2 m/s, the follower turns
    right after it (the camera's last position carried on at the shares' relative velocity: about 0.8 m
    right after 0.4 s) instead of holding on the track's coast; with ``coast_on_shared_position`` off it
    holds on the coast."""
    for on in (True, False):
        cfg = Config(formation=FormationConfig(coast_on_shared_position=on))
        h = Harness(cfg=cfg)
        h.to_follow()
        p_own = np.array(h.ap.p_ned_m)
        h.shared = tuple(np.add(p_own, (5.8, -0.3, 0.0)))
        h.shared_v = (0.0, 0.0, 0.0)
        h.run(3.0)
        assert not h.outputs[-1].coasted_on_shared_position
        h.leader_status = TrackStatus.COASTING
        h.leader_last_measurement_s = h.now_s
        h.shared_v = (0.0, 2.0, 0.0)
        h.run(0.35)
        out = h.step()
        assert isinstance(out.setpoint, VelocityBodySetpoint)
        assert out.formation_error_ned_m is not None
        assert out.coasted_on_shared_position is on
        if on:
            assert out.setpoint.yaw_rate_rad_s > 0.15, out.setpoint
            assert out.formation_error_ned_m[1] == pytest.approx(0.8, abs=0.05)
        else:
            assert abs(out.setpoint.yaw_rate_rad_s) < 0.01, out.setpoint
            assert abs(out.formation_error_ned_m[1]) < 0.01


def test_reacquire_coasts_on_the_leaders_shared_velocity() -> None:
    """A leader lost while the camera had it hovering, which shares that it flies east at 1.5 m/s, is
    coasted after at that velocity (not held station on), and keeps being as its shares change."""
    h = Harness(cfg=cfg_with(reacquire_coast_s=2.0))
    h.to_follow()
    h.shared = (5.0, 0.0, -5.0)
    h.shared_v = (0.0, 1.5, 0.0)
    h.run(0.2)
    h.leader_status = TrackStatus.LOST
    out = h.step()
    assert h.state == S.REACQUIRE
    out = h.step()
    assert isinstance(out.setpoint, VelocityBodySetpoint)
    assert out.setpoint.v_body_m_s[:2] == pytest.approx((0.0, 1.5), abs=1e-6)
    h.shared_v = (1.0, 1.0, 0.0)
    h.run(0.5)
    out = h.step()
    assert isinstance(out.setpoint, VelocityBodySetpoint)
    assert out.setpoint.v_body_m_s[:2] == pytest.approx((1.0, 1.0), abs=1e-6)


def test_a_track_dropped_as_far_field_is_searched_for_from_where_the_follower_is() -> None:
    """A track the tracker drops as far-field (a cloud the follower chased at 2 m/s) is not coasted on:
    the follower stops and searches; the same loss of a real track coasts on at its velocity."""
    for far_field, expect_v_n in ((True, 0.0), (False, 2.0)):
        h = Harness(cfg=cfg_with(reacquire_coast_s=2.0))
        h.to_follow()
        h.leader_v = (2.0, 0.0, 0.0)
        h.run(0.2)
        h.leader_mode = "frozen"
        h._frozen = dataclasses.replace(
            leader(h.now_s, TrackStatus.LOST, h.leader_p, h.leader_v), far_field=far_field
        )
        h.step()
        assert h.state == S.REACQUIRE
        assert ("far-field" in h.last_transition().detail) == far_field
        outs = h.run(1.5)
        assert all(o.state == S.REACQUIRE for o in outs)
        assert all(isinstance(o.setpoint, VelocityBodySetpoint) for o in outs)
        v_n = [o.setpoint.v_body_m_s[0] for o in outs if isinstance(o.setpoint, VelocityBodySetpoint)]
        assert v_n[-1] == pytest.approx(expect_v_n, abs=1e-6), far_field


def test_reacquire_looks_at_a_candidate_but_does_not_fly_to_it() -> None:
    """While scanning, an unsteady track turns the camera onto it (so it stays in view), nothing more."""
    cfg = cfg_with(reacquire_coast_s=0.5, reacquire_scan_s=10.0)
    h = Harness(cfg=cfg)
    h.to_follow()
    h.leader_p = (4.0, 3.0, 0.0)  # last seen to the right: the scan would turn right
    h.run(0.2)
    h.leader_status = TrackStatus.LOST
    h.step()
    h.run(1.0)
    h.leader_status = TrackStatus.TENTATIVE
    h.leader_p = (3.0, -4.0, 0.0)  # something found to the left, not steady
    h.leader_track_age_s, h.leader_hit_ratio = 0.2, 0.5
    outs = h.run(0.5)
    assert all(o.state == S.REACQUIRE for o in outs)
    sps = [o.setpoint for o in outs if isinstance(o.setpoint, VelocityBodySetpoint)]
    assert sps
    assert all(sp.yaw_rate_rad_s < 0.0 for sp in sps)  # toward it, against the scan's direction
    assert all(sp.v_body_m_s[:2] == (0.0, 0.0) for sp in sps)


def test_reacquire_looks_where_the_leaders_shares_put_it() -> None:
    """Lost to the right, the leader shares that it is to the left: the scan turns left and stops there
    (the yaw rate falls as the heading closes on it) instead of sweeping right."""
    cfg = cfg_with(reacquire_coast_s=0.5, reacquire_scan_s=10.0)
    h = Harness(cfg=cfg)
    h.to_follow()
    h.leader_p = (4.0, 3.0, 0.0)  # last seen to the right: the sweep would turn right
    h.run(0.2)
    h.leader_status = TrackStatus.LOST
    h.step()
    h.run(0.6)
    h.shared = (3.0, -4.0, -5.0)
    h.shared_v = (0.0, 0.0, 0.0)
    outs = h.run(0.5)
    sps = [o.setpoint for o in outs if isinstance(o.setpoint, VelocityBodySetpoint)]
    assert sps
    assert all(o.state == S.REACQUIRE for o in outs)
    assert all(sp.yaw_rate_rad_s < 0.0 for sp in sps)
    h.ap.yaw_rad = math.atan2(-4.0, 3.0)  # facing it
    sp = h.step().setpoint
    assert isinstance(sp, VelocityBodySetpoint)
    assert sp.yaw_rate_rad_s == pytest.approx(0.0, abs=1e-6)


def test_reacquire_coasts_then_scans_toward_the_last_bearing_then_aborts() -> None:
    cfg = cfg_with(reacquire_coast_s=2.0, reacquire_scan_s=4.0, leader_lost_action="land")
    h = Harness(cfg=cfg)
    h.to_follow()
    h.leader_p = (4.0, -3.0, 0.0)  # last seen to the left (west of north, yaw 0)
    h.run(0.2)
    h.leader_status = TrackStatus.LOST
    h.step()
    coast = h.run(1.8)
    scan = h.run(3.9)
    assert all(isinstance(o.setpoint, VelocityBodySetpoint) for o in coast + scan)
    assert all(o.state == S.REACQUIRE for o in coast + scan)
    rates = [o.setpoint.yaw_rate_rad_s for o in scan[4:] if isinstance(o.setpoint, VelocityBodySetpoint)]
    assert rates
    assert all(r == pytest.approx(-math.radians(cfg.mission.scan_yaw_rate_deg_s)) for r in rates)
    assert all(
        o.setpoint.v_body_m_s == (0.0, 0.0, 0.0)
        for o in scan[4:]
        if isinstance(o.setpoint, VelocityBodySetpoint)
    )
    out = h.run_until(S.PX4_LAND, timeout_s=1.0)
    assert h.last_transition().reason == R.REACQUIRE_TIMEOUT
    # The stream stops first, then PX4 is told to land, in the same tick.
    assert [c.kind for c in out.commands] == [CommandKind.STOP_OFFBOARD, CommandKind.LAND]
    assert out.setpoint is None


def test_reacquire_timeout_without_gps_lands_under_our_control() -> None:
    h = Harness(cfg=cfg_with(reacquire_coast_s=1.0, reacquire_scan_s=1.0))
    h.to_follow()
    h.lose_gps()
    h.run_until(S.FOLLOW_VISION, timeout_s=2)
    h.leader_status = TrackStatus.LOST
    outs = h.run(1.9)
    assert all(isinstance(o.setpoint, AttitudeSetpoint) for o in outs)
    h.run_until(S.CONTROLLED_LANDING, timeout_s=1)
    assert h.last_transition().reason == R.REACQUIRE_TIMEOUT


def test_gps_lost_while_reacquiring_on_velocity_lands() -> None:
    h = Harness()
    h.to_follow()
    h.leader_status = TrackStatus.LOST
    h.step()
    h.lose_gps()
    h.run_until(S.CONTROLLED_LANDING, timeout_s=2)
    assert h.last_transition().reason == R.GPS_LOST


# ---------------------------------------------------------------------- perception stall
def test_stale_estimate_hovers_and_never_streams_the_old_setpoint() -> None:
    h = Harness()
    h.to_follow()
    h.leader_v = (2.0, 0.0, 0.0)  # the leader flies away: the law commands a fast chase
    h.leader_p = (8.0, 0.0, 0.0)
    chase = h.run(1.0)[-1].setpoint
    assert isinstance(chase, VelocityBodySetpoint)
    assert chase.v_body_m_s[0] > 1.0
    h.leader_mode = "frozen"  # the pipeline stalls: the same estimate keeps being offered
    outs = h.run(h.cfg.mission.stale_estimate_s + 0.2)
    assert h.has(S.HOVER, R.PERCEPTION_STALL)
    for o in outs:
        if o.state == S.HOVER:
            assert o.setpoint == VelocityBodySetpoint((0.0, 0.0, 0.0), 0.0)


def test_stall_resumes_when_estimates_come_back() -> None:
    h = Harness()
    h.to_follow()
    h.leader_mode = None
    h.run_until(S.HOVER, timeout_s=1)
    h.leader_mode = "fresh"
    h.step()
    assert h.state == S.FOLLOW
    assert h.last_transition().reason == R.PERCEPTION_RESUMED


def test_stall_then_lost_goes_to_reacquire() -> None:
    h = Harness()
    h.to_follow()
    h.leader_mode = None
    h.run_until(S.HOVER, timeout_s=1)
    h.leader_mode = "fresh"
    h.leader_status = TrackStatus.LOST
    h.step()
    assert h.state == S.REACQUIRE


def test_stall_timeout_aborts() -> None:
    h = Harness(cfg=cfg_with(leader_lost_action="hold"))
    h.to_follow()
    h.leader_mode = None
    h.run_until(S.HOVER, timeout_s=1)
    h.run_until(S.PX4_HOLD, timeout_s=h.cfg.mission.stall_hover_s + 0.2)
    assert h.last_transition().reason == R.STALL_TIMEOUT
    assert h.ap.mode == FlightMode.HOLD


def test_stall_without_gps_hovers_on_attitude_then_lands() -> None:
    h = Harness()
    h.to_follow()
    h.lose_gps()
    h.run_until(S.FOLLOW_VISION, timeout_s=2)
    h.leader_mode = None
    outs = h.run(h.cfg.mission.stall_hover_s)
    assert any(o.state == S.HOVER for o in outs)
    for o in outs:
        if o.state == S.HOVER:
            sp = o.setpoint
            assert isinstance(sp, AttitudeSetpoint)
            assert sp.roll_rad == 0.0
            assert sp.pitch_rad == 0.0
    h.run_until(S.CONTROLLED_LANDING, timeout_s=1)
    assert h.last_transition().reason == R.STALL_TIMEOUT


def test_gps_lost_while_hovering_on_velocity_lands() -> None:
    h = Harness()
    h.to_follow()
    h.leader_mode = None
    h.run_until(S.HOVER, timeout_s=1)
    h.lose_gps()
    h.run_until(S.CONTROLLED_LANDING, timeout_s=2)
    assert h.last_transition().detail == "while hovering"


@settings(max_examples=40, deadline=None)
@given(gaps=st.lists(st.tuples(st.floats(0.05, 1.5), st.booleans()), min_size=1, max_size=12))
def test_no_setpoint_is_ever_computed_from_a_stale_estimate(gaps: list[tuple[float, bool]]) -> None:
    """Property: whenever the newest estimate is older than stale_estimate_s, the setpoint is a hover."""
    h = Harness()
    h.to_follow()
    h.leader_v = (1.5, 0.5, 0.0)
    h.leader_p = (7.0, 1.0, 0.0)
    stale_s = h.cfg.mission.stale_estimate_s
    for duration_s, fresh in gaps:
        h.leader_mode = "fresh" if fresh else "frozen"
        for _ in range(max(1, round(duration_s / DT_S))):
            out = h.step()
            est = h._frozen
            age = math.inf if est is None else h.now_s - est.stamp_s
            if age > stale_s and out.setpoint is not None:
                sp = out.setpoint
                if isinstance(sp, VelocityBodySetpoint):
                    assert sp.v_body_m_s[:2] == (0.0, 0.0), (out.state, sp)
                else:
                    assert not isinstance(sp, VelocityNedSetpoint) or sp.v_ned_m_s[:2] == (0.0, 0.0)


# ---------------------------------------------------------------------- landing
def test_controlled_landing_descends_at_landing_speed_then_disarms() -> None:
    h = Harness(cfg=cfg_with(gps_loss_policy="land"))
    h.to_follow()
    h.lose_gps()
    h.run_until(S.CONTROLLED_LANDING, timeout_s=2)
    # The fake does not fly; feed a plausible descent and check the law asks for landing_speed.
    h.ap.v_ned_m_s = (0.0, 0.0, h.cfg.mission.landing_speed_m_s)
    for o in h.run(3.0):
        assert isinstance(o.setpoint, AttitudeSetpoint)
        assert 0.05 <= o.setpoint.thrust_norm <= 0.95
    h.ap.landed = LandedState.ON_GROUND
    h.ap.v_ned_m_s = (0.0, 0.0, 0.0)
    out = h.run_until(S.LANDED, timeout_s=2)
    assert h.last_transition().reason == R.TOUCHDOWN
    assert isinstance(out.setpoint, AttitudeSetpoint)
    assert out.setpoint.thrust_norm == 0.0
    assert CommandKind.DISARM in [c.kind for c in out.commands]
    out = h.run_until(S.DISARMED, timeout_s=1)
    assert h.last_transition().reason == R.DISARMED
    assert CommandKind.STOP_OFFBOARD in [c.kind for c in out.commands]
    assert all(o.setpoint is None for o in h.run(1.0))


def test_touchdown_detected_without_px4_land_detector() -> None:
    h = Harness(cfg=cfg_with(gps_loss_policy="land"))
    h.to_follow()
    h.lose_gps()
    h.run_until(S.CONTROLLED_LANDING, timeout_s=2)
    h.ap.v_ned_m_s = (0.0, 0.0, 0.6)
    h.run(3.0)
    h.ap.alt_rel_m = 0.1
    h.ap.v_ned_m_s = (0.0, 0.0, 0.02)  # stopped although we command a descent: on the ground
    h.run_until(S.LANDED, timeout_s=1.5)


def test_controlled_landing_with_gps_uses_velocity() -> None:
    ap = FakeAutopilot()
    ap.fly()
    h = Harness(ap=ap)
    h.run(6.0)
    # Reached with GPS only through a PX4 mode refusal.
    inp = MissionInputs(vehicle=h.ap.state(h.now_s))
    h.machine.transitions.apply(go(S.CONTROLLED_LANDING, R.STALL_TIMEOUT), inp)
    out = h.step()
    assert out.setpoint == VelocityNedSetpoint((0.0, 0.0, h.cfg.mission.landing_speed_m_s), 0.0)


# ---------------------------------------------------------------------- takeover, link, geofence, refusals
def test_pilot_takeover_goes_hands_off_without_commanding_any_mode() -> None:
    h = Harness()
    h.to_follow()
    h.ap.mode = FlightMode.POSCTL
    out = h.step()
    assert h.state == S.PX4_IN_CONTROL
    t = h.last_transition()
    assert t.reason == R.MODE_CHANGED_EXTERNALLY
    assert t.detail == "posctl"
    assert [c.kind for c in out.commands] == [CommandKind.RELEASE_OFFBOARD]
    assert out.setpoint is None
    outs = h.run(5.0)
    assert all(o.setpoint is None and not o.commands for o in outs)
    assert h.ap.mode == FlightMode.POSCTL


def test_px4_failsafe_descend_is_a_takeover_too() -> None:
    h = Harness()
    h.to_follow()
    h.ap.mode = FlightMode.LAND
    h.step()
    assert h.state == S.PX4_IN_CONTROL
    h.ap.landed = LandedState.ON_GROUND
    h.run_until(S.LANDED, timeout_s=2)
    h.run_until(S.DISARMED, timeout_s=3)


def test_link_lost_in_flight_stops_the_stream_and_hands_over() -> None:
    h = Harness()
    h.to_follow()
    h.ap.telemetry = False
    out = h.step()
    assert h.state == S.LINK_LOST
    assert h.last_transition().reason == R.LINK_LOST
    assert [c.kind for c in out.commands] == [CommandKind.STOP_OFFBOARD]
    assert out.setpoint is None
    h.run(2.0)
    h.ap.telemetry = True
    h.ap.mode = FlightMode.RETURN_TO_LAUNCH
    h.step()
    assert h.state == S.PX4_IN_CONTROL
    assert h.last_transition().reason == R.LINK_RESTORED


def test_link_lost_on_the_ground_waits_for_the_link() -> None:
    h = Harness()
    h.run(1.0)
    h.ap.connected = False
    h.step()
    assert h.state == S.WAIT_LINK
    assert h.last_transition().reason == R.LINK_LOST


def test_link_restored_on_the_ground() -> None:
    h = Harness(cfg=cfg_with(gps_loss_policy="land"))
    h.to_follow()
    h.ap.telemetry = False
    h.step()
    h.ap.telemetry = True
    h.ap.landed = LandedState.ON_GROUND
    h.step()
    assert h.state in (S.LANDED, S.DISARMED)
    assert h.last_transition().reason == R.LINK_RESTORED


def test_geofence_breach_returns_home() -> None:
    h = Harness()
    h.to_follow()
    h.ap.p_ned_m = (h.cfg.safety.geofence_radius_m + 1.0, 0.0, -5.0)
    out = h.step()
    assert h.state == S.PX4_RTL
    assert h.last_transition().reason == R.GEOFENCE_BREACH
    assert [c.kind for c in out.commands] == [CommandKind.STOP_OFFBOARD, CommandKind.RTL]


def test_offboard_refused_three_times_aborts() -> None:
    ap = FakeAutopilot(refuse={CommandKind.START_OFFBOARD: "COMMAND_DENIED"})
    h = Harness(cfg=cfg_with(leader_lost_action="hold"), ap=ap)
    h.start = True
    h.leader_mode = "fresh"
    h.run_until(S.PX4_HOLD, timeout_s=60)
    t = h.last_transition()
    assert t.reason == R.OFFBOARD_REJECTED
    assert t.detail == "COMMAND_DENIED"
    assert [c.kind for c in ap.sent].count(CommandKind.START_OFFBOARD) == 3


def test_offboard_refused_without_gps_falls_to_px4_land() -> None:
    ap = FakeAutopilot()
    h = Harness(cfg=cfg_with(gps_loss_policy="land"), ap=ap)
    h.to_follow()
    ap.mode = FlightMode.HOLD
    h.machine.offboard.confirmed = False  # as if offboard had never come up
    ap.refuse[CommandKind.START_OFFBOARD] = "TIMEOUT"
    h.lose_gps()
    h.run_until(S.PX4_LAND, timeout_s=10)
    assert h.last_transition().reason == R.OFFBOARD_REJECTED


def test_px4_hold_refused_lands() -> None:
    ap = FakeAutopilot(refuse={CommandKind.HOLD: "TEMPORARILY_REJECTED"})
    h = Harness(cfg=cfg_with(leader_lost_action="hold"), ap=ap)
    h.to_follow()
    h.leader_mode = None
    h.run_until(S.PX4_LAND, timeout_s=h.cfg.mission.stall_hover_s + 2)
    assert h.last_transition().reason == R.PX4_MODE_REFUSED


def test_gps_lost_in_px4_hold_takes_over_with_controlled_landing() -> None:
    h = Harness(cfg=cfg_with(leader_lost_action="hold"))
    h.to_follow()
    h.leader_mode = None
    h.run_until(S.PX4_HOLD, timeout_s=5)
    h.lose_gps()
    out = h.run_until(S.CONTROLLED_LANDING, timeout_s=2)
    assert h.last_transition().reason == R.GPS_LOST
    assert isinstance(out.setpoint, AttitudeSetpoint)
    assert CommandKind.START_OFFBOARD in [c.kind for c in out.commands]


def test_px4_land_ends_landed_then_disarmed() -> None:
    h = Harness()
    h.to_follow()
    h.leader_mode = None
    h.run_until(S.PX4_LAND, timeout_s=5)
    h.ap.landed = LandedState.ON_GROUND
    h.run_until(S.LANDED, timeout_s=2)
    h.run_until(S.DISARMED, timeout_s=3)


def test_restart_after_disarm_needs_a_new_start_request() -> None:
    ap = FakeAutopilot(refuse={CommandKind.ARM: "denied"})
    h = Harness(ap=ap)
    h.start = True
    h.run_until(S.DISARMED, timeout_s=30)
    h.run(2.0)
    assert h.state == S.DISARMED  # a held start request does not loop
    h.start = False
    h.step()
    h.start = True
    out = h.step()
    # One start goes on through preflight to arming in the same tick: no second start needed.
    assert [(t.to_state, t.reason) for t in out.transitions] == [
        (S.PREFLIGHT, R.START_REQUESTED),
        (S.ARMING, R.PREFLIGHT_OK),
    ]
    assert h.state == S.ARMING


def test_one_start_after_a_landing_arms_and_flies_again() -> None:
    h = Harness()
    h.to_follow()
    h.operator = OperatorCommand.LAND
    h.step()
    h.ap.landed = LandedState.ON_GROUND
    h.run_until(S.DISARMED, timeout_s=30)
    h.run(2.0)
    assert h.state == S.DISARMED
    _operator_start(h)
    out = h.step()
    assert [t.to_state for t in out.transitions] == [S.PREFLIGHT, S.ARMING]
    assert h.machine.next_step().startswith("arms (up to 3 tries), takes off to 5 m")
    h.run_until(S.FOLLOW, timeout_s=60)
    assert not h.machine.c.start.requested  # spent: a later landing waits for a new start


# ---------------------------------------------------------------------- shutdown
def test_shutdown_hold_then_land() -> None:
    h = Harness(cfg=cfg_with(shutdown_action="hold_then_land", shutdown_hold_s=3.0))
    h.to_follow()
    h.shutdown = True
    out = h.step()
    assert h.state == S.PX4_HOLD
    assert h.last_transition().reason == R.SHUTDOWN_REQUESTED
    assert [c.kind for c in out.commands] == [CommandKind.STOP_OFFBOARD, CommandKind.HOLD]
    assert not out.ready_to_exit
    h.run_until(S.PX4_LAND, timeout_s=3.5)
    assert h.last_transition().reason == R.HOLD_TIMEOUT
    assert h.step().ready_to_exit


def test_shutdown_land_and_hold() -> None:
    h = Harness(cfg=cfg_with(shutdown_action="land"))
    h.to_follow()
    h.shutdown = True
    h.step()
    assert h.state == S.PX4_LAND
    assert h.step().ready_to_exit
    h = Harness(cfg=cfg_with(shutdown_action="hold"))
    h.to_follow()
    h.shutdown = True
    h.step()
    assert h.state == S.PX4_HOLD
    assert h.step().ready_to_exit


def test_shutdown_without_gps_is_px4_land() -> None:
    h = Harness(cfg=cfg_with(shutdown_action="hold"))
    h.to_follow()
    h.lose_gps()
    h.run_until(S.FOLLOW_VISION, timeout_s=2)
    h.shutdown = True
    h.step()
    assert h.state == S.PX4_LAND
    assert h.last_transition().detail == "no GPS"


def test_shutdown_on_the_ground_exits_at_once() -> None:
    h = Harness()
    h.run(1.0)
    h.shutdown = True
    out = h.step()
    assert out.ready_to_exit
    assert h.last_transition().reason == R.SHUTDOWN_REQUESTED


def test_shutdown_while_arming_disarms_first() -> None:
    ap = FakeAutopilot(mute={CommandKind.ARM})
    h = Harness(ap=ap)
    h.start = True
    h.run_until(S.ARMING, timeout_s=10)
    ap.armed = True  # the ARM went through after all
    h.shutdown = True
    out = h.step()
    assert h.state == S.LANDED
    assert not out.ready_to_exit
    out = h.run_until(S.DISARMED, timeout_s=3)
    assert out.ready_to_exit


# ---------------------------------------------------------------------- operator
def test_operator_land_with_gps_is_px4_land() -> None:
    h = Harness()
    h.to_follow()
    h.operator = OperatorCommand.LAND
    out = h.step()
    assert h.state == S.PX4_LAND
    assert h.last_transition().reason == R.OPERATOR_LAND
    assert [c.kind for c in out.commands] == [CommandKind.STOP_OFFBOARD, CommandKind.LAND]


def test_operator_land_without_gps_is_our_controlled_landing() -> None:
    h = Harness()
    h.to_follow()
    h.lose_gps()
    h.run_until(S.FOLLOW_VISION, timeout_s=2)
    h.operator = OperatorCommand.LAND
    out = h.step()
    assert h.state == S.CONTROLLED_LANDING
    assert h.last_transition().reason == R.OPERATOR_LAND
    assert isinstance(out.setpoint, AttitudeSetpoint)


def test_operator_hold_needs_gps_and_flight() -> None:
    h = Harness()
    h.operator = OperatorCommand.HOLD
    h.step()
    assert h.state in (S.WAIT_LINK, S.PREFLIGHT)  # on the ground: ignored
    h.to_follow()
    h.operator = OperatorCommand.HOLD
    h.step()
    assert h.state == S.PX4_HOLD
    assert h.last_transition().reason == R.OPERATOR_HOLD


def _operator_start(h: Harness) -> None:
    """A fresh start pulse, as the runner delivers one (the machine reacts to its rising edge)."""
    h.start = h.takeover = False
    h.step()
    h.start = h.takeover = True


def test_a_start_after_an_operators_hold_follows_again() -> None:
    h = Harness()
    h.to_follow()
    h.operator = OperatorCommand.HOLD
    h.step()
    assert h.state == S.PX4_HOLD
    h.run(3.0)
    assert h.state == S.PX4_HOLD  # the start that began the flight is spent: nothing resumes by itself
    assert h.machine.operator_refusal(OperatorCommand.HOLD) == (
        "already holding (PX4 Hold); companion start follows again"
    )
    veh = h.ap.state(h.now_s)
    assert h.machine.start_refusal(veh) is None
    _operator_start(h)
    out = h.step()  # the leader is in view: acquired in the same step
    assert [(t.to_state, t.reason, t.detail) for t in out.transitions] == [
        (S.ACQUIRE, R.OPERATOR_START, "from px4_hold"),
        (S.FOLLOW, R.LEADER_ACQUIRED, ""),
    ]
    h.run(1.0)
    assert h.state == S.FOLLOW
    assert h.ap.mode == FlightMode.OFFBOARD
    assert CommandKind.ARM not in all_commands(h.outputs[-40:])


def test_preflight_problems_are_what_a_start_would_be_refused_for() -> None:
    h = Harness()
    veh = h.ap.state(h.now_s)
    assert h.machine.state == S.WAIT_LINK
    # A heartbeat is not yet a link the mission trusts: health must not call a start possible.
    assert h.machine.preflight_problems(veh) == ("no link to the autopilot (state wait_link)",)
    assert h.machine.start_refusal(veh) == "no link to the autopilot (state wait_link)"
    h.ap.gps_fix = 1
    h.ap.home_ok = False
    h.run(1.0)
    veh = h.ap.state(h.now_s)
    assert h.machine.preflight_problems(veh) == ("no GPS", "no home")
    assert h.machine.start_refusal(veh) == (
        "preflight: no GPS, no home; start again once it passes (companion health --wait 60 waits for it)"
    )
    h.ap.gps_fix = 3
    h.ap.home_ok = True
    h.run(h.cfg.mission.gps_restore_s - 0.5)
    veh = h.ap.state(h.now_s)
    assert h.machine.preflight_problems(veh) == ("no GPS",)  # the fix has not been good for long enough
    h.run(1.0)
    veh = h.ap.state(h.now_s)
    assert h.machine.preflight_problems(veh) == ()
    assert h.machine.start_refusal(veh) is None
    h.to_follow()
    assert h.machine.preflight_problems(h.ap.state(h.now_s)) is None  # not on the ground before a start


def test_a_start_says_why_it_would_do_nothing() -> None:
    h = Harness()
    h.to_follow()
    veh = h.ap.state(h.now_s)
    assert h.machine.start_refusal(veh) == "the mission is already under way (state follow)"
    _operator_start(h)  # a start while following is dropped, never kept for later
    h.run(1.0)
    assert h.state == S.FOLLOW
    assert not h.machine.c.start.requested
    assert not h.machine.c.start.takeover
    h.operator = OperatorCommand.LAND
    h.step()
    veh = h.ap.state(h.now_s)
    assert (
        h.machine.start_refusal(veh) == "PX4 is landing the vehicle: companion command hold first, then start"
    )
    h.operator = OperatorCommand.HOLD  # hold from PX4 Land, then start: following again
    h.step()
    assert h.state == S.PX4_HOLD
    h.lose_gps()  # PX4 cannot hold without a position: the companion lands it, and a start is refused
    h.run_until(S.CONTROLLED_LANDING, timeout_s=5)
    veh = h.ap.state(h.now_s)
    assert h.machine.start_refusal(veh) == "the companion is landing the vehicle (no GPS)"


def test_slot_change_is_validated_then_flown() -> None:
    h = Harness()
    assert h.machine.set_slot((0.0, 0.0, -5.0)) is not None  # behind the camera
    assert h.machine.set_slot((0.0, 0.0, 2.5)) is not None  # inside separation + 1 m
    assert h.machine.set_slot((5.0, 0.0, 5.0)) is not None  # leader out of the image
    assert h.machine.set_slot((0.0, 0.0, float("nan"))) is not None
    h.to_follow()
    assert h.machine.set_slot((0.0, 0.0, 7.0)) is None
    out = h.step()
    assert out.formation_error_ned_m is not None
    assert out.formation_error_ned_m[0] == pytest.approx(-2.0)  # leader at 5 m, slot now 7 m
    assert isinstance(out.setpoint, VelocityBodySetpoint)
    assert out.setpoint.v_body_m_s[0] < 0.0  # back off


# ---------------------------------------------------------------------- events
def test_transitions_are_emitted_once_with_statustext_and_payload() -> None:
    h = Harness()
    h.to_follow()
    h.lose_gps()
    h.run(3.0)
    gps = [t for t in h.transitions if t.reason == R.GPS_LOST]
    assert len(gps) == 1
    t = gps[0]
    assert t.statustext() == "WM follow_vision: GPS lost"
    assert len(t.statustext()) <= 50
    assert t.severity.value == "critical"
    assert t.as_dict()["reason"] == "GPS_LOST"


def test_every_reason_is_reachable() -> None:
    """Runs the scenarios above and checks that together they produce every Reason."""
    seen: set[Reason] = set()
    module = globals()
    for name, fn in sorted(module.items()):
        if not name.startswith("test_") or name == "test_every_reason_is_reachable" or not callable(fn):
            continue
        if hasattr(fn, "hypothesis"):
            continue
        marks = [m for m in getattr(fn, "pytestmark", []) if m.name == "parametrize"]
        if marks:
            for values in marks[0].args[1]:
                seen |= _reasons_of(fn, *values)
        else:
            seen |= _reasons_of(fn)
    assert set(Reason) - seen == set()


def _reasons_of(fn: object, *args: object) -> set[Reason]:
    from . import mission_harness

    collected: set[Reason] = set()
    original = mission_harness.Harness.step

    def spy(self: Harness) -> object:
        out = original(self)
        collected.update(t.reason for t in out.transitions)
        return out

    mission_harness.Harness.step = spy  # type: ignore[method-assign]
    try:
        fn(*args)  # type: ignore[operator]
    finally:
        mission_harness.Harness.step = original  # type: ignore[method-assign]
    return collected


def test_a_fresh_depth_guard_obstacle_holds_the_follower_back_and_a_stale_one_does_not() -> None:
    """The leader far ahead pulls the follower forward; an obstacle 2.3 m ahead stops that, unless stale."""
    cfg = Config()  # the machine uses whatever reading it is given; safety.depth_guard gates the pipeline
    h = Harness(cfg)
    h.to_follow()
    h.leader_p = (9.0, 0.0, 0.0)
    h.run(1.0)
    free = h.step().setpoint
    assert isinstance(free, VelocityBodySetpoint)
    assert free.v_body_m_s[0] > 1.0
    h.obstacle = (2.3, 0.0, 0.0)
    h.run(1.0)
    held = h.step().setpoint
    assert isinstance(held, VelocityBodySetpoint)
    lim = SafetyLimits.from_config(cfg.safety, cfg.formation.max_accel_m_s2)
    # The fake vehicle does not move: what is left is the barrier's speed for the 0.3 m beyond min separation.
    assert held.v_body_m_s[0] <= barrier_speed_m_s(2.3 - lim.min_separation_m, lim.brake_m_s2) + 1e-9
    assert held.v_body_m_s[0] < 0.7 * free.v_body_m_s[0]
    h.obstacle_age_s = 1.0  # older than OBSTACLE_STALE_S: dropped
    h.run(1.0)
    stale = h.step().setpoint
    assert isinstance(stale, VelocityBodySetpoint)
    assert stale.v_body_m_s[0] > 1.0


def test_latency_compensation_brings_the_estimate_to_the_tick_and_can_be_turned_off() -> None:
    """On: a 0.2 s old estimate of a leader 2 m/s faster moves 0.4 m ahead; off: flown as captured."""
    for on, expect_n_m in ((True, 5.4), (False, 5.0)):
        h = Harness(cfg=Config(formation=FormationConfig(latency_compensation=on)))
        h.to_follow()
        est = leader(h.now_s - 0.2, p=(5.0, 0.0, 0.0), v=(2.0, 0.0, 0.0))
        p_rel, v_rel = h.machine.follow.relative_now(est, h.ap.state(h.now_s))
        assert p_rel[0] == pytest.approx(expect_n_m, abs=1e-6)
        assert v_rel[0] == pytest.approx(2.0, abs=1e-6)


def test_the_estimate_is_brought_to_when_the_setpoint_acts_one_measured_link_delay_after_the_tick() -> None:
    """A 0.2 s old estimate of a leader 2 m/s faster, over a link measured at 30 ms one way: 0.46 m ahead.

    Unmeasured (NaN) adds nothing; a delay past the bound is taken at the bound, never further.
    """
    for delay_s, expect_n_m in ((0.03, 5.46), (math.nan, 5.4), (5.0, 5.6)):
        h = Harness()
        h.to_follow()
        veh = dataclasses.replace(h.ap.state(h.now_s), link_delay_s=delay_s)
        est = leader(h.now_s - 0.2, p=(5.0, 0.0, 0.0), v=(2.0, 0.0, 0.0))
        p_rel, v_rel = h.machine.follow.relative_now(est, veh)
        assert p_rel[0] == pytest.approx(expect_n_m, abs=1e-6)
        assert v_rel[0] == pytest.approx(2.0, abs=1e-6)


def test_another_track_winning_in_follow_drops_the_join_planned_for_the_first() -> None:
    """A false track 4 m beyond the slot and 3 m up is flown into FOLLOW and the join planned for it; the
    real leader's track then wins, right at the slot. The follower is not sent back from its slot by the
    old plan's reference (it was, at 4 m/s, before the law and the join started afresh on a new track)."""
    h = Harness()
    h.leader_p = (9.0, 0.0, -3.0)
    h.leader_track_age_s = 5.0
    h.start, h.leader_mode = True, "fresh"
    h.run_until(S.FOLLOW, timeout_s=60.0)
    outs = h.run(0.5)
    sps = [o.setpoint for o in outs if isinstance(o.setpoint, VelocityBodySetpoint)]
    assert sps
    assert sps[-1].v_body_m_s[0] > 0.3  # joining the far track
    h.leader_p, h.leader_track_age_s = (5.0, 0.0, 0.0), 0.1
    outs = h.run(1.0)
    assert all(o.state == S.FOLLOW for o in outs)
    sps = [o.setpoint for o in outs if isinstance(o.setpoint, VelocityBodySetpoint)]
    assert sps
    assert min(sp.v_body_m_s[0] for sp in sps) > -0.6, [round(sp.v_body_m_s[0], 2) for sp in sps]
