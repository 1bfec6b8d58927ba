"""Where a run's deviation from the slot comes from: the split a report keeps, ``companion deviation`` prints.

Pure numpy over a :class:`~companion.lab.evaluation.log.FlightLog` (truth, the service's estimate, heading and
velocity command per tick; the measured range per frame). Two splits of the largest deviation, each adding up
to it (projected on its direction, m):

* **what the law knew**: the true formation error is the error the law saw (its estimate, in its own heading
  frame, minus the slot) plus the perception error (the estimate against the truth in the camera's level
  frame: range and bearing, not the autopilot's heading);
* **how it got there** over the ``WINDOW_S`` before it, in NED: the error it started from, the leader's motion
  against the velocity the law commanded, the autopilot's tracking of that command (commanded minus achieved
  velocity, integrated) and the slot turning with the follower's heading.

Beside them, run-wide: the estimate's error in NED and in the camera frame (the difference is the heading),
the autopilot's velocity tracking (RMS error and its lag), range outliers the tracker accepted, missed frames
while the leader was in view, how many large errors follow a leader manoeuvre, a frame gap or an outlier,
and how regular the control ticks were. Definitions are the report's (docs/evaluation.md).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.lab.evaluation.log import F64, FlightLog
from companion.lab.evaluation.metrics import offset_cam_to_level_body, to_heading_frame

#: The "how it got there" split looks this far back from the largest deviation, s.
WINDOW_S = 2.0
#: A measurement whose range is off the truth by more than this is an outlier, m.
OUTLIER_M = 0.5
#: A formation error this large counts as "large" in the run-wide attribution, m.
LARGE_M = 0.25
#: A large error is attributed to a cause up to this long after it, s.
CAUSE_HORIZON_S = 3.0
#: The leader manoeuvres while its acceleration is over this, m/s^2.
MANOEUVRE_M_S2 = 0.5
#: Frames further apart than this (while the leader is in view) make a gap, s.
GAP_S = 0.3
#: The autopilot's lag behind the velocity command is looked for up to this, s.
MAX_LAG_S = 1.0


def _rot_z(v: F64, yaw_rad: F64) -> F64:
    """N x 3 heading-frame vectors turned into NED by each row's yaw."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    out = np.empty_like(v)
    out[:, 0] = c * v[:, 0] - s * v[:, 1]
    out[:, 1] = s * v[:, 0] + c * v[:, 1]
    out[:, 2] = v[:, 2]
    return out


def _trapz(y: F64, t: F64) -> F64:
    """Trapezoid integral of N x 3 samples over ``t`` (NaN rows count as zero)."""
    if len(t) < 2:
        return np.zeros(y.shape[1])
    y = np.nan_to_num(y)
    dt = np.diff(t)[:, None]
    out: F64 = np.sum(0.5 * (y[1:] + y[:-1]) * dt, axis=0)
    return out


def _rms(x: F64) -> float | None:
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(np.square(x)))) if x.size else None


def _r(x: float | None, digits: int = 3) -> float | None:
    return None if x is None or not math.isfinite(x) else round(float(x), digits)


def rate(x: F64, t: F64, k: int = 2) -> F64:
    """``dx/dt`` per sample (rows of ``x`` over times ``t``) from the samples ``k`` either side.

    Over a few ticks, not one: ticks on the real path can share a stamp or come 1 ms apart.
    """
    n = len(t)
    out = np.zeros_like(x)
    if n < 2:
        return out
    lo, hi = np.clip(np.arange(n) - k, 0, n - 1), np.clip(np.arange(n) + k, 0, n - 1)
    dt = t[hi] - t[lo]
    ok = dt > 1e-6
    out[ok] = (x[hi[ok]] - x[lo[ok]]) / dt[ok, None]
    return out


def leader_velocity(log: FlightLog) -> F64:
    """The leader's true velocity (NED m/s) per tick, differentiated from its positions."""
    return rate(log.p_ned_leader_m, log.t_s)


def lag_s(v_cmd: F64, v_act: F64, dt_s: float) -> float | None:
    """The delay (s) at which the achieved horizontal velocity best matches the command, or None."""
    ok = np.all(np.isfinite(v_cmd[:, :2]), axis=1) & np.all(np.isfinite(v_act[:, :2]), axis=1)
    if ok.sum() < 40 or dt_s <= 0.0:
        return None
    best, best_err = 0, math.inf
    for k in range(int(MAX_LAG_S / dt_s) + 1):
        a = v_cmd[: len(v_cmd) - k, :2]
        b = v_act[k:, :2]
        m = ok[: len(ok) - k] & ok[k:]
        if m.sum() < 40:
            break
        err = float(np.mean(np.sum(np.square(a[m] - b[m]), axis=1)))
        if err < best_err:
            best, best_err = k, err
    return best * dt_s


