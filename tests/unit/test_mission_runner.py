"""The runner's own logic (tick, command queue, exit) with a recording fake link: pure asyncio, no sockets.

The real link is exercised against the simulator in tests/sitl; this checks what the runner adds on top.
"""

from __future__ import annotations

import asyncio
import itertools
from collections.abc import Mapping

from companion.config import Config, MissionConfig
from companion.kernel import compat
from companion.kernel.clock import MonotonicClock
from companion.kernel.errors import CommandRejectedError
from companion.kernel.flight import (
    ExternalPosition,
    FlightMode,
    LandedState,
    Setpoint,
    Severity,
    VehicleState,
)
from companion.mission.machine import MissionMachine
from companion.mission.types import (
    Command,
    CommandKind,
    MissionState,
    OperatorCommand,
    OperatorRequest,
    OperatorVerdict,
    Transition,
)
from companion.service.mission_runner import MissionRunner

from .mission_harness import FakeAutopilot, leader


class RecordingLink:
    """A VehicleLink whose vehicle is the harness's FakeAutopilot; records setpoints with their times."""

    def __init__(self, ap: FakeAutopilot, clock: MonotonicClock, arm_delay_s: float = 0.0) -> None:
        self.ap = ap
        self.clock = clock
        self.arm_delay_s = arm_delay_s
        self.setpoints: list[tuple[float, Setpoint]] = []
        self.calls: list[tuple[float, str]] = []
        self.onboard_status: list[dict[str, int | list[int]]] = []

    def snapshot(self) -> VehicleState:
        self.ap.advance(0.0)
        return self.ap.state(self.clock.now_s())

    async def _cmd(self, kind: CommandKind, altitude_m: float | None = None) -> None:
        self.calls.append((self.clock.now_s(), kind.value))
        r = self.ap.apply(Command(kind, altitude_m))
        if r is not None and not r.ok:
            raise CommandRejectedError(kind.value, r.detail)

    async def arm(self) -> None:
        await asyncio.sleep(self.arm_delay_s)
        await self._cmd(CommandKind.ARM)

    async def disarm(self) -> None:
        await self._cmd(CommandKind.DISARM)

    async def takeoff(self, altitude_m: float) -> None:
        await self._cmd(CommandKind.TAKEOFF, altitude_m)
        self.ap.alt_rel_m = altitude_m
        self.ap.mode = self.ap.mode.HOLD
        self.ap.landed = self.ap.landed.IN_AIR

    async def land(self) -> None:
        await self._cmd(CommandKind.LAND)

    async def hold(self) -> None:
        await self._cmd(CommandKind.HOLD)

    async def return_to_launch(self) -> None:
        await self._cmd(CommandKind.RTL)

    async def set_setpoint(self, setpoint: Setpoint) -> None:
        self.setpoints.append((self.clock.now_s(), setpoint))

    async def start_offboard(self, setpoint: Setpoint) -> None:
        await self.set_setpoint(setpoint)
        await self._cmd(CommandKind.START_OFFBOARD)

    async def stop_offboard(self) -> None:
        await self._cmd(CommandKind.STOP_OFFBOARD)

    async def release_offboard(self) -> None:
        await self._cmd(CommandKind.RELEASE_OFFBOARD)

    async def send_external_position(self, fix: ExternalPosition) -> None:
        del fix

    async def send_status_text(self, text: str, severity: Severity) -> None:
        del text, severity

    async def send_onboard_computer_status(self, fields: Mapping[str, int | list[int]]) -> None:
        self.onboard_status.append(dict(fields))


async def _feed(runner: MissionRunner, clock: MonotonicClock, stop: asyncio.Event) -> None:
    while not stop.is_set():
        runner.submit_leader(leader(clock.now_s()))
        await asyncio.sleep(0.02)


