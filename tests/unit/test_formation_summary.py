"""A formation campaign's summary: every follower counted, swaps summed, the worst separation kept."""

from __future__ import annotations

from companion.lab.evaluation.campaign_summary import formation_summary


def _follower(outcome: str, dev: float, sep: float, swaps: int = 0) -> dict[str, object]:
    return {
        "outcome": outcome,
        "max_deviation_m": dev,
        "min_separation_m": sep,
        "leader_identity_swaps": swaps,
        "identity_swaps_detected": swaps,
    }


def test_followers_of_every_run_are_counted_and_the_worst_kept() -> None:
    runs = [
        {"followers": [_follower("completed", 0.3, 3.2), _follower("completed", 0.7, 2.9)]},
        {"followers": [_follower("landed_safely", 0.2, 2.4, swaps=1), _follower("completed", 0.4, 3.0)]},
    ]
    s = formation_summary(runs)
    assert s["follower_outcomes"] == {"completed": 3, "landed_safely": 1}
    assert s["leader_identity_swaps"] == 1
    assert s["worst_separation_m"] == 2.4
    assert s["follower_max_deviation_m"] == 0.7
    assert s["followers_over_0_6_m"] == 1


def test_single_follower_campaigns_get_no_formation_keys() -> None:
    assert formation_summary([{"outcome": "completed"}]) == {}
