"""The report's plots: drawn from a flight log, with the mission's states; what runs off a scale is marked."""

from __future__ import annotations

from pathlib import Path
from typing import Any

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


def _legend_texts(ax: Any) -> list[str]:
    legend = ax.get_legend()
    return [t.get_text() for t in legend.get_texts()] if legend is not None else []


def test_the_top_view_fits_a_straight_path_and_keeps_a_circle_round() -> None:
    from matplotlib.figure import Figure

    from companion.lab.evaluation.plots import MAX_STRETCH, _top_view_limits

    fig = Figure(figsize=(6, 5))
    ax = fig.subplots()
    north = np.linspace(0.0, 150.0, 300)
    east = 0.3 * np.sin(north / 10.0)  # a straight path with a metre of wander
    note = _top_view_limits(fig, ax, east, north)
    assert note.startswith("not to scale: east stretched x")
    lo, hi = ax.get_xlim()
    assert hi - lo < 150.0 / 2  # not the +-75 m of equal axes around a line
    assert lo < east.min()
    assert east.max() < hi
    assert float(note.rsplit("x", 1)[1]) <= MAX_STRETCH
    fig = Figure(figsize=(6, 5))
    ax = fig.subplots()
    a = np.linspace(0.0, 2 * np.pi, 200)
    assert _top_view_limits(fig, ax, 15.0 * np.cos(a), 15.0 * np.sin(a)) == ""
    assert ax.get_aspect() == 1.0


def test_the_trajectories_key_every_mark(tmp_path: Path) -> None:
    from companion.lab.evaluation.plots import plot_trajectories

    fig = plot_trajectories(_log(), [0.0, 0.0, 5.0], tmp_path / "t.png", "straight")
    top, dev = fig.axes[0], fig.axes[1]
    labels = _legend_texts(top)
    assert labels[:3] == [
        "leader",
        "follower's slot, in formation (under its line where it holds it)",
        "follower",
    ]
    assert "follower, its GPS lost" in labels
    assert "GPS lost (t = 12 s)" in labels
    assert "start (t = 0 s)" in labels
    assert "end (t = 20 s); arrows: direction" in labels
    assert _legend_texts(dev) == ["one tick, GPS good", "one tick, follower's GPS lost"]
    # The leader's band is drawn under the follower's line, never hidden by it.
    lines = {ln.get_label(): ln for ln in top.get_lines()}
    assert lines["leader"].get_zorder() < lines["follower"].get_zorder()
    assert lines["leader"].get_linewidth() > 2 * lines["follower"].get_linewidth()
    assert (tmp_path / "t.png").stat().st_size > 10_000


def test_the_camera_strip_has_a_key_and_a_zoom(tmp_path: Path) -> None:
    from companion.lab.evaluation.plots import Snapshot, plot_camera_strip

    rgb = np.full((480, 640, 3), 120, np.uint8)
    snaps = [
        Snapshot(24.5, rgb, (300.0, 220.0, 330.0, 240.0), (301.0, 221.0, 331.0, 241.0), 0.85),
        Snapshot(25.5, rgb, None, (301.0, 221.0, 331.0, 241.0)),
        Snapshot(26.5, rgb, None, None),
    ]
    fig = plot_camera_strip(snaps, tmp_path / "c.png", "straight: follower camera")
    key = [t.get_text() for t in fig.legends[0].get_texts()]
    assert key == [
        "detection (the number: its score)",
        "true box of the leader (simulator)",
        "inset: zoom on the leader",
    ]
    frames = fig.axes[:3]
    assert [ax.get_title() for ax in frames] == [
        "t = 24.5 s",
        "t = 25.5 s (no detection)",
        "t = 26.5 s (leader not in view, no detection)",
    ]
    assert [t.get_text() for t in frames[0].texts] == ["0.85"]
    assert [len(ax.child_axes) for ax in frames] == [1, 1, 0]  # a zoom wherever there is a leader


