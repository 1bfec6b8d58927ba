"""A formation run's report: one entry per follower and the formation's worst figures, plus a plot.

``report.json`` keeps the single-follower keys (the worst follower's figure for each, so campaign
summaries read it as they read any run) and adds ``followers``: per follower ``name``, ``slot_m``,
``outcome``, ``formation_rmse_m`` and ``max_deviation_m`` (distance from the plan slot turned with the
leader's heading, in formation flight inside the scenario's window), ``min_separation_m`` (to any other
vehicle, whole flight) with ``min_separation_to``, ``leader_identity_swaps`` (from truth: the track sat on
a neighbour for 3 frames in a row), ``identity_swaps_detected`` (what the service itself caught),
``relative_position_rmse_m``, ``detection_recall``, ``gps_loss_s`` and ``transitions``.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.config import Config, FormationPlan
from companion.lab.evaluation.log import save_log
from companion.lab.evaluation.metrics import compute_metrics
from companion.lab.evaluation.report import write_json
from companion.lab.formation.run import FollowerRun, FormationResult


def _r(v: float | None, digits: int = 3) -> float | None:
    return None if v is None or not math.isfinite(v) else round(float(v), digits)


def follower_entry(f: FollowerRun, cfg: Config) -> dict[str, Any]:
    """One follower's entry of ``followers`` (see the module doc)."""
    log = f.scorer.freeze()
    m = compute_metrics(log, cfg.formation.offset_cam_m)
    ident = f.flight.identity
    counters = ident.counters if ident is not None else None
    return {
        "name": f.name,
        "slot_m": list(f.score.slot_leader_m),
        "outcome": m.outcome,
        "formation_rmse_m": _r(f.score.rmse_m),
        "max_deviation_m": _r(f.score.dev_max_m if f.score.dev_n else None),
        "min_separation_m": _r(f.score.min_separation_m),
        "min_separation_to": f.score.min_separation_to,
        "leader_identity_swaps": f.score.swaps,
        "frames_on_neighbour": f.score.frames_on_neighbour,
        "identity_swaps_detected": 0 if counters is None else counters.swaps,
        "identity_rejected": None
        if counters is None
        else {"neighbour": counters.neighbour_rejected, "far": counters.far_rejected},
        "relative_position_rmse_m": _r(m.relative_position_rmse_m),
        "detection_recall": _r(m.detection_recall),
        "false_positive_rate": _r(m.false_positive_rate),
        "formation_s": _r(m.formation_s, 1),
        "frames": m.frames,
        "gps_loss_s": log.gps_loss_t_s,
        "detector_compute_ms_p50": _r(float(np.median(f.compute_ms)) if f.compute_ms else None, 2),
        "transitions": [[round(t.t_s, 3), t.from_state, t.to_state, t.reason] for t in log.transitions],
    }


def _worst(entries: list[dict[str, Any]], key: str, pick: Any) -> Any:
    vals = [e[key] for e in entries if e[key] is not None]
    return pick(vals) if vals else None


def formation_outcome(entries: list[dict[str, Any]]) -> str:
    """``completed`` when every follower completed; otherwise the count of each outcome."""
    counts = Counter(e["outcome"] for e in entries)
    if set(counts) == {"completed"}:
        return "completed"
    if "crashed" in counts:
        return "crashed"
    if "aborted" in counts:
        return "aborted"
    return "partial"


