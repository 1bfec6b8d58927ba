"""The mission machine's phases (:class:`~companion.mission.machine.MissionMachine` owns one of each).

``context`` holds what the phases read (time, the state, the health verdicts, the law); ``launch`` goes
from the link to the formation, ``follow`` flies it, ``recovery`` holds on when the leader is lost or the
estimate stale, ``landing`` goes down and hands the vehicle to PX4. Each keeps its own memory and returns
a :class:`~companion.mission.states.request.PhaseStep`: its setpoint and at most one transition request,
which the machine applies (:mod:`companion.mission.transitions`).
"""

from companion.mission.states.context import (
    AIRBORNE_STATES,
    NOT_IN_CONTROL,
    OFFBOARD_STATES,
    PX4_STATES,
    MissionContext,
)
from companion.mission.states.follow import FollowPhase
from companion.mission.states.landing import LandingPhase
from companion.mission.states.launch import LaunchPhase
from companion.mission.states.recovery import RecoveryPhase

__all__ = [
    "AIRBORNE_STATES",
    "NOT_IN_CONTROL",
    "OFFBOARD_STATES",
    "PX4_STATES",
    "FollowPhase",
    "LandingPhase",
    "LaunchPhase",
    "MissionContext",
    "RecoveryPhase",
]
