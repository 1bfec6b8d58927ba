"""``companion run``: the service."""

from __future__ import annotations

from typing import Any

from companion.cli import not_built
from companion.commands._common import add_config_arg


def register(sub: Any) -> None:
    """Add this module's commands to the ``companion`` subparsers."""
    p = sub.add_parser("run", help="run the follower service")
    add_config_arg(p)
    p.set_defaults(handler=not_built("run"))
