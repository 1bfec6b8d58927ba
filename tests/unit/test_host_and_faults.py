"""The host's verdict on a real-path run, and the camera's depth glitch."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.kernel.camera import GroundTruth, Intrinsics, RgbdFrame
from companion.lab.evaluation.host import HostLoad, starved
from sitl.render.faults import DepthGlitches, offset_leader_depth


def report(gap_ms: float = 60.0, age_ms: float = 25.0) -> dict[str, object]:
    return {
        "deviation_split": {"run": {"ticks": {"interval_p99_ms": gap_ms}}},
        "control_tick_ages_ms": {"telemetry_age_ms": {"p95": age_ms}},
    }


def test_a_run_alone_on_its_host_is_not_starved() -> None:
    assert starved({"others_cpu_frac": 0.02}, report()) == []


def test_other_work_late_ticks_and_old_telemetry_each_starve_a_run() -> None:
    why = starved({"others_cpu_frac": 0.4}, report(gap_ms=400.0, age_ms=90.0))
    assert len(why) == 3
    assert "40%" in why[0]
    assert "400 ms" in why[1]
    assert "90 ms" in why[2]


def test_the_host_load_takes_the_runs_own_cpu_out_of_the_machines(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr("os.cpu_count", lambda: 2)
    cpu = iter([(100.0, 1000.0), (190.0, 1200.0)])  # 90 busy CPU-s over 100 s of a 2-core machine
    now = iter([0.0, 100.0])
    host = HostLoad(read_cpu=lambda: next(cpu), clock=lambda: next(now))
    host.start()
    out = host.stop(own_cpu_s=60.0)
    assert out["machine_busy_frac"] == pytest.approx(0.45)
    assert out["others_cpu_frac"] == pytest.approx(0.15)


def test_the_host_load_reads_this_machine() -> None:
    host = HostLoad()
    host.start()
    out = host.stop(own_cpu_s=0.0)
    assert out["cores"] >= 1
    assert 0.0 <= out.get("machine_busy_frac", 0.0) <= 1.0


def frame_with_leader_box() -> RgbdFrame:
    depth = np.full((48, 64), 9.0, dtype=np.float32)
    depth[10:20, 20:30] = 5.0  # the leader
    depth[12, 22] = 0.0  # an invalid pixel stays invalid
    truth = GroundTruth((20.0, 10.0, 30.0, 20.0), 1.0, np.array([0.0, 0.0, 5.0]), 0.0, None, None, None)
    intr = Intrinsics(width_px=64, height_px=48, fx_px=50.0, fy_px=50.0, cx_px=32.0, cy_px=24.0)
    return RgbdFrame(np.zeros((48, 64, 3), np.uint8), depth, intr, 1.0, 1, truth)


def test_a_depth_glitch_moves_only_the_leaders_box() -> None:
    frame = frame_with_leader_box()
    out = offset_leader_depth(frame, -2.0)
    assert out.depth_m[15, 25] == pytest.approx(3.0)
    assert out.depth_m[12, 22] == 0.0
    assert out.depth_m[30, 50] == pytest.approx(9.0)
    assert frame.depth_m[15, 25] == pytest.approx(5.0)  # the original is untouched


def test_each_glitch_is_taken_once_by_the_first_frame_at_or_after_it() -> None:
    g = DepthGlitches([(60.0, -2.0)])
    assert g.take(59.99) == 0.0
    assert g.take(60.04) == -2.0
    assert g.take(60.1) == 0.0
    assert math.isclose(DepthGlitches([(1.0, -1.0), (1.0, -0.5)]).take(2.0), -1.5)
