"""A formation flown end to end in lockstep: the real detector on rendered frames with a neighbour in view.

Two followers of the V (an inner one and the outer one behind it, which sees the inner one beside the
leader), each with its own service core and camera, the leader on a figure-eight: both reach formation,
the outer one's identity filter turns the neighbour's detections away, nobody comes within 2 m of anyone,
and the report carries the ``followers`` contract and the plot from above.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from companion.lab.evaluation.campaign import RunSpec, run_one

REPO = Path(__file__).resolve().parents[2]

PLAN = """schema_version = 1
name = "pair"
[[slots]]
follower = "follower1"
offset_m = [-3.5, -2.5, 0.0]
[[slots]]
follower = "follower3"
offset_m = [-5.0, -6.0, 0.0]
"""

FOLLOWER_KEYS = (
    "name",
    "outcome",
    "formation_rmse_m",
    "max_deviation_m",
    "min_separation_m",
    "leader_identity_swaps",
    "identity_swaps_detected",
)


def _scenario(tmp_path: Path) -> Path:
    (tmp_path / "pair.toml").write_text(PLAN)
    text = (REPO / "config" / "scenarios" / "variants" / "formation-v.toml").read_text()
    text = text.replace('plan = "v"', f'plan = "{tmp_path / "pair.toml"}"')
    text = text.replace("duration_s = 100.0", "duration_s = 40.0").replace(
        "formation_duration_s = 74.0", "formation_duration_s = 14.0"
    )
    path = tmp_path / "formation-pair.toml"
    path.write_text(text.replace('name = "formation-v"', 'name = "formation-pair"'))
    return path


@pytest.mark.render
@pytest.mark.slow
@pytest.mark.timeout(600)
def test_two_followers_fly_their_slots_and_keep_the_leader(tmp_path: Path) -> None:
    out = tmp_path / "run"
    report = run_one(RunSpec(str(_scenario(tmp_path)), 1, out, harness="lockstep", detector="network"))
    saved = json.loads((out / "report.json").read_text())
    assert saved["followers"] == report["followers"]
    entries = {f["name"]: f for f in report["followers"]}
    assert set(entries) == {"follower1", "follower3"}
    for f in entries.values():
        assert all(f[k] is not None for k in FOLLOWER_KEYS), f
        assert f["outcome"] == "completed", f["transitions"]
        assert f["leader_identity_swaps"] == 0
        assert f["min_separation_m"] >= 2.0
        assert f["max_deviation_m"] < 1.0
    # The outer follower sees the inner one beside the leader: its detections were turned away.
    assert entries["follower3"]["identity_rejected"]["neighbour"] > 20
    assert report["outcome"] == "completed"
    assert (out / "plots" / "formation.png").stat().st_size > 20_000
    assert (out / "followers" / "follower3" / "flight_log.npz").exists()
