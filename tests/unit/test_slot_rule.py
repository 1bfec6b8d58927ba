"""One slot rule: the config, ``companion command set_offset`` and MQTT's ``set_offset`` answer alike."""

from __future__ import annotations

import asyncio
import json

import pytest

from companion.config import Config, load_config, slot_refusal
from companion.kernel.clock import MonotonicClock
from companion.kernel.errors import ConfigError
from companion.mission.machine import MissionMachine
from companion.mission.types import OperatorRequest, OperatorVerdict
from companion.service.mission_runner import MissionRunner
from companion.service.operator import command_request, parse_command
from companion.telemetry.commands import CommandVerifier, sign_command
from companion.telemetry.inbound import Keyring

from .mission_harness import FakeAutopilot
from .test_mission_runner import RecordingLink

KEY = b"k" * 32
TOPIC = "wingman/follower1/cmd"
#: Slots out of bounds one way each: behind the camera, inside the separation bubble, out of the image,
#: beyond the detector's reach (``set_offset 0 0 100``), and beyond it on a diagonal.
OUT_OF_BOUNDS = [(0.0, 0.0, -1.0), (0.0, 0.0, 1.0), (10.0, 0.0, 5.0), (0.0, 0.0, 100.0), (0.0, 40.0, 40.0)]


async def _verdict(req: OperatorRequest) -> OperatorVerdict:
    """``req`` answered by the mission's next control tick."""
    clock = MonotonicClock()
    runner = MissionRunner(RecordingLink(FakeAutopilot(), clock), MissionMachine(Config()), clock)
    answer = asyncio.ensure_future(runner.command(req))
    await asyncio.sleep(0)
    await runner.tick()
    return await answer


def _over_the_socket(slot: tuple[float, float, float]) -> OperatorRequest:
    """What ``companion command set_offset X Y Z`` sends, as the status socket reads it."""
    req = parse_command(json.loads(json.dumps(command_request("set_offset", slot))))
    assert isinstance(req, OperatorRequest)
    return req


def _over_mqtt(slot: tuple[float, float, float]) -> OperatorRequest:
    """A signed MQTT ``set_offset``, verified and handed to the mission as the service does."""
    msg = {"cmd": "set_offset", "offset_cam_m": list(slot), "time_unix_s": 1000.0}
    cmd = CommandVerifier(Keyring({"gcs": KEY}), TOPIC, max_age_s=30.0).verify(
        sign_command(KEY, "gcs", TOPIC, msg), now_unix_s=1000.0
    )
    return OperatorRequest(cmd.name, cmd.offset_cam_m)


@pytest.mark.parametrize("slot", OUT_OF_BOUNDS)
async def test_an_out_of_bounds_slot_gets_one_answer_everywhere(slot: tuple[float, float, float]) -> None:
    why = slot_refusal(slot, Config().safety.min_separation_m)
    assert why is not None
    for req in (_over_the_socket(slot), _over_mqtt(slot)):
        verdict = await _verdict(req)
        assert not verdict.taken
        assert str(verdict) == f"set_offset refused: {why}"
    env = {"WINGMAN_FORMATION__OFFSET_CAM_M": json.dumps(list(slot))}
    with pytest.raises(ConfigError) as exc:
        load_config(None, env)
    assert str(exc.value) == f"$WINGMAN_FORMATION__OFFSET_CAM_M: formation.offset_cam_m: {why}"


def test_the_bounds() -> None:
    assert slot_refusal((0.0, 0.0, 100.0), 2.0) == "slot 100.0 m from the leader: further than 50 m"
    assert slot_refusal((0.0, 0.0, 50.0), 2.0) is None
    assert slot_refusal((0.0, 0.0, 3.0), 2.0) is None
    assert slot_refusal((0.0, 0.0, 2.9), 2.0) is not None
    assert slot_refusal((0.0, 0.0, float("nan")), 2.0) == "offset must be finite"
    with pytest.raises(ValueError, match=r"formation\.offset_cam_m: offset must be finite"):
        Config.model_validate({"formation": {"offset_cam_m": [0.0, 0.0, float("nan")]}})


async def test_a_good_slot_is_taken_on_every_path() -> None:
    slot = (0.5, 0.0, 6.0)
    assert slot_refusal(slot, 2.0) is None
    for req in (_over_the_socket(slot), _over_mqtt(slot)):
        verdict = await _verdict(req)
        assert verdict.taken
        assert str(verdict).startswith("set_offset: slot set to (0.5, 0.0, 6.0). Next: ")
    env = {"WINGMAN_FORMATION__OFFSET_CAM_M": json.dumps(list(slot))}
    assert load_config(None, env).formation.offset_cam_m == slot
