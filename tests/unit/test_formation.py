"""The formation law and the safety limits: hand-computed cases, properties, and a point-mass closed loop."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.config import FormationConfig, SafetyConfig
from companion.kernel.frames import heading_to_ned, ned_to_heading
from companion.mission.formation import FormationLaw
from companion.mission.geometry import FollowerState, Slot, accel_lead, faded, slot_error, tilt_from_accel
from companion.mission.safety import (
    G_M_S2,
    SafetyLimits,
    altitude_limit,
    barrier_speed_m_s,
    clamp_speed,
    geofence_limit,
    separation_limit,
    separation_limit_accel,
)
from companion.mission.static_pass import on_course, path_approach

from .pointmass import Leader, PointMass

LIM = SafetyLimits.from_config(SafetyConfig(), FormationConfig().max_accel_m_s2)
vec = st.tuples(st.floats(-30, 30), st.floats(-30, 30), st.floats(-10, 10)).map(np.array)
vel = st.tuples(st.floats(-8, 8), st.floats(-8, 8), st.floats(-3, 3)).map(np.array)


def law(**kw: object) -> FormationLaw:
    return FormationLaw(FormationConfig(**kw), LIM)  # type: ignore[arg-type]


def hover(
    yaw: float = 0.0, v: tuple[float, float, float] = (0.0, 0.0, 0.0), alt: float = 10.0
) -> FollowerState:
    return FollowerState(
        yaw_rad=yaw, v_ned_m_s=np.array(v), v_down_m_s=v[2], alt_rel_m=alt, p_ned_m=np.zeros(3)
    )


# ---------------------------------------------------------------------- geometry
def test_default_slot_is_five_metres_ahead_level() -> None:
    slot = Slot.from_offset_cam(FormationConfig().offset_cam_m)
    assert (slot.forward_m, slot.right_m, slot.down_m) == (5.0, 0.0, 0.0)
    assert slot.p_ned_m(math.pi / 2) == pytest.approx([0.0, 5.0, 0.0], abs=1e-12)


def test_slot_error_is_zero_at_the_slot_and_radial_otherwise() -> None:
    slot = Slot(5.0, 0.0, 0.0)
    e = slot_error(slot, np.array([0.0, 5.0, 0.0]), np.zeros(3), math.pi / 2)
    assert e.e_range_m == pytest.approx(0.0)
    assert e.yaw_des_rad == pytest.approx(math.pi / 2)
    assert np.linalg.norm(e.error_ned_m) == pytest.approx(0.0, abs=1e-12)
    e = slot_error(slot, np.array([7.0, 0.0, 1.0]), np.array([0.5, 0.0, 0.0]), 0.0)
    assert e.e_range_m == pytest.approx(2.0)
    assert e.e_range_rate_m_s == pytest.approx(0.5)
    assert e.e_down_m == pytest.approx(1.0)


def test_slot_with_lateral_offset_turns_the_desired_yaw() -> None:
    slot = Slot.from_offset_cam((1.0, 0.0, 5.0))  # leader 1 m right of the axis
    e = slot_error(slot, np.array([5.0, 1.0, 0.0]), np.zeros(3), 0.0)
    assert e.yaw_des_rad == pytest.approx(0.0, abs=1e-12)
    assert e.e_range_m == pytest.approx(0.0, abs=1e-12)


def test_bearing_rate_from_relative_velocity() -> None:
    e = slot_error(Slot(5.0, 0.0, 0.0), np.array([5.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]), 0.0)
    assert e.bearing_rate_rad_s == pytest.approx(0.2)


@given(st.floats(-4, 4), vec)
def test_heading_rotation_round_trip(yaw: float, v: np.ndarray) -> None:
    assert heading_to_ned(ned_to_heading(v, yaw), yaw) == pytest.approx(v, abs=1e-9)


def test_tilt_from_accel_signs() -> None:
    roll, pitch = tilt_from_accel(np.array([1.0, 0.0, 0.0]), 0.0)
    assert pitch < 0.0  # nose down to accelerate forward
    assert roll == pytest.approx(0.0)
    roll, pitch = tilt_from_accel(np.array([0.0, 1.0, 0.0]), 0.0)
    assert roll > 0.0  # right wing down to accelerate right
    roll, pitch = tilt_from_accel(np.array([0.0, 1.0, 0.0]), math.pi / 2)  # facing east: east is forward
    assert pitch < 0.0
    assert abs(roll) < 1e-12


# ---------------------------------------------------------------------- velocity law
def test_velocity_law_moves_toward_a_far_leader_and_away_from_a_near_one() -> None:
    lw = law(leader_velocity_ff=0.0)
    far = lw.velocity(np.array([8.0, 0.0, 0.0]), np.zeros(3), hover(), 0.0)
    assert far.v_ned_m_s[0] > 0.0
    lw.reset()
    near = lw.velocity(np.array([3.5, 0.0, 0.0]), np.zeros(3), hover(), 0.0)
    assert near.v_ned_m_s[0] < 0.0


def test_velocity_law_feeds_the_leader_velocity_forward() -> None:
    lw = law()
    cmd = lw.velocity(np.array([5.0, 0.0, 0.0]), np.zeros(3), hover(v=(2.0, 0.5, 0.0)), 0.0)
    assert cmd.v_ned_m_s == pytest.approx((2.0, 0.5, 0.0))
    body = cmd.setpoint.v_body_m_s
    assert body == pytest.approx((2.0, 0.5, 0.0))  # yaw 0: body = NED
    assert cmd.yaw_rate_rad_s == pytest.approx(0.0)


def test_velocity_law_takes_the_trackers_leader_acceleration_bounded() -> None:
    """With the tracker's acceleration the lead is ``leader_accel_ff_s * a``, capped."""
    lw = law(leader_accel_ff_s=0.5, max_accel_m_s2=3.0)
    cmd = lw.velocity(
        np.array([5.0, 0.0, 0.0]),
        np.zeros(3),
        hover(v=(2.0, 0.0, 0.0)),
        0.0,
        a_leader_ned_m_s2=(1.0, 0.0, 0.0),
    )
    assert cmd.v_ned_m_s == pytest.approx((2.5, 0.0, 0.0))
    assert lw.leader_accel_ned_m_s2 == pytest.approx((1.0, 0.0, 0.0))
    lw.reset()
    lw.velocity(
        np.array([5.0, 0.0, 0.0]),
        np.zeros(3),
        hover(v=(2.0, 0.0, 0.0)),
        0.0,
        a_leader_ned_m_s2=(0.0, 9.0, 0.0),
    )
    assert lw.leader_accel_ned_m_s2 == pytest.approx((0.0, 3.0, 0.0))


