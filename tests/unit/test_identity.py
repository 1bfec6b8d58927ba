"""Which autopilot the service flies: its own system id, never the leader's."""

from __future__ import annotations

from companion.vehicle.identity import choose_autopilot

URL = "udpin://0.0.0.0:14540"


def test_the_configured_system_is_chosen_among_others() -> None:
    v = choose_autopilot([1, 2, 7], 2, leader=1, listened_s=0.0, patience_s=10.0, url=URL)
    assert v.system_id == 2
    assert v.refusal is None


def test_unset_takes_the_first_that_is_not_the_leader() -> None:
    assert choose_autopilot([1, 3], 0, leader=1, listened_s=0.0, patience_s=10.0, url=URL).system_id == 3
    v = choose_autopilot([1], 0, leader=1, listened_s=1.0, patience_s=10.0, url=URL)
    assert v.system_id is None
    assert (
        v.waiting
        == f"heard system 1 (the leader) on {URL}, waiting for an autopilot that is not the leader's"
    )


def test_only_the_leader_on_the_link_is_refused_after_patience() -> None:
    v = choose_autopilot([1], 2, leader=1, listened_s=10.0, patience_s=10.0, url=URL)
    assert v.system_id is None
    assert v.refusal == (
        f"{URL} carries autopilot system 1 (the leader), not system 2: refusing to command it "
        "(set link.url to the follower's own autopilot, or link.system_id)"
    )


def test_the_leader_is_never_chosen_even_when_configured() -> None:
    v = choose_autopilot([1], 1, leader=1, listened_s=60.0, patience_s=10.0, url=URL)
    assert v.system_id is None
    assert v.refusal is not None


def test_silence_is_waited_out_not_refused() -> None:
    v = choose_autopilot([], 2, leader=1, listened_s=100.0, patience_s=10.0, url=URL)
    assert v == choose_autopilot([], 2, leader=1, listened_s=0.0, patience_s=10.0, url=URL)
    assert v.refusal is None
    assert v.waiting == f"no autopilot on {URL} yet"
