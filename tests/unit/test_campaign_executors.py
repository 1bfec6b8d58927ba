"""The campaign executors' pure parts: progress and ETA, ``--resume``, the summary, a run's files, errors."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from companion.cli import main as companion_main
from companion.lab.evaluation.campaign import RunSpec, SimError, split_done
from companion.lab.evaluation.campaign_summary import (
    campaign_summary,
    monte_carlo_markdown,
    write_campaign_summary,
)
from companion.lab.evaluation.progress import RunPace, clock_text, eta_from_lengths, eta_s, progress_text
from companion.lab.evaluation.ray_executor import (
    RayOptions,
    RunFailedError,
    error_line,
    run_campaign,
    write_run_files,
)


def _report(seed: int, rmse_m: float, outcome: str = "completed") -> dict[str, Any]:
    return {
        "seed": seed,
        "outcome": outcome,
        "relative_position_rmse_m": rmse_m,
        "relative_yaw_rmse_deg": 0.2,
        "formation_rmse_m": 0.1,
        "formation_max_deviation_m": 0.5,
        "min_separation_m": 4.6,
        "min_obstacle_clearance_m": 30.0,
        "detection_recall": 0.95,
        "detector": "ground-truth boxes (NOT the network)",
    }


def _specs(root: Path, seeds: list[int]) -> list[RunSpec]:
    return [RunSpec("straight", s, root / f"seed-{s:03d}", harness="lockstep") for s in seeds]


def test_eta_is_the_throughput_so_far() -> None:
    assert eta_s(0, 8, 30.0) is None
    assert eta_s(2, 8, 30.0) == pytest.approx(90.0)
    assert eta_s(8, 8, 120.0) == 0.0


def _demo_etas(real_pace: float, lock_pace: float, jobs: int = 2) -> tuple[list[float], list[float], float]:
    """The demo's eight runs flown on a 1 s clock: (ETA by lengths + elapsed, ETA by counts + elapsed, total).

    The real path's four one at a time, then the lockstep four ``jobs`` at a time, each run taking its
    length times its lane's pace in wall seconds.
    """
    real = [88.0, 88.0, 98.0, 88.0]  # straight, circle, gps-loss, visibility
    lock = [88.0, 90.0, 88.0, 88.0]
    runs = [("real", x, real_pace) for x in real] + [("lockstep", x, lock_pace) for x in lock]
    # When each run starts and ends on this schedule.
    start, end, t = {}, {}, 0.0
    for i in range(4):
        start[i], end[i] = t, t + real[i] * real_pace
        t = end[i]
    free = [t] * jobs
    for i in range(4, 8):
        k = free.index(min(free))
        start[i], end[i] = free[k], free[k] + runs[i][1] * lock_pace
        free[k] = end[i]
    total = max(end.values())
    by_lengths, by_counts = [], []
    now = 1.0
    while now < total - 1.0:
        paces = []
        for i, (lane, length, pace) in enumerate(runs):
            started, done = start[i] <= now, end[i] <= now
            flown = min(length, max(0.0, (now - start[i]) / pace))
            wall = (end[i] if done else now) - start[i] if started else 0.0
            paces.append(RunPace(lane, length, length if done else flown, wall, started, done))
        by_lengths.append(now + eta_from_lengths(paces, jobs))
        done_n = sum(p.done for p in paces)
        eta = eta_s(done_n, 8, now)
        if eta is not None:
            by_counts.append(now + eta)
        now += 1.0
    return by_lengths, by_counts, total


def test_the_eta_comes_from_the_scenarios_lengths() -> None:
    """The demo's progress line: the ETA by run counts climbed while a long run flew (20 min for a 7-min
    campaign); the one by the scenarios' lengths stays near the truth from the start."""
    for real_pace, lock_pace in ((1.15, 0.45), (1.3, 0.3), (1.05, 0.6)):
        by_lengths, by_counts, total = _demo_etas(real_pace, lock_pace)
        assert 0.85 * total < min(by_lengths) <= max(by_lengths) < 1.15 * total, (real_pace, lock_pace)
    _, by_counts, total = _demo_etas(1.15, 0.45)
    assert max(by_counts) > 1.3 * total  # what it replaces: the count of runs, blind to their lengths


def test_clock_text() -> None:
    assert clock_text(0.4) == "0:00"
    assert clock_text(83.0) == "1:23"
    assert clock_text(3723.0) == "1:02:03"


def test_progress_text_has_done_total_failures_and_eta() -> None:
    text = progress_text(3, 1, 8, ["5 to go on 2 CPUs"], 60.0, label="sim[ray]")
    assert text == "sim[ray]: 3/8 done, 1 failed | 5 to go on 2 CPUs | 1:00, ETA 1:40"
    assert progress_text(0, 0, 2, [], 5.0) == "sim: 0/2 done | - | 0:05"
    assert progress_text(2, 0, 2, [], 50.0) == "sim: 2/2 done | - | 0:50"


def test_resume_skips_the_seeds_with_a_report(tmp_path: Path) -> None:
    specs = _specs(tmp_path, [1, 2, 3])
    specs[1].out_dir.mkdir()
    (specs[1].out_dir / "report.json").write_text("{}")
    (specs[2].out_dir).mkdir()  # a folder without a report: an interrupted run, flown again
    todo, done = split_done(specs, resume=True)
    assert [s.seed for s in todo] == [1, 3]
    assert [s.seed for s in done] == [2]
    assert split_done(specs, resume=False) == (specs, [])


