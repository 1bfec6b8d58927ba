"""No NaN or infinity reaches a setpoint or the autopilot: properties over the formation law and the link.

Inputs mix ordinary values with NaN, +-inf and +-1e308 (finite, but overflowing once squared) in every
argument the law reads: the relative estimate, the follower's telemetry, a shared slot, the leader's shared
velocity, neighbours and the depth guard's obstacle. Several steps run on one law, so a NaN that poisoned
an integrator would show in a later output.
"""

from __future__ import annotations

import asyncio
import math
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.config import FormationConfig, LinkConfig, SafetyConfig
from companion.kernel.clock import MonotonicClock
from companion.kernel.errors import CommandRejectedError, LinkLostError
from companion.kernel.flight import (
    AttitudeSetpoint,
    ExternalPosition,
    VelocityBodySetpoint,
    VelocityNedSetpoint,
)
from companion.mission.formation import FormationLaw
from companion.mission.geometry import FollowerState
from companion.mission.plan_slot import NeighbourNow, SlotTarget
from companion.mission.safety import SafetyLimits, clamp_speed
from companion.vehicle.finite import require_finite_position, require_finite_setpoint

#: 1e308 overflows on purpose: numpy says so, and the guards must still hold.
pytestmark = pytest.mark.filterwarnings(
    "ignore:overflow:RuntimeWarning", "ignore:invalid value:RuntimeWarning"
)

LIM = SafetyLimits.from_config(SafetyConfig(), FormationConfig().max_accel_m_s2)
HOSTILE = [math.nan, math.inf, -math.inf, 1e308, -1e308]
num = st.one_of(st.floats(-40, 40), st.sampled_from(HOSTILE))
vec = st.tuples(num, num, num).map(np.array)
opt_vec = st.one_of(st.none(), vec)


def finite(*values: Any) -> bool:
    return bool(np.all(np.isfinite(np.asarray(values, dtype=np.float64))))


followers = st.builds(
    FollowerState,
    yaw_rad=num,
    v_ned_m_s=opt_vec,
    v_down_m_s=num,
    alt_rel_m=num,
    p_ned_m=opt_vec,
)
slots = st.one_of(st.none(), st.builds(SlotTarget, p_ned_rel_m=vec, v_ned_rel_m_s=vec))
neighbours = st.lists(st.builds(NeighbourNow, p_ned_rel_m=vec, v_ned_m_s=vec, v_ned_rel_m_s=vec), max_size=2)


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(vec, vec, followers, slots, opt_vec, opt_vec, neighbours), min_size=1, max_size=4))
def test_velocity_law_outputs_are_finite_whatever_the_inputs(steps: list[tuple[Any, ...]]) -> None:
    law = FormationLaw(FormationConfig(), LIM)
    for k, (p_rel, v_rel, follower, slot, v_leader, obstacle, nbrs) in enumerate(steps):
        law.neighbours = nbrs
        cmd = law.velocity(
            p_rel,
            v_rel,
            follower,
            0.05 * k,
            slot_target=slot,
            v_leader_ned_m_s=v_leader,
            obstacle_ned_m=obstacle,
        )
        assert finite(*cmd.setpoint.v_body_m_s, cmd.setpoint.yaw_rate_rad_s), cmd.setpoint
        assert finite(*cmd.v_ned_m_s)
        if v_leader is not None:
            coast = law.coast_velocity(v_leader, p_rel, follower, obstacle)
            assert finite(*coast.v_body_m_s, coast.yaw_rate_rad_s), coast


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(vec, vec, followers, slots, num, num, neighbours), min_size=1, max_size=4))
def test_attitude_laws_output_finite_bounded_attitudes(steps: list[tuple[Any, ...]]) -> None:
    law = FormationLaw(FormationConfig(), LIM)
    for k, (p_rel, v_rel, follower, slot, v_down, yaw_rate, nbrs) in enumerate(steps):
        law.neighbours = nbrs
        for cmd in (
            law.attitude(p_rel, v_rel, follower, 0.05 * k, slot_target=slot),
            law.hover_attitude(follower, v_down, 0.05 * k + 0.01, yaw_rate_rad_s=yaw_rate),
        ):
            sp = cmd.setpoint
            assert finite(sp.roll_rad, sp.pitch_rad, sp.yaw_rad, sp.thrust_norm), sp
            assert 0.0 <= sp.thrust_norm <= 1.0
            assert abs(sp.roll_rad) <= LIM.max_tilt_rad + 1e-9
            assert abs(sp.pitch_rad) <= LIM.max_tilt_rad + 1e-9
        hover = law.hover_velocity(v_down, yaw_rate)
        assert finite(*hover.v_body_m_s, hover.yaw_rate_rad_s)


@given(vec)
def test_clamp_speed_never_passes_nan(v: np.ndarray) -> None:
    out = clamp_speed(v, LIM)
    assert finite(*out)
    assert math.hypot(out[0], out[1]) <= LIM.max_speed_m_s + 1e-9
    assert abs(out[2]) <= LIM.max_vertical_speed_m_s + 1e-9


setpoints = st.one_of(
    st.builds(VelocityBodySetpoint, v_body_m_s=st.tuples(num, num, num), yaw_rate_rad_s=num),
    st.builds(VelocityNedSetpoint, v_ned_m_s=st.tuples(num, num, num), yaw_rad=num),
    st.builds(AttitudeSetpoint, roll_rad=num, pitch_rad=num, yaw_rad=num, thrust_norm=num),
)


@settings(max_examples=200, deadline=None)
@given(setpoints)
def test_the_link_refuses_exactly_the_non_finite_setpoints(sp: Any) -> None:
    """The real MAVSDK link, unconnected: a non-finite setpoint is refused before anything is sent."""
    from companion.vehicle.mavsdk_link import MavsdkVehicleLink

    values = (
        (*sp.v_body_m_s, sp.yaw_rate_rad_s)
        if isinstance(sp, VelocityBodySetpoint)
        else (*sp.v_ned_m_s, sp.yaw_rad)
        if isinstance(sp, VelocityNedSetpoint)
        else (sp.roll_rad, sp.pitch_rad, sp.yaw_rad, sp.thrust_norm)
    )
    link = MavsdkVehicleLink(LinkConfig(), MonotonicClock())
    if all(math.isfinite(v) for v in values):
        require_finite_setpoint(sp)
        with pytest.raises(LinkLostError):  # it got past the check: only the missing link stops it
            asyncio.run(link.set_setpoint(sp))
    else:
        with pytest.raises(CommandRejectedError, match="NON_FINITE"):
            asyncio.run(link.set_setpoint(sp))


@given(st.tuples(num, num, num), st.tuples(num, num, num), num)
def test_external_positions_must_be_finite(p: tuple[float, ...], var: tuple[float, ...], yaw: float) -> None:
    fix = ExternalPosition(stamp_s=0.0, p_ned_m=p, variance_m2=var, yaw_rad=yaw)  # type: ignore[arg-type]
    if all(math.isfinite(v) for v in (*p, *var, yaw)):
        require_finite_position(fix)
    else:
        with pytest.raises(CommandRejectedError, match="NON_FINITE"):
            require_finite_position(fix)
