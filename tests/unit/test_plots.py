"""The report's plots: drawn from a flight log, never clipped, with the mission's states."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from companion.lab.evaluation.log import FlightLog
from companion.lab.evaluation.plots import slot_error_body, write_plots


def _log() -> FlightLog:
    n = 400
    t = np.arange(n) * 0.05
    leader = np.stack([2.0 * t + 5.0, np.zeros(n), np.full(n, -5.0)], axis=1)
    follower = leader - np.array([5.0, 0.0, 0.0])
    follower[:, 1] += 0.2  # 0.2 m right of the slot (heading north)
    follower[300:, 0] -= 1.3  # a 1.3 m lag late in the run: must not be clipped
    states = ["TAKEOFF"] * 50 + ["FOLLOW"] * 200 + ["FOLLOW_VISION"] * 150  # as the log keeps them
    gps_ok = np.ones(n, dtype=bool)
    gps_ok[250:] = False
    return FlightLog(
        t_s=t,
        p_ned_follower_m=follower,
        p_ned_leader_m=leader,
        yaw_follower_rad=np.zeros(n),
        rel_ned_est_m=leader - follower + 0.05,
        formation=np.array([s != "TAKEOFF" for s in states]),
        gps_ok=gps_ok,
        state=states,
        v_ned_follower_m_s=np.tile([2.0, 0.0, 0.0], (n, 1)),
        frame_t_s=np.empty(0),
        frame_leader_visible=np.empty(0, dtype=bool),
        frame_detected=np.empty(0, dtype=bool),
        frame_false_positive=np.empty(0, dtype=bool),
        frame_latency_ms=np.empty(0),
        gps_loss_t_s=12.5,
    )


def test_the_slot_error_is_in_the_heading_frame() -> None:
    err = slot_error_body(_log(), [0.0, 0.0, 5.0])
    assert np.allclose(err[100], [0.0, 0.2], atol=1e-9)  # 0.2 m right, on the slot along track
    assert np.allclose(err[350], [-1.3, 0.2], atol=1e-9)  # 1.3 m behind


def test_every_plot_is_written(tmp_path: Path) -> None:
    names = write_plots(_log(), [0.0, 0.0, 5.0], [], tmp_path / "plots", "straight")
    assert names == ["plots/trajectories.png", "plots/errors.png", "plots/estimate_vs_truth.png"]
    for name in names:
        assert (tmp_path / name).stat().st_size > 10_000


def test_the_mission_states_are_drawn_as_labelled_bands() -> None:
    from matplotlib.figure import Figure

    from companion.lab.evaluation.plots import _state_bands

    ax = Figure().subplots()
    _state_bands(ax, _log())
    labels = [p.get_label() for p in ax.patches]
    assert labels == ["takeoff", "follow", "follow_vision"]
