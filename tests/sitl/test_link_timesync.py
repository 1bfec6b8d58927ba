"""The service's link measures the autopilot's clock with MAVLink TIMESYNC and stamps samples when taken.

In-process: the service's MessageVehicleLink against the simulated autopilot through the World's MAVLink
message link, with 12 ms of latency plus a one-sided 10 ms spread each way (the scenario's link faults).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from companion.config import LinkConfig
from companion.kernel.clock import ManualClock
from companion.vehicle.message_link import MessageVehicleLink
from sitl.world.scenario import Scenario
from tests.sitl.harness import world_with


def test_a_late_link_is_measured_and_its_latency_taken_out_of_the_stamps() -> None:
    scenario = Scenario.model_validate(
        {"name": "late-link", "vehicles": {"follower": {"link": {"latency_ms": 12.0, "jitter_ms": 10.0}}}}
    )
    world = world_with(scenario, seed=4)
    clock = ManualClock(world.t_s)
    spy = _Spy(world.link("follower"))
    link = MessageVehicleLink(spy, clock, LinkConfig(), world.vehicle("follower").sysid)
    lags_s = []
    last_stamp_s = -math.inf
    while world.t_s < 20.0:
        world.step()
        clock.set(world.t_s)
        link.pump()
        st = link.snapshot()
        if world.t_s > 5.0 and st.attitude_stamp_s > last_stamp_s:
            last_stamp_s = st.attitude_stamp_s
            # The simulated autopilot's boot clock is the world's: a sample's true time is its boot time.
            lags_s.append(st.attitude_stamp_s - spy.attitude_boot_s)
    st = link.snapshot()
    # Half the best round trip: 12 ms of link plus half the autopilot's wait for its next 50 Hz step.
    assert 0.012 <= st.link_delay_s <= 0.025
    assert 0.024 <= st.link_rtt_s < 0.12
    assert abs(float(np.median(lags_s))) < 0.005  # stamped when sampled, not 12 ms late


class _Spy:
    """The world's link, noting the boot time of the last ATTITUDE it hands over, s."""

    def __init__(self, inner: Any) -> None:
        self.inner = inner
        self.attitude_boot_s = math.nan

    def receive(self) -> list[Any]:
        msgs = list(self.inner.receive())
        for m in msgs:
            if m.get_type() == "ATTITUDE":
                self.attitude_boot_s = m.time_boot_ms * 1e-3
        return msgs

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)
