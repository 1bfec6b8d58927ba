"""The mission machine's bookkeeping of what it asked PX4 for: commands in flight, and the offboard stream.

:class:`CommandBook` holds the commands of this tick, the ones sent and not answered yet, and the last result
of each kind. :class:`OffboardStream` starts offboard when a state streams setpoints and stops the stream the
tick it no longer does; what to do when PX4 never takes offboard is the machine's call.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from companion.kernel.flight import FlightMode, VehicleState
from companion.mission.types import Command, CommandKind, CommandResult

#: Re-send a command that got no result after this long (the link's own timeouts are shorter), s.
COMMAND_STALE_S = 10.0
OFFBOARD_ATTEMPTS = 3
OFFBOARD_RETRY_S = 1.0


@dataclass(slots=True)
class _Pending:
    """A command sent and not answered yet."""

    kind: CommandKind
    sent_s: float


class CommandBook:
    """This tick's outgoing commands, the commands in flight, and the last result of each kind."""

    def __init__(self) -> None:
        #: This tick's commands, in the order they go out.
        self.outgoing: list[Command] = []
        self.pending: dict[CommandKind, _Pending] = {}
        self.last_result: dict[CommandKind, CommandResult] = {}

    def send(self, kind: CommandKind, now_s: float, altitude_m: float | None = None) -> None:
        self.pending[kind] = _Pending(kind, now_s)
        self.last_result.pop(kind, None)
        self.outgoing.append(Command(kind, altitude_m))

    def send_first(self, kind: CommandKind, now_s: float) -> None:
        """A command that goes out before any other of this tick."""
        self.outgoing.insert(0, Command(kind))
        self.pending[kind] = _Pending(kind, now_s)

    def in_flight(self, kind: CommandKind, now_s: float) -> bool:
        p = self.pending.get(kind)
        return p is not None and now_s - p.sent_s < COMMAND_STALE_S

    def absorb(self, r: CommandResult) -> None:
        self.pending.pop(r.kind, None)
        self.last_result[r.kind] = r

    def failed(self, kind: CommandKind) -> CommandResult | None:
        r = self.last_result.get(kind)
        return r if r is not None and not r.ok else None


class OffboardStream:
    """Whether the machine streams setpoints, and whether PX4 has confirmed offboard for them."""

    def __init__(self, book: CommandBook) -> None:
        self.book = book
        self.streaming = False
        self.confirmed = False
        self.attempts = 0
        self.last_try_s = -math.inf

    def manage(self, veh: VehicleState, wants: bool, now_s: float) -> str | None:
        """Start offboard when a state streams setpoints; stop the stream the tick it no longer does.

        Returns why, when offboard could not be started and the stream gave up (it is stopped then; the
        machine drops this tick's setpoint and leaves offboard for a PX4 mode). None otherwise.
        """
        if not wants:
            if self.streaming:
                self.stop(now_s)
            return None
        self.streaming = True
        if veh.flight_mode == FlightMode.OFFBOARD:
            self.confirmed = True
            self.attempts = 0
            return None
        if self.confirmed or self.book.in_flight(CommandKind.START_OFFBOARD, now_s):
            return None
        if now_s - self.last_try_s < OFFBOARD_RETRY_S:
            return None
        if self.attempts >= OFFBOARD_ATTEMPTS:
            failed = self.book.failed(CommandKind.START_OFFBOARD)
            detail = failed.detail if failed else "mode never became offboard"
            self.stop(now_s)
            return detail
        self.attempts += 1
        self.last_try_s = now_s
        self.book.send(CommandKind.START_OFFBOARD, now_s)
        return None

    def stop(self, now_s: float) -> None:
        """STOP_OFFBOARD goes out first, before any PX4 mode command of the same tick."""
        self.streaming = False
        self.confirmed = False
        self.attempts = 0
        self.last_try_s = -math.inf
        self.book.send_first(CommandKind.STOP_OFFBOARD, now_s)

    def release(self) -> None:
        """A pilot or a failsafe took the vehicle out of offboard: stop streaming without asking for a mode.

        Never STOP_OFFBOARD here: MAVSDK's stop() asks for Hold and would override the pilot.
        """
        self.confirmed = False
        self.streaming = False
        self.book.outgoing.append(Command(CommandKind.RELEASE_OFFBOARD))