def test_the_lead_fades_on_small_accelerations_and_keeps_large_ones() -> None:
    """``leader_accel_fade_m_s2``: 0.3 m/s^2 of hover noise loses most of its lead, a 1.2 start little."""
    assert faded(np.array([0.3, 0.0]), 0.5) == pytest.approx([0.3 * 0.09 / 0.34, 0.0])
    assert faded(np.array([0.0, 1.2]), 0.5) == pytest.approx([0.0, 1.2 * 1.44 / 1.69])
    assert faded(np.array([0.3, -0.4]), 0.0) == pytest.approx([0.3, -0.4])

    def lead(fade: float, a: float) -> float:
        lw = law(leader_accel_ff_s=1.0, leader_accel_fade_m_s2=fade, kp_xy=0.0, kd_xy=0.0, ki_xy=0.0)
        cmd = lw.velocity(np.array([5.0, 0.0, 0.0]), np.zeros(3), hover(), 0.0, a_leader_ned_m_s2=(a, 0, 0))
        return float(cmd.v_ned_m_s[0])

    assert lead(0.5, 0.3) == pytest.approx(0.3 * 0.09 / 0.34)
    assert lead(0.0, 0.3) == pytest.approx(0.3)


def _lead(a: tuple[float, float], e_m: float, e_rate_m_s: float, **kw: float) -> np.ndarray:
    """The lead for a slot 5 m north, the leader ``e_m`` past it and moving away at ``e_rate_m_s``."""
    err = slot_error(
        Slot(5.0, 0.0, 0.0), np.array([5.0 + e_m, 0.0, 0.0]), np.array([e_rate_m_s, 0.0, 0.0]), 0.0
    )
    cfg = FormationConfig(**{"leader_accel_yield_m": 0.07, "leader_accel_yield_dead_m": 0.03, **kw})
    return np.asarray(accel_lead(np.array(a), err, cfg))


def test_the_lead_yields_where_it_would_push_a_growing_range_error_further() -> None:
    """``leader_accel_yield_m``: a speed-up's lead cannot carry the follower past its slot.

    The follower 0.2 m too close and still closing: the along-sight lead is gone, the part across the
    line of sight kept; halfway through the fade at 0.065 m; whole while the error shrinks, while the
    follower is behind (the lead closes that), and with the yield off. A leader slowing down while the
    follower falls further behind: the braking lead yields the same way.
    """
    ff = FormationConfig().leader_accel_ff_s
    assert _lead((1.0, 0.0), 0.2, 0.3) == pytest.approx([ff, 0.0])
    assert _lead((1.0, 0.5), -0.2, -0.3) == pytest.approx([0.0, 0.5 * ff])
    assert _lead((1.0, 0.0), -0.065, -0.3) == pytest.approx([0.5 * ff, 0.0])
    assert _lead((1.0, 0.0), -0.02, -0.3) == pytest.approx([ff, 0.0])  # the dead band
    assert _lead((1.0, 0.0), -0.2, 0.3) == pytest.approx([ff, 0.0])
    assert _lead((1.0, 0.0), -0.2, -0.3, leader_accel_yield_m=0.0) == pytest.approx([ff, 0.0])
    assert _lead((-1.0, 0.0), 0.2, 0.3) == pytest.approx([0.0, 0.0])
    assert _lead((-1.0, 0.0), -0.2, -0.3) == pytest.approx([-ff, 0.0])


