"""Formation plans: the shipped ones load, bad ones are refused in one line each, a service flies its slot."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from companion.config import load_config, load_plan
from companion.kernel.errors import ConfigError

PLANS = Path(__file__).resolve().parents[2] / "config" / "formations"


def test_shipped_plans_load_with_four_followers() -> None:
    for name in ("v", "line"):
        plan = load_plan(PLANS / f"{name}.toml")
        assert plan.followers == ("follower1", "follower2", "follower3", "follower4")
        assert all(s.offset_m[0] < 0 for s in plan.slots)


@pytest.mark.parametrize(
    ("slots", "words"),
    [
        ('[[slots]]\nfollower = "a"\noffset_m = [1.0, 0.0, 0.0]\n', "behind the leader"),
        ('[[slots]]\nfollower = "a"\noffset_m = [-4.0, 0.0, 0.0]\n[[slots]]\nfollower = "b"\n'
         'offset_m = [-4.0, 1.0, 0.0]\n', "closer than"),
        ('[[slots]]\nfollower = "a"\noffset_m = [-4.0, 0.0, 0.0]\n[[slots]]\nfollower = "a"\n'
         'offset_m = [-4.0, 5.0, 0.0]\n', "one slot only"),
    ],
)  # fmt: skip
def test_bad_plans_are_refused_with_the_reason(tmp_path: Path, slots: str, words: str) -> None:
    p = tmp_path / "bad.toml"
    p.write_text(f'schema_version = 1\nname = "bad"\n{slots}')
    with pytest.raises(ConfigError) as exc:
        load_plan(p)
    assert words in str(exc.value)


def test_a_service_with_a_plan_flies_its_slot_facing_the_leader(tmp_path: Path) -> None:
    cfg_file = tmp_path / "wingman.toml"
    cfg_file.write_text(f'vehicle_id = "follower3"\n[formation]\nplan = "{PLANS / "v.toml"}"\n')
    cfg = load_config(cfg_file, environ={})
    plan = load_plan(PLANS / "v.toml")
    slot = plan.slot("follower3").offset_m
    assert cfg.formation.slot_leader_m == slot
    assert cfg.formation.offset_cam_m == pytest.approx((0.0, -slot[2], math.hypot(slot[0], slot[1])))
    assert len(cfg.formation.neighbour_slots_m) == 3
    assert slot not in cfg.formation.neighbour_slots_m


def test_a_vehicle_id_without_a_slot_is_one_clear_error(tmp_path: Path) -> None:
    cfg_file = tmp_path / "wingman.toml"
    cfg_file.write_text(f'vehicle_id = "follower9"\n[formation]\nplan = "{PLANS / "v.toml"}"\n')
    with pytest.raises(ConfigError) as exc:
        load_config(cfg_file, environ={})
    assert "no slot for 'follower9'" in str(exc.value)