def test_the_summary_lists_failures_and_counts_only_reported_runs(tmp_path: Path) -> None:
    specs = _specs(tmp_path, [1, 2, 3])
    reports = {"seed-001": _report(1, 0.03), "seed-003": _report(3, 0.05)}
    summary = campaign_summary(
        specs, reports, ["seed-002: ConfigError: bad"], wall_s=12.34, executor="ray", resumed=1
    )
    assert summary["seeds"] == [1, 2, 3]
    assert summary["runs"] == 2
    assert summary["failed"] == ["seed-002: ConfigError: bad"]
    assert summary["executor"] == "ray"
    assert summary["resumed"] == 1
    assert summary["wall_s"] == 12.3
    assert sorted(summary["runs_by_seed"]) == ["seed-001", "seed-003"]
    md = monte_carlo_markdown(summary)
    assert "Runs without a report: seed-002: ConfigError: bad" in md
    assert "Wall time: 12 s (ray executor); 1 seeds' reports kept from an earlier run." in md


def test_the_summary_is_rebuilt_from_every_seeds_report_in_seed_order(tmp_path: Path) -> None:
    specs = _specs(tmp_path, [1, 2])
    for s, rmse in zip(specs, (0.03, 0.04), strict=True):
        s.out_dir.mkdir()
        (s.out_dir / "report.json").write_text(json.dumps(_report(s.seed, rmse)))
    summary = write_campaign_summary([specs[1], specs[0]], tmp_path, failed=[], wall_s=1.0, executor="local")
    assert summary["seeds"] == [1, 2]
    assert summary["relative_position_rmse_m"]["max"] == 0.04
    assert json.loads((tmp_path / "summary.json").read_text()) == summary
    assert (tmp_path / "summary.md").read_text().startswith("# Monte Carlo: `straight`, 2 seeds")


def test_a_fully_resumed_ray_campaign_writes_the_summary_without_ray(tmp_path: Path) -> None:
    specs = _specs(tmp_path, [4])
    specs[0].out_dir.mkdir()
    (specs[0].out_dir / "report.json").write_text(json.dumps(_report(4, 0.02)))
    summary = run_campaign([], tmp_path, options=RayOptions(), stream=sys.stderr, already_done=specs)
    assert summary["runs"] == 1
    assert summary["resumed"] == 1


def test_run_files_are_written_with_the_report_last(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    order: list[str] = []
    original = Path.replace

    def spy(self: Path, target: Any) -> Path:
        order.append(Path(target).name)
        return original(self, target)

    monkeypatch.setattr(Path, "replace", spy)
    files = {"report.json": b"{}", "flight_log.npz": b"x", "report.md": b"# r", "logs/sim.log": b"w"}
    write_run_files(tmp_path / "seed-001", files)
    assert order[-1] == "report.json"
    assert (tmp_path / "seed-001" / "logs" / "sim.log").read_bytes() == b"w"
    assert not list((tmp_path / "seed-001").rglob("*.part"))
    with pytest.raises(SimError, match="outside its run folder"):
        write_run_files(tmp_path / "seed-002", {"../evil": b""})


def test_error_line_is_the_runs_own_error() -> None:
    class WrappedError(Exception):
        def __init__(self, cause: BaseException) -> None:
            super().__init__("ray::run_seed() (pid=1)\n  traceback ...")
            self.cause = cause

    failed = RunFailedError("ConfigError: formation.kp_xy: not a number\nTraceback (most recent call last):")
    assert error_line(WrappedError(failed)) == "ConfigError: formation.kp_xy: not a number"
    assert error_line(RuntimeError("\n  worker died\nmore")) == "RuntimeError: worker died"
    assert error_line(ValueError()) == "ValueError: (no message)"


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--scenario", "straight", "--executor", "ray"], "go with --seeds"),
        (["--scenario", "straight", "--resume"], "go with --seeds"),
        (["--scenario", "straight", "--seeds", "1-2", "--executor", "ray", "--harness", "real"], "lockstep"),
    ],
)
def test_sim_refuses_executor_options_that_do_not_apply(
    argv: list[str], message: str, tmp_path: Path
) -> None:
    with pytest.raises(SystemExit, match=message):
        companion_main(["sim", *argv, "--detector", "truth", "--out", str(tmp_path)])


def test_neither_the_cli_nor_the_executor_module_imports_ray(repo_root: Path) -> None:
    code = (
        "import sys; from companion.cli import build_parser; build_parser(); "
        "import companion.lab.evaluation.ray_executor; sys.exit('ray' in sys.modules)"
    )
    r = subprocess.run(
        [sys.executable, "-c", code], cwd=repo_root, capture_output=True, text=True, check=False
    )
    assert r.returncode == 0, r.stdout + r.stderr


def test_a_cluster_address_that_refuses_is_one_line_not_a_hang() -> None:
    from companion.lab.evaluation.ray_executor import _check_reachable

    with socket.socket() as s:  # a port nothing listens on: bound, never listening
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
        with pytest.raises(SimError, match=f"--ray-address 127.0.0.1:{port}: no Ray head answers"):
            _check_reachable(f"127.0.0.1:{port}", timeout_s=2.0)
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen()
        _check_reachable(f"127.0.0.1:{server.getsockname()[1]}", timeout_s=2.0)
