"""``companion autolabel``: fly scenarios in lockstep, label the leader from its shared position and depth.

The labels are written as a detector dataset (one folder per flight) and scored against the renderer's true
boxes (:mod:`companion.lab.evaluation.autolabel_check`). Heavy imports happen inside the handler.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from companion.kernel.logs import setup_logging


def register(sub: Any) -> None:
    """Add this module's commands to the ``companion`` subparsers."""
    p = sub.add_parser(
        "autolabel",
        help="fly scenarios in the simulator and auto-label the leader while GPS is good",
        description="Fly scenarios in lockstep with the service's cores; while GPS is good, label the "
        "leader in every frame from its shared position and the depth image, write the labelled frames as "
        "a detector dataset and score the labels against the renderer's true boxes.",
    )
    p.add_argument("--scenario", action="append", required=True, help="scenario name or path (repeatable)")
    p.add_argument("--seeds", default="1", help="seeds, e.g. 1-3 or 1,4 (default 1)")
    p.add_argument("--out", type=Path, required=True, help="output folder: one dataset folder per flight")
    p.add_argument("--no-write", action="store_true", help="score only, write no images")
    p.add_argument(
        "--truth-labels",
        action="store_true",
        help="also write every frame with the renderer's true box (an evaluation set: RUN/truth)",
    )
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="SECTION.KEY=VALUE",
        help="override a service config key for these runs (TOML value)",
    )
    p.set_defaults(handler=_autolabel)


def _seeds(text: str) -> list[int]:
    out: list[int] = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        out.extend(range(int(a), int(b or a) + 1))
    return out


def _autolabel(args: argparse.Namespace) -> int:
    from companion.kernel.config import deep_merge
    from companion.kernel.errors import CompanionError
    from companion.lab.evaluation.autolabel_check import write_sheet
    from companion.lab.evaluation.campaign import effective_scenario, parse_overrides
    from companion.lab.evaluation.lockstep import LockstepOptions
    from companion.lab.evaluation.setup import (
        load_detect,
        run_lockstep,
        scenario_path,
        service_config,
    )
    from companion.lab.evaluation.tomlw import dumps

    setup_logging("human", "WARNING")
    try:
        seeds = _seeds(args.seeds)
    except ValueError:
        print(f"companion autolabel: --seeds: not a list of seeds: {args.seeds!r}", file=sys.stderr)
        return 2
    summaries: dict[str, Any] = {}
    try:
        for name in args.scenario:
            path = scenario_path(name)
            scenario = effective_scenario(path, None)
            for seed in seeds:
                run_name = f"{scenario.name}-s{seed}"
                run_dir = args.out / run_name
                run_dir.mkdir(parents=True, exist_ok=True)
                run_file = run_dir / "scenario.toml"
                run_file.write_text(dumps(scenario.model_dump(mode="json")))
                cfg = service_config(scenario.companion, deep_merge(parse_overrides(tuple(args.set)), {}))
                options = LockstepOptions(
                    auto_label=True,
                    auto_label_dir=None if args.no_write else run_dir / "dataset",
                    auto_label_sequence=run_name,
                    truth_label_dir=run_dir / "truth" if args.truth_labels else None,
                )
                result = run_lockstep(run_file, seed, cfg, load_detect(cfg, "network"), options)
                summary = result.extra["auto_label"]
                summaries[run_name] = summary
                print(f"{run_name}: {_line(summary)}", flush=True)
                if options.auto_label_dir is not None:
                    write_sheet(options.auto_label_dir, run_dir / "sheet.png")
    except CompanionError as exc:
        print(f"companion autolabel: {exc}", file=sys.stderr)
        return 2
    (args.out / "autolabel.json").write_text(json.dumps(summaries, indent=2))
    return 0


def _line(s: dict[str, Any]) -> str:
    share = s["share_iou_ge_0_7"]
    fl = s["false_label_rate_on_leader_free"]
    return (
        f"{s['labels']} labels of {s['visible_frames']} frames with the leader visible "
        f"(IoU >= 0.7: {'-' if share is None else f'{share:.1%}'}), {s['rejected']} rejected, "
        f"{s['negatives']} negatives, false labels on {s['leader_free_frames']} leader-free frames: "
        f"{'-' if fl is None else f'{fl:.1%}'}; {s['gated_out']} frames without GPS or share"
    )
