from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest

from companion.lab.evaluation.log import FlightRecorder, load_log, save_log
from companion.lab.evaluation.metrics import (
    compute_metrics,
    formation_errors,
    join_figures,
    monte_carlo_summary,
)
from companion.lab.evaluation.plots import Snapshot, desired_follower_ned, write_plots
from companion.lab.evaluation.report import build_report, missing_keys, summary_markdown, write_report

OFFSET = (0.0, 0.0, 5.0)


def circle_flight(
    *, lateral_error_m: float = 0.0, est_error_m: tuple[float, float, float] = (0.0, 0.0, 0.0), n: int = 400
) -> FlightRecorder:
    """Leader on a 15 m circle; follower exactly 5 m behind it along its heading, plus a lateral error."""
    rec = FlightRecorder()
    for i in range(n):
        t = i * 0.05
        ang = t * 3.0 / 15.0
        leader = (15 * math.cos(ang), 15 * math.sin(ang), -5.0)
        yaw = ang + math.pi / 2  # tangent direction
        fwd = (math.cos(yaw), math.sin(yaw))
        right = (-math.sin(yaw), math.cos(yaw))
        follower = (
            leader[0] - 5 * fwd[0] + lateral_error_m * right[0],
            leader[1] - 5 * fwd[1] + lateral_error_m * right[1],
            -5.0,
        )
        rel = tuple(a - b for a, b in zip(leader, follower, strict=True))
        est = tuple(r + e for r, e in zip(rel, est_error_m, strict=True))
        rec.tick(t, follower, leader, yaw, est, formation=True, gps_ok=t < 10.0, state="FOLLOW")
        rec.frame(
            t, leader_visible=True, detected=i % 10 != 0, false_positive=i % 100 == 0, latency_ms=8.0 + i % 3
        )
    rec.gps_loss_t_s = 10.0
    return rec


def test_perfect_formation_has_zero_errors() -> None:
    m = compute_metrics(circle_flight().freeze(), OFFSET)
    assert m.formation_rmse_m == pytest.approx(0.0, abs=1e-9)
    assert m.formation_max_deviation_m == pytest.approx(0.0, abs=1e-9)
    assert m.relative_position_rmse_m == pytest.approx(0.0, abs=1e-9)
    assert m.min_separation_m == pytest.approx(5.0)
    assert m.outcome == "completed"


def test_lateral_offset_shows_in_formation_error() -> None:
    m = compute_metrics(circle_flight(lateral_error_m=0.3).freeze(), OFFSET)
    assert m.formation_rmse_m == pytest.approx(0.3, rel=1e-6)
    assert m.formation_max_deviation_m == pytest.approx(0.3, rel=1e-6)


def test_estimate_error_and_bearing() -> None:
    # constant 0.1 m east error: the bearing error depends on heading, bounded by atan(0.1/5)
    m = compute_metrics(circle_flight(est_error_m=(0.0, 0.1, 0.0)).freeze(), OFFSET)
    assert m.relative_position_rmse_m == pytest.approx(0.1, rel=1e-6)
    assert 0.0 < m.relative_yaw_rmse_deg < math.degrees(math.atan(0.1 / 5)) + 1e-6


def test_detection_rates_and_latency() -> None:
    m = compute_metrics(circle_flight().freeze(), OFFSET)
    assert m.detection_recall == pytest.approx(0.9)
    assert m.false_positive_rate == pytest.approx(0.01)
    assert m.perception_latency_ms["p50"] == pytest.approx(9.0)
    assert m.frames == 400


def test_a_saved_log_loads_back_with_the_same_figures(tmp_path: Path) -> None:
    rec = circle_flight(lateral_error_m=0.2)
    rec.transition(3.0, "ACQUIRE", "FOLLOW", "LEADER_ACQUIRED")
    log = rec.freeze()
    save_log(log, tmp_path / "flight_log.npz")
    back = load_log(tmp_path / "flight_log.npz")
    assert back.state == log.state
    assert back.transitions == log.transitions
    np.testing.assert_array_equal(back.frame_detected, log.frame_detected)
    np.testing.assert_allclose(formation_errors(back, OFFSET), formation_errors(log, OFFSET))
    assert compute_metrics(back, OFFSET).formation_max_deviation_m == pytest.approx(0.2, rel=1e-6)


def test_no_estimate_is_not_zero_error() -> None:
    rec = FlightRecorder()
    for i in range(10):
        rec.tick(i * 0.1, (0, 0, -5), (5, 0, -5), 0.0, None, formation=True, gps_ok=True, state="REACQUIRE")
    m = compute_metrics(rec.freeze(), OFFSET)
    assert m.relative_position_rmse_m is None
    assert m.detection_recall is None
    assert m.outcome == "aborted"


def test_a_run_ending_in_formation_far_from_its_slot_strayed() -> None:
    """Ended in FOLLOW, on its slot: completed; ended in FOLLOW 30 m from it (a cloud chased): strayed."""
    for leader_n_m, outcome in ((5.0, "completed"), (35.0, "strayed")):
        rec = FlightRecorder()
        for i in range(10):
            rec.tick(
                i * 0.1,
                (0, 0, -5),
                (leader_n_m, 0, -5),
                0.0,
                None,
                formation=True,
                gps_ok=True,
                state="FOLLOW",
            )
        assert compute_metrics(rec.freeze(), OFFSET).outcome == outcome


