"""``companion deviation``: where a run's deviation from the slot came from, from its folder."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any


def register(sub: Any) -> None:
    """Add this module's command to the ``companion`` subparsers."""
    p = sub.add_parser(
        "deviation",
        help="split a run's largest deviation from the slot into its sources",
        description="Read a run folder of `companion sim` (flight_log.npz, report.json) and split its "
        "largest deviation: what the law knew against the perception error, and how it got there (the "
        "leader's motion against the command, the autopilot's tracking, the follower's turn), with the "
        "run's outliers, missed frames and tick timing. A campaign folder (seed-* inside) gets a line per "
        "seed.",
    )
    p.add_argument("run", type=Path, help="a run folder, or a campaign folder with seed-* runs")
    p.add_argument("--window", type=float, default=None, help="look back this far from the maximum, s (2)")
    p.add_argument("--json", action="store_true", help="print the split as JSON")
    p.set_defaults(handler=_deviation)


def _deviation(args: argparse.Namespace) -> int:
    from companion.lab.evaluation.deviation import WINDOW_S, split_deviation, split_markdown, split_row
    from companion.lab.evaluation.log import load_log

    window_s = WINDOW_S if args.window is None else float(args.window)
    run: Path = args.run
    runs = [run] if (run / "flight_log.npz").is_file() else sorted(run.glob("seed-*/"))
    runs = [r for r in runs if (r / "flight_log.npz").is_file()]
    if not runs:
        raise SystemExit(f"companion deviation: no flight_log.npz in {run} or its seed-* folders")
    splits: dict[str, Any] = {}
    for r in runs:
        splits[r.name] = split_deviation(
            _with_commands(load_log(r / "flight_log.npz"), r), _slot(r), window_s
        )
    if args.json:
        print(json.dumps(splits if len(runs) > 1 else splits[runs[0].name], indent=2))
        return 0
    if len(runs) == 1:
        print("\n".join(split_markdown(splits[runs[0].name])))
        return 0
    cols = list(split_row(next((s for s in splits.values() if s), None)) or {})
    print("| run | " + " | ".join(cols) + " |")
    print("|---|" + "---|" * len(cols))
    for name, split in splits.items():
        row = split_row(split)
        print(f"| {name} | " + " | ".join("n/a" if row.get(c) is None else str(row[c]) for c in cols) + " |")
    return 0


def _with_commands(log: Any, run: Path) -> Any:
    """A log from a version that did not keep the velocity command: taken from the run's trace.jsonl.

    The trace has each tick's body-frame setpoint but not the service's heading, so the command is turned
    into NED with the true one, and the perception part then holds the autopilot's heading error too.
    """
    import math

    import numpy as np

    trace = run / "trace.jsonl"
    n = len(log.t_s)
    if log.v_cmd_ned_m_s.shape == (n, 3) or not trace.is_file():
        return log
    v_cmd = np.full((n, 3), np.nan)
    by_t = {}
    for line in trace.read_text().splitlines():
        row = json.loads(line)
        sp = row.get("setpoint") if "tick" in row else None
        if sp and "v_body_m_s" in sp:
            by_t[round(float(row["tick"]), 4)] = sp["v_body_m_s"]
    for i, t in enumerate(log.t_s):
        v = by_t.get(round(float(t), 4))
        if v is not None:
            c, s = math.cos(log.yaw_follower_rad[i]), math.sin(log.yaw_follower_rad[i])
            v_cmd[i] = (c * v[0] - s * v[1], s * v[0] + c * v[1], v[2])
    log.v_cmd_ned_m_s = v_cmd
    if log.yaw_service_rad.size != n:
        log.yaw_service_rad = log.yaw_follower_rad.copy()
    return log


def _slot(run: Path) -> list[float]:
    """The slot the run flew to: from its report, else from its scenario and the service's defaults."""
    report = run / "report.json"
    if report.is_file():
        split = json.loads(report.read_text()).get("deviation_split") or {}
        if split.get("slot_cam_m"):
            return [float(c) for c in split["slot_cam_m"]]
    from companion.kernel.config import read_toml
    from companion.lab.evaluation.setup import service_config

    scenario = run / "scenario.toml"
    overrides = read_toml(scenario).get("companion", {}) if scenario.is_file() else {}
    return [float(c) for c in service_config(overrides).formation.offset_cam_m]