@settings(max_examples=200, deadline=None)
@given(
    st.tuples(st.floats(-3, 3), st.floats(-3, 3)),
    st.floats(-2, 2),
    st.floats(-3, 3),
)
def test_a_yielded_lead_only_ever_loses_its_along_sight_part(
    a: tuple[float, float], e_m: float, e_rate_m_s: float
) -> None:
    full = _lead(a, e_m, e_rate_m_s, leader_accel_yield_m=0.0)
    got = _lead(a, e_m, e_rate_m_s)
    assert got[1] == pytest.approx(full[1], abs=1e-12)  # across the line of sight (east): untouched
    if full[0] == 0.0:
        assert got[0] == 0.0
    else:  # along the line of sight (north): kept, shrunk or gone, never reversed or grown
        assert 0.0 <= got[0] / full[0] <= 1.0


def test_the_range_gain_can_be_given_per_command() -> None:
    """1 m short of the slot, at rest: the range term is the gain given, ``kp_xy`` without one."""
    for kp, expect in ((None, 1.8), (2.5, 2.5)):
        lw = law(kp_xy=1.8, kd_xy=0.0, ki_xy=0.0)
        cmd = lw.velocity(np.array([6.0, 0.0, 0.0]), np.zeros(3), hover(), 0.0, kp_range_1_s=kp)
        assert cmd.v_ned_m_s[0] == pytest.approx(expect)


def test_velocity_law_yaws_toward_the_leader_with_bearing_rate_feed_forward() -> None:
    lw = law()
    cmd = lw.velocity(np.array([5.0, 0.5, 0.0]), np.array([0.0, 1.0, 0.0]), hover(), 0.0)
    bearing = math.atan2(0.5, 5.0)
    expected = 1.5 * bearing + (5.0 * 1.0) / (5.0**2 + 0.5**2)
    assert cmd.yaw_rate_rad_s == pytest.approx(expected)


def test_yaw_rate_is_limited() -> None:
    lw = law()
    cmd = lw.velocity(np.array([0.0, -5.0, 0.0]), np.zeros(3), hover(yaw=math.pi / 2), 0.0)
    assert abs(cmd.yaw_rate_rad_s) == pytest.approx(math.radians(60.0))


def test_acceleration_slew_limits_command_changes() -> None:
    lw = law()
    lw.seed_velocity(np.zeros(3))
    lw.velocity(np.array([5.0, 0.0, 0.0]), np.zeros(3), hover(), 0.0)
    cmd = lw.velocity(np.array([5.0, 0.0, 0.0]), np.zeros(3), hover(v=(4.0, 0.0, 0.0)), 0.05)
    assert np.linalg.norm(cmd.v_ned_m_s) <= FormationConfig().command_slew_m_s2 * 0.05 + 1e-9


def test_first_command_after_a_seed_is_slewed() -> None:
    # FOLLOW starts with a 3 m range error: the first command moves from the seeded velocity by one
    # control period of acceleration, not straight to the PID output (which pitched the vehicle past 40 deg).
    lw = law()
    lw.seed_velocity(np.array([0.0, 0.0, -1.5]))
    cmd = lw.velocity(np.array([8.0, 0.0, 0.0]), np.zeros(3), hover(v=(0.0, 0.0, -1.5)), 20.0)
    dv = np.asarray(cmd.v_ned_m_s) - np.array([0.0, 0.0, -1.5])
    assert np.linalg.norm(dv) == pytest.approx(FormationConfig().command_slew_m_s2 * 0.05)


def test_command_slew_is_its_own_knob_not_the_acceleration_cap() -> None:
    lw = law(command_slew_m_s2=6.0, max_accel_m_s2=3.0)
    lw.seed_velocity(np.zeros(3))
    cmd = lw.velocity(np.array([8.0, 0.0, 0.0]), np.zeros(3), hover(), 20.0)
    assert np.linalg.norm(cmd.v_ned_m_s) == pytest.approx(6.0 * 0.05)


def test_a_per_call_slew_overrides_the_configured_one() -> None:
    """The mission passes the steady-track slew (``command_slew_steady_m_s2``) this way."""
    lw = law(command_slew_m_s2=3.0)
    lw.seed_velocity(np.zeros(3))
    cmd = lw.velocity(np.array([8.0, 0.0, 0.0]), np.zeros(3), hover(), 20.0, slew_m_s2=8.0)
    assert np.linalg.norm(cmd.v_ned_m_s) == pytest.approx(8.0 * 0.05)


def test_the_steady_slew_is_horizontal_the_vertical_keeps_the_configured_one() -> None:
    """A fast vertical slew swung the height under a lossy link: only the horizontal gets ``slew_m_s2``."""
    lw = law(command_slew_m_s2=3.0, kp_z=5.0)
    lw.seed_velocity(np.zeros(3))
    # The leader 8 m ahead and 2 m above (NED down -2): both channels ask for far more than one step.
    cmd = lw.velocity(np.array([8.0, 0.0, -2.0]), np.zeros(3), hover(), 20.0, slew_m_s2=8.0)
    assert math.hypot(cmd.v_ned_m_s[0], cmd.v_ned_m_s[1]) == pytest.approx(8.0 * 0.05)
    assert cmd.v_ned_m_s[2] == pytest.approx(-3.0 * 0.05)


