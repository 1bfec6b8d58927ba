"""The mission machine's state handlers, by flight phase (:class:`~companion.mission.machine.MissionMachine`).

``base`` holds the machine's memory and the transitions several handlers share; ``launch`` goes from the
link to the formation, ``follow`` flies it, ``recovery`` holds on when the leader is lost or the estimate
stale, ``landing`` goes down and hands the vehicle to PX4.
"""

from companion.mission.states.base import (
    AIRBORNE_STATES,
    NOT_IN_CONTROL,
    OFFBOARD_STATES,
    PX4_STATES,
    MachineBase,
)
from companion.mission.states.follow import FollowStates
from companion.mission.states.landing import LandingStates
from companion.mission.states.launch import LaunchStates
from companion.mission.states.recovery import RecoveryStates

__all__ = [
    "AIRBORNE_STATES",
    "NOT_IN_CONTROL",
    "OFFBOARD_STATES",
    "PX4_STATES",
    "FollowStates",
    "LandingStates",
    "LaunchStates",
    "MachineBase",
    "RecoveryStates",
]
