"""What the mission does next from a state, and what it waits for: the tail of an operator's answer.

An operator who asked for a start, land or hold reads the transitions it caused and then this line, so a
state that waits (arming, the climb, acquiring the leader, PX4's own modes) says for what, for how long,
and what happens when the wait runs out. The CLI and MQTT carry the same words. Pure: no I/O.
"""

from __future__ import annotations

from companion.config import MissionConfig
from companion.mission.types import MissionState

S = MissionState

#: What each configured abort (``mission.leader_lost_action``) leaves the vehicle doing.
_ABORT_WORDS = {"hold": "PX4 holds", "land": "PX4 lands", "rtl": "PX4 returns home and lands"}


def _acquire_words(m: MissionConfig) -> str:
    return (
        f"waits up to {m.acquire_timeout_s:g} s (mission.acquire_timeout_s) for a confirmed track of the "
        f"leader, then follows; without one {_ABORT_WORDS[m.leader_lost_action]}"
    )


def next_step(state: MissionState, m: MissionConfig, *, arm_attempts: int) -> str:
    """One line on what ``state`` leads to and what it waits for ("" where it waits for nothing)."""
    climb = f"takes off to {m.takeoff_altitude_m:g} m (within {m.takeoff_timeout_s:g} s)"
    words = {
        S.PREFLIGHT: "arms once preflight passes (GPS settled, home set, on the ground)",
        S.ARMING: f"arms (up to {arm_attempts} tries), {climb}, then {_acquire_words(m)}",
        S.TAKEOFF: f"{climb}, then {_acquire_words(m)}",
        S.ACQUIRE: _acquire_words(m),
        S.FOLLOW: "follows the leader until companion command hold or land",
        S.FOLLOW_VISION: "follows the leader on vision alone until companion command land",
        S.REACQUIRE: (
            f"looks for the leader for up to {m.reacquire_coast_s + m.reacquire_scan_s:g} s, then follows "
            f"again; without it {_ABORT_WORDS[m.leader_lost_action]}"
        ),
        S.PX4_HOLD: "PX4 holds position until companion start (follow again) or companion command land",
        S.PX4_LAND: "PX4 lands and disarms; companion start once disarmed flies again",
        S.PX4_RTL: "PX4 returns home and lands; companion command hold stops it there",
        S.CONTROLLED_LANDING: "the companion lands the vehicle (no GPS) and PX4 disarms on the ground",
        S.LANDED: "waits for PX4 to disarm; companion start then flies again",
        S.DISARMED: "waits for companion start",
    }
    return words.get(state, "")


def slot_next_step(state: MissionState) -> str:
    """What a new formation slot does from ``state``: flown at once while following, else kept for later."""
    if state in (S.FOLLOW, S.FOLLOW_VISION, S.REACQUIRE, S.HOVER):
        return "the follower moves to it from this control tick"
    return "kept; the follower flies it once it follows the leader"