def test_the_acceleration_lead_can_be_dropped_while_the_track_coasts() -> None:
    """A leader speeding up at 2 m/s^2: the lead is fed forward unless the track coasts with the knob off."""

    def command(coasting: bool, keep: bool) -> float:
        lw = law(accel_lead_while_coasting=keep, kp_xy=0.0, kd_xy=0.0, ki_xy=0.0, command_slew_m_s2=100.0)
        out = None
        for k in range(40):  # the follower hovers while the leader's velocity rises: v_rel = 2 t
            t = k * 0.05
            out = lw.velocity(
                np.array([5.0, 0.0, 0.0]), np.array([2.0 * t, 0.0, 0.0]), hover(), t, coasting=coasting
            )
        assert out is not None
        return out.v_ned_m_s[0]

    v_leader = 2.0 * 39 * 0.05
    lead = command(coasting=False, keep=False) - v_leader
    assert lead > 0.5 * FormationConfig().leader_accel_ff_s * 2.0  # the lead is there
    assert command(coasting=True, keep=True) == pytest.approx(v_leader + lead)
    assert command(coasting=True, keep=False) == pytest.approx(v_leader)


def test_the_acceleration_lead_is_horizontal_unless_a_vertical_one_is_configured() -> None:
    """A leader speeding up north at 1 m/s^2 and climbing at 0.5: the lead goes on the horizontal only."""

    def command(**kw: float) -> np.ndarray:
        lw = law(kp_xy=0.0, kd_xy=0.0, ki_xy=0.0, kp_z=0.0, ki_z=0.0, command_slew_m_s2=100.0, **kw)
        out = None
        for k in range(40):
            t = k * 0.05
            v_rel = np.array([1.0 * t, 0.0, -0.5 * t])
            out = lw.velocity(np.array([5.0, 0.0, 0.0]), v_rel, hover(), t)
        assert out is not None
        return out.v_ned_m_s

    t_end = 39 * 0.05
    cmd = command()
    assert cmd[0] - t_end > 0.5 * FormationConfig().leader_accel_ff_s  # a horizontal lead
    assert cmd[2] == pytest.approx(-0.5 * t_end)  # the climb rate fed forward, no lead on it
    assert command(leader_accel_ff_z_s=0.5)[2] < -0.5 * t_end - 0.1


def test_integrators_are_bounded_and_reset() -> None:
    lw = law(kp_xy=0.0, kd_xy=0.0, leader_velocity_ff=0.0, ki_xy=1.0, i_limit_xy_m_s=0.3)
    out = None
    for k in range(200):
        out = lw.velocity(np.array([9.0, 0.0, 0.0]), np.zeros(3), hover(), k * 0.05)
    assert out is not None
    assert out.v_ned_m_s[0] == pytest.approx(0.3)
    lw.reset()
    out = lw.velocity(np.array([9.0, 0.0, 0.0]), np.zeros(3), hover(), 100.0)
    assert out.v_ned_m_s[0] == pytest.approx(0.0)


def test_integrator_does_not_wind_up_while_saturated() -> None:
    lw = law(kp_xy=10.0, ki_xy=1.0, i_limit_xy_m_s=2.0, leader_velocity_ff=0.0, command_slew_m_s2=100.0)
    for k in range(100):
        lw.velocity(np.array([30.0, 0.0, 0.0]), np.zeros(3), hover(), k * 0.05)  # saturated at max speed
    assert lw._i_range_m_s == pytest.approx(0.0)


def test_a_long_gap_restarts_the_integrators() -> None:
    lw = law(ki_xy=1.0, i_limit_xy_m_s=1.0)
    for k in range(20):
        lw.velocity(np.array([6.0, 0.0, 0.0]), np.zeros(3), hover(), k * 0.05)
    assert lw._i_range_m_s > 0.0
    lw.velocity(np.array([6.0, 0.0, 0.0]), np.zeros(3), hover(), 10.0)
    assert lw._i_range_m_s == 0.0


@settings(max_examples=300, deadline=None)
@given(p_rel=vec, v_rel=vel, v_f=vel, yaw=st.floats(-3.2, 3.2))
def test_velocity_law_never_exceeds_speed_or_closes_inside_the_barrier(
    p_rel: np.ndarray, v_rel: np.ndarray, v_f: np.ndarray, yaw: float
) -> None:
    if np.linalg.norm(p_rel) < 0.05:
        return
    lw = law(kp_xy=3.0, leader_velocity_ff=1.0)
    # Altitude unknown: the altitude band (which wins over separation, see the next test) stays out of it.
    fol = hover(yaw=yaw, v=(float(v_f[0]), float(v_f[1]), float(v_f[2])), alt=math.nan)
    cmd = lw.velocity(p_rel, v_rel, fol, 0.0)
    v = np.array(cmd.v_ned_m_s)
    d = float(np.linalg.norm(p_rel))
    u = p_rel / d
    v_leader = v_f + v_rel
    closing = float(np.dot(v, u) - np.dot(v_leader, u))
    # The barrier leaves room for the distance closed during the vehicle's response (response_s).
    closing_now = max(float(np.dot(v_f, u) - np.dot(v_leader, u)), 0.0)
    allowed = barrier_speed_m_s(d - LIM.min_separation_m - closing_now * LIM.response_s, LIM.brake_m_s2)
    assert closing <= allowed + 1e-6
    if closing < allowed - 1e-6:
        # The barrier did not act, so the speed limits hold.
        assert math.hypot(v[0], v[1]) <= LIM.max_speed_m_s + 1e-6
        assert abs(v[2]) <= LIM.max_vertical_speed_m_s + 1e-6


