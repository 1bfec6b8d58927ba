"""``companion bench``: per-stage perception latency."""

from __future__ import annotations

from typing import Any

from companion.cli import not_built
from companion.commands._common import add_config_arg


def register(sub: Any) -> None:
    """Add this module's commands to the ``companion`` subparsers."""
    p = sub.add_parser("bench", help="time perception per stage (p50/p95/p99)")
    add_config_arg(p)
    p.add_argument("--json", default=None, help="also write the figures to this JSON file")
    p.add_argument("--frames", type=int, default=200)
    p.set_defaults(handler=not_built("bench"))