def test_the_formation_plot_has_start_end_and_timed_snapshots_and_the_report_links_it(tmp_path: Path) -> None:
    from companion.lab.formation.report import draw_formation, report_markdown

    t = np.arange(0.0, 40.0, 0.5)
    lead = np.stack([2.0 * t, np.zeros_like(t), np.full_like(t, -5.0)], axis=1)
    tracks = {"leader": lead, "follower1": lead - [4.0, 3.0, 0.0], "follower2": lead - [4.0, -3.0, 0.0]}
    dev = {"follower1": np.stack([t, np.full_like(t, 0.1)], axis=1), "follower2": np.empty((0, 2))}
    fig = draw_formation(t, tracks, dev, plan_name="v", path=tmp_path / "plots" / "formation.png", title="v")
    top = fig.axes[0]
    labels = _legend_texts(top)
    assert labels == [
        "leader",
        "follower1",
        "follower2",
        "start (t = 0 s)",
        "end (t = 40 s)",
        "the formation every 10 s",
    ]
    assert [a.get_text() for a in top.texts if a.get_text()] == ["0 s", "10 s", "20 s", "30 s"]  # timed
    assert len([a for a in top.texts if not a.get_text() and a.arrow_patch is not None]) == 4  # direction
    plot = str(tmp_path / "plots/formation.png")
    report = {
        "scenario": "formation-v", "seed": 1, "outcome": "completed", "plan": "v", "sim_duration_s": 40.0,
        "wall_s": 60.0, "wall_s_per_sim_s": 1.5, "followers": [], "plots": [plot],
    }  # fmt: skip
    assert report_markdown(report).rstrip().endswith("## Plots\n\n![formation](plots/formation.png)")


def _take_off_log() -> FlightLog:
    """A climb in which the leader leaves the image and the coasting estimate runs 3 m off, then FOLLOW from
    4 s and the scored window from 6 s; no GPS loss."""
    n = 300
    t = np.arange(n) * 0.05
    leader = np.stack([np.full(n, 5.0), np.zeros(n), np.full(n, -5.0)], axis=1)
    follower = np.zeros((n, 3))
    follower[:, 2] = -np.minimum(5.0, 1.25 * t)  # climbs to 5 m in 4 s
    est = leader - follower + 0.03
    est[20:40, 0] += np.linspace(0.0, 3.0, 20)  # coasting while the leader is out of the image
    est[40:60] = np.nan  # the track dropped
    states = ["TAKEOFF"] * 80 + ["FOLLOW"] * 220
    frame_t = t[::2]
    return FlightLog(
        t_s=t,
        p_ned_follower_m=follower,
        p_ned_leader_m=leader,
        yaw_follower_rad=np.zeros(n),
        rel_ned_est_m=est,
        formation=t >= 6.0,
        gps_ok=np.ones(n, dtype=bool),
        state=states,
        v_ned_follower_m_s=np.zeros((n, 3)),
        frame_t_s=frame_t,
        frame_leader_visible=~((frame_t >= 1.0) & (frame_t < 3.0)),
        frame_detected=np.ones(frame_t.size, dtype=bool),
        frame_false_positive=np.zeros(frame_t.size, dtype=bool),
        frame_latency_ms=np.full(frame_t.size, 8.0),
    )


def test_the_error_plots_explain_what_they_leave_out(tmp_path: Path) -> None:
    from companion.lab.evaluation.plots import OUT_OF_VIEW_LABEL, plot_errors, plot_estimate_vs_truth

    log = _take_off_log()
    fig = plot_errors(log, [0.0, 0.0, 5.0], tmp_path / "errors.png", "straight: errors over time")
    ax = fig.axes[0]
    keys = _legend_texts(ax)
    assert OUT_OF_VIEW_LABEL in keys  # why the estimate error leaves the scale, then stops
    assert "estimate error off the scale (up to 3.03 m)" in keys
    assert ax.get_ylim()[1] < 1.0  # the scale is the following states', not the coasting estimate's
    # The formation error is drawn from the first FOLLOW tick, dashed until the scored window starts.
    assert "formation error before the scored window" in keys
    assert "scored from 6.0 s (formation_start_s)" in keys
    assert not any("GPS" in k for k in keys)
    vs = plot_estimate_vs_truth(log, tmp_path / "vs.png", "straight: relative position")
    assert "GPS lost" not in vs.axes[0].get_title()
    assert OUT_OF_VIEW_LABEL in _legend_texts(vs.axes[0])
    assert any(k.startswith("north error off the scale") for k in _legend_texts(vs.axes[3]))
    lost = plot_estimate_vs_truth(_log(), tmp_path / "lost.png", "gps-loss: relative position")
    assert lost.axes[0].get_title().endswith("(red dashes: GPS lost)")