def test_the_altitude_band_wins_over_separation() -> None:
    # A leader dropping onto us at 4 m/s from 1 m above: separation would have us dive at 5 m/s, but
    # the ground is harder than the leader: the descent stays within what the altitude barrier allows.
    lw = law()
    cmd = lw.velocity(
        np.array([0.0, 0.0, -1.0]), np.array([0.0, 0.0, 1.0]), hover(v=(0.0, 0.0, 3.0), alt=10.0), 0.0
    )
    assert cmd.v_ned_m_s[2] == pytest.approx(barrier_speed_m_s(10.0 - LIM.min_altitude_m, LIM.brake_m_s2))


# ---------------------------------------------------------------------- attitude law
@settings(max_examples=300, deadline=None)
@given(p_rel=vec, v_rel=vel, yaw=st.floats(-3.2, 3.2), vz=st.floats(-3, 3), alt=st.floats(0, 50))
def test_attitude_law_respects_tilt_and_thrust_bounds(
    p_rel: np.ndarray, v_rel: np.ndarray, yaw: float, vz: float, alt: float
) -> None:
    lw = law()
    fol = FollowerState(yaw_rad=yaw, v_ned_m_s=None, v_down_m_s=vz, alt_rel_m=alt)
    for k in range(3):
        cmd = lw.attitude(p_rel, v_rel, fol, k * 0.05)
        sp = cmd.setpoint
        tilt = math.acos(math.cos(sp.roll_rad) * math.cos(sp.pitch_rad))
        assert tilt <= LIM.max_tilt_rad + 1e-6
        assert 0.05 <= sp.thrust_norm <= 0.95
        assert abs(math.remainder(sp.yaw_rad - yaw, 2 * math.pi)) <= math.radians(60.0) / 1.5 + 1e-9


def test_each_law_has_its_own_range_gain() -> None:
    """``kp_xy`` tunes the velocity law; the attitude law, with its own inner loop, has ``kp_xy_attitude``."""
    p_rel, v_rel = np.array([5.4, 0.0, 0.0]), np.zeros(3)  # 0.4 m behind the slot: no limit reached
    base = law(leader_velocity_ff=0.0, kp_xy=1.8).velocity(p_rel, v_rel, hover(), 0.0).v_ned_m_s[0]
    stiff = law(leader_velocity_ff=0.0, kp_xy=2.5).velocity(p_rel, v_rel, hover(), 0.0).v_ned_m_s[0]
    assert stiff > base > 0.0
    tilt = law(kp_xy=2.5).attitude(p_rel, v_rel, hover(), 0.0).setpoint.pitch_rad
    assert tilt == law(kp_xy=1.8).attitude(p_rel, v_rel, hover(), 0.0).setpoint.pitch_rad
    assert law(kp_xy_attitude=0.9).attitude(p_rel, v_rel, hover(), 0.0).setpoint.pitch_rad > tilt


def test_attitude_law_brakes_when_closing_inside_the_barrier() -> None:
    lw = law()
    fol = FollowerState(yaw_rad=0.0, v_ned_m_s=None, v_down_m_s=0.0, alt_rel_m=10.0)
    # Leader 2.5 m ahead, we close at 3 m/s: the law must pitch up (brake), whatever the PID says.
    cmd = lw.attitude(np.array([2.5, 0.0, 0.0]), np.array([-3.0, 0.0, 0.0]), fol, 0.0)
    assert cmd.setpoint.pitch_rad > 0.05


def test_hover_attitude_is_level_without_velocity_and_brakes_with_it() -> None:
    lw = law()
    lvl = lw.hover_attitude(FollowerState(0.0, None, 0.0, 10.0), 0.0, 0.0)
    assert (lvl.setpoint.roll_rad, lvl.setpoint.pitch_rad) == (0.0, 0.0)
    brake = lw.hover_attitude(FollowerState(0.0, np.array([3.0, 0.0, 0.0]), 0.0, 10.0), 0.0, 0.05)
    assert brake.setpoint.pitch_rad > 0.0


def test_thrust_controller_learns_the_hover_thrust() -> None:
    lw = law()
    pm = PointMass(p=np.array([0.0, 0.0, -10.0]), hover_thrust=0.62)
    for k in range(400):
        cmd = lw.hover_attitude(pm.follower(velocity_valid=False), 0.0, k * 0.02)
        pm.step_attitude(cmd.setpoint, 0.02)
    assert lw.thrust.hover_thrust_norm == pytest.approx(0.62, abs=0.02)
    assert abs(pm.v[2]) < 0.05


# ---------------------------------------------------------------------- safety
@given(vel)
def test_clamp_speed(v: np.ndarray) -> None:
    out = clamp_speed(v, LIM)
    assert math.hypot(out[0], out[1]) <= LIM.max_speed_m_s + 1e-9
    assert abs(out[2]) <= LIM.max_vertical_speed_m_s + 1e-9


