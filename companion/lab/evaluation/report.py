"""Reports: ``report.json`` (a contract other tools read), ``report.md``, and the all-scenario summary.

report.json keys (add freely, never rename): scenario, seed, sim_duration_s, wall_s, outcome,
relative_position_rmse_m, relative_yaw_rmse_deg, formation_rmse_m, formation_max_deviation_m,
min_separation_m, detection_recall, false_positive_rate, perception_latency_ms {p50, p95, p99}, frames,
gps_loss_s (sim time of the follower's GPS loss, null if none), transitions ([t_s, from, to, reason]),
join_s and join_overshoot_m (how the follower got into its slot, metrics.join_figures).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

from companion.lab.evaluation.deviation import split_deviation, split_markdown
from companion.lab.evaluation.host import starved
from companion.lab.evaluation.log import FlightLog
from companion.lab.evaluation.metrics import (
    PAPER_ROW_NAMES,
    PAPER_TABLE,
    TARGETS,
    FlightMetrics,
    intended_outcome,
    outcome_words,
)

REQUIRED_KEYS = (
    "scenario",
    "seed",
    "sim_duration_s",
    "wall_s",
    "outcome",
    "relative_position_rmse_m",
    "relative_yaw_rmse_deg",
    "formation_rmse_m",
    "formation_max_deviation_m",
    "min_separation_m",
    "detection_recall",
    "false_positive_rate",
    "perception_latency_ms",
    "frames",
    "gps_loss_s",
    "transitions",
)


def build_report(
    scenario: str,
    seed: int,
    log: FlightLog,
    metrics: FlightMetrics,
    *,
    wall_s: float,
    extra: Mapping[str, Any] | None = None,
    offset_cam_m: Sequence[float] | None = None,
) -> dict[str, Any]:
    """The report dict: the contract keys first, then targets and extras.

    With the slot's ``offset_cam_m`` it also keeps where the largest deviation came from
    (:func:`~companion.lab.evaluation.deviation.split_deviation`).
    """
    m = asdict(metrics)
    report: dict[str, Any] = {
        "scenario": scenario,
        "seed": seed,
        "sim_duration_s": float(log.t_s[-1] - log.t_s[0]) if log.t_s.size else 0.0,
        "wall_s": wall_s,
        "outcome": metrics.outcome,
        "relative_position_rmse_m": m["relative_position_rmse_m"],
        "relative_yaw_rmse_deg": m["relative_yaw_rmse_deg"],
        "formation_rmse_m": m["formation_rmse_m"],
        "formation_max_deviation_m": m["formation_max_deviation_m"],
        "min_separation_m": m["min_separation_m"],
        "detection_recall": m["detection_recall"],
        "false_positive_rate": m["false_positive_rate"],
        "perception_latency_ms": m["perception_latency_ms"],
        "frames": metrics.frames,
        "gps_loss_s": log.gps_loss_t_s,
        "transitions": [[round(t.t_s, 3), t.from_state, t.to_state, t.reason] for t in log.transitions],
        "formation_s": metrics.formation_s,
        "join_s": metrics.join_s,
        "join_overshoot_m": metrics.join_overshoot_m,
    }
    intended, because = intended_outcome(scenario)
    if because:
        report["intended_outcome"] = intended
        report["intended_because"] = because
    if scenario in TARGETS:
        report["targets"] = dict(TARGETS[scenario])
        report["meets_targets"] = meets_targets(report)
    if scenario in PAPER_TABLE:
        pos, yaw, dev = PAPER_TABLE[scenario]
        report["paper"] = {
            "relative_position_rmse_m": pos,
            "relative_yaw_rmse_deg": yaw,
            "formation_max_deviation_m": dev,
        }
    if extra:
        report.update(extra)
    if offset_cam_m is not None:
        report["deviation_split"] = split_deviation(log, offset_cam_m)
    if isinstance(report.get("host"), dict):
        report["host"]["starved_because"] = starved(report["host"], report)
    return report


def meets_targets(report: Mapping[str, Any]) -> bool:
    """True when every target of the scenario is met (a missing figure never meets a target)."""
    targets = TARGETS.get(str(report["scenario"]), {})
    return all(report.get(k) is not None and report[k] <= v for k, v in targets.items())


def _fmt(v: Any, digits: int = 2) -> str:
    if v is None:
        return "n/a"
    if isinstance(v, float):
        return f"{v:.{digits}f}"
    return str(v)


def report_markdown(report: Mapping[str, Any]) -> str:
    """A human report for one scenario."""
    lat = report["perception_latency_ms"]
    lines = [
        f"# Scenario `{report['scenario']}` (seed {report['seed']})",
        "",
        f"Outcome: **{outcome_words(report)}**; {report['sim_duration_s']:.1f} s simulated in "
        f"{report['wall_s']:.1f} s wall; {report['frames']} camera frames; "
        f"{report.get('formation_s', 0.0):.1f} s in formation.",
        "",
        "| metric | ours | paper | target |",
        "|---|---|---|---|",
    ]
    paper = report.get("paper", {})
    targets = report.get("targets", {})
    for key, label, digits in (
        ("relative_position_rmse_m", "relative position RMSE (m)", 3),
        ("relative_yaw_rmse_deg", "relative yaw (bearing) RMSE (deg)", 2),
        ("formation_rmse_m", "formation RMSE (m)", 3),
        ("formation_max_deviation_m", "formation max deviation (m)", 3),
        ("min_separation_m", "minimum separation (m)", 2),
        ("min_obstacle_clearance_m", "closest to a tree or building (m, centre to its envelope)", 2),
        ("detection_recall", "detection recall", 3),
        ("false_positive_rate", "false positives per frame", 4),
    ):
        t = targets.get(key)
        lines.append(
            f"| {label} | {_fmt(report.get(key), digits)} | {_fmt(paper.get(key), digits)} | "
            f"{'<= ' + _fmt(t, digits) if t is not None else ''} |"
        )
    lines.append(
        f"| perception latency p50/p95/p99 (ms) | {_fmt(lat['p50'], 1)} / {_fmt(lat['p95'], 1)} / "
        f"{_fmt(lat['p99'], 1)} | 38 (mean, RTX 3060) | |"
    )
    if report.get("join_s") is not None:
        lines += [
            "",
            f"Join: in the slot (error under 0.3 m) {report['join_s']:.1f} s after entering the formation; "
            f"overshoot past the slot's range {_fmt(report.get('join_overshoot_m'), 3)} m.",
        ]
    if report.get("crash_reason"):
        lines += ["", f"Crash: {report['crash_reason']}."]
    if report.get("gps_loss_s") is not None:
        lines += ["", f"Follower GPS lost at t = {report['gps_loss_s']:.1f} s."]
    if report["transitions"]:
        lines += ["", "## Mission transitions", "", "| t (s) | from | to | reason |", "|---|---|---|---|"]
        lines += [f"| {t:.2f} | {a} | {b} | {r} |" for t, a, b, r in report["transitions"]]
    host = report.get("host")
    if host:
        why = host.get("starved_because") or []
        lines += [
            "",
            f"Host: {host.get('cores')} cores, {_fmt(host.get('machine_busy_frac'))} busy over the run, "
            f"other work {_fmt(host.get('others_cpu_frac'))} of it; "
            + ("**starved**: " + "; ".join(why) + "." if why else "the run was not held back."),
        ]
    split = report.get("deviation_split")
    if split:
        lines += ["", *split_markdown(split)]
    lines += _autopilot_markdown(report.get("autopilot"))
    plots = report.get("plots")
    if plots:
        lines += ["", "## Plots", ""] + [f"![{Path(p).stem}]({p})" for p in plots]
    return "\n".join(lines) + "\n"


#: STATUSTEXT severities the report lists (the others are in report.json).
_LOUD = frozenset({"emergency", "alert", "critical", "error", "warning"})


def _autopilot_markdown(ap: Mapping[str, Any] | None) -> list[str]:
    """What the follower's autopilot did by itself: its modes, its loud texts, its failsafes, its logs."""
    if not ap:
        return []
    name = "PX4 SITL (SIH)" if ap.get("backend") == "px4" else "the simulator's own autopilot"
    modes = " -> ".join(
        f"{m['mode']}{'' if m['armed'] else ' (disarmed)'} at {m['t_s']:.1f} s" for m in ap["follower_modes"]
    )
    lines = ["", f"## Autopilot: {name}", "", f"Follower modes (HEARTBEAT): {modes or 'none seen'}."]
    failsafes = ap.get("follower_failsafes", [])
    lines.append(
        "Follower failsafes: "
        + ("; ".join(f"{f['t_s']:.1f} s {f['text']}" for f in failsafes) if failsafes else "none")
        + "."
    )
    loud = [t for t in ap.get("texts", []) if t["vehicle"] == "follower" and t["severity"] in _LOUD]
    if loud:
        lines += ["", "| t (s) | severity | follower's STATUSTEXT |", "|---|---|---|"]
        lines += [f"| {t['t_s']:.2f} | {t['severity']} | {t['text']} |" for t in loud]
    if ap.get("flight_logs"):
        lines += ["", "Flight logs (ULog): " + ", ".join(f"`{p}`" for p in ap["flight_logs"]) + "."]
    return lines


