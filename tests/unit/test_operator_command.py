"""An operator's command from the status socket: checked once, numbers as numbers, one line when refused."""

from __future__ import annotations

import json
import math

import pytest

from companion.mission.types import OperatorCommand, OperatorRequest
from companion.service.operator import command_request, parse_command


def test_what_the_cli_sends_is_what_the_service_reads() -> None:
    for name, offset in (("land", None), ("hold", None), ("set_offset", (0.5, -0.25, 6.0))):
        wire = json.loads(json.dumps(command_request(name, offset)))
        assert parse_command(wire) == OperatorRequest(OperatorCommand(name), offset)


@pytest.mark.parametrize(
    ("req", "why"),
    [
        ({}, "command refused: name one of land, hold, set_offset"),
        ({"name": "takeoff"}, "command refused: name one of land, hold, set_offset"),
        ({"name": "land", "offset_cam_m": [0, 0, 6]}, "land refused: it takes no offset"),
        ({"name": "set_offset"}, "set_offset refused: offset_cam_m must be three finite numbers X Y Z (m)"),
        ({"name": "set_offset", "offset_cam_m": [0, 0]}, "set_offset refused: offset_cam_m must be three"),
        ({"name": "set_offset", "offset_cam_m": ["0", "0", "6"]}, "set_offset refused: offset_cam_m must"),
        ({"name": "set_offset", "offset_cam_m": [0, True, 6]}, "set_offset refused: offset_cam_m must"),
        ({"name": "set_offset", "offset_cam_m": [0, 0, math.inf]}, "set_offset refused: offset_cam_m must"),
        ({"name": "set_offset", "offset_cam_m": [0, 0, math.nan]}, "set_offset refused: offset_cam_m must"),
    ],
)
def test_a_malformed_command_is_refused_in_one_line(req: dict[str, object], why: str) -> None:
    reply = parse_command(req)
    assert isinstance(reply, str)
    assert reply.startswith(why)