def build_formation_report(
    scenario: str,
    seed: int,
    plan: FormationPlan,
    result: FormationResult,
    configs: Mapping[str, Config],
    *,
    extra: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """The formation's report dict (see the module doc)."""
    entries = [follower_entry(f, configs[f.name]) for f in result.followers]
    sim_s = result.t_s[-1] if result.t_s else 0.0
    report: dict[str, Any] = {
        "scenario": scenario,
        "seed": seed,
        "harness": "lockstep",
        "sim_duration_s": sim_s,
        "wall_s": round(result.wall_s, 2),
        "wall_s_per_sim_s": round(result.wall_s / sim_s, 3) if sim_s > 0 else None,
        "outcome": formation_outcome(entries),
        "outcomes": dict(Counter(e["outcome"] for e in entries)),
        "plan": plan.name,
        "followers": entries,
        "relative_position_rmse_m": _worst(entries, "relative_position_rmse_m", max),
        "relative_yaw_rmse_deg": None,
        "formation_rmse_m": _worst(entries, "formation_rmse_m", max),
        "formation_max_deviation_m": _worst(entries, "max_deviation_m", max),
        "min_separation_m": _worst(entries, "min_separation_m", min),
        "detection_recall": _worst(entries, "detection_recall", min),
        "false_positive_rate": _worst(entries, "false_positive_rate", max),
        "perception_latency_ms": None,
        "frames": sum(e["frames"] for e in entries),
        "gps_loss_s": _worst(entries, "gps_loss_s", min),
        "transitions": [],
        "leader_identity_swaps": sum(e["leader_identity_swaps"] for e in entries),
        "identity_swaps_detected": sum(e["identity_swaps_detected"] for e in entries),
    }
    if extra:
        report.update(extra)
    return report


def report_markdown(report: Mapping[str, Any]) -> str:
    """``report.md``: the per-follower table, then the plot (``plots`` in the report, relative links)."""
    lines = [
        f"# {report['scenario']} (seed {report['seed']}): {report['outcome']}",
        "",
        f"Plan `{report['plan']}`; {report['sim_duration_s']:.0f} s simulated in {report['wall_s']:.0f} s "
        f"({report['wall_s_per_sim_s']} s per simulated second), lockstep.",
        "",
        "| follower | slot (fwd, right) m | outcome | slot RMSE m | max deviation m | min separation m "
        "| identity swaps (caught) | recall |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for e in report["followers"]:
        slot = f"{e['slot_m'][0]:g}, {e['slot_m'][1]:g}"
        lines.append(
            f"| {e['name']} | {slot} | {e['outcome']} | {e['formation_rmse_m']} | {e['max_deviation_m']} | "
            f"{e['min_separation_m']} ({e['min_separation_to']}) | {e['leader_identity_swaps']} "
            f"({e['identity_swaps_detected']}) | {e['detection_recall']} |"
        )
    plots = report.get("plots") or []
    if plots:
        lines += ["", "## Plots", ""]
        lines += [f"![{Path(p).stem}](plots/{Path(p).name})" for p in plots]
    return "\n".join(lines) + "\n"


def write_formation_report(out_dir: Path, report: Mapping[str, Any]) -> None:
    """``report.json`` and ``report.md`` into ``out_dir``."""
    out_dir.mkdir(parents=True, exist_ok=True)
    write_json(out_dir / "report.json", report)
    (out_dir / "report.md").write_text(report_markdown(report))


def plot_from_above(result: FormationResult, plan: FormationPlan, path: Path, title: str) -> None:
    """Every vehicle's track seen from above with the formation's shape in time, and slot deviations."""
    draw_formation(
        np.asarray(result.t_s),
        {n: np.asarray(p) for n, p in result.p_ned_m.items()},
        {f.name: np.asarray(f.score.deviation_trace) for f in result.followers},
        plan_name=plan.name,
        path=path,
        title=title,
    )


#: The formation's shape is drawn this often, s, each labelled with its time.
SNAPSHOT_PERIOD_S = 10.0


def draw_formation(
    t_s: NDArray[np.float64],
    tracks_ned_m: Mapping[str, NDArray[np.float64]],
    deviations: Mapping[str, NDArray[np.float64]],
    *,
    plan_name: str,
    path: Path,
    title: str,
) -> Any:
    """The formation plot: tracks from above with the formation's shape in time, and slot deviations.

    Left: the tracks (``leader`` first in ``tracks_ned_m``; N x 3 NED, m) with start, end and direction,
    and the formation every :data:`SNAPSHOT_PERIOD_S` labelled with its sim time. Right: each follower's
    distance from its plan slot over time (``deviations``: K x 2 of time s, distance m). Returns the figure.
    """
    from matplotlib.figure import Figure  # noqa: PLC0415 (plots only)
    from matplotlib.lines import Line2D  # noqa: PLC0415

    from companion.lab.evaluation.plots import direction_arrows  # noqa: PLC0415 (matplotlib)

    path.parent.mkdir(parents=True, exist_ok=True)
    fig = Figure(figsize=(14, 7), dpi=110)
    ax, ax2 = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1.25, 1.0]})
    names = list(tracks_ned_m)
    colour = {n: f"C{i}" for i, n in enumerate(names)}
    for n in names:
        p = tracks_ned_m[n]
        leader = n == "leader"
        ax.plot(
            p[:, 1], p[:, 0], lw=2.2 if leader else 1.1, label=n, color=colour[n], zorder=3 if leader else 2
        )
        ax.plot(p[0, 1], p[0, 0], "o", mfc=colour[n], mec="k", ms=7, zorder=5)
        ax.plot(p[-1, 1], p[-1, 0], "s", mfc=colour[n], mec="k", ms=6, zorder=5)
    lead = tracks_ned_m[names[0]]
    direction_arrows(ax, lead[:, 1], lead[:, 0], colour[names[0]])
    step = max(
        1, round(SNAPSHOT_PERIOD_S / max(float(np.median(np.diff(t_s))) if t_s.size > 1 else 1.0, 1e-3))
    )
    drawn = 0
    for k in range(0, t_s.size, step):
        pts = np.array([tracks_ned_m[n][k] for n in names])
        if not np.all(-pts[:, 2] > 1.0):
            continue  # on the ground or climbing: no formation yet
        for j in range(1, len(names)):
            ax.plot([pts[0, 1], pts[j, 1]], [pts[0, 0], pts[j, 0]], color="0.55", lw=0.7, zorder=1)
        ax.plot(pts[:, 1], pts[:, 0], "k.", ms=3, zorder=4)
        ax.annotate(f"{t_s[k]:.0f} s", (pts[0, 1], pts[0, 0]), xytext=(4, 4), textcoords="offset points",
                    fontsize=7, color="0.25", zorder=6)  # fmt: skip
        drawn += 1
    ax.plot([], [], "o", mfc="w", mec="k", ms=7, label=f"start (t = {t_s[0]:.0f} s)")
    ax.plot([], [], "s", mfc="w", mec="k", ms=6, label=f"end (t = {t_s[-1]:.0f} s)")
    ax.add_line(Line2D([], [], color="0.55", lw=0.7, label=f"the formation every {SNAPSHOT_PERIOD_S:.0f} s"))
    ax.set_xlabel("east, m")
    ax.set_ylabel("north, m")
    ax.set_aspect("equal", "datalim")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="best", framealpha=0.9)
    ax.set_title(
        f"{title}: from above (arrows: the leader's direction; grey: formation, sim time)", fontsize=10
    )
    for n, tr in deviations.items():
        if tr.size:
            ax2.plot(tr[:, 0], tr[:, 1], lw=1.0, label=n, color=colour.get(n, "k"))
    ax2.set_xlabel("sim time, s")
    ax2.set_ylabel("distance from the plan slot, m")
    ax2.grid(alpha=0.3)
    if ax2.lines:
        ax2.legend(fontsize=8)
    ax2.set_title(
        f"plan {plan_name}: each follower's distance from its slot in formation flight", fontsize=10
    )
    fig.tight_layout()
    fig.savefig(path)
    return fig


def save_logs(result: FormationResult, out_dir: Path) -> None:
    """The run's logs: the formation's truth and each follower's flight log.

    ``formation_log.npz``: ``t_s``, ``leader_yaw_rad`` and each vehicle's true world NED track (m);
    ``followers/<name>/flight_log.npz``: each follower's log.
    """
    arrays = {"t_s": np.asarray(result.t_s), "leader_yaw_rad": np.asarray(result.leader_yaw_rad)}
    for n, p in result.p_ned_m.items():
        arrays[f"p_ned_m_{n}"] = np.asarray(p)
    np.savez_compressed(out_dir / "formation_log.npz", **arrays)  # type: ignore[arg-type]
    for f in result.followers:
        folder = out_dir / "followers" / f.name
        folder.mkdir(parents=True, exist_ok=True)
        save_log(f.scorer.freeze(), folder / "flight_log.npz")
