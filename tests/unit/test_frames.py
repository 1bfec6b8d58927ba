from __future__ import annotations

import math

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from companion.kernel.frames import (
    R_BODY_CAM_LEVEL,
    R_body_cam_from_mount,
    R_from_euler,
    R_from_quat,
    euler_from_R,
    quat_from_R,
    wrap_pi,
)

angles = st.floats(-math.pi + 1e-3, math.pi - 1e-3)
pitches = st.floats(-math.pi / 2 + 1e-2, math.pi / 2 - 1e-2)


@given(angles, pitches, angles)
def test_euler_round_trip(roll: float, pitch: float, yaw: float) -> None:
    r2, p2, y2 = euler_from_R(R_from_euler(roll, pitch, yaw))
    assert np.allclose([r2, p2, y2], [roll, pitch, yaw], atol=1e-9)


@given(angles, pitches, angles)
def test_quaternion_round_trip(roll: float, pitch: float, yaw: float) -> None:
    R = R_from_euler(roll, pitch, yaw)
    assert np.allclose(R_from_quat(quat_from_R(R)), R, atol=1e-9)
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-12)


def test_yaw_east_maps_forward_to_east() -> None:
    R_ned_body = R_from_euler(0.0, 0.0, math.pi / 2)
    assert np.allclose(R_ned_body @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])


def test_level_camera_axes() -> None:
    # optical axis -> body forward, image right -> body right, image down -> body down
    assert np.allclose(R_BODY_CAM_LEVEL @ [0, 0, 1], [1, 0, 0])
    assert np.allclose(R_BODY_CAM_LEVEL @ [1, 0, 0], [0, 1, 0])
    assert np.allclose(R_BODY_CAM_LEVEL @ [0, 1, 0], [0, 0, 1])


def test_camera_pitched_up_looks_up() -> None:
    axis_body = R_body_cam_from_mount(pitch_deg=10.0) @ [0.0, 0.0, 1.0]
    assert axis_body[2] < 0  # up is -z in FRD
    assert math.isclose(math.degrees(math.asin(-axis_body[2])), 10.0, abs_tol=1e-9)


def test_wrap_pi() -> None:
    assert math.isclose(wrap_pi(3 * math.pi / 2), -math.pi / 2)
    assert math.isclose(wrap_pi(-3 * math.pi / 2), math.pi / 2)
