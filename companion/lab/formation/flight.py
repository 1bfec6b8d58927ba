"""Flying a formation scenario: the simulator config from the plan, one service config per follower, the run.

A scenario with a ``[formation]`` table (``plan``, optional ``leader_spawn_ned_m``) flies one leader and a
follower per plan slot. The followers spawn in their slots around the leader's spawn point, facing it, and
each service flies the slot named by its ``vehicle_id``.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Mapping
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError

from companion.config import Config, FormationPlan, apply_plan, load_plan
from companion.kernel.config import Section, format_validation_error
from companion.kernel.errors import ConfigError
from companion.kernel.frames import heading_to_ned
from companion.lab.evaluation.setup import REPO, SITL_CONFIG, load_detect
from companion.lab.formation.run import FormationOptions, FormationResult, FormationRun

PLAN_DIR = REPO / "config" / "formations"


class FormationSpec(Section):
    """A scenario's ``[formation]`` table."""

    plan: str
    #: Where the leader starts (world NED, m); the followers start in their slots around it.
    leader_spawn_ned_m: tuple[float, float, float] = (12.0, 0.0, 0.0)


def formation_spec(scenario: Any) -> FormationSpec | None:
    """The scenario's formation, or None for a single follower; one clear error for a bad table."""
    if not scenario.formation:
        return None
    try:
        return FormationSpec.model_validate(scenario.formation)
    except ValidationError as exc:
        raise ConfigError(f"scenario {scenario.name} [formation]", format_validation_error(exc)) from None


def plan_path(name: str) -> Path:
    p = Path(name)
    if p.suffix == ".toml":
        return p
    return PLAN_DIR / f"{name}.toml"


def sitl_config_for(
    plan: FormationPlan, spec: FormationSpec, heading_deg: float, base: Path = SITL_CONFIG
) -> Any:
    """The simulator config: the leader at its spawn point, each follower in its slot, facing the leader."""
    from sitl.config import VehicleConfig, load_sitl_config  # noqa: PLC0415 (the simulator only here)

    sitl = load_sitl_config(base)
    h = math.radians(heading_deg)
    ln, le, _ = spec.leader_spawn_ned_m
    vehicles = [
        VehicleConfig(name="leader", role="leader", spawn_ned_m=(ln, le, 0.0), spawn_yaw_deg=heading_deg)
    ]
    for slot in plan.slots:
        dn, de, _ = heading_to_ned(np.asarray(slot.offset_m, dtype=np.float64), h)
        n, e = ln + float(dn), le + float(de)
        yaw = math.degrees(math.atan2(le - e, ln - n))
        vehicles.append(
            VehicleConfig(name=slot.follower, role="follower", spawn_ned_m=(n, e, 0.0), spawn_yaw_deg=yaw)
        )
    return sitl.model_copy(update={"vehicles": tuple(vehicles)})


def follower_configs(base: Config, plan: FormationPlan, path: Path) -> dict[str, Config]:
    """Each follower's service config: ``base`` with its vehicle id, system id and slot."""
    out = {}
    for i, name in enumerate(plan.followers):
        cfg = base.model_copy(
            update={"vehicle_id": name, "link": base.link.model_copy(update={"system_id": i + 2})}
        )
        out[name] = apply_plan(cfg, path)
    return out


def run_formation(
    scenario_file: Path,
    seed: int,
    base_cfg: Config,
    runtime: str,
    options: FormationOptions,
) -> tuple[FormationResult, FormationPlan, Mapping[str, Config]]:
    """Fly one formation scenario file in lockstep (blocking)."""
    from sitl.render.config import CameraModel, visual_from_mapping  # noqa: PLC0415
    from sitl.render.renderer import Renderer  # noqa: PLC0415
    from sitl.world.lockstep import World  # noqa: PLC0415
    from sitl.world.scenario import load_scenario  # noqa: PLC0415

    scenario = load_scenario(scenario_file)
    spec = formation_spec(scenario)
    if spec is None:
        raise ConfigError(str(scenario_file), ["no [formation] table: not a formation scenario"])
    path = plan_path(spec.plan)
    plan = load_plan(path)
    configs = follower_configs(base_cfg, plan, path)
    world = World(sitl_config_for(plan, spec, scenario.leader.heading_deg), scenario, seed=seed)
    camera = CameraModel(rate_hz=scenario.run.camera_rate_hz)
    visual = visual_from_mapping(scenario.visual, f"{scenario_file} [visual]")
    with ExitStack() as stack:
        followers = []
        for i, (name, cfg) in enumerate(configs.items()):
            renderer = stack.enter_context(
                Renderer(camera=camera, visual=visual, mount=cfg.camera.mount, seed=seed * 16 + i)
            )
            followers.append((name, cfg, load_detect(cfg, runtime), renderer))
        result = asyncio.run(FormationRun(world, followers, options).run())
    return result, plan, configs


__all__ = ["FormationSpec", "follower_configs", "formation_spec", "run_formation", "sitl_config_for"]
