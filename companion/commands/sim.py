"""``companion sim``: closed-loop scenarios against the simulator, with reports and plots."""

from __future__ import annotations

from typing import Any

from companion.cli import not_built


def register(sub: Any) -> None:
    """Add this module's commands to the ``companion`` subparsers."""
    p = sub.add_parser("sim", help="fly a scenario closed-loop in the simulator and write a report")
    p.add_argument("--scenario", default="all", help="scenario name (config/scenarios/NAME.toml) or 'all'")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--seeds", default=None, help="Monte Carlo range, e.g. 1-50 (lockstep harness)")
    p.add_argument("--out", default="runs/sim", help="output folder")
    p.add_argument("--speed", type=float, default=1.0, help="simulation speed factor")
    p.add_argument("--duration", type=float, default=None, help="formation time in s (scenario default)")
    p.set_defaults(handler=not_built("sim"))
