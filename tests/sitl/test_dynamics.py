"""The JSBSim airframe: quiet, sits on its legs, hovers at the documented thrust, drifts with wind."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import pytest

from sitl.physics.dynamics import QUAD, QuadDynamics
from sitl.physics.geo import LocalProjection

REPO = Path(__file__).resolve().parents[2]
WORLD = LocalProjection(47.397742, 8.545594, 488.0)


def test_jsbsim_prints_nothing() -> None:
    code = (
        "from sitl.physics.dynamics import QuadDynamics; from sitl.physics.geo import LocalProjection;"
        "d = QuadDynamics(LocalProjection(47.0, 8.0, 400.0), (0.0, 0.0, 0.0), 0.0, 0.004);"
        "[d.step(0.5, 0.5, 0.5, 0.5) for _ in range(500)]"
    )
    r = subprocess.run(
        [sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60, check=False
    )
    assert r.returncode == 0, r.stderr
    assert r.stdout == ""
    assert r.stderr == ""


def test_rests_on_its_legs_and_hovers_at_hover_thrust() -> None:
    d = QuadDynamics(WORLD, (3.0, -2.0, 0.0), math.radians(30.0), 0.004)
    for _ in range(500):
        d.step(0.0, 0.0, 0.0, 0.0)
    n, e, down, *_ = d.kinematics()
    assert (n, e) == pytest.approx((3.0, -2.0), abs=1e-3)
    assert -down == pytest.approx(QUAD.rest_height_m, abs=0.005)
    assert d.yaw_rad == pytest.approx(math.radians(30.0), abs=1e-3)
    u = QUAD.hover_thrust
    for _ in range(250 * 2):
        d.step(u + 0.03, u + 0.03, u + 0.03, u + 0.03)  # lift off
    *_, v0 = d.kinematics()
    for _ in range(250 * 8):
        d.step(u, u, u, u)
    *_, down, _, _, vd = d.kinematics()
    # At hover thrust only drag acts vertically: the climb decays (linear drag 0.2 N/(m/s) on
    # 1.5 kg, a 7.5 s time constant) and the vehicle neither falls nor keeps accelerating.
    assert v0 < -0.3
    assert v0 < vd < 0.0
    assert vd == pytest.approx(v0 * math.exp(-8.0 / 7.5), abs=0.12)
    assert -down > 1.0


def test_wind_pushes_a_hovering_quad_downwind() -> None:
    d = QuadDynamics(WORLD, (0.0, 0.0, 0.0), 0.0, 0.004)
    u = QUAD.hover_thrust + 0.05
    for _ in range(250):
        d.step(u, u, u, u)
    d.set_wind_ned(0.0, 5.0, 0.0)  # air moving east
    for _ in range(500):
        d.step(u, u, u, u)
    *_, ve, _ = d.kinematics()
    assert ve > 0.3
