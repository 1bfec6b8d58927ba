"""What a phase hands back each tick: its setpoint and at most one transition request; pure.

A phase never moves the machine itself. It returns a :class:`PhaseStep`; the machine applies the request
(:class:`~companion.mission.transitions.Transitions`), so every move between states, and what each move
resets, is written in one place. A request names the move, not always the state: an abort lands under
control without GPS and hands the vehicle to PX4 with it, and a way back into the formation is FOLLOW or
FOLLOW_VISION as the GPS allows; the machine decides which when it applies it.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from typing import NamedTuple

from companion.kernel.flight import ExternalPosition, Setpoint
from companion.kernel.frames import Vec3
from companion.mission.types import MissionState, Reason


class Move(Enum):
    """The kinds of transition a phase can ask for."""

    #: To ``state`` (or, to the state the machine is in, a note in the transition log).
    GO = "go"
    #: To one of PX4's modes (Hold, Land, RTL), its command sent with it.
    PX4 = "px4"
    #: The configured abort: a PX4 mode while GPS is healthy, the controlled landing when it is not.
    ABORT = "abort"
    #: Into the formation: FOLLOW or FOLLOW_VISION, whichever the GPS allows.
    FOLLOW = "follow"
    #: GPS went bad in flight: vision formation if the policy and the leader allow it, else land.
    GPS_LOST = "gps_lost"
    #: The leader was lost: REACQUIRE, remembering where it was going.
    REACQUIRE = "reacquire"
    #: The estimate went stale: HOVER.
    HOVER = "hover"


@dataclass(frozen=True, slots=True)
class TransitionRequest:
    """One requested move, with the reason the log and the operator are given."""

    move: Move
    reason: Reason
    state: MissionState | None = None
    detail: str = ""


def go(state: MissionState, reason: Reason, detail: str = "") -> TransitionRequest:
    """To ``state``; to the state the machine is in, a note in the log (a vision mode change)."""
    return TransitionRequest(Move.GO, reason, state, detail)


def go_px4(state: MissionState, reason: Reason, detail: str = "") -> TransitionRequest:
    """To one of PX4's modes, its command sent the same tick."""
    return TransitionRequest(Move.PX4, reason, state, detail)


def abort(reason: Reason, detail: str = "") -> TransitionRequest:
    """The configured abort (``mission.leader_lost_action`` with GPS, the controlled landing without)."""
    return TransitionRequest(Move.ABORT, reason, None, detail)


def enter_follow(reason: Reason, detail: str = "") -> TransitionRequest:
    """Into the formation: FOLLOW with GPS, else FOLLOW_VISION or down as ``gps_loss_policy`` says."""
    return TransitionRequest(Move.FOLLOW, reason, None, detail)


def gps_lost() -> TransitionRequest:
    """GPS went bad in flight."""
    return TransitionRequest(Move.GPS_LOST, Reason.GPS_LOST)


def reacquire(detail: str) -> TransitionRequest:
    """The leader was lost."""
    return TransitionRequest(Move.REACQUIRE, Reason.LEADER_LOST, MissionState.REACQUIRE, detail)


def hover(detail: str) -> TransitionRequest:
    """The estimate went stale (``detail``: how old it is)."""
    return TransitionRequest(Move.HOVER, Reason.PERCEPTION_STALL, MissionState.HOVER, detail)


class PhaseStep(NamedTuple):
    """One phase's tick: what to stream and where to go.

    The setpoint (None: none), PX4's external fix, the formation error (NED, m, where the law ran) and at
    most one transition request.
    """

    setpoint: Setpoint | None = None
    external: ExternalPosition | None = None
    error_ned_m: Vec3 | None = None
    request: TransitionRequest | None = None


#: A tick with nothing to stream and nowhere to go.
STAY = PhaseStep()


def moving(request: TransitionRequest | None) -> PhaseStep:
    """A tick that only asks for a transition (or, given None, stays)."""
    return PhaseStep(request=request)