@given(vel, vec, st.one_of(st.none(), vel))
def test_separation_barrier_property(v: np.ndarray, p_rel: np.ndarray, v_l: np.ndarray | None) -> None:
    d = float(np.linalg.norm(p_rel))
    if d < 1e-3:
        return
    out = separation_limit(v, p_rel, v_l, LIM)
    u = p_rel / d
    closing = float(np.dot(out, u)) - (float(np.dot(v_l, u)) if v_l is not None else 0.0)
    assert closing <= barrier_speed_m_s(d - LIM.min_separation_m, LIM.brake_m_s2) + 1e-9
    # Only the line-of-sight component is touched.
    assert np.cross(out - v, u) == pytest.approx(np.zeros(3), abs=1e-9)


def test_separation_pushes_out_when_inside() -> None:
    out = separation_limit(np.zeros(3), np.array([1.0, 0.0, 0.0]), np.zeros(3), LIM)
    assert out[0] == pytest.approx(-1.0)  # 1 m inside the 2 m bubble: back off at 1 m/s


def test_separation_accel_barrier_only_brakes() -> None:
    a = separation_limit_accel(np.zeros(3), np.array([10.0, 0.0, 0.0]), np.array([-1.0, 0.0, 0.0]), LIM)
    assert a == pytest.approx(np.zeros(3))  # far and slow: untouched


def test_altitude_barrier() -> None:
    assert altitude_limit(1.0, LIM.min_altitude_m, LIM) == pytest.approx(0.0)
    assert altitude_limit(1.0, LIM.min_altitude_m - 1.0, LIM) == pytest.approx(-1.0)
    assert altitude_limit(-1.0, LIM.max_altitude_m, LIM) == pytest.approx(0.0)
    assert altitude_limit(0.5, 20.0, LIM) == pytest.approx(0.5)
    assert altitude_limit(0.5, math.nan, LIM) == 0.5


def test_geofence_barrier() -> None:
    r = LIM.geofence_radius_m
    out = geofence_limit(np.array([3.0, 1.0, 0.0]), np.array([r, 0.0, -5.0]), LIM)
    assert out == pytest.approx([0.0, 1.0, 0.0])
    assert geofence_limit(np.array([3.0, 0.0, 0.0]), None, LIM) == pytest.approx([3.0, 0.0, 0.0])


def test_tilt_limit_from_config() -> None:
    assert LIM.max_horizontal_accel_m_s2 == pytest.approx(G_M_S2 * math.tan(math.radians(25.0)))


# ---------------------------------------------------------------------- closed loop (point mass, TEST-ONLY)
def _circle_run(mode: str, seconds: float = 60.0, dt: float = 0.02) -> tuple[float, float, float]:
    leader = Leader()
    p_l, v_l = leader.state(0.0)
    heading = math.atan2(v_l[1], v_l[0])
    start = p_l - 5.0 * np.array([math.cos(heading), math.sin(heading), 0.0])
    pm = PointMass(p=start.copy(), v=v_l.copy(), yaw_rad=heading)
    lw = law()
    lw.seed_velocity(pm.v)
    errs, min_sep = [], math.inf
    for k in range(int(seconds / dt)):
        t = k * dt
        p_l, v_l = leader.state(t)
        p_rel, v_rel = p_l - pm.p, v_l - pm.v
        min_sep = min(min_sep, float(np.linalg.norm(p_rel)))
        if mode == "velocity":
            cmd = lw.velocity(p_rel, v_rel, pm.follower(), t)
            pm.step_velocity(cmd.setpoint, dt)
            err = cmd.error.error_ned_m
        else:
            acmd = lw.attitude(p_rel, v_rel, pm.follower(velocity_valid=False), t)
            pm.step_attitude(acmd.setpoint, dt)
            assert acmd.error is not None
            err = acmd.error.error_ned_m
        if t > 10.0:
            errs.append(float(np.linalg.norm(err)))
    e = np.array(errs)
    return float(np.sqrt(np.mean(e**2))), float(e.max()), min_sep


def test_point_mass_circle_velocity_law() -> None:
    rmse, worst, min_sep = _circle_run("velocity")
    assert rmse < 0.2
    assert worst < 0.4
    assert min_sep > 2.0


def test_point_mass_circle_attitude_law() -> None:
    rmse, worst, min_sep = _circle_run("attitude")
    assert rmse < 0.3
    assert worst < 0.6
    assert min_sep > 2.0


def _closest_approach(with_actual_velocity: bool) -> float:
    """A follower with PX4's first-order velocity lag (tau 0.55 s) closing at 1.8 m/s on a leader 3.07 m
    away that keeps asking to come nearer: the barrier alone has to stop it (the network circle case)."""
    tau_s, dt_s = 0.55, 0.02
    p_f, v_f = np.zeros(3), np.array([1.8, 0.0, 0.0])
    p_l = np.array([3.07, 0.0, 0.0])
    closest = 10.0
    for _ in range(400):
        want = np.array([3.0, 0.0, 0.0])  # a formation law still driving toward the leader
        v_cmd = separation_limit(want, p_l - p_f, np.zeros(3), LIM, v_f if with_actual_velocity else None)
        v_f = v_f + (v_cmd - v_f) * (dt_s / tau_s)
        p_f = p_f + v_f * dt_s
        closest = min(closest, float(np.linalg.norm(p_l - p_f)))
    return closest


