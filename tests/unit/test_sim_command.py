"""``companion sim``'s pure parts: seeds, overrides, child command lines, the Monte Carlo page, ego-motion."""

from __future__ import annotations

import asyncio
import io
import math
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from companion.config import Config
from companion.kernel.errors import ConfigError
from companion.lab.evaluation import campaign
from companion.lab.evaluation.campaign import (
    RunSpec,
    child_args,
    effective_scenario,
    parse_overrides,
    parse_seeds,
)
from companion.lab.evaluation.campaign_summary import monte_carlo_markdown
from companion.lab.evaluation.procs import SitlPorts
from companion.lab.evaluation.progress import ProgressLine
from companion.lab.evaluation.realpath import sitl_environment
from companion.lab.evaluation.setup import (
    all_scenarios,
    leader_spawn_ned_m,
    scenario_path,
    service_config,
    sitl_config,
)
from companion.mission.ego import EgoMotion


def test_parse_seeds_ranges_and_lists() -> None:
    assert parse_seeds("1-50") == list(range(1, 51))
    assert parse_seeds("3,7, 9") == [3, 7, 9]
    assert parse_seeds("5") == [5]
    assert parse_seeds("1-2,8") == [1, 2, 8]
    for bad in ("", "a-b", "5-", "-3"):
        with pytest.raises(ConfigError):
            parse_seeds(bad)


def test_parse_overrides_nests_and_parses_toml() -> None:
    got = parse_overrides(["formation.kp_xy=1.5", "detector.runtime=truth", "a.b.c=[1, 2]"])
    assert got == {"formation": {"kp_xy": 1.5}, "detector": {"runtime": "truth"}, "a": {"b": {"c": [1, 2]}}}
    with pytest.raises(ConfigError):
        parse_overrides(["no_equals"])


def test_all_scenarios_paper_first_and_at_least_eight() -> None:
    names = all_scenarios()
    assert names[:4] == ["straight", "circle", "gps-loss", "visibility"]
    assert {"figure8", "leader-occluded", "link-loss", "wind"} <= set(names)
    assert scenario_path("gps-loss-land").exists()  # variants resolve too


def test_the_join_scenarios_spawn_the_leader_off_the_slot_on_both_harnesses() -> None:
    cfg = Config()
    offset = effective_scenario(scenario_path("join"), None).run.leader_spawn_offset_m
    assert offset == (4.0, 2.5)
    assert effective_scenario(scenario_path("straight"), None).run.leader_spawn_offset_m == (0.0, 0.0)
    assert leader_spawn_ned_m(cfg) == (5.0, 0.0, 0.0)  # the slot, 5 m ahead of a follower facing north
    want = (9.0, 2.5, 0.0)
    assert leader_spawn_ned_m(cfg, offset) == want
    lockstep = {v.role: v.spawn_ned_m for v in sitl_config(cfg, offset_ne_m=offset).vehicles}
    assert lockstep["leader"] == want
    assert lockstep["follower"] == (0.0, 0.0, 0.0)
    base = [v.model_dump(mode="json") for v in sitl_config(cfg).vehicles]
    env = sitl_environment(cfg, SitlPorts(20000), base, offset)
    real = {v["role"]: tuple(v["spawn_ned_m"]) for v in tomllib.loads("v = " + env["SITL_VEHICLES"])["v"]}
    assert real == lockstep


def test_duration_reshapes_the_formation_window() -> None:
    sc = effective_scenario(scenario_path("straight"), 15.0)
    assert sc.run.formation_duration_s == 15.0
    assert math.isclose(sc.run.duration_s, sc.run.formation_start_s + 15.0 + 2.0)
    full = effective_scenario(scenario_path("straight"), None)
    assert full.run.formation_duration_s >= 60.0  # the issue: at least 60 s of formation
    with pytest.raises(ConfigError):
        effective_scenario(scenario_path("straight"), -1.0)


def test_child_args_round_trip_the_spec(tmp_path: object) -> None:
    spec = RunSpec("circle", 4, tmp_path / "c", harness="lockstep", detector="truth", duration_s=9.0,  # type: ignore[operator]
                   plots=False, overrides=("formation.kp_xy=2",))  # fmt: skip
    args = child_args(spec)
    assert args[args.index("--scenario") + 1] == "circle"
    assert args[args.index("--harness") + 1] == "lockstep"
    assert args[args.index("--detector") + 1] == "truth"
    assert "--no-plots" in args
    assert args[args.index("--set") + 1] == "formation.kp_xy=2"


