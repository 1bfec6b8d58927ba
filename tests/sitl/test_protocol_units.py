"""Pure protocol pieces: parameter encoding, offboard setpoint parsing, failsafe resolution."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from sitl.autopilot.commander import Action, DisarmTimer, Flags, Probation, resolve_failsafe
from sitl.autopilot.modes import NavState, nav_state_from_mode
from sitl.autopilot.offboard import SetpointKind, parse_attitude_target, parse_local_ned
from sitl.autopilot.params import PARAM_TYPE_INT32, PARAM_TYPE_REAL32, ParamStore, decode_value, encode_value
from sitl.physics.gps import NormalDraws

NAN = math.nan


def test_int_params_are_encoded_bytewise_as_px4_does() -> None:
    raw = encode_value(5_000_000.0, PARAM_TYPE_INT32)
    assert struct.unpack("<i", struct.pack("<f", raw))[0] == 5_000_000
    assert decode_value(raw, PARAM_TYPE_INT32) == 5_000_000.0
    assert encode_value(2.5, PARAM_TYPE_REAL32) == 2.5


def test_param_store_clamps_and_versions() -> None:
    p = ParamStore()
    assert p["MIS_TAKEOFF_ALT"] == 2.5
    assert p["EKF2_NOAID_TOUT"] == 5_000_000
    v0 = p.version
    assert p.set("MPC_XY_VEL_MAX", 1e9) == 20.0
    assert p.set("MPC_XY_VEL_MAX", math.nan) == 20.0  # non-finite: unchanged
    assert p.version == v0 + 1
    assert p.names == tuple(sorted(p.names))
    assert decode_value(math.inf, PARAM_TYPE_REAL32) is None


def _sp(frame: int, mask: int, **kw: float) -> mavlink.MAVLink_set_position_target_local_ned_message:
    f = dict.fromkeys(("x", "y", "z", "vx", "vy", "vz", "afx", "afy", "afz", "yaw", "yaw_rate"), 0.0)
    f.update(kw)
    return mavlink.MAVLink_set_position_target_local_ned_message(0, 1, 1, frame, mask, *f.values())


def test_mavsdk_velocity_ned_mask_is_velocity_plus_yaw() -> None:
    sp = parse_local_ned(_sp(1, 2503, vx=2.0, yaw=0.5, x=99.0), 1.0, 0.0, (1.0, 0.0, 0.0, 0.0))
    assert not isinstance(sp, str)
    assert (sp.position, sp.velocity, sp.acceleration) == (False, True, False)
    assert sp.trajectory.vx == 2.0
    assert math.isnan(sp.trajectory.x)
    assert sp.trajectory.yaw == 0.5
    assert math.isnan(sp.trajectory.yawspeed)


def test_mavsdk_position_mask_ignores_velocity() -> None:
    sp = parse_local_ned(_sp(1, 2552, x=1.0, y=2.0, z=-3.0, vx=9.0), 1.0, 0.0, (1.0, 0.0, 0.0, 0.0))
    assert not isinstance(sp, str)
    assert (sp.position, sp.velocity) == (True, False)
    assert (sp.trajectory.x, sp.trajectory.y, sp.trajectory.z) == (1.0, 2.0, -3.0)


def test_body_ned_rotates_velocity_by_yaw_and_ignores_position() -> None:
    yaw = math.pi / 2  # facing east
    sp = parse_local_ned(_sp(8, 1479, x=5.0, vx=1.0, yaw_rate=0.3), 1.0, yaw, (1.0, 0.0, 0.0, 0.0))
    assert not isinstance(sp, str)
    assert not sp.position
    assert sp.trajectory.vx == pytest.approx(0.0, abs=1e-12)
    assert sp.trajectory.vy == pytest.approx(1.0)
    assert sp.trajectory.yawspeed == pytest.approx(0.3)


@pytest.mark.parametrize(
    ("frame", "mask", "text"),
    [
        (9, 2503, "coordinate frame 9 unsupported"),  # BODY_OFFSET_NED
        (1, 0xFFF, "invalid"),  # everything masked
        (1, 1 | 2 | 4 | 8 | 16 | 32 | 512, "force not supported"),
    ],
)
def test_refusals_match_px4_texts(frame: int, mask: int, text: str) -> None:
    out = parse_local_ned(_sp(frame, mask, afx=1.0), 1.0, 0.0, (1.0, 0.0, 0.0, 0.0))
    assert isinstance(out, str)
    assert text in out


def test_nan_and_inf_fields_count_as_not_given() -> None:
    sp = parse_local_ned(_sp(1, 0b110111111000, x=NAN, y=math.inf, z=-5.0), 1.0, 0.0, (1.0, 0.0, 0.0, 0.0))
    assert not isinstance(sp, str)
    assert math.isnan(sp.trajectory.x)
    assert math.isnan(sp.trajectory.y)
    assert sp.trajectory.z == -5.0
    assert not sp.trajectory.is_valid()  # z alone: PX4's position controller refuses it


def test_attitude_target_quaternion_and_rates() -> None:
    q = [math.cos(0.1), math.sin(0.1), 0.0, 0.0]
    msg = mavlink.MAVLink_set_attitude_target_message(0, 1, 1, 7, q, 0.0, 0.0, 0.0, 0.6)
    sp = parse_attitude_target(msg, 2.0)
    assert not isinstance(sp, str)
    assert sp is not None
    assert sp.kind is SetpointKind.ATTITUDE
    assert sp.thrust == pytest.approx(0.6)
    rates = mavlink.MAVLink_set_attitude_target_message(0, 1, 1, 128, [1, 0, 0, 0], 0.1, 0.2, 0.3, 0.5)
    sp = parse_attitude_target(rates, 2.0)
    assert not isinstance(sp, str)
    assert sp is not None
    assert sp.kind is SetpointKind.RATES
    assert sp.rates_sp == pytest.approx((0.1, 0.2, 0.3))
    bad = mavlink.MAVLink_set_attitude_target_message(0, 1, 1, 7, [NAN, 0, 0, 0], 0, 0, 0, 0.5)
    assert parse_attitude_target(bad, 2.0) == "SET_ATTITUDE_TARGET invalid"


def test_custom_modes_match_px4_table() -> None:
    assert NavState.OFFBOARD.custom_mode == 393216
    assert NavState.AUTO_LOITER.custom_mode == 50593792
    assert NavState.AUTO_RTL.custom_mode == 84148224
    assert NavState.AUTO_LAND.custom_mode == 100925440
    assert NavState.DESCEND.custom_mode == NavState.AUTO_LAND.custom_mode  # Descend shows as AUTO.LAND
    assert NavState.AUTO_TAKEOFF.custom_mode == 33816576
    assert NavState.AUTO_LOITER.base_mode(armed=False) == 29
    assert NavState.AUTO_LOITER.base_mode(armed=True) == 157
    assert NavState.OFFBOARD.base_mode(armed=True) == 145
    assert NavState.POSCTL.base_mode(armed=True) == 209
    assert nav_state_from_mode(4, 0) is NavState.AUTO_MISSION
    assert nav_state_from_mode(4, 99) is None


GOOD = Flags(
    local_position_valid=True,
    local_position_relaxed_valid=True,
    local_velocity_valid=True,
    global_position_valid=True,
    home_valid=True,
    offboard_signal=True,
)
NO_POSITION = Flags(home_valid=True, offboard_signal=False)


def test_offboard_loss_with_gps_goes_to_return() -> None:
    f = Flags(**{**{k: getattr(GOOD, k) for k in GOOD.__slots__}, "offboard_signal": False})
    assert resolve_failsafe(NavState.OFFBOARD, f, com_obl_rc_act=0, nav_rcl_act=2) is Action.RTL
    assert resolve_failsafe(NavState.OFFBOARD, f, com_obl_rc_act=4, nav_rcl_act=2) is Action.LAND
    assert resolve_failsafe(NavState.OFFBOARD, GOOD, com_obl_rc_act=0, nav_rcl_act=2) is Action.NONE


def test_position_loss_falls_through_to_descend() -> None:
    for mode in (NavState.OFFBOARD, NavState.AUTO_LOITER, NavState.AUTO_TAKEOFF, NavState.AUTO_RTL):
        assert resolve_failsafe(mode, NO_POSITION, com_obl_rc_act=0, nav_rcl_act=2) is Action.DESCEND


def test_probation_drops_at_once_and_recovers_after_a_second() -> None:
    p = Probation()
    assert not p.update(0.0, True)
    assert p.update(1.0, True)
    assert not p.update(1.02, False)
    assert not p.update(1.5, True)
    assert p.update(2.5, True)


def test_disarm_timer_land_and_preflight() -> None:
    d = DisarmTimer()
    assert not d.update(0.0, armed=True, landed=True, disarm_land_s=2.0, disarm_prflt_s=10.0)
    assert not d.update(9.9, armed=True, landed=True, disarm_land_s=2.0, disarm_prflt_s=10.0)
    assert d.update(10.0, armed=True, landed=True, disarm_land_s=2.0, disarm_prflt_s=10.0)
    d.reset()
    assert not d.update(20.0, armed=True, landed=False, disarm_land_s=2.0, disarm_prflt_s=10.0)
    assert not d.update(30.0, armed=True, landed=True, disarm_land_s=2.0, disarm_prflt_s=10.0)
    assert d.update(32.0, armed=True, landed=True, disarm_land_s=2.0, disarm_prflt_s=10.0)


@pytest.mark.parametrize(("n", "block"), [(5, 1000), (9, 900), (7, 10), (3, 2)])
def test_block_normal_draws_are_the_one_call_per_sample_sequence(n: int, block: int) -> None:
    reference = np.random.default_rng(11)
    draws = NormalDraws(np.random.default_rng(11), block=block)
    for _ in range(40):
        assert draws.take(n) == reference.standard_normal(n).tolist()
