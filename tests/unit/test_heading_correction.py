"""PX4's heading error out of what the mission sees, back into what PX4 gets (a fake link: pure logic)."""

from __future__ import annotations

import asyncio
import math
from dataclasses import replace

import pytest

from companion.estimation.ego_velocity import EgoModel
from companion.kernel.flight import (
    AttitudeSetpoint,
    Setpoint,
    VehicleState,
    VelocityBodySetpoint,
    VelocityNedSetpoint,
)
from companion.service.heading import MAX_SLEW_RAD_S, HeadingCorrectedLink

E = math.radians(8.0)


class _Link:
    def __init__(self) -> None:
        self.state = replace(VehicleState(), yaw_rad=math.radians(30.0))
        self.sent: list[Setpoint] = []

    def snapshot(self) -> VehicleState:
        return self.state

    async def set_setpoint(self, setpoint: Setpoint) -> None:
        self.sent.append(setpoint)


def _model(sigma_deg: float) -> EgoModel:
    return EgoModel(0.8, (0.0, 0.0), E, 400, math.radians(sigma_deg))


def _settled(sigma_deg: float = 0.5) -> tuple[HeadingCorrectedLink, _Link]:
    raw = _Link()
    link = HeadingCorrectedLink(raw)  # type: ignore[arg-type]
    for i in range(100):
        link.update(_model(sigma_deg), i * 0.5)
    return link, raw


def test_the_correction_slews_in_and_takes_the_error_out_of_the_heading() -> None:
    raw = _Link()
    link = HeadingCorrectedLink(raw)  # type: ignore[arg-type]
    link.update(_model(0.5), 0.0)
    link.update(_model(0.5), 2.0)
    assert link.applied_rad == pytest.approx(2.0 * MAX_SLEW_RAD_S)
    link, raw = _settled()
    assert link.applied_rad == pytest.approx(E)
    assert link.snapshot().yaw_rad == pytest.approx(math.radians(30.0) - E)


def test_an_untrusted_fit_is_not_applied_and_a_lost_model_holds_the_correction() -> None:
    link, _ = _settled(sigma_deg=5.0)
    assert link.applied_rad == 0.0
    link, _ = _settled()
    link.update(None, 100.0)
    assert link.applied_rad == pytest.approx(E)


def test_a_fit_that_stops_seeing_the_error_takes_the_correction_back() -> None:
    # Untrusted and still agreeing (sigma too wide): held. Untrusted and clearly off it (0 deg at a
    # sigma of 0.5 deg, 8 deg away): moved back at the slew rate, and not past zero.
    link, _ = _settled()
    link.update(replace(_model(2.0), heading_error_rad=math.radians(6.0)), 50.5)
    assert link.applied_rad == pytest.approx(E)
    near_zero = replace(_model(0.5), heading_error_rad=math.radians(0.5))
    assert not near_zero.heading_trusted
    link.update(near_zero, 52.5)
    assert link.applied_rad == pytest.approx(E - 2.0 * MAX_SLEW_RAD_S)
    other_side = replace(_model(0.5), heading_error_rad=math.radians(-1.0))
    for i in range(40):
        link.update(other_side, 53.0 + i * 0.5)
    assert link.applied_rad == pytest.approx(0.0, abs=1e-12)


def test_a_small_error_is_never_applied_however_tight_its_fit() -> None:
    link = HeadingCorrectedLink(_Link())  # type: ignore[arg-type]
    small = replace(_model(0.3), heading_error_rad=math.radians(2.0))  # 6.7 sigma, under 3 deg
    assert not small.heading_trusted
    for i in range(100):
        link.update(small, i * 0.5)
    assert link.applied_rad == 0.0


def test_setpoints_reach_px4_in_its_own_heading_frame() -> None:
    link, raw = _settled()
    asyncio.run(link.set_setpoint(VelocityBodySetpoint((2.0, 0.0, 0.1), 0.05)))
    body = raw.sent[-1]
    assert isinstance(body, VelocityBodySetpoint)
    # PX4 turns body velocities by its heading, E more than the true one: sent turned back by E.
    assert body.v_body_m_s == pytest.approx((2.0 * math.cos(E), -2.0 * math.sin(E), 0.1))
    assert body.yaw_rate_rad_s == 0.05
    asyncio.run(link.set_setpoint(AttitudeSetpoint(0.1, -0.2, 1.0, 0.5)))
    att = raw.sent[-1]
    assert isinstance(att, AttitudeSetpoint)
    assert (att.roll_rad, att.pitch_rad, att.thrust_norm) == (0.1, -0.2, 0.5)
    assert att.yaw_rad == pytest.approx(1.0 + E)
    asyncio.run(link.set_setpoint(VelocityNedSetpoint((1.0, 0.0, 0.0), 0.0)))
    ned = raw.sent[-1]
    assert isinstance(ned, VelocityNedSetpoint)
    assert ned.v_ned_m_s == (1.0, 0.0, 0.0)
    assert ned.yaw_rad == pytest.approx(E)


def test_a_body_velocity_flies_the_same_true_direction_as_wanted() -> None:
    link, raw = _settled()
    true_yaw = link.snapshot().yaw_rad
    asyncio.run(link.set_setpoint(VelocityBodySetpoint((2.0, 0.5, 0.0), 0.0)))
    sent = raw.sent[-1]
    assert isinstance(sent, VelocityBodySetpoint)
    px4_yaw = raw.state.yaw_rad  # PX4 turns the body velocity into NED by its own heading
    f, r, _ = sent.v_body_m_s
    px4_n = f * math.cos(px4_yaw) - r * math.sin(px4_yaw)
    px4_e = f * math.sin(px4_yaw) + r * math.cos(px4_yaw)
    want_n = 2.0 * math.cos(true_yaw) - 0.5 * math.sin(true_yaw)
    want_e = 2.0 * math.sin(true_yaw) + 0.5 * math.cos(true_yaw)
    assert (px4_n, px4_e) == pytest.approx((want_n, want_e))


def test_the_operator_hears_when_a_correction_starts_and_ends() -> None:
    link = HeadingCorrectedLink(_Link())  # type: ignore[arg-type]
    said = [link.update(_model(0.5), i * 0.5) for i in range(4)]
    assert said[0] is None  # no time has passed: nothing applied yet
    assert said[1] is not None
    assert said[1].startswith("heading correction on:")
    assert "+8.0 deg" in said[1]
    assert said[2:] == [None, None]
    gone = replace(_model(0.2), heading_error_rad=math.radians(-1.0))
    said = [link.update(gone, 2.0 + i * 0.5) for i in range(40)]
    assert [s for s in said if s is not None] == [
        "heading correction off: the fit no longer sees PX4's heading error"
    ]
    assert link.applied_rad == 0.0
