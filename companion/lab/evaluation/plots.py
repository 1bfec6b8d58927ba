"""Report plots, drawn with matplotlib's object API (``Figure``), never pyplot: no global backend state."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Circle, Patch, Rectangle
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
    "follow_vision": "#d4b9da",  # not orange: the formation error is drawn in the follower's orange
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


#: States in which the follower flies on the leader (its slot error means something from the first tick).
FOLLOWING_STATES = frozenset({"FOLLOW", "FOLLOW_VISION", "REACQUIRE", "HOVER"})
OUT_OF_VIEW_LABEL = "leader out of the image (the tracker coasts, then drops the track)"


def _shade_out_of_view(ax: Axes, log: FlightLog, *, label: bool) -> None:
    """Hatch the stretches whose camera frames had none of the leader in the image (simulator's truth)."""
    if log.frame_t_s.size == 0:
        return
    first = True
    for a, b, visible in _runs([str(bool(v)) for v in log.frame_leader_visible]):
        if visible == "True":
            continue
        ax.axvspan(log.frame_t_s[a], log.frame_t_s[b], facecolor="none", edgecolor="0.55", hatch="///",
                   lw=0, zorder=0.5, label=OUT_OF_VIEW_LABEL if label and first else None)  # fmt: skip
        first = False


def _clip_marks(ax: Axes, t_s: F64, y: F64, top: float, *, colour: str, what: str) -> None:
    """Mark with a triangle at the axis top every tick where ``y`` runs off the top, labelled with its max."""
    off = np.isfinite(y) & (y > top)
    if off.any():
        label = f"{what} off the scale (up to {float(np.max(y[off])):.2f} m)"
        ax.plot(t_s[off], np.full(int(off.sum()), top), ls="none", marker="^", ms=4, color=colour,
                clip_on=False, label=label)  # fmt: skip


def slot_error_body(log: FlightLog, offset_cam_m: Sequence[float]) -> F64:
    """N x 2: the follower's error from its slot, forward and right of its heading (m)."""
    err = log.p_ned_follower_m - desired_follower_ned(log, offset_cam_m)
    c, s = np.cos(log.yaw_follower_rad), np.sin(log.yaw_follower_rad)
    forward = c * err[:, 0] + s * err[:, 1]
    right = -s * err[:, 0] + c * err[:, 1]
    return np.stack([forward, right], axis=1)


#: Colours of the two vehicles, the same in every plot.
LEADER_COLOUR = "tab:blue"
FOLLOWER_COLOUR = "tab:orange"
GPS_LOST_COLOUR = "tab:red"
#: The top view keeps equal axes while that leaves at least this share of the panel to the data.
EQUAL_ASPECT_MIN_FILL = 0.5
#: ...else it stretches the narrow axis, at most this much (more makes metre-scale wander look wild).
MAX_STRETCH = 20.0


def _top_view_limits(fig: Figure, ax: Axes, east_m: F64, north_m: F64) -> str:
    """Fit the top view to the data: equal axes when they fill the panel, else each axis to its data.

    A straight 150 m path drawn at equal aspect is a line in an empty panel; stretched across, its
    metre-scale wander shows. Returns the words for the east axis label ("" at equal aspect).
    """
    e = east_m[np.isfinite(east_m)]
    n = north_m[np.isfinite(north_m)]
    if e.size == 0 or n.size == 0:
        return ""
    (e_lo, e_hi), (n_lo, n_hi) = (float(e.min()), float(e.max())), (float(n.min()), float(n.max()))
    span_e, span_n = max(e_hi - e_lo, 2.0), max(n_hi - n_lo, 2.0)
    box = ax.get_position()
    panel_w, panel_h = box.width * fig.get_figwidth(), box.height * fig.get_figheight()
    fill = (span_e / span_n) / (panel_w / panel_h)
    if EQUAL_ASPECT_MIN_FILL <= fill <= 1.0 / EQUAL_ASPECT_MIN_FILL:
        ax.set_aspect("equal", adjustable="datalim")
        return ""
    stretch = min(MAX_STRETCH, 1.0 / fill if fill < 1.0 else fill)
    if fill < 1.0:  # tall data: widen the east span to what the stretch allows
        span_e = max(span_e, span_n * (panel_w / panel_h) / stretch)
    else:
        span_n = max(span_n, span_e * (panel_h / panel_w) / stretch)
    mid_e, mid_n, pad = 0.5 * (e_lo + e_hi), 0.5 * (n_lo + n_hi), 0.56
    ax.set_xlim(mid_e - pad * span_e, mid_e + pad * span_e)
    ax.set_ylim(mid_n - pad * span_n, mid_n + pad * span_n)
    return f"not to scale: {'east' if fill < 1.0 else 'north'} stretched x{stretch:.0f}"


def direction_arrows(ax: Axes, east_m: F64, north_m: F64, colour: str, n: int = 4) -> None:
    """Arrowheads along a track, at equal shares of its length, pointing the way it was flown."""
    d = np.hypot(np.diff(east_m), np.diff(north_m))
    d[~np.isfinite(d)] = 0.0
    s = np.concatenate([[0.0], np.cumsum(d)])
    if s[-1] < 1.0:
        return
    for frac in (np.arange(n) + 0.5) / n:  # mid-shares: apart from the ends and from each other on a loop
        i = int(np.searchsorted(s, frac * s[-1]))
        j = min(i + max(1, len(s) // 200), len(s) - 1)
        if i >= j:
            continue
        ax.annotate(
            "",
            xy=(east_m[j], north_m[j]),
            xytext=(east_m[i], north_m[i]),
            arrowprops={"arrowstyle": "-|>", "color": colour, "lw": 0.0, "mutation_scale": 16},
            zorder=6,
        )


def _gps_lost_runs(log: FlightLog) -> list[tuple[int, int]]:
    """(first, last index) of each stretch with the follower's GPS lost."""
    return [(a, b) for a, b, v in _runs(["lost" if not ok else "ok" for ok in log.gps_ok]) if v == "lost"]


def plot_trajectories(log: FlightLog, offset_cam_m: Sequence[float], path: Path, title: str) -> Figure:
    """Left: both vehicles from above (east right, north up). Right: the follower's offset from its slot.

    The left panel keeps equal axes only while they fill it (a straight path is stretched across, and
    says so); the leader is the wide pale band, the follower the line on it, red where its GPS was lost.
    Over a 150 m path a 0.3 m deviation is invisible, so the right panel draws the error itself, in the
    follower's heading frame (forward up, right to the right), one dot per control tick coloured by time.
    """
    fig = Figure(figsize=(13, 6.6), dpi=110)
    ax, dev = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1.15, 1.0]})
    fig.subplots_adjust(left=0.06, right=0.95, bottom=0.22, top=0.9, wspace=0.25)
    slot = desired_follower_ned(log, offset_cam_m)
    sel = log.formation
    lead, fol = log.p_ned_leader_m, log.p_ned_follower_m
    ax.plot(lead[:, 1], lead[:, 0], color=LEADER_COLOUR, lw=6, alpha=0.3, solid_capstyle="round",
            label="leader", zorder=2)  # fmt: skip
    slot_e, slot_n = np.where(sel, slot[:, 1], np.nan), np.where(sel, slot[:, 0], np.nan)
    ax.plot(slot_e, slot_n, color="k", lw=0.9, ls=(0, (4, 3)), zorder=3,
            label="follower's slot, in formation (under its line where it holds it)")  # fmt: skip
    ax.plot(fol[:, 1], fol[:, 0], color=FOLLOWER_COLOUR, lw=1.4, label="follower", zorder=4)
    for k, (a, b) in enumerate(_gps_lost_runs(log)):
        ax.plot(fol[a : b + 1, 1], fol[a : b + 1, 0], color=GPS_LOST_COLOUR, lw=1.6, zorder=5,
                label="follower, its GPS lost" if k == 0 else None)  # fmt: skip
    if log.gps_loss_t_s is not None:
        i = int(np.searchsorted(log.t_s, log.gps_loss_t_s))
        if i < log.t_s.size:
            ax.plot(fol[i, 1], fol[i, 0], "x", color=GPS_LOST_COLOUR, ms=11, mew=2.5, zorder=7,
                    label=f"GPS lost (t = {log.t_s[i]:.0f} s)")  # fmt: skip
    direction_arrows(ax, lead[:, 1], lead[:, 0], LEADER_COLOUR)
    for track, colour in ((lead, LEADER_COLOUR), (fol, FOLLOWER_COLOUR)):
        ax.plot(track[0, 1], track[0, 0], "o", mfc=colour, mec="k", ms=8, zorder=8)
        ax.plot(track[-1, 1], track[-1, 0], "s", mfc=colour, mec="k", ms=7, zorder=8)
    ax.plot([], [], "o", mfc="w", mec="k", ms=8, label=f"start (t = {log.t_s[0]:.0f} s)")
    ax.plot([], [], "s", mfc="w", mec="k", ms=7, label=f"end (t = {log.t_s[-1]:.0f} s); arrows: direction")
    note = _top_view_limits(
        fig,
        ax,
        np.concatenate([lead[:, 1], fol[:, 1], slot_e]),
        np.concatenate([lead[:, 0], fol[:, 0], slot_n]),
    )
    ax.set_xlabel("east (m)" + (f", {note}" if "east" in note else ""))
    ax.set_ylabel("north (m)" + (f", {note}" if "north" in note else ""))
    ax.grid(alpha=0.3)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.11), ncol=2, fontsize=8, frameon=False)
    ax.set_title(f"{title}: both vehicles from above", fontsize=10)

    err = slot_error_body(log, offset_cam_m)[sel]
    t = log.t_s[sel]
    if err.size:
        lost = ~log.gps_ok[sel]
        lo, hi = float(t.min()), float(t.max())
        # GPS good on top: the larger GPS-lost triangles would hide the dots of the same place.
        pts = dev.scatter(err[~lost, 1], err[~lost, 0], c=t[~lost], s=12, cmap="viridis", vmin=lo, vmax=hi,
                          lw=0, zorder=4)  # fmt: skip
        if lost.any():
            dev.scatter(err[lost, 1], err[lost, 0], c=t[lost], s=34, cmap="viridis", vmin=lo, vmax=hi,
                        marker="^", edgecolors=GPS_LOST_COLOUR, linewidths=0.5, zorder=3)  # fmt: skip
        fig.colorbar(pts, ax=dev, label="sim time (s)", fraction=0.046, pad=0.04)
        reach = float(np.max(np.hypot(err[:, 0], err[:, 1])))
        lim = max(0.3, 1.15 * reach)
        dev.set_xlim(-lim, lim)
        dev.set_ylim(-lim, lim)
        circle = Circle((0.0, 0.0), reach, fill=False, ec="tab:gray", ls=":", lw=1.0)
        dev.add_patch(circle)
        dev.text(0.0, reach, f" max {reach:.2f} m", fontsize=8, color="tab:gray", va="bottom")
        good = Line2D([], [], ls="", marker="o", mfc="tab:gray", mec="none", ms=5, label="one tick, GPS good")
        bad = Line2D([], [], ls="", marker="^", mfc="tab:gray", mec=GPS_LOST_COLOUR, mew=1.2, ms=9,
                     label="one tick, follower's GPS lost")  # fmt: skip
        handles = [good, bad] if lost.any() else [good]
        dev.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.11), ncol=2, fontsize=8,
                   frameon=False)  # fmt: skip
    dev.axhline(0.0, color="k", lw=0.6)
    dev.axvline(0.0, color="k", lw=0.6)
    dev.set_aspect("equal")
    dev.set_xlabel("right of the slot (m)")
    dev.set_ylabel("ahead of the slot (m)")
    dev.grid(alpha=0.3)
    dev.set_title("follower minus its slot in formation, follower's heading frame\n"
                  "(0, 0): on the slot; colour: sim time", fontsize=10)  # fmt: skip
    fig.savefig(path)
    return fig


