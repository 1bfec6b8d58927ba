"""An operator's command as the status socket carries it: one JSON object, read into an ``OperatorRequest``.

``{"request": "command", "name": "set_offset", "offset_cam_m": [0.0, 0.0, 6.0]}``: numbers travel as
numbers, never as words parsed back. Only the form is checked here (name, three finite numbers); what the
mission makes of it is decided once, on its control tick. Pure: no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from companion.mission.types import SENT_COMMANDS, OperatorCommand, OperatorRequest

#: Commands and whether each takes the slot offset (camera frame, m: right, down, forward). A start has
#: its own request (``{"request": "start"}``).
OPERATOR_COMMANDS = {c.value: c.takes_offset for c in SENT_COMMANDS}


def command_request(name: str, offset_cam_m: tuple[float, float, float] | None = None) -> dict[str, Any]:
    """The status socket's request for ``name`` (what ``companion command`` sends)."""
    req: dict[str, Any] = {"request": "command", "name": name}
    if offset_cam_m is not None:
        req["offset_cam_m"] = list(offset_cam_m)
    return req


def parse_command(req: Mapping[str, Any]) -> OperatorRequest | str:
    """The command in ``req`` (well formed: the mission still judges it), or the line saying why not."""
    name = req.get("name")
    if name not in OPERATOR_COMMANDS:
        return f"command refused: name one of {', '.join(OPERATOR_COMMANDS)}"
    offset = req.get("offset_cam_m")
    if not OPERATOR_COMMANDS[name]:
        return (
            f"{name} refused: it takes no offset"
            if offset is not None
            else OperatorRequest(OperatorCommand(name))
        )
    if not (
        isinstance(offset, list)
        and len(offset) == 3
        and all(isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) for v in offset)
    ):
        return f"{name} refused: offset_cam_m must be three finite numbers X Y Z (m)"
    x, y, z = (float(v) for v in offset)
    return OperatorRequest(OperatorCommand(name), (x, y, z))
