"""The link sets PX4's offboard-loss failsafe on connect, and PX4 then holds instead of climbing to Return.

In-process: the service's MessageVehicleLink talks to the simulated autopilot through the World's MAVLink
message link (the lockstep harness's path), so the PARAM_SET encoding and the failsafe are the real ones.
"""

from __future__ import annotations

import logging
from typing import Any

import pytest

from companion.config import LinkConfig
from companion.kernel.clock import ManualClock
from companion.vehicle import failsafe
from companion.vehicle.message_link import MessageVehicleLink
from sitl.autopilot.modes import NavState
from sitl.world.lockstep import World
from tests.sitl.harness import Client, world_with


def _pump(world: World, link: MessageVehicleLink, clock: ManualClock, seconds: float) -> None:
    end = world.t_s + seconds
    while world.t_s < end - 1e-9:
        world.step()
        clock.set(world.t_s)
        link.pump()


def _service_link(world: World, **cfg: Any) -> tuple[MessageVehicleLink, ManualClock]:
    clock = ManualClock(world.t_s)
    vehicle = world.vehicle("follower")
    return MessageVehicleLink(world.link("follower"), clock, LinkConfig(**cfg), vehicle.sysid), clock


@pytest.mark.parametrize(("action", "value"), [("hold", 5), ("land", 4), ("return", 3)])
def test_link_sets_the_offboard_loss_action_on_connect(action: str, value: int) -> None:
    world = world_with(seed=2)
    assert world.autopilot("follower").state.params["COM_OBL_RC_ACT"] == 0  # PX4's default
    link, clock = _service_link(world, offboard_loss_action=action)
    _pump(world, link, clock, 3.0)
    assert world.autopilot("follower").state.params["COM_OBL_RC_ACT"] == value
    assert link.snapshot().offboard_loss_param == value


def test_autopilot_setting_is_read_and_left_alone(caplog: pytest.LogCaptureFixture) -> None:
    world = world_with(seed=2)
    link, clock = _service_link(world, offboard_loss_action="autopilot")
    with caplog.at_level(logging.INFO, logger="companion.vehicle"):
        _pump(world, link, clock, 3.0)
    assert world.autopilot("follower").state.params["COM_OBL_RC_ACT"] == 0
    assert link.snapshot().offboard_loss_param == 0
    assert any("offboard-loss failsafe: Position (without RC" in r.message for r in caplog.records)


class _Deaf:
    """A transport whose autopilot never answers a parameter message (an old or locked-down firmware)."""

    def __init__(self, inner: Any) -> None:
        self.inner = inner

    def send(self, msg: Any, src_system: int, src_component: int) -> None:
        if msg.get_type() not in ("PARAM_SET", "PARAM_REQUEST_READ"):
            self.inner.send(msg, src_system, src_component)

    def receive(self) -> list[Any]:
        return self.inner.receive()


def test_an_unanswered_set_is_one_warning_and_the_link_goes_on(caplog: pytest.LogCaptureFixture) -> None:
    world = world_with(seed=2)
    clock = ManualClock(world.t_s)
    link = MessageVehicleLink(
        _Deaf(world.link("follower")), clock, LinkConfig(), world.vehicle("follower").sysid
    )
    with caplog.at_level(logging.WARNING, logger="companion.vehicle"):
        _pump(world, link, clock, 5.0)
    lines = [r.message for r in caplog.records if "offboard-loss" in r.message]
    assert lines == ["vehicle link: " + failsafe.not_applied("hold", "no reply")]
    assert link.snapshot().connected
    assert link.snapshot().offboard_loss_param is None


def test_with_hold_set_a_silent_companion_leaves_px4_holding_not_climbing() -> None:
    world = world_with(seed=4)
    link, clock = _service_link(world)  # default: hold
    _pump(world, link, clock, 2.0)
    c = Client(world, link_index=1)  # a GCS on the second link flies the offboard part
    c.take_off(5.0)
    stream = c.start_offboard_velocity(2.0, 0.0, 0.0)
    c.run(3.0, each=stream)
    assert c.ap.nav_state is NavState.OFFBOARD
    alt0 = -world.truth("follower").p_ned_m[2]
    c.run(6.0)  # the stream stops: COM_OF_LOSS_T later, the failsafe
    assert c.ap.nav_state is NavState.AUTO_LOITER
    assert "Failsafe activated: switching to Hold" in [x for _, x in c.texts()]
    # Return would have climbed toward RTL_RETURN_ALT (60 m) at MPC_Z_V_AUTO_UP.
    assert abs(-world.truth("follower").p_ned_m[2] - alt0) < 0.5
