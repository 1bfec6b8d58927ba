"""Report plots, drawn with matplotlib's object API (``Figure``), never pyplot: no global backend state."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.patches import Circle, Rectangle
from numpy.typing import NDArray

from companion.lab.evaluation.log import F64, FlightLog
from companion.lab.evaluation.metrics import offset_cam_to_level_body


@dataclass(frozen=True, slots=True)
class Snapshot:
    """A follower-camera frame kept for the report strip, with the detection and the true box (pixels)."""

    t_s: float
    rgb: NDArray[np.uint8]
    box_xyxy_px: tuple[float, float, float, float] | None
    truth_xyxy_px: tuple[float, float, float, float] | None
    score: float | None = None


def desired_follower_ned(log: FlightLog, offset_cam_m: Sequence[float]) -> F64:
    """Where the follower should be at each tick: the leader minus the slot offset in the heading frame."""
    off = offset_cam_to_level_body(offset_cam_m)
    c, s = np.cos(log.yaw_follower_rad), np.sin(log.yaw_follower_rad)
    out = log.p_ned_leader_m.copy()
    out[:, 0] -= c * off[0] - s * off[1]
    out[:, 1] -= s * off[0] + c * off[1]
    out[:, 2] -= off[2]
    return out


def _shade_gps_loss(ax: Axes, log: FlightLog) -> None:
    lost = ~log.gps_ok
    if not lost.any():
        return
    edges = np.flatnonzero(np.diff(np.concatenate([[0], lost.astype(np.int8), [0]])))
    for start, stop in zip(edges[::2], edges[1::2], strict=True):
        ax.axvspan(log.t_s[start], log.t_s[stop - 1], color="tab:red", alpha=0.12, lw=0)


#: Mission states drawn as bands behind time plots (others are left unshaded).
STATE_COLOURS = {
    "takeoff": "#d9d9d9",
    "acquire": "#c6dbef",
    "follow": "#e5f5e0",
    "follow_vision": "#fdd0a2",
    "reacquire": "#fcbba1",
    "hover": "#dadaeb",
    "controlled_landing": "#fa9fb5",
    "px4_hold": "#bdbdbd",
    "px4_land": "#969696",
}


def _runs(values: Sequence[str]) -> list[tuple[int, int, str]]:
    """(first, last index, value) of each run of equal values."""
    out: list[tuple[int, int, str]] = []
    start = 0
    for i in range(1, len(values) + 1):
        if i == len(values) or values[i] != values[start]:
            out.append((start, i - 1, values[start]))
            start = i
    return out


def _state_bands(ax: Axes, log: FlightLog) -> None:
    """The mission's states as coloured bands, labelled once each in the legend."""
    labelled: set[str] = set()
    for first, last, name in _runs(log.state):
        state = name.lower()  # the log keeps MissionState names (FOLLOW), the legend their values
        colour = STATE_COLOURS.get(state)
        if colour is None:
            continue
        label = None if state in labelled else state
        labelled.add(state)
        ax.axvspan(log.t_s[first], log.t_s[last], color=colour, alpha=0.7, lw=0, label=label, zorder=0)


def slot_error_body(log: FlightLog, offset_cam_m: Sequence[float]) -> F64:
    """N x 2: the follower's error from its slot, forward and right of its heading (m)."""
    err = log.p_ned_follower_m - desired_follower_ned(log, offset_cam_m)
    c, s = np.cos(log.yaw_follower_rad), np.sin(log.yaw_follower_rad)
    forward = c * err[:, 0] + s * err[:, 1]
    right = -s * err[:, 0] + c * err[:, 1]
    return np.stack([forward, right], axis=1)


