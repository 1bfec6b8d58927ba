"""The mission machine's phases (:class:`~companion.mission.machine.MissionMachine` owns one of each).

``context`` holds what the phases share: the machine's memory and the transitions several of them make;
``launch`` goes from the link to the formation, ``follow`` flies it, ``recovery`` holds on when the leader
is lost or the estimate stale, ``landing`` goes down and hands the vehicle to PX4.
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
