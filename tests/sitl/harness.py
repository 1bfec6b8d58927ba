"""A small client for lockstep tests: talks to one vehicle through the World's message link."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

from sitl.autopilot.modes import NavState
from sitl.config import SitlConfig, VehicleConfig
from sitl.world.lockstep import World
from sitl.world.scenario import Scenario

NAN = math.nan
MODE_NAMES = {
    s.custom_mode: s for s in NavState if s is not NavState.DESCEND and s is not NavState.TERMINATION
}


def one_vehicle_config(**world: Any) -> SitlConfig:
    return SitlConfig.model_validate(
        {"world": world, "vehicles": [VehicleConfig(name="follower").model_dump()]}
    )


class Client:
    """Sends like a GCS (255/190) and records what comes back, stamped with sim time."""

    def __init__(self, world: World, name: str = "follower", link_index: int = 0) -> None:
        self.world = world
        self.sysid = world.vehicle(name).sysid
        self.link = world.link(name, link_index)
        self.log: list[tuple[float, Any]] = []
        self.name = name

    @property
    def ap(self) -> Any:
        """The vehicle's autopilot state: what a test reads of it."""
        return self.world.autopilot(self.name).state

    def send(self, msg: Any) -> None:
        self.link.send(msg, 255, 190)

    def command(self, command: int, *params: float) -> int | None:
        p = list(params) + [NAN] * (7 - len(params))
        self.send(mavlink.MAVLink_command_long_message(self.sysid, 1, command, 0, *p))
        self.link.collect(self.world.t_s)
        for m in self.drain():
            if m.get_type() == "COMMAND_ACK" and m.command == command:
                return int(m.result)
        return None

    def drain(self) -> list[Any]:
        msgs = self.link.receive()
        t = self.world.t_s
        self.log.extend((t, m) for m in msgs)
        return msgs

    def run(self, seconds: float, each: Callable[[float], None] | None = None, every_s: float = 0.05) -> None:
        end = self.world.t_s + seconds
        next_each = self.world.t_s
        while self.world.t_s < end - 1e-9:
            if each is not None and self.world.t_s >= next_each - 1e-9:
                each(self.world.t_s)
                next_each += every_s
            self.world.step()
            self.drain()

    def run_until(
        self, cond: Callable[[], bool], timeout_s: float, each: Callable[[float], None] | None = None
    ) -> float:
        end = self.world.t_s + timeout_s
        next_each = self.world.t_s
        while not cond():
            if self.world.t_s > end:
                raise TimeoutError(f"condition not met within {timeout_s} s (t={self.world.t_s:.2f})")
            if each is not None and self.world.t_s >= next_each - 1e-9:
                each(self.world.t_s)
                next_each += 0.05
            self.world.step()
            self.drain()
        return self.world.t_s

    def velocity_setpoint(self, vn: float, ve: float, vd: float, yaw: float = 0.0) -> None:
        self.send(
            mavlink.MAVLink_set_position_target_local_ned_message(
                0, self.sysid, 1, 1, 2503, 0, 0, 0, vn, ve, vd, 0, 0, 0, yaw, 0
            )
        )

    def position_setpoint(self, n: float, e: float, d: float, yaw: float = 0.0) -> None:
        self.send(
            mavlink.MAVLink_set_position_target_local_ned_message(
                0, self.sysid, 1, 1, 2552, n, e, d, 0, 0, 0, 0, 0, 0, yaw, 0
            )
        )

    def heartbeat_modes(self) -> list[tuple[float, NavState | None]]:
        return [(t, MODE_NAMES.get(m.custom_mode)) for t, m in self.log if m.get_type() == "HEARTBEAT"]

    def texts(self) -> list[tuple[float, str]]:
        return [(t, m.text) for t, m in self.log if m.get_type() == "STATUSTEXT"]

    def take_off(self, altitude_m: float = 5.0) -> None:
        self.run_until(lambda: self.ap.status().global_position_ok and self.ap.home is not None, 30.0)
        assert self.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0) == 0
        home = self.ap.home
        assert self.command(mavlink.MAV_CMD_NAV_TAKEOFF, *([NAN] * 6), home.alt_m + altitude_m) == 0
        self.run_until(lambda: self.ap.nav_state is NavState.AUTO_LOITER and not self.ap.landed, 30.0)
        self.run(4.0)

    def start_offboard_velocity(
        self, vn: float = 0.0, ve: float = 0.0, vd: float = 0.0
    ) -> Callable[[float], None]:
        def stream(_t: float) -> None:
            self.velocity_setpoint(vn, ve, vd)

        self.run(1.0, each=stream)
        assert self.command(mavlink.MAV_CMD_DO_SET_MODE, 129.0, 6.0, 0.0) == 0
        return stream


def world_with(scenario: Scenario | None = None, seed: int = 0, **world: Any) -> World:
    return World(one_vehicle_config(**world), scenario, seed=seed)