def test_monte_carlo_page_has_outcomes_and_percentiles() -> None:
    stats = {"min": 0.05, "p5": 0.1, "p50": 0.2, "p95": 0.3, "max": 0.4}
    md = monte_carlo_markdown(
        {
            "scenario": "gps-loss",
            "runs": 3,
            "harness": "lockstep",
            "outcomes": {"completed": 2, "landed_safely": 1},
            "relative_position_rmse_m": stats,
            "wall_s": 12.0,
            "failed": [],
        }
    )
    assert "| completed | 2 |" in md
    assert "| relative_position_rmse_m | 0.050 | 0.100 | 0.200 | 0.300 | 0.400 |" in md
    assert "| formation_rmse_m | n/a |" in md


def test_ego_motion_brings_an_old_estimate_to_now() -> None:
    """Follower accelerating at 1 m/s^2 north, leader at a constant 2 m/s north."""
    ego = EgoMotion()
    for k in range(41):
        t = k * 0.025
        ego.push(t, np.array([1.0 * t, 0.0, 0.0]))
    stamp, now = 0.5, 1.0
    p_f = lambda t: 0.5 * t * t  # noqa: E731
    p_rel_stamp = np.array([5.0 + 2.0 * stamp - p_f(stamp), 0.0, 0.0])
    v_rel_stamp = np.array([2.0 - stamp, 0.0, 0.0])
    rel = ego.predict(stamp, p_rel_stamp, v_rel_stamp, now)
    assert rel.v_ned_leader_m_s is not None
    assert np.allclose(rel.v_ned_leader_m_s, [2.0, 0.0, 0.0])
    assert np.allclose(rel.p_ned_rel_m, [5.0 + 2.0 * now - p_f(now), 0.0, 0.0], atol=1e-3)
    assert np.allclose(rel.v_ned_rel_m_s, [2.0 - now, 0.0, 0.0], atol=1e-9)


def test_ego_motion_without_history_flies_the_estimate_as_captured() -> None:
    rel = EgoMotion().predict(1.0, np.array([5.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0]), 1.2)
    assert rel.v_ned_leader_m_s is None
    assert np.allclose(rel.p_ned_rel_m, [5.0, 0.0, 0.0])
    assert np.allclose(rel.v_ned_rel_m_s, [1.0, 0.0, 0.0])


def test_ego_motion_carries_the_leader_acceleration_over_the_age() -> None:
    ego = EgoMotion()
    for k in range(41):
        ego.push(k * 0.025, np.zeros(3))
    rel = ego.predict(0.8, np.array([5.0, 0.0, 0.0]), np.zeros(3), 1.0, a_leader=np.array([1.0, 0.0, 0.0]))
    assert rel.v_ned_rel_m_s[0] == pytest.approx(0.2)
    assert rel.p_ned_rel_m[0] == pytest.approx(5.0 + 0.5 * 0.04)