def test_separation_barrier_leaves_room_for_the_vehicles_response() -> None:
    assert _closest_approach(with_actual_velocity=False) < LIM.min_separation_m - 0.2  # the old barrier
    assert _closest_approach(with_actual_velocity=True) >= LIM.min_separation_m - 0.05


def test_coast_keeps_the_leaders_velocity_without_closing_on_its_guess() -> None:
    """Coasting: the command is the leader's last velocity (levelled), however far the guess says it is."""
    lw = law()
    fol = hover(v=(3.0, 0.0, 0.0))
    far = lw.coast_velocity(np.array([3.0, 0.0, 0.5]), np.array([9.0, 0.0, 0.0]), fol)
    assert far.v_body_m_s == pytest.approx((3.0, 0.0, 0.0))
    # Near the bubble and closing, the barrier still brakes.
    near = lw.coast_velocity(np.array([0.0, 0.0, 0.0]), np.array([2.5, 0.0, 0.0]), hover(v=(1.5, 0.0, 0.0)))
    assert near.v_body_m_s[0] < 0.5


def test_the_depth_guards_obstacle_is_held_off_as_a_static_object() -> None:
    """An obstacle 2.5 m ahead: the law may not close on it faster than the barrier allows, leader or not."""
    lw = law()
    fol = hover(v=(2.0, 0.0, 0.0))
    free = lw.velocity(np.array([7.0, 0.0, 0.0]), np.zeros(3), fol, 0.0)
    lw.reset()
    held = lw.velocity(
        np.array([7.0, 0.0, 0.0]), np.zeros(3), fol, 0.0, obstacle_ned_m=np.array([2.5, 0.0, 0.0])
    )
    assert free.v_ned_m_s[0] > 2.0
    assert held.v_ned_m_s[0] < 0.5 * free.v_ned_m_s[0]
    # An obstacle behind does not hold the follower back.
    lw.reset()
    behind = lw.velocity(
        np.array([7.0, 0.0, 0.0]), np.zeros(3), fol, 0.0, obstacle_ned_m=np.array([-2.5, 0.0, 0.0])
    )
    assert behind.v_ned_m_s[0] == pytest.approx(free.v_ned_m_s[0])


def test_on_course_is_the_corridor_ahead_along_the_velocity() -> None:
    v = np.array([2.0, 0.0, 0.0])
    assert on_course(np.array([3.0, 0.2, 0.0]), v, 0.6)  # a leader just off the path
    assert not on_course(np.array([3.0, 0.9, 0.0]), v, 0.6)  # a pole passed 0.9 m to the side
    assert not on_course(np.array([-3.0, 0.0, 0.0]), v, 0.6)  # behind
    assert not on_course(np.array([3.0, 0.0, 0.0]), np.zeros(3), 0.6)  # not moving: nothing to hit


def test_path_approach_follows_px4s_lag_from_the_present_velocity() -> None:
    # Flying north at 2 m/s, commanded 6 deg right: the path bends over ~0.55 s, so a pole 4 m ahead and
    # 0.95 m right is passed ~0.64 m off, where the command's straight ray passes it 0.53 m off.
    v_now = np.array([2.0, 0.0, 0.0])
    v_cmd = np.array([1.99, 0.21, 0.0])
    pole = np.array([4.0, 0.95, 0.0])
    cpa, q = path_approach(pole, v_now, v_cmd)
    assert on_course(pole, v_cmd, 0.6)
    assert 0.6 < cpa < 0.7
    assert q[1] > 0.0  # the pole is to the right of the path's nearest point
    # Behind, or moving away: never approached.
    assert path_approach(np.array([-3.0, 0.0, 0.0]), v_now, v_now)[0] == math.inf
    assert path_approach(np.array([3.0, 0.0, 0.0]), np.zeros(3), np.zeros(3))[0] == math.inf


def test_the_depth_guard_slides_past_an_obstacle_beside_the_path_without_braking() -> None:
    """A pole 0.45 m beside the path (corridor 0.8 m): full speed, turned away; dead ahead: a brake."""
    fol = hover(v=(2.0, 0.0, 0.0))
    lw = law()
    free = lw.velocity(np.array([7.0, 0.0, 0.0]), np.zeros(3), fol, 0.0)
    lw.reset()
    beside = lw.velocity(
        np.array([7.0, 0.0, 0.0]), np.zeros(3), fol, 0.0, obstacle_ned_m=np.array([3.0, 0.45, 0.0])
    )
    assert beside.v_ned_m_s[0] == pytest.approx(free.v_ned_m_s[0])  # no braking
    assert beside.v_ned_m_s[1] < free.v_ned_m_s[1] - 0.1  # stepping left, away from the pole
    assert beside.v_ned_m_s[1] > -0.5  # a step, not a swerve
    lw.reset()
    ahead = lw.velocity(
        np.array([7.0, 0.0, 0.0]), np.zeros(3), fol, 0.0, obstacle_ned_m=np.array([3.0, 0.1, 0.0])
    )
    assert ahead.v_ned_m_s[0] < 0.5 * free.v_ned_m_s[0]
    lw.reset()
    clear = lw.velocity(
        np.array([7.0, 0.0, 0.0]), np.zeros(3), fol, 0.0, obstacle_ned_m=np.array([3.0, 0.9, 0.0])
    )
    assert clear.v_ned_m_s == pytest.approx(free.v_ned_m_s)


