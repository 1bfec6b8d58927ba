"""The leader's own motion from its shares: the acceleration between them, brought to now, none when stale."""

from __future__ import annotations

import numpy as np
import pytest

from companion.kernel.flight import VehicleState
from companion.mission.shared_motion import (
    DEAD_RECKON_MAX_S,
    OWN_CARRY_MAX_S,
    LeaderMotion,
    SharedLeaderMotion,
    SharedRelativeFix,
    shared_rel_now,
)
from companion.mission.types import SharedLeaderPosition


def _share(t_s: float, v_n: float) -> SharedLeaderPosition:
    return SharedLeaderPosition(t_s, (0.0, 0.0, -5.0), v_ned_m_s=(v_n, 0.0, 0.0))


def test_a_leader_speeding_up_is_read_within_a_few_shares_and_carried_to_now() -> None:
    """10 Hz shares of a leader speeding up at 1 m/s^2: the acceleration is 0.85 m/s^2 or more after four
    shares, and the velocity is brought forward over the share's age (0.1 s late here)."""
    m = SharedLeaderMotion(tau_s=0.1, max_age_s=0.4, max_accel_m_s2=3.0)
    out = None
    for k in range(4):
        t_s = 10.0 + 0.1 * k
        out = m.update(_share(t_s, 1.0 * (t_s - 10.0)), t_s + 0.1)
    assert out is not None
    assert out.a_ned_m_s2[0] > 0.85
    assert out.v_ned_m_s[0] == pytest.approx(0.3 + out.a_ned_m_s2[0] * 0.1)


def test_the_same_share_seen_again_does_not_change_the_acceleration() -> None:
    """Control ticks come faster than shares: a share already seen only ages, its acceleration unchanged."""
    m = SharedLeaderMotion(tau_s=0.1, max_age_s=0.4, max_accel_m_s2=3.0)
    m.update(_share(10.0, 0.0), 10.0)
    first = m.update(_share(10.1, 0.1), 10.1)
    again = m.update(_share(10.1, 0.1), 10.15)
    assert first is not None
    assert again is not None
    assert again.a_ned_m_s2 == pytest.approx(first.a_ned_m_s2)
    assert again.v_ned_m_s[0] == pytest.approx(0.1 + first.a_ned_m_s2[0] * 0.05)


def test_a_stale_share_or_one_without_velocity_gives_nothing() -> None:
    m = SharedLeaderMotion(tau_s=0.1, max_age_s=0.4, max_accel_m_s2=3.0)
    assert m.update(_share(10.0, 1.0), 10.5) is None
    assert m.update(SharedLeaderPosition(10.6, (0.0, 0.0, -5.0)), 10.6) is None
    assert m.update(None, 10.7) is None


def test_a_gap_between_shares_or_a_jump_gives_no_spike() -> None:
    """Shares 2 s apart start the acceleration afresh; a velocity jump is bounded by the law's cap."""
    m = SharedLeaderMotion(tau_s=0.1, max_age_s=0.4, max_accel_m_s2=3.0)
    m.update(_share(10.0, 0.0), 10.0)
    out = m.update(_share(12.0, 2.0), 12.0)
    assert out is not None
    assert np.allclose(out.a_ned_m_s2, 0.0)
    out = m.update(_share(12.1, 12.0), 12.1)
    assert out is not None
    assert float(np.linalg.norm(out.a_ned_m_s2)) <= 3.0


