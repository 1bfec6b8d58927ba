"""ONBOARD_COMPUTER_STATUS goes out through the vehicle link's own method, encoded as on the wire."""

from __future__ import annotations

import asyncio
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

from companion.config import LinkConfig
from companion.kernel.clock import ManualClock
from companion.service.gcs import OnboardStatusBuilder
from companion.service.sysinfo import SystemReading
from companion.vehicle.message_link import MessageVehicleLink


class _Wire:
    """A transport that encodes what the link sends (as a socket would) and hands over what it is given."""

    def __init__(self) -> None:
        self.sent: list[Any] = []
        self.inbox: list[Any] = []
        self._mav = mavlink.MAVLink(None)

    def send(self, msg: Any, src_system: int, src_component: int) -> None:
        self._mav.srcSystem, self._mav.srcComponent = src_system, src_component
        self.sent.append(self._mav.decode(bytearray(msg.pack(self._mav))))

    def receive(self) -> list[Any]:
        msgs, self.inbox = self.inbox, []
        return msgs


def test_the_link_sends_the_status_once_connected() -> None:
    wire, clock = _Wire(), ManualClock(10.0)
    link = MessageVehicleLink(wire, clock, LinkConfig(), target_system=1)
    fields = OnboardStatusBuilder().build(SystemReading(0.5, 20.0, (20.0, 20.0), 900.0, 7600.0), 12.5, 1e9)
    asyncio.run(link.send_onboard_computer_status(fields.fields))
    assert not [m for m in wire.sent if m.get_type() == "ONBOARD_COMPUTER_STATUS"]  # no autopilot yet
    wire.inbox.append(
        mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, 0, 0, 3, 3)
    )
    link.pump()
    asyncio.run(link.send_onboard_computer_status(fields.fields))
    (msg,) = [m for m in wire.sent if m.get_type() == "ONBOARD_COMPUTER_STATUS"]
    assert (msg.uptime, msg.ram_usage, msg.ram_total) == (12500, 900, 7600)
    assert msg.get_srcComponent() == mavlink.MAV_COMP_ID_ONBOARD_COMPUTER