def test_outcomes() -> None:
    rec = circle_flight(n=20)
    rec.landed = True
    assert compute_metrics(rec.freeze(), OFFSET).outcome == "landed_safely"
    rec.crashed = True
    assert compute_metrics(rec.freeze(), OFFSET).outcome == "crashed"


def test_desired_slot_is_consistent_with_formation_error() -> None:
    log = circle_flight(lateral_error_m=0.2).freeze()
    d = np.linalg.norm(log.p_ned_follower_m - desired_follower_ned(log, OFFSET), axis=1)
    assert np.allclose(d, 0.2)


def test_report_contract_and_files(tmp_path: Path) -> None:
    rec = circle_flight()
    rec.transition(1.0, "ACQUIRE", "FOLLOW", "LEADER_CONFIRMED")
    log = rec.freeze()
    report = build_report("circle", 7, log, compute_metrics(log, OFFSET), wall_s=12.5)
    assert missing_keys(report) == []
    assert report["meets_targets"] is True
    assert report["transitions"] == [[1.0, "ACQUIRE", "FOLLOW", "LEADER_CONFIRMED"]]
    snaps = [Snapshot(1.0, np.zeros((48, 64, 3), np.uint8), (10, 10, 20, 20), (11, 11, 21, 21), 0.9)]
    report["plots"] = write_plots(log, OFFSET, snaps, tmp_path / "plots", "circle")
    write_report(tmp_path, report)
    back = json.loads((tmp_path / "report.json").read_text())
    assert back["scenario"] == "circle"
    assert back["gps_loss_s"] == 10.0
    for p in report["plots"]:
        assert (tmp_path / p).stat().st_size > 5000
    assert "| relative position RMSE (m) | 0.000 | 0.320 |" in (tmp_path / "report.md").read_text()


def test_missing_target_figure_fails_targets() -> None:
    rec = FlightRecorder()
    rec.tick(0.0, (0, 0, -5), (5, 0, -5), 0.0, None, formation=True, gps_ok=True, state="FOLLOW")
    log = rec.freeze()
    assert (
        build_report("straight", 1, log, compute_metrics(log, OFFSET), wall_s=1.0)["meets_targets"] is False
    )


def test_summary_markdown_has_paper_rows() -> None:
    log = circle_flight().freeze()
    r = build_report("circle", 1, log, compute_metrics(log, OFFSET), wall_s=1.0)
    md = summary_markdown({"circle": r})
    assert "| Circular path | 0.32 / 0.000 | 3.1 / 0.00 | 0.75 / 0.000 | completed | yes |" in md
    assert "| Straight line | 0.25 / not run |" in md


def test_the_summary_marks_a_scenarios_intended_outcome() -> None:
    log = circle_flight().freeze()
    metrics = compute_metrics(log, OFFSET)
    aborted = build_report("link-loss", 1, log, dataclasses.replace(metrics, outcome="aborted"), wall_s=1.0)
    completed = build_report("link-loss", 2, log, metrics, wall_s=1.0)
    plain = build_report("circle", 1, log, metrics, wall_s=1.0)
    assert aborted["intended_outcome"] == "aborted"
    assert "intended_outcome" not in plain
    md = summary_markdown({"link-loss": aborted, "circle": plain})
    assert "| link-loss | aborted (as intended) |" in md
    assert "| circle | completed |" in md
    assert (
        "`link-loss` is meant to end `aborted`: the link's 1.5 s cut trips PX4's offboard-loss failsafe" in md
    )
    assert "| link-loss | completed (intended: aborted) |" in summary_markdown({"link-loss": completed})


def test_monte_carlo_summary() -> None:
    runs = [
        {"outcome": "completed", "relative_position_rmse_m": float(i), "relative_yaw_rmse_deg": None}
        for i in range(1, 101)
    ]
    runs.append({"outcome": "crashed", "relative_position_rmse_m": None})
    s = monte_carlo_summary(runs)
    assert s["runs"] == 101
    assert s["outcomes"]["crashed"] == 1
    assert s["relative_position_rmse_m"]["p50"] == pytest.approx(50.5)
    assert s["relative_position_rmse_m"]["min"] == pytest.approx(1.0)
    assert s["relative_yaw_rmse_deg"] is None


def test_the_join_is_timed_from_the_first_follow_tick_to_the_slot() -> None:
    rec = FlightRecorder()
    leader = (9.0, 0.0, -5.0)
    for k in range(200):  # 10 s at 20 Hz: 1 s acquiring, 4 s closing 4 m, 0.2 m past the slot, back
        t = k * 0.05
        if t < 1.0:
            north, state = 0.0, "ACQUIRE"
        elif t < 5.0:
            north, state = t - 1.0, "FOLLOW"
        else:
            north, state = 4.0 + 0.2 * math.sin(math.pi * min(t - 5.0, 1.0)), "FOLLOW"
        rec.tick(t, (north, 0.0, -5.0), leader, 0.0, None, formation=False, gps_ok=True, state=state)
    join_s, overshoot_m = join_figures(rec.freeze(), (0.0, 0.0, 5.0))
    assert join_s == pytest.approx(3.75, abs=0.051)  # error 4 - (t - 1) under 0.3 m
    assert overshoot_m == pytest.approx(0.2, abs=1e-3)  # 0.2 m closer to the leader than the slot
    never = FlightRecorder()
    never.tick(0.0, (0.0, 0.0, -5.0), leader, 0.0, None, formation=False, gps_ok=True, state="FOLLOW")
    assert join_figures(never.freeze(), (0.0, 0.0, 5.0)) == (None, None)
