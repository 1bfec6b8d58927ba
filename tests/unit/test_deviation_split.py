"""The split of a run's deviation: each part is what a constructed flight put there."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.lab.evaluation.deviation import split_deviation, split_markdown, split_row
from companion.lab.evaluation.log import FlightLog, FlightRecorder

SLOT = (0.0, 0.0, 5.0)  # the leader 5 m ahead on the camera axis
DT = 0.05


def leader_speed(t: float) -> float:
    """The leader speeds up from 0 to 2 m/s north over 1 s, starting at 5 s."""
    return 2.0 * min(max(t - 5.0, 0.0), 1.0)


def leader_north(t: float) -> float:
    if t <= 5.0:
        return 0.0
    if t <= 6.0:
        return (t - 5.0) ** 2
    return 1.0 + 2.0 * (t - 6.0)


def straight_flight(
    *,
    lag_s: float = 0.0,
    heading_error_rad: float = 0.0,
    range_outlier_at_s: float | None = None,
    n: int = 300,
) -> FlightLog:
    """Follower 5 m behind a leader flying north; the command is the leader's velocity, achieved ``lag_s``
    late; the service's heading is off the truth by ``heading_error_rad`` (the camera itself exact)."""
    rec = FlightRecorder()
    north_f = -5.0
    for i in range(n):
        t = i * DT
        leader = (leader_north(t), 0.0, -5.0)
        v_f = leader_speed(t - lag_s)
        follower = (north_f, 0.0, -5.0)
        rel = np.subtract(leader, follower)
        c, s = math.cos(heading_error_rad), math.sin(heading_error_rad)
        est = (c * rel[0] - s * rel[1], s * rel[0] + c * rel[1], rel[2])  # body vector turned by a wrong yaw
        rec.tick(
            t,
            follower,
            leader,
            0.0,
            est,
            formation=t >= 2.0,
            gps_ok=True,
            state="FOLLOW",
            v_ned_follower_m_s=(v_f, 0.0, 0.0),
            yaw_service_rad=heading_error_rad,
            v_cmd_ned_m_s=(leader_speed(t), 0.0, 0.0),
        )
        off = 2.0 if range_outlier_at_s is not None and abs(t - range_outlier_at_s) < DT / 2 else 0.0
        rec.frame(
            t,
            leader_visible=True,
            detected=True,
            false_positive=False,
            rel_est_ned_m=est,
            rel_true_ned_m=(float(rel[0]), float(rel[1]), float(rel[2])),
            yaw_follower_rad=0.0,
            formation=t >= 2.0,
            range_meas_m=float(np.linalg.norm(rel)) - off,
        )
        north_f += v_f * DT
    return rec.freeze()


def test_an_autopilot_that_lags_its_command_shows_as_tracking() -> None:
    split = split_deviation(straight_flight(lag_s=0.5), SLOT, window_s=10.0)  # back to before the start
    assert split is not None
    a, knew, got = split["at_max"], split["what_the_law_knew"], split["how_it_got_there"]
    # 2 m/s reached half a second late: the follower falls 1 m behind, all of it the autopilot's lag.
    assert a["deviation_m"] == pytest.approx(1.0, abs=0.06)
    assert knew["perception_error_m"] == pytest.approx(0.0, abs=1e-6)
    assert knew["error_the_law_saw_m"] == pytest.approx(a["deviation_m"], abs=1e-3)
    assert got["autopilot_tracking_m"] == pytest.approx(a["deviation_m"], abs=0.06)
    assert abs(got["leader_against_command_m"]) < 0.06
    parts = (
        got["start_m"]
        + got["leader_against_command_m"]
        + got["autopilot_tracking_m"]
        + got["follower_turn_m"]
    )
    assert parts == pytest.approx(a["deviation_m"], abs=2e-3)
    assert split["run"]["autopilot_lag_s"] == pytest.approx(0.5, abs=DT)


def test_a_wrong_heading_is_an_ned_error_and_not_a_camera_error() -> None:
    split = split_deviation(straight_flight(heading_error_rad=math.radians(5.0)), SLOT)
    assert split is not None
    run = split["run"]
    assert run["estimate_rmse_camera_frame_m"] == pytest.approx(0.0, abs=1e-6)
    # 5 m at 5 deg: 0.44 m sideways in NED.
    assert run["estimate_rmse_ned_m"] == pytest.approx(5.0 * 2 * math.sin(math.radians(2.5)), abs=0.03)


def test_an_accepted_range_outlier_is_counted_and_the_large_errors_attributed() -> None:
    # The flight ends 3 s after the leader's speed-up: every large error lies within 3 s of it.
    split = split_deviation(straight_flight(lag_s=0.5, range_outlier_at_s=5.5, n=180), SLOT)
    assert split is not None
    run = split["run"]
    assert run["range_outliers_taken"] == 1
    assert run["range_error_max_m"] == pytest.approx(2.0, abs=1e-6)
    large = run["large_errors"]
    assert large["ticks"] > 0
    share = large["share_following"]
    assert share["leader_manoeuvre"] == pytest.approx(1.0)
    assert 0.0 < share["range_outlier"] < 1.0  # the outlier at 5.5 s reaches up to 8.5 s
    assert share["frame_gap"] == 0.0
    assert split_row(split)["range_outliers_taken"] == 1
    text = "\n".join(split_markdown(split))
    assert "autopilot's tracking of the command" in text
    assert "range outliers taken 1" in text


def test_no_formation_no_split() -> None:
    log = straight_flight(n=30)  # formation starts at 2 s: 1.5 s of flight never gets there
    assert split_deviation(log, SLOT) is None