def plot_errors(log: FlightLog, offset_cam_m: Sequence[float], path: Path, title: str) -> Figure:
    """Formation error and the relative-position estimate's error over time, on the mission's states.

    The formation error is solid in the scored window (the scenario's ``formation_start_s`` on) and dashed
    from the first formation state before it. The scale is set by the errors while following: the estimate
    error before it (take-off, the leader out of the image while the tracker coasts) may run off the top,
    marked there with triangles and its largest value.
    """
    slot = desired_follower_ned(log, offset_cam_m)
    slot_err = np.linalg.norm(log.p_ned_follower_m - slot, axis=1)
    following = np.array([s.upper() in FOLLOWING_STATES for s in log.state], dtype=bool)
    form = np.where(log.formation, slot_err, np.nan)
    scored = np.flatnonzero(log.formation)
    before = following & (np.arange(len(log.t_s)) <= (scored[0] if scored.size else len(log.t_s)))
    joining = np.where(before, slot_err, np.nan)
    rel_true = log.p_ned_leader_m - log.p_ned_follower_m
    est = np.linalg.norm(log.rel_ned_est_m - rel_true, axis=1)
    fig = Figure(figsize=(10, 5.2), dpi=110)
    ax = fig.subplots()
    _state_bands(ax, log)
    _shade_out_of_view(ax, log, label=True)
    ax.plot(log.t_s, form, color="tab:orange", lw=1.3, label="formation error: |follower - slot| (m)")
    if np.isfinite(joining).any():
        ax.plot(log.t_s, joining, color="tab:orange", lw=1.0, ls="--",
                label="formation error before the scored window")  # fmt: skip
    if scored.size:
        ax.axvline(log.t_s[scored[0]], color="tab:orange", lw=0.8, ls=":",
                   label=f"scored from {log.t_s[scored[0]]:.1f} s (formation_start_s)")  # fmt: skip
    ax.plot(log.t_s, est, color="tab:green", lw=1.0, alpha=0.85, label="estimate error: |est - true| (m)")
    lost = ~log.gps_ok
    if lost.any():
        first = int(np.argmax(lost))
        ax.axvline(log.t_s[first], color="tab:red", lw=1.2, ls="--", label="follower GPS lost")
    scale = np.concatenate([slot_err[following | log.formation], est[following]])
    scale = scale[np.isfinite(scale)]
    if scale.size == 0:
        scale = np.concatenate([slot_err[np.isfinite(slot_err)], est[np.isfinite(est)]])
    top = 1.08 * max(float(np.max(scale)) if scale.size else 1.0, 0.1)
    ax.set_ylim(0.0, top)
    _clip_marks(ax, log.t_s, est, top, colour="tab:green", what="estimate error")
    ax.set_xlabel("sim time (s)")
    ax.set_ylabel("error (m)")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.13), fontsize=7, ncol=3, frameon=False)
    ax.set_title(f"{title} (bands: mission state)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path)
    return fig


def plot_estimate_vs_truth(log: FlightLog, path: Path, title: str) -> Figure:
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
        _shade_out_of_view(ax, log, label=i == 0)
        ax.plot(log.t_s, rel_true[:, i], color="k", lw=1.0, label="truth (simulator)")
        ax.plot(log.t_s, log.rel_ned_est_m[:, i], color="tab:green", lw=1.0, alpha=0.85,
                label="estimate (tracker)")  # fmt: skip
        ax.set_ylabel(f"{name} (m)")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper right", fontsize=7, ncol=3)
    colours = ("tab:blue", "tab:orange", "tab:purple")
    _shade_out_of_view(axes[3], log, label=False)
    for i, (name, colour) in enumerate(zip(("north", "east", "down"), colours, strict=True)):
        axes[3].plot(log.t_s, err[:, i], color=colour, lw=0.9, label=f"{name} error")
    # The error panel's scale is the following states' errors: a coasting estimate before them (the
    # leader out of the image in the take-off) runs off it, marked at the edge.
    following = np.array([s.upper() in FOLLOWING_STATES for s in log.state], dtype=bool)
    held = np.abs(err[following])
    held = held[np.isfinite(held)]
    if held.size:
        lim = 1.15 * max(float(np.max(held)), 0.05)
        axes[3].set_ylim(-lim, lim)
        for i, (name, colour) in enumerate(zip(("north", "east", "down"), colours, strict=True)):
            _clip_marks(axes[3], log.t_s, np.abs(err[:, i]), lim, colour=colour, what=f"{name} error")
    lost = ~log.gps_ok
    if lost.any():
        for ax in axes:
            ax.axvline(log.t_s[int(np.argmax(lost))], color="tab:red", lw=1.0, ls="--")
    axes[3].axhline(0.0, color="k", lw=0.6)
    axes[3].set_ylabel("estimate - truth (m)")
    axes[3].legend(loc="upper right", fontsize=7, ncol=3)
    axes[3].grid(alpha=0.3)
    note = " (red dashes: GPS lost)" if lost.any() else ""
    axes[0].set_title(f"{title}: leader relative to the follower, NED{note}", fontsize=10)
    axes[-1].set_xlabel("sim time (s)")
    fig.tight_layout()
    fig.savefig(path)
    return fig


#: The true box on the camera frames: dashed magenta shows on sky, grass and buildings alike.
TRUTH_BOX_COLOUR = "magenta"
DETECTION_COLOUR = "lime"


#: The zoomed inset shows this many times the leader's box (at least :data:`ZOOM_MIN_PX` wide).
ZOOM_BOX_MULTIPLE = 3.0
ZOOM_MIN_PX = 48.0


def _boxes(ax: Axes, snap: Snapshot, dx: float = 0.0, dy: float = 0.0, *, label: bool = True) -> None:
    """The detection (solid) and the true box (dashed, on top so that both show), shifted by (dx, dy)."""
    if snap.box_xyxy_px is not None:
        x0, y0, x1, y1 = snap.box_xyxy_px
        ax.add_patch(Rectangle((x0 - dx, y0 - dy), x1 - x0, y1 - y0, fill=False, ec=DETECTION_COLOUR, lw=1.5))
        if label and snap.score is not None:
            tag = {"facecolor": DETECTION_COLOUR, "edgecolor": "none", "pad": 1.2, "alpha": 0.9}
            ax.text(x0 - dx, y0 - dy - 6, f"{snap.score:.2f}", color="black", fontsize=8, fontweight="bold",
                    bbox=tag)  # fmt: skip
    if snap.truth_xyxy_px is not None:
        x0, y0, x1, y1 = snap.truth_xyxy_px
        ax.add_patch(Rectangle((x0 - dx, y0 - dy), x1 - x0, y1 - y0, fill=False, ec=TRUTH_BOX_COLOUR, lw=1.1,
                               ls=(0, (3, 2))))  # fmt: skip


def plot_camera_strip(snapshots: Sequence[Snapshot], path: Path, title: str) -> Figure:
    """A strip of follower-camera frames with the detection and its score, and the simulator's true box.

    At formation range the leader is a few dozen pixels wide, so each frame has an inset that zooms on it.
    The key sits under the strip; a frame without a detection or without the leader in view says so.
    """
    n = max(1, len(snapshots))
    fig = Figure(figsize=(3.4 * n, 3.4), dpi=110)
    axes = fig.subplots(1, n, squeeze=False)
    for ax, snap in zip(axes[0], snapshots, strict=False):
        ax.imshow(snap.rgb)
        _boxes(ax, snap)
        notes = [] if snap.truth_xyxy_px is not None else ["leader not in view"]
        if snap.box_xyxy_px is None:
            notes.append("no detection")
        focus = snap.truth_xyxy_px or snap.box_xyxy_px
        if focus is not None:
            h_px, w_px = snap.rgb.shape[:2]
            cx, cy = 0.5 * (focus[0] + focus[2]), 0.5 * (focus[1] + focus[3])
            half = 0.5 * max(ZOOM_MIN_PX, ZOOM_BOX_MULTIPLE * max(focus[2] - focus[0], focus[3] - focus[1]))
            x0, y0 = int(max(0.0, cx - half)), int(max(0.0, cy - 0.75 * half))
            x1, y1 = int(min(w_px, cx + half)), int(min(h_px, cy + 0.75 * half))
            inset = ax.inset_axes((0.56, 0.56, 0.42, 0.42))
            inset.imshow(snap.rgb[y0:y1, x0:x1])
            _boxes(inset, snap, x0, y0, label=False)
            inset.set_xlim(-0.5, x1 - x0 - 0.5)
            inset.set_ylim(y1 - y0 - 0.5, -0.5)
            inset.set_xticks([])
            inset.set_yticks([])
            for side in inset.spines.values():
                side.set_edgecolor("white")
            ax.indicate_inset((x0, y0, x1 - x0, y1 - y0), inset, edgecolor="white", alpha=0.8)
        ax.set_title(f"t = {snap.t_s:.1f} s" + (f" ({', '.join(notes)})" if notes else ""), fontsize=8)
        ax.axis("off")
    for ax in axes[0][len(snapshots) :]:
        ax.axis("off")
    key = [
        Patch(fill=False, ec=DETECTION_COLOUR, lw=1.5, label="detection (the number: its score)"),
        Patch(fill=False, ec=TRUTH_BOX_COLOUR, lw=1.1, ls="--", label="true box of the leader (simulator)"),
        Patch(fill=False, ec="white", lw=1.0, label="inset: zoom on the leader"),
    ]
    fig.legend(handles=key, loc="lower center", ncol=3, fontsize=8, frameon=True, facecolor="0.85")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout(rect=(0.0, 0.08, 1.0, 1.0))
    fig.savefig(path)
    return fig


def write_plots(
    log: FlightLog,
    offset_cam_m: Sequence[float],
    snapshots: Sequence[Snapshot],
    plots_dir: Path,
    scenario: str,
) -> list[str]:
    """All report plots into ``plots_dir``; returns their paths relative to its parent."""
    plots_dir.mkdir(parents=True, exist_ok=True)
    plot_trajectories(log, offset_cam_m, plots_dir / "trajectories.png", scenario)
    plot_errors(log, offset_cam_m, plots_dir / "errors.png", f"{scenario}: errors over time")
    plot_estimate_vs_truth(log, plots_dir / "estimate_vs_truth.png", f"{scenario}: relative position")
    names = ["trajectories.png", "errors.png", "estimate_vs_truth.png"]
    if snapshots:
        plot_camera_strip(snapshots, plots_dir / "camera.png", f"{scenario}: follower camera")
        names.append("camera.png")
    return [f"{plots_dir.name}/{n}" for n in names]
