"""Transitions: phases ask, the machine applies, in one place (companion.mission.transitions)."""

from __future__ import annotations

from companion.config import Config, MissionConfig
from companion.mission.states.request import Move, abort, go, go_px4, hover
from companion.mission.types import CommandKind, MissionInputs, MissionState, Reason

from .mission_harness import Harness

S = MissionState


def _inputs(h: Harness) -> MissionInputs:
    return MissionInputs(vehicle=h.ap.state(h.now_s))


def test_a_phase_returns_its_request_and_leaves_the_state_to_the_machine() -> None:
    h = Harness()
    h.to_follow()
    h.machine.transitions.apply(go(S.HOVER, Reason.PERCEPTION_STALL), _inputs(h))
    h.machine.c.now_s += h.cfg.mission.stall_hover_s + 1.0
    step = h.machine.recovery.hover(_inputs(h))
    assert h.state == S.HOVER  # the handler asked; nothing moved yet
    assert step.setpoint is None
    assert step.request is not None
    assert step.request.move == Move.ABORT
    assert step.request.reason == Reason.STALL_TIMEOUT


def test_an_abort_is_the_configured_px4_mode_with_gps_and_its_command_goes_out() -> None:
    h = Harness(Config(mission=MissionConfig(leader_lost_action="rtl")))
    h.to_follow()
    h.machine.c.book.outgoing = []
    h.machine.transitions.apply(abort(Reason.REACQUIRE_TIMEOUT), _inputs(h))
    assert h.state == S.PX4_RTL
    assert [c.kind for c in h.machine.c.book.outgoing] == [CommandKind.RTL]
    assert h.machine.transitions.log[-1].reason == Reason.REACQUIRE_TIMEOUT


def test_an_abort_without_gps_is_the_controlled_landing_and_sends_nothing() -> None:
    h = Harness()
    h.to_follow()
    h.lose_gps()
    h.run(h.cfg.mission.gps_loss_confirm_s + 0.5)
    h.machine.c.book.outgoing = []
    h.machine.transitions.apply(abort(Reason.STALL_TIMEOUT), _inputs(h))
    assert h.state == S.CONTROLLED_LANDING
    assert h.machine.c.book.outgoing == []
    assert h.machine.transitions.log[-1].detail == "no GPS"


def test_a_change_of_state_starts_its_clock_and_clears_the_retries_a_note_does_not() -> None:
    h = Harness()
    h.to_follow()
    h.machine.launch.retries.tried(h.now_s)
    h.machine.transitions.apply(hover("0.50 s old"), _inputs(h))
    assert h.state == S.HOVER
    assert h.machine.c.entered_s == h.machine.c.now_s
    assert h.machine.launch.retries.attempts == 0
    h.machine.launch.retries.tried(h.now_s)
    h.machine.transitions.apply(go(S.HOVER, Reason.PERCEPTION_STALL), _inputs(h))  # no move, no log
    assert h.machine.launch.retries.attempts == 1
    assert h.machine.transitions.log[-1].to_state == S.HOVER


def test_a_px4_mode_request_sends_its_command_even_when_already_there() -> None:
    h = Harness()
    h.to_follow()
    h.machine.transitions.apply(go_px4(S.PX4_HOLD, Reason.OPERATOR_HOLD), _inputs(h))
    h.machine.c.book.outgoing = []
    h.machine.transitions.apply(go_px4(S.PX4_HOLD, Reason.OPERATOR_HOLD), _inputs(h))
    assert h.state == S.PX4_HOLD
    assert [c.kind for c in h.machine.c.book.outgoing] == [CommandKind.HOLD]
