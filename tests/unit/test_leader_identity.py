"""Telling the leader from look-alike neighbours: expectations, the measurement filter, swap detection."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.config import LeaderConfig, PoseConfig, TrackerConfig
from companion.estimation.identity import (
    PLAN_SIGMA_M,
    SWAP_FRAMES,
    Expectation,
    LeaderIdentity,
    expectations,
)
from companion.estimation.leader import TrackStatus
from companion.estimation.pipeline import PerceptionPipeline
from companion.kernel.camera import MountConfig
from companion.perception.transform import CameraGeometry
from tests.unit.test_tracker import meas

SLOT_ME = (-5.0, -6.0, 0.0)
SLOT_INNER = (-3.5, -2.5, 0.0)


def test_with_gps_the_shares_place_leader_and_neighbours_relative_to_us() -> None:
    leader, others = expectations(
        own_p_ned_m=np.array([1.0, 2.0, -5.0]),
        leader_p_ned_m=np.array([9.0, 2.0, -5.0]),
        leader_age_s=0.2,
        leader_yaw_rad=0.0,
        neighbour_p_ned_m=[np.array([3.0, 6.0, -5.0])],
        slot_leader_m=SLOT_ME,
        neighbour_slots_m=[SLOT_INNER],
    )
    assert leader is not None
    np.testing.assert_allclose(leader.p_ned_rel_m, [8.0, 0.0, 0.0])
    np.testing.assert_allclose(others[0].p_ned_rel_m, [2.0, 4.0, 0.0])
    assert leader.sigma_m < PLAN_SIGMA_M


def test_without_gps_the_plan_turned_by_the_leader_heading() -> None:
    leader, others = expectations(
        own_p_ned_m=None,
        leader_p_ned_m=np.array([9.0, 2.0, -5.0]),
        leader_age_s=0.0,
        leader_yaw_rad=math.pi / 2,  # the leader flies east: "right" is south
        slot_leader_m=SLOT_ME,
        neighbour_slots_m=[SLOT_INNER],
    )
    assert leader is not None
    # We sit 5 m behind (west) and 6 m left (north) of the leader: it is 5 m east, 6 m south of us.
    np.testing.assert_allclose(leader.p_ned_rel_m, [-6.0, 5.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(others[0].p_ned_rel_m, [-3.5, 1.5, 0.0], atol=1e-9)
    assert leader.sigma_m == PLAN_SIGMA_M


def test_nothing_known_means_no_expectation() -> None:
    assert expectations(own_p_ned_m=None, leader_p_ned_m=None, leader_age_s=0.0, leader_yaw_rad=None) == (
        None,
        [],
    )


def _identity() -> LeaderIdentity:
    ident = LeaderIdentity()
    ident.set(Expectation(np.array([6.0, 5.0, 0.0]), 1.0), [Expectation(np.array([2.5, 2.5, 0.0]), 1.0)])
    return ident


def test_measurements_at_a_neighbour_or_far_away_are_not_the_leader() -> None:
    ident = _identity()
    assert ident.keep(np.array([6.2, 4.9, 0.1]), 0.2)
    assert not ident.keep(np.array([2.6, 2.4, 0.0]), 0.2)
    assert not ident.keep(np.array([20.0, -10.0, 0.0]), 0.2)
    assert ident.counters.neighbour_rejected == 1
    assert ident.counters.far_rejected == 1


def test_a_track_on_a_neighbour_is_a_swap_after_a_few_frames_and_counted_once() -> None:
    ident = _identity()
    for k in range(SWAP_FRAMES - 1):
        assert not ident.check_track(float(k), np.array([2.5, 2.5, 0.0]), 0.2)
    assert ident.check_track(10.0, np.array([2.5, 2.5, 0.0]), 0.2)
    assert ident.counters.swaps == 1
    for k in range(10):
        assert not ident.check_track(20.0 + k, np.array([6.0, 5.0, 0.0]), 0.2)
    assert ident.counters.swaps == 1


def test_the_pipeline_tracks_the_leader_not_the_nearer_neighbour() -> None:
    """Both in view every frame; the neighbour is nearer and scores higher; the track stays on the leader."""
    camera = CameraGeometry.from_mount(MountConfig(x_m=0.0, pitch_deg=0.0))
    pipe = PerceptionPipeline(LeaderConfig(), PoseConfig(), TrackerConfig(), camera)
    # Level, facing north: camera x right = east, z forward = north, y down.
    leader_cam, neighbour_cam = np.array([1.0, 0.0, 7.0]), np.array([-0.5, 0.0, 3.5])
    ident = LeaderIdentity()
    ident.set(Expectation(np.array([7.0, 1.0, 0.0]), 1.0), [Expectation(np.array([3.5, -0.5, 0.0]), 1.0)])
    pipe.identity = ident
    state = None
    for k in range(30):
        t = k / 15.0
        state = pipe.track(t, [meas(neighbour_cam, t, score=0.95), meas(leader_cam, t, score=0.6)])
    assert state is not None
    assert state.status == TrackStatus.CONFIRMED
    assert state.estimate is not None
    np.testing.assert_allclose(state.estimate.p_ned_rel_m, [7.0, 1.0, 0.0], atol=0.2)
    assert ident.counters.neighbour_rejected == 30
    assert ident.counters.swaps == 0


def test_without_identity_the_same_scene_can_lock_onto_the_neighbour() -> None:
    """The check above is not vacuous: the plain tracker takes the better-scoring nearer object."""
    camera = CameraGeometry.from_mount(MountConfig(x_m=0.0, pitch_deg=0.0))
    pipe = PerceptionPipeline(LeaderConfig(), PoseConfig(), TrackerConfig(), camera)
    state = None
    for k in range(30):
        t = k / 15.0
        state = pipe.track(
            t,
            [meas(np.array([-0.5, 0.0, 3.5]), t, score=0.95), meas(np.array([1.0, 0.0, 7.0]), t, score=0.6)],
        )
    assert state is not None
    assert state.estimate is not None
    assert float(np.linalg.norm(state.estimate.p_ned_rel_m - np.array([3.5, -0.5, 0.0]))) == pytest.approx(
        0.0, abs=0.3
    )
