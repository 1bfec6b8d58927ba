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
    ident = f.core.pipeline.identity
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
    """``report.md``: the per-follower table."""
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
    return "\n".join(lines) + "\n"


def write_formation_report(out_dir: Path, report: Mapping[str, Any]) -> None:
    """``report.json`` and ``report.md`` into ``out_dir``."""
    out_dir.mkdir(parents=True, exist_ok=True)
    write_json(out_dir / "report.json", report)
    (out_dir / "report.md").write_text(report_markdown(report))


def plot_from_above(result: FormationResult, plan: FormationPlan, path: Path, title: str) -> None:
    """Every vehicle's track seen from above, with the formation drawn every 10 s, and slot deviations."""
    import matplotlib as mpl  # noqa: PLC0415 (plots only)

    mpl.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    path.parent.mkdir(parents=True, exist_ok=True)
    t = np.asarray(result.t_s)
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(13, 6), gridspec_kw={"width_ratios": [1.2, 1]})
    names = list(result.p_ned_m)
    colour = {n: f"C{i}" for i, n in enumerate(names)}
    for n in names:
        p = np.asarray(result.p_ned_m[n])
        ax.plot(p[:, 1], p[:, 0], lw=2.0 if n == "leader" else 1.0, label=n, color=colour[n])
    step = max(1, round(10.0 / max(float(np.median(np.diff(t))) if t.size > 1 else 1.0, 1e-3)))
    for k in range(0, t.size, step):
        pts = np.array([result.p_ned_m[n][k] for n in names])
        if np.all(-pts[:, 2] > 1.0):
            ax.plot(pts[:, 1], pts[:, 0], "k.", ms=3)
            for j in range(1, len(names)):
                ax.plot([pts[0, 1], pts[j, 1]], [pts[0, 0], pts[j, 0]], color="0.7", lw=0.5)
    ax.set_xlabel("east, m")
    ax.set_ylabel("north, m")
    ax.set_aspect("equal", "datalim")
    ax.legend(fontsize=8)
    ax.set_title(f"{title}: from above (grey: the formation every 10 s)")
    for f in result.followers:
        tr = np.asarray(f.score.deviation_trace)
        if tr.size:
            ax2.plot(tr[:, 0], tr[:, 1], lw=1.0, label=f.name, color=colour[f.name])
    ax2.set_xlabel("sim time, s")
    ax2.set_ylabel("distance from the plan slot, m")
    ax2.legend(fontsize=8)
    ax2.set_title(f"plan {plan.name}: deviation in formation flight")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


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