def split_deviation(
    log: FlightLog, offset_cam_m: Sequence[float], window_s: float = WINDOW_S
) -> dict[str, Any] | None:
    """The split of the run's largest deviation and the run-wide figures (None: no formation ticks).

    ``offset_cam_m``: the slot (camera frame, m); ``window_s``: how far back "how it got there" looks, s.
    """
    sel = log.formation
    if not sel.any():
        return None
    t = log.t_s
    slot = offset_cam_to_level_body(offset_cam_m)
    rel_true = log.p_ned_leader_m - log.p_ned_follower_m
    e_true_h = to_heading_frame(rel_true, log.yaw_follower_rad) - slot
    have_yaw = log.yaw_service_rad.size == len(t)
    yaw_svc = log.yaw_service_rad if have_yaw else np.full(len(t), np.nan)
    e_law_h = to_heading_frame(log.rel_ned_est_m, yaw_svc) - slot
    dev = np.linalg.norm(e_true_h, axis=1)
    idx = np.flatnonzero(sel)
    k = int(idx[np.argmax(dev[idx])])
    u = e_true_h[k] / max(dev[k], 1e-9)

    # What the law knew: the error it saw plus the perception error, on the deviation's direction.
    seen = e_law_h[k] if np.all(np.isfinite(e_law_h[k])) else None
    knew: dict[str, float | None] = {
        "error_the_law_saw_m": None if seen is None else _r(float(seen @ u)),
        "perception_error_m": None if seen is None else _r(float((e_true_h[k] - seen) @ u)),
    }

    # How it got there, in NED, over the window before the maximum.
    v_cmd = log.v_cmd_ned_m_s if log.v_cmd_ned_m_s.shape == (len(t), 3) else np.full((len(t), 3), np.nan)
    k0 = int(np.searchsorted(t, t[k] - window_s))
    w = slice(k0, k + 1)
    slot_ned = _rot_z(np.tile(slot, (len(t), 1)), log.yaw_follower_rad)
    e_ned = rel_true - slot_ned
    u_ned = e_ned[k] / max(float(np.linalg.norm(e_ned[k])), 1e-9)
    commanded = bool(np.all(np.isfinite(v_cmd[w])))
    d_rel = rel_true[k] - rel_true[k0]
    turn = -(slot_ned[k] - slot_ned[k0])
    got: dict[str, float | None] = {"window_s": _r(t[k] - t[k0], 2), "start_m": _r(float(e_ned[k0] @ u_ned))}
    if commanded:
        px4 = -_trapz(log.v_ned_follower_m_s[w] - v_cmd[w], t[w])
        got["leader_against_command_m"] = _r(float((d_rel - px4) @ u_ned))
        got["autopilot_tracking_m"] = _r(float(px4 @ u_ned))
    else:  # attitude setpoints (no GPS): the law and the autopilot are one loop here
        got["leader_against_command_m"] = None
        got["autopilot_tracking_m"] = None
        got["leader_and_follower_m"] = _r(float(d_rel @ u_ned))
    got["follower_turn_m"] = _r(float(turn @ u_ned))

    # Context of the maximum.
    v_lead = leader_velocity(log)
    a_lead = rate(v_lead, t)
    a_lead_h = np.linalg.norm(a_lead[:, :2], axis=1)
    fr = _frame_figures(log, (t[k0], t[k]))
    at_max = {
        "t_s": _r(t[k], 2),
        "deviation_m": _r(dev[k]),
        "state": log.state[k] if k < len(log.state) else None,
        "leader_accel_max_m_s2": _r(float(np.max(a_lead_h[w])), 2),
        **{f"window_{key}": value for key, value in fr.items()},
    }

    # Run-wide.
    est_ok = sel & np.all(np.isfinite(log.rel_ned_est_m), axis=1)
    ned_err = np.linalg.norm(log.rel_ned_est_m - rel_true, axis=1)[est_ok]
    cam_err = np.linalg.norm(e_true_h - e_law_h, axis=1)[est_ok & np.isfinite(yaw_svc)]
    vel_ok = sel & np.all(np.isfinite(v_cmd), axis=1)
    track_err = np.linalg.norm((log.v_ned_follower_m_s - v_cmd)[vel_ok][:, :2], axis=1)
    dt = float(np.median(np.diff(t))) if len(t) > 2 else 0.0
    v_cmd_sel = np.where(vel_ok[:, None], v_cmd, np.nan)
    run = {
        "formation_rmse_m": _r(_rms(dev[idx])),
        "estimate_rmse_ned_m": _r(_rms(ned_err)),
        "estimate_rmse_camera_frame_m": _r(_rms(cam_err)),
        "autopilot_velocity_error_rms_m_s": _r(_rms(track_err)),
        "autopilot_lag_s": _r(lag_s(v_cmd_sel, log.v_ned_follower_m_s, dt), 2),
        **_frame_figures(log, (t[idx[0]], t[idx[-1]])),
        "large_errors": _attribute(log, dev, a_lead_h),
        "ticks": _tick_figures(t[(t >= t[idx[0]]) & (t <= t[idx[-1]])]),
    }
    return {
        "slot_cam_m": [float(c) for c in offset_cam_m],
        "at_max": at_max,
        "what_the_law_knew": knew,
        "how_it_got_there": got,
        "run": run,
    }


