"""The far-field check: a track that never comes closer while the follower flies at it is dropped."""

from __future__ import annotations

import dataclasses

import numpy as np

from companion.config import LeaderConfig, PoseConfig, TrackerConfig
from companion.estimation.far_field import FarFieldCheck
from companion.estimation.leader import TrackStatus
from companion.estimation.pipeline import PerceptionPipeline
from companion.kernel.camera import MountConfig
from companion.perception.transform import CameraGeometry
from tests.unit.test_tracker import meas

DT = 1.0 / 15.0
#: A gap between clouds as a track sees it: behind-left of the start, well above, its size saying 13 m.
CLOUD_NED_M = np.array([-12.0, -2.8, -5.3])


def check() -> FarFieldCheck:
    return FarFieldCheck(flown_m=6.0, closure_fraction=0.25, min_range_m=6.0, cone_deg=5.0, ignore_s=120.0)


def test_a_cloud_that_keeps_its_place_while_the_follower_flies_at_it_is_dropped() -> None:
    far = check()
    u = CLOUD_NED_M / np.linalg.norm(CLOUD_NED_M)
    v_follower = 2.5 * u
    dropped_at = None
    for k in range(200):
        t = k * DT
        r = far.step(t, 1, False, CLOUD_NED_M, v_follower)
        if r is not None:
            dropped_at = t
            break
    assert dropped_at is not None
    # Dropped once 6 m are flown at 2.5 m/s (one step integrates nothing: it sets the bearing).
    assert 6.0 / 2.5 <= dropped_at <= 6.0 / 2.5 + 2 * DT
    assert r is not None
    assert 6.0 <= r.flown_m < 6.0 + 2.5 * DT
    assert "never came closer" in r.describe()
    # Its bearing is ignored (for boxes without depth), a bearing 10 deg off is not, and not for ever.
    assert far.ignores(dropped_at, 30.0 * u)
    R_10deg = np.array(
        [[np.cos(0.1745), -np.sin(0.1745), 0.0], [np.sin(0.1745), np.cos(0.1745), 0.0], [0, 0, 1]]
    )
    assert not far.ignores(dropped_at, R_10deg @ CLOUD_NED_M)
    assert not far.ignores(dropped_at + 121.0, CLOUD_NED_M)


def test_a_real_leader_out_of_stereo_range_comes_closer_and_is_kept() -> None:
    """The follower closes at 2.5 m/s on a leader 13 m off that flies away at 1.5 m/s."""
    far = check()
    u = CLOUD_NED_M / np.linalg.norm(CLOUD_NED_M)
    p = CLOUD_NED_M.copy()
    for k in range(200):
        t = k * DT
        assert far.step(t, 1, False, p, 2.5 * u) is None
        p = p - (2.5 - 1.5) * DT * u
    assert far.rejections == 0


def test_a_track_that_had_depth_or_stays_near_the_slot_is_never_checked() -> None:
    u = CLOUD_NED_M / np.linalg.norm(CLOUD_NED_M)
    far = check()
    far.step(0.0, 7, True, 5.0 * u, None)  # track 7 had a stereo range once
    assert all(far.step(k * DT, 7, False, CLOUD_NED_M, 3.0 * u) is None for k in range(1, 200))
    near = check()
    # A leader 5.5 m off (within the slot's range and margin), flying away as fast as the follower flies.
    assert all(near.step(k * DT, 1, False, 5.5 * u, 3.0 * u) is None for k in range(200))
    # The check does not run without the follower's velocity.
    blind = check()
    assert all(blind.step(k * DT, 1, False, CLOUD_NED_M, None) is None for k in range(200))


def test_the_pipeline_drops_the_track_ignores_the_cloud_and_still_takes_the_leader_with_depth() -> None:
    camera = CameraGeometry.from_mount(MountConfig())
    pipe = PerceptionPipeline(LeaderConfig(), PoseConfig(), TrackerConfig(), camera, slot_range_m=5.0)
    level = (1.0, 0.0, 0.0, 0.0)
    # Level and facing north: the camera sees the cloud up and ahead, and the follower flies at it.
    cloud_cam = np.array([0.0, -5.0, 12.0])
    v_ned = np.array([2.3, 0.0, -0.96])
    statuses = []
    dropped = None
    for k in range(120):
        t = k * DT
        pipe.attitude.push(t, level)
        pipe.velocity.push(t, v_ned)
        m = dataclasses.replace(meas(cloud_cam, t, sigma_z=1.5), range_source="size")
        state = pipe.track(t, [m])
        statuses.append(state.status)
        if pipe.far_field_rejection is not None:
            dropped = t
            # Told to the mission once as lost and far-field, then gone.
            lost = state.leader_estimate()
            assert state.status == TrackStatus.LOST
            assert lost is not None
            assert lost.far_field
        elif dropped is not None:
            assert state.estimate is None
    assert TrackStatus.CONFIRMED in statuses
    assert dropped is not None
    assert dropped < 4.0
    # After the drop the cloud, still in view, never starts a track again.
    after = statuses[round(dropped / DT) :]
    assert all(s == TrackStatus.LOST for s in after)
    # The leader with stereo depth in the same direction is taken.
    t = 120 * DT
    pipe.attitude.push(t, level)
    pipe.velocity.push(t, v_ned)
    state = pipe.track(t, [meas(np.array([0.0, -2.0, 5.0]), t)])
    assert state.status == TrackStatus.TENTATIVE
    assert state.estimate is not None


def test_the_check_is_off_at_zero_metres_flown_or_without_a_slot() -> None:
    camera = CameraGeometry.from_mount(MountConfig())
    off = TrackerConfig(far_field_flown_m=0.0)
    assert PerceptionPipeline(LeaderConfig(), PoseConfig(), off, camera, slot_range_m=5.0).far_field is None
    assert PerceptionPipeline(LeaderConfig(), PoseConfig(), TrackerConfig(), camera).far_field is None
