"""The mission runner: the thin asyncio edge around :class:`~companion.mission.machine.MissionMachine`.

Each control tick (``LinkConfig.setpoint_rate_hz``) it reads the latest vehicle snapshot and the latest
tracker output, steps the machine, streams the setpoint the machine computed *for this tick* (so MAVSDK's
own 20 Hz resend only ever repeats a setpoint at most one tick old), and queues the machine's one-shot
commands for a separate task, so a slow command (an arm waiting for its ACK) never delays the setpoint
stream. If this loop ever stops refreshing, the link's setpoint guard stops offboard by itself
(``LinkConfig.setpoint_timeout_s``).
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable, Mapping

from companion.estimation.leader import LeaderEstimate, ObstacleAhead
from companion.kernel import compat
from companion.kernel.clock import Clock
from companion.kernel.errors import CommandRejectedError, CompanionError, LinkLostError
from companion.kernel.flight import Setpoint, Severity
from companion.mission.machine import MissionMachine
from companion.mission.next_step import slot_next_step
from companion.mission.types import (
    AirframeDrag,
    Command,
    CommandKind,
    CommandResult,
    MissionInputs,
    MissionState,
    OperatorCommand,
    OperatorRequest,
    OperatorVerdict,
    SharedLeaderPosition,
    SharedNeighbour,
    StepOutput,
    Transition,
)
from companion.vehicle.link import VehicleLink

log = logging.getLogger("companion.mission")

_LOG_LEVEL = {
    Severity.EMERGENCY: logging.CRITICAL,
    Severity.ALERT: logging.CRITICAL,
    Severity.CRITICAL: logging.CRITICAL,
    Severity.ERROR: logging.ERROR,
    Severity.WARNING: logging.WARNING,
    Severity.NOTICE: logging.INFO,
    Severity.INFO: logging.INFO,
    Severity.DEBUG: logging.DEBUG,
}
#: A command that has not finished after this many command timeouts is reported as failed.
COMMAND_GRACE_FACTOR = 3.0
#: An operator's start, land or hold is answered after the next control tick; a loop that has not
#: stepped by then gets the request withdrawn, s (under the CLI's 3 s wait for the status socket).
ANSWER_TIMEOUT_S = 2.0


class MissionRunner:
    """Runs the machine against a link in real time.

    Feed it with :meth:`submit_leader` (every tracker output) and :meth:`submit_leader_shared`; start and stop
    the mission with :meth:`request_start` and :meth:`request_shutdown`. ``on_transition`` receives every
    transition once (the service sends it as STATUSTEXT and MQTT); ``on_step`` sees every tick's inputs and
    output (flight logs, telemetry).
    """

    def __init__(
        self,
        link: VehicleLink,
        machine: MissionMachine,
        clock: Clock,
        *,
        rate_hz: float = 20.0,
        command_timeout_s: float = 3.0,
        on_transition: Callable[[Transition], None] | None = None,
        on_step: Callable[[MissionInputs, StepOutput], None] | None = None,
    ) -> None:
        self.link = link
        self.machine = machine
        self.clock = clock
        self.period_s = 1.0 / rate_hz
        self.command_timeout_s = command_timeout_s
        self.on_transition = on_transition
        self.on_step = on_step
        self.last_output: StepOutput | None = None
        self._leader: LeaderEstimate | None = None
        self._shared: SharedLeaderPosition | None = None
        self._obstacle: ObstacleAhead | None = None
        self._neighbours: dict[str, SharedNeighbour] = {}
        self._airframe: AirframeDrag | None = None
        self._start = False
        self._takeover = False
        self._shutdown = False
        self._commands: asyncio.Queue[Command] = asyncio.Queue()
        self._results: list[CommandResult] = []
        self._last_setpoint: Setpoint | None = None
        self._setpoint_failures = 0
        self._operator: OperatorRequest | None = None
        #: The operator waiting for the answer to the request in ``_operator`` (one at a time).
        self._waiting: tuple[OperatorRequest, asyncio.Future[OperatorVerdict]] | None = None
        self.last_transition: Transition | None = None

    # ------------------------------------------------------------------ inputs
    def submit_leader(self, estimate: LeaderEstimate) -> None:
        """Latest-value mailbox: a newer estimate replaces an older one that was never used."""
        self._leader = estimate

    def submit_leader_shared(self, position: SharedLeaderPosition) -> None:
        self._shared = position

    @property
    def leader_shared(self) -> SharedLeaderPosition | None:
        """The leader's latest share, as the next tick hands it to the mission (None: none yet)."""
        return self._shared

    @property
    def neighbours(self) -> Mapping[str, SharedNeighbour]:
        """The other followers' latest shares by name, as the next tick hands them to the mission."""
        return self._neighbours

    def submit_airframe(self, airframe: AirframeDrag | None) -> None:
        """The follower's drag as learnt so far (None: not yet); latest value wins."""
        self._airframe = airframe

    def submit_obstacle(self, obstacle: ObstacleAhead | None) -> None:
        """The depth guard's reading for the latest frame (None: nothing near); latest value wins."""
        self._obstacle = obstacle

    def submit_neighbour(self, neighbour: SharedNeighbour) -> None:
        """Another follower's shared position; the latest per neighbour wins."""
        self._neighbours[neighbour.name] = neighbour

    def request_start(self, *, takeover: bool = True) -> None:
        """Start the mission, without waiting for an answer (``service.auto_start``, the harnesses).

        Delivered on the next tick; the machine keeps it until it can act (from the ground: once preflight
        passes) or drops it where a start means nothing. ``takeover``: an operator's start, which may also
        take a vehicle already in the air; ``service.auto_start`` passes False (from the ground only).
        """
        self._start = True
        self._takeover = self._takeover or takeover

    def request_shutdown(self) -> None:
        """Ask for the configured safe action; :meth:`run` returns once it is under way."""
        self._shutdown = True

    async def command(self, req: OperatorRequest, timeout_s: float = ANSWER_TIMEOUT_S) -> OperatorVerdict:
        """An operator's request: what the next tick did with it, or why it refused.

        The machine checks the request once, on the tick that takes it (``StepOutput.operator_refused``), so
        the answer is the verdict the mission acted on. A start, land or hold is answered with the
        transitions it caused; a start from the ground arms once preflight passes, one in the air takes the
        vehicle back. A new slot applies from that tick.
        """
        cmd = req.command
        if self._operator is not None or self._waiting is not None:
            return OperatorVerdict(cmd, False, "another command is waiting for the control tick")
        self._operator = req
        answer: asyncio.Future[OperatorVerdict] = asyncio.get_running_loop().create_future()
        self._waiting = (req, answer)
        try:
            async with compat.timeout(timeout_s):
                return await answer
        except TimeoutError:
            # Withdrawn, so that it cannot act later behind the operator's back.
            if self._waiting is not None and self._waiting[1] is answer:
                self._waiting = None
            self._operator = None
            self.machine.withdraw_start()
            return OperatorVerdict(
                cmd, False, f"the mission loop did not step within {timeout_s:g} s (nothing done)"
            )

    def _settle(
        self, waiting: tuple[OperatorRequest, asyncio.Future[OperatorVerdict]], out: StepOutput
    ) -> None:
        """Answer the request this tick took: the machine's refusal, the transitions it caused, or none."""
        req, answer = waiting
        if answer.done():
            return
        cmd = req.command
        if out.operator_refused is not None:
            answer.set_result(OperatorVerdict(cmd, False, out.operator_refused))
        elif req.command == OperatorCommand.SET_OFFSET and req.offset_cam_m is not None:
            log.info("mission: operator set the slot to %s (camera frame, m)", req.offset_cam_m)
            slot = tuple(round(c, 2) for c in req.offset_cam_m)
            answer.set_result(
                OperatorVerdict(cmd, True, f"slot set to {slot}. Next: {slot_next_step(out.state)}")
            )
        elif out.transitions:
            moves = "; ".join(
                f"{t.from_state.value} -> {t.to_state.value} ({t.reason.value}"
                + (f": {t.detail})" if t.detail else ")")
                for t in out.transitions
            )
            after = self.machine.next_step()
            answer.set_result(OperatorVerdict(cmd, True, moves + (f". Next: {after}" if after else "")))
        else:
            if req.command == OperatorCommand.START:
                self.machine.withdraw_start()  # never kept to act later
            answer.set_result(OperatorVerdict(cmd, False, f"nothing to do in state {out.state.value}"))

    @property
    def state(self) -> MissionState:
        return self.machine.state

    # ------------------------------------------------------------------ loop
    async def run(self) -> None:
        """Control loop plus command executor, until a requested shutdown is complete."""
        async with compat.TaskGroup() as tg:
            executor = tg.create_task(self._execute_commands(), name="companion.mission.commands")
            try:
                await self._control_loop()
            finally:
                executor.cancel()

    async def _control_loop(self) -> None:
        next_s = self.clock.now_s()
        while True:
            out = await self.tick()
            if out.ready_to_exit:
                log.info("mission: shutdown action under way in %s; runner exits", out.state.value)
                return
            next_s += self.period_s
            now_s = self.clock.now_s()
            if next_s < now_s - self.period_s:
                next_s = now_s  # we fell behind (a stalled loop): do not burst to catch up
            await self.clock.sleep_until(next_s)

    async def tick(self) -> StepOutput:
        """One control step: inputs -> machine -> setpoint, commands, external fix, events."""
        now_s = self.clock.now_s()
        results, self._results = tuple(self._results), []
        operator, self._operator = self._operator, None
        waiting, self._waiting = self._waiting, None
        start, takeover, self._start, self._takeover = self._start, self._takeover, False, False
        inputs = MissionInputs(
            vehicle=self.link.snapshot(),
            leader=self._leader,
            leader_shared=self._shared,
            obstacle=self._obstacle,
            neighbours=tuple(self._neighbours.values()),
            start_requested=start,
            takeover_requested=takeover,
            shutdown_requested=self._shutdown,
            command_results=results,
            operator=operator,
            airframe=self._airframe,
        )
        out = self.machine.step(inputs, now_s)
        self.last_output = out
        if waiting is not None:
            self._settle(waiting, out)
        for tr in out.transitions:
            self._report(tr)
        if out.setpoint is not None:
            self._last_setpoint = out.setpoint
            await self._stream(out.setpoint)
        for cmd in out.commands:
            self._commands.put_nowait(cmd)
        if out.external_position is not None:
            try:
                await self.link.send_external_position(out.external_position)
            except CompanionError as exc:
                log.debug("external position not sent: %s", exc)
        if self.on_step is not None:
            self.on_step(inputs, out)
        return out

    def _report(self, tr: Transition) -> None:
        self.last_transition = tr
        detail = f" ({tr.detail})" if tr.detail else ""
        log.log(
            _LOG_LEVEL[tr.severity],
            "mission: %s -> %s: %s%s",
            tr.from_state.value,
            tr.to_state.value,
            tr.reason.value,
            detail,
            extra={"event": tr.as_dict()},
        )
        if self.on_transition is not None:
            self.on_transition(tr)

    async def _stream(self, setpoint: Setpoint) -> None:
        try:
            await self.link.set_setpoint(setpoint)
        except CompanionError as exc:
            # Count, then say it once per streak: a lost link shows up in the snapshot and the machine acts.
            self._setpoint_failures += 1
            if self._setpoint_failures == 1:
                log.warning("mission: setpoint not accepted by the link: %s", exc)
        else:
            if self._setpoint_failures:
                log.info("mission: setpoints flow again after %d failures", self._setpoint_failures)
            self._setpoint_failures = 0

    async def _execute_commands(self) -> None:
        while True:
            cmd = await self._commands.get()
            # Awaited first: ``self._results.append`` taken before the await would append to the list that
            # a tick swapped out meanwhile, and a result of a command that spanned a tick was lost (a refused
            # offboard start then looked in flight for COMMAND_STALE_S, and the follower hovered 10 s).
            result = await self._execute(cmd)
            self._results.append(result)

    async def _execute(self, cmd: Command) -> CommandResult:
        log.info("mission: command %s", cmd.kind.value)
        try:
            async with compat.timeout(self.command_timeout_s * COMMAND_GRACE_FACTOR):
                await self._dispatch(cmd)
        except CommandRejectedError as exc:
            log.warning("mission: %s refused: %s", cmd.kind.value, exc.result)
            return CommandResult(cmd.kind, False, exc.result)
        except LinkLostError as exc:
            return CommandResult(cmd.kind, False, f"link lost: {exc}")
        except TimeoutError:
            log.warning("mission: %s timed out", cmd.kind.value)
            return CommandResult(cmd.kind, False, "TIMEOUT")
        return CommandResult(cmd.kind, True)

    async def _dispatch(self, cmd: Command) -> None:
        link = self.link
        k = cmd.kind
        if k == CommandKind.ARM:
            await link.arm()
        elif k == CommandKind.DISARM:
            await link.disarm()
        elif k == CommandKind.TAKEOFF:
            await link.takeoff(cmd.altitude_m if cmd.altitude_m is not None else 2.5)
        elif k == CommandKind.START_OFFBOARD:
            if self._last_setpoint is None:
                raise CommandRejectedError("start_offboard", "NO_SETPOINT_SET")
            await link.start_offboard(self._last_setpoint)
        elif k == CommandKind.STOP_OFFBOARD:
            self._last_setpoint = None
            await link.stop_offboard()
        elif k == CommandKind.RELEASE_OFFBOARD:
            self._last_setpoint = None
            await link.release_offboard()
        elif k == CommandKind.HOLD:
            await link.hold()
        elif k == CommandKind.LAND:
            await link.land()
        elif k == CommandKind.RTL:
            await link.return_to_launch()
        else:  # pragma: no cover - exhaustive over CommandKind
            raise AssertionError(k)