def split_row(split: dict[str, Any] | None) -> dict[str, float | None]:
    """One line of a campaign's split table: the largest deviation and its parts, m."""
    if not split:
        return {}
    a, knew, got, run = split["at_max"], split["what_the_law_knew"], split["how_it_got_there"], split["run"]
    return {
        "t_s": a["t_s"],
        "deviation_m": a["deviation_m"],
        "perception_m": knew["perception_error_m"],
        "leader_against_command_m": got.get("leader_against_command_m"),
        "autopilot_tracking_m": got.get("autopilot_tracking_m"),
        "estimate_rmse_ned_m": run["estimate_rmse_ned_m"],
        "estimate_rmse_camera_frame_m": run["estimate_rmse_camera_frame_m"],
        "frames_missed_in_window": a["window_frames_missed_in_view"],
        "range_outliers_taken": run["range_outliers_taken"],
        "tick_interval_max_ms": run["ticks"]["interval_max_ms"],
    }


def _frame_figures(log: FlightLog, span_s: tuple[float, float]) -> dict[str, Any]:
    """Outliers the tracker took and frames missed with the leader in view, over ``span_s``."""
    ft = log.frame_t_s
    m = (ft >= span_s[0]) & (ft <= span_s[1])
    rng_true = np.linalg.norm(log.frame_rel_true_ned_m, axis=1) if len(ft) else np.empty(0)
    rng_meas = log.frame_range_meas_m if log.frame_range_meas_m.size == len(ft) else np.full(len(ft), np.nan)
    took = m & np.isfinite(rng_meas) & np.isfinite(rng_true)
    r_err = rng_meas[took] - rng_true[took]
    visible = m & log.frame_leader_visible
    if log.frame_range_meas_m.size != len(ft):  # a log that did not keep the measurements
        return {"range_outliers_taken": None, "range_error_max_m": None, "frames_in_view": int(visible.sum()),
                "frames_missed_in_view": None, "longest_gap_s": None}  # fmt: skip
    missed = visible & ~np.isfinite(rng_meas)
    gaps = _gaps(ft[m & np.isfinite(rng_meas)]) if took.any() else []
    return {
        "range_outliers_taken": int(np.sum(np.abs(r_err) > OUTLIER_M)),
        "range_error_max_m": _r(float(np.max(np.abs(r_err)))) if r_err.size else None,
        "frames_in_view": int(visible.sum()),
        "frames_missed_in_view": int(missed.sum()),
        "longest_gap_s": _r(max(gaps, default=0.0), 2),
    }


def _gaps(t_updates: F64) -> list[float]:
    if t_updates.size < 2:
        return []
    d = np.diff(t_updates)
    return [float(x) for x in d[d > GAP_S]]


def _attribute(log: FlightLog, dev: F64, a_lead_h: F64) -> dict[str, Any]:
    """Of the formation ticks over ``LARGE_M``: the share that follow each cause within the horizon."""
    t, sel = log.t_s, log.formation
    large = sel & (dev > LARGE_M)
    n = int(large.sum())
    ft = log.frame_t_s
    rng_meas = log.frame_range_meas_m if log.frame_range_meas_m.size == len(ft) else np.full(len(ft), np.nan)
    rng_true = np.linalg.norm(log.frame_rel_true_ned_m, axis=1) if len(ft) else np.empty(0)
    outlier_t = ft[np.isfinite(rng_meas) & (np.abs(rng_meas - rng_true) > OUTLIER_M)]
    upd = ft[np.isfinite(rng_meas)]
    gap_end_t = upd[1:][np.diff(upd) > GAP_S] if upd.size > 1 else np.empty(0)
    manoeuvre_t = t[a_lead_h > MANOEUVRE_M_S2]

    def after(events: F64) -> NDArray[np.bool_]:
        if events.size == 0:
            return np.zeros(len(t), dtype=bool)
        j = np.searchsorted(events, t, side="right") - 1
        ok = j >= 0
        out = np.zeros(len(t), dtype=bool)
        out[ok] = t[ok] - events[j[ok]] <= CAUSE_HORIZON_S
        return out

    share = {}
    for name, ev in (
        ("leader_manoeuvre", manoeuvre_t),
        ("frame_gap", gap_end_t),
        ("range_outlier", outlier_t),
    ):
        share[name] = _r(float(np.mean(after(np.sort(ev))[large])), 2) if n else None
    return {"ticks_over_m": LARGE_M, "ticks": n, "share_following": share}