def test_through_a_short_gap_the_cameras_last_position_is_carried_on_at_the_shared_relative_velocity() -> (
    None
):
    """GPS puts the shares 0.8 m off and drifts them by 0.15 m while the camera misses the leader for a
    second: the camera's last relative position carried at the shares' relative velocity stays on the
    leader; the shares plus their averaged offset would be off by the drift."""
    fix = SharedRelativeFix(tau_s=2.0, max_age_s=10.0)
    gps_error = np.array([0.8, -0.3, 0.2])
    assert fix.fix(np.zeros(3), np.zeros(3), 0.0) is None
    for k in range(200):  # 10 s at 20 Hz, the leader 5 m ahead
        fix.observe(np.array([5.0, 0.0, 0.0]), np.array([5.0, 0.0, 0.0]) - gps_error, 0.05 * k)
    v_rel = np.array([-0.5, 0.2, 0.0])  # the follower closes, the leader drifts right
    rel_true = np.array([5.0, 0.0, 0.0])
    drift = np.zeros(3)
    out = None
    for k in range(1, 21):
        rel_true = rel_true + v_rel * 0.05
        drift = drift + np.array([0.15, 0.0, 0.0]) / 20
        out = fix.fix(rel_true - gps_error + drift, v_rel, 9.95 + 0.05 * k)
    assert out is not None
    assert out == pytest.approx(rel_true, abs=1e-9)


def test_past_the_dead_reckoning_the_shares_stand_in_with_their_offset_from_the_camera() -> None:
    """The offset is learnt through the camera's noise; after ``DEAD_RECKON_MAX_S`` of misses the shares
    plus it are where the leader is; an offset not renewed for longer than its age limit is not used."""
    rng = np.random.default_rng(3)
    fix = SharedRelativeFix(tau_s=2.0, max_age_s=10.0)
    gps_error = np.array([0.8, -0.3, 0.2])
    for k in range(200):
        rel_true = np.array([5.0, 0.1 * np.sin(0.3 * k), 0.0])
        fix.observe(rel_true + rng.normal(0.0, 0.03, 3), rel_true - gps_error, 0.05 * k)
    rel_true = np.array([4.0, 1.5, -0.2])  # the leader moved while the camera missed it
    out = fix.fix(rel_true - gps_error, np.zeros(3), 9.95 + DEAD_RECKON_MAX_S + 0.1)
    assert out is not None
    assert np.linalg.norm(out - rel_true) < 0.03
    assert fix.fix(rel_true - gps_error, np.zeros(3), 9.95 + 10.1) is None


def test_a_camera_seen_again_after_long_renews_the_offset_at_once() -> None:
    """The receivers' errors move on: after the age limit the first sighting sets the offset afresh."""
    fix = SharedRelativeFix(tau_s=2.0, max_age_s=10.0)
    fix.observe(np.array([5.0, 0.0, 0.0]), np.array([4.0, 0.0, 0.0]), 0.0)
    fix.observe(np.array([5.0, 0.0, 0.0]), np.array([5.5, 0.0, 0.0]), 20.0)
    out = fix.fix(np.array([5.5, 0.0, 0.0]), np.zeros(3), 20.0 + DEAD_RECKON_MAX_S + 0.1)
    assert out is not None
    assert out == pytest.approx([5.0, 0.0, 0.0])


def test_both_ends_are_carried_to_now_the_followers_own_report_only_so_far() -> None:
    """Leader and follower both fly north at 2 m/s, 5 m apart: the leader's share 0.1 s old and the
    follower's own position report 0.05 s old still give 5 m; a report older than the carry limit is
    carried only that far (a link in trouble is not a delay to plan on)."""
    v = np.array([2.0, 0.0, 0.0])
    now_s = 20.0
    share = SharedLeaderPosition(
        now_s - 0.1, (5.0 + 2.0 * (now_s - 0.1), 0.0, -5.0), v_ned_m_s=(2.0, 0.0, 0.0)
    )
    motion = LeaderMotion(v, np.zeros(3))

    def own(age_s: float) -> VehicleState:
        return VehicleState(
            p_ned_m=(2.0 * (now_s - age_s), 0.0, -5.0),
            v_ned_m_s=(2.0, 0.0, 0.0),
            local_position_stamp_s=now_s - age_s,
        )

    assert shared_rel_now(share, motion, own(0.05), now_s) == pytest.approx([5.0, 0.0, 0.0])
    late = shared_rel_now(share, motion, own(1.0), now_s)
    assert late[0] == pytest.approx(5.0 + 2.0 * (1.0 - OWN_CARRY_MAX_S))
