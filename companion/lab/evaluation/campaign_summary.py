"""A campaign's Monte Carlo summary: every seed's report, percentiles of each metric, ``summary.json/.md``."""

from __future__ import annotations

import json
from collections import Counter
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from companion.lab.evaluation.metrics import monte_carlo_summary
from companion.lab.evaluation.report import write_json

if TYPE_CHECKING:
    from companion.lab.evaluation.campaign import RunSpec

#: What the Monte Carlo summary keeps of each run.
SEED_KEYS = (
    "seed",
    "outcome",
    "relative_position_rmse_m",
    "relative_yaw_rmse_deg",
    "formation_rmse_m",
    "formation_max_deviation_m",
    "min_separation_m",
    "min_obstacle_clearance_m",
    "touchdown_m_s",
    "outcomes",
    "leader_identity_swaps",
    "identity_swaps_detected",
    "host",
)


def campaign_summary(
    specs: Sequence[RunSpec],
    reports: Mapping[str, Mapping[str, Any]],
    failed: Sequence[str],
    *,
    wall_s: float,
    executor: str,
    resumed: int = 0,
) -> dict[str, Any]:
    """The Monte Carlo summary of a campaign: every seed's report (by folder name) and the failed runs.

    ``wall_s`` is this invocation's; ``resumed`` counts the seeds whose reports an earlier one wrote.
    """
    first = specs[0] if specs else None
    return {
        "scenario": first.scenario if first else None,
        "seeds": [s.seed for s in specs],
        "harness": first.harness if first else None,
        "detector": next(iter(reports.values())).get("detector") if reports else None,
        "formation_duration_s": first.duration_s if first else None,
        "executor": executor,
        "wall_s": round(wall_s, 1),
        "resumed": resumed,
        "failed": list(failed),
        **monte_carlo_summary(reports.values()),
        **formation_summary(reports.values()),
        "runs_by_seed": {name: {k: r.get(k) for k in SEED_KEYS} for name, r in reports.items()},
    }


def formation_summary(reports: Any) -> dict[str, Any]:
    """Formation campaigns: every follower's outcome counted, identity swaps summed, the worst follower."""
    runs = [r for r in reports if "followers" in r]
    if not runs:
        return {}
    followers = [f for r in runs for f in r["followers"]]
    worst_sep = min(
        (f for f in followers if f["min_separation_m"] is not None),
        key=lambda f: f["min_separation_m"],
        default=None,
    )
    devs = [f["max_deviation_m"] for f in followers if f["max_deviation_m"] is not None]
    return {
        "follower_outcomes": dict(Counter(f["outcome"] for f in followers)),
        "leader_identity_swaps": sum(f["leader_identity_swaps"] for f in followers),
        "identity_swaps_detected": sum(f["identity_swaps_detected"] for f in followers),
        "worst_separation_m": None if worst_sep is None else worst_sep["min_separation_m"],
        "followers_over_0_6_m": sum(1 for d in devs if d > 0.6),
        "follower_max_deviation_m": max(devs) if devs else None,
    }


def write_campaign_summary(
    specs: Sequence[RunSpec],
    out_dir: Path,
    *,
    failed: Sequence[str],
    wall_s: float,
    executor: str,
    resumed: int = 0,
) -> dict[str, Any]:
    """Read every seed's report from its folder, write ``summary.json`` / ``summary.md``; the summary."""
    specs = sorted(specs, key=lambda s: s.seed)
    reports: dict[str, dict[str, Any]] = {}
    for s in specs:
        p = s.out_dir / "report.json"
        if p.exists():
            reports[s.out_dir.name] = json.loads(p.read_text())
    summary = campaign_summary(specs, reports, failed, wall_s=wall_s, executor=executor, resumed=resumed)
    write_json(out_dir / "summary.json", summary)
    (out_dir / "summary.md").write_text(monte_carlo_markdown(summary))
    return summary


def monte_carlo_markdown(summary: dict[str, Any]) -> str:
    """The Monte Carlo summary as a page: outcomes, then percentiles of each metric."""
    lines = [
        f"# Monte Carlo: `{summary['scenario']}`, {summary['runs']} seeds ({summary['harness']} harness)",
        "",
        f"Detector: {summary.get('detector')}. Formation window: "
        f"{summary.get('formation_duration_s') or 'the scenario default'} s.",
        "",
        "| outcome | runs |",
        "|---|---|",
    ]
    lines += [f"| {k} | {v} |" for k, v in summary["outcomes"].items()]
    lines += ["", "| metric | min | p5 | p50 | p95 | max |", "|---|---|---|---|---|---|"]
    for key in (
        "relative_position_rmse_m",
        "relative_yaw_rmse_deg",
        "formation_rmse_m",
        "formation_max_deviation_m",
        "min_separation_m",
        "min_obstacle_clearance_m",
        "detection_recall",
    ):
        v = summary.get(key)
        if v is None:
            lines.append(f"| {key} | n/a | n/a | n/a | n/a | n/a |")
        else:
            cells = " | ".join(f"{v[q]:.3f}" if q in v else "n/a" for q in ("min", "p5", "p50", "p95", "max"))
            lines.append(f"| {key} | {cells} |")
    if "follower_outcomes" in summary:
        lines += [
            "",
            f"Followers: outcomes {summary['follower_outcomes']}; leader identity swaps "
            f"{summary['leader_identity_swaps']} (the service caught {summary['identity_swaps_detected']}); "
            f"worst separation {summary['worst_separation_m']:.2f} m; largest follower deviation "
            f"{summary['follower_max_deviation_m']:.2f} m (over 0.6 m: {summary['followers_over_0_6_m']} of "
            f"{sum(summary['follower_outcomes'].values())}).",
        ]
    lines += _per_seed(summary)
    if summary.get("failed"):
        lines += ["", "Runs without a report: " + "; ".join(summary["failed"])]
    executor = f" ({summary['executor']} executor)" if summary.get("executor") else ""
    resumed = (
        f"; {summary['resumed']} seeds' reports kept from an earlier run" if summary.get("resumed") else ""
    )
    lines += ["", f"Wall time: {summary['wall_s']:.0f} s{executor}{resumed}."]
    return "\n".join(lines) + "\n"


def _per_seed(summary: dict[str, Any]) -> list[str]:
    """Each seed's outcome and figures; on the real path, whether the host starved it."""
    runs = summary.get("runs_by_seed") or {}
    if not runs:
        return []
    lines = [
        "",
        "| run | outcome | relative position RMSE (m) | max deviation (m) | host |",
        "|---|---|---|---|---|",
    ]
    starved = 0
    for name, r in runs.items():
        host = r.get("host") or {}
        why = host.get("starved_because")
        starved += bool(why)
        note = "n/a" if why is None else ("starved: " + "; ".join(why) if why else "ok")
        rmse, dev = r.get("relative_position_rmse_m"), r.get("formation_max_deviation_m")
        lines.append(
            f"| {name} | {r.get('outcome')} | {'n/a' if rmse is None else f'{rmse:.3f}'} | "
            f"{'n/a' if dev is None else f'{dev:.3f}'} | {note} |"
        )
    if any((r.get("host") or {}).get("starved_because") is not None for r in runs.values()):
        lines += ["", f"Runs the host starved: {starved} of {len(runs)}."]
    return lines