def test_all_flies_the_real_path_alone_then_the_lockstep_runs_side_by_side(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A lockstep run beside a real-time one delayed its follower (straight 0.353 m against 0.247 m alone)."""
    running: set[str] = set()
    seen: list[tuple[str, frozenset[str]]] = []

    async def fake_child(child: Any, env: Any, line: Any, children: Any) -> None:
        running.add(child.name)
        seen.append((child.name, frozenset(running)))
        await asyncio.sleep(0.01)
        running.discard(child.name)
        child.done = True

    monkeypatch.setattr(campaign, "_run_child", fake_child)
    specs = [
        RunSpec(name, 1, tmp_path / name, harness=harness)  # type: ignore[arg-type]
        for name, harness in (
            ("straight", "real"),
            ("figure8", "lockstep"),
            ("circle", "real"),
            ("wind", "lockstep"),
            ("link-loss", "lockstep"),
        )
    ]
    line = ProgressLine(io.StringIO(), len(specs))
    asyncio.run(campaign._run_children(specs, 2, line, {}))
    order = [name for name, _ in seen]
    assert order[:2] == ["straight", "circle"]  # the real path first, one at a time
    assert all(others == {name} for name, others in seen if name in ("straight", "circle"))
    lockstep_together = [others for name, others in seen if name not in ("straight", "circle")]
    assert max(len(o) for o in lockstep_together) == 2  # then two lockstep runs side by side


def test_a_runs_folder_keeps_its_seed_and_flies_it_again(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``--seed 2`` is the seed in the run's scenario.toml, and that file alone flies seed 2 again."""
    from companion.cli import main
    from companion.lab.evaluation import setup
    from sitl.world.scenario import load_scenario

    class WrittenError(Exception):
        pass

    def stop_after_the_scenario_file(*_args: object, **_kw: object) -> None:
        raise WrittenError  # the run's folder has its scenario.toml: nothing more is needed here

    with monkeypatch.context() as m:
        m.setattr(setup, "service_config", stop_after_the_scenario_file)
        with pytest.raises(WrittenError):
            campaign.run_one(RunSpec("formation-v", 2, tmp_path / "run", harness="lockstep"))
    run_file = tmp_path / "run" / "scenario.toml"
    assert load_scenario(run_file).seed == 2
    assert load_scenario(scenario_path("formation-v")).seed == 1  # the shipped file's own

    flown: list[RunSpec] = []

    def fake_run_one(spec: RunSpec, progress: object = None) -> dict[str, Any]:
        flown.append(spec)
        return {"scenario": "formation-v", "outcome": "completed", "relative_position_rmse_m": None,
                "formation_max_deviation_m": None}  # fmt: skip

    monkeypatch.setattr(campaign, "run_one", fake_run_one)
    argv = ["sim", "--scenario", str(run_file), "--harness", "lockstep", "--out", str(tmp_path / "again")]
    assert main(argv) == 0
    assert [s.seed for s in flown] == [2]  # no --seed: the file's
    assert main([*argv, "--seed", "5"]) == 0
    assert [s.seed for s in flown] == [2, 5]


def test_a_run_finds_the_shipped_weights_from_any_folder(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    cfg = service_config({})
    model = Path(cfg.detector.model_path)
    assert model.is_absolute()
    assert model == (Path(__file__).resolve().parents[2] / "models" / "leader_detector.pt")
    assert cfg.formation.plan == ""  # nothing named, nothing resolved


def test_px4_runs_alone_even_when_every_run_is_real(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``all --autopilot px4`` is four real-path runs: two at once raced for the same free PX4 ports."""
    running: set[str] = set()
    most = [0]

    async def fake_child(child: Any, env: Any, line: Any, children: Any) -> None:
        running.add(child.name)
        most[0] = max(most[0], len(running))
        await asyncio.sleep(0.01)
        running.discard(child.name)
        child.done = True

    monkeypatch.setattr(campaign, "_run_child", fake_child)
    specs = [
        RunSpec(name, 1, tmp_path / name, harness="real", autopilot="px4")  # type: ignore[arg-type]
        for name in ("straight", "circle", "gps-loss", "visibility")
    ]
    asyncio.run(campaign._run_children(specs, 2, ProgressLine(io.StringIO(), len(specs)), {}))
    assert most[0] == 1


def test_jobs_with_px4_is_refused_in_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    from companion.cli import main

    with pytest.raises(SystemExit) as exc:
        main(["sim", "--scenario", "straight", "--seeds", "1-2", "--autopilot", "px4", "--jobs", "2"])
    assert "one run at a time" in str(exc.value)
    assert "\n" not in str(exc.value)


def test_a_campaign_page_lists_each_seed_with_the_hosts_verdict() -> None:
    stats = {"min": 0.1, "p5": 0.1, "p50": 0.2, "p95": 0.3, "max": 0.3}
    md = monte_carlo_markdown(
        {
            "scenario": "circle",
            "runs": 2,
            "harness": "real",
            "outcomes": {"completed": 2},
            "formation_max_deviation_m": stats,
            "wall_s": 190.0,
            "failed": [],
            "runs_by_seed": {
                "seed-001": {"outcome": "completed", "relative_position_rmse_m": 0.31,
                             "formation_max_deviation_m": 0.55, "host": {"starved_because": []}},
                "seed-002": {"outcome": "completed", "relative_position_rmse_m": 0.40,
                             "formation_max_deviation_m": 1.9,
                             "host": {"starved_because": ["other work took 40% of the machine"]}},
            },
        }
    )  # fmt: skip
    assert "| seed-001 | completed | 0.310 | 0.550 | ok |" in md
    assert "| seed-002 | completed | 0.400 | 1.900 | starved: other work took 40% of the machine |" in md
    assert "Runs the host starved: 1 of 2." in md
