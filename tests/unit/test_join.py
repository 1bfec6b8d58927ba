"""The join into the slot: the trapezoid, the planner, the law flying it, and the machine planning it."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.config import Config, FormationConfig, SafetyConfig
from companion.kernel.flight import VelocityBodySetpoint
from companion.mission.formation import FormationLaw
from companion.mission.geometry import FollowerState, Slot, slot_error
from companion.mission.join import JoinPlanner, JoinReference, joined, trapezoid, trapezoid_duration_s
from companion.mission.safety import SafetyLimits
from companion.mission.types import MissionState

from .mission_harness import Harness
from .pointmass import PointMass

SLOT = Slot.from_offset_cam((0.0, 0.0, 5.0))
LIM = SafetyLimits.from_config(SafetyConfig(), FormationConfig().max_accel_m_s2)


@settings(max_examples=200, deadline=None)
@given(
    distance=st.floats(0.01, 50.0),
    speed=st.floats(0.2, 5.0),
    accel=st.floats(0.2, 5.0),
    frac=st.floats(0.0, 1.2),
)
def test_the_trapezoid_stays_in_its_limits_and_stops_at_the_distance(
    distance: float, speed: float, accel: float, frac: float
) -> None:
    total = trapezoid_duration_s(distance, speed, accel)
    covered, v, a = trapezoid(distance, speed, accel, frac * total)
    assert -1e-9 <= covered <= distance + 1e-9
    assert 0.0 <= v <= speed + 1e-9
    assert abs(a) <= accel + 1e-9
    end = trapezoid(distance, speed, accel, total * (1.0 + 1e-9) + 1e-9)
    assert end == pytest.approx((distance, 0.0, 0.0), abs=1e-9)


def test_the_trapezoid_is_continuous_and_its_speed_is_its_slope() -> None:
    distance, speed, accel = 4.0, 1.5, 1.0
    total = trapezoid_duration_s(distance, speed, accel)
    ts = np.linspace(0.0, total, 2001)
    s = np.array([trapezoid(distance, speed, accel, t)[0] for t in ts])
    v = np.array([trapezoid(distance, speed, accel, t)[1] for t in ts])
    assert np.max(np.abs(np.diff(s))) < speed * (ts[1] - ts[0]) + 1e-9
    assert np.gradient(s, ts)[1:-1] == pytest.approx(v[1:-1], abs=2e-3)
    # 1.5 s up, 1.17 s at 1.5 m/s, 1.5 s down.
    assert total == pytest.approx(1.5 + 4.0 / 1.5)


def test_a_short_join_is_a_triangle_under_the_speed_limit() -> None:
    _, v_peak, _ = trapezoid(1.0, 5.0, 1.0, 1.0)
    assert v_peak == pytest.approx(1.0)  # sqrt(d * a): never reaches 5 m/s
    assert trapezoid_duration_s(1.0, 5.0, 1.0) == pytest.approx(2.0)


def test_no_join_under_the_minimum_error_or_when_turned_off() -> None:
    near = JoinPlanner(1.5, 1.0, min_error_m=0.5)
    near.arm()
    assert near.reference(SLOT, np.array([5.3, 0.0, 0.0]), 0.0, 0.0) is None
    off = JoinPlanner(0.0, 1.0, min_error_m=0.5)
    off.arm()
    assert off.reference(SLOT, np.array([9.0, 0.0, 0.0]), 0.0, 0.0) is None
    assert near.planned == off.planned == 0


def on_reference(ref: JoinReference | None) -> np.ndarray:
    """The relative position of a follower exactly where the reference wants it (slot 5 m ahead, yaw 0)."""
    if ref is None:
        return np.array([5.0, 0.0, 0.0])
    return np.array([5.0 + ref.range_offset_m, 0.0, ref.down_offset_m])


def test_the_join_starts_at_the_error_and_ends_in_the_slot() -> None:
    planner = JoinPlanner(1.5, 1.0, min_error_m=0.5)
    planner.arm()
    p = np.array([9.0, 0.0, -3.0])  # 4 m beyond the slot's range, 3 m above the follower
    start = planner.reference(SLOT, p, 0.0, 10.0)
    assert start is not None
    assert (start.range_offset_m, start.down_offset_m) == pytest.approx((4.0, -3.0))
    assert (start.range_rate_m_s, start.down_rate_m_s) == pytest.approx((0.0, 0.0))
    total = trapezoid_duration_s(5.0, 1.5, 1.0)
    ref, t = start, 10.0
    while t < 10.0 + total / 2 - 1e-9:  # a follower that keeps to the plan: its clock runs at full rate
        t += 0.05
        ref = planner.reference(SLOT, on_reference(ref), 0.0, t)
    assert ref is not None
    # Halfway, along the same line: range and height close together, at the full speed.
    assert (ref.range_offset_m, ref.down_offset_m) == pytest.approx((2.0, -1.5), abs=0.07)  # a tick
    assert np.hypot(ref.range_rate_m_s, ref.down_rate_m_s) == pytest.approx(1.5)
    assert ref.range_rate_m_s < 0.0 < ref.down_rate_m_s
    while ref is not None:
        t += 0.05
        ref = planner.reference(SLOT, on_reference(ref), 0.0, t)
    assert t - 10.0 == pytest.approx(total, abs=0.051)
    assert not planner.active
    assert planner.planned == 1


def test_the_plan_waits_for_a_follower_that_trails_it() -> None:
    planner = JoinPlanner(1.5, 1.0, min_error_m=0.5)
    planner.arm()
    stuck = np.array([9.0, 0.0, 0.0])
    refs = [planner.reference(SLOT, stuck, 0.0, 0.05 * k) for k in range(200)]
    last = refs[-1]
    assert last is not None  # 10 s on: a 4 m join at 1.5 m/s is long over, but the follower never moved
    # The reference stopped 0.2-0.5 m ahead of the follower along the plan, and stands still there.
    assert 4.0 - 0.5 <= last.range_offset_m <= 4.0 - 0.2
    assert last.range_rate_m_s == pytest.approx(0.0)
    moving = planner.reference(SLOT, on_reference(last), 0.0, 10.05)
    assert moving is not None
    assert moving.range_rate_m_s < 0.0  # caught up: the plan goes on


def test_a_cancelled_join_gives_no_reference() -> None:
    planner = JoinPlanner(1.5, 1.0, min_error_m=0.5)
    planner.arm()
    assert planner.reference(SLOT, np.array([9.0, 0.0, 0.0]), 0.0, 0.0) is not None
    planner.cancel()
    assert planner.reference(SLOT, np.array([9.0, 0.0, 0.0]), 0.0, 0.1) is None


def test_the_joined_error_is_the_error_to_the_reference_and_its_motion_is_fed_forward() -> None:
    err = slot_error(SLOT, np.array([9.0, 0.0, -1.0]), np.zeros(3), 0.0)
    ref = JoinReference(range_offset_m=3.0, range_rate_m_s=-1.2, down_offset_m=-0.5, down_rate_m_s=0.2)
    shifted, ff = joined(err, ref)
    assert shifted.e_range_m == pytest.approx(1.0)
    assert shifted.e_range_rate_m_s == pytest.approx(1.2)
    assert shifted.e_down_m == pytest.approx(-0.5)
    # Closing the range at 1.2 m/s: toward the leader (north); the height rises 0.2 m/s less.
    assert ff == pytest.approx((1.2, 0.0, -0.2))
    braking = JoinReference(1.0, -1.0, 0.0, 0.0, range_accel_m_s2=1.0)
    _, ff_lead = joined(err, braking, accel_lead_s=0.5)
    assert ff_lead[0] == pytest.approx(0.5)  # the reference is braking: lead it


def test_the_law_starts_a_join_gently_where_the_step_commands_the_full_gain() -> None:
    p_rel = np.array([9.0, 0.0, 0.0])
    follower = FollowerState(yaw_rad=0.0, v_ned_m_s=np.zeros(3), v_down_m_s=0.0, alt_rel_m=5.0)
    step = FormationLaw(FormationConfig(), LIM).velocity(p_rel, np.zeros(3), follower, 0.0)
    ref = JoinReference(range_offset_m=4.0, range_rate_m_s=0.0, down_offset_m=0.0, down_rate_m_s=0.0)
    join = FormationLaw(FormationConfig(), LIM).velocity(p_rel, np.zeros(3), follower, 0.0, join=ref)
    assert step.v_ned_m_s[0] > 3.0
    assert join.v_ned_m_s[0] == pytest.approx(0.0, abs=1e-9)


def fly_in(join_speed_m_s: float) -> tuple[float, float]:
    """Point-mass follower 4 m short of the slot behind a hovering leader: (peak speed, closest range)."""
    law = FormationLaw(FormationConfig(join_speed_m_s=join_speed_m_s), LIM)
    planner = JoinPlanner(join_speed_m_s, 1.0, 0.5)
    planner.arm()
    follower, leader = PointMass(p=np.array([0.0, 0.0, -5.0])), np.array([9.0, 0.0, -5.0])
    peak, closest = 0.0, np.inf
    dt = 0.05
    for k in range(400):
        t = k * dt
        p_rel, v_rel = leader - follower.p, -follower.v
        ref = planner.reference(law.slot, p_rel, follower.yaw_rad, t)
        cmd = law.velocity(p_rel, v_rel, follower.follower(), t, join=ref)
        follower.step_velocity(cmd.setpoint, dt)
        peak = max(peak, float(np.linalg.norm(follower.v)))
        closest = min(closest, float(np.linalg.norm(leader - follower.p)))
    assert float(np.linalg.norm(leader - follower.p)) == pytest.approx(5.0, abs=0.1)
    return peak, closest


def test_a_joining_follower_is_slower_and_overshoots_less_than_the_step() -> None:
    peak_step, closest_step = fly_in(0.0)
    peak_join, closest_join = fly_in(1.5)
    assert peak_join < 1.6 < peak_step
    assert 5.0 - closest_join < 5.0 - closest_step


def forward_commands(cfg: Config, seconds: float) -> tuple[list[float], int]:
    """The forward velocity commanded over the first ``seconds`` of FOLLOW with the leader 4 m beyond the
    slot (the fake autopilot does not move), and how many joins the machine planned."""
    h = Harness(cfg)
    h.leader_mode = "fresh"
    h.leader_p = (9.0, 0.0, 0.0)
    h.start = True
    h.run_until(MissionState.FOLLOW, timeout_s=60.0)
    out = [o.setpoint for o in h.run(seconds)]
    assert all(isinstance(sp, VelocityBodySetpoint) for sp in out)
    return [
        sp.v_body_m_s[0] for sp in out if isinstance(sp, VelocityBodySetpoint)
    ], h.machine.follow.join.planned


def test_the_machine_plans_a_join_when_it_enters_the_formation_off_the_slot() -> None:
    joining, planned = forward_commands(Config(), 0.5)
    stepping, planned_off = forward_commands(
        Config.model_validate({"formation": {"join_speed_m_s": 0.0}}), 0.5
    )
    assert (planned, planned_off) == (1, 0)
    assert max(joining) < 0.6 * max(stepping)


def test_entering_the_formation_in_the_slot_plans_nothing() -> None:
    h = Harness(Config())
    h.leader_mode = "fresh"
    h.to_follow()
    h.run(1.0)
    assert h.state == MissionState.FOLLOW
    assert h.machine.follow.join.planned == 0