def summary_markdown(reports: Mapping[str, Mapping[str, Any]]) -> str:
    """The paper's table beside ours, then every scenario's headline figures."""
    lines = [
        "# Wingman vs the paper",
        "",
        "Paper: XTDrone/Gazebo SITL, YOLOv8 on an RTX 3060. Ours: Wingman SITL (JSBSim, PX4-like autopilot "
        "over MAVLink); the harness and detector of each run are in the second table. Lower is better; "
        "the targets are the project's, about twice as tight as the paper's.",
        "",
        *_detector_note(reports),
        "| scenario | position RMSE (m) paper / ours | yaw RMSE (deg) paper / ours "
        "| max deviation (m) paper / ours | outcome | targets met |",
        "|---|---|---|---|---|---|",
    ]
    for key, name in PAPER_ROW_NAMES.items():
        r = reports.get(key)
        pos, yaw, dev = PAPER_TABLE[key]
        if r is None:
            lines.append(f"| {name} | {pos:.2f} / not run | {yaw:.1f} / not run | {dev:.2f} / not run | | |")
            continue
        lines.append(
            f"| {name} | {pos:.2f} / {_fmt(r['relative_position_rmse_m'], 3)} | {yaw:.1f} / "
            f"{_fmt(r['relative_yaw_rmse_deg'], 2)} | {dev:.2f} / {_fmt(r['formation_max_deviation_m'], 3)} "
            f"| {outcome_words(r)} | {'yes' if r.get('meets_targets') else 'no'} |"
        )
    lines += [
        "",
        "## All scenarios",
        "",
        "| scenario | outcome | rel. pos RMSE (m) | yaw RMSE (deg) | formation RMSE (m) | max dev (m) "
        "| min sep (m) | recall | FP/frame | latency p50 (ms) | harness | detector |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, r in reports.items():
        lines.append(
            f"| {name} | {outcome_words(r)} | {_fmt(r['relative_position_rmse_m'], 3)} | "
            f"{_fmt(r['relative_yaw_rmse_deg'], 2)} | {_fmt(r['formation_rmse_m'], 3)} | "
            f"{_fmt(r['formation_max_deviation_m'], 3)} | {_fmt(r['min_separation_m'], 2)} | "
            f"{_fmt(r['detection_recall'], 3)} | {_fmt(r['false_positive_rate'], 4)} | "
            f"{_fmt(r['perception_latency_ms']['p50'], 1)} | {r.get('harness', '?')} | "
            f"{r.get('detector', '?')} |"
        )
    intended = [(name, r) for name, r in reports.items() if r.get("intended_because")]
    if intended:
        lines.append("")
        lines += [
            f"`{name}` is meant to end `{r['intended_outcome']}`: {r['intended_because']}."
            for name, r in intended
        ]
    return "\n".join(lines) + "\n"


def _detector_note(reports: Mapping[str, Mapping[str, Any]]) -> list[str]:
    """A warning line when any run used the simulator's boxes instead of the network."""
    truth = [name for name, r in reports.items() if "ground-truth" in str(r.get("detector", ""))]
    if not truth:
        return []
    return [
        f"**Detector: ground-truth boxes from the simulator (not the network) in {', '.join(truth)}**: these "
        "figures check the pose, tracker and control path, not vision.",
        "",
    ]


def write_json(path: Path, data: Any) -> None:
    """Write JSON atomically (a reader never sees half a report)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(data, indent=2, allow_nan=False) + "\n")
    tmp.replace(path)


def write_report(out_dir: Path, report: Mapping[str, Any]) -> None:
    """``out_dir/report.json`` and ``out_dir/report.md``."""
    write_json(out_dir / "report.json", report)
    (out_dir / "report.md").write_text(report_markdown(report))


def write_summary(out_dir: Path, reports: Mapping[str, Mapping[str, Any]]) -> None:
    """``out_dir/summary.json`` (scenario name -> report) and ``out_dir/summary.md``."""
    write_json(out_dir / "summary.json", dict(reports))
    (out_dir / "summary.md").write_text(summary_markdown(reports))


def missing_keys(report: Mapping[str, Any], keys: Sequence[str] = REQUIRED_KEYS) -> list[str]:
    """Contract keys absent from a report (empty when it honours the contract)."""
    return [k for k in keys if k not in report]
