"""``companion status`` and ``companion health``."""

from __future__ import annotations

from typing import Any

from companion.cli import not_built
from companion.commands._common import add_config_arg


def register(sub: Any) -> None:
    """Add this module's commands to the ``companion`` subparsers."""
    p = sub.add_parser("status", help="show the running service's state")
    add_config_arg(p)
    p.add_argument("--json", action="store_true", help="print the raw JSON snapshot")
    p.set_defaults(handler=not_built("status"))
    h = sub.add_parser("health", help="run preflight checks; exit 0 healthy, 1 not")
    add_config_arg(h)
    h.add_argument("--json", action="store_true", help="print the checks as JSON")
    h.set_defaults(handler=not_built("health"))
