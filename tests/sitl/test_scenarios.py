"""Scenario files, trajectories, wind and link faults: the pure pieces a scenario is made of."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from companion.kernel.errors import ConfigError
from sitl.physics.wind import WindModel, WindParams
from sitl.world.links import LinkFaults
from sitl.world.scenario import LinkSpec, LinkWindowSpec, Scenario, load_scenario
from sitl.world.trajectory import Circle, FigureEight, SpeedProfile, Straight, Waypoints

REPO = Path(__file__).resolve().parents[2]
SCENARIOS = sorted((REPO / "config" / "scenarios").glob("*.toml"))
NAMES = {"straight", "circle", "gps-loss", "visibility", "figure8", "leader-occluded", "link-loss", "wind"}


def test_the_eight_evaluation_scenarios_exist() -> None:
    assert {p.stem for p in SCENARIOS} == NAMES


@pytest.mark.parametrize("path", SCENARIOS, ids=lambda p: p.stem)
def test_scenario_loads_and_has_a_minute_of_formation(path: Path) -> None:
    sc = load_scenario(path)
    assert sc.name == path.stem
    assert sc.run.formation_duration_s >= 60.0
    assert sc.leader.type != "none"
    assert sc.leader.start_s <= sc.run.formation_start_s
    assert sc.leader.trajectory() is not None


def test_scenario_specifics() -> None:
    by = {p.stem: load_scenario(p) for p in SCENARIOS}
    assert by["straight"].leader.speed_m_s == 2.0
    assert (by["circle"].leader.radius_m, by["circle"].leader.speed_m_s) == (15.0, 3.0)
    loss = by["gps-loss"]
    assert loss.gps_loss_s is not None
    assert (
        loss.run.formation_start_s
        < loss.gps_loss_s
        < loss.run.formation_start_s + loss.run.formation_duration_s
    )
    assert by["visibility"].visual["leader_distance_m"] == [8.0, 12.0]
    windows = by["link-loss"].faults("follower").link.windows
    assert any(w.loss == pytest.approx(0.3) for w in windows)
    wind = by["wind"].wind
    assert wind.mean_speed_m_s + wind.gust_max_m_s == pytest.approx(8.0)
    assert by["straight"].gps_loss_s is None


def test_unknown_keys_are_errors_except_in_visual(tmp_path: Path) -> None:
    p = tmp_path / "s.toml"
    p.write_text('name = "x"\n[leader]\ntype = "straight"\nspeeed_m_s = 2.0\n[visual]\nanything = 1\n')
    with pytest.raises(ConfigError) as err:
        load_scenario(p)
    assert err.value.problems == ["leader.speeed_m_s: unknown key"]
    p.write_text('name = "x"\n[visual]\nanything = { nested = [1, 2] }\n')
    assert load_scenario(p).visual == {"anything": {"nested": [1, 2]}}


def test_formation_window_must_fit_the_run() -> None:
    with pytest.raises(ValueError, match="exceeds duration_s"):
        Scenario.model_validate({"name": "x", "run": {"duration_s": 60, "formation_duration_s": 60}})


@pytest.mark.parametrize(
    "traj",
    [
        Straight(SpeedProfile(2.0), 0.3),
        Circle(SpeedProfile(3.0), 15.0, 0.0, clockwise=True),
        Circle(SpeedProfile(3.0), 15.0, 1.0, clockwise=False),
        FigureEight(SpeedProfile(2.5), 10.0, 0.0),
        Waypoints(SpeedProfile(2.0), ((0.0, 0.0), (20.0, 0.0), (20.0, 20.0)), loop=True),
    ],
    ids=["straight", "circle-cw", "circle-ccw", "figure8", "waypoints"],
)
def test_trajectory_velocity_is_the_derivative_of_position(traj: object) -> None:
    dt = 1e-3
    for tau in np.linspace(0.0, 90.0, 181):
        n0, e0, *_ = traj.sample(tau)  # type: ignore[attr-defined]
        n1, e1, vn, ve, heading = traj.sample(tau + dt)  # type: ignore[attr-defined]
        speed = math.hypot(vn, ve)
        if isinstance(traj, Waypoints) and math.hypot((n1 - n0) / dt - vn, (e1 - e0) / dt - ve) > 0.1:
            continue  # a corner falls inside this dt
        assert (n1 - n0) / dt == pytest.approx(vn, abs=0.05)
        assert (e1 - e0) / dt == pytest.approx(ve, abs=0.05)
        if speed > 0.1:
            assert math.atan2(ve, vn) == pytest.approx(
                math.atan2(math.sin(heading), math.cos(heading)), abs=1e-6
            )
    assert traj.sample(0.0)[:2] == pytest.approx((0.0, 0.0), abs=1e-9)  # type: ignore[attr-defined]


def test_figure_eight_returns_through_its_anchor() -> None:
    f = FigureEight(SpeedProfile(2.5, accel_m_s2=100.0), 10.0)
    lap_s = 2 * math.pi * 10.0 / 2.5
    for k in (1, 2, 3):
        n, e, *_ = f.sample(k * lap_s)
        assert math.hypot(n, e) < 0.05


def test_wind_is_seeded_and_gusts_stay_under_the_peak() -> None:
    params = WindParams(mean_speed_m_s=2.0, from_deg=270.0, gust_max_m_s=6.0, gust_interval_s=5.0)
    a = WindModel(params, np.random.default_rng(3))
    b = WindModel(params, np.random.default_rng(3))
    speeds = []
    for k in range(1, 6000):
        t = k * 0.02
        wa, wb = a.sample(t), b.sample(t)
        assert wa == wb
        speeds.append(math.hypot(wa[0], wa[1]))
    assert max(speeds) <= 8.0 + 1e-9
    assert max(speeds) > 5.0  # gusts do come
    assert np.mean([a.sample(200.0 + k * 0.02)[1] for k in range(10)]) > 1.5  # from the west: blows east


def test_link_faults_cut_loss_and_latency() -> None:
    spec = LinkSpec(
        latency_ms=10.0,
        windows=(
            LinkWindowSpec(start_s=10.0, end_s=20.0, loss=0.3, latency_ms=50.0),
            LinkWindowSpec(start_s=30.0, end_s=31.0, cut=True),
        ),
    )
    f = LinkFaults(spec, np.random.default_rng(0))
    assert f.delay_s(5.0) == pytest.approx(0.010)
    assert all(f.delay_s(30.5) is None for _ in range(100))
    inside = [f.delay_s(15.0) for _ in range(4000)]
    lost = sum(d is None for d in inside) / len(inside)
    assert lost == pytest.approx(0.3, abs=0.03)
    assert all(d == pytest.approx(0.050) for d in inside if d is not None)


def test_gps_sensor_outages_stuck_wrong_and_jumps() -> None:
    from sitl.physics.geo import LocalProjection
    from sitl.physics.gps import GpsFailure, GpsJump, GpsOutage, GpsSensor

    world = LocalProjection(47.0, 8.0, 400.0)
    gps = GpsSensor(
        world,
        np.random.default_rng(0),
        outages=(GpsOutage(10.0, 12.0, GpsFailure.OFF), GpsOutage(20.0, None, GpsFailure.STUCK)),
        jumps=(GpsJump(5.0, 1.0, (30.0, 0.0, 0.0)),),
    )
    fixes = {}
    for k in range(1, 300):
        t = k * 0.1
        s = gps.sample(t, (t, 0.0, -5.0), (1.0, 0.0, 0.0))
        fixes[round(t, 1)] = None if s is None else world.to_ned(s.lat_deg, s.lon_deg, s.alt_m)
    assert fixes[4.0][0] == pytest.approx(4.0, abs=1.5)
    assert fixes[5.5][0] == pytest.approx(35.5, abs=1.5)  # the 30 m jump
    assert all(fixes[round(10.0 + 0.1 * i, 1)] is None for i in range(1, 20))  # off
    assert fixes[12.5] is not None
    assert fixes[25.0] == fixes[28.0]  # stuck: the same fix over and over
    gps.injected = GpsFailure.WRONG
    s = gps.sample(40.0, (40.0, 0.0, -5.0), (0.0, 0.0, 0.0))
    assert s is not None
    assert world.to_ned(s.lat_deg, s.lon_deg, s.alt_m)[0] == pytest.approx(160.0, abs=1.5)


def test_link_loss_scenario_cuts_and_bursts_reach_the_client() -> None:
    from sitl.config import SitlConfig
    from sitl.world.lockstep import World

    sc = Scenario.model_validate(
        {
            "name": "links",
            "vehicles": {
                "follower": {
                    "link": {
                        "latency_ms": 20.0,
                        "windows": [
                            {"start_s": 4.0, "end_s": 8.0, "cut": True},
                            {"start_s": 10.0, "end_s": 20.0, "loss": 0.3},
                        ],
                    }
                }
            },
        }
    )
    world = World(SitlConfig(), sc, seed=1)
    link = world.link("follower")
    got: list[tuple[float, str]] = []
    while world.t_s < 20.0:
        world.step()
        got.extend((world.t_s, m.get_type()) for m in link.receive())
    att = [t for t, kind in got if kind == "ATTITUDE"]
    assert not [t for t in att if 4.03 <= t < 8.0]  # nothing through the cut (after in-flight ones)
    before = sum(1 for t in att if 0.0 < t < 4.0) / 4.0
    burst = sum(1 for t in att if 10.0 <= t < 20.0) / 10.0
    assert before == pytest.approx(100.0, rel=0.05)  # PX4's 100 Hz ATTITUDE on the API link
    assert burst == pytest.approx(70.0, rel=0.1)  # 30 % lost
    assert min(att) >= 0.02  # 20 ms latency
    assert link.dropped_out > 0


def test_shipped_sitl_config_documents_the_defaults() -> None:
    from sitl.config import SitlConfig, load_sitl_config

    assert load_sitl_config(REPO / "config" / "sitl.toml", environ={}) == SitlConfig()