def _tick_figures(t_formation: F64) -> dict[str, float | None]:
    """How regular the control ticks over the formation were (sim s): their interval's p50, p99 and max."""
    if t_formation.size < 3:
        return {"interval_p50_ms": None, "interval_p99_ms": None, "interval_max_ms": None}
    d = np.diff(t_formation) * 1e3
    p50, p99 = np.percentile(d, [50.0, 99.0])
    return {"interval_p50_ms": _r(p50, 1), "interval_p99_ms": _r(p99, 1), "interval_max_ms": _r(d.max(), 1)}


def split_markdown(split: dict[str, Any] | None) -> list[str]:
    """The split as report lines (empty without one)."""
    if not split:
        return []
    a, knew, got, run = split["at_max"], split["what_the_law_knew"], split["how_it_got_there"], split["run"]

    def f(v: Any, unit: str = " m") -> str:
        """A signed part of a split."""
        return "n/a" if v is None else f"{v:+.3f}{unit}" if isinstance(v, float) else f"{v}{unit}"

    def g(v: Any, unit: str = " m") -> str:
        """A magnitude."""
        return "n/a" if v is None else f"{v:.3f}{unit}" if isinstance(v, float) else f"{v}{unit}"

    lines = [
        "## Where the deviation comes from",
        "",
        f"Largest deviation {a['deviation_m']:.3f} m at {a['t_s']:.2f} s ({a['state']}), split two ways "
        "(each part projected on the deviation's direction; each split adds up to it):",
        "",
        f"| what the law knew | m | how it got there (last {got['window_s']} s) | m |",
        "|---|---|---|---|",
        f"| the error the law saw | {f(knew['error_the_law_saw_m'], '')} | the error it started from | "
        f"{f(got['start_m'], '')} |",
        f"| perception (estimate vs truth, camera frame) | {f(knew['perception_error_m'], '')} | "
        f"the leader's motion against the command | {f(got.get('leader_against_command_m'), '')} |",
        f"| | | the autopilot's tracking of the command | {f(got.get('autopilot_tracking_m'), '')} |",
        f"| | | the slot turning with the follower | {f(got['follower_turn_m'], '')} |",
    ]
    if got.get("leader_and_follower_m") is not None:
        lines.append(
            f"| | | leader and follower (attitude setpoints) | {f(got['leader_and_follower_m'], '')} |"
        )
    lines += [
        "",
        f"Around it: the leader's acceleration up to {a['leader_accel_max_m_s2']} m/s^2; frames with the "
        f"leader in view {a['window_frames_in_view']}, missed {a['window_frames_missed_in_view']}, longest "
        f"gap {a['window_longest_gap_s']} s; range outliers taken {a['window_range_outliers_taken']}.",
        "",
        f"Over the formation: estimate RMSE {g(run['estimate_rmse_ned_m'])} in NED, "
        f"{g(run['estimate_rmse_camera_frame_m'])} in the camera frame (the difference is the heading); "
        f"the autopilot's velocity error {g(run['autopilot_velocity_error_rms_m_s'], ' m/s')} RMS, lag "
        f"{g(run['autopilot_lag_s'], ' s')}; range outliers taken {run['range_outliers_taken']} (largest "
        f"range error {g(run['range_error_max_m'])}); frames missed with the leader in view "
        f"{run['frames_missed_in_view']} of {run['frames_in_view']}, longest gap {run['longest_gap_s']} s; "
        f"control tick interval p50 / p99 / max {run['ticks']['interval_p50_ms']} / "
        f"{run['ticks']['interval_p99_ms']} / {run['ticks']['interval_max_ms']} ms.",
    ]
    large = run["large_errors"]
    if large["ticks"]:
        sh = large["share_following"]
        lines += [
            "",
            f"Of the {large['ticks']} formation ticks over {large['ticks_over_m']} m, within "
            f"{CAUSE_HORIZON_S:.0f} s after a leader manoeuvre {sh['leader_manoeuvre']:.0%}, a frame gap "
            f"{sh['frame_gap']:.0%}, a range outlier {sh['range_outlier']:.0%}.",
        ]
    return lines
