"""The control cascade's pure pieces: hand-computed cases and properties."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from companion.kernel.frames import R_from_quat, quat_from_euler
from sitl.autopilot.attitude import attitude_from_thrust, quat_between, quat_mul, yaw_of
from sitl.autopilot.attitude import quat_from_euler as quat_from_euler_fast
from sitl.autopilot.control import NAN, PositionController, PositionLimits, TrajectorySetpoint
from sitl.autopilot.inner_loop import InnerLoop
from sitl.physics.dynamics import QUAD

angles = st.floats(-1.2, 1.2)


@given(angles, angles, st.floats(-math.pi, math.pi))
def test_fast_euler_quaternion_matches_frames(roll: float, pitch: float, yaw: float) -> None:
    q = quat_from_euler_fast(roll, pitch, yaw)
    ref = quat_from_euler(roll, pitch, yaw)
    sign = 1.0 if q[0] >= 0 else -1.0
    assert [sign * c for c in q] == pytest.approx(list(ref), abs=1e-9)


unit = st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1)).filter(
    lambda v: math.sqrt(v[0] ** 2 + v[1] ** 2 + v[2] ** 2) > 1e-3
)


@given(unit, unit)
def test_quat_between_rotates_u_onto_v(a: tuple[float, float, float], b: tuple[float, float, float]) -> None:
    na, nb = math.sqrt(sum(x * x for x in a)), math.sqrt(sum(x * x for x in b))
    u = (a[0] / na, a[1] / na, a[2] / na)
    v = (b[0] / nb, b[1] / nb, b[2] / nb)
    R = R_from_quat(quat_between(u, v))
    assert list(R @ u) == pytest.approx(list(v), abs=1e-6)


@pytest.mark.parametrize(
    ("u", "v"),
    [
        ((0.0, 0.0, -1.0), (0.0, 1e-5, 1.0)),
        ((1.0, 0.0, 0.0), (-1.0, 0.0, 0.0)),
        ((0.0, 0.0, 1.0), (0.0, 0.0, 1.0)),
    ],
)
def test_quat_between_nearly_opposite_and_equal(
    u: tuple[float, float, float], v: tuple[float, float, float]
) -> None:
    n = math.sqrt(sum(x * x for x in v))
    v = (v[0] / n, v[1] / n, v[2] / n)
    assert list(R_from_quat(quat_between(u, v)) @ u) == pytest.approx(list(v), abs=1e-9)


def test_quat_mul_composes_yaws() -> None:
    q = quat_mul(quat_from_euler_fast(0, 0, 0.3), quat_from_euler_fast(0, 0, 0.4))
    assert yaw_of(q) == pytest.approx(0.7)


def test_hover_thrust_is_level_with_requested_heading() -> None:
    # Straight up at hover thrust: level attitude, heading as asked.
    q, thrust = attitude_from_thrust(0.0, 0.0, -0.5, 1.0)
    assert thrust == pytest.approx(0.5)
    assert yaw_of(q) == pytest.approx(1.0)
    assert list(R_from_quat(q)[:, 2]) == pytest.approx([0.0, 0.0, 1.0], abs=1e-9)


def test_forward_thrust_pitches_nose_down() -> None:
    # Thrust tilted north while facing north: body z tilts back, i.e. nose down (negative pitch).
    q, _ = attitude_from_thrust(0.2, 0.0, -0.5, 0.0)
    R = R_from_quat(q)
    assert R[0, 2] < 0  # body z has a southward (negative north) component
    pitch = -math.asin(R[2, 0])
    assert pitch == pytest.approx(-math.atan2(0.2, 0.5), abs=1e-9)


def test_position_controller_hovers_at_hover_thrust() -> None:
    pc = PositionController(PositionLimits(hover_thrust=0.5))
    sp = TrajectorySetpoint().set(pos=(0.0, 0.0, -5.0))
    thr = pc.update(sp, (0.0, 0.0, -5.0), (0.0, 0.0, 0.0), 0.02)
    assert thr == pytest.approx((0.0, 0.0, -0.5))


def test_position_controller_limits_tilt_and_velocity() -> None:
    lim = PositionLimits(tilt_max_rad=math.radians(30.0), vel_max_xy_m_s=12.0)
    pc = PositionController(lim)
    sp = TrajectorySetpoint().set(pos=(1000.0, 0.0, -5.0))
    tn, te, td = pc.update(sp, (0.0, 0.0, -5.0), (0.0, 0.0, 0.0), 0.02)
    assert pc.vel_sp_ned_m_s[0] == pytest.approx(12.0)
    assert math.degrees(math.atan2(math.hypot(tn, te), -td)) == pytest.approx(30.0, abs=1e-6)


def test_setpoint_validity_follows_px4_input_checks() -> None:
    assert TrajectorySetpoint().set(vel=(1.0, 0.0, 0.0)).is_valid()
    assert TrajectorySetpoint().set(pos=(0.0, 0.0, NAN), vel=(NAN, NAN, 0.5)).is_valid()
    assert TrajectorySetpoint().set(acc=(0.0, 0.0, NAN), vel=(NAN, NAN, 0.7)).is_valid()
    assert not TrajectorySetpoint().set(vel=(1.0, NAN, 0.0)).is_valid()  # x without y
    assert not TrajectorySetpoint().set(pos=(1.0, 2.0, NAN)).is_valid()  # z uncontrolled
    assert not TrajectorySetpoint().is_valid()


def test_mixer_gives_pitch_priority_over_yaw_and_stays_in_range() -> None:
    loop = InnerLoop(QUAD)
    # Huge yaw and pitch demands: outputs stay in [0, 1] and still pitch the right way.
    u = loop.rates_to_motors(0.0, 50.0, 50.0, 0.5, 0.0, 0.0, 0.0, 0.004, integrate=False)
    assert all(0.0 <= x <= 1.0 for x in u)
    front = u[0] + u[2]
    rear = u[1] + u[3]
    assert front > rear  # nose up: front motors push harder


def test_mixer_zero_demand_is_equal_thrust() -> None:
    loop = InnerLoop(QUAD)
    u = loop.rates_to_motors(0.0, 0.0, 0.0, 0.5, 0.0, 0.0, 0.0, 0.004, integrate=False)
    assert u == pytest.approx((0.5, 0.5, 0.5, 0.5))


@given(angles, angles, st.floats(-math.pi, math.pi))
def test_attitude_loop_rates_point_towards_the_setpoint(roll: float, pitch: float, yaw: float) -> None:
    loop = InnerLoop(QUAD)
    q = quat_from_euler_fast(roll, pitch, yaw)
    level = quat_from_euler_fast(0.0, 0.0, yaw)
    rx, ry, _ = loop.attitude_to_rates(q, level, NAN)
    # Levelling: the rate setpoint opposes the tilt (for modest angles, roll and pitch decouple).
    if abs(roll) > 0.05 and abs(pitch) < 0.5:
        assert rx * roll < 0
    if abs(pitch) > 0.05 and abs(roll) < 0.5:
        assert ry * pitch < 0


@given(
    st.tuples(angles, angles, st.floats(-math.pi, math.pi)),
    st.tuples(angles, angles, st.floats(-math.pi, math.pi)),
    st.tuples(st.floats(-5, 5), st.floats(-5, 5), st.floats(-5, 5)),
    st.tuples(st.one_of(st.just(NAN), st.floats(-2, 2)), st.floats(0, 1)),
    st.booleans(),
)
def test_fused_inner_step_is_the_staged_cascade_bit_for_bit(
    att: tuple[float, float, float],
    att_sp: tuple[float, float, float],
    rates: tuple[float, float, float],
    yawspeed_thrust: tuple[float, float],
    integrate: bool,
) -> None:
    yawspeed, thrust = yawspeed_thrust
    staged, fused = InnerLoop(QUAD), InnerLoop(QUAD)
    q_sp = quat_from_euler_fast(*att_sp)
    for k in range(3):  # integrator and D-term state carry over, the cached setpoint axis too
        p, q, r = (c * (1.0 + 0.1 * k) for c in rates)
        sp = staged.attitude_to_rates(quat_from_euler_fast(*att), q_sp, yawspeed)
        expected = staged.rates_to_motors(*sp, thrust, p, q, r, 0.005, integrate)
        assert fused.update(*att, p, q, r, q_sp, yawspeed, thrust, 0.005, integrate) == expected
