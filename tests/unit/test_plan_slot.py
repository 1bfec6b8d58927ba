"""A plan's slot turned with the leader, neighbours brought to now, and the law keeping clear of them."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.config import FormationConfig, SafetyConfig
from companion.mission.formation import FormationLaw
from companion.mission.geometry import FollowerState
from companion.mission.plan_slot import HEADING_STALE_S, SlotTurner, neighbours_now
from companion.mission.safety import SafetyLimits, barrier_speed_m_s
from companion.mission.types import SharedLeaderPosition, SharedNeighbour

SLOT = (-5.0, -6.0, 0.0)


def _share(t_s: float, yaw: float, rate: float | None = None) -> SharedLeaderPosition:
    return SharedLeaderPosition(
        t_s, (0.0, 0.0, -5.0), yaw_rad=yaw, v_ned_m_s=(2.0, 0.0, 0.0), yaw_rate_rad_s=rate
    )


def test_the_slot_turns_with_the_leader_heading() -> None:
    turner = SlotTurner(SLOT)
    north = turner.update(_share(0.0, 0.0), 0.0)
    assert north is not None
    np.testing.assert_allclose(north.p_ned_rel_m, [5.0, 6.0, 0.0])
    east = SlotTurner(SLOT).update(_share(0.0, math.pi / 2), 0.0)
    assert east is not None
    np.testing.assert_allclose(east.p_ned_rel_m, [-6.0, 5.0, 0.0], atol=1e-9)


def test_a_turning_leader_moves_the_slot_round_it_at_rate_times_radius() -> None:
    turner = SlotTurner(SLOT)
    target = turner.update(_share(0.0, 0.0, rate=0.1), 0.0)
    assert target is not None
    radius = math.hypot(SLOT[0], SLOT[1])
    assert float(np.linalg.norm(target.v_ned_rel_m_s)) == pytest.approx(0.1 * radius)
    # The slot's motion is across the line to the leader, not along it.
    assert float(np.dot(target.v_ned_rel_m_s, target.p_ned_rel_m)) == pytest.approx(0.0, abs=1e-9)


def test_the_turn_rate_comes_from_successive_headings_without_a_shared_rate() -> None:
    turner = SlotTurner(SLOT)
    for k in range(40):
        turner.update(_share(k * 0.1, 0.1 * k * 0.1), k * 0.1)
    assert turner.turn_rate_rad_s == pytest.approx(0.1, rel=0.05)


def test_no_heading_or_a_stale_one_means_no_slot() -> None:
    turner = SlotTurner(SLOT)
    assert turner.update(None, 0.0) is None
    assert turner.update(SharedLeaderPosition(0.0, (0.0, 0.0, 0.0)), 0.0) is None
    assert turner.update(_share(0.0, 0.0), 0.0) is not None
    assert turner.update(None, HEADING_STALE_S + 0.5) is None


def test_neighbours_relative_to_us_with_and_without_our_gps() -> None:
    n = SharedNeighbour("follower1", 10.0, (4.0, 1.0, -5.0), (1.0, 0.0, 0.0))
    with_gps = neighbours_now([n], 10.5, p_own_ned_m=np.array([0.0, 0.0, -5.0]), v_own_ned_m_s=np.zeros(3))
    np.testing.assert_allclose(with_gps[0].p_ned_rel_m, [4.5, 1.0, 0.0])
    # Without GPS: the leader's share minus the seen relative vector places us.
    leader = SharedLeaderPosition(10.5, (8.0, 0.0, -5.0), v_ned_m_s=(0.0, 0.0, 0.0))
    blind = neighbours_now(
        [n],
        10.5,
        p_own_ned_m=None,
        v_own_ned_m_s=None,
        leader_shared=leader,
        p_ned_rel_leader_m=np.array([8.0, 0.0, 0.0]),
    )
    np.testing.assert_allclose(blind[0].p_ned_rel_m, [4.5, 1.0, 0.0])
    assert neighbours_now([n], 10.5, p_own_ned_m=None, v_own_ned_m_s=None) == []
    assert neighbours_now([n], 20.0, p_own_ned_m=np.zeros(3), v_own_ned_m_s=None) == []


def test_the_law_never_closes_on_a_neighbour_inside_the_separation() -> None:
    cfg = FormationConfig()
    limits = SafetyLimits.from_config(SafetyConfig(), cfg.max_accel_m_s2)
    follower = FollowerState(
        yaw_rad=0.0, v_ned_m_s=np.zeros(3), v_down_m_s=0.0, alt_rel_m=5.0, p_ned_m=np.zeros(3)
    )
    # The leader 5 m ahead but 3 m too far: the law wants to fly north; a neighbour north is in the way.
    p_rel, v_rel = np.array([8.0, 0.0, 0.0]), np.zeros(3)
    free = FormationLaw(cfg, limits).velocity(p_rel, v_rel, follower, 0.0).v_ned_m_s
    assert free[0] > 2.0

    def north_with_neighbour_at(d_m: float) -> float:
        law = FormationLaw(cfg, limits)
        law.neighbours = neighbours_now(
            [SharedNeighbour("follower1", 0.0, (d_m, 0.0, 0.0))],
            0.0,
            p_own_ned_m=np.zeros(3),
            v_own_ned_m_s=np.zeros(3),
        )
        return float(law.velocity(p_rel, v_rel, follower, 0.0).v_ned_m_s[0])

    sep = limits.min_separation_m
    for inside_m in (0.5 * sep, 0.95 * sep, sep):
        assert north_with_neighbour_at(inside_m) <= 0.0, inside_m  # holds or backs off, never closes
    for outside_m in (sep + 0.2, sep + 1.0, sep + 2.0):
        # Closing no faster than it can brake to a stop at the separation.
        assert (
            north_with_neighbour_at(outside_m) <= barrier_speed_m_s(outside_m - sep, limits.brake_m_s2) + 1e-9
        )


def test_a_shared_leader_velocity_replaces_the_estimated_one_in_the_feed_forward() -> None:
    cfg = FormationConfig(kp_xy=0.0, ki_xy=0.0, kd_xy=0.0, kp_z=0.0, ki_z=0.0, leader_accel_ff_s=0.0)
    law = FormationLaw(cfg, SafetyLimits.from_config(SafetyConfig(), cfg.max_accel_m_s2))
    follower = FollowerState(
        yaw_rad=0.0, v_ned_m_s=np.zeros(3), v_down_m_s=0.0, alt_rel_m=5.0, p_ned_m=np.zeros(3)
    )
    p_rel = np.array([5.0, 0.0, 0.0])
    # The camera's relative velocity says 1.4 m/s; the leader's own (GPS) says 1.0 m/s.
    seen = law.velocity(p_rel, np.array([1.4, 0.0, 0.0]), follower, 0.0).v_ned_m_s
    law.reset()
    shared = law.velocity(
        p_rel, np.array([1.4, 0.0, 0.0]), follower, 0.0, v_leader_ned_m_s=np.array([1.0, 0.0, 0.0])
    )
    assert seen[0] == pytest.approx(1.4, abs=1e-6)
    assert shared.v_ned_m_s[0] == pytest.approx(1.0, abs=1e-6)
