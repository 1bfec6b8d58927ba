"""Structure envelopes, the follower's clearance from them, and the crash verdict they give."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.lab.evaluation.obstacles import Envelopes
from companion.lab.evaluation.outcome import TruthMonitor
from companion.lab.evaluation.setup import scenario_path
from sitl.render import surroundings
from sitl.render.config import OccluderSpec, VisualConfig, visual_from_mapping
from sitl.render.structures import solid_structures
from sitl.world.scenario import load_scenario

LEVEL = (1.0, 0.0, 0.0, 0.0)


def _tree(n: float, e: float, radius_m: float = 2.0, height_m: float = 9.0) -> OccluderSpec:
    return OccluderSpec(kind="tree", p_ned_m=(n, e, 0.0), radius_m=radius_m, height_m=height_m)


def test_tree_envelope_distances() -> None:
    env = Envelopes.from_specs([_tree(30.0, 3.0)])
    assert env.clearance((30.0, 8.0, -5.0)) == pytest.approx((3.0, "tree"))  # 5 m off the axis, r 2
    assert env.clearance((30.0, 3.0, -5.0))[0] == pytest.approx(-2.0)  # on the axis: 2 m deep
    assert env.clearance((30.0, 3.0, -12.0))[0] == pytest.approx(3.0)  # 3 m above its top
    corner = env.clearance((30.0, 8.0, -13.0))[0]  # beside and above: to the rim
    assert corner == pytest.approx(5.0)


def test_yawed_building_with_its_roof() -> None:
    spec = OccluderSpec(kind="building", p_ned_m=(70.0, 14.0, 0.0), size_m=(8.0, 4.0, 10.0), yaw_deg=90.0)
    env = Envelopes.from_specs([spec])
    # Yawed 90 deg, its 8 m side runs east: 1 m north of its 2 m half-depth it is 1 m away...
    assert env.clearance((73.0, 14.0, -5.0)) == pytest.approx((1.0, "building"))
    # ...while 3.5 m east is still inside (half-length 4 m).
    assert env.clearance((70.0, 17.5, -5.0))[0] < 0.0
    # A roof may rise 0.45 x 4 m above the 10 m walls.
    assert env.clearance((70.0, 14.0, -12.5))[0] == pytest.approx(0.7)


def test_no_structures_gives_infinite_clearance() -> None:
    env = Envelopes.from_specs([])
    assert len(env) == 0
    assert env.clearance((0.0, 0.0, -5.0)) == (math.inf, "")


def test_flying_into_a_tree_is_a_crash_and_passing_it_is_not() -> None:
    env = Envelopes.from_specs([_tree(30.0, 3.0)])
    passing = TruthMonitor(obstacles=env)
    hitting = TruthMonitor(obstacles=env)
    for k in range(200):
        n = 20.0 + 0.1 * k
        passing.update(0.05 * k, (n, 0.5, -5.0), (2.0, 0.0, 0.0), LEVEL, None)  # 0.5 m off the crown
        hitting.update(0.05 * k, (n, 1.5, -5.0), (2.0, 0.0, 0.0), LEVEL, None)
    assert not passing.crashed
    assert passing.min_obstacle_clearance_m == pytest.approx(0.5, abs=1e-6)
    assert hitting.crashed
    assert "tree" in hitting.crash_reason


def test_solid_structures_are_the_ones_the_world_builds(monkeypatch: pytest.MonkeyPatch) -> None:
    built: list[OccluderSpec] = []
    real_add = surroundings.add_structure

    def record(b: object, spec: OccluderSpec, rng: np.random.Generator) -> None:
        built.append(spec)
        real_add(b, spec, rng)  # type: ignore[arg-type]

    monkeypatch.setattr(surroundings, "add_structure", record)
    visual = VisualConfig(seed=7, structures=25, occluders=(_tree(30.0, 3.0),))
    surroundings.build_world(visual, np.linspace(0.0, 1.0, 101))
    assert built == list(solid_structures(visual))
    assert len(built) == 26


@pytest.mark.parametrize(
    "name",
    [
        *("straight", "circle", "gps-loss", "visibility", "figure8", "leader-occluded", "link-loss", "wind"),
        *("gps-loss-land", "leader-lost"),
    ],
)
def test_every_scenario_leader_path_clears_the_scene(name: str) -> None:
    """The scripted leader must not graze a tree either: 0.8 m = its radius 0.3 m + 0.5 m."""
    sc = load_scenario(scenario_path(name))
    env = Envelopes.from_specs(solid_structures(visual_from_mapping(sc.visual, name)))
    traj = sc.leader.trajectory()
    assert traj is not None
    duration_s = sc.run.duration_s - sc.leader.start_s
    closest = min(
        env.clearance((5.0 + s[0], s[1], -sc.leader.altitude_m))[0]
        for s in (traj.sample(0.1 * k) for k in range(int(duration_s * 10)))
    )
    assert closest >= 0.8, f"{name}: the leader's path passes {closest:.2f} m from a structure"
