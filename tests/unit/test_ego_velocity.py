"""The follower's velocity without GPS: a drag model learnt from GPS velocity and attitude, flown after."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.estimation.ego_velocity import G_M_S2, EgoVelocityObserver, thrust_accel_h
from companion.kernel.frames import R_from_euler

DT_S = 0.05


def _attitude(thrust_ne: np.ndarray, heading_error_rad: float) -> np.ndarray:
    """The attitude PX4 reports for a true horizontal thrust acceleration (true heading north)."""
    pitch = math.atan(-thrust_ne[0] / G_M_S2)
    roll = math.atan(thrust_ne[1] * math.cos(pitch) / G_M_S2)
    return R_from_euler(roll, pitch, heading_error_rad)


def _fly(
    obs: EgoVelocityObserver, *, drag: float, wind: tuple[float, float], err: float, seconds: float, gps: bool
) -> tuple[list[np.ndarray], list[np.ndarray | None]]:
    """A follower speeding up and slowing down along a bent path; true and observed velocities."""
    rng = np.random.default_rng(3)
    v = np.zeros(2)
    w = np.asarray(wind)
    truth: list[np.ndarray] = []
    seen: list[np.ndarray | None] = []
    for i in range(int(seconds / DT_S)):
        t = i * DT_S
        a_want = np.array([0.6 * math.sin(0.25 * t), 0.4 * math.cos(0.17 * t)])
        thrust = a_want + drag * (v - w)
        R = _attitude(thrust, err)
        v = v + (thrust - drag * (v - w)) * DT_S
        if gps:
            noisy = np.array([v[0], v[1], 0.0]) + rng.normal(0.0, 0.03, 3)
            obs.learn(t, noisy, R)
            seen.append(None)
        else:
            out = obs.step(t, R, np.array([v[0], v[1], 0.0]))
            seen.append(None if out is None else np.asarray(out))
        truth.append(v.copy())
    return truth, seen


def test_thrust_gives_the_tilt_acceleration() -> None:
    assert thrust_accel_h(np.eye(3)) == pytest.approx((0.0, 0.0))
    ax, ay = thrust_accel_h(R_from_euler(0.0, math.radians(-10.0), 0.0))  # nose down
    assert ax == pytest.approx(G_M_S2 * math.tan(math.radians(10.0)))
    assert ay == pytest.approx(0.0, abs=1e-9)


def test_the_fit_finds_drag_wind_and_heading_error() -> None:
    obs = EgoVelocityObserver()
    _fly(obs, drag=0.9, wind=(1.0, -0.5), err=math.radians(7.0), seconds=60.0, gps=True)
    m = obs.model()
    assert m is not None
    assert m.drag_per_s == pytest.approx(0.9, abs=0.1)
    assert m.push_ne_m_s2 == pytest.approx((0.9, -0.45), abs=0.15)
    assert math.degrees(m.heading_error_rad) == pytest.approx(7.0, abs=1.5)


def test_without_gps_the_model_holds_the_velocity() -> None:
    err = math.radians(7.0)
    obs = EgoVelocityObserver()
    _fly(obs, drag=0.9, wind=(1.0, -0.5), err=err, seconds=60.0, gps=True)
    # Then without GPS (from rest): the observer sees the attitude only.
    truth2, seen = _fly(obs, drag=0.9, wind=(1.0, -0.5), err=err, seconds=10.0, gps=False)
    errors = [
        math.hypot(o[0] - v[0], o[1] - v[1]) for v, o in zip(truth2, seen, strict=True) if o is not None
    ]
    assert len(errors) == len(truth2)
    assert max(errors) < 0.3  # where dead-reckoning on the accelerometers ran off by 1-2 m/s


def test_without_gps_the_vertical_is_the_autopilots_barometric_one() -> None:
    # Height stays aided by the barometer after a GPS loss: its vertical velocity is passed through; one
    # missing or not finite holds the last known.
    obs = EgoVelocityObserver()
    _fly(obs, drag=0.9, wind=(1.0, -0.5), err=0.0, seconds=60.0, gps=True)
    R = np.eye(3)
    out = obs.step(60.0, R, np.zeros(3), 0.4)
    assert out is not None
    assert out[2] == pytest.approx(0.4)
    held = obs.step(60.05, R, np.zeros(3), math.nan)
    assert held is not None
    assert held[2] == pytest.approx(0.4)
    none = obs.step(60.1, R, np.zeros(3))
    assert none is not None
    assert none[2] == pytest.approx(0.4)


def test_no_model_from_a_hover_and_none_offered() -> None:
    obs = EgoVelocityObserver()
    R = np.eye(3)
    for i in range(400):
        obs.learn(i * DT_S, np.array([0.01, 0.0, 0.0]), R)
    assert obs.model() is None
    assert obs.step(30.0, R, np.zeros(3)) is None


def test_non_finite_samples_are_ignored() -> None:
    obs = EgoVelocityObserver()
    obs.learn(0.0, np.array([math.nan, 0.0, 0.0]), np.eye(3))
    obs.learn(0.3, np.array([0.0, math.inf, 0.0]), np.eye(3))
    assert obs.model() is None


def test_a_tilted_flight_trusts_its_heading_fit_and_a_nearly_level_one_does_not() -> None:
    tilted = EgoVelocityObserver()
    _fly(tilted, drag=0.9, wind=(1.0, -0.5), err=math.radians(7.0), seconds=60.0, gps=True)
    m = tilted.model()
    assert m is not None
    assert m.heading_trusted
    assert math.degrees(m.heading_sigma_rad) < 1.0
    level = EgoVelocityObserver()
    _fly(level, drag=0.02, wind=(0.0, 0.0), err=math.radians(7.0), seconds=20.0, gps=True)
    m2 = level.model()
    assert m2 is None or not m2.heading_trusted


def test_a_heading_error_within_its_noise_is_not_trusted() -> None:
    obs = EgoVelocityObserver()
    _fly(obs, drag=0.9, wind=(1.0, -0.5), err=0.0, seconds=60.0, gps=True)
    m = obs.model()
    assert m is not None
    assert abs(math.degrees(m.heading_error_rad)) < 1.0
    assert not m.heading_trusted
