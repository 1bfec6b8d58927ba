"""What an operator's answer says comes next: every state a command can leave the mission in says it."""

from __future__ import annotations

from companion.config import MissionConfig
from companion.mission.next_step import next_step, slot_next_step
from companion.mission.types import MissionState

S = MissionState

#: The states a start, land or hold can leave the mission in.
ANSWERED_STATES = (
    S.PREFLIGHT,
    S.ARMING,
    S.ACQUIRE,
    S.FOLLOW,
    S.FOLLOW_VISION,
    S.PX4_HOLD,
    S.PX4_LAND,
    S.PX4_RTL,
    S.CONTROLLED_LANDING,
)


def test_every_state_a_command_leaves_says_what_comes_next() -> None:
    m = MissionConfig()
    for state in ANSWERED_STATES:
        words = next_step(state, m, arm_attempts=3)
        assert words, state
        assert " refused: " not in words  # the service reads that as a refusal


def test_acquire_says_how_long_it_waits_and_what_follows_a_timeout() -> None:
    m = MissionConfig(acquire_timeout_s=25.0, leader_lost_action="hold")
    assert next_step(S.ACQUIRE, m, arm_attempts=3) == (
        "waits up to 25 s (mission.acquire_timeout_s) for a confirmed track of the leader, then follows; "
        "without one PX4 holds"
    )
    assert next_step(S.PX4_HOLD, m, arm_attempts=3) == (
        "PX4 holds position until companion start (follow again) or companion command land"
    )
    assert next_step(S.PX4_LAND, m, arm_attempts=3).endswith("companion start once disarmed flies again")


def test_a_new_slot_says_whether_it_is_flown_now() -> None:
    assert slot_next_step(S.FOLLOW) == "the follower moves to it from this control tick"
    assert slot_next_step(S.PREFLIGHT) == "kept; the follower flies it once it follows the leader"
