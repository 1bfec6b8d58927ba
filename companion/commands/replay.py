"""``companion replay`` and ``companion record``."""

from __future__ import annotations

from typing import Any

from companion.cli import not_built
from companion.commands._common import add_config_arg


def register(sub: Any) -> None:
    """Add this module's commands to the ``companion`` subparsers."""
    p = sub.add_parser("replay", help="run perception on a recording and write per-frame estimates")
    add_config_arg(p)
    p.add_argument("--source", required=True, help="file:PATH (folder or .bag)")
    p.add_argument("--out", default=None, help="CSV of per-frame estimates and errors")
    p.set_defaults(handler=not_built("replay"))
    r = sub.add_parser("record", help="record any frame source to the folder format")
    add_config_arg(r)
    r.add_argument("--source", required=True, help="sim | realsense | file:PATH")
    r.add_argument("--out", required=True, help="output folder")
    r.add_argument("--frames", type=int, default=0, help="stop after N frames (0: until Ctrl-C/end)")
    r.set_defaults(handler=not_built("record"))
