"""Report plots, drawn with matplotlib's object API (``Figure``), never pyplot: no global backend state."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle
from numpy.typing import NDArray

from companion.evaluation.log import F64, FlightLog
from companion.evaluation.metrics import offset_cam_to_level_body


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


def plot_trajectories(log: FlightLog, offset_cam_m: Sequence[float], path: Path, title: str) -> None:
    """Top-down view (east right, north up) of both vehicles and the desired slot."""
    fig = Figure(figsize=(7, 6), dpi=110)
    ax = fig.subplots()
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
    ax.set_title(title)
    fig.tight_layout()
    fig.savefig(path)


def plot_errors(log: FlightLog, offset_cam_m: Sequence[float], path: Path, title: str) -> None:
    """Formation error and relative-position estimate error over time, GPS loss shaded."""
    slot = desired_follower_ned(log, offset_cam_m)
    form = np.linalg.norm(log.p_ned_follower_m - slot, axis=1)
    form[~log.formation] = np.nan
    rel_true = log.p_ned_leader_m - log.p_ned_follower_m
    est = np.linalg.norm(log.rel_ned_est_m - rel_true, axis=1)
    fig = Figure(figsize=(9, 4), dpi=110)
    ax = fig.subplots()
    ax.plot(log.t_s, form, color="tab:orange", lw=1.2, label="formation error (m)")
    ax.plot(log.t_s, est, color="tab:green", lw=1.0, alpha=0.8, label="relative position estimate error (m)")
    _shade_gps_loss(ax, log)
    ax.set_xlabel("sim time (s)")
    ax.set_ylabel("error (m)")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", fontsize=8)
    ax.set_title(title + " (red: follower GPS lost)" if (~log.gps_ok).any() else title)
    fig.tight_layout()
    fig.savefig(path)


def plot_estimate_vs_truth(log: FlightLog, path: Path, title: str) -> None:
    """Leader-minus-follower position per NED axis: the service's estimate against the truth."""
    rel_true = log.p_ned_leader_m - log.p_ned_follower_m
    fig = Figure(figsize=(9, 6.5), dpi=110)
    axes = fig.subplots(3, 1, sharex=True)
    for i, (ax, name) in enumerate(zip(axes, ("north", "east", "down"), strict=True)):
        ax.plot(log.t_s, rel_true[:, i], color="k", lw=1.0, label="truth")
        ax.plot(log.t_s, log.rel_ned_est_m[:, i], color="tab:green", lw=1.0, alpha=0.85, label="estimate")
        _shade_gps_loss(ax, log)
        ax.set_ylabel(f"{name} (m)")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper right", fontsize=8)
    axes[0].set_title(title)
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
                ax.text(x0, y0 - 4, f"{snap.score:.2f}", color="lime", fontsize=7)
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