def plot_trajectories(log: FlightLog, offset_cam_m: Sequence[float], path: Path, title: str) -> None:
    """Left: both vehicles from above (east right, north up). Right: the follower's offset from its slot.

    Over a 150 m path a 0.3 m deviation is invisible at equal aspect, so the right panel draws the error
    itself, in the follower's heading frame (forward up, right to the right), coloured by time.
    """
    fig = Figure(figsize=(12, 5.5), dpi=110)
    ax, dev = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1.25, 1.0]})
    slot = desired_follower_ned(log, offset_cam_m)
    sel = log.formation
    ax.plot(log.p_ned_leader_m[:, 1], log.p_ned_leader_m[:, 0], color="tab:blue", lw=1.6, label="leader")
    ax.plot(
        log.p_ned_follower_m[:, 1], log.p_ned_follower_m[:, 0], color="tab:orange", lw=1.4, label="follower"
    )
    ax.plot(slot[sel, 1], slot[sel, 0], color="k", lw=0.8, ls="--", label="desired slot (in formation)")
    if log.gps_loss_t_s is not None:
        i = int(np.searchsorted(log.t_s, log.gps_loss_t_s))
        if i < log.t_s.size:
            ax.plot(
                log.p_ned_follower_m[i, 1], log.p_ned_follower_m[i, 0], "rx", ms=10, mew=2, label="GPS lost"
            )
    ax.plot(log.p_ned_follower_m[0, 1], log.p_ned_follower_m[0, 0], "o", color="tab:orange", ms=5)
    ax.plot(log.p_ned_leader_m[0, 1], log.p_ned_leader_m[0, 0], "o", color="tab:blue", ms=5)
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    ax.set_title(title, fontsize=10)

    err = slot_error_body(log, offset_cam_m)[sel]
    t = log.t_s[sel]
    if err.size:
        lost = ~log.gps_ok[sel]
        lo, hi = float(t.min()), float(t.max())
        pts = dev.scatter(err[~lost, 1], err[~lost, 0], c=t[~lost], s=4, cmap="viridis", vmin=lo, vmax=hi,
                          lw=0, label="GPS good")  # fmt: skip
        if lost.any():
            dev.scatter(err[lost, 1], err[lost, 0], c=t[lost], s=9, cmap="viridis", vmin=lo, vmax=hi,
                        marker="^", lw=0, label="follower GPS lost")  # fmt: skip
        fig.colorbar(pts, ax=dev, label="sim time (s)", fraction=0.046, pad=0.04)
        reach = float(np.max(np.hypot(err[:, 0], err[:, 1])))
        lim = max(0.3, 1.15 * reach)
        dev.set_xlim(-lim, lim)
        dev.set_ylim(-lim, lim)
        circle = Circle((0.0, 0.0), reach, fill=False, ec="tab:gray", ls=":", lw=1.0)
        dev.add_patch(circle)
        dev.text(0.0, reach, f" max {reach:.2f} m", fontsize=8, color="tab:gray", va="bottom")
    dev.axhline(0.0, color="k", lw=0.6)
    dev.axvline(0.0, color="k", lw=0.6)
    dev.set_aspect("equal")
    dev.set_xlabel("right of the slot (m)")
    dev.set_ylabel("ahead of the slot (m)")
    dev.grid(alpha=0.3)
    if (~log.gps_ok[sel]).any():
        dev.legend(loc="lower right", fontsize=8)
    dev.set_title("follower minus slot, in formation (heading frame)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path)


def plot_errors(log: FlightLog, offset_cam_m: Sequence[float], path: Path, title: str) -> None:
    """Formation error and the relative-position estimate's error over time, on the mission's states."""
    slot = desired_follower_ned(log, offset_cam_m)
    form = np.linalg.norm(log.p_ned_follower_m - slot, axis=1)
    form[~log.formation] = np.nan
    rel_true = log.p_ned_leader_m - log.p_ned_follower_m
    est = np.linalg.norm(log.rel_ned_est_m - rel_true, axis=1)
    fig = Figure(figsize=(10, 4.5), dpi=110)
    ax = fig.subplots()
    _state_bands(ax, log)
    ax.plot(log.t_s, form, color="tab:orange", lw=1.3, label="formation error: |follower - slot| (m)")
    ax.plot(log.t_s, est, color="tab:green", lw=1.0, alpha=0.85, label="estimate error: |est - true| (m)")
    lost = ~log.gps_ok
    if lost.any():
        first = int(np.argmax(lost))
        ax.axvline(log.t_s[first], color="tab:red", lw=1.2, ls="--", label="follower GPS lost")
    finite = np.concatenate([form[np.isfinite(form)], est[np.isfinite(est)]])
    top = float(np.max(finite)) if finite.size else 1.0
    ax.set_ylim(0.0, 1.08 * max(top, 0.1))  # never clipped: the largest error sets the scale
    ax.set_xlabel("sim time (s)")
    ax.set_ylabel("error (m)")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", fontsize=7, ncol=3)
    ax.set_title(f"{title} (bands: mission state)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path)


def plot_estimate_vs_truth(log: FlightLog, path: Path, title: str) -> None:
    """The leader's position relative to the follower, per NED axis: the tracker's estimate against truth.

    Truth is the simulator's (leader minus follower); the estimate is what the service's tracker held at
    each control tick, brought to that instant. Gaps: no estimate (before acquisition, after a loss).
    """
    rel_true = log.p_ned_leader_m - log.p_ned_follower_m
    err = log.rel_ned_est_m - rel_true
    fig = Figure(figsize=(10, 8), dpi=110)
    axes = fig.subplots(4, 1, sharex=True, gridspec_kw={"height_ratios": [1, 1, 1, 1.1]})
    for i, (ax, name) in enumerate(zip(axes[:3], ("north", "east", "down"), strict=True)):
        if i == 0:
            _state_bands(ax, log)
        ax.plot(log.t_s, rel_true[:, i], color="k", lw=1.0, label="truth (simulator)")
        ax.plot(log.t_s, log.rel_ned_est_m[:, i], color="tab:green", lw=1.0, alpha=0.85,
                label="estimate (tracker)")  # fmt: skip
        ax.set_ylabel(f"{name} (m)")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper right", fontsize=7, ncol=4)
    colours = ("tab:blue", "tab:orange", "tab:purple")
    for i, (name, colour) in enumerate(zip(("north", "east", "down"), colours, strict=True)):
        axes[3].plot(log.t_s, err[:, i], color=colour, lw=0.9, label=f"{name} error")
    lost = ~log.gps_ok
    if lost.any():
        for ax in axes:
            ax.axvline(log.t_s[int(np.argmax(lost))], color="tab:red", lw=1.0, ls="--")
    axes[3].axhline(0.0, color="k", lw=0.6)
    axes[3].set_ylabel("estimate - truth (m)")
    axes[3].legend(loc="upper right", fontsize=7, ncol=3)
    axes[3].grid(alpha=0.3)
    axes[0].set_title(f"{title}: leader relative to the follower, NED (red dashes: GPS lost)", fontsize=10)
    axes[-1].set_xlabel("sim time (s)")
    fig.tight_layout()
    fig.savefig(path)


def plot_camera_strip(snapshots: Sequence[Snapshot], path: Path, title: str) -> None:
    """A strip of follower-camera frames with the detection (green) and the true box (white, dashed)."""
    n = max(1, len(snapshots))
    fig = Figure(figsize=(3.2 * n, 2.9), dpi=110)
    axes = fig.subplots(1, n, squeeze=False)
    for ax, snap in zip(axes[0], snapshots, strict=False):
        ax.imshow(snap.rgb)
        if snap.truth_xyxy_px is not None:
            x0, y0, x1, y1 = snap.truth_xyxy_px
            ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, ec="white", lw=1, ls="--"))
        if snap.box_xyxy_px is not None:
            x0, y0, x1, y1 = snap.box_xyxy_px
            ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, ec="lime", lw=1.5))
            if snap.score is not None:
                ax.text(
                    x0,
                    y0 - 6,
                    f"{snap.score:.2f}",
                    color="black",
                    fontsize=9,
                    fontweight="bold",
                    bbox={"facecolor": "lime", "edgecolor": "none", "pad": 1.5, "alpha": 0.9},
                )
        ax.set_title(f"t = {snap.t_s:.1f} s", fontsize=8)
        ax.axis("off")
    for ax in axes[0][len(snapshots) :]:
        ax.axis("off")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path)


def write_plots(
    log: FlightLog,
    offset_cam_m: Sequence[float],
    snapshots: Sequence[Snapshot],
    plots_dir: Path,
    scenario: str,
) -> list[str]:
    """All report plots into ``plots_dir``; returns their paths relative to its parent."""
    plots_dir.mkdir(parents=True, exist_ok=True)
    plot_trajectories(log, offset_cam_m, plots_dir / "trajectories.png", f"{scenario}: top-down trajectories")
    plot_errors(log, offset_cam_m, plots_dir / "errors.png", f"{scenario}: errors over time")
    plot_estimate_vs_truth(log, plots_dir / "estimate_vs_truth.png", f"{scenario}: relative position")
    names = ["trajectories.png", "errors.png", "estimate_vs_truth.png"]
    if snapshots:
        plot_camera_strip(snapshots, plots_dir / "camera.png", f"{scenario}: follower camera")
        names.append("camera.png")
    return [f"{plots_dir.name}/{n}" for n in names]