async def test_runner_flies_to_follow_streams_every_tick_and_exits_on_shutdown() -> None:
    clock = MonotonicClock()
    cfg = Config(mission=MissionConfig(gps_restore_s=0.2, shutdown_action="land"))
    ap = FakeAutopilot()
    link = RecordingLink(ap, clock, arm_delay_s=0.3)
    events: list[Transition] = []
    following = asyncio.Event()

    def on_transition(tr: Transition) -> None:
        events.append(tr)
        if tr.to_state == MissionState.FOLLOW:
            following.set()

    runner = MissionRunner(link, MissionMachine(cfg), clock, rate_hz=50.0, on_transition=on_transition)
    runner.request_start()
    stop = asyncio.Event()

    async def pilot() -> None:
        await following.wait()
        await asyncio.sleep(0.5)
        runner.request_shutdown()

    async with compat.timeout(60), compat.TaskGroup() as tg:
        feeder = tg.create_task(_feed(runner, clock, stop), name="test.feed")
        tg.create_task(pilot(), name="test.pilot")
        await runner.run()
        stop.set()
        await feeder

    assert [e.reason.name for e in events][:5] == [
        "LINK_UP",
        "PREFLIGHT_OK",
        "ARMED",
        "TAKEOFF_DONE",
        "LEADER_ACQUIRED",
    ]
    assert events[-1].reason.name == "SHUTDOWN_REQUESTED"
    kinds = [k for _, k in link.calls]
    assert kinds[-2:] == ["stop_offboard", "land"]
    # Setpoints were refreshed every tick while following (no gap longer than a few ticks).
    times = [t for t, _ in link.setpoints]
    assert len(times) > 10
    gaps = [b - a for a, b in itertools.pairwise(times)]
    assert max(gaps) < 0.1


async def test_a_slow_command_does_not_hold_up_the_setpoint_stream() -> None:
    clock = MonotonicClock()
    cfg = Config(mission=MissionConfig(gps_restore_s=0.1, shutdown_action="hold"))
    ap = FakeAutopilot()
    ap.fly()
    link = RecordingLink(ap, clock)
    following = asyncio.Event()

    def on_transition(tr: Transition) -> None:
        if tr.to_state == MissionState.FOLLOW:
            following.set()

    runner = MissionRunner(link, MissionMachine(cfg), clock, rate_hz=50.0, on_transition=on_transition)
    runner.request_start()  # an operator's start: takes the vehicle already in the air
    stop = asyncio.Event()

    async def slow_land() -> None:
        await asyncio.sleep(1.0)
        await link._cmd(CommandKind.LAND)

    link.land = slow_land  # type: ignore[method-assign]

    async def scenario() -> None:
        await following.wait()
        # Queue a slow command by hand, then watch the stream keep going while it runs.
        runner._commands.put_nowait(Command(CommandKind.LAND))
        n0 = len(link.setpoints)
        await asyncio.sleep(0.5)
        assert len(link.setpoints) - n0 >= 15
        runner.request_shutdown()

    async with compat.timeout(60), compat.TaskGroup() as tg:
        feeder = tg.create_task(_feed(runner, clock, stop), name="test.feed")
        tg.create_task(scenario(), name="test.scenario")
        await runner.run()
        stop.set()
        await feeder


def _req(name: str, offset_cam_m: tuple[float, float, float] | None = None) -> OperatorRequest:
    return OperatorRequest(OperatorCommand(name), offset_cam_m)


async def _ask(runner: MissionRunner, req: OperatorRequest) -> str:
    """``req`` as an operator sends it, answered by the next control tick: the verdict as printed."""
    answer = asyncio.ensure_future(runner.command(req))
    await asyncio.sleep(0)
    await runner.tick()
    verdict = await answer
    assert verdict.taken == (" refused: " not in str(verdict))
    return str(verdict)


async def test_operator_commands_are_answered_with_the_ticks_verdict() -> None:
    clock = MonotonicClock()
    runner = MissionRunner(RecordingLink(FakeAutopilot(), clock), MissionMachine(Config()), clock)
    # On the ground the companion flies nothing: land and hold are the autopilot's, not ours.
    assert await _ask(runner, _req("land")) == (
        "land refused: the companion is not flying the vehicle (state wait_link)"
    )
    runner.machine.state = MissionState.WAIT_LINK
    assert await _ask(runner, _req("start")) == "start refused: no link to the autopilot (state wait_link)"
    runner.machine.state = MissionState.FOLLOW
    # No control loop is stepping: the request is withdrawn, never left to act later.
    assert await runner.command(_req("land"), timeout_s=0.1) == OperatorVerdict(
        OperatorCommand.LAND, False, "the mission loop did not step within 0.1 s (nothing done)"
    )
    assert runner._operator is None
    assert (await _ask(runner, _req("hold"))).startswith("hold refused: hold needs GPS")
    runner.machine.state = MissionState.FOLLOW
    assert await _ask(runner, _req("set_offset", (0.0, 0.0, 6.0))) == (
        "set_offset: slot set to (0.0, 0.0, 6.0). "
        "Next: kept; the follower flies it once it follows the leader"
    )
    assert runner.machine.law.slot.forward_m == 6.0
    assert (await _ask(runner, _req("set_offset", (0.0, 0.0, 1.0)))).startswith(
        "set_offset refused: slot 1.0 m"
    )
    assert runner.machine.law.slot.forward_m == 6.0
    assert (await _ask(runner, _req("set_offset"))).startswith("set_offset refused:")


