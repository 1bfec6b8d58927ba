"""The one place the mission machine changes state: a phase's or a global check's request, applied.

Every move between states goes through :meth:`Transitions.apply`: what a move resets (the state's clock,
the retries, the law, the join into the slot), which state an abort or a way back into the formation
resolves to (the GPS decides), the memory a phase takes on entry (REACQUIRE's coast and scan, FOLLOW_VISION's
attitude start) and the command a PX4 mode is entered with. Pure: time is the context's ``now_s``.
"""

from __future__ import annotations

import numpy as np

from companion.mission.states import FollowPhase, LandingPhase, LaunchPhase, MissionContext, RecoveryPhase
from companion.mission.states.request import Move, TransitionRequest
from companion.mission.types import CommandKind, MissionInputs, MissionState, Reason, Transition, VisionMode

#: The command each of PX4's modes is entered with.
PX4_MODE_COMMAND = {
    MissionState.PX4_HOLD: CommandKind.HOLD,
    MissionState.PX4_LAND: CommandKind.LAND,
    MissionState.PX4_RTL: CommandKind.RTL,
}
#: The PX4 mode each ``mission.leader_lost_action`` aborts to.
ABORT_MODE = {"hold": MissionState.PX4_HOLD, "land": MissionState.PX4_LAND, "rtl": MissionState.PX4_RTL}


class Transitions:
    """Applies transition requests to the machine's state; keeps this tick's log of them."""

    def __init__(
        self,
        ctx: MissionContext,
        launch: LaunchPhase,
        follow: FollowPhase,
        recovery: RecoveryPhase,
        landing: LandingPhase,
    ) -> None:
        self.c = ctx
        self.launch = launch
        self.follow = follow
        self.recovery = recovery
        self.landing = landing
        #: This tick's transitions, in the order they happened.
        self.log: list[Transition] = []

    def begin_tick(self) -> None:
        self.log = []

    def apply(self, req: TransitionRequest | None, inp: MissionInputs) -> None:
        """Carry out one request (None: nothing to do)."""
        if req is None:
            return
        if req.move in (Move.GO, Move.PX4):
            if req.state is None:  # pragma: no cover - the request's constructors set it
                raise ValueError(f"{req.move} needs a state")
            self._go(req.state, req.reason, req.detail)
            if req.move == Move.PX4:
                self.c.book.send(PX4_MODE_COMMAND[req.state], self.c.now_s)
        elif req.move == Move.ABORT:
            self._abort(req.reason, req.detail)
        elif req.move == Move.FOLLOW:
            self._enter_follow(inp, req.reason, req.detail)
        elif req.move == Move.GPS_LOST:
            self._on_gps_lost(inp)
        elif req.move == Move.REACQUIRE:
            self.recovery.remember_loss(inp, attitude=self.flying_attitude())
            self._go(MissionState.REACQUIRE, req.reason, req.detail)
        elif req.move == Move.HOVER:
            self.recovery.remember_hover(inp, attitude=self.flying_attitude())
            self._go(MissionState.HOVER, req.reason, req.detail)
        else:  # pragma: no cover
            raise AssertionError(f"unhandled move {req.move}")

    def note(self, reason: Reason, *, restart_clock: bool = False) -> None:
        """Log ``reason`` against the state the machine stays in (and start its clock again if asked)."""
        st = self.c.state
        if restart_clock:
            self.c.entered_s = self.c.now_s
        self.log.append(Transition(self.c.now_s, st, st, reason))

    def flying_attitude(self) -> bool:
        """Whether the current flight uses attitude setpoints (no GPS, or vision on attitude)."""
        if not self.c.gps.ok:
            return True
        return self.c.state == MissionState.FOLLOW_VISION and self.follow.vision_mode == VisionMode.ATTITUDE

    def _go(self, state: MissionState, reason: Reason, detail: str = "") -> None:
        c = self.c
        if state == c.state and reason != Reason.VISION_MODE_CHANGED:
            return
        self.log.append(Transition(c.now_s, c.state, state, reason, detail))
        if state != c.state:
            c.state = state
            c.entered_s = c.now_s
            self.launch.retries.clear()
            self.landing.retries.clear()
            c.law.reset()
            # A planned approach into the slot on every entry into FOLLOW (planned on its first tick).
            if state == MissionState.FOLLOW:
                self.follow.join.arm()
            else:
                self.follow.join.cancel()

    def _abort(self, reason: Reason, detail: str) -> None:
        if not self.c.gps.ok:
            self._go(MissionState.CONTROLLED_LANDING, reason, detail or "no GPS")
            return
        target = ABORT_MODE[self.c.m.leader_lost_action]
        self._go(target, reason, detail)
        self.c.book.send(PX4_MODE_COMMAND[target], self.c.now_s)

    def _enter_follow(self, inp: MissionInputs, reason: Reason, detail: str) -> None:
        m = self.c.m
        if self.c.gps.ok:
            self._go(MissionState.FOLLOW, reason, detail)
            self.c.law.seed_velocity(np.array(inp.vehicle.v_ned_m_s))
        elif m.gps_loss_policy == "land":
            self._go(MissionState.CONTROLLED_LANDING, Reason.GPS_LOST, "policy land")
        else:
            self.follow.start_vision_on_attitude()
            self._go(MissionState.FOLLOW_VISION, reason, detail or f"policy {m.gps_loss_policy}")

    def _on_gps_lost(self, inp: MissionInputs) -> None:
        c, m = self.c, self.c.m
        self.follow.forget_share_fix()  # the GPS that comes back may put both ends elsewhere
        if m.gps_loss_policy == "land":
            self._go(MissionState.CONTROLLED_LANDING, Reason.GPS_LOST, "policy land")
        elif not c.tracked(inp):
            self._go(MissionState.CONTROLLED_LANDING, Reason.GPS_LOST, "leader not tracked")
        elif not c.link.attitude_available(inp.vehicle, c.now_s):
            self._go(MissionState.CONTROLLED_LANDING, Reason.NO_VISION_FALLBACK, "no attitude or altitude")
        else:
            self.follow.start_vision_on_attitude()
            self._go(MissionState.FOLLOW_VISION, Reason.GPS_LOST, f"policy {m.gps_loss_policy}")
