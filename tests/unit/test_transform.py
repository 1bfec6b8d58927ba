from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from companion.kernel.camera import MountConfig
from companion.kernel.frames import R_from_euler, R_from_quat, quat_from_euler
from companion.perception.transform import AttitudeHistory, CameraGeometry, rotate_cov, slerp

angles = st.floats(-math.pi + 1e-3, math.pi - 1e-3)
small = st.floats(-0.5, 0.5)
coords = st.floats(-20.0, 20.0)


def test_level_camera_looks_along_body_x() -> None:
    cam = CameraGeometry.from_mount(MountConfig(x_m=0.1, pitch_deg=0.0))
    # 5 m straight ahead of the camera is 5.1 m ahead of the body centre.
    assert np.allclose(cam.cam_to_body(np.array([0.0, 0.0, 5.0])), [5.1, 0.0, 0.0])
    # Camera x right -> body y right; camera y down -> body z down.
    assert np.allclose(cam.cam_to_body(np.array([1.0, 2.0, 0.0])), [0.1, 1.0, 2.0])


def test_up_tilted_camera_sees_forward_points_below_its_axis() -> None:
    cam = CameraGeometry.from_mount(MountConfig(x_m=0.0, pitch_deg=10.0))
    p_cam = cam.body_to_cam(np.array([5.0, 0.0, 0.0]))  # level with the body, ahead
    assert p_cam[1] > 0  # below the optical axis (y down) since the camera looks up


@given(st.tuples(angles, small, small), st.tuples(coords, coords, st.floats(0.5, 30.0)))
def test_cam_ned_round_trip(att: tuple[float, float, float], xyz: tuple[float, float, float]) -> None:
    cam = CameraGeometry.from_mount(MountConfig())
    R = R_from_euler(att[2], att[1], att[0])
    p = np.array(xyz)
    assert np.allclose(cam.ned_rel_to_cam(cam.cam_to_ned_rel(p, R), R), p, atol=1e-9)


def test_yawed_follower_puts_the_leader_east() -> None:
    cam = CameraGeometry.from_mount(MountConfig(x_m=0.0, pitch_deg=0.0))
    R = R_from_euler(0.0, 0.0, math.pi / 2)  # facing east
    assert np.allclose(cam.cam_to_ned_rel(np.array([0.0, 0.0, 6.0]), R), [0.0, 6.0, 0.0], atol=1e-12)


@given(angles, small, small)
def test_rotate_cov_keeps_psd(yaw: float, pitch: float, roll: float) -> None:
    C = np.diag([0.01, 0.04, 0.3])
    C2 = rotate_cov(R_from_euler(roll, pitch, yaw), C)
    assert np.allclose(C2, C2.T)
    assert np.linalg.eigvalsh(C2).min() > 0
    assert np.trace(C2) == pytest.approx(np.trace(C))


@given(angles, angles, st.floats(0.0, 1.0))
def test_slerp_is_unit_and_hits_the_ends(y0: float, y1: float, t: float) -> None:
    q0, q1 = quat_from_euler(0.1, 0.0, y0), quat_from_euler(0.0, 0.1, y1)
    q = slerp(q0, q1, t)
    assert np.linalg.norm(q) == pytest.approx(1.0)
    assert np.allclose(R_from_quat(slerp(q0, q1, 0.0)), R_from_quat(q0), atol=1e-9)
    assert np.allclose(R_from_quat(slerp(q0, q1, 1.0)), R_from_quat(q1), atol=1e-6)


def test_history_interpolates_yaw_at_the_frame_time() -> None:
    hist = AttitudeHistory()
    hist.push(10.0, quat_from_euler(0.0, 0.0, math.radians(170.0)))
    hist.push(10.1, quat_from_euler(0.0, 0.0, math.radians(-170.0)))  # across +-180: the short way
    R = hist.R_at(10.025)
    assert R is not None
    yaw = math.degrees(math.atan2(R[1, 0], R[0, 0]))
    assert yaw == pytest.approx(175.0, abs=1e-6)


def test_history_refuses_stamps_far_from_any_sample() -> None:
    hist = AttitudeHistory(max_extrapolation_s=0.05)
    assert hist.R_at(1.0) is None
    hist.push(1.0, (1.0, 0.0, 0.0, 0.0))
    hist.push(2.0, (1.0, 0.0, 0.0, 0.0))
    assert hist.R_at(2.04) is not None
    assert hist.R_at(2.06) is None
    assert hist.R_at(0.9) is None
    hist.push(1.5, (0.0, 1.0, 0.0, 0.0))  # out of order: ignored
    assert len(hist) == 2


def test_history_is_bounded() -> None:
    hist = AttitudeHistory(capacity=8)
    for k in range(100):
        hist.push(k * 0.01, quat_from_euler(0.0, 0.0, k * 0.01))
    assert len(hist) <= 16
    R = hist.R_at(0.985)
    assert R is not None
    assert math.atan2(R[1, 0], R[0, 0]) == pytest.approx(0.985, abs=1e-6)