async def test_one_command_at_a_time() -> None:
    clock = MonotonicClock()
    runner = MissionRunner(RecordingLink(FakeAutopilot(), clock), MissionMachine(Config()), clock)
    first = asyncio.ensure_future(runner.command(_req("land")))
    await asyncio.sleep(0)
    assert (
        str(await runner.command(_req("hold")))
        == "hold refused: another command is waiting for the control tick"
    )
    await runner.tick()
    assert str(await first).startswith("land refused: the companion is not flying the vehicle")


async def test_a_command_refused_at_the_tick_is_answered_as_refused() -> None:
    """A hold that was possible when asked (GPS good) but not on the tick that takes it: PX4 lost position."""
    clock = MonotonicClock()
    ap = FakeAutopilot()
    runner = MissionRunner(
        RecordingLink(ap, clock), MissionMachine(Config(mission=MissionConfig(gps_restore_s=0.0))), clock
    )
    await runner.tick()
    assert runner.machine.gps_ok
    runner.machine.state = MissionState.FOLLOW
    ap.armed, ap.landed, ap.mode = True, LandedState.IN_AIR, FlightMode.OFFBOARD
    assert runner.machine.operator_refusal(OperatorCommand.HOLD) is None  # what a check on asking would say
    answer = asyncio.ensure_future(runner.command(_req("hold")))
    await asyncio.sleep(0)
    ap.position_valid = False
    await runner.tick()
    assert (
        str(await answer) == "hold refused: hold needs GPS (PX4 cannot hold without a position); land instead"
    )
    assert CommandKind.HOLD not in {c.kind for c in ap.sent}
    assert runner.state != MissionState.PX4_HOLD


async def test_an_operator_start_is_answered_with_what_the_mission_did() -> None:
    clock = MonotonicClock()
    cfg = Config(mission=MissionConfig(gps_restore_s=0.1))
    runner = MissionRunner(RecordingLink(FakeAutopilot(), clock), MissionMachine(cfg), clock, rate_hz=50.0)
    for _ in range(20):  # link up, GPS good: preflight
        await runner.tick()
        await asyncio.sleep(0.01)
    assert runner.state == MissionState.PREFLIGHT
    answer = asyncio.ensure_future(runner.command(_req("start")))
    await asyncio.sleep(0)
    await runner.tick()
    assert str(await answer) == (
        "start: preflight -> arming (preflight checks passed). Next: arms (up to 3 tries), takes off to 5 m "
        "(within 40 s), then waits up to 60 s (mission.acquire_timeout_s) for a confirmed track of the "
        "leader, then follows; without one PX4 lands"
    )
    assert (
        await _ask(runner, _req("start")) == "start refused: the mission is already under way (state arming)"
    )


async def test_the_result_of_a_command_that_spans_ticks_reaches_the_machine() -> None:
    """A command answered after a tick swapped the results list: its result must not be lost."""
    clock = MonotonicClock()
    ap = FakeAutopilot()
    ap.fly()
    link = RecordingLink(ap, clock)

    async def slow_hold() -> None:
        await asyncio.sleep(0.1)
        await link._cmd(CommandKind.HOLD)

    link.hold = slow_hold  # type: ignore[method-assign]
    machine = MissionMachine(Config())
    runner = MissionRunner(link, machine, clock, rate_hz=50.0)
    async with compat.timeout(60), compat.TaskGroup() as tg:
        executor = tg.create_task(runner._execute_commands(), name="test.commands")
        runner._commands.put_nowait(Command(CommandKind.HOLD))
        for _ in range(15):  # ticks every 20 ms while the command takes 100 ms
            await runner.tick()
            await asyncio.sleep(0.02)
        executor.cancel()
    assert CommandKind.HOLD in machine.c.book.last_result
