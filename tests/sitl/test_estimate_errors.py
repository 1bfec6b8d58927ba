"""The PX4 profile's estimate errors: GPS's velocity wander, carried by the estimate the autopilot flies."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from companion.lab.evaluation.campaign import effective_scenario
from sitl.autopilot.estimator import Estimator
from sitl.config import SitlConfig
from sitl.physics.geo import LocalProjection
from sitl.physics.gps import GpsNoise, GpsSensor
from sitl.world.lockstep import gps_noise

REPO = Path(__file__).resolve().parents[2]
PROJ = LocalProjection(47.397742, 8.545594, 488.0)
DT_S = 0.02


def _fly_straight(noise: GpsNoise, seconds: float = 400.0) -> tuple[np.ndarray, np.ndarray]:
    """GPS's and the estimate's horizontal velocity errors (m/s, one row per 50 Hz tick after 20 s)."""
    gps = GpsSensor(PROJ, np.random.default_rng(1), noise=noise)
    est = Estimator(PROJ, np.random.default_rng(2))
    v = (3.0, 0.0, 0.0)
    gps_err: list[tuple[float, float]] = []
    est_err: list[tuple[float, float]] = []
    for k in range(int(seconds / DT_S)):
        t = k * DT_S
        p = (3.0 * t, 0.0, -10.0)
        fix = gps.sample(t, p, v)
        est.update(t, DT_S, p_local_true_m=p, v_true_m_s=v, gps=fix, vision=None)
        if t > 20.0:
            if fix is not None:
                gps_err.append((fix.vn_m_s - v[0], fix.ve_m_s - v[1]))
            est_err.append((est.vn_m_s - v[0], est.ve_m_s - v[1]))
    return np.array(gps_err), np.array(est_err)


def _one_over_e_s(x: np.ndarray, dt_s: float) -> float:
    x = x - x.mean()
    ac = np.correlate(x, x, "full")[len(x) - 1 :]
    return float(np.argmax(ac / ac[0] < math.exp(-1.0))) * dt_s


def test_gps_velocity_wander_has_its_sigma_and_time_constant_and_the_estimate_carries_it() -> None:
    gps_err, est_err = _fly_straight(GpsNoise(vel_bias_m_s=0.25, vel_bias_tau_s=3.5))
    sigma = np.sqrt((gps_err**2).mean(axis=0))
    assert np.all((sigma > 0.18) & (sigma < 0.33)), sigma
    assert 2.0 < _one_over_e_s(gps_err[:, 1], 0.1) < 5.5
    # The autopilot flies its estimate: PX4 SITL's is 0.18-0.26 m/s RMS per axis off SIH's truth.
    est_rms = np.sqrt((est_err**2).mean(axis=0))
    assert np.all((est_rms > 0.15) & (est_rms < 0.3)), est_rms


def test_without_the_wander_the_gps_velocity_error_is_white_and_the_estimate_close() -> None:
    gps_err, est_err = _fly_straight(GpsNoise())
    assert _one_over_e_s(gps_err[:, 1], 0.1) <= 0.2
    assert np.all(np.sqrt((est_err**2).mean(axis=0)) < 0.06)


def test_the_px4_profile_turns_the_wander_on_for_every_vehicle_and_the_default_world_does_not() -> None:
    sc = effective_scenario(
        REPO / "config/scenarios/straight.toml", None, REPO / "config/timing/px4-sih.toml"
    )
    world = sc.world_config(SitlConfig().world)
    assert world.gps_velocity_wander_m_s == 0.25
    noise = gps_noise(SitlConfig().model_copy(update={"world": world}), GpsNoise())
    assert (noise.vel_bias_m_s, noise.vel_bias_tau_s) == (0.25, 3.5)
    assert gps_noise(SitlConfig(), GpsNoise()) == GpsNoise()