# ---------------------------------------------------------------------- trailing and feed-forward
def test_a_leader_flying_across_the_line_of_sight_is_trailed() -> None:
    """Leader 5 m north flying east at 3 m/s: the follower also slides west, to end up behind it."""
    moving_east = hover(v=(0.0, 3.0, 0.0))
    held = law(trail_gain_1_s=0.0).velocity(np.array([5.0, 0.0, 0.0]), np.zeros(3), moving_east, 0.0)
    assert held.v_ned_m_s == pytest.approx((0.0, 3.0, 0.0))
    trailed = law().velocity(np.array([5.0, 0.0, 0.0]), np.zeros(3), moving_east, 0.0)
    # 90 deg off the course, 45 deg past the free band: k r sin(45 deg) = 2.8 m/s, capped at 1.5 m/s.
    assert trailed.v_ned_m_s == pytest.approx((0.0, 3.0 - 1.5, 0.0))


def test_trailing_leaves_a_leader_within_the_free_angle_or_hovering_alone() -> None:
    # 30 deg off the course: within trail_free_deg (45), the follower keeps its place in NED.
    v = (3.0 * math.cos(math.radians(30.0)), 3.0 * math.sin(math.radians(30.0)), 0.0)
    cmd = law().velocity(np.array([5.0, 0.0, 0.0]), np.zeros(3), hover(v=v), 0.0)
    assert cmd.v_ned_m_s == pytest.approx(v)
    slow = (0.0, 0.4, 0.0)  # under trail_min_speed_m_s: no course to trail
    cmd = law().velocity(np.array([5.0, 0.0, 0.0]), np.zeros(3), hover(v=slow), 0.0)
    assert cmd.v_ned_m_s == pytest.approx(slow)


def test_the_feedforward_setpoint_carries_the_drag_at_the_command_and_an_absolute_yaw() -> None:
    from companion.kernel.flight import VelocityNedSetpoint
    from companion.mission.types import AirframeDrag

    follower = FollowerState(
        yaw_rad=0.3,
        v_ned_m_s=np.array([2.0, 0.0, 0.0]),
        v_down_m_s=0.0,
        alt_rel_m=10.0,
        p_ned_m=np.zeros(3),
        airframe=AirframeDrag(drag_per_s=1.0, push_ne_m_s2=(0.2, -0.1)),
    )
    p_rel = 5.0 * np.array([math.cos(0.3), math.sin(0.3), 0.0])
    lw = law(acceleration_feedforward=True)
    cmd = lw.velocity(p_rel, np.zeros(3), follower, 0.0)
    sp = cmd.setpoint
    assert isinstance(sp, VelocityNedSetpoint)
    assert sp.v_ned_m_s == pytest.approx(cmd.v_ned_m_s)
    assert sp.a_ned_m_s2 is not None
    # Holding the commanded velocity against the drag, less the wind's push; no leader acceleration yet.
    expect = (1.0 * cmd.v_ned_m_s[0] - 0.2, 1.0 * cmd.v_ned_m_s[1] + 0.1, 0.0)
    assert sp.a_ned_m_s2 == pytest.approx(expect)
    assert sp.yaw_rad == pytest.approx(0.3 + cmd.yaw_rate_rad_s * FormationLaw.YAW_LEAD_S)
    # Without a learnt drag only the leader's acceleration would be fed forward (none here).
    no_drag = law(acceleration_feedforward=True).velocity(
        p_rel, np.zeros(3), hover(yaw=0.3, v=(2.0, 0.0, 0.0)), 0.0
    )
    assert isinstance(no_drag.setpoint, VelocityNedSetpoint)
    assert no_drag.setpoint.a_ned_m_s2 == pytest.approx((0.0, 0.0, 0.0))


def test_the_attitude_law_starts_from_the_tilt_flown_at_the_switch() -> None:
    """GPS lost while holding 2 m/s against a 1 /s drag (11 deg nose down): the first attitude keeps it."""
    pitch = -math.atan2(2.0, G_M_S2)
    flying = FollowerState(
        yaw_rad=0.0, v_ned_m_s=None, v_down_m_s=0.0, alt_rel_m=10.0, p_ned_m=None, pitch_rad=pitch
    )
    at_slot = np.array([5.0, 0.0, 0.0])
    cmd = law().attitude(at_slot, np.zeros(3), flying, 0.0)
    assert cmd.setpoint.pitch_rad == pytest.approx(pitch, abs=1e-6)
    level = FollowerState(yaw_rad=0.0, v_ned_m_s=None, v_down_m_s=0.0, alt_rel_m=10.0, p_ned_m=None)
    assert law().attitude(at_slot, np.zeros(3), level, 0.0).setpoint.pitch_rad == pytest.approx(0.0, abs=1e-9)
